"""Write and execute ``delta_lambda_tradeoffs.ipynb`` (outputs are kept in the file).

Run ``python notebooks/build_notebook.py`` after changing the cells below.
"""

from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).parent

CELLS = [
    (
        "md",
        """# Choosing delta and lambda for Huber SINDy

The Huber-Lasso estimator has two knobs: the Huber threshold `delta` (where a residual
stops counting quadratically) and the L1 weight `lam`. They are coupled:
`lambda_max(delta) = max_j |Theta_j^T psi_delta(xdot)| <= delta * max_j ||Theta_j||_1`, so a
fixed `lam` means something very different at different `delta`. This notebook shows,
on the Lorenz system and the planar drone with the paper's contamination (20 % of the
samples with state noise sigma 0.5, the rest 1e-3), what each choice does, and why
`HuberSINDy()` screens rows, chooses `delta` from a robust residual scale, and chooses
`lam` by a robust BIC after a threshold-and-refit stage.""",
    ),
    (
        "code",
        """import warnings

import matplotlib.pyplot as plt
import numpy as np

import robust_sindy as rs
from robust_sindy.metrics import iae
from robust_sindy.noise import contaminate
from robust_sindy.selection import auto_delta, lambda_max, screen_rows, select, threshold_refit
from robust_sindy.systems import Drone, Lorenz

warnings.simplefilter("ignore", rs.ConvergenceWarning)  # certification is reported below


def heat_maps(iae_grid, nnz_grid, fracs, row_labels, ylabel, title):
    # log10 IAE and the number of nonzero coefficients over (row, lam / lambda_max)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, val, what in [(axes[0], np.log10(iae_grid), "log10 IAE"),
                          (axes[1], nnz_grid, "nonzero coefficients (true: 7)")]:
        im = ax.imshow(val, aspect="auto", origin="lower", cmap="viridis")
        ax.set_xticks(range(fracs.size), [f"{f:.0e}" for f in fracs], rotation=60)
        ax.set_yticks(range(len(row_labels)), row_labels)
        ax.set_xlabel("lam / lambda_max(delta)")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{title}: {what}")
        fig.colorbar(im, ax=ax)
    fig.tight_layout()


lorenz = Lorenz()
data = lorenz.generate()
noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
theta = lorenz.fitted_library().transform(noisy.x)
y = noisy.x_dot
true = lorenz.true_coef()
print(theta.shape, "samples x library terms;", noisy.outliers.sum(), "contaminated samples")""",
    ),
    (
        "md",
        """## 1. IAE over (delta, lam / lambda_max) for the plain Huber-Lasso

Each cell solves the paper's problem (all samples, no selection stage) to a certified
optimum and records the IAE against the true coefficients. `lam` is given as a
fraction of `lambda_max(delta)`, which is what makes rows comparable.""",
    ),
    (
        "code",
        """deltas = np.geomspace(1e-3, 10.0, 9)
fracs = np.geomspace(1.0, 1e-5, 11)[1:]
grid_iae = np.zeros((deltas.size, fracs.size))
grid_nnz = np.zeros_like(grid_iae)
certified = 0
for i, d in enumerate(deltas):
    lmax = lambda_max(theta, y, d)
    for j, f in enumerate(fracs):
        res = rs.fit(theta, y, delta=d, lam=f * lmax)
        certified += res.converged
        grid_iae[i, j] = iae(true, res.coef)
        grid_nnz[i, j] = np.count_nonzero(res.coef)
best = np.unravel_index(grid_iae.argmin(), grid_iae.shape)
print(f"certified {certified} of {grid_iae.size} fits")
print(f"best IAE {grid_iae[best]:.4f} at delta {deltas[best[0]]:.0e}, "
      f"lam {fracs[best[1]]:.0e} lambda_max, with {grid_nnz[best]:.0f} nonzero terms (true 7)")
seven = grid_nnz == 7
print(f"cells with 7 nonzero terms: {seven.sum()}, their smallest IAE: "
      f"{grid_iae[seven].min() if seven.any() else float('nan'):.2f}")
heat_maps(grid_iae, grid_nnz, fracs, [f"{d:.0e}" for d in deltas], "delta",
          "Lorenz, plain Huber-Lasso")""",
    ),
    (
        "md",
        """No cell of the grid gives a sparse and accurate model. Where the IAE is
smallest, most of the 30 coefficients are nonzero (small spurious terms); where only a
handful are nonzero, `lam` is so large that the true coefficients are shrunk or replaced
and the IAE is above 10. The contaminated *states* enter the library rows, which a Huber
loss on the residual cannot down-weight (bad leverage), so every fit carries a bias that
no `(delta, lam)` removes.""",
    ),
    (
        "md",
        """## 2. Row screening: how many samples are flagged

`screen_rows` fits an unpenalised Huber pilot, measures each equation's robust residual
scale and flags a sample whose residual exceeds 3.5 robust standard deviations in any
well-fitted equation, refitting until the flags settle. The truth is 200 contaminated
samples of 1001 (20 %).""",
    ),
    (
        "code",
        """drone = Drone()
ddata = drone.generate()
dnoisy = contaminate(ddata.x, ddata.x_dot, rng=np.random.default_rng(0))
dtheta = drone.fitted_library().transform(np.hstack([dnoisy.x, ddata.u]))
dy = dnoisy.x_dot[:, 3:]
dtrue = drone.true_coef()
rows = []
for name, th, yy, out in [("Lorenz", theta, y, noisy.outliers),
                          ("drone", dtheta, dy, dnoisy.outliers)]:
    s = screen_rows(th, yy)
    rows.append((name, s.outliers.mean(), (s.outliers & out).sum() / out.sum(),
                 (s.outliers & ~out).sum() / (~out).sum()))
    print(f"{name}: flagged {100 * s.outliers.mean():.1f} % of samples (true 20 %), "
          f"{100 * rows[-1][2]:.1f} % of the contaminated ones found, "
          f"{100 * rows[-1][3]:.1f} % of the clean ones flagged; {s}")
fig, ax = plt.subplots(figsize=(6, 3))
pos = np.arange(len(rows))
ax.bar(pos - 0.2, [100 * r[1] for r in rows], 0.4, label="flagged samples")
ax.bar(pos + 0.2, [100 * r[3] for r in rows], 0.4, label="clean samples flagged")
ax.axhline(20, color="k", ls="--", label="true contamination")
ax.set_xticks(pos, [r[0] for r in rows])
ax.set_ylabel("% of samples")
ax.legend(fontsize=8)
fig.tight_layout()""",
    ),
    (
        "md",
        """The screen finds essentially all contaminated samples; the extra few percent
are clean samples in the Gaussian tails of the residuals (3.5 standard deviations in any
of three equations). Losing them costs little information.""",
    ),
    (
        "md",
        """## 3. After screening: the same heat map, now with the selection stage

On the kept samples, each `(delta, lam)` fit is followed by the selection stage (drop
terms carrying less than 0.5 % of their equation's signal, refit by Huber with
`lam = 0`). The support size is plotted beside it.""",
    ),
    (
        "code",
        """keep = ~screen_rows(theta, y).outliers
th_k, y_k = theta[keep], y[keep]
d_auto = auto_delta(th_k, y_k)
print("automatic delta per equation:", np.array2string(d_auto, precision=4))
scales = np.geomspace(0.1, 1e3, 8)  # delta as multiples of the automatic one
stage_iae = np.zeros((scales.size, fracs.size))
stage_nnz = np.zeros_like(stage_iae)
for i, c in enumerate(scales):
    d = c * d_auto
    lmax = lambda_max(th_k, y_k, d)
    for j, f in enumerate(fracs):
        coef = threshold_refit(th_k, y_k, rs.fit(th_k, y_k, delta=d, lam=f * lmax).coef, d)
        stage_iae[i, j] = iae(true, coef)
        stage_nnz[i, j] = np.count_nonzero(coef)
heat_maps(stage_iae, stage_nnz, fracs, [f"{c:g}" for c in scales], "delta / automatic delta",
          "screened + selection stage")
exact = (stage_nnz == 7) & (stage_iae < 1e-2)
print(f"cells with the 7 true terms and IAE < 0.01: {exact.sum()} of {exact.size}")""",
    ),
    (
        "md",
        """With the contaminated samples gone and the shrinkage removed by the refit,
every `lam` below about 3e-4 `lambda_max` gives the seven true terms at an IAE around
1e-3, whatever `delta` between a tenth and a thousand times the automatic value. A
larger `lam` removes true terms before the refit can restore them (the left columns),
and near the edge of the band a very large `delta` (the loss is then least squares)
lets spurious terms through. Inside the band the choice barely matters; the criterion's
job is to land inside it.""",
    ),
    (
        "md",
        """## 4. The loss-versus-sparsity curve and the automatically selected point

`select` walks a 50-point warm-started path, applies the selection stage at every point,
and scores each refit by a robust BIC (`2 sum H_delta(r) / sigma^2 + k log m`); an
equation's path stops once the stage keeps proposing the support of its limit (the
stage of the unpenalised fit), so only the points walked have scores. Beside it, the
same curve for STLS as its threshold varies (all samples, least squares).""",
    ),
    (
        "code",
        """sel = select(th_k, y_k, d_auto)
print(sel)
print("path: certified", int(sel.path.converged.sum()), "of", sel.path.converged.size,
      f"points in {sel.path.solve_time:.2f} s")
fig, axes = plt.subplots(1, 2, figsize=(11, 4))
def envelope(nnz, val):
    # smallest value per number of terms (the Pareto curve)
    ks = np.unique(nnz)
    return ks, np.array([min(v for n, v in zip(nnz, val, strict=True) if n == k) for k in ks])

for k, name in enumerate(["(x)'", "(y)'", "(z)'"]):
    used = np.flatnonzero(np.isfinite(sel.scores[:, k]))  # the points walked
    nnz = np.count_nonzero(sel.candidates[used, :, k], axis=1)
    loss = [rs.objective(th_k, y_k[:, k], sel.candidates[i, :, k], d_auto[k], 0.0)[0]
            for i in used]
    axes[0].plot(*envelope(nnz, loss), "o-", ms=4, label=name)
    i = list(used).index(sel.index[k])
    axes[0].plot(nnz[i], loss[i], "r*", ms=14)
axes[0].set_yscale("log")
axes[0].set_xlabel("nonzero terms")
axes[0].set_ylabel("Huber loss of the refit (lowest per size)")
axes[0].set_title("Huber path + selection stage (red star: BIC choice)")
axes[0].legend()
ths = np.geomspace(1e-3, 20, 30)
best_stls = []
for k, name in enumerate(["(x)'", "(y)'", "(z)'"]):
    nnz, err = [], []
    for t in ths:
        c = rs.fit(theta, y[:, k], method="stls", threshold=t).coef
        nnz.append(np.count_nonzero(c))
        err.append(np.abs(c - true[:, k]).sum())
    axes[1].plot(*envelope(nnz, err), "o-", ms=4, label=name)
    best_stls.append(min(err))
axes[1].set_yscale("log")
axes[1].set_xlabel("nonzero terms")
axes[1].set_ylabel("IAE of the equation")
axes[1].set_title("STLS threshold sweep (all samples), best IAE per size")
axes[1].legend()
fig.tight_layout()
sel_eq = np.abs(sel.coef - true).sum(axis=0)
print("IAE per equation, Huber selected automatically:", np.array2string(sel_eq, precision=5))
print("IAE per equation, STLS at its best threshold (chosen knowing the truth):",
      np.array2string(np.array(best_stls), precision=3))
model = rs.HuberSINDy().fit(noisy.x, data.t, x_dot=noisy.x_dot, feature_names=["x", "y", "z"])
model.print()""",
    ),
    (
        "md",
        """Every model the path proposes after the selection stage, reduced to the lowest
loss per number of terms: the true supports (two, three and two terms) have a Huber
loss three to four orders of magnitude below every other candidate, smaller or larger,
and the BIC picks them. The larger candidates come from the middle of the path, where
`lam` has let wrong terms in before the true ones; at small `lam` the selection stage
thins the path's dense solutions back to the true terms. STLS, even at the threshold
that is best for each equation (which needs the true coefficients to find), stays two
to three orders of magnitude worse: its least-squares fits on all samples are biased by
the contaminated rows.""",
    ),
    (
        "md",
        """## 5. The drone

The same automatic procedure on the drone, whose contaminated attitude makes
`(f1+f2) sin(theta)` a bad-leverage column.""",
    ),
    (
        "code",
        """dmodel = rs.HuberSINDy(library=drone.library()).fit(
    dnoisy.x, ddata.t, x_dot=dnoisy.x_dot, u=ddata.u, feature_names=drone.input_names)
dmodel.print(precision=4)
stls = rs.fit(dtheta, dy, method="stls", threshold=0.05).coef
print("IAE, Huber auto:", iae(dtrue, dmodel.coef_[3:].T), " STLS:", iae(dtrue, stls))
print("flagged samples:", dmodel.screened_.sum(), " chosen lam:", dmodel.lam_[3:])""",
    ),
    (
        "md",
        """Without screening, every method fails on the drone (the 20-seed reproduction
in `validation/results/reproduce.md` has STLS at IAE 12); with it, the three equations
come out with the right terms and coefficients to three or four digits.""",
    ),
]


def build() -> nbformat.NotebookNode:
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}  # fmt: skip
    for kind, src in CELLS:
        make = nbformat.v4.new_markdown_cell if kind == "md" else nbformat.v4.new_code_cell
        nb.cells.append(make(src))
    return nb


if __name__ == "__main__":
    nb = build()
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={
        "metadata": {"path": str(HERE)}}).execute()  # fmt: skip
    nbformat.write(nb, HERE / "delta_lambda_tradeoffs.ipynb")
    print("wrote", HERE / "delta_lambda_tradeoffs.ipynb")
