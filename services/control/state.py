"""Control's durable state in one SQLite file: robots (spec, owner, last status), every finished episode
(with the experiment it ran in), workers, experiments (running or stopped, and the definitions of those
defined at run time), each robot's last lease and
the command history. A restarted control knows every robot (offline until its edge reconnects), its
episode history, the GPU pool, which experiments run and every command it sent with the results edges
reported; a live edge registers again and gets its lease back (the last holder is preferred at max_robots).

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
CREATE TABLE IF NOT EXISTS experiments (
  name TEXT PRIMARY KEY, running INTEGER NOT NULL, started_at_ns INTEGER NOT NULL, stopped_at_ns INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS leases (robot_id TEXT PRIMARY KEY, experiment TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS defined_experiments (
  seq INTEGER PRIMARY KEY AUTOINCREMENT, name TEXT NOT NULL UNIQUE, definition TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS removed_experiments (name TEXT PRIMARY KEY, removed_at_ns INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS commands (command_id TEXT PRIMARY KEY, seq INTEGER NOT NULL, status BLOB NOT NULL);
"""
# Columns added to `episodes` after the first release (older files get them with these defaults).
EPISODE_COLUMNS = {
    "experiment": "TEXT NOT NULL DEFAULT ''",
    "success": "INTEGER NOT NULL DEFAULT 0",
    "episode_return": "REAL NOT NULL DEFAULT 0",
    "intervention_steps": "INTEGER NOT NULL DEFAULT 0",  # success without human help counts the 0 rows
}


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
            have = {row[1] for row in self._db.execute("PRAGMA table_info(episodes)")}
            for name, decl in EPISODE_COLUMNS.items():
                if name not in have:
                    self._db.execute(f"ALTER TABLE episodes ADD COLUMN {name} {decl}")
            if "intervention_steps" not in have:
                self._backfill_interventions()

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

    def _backfill_interventions(self) -> None:
        """A file from before the column: its episodes' intervention steps come from their stored summaries."""
        rows = self._db.execute("SELECT seq, summary FROM episodes").fetchall()
        helped = []
        for seq, blob in rows:
            steps = control_pb2.EpisodeSummary.FromString(blob).intervention_steps
            if steps:
                helped.append((steps, seq))
        self._db.executemany("UPDATE episodes SET intervention_steps = ? WHERE seq = ?", helped)

    def add_episodes(self, episodes: list[control_pb2.EpisodeSummary], experiment: str = "") -> None:
        """Idempotent: an episode re-sent after a broken stream is stored once."""
        if not episodes:
            return
        with self._lock:
            if self._closed:
                return
            self._db.executemany(
                "INSERT OR IGNORE INTO episodes"
                " (robot_id, episode_id, summary, experiment, success, episode_return, intervention_steps)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                [
                    (
                        e.robot_id,
                        e.episode_id,
                        e.SerializeToString(),
                        experiment,
                        int(e.success),
                        e.episode_return,
                        e.intervention_steps,
                    )
                    for e in episodes
                ],
            )

    def episode_totals(self) -> list[tuple[str, str, int, int, float, int, int]]:
        """(experiment, robot_id, episodes, successes, sum of returns, episodes without interventions,
        successes among those) over the whole history."""
        with self._lock:
            return self._db.execute(
                "SELECT experiment, robot_id, COUNT(*), SUM(success), SUM(episode_return),"
                " SUM(intervention_steps = 0), SUM(success AND intervention_steps = 0) FROM episodes"
                " GROUP BY experiment, robot_id"
            ).fetchall()

    # ------------------------------------------------------------------ experiments, leases, commands

    def load_experiments(self) -> dict[str, tuple[bool, int, int]]:
        """name -> (running, started_at_ns, stopped_at_ns)."""
        with self._lock:
            rows = self._db.execute("SELECT name, running, started_at_ns, stopped_at_ns FROM experiments").fetchall()
        return {name: (bool(running), started, stopped) for name, running, started, stopped in rows}

    def save_experiment(self, name: str, running: bool, started_at_ns: int, stopped_at_ns: int) -> None:
        with self._lock:
            if not self._closed:
                self._db.execute(
                    "INSERT OR REPLACE INTO experiments VALUES (?, ?, ?, ?)",
                    (name, int(running), started_at_ns, stopped_at_ns),
                )

    def load_definitions(self) -> list[str]:
        """Experiments defined at run time (DefineExperiment), as ExperimentConfig JSON, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT definition FROM defined_experiments ORDER BY seq").fetchall()
        return [row[0] for row in rows]

    def save_definition(self, name: str, definition_json: str) -> None:
        with self._lock:
            if not self._closed:
                self._db.execute(
                    "INSERT INTO defined_experiments (name, definition) VALUES (?, ?)", (name, definition_json)
                )

    def remove_definition(self, name: str, removed_at_ns: int) -> None:
        """RemoveExperiment: the definition and run state go; the name stays taken (its history keeps it)."""
        with self._lock:
            if not self._closed:
                self._db.execute("BEGIN")  # all three or none (autocommit otherwise)
                try:
                    self._db.execute("DELETE FROM defined_experiments WHERE name = ?", (name,))
                    self._db.execute("DELETE FROM experiments WHERE name = ?", (name,))
                    self._db.execute("INSERT OR REPLACE INTO removed_experiments VALUES (?, ?)", (name, removed_at_ns))
                except BaseException:
                    self._db.execute("ROLLBACK")
                    raise
                self._db.execute("COMMIT")

    def load_removed(self) -> set[str]:
        """Names of experiments removed by RemoveExperiment (never defined again)."""
        with self._lock:
            return {row[0] for row in self._db.execute("SELECT name FROM removed_experiments").fetchall()}

    def load_leases(self) -> dict[str, str]:
        """robot_id -> the experiment it was last leased to."""
        with self._lock:
            return dict(self._db.execute("SELECT robot_id, experiment FROM leases").fetchall())

    def save_lease(self, robot_id: str, experiment: str) -> None:
        with self._lock:
            if not self._closed:
                self._db.execute("INSERT OR REPLACE INTO leases VALUES (?, ?)", (robot_id, experiment))

    def load_commands(self, kept: int) -> list[control_pb2.CommandStatus]:
        """The newest `kept` commands, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT status FROM commands ORDER BY seq DESC LIMIT ?", (kept,)).fetchall()
        return [control_pb2.CommandStatus.FromString(s) for (s,) in reversed(rows)]

    def save_command(self, status: control_pb2.CommandStatus, kept: int) -> None:
        """Insert or update (results arrive later); the history keeps the newest `kept`."""
        cid = status.command.command_id
        with self._lock:
            if self._closed:
                return
            row = self._db.execute("SELECT seq FROM commands WHERE command_id = ?", (cid,)).fetchone()
            if row is not None:
                blob = status.SerializeToString()
                self._db.execute("UPDATE commands SET status = ? WHERE command_id = ?", (blob, cid))
                return
            top = self._db.execute("SELECT COALESCE(MAX(seq), 0) FROM commands").fetchone()[0]
            self._db.execute("INSERT INTO commands VALUES (?, ?, ?)", (cid, top + 1, status.SerializeToString()))
            self._db.execute("DELETE FROM commands WHERE seq <= ?", (top + 1 - kept,))

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
