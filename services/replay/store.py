"""The persistent replay buffer: LMDB on disk, an index of sampleable transitions in memory.

One LMDB environment under `path` (data.mdb + lock.mdb), named databases:
  steps:  b"<robot_id>/<episode_id>/" + big-endian uint64 step_index -> serialized user.v1.Step
  ends:   same key -> b""  for steps that end an episode (they carry final_observation)
  specs:  robot_id -> serialized RobotSpec (so a restarted replay can validate while control is down)
  meta:   b"format" -> b"1"; b"duplicates" -> big-endian uint64
Keys sort by robot, episode and step, so an episode's steps are adjacent and a re-sent step hits
the same key and is stored once. The next observation of step t is the observation of step t+1,
or t's own final_observation when t ends the episode: no observation is stored twice.

Step t is sampleable once its next observation exists. The index of sampleable keys lives in
memory, is rebuilt at open from a keys-only scan and grows as commits land, in any arrival order.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lmdb
import numpy as np

from user import wire
from user.log import kv
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

log = logging.getLogger(__name__)

FORMAT = b"1"
_INDEX = struct.Struct(">Q")
_U64 = struct.Struct(">Q")
DEFAULT_CACHE_MB = 256
_OVERHEAD_BYTES = 600  # Python objects around one cached step's arrays


class ReplayError(RuntimeError):
    """Base class for store errors the service maps to a gRPC status."""


class EmptyBufferError(ReplayError):
    """Nothing sampleable (yet, or for the robots asked for)."""


class LayoutError(ReplayError):
    """Sampled transitions do not share one observation layout (robots with different specs)."""


class ReplayFullError(ReplayError):
    """The LMDB map is full: raise replay.map_size_mb."""


class StoreClosedError(ReplayError):
    """The store was closed (the service is shutting down)."""


def episode_prefix(robot_id: str, episode_id: str) -> bytes:
    return f"{robot_id}/{episode_id}/".encode()


def step_key(robot_id: str, episode_id: str, step_index: int) -> bytes:
    return episode_prefix(robot_id, episode_id) + _INDEX.pack(step_index)


def split_key(key: bytes) -> tuple[bytes, int]:
    """(episode prefix, step index)."""
    return key[:-8], _INDEX.unpack(key[-8:])[0]


def _robot_of(prefix: bytes) -> str:
    return prefix[: prefix.index(b"/")].decode()


def _raw_bytes(tensor: tpb.Tensor) -> bytes:
    """Stored tensors were validated on insert: RAW data is used as is, other encodings are decoded once."""
    if tensor.encoding == tpb.ENCODING_RAW:
        return tensor.data
    return wire.from_tensor(tensor).tobytes()


Layout = tuple[tuple[tuple[str, np.dtype, tuple[int, ...]], ...], tuple[np.dtype, tuple[int, ...]]]


@dataclass(slots=True)
class _Decoded:
    """One step as raw little-endian bytes per tensor, kept in the LRU cache.

    A batch column is then one bytes join + one frombuffer, instead of B small arrays stacked.
    `layout` is interned by the store, so rows of the same layout compare by identity.
    """

    observation: dict[str, bytes]
    final_observation: dict[str, bytes] | None
    layout: Layout
    action: bytes
    reward: float
    terminated: bool
    truncated: bool
    intervention: bool
    policy_version: int
    nbytes: int

    @classmethod
    def parse(cls, raw: bytes, intern: dict[Layout, Layout]) -> _Decoded:
        step = step_pb2.Step.FromString(raw)
        obs: dict[str, bytes] = {}
        features = []
        for name, tensor in sorted(step.observation.tensors.items()):
            obs[name] = _raw_bytes(tensor)
            features.append((name, wire.dtype_from_proto(tensor.dtype), tuple(tensor.shape)))
        final = None
        if step.HasField("final_observation"):
            final = {name: _raw_bytes(t) for name, t in step.final_observation.tensors.items()}
        act = step.action
        layout = (tuple(features), (wire.dtype_from_proto(act.dtype), tuple(act.shape)))
        layout = intern.setdefault(layout, layout)
        action = _raw_bytes(act)
        nbytes = _OVERHEAD_BYTES + sum(map(len, obs.values())) + len(action)
        if final is not None:
            nbytes += sum(map(len, final.values()))
        return cls(
            obs,
            final,
            layout,
            action,
            step.reward,
            step.terminated,
            step.truncated,
            step.intervention,
            step.policy_version,
            nbytes,
        )


class _LRU:
    """Decoded steps by key, bounded by bytes."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self._items: OrderedDict[bytes, _Decoded] = OrderedDict()
        self.hits = self.misses = 0

    def get(self, key: bytes) -> _Decoded | None:
        item = self._items.get(key)
        if item is None:
            self.misses += 1
            return None
        self._items.move_to_end(key)
        self.hits += 1
        return item

    def put(self, key: bytes, item: _Decoded) -> None:
        if item.nbytes > self.max_bytes:
            return
        self._items[key] = item
        self.bytes += item.nbytes
        while self.bytes > self.max_bytes:
            _, old = self._items.popitem(last=False)
            self.bytes -= old.nbytes

    def __len__(self) -> int:
        return len(self._items)


class ReplayStore:
    """Thread-safe: one writer at a time (put_steps), samples and stats from any thread."""

    def __init__(self, path: str | Path, map_size_mb: int = 4096, cache_mb: int = DEFAULT_CACHE_MB) -> None:
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.env = lmdb.open(
            str(self.path),
            map_size=int(map_size_mb) << 20,
            max_dbs=4,
            subdir=True,
            readahead=False,  # samples are random reads; readahead only pollutes the page cache
            meminit=False,
        )
        self.map_size_mb = map_size_mb
        stale = self.env.reader_check()  # reader slots left by a process that was killed
        if stale:
            log.info("cleared stale LMDB readers", extra=kv(path=str(self.path), readers=stale))
        self._steps = self.env.open_db(b"steps")
        self._ends = self.env.open_db(b"ends")
        self._specs = self.env.open_db(b"specs")
        self._meta = self.env.open_db(b"meta")
        self._write_lock = threading.Lock()  # one writer; also guards close()
        self._index_lock = threading.Lock()  # the in-memory index below
        self._sample_lock = threading.Lock()  # the decode cache
        self._cache = _LRU(int(cache_mb) << 20)
        self._layouts: dict[Layout, Layout] = {}
        self._closed = False
        self._pools: dict[str, list[bytes]] = {}  # robot_id -> sampleable step keys (append-only)
        self._steps_per_robot: dict[str, int] = {}
        self._episodes: set[bytes] = set()
        self._n_steps = 0
        self._duplicates = 0
        try:
            self._open_meta()
            self._rebuild_index()
        except BaseException:
            self.env.close()
            raise
        log.info(
            "replay store open",
            extra=kv(
                path=str(self.path), steps=self._n_steps, transitions=self.transitions, episodes=len(self._episodes)
            ),
        )

    # ------------------------------------------------------------------ open

    def _open_meta(self) -> None:
        with self.env.begin(write=True, db=self._meta) as txn:
            fmt = txn.get(b"format")
            if fmt is None:
                if txn.stat(self._steps)["entries"]:
                    raise ReplayError(f"{self.path} holds steps of an older replay format; move it away to start anew")
                txn.put(b"format", FORMAT)
            elif fmt != FORMAT:
                raise ReplayError(f"{self.path}: replay format {fmt!r}, this code reads {FORMAT!r}")
            dups = txn.get(b"duplicates")
            self._duplicates = _U64.unpack(dups)[0] if dups else 0

    def _rebuild_index(self) -> None:
        """Keys-only scan (values are never read), so a restarted service samples everything it had."""
        with self.env.begin() as txn:
            ends = set(txn.cursor(db=self._ends).iternext(keys=True, values=False))
            prev_key: bytes | None = None
            prev_prefix, prev_index, robot = b"", -1, ""
            for key in txn.cursor(db=self._steps).iternext(keys=True, values=False):
                prefix, index = split_key(key)
                if prefix != prev_prefix:
                    robot = _robot_of(prefix)
                    self._episodes.add(prefix)
                elif prev_key is not None and index == prev_index + 1 and prev_key not in ends:
                    self._pools.setdefault(robot, []).append(prev_key)
                if key in ends:
                    self._pools.setdefault(robot, []).append(key)
                self._steps_per_robot[robot] = self._steps_per_robot.get(robot, 0) + 1
                self._n_steps += 1
                prev_key, prev_prefix, prev_index = key, prefix, index

    # ------------------------------------------------------------------ writes

    def _check_open(self) -> None:
        if self._closed:
            raise StoreClosedError(f"replay store {self.path} is closed")

    def put_steps(self, steps: list[step_pb2.Step], specs: Iterable[robot_pb2.RobotSpec] = ()) -> tuple[int, int]:
        """Store validated steps (and specs) in ONE transaction; (stored, duplicates) once it has committed."""
        stored: list[tuple[str, bytes]] = []  # (robot, episode prefix)
        sampleable: list[tuple[str, bytes]] = []
        dups = 0
        with self._write_lock:
            self._check_open()
            try:
                with self.env.begin(write=True) as txn:
                    for step in steps:
                        if self._put_one(txn, step, sampleable):
                            stored.append((step.robot_id, episode_prefix(step.robot_id, step.episode_id)))
                        else:
                            dups += 1
                    for spec in specs:
                        txn.put(spec.robot_id.encode(), spec.SerializeToString(), db=self._specs)
                    if dups:
                        txn.put(b"duplicates", _U64.pack(self._duplicates + dups), db=self._meta)
            except lmdb.MapFullError as exc:
                raise ReplayFullError(
                    f"replay store {self.path} is full (map_size_mb={self.map_size_mb}); raise replay.map_size_mb"
                ) from exc
            # Committed: only now may samples see these steps.
            with self._index_lock:
                for robot, key in sampleable:
                    self._pools.setdefault(robot, []).append(key)
                for robot, prefix in stored:
                    self._steps_per_robot[robot] = self._steps_per_robot.get(robot, 0) + 1
                    self._episodes.add(prefix)
                self._n_steps += len(stored)
                self._duplicates += dups
        return len(stored), dups

    def _put_one(self, txn: lmdb.Transaction, step: step_pb2.Step, sampleable: list[tuple[str, bytes]]) -> bool:
        """Put one step unless its key exists; note which transitions its arrival completes."""
        rid, eid, t = step.robot_id, step.episode_id, step.step_index
        key = step_key(rid, eid, t)
        if not txn.put(key, step.SerializeToString(), db=self._steps, overwrite=False):
            return False
        if step.HasField("final_observation"):  # validated: only the last step carries one
            txn.put(key, b"", db=self._ends)
            sampleable.append((rid, key))
        elif txn.get(step_key(rid, eid, t + 1), db=self._steps) is not None:
            sampleable.append((rid, key))  # its successor arrived first (re-sent out of order)
        if t > 0:
            prev = step_key(rid, eid, t - 1)
            # prev waited for this observation, unless it ended an episode (then it was sampleable already)
            if txn.get(prev, db=self._steps) is not None and txn.get(prev, db=self._ends) is None:
                sampleable.append((rid, prev))
        return True

    def put_spec(self, spec: robot_pb2.RobotSpec) -> None:
        with self._write_lock:
            self._check_open()
            with self.env.begin(write=True, db=self._specs) as txn:
                txn.put(spec.robot_id.encode(), spec.SerializeToString())

    def get_spec(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        self._check_open()
        with self.env.begin(db=self._specs) as txn:
            raw = txn.get(robot_id.encode())
        return None if raw is None else robot_pb2.RobotSpec.FromString(raw)

    # ------------------------------------------------------------------ reads

    @property
    def transitions(self) -> int:
        with self._index_lock:
            return sum(len(p) for p in self._pools.values())

    def transitions_for(self, robot_ids: list[str] | None = None) -> int:
        with self._index_lock:
            if not robot_ids:
                return sum(len(p) for p in self._pools.values())
            return sum(len(self._pools.get(r, ())) for r in set(robot_ids))

    def _draw(self, batch_size: int, rng: np.random.Generator, robot_ids: list[str] | None) -> list[bytes]:
        """Uniform over the sampleable transitions of the robots asked for, with replacement."""
        with self._index_lock:
            names = sorted(set(robot_ids)) if robot_ids else sorted(self._pools)
            pools = [self._pools[r] for r in names if self._pools.get(r)]
            sizes = np.array([len(p) for p in pools], dtype=np.int64)
        total = int(sizes.sum()) if len(sizes) else 0
        if total == 0:
            which = f" for robots {sorted(set(robot_ids))}" if robot_ids else ""
            raise EmptyBufferError(f"no sampleable transitions{which} yet")
        picks = rng.integers(0, total, size=batch_size)
        if len(pools) == 1:
            pool = pools[0]
            return [pool[i] for i in picks.tolist()]
        # Pools only grow, so indices below the sizes read under the lock stay valid.
        ends = np.cumsum(sizes)
        owner = np.searchsorted(ends, picks, side="right")
        local = picks - (ends[owner] - sizes[owner])
        return [pools[o][i] for o, i in zip(owner.tolist(), local.tolist(), strict=True)]

    def _decoded(self, txn: lmdb.Transaction, key: bytes) -> _Decoded:
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        raw = txn.get(key, db=self._steps)
        if raw is None:
            raise ReplayError(f"index points at a missing step {key!r}")
        item = _Decoded.parse(raw, self._layouts)
        self._cache.put(key, item)
        return item

    def sample(self, batch_size: int, rng: np.random.Generator, robot_ids: list[str] | None = None) -> dict[str, Any]:
        """A ready-to-train batch of stacked numpy arrays (see module doc for next_observation)."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        keys = self._draw(batch_size, rng, robot_ids)
        rows: list[tuple[_Decoded, dict[str, bytes], Layout]] = []
        with self._sample_lock:
            self._check_open()
            with self.env.begin(db=self._steps) as txn:
                for key in keys:
                    cur = self._decoded(txn, key)
                    if cur.final_observation is not None:
                        rows.append((cur, cur.final_observation, cur.layout))
                    else:
                        prefix, t = split_key(key)
                        nxt = self._decoded(txn, prefix + _INDEX.pack(t + 1))
                        rows.append((cur, nxt.observation, nxt.layout))
        return self._stack(rows, keys)

    @staticmethod
    def _stack(rows: list[tuple[_Decoded, dict[str, bytes], Layout]], keys: list[bytes]) -> dict[str, Any]:
        layout = rows[0][0].layout
        for i, (cur, _, nxt_layout) in enumerate(rows):
            if cur.layout is not layout or nxt_layout is not layout:
                raise LayoutError(
                    f"sampled transitions have different observation layouts ({keys[0][:-8]!r} vs "
                    f"{keys[i][:-8]!r}); sample robots with different specs separately (robot_ids)"
                )
        features, (act_dtype, act_shape) = layout
        n = len(rows)

        def column(parts: list[bytes], dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
            # one copy into a writable buffer, viewed as (B, *shape)
            return np.frombuffer(bytearray().join(parts), dtype=dtype).reshape((n, *shape))

        return {
            "observation": {f: column([c.observation[f] for c, _, _ in rows], dt, sh) for f, dt, sh in features},
            "next_observation": {f: column([x[f] for _, x, _ in rows], dt, sh) for f, dt, sh in features},
            "action": column([c.action for c, _, _ in rows], act_dtype, act_shape).astype(np.float32, copy=False),
            "reward": np.fromiter((c.reward for c, _, _ in rows), dtype=np.float32, count=n),
            "terminated": np.fromiter((c.terminated for c, _, _ in rows), dtype=bool, count=n),
            "truncated": np.fromiter((c.truncated for c, _, _ in rows), dtype=bool, count=n),
            "intervention": np.fromiter((c.intervention for c, _, _ in rows), dtype=bool, count=n),
            "policy_version": np.fromiter((c.policy_version for c, _, _ in rows), dtype=np.int64, count=n),
        }

    def bytes_on_disk(self) -> int:
        """Bytes of LMDB pages in use in data.mdb (the map itself is sparse)."""
        self._check_open()
        return (self.env.info()["last_pgno"] + 1) * self.env.stat()["psize"]

    def stats(self) -> dict[str, Any]:
        on_disk = self.bytes_on_disk()
        with self._index_lock:
            return {
                "steps": self._n_steps,
                "transitions": sum(len(p) for p in self._pools.values()),
                "episodes": len(self._episodes),
                "bytes_on_disk": on_disk,
                "steps_per_robot": dict(self._steps_per_robot),
                "duplicates": self._duplicates,
            }

    def cache_info(self) -> dict[str, int]:
        with self._sample_lock:
            c = self._cache
            return {"entries": len(c), "bytes": c.bytes, "hits": c.hits, "misses": c.misses}

    def close(self) -> None:
        """Idempotent; waits for a commit or sample in progress."""
        with self._write_lock, self._sample_lock:
            if self._closed:
                return
            self._closed = True
            self.env.sync(True)
            self.env.close()
