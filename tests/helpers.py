"""Small helpers shared by the tests."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate: Callable[[], Any], what: str = "condition", limit_s: float = 30.0, poll_s: float = 0.02) -> Any:
    """The first truthy value of predicate(). A liveness bound, never a speed threshold: it fails only
    when something is stuck."""
    end = time.monotonic() + limit_s
    last = None
    while time.monotonic() < end:
        last = predicate()
        if last:
            return last
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {limit_s}s waiting for {what}; last={last!r}")
