"""Soft Actor-Critic, readable top to bottom: twin Q critics, target critics, auto-tuned entropy.

The learner service feeds `SAC.update` with batches from the replay service; `train_local` runs the
same algorithm in-process against one robot (tests, tuning). The actor is `user.policy`'s network so
the weights the learner publishes rebuild unchanged on the inference service and the edge.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from edge_agent.robot import Robot, action_bounds
from user.config import LearnerConfig
from user.policy import SquashedGaussianActor, module_tensors


class QNetwork(nn.Module):
    """Q(s, a): MLP over the concatenated observation and action."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: list[int]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = obs_dim + action_dim
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], dim=-1)).squeeze(-1)


class SAC:
    def __init__(
        self,
        obs_dim: int,
        action_low: np.ndarray,
        action_high: np.ndarray,
        cfg: LearnerConfig,
        device: str | torch.device = "cpu",
    ) -> None:
        self.cfg = cfg
        self.device = torch.device(device)
        self.obs_dim = int(obs_dim)
        self.action_low = np.asarray(action_low, dtype=np.float32).reshape(-1)
        self.action_high = np.asarray(action_high, dtype=np.float32).reshape(-1)
        self.action_dim = int(self.action_low.size)
        hidden = [int(h) for h in cfg.hidden]

        self.actor = SquashedGaussianActor(self.obs_dim, self.action_dim, hidden, self.action_low, self.action_high)
        self.qf1 = QNetwork(self.obs_dim, self.action_dim, hidden)
        self.qf2 = QNetwork(self.obs_dim, self.action_dim, hidden)
        self.qf1_target = copy.deepcopy(self.qf1).requires_grad_(False)
        self.qf2_target = copy.deepcopy(self.qf2).requires_grad_(False)
        for net in (self.actor, self.qf1, self.qf2, self.qf1_target, self.qf2_target):
            net.to(self.device)

        # Entropy temperature: tuned so the policy's entropy tracks -action_dim (the usual heuristic).
        self.target_entropy = -float(self.action_dim)
        self.log_alpha = torch.tensor(math.log(cfg.init_alpha), device=self.device, requires_grad=True)

        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.q_optimizer = torch.optim.Adam([*self.qf1.parameters(), *self.qf2.parameters()], lr=cfg.critic_lr)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=cfg.alpha_lr)
        self.updates = 0

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    @torch.no_grad()
    def td_target(
        self, reward: torch.Tensor, next_obs: torch.Tensor, not_done: torch.Tensor, alpha: torch.Tensor
    ) -> torch.Tensor:
        """r + gamma * (min of the target critics - alpha * log pi) at a fresh next action, if not terminated."""
        next_action, next_log_prob, _ = self.actor(next_obs)
        next_q = torch.min(self.qf1_target(next_obs, next_action), self.qf2_target(next_obs, next_action))
        return reward + self.cfg.gamma * not_done * (next_q - alpha * next_log_prob)

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One gradient step on critics, actor and temperature; then Polyak-average the targets."""
        obs = batch["obs"].to(self.device, torch.float32)
        action = batch["action"].to(self.device, torch.float32)
        reward = batch["reward"].to(self.device, torch.float32).reshape(-1)
        next_obs = batch["next_obs"].to(self.device, torch.float32)
        # Only termination stops bootstrapping; a truncated episode still has a future.
        not_done = 1.0 - batch["terminated"].to(self.device, torch.float32).reshape(-1)
        alpha = self.log_alpha.detach().exp()

        # Critics: regress both onto one soft Bellman target.
        target_q = self.td_target(reward, next_obs, not_done, alpha)
        q1, q2 = self.qf1(obs, action), self.qf2(obs, action)
        qf_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.q_optimizer.zero_grad(set_to_none=True)
        qf_loss.backward()
        self.q_optimizer.step()

        # Actor: maximize min-Q minus the entropy cost of its own fresh samples.
        new_action, log_prob, _ = self.actor(obs)
        min_q = torch.min(self.qf1(obs, new_action), self.qf2(obs, new_action))
        actor_loss = (alpha * log_prob - min_q).mean()
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()

        # Temperature: raise alpha when entropy is below target, lower it when above.
        alpha_loss = -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_optimizer.step()

        with torch.no_grad():
            for net, target in ((self.qf1, self.qf1_target), (self.qf2, self.qf2_target)):
                for p, tp in zip(net.parameters(), target.parameters(), strict=True):
                    tp.lerp_(p, self.cfg.tau)

        self.updates += 1
        return {
            "qf_loss": float(qf_loss.detach()),
            "q1": float(q1.detach().mean()),
            "actor_loss": float(actor_loss.detach()),
            "alpha_loss": float(alpha_loss.detach()),
            "alpha": self.alpha,
            "entropy": float(-log_prob.detach().mean()),
        }

    # --- what the learner publishes and checkpoints -------------------------------------------------

    def actor_config(self) -> dict[str, Any]:
        """The sac_mlp PolicySpec config (see user.policy)."""
        return {
            "obs_keys": ["state"],
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "hidden": [int(h) for h in self.cfg.hidden],
            "action_low": [float(x) for x in self.action_low],
            "action_high": [float(x) for x in self.action_high],
        }

    def actor_tensors(self) -> dict[str, np.ndarray]:
        return module_tensors(self.actor)

    def state_dict(self) -> dict[str, Any]:
        """Tensors, ints and plain dicts only, so torch.load(weights_only=True) can read it back."""
        return {
            "actor": self.actor.state_dict(),
            "qf1": self.qf1.state_dict(),
            "qf2": self.qf2.state_dict(),
            "qf1_target": self.qf1_target.state_dict(),
            "qf2_target": self.qf2_target.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "q_optimizer": self.q_optimizer.state_dict(),
            "alpha_optimizer": self.alpha_optimizer.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "updates": int(self.updates),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.qf1.load_state_dict(state["qf1"])
        self.qf2.load_state_dict(state["qf2"])
        self.qf1_target.load_state_dict(state["qf1_target"])
        self.qf2_target.load_state_dict(state["qf2_target"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.q_optimizer.load_state_dict(state["q_optimizer"])
        self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        with torch.no_grad():
            self.log_alpha.copy_(torch.as_tensor(state["log_alpha"], device=self.device))
        self.updates = int(state["updates"])


# --- in-process training: the learning test and tuning ---------------------------------------------


class RingBuffer:
    """Fixed-size numpy replay buffer; the oldest transitions are overwritten."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int) -> None:
        self.capacity, self.size, self._next = int(capacity), 0, 0
        self.obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.action = np.zeros((self.capacity, action_dim), np.float32)
        self.reward = np.zeros(self.capacity, np.float32)
        self.terminated = np.zeros(self.capacity, np.float32)

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, next_obs: np.ndarray, terminated: bool) -> None:
        i = self._next
        self.obs[i], self.action[i], self.reward[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, float(terminated)
        self._next = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
        idx = rng.integers(0, self.size, size=batch_size)
        return {
            "obs": torch.from_numpy(self.obs[idx]),
            "action": torch.from_numpy(self.action[idx]),
            "reward": torch.from_numpy(self.reward[idx]),
            "next_obs": torch.from_numpy(self.next_obs[idx]),
            "terminated": torch.from_numpy(self.terminated[idx]),
        }


def _state_vector(features: dict[str, np.ndarray]) -> np.ndarray:
    return np.asarray(features["state"], dtype=np.float32).reshape(-1)


def train_local(
    robot: Robot,
    cfg: LearnerConfig,
    env_steps: int,
    seed: int,
    updates_per_step: float = 1.0,
    random_steps: int | None = None,
) -> dict[str, Any]:
    """Collect with the stochastic actor and train after every step, all in one process.

    Random actions for the first `random_steps` (default cfg.min_transitions) steps; updates
    start once the buffer holds cfg.min_transitions. Episodes are truncated at the robot's
    spec.max_episode_steps, as the edge agent does.
    """
    torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    spec = robot.spec
    low, high = action_bounds(spec)
    low, high = low.reshape(-1), high.reshape(-1)
    max_steps = int(spec.max_episode_steps) or 1_000_000
    random_steps = cfg.min_transitions if random_steps is None else random_steps

    obs = _state_vector(robot.reset(seed=seed).features)
    agent = SAC(obs.size, low, high, cfg)
    buffer = RingBuffer(max(env_steps, 1), obs.size, low.size)
    successes: list[bool] = []
    returns: list[float] = []
    lengths: list[int] = []
    episode_end_steps: list[int] = []
    ep_return, ep_len, credit = 0.0, 0, 0.0

    for step in range(env_steps):
        if step < random_steps:
            action = rng.uniform(low, high).astype(np.float32)
        else:
            with torch.no_grad():
                action = agent.actor(torch.from_numpy(obs)[None])[0][0].numpy()
        applied = robot.act(action)
        ob = robot.observe()
        next_obs = _state_vector(ob.features)
        buffer.add(obs, applied, ob.reward, next_obs, ob.terminated)
        obs, ep_return, ep_len = next_obs, ep_return + ob.reward, ep_len + 1

        if ob.terminated or ep_len >= max_steps:
            successes.append(bool(ob.success))
            returns.append(ep_return)
            lengths.append(ep_len)
            episode_end_steps.append(step + 1)
            obs = _state_vector(robot.reset().features)
            ep_return, ep_len = 0.0, 0

        if buffer.size >= cfg.min_transitions:
            credit += updates_per_step
            while credit >= 1.0:
                agent.update(buffer.sample(cfg.batch_size, rng))
                credit -= 1.0

    return {
        "successes": successes,
        "returns": returns,
        "lengths": lengths,
        "episode_end_steps": episode_end_steps,
        "updates": agent.updates,
        "env_steps": env_steps,
        "agent": agent,
    }
