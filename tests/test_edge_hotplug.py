"""Hot-plug: robots plugged in after the agent started register, unplugged ones go offline and free their lease.

Real control, replay and inference services; the edge agent drives two `test_pluggable` sim arms whose
"cable" is a file the test creates and deletes (connect fails and bus calls raise while it is missing,
as a lerobot arm's serial bus does when its USB cable is pulled).
"""

from __future__ import annotations

import queue
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

import tests.plugins  # noqa: F401 - registers test_pluggable
from edge_agent.agent import DETACHES, TELEOP_DETACHES, EdgeAgent, RobotLoop
from services.control.server import ControlService
from services.inference.server import InferenceService
from services.replay.server import ReplayService
from tests.helpers import wait_for
from tests.test_control import spec as robot_spec
from tests.test_edge_agent import control, control_stub, edge_cfg, random_weights, replay_stats, robot_info, stack_cfg
from user.config import AuthConfig, ExperimentConfig, PluginConfig, RobotConfig, RobotSelector, StackConfig
from user.v1 import control_pb2, robot_pb2

__all__ = ["control"]  # a fixture


@pytest.fixture
def one_place(tmp_path: Path) -> Iterator[tuple[StackConfig, ControlService]]:
    """Control (one experiment with one place for the sim arms) + replay + inference with random weights."""
    cfg = stack_cfg(tmp_path)
    # Slow heartbeats: episodes a robot finished before its cable was pulled are still unreported then.
    cfg.control.heartbeat_interval_s, cfg.control.lease_ttl_s = 1.0, 10.0
    cfg.experiments = [ExperimentConfig(name="reach", robots=RobotSelector(kinds=["sim_reach_arm"]), max_robots=1)]
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    inference.load_weights(random_weights(5))
    try:
        yield edge_cfg(cfg, control, replay, inference), control
    finally:
        inference.stop()
        replay.stop()
        control.stop()


def pluggable(rid: str, cable: Path) -> RobotConfig:
    return RobotConfig(id=rid, kind="test_pluggable", params={"max_episode_steps": 20, "cable": str(cable)})


def lease_of(control: ControlService, rid: str) -> tuple[str, str] | None:
    """(experiment leased to, reason for none) while the robot is online; None while it is not."""
    info = robot_info(control, rid)
    return (info.lease, info.lease_reason) if info is not None and info.online else None


def test_robots_plugged_in_later_register_and_unplugged_ones_go_offline_and_free_their_place(
    one_place: tuple[StackConfig, ControlService], tmp_path: Path
) -> None:
    cloud, control = one_place
    cable_a, cable_b = tmp_path / "cable-a", tmp_path / "cable-b"
    cable_a.touch()  # arm-a is plugged in at start, arm-b is not
    cloud.edge.robots = [pluggable("arm-a", cable_a), pluggable("arm-b", cable_b)]
    cloud.edge.replug_s = 0.2
    # One place (max_robots=1): the robot holding it keeps it; a robot that goes offline frees it for the other.
    detached_before = DETACHES.labels("arm-a")._value.get()
    agent = EdgeAgent(cloud)
    agent.start()
    lives: dict[str, list[RobotLoop]] = {"arm-a": [], "arm-b": []}

    def note_loops() -> None:
        for rid, loop in agent.loops.items():
            if all(loop is not seen for seen in lives[rid]):
                lives[rid].append(loop)

    try:
        note_loops()
        assert list(agent.loops) == ["arm-a"]
        wait_for(lambda: (info := robot_info(control, "arm-a")) is not None and info.status.env_steps >= 50)
        assert robot_info(control, "arm-b") is None  # never plugged in: control has not heard of it
        assert lease_of(control, "arm-a") == ("reach", "")

        cable_b.touch()  # plug arm-b in: it registers, and waits, since arm-a holds the one place
        wait_for(lambda: lease_of(control, "arm-b") is not None, "arm-b registered")
        note_loops()
        wait_for(lambda: lives["arm-b"][0].held_by_lease, "arm-b held at max_robots")
        assert "max_robots" in lease_of(control, "arm-b")[1]
        assert lives["arm-b"][0].env_steps == 0

        finished = lives["arm-a"][0].episodes
        wait_for(lambda: lives["arm-a"][0].episodes > finished, "an episode of arm-a ends")
        cable_a.unlink()  # pull arm-a's cable: its loop fails, it goes offline, arm-b takes the place
        wait_for(lambda: (info := robot_info(control, "arm-a")) is not None and not info.online, "arm-a offline")
        assert robot_info(control, "arm-a").status.state == control_pb2.ROBOT_STATE_OFFLINE
        assert "arm-a" not in agent.loops
        wait_for(lambda: lease_of(control, "arm-b") == ("reach", ""), "arm-b leased")
        wait_for(lambda: lives["arm-b"][0].env_steps >= 50, "arm-b collecting")
        assert DETACHES.labels("arm-a")._value.get() == detached_before + 1

        cable_a.touch()  # plug arm-a back in: a fresh instance registers and holds (arm-b keeps the place)
        wait_for(lambda: len(lives["arm-a"]) == 2 or note_loops(), "arm-a attached again")
        wait_for(lambda: (lease := lease_of(control, "arm-a")) is not None and "max_robots" in lease[1], "arm-a back")
        wait_for(lambda: lives["arm-a"][1].held_by_lease and lives["arm-a"][1].lease.reason.endswith("max_robots=1"))
        assert lease_of(control, "arm-b") == ("reach", "")
        assert lives["arm-a"][1].robot is not lives["arm-a"][0].robot
    finally:
        agent.stop()
    # Nothing the robots completed was lost: every step of every life reached replay, none refused.
    stats = replay_stats(cloud.edge.replay_addr)
    assert stats.rejected == 0
    for rid, loops in lives.items():
        assert stats.steps_per_robot[rid] == sum(loop.env_steps for loop in loops) > 0
        # Episodes a robot finished just before its cable was pulled still reached control.
        info = robot_info(control, rid)
        assert len({e.episode_id for e in info.recent_episodes}) == sum(loop.episodes for loop in loops)


def test_a_teleoperator_plugged_in_later_takes_over_and_one_pulled_mid_run_reconnects(
    one_place: tuple[StackConfig, ControlService], tmp_path: Path
) -> None:
    cloud, control = one_place
    cable = tmp_path / "gamepad"
    cloud.edge.replug_s = 0.2
    cloud.edge.robots = [
        RobotConfig(
            id="arm-0",
            kind="sim_reach_arm",
            params={"max_episode_steps": 20},
            teleop=PluginConfig(kind="test_pluggable", params={"cable": str(cable)}),
        )
    ]
    agent = EdgeAgent(cloud)
    agent.start()  # the gamepad is not there: the agent starts anyway and the policy drives
    try:
        loop = agent.loops["arm-0"]
        wait_for(lambda: loop.env_steps >= 50, "the policy drives")
        assert loop.intervention_steps == 0 and loop.teleop is None
        cable.touch()
        wait_for(lambda: loop.intervention_steps >= 20, "the human drives once the gamepad connects")
        wait_for(lambda: robot_info(control, "arm-0").status.intervention_steps >= 20, "interventions at control")
        first, detaches = loop.teleop, TELEOP_DETACHES.labels("arm-0")._value.get()
        cable.unlink()  # pulled while its human drives: polls fail, the robot holds, the gamepad is released
        wait_for(lambda: loop.teleop is None, "the failing gamepad detached")
        assert TELEOP_DETACHES.labels("arm-0")._value.get() == detaches + 1
        helped, steps = loop.intervention_steps, loop.env_steps
        wait_for(lambda: loop.env_steps >= steps + 20, "held steps without the gamepad")
        assert loop.intervention_steps == helped and loop.alive and loop.teleop_lost  # not handed to the policy
        cable.touch()  # re-plugged: the old handle stays dead, a fresh instance connects and drives
        wait_for(lambda: loop.intervention_steps >= helped + 20, "the human drives again after re-plugging")
        assert loop.teleop is not None and loop.teleop is not first and agent.teleops["arm-0"] is loop.teleop
    finally:
        agent.stop()
    assert replay_stats(cloud.edge.replay_addr).rejected == 0


def test_control_checks_a_robots_update_like_a_registration(control: ControlService) -> None:
    """A hot-plug update with a robot another live agent holds ends the stream with ALREADY_EXISTS and changes
    nothing; a good one adds and removes robots; an agent may register with no robot yet."""
    stub = control_stub(control)

    def stream(agent_id: str, specs: list[robot_pb2.RobotSpec]) -> tuple[queue.Queue, object]:
        up: queue.Queue = queue.Queue()
        up.put(control_pb2.EdgeMessage(register=control_pb2.RegisterRequest(agent_id=agent_id, robots=specs)))
        call = stub.Connect(iter(up.get, None), timeout=30)
        assert next(call).WhichOneof("msg") == "registered"
        return up, call

    from services.control.server import ROBOT_SET_UPDATES

    updates_before = ROBOT_SET_UPDATES._value.get()
    up_a, call_a = stream("edge-a", [robot_spec("r1")])
    up_b, call_b = stream("edge-b", [])  # nothing plugged in yet
    try:
        up_b.put(control_pb2.EdgeMessage(robots=control_pb2.RobotsUpdate(robots=[robot_spec("r2")])))
        leases = next(call_b)
        assert [lease.robot_id for lease in leases.leases.leases] == ["r2"]
        assert robot_info(control, "r2").online and robot_info(control, "r2").agent_id == "edge-b"
        assert ROBOT_SET_UPDATES._value.get() == updates_before + 1  # the refused update below is not counted
        up_b.put(control_pb2.EdgeMessage(robots=control_pb2.RobotsUpdate(robots=[robot_spec("r1"), robot_spec("r2")])))
        with pytest.raises(grpc.RpcError) as err:
            next(call_b)
        assert err.value.code() == grpc.StatusCode.ALREADY_EXISTS
        assert robot_info(control, "r1").agent_id == "edge-a" and robot_info(control, "r1").online
        up_a.put(control_pb2.EdgeMessage(robots=control_pb2.RobotsUpdate()))  # r1 unplugged from edge-a
        wait_for(lambda: not robot_info(control, "r1").online, "r1 offline")
        assert robot_info(control, "r1").status.state == control_pb2.ROBOT_STATE_OFFLINE
    finally:
        up_a.put(None)
        up_b.put(None)
        call_a.cancel()
        call_b.cancel()


def test_a_late_robot_joins_the_agents_tick_grid_and_retries_back_off() -> None:
    import time

    from edge_agent.agent import REPLUG_MAX_S
    from tests.test_edge_plugins import ConstantPolicy, ListSink

    cfg = StackConfig(auth=AuthConfig(token="test-token"))
    cfg.edge.mode, cfg.edge.replug_s = "realtime", 0.5
    cfg.edge.robots = [RobotConfig(id="arm-0", kind="sim_reach_arm")]
    agent = EdgeAgent(cfg, policy=ConstantPolicy(), sender=ListSink())  # type: ignore[arg-type]
    try:
        agent._grid0 = time.monotonic() - 10.0
        before = time.monotonic()
        tick = agent._next_tick(0.05)
        assert tick > before  # ahead of now, on the grid the first robots tick on (20 Hz: whole periods)
        assert abs((tick - agent._grid0) / 0.05 - round((tick - agent._grid0) / 0.05)) < 1e-6
        assert [agent._retry_s(n) for n in (1, 2, 3)] == [0.5, 1.0, 2.0]
        assert agent._retry_s(50) == REPLUG_MAX_S
    finally:
        agent.control.close(0)
        for robot in agent.robots:
            robot.close()
