"""Robust ensembles: how sure is the identified model?

:class:`EnsembleSINDy` fits a :class:`~robust_sindy.HuberSINDy` to many resamplings of
the data and reports, per equation and term, how often the term was selected (its
inclusion probability), the quantiles of its coefficient, and the spread of the
simulated trajectories.  Samples of a time series are correlated, so the default
resampling draws contiguous blocks of time (a moving-block bootstrap), each block a
trajectory of its own; ``sampling="rows"`` draws single samples instead (as PySINDy's
ensembles do), with derivatives computed once on the full trajectories.  With
``library_ensemble=True`` each model also loses ``n_drop`` random candidate terms.

Models are fitted through joblib (``n_jobs``); inside ``joblib.parallel_config(backend=
"dask")`` with a ``dask.distributed.Client`` they run on a Dask cluster.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import NotFittedError

from .core.validation import check_int
from .diagnostics import IdentificationWarning
from .estimator import HuberSINDy
from .export import ExportedRHS
from .library import BaseLibrary, PolynomialLibrary
from .simulate import integrate, simulation_inputs
from .timeseries.derivatives import differentiate
from .timeseries.trajectories import Trajectories

__all__ = ["UNCERTAIN_BAND", "DroppedTerms", "EnsembleSINDy"]

#: Inclusion probabilities within this distance of ``inclusion_threshold`` are reported
#: as uncertain (a warning names the terms).
UNCERTAIN_BAND = 0.25
#: Shortest default block: each block is screened and differentiated as a trajectory of
#: its own, and the temporal screen's noise scales need about this many samples (with 32
#: the drone's 20 % contaminated rows inflated them and true terms were lost).
MIN_BLOCK = 100
#: Fraction of the samples ``sampling="rows"`` draws (with replacement) per model.
ROW_FRACTION = 1.0


class DroppedTerms(BaseLibrary):
    """A library without some of its terms (used by library ensembles).

    Parameters
    ----------
    library : BaseLibrary
    drop : sequence of int
        Positions of the terms of ``library`` to leave out.
    """

    def __init__(self, library: BaseLibrary, drop=()):
        self.library = library
        self.drop = drop

    def fit(self, x, y=None, input_names=None) -> DroppedTerms:
        x = self._fit_inputs(x, input_names)
        self.library_ = clone(self.library).fit(x, input_names=self.input_names_)
        p = self.library_.n_output_features_
        drop = {int(j) for j in self.drop}
        if any(not 0 <= j < p for j in drop):
            raise ValueError(f"drop must hold term positions in [0, {p}); got {sorted(drop)}")
        self.keep_ = np.array([j for j in range(p) if j not in drop], dtype=int)
        if self.keep_.size == 0:
            raise ValueError("drop leaves no term")
        self.n_output_features_ = int(self.keep_.size)
        return self

    def transform(self, x) -> np.ndarray:
        x = self._check_transform_input(x)
        return self.library_.transform(x)[:, self.keep_]

    def get_feature_names(self, input_names=None) -> list[str]:
        self._check_fitted()
        names = self.library_.get_feature_names(input_names)
        return [names[j] for j in self.keep_]

    def term_codes(self, args):
        self._check_fitted()
        codes, extra = self.library_.term_codes(args)
        return [codes[j] for j in self.keep_], extra


def _blocks(rng, length: int, block: int) -> list[slice]:
    """Moving-block bootstrap of one trajectory: ``ceil(length / block)`` blocks."""
    block = min(block, length)
    starts = rng.integers(0, length - block + 1, size=math.ceil(length / block))
    return [slice(int(s), int(s) + block) for s in starts]


def _fit_member(estimator, data, drop, p_full, template):
    """One ensemble member: its coefficients on the full library and what it warned."""
    xs, ts, ds, us, names = data
    estimator = clone(estimator)
    if drop is not None:
        estimator.set_params(library=DroppedTerms(template, drop))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            estimator.fit(xs, ts, x_dot=ds, u=us, feature_names=names)
        except ValueError as exc:  # a resample the estimator refuses (e.g. too little)
            return None, [f"{type(exc).__name__}: {exc}"], False
    coef = np.zeros((estimator.coef_.shape[0], p_full))
    keep = estimator.library_.keep_ if drop is not None else np.arange(p_full)
    coef[:, keep] = estimator.coef_
    messages = [str(w.message) for w in caught]
    certified = bool(np.all(estimator.diagnostics_.certified))
    return coef, messages, certified


class EnsembleSINDy(BaseEstimator):
    """Bagged (or bragged) :class:`HuberSINDy` fits with inclusion probabilities.

    Parameters
    ----------
    estimator : HuberSINDy, optional
        The model fitted to every resampling (default ``HuberSINDy()``); cloned.
    n_models : int
        Number of resamplings.
    sampling : {"blocks", "rows"}
        ``"blocks"``: contiguous blocks of ``block_length`` samples drawn with
        replacement until each trajectory's length is reached, each block a trajectory
        of its own (the estimator screens and differentiates it as such).
        ``"rows"``: samples drawn with replacement, kept once each and in time order
        (about 63 % of them), derivatives computed once on the full trajectories by the
        estimator's ``differentiation`` when ``x_dot`` is not given.
    block_length : int, optional
        Default: ``max(MIN_BLOCK, round(sqrt(m)))`` (``MIN_BLOCK = 100``) for a
        trajectory of ``m`` samples.
    library_ensemble : bool
        Also drop ``n_drop`` random candidate terms in each model.
    n_drop : int
        Terms dropped per model with ``library_ensemble``.
    aggregate : {"median", "mean"}
        How the coefficients of the models that selected a term are combined.
    inclusion_threshold : float
        A term is in the aggregated model when the fraction of models selecting it (among
        those that could) is at least this.
    quantiles : sequence of float
        Coefficient quantiles reported in ``coef_quantiles_``.
    n_jobs : int, optional
        joblib workers (``None``: joblib's default, one unless a ``parallel_config``
        says otherwise).
    random_state : int, optional

    Attributes
    ----------
    coef_ : ndarray (n_targets, n_features)
        Aggregated coefficients of the terms that pass ``inclusion_threshold``.
    inclusion_probability_ : ndarray (n_targets, n_features)
    coef_quantiles_ : ndarray (len(quantiles), n_targets, n_features)
        Quantiles of the coefficient stack (zeros included).
    coef_stack_ : ndarray (n_fitted, n_targets, n_features)
        Every fitted model's coefficients (zeros for terms it did not select or have).
    available_ : ndarray of bool (n_fitted, n_features)
        The terms each model could use (all, without ``library_ensemble``).
    uncertain_ : ndarray of bool (n_targets, n_features)
        Terms whose inclusion probability is within ``UNCERTAIN_BAND`` of the threshold
        (named in an ``IdentificationWarning``; so is the most frequent warning of the
        models when more than half of them warned).
    warned_fraction_ : float
        Fraction of the models whose fit raised a warning; ``member_warnings_`` counts
        the messages.
    certified_fraction_ : float
        Fraction of the models whose every equation was certified.
    library_, feature_names_, n_control_features_
        As for :class:`HuberSINDy`.
    """

    def __init__(
        self,
        estimator: HuberSINDy | None = None,
        n_models: int = 20,
        sampling: str = "blocks",
        block_length: int | None = None,
        library_ensemble: bool = False,
        n_drop: int = 1,
        aggregate: str = "median",
        inclusion_threshold: float = 0.5,
        quantiles=(0.05, 0.5, 0.95),
        n_jobs: int | None = None,
        random_state: int | None = None,
    ):
        self.estimator = estimator
        self.n_models = n_models
        self.sampling = sampling
        self.block_length = block_length
        self.library_ensemble = library_ensemble
        self.n_drop = n_drop
        self.aggregate = aggregate
        self.inclusion_threshold = inclusion_threshold
        self.quantiles = quantiles
        self.n_jobs = n_jobs
        self.random_state = random_state

    # ------------------------------------------------------------------ fitting
    def _check_params(self):
        if self.estimator is not None and not isinstance(self.estimator, HuberSINDy):
            raise ValueError(f"estimator must be a HuberSINDy; got {type(self.estimator).__name__}")
        check_int(self.n_models, "n_models", 2)
        if self.sampling not in ("blocks", "rows"):
            raise ValueError(f"sampling must be 'blocks' or 'rows'; got {self.sampling!r}")
        if self.block_length is not None:
            check_int(self.block_length, "block_length", 10)
        check_int(self.n_drop, "n_drop", 1)
        if self.aggregate not in ("median", "mean"):
            raise ValueError(f"aggregate must be 'median' or 'mean'; got {self.aggregate!r}")
        thr = self.inclusion_threshold
        if isinstance(thr, bool) or not isinstance(thr, (int, float)) or not 0 < thr <= 1:
            raise ValueError(f"inclusion_threshold must be in (0, 1]; got {thr!r}")
        q = np.asarray(self.quantiles, dtype=float)
        if q.ndim != 1 or q.size == 0 or np.any((q < 0) | (q > 1)):
            raise ValueError(f"quantiles must be numbers in [0, 1]; got {self.quantiles!r}")

    def fit(self, x, t=None, x_dot=None, u=None, feature_names=None) -> EnsembleSINDy:
        """Fit ``n_models`` resamplings of the data (arguments as :meth:`HuberSINDy.fit`)."""
        from joblib import Parallel, delayed

        self._check_params()
        base = clone(self.estimator) if self.estimator is not None else HuberSINDy()
        base.check_params()
        data = Trajectories.from_user(
            x, t, x_dot, u, feature_names, need_t=self.sampling == "blocks"
        )
        xs, ts, ds, us = data.x, data.t, data.x_dot, data.u
        # The full library: the coordinates of every model's coefficients.
        n, q = data.n_states, data.n_controls
        names = data.feature_names()
        template = base.library if base.library is not None else PolynomialLibrary()
        self.library_ = clone(template).fit(np.zeros((1, n + q)), input_names=names)
        if self.sampling == "rows" and ds is None:
            # Once for all models, as a single fit computes them (windows guarded by
            # the library).
            ds = [
                differentiate(
                    a, ti, base.differentiation, base.derivative_window,
                    library=self.library_.transform(a if b is None else np.hstack([a, b])),
                )
                for (a, b), ti in zip(data.pairs(), ts, strict=True)
            ]  # fmt: skip
        self.feature_names_ = names
        self.n_control_features_ = q
        p = self.library_.n_output_features_
        if self.library_ensemble and self.n_drop >= p:
            raise ValueError(f"n_drop ({self.n_drop}) must be below the number of terms ({p})")
        rng = np.random.default_rng(self.random_state)
        tasks, drops = [], []
        for _ in range(self.n_models):
            data = self._resample(rng, xs, ts, ds, us, names)
            drop = (
                np.sort(rng.choice(p, self.n_drop, replace=False))
                if self.library_ensemble
                else None
            )
            drops.append(drop)
            tasks.append(delayed(_fit_member)(base, data, drop, p, template))
        results = Parallel(n_jobs=self.n_jobs)(tasks)
        ok = [i for i, r in enumerate(results) if r[0] is not None]
        if len(ok) < 2:
            reasons = "; ".join(sorted({r[1][0] for r in results if r[0] is None}))
            raise ValueError(
                f"only {len(ok)} of {self.n_models} resamplings could be fitted ({reasons}); "
                "use longer blocks or more data"
            )
        self.coef_stack_ = np.stack([results[i][0] for i in ok])
        self.available_ = np.ones((len(ok), p), dtype=bool)
        for row, i in enumerate(ok):
            if drops[i] is not None:
                self.available_[row, drops[i]] = False
        self.n_failed_ = self.n_models - len(ok)
        messages = [m for i in ok for m in results[i][1]]
        self.member_warnings_ = {m: messages.count(m) for m in dict.fromkeys(messages)}
        self.warned_fraction_ = float(np.mean([bool(results[i][1]) for i in ok]))
        self.certified_fraction_ = float(np.mean([results[i][2] for i in ok]))
        self._aggregate()
        self._warn()
        return self

    def _resample(self, rng, xs, ts, ds, us, names):
        pieces = []  # (trajectory, index array or slice)
        for k, a in enumerate(xs):
            m = a.shape[0]
            if self.sampling == "blocks":
                block = self.block_length or max(MIN_BLOCK, round(math.sqrt(m)))
                pieces += [(k, sl) for sl in _blocks(rng, m, block)]
            else:
                rows = np.unique(rng.integers(0, m, size=max(1, round(ROW_FRACTION * m))))
                pieces.append((k, rows))

        def take(arrays, k, sel):
            return None if arrays is None else arrays[k][sel]

        out_x = [xs[k][sel] for k, sel in pieces]
        out_t = None if ts is None else [ts[k][sel] for k, sel in pieces]
        out_d = None if ds is None else [take(ds, k, sel) for k, sel in pieces]
        out_u = None if us is None else [take(us, k, sel) for k, sel in pieces]
        return out_x, out_t, out_d, out_u, names

    def _aggregate(self):
        stack, avail = self.coef_stack_, self.available_
        selected = stack != 0
        could = np.maximum(avail.sum(axis=0), 1)[None, :]
        self.inclusion_probability_ = selected.sum(axis=0) / could
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: never selected
            picked = np.where(selected, stack, np.nan)
            combine = np.nanmedian if self.aggregate == "median" else np.nanmean
            value = np.nan_to_num(combine(picked, axis=0), nan=0.0)
        keep = self.inclusion_probability_ >= self.inclusion_threshold
        self.coef_ = np.where(keep, value, 0.0)
        self.support_ = self.coef_ != 0
        q = np.asarray(self.quantiles, dtype=float)
        self.coef_quantiles_ = np.quantile(stack, q, axis=0)
        self.uncertain_ = (
            np.abs(self.inclusion_probability_ - self.inclusion_threshold) < UNCERTAIN_BAND
        )

    def _warn(self):
        if self.uncertain_.any():
            names = self.library_.get_feature_names()
            parts = []
            for k in np.flatnonzero(self.uncertain_.any(axis=1)):
                terms = ", ".join(
                    f"{names[j]} ({self.inclusion_probability_[k, j]:.2f})"
                    for j in np.flatnonzero(self.uncertain_[k])
                )
                parts.append(f"({self.feature_names_[k]})': {terms}")
            warnings.warn(
                "the resampled fits disagree on these terms (inclusion probability near "
                f"the threshold {self.inclusion_threshold}): "
                + "; ".join(parts)
                + ". The data do not settle whether they belong in the model.",
                IdentificationWarning,
                stacklevel=3,
            )
        if self.warned_fraction_ > 0.5:
            common = max(self.member_warnings_, key=self.member_warnings_.get)
            warnings.warn(
                f"{100 * self.warned_fraction_:.0f} % of the resampled fits warned (see "
                f"member_warnings_); the most frequent: {common}",
                IdentificationWarning,
                stacklevel=3,
            )
        if self.n_failed_:
            warnings.warn(
                f"{self.n_failed_} of {self.n_models} resamplings could not be fitted",
                IdentificationWarning,
                stacklevel=3,
            )

    # ------------------------------------------------------------------ using the model
    def _check_fitted(self, what):
        if not hasattr(self, "coef_"):
            raise NotFittedError(f"this EnsembleSINDy is not fitted yet: call fit before {what}")

    def _consensus(self) -> HuberSINDy:
        model = HuberSINDy(library=self.library_)
        model.library_ = self.library_
        model.coef_ = self.coef_
        model.support_ = self.support_
        model.feature_names_ = self.feature_names_
        model.n_control_features_ = self.n_control_features_
        return model

    def get_feature_names(self) -> list[str]:
        self._check_fitted("get_feature_names")
        return self.library_.get_feature_names()

    def equations(self, precision: int = 3) -> list[str]:
        """The aggregated model's right-hand sides as text."""
        self._check_fitted("equations")
        return self._consensus().equations(precision)

    def print(self, precision: int = 3) -> None:
        self._check_fitted("print")
        self._consensus().print(precision)

    def predict(self, x, u=None):
        """Derivatives predicted by the aggregated model."""
        self._check_fitted("predict")
        return self._consensus().predict(x, u)

    def simulate(self, x0, t, u=None, quantiles=None, **integrator_kws) -> np.ndarray:
        """Quantiles of the trajectories of every fitted model, shape (len(q), len(t), n).

        Each model is integrated from ``x0`` (:func:`scipy.integrate.solve_ivp`, default
        LSODA at 1e-8); a model whose integration stops early contributes NaN from
        there, and the quantiles are taken over the models still running (a warning
        counts them).  ``quantiles`` default to ``self.quantiles``.
        """
        self._check_fitted("simulate")
        n = self.coef_.shape[0]
        t, x0, uf = simulation_inputs(x0, t, u, n, self.n_control_features_)
        q = np.asarray(self.quantiles if quantiles is None else quantiles, dtype=float)
        kws = {"method": "LSODA", "rtol": 1e-8, "atol": 1e-8, **integrator_kws}
        trajectories = np.full((len(self.coef_stack_), t.size, n), np.nan)
        stopped = 0
        for i, coef in enumerate(self.coef_stack_):
            f = ExportedRHS(self.library_, coef, self.feature_names_[:n], self.n_control_features_)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sol = integrate(f, x0, t, uf, kws)
            trajectories[i, : sol.y.shape[1]] = sol.y.T
            stopped += not sol.success
        if stopped:
            warnings.warn(
                f"{stopped} of {len(self.coef_stack_)} ensemble models stopped early (their "
                "trajectories diverge); the band is taken over the others",
                UserWarning,
                stacklevel=2,
            )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanquantile(trajectories, q, axis=0)

    # ------------------------------------------------------------------ figures
    def plot_inclusion(self, ax=None):
        """Inclusion probability per equation and term (terms ever selected); the axes."""
        import matplotlib.pyplot as plt

        self._check_fitted("plot_inclusion")
        pi = self.inclusion_probability_
        used = np.flatnonzero(pi.max(axis=0) > 0)
        used = used if used.size else np.arange(pi.shape[1])
        names = self.library_.get_feature_names()
        n = pi.shape[0]
        if ax is None:
            _, ax = plt.subplots(figsize=(1.5 + 0.7 * len(used), 1.2 + 0.5 * n))
        img = ax.imshow(pi[:, used], vmin=0, vmax=1, cmap="viridis", aspect="auto")
        for (i, j), v in np.ndenumerate(pi[:, used]):
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=8,
                    color="black" if v > 0.6 else "white")  # fmt: skip
        ax.set_xticks(range(len(used)), [names[j] for j in used], rotation=45, ha="right")
        ax.set_yticks(range(n), [f"({s})'" for s in self.feature_names_[:n]])
        ax.set_title(f"inclusion probability over {len(self.coef_stack_)} models")
        ax.figure.colorbar(img, ax=ax, fraction=0.04)
        return ax

    def plot_simulation(self, x0, t, u=None, data=None, axes=None):
        """The ensemble's median trajectory and its band (first to last quantile)."""
        import matplotlib.pyplot as plt

        band = self.simulate(x0, t, u)
        n = band.shape[2]
        if axes is None:
            _, axes = plt.subplots(n, 1, figsize=(7, 1.5 + 1.5 * n), sharex=True, squeeze=False)
            axes = axes[:, 0]
        mid = band.shape[0] // 2
        for i, ax in enumerate(axes):
            if data is not None:
                ax.plot(t, np.asarray(data)[:, i], ".", ms=2, color="0.5", label="data")
            label = f"models, quantiles {self.quantiles[0]:g}-{self.quantiles[-1]:g}"
            ax.fill_between(t, band[0, :, i], band[-1, :, i], alpha=0.3, color="C0", label=label)
            ax.plot(t, band[mid, :, i], color="C0", lw=1.5, label="median")
            ax.set_ylabel(self.feature_names_[i])
        axes[0].legend(loc="best", fontsize=8)
        axes[-1].set_xlabel("t")
        return axes
