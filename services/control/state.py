"""Control's durable state in one SQLite file: robots (spec, owner, last status), every finished episode
(with the experiment it ran in), workers, experiments (running or stopped, and the definitions of those
defined at run time), each robot's last lease and
the command history. A restarted control knows every robot (offline until its edge reconnects), its
episode history, the GPU pool, which experiments run and every command it sent with the results edges
reported; a live edge registers again and gets its lease back (the last holder is preferred at max_robots).
A forgotten robot (Control.ForgetRobot, control.forget_offline_after_days) leaves every table; its episodes stay
counted in `forgotten_totals`, per experiment, so an experiment's totals never drop. Workers offline for long are
deleted.

Rows hold serialized protos (the wire types are the schema); writes happen at registration, at the end of
a lease, when episodes arrive and when a worker reports, never per heartbeat, so the file stays quiet.

One control per file: `<state_path>.lock` is flocked (and names the holder's pid) for the control's life.
A write that fails (a full disk, an I/O error) never fails the caller: control serves from memory, the
write waits in order (a row rewritten meanwhile keeps only its newest value) and is retried with later
writes and by the reaper, at most every RETRY_S; user_control_persist_failing is 1 meanwhile. What waits
is lost only if control stops before the disk takes it.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import prometheus_client

from user import owner_lock
from user.config import ConfigError
from user.log import kv
from user.v1 import control_pb2, robot_pb2

log = logging.getLogger(__name__)

LOCK_SUFFIX = ".lock"  # <state_path>.lock: flocked by the control using the file; holds its pid
# Checkpoint the WAL into the file every 32 pages (~128 KiB; a commit writes a few pages): with the default
# (1000 pages, 4 MiB) the WAL took a small disk's free space, and what others freed later, before it was ever
# checkpointed; the checkpoint then needs room in the file that the WAL holds, and control stayed wedged.
WAL_AUTOCHECKPOINT_PAGES = 32
RETRY_S = 1.0  # while writes fail, how often they are tried again (each try costs a checkpoint attempt)
MAX_PENDING_EPISODES = 100_000  # episode summaries kept for a failing disk (~50 MB); the oldest go beyond

PERSIST_FAILING = prometheus_client.Gauge(
    "user_control_persist_failing",
    "1 while control.state_path cannot be written (disk full, I/O error): served from memory, writes retried",
)
PERSIST_FAILURES = prometheus_client.Counter(
    "user_control_persist_failures_total", "Attempts to write control's state that failed (retried later)"
)
PERSIST_PENDING = prometheus_client.Gauge(
    "user_control_persist_pending", "Writes of control's state waiting for the disk (lost if control stops)"
)
PERSIST_DROPPED = prometheus_client.Counter(
    "user_control_persist_dropped_total",
    f"Episode summaries never written: more than {MAX_PENDING_EPISODES} waited for a failing disk",
)

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
CREATE TABLE IF NOT EXISTS forgotten_totals (
  experiment TEXT PRIMARY KEY, episodes INTEGER NOT NULL, successes INTEGER NOT NULL, return_sum REAL NOT NULL,
  unhelped INTEGER NOT NULL, unhelped_successes INTEGER NOT NULL
);
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


Op = Callable[[sqlite3.Connection], object]
# Errors of one row (a bug, not the disk): that write is dropped, never retried.
ROW_ERRORS = (sqlite3.IntegrityError, sqlite3.DataError, sqlite3.ProgrammingError, sqlite3.InterfaceError)


@dataclass
class Pending:
    """A write waiting for the disk; `episodes`: summaries it carries (bounded by MAX_PENDING_EPISODES)."""

    op: Op
    episodes: int = 0


class StateInUse(ConfigError):
    """Another live control (or another ControlState of this process) holds the state file."""


def _why(exc: BaseException) -> str:
    return exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)


def lock_state(path: Path) -> int:
    """Take `path` for this process: an exclusive flock on <path>.lock, returned as its fd (closing it drops
    the lock; so does the kernel when the process dies, kill -9 included). Raises StateInUse naming the
    holder's pid, or ConfigError when the lock file cannot be made."""
    lock_path = Path(f"{path}{LOCK_SUFFIX}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return owner_lock.take(lock_path)
    except owner_lock.Held as held:
        raise StateInUse(f"control.state_path {path} is in use by pid {held.holder}") from None
    except OSError as exc:
        raise ConfigError(f"control.state_path {path}: cannot create {lock_path} ({_why(exc)})") from None


def _open_db(path: Path) -> sqlite3.Connection:
    db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        db.execute(f"PRAGMA wal_autocheckpoint={WAL_AUTOCHECKPOINT_PAGES}")
        db.executescript(SCHEMA)
        have = {row[1] for row in db.execute("PRAGMA table_info(episodes)")}
        for name, decl in EPISODE_COLUMNS.items():
            if name not in have:
                db.execute(f"ALTER TABLE episodes ADD COLUMN {name} {decl}")
        if "intervention_steps" not in have:
            _backfill_interventions(db)
    except BaseException:
        db.close()
        raise
    return db


def _backfill_interventions(db: sqlite3.Connection) -> None:
    """A file from before the column: its episodes' intervention steps come from their stored summaries."""
    rows = db.execute("SELECT seq, summary FROM episodes").fetchall()
    helped = []
    for seq, blob in rows:
        steps = control_pb2.EpisodeSummary.FromString(blob).intervention_steps
        if steps:
            helped.append((steps, seq))
    db.executemany("UPDATE episodes SET intervention_steps = ? WHERE seq = ?", helped)


class ControlState:
    """SQLite-backed (WAL, synchronous=NORMAL: a power cut may lose the last commit, never corrupt).
    Raises ConfigError (one line naming control.state_path) when the file is held or cannot be opened."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._closed = False
        self._pending: dict[tuple[str, str], Pending] = {}  # in write order; a key's rewrite keeps its place
        self._pending_episodes = 0
        self._seq = itertools.count()  # keys of writes that never replace one another
        self._failing = ""  # why the last write failed; "" while the disk takes writes
        self._next_try = 0.0  # monotonic: no try before this while failing
        self._dropping = False  # the drop of waiting episodes was logged (once per failing spell)
        self._owner = lock_state(path)
        try:
            self._db = _open_db(path)
        except (sqlite3.Error, OSError) as exc:
            os.close(self._owner)
            raise ConfigError(f"control.state_path {path}: cannot open the SQLite state ({_why(exc)})") from None
        PERSIST_FAILING.set(0)
        PERSIST_PENDING.set(0)

    # ------------------------------------------------------------------ writes that wait out a failing disk

    def _write(self, key: tuple[str, str] | None, op: Op, episodes: int = 0) -> None:
        """Queue `op` (replacing a waiting write of the same key) and write everything that waits, in order."""
        with self._lock:
            if self._closed:  # a stream still ending after stop(): its state was saved at close
                return
            key = key or ("once", str(next(self._seq)))
            old = self._pending.get(key)
            self._pending[key] = Pending(op, episodes)
            self._pending_episodes += episodes - (old.episodes if old else 0)
            self._bound_locked()
            self._flush_locked()

    def retry(self) -> None:
        """Write what waits for the disk (the reaper calls this: space may come back while nothing is written)."""
        with self._lock:
            if self._pending and not self._closed:
                self._flush_locked()

    def _flush_locked(self, force: bool = False) -> None:
        """Write what waits, unless it failed less than RETRY_S ago (then it waits on, with this write)."""
        if not self._failing or force or time.monotonic() >= self._next_try:
            self._try_locked()
        PERSIST_PENDING.set(len(self._pending))

    def _try_locked(self) -> None:
        if self._failing:  # space freed since: a checkpoint gives back what the WAL took first
            self._checkpoint_locked()
        error = self._apply_pending_locked()
        if error is not None and not self._failing:  # the WAL may hold the space: checkpoint, try once more
            self._checkpoint_locked()
            error = self._apply_pending_locked()
        if error is None:
            self._recovered_locked()
        else:
            self._failed_locked(error)

    def _apply_pending_locked(self) -> Exception | None:
        """Write waiting ops oldest first, each in its own transaction; the error that stopped it, or None."""
        while self._pending:
            key = next(iter(self._pending))
            try:
                self._transaction_locked(self._pending[key].op)
            except ROW_ERRORS as exc:  # this row can never be written: dropped so that the others go on
                log.error("control state write dropped", extra=kv(path=str(self.path), key=key, error=str(exc)))
            except sqlite3.Error as exc:  # full, I/O error, read-only, damaged: the disk's state, retried
                return exc
            self._pending_episodes -= self._pending.pop(key).episodes
        return None

    def _transaction_locked(self, op: Op) -> None:
        self._db.execute("BEGIN")
        try:
            op(self._db)
            self._db.execute("COMMIT")
        except BaseException:
            if self._db.in_transaction:  # SQLite may have rolled back already (SQLITE_FULL)
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
            raise

    def _checkpoint_locked(self) -> None:
        with contextlib.suppress(sqlite3.Error):  # fails as long as the disk is full: the next try may not
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()

    def _failed_locked(self, exc: Exception) -> None:
        PERSIST_FAILURES.inc()
        self._next_try = time.monotonic() + RETRY_S
        if not self._failing:
            PERSIST_FAILING.set(1)
            log.warning(
                "control state cannot be written: serving from memory; the waiting writes are retried with later"
                " writes and every second, and are lost if control stops before the disk takes them",
                extra=kv(path=str(self.path), error=_why(exc), waiting=len(self._pending)),
            )
        self._failing = _why(exc)

    def _recovered_locked(self) -> None:
        if self._failing:
            PERSIST_FAILING.set(0)
            log.info("control state written again", extra=kv(path=str(self.path), failed_with=self._failing))
            self._failing, self._dropping = "", False

    def _bound_locked(self) -> None:
        """Beyond MAX_PENDING_EPISODES waiting summaries the oldest go (in memory they still count)."""
        while self._pending_episodes > MAX_PENDING_EPISODES:
            key = next(k for k, p in self._pending.items() if p.episodes)
            dropped = self._pending.pop(key).episodes
            self._pending_episodes -= dropped
            PERSIST_DROPPED.inc(dropped)
            if not self._dropping:
                self._dropping = True
                log.error(
                    "episode summaries dropped unwritten: the disk has failed for too long",
                    extra=kv(path=str(self.path), kept=MAX_PENDING_EPISODES, error=self._failing),
                )

    # ------------------------------------------------------------------ robots and episodes

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
        row = (
            spec.robot_id,
            spec.SerializeToString(),
            agent_id,
            hostname,
            registered_at_ns,
            last_heartbeat_ns,
            status.SerializeToString(),
        )
        self._write(
            ("robot", spec.robot_id),
            lambda db: db.execute("INSERT OR REPLACE INTO robots VALUES (?, ?, ?, ?, ?, ?, ?)", row),
        )

    def add_episodes(self, episodes: list[control_pb2.EpisodeSummary], experiment: str = "") -> None:
        """Idempotent: an episode re-sent after a broken stream is stored once."""
        if not episodes:
            return
        rows = [
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
        ]
        sql = (
            "INSERT OR IGNORE INTO episodes"
            " (robot_id, episode_id, summary, experiment, success, episode_return, intervention_steps)"
            " VALUES (?, ?, ?, ?, ?, ?, ?)"
        )
        self._write(None, lambda db: db.executemany(sql, rows), episodes=len(rows))

    def forget_robot(self, robot_id: str) -> None:
        """The robot's row, lease and episodes go in one transaction; its episodes' sums move to forgotten_totals.
        Its waiting robot and lease rows are dropped (deleted anyway), so that a robot registering again with
        this id is written after this delete, not before it."""
        fold = (
            "INSERT INTO forgotten_totals"
            " SELECT experiment, COUNT(*), SUM(success), SUM(episode_return), SUM(intervention_steps = 0),"
            " SUM(success AND intervention_steps = 0) FROM episodes WHERE robot_id = ? GROUP BY experiment"
            " ON CONFLICT (experiment) DO UPDATE SET episodes = episodes + excluded.episodes,"
            " successes = successes + excluded.successes, return_sum = return_sum + excluded.return_sum,"
            " unhelped = unhelped + excluded.unhelped,"
            " unhelped_successes = unhelped_successes + excluded.unhelped_successes"
        )

        def op(db: sqlite3.Connection) -> None:
            db.execute(fold, (robot_id,))
            for table in ("episodes", "robots", "leases"):
                db.execute(f"DELETE FROM {table} WHERE robot_id = ?", (robot_id,))

        with self._lock:
            for kind in ("robot", "lease"):
                self._pending.pop((kind, robot_id), None)
        self._write(None, op)

    def forgotten_totals(self) -> list[tuple[str, int, int, float, int, int]]:
        """(experiment, episodes, successes, sum of returns, episodes without interventions, successes among
        those) of every robot forgotten."""
        with self._lock:
            return self._db.execute("SELECT * FROM forgotten_totals").fetchall()

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
        row = (name, int(running), started_at_ns, stopped_at_ns)
        self._write(
            ("experiment", name), lambda db: db.execute("INSERT OR REPLACE INTO experiments VALUES (?, ?, ?, ?)", row)
        )

    def load_definitions(self) -> list[str]:
        """Experiments defined at run time (DefineExperiment), as ExperimentConfig JSON, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT definition FROM defined_experiments ORDER BY seq").fetchall()
        return [row[0] for row in rows]

    def save_definition(self, name: str, definition_json: str) -> None:
        sql = "INSERT INTO defined_experiments (name, definition) VALUES (?, ?)"
        self._write(("definition", name), lambda db: db.execute(sql, (name, definition_json)))

    def remove_definition(self, name: str, removed_at_ns: int) -> None:
        """RemoveExperiment: the definition and run state go; the name stays taken (its history keeps it).
        All three or none (one transaction), after the writes of that name that wait."""

        def op(db: sqlite3.Connection) -> None:
            db.execute("DELETE FROM defined_experiments WHERE name = ?", (name,))
            db.execute("DELETE FROM experiments WHERE name = ?", (name,))
            db.execute("INSERT OR REPLACE INTO removed_experiments VALUES (?, ?)", (name, removed_at_ns))

        self._write(("removed", name), op)

    def load_removed(self) -> set[str]:
        """Names of experiments removed by RemoveExperiment (never defined again)."""
        with self._lock:
            return {row[0] for row in self._db.execute("SELECT name FROM removed_experiments").fetchall()}

    def load_leases(self) -> dict[str, str]:
        """robot_id -> the experiment it was last leased to."""
        with self._lock:
            return dict(self._db.execute("SELECT robot_id, experiment FROM leases").fetchall())

    def save_lease(self, robot_id: str, experiment: str) -> None:
        sql = "INSERT OR REPLACE INTO leases VALUES (?, ?)"
        self._write(("lease", robot_id), lambda db: db.execute(sql, (robot_id, experiment)))

    def load_commands(self, kept: int) -> list[control_pb2.CommandStatus]:
        """The newest `kept` commands, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT status FROM commands ORDER BY seq DESC LIMIT ?", (kept,)).fetchall()
        return [control_pb2.CommandStatus.FromString(s) for (s,) in reversed(rows)]

    def save_command(self, status: control_pb2.CommandStatus, kept: int) -> None:
        """Insert or update (results arrive later); the history keeps the newest `kept`."""
        cid, blob = status.command.command_id, status.SerializeToString()

        def op(db: sqlite3.Connection) -> None:
            if db.execute("SELECT 1 FROM commands WHERE command_id = ?", (cid,)).fetchone() is not None:
                db.execute("UPDATE commands SET status = ? WHERE command_id = ?", (blob, cid))
                return
            top = db.execute("SELECT COALESCE(MAX(seq), 0) FROM commands").fetchone()[0]
            db.execute("INSERT INTO commands VALUES (?, ?, ?)", (cid, top + 1, blob))
            db.execute("DELETE FROM commands WHERE seq <= ?", (top + 1 - kept,))

        self._write(("command", cid), op)

    def episode_count(self, robot_id: str) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM episodes WHERE robot_id = ?", (robot_id,)).fetchone()[0]

    def load_workers(self) -> list[control_pb2.WorkerInfo]:
        with self._lock:
            rows = self._db.execute("SELECT info FROM workers ORDER BY worker_id").fetchall()
        return [control_pb2.WorkerInfo.FromString(info) for (info,) in rows]

    def save_worker(self, info: control_pb2.WorkerInfo) -> None:
        row = (info.worker_id, info.SerializeToString())
        self._write(
            ("worker", info.worker_id), lambda db: db.execute("INSERT OR REPLACE INTO workers VALUES (?, ?)", row)
        )

    def forget_worker(self, worker_id: str) -> None:
        """Same key as save_worker: a report arriving later replaces this delete (the row's newest value wins)."""
        sql = "DELETE FROM workers WHERE worker_id = ?"
        self._write(("worker", worker_id), lambda db: db.execute(sql, (worker_id,)))

    def close(self) -> None:
        """A last try at what waits (logged when lost), then the file and its lock go."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._pending:
                self._flush_locked(force=True)
            if self._pending:
                log.error(
                    "control state not written at stop: these writes are lost",
                    extra=kv(path=str(self.path), lost=len(self._pending), error=self._failing),
                )
            self._db.close()
            os.close(self._owner)  # drops the flock
