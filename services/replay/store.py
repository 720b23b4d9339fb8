"""The persistent replay buffer: LMDB on disk, an index of sampleable transitions in memory.

Layout (one LMDB environment, named databases):
  steps: b"<robot_id>/<episode_id>/" + big-endian uint64 step_index -> flag byte + serialized Step
  specs: robot_id -> serialized RobotSpec
Keys sort by robot, episode and step, so an episode's steps are adjacent and a re-sent step hits
the same key (stored once). Step t's next observation is step t+1's observation (or t's
final_observation when t ends the episode): no observation is stored twice.
"""

from __future__ import annotations

import struct
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import lmdb
import numpy as np

from user import wire
from user.v1 import robot_pb2, step_pb2

LAST_STEP = 1  # flag bit: terminated or truncated; final_observation is inside
_INDEX = struct.Struct(">Q")


class EmptyBufferError(RuntimeError):
    """Nothing sampleable yet."""


def episode_prefix(robot_id: str, episode_id: str) -> bytes:
    return f"{robot_id}/{episode_id}/".encode()


def step_key(robot_id: str, episode_id: str, step_index: int) -> bytes:
    return episode_prefix(robot_id, episode_id) + _INDEX.pack(step_index)


def _split(key: bytes) -> tuple[bytes, int]:
    return key[:-8], _INDEX.unpack(key[-8:])[0]


def _robot_of(key: bytes) -> str:
    return key[: key.index(b"/")].decode()


class _Decoded:
    """A step decoded once and kept in the LRU cache."""

    __slots__ = (
        "action",
        "final_observation",
        "intervention",
        "observation",
        "policy_version",
        "reward",
        "terminated",
        "truncated",
    )

    def __init__(self, step: step_pb2.Step) -> None:
        self.observation = wire.from_tensor_map(step.observation)
        self.final_observation = (
            wire.from_tensor_map(step.final_observation) if step.final_observation.tensors else None
        )
        self.action = wire.from_tensor(step.action)
        self.reward = step.reward
        self.terminated = step.terminated
        self.truncated = step.truncated
        self.intervention = step.intervention
        self.policy_version = step.policy_version


class ReplayStore:
    def __init__(self, path: str | Path, map_size_mb: int = 4096, cache_steps: int = 200_000) -> None:
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.env = lmdb.open(str(self.path), map_size=map_size_mb << 20, max_dbs=4, subdir=True)
        self._steps = self.env.open_db(b"steps")
        self._specs = self.env.open_db(b"specs")
        self._lock = threading.Lock()
        self._cache: OrderedDict[bytes, _Decoded] = OrderedDict()
        self._cache_steps = cache_steps
        self._sampleable: list[bytes] = []
        self._by_robot: dict[str, list[bytes]] = {}
        self._episodes: set[bytes] = set()
        self._steps_per_robot: dict[str, int] = {}
        self.duplicates = 0
        self._rebuild_index()

    # ------------------------------------------------------------------ index

    def _mark_sampleable(self, key: bytes) -> None:
        self._sampleable.append(key)
        self._by_robot.setdefault(_robot_of(key), []).append(key)

    def _rebuild_index(self) -> None:
        """Scan keys once at open, so a restarted service samples everything it had."""
        with self.env.begin(db=self._steps) as txn:
            prev_key, prev_flag = None, 0
            for key, value in txn.cursor():
                key = bytes(key)
                prefix, index = _split(key)
                self._episodes.add(prefix)
                robot = _robot_of(key)
                self._steps_per_robot[robot] = self._steps_per_robot.get(robot, 0) + 1
                if prev_key is not None and not prev_flag & LAST_STEP:
                    p_prefix, p_index = _split(prev_key)
                    if p_prefix == prefix and p_index + 1 == index:
                        self._mark_sampleable(prev_key)
                if value[0] & LAST_STEP:
                    self._mark_sampleable(key)
                prev_key, prev_flag = key, value[0]

    # ------------------------------------------------------------------ writes

    def put_steps(self, steps: list[step_pb2.Step]) -> tuple[int, int]:
        """Store validated steps in ONE transaction; returns (stored, duplicates) after commit."""
        dups = 0
        stored_robots: list[str] = []
        new_sampleable: list[bytes] = []
        with self._lock:
            with self.env.begin(write=True, db=self._steps) as txn:
                for step in steps:
                    key = step_key(step.robot_id, step.episode_id, step.step_index)
                    last = step.terminated or step.truncated
                    value = bytes([LAST_STEP if last else 0]) + step.SerializeToString()
                    if not txn.put(key, value, overwrite=False):
                        dups += 1
                        continue
                    stored_robots.append(step.robot_id)
                    if last:
                        new_sampleable.append(key)
                    elif txn.get(step_key(step.robot_id, step.episode_id, step.step_index + 1)) is not None:
                        new_sampleable.append(key)  # its successor arrived first (re-sent out of order)
                    if step.step_index > 0:
                        prev = step_key(step.robot_id, step.episode_id, step.step_index - 1)
                        pv = txn.get(prev)
                        if pv is not None and not pv[0] & LAST_STEP:
                            new_sampleable.append(prev)
            # Committed: only now does the index (and so sampling) see the steps.
            for key in new_sampleable:
                self._mark_sampleable(key)
            for step in steps:
                self._episodes.add(episode_prefix(step.robot_id, step.episode_id))
            for robot in stored_robots:
                self._steps_per_robot[robot] = self._steps_per_robot.get(robot, 0) + 1
            self.duplicates += dups
        return len(stored_robots), dups

    def put_spec(self, spec: robot_pb2.RobotSpec) -> None:
        with self.env.begin(write=True, db=self._specs) as txn:
            txn.put(spec.robot_id.encode(), spec.SerializeToString())

    def get_spec(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        with self.env.begin(db=self._specs) as txn:
            raw = txn.get(robot_id.encode())
        return None if raw is None else robot_pb2.RobotSpec.FromString(raw)

    # ------------------------------------------------------------------ reads

    def _decoded(self, txn: lmdb.Transaction, key: bytes) -> _Decoded:
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        raw = txn.get(key, db=self._steps)
        if raw is None:
            raise KeyError(key)
        dec = _Decoded(step_pb2.Step.FromString(raw[1:]))
        self._cache[key] = dec
        if len(self._cache) > self._cache_steps:
            self._cache.popitem(last=False)
        return dec

    @property
    def transitions(self) -> int:
        return len(self._sampleable)

    def transitions_for(self, robot_ids: list[str] | None) -> int:
        if not robot_ids:
            return len(self._sampleable)
        return sum(len(self._by_robot.get(r, ())) for r in robot_ids)

    def sample(self, batch_size: int, rng: np.random.Generator, robot_ids: list[str] | None = None) -> dict[str, Any]:
        """Uniform (with replacement) over sampleable transitions; stacked numpy arrays."""
        with self._lock:
            if robot_ids:
                pools = [self._by_robot.get(r, []) for r in robot_ids]
                flat = [k for pool in pools for k in pool]
            else:
                flat = self._sampleable
            if not flat:
                raise EmptyBufferError("no sampleable transitions" + (f" for {robot_ids}" if robot_ids else ""))
            keys = [flat[i] for i in rng.integers(0, len(flat), size=batch_size)]
            with self.env.begin(db=self._steps) as txn:
                rows = []
                for key in keys:
                    cur = self._decoded(txn, key)
                    if cur.final_observation is not None:
                        nxt = cur.final_observation
                    else:
                        prefix, index = _split(key)
                        nxt = self._decoded(txn, prefix + _INDEX.pack(index + 1)).observation
                    rows.append((cur, nxt))
        names = list(rows[0][0].observation)
        return {
            "observation": {n: np.stack([c.observation[n] for c, _ in rows]) for n in names},
            "next_observation": {n: np.stack([x[n] for _, x in rows]) for n in names},
            "action": np.stack([c.action for c, _ in rows]).astype(np.float32),
            "reward": np.array([c.reward for c, _ in rows], dtype=np.float32),
            "terminated": np.array([c.terminated for c, _ in rows], dtype=bool),
            "truncated": np.array([c.truncated for c, _ in rows], dtype=bool),
            "intervention": np.array([c.intervention for c, _ in rows], dtype=bool),
            "policy_version": np.array([c.policy_version for c, _ in rows], dtype=np.int64),
        }

    def stats(self) -> dict[str, Any]:
        with self._lock:
            with self.env.begin(db=self._steps) as txn:
                steps = txn.stat(self._steps)["entries"]
            info = self.env.info()
            return {
                "steps": steps,
                "transitions": len(self._sampleable),
                "episodes": len(self._episodes),
                "bytes_on_disk": (info["last_pgno"] + 1) * self.env.stat()["psize"],
                "steps_per_robot": dict(self._steps_per_robot),
                "duplicates": self.duplicates,
            }

    def close(self) -> None:
        with self._lock:
            self.env.sync(True)
            self.env.close()
