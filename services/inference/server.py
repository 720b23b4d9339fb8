"""Inference service: observations in, actions out, batched across robots.

The policy is whatever the learner published last: a WeightSubscriber streams weight sets from
Learner.SubscribeWeights and `load_weights` rebuilds the policy from PolicySpec + tensors (no code
and no pickle from the wire). Act requests are validated, queued on a MicroBatcher and answered
from one policy forward per batch. Until the first weights arrive Act answers UNAVAILABLE and the
edges hold their robots still.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Mapping
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Literal

import grpc
import numpy as np
import prometheus_client

from services.inference.batcher import ActResult, MicroBatcher, NoPolicyError
from user import rpc, wire
from user.config import ConfigError, StackConfig
from user.log import kv
from user.policy import Policy, build_policy, check_device
from user.v1 import inference_pb2, inference_pb2_grpc
from user.weights import WeightSet, WeightSubscriber
from user.worker import report_worker

log = logging.getLogger(__name__)

SERVICE_NAME = inference_pb2.DESCRIPTOR.services_by_name["Inference"].full_name
MAX_ACT_WAIT_S = 10.0  # a caller without a deadline still gets an answer (or an error) in bounded time

REQUESTS = prometheus_client.Counter("user_inference_requests_total", "Act requests by status code", ["code"])
BATCH_SIZE = prometheus_client.Histogram(
    "user_inference_batch_size", "Requests per policy forward", buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256)
)
QUEUE_SECONDS = prometheus_client.Histogram(
    "user_inference_queue_seconds",
    "Time an Act request waited to be batched",
    buckets=(0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5),
)
COMPUTE_SECONDS = prometheus_client.Histogram(
    "user_inference_compute_seconds",
    "Policy forward time per batch",
    buckets=(0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5),
)
POLICY_VERSION = prometheus_client.Gauge("user_inference_policy_version", "Version of the policy being served")
WEIGHT_UPDATES = prometheus_client.Counter("user_inference_weight_updates_total", "Weight sets loaded")


def _observe_batch(size: int, compute_s: float) -> None:
    BATCH_SIZE.observe(size)
    COMPUTE_SECONDS.observe(compute_s)


def validate_observation(observation: Mapping[str, np.ndarray], policy: Policy) -> dict[str, np.ndarray]:
    """Keep the keys the policy reads, as float32 (uint8 images stay uint8); ValueError on a mismatch."""
    keys: list[str] = list(getattr(policy, "obs_keys", None) or observation)
    missing = [k for k in keys if k not in observation]
    if missing:
        raise ValueError(f"observation lacks {missing}; the policy reads {keys}")
    out: dict[str, np.ndarray] = {}
    for k in keys:
        arr = observation[k]
        if arr.dtype != np.uint8:
            arr = arr.astype(np.float32, copy=False)
            if not np.isfinite(arr).all():
                raise ValueError(f"observation {k!r} has NaN or Inf")
        out[k] = arr
    obs_dim = getattr(policy, "obs_dim", None)
    if obs_dim is not None:
        got = sum(int(a.size) for a in out.values())
        if got != int(obs_dim):
            shapes = {k: list(a.shape) for k, a in out.items()}
            raise ValueError(f"observation has {got} features {shapes}, the policy expects {obs_dim}")
    return out


class InferenceServicer(inference_pb2_grpc.InferenceServicer):
    def __init__(self, service: InferenceService) -> None:
        self.service = service

    @staticmethod
    def _abort(context: grpc.ServicerContext, code: grpc.StatusCode, message: str) -> None:
        REQUESTS.labels(code.name).inc()
        context.abort(code, message)

    def Act(self, request: inference_pb2.ActRequest, context: grpc.ServicerContext) -> inference_pb2.ActResponse:
        policy = self.service.policy
        if policy is None:
            self._abort(context, grpc.StatusCode.UNAVAILABLE, "no policy yet")
        try:
            obs = validate_observation(wire.from_tensor_map(request.observation), policy)
        except ValueError as exc:  # WireError is a ValueError
            self._abort(context, grpc.StatusCode.INVALID_ARGUMENT, f"bad observation: {exc}")
        try:
            future = self.service.batcher.submit(obs, request.deterministic, key=request.robot_id)
        except NoPolicyError:
            self._abort(context, grpc.StatusCode.UNAVAILABLE, "no policy yet")
        remaining = context.time_remaining()
        wait_s = MAX_ACT_WAIT_S if remaining is None else max(0.0, min(remaining, MAX_ACT_WAIT_S))
        try:
            result: ActResult = future.result(timeout=wait_s)
        except FutureTimeout:
            future.cancel()  # the worker skips it if it has not started
            self._abort(context, grpc.StatusCode.DEADLINE_EXCEEDED, f"no action within {wait_s * 1000:.0f} ms")
        except NoPolicyError:
            self._abort(context, grpc.StatusCode.UNAVAILABLE, "no policy yet")
        except Exception as exc:
            self._abort(context, grpc.StatusCode.INTERNAL, f"policy forward failed: {exc}")
        REQUESTS.labels("OK").inc()
        QUEUE_SECONDS.observe(result.queue_us / 1e6)
        return inference_pb2.ActResponse(
            action=wire.to_tensor(np.asarray(result.action, dtype=np.float32)),
            policy_version=result.version,
            queue_us=result.queue_us,
            compute_us=result.compute_us,
            batch_size=result.batch_size,
        )

    def Status(
        self, request: inference_pb2.InferenceStatusRequest, context: grpc.ServicerContext
    ) -> inference_pb2.InferenceStatus:
        policy = self.service.policy
        batcher = self.service.batcher
        return inference_pb2.InferenceStatus(
            policy_version=policy.version if policy else 0,
            policy_kind=policy.spec.kind if policy else "",
            requests=batcher.requests,
            mean_batch_size=batcher.mean_batch_size,
        )


class InferenceService(rpc.GrpcService):
    """In-process inference server: start() binds (port 0 works), stop() drains and shuts down.

    policy_source: "learner" (default, also None) streams weights from cfg.inference.learner_addr;
    "manual" waits for load_weights() calls (tests, or a caller with its own weight source).
    """

    def __init__(
        self,
        cfg: StackConfig,
        policy_source: Literal["learner", "manual"] | None = None,
        start_metrics: bool = True,
    ) -> None:
        self.cfg = cfg
        self.policy_source = policy_source or "learner"
        if self.policy_source not in ("learner", "manual"):
            raise ValueError(f"policy_source must be 'learner' or 'manual', got {policy_source!r}")
        self.start_metrics = start_metrics
        icfg = cfg.inference
        self.batcher = MicroBatcher(icfg.max_batch, icfg.max_wait_ms, on_batch=_observe_batch, name="inference-batch")
        self._policy: Policy | None = None
        self._load_lock = threading.Lock()
        self.subscriber: WeightSubscriber | None = None
        self.running: rpc.RunningServer | None = None
        try:
            check_device(icfg.device)
        except ValueError as exc:
            raise ConfigError(f"inference.device: {exc}") from None

    @property
    def policy(self) -> Policy | None:
        return self._policy

    def load_weights(self, weights: WeightSet) -> Policy:
        """Rebuild the policy from a weight set and serve it; raises ValueError (keeping the old one) if bad."""
        start = time.perf_counter()
        policy = build_policy(weights.policy, weights.tensors, weights.version, self.cfg.inference.device)
        with self._load_lock:
            self._policy = policy
            self.batcher.set_policy(policy.act, policy.version)
        WEIGHT_UPDATES.inc()
        POLICY_VERSION.set(policy.version)
        log.info(
            "policy loaded",
            extra=kv(
                version=policy.version, kind=weights.policy.kind, build_ms=round((time.perf_counter() - start) * 1e3, 2)
            ),
        )
        return policy

    def start(self) -> InferenceService:
        self.batcher.start()
        self.running = rpc.start_server(
            "inference",
            lambda server: inference_pb2_grpc.add_InferenceServicer_to_server(InferenceServicer(self), server),
            [SERVICE_NAME],
            self.cfg.inference.server,
            self.cfg.auth,
            start_metrics=self.start_metrics,
        )
        if self.policy_source == "learner":
            self.subscriber = WeightSubscriber(
                self.cfg.inference.learner_addr,
                self.cfg.auth,
                client_id=f"inference-{socket.gethostname()}-{self.running.port}",
                on_weights=self.load_weights,
            ).start()
        return self

    def stop(self) -> None:
        # Calls in flight finish (the batcher still runs during the server's grace), then the workers go.
        if self.running is not None:
            self.running.stop()
            self.running = None
        if self.subscriber is not None:
            self.subscriber.stop()
            self.subscriber = None
        self.batcher.stop()


def run(cfg: StackConfig, ready_file: str | None) -> int:
    import torch

    # Per-robot MLP forwards are latency-bound; extra intra-op threads only contend with the learner.
    torch.set_num_threads(1)
    service, ic = InferenceService(cfg), cfg.inference
    with report_worker(service, "inference", ic.control_addr, cfg.auth, ic.device, []):
        rpc.serve_until_signal(service, "inference", ready_file)
    return 0
