"""compare(): the simplest adequate structure on simulated plants with known truth, real data."""

from pathlib import Path

from ctid_ros.core.data import Data
from ctid_ros.core.excitation import prbs
from ctid_ros.core.model import Model
from ctid_ros.core.reference_systems import first_order_dead_time, two_lags_dead_time
from ctid_ros.errors import ConfigError, DataError
from ctid_ros.estimation.compare import compare, information_criteria, paired_improvement
from ctid_ros.files.csv_file import load_csv
import numpy as np
import pytest

FOPDT = 'K*exp(-tau*s)/(T*s + 1)'
SOPDT = 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'
DATA = Path(__file__).resolve().parents[1] / 'data'


def recommended(comparison):
    chosen = [item for item in comparison.candidates if item.recommended]
    assert len(chosen) == 1 and comparison.candidates[0] is chosen[0]
    return chosen[0]


@pytest.mark.parametrize('seed', [1, 2])
def test_an_adequate_fopdt_is_recommended_over_an_sopdt(seed):
    system = first_order_dead_time()
    comparison = compare([SOPDT, FOPDT], system.data(seed))
    best = recommended(comparison)
    assert best.model.expression == FOPDT and best.consistent is True
    assert best.estimate.params['tau'] == pytest.approx(1.234, abs=0.05)
    assert 'simplest adequate' in best.why
    other = comparison.candidates[1]
    # The SOPDT fits as well (it contains the FOPDT) but adds a parameter for nothing.
    assert abs(other.fit - best.fit) < 0.5 and other.bic > best.bic


def test_an_inconsistent_fopdt_loses_to_a_consistent_sopdt():
    # Well separated lags plus dead time; slow steps, then fast PRBS: the FOPDT that fits the
    # slow part is not the one that fits the fast part.
    truth = {'K': 1.5, 'T1': 3.0, 'T2': 0.3, 'tau': 0.3}
    u = np.concatenate([prbs(7, 40)[:6000], prbs(10, 4)[:6000]])
    clean = Model(SOPDT).simulate(truth, u, 0.05)
    noise = np.random.default_rng(0).standard_normal(u.size)
    data = Data(u, clean + 10 ** (-30 / 20) * np.std(clean) * noise, 0.05)
    comparison = compare([FOPDT, SOPDT], data)
    best = recommended(comparison)
    assert best.model.expression == SOPDT and best.consistent is True
    params = best.estimate.params
    for name in ('K', 'tau'):
        assert params[name] == pytest.approx(truth[name], rel=0.05), name
    # T1 and T2 are interchangeable (one model either way round): compare the sorted pair.
    assert sorted([params['T1'], params['T2']]) == pytest.approx([0.3, 3.0], rel=0.05)
    fopdt = comparison.candidates[1]
    assert fopdt.consistent is False
    assert any('not consistent over the record' in problem for problem in fopdt.problems)


def test_missing_lag_is_seen_in_the_residual_and_on_validation():
    comparison = compare([FOPDT, SOPDT], two_lags_dead_time().data(1))
    assert recommended(comparison).model.expression == SOPDT
    fopdt = comparison.candidates[1]
    assert 'residual correlated with the input' in fopdt.why


def test_real_dryer_prefers_two_lags_and_refuses_an_unidentifiable_zero():
    data = load_csv(DATA / 'dryer_daisy.csv').detrend('mean')
    lead = 'K*exp(-tau*s)*(b*s + 1)/((T1*s + 1)*(T2*s + 1))'
    comparison = compare([FOPDT, SOPDT, lead], data)
    assert recommended(comparison).model.expression == SOPDT
    by_model = {item.model.expression: item for item in comparison.candidates}
    assert any(problem.startswith('not identifiable') for problem in by_model[lead].problems)
    assert by_model[FOPDT].problems and by_model[FOPDT].fit < by_model[SOPDT].fit - 2.0
    listed = comparison.to_list()
    assert [item['recommended'] for item in listed] == [True, False, False]
    assert set(listed[0]) >= {'model', 'params', 'std', 'fit', 'consistent', 'recommended',
                              'why'}


def test_separate_validation_data():
    system = first_order_dead_time()
    comparison = compare([FOPDT, SOPDT], system.data(1), validation=system.data(2))
    assert not comparison.held_out and len(comparison.validation) == len(system.u)
    assert recommended(comparison).model.expression == FOPDT


def test_information_criteria_count_the_parameters():
    system = first_order_dead_time()
    comparison = compare([FOPDT, SOPDT], system.data(1))
    for item in comparison.candidates:
        criteria = information_criteria(item.estimate)
        assert criteria['samples'] == pytest.approx(len(comparison.estimation), abs=1)
        assert criteria['bic'] - criteria['aic'] == pytest.approx(
            item.parameters * (np.log(criteria['samples']) - 2.0))


def test_bad_requests():
    data = first_order_dead_time().data(1)
    with pytest.raises(ConfigError, match='at least two'):
        compare([FOPDT], data)
    with pytest.raises(ConfigError, match='twice'):
        compare([FOPDT, FOPDT], data)
    with pytest.raises(DataError, match='at least 50'):
        compare([FOPDT, SOPDT], data.segment(0, 100))
    with pytest.raises(ConfigError, match='holdout'):
        compare([FOPDT, SOPDT], data, holdout=1.5)


def test_a_time_varying_plant_gets_the_simplest_structure_with_a_warning():
    # The gain steps up 10 % halfway: no structure holds over the record.
    model = Model(FOPDT)
    u = prbs(9, 8)[:4000]
    before = model.simulate({'K': 2.0, 'T': 1.0, 'tau': 0.3}, u, 0.05)
    after = model.simulate({'K': 2.2, 'T': 1.0, 'tau': 0.3}, u, 0.05)
    clean = np.where(np.arange(u.size) < 2000, before, after)
    noise = np.random.default_rng(0).standard_normal(u.size)
    comparison = compare([SOPDT, FOPDT], Data(u, clean + 0.1 * np.std(clean) * noise, 0.05))
    best = recommended(comparison)
    assert best.model.expression == FOPDT and best.consistent is False
    assert best.why.startswith('no candidate is adequate; the simplest adequate but for '
                               'consistency') and 'may change over the record' in best.why


def test_paired_improvement_sees_a_small_certain_gain_and_no_gain():
    rng = np.random.default_rng(5)
    noise = rng.standard_normal(800)
    missing = 0.3 * np.sin(np.arange(800) / 7.0)
    assert paired_improvement(noise + missing, noise) > 5.0
    assert abs(paired_improvement(noise, rng.standard_normal(800))) < 3.0
    assert paired_improvement(None, noise) == 0.0
