"""
A dropped input message costs one sample's information, never bias (issue 25 item 6).

A first-order lag with dead time (K=2, T=0.5 s, tau=0.137 s) under a square-wave command at
100 Hz, 1 % output noise (seeded). The command's message at a step is dropped: the buffer
cannot know whether the step was at that instant or the next, and its midpoint guess biased
the dead time by about 5 standard deviations. The session now estimates that value within its
bounds together with the parameters (:func:`refine_lost_inputs`). "Before" is the same
pipeline with that step turned off.
"""

from types import SimpleNamespace

from ctid_ros import EstimationError, Model
from ctid_ros.streaming import session as session_module
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.replay import replay_messages
import numpy as np
import pytest

T0_NS = 1_700_000_000_000_000_000
STEP_NS = 10_000_000
MODEL = 'K*exp(-tau*s)/(T*s + 1)'
TRUTH = np.array([2.0, 0.5, 0.137])


def recording(count, half_period, seed=0):
    u = ((np.arange(count) // half_period) % 2).astype(float)
    y = Model(MODEL).simulate(dict(zip(('K', 'T', 'tau'), TRUTH)), u, 0.01)
    y = y + 0.01 * np.std(y) * np.random.default_rng(seed).standard_normal(count)
    return u, y, np.flatnonzero(np.diff(u)) + 1


def messages(u, y, drop=()):
    """Input and output messages of each instant, stamped alike; the ``drop`` inputs lost."""
    for k, (u_k, y_k) in enumerate(zip(u, y)):
        if k not in drop:
            yield '/plant/u', T0_NS + k * STEP_NS, SimpleNamespace(data=float(u_k))
        yield '/plant/y', T0_NS + k * STEP_NS, SimpleNamespace(data=float(y_k))


def config(**options):
    return IdentificationConfig(model=MODEL, input_topic='/plant/u', output_topic='/plant/y',
                                parameter_names=['K', 'T', 'tau'], lower=[0.01, 0.01, 0.0],
                                upper=[100.0, 100.0, 2.0], delay_min=0.0, delay_max=1.0,
                                **options)


def without_refinement(monkeypatch):
    monkeypatch.setattr(session_module, 'refine_lost_inputs', lambda *arguments: None)


def test_a_message_dropped_at_a_step_no_longer_biases_the_estimate(monkeypatch):
    u, y, steps = recording(2000, 500)
    step = int(steps[0])
    whole = replay_messages(messages(u, y), config()).updates[0]
    # The message of the step's first instant lost: the input changed there (value 1).
    after = replay_messages(messages(u, y, (step,)), config()).updates[0]
    assert after.window.missing == (1, 0)
    assert after.window.data.u[step] == pytest.approx(1.0, abs=0.05)
    shift = np.abs(after.values - whole.values) / after.stds
    assert np.all(shift < 1.0), shift
    # The noise puts K 2.3 standard deviations off with or without the drop; the dead time,
    # which the drop biased, is within two.
    assert np.all(np.abs(after.values - TRUTH) < 3.0 * after.stds), (after.values, after.stds)
    assert abs(after.values[2] - TRUTH[2]) < 2.0 * after.stds[2]
    # The value of that instant was fitted: the standard deviations grow a little for it.
    assert np.all(after.stds >= whole.stds) and np.all(after.stds < 1.3 * whole.stds)
    # The message before the step lost: there the input had not changed yet (value 0).
    early = replay_messages(messages(u, y, (step - 1,)), config()).updates[0]
    assert early.window.data.u[step - 1] == pytest.approx(0.0, abs=0.05)
    assert np.all(np.abs(early.values - whole.values) < whole.stds)
    # Before: the midpoint moved the dead time by more than three standard deviations.
    without_refinement(monkeypatch)
    before = replay_messages(messages(u, y, (step,)), config()).updates[0]
    assert before.window.data.u[step] == 0.5
    noise_only = before.result.std_noise['tau']
    assert abs(before.values[2] - TRUTH[2]) > 3.0 * noise_only
    assert abs(before.values[2] - whole.values[2]) > 3.0 * whole.stds[2]
    # The consistency check sees the one wrong input: the quarters disagree, and the std
    # reported then covers their scatter instead of the noise alone.
    assert not before.result.consistency.consistent
    assert before.stds[2] > 3.0 * noise_only


def test_three_single_drops_in_a_sliding_replay_cost_no_window_and_no_bias(monkeypatch):
    u, y, steps = recording(4000, 300)
    drops = (int(steps[2]), int(steps[6]), int(steps[10]))
    settings = config(window=10.0, update_period=2.0)
    whole = replay_messages(messages(u, y), settings, sliding=True)
    dropped = replay_messages(messages(u, y, drops), settings, sliding=True)
    assert [update.end_ns for update in dropped.updates] == [
        update.end_ns for update in whole.updates]
    assert len(dropped.updates) == 17

    def worst(replay):
        shifts = [np.abs(update.values - reference.values) / update.stds
                  for update, reference in zip(replay.updates, whole.updates)]
        ratios = [update.stds / reference.stds
                  for update, reference in zip(replay.updates, whole.updates)]
        return float(np.max(shifts)), float(np.max(ratios))

    shift, ratio = worst(dropped)
    assert shift < 2.0 and ratio < 1.3, (shift, ratio)
    without_refinement(monkeypatch)
    shift, _ = worst(replay_messages(messages(u, y, drops), settings, sliding=True))
    assert shift > 3.0


def test_too_many_lost_changes_are_left_at_the_midpoint_with_a_warning(monkeypatch):
    monkeypatch.setattr(session_module, 'MAX_UNCERTAIN_INPUTS', 2)
    u, y, steps = recording(2000, 500)
    drops = tuple(int(step) for step in steps[:3])
    update = replay_messages(messages(u, y, drops), config()).updates[0]
    assert list(update.window.data.u[list(drops)]) == [0.5, 0.5, 0.5]
    assert any('3 input instants lost their messages while the input changed, more than the '
               '2 estimated' in note for note in update.warnings), update.warnings


def test_a_failed_refit_keeps_the_first_estimate(monkeypatch):
    u, y, steps = recording(2000, 500)
    step = int(steps[0])
    calls = []
    real = session_module.estimate

    def failing_refit(*arguments, **options):
        calls.append(options.get('initial'))
        if len(calls) > 1:
            raise EstimationError('refit failed')
        return real(*arguments, **options)

    monkeypatch.setattr(session_module, 'estimate', failing_refit)
    update = replay_messages(messages(u, y, (step,)), config()).updates[0]
    assert len(calls) == 2 and calls[1] is not None
    # The first estimate and the window it was made on.
    assert update.window.data.u[step] == 0.5
    assert update.values == pytest.approx(TRUTH, rel=0.05)
