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

A full spool (the next step would pass `max_bytes`, itself at most what half the free disk holds)
follows its policy: `drop_oldest` deletes the oldest steps
to make room (counted); `pause` keeps every step and reports `accepting = False`, which the robot
loop obeys by holding still until acks free space. Steps set aside (`quarantine`) are not awaiting an
ack: they leave `count`, are moved back and tried again when the spool is next opened or when the sender
sees replay take their robot's steps again (`release_quarantined`: an operator may have let the token
write it meanwhile), and are the first to go when room is needed under either policy, so refused steps
never make the robots hold.
"""

from __future__ import annotations

import fcntl
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

from user.config import EdgeConfig
from user.log import kv
from user.v1 import replay_pb2, step_pb2

log = logging.getLogger(__name__)

FullPolicy = Literal["pause", "drop_oldest"]

SPOOL_STEPS = prometheus_client.Gauge("user_edge_spool_steps", "Steps in the outbox, waiting for replay's ack")
SPOOL_BYTES = prometheus_client.Gauge("user_edge_spool_bytes", "Serialized step bytes in the outbox")
SPOOL_DROPPED = prometheus_client.Counter(
    "user_edge_spool_dropped_total", "Oldest unacked steps dropped because the outbox was full"
)
SPOOL_QUARANTINED = prometheus_client.Gauge(
    "user_edge_spool_quarantined_steps",
    "Steps replay refused for this agent's identity, set aside in the spool until replay takes their robot's "
    "steps again or the spool is next opened",
)
SPOOL_FULL = prometheus_client.Gauge(
    "user_edge_spool_full", "1 while the outbox is at its cap (pause: robots hold; drop_oldest: dropping)"
)

_SYNC_EVERY_S = 1.0
_DROP_LOG_EVERY_S = 10.0
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

    def put(self, step: step_pb2.Step, table: str = "") -> int:
        req = replay_pb2.InsertRequest(step=step, table=table)
        size = req.step.ByteSize()
        with self._lock:
            seq = req.seq = self._next_seq
            self._next_seq += 1
            self._steps[seq] = req
            self._bytes += size
            while len(self._steps) > self.max_steps:
                _, old = self._steps.popitem(last=False)
                self._bytes -= old.step.ByteSize()
                self.dropped += 1
                SPOOL_DROPPED.inc()
        self._publish_metrics()
        return seq

    def read(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
        with self._lock:
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
        with self._lock:
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


def _key(seq: int) -> bytes:
    return seq.to_bytes(8, "big")


class SpoolInUse(RuntimeError):
    """Another live process owns this spool (two agents with one agent_id on one machine)."""


class LmdbSpool(Outbox):
    """Steps in a local LMDB environment at `path` until acked; see the module docstring."""

    def __init__(self, path: str | Path, max_bytes: int, policy: FullPolicy = "pause", fsync: bool = False) -> None:
        if policy not in ("pause", "drop_oldest"):
            raise ValueError(f"spool full policy must be pause or drop_oldest, got {policy!r}")
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        # One owner at a time: two writers would hand out the same seqs. The kernel drops the lock when
        # its process dies, kill -9 included, so a restarted edge takes it over at once.
        self._owner = os.open(self.path / "owner.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self._owner, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._owner)
            raise SpoolInUse(f"spool {self.path} is used by another live process (same edge.agent_id?)") from None
        self.max_bytes = max_bytes
        self.policy = policy
        self._lock = threading.Lock()
        self._last_size = 0  # bytes of the newest step: "full" means the next one like it would not fit
        self._disk_error = False
        self._last_drop_log = -float("inf")
        self._env = lmdb.open(
            str(self.path), map_size=2 * max_bytes + _MAP_HEADROOM, max_dbs=4, sync=fsync, metasync=fsync
        )
        self._steps = self._env.open_db(b"steps")
        self._meta = self._env.open_db(b"meta")
        self._tables = self._env.open_db(b"tables")  # seq -> replay table, only for steps not in the default
        self._held = self._env.open_db(b"held")  # seq -> step replay refused for this identity (quarantine)
        self._held_count = self._held_bytes = 0
        restored, _ = self._restore_held()
        with self._env.begin() as txn:
            self._next_seq = self._meta_int(txn, b"next_seq", 1)
            self._bytes = self._meta_int(txn, b"bytes", 0)
            self.dropped = self._meta_int(txn, b"dropped", 0)
            self._count = txn.stat(self._steps)["entries"]
            last = txn.cursor(self._steps)
            if last.last():  # next_seq is committed with each put; this only guards a hand-edited file
                self._next_seq = max(self._next_seq, int.from_bytes(last.key(), "big") + 1)
        self._closed = threading.Event()
        self._syncer: threading.Thread | None = None
        if not fsync:
            self._syncer = threading.Thread(target=self._sync_loop, name="spool-sync", daemon=True)
            self._syncer.start()
        # LMDB needs free pages even to delete (copy-on-write): the cap leaves half the free disk spare,
        # so a full spool is reached, and drained by acks, before the disk is.
        room = self._bytes + shutil.disk_usage(self.path).free // 2
        if room < max_bytes:
            self.max_bytes = room
            log.warning(
                "spool cap lowered to half the free disk",
                extra=kv(path=str(self.path), asked_bytes=max_bytes, max_bytes=room),
            )
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

    def put(self, step: step_pb2.Step, table: str = "") -> int:
        data = step.SerializeToString()
        with self._lock:
            was_full = self.full
            seq = self._next_seq
            try:
                dropped = self._write(seq, data, table)
                self._disk_error = False
            except lmdb.Error as exc:  # the disk filled before the cap
                dropped = self._disk_full(seq, data, table, exc)
            self._next_seq += 1
            self._last_size = len(data)
        if self.policy == "pause" and self.full and not was_full:
            log.warning(
                "spool full; robots hold until replay acknowledges steps",
                extra=kv(path=str(self.path), steps=self._count, bytes=self._bytes),
            )
        if dropped:
            SPOOL_DROPPED.inc(dropped)
            now = time.monotonic()
            if now - self._last_drop_log >= _DROP_LOG_EVERY_S:  # at the cap every step drops one: log rarely
                self._last_drop_log = now
                log.warning("spool full; dropping the oldest steps", extra=kv(path=str(self.path), total=self.dropped))
        self._publish_metrics()
        return seq

    def _disk_full(self, seq: int, data: bytes, table: str, exc: lmdb.Error) -> int:
        """Caller holds the lock. The disk filled before the cap: the cap drops to the bytes held now.
        drop_oldest frees the oldest 1 % in a transaction of its own and retries; pause loses this one
        step (counted) and reports full, so the robots hold until acks free space."""
        if not self._disk_error:
            log.error("spool disk full; cap lowered to what it holds", extra=kv(path=str(self.path), error=str(exc)))
        self._disk_error = True
        self.max_bytes = max(1, self._bytes + self._held_bytes)
        freed = 0
        if self._held_count:  # refused steps go first, whatever the policy
            try:
                with self._env.begin(write=True) as txn:
                    held, _ = self._drop_held(txn, self._held_bytes)
                    txn.put(b"dropped", _key(self.dropped + held), db=self._meta)
                self._held_count = self._held_bytes = 0
                self.dropped += held
                freed += held
                return freed + self._write(seq, data, table)
            except lmdb.Error:
                pass
        if self.policy == "drop_oldest":
            try:
                freed += self._drop_oldest(max(1, self._count // 100))
                return freed + self._write(seq, data, table)
            except lmdb.Error:
                pass
        self.dropped += 1
        return freed + 1

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
        with self._env.begin(write=True) as txn:
            cursor, nbytes, dropped = txn.cursor(self._steps), self._bytes, 0
            while dropped < n and cursor.first():
                nbytes -= len(cursor.value())
                txn.delete(cursor.key(), db=self._tables)
                cursor.delete()
                dropped += 1
            txn.put(b"bytes", _key(nbytes), db=self._meta)
            txn.put(b"dropped", _key(self.dropped + dropped), db=self._meta)
        self._bytes, self._count = nbytes, self._count - dropped
        self.dropped += dropped
        return dropped

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
                    if self.policy == "drop_oldest":
                        cursor = txn.cursor(self._steps)
                        while count and nbytes + len(data) > self.max_bytes and cursor.first():
                            nbytes -= len(cursor.value())
                            txn.delete(cursor.key(), db=self._tables)
                            cursor.delete()
                            count, dropped = count - 1, dropped + 1
                    txn.put(_key(seq), data, db=self._steps)
                    if table:  # most steps go to the default table: nothing kept for them
                        txn.put(_key(seq), table.encode(), db=self._tables)
                    nbytes, count = nbytes + len(data), count + 1
                    txn.put(b"next_seq", _key(seq + 1), db=self._meta)
                    txn.put(b"bytes", _key(nbytes), db=self._meta)
                    txn.put(b"dropped", _key(self.dropped + dropped), db=self._meta)
                self._bytes, self._count = nbytes, count
                self._held_count, self._held_bytes = held, held_bytes
                self.dropped += dropped
                return dropped
            except lmdb.MapFullError:
                if attempt == 3:
                    raise
                # Page overhead outgrew the map before the byte cap: grow it (no transaction is open).
                size = self._env.info()["map_size"] * 2
                log.warning("spool map grown", extra=kv(path=str(self.path), map_size=size))
                self._env.set_mapsize(size)
        raise AssertionError("unreachable")

    def read(self, after_seq: int, limit: int) -> list[replay_pb2.InsertRequest]:
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
        n = 0
        with self._lock:
            try:
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
            except lmdb.Error as exc:  # a full disk: the steps stay and go again later (replay dedupes)
                log.warning("spool could not forget acked steps", extra=kv(path=str(self.path), error=str(exc)))
                return 0
            self._bytes, self._count = nbytes, self._count - n
        self._publish_metrics()
        return n

    def quarantine(self, seqs: Iterable[int]) -> int:
        n = 0
        with self._lock:
            try:
                with self._env.begin(write=True) as txn:
                    nbytes, moved = self._bytes, 0
                    for seq in seqs:
                        value = txn.pop(_key(seq), db=self._steps)
                        if value is not None:  # its `tables` entry stays: it goes to that table when retried
                            txn.put(_key(seq), value, db=self._held)
                            nbytes, moved, n = nbytes - len(value), moved + len(value), n + 1
                    if n:
                        txn.put(b"bytes", _key(nbytes), db=self._meta)
            except lmdb.Error as exc:  # a full disk: the steps stay and are refused again later
                log.warning("spool could not set steps aside", extra=kv(path=str(self.path), error=str(exc)))
                return 0
            self._bytes, self._count = nbytes, self._count - n
            self._held_count, self._held_bytes = self._held_count + n, self._held_bytes + moved
        self._publish_metrics()
        return n

    @property
    def quarantined(self) -> int:
        return self._held_count

    @property
    def count(self) -> int:
        return self._count

    @property
    def nbytes(self) -> int:
        return self._bytes

    @property
    def last_seq(self) -> int:
        return self._next_seq - 1

    @property
    def full(self) -> bool:  # steps set aside are not counted: they make room when needed (see _write)
        return self._bytes + self._last_size > self.max_bytes

    def _sync_loop(self) -> None:
        while not self._closed.wait(_SYNC_EVERY_S):
            try:
                self._env.sync(True)
            except lmdb.Error:
                return  # closed meanwhile

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        if self._syncer is not None:
            self._syncer.join()
        with self._lock:
            self._env.sync(True)
            self._env.close()
        os.close(self._owner)  # releases the owner lock


def open_outbox(edge: EdgeConfig) -> Outbox:
    """The agent's outbox from its config: an LMDB spool under spool_dir/agent_id, or RAM when spool_dir is null."""
    if edge.spool_dir is None:
        return MemoryOutbox(edge.max_unacked_steps)
    return LmdbSpool(
        edge.spool_dir / edge.agent_id, edge.spool_max_mb << 20, edge.spool_full_policy, fsync=edge.spool_fsync
    )
