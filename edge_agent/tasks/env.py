"""The simulator's own judgement: reward, termination and success as the robot's env reports them.

Used by gym-hil's Panda and the SO-101 (their gym envs compute a dense or sparse pick reward) and by
any robot whose driver knows when the task is done.
"""

from __future__ import annotations

import numpy as np

from edge_agent.robot import Observation
from edge_agent.task import TASKS, Outcome, Task
from user.registry import PluginParams


@TASKS.register("env")
class EnvTask(Task):
    """Pass through the robot's simulator reward, termination and success."""

    class Params(PluginParams):
        reward_scale: float = 1.0

    params: Params

    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        return Outcome(
            reward=self.params.reward_scale * float(next_observation.reward),
            terminated=bool(next_observation.terminated),
            success=bool(next_observation.success),
        )
