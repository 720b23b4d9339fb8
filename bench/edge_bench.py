"""Edge robots: control steps per second through our Robot + Task adapters vs the bare gym envs.

Each side steps the same env with the same random actions, taking turns in rounds (so background
load hits both alike); the median round counts. Ours is `robot.act` + `robot.observe` + the `env`
task's judgement (what the edge loop does per tick, minus the network); the peer is `env.step`.
With cameras, ours renders gym-hil's two 128x128 views with shadows and multisampling off, the peer
with gym-hil's own `image_obs=True` renderer (the default 4096 shadow map), as lerobot's gym_hil
environment does.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench import Row, median

GYM_HIL = "gym-hil 0.1.14 env.step"
SO101_PKG = "lerobot-env-so101 0.4.0 env.step"


def _ours(kind: str, params: dict[str, Any]) -> tuple[Callable[[int], float], Callable[[], None]]:
    import time

    from edge_agent.robot import make_robot
    from edge_agent.task import TASKS

    robot = make_robot(kind, "bench", params, seed=0)
    task = TASKS.build("env", spec=robot.spec)
    low, high = np.asarray(robot.spec.action.low), np.asarray(robot.spec.action.high)
    rng = np.random.default_rng(0)
    obs = robot.reset()

    def steps_per_s(n: int) -> float:
        nonlocal obs
        start = time.perf_counter()
        for _ in range(n):
            applied = robot.act(rng.uniform(low, high))
            nxt = robot.observe()
            obs = robot.reset() if task.evaluate(obs, applied, nxt).terminated else nxt
        return n / (time.perf_counter() - start)

    return steps_per_s, robot.close


def _peer(env_id: str, kwargs: dict[str, Any]) -> tuple[Callable[[int], float], Callable[[], None]]:
    import time

    import gymnasium

    if env_id.startswith("gym_hil"):
        import gym_hil  # noqa: F401
    else:
        import lerobot_env_so101  # noqa: F401
    env = gymnasium.make(env_id, **kwargs)
    env.reset(seed=0)
    env.action_space.seed(0)

    def steps_per_s(n: int) -> float:
        start = time.perf_counter()
        for _ in range(n):
            _obs, _r, terminated, truncated, _info = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        return n / (time.perf_counter() - start)

    return steps_per_s, env.close


def _compare(
    group: str, ours: tuple[str, dict[str, Any]], peer: tuple[str, dict[str, Any]], peer_name: str, n: int, rounds: int
) -> Row:
    ours_rate, ours_close = _ours(*ours)
    peer_rate, peer_close = _peer(*peer)
    try:
        ours_rate(1), peer_rate(1)  # warm up (first render, IK caches)
        ours_runs, peer_runs = [], []
        for _ in range(rounds):
            ours_runs.append(ours_rate(n))
            peer_runs.append(peer_rate(n))
    finally:
        ours_close()
        peer_close()
    return Row(
        group=group,
        metric="control steps/s, one process",
        ours=median(ours_runs),
        peer=median(peer_runs),
        unit="steps/s",
        higher_is_better=True,
        note=f"median of {rounds} rounds x {n} steps, random actions",
        peer_name=peer_name,
    )


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    rounds = 1 if quick else 3
    panda = {"reward_type": "dense", "random_block_position": True}
    cases = [
        (
            "edge Panda pick-cube, 2 cameras 128x128",
            ("gym_hil_panda", {"cameras": True}),
            ("gym_hil/PandaPickCubeBase-v0", {**panda, "image_obs": True}),
            GYM_HIL + " (image_obs)",
            1 if quick else 10,
        ),
        (
            "edge Panda pick-cube, state",
            ("gym_hil_panda", {}),
            ("gym_hil/PandaPickCubeBase-v0", panda),
            GYM_HIL,
            2 if quick else 200,
        ),
        (
            "edge SO-101 pick-cube, state",
            ("so101", {}),
            ("lerobot_env_so101/SO101PickCube-v0", {"action_scale": 0.025, "reward_type": "dense"}),
            SO101_PKG,
            2 if quick else 300,
        ),
    ]
    rows = []
    for group, ours, peer, peer_name, n in cases:
        log(f"edge: {group}")
        rows.append(_compare(group, ours, peer, peer_name, n, rounds))
    return rows
