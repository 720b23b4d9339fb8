"""lerobot's teleoperators (keyboard, gamepad, leader arms) as one teleoperator kind.

    teleop: {kind: lerobot, params: {type: gamepad, config: {use_gripper: true}}}

Every tick the device's action dict is read and mapped onto the robot's action vector by name: a
robot action takes the device key of the same name, else its entry in `action_map`, else a common
alias (dx/vx -> delta_x, ..., grip/grasp -> gripper). Deltas are multiplied by `scale`. lerobot's
end-effector teleoperators send the gripper as 0 close / 1 stay / 2 open: `gripper: delta` turns
that into -1..1 with +1 closing (gym-hil's Panda), `absolute` into a 0 closed / 1 open target that
keeps its value on "stay" (SO-101). The human takes over while the device says so: lerobot's
`get_teleop_events()` IS_INTERVENTION (keyboard: a movement key held; gamepad: the intervention
button) or, for devices without events (leader arms), whenever `intervention: always`. The same
call's SUCCESS / FAILURE / TERMINATE_EPISODE / RERECORD_EPISODE (keyboard: s, q, r; gamepad: its
buttons) become label events (`events()`) for the human_label task with `source: teleop`.
"""

from __future__ import annotations

import importlib.util
import threading
from typing import Any, Literal

import numpy as np
from pydantic import Field

from edge_agent.robot import Observation
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from user.registry import PluginParams
from user.v1 import robot_pb2

if importlib.util.find_spec("lerobot") is None:
    raise ImportError("the lerobot teleoperator adapter needs the lerobot package")

ALIASES = {
    "dx": "delta_x",
    "vx": "delta_x",
    "x": "delta_x",
    "dy": "delta_y",
    "vy": "delta_y",
    "y": "delta_y",
    "dz": "delta_z",
    "vz": "delta_z",
    "z": "delta_z",
    "grip": "gripper",
    "grasp": "gripper",
}
GRIPPER_CLOSE, GRIPPER_STAY, GRIPPER_OPEN = 0, 1, 2


@TELEOPERATORS.register("lerobot")
class LerobotTeleop(Teleoperator):
    """A lerobot teleoperator (keyboard_ee, gamepad, so101_leader, ...) that takes over on its intervention event."""

    class Params(PluginParams):
        type: str = Field(min_length=1, description="lerobot teleoperator type: keyboard_ee, gamepad, so101_leader")
        config: dict[str, Any] = Field(default={}, description="the lerobot teleoperator config")
        action_map: dict[str, str] = Field(default={}, description="robot action name -> device action key")
        scale: float = Field(default=1.0, description="multiplies the device's non-gripper values")
        gripper: Literal["delta", "absolute", "raw"] = "delta"
        intervention: Literal["events", "always"] = Field(
            default="events", description="events: while the device says so; always: every tick"
        )

    params: Params

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec, device: Any | None = None) -> None:
        super().__init__(params, spec)
        from edge_agent.lerobot_devices import make_lerobot_teleoperator

        self.device = device if device is not None else make_lerobot_teleoperator(params.type, params.config)
        self.names = list(spec.action.names)
        if len(self.names) != int(np.prod(spec.action.shape)):
            raise ValueError("lerobot teleop: the robot's action space must name every action")
        self._grasp = 1.0  # absolute gripper target until the human moves it: open
        self._labels: list[str] = []
        self._lock = threading.Lock()  # events() may be read from another thread than poll()

    def connect(self) -> None:
        if not self.device.is_connected:
            self.device.connect()

    def disconnect(self) -> None:
        if self.device.is_connected:
            self.device.disconnect()

    def _key(self, name: str, action: dict[str, Any]) -> str | None:
        for key in (self.params.action_map.get(name), name, ALIASES.get(name)):
            if key is not None and key in action:
                return key
        return None

    def _gripper(self, value: float) -> float:
        if self.params.gripper == "raw":
            return value
        command = round(value)
        if self.params.gripper == "delta":
            return {GRIPPER_CLOSE: 1.0, GRIPPER_OPEN: -1.0}.get(command, 0.0)
        self._grasp = {GRIPPER_CLOSE: 0.0, GRIPPER_OPEN: 1.0}.get(command, self._grasp)
        return self._grasp

    def _intervening(self) -> bool:
        """Read the device's events once per tick (reading drains them): keep its labels, say if it intervenes."""
        read = getattr(self.device, "get_teleop_events", None)
        if read is None:
            return self.params.intervention == "always"
        from lerobot.teleoperators import TeleopEvents

        events = read()
        label = None
        if events.get(TeleopEvents.SUCCESS):
            label = "success"
        elif events.get(TeleopEvents.RERECORD_EPISODE):
            label = "rerecord"
        elif events.get(TeleopEvents.FAILURE) or events.get(TeleopEvents.TERMINATE_EPISODE):
            label = "failure"
        if label is not None:
            with self._lock:
                self._labels.append(label)
        return self.params.intervention == "always" or bool(events.get(TeleopEvents.IS_INTERVENTION, False))

    def events(self) -> list[str]:
        with self._lock:
            labels, self._labels = self._labels, []
        return labels

    def poll(self, observation: Observation) -> np.ndarray | None:
        action = dict(self.device.get_action())  # first: lerobot's keyboard drains its key queue here
        if not self._intervening():
            return None
        vec = np.zeros(len(self.names), np.float32)
        for i, name in enumerate(self.names):
            key = self._key(name, action)
            if key is None:
                continue
            value = float(action[key])
            vec[i] = self._gripper(value) if key == "gripper" else self.params.scale * value
        return vec.reshape(tuple(self.spec.action.shape))
