"""Where a robot's actions come from: the Inference service (remote) or a weight-streamed local copy.

Both answer within a deadline or return None, and the robot holds still: the control loop never
waits on the network or the learner.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import grpc
import numpy as np
import prometheus_client

from user import wire
from user.config import AuthConfig, StackConfig
from user.log import kv
from user.rpc import make_channel
from user.v1 import inference_pb2, inference_pb2_grpc

if TYPE_CHECKING:  # torch is imported only by edges that run a local copy
    from user.policy import Policy
    from user.weights import WeightSet

log = logging.getLogger(__name__)

ACTION_LATENCY = prometheus_client.Histogram(
    "user_edge_action_latency_seconds",
    "Time from asking the policy source for an action to having it (answered requests)",
    ["source"],
    buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.5, 1.0),
)
ACTION_TIMEOUTS = prometheus_client.Counter(
    "user_edge_action_timeouts_total",
    "Action requests without a usable answer in time (the robot held), by reason",
    ["source", "reason"],
)


class PolicySource(ABC):
    """act() answers within deadline_s or returns None; it never raises for transport problems."""

    @abstractmethod
    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        """(action (A,), policy version) for one unbatched observation, or None (robot holds)."""

    @property
    @abstractmethod
    def version(self) -> int:
        """Latest policy version seen (0 = none yet)."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release channels and threads."""


def _first_action(action: np.ndarray) -> np.ndarray:
    """A chunk (horizon, A) is reduced to its first action; the loop re-plans every tick."""
    arr = np.asarray(action, dtype=np.float32)
    return arr[0] if arr.ndim == 2 else arr.reshape(-1)


class RemotePolicy(PolicySource):
    """Inference.Act with timeout=deadline: DEADLINE_EXCEEDED, UNAVAILABLE ("no policy yet") -> None."""

    def __init__(self, addr: str, auth: AuthConfig, deterministic: bool = False) -> None:
        self.addr = addr
        self._channel = make_channel(addr, auth)
        self._stub = inference_pb2_grpc.InferenceStub(self._channel)
        # Connect now (a cheap Status call, result unused), so the first action does not pay the
        # TCP/HTTP2 handshake inside its deadline.
        self._warmup = self._stub.Status.future(inference_pb2.InferenceStatusRequest(), timeout=5.0)
        self._deterministic = deterministic
        self._version = 0
        self._last_error: grpc.StatusCode | None = None

    @property
    def version(self) -> int:
        return self._version

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        request = inference_pb2.ActRequest(
            robot_id=robot_id, observation=wire.to_tensor_map(observation), deterministic=self._deterministic
        )
        start = time.perf_counter()
        try:
            resp = self._stub.Act(request, timeout=deadline_s)
            action = _first_action(wire.from_tensor(resp.action))
        except grpc.RpcError as err:
            self._note_error(err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN, err)
            return None
        except wire.WireError as err:
            ACTION_TIMEOUTS.labels("remote", "bad_action").inc()
            log.warning("undecodable action from inference", extra=kv(error=str(err)))
            return None
        ACTION_LATENCY.labels("remote").observe(time.perf_counter() - start)
        if self._last_error is not None:
            log.info("inference answers again", extra=kv(addr=self.addr, version=resp.policy_version))
            self._last_error = None
        self._version = int(resp.policy_version)
        return action, self._version

    def _note_error(self, code: grpc.StatusCode, err: grpc.RpcError) -> None:
        ACTION_TIMEOUTS.labels("remote", code.name.lower()).inc()
        if code != self._last_error:  # log transitions, not every held tick
            details = err.details() if hasattr(err, "details") else str(err)
            log.warning("no action from inference; holding", extra=kv(addr=self.addr, code=code.name, details=details))
            self._last_error = code

    def close(self) -> None:
        self._warmup.cancel()
        self._channel.close()


class LocalPolicy(PolicySource):
    """A local policy copy kept fresh by a WeightSubscriber; new weights swap in atomically."""

    def __init__(
        self,
        learner_addr: str,
        auth: AuthConfig,
        client_id: str,
        deterministic: bool = False,
        start: bool = True,
        allow_lossy: bool = False,
    ) -> None:
        import user.policy  # noqa: F401 - torch loads now, not in the weight thread while robots run
        from user.weights import WeightSubscriber

        self._policy: Policy | None = None  # replaced whole, never mutated: reading it needs no lock
        self._deterministic = deterministic
        self._lock = threading.Lock()  # serialises forward passes of robots sharing this copy
        self._subscriber = WeightSubscriber(learner_addr, auth, client_id, self._on_weights, allow_lossy=allow_lossy)
        if start:
            self._subscriber.start()

    @property
    def version(self) -> int:
        policy = self._policy
        return int(policy.version) if policy is not None else 0

    def _on_weights(self, weights: WeightSet) -> None:
        """Build the new network off the control path, then swap the reference. A build error
        propagates to the subscriber, which logs it and keeps the previous version."""
        from user.policy import build_policy

        policy = build_policy(weights.policy, weights.policy_tensors(), weights.version)
        self._policy = policy
        log.info("local policy updated", extra=kv(version=int(policy.version)))

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        policy = self._policy
        if policy is None:
            ACTION_TIMEOUTS.labels("local", "no_policy").inc()
            return None
        start = time.perf_counter()
        batched = {name: np.asarray(v)[None] for name, v in observation.items()}
        try:
            with self._lock:
                action = policy.act(batched, self._deterministic)
        except ValueError as err:  # observation does not fit this policy: hold, say why once
            ACTION_TIMEOUTS.labels("local", "bad_observation").inc()
            log.warning("local policy refused the observation", extra=kv(robot_id=robot_id, error=str(err)))
            return None
        elapsed = time.perf_counter() - start
        if elapsed > deadline_s:  # a stale action is worse than holding still
            ACTION_TIMEOUTS.labels("local", "late").inc()
            return None
        ACTION_LATENCY.labels("local").observe(elapsed)
        return _first_action(np.asarray(action)[0]), int(policy.version)

    def close(self) -> None:
        self._subscriber.stop()


def make_policy_source(cfg: StackConfig, client_id: str) -> PolicySource:
    if cfg.edge.policy_source == "local":
        return LocalPolicy(cfg.edge.learner_addr, cfg.auth, client_id, allow_lossy=cfg.edge.weights_lossy)
    return RemotePolicy(cfg.edge.inference_addr, cfg.auth)
