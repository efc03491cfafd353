"""
The whole fit a user writes by hand with scipy: read a CSV, fit ``K exp(-tau s)/(T s + 1)``.

The hand-written counterpart of ``ctid fit data.csv --model 'K*exp(-tau*s)/(T*s + 1)'`` that
``bench/cli_startup.py`` times as a fresh process (issue #26): numpy reads the columns ``t``,
``u``, ``y``; :func:`bench.user_simulator.user_simulate` simulates; scipy's least_squares (LM,
forward differences) fits from the start given on the command line; the estimate is printed.

Run from the repository with ``python -m bench.user_fit_script data.csv K T tau``.
"""

import sys

from bench.user_simulator import user_simulate
import numpy as np
from scipy import optimize

__all__ = ['main']


def main(argv=None) -> int:
    """Fit the first-order model with dead time to the CSV file and print the estimate."""
    path, *start = sys.argv[1:] if argv is None else argv
    table = np.genfromtxt(path, delimiter=',', names=True)
    t, u, y = table['t'], table['u'], table['y']
    ts = float(np.median(np.diff(t)))

    def residual(theta):
        gain, lag, delay = theta
        if delay < 0.0 or lag == 0.0:
            return np.full(y.size, 1e12)
        return y - user_simulate(np.array([gain]), np.array([lag, 1.0]), delay, u, ts)

    result = optimize.least_squares(residual, np.array(start, dtype=float), method='lm',
                                    x_scale='jac')
    print(dict(zip(('K', 'T', 'tau'), result.x)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
