"""HG-DAgger through the services: success before and after, expert steps, async vs sync training.

The stack of configs/hgdagger.yaml as real processes (`userctl up`'s Stack: control, replay, learner,
inference, one edge agent per lang_reach_arm robot acting at 20 Hz through Inference.Act with chunks,
the scripted expert as each edge's teleoperator):

1. Demonstrations: the expert drives `demos` episodes of an in-process lang_reach_arm; flow_bc (the
   learner's own build path, `build_algorithm`) is trained on them here, offline, and written as the
   learner's checkpoint: the policy a lab deploys before correcting it online.
2. The stack starts with the experiment stopped (Control.StopExperiment before any edge connects), so
   the robots hold and the learner only publishes the resumed policy; the demos go into replay's
   "demos" table (robot arm-0, Replay.Insert); "before" = fixed evaluation episodes through
   Inference.Act (deterministic, interventions off) on an in-process robot.
3. Control.StartExperiment: the robots act, the expert takes over when the policy errs (steps flagged
   `intervention`, replay indexes them in "interventions"), the learner trains flow_bc on demos +
   interventions 50/50 and publishes to inference, for `window_s`.
4. Control.StopExperiment; once inference serves the learner's last version, "after" = the same
   evaluation episodes. Expert steps = the robots' intervention steps (Control).

Run twice on the same checkpoint, demos and window: learner.mode=async (ours) and learner.mode=sync
(collect sync_env_steps, pause the robots, sync_updates updates, publish, resume). Env steps/s and
updates/s over the window are the async/sync ratios (RLinf-USER: 5.7x for pi0 + HG-DAgger). The two windows
run one after the other, so other jobs' load may differ between them: the throughput ratio measured in
alternating windows of both stacks at once is `python -m bench --only learning` (its hgdagger config).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench import Row

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "hgdagger.yaml"
EXPERIMENT = "lang"
DEMO_ROBOT = "arm-0"  # demos are stored under an edge robot's id: the learner samples its experiment's robots
PEER = "USER learner.mode=sync (collect, pause robots, train, publish), same config"


@dataclass
class Demo:
    steps: list[Any]  # step_pb2.Step for replay
    observations: list[dict[str, np.ndarray]]
    actions: list[np.ndarray]


def record_demo(robot: Any, expert: Any, seed: int, episode_id: str) -> Demo:
    """One episode the expert drives start to end, as the Steps an edge would send (not flagged: the
    "demos" table is all human; replay's "interventions" table stays the corrections only)."""
    from user import wire
    from user.v1 import step_pb2

    obs = robot.reset(seed=seed)
    expert.reset(obs)
    demo = Demo([], [], [])
    for t in range(robot.max_episode_steps):
        features = {k: v.copy() for k, v in obs.features.items()}
        action = np.asarray(robot.act(expert.poll(obs)), np.float32)
        nxt = robot.observe()
        truncated = not nxt.terminated and t == robot.max_episode_steps - 1
        step = step_pb2.Step(
            robot_id=DEMO_ROBOT,
            episode_id=episode_id,
            step_index=t,
            observation=wire.to_tensor_map(features),
            action=wire.to_tensor(action),
            reward=float(nxt.reward),
            terminated=bool(nxt.terminated),
            truncated=bool(truncated),
            success=bool(nxt.success),
            policy_version=0,
        )
        if nxt.terminated or truncated:
            step.final_observation.CopyFrom(wire.to_tensor_map(nxt.features))
        demo.steps.append(step)
        demo.observations.append(features)
        demo.actions.append(action)
        obs = nxt
        if nxt.terminated:
            break
    return demo


def pretrain(cfg: Any, spec: Any, demos: list[Demo], updates: int, log: Callable[..., None]) -> dict[str, Any]:
    """flow_bc on the demos through the learner's own build path; returns the learner checkpoint state."""
    import torch

    from bench.hg_dagger_bench import Table, train
    from cloud_learner.learner import build_algorithm, checkpoint_state
    from user.experiments import layout_for

    exp = next(e for e in cfg.experiments if e.name == EXPERIMENT)
    layout = layout_for(exp, [spec])
    torch.manual_seed(0)
    algo = build_algorithm(0, exp, layout, "cpu")
    table = Table()
    for d in demos:
        table.add_episode(d.observations, d.actions, [True] * len(d.actions))
    t0 = time.perf_counter()
    train(algo, [(table, 1.0)], updates, np.random.default_rng(0))
    took = time.perf_counter() - t0
    log(f"hgdagger_stack: pretrained {updates} updates on {len(table.obs)} demo steps in {took:.0f} s")
    return checkpoint_state(algo, exp.algorithm.kind, 1, layout)


class ServedPolicy:
    """The policy the inference service serves, as hg_dagger_bench.run_episode wants it (act -> chunks)."""

    def __init__(self, addr: str, auth: Any, probe: dict[str, np.ndarray], robot_id: str = "eval-0") -> None:
        from user.rpc import make_channel
        from user.v1 import inference_pb2_grpc

        self.channel = make_channel(addr, auth)
        self.stub = inference_pb2_grpc.InferenceStub(self.channel)
        self.robot_id = robot_id
        self.probe = probe  # an observation to ask with when only the served version matters
        self.versions: set[int] = set()

    def act(self, batched: dict[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
        from user import wire
        from user.v1 import inference_pb2

        obs = {k: v[0] for k, v in batched.items()}
        req = inference_pb2.ActRequest(
            robot_id=self.robot_id, observation=wire.to_tensor_map(obs), deterministic=deterministic
        )
        resp = self.stub.Act(req, timeout=30)
        self.versions.add(int(resp.policy_version))
        chunk = wire.from_tensor(resp.action)
        return (chunk if chunk.ndim == 2 else chunk.reshape(1, -1))[None]

    def version(self) -> int:
        self.act({k: v[None] for k, v in self.probe.items()})
        return max(self.versions)

    def close(self) -> None:
        self.channel.close()


def evaluate(served: ServedPolicy, robot: Any, never: Any, seeds: list[int]) -> tuple[float, set[int]]:
    """Fixed episodes, interventions off, the served policy deterministic: (success rate, versions seen)."""
    from bench.hg_dagger_bench import run_episode

    served.versions.clear()
    rate = float(np.mean([run_episode(robot, never, served, s)[0] for s in seeds]))
    return rate, set(served.versions)


@dataclass
class Outcome:
    mode: str
    before: float | None = None
    after: float = 0.0
    env_steps_per_s: float = 0.0
    updates_per_s: float = 0.0
    expert_steps: int = 0
    env_steps: int = 0
    updates: int = 0
    learner_cpu_s: float = 0.0  # the learner process's CPU seconds over the window (load-independent)
    window_s: float = 0.0
    load: tuple[float, float] = (0.0, 0.0)  # 1-minute load average at the window's start and end
    versions: dict[str, Any] = field(default_factory=dict)


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _Stubs:
    def __init__(self, stack: Any) -> None:
        from user.rpc import make_channel
        from user.v1 import control_pb2_grpc, learner_pb2_grpc, replay_pb2_grpc

        auth = stack.auth
        self.channels = [make_channel(stack.child(n).grpc_addr, auth) for n in ("control", "learner", "replay")]
        self.control = control_pb2_grpc.ControlStub(self.channels[0])
        self.learner = learner_pb2_grpc.LearnerStub(self.channels[1])
        self.replay = replay_pb2_grpc.ReplayStub(self.channels[2])

    def experiment(self) -> Any:
        from user.v1 import learner_pb2

        status = self.learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10)
        return next(e for e in status.experiments if e.name == EXPERIMENT)

    def robots(self) -> list[Any]:
        from user.v1 import control_pb2

        return list(self.control.ListRobots(control_pb2.ListRobotsRequest(), timeout=10).robots)

    def counts(self) -> tuple[int, int, int]:
        """(learner updates, robots' env steps, robots' intervention steps) now."""
        robots = self.robots()
        return (
            int(self.experiment().updates),
            sum(int(r.status.env_steps) for r in robots),
            sum(int(r.status.intervention_steps) for r in robots),
        )

    def close(self) -> None:
        for ch in self.channels:
            ch.close()


def _wait(what: str, check: Callable[[], Any], limit_s: float = 180.0) -> Any:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.5)
    raise RuntimeError(f"hgdagger_stack: no {what} within {limit_s:.0f} s")


def insert_demos(stub: Any, demos: list[Demo]) -> None:
    from user.v1 import replay_pb2

    reqs = [
        replay_pb2.InsertRequest(seq=i, step=s, table="demos") for i, s in enumerate(s for d in demos for s in d.steps)
    ]
    acked = sum(len(a.seqs) for a in stub.Insert(iter(reqs), timeout=120))
    if acked != len(reqs):
        raise RuntimeError(f"replay acked {acked} of {len(reqs)} demo steps")


def stack_run(
    mode: str,
    ckpt: dict[str, Any],
    demos: list[Demo],
    window_s: float,
    eval_seeds: list[int],
    eval_before: bool,
    workdir: Path,
    extra: list[str],
    log: Callable[..., None],
) -> Outcome:
    from cloud_learner.checkpoint import save_checkpoint
    from user.config import load_config
    from user.up import Stack
    from user.v1 import control_pb2

    overrides = [f"learner.mode={mode}", *extra]
    cfg = load_config(CONFIG, overrides)
    run_dir = workdir / mode
    save_checkpoint(run_dir / "checkpoints" / EXPERIMENT, ckpt)
    stack = Stack(cfg, str(CONFIG), overrides, run_dir)
    robot, never = _eval_robot(cfg)
    out = Outcome(mode)
    stubs = served = None
    try:
        stack.start_services()
        stubs = _Stubs(stack)
        # Stopped before any robot connects: robots hold from their first tick, the learner waits.
        stubs.control.StopExperiment(control_pb2.StopExperimentRequest(name=EXPERIMENT), timeout=10)
        edges = [
            stack.spawn_edge(f"edge-{i}", [r], cfg.edge.seed + 1000 * i) for i, r in enumerate(stack._edge_robots())
        ]
        for edge in edges:
            stack.wait_ready(edge)
        _wait("resumed policy", lambda: stubs.experiment().weight_version >= 2)
        served = ServedPolicy(stack.child("inference").grpc_addr, stack.auth, robot.reset(seed=0).features)
        _wait("served policy", lambda: _try_version(served) >= 1)
        if eval_before:
            out.before, seen = evaluate(served, robot, never, eval_seeds)
            out.versions["before"] = sorted(seen)
            log(f"hgdagger_stack {mode}: before {out.before:.2f} (versions {sorted(seen)})")
        insert_demos(stubs.replay, demos)
        u0, s0, h0 = stubs.counts()
        c0, load0 = _cpu_s(stack.child("learner").proc.pid), os.getloadavg()[0]
        stubs.control.StartExperiment(control_pb2.StartExperimentRequest(name=EXPERIMENT), timeout=10)
        t0 = time.monotonic()
        while time.monotonic() - t0 < window_s:
            time.sleep(min(5.0, window_s))
            if stack.dead_children():
                raise RuntimeError(f"children died: {[c.name for c in stack.dead_children()]}")
        u1, s1, _ = stubs.counts()
        elapsed = time.monotonic() - t0
        out.learner_cpu_s, out.window_s = _cpu_s(stack.child("learner").proc.pid) - c0, elapsed
        out.load = (round(load0, 1), round(os.getloadavg()[0], 1))
        stubs.control.StopExperiment(control_pb2.StopExperimentRequest(name=EXPERIMENT), timeout=10)
        _wait("learner stopped", lambda: stubs.experiment().state == "stopped", 60)
        time.sleep(2.0)  # sync mode publishes the round it was in after the stop
        exp = stubs.experiment()
        if exp.sample_errors:
            raise RuntimeError(f"learner sample errors: {exp.sample_errors}: {exp.error}")
        published = int(exp.weight_version)
        _wait("last version served", lambda: _try_version(served) >= published, 60)
        out.after, seen = evaluate(served, robot, never, eval_seeds)
        out.versions["after"], out.versions["published"] = sorted(seen), published
        time.sleep(1.5)  # the last heartbeats carry the final counts
        _, s2, h2 = stubs.counts()
        out.env_steps_per_s, out.updates_per_s = (s1 - s0) / elapsed, (u1 - u0) / elapsed
        out.env_steps, out.updates, out.expert_steps = s2 - s0, u1 - u0, h2 - h0
        log(f"hgdagger_stack {mode}: {out}")
    finally:
        if served is not None:
            served.close()
        if stubs is not None:
            stubs.close()
        robot.close()
        stack.stop()
    return out


def _try_version(served: ServedPolicy) -> int:
    import grpc

    try:
        return served.version()
    except grpc.RpcError:
        return 0


def _eval_robot(cfg: Any) -> tuple[Any, Any]:
    from edge_agent.robot import make_robot
    from edge_agent.teleop import TELEOPERATORS

    rc = cfg.edge.robots[0]
    robot = make_robot(rc.kind, "eval-0", rc.params, seed=0)
    never = TELEOPERATORS.build("lang_reach_expert", {"mode": "never"}, spec=robot.spec)
    return robot, never


def _rate(success: float | None, n: int) -> str:
    return "-" if success is None else f"{round(success * n)}/{n} ({success:.2f})"


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    from user.config import load_config

    n_demos, updates, window_s, n_eval = (4, 30, 20.0, 4) if quick else (60, 1500, 150.0, 40)
    cfg = load_config(CONFIG)
    robot, _ = _eval_robot(cfg)
    from edge_agent.teleop import TELEOPERATORS

    always = TELEOPERATORS.build("lang_reach_expert", {"mode": "always"}, spec=robot.spec)
    demos = [record_demo(robot, always, s, f"demo-{s}") for s in range(n_demos)]
    spec = robot.spec
    robot.close()
    ckpt = pretrain(cfg, spec, demos, updates, log)
    seeds = list(range(10_000, 10_000 + n_eval))
    load0 = os.getloadavg()[0]
    ours = stack_run("async", ckpt, demos, window_s, seeds, True, workdir, [], log)
    peer = stack_run("sync", ckpt, demos, window_s, seeds, False, workdir, [], log)
    load1 = os.getloadavg()[0]
    group = f"hgdagger_stack (lang_reach_arm x{cfg.up.edge_agents} at 20 Hz, flow_bc, {window_s:.0f} s window)"
    demo_steps = sum(len(d.steps) for d in demos)
    note = (
        f"{n_eval} fixed eval episodes via Inference.Act, interventions off; before (BC on {n_demos} demos, "
        f"{demo_steps} steps, {updates} updates) {_rate(ours.before, n_eval)}; load {load0:.1f}->{load1:.1f}"
    )
    return [
        Row(
            group,
            "eval success after correction",
            _rate(ours.after, n_eval),
            _rate(peer.after, n_eval),
            "",
            None,
            note,
            PEER,
            extra={"before": ours.before},
        ),
        Row(
            group,
            "expert (intervention) steps in the window",
            float(ours.expert_steps),
            float(peer.expert_steps),
            "steps",
            None,
            "",
            PEER,
        ),
        Row(
            group,
            "env steps/s",
            ours.env_steps_per_s,
            peer.env_steps_per_s,
            "/s",
            True,
            f"env steps {ours.env_steps} vs {peer.env_steps}; load {ours.load} vs {peer.load}; sequential windows "
            "(interleaved: bench learning)",
            PEER,
        ),
        Row(
            group,
            "updates/s",
            ours.updates_per_s,
            peer.updates_per_s,
            "/s",
            True,
            f"updates {ours.updates} vs {peer.updates}; learner CPU {ours.learner_cpu_s:.0f} vs "
            f"{peer.learner_cpu_s:.0f} s in {ours.window_s:.0f} / {peer.window_s:.0f} s",
            PEER,
        ),
    ]
