"""Replay service over real gRPC on 127.0.0.1:0 with a real LMDB in tmp_path (and a real Control service)."""

from __future__ import annotations

import queue
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import prometheus_client
import pytest

from services.control.server import ControlService
from services.replay import server as replay_server
from services.replay.server import ReplayService
from services.replay.store import ReplayStore
from tests import helpers
from tests.helpers import wait_for
from tests.test_replay_store import episode, make_step, spec
from user import wire
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2

AUTH = AuthConfig(token="test-token")


def _cfg(path: Path, **replay: Any) -> StackConfig:
    cfg = StackConfig(auth=AUTH)
    cfg.replay.path = path
    cfg.replay.map_size_mb = 64
    cfg.replay.server.port = 0
    cfg.replay.server.metrics_port = 0
    cfg.replay.server.grace_s = 1.0
    for key, value in replay.items():
        setattr(cfg.replay, key, value)
    return cfg


@pytest.fixture
def specs() -> dict[str, robot_pb2.RobotSpec]:
    return {"arm-0": spec("arm-0"), "arm-1": spec("arm-1")}


@pytest.fixture
def make_service(tmp_path: Path, specs: dict[str, robot_pb2.RobotSpec]) -> Iterator[Callable[..., ReplayService]]:
    started: list[ReplayService] = []

    def make(spec_source: Any = specs.get, **replay: Any) -> ReplayService:
        svc = ReplayService(_cfg(tmp_path / "replay", **replay), spec_source=spec_source, start_metrics=False)
        started.append(svc.start())
        return svc

    yield make
    for svc in started:
        svc.stop()


@pytest.fixture
def service(make_service: Callable[..., ReplayService]) -> ReplayService:
    return make_service()


def stub(svc: ReplayService, auth: AuthConfig = AUTH) -> replay_pb2_grpc.ReplayStub:
    return replay_pb2_grpc.ReplayStub(make_channel(svc.address, auth))


def requests(steps: list[step_pb2.Step], first_seq: int = 0) -> list[replay_pb2.InsertRequest]:
    return [replay_pb2.InsertRequest(seq=first_seq + i, step=s) for i, s in enumerate(steps)]


def insert(svc: ReplayService, steps: list[step_pb2.Step], first_seq: int = 0) -> list[replay_pb2.InsertAck]:
    return list(stub(svc).Insert(iter(requests(steps, first_seq)), timeout=10))


def insert_failing(
    svc: ReplayService, steps: list[step_pb2.Step], first_seq: int = 0
) -> tuple[list[int], grpc.RpcError]:
    """Acked seqs and the error that ended the stream."""
    acked: list[int] = []
    with pytest.raises(grpc.RpcError) as err:
        for ack in stub(svc).Insert(iter(requests(steps, first_seq)), timeout=10):
            acked += ack.seqs
    return acked, err.value


def stats(svc: ReplayService) -> replay_pb2.StatsResponse:
    return stub(svc).Stats(replay_pb2.StatsRequest(), timeout=5)


def _sans_rejected(st: replay_pb2.StatsResponse) -> replay_pb2.StatsResponse:
    out = replay_pb2.StatsResponse()
    out.CopyFrom(st)
    out.rejected = 0
    return out


def _metric(name: str, **labels: str) -> float:
    return prometheus_client.REGISTRY.get_sample_value(name, labels) or 0.0


class OpenStream:
    """An Insert stream the test feeds step by step and keeps open."""

    def __init__(self, svc: ReplayService) -> None:
        self._up: queue.Queue = queue.Queue()
        self.call = stub(svc).Insert(iter(self._up.get, None), timeout=30)

    def send(self, seq: int, step: step_pb2.Step) -> None:
        self._up.put(replay_pb2.InsertRequest(seq=seq, step=step))

    def close(self) -> None:
        self._up.put(None)


# --------------------------------------------------------------------------- tests


def test_acks_follow_commit_and_data_survives_reopen(
    make_service: Callable[..., ReplayService], tmp_path: Path
) -> None:
    service = make_service(commit_max_steps=16)
    stored_before = _metric("user_replay_steps_stored_total")
    steps = episode("arm-0", "e", 40) + episode("arm-1", "f", 10, terminated=True)
    acks = insert(service, steps)
    assert sorted(s for a in acks for s in a.seqs) == list(range(50))
    assert max(len(a.seqs) for a in acks) <= 16  # grouped into transactions of at most commit_max_steps
    assert sum(a.stored for a in acks) == 50 and sum(a.duplicates for a in acks) == 0
    assert _metric("user_replay_steps_stored_total") - stored_before == 50
    service.stop()
    store = ReplayStore(tmp_path / "replay", 64)  # every acknowledged step is on disk
    try:
        st = store.stats()
        assert st["steps"] == 50 and st["transitions"] == 50 and st["episodes"] == 2
        assert st["steps_per_robot"] == {"arm-0": 40, "arm-1": 10}
        assert store.get_spec("arm-0") == spec("arm-0")  # persisted with the steps
        batch = store.sample(64, np.random.default_rng(0))
        np.testing.assert_array_equal(batch["next_observation"]["state"], batch["observation"]["state"] + 1)
    finally:
        store.close()


def test_a_half_full_batch_commits_on_the_timer(service: ReplayService) -> None:
    stream = OpenStream(service)
    try:
        for t in range(3):
            stream.send(t, make_step("arm-0", "e", t))
        acked: list[int] = []
        while len(acked) < 3:  # the client is idle and the stream stays open: acks still come
            acked += next(stream.call).seqs
        assert acked == [0, 1, 2]
        assert stats(service).steps == 3
        stream.send(3, make_step("arm-0", "e", 3, last=True))
        assert list(next(stream.call).seqs) == [3]
    finally:
        stream.close()
    assert list(stream.call) == []  # ends cleanly once the client closes its side
    assert stats(service).transitions == 4


def test_resending_is_idempotent(service: ReplayService) -> None:
    steps = episode("arm-0", "e", 20)
    insert(service, steps)
    before = stats(service)
    acks = insert(service, steps, first_seq=100)
    assert sorted(s for a in acks for s in a.seqs) == list(range(100, 120))
    assert sum(a.duplicates for a in acks) == 20 and sum(a.stored for a in acks) == 0
    after = stats(service)
    assert after.steps == before.steps == 20 and after.transitions == 20
    assert after.duplicates == 20  # persisted in the meta DB (a write, so pages may move)


def _wrong_shape() -> step_pb2.Step:
    step = make_step("arm-0", "e", 3)
    step.observation.tensors["state"].CopyFrom(wire.to_tensor(np.zeros(5, np.float32)))
    return step


def _wrong_dtype() -> step_pb2.Step:
    step = make_step("arm-0", "e", 3)
    step.action.CopyFrom(wire.to_tensor(np.zeros(3, np.int32)))
    return step


def _nan() -> step_pb2.Step:
    step = make_step("arm-0", "e", 3)
    step.observation.tensors["state"].CopyFrom(wire.to_tensor(np.full(6, np.nan, np.float32)))
    return step


def _no_final_observation() -> step_pb2.Step:
    step = make_step("arm-0", "e", 3, last=True)
    step.ClearField("final_observation")
    return step


@pytest.mark.parametrize(
    "bad, reason, message",
    [
        (lambda: make_step("arm-9", "e", 3), "unknown_robot", "unknown robot arm-9"),
        (_wrong_shape, "shape", "shape [5], spec says [6]"),
        (_wrong_dtype, "dtype", "dtype int32, spec says float32"),
        (_nan, "non_finite", "NaN"),
        (_no_final_observation, "final_observation", "required"),
    ],
    ids=["unknown-robot", "wrong-shape", "wrong-dtype", "nan", "no-final-observation"],
)
def test_a_bad_step_is_rejected_and_changes_nothing(
    service: ReplayService, bad: Callable[[], step_pb2.Step], reason: str, message: str
) -> None:
    insert(service, episode("arm-0", "base", 5))
    before = stats(service)
    rejected_before = _metric("user_replay_rejected_total", reason=reason)

    # Alone: INVALID_ARGUMENT naming the seq and the reason; nothing on disk or in the index changes.
    acked, err = insert_failing(service, [bad()], first_seq=7)
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "seq 7" in err.details() and message in err.details()
    assert acked == []
    assert _sans_rejected(stats(service)) == _sans_rejected(before)
    assert stats(service).rejected == before.rejected + 1
    assert _metric("user_replay_rejected_total", reason=reason) == rejected_before + 1

    # After good steps: they are committed and acknowledged first; nothing after the bad one is.
    good = [make_step("arm-0", "e", 0), make_step("arm-0", "e", 1), make_step("arm-0", "e", 2)]
    acked, err = insert_failing(service, [*good, bad(), make_step("arm-0", "e", 4)])
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "seq 3" in err.details()
    assert acked == [0, 1, 2]
    after = stats(service)
    assert after.steps == before.steps + 3 and after.transitions == before.transitions + 2

    # The service keeps serving.
    insert(service, [make_step("arm-0", "e", 3), make_step("arm-0", "e", 4, last=True)], first_seq=10)
    assert stats(service).steps == before.steps + 5
    assert stub(service).Sample(replay_pb2.SampleRequest(batch_size=4), timeout=5).transitions == 10


def test_sample_and_stats(service: ReplayService) -> None:
    with pytest.raises(grpc.RpcError) as err:
        stub(service).Sample(replay_pb2.SampleRequest(batch_size=8), timeout=5)
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    insert(service, episode("arm-0", "e", 10, terminated=True) + episode("arm-1", "f", 6, policy_version=3))
    resp = stub(service).Sample(replay_pb2.SampleRequest(batch_size=32), timeout=5)
    assert resp.transitions == 16
    batch = resp.batch
    state = wire.from_tensor(batch.observation.tensors["state"])
    assert state.shape == (32, 6) and state.dtype == np.float32
    np.testing.assert_array_equal(wire.from_tensor(batch.next_observation.tensors["state"]), state + 1)
    assert wire.from_tensor(batch.action).shape == (32, 3)
    assert wire.from_tensor(batch.reward).dtype == np.float32
    for flag in (batch.terminated, batch.truncated, batch.intervention):
        assert wire.from_tensor(flag).dtype == bool
    assert wire.from_tensor(batch.policy_version).dtype == np.int64

    only = stub(service).Sample(replay_pb2.SampleRequest(batch_size=16, robot_ids=["arm-1"]), timeout=5)
    assert only.transitions == 6 and set(wire.from_tensor(only.batch.policy_version)) == {3}
    for size in (0, replay_server.MAX_SAMPLE + 1):
        with pytest.raises(grpc.RpcError) as err:
            stub(service).Sample(replay_pb2.SampleRequest(batch_size=size), timeout=5)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(grpc.RpcError) as err:
        stub(service).Sample(replay_pb2.SampleRequest(batch_size=4, robot_ids=["nobody"]), timeout=5)
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION

    st = stats(service)
    assert (st.steps, st.transitions, st.episodes, st.duplicates, st.rejected) == (16, 16, 2, 0, 0)
    assert dict(st.steps_per_robot) == {"arm-0": 10, "arm-1": 6}
    assert st.bytes_on_disk > 0


def test_missing_token_is_unauthenticated(service: ReplayService) -> None:
    anonymous = stub(service, AuthConfig(enabled=False))
    wrong = stub(service, AuthConfig(token="wrong"))
    for client in (anonymous, wrong):
        with pytest.raises(grpc.RpcError) as err:
            client.Stats(replay_pb2.StatsRequest(), timeout=5)
        assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    with pytest.raises(grpc.RpcError) as err:
        anonymous.Sample(replay_pb2.SampleRequest(batch_size=1), timeout=5)
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    with pytest.raises(grpc.RpcError) as err:
        list(anonymous.Insert(iter(requests([make_step("arm-0", "e", 0)])), timeout=5))
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert stats(service).steps == 0


def test_shutdown_commits_and_acks_in_flight_steps(make_service: Callable[..., ReplayService], tmp_path: Path) -> None:
    service = make_service(commit_max_delay_ms=60_000.0, commit_max_steps=1000)  # only shutdown commits
    received = _metric("user_replay_steps_received_total")
    stream = OpenStream(service)
    for t in range(5):
        stream.send(t, make_step("arm-0", "e", t))
    wait_for(lambda: _metric("user_replay_steps_received_total") - received == 5, "replay to read 5 steps")
    assert service.servicer.wait_streams(0) is False  # the stream is open, nothing committed yet
    assert stats(service).steps == 0
    service.stop()
    acked: list[int] = []
    with pytest.raises(grpc.RpcError) as err:
        for ack in stream.call:
            acked += ack.seqs
    assert err.value.code() == grpc.StatusCode.UNAVAILABLE  # the edge re-sends anything unacked
    stream.close()
    store = ReplayStore(tmp_path / "replay", 64)
    try:
        assert store.stats()["steps"] == len(acked) == 5
    finally:
        store.close()


def test_a_robot_that_reregistered_with_a_new_spec(
    service: ReplayService, specs: dict[str, robot_pb2.RobotSpec], monkeypatch: pytest.MonkeyPatch
) -> None:
    insert(service, [make_step("arm-0", "e", 0)])  # caches the 6-float spec
    specs["arm-0"] = spec("arm-0", obs_dim=8)
    monkeypatch.setattr(replay_server, "SPEC_REFRESH_S", 0.0)
    acks = insert(service, [make_step("arm-0", "e2", 0, dim=8)], first_seq=1)
    assert [s for a in acks for s in a.seqs] == [1]  # the failing cached spec was refreshed, not trusted


# --------------------------------------------------------------------------- with the real Control service


class _Edge:
    """Registers robots with control over a Connect stream and keeps it open."""

    def __init__(self, address: str, *robots: robot_pb2.RobotSpec) -> None:
        self._up: queue.Queue = queue.Queue()
        self._up.put(
            control_pb2.EdgeMessage(
                register=control_pb2.RegisterRequest(agent_id="edge-t", hostname="test", robots=list(robots))
            )
        )
        stub = control_pb2_grpc.ControlStub(make_channel(address, AUTH))
        self.call = stub.Connect(iter(self._up.get, None), timeout=30)
        assert next(self.call).WhichOneof("msg") == "registered"

    def close(self) -> None:
        self._up.put(None)
        self.call.cancel()


def test_specs_come_from_control_and_survive_it_going_down(
    make_service: Callable[..., ReplayService], tmp_path: Path
) -> None:
    cfg = StackConfig(auth=AUTH)
    cfg.control.server.port = 0
    cfg.control.server.grace_s = 0.5
    control = ControlService(cfg, start_metrics=False).start()
    control_addr = control.address
    edge = _Edge(control_addr, spec("arm-0"))
    try:
        replay = make_service(spec_source=None, control_addr=control_addr, rpc_timeout_s=1.0)
        insert(replay, episode("arm-0", "e", 5)[:4])  # an open episode, ended after the restart
        acked, err = insert_failing(replay, [make_step("arm-7", "e", 0)])
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "unknown robot arm-7" in err.details()
        bad = _wrong_shape()
        acked, err = insert_failing(replay, [bad])
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "shape" in err.details()
        replay.stop()
    finally:
        edge.close()
        control.stop()

    # Control is gone: a restarted replay validates with the spec it persisted ...
    replay = make_service(spec_source=None, control_addr=control_addr, rpc_timeout_s=1.0)
    acks = insert(replay, [make_step("arm-0", "e", 4, last=True)])
    assert sum(a.stored for a in acks) == 1 and stats(replay).transitions == 5
    # ... and a robot it never saw ends the stream UNAVAILABLE (re-send later), not INVALID_ARGUMENT (dropped).
    acked, err = insert_failing(replay, [make_step("arm-0", "g", 0), make_step("arm-5", "e", 0)])
    assert err.code() == grpc.StatusCode.UNAVAILABLE and "arm-5" in err.details()
    assert acked == [0] and stats(replay).rejected == 0


def test_a_restart_remembers_which_episodes_ended(make_service: Callable[..., ReplayService]) -> None:
    """The episode guard is rebuilt from LMDB at open: a real stop + start of the service, then steps that
    break an episode stored before the restart are refused, and nothing changes."""
    first = make_service()
    insert(first, episode("arm-0", "ended", 5) + episode("arm-0", "open", 9)[:3])
    first.stop()
    again = make_service()
    before = stats(again)
    assert before.steps == 8
    for bad, why in (
        (make_step("arm-0", "ended", 5), "after the episode's last step 4"),
        (make_step("arm-0", "ended", 7, last=True), "after the episode's last step 4"),
        (make_step("arm-0", "open", 1, last=True), "step 2 was seen"),
    ):
        acked, err = insert_failing(again, [bad])
        assert acked == [] and err.code() == grpc.StatusCode.INVALID_ARGUMENT and why in err.details()
    assert _sans_rejected(stats(again)) == _sans_rejected(before)
    # what is legal still passes: a re-sent last step, and the open episode going on to its end
    insert(again, [make_step("arm-0", "ended", 4, last=True), make_step("arm-0", "open", 3, last=True)])
    assert stats(again).steps == 9


def test_an_insert_stream_dropped_mid_ack_is_counted_out_when_the_rpc_ends(service: ReplayService) -> None:
    """gRPC may drop the Insert generator at an ack's yield (the edge cancelled while it was being sent) and
    never resume it: the open-stream count that shutdown waits for must still come down when the RPC ends."""
    ctx = helpers.EndingContext()
    up: queue.Queue = queue.Queue()
    for req in requests(episode("arm-0", "drop", 3)):
        up.put(req)
    stream = service.servicer.Insert(iter(up.get, None), ctx)
    assert sorted(next(stream).seqs) == [0, 1, 2]  # committed and acknowledged; the client is still "sending"
    assert service.servicer._streams == 1
    ctx.end()  # `stream` stays suspended and referenced, as gRPC leaves it
    assert service.servicer._streams == 0 and service.servicer.wait_streams(0.1)
    up.put(None)
