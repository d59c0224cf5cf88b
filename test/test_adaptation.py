"""Adaptation report: its measures on synthetic data and on small real checkpoints."""

from dataclasses import replace
import subprocess
import sys
from pathlib import Path

from conftest import built_once
import numpy as np
import pytest

from sim_node.env import ParamEnv
from sim_node.families import get_family
from zeus_ros.learning_tools.adaptation import (build_report, held_out_values, OtherPhysicsWindow,
                                                r_squared, ReportConfig, steps_to_cover,
                                                ZeroedContext)
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode

pytestmark = pytest.mark.ros   # starts processes of its own

REPO = Path(__file__).resolve().parents[1]
FAMILY = 'walker-walk-slippery'
QUICK = ReportConfig(episodes=1, max_steps=40, swap_step=20, swap_steps=40)


def train_tiny(tmp_path_factory, method, family=FAMILY):
    def build(directory):
        out = directory / 'run'
        subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.train', '--family',
                        family, '--method', method, '--steps', '150', '--out', str(out),
                        '--eval-every', '0', '--checkpoint-every', '150', '--quiet',
                        '--set', 'init_steps=100', 'hidden_dim=32', 'batch_size_per_task=4',
                        'replay_capacity=2000', 'context_length=5'],
                       check=True, cwd=REPO, capture_output=True)
        return out / 'checkpoint'
    return built_once(tmp_path_factory, f'adaptation-{family}-{method}', build)


@pytest.fixture(scope='module')
def oracle(tmp_path_factory):
    return train_tiny(tmp_path_factory, 'oracle')


@pytest.fixture(scope='module')
def sac(tmp_path_factory):
    return train_tiny(tmp_path_factory, 'sac')


@pytest.fixture(scope='module')
def zeus_id(tmp_path_factory):
    return train_tiny(tmp_path_factory, 'zeus-id')


@pytest.fixture(scope='module')
def target_velocity_sac(tmp_path_factory):
    return train_tiny(tmp_path_factory, 'sac', 'cheetah-run-v1')


def test_r_squared_and_swap_coverage_on_known_series():
    assert r_squared([1, 2, 3], [1, 2, 3]) == 1.0
    assert r_squared([1, 2, 3], [2, 2, 2]) == 0.0
    est = np.concatenate([np.full(100, 1.0), np.linspace(1.0, 2.0, 11), np.full(50, 2.0)])
    # from 1.0 to 2.0: 70 % covered once the ramp passes 1.7, i.e. 7 steps after the swap
    assert steps_to_cover(est, 100, 1.0, 2.0) == 7
    assert steps_to_cover(np.ones(200), 100, 1.0, 2.0) is None
    # a decrease is covered when the estimate falls far enough
    assert steps_to_cover(est[::-1].copy(), 50, 2.0, 1.0) == 7


def test_oracle_report_identifies_exactly_and_reacts_at_once(oracle):
    report = build_report(str(oracle), QUICK)
    assert report.method == 'oracle' and report.context_dim == 1
    assert report.identification.r2_per_step == pytest.approx(1.0)
    assert all(s.steps_to_70pct == 0 for s in report.swaps)
    assert all(s.steps_to_within_20pct == 0 for s in report.swaps)   # the truth, at once
    assert {r.split for r in report.returns} == {'train', 'interpolation', 'extrapolation'}
    assert report.context_use.split == 'extrapolation'
    assert report.context_use_train.split == 'train'
    # the oracle's input is the truth: frozen at another value's, it is that value's
    assert report.context_use_train.frozen_other != report.context_use_train.intact
    quicker = build_report(str(oracle), replace(QUICK, context_use_train=False))
    assert quicker.context_use_train is None and quicker.context_use == report.context_use


def test_held_out_means_values_never_trained_on(tmp_path_factory):
    spec = get_family('cheetah-run-v0')   # Table 3 prints 1.25, 1.4, 1.5 in both splits
    assert held_out_values(spec, 'extrapolation') == (0.3, 0.4, 0.5, 0.55, 1.2)
    assert held_out_values(spec, 'interpolation') == spec.interpolation
    report = build_report(str(train_tiny(tmp_path_factory, 'oracle', 'cheetah-run-v0')),
                          replace(QUICK, context_use_train=False))
    extrapolation = next(r for r in report.returns if r.split == 'extrapolation')
    assert sorted(extrapolation.per_value) == ['0.3', '0.4', '0.5', '0.55', '1.2']
    assert extrapolation.left_out == ('1.25', '1.4', '1.5')
    assert extrapolation.mean == pytest.approx(np.mean(list(extrapolation.per_value.values())))


def test_sac_report_has_no_context_sections(sac):
    report = build_report(str(sac), QUICK)
    assert report.context_dim == 0 and report.identification is None
    assert report.swaps == [] and report.context_use is None
    assert report.context_use_train is None


def test_velocity_error_is_measured_per_target_and_bounded_by_the_reward(
        target_velocity_sac):
    report = build_report(str(target_velocity_sac), QUICK)
    spec = ParamEnv('cheetah-run-v1').spec
    errors = report.velocity_error
    assert set(errors.per_value) == {str(v) for v in spec.train + spec.interpolation}
    assert set(errors.mean_per_split) == {'train', 'interpolation'}
    model = InferenceModel.load(target_velocity_sac)
    # reward = -|speed - target| - 0.05 |a|^2, so the error is at most minus the mean reward
    for v in (0.0, 3.0):
        rec = run_episode(model, 'cheetah-run-v1', v, seed=0, max_steps=40)
        assert 0.0 <= errors.per_value[str(v)] <= -rec.rewards.mean() + 1e-9
    assert errors.per_value['3.0'] > errors.per_value['0.0']   # a tiny policy barely moves
    assert build_report(str(target_velocity_sac), QUICK).velocity_error == errors


def test_zeroed_probe_feeds_zero_latents(zeus_id):
    model = InferenceModel.load(zeus_id)
    rec = run_episode(model, FAMILY, 0.2, seed=0, max_steps=30, probe=ZeroedContext(model))
    assert not rec.latents.any()
    intact = run_episode(model, FAMILY, 0.2, seed=0, max_steps=30)
    assert intact.latents[5:].any()


def test_a_shorter_deployment_window_changes_the_latent_only_once_the_window_is_full(zeus_id):
    full = run_episode(InferenceModel.load(zeus_id), FAMILY, 0.2, seed=0, max_steps=30)
    short_model = InferenceModel.load(zeus_id)
    short_model.k = 2     # what the report's --window 2 deploys
    short = run_episode(short_model, FAMILY, 0.2, seed=0, max_steps=30)
    # Until two transitions exist both windows hold the same rows; later the k = 5
    # window pools three to five of them, the short one only the last two.
    np.testing.assert_allclose(short.latents[:2], full.latents[:2], atol=1e-6)
    assert np.abs(short.latents[6:] - full.latents[6:]).max() > 1e-4
    report = build_report(str(zeus_id), replace(QUICK, window=2, context_use_train=False))
    assert report.k == 2
    refused = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.adaptation',
                              '--weights',
                              str(zeus_id), '--window', '-1'], cwd=REPO, capture_output=True,
                             text=True)
    assert refused.returncode == 2 and 'window must be >= 0' in refused.stderr

def test_other_physics_window_is_the_same_step_under_the_other_value():
    env = ParamEnv(FAMILY, 0.1, seed=3)
    env.reset(seed=3)
    probe = OtherPhysicsWindow(FAMILY, 0.6, max_steps=1000)
    twin = ParamEnv(FAMILY, 0.6, seed=3)
    action = np.full(env.action_dim, 0.5)
    for _ in range(80):  # long enough for the feet to touch the floor
        env.step(action)
    twin.copy_state_from(env)
    expected = twin.step(action)
    probe.before_step(env, action)
    real = env.step(action)
    reward, obs = probe.window_transition(real)
    np.testing.assert_array_equal(obs, expected.observation)
    assert reward == expected.reward
    assert not np.array_equal(obs, real.observation)  # the friction does change s'


def test_a_two_parameter_oracle_is_identified_per_parameter_with_success_rates(
        tmp_path_factory):
    """Sawyer-Peg-v0: R^2 per goal coordinate, swaps along the goal change, success rates."""
    report = build_report(str(train_tiny(tmp_path_factory, 'oracle', 'sawyer-peg-v0')),
                          ReportConfig(episodes=1))
    ident = report.identification
    assert set(ident.r2_per_parameter) == {'goal_x', 'goal_y'}
    assert all(r2 > 0.999 for r2 in ident.r2_per_parameter.values())   # the truth itself
    assert ident.r2_per_step == pytest.approx(np.mean(list(ident.r2_per_parameter.values())))
    assert all(len(s.from_value) == 2 and s.steps_to_70pct == 0 for s in report.swaps)
    assert {r.split for r in report.returns} == {'train', 'interpolation'}
    assert all(0.0 <= r.success_rate <= 1.0 for r in report.returns)
    assert report.context_use.split == 'interpolation'


def test_swap_coverage_of_a_two_parameter_change_is_measured_along_it():
    estimates = np.zeros((20, 2))
    estimates[10:] = [0.3, 0.6]          # the change is (0.5, 1.0): 60 % of it, then all
    estimates[14:] = [0.5, 1.0]
    assert steps_to_cover(estimates, 10, (0.0, 0.0), (0.5, 1.0)) == 4
    assert steps_to_cover(estimates[:14], 10, (0.0, 0.0), (0.5, 1.0)) is None


def test_cross_reader_rebuilds_the_windows_the_live_episode_read(zeus_id):
    """The batched windows of research/analysis/cross_reader.py are the live loop's, step for step.

    It decodes the transitions of a recorded episode in one batch.
    """
    sys.path.insert(0, str(REPO / 'research' / 'analysis'))
    from cross_reader import episode_rows, reader_estimates
    model = InferenceModel.load(zeus_id)
    record = run_episode(model, FAMILY, 0.2, seed=3, max_steps=40)
    batched = reader_estimates(model, episode_rows(record))
    assert len(batched) == len(record.estimates) - model.k
    np.testing.assert_allclose(batched, record.estimates[model.k:], rtol=1e-5, atol=1e-5)
    assert np.ptp(batched) > 0   # not a constant: the comparison can fail


@pytest.fixture(scope='module')
def up_osi(tmp_path_factory):
    return train_tiny(tmp_path_factory, 'up-osi')


def test_estimate_gap_feeds_the_true_parameter_where_the_estimate_sits(up_osi):
    """research/analysis/estimate_gap.py: its probe gives the policy the truth, not OSI's guess."""
    sys.path.insert(0, str(REPO / 'research' / 'analysis'))
    from estimate_gap import TrueEstimate
    model = InferenceModel.load(up_osi)
    inferred = run_episode(model, FAMILY, 0.3, seed=1, max_steps=40)
    truth = run_episode(model, FAMILY, 0.3, seed=1, max_steps=40,
                        probe=TrueEstimate(model, 0.3))
    np.testing.assert_allclose(truth.estimates, 0.3, atol=1e-6)   # decoded back to the truth
    assert np.ptp(inferred.estimates) > 0   # OSI's own estimate moves: the probe changed it
    assert not np.allclose(inferred.actions, truth.actions)


def test_estimate_gap_gives_rma_its_teachers_latent_for_the_true_parameter(tmp_path_factory):
    """For rma the truth is mu(true parameter), the latent its student estimates."""
    sys.path.insert(0, str(REPO / 'research' / 'analysis'))
    import torch
    from estimate_gap import TeacherLatent, truth_probe
    model = InferenceModel.load(train_tiny(tmp_path_factory, 'rma'))
    probe = truth_probe(model, 0.3)
    assert isinstance(probe, TeacherLatent)
    inferred = run_episode(model, FAMILY, 0.3, seed=1, max_steps=40)
    truth = run_episode(model, FAMILY, 0.3, seed=1, max_steps=40, probe=probe)
    with torch.no_grad():
        teacher = model.method.teacher(torch.tensor([[0.3]])).numpy()[0]
    np.testing.assert_allclose(truth.latents, np.broadcast_to(teacher, truth.latents.shape),
                               atol=1e-6)
    assert not np.allclose(inferred.latents, truth.latents)   # psi's estimate is not mu's
    assert not np.allclose(inferred.actions, truth.actions)
