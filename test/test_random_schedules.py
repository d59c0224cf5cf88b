"""research/analysis/random_schedules.py and the adaptation report's lag (issue #47)."""

from itertools import pairwise
import json
import math
from pathlib import Path
import sys

import numpy as np
import pytest

from zeus_ros.learning_tools.adaptation import steps_to_within, WITHIN_HELD

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'research' / 'analysis'))
import random_schedules as rs  # noqa: E402 (its folder goes on the path first)

LIVE = (0.01, 8.0)          # cheetah-run-wide-friction's live range
TRAIN_SPAN = (0.05, 4.5)    # and the span of its train values
PILOTS = REPO / 'research' / 'results' / 'pilots_36'


# -- the lag -----------------------------------------------------------------------
def test_the_lag_counts_from_the_swap_until_the_estimate_holds_within_20_percent():
    # 1.0 until step 100, then the estimate falls 1.0 -> 0.1 in log space over
    # 30 steps; within 20 % of 0.1 (<= 0.12) from the 1st step with ln <= ln 0.12.
    ramp = np.exp(np.linspace(0.0, math.log(0.1), 31))
    est = np.concatenate([np.ones(100), ramp, np.full(69, 0.1)])
    first = int(np.flatnonzero(ramp <= 0.12)[0])
    assert 0 < first < 30
    assert steps_to_within(est, 100, 0.1) == first
    # one step inside the band and out again (an overshoot through it) is not arrival
    blip = est.copy()
    blip[105] = 0.1
    assert steps_to_within(blip, 100, 0.1) == first
    # the estimate already within at the swap step: lag 0; 20 % above still within
    assert steps_to_within(np.full(50, 0.119), 10, 0.1) == 0


def test_a_lag_never_within_the_segment_is_censored_not_a_number():
    est = np.concatenate([np.ones(100), np.full(100, 0.13)])   # 30 % above 0.1, forever
    assert steps_to_within(est, 100, 0.1) is None
    # within only for the segment's last WITHIN_HELD - 1 steps: censored too
    late = np.concatenate([np.ones(100), np.full(50, 0.5), np.full(WITHIN_HELD - 1, 0.1)])
    assert steps_to_within(late, 100, 0.1, end=len(late)) is None
    # the next segment's steps do not count: `end` cuts them off
    ok_later = np.concatenate([late, np.full(20, 0.1)])
    assert steps_to_within(ok_later, 100, 0.1) == 50
    assert steps_to_within(ok_later, 100, 0.1, end=len(late)) is None


def test_the_lag_of_non_positive_values_or_estimates():
    assert steps_to_within(np.zeros(20), 5, 0.0) is None       # no log space at a true 0
    assert steps_to_within(np.full(20, -1.0), 5, 1.0) is None  # an estimate <= 0: never within


# -- schedules and regions -----------------------------------------------------------
def test_a_schedule_is_the_same_for_a_seed_and_another_for_another_seed():
    assert rs.draw_schedule(LIVE, 1000, 3) == rs.draw_schedule(LIVE, 1000, 3)
    assert rs.draw_schedule(LIVE, 1000, 3) != rs.draw_schedule(LIVE, 1000, 4)


def test_schedules_keep_their_count_segments_range_and_ratio():
    counts = set()
    for seed in range(300):
        schedule = rs.draw_schedule(LIVE, 1000, seed, swaps=(3, 5), min_segment=60)
        steps, values = list(schedule), list(schedule.values())
        assert steps[0] == 0 and steps == sorted(steps)
        counts.add(len(steps) - 1)
        assert min(np.diff([*steps, 1000])) >= 60
        assert all(LIVE[0] <= v <= LIVE[1] for v in values)
        assert all(abs(math.log(b / a)) >= math.log(1.5) - 1e-12
                   for a, b in pairwise(values))
    assert counts == {3, 4, 5}
    with pytest.raises(ValueError):
        rs.draw_schedule(LIVE, 200, 0, swaps=(3, 5), min_segment=60)   # 6 x 60 > 200


def test_schedule_values_are_log_uniform_over_the_live_range():
    values = [v for seed in range(400) for v in rs.draw_schedule(LIVE, 1000, seed).values()]
    position = (np.log(values) - math.log(LIVE[0])) / (math.log(LIVE[1]) - math.log(LIVE[0]))
    share = np.histogram(position, bins=4, range=(0, 1))[0] / len(values)
    # uniform in log space: a quarter per quarter (the 1.5x rule thins the ends a little)
    assert np.all(np.abs(share - 0.25) < 0.05), share
    # a linear-uniform draw would put 3/4 of the values in the top quarter of the logs
    assert np.median(values) < 0.5


def test_regions_are_thirds_of_the_train_span_in_log_space():
    low, high = TRAIN_SPAN
    third = (high / low) ** (1 / 3)        # 0.05 -> 0.224 -> 1.0 -> 4.5
    assert [rs.region(v, TRAIN_SPAN) for v in
            (0.01, low, low * third * 0.99, low * third * 1.01, 0.99, 1.01, high, 6.0)] == [
        'below train', 'low', 'low', 'mid', 'mid', 'high', 'high', 'above train']


def test_the_gap_share_is_zero_at_sac_one_at_the_oracle_and_none_without_them():
    assert rs.gap_share(100.0, 100.0, 300.0) == 0.0
    assert rs.gap_share(300.0, 100.0, 300.0) == 1.0
    assert rs.gap_share(150.0, 100.0, 300.0) == pytest.approx(0.25)
    assert rs.gap_share(50.0, 100.0, 300.0) == pytest.approx(-0.25)
    assert rs.gap_share(150.0, None, 300.0) is None
    assert rs.gap_share(150.0, 100.0, 100.0) is None


def test_swap_figures_on_a_synthetic_episode():
    # 1.0 for 100 steps, then a swap down to 0.1 the estimate reaches after 10 steps
    est = np.concatenate([np.ones(110), np.full(90, 0.1)])
    swap = rs.swap_figures(est, 0.001, 100, 200, 1.0, 0.1, TRAIN_SPAN)
    assert (swap.direction, swap.region, swap.inside_train) == ('down', 'low', True)
    assert swap.lag == 10 and swap.covered_70_in_20
    late = rs.swap_figures(np.concatenate([np.ones(130), np.full(70, 0.1)]), 0.001, 100, 200,
                           1.0, 0.1, TRAIN_SPAN)
    assert late.lag == 30 and not late.covered_70_in_20
    up = rs.swap_figures(np.ones(200), 0.001, 100, 200, 1.0, 6.0, TRAIN_SPAN)
    assert (up.direction, up.region, up.inside_train, up.lag) == ('up', 'above train', False,
                                                                  None)


def test_the_median_lag_sorts_censored_swaps_last():
    assert rs.median_lag([3, 5, 40]) == '5'
    assert rs.median_lag([3, 5, None, None]) == 'never'
    assert rs.median_lag([3, 5, 7, None]) == '6'
    assert rs.median_lag([]) == '-'


# -- end to end ----------------------------------------------------------------------
def test_the_script_writes_finite_tables_for_real_checkpoints(tmp_path):
    runs = [PILOTS / f'cw-{m}-s1' / 'checkpoint' for m in ('sac', 'oracle', 'rma-raw-k10-swap')]
    out = tmp_path / 'cw.md'
    assert rs.main(['--runs', *map(str, runs), '--episodes', '1', '--steps', '300',
                    '--swaps-min', '2', '--swaps-max', '3', '--out', str(out)]) == 0
    text = out.read_text()
    assert text.startswith('`PYTHONPATH=. OMP_NUM_THREADS=1 python '
                           'research/analysis/random_schedules.py --runs')
    for head in ('| method | runs | return | share of the sac-oracle gap',
                 '| method | direction | region | swaps | median lag',
                 '| method | below train | low | mid | high | above train |',
                 '| method | up: covered / swaps'):
        assert head in text
    returns = text.split('| method | runs | return')[1].split('\n\n')[0]
    rows = {line.split(' | ')[0].strip('| '): line for line in returns.splitlines()[2:]}
    assert rows.keys() == {'oracle (swaps in training)', 'sac (swaps in training)',
                           'rma (k=10, swaps in training, raw extrinsics)'}
    assert '| 100% | 1.00 | 1.00 | 0.00 | 0.00 |' in rows['oracle (swaps in training)']
    assert '| 0% | - | - | - |' in rows['sac (swaps in training)']
    figures = json.loads(out.with_suffix('.json').read_text())['runs']
    rma = figures[2]
    assert len(rma['swaps']) in (2, 3) and len(rma['segments']) == len(rma['swaps']) + 1
    assert all(math.isfinite(x) for x in [*rma['returns'], rma['r2_log']]
               + [s['error_all'] for s in rma['segments']])
    assert all(s['lag'] == 0 for s in figures[1]['swaps'])   # the oracle reads the truth
    # sac has segments (their rewards) but no estimate, so no swaps to time
    assert figures[0]['swaps'] == [] and len(figures[0]['segments']) == len(rma['segments'])
    assert all(math.isfinite(s['reward']) and s['error_all'] is None
               for s in figures[0]['segments'])
