"""Train an Algorithm against one robot in one process: the learning tests and the learning bench.

The same Algorithm the learner service runs, fed from an in-memory buffer instead of the replay
service; the robot acts through the *published* policy (`build_policy(*algorithm.policy())`, as the
edge does), refreshed every `policy_every` steps. Reward, termination and success come from a Task
when one is given, else from the robot's own Observation. An optional `expert` returns an action
when a human (or a script standing in for one) takes over: that step is stored as an intervention,
in the "online" table and in the "interventions" table, as RLPD and BC sample them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Feature, Layout
from edge_agent.robot import Observation, Robot, action_bounds
from edge_agent.task import Task
from user.policy import build_policy
from user.v1 import robot_pb2, tensor_pb2

# (observation, step within the episode) -> the expert's action, or None to let the policy act
Expert = Callable[[Observation, int], np.ndarray | None]


def layout_from_spec(spec: robot_pb2.RobotSpec) -> Layout:
    """One robot's observation features and action bounds as the algorithms see them."""
    observation = {
        f.name: Feature(tuple(int(s) for s in f.shape), tensor_pb2.DType.Name(f.dtype)[6:].lower(), bool(f.is_image))
        for f in spec.observation
    }
    low, high = action_bounds(spec)
    return Layout(observation, low.reshape(-1), high.reshape(-1), (spec.kind,))


def make_algorithm(kind: str, params: Mapping[str, Any] | None, spec: robot_pb2.RobotSpec, device: str = "cpu"):
    return ALGORITHMS.build(kind, params, layout=layout_from_spec(spec), device=torch.device(device))


class Table:
    """A growable in-memory table of transitions (numpy, images kept uint8)."""

    def __init__(self) -> None:
        self.rows: dict[str, list[np.ndarray]] = {}
        self.size = 0

    def add(
        self,
        obs: Mapping[str, np.ndarray],
        action: np.ndarray,
        reward: float,
        next_obs: Mapping[str, np.ndarray],
        terminated: bool,
        intervention: bool = False,
    ) -> None:
        row = {f"obs/{k}": v for k, v in obs.items()} | {f"next/{k}": v for k, v in next_obs.items()}
        row |= {
            "action": np.asarray(action, np.float32),
            "reward": np.float32(reward),
            "terminated": np.float32(terminated),
            "intervention": np.bool_(intervention),
        }
        for k, v in row.items():
            self.rows.setdefault(k, []).append(np.asarray(v))
        self.size += 1

    def extend(self, other: Table) -> None:
        for k, v in other.rows.items():
            self.rows.setdefault(k, []).extend(v)
        self.size += other.size

    def sample(self, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        idx = rng.integers(0, self.size, size=n)
        return {k: np.stack([v[i] for i in idx]) for k, v in self.rows.items()}


@dataclass
class Buffer:
    """Named tables; a batch takes each table's share of the rows (empty tables give theirs to "online")."""

    tables: dict[str, Table] = field(default_factory=lambda: {"online": Table()})

    def table(self, name: str) -> Table:
        return self.tables.setdefault(name, Table())

    def sample(self, request: BatchRequest, rng: np.random.Generator, device: torch.device) -> Batch:
        shares = {t: s for t, s in request.tables.items() if self.tables.get(t) and self.tables[t].size > 0}
        if not shares:
            shares = {"online": 1.0}
        total = sum(shares.values())
        names = sorted(shares)
        counts = [round(request.batch_size * shares[t] / total) for t in names]
        counts[-1] = request.batch_size - sum(counts[:-1])
        parts = []
        for name, count in zip(names, counts, strict=True):
            if count > 0:
                part = self.tables[name].sample(count, rng)
                if name in request.human_tables:  # as replay flags them: every action there is a demonstrator's
                    part["intervention"] = np.ones(count, np.bool_)
                parts.append(part)
        rows = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

        def tensor(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(x).to(device)

        return Batch(
            observation={k[4:]: tensor(v) for k, v in rows.items() if k.startswith("obs/")},
            action=tensor(rows["action"]),
            reward=tensor(rows["reward"]),
            next_observation={k[5:]: tensor(v) for k, v in rows.items() if k.startswith("next/")},
            terminated=tensor(rows["terminated"]),
            intervention=tensor(rows["intervention"]),
        )


@dataclass
class Curve:
    """One row per finished episode: when it ended (env steps, wall and process CPU seconds) and how it went.
    CPU seconds tell what a dedicated core would take when the machine is shared."""

    env_steps: list[int] = field(default_factory=list)
    wall_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    success: list[bool] = field(default_factory=list)
    episode_return: list[float] = field(default_factory=list)
    interventions: list[int] = field(default_factory=list)
    evaluation: list[bool] = field(default_factory=list)  # acted with the mean action, no expert
    # per episode, the mean of each scalar the updates during it returned (alpha, q, q_pi, bc_term, ...):
    # what the learner was doing while the success rate moved; {} for an episode without updates
    learner: list[dict[str, float]] = field(default_factory=list)

    def autonomous_success(self) -> list[bool]:
        """Successes of the episodes nobody intervened in: what the policy does on its own."""
        return [s for s, n in zip(self.success, self.interventions, strict=True) if n == 0]

    def to_json(self) -> dict[str, list]:
        return {k: list(v) for k, v in self.__dict__.items()}


def _judge(task: Task | None, obs: Observation, action: np.ndarray, next_obs: Observation) -> tuple[float, bool, bool]:
    if task is None:
        return float(next_obs.reward), bool(next_obs.terminated), bool(next_obs.success)
    out = task.evaluate(obs, action, next_obs)
    return float(out.reward), bool(out.terminated), bool(out.success)


def train_local(
    robot: Robot,
    algorithm: Algorithm,
    env_steps: int,
    seed: int = 0,
    task: Task | None = None,
    buffer: Buffer | None = None,
    expert: Expert | None = None,
    min_transitions: int = 250,
    random_steps: int | None = None,
    updates_per_step: float = 1.0,
    policy_every: int = 1,
    on_episode: Callable[[Curve], None] | None = None,
    max_seconds: float | None = None,
    pretrain_updates: int = 0,
    max_cpu_seconds: float | None = None,
    eval_every: int = 0,
) -> dict[str, Any]:
    """Collect with the published stochastic policy and update after every step.

    Uniform random actions for the first `random_steps` (default `min_transitions`) steps; updates
    start once the online table holds `min_transitions` rows, `updates_per_step` per env step.
    Episodes are truncated at spec.max_episode_steps, as the edge agent does. `buffer` may arrive
    pre-filled (e.g. a "demos" table); `pretrain_updates` updates run on it before the first step
    (the offline phase: critic and, with a BC term, actor warm-start on the demos). Every
    `eval_every`-th episode (0: none) acts with the mean action and no expert: an evaluation episode,
    flagged in the curve (its transitions are still stored). Stops early after `max_seconds` of wall time
    or `max_cpu_seconds` of this process's CPU time (comparable between runs on a shared machine).
    """
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    spec = robot.spec
    low, high = (b.reshape(-1) for b in action_bounds(spec))
    max_steps = int(spec.max_episode_steps) or 1_000_000
    random_steps = min_transitions if random_steps is None else random_steps
    buffer = buffer or Buffer()
    online = buffer.table("online")
    curve = Curve()
    start, cpu_start = time.perf_counter(), time.process_time()
    if pretrain_updates and not any(t.size for t in buffer.tables.values()):
        raise ValueError("pretrain_updates needs a pre-filled buffer (e.g. a demos table)")
    pretrain_info: list[dict[str, float]] = []
    for _ in range(pretrain_updates):
        pretrain_info.append(algorithm.update(buffer.sample(algorithm.batch_request(), rng, algorithm.device)))
    scalars: dict[str, list[float]] = {}  # update scalars since the last episode ended
    policy = build_policy(*algorithm.policy(), version=algorithm.updates)
    evaluating = False

    obs = robot.reset(seed=seed)
    if task is not None:
        task.reset(obs)
    ep_return, ep_len, ep_interventions, credit, step = 0.0, 0, 0, 0.0, -1
    for step in range(env_steps):
        override = expert(obs, ep_len) if expert is not None and not evaluating else None
        if override is not None:
            action = np.asarray(override, np.float32)
        elif step < random_steps and not evaluating:
            action = rng.uniform(low, high).astype(np.float32)
        else:
            action = policy.act({k: v[None] for k, v in obs.features.items()}, deterministic=evaluating)[0]
        applied = robot.act(action)
        next_obs = robot.observe()
        reward, terminated, success = _judge(task, obs, applied, next_obs)
        row = (obs.features, applied, reward, next_obs.features, terminated, override is not None)
        online.add(*row)
        if override is not None:
            buffer.table("interventions").add(*row)
        obs, ep_return, ep_len = next_obs, ep_return + reward, ep_len + 1
        ep_interventions += override is not None

        if terminated or ep_len >= max_steps:
            curve.env_steps.append(step + 1)
            curve.wall_s.append(time.perf_counter() - start)
            curve.cpu_s.append(time.process_time() - cpu_start)
            curve.success.append(success)
            curve.episode_return.append(ep_return)
            curve.interventions.append(ep_interventions)
            curve.evaluation.append(evaluating)
            curve.learner.append({k: float(np.mean(v)) for k, v in scalars.items()})
            scalars = {}
            evaluating = eval_every > 0 and (len(curve.success) + 1) % eval_every == 0
            if on_episode is not None:
                on_episode(curve)
            obs = robot.reset()
            if task is not None:
                task.reset(obs)
            ep_return, ep_len, ep_interventions = 0.0, 0, 0

        if online.size >= min_transitions:
            credit += updates_per_step
            while credit >= 1.0:
                info = algorithm.update(buffer.sample(algorithm.batch_request(), rng, algorithm.device))
                for k, v in info.items():
                    scalars.setdefault(k, []).append(v)
                credit -= 1.0
            if (step + 1) % policy_every == 0:
                policy = build_policy(*algorithm.policy(), version=algorithm.updates)

        if max_seconds is not None and time.perf_counter() - start > max_seconds:
            break
        if max_cpu_seconds is not None and time.process_time() - cpu_start > max_cpu_seconds:
            break

    # the offline phase's last scalars (e.g. the BC loss the actor reached, the critics' Q after their warm-up)
    last = pretrain_info[-1] if pretrain_info else {}
    return {
        "curve": curve,
        "updates": algorithm.updates,
        "env_steps": step + 1,
        "buffer": buffer,
        "pretrain_last": {k: float(v) for k, v in last.items()},
    }


def record_episodes(
    robot: Robot,
    expert: Expert,
    episodes: int,
    table: Table,
    task: Task | None = None,
    seed: int = 0,
    only_successes: bool = False,
) -> list[bool]:
    """Run `expert` alone for `episodes` episodes into `table` (scripted demos); returns their successes.

    With `only_successes` a failed episode's transitions are dropped and another is tried until `table` holds
    `episodes` successful ones (at most 3x as many tries), as one keeps only good human demos; the returned
    list still has every try, so the expert's own success rate stays visible."""
    successes: list[bool] = []
    tries = 3 * episodes if only_successes else episodes
    while len(successes) < tries and (not only_successes or sum(successes) < episodes):
        episode = Table()
        successes.append(_record_one(robot, expert, episode, task, seed + len(successes)))
        if successes[-1] or not only_successes:
            table.extend(episode)
    return successes


def _record_one(robot: Robot, expert: Expert, table: Table, task: Task | None, seed: int) -> bool:
    """One expert episode from reset into `table`; whether it succeeded."""
    obs, success = robot.reset(seed=seed), False
    if task is not None:
        task.reset(obs)
    for ep_step in range(int(robot.spec.max_episode_steps) or 1_000_000):
        action = expert(obs, ep_step)
        if action is None:
            raise ValueError("the expert must act on every step of a recorded episode")
        applied = robot.act(action)
        next_obs = robot.observe()
        reward, terminated, success = _judge(task, obs, applied, next_obs)
        table.add(obs.features, applied, reward, next_obs.features, terminated, intervention=True)
        obs = next_obs
        if terminated:
            break
    return success
