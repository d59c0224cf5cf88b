"""A short, tiny training run writes a checkpoint that `evaluate` loads and runs."""

import csv
import os
from pathlib import Path
import shutil
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from test_learning_core import make_agent, make_batch
from zeus_ros.learning_tools import evaluate, train
from zeus_ros.core.config import ZeusConfig
from sim_node.families import get_sim_family
from zeus_ros.core.methods import METHODS
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.core.window import ContextWindow

FAMILY = 'finger-spin-v0'
TINY = ['hidden_dim=32', 'context_dim=6', 'feature_dim=8', 'encoder_hidden=16',
        'context_hidden=16', 'dynamics_hidden=16', 'decoder_hidden=8',
        'batch_size_per_task=4', 'replay_capacity=3000', 'init_steps=60',
        'episode_steps=100', 'num_threads=1']


@pytest.fixture(scope='module')
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp('run')
    argv = ['--family', FAMILY, '--steps', '150', '--seed', '3', '--out', str(out),
            '--eval-every', '150', '--eval-max-steps', '30', '--eval-splits', 'train',
            '--checkpoint-every', '100', '--log-every', '50', '--quiet', '--set', *TINY]
    assert train.main(argv) == 0
    return out


def test_training_writes_logs_and_checkpoint(run_dir):
    assert (run_dir / 'checkpoint' / 'model.safetensors').exists()
    rows = list(csv.DictReader(open(run_dir / 'train_log.csv')))
    assert [int(r['timestep']) for r in rows] == [50, 100, 150]
    assert rows[-1]['critic_loss'] != '' and rows[0]['critic_loss'] == ''  # updates after 60
    for metric in ('dynamics_loss', 'reward_loss', 'context_loss', 'decoder_loss'):
        assert rows[-1][metric] != '', metric   # zeus's own metrics, columns by their names
    assert float(rows[-1]['env_steps']) == 150 * 8
    evals = list(csv.DictReader(open(run_dir / 'eval_log.csv')))
    assert len(evals) == 8 and all(r['split'] == 'train' for r in evals)
    assert all(r['success'] == '' for r in evals)   # finger-spin has no success flag
    episodes = list(csv.DictReader(open(run_dir / 'episodes.csv')))
    assert len(episodes) == 8  # every task finished one 100-step episode by t=150
    assert list(run_dir.glob('tb/events.out.tfevents.*'))


def test_evaluate_cli_loads_and_runs(run_dir, capsys):
    code = evaluate.main(['--weights', str(run_dir), '--split', 'interpolation',
                          '--episodes', '1', '--max-steps', '20'])
    assert code == 0
    out = capsys.readouterr().out
    assert 'finger-spin-v0' in out and out.count('\n') >= 6
    assert evaluate.main(['--weights', str(run_dir / 'nope')]) == 2


def test_run_episode_order_and_determinism(run_dir):
    model = InferenceModel.load(run_dir)
    r1 = evaluate.run_episode(model, FAMILY, 0.1, seed=4, max_steps=25)
    r2 = evaluate.run_episode(model, FAMILY, 0.1, seed=4, max_steps=25)
    assert len(r1.actions) == 25 and r1.latents.dtype == np.float32
    assert not r1.latents[0].any()  # empty window at episode start -> zero latent
    assert r1.latents[1].any()
    np.testing.assert_array_equal(r1.actions, r2.actions)
    assert np.all(np.abs(r1.actions) <= 1)
    # the ROS loop: context from the window, act, step, push -- replayed by hand
    from sim_node.env import ParamEnv
    from zeus_ros.core.window import ContextWindow
    env = ParamEnv(FAMILY, 0.1, seed=4, episode_steps=25)
    obs = env.reset(seed=4)
    w = ContextWindow(model.k, env.obs_dim, env.action_dim)
    for t in range(25):
        latent = model.context(*w.arrays())
        action = model.act(obs, latent)
        assert np.array_equal(action, r1.actions[t])
        res = env.step(action)
        w.push(obs, action, res.reward, res.observation)
        obs = res.observation
    # a live swap changes the parameter in force from that step on
    r3 = evaluate.run_episode(model, FAMILY, 0.1, seed=4, max_steps=25,
                              swap_schedule={10: 0.2})
    assert r3.param_values[9] == 0.1 and r3.param_values[10] == 0.2
    np.testing.assert_array_equal(r3.actions[:10], r1.actions[:10])
    # inference pins torch to one thread even if the process asked for more
    import torch
    torch.set_num_threads(2)
    r4 = evaluate.run_episode(model, FAMILY, 0.1, seed=4, max_steps=25)
    assert torch.get_num_threads() == 1
    np.testing.assert_array_equal(r4.actions, r1.actions)


def test_checkpoint_records_seed_and_run_arguments(run_dir):
    meta = InferenceModel.load(run_dir).meta
    assert meta.seed == 3 and meta.run.seed == 3
    assert meta.run.method == 'zeus' and meta.run.overrides['hidden_dim'] == 32
    assert meta.steps.wall_s > 0


def test_periodic_evaluation_is_the_eval_clis_evaluator(run_dir):
    """The trainer's eval rows equal evaluate.evaluate on the checkpoint it saved then."""
    rows = list(csv.DictReader(open(run_dir / 'eval_log.csv')))
    model = InferenceModel.load(run_dir)
    again = evaluate.evaluate(model, [float(r['value']) for r in rows], 1, train.EVAL_SEED,
                              max_steps=30)
    for logged, fresh in zip(rows, again, strict=True):
        assert float(logged['return']) == pytest.approx(fresh['mean_return'], abs=1e-4)


def test_resume_continues_from_checkpoint(run_dir, tmp_path, capsys):
    own = tmp_path / 'run'
    shutil.copytree(run_dir, own)   # this test must not change the shared run
    wall_before = InferenceModel.load(own).meta.steps.wall_s
    argv = ['--family', FAMILY, '--steps', '170', '--seed', '3', '--out', str(own),
            '--eval-every', '0', '--checkpoint-every', '1000', '--log-every', '10',
            '--quiet', '--resume', '--set', *TINY]
    assert train.main(argv) == 0
    assert 'resumed at timestep 150' in capsys.readouterr().out
    model = InferenceModel.load(own)
    assert model.meta.steps.timestep == 170
    assert model.meta.steps.wall_s > wall_before   # wall time keeps counting
    # a different config cannot resume this run
    bad = [*argv, 'hidden_dim=64']
    assert train.main(bad) == 2
    with pytest.raises(CheckpointError):
        InferenceModel.load(own, expected_family='walker-walk-v0')


def test_csv_log_keeps_the_columns_a_resumed_run_started_with_and_adds_new_ones(tmp_path):
    path = tmp_path / 'log.csv'
    old = train.CsvLog(path, ('a', 'b'))
    old.write({'a': 1, 'b': 2})
    old.close()
    resumed = train.CsvLog(path, ('a', 'new', 'b'))
    resumed.write({'a': 3, 'new': 9, 'b': 4})
    resumed.write({'a': 5, 'late': 7})   # a name first seen after the header was written
    resumed.close()
    assert next(csv.reader(open(path))) == ['a', 'b', 'new', 'late']
    assert list(csv.DictReader(open(path))) == [
        {'a': '1', 'b': '2', 'new': '', 'late': ''}, {'a': '3', 'b': '4', 'new': '9', 'late': ''},
        {'a': '5', 'b': '', 'new': '', 'late': '7'}]


def logged_row(out, metric_names: tuple[str, ...], metrics: list[dict]) -> dict:
    """Write one train-log row of `metrics` (averaged, as the trainer does) and read it back."""
    logs = train.TrainingLogs(out, metric_names)
    for m in metrics:
        logs.accumulate(m)
    trainer = SimpleNamespace(timestep=1, env_steps=8, wall_s=lambda: 1.0,
                              last_returns=np.full(2, np.nan))
    logs.train_row(trainer, SimpleNamespace(set_postfix=lambda **kw: None))
    logs.close()
    return list(csv.DictReader(open(out / 'train_log.csv')))[-1]


@pytest.mark.parametrize('method', sorted(METHODS))
def test_every_metric_a_methods_update_returns_reaches_the_train_log(method, tmp_path):
    agent, batch = make_agent(method), make_batch()
    metrics = [agent.update(batch), agent.update(batch)]   # the actor steps every 2nd update
    row = logged_row(tmp_path, agent.metric_names(), metrics)
    returned = {k for m in metrics for k in m}
    assert set(agent.method.metric_names) - {'context_loss'} <= returned
    assert all(row[k] != '' for k in returned), row
    assert not {'dynamics_mse'} & set(row)   # a column no method ever wrote


def test_a_run_resumed_from_an_old_log_gains_its_methods_columns(tmp_path):
    """A log started before the columns came from the metric names (cadm's were dropped)."""
    old = ('timestep', 'env_steps', 'wall_s', 'env_steps_per_s', 'critic_loss', 'q1',
           'actor_loss', 'alpha_loss', 'alpha', 'entropy', 'dynamics_loss', 'dynamics_mse',
           'reward_loss', 'context_loss', 'decoder_loss')
    (tmp_path / 'train_log.csv').write_text(','.join(old) + '\n' + '1,8' + ',' * 13 + '\n')
    agent, batch = make_agent('cadm'), make_batch()
    row = logged_row(tmp_path, agent.metric_names(), [agent.update(batch)])
    rows = list(csv.DictReader(open(tmp_path / 'train_log.csv')))
    assert next(csv.reader(open(tmp_path / 'train_log.csv')))[:len(old)] == list(old)
    assert row['backward_loss'] != '' and rows[0]['backward_loss'] == '' and len(rows) == 2


def test_repeated_set_options_accumulate_the_last_value_of_a_field_wins():
    # The training queue appends its own --set num_threads=1 to each job's line.
    ns = train.build_parser().parse_args(['--out', 'x', '--set', 'batch_size_per_task=16',
                                    'init_steps=7', '--set', 'num_threads=1', 'init_steps=9'])
    assert train.RunArgs.from_cli(ns).overrides == {'batch_size_per_task': 16, 'init_steps': 9,
                                              'num_threads': 1}


def test_reward_varying_families_put_the_reward_into_the_observation(tmp_path):
    # Appendix B.2.1: only where the reward is all that differs between tasks.
    assert train.family_config('cheetah-run-v1').reward_in_observation
    assert not train.family_config('walker-walk-v0').reward_in_observation
    out = tmp_path / 'run'
    argv = ['--family', 'cheetah-run-v1', '--method', 'sac', '--steps', '70', '--out',
            str(out), '--eval-every', '0', '--checkpoint-every', '70', '--quiet', '--set',
            *TINY]
    assert train.main(argv) == 0
    model = InferenceModel.load(out / 'checkpoint')
    assert model.reward_in_observation
    record = evaluate.run_episode(model, model.family, 1.0, seed=0, max_steps=20)
    assert record.observations.shape[1] == model.obs_dim
    np.testing.assert_array_equal(record.observations[1:, -1], record.rewards[:-1])
    assert record.observations[0, -1] == 0.0


def test_train_swaps_move_tasks_between_training_values_and_the_replay_follows(tmp_path):
    args = train.RunArgs(out=tmp_path / 'run', family=FAMILY, method='oracle', steps=0,
                         overrides=train.parse_overrides([*TINY, 'train_swap_prob=0.5']))
    trainer = train.Trainer(args)
    seen = set()
    for _ in range(20):
        trainer.collect()
        trainer.timestep += 1
        seen |= {env.param_values for env in trainer.envs}
        assert seen <= set(trainer.values)     # value tuples, one number each here
    n = len(trainer.replay)
    params = trainer.replay.param[:n].reshape(20, len(trainer.envs))
    assert len(seen) > 1 and len(set(params[-1])) > 1
    # Every transition carries the value in force when it was taken, which
    # after a swap is not its task's first one.
    assert (params[-1] == np.float32([env.param_values[0] for env in trainer.envs])).all()
    assert (params != np.asarray(trainer.values, np.float32).reshape(-1)).any()
    # Without swaps nothing moves, and no random draw is spent on them.
    still = train.Trainer(train.RunArgs(out=tmp_path / 'still', family=FAMILY,
                                        method='oracle', steps=0,
                                        overrides=train.parse_overrides(TINY)))
    for _ in range(5):
        still.collect()
        still.timestep += 1
    assert [env.param_values for env in still.envs] == list(still.values)


def test_downward_train_swaps_only_ever_lower_a_tasks_value(tmp_path):
    overrides = train.parse_overrides([*TINY, 'train_swap_prob=0.5',
                                       'train_swap_direction=down'])
    trainer = train.Trainer(train.RunArgs(out=tmp_path / 'run', family=FAMILY, method='oracle',
                                          steps=0, overrides=overrides))
    lowest = min(trainer.values)
    before = [env.param_values for env in trainer.envs]
    moved = 0
    for _ in range(20):
        trainer.collect()
        trainer.timestep += 1
        after = [env.param_values for env in trainer.envs]
        assert all(a <= b for a, b in zip(after, before, strict=True))
        moved += sum(a != b for a, b in zip(after, before, strict=True))
        before = after
    assert moved > 0 and min(before) == lowest
    with pytest.raises(ValueError, match='train_swap_direction'):
        ZeusConfig(train_swap_direction='up').validate()


@pytest.mark.parametrize('sampling', ['range', 'log-range'])
def test_range_sampling_draws_every_episode_and_swap_inside_the_train_span(tmp_path, sampling):
    overrides = train.parse_overrides([*TINY, 'episode_steps=5', 'train_swap_prob=0.2',
                                       f'train_sampling={sampling}'])
    trainer = train.Trainer(train.RunArgs(out=tmp_path / 'run', family=FAMILY, method='oracle',
                                          steps=0, overrides=overrides))
    lo, hi = min(trainer.values)[0], max(trainer.values)[0]
    draw, drawn = trainer._draw_value, []
    trainer._draw_value = lambda: drawn.append(draw()) or drawn[-1]
    seen = {env.param_values for env in trainer.envs}
    for _ in range(30):
        trainer.collect()
        trainer.timestep += 1
        seen |= {env.param_values for env in trainer.envs}
    seen |= set(drawn)
    assert len(drawn) > 60                             # fresh values, not the 8 train ones
    assert all(lo <= v[0] <= hi for v in seen)
    assert not seen & set(trainer.values)
    n = len(trainer.replay)                            # the replay records the value in force
    recorded = trainer.replay.param[:n].reshape(-1, 1)
    in_force = np.float32([v[0] for v in seen])
    assert np.abs(recorded - in_force[None]).min(axis=1).max() == 0.0
    values = np.float64([v[0] for v in drawn])
    linear_middle, log_middle = (lo + hi) / 2, np.sqrt(lo * hi)
    own, other = (log_middle, linear_middle) if sampling == 'log-range' \
        else (linear_middle, log_middle)
    assert 0.3 < np.mean(values < own) < 0.7           # uniform in its own scale
    assert abs(np.mean(values < other) - 0.5) > 0.1    # and not in the other's
    with pytest.raises(ValueError, match='train_sampling'):
        ZeusConfig(train_sampling='grid').validate()


def test_live_span_draws_over_the_live_range_beyond_the_train_values(tmp_path):
    """train_span=live: episodes and swaps reach the live range's ends, not only the train span."""
    overrides = train.parse_overrides([*TINY, 'episode_steps=5', 'train_swap_prob=0.5',
                                       'train_sampling=log-range', 'train_span=live'])
    trainer = train.Trainer(train.RunArgs(out=tmp_path / 'run', family=FAMILY, method='oracle',
                                          steps=0, overrides=overrides))
    (live_lo, live_hi), = [p.live_range for p in get_sim_family(FAMILY).live_params]
    lo, hi = min(trainer.values)[0], max(trainer.values)[0]
    drawn = np.float64([trainer._draw_value()[0] for _ in range(400)])
    assert live_lo <= drawn.min() < lo and hi < drawn.max() <= live_hi
    for _ in range(20):                               # swaps put live values into force
        trainer.collect()
        trainer.timestep += 1
    seen = [env.param_values[0] for env in trainer.envs]
    assert all(live_lo <= v <= live_hi for v in seen)
    with pytest.raises(ValueError, match="train_span='live' needs"):
        ZeusConfig(train_span='live').validate()


def test_param_space_log_normalises_logs_and_the_checkpoint_decodes_back(tmp_path):
    """param_space=log: the oracle sees ln(value) min-max scaled; the checkpoint says so.

    The saved metadata passes its schema, and a deployed decoder's 0.5 reads back as the
    train values' geometric midpoint (exp of the log mean), not their linear one.
    """
    run = tmp_path / 'run'
    argv = ['--family', FAMILY, '--method', 'oracle', '--steps', '20', '--seed', '1',
            '--out', str(run), '--eval-every', '1000', '--checkpoint-every', '20',
            '--set', *TINY, 'init_steps=10', 'num_threads=1', 'param_space=log']
    assert train.main(argv) == 0
    model = InferenceModel.load(run / 'checkpoint')
    norm = model.meta.param_normalisation
    values = np.log(np.float64(norm.train_values))
    assert norm.log and norm.offset == pytest.approx(values.min())
    assert norm.scale == pytest.approx(values.max() - values.min())
    rows, mask = ContextWindow(model.k, model.obs_dim, model.action_dim).arrays()
    low, high = min(norm.train_values), max(norm.train_values)
    assert model.context(rows, mask, low)[0] == pytest.approx(0.0, abs=1e-6)   # oracle: e
    assert model.context(rows, mask, high)[0] == pytest.approx(1.0, abs=1e-6)
    geo = float(np.sqrt(low * high))                 # the log midpoint reads 0.5, not linear
    assert model.context(rows, mask, geo)[0] == pytest.approx(0.5, abs=1e-5)
    model._decode = lambda latent: np.float32([[0.5]])   # what a decoder would read
    assert model.decode_values(np.zeros(model.context_dim))[0] == pytest.approx(geo)
    with pytest.raises(ValueError, match='train_sampling|param_space'):
        ZeusConfig(param_space='sqrt').validate()


def test_a_task_with_a_success_flag_logs_its_success_rate(tmp_path, capsys):
    """Sawyer-Peg-v0's periodic evaluation writes a success rate per goal and prints it."""
    argv = ['--family', 'sawyer-peg-v0', '--steps', '40', '--seed', '1', '--out', str(tmp_path),
            '--eval-every', '40', '--eval-max-steps', '10', '--eval-splits', 'train',
            '--checkpoint-every', '40', '--log-every', '20', '--set', *TINY[:-3],
            'init_steps=30', 'num_threads=1']
    assert train.main(argv) == 0
    rows = list(csv.DictReader(open(tmp_path / 'eval_log.csv')))
    assert rows and all(0.0 <= float(r['success']) <= 1.0 for r in rows)
    printed = capsys.readouterr().out
    assert '] train=' in printed and '(success ' in printed


def test_collected_run_with_weights_loads_from_the_results_folder(run_dir, tmp_path):
    """collect_runs --with-weights: the committed folder alone replays the policy."""
    repo = Path(__file__).resolve().parents[1]
    collect = repo / 'research' / 'analysis' / 'collect_runs.py'
    subprocess.run([sys.executable, str(collect), str(tmp_path),
                    str(run_dir), '--with-weights'], check=True, capture_output=True,
                   env=os.environ | {'PYTHONPATH': str(repo)})
    collected = tmp_path / run_dir.name
    assert sorted(p.name for p in (collected / 'checkpoint').iterdir()) == [
        'metadata.json', 'model.safetensors']          # no training state, no replay
    assert (collected / 'run.json').exists() and (collected / 'train_log.csv').exists()
    replayed = evaluate.run_episode(InferenceModel.load(collected), FAMILY, 0.1, seed=4,
                                    max_steps=25)
    original = evaluate.run_episode(InferenceModel.load(run_dir), FAMILY, 0.1, seed=4,
                                    max_steps=25)
    np.testing.assert_array_equal(replayed.actions, original.actions)
