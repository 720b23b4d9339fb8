"""A simulated 3-joint MuJoCo arm that learns to reach random targets.

The policy commands an end-effector velocity; damped least-squares IK turns it into joint
position targets for the servo actuators, the same interface a real arm's Cartesian
controller offers. One act() = one control period of simulated time.

The arm does not judge: the `reach` task (its default) computes reward and success from the
end-effector-to-target distance this robot reports in `Observation.info`. `Observation.reward` still
carries the same reach reward as the simulator's own, so code that steps the arm directly, gym-style
(cloud_learner.local.train_local), sees it too; both come from `tasks.reach.reach_outcome`.
"""

from __future__ import annotations

import math
import os

# Headless rendering for the optional camera; must be set before mujoco is imported.
os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
from pydantic import Field

from edge_agent.rendering import CameraRenderer
from edge_agent.robot import ROBOTS, Observation, Robot, clip_action
from edge_agent.tasks.reach import reach_outcome
from user.registry import PluginParams
from user.v1 import robot_pb2, tensor_pb2

KIND = "sim_reach_arm"
TIMESTEP = 0.002  # physics step (s)
MAX_SPEED = 0.3  # m/s of end-effector motion for |action| = 1
IK_DAMPING = 0.02
_IK_DAMPING_EYE = IK_DAMPING**2 * np.eye(3)  # made once: the IK solve runs every step
SHOULDER = np.array([0.0, 0.0, 0.15])  # shoulder pitch axis position in the world
HOME_QPOS = np.array([0.0, -0.6, 1.4])
INIT_NOISE = 0.15  # rad, uniform per joint around HOME_QPOS
CAMERA_SIZE = 64

ARM_XML = """
<mujoco model="sim_reach_arm">
  <compiler angle="radian"/>
  <option timestep="0.002" integrator="implicitfast"/>
  <visual><quality shadowsize="0" offsamples="0"/></visual>
  <default>
    <geom contype="0" conaffinity="0" density="500"/>
    <joint damping="0.5" armature="0.01"/>
    <position kp="150" dampratio="1"/>
  </default>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="1 1 0.01" rgba="0.8 0.8 0.8 1"/>
    <camera name="front" pos="1.0 0 0.55" xyaxes="0 1 0 -0.45 0 0.9" fovy="60"/>
    <geom name="pedestal" type="cylinder" size="0.05 0.05" pos="0 0 0.05" rgba="0.3 0.3 0.3 1"/>
    <body name="base" pos="0 0 0.1" gravcomp="1">
      <joint name="base_yaw" type="hinge" axis="0 0 1" range="-1.6 1.6"/>
      <geom type="cylinder" size="0.04 0.025" pos="0 0 0.025" rgba="0.2 0.4 0.8 1"/>
      <body name="upper_arm" pos="0 0 0.05" gravcomp="1">
        <joint name="shoulder_pitch" type="hinge" axis="0 1 0" range="-2.2 0.6"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" rgba="0.2 0.6 0.9 1"/>
        <body name="forearm" pos="0.3 0 0" gravcomp="1">
          <joint name="elbow_pitch" type="hinge" axis="0 1 0" range="-0.2 2.8"/>
          <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.02" rgba="0.9 0.6 0.2 1"/>
          <site name="ee" pos="0.25 0 0" size="0.015" rgba="1 0 0 1"/>
        </body>
      </body>
    </body>
    <body name="target" mocap="true" pos="0.3 0 0.3">
      <geom type="sphere" size="0.02" rgba="0 1 0 0.6"/>
    </body>
  </worldbody>
  <actuator>
    <position name="base_yaw" joint="base_yaw" ctrlrange="-1.6 1.6"/>
    <position name="shoulder_pitch" joint="shoulder_pitch" ctrlrange="-2.2 0.6"/>
    <position name="elbow_pitch" joint="elbow_pitch" ctrlrange="-0.2 2.8"/>
  </actuator>
</mujoco>
"""


def ee_velocity_action() -> robot_pb2.ActionSpace:
    """End-effector velocity (vx, vy, vz) in [-1, 1], scaled by MAX_SPEED."""
    return robot_pb2.ActionSpace(
        shape=[3], low=[-1.0] * 3, high=[1.0] * 3, names=["vx", "vy", "vz"], dtype=tensor_pb2.DTYPE_FLOAT32
    )


def sample_target(rng: np.random.Generator) -> np.ndarray:
    """A point in front of the arm, well inside its reach (0.55 m) and above the floor."""
    yaw = rng.uniform(-np.pi / 3, np.pi / 3)
    elevation = rng.uniform(-np.pi / 8, np.pi / 4)
    radius = rng.uniform(0.22, 0.45)
    offset = radius * np.array([np.cos(elevation) * np.cos(yaw), np.cos(elevation) * np.sin(yaw), np.sin(elevation)])
    return SHOULDER + offset


@ROBOTS.register(KIND)
class SimReachArm(Robot):
    """3-joint MuJoCo arm reaching a random target (task: reach within 2 cm)."""

    class Params(PluginParams):
        control_rate_hz: float = Field(default=20.0, gt=0)
        max_episode_steps: int = Field(default=50, ge=1)
        camera: bool = Field(default=False, description="add a 64x64 front camera image")

    default_task = "reach"

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        camera = params.camera
        self._load_arm(ARM_XML, robot_id, params.control_rate_hz, params.max_episode_steps, seed)
        self._target = sample_target(self._rng)
        self._renderer: CameraRenderer | None = None
        if camera:
            self._renderer = CameraRenderer(self.model, CAMERA_SIZE, CAMERA_SIZE)
        self._spec = self._build_spec(camera)
        self._reward, self._terminated, self._success = 0.0, False, False
        self._holding = False
        self.reset()

    def _load_arm(self, xml: str, robot_id: str, control_rate_hz: float, max_episode_steps: int, seed: int) -> None:
        """The MuJoCo model, timing and IK buffers every arm built on this one shares."""
        self.robot_id = robot_id
        self.control_rate_hz = float(control_rate_hz)
        self.max_episode_steps = int(max_episode_steps)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self.period = 1.0 / self.control_rate_hz
        self.substeps = max(1, round(self.period / TIMESTEP))
        self._site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "ee")
        self._qlow = self.model.jnt_range[:, 0].copy()
        self._qhigh = self.model.jnt_range[:, 1].copy()
        self._jacp = np.zeros((3, self.model.nv))
        self._rng = np.random.default_rng(seed)

    def _build_spec(self, camera: bool) -> robot_pb2.RobotSpec:
        observation = [
            robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[15], allow_nan=False),
        ]
        cameras = []
        if camera:
            observation.append(
                robot_pb2.FeatureSpec(
                    name="camera.front",
                    dtype=tensor_pb2.DTYPE_UINT8,
                    shape=[CAMERA_SIZE, CAMERA_SIZE, 3],
                    is_image=True,
                )
            )
            cameras.append(
                robot_pb2.CameraSpec(name="front", width=CAMERA_SIZE, height=CAMERA_SIZE, fps=self.control_rate_hz)
            )
        return robot_pb2.RobotSpec(
            robot_id=self.robot_id,
            kind=KIND,
            action=ee_velocity_action(),
            observation=observation,
            cameras=cameras,
            control_rate_hz=self.control_rate_hz,
            max_episode_steps=self.max_episode_steps,
            task="reach the green target with the end-effector (within 2 cm)",
            labels={"sim": "mujoco", "ee_max_speed_mps": str(MAX_SPEED)},
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    # --- state -------------------------------------------------------------------------------------

    def ee_pos(self) -> np.ndarray:
        return self.data.site_xpos[self._site].copy()

    @property
    def target(self) -> np.ndarray:
        return self._target.copy()

    def distance(self) -> float:
        # math.dist over the two 3-vectors: ~7x cheaper than np.linalg.norm's dispatch, and it runs 3x a step
        return math.dist(self._target, self.data.site_xpos[self._site])

    def _state(self) -> np.ndarray:
        ee = self.data.site_xpos[self._site]
        # Joint velocities are scaled down so every feature is O(1) or smaller.
        return np.concatenate([ee, self._target, self._target - ee, self.data.qpos, 0.1 * self.data.qvel]).astype(
            np.float32
        )

    def observe(self) -> Observation:
        features = {"state": self._state()}
        if self._renderer is not None:
            features["camera.front"] = self._renderer.render(self.data, "front")
        return Observation(
            features=features,
            reward=self._reward,
            terminated=self._terminated,
            success=self._success,
            info={"distance": self.distance(), "ee_pos": self.ee_pos(), "target_pos": self.target},
        )

    # --- control -----------------------------------------------------------------------------------

    def reset(self, seed: int | None = None) -> Observation:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        mujoco.mj_resetData(self.model, self.data)
        qpos = HOME_QPOS + self._rng.uniform(-INIT_NOISE, INIT_NOISE, size=3)
        self.data.qpos[:] = np.clip(qpos, self._qlow, self._qhigh)
        self.data.ctrl[:] = self.data.qpos
        mujoco.mj_forward(self.model, self.data)
        # A target already within reach would be a free success; resample it.
        while True:
            self._target = sample_target(self._rng)
            if self.distance() > 0.1:
                break
        self.data.mocap_pos[0] = self._target
        self._reward, self._terminated, self._success = 0.0, False, False
        self._holding = False
        return self.observe()

    def _ik_targets(self, ee_velocity: np.ndarray) -> np.ndarray:
        """Joint targets that move the site by ee_velocity * period (damped least squares)."""
        mujoco.mj_jacSite(self.model, self.data, self._jacp, None, self._site)
        jac = self._jacp
        dx = ee_velocity * self.period
        dq = jac.T @ np.linalg.solve(jac @ jac.T + _IK_DAMPING_EYE, dx)
        return np.clip(self.data.ctrl + dq, self._qlow, self._qhigh)

    def _advance(self) -> None:
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)  # one call: the substeps loop in C

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        self._holding = False
        before = self.distance()
        self.data.ctrl[:] = self._ik_targets(applied.astype(np.float64) * MAX_SPEED)
        self._advance()
        outcome = reach_outcome(before, self.distance(), MAX_SPEED * self.period)
        self._reward, self._terminated, self._success = outcome.reward, outcome.terminated, outcome.success
        return applied

    def hold(self) -> np.ndarray:
        """Stop and stay: the first hold pins the joint targets to where the arm is now, later ones keep them.
        As an action that is zero end-effector velocity."""
        if not self._holding:
            # Targets run slightly ahead of a moving arm; pinning them stops it within a few millimetres.
            self.data.ctrl[:] = self.data.qpos
            self._holding = True
        self._advance()
        self._reward = 0.0
        return clip_action(self._spec, np.zeros(tuple(self._spec.action.shape), np.float32))

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
