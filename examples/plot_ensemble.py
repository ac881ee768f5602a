"""
How sure is the model? Ensembles
================================

``EnsembleSINDy`` fits the estimator to resampled blocks of the time series and reports
how often each term was selected.
"""

import numpy as np

import robust_sindy as rs
from robust_sindy.noise import contaminate

data = rs.systems.Lorenz().generate(t_end=10.0)
noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))  # 20 % of rows
ens = rs.EnsembleSINDy(n_models=8, random_state=0, n_jobs=1)
ens.fit(noisy.x, data.t, x_dot=noisy.x_dot, feature_names=["x", "y", "z"])
ens.print()
names = ens.get_feature_names()
for k, eq in enumerate(["x", "y", "z"]):
    kept = [f"{names[j]} {p:.2f}" for j, p in enumerate(ens.inclusion_probability_[k]) if p > 0]
    print(f"({eq})' inclusion:", ", ".join(kept))

# %%
fig = ens.plot_inclusion()
