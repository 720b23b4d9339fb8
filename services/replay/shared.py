"""Sample batches through shared memory for learners on replay's host (OpenSharedMemory, SharedBatch).

A batch of 256 transitions with two 128x128 cameras is ~50 MB. Through the socket it is copied about
eight times (arrays -> proto -> serialized -> gRPC -> received -> parsed -> bytes -> arrays); a learner on
the same host instead gets a slot file in replay's shared-memory directory that replay wrote the arrays
into, and copies them out once. Same host is proven, never assumed: OpenSharedMemory answers a caller
with replay's boot id with a probe file (0600, a random nonce); the caller echoes its bytes in
SampleRequest.shm_session, which only a reader of this directory as this user can.

Each session owns up to `slots` slot files, reused (their tmpfs pages stay: a rewrite costs no page
faults). A slot is the caller's from the response that names it until a later request lists it in
shm_release; with no free slot, or past `max_bytes` in all, the batch goes through the socket as usual.
Sessions idle for IDLE_S are closed and their files removed; a replay killed without close leaves its
files to the next replay's sweep (user/shm_files.py).
"""

from __future__ import annotations

import hmac
import logging
import mmap
import os
import secrets
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import prometheus_client

from user import wire
from user.log import kv
from user.shm_files import PROBE_BYTES, ShmOwner, create_private, host_id, name_pattern
from user.v1 import replay_pb2

log = logging.getLogger(__name__)

PREFIX = "user-replay-"
NAME = name_pattern(PREFIX)
IDLE_S = 60.0  # a session nobody sampled with for this long is closed
ALIGN = 64  # array offsets in a slot: cache-line aligned
MAX_SESSIONS = 64

SHARED_BATCHES = prometheus_client.Counter(
    "user_replay_shm_batches_total", "Sample batches handed to same-host learners through shared memory"
)
SHARED_FALLBACK = prometheus_client.Counter(
    "user_replay_shm_fallback_total",
    "Shared-memory sample requests answered through the socket instead",
    ["reason"],
)


def batch_arrays(arrays: dict[str, Any]) -> list[tuple[str, np.ndarray]]:
    """store.sample() arrays as (SharedArray name, array), in a fixed order."""
    out: list[tuple[str, np.ndarray]] = []
    for part in ("observation", "next_observation"):
        out += [(f"{part}/{key}", arr) for key, arr in sorted(arrays[part].items())]
    out += [(name, arr) for name, arr in arrays.items() if isinstance(arr, np.ndarray)]
    return out


@dataclass
class _Slot:
    name: str
    map: mmap.mmap
    nbytes: int
    busy: bool = True  # the caller holds it (or replay is writing it)


def _unmap(slot: _Slot) -> None:
    try:
        slot.map.close()
    except BufferError:  # a write into it is still under way (close at shutdown): unmapped when it lets go
        pass


@dataclass
class _Session:
    key: str  # short id in file names
    probe: str  # the probe file (removed at the first sample)
    slots: dict[str, _Slot] = field(default_factory=dict)
    last_used: float = field(default_factory=time.monotonic)


class SharedBatches:
    """Replay's side: sessions, their slot files, and writing a batch into a free slot (thread-safe)."""

    def __init__(self, directory: str, max_bytes: int, slots: int = 8, host: str | None = None) -> None:
        self.directory, self.max_bytes, self.slots = directory, max_bytes, max(1, slots)
        self.host = host_id() if host is None else host
        self.owner = ShmOwner(directory, PREFIX)
        self._sessions: dict[bytes, _Session] = {}
        self._bytes = 0
        self._lock = threading.Lock()
        self._expired_at = time.monotonic()

    # ------------------------------------------------------------------ sessions

    def offer(self, caller_host: str) -> replay_pb2.SharedMemoryOffer:
        """A probe file for a caller on this host, or the reason there is none."""
        if not self.host or not hmac.compare_digest(self.host.encode(), caller_host.encode()):
            return replay_pb2.SharedMemoryOffer(reason="another host (boot ids differ)")
        self._expire()
        with self._lock:
            if self.owner.closed:
                return replay_pb2.SharedMemoryOffer(reason="replay is shutting down")
            if len(self._sessions) >= MAX_SESSIONS:
                return replay_pb2.SharedMemoryOffer(reason=f"{MAX_SESSIONS} sessions open")
        nonce, key = secrets.token_bytes(PROBE_BYTES), secrets.token_hex(4)
        probe = f"{PREFIX}{self.owner.token}-{key}-probe"
        try:
            self._write_probe(probe, nonce)
        except OSError as exc:
            return replay_pb2.SharedMemoryOffer(reason=f"cannot write to {self.directory}: {exc.strerror}")
        with self._lock:
            self._sessions[nonce] = _Session(key, probe)
        return replay_pb2.SharedMemoryOffer(probe_file=probe)

    def _write_probe(self, name: str, nonce: bytes) -> None:
        self.owner.hold()
        fd = create_private(os.path.join(self.directory, name))
        try:
            if os.write(fd, nonce) != len(nonce):
                raise OSError(28, "short write")  # ENOSPC
        except OSError:
            self.owner.unlink(name)
            raise
        finally:
            os.close(fd)

    def _expire(self) -> None:
        """Close sessions idle for IDLE_S (a learner that died, or moved to a new session)."""
        now = time.monotonic()
        with self._lock:
            self._expired_at = now
            idle = [n for n, s in self._sessions.items() if now - s.last_used > IDLE_S]
            for nonce in idle:
                self._close_session(self._sessions.pop(nonce))

    def _close_session(self, session: _Session) -> None:
        """Under the lock: the session's files go (a caller still copying keeps its pages until it unmaps)."""
        self.owner.unlink(session.probe)
        for slot in session.slots.values():
            self._bytes -= slot.nbytes
            self.owner.unlink(slot.name)
            _unmap(slot)
        session.slots.clear()

    def sessions(self) -> int:
        with self._lock:
            return len(self._sessions)

    # ------------------------------------------------------------------ batches

    def write(
        self, nonce: bytes, release: list[str], arrays: dict[str, Any]
    ) -> tuple[replay_pb2.SharedBatch | None, str]:
        """(the batch in a slot of the session, "") or (None, why not: the caller answers through the socket)."""
        self._expire_now_and_then()
        named = batch_arrays(arrays)
        layout, total = [], 0
        for name, arr in named:
            total = -(-total // ALIGN) * ALIGN
            layout.append((name, arr, total))
            total += arr.nbytes
        slot, why = self._take(nonce, release, max(total, 1))
        if slot is None:
            return None, why
        try:
            view = np.frombuffer(slot.map, dtype=np.uint8)
            out = replay_pb2.SharedBatch(file=slot.name, file_bytes=slot.nbytes)
            for name, arr, offset in layout:
                flat = np.ascontiguousarray(arr).reshape(-1).view(np.uint8)
                view[offset : offset + flat.size] = flat
                out.arrays.add(name=name, dtype=wire.dtype_to_proto(arr.dtype), shape=arr.shape, offset=offset)
            del view
        except BaseException:
            with self._lock:
                slot.busy = False
            raise
        SHARED_BATCHES.inc()
        return out, ""

    def _expire_now_and_then(self) -> None:
        if time.monotonic() - self._expired_at > 1.0:
            self._expire()

    def release(self, nonce: bytes, release: list[str]) -> _Session | None:
        """Free the slots the caller is done with; its session (None if unknown)."""
        self._expire_now_and_then()
        with self._lock:
            return self._release(nonce, release)

    def _release(self, nonce: bytes, release: list[str]) -> _Session | None:
        session = self._sessions.get(nonce)
        if session is None:
            return None
        session.last_used = time.monotonic()
        if session.probe:  # proven: the caller read it
            self.owner.unlink(session.probe)
            session.probe = ""
        for name in release:
            if name in session.slots:
                session.slots[name].busy = False
        return session

    def _take(self, nonce: bytes, release: list[str], nbytes: int) -> tuple[_Slot | None, str]:
        """A free slot of at least nbytes, marked busy (released ones freed first); (None, reason) if none."""
        with self._lock:
            session = self._release(nonce, release)
            if session is None:
                return None, "unknown session"
            free = [s for s in session.slots.values() if not s.busy]
            fits = [s for s in free if s.nbytes >= nbytes]
            if fits:
                slot = min(fits, key=lambda s: s.nbytes)
                slot.busy = True
                return slot, ""
            if free and len(session.slots) >= self.slots:  # all made, some free but small: replace one
                small = free[0]
                del session.slots[small.name]
                self._bytes -= small.nbytes
                self.owner.unlink(small.name)
                _unmap(small)
            if len(session.slots) >= self.slots:
                return None, "no free slot"
            if self._bytes + nbytes > self.max_bytes:
                return None, "shared-memory budget"
            name = f"{PREFIX}{self.owner.token}-{session.key}-{secrets.token_hex(4)}"
            self._bytes += nbytes  # reserved before the file exists: racing requests cannot overshoot
        try:
            slot = _Slot(name, self._create(name, nbytes), nbytes)
        except OSError as exc:
            with self._lock:
                self._bytes -= nbytes
            log.info("no shared-memory slot", extra=kv(error=str(exc)))
            return None, "directory full"
        with self._lock:
            if self._sessions.get(nonce) is session:
                session.slots[name] = slot
                return slot, ""
            self._bytes -= nbytes  # the session closed meanwhile
        self.owner.unlink(name)
        _unmap(slot)
        return None, "unknown session"

    def _create(self, name: str, nbytes: int) -> mmap.mmap:
        self.owner.hold()
        fd = create_private(os.path.join(self.directory, name))
        try:
            # every page now, or ENOSPC now: a write through the map into a full tmpfs would be a SIGBUS later
            os.posix_fallocate(fd, 0, nbytes)
            return mmap.mmap(fd, nbytes, mmap.MAP_SHARED)
        except BaseException:
            self.owner.unlink(name)
            raise
        finally:
            os.close(fd)

    def close(self) -> None:
        with self._lock:
            for session in self._sessions.values():
                self._close_session(session)
            self._sessions.clear()
        self.owner.close()
