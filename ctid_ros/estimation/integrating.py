"""
Integrating plants: an exact reformulation with a stable denominator.

A position driven by a motor has ``D(s, theta) = s^k D'(s, theta)``: ``D`` has ``k`` roots at
zero for every ``theta``, so the filters ``1/D`` of the method are not stable and the simulated
output drifts with any error in an offset. Multiplying the model ``D y = N u`` by the stable
``1/(D' (s + c)^k)`` gives the equivalent model

    y_c = N(s, theta) / (D'(s, theta) (s + c)^k) u,    y_c = (s / (s + c))^k y,

whose output ``y_c`` is the measured output through a fixed high-pass filter with corner ``c``
(rad/s) and whose denominator is Hurwitz whenever ``D'`` is. The parameters, the inputs and the
numerators are unchanged, so the whole method (projections, instruments, covariance) applies
to it as it is. The high pass removes what an integrator cannot be fitted on: the initial
position and slow drift (``y`` is filtered from rest at its first sample). See
``docs/algorithm.md`` section 13.
"""

from ctid_ros.core.model import Coefficients, Model
from ctid_ros.core.simulation import response
import numpy as np

__all__ = ['StabilizedModel', 'default_cutoff']


def default_cutoff(duration: float) -> float:
    """Corner (rad/s) of the high pass for a record of ``duration`` seconds: ten periods."""
    return 20.0 * np.pi / duration


class StabilizedModel:
    """
    The model ``N / (D' (s + cutoff)^k)`` equivalent to an integrating ``N / (s^k D')``.

    It stands in for the :class:`~ctid_ros.core.model.Model` during estimation: it has the same
    parameters, inputs and attributes, and only :meth:`coefficients` differs.
    """

    def __init__(self, model: Model, cutoff: float):
        if not (np.isfinite(cutoff) and cutoff > 0.0):
            raise ValueError(f'the integrator cutoff must be a positive frequency in rad/s, '
                             f'got {cutoff}')
        self.model = model
        self.cutoff = float(cutoff)
        self.integrators = 0
        self._order = model.integrators
        self._factor = np.poly(np.full(model.integrators, -self.cutoff))

    def __getattr__(self, name: str):
        return getattr(self.model, name)

    def coefficients(self, params) -> Coefficients:
        """Return the coefficients of the stabilised model at ``params``."""
        original = self.model.coefficients(params)
        order = self._order
        den = np.convolve(original.den[:-order], self._factor)
        den_jacobian = np.array([np.convolve(row[:-order], self._factor)
                                 for row in original.den_jacobian])
        return Coefficients(original.num, den, original.delay, original.num_jacobian,
                            den_jacobian, original.delay_gradient)

    def filtered_output(self, y: np.ndarray, ts: float) -> np.ndarray:
        """Return ``(s / (s + cutoff))^k y`` (``y`` linear between samples, at rest at y[0])."""
        highpass = np.zeros(self._order + 1)
        highpass[0] = 1.0
        return response(highpass, self._factor, y - y[0], ts, intersample='foh')
