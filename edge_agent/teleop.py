"""The teleoperator interface: a human (or a scripted stand-in) who may take over the robot.

Every control tick the edge loop asks `poll(observation)`. None means "the policy drives"; an
array means "a human drives": the edge applies it instead of the policy's action (clipped to the
robot's limits like any action) and sends the step with `intervention = true` and the human action
as the action, so replay keeps it in the interventions table (HIL-SERL, HG-DAgger). `poll` is on the
control loop's hot path: it must not block.

New teleoperators are one class plus `@TELEOPERATORS.register("kind")` in a module of
`edge_agent.teleoperators`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from edge_agent.robot import Observation
from user.registry import PluginParams, Registry
from user.v1 import robot_pb2


class Teleoperator(ABC):
    """connect -> (poll)* -> disconnect."""

    Params: type[PluginParams] = PluginParams

    def __init__(self, params: PluginParams, spec: robot_pb2.RobotSpec) -> None:
        self.params = params
        self.spec = spec

    def connect(self) -> None:  # noqa: B027 - optional hook
        """Open the device (keyboard listener, gamepad, leader arm)."""

    def reset(self, observation: Observation) -> None:  # noqa: B027 - optional hook
        """A new episode starts (a scripted expert re-plans here)."""

    @abstractmethod
    def poll(self, observation: Observation) -> np.ndarray | None:
        """The human's action for this tick, shaped like the robot's action space, or None to let the policy act."""

    def events(self) -> list[str]:
        """Label events the human gave since the last call: "success", "failure" or "rerecord" (a
        device's success/failure buttons; the human_label task reads them). Default: none."""
        return []

    def disconnect(self) -> None:  # noqa: B027 - optional hook
        """Close the device."""


TELEOPERATORS: Registry[Teleoperator] = Registry("teleoperator", Teleoperator, "edge_agent.teleoperators")
