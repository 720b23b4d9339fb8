"""lerobot's teleoperators (keyboard, gamepad, leader arms) as one teleoperator kind.

    teleop: {kind: lerobot, params: {type: gamepad, config: {use_gripper: true}}}

Every tick the device's action dict is read and mapped onto the robot's action vector by name: a
robot action takes its entry in `action_map`, else the device key of the same name, else a common
alias (dx/vx -> delta_x, ..., grip/grasp -> gripper), else its value in `defaults`. A pairing that
leaves a robot action with none of these is refused when the teleoperator is built (naming
`params.action_map`): 0 is no safe stand-in (for a position joint it is a jump to mid-range).
Deltas are multiplied by `scale`. lerobot's
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
from edge_agent.task import ParamError
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
        defaults: dict[str, float] = Field(
            default={},
            description="robot action name -> the value sent for it while the device has no key for it "
            "(e.g. {rx: 0, ry: 0, rz: 0}: a pad does not turn a Panda's unused rotation)",
        )
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
        self.keys = self._map(_device_keys(self.device))
        self._grasp = 1.0  # absolute gripper target until the human moves it: open
        self._labels: list[str] = []
        self._lock = threading.Lock()  # events() may be read from another thread than poll()

    def connect(self) -> None:
        if not self.device.is_connected:
            self.device.connect()

    def disconnect(self) -> None:
        if self.device.is_connected:
            self.device.disconnect()

    def _map(self, device_keys: list[str]) -> dict[str, str]:
        """Robot action name -> device key, for every action the device drives; refuses a pairing that leaves an
        action with neither a device key nor a default."""
        p = self.params
        for field_name, names in (("action_map", p.action_map), ("defaults", p.defaults)):
            if unknown := sorted(set(names) - set(self.names)):
                raise ParamError(
                    field_name, f"{unknown} are not actions of robot {self.spec.robot_id!r} ({self.names})"
                )
        if missing := sorted(set(p.action_map.values()) - set(device_keys)):
            raise ParamError("action_map", f"the {p.type} device has no keys {missing} (it has {device_keys})")
        if not all(np.isfinite(v) for v in p.defaults.values()):
            raise ParamError("defaults", f"must be finite, got {p.defaults}")
        keys: dict[str, str] = {}
        for name in self.names:
            key = next((k for k in (p.action_map.get(name), name, ALIASES.get(name)) if k in device_keys), None)
            if key is not None:
                keys[name] = key
        if unmapped := [n for n in self.names if n not in keys and n not in p.defaults]:
            raise ParamError(
                "action_map",
                f"the {p.type} device (keys {device_keys}) drives none of the robot's actions {unmapped}: map each "
                "to a device key in action_map, or give it a value in defaults",
            )
        return keys

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
            key = self.keys.get(name)
            if key is None:
                vec[i] = self.params.defaults[name]
                continue
            if key not in action:  # a device that stops sending a key it declared: never guess a value
                raise ValueError(f"the {self.params.type} teleoperator sent no {key!r} (robot action {name!r})")
            value = float(action[key])
            vec[i] = self._gripper(value) if key == "gripper" else self.params.scale * value
        return vec.reshape(tuple(self.spec.action.shape))


def _device_keys(device: Any) -> list[str]:
    """The action keys a lerobot teleoperator declares: end-effector pads name them in `names` (key -> index),
    leader arms map each to `float`."""
    features = dict(device.action_features or {})
    names = features.get("names")
    if isinstance(names, dict) and all(isinstance(v, int) for v in names.values()):
        return [str(k) for k in names]
    return [str(k) for k, v in features.items() if v is float]
