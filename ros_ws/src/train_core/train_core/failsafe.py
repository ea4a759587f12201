"""One fail-safe latch for the nodes' cores (pure: no rclpy).

A node's last resort against a defect, or an input no check foresaw: a method decorated with
:func:`guarded` on an object whose ``fail_safe`` attribute is true never raises. The first
exception latches the object as failed (``failure``: "call: Type: message"; ``failure_trace``:
its traceback, for the node's log), and from then on ``on_failure`` answers that call and every
later call of every decorated method: the state a half-done update left is not trusted again
(a filter's covariance does not describe it; a zone controller's trains may be half reordered).
What the answer is belongs to the object: an estimator publishes ALARM, a zone controller
brakes every train. With ``fail_safe`` false (offline analysis, tests, campaigns) the exception
propagates, so that it is seen and counted.
"""

from __future__ import annotations

import functools
import traceback

FAILURE_TEXT = 300  # characters of "call: Type: message" kept in ``failure`` (a log line)


def guarded(on_failure):
    """Decorator: ``on_failure(self, *args, **kw)`` answers once ``self.failure`` is set; with
    ``self.fail_safe`` an exception from the method sets it (module doc)."""
    def wrap(method):
        @functools.wraps(method)
        def call(self, *args, **kw):
            if self.failure is None:
                if not self.fail_safe:
                    return method(self, *args, **kw)
                try:
                    return method(self, *args, **kw)
                except Exception as exc:  # noqa: BLE001 - the node's last resort: latched
                    self.failure = f"{method.__name__}: {type(exc).__name__}: {exc}"[
                        :FAILURE_TEXT]
                    self.failure_trace = traceback.format_exc()
            return on_failure(self, *args, **kw)
        return call
    return wrap
