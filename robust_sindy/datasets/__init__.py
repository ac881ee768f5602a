"""Small real data sets shipped with the package.

:func:`load_lynx_hare` -- the Hudson's Bay Company pelt records of snowshoe hare and
Canada lynx, 1900-1920: 21 yearly samples of the classic predator-prey cycle.
"""

from __future__ import annotations

import csv
from importlib import resources
from typing import NamedTuple

import numpy as np

__all__ = ["LynxHare", "load_lynx_hare"]


class LynxHare(NamedTuple):
    t: np.ndarray  # (21,) years
    x: np.ndarray  # (21, 2) pelts in thousands: hare, lynx
    names: list[str]


def load_lynx_hare(as_frame: bool = False):
    """Hare and lynx pelts traded by the Hudson's Bay Company, 1900-1920 (thousands).

    The yearly counts as compiled from the Company's records (MacLulich 1937; Elton &
    Nicholson 1942) and tabulated by Odum, *Fundamentals of Ecology* (1953); public
    domain, the standard predator-prey data set of textbooks and of the Stan
    Lotka-Volterra case study (Carpenter 2018).  The file is
    ``robust_sindy/datasets/lynx_hare.csv``.

    21 samples, a year apart, about two cycles: enough to fit a model with few terms
    (e.g. Lotka-Volterra's four), not to choose among many candidates; pelts are a proxy
    for abundance (trapping effort varies).

    Parameters
    ----------
    as_frame : bool
        Return a pandas DataFrame indexed by year (columns ``hare``, ``lynx``) instead of
        ``LynxHare(t, x, names)``.

    Examples
    --------
    >>> from robust_sindy.datasets import load_lynx_hare
    >>> data = load_lynx_hare()
    >>> data.x.shape, data.names, float(data.t[0])
    ((21, 2), ['hare', 'lynx'], 1900.0)
    """
    text = resources.files(__name__).joinpath("lynx_hare.csv").read_text()
    rows = list(csv.reader(text.splitlines()))
    header, values = rows[0], np.array(rows[1:], dtype=float)
    names = header[1:]
    if as_frame:
        import pandas as pd

        frame = pd.DataFrame(values[:, 1:], columns=names, index=values[:, 0].astype(int))
        frame.index.name = header[0]
        return frame
    return LynxHare(values[:, 0], values[:, 1:], names)
