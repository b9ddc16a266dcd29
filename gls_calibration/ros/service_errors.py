"""Errors of service calls and the decorator that turns a service's exceptions into ``success=false``."""
from __future__ import annotations

import functools
import inspect
import traceback
from typing import Any, Callable

from rclpy.node import Node


class ServiceCallError(RuntimeError):
    """A service another node serves did not answer in time, or answered with a failure."""


class DeadlineExpired(ServiceCallError):
    """No answer (or condition) within the time limit, the server still being there."""


def answers_errors(*errors: type[BaseException]) -> Callable:
    """Decorate a service handler so that its ``errors`` answer ``success=false`` with their text.

    Decorate a service handler ``(self, request, response)``: when it raises one of ``errors``
    (default ValueError), answer ``success=false`` with the error's text instead of failing the call.

    Works on plain and coroutine handlers. Only expected, explained errors belong in ``errors``. Any
    other exception is a bug: it is logged with its traceback and answered ``success=false``
    ("internal error ..."), so that the caller learns at once and the node goes on serving (raised
    into the executor, it ended the node's spinning thread: every later call went unanswered).
    """
    caught = errors or (ValueError,)

    def refuse(response: Any, error: BaseException) -> Any:
        response.success, response.message = False, str(error)
        return response

    def internal(node: Node, handler: Callable, response: Any, error: Exception) -> Any:
        node.get_logger().error(f"{handler.__name__} failed (a bug):\n{traceback.format_exc()}")
        response.success = False
        response.message = f"internal error: {type(error).__name__}: {error} (see the node's log)"
        return response

    def decorate(handler: Callable) -> Callable:
        if inspect.iscoroutinefunction(handler):
            @functools.wraps(handler)
            async def answer_async(self, request, response):
                try:
                    return await handler(self, request, response)
                except caught as error:
                    return refuse(response, error)
                except Exception as error:
                    return internal(self, handler, response, error)
            return answer_async

        @functools.wraps(handler)
        def answer(self, request, response):
            try:
                return handler(self, request, response)
            except caught as error:
                return refuse(response, error)
            except Exception as error:
                return internal(self, handler, response, error)
        return answer
    return decorate
