"""The edge's outbox: steps wait here, numbered, until replay acknowledges them.

Two kinds behind one small interface:

- `LmdbSpool` (the default): every step is committed to a local LMDB file *before* it is sent and
  deleted only when replay's InsertAck names its seq. A kill -9 of the edge, or a network outage of
  any length the disk can hold, loses nothing: on start the sender re-sends whatever is still here,
  and replay stores each step once because it keys steps by (robot, episode, step). Layout: table
  `steps` maps seq (8-byte big-endian, so key order is send order) to the serialized Step; table
  `meta` holds next_seq (never reused, even after every step was acked), the byte total and the
  dropped count, each updated in the same transaction as the steps; table `tables` maps the seq of a
  step bound for a replay table other than the default to that table's name; table `held` keeps steps
  replay refused for this agent's identity (PERMISSION_DENIED), set aside so the steps after them go on
  (see `quarantine`). Without `fsync` a commit
  survives the death of the process (the kernel holds the pages) and is flushed to the device
  every second; with it, every commit is flushed (power loss too, ~2 ms a step on these disks).
- `MemoryOutbox`: the same in RAM, bounded by a step count (today's behaviour; lost on a crash).

A full spool (the next step would pass `max_bytes`) follows its policy: `drop_oldest` deletes the oldest
steps to make room; `dropped` counts the lost ones: never sent, or sent and never acknowledged (a step replay
stored and acks after its drop is not lost; a kill -9 forgets drops still awaiting their ack), and a log line
per episode names their step range. `pause` keeps every step and reports `accepting = False`, which the robot
loop obeys by holding still until acks free space. `max_bytes` is the configured cap lowered to what the
disk allows now: the spool's pages may fill half of its file plus the free disk (LMDB deletes copy pages
too, so acks still work on a full spool). It is re-read from the disk every second, on acks and as the
spool grows, so a disk another process fills or frees moves it both ways. A write the disk refuses anyway
(ENOSPC) lowers it to what the spool holds until the free disk grows or acks free pages; under `pause` that
step, and any that come while the disk has no room, wait in RAM (sent from there, counted, written to disk
once it has room; lost only if the edge stops first) so nothing collected is dropped. Steps set aside
(`quarantine`) are not awaiting an ack: they leave `count`, are moved back and tried again when the spool
is next opened or when the sender sees replay take their robot's steps again (`release_quarantined`: an
operator may have let the token write it meanwhile), and are the first to go when room is needed under
either policy, so refused steps never make the robots hold.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from abc import ABC, abstractmethod
from collections import OrderedDict
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

import lmdb
import prometheus_client

from user import owner_lock
from user.config import ConfigError, EdgeConfig
from user.log import kv
from user.v1 import replay_pb2, step_pb2

log = logging.getLogger(__name__)

FullPolicy = Literal["pause", "drop_oldest"]

SPOOL_STEPS = prometheus_client.Gauge("user_edge_spool_steps", "Steps in the outbox, waiting for replay's ack")
SPOOL_BYTES = prometheus_client.Gauge("user_edge_spool_bytes", "Serialized step bytes in the outbox")
SPOOL_DROPPED = prometheus_client.Counter(
    "user_edge_spool_dropped_total",
    "Steps dropped because the outbox was full and lost: never sent, or sent and never acknowledged by replay",
)
SPOOL_QUARANTINED = prometheus_client.Gauge(
    "user_edge_spool_quarantined_steps",
    "Steps replay refused for this agent's identity, set aside in the spool until replay takes their robot's "
    "steps again or the spool is next opened",
)
SPOOL_FULL = prometheus_client.Gauge(
    "user_edge_spool_full", "1 while the outbox is at its cap (pause: robots hold; drop_oldest: dropping)"
)

_SYNC_EVERY_S = 1.0  # also how often the free disk is re-read
_DROP_LOG_EVERY_S = 10.0
_META_PAGES = 2  # LMDB's two meta pages: in the file, in no database's stat
_RECHECK_MIN_BYTES = 64 << 10  # a put re-reads the free disk after the spool grew by this or a quarter of its room
_MAP_HEADROOM = 64 << 20  # LMDB pages cost more than the step bytes they hold; the map grows past this too


class Outbox(ABC):
    """Numbered steps awaiting replay's ack, oldest first. Thread-safe."""

    policy: FullPolicy
    dropped: int

    @abstractmethod
    def put(self, step: step_pb2.Step, table: str = "") -> int:
        """Keep the step and its replay table (durably, for a spool) and return its seq; never blocks on the
        network. "" is replay's default table ("online")."""

    @abstractmethod
    def read(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
        """Up to `limit` kept steps with seq > after_seq, in seq order, ready to send."""

    @abstractmethod
    def ack(self, seqs: Iterable[int]) -> int:
        """Forget these seqs (acknowledged or rejected); returns how many were still kept."""

    def quarantine(self, seqs: Iterable[int]) -> int:
        """Set these kept seqs aside: no longer sent nor counted as awaiting an ack, so later steps go on.
        Only a spool keeps them (see release_quarantined); in RAM they are dropped. Returns how many."""
        return self.ack(seqs)

    @property
    def quarantined(self) -> int:
        """Steps set aside and still kept."""
        return 0

    def release_quarantined(self) -> int:
        """Put every step set aside back among the kept ones, under its old seq; returns how many."""
        return 0

    @property
    @abstractmethod
    def count(self) -> int: ...

    @property
    @abstractmethod
    def nbytes(self) -> int: ...

    @property
    @abstractmethod
    def last_seq(self) -> int:
        """The newest seq handed out (0 before the first)."""

    @property
    @abstractmethod
    def full(self) -> bool: ...

    @property
    def accepting(self) -> bool:
        """False while full under the pause policy: the robot loop holds instead of collecting."""
        return not (self.policy == "pause" and self.full)

    def close(self) -> None:  # noqa: B027 (optional hook: only a spool has something to release)
        """Release the store; kept steps stay (for a spool) until the next open."""

    def _publish_metrics(self) -> None:
        SPOOL_STEPS.set(self.count)
        SPOOL_BYTES.set(self.nbytes)
        SPOOL_QUARANTINED.set(self.quarantined)
        SPOOL_FULL.set(int(self.full))


_MAX_DROPPED_IN_FLIGHT = 100_000  # dropped steps awaiting a possible ack; beyond, the oldest count as lost


def _step_id(data: bytes) -> tuple[str, str, int]:
    step = step_pb2.Step.FromString(data)
    return step.robot_id, step.episode_id, step.step_index


class _Drops:
    """Which steps dropped from a full outbox are lost. One the sender has not read yet is lost at once. One it
    read is in flight: replay may store and ack it still, so it is lost only if its stream ends without that ack
    (the sender's next read from below what it read before starts a new stream). Lost steps are logged per episode
    with their step range, one line per burst of drops (and at least every _DROP_LOG_EVERY_S while one lasts).
    The caller holds its outbox's lock; `read` sees the reads in the same lock as the drops."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.read_upto = 0  # newest seq the sender read on its current stream
        self.in_flight: dict[int, tuple[str, str, int]] = {}  # dropped after being read: seq -> step id, until acked
        self.burst: dict[tuple[str, str], list[int]] = {}  # (robot, episode) -> [first, last, steps] lost, unlogged
        self.first_at = self.last_at = 0.0

    def lost_now(self, seqs: Iterable[int]) -> int:
        """How many of these drops are lost at once (not read yet); changes nothing."""
        return sum(seq > self.read_upto for seq in seqs)

    def dropped(self, gone: Iterable[tuple[int, tuple[str, str, int]]]) -> int:
        """Steps (seq, step id) that left the outbox unacknowledged; returns how many are lost now."""
        lost = 0
        for seq, step in gone:
            if seq > self.read_upto:
                self._lost(step)
                lost += 1
            else:
                self.in_flight[seq] = step
        while len(self.in_flight) > _MAX_DROPPED_IN_FLIGHT:
            self._lost(self.in_flight.pop(next(iter(self.in_flight))))
            lost += 1
        return lost

    def acked(self, seqs: Iterable[int]) -> None:
        """Replay stored these: a dropped one among them was not lost."""
        if self.in_flight:
            for seq in seqs:
                self.in_flight.pop(seq, None)

    def read(self, after_seq: int, top: int) -> int:
        """The sender read (after_seq, top]; returns how many in-flight drops this shows lost."""
        lost = 0
        if after_seq < self.read_upto:  # a new stream: the old one's acks are over
            lost = self.end_stream()
            self.read_upto = after_seq
        self.read_upto = max(self.read_upto, top)
        return lost

    def end_stream(self) -> int:
        """Every drop still in flight was never acked: lost. Returns how many."""
        for step in self.in_flight.values():
            self._lost(step)
        lost, self.in_flight = len(self.in_flight), {}
        return lost

    def _lost(self, step: tuple[str, str, int]) -> None:
        now = time.monotonic()
        if not self.burst:
            self.first_at = now
        self.last_at = now
        robot, episode, t = step
        span = self.burst.setdefault((robot, episode), [t, t, 0])
        span[0], span[1], span[2] = min(span[0], t), max(span[1], t), span[2] + 1

    def log(self, force: bool = False) -> None:
        """One warning per episode for the lost steps gathered, once their burst ended (a quiet second), every
        _DROP_LOG_EVERY_S while it lasts, or when forced (close)."""
        now = time.monotonic()
        if not self.burst or not (force or now - self.last_at >= 1.0 or now - self.first_at >= _DROP_LOG_EVERY_S):
            return
        for (robot, episode), (first, last, n) in self.burst.items():
            log.warning(
                "spool full; steps dropped that replay never acknowledged",
                extra=kv(path=self.where, robot_id=robot, episode_id=episode, steps=f"{first}-{last}", count=n),
            )
        self.burst = {}


class MemoryOutbox(Outbox):
    """In RAM, at most `max_steps`; the oldest are dropped beyond (lost on a crash)."""

    policy: FullPolicy = "drop_oldest"

    def __init__(self, max_steps: int = 100_000) -> None:
        self.max_steps = max_steps
        self.dropped = 0
        self._lock = threading.Lock()
        self._steps: OrderedDict[int, replay_pb2.InsertRequest] = OrderedDict()
        self._bytes = 0
        self._next_seq = 1
        self._drops = _Drops("memory")

    def put(self, step: step_pb2.Step, table: str = "") -> int:
        req = replay_pb2.InsertRequest(step=step, table=table)
        size = req.step.ByteSize()
        with self._lock:
            seq = req.seq = self._next_seq
            self._next_seq += 1
            self._steps[seq] = req
            self._bytes += size
            gone = []
            while len(self._steps) > self.max_steps:
                old_seq, old = self._steps.popitem(last=False)
                self._bytes -= old.step.ByteSize()
                gone.append((old_seq, (old.step.robot_id, old.step.episode_id, old.step.step_index)))
            self._count_lost(self._drops.dropped(gone))
            self._drops.log()
        self._publish_metrics()
        return seq

    def _count_lost(self, n: int) -> None:
        self.dropped += n
        SPOOL_DROPPED.inc(n)

    def read(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
        with self._lock:
            out = self._read(after_seq, limit)
            self._count_lost(self._drops.read(after_seq, out[-1].seq if out else after_seq))
            return out

    def _read(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
        """Caller holds the lock."""
        if not self._steps or after_seq >= self._next_seq - 1:
            return []
        out = []
        # Seqs only grow, so every kept seq from after_seq+1 on is found by probing upwards;
        # the gaps (acked or dropped) are skipped by starting at the oldest kept seq.
        seq = max(after_seq + 1, next(iter(self._steps)))
        while seq < self._next_seq and len(out) < limit:
            req = self._steps.get(seq)
            if req is not None:
                out.append(req)
            seq += 1
        return out

    def ack(self, seqs: Iterable[int]) -> int:
        n = 0
        seqs = list(seqs)
        with self._lock:
            self._drops.acked(seqs)
            for seq in seqs:
                req = self._steps.pop(seq, None)
                if req is not None:
                    self._bytes -= req.step.ByteSize()
                    n += 1
        self._publish_metrics()
        return n

    @property
    def count(self) -> int:
        return len(self._steps)

    @property
    def nbytes(self) -> int:
        return self._bytes

    @property
    def last_seq(self) -> int:
        return self._next_seq - 1

    @property
    def full(self) -> bool:
        return len(self._steps) >= self.max_steps

    def close(self) -> None:
        with self._lock:  # drops still in flight get no ack now
            self._count_lost(self._drops.end_stream())
            self._drops.log(force=True)


def _key(seq: int) -> bytes:
    return seq.to_bytes(8, "big")


class SpoolInUse(ConfigError):
    """Another live process owns this spool (two agents with one agent_id on one machine): a start-up error,
    one line through the CLI (exit 2), not a traceback that a service manager restarts forever."""


def _pages(stat: dict[str, int]) -> int:
    return stat["branch_pages"] + stat["leaf_pages"] + stat["overflow_pages"]


def _take_owner(path: Path) -> int:
    """One owner at a time: two writers would hand out the same seqs. The kernel drops the lock when its
    process dies, kill -9 included, so a restarted edge takes it over at once. Returns the locked fd."""
    try:
        return owner_lock.take(path / "owner.lock")
    except owner_lock.Held as held:
        raise SpoolInUse(
            f"edge.spool_dir: spool {path} is in use by pid {held.holder} (another edge with this edge.agent_id?)"
        ) from None


class LmdbSpool(Outbox):
    """Steps in a local LMDB environment at `path` until acked; see the module docstring."""

    def __init__(self, path: str | Path, max_bytes: int, policy: FullPolicy = "pause", fsync: bool = False) -> None:
        if policy not in ("pause", "drop_oldest"):
            raise ValueError(f"spool full policy must be pause or drop_oldest, got {policy!r}")
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self._owner = _take_owner(self.path)
        self.asked_bytes = max_bytes  # the configured cap: max_bytes never goes above it
        self.max_bytes = max_bytes
        self.policy = policy
        self._fsync = fsync
        self._lock = threading.Lock()
        self._last_size = 0  # bytes of the newest step: "full" means the next one like it would not fit
        self._disk_error = False  # a write failed: the cap stays at what the spool held until the disk changes
        self._free_at_error = 0
        self._recheck_at = 0  # spool + held bytes past which a put re-reads the free disk
        self._pending: dict[int, tuple[bytes, str]] = {}  # pause, disk full: seq -> (step, table), in seq order
        self._pending_bytes = 0
        self._last_drop_log = -float("inf")
        self._drops = _Drops(str(self.path))
        self._env = lmdb.open(
            str(self.path), map_size=2 * max_bytes + _MAP_HEADROOM, max_dbs=4, sync=fsync, metasync=fsync
        )
        self._steps = self._env.open_db(b"steps")
        self._meta = self._env.open_db(b"meta")
        self._tables = self._env.open_db(b"tables")  # seq -> replay table, only for steps not in the default
        self._held = self._env.open_db(b"held")  # seq -> step replay refused for this identity (quarantine)
        self._held_count = self._held_bytes = 0
        restored, _ = self._restore_held()
        self._load_meta()
        with self._lock:
            self._refresh_cap()
        if self.max_bytes < max_bytes:
            log.warning(
                "spool cap lowered to half the free disk",
                extra=kv(path=str(self.path), asked_bytes=max_bytes, max_bytes=self.max_bytes),
            )
        self._closed = threading.Event()
        self._keeper = threading.Thread(target=self._keep_loop, name="spool-sync", daemon=True)
        self._keeper.start()
        self._publish_metrics()
        log.info(
            "spool opened",
            extra=kv(path=str(self.path), steps=self._count, bytes=self._bytes, policy=policy, cap=self.max_bytes),
        )
        if restored:
            log.warning(
                "steps replay refused earlier for this agent's token are tried again",
                extra=kv(path=str(self.path), steps=restored),
            )

    def _load_meta(self) -> None:
        with self._env.begin() as txn:
            self._next_seq = self._meta_int(txn, b"next_seq", 1)
            self._bytes = self._meta_int(txn, b"bytes", 0)
            self.dropped = self._meta_int(txn, b"dropped", 0)
            self._count = txn.stat(self._steps)["entries"]
            last = txn.cursor(self._steps)
            if last.last():  # next_seq is committed with each put; this only guards a hand-edited file
                self._next_seq = max(self._next_seq, int.from_bytes(last.key(), "big") + 1)

    def _restore_held(self) -> tuple[int, int]:
        """Move steps set aside back among the kept ones (same seqs, so send order holds), at open (the token
        may write their robot by now; if not, replay refuses them again and they go back aside) or when replay
        took a refused robot's step again. The caller updates the counts. Returns (steps, bytes)."""
        with self._env.begin(write=True) as txn:
            cursor, moved, nbytes = txn.cursor(self._held), 0, 0
            for key, value in cursor:
                txn.put(key, value, db=self._steps)
                moved, nbytes = moved + 1, nbytes + len(value)
            cursor.close()
            if moved:
                txn.drop(self._held, delete=False)
                txn.put(b"bytes", _key(self._meta_int(txn, b"bytes", 0) + nbytes), db=self._meta)
        return moved, nbytes

    def release_quarantined(self) -> int:
        with self._lock:
            if not self._held_count:
                return 0
            try:
                moved, nbytes = self._restore_held()
            except lmdb.Error as exc:  # a full disk: they stay aside until the next open
                log.warning("spool could not release steps set aside", extra=kv(path=str(self.path), error=str(exc)))
                return 0
            self._bytes, self._count = self._bytes + nbytes, self._count + moved
            self._held_count = self._held_bytes = 0
        self._publish_metrics()
        return moved

    def _meta_int(self, txn: lmdb.Transaction, name: bytes, default: int) -> int:
        raw = txn.get(name, db=self._meta)
        return int.from_bytes(raw, "big") if raw is not None else default

    # ------------------------------------------------------------------ the cap and the disk

    def _disk_room(self, free: int) -> int:
        """Bytes the spool may still fill (negative: it holds more than its share): its file's free pages plus
        half of the free disk beyond its file, i.e. its pages stay within half of (its file + the free disk).
        Stable as the spool grows (file and free disk change together), so re-reading it never creeps up."""
        psize = self._env.stat()["psize"]
        file_pages = self._env.info()["last_pgno"] + 1
        with self._env.begin() as txn:
            dbs = (self._steps, self._meta, self._tables, self._held)
            used = _META_PAGES + _pages(self._env.stat()) + sum(_pages(txn.stat(db)) for db in dbs)
        return (file_pages - used) * psize + (free - file_pages * psize) // 2

    def _free_disk(self) -> int | None:
        try:
            return shutil.disk_usage(self.path).free  # statvfs
        except OSError as exc:  # never fails a put: the cap stays as it was
            log.warning("spool cannot read the free disk", extra=kv(path=str(self.path), error=str(exc)))
            return None

    def _refresh_cap(self, freed: bool = False) -> None:
        """Caller holds the lock. The cap from the disk as it is now: at most the configured one, and otherwise
        never below what the spool holds (a tighter disk never drops kept steps by itself). After a write failed
        it stays lowered until the free disk grew or acks freed pages (`freed`): a retry needs a change."""
        free = self._free_disk()
        if free is None or (self._disk_error and free <= self._free_at_error and not freed):
            return
        if self._disk_error:
            log.info("spool disk has room again; cap recomputed", extra=kv(path=str(self.path), free_bytes=free))
        self._disk_error = False
        held = self._bytes + self._held_bytes
        room = self._disk_room(free)
        self.max_bytes = min(self.asked_bytes, held + max(0, room))
        self._recheck_at = held + max(room // 4, _RECHECK_MIN_BYTES)

    def _note_disk_full(self, exc: lmdb.Error) -> None:
        """Caller holds the lock. The disk refused a write before the cap: the cap drops to what the spool holds
        until the disk changes (see _refresh_cap), so pause holds the robots and drop_oldest recycles pages."""
        if not self._disk_error:
            log.error("spool disk full; cap lowered until space returns", extra=kv(path=str(self.path), error=str(exc)))
        self._disk_error = True
        self._free_at_error = self._free_disk() or 0
        self.max_bytes = min(self.max_bytes, self._bytes + self._held_bytes)

    def _keep_loop(self) -> None:
        """Flush commits to the device every second (unless each commit is fsynced) and re-read the free disk:
        one another process filled lowers the cap before the spool hits it, one it freed lifts a lowered cap
        even when no put or ack comes (a paused robot, an empty spool)."""
        while not self._closed.wait(_SYNC_EVERY_S):
            try:
                if not self._fsync:
                    self._env.sync(True)
                with self._lock:
                    self._refresh_cap()
                    self._flush_pending()
                    self._drops.log()
            except (lmdb.Error, OSError) as exc:  # a full or failing disk: the next round tries again
                log.warning("spool upkeep failed", extra=kv(path=str(self.path), error=str(exc)))
            self._publish_metrics()

    # ------------------------------------------------------------------ put

    def put(self, step: step_pb2.Step, table: str = "") -> int:
        data = step.SerializeToString()
        with self._lock:
            was_full = self.full
            seq = self._next_seq
            if self._bytes + self._held_bytes > self._recheck_at:  # grown a good part of its room: is it still there?
                self._refresh_cap()
            dropped = self._store(seq, data, table)
            # Only now: the sender takes every seq up to last_seq as readable (or acked or dropped).
            self._next_seq, self._last_size = seq + 1, len(data)
            self._drops.log()
        if self.policy == "pause" and self.full and not was_full:
            log.warning(
                "spool full; robots hold until replay acknowledges steps",
                extra=kv(path=str(self.path), steps=self.count, bytes=self.nbytes),
            )
        if dropped:
            self._log_dropped()
        self._publish_metrics()
        return seq

    def _log_dropped(self) -> None:
        now = time.monotonic()
        if now - self._last_drop_log < _DROP_LOG_EVERY_S:  # at the cap every step drops one: log rarely
            return
        self._last_drop_log = now
        what = "the oldest steps" if self.policy == "drop_oldest" else "steps replay refused (set aside)"
        log.warning(f"spool full; dropping {what}", extra=kv(path=str(self.path), total=self.dropped))

    def _count_dropped(self, n: int) -> int:
        self.dropped += n
        SPOOL_DROPPED.inc(n)
        return n

    def _store(self, seq: int, data: bytes, table: str) -> int:
        """Caller holds the lock. Steps waiting in RAM go to disk first, so seq order holds; this one after
        them (in RAM too while the disk has no room). Returns the steps dropped making room."""
        dropped = self._flush_pending()
        if self._pending:
            self._keep_in_ram(seq, data, table)
            return dropped
        try:
            return dropped + self._write(seq, data, table)
        except lmdb.Error as exc:  # the disk filled before the cap
            return dropped + self._disk_full(seq, data, table, exc)

    def _disk_full(self, seq: int, data: bytes, table: str, exc: lmdb.Error) -> int:
        """Caller holds the lock. Steps set aside go first, whatever the policy; then drop_oldest frees the
        oldest 1 % in a transaction of its own, and drops this step if even that fails. pause drops nothing
        collected: the step waits in RAM, the spool reports full and the robots hold."""
        self._note_disk_full(exc)
        dropped = 0
        if self._held_count:
            try:
                with self._env.begin(write=True) as txn:
                    held, _ = self._drop_held(txn, self._held_bytes)
                    txn.put(b"dropped", _key(self.dropped + held), db=self._meta)
                self._held_count = self._held_bytes = 0
                dropped += self._count_dropped(held)
                return dropped + self._write(seq, data, table)
            except lmdb.Error:
                pass
        if self.policy == "drop_oldest":
            try:
                dropped += self._drop_oldest(max(1, self._count // 100))
                return dropped + self._write(seq, data, table)
            except lmdb.Error:  # this step goes, never sent
                return dropped + self._count_dropped(self._drops.dropped([(seq, _step_id(data))]))
        self._keep_in_ram(seq, data, table)
        return dropped

    def _keep_in_ram(self, seq: int, data: bytes, table: str) -> None:
        """Caller holds the lock (pause, the disk has no room): the step waits in RAM, sent from there."""
        if not self._pending:
            log.warning(
                "spool disk full; new steps wait in RAM until it has room (robots hold)",
                extra=kv(path=str(self.path), seq=seq),
            )
        self._pending[seq] = (data, table)
        self._pending_bytes += len(data)

    def _flush_pending(self) -> int:
        """Caller holds the lock. Write the steps waiting in RAM to disk, oldest first, unless the disk is known
        to have no room; stops at the first it refuses. Returns the steps dropped making room."""
        dropped = 0
        while self._pending and not self._disk_error:
            seq, (data, table) = next(iter(self._pending.items()))
            try:
                dropped += self._write(seq, data, table)
            except lmdb.Error as exc:
                self._note_disk_full(exc)
                break
            del self._pending[seq]
            self._pending_bytes -= len(data)
        return dropped

    def _drop_held(self, txn: lmdb.Transaction, need: int) -> tuple[int, int]:
        """Caller holds the lock, in `txn`. Drop the oldest steps set aside until `need` bytes are free or none
        is left: refused steps go before any awaiting an ack. Returns (steps, bytes) dropped."""
        cursor, dropped, freed = txn.cursor(self._held), 0, 0
        while freed < need and cursor.first():
            freed += len(cursor.value())
            txn.delete(cursor.key(), db=self._tables)
            cursor.delete()
            dropped += 1
        return dropped, freed

    def _drop_oldest(self, n: int) -> int:
        """Caller holds the lock. Drop the n oldest kept steps in a transaction of their own; returns how many."""
        with self._env.begin(write=True) as txn:
            cursor, nbytes, gone = txn.cursor(self._steps), self._bytes, []
            while len(gone) < n and cursor.first():
                nbytes -= self._pop_oldest(txn, cursor, gone)
            txn.put(b"bytes", _key(nbytes), db=self._meta)
            lost = self._drops.lost_now(seq for seq, _ in gone)
            txn.put(b"dropped", _key(self.dropped + lost), db=self._meta)
        self._bytes, self._count = nbytes, self._count - len(gone)
        self._count_dropped(self._drops.dropped(gone))
        return len(gone)

    def _pop_oldest(
        self, txn: lmdb.Transaction, cursor: lmdb.Cursor, gone: list[tuple[int, tuple[str, str, int]]]
    ) -> int:
        """Delete the step under `cursor` (the oldest kept), noting (seq, step id) in `gone`; returns its bytes."""
        key, value = cursor.key(), cursor.value()
        gone.append((int.from_bytes(key, "big"), _step_id(value)))
        txn.delete(key, db=self._tables)
        cursor.delete()
        return len(value)

    def _write(self, seq: int, data: bytes, table: str = "") -> int:
        """Caller holds the lock. One transaction: make room (drop_oldest), put, update meta."""
        for attempt in range(4):
            try:
                with self._env.begin(write=True) as txn:
                    nbytes, count, dropped = self._bytes, self._count, 0
                    held, held_bytes = self._held_count, self._held_bytes
                    over = nbytes + held_bytes + len(data) - self.max_bytes
                    if held and over > 0:  # refused steps make room first: they never make the robots hold
                        gone, freed = self._drop_held(txn, over)
                        held, held_bytes, dropped = held - gone, held_bytes - freed, gone
                    oldest: list[tuple[int, tuple[str, str, int]]] = []  # (seq, step id) of kept steps dropped
                    if self.policy == "drop_oldest":
                        cursor = txn.cursor(self._steps)
                        while count and nbytes + len(data) > self.max_bytes and cursor.first():
                            nbytes -= self._pop_oldest(txn, cursor, oldest)
                            count -= 1
                    txn.put(_key(seq), data, db=self._steps)
                    if table:  # most steps go to the default table: nothing kept for them
                        txn.put(_key(seq), table.encode(), db=self._tables)
                    nbytes, count = nbytes + len(data), count + 1
                    txn.put(b"next_seq", _key(max(seq + 1, self._next_seq)), db=self._meta)  # older ones from RAM too
                    txn.put(b"bytes", _key(nbytes), db=self._meta)
                    # a step the sender read may still be stored and acked: lost only once its stream ends
                    lost = dropped + self._drops.lost_now(s for s, _ in oldest)
                    txn.put(b"dropped", _key(self.dropped + lost), db=self._meta)
                self._bytes, self._count = nbytes, count
                self._held_count, self._held_bytes = held, held_bytes
                self._count_dropped(dropped + self._drops.dropped(oldest))
                return dropped + len(oldest)
            except lmdb.MapFullError:
                if attempt == 3:
                    raise
                # Page overhead outgrew the map before the byte cap: grow it (no transaction is open).
                size = self._env.info()["map_size"] * 2
                log.warning("spool map grown", extra=kv(path=str(self.path), map_size=size))
                self._env.set_mapsize(size)
        raise AssertionError("unreachable")

    # ------------------------------------------------------------------ read, ack, set aside

    def read(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
        """The disk is read and parsed outside the lock: `put` runs on the robots' control threads, and a drain
        of large steps must not hold them. RAM is taken first (under the lock), then the disk (one LMDB snapshot):
        steps move from RAM to disk oldest first, so every step up to the newest returned is seen (a step seen in
        both is returned once). A drop racing the read (between the disk read and the lock that notes it) counts
        as lost even if replay stores the step it was sent as (see _Drops)."""
        with self._lock:
            in_ram = [(seq, kept) for seq, kept in self._pending.items() if seq > after_seq][:limit]
        out = {req.seq: req for req in self._read_disk(after_seq, limit)}
        for seq, (data, table) in in_ram:
            if seq not in out:
                req = out[seq] = replay_pb2.InsertRequest(seq=seq, table=table)
                req.step.ParseFromString(data)
        reqs = sorted(out.values(), key=lambda r: r.seq)[:limit]
        with self._lock:  # a drop from now on knows the sender read its step
            self._count_dropped(self._drops.read(after_seq, reqs[-1].seq if reqs else after_seq))
        return reqs

    def _read_disk(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
        out: list[replay_pb2.InsertRequest] = []
        with self._env.begin(db=self._steps) as txn:
            cursor = txn.cursor()
            if not cursor.set_range(_key(after_seq + 1)):
                return out
            for key, value in cursor:
                table = txn.get(key, db=self._tables)
                req = replay_pb2.InsertRequest(seq=int.from_bytes(key, "big"), table=table.decode() if table else "")
                req.step.ParseFromString(value)
                out.append(req)
                if len(out) >= limit:
                    break
        return out

    def ack(self, seqs: Iterable[int]) -> int:
        seqs = list(seqs)
        with self._lock:
            self._drops.acked(seqs)
            n = self._forget_pending(seqs)
            try:
                deleted = self._delete(seqs)
            except lmdb.Error as exc:  # a full disk: the steps stay and go again later (replay dedupes)
                log.warning("spool could not forget acked steps", extra=kv(path=str(self.path), error=str(exc)))
                deleted = 0
            if deleted:  # pages freed: room again, maybe
                self._refresh_cap(freed=True)
                self._flush_pending()
        self._publish_metrics()
        return n + deleted

    def _forget_pending(self, seqs: list[int]) -> int:
        """Caller holds the lock. Drop acked steps still waiting in RAM; returns how many."""
        n = 0
        for seq in seqs:
            kept = self._pending.pop(seq, None)
            if kept is not None:
                self._pending_bytes -= len(kept[0])
                n += 1
        return n

    def _delete(self, seqs: list[int]) -> int:
        """Caller holds the lock. Delete these seqs from disk in one transaction; returns how many were there."""
        n = 0
        with self._env.begin(write=True) as txn:
            nbytes = self._bytes
            for seq in seqs:
                value = txn.pop(_key(seq), db=self._steps)
                if value is not None:  # a step set aside keeps its table for when it is tried again
                    txn.delete(_key(seq), db=self._tables)
                    nbytes -= len(value)
                    n += 1
            if n:
                txn.put(b"bytes", _key(nbytes), db=self._meta)
        self._bytes, self._count = nbytes, self._count - n
        return n

    def quarantine(self, seqs: Iterable[int]) -> int:
        seqs = list(seqs)
        with self._lock:
            in_ram = {seq: self._pending[seq] for seq in seqs if seq in self._pending}
            try:
                n, moved = self._set_aside(seqs, in_ram)
            except lmdb.Error as exc:  # a full disk: the steps stay and are refused again later
                log.warning("spool could not set steps aside", extra=kv(path=str(self.path), error=str(exc)))
                # Refused steps waiting in RAM would hold the robots (pause): they are the first to go anyway.
                n, moved = self._count_dropped(self._forget_pending(list(in_ram))), 0
            else:
                self._forget_pending(list(in_ram))
                self._held_count, self._held_bytes = self._held_count + n, self._held_bytes + moved
        self._publish_metrics()
        return n

    def _set_aside(self, seqs: list[int], in_ram: dict[int, tuple[bytes, str]]) -> tuple[int, int]:
        """Caller holds the lock. Move these seqs (from disk or RAM) to `held` in one transaction; returns
        (steps, bytes) moved."""
        n = moved = 0
        with self._env.begin(write=True) as txn:
            nbytes = self._bytes
            for seq in seqs:
                value = txn.pop(_key(seq), db=self._steps)
                if value is not None:  # its `tables` entry stays: it goes to that table when retried
                    txn.put(_key(seq), value, db=self._held)
                    nbytes, moved, n = nbytes - len(value), moved + len(value), n + 1
            for seq, (data, table) in in_ram.items():
                txn.put(_key(seq), data, db=self._held)
                if table:
                    txn.put(_key(seq), table.encode(), db=self._tables)
                moved, n = moved + len(data), n + 1
            if n:
                txn.put(b"bytes", _key(nbytes), db=self._meta)
                txn.put(b"next_seq", _key(self._next_seq), db=self._meta)
        self._bytes, self._count = nbytes, self._count - (n - len(in_ram))
        return n, moved

    # ------------------------------------------------------------------ state

    @property
    def quarantined(self) -> int:
        return self._held_count

    @property
    def count(self) -> int:
        return self._count + len(self._pending)

    @property
    def nbytes(self) -> int:
        return self._bytes + self._pending_bytes

    @property
    def last_seq(self) -> int:
        return self._next_seq - 1

    @property
    def full(self) -> bool:  # steps set aside are not counted: they make room when needed (see _write)
        return bool(self._pending) or self._bytes + self._last_size > self.max_bytes

    def _close_drops(self) -> None:
        """Caller holds the lock. Drops still in flight get no ack now: lost; the count is kept on disk."""
        self._count_dropped(self._drops.end_stream())
        self._drops.log(force=True)
        try:
            with self._env.begin(write=True) as txn:
                txn.put(b"dropped", _key(self.dropped), db=self._meta)
        except lmdb.Error as exc:  # a full disk: the count on disk stays what the last write left
            log.warning("spool could not record its dropped count", extra=kv(path=str(self.path), error=str(exc)))

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._keeper.join()
        with self._lock:
            self._disk_error = False  # a last try for the steps waiting in RAM
            self._flush_pending()
            if self._pending:
                log.error(
                    "spool disk full at close; steps waiting in RAM are lost",
                    extra=kv(path=str(self.path), steps=len(self._pending)),
                )
            self._close_drops()
            try:
                self._env.sync(True)
            finally:
                self._env.close()
                os.close(self._owner)  # releases the owner lock


def open_outbox(edge: EdgeConfig) -> Outbox:
    """The agent's outbox from its config: an LMDB spool under spool_dir/agent_id, or RAM when spool_dir is null."""
    if edge.spool_dir is None:
        return MemoryOutbox(edge.max_unacked_steps)
    return LmdbSpool(
        edge.spool_dir / edge.agent_id, edge.spool_max_mb << 20, edge.spool_full_policy, fsync=edge.spool_fsync
    )
