"""
Which model holds: candidate structures fitted on one record, ranked, the simplest adequate one.

:func:`compare` fits every candidate with :func:`~ctid_ros.estimation.estimate.estimate` on
the same estimation data and judges each on what a control engineer weighs:

* **fit on validation data**: the held-out last part of the record (the model simulated over
  the whole record from rest, scored on the held-out samples only, so no initial state is
  guessed) or a separate validation record (:meth:`Estimate.compare`);
* **information criteria** from the output-error cost ``V = |e|^2 / N``:
  ``AIC = N ln V + 2 k`` and ``BIC = N ln V + k ln N`` (``k`` parameters, ``N`` fitted samples);
* **consistency across the record**: :attr:`Estimate.consistency` (one parameter vector over
  halves and quarters); a candidate without it counts as "not checked";
* **the residual verdict**: a residual correlated with the input means missing dynamics;
* **identifiability**: the estimate's warnings that the data barely determine a combination,
  do not determine a parameter, or drop a lag.

A candidate is *adequate* if it converged, its residual is independent of the input, it is
not inconsistent over the record, the data determine its parameters, its validation fit is
within :data:`FIT_TOLERANCE` percentage points of the best candidate's, and no candidate with
more parameters beats it decisively: a BIC lower by more than :data:`BIC_MARGIN` (strong
evidence on Kass and Raftery's scale) confirmed on the validation data, where its errors are
smaller (:func:`paired_improvement`: the squared errors of the two compared sample by sample,
in :data:`BATCHES` contiguous batches so that correlated errors are not counted as
independent, ``t >`` :data:`SIGNIFICANT`). The BIC is the evidence (at 10 dB of noise a
missing lag costs 0.3-0.8 points of validation fit, too little to test on a few hundred
samples, and 30-140 of BIC); the held-out data must point the same way, so that the BIC's
overconfidence when residuals are correlated cannot decide alone.

The recommendation is the adequate candidate with the fewest parameters (ties: lower BIC).
If none is adequate, consistency is set aside (a plant that changes over the record defeats
every structure, and a borderline check may be a false alarm): the simplest candidate adequate
but for it is recommended, saying so; failing that, the best validation fit, saying why it is
still not adequate. Exactly one candidate is recommended.

Nested starts: a candidate whose parameter names include all of an already fitted, simpler
candidate's starts from that candidate's values for them (the rest automatic); the estimator's
own nested starts (:func:`~ctid_ros.estimation.estimate.estimate`) then keep it from ending
worse than the structures it contains.
"""

from dataclasses import dataclass, field
import math
from typing import Dict, List, Mapping, Optional, Sequence, Union

from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import ConfigError, CtidError, DataError, EstimationError
from ctid_ros.estimation.estimate import Estimate, estimate, fit_percent
import numpy as np

__all__ = ['BATCHES', 'BIC_MARGIN', 'Candidate', 'Comparison', 'FIT_TOLERANCE', 'HOLDOUT',
           'SIGNIFICANT', 'compare', 'information_criteria', 'paired_improvement']

# Share of the record held out for validation when no validation data are given.
HOLDOUT = 0.3
# Validation fit (percentage points) an adequate candidate may lose to the best one.
FIT_TOLERANCE = 5.0
# A richer candidate decisively better: BIC lower by this much ...
BIC_MARGIN = 10.0
# ... and confirmed on the validation data: its errors smaller by this t statistic of batch
# means (about 83 % one-sided for BATCHES - 1 = 9 degrees of freedom).
SIGNIFICANT = 1.0
BATCHES = 10
# The problem text of an inconsistent candidate starts so.
_INCONSISTENT = 'not consistent over the record'
# Words of the estimator's warnings that say the data do not determine the parameters.
_UNIDENTIFIED = ('barely determine', 'do not determine', 'not identifiable',
                 'the data prefer the model without it')
# Fewest samples of either part of a held-out split.
_MIN_SAMPLES = 50


@dataclass
class Candidate:
    """
    One candidate structure of :func:`compare`, fitted and judged.

    Attributes
    ----------
    model : Model
        The structure.
    estimate : Estimate or None
        Its fit on the estimation data (None if the estimation failed).
    error : str
        Why the estimation failed ('' if it did not).
    fit : float
        Fit in percent on the validation data (NaN if failed).
    aic, bic : float
        Information criteria of the output-error cost on the estimation data.
    consistent : bool or None
        Consistency across the record (None: not checked).
    residual : str
        The residual verdict.
    problems : list of str
        What makes it inadequate, in words (empty: adequate).
    recommended : bool
        The one recommended.
    why : str
        One line: why it is (not) recommended.

    """

    model: Model
    estimate: Optional[Estimate]
    error: str = ''
    fit: float = float('nan')
    aic: float = float('nan')
    bic: float = float('nan')
    consistent: Optional[bool] = None
    residual: str = ''
    problems: List[str] = field(default_factory=list)
    recommended: bool = False
    why: str = ''
    validation_error: Optional[np.ndarray] = field(default=None, repr=False)

    @property
    def parameters(self) -> int:
        """Return the number of parameters of the structure."""
        return len(self.model.parameters)

    @property
    def adequate(self) -> bool:
        """Return True if nothing makes the candidate inadequate."""
        return self.estimate is not None and not self.problems

    def to_dict(self) -> dict:
        """
        Return the ``ctid compare --json`` item.

        ``model``, ``params``, ``std``, ``fit`` (validation, %), ``consistent`` (null: not
        checked), ``recommended``, ``why``; also ``aic``, ``bic``, ``parameters``,
        ``estimation_fit``, ``residual``, ``problems``, ``warnings`` and ``error``.
        """
        def number(value: float) -> Optional[float]:
            return float(value) if value is not None and np.isfinite(value) else None

        result = self.estimate
        summary = {
            'model': self.model.expression,
            'params': dict(result.params) if result else {},
            'std': {name: number(value) for name, value in result.std.items()} if result else {},
            'fit': number(self.fit),
            'consistent': self.consistent,
            'recommended': bool(self.recommended),
            'why': self.why,
            'aic': number(self.aic), 'bic': number(self.bic),
            'parameters': self.parameters,
            'estimation_fit': number(result.fit) if result else None,
            'residual': self.residual,
            'problems': list(self.problems),
            'warnings': list(result.warnings) if result else [],
        }
        if self.error:
            summary['error'] = self.error
        return summary


@dataclass
class Comparison:
    """
    The outcome of :func:`compare`: the candidates ranked, best first.

    Attributes
    ----------
    candidates : list of Candidate
        Best first: the recommended one, the other adequate ones (fewest parameters, then
        BIC), then the inadequate ones by validation fit, failed ones last.
    estimation, validation : Data
        The data fitted and the data scored.
    held_out : bool
        True if ``validation`` is the held-out end of the record (scored after simulating
        the whole record), False for separate validation data.
    record : Data
        The whole record given.

    """

    candidates: List[Candidate]
    estimation: Data
    validation: Data
    held_out: bool
    record: Data

    def simulated(self, candidate: Candidate) -> np.ndarray:
        """Return the output of a fitted candidate on the validation samples, as scored."""
        if self.held_out:
            return candidate.estimate.predict(self.record)[len(self.estimation):]
        return candidate.estimate.predict(self.validation)

    @property
    def recommended(self) -> Candidate:
        """Return the recommended candidate."""
        return next(item for item in self.candidates if item.recommended)

    def to_list(self) -> List[dict]:
        """Return the ``ctid compare --json`` list, best first."""
        return [item.to_dict() for item in self.candidates]


def information_criteria(result: Estimate) -> Dict[str, float]:
    """
    Return ``{'aic', 'bic', 'samples'}`` from the output-error cost of ``result``.

    ``N`` is the number of fitted samples (from the residual variance ``|e|^2 / (N - k)``),
    ``V = 2 cost / N``.
    """
    count = len(result.model.parameters)
    if result.noise_variance > 0.0:
        samples = 2.0 * result.cost / result.noise_variance + count
    else:
        samples = float('nan')
    if not (np.isfinite(samples) and samples > count and result.cost > 0.0):
        return {'aic': float('nan'), 'bic': float('nan'), 'samples': samples}
    loss = math.log(2.0 * result.cost / samples)
    return {'aic': samples * loss + 2.0 * count,
            'bic': samples * loss + count * math.log(samples), 'samples': samples}


def _models(models: Sequence[Union[Model, str]]) -> List[Model]:
    if isinstance(models, (str, Model)) or len(models) < 2:
        raise ConfigError('compare needs at least two candidate models')
    result = [item if isinstance(item, Model) else Model(item) for item in models]
    texts = [item.expression for item in result]
    repeated = sorted({text for text in texts if texts.count(text) > 1})
    if repeated:
        raise ConfigError(f'candidate models given twice: {", ".join(repeated)}')
    return result


def _split(data: Data, holdout: float) -> int:
    """Return the first held-out sample."""
    if not 0.0 < holdout < 1.0:
        raise ConfigError(f'holdout must be a fraction between 0 and 1, got {holdout!r}')
    count = len(data)
    cut = int(round(count * (1.0 - holdout)))
    if cut < _MIN_SAMPLES or count - cut < _MIN_SAMPLES:
        raise DataError(f'holding out the last {holdout:.0%} of {count} samples leaves {cut} '
                        f'to estimate on and {count - cut} to validate on; at least '
                        f'{_MIN_SAMPLES} each (give validation data, or a longer record)')
    return cut


def _hints(model: Model, fitted: Sequence[Candidate]) -> Union[str, Dict[str, float]]:
    """Return the values of the largest fitted candidate nested in ``model`` by name."""
    names = set(model.parameters)
    best = None
    for other in fitted:
        if other.estimate is None or other.parameters >= len(names):
            continue
        if set(other.model.parameters) <= names and (
                best is None or other.parameters > best.parameters):
            best = other
    return dict(best.estimate.params) if best is not None else 'auto'


def compare(models: Sequence[Union[Model, str]], data: Data, *,
            validation: Optional[Data] = None, holdout: float = HOLDOUT,
            initial: Optional[Mapping[str, Mapping[str, float]]] = None,
            **options) -> Comparison:
    """
    Fit candidate models on the same data and recommend the simplest adequate one.

    Parameters
    ----------
    models : sequence of Model or str
        At least two candidate structures (transfer functions or equations of the same
        signals).
    data : Data
        The record. Without ``validation`` its last ``holdout`` share is held out.
    validation : Data, optional
        Separate validation data; then all of ``data`` is fitted.
    holdout : float
        Share of ``data`` held out for validation when ``validation`` is None.
    initial : dict, optional
        ``{model expression: {name: value}}`` initial values of some candidates.
    **options
        Passed to :func:`~ctid_ros.estimation.estimate.estimate` for every candidate
        (``bounds`` only where it names parameters of the candidate).

    Returns
    -------
    Comparison
        The candidates ranked best first, exactly one recommended.

    Raises
    ------
    ConfigError
        For fewer than two models, a model given twice, a bad ``holdout``.
    DataError
        If a held-out split leaves too few samples.
    EstimationError
        If no candidate could be estimated.

    """
    candidates_models = _models(models)
    held_out = validation is None
    if held_out:
        cut = _split(data, holdout)
        estimation, scored = data.segment(0, cut), data.segment(cut, len(data))
    else:
        estimation, scored = data, validation
    bounds = options.pop('bounds', None) or {}
    order = sorted(range(len(candidates_models)),
                   key=lambda index: (len(candidates_models[index].parameters),
                                      candidates_models[index].den_degree, index))
    fitted: List[Candidate] = []
    for index in order:
        model = candidates_models[index]
        start = (initial or {}).get(model.expression) or _hints(model, fitted)
        own = {name: value for name, value in bounds.items() if name in model.parameters}
        candidate = Candidate(model, None)
        try:
            candidate.estimate = estimate(model, estimation, start, bounds=own or None,
                                          **options)
        except (EstimationError, DataError) as error:
            candidate.error = str(error)
        fitted.append(candidate)
    if all(item.estimate is None for item in fitted):
        raise EstimationError('no candidate model could be estimated: ' + '; '.join(
            f'{item.model.expression}: {item.error}' for item in fitted))
    comparison = Comparison(fitted, estimation, scored, held_out, data)
    for candidate in fitted:
        _score(candidate, comparison)
    _judge(fitted)
    comparison.candidates = _ranked(fitted)
    return comparison


def _score(candidate: Candidate, comparison: Comparison) -> None:
    """Fill in the validation fit, criteria, consistency and residual of a fitted candidate."""
    result = candidate.estimate
    if result is None:
        return
    try:
        simulated = comparison.simulated(candidate)
        candidate.fit = fit_percent(comparison.validation.y, simulated)
        candidate.validation_error = comparison.validation.y - simulated
    except CtidError as error:
        candidate.error = f'cannot simulate it on the validation data: {error}'
    criteria = information_criteria(result)
    candidate.aic, candidate.bic = criteria['aic'], criteria['bic']
    consistency = getattr(result, 'consistency', None)
    candidate.consistent = None if consistency is None else bool(consistency.consistent)
    candidate.residual = result.residuals.verdict if result.residuals is not None else ''


def _judge(candidates: List[Candidate]) -> None:
    """Find what makes each candidate inadequate, recommend one and say why."""
    fits = [item.fit for item in candidates if item.estimate is not None and np.isfinite(item.fit)]
    best_fit = max(fits) if fits else float('nan')
    for item in candidates:
        result = item.estimate
        if result is None:
            item.problems.append(f'the estimation failed: {item.error}')
            continue
        if not np.isfinite(item.fit):
            item.problems.append(item.error or 'no validation fit')
        elif item.fit < best_fit - FIT_TOLERANCE:
            item.problems.append(f'validation fit {item.fit:.1f} %, {best_fit - item.fit:.1f} '
                                 'points below the best')
        else:
            richer = _decisively_better(item, candidates)
            if richer is not None:
                item.problems.append(
                    f'{richer.model.expression} explains the validation data better (t '
                    f'{paired_improvement(item.validation_error, richer.validation_error):.1f}'
                    f', fit {richer.fit - item.fit:+.1f} points) with BIC '
                    f'{richer.bic - item.bic:+.0f}: this structure misses something')
        if item.consistent is False:
            consistency = result.consistency
            item.problems.append(f'{_INCONSISTENT} (max z {consistency.max_z:.1f} > '
                                 f'{getattr(consistency, "bound", float("nan")):.1f})')
        if result.residuals is not None and result.residuals.input_correlated:
            item.problems.append('residual correlated with the input (missing dynamics or a '
                                 'wrong dead time)')
        unidentified = [note for note in result.warnings
                        if any(words in note for words in _UNIDENTIFIED)]
        if unidentified:
            item.problems.append('not identifiable: ' + unidentified[0].split(':')[0])
        if not result.converged:
            item.problems.append('not converged')
    adequate = [item for item in candidates if item.adequate]
    if adequate:
        choice = min(adequate, key=lambda item: (item.parameters, _finite(item.bic)))
        checked = 'consistent over the record' if choice.consistent else \
            'consistency not checked'
        choice.why = (f'simplest adequate structure ({choice.parameters} parameters): '
                      f'validation fit {choice.fit:.1f} % (best {best_fit:.1f} %), residual '
                      f'independent of the input, {checked}, parameters determined')
    else:
        but_consistency = [item for item in candidates if item.estimate is not None and all(
            problem.startswith(_INCONSISTENT) for problem in item.problems)]
        if but_consistency:
            choice = min(but_consistency, key=lambda item: (item.parameters, _finite(item.bic)))
            choice.why = ('no candidate is adequate; the simplest adequate but for consistency '
                          f'(validation fit {choice.fit:.1f} %), and ' + '; '.join(choice.problems)
                          + ': the parameters may change over the record')
        else:
            choice = max((item for item in candidates if item.estimate is not None),
                         key=lambda item: _finite(item.fit, -np.inf))
            choice.why = ('no candidate is adequate; best validation fit, but '
                          + '; '.join(choice.problems))
    choice.recommended = True
    for item in candidates:
        if item is choice:
            continue
        if item.adequate:
            delta = item.bic - choice.bic
            item.why = (f'adequate too, but {item.parameters} parameters where '
                        f'{choice.model.expression} has {choice.parameters}'
                        + (f' (BIC {delta:+.1f})' if np.isfinite(delta) else ''))
        else:
            item.why = '; '.join(item.problems)


def _decisively_better(item: Candidate, candidates: Sequence[Candidate]
                       ) -> Optional[Candidate]:
    """Return the simplest candidate with more parameters that beats ``item`` decisively."""
    richer = [other for other in candidates
              if other.estimate is not None and other.parameters > item.parameters
              and np.isfinite(other.bic) and np.isfinite(item.bic)
              and other.bic < item.bic - BIC_MARGIN
              and paired_improvement(item.validation_error, other.validation_error)
              > SIGNIFICANT]
    return min(richer, key=lambda other: (other.parameters, -other.fit)) if richer else None


def paired_improvement(first: Optional[np.ndarray], second: Optional[np.ndarray],
                       batches: int = BATCHES) -> float:
    """
    Return the t statistic of ``second``'s squared errors being smaller than ``first``'s.

    The differences ``first_k^2 - second_k^2`` on the same samples are averaged over
    ``batches`` contiguous batches (batch means: errors correlated within a batch are not
    counted as independent); ``t = mean / (std / sqrt(batches))`` of the batch means. 0 when
    either is missing or too short, ``inf`` for a perfect and constant improvement.
    """
    if first is None or second is None or first.size != second.size or \
            first.size < 2 * batches:
        return 0.0
    difference = first ** 2 - second ** 2
    means = np.array([chunk.mean() for chunk in np.array_split(difference, batches)])
    spread = float(np.std(means, ddof=1))
    if spread == 0.0:
        return float('inf') if means.mean() > 0 else 0.0
    return float(means.mean() / (spread / math.sqrt(batches)))


def _finite(value: float, default: float = np.inf) -> float:
    return value if np.isfinite(value) else default


def _ranked(candidates: List[Candidate]) -> List[Candidate]:
    """Return the candidates best first (see :class:`Comparison`)."""
    def key(item: Candidate):
        if item.recommended:
            return (0, 0, 0.0)
        if item.adequate:
            return (1, item.parameters, _finite(item.bic))
        if item.estimate is not None:
            return (2, 0, -_finite(item.fit, -np.inf))
        return (3, 0, 0.0)

    return sorted(candidates, key=key)
