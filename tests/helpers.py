"""Small helpers shared by the tests."""

from __future__ import annotations

import errno
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from user.v1 import step_pb2


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


def random_weights(actor_config: dict[str, Any], version: int, seed: int = 0) -> Any:
    """A sac_mlp weight set with seeded random weights, as the learner would publish it."""
    import torch

    from user.policy import actor_from_config, module_tensors, policy_spec_for
    from user.weights import WeightSet

    torch.manual_seed(seed)
    return WeightSet(
        version=version, policy=policy_spec_for(actor_config), tensors=module_tensors(actor_from_config(actor_config))
    )


def random_sac_batch(obs_dim: int, act_dim: int, seed: int, n: int = 16, p_terminal: float = 0.1) -> dict[str, Any]:
    """A seeded batch in the learner's format (actions in [-1, 1])."""
    import torch

    g = torch.Generator().manual_seed(seed)
    return {
        "obs": torch.randn(n, obs_dim, generator=g),
        "action": torch.rand(n, act_dim, generator=g) * 2 - 1,
        "reward": torch.randn(n, generator=g),
        "next_obs": torch.randn(n, obs_dim, generator=g),
        "terminated": (torch.rand(n, generator=g) < p_terminal).float(),
    }


class EndingContext:
    """The part of a grpc.ServicerContext a streaming handler uses, for driving the handler's generator by hand;
    `end()` does what gRPC does when the RPC terminates (runs the callbacks), without resuming or closing it."""

    def __init__(self) -> None:
        self.callbacks: list[Callable[[], object]] = []
        self.active = True

    def add_callback(self, callback: Callable[[], object]) -> bool:
        self.callbacks.append(callback)
        return True

    def is_active(self) -> bool:
        return self.active

    def abort(self, code: object, details: str) -> None:
        raise AssertionError(f"aborted {code}: {details}")

    def end(self) -> None:
        self.active = False
        for callback in self.callbacks:
            callback()


def fill(mnt: Path) -> Path:
    """(For tiny_disk mounts.) Another process's file takes every free byte of the disk."""
    filler = mnt / "filler"
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    return filler


class ListSink:
    """Collects an edge loop's steps in memory (a StepSink, for loop tests that need no replay)."""

    def __init__(self) -> None:
        self.steps: list[step_pb2.Step] = []
        self._lock = threading.Lock()

    def send(self, step: step_pb2.Step, table: str = "") -> int:
        with self._lock:
            self.steps.append(step)
            return len(self.steps)

    @property
    def unacked(self) -> int:
        return 0

    def snapshot(self) -> list[step_pb2.Step]:
        with self._lock:
            return list(self.steps)


class NoHardware:
    """The lerobot Robot/Teleoperator lifecycle of a device with no hardware (put first in the bases): it connects
    at once and needs no calibration, so a test device defines only its features and its I/O."""

    _connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass
