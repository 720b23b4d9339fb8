"""Any lerobot robot (SO-100/101 follower, Koch, OMX, LeKiwi, ...) behind the Robot interface.

    robots: [{id: so101, kind: lerobot, params: {type: so101_follower, config: {port: /dev/ttyACM0}}}]

lerobot describes a robot by dicts: observation_features maps a name to `float` (a joint position,
a velocity) or to an image shape (h, w, 3); action_features maps a name to `float`. Here the float
observations, in the robot's declared order, become one float32 "state" vector, each camera a uint8
"camera.<name>" image, and the float actions the action vector (names in the spec, limits from params:
lerobot declares none). `connect`/`disconnect` open and release the bus and cameras. A real robot has no
simulator judging it: its default task is `human_label` (a key marks success).

How `hold` keeps each action still depends on what the action commands, told by its name:
- a velocity (`x.vel`, `theta.vel`: LeKiwi's base), or a key in `hold_zero_keys`: 0, stop;
- a position (`shoulder_pan.pos`, unitree's `.q`), or a key in `hold_position_keys`: its last observed value (else
  its last command), so the joint stays where it is; a position never observed nor commanded is not sent at all
  (no value is a safe guess: 0 would be a jump to mid-range).
An action named otherwise (EarthRover's `linear_velocity`) is refused when the robot is built until one of the two
lists names it. Velocity-like actions (the zero-held ones) also need explicit `action_low`/`action_high`: the
default +-100 is lerobot's normalised range of SO-101/Koch position joints, not a speed.

`disconnect` (edge stop, restart, hot-plug detach) leaves the motors' torque on by default, so an arm keeps its pose
instead of falling: `disable_torque_on_disconnect` is set on lerobot configs that have it (SO-100/101, Koch, OMX,
LeKiwi, their bimanual versions), where lerobot's own default is true.

lerobot (and torch, which it imports) loads on first build, so discovering robot kinds stays fast.
The type and config are checked with the params (an unknown type or a config lerobot cannot decode names
`...params.type` / `...params.config`); a driver package the device needs is only found missing when it is
built (an ImportError, which the edge agent reports as one line naming the robot).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import typing
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from edge_agent.robot import ROBOTS, Observation, Robot, action_bounds, clip_action
from user.registry import PluginParams
from user.v1 import robot_pb2, tensor_pb2

if importlib.util.find_spec("lerobot") is None:
    raise ImportError("the lerobot robot adapter needs the lerobot package")

KIND = "lerobot"
POSITION_SUFFIXES = (".pos", ".q")  # lerobot's position goals (.q: unitree G1 joints)
VELOCITY_SUFFIXES = (".vel",)  # lerobot's velocity goals (LeKiwi's base)
TORQUE_FIELD = "disable_torque_on_disconnect"


def _config_class(type_name: str) -> type:
    """lerobot's config class of a robot type; ValueError naming the known types when there is none."""
    from lerobot.robots import RobotConfig

    from edge_agent.lerobot_devices import _import_device_packages

    try:
        return RobotConfig.get_choice_class(type_name)
    except KeyError:
        _import_device_packages("lerobot.robots")  # devices register on import
    try:
        return RobotConfig.get_choice_class(type_name)
    except KeyError:
        raise ValueError(
            f"unknown lerobot type {type_name!r}; known: {sorted(RobotConfig.get_known_choices())}"
        ) from None


@ROBOTS.register(KIND)
class LerobotRobot(Robot):
    """Any lerobot Robot (type + config) mapped to a RobotSpec; holds positions where they are and velocities at 0."""

    class Params(PluginParams):
        type: str = Field(min_length=1, description="lerobot robot type, e.g. so101_follower")
        config: dict[str, Any] = Field(default={}, description="the lerobot robot config (port, cameras, ...)")
        control_rate_hz: float = Field(default=30.0, gt=0)
        max_episode_steps: int = Field(default=300, ge=0, description="0: episodes end only by the task")
        action_low: float | list[float] = Field(
            default=-100.0,
            description="per action or one for all; the default +-100 (lerobot's normalised joint range) only "
            "applies to positions: velocity actions (.vel, hold_zero_keys) need explicit limits",
        )
        action_high: float | list[float] = 100.0
        hold_zero_keys: list[str] = Field(
            default=[], description="actions hold() sends as 0 (velocities, stick axes) besides those ending .vel"
        )
        hold_position_keys: list[str] = Field(
            default=[],
            description="actions hold() repeats the last observed value of (positions) besides those ending .pos/.q",
        )
        disable_torque_on_disconnect: bool = Field(
            default=False,
            description="false: motors keep torque when the edge stops or restarts, so an arm holds its pose; true: "
            "lerobot's default, the arm goes limp and falls (set on the lerobot config when it has the field)",
        )
        calibrate: bool = Field(default=False, description="calibrate on connect if the robot needs it")
        task: str = Field(default="", description="what the robot should do, in words")

        @field_validator("type")
        @classmethod
        def _known_type(cls, value: str) -> str:
            _config_class(value)
            return value

        @field_validator("config")
        @classmethod
        def _decodes(cls, value: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
            """Decoded as lerobot will decode it when building, so a bad key fails here naming this field."""
            type_name = info.data.get("type")
            if type_name is None:  # the type itself was refused: that error says enough
                return value
            import draccus

            try:
                draccus.decode(_config_class(type_name), dict(value))
            except Exception as exc:  # draccus errors are not ValueErrors; some span lines
                raise ValueError(" ".join(str(exc).split())) from None
            return value

        @model_validator(mode="after")
        def _ordered(self) -> LerobotRobot.Params:
            lows = np.atleast_1d(self.action_low)
            highs = np.atleast_1d(self.action_high)
            if lows.size > 1 and highs.size > 1 and lows.size != highs.size:
                raise ValueError("action_low and action_high must have the same length")
            if np.any(lows > highs):
                raise ValueError("action_low must be <= action_high")
            if both := set(self.hold_zero_keys) & set(self.hold_position_keys):
                raise ValueError(f"hold_zero_keys and hold_position_keys both name {sorted(both)}")
            return self

        @model_validator(mode="after")
        def _one_torque_setting(self) -> LerobotRobot.Params:
            """The torque on disconnect has one place (this param): a config value that disagrees is refused, and so
            is the param set for a type without the setting (it would do nothing)."""
            if "disable_torque_on_disconnect" in self.model_fields_set and not _torque_fields(_config_class(self.type)):
                raise ValueError(f"disable_torque_on_disconnect: lerobot type {self.type!r} has no such setting")
            for where, value in _torque_settings(self.config):
                if bool(value) != self.disable_torque_on_disconnect:
                    raise ValueError(
                        f"config.{where} is {value} but disable_torque_on_disconnect is "
                        f"{self.disable_torque_on_disconnect}: set params.disable_torque_on_disconnect only"
                    )
            return self

    default_task = "human_label"

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        from edge_agent.lerobot_devices import make_lerobot_robot

        self.robot_id, self.params = robot_id, params
        self.device = make_lerobot_robot(params.type, _with_torque_setting(params))
        obs_features: dict[str, Any] = dict(self.device.observation_features)
        self.state_keys = [k for k, v in obs_features.items() if v is float]
        self.camera_keys = [k for k, v in obs_features.items() if isinstance(v, tuple) and len(v) == 3]
        self.action_keys = [k for k, v in dict(self.device.action_features).items() if v is float]
        if not self.action_keys:
            raise ValueError(f"lerobot robot {params.type!r} declares no float action features")
        self.zero_keys = self._classify_hold()
        self._camera_shapes = {k: tuple(int(d) for d in obs_features[k]) for k in self.camera_keys}
        self._spec = self._build_spec()
        self._last_obs: dict[str, Any] | None = None
        self._commanded: dict[str, float] = {}  # last value sent per action (none yet: nothing is known)

    def _classify_hold(self) -> frozenset[str]:
        """The actions hold() sends as 0; every other action is a position. Unclassifiable names are refused."""
        p = self.params
        for field_name, keys in (("hold_zero_keys", p.hold_zero_keys), ("hold_position_keys", p.hold_position_keys)):
            if unknown := [k for k in keys if k not in self.action_keys]:
                raise ValueError(f"{field_name}: {unknown} are not actions of {p.type!r} ({self.action_keys})")
        zero = {k for k in self.action_keys if k.endswith(VELOCITY_SUFFIXES)} - set(p.hold_position_keys)
        zero |= set(p.hold_zero_keys)
        position = {k for k in self.action_keys if k.endswith(POSITION_SUFFIXES)} - zero
        position |= set(p.hold_position_keys)
        if unclassified := [k for k in self.action_keys if k not in zero | position]:
            raise ValueError(
                f"hold_zero_keys/hold_position_keys: hold() cannot tell how to keep {unclassified} still (not a "
                f"position {'/'.join(POSITION_SUFFIXES)} nor a velocity {'/'.join(VELOCITY_SUFFIXES)}): list each in "
                "hold_zero_keys (sent as 0) or hold_position_keys (its observed value repeated)"
            )
        explicit = {"action_low", "action_high"} <= p.model_fields_set
        if zero and not explicit:
            raise ValueError(
                f"action_low/action_high: set them for the velocity actions {sorted(zero)}: the default +-100 is "
                "lerobot's normalised range of position joints, not a speed"
            )
        return frozenset(zero)

    def _bounds(self) -> tuple[list[float], list[float]]:
        n = len(self.action_keys)
        low, high = np.atleast_1d(self.params.action_low), np.atleast_1d(self.params.action_high)
        if low.size not in (1, n) or high.size not in (1, n):
            raise ValueError(f"action_low/action_high need 1 or {n} values ({self.action_keys})")
        return [float(x) for x in np.broadcast_to(low, n)], [float(x) for x in np.broadcast_to(high, n)]

    def _build_spec(self) -> robot_pb2.RobotSpec:
        low, high = self._bounds()
        if outside := [
            k
            for k, lo, hi in zip(self.action_keys, low, high, strict=True)
            if k in self.zero_keys and not lo <= 0 <= hi
        ]:
            raise ValueError(f"action_low/action_high: hold() sends 0 to {outside}, outside their limits")
        observation = [
            robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[len(self.state_keys)])
        ]
        cameras = []
        for key in self.camera_keys:
            h, w, c = self._camera_shapes[key]
            name = f"camera.{key}"
            observation.append(
                robot_pb2.FeatureSpec(name=name, dtype=tensor_pb2.DTYPE_UINT8, shape=[h, w, c], is_image=True)
            )
            cameras.append(robot_pb2.CameraSpec(name=key, width=w, height=h, fps=self.params.control_rate_hz))
        return robot_pb2.RobotSpec(
            robot_id=self.robot_id,
            kind=f"{KIND}:{self.params.type}",  # robots of one lerobot type share a learner (learner.robot_kind)
            action=robot_pb2.ActionSpace(
                shape=[len(self.action_keys)],
                low=low,
                high=high,
                names=self.action_keys,
                dtype=tensor_pb2.DTYPE_FLOAT32,
            ),
            observation=observation,
            cameras=cameras,
            control_rate_hz=self.params.control_rate_hz,
            max_episode_steps=self.params.max_episode_steps,
            task=self.params.task,
            labels={"lerobot_type": self.params.type, "state_names": ",".join(self.state_keys)},
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    # --- lifecycle ---------------------------------------------------------------------------------

    def connect(self) -> None:
        if not self.device.is_connected:
            self.device.connect(calibrate=self.params.calibrate)

    def disconnect(self) -> None:
        if self.device.is_connected:
            self.device.disconnect()

    def close(self) -> None:
        self.disconnect()

    # --- observe and act ---------------------------------------------------------------------------

    def observe(self) -> Observation:
        raw = self.device.get_observation()
        self._last_obs = raw
        features: dict[str, np.ndarray] = {
            "state": np.asarray([float(raw[k]) for k in self.state_keys], dtype=np.float32)
        }
        for key in self.camera_keys:
            features[f"camera.{key}"] = np.ascontiguousarray(raw[key], dtype=np.uint8).reshape(self._camera_shapes[key])
        return Observation(features=features)

    def reset(self, seed: int | None = None) -> Observation:
        """A real scene is reset by a person or a routine; a new episode starts from where the robot is."""
        return self.observe()

    def _send(self, command: dict[str, float]) -> dict[str, float]:
        """Send `command` (a value per action name, maybe not all); the values the device reports it sent."""
        sent = self.device.send_action(command)
        applied = {k: float(sent.get(k, v)) for k, v in command.items()}
        self._commanded.update(applied)
        return applied

    def act(self, action: np.ndarray) -> np.ndarray:
        clipped = clip_action(self._spec, action)
        applied = self._send({k: float(v) for k, v in zip(self.action_keys, clipped, strict=True)})
        return np.asarray([applied[k] for k in self.action_keys], np.float32)

    def hold(self) -> np.ndarray | None:
        """Velocities to 0; positions to where they were last seen, else to their last command (a reading that is
        not finite counts as none: a glitching encoder must not become a jump); a position neither seen nor
        commanded is left out (no reading is tried here: it blocks on the cameras, and a hold often follows a
        failed read). Returns the action vector sent, or None when some action (or all) was not sent."""
        low, high = action_bounds(self._spec)
        command: dict[str, float] = {}
        for i, key in enumerate(self.action_keys):
            value = self._hold_value(key)
            if value is not None:
                command[key] = float(np.clip(value, low[i], high[i]))
        if not command:
            return None
        applied = self._send(command)
        if len(applied) < len(self.action_keys):
            return None
        return np.asarray([applied[k] for k in self.action_keys], np.float32)

    def _hold_value(self, key: str) -> float | None:
        if key in self.zero_keys:
            return 0.0
        seen = (self._last_obs or {}).get(key)
        if seen is not None and np.isfinite(float(seen)):
            return float(seen)
        return self._commanded.get(key)


def _torque_fields(config_cls: type) -> list[str]:
    """Where a lerobot config class keeps disable_torque_on_disconnect: itself and/or its per-arm sub-configs."""
    if not dataclasses.is_dataclass(config_cls):
        return []
    try:
        hints = typing.get_type_hints(config_cls)
    except Exception:  # an annotation that does not resolve: look at the fields as declared
        hints = {f.name: f.type for f in dataclasses.fields(config_cls)}
    found = []
    for f in dataclasses.fields(config_cls):
        kind = hints.get(f.name)
        if f.name == TORQUE_FIELD:
            found.append(f.name)
        elif isinstance(kind, type) and dataclasses.is_dataclass(kind) and TORQUE_FIELD in _field_names(kind):
            found.append(f"{f.name}.{TORQUE_FIELD}")
    return found


def _field_names(config_cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(config_cls)}  # type: ignore[arg-type]


def _torque_settings(config: dict[str, Any]) -> list[tuple[str, object]]:
    """The disable_torque_on_disconnect values a raw config sets itself (dotted path, value)."""
    found: list[tuple[str, object]] = []
    if TORQUE_FIELD in config:
        found.append((TORQUE_FIELD, config[TORQUE_FIELD]))
    for name, sub in config.items():
        if isinstance(sub, dict) and TORQUE_FIELD in sub:
            found.append((f"{name}.{TORQUE_FIELD}", sub[TORQUE_FIELD]))
    return found


def _with_torque_setting(params: LerobotRobot.Params) -> dict[str, Any]:
    """The lerobot config with params.disable_torque_on_disconnect wherever its class has that field."""
    config = dict(params.config)
    for path in _torque_fields(_config_class(params.type)):
        head, _, leaf = path.partition(".")
        if leaf:
            config[head] = {**dict(config.get(head) or {}), leaf: params.disable_torque_on_disconnect}
        else:
            config[head] = params.disable_torque_on_disconnect
    return config
