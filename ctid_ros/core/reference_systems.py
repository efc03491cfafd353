"""
Reference identification problems with known answers.

The test systems of ``docs/algorithm.md`` section 16: models, true parameters, inputs, noise
levels, physical bounds and the Cramer-Rao standard deviations at the truth. Tests, benchmarks
and the demo all draw on them.
"""

from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence, Tuple

from ctid_ros.core.data import Data
from ctid_ros.core.excitation import prbs
from ctid_ros.core.model import Model
import numpy as np


@dataclass
class ReferenceSystem:
    """A model, its true parameters, an input and the experiment's noise level."""

    name: str
    model: Model
    truth: Dict[str, float]
    u: np.ndarray
    ts: float
    snr_db: float = 10.0
    bounds: Optional[Dict[str, Tuple[Optional[float], Optional[float]]]] = None
    crlb_std: Dict[str, float] = field(default_factory=dict)
    # Pairs of parameters the model does not tell apart (swapping them changes nothing).
    interchangeable: Sequence[Tuple[str, str]] = ()

    def noise_free(self) -> np.ndarray:
        """Return the exact output at the true parameters."""
        return self.model.simulate(self.truth, self.u, self.ts)

    def data(self, seed: int) -> Data:
        """Return noisy data: white Gaussian output noise at the system's SNR."""
        clean = self.noise_free()
        sigma = np.std(clean) / 10.0 ** (self.snr_db / 20.0)
        noise = np.random.default_rng(seed).standard_normal(clean.size)
        return Data(self.u, clean + sigma * noise, self.ts)

    def labelled_like_truth(self, theta: np.ndarray) -> np.ndarray:
        """
        Return ``theta`` (``model.parameters`` order), interchangeable pairs ordered as the truth.

        ``T1`` and ``T2`` of ``(T1 s + 1)(T2 s + 1)`` are one model either way round: an estimate
        is compared with the truth after putting the larger value where the truth has it.
        """
        theta = np.array(theta, dtype=float)
        names = list(self.model.parameters)
        for first, second in self.interchangeable:
            i, j = names.index(first), names.index(second)
            if (theta[i] > theta[j]) != (self.truth[first] > self.truth[second]):
                theta[[i, j]] = theta[[j, i]]
        return theta


def rao_garnier() -> ReferenceSystem:
    """Rao-Garnier 4th-order black-box benchmark (test 1)."""
    return ReferenceSystem(
        'Rao-Garnier', Model('(b1*s + b0)/(s**4 + a3*s**3 + a2*s**2 + a1*s + a0)'),
        {'a0': 1600.0, 'a1': 416.0, 'a2': 408.0, 'a3': 5.0, 'b0': 1600.0, 'b1': -6400.0},
        prbs(10, 7), 0.01,
        crlb_std={'a0': 7.74, 'a1': 3.55, 'a2': 1.06, 'a3': 0.0604, 'b0': 71.6, 'b1': 40.4})


def mass_spring_damper() -> ReferenceSystem:
    """Open-loop mass-spring-damper 1/(m s^2 + d s + k) (test 2)."""
    return ReferenceSystem(
        'mass-spring-damper', Model('1/(m*s**2 + d*s + k)'),
        {'m': 0.5, 'd': 1.0, 'k': 50.0}, prbs(9, 4), 0.01,
        bounds={'m': (1e-3, 100.0), 'd': (0.0, 100.0), 'k': (0.0, 1e4)},
        crlb_std={'m': 0.0050, 'd': 0.0105, 'k': 0.476})


def closed_loop_pid() -> ReferenceSystem:
    """Unstable mass-spring plant under a known PID controller (test 3)."""
    return ReferenceSystem(
        'closed-loop unstable plant (PID)',
        Model('1/(m*s**2 + d*s + k)', controller='(5*s**2 + 20*s + 10)/(s*(0.02*s + 1))'),
        {'m': 1.0, 'd': 0.5, 'k': -2.0}, prbs(9, 20), 0.01,
        bounds={'m': (1e-3, 50.0), 'd': (-10.0, 50.0), 'k': (-50.0, 50.0)},
        crlb_std={'m': 0.00527, 'd': 0.01886, 'k': 0.0864})


def first_order_dead_time() -> ReferenceSystem:
    """First order plus a fractional dead time (test 4)."""
    return ReferenceSystem(
        'first order plus dead time', Model('K*exp(-tau*s)/(T*s + 1)'),
        {'K': 2.0, 'T': 5.0, 'tau': 1.234}, prbs(8, 10), 0.1,
        bounds={'T': (1e-3, None), 'tau': (0.0, 10.0)},
        crlb_std={'K': 0.0176, 'T': 0.0661, 'tau': 0.0107})


def second_order_dead_time() -> ReferenceSystem:
    """Second order with a long dead time, the CONTSID TDSRIVC demo (multimodal in tau)."""
    return ReferenceSystem(
        'second order plus long dead time', Model('b0*exp(-tau*s)/(s**2 + a1*s + a0)'),
        {'b0': 12.0, 'a1': 4.0, 'a0': 4.0, 'tau': 8.0}, prbs(8, 20), 0.1, snr_db=15.0,
        bounds={'tau': (0.0, 15.0)},
        crlb_std={'b0': 0.52, 'a1': 0.15, 'a0': 0.17, 'tau': 0.010})


def second_order_nonaffine() -> ReferenceSystem:
    """Second order in gain, natural frequency and damping: not affine (test 5)."""
    return ReferenceSystem(
        'non-affine second order', Model('K*w**2/(s**2 + 2*z*w*s + w**2)'),
        {'K': 1.5, 'w': 3.0, 'z': 0.2}, prbs(9, 5), 0.02,
        bounds={'w': (1e-3, None), 'z': (1e-3, None)},
        crlb_std={'K': 0.0136, 'w': 0.0053, 'z': 0.0026})


def two_lags_dead_time() -> ReferenceSystem:
    """Two real lags plus a dead time (the hair dryer's structure): not affine, symmetric."""
    return ReferenceSystem(
        'two lags plus dead time', Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'),
        {'K': 2.0, 'T1': 1.5, 'T2': 0.4, 'tau': 0.7}, prbs(8, 10), 0.1,
        bounds={'T1': (1e-3, None), 'T2': (1e-3, None), 'tau': (0.0, 10.0)},
        crlb_std={'K': 0.0176, 'T1': 0.0438, 'T2': 0.0331, 'tau': 0.0171},
        interchangeable=(('T1', 'T2'),))


ALL = (rao_garnier, mass_spring_damper, closed_loop_pid, first_order_dead_time,
       second_order_dead_time, second_order_nonaffine, two_lags_dead_time)
