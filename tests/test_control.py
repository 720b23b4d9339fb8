"""Control service over real gRPC on 127.0.0.1:0: registration, leases, heartbeats, commands, auth."""

from __future__ import annotations

import queue
import time
import urllib.request
from collections.abc import Callable, Iterator
from typing import Any

import grpc
import prometheus_client
import pytest

from services.control.server import ControlService
from tests.helpers import wait_for
from user.config import AuthConfig, StackConfig
from user.rpc import check_health, make_channel
from user.v1 import control_pb2, control_pb2_grpc, robot_pb2
from user.v1 import tensor_pb2 as tpb

AUTH = AuthConfig(token="test-token")


def _cfg(lease_ttl_s: float = 10.0, episodes_kept: int = 200) -> StackConfig:
    cfg = StackConfig(auth=AUTH)
    cfg.control.server.port = 0
    cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 1.0
    cfg.control.lease_ttl_s = lease_ttl_s
    cfg.control.heartbeat_interval_s = 0.1
    cfg.control.episodes_kept = episodes_kept
    return cfg


@pytest.fixture
def make_service() -> Iterator[Callable[..., ControlService]]:
    started: list[ControlService] = []

    def make(metrics_http: bool = False, **kw: Any) -> ControlService:
        # The /metrics HTTP server costs 0.5 s to shut down; only the test that scrapes it starts one.
        svc = ControlService(_cfg(**kw), start_metrics=metrics_http).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


def _stub(svc: ControlService, auth: AuthConfig = AUTH) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(svc.address, auth))


def spec(robot_id: str = "arm-0", **over: Any) -> robot_pb2.RobotSpec:
    s = robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="sim_reach_arm",
        action=robot_pb2.ActionSpace(shape=[3], low=[-1, -1, -1], high=[1, 1, 1], dtype=tpb.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[6])],
        control_rate_hz=10.0,
        max_episode_steps=50,
    )
    for key, value in over.items():
        if key == "action":
            s.action.CopyFrom(value)
        elif key == "observation":
            del s.observation[:]
            s.observation.extend(value)
        else:
            setattr(s, key, value)
    return s


def register_msg(agent_id: str, *specs: robot_pb2.RobotSpec) -> control_pb2.EdgeMessage:
    req = control_pb2.RegisterRequest(agent_id=agent_id, hostname="test-host", robots=list(specs))
    return control_pb2.EdgeMessage(register=req)


class Edge:
    """The edge side of one Connect stream: put() messages up, next_message() reads what comes down."""

    def __init__(self, stub: control_pb2_grpc.ControlStub, first: control_pb2.EdgeMessage) -> None:
        self._up: queue.Queue = queue.Queue()
        self._up.put(first)
        self.call = stub.Connect(self._requests(), timeout=60)

    def _requests(self) -> Iterator[control_pb2.EdgeMessage]:
        while (msg := self._up.get()) is not None:
            yield msg

    def put(self, msg: control_pb2.EdgeMessage) -> None:
        self._up.put(msg)

    def heartbeat(self, seq: int, *statuses: control_pb2.RobotStatus) -> None:
        self.put(
            control_pb2.EdgeMessage(
                heartbeat=control_pb2.Heartbeat(seq=seq, sent_at_ns=time.time_ns(), robots=list(statuses))
            )
        )

    def next_message(self) -> control_pb2.ControlMessage:
        return next(self.call)

    def hang_up(self) -> None:
        self._up.put(None)

    def close(self) -> None:
        self.hang_up()
        self.call.cancel()


def _metric(name: str, **labels: str) -> float:
    return prometheus_client.REGISTRY.get_sample_value(name, labels) or 0.0


def test_register_heartbeat_list_get(make_service: Callable[..., ControlService]) -> None:
    svc = make_service(episodes_kept=3)
    stub = _stub(svc)
    regs_before = _metric("user_control_registrations_total")
    edge = Edge(stub, register_msg("edge-a", spec("arm-0"), spec("arm-1")))
    try:
        reply = edge.next_message()
        assert reply.WhichOneof("msg") == "registered"
        assert reply.registered.lease_id
        assert reply.registered.lease_ttl_s == pytest.approx(10.0)
        assert reply.registered.heartbeat_interval_s == pytest.approx(0.1)
        assert _metric("user_control_registrations_total") == regs_before + 1
        assert _metric("user_control_robots_online") == 2

        robots = stub.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
        assert [r.spec.robot_id for r in robots] == ["arm-0", "arm-1"]
        assert all(r.online and r.agent_id == "edge-a" and r.hostname == "test-host" for r in robots)

        episodes = [
            control_pb2.EpisodeSummary(
                episode_id=f"ep{i}", length=50, episode_return=float(i), success=i % 2 == 0, policy_version=i
            )
            for i in range(5)
        ]
        status = control_pb2.RobotStatus(
            robot_id="arm-0",
            state=control_pb2.ROBOT_STATE_RUNNING,
            episodes=5,
            env_steps=250,
            policy_version=4,
            new_episodes=episodes,
        )
        edge.heartbeat(1, status, control_pb2.RobotStatus(robot_id="arm-1", state=control_pb2.ROBOT_STATE_PAUSED))
        info = wait_for(
            lambda: (
                (i := stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)).status.env_steps and i
            ),
            "heartbeat applied",
        )
        assert info.online and info.status.policy_version == 4 and info.status.episodes == 5
        assert not info.status.new_episodes  # episodes are kept in recent_episodes, bounded
        assert [e.episode_id for e in info.recent_episodes] == ["ep2", "ep3", "ep4"]  # newest last
        assert all(e.robot_id == "arm-0" for e in info.recent_episodes)
        assert info.lease_expires_ns > info.last_heartbeat_ns >= info.registered_at_ns
        arm1 = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-1"), timeout=5)
        assert arm1.status.state == control_pb2.ROBOT_STATE_PAUSED
        assert _metric("user_control_episodes_total", success="true") >= 3

        # After a broken stream the edge re-sends its last episodes: each is kept once.
        resent = [episodes[4], control_pb2.EpisodeSummary(episode_id="ep5", length=9, success=True)]
        status.ClearField("new_episodes")
        status.new_episodes.extend(resent)
        status.env_steps = 260
        edge.heartbeat(2, status)
        wait_for(
            lambda: stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).status.env_steps == 260,
            "second heartbeat applied",
        )
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert [e.episode_id for e in info.recent_episodes] == ["ep3", "ep4", "ep5"]
        listed = stub.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
        assert [len(r.recent_episodes) for r in listed] == [3, 0]
        lean = stub.ListRobots(control_pb2.ListRobotsRequest(without_episodes=True), timeout=5).robots
        assert [(r.spec.robot_id, len(r.recent_episodes)) for r in lean] == [("arm-0", 0), ("arm-1", 0)]
        assert lean[0].status.env_steps == 260 and lean[0].spec == listed[0].spec  # the rest is the same

        with pytest.raises(grpc.RpcError) as err:
            stub.GetRobot(control_pb2.GetRobotRequest(robot_id="nope"), timeout=5)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND

        # The edge hangs up: its robots go offline, their specs stay queryable.
        edge.hang_up()
        wait_for(lambda: not stub.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots, "robots offline")
        offline = stub.ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=5).robots
        assert [r.spec.robot_id for r in offline] == ["arm-0", "arm-1"]
        assert not any(r.online for r in offline)
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert info.spec.action.shape == [3] and info.status.state == control_pb2.ROBOT_STATE_OFFLINE
        assert _metric("user_control_robots_online") == 0
    finally:
        edge.close()


def test_heartbeats_renew_then_lease_expires(make_service: Callable[..., ControlService]) -> None:
    svc = make_service(lease_ttl_s=1.0)
    stub = _stub(svc)
    expirations = _metric("user_control_lease_expirations_total")
    edge = Edge(stub, register_msg("edge-a", spec("arm-0")))
    try:
        assert edge.next_message().registered.lease_ttl_s == pytest.approx(1.0)
        # Heartbeats for longer than the TTL keep the lease.
        end = time.monotonic() + 1.5
        seq = 0
        while time.monotonic() < end:
            seq += 1
            edge.heartbeat(seq, control_pb2.RobotStatus(robot_id="arm-0", env_steps=seq))
            time.sleep(0.05)
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert info.online and info.status.env_steps > 0
        # Silence: the reaper ends the lease and the stream with ABORTED.
        with pytest.raises(grpc.RpcError) as err:
            edge.next_message()
        assert err.value.code() == grpc.StatusCode.ABORTED
        assert "lease expired" in err.value.details()
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert not info.online and info.spec.robot_id == "arm-0"
        assert _metric("user_control_lease_expirations_total") == expirations + 1
        # A reconnect takes the robot back.
        again = Edge(stub, register_msg("edge-a", spec("arm-0")))
        assert again.next_message().WhichOneof("msg") == "registered"
        assert stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).online
        again.close()
    finally:
        edge.close()


def _expect_abort(stub: control_pb2_grpc.ControlStub, first: control_pb2.EdgeMessage) -> grpc.RpcError:
    edge = Edge(stub, first)
    try:
        with pytest.raises(grpc.RpcError) as err:
            edge.next_message()
        return err.value
    finally:
        edge.close()


def test_first_message_must_be_register(make_service: Callable[..., ControlService]) -> None:
    stub = _stub(make_service())
    err = _expect_abort(stub, control_pb2.EdgeMessage(heartbeat=control_pb2.Heartbeat(seq=1)))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "register" in err.details()


BAD_SPECS = {
    "empty robot_id": spec(robot_id=""),
    "robot_id charset": spec(robot_id="arm 0/evil"),
    "low/high count": spec(action=robot_pb2.ActionSpace(shape=[3], low=[-1, -1], high=[1, 1, 1])),
    "low > high": spec(action=robot_pb2.ActionSpace(shape=[2], low=[-1, 2], high=[1, 1])),
    "empty action shape": spec(action=robot_pb2.ActionSpace(shape=[], low=[], high=[])),
    "unnamed feature": spec(observation=[robot_pb2.FeatureSpec(name="", dtype=tpb.DTYPE_FLOAT32, shape=[3])]),
    "unshaped feature": spec(observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32)]),
    "no features": spec(observation=[]),
    "zero rate": spec(control_rate_hz=0.0),
}


@pytest.mark.parametrize("case", sorted(BAD_SPECS))
def test_bad_spec_is_invalid_argument(make_service: Callable[..., ControlService], case: str) -> None:
    stub = _stub(make_service())
    err = _expect_abort(stub, register_msg("edge-a", BAD_SPECS[case]))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert err.details().startswith("bad registration")
    # The service keeps running and accepts a good registration afterwards.
    edge = Edge(stub, register_msg("edge-a", spec("arm-0")))
    assert edge.next_message().WhichOneof("msg") == "registered"
    edge.close()


def test_duplicate_robot_other_agent_and_takeover(make_service: Callable[..., ControlService]) -> None:
    stub = _stub(make_service())
    first = Edge(stub, register_msg("edge-a", spec("arm-0")))
    try:
        assert first.next_message().WhichOneof("msg") == "registered"
        err = _expect_abort(stub, register_msg("edge-b", spec("arm-0")))
        assert err.code() == grpc.StatusCode.ALREADY_EXISTS
        assert "edge-a" in err.details()
        # The same agent reconnecting takes over; its stale stream is told so.
        second = Edge(stub, register_msg("edge-a", spec("arm-0")))
        assert second.next_message().WhichOneof("msg") == "registered"
        with pytest.raises(grpc.RpcError) as stale:
            first.next_message()
        assert stale.value.code() == grpc.StatusCode.ABORTED
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert info.online and info.agent_id == "edge-a"
        second.close()
    finally:
        first.close()


def test_send_command_reaches_edge(make_service: Callable[..., ControlService]) -> None:
    stub = _stub(make_service())
    edge = Edge(stub, register_msg("edge-a", spec("arm-0"), spec("arm-1")))
    try:
        assert edge.next_message().WhichOneof("msg") == "registered"
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id="arm-1")
        resp = stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5)
        assert resp.delivered and resp.command_id
        down = edge.next_message()
        assert down.WhichOneof("msg") == "command"
        assert down.command.command_id == resp.command_id
        assert down.command.kind == control_pb2.COMMAND_KIND_PAUSE and down.command.robot_id == "arm-1"
        edge.put(control_pb2.EdgeMessage(command_result=control_pb2.CommandResult(command_id=resp.command_id, ok=True)))

        with pytest.raises(grpc.RpcError) as err:
            stub.SendCommand(
                control_pb2.SendCommandRequest(
                    command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESET, robot_id="ghost")
                ),
                timeout=5,
            )
        assert err.value.code() == grpc.StatusCode.NOT_FOUND
        with pytest.raises(grpc.RpcError) as err:
            stub.SendCommand(control_pb2.SendCommandRequest(command=control_pb2.Command(robot_id="arm-0")), timeout=5)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT

        edge.hang_up()
        wait_for(
            lambda: not stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).online, "arm-0 offline"
        )
        resp = stub.SendCommand(
            control_pb2.SendCommandRequest(
                command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESUME, robot_id="arm-0")
            ),
            timeout=5,
        )
        assert not resp.delivered
    finally:
        edge.close()


def test_auth_health_and_metrics(make_service: Callable[..., ControlService]) -> None:
    svc = make_service(metrics_http=True)
    anonymous = _stub(svc, AuthConfig(enabled=False))
    with pytest.raises(grpc.RpcError) as err:
        anonymous.ListRobots(control_pb2.ListRobotsRequest(), timeout=5)
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    wrong = _stub(svc, AuthConfig(token="wrong"))
    with pytest.raises(grpc.RpcError) as err:
        wrong.ListRobots(control_pb2.ListRobotsRequest(), timeout=5)
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert check_health(svc.address, AuthConfig(enabled=False))
    assert check_health(svc.address, AUTH, service="user.v1.Control")
    assert svc.running is not None
    body = urllib.request.urlopen(f"http://127.0.0.1:{svc.running.metrics_port}/metrics", timeout=5).read().decode()
    assert "user_control_robots_online" in body and "user_control_heartbeats_total" in body


def test_a_long_run_keeps_control_state_bounded(make_service: Callable[..., ControlService]) -> None:
    """Many more episodes, commands and reconnects than control keeps: its per-robot history, command history
    and connections stay at their bounds (episodes_kept, commands_kept, live streams), totals count everything."""
    svc = make_service(episodes_kept=4)
    svc.registry.commands_kept = 5
    stub = _stub(svc)
    robots = ("arm-0", "arm-1")
    sent = 0
    for life in range(3):  # the edge reconnects twice (a new stream and connection each time)
        edge = Edge(stub, register_msg("edge-a", *(spec(r) for r in robots)))
        try:
            assert edge.next_message().WhichOneof("msg") == "registered"
            for beat in range(10):
                statuses = []
                for rid in robots:
                    eps = [control_pb2.EpisodeSummary(episode_id=f"{rid}-{sent + k}", length=50, episode_return=1.0)
                           for k in range(3)]  # fmt: skip
                    # the last one of the previous heartbeat again (a re-send is counted once)
                    if sent:
                        eps.insert(0, control_pb2.EpisodeSummary(episode_id=f"{rid}-{sent - 1}", length=50))
                    statuses.append(
                        control_pb2.RobotStatus(
                            robot_id=rid, state=control_pb2.ROBOT_STATE_RUNNING, env_steps=sent + 3, new_episodes=eps
                        )
                    )
                sent += 3
                edge.heartbeat(100 * life + beat, *statuses)
            for k in range(4):  # commands, each answered
                cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id=robots[k % 2])
                resp = stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5)
                down = edge.next_message()
                assert down.command.command_id == resp.command_id
                result = control_pb2.CommandResult(command_id=resp.command_id, ok=True, message="x" * 100)
                edge.put(control_pb2.EdgeMessage(command_result=result))
                done = stub.GetCommand(control_pb2.GetCommandRequest(command_id=resp.command_id), timeout=5)
                wait_for(
                    lambda r=resp: (
                        stub.GetCommand(control_pb2.GetCommandRequest(command_id=r.command_id), timeout=5).results
                    ),
                    "command result kept",
                )
            wait_for(
                lambda n=sent: (
                    stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-1"), timeout=5).status.env_steps == n
                ),
                "heartbeats applied",
            )
        finally:
            edge.close()
        wait_for(lambda: not stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5).online, "offline")
    reg = svc.registry
    for rid in robots:
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id=rid), timeout=5)
        assert [e.episode_id for e in info.recent_episodes] == [f"{rid}-{k}" for k in range(sent - 4, sent)]
        assert all(e.robot_id == rid for e in info.recent_episodes)
        assert len(reg._robots[rid].episodes) == 4
    assert sum(t.episodes for t in reg._totals.values()) == 2 * sent == 180  # every episode counted once
    assert len(reg._commands) == 5 and all(len(c.results) == 1 for c in reg._commands.values())
    assert not reg._conns and len(reg._robots) == 2
    assert done.command.kind == control_pb2.COMMAND_KIND_PAUSE
