"""A task or teleoperator entry that cannot work with its robot fails `userctl edge` at start in one line naming the
dotted field (exit 2), and a teleoperator whose polls always fail logs its traceback once, not every reconnect."""

from __future__ import annotations

import logging
import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from edge_agent import agent as agent_module
from edge_agent.agent import TELEOP_DETACHES, EdgeAgent, build_judges_and_teleops
from edge_agent.policy_source import PolicySource
from edge_agent.robot import Observation, Robot, make_robot
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from tests.helpers import free_port, wait_for
from user import cli
from user.config import AuthConfig, PluginConfig, RobotConfig, StackConfig
from user.registry import PluginError
from user.reward_model import ClassifierConfig, SuccessClassifier, save_classifier


@TELEOPERATORS.register("test_stuck_expert", description="test: every poll fails with the same KeyError")
class StuckExpert(Teleoperator):
    """Declares nothing, so it is accepted at start; its polls read an info key the robot never has."""

    def poll(self, observation: Observation) -> np.ndarray | None:
        return np.asarray(observation.info["goal_pos"], np.float32)


class ZeroPolicy(PolicySource):
    def act(self, robot_id: str, features: dict[str, np.ndarray], deadline_s: float) -> tuple[np.ndarray, int]:
        return np.zeros(3, np.float32), 1

    @property
    def version(self) -> int:
        return 1


@pytest.fixture
def sim_arm() -> Iterator[Robot]:
    robot = make_robot("sim_reach_arm", "a", {"max_episode_steps": 20})
    yield robot
    robot.close()


def camera_model(path: Path) -> str:
    """A (untrained) success classifier for 64x64 `camera.front` frames, as `userctl reward train` writes one."""
    save_classifier(SuccessClassifier(ClassifierConfig(camera="camera.front", image_shape=[64, 64, 3])), path)
    return str(path)


def userctl_edge(robots: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """`userctl edge` in this process with edge.robots set: exit code and its stderr lines that are not log records."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    on_signal = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:  # `userctl edge` sets up its logging and signal handlers in this process: put pytest's back after it
        code = cli.main(["edge", "--set", f"edge.robots={robots}", "--set", "auth.token=t"])
    finally:
        root.handlers[:], root.level = handlers, level
        for sig, handler in on_signal.items():
            signal.signal(sig, handler)
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, [line for line in err.splitlines() if not line.startswith("{")]


def build(entry: RobotConfig, robot: Robot) -> None:
    cfg = StackConfig()
    cfg.edge.robots = [entry]
    build_judges_and_teleops(cfg, [robot])


# --------------------------------------------------------------------------- classifier task


def test_userctl_edge_names_a_classifier_model_that_is_not_there(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    robots = f"[{{id: a, kind: sim_reach_arm, task: {{kind: classifier, params: {{model: {tmp_path}/nope}}}}}}]"
    assert userctl_edge(robots, capsys) == (
        2,
        [
            f"userctl edge: edge.robots[0].task.params.model: {tmp_path}/nope needs model.safetensors and "
            "config.json (written by `userctl reward train`)"
        ],
    )


def test_userctl_edge_names_a_classifier_for_a_camera_the_robot_lacks(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    model = camera_model(tmp_path / "model")
    robots = f"[{{id: a, kind: sim_reach_arm, task: {{kind: classifier, params: {{model: {model}}}}}}}]"
    assert userctl_edge(robots, capsys) == (
        2,
        [
            "userctl edge: edge.robots[0].task.params.model: robot 'a' has no observation 'camera.front'; "
            "the classifier needs it"
        ],
    )


@pytest.mark.parametrize(
    ("damage", "said"),
    [
        ("weights", "edge.robots[0].task.params.model: "),  # model.safetensors that is not safetensors
        ("config", "edge.robots[0].task.params.model: "),  # config.json that is not a classifier's
        ("device", "edge.robots[0].task.params.device: device 'cuda:7' requested"),
    ],
)
def test_a_broken_classifier_model_is_one_line_naming_the_param(
    sim_arm: Robot, tmp_path: Path, damage: str, said: str
) -> None:
    model = camera_model(tmp_path / "model")
    params = {"model": model}
    if damage == "weights":
        (tmp_path / "model" / "model.safetensors").write_bytes(b"not a tensor file")
    elif damage == "config":
        (tmp_path / "model" / "config.json").write_text('{"camera": 3}')
    else:
        params["device"] = "cuda:7"
    entry = RobotConfig(id="a", kind="sim_reach_arm", task=PluginConfig(kind="classifier", params=params))
    with pytest.raises(PluginError) as err:
        build(entry, sim_arm)
    assert str(err.value).startswith(said) and "\n" not in str(err.value), str(err.value)


# --------------------------------------------------------------------------- teleoperators and their robots


def test_userctl_edge_refuses_an_expert_for_another_robot_kind(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    code, lines = userctl_edge("[{id: a, kind: sim_reach_arm, teleop: {kind: lang_reach_expert}}]", capsys)
    assert (code, lines) == (
        2,
        [
            "userctl edge: edge.robots[0].teleop.kind: lang_reach_expert cannot drive robot 'a' (kind sim_reach_arm): "
            "it needs robot kind lang_reach_arm, observation state, info goal_pos"
        ],
    )


def test_scripted_expert_without_an_expert_for_the_robot_is_refused_naming_the_kind_field() -> None:
    robot = make_robot("lang_reach_arm", "a", {"camera": False})
    try:
        with pytest.raises(PluginError) as err:
            build(RobotConfig(id="a", kind="lang_reach_arm", teleop=PluginConfig(kind="scripted_expert")), robot)
    finally:
        robot.close()
    assert str(err.value).startswith(
        "edge.robots[0].teleop.kind: scripted_expert cannot drive robot 'a' (kind lang_reach_arm): "
        "no expert for robot kind 'lang_reach_arm'"
    ), str(err.value)


def test_an_expert_is_accepted_by_its_robot_and_refused_when_built_for_another(sim_arm: Robot) -> None:
    lang = make_robot("lang_reach_arm", "b", {"camera": False})
    try:
        entry = RobotConfig(id="b", kind="lang_reach_arm", teleop=PluginConfig(kind="lang_reach_expert"))
        cfg = StackConfig()
        cfg.edge.robots = [entry]
        _, teleops = build_judges_and_teleops(cfg, [lang])
        obs = lang.reset()
        teleops["b"].reset(obs)
        assert teleops["b"].poll(obs) is None  # intervene mode: fine so far, it watches (it can read its robot)
        # Built directly (a bench, a test) for a robot it cannot read, it refuses at once instead of at every poll.
        with pytest.raises(ValueError, match=r"cannot drive robot 'a' .*robot kind lang_reach_arm"):
            TELEOPERATORS.build("lang_reach_expert", {"mode": "always"}, spec=sim_arm.spec)
    finally:
        lang.close()


def test_a_teleoperator_needing_an_observation_the_robot_lacks_says_which(sim_arm: Robot) -> None:
    class FrontCameraHuman(StuckExpert):
        observation_keys = ("state", "camera.front")

    why = FrontCameraHuman.unsupported(sim_arm.spec)
    assert why == "it needs observation state, camera.front; the robot has no observation camera.front"
    with pytest.raises(ValueError, match=r"the robot has no observation camera\.front"):
        FrontCameraHuman(FrontCameraHuman.Params(), sim_arm.spec)


# --------------------------------------------------------------------------- a teleoperator that always fails


def test_a_teleoperator_that_always_fails_logs_its_traceback_once_then_a_line_per_detach(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(agent_module, "TELEOP_DETACH_S", 0.05)  # detach cycles come quickly
    cfg = StackConfig(auth=AuthConfig(token="t"))
    cfg.edge.mode, cfg.edge.replug_s, cfg.edge.spool_dir, cfg.edge.rpc_timeout_s = "fast", 0.05, None, 0.1
    cfg.edge.control_addr = cfg.edge.replay_addr = f"127.0.0.1:{free_port()}"  # nothing there: robots act anyway
    cfg.edge.robots = [
        RobotConfig(
            id="stuck-arm",
            kind="sim_reach_arm",
            params={"max_episode_steps": 20},
            teleop=PluginConfig(kind="test_stuck_expert"),
        )
    ]
    detaches = TELEOP_DETACHES.labels("stuck-arm")._value.get()
    caplog.set_level(logging.DEBUG, logger="edge_agent.agent")
    agent = EdgeAgent(cfg, policy=ZeroPolicy())
    agent.start()
    try:
        wait_for(lambda: TELEOP_DETACHES.labels("stuck-arm")._value.get() >= detaches + 3, "three detach cycles")
    finally:
        agent.stop(flush_timeout_s=0.1)
    records = [r for r in caplog.records if r.name == "edge_agent.agent"]
    tracebacks = [r for r in records if r.exc_info is not None]
    assert [r.getMessage() for r in tracebacks] == ["teleoperator poll failed; the policy drives"]
    detached = [r for r in records if r.getMessage().startswith("teleoperator detached")]
    assert len(detached) >= 3
    assert all(r.fields["error"] == "KeyError: 'goal_pos'" for r in detached)  # type: ignore[attr-defined]
    again = [r for r in records if r.getMessage() == "teleoperator poll failed again"]
    assert len(again) >= 2 and all(r.levelno == logging.DEBUG for r in again)
