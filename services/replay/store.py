"""The replay buffer: LMDB is the durable truth (disk.py), RAM holds what sampling needs.

- disk.StepDB: every step, acknowledged only after its transaction committed; idempotent keys.
- tables.Index: every sampleable transition's id, robot, table(s), scalars and priority.
- hot.HotGroup: the most recent transitions as contiguous columns (frames stored once as uint8);
  a sampled transition that has left the hot tier is read from LMDB (a miss).

Step t is sampleable once its next observation exists (step t+1's observation, or its own
final_observation when it ends the episode), in any arrival order. Capacity is by bytes: when the
stored steps exceed capacity_mb, whole episodes leave, oldest first (FIFO), from LMDB and RAM; one still being
written is never cut (see _evict_over_capacity).
"""

from __future__ import annotations

import fcntl
import logging
import os
import threading
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import prometheus_client

from services.replay.disk import (
    ENDS,
    INTERVENTION,
    ONLINE,
    SUCCESS,
    TERMINATED,
    TRUNCATED,
    DiskFullError,
    DiskWriteError,
    NotInOrder,
    ReplayError,
    ReplayFullError,
    StepDB,
    StoreClosedError,
    episode_prefix,
    flags_of,
    next_key,
    robot_of,
    split_key,
    step_key,
)
from services.replay.hot import HotGroup, Layout, decode_blobs, decode_image, frame_nbytes
from services.replay.rawstep import Span, StepSpans, Unexpected, step_spans
from services.replay.tables import INTERVENTIONS, Draw, EmptyBufferError, Index, Record
from user import owner_lock, wire
from user.config import ConfigError
from user.log import kv
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb
from user.wire import EncodedFrames, stack_frames

__all__ = [
    "BufferHeld",
    "DiskFullError",
    "DiskWriteError",
    "EmptyBufferError",
    "LayoutError",
    "ReplayError",
    "ReplayFullError",
    "ReplayStore",
    "StoreClosedError",
    "episode_prefix",
    "split_key",
]

log = logging.getLogger(__name__)
DEFAULT_HOT_MB = 256
MAX_OPEN_TAILS = 100_000
ENCODINGS = {"raw": 0, "jpeg": tpb.ENCODING_JPEG, "png": tpb.ENCODING_PNG}
MAX_GROUP_STEPS = 4096  # most steps the writer merges into one transaction
RAW_READ_MIN_BYTES = 4096  # observations this large are read from LMDB pages without protobuf (see _fill_mixed)
MAX_GROUP_BYTES = 16 << 20  # and most bytes: LMDB keeps a transaction's dirty pages in RAM until commit
COMMITS = prometheus_client.Histogram(
    "user_replay_group_commit_steps",
    "Steps per LMDB transaction after merging queued requests (group commit)",
    buckets=(1, 4, 16, 64, 256, 1024, 4096),
)
COMPACTIONS = prometheus_client.Counter(
    "user_replay_index_compactions_total", "Index compactions (evicted rows dropped, live rows renumbered)"
)
DISK_FULL = prometheus_client.Gauge(
    "user_replay_disk_full",
    "1 while commits fail because replay's disk is full (Insert ends RESOURCE_EXHAUSTED, Sample still works), else 0",
)
FAILED_COMMITS = prometheus_client.Counter(
    "user_replay_failed_commits_total",
    "Write transactions that did not commit (nothing of them stored or acknowledged), by reason",
    ["reason"],
)
OVER_CAPACITY = prometheus_client.Gauge(
    "user_replay_over_capacity",
    "1 while stored bytes exceed capacity_mb but nothing left may be evicted (episodes still being written, "
    "which are never cut, and the newest episode), else 0",
)
REFUSED_EVICTED = prometheus_client.Counter(
    "user_replay_evicted_episode_steps_refused_total",
    "Steps refused (acked as duplicates, not stored) because their episode was evicted: no headless part is kept",
)
MAX_EVICTED_REMEMBERED = 100_000  # evicted episodes whose late steps are refused (the oldest are forgotten)


class LayoutError(ReplayError):
    """Sampled transitions do not share one observation layout (robots with different specs)."""


HOLDER_FILE = "holder.lock"  # in the buffer's directory: flocked by the process writing it (service or import)


class BufferHeld(ReplayError):
    """Another live process (the replay service, an import) holds the buffer for writing."""

    def __init__(self, message: str, holder: str = "") -> None:
        super().__init__(message)
        self.holder = holder  # "the replay service (pid N)"


def hold_buffer(path: str | Path, holder: str) -> int:
    """Take the buffer at path for this process: an exclusive flock on path/holder.lock, which names `holder`
    and this pid. Returns its fd (keep it open while writing; release_buffer closes it). The kernel drops the
    lock when the process dies, however it dies, so a kill -9 leaves no stale holder. Raises BufferHeld,
    writing nothing, when another process (or another fd of this one) holds it."""
    Path(path).mkdir(parents=True, exist_ok=True)
    try:
        return owner_lock.take(Path(path) / HOLDER_FILE, f"{holder} (pid {os.getpid()})")
    except owner_lock.Held as held:
        holder = held.holder if not _attached_only(Path(path)) else ATTACHED_HOLDER
        raise BufferHeld(f"{path} is held by {holder}", holder) from None


def buffer_holder(path: str | Path) -> str | None:
    """Who holds the buffer at path now ("the replay service (pid N)"), or None; a probe that creates nothing."""
    return owner_lock.holder(Path(path) / HOLDER_FILE)


def release_buffer(fd: int) -> None:
    os.close(fd)  # closing the fd drops its flock


ATTACHED_HOLDER = "a replay that attached it read-only (replay.attach): stop that one first"


def _attached_only(path: Path) -> bool:
    """Whether the buffer's holders hold it shared (attach) only: then holder.lock still names its last owner."""
    try:
        fd = os.open(path / HOLDER_FILE, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    finally:
        os.close(fd)
    return True


def _share_buffer(path: Path, setting: str) -> int | None:
    """A shared flock on path/holder.lock, kept while a store reads that buffer without LMDB's locks (attach): its
    owner's hold_buffer (LOCK_EX) fails meanwhile, so nothing writes it under the reader. Opening the file for
    reading creates nothing. None for a buffer without holder.lock (a copy): nothing to lock. Raises ConfigError
    naming `setting` and the holder while a live process holds the buffer."""
    try:
        fd = os.open(path / HOLDER_FILE, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 256, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise ConfigError(
            f"{setting}: {path} is held by {holder}, which may still write it; attach it once that process has "
            "stopped, or attach a copy"
        ) from None
    return fd


def tensor_array(tensor: tpb.Tensor) -> np.ndarray:
    """Stored tensors were validated on insert: RAW data is viewed as is, other encodings decoded."""
    if tensor.encoding == tpb.ENCODING_RAW:
        return np.frombuffer(tensor.data, dtype=wire.dtype_from_proto(tensor.dtype)).reshape(tuple(tensor.shape))
    if tensor.encoding in (tpb.ENCODING_JPEG, tpb.ENCODING_PNG):
        return decode_image(tensor)
    return wire.from_tensor(tensor)


def _np_dtype(code: int) -> np.dtype | None:
    """numpy dtype of a stored tensor's bytes; None for a code this build does not know."""
    try:
        return wire.dtype_from_proto(code)
    except wire.WireError:
        return None


def arrays_of(tmap: tpb.TensorMap) -> dict[str, np.ndarray]:
    return {name: tensor_array(t) for name, t in tmap.tensors.items()}


def layout_of(step: step_pb2.Step) -> Layout:
    features = tuple(
        (name, wire.dtype_from_proto(t.dtype), tuple(t.shape)) for name, t in sorted(step.observation.tensors.items())
    )
    return features, (wire.dtype_from_proto(step.action.dtype), tuple(step.action.shape))


@dataclass
class Episode:
    robot: str
    table: str
    steps: int = 0
    nbytes: int = 0
    success: bool = False
    interventions: int = 0
    top: int = -1  # highest step index stored
    last: int = -1  # index of the step that ended it, -1 while open


@dataclass(slots=True)
class _Pending:
    """A put_steps request waiting for the writer."""

    steps: list[step_pb2.Step]
    tables: list[str]
    specs: list[robot_pb2.RobotSpec]
    raws: list[bytes]
    future: Future[tuple[int, int]]
    nbytes: int = 0
    keys: list[bytes] = field(default_factory=list)
    scalars: list[tuple[float, int, int, int]] = field(default_factory=list)  # reward, flags, version, bytes
    refused: int = 0  # steps of evicted episodes taken out before the commit (answered as duplicates)


@dataclass(slots=True)
class _Tail:
    """A stored step waiting for its successor's observation."""

    group: int
    seq: int  # its observation's frame
    action: np.ndarray | None  # None while the hot tier is off
    reward: float
    terminated: bool
    truncated: bool
    intervention: bool
    policy_version: int
    final_seq: int = -1


@dataclass(slots=True)
class _Columns:
    """Transitions completed from waiting steps, gathered before the group's own (see _transitions_columns)."""

    keys: list[bytes] = field(default_factory=list)
    robot: list[int] = field(default_factory=list)
    tables: list[str] = field(default_factory=list)
    flags: list[int] = field(default_factory=list)
    reward: list[float] = field(default_factory=list)
    version: list[int] = field(default_factory=list)
    group: list[int] = field(default_factory=list)
    obs: list[int] = field(default_factory=list)
    nxt: list[int] = field(default_factory=list)
    action: list[np.ndarray | None] = field(default_factory=list)


IMAGE_ENC = (tpb.ENCODING_JPEG, tpb.ENCODING_PNG)


def _episodes_contiguous(keys: list[bytes]) -> bool:
    """Whether each episode's keys form one run (a stream of one robot's steps): no sort needed then."""
    prefixes = [k[:-8] for k in keys]
    runs = 1 + sum(map(bytes.__ne__, prefixes[1:], prefixes[:-1]))
    return runs == len(set(prefixes))


def _stack(parts: list[Any]) -> Any:
    """Frame stacking of one feature: arrays, or encoded frames (decoded if only some parts kept their bytes)."""
    if all(isinstance(p, EncodedFrames) for p in parts) and len({(p.encoding, p.image_shape) for p in parts}) == 1:
        return stack_frames(parts)
    return np.stack([p.decoded() if isinstance(p, EncodedFrames) else p for p in parts], axis=1)


def _kept_frames(
    hot: HotGroup | None,
    name: str,
    shape: tuple[int, ...],
    at: np.ndarray | None,
    ok: np.ndarray,
    cold: np.ndarray,
    tensors: list[tpb.Tensor],
) -> Any:
    """One encoded feature's frames for a batch: the hot draws' (`ok`) bytes from ring rows `at`, the cold draws'
    from their stored tensors; as kept when all share one image encoding, else decoded."""
    n = len(ok)
    blobs, encs = np.empty(n, object), np.empty(n, np.uint8)
    if hot is not None and at is not None:
        blobs[ok], encs[ok] = hot.blobs[name][at], hot.blob_enc[name][at]
    for i, t in zip(cold.tolist(), tensors, strict=True):
        if t.dtype != tpb.DTYPE_UINT8 or tuple(t.shape) != shape:
            raise ValueError(f"{name}: dtype or shape differs from the batch's layout")
        blobs[i], encs[i] = t.data, t.encoding
    enc = int(encs[0])
    if enc != tpb.ENCODING_RAW and (encs == enc).all():
        return EncodedFrames(blobs, enc, shape)
    return decode_blobs(blobs, encs, shape)


def _stack_actions(parts: list[tuple[list[int], np.ndarray | None]], n: int) -> np.ndarray | None:
    """Per-robot action arrays as one array in step order; None when a robot has none or layouts differ."""
    if any(acts is None for _, acts in parts):
        return None
    if len(parts) == 1:
        return parts[0][1]
    first = parts[0][1]
    if any(a.dtype != first.dtype or a.shape[1:] != first.shape[1:] for _, a in parts):  # type: ignore[union-attr]
        return None
    out = np.empty((n, *first.shape[1:]), first.dtype)  # type: ignore[union-attr]
    for idx, acts in parts:
        out[idx] = acts
    return out


def _rows(actions: list[np.ndarray | None], like: np.ndarray) -> np.ndarray:
    """Waiting steps' actions as rows shaped like `like` (zeros where a step has none: not hot anyway)."""
    out = np.zeros((len(actions), *like.shape[1:]), like.dtype)
    for i, a in enumerate(actions):
        if a is not None and a.shape == like.shape[1:]:
            out[i] = a
    return out


def _step_text(step: step_pb2.Step) -> str:
    return f"step {step.step_index} of robot {step.robot_id!r} episode {step.episode_id!r}"


def _layout_difference(got: Layout, expected: Layout, reference: str) -> str:
    """What a step has that differs from the reference layout: "feature 'x' int64 (64,), <reference> uint8 (64,)"."""
    have = {name: (dtype, shape) for name, dtype, shape in got[0]}
    want = {name: (dtype, shape) for name, dtype, shape in expected[0]}
    parts = [
        f"feature {name!r} {_dtype_shape(have.get(name))}, {reference} {_dtype_shape(want.get(name))}"
        for name in sorted(want.keys() | have.keys())
        if want.get(name) != have.get(name)
    ]
    if expected[1] != got[1]:
        parts.append(f"action {_dtype_shape(got[1])}, {reference} {_dtype_shape(expected[1])}")
    return "; ".join(parts)


def _dtype_shape(item: tuple[np.dtype, tuple[int, ...]] | None) -> str:
    return "missing" if item is None else f"{item[0]} {item[1]}"


def _stats_rows(out: dict[str, dict[str, Any]], table: str, robot: str) -> tuple[dict[str, Any], ...]:
    """table_stats' total row of a table and its robot's row, made at first use."""
    total = out.setdefault(table, {**_zero_stats(), "robots": {}})
    return total, total["robots"].setdefault(robot, _zero_stats())


def _zero_stats() -> dict[str, Any]:
    return {"transitions": 0, "steps": 0, "episodes": 0, "bytes": 0, "successes": 0}


def _count_episode(out: dict[str, dict[str, Any]], table: str, ep: Episode, steps: int, nbytes: int) -> None:
    for target in _stats_rows(out, table, ep.robot):
        target["steps"] += steps
        target["episodes"] += 1
        target["bytes"] += nbytes
        target["successes"] += ep.success


def _complete(ep: Episode) -> bool:
    """Its last step and every step below it are stored."""
    return ep.last >= 0 and ep.steps == ep.last + 1


class ReplayStore:
    """Thread-safe: one writer at a time (put_steps), samples and stats from any thread."""

    def __init__(
        self,
        path: str | Path,
        map_size_mb: int = 4096,
        cache_mb: int = DEFAULT_HOT_MB,
        *,
        max_map_mb: int | None = None,
        capacity_mb: int = 0,
        durability: str = "fsync",
        readonly: bool = False,
        image_encoding: dict[str, str] | None = None,
        decoded_mb: int = 0,
        cache_prefault: bool = False,
    ) -> None:
        self.path = Path(path)
        self.cache_prefault = cache_prefault  # hot groups touch their columns' pages when made
        self.decoded_bytes = int(decoded_mb) << 20  # per hot group: newest JPEG/PNG frames kept decoded
        # observation feature -> how its uint8 images are stored in LMDB ("raw", "jpeg", "png"); "*" = every camera
        self.image_encoding = {k: ENCODINGS[v] for k, v in (image_encoding or {}).items() if ENCODINGS[v]}
        self.capacity_bytes = int(capacity_mb) << 20  # 0 = no limit but the map
        # the hot tier never needs more rows than are stored: with a capacity, at most twice its bytes (a hot row
        # is about a stored step's size or less), so a small bounded buffer does not fill a 256 MB ring of
        # evicted transitions
        self.hot_bytes = int(cache_mb) << 20
        if self.capacity_bytes:
            self.hot_bytes = min(self.hot_bytes, 2 * self.capacity_bytes)
        self._write_lock = threading.Lock()  # one writer; also guards close()
        self._queue: deque[_Pending] = deque()
        self._queue_cond = threading.Condition()
        self._writer: threading.Thread | None = None
        self._closing = False
        self.disk_full = False  # the last commit failed for want of space (the writer thread sets it)
        self._failing: type[Exception] | None = None  # the kind of error failing commits now: logged once per run
        self._lock = threading.RLock()  # index, hot tier, LMDB read transactions vs map growth
        self.db = StepDB(
            path,
            map_size_mb,
            max_map_mb=max_map_mb if max_map_mb is not None else max(map_size_mb, 4 * capacity_mb),
            durability=durability,
            readonly=readonly,
            guard=self._lock,
        )
        self.index = Index()
        self._groups: list[HotGroup] = []
        self._layout_ids: dict[Layout, int] = {}
        self._robot_group: dict[str, int] = {}
        self._tails: dict[bytes, _Tail] = {}
        self._episodes: dict[bytes, Episode] = {}
        self._attached: list[StepDB] = []
        self._attached_episodes: dict[str, dict[bytes, Episode]] = {}
        self._n_steps = 0
        self._steps_per_robot: dict[str, int] = {}
        self._bytes = 0
        self._evicted_episodes = 0
        self._evicted_steps_per_robot: dict[str, int] = {}  # since open: stored + evicted = everything acked
        self._evicted: dict[bytes, bool] = {}  # evicted episode prefix -> its refusal was logged (_refuse_evicted)
        self._over_capacity = False  # above capacity_mb with nothing evictable left (warned once)
        self._attached_holds: list[int] = []  # shared flocks on attached buffers' holder.lock (see attach)
        self.compactions = 0  # index compactions (dropping evicted rows)
        self.hits = self.misses = 0
        self.generation = 0  # bumps when a commit or an eviction changes what can be sampled
        self.inserted = 0  # steps stored by this process (the rate limiter's insert count)
        self._closed = False
        try:
            self._rebuild()
            if not readonly:
                self._warm()
                DISK_FULL.set(0)
        except BaseException:
            self.db.close()
            raise
        log.info(
            "replay store open",
            extra=kv(
                path=str(self.path), steps=self._n_steps, transitions=len(self.index), episodes=len(self._episodes)
            ),
        )

    # ------------------------------------------------------------------ open

    def _rebuild(self) -> None:
        """Index every sampleable transition from the scalars table, in arrival order."""
        self._episodes = self._scan(self.db, b"", None, count=True)

    def _scan(self, db: StepDB, mark: bytes, table: str | None, count: bool = False) -> dict[bytes, Episode]:
        """Episodes and sampleable transitions of `db` into the index; keys get `mark` in front (attached dbs)."""
        tables = db.episode_tables()
        episodes: dict[bytes, Episode] = {}
        found: list[tuple[int, bytes, tuple[float, int, int, int, int]]] = []
        firsts: dict[bytes, int] = {}
        prev: tuple[bytes, int, tuple[float, int, int, int, int]] | None = None
        for key, sc in db.scan():
            prefix, t = split_key(key)
            ep = episodes.get(prefix)
            if ep is None:
                ep = episodes[prefix] = Episode(robot_of(prefix), table or tables.get(prefix, ONLINE))
                firsts[prefix] = sc[3]
            firsts[prefix] = min(firsts[prefix], sc[3])
            ep.steps += 1
            ep.top = max(ep.top, t)
            if sc[1] & ENDS:
                ep.last = t
            ep.nbytes += sc[4] + len(key)
            ep.success |= bool(sc[1] & SUCCESS)
            ep.interventions += bool(sc[1] & INTERVENTION)
            if count:
                self._n_steps += 1
                self._steps_per_robot[ep.robot] = self._steps_per_robot.get(ep.robot, 0) + 1
                self._bytes += sc[4] + len(key)
            if prev is not None and prev[0][:-8] == prefix and prev[1] == t - 1 and not prev[2][1] & ENDS:
                found.append((max(prev[2][3], sc[3]), prev[0], prev[2]))
            if sc[1] & ENDS:
                found.append((sc[3], key, sc))
            prev = (key, t, sc)
            db.arrival = max(db.arrival, sc[3] + 1)
        episodes = dict(sorted(episodes.items(), key=lambda kv_: firsts[kv_[0]]))
        records = []
        for _, key, sc in sorted(found):
            ep = episodes[key[:-8]]
            flags = sc[1]
            records.append(
                Record(
                    mark + key,
                    self.index.code(ep.robot),
                    ep.table,
                    sc[0],
                    bool(flags & TERMINATED),
                    bool(flags & TRUNCATED),
                    bool(flags & INTERVENTION),
                    sc[2],
                )
            )
        self.index.add_many(records)  # (rows of each episode: the index keeps them)
        return episodes

    def _warm(self) -> None:
        """After a restart, read the newest transitions back into the hot tier (what online RL samples most)."""
        n = self.index.n_rows
        if self.hot_bytes <= 0 or n == 0:
            return
        newest = self._read([self.index.key(n - 1)])[0]
        gid = self._robot_group[newest.robot_id] = self._group(layout_of(newest), newest)
        group = self._groups[gid]
        first = max(0, n - int(group.capacity * 0.85))
        warmed = 0
        for start in range(first, n, 1024):
            tids = [t for t in range(start, min(n, start + 1024)) if self.index.alive.a[t]]
            keys = self.index.keys_of(tids)
            steps = dict(zip(keys, self._read(keys), strict=True))
            missing = [next_key(k) for k, s in steps.items() if not s.HasField("final_observation")]
            missing = [k for k in missing if k not in steps]
            steps.update(zip(missing, self._read(missing), strict=True))
            seq_of: dict[bytes, int] = {}
            for key in keys:  # observations once; a transition's next is its successor's observation
                step = steps[key]
                if layout_of(step) == group.layout:
                    seq_of[key] = group.write_tensors(step.observation)
            rows_tids, obs_seqs, next_seqs, actions = [], [], [], []
            for tid, key in zip(tids, keys, strict=True):
                if key not in seq_of:
                    continue
                step = steps[key]
                nxt_seq = seq_of.get(next_key(key))
                if nxt_seq is None:
                    final = step.HasField("final_observation")
                    nxt = step.final_observation if final else steps[next_key(key)].observation
                    try:
                        nxt_seq = group.write_tensors(nxt)
                    except (ValueError, KeyError):  # a successor of another layout
                        continue
                rows_tids.append(tid)
                obs_seqs.append(seq_of[key])
                next_seqs.append(nxt_seq)
                actions.append(tensor_array(step.action))
            if rows_tids:
                rows = group.add_many(rows_tids, obs_seqs, next_seqs, actions)
                self.index.hot_row.a[rows_tids] = rows
                self.index.group.a[rows_tids] = gid
                warmed += len(rows_tids)
        log.info("hot tier warmed from LMDB", extra=kv(path=str(self.path), transitions=warmed))

    def attach(self, path: str | Path, table: str) -> int:
        """Open another buffer read-only and sample its transitions as `table`; returns how many.

        Its steps are read from its own LMDB on demand: never copied, never evicted, never written, and nothing is
        created in its directory (LMDB opens without its lock file, lock=False). Without LMDB's locks a reader is
        safe only while no process writes, so a buffer held by its owner (a replay service, `userctl replay
        import`) is refused (ConfigError naming replay.attach.<table> and the holder), and until this store closes
        it keeps a shared flock on the buffer's holder.lock, so the owner refuses to start on it meanwhile. A copy
        without holder.lock cannot be guarded so: do not write it while it is attached.
        """
        if table in self.index.tables:
            raise ValueError(f"table {table!r} exists already; attach under a new name")
        if len(self._attached) >= 250:
            raise ValueError("at most 250 attached buffers")
        path, setting = Path(path), f"replay.attach.{table}"
        if not (path / "data.mdb").is_file():
            raise ConfigError(f"{setting}: {path} holds no replay buffer (no data.mdb)")
        hold = _share_buffer(path, setting)
        try:
            db = StepDB(path, readonly=True, lock=False)
        except BaseException:
            if hold is not None:
                os.close(hold)
            raise
        with self._lock:
            source = len(self._attached) + 1
            self._attached.append(db)
            if hold is not None:
                self._attached_holds.append(hold)
            self._attached_episodes[table] = self._scan(db, bytes([0, source]), table)
            self.generation += 1
            n = self.index.count(table)
        log.info("attached a buffer read-only", extra=kv(path=str(path), table=table, transitions=n))
        return n

    def _get_many(self, keys: list[bytes]) -> list[bytes | None]:
        """Values of index keys: own ones from this LMDB, marked ones (b"\\0" + source) from an attached one."""
        if not self._attached:
            return self.db.get_many(keys)
        out: list[bytes | None] = [None] * len(keys)
        by_source: dict[int, list[int]] = {}
        for i, k in enumerate(keys):
            by_source.setdefault(k[1] if k[:1] == b"\0" else 0, []).append(i)
        for source, where in by_source.items():
            db = self.db if source == 0 else self._attached[source - 1]
            strip = 0 if source == 0 else 2
            for i, raw in zip(where, db.get_many([keys[i][strip:] for i in where]), strict=True):
                out[i] = raw
        return out

    # ------------------------------------------------------------------ writes

    def _check_open(self) -> None:
        if self._closed:
            raise StoreClosedError(f"replay store {self.path} is closed")

    def _group(self, layout: Layout, step: step_pb2.Step) -> int:
        """The hot group of a layout, made at its first step. With a capacity, its ring holds at most the rows
        that capacity could store of steps like this one (+25%): the rest would be rows of evicted transitions
        (a 104-byte state row vs ~230 stored bytes a step: 2x capacity_mb of rows alone is 4x too many)."""
        gid = self._layout_ids.get(layout)
        if gid is None:
            gid = self._layout_ids[layout] = len(self._groups)
            max_rows = None
            if self.capacity_bytes:
                max_rows = int(self.capacity_bytes * 1.25 // max(1, step.ByteSize() + len(step.robot_id) + 32))
            encoded = self._encoded_features(layout, step)
            group = HotGroup(layout, self.hot_bytes, encoded, max_rows, self.decoded_bytes)
            if self.cache_prefault:
                group.prefault()
            self._groups.append(group)
        return gid

    def _encoded_features(self, layout: Layout, step: step_pb2.Step) -> frozenset[str]:
        """Camera features LMDB keeps as JPEG/PNG: those of replay.image_encoding and those the edge sends encoded
        (stored as sent). The hot tier keeps their bytes too and the sampler decodes them."""
        tensors = step.observation.tensors
        out = set()
        for name, dtype, shape in layout[0]:
            enc = self.image_encoding.get(name, self.image_encoding.get("*") if name.startswith("camera.") else 0)
            enc = enc or (name in tensors and tensors[name].encoding in (tpb.ENCODING_JPEG, tpb.ENCODING_PNG))
            if enc and dtype == np.uint8 and wire.is_image_shape(shape):
                out.add(name)
        return frozenset(out)

    def put_steps(
        self,
        steps: list[step_pb2.Step],
        specs: Iterable[robot_pb2.RobotSpec] = (),
        table: str | list[str] = ONLINE,
    ) -> tuple[int, int]:
        """Store validated steps (and specs); (stored, duplicates) once committed and sampleable."""
        return self.submit(steps, specs, table).result()

    def submit(
        self,
        steps: list[step_pb2.Step],
        specs: Iterable[robot_pb2.RobotSpec] = (),
        table: str | list[str] = ONLINE,
    ) -> Future[tuple[int, int]]:
        """Queue steps for the writer; the future resolves once they are committed and indexed. Cancelling
        the future before the writer takes it withdraws the steps (nothing of them is written).

        Group commit: the writer merges everything queued (from every stream) into one transaction,
        so one fsync covers many requests, and callers serialize the next steps while it syncs.
        """
        tables = [table] * len(steps) if isinstance(table, str) else list(table)
        if self.image_encoding:
            steps = [self._stored_form(s) for s in steps]  # the hot tier keeps encoded frames as stored
        raws = [s.SerializeToString() for s in steps]
        # keys and scalars here, in the caller's thread, while the writer may be waiting for an fsync
        keys = [step_key(s.robot_id, s.episode_id, s.step_index) for s in steps]
        scalars = [
            (s.reward, flags_of(s) | (ENDS if s.HasField("final_observation") else 0), s.policy_version, len(raw))
            for s, raw in zip(steps, raws, strict=True)
        ]
        item = _Pending(steps, tables, list(specs), raws, Future(), sum(map(len, raws)), keys, scalars)
        with self._queue_cond:
            if self._closing:
                raise StoreClosedError(f"replay store {self.path} is closed")
            self._queue.append(item)
            if self._writer is None:
                self._writer = threading.Thread(target=self._write_loop, name="replay-writer", daemon=True)
                self._writer.start()
            self._queue_cond.notify()
        return item.future

    def _stored_form(self, step: step_pb2.Step) -> step_pb2.Step:
        """The step as LMDB keeps it: camera frames JPEG/PNG-encoded where configured (the hot tier keeps raw)."""
        if not self.image_encoding:
            return step
        out: step_pb2.Step | None = None
        for part in ("observation", "final_observation"):
            if part == "final_observation" and not step.HasField(part):
                continue
            for name, tensor in getattr(step, part).tensors.items():
                enc = self.image_encoding.get(name, self.image_encoding.get("*") if name.startswith("camera.") else 0)
                if not enc or tensor.encoding != tpb.ENCODING_RAW or tensor.dtype != tpb.DTYPE_UINT8:
                    continue
                if len(tensor.shape) not in (2, 3) or (len(tensor.shape) == 3 and tensor.shape[2] not in (1, 3)):
                    continue
                if out is None:
                    out = step_pb2.Step()
                    out.CopyFrom(step)
                getattr(out, part).tensors[name].CopyFrom(wire.to_tensor(tensor_array(tensor), enc))
        return out if out is not None else step

    def _write_loop(self) -> None:
        while True:
            with self._queue_cond:
                while not self._queue and not self._closing:
                    self._queue_cond.wait()
                if not self._queue:
                    return
                group, n, size = [], 0, 0
                while self._queue and (
                    not group
                    or (
                        n + len(self._queue[0].steps) <= MAX_GROUP_STEPS
                        and size + self._queue[0].nbytes <= MAX_GROUP_BYTES
                    )
                ):
                    item = self._queue.popleft()
                    if not item.future.set_running_or_notify_cancel():  # its stream ended on a failed commit
                        continue
                    group.append(item)
                    n += len(item.steps)
                    size += item.nbytes
            if group:
                self._write(group)

    def _write(self, group: list[_Pending]) -> None:
        """Commit a group; a failure fails its requests (nothing of them stored) and the writer goes on."""
        try:
            self._commit_group(group)
        except (DiskFullError, DiskWriteError) as exc:  # the disk, not a request: each alone would fail alike
            self._failed(group, exc)
        except ReplayError as exc:  # e.g. the map is full: attribute the failure, commit each request alone
            self._count_failure(exc)
            for item in group:
                try:
                    self._commit_group([item])
                except Exception as exc:
                    self._failed([item], exc)
        except Exception as exc:
            self._failed(group, exc)

    def _failed(self, group: list[_Pending], exc: Exception) -> None:
        self._count_failure(exc)
        for item in group:
            if not item.future.done():
                item.future.set_exception(exc)

    def _count_failure(self, exc: Exception) -> None:
        """Count a transaction that did not commit; warn once per run of failures of one kind (every retry
        of every edge fails alike until space returns)."""
        reasons = {DiskFullError: "disk_full", DiskWriteError: "io_error", ReplayFullError: "map_full"}
        FAILED_COMMITS.labels(reasons.get(type(exc), "error")).inc()
        if type(exc) is not self._failing:
            self._failing = type(exc)
            if isinstance(exc, DiskFullError):
                log.warning(
                    "replay's disk is full: commits fail and Insert streams end RESOURCE_EXHAUSTED until space "
                    "returns (edges keep unacknowledged steps and re-send them); health stays SERVING, Sample works",
                    extra=kv(path=str(self.path), error=str(exc)),
                )
            else:
                log.warning("replay commits fail", extra=kv(path=str(self.path), error=repr(exc)))
        if isinstance(exc, DiskFullError) and not self.disk_full:
            self.disk_full = True
            DISK_FULL.set(1)

    def _committed(self) -> None:
        """A commit succeeded: a run of failures (a full disk) is over."""
        if self._failing is None:
            return
        log.info("replay commits succeed again", extra=kv(path=str(self.path), was=self._failing.__name__))
        self._failing = None
        if self.disk_full:
            self.disk_full = False
            DISK_FULL.set(0)

    def _in_order(self, keys: list[bytes], scalars: list[tuple[float, int, int, int]]) -> bool:
        """Every step is its episode's next index after what is stored (so new, its predecessor waiting,
        its successor not stored): the usual stream, written and indexed without lookups (writer thread)."""
        running: dict[bytes, int] = {}
        closed = 1 << 62
        for key, sc in zip(keys, scalars, strict=True):
            prefix = key[:-8]
            top = running.get(prefix)
            if top is None:
                ep = self._episodes.get(prefix)
                top = -1 if ep is None else (ep.top if ep.last < 0 else closed)
            t = int.from_bytes(key[-8:], "big")
            if t != top + 1:
                return False
            running[prefix] = closed if sc[1] & ENDS else t
        return True

    def _commit_in_order(self, group: list[_Pending]) -> bool:
        """The fast path of _commit_group; False (nothing written) when the group is not in order."""
        keys = [k for item in group for k in item.keys]
        scalars = [sc for item in group for sc in item.scalars]
        if not self._in_order(keys, scalars):
            return False
        tables = [t for item in group for t in item.tables]
        raws = [r for item in group for r in item.raws]
        steps = [s for item in group for s in item.steps]
        # An episode's steps next to each other, ascending: indexing completes a step's transition with its
        # successor in the same group only when that is its neighbour. Interleaved robots (an edge streams its
        # robots' steps in turn) left most steps waiting as tails (up to MAX_OPEN_TAILS, ~40 MB) that were
        # then completed from LMDB, outside the hot tier.
        if not _episodes_contiguous(keys):  # (in order: each episode's steps already ascend)
            order = sorted(range(len(keys)), key=lambda i: (keys[i][:-8], keys[i][-8:]))
            keys, scalars = [keys[i] for i in order], [scalars[i] for i in order]
            tables, raws, steps = [tables[i] for i in order], [raws[i] for i in order], [steps[i] for i in order]
        episode_tables = {k[:-8]: t for k, t in zip(keys, tables, strict=True) if t != ONLINE}
        try:
            self.db.put_in_order(keys, raws, scalars, episode_tables, [spec for item in group for spec in item.specs])
        except NotInOrder:
            return False
        self._committed()
        with self._lock:  # committed: only now may samples see these steps
            self._index_in_order(steps, keys, scalars, tables)
            self.inserted += len(keys)
            self.generation += 1
        self._evict_over_capacity()
        COMMITS.observe(len(keys))
        for item in group:
            item.future.set_result((len(item.steps), item.refused))
        return True

    def _commit_group(self, group: list[_Pending]) -> None:
        with self._write_lock:
            if self._evicted and self._refuse_evicted(group):
                return  # every step was of an evicted episode
            if self._commit_in_order(group):
                return
            steps = [s for item in group for s in item.steps]
            done = self.db.put_steps(
                steps,
                [t for item in group for t in item.tables],
                [spec for item in group for spec in item.specs],
                [r for item in group for r in item.raws],
                self._tails,  # stored steps still waiting for their successor (this thread alone changes it)
            )
            self._committed()
            # Committed: only now may samples see these steps.
            with self._lock:
                self._index_committed(done.stored, done.sampleable)
                self.inserted += len(done.stored)
                self.generation += bool(done.stored)
            self._evict_over_capacity()
        COMMITS.observe(len(steps))
        at = 0
        for item in group:
            stored = sum(done.stored_mask[at : at + len(item.steps)])
            item.future.set_result((stored, len(item.steps) - stored + item.refused))
            at += len(item.steps)

    def _index_committed(self, stored: list[tuple[bytes, step_pb2.Step, int, str]], sampleable: list[bytes]) -> None:
        for key, step, nbytes, table in stored:
            prefix = key[:-8]
            ep = self._episodes.get(prefix)
            if ep is None:
                ep = self._episodes[prefix] = Episode(step.robot_id, table)
            ep.steps += 1
            ep.top = max(ep.top, step.step_index)
            if step.HasField("final_observation"):
                ep.last = step.step_index
            ep.nbytes += nbytes + len(key)
            ep.success |= step.success
            ep.interventions += step.intervention
            self._n_steps += 1
            self._steps_per_robot[ep.robot] = self._steps_per_robot.get(ep.robot, 0) + 1
            self._bytes += nbytes + len(key)
        if self.hot_bytes > 0:
            self._tails_many([(key, step) for key, step, _, _ in stored])
        hot: dict[int, list[tuple[int, int, int, np.ndarray]]] = {}  # group -> (record, obs seq, next seq, action)
        records: list[Record] = []
        for key in sampleable:
            tail = self._tails.get(key)
            nxt = None if tail is None or tail.final_seq >= 0 else self._tails.get(next_key(key))
            ep = self._episodes[key[:-8]]
            code = self.index.code(ep.robot)
            if tail is not None and (tail.final_seq >= 0 or (nxt is not None and nxt.group == tail.group)):
                next_seq = tail.final_seq if tail.final_seq >= 0 else nxt.seq  # type: ignore[union-attr]
                hot.setdefault(tail.group, []).append((len(records), tail.seq, next_seq, tail.action))
                records.append(
                    Record(
                        key,
                        code,
                        ep.table,
                        tail.reward,
                        tail.terminated,
                        tail.truncated,
                        tail.intervention,
                        tail.policy_version,
                        tail.group,
                    )
                )
            else:  # completed out of order or after a restart: its data stays in LMDB
                step = self._read([key])[0]
                records.append(
                    Record(
                        key,
                        code,
                        ep.table,
                        step.reward,
                        step.terminated,
                        step.truncated,
                        step.intervention,
                        step.policy_version,
                    )
                )
        first = self.index.n_rows
        for gid, items in hot.items():
            rows = self._groups[gid].add_many(
                [first + i for i, _, _, _ in items],
                [o for _, o, _, _ in items],
                [x for _, _, x, _ in items],
                [a for _, _, _, a in items],
            )
            for (i, _, _, _), row in zip(items, rows.tolist(), strict=True):
                records[i].hot_row = row
        self.index.add_many(records)
        for key in sampleable:  # their transitions are indexed; a successor finds its frame in the ring
            self._tails.pop(key, None)

    def _index_in_order(
        self,
        steps: list[step_pb2.Step],
        keys: list[bytes],
        scalars: list[tuple[float, int, int, int]],
        tables: list[str],
    ) -> None:
        """Index a committed in-order group: episode counts, frames into the hot tier per robot in one copy,
        then the transitions it completes (each step completes its predecessor's; a last step its own)."""
        robots = self._count_in_order(steps, keys, scalars, tables)
        n = len(steps)
        gids, seqs, finals = np.full(n, -1, np.int64), np.full(n, -1, np.int64), np.full(n, -1, np.int64)
        actions: list[np.ndarray | None] = [None] * n
        full: np.ndarray | None = None  # every step's action in one array, when they share a layout
        if self.hot_bytes > 0:
            by_robot: dict[str, list[int]] = {}
            for i, robot in enumerate(robots):
                by_robot.setdefault(robot, []).append(i)
            parts = [(idx, self._frames_in_order(r, idx, steps, scalars, gids, seqs, finals, actions))
                     for r, idx in by_robot.items()]  # fmt: skip
            full = _stack_actions(parts, n)
            if full is None:
                for idx, acts in parts:
                    if acts is not None:
                        for j, i in enumerate(idx):
                            actions[i] = acts[j]
                self._transitions_in_order(
                    keys, scalars, robots, gids.tolist(), seqs.tolist(), finals.tolist(), actions
                )
                return
        self._transitions_columns(keys, scalars, robots, gids, seqs, finals, full)

    def _transitions_columns(
        self,
        keys: list[bytes],
        scalars: list[tuple[float, int, int, int]],
        robots: list[str],
        gids: np.ndarray,
        seqs: np.ndarray,
        finals: np.ndarray,
        full: np.ndarray | None,
    ) -> None:
        """_transitions_in_order as numpy columns: step j's transition is complete when j ends its episode
        or j+1 is its successor in this group; an episode's first step here completes a waiting one."""
        n = len(keys)
        prefixes = [k[:-8] for k in keys]
        t = np.fromiter((int.from_bytes(k[-8:], "big") for k in keys), np.int64, n)
        flags = np.fromiter((sc[1] for sc in scalars), np.int64, n)
        reward = np.fromiter((sc[0] for sc in scalars), np.float32, n)
        version = np.fromiter((sc[2] for sc in scalars), np.int64, n)
        same_next = np.zeros(n, np.bool_)
        if n > 1:
            same_next[:-1] = np.fromiter(map(bytes.__eq__, prefixes[1:], prefixes[:-1]), np.bool_, n - 1)
        ends = (flags & ENDS) != 0
        first = np.ones(n, np.bool_)
        first[1:] = ~same_next[:-1]
        cols = _Columns()
        for i in np.flatnonzero(first & (t > 0)).tolist():  # completes a step of an earlier group
            self._complete_waiting_column(cols, prefixes[i] + int(t[i] - 1).to_bytes(8, "big"), robots[i],
                                          int(gids[i]), int(seqs[i]))  # fmt: skip
        j = np.flatnonzero(ends | same_next)
        nxt_gid = np.where(ends, gids, np.roll(gids, -1))[j]
        nxt_seq = np.where(ends, finals, np.roll(seqs, -1))[j]
        code_of = {r: self.index.code(r) for r in set(robots)}
        table_of = {p: self._episodes[p].table for p in set(prefixes)}
        jl = j.tolist()
        rec_keys = cols.keys + [keys[x] for x in jl]
        robot = np.concatenate(
            [np.asarray(cols.robot, np.int32), np.fromiter((code_of[robots[x]] for x in jl), np.int32, len(jl))]
        )
        rec_tables = cols.tables + [table_of[prefixes[x]] for x in jl]
        rec_flags = np.concatenate([np.asarray(cols.flags, np.int64), flags[j]])
        group = np.concatenate([np.asarray(cols.group, np.int64), gids[j]])
        obs = np.concatenate([np.asarray(cols.obs, np.int64), seqs[j]])
        nxt = np.concatenate([np.asarray(cols.nxt, np.int64), np.where(nxt_gid == gids[j], nxt_seq, -1)])
        hot = (group >= 0) & (obs >= 0) & (nxt >= 0)
        hot_row = np.full(len(rec_keys), -1, np.int64)
        tid0 = self.index.n_rows
        if hot.any() and full is not None:
            acts = full[j] if not cols.keys else np.concatenate([_rows(cols.action, full), full[j]])
            for gid in np.unique(group[hot]).tolist():
                m = np.flatnonzero(hot & (group == gid))
                hot_row[m] = self._groups[gid].add_many((tid0 + m).tolist(), obs[m], nxt[m], acts[m])
        self.index.add_columns(
            rec_keys,
            robot,
            rec_tables,
            np.concatenate([np.asarray(cols.reward, np.float32), reward[j]]),
            (rec_flags & TERMINATED) != 0,
            (rec_flags & TRUNCATED) != 0,
            (rec_flags & INTERVENTION) != 0,
            np.concatenate([np.asarray(cols.version, np.int64), version[j]]),
            np.where(hot, group, -1).astype(np.int32),
            hot_row,
        )
        for i in np.flatnonzero(~same_next & ~ends).tolist():  # wait for their successor (a later group)
            f = int(flags[i])
            act = None if full is None else full[i].copy()
            tail = _Tail(int(gids[i]), int(seqs[i]), act, float(reward[i]), bool(f & TERMINATED),
                         bool(f & TRUNCATED), bool(f & INTERVENTION), int(version[i]))  # fmt: skip
            self._remember(keys[i], tail)

    def _complete_waiting_column(self, cols: _Columns, prev: bytes, robot: str, gid: int, seq: int) -> None:
        tail = self._tails.pop(prev, None)
        cols.keys.append(prev)
        cols.robot.append(self.index.code(robot))
        cols.tables.append(self._episodes[prev[:-8]].table)
        if tail is not None:
            cols.flags.append(
                TERMINATED * tail.terminated | TRUNCATED * tail.truncated | INTERVENTION * tail.intervention
            )
            cols.reward.append(tail.reward)
            cols.version.append(tail.policy_version)
            ok = tail.action is not None and tail.group >= 0 and tail.group == gid
            cols.group.append(tail.group if ok else -1)
            cols.obs.append(tail.seq if ok else -1)
            cols.nxt.append(seq if ok else -1)
            cols.action.append(tail.action if ok else None)
            return
        step = self._read([prev])[0]  # forgotten (MAX_OPEN_TAILS) or stored before a restart: scalars from LMDB
        cols.flags.append(flags_of(step))
        cols.reward.append(step.reward)
        cols.version.append(step.policy_version)
        cols.group.append(-1)
        cols.obs.append(-1)
        cols.nxt.append(-1)
        cols.action.append(None)

    def _count_in_order(
        self,
        steps: list[step_pb2.Step],
        keys: list[bytes],
        scalars: list[tuple[float, int, int, int]],
        tables: list[str],
    ) -> list[str]:
        """Episode, step and byte counts; returns each step's robot."""
        eps = self._episodes
        robots: list[str] = []
        per_robot: dict[str, int] = {}
        last_prefix, ep = b"", None
        for i, key in enumerate(keys):
            prefix = key[:-8]
            if prefix != last_prefix:
                ep = eps.get(prefix)
                if ep is None:
                    ep = eps[prefix] = Episode(steps[i].robot_id, tables[i])
                last_prefix = prefix
            _, flags, _, nbytes = scalars[i]
            t = int.from_bytes(key[-8:], "big")
            ep.steps += 1  # type: ignore[union-attr]
            ep.nbytes += nbytes + len(key)  # type: ignore[union-attr]
            ep.top = t  # type: ignore[union-attr]
            if flags & (ENDS | SUCCESS | INTERVENTION):
                ep.last = t if flags & ENDS else ep.last  # type: ignore[union-attr]
                ep.success |= bool(flags & SUCCESS)  # type: ignore[union-attr]
                ep.interventions += bool(flags & INTERVENTION)  # type: ignore[union-attr]
            robots.append(ep.robot)  # type: ignore[union-attr]
            per_robot[ep.robot] = per_robot.get(ep.robot, 0) + 1  # type: ignore[union-attr]
            self._bytes += nbytes + len(key)
        self._n_steps += len(keys)
        for robot, k in per_robot.items():
            self._steps_per_robot[robot] = self._steps_per_robot.get(robot, 0) + k
        return robots

    def _frames_in_order(
        self,
        robot: str,
        idx: list[int],
        steps: list[step_pb2.Step],
        scalars: list[tuple[float, int, int, int]],
        gids: np.ndarray,
        seqs: np.ndarray,
        finals: np.ndarray,
        actions: list[np.ndarray | None],
    ) -> np.ndarray | None:
        """One robot's observations into its hot group in one copy (one by one for a robot's first steps,
        a new layout or encoded frames), its actions as one array, final observations after."""
        gid = self._robot_group.get(robot)
        if gid is None:  # a robot's first steps: the group of its layout (robots with one spec share one)
            gid = self._robot_group[robot] = self._group(layout_of(steps[idx[0]]), steps[idx[0]])
        group = self._groups[gid]
        got = group.write_many([steps[i].observation for i in idx])
        acts = None if got is None else group.actions_of([steps[i].action for i in idx])
        if got is None or acts is None:
            for i in idx:
                tail = self._tail(b"", steps[i], remember=False)
                gids[i], seqs[i], finals[i], actions[i] = tail.group, tail.seq, tail.final_seq, tail.action
            return None
        gids[idx] = gid
        seqs[idx] = got
        for i in idx:
            if scalars[i][1] & ENDS:
                try:
                    finals[i] = group.write_tensors(steps[i].final_observation)
                except (ValueError, KeyError):
                    finals[i] = -1
        return acts

    def _transitions_in_order(
        self,
        keys: list[bytes],
        scalars: list[tuple[float, int, int, int]],
        robots: list[str],
        gids: list[int],
        seqs: list[int],
        finals: list[int],
        actions: list[np.ndarray | None],
    ) -> None:
        records: list[Record] = []
        hot: dict[int, tuple[list[int], list[int], list[int], list[np.ndarray]]] = {}

        def add(
            key: bytes, robot: str, sc: tuple[float, int, int, int], gid: int, seq: int, nxt: int, act: Any
        ) -> None:
            flags = sc[1]
            ep = self._episodes[key[:-8]]
            rec = Record(
                key,
                self.index.code(robot),
                ep.table,
                sc[0],
                bool(flags & TERMINATED),
                bool(flags & TRUNCATED),
                bool(flags & INTERVENTION),
                sc[2],
            )
            if gid >= 0 and seq >= 0 and nxt >= 0 and act is not None:
                rec.group = gid
                cols = hot.setdefault(gid, ([], [], [], []))
                cols[0].append(len(records))
                cols[1].append(seq)
                cols[2].append(nxt)
                cols[3].append(act)
            records.append(rec)

        n = len(keys)
        for i, key in enumerate(keys):
            prefix, t = key[:-8], int.from_bytes(key[-8:], "big")
            if t > 0:
                if i and keys[i - 1][:-8] == prefix:  # its predecessor came in this group
                    j = i - 1
                    add(
                        keys[j],
                        robots[j],
                        scalars[j],
                        gids[j],
                        seqs[j],
                        seqs[i] if gids[i] == gids[j] else -1,
                        actions[j],
                    )
                else:
                    self._complete_waiting(prefix + (t - 1).to_bytes(8, "big"), robots[i], gids[i], seqs[i], add)
            flags = scalars[i][1]
            if flags & ENDS:
                add(key, robots[i], scalars[i], gids[i], seqs[i], finals[i], actions[i])
            elif i == n - 1 or keys[i + 1][:-8] != prefix:  # waits for its successor (a later group)
                r, _, v, _ = scalars[i]
                tail = _Tail(gids[i], seqs[i], actions[i], r, bool(flags & TERMINATED), bool(flags & TRUNCATED),
                             bool(flags & INTERVENTION), v)  # fmt: skip
                self._remember(key, tail)
        first = self.index.n_rows
        for gid, (ridx, obs, nxt, acts) in hot.items():
            rows = self._groups[gid].add_many([first + i for i in ridx], obs, nxt, acts)
            for i, row in zip(ridx, rows.tolist(), strict=True):
                records[i].hot_row = row
        self.index.add_many(records)

    def _complete_waiting(self, prev: bytes, robot: str, gid: int, seq: int, add: Callable[..., None]) -> None:
        """The transition of a step stored in an earlier group, completed by its successor's frame."""
        tail = self._tails.pop(prev, None)
        if tail is not None:
            sc = (tail.reward, TERMINATED * tail.terminated | TRUNCATED * tail.truncated
                  | INTERVENTION * tail.intervention, tail.policy_version, 0)  # fmt: skip
            add(prev, robot, sc, tail.group, tail.seq, seq if gid == tail.group else -1, tail.action)
            return
        step = self._read([prev])[0]  # forgotten (MAX_OPEN_TAILS) or stored before a restart: scalars from LMDB
        add(prev, robot, (step.reward, flags_of(step), step.policy_version, 0), -1, -1, -1, None)

    def _tails_many(self, items: list[tuple[bytes, step_pb2.Step]]) -> None:
        """_tail for many steps: per robot, observations copied into the hot tier in one go."""
        by_robot: dict[str, list[tuple[bytes, step_pb2.Step]]] = {}
        for key, step in items:
            by_robot.setdefault(step.robot_id, []).append((key, step))
        for robot, mine in by_robot.items():
            gid = self._robot_group.get(robot)
            seqs = None if gid is None else self._groups[gid].write_many([s.observation for _, s in mine])
            if seqs is None:  # first steps of a robot, a new layout, or encoded frames: one by one
                for key, step in mine:
                    self._tail(key, step)
                continue
            group = self._groups[gid]  # type: ignore[index]
            for (key, step), seq in zip(mine, seqs.tolist(), strict=True):
                self._remember(key, self._new_tail(gid, seq, group, step))  # type: ignore[arg-type]

    def _remember(self, key: bytes, tail: _Tail) -> None:
        if len(self._tails) >= MAX_OPEN_TAILS:  # successors that never came: forget the oldest
            self._tails.pop(next(iter(self._tails)))
        self._tails[key] = tail

    def _tail(self, key: bytes, step: step_pb2.Step, remember: bool = True) -> _Tail:
        """Copy a stored step's observation(s) into the hot tier; remember it until its transition completes."""
        gid = self._robot_group.get(step.robot_id)
        try:
            if gid is None:
                raise ValueError("no group yet")
            group = self._groups[gid]
            seq = group.write_tensors(step.observation)
        except (ValueError, KeyError):  # first step of the robot, or it re-registered with a new layout
            gid = self._robot_group[step.robot_id] = self._group(layout_of(step), step)
            group = self._groups[gid]
            seq = group.write_tensors(step.observation)
        tail = self._new_tail(gid, seq, group, step)
        if remember:
            self._remember(key, tail)
        return tail

    @staticmethod
    def _new_tail(gid: int, seq: int, group: Any, step: step_pb2.Step) -> _Tail:
        """A stored step's row-to-be: its observation's frame, action, flags and (last step) final frame."""
        tail = _Tail(
            gid,
            seq,
            tensor_array(step.action),
            step.reward,
            step.terminated,
            step.truncated,
            step.intervention,
            step.policy_version,
        )
        if step.HasField("final_observation"):
            tail.final_seq = group.write_tensors(step.final_observation)
        return tail

    def _evict_over_capacity(self) -> None:
        """Whole episodes, oldest first (by first arrival), until the stored bytes fit capacity_mb again (with 5%
        slack), from LMDB and RAM.

        Only complete episodes go (a last step and every step below it), and abandoned ones: an episode still
        being written stays unless its robot has since completed a later episode (a robot writes one episode at
        a time and its edge sends in order, so a merely late tail, set aside after PERMISSION_DENIED or behind a
        slow spool drain, comes before that later episode is whole: this one will not go on, its edge restarted
        mid-episode or its spool dropped the rest). A later episode only begun is not enough: the refused tail
        would be acked and dropped by the edge. No wall clock: a robot that stops for good keeps its one open
        episode. When only episodes still being written are left, nothing more is evicted: the bytes stay above
        capacity_mb (warned once, gauge user_replay_over_capacity) rather than cut one. Later steps of an evicted
        episode are refused (_refuse_evicted), so no headless part of it is stored; a restarted replay no longer
        knows which episodes it evicted."""
        if not self.capacity_bytes or self._bytes <= self.capacity_bytes:
            self._note_over_capacity(False)
            return
        with self._lock:
            victims, freed = self._eviction_victims(int(self.capacity_bytes * 0.95))
        self._note_over_capacity(self._bytes - freed > self.capacity_bytes)
        if not victims:
            return
        # Out of the index first, then out of LMDB: a sample (which holds the lock from draw to read) never draws
        # a step whose bytes are already gone.
        with self._lock:
            for prefix in victims:
                ep = self._episodes.pop(prefix)
                self._n_steps -= ep.steps
                left = self._steps_per_robot[ep.robot] - ep.steps
                if left:
                    self._steps_per_robot[ep.robot] = left
                else:
                    del self._steps_per_robot[ep.robot]
                self._bytes -= ep.nbytes
                self._evicted_steps_per_robot[ep.robot] = self._evicted_steps_per_robot.get(ep.robot, 0) + ep.steps
                self._remember_evicted(prefix)
            self.index.evict_episodes(victims)
            if self.index.wants_compaction():
                self._compact_index()
            gone = set(victims)
            for key in [k for k in self._tails if k[:-8] in gone]:  # their steps left LMDB: nothing waits
                del self._tails[key]
            self._evicted_episodes += len(victims)
            self.generation += 1
        self.db.delete_episodes_later(victims)  # with the next commit: no transaction (fsync) of its own
        log.info("evicted episodes", extra=kv(episodes=len(victims), bytes=freed))

    def _eviction_victims(self, target: int) -> tuple[list[bytes], int]:
        """The oldest evictable episodes whose bytes bring the store down to `target`, and those bytes (caller
        holds the lock). Evictable: complete, or abandoned (see _evict_over_capacity); the newest episode stays, so
        the buffer never empties itself (one episode above capacity_mb stays until the next one arrives)."""
        completed: dict[str, int] | None = None  # robot -> arrival position of its newest complete episode
        victims: list[bytes] = []
        freed = 0
        for position, (prefix, ep) in enumerate(self._episodes.items()):
            if self._bytes - freed <= target or len(victims) == len(self._episodes) - 1:  # one always stays
                break
            if not _complete(ep):  # still being written, unless abandoned
                if completed is None:  # built only if an open one is met
                    completed = self._newest_complete()
                if completed.get(ep.robot, -1) < position:
                    continue
            victims.append(prefix)
            freed += ep.nbytes
        return victims, freed

    def _newest_complete(self) -> dict[str, int]:
        """Robot -> arrival position of its newest complete episode (caller holds the lock)."""
        out: dict[str, int] = {}
        for position, ep in enumerate(self._episodes.values()):
            if _complete(ep):
                out[ep.robot] = position
        return out

    def _note_over_capacity(self, over: bool) -> None:
        """Warn once when the bytes stay above capacity_mb for want of evictable episodes; note when it ends."""
        if over == self._over_capacity:
            return
        self._over_capacity = over
        OVER_CAPACITY.set(int(over))
        if over:
            log.warning(
                "replay above capacity_mb, but only episodes still being written (never cut) and the newest are "
                "left; eviction goes on once they end",
                extra=kv(path=str(self.path), stored_bytes=self._bytes, capacity_bytes=self.capacity_bytes),
            )
        else:
            log.info("replay within capacity_mb again", extra=kv(path=str(self.path), stored_bytes=self._bytes))

    def _remember_evicted(self, prefix: bytes) -> None:
        if len(self._evicted) >= MAX_EVICTED_REMEMBERED:
            self._evicted.pop(next(iter(self._evicted)))
        self._evicted[prefix] = False

    def _refuse_evicted(self, group: list[_Pending]) -> bool:
        """Take steps of evicted episodes out of the group before its commit (writer thread): stored, they would
        be an episode without its start (or a stray re-sent step). They are answered as duplicates (the edge
        forgets them), counted, and logged once per episode. Returns True when no step is left to commit."""
        left = 0
        for item in group:
            gone = [i for i, key in enumerate(item.keys) if key[:-8] in self._evicted]
            if gone:
                self._refuse(item, gone)
            left += len(item.steps)
        if left:
            return False
        for item in group:
            item.future.set_result((0, item.refused))
        return True

    def _refuse(self, item: _Pending, gone: list[int]) -> None:
        """Take the steps at `gone` out of `item`; count them, log each episode's first."""
        for i in gone:
            prefix = item.keys[i][:-8]
            if not self._evicted[prefix]:
                self._evicted[prefix] = True
                step = item.steps[i]
                log.warning(
                    "steps of an evicted episode refused (not stored): its start is gone",
                    extra=kv(robot_id=step.robot_id, episode_id=step.episode_id, step_index=step.step_index),
                )
        item.refused += len(gone)
        REFUSED_EVICTED.inc(len(gone))
        keep = sorted(set(range(len(item.keys))) - set(gone))
        item.steps = [item.steps[i] for i in keep]
        item.tables = [item.tables[i] for i in keep]
        item.raws = [item.raws[i] for i in keep]
        item.keys = [item.keys[i] for i in keep]
        item.scalars = [item.scalars[i] for i in keep]
        item.nbytes = sum(map(len, item.raws))

    def _compact_index(self) -> None:
        """Drop evicted rows from the index, so it stays proportional to what is stored (a months-long run
        evicts far more than it keeps), and renumber every holder of rows (caller holds the lock; generation
        bumps with the eviction, and public ids (Batch.indices) do not change)."""
        remap = self.index.compact()
        for group in self._groups:  # rows whose transition was dropped never validate again
            held = group.t_tid >= 0
            group.t_tid[held] = remap[group.t_tid[held]]
        self.compactions += 1
        COMPACTIONS.inc()

    def put_spec(self, spec: robot_pb2.RobotSpec) -> None:
        with self._write_lock:
            self._check_open()
            self.db.put_spec(spec)

    def get_spec(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        self._check_open()
        with self._lock:
            return self.db.get_spec(robot_id)

    def table_specs(self, tables: Iterable[str], limit: int) -> tuple[list[robot_pb2.RobotSpec], int]:
        """The stored specs of the robots with sampleable transitions in `tables`, by robot id: at most `limit`, and
        how many more robots have one (StatsResponse.specs, specs_left_out)."""
        self._check_open()
        with self._lock:
            index = self.index
            # an attached table's robots keep their specs in their own buffer (read-only), not in this one
            dbs = dict(zip(self._attached_episodes, self._attached, strict=True))
            found: dict[str, robot_pb2.RobotSpec] = {}
            for table in tables:
                for code, grow in index.tables.get(table, {}).items():
                    robot = index.robots[code]
                    if not grow.n or robot in found:
                        continue
                    spec = dbs[table].get_spec(robot) if table in dbs else None
                    if (spec := spec or self.db.get_spec(robot)) is not None:
                        found[robot] = spec
            specs = [found[r] for r in sorted(found)]
        return specs[:limit], max(0, len(specs) - limit)

    # ------------------------------------------------------------------ reads

    def _read(self, keys: list[bytes]) -> list[step_pb2.Step]:
        with self._lock:
            raws = self.db.get_many(keys)
        out = []
        for key, raw in zip(keys, raws, strict=True):
            if raw is None:
                raise ReplayError(f"index points at a missing step {key!r}")
            out.append(step_pb2.Step.FromString(raw))
        return out

    @property
    def transitions(self) -> int:
        with self._lock:
            return len(self.index)

    def transitions_for(self, robot_ids: list[str] | None = None, tables: Iterable[str] = ()) -> int:
        with self._lock:
            names = list(tables) or [""]
            return sum(self.index.count(t, robot_ids) for t in names)

    def too_many_tables(self, table: str, limit: int) -> bool:
        """Whether inserting into `table` would make more than `limit` tables."""
        with self._lock:
            return table not in self.index.tables and len(self.index.tables) >= limit

    def tables(self) -> list[str]:
        with self._lock:
            return sorted(self.index.tables)

    def sample(
        self,
        batch_size: int,
        rng: np.random.Generator,
        robot_ids: list[str] | None = None,
        draw: Draw | None = None,
    ) -> dict[str, Any]:
        """A ready-to-train batch of stacked numpy arrays (see module doc for next_observation)."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        req = draw or Draw(batch_size=batch_size, robot_ids=list(robot_ids or []))
        req.batch_size = batch_size
        with self._lock:
            self._check_open()
            drawn = self.index.draw(req, rng)
            idx = self.index
            tids, last = drawn.tids, drawn.last
            human = idx.intervention.a[tids]
            if drawn.human is not None:  # a human table's rows (Draw.human_tables): a demonstrator's, unflagged or not
                human = human | drawn.human
            out: dict[str, Any] = {
                "reward": drawn.reward,
                "terminated": drawn.terminated,
                "truncated": drawn.truncated,
                "intervention": human,
                "policy_version": idx.policy_version.a[tids],
                "indices": idx.ids.a[tids],  # public ids: rows are renumbered when the index compacts
                "weights": drawn.weights,
                "n_steps": drawn.n_steps,
            }
            k, enc = max(1, req.frame_stack), req.encoded_frames
            if k == 1:
                self._gather(out, tids, last, enc)
                return out
            # frame stacking: the k newest observations up to t, and up to t+n for next_observation
            # (oldest first), repeating an episode's first observation where fewer than k came before
            newest: dict[str, Any] = {}
            self._gather(newest, tids, last, enc)
            obs_parts, next_parts = [], []
            for back in range(k - 1, 0, -1):
                part: dict[str, Any] = {}
                self._gather(part, idx.back(tids, back), last, enc)  # (its next_observation is not used)
                obs_parts.append(part["observation"])
                before_end: dict[str, Any] = {}
                self._gather(before_end, idx.back(last, back - 1), last, enc)
                next_parts.append(before_end["observation"])
            obs_parts.append(newest["observation"])
            next_parts.append(newest["next_observation"])
            out["action"] = newest["action"]
            out["observation"] = {f: _stack([p[f] for p in obs_parts]) for f in obs_parts[-1]}
            out["next_observation"] = {f: _stack([p[f] for p in next_parts]) for f in next_parts[-1]}
            return out

    def _gather(self, out: dict[str, Any], tids: np.ndarray, last: np.ndarray, keep_encoded: bool = False) -> None:
        """observation (of tids), next_observation (after last) and action columns (caller holds the lock).
        keep_encoded: JPEG/PNG frames of the hot tier's encoded features as kept (wire.EncodedFrames) where a
        feature's drawn frames share one encoding."""
        idx = self.index
        same = last is tids  # one-step transitions: one set of checks
        rows = idx.hot_row.a[tids]
        next_rows = rows if same else idx.hot_row.a[last]
        if self._gather_hot(out, tids, last, rows, next_rows, keep_encoded):
            return
        g_obs = idx.group.a[tids]
        g_next = g_obs if same else idx.group.a[last]
        g0 = int(g_obs[0])
        if (g_obs == g0).all() and (same or (g_next == g0).all()):
            known = [g0] if g0 >= 0 else []
        else:
            gids = np.unique(np.concatenate([g_obs, g_next]))
            known = gids[gids >= 0].tolist()
        if len(known) > 1:
            raise LayoutError(
                "sampled transitions have different observation layouts; "
                "sample robots with different specs separately (robot_ids)"
            )
        hot = self._groups[known[0]] if known else None
        if hot is not None:
            ok_obs = hot.valid(rows, tids)
            ok_next = ok_obs if same else hot.valid(next_rows, last)
        else:
            ok_obs = ok_next = np.zeros(len(tids), bool)
        n_hot = int(np.count_nonzero(ok_obs))
        self.hits += n_hot
        self.misses += len(tids) - n_hot
        self._fill_mixed(out, hot, tids, last, ok_obs, ok_next, keep_encoded)

    def _gather_hot(
        self,
        out: dict[str, Any],
        tids: np.ndarray,
        last: np.ndarray,
        rows: np.ndarray,
        next_rows: np.ndarray,
        keep_encoded: bool = False,
    ) -> bool:
        """The usual batch, every draw still in the first draw's hot ring: gathered from RAM (True), else
        nothing done (False). A transition is only ever written to its own group's ring, so draws that all
        validate in g0's ring all have g0's layout: the per-draw group check of _gather would pass."""
        g0 = int(self.index.group.a[tids[0]])
        if g0 < 0:
            return False
        hot = self._groups[g0]
        n_hot = int(np.count_nonzero(hot.valid(rows, tids)))
        if n_hot != len(tids) or not (last is tids or hot.valid(next_rows, last).all()):
            return False
        self.hits += n_hot
        out["observation"], out["next_observation"] = hot.observations_pair(rows, next_rows, keep_encoded)
        action = hot.action.take(rows, axis=0)
        out["action"] = action if action.dtype == np.float32 else action.astype(np.float32)
        return True

    def _fill_mixed(
        self,
        out: dict[str, Any],
        hot: HotGroup | None,
        tids: np.ndarray,
        last: np.ndarray,
        ok_obs: np.ndarray,
        ok_next: np.ndarray,
        keep_encoded: bool = False,
    ) -> None:
        """Hot rows gathered from RAM, the rest read from LMDB into the same columns (caller holds the lock)."""
        idx = self.index
        kept = frozenset(hot.encoded) if keep_encoded and hot is not None else frozenset()
        cold_obs, cold_next = np.flatnonzero(~ok_obs), np.flatnonzero(~ok_next)
        keys = idx.keys_of(tids[cold_obs])
        last_keys = idx.keys_of(last[cold_next])
        n = len(tids)
        layout = hot.layout if hot is not None else None
        if layout is None and not self._attached:
            layout = layout_of(self._read([(keys or last_keys)[0]])[0])
        # large frames (cameras): copied straight from the LMDB pages into the batch; small steps parse
        # faster with protobuf (C) than rawstep walks them (Python)
        raw_read = not kept and not self._attached  # (encoded frames are never raw: _read_cold_raw would say no)
        if layout is not None and raw_read and frame_nbytes(layout) >= RAW_READ_MIN_BYTES:
            obs, next_obs, action = self._columns(layout, n, hot, tids, last, ok_obs, ok_next)
            if self._read_cold_raw(layout, keys, last_keys, cold_obs, cold_next, obs, next_obs, action):
                out["observation"] = obs
                out["next_observation"] = next_obs
                out["action"] = action.astype(np.float32, copy=False)
                return
        uniq = sorted(set(keys) | set(last_keys) | {next_key(k) for k in last_keys})
        raws = dict(zip(uniq, self._get_many(uniq), strict=True))
        steps: dict[bytes, step_pb2.Step] = {}

        def step(key: bytes) -> step_pb2.Step:
            s = steps.get(key)
            if s is None:
                raw = raws.get(key)
                if raw is None:
                    raise ReplayError(f"index points at a missing step {key!r}")
                s = steps[key] = step_pb2.Step.FromString(raw)
            return s

        cur = [step(k) for k in keys]
        nxt = []
        for k in last_keys:
            s = step(k)
            nxt.append(s.final_observation if s.HasField("final_observation") else step(next_key(k)).observation)
        first_step = cur[0] if cur else step(last_keys[0])
        layout = hot.layout if hot is not None else layout_of(first_step)
        for s in cur:
            if layout_of(s) != layout:
                reference = "the hot tier's layout" if hot is not None else _step_text(first_step)
                raise LayoutError(
                    f"sampled transitions have different observation layouts: {_step_text(s)} has "
                    f"{_layout_difference(layout_of(s), layout, reference)}; "
                    "sample robots with different specs separately (robot_ids)"
                )
        try:
            if keep_encoded and hot is None:  # no hot tier: the features the stored steps keep as JPEG/PNG
                first = cur[0].observation if cur else nxt[0]
                kept = frozenset(
                    f for f, dt, _ in layout[0] if dt == np.uint8 and first.tensors[f].encoding in IMAGE_ENC
                )
            features = [f for f, _, _ in layout[0] if f not in kept]
            obs, next_obs, action = self._columns(layout, n, hot, tids, last, ok_obs, ok_next, kept)
            for i, s in zip(cold_obs.tolist(), cur, strict=True):
                for f in features:
                    obs[f][i] = tensor_array(s.observation.tensors[f])
                action[i] = tensor_array(s.action)
            for i, m in zip(cold_next.tolist(), nxt, strict=True):
                for f in features:
                    next_obs[f][i] = tensor_array(m.tensors[f])
            if kept:
                shapes = {f: sh for f, _, sh in layout[0]}
                obs_at = hot.frame_rows(idx.hot_row.a[tids[ok_obs]], "obs") if hot is not None else None
                next_at = hot.frame_rows(idx.hot_row.a[last[ok_next]], "next") if hot is not None else None
                for f in kept:
                    cold = [s.observation.tensors[f] for s in cur]
                    obs[f] = _kept_frames(hot, f, shapes[f], obs_at, ok_obs, cold_obs, cold)
                    cold = [m.tensors[f] for m in nxt]
                    next_obs[f] = _kept_frames(hot, f, shapes[f], next_at, ok_next, cold_next, cold)
        except (KeyError, ValueError) as exc:
            raise LayoutError(f"sampled observations do not match one layout: {exc}") from None
        out["observation"] = obs
        out["next_observation"] = next_obs
        out["action"] = action.astype(np.float32, copy=False)

    def _columns(
        self,
        layout: Layout,
        n: int,
        hot: HotGroup | None,
        tids: np.ndarray,
        last: np.ndarray,
        ok_obs: np.ndarray,
        ok_next: np.ndarray,
        skip: frozenset[str] = frozenset(),
    ) -> tuple[dict[str, Any], dict[str, Any], np.ndarray]:
        """Batch columns of `layout` with the hot rows gathered from RAM (the cold rows are left to fill); features
        in `skip` (encoded ones the caller passes on as kept) get no column."""
        features, (act_dtype, act_shape) = layout
        obs: dict[str, Any] = {f: np.empty((n, *sh), dt) for f, dt, sh in features if f not in skip}
        next_obs: dict[str, Any] = {f: np.empty((n, *sh), dt) for f, dt, sh in features if f not in skip}
        action = np.empty((n, *act_shape), act_dtype)
        idx = self.index
        if hot is not None and ok_obs.any():
            rows = idx.hot_row.a[tids[ok_obs]]
            for f, col in hot.observations(rows, "obs", skip).items():
                obs[f][ok_obs] = col
            action[ok_obs] = hot.action[rows]
        if hot is not None and ok_next.any():
            for f, col in hot.observations(idx.hot_row.a[last[ok_next]], "next", skip).items():
                next_obs[f][ok_next] = col
        return obs, next_obs, action

    def _read_cold_raw(
        self,
        layout: Layout,
        keys: list[bytes],
        last_keys: list[bytes],
        cold_obs: np.ndarray,
        cold_next: np.ndarray,
        obs: dict[str, np.ndarray],
        next_obs: dict[str, np.ndarray],
        action: np.ndarray,
    ) -> bool:
        """Cold rows read in key order in one read transaction, each raw tensor copied once from its LMDB page
        into its column (rawstep.py finds it; no Step objects). False when a step is not all raw tensors of
        `layout` (encoded frames, another layout): the caller parses them with protobuf (caller holds the lock)."""
        features, (act_dtype, act_shape) = layout
        want = [(f, dt, sh, int(np.prod(sh)), int(np.prod(sh)) * dt.itemsize) for f, dt, sh in features]
        act_count = int(np.prod(act_shape))
        spans: dict[bytes, tuple[memoryview, StepSpans]] = {}
        with self.db.env.begin(db=self.db.steps, buffers=True) as txn:

            def get(key: bytes) -> tuple[memoryview, StepSpans]:
                got = spans.get(key)
                if got is None:
                    buf = txn.get(key)
                    if buf is None:
                        raise ReplayError(f"index points at a missing step {key!r}")
                    got = spans[key] = (buf, step_spans(buf))
                return got

            def put(cols: dict[str, np.ndarray], i: int, buf: memoryview, tmap: dict[str, Span]) -> bool:
                if len(tmap) != len(want):
                    return False
                for f, dt, sh, count, size in want:
                    sp = tmap.get(f)
                    if sp is None or sp.encoding or sp.shape != sh or sp.size != size or _np_dtype(sp.dtype) != dt:
                        return False
                    cols[f][i] = np.frombuffer(buf, dt, count, sp.offset).reshape(sh)
                return True

            try:
                for key in sorted(set(keys) | set(last_keys)):  # B-tree order: neighbouring pages
                    get(key)
                for i, key in zip(cold_obs.tolist(), keys, strict=True):
                    buf, sp = get(key)
                    act = sp.action
                    if act is None or act.encoding or act.shape != act_shape or _np_dtype(act.dtype) != act_dtype:
                        return False
                    if act.size != act_count * act_dtype.itemsize or not put(obs, i, buf, sp.observation):
                        return False
                    action[i] = np.frombuffer(buf, act_dtype, act_count, act.offset).reshape(act_shape)
                for i, key in zip(cold_next.tolist(), last_keys, strict=True):
                    buf, sp = get(key)
                    if sp.final is None:
                        buf, nxt = get(next_key(key))
                        tmap = nxt.observation
                    else:
                        tmap = sp.final
                    if not put(next_obs, i, buf, tmap):
                        return False
            except (Unexpected, IndexError, ValueError):
                return False
            finally:
                spans.clear()  # the pages' buffers are only valid inside the transaction
        return True

    def update_priorities(self, tids: np.ndarray, priorities: np.ndarray) -> int:
        with self._lock:
            return self.index.update_priorities(np.asarray(tids, np.int64), np.asarray(priorities, np.float32))

    # ------------------------------------------------------------------ stats

    def bytes_on_disk(self) -> int:
        self._check_open()
        with self._lock:
            return self.db.bytes_on_disk()

    def stats(self) -> dict[str, Any]:
        on_disk = self.bytes_on_disk()
        with self._lock:
            per_robot = dict(self._steps_per_robot)
            return {
                "steps": self._n_steps,
                "transitions": len(self.index),
                "episodes": len(self._episodes),
                "bytes_on_disk": on_disk,
                "steps_per_robot": per_robot,
                "evicted_steps_per_robot": dict(self._evicted_steps_per_robot),
                "duplicates": self.db.duplicates,
            }

    def table_stats(self, counts_only: bool = False) -> dict[str, dict[str, Any]]:
        """Per table (and per robot within it): transitions, steps, episodes, bytes, success rate. `counts_only`:
        transitions alone (the rest 0), from the index's per-table per-robot counts: O(robots x tables), where the
        whole answer walks every stored episode under the lock (~0.14 s per 100k episodes: inserts and samples wait).

        A step is stored once, in the table it was inserted into, and its bytes count there. "interventions" also
        indexes the human steps of other tables' episodes; there such an episode counts once (per robot and in the
        total), its steps are its human steps, its bytes stay with its own table, and it is a success when the
        episode is (a step of it has success, as every table counts): the success rate of episodes a human
        stepped into. Episodes inserted into "interventions" count whole, as in any table.
        """
        with self._lock:
            out: dict[str, dict[str, Any]] = {}
            attached = [] if counts_only else [e for eps in self._attached_episodes.values() for e in eps.values()]
            for ep in [] if counts_only else [*self._episodes.values(), *attached]:
                _count_episode(out, ep.table, ep, ep.steps, ep.nbytes)
                if ep.interventions and ep.table != INTERVENTIONS:  # its human steps are indexed there too
                    _count_episode(out, INTERVENTIONS, ep, ep.interventions, 0)
            for name in self.index.tables:
                for code, grow in self.index.tables[name].items():
                    for target in _stats_rows(out, name, self.index.robots[code]):
                        target["transitions"] += grow.n
            for t in out.values():
                for r in [t, *t["robots"].values()]:
                    r["success_rate"] = r["successes"] / r["episodes"] if r["episodes"] else 0.0
            return out

    def episode_bounds(self) -> list[tuple[str, str, int, int | None]]:
        """(robot, episode, highest step index, last step index or None) of every stored episode, oldest first:
        what the service's episode guard needs after a restart to refuse steps after an episode's end."""
        with self._lock:
            out = []
            for prefix, ep in self._episodes.items():
                episode_id = prefix[len(ep.robot.encode()) + 1 : -1].decode()
                out.append((ep.robot, episode_id, ep.top, ep.last if ep.last >= 0 else None))
            return out

    def cache_info(self) -> dict[str, int]:
        with self._lock:
            return {
                "entries": sum(g.hot_transitions() for g in self._groups),
                "bytes": sum(g.resident_bytes() for g in self._groups),
                "capacity": sum(g.capacity for g in self._groups),
                "hits": self.hits,
                "misses": self.misses,
                "decoded_hits": sum(g.decoded_hits for g in self._groups),  # frames served from the decoded window
                "decoded_misses": sum(g.decoded_misses for g in self._groups),  # frames decoded (window on)
                "evicted_episodes": self._evicted_episodes,
                "stored_bytes": self._bytes,
            }

    def close(self) -> None:
        """Idempotent; commits what is queued, then waits for a commit or sample in progress."""
        with self._queue_cond:
            self._closing = True
            self._queue_cond.notify_all()
            writer = self._writer
        if writer is not None and writer is not threading.current_thread():
            writer.join()
        with self._write_lock, self._lock:
            if self._closed:
                return
            self._closed = True
            self.db.close()
            for db in self._attached:
                db.close()
            for fd in self._attached_holds:  # owners may write those buffers again
                os.close(fd)
