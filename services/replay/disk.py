"""The durable truth of the replay buffer: one LMDB environment under `path` (data.mdb + lock.mdb).

Named databases:
  steps:    b"<robot_id>/<episode_id>/" + big-endian uint64 step_index -> serialized user.v1.Step
  ends:     same key -> b""  for steps that end an episode (they carry final_observation)
  scalars:  same key -> packed (reward, flags, policy_version, arrival, value bytes): what the
            in-memory index needs, so reopening reads 25 bytes per step instead of whole steps
  episodes: b"<robot_id>/<episode_id>/" -> table name, for episodes of a table other than "online"
  specs:    robot_id -> serialized RobotSpec (so a restarted replay can validate while control is down)
  meta:     b"format" -> b"1"; b"duplicates" -> big-endian uint64
Keys sort by robot, episode and step, so an episode's steps are adjacent and a re-sent step hits
the same key and is stored once. The next observation of step t is the observation of step t+1,
or t's own final_observation when t ends the episode: no observation is stored twice.

Durability: put_steps returns only after its transaction committed. With durability="fsync" (the
default) the commit is fsync'd, so an acknowledged step survives a power cut; with "os" it is in
the page cache (survives kill -9 of replay, not a power cut) and is fsync'd every sync_interval_s.
Either way many steps share one transaction (group commit), so fsync is paid per batch, not per step.
The map grows by itself (doubling) up to max_map_mb instead of failing when full.
A transaction that fails to commit (a full disk, an I/O error) stores nothing of itself: LMDB aborts it
and the environment stays usable, so the next commit, once there is space, succeeds.
"""

from __future__ import annotations

import errno
import logging
import os
import struct
import threading
import time
from collections.abc import Callable, Container, Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import lmdb

from user.log import kv
from user.v1 import robot_pb2, step_pb2

log = logging.getLogger(__name__)
T = TypeVar("T")

FORMAT = b"1"
_INDEX = struct.Struct(">Q")
_U64 = struct.Struct(">Q")
SCALARS = struct.Struct("<fBQQI")  # reward, flags, policy_version, arrival, value bytes
TERMINATED, TRUNCATED, INTERVENTION, SUCCESS, ENDS = 1, 2, 4, 8, 16
ONLINE = "online"
DURABILITY = ("fsync", "os")
_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
FULL_MARGIN = 4 << 20  # a failed commit with less free than twice its bytes plus this is taken for a full disk


class ReplayError(RuntimeError):
    """Base class for store errors the service maps to a gRPC status."""


class ReplayFullError(ReplayError):
    """The LMDB map reached max_map_mb: raise replay.max_map_mb or lower replay.capacity_mb."""


class StoreClosedError(ReplayError):
    """The store was closed (the service is shutting down)."""


class DiskFullError(ReplayError):
    """A write transaction did not commit because the filesystem under the store is full; nothing of it is stored."""


class DiskWriteError(ReplayError):
    """A write transaction did not commit for another reason (an I/O error); nothing of it is stored."""


def episode_prefix(robot_id: str, episode_id: str) -> bytes:
    return f"{robot_id}/{episode_id}/".encode()


def step_key(robot_id: str, episode_id: str, step_index: int) -> bytes:
    return episode_prefix(robot_id, episode_id) + _INDEX.pack(step_index)


def split_key(key: bytes) -> tuple[bytes, int]:
    """(episode prefix, step index)."""
    return key[:-8], _INDEX.unpack(key[-8:])[0]


def next_key(key: bytes) -> bytes:
    prefix, t = split_key(key)
    return prefix + _INDEX.pack(t + 1)


def robot_of(prefix: bytes) -> str:
    return prefix[: prefix.index(b"/")].decode()


def flags_of(step: step_pb2.Step) -> int:
    return (
        (TERMINATED if step.terminated else 0)
        | (TRUNCATED if step.truncated else 0)
        | (INTERVENTION if step.intervention else 0)
        | (SUCCESS if step.success else 0)
    )


def _delete_range(cur: lmdb.Cursor, prefix: bytes) -> int:
    """Delete every key starting with prefix; returns how many."""
    n = 0
    if cur.set_range(prefix):
        while cur.key().startswith(prefix) and cur.delete():  # delete() moves on to the next key
            n += 1
    return n


class NotInOrder(ReplayError):
    """put_in_order met a step already stored: the caller falls back to put_steps (nothing was written)."""


class Committed:
    """What one put_steps transaction changed: new steps (in arrival order) and newly sampleable keys."""

    __slots__ = ("duplicates", "nbytes", "sampleable", "stored", "stored_mask")

    def __init__(self) -> None:
        self.stored_mask: list[bool] = []  # per step given: stored (True) or a duplicate
        self.stored: list[tuple[bytes, step_pb2.Step, int, str]] = []  # (key, step, value bytes, table)
        self.sampleable: list[bytes] = []
        self.duplicates = 0
        self.nbytes = 0


class StepDB:
    """LMDB access. One writer at a time (callers hold their own lock); reads from any thread."""

    def __init__(
        self,
        path: str | Path,
        map_size_mb: int = 4096,
        *,
        max_map_mb: int | None = None,
        durability: str = "fsync",
        sync_interval_s: float = 1.0,
        readonly: bool = False,
        lock: bool = True,
        guard: threading.RLock | None = None,
    ) -> None:
        """lock=False (read-only only): no LMDB lock file is used or created; the caller guarantees no writer."""
        if durability not in DURABILITY:
            raise ValueError(f"durability must be one of {DURABILITY}, got {durability!r}")
        self.path = Path(path)
        self.readonly = readonly
        if not readonly:
            self.path.mkdir(parents=True, exist_ok=True)
        self.durability = durability
        self._guard = guard or threading.RLock()  # held by this process's readers; map growth excludes them
        self.max_map_bytes = int(max_map_mb if max_map_mb is not None else map_size_mb) << 20
        self.env = lmdb.open(
            str(self.path),
            map_size=int(map_size_mb) << 20,
            max_dbs=8,
            subdir=True,
            readonly=readonly,
            lock=lock or not readonly,  # also read-only, unless the caller knows nothing writes (attach)
            readahead=False,  # samples are random reads; readahead only pollutes the page cache
            meminit=False,
            # no writemap: measured here, puts into a sparse writable map page-fault (~3x the CPU of a
            # malloc page + pwrite at commit) once evicted pages are being reused
            writemap=False,
            sync=durability == "fsync",
            metasync=durability == "fsync",
        )
        self.map_bytes = self.env.info()["map_size"]
        if not readonly:
            stale = self.env.reader_check()  # reader slots left by a process that was killed
            if stale:
                log.info("cleared stale LMDB readers", extra=kv(path=str(self.path), readers=stale))
        create = not readonly
        self.steps = self.env.open_db(b"steps", create=create)
        self.ends = self.env.open_db(b"ends", create=create)
        self.scalars = self._open_optional(b"scalars", create)
        self.episodes = self._open_optional(b"episodes", create)
        self.specs = self._open_optional(b"specs", create)
        self.meta = self._open_optional(b"meta", create)
        self.duplicates = 0
        self._doomed: list[bytes] = []  # evicted episodes, deleted by the next write transaction (or close)
        self.arrival = 0  # the store sets it past the newest arrival it scanned
        self._sync_interval_s = sync_interval_s
        self._last_sync = time.monotonic()
        self._stop = threading.Event()
        self._syncer: threading.Thread | None = None
        if durability == "os" and not readonly:
            self._syncer = threading.Thread(target=self._sync_loop, name="replay-lmdb-sync", daemon=True)
            self._syncer.start()
        if not readonly:
            self._open_meta()

    def _open_optional(self, name: bytes, create: bool) -> object | None:
        try:
            return self.env.open_db(name, create=create)
        except lmdb.NotFoundError:
            return None

    def _open_meta(self) -> None:
        with self.env.begin(write=True, db=self.meta) as txn:
            fmt = txn.get(b"format")
            if fmt is None:
                if txn.stat(self.steps)["entries"]:
                    raise ReplayError(f"{self.path} holds steps of an older replay format; move it away to start anew")
                txn.put(b"format", FORMAT)
            elif fmt != FORMAT:
                raise ReplayError(f"{self.path}: replay format {fmt!r}, this code reads {FORMAT!r}")
            dups = txn.get(b"duplicates")
            self.duplicates = _U64.unpack(dups)[0] if dups else 0

    def _sync_loop(self) -> None:
        failing = False  # warn once per run of failures: a full disk fails every sync until space returns
        while not self._stop.wait(self._sync_interval_s):
            try:
                self.env.sync(True)
            except lmdb.Error as exc:
                if self._stop.is_set():  # closed under us
                    return
                if not failing:
                    log.warning("replay's periodic fsync failed", extra=kv(path=str(self.path), error=str(exc)))
                failing = True
                continue
            failing = False

    # ------------------------------------------------------------------ scans (open)

    def scan(self) -> Iterator[tuple[bytes, tuple[float, int, int, int, int]]]:
        """(key, scalars) of every step in key order, from the small scalars table.

        A step without scalars (written by an older build) is read whole, once.
        """
        with self.env.begin() as txn:
            packed = dict(txn.cursor(db=self.scalars).iternext()) if self.scalars is not None else {}
            ends = set(txn.cursor(db=self.ends).iternext(keys=True, values=False))
            arrival = 1 << 62
            for key in txn.cursor(db=self.steps).iternext(keys=True, values=False):
                rec = packed.get(key)
                if rec is not None:
                    yield key, SCALARS.unpack(rec)
                    continue
                raw = txn.get(key, db=self.steps)
                step = step_pb2.Step.FromString(raw)
                arrival += 1
                yield (
                    key,
                    (
                        step.reward,
                        flags_of(step) | (ENDS if key in ends else 0),
                        step.policy_version,
                        arrival,
                        len(raw),
                    ),
                )

    def episode_tables(self) -> dict[bytes, str]:
        if self.episodes is None:
            return {}
        with self.env.begin(db=self.episodes) as txn:
            return {bytes(k): bytes(v).decode() for k, v in txn.cursor()}

    # ------------------------------------------------------------------ writes

    def put_steps(
        self,
        steps: list[step_pb2.Step],
        table: str | list[str] = ONLINE,
        specs: Iterable[robot_pb2.RobotSpec] = (),
        raws: list[bytes] | None = None,
        known_waiting: Container[bytes] = (),
    ) -> Committed:
        """Store steps (and specs) in ONE transaction; returns once it has committed. Grows the map when full.

        `table` names the table of every step, or of each step (a list as long as `steps`).
        `known_waiting`: keys the caller knows are stored, end no episode and still wait for a successor.
        """
        specs = list(specs)
        tables = [table] * len(steps) if isinstance(table, str) else table
        raws = raws if raws is not None else [s.SerializeToString() for s in steps]
        nbytes = sum(map(len, raws))
        return self._growing(lambda: self._put_txn(steps, tables, specs, raws, known_waiting), nbytes)

    def _growing(self, write: Callable[[], T], nbytes: int = 0) -> T:
        """Run a write transaction, growing the map and retrying while LMDB says it is full (up to max_map_mb).

        A transaction that fails otherwise (LMDB has aborted it) raises DiskFullError or DiskWriteError."""
        while True:
            try:
                return write()
            except lmdb.MapFullError:
                if not self._grow():
                    raise ReplayFullError(
                        f"replay store {self.path} is full (map {self.map_bytes >> 20} MiB = max_map_mb); "
                        "raise replay.max_map_mb or lower replay.capacity_mb"
                    ) from None
            except (lmdb.Error, OSError) as exc:
                raise self._write_failed(exc, nbytes) from exc

    def _write_failed(self, exc: Exception, nbytes: int) -> ReplayError:
        """Why a write transaction of about `nbytes` failed: DiskFullError when the filesystem is (nearly) full.

        LMDB reports a short write, what a full disk gives, as EIO ("Input/output error"), not ENOSPC: an error
        with less free space left than the transaction needs counts as a full disk."""
        free = self.free_bytes()
        if isinstance(exc, lmdb.PanicError):  # a failed meta page write: LMDB refuses every transaction until reopened
            return DiskWriteError(f"replay's LMDB at {self.path} failed a write and must be reopened; restart replay")
        full = isinstance(exc, lmdb.DiskError) or getattr(exc, "errno", None) in _FULL_ERRNOS
        if full or 0 <= free < 2 * nbytes + FULL_MARGIN:
            return DiskFullError(f"replay's disk is full (path {self.path}, {free >> 10} KiB free: {exc})")
        return DiskWriteError(f"replay could not write {self.path} ({free >> 20} MiB free): {exc}")

    def free_bytes(self) -> int:
        """Bytes free for us on the filesystem under the store; -1 when it cannot be asked."""
        try:
            st = os.statvfs(self.path)
        except OSError:
            return -1
        return st.f_bavail * st.f_frsize

    def put_in_order(
        self,
        keys: list[bytes],
        raws: list[bytes],
        scalars: list[tuple[float, int, int, int]],
        episode_tables: dict[bytes, str],
        specs: list[robot_pb2.RobotSpec],
    ) -> int:
        """Steps the caller knows are new and in order (each its episode's next index, no successor stored):
        one transaction, every table written with one putmulti, no lookups. Returns the first arrival number.

        scalars: (reward, flags incl. ENDS, policy_version, value bytes) per step. Raises NotInOrder (and
        writes nothing) if a key was stored after all.
        """
        nbytes = sum(map(len, raws))
        return self._growing(lambda: self._put_in_order_txn(keys, raws, scalars, episode_tables, specs), nbytes)

    def _put_in_order_txn(
        self,
        keys: list[bytes],
        raws: list[bytes],
        scalars: list[tuple[float, int, int, int]],
        episode_tables: dict[bytes, str],
        specs: list[robot_pb2.RobotSpec],
    ) -> int:
        first = self.arrival
        pack = SCALARS.pack
        with self.env.begin(write=True) as txn:
            doomed = self._delete_doomed(txn)
            _, added = txn.cursor(db=self.steps).putmulti(zip(keys, raws, strict=True), overwrite=False)
            if added != len(keys):
                raise NotInOrder(f"{len(keys) - added} of {len(keys)} steps were stored already")
            packed = [pack(r, f, v, first + i, n) for i, (r, f, v, n) in enumerate(scalars)]
            txn.cursor(db=self.scalars).putmulti(zip(keys, packed, strict=True))
            ends = [(k, b"") for k, sc in zip(keys, scalars, strict=True) if sc[1] & ENDS]
            if ends:
                txn.cursor(db=self.ends).putmulti(ends)
            for prefix, table in episode_tables.items():
                txn.put(prefix, table.encode(), db=self.episodes, overwrite=False)
            for spec in specs:
                txn.put(spec.robot_id.encode(), spec.SerializeToString(), db=self.specs)
        del self._doomed[:doomed]
        self.arrival = first + len(keys)
        return first

    def _grow(self) -> bool:
        """Double the map (callers exclude readers of this process while it runs)."""
        if self.map_bytes >= self.max_map_bytes:
            return False
        new = min(self.map_bytes * 2, self.max_map_bytes)
        with self._guard:
            self.env.set_mapsize(new)
        log.info("replay map grown", extra=kv(path=str(self.path), mb=new >> 20))
        self.map_bytes = new
        return True

    def _put_txn(
        self,
        steps: list[step_pb2.Step],
        tables: list[str],
        specs: list[robot_pb2.RobotSpec],
        raws: list[bytes],
        known_waiting: Container[bytes],
    ) -> Committed:
        out = Committed()
        seen: set[bytes] = set()
        waiting: set[bytes] = set()  # stored in this transaction, not ending an episode
        with self.env.begin(write=True) as txn:
            doomed = self._delete_doomed(txn)
            for step, table, raw in zip(steps, tables, raws, strict=True):
                rid, eid, t = step.robot_id, step.episode_id, step.step_index
                key = step_key(rid, eid, t)
                if key in seen or not txn.put(key, raw, db=self.steps, overwrite=False):
                    out.duplicates += 1
                    out.stored_mask.append(False)
                    continue
                out.stored_mask.append(True)
                seen.add(key)
                out.stored.append((key, step, len(raw), table))
                out.nbytes += len(raw) + len(key)
                if table != ONLINE:
                    txn.put(episode_prefix(rid, eid), table.encode(), db=self.episodes, overwrite=False)
                ends = step.HasField("final_observation")  # validated: only the last step carries one
                flags = flags_of(step) | (ENDS if ends else 0)
                txn.put(
                    key, SCALARS.pack(step.reward, flags, step.policy_version, self.arrival, len(raw)), db=self.scalars
                )
                self.arrival += 1
                if ends:
                    txn.put(key, b"", db=self.ends)
                    out.sampleable.append(key)
                elif txn.get(next_key(key), db=self.steps) is not None:
                    out.sampleable.append(key)  # its successor arrived first (re-sent out of order)
                if not ends:
                    waiting.add(key)
                if t > 0:
                    prev = key[:-8] + _INDEX.pack(t - 1)
                    # prev waited for this observation, unless it ended an episode (sampleable already);
                    # known from memory for in-order arrivals, else asked of LMDB
                    known = prev in waiting or prev in known_waiting
                    if known or (txn.get(prev, db=self.steps) is not None and txn.get(prev, db=self.ends) is None):
                        out.sampleable.append(prev)
            for spec in specs:
                txn.put(spec.robot_id.encode(), spec.SerializeToString(), db=self.specs)
            if out.duplicates:
                txn.put(b"duplicates", _U64.pack(self.duplicates + out.duplicates), db=self.meta)
        del self._doomed[:doomed]
        self.duplicates += out.duplicates
        return out

    def delete_episodes(self, prefixes: list[bytes]) -> int:
        """Delete whole episodes now, in one transaction; returns the steps deleted."""
        return self._growing(lambda: self._delete_txn(prefixes))

    def _delete_txn(self, prefixes: list[bytes]) -> int:
        with self.env.begin(write=True) as txn:
            return self._delete(txn, prefixes)

    def delete_episodes_later(self, prefixes: list[bytes]) -> None:
        """Delete whole episodes (eviction) in the next write transaction, before its puts: no commit (and
        fsync) of its own. Until then they stay in LMDB (a crash meanwhile keeps them; a reopened store
        evicts them again). Callers have taken them out of every index already."""
        self._doomed.extend(prefixes)

    def _delete_doomed(self, txn: lmdb.Transaction) -> int:
        """Delete the episodes evicted so far inside `txn`; returns how many the caller drops once it commits."""
        if self._doomed:
            self._delete(txn, self._doomed)
        return len(self._doomed)

    def _delete(self, txn: lmdb.Transaction, prefixes: list[bytes]) -> int:
        """Prefixes in key order, each table with one cursor that deletes as it walks (no lookup per key)."""
        deleted = 0
        steps, scalars, ends = (txn.cursor(db=db) for db in (self.steps, self.scalars, self.ends))
        for prefix in sorted(prefixes):
            deleted += _delete_range(steps, prefix)
            _delete_range(scalars, prefix)
            _delete_range(ends, prefix)
            txn.delete(prefix, db=self.episodes)
        return deleted

    def put_spec(self, spec: robot_pb2.RobotSpec) -> None:
        raw = spec.SerializeToString()
        self._growing(lambda: self._put_spec_txn(spec.robot_id.encode(), raw), len(raw))

    def _put_spec_txn(self, key: bytes, raw: bytes) -> None:
        with self.env.begin(write=True, db=self.specs) as txn:
            txn.put(key, raw)

    # ------------------------------------------------------------------ reads

    def get_spec(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        if self.specs is None:
            return None
        with self.env.begin(db=self.specs) as txn:
            raw = txn.get(robot_id.encode())
        return None if raw is None else robot_pb2.RobotSpec.FromString(raw)

    def get_many(self, keys: list[bytes]) -> list[bytes | None]:
        with self.env.begin(db=self.steps, buffers=False) as txn:
            return [txn.get(k) for k in keys]

    def bytes_on_disk(self) -> int:
        """Bytes of LMDB pages in use in data.mdb (the map itself is sparse)."""
        return (self.env.info()["last_pgno"] + 1) * self.env.stat()["psize"]

    def close(self) -> None:
        self._stop.set()
        if not self.readonly:
            self._finish_writes()
        self.env.close()

    def _finish_writes(self) -> None:
        """Delete what eviction left and fsync; on a full disk log it and close anyway (what committed is safe,
        and a reopened store evicts those episodes again)."""
        try:
            if self._doomed:
                self.delete_episodes(self._doomed)
                self._doomed.clear()
            self.env.sync(True)
        except (ReplayError, lmdb.Error) as exc:
            log.warning("replay closed without finishing its writes", extra=kv(path=str(self.path), error=str(exc)))
