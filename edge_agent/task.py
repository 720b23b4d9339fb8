"""The task interface: what counts as reward, success and the end of an episode, apart from the robot.

A robot only moves and observes; a task judges. The edge loop calls `reset` at the start of an
episode and `evaluate` after every step with (observation, applied action, next observation). The
robot's own simulator reward and termination (gym envs have them) reach a task through
`Observation.reward/terminated/success` and `info`; the `env` task passes them through, others
compute their own (a dense distance reward, a human success key, a trained success classifier).

New tasks are one class plus `@TASKS.register("kind")` in a module of `edge_agent.tasks`. A constructor
that refuses its params raises `ParamError(field, why)`; the edge agent names the entry's field
(`edge.robots[0].task.params.model: ...`) and stops at start with one line.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from edge_agent.robot import Observation
from user.registry import PluginParams, Registry
from user.v1 import robot_pb2


class ParamError(ValueError):
    """A task's or teleoperator's param that validates alone but cannot be used (a model folder without a model,
    a model for an observation the robot lacks); `field` is the param's name, for the error's dotted field."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class Outcome:
    reward: float
    terminated: bool = False  # no bootstrapping past this step (success or failure)
    success: bool = False


class Task(ABC):
    """reset(first observation) -> evaluate(obs, action, next_obs)* per episode."""

    Params: type[PluginParams] = PluginParams

    def __init__(self, params: PluginParams, spec: robot_pb2.RobotSpec) -> None:
        self.params = params
        self.spec = spec

    def reset(self, observation: Observation) -> None:  # noqa: B027 - optional hook
        """A new episode starts with `observation`."""

    @abstractmethod
    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        """Reward for applying `action` in `observation`, and whether `next_observation` ends the episode."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release models, windows or devices the task holds."""


TASKS: Registry[Task] = Registry("task", Task, "edge_agent.tasks")
