"""Same-host weight versions through shared memory (WEIGHT_ENCODING_FP32_SHM).

A subscriber on the learner's machine (an inference service beside it, a compose stack on one box)
gets a version as a file in a shared-memory directory (tmpfs, /dev/shm by default) instead of its bytes
through the gRPC socket: the stream carries only the header naming the file.

Same host is never assumed from an address. The subscriber announces its host identity (the Linux boot
id) and the server, if it is its own, proves per stream that the subscriber reads the files it writes:
it writes a random nonce file, names it in a WeightShmProbe, and uses shared memory only if the
subscriber's ack echoes the nonce (containers share a boot id but not always /dev/shm; another user
cannot read our 0600 files). The digest of the payload is checked as for any full set, so a file that
was tampered with, truncated or replaced is rejected and the version is sent over the stream instead.

Server side (`ShmWeights`): each (experiment, version, selection) is written once (0600, under a
temporary name, then renamed), shared by every shared-memory subscriber; the newest `keep` versions
per experiment stay, older files are unlinked, and the whole is bounded in bytes. drop(experiment) removes a removed
experiment's files (it never publishes again to evict them), close() all of them.
The learner's payload buffers may themselves live here (`buffer`, a mapped hidden file): a version packed
into one is published by a hard link to it, with no copy at all. Each learner flocks a lock file here for its
whole life; the next learner removes the files of any whose lock is free (it died: kill -9, a container killed).
Client side (`read_probe`, `read_payload`): file names are checked (no directory part, our prefix),
files are opened without following links and must be regular files of exactly the declared size.
"""

from __future__ import annotations

import hmac
import logging
import mmap
import os
import re
import secrets
import threading
import weakref
from collections import OrderedDict, deque

import numpy as np
import prometheus_client

from user import shm_files
from user.shm_files import LOCK_SUFFIX, PROBE_BYTES, ShmOwner, create_private, host_id, open_regular
from user.wire import WireError

__all__ = ["LOCK_SUFFIX", "ShmWeights", "host_id", "read_payload", "read_probe"]

log = logging.getLogger(__name__)

DEFAULT_SHM_DIR = "/dev/shm"
PREFIX = "user-weights-"
DEFAULT_KEEP = 3  # versions per experiment: a subscriber still opening the previous one finds it
DEFAULT_MAX_BYTES = 2 << 30  # of all files together (tmpfs is RAM)
MIN_BUFFER_BYTES = 1 << 20  # smaller payloads are not pooled (BufferPool): a file each would cost more than a copy
_NAME = re.compile(r"user-weights-[A-Za-z0-9_.-]{1,200}")

SHM_WRITTEN = prometheus_client.Counter(
    "user_weights_shm_written_total", "Weight versions written to shared memory for same-host subscribers"
)
SHM_FALLBACK = prometheus_client.Counter(
    "user_weights_shm_fallback_total",
    "Shared-memory weight versions this client could not use (gone, wrong size or digest): sent over the stream",
)


def owner_of(name: str) -> tuple[str, int] | None:
    """(token, pid) of the learner that wrote this file (a version, buffer, probe, lock or temporary file)."""
    match = _OWNER.fullmatch(name)
    return (match.group(1), int(match.group(2))) if match else None


_OWNER = re.compile(r"\.?user-weights-((\d+)-[0-9a-f]{8})[-.].*")


def valid_name(name: str) -> bool:
    """A file name the server may name: ours, no directory part (never a path outside the shm dir)."""
    return bool(_NAME.fullmatch(name)) and name not in (".", "..")


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)[:64]


def _open_regular(directory: str, name: str) -> int:
    """fd of directory/name, read-only, not through a link, a regular file; WireError otherwise."""
    if not valid_name(name):
        raise WireError(f"shared-memory name {name[:80]!r} is not a weight file name")
    return open_regular(directory, name, _NAME)


def read_probe(directory: str, name: str) -> bytes:
    """The probe file's bytes (b"" if it cannot be read: the server then streams as usual)."""
    return shm_files.read_probe(directory, name, _NAME)


def read_payload(directory: str, name: str, size: int, out: np.ndarray) -> np.ndarray:
    """The file's `size` bytes copied into out[:size] (a reused buffer); WireError if it is gone, not a
    regular file or not exactly `size` bytes. The caller checks the digest."""
    fd = _open_regular(directory, name)
    try:
        if os.fstat(fd).st_size != size:
            raise WireError(f"shared-memory file {name}: {os.fstat(fd).st_size} bytes, the header says {size}")
        view, filled = memoryview(out[:size]), 0
        with os.fdopen(os.dup(fd), "rb", buffering=0) as f:
            while filled < size and (got := f.readinto(view[filled:])):
                filled += got
        if filled != size:
            raise WireError(f"shared-memory file {name}: read {filled} of {size} bytes")
        return out[:size]
    except OSError as exc:
        raise WireError(f"shared-memory file {name}: {exc.strerror}") from exc
    finally:
        os.close(fd)


class _Written:
    def __init__(self) -> None:
        self.done = threading.Event()
        self.name = ""  # "" = could not be written (the stream sends the version instead)
        self.nbytes = 0
        self.linked = False  # a hard link to a payload buffer: never a spare (the next pack reuses its pages)


class ShmWeights:
    """The learner's shared-memory directory: probe files and one file per version shared by every
    same-host subscriber (thread-safe)."""

    def __init__(
        self,
        directory: str,
        keep: int = DEFAULT_KEEP,
        max_bytes: int = DEFAULT_MAX_BYTES,
        host: str | None = None,
    ) -> None:
        self.directory = directory
        self.keep = max(1, keep)
        self.max_bytes = max_bytes
        self.host = host_id() if host is None else host
        # The token in every name. Files of a learner that died without close() (kill -9) are swept by the next
        # one: each learner holds an flock on its own lock file here, which the kernel drops when the process
        # dies, whatever its pid namespace (a restarted container's learner often has its predecessor's pid).
        self.owner = ShmOwner(directory, PREFIX)
        self.token = self.owner.token
        self._lock = threading.Lock()
        self._files: OrderedDict[tuple[str, int, bytes], _Written] = OrderedDict()  # oldest first
        # The file of the version that just left, renamed: the next version is written over its pages. A
        # fresh 4 MiB tmpfs file costs ~5 ms here (page allocation), a rewrite ~1 ms. A subscriber still
        # reading it (`keep` versions behind) sees a digest mismatch and gets that version streamed.
        self._spare = ""
        # payload buffers handed out by `buffer`, by id of their array: (its weakref, hidden file name, bytes)
        self._buffers: dict[int, tuple[weakref.ref[np.ndarray], str, int]] = {}
        self._buffer_bytes = 0
        self._dropped: deque[tuple[int, str]] = deque()  # buffers collected since, tidied under the lock
        self._closed = False
        self.swept = self.owner.swept

    def same_host(self, subscriber_host: str) -> bool:
        return bool(self.host) and hmac.compare_digest(self.host.encode(), subscriber_host.encode())

    # ------------------------------------------------------------------ probe

    def new_probe(self) -> tuple[str, bytes]:
        """(file name, nonce) of a fresh probe file; OSError if the directory cannot take it."""
        nonce = secrets.token_bytes(PROBE_BYTES)
        name = f"{PREFIX}{self.token}-probe-{secrets.token_hex(8)}"
        self._write_file(name, memoryview(nonce))
        return name, nonce

    def end_probe(self, name: str) -> None:
        self._unlink(name)

    # ------------------------------------------------------------------ versions

    def file_for(self, experiment: str, version: int, digest: bytes, payload: np.ndarray) -> str:
        """The file name holding this payload, written by the first caller (the others wait for it);
        "" if it cannot be (too big, directory full or gone): the caller streams the version instead."""
        key = (experiment, version, digest)
        with self._lock:
            if self._closed:
                return ""
            entry = self._files.get(key)
            owner = entry is None
            if entry is None:
                entry = self._files[key] = _Written()
        if owner:
            self._write_version(key, entry, payload)
        entry.done.wait()
        return entry.name

    def _write_version(self, key: tuple[str, int, bytes], entry: _Written, payload: np.ndarray) -> None:
        experiment, version, digest = key
        name = f"{PREFIX}{self.token}-{_safe(experiment)}-v{version}-{digest.hex()[:32]}"
        try:
            if payload.nbytes > self.max_bytes:
                raise OSError(f"{payload.nbytes} bytes exceed the shared-memory cap of {self.max_bytes}")
            self._evict(experiment, payload.nbytes)
            backing = self._backing(payload)
            if backing:  # packed into one of our files already: name it, no copy
                os.link(os.path.join(self.directory, backing), os.path.join(self.directory, name))
                entry.linked = True
            else:
                self._write_file(name, memoryview(payload).cast("B"), self._take_spare())
            entry.name, entry.nbytes = name, payload.nbytes
            SHM_WRITTEN.inc()
        except OSError as exc:
            log.warning("weights not written to shared memory; streamed instead", extra={"error": str(exc)})
            with self._lock:
                self._files.pop(key, None)  # a later stream may try again
        finally:
            entry.done.set()
        with self._lock:
            if entry.name and (self._closed or self._files.get(key) is not entry):
                self._unlink(name)  # closed or dropped while writing: nobody will remove it otherwise

    def _evict(self, experiment: str, incoming: int) -> None:
        """Unlink the oldest files: beyond `keep` per experiment (counting the one to come) and beyond
        max_bytes in all. A subscriber that opened one already still reads it (tmpfs keeps it until closed)."""
        with self._lock:
            done = [(k, e) for k, e in self._files.items() if e.done.is_set() and e.name]
            mine = [k for k, _ in done if k[0] == experiment]
            gone = set(mine[: max(0, len(mine) - (self.keep - 1))])
            total = sum(e.nbytes for k, e in done if k not in gone) + incoming
            for k, e in done:
                if total <= self.max_bytes:
                    break
                if k not in gone:
                    gone.add(k)
                    total -= e.nbytes
            for k in gone:
                entry = self._files.pop(k)
                if entry.linked:
                    self._unlink(entry.name)
                else:
                    self._retire(entry.name)

    def _retire(self, name: str) -> None:
        """Unlink a version's file, or keep it (renamed) as the spare the next version is written over."""
        if self._spare:
            self._unlink(name)
            return
        spare = f".{PREFIX}{self.token}-spare-{secrets.token_hex(4)}"
        try:
            os.rename(os.path.join(self.directory, name), os.path.join(self.directory, spare))
            self._spare = spare
        except OSError:
            self._unlink(name)

    def _take_spare(self) -> str:
        with self._lock:
            spare, self._spare = self._spare, ""
            return spare

    def drop(self, experiment: str) -> int:
        """A removed experiment's version files go now (they went only when it published again: never); how many.
        Those linked to payload buffers free their pages once the buffer goes too (the store lets go of it)."""
        with self._lock:
            gone = [k for k in self._files if k[0] == experiment]
            for key in gone:
                entry = self._files.pop(key)
                if entry.name:  # one still being written is unlinked by its writer (not in _files any more)
                    self._unlink(entry.name)
            self._tidy_buffers()
        return len(gone)

    def files(self) -> list[str]:
        with self._lock:
            return [e.name for e in self._files.values() if e.name]

    def close(self) -> None:
        """Shutdown: every file this learner wrote goes."""
        with self._lock:
            self._closed = True
            for entry in self._files.values():
                if entry.name:
                    self._unlink(entry.name)
            self._files.clear()
            if self._spare:
                self._unlink(self._spare)
                self._spare = ""
            for _, buffer_name, _ in self._buffers.values():
                self._unlink(buffer_name)  # the learner may still map it: the pages go when it lets go
            self._buffers.clear()
            self._buffer_bytes = 0
        self.owner.close()

    # ------------------------------------------------------------------ payload buffers

    def buffer(self, nbytes: int) -> np.ndarray | None:
        """A writable payload buffer of `nbytes` mapped from a hidden 0600 file here (a BufferPool's `fresh`):
        a version packed into it is published by a hard link instead of a 4 MiB-per-1M-params copy. None (use
        ordinary memory) below MIN_BUFFER_BYTES, beyond max_bytes, or when the directory cannot hold it."""
        with self._lock:
            self._tidy_buffers()
            if self._closed or nbytes < MIN_BUFFER_BYTES or self._buffer_bytes + nbytes > self.max_bytes:
                return None
        self.owner.hold()
        name = f".{PREFIX}{self.token}-buf-{secrets.token_hex(8)}"
        try:
            fd = create_private(os.path.join(self.directory, name))
        except OSError:
            return None
        try:
            # every page now, or ENOSPC now: a write through the map into a full tmpfs would be a SIGBUS later
            os.posix_fallocate(fd, 0, nbytes)
            array = np.frombuffer(mmap.mmap(fd, nbytes, mmap.MAP_SHARED), dtype=np.uint8)
        except (OSError, ValueError) as exc:
            log.info("payload buffer not in shared memory", extra={"error": str(exc)})
            self._unlink(name)
            return None
        finally:
            os.close(fd)  # the map keeps the file
        with self._lock:
            self._buffers[id(array)] = (weakref.ref(array), name, nbytes)
            self._buffer_bytes += nbytes
        weakref.finalize(array, self._drop_buffer, id(array), name)
        return array

    def _tidy_buffers(self) -> None:
        """Forget the buffers collected since (caller holds the lock)."""
        while self._dropped:
            key, gone = self._dropped.popleft()
            found = self._buffers.get(key)
            if found is not None and found[1] == gone:
                del self._buffers[key]
                self._buffer_bytes -= found[2]

    def _drop_buffer(self, key: int, name: str) -> None:
        """The buffer's array is gone (its pool let it go): its file goes too (links of versions stay). No lock:
        a finalizer may run in any thread, even one that holds it; the next `buffer` call tidies the table."""
        self._unlink(name)
        self._dropped.append((key, name))

    def _backing(self, payload: np.ndarray) -> str:
        """The hidden file `payload` fills exactly (all of one of our buffers), or ""."""
        owner = payload
        while isinstance(owner.base, np.ndarray):
            owner = owner.base
        with self._lock:
            found = self._buffers.get(id(owner))
        if found is None or found[0]() is not owner or payload.nbytes != found[2]:
            return ""
        if payload.__array_interface__["data"][0] != owner.__array_interface__["data"][0]:
            return ""
        return found[1]

    # ------------------------------------------------------------------ files

    def _write_file(self, name: str, data: memoryview, spare: str = "") -> None:
        """0600, written under a temporary name (a fresh file, or over the spare's pages) and renamed: a
        reader never sees a partial file under a version's name."""
        self.owner.hold()
        tmp = os.path.join(self.directory, spare or f".{name}.{secrets.token_hex(4)}.tmp")
        flags = os.O_WRONLY | os.O_NOFOLLOW | os.O_CLOEXEC | (0 if spare else os.O_CREAT | os.O_EXCL)
        try:
            fd = os.open(tmp, flags, 0o600)
        except OSError:
            if not spare:
                raise
            self._unlink(spare)  # the spare went away: a fresh file then
            return self._write_file(name, data)
        try:
            with os.fdopen(fd, "wb", buffering=0) as f:
                written = 0
                while written < len(data):
                    written += os.pwrite(f.fileno(), data[written:], written)
                f.truncate(len(data))  # a spare of another size
            os.rename(tmp, os.path.join(self.directory, name))
        except BaseException:
            self._unlink(os.path.basename(tmp))
            raise

    def _unlink(self, name: str) -> None:
        try:
            os.unlink(os.path.join(self.directory, name))
        except OSError:
            pass  # gone already
