"""A service whose answer may come after its callback returned, from another callback.

rclpy answers a request with what the callback returns. `~/step` can only
answer once the steps are taken, by the control loop: blocking the callback
would block that loop (spin_loop runs every callback under one lock), and an
async callback is polled by rclpy's executor at every spin, a busy wait on
the loop's two cores. So the callback marks its response `defer`red and
returns it; the executor then hands it to the service's send_response with
the request's header, which is kept; `answer(response)` sends it later.
"""

from __future__ import annotations

from typing import Callable, TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.node import Node


class DeferredService:
    """`node.create_service`, with responses that `defer` holds until `answer`."""

    def __init__(self, node: Node, srv_type: type, name: str, callback: Callable, **options):
        self.service = node.create_service(srv_type, name, callback, **options)
        self._send = self.service.send_response
        # The executor calls this with each returned response and its request's header.
        self.service.send_response = self._send_or_keep
        self._waiting: dict[int, list] = {}   # id(response) -> [response, header, answered]

    # A response is the service type's Response message, only kept and passed on here.
    def defer(self, response: object) -> None:
        """Keep `response` (returned by the callback) until `answer(response)`."""
        self._waiting[id(response)] = [response, None, False]

    def answer(self, response: object) -> None:
        """Send a deferred response (at once, or as soon as its header is known)."""
        entry = self._waiting[id(response)]
        if entry[1] is None:
            entry[2] = True   # the executor has not handed its header over yet
            return
        del self._waiting[id(response)]
        self._send(response, entry[1])

    # `header`: the request's id as rclpy's executor hands it over, kept for send_response.
    def _send_or_keep(self, response: object, header: object) -> None:
        entry = self._waiting.get(id(response))
        if entry is None:
            self._send(response, header)
            return
        entry[1] = header
        if entry[2]:
            self.answer(response)
