"""Control against hostile or broken input over real gRPC on 127.0.0.1:0 (real SQLite in tmp_path): streams that
never register, values too long to echo, heartbeats with NaN, oversized or foreign episode summaries, reused
command ids, experiment definitions of absurd size and image features no camera produces."""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import prometheus_client
import pytest

from services.control import server
from services.control.server import ControlService
from tests.helpers import wait_for
from user import spec as contract
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, robot_pb2
from user.v1 import tensor_pb2 as tpb

AUTH = AuthConfig(token="test-token-0123456789")
HUGE = "x" * 20000  # echoed in a status it would overflow gRPC's 16 KiB header limit
SHORT_DETAILS = 1000  # no status of control quotes more of a client's value than this
REJECTED = "user_control_heartbeat_rejected_total"


def _cfg(tmp_path: Path) -> StackConfig:
    cfg = StackConfig(auth=AUTH)
    cfg.control.server.port = 0
    cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 1.0
    cfg.control.heartbeat_interval_s = 0.1
    cfg.control.state_path = tmp_path / "control.sqlite"
    return cfg


@pytest.fixture
def make_service(tmp_path: Path) -> Iterator[Callable[[], ControlService]]:
    started: list[ControlService] = []

    def make() -> ControlService:
        svc = ControlService(_cfg(tmp_path), start_metrics=False).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


def _stub(svc: ControlService) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(svc.address, AUTH))


def spec(robot_id: str = "arm-0", **over: Any) -> robot_pb2.RobotSpec:
    s = robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="sim_reach_arm",  # the default experiment's kind
        action=robot_pb2.ActionSpace(shape=[3], low=[-1, -1, -1], high=[1, 1, 1], dtype=tpb.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[6])],
        control_rate_hz=10.0,
        max_episode_steps=50,
    )
    for key, value in over.items():
        if key == "observation":
            s.observation.extend(value)
        else:
            setattr(s, key, value)
    return s


def register(agent_id: str, *specs: robot_pb2.RobotSpec) -> control_pb2.EdgeMessage:
    return control_pb2.EdgeMessage(register=control_pb2.RegisterRequest(agent_id=agent_id, robots=list(specs)))


class Edge:
    """The edge side of one Connect stream: put() messages up, next() reads what comes down."""

    def __init__(self, stub: control_pb2_grpc.ControlStub, first: control_pb2.EdgeMessage | None) -> None:
        self._up: queue.Queue[control_pb2.EdgeMessage | None] = queue.Queue()
        if first is not None:
            self._up.put(first)
        self.call = stub.Connect(self._requests(), timeout=60)

    def _requests(self) -> Iterator[control_pb2.EdgeMessage]:
        while (msg := self._up.get()) is not None:
            yield msg

    def put(self, msg: control_pb2.EdgeMessage) -> None:
        self._up.put(msg)

    def heartbeat(self, *statuses: control_pb2.RobotStatus) -> None:
        self.put(control_pb2.EdgeMessage(heartbeat=control_pb2.Heartbeat(seq=1, robots=list(statuses))))

    def next(self) -> control_pb2.ControlMessage:
        return next(self.call)

    def close(self) -> None:
        self._up.put(None)
        self.call.cancel()


def _refusal(call: Callable[[], Any]) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        call()
    return err.value


def _metric(name: str, **labels: str) -> float:
    return prometheus_client.REGISTRY.get_sample_value(name, labels) or 0.0


def _first_message_readers() -> int:
    return sum(t.name == "control-first-message" for t in threading.enumerate())


# --------------------------------------------------------------------------- 1: a stream that never registers


def test_a_stream_that_never_registers_ends_and_frees_its_thread(
    make_service: Callable[[], ControlService], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(server, "REGISTER_TIMEOUT_S", 0.2)
    svc = make_service()
    stub = _stub(svc)
    silent = Edge(stub, None)  # its client deadline (60 s) is far off: only control can end it
    try:
        err = _refusal(silent.next)
        assert err.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        assert "no register within 0.2 s" in err.details()
        wait_for(lambda: _first_message_readers() == 0, "the first-message reader to end with its stream")
    finally:
        silent.close()

    # A stream that registers in time lives on well past the register deadline.
    edge = Edge(stub, register("edge-a", spec("arm-0")))
    try:
        assert edge.next().WhichOneof("msg") == "registered"
        registered = time.monotonic()

        def beat_past_deadline() -> bool:
            edge.heartbeat(control_pb2.RobotStatus(robot_id="arm-0", env_steps=1))
            return time.monotonic() - registered > 5 * svc.servicer.register_timeout_s

        wait_for(beat_past_deadline, "time past the register deadline", poll_s=0.1)
        info = stub.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
        assert info.online and info.status.env_steps == 1
    finally:
        edge.close()


# --------------------------------------------------------------------------- 2: nothing unbounded echoed


def _short_invalid(err: grpc.RpcError, names: str) -> None:
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, err.details()
    assert names in err.details() and len(err.details()) < SHORT_DETAILS


@pytest.mark.parametrize(
    ("label", "message", "names"),
    [
        ("agent_id", register(HUGE, spec("arm-0")), "agent_id"),
        ("robot_id", register("edge-a", spec(HUGE)), "robot_id"),
        ("duplicate ids", register("edge-a", spec("arm-0"), spec("arm-0")), "['arm-0'] more than once"),
        (
            "feature name",
            register("edge-a", spec(observation=[robot_pb2.FeatureSpec(name=HUGE)])),
            "observation[1].name",
        ),
        ("kind", register("edge-a", spec(kind=HUGE)), "kind is longer than 256 bytes"),
        ("task", register("edge-a", spec(task=HUGE)), "task is longer than 4096 bytes"),
    ],
)
def test_registration_refusals_name_the_field_without_echoing_it(
    make_service: Callable[[], ControlService], label: str, message: control_pb2.EdgeMessage, names: str
) -> None:
    edge = Edge(_stub(make_service()), message)
    try:
        _short_invalid(_refusal(edge.next), names)
    finally:
        edge.close()


def test_unary_refusals_do_not_echo_long_values(make_service: Callable[[], ControlService]) -> None:
    stub = _stub(make_service())
    err = _refusal(lambda: stub.GetRobot(control_pb2.GetRobotRequest(robot_id=HUGE), timeout=5))
    assert err.code() == grpc.StatusCode.NOT_FOUND and len(err.details()) < SHORT_DETAILS
    cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id=HUGE)
    _short_invalid(
        _refusal(lambda: stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5)), "robot_id"
    )
    for worker, names in [
        (control_pb2.WorkerInfo(worker_id=HUGE, kind="learner"), "worker_id"),
        (control_pb2.WorkerInfo(worker_id="w", kind=HUGE), "kind"),
        (control_pb2.WorkerInfo(worker_id="w", kind="learner", preparing=[HUGE] * 3), "preparing"),
    ]:
        req = control_pb2.RegisterWorkerRequest(worker=worker)
        _short_invalid(_refusal(lambda req=req: stub.RegisterWorker(req, timeout=5)), names)


# --------------------------------------------------------------------------- 3: heartbeats


def _episode(episode_id: str, **kw: Any) -> control_pb2.EpisodeSummary:
    return control_pb2.EpisodeSummary(episode_id=episode_id, **{"length": 10, "episode_return": 1.0, **kw})


BAD_EPISODES = {
    "episode_return": [_episode("nan", episode_return=float("nan")), _episode("inf", episode_return=float("inf"))],
    "length": [_episode("long", length=4_000_000_000)],
    "episode_id": [_episode("e" * 100_000), _episode(""), _episode("a/b")],
    "robot_id": [_episode("ghost-ep", robot_id="ghost"), _episode("other-ep", robot_id="arm-1")],
    "intervention_steps": [_episode("helped", intervention_steps=11)],
}


def test_bad_heartbeat_parts_are_dropped_and_counted_and_the_stream_goes_on(
    make_service: Callable[[], ControlService],
) -> None:
    svc = make_service()
    stub = _stub(svc)
    before = {r: _metric(REJECTED, reason=r) for r in [*BAD_EPISODES, "state", "rate", "foreign_robot"]}
    edge = Edge(stub, register("edge-a", spec("arm-0"), spec("arm-1")))
    try:
        assert edge.next().WhichOneof("msg") == "registered"
        good = [_episode("good-1", episode_return=2.0, robot_id="arm-0"), _episode("good-2", episode_return=4.0)]
        bad = [ep for eps in BAD_EPISODES.values() for ep in eps]
        running = control_pb2.ROBOT_STATE_RUNNING
        edge.heartbeat(
            control_pb2.RobotStatus(robot_id="arm-0", state=99, env_steps=5, new_episodes=[good[0], *bad, good[1]]),
            control_pb2.RobotStatus(robot_id="arm-1", state=running, env_steps_per_s=float("nan"), env_steps=5),
            control_pb2.RobotStatus(robot_id="not-mine", state=running),
        )
        # The stream lives on: a later good heartbeat is applied.
        edge.heartbeat(control_pb2.RobotStatus(robot_id="arm-1", state=running, env_steps=7, env_steps_per_s=3.0))
        get = lambda rid: stub.GetRobot(control_pb2.GetRobotRequest(robot_id=rid), timeout=5)  # noqa: E731
        wait_for(lambda: get("arm-1").status.env_steps == 7, "the good heartbeat after the bad one")

        arm0 = get("arm-0")
        assert [(e.episode_id, e.robot_id) for e in arm0.recent_episodes] == [("good-1", "arm-0"), ("good-2", "arm-0")]
        assert arm0.status.state == running and arm0.status.env_steps == 0  # the bad status was not stored
        info = stub.GetExperiment(control_pb2.GetExperimentRequest(name="default"), timeout=5)
        assert (info.episodes, info.mean_return) == (2, 3.0)
        # At least (other tests' streams in this process may count too; the stores above are this stream's).
        for reason, episodes in BAD_EPISODES.items():
            assert _metric(REJECTED, reason=reason) - before[reason] >= len(episodes), reason
        for reason in ("state", "rate", "foreign_robot"):
            assert _metric(REJECTED, reason=reason) - before[reason] >= 1, reason
    finally:
        edge.close()
    svc.stop()

    # Nothing bad reached SQLite: a restarted control totals the same.
    again = _stub(make_service())
    info = again.GetExperiment(control_pb2.GetExperimentRequest(name="default"), timeout=5)
    assert (info.episodes, info.mean_return) == (2, 3.0)
    robot = again.GetRobot(control_pb2.GetRobotRequest(robot_id="arm-0"), timeout=5)
    assert [e.episode_id for e in robot.recent_episodes] == ["good-1", "good-2"]


# --------------------------------------------------------------------------- 4: command ids


def test_a_reused_command_id_is_idempotent_for_the_same_command_and_refused_for_another(
    make_service: Callable[[], ControlService],
) -> None:
    stub = _stub(make_service())
    edge = Edge(stub, register("edge-a", spec("arm-0")))
    try:
        assert edge.next().WhichOneof("msg") == "registered"
        pause = control_pb2.Command(command_id="cmd-1", kind=control_pb2.COMMAND_KIND_PAUSE, robot_id="arm-0")
        first = stub.SendCommand(control_pb2.SendCommandRequest(command=pause), timeout=5)
        assert (first.command_id, first.delivered, list(first.agents)) == ("cmd-1", True, ["edge-a"])
        assert edge.next().command == pause
        edge.put(control_pb2.EdgeMessage(command_result=control_pb2.CommandResult(command_id="cmd-1", ok=True)))
        wait_for(lambda: stub.GetCommand(control_pb2.GetCommandRequest(command_id="cmd-1"), timeout=5).results)

        again = stub.SendCommand(control_pb2.SendCommandRequest(command=pause, wait_result_s=5), timeout=10)
        assert (again.command_id, again.delivered, list(again.agents)) == ("cmd-1", True, ["edge-a"])
        assert [r.ok for r in again.results] == [True]  # the first send's result

        reset = control_pb2.Command(command_id="cmd-1", kind=control_pb2.COMMAND_KIND_RESET, robot_id="arm-0")
        err = _refusal(lambda: stub.SendCommand(control_pb2.SendCommandRequest(command=reset), timeout=5))
        assert err.code() == grpc.StatusCode.ALREADY_EXISTS and "cmd-1" in err.details()
        status = stub.GetCommand(control_pb2.GetCommandRequest(command_id="cmd-1"), timeout=5)
        assert status.command == pause and [r.ok for r in status.results] == [True]

        # The edge got the PAUSE once: the next thing down the stream is a new command.
        marker = control_pb2.Command(command_id="cmd-2", kind=control_pb2.COMMAND_KIND_RESUME, robot_id="arm-0")
        stub.SendCommand(control_pb2.SendCommandRequest(command=marker), timeout=5)
        assert edge.next().command == marker
    finally:
        edge.close()


# --------------------------------------------------------------------------- 5: experiment sizes


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"hidden": [1e12]}, "hidden.0"),
        ({"hidden": [16384] * 3}, "hidden"),
        ({"hidden": [64] * 17}, "hidden"),
        ({"batch_size": 10**7}, "batch_size"),
        ({"num_critics": 10**6}, "num_critics"),
        ({"channels": [10**6, 32, 32]}, "channels.0"),
        ({"image_size": 10**6}, "image_size"),
        ({"n_step": 10**6}, "n_step"),
    ],
)
def test_define_refuses_absurd_sizes_naming_the_param(
    make_service: Callable[[], ControlService], params: dict[str, Any], field: str
) -> None:
    stub = _stub(make_service())
    definition = json.dumps({"name": "big", "algorithm": {"kind": "sac", "params": params}})
    err = _refusal(lambda: stub.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=definition)))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert f"definition.algorithm.params.{field}:" in err.details()
    assert "big" not in [e.name for e in stub.ListExperiments(control_pb2.ListExperimentsRequest()).experiments]


def test_every_algorithms_defaults_and_sane_sizes_still_define(make_service: Callable[[], ControlService]) -> None:
    stub = _stub(make_service())
    for i, (kind, params) in enumerate(
        [
            ("sac", {}),
            ("sac", {"hidden": [1024, 1024, 1024], "batch_size": 4096, "num_critics": 10, "image_size": 128}),
            ("rlpd", {}),
            ("bc", {"hidden": [512, 512]}),
            ("flow_bc", {"hidden": 512, "horizon": 16}),
        ]
    ):
        definition = json.dumps({"name": f"ok-{i}", "algorithm": {"kind": kind, "params": params}})
        info = stub.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=definition), timeout=30)
        assert info.state == control_pb2.EXPERIMENT_STATE_RUNNING


# --------------------------------------------------------------------------- 6: image features


@pytest.mark.parametrize(
    ("dtype", "shape"),
    [
        (tpb.DTYPE_FLOAT32, [5]),
        (tpb.DTYPE_FLOAT32, [64, 64, 3]),
        (tpb.DTYPE_UINT8, [5]),
        (tpb.DTYPE_UINT8, [64, 64, 2]),
        (tpb.DTYPE_UINT8, [2, 64, 64, 3]),
    ],
)
def test_an_image_feature_no_camera_produces_is_refused_at_registration(
    make_service: Callable[[], ControlService], dtype: int, shape: list[int]
) -> None:
    odd = robot_pb2.FeatureSpec(name="camera.front", dtype=dtype, shape=shape, is_image=True)
    edge = Edge(_stub(make_service()), register("edge-a", spec(observation=[odd])))
    try:
        _short_invalid(_refusal(edge.next), "'camera.front' has is_image set")
    finally:
        edge.close()


def test_camera_shaped_images_are_accepted() -> None:
    for shape in ([64, 64], [64, 64, 1], [480, 640, 3], [8, 8, 4]):
        cam = robot_pb2.FeatureSpec(name="camera.front", dtype=tpb.DTYPE_UINT8, shape=shape, is_image=True)
        contract.validate_spec(spec(observation=[cam]))
