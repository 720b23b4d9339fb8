"""The robot interface every robot implements (sim arm, gym-hil Panda, lerobot robots).

A robot is physical: `act` clips to the declared limits, `hold` keeps it still and safe.
New robots are one class plus `@register_robot("kind")`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from user import spec as spec_contract
from user.v1 import robot_pb2


@dataclass
class Observation:
    features: dict[str, np.ndarray]  # must match spec.observation by name, dtype and shape
    reward: float = 0.0  # reward for the action that led here
    terminated: bool = False  # task over (success or failure): no bootstrapping past it
    success: bool = False
    info: dict[str, Any] = field(default_factory=dict)


class Robot(ABC):
    """spec -> reset -> (act -> observe)* -> close. Sims advance one control period per act."""

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
    def hold(self) -> None:
        """Keep still (no policy answer, link lost, paused)."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release hardware or simulator resources."""


# The action contract lives in user.spec (one place for every organ); re-exported for robot plug-ins.
action_bounds = spec_contract.action_bounds
clip_action = spec_contract.clip_action


RobotFactory = Callable[..., Robot]
_REGISTRY: dict[str, RobotFactory] = {}


def register_robot(kind: str) -> Callable[[RobotFactory], RobotFactory]:
    def deco(factory: RobotFactory) -> RobotFactory:
        _REGISTRY[kind] = factory
        return factory

    return deco


def make_robot(kind: str, robot_id: str, params: dict[str, Any] | None = None, seed: int = 0) -> Robot:
    """Build a registered robot: factory(robot_id=..., seed=..., **params)."""
    import edge_agent.robots  # noqa: F401 - registers the built-in robots

    try:
        factory = _REGISTRY[kind]
    except KeyError:
        raise ValueError(f"unknown robot kind {kind!r}; known: {sorted(_REGISTRY)}") from None
    return factory(robot_id=robot_id, seed=seed, **(params or {}))


def known_robot_kinds() -> list[str]:
    import edge_agent.robots  # noqa: F401

    return sorted(_REGISTRY)
