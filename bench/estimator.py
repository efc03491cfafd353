"""
Estimator benchmark against scipy.optimize.least_squares on the same data.

For every reference system and run: fresh noise, a start drawn log-uniformly within a factor
10 of the truth (same start for every method), then

* ctid_ros: the projection estimator (``method='iv'``, automatic dead-time search);
* least_squares LM and TRF on the output error ``y - yhat(theta)``, given the same exact
  simulator and the exact Jacobian (the sensitivities), i.e. a strong hand-rolled baseline;
* least_squares LM-FD: the same LM with scipy's forward-difference Jacobian, the plain
  least_squares fit issue #18 measures the estimator against.

Reported: success rate (every parameter within 20 % of the truth, interchangeable parameters
such as ``T1``, ``T2`` of two lags ordered as in the truth), median time per fit and its
ratio to ctid_ros, and per method the Monte Carlo standard deviation of its successful
estimates divided by the Cramer-Rao bound per parameter, plus the joint ratio over all
parameters (:func:`joint_efficiency`) with the 95 % band an efficient estimator falls in. A
converged least_squares fit is the output-error (maximum-likelihood) estimate itself, so its
ratios show how close to the bound any estimator gets with this record length and noise level.
"""

import argparse
import json
import time
from typing import Callable, Dict, Iterator, List, Optional, Tuple
import warnings

from ctid_ros import estimate, EstimationError, ModelError
from ctid_ros.core import reference_systems
from ctid_ros.core.reference_systems import ReferenceSystem
from ctid_ros.estimation.problem import bound_vectors
from ctid_ros.estimation.regressors import is_stable, SignalBank
import numpy as np
from scipy import optimize, stats
from threadpoolctl import threadpool_limits

FAR = 0.2


def crlb(system: ReferenceSystem) -> np.ndarray:
    """Cramer-Rao bound at the truth, sigma^2 (Psi^T Psi)^-1 (a covariance matrix)."""
    model = system.model
    clean = system.noise_free()
    sigma = np.std(clean) / 10.0 ** (system.snr_db / 20.0)
    bank = SignalBank(model, system.u, clean, system.ts)
    psi = bank.linearize(model.coefficients(system.truth), regressors=False).psi
    return sigma ** 2 * np.linalg.inv(psi.T @ psi)


def joint_efficiency(estimates: np.ndarray, truth: np.ndarray, bound: np.ndarray
                     ) -> Tuple[float, Tuple[float, float]]:
    """
    Return the joint ratio ``sqrt(mean e^T CRLB^-1 e / p)`` and its 95 % band if efficient.

    For an efficient unbiased estimator every run's ``e^T CRLB^-1 e`` is chi-square with ``p``
    degrees of freedom, so over ``M`` runs the ratio is ``sqrt(chi2(M p) / (M p))``: one number
    with a band much narrower than that of each parameter's std/sqrt(CRLB).
    """
    errors = estimates - truth
    degrees = errors.size
    squared = np.einsum('ri,ij,rj->', errors, np.linalg.inv(bound), errors)
    band = tuple(float(np.sqrt(stats.chi2.ppf(q, degrees) / degrees)) for q in (0.025, 0.975))
    return float(np.sqrt(squared / degrees)), band


def draw_start(system: ReferenceSystem, rng: np.random.Generator) -> np.ndarray:
    """Start within a factor 10 of the truth, inside the bounds, with a stable D."""
    model = system.model
    truth = model.vector(system.truth)
    lower, upper = bound_vectors(model, system.bounds)
    while True:
        start = np.clip(truth * 10.0 ** rng.uniform(-1.0, 1.0, truth.size), lower, upper)
        if is_stable(model.coefficients(start).den):
            return start


def least_squares_fit(system: ReferenceSystem, data, start: np.ndarray, method: str,
                      exact_jacobian: bool = True) -> np.ndarray:
    """
    Output-error fit with scipy.optimize.least_squares.

    With the exact sensitivities as its Jacobian, or (``exact_jacobian=False``) scipy's own
    forward differences, as a plain least_squares call would have it.
    """
    model = system.model
    bank = SignalBank(model, data.u, data.y, data.ts)

    def residual(theta):
        # LM has no bounds: a negative dead time is a very bad fit to back off from, not a
        # crash of the baseline.
        try:
            coefficients = model.coefficients(theta)
            with np.errstate(all='ignore'):
                error = data.y - bank.output(coefficients)
        except ModelError:
            return np.full(data.y.size, 1e12)
        return np.where(np.isfinite(error), error, 1e12)

    def jacobian(theta):
        with np.errstate(all='ignore'):
            psi = -bank.linearize(model.coefficients(theta), regressors=False).psi
        return np.where(np.isfinite(psi), psi, 0.0)

    bounds = (-np.inf, np.inf)
    if method == 'trf' and system.bounds:
        bounds = bound_vectors(model, system.bounds)
    with warnings.catch_warnings():
        # Far starts overflow inside scipy's own cost; the failed fit is what counts.
        warnings.simplefilter('ignore', RuntimeWarning)
        result = optimize.least_squares(residual, start,
                                        jac=jacobian if exact_jacobian else '2-point',
                                        method=method, bounds=bounds, x_scale='jac',
                                        max_nfev=2000)
    return result.x


def ctid_fit(system: ReferenceSystem, data, start: np.ndarray) -> np.ndarray:
    result = estimate(system.model, data, system.model.as_dict(start), bounds=system.bounds)
    return system.model.vector(result.params)


METHODS: Dict[str, Callable] = {
    'ctid_ros': ctid_fit,
    'least_squares LM': lambda system, data, start: least_squares_fit(system, data, start, 'lm'),
    'least_squares TRF': lambda system, data, start: least_squares_fit(system, data, start,
                                                                       'trf'),
    # Issue #18's reference: the same LM with finite differences, as a plain call has it.
    'least_squares LM-FD': lambda system, data, start: least_squares_fit(
        system, data, start, 'lm', exact_jacobian=False),
}


def timed_fits(system: ReferenceSystem, runs: int, seed: int,
               fits: Dict[str, Callable[..., np.ndarray]],
               clock: Callable[[], float] = time.perf_counter
               ) -> Iterator[Tuple[str, np.ndarray, float]]:
    """
    Yield ``(name, theta, seconds)`` of every fit of ``runs`` seeded noisy records.

    Each record gets one start (:func:`draw_start`) that every fit in ``fits`` (called as
    ``fit(system, data, start)``) begins from; ``seconds`` is the fit alone on ``clock``;
    ``theta`` is labelled like the truth, NaN where the fit raised.
    """
    size = system.model.vector(system.truth).size
    rng = np.random.default_rng(seed)
    for run in range(runs):
        data = system.data(seed=seed * 1000 + run)
        start = draw_start(system, rng)
        for name, fit in fits.items():
            began = clock()
            try:
                theta = fit(system, data, start)
            except (EstimationError, ValueError, np.linalg.LinAlgError):
                theta = np.full(size, np.nan)
            seconds = clock() - began
            yield name, system.labelled_like_truth(theta), seconds


def run_system(system: ReferenceSystem, runs: int, seed: int) -> dict:
    truth = system.model.vector(system.truth)
    outcomes = {name: {'success': 0, 'times': [], 'estimates': []} for name in METHODS}
    for name, theta, seconds in timed_fits(system, runs, seed, METHODS):
        outcomes[name]['times'].append(seconds)
        close = np.all(np.abs(theta - truth) <= FAR * np.abs(truth))
        outcomes[name]['success'] += bool(close)
        if close:
            outcomes[name]['estimates'].append(theta)
    bound = crlb(system)
    bound_std = np.sqrt(np.diag(bound))
    summary = {'system': system.name, 'runs': runs, 'parameters': list(system.model.parameters),
               'methods': {}}
    baseline = np.median(outcomes['ctid_ros']['times'])
    for name, outcome in outcomes.items():
        median = float(np.median(outcome['times']))
        entry = {'success_rate': outcome['success'] / runs, 'median_time': median,
                 'time_ratio_to_ctid': median / baseline}
        if len(outcome['estimates']) > 2:
            estimates = np.array(outcome['estimates'])
            entry['std_over_sqrt_crlb'] = list(np.std(estimates, axis=0, ddof=1) / bound_std)
            joint, band = joint_efficiency(estimates, truth, bound)
            entry['joint_over_crlb'], entry['joint_band'] = joint, band
            entry['mean_error_in_std'] = list((estimates.mean(axis=0) - truth)
                                              / np.std(estimates, axis=0, ddof=1))
        summary['methods'][name] = entry
    return summary


def print_table(results: List[dict]) -> None:
    print(f'{"system":<36} {"method":<20} {"success":>8} {"median s":>9} {"t/t_ctid":>9} '
          f'{"joint (95% band)":>19}  std/sqrt(CRLB)')
    for result in results:
        for name, entry in result['methods'].items():
            ratios = entry.get('std_over_sqrt_crlb')
            ratio_text = ' '.join(f'{p}={r:.2f}' for p, r in zip(result['parameters'], ratios)
                                  ) if ratios else ''
            joint = f'{entry["joint_over_crlb"]:.2f} ({entry["joint_band"][0]:.2f}-' \
                f'{entry["joint_band"][1]:.2f})' if ratios else ''
            print(f'{result["system"]:<36} {name:<20} {100 * entry["success_rate"]:>7.0f}% '
                  f'{entry["median_time"]:>9.3f} {entry["time_ratio_to_ctid"]:>9.2f} '
                  f'{joint:>19}  {ratio_text}')


def run_on_reference_systems(argv: Optional[List[str]], description: str, default_runs: int,
                             run_system: Callable[[ReferenceSystem, int, int], dict],
                             print_table: Callable[[List[dict]], None]) -> List[dict]:
    """
    Parse ``--runs --seed --json --systems``, run ``run_system`` on each reference system.

    Each system's row is printed as it finishes and the whole table at the end; the results
    go to ``--json`` if given. BLAS is single-threaded for every method alike.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument('--runs', type=int, default=default_runs,
                        help=f'runs per system (default {default_runs})')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--json', default=None, help='also write the results to this file')
    parser.add_argument('--systems', nargs='*', default=None,
                        help='subset of: ' + ', '.join(f.__name__ for f in reference_systems.ALL))
    arguments = parser.parse_args(argv)
    factories = [f for f in reference_systems.ALL
                 if arguments.systems is None or f.__name__ in arguments.systems]
    results = []
    with threadpool_limits(limits=1, user_api='blas'):
        for factory in factories:
            results.append(run_system(factory(), arguments.runs, arguments.seed))
            print_table(results[-1:])
    print()
    print_table(results)
    if arguments.json:
        with open(arguments.json, 'w') as handle:
            json.dump(results, handle, indent=2)
    return results


def main(argv=None) -> List[dict]:
    """Run the benchmark and print its table."""
    return run_on_reference_systems(argv, __doc__.split('\n\n')[0].strip(), 50, run_system,
                                    print_table)


if __name__ == '__main__':
    main()
