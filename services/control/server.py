"""Control service: the registry of robots, their leases and heartbeats, experiments, and cloud-to-edge commands.

An edge agent opens one long-lived Connect stream: `register` first, within REGISTER_TIMEOUT_S (validated specs ->
a lease), then heartbeats that renew the lease and report each robot's status and finished episodes (a status or
summary that breaks the contract is dropped and counted, the stream goes on), and a
`robots` update whenever a robot is plugged in or unplugged (hot-plug: the new set, validated like a
registration). Commands from SendCommand travel down the same stream. A robot goes offline when its stream ends
or when no heartbeat arrives for lease_ttl_s (a reaper thread); its spec stays queryable so replay
can keep validating steps that arrive late, until an operator forgets it (ForgetRobot) or it has been offline
for control.forget_offline_after_days. The reaper also deletes workers offline for WORKER_FORGET_TTLS x worker_ttl_s.
"""

from __future__ import annotations

import fnmatch
import logging
import math
import queue
import re
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import grpc
import prometheus_client
from pydantic import ValidationError

from services.control.state import ControlState
from user import rpc
from user.auth import Identity
from user.config import ExperimentConfig, ReplayShard, StackConfig
from user.experiments import experiment_for, parse_definition, shadowed
from user.log import kv
from user.spec import (
    MAX_EPISODE_ID_BYTES,
    ROBOT_ID_RE,
    SHOWN_CHARS,
    SpecError,
    clipped,
    enum_name,
    id_ok,
    validate_spec,
)
from user.v1 import control_pb2, control_pb2_grpc, robot_pb2

log = logging.getLogger(__name__)

SERVICE_NAME = control_pb2.DESCRIPTOR.services_by_name["Control"].full_name
MAX_TEXT_BYTES = 256  # hostname, software_version, command ids: enough for any real value, bounded in memory
MAX_ERROR_BYTES = 1024  # a learner's reason an experiment failed (WorkerInfo.failed), cut beyond this
MAX_REASON_CHARS = 200  # of that reason, in the hold lease sent down to every robot of the experiment
MAX_MISFIT_ROBOTS = 1024  # WorkerInfo.misfit_robots entries one learner may report
MAX_ROBOTS_PER_AGENT = 256
MAX_COMMAND_WAIT_S = 60.0
WORKER_ID_RE = re.compile(r"[A-Za-z0-9_.@:\-]{1,128}")
WORKER_KINDS = frozenset({"learner", "inference"})
EXPERIMENT_NAME_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")  # ExperimentConfig.name
MAX_EXPERIMENTS = 256  # configured plus defined at run time (a worker reports at most 256 too)
QUEUE_POLL_S = 0.25  # how often a Connect stream notices its client went away
# A Connect stream must say `register` this soon: one that says nothing would hold a server thread forever.
REGISTER_TIMEOUT_S = 30.0
MAX_NAMES_SHOWN = 20  # experiment names listed in a NOT_FOUND (256 of them would overflow the status headers)
# A worker offline this many worker_ttl_s is deleted: its id names a host:port, so every learner or inference
# restart on a new port would otherwise add a record for good (kept in SQLite, scanned on every report).
WORKER_FORGET_TTLS = 10

ROBOTS_ONLINE = prometheus_client.Gauge("user_control_robots_online", "Robots with a live lease")
REGISTRATIONS = prometheus_client.Counter("user_control_registrations_total", "Accepted edge registrations")
ROBOT_SET_UPDATES = prometheus_client.Counter(
    "user_control_robot_set_updates_total", "Accepted hot-plug robot set updates from edges"
)
HEARTBEATS = prometheus_client.Counter("user_control_heartbeats_total", "Heartbeats received")
LEASE_EXPIRATIONS = prometheus_client.Counter(
    "user_control_lease_expirations_total", "Leases ended because no heartbeat arrived within lease_ttl_s"
)
COMMANDS = prometheus_client.Counter("user_control_commands_total", "Commands sent to edges", ["kind"])
LEASED = prometheus_client.Gauge("user_control_robots_leased", "Robots leased to an experiment", ["experiment"])
EXPERIMENT_RUNNING = prometheus_client.Gauge(
    "user_control_experiment_running", "1 while an experiment runs, 0 while stopped", ["experiment"]
)
# Not per robot: each edge exports user_edge_episodes_total{robot_id, success} (what the dashboards plot), and a
# robot_id label here would keep a series for every robot control ever saw.
EPISODES = prometheus_client.Counter(
    "user_control_episodes_total",
    "Finished episodes reported by edges (per robot: user_edge_episodes_total)",
    ["success"],
)
ROBOTS_FORGOTTEN = prometheus_client.Counter(
    "user_control_robots_forgotten_total",
    "Robots dropped from control's registry and state: requested (ForgetRobot) or offline (forget_offline_after_days)",
    ["how"],
)
HEARTBEAT_REJECTED = prometheus_client.Counter(
    "user_control_heartbeat_rejected_total",
    "Robot statuses and episode summaries of heartbeats dropped (not stored) for breaking the contract",
    ["reason"],
)


# --------------------------------------------------------------------------- validation
# The RobotSpec checks live in user.spec (shared with replay, inference, edge and learner).


def validate_register(req: control_pb2.RegisterRequest) -> None:
    """An agent may register with no robot attached yet: they arrive later as `robots` updates."""
    if not ROBOT_ID_RE.fullmatch(req.agent_id):
        raise SpecError(f"agent_id {clipped(req.agent_id)} must match {ROBOT_ID_RE.pattern}")
    for name in ("hostname", "software_version"):
        if len(getattr(req, name).encode()) > MAX_TEXT_BYTES:
            raise SpecError(f"{name} is longer than {MAX_TEXT_BYTES} bytes")
    validate_robot_set(req.robots)


def validate_robot_set(specs: Iterable[robot_pb2.RobotSpec]) -> None:
    specs = list(specs)
    if len(specs) > MAX_ROBOTS_PER_AGENT:
        raise SpecError(f"one agent registers at most {MAX_ROBOTS_PER_AGENT} robots, got {len(specs)}")
    for spec in specs:  # first: the ids quoted below are then valid (bounded)
        validate_spec(spec)
    ids = [spec.robot_id for spec in specs]
    if len(ids) != len(set(ids)):
        twice = sorted({rid for rid in ids if ids.count(rid) > 1})
        raise SpecError(f"robot ids must be unique within a registration, got {twice} more than once")


def command_problem(cmd: control_pb2.Command) -> str | None:
    """Why a command must not reach an edge, or None. Only what an edge knows how to do is forwarded."""
    if cmd.kind not in KNOWN_COMMANDS:
        return f"command.kind must be PAUSE, RESUME or RESET, got {enum_name(control_pb2.CommandKind, cmd.kind)}"
    if cmd.robot_id and not ROBOT_ID_RE.fullmatch(cmd.robot_id):
        return f"command.robot_id {clipped(cmd.robot_id)} must be empty (every robot) or match {ROBOT_ID_RE.pattern}"
    if len(cmd.command_id.encode()) > MAX_TEXT_BYTES:
        return f"command.command_id is longer than {MAX_TEXT_BYTES} bytes"
    return None


def worker_problem(w: control_pb2.WorkerInfo) -> str | None:
    """Why a worker report cannot be stored, or None."""
    if not WORKER_ID_RE.fullmatch(w.worker_id):
        return f"worker_id {clipped(w.worker_id)} must match {WORKER_ID_RE.pattern}"
    if w.kind not in WORKER_KINDS:
        return f"kind must be one of {sorted(WORKER_KINDS)}, got {clipped(w.kind)}"
    texts = [w.hostname, w.address, w.software_version, w.device, *w.experiments]
    texts += [t for d in w.devices for t in (d.name, d.model)]
    if any(len(t.encode()) > MAX_TEXT_BYTES for t in texts):
        return f"a text field is longer than {MAX_TEXT_BYTES} bytes"
    if len(w.devices) > 64 or len(w.experiments) > 256 or len(w.preparing) > 256:
        return "at most 64 devices, 256 experiments and 256 preparing"
    stray = sorted(set(w.preparing) - set(w.experiments))
    if stray:
        return f"preparing {[clipped(n) for n in stray[:5]]} ({len(stray)} in all) are not among its experiments"
    # `failed` may name an experiment outside `experiments` (a defined one whose definition did not check).
    if len(w.failed) > 256 or any(not EXPERIMENT_NAME_RE.fullmatch(name) for name in w.failed):
        return "failed: at most 256 entries, keyed by experiment name"
    if len(w.misfit_robots) > MAX_MISFIT_ROBOTS:
        return f"misfit_robots: at most {MAX_MISFIT_ROBOTS} entries, got {len(w.misfit_robots)}"
    bad = sorted(rid for rid in w.misfit_robots if not ROBOT_ID_RE.fullmatch(rid))
    if bad:
        return f"misfit_robots {[clipped(r) for r in bad[:5]]} ({len(bad)} in all) must match {ROBOT_ID_RE.pattern}"
    return None


def status_problem(status: control_pb2.RobotStatus) -> tuple[str, str] | None:
    """(reason, why) a robot's status is not stored, or None."""
    if status.state not in control_pb2.RobotState.values():  # proto3 enums are open: any int32 arrives
        return "state", f"state {status.state} is not a RobotState"
    for name in ("env_steps_per_s", "loop_period_p99_ms"):
        value = getattr(status, name)
        if not (math.isfinite(value) and value >= 0):
            return "rate", f"{name} must be finite and >= 0, got {value}"
    return None


def summary_problem(ep: control_pb2.EpisodeSummary, spec: robot_pb2.RobotSpec) -> tuple[str, str] | None:
    """(reason, why) an episode summary is not stored, or None. It belongs to the robot whose status carried it."""
    if ep.robot_id and ep.robot_id != spec.robot_id:
        return "robot_id", f"a summary of robot {clipped(ep.robot_id)} in the status of robot {spec.robot_id}"
    if not id_ok(ep.episode_id, MAX_EPISODE_ID_BYTES):  # as replay keys episodes
        return (
            "episode_id",
            f"episode_id {clipped(ep.episode_id)} must be 1..{MAX_EPISODE_ID_BYTES} bytes, no '/' or NUL",
        )
    if not math.isfinite(ep.episode_return):  # one NaN would make the experiment's mean_return NaN for good
        return "episode_return", f"episode_return must be finite, got {ep.episode_return}"
    if spec.max_episode_steps and ep.length > spec.max_episode_steps:
        return "length", f"length {ep.length} exceeds the spec's max_episode_steps {spec.max_episode_steps}"
    if ep.intervention_steps > ep.length:
        return "intervention_steps", f"intervention_steps {ep.intervention_steps} exceed the length {ep.length}"
    return None


KNOWN_COMMANDS = frozenset(
    {control_pb2.COMMAND_KIND_PAUSE, control_pb2.COMMAND_KIND_RESUME, control_pb2.COMMAND_KIND_RESET}
)


# --------------------------------------------------------------------------- registry


def _copy(lease: control_pb2.RobotLease) -> control_pb2.RobotLease:
    out = control_pb2.RobotLease()
    out.CopyFrom(lease)
    return out


class AlreadyRegistered(Exception):
    """A robot_id held by a different live agent (-> ALREADY_EXISTS)."""


class RobotOnline(Exception):
    """ForgetRobot of a robot with a live lease (-> FAILED_PRECONDITION)."""


class CommandIdTaken(Exception):
    """A command_id already names a different command (-> ALREADY_EXISTS)."""


@dataclass(frozen=True)
class Rejected:
    """A part of a heartbeat dropped instead of stored; `reason` labels the metric."""

    robot_id: str  # as sent (cut when logged)
    reason: str
    why: str


@dataclass
class Abort:
    """Queued on a connection to end its stream with this status."""

    code: grpc.StatusCode
    message: str


@dataclass(eq=False)
class Connection:
    """One live Connect stream: an agent, its robots, its lease and its outbound queue."""

    lease_id: str
    agent_id: str
    hostname: str
    robot_ids: list[str]
    lease_deadline: float  # monotonic
    outbox: queue.Queue = field(default_factory=queue.Queue)
    live: bool = True
    warned: set[str] = field(default_factory=set)  # heartbeat rejection reasons already logged for this stream


class EpisodeHistory:
    """A robot's newest episode summaries (at most `maxlen`), kept serialized with their ids beside them:
    ~190 bytes a kept episode instead of ~570 for a protobuf message (64 robots x 200 episodes: ~2.4 MB
    instead of ~7 MB), parsed only when an RPC reads them."""

    def __init__(self, maxlen: int, episodes: Iterable[control_pb2.EpisodeSummary] = ()) -> None:
        self.maxlen = maxlen
        self._ids: deque[str] = deque(maxlen=maxlen)
        self._blobs: deque[bytes] = deque(maxlen=maxlen)
        for ep in episodes:
            self.append(ep)

    def __len__(self) -> int:
        return len(self._blobs)

    def ids(self) -> set[str]:
        return set(self._ids)

    def append(self, ep: control_pb2.EpisodeSummary) -> None:
        self._ids.append(ep.episode_id)
        self._blobs.append(ep.SerializeToString())

    def messages(self) -> list[control_pb2.EpisodeSummary]:
        """Oldest first."""
        return [control_pb2.EpisodeSummary.FromString(b) for b in self._blobs]


@dataclass
class RobotRecord:
    spec: robot_pb2.RobotSpec
    agent_id: str
    hostname: str
    registered_at_ns: int
    conn: Connection | None
    last_heartbeat_ns: int = 0
    lease_expires_ns: int = 0
    status: control_pb2.RobotStatus = field(default_factory=control_pb2.RobotStatus)
    episodes: EpisodeHistory = field(default_factory=lambda: EpisodeHistory(200))
    lease: control_pb2.RobotLease | None = None  # what its edge was last told; None = offline, nothing sent

    @property
    def online(self) -> bool:
        return self.conn is not None and self.conn.live


@dataclass
class CommandRecord:
    """A sent command, where it went and what came back (bounded history in RAM)."""

    command: control_pb2.Command
    sent_at_ns: int
    agents: list[str]
    results: list[control_pb2.CommandResult] = field(default_factory=list)

    def status(self) -> control_pb2.CommandStatus:
        return control_pb2.CommandStatus(
            command=self.command, sent_at_ns=self.sent_at_ns, agents=self.agents, results=self.results
        )


@dataclass
class ExperimentRecord:
    """An experiment of the stack config and whether it runs (persisted: a restart keeps a stop)."""

    config: ExperimentConfig
    running: bool
    started_at_ns: int
    stopped_at_ns: int = 0
    defined_at_runtime: bool = False  # by DefineExperiment (persisted with its definition), not the config


@dataclass
class EpisodeTotals:
    episodes: int = 0
    successes: int = 0
    return_sum: float = 0.0
    unhelped: int = 0  # episodes no teleoperator drove a step of: the policy's own record
    unhelped_successes: int = 0

    def add(self, other: EpisodeTotals) -> None:
        self.episodes += other.episodes
        self.successes += other.successes
        self.return_sum += other.return_sum
        self.unhelped += other.unhelped
        self.unhelped_successes += other.unhelped_successes


class Registry:
    """Thread-safe state shared by the Connect streams, the unary RPCs and the reaper.

    With a ControlState, robots, episodes, workers, experiments, leases and commands are written through
    to SQLite and read back at start (robots come back offline: a lease needs a live stream).

    Leases: every online robot that a running experiment's selector picks (the first experiment whose
    selector holds, as the learner and inference route) is leased to it, up to its max_robots (a robot
    holding a place keeps it, then the one that held it last, then by id). A robot whose experiment is
    stopped or full, or whose online learner prepares its first policy or reports the experiment failed
    (WorkerInfo.failed), is told to hold, as is a robot that learner reports does not fit the experiment's layout
    (WorkerInfo.misfit_robots; it takes no place); one no experiment selects is free. Leases are recomputed whenever a
    robot comes or goes, when an experiment starts or stops and when what learners report changes; edges hear
    only the robots whose lease changed."""

    def __init__(
        self,
        lease_ttl_s: float,
        episodes_kept: int,
        state: ControlState | None = None,
        worker_ttl_s: float = 30.0,
        commands_kept: int = 1000,
        experiments: list[ExperimentConfig] | None = None,
    ) -> None:
        self.lease_ttl_s = lease_ttl_s
        self.episodes_kept = episodes_kept
        self.worker_ttl_s = worker_ttl_s
        self.commands_kept = commands_kept
        self.state = state
        self._lock = threading.Lock()
        self._results = threading.Condition(self._lock)
        self._robots: dict[str, RobotRecord] = {}
        self._conns: dict[str, Connection] = {}  # lease_id -> live connection
        self._workers: dict[str, control_pb2.WorkerInfo] = {}
        self._preparing: set[str] = set()  # experiments an online learner is still preparing: robots hold
        self._failed: dict[str, str] = {}  # experiment -> why an online learner cannot train it: robots hold
        # robot_id -> (why it does not fit its experiment's layout, the experiments its reporting learners serve):
        # it holds while one of those experiments selects it
        self._misfits: dict[str, tuple[str, frozenset[str]]] = {}
        self._commands: OrderedDict[str, CommandRecord] = OrderedDict()
        self._experiments: dict[str, ExperimentRecord] = {}  # config order: the first matching selector wins
        self._removed: set[str] = state.load_removed() if state is not None else set()  # names never reused
        self._last_lease: dict[str, str] = state.load_leases() if state is not None else {}
        self._totals: dict[tuple[str, str], EpisodeTotals] = {}  # (experiment, robot_id) -> whole history
        self._robot_totals: dict[str, EpisodeTotals] = {}  # robot_id -> whole history, every experiment
        # experiment -> episodes of robots forgotten since (ForgetRobot): still counted in the experiment's totals
        self._forgotten: dict[str, EpisodeTotals] = {}
        # Offline clocks start no earlier than this: a robot saved online before a kill -9 has only its registration
        # time on disk, and must not be forgotten before its edge had a chance to reconnect.
        self._started_ns = time.time_ns()
        self._load_experiments(experiments or [])
        if state is not None:
            for exp, rid, n, succ, ret, alone, alone_succ in state.episode_totals():
                self._totals[(exp, rid)] = EpisodeTotals(
                    int(n), int(succ or 0), float(ret or 0.0), int(alone or 0), int(alone_succ or 0)
                )
                robot = self._robot_totals.setdefault(rid, EpisodeTotals())
                robot.episodes, robot.successes = robot.episodes + int(n), robot.successes + int(succ or 0)
            for exp, n, succ, ret, alone, alone_succ in state.forgotten_totals():
                self._forgotten[exp] = EpisodeTotals(int(n), int(succ), float(ret), int(alone), int(alone_succ))
            for st in state.load_commands(commands_kept):
                rec = CommandRecord(st.command, st.sent_at_ns, list(st.agents), list(st.results))
                self._commands[st.command.command_id] = rec
        if state is not None:
            for saved in state.load_robots(episodes_kept):
                saved.status.state = control_pb2.ROBOT_STATE_OFFLINE
                self._robots[saved.spec.robot_id] = RobotRecord(
                    spec=saved.spec,
                    agent_id=saved.agent_id,
                    hostname=saved.hostname,
                    registered_at_ns=saved.registered_at_ns,
                    conn=None,
                    last_heartbeat_ns=saved.last_heartbeat_ns,
                    status=saved.status,
                    episodes=EpisodeHistory(episodes_kept, saved.episodes),
                )
            self._workers = {w.worker_id: w for w in state.load_workers()}

    def _load_experiments(self, experiments: list[ExperimentConfig]) -> None:
        """The config's experiments, then those defined at run time (in the order they were defined); a state
        file says which were stopped (a new one starts running). A config entry wins over a definition of
        the same name (the definition is skipped, with a warning)."""
        saved = self.state.load_experiments() if self.state is not None else {}
        defined: list[ExperimentConfig] = []
        for text in self.state.load_definitions() if self.state is not None else []:
            try:
                exp = ExperimentConfig.model_validate_json(text)
            except ValidationError as exc:  # e.g. a field an older version accepted: skipped, not fatal
                log.error("a stored experiment definition no longer checks; skipped", extra=kv(error=str(exc)))
                continue
            if any(e.name == exp.name for e in experiments):
                log.warning(
                    "a defined experiment's name is now in the config: the config's is used",
                    extra=kv(experiment=exp.name),
                )
                continue
            defined.append(exp)
        for name, first in shadowed([*experiments, *defined]).items():
            log.warning(
                "an experiment can get no robot: an earlier one selects all of its robots",
                extra=kv(experiment=name, taken_by=first),
            )
        now_ns = time.time_ns()
        defined_names = {exp.name for exp in defined}
        for exp in [*experiments, *defined]:
            running, started, stopped = saved.get(exp.name, (True, now_ns, 0))
            at_runtime = exp.name in defined_names
            self._experiments[exp.name] = ExperimentRecord(exp, running, started, stopped, at_runtime)
            if exp.name not in saved and self.state is not None:
                self.state.save_experiment(exp.name, running, started, stopped)

    def define_experiment(self, exp: ExperimentConfig) -> control_pb2.ExperimentInfo | None:
        """Add a validated experiment after the others, running, persisted; None if the name is taken."""
        with self._lock:
            if exp.name in self._experiments or exp.name in self._removed:
                return None
            first = shadowed([*(e.config for e in self._experiments.values()), exp]).get(exp.name)
            if self.state is not None:
                self.state.save_definition(exp.name, exp.model_dump_json())
            rec = ExperimentRecord(exp, True, time.time_ns(), defined_at_runtime=True)
            self._experiments[exp.name] = rec
            if self.state is not None:
                self.state.save_experiment(exp.name, True, rec.started_at_ns, 0)
            if first is not None:
                log.warning(
                    "a defined experiment can get no robot: an earlier one selects all of its robots",
                    extra=kv(experiment=exp.name, taken_by=first),
                )
            log.info("experiment defined", extra=kv(experiment=exp.name))
            self._relay_leases_locked()
            return self._experiment_info_locked(rec)

    def _save_locked(self, rec: RobotRecord) -> None:
        if self.state is not None:
            self.state.save_robot(
                rec.spec, rec.agent_id, rec.hostname, rec.registered_at_ns, rec.last_heartbeat_ns, rec.status
            )

    def register(self, req: control_pb2.RegisterRequest) -> tuple[Connection, list[Connection]]:
        """Take the robots for this agent; returns the new connection and the ones it replaced."""
        now_ns = time.time_ns()
        with self._lock:
            self._check_free_locked(req.robots, req.agent_id)
            # One stream per agent: a re-registration (reconnect) supersedes the old one.
            replaced = [c for c in self._conns.values() if c.agent_id == req.agent_id]
            for old in replaced:  # leases are recomputed below, so a reconnect keeps its max_robots places
                self._end_locked(old, relay=False)
            conn = Connection(
                lease_id=uuid.uuid4().hex,
                agent_id=req.agent_id,
                hostname=req.hostname,
                robot_ids=[s.robot_id for s in req.robots],
                lease_deadline=time.monotonic() + self.lease_ttl_s,
            )
            self._conns[conn.lease_id] = conn
            for spec in req.robots:
                self._take_locked(spec, conn, now_ns)
            self._update_gauge_locked()
            self._relay_leases_locked(skip=conn)  # robots of other agents may lose a max_robots place
        return conn, replaced

    def update_robots(self, conn: Connection, specs: list[robot_pb2.RobotSpec]) -> tuple[list[str], list[str]]:
        """Hot-plug: `specs` is the agent's whole robot set now. New robots come online on this stream,
        missing ones go offline (their lease is released and relayed to the others); returns (added, removed).
        Leases of the new robots go down the stream as a LeaseUpdate."""
        now_ns = time.time_ns()
        with self._lock:
            if not conn.live:
                return [], []
            self._check_free_locked(specs, conn.agent_id)
            wanted = {s.robot_id: s for s in specs}
            removed = [rid for rid in conn.robot_ids if rid not in wanted]
            added = [rid for rid in wanted if rid not in conn.robot_ids]
            self._release_locked(conn, removed)
            for spec in specs:
                rec = self._robots.get(spec.robot_id)
                if spec.robot_id in added or rec is None or rec.conn is not conn:
                    self._take_locked(spec, conn, now_ns)
                elif rec.spec != spec:  # re-plugged with another spec between two updates
                    rec.spec = spec
                    self._save_locked(rec)
            conn.robot_ids = list(wanted)
            self._update_gauge_locked()
            self._relay_leases_locked()
        return added, removed

    def _check_free_locked(self, specs: Iterable[robot_pb2.RobotSpec], agent_id: str) -> None:
        for spec in specs:
            rec = self._robots.get(spec.robot_id)
            if rec is not None and rec.online and rec.agent_id != agent_id:
                raise AlreadyRegistered(
                    f"robot {spec.robot_id} is registered by live agent {rec.agent_id!r} "
                    f"({rec.hostname}); a robot belongs to one agent at a time"
                )

    def _take_locked(self, spec: robot_pb2.RobotSpec, conn: Connection, now_ns: int) -> None:
        """Put `spec` online on `conn`, keeping the robot's episode history."""
        old_rec = self._robots.get(spec.robot_id)
        rec = RobotRecord(
            spec=spec,
            agent_id=conn.agent_id,
            hostname=conn.hostname,
            registered_at_ns=now_ns,
            conn=conn,
            last_heartbeat_ns=now_ns,
            lease_expires_ns=now_ns + int(self.lease_ttl_s * 1e9),
            status=control_pb2.RobotStatus(robot_id=spec.robot_id, state=control_pb2.ROBOT_STATE_RUNNING),
            episodes=old_rec.episodes if old_rec else EpisodeHistory(self.episodes_kept),
        )
        self._robots[spec.robot_id] = rec
        self._save_locked(rec)

    def _release_locked(self, conn: Connection, robot_ids: Iterable[str]) -> None:
        """These robots of `conn` go offline; their leases are free for others (caller relays)."""
        for rid in robot_ids:
            rec = self._robots.get(rid)
            if rec is not None and rec.conn is conn:
                rec.conn = None
                rec.lease = None  # released: its experiment goes on with the others
                rec.status.state = control_pb2.ROBOT_STATE_OFFLINE
                self._save_locked(rec)

    def leases_of(self, conn: Connection) -> list[control_pb2.RobotLease]:
        """The leases of a connection's robots, for its Registered message."""
        with self._lock:
            out = []
            for rid in conn.robot_ids:
                rec = self._robots.get(rid)
                if rec is not None and rec.conn is conn and rec.lease is not None:
                    out.append(_copy(rec.lease))
            return out

    def heartbeat(self, conn: Connection, hb: control_pb2.Heartbeat) -> list[Rejected]:
        """Renew the lease and store statuses; returns what was dropped (statuses of robots this stream does not
        own, statuses and episode summaries that break the contract). A bad part never ends the stream: the edge
        would send the same summary again after reconnecting, and lose its lease over one bad value."""
        now_ns = time.time_ns()
        rejected: list[Rejected] = []
        with self._lock:
            if not conn.live:
                return rejected
            conn.lease_deadline = time.monotonic() + self.lease_ttl_s
            for rid in conn.robot_ids:
                rec = self._robots.get(rid)
                if rec is not None and rec.conn is conn:
                    rec.last_heartbeat_ns = now_ns
                    rec.lease_expires_ns = now_ns + int(self.lease_ttl_s * 1e9)
            for status in hb.robots:
                rec = self._robots.get(status.robot_id)
                if rec is None or rec.conn is not conn:
                    rejected.append(Rejected(status.robot_id, "foreign_robot", "a robot this stream did not register"))
                    continue
                rejected += self._store_status_locked(rec, status)
        return rejected

    def _store_status_locked(self, rec: RobotRecord, status: control_pb2.RobotStatus) -> list[Rejected]:
        """The valid episode summaries, then the status unless it is invalid (the last good one stays)."""
        rid = rec.spec.robot_id
        rejected = self._add_episodes_locked(rec, status.new_episodes)
        problem = status_problem(status)
        if problem is not None:
            return [*rejected, Rejected(rid, *problem)]
        kept = control_pb2.RobotStatus()
        kept.CopyFrom(status)
        kept.ClearField("new_episodes")  # they live in rec.episodes, bounded
        rec.status = kept
        return rejected

    def _add_episodes_locked(self, rec: RobotRecord, episodes: Iterable[control_pb2.EpisodeSummary]) -> list[Rejected]:
        known = rec.episodes.ids()
        fresh: list[control_pb2.EpisodeSummary] = []
        rejected: list[Rejected] = []
        for sent in episodes:
            if (problem := summary_problem(sent, rec.spec)) is not None:
                rejected.append(Rejected(rec.spec.robot_id, *problem))
                continue
            if sent.episode_id in known:  # re-sent after a broken stream: count it once
                continue
            known.add(sent.episode_id)
            # A copy: a kept sub-message would pin its whole Heartbeat (one protobuf arena).
            ep = control_pb2.EpisodeSummary()
            ep.CopyFrom(sent)
            ep.robot_id = rec.spec.robot_id  # it was empty or this robot's id (summary_problem)
            rec.episodes.append(ep)
            fresh.append(ep)
            EPISODES.labels("true" if ep.success else "false").inc()
        if fresh:
            self._count_episodes_locked(rec, fresh)
        return rejected

    def _count_episodes_locked(self, rec: RobotRecord, fresh: list[control_pb2.EpisodeSummary]) -> None:
        """Add new episodes to their experiment's totals and to SQLite."""
        experiment = self._episode_experiment_locked(rec)
        totals = self._totals.setdefault((experiment, rec.spec.robot_id), EpisodeTotals())
        robot = self._robot_totals.setdefault(rec.spec.robot_id, EpisodeTotals())
        for ep in fresh:
            robot.episodes += 1
            robot.successes += int(ep.success)
            totals.episodes += 1
            totals.successes += int(ep.success)
            totals.return_sum += float(ep.episode_return)
            if not ep.intervention_steps:
                totals.unhelped += 1
                totals.unhelped_successes += int(ep.success)
        if self.state is not None:
            self.state.add_episodes(fresh, experiment)

    def disconnect(self, conn: Connection) -> bool:
        """The stream ended; True if this ended a live lease."""
        with self._lock:
            if not conn.live:
                return False
            self._end_locked(conn)
            return True

    def expire(self) -> list[Connection]:
        """End every lease whose heartbeat deadline has passed."""
        now = time.monotonic()
        with self._lock:
            expired = [c for c in self._conns.values() if c.lease_deadline < now]
            for conn in expired:
                self._end_locked(conn)
        return expired

    def close_all(self) -> list[Connection]:
        with self._lock:
            conns = list(self._conns.values())
            for conn in conns:
                self._end_locked(conn)
        return conns

    def _end_locked(self, conn: Connection, relay: bool = True) -> None:
        conn.live = False
        self._conns.pop(conn.lease_id, None)
        self._release_locked(conn, conn.robot_ids)
        self._update_gauge_locked()
        if relay:
            self._relay_leases_locked()  # a place it held at max_robots goes to a waiting robot

    # ------------------------------------------------------------------ leases

    def _episode_experiment_locked(self, rec: RobotRecord) -> str:
        if rec.lease is not None and rec.lease.experiment:
            return rec.lease.experiment
        exp = experiment_for(rec.spec, [e.config for e in self._experiments.values()])
        return exp.name if exp is not None else ""

    def _compute_leases_locked(self) -> dict[str, control_pb2.RobotLease]:
        """robot_id -> its lease, for every online robot."""
        configs = [e.config for e in self._experiments.values()]
        wanted: dict[str, list[RobotRecord]] = {}
        out: dict[str, control_pb2.RobotLease] = {}
        for rid in sorted(self._robots):
            rec = self._robots[rid]
            if not rec.online:
                continue
            exp = experiment_for(rec.spec, configs)
            if exp is None:
                out[rid] = control_pb2.RobotLease(robot_id=rid)  # free: no experiment selects it
            else:
                wanted.setdefault(exp.name, []).append(rec)
        for name, recs in wanted.items():
            exp = self._experiments[name]
            hold = self._hold_reason_locked(exp)
            if hold:
                for rec in recs:
                    out[rec.spec.robot_id] = control_pb2.RobotLease(robot_id=rec.spec.robot_id, hold=True, reason=hold)
                continue
            # Robots holding a place keep it; then those it had last (across reconnects and restarts); then by id.
            recs.sort(
                key=lambda r: (
                    r.lease is None or r.lease.experiment != name,
                    self._last_lease.get(r.spec.robot_id) != name,
                    r.spec.robot_id,
                )
            )
            # A robot its learner cannot train holds (its steps would fill replay for nothing) and takes no place.
            fit = []
            for rec in recs:
                why, served = self._misfits.get(rec.spec.robot_id, ("", frozenset()))
                if name not in served:
                    fit.append(rec)
                else:
                    out[rec.spec.robot_id] = control_pb2.RobotLease(
                        robot_id=rec.spec.robot_id, hold=True, reason=f"experiment {name}: {why}"
                    )
            recs = fit
            cap = exp.config.max_robots or len(recs)
            for i, rec in enumerate(recs):
                rid = rec.spec.robot_id
                if i < cap:
                    table = "" if exp.config.table == "online" else exp.config.table  # "" is replay's default
                    out[rid] = control_pb2.RobotLease(robot_id=rid, experiment=name, table=table)
                else:
                    out[rid] = control_pb2.RobotLease(
                        robot_id=rid, hold=True, reason=f"experiment {name} at max_robots={cap}"
                    )
        return out

    def _hold_reason_locked(self, exp: ExperimentRecord) -> str:
        """Why every robot of `exp` holds (records nothing), or "" when they act."""
        name = exp.config.name
        if not exp.running:
            return f"experiment {name} stopped"
        if name in self._failed:  # nothing learns from its steps: acting would fill replay with the v0 policy's
            why = self._failed[name]
            why = why if len(why) <= MAX_REASON_CHARS else why[:MAX_REASON_CHARS] + "..."
            return f"experiment {name}: its learner failed it ({why}); robots hold until a learner trains it"
        if name in self._preparing:  # no policy yet: acting would only record still frames
            return f"experiment {name}: the learner prepares its first policy (normalize/pretrain)"
        return ""

    def _relay_leases_locked(self, skip: Connection | None = None) -> None:
        """Recompute every lease; queue a LeaseUpdate on each stream whose robots' leases changed.
        `skip`: a stream not yet answered with Registered (which carries its leases)."""
        updates: dict[str, list[control_pb2.RobotLease]] = {}
        for rid, lease in self._compute_leases_locked().items():
            rec = self._robots[rid]
            if rec.lease == lease:
                continue
            rec.lease = lease
            if lease.experiment and self._last_lease.get(rid) != lease.experiment:
                self._last_lease[rid] = lease.experiment
                if self.state is not None:
                    self.state.save_lease(rid, lease.experiment)
            if rec.conn is not None and rec.conn is not skip:
                updates.setdefault(rec.conn.lease_id, []).append(_copy(lease))
            log.info(
                "lease",
                extra=kv(robot_id=rid, experiment=lease.experiment, hold=lease.hold, reason=lease.reason),
            )
        leased = [r.lease.experiment for r in self._robots.values() if r.online and r.lease is not None]
        for name, exp in self._experiments.items():
            LEASED.labels(name).set(leased.count(name))
            EXPERIMENT_RUNNING.labels(name).set(int(exp.running))
        for lease_id, leases in updates.items():
            conn = self._conns.get(lease_id)
            if conn is not None:
                conn.outbox.put(control_pb2.ControlMessage(leases=control_pb2.LeaseUpdate(leases=leases)))

    # ------------------------------------------------------------------ experiments

    def experiment_names(self) -> list[str]:
        with self._lock:
            return list(self._experiments)

    def experiment_configs(self) -> list[ExperimentConfig]:
        with self._lock:
            return [e.config for e in self._experiments.values()]

    def set_running(self, name: str, running: bool) -> control_pb2.ExperimentInfo | None:
        """Start or stop an experiment (idempotent); None if unknown."""
        with self._lock:
            exp = self._experiments.get(name)
            if exp is None:
                return None
            if exp.running != running:
                exp.running = running
                if running:
                    exp.started_at_ns = time.time_ns()
                else:
                    exp.stopped_at_ns = time.time_ns()
                if self.state is not None:
                    self.state.save_experiment(name, exp.running, exp.started_at_ns, exp.stopped_at_ns)
                log.info("experiment " + ("started" if running else "stopped"), extra=kv(experiment=name))
                self._relay_leases_locked()
            return self._experiment_info_locked(exp)

    def remove_experiment(self, name: str) -> tuple[control_pb2.ExperimentInfo | None, str]:
        """Take away a stopped experiment defined at run time: (its last info, "") or (None, why not; "" = unknown).
        Robots its selector held go to the next experiment that selects them."""
        with self._lock:
            exp = self._experiments.get(name)
            if exp is None:
                return None, ""
            if not exp.defined_at_runtime:
                return None, f"experiment {name!r} comes from the stack config: remove it there (and restart control)"
            if exp.running:
                return None, f"experiment {name!r} is running: stop it first (userctl exp stop {name})"
            info = self._experiment_info_locked(exp)
            if self.state is not None:
                self.state.remove_definition(name, time.time_ns())
            del self._experiments[name]
            self._removed.add(name)
            LEASED.remove(name)  # _relay_leases_locked sets the series of listed experiments only
            EXPERIMENT_RUNNING.remove(name)
            log.info("experiment removed", extra=kv(experiment=name))
            self._relay_leases_locked()
            return info, ""

    def was_removed(self, name: str) -> bool:
        with self._lock:
            return name in self._removed

    def experiment_info(self, name: str) -> control_pb2.ExperimentInfo | None:
        with self._lock:
            exp = self._experiments.get(name)
            return self._experiment_info_locked(exp) if exp is not None else None

    def experiments(self) -> list[control_pb2.ExperimentInfo]:
        with self._lock:
            return [self._experiment_info_locked(e) for e in self._experiments.values()]

    def _experiment_info_locked(self, exp: ExperimentRecord) -> control_pb2.ExperimentInfo:
        name = exp.config.name
        configs = [e.config for e in self._experiments.values()]
        rids = {rid for (e, rid) in self._totals if e == name}
        selected = set()
        for rid, rec in self._robots.items():
            match = experiment_for(rec.spec, configs)
            if match is not None and match.name == name:
                selected.add(rid)
        rids |= selected
        info = control_pb2.ExperimentInfo(
            name=name,
            state=control_pb2.EXPERIMENT_STATE_RUNNING if exp.running else control_pb2.EXPERIMENT_STATE_STOPPED,
            definition_json=exp.config.model_dump_json(),
            started_at_ns=exp.started_at_ns,
            stopped_at_ns=exp.stopped_at_ns,
            max_robots=exp.config.max_robots,
            defined_at_runtime=exp.defined_at_runtime,
        )
        return_sum = 0.0
        for rid in sorted(rids):
            rec = self._robots.get(rid)
            totals = self._totals.get((name, rid), EpisodeTotals())
            leased = rec is not None and rec.lease is not None and rec.lease.experiment == name
            version = rec.status.policy_version if rec is not None else 0
            lease = rec.lease if rec is not None and rec.online and rid in selected else None
            info.robots.append(
                control_pb2.ExperimentRobot(
                    robot_id=rid,
                    online=rec is not None and rec.online,
                    leased=leased,
                    episodes=totals.episodes,
                    successes=totals.successes,
                    mean_return=totals.return_sum / totals.episodes if totals.episodes else 0.0,
                    policy_version=version,
                    unhelped_episodes=totals.unhelped,
                    unhelped_successes=totals.unhelped_successes,
                    hold_reason=lease.reason if lease is not None and lease.hold else "",
                )
            )
            if leased:
                info.leased_robots.append(rid)
            info.episodes += totals.episodes
            info.successes += totals.successes
            info.unhelped_episodes += totals.unhelped
            info.unhelped_successes += totals.unhelped_successes
            return_sum += totals.return_sum
            info.policy_version = max(info.policy_version, version)
        gone = self._forgotten.get(name)
        if gone is not None:  # robots forgotten since: no longer listed, their episodes still count
            info.episodes += gone.episodes
            info.successes += gone.successes
            info.unhelped_episodes += gone.unhelped
            info.unhelped_successes += gone.unhelped_successes
            return_sum += gone.return_sum
        info.mean_return = return_sum / info.episodes if info.episodes else 0.0
        cutoff = time.time_ns() - int(self.worker_ttl_s * 1e9)
        online = [w for w in self._workers.values() if w.kind == "learner" and w.last_seen_ns >= cutoff]
        info.learners.extend(w.worker_id for w in online if name in w.experiments)
        errors = [w.failed[name] for w in online if name in w.failed]
        if errors:  # leased robots and a running state say nothing about whether it learns: say it does not
            info.learner_failed, info.learner_error = True, errors[0]
        return info

    def _update_gauge_locked(self) -> None:
        ROBOTS_ONLINE.set(sum(1 for r in self._robots.values() if r.online))

    def info(self, robot_id: str) -> control_pb2.RobotInfo | None:
        with self._lock:
            rec = self._robots.get(robot_id)
            return self._info_locked(rec) if rec else None

    def list(self, include_offline: bool, episodes: bool = True) -> list[control_pb2.RobotInfo]:
        with self._lock:
            recs = [self._robots[k] for k in sorted(self._robots)]
            return [self._info_locked(r, episodes) for r in recs if include_offline or r.online]

    def _info_locked(self, rec: RobotRecord, episodes: bool = True) -> control_pb2.RobotInfo:
        """status.episodes and status.successes are control's stored totals for the robot (every experiment, across
        edge and control restarts: what `exp status` sums), not the edge's counters, which restart with the edge."""
        lease = rec.lease if rec.online and rec.lease is not None else control_pb2.RobotLease()
        info = control_pb2.RobotInfo(
            lease=lease.experiment,
            lease_reason=lease.reason,
            spec=rec.spec,
            agent_id=rec.agent_id,
            hostname=rec.hostname,
            online=rec.online,
            registered_at_ns=rec.registered_at_ns,
            last_heartbeat_ns=rec.last_heartbeat_ns,
            lease_expires_ns=rec.lease_expires_ns,
            status=rec.status,
            recent_episodes=rec.episodes.messages() if episodes else (),
        )
        totals = self._robot_totals.get(rec.spec.robot_id, EpisodeTotals())
        info.status.episodes, info.status.successes = totals.episodes, totals.successes
        return info

    def forget(self, robot_id: str) -> int | None:
        """ForgetRobot: drop an offline robot; its episode count, or None for an unknown id. RobotOnline if online."""
        with self._lock:
            rec = self._robots.get(robot_id)
            if rec is None:
                return None
            if rec.online:
                raise RobotOnline(
                    f"robot {robot_id} is online (agent {rec.agent_id!r} on {rec.hostname}): unplug it or stop its"
                    " edge first"
                )
            return self._forget_locked(robot_id, "requested", "requested")

    def forget_offline(self, max_age_s: float) -> list[str]:
        """Forget every robot offline for longer than max_age_s (the reaper: control.forget_offline_after_days)."""
        cutoff = time.time_ns() - int(max_age_s * 1e9)
        with self._lock:
            old = [
                rid
                for rid, rec in self._robots.items()
                if not rec.online and max(rec.last_heartbeat_ns, rec.registered_at_ns, self._started_ns) < cutoff
            ]
            for rid in old:
                self._forget_locked(rid, "offline", f"offline for more than {max_age_s / 86400:g} days")
        return old

    def _forget_locked(self, robot_id: str, how: str, why: str) -> int:
        """Its record, history and totals go; its experiments keep its episodes in their totals."""
        del self._robots[robot_id]
        self._last_lease.pop(robot_id, None)
        episodes = self._robot_totals.pop(robot_id, EpisodeTotals()).episodes
        for key in [k for k in self._totals if k[1] == robot_id]:
            self._forgotten.setdefault(key[0], EpisodeTotals()).add(self._totals.pop(key))
        if self.state is not None:
            self.state.forget_robot(robot_id)
        ROBOTS_FORGOTTEN.labels(how).inc()
        log.info("robot forgotten", extra=kv(robot_id=robot_id, episodes=episodes, why=why))
        return episodes

    def route(self, command: control_pb2.Command) -> tuple[bool, list[str], bool]:
        """Queue a command on the owning stream(s): (robot known, agents it was queued for, new). The same
        command sent again under its command_id is not queued twice (new False: a client's retry);
        CommandIdTaken when the id names another command (its record and results must not be replaced)."""
        with self._lock:
            old = self._commands.get(command.command_id)
            if old is not None and old.command == command:
                return True, list(old.agents), False
            if old is not None:
                kind = enum_name(control_pb2.CommandKind, old.command.kind)
                raise CommandIdTaken(
                    f"command_id {clipped(command.command_id)} already names a {kind} command for robot "
                    f"{old.command.robot_id or '(every robot)'}; use a new id (sending the same command again is "
                    "idempotent)"
                )
            if not command.robot_id:  # every robot of every live agent
                conns = list(self._conns.values())
            else:
                rec = self._robots.get(command.robot_id)
                if rec is None:
                    return False, [], True
                conns = [rec.conn] if rec.online and rec.conn is not None else []
            for conn in conns:
                conn.outbox.put(control_pb2.ControlMessage(command=command))
            agents = [c.agent_id for c in conns]
            rec = CommandRecord(command, time.time_ns(), agents)
            self._commands[command.command_id] = rec
            self._commands.move_to_end(command.command_id)
            while len(self._commands) > self.commands_kept:
                self._commands.popitem(last=False)
            if self.state is not None:
                self.state.save_command(rec.status(), self.commands_kept)
            return True, agents, True

    def command_result(self, conn: Connection, result: control_pb2.CommandResult) -> bool:
        """Attach an edge's result to its command; False for a command this control did not send to it."""
        with self._lock:
            rec = self._commands.get(result.command_id)
            if rec is None or conn.agent_id not in rec.agents:
                return False
            if any(r.agent_id == conn.agent_id for r in rec.results):
                return True  # re-sent after a reconnect
            kept = control_pb2.CommandResult()
            kept.CopyFrom(result)
            kept.agent_id = conn.agent_id
            kept.message = kept.message[:MAX_TEXT_BYTES]
            rec.results.append(kept)
            if self.state is not None:
                self.state.save_command(rec.status(), self.commands_kept)
            self._results.notify_all()
            return True

    def wait_results(self, command_id: str, timeout_s: float) -> control_pb2.CommandStatus | None:
        """The command's status once every agent answered or timeout_s passed."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                rec = self._commands.get(command_id)
                if rec is None:
                    return None
                left = deadline - time.monotonic()
                if len(rec.results) >= len(rec.agents) or left <= 0:
                    return rec.status()
                self._results.wait(left)

    def register_worker(self, info: control_pb2.WorkerInfo) -> None:
        now_ns = time.time_ns()
        with self._lock:
            old = self._workers.get(info.worker_id)
            kept = control_pb2.WorkerInfo()
            kept.CopyFrom(info)
            for name, error in info.failed.items():  # an exception's text can be long: bounded in memory and SQLite
                kept.failed[name] = error.encode()[:MAX_ERROR_BYTES].decode(errors="ignore")
            for rid, why in info.misfit_robots.items():  # sent down in a lease: bounded like other hold reasons
                kept.misfit_robots[rid] = why if len(why) <= MAX_REASON_CHARS else why[:MAX_REASON_CHARS] + "..."
            kept.registered_at_ns = old.registered_at_ns if old and old.online else now_ns
            kept.last_seen_ns = now_ns
            kept.online = True
            self._workers[info.worker_id] = kept
            if self.state is not None:
                self.state.save_worker(kept)
            self._refresh_learners_locked()

    def refresh_learners(self) -> None:
        """A learner that stopped reporting no longer holds its experiments' robots (called by the reaper)."""
        with self._lock:
            self._refresh_learners_locked()

    def _refresh_learners_locked(self) -> None:
        """What online learners prepare or failed: their robots hold (relayed when it changes)."""
        cutoff = time.time_ns() - int(self.worker_ttl_s * 1e9)
        online = [w for w in self._workers.values() if w.kind == "learner" and w.last_seen_ns >= cutoff]
        preparing = {name for w in online for name in w.preparing}
        failed = {name: why for w in online for name, why in sorted(w.failed.items())}
        # With the experiments that learner serves: a robot holds only in an experiment its reporter trains.
        misfits: dict[str, tuple[str, frozenset[str]]] = {}
        for w in online:
            for rid, why in sorted(w.misfit_robots.items()):
                first, served = misfits.get(rid, (why or "does not fit the experiment's layout", frozenset()))
                misfits[rid] = (first, served | frozenset(w.experiments))
        if preparing == self._preparing and failed == self._failed and misfits == self._misfits:
            return
        if preparing != self._preparing:
            log.info("learners preparing", extra=kv(experiments=sorted(preparing)))
        if failed.keys() != self._failed.keys():
            log.warning("learners failed experiments: their robots hold", extra=kv(experiments=sorted(failed)))
        if misfits.keys() != self._misfits.keys():
            log.warning("learners report misfit robots: they hold", extra=kv(robots=sorted(misfits)))
        self._preparing, self._failed, self._misfits = preparing, failed, misfits
        self._relay_leases_locked()

    def prune_workers(self) -> list[str]:
        """Delete workers offline for WORKER_FORGET_TTLS x worker_ttl_s (the reaper); their ids."""
        cutoff = time.time_ns() - int(WORKER_FORGET_TTLS * self.worker_ttl_s * 1e9)
        with self._lock:
            old = [wid for wid, w in self._workers.items() if w.last_seen_ns < cutoff]
            for wid in old:
                del self._workers[wid]
                if self.state is not None:
                    self.state.forget_worker(wid)
        if old:
            offline_s = WORKER_FORGET_TTLS * self.worker_ttl_s
            log.info("offline workers forgotten", extra=kv(workers=old, offline_s=offline_s))
        return old

    def workers(self, include_offline: bool) -> list[control_pb2.WorkerInfo]:
        cutoff = time.time_ns() - int(self.worker_ttl_s * 1e9)
        out = []
        with self._lock:
            for wid in sorted(self._workers):
                w = control_pb2.WorkerInfo()
                w.CopyFrom(self._workers[wid])
                w.online = w.last_seen_ns >= cutoff
                if include_offline or w.online:
                    out.append(w)
        return out


# --------------------------------------------------------------------------- gRPC servicer


def replay_shard_for(shards: list[ReplayShard], agent_id: str, site: str) -> str:
    """The replay address of the first shard serving this site or agent; "" = the edge keeps its own."""
    for shard in shards:
        if (site and site in shard.sites) or any(fnmatch.fnmatchcase(agent_id, p) for p in shard.agents):
            return shard.addr
    return ""


class ControlServicer(control_pb2_grpc.ControlServicer):
    def __init__(
        self,
        registry: Registry,
        heartbeat_interval_s: float,
        replay_shards: list[ReplayShard] | None = None,
        register_timeout_s: float | None = None,
    ) -> None:
        self.registry = registry
        self.heartbeat_interval_s = heartbeat_interval_s
        self.replay_shards = replay_shards or []
        self.register_timeout_s = REGISTER_TIMEOUT_S if register_timeout_s is None else register_timeout_s

    def _tag(self, info: control_pb2.RobotInfo) -> control_pb2.RobotInfo:
        exp = experiment_for(info.spec, self.registry.experiment_configs())
        info.experiment = exp.name if exp is not None else ""
        return info

    def Connect(
        self, request_iterator: Iterator[control_pb2.EdgeMessage], context: grpc.ServicerContext
    ) -> Iterator[control_pb2.ControlMessage]:
        first = self._first_message(request_iterator, context)
        if first is None:
            return
        if first.WhichOneof("msg") != "register":
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "the first message on Connect must be `register`")
        req = first.register
        who = rpc.caller(context)
        if who is not None and not (
            who.owns_agent(req.agent_id) and all(who.owns_robot(s.robot_id) for s in req.robots)
        ):
            context.abort(
                grpc.StatusCode.PERMISSION_DENIED,
                f"{who.role} token of {who.name!r} may not register agent {clipped(req.agent_id)} with these robots",
            )
        try:
            validate_register(req)
            conn, replaced = self.registry.register(req)
        except SpecError as exc:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"bad registration: {exc}")
        except AlreadyRegistered as exc:
            context.abort(grpc.StatusCode.ALREADY_EXISTS, str(exc))
        for old in replaced:
            old.outbox.put(Abort(grpc.StatusCode.ABORTED, "superseded by a newer registration of this agent"))
        # However the stream ends (even while `registered` is being sent), its robots go offline then, not at
        # lease expiry.
        hung_up = rpc.at_stream_end(context, lambda: self._hung_up(conn))
        REGISTRATIONS.inc()
        replay_addr = replay_shard_for(self.replay_shards, req.agent_id, req.site)
        log.info(
            "agent registered",
            extra=kv(
                agent_id=req.agent_id,
                hostname=req.hostname,
                robots=conn.robot_ids,
                lease_id=conn.lease_id,
                software_version=req.software_version,
                replaced=len(replaced),
                site=req.site,
                replay_addr=replay_addr,
            ),
        )
        yield control_pb2.ControlMessage(
            registered=control_pb2.Registered(
                lease_id=conn.lease_id,
                lease_ttl_s=self.registry.lease_ttl_s,
                heartbeat_interval_s=self.heartbeat_interval_s,
                replay_addr=replay_addr,
                leases=self.registry.leases_of(conn),
            )
        )
        reader_done = threading.Event()
        reader = threading.Thread(
            target=self._read,
            args=(conn, request_iterator, reader_done, who),
            name=f"control-{req.agent_id}",
            daemon=True,
        )
        reader.start()
        try:
            yield from self._outbound(conn, context, reader_done)
        finally:
            hung_up()

    def _first_message(
        self, requests: Iterator[control_pb2.EdgeMessage], context: grpc.ServicerContext
    ) -> control_pb2.EdgeMessage | None:
        """The stream's first message; None when the edge hung up before sending one. Read in a helper thread so
        that a silent stream ends after register_timeout_s instead of holding this server thread forever."""
        box: queue.Queue[control_pb2.EdgeMessage | None] = queue.Queue(maxsize=1)

        def read() -> None:
            try:
                box.put(next(requests, None))
            except Exception:  # cancelled or broken: as if it hung up (the RPC's end wakes this read)
                box.put(None)

        threading.Thread(target=read, name="control-first-message", daemon=True).start()
        deadline = time.monotonic() + self.register_timeout_s
        while True:
            try:
                return box.get(timeout=min(0.5, max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                if not context.is_active():  # the edge went away: free this thread now, not at the deadline
                    return None
                if time.monotonic() >= deadline:
                    context.abort(
                        grpc.StatusCode.DEADLINE_EXCEEDED,
                        f"no register within {self.register_timeout_s:g} s: the first message on Connect must be "
                        "`register`",
                    )

    def _hung_up(self, conn: Connection) -> None:
        if self.registry.disconnect(conn):
            log.info("agent disconnected", extra=kv(agent_id=conn.agent_id, robots=conn.robot_ids))

    def _outbound(
        self, conn: Connection, context: grpc.ServicerContext, reader_done: threading.Event
    ) -> Iterator[control_pb2.ControlMessage]:
        """Commands for this agent, until the edge hangs up or the lease ends."""
        while True:
            try:
                item = conn.outbox.get(timeout=QUEUE_POLL_S)
            except queue.Empty:
                if reader_done.is_set() or not context.is_active():
                    return
                continue
            if isinstance(item, Abort):
                context.abort(item.code, item.message)
            yield item

    def _read(
        self,
        conn: Connection,
        requests: Iterator[control_pb2.EdgeMessage],
        done: threading.Event,
        who: Identity | None = None,
    ) -> None:
        try:
            for msg in requests:
                kind = msg.WhichOneof("msg")
                if kind == "robots":
                    refusal = self._update_robots(conn, msg.robots, who)
                    if refusal is not None:  # like a refused registration: the stream ends with its status
                        conn.outbox.put(refusal)
                        return
                elif kind == "heartbeat":
                    HEARTBEATS.inc()
                    self._rejected(conn, self.registry.heartbeat(conn, msg.heartbeat))
                elif kind == "command_result":
                    res = msg.command_result
                    known = self.registry.command_result(conn, res)
                    log.info(
                        "command result",
                        extra=kv(
                            agent_id=conn.agent_id,
                            command_id=res.command_id[:MAX_TEXT_BYTES],
                            ok=res.ok,
                            message=res.message[:MAX_TEXT_BYTES],
                            known=known,
                        ),
                    )
                else:
                    conn.outbox.put(
                        Abort(
                            grpc.StatusCode.INVALID_ARGUMENT,
                            f"unexpected {kind or 'empty'} message after register; register once per stream",
                        )
                    )
                    return
        except Exception as exc:  # the stream was cancelled or broke: same as hanging up
            log.debug("edge stream read ended", extra=kv(agent_id=conn.agent_id, error=repr(exc)))
        finally:
            done.set()

    @staticmethod
    def _rejected(conn: Connection, rejected: list[Rejected]) -> None:
        """Count dropped heartbeat parts; warn once per stream and reason (an edge repeats a bad value each beat)."""
        for r in rejected:
            HEARTBEAT_REJECTED.labels(r.reason).inc()
            if r.reason not in conn.warned:
                conn.warned.add(r.reason)
                log.warning(
                    "heartbeat part dropped",
                    extra=kv(agent_id=conn.agent_id, robot_id=r.robot_id[:SHOWN_CHARS], reason=r.reason, why=r.why),
                )

    def _update_robots(self, conn: Connection, update: control_pb2.RobotsUpdate, who: Identity | None) -> Abort | None:
        """A hot-plug update: the agent's new robot set, checked as a registration would be."""
        if who is not None and not all(who.owns_robot(s.robot_id) for s in update.robots):
            return Abort(
                grpc.StatusCode.PERMISSION_DENIED,
                f"{who.role} token of {who.name!r} may not register these robots for agent {conn.agent_id!r}",
            )
        try:
            validate_robot_set(update.robots)
            added, removed = self.registry.update_robots(conn, list(update.robots))
        except SpecError as exc:
            return Abort(grpc.StatusCode.INVALID_ARGUMENT, f"bad robots update: {exc}")
        except AlreadyRegistered as exc:
            return Abort(grpc.StatusCode.ALREADY_EXISTS, str(exc))
        ROBOT_SET_UPDATES.inc()
        if added or removed:
            log.info("agent robots changed", extra=kv(agent_id=conn.agent_id, added=added, removed=removed))
        return None

    def ListRobots(
        self, request: control_pb2.ListRobotsRequest, context: grpc.ServicerContext
    ) -> control_pb2.ListRobotsResponse:
        robots = [self._tag(info) for info in self.registry.list(request.include_offline, not request.without_episodes)]
        return control_pb2.ListRobotsResponse(robots=robots)

    def GetRobot(self, request: control_pb2.GetRobotRequest, context: grpc.ServicerContext) -> control_pb2.RobotInfo:
        info = self.registry.info(request.robot_id)
        if info is None:
            context.abort(grpc.StatusCode.NOT_FOUND, f"unknown robot {clipped(request.robot_id)}")
        return self._tag(info)

    def ForgetRobot(
        self, request: control_pb2.ForgetRobotRequest, context: grpc.ServicerContext
    ) -> control_pb2.ForgetRobotResponse:
        rid = request.robot_id
        if not ROBOT_ID_RE.fullmatch(rid):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"robot_id {clipped(rid)} must match {ROBOT_ID_RE.pattern}")
        try:
            episodes = self.registry.forget(rid)
        except RobotOnline as exc:
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(exc))
        if episodes is None:
            context.abort(grpc.StatusCode.NOT_FOUND, f"unknown robot {rid!r} (userctl robots ls --all lists them)")
        who = rpc.caller(context)
        log.info("robot forgotten by request", extra=kv(robot_id=rid, by=who.name if who is not None else ""))
        return control_pb2.ForgetRobotResponse(robot_id=rid, episodes=episodes)

    def SendCommand(
        self, request: control_pb2.SendCommandRequest, context: grpc.ServicerContext
    ) -> control_pb2.SendCommandResponse:
        cmd = control_pb2.Command()
        cmd.CopyFrom(request.command)
        problem = command_problem(cmd)
        if problem:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, problem)
        if not cmd.command_id:
            cmd.command_id = uuid.uuid4().hex
        wait_s = request.wait_result_s
        if not (math.isfinite(wait_s) and 0 <= wait_s <= MAX_COMMAND_WAIT_S):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"wait_result_s must be in 0..{MAX_COMMAND_WAIT_S}")
        try:
            known, agents, new = self.registry.route(cmd)
        except CommandIdTaken as exc:
            context.abort(grpc.StatusCode.ALREADY_EXISTS, str(exc))
        if not known:
            context.abort(grpc.StatusCode.NOT_FOUND, f"unknown robot {cmd.robot_id!r}")
        kind = control_pb2.CommandKind.Name(cmd.kind).removeprefix("COMMAND_KIND_").lower()
        if new:
            COMMANDS.labels(kind).inc()
        log.info(
            "command" if new else "command sent again: not queued twice",
            extra=kv(command_id=cmd.command_id, kind=kind, robot_id=cmd.robot_id, agents=agents),
        )
        resp = control_pb2.SendCommandResponse(command_id=cmd.command_id, delivered=bool(agents), agents=agents)
        if wait_s > 0 and agents:
            remaining = context.time_remaining()
            if remaining is not None:  # answer before the caller's deadline, with what arrived
                wait_s = min(wait_s, max(0.0, remaining - 0.05))
            status = self.registry.wait_results(cmd.command_id, wait_s)
            if status is not None:
                resp.results.extend(status.results)
        return resp

    def GetCommand(
        self, request: control_pb2.GetCommandRequest, context: grpc.ServicerContext
    ) -> control_pb2.CommandStatus:
        status = self.registry.wait_results(request.command_id, 0.0)
        if status is None:
            context.abort(grpc.StatusCode.NOT_FOUND, f"unknown command {request.command_id[:MAX_TEXT_BYTES]!r}")
        return status

    def RegisterWorker(
        self, request: control_pb2.RegisterWorkerRequest, context: grpc.ServicerContext
    ) -> control_pb2.RegisterWorkerResponse:
        problem = worker_problem(request.worker)
        if problem:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"bad worker: {problem}")
        self.registry.register_worker(request.worker)
        return control_pb2.RegisterWorkerResponse(
            ttl_s=self.registry.worker_ttl_s, interval_s=self.registry.worker_ttl_s / 3
        )

    def ListWorkers(
        self, request: control_pb2.ListWorkersRequest, context: grpc.ServicerContext
    ) -> control_pb2.ListWorkersResponse:
        return control_pb2.ListWorkersResponse(workers=self.registry.workers(request.include_offline))

    def ListExperiments(
        self, request: control_pb2.ListExperimentsRequest, context: grpc.ServicerContext
    ) -> control_pb2.ListExperimentsResponse:
        return control_pb2.ListExperimentsResponse(experiments=self.registry.experiments())

    def GetExperiment(
        self, request: control_pb2.GetExperimentRequest, context: grpc.ServicerContext
    ) -> control_pb2.ExperimentInfo:
        self._check_name(request.name, context)
        info = self.registry.experiment_info(request.name)
        if info is None:
            self._not_found(request.name, context)
        return info

    def StartExperiment(
        self, request: control_pb2.StartExperimentRequest, context: grpc.ServicerContext
    ) -> control_pb2.ExperimentInfo:
        return self._set_running(request.name, True, context)

    def StopExperiment(
        self, request: control_pb2.StopExperimentRequest, context: grpc.ServicerContext
    ) -> control_pb2.ExperimentInfo:
        return self._set_running(request.name, False, context)

    def DefineExperiment(
        self, request: control_pb2.DefineExperimentRequest, context: grpc.ServicerContext
    ) -> control_pb2.ExperimentInfo:
        try:
            exp = parse_definition(request.definition_json)
        except ValueError as exc:  # PluginError and pydantic's field errors are ValueErrors
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc)[:2000])
        except ImportError as exc:  # plug-in params are checked with the learner's registries (torch)
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, f"cannot check plug-in params on this host: {exc}")
        if len(self.registry.experiment_names()) >= MAX_EXPERIMENTS:
            context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, f"control holds {MAX_EXPERIMENTS} experiments already")
        info = self.registry.define_experiment(exp)
        if info is None:
            was = "was removed" if self.registry.was_removed(exp.name) else "exists"
            context.abort(
                grpc.StatusCode.ALREADY_EXISTS,
                f"experiment {exp.name!r} {was} (a name keeps its history, stopped, removed or not: pick another name)",
            )
        who = rpc.caller(context)
        log.info("experiment defined by request", extra=kv(experiment=exp.name, by=who.name if who is not None else ""))
        return info

    def RemoveExperiment(
        self, request: control_pb2.RemoveExperimentRequest, context: grpc.ServicerContext
    ) -> control_pb2.ExperimentInfo:
        self._check_name(request.name, context)
        info, why = self.registry.remove_experiment(request.name)
        if info is None and why:
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, why)
        if info is None:
            self._not_found(request.name, context)
        who = rpc.caller(context)
        log.info("experiment removed by request", extra=kv(experiment=request.name, by=who.name if who else ""))
        return info

    def _set_running(self, name: str, running: bool, context: grpc.ServicerContext) -> control_pb2.ExperimentInfo:
        self._check_name(name, context)
        info = self.registry.set_running(name, running)
        if info is None:
            self._not_found(name, context)
        who = rpc.caller(context)
        log.info(
            "experiment " + ("start" if running else "stop") + " requested",
            extra=kv(experiment=name, by=who.name if who is not None else ""),
        )
        return info

    @staticmethod
    def _check_name(name: str, context: grpc.ServicerContext) -> None:
        if not EXPERIMENT_NAME_RE.fullmatch(name):
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"experiment name {name[:64]!r} must match {EXPERIMENT_NAME_RE.pattern}",
            )

    def _not_found(self, name: str, context: grpc.ServicerContext) -> None:
        names = self.registry.experiment_names()
        more = f" and {len(names) - MAX_NAMES_SHOWN} more" if len(names) > MAX_NAMES_SHOWN else ""
        known = ", ".join(names[:MAX_NAMES_SHOWN]) + more or "none"
        context.abort(
            grpc.StatusCode.NOT_FOUND,
            f"unknown experiment {name!r} (known: {known}); experiments come from the stack config or DefineExperiment",
        )


# --------------------------------------------------------------------------- service lifecycle


class ControlService(rpc.GrpcService):
    """The control server in-process: start() binds (port 0 works), stop() ends streams and shuts down."""

    def __init__(self, cfg: StackConfig, start_metrics: bool = True) -> None:
        self.cfg = cfg
        c = cfg.control
        self.state = ControlState(c.state_path) if c.state_path else None
        self.registry = Registry(
            c.lease_ttl_s, c.episodes_kept, self.state, c.worker_ttl_s, experiments=cfg.resolved_experiments()
        )
        self.servicer = ControlServicer(self.registry, c.heartbeat_interval_s, c.replay_shards)
        self.start_metrics = start_metrics
        self.running: rpc.RunningServer | None = None
        self._stop = threading.Event()
        self._reaper: threading.Thread | None = None

    def start(self) -> ControlService:
        try:
            self.running = rpc.start_server(
                "control",
                lambda server: control_pb2_grpc.add_ControlServicer_to_server(self.servicer, server),
                [SERVICE_NAME],
                self.cfg.control.server,
                self.cfg.auth,
                start_metrics=self.start_metrics,
            )
        except BaseException:  # a busy port: the state file's lock goes too, so a retry can take it
            if self.state is not None:
                self.state.close()
                self.state = None
            raise
        self._reaper = threading.Thread(target=self._reap, name="control-reaper", daemon=True)
        self._reaper.start()
        return self

    def _reap(self) -> None:
        period = min(0.5, self.registry.lease_ttl_s / 4)
        while not self._stop.wait(period):
            self.registry.refresh_learners()
            self.registry.prune_workers()
            days = self.cfg.control.forget_offline_after_days
            if days > 0:
                self.registry.forget_offline(days * 86400)
            if self.state is not None:  # the disk may take what waits again although nothing new is written
                self.state.retry()
            for conn in self.registry.expire():
                LEASE_EXPIRATIONS.inc()
                conn.outbox.put(
                    Abort(
                        grpc.StatusCode.ABORTED,
                        f"lease expired: no heartbeat for {self.registry.lease_ttl_s}s; reconnect and register again",
                    )
                )
                log.warning("lease expired", extra=kv(agent_id=conn.agent_id, robots=conn.robot_ids))

    def stop(self) -> None:
        self._stop.set()
        if self._reaper is not None:
            self._reaper.join()
        # End the long-lived streams first so the graceful stop does not wait out its grace on them.
        for conn in self.registry.close_all():
            conn.outbox.put(Abort(grpc.StatusCode.UNAVAILABLE, "control is shutting down"))
        if self.running is not None:
            self.running.stop()
            self.running = None
        if self.state is not None:  # after the streams ended: their robots were saved offline
            self.state.close()
            self.state = None


def run(cfg: StackConfig, ready_file: str | None) -> int:
    rpc.serve_until_signal(ControlService(cfg), "control", ready_file)
    return 0
