"""
The `make demo` scenario on real DDS: live identification, recording, replay.

The shortened demo (8 s, the payload picked up at 4 s, 2 s windows every 1.5 s) runs plant and
node on real DDS, and its recording is checked sample by sample against the ROS-free simulation
of the same plant (whose digital PI loop test/core/test_plant.py checks by hand).
"""

from dataclasses import replace
import re

from ctid_ros.core.plant import excitation, PlantSimulator
from ctid_ros.demo.wheel import copy_to_docs, main, PLANT_CONFIG, Scenario
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.streaming.params_file import find_config
import numpy as np
import pytest
import yaml


def _simulate(scenario: Scenario, samples: int) -> np.ndarray:
    """Return ``(r, u, y)`` of the scenario's plant, simulated without ROS."""
    settings = yaml.safe_load(scenario.params_file.read_text())['ctid_plant']['ros__parameters']
    simulator = PlantSimulator(scenario.model, scenario.before, scenario.sample_time,
                               pi_gains=scenario.pi_gains, noise_std=scenario.noise_std,
                               seed=settings['seed'])
    references = excitation(settings['prbs_bits'], settings['prbs_clock'],
                            settings['amplitude'], settings['offset'])
    rows = []
    for k in range(samples):
        if k == round(scenario.drift_time / scenario.sample_time):
            simulator.retune(scenario.after)
        r = next(references)
        rows.append((r, *simulator.step(r)))
    return np.array(rows)


@pytest.mark.ros
def test_shortened_demo_records_replays_and_recovers_the_drift(tmp_path, capsys):
    node_file = tmp_path / 'node.yaml'
    node_file.write_text(find_config('wheel_demo').read_text()
                         .replace('window: 4.0', 'window: 2.0')
                         .replace('update_period: 2.0', 'update_period: 1.5'))
    output = tmp_path / 'out'
    assert main(['--output', str(output), '--duration', '8', '--params-file',
                 str(node_file)]) == 0
    printed = capsys.readouterr().out
    # How many estimates the live node gets out in 8 s depends on the machine's load.
    table = printed[printed.index('live estimates'):printed.index('recorded 800 samples')]
    assert re.search(r'^ +\d+\.\d\d +0\.0\d+ ± ', table, re.MULTILINE), table
    assert 'before the payload' in printed and 'after the payload' in printed
    # The change alarm against the data-sheet baseline: nothing before the payload (this short
    # run may end before two whole windows after it have confirmed it).
    assert '  live node: 0 alarm(s) before the payload' in printed
    assert '  ctid replay: 0 alarm(s) before the payload' in printed

    # The recording: every sample of the loop, exactly as simulated without ROS.
    scenario = Scenario.load(find_config(PLANT_CONFIG))
    scenario = replace(scenario, drift_time=4.0)
    with BagReader(output / 'wheel.mcap') as bag:
        assert set(bag.topics()) == {'/wheel/r', '/wheel/u', '/wheel/y', '/ctid_node/estimate',
                                     '/ctid_node/estimate_std', '/diagnostics',
                                     '/ctid_node/alarm'}
        assert {topic: bag.message_count(topic) for topic in scenario.topics.values()} == \
            dict.fromkeys(scenario.topics.values(), 800)
        signals = {}
        for topic, _, msg in bag.messages(list(scenario.topics.values())):
            stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
            signals.setdefault(topic, []).append((stamp, msg.point.x))
        assert bag.message_count('/ctid_node/estimate') >= 1
    expected = _simulate(scenario, 800)
    for column, role in enumerate('ruy'):
        stamps, values = zip(*sorted(signals[scenario.topics[role]]))
        assert np.all(np.diff(stamps) == 10_000_000) and stamps[0] % 10_000_000 == 0, role
        np.testing.assert_allclose(values, expected[:, column], rtol=0, atol=1e-12,
                                   err_msg=role)

    # The replay: estimates on both sides of the drift; the figures.
    report = (output / 'replay.txt').read_text()
    assert report.startswith('ctid replay ') and 'samples used of 800' in report
    summary = printed[printed.index('before the payload'):]
    before, after = summary.split('after the payload')
    for block, truth in ((before, scenario.before), (after, scenario.after)):
        for name, tolerance in (('J', 0.03), ('b', 0.03), ('tau', 0.06)):
            line = next(line.split() for line in block.splitlines()
                        if line.split()[:1] == [name])
            assert float(line[1]) == truth[name]
            assert float(line[2]) == pytest.approx(truth[name], rel=tolerance), (name, block)
    copied = copy_to_docs(output, tmp_path / 'docs')
    assert [path.name for path in copied] == ['demo_fit.png', 'demo_parameters.png',
                                              'demo_bode.png']
    for path in copied:
        assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
