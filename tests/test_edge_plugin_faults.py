"""Robot and task plug-ins that break their contract: the edge finds out itself, on the step it happens.

A bad observation (float64 for float32, an undeclared key, a Python list), an action the robot reports that is not
the one it could have applied (unclipped, wrong shape, None), a task's NaN reward or exception: the robot holds, its
loop stops for good with one error naming the plug-in, its config entry and the field, and it is reported failed (the
edge's metrics, `userctl up`'s console and summary). A robot whose reset keeps raising stays on hot-plug's reconnect
path (its hardware may come back) but is reported failing. Other robots on the edge keep running. Real control,
replay and metrics HTTP; the plug-ins below are registered under kinds only this module uses.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import prometheus_client
import pytest

from edge_agent.agent import DETACHES, ROBOT_FAILED, ROBOT_FAILING, EdgeAgent, RobotLoop
from edge_agent.robot import ROBOTS, Observation, Robot, make_robot
from edge_agent.task import TASKS, Outcome, Task
from services.control.server import ControlService
from tests.helpers import wait_for
from tests.test_edge_agent import replay_stats, robot_info
from tests.test_edge_plugins import ConstantPolicy, ListSink, cloud
from user import rpc
from user.config import PluginConfig, RobotConfig, StackConfig, load_config
from user.registry import PluginError, PluginParams
from user.spec import validate_step
from user.up import (
    Child,
    Monitor,
    RobotFault,
    Snapshot,
    Stack,
    _in_entry,
    _print_summary,
    _robot_cells,
    _summary,
    exits_text,
)
from user.v1 import control_pb2, robot_pb2, tensor_pb2

__all__ = ["cloud"]  # a fixture

ROBOT_KIND, TASK_KIND = "fault_test_slider", "fault_test_goal"


@ROBOTS.register(ROBOT_KIND, description="test: a slider whose `bug` param breaks the robot contract")
class FaultySlider(Robot):
    """A point on a line (velocity action in [-1, 1]); `bug` picks the mistake; `cable` must exist to connect."""

    class Params(PluginParams):
        bug: str = "none"
        cable: str = ""
        max_episode_steps: int = 20

    default_task = TASK_KIND

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        self.params, self.x = params, 0.0
        self.calls: list[str] = []  # connect, reset, observe, act, hold: in order
        low, high = ([1.0], [-1.0]) if params.bug == "spec_low_above_high" else ([-1.0], [1.0])
        self._spec = robot_pb2.RobotSpec(
            robot_id=robot_id,
            kind=ROBOT_KIND,
            action=robot_pb2.ActionSpace(shape=[1], low=low, high=high, dtype=tensor_pb2.DTYPE_FLOAT32),
            observation=[robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[2])],
            control_rate_hz=100.0,
            max_episode_steps=params.max_episode_steps,
        )

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    def connect(self) -> None:
        if self.params.cable and not Path(self.params.cable).exists():
            raise OSError("not plugged in")
        self.calls.append("connect")
        if self.params.bug == "spec_bad_once_connected":  # limits read from the device: an impossible range
            del self._spec.action.low[:], self._spec.action.high[:]
            self._spec.action.low.append(1.0)
            self._spec.action.high.append(-1.0)

    def reset(self, seed: int | None = None) -> Observation:
        self.calls.append("reset")
        if self.params.bug == "reset_raises":
            raise RuntimeError("homing failed")
        self.x = 0.0
        return self._observation()

    def observe(self) -> Observation:
        self.calls.append("observe")
        return self._observation()

    def _observation(self) -> Observation:
        state = np.array([self.x, 0.0], np.float32)
        bug = self.params.bug
        if bug == "obs_float64":
            return Observation({"state": state.astype(np.float64)})
        if bug == "obs_extra_key":
            return Observation({"state": state, "debug": np.zeros(3, np.float32)})
        if bug == "obs_list":
            return Observation({"state": state.tolist()})  # type: ignore[dict-item]
        return Observation({"state": state}, info={"x": self.x})

    def act(self, action: np.ndarray) -> np.ndarray:
        self.calls.append("act")
        self.x += 0.01 * float(action[0])
        bug = self.params.bug
        if bug == "act_unclipped":
            return action * 10.0  # reports more than the limits allow
        if bug == "act_wrong_shape":
            return np.zeros(3, np.float32)
        if bug == "act_none":
            return None  # type: ignore[return-value]
        return action

    def hold(self) -> None:
        self.calls.append("hold")


@TASKS.register(TASK_KIND, description="test: minus the distance to 1; `bug` breaks the task contract")
class FaultyGoal(Task):
    class Params(PluginParams):
        bug: str = "none"

    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        bug = self.params.bug
        if bug == "raises":
            return {}["distance"]  # a reward-code bug: KeyError
        if bug == "returns_tuple":
            return (0.0, False, False)  # type: ignore[return-value]
        reward = {"nan": math.nan, "inf": math.inf}.get(bug, -abs(1.0 - next_observation.features["state"][0]))
        return Outcome(reward=float(reward))


def gauge(metric: prometheus_client.Gauge, rid: str) -> float:
    return metric.labels(rid)._value.get()


# --------------------------------------------------------------------------- one loop, each mistake


@pytest.mark.parametrize(
    ("robot_bug", "task_bug", "where", "why"),
    [
        ("obs_float64", "none", "edge.robots[3] (robot fault_test_slider", "observation['state']: dtype float64"),
        ("obs_extra_key", "none", "edge.robots[3] (robot fault_test_slider", "extra ['debug']"),
        ("obs_list", "none", "edge.robots[3] (robot fault_test_slider", "observation['state'] as a list"),
        ("act_unclipped", "none", "edge.robots[3] (robot fault_test_slider", "act() returned a bad action: action[0]"),
        ("act_wrong_shape", "none", "edge.robots[3] (robot fault_test_slider", "shape [3], spec says [1]"),
        ("act_none", "none", "edge.robots[3] (robot fault_test_slider", "act() returned None"),
        ("none", "nan", "edge.robots[3].task (task fault_test_goal", "evaluate() returned reward nan"),
        ("none", "inf", "edge.robots[3].task (task fault_test_goal", "evaluate() returned reward inf"),
        ("none", "raises", "edge.robots[3].task (task fault_test_goal", "evaluate() raised KeyError: 'distance'"),
        ("none", "returns_tuple", "edge.robots[3].task (task fault_test_goal", "returned tuple, not an Outcome"),
    ],
)
def test_a_plugin_breaking_its_contract_stops_its_robot_held_on_the_first_bad_step(
    robot_bug: str, task_bug: str, where: str, why: str
) -> None:
    rid = f"arm-{robot_bug}-{task_bug}".replace("_", "-")
    robot = make_robot(ROBOT_KIND, rid, {"bug": robot_bug})
    task = TASKS.build(TASK_KIND, {"bug": task_bug}, spec=robot.spec)
    sink = ListSink()
    loop = RobotLoop(robot, ConstantPolicy(), sink, mode="fast", task=task, where="edge.robots[3]")  # type: ignore[arg-type]
    loop.start()
    try:
        wait_for(lambda: not loop.alive, "the loop stops on the bad step")
    finally:
        loop.stop()
    assert loop.failed is not None and loop.failed.startswith(where) and why in loop.failed, loop.failed
    assert loop.error == loop.failed and gauge(ROBOT_FAILED, rid) == 1
    assert robot.calls[-1] == "hold"  # it holds, and nothing moved it after the bad step
    assert robot.calls.count("act") <= 1 and not sink.steps  # the first step was bad: nothing reached the sink
    assert loop.status().state == control_pb2.ROBOT_STATE_OFFLINE


def test_good_plugins_run_and_every_step_they_send_passes_replays_check() -> None:
    robot = make_robot(ROBOT_KIND, "arm-good")
    sink = ListSink()
    loop = RobotLoop(robot, ConstantPolicy(), sink, mode="fast", task=TASKS.build(TASK_KIND, spec=robot.spec))  # type: ignore[arg-type]
    loop.start()
    try:
        wait_for(lambda: len(sink.steps) >= 50, "steps")
    finally:
        loop.stop()
    assert loop.failed is None and loop.error is None and gauge(ROBOT_FAILED, "arm-good") == 0
    for step in sink.steps:
        validate_step(step, robot.spec)


# --------------------------------------------------------------------------- an edge with good and bad robots


def test_failed_robots_hold_for_good_while_the_others_on_the_edge_run_and_up_reports_them(
    cloud: tuple[StackConfig, ControlService], tmp_path: Path
) -> None:
    cfg, control = cloud
    cfg.edge.mode = "realtime"  # 100 Hz: a bounded step rate, whatever the machine
    cfg.edge.replug_s = 0.05  # hot-plug on: a failed robot must not take its reconnect path
    cfg.edge.robots = [
        RobotConfig(id="good-0", kind=ROBOT_KIND),
        RobotConfig(id="float64-0", kind=ROBOT_KIND, params={"bug": "obs_float64"}),
        RobotConfig(id="keyerror-0", kind=ROBOT_KIND, task=PluginConfig(kind=TASK_KIND, params={"bug": "raises"})),
    ]
    detaches = {rid: DETACHES.labels(rid)._value.get() for rid in ("float64-0", "keyerror-0")}
    agent = EdgeAgent(cfg, policy=ConstantPolicy())
    robots = {r.spec.robot_id: r for r in agent.robots}
    httpd, metrics_port = rpc.start_metrics_http("127.0.0.1", 0)
    agent.start()
    try:
        wait_for(lambda: {"float64-0", "keyerror-0"} <= set(agent.failed), "both bad robots failed")
        good = agent.loops["good-0"]
        steps = good.env_steps
        wait_for(lambda: good.env_steps >= steps + 50, "the good robot keeps running")
        wait_for(lambda: not robot_info(control, "keyerror-0").online, "control sees the failed robot leave")
        assert list(agent.loops) == ["good-0"] and not agent._absent  # not retried as absent hardware
        assert agent.failed["float64-0"].startswith("edge.robots[1] (robot fault_test_slider, id float64-0): ")
        assert "observation['state']: dtype float64, spec says float32" in agent.failed["float64-0"]
        assert agent.failed["keyerror-0"].startswith("edge.robots[2].task (task fault_test_goal, robot keyerror-0): ")
        for rid in ("float64-0", "keyerror-0"):
            assert DETACHES.labels(rid)._value.get() == detaches[rid]
            assert [r.spec.robot_id for r in agent.robots].count(rid) == 1 and robots[rid] in agent.robots
            assert robots[rid].calls.count("connect") == 1 and robots[rid].calls[-1] == "hold"
            assert gauge(ROBOT_FAILED, rid) == 1
        assert gauge(ROBOT_FAILED, "good-0") == 0
        faults = up_monitor(cfg, tmp_path, metrics_port).poll_faults()  # what `userctl up` reads from the edge
        assert faults["float64-0"] == RobotFault("failed", agent.failed["float64-0"])
        assert faults["keyerror-0"].state == "failed" and "good-0" not in faults
    finally:
        agent.stop()
        httpd.shutdown()
        httpd.server_close()
    assert replay_stats(cfg.edge.replay_addr).rejected == 0  # nothing the edge sent was refused


def up_monitor(cfg: StackConfig, run_dir: Path, edge_metrics_port: int) -> Monitor:
    """`userctl up`'s monitor over an edge child whose metrics are this process's (the agent under test)."""
    stack = Stack(cfg, None, [], run_dir)
    for name, info in [("control", {"grpc_port": 1}), ("learner", {"grpc_port": 1}), ("replay", {"grpc_port": 1})]:
        stack.children.append(Child(name, None, run_dir / name, run_dir / name, info=info))  # type: ignore[arg-type]
    edge = Child("edge-0", None, run_dir / "edge", run_dir / "edge", info={"metrics_port": edge_metrics_port})  # type: ignore[arg-type]
    stack.children.append(edge)
    return Monitor(stack, 0.0)


def test_a_robot_whose_reset_keeps_raising_stays_on_hotplug_but_is_reported_failing(
    cloud: tuple[StackConfig, ControlService],
) -> None:
    cfg, _control = cloud
    cfg.edge.mode = "realtime"  # 100 Hz: a bounded step rate, whatever the machine
    cfg.edge.replug_s = 0.02
    cfg.edge.robots = [
        RobotConfig(id="good-1", kind=ROBOT_KIND),
        RobotConfig(id="homing-0", kind=ROBOT_KIND, params={"bug": "reset_raises"}),
    ]
    detaches = DETACHES.labels("homing-0")._value.get()
    agent = EdgeAgent(cfg, policy=ConstantPolicy())
    agent.start()
    try:
        wait_for(lambda: gauge(ROBOT_FAILING, "homing-0") == 1, "the robot is reported failing")
        assert DETACHES.labels("homing-0")._value.get() - detaches >= 3  # hardware path: detached, reconnected
        assert "homing-0" not in agent.failed  # not a plug-in error: still retried
        wait_for(lambda: DETACHES.labels("homing-0")._value.get() - detaches >= 4, "still retried after that")
        fault = next(s for s in prometheus_client.REGISTRY.collect() if s.name == "user_edge_robot_fault")
        sample = next(s for s in fault.samples if s.labels["robot_id"] == "homing-0")
        assert sample.labels["state"] == "failing"
        assert sample.labels["error"].startswith("edge.robots[1] (robot fault_test_slider, id homing-0): its loop")
        assert "RuntimeError('homing failed')" in sample.labels["error"]
        assert agent.loops["good-1"].alive and gauge(ROBOT_FAILING, "good-1") == 0
    finally:
        agent.stop()


# --------------------------------------------------------------------------- specs that can never be valid


def test_a_spec_that_can_never_be_valid_stops_the_edge_at_start_naming_the_entry() -> None:
    cfg = StackConfig()
    cfg.edge.robots = [
        RobotConfig(id="ok-0", kind=ROBOT_KIND),
        RobotConfig(id="bad-0", kind=ROBOT_KIND, params={"bug": "spec_low_above_high"}),
    ]
    with pytest.raises(PluginError) as err:
        EdgeAgent(cfg, policy=ConstantPolicy(), sender=ListSink())  # type: ignore[arg-type]
    assert str(err.value).startswith("edge.robots[1] (robot fault_test_slider): its spec is invalid: ")
    assert "action bound 0 needs finite low <= high, got low=1.0 high=-1.0" in str(err.value)


def test_userctl_edge_exits_2_with_one_line_for_an_invalid_spec(capsys: pytest.CaptureFixture[str]) -> None:
    import logging
    import signal

    from user import cli

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    on_signal = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    entry = f"edge.robots=[{{id: bad-0, kind: {ROBOT_KIND}, params: {{bug: spec_low_above_high}}}}]"
    try:  # `userctl edge` sets up its logging and signal handlers in this process: put pytest's back after it
        assert cli.main(["edge", "--set", entry, "--set", "auth.token=t"]) == 2
    finally:
        root.handlers[:], root.level = handlers, level
        for sig, handler in on_signal.items():
            signal.signal(sig, handler)
    err = capsys.readouterr().err
    assert "userctl edge: edge.robots[0] (robot fault_test_slider): its spec is invalid: robot bad-0: action" in err
    assert "Traceback" not in err


def test_a_robot_plugged_in_later_with_an_invalid_spec_is_failed_not_retried(
    cloud: tuple[StackConfig, ControlService], tmp_path: Path
) -> None:
    cfg, control = cloud
    cable = tmp_path / "cable"
    cfg.edge.mode = "realtime"  # 100 Hz: a bounded step rate, whatever the machine
    cfg.edge.replug_s = 0.02
    cfg.edge.robots = [
        RobotConfig(id="good-2", kind=ROBOT_KIND),
        RobotConfig(id="late-0", kind=ROBOT_KIND, params={"bug": "spec_bad_once_connected", "cable": str(cable)}),
    ]
    agent = EdgeAgent(cfg, policy=ConstantPolicy())
    agent.start()
    try:
        assert list(agent.loops) == ["good-2"]  # late-0 is not plugged in yet
        cable.touch()
        wait_for(lambda: "late-0" in agent.failed, "the late robot failed on its spec")
        assert agent.failed["late-0"].startswith("edge.robots[1] (robot fault_test_slider): its spec is invalid: ")
        late = next(r for r in agent.robots if r.spec.robot_id == "late-0")
        assert late.calls == ["connect", "hold"]  # connected once, held, never reset or moved
        assert "late-0" not in agent._absent and "late-0" not in agent.loops and gauge(ROBOT_FAILED, "late-0") == 1
        steps = agent.loops["good-2"].env_steps
        wait_for(lambda: agent.loops["good-2"].env_steps >= steps + 20, "the other robot runs on")
        assert robot_info(control, "late-0") is None  # never registered: control would refuse it
    finally:
        agent.stop()


# --------------------------------------------------------------------------- `userctl up`


def test_up_summary_shows_failed_robots_in_the_entry_of_its_config_and_never_all_clean(tmp_path: Path) -> None:
    cfg = StackConfig()
    fault = _in_entry(RobotFault("failed", "edge.robots[0] (robot k, id arm-3): act() returned None"), 3)
    assert fault.error == "edge.robots[3] (robot k, id arm-3): act() returned None"  # its entry in up's config
    info = control_pb2.RobotInfo(spec=robot_pb2.RobotSpec(robot_id="ok-0"), status=control_pb2.RobotStatus(env_steps=9))
    snap = Snapshot(1.0, [info], None, None, {"arm-3": fault})
    summary = _summary(cfg, "budget exhausted", None, snap, [], {"edge-0": 0, "edge-1": 0}, 1.0)
    assert summary["robots"]["arm-3"]["fault"] == {"state": "failed", "error": fault.error}
    assert "fault" not in summary["robots"]["ok-0"]
    from rich.console import Console

    console = Console(record=True, width=400)
    _print_summary(console, summary, tmp_path)
    text = console.export_text()
    assert "FAILED: edge.robots[3] (robot k, id arm-3): act() returned None; 0 steps" in text
    assert "robot arm-3 failed" in text and "all clean" not in text
    assert exits_text({"edge-0": 0}, {}, {"arm-1": "failing"}) == "robot arm-1 failing"
    assert exits_text({"edge-0": 0}, {}, {}) == "all clean"
    mon = up_monitor(cfg, tmp_path, edge_metrics_port=1)  # the live console's robot row
    assert _robot_cells(info, mon, {}, 20, {"ok-0": fault})["state"] == "FAILED"
    assert _robot_cells(info, mon, {}, 20, {"ok-0": RobotFault("failing", "x")})["state"] == "failing"
    assert _robot_cells(info, mon, {}, 20, {})["state"] == "offline"


def test_up_hands_nan_and_inf_params_to_the_edge_exactly(tmp_path: Path) -> None:
    cfg = StackConfig()
    cfg.up.edge_agents = 2
    cfg.edge.robots = [
        RobotConfig(id="arm-0", kind="k", params={"gain": math.nan, "limit": math.inf, "note": "a: b, [c]"}),
        RobotConfig(id="cam-0", kind="k", task=PluginConfig(kind="t", params={"floor": -math.inf, "x": None})),
    ]
    stack = Stack(cfg, None, [], tmp_path)
    for name in ("control", "replay", "inference", "learner"):
        stack.children.append(Child(name, None, tmp_path / name, tmp_path / name, info={"grpc_port": 1}))  # type: ignore[arg-type]
    robots = stack._edge_robots()
    items = stack.edge_overrides("edge-2", [robots[2]], seed=3)
    assert "edge.robots=[{" in " ".join(items)  # the --set value the child parses
    child = load_config(overrides=items).edge.robots  # the child's own --set parser
    assert child[0].id == "cam-0" and child[0].task is not None
    assert child[0].task.params["floor"] == -math.inf and child[0].task.params["x"] is None
    first = load_config(overrides=stack.edge_overrides("edge-1", [robots[1]], seed=2)).edge.robots[0]
    assert first.id == "arm-1" and math.isnan(first.params["gain"]) and first.params["limit"] == math.inf
    assert first.params["note"] == "a: b, [c]"


def test_up_numbers_robot_copies_on_from_the_configured_id(tmp_path: Path) -> None:
    ids = {}
    for first, agents in (("arm-9", 1), ("arm-9", 3), ("arm-0", 2), ("panda", 2)):
        cfg = StackConfig()
        cfg.up.edge_agents = agents
        cfg.edge.robots = [RobotConfig(id=first, kind="k")]
        ids[first, agents] = [r["id"] for r in Stack(cfg, None, [], tmp_path)._edge_robots()]
    assert ids["arm-9", 1] == ["arm-9"]  # a single robot keeps the id it was configured with
    assert ids["arm-9", 3] == ["arm-9", "arm-10", "arm-11"]
    assert ids["arm-0", 2] == ["arm-0", "arm-1"]
    assert ids["panda", 2] == ["panda-0", "panda-1"]
