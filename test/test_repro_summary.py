"""research/analysis/summarize_runs.py: adaptation tables over seeds, from committed reports."""

import json
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
ANALYSIS = REPO / 'research' / 'analysis'
SUMMARIZE = ANALYSIS / 'summarize_runs.py'


def _report(folder: Path, train: float, interp: float, r2: float | None,
            success: float | None = None) -> None:
    folder.mkdir(parents=True)
    report = {'returns': [{'split': 'train', 'mean': train, 'success_rate': success},
                          {'split': 'interpolation', 'mean': interp, 'success_rate': success}],
              'identification': None if r2 is None else {'r2_per_step': r2},
              'context_use': None}
    (folder / 'adaptation.json').write_text(json.dumps(report))


@pytest.mark.ros   # starts the summary script: a process, not a unit test
def test_groups_seeds_and_gives_mean_and_standard_error(tmp_path):
    _report(tmp_path / 'cv1-zeus-s1', -500.0, -600.0, 0.9)
    _report(tmp_path / 'cv1-zeus-s2', -700.0, -800.0, 0.7)
    _report(tmp_path / 'cv1-sac-s1', -900.0, -850.0, None)
    (tmp_path / 'cv1-zeus-s3').mkdir()          # trained, not yet reported
    out = subprocess.run([sys.executable, str(SUMMARIZE),
                          str(tmp_path)], check=True, capture_output=True, text=True,
                         env=os.environ | {'PYTHONPATH': str(REPO)}).stdout
    rows = {line.split(' | ')[0].strip('| '): line for line in out.splitlines()
            if line.startswith('| cv1')}
    # Two seeds: mean -700, standard error sqrt(((100^2) * 2 / 1) / 2) = 100.
    assert '| 1, 2 | -600 +- 100 | -700 +- 100 | - |' in rows['cv1-zeus']
    assert '0.80 +- 0.10' in rows['cv1-zeus']
    assert rows['cv1-sac'].endswith('| -900 | -850 | - | - | - | - |')
    assert 'no adaptation report yet: cv1-zeus-s3' in out



def _summary(folder: Path) -> str:
    return subprocess.run([sys.executable, str(SUMMARIZE),
                           str(folder)], check=True, capture_output=True, text=True,
                          env=os.environ | {'PYTHONPATH': str(REPO)}).stdout


@pytest.mark.ros   # starts the summary script: a process, not a unit test
def test_success_rates_get_columns_only_where_the_task_has_them(tmp_path):
    _report(tmp_path / 'cheetah' / 'cv0-sac-s1', 400.0, 410.0, None)
    assert 'success' not in _summary(tmp_path / 'cheetah')
    _report(tmp_path / 'sawyer' / 'sawyer-zeus-s1', 40.0, 45.0, 0.8, success=0.5)
    _report(tmp_path / 'sawyer' / 'sawyer-zeus-s2', 50.0, 55.0, 0.6, success=0.7)
    out = _summary(tmp_path / 'sawyer')
    assert 'success, train | success, interpolation |' in out
    assert out.splitlines()[2].endswith('| 0.60 +- 0.10 | 0.60 +- 0.10 |')


@pytest.mark.ros   # starts the summary script: a process, not a unit test
def test_context_use_at_the_train_values_gets_a_column_where_reports_measured_it(tmp_path):
    _report(tmp_path / 'old' / 'cs-oracle-s1', 300.0, 350.0, 1.0)
    assert 'at the train values' not in _summary(tmp_path / 'old')
    for seed, gap in ((1, 60.0), (2, 80.0)):
        folder = tmp_path / 'new' / f'cs-oracle-s{seed}'
        _report(folder, 300.0, 350.0, 1.0)
        report = json.loads((folder / 'adaptation.json').read_text())
        report['context_use'] = {'largest_gap': 5.0}
        report['context_use_train'] = {'largest_gap': gap}
        (folder / 'adaptation.json').write_text(json.dumps(report))
    out = _summary(tmp_path / 'new')
    assert 'the same at the train values |' in out
    assert out.splitlines()[2].endswith('| 5 +- 0 | 70 +- 10 |')


@pytest.mark.ros   # starts the summary script: a process, not a unit test
def test_live_swaps_count_as_covered_only_within_twenty_steps(tmp_path):
    swaps_per_seed = {1: [5, 20, 21, None], 2: [3, 4, 30, 40]}   # 2 of 4, then 2 of 4 covered
    for seed, steps in swaps_per_seed.items():
        folder = tmp_path / 'with' / f'cv0-zeus-s{seed}'
        _report(folder, 500.0, 510.0, 0.7)
        report = json.loads((folder / 'adaptation.json').read_text())
        report['swaps'] = [{'from_value': 0.6, 'to_value': 1.5, 'steps_to_70pct': n}
                           for n in steps]
        (folder / 'adaptation.json').write_text(json.dumps(report))
    _report(tmp_path / 'with' / 'cv0-sac-s1', 400.0, 410.0, None)   # no latent: no swaps
    lines = _summary(tmp_path / 'with').splitlines()
    assert 'live swaps 70 % covered within 20 steps' in lines[0]
    rows = {line.split(' | ')[0].strip('| '): line for line in lines[2:]}
    assert '| 0.70 +- 0.00 | 0.50 +- 0.00 | - |' in rows['cv0-zeus']
    assert rows['cv0-sac'].endswith('| - | - | - |')
    _report(tmp_path / 'without' / 'cv0-sac-s1', 400.0, 410.0, None)
    assert 'live swaps' not in _summary(tmp_path / 'without')


def _eval_log(folder: Path, returns: list[float]) -> None:
    """Write an eval_log.csv with one train value, evaluated at 1000, 2000, ... timesteps."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = ['timestep,env_steps,wall_s,split,value,return']
    rows += [f'{1000 * (i + 1)},{8000 * (i + 1)},1.0,train,1.0,{r}' for i, r in enumerate(returns)]
    (folder / 'eval_log.csv').write_text('\n'.join(rows) + '\n')


@pytest.mark.ros   # starts the summary script: a process, not a unit test
def test_learning_curves_average_the_seeds_of_a_group_over_their_common_steps(tmp_path):
    from zeus_ros.learning_tools.sweep_results import mean_curve, read_curve
    _eval_log(tmp_path / 'cv0-zeus-s1', [10.0, 30.0, 50.0])
    _eval_log(tmp_path / 'cv0-zeus-s2', [20.0, 50.0])          # still training
    runs = {s: read_curve(tmp_path / f'cv0-zeus-s{s}' / 'eval_log.csv') for s in (1, 2)}
    steps, mean, sem, seeds = mean_curve(runs, 'train')
    assert list(steps) == [8000, 16000] and seeds == 2
    np.testing.assert_allclose(mean, [15.0, 40.0])
    np.testing.assert_allclose(sem, [5.0, 10.0])
    assert mean_curve(runs, 'extrapolation') is None
    png = tmp_path / 'curves.png'
    subprocess.run([sys.executable, str(SUMMARIZE), str(tmp_path),
                    '--curves', str(png)], check=True, capture_output=True,
                   env=os.environ | {'PYTHONPATH': str(REPO)})
    assert png.stat().st_size > 1000


def test_window_tradeoff_tabulates_each_window_over_runs():
    sys.path.insert(0, str(ANALYSIS))
    from window_tradeoff import figures, markdown

    def report(k, r2, steps):
        return {'method': 'zeus-id', 'k': k, 'returns': [{'split': 'train', 'mean': 100.0 * r2}],
                'identification': {'r2_per_step': r2},
                'swaps': [{'steps_to_70pct': n} for n in steps]}
    rows = [figures(report(25, 0.9, [30, 40, None, 10]), 25),
            figures(report(25, 0.7, [50, 60, 70, 80]), 25),
            figures(report(15, 0.8, [5, 12, 18, 25]), 25)]
    assert rows[0].median_steps == 30 and rows[2].covered == 0.75
    text = markdown(rows, 'cmd').splitlines()
    short, own = (line for line in text if line.startswith('| zeus-id (25) |'))
    assert short.startswith('| zeus-id (25) | 15 | 1 | 80 | 0.80 |')   # one run: no +-
    assert own.startswith('| zeus-id (25) | 25 | 2 | 80 +- 10 | 0.80 +- 0.10 | 0.12 +- 0.12 |')


def test_estimate_gap_table_gives_the_mean_over_runs():
    sys.path.insert(0, str(ANALYSIS))
    from estimate_gap import render, ValueFigures
    one = [ValueFigures(1.0, -300.0, -250.0, 1.1), ValueFigures(2.0, -310.0, -240.0, 2.1)]
    two = [ValueFigures(1.0, -320.0, -250.0, 1.1), ValueFigures(2.0, -330.0, -240.0, 2.1)]
    out = render({'a': ('up-osi', one), 'b': ('up-osi', two)}, 'interpolation', 2, [])
    assert '| a | up-osi | -305.0 | -245.0 | 60.0 |' in out
    assert '| mean +- SE over 2 runs | | -315.0 +- 10.0 | -245.0 +- 0.0 | |' in out


def test_live_swaps_table_gives_decoded_means_and_keeps_recipes_apart():
    sys.path.insert(0, str(ANALYSIS))
    from live_swaps import RunFigures, table
    nan = float('nan')
    figures = [RunFigures('a', 'rma (k=10)', (90.0, 40.0), 130.0, (130.0,), (1.0, 4.0)),
               RunFigures('b', 'rma (k=10)', (70.0, 60.0), 130.0, (130.0,), (1.2, 3.0)),
               RunFigures('c', 'rma (k=10, raw extrinsics)', (80.0, 20.0), 100.0, (100.0,),
                          (1.1, 2.0)),
               RunFigures('d', 'sac', (95.0, 5.0), 100.0, (100.0,), (nan, nan))]
    rows = {line.split(' | ')[0].strip('| '): line
            for line in table(figures, {0: 1.0, 333: 4.0}).splitlines()[2:]}
    assert rows['rma (k=10)'] == ('| rma (k=10) | 2 | 80 +- 10 | 50 +- 10 | 130 +- 0 '
                                  '| 1.10 +- 0.10 | 3.50 +- 0.50 |')
    assert rows['rma (k=10, raw extrinsics)'].endswith('| 1.10 | 2.00 |')   # one run: no +-
    assert rows['sac'].endswith('| 100 | - | - |')                          # no decoder


@pytest.mark.ros   # starts the summary script: a process, not a unit test
def test_gaps_table_tests_the_oracle_against_sac_and_the_share_each_method_closes(tmp_path):
    for seed, (oracle, sac, rma) in enumerate([(700, 300, 620), (720, 320, 660),
                                               (710, 280, 640)], start=1):
        _report(tmp_path / f'rl-oracle-s{seed}', oracle, oracle + 10, 1.0)
        _report(tmp_path / f'rl-sac-s{seed}', sac, sac + 10, None)
        _report(tmp_path / f'rl-rma-s{seed}', rma, rma + 10, 0.9)
    _report(tmp_path / 'cp-oracle-s1', 500, 500, 1.0)     # one seed: no verdict
    _report(tmp_path / 'cp-sac-s1', 450, 450, None)
    out = subprocess.run([sys.executable, str(SUMMARIZE),
                          str(tmp_path), '--gaps'], check=True, capture_output=True, text=True,
                         env=os.environ | {'PYTHONPATH': str(REPO)}).stdout
    rows = [line for line in out.splitlines() if line.startswith('| rl | train')]
    # oracle 710 +- 6, sac 300 +- 12: +410, apart; rma 640 closes (640 - 300) / 410 = 83 %
    assert rows == ['| rl | train | 710 +- 6 (3) | 300 +- 12 (3) | +410 (+137 %) | yes | '
                    'rma 83 % |']
    assert '| cp | train | 500 (1) | 450 (1) | +50 (+11 %) | - | - |' in out
    # References trained another way (swaps): the same table against those groups.
    for seed, (oracle, sac) in enumerate([(900, 400), (920, 420), (910, 380)], start=1):
        _report(tmp_path / f'rl-oracle-swap-s{seed}', oracle, oracle + 10, 1.0)
        _report(tmp_path / f'rl-sac-swap-s{seed}', sac, sac + 10, None)
    out = subprocess.run([sys.executable, str(SUMMARIZE), str(tmp_path), '--gaps',
                          '--references', 'oracle-swap', 'sac-swap'], check=True,
                         capture_output=True, text=True,
                         env=os.environ | {'PYTHONPATH': str(REPO)}).stdout
    rows = [line for line in out.splitlines() if line.startswith('| rl | train')]
    # 910 against 400: +510; rma 640 closes (640 - 400) / 510 = 47 %; the old pair are methods now
    assert rows == ['| rl | train | 910 +- 6 (3) | 400 +- 12 (3) | +510 (+128 %) | yes | '
                    'oracle 61 %, rma 47 %, sac -20 % |'], out
    assert '| cp |' not in out   # no oracle-swap there


def test_gaps_verdict_names_the_threshold_a_gap_meets():
    sys.path.insert(0, str(ANALYSIS))
    from summarize_runs import _verdict
    assert _verdict(True, 410.0, 300.0) == 'yes'
    assert _verdict(True, 67.0, 194.0) == '15 % only'       # +35 %, under 100 points
    assert _verdict(True, 120.0, 1000.0) == '100 only'      # +12 %, over 100 points
    assert _verdict(False, 410.0, 300.0) == 'no'            # standard errors overlap
    assert _verdict(True, 20.0, 300.0) == 'no'
