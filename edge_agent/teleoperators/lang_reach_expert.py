"""A scripted human for lang_reach_arm: drives to the named target, and in HG-DAgger mode takes
over only when the policy errs.

The expert sees what a person beside the robot sees: where the named target is (`goal_pos` in
the observation's info). Its action moves the end-effector straight at the target at full speed,
slowing inside the last step. Modes:

- `always`: every tick is the expert's (collecting demonstrations);
- `intervene` (HG-DAgger gating): the policy drives; when the arm has not come closer to the
  named target by `min_progress_m` over the last `patience` ticks, or is heading for another
  target, the expert takes over for `takeover_steps` ticks (or until success), then hands back;
- `never`: only watches (evaluation).
"""

from __future__ import annotations

from collections import deque
from typing import Literal

import numpy as np
from pydantic import Field

from edge_agent.robot import Observation
from edge_agent.robots.lang_reach import KIND as LANG_REACH_ARM
from edge_agent.robots.sim_arm import MAX_SPEED
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from user.registry import PluginParams
from user.v1 import robot_pb2


def expert_action(ee: np.ndarray, goal: np.ndarray, period_s: float) -> np.ndarray:
    """Full speed straight at the goal; proportional inside one step's travel."""
    step = MAX_SPEED * period_s
    delta = np.asarray(goal, np.float64) - np.asarray(ee, np.float64)
    dist = float(np.linalg.norm(delta))
    if dist < 1e-9:
        return np.zeros(3, np.float32)
    return (delta / dist * min(1.0, dist / step)).astype(np.float32)


@TELEOPERATORS.register("lang_reach_expert")
class LangReachExpert(Teleoperator):
    """Scripted expert for lang_reach_arm (demonstrations and HG-DAgger interventions)."""

    robot_kinds = (LANG_REACH_ARM,)  # the named target's position is that simulator's privileged info
    observation_keys = ("state",)  # the end-effector: its first three values
    info_keys = ("goal_pos",)

    class Params(PluginParams):
        mode: Literal["always", "intervene", "never"] = "intervene"
        patience: int = Field(4, ge=1, description="ticks of too little progress before taking over")
        min_progress_m: float = Field(0.01, ge=0, description="progress over `patience` ticks that counts as fine")
        takeover_steps: int = Field(10, ge=1, description="ticks the expert drives once it takes over")

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec) -> None:
        super().__init__(params, spec)
        self.p = params
        self.period_s = 1.0 / (spec.control_rate_hz or 20.0)
        self._distances: deque[float] = deque(maxlen=params.patience + 1)
        self._driving = 0
        self.takeovers = 0
        self.steps = 0  # ticks the expert drove

    def reset(self, observation: Observation) -> None:
        self._distances.clear()
        self._driving = 0

    def poll(self, observation: Observation) -> np.ndarray | None:
        ee = np.asarray(observation.features["state"][:3], np.float64)
        goal = np.asarray(observation.info["goal_pos"], np.float64)
        self._distances.append(float(np.linalg.norm(goal - ee)))
        if self.p.mode == "never":
            return None
        if self.p.mode == "intervene" and self._driving == 0:
            if not self._erring(observation, ee):
                return None
            self._driving = self.p.takeover_steps
            self.takeovers += 1
        self._driving = max(0, self._driving - 1)
        self.steps += 1
        if self._driving == 0:
            self._distances.clear()  # hand back with a fresh window
        return expert_action(ee, goal, self.period_s)

    def _erring(self, observation: Observation, ee: np.ndarray) -> bool:
        window_full = len(self._distances) > self.p.patience
        if window_full and self._distances[0] - self._distances[-1] < self.p.min_progress_m:
            return True
        targets = observation.info.get("targets")
        if targets is not None:  # closer to a wrong target than to the named one, and near it
            goal_d = self._distances[-1]
            return any(min(0.08, goal_d) > np.linalg.norm(t - ee) for t in targets)
        return False
