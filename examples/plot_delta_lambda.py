"""
The delta/lambda trade-off, and what the automatic choice does
===============================================================

On the paper's contaminated Lorenz data, the plain Huber-Lasso (no screening, no
selection stage) is fitted over a grid of delta and lambda.  No cell of the grid is both
sparse and accurate: the contaminated library rows are bad-leverage points that no
delta down-weights.  ``HuberSINDy()`` screens them out and chooses delta and lambda on
standardised columns.
"""

import matplotlib.pyplot as plt
import numpy as np

import robust_sindy as rs
from robust_sindy.noise import contaminate
from robust_sindy.selection import lambda_max

lorenz = rs.systems.Lorenz()
data = lorenz.generate()
noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
theta = lorenz.fitted_library().transform(noisy.x)
y = noisy.x_dot
true = lorenz.true_coef()
deltas = np.geomspace(0.01, 10.0, 5)
fractions = np.geomspace(1e-4, 1e-1, 5)
iae = np.zeros((deltas.size, fractions.size))
for i, delta in enumerate(deltas):
    lmax = lambda_max(theta, y, delta)
    for j, frac in enumerate(fractions):
        coef = rs.fit(theta, y, delta=delta, lam=frac * lmax).coef
        iae[i, j] = rs.metrics.iae(true, coef)
print("IAE of the plain estimator (rows: delta, columns: lam / lambda_max):")
print(np.array2string(iae, precision=2))

auto = rs.HuberSINDy(library=lorenz.library()).fit(noisy.x, data.t, x_dot=noisy.x_dot)
print(
    f"HuberSINDy(): IAE {rs.metrics.iae(true, auto.coef_.T):.1e}, delta {np.round(auto.delta_, 3)}"
)

fig, ax = plt.subplots(figsize=(5, 3.5))
image = ax.imshow(np.log10(iae), origin="lower", aspect="auto", cmap="viridis")
ax.set_xticks(range(fractions.size), [f"{v:.0e}" for v in fractions])
ax.set_yticks(range(deltas.size), [f"{v:.2g}" for v in deltas])
ax.set_xlabel("lam / lambda_max")
ax.set_ylabel("delta")
fig.colorbar(image, label="log10 IAE")
fig.tight_layout()
