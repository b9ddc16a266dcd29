"""Requests that must not be carried out twice (a sweep, a marking job) but may need sending twice.

A server that has just (re)started may not yet know a client's reader and then drops its answer:
DDS discovery is not symmetric, and Fast DDS gives up on an answer after 100 ms. The client cannot
tell a lost answer from a slow one, so it sends the request again; the request carries the client's
id (``unique_identifier_msgs/UUID``), and the server answers a repeated id with the first answer
instead of starting a second sweep or marking the plate twice.
"""
from __future__ import annotations

import uuid
from collections import OrderedDict
from typing import Any, Awaitable, Callable

from rclpy.task import Future
from unique_identifier_msgs.msg import UUID

NO_ID = bytes(16)
# A request with an id is sent again after this long without an answer (then after twice as long...):
# a repeat costs the server only its transport, and a sweep or marking job starts within a second.
RESEND_WITH_ID_AFTER_S = 2.0


def new_request_id() -> UUID:
    """Return a fresh random id (UUID version 4) for one request and its repeats."""
    return UUID(uuid=list(uuid.uuid4().bytes))


def id_key(request_id: UUID) -> bytes:
    """Return the 16 bytes of ``request_id``: the key under which its answer is kept."""
    return bytes(bytearray(request_id.uuid))


class AnsweredRequests:
    """The answers of a server's last ``keep`` requests that carried an id.

    A repeat of a request still being served waits for that first service's answer. A request whose
    service raised is forgotten (its repeat runs again): only answers are kept.
    """

    def __init__(self, keep: int = 32) -> None:
        if keep < 1:
            raise ValueError(f"keep must be at least 1, got {keep}")
        self.keep = keep
        self.answers: OrderedDict[bytes, Future] = OrderedDict()

    def _remember(self, key: bytes) -> Future:
        answer = Future()
        self.answers[key] = answer
        while len(self.answers) > self.keep:
            self.answers.popitem(last=False)
        return answer

    def answer(self, request_id: UUID, serve: Callable[[], Any]) -> Any:
        """Return ``serve()``'s answer, or the kept answer of an earlier request with the same id.

        For handlers that run one at a time (a mutually exclusive callback group): a repeat never
        finds its first request still being served.
        """
        key = id_key(request_id)
        if key == NO_ID:
            return serve()
        kept = self.answers.get(key)
        if kept is not None and kept.done():
            return kept.result()
        answer = self._remember(key)
        try:
            answer.set_result(serve())
        except BaseException:
            self.answers.pop(key, None)
            raise
        return answer.result()

    async def answer_async(self, request_id: UUID, serve: Callable[[], Awaitable[Any]]) -> Any:
        """Answer as :meth:`answer` does, for coroutine handlers that interleave.

        As :meth:`answer`, for coroutine handlers that interleave: a repeat that arrives while its
        first request is being served awaits that service's answer.
        """
        key = id_key(request_id)
        if key == NO_ID:
            return await serve()
        kept = self.answers.get(key)
        if kept is not None:
            return await kept
        answer = self._remember(key)
        try:
            answer.set_result(await serve())
        except BaseException as error:
            self.answers.pop(key, None)
            answer.set_exception(error)   # a repeat waiting for this answer gets the error too
            answer.exception()            # raised to the caller below: not an error nobody saw
            raise
        return answer.result()
