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
import math
import queue
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import Any

import grpc
import numpy as np
import prometheus_client

from services.replay.chunks import add_action_chunks, horizon_problem
from services.replay.disk import ReplayError
from services.replay.hot import single_threaded_cv2
from services.replay.prefetch import Prefetcher
from services.replay.shared import NAME as SHARED_NAME
from services.replay.shared import SHARED_FALLBACK, SharedBatches
from services.replay.store import (
    BufferHeld,
    DiskFullError,
    DiskWriteError,
    EmptyBufferError,
    LayoutError,
    ReplayFullError,
    ReplayStore,
    StoreClosedError,
    hold_buffer,
    release_buffer,
)
from services.replay.tables import ONLINE, Draw
from services.replay.validate import EpisodeGuard, StepError, validate_step
from user import rpc, wire
from user.auth import Identity
from user.config import AuthConfig, ConfigError, StackConfig
from user.log import kv
from user.shm_files import PROBE_BYTES
from user.spec import MAX_ROBOT_ID_BYTES
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

log = logging.getLogger(__name__)

SERVICE_NAME = replay_pb2.DESCRIPTOR.services_by_name["Replay"].full_name
MAX_SAMPLE = 65536
MAX_RELEASE = 64  # slot files released per SampleRequest
MAX_N_STEP = 1000
MAX_FRAME_STACK = 64
MAX_TABLES = 64
MAX_SAMPLE_ROBOTS = 4096  # robot_ids of one SampleRequest: a learner names its experiment's fleet
MAX_STATS_SPECS = 1024  # StatsResponse.specs: ~0.3 KB each, a learner asks for its demo tables' robots
MAX_STORE_TABLES = 256  # distinct tables one buffer holds: each costs index columns and a metric series
PREFETCH_MAX_BYTES = 16 << 20  # larger batches are assembled per request, not kept ready in RAM
# batches for a same-host learner: assembling one (~5 ms for 50 MB of frames) overlaps the learner's copy-out
SHM_PREFETCH_MAX_BYTES = 64 << 20
# smaller batches go through the socket: state-only rows (~165 B) per batch, ms through a slot vs the socket, 2 cores:
# 256 rows 1.26 vs 1.15, 1024 rows 1.80 vs 2.14, 2048 rows 1.59 vs 1.76, 4096 rows 1.96 vs 4.80
SHM_MIN_BYTES = 128 << 10
TABLE_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
SAMPLERS = {
    replay_pb2.SAMPLER_UNIFORM: "uniform",
    replay_pb2.SAMPLER_RECENCY: "recency",
    replay_pb2.SAMPLER_PRIORITIZED: "prioritized",
}
MAX_BATCH_BYTES = rpc.MAX_MESSAGE_BYTES - (1 << 20)  # room for the envelope
POLL_S = 0.1  # how often an idle Insert stream notices shutdown
ACK_POLL_S = 0.002  # how often a stream with batches in flight looks for their commits
MAX_IN_FLIGHT = 4  # batches of one stream waiting for the writer at once
SPEC_REFRESH_S = 2.0  # a step failing a cached spec re-asks control at most this often per robot
RESEND = "steps not acknowledged are kept by the edge and re-sent"

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
    "user_replay_commit_seconds",
    "A stream's batch from submit to committed (queue + put + commit + fsync)",
    buckets=_SECONDS,
)
COMMIT_STEPS = prometheus_client.Histogram(
    "user_replay_commit_steps", "Steps per write transaction", buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
)
SAMPLE_SECONDS = prometheus_client.Histogram(
    "user_replay_sample_seconds", "Sample RPC: a prefetched batch handed out, or one assembled now", buckets=_SECONDS
)
HOT_TRANSITIONS = prometheus_client.Gauge("user_replay_hot_transitions", "Transitions held by the RAM tier")
HOT_BYTES = prometheus_client.Gauge("user_replay_hot_bytes", "RAM tier bytes in use")
HOT_HIT_RATE = prometheus_client.Gauge("user_replay_hot_hit_rate", "Sampled transitions served from RAM / all sampled")
DECODED_HIT_RATE = prometheus_client.Gauge(
    "user_replay_decoded_window_hit_rate", "JPEG/PNG frames of hot samples copied from the decoded window / all read"
)
TABLE_TRANSITIONS = prometheus_client.Gauge("user_replay_table_transitions", "Transitions per table", ["table"])
PREFETCH_SERVED = prometheus_client.Counter("user_replay_prefetch_served_total", "Samples served from a ready batch")
RATE_LIMITED = prometheus_client.Counter("user_replay_rate_limited_total", "Samples refused by the rate limiter")
FRAMES_KEPT = prometheus_client.Counter(
    "user_replay_sampled_frames_kept_total",
    "Camera frames sent in samples as replay keeps them (JPEG/PNG bytes, encoded_frames), not decoded",
)
SAMPLE_ABORTED = prometheus_client.Counter(
    "user_replay_sample_aborted_total", "Samples answered ABORTED: they raced a change of the buffer (e.g. an eviction)"
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
            if spec is None:  # unknown robots leave nothing behind (a client may send any number of ids)
                self._cache.pop(robot_id, None)
                self._fetched_at.pop(robot_id, None)
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


class _Refused(Exception):
    """A request message refused as a whole (not one of its steps): the stream ends with INVALID_ARGUMENT."""


def _unbatched(batches: Iterator[replay_pb2.InsertBatchRequest]) -> Iterator[replay_pb2.InsertRequest]:
    """InsertBatch's steps one by one; an empty message is refused (our edge never sends one)."""
    for batch in batches:
        if not batch.requests:
            raise _Refused("an InsertBatchRequest with no steps (requests is empty)")
        yield from batch.requests


_IMAGE_ENCODINGS = (tpb.ENCODING_JPEG, tpb.ENCODING_PNG)
_HELPER = object()  # an item's frames are checked by the stream's check helper: its verdict comes from there
# Steps the helper may hold (checking one, one waiting) before the reader checks the next itself: with "only when
# idle" a helper woken late (a loaded machine) got ~30% of the checks and the reader stayed the bottleneck.
_HELPER_BACKLOG = 2


def _frames(step: step_pb2.Step) -> list[tpb.Tensor]:
    """A step's JPEG/PNG tensors (observation and final observation)."""
    frames = [t for t in step.observation.tensors.values() if t.encoding in _IMAGE_ENCODINGS]
    if step.HasField("final_observation"):
        frames += [t for t in step.final_observation.tensors.values() if t.encoding in _IMAGE_ENCODINGS]
    return frames


def _frames_pass(frames: list[tpb.Tensor]) -> bool:
    """Whether every frame passes wire.check_image (False: validate_step checks them again and says which one
    fails and why)."""
    single_threaded_cv2()
    for tensor in frames:
        try:
            wire.check_image(tensor)
        except Exception:  # WireError, or anything odd: the stream thread's own check decides
            return False
    return True


class _Inbox:
    """Reads the request stream in a thread, so a half-full batch commits on time while the client is idle.

    The JPEG/PNG frames of each step are checked before the stream thread sees it (cv2 releases the GIL), in
    parallel with the stream thread's validation of the steps before it, on two threads: the reader and one
    check helper. The reader hands a step to the helper unless the helper already holds _HELPER_BACKLOG, and
    checks it itself otherwise, so on a busy stream they share the checks (a camera step's two 128x128 checks,
    ~70-110 us, were the reader's whole budget and capped one stream below the peer's add() rate). Items are
    (request, frames passed check_image), in stream order; a step handed over carries _HELPER, and its verdict
    is the next one the helper returns (both queues are FIFO and the stream thread takes items in order)."""

    def __init__(self, requests: Iterator[replay_pb2.InsertRequest], maxsize: int) -> None:
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)  # bounded: backpressure on the client
        self._closed = threading.Event()
        self._to_helper: queue.SimpleQueue = queue.SimpleQueue()
        self._verdicts: queue.SimpleQueue = queue.SimpleQueue()
        self._handed = self._checked = 0  # steps given to the helper / checked by it (one writer each)
        self._helper: threading.Thread | None = None  # started with the first frame (state-only streams need none)
        threading.Thread(target=self._read, args=(requests,), name="replay-insert-reader", daemon=True).start()

    def _read(self, requests: Iterator[replay_pb2.InsertRequest]) -> None:
        end = _END
        try:
            for req in requests:
                frames = _frames(req.step)
                if not frames:
                    verdict: Any = True
                elif self._handed - self._checked < _HELPER_BACKLOG and self._helper_started():
                    self._handed += 1
                    self._to_helper.put(frames)
                    verdict = _HELPER
                else:
                    verdict = _frames_pass(frames)
                if not self._offer((req, verdict)):
                    return
        except _Refused as exc:
            end = exc
        except Exception as exc:  # cancelled, deadline, connection lost
            log.debug("insert stream read ended", extra=kv(error=repr(exc)))
            end = _BROKEN
        finally:
            self._to_helper.put(None)
        self._offer(end)

    def _helper_started(self) -> bool:
        """Start the check helper once; False if no thread can be started (the reader then checks every step)."""
        if self._helper is None:
            self._helper = threading.Thread(target=self._help, name="replay-insert-check", daemon=True)
            try:
                self._helper.start()
            except RuntimeError as exc:  # "can't start new thread": out of threads or memory
                log.warning("insert check helper not started", extra=kv(error=str(exc)))
                self._checked = self._handed - _HELPER_BACKLOG  # never hand a step over
                return False
        return True

    def _help(self) -> None:
        while (frames := self._to_helper.get()) is not None:
            try:
                verdict = _frames_pass(frames)
            except Exception:  # (MemoryError, ...): the stream thread waits on this verdict, so always give one
                verdict = False  # False: validate_step checks the frames itself and names what fails
            self._checked += 1
            self._verdicts.put(verdict)

    def _offer(self, item: Any) -> bool:
        while not self._closed.is_set():
            try:
                self._queue.put(item, timeout=POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def get(self, timeout: float) -> Any:
        """The next (request, frames passed), _END, a _Refused, _BROKEN (also once closed with nothing left: the
        reader cannot queue its end then), or None after `timeout` seconds."""
        try:
            item = self._queue.get(timeout=timeout) if timeout > 0 else self._queue.get_nowait()
        except queue.Empty:
            return _BROKEN if self._closed.is_set() else None
        if type(item) is tuple and item[1] is _HELPER:
            return item[0], self._verdicts.get()  # the helper always answers (_frames_pass never raises)
        return item

    def close(self) -> None:
        self._closed.set()


@dataclass
class _InFlight:
    """A batch of one stream submitted to the writer, not yet acknowledged."""

    future: Future[tuple[int, int]]
    seqs: list[int]
    specs: list[robot_pb2.RobotSpec]
    started: float


class ReplayServicer(replay_pb2_grpc.ReplayServicer):
    def __init__(
        self,
        store: ReplayStore,
        spec_source: SpecSource,
        commit_max_steps: int,
        commit_max_delay_s: float,
        seed: int | None = None,
        prefetch_batches: int = 0,
        prefetch_max_age_s: float = 0.05,
        min_size_to_sample: int = 0,
        samples_per_insert: float = 0.0,
        samples_per_insert_slack: float = 0.0,
        shared: SharedBatches | None = None,
    ) -> None:
        """shared: batches through shared memory for same-host learners (None: always through the socket)."""
        self.store = store
        self.shared = shared
        self.prefetch = Prefetcher(prefetch_batches, prefetch_max_age_s, lambda: store.generation)
        self.min_size_to_sample = min_size_to_sample
        self.samples_per_insert = samples_per_insert
        self.samples_per_insert_slack = samples_per_insert_slack
        self.sampled = 0  # transitions handed out (the rate limiter's sample count)
        self.specs = SpecBook(spec_source, store)
        self.episodes = EpisodeGuard()
        self.episodes.seed(store.episode_bounds())  # episodes that ended before a restart stay ended
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
        self.prefetch.close()

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

        def close() -> None:
            inbox.close()
            self._stream_delta(-1)

        ended = rpc.at_stream_end(context, close)  # shutdown waits for this count: it must come down once
        inflight: deque[_InFlight] = deque()
        try:
            yield from self._insert(inbox, context, rpc.caller(context), inflight)
        except Exception:  # an abort: left in flight only after a failed commit, withdraw what the writer has not
            for job in inflight:  # taken (the edge re-sends it; on a full disk it would fail too)
                job.future.cancel()
            raise
        finally:
            ended()

    def InsertBatch(
        self, request_iterator: Iterator[replay_pb2.InsertBatchRequest], context: grpc.ServicerContext
    ) -> Iterator[replay_pb2.InsertAck]:
        """Insert, several steps a message: unpacked in the stream's reader thread, handled step by step."""
        return self.Insert(_unbatched(request_iterator), context)

    def _insert(
        self,
        inbox: _Inbox,
        context: grpc.ServicerContext,
        who: Identity | None = None,
        inflight: deque[_InFlight] | None = None,
    ) -> Iterator[replay_pb2.InsertAck]:
        """Validate while earlier batches commit: up to MAX_IN_FLIGHT batches wait for the writer at once.

        Acks still go out in order and only after the commit that holds their steps. `inflight`: the caller's,
        to withdraw what is left in it when the stream ends early.
        """
        pending: list[replay_pb2.InsertRequest] = []
        inflight = deque() if inflight is None else inflight
        deadline = 0.0
        while True:
            while inflight and (inflight[0].future.done() or len(inflight) >= MAX_IN_FLIGHT):
                yield self._acked(inflight.popleft(), context)
            if self._closing.is_set():
                yield from self._drain(pending, inflight, context)
                context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send unacknowledged steps")
            wait = min(POLL_S, deadline - time.monotonic()) if pending else POLL_S
            item = inbox.get(min(wait, ACK_POLL_S) if inflight else wait)
            if item is None and not context.is_active():  # the client went away: end now, freeing the thread
                item = _BROKEN
            if item is _END:
                yield from self._drain(pending, inflight, context)
                return
            if isinstance(item, _Refused):  # everything before the bad message is committed and acknowledged first
                yield from self._drain(pending, inflight, context)
                context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(item))
            if item is _BROKEN:  # nobody to ack; commit anyway, a re-send is deduplicated
                for _ in self._drain(pending, inflight, context):
                    pass
                return
            if item is not None:
                item, images_checked = item
                RECEIVED.inc()
                if who is not None and not who.owns_robot(item.step.robot_id):  # before _admit records anything
                    failure = (
                        grpc.StatusCode.PERMISSION_DENIED,
                        f"seq {item.seq}: {who.name!r} may not write robot {item.step.robot_id!r}",
                    )
                else:
                    failure = self._admit(item, images_checked)
                if failure is not None:  # everything before the failing step is committed and acknowledged first
                    yield from self._drain(pending, inflight, context)
                    context.abort(*failure)
                pending.append(item)
                if len(pending) == 1:
                    deadline = time.monotonic() + self.commit_max_delay_s
            if pending and (len(pending) >= self.commit_max_steps or time.monotonic() >= deadline):
                inflight.append(self._submit(pending, context))
                pending = []

    def _drain(
        self, pending: list[replay_pb2.InsertRequest], inflight: deque[_InFlight], context: grpc.ServicerContext
    ) -> Iterator[replay_pb2.InsertAck]:
        if pending:
            inflight.append(self._submit(pending, context))
        while inflight:
            yield self._acked(inflight.popleft(), context)

    def _submit(self, pending: list[replay_pb2.InsertRequest], context: grpc.ServicerContext) -> _InFlight:
        specs = self.specs.take_dirty()
        try:
            future = self.store.submit([r.step for r in pending], specs, [r.table or ONLINE for r in pending])
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send unacknowledged steps")
        return _InFlight(future, [r.seq for r in pending], specs, time.perf_counter())

    def _acked(self, job: _InFlight, context: grpc.ServicerContext) -> replay_pb2.InsertAck:
        """Wait for one submitted batch to commit; its ack, or the status that ends the stream."""
        try:
            stored, dups = job.future.result()
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down; re-send unacknowledged steps")
        except Exception as exc:  # nothing of the batch committed: its specs wait for the next commit
            self.specs.restore_dirty(job.specs)
            context.abort(*self._commit_failure(exc))
        COMMIT_SECONDS.observe(time.perf_counter() - job.started)
        COMMIT_STEPS.observe(len(job.seqs))
        STORED.inc(stored)
        DUPLICATES.inc(dups)
        self._update_gauges()
        return replay_pb2.InsertAck(seqs=job.seqs, stored=stored, duplicates=dups)

    @staticmethod
    def _commit_failure(exc: Exception) -> tuple[grpc.StatusCode, str]:
        """The status ending a stream whose batch did not commit (the store logged the disk's state once)."""
        if isinstance(exc, DiskFullError):
            return grpc.StatusCode.RESOURCE_EXHAUSTED, f"{exc}; {RESEND}"
        if isinstance(exc, ReplayFullError):
            log.error("replay full", extra=kv(error=str(exc)))
            return grpc.StatusCode.RESOURCE_EXHAUSTED, str(exc)
        if isinstance(exc, DiskWriteError):
            return grpc.StatusCode.UNAVAILABLE, f"{exc}; {RESEND}"
        log.error("insert commit failed", exc_info=exc)
        return grpc.StatusCode.INTERNAL, f"replay could not commit steps ({exc!r}); {RESEND}"

    def _admit(self, req: replay_pb2.InsertRequest, images_checked: bool = False) -> tuple[grpc.StatusCode, str] | None:
        """None for a valid step; otherwise the status that ends the stream (after the steps before it)."""
        step = req.step
        try:
            problem = self._check(step, images_checked)
            if problem is None and req.table and not TABLE_NAME.match(req.table):
                problem = "table", f"table {req.table[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . -"
            if problem is None and req.table and self.store.too_many_tables(req.table, MAX_STORE_TABLES):
                problem = (
                    "table",
                    f"table {req.table!r} would be table {MAX_STORE_TABLES + 1}; at most {MAX_STORE_TABLES}",
                )
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

    def _check(self, step: step_pb2.Step, images_checked: bool = False) -> tuple[str, str] | None:
        """None when valid, else (metric reason, message). Raises SpecUnavailable."""
        rid = step.robot_id
        if not rid:
            return "robot_id", "robot_id is empty"
        if step.held and step.intervention:  # would be indexed in "interventions" as a human's action
            return "held", "held and intervention are both set: a held step (no action from anyone) is no intervention"
        spec = self.specs.get(rid)
        if spec is None:
            return "unknown_robot", f"unknown robot {rid} (control has no registration for it)"
        try:
            validate_step(step, spec, images_checked)
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
                    validate_step(step, fresh, images_checked)
                    self.episodes.check(step)
                    return None
                except StepError as exc:
                    error = exc
        return error.reason, str(error)

    def _update_gauges(self) -> None:
        try:
            st = self.store.stats()
        except StoreClosedError:
            return
        STEPS.set(st["steps"])
        TRANSITIONS.set(st["transitions"])
        BYTES_ON_DISK.set(st["bytes_on_disk"])
        cache = self.store.cache_info()
        HOT_TRANSITIONS.set(cache["entries"])
        HOT_BYTES.set(cache["bytes"])
        drawn = cache["hits"] + cache["misses"]
        HOT_HIT_RATE.set(cache["hits"] / drawn if drawn else 0.0)
        frames = cache["decoded_hits"] + cache["decoded_misses"]
        DECODED_HIT_RATE.set(cache["decoded_hits"] / frames if frames else 0.0)
        for table in self.store.tables():
            TABLE_TRANSITIONS.labels(table).set(self.store.transitions_for(None, [table]))

    # ------------------------------------------------------------------ Sample / Stats

    def Sample(self, request: replay_pb2.SampleRequest, context: grpc.ServicerContext) -> replay_pb2.SampleResponse:
        problem = sample_request_problem(request)
        if problem is not None:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, problem)
        draw = to_draw(request)
        robot_ids = draw.robot_ids or None
        start = time.perf_counter()
        shm = bool(request.shm_session) and self.shared is not None
        try:
            self._rate_limit(request, robot_ids, context)
            kind = request
            if request.shm_session or request.shm_release:  # the same kind of batch, whichever session asks
                kind = replay_pb2.SampleRequest()
                kind.CopyFrom(request)
                kind.ClearField("shm_session")
                kind.ClearField("shm_release")
            # a shared-memory kind is prefetched as arrays (written into a slot), the other as its proto
            key = kind.SerializeToString(deterministic=True) + (b"\0shm" if shm else b"")
            served = self.prefetch.served
            assembled, size = self.prefetch.get(
                key,
                lambda: self._assemble(draw, request.action_horizon, as_proto=not shm),
                lambda r: r[1] <= (SHM_PREFETCH_MAX_BYTES if shm else PREFETCH_MAX_BYTES),
            )
            if self.prefetch.served > served:
                PREFETCH_SERVED.inc()
            transitions = self.store.transitions_for(robot_ids)
            per_table = {t: self.store.transitions_for(draw.robots_of(t) or None, [t]) for t in draw.tables}
        except (EmptyBufferError, LayoutError) as exc:
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(exc))
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down")
        except ReplayError as exc:  # e.g. a step evicted while the batch was assembled: asking again works
            log.warning("sample aborted", extra=kv(error=str(exc)))
            SAMPLE_ABORTED.inc()
            context.abort(grpc.StatusCode.ABORTED, f"sample raced a change of the buffer, retry: {exc}")
        resp = replay_pb2.SampleResponse(transitions=transitions, table_transitions=per_table)
        if shm and size < SHM_MIN_BYTES:  # a small batch costs less through the socket than a slot round trip
            known = self.shared.release(request.shm_session, list(request.shm_release))  # type: ignore[union-attr]
            resp.shm_reason = "small batch" if known is not None else "unknown session"
            assembled = to_batch(assembled)
        elif shm:
            assert self.shared is not None
            try:
                shared, why = self.shared.write(request.shm_session, list(request.shm_release), assembled)
            except Exception as exc:  # a slot we could not fill: this batch goes through the socket
                log.warning("shared-memory batch not written", extra=kv(error=repr(exc)))
                shared, why = None, "error"
            if shared is not None:
                resp.shared.CopyFrom(shared)
            else:
                SHARED_FALLBACK.labels(why).inc()
                resp.shm_reason = why
                assembled = to_batch(assembled) if size <= MAX_BATCH_BYTES else None
        if size > MAX_BATCH_BYTES and not resp.HasField("shared"):
            per = max(1, size // request.batch_size)
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"a batch of {request.batch_size} is {size} bytes, over the {MAX_BATCH_BYTES}-byte message limit; "
                f"ask for at most {MAX_BATCH_BYTES // per}",
            )
        if not resp.HasField("shared"):
            resp.batch.CopyFrom(assembled)
            if request.encoded_frames:
                b = resp.batch
                FRAMES_KEPT.inc(
                    sum(len(t.frame_bytes) for m in (b.observation, b.next_observation) for t in m.tensors.values())
                )
        with self._count_lock:
            self.sampled += request.batch_size
        SAMPLE_SECONDS.observe(time.perf_counter() - start)
        return resp

    def OpenSharedMemory(
        self, request: replay_pb2.SharedMemoryRequest, context: grpc.ServicerContext
    ) -> replay_pb2.SharedMemoryOffer:
        if len(request.host_id) > 128:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "host_id is at most 128 characters")
        if self.shared is None:
            return replay_pb2.SharedMemoryOffer(reason="shared memory is off (replay.shm_dir)")
        return self.shared.offer(request.host_id)

    def _assemble(
        self, draw: Draw, action_horizon: int = 1, as_proto: bool = True
    ) -> tuple[replay_pb2.Batch | dict[str, Any], int]:
        with self._rng_lock:
            rng = np.random.default_rng(self._rng.integers(1 << 63))
        if draw.encoded_frames and not as_proto:  # a shared-memory slot holds arrays: frames come decoded
            draw = replace(draw, encoded_frames=False)
        arrays = self.store.sample(draw.batch_size, rng, draw=draw)
        add_action_chunks(self.store, arrays, action_horizon)  # the next H actions per row (H > 1)
        size = _nbytes(arrays)
        if not as_proto:
            return arrays, size
        if size > MAX_BATCH_BYTES:
            return replay_pb2.Batch(), size
        return to_batch(arrays), size

    def _rate_limit(
        self, request: replay_pb2.SampleRequest, robot_ids: list[str] | None, context: grpc.ServicerContext
    ) -> None:
        """Reverb-like: a minimum size, and at most samples_per_insert sampled per inserted (plus slack).

        Only samples wait: inserts are never held back, a robot must not stall on the learner.
        """
        if self.min_size_to_sample and self.store.transitions_for(robot_ids) < self.min_size_to_sample:
            raise EmptyBufferError(f"fewer than min_size_to_sample={self.min_size_to_sample} transitions yet")
        if self.samples_per_insert > 0:
            allowed = self.samples_per_insert * self.store.inserted + self.samples_per_insert_slack
            with self._count_lock:
                over = self.sampled + request.batch_size > allowed
            if over:
                RATE_LIMITED.inc()
                context.abort(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"rate limited: {self.sampled} sampled for {self.store.inserted} inserted "
                    f"(samples_per_insert={self.samples_per_insert}); retry after more inserts",
                )

    def UpdatePriorities(
        self, request: replay_pb2.UpdatePrioritiesRequest, context: grpc.ServicerContext
    ) -> replay_pb2.UpdatePrioritiesResponse:
        idx = np.asarray(request.indices, np.int64)
        pri = np.asarray(request.priorities, np.float64)
        if len(idx) != len(pri):
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT, f"{len(idx)} indices but {len(pri)} priorities (must be equal)"
            )
        if len(idx) > MAX_SAMPLE:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"at most {MAX_SAMPLE} priorities per call")
        if len(pri) and (not np.isfinite(pri).all() or (pri < 0).any()):  # any finite float32 >= 0 is stored
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "priorities must be finite and >= 0")
        if len(idx) and (idx < 0).any():
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "indices must be >= 0 (from Batch.indices)")
        try:
            updated = self.store.update_priorities(idx, pri.astype(np.float32))
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down")
        return replay_pb2.UpdatePrioritiesResponse(updated=updated)

    def Stats(self, request: replay_pb2.StatsRequest, context: grpc.ServicerContext) -> replay_pb2.StatsResponse:
        problem = _table_names_problem("spec_tables", request.spec_tables)
        if problem is not None:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, problem)
        try:
            st = self.store.stats()
            tables = self.store.table_stats(counts_only=request.counts_only)  # a timed poll: no walk of every episode
            cache = self.store.cache_info()
            specs, left_out = self.store.table_specs(request.spec_tables, MAX_STATS_SPECS)
        except StoreClosedError:
            context.abort(grpc.StatusCode.UNAVAILABLE, "replay is shutting down")
        return replay_pb2.StatsResponse(
            specs=specs,
            specs_left_out=left_out,
            steps=st["steps"],
            transitions=st["transitions"],
            episodes=st["episodes"],
            bytes_on_disk=st["bytes_on_disk"],
            steps_per_robot=st["steps_per_robot"],
            evicted_steps_per_robot=st["evicted_steps_per_robot"],
            duplicates=st["duplicates"],
            rejected=self.rejected,
            tables={name: _table_stats(t) for name, t in tables.items()},
            hot_transitions=cache["entries"],
            hot_bytes=cache["bytes"],
            hot_hits=cache["hits"],
            hot_misses=cache["misses"],
            evicted_episodes=cache["evicted_episodes"],
            stored_bytes=cache["stored_bytes"],
        )


def _table_stats(t: dict[str, Any]) -> replay_pb2.TableStats:
    return replay_pb2.TableStats(
        transitions=t["transitions"],
        steps=t["steps"],
        episodes=t["episodes"],
        bytes=t["bytes"],
        success_rate=t["success_rate"],
        robots={r: _table_stats({**v, "robots": {}}) for r, v in t.get("robots", {}).items()},
    )


def sample_request_problem(req: replay_pb2.SampleRequest) -> str | None:
    """Why a SampleRequest is invalid, or None."""
    if not 1 <= req.batch_size <= MAX_SAMPLE:
        return f"batch_size must be in 1..{MAX_SAMPLE}, got {req.batch_size}"
    if len(req.tables) > MAX_TABLES:
        return f"at most {MAX_TABLES} tables per sample"
    if (problem := _robot_ids_problem(req.robot_ids)) is not None:
        return problem
    for name, ratio in req.tables.items():
        if not TABLE_NAME.match(name):
            return f"table {name[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . -"
        if not (math.isfinite(ratio) and ratio > 0):
            return f"ratio of table {name!r} must be finite and > 0, got {ratio}"
    if (problem := _table_names_problem("human_tables", req.human_tables)) is not None:
        return problem
    if (problem := _table_robot_ids_problem(req)) is not None:
        return problem
    if req.sampler not in SAMPLERS:
        return f"unknown sampler {req.sampler}"
    if req.frame_stack > MAX_FRAME_STACK:
        return f"frame_stack must be at most {MAX_FRAME_STACK}, got {req.frame_stack}"
    if (problem := horizon_problem(req.action_horizon)) is not None:
        return problem
    if req.n_step > MAX_N_STEP:
        return f"n_step must be at most {MAX_N_STEP}, got {req.n_step}"
    if len(req.shm_session) not in (0, PROBE_BYTES):
        return f"shm_session is the {PROBE_BYTES} bytes of an OpenSharedMemory probe file"
    if len(req.shm_release) > MAX_RELEASE or not all(SHARED_NAME.fullmatch(n) for n in req.shm_release):
        return f"shm_release names at most {MAX_RELEASE} slot files of this replay"
    if req.n_step > 1 and not (0 < req.gamma <= 1):
        return f"gamma must be in (0, 1] for n_step > 1, got {req.gamma}"
    for field, value in (("priority_alpha", req.priority_alpha), ("priority_beta", req.priority_beta)):
        if not (math.isfinite(value) and 0 <= value <= 10):
            return f"{field} must be in [0, 10], got {value}"
    return None


def _table_names_problem(field: str, names: Sequence[str]) -> str | None:
    """Why a list of table names (SampleRequest.human_tables, StatsRequest.spec_tables) is refused, or None (a table
    this replay lacks is fine: it marks, or holds, nothing)."""
    if len(names) > MAX_TABLES:
        return f"{field}: at most {MAX_TABLES} tables, got {len(names)}"
    for i, name in enumerate(names):
        if not TABLE_NAME.fullmatch(name):
            return f"{field}[{i}]: {name[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . -"
    return None


def _robot_ids_problem(robot_ids: Sequence[str], field: str = "robot_ids") -> str | None:
    """Why SampleRequest.robot_ids (or a list of table_robot_ids) is refused (never quoting an id: one may be
    megabytes), or None."""
    if len(robot_ids) > MAX_SAMPLE_ROBOTS:
        return f"{field}: at most {MAX_SAMPLE_ROBOTS} robots per sample, got {len(robot_ids)}"
    for i, rid in enumerate(robot_ids):
        if not rid or len(rid.encode()) > MAX_ROBOT_ID_BYTES:
            return f"{field}[{i}]: a robot id is 1 to {MAX_ROBOT_ID_BYTES} bytes, got {len(rid.encode())}"
    return None


def _table_robot_ids_problem(req: replay_pb2.SampleRequest) -> str | None:
    """Why SampleRequest.table_robot_ids is refused, or None: each key one of `tables`, each list as robot_ids."""
    for table, robots in req.table_robot_ids.items():  # at most MAX_TABLES keys: each is a key of `tables`
        if table not in req.tables:
            return f"table_robot_ids: {table[:80]!r} is not one of tables {sorted(req.tables)}"
        if (problem := _robot_ids_problem(robots.ids, f"table_robot_ids[{table!r}].ids")) is not None:
            return problem
    return None


def to_draw(req: replay_pb2.SampleRequest) -> Draw:
    return Draw(
        batch_size=req.batch_size,
        tables=dict(req.tables),
        robot_ids=sorted(set(req.robot_ids)),
        sampler=SAMPLERS[req.sampler],
        window=req.recency_window,
        alpha=req.priority_alpha or 0.6,
        beta=req.priority_beta or 0.4,
        n_step=max(1, req.n_step),
        gamma=req.gamma or 0.99,
        frame_stack=max(1, req.frame_stack),
        encoded_frames=req.encoded_frames,
        human_tables=tuple(sorted(set(req.human_tables))),
        table_robot_ids={t: sorted(set(r.ids)) for t, r in req.table_robot_ids.items()},
    )


def _nbytes(arrays: dict[str, Any]) -> int:
    total = 0
    for value in arrays.values():
        total += sum(a.nbytes for a in value.values()) if isinstance(value, dict) else value.nbytes
    return total


def to_batch(arrays: dict[str, Any]) -> replay_pb2.Batch:
    """store.sample() arrays -> the wire Batch (RAW tensors; encoded frames as kept, with frame_bytes)."""
    return replay_pb2.Batch(
        observation=wire.to_tensor_map(arrays["observation"]),
        action=wire.to_tensor(arrays["action"]),
        reward=wire.to_tensor(arrays["reward"]),
        next_observation=wire.to_tensor_map(arrays["next_observation"]),
        terminated=wire.to_tensor(arrays["terminated"]),
        truncated=wire.to_tensor(arrays["truncated"]),
        intervention=wire.to_tensor(arrays["intervention"]),
        policy_version=wire.to_tensor(arrays["policy_version"]),
        indices=wire.to_tensor(arrays["indices"]) if "indices" in arrays else None,
        weights=wire.to_tensor(arrays["weights"]) if "weights" in arrays else None,
        n_steps=wire.to_tensor(arrays["n_steps"]) if "n_steps" in arrays else None,
        action_chunk=wire.to_tensor(arrays["action_chunk"]) if "action_chunk" in arrays else None,
        chunk_mask=wire.to_tensor(arrays["chunk_mask"]) if "chunk_mask" in arrays else None,
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
        # held while the service lives, so `userctl replay import` refuses to write behind its index (and a
        # second service on this path refuses to start)
        try:
            self._holder = hold_buffer(rc.path, "the replay service")
        except BufferHeld as exc:
            raise ConfigError(f"replay.path: {exc}") from None
        try:
            self.store = ReplayStore(
                rc.path,
                rc.map_size_mb,
                cache_mb=rc.cache_mb,
                max_map_mb=rc.max_map_mb or 4 * rc.map_size_mb,
                capacity_mb=rc.capacity_mb,
                durability=rc.durability,
                image_encoding=rc.image_encoding,
                decoded_mb=rc.decoded_mb,
                cache_prefault=rc.cache_prefault,
            )
        except BaseException:
            release_buffer(self._holder)
            raise
        try:
            for table, path in rc.attach.items():
                self.store.attach(path, table)
        except BaseException:
            self.store.close()
            release_buffer(self._holder)
            raise
        self.shared = SharedBatches(rc.shm_dir, rc.shm_max_mb << 20, rc.shm_slots) if rc.shm_dir else None
        self._control: ControlSpecSource | None = None
        if spec_source is None:
            self._control = ControlSpecSource(rc.control_addr, cfg.auth, rc.rpc_timeout_s)
            spec_source = self._control
        self.servicer = ReplayServicer(
            self.store,
            spec_source,
            rc.commit_max_steps,
            rc.commit_max_delay_ms / 1000.0,
            prefetch_batches=rc.prefetch_batches,
            prefetch_max_age_s=rc.prefetch_max_age_ms / 1000.0,
            min_size_to_sample=rc.min_size_to_sample,
            samples_per_insert=rc.samples_per_insert,
            samples_per_insert_slack=rc.samples_per_insert_slack,
            shared=self.shared,
        )
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
        release_buffer(self._holder)
        if self.shared is not None:
            self.shared.close()
        if self._control is not None:
            self._control.close()


def run(cfg: StackConfig, ready_file: str | None) -> int:
    rpc.serve_until_signal(ReplayService(cfg), "replay", ready_file)
    return 0
