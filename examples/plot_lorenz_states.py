"""
Lorenz from noisy states alone
==============================

No derivatives are measured: ``HuberSINDy`` screens the states in time, differentiates
them by local polynomials whose windows it chooses from the data, and identifies the
equations.  The states carry Gaussian noise of 1 % of their spread and a few spikes in
one channel at a time.
"""

import matplotlib.pyplot as plt
import numpy as np

import robust_sindy as rs

lorenz = rs.systems.Lorenz()
data = lorenz.generate(t_end=20.0, dt=0.01)
rng = np.random.default_rng(1)
x = data.x + 0.01 * data.x.std(axis=0) * rng.normal(size=data.x.shape)
spikes = rng.choice(x.size, 30, replace=False)
x.flat[spikes] += rng.choice([-1.0, 1.0], 30) * 5 * data.x.std()

model = rs.HuberSINDy().fit(x, data.t, feature_names=["x", "y", "z"])
model.print()
exact = np.array_equal(model.support_, lorenz.true_coef().T != 0)
print("support exact:", exact)
print("derivative half windows per state:", model.derivative_windows_)

# %%
# The identified equations, simulated from the first measured state, against the data.
sim = model.simulate(data.x[0], data.t[:300])
fig, ax = plt.subplots(figsize=(7, 3))
ax.plot(data.t[:300], x[:300, 0], ".", ms=2, label="measured x")
ax.plot(data.t[:300], sim[:, 0], lw=1.2, label="identified model")
ax.set_xlabel("t")
ax.legend(fontsize=8)
fig.tight_layout()
