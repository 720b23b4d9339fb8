"""Replay batches through shared memory for a learner on replay's host (the client of services/replay/shared.py).

The learner proves it reads replay's shared-memory directory (Replay.OpenSharedMemory: it echoes the bytes of a
probe file replay wrote there), then each large batch arrives as a slot file replay filled. The slot stays mapped
here and the batch's arrays are views of it (no copy); the slot goes back to replay with the first request after
every array of that batch is gone. Anything amiss answers through the socket in the same call.
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
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np
import prometheus_client

from user import wire
from user.log import kv
from user.shm_files import PROBE_BYTES, host_id, name_pattern, open_regular, read_probe
from user.v1 import replay_pb2, replay_pb2_grpc
from user.wire import WireError

log = logging.getLogger(__name__)

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


SLOT_NAME = name_pattern("user-replay-")  # services/replay/shared.py's PREFIX
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
    """A batch from a shared-memory slot: arrays (views of the slot) by SharedArray name ("action",
    "observation/<key>")."""


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
        nonce = read_probe(self.directory, offer.probe_file, SLOT_NAME)
        if len(nonce) != PROBE_BYTES:
            log.info("replay's shared-memory directory is not this one", extra=kv(directory=self.directory))
        else:
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
