"""Language-conditioned reach: the 3-joint MuJoCo arm, three coloured targets, an instruction naming one.

Each episode places a red, a green and a blue target apart from each other and picks one; the
instruction ("reach the blue target") is in the observation as UTF-8 bytes (`instruction`,
uint8 (64,), see user/text.py) and in `info`. Success: the end-effector within 3 cm of the named
target. Reward: progress toward it, plus a bonus on success; touching another target ends the
episode as a failure.

Observation: `state` = end-effector (3), scaled joint velocities (3) and, with
`target_state` on (default), the three targets' offsets from the hand in red, green, blue order
(9, in decimetres): the
instruction still decides which one counts, so the policy must ground the words. With
`target_state` off only the camera shows where the targets are. `camera.front` is rendered
(64x64 by default, shadows off) when `camera` is on.
"""

from __future__ import annotations

import threading

import mujoco
import numpy as np
from pydantic import Field

from edge_agent.robot import Observation, clip_action, register_robot
from edge_agent.robots.sim_arm import (
    ARM_XML,
    HOME_QPOS,
    INIT_NOISE,
    MAX_SPEED,
    SimReachArm,
    ee_velocity_action,
    sample_target,
)
from user.registry import PluginParams
from user.text import INSTRUCTION_BYTES, INSTRUCTION_KEY, encode_instruction
from user.v1 import robot_pb2, tensor_pb2

KIND = "lang_reach_arm"
COLOURS = {"red": (0.9, 0.1, 0.1), "green": (0.1, 0.8, 0.1), "blue": (0.1, 0.2, 0.95)}
SUCCESS_RADIUS = 0.03  # m
WRONG_RADIUS = 0.03  # m: reaching another target ends the episode
MIN_SEPARATION = 0.15  # m between targets
SUCCESS_BONUS = 5.0
TARGET_SCALE = 10.0  # target offsets in the state are in decimetres


def _xml() -> str:
    targets = "\n".join(
        f'    <body name="target_{name}" mocap="true" pos="0.3 0 0.3">'
        f'<geom type="sphere" size="0.025" rgba="{r} {g} {b} 1"/></body>'
        for name, (r, g, b) in COLOURS.items()
    )
    start = ARM_XML.index('    <body name="target"')
    end = ARM_XML.index("</body>", start) + len("</body>")
    return ARM_XML[:start] + targets + ARM_XML[end:].replace('model="sim_reach_arm"', f'model="{KIND}"')


def instruction_for(colour: str) -> str:
    return f"reach the {colour} target"


@register_robot(KIND)
class LangReachArm(SimReachArm):
    """Reach the target the instruction names (red, green or blue)."""

    class Params(PluginParams):
        control_rate_hz: float = Field(default=20.0, gt=0)
        max_episode_steps: int = Field(default=60, ge=1)
        camera: bool = Field(default=True, description="render the front camera (camera.front)")
        camera_size: int = Field(default=64, ge=8, le=512, description="camera image side in pixels")
        target_state: bool = Field(default=True, description="the three targets' offsets in the state vector")

    default_task = "env"  # the robot scores the named target itself (wrong targets end the episode)

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:  # type: ignore[override]
        camera, camera_size = params.camera, params.camera_size
        self.target_state = bool(params.target_state)
        self._load_arm(_xml(), robot_id, params.control_rate_hz, params.max_episode_steps, seed)
        self.camera_size = int(camera_size)
        self._renderer = None  # SimReachArm's; cameras here render through _camera() (one per thread)
        self.camera = bool(camera)
        self._renderers: dict[int, mujoco.Renderer] = {}
        self.targets = np.zeros((len(COLOURS), 3))
        self.goal = 0
        self._target = self.targets[0]
        self._spec = self._build_spec(camera)
        self._reward, self._terminated, self._success = 0.0, False, False
        self._holding = False
        self.reset()

    def _build_spec(self, camera: bool) -> robot_pb2.RobotSpec:
        state_dim = 6 + (9 if self.target_state else 0)
        observation = [
            robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[state_dim], allow_nan=False),
            robot_pb2.FeatureSpec(name=INSTRUCTION_KEY, dtype=tensor_pb2.DTYPE_UINT8, shape=[INSTRUCTION_BYTES]),
        ]
        cameras = []
        if camera:
            size = self.camera_size
            observation.append(
                robot_pb2.FeatureSpec(
                    name="camera.front", dtype=tensor_pb2.DTYPE_UINT8, shape=[size, size, 3], is_image=True
                )
            )
            cameras.append(robot_pb2.CameraSpec(name="front", width=size, height=size, fps=self.control_rate_hz))
        return robot_pb2.RobotSpec(
            robot_id=self.robot_id,
            kind=KIND,
            action=ee_velocity_action(),
            observation=observation,
            cameras=cameras,
            control_rate_hz=self.control_rate_hz,
            max_episode_steps=self.max_episode_steps,
            task="reach the target the instruction names (red, green or blue)",
            labels={"sim": "mujoco", "ee_max_speed_mps": str(MAX_SPEED), "language": "true"},
        )

    @property
    def colour(self) -> str:
        return list(COLOURS)[self.goal]

    @property
    def instruction(self) -> str:
        return instruction_for(self.colour)

    def _state(self) -> np.ndarray:
        ee = self.data.site_xpos[self._site]
        # No joint angles: within one demonstration they track the actions so closely that a cloned
        # policy keys on them instead of on where the named target is (causal confusion).
        parts = [ee, 0.1 * self.data.qvel]
        if self.target_state:  # where each target is from the hand, in decimetres (O(1) numbers)
            parts.append(TARGET_SCALE * (self.targets - ee).reshape(-1))
        return np.concatenate(parts).astype(np.float32)

    def _camera(self) -> mujoco.Renderer:
        """An EGL context belongs to the thread that made it: the robot loop's thread gets its own."""
        key = threading.get_ident()
        if key not in self._renderers:
            self._renderers[key] = mujoco.Renderer(self.model, self.camera_size, self.camera_size)
        return self._renderers[key]

    def close(self) -> None:
        key = threading.get_ident()
        for owner, renderer in list(self._renderers.items()):
            if owner == key:  # other threads' contexts cannot be released from here; they go at exit
                renderer.close()
        self._renderers.clear()

    def observe(self) -> Observation:
        obs = super().observe()
        if self.camera:
            renderer = self._camera()
            renderer.update_scene(self.data, camera="front")
            obs.features["camera.front"] = renderer.render().copy()
        obs.features[INSTRUCTION_KEY] = encode_instruction(self.instruction)
        obs.info.update(
            goal=self.goal, instruction=self.instruction, goal_pos=self._target.copy(), targets=self.targets.copy()
        )
        return obs

    def reset(self, seed: int | None = None) -> Observation:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        mujoco.mj_resetData(self.model, self.data)
        qpos = HOME_QPOS + self._rng.uniform(-INIT_NOISE, INIT_NOISE, size=3)
        self.data.qpos[:] = np.clip(qpos, self._qlow, self._qhigh)
        self.data.ctrl[:] = self.data.qpos
        mujoco.mj_forward(self.model, self.data)
        ee = self.data.site_xpos[self._site].copy()
        placed: list[np.ndarray] = []
        while len(placed) < len(COLOURS):
            p = sample_target(self._rng)
            if np.linalg.norm(p - ee) > 0.1 and all(np.linalg.norm(p - q) > MIN_SEPARATION for q in placed):
                placed.append(p)
        self.targets = np.stack(placed)
        self.data.mocap_pos[:] = self.targets
        self.goal = int(self._rng.integers(len(COLOURS)))
        self._target = self.targets[self.goal]
        mujoco.mj_forward(self.model, self.data)
        self._reward, self._terminated, self._success = 0.0, False, False
        self._holding = False
        return self.observe()

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        self._holding = False
        before = self.distance()
        self.data.ctrl[:] = self._ik_targets(applied.astype(np.float64) * MAX_SPEED)
        self._advance()
        after = self.distance()
        ee = self.data.site_xpos[self._site]
        wrong = any(np.linalg.norm(ee - t) < WRONG_RADIUS for i, t in enumerate(self.targets) if i != self.goal)
        self._success = after < SUCCESS_RADIUS
        self._terminated = self._success or wrong
        self._reward = (before - after) / (MAX_SPEED * self.period) + (SUCCESS_BONUS if self._success else 0.0)
        return applied
