"""Edge robots: control steps per second through our Robot + Task adapters vs the bare gym envs.

Each side steps the same env with the same seeded random actions (the same physical commands) and
the same episode limit, taking turns in rounds (so background load hits both alike); the median
round counts. Ours is `robot.act` + `robot.observe` + the `env`
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


def _actions(low: np.ndarray, high: np.ndarray) -> Callable[[], np.ndarray]:
    """The same random action sequence for both sides (seeded), in the robot's declared bounds."""
    rng = np.random.default_rng(0)
    return lambda: rng.uniform(low, high).astype(np.float32)


def _ours(kind: str, params: dict[str, Any]) -> tuple[Callable[[int], float], Callable[[], None], Any]:
    import time

    from edge_agent.robot import make_robot
    from edge_agent.task import TASKS

    robot = make_robot(kind, "bench", params, seed=0)
    spec = robot.spec
    task = TASKS.build("env", spec=spec)
    action = _actions(np.asarray(spec.action.low), np.asarray(spec.action.high))
    obs, length = robot.reset(), 0

    def steps_per_s(n: int) -> float:
        nonlocal obs, length
        start = time.perf_counter()
        for _ in range(n):
            applied = robot.act(action())
            nxt = robot.observe()
            length += 1
            done = task.evaluate(obs, applied, nxt).terminated or length >= spec.max_episode_steps
            obs, length = (robot.reset(), 0) if done else (nxt, length)
        return n / (time.perf_counter() - start)

    return steps_per_s, robot.close, spec


def _peer(
    env_id: str, kwargs: dict[str, Any], spec: Any, to_env: Callable[[np.ndarray], np.ndarray]
) -> tuple[Callable[[int], float], Callable[[], None]]:
    import time

    import gymnasium

    if env_id.startswith("gym_hil"):
        import gym_hil  # noqa: F401
    else:
        import lerobot_env_so101  # noqa: F401
    env = gymnasium.make(env_id, max_episode_steps=spec.max_episode_steps, **kwargs)
    env.reset(seed=0)
    action = _actions(np.asarray(spec.action.low), np.asarray(spec.action.high))

    def steps_per_s(n: int) -> float:
        start = time.perf_counter()
        for _ in range(n):
            _obs, _r, terminated, truncated, _info = env.step(to_env(action()))
            if terminated or truncated:
                env.reset()
        return n / (time.perf_counter() - start)

    return steps_per_s, env.close


def _compare(
    group: str,
    ours: tuple[str, dict[str, Any]],
    peer: tuple[str, dict[str, Any]],
    to_env: Callable[[np.ndarray], np.ndarray],
    peer_name: str,
    n: int,
    rounds: int,
) -> Row:
    ours_rate, ours_close, spec = _ours(*ours)
    peer_rate, peer_close = _peer(*peer, spec, to_env)
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


def _panda_env_action(action: np.ndarray) -> np.ndarray:
    """What our Panda sends gym-hil for an action: position scaled to 2.5 cm per unit (gym-hil takes metres)."""
    env_action = action.astype(np.float64)
    env_action[:3] *= 0.025
    return env_action


def _same(action: np.ndarray) -> np.ndarray:
    return action


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    rounds = 1 if quick else 3
    panda = {"reward_type": "dense", "random_block_position": True}
    so101 = {"action_scale": 0.025, "reward_type": "dense", "random_block_position": True, "top_down_ik": True}
    so101["jaw_pads"] = True
    cases = [
        (
            "edge Panda pick-cube, 2 cameras 128x128",
            ("gym_hil_panda", {"cameras": True}),
            ("gym_hil/PandaPickCubeBase-v0", {**panda, "image_obs": True}),
            _panda_env_action,
            GYM_HIL + " (image_obs)",
            1 if quick else 10,
        ),
        (
            "edge Panda pick-cube, state",
            ("gym_hil_panda", {}),
            ("gym_hil/PandaPickCubeBase-v0", panda),
            _panda_env_action,
            GYM_HIL,
            2 if quick else 200,
        ),
        (
            "edge SO-101 pick-cube, state",
            ("so101", {}),
            ("lerobot_env_so101/SO101PickCube-v0", so101),
            _same,
            SO101_PKG,
            2 if quick else 300,
        ),
    ]
    if quick:  # a smoke run: one light case (the camera peer and the SO-101 import take tens of seconds)
        cases = cases[1:2]
    rows = []
    for group, ours, peer, to_env, peer_name, n in cases:
        log(f"edge: {group}")
        rows.append(_compare(group, ours, peer, to_env, peer_name, n, rounds))
    return rows
