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
per experiment stay, older files are unlinked, and the whole is bounded in bytes. close() removes them.
The learner's payload buffers may themselves live here (`buffer`, a mapped hidden file): a version packed
into one is published by a hard link to it, with no copy at all. Each learner flocks a lock file here for its
whole life; the next learner removes the files of any whose lock is free (it died: kill -9, a container killed).
Client side (`read_probe`, `read_payload`): file names are checked (no directory part, our prefix),
files are opened without following links and must be regular files of exactly the declared size.
"""

from __future__ import annotations

import fcntl
import hmac
import logging
import mmap
import os
import re
import secrets
import stat
import threading
import weakref
from collections import OrderedDict, deque
from pathlib import Path

import numpy as np
import prometheus_client

from user.wire import WireError

log = logging.getLogger(__name__)

BOOT_ID = Path("/proc/sys/kernel/random/boot_id")
DEFAULT_SHM_DIR = "/dev/shm"
PREFIX = "user-weights-"
DEFAULT_KEEP = 3  # versions per experiment: a subscriber still opening the previous one finds it
DEFAULT_MAX_BYTES = 2 << 30  # of all files together (tmpfs is RAM)
MIN_BUFFER_BYTES = 1 << 20  # smaller payloads are not pooled (BufferPool): a file each would cost more than a copy
PROBE_BYTES = 32
_NAME = re.compile(r"user-weights-[A-Za-z0-9_.-]{1,200}")

SHM_WRITTEN = prometheus_client.Counter(
    "user_weights_shm_written_total", "Weight versions written to shared memory for same-host subscribers"
)
SHM_FALLBACK = prometheus_client.Counter(
    "user_weights_shm_fallback_total",
    "Shared-memory weight versions this client could not use (gone, wrong size or digest): sent over the stream",
)


# a learner's file (or temporary file): (its token, its pid); the token is "<pid>-<8 hex>"
_OWNER = re.compile(r"\.?user-weights-((\d+)-[0-9a-f]{8})[-.].*")
LOCK_SUFFIX = ".lock"  # .user-weights-<token>.lock: flock-held by its learner for its whole life


def owner_of(name: str) -> tuple[str, int] | None:
    """(token, pid) of the learner that wrote this file (a version, buffer, probe, lock or temporary file)."""
    match = _OWNER.fullmatch(name)
    return (match.group(1), int(match.group(2))) if match else None


def _create_private(path: str) -> int:
    """A new file only this user can read, opened read-write (never through a link); OSError if it exists."""
    return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, not ours to signal
    return True


def host_id() -> str:
    """This machine's identity for the same-host check: the boot id ("" where there is none: no shm)."""
    try:
        return BOOT_ID.read_text().strip()
    except OSError:
        return ""


def valid_name(name: str) -> bool:
    """A file name the server may name: ours, no directory part (never a path outside the shm dir)."""
    return bool(_NAME.fullmatch(name)) and name not in (".", "..")


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)[:64]


def _open_regular(directory: str, name: str) -> int:
    """fd of directory/name, read-only, not through a link, a regular file; WireError otherwise."""
    if not valid_name(name):
        raise WireError(f"shared-memory name {name[:80]!r} is not a weight file name")
    try:
        fd = os.open(os.path.join(directory, name), os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise WireError(f"shared-memory file {name}: {exc.strerror}") from exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise WireError(f"shared-memory file {name} is not a regular file")
    return fd


def read_probe(directory: str, name: str) -> bytes:
    """The probe file's bytes (b"" if it cannot be read: the server then streams as usual)."""
    try:
        fd = _open_regular(directory, name)
    except WireError:
        return b""
    try:
        return os.read(fd, PROBE_BYTES + 1)[: PROBE_BYTES + 1]
    except OSError:
        return b""
    finally:
        os.close(fd)


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
        self.token = f"{os.getpid()}-{secrets.token_hex(4)}"
        self._owner_fd = -1
        self._owner_mutex = threading.Lock()  # one lock file, even when stream threads race to make it
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
        self._hold_owner_lock()
        self.swept = self._sweep()

    def _hold_owner_lock(self) -> None:
        """Create and flock our lock file (under a temporary name first, so no sweeper sees it unlocked);
        retried before each write while the directory is missing."""
        if self._owner_fd >= 0 or self._closed:
            return
        with self._owner_mutex:
            if self._owner_fd < 0 and not self._closed:
                self._make_owner_lock()

    def _make_owner_lock(self) -> None:
        final = os.path.join(self.directory, f".{PREFIX}{self.token}{LOCK_SUFFIX}")
        tmp = f"{final}.{secrets.token_hex(4)}.tmp"
        try:
            fd = _create_private(tmp)
        except OSError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.rename(tmp, final)
        except OSError:
            os.close(fd)
            self._unlink(os.path.basename(tmp))
            return
        self._owner_fd = fd
        self._release_owner = weakref.finalize(self, os.close, fd)  # dropped without close(): the lock goes too

    def _owner_gone(self, lock_name: str) -> bool:
        """Whether the learner holding this lock file has died (its flock is free)."""
        try:
            fd = os.open(os.path.join(self.directory, lock_name), os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError:
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError:
            return False  # held (alive), or cannot tell
        finally:
            os.close(fd)

    def _sweep(self) -> int:
        """Remove the files of learners (this user's) whose process is gone; the number removed."""
        try:
            names = os.listdir(self.directory)
        except OSError:
            return 0
        owners: dict[str, list[str]] = {}
        pids: dict[str, int] = {}
        for name in names:
            owner = owner_of(name)
            if owner is not None and owner[0] != self.token:
                owners.setdefault(owner[0], []).append(name)
                pids[owner[0]] = owner[1]
        removed = 0
        for token, owned in owners.items():
            lock = f".{PREFIX}{token}{LOCK_SUFFIX}"
            # no lock file: a learner from before lock files, judged by its pid
            if not (self._owner_gone(lock) if lock in owned else not _alive(pids[token])):
                continue
            for name in sorted(owned, key=lambda n: n == lock):  # the lock last: a crash midway is swept again
                try:
                    if os.lstat(os.path.join(self.directory, name)).st_uid == os.getuid():
                        os.unlink(os.path.join(self.directory, name))
                        removed += name != lock
                except OSError:
                    pass  # gone already, or not ours to remove
        return removed

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
            if self._closed:  # closed while writing: nobody will remove it otherwise
                self._unlink(name)

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
            if self._owner_fd >= 0:
                self._unlink(f".{PREFIX}{self.token}{LOCK_SUFFIX}")
                self._release_owner()
                self._owner_fd = -1

    # ------------------------------------------------------------------ payload buffers

    def buffer(self, nbytes: int) -> np.ndarray | None:
        """A writable payload buffer of `nbytes` mapped from a hidden 0600 file here (a BufferPool's `fresh`):
        a version packed into it is published by a hard link instead of a 4 MiB-per-1M-params copy. None (use
        ordinary memory) below MIN_BUFFER_BYTES, beyond max_bytes, or when the directory cannot hold it."""
        with self._lock:
            while self._dropped:
                key, gone = self._dropped.popleft()
                found = self._buffers.get(key)
                if found is not None and found[1] == gone:
                    del self._buffers[key]
                    self._buffer_bytes -= found[2]
            if self._closed or nbytes < MIN_BUFFER_BYTES or self._buffer_bytes + nbytes > self.max_bytes:
                return None
        self._hold_owner_lock()
        name = f".{PREFIX}{self.token}-buf-{secrets.token_hex(8)}"
        try:
            fd = _create_private(os.path.join(self.directory, name))
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
        self._hold_owner_lock()
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
