"""The engine shared by node and replay: windows in, published quantities out."""

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from ctid_ros.streaming.buffer import resample
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.session import IdentificationSession
import numpy as np
import pytest

TRUTH = {'K': 2.0, 'T': 1.5, 'tau': 0.237}


def plant_streams(seconds=40.0, ts=0.01, seed=0):
    """Input held between asynchronous stamps, output measured with noise and jitter."""
    rng = np.random.default_rng(seed)
    u = prbs(10, 20)[:int(seconds / ts)]
    y = Model('K*exp(-tau*s)/(T*s + 1)').simulate(TRUTH, u, ts)
    y = y + 0.02 * rng.standard_normal(y.size)
    stamps = (1_700_000_000 * 10 ** 9 + np.arange(u.size) * int(ts * 1e9)).astype(np.int64)
    jitter = rng.integers(0, 200_000, size=u.size)        # up to 0.2 ms late
    return stamps, u, stamps + jitter, y


def test_successive_windows_recover_the_parameters_in_published_order():
    config = IdentificationConfig(
        model='K*exp(-tau*s)/(T*s + 1)', parameter_names=('tau', 'K', 'T'),
        lower=(0.0, 0.01, 0.01), upper=(2.0, 100.0, 100.0), sample_time=0.01, window=15.0)
    session = IdentificationSession(config)
    u_stamps, u, y_stamps, y = plant_streams()
    updates = []
    for end in (20.0, 30.0, 39.0):
        end_ns = int(u_stamps[0] + end * 1e9)
        window, _ = resample(u_stamps, u, y_stamps, y, config.sample_time, length=config.window,
                             end_ns=end_ns, max_gap=config.max_gap,
                             reorder_horizon=config.reorder_horizon)
        updates.append(session.update(window))
    for update in updates:
        assert update.names == ('tau', 'K', 'T')
        assert update.values == pytest.approx([0.237, 2.0, 1.5], rel=0.03)
        assert np.all(update.stds > 0)
        assert update.prediction.size == update.prediction_times_ns.size
        assert update.diagnostics()['fit_percent'] > 90.0
        # The plant is the model: one parameter vector holds over each window.
        assert update.diagnostics()['consistent'] is True
        assert update.diagnostics()['consistency_max_z'] > 0.0
        # A linear plant: the residual does not depend on the signals' amplitude.
        assert update.diagnostics()['residual_amplitude_dependent'] is False
        summary = update.to_dict()
        assert summary['consistency']['consistent'] is True
        assert list(summary['params']) == ['tau', 'K', 'T']
    assert updates[1].result.iterations <= updates[0].result.iterations + 2   # warm start
    # Each warm start explains its window after a few iterations: no start search, no profile.
    assert [update.diagnostics()['start'] for update in updates] == ['search', 'initial',
                                                                     'initial']
    assert session.previous is not None
    session.reset()
    assert session.previous is None
