"""The robot interface every robot implements (sim arm, gym-hil Panda, SO-101, any lerobot robot).

A robot is physical: `act` clips to the declared limits, `hold` keeps it still and safe. A robot
moves and observes; whether a step earned reward is a task's call (edge_agent/task.py). Simulated
robots still report their simulator's own reward in `Observation.reward`, which the `env` task
passes through.

New robots are one class with a typed `Params` model plus `@ROBOTS.register("kind")` in a module of
`edge_agent.robots` (no import list to edit). The class is built as cls(params, robot_id=, seed=).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from user import spec as spec_contract
from user.registry import PluginParams, Registry
from user.v1 import robot_pb2


@dataclass
class Observation:
    features: dict[str, np.ndarray]  # must match spec.observation by name, dtype and shape
    reward: float = 0.0  # reward for the action that led here
    terminated: bool = False  # task over (success or failure): no bootstrapping past it
    success: bool = False
    info: dict[str, Any] = field(default_factory=dict)


class Robot(ABC):
    """connect -> spec -> reset -> (act -> observe)* -> disconnect. Sims advance one control period per act."""

    Params: type[PluginParams] = PluginParams
    default_task: str = "env"  # the task kind a config entry without `task:` gets

    @property
    @abstractmethod
    def spec(self) -> robot_pb2.RobotSpec: ...

    @abstractmethod
    def reset(self, seed: int | None = None) -> Observation:
        """Start a new episode and return its first observation."""

    @abstractmethod
    def observe(self) -> Observation:
        """The current observation, reward and termination."""

    @abstractmethod
    def act(self, action: np.ndarray) -> np.ndarray:
        """Clip `action` to the spec's limits, apply it, return what was applied."""

    @abstractmethod
    def hold(self) -> np.ndarray | None:
        """Keep still (no policy answer, link lost, paused). Return the action this amounts to, as `act` would
        return it (the spec's action layout and dtype, within its limits: what a policy would send for the same
        effect, e.g. a zero delta, or the position that was commanded), so a held step records what the robot
        did; None when nothing was sent or it cannot say."""

    def connect(self) -> None:  # noqa: B027 - optional hook
        """Open the hardware (serial bus, cameras). Sims are ready when built."""

    def disconnect(self) -> None:
        """Leave the hardware safe and release it; sims close their simulator."""
        self.close()

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release hardware or simulator resources."""


# The action contract lives in user.spec (one place for every organ); re-exported for robot plug-ins.
action_bounds = spec_contract.action_bounds
clip_action = spec_contract.clip_action


ROBOTS: Registry[Robot] = Registry("robot", Robot, "edge_agent.robots")


def register_robot(kind: str, description: str | None = None) -> Callable[[type[Robot]], type[Robot]]:
    """Kept for existing plug-ins: the same as `ROBOTS.register(kind)`."""
    return ROBOTS.register(kind, description)


def make_robot(
    kind: str, robot_id: str, params: dict[str, Any] | None = None, seed: int = 0, where: str = "params"
) -> Robot:
    """Build a registered robot after validating `params` against its `Params` (errors name `where.<field>`)."""
    return ROBOTS.build(kind, params, where=where, robot_id=robot_id, seed=seed)


def known_robot_kinds() -> list[str]:
    return ROBOTS.kinds()
