"""Ray Tune sweep: a tiny real grid trains, a killed sweep resumes its trials, results gather."""

import csv
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import pytest
import yaml

from sweep_helpers import assert_resumed_not_restarted, checkpoint_timestep, \
    listening_beyond_loopback
from zeus_ros.learning_tools.sweep_config import run_dir, SweepConfig

pytestmark = pytest.mark.ros   # starts processes of its own

REPO = Path(__file__).resolve().parents[1]
TINY = {'hidden_dim': 32, 'batch_size_per_task': 4, 'replay_capacity': 3000,
        'init_steps': 40, 'episode_steps': 60, 'context_length': 5}


def write_sweep(tmp_path, steps, name='tiny'):
    path = tmp_path / f'{name}.yaml'
    path.write_text(yaml.safe_dump({
        'name': name, 'storage': str(tmp_path / 'sweeps'), 'families': ['finger-spin-v0'],
        'methods': ['sac', 'zeus-id'], 'seeds': [1], 'steps': steps, 'max_concurrent': 2,
        'train': {'eval_every': 50, 'eval_max_steps': 20, 'checkpoint_every': 20,
                  'log_every': 10},
        'overrides': TINY}))
    return path


def sweep(args, **kw):
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED='0')
    return subprocess.Popen([sys.executable, '-m', 'zeus_ros.learning_tools.sweep',
                             *map(str, args)],
                            cwd=REPO, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


@pytest.mark.parametrize('path', sorted((REPO / 'config' / 'sweeps').glob('*.yaml')),
                         ids=lambda path: path.stem)
def test_every_shipped_sweep_file_loads(path):
    cfg = SweepConfig.load(path)
    assert cfg.name == path.stem and cfg.families and cfg.methods and len(cfg.seeds) >= 3


def test_bad_sweep_file_is_refused(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('name: x\nfamilies: [nope]\nmethods: [sac]\nseeds: [1]\nsteps: 5\n')
    with pytest.raises(ValueError, match='nope'):
        SweepConfig.load(bad)
    for override, error in (('{nope: 1}', 'nope'), ('{train_swap_prob: 2.0}', 'train_swap_prob')):
        bad.write_text('name: x\nfamilies: [finger-spin-v0]\nmethods: [sac]\nseeds: [1]\n'
                       f'steps: 5\noverrides: {override}\n')
        with pytest.raises(ValueError, match=error):
            SweepConfig.load(bad)


@pytest.mark.timeout(900)   # two sweeps, its own waits 240 s + 420 s
def test_killed_sweep_resumes_its_trials_and_gathers_results(tmp_path):
    path = write_sweep(tmp_path, steps=240)
    cfg = SweepConfig.load(path)
    runs = [run_dir(cfg, 'finger-spin-v0', m, 1) for m in ('sac', 'zeus-id')]
    proc = sweep(['run', path])
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and not all(
            (r / 'checkpoint' / 'metadata.json').exists() for r in runs):
        assert proc.poll() is None, proc.stdout.read()
        time.sleep(0.5)
    # local Ray listens on loopback only, even where the default route is another interface
    ours, outside = listening_beyond_loopback(proc.pid)
    assert ours and not outside, outside
    os.killpg(proc.pid, signal.SIGKILL)   # the whole sweep, Ray included, mid-training
    proc.wait()
    killed_at = {r: checkpoint_timestep(r) for r in runs}
    assert all(0 < t < 240 for t in killed_at.values()), killed_at
    resumed = sweep(['run', path, '--resume'])
    out, _ = resumed.communicate(timeout=420)
    assert resumed.returncode == 0, out[-3000:]
    for r in runs:
        assert checkpoint_timestep(r) == 240
        # the resumed trial continued from its checkpoint instead of starting over:
        # it repeats at most the one checkpoint interval (20 timesteps) it lost
        assert_resumed_not_restarted(r, steps=240, log_every=10, lost_rows=2)
    table = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.sweep', 'table',
                            str(path)],
                           cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert '| sac |' in table and '| zeus-id |' in table
    rows = list(csv.DictReader(open(cfg.root / 'comparison.csv')))
    assert {(r['method'], r['split']) for r in rows} >= {('sac', 'train'), ('zeus-id', 'train')}
    assert (cfg.root / 'curves_finger-spin-v0.png').stat().st_size > 1000


@pytest.mark.unit
def test_the_report_table_takes_only_finished_runs_and_reuses_their_reports(tmp_path):
    from dataclasses import replace
    from zeus_ros.deploy.checkpoint import load_metadata, write_metadata
    from zeus_ros.learning_tools.sweep_results import run_report
    run = tmp_path / 'run'
    (run / 'checkpoint').mkdir(parents=True)
    meta = run / 'checkpoint' / 'metadata.json'
    shipped = load_metadata(REPO / 'weights' / 'cheetah-run-v0-sac')

    def checkpoint_at(timestep):
        write_metadata(run / 'checkpoint',
                       replace(shipped, steps=replace(shipped.steps, timestep=timestep)))
    checkpoint_at(900)
    assert run_report(run, episodes=1, steps=1000) is None     # still training
    checkpoint_at(1000)
    cached = run / 'adaptation.json'
    cached.write_text('{"returns": [], "identification": null}')
    os.utime(meta, (1, 1))                                   # the report is newer
    assert run_report(run, episodes=1, steps=1000) == {'returns': [], 'identification': None}


def test_the_final_evaluation_table_leaves_unfinished_runs_out_and_says_so():
    from zeus_ros.learning_tools.sweep_results import Curve, markdown, table_rows
    done = Curve((800, 1600), (100, 200), {'train': (10.0, 30.0)})
    other = Curve((800, 1600), (100, 200), {'train': (12.0, 50.0)})
    half = Curve((800,), (100,), {'train': (900.0,)})
    rows = table_rows({('f', 'sac'): {1: done, 2: half, 3: other}},
                      lambda family, method, seed: seed != 2)
    assert rows == [{'family': 'f', 'method': 'sac', 'split': 'train', 'mean': 40.0,
                     'sem': 10.0, 'seeds': 2, 'timestep': 200, 'unfinished': 1}]
    assert '| 2 (+1 unfinished, left out) | 200 |' in markdown(rows, {})


@pytest.mark.unit
def test_the_report_tables_give_success_rates_and_speed_errors_where_reports_have_them():
    from zeus_ros.learning_tools.sweep_results import markdown, ReportFigures
    rows = [{'family': 'sawyer-peg-v0', 'method': m, 'split': 'train', 'mean': 40.0, 'sem': 1.0,
             'seeds': 2, 'timestep': 100, 'unfinished': 0} for m in ('zeus', 'sac')]
    figures = {('sawyer-peg-v0', 'zeus'): ReportFigures(
                   {'train': [40.0, 50.0]}, [0.7, 0.9], [30.0, 50.0],
                   success_rate={'train': [0.5, 0.7], 'interpolation': [0.6, 0.6]}),
               ('sawyer-peg-v0', 'sac'): ReportFigures({'train': [30.0, 32.0]}, [], [])}
    text = markdown(rows, figures)
    assert 'Success rate' in text and '| zeus | 0.60 +- 0.10 | 0.60 +- 0.00 | - |' in text
    assert '| sac | ' in text and 'speed - target' not in text   # no method has one


@pytest.mark.unit
def test_the_report_table_gives_context_use_at_the_train_values_only_where_measured():
    from zeus_ros.learning_tools.sweep_results import markdown, ReportFigures
    rows = [{'family': 'f', 'method': m, 'split': 'train', 'mean': 40.0, 'sem': 1.0,
             'seeds': 2, 'timestep': 100, 'unfinished': 0} for m in ('zeus', 'sac')]
    older = {('f', 'zeus'): ReportFigures({'train': [40.0, 50.0]}, [0.7, 0.9], [30.0, 50.0]),
             ('f', 'sac'): ReportFigures({'train': [30.0, 32.0]}, [], [])}
    assert 'the same at the train values' not in markdown(rows, older)
    newer = {**older, ('f', 'zeus'): ReportFigures({'train': [40.0, 50.0]}, [0.7, 0.9],
                                                   [30.0, 50.0], largest_gap_train=[10.0, 20.0],
                                                   swaps_covered=[0.5, 1.0])}
    table = [line for line in markdown(rows, newer).splitlines() if line.startswith('| ')]
    header = next(line for line in table if 'the same at the train values' in line)
    # the report's rows come after the trainer's own table
    zeus, sac = ([line for line in table if line.startswith(f'| {m} |')][-1]
                 for m in ('zeus', 'sac'))
    assert zeus.endswith('| 0.80 +- 0.10 | 0.75 +- 0.25 | 40 +- 10 | 15 +- 5 |')
    assert sac.endswith('| - | - | - |')
    assert header.count('|') == zeus.count('|') == sac.count('|')
