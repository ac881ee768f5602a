"""Time series: the records, the temporal screen, the derivatives.

* :mod:`~robust_sindy.timeseries.trajectories` -- the user's records, checked
  (:class:`~robust_sindy.timeseries.trajectories.Trajectories`);
* :mod:`~robust_sindy.timeseries.temporal` -- entries inconsistent with their
  neighbours in time (model-free);
* :mod:`~robust_sindy.timeseries.differentiation` -- numerical derivatives;
* :mod:`~robust_sindy.timeseries.derivatives` -- the derivative stage of a fit.
"""
