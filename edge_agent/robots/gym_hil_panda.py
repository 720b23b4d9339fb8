"""gym-hil's simulated Franka Panda (PandaPickCubeBase-v0) behind the Robot interface.

State features only: "state" = agent_pos (joint positions and velocities, gripper, TCP position)
followed by the cube position. The 7-d action in [-1, 1] is (dx, dy, dz, rx, ry, rz, grip): the
position part is scaled to ee_step_m metres per control step (the base env takes metres, so an
unscaled 1.0 would jump a metre), the rotation part is ignored by the env, grip is a gripper delta.

gym-hil is optional: without it this module registers nothing and the registry still imports.
"""

from __future__ import annotations

import os
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from edge_agent.robot import Observation, Robot, clip_action, register_robot
from user.v1 import robot_pb2, tensor_pb2

try:
    import gym_hil  # noqa: F401 - registers the gym_hil/* env ids
    import gymnasium
except ImportError:  # optional dependency
    gymnasium = None

KIND = "gym_hil_panda"
ENV_ID = "gym_hil/PandaPickCubeBase-v0"
ACTION_NAMES = ["dx", "dy", "dz", "rx", "ry", "rz", "grip"]


class GymHilPanda(Robot):
    """Pick up the cube. One act() = one env step (control_dt of simulated time, 10 Hz by default)."""

    def __init__(
        self,
        robot_id: str,
        seed: int = 0,
        max_episode_steps: int = 100,
        ee_step_m: float = 0.025,
        reward_type: str = "dense",
        random_block_position: bool = True,
        **_: Any,
    ) -> None:
        if gymnasium is None:
            raise RuntimeError("gym_hil_panda needs the gym-hil package (pip install gym-hil)")
        self.robot_id = robot_id
        self.ee_step_m = float(ee_step_m)
        self.max_episode_steps = int(max_episode_steps)
        self._env = gymnasium.make(
            ENV_ID,
            max_episode_steps=self.max_episode_steps,
            seed=seed,
            reward_type=reward_type,
            random_block_position=random_block_position,
        )
        self._base = self._env.unwrapped
        self._obs: dict[str, np.ndarray] = {}
        self._reward, self._terminated, self._success = 0.0, False, False
        obs, _ = self._env.reset(seed=seed)
        self._obs = obs
        self._spec = self._build_spec(self._state(obs).shape[0])

    def _build_spec(self, state_dim: int) -> robot_pb2.RobotSpec:
        return robot_pb2.RobotSpec(
            robot_id=self.robot_id,
            kind=KIND,
            action=robot_pb2.ActionSpace(
                shape=[7], low=[-1.0] * 7, high=[1.0] * 7, names=ACTION_NAMES, dtype=tensor_pb2.DTYPE_FLOAT32
            ),
            observation=[robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[state_dim])],
            control_rate_hz=1.0 / float(self._base.control_dt),
            max_episode_steps=self.max_episode_steps,
            task="pick up the cube and lift it 10 cm",
            labels={"sim": "mujoco", "env": ENV_ID, "ee_step_m": str(self.ee_step_m)},
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    @staticmethod
    def _state(obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([obs["agent_pos"], obs["environment_state"]]).astype(np.float32)

    def observe(self) -> Observation:
        return Observation(
            features={"state": self._state(self._obs)},
            reward=self._reward,
            terminated=self._terminated,
            success=self._success,
        )

    def reset(self, seed: int | None = None) -> Observation:
        obs, _ = self._env.reset(seed=seed)
        self._obs = obs
        self._reward, self._terminated, self._success = 0.0, False, False
        return self.observe()

    def _env_action(self, applied: np.ndarray) -> np.ndarray:
        env_action = applied.astype(np.float64).copy()
        env_action[:3] *= self.ee_step_m
        return env_action

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        obs, reward, terminated, _truncated, info = self._env.step(self._env_action(applied))
        self._obs = obs
        self._reward = float(reward)
        self._terminated = bool(terminated)
        self._success = bool(info.get("succeed", False))
        return applied

    def hold(self) -> None:
        """Keep the mocap target and gripper where they are; the controller keeps servoing to them."""
        self._base.apply_action(np.zeros(7))
        self._obs = self._base._compute_observation()
        self._reward = 0.0

    def close(self) -> None:
        self._env.close()


if gymnasium is not None:
    register_robot(KIND)(GymHilPanda)
