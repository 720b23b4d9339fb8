"""Replay service: validated, acknowledged-after-commit inserts; ready-to-train samples.

An Insert stream groups steps into LMDB transactions (at most commit_max_steps steps, or whatever
arrived within commit_max_delay_ms of the first pending step) and acknowledges a step only after
its transaction has committed. The first invalid step ends the stream with INVALID_ARGUMENT
("seq N: reason") after everything before it has been committed and acknowledged; the invalid
step itself changes nothing.

Steps are validated against the spec their robot registered with the Control service (GetRobot,
cached in memory, persisted beside the steps). When control cannot be reached a persisted spec is
used; with none, the stream ends with UNAVAILABLE so the edge re-sends later instead of losing data.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import grpc
import numpy as np
import prometheus_client

from services.replay.store import (
    EmptyBufferError,
    LayoutError,
    ReplayFullError,
    ReplayStore,
    StoreClosedError,
)
from services.replay.validate import EpisodeGuard, StepError, validate_step
from user import rpc, wire
from user.auth import Identity
from user.config import AuthConfig, StackConfig
from user.log import kv
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2

log = logging.getLogger(__name__)

SERVICE_NAME = replay_pb2.DESCRIPTOR.services_by_name["Replay"].full_name
MAX_SAMPLE = 65536
MAX_BATCH_BYTES = rpc.MAX_MESSAGE_BYTES - (1 << 20)  # room for the envelope
POLL_S = 0.1  # how often an idle Insert stream notices shutdown
SPEC_REFRESH_S = 2.0  # a step failing a cached spec re-asks control at most this often per robot

_SECONDS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1.0)
RECEIVED = prometheus_client.Counter("user_replay_steps_received_total", "Steps read from Insert streams")
STORED = prometheus_client.Counter("user_replay_steps_stored_total", "Steps committed to LMDB")
DUPLICATES = prometheus_client.Counter(
    "user_replay_duplicates_total", "Re-sent steps that were already stored (acknowledged, not stored again)"
)
REJECTED = prometheus_client.Counter(
    "user_replay_rejected_total", "Steps refused with INVALID_ARGUMENT, by reason", ["reason"]
)
STEPS = prometheus_client.Gauge("user_replay_steps", "Steps stored")
TRANSITIONS = prometheus_client.Gauge("user_replay_transitions", "Sampleable transitions")
BYTES_ON_DISK = prometheus_client.Gauge("user_replay_bytes_on_disk", "LMDB pages in use, bytes")
INSERT_STREAMS = prometheus_client.Gauge("user_replay_insert_streams", "Open Insert streams")
COMMIT_SECONDS = prometheus_client.Histogram(
    "user_replay_commit_seconds", "One LMDB write transaction (put + commit + fsync)", buckets=_SECONDS
)
COMMIT_STEPS = prometheus_client.Histogram(
    "user_replay_commit_steps", "Steps per write transaction", buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
)
SAMPLE_SECONDS = prometheus_client.Histogram(
    "user_replay_sample_seconds", "Sample: draw, read, decode, stack and encode a batch", buckets=_SECONDS
)


class SpecUnavailable(Exception):
    """The spec source cannot answer now (control unreachable); not the same as an unknown robot."""


# A spec source returns the robot's registered spec, None for a robot it does not know, or raises
# SpecUnavailable when it cannot tell.
SpecSource = Callable[[str], robot_pb2.RobotSpec | None]


class ControlSpecSource:
    """Specs from the Control service's GetRobot (NOT_FOUND -> None)."""

    def __init__(self, addr: str, auth: AuthConfig, timeout_s: float) -> None:
        self.addr = addr
        self.timeout_s = timeout_s
        self._channel = rpc.make_channel(addr, auth)
        self._stub = control_pb2_grpc.ControlStub(self._channel)

    def __call__(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        try:
            info = self._stub.GetRobot(control_pb2.GetRobotRequest(robot_id=robot_id), timeout=self.timeout_s)
        except grpc.RpcError as err:
            code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
            if code == grpc.StatusCode.NOT_FOUND:
                return None
            details = err.details() if hasattr(err, "details") else ""
            raise SpecUnavailable(f"control at {self.addr} answered {code.name}: {details}") from None
        return info.spec

    def close(self) -> None:
        self._channel.close()


class SpecBook:
    """Specs by robot id: fetched from the source once, cached; the persisted copy when the source is down.

    A spec fetched from the source that differs from the persisted one is "dirty" and is written in the
    next step commit, so a stream whose only step is rejected changes nothing on disk.
    """

    def __init__(self, source: SpecSource, store: ReplayStore) -> None:
        self._source = source
        self._store = store
        self._lock = threading.Lock()
        self._cache: dict[str, robot_pb2.RobotSpec] = {}
        self._fetched_at: dict[str, float] = {}
        self._dirty: dict[str, robot_pb2.RobotSpec] = {}

    def get(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        with self._lock:
            spec = self._cache.get(robot_id)
        return spec if spec is not None else self.refresh(robot_id)

    def may_refresh(self, robot_id: str) -> bool:
        with self._lock:
            return time.monotonic() - self._fetched_at.get(robot_id, -float("inf")) >= SPEC_REFRESH_S

    def refresh(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        """Ask the source. None = unknown robot; SpecUnavailable when neither source nor disk has it."""
        with self._lock:
            self._fetched_at[robot_id] = time.monotonic()
        try:
            spec = self._source(robot_id)
        except Exception as exc:  # SpecUnavailable, or a broken source: never reject steps for it
            return self._fallback(robot_id, exc)
        with self._lock:
            if spec is None:
                self._cache.pop(robot_id, None)
                return None
            if self._cache.get(robot_id) != spec and self._store.get_spec(robot_id) != spec:
                self._dirty[robot_id] = spec
            self._cache[robot_id] = spec
        return spec

    def _fallback(self, robot_id: str, exc: Exception) -> robot_pb2.RobotSpec:
        persisted = self._store.get_spec(robot_id)
        if persisted is None:
            raise SpecUnavailable(f"cannot validate steps of robot {robot_id}: {exc}; no spec of it was persisted")
        log.warning("spec source unavailable; using the persisted spec", extra=kv(robot_id=robot_id, error=str(exc)))
        with self._lock:
            self._cache[robot_id] = persisted
        return persisted

    def take_dirty(self) -> list[robot_pb2.RobotSpec]:
        with self._lock:
            specs = list(self._dirty.values())
            self._dirty.clear()
        return specs

    def restore_dirty(self, specs: list[robot_pb2.RobotSpec]) -> None:
        with self._lock:
            for spec in specs:
                self._dirty.setdefault(spec.robot_id, spec)


# --------------------------------------------------------------------------- Insert plumbing

_END = object()  # the client closed its side
_BROKEN = object()  # the call was cancelled or broke


class _Inbox:
    """Reads the request stream in a thread, so a half-full batch commits on time while the client is idle."""

    def __init__(self, requests: Iterator[replay_pb2.InsertRequest], maxsize: int) -> None:
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)  # bounded: backpressure on the client
        self._closed = threading.Event()
        threading.Thread(target=self._read, args=(requests,), name="replay-insert-reader", daemon=True).start()

    def _read(self, requests: Iterator[replay_pb2.InsertRequest]) -> None:
        end = _END
        try:
            for req in requests:
                if not self._offer(req):
                    return
        except Exception as exc:  # cancelled, deadline, connection lost
            log.debug("insert stream read ended", extra=kv(error=repr(exc)))
            end = _BROKEN
        self._offer(end)

    def _offer(self, item: Any) -> bool:
        while not self._closed.is_set():
            try:
                self._queue.put(item, timeout=POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def get(self, timeout: float) -> Any:
        """The next request, _END, _BROKEN, or None after `timeout` seconds."""
        try:
            return self._queue.get(timeout=timeout) if timeout > 0 else self._queue.get_nowait()
        except queue.Empty:
            return None

    def close(self) -> None:
        self._closed.set()


class ReplayServicer(replay_pb2_grpc.ReplayServicer):
    def __init__(
        self,
        store: ReplayStore,
        spec_source: SpecSource,
        commit_max_steps: int,
        commit_max_delay_s: float,
        seed: int | None = None,
    ) -> None:
        self.store = store
        self.specs = SpecBook(spec_source, store)
        self.episodes = EpisodeGuard()
        self.commit_max_steps = commit_max_steps
        self.commit_max_delay_s = commit_max_delay_s
        self.rejected = 0
        self._count_lock = threading.Lock()
        self._rng = np.random.default_rng(seed)
        self._rng_lock = threading.Lock()
        self._closing = threading.Event()
        self._streams = 0
        self._streams_cond = threading.Condition()

    # ------------------------------------------------------------------ lifecycle

    def begin_shutdown(self) -> None:
        """Open streams commit and acknowledge what they hold, then end with UNAVAILABLE."""
        self._closing.set()

    def wait_streams(self, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        with self._streams_cond:
            while self._streams:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._streams_cond.wait(left)
        return True

    def _stream_delta(self, delta: int) -> None:
        with self._streams_cond:
            self._streams += delta
            INSERT_STREAMS.set(self._streams)
            self._streams_cond.notify_all()

    # ------------------------------------------------------------------ Insert

    def Insert(
        self, request_iterator: Iterator[replay_pb2.InsertRequest], context: grpc.ServicerContext
    ) -> Iterator[replay_pb2.InsertAck]:
        if self._closing.is_set():
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send later")
        inbox = _Inbox(request_iterator, maxsize=2 * self.commit_max_steps)
        self._stream_delta(+1)
        try:
            yield from self._insert(inbox, context, rpc.caller(context))
        finally:
            inbox.close()
            self._stream_delta(-1)

    def _insert(
        self, inbox: _Inbox, context: grpc.ServicerContext, who: Identity | None = None
    ) -> Iterator[replay_pb2.InsertAck]:
        pending: list[replay_pb2.InsertRequest] = []
        deadline = 0.0
        while True:
            if self._closing.is_set():
                if pending:
                    yield self._commit(pending, context)
                context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send unacknowledged steps")
            wait = min(POLL_S, deadline - time.monotonic()) if pending else POLL_S
            item = inbox.get(wait)
            if item is _END:
                if pending:
                    yield self._commit(pending, context)
                return
            if item is _BROKEN:  # nobody to ack; commit anyway, a re-send is deduplicated
                if pending:
                    self._commit(pending, context)
                return
            if item is not None:
                RECEIVED.inc()
                if who is not None and not who.owns_robot(item.step.robot_id):  # before _admit records anything
                    failure = (
                        grpc.StatusCode.PERMISSION_DENIED,
                        f"seq {item.seq}: {who.name!r} may not write robot {item.step.robot_id!r}",
                    )
                else:
                    failure = self._admit(item)
                if failure is not None:
                    if pending:  # everything before the failing step is committed and acknowledged first
                        yield self._commit(pending, context)
                    context.abort(*failure)
                pending.append(item)
                if len(pending) == 1:
                    deadline = time.monotonic() + self.commit_max_delay_s
            if pending and (len(pending) >= self.commit_max_steps or time.monotonic() >= deadline):
                yield self._commit(pending, context)
                pending = []

    def _admit(self, req: replay_pb2.InsertRequest) -> tuple[grpc.StatusCode, str] | None:
        """None for a valid step; otherwise the status that ends the stream (after the steps before it)."""
        step = req.step
        try:
            problem = self._check(step)
        except SpecUnavailable as exc:
            log.warning("cannot validate step", extra=kv(seq=req.seq, robot_id=step.robot_id, error=str(exc)))
            return grpc.StatusCode.UNAVAILABLE, f"seq {req.seq}: {exc}"
        except StoreClosedError:
            return grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send unacknowledged steps"
        if problem is None:
            return None
        reason, message = problem
        REJECTED.labels(reason).inc()
        with self._count_lock:
            self.rejected += 1
        log.warning(
            "step rejected",
            extra=kv(
                seq=req.seq,
                robot_id=step.robot_id,
                episode_id=step.episode_id,
                step_index=step.step_index,
                reason=reason,
                error=message,
            ),
        )
        return grpc.StatusCode.INVALID_ARGUMENT, f"seq {req.seq}: {message}"

    def _check(self, step: step_pb2.Step) -> tuple[str, str] | None:
        """None when valid, else (metric reason, message). Raises SpecUnavailable."""
        rid = step.robot_id
        if not rid:
            return "robot_id", "robot_id is empty"
        spec = self.specs.get(rid)
        if spec is None:
            return "unknown_robot", f"unknown robot {rid} (control has no registration for it)"
        try:
            validate_step(step, spec)
            self.episodes.check(step)
            return None
        except StepError as exc:
            error = exc
            if error.reason == "episode_order":  # a fresher spec cannot fix the order
                return error.reason, str(error)
        # The robot may have re-registered with a new spec since it was cached: ask again, rarely.
        if self.specs.may_refresh(rid):
            try:
                fresh = self.specs.refresh(rid)
            except SpecUnavailable:
                fresh = spec
            if fresh is None:
                return "unknown_robot", f"unknown robot {rid} (control has no registration for it)"
            if fresh != spec:
                try:
                    validate_step(step, fresh)
                    self.episodes.check(step)
                    return None
                except StepError as exc:
                    error = exc
        return error.reason, str(error)

    def _commit(self, pending: list[replay_pb2.InsertRequest], context: grpc.ServicerContext) -> replay_pb2.InsertAck:
        specs = self.specs.take_dirty()
        start = time.perf_counter()
        try:
            stored, dups = self.store.put_steps([r.step for r in pending], specs)
        except ReplayFullError as exc:
            self.specs.restore_dirty(specs)
            log.error("replay full", extra=kv(error=str(exc)))
            context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, str(exc))
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send unacknowledged steps")
        COMMIT_SECONDS.observe(time.perf_counter() - start)
        COMMIT_STEPS.observe(len(pending))
        STORED.inc(stored)
        DUPLICATES.inc(dups)
        self._update_gauges()
        return replay_pb2.InsertAck(seqs=[r.seq for r in pending], stored=stored, duplicates=dups)

    def _update_gauges(self) -> None:
        try:
            st = self.store.stats()
        except StoreClosedError:
            return
        STEPS.set(st["steps"])
        TRANSITIONS.set(st["transitions"])
        BYTES_ON_DISK.set(st["bytes_on_disk"])

    # ------------------------------------------------------------------ Sample / Stats

    def Sample(self, request: replay_pb2.SampleRequest, context: grpc.ServicerContext) -> replay_pb2.SampleResponse:
        n = request.batch_size
        if not 1 <= n <= MAX_SAMPLE:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"batch_size must be in 1..{MAX_SAMPLE}, got {n}")
        robot_ids = list(request.robot_ids) or None
        start = time.perf_counter()
        try:
            with self._rng_lock:
                arrays = self.store.sample(n, self._rng, robot_ids)
        except (EmptyBufferError, LayoutError) as exc:
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(exc))
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down")
        size = _nbytes(arrays)
        if size > MAX_BATCH_BYTES:
            per = max(1, size // n)
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"a batch of {n} is {size} bytes, over the {MAX_BATCH_BYTES}-byte message limit; "
                f"ask for at most {MAX_BATCH_BYTES // per}",
            )
        resp = replay_pb2.SampleResponse(batch=to_batch(arrays), transitions=self.store.transitions_for(robot_ids))
        SAMPLE_SECONDS.observe(time.perf_counter() - start)
        return resp

    def Stats(self, request: replay_pb2.StatsRequest, context: grpc.ServicerContext) -> replay_pb2.StatsResponse:
        try:
            st = self.store.stats()
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down")
        return replay_pb2.StatsResponse(
            steps=st["steps"],
            transitions=st["transitions"],
            episodes=st["episodes"],
            bytes_on_disk=st["bytes_on_disk"],
            steps_per_robot=st["steps_per_robot"],
            duplicates=st["duplicates"],
            rejected=self.rejected,
        )


def _nbytes(arrays: dict[str, Any]) -> int:
    total = 0
    for value in arrays.values():
        total += sum(a.nbytes for a in value.values()) if isinstance(value, dict) else value.nbytes
    return total


def to_batch(arrays: dict[str, Any]) -> replay_pb2.Batch:
    """store.sample() arrays -> the wire Batch (RAW tensors)."""
    return replay_pb2.Batch(
        observation=wire.to_tensor_map(arrays["observation"]),
        action=wire.to_tensor(arrays["action"]),
        reward=wire.to_tensor(arrays["reward"]),
        next_observation=wire.to_tensor_map(arrays["next_observation"]),
        terminated=wire.to_tensor(arrays["terminated"]),
        truncated=wire.to_tensor(arrays["truncated"]),
        intervention=wire.to_tensor(arrays["intervention"]),
        policy_version=wire.to_tensor(arrays["policy_version"]),
    )


# --------------------------------------------------------------------------- service lifecycle


class ReplayService(rpc.GrpcService):
    """The replay server in-process: start() binds (port 0 works), stop() drains streams and closes LMDB."""

    def __init__(
        self,
        cfg: StackConfig,
        spec_source: SpecSource | None = None,
        start_metrics: bool = True,
    ) -> None:
        self.cfg = cfg
        rc = cfg.replay
        self.store = ReplayStore(rc.path, rc.map_size_mb, cache_mb=rc.cache_mb)
        self._control: ControlSpecSource | None = None
        if spec_source is None:
            self._control = ControlSpecSource(rc.control_addr, cfg.auth, rc.rpc_timeout_s)
            spec_source = self._control
        self.servicer = ReplayServicer(self.store, spec_source, rc.commit_max_steps, rc.commit_max_delay_ms / 1000.0)
        self.start_metrics = start_metrics
        self.running: rpc.RunningServer | None = None
        self._stopped = False

    def start(self) -> ReplayService:
        self.running = rpc.start_server(
            "replay",
            lambda server: replay_pb2_grpc.add_ReplayServicer_to_server(self.servicer, server),
            [SERVICE_NAME],
            self.cfg.replay.server,
            self.cfg.auth,
            start_metrics=self.start_metrics,
        )
        self.servicer._update_gauges()
        log.info("replay serving", extra=kv(path=str(self.cfg.replay.path), **self.store.stats()))
        return self

    def stop(self) -> None:
        """Graceful and idempotent: refuse new calls, let streams commit and ack, close LMDB."""
        if self._stopped:
            return
        self._stopped = True
        self.servicer.begin_shutdown()
        grace = self.cfg.replay.server.grace_s
        if self.running is not None:
            self.running.stop()
        if not self.servicer.wait_streams(grace + 1.0):
            log.warning("insert streams still open at shutdown")
        self.store.close()
        if self._control is not None:
            self._control.close()


def run(cfg: StackConfig, ready_file: str | None) -> int:
    rpc.serve_until_signal(ReplayService(cfg), "replay", ready_file)
    return 0
