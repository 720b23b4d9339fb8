"""gym-hil's simulated Franka Panda (PandaPickCubeBase-v0) behind the Robot interface.

Features: "state" = agent_pos (joint positions and velocities, gripper, TCP position) followed by the
cube position (left out with `block_in_state: false`: proprioception only, for policies that must find
the cube in the camera images), and with `cameras: true` two 128x128 uint8 images, "camera.front" and "camera.wrist"
(rendered headless with EGL from any thread, shadows and multisampling off: ~10x faster than
gym-hil's own image_obs renderer at this size). The 7-d action
in [-1, 1] is (dx, dy, dz, rx, ry, rz, grip): the position part is scaled to ee_step_m metres per
control step (the base env takes metres, so an unscaled 1.0 would jump a metre), the rotation part
is ignored by the env, grip is a gripper delta (+1 closes fully).

The env's own reward, termination and success reach the `env` task (the default) through the
Observation; `info` carries privileged sim state (TCP, cube, gripper) for scripted experts.

Needs the gym-hil package; without it this module fails to import and the registry reports why.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from typing import Literal

import gym_hil  # noqa: F401 - registers the gym_hil/* env ids
import gymnasium
import mujoco
import numpy as np
from pydantic import Field

from edge_agent.rendering import CameraRenderer
from edge_agent.robot import ROBOTS, Observation, Robot, clip_action
from user.registry import PluginParams
from user.v1 import robot_pb2, tensor_pb2

KIND = "gym_hil_panda"
ENV_ID = "gym_hil/PandaPickCubeBase-v0"
ACTION_NAMES = ["dx", "dy", "dz", "rx", "ry", "rz", "grip"]
CAMERAS = ("front", "wrist")  # gym-hil's camera names: front, handcam_rgb
CAMERA_IDS = {"front": "front", "wrist": "handcam_rgb"}
MAX_GRIPPER_COMMAND = 255.0


@ROBOTS.register(KIND)
class GymHilPanda(Robot):
    """gym-hil Franka Panda picking a cube (MuJoCo), optional front and wrist cameras."""

    class Params(PluginParams):
        max_episode_steps: int = Field(default=100, ge=1)
        ee_step_m: float = Field(default=0.025, gt=0, description="metres per unit of position action per step")
        reward_type: Literal["dense", "sparse"] = "dense"
        random_block_position: bool = True
        cameras: bool = Field(default=False, description="add the 128x128 front and wrist images")
        camera_size: int = Field(default=128, ge=16, le=512)
        block_in_state: bool = Field(
            default=True, description="append the cube position (privileged) to state; false: proprioception only"
        )

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        self.robot_id = robot_id
        self.params = params
        self.ee_step_m = float(params.ee_step_m)
        self.max_episode_steps = int(params.max_episode_steps)
        self._env = gymnasium.make(
            ENV_ID,
            max_episode_steps=self.max_episode_steps,
            seed=seed,
            reward_type=params.reward_type,
            random_block_position=params.random_block_position,
        )
        self._base = self._env.unwrapped
        # gym-hil builds (and renders once with) an EGL renderer it never needs here: free it now, in the
        # thread that made it, instead of whenever the process exits.
        viewer = getattr(self._base, "_viewer", None)
        if viewer is not None:
            viewer.close()
            self._base._viewer = None
        self._cameras: CameraRenderer | None = None
        if params.cameras:  # our own renderer: gym-hil's keeps the 4096 shadow map and MSAA
            self._cameras = CameraRenderer(self._base.model, params.camera_size, params.camera_size)
        model = self._base.model
        self._camera_ids = {n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, c) for n, c in CAMERA_IDS.items()}
        self._reward, self._terminated, self._success = 0.0, False, False
        self._env.reset(seed=seed)
        self._spec = self._build_spec(self._state().shape[0])

    def _build_spec(self, state_dim: int) -> robot_pb2.RobotSpec:
        rate = 1.0 / float(self._base.control_dt)
        observation = [robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[state_dim])]
        cameras = []
        if self._cameras is not None:
            size = self.params.camera_size
            for name in CAMERAS:
                observation.append(
                    robot_pb2.FeatureSpec(
                        name=f"camera.{name}", dtype=tensor_pb2.DTYPE_UINT8, shape=[size, size, 3], is_image=True
                    )
                )
                cameras.append(robot_pb2.CameraSpec(name=name, width=size, height=size, fps=rate))
        return robot_pb2.RobotSpec(
            robot_id=self.robot_id,
            kind=KIND,
            action=robot_pb2.ActionSpace(
                shape=[7], low=[-1.0] * 7, high=[1.0] * 7, names=ACTION_NAMES, dtype=tensor_pb2.DTYPE_FLOAT32
            ),
            observation=observation,
            cameras=cameras,
            control_rate_hz=rate,
            max_episode_steps=self.max_episode_steps,
            task="pick up the cube and lift it 10 cm",
            labels={"sim": "mujoco", "env": ENV_ID, "ee_step_m": str(self.ee_step_m)},
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    # --- state -------------------------------------------------------------------------------------

    def _state(self) -> np.ndarray:
        robot = self._base.get_robot_state()
        if not self.params.block_in_state:
            return robot.astype(np.float32)
        return np.concatenate([robot, self._base.data.sensor("block_pos").data]).astype(np.float32)

    def _privileged(self) -> dict[str, np.ndarray | float]:
        data = self._base.data
        return {
            "tcp_pos": data.sensor("2f85/pinch_pos").data.copy(),
            "block_pos": data.sensor("block_pos").data.copy(),
            "block_z_init": float(getattr(self._base, "_z_init", 0.0)),
            "gripper": float(data.ctrl[self._base._gripper_ctrl_id] / MAX_GRIPPER_COMMAND),
        }

    def observe(self) -> Observation:
        features = {"state": self._state()}
        if self._cameras is not None:
            for name in CAMERAS:
                features[f"camera.{name}"] = self._cameras.render(self._base.data, self._camera_ids[name])
        return Observation(
            features=features,
            reward=self._reward,
            terminated=self._terminated,
            success=self._success,
            info=self._privileged(),
        )

    # --- control -----------------------------------------------------------------------------------

    def reset(self, seed: int | None = None) -> Observation:
        self._env.reset(seed=seed)
        self._reward, self._terminated, self._success = 0.0, False, False
        return self.observe()

    def _env_action(self, applied: np.ndarray) -> np.ndarray:
        env_action = applied.astype(np.float64).copy()
        env_action[:3] *= self.ee_step_m
        return env_action

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        _obs, reward, terminated, _truncated, info = self._env.step(self._env_action(applied))
        self._reward = float(reward)
        self._terminated = bool(terminated)
        self._success = bool(info.get("succeed", False))
        return applied

    def hold(self) -> np.ndarray:
        """Keep the mocap target and gripper where they are; the controller keeps servoing to them. The action
        is all deltas (position and gripper), so this is the zero action."""
        self._base.apply_action(np.zeros(7))
        self._reward = 0.0
        return clip_action(self._spec, np.zeros(7, np.float32))

    def close(self) -> None:
        if self._cameras is not None:
            self._cameras.close()
            self._cameras = None
        self._env.close()
