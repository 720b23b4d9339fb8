"""Replay service: validated, acknowledged-after-commit inserts; ready-to-train samples.

An Insert stream groups steps into LMDB transactions (at most commit_max_steps steps or
commit_max_delay_ms old) and acknowledges each step only after its transaction commits. The
first invalid step ends the stream with INVALID_ARGUMENT, after everything before it has been
committed and acknowledged; the invalid step changes nothing.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator

import grpc
import numpy as np
import prometheus_client

from services.replay.store import EmptyBufferError, ReplayStore
from services.replay.validate import validate_step
from user import rpc, wire
from user.config import AuthConfig, StackConfig
from user.log import kv
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2

log = logging.getLogger(__name__)

SERVICE_NAME = replay_pb2.DESCRIPTOR.services_by_name["Replay"].full_name
MAX_SAMPLE = 65536

STORED = prometheus_client.Counter("user_replay_steps_stored_total", "Steps committed to LMDB")
DUPLICATES = prometheus_client.Counter(
    "user_replay_duplicates_total", "Re-sent steps already stored (acked, not stored)"
)
REJECTED = prometheus_client.Counter("user_replay_rejected_total", "Steps refused", ["reason"])
TRANSITIONS = prometheus_client.Gauge("user_replay_transitions", "Sampleable transitions")
BYTES = prometheus_client.Gauge("user_replay_bytes_on_disk", "LMDB bytes in use")
STREAMS = prometheus_client.Gauge("user_replay_insert_streams", "Open Insert streams")
COMMIT_SECONDS = prometheus_client.Histogram(
    "user_replay_commit_seconds",
    "LMDB write transaction time",
    buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5),
)
COMMIT_STEPS = prometheus_client.Histogram(
    "user_replay_commit_steps", "Steps per transaction", buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 1024)
)
SAMPLE_SECONDS = prometheus_client.Histogram(
    "user_replay_sample_seconds", "Sample RPC time", buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5)
)

SpecSource = Callable[[str], robot_pb2.RobotSpec | None]


class ControlSpecSource:
    """Registered specs from the Control service, cached; persisted copies when control is down."""

    def __init__(self, addr: str, auth: AuthConfig, store: ReplayStore, timeout_s: float) -> None:
        self._stub = control_pb2_grpc.ControlStub(rpc.make_channel(addr, auth))
        self._store, self._timeout = store, timeout_s
        self._cache: dict[str, robot_pb2.RobotSpec] = {}

    def __call__(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        spec = self._cache.get(robot_id)
        if spec is not None:
            return spec
        try:
            spec = self._stub.GetRobot(control_pb2.GetRobotRequest(robot_id=robot_id), timeout=self._timeout).spec
        except grpc.RpcError as err:
            if err.code() != grpc.StatusCode.NOT_FOUND:
                log.warning(
                    "control unreachable; using persisted spec", extra=kv(robot_id=robot_id, code=err.code().name)
                )
            spec = self._store.get_spec(robot_id)
            if spec is not None:
                self._cache[robot_id] = spec
            return spec
        self._store.put_spec(spec)
        self._cache[robot_id] = spec
        return spec


_END = object()


class ReplayServicer(replay_pb2_grpc.ReplayServicer):
    def __init__(
        self, store: ReplayStore, spec_source: SpecSource, commit_max_steps: int, commit_max_delay_s: float
    ) -> None:
        self.store = store
        self.spec_source = spec_source
        self.commit_max_steps = commit_max_steps
        self.commit_max_delay_s = commit_max_delay_s
        self.rejected = 0
        self._rng = np.random.default_rng()
        self._rng_lock = threading.Lock()
        self.closing = threading.Event()

    def _commit(self, pending: list[replay_pb2.InsertRequest]) -> replay_pb2.InsertAck:
        start = time.perf_counter()
        stored, dups = self.store.put_steps([r.step for r in pending])
        COMMIT_SECONDS.observe(time.perf_counter() - start)
        COMMIT_STEPS.observe(len(pending))
        STORED.inc(stored)
        DUPLICATES.inc(dups)
        TRANSITIONS.set(self.store.transitions)
        return replay_pb2.InsertAck(seqs=[r.seq for r in pending], stored=stored, duplicates=dups)

    def _check(self, step: step_pb2.Step) -> str | None:
        """None when valid, else the reason."""
        spec = self.spec_source(step.robot_id) if step.robot_id else None
        if spec is None:
            REJECTED.labels("unknown_robot").inc()
            return f"unknown robot {step.robot_id!r} (register it with the control service first)"
        try:
            validate_step(step, spec)
        except wire.WireError as exc:
            REJECTED.labels("invalid").inc()
            return str(exc)
        return None

    def Insert(self, request_iterator: Iterator[replay_pb2.InsertRequest], context: grpc.ServicerContext):
        # A reader thread feeds a queue so a half-full batch commits on time while the client is idle.
        inbox: queue.Queue = queue.Queue(maxsize=4 * self.commit_max_steps)

        def read() -> None:
            try:
                for req in request_iterator:
                    inbox.put(req)
            except Exception:  # client went away: commit what we have, nobody to ack
                pass
            inbox.put(_END)

        threading.Thread(target=read, name="replay-insert-reader", daemon=True).start()
        STREAMS.inc()
        pending: list[replay_pb2.InsertRequest] = []
        deadline = None
        try:
            while True:
                timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    item = inbox.get(timeout=timeout if timeout is not None else 0.5)
                except queue.Empty:
                    item = None
                if item is _END or (item is None and self.closing.is_set()):
                    if pending:
                        yield self._commit(pending)
                    return
                if item is not None:
                    reason = self._check(item.step)
                    if reason is not None:
                        self.rejected += 1
                        if pending:
                            yield self._commit(pending)
                        log.warning("step rejected", extra=kv(seq=item.seq, robot_id=item.step.robot_id, reason=reason))
                        context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"seq {item.seq}: {reason}")
                    pending.append(item)
                    if deadline is None:
                        deadline = time.monotonic() + self.commit_max_delay_s
                due = deadline is not None and time.monotonic() >= deadline
                if pending and (len(pending) >= self.commit_max_steps or due):
                    yield self._commit(pending)
                    pending, deadline = [], None
        finally:
            STREAMS.dec()

    def Sample(self, request: replay_pb2.SampleRequest, context: grpc.ServicerContext) -> replay_pb2.SampleResponse:
        if not 0 < request.batch_size <= MAX_SAMPLE:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"batch_size must be in 1..{MAX_SAMPLE}")
        start = time.perf_counter()
        with self._rng_lock:
            seed = int(self._rng.integers(1 << 62))
        try:
            arrays = self.store.sample(request.batch_size, np.random.default_rng(seed), list(request.robot_ids))
        except EmptyBufferError as exc:
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(exc))
        batch = replay_pb2.Batch(
            observation=wire.to_tensor_map(arrays["observation"]),
            next_observation=wire.to_tensor_map(arrays["next_observation"]),
            action=wire.to_tensor(arrays["action"]),
            reward=wire.to_tensor(arrays["reward"]),
            terminated=wire.to_tensor(arrays["terminated"]),
            truncated=wire.to_tensor(arrays["truncated"]),
            intervention=wire.to_tensor(arrays["intervention"]),
            policy_version=wire.to_tensor(arrays["policy_version"]),
        )
        SAMPLE_SECONDS.observe(time.perf_counter() - start)
        return replay_pb2.SampleResponse(batch=batch, transitions=self.store.transitions_for(list(request.robot_ids)))

    def Stats(self, request: replay_pb2.StatsRequest, context: grpc.ServicerContext) -> replay_pb2.StatsResponse:
        st = self.store.stats()
        BYTES.set(st["bytes_on_disk"])
        return replay_pb2.StatsResponse(
            steps=st["steps"],
            transitions=st["transitions"],
            episodes=st["episodes"],
            bytes_on_disk=st["bytes_on_disk"],
            steps_per_robot=st["steps_per_robot"],
            duplicates=st["duplicates"],
            rejected=self.rejected,
        )


class ReplayService:
    """In-process replay server (tests, benchmarks) and the body of `userctl replay`."""

    def __init__(self, cfg: StackConfig, spec_source: SpecSource | None = None, start_metrics: bool = True) -> None:
        self.cfg = cfg
        self.store = ReplayStore(cfg.replay.path, cfg.replay.map_size_mb)
        source = spec_source or ControlSpecSource(
            cfg.replay.control_addr, cfg.auth, self.store, cfg.replay.rpc_timeout_s
        )
        self.servicer = ReplayServicer(
            self.store, source, cfg.replay.commit_max_steps, cfg.replay.commit_max_delay_ms / 1000.0
        )
        self.start_metrics = start_metrics
        self.running: rpc.RunningServer | None = None

    @property
    def port(self) -> int:
        assert self.running is not None
        return self.running.port

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def start(self) -> ReplayService:
        self.running = rpc.start_server(
            "replay",
            lambda server: replay_pb2_grpc.add_ReplayServicer_to_server(self.servicer, server),
            [SERVICE_NAME],
            self.cfg.replay.server,
            self.cfg.auth,
            start_metrics=self.start_metrics,
        )
        TRANSITIONS.set(self.store.transitions)
        log.info("replay open", extra=kv(path=str(self.cfg.replay.path), **self.store.stats()))
        return self

    def stop(self) -> None:
        """Open streams commit what they hold, then the server drains and LMDB is closed."""
        self.servicer.closing.set()
        if self.running is not None:
            self.running.stop()
        self.store.close()


def run(cfg: StackConfig, ready_file: str | None) -> int:
    service = ReplayService(cfg).start()
    assert service.running is not None
    rpc.write_ready_file(ready_file, grpc_port=service.running.port, metrics_port=service.running.metrics_port)
    stop = rpc.install_signal_handlers()
    stop.wait()
    service.stop()
    log.info("replay stopped")
    return 0
