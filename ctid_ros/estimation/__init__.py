"""
Estimation of grey-box parameters: the projection iteration, its starts and the covariance.

Depends on :mod:`ctid_ros.core` only; imports no ROS code. The modules, each importing only
those listed before it (the method is described in ``docs/algorithm.md``):

* :mod:`~ctid_ros.estimation.regressors`: model output, regressors ``phi`` and instruments
  ``psi`` at given coefficients;
* :mod:`~ctid_ros.estimation.correlation`: residual-input correlation and the data's own
  dead-time guess;
* :mod:`~ctid_ros.estimation.integrating`: the stable reformulation of integrating plants;
* :mod:`~ctid_ros.estimation.noise`: the residual's noise model, the covariance valid under
  coloured residuals, the rate the output was measured at;
* :mod:`~ctid_ros.estimation.residual_analysis`: MATLAB ``resid``-style correlations, bounds
  and verdict;
* :mod:`~ctid_ros.estimation.problem`: data, model and bounds of one estimation, its cost and
  linearisation, :class:`~ctid_ros.estimation.problem.State`;
* :mod:`~ctid_ros.estimation.iteration`: the controlled projection iteration and its stop
  reasons;
* :mod:`~ctid_ros.estimation.starts`: equation-error starts and the warm-start check;
* :mod:`~ctid_ros.estimation.delay_search`: the dead-time profile;
* :mod:`~ctid_ros.estimation.estimate`: :func:`~ctid_ros.estimation.estimate.estimate` and
  :class:`~ctid_ros.estimation.estimate.Estimate`.
* :mod:`~ctid_ros.estimation.compare`: candidate structures fitted on one record and ranked,
  the simplest adequate one recommended.
"""

# The package exports nothing itself: import from its modules.
__all__: list = []
