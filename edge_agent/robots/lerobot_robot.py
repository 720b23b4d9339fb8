"""Any lerobot robot (SO-100/101 follower, Koch, OMX, LeKiwi, ...) behind the Robot interface.

    robots: [{id: so101, kind: lerobot, params: {type: so101_follower, config: {port: /dev/ttyACM0}}}]

lerobot describes a robot by dicts: observation_features maps a name to `float` (a joint position,
a velocity) or to an image shape (h, w, 3); action_features maps a name to `float`. Here the float
observations, in the robot's declared order, become one float32 "state" vector, each camera a uint8
"camera.<name>" image, and the float actions the action vector (names in the spec, limits from params:
lerobot declares none). `connect`/`disconnect` open and release the bus and cameras; `hold` sends the
last observed position of every commanded joint, so the arm stays where it is. A real robot has no
simulator judging it: its default task is `human_label` (a key marks success).

lerobot (and torch, which it imports) loads on first build, so discovering robot kinds stays fast.
The type and config are checked with the params (an unknown type or a config lerobot cannot decode names
`...params.type` / `...params.config`); a driver package the device needs is only found missing when it is
built (an ImportError, which the edge agent reports as one line naming the robot).
"""

from __future__ import annotations

import importlib.util
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from edge_agent.robot import ROBOTS, Observation, Robot, clip_action
from user.registry import PluginParams
from user.v1 import robot_pb2, tensor_pb2

if importlib.util.find_spec("lerobot") is None:
    raise ImportError("the lerobot robot adapter needs the lerobot package")

KIND = "lerobot"


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
    """Any lerobot Robot (type + config) mapped to a RobotSpec; holds by repeating the last position."""

    class Params(PluginParams):
        type: str = Field(min_length=1, description="lerobot robot type, e.g. so101_follower")
        config: dict[str, Any] = Field(default={}, description="the lerobot robot config (port, cameras, ...)")
        control_rate_hz: float = Field(default=30.0, gt=0)
        max_episode_steps: int = Field(default=300, ge=0, description="0: episodes end only by the task")
        action_low: float | list[float] = Field(default=-100.0, description="per action or one for all")
        action_high: float | list[float] = 100.0
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
            return self

    default_task = "human_label"

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        from edge_agent.lerobot_devices import make_lerobot_robot

        self.robot_id, self.params = robot_id, params
        self.device = make_lerobot_robot(params.type, params.config)
        obs_features: dict[str, Any] = dict(self.device.observation_features)
        self.state_keys = [k for k, v in obs_features.items() if v is float]
        self.camera_keys = [k for k, v in obs_features.items() if isinstance(v, tuple) and len(v) == 3]
        self.action_keys = [k for k, v in dict(self.device.action_features).items() if v is float]
        if not self.action_keys:
            raise ValueError(f"lerobot robot {params.type!r} declares no float action features")
        self._camera_shapes = {k: tuple(int(d) for d in obs_features[k]) for k in self.camera_keys}
        self._spec = self._build_spec()
        self._last_obs: dict[str, Any] | None = None
        self._last_action = np.zeros(len(self.action_keys), np.float32)

    def _bounds(self) -> tuple[list[float], list[float]]:
        n = len(self.action_keys)
        low, high = np.atleast_1d(self.params.action_low), np.atleast_1d(self.params.action_high)
        if low.size not in (1, n) or high.size not in (1, n):
            raise ValueError(f"action_low/action_high need 1 or {n} values ({self.action_keys})")
        return [float(x) for x in np.broadcast_to(low, n)], [float(x) for x in np.broadcast_to(high, n)]

    def _build_spec(self) -> robot_pb2.RobotSpec:
        low, high = self._bounds()
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

    def _send(self, action: np.ndarray) -> np.ndarray:
        sent = self.device.send_action({k: float(v) for k, v in zip(self.action_keys, action, strict=True)})
        applied = np.asarray([float(sent.get(k, a)) for k, a in zip(self.action_keys, action, strict=True)], np.float32)
        self._last_action = applied
        return applied

    def act(self, action: np.ndarray) -> np.ndarray:
        return self._send(clip_action(self._spec, action))

    def hold(self) -> None:
        """Command every joint to where it was last seen (or to the last command if it is not observed, or its
        reading is not finite: a glitching encoder must not become a jump)."""
        seen = self._last_obs or {}
        position = np.asarray(
            [_finite_or(seen.get(k, last), last) for k, last in zip(self.action_keys, self._last_action, strict=True)],
            np.float32,
        )
        self._send(clip_action(self._spec, position))


def _finite_or(value: object, fallback: float) -> float:
    """float(value) when finite, else `fallback` (itself a finite command this robot was sent)."""
    x = float(value)  # type: ignore[arg-type]
    return x if np.isfinite(x) else float(fallback)
