"""Live parameter swaps built off the control loop: a FIFO of values and a worker thread.

A swap has a slow half, compiling the model of the new value from the
family's edited MJCF (`ParamEnv.prepare_values`: 2-5 ms, 1-2 ms of it Python),
and a fast half, writing that model into the live one in place at a step
boundary (`ParamEnv.apply_prepared`: ~0.2 ms). The slow half used to rebuild
the whole Physics on the loop thread (~70 ms, the skybox texture included), and
every realtime tick around a swap was late (issue #17.3). Here a worker thread
compiles the value at the head of the queue while the loop goes on (MuJoCo's
compiler releases the GIL); the loop only takes a built head.

A value is the family's value tuple (one number for most families, the
goal's x and y for Sawyer-Peg-v0), in the family's `param_names` order.
Every accepted value takes effect, in the order requested: the loop takes at
most one value per step boundary, so each is in force for at least one step
(a reset may put several into force before its first state). The queue holds
`capacity` values; a request beyond that is refused by the caller with
`full_reason` (the answer says so), rather than growing a backlog of values
that would take effect long after they were asked for.
"""

from __future__ import annotations

from collections import deque
import threading
from typing import Callable

from sim_node.family_env import PreparedValues, Values

# At one value per step, the last of 8 is in force 8 steps (0.08-0.2 s) after it was asked
# for; a flood beyond that is refused, not queued into stale values.
SWAP_CAPACITY = 8


def format_values(values: Values) -> str:
    """'0.4' for one value, '(0.6, 0.07)' for several: as a log line or an answer says it."""
    if len(values) == 1:
        return f'{values[0]:g}'
    return '(' + ', '.join(f'{v:g}' for v in values) + ')'


class SwapQueue:
    """Parameter values waiting to be put into force, the head's physics built by a worker.

    `prepare(values) -> PreparedValues` runs on the worker thread and must not
    touch the live env (`FamilyEnv.prepare_values` does not). Every other method
    is for the loop's side; they may be called from any thread.
    """

    def __init__(self, prepare: Callable[[Values], PreparedValues],
                 capacity: int = SWAP_CAPACITY):
        self.capacity = capacity
        self._prepare = prepare
        self._cond = threading.Condition()
        self._values: deque[Values] = deque()
        self._built: PreparedValues | None = None  # the head's, once built
        self._error: BaseException | None = None
        self._generation = 0      # bumped by clear(): a build under way is then stale
        self._retired: list = []  # used or dropped builds, freed by the worker
        self._closed = False
        self._worker: threading.Thread | None = None   # started by the first push

    # -- the loop's side --------------------------------------------------------
    @property
    def values(self) -> tuple[Values, ...]:
        """The values waiting, head first."""
        with self._cond:
            return tuple(self._values)

    def __len__(self) -> int:
        with self._cond:
            return len(self._values)

    def full_reason(self) -> str | None:
        """Why a new value cannot be queued now, or None."""
        with self._cond:
            if len(self._values) < self.capacity:
                return None
            waiting = ', '.join(format_values(v) for v in self._values)
        return (f'{self.capacity} values are already waiting to be put into force '
                f'({waiting}); set it again once they are')

    def push(self, values: Values) -> None:
        """Queue a value tuple (the caller checked `full_reason`)."""
        with self._cond:
            self._values.append(tuple(float(v) for v in values))
            if self._worker is None:
                # Started here, by a thread of the running node, the worker inherits its
                # scheduler: SCHED_FIFO with thread_priority. Under the normal scheduler,
                # descheduled by a busy machine while it held the GIL, it stalled the FIFO
                # loop thread for 67 ms once (priority inversion).
                self._worker = threading.Thread(target=self._run, name='swap-builder',
                                                daemon=True)
                self._worker.start()
            self._cond.notify_all()

    def take_ready(self) -> PreparedValues | None:
        """Pop the head if its physics is built; never waits."""
        with self._cond:
            return self._pop_built()

    def take_waiting(self) -> PreparedValues | None:
        """Pop the head, waiting for its build; None if nothing is queued."""
        with self._cond:
            self._cond.wait_for(lambda: not self._values or self._built is not None
                                or self._error is not None or self._closed)
            return self._pop_built()

    def clear(self) -> tuple[Values, ...]:
        """Drop every waiting value (none will take effect); return them."""
        with self._cond:
            dropped = tuple(self._values)
            self._values.clear()
            self._retire(self._built)
            self._built = None
            self._generation += 1
            return dropped

    def retire(self, prepared: PreparedValues) -> None:
        """Hand back a value put into force, for the worker to free its compiled model."""
        with self._cond:
            self._retire(prepared)
            self._cond.notify_all()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the worker (a build under way is finished first, then dropped)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            worker = self._worker
        if worker is not None:
            worker.join(timeout)

    def _pop_built(self) -> PreparedValues | None:
        if self._error is not None:
            error, self._error = self._error, None
            self._values.popleft()   # that value cannot be built: it will never take effect
            self._cond.notify_all()
            raise error
        built, self._built = self._built, None
        if built is not None:
            self._values.popleft()
            self._cond.notify_all()  # the worker starts on the next head
        return built

    def _retire(self, prepared: PreparedValues | None) -> None:
        if prepared is not None:
            self._retired.append(prepared)

    # -- the worker's side ------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(self._has_work)
                if self._closed:
                    return
                retired, self._retired = self._retired, []
                job = self._next_job()
            del retired  # the last references: the old models are freed here, not on the loop
            if job is not None:
                self._build(*job)

    def _has_work(self) -> bool:
        return self._closed or bool(self._retired) or self._next_job() is not None

    def _next_job(self) -> tuple[int, Values] | None:
        if self._values and self._built is None and self._error is None:
            return self._generation, self._values[0]
        return None

    def _build(self, generation: int, value: Values) -> None:
        try:
            prepared, error = self._prepare(value), None
        # Whatever the build raises is handed, unchanged, to the take that wanted it.
        except Exception as failure:  # noqa: BLE001
            prepared, error = None, failure
        with self._cond:
            if generation != self._generation or not self._values or self._values[0] != value:
                self._retire(prepared)   # cleared meanwhile
                return
            self._built, self._error = prepared, error
            self._cond.notify_all()
