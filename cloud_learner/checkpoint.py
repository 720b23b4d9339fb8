"""Atomic learner checkpoints on our own disk.

Each checkpoint is written to a temp file in the same directory, fsynced, renamed to
`ckpt-<updates:09d>.pt`, and only then named by the `latest` pointer file (itself replaced
atomically). A crash at any point leaves the previous checkpoint loadable; stray `.tmp` files
are never read. Loading uses torch.load(weights_only=True): these files are ours, never wire bytes.
A checkpoint that does not load (a torn disk write, `truncate`) is skipped with a warning for the next
older one, never deleted; pruning keeps the newest files at or below the one just written, so files of a
higher count (such a skipped one) neither push this run's own checkpoints out nor get deleted. A removed experiment
keeps its final checkpoint alone (`keep_final_checkpoint`). "checkpoint saved" is at INFO for a directory's first
save (and the first after a failed one), then at DEBUG with one INFO line a minute (user.log.RoutineLog).

One learner per checkpoint directory (`lock_checkpoint_dir`): two would publish one weight version number
with different weights. A write the disk refuses (ENOSPC) raises CheckpointWriteError with no temp file left
and the previous checkpoint still named by `latest`; temp files a killed writer left are removed at start
(`sweep_temp_files`, under the lock, so no live writer owns them).
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import torch

from user import owner_lock
from user.config import ConfigError
from user.log import RoutineLog, kv

log = logging.getLogger(__name__)

LATEST = "latest"
VERSION_MARK = "weight_version"  # the highest weight version ever published from this directory
KEEP = 3
_NAME = re.compile(r"^ckpt-(\d{9,})\.pt$")
OWNER_LOCK = "owner.lock"  # flocked by the learner using the directory; holds its pid for the refusal message
# Our temp files: mkstemp's (".<final name>.<8 of [a-z0-9_]>.tmp") and the per-pid version mark older builds wrote.
_TEMP = re.compile(r"^\.(?:(?:ckpt-\d{9,}\.pt|latest|weight_version)\.[a-z0-9_]{8}|weight_version\.\d+)\.tmp$")
_SAVED = RoutineLog("checkpoint saved")  # by checkpoint directory


class CheckpointError(RuntimeError):
    """Checkpoints exist but none of them can be read: training must not silently start over."""


class CheckpointDirInUse(ConfigError):
    """Another live process holds the checkpoint directory (a second learner on one learner.checkpoint_dir)."""


class CheckpointWriteError(OSError):
    """A checkpoint file could not be written (ENOSPC, EIO, ...): nothing partial is left and the previous
    checkpoint is still the one `latest` names. errno is the cause's; `path` the file that was not written."""

    def __init__(self, path: Path, cause: OSError) -> None:
        super().__init__(cause.errno, f"checkpoint not written: {cause.strerror or cause}", str(path))
        self.path = path


class CheckpointDirLock:
    """The exclusive flock on a checkpoint directory's owner.lock; release() (or leaving the `with`) drops it.
    The kernel drops it too when the process dies, kill -9 included, so a restarted learner takes it at once."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path, self._fd = path, fd

    def release(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)  # closing the fd drops its flock
            self._fd = -1

    def __enter__(self) -> CheckpointDirLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def lock_checkpoint_dir(path: str | Path) -> CheckpointDirLock:
    """Take `path` (learner.checkpoint_dir) for this process, before any checkpoint is read or written.
    Raises CheckpointDirInUse naming the holder's pid when another process, or another lock of this one, has it."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    try:
        fd = owner_lock.take(path / OWNER_LOCK)
    except owner_lock.Held as held:
        raise CheckpointDirInUse(f"learner.checkpoint_dir {path} is in use by pid {held.holder}") from None
    return CheckpointDirLock(path, fd)


def sweep_temp_files(path: str | Path) -> list[Path]:
    """Remove the temp files killed writers left in `path` (learner.checkpoint_dir) and its experiment
    directories: only regular files named exactly as this module names its temp files. Call it holding the
    directory's lock (lock_checkpoint_dir), so none of them belongs to a live writer. Returns what was removed."""
    path = Path(path)
    if not path.is_dir():
        return []
    dirs = [path, *(d for d in path.iterdir() if d.is_dir() and not d.is_symlink())]
    removed = []
    for entry in (e for d in dirs for e in os.scandir(d)):
        if _TEMP.match(entry.name) and entry.is_file(follow_symlinks=False):
            Path(entry.path).unlink(missing_ok=True)
            removed.append(Path(entry.path))
    if removed:
        log.info("stale checkpoint temp files removed", extra=kv(path=str(path), files=[p.name for p in removed]))
    return removed


def _fsync_dir(path: Path) -> None:
    """Make the renames durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class _Recorded:
    """The temp file as torch.save sees it: torch reports a failed write (ENOSPC) only as a RuntimeError
    ("unexpected pos"), so the OSError is kept here to say what happened."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.error: OSError | None = None

    def write(self, data: Any) -> int:
        try:
            return self.f.write(data)
        except OSError as exc:
            self.error = self.error or exc
            raise

    def flush(self) -> None:
        self.f.flush()


def _write_atomic(path: Path, write: Any, durable: bool = True) -> None:
    """write(file) into a temp file beside `path`, fsync (if durable), rename over `path`. An OSError on the way
    (the temp file's own, or under torch.save's RuntimeError) raises CheckpointWriteError with the temp removed."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise CheckpointWriteError(path, exc) from exc
    out: _Recorded | None = None
    try:
        with os.fdopen(fd, "wb") as f:
            out = _Recorded(f)
            write(out)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        cause = exc if isinstance(exc, OSError) else None
        if cause is None and out is not None:
            cause = out.error  # torch.save's RuntimeError over a failed write
        if cause is not None:
            raise CheckpointWriteError(path, cause) from exc
        raise


def checkpoint_name(updates: int) -> str:
    return f"ckpt-{updates:09d}.pt"


def _updates_of(path: Path) -> int:
    m = _NAME.match(path.name)
    return int(m.group(1)) if m else -1


def list_checkpoints(ckpt_dir: str | Path) -> list[Path]:
    """Complete checkpoints, oldest first (temp files are ignored)."""
    ckpt_dir = Path(ckpt_dir)
    if not ckpt_dir.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in ckpt_dir.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def save_checkpoint(ckpt_dir: str | Path, state: dict[str, Any], keep: int = KEEP) -> Path:
    """Write `state` (must hold "updates") atomically, point `latest` at it, keep the newest `keep`.
    CheckpointWriteError when the disk refuses (ENOSPC): nothing of this save is left, `latest` and the
    previous checkpoint are as they were, so the caller may log it and try again later."""
    ckpt_dir = Path(ckpt_dir)
    path = ckpt_dir / checkpoint_name(int(state["updates"]))
    try:
        _write_named(ckpt_dir, path, state)
    except CheckpointWriteError:
        _SAVED.reset(str(ckpt_dir))  # the next one saved says so at INFO
        raise
    _prune_below(ckpt_dir, path, keep)
    _SAVED.log(log, str(ckpt_dir), path=str(path), updates=int(state["updates"]))
    return path


def _write_named(ckpt_dir: Path, path: Path, state: dict[str, Any]) -> None:
    """`state` at `path`, then named by `latest`; CheckpointWriteError with nothing of it left otherwise."""
    try:
        ckpt_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CheckpointWriteError(ckpt_dir, exc) from exc
    _write_atomic(path, lambda f: torch.save(state, f))
    try:
        _write_atomic(ckpt_dir / LATEST, lambda f: f.write(path.name.encode() + b"\n"))
        _fsync_dir(ckpt_dir)
    except OSError as exc:
        if latest_path(ckpt_dir) != path:  # never named: a file nobody loads, taking the room the disk lacks
            path.unlink(missing_ok=True)
        if isinstance(exc, CheckpointWriteError):
            raise
        raise CheckpointWriteError(ckpt_dir / LATEST, exc) from exc


def _prune_below(ckpt_dir: Path, path: Path, keep: int) -> list[Path]:
    """Keep `path` and the newest keep - 1 below it; returns what went. Only files below it are pruned: a higher
    count is not this run's (e.g. an unreadable newest one it fell back from) and must not push this run's own
    recent checkpoints out."""
    below = [p for p in list_checkpoints(ckpt_dir) if _updates_of(p) < _updates_of(path)]
    gone = below[: max(0, len(below) - (keep - 1))]
    for old in gone:
        old.unlink(missing_ok=True)
    return gone


def keep_final_checkpoint(ckpt_dir: str | Path) -> list[Path]:
    """A removed experiment's directory keeps the checkpoint `latest` names alone (its final one; the previous one
    if the final write failed); the others below it go, as pruning would. Returns what went."""
    ckpt_dir = Path(ckpt_dir)
    _SAVED.reset(str(ckpt_dir))
    final = latest_path(ckpt_dir)
    if final is None:
        return []
    gone = _prune_below(ckpt_dir, final, keep=1)
    if gone:
        log.info("older checkpoints removed; the final one stays", extra=kv(path=str(final), removed=len(gone)))
    return gone


def latest_path(ckpt_dir: str | Path) -> Path | None:
    """The checkpoint `latest` names; falls back to the newest complete file if the pointer is missing or stale."""
    ckpt_dir = Path(ckpt_dir)
    pointer = ckpt_dir / LATEST
    if pointer.is_file():
        name = pointer.read_text().strip()
        if _NAME.match(name) and (ckpt_dir / name).is_file():
            return ckpt_dir / name
        log.warning("latest pointer names no checkpoint; using the newest file", extra=kv(pointer=name))
    found = list_checkpoints(ckpt_dir)
    return found[-1] if found else None


def _read(path: Path, map_location: str | torch.device) -> dict[str, Any]:
    state = torch.load(path, map_location=map_location, weights_only=True)
    if not isinstance(state, dict) or not isinstance(state.get("updates"), int | torch.Tensor):
        raise ValueError("not a checkpoint (no update count)")
    return state


def load_latest(ckpt_dir: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any] | None:
    """The checkpoint `latest` names; if it cannot be read, the next older readable one (with a warning).
    None when there is none; CheckpointError when there are some but none reads."""
    path = latest_path(ckpt_dir)
    if path is None:
        return None
    # Older ones only: a file above the one `latest` names was never completed as this run's newest.
    candidates = [path, *(p for p in reversed(list_checkpoints(ckpt_dir)) if _updates_of(p) < _updates_of(path))]
    errors = []
    for candidate in candidates:
        try:
            state = _read(candidate, map_location)
        except Exception as exc:  # torch raises many kinds (RuntimeError, EOFError, UnpicklingError, ...)
            errors.append(f"{candidate.name}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
            log.warning(
                "checkpoint unreadable; trying the previous one (the file is kept)",
                extra=kv(path=str(candidate), error=errors[-1]),
            )
            continue
        log.info("checkpoint loaded", extra=kv(path=str(candidate), updates=int(state.get("updates", 0))))
        return state
    raise CheckpointError(f"no checkpoint in {ckpt_dir} can be read ({'; '.join(errors)}); training would start over")


def read_version_mark(ckpt_dir: str | Path) -> int:
    """The highest weight version published from this checkpoint directory (0 if none yet)."""
    path = Path(ckpt_dir) / VERSION_MARK
    try:
        text = path.read_text().strip()
    except FileNotFoundError:
        return 0
    if not text.isdigit():
        raise ValueError(f"{path} holds {text!r}, not a weight version; remove it only if no subscriber is running")
    return int(text)


def write_version_mark(ckpt_dir: str | Path, version: int, durable: bool = False) -> None:
    """Record `version` before it is published, so a restarted learner (even after kill -9) never
    reuses a number: a version names one weight set forever. Atomic (rename); fsync only if durable,
    since a process crash keeps the page cache and a power loss also loses the subscribers' state.
    CheckpointWriteError (no temp file left) when the disk refuses: that version must not be published."""
    ckpt_dir = Path(ckpt_dir)
    try:
        ckpt_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CheckpointWriteError(ckpt_dir, exc) from exc
    _write_atomic(ckpt_dir / VERSION_MARK, lambda f: f.write(f"{version}\n".encode()), durable=durable)
