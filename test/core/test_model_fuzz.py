"""
Seeded fuzz test of model text (issue #16): hostile texts are answered, never hang or crash.

Every text of the corpus of ``test/model_texts.py`` goes to ``Model`` as a plant, as the
controller of a fixed plant and, once accepted as a plant, with a PI controller. Each call must
raise a :class:`ModelError` with a message, or give a model that is causal (proper, dead time
>= 0, and a pole if the dead time is estimated) and simulates to finite values where stable.
A watchdog fails a call that takes longer than :data:`WATCHDOG` seconds instead of letting the
run hang; the one-second bound of the issue is measured by ``bench/model_text.py`` over a
larger corpus.
"""

from contextlib import contextmanager
import signal

from ctid_ros import CtidError, Model, ModelError
from model_texts import CONTROLLER_PLANT, corpus, GENERATORS
import numpy as np
import pytest

SEED = 16
PER_KIND = 12
WATCHDOG = 10.0
CORPUS = corpus(SEED, PER_KIND * len(GENERATORS))
INPUT = np.where(np.sin(0.37 * np.arange(60)) >= 0.0, 1.0, -1.0)


@contextmanager
def watchdog(what: str):
    """Raise TimeoutError in the test if the block runs longer than WATCHDOG seconds."""
    def expired(signum, frame):
        raise TimeoutError(f'{what} took longer than {WATCHDOG} s')

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, WATCHDOG)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)


def answer(plant: str, controller=None):
    """Return the model of the text, or None when it is rejected with a message."""
    what = f'Model({plant[:80]!r}, controller={controller!r})'
    with watchdog(what):
        try:
            model = Model(plant, controller=controller)
        except ModelError as error:
            assert str(error).strip(), what
            return None
        check_valid(model, what)
    return model


def check_valid(model: Model, what: str) -> None:
    """Assert that an accepted model is causal and simulates to finite values where stable."""
    assert model.num_degree <= model.den_degree, what
    assert not (model.delay_is_estimated and model.den_degree == 0), what
    theta = {name: 1.0 + 0.25 * (index % 4) for index, name in enumerate(model.parameters)}
    u = np.column_stack([INPUT] * len(model.inputs))
    try:
        coefficients = model.coefficients(theta)
        y = model.simulate(theta, u, 0.05)
    except CtidError as error:       # e.g. a coefficient undefined at theta: said, not crashed
        assert str(error).strip(), what
        return
    assert coefficients.delay >= 0.0, what
    poles = np.roots(coefficients.den) if coefficients.den.size > 1 else np.zeros(0)
    if np.all(poles.real < 0.0):
        assert np.all(np.isfinite(y)), what


def test_corpus_is_seeded_and_has_every_kind():
    assert corpus(SEED, 50) == corpus(SEED, 50)
    assert corpus(SEED, 50) != corpus(SEED + 1, 50)
    assert {kind for kind, _ in CORPUS} == {name for name, _ in GENERATORS}


@pytest.mark.parametrize('kind', [name for name, _ in GENERATORS])
def test_every_hostile_text_is_answered(kind):
    texts = [text for name, text in CORPUS if name == kind]
    assert len(texts) == PER_KIND
    for text in texts:
        plant = answer(text)
        answer(CONTROLLER_PLANT, controller=text)
        if plant is not None and len(plant.inputs) == 1 and not plant.has_delay:
            answer(text, controller='20 + 10/s')


def test_the_corpus_reaches_both_answers():
    # A corpus that every text fails (or passes) the same way would test little.
    outcomes = [answer(text) is not None for _, text in CORPUS[:90]]
    assert 10 <= sum(outcomes) <= 80
