"""SimStepper and SwapQueue without ROS: the sim node's stepping rules, driven call by call.

No DDS, no processes: a real ParamEnv, a list for the published states, a fake
clock, and (for the stepper) a swap queue whose builds finish when the test says.
"""

import threading

import numpy as np
import pytest
from sim_node.env import ParamEnv
from sim_node.stepper import SimStepper, SWAP_POLL_S
from sim_node.swaps import SwapQueue

FAMILY = 'walker-walk-v0'
PERIOD = 0.025      # walker's control period
TIMEOUT = 0.5


class FakeClock:
    """The stepper's clock: stands still until the test moves it."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class GatedSwaps:
    """SwapQueue's interface; a value's physics is built when the test calls `finish()`."""

    def __init__(self, env, capacity=3):
        self.env, self.capacity = env, capacity
        self.waiting, self.built, self.retired = [], [], []

    @property
    def values(self):
        return tuple(self.waiting)

    def __len__(self):
        return len(self.waiting)

    def full_reason(self):
        return 'full' if len(self.waiting) >= self.capacity else None

    def push(self, value):
        self.waiting.append(value)

    def finish(self, count=1):
        for value in self.waiting[len(self.built):len(self.built) + count]:
            self.built.append(self.env.prepare_values(value))

    def take_ready(self):
        if not self.built:
            return None
        self.waiting.pop(0)
        return self.built.pop(0)

    def take_waiting(self):
        if self.waiting and not self.built:
            self.finish()
        return self.take_ready()

    def clear(self):
        dropped, self.waiting, self.built = tuple(self.waiting), [], []
        return dropped

    def retire(self, physics):
        self.retired.append(physics)


@pytest.fixture
def rig():
    """Make a walker stepper in lockstep at friction 1.0, seed 3, its first state published."""
    env = ParamEnv(FAMILY, 1.0, seed=3)
    clock, published = FakeClock(), []
    swaps = GatedSwaps(env)
    stepper = SimStepper(env, published.append, swaps, clock=clock, seed=3)
    stepper.configure('lockstep', TIMEOUT, 1.0, clock.now)
    stepper.start()
    return stepper, published, clock, swaps


def realtime(rig):
    stepper, published, clock, swaps = rig
    stepper.configure('realtime', TIMEOUT, 1.0, clock.now)
    return stepper, published, clock, swaps


def actions(n, seed=0):
    return np.random.RandomState(seed).uniform(-1, 1, (n, 6))


def answer(stepper, published, clock, action, delay=0.001):
    """Answer the newest published state `delay` seconds after it went out."""
    clock.now += delay
    return stepper.on_command(published[-1].stamp_ns, action, clock.now)


# -- lockstep ---------------------------------------------------------------------
def test_lockstep_steps_once_per_answer_exactly_as_in_process(rig):
    stepper, published, clock, _ = rig
    twin = ParamEnv(FAMILY, 1.0, seed=3)
    twin.reset(seed=3)
    assert published[0].step == 0 and published[0].stamp_ns == stepper.dt_ns
    for action in actions(20):
        outcome = answer(stepper, published, clock, action)
        twin.step(action)
        assert outcome.stepped and outcome.latency_s == pytest.approx(0.001)
        np.testing.assert_array_equal(published[-1].positions, twin.joint_positions())
        np.testing.assert_array_equal(published[-1].applied_action, np.clip(action, -1, 1))
    assert [s.step for s in published] == list(range(21))
    assert [s.stamp_ns for s in published] == [stepper.dt_ns * (i + 1) for i in range(21)]
    assert stepper.counters['answered'] == stepper.counters['steps'] == 20


def test_stale_commands_are_counted_and_never_step(rig):
    stepper, published, clock, _ = rig
    old = published[-1].stamp_ns
    answer(stepper, published, clock, np.zeros(6))
    for stamp in (old, old + 12345, 0):          # answered already, never published, zero
        outcome = stepper.on_command(stamp, np.ones(6), clock.now)
        assert outcome.stale and not outcome.stepped
    assert stepper.counters['stale'] == 3 and len(published) == 2


def test_lockstep_timeout_steps_on_a_zero_action(rig):
    stepper, published, clock, _ = rig
    sent = clock.now
    assert stepper.deadline() == pytest.approx(sent + TIMEOUT)
    assert not stepper.due(sent + TIMEOUT - 1e-6) and stepper.due(sent + TIMEOUT)
    outcome = stepper.on_deadline(sent + TIMEOUT)
    assert outcome.timed_out and outcome.stepped
    assert stepper.counters['timeouts'] == 1
    np.testing.assert_array_equal(published[-1].applied_action, np.zeros(6))
    # The late answer to the state that timed out is stale now.
    assert stepper.on_command(published[-2].stamp_ns, np.ones(6), clock.now).stale


def test_a_rejected_command_is_counted_and_answered_with_a_zero_action(rig):
    stepper, published, clock, _ = rig
    outcome = answer(stepper, published, clock, None)
    assert outcome.stepped and stepper.counters['rejected'] == 1
    np.testing.assert_array_equal(published[-1].applied_action, np.zeros(6))


def test_the_end_of_an_episode_starts_the_next_and_nothing_awaits_the_last_state():
    env = ParamEnv(FAMILY, 1.0, seed=0, episode_steps=3)
    clock, published = FakeClock(), []
    stepper = SimStepper(env, published.append, GatedSwaps(env), clock=clock)
    stepper.start()
    for _ in range(3):
        answer(stepper, published, clock, np.zeros(6))
    last, first = published[-2], published[-1]
    assert last.truncated and (last.episode, last.step) == (0, 3)
    assert (first.episode, first.step) == (1, 0)
    assert stepper.awaited_ns == first.stamp_ns


def test_an_instability_restarts_the_episode_and_is_reported(rig, monkeypatch):
    stepper, published, clock, _ = rig
    from sim_node.layout import StepResult
    env = stepper.env
    real_step = env.step

    def unstable(action):
        real_step(action)
        return StepResult(env.observation(), 0.0, False, True, instability='mjWARN_BADQACC')
    monkeypatch.setattr(env, 'step', unstable)
    outcome = answer(stepper, published, clock, np.zeros(6))
    assert outcome.instability == 'mjWARN_BADQACC'
    assert stepper.counters['instabilities'] == 1
    assert (published[-1].episode, published[-1].step) == (1, 0)


# -- realtime ---------------------------------------------------------------------
def test_realtime_ticks_on_an_absolute_schedule(rig):
    stepper, published, clock, _ = realtime(rig)
    start = clock.now
    assert stepper.deadline() == pytest.approx(start + PERIOD)
    # Ticks a little late do not push the schedule: tick n stays at start + n x period.
    for n in range(1, 6):
        outcome = stepper.on_deadline(start + n * PERIOD + 0.0003)
        assert outcome.tick_late_s == pytest.approx(0.0003) and outcome.stepped
        assert stepper.deadline() == pytest.approx(start + (n + 1) * PERIOD)
    # A tick more than a period late is a missed deadline; the schedule restarts from it.
    late = start + 6 * PERIOD + 1.5 * PERIOD
    stepper.on_deadline(late)
    assert stepper.counters['late_ticks'] == 1
    assert stepper.deadline() == pytest.approx(late + PERIOD)
    assert stepper.counters['steps'] == 6


def test_a_tick_before_the_previous_states_command_is_unanswered(rig):
    stepper, published, clock, _ = realtime(rig)
    outcome = stepper.on_deadline(stepper.deadline())
    assert not outcome.answered                  # nobody answered the first state
    answer(stepper, published, clock, np.full(6, 0.5))
    outcome = stepper.on_deadline(stepper.deadline())
    assert outcome.answered
    np.testing.assert_array_equal(published[-1].applied_action, np.full(6, 0.5))
    outcome = stepper.on_deadline(stepper.deadline())   # its state got no answer
    assert not outcome.answered
    assert stepper.counters['answered'] == 1 and stepper.counters['steps'] == 3


def test_realtime_steps_on_the_latest_command_until_it_is_too_old(rig):
    stepper, published, clock, _ = realtime(rig)
    for value in (0.2, 0.7):                     # the later command wins
        stepper.on_command(published[-1].stamp_ns, np.full(6, value), clock.now)
    outcome = stepper.on_deadline(stepper.deadline())
    np.testing.assert_array_equal(published[-1].applied_action, np.full(6, 0.7))
    assert outcome.latency_s == pytest.approx(PERIOD)      # the command's age
    # Older than the timeout: the tick applies a zero action instead.
    stepper.next_tick = clock.now + TIMEOUT + 0.01
    stepper.on_deadline(stepper.next_tick)
    np.testing.assert_array_equal(published[-1].applied_action, np.zeros(6))


def test_mode_switches_restart_the_schedule_and_lockstep_waits_again(rig):
    stepper, published, clock, _ = realtime(rig)
    stepper.on_deadline(stepper.deadline())
    clock.now += 5.0
    stepper.configure('lockstep', TIMEOUT, 1.0, clock.now)
    # Lockstep: nothing happens before the answer or the timeout of the last state.
    assert stepper.deadline() == pytest.approx(stepper.awaited_since + TIMEOUT)
    answer(stepper, published, clock, np.zeros(6))
    assert stepper.counters['steps'] == 2
    stepper.configure('realtime', TIMEOUT, 2.0, clock.now)
    assert stepper.deadline() == pytest.approx(clock.now + PERIOD / 2)   # real_time_factor 2
    with pytest.raises(ValueError, match='mode must be one of'):
        stepper.configure('fast', TIMEOUT, 1.0, clock.now)


# -- swaps at step boundaries -------------------------------------------------------
def test_realtime_never_waits_for_a_build_and_swaps_at_the_first_tick_after_it(rig):
    stepper, published, clock, swaps = realtime(rig)
    assert stepper.request_swap((0.4,))
    for _ in range(3):                           # building: the ticks go on at 1.0
        outcome = stepper.on_deadline(stepper.deadline())
        assert outcome.stepped and not outcome.swaps
    assert [s.param_values[0] for s in published[-3:]] == [1.0] * 3
    swaps.finish()
    outcome = stepper.on_deadline(stepper.deadline())
    assert [(s.old, s.new) for s in outcome.swaps] == [((1.0,), (0.4,))]
    assert outcome.swaps[0].where == 'episode 0 step 3'
    assert published[-1].param_values[0] == 0.4 and len(swaps.retired) == 1


def test_lockstep_holds_a_step_until_the_swap_is_built(rig):
    stepper, published, clock, swaps = rig
    stepper.request_swap((0.4,))
    stamp = published[-1].stamp_ns
    outcome = answer(stepper, published, clock, np.full(6, 0.3))
    assert outcome.waiting_for_swap and not outcome.stepped and len(published) == 1
    # The held step polls; the command it holds answered its state (a repeat is stale).
    assert stepper.deadline() == pytest.approx(clock.now + SWAP_POLL_S)
    assert stepper.on_command(stamp, np.ones(6), clock.now).stale
    clock.now += SWAP_POLL_S
    assert stepper.on_deadline(clock.now).waiting_for_swap
    swaps.finish()
    clock.now += SWAP_POLL_S
    outcome = stepper.on_deadline(clock.now)
    assert outcome.stepped and [s.new for s in outcome.swaps] == [(0.4,)]
    assert published[-1].param_values[0] == 0.4 and published[-1].step == 1
    np.testing.assert_array_equal(published[-1].applied_action, np.full(6, 0.3))
    assert stepper.counters['timeouts'] == 0


def test_queued_values_take_effect_one_per_step_in_order(rig):
    stepper, published, clock, swaps = rig
    for value in (0.4, 1.2, 0.8):
        assert stepper.swap_refusal((value,)) is None and stepper.request_swap((value,))
    assert stepper.swap_refusal((2.0,)) == 'full'            # capacity 3
    assert stepper.swap_refusal((0.8,)) is None               # what it will have anyway
    assert not stepper.request_swap((0.8,))
    swaps.finish(3)
    for _ in range(4):
        answer(stepper, published, clock, np.zeros(6))
    assert [s.param_values[0] for s in published] == [1.0, 0.4, 1.2, 0.8, 0.8]
    assert stepper.counters['swaps'] == 3


def test_a_reset_puts_every_queued_value_into_force_before_its_first_state(rig):
    stepper, published, clock, swaps = rig
    answer(stepper, published, clock, np.zeros(6))
    stepper.request_swap((0.4,))
    stepper.request_swap((1.5,))
    stepper.pending_seed = 9
    outcome = stepper.reset()                     # waits for the builds
    assert [(s.new, s.where) for s in outcome.swaps] == [
        ((0.4,), 'the start of episode 1'), ((1.5,), 'the start of episode 1')]
    first = published[-1]
    assert (first.episode, first.step, first.param_values[0]) == (1, 0, 1.5)
    assert stepper.stream_seed == 9 and stepper.pending_seed is None
    twin = ParamEnv(FAMILY, 1.5, seed=0)
    twin.reset(seed=9)
    np.testing.assert_array_equal(first.positions, twin.joint_positions())


def test_switching_to_realtime_hands_a_held_command_to_the_ticks(rig):
    stepper, published, clock, _ = rig
    stepper.request_swap((0.4,))
    answer(stepper, published, clock, np.full(6, 0.6))     # held for the build
    stepper.configure('realtime', TIMEOUT, 1.0, clock.now)
    stepper.on_deadline(stepper.deadline())                 # still building: old physics
    assert published[-1].param_values[0] == 1.0
    np.testing.assert_array_equal(published[-1].applied_action, np.full(6, 0.6))


# -- with the real worker thread ------------------------------------------------------
def test_a_swap_through_the_worker_equals_set_values_in_process():
    """The bit-exact rule: a swap at step 10 gives the trajectory of env.set_values at step 10."""
    sequence = actions(30, seed=4)
    twin = ParamEnv(FAMILY, 1.0, seed=2)
    twin.reset(seed=2)
    expected = []
    for i, action in enumerate(sequence):
        if i == 10:
            twin.set_values((0.4,))
        twin.step(action)
        expected.append(twin.joint_positions())
    env = ParamEnv(FAMILY, 1.0, seed=2)
    clock, published = FakeClock(), []
    swaps = SwapQueue(env.prepare_values)
    try:
        stepper = SimStepper(env, published.append, swaps, clock=clock, seed=2)
        stepper.start()
        for i, action in enumerate(sequence):
            if i == 10:
                stepper.request_swap((0.4,))
            outcome = answer(stepper, published, clock, action)
            while outcome.waiting_for_swap:            # lockstep holds the step for the build
                threading.Event().wait(0.005)
                outcome = stepper.on_deadline(clock.now)
    finally:
        swaps.close()
    np.testing.assert_array_equal([s.positions for s in published[1:]], expected)
    assert [s.param_values[0] for s in published[1:]] == [1.0] * 10 + [0.4] * 20


def test_the_swap_queue_builds_on_its_worker_in_order():
    env = ParamEnv(FAMILY, 1.0, seed=0)
    built_on = []

    def prepare(value):
        built_on.append(threading.get_ident())
        return env.prepare_values(value)
    swaps = SwapQueue(prepare, capacity=2)
    try:
        assert swaps.take_ready() is None and swaps.take_waiting() is None  # nothing queued
        swaps.push((0.4,))
        swaps.push((1.2,))
        assert 'already waiting' in swaps.full_reason() and '0.4, 1.2' in swaps.full_reason()
        assert [swaps.take_waiting().values, swaps.take_waiting().values] == [(0.4,), (1.2,)]
        assert len(set(built_on)) == 1 and threading.get_ident() not in built_on
        swaps.push((0.5,))
        swaps.push((0.6,))
        assert swaps.clear() == ((0.5,), (0.6,)) and len(swaps) == 0
        assert swaps.take_waiting() is None
    finally:
        swaps.close()


def test_a_value_that_cannot_be_built_raises_to_the_loop_and_leaves_the_queue():
    def prepare(value):
        raise RuntimeError(f'cannot compile {value}')
    swaps = SwapQueue(prepare)
    try:
        swaps.push((0.4,))
        with pytest.raises(RuntimeError, match=r'cannot compile \(0.4,\)'):
            swaps.take_waiting()
        assert len(swaps) == 0
    finally:
        swaps.close()


# -- pause, resume, step (~/pause, ~/resume, ~/step) ------------------------------
def test_paused_lockstep_holds_the_answer_and_steps_on_it_at_the_next_step(rig):
    stepper, published, clock, _ = rig
    assert stepper.pause(clock.now) and not stepper.pause(clock.now)
    assert stepper.deadline() is None            # no timeout while paused
    outcome = answer(stepper, published, clock, np.full(6, 0.3))
    assert not outcome.stepped and len(published) == 1
    clock.now += 10 * TIMEOUT                     # paused far past the timeout: no zero action
    assert stepper.deadline() is None
    stepper.step(1, clock.now)
    assert stepper.due(clock.now)
    assert stepper.on_deadline(clock.now).stepped
    np.testing.assert_array_equal(published[-1].applied_action, np.full(6, 0.3))
    assert stepper.paused and stepper.deadline() is None
    assert stepper.counters['timeouts'] == 0


def test_step_n_takes_exactly_n_steps_then_pauses_and_resume_runs_on(rig):
    stepper, published, clock, _ = rig
    stepper.pause(clock.now)
    with pytest.raises(ValueError):
        stepper.step(0, clock.now)
    stepper.step(3, clock.now)
    for action in actions(5):
        answer(stepper, published, clock, action)
    assert [s.step for s in published] == [0, 1, 2, 3] and stepper.paused
    assert stepper.resume(clock.now) and not stepper.resume(clock.now)
    with pytest.raises(ValueError):
        stepper.step(2, clock.now)                # running: nothing to step
    stepper.on_deadline(clock.now)                # the 4th answer, held while paused
    assert published[-1].step == 4 and stepper.budget is None
    np.testing.assert_array_equal(published[-1].applied_action, actions(5)[3])


def test_paused_time_does_not_count_towards_the_lockstep_timeout(rig):
    stepper, published, clock, _ = rig
    clock.now += 0.4                              # 0.1 s of the timeout left
    stepper.pause(clock.now)
    clock.now += 5.0
    stepper.resume(clock.now)
    assert stepper.deadline() == pytest.approx(clock.now + 0.1)


def test_paused_realtime_does_not_tick_and_steps_at_once_on_the_latest_command(rig):
    stepper, published, clock, _ = realtime(rig)
    stepper.on_command(published[-1].stamp_ns, np.full(6, 0.5), clock.now)
    stepper.pause(clock.now)
    assert stepper.deadline() is None
    clock.now += 10.0                             # older than the timeout, but paused
    stepper.step(2, clock.now)
    assert stepper.deadline() == clock.now        # the first step right away
    stepper.on_deadline(clock.now)
    np.testing.assert_array_equal(published[-1].applied_action, np.full(6, 0.5))
    stepper.on_deadline(stepper.deadline())
    assert stepper.paused and len(published) == 3 and stepper.deadline() is None


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_a_value_set_while_paused_is_in_force_at_the_next_step(rig, mode):
    stepper, published, clock, swaps = realtime(rig) if mode == 'realtime' else rig
    stepper.pause(clock.now)
    stepper.request_swap((0.4,))                  # not built yet: the next step waits for it
    stepper.step(1, clock.now)
    if mode == 'lockstep':                        # waits for the build, as ever
        answer(stepper, published, clock, np.zeros(6))
        swaps.finish()
        stepper.on_deadline(stepper.deadline())
    else:                                         # waits for the build this once
        stepper.on_deadline(clock.now)
    assert [s.param_values[0] for s in published] == [1.0, 0.4]
