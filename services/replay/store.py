"""The replay buffer: LMDB is the durable truth (disk.py), RAM holds what sampling needs.

- disk.StepDB: every step, acknowledged only after its transaction committed; idempotent keys.
- tables.Index: every sampleable transition's id, robot, table(s), scalars and priority.
- hot.HotGroup: the most recent transitions as contiguous columns (frames stored once as uint8);
  a sampled transition that has left the hot tier is read from LMDB (a miss).

Step t is sampleable once its next observation exists (step t+1's observation, or its own
final_observation when it ends the episode), in any arrival order. Capacity is by bytes: when the
stored steps exceed capacity_mb, whole episodes leave, oldest first (FIFO), from LMDB and RAM.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.replay.disk import (
    ENDS,
    INTERVENTION,
    ONLINE,
    SUCCESS,
    TERMINATED,
    TRUNCATED,
    ReplayError,
    ReplayFullError,
    StepDB,
    StoreClosedError,
    episode_prefix,
    next_key,
    robot_of,
    split_key,
)
from services.replay.hot import HotGroup, Layout
from services.replay.tables import INTERVENTIONS, Draw, EmptyBufferError, Index
from user import wire
from user.log import kv
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

__all__ = [
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
MAX_OPEN_TAILS = 100_000  # steps waiting for their successor, kept to place transitions in the hot tier


class LayoutError(ReplayError):
    """Sampled transitions do not share one observation layout (robots with different specs)."""


def tensor_array(tensor: tpb.Tensor) -> np.ndarray:
    """Stored tensors were validated on insert: RAW data is viewed as is, other encodings decoded."""
    if tensor.encoding == tpb.ENCODING_RAW:
        return np.frombuffer(tensor.data, dtype=wire.dtype_from_proto(tensor.dtype)).reshape(tuple(tensor.shape))
    return wire.from_tensor(tensor)


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
    tids: list[int] = field(default_factory=list)


@dataclass(slots=True)
class _Tail:
    """A stored step waiting for its successor's observation."""

    group: int
    seq: int  # its observation's frame
    action: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    intervention: bool
    policy_version: int
    final_seq: int = -1


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
    ) -> None:
        self.path = Path(path)
        self.hot_bytes = int(cache_mb) << 20
        self.capacity_bytes = int(capacity_mb) << 20  # 0 = no limit but the map
        self._write_lock = threading.Lock()  # one writer; also guards close()
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
        self._n_steps = 0
        self._bytes = 0
        self._evicted_episodes = 0
        self.hits = self.misses = 0
        self.generation = 0  # bumps when a commit or an eviction changes what can be sampled
        self.inserted = 0  # steps stored by this process (the rate limiter's insert count)
        self._closed = False
        try:
            self._rebuild()
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
        tables = self.db.episode_tables()
        found: list[tuple[int, bytes, tuple[float, int, int, int, int]]] = []
        firsts: dict[bytes, int] = {}
        prev: tuple[bytes, int, tuple[float, int, int, int, int]] | None = None
        for key, sc in self.db.scan():
            prefix, t = split_key(key)
            ep = self._episodes.get(prefix)
            if ep is None:
                ep = self._episodes[prefix] = Episode(robot_of(prefix), tables.get(prefix, ONLINE))
                firsts[prefix] = sc[3]
            firsts[prefix] = min(firsts[prefix], sc[3])
            ep.steps += 1
            ep.nbytes += sc[4] + len(key)
            ep.success |= bool(sc[1] & SUCCESS)
            ep.interventions += bool(sc[1] & INTERVENTION)
            self._n_steps += 1
            self._bytes += sc[4] + len(key)
            if prev is not None and prev[0][:-8] == prefix and prev[1] == t - 1 and not prev[2][1] & ENDS:
                found.append((max(prev[2][3], sc[3]), prev[0], prev[2]))
            if sc[1] & ENDS:
                found.append((sc[3], key, sc))
            prev = (key, t, sc)
            self.db.arrival = max(self.db.arrival, sc[3] + 1)
        self._episodes = dict(sorted(self._episodes.items(), key=lambda kv_: firsts[kv_[0]]))
        for _, key, sc in sorted(found):
            prefix = key[:-8]
            ep = self._episodes[prefix]
            tid = self.index.add(
                key,
                ep.robot,
                ep.table,
                reward=sc[0],
                terminated=bool(sc[1] & TERMINATED),
                truncated=bool(sc[1] & TRUNCATED),
                intervention=bool(sc[1] & INTERVENTION),
                policy_version=sc[2],
                group=-1,
            )
            ep.tids.append(tid)

    # ------------------------------------------------------------------ writes

    def _check_open(self) -> None:
        if self._closed:
            raise StoreClosedError(f"replay store {self.path} is closed")

    def _group(self, layout: Layout) -> int:
        gid = self._layout_ids.get(layout)
        if gid is None:
            gid = self._layout_ids[layout] = len(self._groups)
            self._groups.append(HotGroup(layout, self.hot_bytes))
        return gid

    def put_steps(
        self,
        steps: list[step_pb2.Step],
        specs: Iterable[robot_pb2.RobotSpec] = (),
        table: str | list[str] = ONLINE,
    ) -> tuple[int, int]:
        """Store validated steps (and specs) in ONE transaction; (stored, duplicates) once it has committed."""
        with self._write_lock:
            self._check_open()
            done = self.db.put_steps(steps, table, specs)
            # Committed: only now may samples see these steps.
            with self._lock:
                self._index_committed(done.stored, done.sampleable)
                self.inserted += len(done.stored)
                self.generation += bool(done.stored)
            self._evict_over_capacity()
        return len(done.stored), done.duplicates

    def _index_committed(self, stored: list[tuple[bytes, step_pb2.Step, int, str]], sampleable: list[bytes]) -> None:
        for key, step, nbytes, table in stored:
            prefix = key[:-8]
            ep = self._episodes.get(prefix)
            if ep is None:
                ep = self._episodes[prefix] = Episode(step.robot_id, table)
            ep.steps += 1
            ep.nbytes += nbytes + len(key)
            ep.success |= step.success
            ep.interventions += step.intervention
            self._n_steps += 1
            self._bytes += nbytes + len(key)
            if self.hot_bytes <= 0:
                continue
            gid = self._group(layout_of(step))
            self._robot_group.setdefault(step.robot_id, gid)
            group = self._groups[gid]
            tail = _Tail(
                gid,
                group.write_frame(arrays_of(step.observation)),
                tensor_array(step.action),
                step.reward,
                step.terminated,
                step.truncated,
                step.intervention,
                step.policy_version,
            )
            if step.HasField("final_observation"):
                tail.final_seq = group.write_frame(arrays_of(step.final_observation))
            if len(self._tails) >= MAX_OPEN_TAILS:  # successors that never came: forget the oldest
                self._tails.pop(next(iter(self._tails)))
            self._tails[key] = tail
        for key in sampleable:
            tail = self._tails.get(key)
            nxt = None if tail is None or tail.final_seq >= 0 else self._tails.get(next_key(key))
            ep = self._episodes[key[:-8]]
            if tail is not None and (tail.final_seq >= 0 or (nxt is not None and nxt.group == tail.group)):
                tid = len(self.index.keys)
                next_seq = tail.final_seq if tail.final_seq >= 0 else nxt.seq  # type: ignore[union-attr]
                row = self._groups[tail.group].add(tid, tail.seq, next_seq, tail.action)
                self.index.add(
                    key,
                    ep.robot,
                    ep.table,
                    reward=tail.reward,
                    terminated=tail.terminated,
                    truncated=tail.truncated,
                    intervention=tail.intervention,
                    policy_version=tail.policy_version,
                    group=tail.group,
                    hot_row=row,
                )
            else:  # completed out of order or after a restart: its data stays in LMDB
                step = self._read([key])[0]
                tid = self.index.add(
                    key,
                    ep.robot,
                    ep.table,
                    reward=step.reward,
                    terminated=step.terminated,
                    truncated=step.truncated,
                    intervention=step.intervention,
                    policy_version=step.policy_version,
                    group=-1,
                )
            ep.tids.append(tid)
        for key in sampleable:  # their transitions are indexed; a successor finds its frame in the ring
            self._tails.pop(key, None)

    def _evict_over_capacity(self) -> None:
        """Whole episodes, oldest first, until the stored bytes fit capacity_mb again (with 5% slack)."""
        if not self.capacity_bytes or self._bytes <= self.capacity_bytes:
            return
        target = int(self.capacity_bytes * 0.95)
        with self._lock:
            victims: list[bytes] = []
            freed = 0
            for prefix, ep in self._episodes.items():
                if self._bytes - freed <= target or len(victims) == len(self._episodes) - 1:
                    break
                victims.append(prefix)
                freed += ep.nbytes
        if not victims:
            return
        self.db.delete_episodes(victims)
        with self._lock:
            tids: list[int] = []
            for prefix in victims:
                ep = self._episodes.pop(prefix)
                tids += ep.tids
                self._n_steps -= ep.steps
                self._bytes -= ep.nbytes
            self.index.evict(tids)
            self._evicted_episodes += len(victims)
            self.generation += 1
        log.info("evicted episodes", extra=kv(episodes=len(victims), bytes=freed))

    def put_spec(self, spec: robot_pb2.RobotSpec) -> None:
        with self._write_lock:
            self._check_open()
            self.db.put_spec(spec)

    def get_spec(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        self._check_open()
        with self._lock:
            return self.db.get_spec(robot_id)

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
            out: dict[str, Any] = {
                "reward": drawn.reward,
                "terminated": drawn.terminated,
                "truncated": drawn.truncated,
                "intervention": idx.intervention.a[tids],
                "policy_version": idx.policy_version.a[tids],
                "indices": tids,
                "weights": drawn.weights,
                "n_steps": drawn.n_steps,
            }
            gids = np.unique(np.concatenate([idx.group.a[tids], idx.group.a[last]]))
            hot = self._groups[int(gids[0])] if len(gids) == 1 and gids[0] >= 0 else None
            if hot is not None:
                rows, next_rows = idx.hot_row.a[tids], idx.hot_row.a[last]
                ok = hot.valid(rows, tids) & hot.valid(next_rows, last)
                if ok.all():
                    self.hits += len(tids)
                    out["observation"] = hot.observations(rows, "obs")
                    out["next_observation"] = hot.observations(next_rows, "next")
                    out["action"] = hot.action[rows].astype(np.float32, copy=False)
                    return out
            keys = [idx.keys[t] for t in tids.tolist()]
            next_keys = [idx.keys[t] for t in last.tolist()]
        return self._sample_cold(out, keys, next_keys)

    def _sample_cold(self, out: dict[str, Any], keys: list[bytes], last_keys: list[bytes]) -> dict[str, Any]:
        """Read the batch from LMDB (some or all of its transitions left the hot tier)."""
        self.misses += len(keys)
        uniq = sorted(set(keys) | set(last_keys) | {next_key(k) for k in last_keys})
        with self._lock:
            self._check_open()
            raws = dict(zip(uniq, self.db.get_many(uniq), strict=True))
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
        nxt_maps = []
        layout = layout_of(cur[0])
        for k in last_keys:
            s = step(k)
            nxt_maps.append(s.final_observation if s.HasField("final_observation") else step(next_key(k)).observation)
        for i, s in enumerate(cur):
            if layout_of(s) != layout:
                raise LayoutError(
                    f"sampled transitions have different observation layouts ({keys[0][:-8]!r} vs "
                    f"{keys[i][:-8]!r}); sample robots with different specs separately (robot_ids)"
                )
        features = layout[0]
        out["observation"] = {
            f: np.stack([tensor_array(s.observation.tensors[f]) for s in cur]) for f, _, _ in features
        }
        try:
            out["next_observation"] = {
                f: np.stack([tensor_array(m.tensors[f]) for m in nxt_maps]) for f, _, _ in features
            }
        except (KeyError, ValueError) as exc:
            raise LayoutError(f"sampled next observations do not match the layout: {exc}") from None
        out["action"] = np.stack([tensor_array(s.action) for s in cur]).astype(np.float32, copy=False)
        return out

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
            per_robot: dict[str, int] = {}
            for ep in self._episodes.values():
                per_robot[ep.robot] = per_robot.get(ep.robot, 0) + ep.steps
            return {
                "steps": self._n_steps,
                "transitions": len(self.index),
                "episodes": len(self._episodes),
                "bytes_on_disk": on_disk,
                "steps_per_robot": per_robot,
                "duplicates": self.db.duplicates,
            }

    def table_stats(self) -> dict[str, dict[str, Any]]:
        """Per table (and per robot within it): transitions, steps, episodes, bytes, success rate."""
        with self._lock:
            out: dict[str, dict[str, Any]] = {}

            def row(table: str, robot: str | None) -> dict[str, Any]:
                t = out.setdefault(table, {"transitions": 0, "steps": 0, "episodes": 0, "bytes": 0, "successes": 0})
                t.setdefault("robots", {})
                if robot is None:
                    return t
                return t["robots"].setdefault(
                    robot, {"transitions": 0, "steps": 0, "episodes": 0, "bytes": 0, "successes": 0}
                )

            for ep in self._episodes.values():
                for target in (row(ep.table, None), row(ep.table, ep.robot)):
                    target["steps"] += ep.steps
                    target["episodes"] += 1
                    target["bytes"] += ep.nbytes
                    target["successes"] += ep.success
            for name in self.index.tables:
                for code, grow in self.index.tables[name].items():
                    robot = self.index.robots[code]
                    row(name, None)["transitions"] += grow.n
                    row(name, robot)["transitions"] += grow.n
            for t in out.values():
                for r in [t, *t["robots"].values()]:
                    r["success_rate"] = r["successes"] / r["episodes"] if r["episodes"] else 0.0
            if INTERVENTIONS in out:  # its episodes and bytes belong to the tables they were inserted into
                out[INTERVENTIONS]["episodes"] = sum(e.interventions > 0 for e in self._episodes.values())
            return out

    def cache_info(self) -> dict[str, int]:
        with self._lock:
            return {
                "entries": sum(g.hot_transitions() for g in self._groups),
                "bytes": sum(g.resident_bytes() for g in self._groups),
                "capacity": sum(g.capacity for g in self._groups),
                "hits": self.hits,
                "misses": self.misses,
                "evicted_episodes": self._evicted_episodes,
                "stored_bytes": self._bytes,
            }

    def close(self) -> None:
        """Idempotent; waits for a commit or sample in progress."""
        with self._write_lock, self._lock:
            if self._closed:
                return
            self._closed = True
            self.db.close()
