"""
The simulator a user writes by hand with scipy, for the benchmarks' user baselines (issue #26).

Nothing of ctid_ros: an exact sampled response of ``num(s)/den(s) exp(-delay s)`` to a held
input from ``scipy.signal.cont2discrete`` and one ``scipy.signal.lfilter`` pass.
"""

import numpy as np
from scipy import signal

__all__ = ['user_simulate']


def user_simulate(num: np.ndarray, den: np.ndarray, delay: float, u: np.ndarray,
                  ts: float) -> np.ndarray:
    """
    Exact sampled response of ``num/den exp(-delay s)`` to a held input, starting at rest.

    ``delay = d ts + eps``: ``x[k+1] = Phi x[k] + G0 u[k-d] + G1 u[k-d-1]`` with
    ``G0 = int_0^{ts-eps} e^{As} B ds`` and ``G1 = e^{A(ts-eps)} int_0^eps e^{As} B ds``;
    the output ``C x + D u[k-d]`` is one lfilter pass of the combined transfer function.
    """
    a, b, c, d = signal.tf2ss(num, den)
    whole = int(np.floor(delay / ts + 1e-9))
    eps = delay - whole * ts
    if eps < 1e-9 * ts:
        phi, gamma0, c, d, _ = signal.cont2discrete((a, b, c, d), ts, method='zoh')
        gamma1 = np.zeros_like(gamma0)
    else:
        phi0, gamma0, _, _, _ = signal.cont2discrete((a, b, c, d), ts - eps, method='zoh')
        phi_eps, gamma_eps, _, _, _ = signal.cont2discrete((a, b, c, d), eps, method='zoh')
        phi = phi0 @ phi_eps
        gamma1 = phi0 @ gamma_eps
    # Output of input u[k-d] through C (zI - Phi)^-1 (G0 + G1 z^-1) + D, over det(zI - Phi).
    num0, den_z = signal.ss2tf(phi, gamma0, c, d)
    num1, _ = signal.ss2tf(phi, gamma1, c, np.zeros_like(d))
    order = den_z.size
    b_z = np.zeros(order + 1)
    b_z[:order] += num0[0]
    b_z[1:] += num1[0]
    shifted = np.zeros_like(u)
    if whole < u.size:
        shifted[whole:] = u[:u.size - whole]
    return signal.lfilter(b_z, den_z, shifted)
