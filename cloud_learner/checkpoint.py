"""Atomic learner checkpoints on our own disk.

Each checkpoint is written to a temp file in the same directory, fsynced, renamed to
`ckpt-<updates:09d>.pt`, and only then named by the `latest` pointer file (itself replaced
atomically). A crash at any point leaves the previous checkpoint loadable; stray `.tmp` files
are never read. Loading uses torch.load(weights_only=True): these files are ours, never wire bytes.
A checkpoint that does not load (a torn disk write, `truncate`) is skipped with a warning for the next
older one, never deleted; pruning keeps the newest files at or below the one just written, so files of a
higher count (such a skipped one) neither push this run's own checkpoints out nor get deleted.
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import torch

from user.log import kv

log = logging.getLogger(__name__)

LATEST = "latest"
VERSION_MARK = "weight_version"  # the highest weight version ever published from this directory
KEEP = 3
_NAME = re.compile(r"^ckpt-(\d{9,})\.pt$")


class CheckpointError(RuntimeError):
    """Checkpoints exist but none of them can be read: training must not silently start over."""


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


def _write_atomic(path: Path, write: Any) -> None:
    """write(file) into a temp file beside `path`, fsync, rename over `path`."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
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
    """Write `state` (must hold "updates") atomically, point `latest` at it, keep the newest `keep`."""
    ckpt_dir = Path(ckpt_dir)
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    path = ckpt_dir / checkpoint_name(int(state["updates"]))
    _write_atomic(path, lambda f: torch.save(state, f))
    _write_atomic(ckpt_dir / LATEST, lambda f: f.write(path.name.encode() + b"\n"))
    _fsync_dir(ckpt_dir)
    # Only files below this one are pruned: a higher count is not this run's (e.g. an unreadable newest one it
    # fell back from) and must not push this run's own recent checkpoints out.
    below = [p for p in list_checkpoints(ckpt_dir) if _updates_of(p) < _updates_of(path)]
    for old in below[: max(0, len(below) - (keep - 1))]:
        old.unlink(missing_ok=True)
    log.info("checkpoint saved", extra=kv(path=str(path), updates=int(state["updates"])))
    return path


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
    since a process crash keeps the page cache and a power loss also loses the subscribers' state."""
    ckpt_dir = Path(ckpt_dir)
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    path = ckpt_dir / VERSION_MARK
    if durable:
        _write_atomic(path, lambda f: f.write(f"{version}\n".encode()))
        return
    tmp = ckpt_dir / f".{VERSION_MARK}.{os.getpid()}.tmp"
    tmp.write_text(f"{version}\n")
    os.replace(tmp, path)
