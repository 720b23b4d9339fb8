"""The bad inputs reported in issue #10, each pinned by a test against real services."""

from __future__ import annotations

import queue
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from services.replay.server import ReplayService
from services.replay.validate import EpisodeGuard, StepError, validate_step
from tests.test_replay_store import episode, make_step, spec
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc
from user.v1 import tensor_pb2 as tpb

AUTH = AuthConfig(token="test-token")


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[tuple[ControlService, ReplayService]]:
    cfg = StackConfig(auth=AUTH)
    for section in (cfg.control, cfg.replay):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.1
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    yield control, replay
    replay.stop()
    control.stop()


def _insert_error(replay: ReplayService, steps: list) -> grpc.RpcError:
    stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, AUTH))
    reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]
    with pytest.raises(grpc.RpcError) as err:
        list(stub.Insert(iter(reqs), timeout=10))
    return err.value


def test_unknown_command_kind_is_refused_and_the_edge_stays_online(stack) -> None:
    control, _ = stack
    commands: queue.Queue = queue.Queue()
    client = ControlClient(
        control.address, AUTH, "edge-1", [spec("arm-0")], status_fn=lambda: [], on_command=commands.put
    )
    try:
        assert client.wait_registered(10)
        stub = control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))
        for kind in (99, -1, 0):
            with pytest.raises(grpc.RpcError) as err:
                stub.SendCommand(
                    control_pb2.SendCommandRequest(command=control_pb2.Command(kind=kind, robot_id="arm-0")), timeout=5
                )
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        # A known command still goes through, so the edge is alive and listening.
        resp = stub.SendCommand(
            control_pb2.SendCommandRequest(command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE)), timeout=5
        )
        assert resp.delivered
        assert commands.get(timeout=10).kind == control_pb2.COMMAND_KIND_PAUSE
        assert commands.empty()
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert info.online
    finally:
        client.close()


def test_edge_survives_an_unknown_command_from_an_older_or_newer_control() -> None:
    # Control refuses unknown kinds, but an edge may meet a newer control: it answers ok=False and keeps going.
    handled: list = []
    client = ControlClient("127.0.0.1:1", AUTH, "edge-1", [spec("arm-0")], lambda: [], handled.append, start=False)
    client._dispatch(control_pb2.Command(command_id="c1", kind=77))
    client._dispatch(control_pb2.Command(command_id="c2", kind=control_pb2.COMMAND_KIND_RESET))
    assert [c.command_id for c in handled] == ["c2"]
    first = client._results.get_nowait()
    assert (first.command_id, first.ok) == ("c1", False)


@pytest.mark.parametrize(
    "mutate",
    [
        lambda r: setattr(r.robots[0].action, "dtype", 12345),  # unknown enum number
        lambda r: setattr(r, "agent_id", "edge\n"),  # `$` in a pattern matches before a newline
        lambda r: setattr(r.robots[0], "robot_id", "arm-0\n"),
        lambda r: setattr(r, "hostname", "h" * 10_000),
        lambda r: r.robots[0].action.shape.append(2**62),
        lambda r: setattr(r.robots[0].action, "dtype", tpb.DTYPE_INT64),
    ],
)
def test_malformed_registration_is_invalid_argument(stack, mutate) -> None:
    control, _ = stack
    req = control_pb2.RegisterRequest(agent_id="edge-1", hostname="h", robots=[spec("arm-0")])
    mutate(req)
    stub = control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))
    with pytest.raises(grpc.RpcError) as err:
        list(stub.Connect(iter([control_pb2.EdgeMessage(register=req)]), timeout=10))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, err.value.details()


def _registered_edge(control: ControlService) -> ControlClient:
    client = ControlClient(control.address, AUTH, "edge-1", [spec("arm-0")], lambda: [], lambda c: None)
    assert client.wait_registered(10)
    return client


@pytest.mark.parametrize("field", ["step_index", "policy_version"])
def test_out_of_range_uint64_is_invalid_argument(stack, field: str) -> None:
    control, replay = stack
    client = _registered_edge(control)
    try:
        step = make_step("arm-0", "ep", 0)
        setattr(step, field, 2**64 - 1)
        err = _insert_error(replay, [step])
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert field in err.details()
    finally:
        client.close()


def test_episode_semantics_over_the_wire(stack) -> None:
    control, replay = stack
    client = _registered_edge(control)
    try:
        steps = episode("arm-0", "ep", 3)  # 0, 1, 2(last)
        stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, AUTH))
        acks = list(stub.Insert(iter(replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)), timeout=10))
        assert sum(a.stored for a in acks) == 3
        before = stub.Stats(replay_pb2.StatsRequest(), timeout=5).steps
        err = _insert_error(replay, [make_step("arm-0", "ep", 3)])  # after the last step
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "last step" in err.details()
        err = _insert_error(replay, [make_step("arm-0", "ep", 1, last=True)])  # a second, earlier end
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert stub.Stats(replay_pb2.StatsRequest(), timeout=5).steps == before
        # Re-sending the episode is still harmless.
        acks = list(stub.Insert(iter(replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)), timeout=10))
        assert sum(a.duplicates for a in acks) == 3
    finally:
        client.close()


def test_episode_guard_rules() -> None:
    guard = EpisodeGuard(capacity=2)
    for t in (0, 2, 1):  # out of order within an episode is fine
        guard.check(make_step("r", "e", t))
    with pytest.raises(StepError, match="was seen"):
        guard.check(make_step("r", "e", 1, last=True))  # step 2 exists, so 1 cannot be the last
    guard.check(make_step("r", "e", 3, last=True))
    guard.check(make_step("r", "e", 3, last=True))  # re-sent
    guard.check(make_step("r", "e", 0))  # re-sent
    with pytest.raises(StepError, match="after the episode's last step"):
        guard.check(make_step("r", "e", 4))
    # Bounded memory: the oldest episode is forgotten first.
    guard.check(make_step("r", "f", 0))
    guard.check(make_step("r", "g", 0))
    guard.check(make_step("r", "e", 9))


def test_episode_guard_memory_stays_small_and_bounded() -> None:
    """The guard keeps up to 100k episodes (hours of a 64-robot fleet): an entry must stay small, or it is a
    slow leak until full (it was ~600 B with the ids kept as strings; 60 MB at capacity)."""
    guard = EpisodeGuard(capacity=4000)

    def episodes(first: int, n: int) -> None:
        for e in range(first, first + n):
            robot = f"arm-{e % 64}"
            for t in (0, 1, 49):  # the edge's id format: robot, start time in ns, a counter
                guard.check(make_step(robot, f"{robot}-1763924000000000000-{e}", t, last=t == 49))

    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        episodes(0, 4000)
        full = tracemalloc.get_traced_memory()[0] - base
        episodes(4000, 8000)  # past capacity: the oldest are forgotten
        later = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert len(guard) == 4000
    assert full / 4000 < 250, f"{full / 4000:.0f} B per remembered episode"
    # no growth with the count of episodes seen, beyond the dict's hash table sizing under churn (~1.3x)
    assert later < 1.5 * full, f"{full} B at capacity, {later} B after twice as many more episodes"
    with pytest.raises(StepError):  # the newest episodes are still known
        guard.check(make_step("arm-31", "arm-31-1763924000000000000-11999", 50))  # after its last step 49


def test_final_observation_only_on_the_last_step() -> None:
    step = make_step("arm-0", "ep", 0, last=True)
    step.truncated = False
    with pytest.raises(StepError, match="only on the last step"):
        validate_step(step, spec("arm-0"))


@pytest.mark.parametrize("shape", [[], [4], [2, 2, 2, 2], [2, 2, 4]])
def test_an_image_tensor_with_a_non_image_shape_is_a_wire_error(shape: list[int]) -> None:
    # Found by the fuzz suite: an empty shape with ENCODING_JPEG raised IndexError (-> UNKNOWN in Act).
    from user import wire

    tensor = tpb.Tensor(dtype=tpb.DTYPE_UINT8, shape=shape, encoding=tpb.ENCODING_JPEG, data=b"\xff\xd8")
    with pytest.raises(wire.WireError, match="images"):
        wire.from_tensor(tensor)


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_an_image_is_checked_against_its_declared_shape_before_decoding(ext: str) -> None:
    # A 22 kB PNG of zeros decodes to 16 MB: the header's size must match the declared shape first.
    import cv2
    import numpy as np

    from user import wire

    _, buf = cv2.imencode(ext, np.zeros((4000, 4000), np.uint8))
    enc = tpb.ENCODING_PNG if ext == ".png" else tpb.ENCODING_JPEG
    tensor = tpb.Tensor(dtype=tpb.DTYPE_UINT8, shape=[10, 10], encoding=enc, data=buf.tobytes())
    with pytest.raises(wire.WireError, match=r"header says \(4000, 4000\)"):
        wire.from_tensor(tensor)
    small = wire.to_tensor(np.full((10, 10), 7, np.uint8), encoding=enc)
    assert wire.from_tensor(small).shape == (10, 10)
