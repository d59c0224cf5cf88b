"""Plain logic of commands in ros2_control's form and of the window built from them (#49)."""

import math

import numpy as np
import pytest

from sim_node.layout import ObservationLayout
from zeus_ros.core.window import ContextWindow
from zeus_ros.ros.commands import (ActuatorUnits, command_topic, CommandSetupError,
                                   CommandTransitionAssembler, joint_order, make_codec,
                                   reward_free_refusal)
from zeus_ros.ros.pairing import TransitionAssembler

ACTUATORS = ('bthigh', 'bshin', 'bfoot')
JOINTS = ('j0', 'j1')
LAYOUT = ObservationLayout(JOINTS, ('raw', 'raw'), False, None)


def test_joint_order_keeps_the_checkpoint_order_unless_mapped():
    assert joint_order(ACTUATORS, []) == (0, 1, 2)
    assert joint_order(ACTUATORS, ['bfoot', 'bthigh', 'bshin']) == (2, 0, 1)


@pytest.mark.parametrize('joints, words', [
    (['bthigh', 'bshin'], "left out ['bfoot']"),
    (['bthigh', 'bshin', 'bfoot', 'tail'], "unknown ['tail']"),
    (['bthigh', 'bshin', 'bshin'], "twice ['bshin']"),
])
def test_a_bad_mapping_is_refused_in_one_line(joints, words):
    with pytest.raises(CommandSetupError) as error:
        joint_order(ACTUATORS, joints)
    assert words in str(error.value) and '\n' not in str(error.value)


def test_default_topics_and_bad_types():
    assert command_topic('float64_array', '') == '/forward_effort_controller/commands'
    assert command_topic('joint_state', '') == '/joint_commands'
    assert command_topic('float64_array', '/x/commands') == '/x/commands'
    with pytest.raises(CommandSetupError, match='command_type'):
        command_topic('trajectory', '')


def test_codec_round_trips_in_declared_order_and_units():
    units = ActuatorUnits.of([-1, -1, -2], [1, 1, 2], [120, 90, 60])
    codec = make_codec(ACTUATORS, ['bfoot', 'bthigh', 'bshin'], 'actuator', units)
    action = np.array([0.5, -0.25, 1.0])
    values = codec.encode(action)
    # bfoot: ctrl = -2 + 2 * 4 / 2 = 2, effort 120; bthigh 0.5 * 120; bshin -0.25 * 90
    assert values == pytest.approx([120.0, 60.0, -22.5])
    decoded, reason = codec.decode(values)
    assert reason is None and decoded == pytest.approx(action)
    assert codec.joint_names == ['bfoot', 'bthigh', 'bshin']


def test_codec_normalised_is_exact_and_clips_and_refuses():
    codec = make_codec(ACTUATORS, [], 'normalised', None)
    action = np.array([0.1, -0.3, 0.7])
    decoded, _ = codec.decode(codec.encode(action))
    assert np.array_equal(decoded, action)
    assert codec.decode([2.0, -5.0, 0.0])[0].tolist() == [1.0, -1.0, 0.0]
    assert codec.decode([0.0, 0.0])[1] == '2 values for the 3 joints'
    assert 'NaN' in codec.decode([0.0, math.nan, 0.0])[1]


def test_actuator_units_need_the_checkpoint_to_record_them():
    with pytest.raises(CommandSetupError, match='records no control range'):
        make_codec(ACTUATORS, [], 'actuator', None)
    with pytest.raises(CommandSetupError, match='command_units'):
        make_codec(ACTUATORS, [], 'volts', None)


def test_only_a_context_free_checkpoint_runs_without_the_reward():
    assert reward_free_refusal('sac', 0, False, False) is None
    assert 'reward in its window rows' in reward_free_refusal('rma', 1, False, False)
    # Trained with context_reward false, psi never reads the column: it runs reward-free.
    assert reward_free_refusal('rma', 8, False, False, reads_reward=False) is None
    assert 'true parameter' in reward_free_refusal('oracle', 1, True, False,
                                                    reads_reward=False)
    assert 'true parameter' in reward_free_refusal('oracle', 1, True, False)
    assert 'observes the reward' in reward_free_refusal('sac', 0, False, True)


def _state(t: int) -> tuple[list[float], list[float]]:
    return [0.1 * t, -0.2 * t], [1.0 + t, 2.0 - t]


def _trajectory(n: int) -> list[tuple[int, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [((t + 1) * 10_000_000, rng.uniform(-1, 1, 2)) for t in range(n)]


def _step_info_windows(steps) -> list[np.ndarray]:
    window = ContextWindow(3, 4, 2)
    assembler = TransitionAssembler(window, LAYOUT)
    out = []
    for t, (stamp, _) in enumerate(steps):
        applied = steps[t - 1][1] if t else []
        assembler.add_step_info(stamp, 0, t, 0.5 * t, applied, False)
        assert assembler.add_joint_state(stamp, JOINTS, *_state(t)) is not None
        out.append(window.arrays()[0].copy())
    return out


def _command_windows(steps, stamped: bool, command_first: bool) -> list[np.ndarray]:
    window = ContextWindow(3, 4, 2)
    assembler = CommandTransitionAssembler(window, LAYOUT)
    out = []
    for t, (stamp, action) in enumerate(steps):
        if t and command_first:   # the command of the state before comes late (a race)
            done = assembler.add_joint_state(stamp, JOINTS, *_state(t))
            assert done == []
            done = assembler.add_command(steps[t - 1][1], steps[t - 1][0] if stamped else None)
        else:
            done = assembler.add_joint_state(stamp, JOINTS, *_state(t))
        assert [r.stamp_ns for r in done] == [stamp]
        out.append(window.arrays()[0].copy())
        if not command_first or t == len(steps) - 1:
            assembler.add_command(action, stamp if stamped else None)
    return out


@pytest.mark.parametrize('stamped', [True, False])
@pytest.mark.parametrize('command_first', [False, True])
def test_command_window_equals_the_step_info_window_but_for_the_reward(stamped, command_first):
    steps = _trajectory(6)
    reference = _step_info_windows(steps)
    got = _command_windows(steps, stamped, command_first)
    reward_column = 4 + 2    # after s (4 values) and a (2)
    for ref, mine in zip(reference, got, strict=True):
        keep = np.ones(ref.shape[1], dtype=bool)
        keep[reward_column] = False
        assert ref[:, keep].tobytes() == mine[:, keep].tobytes()
        filled = np.any(ref != 0, axis=1)
        assert np.all(np.isnan(mine[filled, reward_column]))


def test_a_state_whose_predecessor_got_no_command_starts_an_empty_window():
    window = ContextWindow(3, 4, 2)
    assembler = CommandTransitionAssembler(window, LAYOUT)
    assembler.add_joint_state(10, JOINTS, *_state(0))
    assembler.add_command(np.zeros(2), 10)
    assembler.add_joint_state(20, JOINTS, *_state(1))
    assert window.fill == 1
    assert assembler.add_joint_state(30, JOINTS, *_state(2)) == []   # waits for 20's command
    done = assembler.add_joint_state(40, JOINTS, *_state(3))        # 20's never came
    assert [r.stamp_ns for r in done] == [30] and window.fill == 0 and assembler.gaps == 1
    assembler.add_command(np.ones(2), 30)
    assert window.fill == 1


def test_a_restarted_clock_starts_over():
    window = ContextWindow(3, 4, 2)
    assembler = CommandTransitionAssembler(window, LAYOUT)
    for stamp in (10, 20):
        assembler.add_joint_state(stamp, JOINTS, *_state(0))
        assembler.add_command(np.zeros(2))
    assert window.fill == 1
    done = assembler.add_joint_state(10, JOINTS, *_state(0))
    assert [r.stamp_ns for r in done] == [10] and window.fill == 0 and assembler.restarts == 1


def test_a_stand_in_reward_lets_a_reward_reading_context_run():
    assert reward_free_refusal('rma', 1, False, False, reward_prior=0.33) is None
    # ... but never a privileged one, nor one that observes the reward
    assert reward_free_refusal('oracle', 1, True, False, reward_prior=0.33) is not None
    assert reward_free_refusal('zeus', 1, False, True, reward_prior=0.33) is not None
    window = ContextWindow(3, 4, 2)
    assembler = CommandTransitionAssembler(window, LAYOUT, reward=0.25)
    assembler.add_joint_state(10, JOINTS, *_state(0))
    assembler.add_command(np.ones(2))
    assembler.add_joint_state(20, JOINTS, *_state(1))
    assert window.arrays()[0][0, 6] == np.float32(0.25)


def test_the_shipped_rma_knows_its_training_mean_of_the_reward():
    from conftest import REPO
    from zeus_ros.deploy.inference import InferenceModel
    rma = InferenceModel.load(REPO / 'weights' / 'cheetah-run-wide-friction-rma-raw-150k')
    sac = InferenceModel.load(REPO / 'weights' / 'cheetah-run-wide-friction-sac-150k')
    assert 0.0 < rma.reward_prior() < 1.0    # cheetah-run's reward lies in [0, 1]
    assert sac.reward_prior() is None


def test_the_decimator_keeps_one_state_per_control_period():
    from zeus_ros.ros.timing import Decimator
    ms = 1_000_000
    twice = Decimator(10 * ms)
    kept = [t for t in range(0, 100 * ms, 5 * ms) if twice.accept(t)]
    assert kept == list(range(0, 100 * ms, 10 * ms)) and twice.skipped == 10
    half = Decimator(10 * ms)
    assert all(half.accept(t) for t in range(0, 200 * ms, 20 * ms))   # slower: all kept
    jitter = Decimator(10 * ms)
    assert [jitter.accept(t * ms) for t in (0, 9, 12, 19, 21)] == [True, True, False, True,
                                                                    False]
    assert jitter.accept(3 * ms), 'a clock that went back is a restart: kept'
    every = Decimator(0)
    assert all(every.accept(t) for t in (5, 6, 7))


def test_latency_percentiles():
    from zeus_ros.ros.timing import LatencyWindow
    window = LatencyWindow()
    assert window.report()['latency_p50_ms'] == 'nan'
    for ms in range(1, 101):
        window.record(ms / 1e3)
    report = window.report()
    assert float(report['latency_p50_ms']) == pytest.approx(50.5)
    assert float(report['latency_p99_ms']) == pytest.approx(99.01)
