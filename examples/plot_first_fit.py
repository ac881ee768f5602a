"""
A first fit: the Huber loss against least squares
=================================================

``rs.fit`` solves the Huber-loss Lasso for a given library matrix and targets.  A fifth
of the targets here carry gross errors: least squares spreads them over every term, the
Huber loss bounds their influence, and the certificate says whether the answer is the
optimum.
"""

import matplotlib.pyplot as plt
import numpy as np

import robust_sindy as rs

rng = np.random.default_rng(0)
theta = rng.normal(size=(500, 6))  # library: 500 samples x 6 candidate functions
xi_true = np.array([0.0, 2.0, 0.0, 0.0, -1.5, 0.0])
xdot = theta @ xi_true + 0.05 * rng.normal(size=500)
bad = rng.choice(500, 100, replace=False)
xdot[bad] += rng.normal(scale=20.0, size=100)  # 20 % gross outliers

res = rs.fit(theta, xdot, method="admm", delta=0.1, lam=5.0)
ols = rs.fit(theta, xdot, method="ols")
print("Huber-Lasso:", np.round(res.coef, 3), "certified:", res.converged)
print(f"relative KKT violation {res.kkt.max():.1e}, duality gap {res.gap.max():.1e}")
print("least squares:", np.round(ols.coef, 3))

# %%
# The same problem posed in CVXPY and solved by Clarabel (the reference) gives the same
# optimum.
ref = rs.fit(theta, xdot, method="cvxpy", delta=0.1, lam=5.0)
print(f"objective: fast path {res.objective[0]:.6f}, Clarabel {ref.objective[0]:.6f}")

fig, ax = plt.subplots(figsize=(6, 3))
width = 0.27
terms = np.arange(6)
ax.bar(terms - width, xi_true, width, label="true")
ax.bar(terms, res.coef, width, label="Huber-Lasso")
ax.bar(terms + width, ols.coef, width, label="least squares")
ax.set_xticks(terms, [f"theta_{j}" for j in terms])
ax.set_ylabel("coefficient")
ax.legend()
fig.tight_layout()
