"""Asynchronous vs synchronous learning on the same config and machine: env steps/s and updates/s.

Both runs are the whole stack as real processes (`userctl up`'s Stack: control, replay, learner,
inference, two edge agents driving simulated arms at their real control rate). Two configs:

- cnn (the RLinf-USER comparison, CNN+SAC): each arm renders a 64x64 front camera; SAC learns from
  the camera and the state through one shared CNN encoder (DrQ shift), the inference service runs
  the CNN policy for every Act;
- state (full runs only): the state-reach experiment with SAC, MLP networks.

Only `learner.mode` differs within a config:

- async (ours): robots act while the learner trains and publishes (the pipeline USER runs);
- sync (baseline): collect `sync_env_steps` transitions, pause the robots, run `sync_updates`
  updates, publish, resume, in turn (what a single-process RL loop does).

Each is measured over the same window after its first update. RLinf-USER reports 1.55x generation
and 4.61x training throughput for its asynchronous pipeline over a synchronous one.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

from bench import Row

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"
PEER = "USER sync mode (collect, pause, train, publish)"
REACH_ONLY = [
    "experiments=[{name: reach, robots: {kinds: [sim_reach_arm]}, algorithm: {kind: sac}}]",
    "edge.robots=[{id: arm-0, kind: sim_reach_arm, params: {control_rate_hz: 20, max_episode_steps: 50}}]",
    "up.edge_agents=2",
    "log_json=true",
]
CNN = [
    "experiments=[{name: reach, robots: {kinds: [sim_reach_arm]}, algorithm: {kind: sac, "
    "params: {features: [camera.front, state], batch_size: 64}}}]",
    "edge.robots=[{id: arm-0, kind: sim_reach_arm, params: {control_rate_hz: 20, max_episode_steps: 50, "
    "camera: true}}]",
    "up.edge_agents=2",
    "log_json=true",
]
CONFIGS = {"cnn": CNN, "state": REACH_ONLY}


def _counts(stack) -> tuple[int, int]:
    """(learner updates of the reach experiment, env steps of all robots) now."""
    from user.rpc import make_channel
    from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc

    auth = stack.auth
    with make_channel(stack.child("learner").grpc_addr, auth) as ch:
        status = learner_pb2_grpc.LearnerStub(ch).GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
    with make_channel(stack.child("control").grpc_addr, auth) as ch:
        robots = control_pb2_grpc.ControlStub(ch).ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
    return int(status.updates), sum(int(r.status.env_steps) for r in robots)


def measure(
    mode: str, window_s: float, workdir: Path, extra: list[str], log: Callable[..., None], config: str = "cnn"
) -> dict[str, float]:
    from user.config import load_config
    from user.up import Stack

    overrides = [*CONFIGS[config], f"learner.mode={mode}", *extra]
    cfg = load_config(CONFIG, overrides)
    stack = Stack(cfg, str(CONFIG), overrides, workdir / f"{config}-{mode}")
    try:
        stack.start()
        deadline = time.monotonic() + 180
        while _counts(stack)[0] == 0:  # start the window once training runs
            if time.monotonic() > deadline:
                raise RuntimeError(f"{mode}: no update within 180 s")
            time.sleep(0.5)
        u0, s0 = _counts(stack)
        t0 = time.monotonic()
        time.sleep(window_s)
        u1, s1 = _counts(stack)
        elapsed = time.monotonic() - t0
    finally:
        stack.stop()
    out = {"env_steps_per_s": (s1 - s0) / elapsed, "updates_per_s": (u1 - u0) / elapsed, "load": os.getloadavg()[0]}
    log(f"learning {config} {mode}: {out}")
    return out


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    window_s = 15.0 if quick else 60.0
    extra = ["learner.min_transitions=100", "learner.sync_env_steps=100", "learner.sync_updates=100"]
    rows = []
    for config in ["cnn"] if quick else ["cnn", "state"]:
        ours = measure("async", window_s, workdir, extra, log, config)
        peer = measure("sync", window_s, workdir, extra, log, config)
        what = "CNN+SAC, 64x64 camera + state" if config == "cnn" else "SAC from state"
        group = f"learning async vs sync (2 sim arms at 20 Hz, {what}, {window_s:.0f} s window)"
        note = (
            "same config and machine; sync: 100 env steps then 100 updates per round; "
            f"load {ours['load']:.1f} / {peer['load']:.1f}"
        )
        rows += [
            Row(group, "env steps/s", ours["env_steps_per_s"], peer["env_steps_per_s"], "/s", True, note, PEER),
            Row(group, "updates/s", ours["updates_per_s"], peer["updates_per_s"], "/s", True, note, PEER),
        ]
    return rows
