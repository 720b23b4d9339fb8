"""SAC (cloud_learner/algorithms/sac.py, the learner's) learns the reach task, acting through the policy it
publishes; its unit tests (bootstrapping, checkpoints, published weights) are in tests/test_algorithms.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from edge_agent.robot import make_robot


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _random_policy_successes(env_steps: int, seed: int) -> list[bool]:
    robot = make_robot("sim_reach_arm", "random", seed=seed)
    rng = np.random.default_rng(seed)
    max_steps = robot.spec.max_episode_steps
    successes, ep_len = [], 0
    robot.reset(seed=seed)
    for _ in range(env_steps):
        robot.act(rng.uniform(-1.0, 1.0, size=3))
        obs, ep_len = robot.observe(), ep_len + 1
        if obs.terminated or ep_len >= max_steps:
            successes.append(obs.success)
            robot.reset()
            ep_len = 0
    return successes


@pytest.mark.slow
def test_sac_learns_to_reach() -> None:
    """3000 env steps, 1 update per step, SAC's default params (cloud_learner.algorithms.sac), acting
    through the published "mlp" policy as an edge does."""
    from cloud_learner.local import make_algorithm, train_local

    env_steps, seed, window, min_transitions = 3000, 0, 20, 250
    robot = make_robot("sim_reach_arm", "learner-test", seed=seed)
    algorithm = make_algorithm("sac", {}, robot.spec)
    out = train_local(robot, algorithm, env_steps, seed=seed, min_transitions=min_transitions)
    robot.close()
    learned = float(np.mean(out["curve"].success[-window:]))
    random = float(np.mean(_random_policy_successes(env_steps, seed)[-window:]))
    assert out["updates"] == env_steps - min_transitions + 1
    assert random <= 0.1, f"the reach task is too easy for a random policy ({random:.2f})"
    assert learned >= 0.85, f"SAC success over the last {window} episodes: {learned:.2f} (random {random:.2f})"
