"""The sim node's ~/pause, ~/resume and ~/step services (the stepping rules are SimStepper's).

As Gazebo's pause and step: `~/pause` stops the simulation (no state is
published, /clock stands still), `~/resume` runs it on, `~/step` (a paused
sim only) runs exactly N control steps with the controllers in the loop and
pauses again; its answer carries every state published meanwhile, sent by
the loop once the last step is taken. A pause or resume while a step is
under way ends it there; its answer says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Callable, Protocol, TYPE_CHECKING

from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Step

from zeus_ros.ros.deferred import DeferredService

if TYPE_CHECKING:
    from rclpy.node import Node

STEP_MAX = 10_000   # ten walker episodes; an answer holds every state


def step_refusal(steps: int, paused: bool, under_way: int | None) -> str | None:
    """Why a step request is refused, or None (`under_way`: steps left of one taking place)."""
    if not 1 <= steps <= STEP_MAX:
        return f'steps must be in [1, {STEP_MAX}], got {steps}'
    if under_way is not None:
        return f'a step is under way ({under_way} steps to go): wait for its answer'
    if not paused:
        return 'the sim is running: call ~/pause first'
    return None


class _Episode(Protocol):
    @property
    def step_count(self) -> int: ...


class Stepping(Protocol):
    """What the services read and drive of the sim's stepper: a sim_node.stepper.SimStepper.

    A protocol of its own: the plumbing imports none of the simulation's
    stepping code (test_layers), not even for a type; the sim node hands its
    stepper in.
    """

    @property
    def env(self) -> _Episode: ...

    @property
    def episode(self) -> int: ...

    @property
    def budget(self) -> int | None: ...

    @property
    def paused(self) -> bool: ...

    @property
    def counters(self) -> dict[str, int]: ...

    def pause(self, now: float) -> bool: ...

    def resume(self, now: float) -> bool: ...

    def step(self, steps: int, now: float) -> None: ...


@dataclass
class StepCall:
    """A ~/step request being carried out: its response, filled as the states go out."""

    response: Step.Response
    asked: int
    states: list[JointState] = field(default_factory=list)
    infos: list[StepInfo] = field(default_factory=list)


class PauseServices:
    """~/pause, ~/resume and ~/step on `node`, over its `stepper`."""

    def __init__(self, node: Node, stepper: Stepping,
                 clock: Callable[[], float] = time.monotonic):
        self.node, self.stepper, self.clock = node, stepper, clock
        node.create_service(Trigger, '~/pause', self.pause_callback)
        node.create_service(Trigger, '~/resume', self.resume_callback)
        self.step_service = DeferredService(node, Step, '~/step', self.step_callback)
        self.call: StepCall | None = None
        self._taken_before = 0

    def _where(self) -> str:
        return f'episode {self.stepper.episode} step {self.stepper.env.step_count}'

    def pause_callback(self, _request: Trigger.Request,
                       response: Trigger.Response) -> Trigger.Response:
        response.success = True
        if self.stepper.pause(self.clock()):   # from running, or from a step under way
            response.message = f'paused at {self._where()}'
            self.node.get_logger().info(response.message)
            self._end_call('interrupted by ~/pause')
        else:
            response.message = f'already paused at {self._where()}'
        return response

    def resume_callback(self, _request: Trigger.Request,
                        response: Trigger.Response) -> Trigger.Response:
        response.success = True
        self._end_call('interrupted by ~/resume')
        if self.stepper.resume(self.clock()):
            response.message = f'resumed at {self._where()}'
            self.node.get_logger().info(response.message)
        else:
            response.message = f'already running ({self._where()})'
        return response

    def step_callback(self, request: Step.Request, response: Step.Response) -> Step.Response:
        under_way = None if self.call is None else self.stepper.budget
        refusal = step_refusal(request.steps, self.stepper.paused, under_way)
        if refusal is not None:
            response.success, response.message = False, f'step refused: {refusal}'
            self.node.get_logger().warning(response.message)
            return response
        self.call = StepCall(response, request.steps)
        self._taken_before = self.stepper.counters['steps']
        self.step_service.defer(response)
        self.stepper.step(request.steps, self.clock())
        return response

    def record(self, joint_state: JointState, info: StepInfo) -> None:
        """Keep a published state for the step under way, if any."""
        if self.call is not None:
            self.call.states.append(joint_state)
            self.call.infos.append(info)

    def after_step(self) -> None:
        """Answer the step under way once its last step is taken (call after each stepping)."""
        if self.call is not None and self.stepper.paused:
            self._end_call(None)

    def _end_call(self, interrupted: str | None) -> None:
        call, self.call = self.call, None
        if call is None:
            return
        taken = self.stepper.counters['steps'] - self._taken_before
        response = call.response
        response.steps_taken, response.success = taken, interrupted is None
        response.joint_states, response.step_infos = call.states, call.infos
        response.message = (f'{taken} steps, now at {self._where()}' if interrupted is None
                            else f'{interrupted} after {taken} of {call.asked} steps')
        self.step_service.answer(response)
