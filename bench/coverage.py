"""
Coverage of the reported uncertainty: how often the 95 % intervals contain the truth.

For reference systems with known parameters, Monte Carlo runs (fresh noise each) of
``estimate(..., 'auto')`` in these cases:

* ``white``: white Gaussian output noise at the system's SNR;
* ``AR(1) 0.9``: the same variance, coloured by ``1/(1 - 0.9 q^-1)``;
* ``grid 4x``: white noise, the input held and the output measured every ``ts``, then put on a
  grid four times finer (input held, output linearly interpolated) and estimated there, as a
  resampler with a too-fine ``sample_time`` would.

and for two systems of issue #24:

* ``fed back``: the plant ``K/(s (T s + 1))`` under a known PI (the model is the closed loop
  from ``r``), white measurement noise at 10 dB fed back through the controller;
* ``ARMA`` on a 300-sample first order with a fractional dead time (also on the systems
  above): noise ``(1 + 0.5 q^-1)/(1 - 0.9 q^-1)``.

Reported per case and parameter: the fraction of runs whose interval ``estimate +- 1.96 std``
contains the truth (target 90-98 %), the Monte Carlo spread over the mean reported std, the
same fraction for the white-noise formula ``sigma^2 (Psi^T Psi)^-1`` at the same estimates
(what the estimator reported before issue #13), the same for the noise model's order chosen
by BIC (before issue #24), the median time per estimate and how many fits the consistency check
flagged (false alarms: these models are adequate). Then (``adequacy``) a FOPDT fitted to
records it does not describe over their whole length (a missed lag, a drifting gain, a
saturation, on an input whose character changes halfway): how often the check flags it.

Run with ``.venv/bin/python -m bench.coverage [--runs 200]``.
"""

import argparse
import json
import time
from typing import Callable, Dict, List, Optional, Tuple

from ctid_ros import Data, estimate, EstimationError, Model
from ctid_ros.core import reference_systems
from ctid_ros.core.excitation import prbs
from ctid_ros.core.reference_systems import ReferenceSystem
from ctid_ros.estimation.estimate import build_problem
from ctid_ros.estimation.noise import coloured_covariance
import numpy as np
from scipy import signal
from threadpoolctl import threadpool_limits

FINER = 4
Z95 = 1.959964


def _noise(system: ReferenceSystem, clean: np.ndarray, rng: np.random.Generator,
           pole: float) -> np.ndarray:
    sigma = np.std(clean) / 10.0 ** (system.snr_db / 20.0)
    white = rng.standard_normal(clean.size + 500)
    if pole:
        # Unit variance after the filter; 500 samples discarded so it starts stationary.
        coloured = signal.lfilter([np.sqrt(1.0 - pole ** 2)], [1.0, -pole], white)[500:]
        return sigma * coloured
    return sigma * white[500:]


def white_data(system: ReferenceSystem, rng: np.random.Generator) -> Data:
    """Return the system's data with white output noise."""
    clean = system.noise_free()
    return Data(system.u, clean + _noise(system, clean, rng, 0.0), system.ts)


def coloured_data(system: ReferenceSystem, rng: np.random.Generator) -> Data:
    """Return the system's data with AR(1) output noise of pole 0.9, same variance."""
    clean = system.noise_free()
    return Data(system.u, clean + _noise(system, clean, rng, 0.9), system.ts)


def fine_grid_data(system: ReferenceSystem, rng: np.random.Generator) -> Data:
    """Return white-noise data measured every ts, put on a grid ts / 4 (u held, y linear)."""
    measured = white_data(system, rng)
    count = len(measured) * FINER - (FINER - 1)
    fine_time = np.arange(count) / FINER
    u = np.repeat(measured.u, FINER)[:count]
    y = np.interp(fine_time, np.arange(len(measured)), measured.y)
    return Data(u, y, system.ts / FINER)


def arma_noise(rng: np.random.Generator, count: int) -> np.ndarray:
    """Return stationary ARMA noise ``(1 + 0.5 q^-1) / (1 - 0.9 q^-1)`` of unit variance."""
    white = rng.standard_normal(count + 500)
    coloured = signal.lfilter([1.0, 0.5], [1.0, -0.9], white)[500:]
    # The filter's power gain: 1 + (0.5 + 0.9)^2 / (1 - 0.81).
    return coloured / np.sqrt(1.0 + 1.4 ** 2 / (1.0 - 0.81))


def arma_data(system: ReferenceSystem, rng: np.random.Generator) -> Data:
    """Return the system's data with ARMA output noise of the same variance."""
    clean = system.noise_free()
    sigma = np.std(clean) / 10.0 ** (system.snr_db / 20.0)
    return Data(system.u, clean + sigma * arma_noise(rng, clean.size), system.ts)


def fed_back_data(system: ReferenceSystem, rng: np.random.Generator) -> Data:
    """
    Return closed-loop data whose measured output, noise included, is fed back.

    The model is the closed loop ``T`` from ``r`` to ``y``: the noise ``v`` enters where the
    measurement is subtracted from ``r``, so ``y = T r + (1 - T) v``, ``1 - T`` the sensitivity
    ``1 / (1 + C G)``; white ``v`` at the system's SNR.
    """
    clean = system.noise_free()
    sigma = np.std(clean) / 10.0 ** (system.snr_db / 20.0)
    noise = sigma * rng.standard_normal(clean.size)
    return Data(system.u, clean + noise - system.model.simulate(system.truth, noise, system.ts),
                system.ts)


def closed_loop_integrator() -> ReferenceSystem:
    """Return the plant ``K/(s (T s + 1))`` under a known PI, r -> y, at 10 dB."""
    return ReferenceSystem(
        'integrator + lag under PI', Model('K/(s*(T*s + 1))', controller='(0.8*s + 0.2)/s'),
        {'K': 2.0, 'T': 0.5}, prbs(9, 8)[:4000], 0.05,
        bounds={'K': (1e-3, None), 'T': (1e-3, None)})


def short_dead_time() -> ReferenceSystem:
    """Return a 300-sample first order with a fractional dead time (3.7 samples), 10 dB."""
    return ReferenceSystem(
        'short record, FOPDT', Model('K*exp(-tau*s)/(T*s + 1)'),
        {'K': 2.0, 'T': 1.0, 'tau': 0.37}, prbs(6, 5)[:300], 0.1,
        bounds={'T': (1e-3, None), 'tau': (0.0, 3.0)})


CASES: Dict[str, Callable[[ReferenceSystem, np.random.Generator], Data]] = {
    'white': white_data,
    'AR(1) 0.9': coloured_data,
    'grid 4x': fine_grid_data,
    'ARMA': arma_data,
    'fed back': fed_back_data,
}
# Each system with its cases.
SYSTEMS: Tuple[Tuple[Callable[[], ReferenceSystem], Tuple[str, ...]], ...] = (
    (reference_systems.first_order_dead_time, ('white', 'AR(1) 0.9', 'grid 4x', 'ARMA')),
    (reference_systems.second_order_nonaffine, ('white', 'AR(1) 0.9', 'grid 4x', 'ARMA')),
    (closed_loop_integrator, ('fed back',)),
    (short_dead_time, ('ARMA',)),
)


FOPDT = Model('K*exp(-tau*s)/(T*s + 1)')
FOPDT_BOUNDS = {'T': (1e-3, None), 'tau': (0.0, 10.0)}
FOPDT_TRUTH = {'K': 2.0, 'T': 5.0, 'tau': 1.234}


def operating_input(slow: float = 1.0, fast: float = 1.0) -> np.ndarray:
    """Return an input that is not stationary: slow moves, then faster ones (Ts 0.1 s)."""
    return np.concatenate([slow * prbs(7, 30), fast * prbs(8, 6)])


def missing_lag(rng: np.random.Generator) -> Data:
    """Return a second order plus dead time (the FOPDT misses a lag), ARMA noise at 20 dB."""
    u = operating_input()
    clean = Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))').simulate(
        {'K': 2.0, 'T1': 1.5, 'T2': 0.6, 'tau': 0.7}, u, 0.1)
    return Data(u, clean + np.std(clean) / 10.0 * arma_noise(rng, u.size), 0.1)


def drifting_gain(rng: np.random.Generator) -> Data:
    """Return a FOPDT whose gain drifts from -15 % to +15 % over the record, ARMA at 20 dB."""
    u = operating_input()
    clean = FOPDT.simulate(FOPDT_TRUTH, u, 0.1) * np.linspace(0.85, 1.15, u.size)
    return Data(u, clean + np.std(clean) / 10.0 * arma_noise(rng, u.size), 0.1)


def saturating(rng: np.random.Generator) -> Data:
    """Return a FOPDT followed by a saturation ``0.7 tanh(x / 0.7)``, small then large moves."""
    u = operating_input(0.3, 1.5)
    clean = 0.7 * np.tanh(FOPDT.simulate(FOPDT_TRUTH, u, 0.1) / 0.7)
    return Data(u, clean + np.std(clean) / 10.0 * arma_noise(rng, u.size), 0.1)


# Records a FOPDT does not describe over their whole length (docs/algorithm.md section 18).
INADEQUATE: Dict[str, Callable[[np.random.Generator], Data]] = {
    'missing lag': missing_lag,
    'drifting gain': drifting_gain,
    'saturation': saturating,
}


def adequacy(runs: int, seed: int) -> List[dict]:
    """Return how often the FOPDT fitted to each :data:`INADEQUATE` record is flagged."""
    results = []
    for index, (name, make) in enumerate(INADEQUATE.items()):
        rng = np.random.default_rng(seed + index)
        flagged, max_z, widened = 0, [], []
        for _ in range(runs):
            result = estimate(FOPDT, make(rng), 'auto', bounds=FOPDT_BOUNDS)
            flagged += not result.consistency.consistent
            max_z.append(result.consistency.max_z)
            widened.append(max(result.std[key] / result.std_noise[key] for key in result.std))
        results.append({'case': name, 'runs': runs, 'flagged': flagged,
                        'max_z_median': float(np.median(max_z)),
                        'std_over_noise_std_median': float(np.median(widened))})
        print(f'FOPDT on {name:<14} flagged {flagged}/{runs}, median max z '
              f'{np.median(max_z):.2f}, median std / noise-only std {np.median(widened):.2f}',
              flush=True)
    return results


def white_formula_std(system: ReferenceSystem, data: Data, theta: np.ndarray) -> np.ndarray:
    """Return the standard deviations of ``sigma^2 (Psi^T Psi)^-1`` at ``theta``."""
    problem, _ = build_problem(system.model, data, bounds=system.bounds)
    lin = problem.linearize(problem.model.coefficients(theta), regressors=False)
    error = problem.measured - lin.output
    variance = float(error @ error) / (error.size - theta.size)
    return np.sqrt(np.diag(variance * np.linalg.inv(lin.psi.T @ lin.psi)))


def bic_noise_std(system: ReferenceSystem, data: Data, theta: np.ndarray) -> np.ndarray:
    """Return the standard deviations with the noise model's order chosen by BIC at ``theta``."""
    problem, _ = build_problem(system.model, data, bounds=system.bounds)
    lin = problem.linearize(problem.model.coefficients(theta), regressors=False)
    scales = np.linalg.norm(lin.psi, axis=0)
    scaled, _ = coloured_covariance(lin.psi / scales, problem.measured - lin.output,
                                    theta.size, criterion='bic')
    return np.sqrt(np.diag(scaled)) / scales


def run_case(system: ReferenceSystem, case: str, runs: int, seed: int) -> dict:
    """Return the coverage of every parameter over ``runs`` estimates."""
    make = CASES[case]
    rng = np.random.default_rng(seed)
    names = system.model.parameters
    truth = system.model.vector(system.truth)
    inside = np.zeros(len(names))
    inside_white = np.zeros(len(names))
    inside_bic = np.zeros(len(names))
    inside_noise = np.zeros(len(names))
    errors, stds, times, verdicts = [], [], [], {'white': 0, 'coloured': 0, 'input': 0}
    failures = flagged = 0
    for _ in range(runs):
        data = make(system, rng)
        began = time.perf_counter()
        try:
            result = estimate(system.model, data, 'auto', bounds=system.bounds)
        except EstimationError:
            failures += 1
            continue
        times.append(time.perf_counter() - began)
        theta = system.model.vector(result.params)
        # A parameter held at a bound has no interval (NaN): it does not cover the truth.
        std = np.array([result.std[name] for name in names])
        inside += np.abs(theta - truth) <= Z95 * std
        inside_white += np.abs(theta - truth) <= Z95 * white_formula_std(system, data, theta)
        inside_bic += np.abs(theta - truth) <= Z95 * bic_noise_std(system, data, theta)
        noise_only = np.array([result.std_noise[name] for name in names])
        inside_noise += np.abs(theta - truth) <= Z95 * noise_only
        flagged += not result.consistency.consistent
        if np.all(np.isfinite(std)):
            errors.append(theta - truth)
            stds.append(std)
        residuals = result.residuals
        verdicts['input' if residuals.input_correlated else
                 'white' if residuals.white else 'coloured'] += 1
    done = max(runs - failures, 1)
    spread = np.std(np.array(errors), axis=0, ddof=1)
    return {'system': system.name, 'case': case, 'runs': runs, 'failures': failures,
            'parameters': list(names), 'coverage': list(inside / done),
            'white_formula_coverage': list(inside_white / done),
            'bic_noise_coverage': list(inside_bic / done),
            'noise_only_coverage': list(inside_noise / done),
            'inconsistent': flagged,
            'spread_over_std': list(spread / np.mean(np.array(stds), axis=0)),
            'median_time': float(np.median(times)), 'verdicts': verdicts}


def print_table(results: List[dict]) -> None:
    """Print one line per system and case."""
    print(f'{"system":<30} {"case":<10} {"runs":>5} {"time s":>7}  coverage of 95 % intervals '
          '(MC spread / reported std) [BIC noise model | white formula]   verdicts '
          'white/coloured/input   inconsistent')
    for result in results:
        cells = '  '.join(f'{name} {100 * value:5.1f}% ({ratio:.2f}) [{100 * bic:4.1f}% | '
                          f'{100 * white:4.1f}%]' for name, value, ratio, bic, white in
                          zip(result['parameters'], result['coverage'],
                              result['spread_over_std'], result['bic_noise_coverage'],
                              result['white_formula_coverage']))
        verdicts = result['verdicts']
        print(f'{result["system"]:<30} {result["case"]:<10} {result["runs"]:>5} '
              f'{result["median_time"]:>7.3f}  {cells}   {verdicts["white"]}/'
              f'{verdicts["coloured"]}/{verdicts["input"]}   {result["inconsistent"]}'
              + (f'  ({result["failures"]} failed)' if result['failures'] else ''))


def main(argv: Optional[List[str]] = None) -> List[dict]:
    """Run every system and case and print the coverage table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--runs', type=int, default=200, help='runs per case (default 200)')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--json', default=None, help='also write the results to this file')
    parser.add_argument('--only', nargs='*', default=None, metavar='SYSTEM',
                        help='only these systems (by name)')
    arguments = parser.parse_args(argv)
    results = []
    with threadpool_limits(limits=1, user_api='blas'):
        for factory, cases in SYSTEMS:
            system = factory()
            for case in cases:
                if arguments.only and system.name not in arguments.only:
                    continue
                results.append(run_case(system, case, arguments.runs,
                                        arguments.seed * 100 + list(CASES).index(case)))
                print_table(results[-1:])
    print()
    print_table(results)
    inadequate = [] if arguments.only else adequacy(max(arguments.runs // 4, 10),
                                                    arguments.seed * 100 + 50)
    if arguments.json:
        with open(arguments.json, 'w') as handle:
            json.dump({'coverage': results, 'inadequate': inadequate}, handle, indent=2)
    return results


if __name__ == '__main__':
    main()
