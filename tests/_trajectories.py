"""Zoo systems integrated with fixed arithmetic, for tests that need a trajectory."""

import numpy as np


def rk4_trajectory(system, n_samples, burn):
    """States and exact derivatives of a zoo system sampled at its time step, integrated
    by RK4 (four steps per sample) after ``burn`` samples from its initial state: fixed
    arithmetic, so the data are the same in every environment (the zoo's adaptive
    integration of a chaotic system, run for tens of Lyapunov times, is not: its
    trajectories differ between builds of SciPy and NumPy)."""
    from robust_sindy.simulate import rk4

    t = system.dt * np.arange(burn + n_samples)
    x = rk4(lambda _t, v, _u: system.rhs(v[None, :])[0], system.ic, t, substeps=4)[burn:]
    return t[:n_samples], x, system.rhs(x)
