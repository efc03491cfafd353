"""
Memory of a long live run: RSS of a 1 kHz streaming session, minute after minute.

The node's data path without DDS: every millisecond a std_msgs/Float64-like message on the
input topic and one on the output topic go through the node's
:class:`~ctid_ros.streaming.sampler.MessageSampler` into its
:class:`~ctid_ros.streaming.buffer.SampleBuffer`; every ``update_period`` an
:class:`~ctid_ros.streaming.session.IdentificationSession` estimates on the buffer's window and
the change alarm is fed, keeping only the last update, as the node does. The plant is the
first-order lag with dead time of ``bench/node_throughput.py`` (K=2, T=0.5 s, tau=0.137 s) under
a periodic PRBS, with 1 % output noise and 0.1 ms stamp jitter, so windows alternate between the
warm start and the automatic start search (the path whose cache used to keep every window).

``--realtime`` paces the messages by the wall clock (a 20-minute run takes 20 minutes; run it
with ``nice``); by default simulated time runs as fast as the estimates allow, which gives the
same messages, windows and estimates in the same order, only sooner. Once in the run, one
message carries a 1e7-element array (``--huge``), read by index as a field path reads it.

RSS is read from ``/proc/self/status`` after every simulated minute; the figure is the growth
from the end of the warm-up (default 2 minutes) to the end, and the largest excursion above
the warm-up value.

Run with ``.venv/bin/python -m bench memory`` or ``python -m bench.memory --minutes 20``.
"""

import argparse
import gc
import json
import time
from types import SimpleNamespace
from typing import Any, Dict, List, Optional

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from ctid_ros.errors import DataError, EstimationError
from ctid_ros.streaming.alarm import ChangeDetector
from ctid_ros.streaming.baseline import configured_baseline
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.sampler import MessageSampler
from ctid_ros.streaming.session import IdentificationSession
import numpy as np

__all__ = ['main', 'rss_mb', 'run']

RATE = 1000
TOPICS = ('/plant/u', '/plant/y')
MODEL = 'K*exp(-tau*s)/(T*s + 1)'
TRUTH = {'K': 2.0, 'T': 0.5, 'tau': 0.137}
# A PRBS of 2**9 - 1 bits of 20 ms: the input repeats every 10.22 s.
PRBS_ORDER, PRBS_CLOCK = 9, 20


def rss_mb() -> float:
    """Return the resident set size of this process in MiB (Linux)."""
    with open('/proc/self/status') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError('no VmRSS in /proc/self/status')


def _periodic_plant(seed: int) -> Dict[str, np.ndarray]:
    """One period of the input and of the plant's periodic steady-state output."""
    u = prbs(PRBS_ORDER, PRBS_CLOCK)
    # Two periods simulated: the second is the steady state, which repeats exactly.
    y = Model(MODEL).simulate(TRUTH, np.tile(u, 2), 1.0 / RATE)[u.size:]
    return {'u': u, 'y': y, 'noise': 0.01 * float(np.std(y)) *
            np.random.default_rng(seed).standard_normal(u.size)}


def run(minutes: float = 20.0, warm_up: float = 2.0, window: float = 10.0,
        update_period: float = 1.0, realtime: bool = False, huge: float = 0.5,
        seed: int = 0, log=print) -> Dict[str, Any]:
    """
    Stream ``minutes`` of 1 kHz messages through the node's data path; return the figures.

    Parameters
    ----------
    minutes, warm_up : float
        Simulated run length and the warm-up after which RSS is the reference, in minutes.
    window, update_period : float
        The node's window and update period in seconds.
    realtime : bool
        Pace the messages by the wall clock.
    huge : float
        Fraction of the run after which one message carries a 1e7-element array (negative:
        none).
    seed : int
        Seed of the noise and the stamp jitter.
    log : callable
        Called with one line per simulated minute.

    """
    plant = _periodic_plant(seed)
    period = plant['u'].size
    config = IdentificationConfig(
        model=MODEL, input_topic=TOPICS[0], output_topic=TOPICS[1], input_field='data[0]',
        sample_time=1.0 / RATE,
        window=window, update_period=update_period, parameter_names=['K', 'T', 'tau'],
        lower=[0.001, 0.01, 0.0], upper=[100.0, 100.0, 1.0], delay_min=0.0, delay_max=1.0)
    sampler = MessageSampler(config, TOPICS)
    buffer = sampler.buffer(config.buffer_capacity(RATE), config)
    session = IdentificationSession(config)
    detector = ChangeDetector.from_config(config, configured_baseline(config)[0])
    rng = np.random.default_rng(seed + 1)
    total = round(minutes * 60 * RATE)
    step_ns = 10 ** 9 // RATE
    per_update = round(update_period * RATE)
    huge_at = round(huge * total) if huge >= 0 else -1
    samples: List[Dict[str, float]] = []
    reference: Optional[float] = None
    huge_rss = before_huge = None
    last_update = None
    estimates = failures = 0
    compute = 0.0
    started = time.monotonic()
    for k in range(total):
        stamp = k * step_ns + int(rng.integers(-100_000, 100_000))
        phase = k % period
        u_msg = SimpleNamespace(data=[float(plant['u'][phase])])
        y_msg = SimpleNamespace(data=float(plant['y'][phase] + plant['noise'][phase]))
        if k == huge_at:
            # One message with a 1e7-element array of distinct floats (as a decoder gives).
            gc.collect()
            before_huge = rss_mb()
            u_msg = SimpleNamespace(data=np.full(10_000_000, float(plant['u'][phase])).tolist())
        sampler(TOPICS[0], stamp, u_msg).add_to(buffer)
        sampler(TOPICS[1], stamp + 200_000, y_msg).add_to(buffer)
        del u_msg, y_msg
        if k == huge_at:
            gc.collect()
            huge_rss = (before_huge, rss_mb())
            log(f'1e7-element message: RSS {huge_rss[0]:.1f} -> {huge_rss[1]:.1f} MiB')
        if realtime:
            delay = started + (k + 1) / RATE - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        if (k + 1) % per_update == 0:
            begun = time.perf_counter()
            try:
                last_update = session.update(session.take_window(buffer))
                detector.update(last_update)
                estimates += 1
            except (DataError, EstimationError):
                failures += 1
            compute += time.perf_counter() - begun
        if (k + 1) % (60 * RATE) == 0:
            minute = (k + 1) / (60.0 * RATE)
            gc.collect()
            rss = rss_mb()
            if reference is None and minute >= warm_up:
                reference = rss
            samples.append({'minute': minute, 'rss_mb': rss})
            values = '' if last_update is None else ', '.join(
                f'{name}={value:.4g}'
                for name, value in zip(last_update.names, last_update.values))
            log(f'minute {minute:5.1f}: RSS {rss:7.1f} MiB, {estimates} estimates '
                f'({failures} failed), {compute / max(estimates, 1):.3f} s each; {values}')
    stats = buffer.stats()
    after = [sample['rss_mb'] for sample in samples if sample['minute'] >= warm_up]
    return {
        'minutes': minutes, 'realtime': realtime, 'rate_hz': RATE, 'window_s': window,
        'update_period_s': update_period, 'estimates': estimates, 'failures': failures,
        'wall_s': time.monotonic() - started, 'rss': samples,
        'rss_after_warm_up_mb': reference,
        'rss_end_mb': samples[-1]['rss_mb'] if samples else None,
        'growth_mb': (after[-1] - after[0]) if after else None,
        'excursion_mb': (max(after) - after[0]) if after else None,
        'huge_message_rss_mb': huge_rss,
        'evicted': [stats.u.evicted, stats.y.evicted],
        'received': [stats.u.received, stats.y.received],
    }


def main(argv: Optional[List[str]] = None) -> Dict[str, Any]:
    """Run from the command line; print the figures and optionally write them as JSON."""
    parser = argparse.ArgumentParser(prog='python -m bench.memory',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--minutes', type=float, default=20.0)
    parser.add_argument('--warm-up', type=float, default=2.0)
    parser.add_argument('--window', type=float, default=10.0)
    parser.add_argument('--update-period', type=float, default=1.0)
    parser.add_argument('--realtime', action='store_true')
    parser.add_argument('--huge', type=float, default=0.5)
    parser.add_argument('--json', help='write the figures to this file')
    arguments = parser.parse_args(argv)
    figures = run(arguments.minutes, arguments.warm_up, arguments.window,
                  arguments.update_period, arguments.realtime, arguments.huge)
    print(f"RSS after {arguments.warm_up:g} min warm-up {figures['rss_after_warm_up_mb']:.1f} MiB,"
          f" at the end {figures['rss_end_mb']:.1f} MiB: growth {figures['growth_mb']:+.1f} MiB,"
          f" largest excursion {figures['excursion_mb']:+.1f} MiB over "
          f"{figures['estimates']} estimates in {figures['wall_s']:.0f} s "
          f"({'real time' if figures['realtime'] else 'compressed time'}); evicted "
          f"{figures['evicted']} of {figures['received']} samples")
    if arguments.json:
        with open(arguments.json, 'w') as stream:
            json.dump(figures, stream, indent=2)
    return figures


if __name__ == '__main__':
    main()
