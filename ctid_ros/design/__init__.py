"""
Decisions from an identified model: the controller it implies, checked against its uncertainty.

Depends on :mod:`ctid_ros.core` and :mod:`ctid_ros.estimation` only; imports no ROS code. The
modules, each importing only those listed before it:

* :mod:`~ctid_ros.design.margins`: PID controllers as transfer functions, the loop's stability
  (Nyquist, with the exact dead time), gain and phase margins, Ms, bandwidth, and the
  closed-loop step response;
* :mod:`~ctid_ros.design.tune`: :func:`~ctid_ros.design.tune.tune`, gains from an estimate by
  a stated rule (SIMC) or a loop-shaping design, verified on the estimate and on draws from
  its covariance.

The comparison of candidate structures that comes before a design is
:mod:`ctid_ros.estimation.compare`.
"""

# The package exports nothing itself: import from its modules.
__all__: list = []
