"""What the edge does when a service or its config says no: steps replay refuses for the agent's token are set
aside so the steps after them go on, robots of an agent control refuses hold, and a lerobot robot that cannot
be built stops `userctl edge` with one line.

Real Control and Replay servers on 127.0.0.1:0 with a tokens file, real LMDB spools in tmp dirs, the real
MuJoCo sim arm; lerobot devices are scripted subclasses registered through lerobot's own config registry.
"""

from __future__ import annotations

import importlib.util
import logging
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import pytest
import yaml
from lerobot.robots import Robot as LeRobot
from lerobot.robots import RobotConfig as LeRobotConfig

from edge_agent.agent import EdgeAgent
from edge_agent.replay_client import STEPS_QUARANTINED, ReplaySender
from edge_agent.spool import LmdbSpool
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests.helpers import free_port, wait_for
from tests.test_edge_agent import SIM_SPEC, sim_steps
from user.config import AuthConfig, RobotConfig, StackConfig
from user.rpc import Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2

ADMIN = "admin-token-0123456789"
EDGE = "edgetoken00000000001"
AGENT = "pc-1"


def write_tokens(path: Path, robots: list[str]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(yaml.safe_dump([{"token": EDGE, "role": "edge", "agent_id": AGENT, "robots": robots}]))
    tmp.replace(path)


@pytest.fixture
def services(tmp_path: Path) -> Iterator[tuple[ControlService, ReplayService, Path]]:
    """Control and replay with an edge token that may write `arm-*` only."""
    tokens = tmp_path / "tokens.yaml"
    write_tokens(tokens, ["arm-*"])
    cfg = StackConfig(auth=AuthConfig(token=ADMIN, tokens_file=tokens))
    for section in (cfg.control, cfg.replay):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.1
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.commit_max_delay_ms = 5.0
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    try:
        yield control, replay, tokens
    finally:
        replay.stop()
        control.stop()


def edge_cfg(control: ControlService, replay: ReplayService, spool_dir: Path, robot_id: str, mode: str) -> StackConfig:
    cfg = StackConfig(auth=AuthConfig(token=EDGE))
    edge = cfg.edge
    edge.agent_id, edge.control_addr, edge.replay_addr = AGENT, control.address, replay.address
    edge.inference_addr = f"127.0.0.1:{free_port()}"  # no policy: the arm holds, its steps still flow
    edge.mode, edge.action_deadline_ms, edge.metrics_port = mode, 2.0, 0
    edge.robots = [RobotConfig(id=robot_id, kind="sim_reach_arm", params={"max_episode_steps": 20})]
    edge.spool_dir = spool_dir
    return cfg


def replay_stats(replay: ReplayService) -> replay_pb2.StatsResponse:
    stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, AuthConfig(token=ADMIN)))
    return stub.Stats(replay_pb2.StatsRequest(), timeout=5)


def register_and_hang_up(control: ControlService, spec: robot_pb2.RobotSpec) -> None:
    """Control knows the robot's spec from now on (replay validates steps against it); it goes offline."""
    stub = control_pb2_grpc.ControlStub(make_channel(control.address, AuthConfig(token=ADMIN)))
    register = control_pb2.RegisterRequest(agent_id="admin-probe", hostname="h", robots=[spec])
    for _ in stub.Connect(iter([control_pb2.EdgeMessage(register=register)]), timeout=10):
        pass  # `registered`; the stream ends once control has read our end


def edge_may_write(replay: ReplayService, robot_id: str) -> bool:
    """Whether replay lets the edge token write the robot now: a step it may write but that is not valid for
    the spec is INVALID_ARGUMENT (stores nothing); one it may not is PERMISSION_DENIED."""
    bad = sim_steps(1, robot_id=robot_id)[0]
    bad.action.shape[:] = [7]  # not the spec's action shape
    stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, AuthConfig(token=EDGE)))
    try:
        for _ in stub.Insert(iter([replay_pb2.InsertRequest(seq=1, step=bad)]), timeout=10):
            pass
    except grpc.RpcError as err:
        return err.code() != grpc.StatusCode.PERMISSION_DENIED
    raise AssertionError("replay stored a step with the wrong action shape")


def quarantined_metric(robot_id: str) -> float:
    return STEPS_QUARANTINED.labels(robot_id, "permission_denied")._value.get()


# --------------------------------------------------------------------------- the spool


def test_steps_set_aside_leave_the_outbox_keep_their_table_and_come_back_when_the_spool_reopens(
    tmp_path: Path,
) -> None:
    steps = sim_steps(5)
    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    seqs = [spool.put(step, table="demos" if i in (1, 4) else "") for i, step in enumerate(steps)]
    total = spool.nbytes
    assert spool.quarantine([2, 3, 99]) == 2  # 99 is not kept: nothing to set aside
    assert spool.count == 3 and spool.quarantined == 2
    assert spool.nbytes == total - steps[1].ByteSize() - steps[2].ByteSize()
    assert [r.seq for r in spool.read(0, 10)] == [1, 4, 5]  # no longer sent
    assert spool.ack([2]) == 0 and spool.quarantined == 2  # a stray ack does not touch a step set aside
    assert spool.release_quarantined() == 2  # replay takes their robot's steps again: back in seq order
    assert [r.seq for r in spool.read(0, 10)] == seqs and spool.nbytes == total and spool.quarantined == 0
    assert spool.quarantine([2, 3]) == 2
    spool.close()

    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)  # the next start tries them again
    kept = spool.read(0, 10)
    assert [r.seq for r in kept] == seqs and [r.step for r in kept] == steps
    assert [r.table for r in kept] == ["", "demos", "", "", "demos"]
    assert spool.count == 5 and spool.quarantined == 0 and spool.nbytes == total
    assert spool.put(steps[0]) == 6  # seqs are still never reused
    spool.close()


def test_steps_set_aside_make_room_first_so_they_never_make_the_robots_hold(tmp_path: Path) -> None:
    steps = sim_steps(9)[1:]  # step 0 is a little smaller (step_index 0 is not written)
    size = max(s.ByteSize() for s in steps)
    spool = LmdbSpool(tmp_path / "spool", max_bytes=2 * size + size // 2, policy="pause")
    spool.put(steps[0])
    spool.put(steps[1])
    assert spool.full and not spool.accepting
    spool.quarantine([1, 2])  # refused for this token: the robots must not wait for them
    assert spool.accepting and spool.count == 0 and spool.quarantined == 2
    for step in steps[2:4]:
        spool.put(step)  # room is made by dropping the oldest steps set aside, counted
    assert spool.count == 2 and spool.quarantined == 0 and spool.dropped == 2
    assert [r.seq for r in spool.read(0, 10)] == [3, 4]
    spool.close()
    reopened = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    assert reopened.count == 2 and reopened.dropped == 2 and reopened.quarantined == 0
    reopened.close()


# --------------------------------------------------------------------------- replay refuses a robot's steps


def test_steps_replay_refuses_for_the_token_are_set_aside_so_later_steps_go_on_and_stored_once_allowed(
    tmp_path: Path, services: tuple[ControlService, ReplayService, Path]
) -> None:
    control, replay, tokens = services
    spool_dir = tmp_path / "spool"
    # An earlier life spooled steps of a robot the token may not write (an older edge, or a token narrowed
    # while it ran), then steps of one it may: replay refuses the first with PERMISSION_DENIED every time.
    refused = sim_steps(120, robot_id="other-0")
    spool = LmdbSpool(spool_dir / AGENT, 1 << 26)
    for step in refused:
        spool.put(step)
    spool.close()
    register_and_hang_up(control, make_spec("other-0"))  # control knows it: only the token stands in the way
    before = quarantined_metric("other-0")
    agent = EdgeAgent(edge_cfg(control, replay, spool_dir, "arm-0", mode="fast"))
    agent.start()
    try:
        wait_for(lambda: replay_stats(replay).steps_per_robot["arm-0"] >= 100, "arm-0's steps stored", limit_s=120)
        assert agent.sender.quarantined == len(refused) and agent.sender.rejected == 0
        assert quarantined_metric("other-0") - before == len(refused)
        assert agent.sender.outbox.quarantined == len(refused)
    finally:
        agent.stop()
    assert agent.sender.unacked == 0  # every other step was acknowledged: nothing blocked
    stats = replay_stats(replay)
    assert stats.steps_per_robot["other-0"] == 0 and stats.rejected == 0
    assert stats.steps_per_robot["arm-0"] == agent.loops["arm-0"].env_steps

    # The operator lets the token write the robot; the next start sends what was set aside, stored once.
    write_tokens(tokens, ["arm-*", "other-*"])
    wait_for(lambda: edge_may_write(replay, "other-0"), "replay re-reads the tokens file")
    sender = ReplaySender(
        replay.address, AuthConfig(token=EDGE), outbox=LmdbSpool(spool_dir / AGENT, 1 << 26), backoff=Backoff(0.05, 0.5)
    )
    try:
        assert sender.unacked == len(refused)
        assert sender.flush(60)
        assert sender.quarantined == 0 and sender.outbox.quarantined == 0
    finally:
        sender.close()
    stats = replay_stats(replay)
    assert stats.steps_per_robot["other-0"] == len(refused) and stats.duplicates == 0


def make_spec(robot_id: str) -> robot_pb2.RobotSpec:
    spec = robot_pb2.RobotSpec()
    spec.CopyFrom(SIM_SPEC)
    spec.robot_id = robot_id
    return spec


# --------------------------------------------------------------------------- control refuses the agent


def test_robots_of_an_agent_control_refuses_hold_and_act_once_the_token_allows_them(
    tmp_path: Path, services: tuple[ControlService, ReplayService, Path]
) -> None:
    control, replay, tokens = services
    agent = EdgeAgent(edge_cfg(control, replay, tmp_path / "spool", "other-0", mode="realtime"))
    agent.start()
    loop = agent.loops["other-0"]
    try:
        refusal = wait_for(lambda: agent.control.refusal, "control's refusal")
        assert refusal[0] == grpc.StatusCode.PERMISSION_DENIED
        assert loop.held_by_lease and loop.lease.reason.startswith("control refused this agent (PERMISSION_DENIED)")
        wait_for(lambda: loop.scheduler.ticks >= 20, "the loop ticks")  # it ticks, holding
        assert loop.env_steps == 0 and agent.sender.outbox.count == 0  # no actions, no steps, nothing spooled
        assert loop.status(drain=False).state == control_pb2.ROBOT_STATE_PAUSED

        write_tokens(tokens, ["arm-*", "other-*"])  # control re-reads the file; the slow retry registers
        wait_for(lambda: agent.control.registered is not None, "registered", limit_s=120)
        assert agent.control.refusal is None
        wait_for(lambda: replay_stats(replay).steps_per_robot["other-0"] >= 20, "other-0 collects", limit_s=120)
        assert not loop.held_by_lease
    finally:
        agent.stop()
    # Replay may refuse the first steps a moment longer (its Insert stream was opened under the old token):
    # they are set aside, then sent once it takes the robot's steps. Every step the robot took is stored.
    assert agent.sender.unacked == 0 and agent.sender.outbox.quarantined == 0 and agent.sender.rejected == 0
    assert replay_stats(replay).steps_per_robot["other-0"] == loop.env_steps


# --------------------------------------------------------------------------- lerobot robots that cannot be built


@LeRobotConfig.register_subclass("user_test_driverless_arm")
@dataclass(kw_only=True)
class DriverlessArmConfig(LeRobotConfig):
    port: str = "/dev/ttyNONE"


class DriverlessArm(LeRobot):
    """Built like a lerobot arm whose motor SDK is not installed: lerobot's bus raises ImportError in __init__."""

    config_class = DriverlessArmConfig
    name = "user_test_driverless_arm"

    def __init__(self, config: DriverlessArmConfig) -> None:
        raise ImportError("'fake-servo-sdk' is required but not installed. Install it with: pip install fake")

    # The rest of lerobot's Robot interface, never reached.
    @property
    def observation_features(self) -> dict:
        return {}

    @property
    def action_features(self) -> dict:
        return {}

    @property
    def is_connected(self) -> bool:
        return False

    @property
    def is_calibrated(self) -> bool:
        return True

    def connect(self, calibrate: bool = True) -> None:
        pass

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict[str, Any]:
        return {}

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        return action

    def disconnect(self) -> None:
        pass


def userctl_edge(overrides: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """`userctl edge` in this process: (exit code, stderr)."""
    from user import cli

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    on_signal = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    args = ["edge", "--set", "auth.token=t", "--set", "edge.agent_id=pc-2", "--set", "edge.metrics_port=0"]
    try:  # `userctl edge` sets up its logging and signal handlers here: put pytest's back after it
        code = cli.main(args + [a for o in overrides for a in ("--set", o)])
    finally:
        root.handlers[:], root.level = handlers, level
        for sig, handler in on_signal.items():
            signal.signal(sig, handler)
    return code, capsys.readouterr().err


SIM = "{id: arm-1, kind: sim_reach_arm}"
NO_FEETECH = importlib.util.find_spec("scservo_sdk") is None


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ("{type: nosuch}", "edge.robots[1].params.type: Value error, unknown lerobot type 'nosuch'; known: ["),
        (
            "{type: user_test_driverless_arm, config: {prot: x}}",
            "edge.robots[1].params.config: Value error, The fields `prot` are not valid",
        ),
        (
            "{type: user_test_driverless_arm}",
            "edge.robots[1] (robot 'real-1', kind lerobot): a driver it needs is missing: 'fake-servo-sdk' is "
            "required but not installed",
        ),
        pytest.param(
            "{type: so101_follower, config: {port: /dev/ttyNONE}}",
            "edge.robots[1] (robot 'real-1', kind lerobot): a driver it needs is missing: 'feetech-servo-sdk'",
            marks=pytest.mark.skipif(not NO_FEETECH, reason="feetech-servo-sdk is installed here"),
        ),
    ],
    ids=["unknown-type", "bad-config", "missing-driver", "so101-without-feetech"],
)
def test_a_lerobot_robot_that_cannot_be_built_stops_the_edge_in_one_line_with_exit_2(
    entry: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robots = f"edge.robots=[{SIM}, {{id: real-1, kind: lerobot, params: {entry}}}]"
    code, err = userctl_edge([robots, f"edge.spool_dir={tmp_path / 'spool'}"], capsys)
    assert code == 2, err
    assert f"userctl edge: {message}" in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "spool").exists()  # it stopped before opening anything
