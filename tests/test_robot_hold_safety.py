"""What holding, stopping and teleoperating do to a physical robot: lerobot's own device ABCs subclassed without
hardware (registered through lerobot's config choice registries), and the simulated robots' hold contract."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from lerobot.robots import Robot as LeRobot
from lerobot.robots import RobotConfig as LeRobotConfig
from lerobot.teleoperators import Teleoperator as LeTeleoperator
from lerobot.teleoperators import TeleoperatorConfig as LeTeleoperatorConfig
from lerobot.teleoperators import TeleopEvents

from edge_agent.robot import make_robot
from edge_agent.task import ParamError
from edge_agent.teleop import TELEOPERATORS
from tests.helpers import NoHardware
from user.config import ConfigError, load_config
from user.registry import PluginError

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"

# --------------------------------------------------------------------------- hardware-free lerobot devices


@LeRobotConfig.register_subclass("user_test_hold_device")
@dataclass(kw_only=True)
class HoldDeviceConfig(LeRobotConfig):
    """`positions` are goal-position actions (name.pos), `velocities` velocity actions (x.vel), `others` actions
    named neither way (EarthRover's linear_velocity); all are observed as they were last commanded."""

    positions: list[str] = field(default_factory=lambda: ["shoulder_pan", "elbow_flex", "gripper"])
    velocities: list[str] = field(default_factory=list)
    others: list[str] = field(default_factory=list)
    start: float = 40.0
    fail_first_reads: int = 0


class HoldDevice(NoHardware, LeRobot):
    """Joints jump to their goal positions, velocities are measured as commanded; the first `fail_first_reads`
    observations raise as a Feetech bus read glitch does."""

    config_class = HoldDeviceConfig
    name = "user_test_hold_device"

    def __init__(self, config: HoldDeviceConfig) -> None:
        super().__init__(config)
        self.config = config
        keys = [f"{j}.pos" for j in config.positions] + [f"{v}.vel" for v in config.velocities] + config.others
        self.state = {k: (config.start if k.endswith(".pos") else 0.0) for k in keys}
        self.sent: list[dict[str, float]] = []
        self.reads = 0
        self._connected = False

    @property
    def observation_features(self) -> dict:
        return dict.fromkeys(self.state, float)

    @property
    def action_features(self) -> dict:
        return dict.fromkeys(self.state, float)

    def get_observation(self) -> dict[str, Any]:
        self.reads += 1
        if self.reads <= self.config.fail_first_reads:
            raise ConnectionError("Failed to sync read 'Present_Position' on ids=[1, 2, 3]")
        return dict(self.state)

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        self.sent.append(dict(action))
        self.state.update({k: float(v) for k, v in action.items()})
        return action


@dataclass
class ArmBusConfig:
    """One arm of a bimanual follower (as lerobot's SOFollowerConfig): torque off on disconnect by default."""

    disable_torque_on_disconnect: bool = True


@LeRobotConfig.register_subclass("user_test_hold_torque_arm")
@dataclass(kw_only=True)
class TorqueArmConfig(HoldDeviceConfig):
    disable_torque_on_disconnect: bool = True  # lerobot's SO-100/101 and Koch default


@LeRobotConfig.register_subclass("user_test_hold_bi_arm")
@dataclass(kw_only=True)
class BiArmConfig(HoldDeviceConfig):
    left_arm_config: ArmBusConfig = field(default_factory=ArmBusConfig)
    right_arm_config: ArmBusConfig = field(default_factory=ArmBusConfig)


class TorqueArm(HoldDevice):
    """Records whether its disconnect turned the motors' torque off (the arm would fall)."""

    config_class = TorqueArmConfig
    name = "user_test_hold_torque_arm"

    def __init__(self, config: HoldDeviceConfig) -> None:
        super().__init__(config)
        self.torque_off: bool | None = None

    def disconnect(self) -> None:
        self.torque_off = bool(self.config.disable_torque_on_disconnect)  # type: ignore[attr-defined]
        super().disconnect()


class BiArm(HoldDevice):
    config_class = BiArmConfig
    name = "user_test_hold_bi_arm"


@LeTeleoperatorConfig.register_subclass("user_test_hold_pad")
@dataclass(kw_only=True)
class HoldPadConfig(LeTeleoperatorConfig):
    pass


class HoldPad(NoHardware, LeTeleoperator):
    """An end-effector pad (lerobot's gamepad / keyboard_ee keys) whose intervention button is held."""

    config_class = HoldPadConfig
    name = "user_test_hold_pad"

    def __init__(self, config: HoldPadConfig) -> None:
        super().__init__(config)
        self._connected = False

    @property
    def action_features(self) -> dict:
        return {"dtype": "float32", "shape": (4,), "names": {"delta_x": 0, "delta_y": 1, "delta_z": 2, "gripper": 3}}

    @property
    def feedback_features(self) -> dict:
        return {}

    def get_action(self) -> dict[str, Any]:
        return {"delta_x": 0.5, "delta_y": -0.5, "delta_z": 0.0, "gripper": 1.0}

    def get_teleop_events(self) -> dict[Any, Any]:
        return {TeleopEvents.IS_INTERVENTION: True}

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        pass


def lerobot_robot(tmp_path: Path, config: dict[str, Any] | None = None, **params: Any) -> Any:
    entry = {"type": "user_test_hold_device", "config": {"calibration_dir": str(tmp_path), **(config or {})}}
    robot = make_robot("lerobot", "real-0", {**entry, **params})
    robot.connect()
    return robot


# --------------------------------------------------------------------------- 1. velocity actions hold at 0


def test_hold_stops_velocity_actions_and_keeps_positions_where_they_are(tmp_path: Path) -> None:
    """A LeKiwi-like robot (an arm's .pos goals and a base's .vel goals, both observed) driving at 0.3 m/s: hold
    sends the base 0, not its measured 0.3 (which kept it driving), and the arm where it was last seen."""
    robot = lerobot_robot(
        tmp_path,
        {"positions": ["shoulder_pan"], "velocities": ["x", "theta"]},
        action_low=[-100, -0.5, -90],
        action_high=[100, 0.5, 90],
    )
    device = robot.device
    robot.act(np.array([25.0, 0.3, 10.0]))
    np.testing.assert_allclose(robot.observe().features["state"], [25.0, 0.3, 10.0])  # measured: still moving
    held = robot.hold()
    assert device.sent[-1] == {"shoulder_pan.pos": 25.0, "x.vel": 0.0, "theta.vel": 0.0}
    np.testing.assert_array_equal(held, [25.0, 0.0, 0.0])


def test_hold_refuses_actions_it_cannot_classify_until_params_say(tmp_path: Path) -> None:
    """An action named neither .pos nor .vel (EarthRover's linear_velocity) has no known way to be held still:
    refused at build naming the params, then held at 0 once hold_zero_keys lists it."""
    rover = {"positions": [], "others": ["linear_velocity"]}
    with pytest.raises(ValueError, match=r"hold_zero_keys/hold_position_keys: .*'linear_velocity'"):
        lerobot_robot(tmp_path, rover, action_low=-1, action_high=1)
    with pytest.raises(ValueError, match=r"hold_zero_keys: \['nope'\] are not actions"):
        lerobot_robot(tmp_path, rover, action_low=-1, action_high=1, hold_zero_keys=["nope"])
    robot = lerobot_robot(tmp_path, rover, action_low=-1, action_high=1, hold_zero_keys=["linear_velocity"])
    robot.act(np.array([0.8]))
    robot.observe()
    np.testing.assert_array_equal(robot.hold(), [0.0])
    assert robot.device.sent[-1] == {"linear_velocity": 0.0}


# --------------------------------------------------------------------------- 2. no position known: none sent


def test_hold_before_any_observation_sends_no_position(tmp_path: Path) -> None:
    """The arm rests at 40 and its first read fails (a bus glitch): a hold then has no position to send and sends
    none (it sent 0: every joint jumped to mid-range). A velocity action still gets its 0."""
    arm = lerobot_robot(tmp_path, {"fail_first_reads": 1})
    with pytest.raises(ConnectionError):
        arm.observe()
    assert arm.hold() is None
    assert arm.device.sent == [] and set(arm.device.state.values()) == {40.0}

    base = lerobot_robot(
        tmp_path, {"positions": ["shoulder_pan"], "velocities": ["x"]}, action_low=[-100, -1], action_high=[100, 1]
    )
    assert base.hold() is None  # not every action was sent: no vector to record
    assert base.device.sent == [{"x.vel": 0.0}]

    base.act(np.array([12.0, 0.0]))  # once commanded, an unobserved position holds at its last command
    np.testing.assert_array_equal(base.hold(), [12.0, 0.0])


# --------------------------------------------------------------------------- 3. a teleop must drive every action


def test_lerobot_teleop_pairing_that_leaves_joints_unmapped_is_refused_at_start(tmp_path: Path) -> None:
    """An end-effector pad (delta_x/y/z, gripper) cannot drive a position arm's joints: refused at start naming
    the param (it was accepted and each intervention sent every joint to 0)."""
    from edge_agent.agent import build_judges_and_teleops

    arm = {"type": "user_test_hold_device", "config": {"calibration_dir": str(tmp_path)}}
    pad = {"type": "user_test_hold_pad", "config": {"calibration_dir": str(tmp_path)}}
    teleop = {"kind": "lerobot", "params": pad}
    entry = {"id": "real-0", "kind": "lerobot", "params": arm, "task": {"kind": "env"}, "teleop": teleop}
    cfg = load_config(CONFIG, [f"edge.robots=[{json.dumps(entry)}]"])
    robot = make_robot("lerobot", "real-0", arm)
    with pytest.raises(PluginError, match=r"^edge\.robots\[0\]\.teleop\.params\.action_map: .*'shoulder_pan\.pos'"):
        build_judges_and_teleops(cfg, [robot])

    # Mapped, or given a value, every action is driven; nothing unmapped is ever sent as 0.
    mapped = {**pad, "action_map": {"shoulder_pan.pos": "delta_x", "elbow_flex.pos": "delta_y"}}
    with pytest.raises(ParamError, match=r"gripper\.pos"):
        TELEOPERATORS.build("lerobot", mapped, spec=robot.spec)
    teleop = TELEOPERATORS.build("lerobot", {**mapped, "defaults": {"gripper.pos": 40.0}}, spec=robot.spec)
    teleop.connect()
    from edge_agent.robot import Observation

    np.testing.assert_array_equal(teleop.poll(Observation(features={})), [0.5, -0.5, 40.0])
    with pytest.raises(ParamError, match=r"no keys \['nope'\]") as info:
        TELEOPERATORS.build("lerobot", {**pad, "action_map": {"gripper.pos": "nope"}}, spec=robot.spec)
    assert info.value.field == "action_map"


# --------------------------------------------------------------------------- 4. hold says what it applied


@pytest.mark.parametrize(
    ("kind", "params"),
    [("sim_reach_arm", {}), ("lang_reach_arm", {"camera": False}), ("gym_hil_panda", {}), ("so101", {})],
)
def test_simulated_robots_hold_returns_the_action_it_amounts_to(kind: str, params: dict[str, Any]) -> None:
    """A held step is recorded with what hold applied: the zero delta/velocity, and SO-101's grasp target kept."""
    robot = make_robot(kind, f"{kind}-0", params, seed=0)
    try:
        robot.reset(seed=0)
        shape = tuple(robot.spec.action.shape)
        action = np.zeros(shape, np.float32)
        if kind == "so101":
            action[3] = 0.25  # an absolute grasp target: holding keeps it, it is not "close" (0)
        robot.act(action)
        held = robot.hold()
        assert held is not None and held.dtype == np.float32 and held.shape == shape
        np.testing.assert_array_equal(held, action)
    finally:
        robot.close()


def test_lerobot_hold_returns_the_positions_it_sent_within_limits(tmp_path: Path) -> None:
    arm = lerobot_robot(tmp_path, {"start": 5.0}, action_low=[-100, -100, 10], action_high=[100, 100, 90])
    arm.observe()
    held = arm.hold()
    assert held is not None and held.dtype == np.float32 and held.shape == (3,)
    np.testing.assert_array_equal(held, [5.0, 5.0, 10.0])  # the gripper's reading clipped into its limits
    assert arm.device.sent[-1] == {"shoulder_pan.pos": 5.0, "elbow_flex.pos": 5.0, "gripper.pos": 10.0}
    arm.device.state["elbow_flex.pos"] = float("nan")  # a glitching encoder: its last command instead
    arm.observe()
    np.testing.assert_array_equal(arm.hold(), [5.0, 5.0, 10.0])


# --------------------------------------------------------------------------- 5. stopping keeps the torque on


def test_disconnect_keeps_torque_on_unless_asked(tmp_path: Path) -> None:
    """lerobot's followers turn torque off on disconnect by default, so an arm fell on every edge stop or restart;
    the adapter keeps it on (the arm holds its pose) unless disable_torque_on_disconnect says otherwise."""
    cal = {"calibration_dir": str(tmp_path)}
    arm = make_robot("lerobot", "real-0", {"type": "user_test_hold_torque_arm", "config": cal})
    arm.connect()
    arm.disconnect()
    assert arm.device.torque_off is False
    limp = make_robot(
        "lerobot", "real-0", {"type": "user_test_hold_torque_arm", "config": cal, "disable_torque_on_disconnect": True}
    )
    limp.connect()
    limp.disconnect()
    assert limp.device.torque_off is True
    bimanual = make_robot("lerobot", "real-0", {"type": "user_test_hold_bi_arm", "config": cal})
    assert bimanual.device.config.left_arm_config.disable_torque_on_disconnect is False
    assert bimanual.device.config.right_arm_config.disable_torque_on_disconnect is False
    with pytest.raises(PluginError, match=r"config\.disable_torque_on_disconnect is True"):
        make_robot(
            "lerobot",
            "real-0",
            {"type": "user_test_hold_torque_arm", "config": {**cal, "disable_torque_on_disconnect": True}},
        )
    with pytest.raises(PluginError, match=r"disable_torque_on_disconnect: lerobot type 'user_test_hold_device' has no"):
        make_robot(
            "lerobot", "real-0", {"type": "user_test_hold_device", "config": cal, "disable_torque_on_disconnect": True}
        )


# --------------------------------------------------------------------------- 6. fast mode is for simulators


def test_fast_mode_is_refused_for_a_hardware_robot() -> None:
    lerobot = json.dumps({"id": "real-0", "kind": "lerobot", "params": {"type": "so101_follower"}})
    with pytest.raises(ConfigError, match=r"edge\.mode: fast .*\['real-0'\]"):
        load_config(CONFIG, ["edge.mode=fast", f"edge.robots=[{lerobot}]"])
    assert load_config(CONFIG, ["edge.mode=fast"]).edge.mode == "fast"  # simulators may run unthrottled


# --------------------------------------------------------------------------- 7. velocity limits are explicit


def test_velocity_actions_need_explicit_limits(tmp_path: Path) -> None:
    """+-100 is lerobot's normalised range of position joints; as a base speed it is no limit at all."""
    base = {"positions": [], "velocities": ["x", "theta"]}
    with pytest.raises(ValueError, match=r"action_low/action_high: set them for the velocity actions"):
        lerobot_robot(tmp_path, base)
    with pytest.raises(ValueError, match=r"action_low/action_high: hold\(\) sends 0 to \['x\.vel'\]"):
        lerobot_robot(tmp_path, base, action_low=[0.1, -90], action_high=[0.5, 90])
    robot = lerobot_robot(tmp_path, base, action_low=[-0.5, -90], action_high=[0.5, 90])
    assert list(robot.spec.action.high) == [0.5, 90]
    arm = lerobot_robot(tmp_path)  # positions keep the normalised default
    assert list(arm.spec.action.low) == [-100] * 3 and list(arm.spec.action.high) == [100] * 3
