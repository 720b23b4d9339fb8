"""Control as operators use it: a registry that survives restarts, the worker (GPU) pool, command results
back to the sender, and the userctl views. Real Control, real edge ControlClient, real SQLite in tmp_path."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from services.inference.server import InferenceService, report_to_control
from tests.helpers import wait_for
from tests.test_replay_store import spec
from user import cli
from user.config import AuthConfig, ExperimentConfig, RobotSelector, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc

AUTH = AuthConfig(token="test-token")


@pytest.fixture
def make_control(tmp_path: Path) -> Iterator[Callable[[], ControlService]]:
    started: list[ControlService] = []

    def make() -> ControlService:
        cfg = StackConfig(auth=AUTH)
        cfg.control.server.port = cfg.control.server.metrics_port = 0
        cfg.control.server.grace_s = 0.5
        cfg.control.heartbeat_interval_s = 0.05
        cfg.control.state_path = tmp_path / "control.sqlite"
        svc = ControlService(cfg, start_metrics=False).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


def stub(svc: ControlService) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(svc.address, AUTH))


def episode(robot_id: str, n: int) -> control_pb2.EpisodeSummary:
    return control_pb2.EpisodeSummary(robot_id=robot_id, episode_id=f"ep-{n}", length=10, success=n % 2 == 0)


def edge_client(svc: ControlService, statuses: list, on_command=lambda c: (True, "done")) -> ControlClient:
    client = ControlClient(svc.address, AUTH, "lab-pc-1", [spec("arm-0"), spec("arm-1")], lambda: statuses, on_command)
    assert client.wait_registered(10)
    return client


def test_a_restarted_control_keeps_robots_episodes_and_workers(make_control) -> None:
    control = make_control()
    status = control_pb2.RobotStatus(
        robot_id="arm-0", episodes=2, new_episodes=[episode("arm-0", 1), episode("arm-0", 2)]
    )
    client = edge_client(control, [status])
    s = stub(control)
    wait_for(lambda: len(s.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).recent_episodes) == 2)
    worker = control_pb2.WorkerInfo(worker_id="learner@gpu-1:50054", kind="learner", device="cuda:0")
    worker.devices.add(name="cuda:0", model="H100", memory_bytes=80 * 2**30)
    s.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=worker), timeout=5)
    client.close()
    control.stop()

    control = make_control()  # same SQLite file
    s = stub(control)
    robots = s.ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=5).robots
    assert [(r.spec.robot_id, r.agent_id, r.online) for r in robots] == [
        ("arm-0", "lab-pc-1", False),
        ("arm-1", "lab-pc-1", False),
    ]
    assert robots[0].spec == spec("arm-0")
    assert [e.episode_id for e in robots[0].recent_episodes] == ["ep-1", "ep-2"]
    assert robots[0].status.episodes == 2
    workers = s.ListWorkers(control_pb2.ListWorkersRequest(include_offline=True), timeout=5).workers
    assert [(w.worker_id, w.devices[0].memory_bytes) for w in workers] == [("learner@gpu-1:50054", 80 * 2**30)]
    # The edge comes back; the episodes it re-sends are stored once.
    client = edge_client(control, [status])
    try:
        wait_for(lambda: s.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).online)
        for _ in range(3):  # several heartbeats re-send the same two episodes
            before = s.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).last_heartbeat_ns
            wait_for(
                lambda b=before: (
                    s.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).last_heartbeat_ns > b
                )
            )
        info = s.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert [e.episode_id for e in info.recent_episodes] == ["ep-1", "ep-2"]
        assert control.state.episode_count("arm-0") == 2
    finally:
        client.close()


def test_command_results_reach_the_sender(make_control, capsys: pytest.CaptureFixture[str]) -> None:
    control = make_control()
    seen: list[int] = []

    def on_command(cmd: control_pb2.Command) -> tuple[bool, str]:
        seen.append(cmd.kind)
        return (cmd.kind != control_pb2.COMMAND_KIND_RESET, "paused" if cmd.kind == 1 else "no episode to end")

    client = edge_client(control, [], on_command)
    try:
        s = stub(control)
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id="arm-0")
        resp = s.SendCommand(control_pb2.SendCommandRequest(command=cmd, wait_result_s=10), timeout=15)
        assert list(resp.agents) == ["lab-pc-1"]
        assert [(r.agent_id, r.ok, r.message) for r in resp.results] == [("lab-pc-1", True, "paused")]
        status = s.GetCommand(control_pb2.GetCommandRequest(command_id=resp.command_id), timeout=5)
        assert status.command.kind == control_pb2.COMMAND_KIND_PAUSE and len(status.results) == 1
        # The same through userctl: exit 1 when an edge reports failure.
        base = ["--control", control.address, "--set", "auth.token=test-token"]
        assert cli.main(["command", "reset", "arm-0", "--wait", "10", *base]) == 1
        assert "lab-pc-1: FAILED no episode to end" in capsys.readouterr().out
        assert seen == [control_pb2.COMMAND_KIND_PAUSE, control_pb2.COMMAND_KIND_RESET]
    finally:
        client.close()


def test_workers_register_their_devices_and_operators_list_them(
    make_control, capsys: pytest.CaptureFixture[str]
) -> None:
    control = make_control()
    cfg = StackConfig(auth=AUTH)
    cfg.inference.server.port = cfg.inference.server.metrics_port = 0
    cfg.inference.server.grace_s = 0.5
    cfg.inference.control_addr = control.address
    cfg.experiments = [
        ExperimentConfig(name=name, robots=RobotSelector(ids=[robot]))
        for name, robot in (("reach", "arm-0"), ("push", "arm-1"))
    ]
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    client = edge_client(control, [])
    try:
        with report_to_control(inference) as reporter:  # what `userctl inference` reports: the experiments it serves
            assert reporter.reported.wait(10)
        workers = stub(control).ListWorkers(control_pb2.ListWorkersRequest(), timeout=5).workers
        assert len(workers) == 1
        w = workers[0]
        assert (w.kind, w.device, list(w.experiments), w.online) == ("inference", "cpu", ["reach", "push"], True)
        assert w.address.endswith(f":{inference.port}") and w.cpu_count >= 1
        assert w.devices[0].name == "cpu" and w.devices[0].memory_bytes > 2**20
        base = ["--control", control.address, "--set", "auth.token=test-token"]
        assert cli.main(["workers", "ls", *base]) == 0
        assert w.worker_id[:20] in capsys.readouterr().out
        assert cli.main(["robots", "ls", *base]) == 0
        out = capsys.readouterr().out
        assert "arm-0" in out and "arm-1" in out and "lab-pc-1" in out
        assert cli.main(["robots", "ls", "--json", *base]) == 0
        assert '"robotId": "arm-1"' in capsys.readouterr().out
    finally:
        client.close()
        inference.stop()


def test_a_bad_worker_report_is_invalid_argument(make_control) -> None:
    import grpc

    control = make_control()
    with pytest.raises(grpc.RpcError) as err:
        stub(control).RegisterWorker(
            control_pb2.RegisterWorkerRequest(worker=control_pb2.WorkerInfo(worker_id="w", kind="trainer")), timeout=5
        )
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_a_robot_plugged_in_is_announced_before_its_status_and_its_first_episode_arrives(make_control) -> None:
    """Hot-plug: the heartbeat that goes with a robot-set change carries only robots control already knows; a
    new robot's status (and an episode it finished meanwhile) follows the set update, never refused as foreign."""
    from services.control.server import HEARTBEAT_REJECTED

    def foreign() -> float:
        return HEARTBEAT_REJECTED.labels("foreign_robot")._value.get()

    control = make_control()
    statuses = [control_pb2.RobotStatus(robot_id="arm-0")]
    client = ControlClient(control.address, AUTH, "lab-pc-1", [spec("arm-0")], lambda: list(statuses), lambda c: None)
    try:
        assert client.wait_registered(10)
        before = foreign()
        statuses.append(control_pb2.RobotStatus(robot_id="arm-2", episodes=1, new_episodes=[episode("arm-2", 1)]))
        client.set_robots([spec("arm-0"), spec("arm-2")])
        s = stub(control)

        def arm_2() -> control_pb2.RobotInfo | None:
            robots = s.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
            return next((r for r in robots if r.spec.robot_id == "arm-2" and r.recent_episodes), None)

        got = wait_for(arm_2, "arm-2's episode at control")
        assert [e.episode_id for e in got.recent_episodes] == ["ep-1"]
        assert foreign() == before
    finally:
        client.close()
