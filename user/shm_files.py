"""Files a process shares with same-host peers through a shared-memory directory (tmpfs, /dev/shm).

Used by the learner's weight versions (user/weight_shm.py) and replay's sample batches
(services/replay/shared.py). Each owner names its files `<prefix><token>-...` (token = "<pid>-<8 hex>")
and holds an flock on `.<prefix><token>.lock` for its whole life: the kernel drops it when the process
dies, whatever its pid namespace, so the next owner of the same prefix removes a dead one's files
(kill -9, a killed container). Readers open names they were told only if they match the prefix, without
following links, and only regular files.
"""

from __future__ import annotations

import fcntl
import os
import re
import secrets
import stat
import threading
import weakref
from pathlib import Path

from user.wire import WireError

BOOT_ID = Path("/proc/sys/kernel/random/boot_id")
LOCK_SUFFIX = ".lock"
PROBE_BYTES = 32  # a probe file's random nonce: the peer proves it reads our directory by echoing it


def host_id() -> str:
    """This machine's identity for the same-host check: the boot id ("" where there is none: no shm)."""
    try:
        return BOOT_ID.read_text().strip()
    except OSError:
        return ""


def create_private(path: str) -> int:
    """A new file only this user can read, opened read-write (never through a link); OSError if it exists."""
    return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, not ours to signal
    return True


def name_pattern(prefix: str) -> re.Pattern[str]:
    """File names an owner of `prefix` may tell a reader: no directory part."""
    return re.compile(re.escape(prefix) + r"[A-Za-z0-9_.-]{1,200}")


def open_regular(directory: str, name: str, pattern: re.Pattern[str], writable: bool = False) -> int:
    """fd of directory/name, read-only (or read-write), not through a link, a regular file; WireError otherwise."""
    if not pattern.fullmatch(name) or name in (".", ".."):
        raise WireError(f"shared-memory name {name[:80]!r} is not one of ours")
    try:
        mode = os.O_RDWR if writable else os.O_RDONLY
        fd = os.open(os.path.join(directory, name), mode | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise WireError(f"shared-memory file {name}: {exc.strerror}") from exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise WireError(f"shared-memory file {name} is not a regular file")
    return fd


def read_probe(directory: str, name: str, pattern: re.Pattern[str]) -> bytes:
    """A probe file's bytes (up to PROBE_BYTES + 1; b"" if it cannot be read: the caller uses the socket)."""
    try:
        fd = open_regular(directory, name, pattern)
    except WireError:
        return b""
    try:
        return os.read(fd, PROBE_BYTES + 1)
    except OSError:
        return b""
    finally:
        os.close(fd)


class ShmOwner:
    """One process's claim on its files under `prefix` in `directory` (thread-safe)."""

    def __init__(self, directory: str, prefix: str) -> None:
        self.directory, self.prefix = directory, prefix
        self.token = f"{os.getpid()}-{secrets.token_hex(4)}"
        self._owner = re.compile(r"\.?" + re.escape(prefix) + r"((\d+)-[0-9a-f]{8})[-.].*")
        self._fd = -1
        self._release: weakref.finalize | None = None
        self._mutex = threading.Lock()  # one lock file, even when threads race to make it
        self.closed = False
        self.hold()
        self.swept = self.sweep()

    @property
    def lock_name(self) -> str:
        return f".{self.prefix}{self.token}{LOCK_SUFFIX}"

    def owner_of(self, name: str) -> tuple[str, int] | None:
        """(token, pid) of the owner of this file (any of its files, temporary or lock)."""
        match = self._owner.fullmatch(name)
        return (match.group(1), int(match.group(2))) if match else None

    def hold(self) -> None:
        """Create and flock our lock file (under a temporary name first, so no sweeper sees it unlocked);
        called before each write, so a directory that was missing is claimed once it exists."""
        if self._fd >= 0 or self.closed:
            return
        with self._mutex:
            if self._fd < 0 and not self.closed:
                self._make_lock()

    def _make_lock(self) -> None:
        final = os.path.join(self.directory, self.lock_name)
        tmp = f"{final}.{secrets.token_hex(4)}.tmp"
        try:
            fd = create_private(tmp)
        except OSError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.rename(tmp, final)
        except OSError:
            os.close(fd)
            self.unlink(os.path.basename(tmp))
            return
        self._fd = fd
        self._release = weakref.finalize(self, os.close, fd)  # dropped without close(): the lock goes too

    def _gone(self, lock_name: str) -> bool:
        """Whether the owner holding this lock file has died (its flock is free)."""
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

    def sweep(self) -> int:
        """Remove the files of owners of this prefix (this user's) whose process is gone; the number removed."""
        try:
            names = os.listdir(self.directory)
        except OSError:
            return 0
        owners: dict[str, list[str]] = {}
        pids: dict[str, int] = {}
        for name in names:
            owner = self.owner_of(name)
            if owner is not None and owner[0] != self.token:
                owners.setdefault(owner[0], []).append(name)
                pids[owner[0]] = owner[1]
        removed = 0
        for token, owned in owners.items():
            lock = f".{self.prefix}{token}{LOCK_SUFFIX}"
            # no lock file: an owner from before lock files, judged by its pid
            if not (self._gone(lock) if lock in owned else not alive(pids[token])):
                continue
            for name in sorted(owned, key=lambda n: n == lock):  # the lock last: a crash midway is swept again
                try:
                    if os.lstat(os.path.join(self.directory, name)).st_uid == os.getuid():
                        os.unlink(os.path.join(self.directory, name))
                        removed += name != lock
                except OSError:
                    pass  # gone already, or not ours to remove
        return removed

    def unlink(self, name: str) -> None:
        try:
            os.unlink(os.path.join(self.directory, name))
        except OSError:
            pass  # gone already

    def close(self) -> None:
        """Give up the claim (the caller has removed its files)."""
        with self._mutex:
            self.closed = True
            if self._fd >= 0:
                self.unlink(self.lock_name)
                if self._release is not None:
                    self._release()
                self._fd = -1
