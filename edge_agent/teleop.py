"""The teleoperator interface: a human (or a scripted stand-in) who may take over the robot.

Every control tick the edge loop asks `poll(observation)`. None means "the policy drives"; an
array means "a human drives": the edge applies it instead of the policy's action (clipped to the
robot's limits like any action) and sends the step with `intervention = true` and the human action
as the action, so replay keeps it in the interventions table (HIL-SERL, HG-DAgger). `poll` is on the
control loop's hot path: it must not block.

New teleoperators are one class plus `@TELEOPERATORS.register("kind")` in a module of
`edge_agent.teleoperators`. One that can drive only some robots (a scripted expert reads one
simulator's privileged `info`) says so in `robot_kinds` / `observation_keys` (and `info_keys`, for
the refusal's text): the edge agent refuses the pairing at start, naming `edge.robots[i].teleop.kind`,
instead of failing every poll. One that learns what it drives only from its device (lerobot's, by action
name) refuses in its constructor, also at start, with a ParamError naming the param to fix.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from edge_agent.robot import Observation
from user.registry import PluginParams, Registry
from user.v1 import robot_pb2


class Teleoperator(ABC):
    """connect -> (poll)* -> disconnect."""

    Params: type[PluginParams] = PluginParams
    robot_kinds: ClassVar[tuple[str, ...]] = ()
    """Robot kinds it can drive; empty: any kind."""
    observation_keys: ClassVar[tuple[str, ...]] = ()
    """Observation features (the spec's observation names) its poll reads: the robot must have every one."""
    info_keys: ClassVar[tuple[str, ...]] = ()
    """`Observation.info` entries its poll reads (not in a spec: told in a refusal, checked through robot_kinds)."""

    def __init__(self, params: PluginParams, spec: robot_pb2.RobotSpec) -> None:
        if (why := self.unsupported(spec)) is not None:
            raise ValueError(f"{type(self).__name__} cannot drive robot {spec.robot_id!r} ({spec.kind}): {why}")
        self.params = params
        self.spec = spec

    @classmethod
    def needs(cls) -> str:
        """What it needs of a robot, in words ("" for any robot)."""
        parts = []
        if cls.robot_kinds:
            parts.append(f"robot kind {' or '.join(cls.robot_kinds)}")
        if cls.observation_keys:
            parts.append(f"observation {', '.join(cls.observation_keys)}")
        if cls.info_keys:
            parts.append(f"info {', '.join(cls.info_keys)}")
        return ", ".join(parts)

    @classmethod
    def unsupported(cls, spec: robot_pb2.RobotSpec) -> str | None:
        """Why it cannot drive the robot of `spec` (checked at start, before it is built), or None if it can."""
        if cls.robot_kinds and spec.kind not in cls.robot_kinds:
            return f"it needs {cls.needs()}"
        have = {f.name for f in spec.observation}
        if missing := [key for key in cls.observation_keys if key not in have]:
            return f"it needs {cls.needs()}; the robot has no observation {', '.join(missing)}"
        return None

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
