"""Control's durable state in one SQLite file: robots (spec, owner, last status), every finished episode,
and workers. A restarted control knows every robot (offline until its edge reconnects), its episode
history and the GPU pool; leases are not persisted, a live edge simply registers again.

Rows hold serialized protos (the wire types are the schema); writes happen at registration, at the end of
a lease, when episodes arrive and when a worker reports, never per heartbeat, so the file stays quiet.
"""

from __future__ import annotations

import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path

from user.v1 import control_pb2, robot_pb2

SCHEMA = """
CREATE TABLE IF NOT EXISTS robots (
  robot_id TEXT PRIMARY KEY, spec BLOB NOT NULL, agent_id TEXT NOT NULL, hostname TEXT NOT NULL,
  registered_at_ns INTEGER NOT NULL, last_heartbeat_ns INTEGER NOT NULL, status BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS episodes (
  seq INTEGER PRIMARY KEY AUTOINCREMENT, robot_id TEXT NOT NULL, episode_id TEXT NOT NULL,
  summary BLOB NOT NULL, UNIQUE (robot_id, episode_id)
);
CREATE TABLE IF NOT EXISTS workers (worker_id TEXT PRIMARY KEY, info BLOB NOT NULL);
"""


@dataclass
class SavedRobot:
    spec: robot_pb2.RobotSpec
    agent_id: str
    hostname: str
    registered_at_ns: int
    last_heartbeat_ns: int
    status: control_pb2.RobotStatus
    episodes: list[control_pb2.EpisodeSummary]


class ControlState:
    """SQLite-backed (WAL, synchronous=NORMAL: a power cut may lose the last commit, never corrupt)."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        self._closed = False
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(SCHEMA)

    def load_robots(self, episodes_kept: int) -> list[SavedRobot]:
        with self._lock:
            rows = self._db.execute("SELECT * FROM robots ORDER BY robot_id").fetchall()
            out = []
            for rid, spec, agent_id, hostname, reg_ns, hb_ns, status in rows:
                eps = self._db.execute(
                    "SELECT summary FROM episodes WHERE robot_id = ? ORDER BY seq DESC LIMIT ?", (rid, episodes_kept)
                ).fetchall()
                out.append(
                    SavedRobot(
                        robot_pb2.RobotSpec.FromString(spec),
                        agent_id,
                        hostname,
                        reg_ns,
                        hb_ns,
                        control_pb2.RobotStatus.FromString(status),
                        [control_pb2.EpisodeSummary.FromString(e) for (e,) in reversed(eps)],
                    )
                )
        return out

    def save_robot(
        self,
        spec: robot_pb2.RobotSpec,
        agent_id: str,
        hostname: str,
        registered_at_ns: int,
        last_heartbeat_ns: int,
        status: control_pb2.RobotStatus,
    ) -> None:
        with self._lock:
            if self._closed:  # a stream still ending after stop(): its state was saved at close
                return
            self._db.execute(
                "INSERT OR REPLACE INTO robots VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    spec.robot_id,
                    spec.SerializeToString(),
                    agent_id,
                    hostname,
                    registered_at_ns,
                    last_heartbeat_ns,
                    status.SerializeToString(),
                ),
            )

    def add_episodes(self, episodes: list[control_pb2.EpisodeSummary]) -> None:
        """Idempotent: an episode re-sent after a broken stream is stored once."""
        if not episodes:
            return
        with self._lock:
            if self._closed:
                return
            self._db.executemany(
                "INSERT OR IGNORE INTO episodes (robot_id, episode_id, summary) VALUES (?, ?, ?)",
                [(e.robot_id, e.episode_id, e.SerializeToString()) for e in episodes],
            )

    def episode_count(self, robot_id: str) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM episodes WHERE robot_id = ?", (robot_id,)).fetchone()[0]

    def load_workers(self) -> list[control_pb2.WorkerInfo]:
        with self._lock:
            rows = self._db.execute("SELECT info FROM workers ORDER BY worker_id").fetchall()
        return [control_pb2.WorkerInfo.FromString(info) for (info,) in rows]

    def save_worker(self, info: control_pb2.WorkerInfo) -> None:
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO workers VALUES (?, ?)", (info.worker_id, info.SerializeToString()))

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._db.close()
