"""One owner per piece of state (a run dir, a replay buffer, a checkpoint dir, control's SQLite file, an edge
spool): an exclusive flock on a lock file that names its holder. The kernel drops the lock when the holder dies,
kill -9 included, so nothing stale is left to clean up; each caller turns `Held` into its own one-line error."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path


class Held(Exception):
    """Another process (or another open of this file in this one) holds the lock; `holder` is what it wrote."""

    def __init__(self, holder: str) -> None:
        super().__init__(holder)
        self.holder = holder


def take(lock_path: Path, label: str | None = None) -> int:
    """Flock `lock_path` exclusively for this process and write `label` (default: this pid) into it. Returns the
    fd: keep it open while owning the state, close it to let go. Raises Held, changing nothing, when taken."""
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)  # O_CLOEXEC (PEP 446): started children never hold it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 256, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise Held(holder) from None
    with contextlib.suppress(OSError):  # on a full disk the holder goes unnamed; the lock holds all the same
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{label or os.getpid()}\n".encode(), 0)
    return fd


def holder(lock_path: Path) -> str | None:
    """What the live holder of `lock_path` wrote, or None when nobody holds it (a probe that creates nothing)."""
    try:
        fd = os.open(lock_path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return os.pread(fd, 256, 0).decode(errors="replace").strip() or "unknown"
    finally:
        os.close(fd)  # closing drops the probe's own lock too
    return None
