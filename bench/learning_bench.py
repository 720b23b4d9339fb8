"""Asynchronous vs synchronous learning on the same config and machine, in interleaved windows.

Both modes run as whole stacks of real processes (`userctl up`'s Stack: control, replay, learner,
inference, one edge agent per simulated arm at its real control rate), started side by side; only
`learner.mode` differs:

- async (ours): robots act while the learner trains and publishes (the pipeline USER runs);
- sync (baseline): collect `sync_env_steps` transitions, pause the robots, run `sync_updates`
  updates, publish, resume, in turn (what a collect-then-train loop does).

The experiment of both stacks is stopped (Control.StopExperiment: robots hold, the learner idles)
except during its own window; windows alternate A S S A A S ... so the machine's load (shared with
other jobs) falls on both modes alike. Each window counts updates (Learner.GetStatus), env steps
(Control's robot status), each process's CPU seconds (/proc) and the learner's training-thread time
by phase (`user_learner_loop_seconds_total`: update, publish, wait_batch, wait_robots, sample), with
the 1-minute load average at its start and end. Same config, model, batch size and window per mode;
every counted update is one full `Algorithm.update` on a fresh batch in both modes.

Configs: cnn (RLinf-USER's CNN+SAC comparison: 64x64 camera + state, shared CNN encoder, DrQ),
state (SAC on state, full runs), hgdagger (configs/hgdagger.yaml: flow_bc on demos + interventions,
the scripted expert as teleoperator; RLinf-USER: 5.7x training throughput for pi0 + HG-DAgger).
"""

from __future__ import annotations

import os
import statistics
import time
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench import Row

ROOT = Path(__file__).resolve().parents[1]
PEER = "USER sync mode (collect, pause robots, train, publish), same config, interleaved windows"
SYNC_ROUNDS = ["learner.min_transitions=100", "learner.sync_env_steps=100", "learner.sync_updates=100"]
REACH_ONLY = [
    "experiments=[{name: reach, robots: {kinds: [sim_reach_arm]}, algorithm: {kind: sac}}]",
    "edge.robots=[{id: arm-0, kind: sim_reach_arm, params: {control_rate_hz: 20, max_episode_steps: 50}}]",
    "up.edge_agents=2",
    "log_json=true",
    *SYNC_ROUNDS,
]
CNN = [
    "experiments=[{name: reach, robots: {kinds: [sim_reach_arm]}, algorithm: {kind: sac, "
    "params: {features: [camera.front, state], batch_size: 64}}}]",
    "edge.robots=[{id: arm-0, kind: sim_reach_arm, params: {control_rate_hz: 20, max_episode_steps: 50, "
    "camera: true}}]",
    "up.edge_agents=2",
    "log_json=true",
    *SYNC_ROUNDS,
]


@dataclass
class Setup:
    config: Path
    overrides: list[str]
    experiment: str
    what: str  # for the row's group
    rounds: str  # the sync round, for the note


SETUPS = {
    "cnn": Setup(ROOT / "configs" / "demo.yaml", CNN, "reach", "CNN+SAC, 64x64 camera + state", "100 steps/100 upd"),
    "state": Setup(ROOT / "configs" / "demo.yaml", REACH_ONLY, "reach", "SAC from state", "100 steps/100 upd"),
    "hgdagger": Setup(
        ROOT / "configs" / "hgdagger.yaml", [], "lang", "HG-DAgger, flow_bc on lang_reach_arm", "400 steps/200 upd"
    ),
}


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc); 0 once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _threads(pid: int) -> dict[str, tuple[float, float]]:
    """(CPU s, run-queue wait s) per thread name of a process, from /proc/<pid>/task/*/schedstat: a thread
    starved by the machine's load waits on the run queue; one blocked (GIL, a queue) does not."""
    out: dict[str, tuple[float, float]] = {}
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            name = (task / "comm").read_text().strip()
            cpu_ns, wait_ns = (int(x) for x in (task / "schedstat").read_text().split()[:2])
        except (OSError, ValueError):
            continue
        key = name if name in ("train", "sampler") else "other"
        cpu, wait = out.get(key, (0.0, 0.0))
        out[key] = (cpu + cpu_ns / 1e9, wait + wait_ns / 1e9)
    return out


def _load() -> float:
    return round(os.getloadavg()[0], 1)


@dataclass
class Window:
    mode: str
    rep: int
    seconds: float
    updates: int
    env_steps: int
    held_steps: int  # robot ticks without an action in time (the robot held still)
    cpu_s: dict[str, float]  # per process of the stack (edges summed)
    phases_s: dict[str, float]  # the learner's training-thread wall time by phase
    load: tuple[float, float]
    threads: dict[str, tuple[float, float]] = field(default_factory=dict)  # learner: (CPU s, run-queue wait s)

    @property
    def updates_per_s(self) -> float:
        return self.updates / self.seconds

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.seconds


@dataclass
class ModeStack:
    """One stack (one learner.mode) whose experiment runs only during its windows."""

    mode: str
    setup: Setup
    workdir: Path
    extra: list[str]
    stack: Any = None
    stubs: list[Any] = field(default_factory=list)

    def start(self, prep: _HgDaggerPrep | None = None) -> None:
        from user.config import load_config
        from user.rpc import make_channel
        from user.up import Stack
        from user.v1 import control_pb2_grpc, learner_pb2_grpc, replay_pb2_grpc

        overrides = [*self.setup.overrides, f"learner.mode={self.mode}", *self.extra]
        cfg = load_config(self.setup.config, overrides)
        self.run_dir = self.workdir / self.mode
        if prep is not None:
            prep.checkpoint(self.run_dir)
        self.stack = Stack(cfg, str(self.setup.config), overrides, self.run_dir)
        self.stack.start_services()
        auth = self.stack.auth
        self.channels = [make_channel(self.stack.child(n).grpc_addr, auth) for n in ("control", "learner", "replay")]
        self.control = control_pb2_grpc.ControlStub(self.channels[0])
        self.learner = learner_pb2_grpc.LearnerStub(self.channels[1])
        self.replay = replay_pb2_grpc.ReplayStub(self.channels[2])
        self.stop_experiment(wait=False)  # robots hold from their first tick until this stack's window
        edges = [
            self.stack.spawn_edge(f"edge-{i}", [r], cfg.edge.seed + 1000 * i)
            for i, r in enumerate(self.stack._edge_robots())
        ]
        for edge in edges:
            self.stack.wait_ready(edge)
        if prep is not None:
            prep.insert(self)

    def experiment(self) -> Any:
        from user.v1 import learner_pb2

        status = self.learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10)
        return next(e for e in status.experiments if e.name == self.setup.experiment)

    def counts(self) -> tuple[int, int, int]:
        """(learner updates, the robots' env steps, steps they held for want of an action in time) now."""
        from user.v1 import control_pb2

        robots = self.control.ListRobots(control_pb2.ListRobotsRequest(), timeout=10).robots
        steps, held = sum(int(r.status.env_steps) for r in robots), sum(int(r.status.held_steps) for r in robots)
        return int(self.experiment().updates), steps, held

    def cpu(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for child in self.stack.children:
            name = "edges" if child.name.startswith("edge") else child.name
            out[name] = out.get(name, 0.0) + _cpu_s(child.proc.pid)
        return out

    def phases(self) -> dict[str, float]:
        """The learner's `user_learner_loop_seconds_total` by phase (this stack's experiment)."""
        from prometheus_client.parser import text_string_to_metric_families

        port = self.stack.child("learner").info["metrics_port"]
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
        out: dict[str, float] = {}
        for family in text_string_to_metric_families(text):
            for s in family.samples:
                if s.name == "user_learner_loop_seconds_total" and s.labels["experiment"] == self.setup.experiment:
                    out[s.labels["phase"]] = s.value
        return out

    def start_experiment(self) -> None:
        from user.v1 import control_pb2

        self.control.StartExperiment(control_pb2.StartExperimentRequest(name=self.setup.experiment), timeout=10)

    def stop_experiment(self, wait: bool = True) -> None:
        from user.v1 import control_pb2

        self.control.StopExperiment(control_pb2.StopExperimentRequest(name=self.setup.experiment), timeout=10)
        if wait:
            _wait(f"{self.mode} learner stopped", lambda: self.experiment().state == "stopped", 120)

    def _settle(self, per_update_s: float) -> None:
        """Until the training thread has parked: "stopped" is reported at once, but an update in progress
        (seconds each under load) finishes first, and a window of the same mode right after this one
        (A S S A) must not start inside the old one's sync round."""
        quiet_s = min(30.0, max(1.0, 2.0 * per_update_s))
        deadline = time.monotonic() + 120
        last = self.experiment().updates
        while time.monotonic() < deadline:
            time.sleep(quiet_s)
            now = self.experiment().updates
            if now == last:
                return
            last = now

    def warm_up(self, extra_s: float) -> None:
        """Run until the learner has updated (replay past min_transitions), then `extra_s` more; stop."""
        u0 = self.experiment().updates
        self.start_experiment()
        _wait(f"{self.mode} first update", lambda: self.experiment().updates > u0, 300)
        time.sleep(extra_s)
        self.stop_experiment()
        self._settle(5.0)

    def window(self, rep: int, seconds: float) -> Window:
        u0, s0, h0 = self.counts()
        learner_pid = self.stack.child("learner").proc.pid
        c0, p0, t0_threads, load0 = self.cpu(), self.phases(), _threads(learner_pid), _load()
        t0 = time.monotonic()
        self.start_experiment()
        while time.monotonic() - t0 < seconds:
            time.sleep(min(2.0, seconds))
            if self.stack.dead_children():
                raise RuntimeError(f"{self.mode}: children died: {[c.name for c in self.stack.dead_children()]}")
        u1, s1, h1 = self.counts()
        elapsed = time.monotonic() - t0
        c1, p1, t1_threads, load1 = self.cpu(), self.phases(), _threads(learner_pid), _load()
        self.stop_experiment()
        self._settle(2.0 * elapsed / max(u1 - u0, 1))
        exp = self.experiment()
        if exp.sample_errors:
            raise RuntimeError(f"{self.mode}: learner sample errors: {exp.sample_errors}: {exp.error}")
        return Window(
            self.mode,
            rep,
            elapsed,
            u1 - u0,
            s1 - s0,
            h1 - h0,
            {k: round(c1[k] - c0.get(k, 0.0), 2) for k in c1},
            {k: round(p1[k] - p0.get(k, 0.0), 2) for k in p1},
            (load0, load1),
            {
                k: (round(v[0] - t0_threads.get(k, (0, 0))[0], 2), round(v[1] - t0_threads.get(k, (0, 0))[1], 2))
                for k, v in t1_threads.items()
            },
        )

    def close(self) -> None:
        for ch in getattr(self, "channels", []):
            ch.close()
        if self.stack is not None:
            self.stack.stop()


def _wait(what: str, check: Callable[[], Any], limit_s: float) -> Any:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.25)
    raise RuntimeError(f"learning bench: no {what} within {limit_s:.0f} s")


class _HgDaggerPrep:
    """configs/hgdagger.yaml needs demos in replay's "demos" table and starts from a BC checkpoint
    (the same for both modes): recorded and pretrained once, here."""

    def __init__(self, quick: bool, log: Callable[..., None]) -> None:
        from bench.hgdagger_stack_bench import EXPERIMENT, _eval_robot, pretrain, record_demo
        from edge_agent.teleop import TELEOPERATORS
        from user.config import load_config

        cfg = load_config(SETUPS["hgdagger"].config)
        robot, _ = _eval_robot(cfg)
        always = TELEOPERATORS.build("lang_reach_expert", {"mode": "always"}, spec=robot.spec)
        n_demos, updates = (4, 30) if quick else (10, 300)
        self.demos = [record_demo(robot, always, s, f"demo-{s}") for s in range(n_demos)]
        self.ckpt = pretrain(cfg, robot.spec, self.demos, updates, log)
        self.experiment = EXPERIMENT
        robot.close()

    def checkpoint(self, run_dir: Path) -> None:
        from cloud_learner.checkpoint import save_checkpoint

        save_checkpoint(run_dir / "checkpoints" / self.experiment, self.ckpt)

    def insert(self, ms: ModeStack) -> None:
        from bench.hgdagger_stack_bench import insert_demos

        insert_demos(ms.replay, self.demos)


def _ratios(windows: list[Window], attr: str) -> list[float]:
    """async / sync of each repetition's pair of windows."""
    out = []
    for rep in sorted({w.rep for w in windows}):
        a = next(w for w in windows if w.rep == rep and w.mode == "async")
        s = next(w for w in windows if w.rep == rep and w.mode == "sync")
        den = getattr(s, attr)
        out.append(getattr(a, attr) / den if den > 0 else float("inf"))
    return out


def _pooled(windows: list[Window], mode: str, count: str) -> float:
    """The mode's `count` (updates, env_steps) over all its windows, per second."""
    ws = [w for w in windows if w.mode == mode]
    return sum(getattr(w, count) for w in ws) / sum(w.seconds for w in ws)


def _share(windows: list[Window], mode: str, key: str, of: str = "cpu") -> float:
    """Summed CPU (or training-thread phase) seconds of `key` over the mode's windows, per window second."""
    ws = [w for w in windows if w.mode == mode]
    return sum((w.cpu_s if of == "cpu" else w.phases_s).get(key, 0.0) for w in ws) / sum(w.seconds for w in ws)


def _thread_split(windows: list[Window], mode: str) -> str:
    ws = [w for w in windows if w.mode == mode and "train" in w.threads]
    if not ws:
        return "-"
    total = sum(w.seconds for w in ws)
    cpu = sum(w.threads["train"][0] for w in ws) / total
    wait = sum(w.threads["train"][1] for w in ws) / total
    return f"{cpu * 100:.0f} / {wait * 100:.0f} / {max(0.0, 1 - cpu - wait) * 100:.0f}"


def _spread(values: list[float]) -> str:
    vals = ", ".join(f"{v:.2f}" for v in values)
    return f"per pair {vals} (median {statistics.median(values):.2f}x, {min(values):.2f}-{max(values):.2f}x)"


def measure(
    config: str,
    quick: bool,
    workdir: Path,
    log: Callable[..., None],
    reps: int | None = None,
    overrides: list[str] | None = None,
) -> tuple[list[Window], float]:
    """Both modes' stacks up side by side, windows alternating A S S A ...; returns them and the window."""
    setup = SETUPS[config]
    window_s = {"cnn": 45.0, "state": 30.0, "hgdagger": 40.0}[config] if not quick else 15.0
    reps = reps or (1 if quick else int(os.environ.get("USER_LEARNING_REPS", "3")))
    prep = _HgDaggerPrep(quick, log) if config == "hgdagger" else None
    stacks = {m: ModeStack(m, setup, workdir / config, list(overrides or [])) for m in ("async", "sync")}
    windows: list[Window] = []
    try:
        for ms in stacks.values():
            ms.start(prep)
        for ms in stacks.values():
            ms.warm_up(3.0 if quick else 10.0)
        for rep in range(reps):
            order = ("async", "sync") if rep % 2 == 0 else ("sync", "async")
            for mode in order:
                w = stacks[mode].window(rep, window_s)
                windows.append(w)
                log(
                    f"learning {config} rep {rep} {mode}: {w.updates_per_s:.2f} upd/s, {w.env_steps_per_s:.1f} "
                    f"steps/s, held {w.held_steps}, load {w.load}, cpu {w.cpu_s}, phases {w.phases_s}, "
                    f"learner threads {w.threads}"
                )
    finally:
        for ms in stacks.values():
            ms.close()
    return windows, window_s


def rows_for(config: str, windows: list[Window], window_s: float, overrides: list[str] | None = None) -> list[Row]:
    setup = SETUPS[config]
    reps = len({w.rep for w in windows})
    on = "".join(f"; {o}" for o in overrides or [])
    group = (
        f"learning async vs sync ({setup.what}{on}; 2 arms at 20 Hz; {reps} x {window_s:.0f} s windows per mode, "
        "alternating)"
    )
    loads = [x for w in windows for x in w.load]
    load = f"load {min(loads):.1f}-{max(loads):.1f}"
    extra = {"windows": [w.__dict__ for w in windows]}
    rows = []
    for metric, attr, count in (
        ("env steps/s", "env_steps_per_s", "env_steps"),
        ("updates/s", "updates_per_s", "updates"),
    ):
        note = f"{_spread(_ratios(windows, attr))}; sync round {setup.rounds}; {load}"
        rows.append(
            Row(
                group, metric, _pooled(windows, "async", count), _pooled(windows, "sync", count), "/s", True, note, PEER
            )
        )
    waited = {
        m: _share(windows, m, "wait_batch", "phases") + _share(windows, m, "wait_robots", "phases")
        for m in ("async", "sync")
    }
    rows.append(
        Row(
            group,
            "learner time waiting for data/robots",
            waited["async"] * 100,
            waited["sync"] * 100,
            "% of window",
            False,
            "training thread: async waits for the sampler's prefetched batches, sync for its round's env steps",
            PEER,
        )
    )
    held = {m: sum(w.held_steps for w in windows if w.mode == m) for m in ("async", "sync")}
    steps = {m: max(1, sum(w.env_steps for w in windows if w.mode == m)) for m in ("async", "sync")}
    rows.append(
        Row(
            group,
            "robot steps held (no action in time)",
            held["async"] / steps["async"] * 100,
            held["sync"] / steps["sync"] * 100,
            "% of steps",
            False,
            f"{held['async']} of {steps['async']} vs {held['sync']} of {steps['sync']}; robots' cap 2 x 20 Hz = 40 "
            "steps/s (sync: paused while its learner trains)",
            PEER,
        )
    )
    rows.append(
        Row(
            group,
            "training thread: on CPU / waiting for a CPU / other",
            _thread_split(windows, "async"),
            _thread_split(windows, "sync"),
            "% of window",
            None,
            "the learner's training thread (/proc schedstat): run-queue wait = starved by the machine's load; "
            "other = sleeping or blocked (sync: waiting for its round's env steps; async: the sampler's queue or "
            "the GIL)",
            PEER,
        )
    )
    learner_cpu = {m: _share(windows, m, "learner") for m in ("async", "sync")}
    per_update = {  # the same update work in both modes: learner CPU seconds per counted update
        m: learner_cpu[m] / max(_pooled(windows, m, "updates"), 1e-9) * 1e3 for m in ("async", "sync")
    }
    rows.append(
        Row(
            group,
            "learner CPU",
            learner_cpu["async"] * 100,
            learner_cpu["sync"] * 100,
            "% of a core",
            None,
            f"learner process CPU over the windows, {per_update['async']:.0f} / {per_update['sync']:.0f} ms per "
            "update (other processes of the stack: "
            + ", ".join(
                f"{k} {_share(windows, 'async', k) * 100:.0f}/{_share(windows, 'sync', k) * 100:.0f}%"
                for k in ("edges", "inference", "replay", "control")
            )
            + " async/sync)",
            PEER,
            extra=extra,
        )
    )
    return rows


def run(quick: bool, workdir: Path, log: Callable[..., None] = print, overrides: list[str] | None = None) -> list[Row]:
    """`overrides` (`--set`) reach both stacks alike, e.g. learner.device=cuda on a GPU machine."""
    configs = ["cnn"] if quick else [c for c in os.environ.get("USER_LEARNING_CONFIGS", "cnn,hgdagger").split(",")]
    rows = []
    for config in configs:
        windows, window_s = measure(config, quick, workdir, log, overrides=overrides)
        rows += rows_for(config, windows, window_s, overrides or [])
    return rows
