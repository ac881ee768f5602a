"""Small real data sets shipped with the package.

:func:`load_lynx_hare` -- the Hudson's Bay Company pelt records of snowshoe hare and
Canada lynx, 1900-1920: 21 yearly samples of the classic predator-prey cycle.

:func:`load_cylinder_wake` -- the POD amplitudes of a simulated flow past a circular
cylinder: the two leading oscillating modes and the shift mode, from the unstable
steady flow to the vortex street's limit cycle (3000 samples).
"""

from __future__ import annotations

import csv
from importlib import resources
from typing import NamedTuple

import numpy as np

__all__ = ["CylinderWake", "LynxHare", "load_cylinder_wake", "load_lynx_hare"]


class LynxHare(NamedTuple):
    t: np.ndarray  # (21,) years
    x: np.ndarray  # (21, 2) pelts in thousands: hare, lynx
    names: list[str]


class CylinderWake(NamedTuple):
    t: np.ndarray  # (3000,) convective time units
    x: np.ndarray  # (3000, 3) amplitudes: a1, a2 (oscillating modes), a_shift
    names: list[str]


def _read_csv(name: str):
    text = resources.files(__name__).joinpath(name).read_text()
    rows = list(csv.reader(text.splitlines()))
    return rows[0], np.array(rows[1:], dtype=float)


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
    header, values = _read_csv("lynx_hare.csv")
    names = header[1:]
    if as_frame:
        import pandas as pd

        frame = pd.DataFrame(values[:, 1:], columns=names, index=values[:, 0].astype(int))
        frame.index.name = header[0]
        return frame
    return LynxHare(values[:, 0], values[:, 1:], names)


def load_cylinder_wake(as_frame: bool = False):
    """POD amplitudes of the flow past a circular cylinder, from its unstable steady
    state to the limit cycle of vortex shedding.

    A two-dimensional direct numerical simulation (Nek5000) projected on its POD modes,
    as distributed with the examples of PySINDy (``examples/data/vonKarman_pod/
    vonKarman_a.dat``, MIT licence; de Silva et al. 2020, Kaptanoglu et al. 2022): the
    setting of sparse Galerkin regression of this flow (Loiseau & Brunton 2018, J.
    Fluid Mech. 838:42; Kaptanoglu et al. 2021, Phys. Rev. Fluids 6:094401).  Kept: the
    two leading oscillating modes ``a1``, ``a2`` (columns 1 and 2 of the file) and the
    shift mode ``a_shift`` (its last column), 3000 samples 0.1 time units apart, as
    printed there (six decimals).  The file is
    ``robust_sindy/datasets/cylinder_wake.csv``.

    The record starts next to the unstable steady flow (amplitudes about 1e-5), grows
    for about 100 time units and settles on the limit cycle: ``a1, a2`` oscillate with
    radius about 2.30 while ``a_shift`` levels at about 2.245.  The classical
    mean-field model of Noack et al. (2003) describes it with a quadratic nonlinearity
    that conserves energy; see ``validation/cylinder_wake.py``.

    Parameters
    ----------
    as_frame : bool
        Return a pandas DataFrame indexed by time (columns ``a1``, ``a2``,
        ``a_shift``) instead of ``CylinderWake(t, x, names)``.

    Examples
    --------
    >>> from robust_sindy.datasets import load_cylinder_wake
    >>> data = load_cylinder_wake()
    >>> data.x.shape, data.names, float(data.t[1] - data.t[0])
    ((3000, 3), ['a1', 'a2', 'a_shift'], 0.1)
    """
    header, values = _read_csv("cylinder_wake.csv")
    names = header[1:]
    if as_frame:
        import pandas as pd

        frame = pd.DataFrame(values[:, 1:], columns=names, index=values[:, 0])
        frame.index.name = header[0]
        return frame
    return CylinderWake(values[:, 0], values[:, 1:], names)
