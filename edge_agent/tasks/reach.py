"""Reach a target: dense progress reward plus a bonus, success within a radius.

The reward is progress toward the target normalised by the farthest the end-effector can move in one
control period (about 1 per step at full speed straight at it), plus `success_bonus` when the
end-effector ends within `success_radius` of the target, which also ends the episode. The robot
reports `distance` (metres, end-effector to target) in `Observation.info`; the top speed comes from
the spec label `ee_max_speed_mps` unless given.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from edge_agent.robot import Observation
from edge_agent.task import TASKS, Outcome, Task
from user.registry import PluginParams
from user.v1 import robot_pb2

SUCCESS_RADIUS = 0.02  # m
SUCCESS_BONUS = 5.0


def reach_outcome(
    before_m: float,
    after_m: float,
    max_step_m: float,
    success_radius: float = SUCCESS_RADIUS,
    bonus: float = SUCCESS_BONUS,
) -> Outcome:
    """The reach reward for one step from the end-effector-to-target distance before and after it."""
    success = after_m < success_radius
    reward = (before_m - after_m) / max_step_m + (bonus if success else 0.0)
    return Outcome(reward=reward, terminated=success, success=success)


@TASKS.register("reach")
class ReachTask(Task):
    """Bring the end-effector within success_radius of the target (dense progress reward)."""

    class Params(PluginParams):
        success_radius: float = Field(default=SUCCESS_RADIUS, gt=0, description="metres")
        success_bonus: float = SUCCESS_BONUS
        max_speed_mps: float | None = Field(default=None, gt=0, description="default: spec label ee_max_speed_mps")

    params: Params

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec) -> None:
        super().__init__(params, spec)
        speed = params.max_speed_mps or float(spec.labels.get("ee_max_speed_mps", "0") or 0)
        if speed <= 0 or spec.control_rate_hz <= 0:
            raise ValueError("reach task: needs max_speed_mps (or spec label ee_max_speed_mps) and a control rate")
        self.max_step_m = speed * (1.0 / spec.control_rate_hz)

    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        return reach_outcome(
            distance(observation),
            distance(next_observation),
            self.max_step_m,
            self.params.success_radius,
            self.params.success_bonus,
        )


def distance(observation: Observation) -> float:
    info = observation.info
    if "distance" in info:
        return float(info["distance"])
    return float(np.linalg.norm(np.asarray(info["target_pos"]) - np.asarray(info["ee_pos"])))
