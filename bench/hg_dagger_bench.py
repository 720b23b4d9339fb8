"""HG-DAgger on the language-conditioned reach: success before and after online correction.

In one process, with the real MuJoCo lang_reach_arm, its scripted expert, the flow_vla policy and
the flow_bc learner (the algorithm the learner service runs); tables are in-memory lists here, not
the replay service (the table work on replay lands separately).

1. Demonstrations: the expert drives `demo_episodes` episodes; BC on them -> the starting policy.
2. Evaluation: fixed episodes (seeds), interventions off, deterministic policy -> success rate.
3. HG-DAgger (ours): rounds of episodes where the policy drives and the expert takes over when it
   errs; intervention steps go to the interventions table; flow_bc trains on demos + interventions
   (50/50). Peer: plain BC given the same number of extra expert steps as more full demonstrations,
   trained with the same number of updates. Both start from the same policy and are evaluated on
   the same episodes.
4. Async vs sync: the same HG-DAgger loop with the learner in its own thread updating while the
   robot keeps acting (new weights copied to the actor after every episode) vs collect-then-train
   in turn; learner updates/s and robot steps/s over the same wall time.

Chunks: targets are the next `horizon` expert actions of the same episode (the last one repeated
past the end, masked out of the loss), as replay's SampleRequest.action_horizon assembles them;
the robot executes chunks through the edge's ChunkExecutor.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench import Row

HORIZON = 4
PEER = "BC on demos only, same expert steps and updates"


@dataclass
class Table:
    """Human-labelled steps: observations and the chunk of actions that followed."""

    obs: list[dict[str, np.ndarray]] = field(default_factory=list)
    chunks: list[np.ndarray] = field(default_factory=list)
    masks: list[np.ndarray] = field(default_factory=list)  # real (not padded) actions of each chunk

    def add_episode(
        self, observations: list[dict[str, np.ndarray]], actions: list[np.ndarray], human: list[bool]
    ) -> int:
        acts = np.asarray(actions, np.float32)
        added = 0
        run_end = len(acts) - 1  # last step of the human run a step belongs to (targets stay human)
        ends = []
        for t in reversed(range(len(acts))):
            if not human[t] or t == len(acts) - 1 or not human[t + 1]:
                run_end = t
            ends.append(run_end)
        ends.reverse()
        for t, (o, h) in enumerate(zip(observations, human, strict=True)):
            if not h:
                continue
            steps = np.arange(t, t + HORIZON)
            self.obs.append(o)
            self.chunks.append(acts[np.minimum(steps, ends[t])])
            self.masks.append(steps <= ends[t])
            added += 1
        return added

    def sample(self, n: int, rng: np.random.Generator) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        idx = rng.integers(len(self.obs), size=n)
        obs = {k: np.stack([self.obs[i][k] for i in idx]) for k in self.obs[0]}
        return obs, np.stack([self.chunks[i] for i in idx]), np.stack([self.masks[i] for i in idx])


def make_batch(tables: list[tuple[Table, float]], n: int, rng: np.random.Generator) -> Any:
    from cloud_learner.algorithm import Batch

    parts = [(t, max(1, round(n * share))) for t, share in tables if t.obs]
    sampled = [t.sample(k, rng) for t, k in parts]
    obs = {k: torch.from_numpy(np.concatenate([o[k] for o, _, _ in sampled])) for k in sampled[0][0]}
    chunk = torch.from_numpy(np.concatenate([c for _, c, _ in sampled]))
    mask = torch.from_numpy(np.concatenate([m for _, _, m in sampled]))
    b = len(chunk)
    ones = torch.ones(b, dtype=torch.bool)
    return Batch(obs, chunk[:, 0], torch.zeros(b), obs, torch.zeros(b), ones, action_chunk=chunk, chunk_mask=mask)


def run_episode(robot: Any, expert: Any, policy: Any | None, seed: int) -> tuple[bool, list, list, list]:
    """One episode; the expert decides per tick whether it drives. Returns (success, obs, actions, human)."""
    from edge_agent.chunks import ChunkExecutor

    obs = robot.reset(seed=seed)
    expert.reset(obs)
    executor = None
    if policy is not None:

        def fetch(o: dict[str, np.ndarray]) -> tuple[np.ndarray, int]:
            return policy.act({k: v[None] for k, v in o.items()}, deterministic=True)[0], 0

        executor = ChunkExecutor(fetch, prefetch=1, runner=lambda job: job())
    observations, actions, human = [], [], []
    for _ in range(robot.max_episode_steps):
        features = {k: v.copy() for k, v in obs.features.items()}
        action = expert.poll(obs)
        is_human = action is not None
        if action is None:
            answer = executor.tick(features) if executor is not None else None
            action = answer[0] if answer is not None else np.zeros(3, np.float32)
        applied = robot.act(action)
        observations.append(features)
        actions.append(applied)
        human.append(is_human)
        obs = robot.observe()
        if obs.terminated:
            return obs.success, observations, actions, human
    return False, observations, actions, human


def current_policy(algo: Any) -> Any:
    from user.policy import build_policy

    spec, tensors = algo.policy()
    return build_policy(spec, tensors, version=algo.updates)


def evaluate(robot: Any, never: Any, algo: Any, seeds: list[int]) -> float:
    policy = current_policy(algo)
    return float(np.mean([run_episode(robot, never, policy, s)[0] for s in seeds]))


def train(algo: Any, tables: list[tuple[Table, float]], updates: int, rng: np.random.Generator) -> None:
    for _ in range(updates):
        algo.update(make_batch(tables, algo.p.batch_size, rng))


@dataclass
class Setup:
    robot: Any
    experts: dict[str, Any]
    make_algo: Callable[[], Any]


def setup(camera: bool) -> Setup:
    from cloud_learner.algorithm import ALGORITHMS, Feature, Layout
    from edge_agent.robot import make_robot
    from edge_agent.teleop import TELEOPERATORS
    from user import wire

    robot = make_robot("lang_reach_arm", "lang-bench", {"camera": camera, "max_episode_steps": 50}, seed=0)
    experts = {
        mode: TELEOPERATORS.build("lang_reach_expert", {"mode": mode}, spec=robot.spec)
        for mode in ("always", "intervene", "never")
    }
    layout = Layout(
        observation={
            f.name: Feature(tuple(f.shape), wire.dtype_from_proto(f.dtype).name, f.is_image)
            for f in robot.spec.observation
        },
        action_low=np.asarray(robot.spec.action.low, np.float32),
        action_high=np.asarray(robot.spec.action.high, np.float32),
    )
    params = {"batch_size": 64, "lr": 1e-3, "horizon": HORIZON, "hidden": 128, "flow_steps": 5}

    def make_algo() -> Any:
        return ALGORITHMS.build("flow_bc", params, layout=layout, device=torch.device("cpu"))

    return Setup(robot, experts, make_algo)


def hg_dagger_round(
    s: Setup, algo: Any, demos: Table, interventions: Table, episodes: int, seed0: int
) -> tuple[int, int]:
    """Policy drives, the expert corrects; returns (expert steps, robot steps)."""
    policy = current_policy(algo)
    expert_steps = robot_steps = 0
    for e in range(episodes):
        _, obs, acts, human = run_episode(s.robot, s.experts["intervene"], policy, seed0 + e)
        expert_steps += interventions.add_episode(obs, acts, human)
        robot_steps += len(acts)
    return expert_steps, robot_steps


def _rate(success: float, episodes: int) -> str:
    return f"{round(success * episodes)}/{episodes} ({success:.2f})"


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    import copy

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    # The camera stays off here: on two shared CPU cores a CNN over 64x64 images trains too slowly for
    # a benchmark run; the vision path is exercised by the tests and the inference benchmark.
    camera = False
    demo_episodes, pre_updates, rounds, round_episodes, round_updates, eval_n = (
        (4, 30, 1, 2, 20, 4) if quick else (60, 1500, 5, 20, 600, 40)
    )
    s = setup(camera)
    eval_seeds = list(range(10_000, 10_000 + eval_n))
    demos = Table()
    demo_steps = 0
    for e in range(demo_episodes):
        _, obs, acts, human = run_episode(s.robot, s.experts["always"], None, e)
        demo_steps += demos.add_episode(obs, acts, human)
    log(f"hg_dagger: {demo_steps} demo steps; BC pre-training")
    base = s.make_algo()
    train(base, [(demos, 1.0)], pre_updates, rng)
    before = evaluate(s.robot, s.experts["never"], base, eval_seeds)

    # Ours: HG-DAgger rounds (sync: collect, then train).
    ours = copy.deepcopy(base)
    interventions = Table()
    expert_steps = 0
    t0 = time.perf_counter()
    sync_robot_steps = 0
    for r in range(rounds):
        taken, moved = hg_dagger_round(s, ours, demos, interventions, round_episodes, 1000 + 100 * r)
        expert_steps += taken
        sync_robot_steps += moved
        train(ours, [(demos, 0.5), (interventions, 0.5)], round_updates, rng)
    sync_s = time.perf_counter() - t0
    after = evaluate(s.robot, s.experts["never"], ours, eval_seeds)
    log(f"hg_dagger: before {before:.2f}, after {after:.2f}, {expert_steps} intervention steps")

    # Peer: the same expert budget as more demonstrations, the same updates.
    peer = copy.deepcopy(base)
    more = copy.deepcopy(demos)
    extra, e = 0, 0
    while extra < expert_steps:
        _, obs, acts, human = run_episode(s.robot, s.experts["always"], None, 5000 + e)
        extra += more.add_episode(obs, acts, human)
        e += 1
    train(peer, [(more, 1.0)], rounds * round_updates, rng)
    peer_after = evaluate(s.robot, s.experts["never"], peer, eval_seeds)

    # Async vs sync throughput: the learner trains in a thread while the robot keeps running.
    sync_rate = rounds * round_updates / sync_s
    async_algo = copy.deepcopy(base)
    async_ivs = Table()
    stop = threading.Event()
    updates = [0]

    def learner() -> None:  # the demos' half alone until interventions arrive, as the sync rounds train
        while not stop.is_set():
            async_algo.update(make_batch([(demos, 0.5), (async_ivs, 0.5)], async_algo.p.batch_size, rng))
            updates[0] += 1

    thread = threading.Thread(target=learner, daemon=True)
    t0 = time.perf_counter()
    thread.start()
    episodes = async_robot_steps = 0
    try:
        while time.perf_counter() - t0 < sync_s:
            # Fresh weights every episode, while the learner keeps training.
            async_robot_steps += hg_dagger_round(s, async_algo, demos, async_ivs, 1, 2000 + episodes)[1]
            episodes += 1
    finally:
        stop.set()
        thread.join(30)
    async_s = time.perf_counter() - t0
    s.robot.close()
    group = f"hg_dagger lang_reach_arm flow_vla ({'64x64 camera + ' if camera else ''}state + instruction)"
    note = f"{len(eval_seeds)} fixed eval episodes, interventions off; before (demos BC) {before:.2f}"
    sync = "sync (collect, then train, in turn)"
    return [
        # A count, not a ratio: a success rate of 0 on either side has no meaningful "x times better".
        Row(
            group,
            "eval success after correction",
            _rate(after, eval_n),
            _rate(peer_after, eval_n),
            "",
            None,
            note,
            PEER,
        ),
        Row(group, "expert steps used (after demos)", float(expert_steps), float(extra), "steps", False, "", PEER),
        Row(
            f"{group}: async vs sync", "learner updates/s", updates[0] / async_s, sync_rate, "updates/s", True, "", sync
        ),
        Row(
            f"{group}: async vs sync",
            "robot steps/s",
            async_robot_steps / async_s,
            sync_robot_steps / sync_s,
            "steps/s",
            True,
            f"same wall time ({sync_s:.0f} s); async: learner thread + acting thread in one process",
            sync,
        ),
    ]
