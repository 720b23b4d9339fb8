"""SAC: the service learner's cloud_learner/sac.py (bootstrapping, checkpoint, published weights) and
that the Algorithm-interface SAC (cloud_learner/algorithms/sac.py) learns the reach task."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from cloud_learner.sac import SAC
from edge_agent.robot import make_robot
from tests import helpers
from user.config import LearnerConfig
from user.policy import build_policy, policy_spec_for

OBS_DIM, ACT_DIM = 5, 2


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _agent(seed: int = 0) -> SAC:
    torch.manual_seed(seed)
    cfg = LearnerConfig(hidden=[32, 32], batch_size=16)
    return SAC(OBS_DIM, np.array([-1.0, -2.0]), np.array([1.0, 2.0]), cfg)


def _batch(seed: int = 0) -> dict[str, torch.Tensor]:
    return helpers.random_sac_batch(OBS_DIM, ACT_DIM, seed, p_terminal=0.3)


def test_update_returns_finite_losses() -> None:
    agent = _agent()
    alpha0 = agent.alpha
    for i in range(5):
        losses = agent.update(_batch(i))
    assert agent.updates == 5
    assert {"qf_loss", "actor_loss", "alpha_loss", "alpha", "entropy"} <= set(losses)
    assert all(np.isfinite(v) for v in losses.values())
    assert losses["alpha"] == agent.alpha != alpha0
    assert agent.target_entropy == -ACT_DIM


def test_termination_stops_bootstrapping_truncation_does_not() -> None:
    agent = _agent()
    batch = _batch()
    alpha = agent.log_alpha.detach().exp()
    terminal = agent.td_target(batch["reward"], batch["next_obs"], torch.zeros(16), alpha)
    torch.testing.assert_close(terminal, batch["reward"])
    # A truncated step (terminated=0) keeps the discounted future value.
    continuing = agent.td_target(batch["reward"], batch["next_obs"], torch.ones(16), alpha)
    assert not torch.allclose(continuing, batch["reward"])


def test_checkpoint_round_trip_with_weights_only_load() -> None:
    agent = _agent(seed=0)
    for i in range(3):
        agent.update(_batch(i))
    buf = io.BytesIO()
    torch.save(agent.state_dict(), buf)
    buf.seek(0)
    restored = _agent(seed=1)  # different init: everything must come from the checkpoint
    restored.load_state_dict(torch.load(buf, weights_only=True))
    assert restored.updates == 3 and restored.alpha == pytest.approx(agent.alpha)
    for name, t in agent.actor.state_dict().items():
        torch.testing.assert_close(restored.actor.state_dict()[name], t)
    # Same optimizer state and same sampling noise -> the same next update.
    torch.manual_seed(7)
    a = agent.update(_batch(9))
    torch.manual_seed(7)
    b = restored.update(_batch(9))
    assert a == pytest.approx(b, rel=1e-5, abs=1e-6)
    for name, t in agent.qf1_target.state_dict().items():
        torch.testing.assert_close(restored.qf1_target.state_dict()[name], t)


def test_published_actor_rebuilds_as_policy() -> None:
    agent = _agent()
    agent.update(_batch())
    config = agent.actor_config()
    assert config["obs_keys"] == ["state"] and config["obs_dim"] == OBS_DIM and config["action_dim"] == ACT_DIM
    policy = build_policy(policy_spec_for(config), agent.actor_tensors(), version=3)
    obs = np.random.default_rng(0).normal(size=(4, OBS_DIM)).astype(np.float32)
    with torch.no_grad():
        expected = agent.actor(torch.from_numpy(obs))[2].numpy()
    np.testing.assert_allclose(policy.act({"state": obs}, deterministic=True), expected, rtol=1e-6, atol=1e-6)


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
