"""Time series: the records, the temporal screen, missing readings, the derivatives and
the weak form.

* :mod:`~robust_sindy.timeseries.trajectories` -- the user's records, checked
  (:class:`~robust_sindy.timeseries.trajectories.Trajectories`);
* :mod:`~robust_sindy.timeseries.temporal` -- entries inconsistent with their
  neighbours in time (model-free), missing ones filled;
* :mod:`~robust_sindy.timeseries.missing` -- readings not measured (NaN): how each kind
  is handled, and the counts;
* :mod:`~robust_sindy.timeseries.differentiation` -- numerical derivatives;
* :mod:`~robust_sindy.timeseries.derivatives` -- the derivative stage of a fit;
* :mod:`~robust_sindy.timeseries.weak` -- the weak form's rows (integrals against test
  functions).
"""
