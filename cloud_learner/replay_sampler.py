"""Sampling from several replay shards as if they were one buffer.

Each site writes to its own replay process (control assigns the shard, see ControlConfig.replay_shards);
the learner asks `ShardedSampler.Sample` for a batch like it asks one replay's stub. A batch of n is
split across the live shards by a multinomial draw with probabilities proportional to their sampleable
transitions (so every stored transition is equally likely, whichever shard holds it), the shards are
asked in parallel and their Batch protos concatenated. A shard that fails is marked down and skipped,
re-probed with Stats after a growing backoff, and sampled again as soon as it answers (its data is on
its disk: it is back with it). The part of a batch a shard failed to deliver is re-asked of the others.

Errors look like the stub's (grpc.RpcError with code()): FAILED_PRECONDITION when every live shard is
empty, UNAVAILABLE when none is live.
"""

from __future__ import annotations

import logging
import math
import mmap
import os
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np
import prometheus_client

from user import rpc, wire
from user.config import AuthConfig, LearnerConfig
from user.log import kv
from user.shm_files import host_id, name_pattern, open_regular
from user.v1 import replay_pb2, replay_pb2_grpc, tensor_pb2
from user.wire import WireError

log = logging.getLogger(__name__)

SHARD_UP = prometheus_client.Gauge("user_learner_replay_shard_up", "1 while a replay shard answers", ["addr"])
SHARD_TRANSITIONS = prometheus_client.Gauge(
    "user_learner_replay_shard_transitions", "Sampleable transitions last reported by a replay shard", ["addr"]
)
SHARD_SAMPLED = prometheus_client.Counter(
    "user_learner_replay_shard_sampled_total", "Transitions sampled from a replay shard", ["addr"]
)
SHM_BATCHES = prometheus_client.Counter(
    "user_learner_replay_shm_batches_total", "Batches taken from replay's shared-memory slots (same host)"
)
SHM_SESSIONS = prometheus_client.Counter(
    "user_learner_replay_shm_sessions_total",
    "Shared-memory sessions opened with replay (it proved to share its directory)",
)
SHM_SOCKET = prometheus_client.Counter(
    "user_learner_replay_shm_socket_total",
    "Batches asked for through shared memory that came through the socket (no session or slot, a bad slot)",
)


class SamplerError(grpc.RpcError):
    """What Sample raises, shaped like a stub's error so callers handle both alike."""

    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(details)
        self._code, self._details = code, details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


@dataclass
class Shard:
    addr: str
    channel: grpc.Channel
    stub: replay_pb2_grpc.ReplayStub
    transitions: int = 0
    up: bool = False
    known: bool = False  # answered at least once since it was last down
    retry_at: float = 0.0  # down, or empty: next Stats probe at this time
    probing: bool = False  # a Stats probe is in flight
    backoff_s: float = 0.0


class ShardedSampler:
    """`Sample(request, timeout)` over `addrs`, like ReplayStub.Sample over one replay."""

    def __init__(
        self,
        addrs: list[str],
        auth: AuthConfig,
        timeout_s: float = 10.0,
        seed: int | None = None,
        min_backoff_s: float = 0.2,
        max_backoff_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not addrs or len(set(addrs)) != len(addrs):
            raise ValueError(f"need distinct replay addresses, got {addrs}")
        self.timeout_s = timeout_s
        self.min_backoff_s, self.max_backoff_s = min_backoff_s, max_backoff_s
        self._clock = clock
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()  # one Sample at a time: shard state and rng are not shared
        self.shards = []
        for addr in addrs:
            channel = rpc.make_channel(addr, auth)
            self.shards.append(Shard(addr, channel, replay_pb2_grpc.ReplayStub(channel)))
        # A probe of a silent shard may hold a worker for `timeout` while the others are sampled.
        self._pool = ThreadPoolExecutor(max_workers=2 * len(addrs), thread_name_prefix="replay-shard")

    # ------------------------------------------------------------------ the stub's call

    def Sample(self, request: replay_pb2.SampleRequest, timeout: float | None = None) -> replay_pb2.SampleResponse:
        timeout = timeout or self.timeout_s
        with self._lock:
            self._probe(timeout)
            batches: list[replay_pb2.Batch] = []
            missing, failed = int(request.batch_size), set()
            for _ in range(len(self.shards)):  # a round per shard at most: each failure removes one
                ready = [s for s in self.shards if s.up and s.transitions > 0 and s.addr not in failed]
                if missing <= 0 or not ready:
                    break
                sizes = np.array([s.transitions for s in ready], dtype=float)
                counts = self._rng.multinomial(missing, sizes / sizes.sum())
                asked = [(s, int(c)) for s, c in zip(ready, counts, strict=True) if c > 0]
                futures = [self._pool.submit(self._sample_one, s, request, c, timeout) for s, c in asked]
                for (shard, _), future in zip(asked, futures, strict=True):
                    batch = future.result()
                    if batch is None:
                        failed.add(shard.addr)  # its share goes to the others next round
                    else:
                        batches.append(batch)
                        missing -= _batch_len(batch)
            if not batches:
                raise self._nothing_error()
            return replay_pb2.SampleResponse(
                batch=merge_batches(batches), transitions=sum(s.transitions for s in self.shards if s.up)
            )

    def Stats(self, request: replay_pb2.StatsRequest, timeout: float | None = None) -> replay_pb2.StatsResponse:
        """Counts summed over the shards that answer (steps, transitions, episodes, steps per robot):
        sync mode's env-step count. UNAVAILABLE when none answers."""
        timeout = timeout or self.timeout_s
        futures = [self._pool.submit(s.stub.Stats, request, timeout=timeout) for s in self.shards]
        out, answered = replay_pb2.StatsResponse(), 0
        for future in futures:
            try:
                part = future.result()
            except grpc.RpcError:
                continue
            answered += 1
            out.steps += part.steps
            out.transitions += part.transitions
            out.episodes += part.episodes
            for robot_id, n in part.steps_per_robot.items():
                out.steps_per_robot[robot_id] += n
        if not answered:
            raise self._nothing_error()
        return out

    def close(self) -> None:
        self._pool.shutdown(wait=False)
        for shard in self.shards:
            shard.channel.close()

    # ------------------------------------------------------------------ shard health

    def _probe(self, timeout: float) -> None:
        """Stats of every shard not known up with data whose retry time has come. The first probe of a shard
        is waited for (the first batches must see every shard); a re-probe only while no shard can be
        sampled: a shard gone silent (a black-holed link) must not stall the others."""
        now = self._clock()
        due = [s for s in self.shards if not (s.up and s.transitions > 0) and now >= s.retry_at and not s.probing]
        first = [s for s in due if not s.known]
        for shard in due:
            shard.probing = True
        futures = {self._pool.submit(self._stats, s, timeout): s for s in due}
        wait([f for f, s in futures.items() if s in first], timeout=timeout)
        pending = {f for f in futures if not f.done()}
        end = self._clock() + timeout
        while pending and not any(s.up and s.transitions > 0 for s in self.shards) and self._clock() < end:
            _, pending = wait(pending, timeout=max(0.0, end - self._clock()), return_when=FIRST_COMPLETED)

    def _stats(self, shard: Shard, timeout: float) -> None:
        try:
            stats = shard.stub.Stats(replay_pb2.StatsRequest(), timeout=timeout)
        except grpc.RpcError as err:
            self._mark_down(shard, err)
            return
        finally:
            shard.probing = False
        self._mark_up(shard, int(stats.transitions))
        if not shard.transitions:  # empty: look again later, without hammering it
            shard.retry_at = self._clock() + self.min_backoff_s

    def _sample_one(
        self, shard: Shard, request: replay_pb2.SampleRequest, n: int, timeout: float
    ) -> replay_pb2.Batch | None:
        req = replay_pb2.SampleRequest()
        req.CopyFrom(request)  # the same tables, sampler, n-step, frame stack and action horizon
        req.batch_size = n
        try:
            resp = shard.stub.Sample(req, timeout=timeout)
        except grpc.RpcError as err:
            if err.code() == grpc.StatusCode.FAILED_PRECONDITION:  # nothing sampleable there (for these robots)
                self._mark_up(shard, 0)
                shard.retry_at = self._clock() + self.min_backoff_s
            else:
                self._mark_down(shard, err)
            return None
        self._mark_up(shard, int(resp.transitions))
        SHARD_SAMPLED.labels(shard.addr).inc(n)
        return resp.batch

    def _mark_up(self, shard: Shard, transitions: int) -> None:
        if not shard.up:
            log.info("replay shard up", extra=kv(addr=shard.addr, transitions=transitions))
        shard.up, shard.known, shard.transitions, shard.backoff_s = True, True, transitions, 0.0
        SHARD_UP.labels(shard.addr).set(1)
        SHARD_TRANSITIONS.labels(shard.addr).set(transitions)

    def _mark_down(self, shard: Shard, err: grpc.RpcError) -> None:
        code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
        if shard.up or not shard.known:
            log.warning("replay shard down; sampling the others", extra=kv(addr=shard.addr, code=str(code)))
        shard.backoff_s = min(self.max_backoff_s, max(self.min_backoff_s, 2 * shard.backoff_s))
        shard.up, shard.known = False, True
        shard.retry_at = self._clock() + shard.backoff_s
        SHARD_UP.labels(shard.addr).set(0)

    def _nothing_error(self) -> SamplerError:
        if any(s.up for s in self.shards):
            return SamplerError(grpc.StatusCode.FAILED_PRECONDITION, "every live replay shard is empty")
        down = ", ".join(s.addr for s in self.shards)
        return SamplerError(grpc.StatusCode.UNAVAILABLE, f"no replay shard answers ({down})")


def replay_source(
    lc: LearnerConfig, auth: AuthConfig, channel: grpc.Channel
) -> replay_pb2_grpc.ReplayStub | ShardedSampler | SharedMemoryReplay:
    """What the learner samples from: the one replay on `channel` (through shared memory where it proves to be on
    this host), or every shard of lc.replay_addrs."""
    if lc.replay_addrs:
        return ShardedSampler(lc.replay_addrs, auth, lc.rpc_timeout_s, seed=lc.seed)
    stub = replay_pb2_grpc.ReplayStub(channel)
    return SharedMemoryReplay(stub, lc.replay_shm_dir) if lc.replay_shm_dir else stub


# --------------------------------------------------------------------------- same host: shared memory

SLOT_NAME = name_pattern("user-replay-")  # services/replay/shared.py's PREFIX
NONCE_BYTES = 32
REOPEN_S = 30.0  # after a session is refused or lost, the next OpenSharedMemory waits this long
MAX_MAPPED = 80  # slot mappings kept (replay.shm_slots is at most 64 per session)
# a Sample that failed with these may have filled a slot after all (the answer was lost)
LOST_ANSWER = (
    grpc.StatusCode.DEADLINE_EXCEEDED,
    grpc.StatusCode.CANCELLED,
    grpc.StatusCode.UNAVAILABLE,
    grpc.StatusCode.UNKNOWN,
    grpc.StatusCode.INTERNAL,
)


class SharedArrays(dict[str, np.ndarray]):
    """A batch copied out of a shared-memory slot: arrays by SharedArray name ("action", "observation/<key>")."""


@dataclass
class SharedSample:
    """What SharedMemoryReplay.Sample returns for a batch that came through shared memory (shaped like a
    SampleResponse where the learner reads it)."""

    batch: SharedArrays
    transitions: int
    table_transitions: dict[str, int]


def shared_arrays(base: np.ndarray, shared: replay_pb2.SharedBatch) -> SharedArrays:
    """The batch's arrays as views of `base` (the slot's bytes), each checked to lie inside it; WireError else."""
    arrays = SharedArrays()
    for arr in shared.arrays:
        dtype = wire.dtype_from_proto(arr.dtype)
        shape = tuple(int(d) for d in arr.shape)
        nbytes = math.prod(shape) * dtype.itemsize
        if any(d < 0 for d in shape) or arr.offset + nbytes > base.nbytes or arr.name in arrays:
            raise WireError(f"slot {shared.file}: array {arr.name[:80]!r} {shape} does not fit")
        arrays[arr.name] = base[arr.offset : arr.offset + nbytes].view(dtype).reshape(shape)
    return arrays


@dataclass
class _Mapped:
    """A slot file this learner keeps mapped: reading a batch in it costs no copy and, after its first, no page
    faults. `held` while arrays of the batch last read from it may be alive (they view `base`)."""

    map: mmap.mmap
    base: np.ndarray
    session: bytes = b""  # the session it was handed out in
    held: bool = False

    def in_use(self) -> bool:
        return sys.getrefcount(self.base) > 2  # this attribute, getrefcount's argument; every view adds one

    def close(self) -> bool:
        """Unmap if nothing views it; whether it was."""
        if self.in_use():
            return False
        del self.base
        try:
            self.map.close()
        except BufferError:  # a view appeared after all (another thread): the map goes when it does
            pass
        return True


def map_slot(directory: str, shared: replay_pb2.SharedBatch) -> _Mapped:
    """Map a slot file (our name, no links, a regular file of the stated size); WireError otherwise."""
    fd = open_regular(directory, shared.file, SLOT_NAME, writable=True)  # writable: the batch is the learner's
    try:
        size = os.fstat(fd).st_size
        if size != shared.file_bytes or size == 0:
            raise WireError(f"slot {shared.file}: {size} bytes, the response says {shared.file_bytes}")
        mapped = mmap.mmap(fd, size, mmap.MAP_SHARED)
    except OSError as exc:
        raise WireError(f"slot {shared.file}: {exc.strerror}") from exc
    finally:
        os.close(fd)
    return _Mapped(mapped, np.frombuffer(mapped, dtype=np.uint8))


class SharedMemoryReplay:
    """The replay stub, with Sample's batches taken from replay's shared-memory slots when it proves to be on
    this host (OpenSharedMemory), through the socket otherwise. One per sampling thread's channel; other calls
    go to the stub.

    A batch's arrays are views of the slot file, mapped once and kept mapped: no copy. The slot is released to
    replay (SampleRequest.shm_release) with the first request after every array of that batch is gone, so a
    learner holding batches in its prefetch queue holds their slots (replay.shm_slots per session)."""

    def __init__(self, stub: replay_pb2_grpc.ReplayStub, directory: str) -> None:
        self.stub, self.directory = stub, directory
        self._nonce = b""
        self._open_after = 0.0
        self._mapped: OrderedDict[str, _Mapped] = OrderedDict()  # slot name -> its mapping, oldest use first
        self._unsent: list[str] = []  # slots released here, not yet told to replay by a call that succeeded
        self._lock = threading.Lock()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stub, name)

    def _open(self, timeout: float) -> None:
        if time.monotonic() < self._open_after:
            return
        self._open_after = time.monotonic() + REOPEN_S
        try:
            offer = self.stub.OpenSharedMemory(replay_pb2.SharedMemoryRequest(host_id=host_id()), timeout=timeout)
        except grpc.RpcError as err:  # e.g. UNIMPLEMENTED by an older replay: the socket it is
            log.info("replay offers no shared memory", extra=kv(code=err.code().name))
            return
        if not offer.probe_file:
            log.info("replay offers no shared memory", extra=kv(reason=offer.reason))
            return
        try:
            fd = open_regular(self.directory, offer.probe_file, SLOT_NAME)
        except WireError as exc:
            log.info("replay's shared memory is not ours", extra=kv(error=str(exc)))
            return
        try:
            nonce = os.read(fd, NONCE_BYTES + 1)
        finally:
            os.close(fd)
        if len(nonce) == NONCE_BYTES:
            self._nonce = nonce
            SHM_SESSIONS.inc()
            log.info("replay batches through shared memory", extra=kv(directory=self.directory))

    def _released(self) -> list[str]:
        """Slots to release: those whose batch nobody views any more, and any a failed call did not deliver.
        Old mappings are dropped."""
        for name, mapped in list(self._mapped.items()):
            if mapped.session != self._nonce:  # a past session's (replay restarted): its file is gone, unmap it
                if mapped.close():
                    del self._mapped[name]
            elif mapped.held and not mapped.in_use():
                mapped.held = False
                self._unsent.append(name)
        while len(self._mapped) > MAX_MAPPED:  # slots replay replaced or a past session's: unmap the oldest free
            name = next((n for n, m in self._mapped.items() if not m.held and not m.in_use()), None)
            if name is None or not self._mapped.pop(name).close():
                break
        return list(self._unsent)

    def _drop_session(self, reopen_in: float) -> None:
        """Stop using this session (its slots idle out at replay); a new one is opened after `reopen_in`."""
        self._nonce, self._open_after = b"", time.monotonic() + reopen_in
        self._unsent.clear()
        for name in [n for n, m in self._mapped.items() if not m.held]:
            if self._mapped[name].close():
                del self._mapped[name]

    def Sample(self, request: replay_pb2.SampleRequest, timeout: float) -> Any:
        with self._lock:
            if not self._nonce:
                self._open(timeout)
            if not self._nonce:
                self._released()  # unmaps what past sessions handed out, once free
                self._unsent.clear()
                return self.stub.Sample(request, timeout=timeout)
            ask = replay_pb2.SampleRequest()
            ask.CopyFrom(request)
            ask.shm_session = self._nonce
            ask.shm_release.extend(self._released())
            try:
                resp = self.stub.Sample(ask, timeout=timeout)
            except grpc.RpcError as err:
                if err.code() in LOST_ANSWER:  # replay may have filled a slot we never heard of: a new session
                    self._drop_session(0.0)
                raise  # else refused before any slot was touched: the releases go again with the next call
            self._unsent.clear()
            if not resp.HasField("shared"):
                if resp.shm_reason != "small batch":
                    SHM_SOCKET.inc()
                held = any(m.held for m in self._mapped.values())
                # replay restarted or the session idled out; or every slot is taken while we hold none (a slot
                # filled for an answer that never arrived): a new session
                if resp.shm_reason == "unknown session" or (resp.shm_reason == "no free slot" and not held):
                    self._drop_session(0.0)
                return resp
            try:
                arrays = self._read(resp.shared)
            except WireError as exc:
                log.warning("bad shared-memory batch; through the socket now", extra=kv(error=str(exc)))
                SHM_SOCKET.inc()
                self._drop_session(REOPEN_S)
                return self.stub.Sample(request, timeout=timeout)
            SHM_BATCHES.inc()
            return SharedSample(arrays, int(resp.transitions), dict(resp.table_transitions))

    def _read(self, shared: replay_pb2.SharedBatch) -> SharedArrays:
        mapped = self._mapped.get(shared.file)
        if mapped is not None and mapped.held:
            raise WireError(f"slot {shared.file} came back before this learner released it")
        if mapped is None or mapped.base.nbytes != shared.file_bytes:
            if mapped is not None and mapped.close():
                del self._mapped[shared.file]
            mapped = map_slot(self.directory, shared)
            mapped.session = self._nonce
            self._mapped[shared.file] = mapped
        self._mapped.move_to_end(shared.file)
        arrays = shared_arrays(mapped.base, shared)
        mapped.held = True
        return arrays


# --------------------------------------------------------------------------- batches


def _batch_len(batch: replay_pb2.Batch) -> int:
    return int(batch.reward.shape[0]) if batch.reward.shape else 0


def merge_batches(batches: list[replay_pb2.Batch]) -> replay_pb2.Batch:
    """Concatenate batches along the leading dimension, field by field (same keys and dtypes required)."""
    if len(batches) == 1:
        return batches[0]
    out = replay_pb2.Batch()
    for field in replay_pb2.Batch.DESCRIPTOR.fields:
        name = field.name
        present = [b for b in batches if b.HasField(name)]
        if not present:
            continue
        if len(present) != len(batches):
            raise SamplerError(grpc.StatusCode.FAILED_PRECONDITION, f"replay shards disagree: {name} missing in some")
        if field.message_type.name == tensor_pb2.TensorMap.DESCRIPTOR.name:
            keys = set(getattr(present[0], name).tensors)
            if any(set(getattr(b, name).tensors) != keys for b in present):
                raise SamplerError(grpc.StatusCode.FAILED_PRECONDITION, f"replay shards disagree on {name} keys")
            getattr(out, name).CopyFrom(
                wire.to_tensor_map({k: _concat([getattr(b, name).tensors[k] for b in present]) for k in sorted(keys)})
            )
        else:
            getattr(out, name).CopyFrom(wire.to_tensor(_concat([getattr(b, name) for b in present])))
    return out


def _concat(tensors: list[tensor_pb2.Tensor]) -> np.ndarray:
    try:
        arrays = [wire.from_tensor(t) for t in tensors]
    except wire.WireError as exc:
        raise SamplerError(grpc.StatusCode.INTERNAL, f"a replay shard sent an undecodable tensor: {exc}") from None
    if len({(a.dtype, a.shape[1:]) for a in arrays}) != 1:
        raise SamplerError(grpc.StatusCode.FAILED_PRECONDITION, "replay shards disagree on a tensor's dtype or shape")
    return np.concatenate(arrays)
