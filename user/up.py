"""`userctl up`: the whole stack as local processes on 127.0.0.1, a live console, a report.

Each service is a separate `userctl <service>` process bound to an ephemeral port; it announces
its ports in a ready file, and the supervisor wires the next service to them. Children die
with the supervisor (PR_SET_PDEATHSIG), and Ctrl-C stops them in reverse order so the edges
flush their steps and the learner writes its final checkpoint.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import math
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import grpc
import yaml

from user import owner_lock
from user.config import AuthConfig, StackConfig
from user.log import kv
from user.rpc import make_channel
from user.v1 import (
    control_pb2,
    control_pb2_grpc,
    learner_pb2,
    learner_pb2_grpc,
    replay_pb2,
    replay_pb2_grpc,
)

READY_TIMEOUT_S = 120.0
START_RESTARTS = 2  # a child killed by a signal while starting is started again this many times
SERVICES = ("control", "replay", "learner", "inference")  # servers: restarted on their previous ports
STOP_TIMEOUT_S = 20.0
# stop order (edges are tier 0): edges flush their spools to replay, so replay and control stop last
_STOP_TIER = {"inference": 1, "learner": 1, "replay": 2, "control": 3}
PR_SET_PDEATHSIG = 1
LOCK_FILE = "up.lock"  # held (flock) by the supervisor running the run dir; holds its pid
TOKEN_FILE = "token"  # the generated per-run auth token, mode 0600, for operators' commands

if TYPE_CHECKING:
    from rich.console import Console

log = logging.getLogger(__name__)


def _die_with_parent() -> None:
    """Runs in the child before exec: SIGTERM it when the supervisor dies, however it dies."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


# --------------------------------------------------------------------------- the run directory


class RunDirBusy(RuntimeError):
    """Another `userctl up` holds the run directory."""


def lock_run_dir(run_dir: Path) -> int:
    """Take the run dir for this process: an exclusive flock on run_dir/up.lock, returned as its fd (keep it
    open while the stack runs). The kernel drops the lock when the process dies, however it dies, so a
    `kill -9` leaves no stale lock. Raises RunDirBusy, writing nothing, when another process holds it."""
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        return owner_lock.take(run_dir / LOCK_FILE)
    except owner_lock.Held as held:
        raise RunDirBusy(f"{run_dir} is in use by another `userctl up` (pid {held.holder})") from None


def run_dir_live(run_dir: Path) -> bool:
    """True while a `userctl up` holds run_dir (probed with a shared lock taken and dropped at once)."""
    return owner_lock.holder(run_dir / LOCK_FILE) is not None


def clear_run_dir(run_dir: Path) -> None:
    """--fresh: delete everything but the lock file, which this process holds."""
    for entry in run_dir.iterdir():
        if entry.name == LOCK_FILE:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def _token_configured(auth: AuthConfig) -> bool:
    return bool(auth.token or auth.token_file or os.environ.get("USER_TOKEN"))


def write_run_token(run_dir: Path, token: str) -> Path:
    """run_dir/token, created 0600 before the secret goes in (never readable by others, even briefly)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path, tmp = run_dir / TOKEN_FILE, run_dir / f"{TOKEN_FILE}.tmp"
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(token + "\n")
    os.replace(tmp, path)
    return path


def _same_address(a: str, b: str) -> bool:
    loopback = {"127.0.0.1", "localhost"}
    (host_a, _, port_a), (host_b, _, port_b) = a.rpartition(":"), b.rpartition(":")
    return port_a == port_b and (host_a == host_b or {host_a, host_b} <= loopback)


def ops_target(cfg: StackConfig, control: str | None) -> tuple[str, AuthConfig]:
    """Where operators' commands (`userctl robots|workers|command|exp`) call, and with which auth.

    While a `userctl up` of this config runs (it holds up.runs_dir/up.name), its control is the default
    address, and its generated token is used when no token is configured (auth.token, $USER_TOKEN,
    auth.token_file) and the call goes to that control. Otherwise: --control, else edge.control_addr."""
    run_dir = cfg.up.runs_dir / cfg.up.name
    run_addr = _live_control_addr(run_dir)
    target = control or run_addr or cfg.edge.control_addr
    auth = cfg.auth
    token_path = run_dir / TOKEN_FILE
    if (
        auth.enabled
        and not _token_configured(auth)
        and run_addr
        and _same_address(target, run_addr)
        and token_path.exists()
    ):
        auth = auth.model_copy(update={"token": token_path.read_text().strip()})
    return target, auth


def _live_control_addr(run_dir: Path) -> str | None:
    """The control address a running `userctl up` announced in run_dir, or None."""
    if not run_dir_live(run_dir):
        return None
    try:
        port = json.loads((run_dir / "ready" / "control.json").read_text())["grpc_port"]
    except (OSError, ValueError, KeyError):
        return None
    return f"127.0.0.1:{port}"


def robots_value(robots: list[dict[str, Any]]) -> str:
    """edge.robots as a --set value: YAML flow style, which the child's --set parser (yaml.safe_load) reads back
    exactly, NaN and Inf params included (.nan, .inf); JSON has no NaN."""
    return yaml.safe_dump(robots, default_flow_style=True, width=math.inf, sort_keys=False).strip()


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    ready_file: Path
    log_path: Path
    info: dict[str, Any] = field(default_factory=dict)
    cmd: list[str] = field(default_factory=list)
    env: dict[str, str] | None = None
    restarts: int = 0  # while starting
    crashes: int = 0  # mid-run deaths the supervisor started it again after
    restart_codes: list[int] = field(default_factory=list)  # exit code of each death it was started again after
    log_cap_failed: bool = False  # capping its log failed once (said once, not every pass)

    def launch(self) -> None:
        with open(self.log_path, "ab") as log_file:
            self.proc = subprocess.Popen(
                self.cmd,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=self.env,
                preexec_fn=_die_with_parent,
                start_new_session=True,  # Ctrl-C reaches only the supervisor, which stops children in order
            )

    @property
    def grpc_addr(self) -> str:
        return f"127.0.0.1:{self.info['grpc_port']}"

    @property
    def metrics_url(self) -> str:
        return f"http://127.0.0.1:{self.info['metrics_port']}/metrics"

    def log_tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class Stack:
    """Starts control -> replay -> learner -> inference -> edges, each its own process."""

    def __init__(
        self,
        cfg: StackConfig,
        config_path: str | None,
        overrides: list[str],
        run_dir: Path,
        per_edge_overrides: dict[int, list[str]] | None = None,
    ) -> None:
        self.cfg = cfg
        self.per_edge_overrides = per_edge_overrides or {}
        self.config_path = config_path
        self.overrides = list(overrides)
        self.run_dir = run_dir
        self.children: list[Child] = []
        # edge -> the edge.robots entry (of this config) its one robot comes from: an edge's errors say edge.robots[0]
        self.edge_entries: dict[str, int] = {}
        self.env = dict(os.environ)
        self.token_path: Path | None = None  # where the generated token is, for operators
        if cfg.auth.enabled and not _token_configured(cfg.auth):
            # A fresh secret per run: the children inherit it; operators read it from the run dir (mode 0600).
            self.env["USER_TOKEN"] = secrets.token_hex(16)
            self.token_path = write_run_token(run_dir, self.env["USER_TOKEN"])
        else:  # a previous run's token would mislead operators' commands
            (run_dir / TOKEN_FILE).unlink(missing_ok=True)
        self.env.setdefault("MUJOCO_GL", "egl")
        self.env["PYTHONUNBUFFERED"] = "1"
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            self.env.setdefault(var, "1")
        # glibc's per-thread arenas keep freed large buffers (replay's sample batches) as RSS: 2 arenas cap that
        # at no measured speed cost (docs/notes/ops.md); the Dockerfile and the systemd unit set the same
        self.env.setdefault("MALLOC_ARENA_MAX", "2")

    @property
    def auth(self):
        auth = self.cfg.auth.model_copy()
        if self.env.get("USER_TOKEN") and not auth.token:
            auth.token = self.env["USER_TOKEN"]
        return auth

    def child(self, name: str) -> Child:
        return next(c for c in self.children if c.name == name)

    def _spawn(self, name: str, service: str, extra: list[str]) -> Child:
        ready = self.run_dir / "ready" / f"{name}.json"
        ready.unlink(missing_ok=True)
        log_path = self.run_dir / "logs" / f"{name}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "user.cli", service]
        if self.config_path:
            cmd += ["--config", self.config_path]
        for item in [*self.overrides, *extra]:
            cmd += ["--set", item]
        cmd += ["--ready-file", str(ready)]
        child = Child(name, None, ready, log_path, cmd=cmd, env=self.env)  # type: ignore[arg-type]
        child.launch()
        self.children.append(child)
        return child

    def _wait_ready(self, child: Child) -> None:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline:
            if child.ready_file.exists():
                child.info = json.loads(child.ready_file.read_text())
                return
            code = child.proc.poll()
            if code is not None and code < 0 and child.restarts < START_RESTARTS:
                # Killed by a signal while starting (a native library aborting): a supervisor restarts it.
                child.restarts += 1
                child.restart_codes.append(code)
                log.warning("child crashed while starting; restarting", extra=kv(child=child.name, code=code))
                child.launch()
                continue
            if code is not None:
                raise RuntimeError(f"{child.name} exited with {code}:\n{child.log_tail()}")
            time.sleep(0.05)
        raise RuntimeError(f"{child.name} not ready after {READY_TIMEOUT_S:.0f}s:\n{child.log_tail()}")

    def start(self, on_progress: Callable[[str], None] = lambda _msg: None) -> None:
        self.start_services(on_progress)
        edges = []
        for i, robot in enumerate(self._edge_robots()):
            on_progress(f"edge-{i}")
            self.edge_entries[f"edge-{i}"] = max(0, i - self.cfg.up.edge_agents + 1)
            edges.append(
                self.spawn_edge(f"edge-{i}", [robot], self.cfg.edge.seed + 1000 * i, self.per_edge_overrides.get(i, []))
            )
        for edge in edges:
            self._wait_ready(edge)

    def spawn_edge(self, name: str, robots: list[dict[str, Any]], seed: int, extra: Sequence[str] = ()) -> Child:
        """An edge agent process `name` driving `robots` (RobotConfig dicts), wired to the running services.
        Not waited for: wait_ready() it (several edges start faster side by side)."""
        return self._spawn(name, "edge", self.edge_overrides(name, robots, seed, extra))

    def edge_overrides(
        self, name: str, robots: list[dict[str, Any]], seed: int, extra: Sequence[str] = ()
    ) -> list[str]:
        """The --set items of edge `name`'s command line."""
        control, replay = self.child("control"), self.child("replay")
        inference, learner = self.child("inference"), self.child("learner")
        return [
            f"edge.agent_id={name}",
            f"edge.robots={robots_value(robots)}",
            f"edge.seed={seed}",
            "edge.metrics_port=0",
            f"edge.control_addr={control.grpc_addr}",
            f"edge.replay_addr={replay.grpc_addr}",
            f"edge.inference_addr={inference.grpc_addr}",
            f"edge.learner_addr={learner.grpc_addr}",
            f"edge.spool_dir={self.run_dir / 'spool'}",
            *extra,
        ]

    def wait_ready(self, child: Child) -> None:
        self._wait_ready(child)

    def start_services(self, on_progress: Callable[[str], None] = lambda _msg: None) -> None:
        """control -> replay -> learner -> inference, each ready before the next starts."""
        rd = self.run_dir
        listen = ["server.host=127.0.0.1", "server.port=0", "server.metrics_port=0"]
        on_progress("control")
        control = self._spawn(
            "control", "control", [*(f"control.{x}" for x in listen), f"control.state_path={rd / 'control.sqlite'}"]
        )
        self._wait_ready(control)
        on_progress("replay")
        replay = self._spawn(
            "replay",
            "replay",
            [
                *(f"replay.{x}" for x in listen),
                f"replay.path={rd / 'replay'}",
                f"replay.control_addr={control.grpc_addr}",
            ],
        )
        self._wait_ready(replay)
        on_progress("learner")
        learner = self._spawn(
            "learner",
            "learner",
            [
                *(f"learner.{x}" for x in listen),
                f"learner.checkpoint_dir={rd / 'checkpoints'}",
                f"learner.replay_addr={replay.grpc_addr}",
                f"learner.control_addr={control.grpc_addr}",
            ],
        )
        self._wait_ready(learner)
        on_progress("inference")
        inference = self._spawn(
            "inference",
            "inference",
            [
                *(f"inference.{x}" for x in listen),
                f"inference.learner_addr={learner.grpc_addr}",
                f"inference.control_addr={control.grpc_addr}",
            ],
        )
        self._wait_ready(inference)

    def _edge_robots(self) -> list[dict[str, Any]]:
        """One edge agent per robot: up.edge_agents copies of the first robot entry, numbered on from its id
        (arm-0 -> arm-0, arm-1, ...; arm-9 -> arm-9, arm-10, ...; panda -> panda-0, ...), then each further entry
        once (another embodiment beside them)."""
        first, *others = self.cfg.edge.robots
        numbered = re.fullmatch(r"(.*)-(\d+)", first.id)
        base_id, start = (numbered.group(1), int(numbered.group(2))) if numbered else (first.id, 0)
        # Python mode: JSON mode would turn a NaN or Inf param into null (robots_value keeps them)
        dump = {**first.model_dump(exclude_none=True)}
        robots = [{**dump, "id": f"{base_id}-{start + i}"} for i in range(self.cfg.up.edge_agents)]
        return robots + [r.model_dump(exclude_none=True) for r in others]

    def cap_logs(self, max_bytes: int) -> None:
        """Copy-and-truncate each child's log past `max_bytes` (as logrotate's copytruncate): children keep
        writing to their open O_APPEND file, which continues from 0; lines written between copy and truncate
        are lost, a few at most."""
        for child in self.children:
            try:
                if max_bytes <= 0 or child.log_path.stat().st_size <= max_bytes:
                    continue
                shutil.copyfile(child.log_path, child.log_path.with_name(child.log_path.name + ".1"))
                os.truncate(child.log_path, 0)
            except OSError as exc:  # a full disk must not stop the run: the log keeps growing, said once
                if not child.log_cap_failed:
                    log.warning("log not capped", extra=kv(child=child.name, error=str(exc)))
                child.log_cap_failed = True

    def dead_children(self) -> list[Child]:
        return [c for c in self.children if c.proc.poll() is not None]

    def restart(self, child: Child) -> None:
        """Start a dead child again where the others expect it: a service on its previous gRPC and metrics ports
        (edges and the other services keep their addresses and reconnect), with its state where it left it
        (control's SQLite, replay's LMDB, the learner's checkpoints, an edge's spool)."""
        if child.name in SERVICES and "grpc_port" in child.info:
            at = child.cmd.index("--ready-file")
            pinned = [f"{child.name}.server.port={child.info['grpc_port']}"]
            if child.info.get("metrics_port"):
                pinned.append(f"{child.name}.server.metrics_port={child.info['metrics_port']}")
            child.cmd = [*child.cmd[:at], *(x for p in pinned for x in ("--set", p)), *child.cmd[at:]]
        child.crashes += 1
        child.restart_codes.append(child.proc.returncode)
        log.warning(
            "child died mid-run; starting it again",
            extra=kv(child=child.name, code=child.proc.returncode, crashes=child.crashes),
        )
        child.ready_file.unlink(missing_ok=True)
        child.launch()
        self._wait_ready(child)

    def restart_dead(self, max_restarts: int) -> Child | None:
        """Start every dead child again; the first that has died more than max_restarts times is returned (the
        run should stop), else None."""
        for child in self.dead_children():
            if child.crashes >= max_restarts:
                return child
            self.restart(child)
        return None

    def restarts(self) -> dict[str, list[int]]:
        """Per child started again at least once, the exit code of each death before it."""
        return {c.name: list(c.restart_codes) for c in self.children if c.restart_codes}

    def stop(self) -> dict[str, int | None]:
        """SIGTERM tier by tier, the edges first (they flush to replay), then inference and the learner together,
        then replay, then control; each tier's processes stop side by side, stragglers get SIGKILL. Returns exit
        codes."""
        tiers: dict[int, list[Child]] = {}
        for child in self.children:
            tiers.setdefault(_STOP_TIER.get(child.name, 0), []).append(child)
        for tier in sorted(tiers):
            live = [c for c in tiers[tier] if c.proc.poll() is None]
            for child in live:
                child.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + STOP_TIMEOUT_S
            for child in live:
                try:
                    child.proc.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    child.proc.kill()
                    child.proc.wait()
        return {c.name: c.proc.returncode for c in self.children}


# --------------------------------------------------------------------------- monitoring


@dataclass
class Episode:
    robot_id: str
    episode_id: str
    t: float  # seconds since start (supervisor clock)
    success: bool
    episode_return: float
    length: int
    policy_version: int
    experiment: str = ""
    intervention_steps: int = 0  # steps a teleoperator drove


@dataclass
class Snapshot:
    t: float
    robots: list[control_pb2.RobotInfo]
    learner: learner_pb2.LearnerStatus | None
    replay: replay_pb2.StatsResponse | None
    faults: dict[str, RobotFault] = field(default_factory=dict)  # robot_id -> why it failed (the edges' metrics)


@dataclass(frozen=True)
class RobotFault:
    """A robot its edge reports as failed (a plug-in error stopped it for good) or failing (its loop keeps failing
    soon after each reconnect): control only sees such a robot go offline."""

    state: str  # "failed" or "failing"
    error: str


FAULT_SAMPLE = "user_edge_robot_fault_info"  # edge_agent.agent's ROBOT_FAULT, as Prometheus exposes an Info


def edge_faults(metrics_text: str) -> dict[str, RobotFault]:
    """The robots an edge's /metrics page reports as failed or failing."""
    from prometheus_client.parser import text_string_to_metric_families

    lines = "\n".join(line for line in metrics_text.splitlines() if line.startswith(FAULT_SAMPLE + "{"))
    return {
        sample.labels["robot_id"]: RobotFault(sample.labels.get("state", ""), sample.labels.get("error", ""))
        for family in text_string_to_metric_families(lines + "\n")
        for sample in family.samples
        if sample.name == FAULT_SAMPLE and "robot_id" in sample.labels
    }


def _in_entry(fault: RobotFault, entry: int) -> RobotFault:
    """A fault of an edge started with one robot (edge.robots[0] there) naming that robot's entry in up's config."""
    return RobotFault(fault.state, fault.error.replace("edge.robots[0]", f"edge.robots[{entry}]"))


class Monitor:
    """Polls control, learner and replay; accumulates this session's finished episodes.

    Control keeps episodes across runs: on a resumed run dir, the ones that ended before `session_start_ns`
    (wall clock) are only counted (`earlier`), so plots, the stop rule and its time cover this session."""

    def __init__(self, stack: Stack, t0: float, session_start_ns: int = 0) -> None:
        auth = stack.auth
        self.t0 = t0
        self.session_start_ns = session_start_ns
        self.earlier: set[tuple[str, str]] = set()
        self.control = control_pb2_grpc.ControlStub(make_channel(stack.child("control").grpc_addr, auth))
        self.learner = learner_pb2_grpc.LearnerStub(make_channel(stack.child("learner").grpc_addr, auth))
        self.replay = replay_pb2_grpc.ReplayStub(make_channel(stack.child("replay").grpc_addr, auth))
        self.episodes: dict[tuple[str, str], Episode] = {}
        self.stack = stack
        self._edge_faults: dict[str, dict[str, RobotFault]] = {}  # edge -> its last report
        self._announced: set[tuple[str, RobotFault]] = set()

    def poll_faults(self) -> dict[str, RobotFault]:
        """Failed and failing robots, from each edge's metrics (an edge that does not answer keeps its last report)."""
        for child in self.stack.children:
            if not child.name.startswith("edge-") or not child.info.get("metrics_port"):
                continue
            try:
                with urllib.request.urlopen(child.metrics_url, timeout=1) as answer:
                    faults = edge_faults(answer.read().decode(errors="replace"))
            except OSError:
                continue
            if (entry := self.stack.edge_entries.get(child.name)) is not None:
                faults = {rid: _in_entry(fault, entry) for rid, fault in faults.items()}
            self._edge_faults[child.name] = faults
        return {rid: fault for faults in self._edge_faults.values() for rid, fault in faults.items()}

    def new_faults(self, faults: dict[str, RobotFault]) -> list[tuple[str, RobotFault]]:
        """Faults not shown yet (each is printed once)."""
        fresh = [(rid, fault) for rid, fault in sorted(faults.items()) if (rid, fault) not in self._announced]
        self._announced.update(fresh)
        return fresh

    def poll(self) -> Snapshot:
        now = time.monotonic() - self.t0
        robots, learner, replay = [], None, None
        try:
            robots = list(
                self.control.ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=2).robots
            )
        except grpc.RpcError:
            pass
        try:
            learner = self.learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=2)
        except grpc.RpcError:
            pass
        try:
            replay = self.replay.Stats(replay_pb2.StatsRequest(), timeout=2)
        except grpc.RpcError:
            pass
        self.record_episodes(robots, now)
        return Snapshot(now, robots, learner, replay, self.poll_faults())

    def record_episodes(self, robots: list[control_pb2.RobotInfo], now: float) -> None:
        """Take the episodes not seen yet, stamped `now` (seconds into the session); earlier runs' only counted."""
        for info in robots:
            for ep in info.recent_episodes:
                key = (ep.robot_id or info.spec.robot_id, ep.episode_id)
                if key in self.episodes or key in self.earlier:
                    continue
                if 0 < ep.ended_at_ns < self.session_start_ns:
                    self.earlier.add(key)
                    continue
                self.episodes[key] = Episode(
                    key[0],
                    ep.episode_id,
                    now,
                    ep.success,
                    ep.episode_return,
                    ep.length,
                    ep.policy_version,
                    info.experiment,
                    ep.intervention_steps,
                )

    def ordered(self) -> list[Episode]:
        return sorted(self.episodes.values(), key=lambda e: (e.t, e.robot_id, e.episode_id))

    def success_rate(self, window: int, experiment: str | None = None, autonomous: bool = True) -> float | None:
        """Over the last `window` episodes (of `experiment`'s robots when given); None until there are that many.

        `autonomous` (the stop rule's count) leaves out episodes a teleoperator drove any step of: an
        expert's rescue is not the policy's success. False counts every episode (shown beside it)."""
        eps = [
            e
            for e in self.ordered()
            if (experiment is None or e.experiment == experiment) and not (autonomous and e.intervention_steps)
        ][-window:]
        if len(eps) < window:
            return None
        return sum(e.success for e in eps) / len(eps)


def target_experiment(cfg: StackConfig) -> str:
    """The experiment whose success stops `userctl up` (up.target_experiment, default the first)."""
    return cfg.up.target_experiment or cfg.resolved_experiments()[0].name


def _scalars_text(scalars: Any, limit: int = 2) -> str:
    return " ".join(f"{k}={v:.3g}" for k, v in sorted(scalars.items())[:limit]) or "-"


NARROW_COLUMNS = 120  # below this terminal width the console leaves out the columns marked wide
ROBOT_WIDE = ("steps", "p99", "human")
LEARNER_WIDE = ("sync", "buffer")


def _render(snap: Snapshot, mon: Monitor, cfg: StackConfig, budget_s: float, width: int = 160):
    """The live console: a row per robot, a row per experiment. Below NARROW_COLUMNS (an 80-column terminal) it
    drops the wide columns and the borders' padding so every header stays readable."""
    from rich import box
    from rich.console import Group
    from rich.table import Table

    narrow = width < NARROW_COLUMNS
    style: dict[str, Any] = {"box": box.SIMPLE_HEAD, "padding": (0, 1), "pad_edge": False} if narrow else {}
    versions = {e.name: e.weight_version for e in snap.learner.experiments} if snap.learner else {}
    window = cfg.up.window_episodes
    robots = Table(
        title=f"USER · {cfg.up.name} · {snap.t:5.0f}s / {budget_s:.0f}s",
        caption=f"success: each robot's last {window} episodes without human help (all episodes in brackets;"
        f" the stop rule counts experiment {target_experiment(cfg)}'s unhelped ones)"
        " · stale = learner version - acting version · p99 = control-loop period (ms)"
        " · spool = steps on the edge awaiting replay's ack (FULL: at its cap)",
        expand=True,
        **style,
    )
    rows = [_robot_cells(info, mon, versions, window, snap.faults) for info in sorted(snap.robots, key=_by_experiment)]
    _fill(robots, rows, ROBOT_COLUMNS, ROBOT_WIDE if narrow else ())
    experiments = list(snap.learner.experiments) if snap.learner else []
    rows = [_experiment_cells(exp, snap.learner, mon, window) for exp in experiments]
    # Narrow: each experiment's scalars on a line under the table instead of a column folded to a few letters.
    caption = "\n".join(f"{r['experiment']}: {r['scalars']}" for r in rows) if narrow else None
    learner = Table(expand=True, caption=caption, caption_justify="left", **style)
    _fill(learner, rows, LEARNER_COLUMNS, (*LEARNER_WIDE, "scalars") if narrow else ())
    return Group(robots, learner)


# Header -> left-justified; headers are short so the tables stay readable in an 80-column terminal.
ROBOT_COLUMNS = {
    "robot": True,
    "exp": True,
    "state": False,
    "eps": False,
    "success": False,
    "steps": False,
    "steps/s": False,
    "policy": False,
    "stale": False,
    "p99": False,
    "spool": False,
    "human": False,
}
LEARNER_COLUMNS = {
    "experiment": True,
    "algo": True,
    "state": True,
    "updates": False,
    "updates/s": False,
    "weights": False,
    "sync": False,
    "buffer": False,
    "scalars": True,
    "success": False,
}


def _fill(table: Any, rows: list[dict[str, str]], columns: dict[str, bool], leave_out: Sequence[str]) -> None:
    """Columns whose headers never shrink below their own width (long cells fold), then the rows."""
    shown = [c for c in columns if c not in leave_out]
    for col in shown:
        overflow = "fold" if col == "scalars" else "ellipsis"
        table.add_column(col, justify="left" if columns[col] else "right", min_width=len(col), overflow=overflow)
    for row in rows:
        table.add_row(*(row[c] for c in shown))


def _by_experiment(info: control_pb2.RobotInfo) -> tuple[str, str]:
    return info.experiment, info.spec.robot_id


def _robot_cells(
    info: control_pb2.RobotInfo,
    mon: Monitor,
    versions: dict[str, int],
    window: int,
    faults: dict[str, RobotFault] | None = None,
) -> dict[str, str]:
    st, rid, faults = info.status, info.spec.robot_id, faults or {}
    mine = [e for e in mon.ordered() if e.robot_id == rid]
    state = control_pb2.RobotState.Name(st.state).removeprefix("ROBOT_STATE_").lower() if info.online else "offline"
    if (fault := faults.get(rid)) is not None:  # control sees only "offline": the edge knows it failed
        state = fault.state.upper() if fault.state == "failed" else fault.state
    return {
        "robot": rid,
        "exp": info.experiment or "-",
        "state": state,
        "eps": str(len(mine)),  # this session's, as the success column (control's count is all-time)
        "success": _rate_cell([e for e in mine if not e.intervention_steps][-window:], mine[-window:]),
        "steps": str(st.env_steps),
        "steps/s": f"{st.env_steps_per_s:.1f}",
        "policy": str(st.policy_version),
        "stale": str(max(0, versions.get(info.experiment, 0) - st.policy_version)),
        "p99": f"{st.loop_period_p99_ms:.1f}",
        "spool": f"{st.spool_steps}{' FULL' if st.spool_full else ''}",
        "human": str(st.intervention_steps),
    }


def _state_cell(exp: learner_pb2.ExperimentStatus) -> str:
    """The learner's state, with why it failed, or why it has no batch yet (an empty table, a refused sample)."""
    why = exp.error or (exp.waiting_for if exp.state != "training" else "")
    errors = f" ({exp.sample_errors} sample errors)" if exp.sample_errors else ""
    return f"{exp.state}: {why[:60]}{errors}" if why else exp.state + errors


def _experiment_cells(
    exp: learner_pb2.ExperimentStatus, status: learner_pb2.LearnerStatus, mon: Monitor, window: int
) -> dict[str, str]:
    rate, rate_all = mon.success_rate(window, exp.name), mon.success_rate(window, exp.name, autonomous=False)
    return {
        "experiment": exp.name,
        "algo": exp.algorithm,
        "state": _state_cell(exp),
        "updates": str(exp.updates),
        "updates/s": f"{exp.updates_per_s:.1f}",
        "weights": str(exp.weight_version),
        "sync": _sync_cell(status, exp.name),
        "buffer": str(exp.buffer_transitions),
        "scalars": _scalars_text(exp.scalars),
        "success": ("-" if rate is None else f"{100 * rate:.0f} %")
        + ("" if rate_all is None or rate_all == rate else f" ({100 * rate_all:.0f} %)"),
    }


def _rate_cell(autonomous: list[Episode], every: list[Episode]) -> str:
    """ "80 % (20)" over unhelped episodes, with the rate over all episodes in brackets when they differ."""
    if not every:
        return "-"
    cell = "-"
    if autonomous:
        cell = f"{100 * sum(e.success for e in autonomous) / len(autonomous):.0f} % ({len(autonomous)})"
    if len(autonomous) != len(every):
        cell += f" [{100 * sum(e.success for e in every) / len(every):.0f} % all]"
    return cell


def _sync_cell(lr: learner_pb2.LearnerStatus, experiment: str) -> str:
    """Slowest subscriber's publish -> applied latency and its staleness in versions, e.g. "120ms +1"."""
    subs = [s for s in lr.subscriber_status if s.experiment in (experiment, "")]
    if not subs:
        return "-"
    worst = max(subs, key=lambda s: (s.staleness, s.sync_latency_s))
    return f"{worst.sync_latency_s * 1e3:.0f}ms +{worst.staleness}"


def write_report(run_dir: Path, episodes: list[Episode], summary: dict[str, Any], window: int) -> None:
    """metrics.json and report.png (rolling success rate and return against this session's wall time; a resumed
    run's earlier episodes are only counted, in summary["earlier_episodes"] and the title)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    rolling = _rolling(episodes, window)
    rolling_autonomous = _rolling(episodes, window, autonomous=True)
    doc = {
        **summary,
        "episodes": [
            {
                "t": round(e.t, 3),
                "robot_id": e.robot_id,
                "success": e.success,
                "return": e.episode_return,
                "length": e.length,
                "policy_version": e.policy_version,
                "experiment": e.experiment,
                "intervention_steps": e.intervention_steps,
            }
            for e in episodes
        ],
        "rolling_success": [round(r, 4) for r in rolling],
        # per episode: success over the last `window` episodes nobody intervened in (None before the first)
        "rolling_success_autonomous": [None if r is None else round(r, 4) for r in rolling_autonomous],
    }
    tmp = run_dir / "metrics.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, run_dir / "metrics.json")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for name in sorted({e.experiment for e in episodes}):
        mine = [e for e in episodes if e.experiment == name]
        auto = _rolling(mine, window, autonomous=True)
        line = ax1.plot(
            [e.t for e in mine], [None if r is None else 100 * r for r in auto], label=f"{name or 'run'} (no help)"
        )
        if any(e.intervention_steps for e in mine):  # every episode, helped ones too: dashed, same colour
            ax1.plot(
                [e.t for e in mine],
                [100 * r for r in _rolling(mine, window)],
                linestyle="--",
                color=line[0].get_color(),
                label=f"{name or 'run'} (all episodes)",
            )
    if episodes:
        ax1.legend(loc="lower right")
    ax1.axhline(100 * summary.get("target_success", 0.9), color="grey", linestyle="--", linewidth=1)
    ax1.set_ylabel(f"success rate, last {window} episodes (%)")
    ax1.set_ylim(-2, 102)
    for rid in sorted({e.robot_id for e in episodes}):
        mine = [e for e in episodes if e.robot_id == rid]
        ax2.plot([e.t for e in mine], [e.episode_return for e in mine], ".", markersize=3, label=rid)
    ax2.set_ylabel("episode return")
    ax2.set_xlabel("wall time (s)")
    if episodes:
        ax2.legend(loc="lower right")
    fig.suptitle(_report_title(summary))
    fig.tight_layout()
    fig.savefig(run_dir / "report.png", dpi=100)
    plt.close(fig)


def _report_title(summary: dict[str, Any]) -> str:
    title = summary.get("name", "")
    if summary.get("time_to_target_s") is not None:
        title += f" — {100 * summary['target_success']:.0f} % success after {summary['time_to_target_s']:.0f} s"
    if summary.get("earlier_episodes"):
        title += f"\nthis session only; {summary['earlier_episodes']} episodes of earlier runs not shown"
    return title


def _rolling(episodes: list[Episode], window: int, autonomous: bool = False) -> list[float | None]:
    """Per episode, the success rate over the last `window` episodes up to it (only those nobody
    intervened in when `autonomous`; None while there are none)."""
    out: list[float | None] = []
    recent: list[bool] = []
    for e in episodes:
        if not (autonomous and e.intervention_steps):
            recent = [*recent[-(window - 1) :], e.success] if window > 1 else [e.success]
        out.append(sum(recent) / len(recent) if recent else None)
    return out


def run_up(cfg: StackConfig, config_path: str | None, overrides: list[str], fresh: bool = False) -> int:
    """The whole stack on one run dir, which this process holds for its life; 2 when another `up` holds it."""
    from rich.console import Console

    console = Console()
    run_dir = cfg.up.runs_dir / cfg.up.name
    try:
        lock_fd = lock_run_dir(run_dir)  # before anything else: a live run's data must not be touched
    except RunDirBusy as exc:
        print(f"userctl up: {exc}; nothing started or changed", file=sys.stderr)
        return 2
    try:
        if fresh:
            clear_run_dir(run_dir)
        elif any(entry.name != LOCK_FILE for entry in run_dir.iterdir()):
            console.print(f"[yellow]resuming {run_dir}: replay and learner checkpoints are kept (--fresh starts over)")
        return _run_stack(console, cfg, config_path, overrides, run_dir)
    finally:
        os.close(lock_fd)


def _run_stack(console: Console, cfg: StackConfig, config_path: str | None, overrides: list[str], run_dir: Path) -> int:
    from rich.live import Live
    from rich.markup import escape

    stack = Stack(cfg, config_path, overrides, run_dir)
    if stack.token_path is not None:
        console.print(f"auth token in {stack.token_path} (mode 0600; `userctl robots ls` etc. use it)", soft_wrap=True)
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    budget_s = cfg.up.budget_s
    reason, time_to_target, mon = "interrupted", None, None
    t0, session_start_ns = time.monotonic(), time.time_ns()
    try:
        with console.status("starting") as status:
            stack.start(lambda name: status.update(f"starting {name}"))
        console.print(f"[green]stack up in {time.monotonic() - t0:.1f}s; logs in {run_dir / 'logs'}")
        t0 = time.monotonic()
        mon = Monitor(stack, t0, session_start_ns)
        snap = mon.poll()
        live_view = (
            Live(
                _render(snap, mon, cfg, budget_s, console.width),
                console=console,
                refresh_per_second=2,
                transient=False,
            )
            if cfg.up.console
            else contextlib.nullcontext()
        )
        with live_view as live:
            while not stop.wait(0.5):
                snap = mon.poll()
                stack.cap_logs(int(cfg.up.log_max_mb * 2**20))
                for rid, fault in mon.new_faults(snap.faults):
                    console.print(f"[red]robot {escape(rid)} {fault.state}: {escape(fault.error)}", soft_wrap=True)
                if live is not None:
                    live.update(_render(snap, mon, cfg, budget_s, console.width))
                rate = mon.success_rate(cfg.up.window_episodes, target_experiment(cfg))
                if rate is not None and rate >= cfg.up.target_success:
                    reason, time_to_target = "target reached", snap.t
                    break
                if snap.t >= budget_s:
                    reason = "budget exhausted"
                    break
                for child in stack.dead_children():
                    if child.crashes < cfg.up.max_restarts:
                        console.print(f"[yellow]{child.name} exited with {child.proc.returncode}; starting it again")
                failed = stack.restart_dead(cfg.up.max_restarts)
                if failed is not None:
                    reason = f"{failed.name} exited with {failed.proc.returncode} ({failed.crashes} restarts)"
                    console.print(f"[red]{reason}:\n{failed.log_tail()}")
                    break
    except RuntimeError as exc:
        reason = f"start failed: {exc}"
        console.print(f"[red]{reason}")
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not orphan children mid-stop
        with console.status("stopping"):
            final = mon.poll() if mon else None
            codes = stack.stop()
        signal.signal(signal.SIGINT, signal.default_int_handler)
    episodes = mon.ordered() if mon else []
    summary = _summary(
        cfg,
        reason,
        time_to_target,
        final,
        episodes,
        codes,
        time.monotonic() - t0,
        restarts=stack.restarts(),
        earlier_episodes=len(mon.earlier) if mon else 0,
    )
    write_report(run_dir, episodes, summary, cfg.up.window_episodes)
    _print_summary(console, summary, run_dir)
    return 0 if time_to_target is not None else 1


def _summary(
    cfg: StackConfig,
    reason: str,
    time_to_target: float | None,
    final: Snapshot | None,
    episodes: list[Episode],
    codes: dict[str, int | None],
    wall_s: float,
    restarts: dict[str, list[int]] | None = None,
    earlier_episodes: int = 0,
) -> dict[str, Any]:
    """metrics.json's document; `episodes` are this session's (`earlier_episodes` more ended in earlier runs).
    The headline success rates are the target experiment's, the one the stop rule watches."""
    target = [e for e in episodes if e.experiment == target_experiment(cfg)]
    window = target[-cfg.up.window_episodes :]
    unhelped = [e for e in target if not e.intervention_steps][-cfg.up.window_episodes :]
    robots = _summary_robots(final)
    learner = final.learner if final else None
    return {
        "name": cfg.up.name,
        "reason": reason,
        "target_success": cfg.up.target_success,
        "time_to_target_s": None if time_to_target is None else round(time_to_target, 1),
        "wall_s": round(wall_s, 1),
        "episodes_total": len(episodes),
        "earlier_episodes": earlier_episodes,
        "final_success_rate": round(sum(e.success for e in window) / len(window), 3) if window else None,
        "final_success_rate_autonomous": round(sum(e.success for e in unhelped) / len(unhelped), 3)
        if unhelped
        else None,
        "episodes_with_interventions": sum(1 for e in episodes if e.intervention_steps),
        "edge_mode": cfg.edge.mode,
        "policy_source": cfg.edge.policy_source,
        "robots": robots,
        "target_experiment": target_experiment(cfg),
        "learner": None
        if learner is None
        else {
            "updates": learner.updates,
            "weight_version": learner.weight_version,
            "updates_per_s": round(learner.updates_per_s, 1),
            "experiments": {
                e.name: {
                    "algorithm": e.algorithm,
                    "state": e.state,
                    "error": e.error,
                    "updates": e.updates,
                    "weight_version": e.weight_version,
                    "robots": list(e.robot_ids),
                    "sample_errors": e.sample_errors,
                    "scalars": {k: round(v, 4) for k, v in sorted(e.scalars.items())},
                    "final_success_rate": _rate(
                        [x for x in episodes if x.experiment == e.name], cfg.up.window_episodes
                    ),
                    "final_success_rate_autonomous": _rate(
                        [x for x in episodes if x.experiment == e.name and not x.intervention_steps],
                        cfg.up.window_episodes,
                    ),
                }
                for e in learner.experiments
            },
        },
        "replay_steps": final.replay.steps if final and final.replay else None,
        "exit_codes": codes,
        "restarts": restarts or {},  # child -> exit code of each death it was started again after
    }


def _summary_robots(final: Snapshot | None) -> dict[str, dict[str, Any]]:
    """Per robot: its last status at control, and its fault when its edge reports one (a robot that failed before
    control heard of it has only the fault)."""
    if final is None:
        return {}
    robots = {info.spec.robot_id: _robot_entry(info.status) for info in final.robots}
    for rid, fault in sorted(final.faults.items()):
        robots.setdefault(rid, _robot_entry(control_pb2.RobotStatus()))["fault"] = {
            "state": fault.state,
            "error": fault.error,
        }
    return robots


def _robot_entry(st: control_pb2.RobotStatus) -> dict[str, Any]:
    return {
        "env_steps": st.env_steps,
        "episodes": st.episodes,
        "successes": st.successes,
        "env_steps_per_s": round(st.env_steps_per_s, 2),
        "policy_version": st.policy_version,
        "loop_period_p99_ms": round(st.loop_period_p99_ms, 2),
        "held_steps": st.held_steps,
        "intervention_steps": st.intervention_steps,
    }


def _rate(episodes: list[Episode], window: int) -> float | None:
    recent = episodes[-window:]
    return round(sum(e.success for e in recent) / len(recent), 3) if recent else None


def _print_summary(console: Console, summary: dict[str, Any], run_dir: Path) -> None:
    from rich.markup import escape
    from rich.table import Table

    console.print()  # Live leaves the cursor after its last line when stdout is not a terminal
    table = Table(title="summary", show_header=False)
    table.add_row("stopped because", summary["reason"])
    ttt = summary["time_to_target_s"]
    table.add_row(f"time to {100 * summary['target_success']:.0f} % success", "-" if ttt is None else f"{ttt:.0f} s")
    earlier = summary.get("earlier_episodes")
    table.add_row("episodes", str(summary["episodes_total"]) + (f" (+{earlier} in earlier runs)" if earlier else ""))
    if summary["final_success_rate"] is not None:
        table.add_row(
            f"success, last episodes of {summary['target_experiment']}",
            _summary_rate(summary["final_success_rate_autonomous"], summary["final_success_rate"]),
        )
    if summary.get("episodes_with_interventions"):
        table.add_row(
            "episodes with interventions",
            f"{summary['episodes_with_interventions']} (left out of success, counted in the all-episodes rate)",
        )
    if summary["learner"]:
        table.add_row("learner updates", str(summary["learner"]["updates"]))
        for name, exp in summary["learner"]["experiments"].items():
            # A learner that cannot train the experiment says so first (control held its robots meanwhile).
            failed = f"FAILED: {exp.get('error') or 'no reason given'}; " if exp.get("state") == "failed" else ""
            rate = _summary_rate(exp["final_success_rate_autonomous"], exp["final_success_rate"])
            table.add_row(
                f"experiment {name}",
                f"{failed}{exp['algorithm']}, {exp['updates']} updates, weights v{exp['weight_version']}, "
                f"success {rate}",
            )
    for rid, st in summary["robots"].items():
        counts = f"{st['env_steps']} steps, {st['episodes']} episodes, policy v{st['policy_version']}"
        fault = st.get("fault")
        table.add_row(escape(rid), escape(f"{fault['state'].upper()}: {fault['error']}; {counts}" if fault else counts))
    robot_faults = {rid: st["fault"]["state"] for rid, st in summary["robots"].items() if st.get("fault")}
    table.add_row("process exits", escape(exits_text(summary["exit_codes"], summary.get("restarts", {}), robot_faults)))
    table.add_row("report", f"{run_dir / 'report.png'}, {run_dir / 'metrics.json'}")
    console.print(table)


def _summary_rate(unhelped: float | None, every: float | None) -> str:
    """The summary's success: over episodes without human help ("-" when every one was helped), the rate
    over all episodes in brackets when it differs."""
    if every is None:
        return "-"
    cell = "-" if unhelped is None else f"{100 * unhelped:.0f} %"
    return cell if unhelped == every else f"{cell} [{100 * every:.0f} % all]"


def exits_text(
    codes: dict[str, int | None], restarts: dict[str, list[int]], robot_faults: dict[str, str] | None = None
) -> str:
    """The summary's "process exits": restarts during the run (a kill -9 the supervisor recovered from is not
    clean), final exits other than 0, and robots an edge reports failed or failing (`robot_faults`: robot_id ->
    state; its process exits cleanly, its robot did not run), else "all clean"."""
    parts = [
        f"{name} restarted {len(deaths)}x (exit {', '.join(str(code) for code in deaths)})"
        for name, deaths in restarts.items()
    ]
    parts += [f"{name} exited with {code}" for name, code in codes.items() if code not in (0, None)]
    parts += [f"robot {rid} {state}" for rid, state in sorted((robot_faults or {}).items())]
    return "; ".join(parts) or "all clean"
