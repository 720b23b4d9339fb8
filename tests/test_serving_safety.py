"""Serving safety: no non-finite action ever reaches a robot, bad or oversized requests are refused before they
cost memory or batch time, and per-experiment state is reported per experiment. Real inference servers on
127.0.0.1 ephemeral ports; the edge's RobotLoop with a recording robot."""

from __future__ import annotations

import functools
import tracemalloc
from collections.abc import Iterator
from typing import Any

import grpc
import numpy as np
import pytest
import torch
import zstandard
from prometheus_client import REGISTRY

from edge_agent.agent import RobotLoop
from edge_agent.policy_source import PolicySource
from edge_agent.robot import Observation, Robot
from edge_agent.teleop import Teleoperator
from services.inference import server as server_module
from services.inference.server import InferenceService
from tests import helpers
from tests.helpers import ListSink
from user import spec as spec_contract
from user import wire
from user.config import AuthConfig, StackConfig
from user.policies.flow_vla import FlowVlaConfig, policy_spec, random_weights
from user.policy import MAX_IMAGE_SIDE, build_policy
from user.registry import PluginParams
from user.rpc import make_channel
from user.v1 import inference_pb2, inference_pb2_grpc, robot_pb2
from user.v1 import tensor_pb2 as tpb
from user.weights import WeightSet

torch.set_num_threads(1)

AUTH = AuthConfig(token="test-token")
SAC = {
    "obs_keys": ["state"],
    "obs_dim": 15,
    "action_dim": 3,
    "hidden": [16, 16],
    "action_low": [-1.0, -1.0, -1.0],
    "action_high": [1.0, 1.0, 1.0],
}
sac_weights = functools.partial(helpers.random_weights, SAC)
VLA = FlowVlaConfig(
    image_keys=["camera.front"],
    state_keys=["state"],
    state_dim=5,
    action_dim=3,
    action_low=[-1.0, -1.0, 0.0],
    action_high=[1.0, 1.0, 0.5],
    horizon=4,
    hidden=32,
    flow_steps=3,
)


def _cfg(experiments: list[dict[str, Any]] | None = None) -> StackConfig:
    extra = {"experiments": experiments} if experiments else {}
    cfg = StackConfig.model_validate({"auth": AUTH.model_dump(), **extra})
    cfg.inference.server.port = cfg.inference.server.metrics_port = 0
    cfg.inference.server.grace_s = 0.5
    return cfg


@pytest.fixture
def service() -> Iterator[InferenceService]:
    svc = InferenceService(_cfg(), policy_source="manual", start_metrics=False).start()
    yield svc
    svc.stop()


@pytest.fixture
def stub(service: InferenceService) -> inference_pb2_grpc.InferenceStub:
    return inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))


def _request(robot_id: str = "arm-0", tensors: dict[str, tpb.Tensor] | None = None, **arrays: np.ndarray) -> Any:
    tmap = wire.to_tensor_map(arrays or {"state": np.zeros(15, np.float32)})
    for key, tensor in (tensors or {}).items():
        tmap.tensors[key].CopyFrom(tensor)
    return inference_pb2.ActRequest(robot_id=robot_id, observation=tmap, deterministic=True)


def _refused(stub: inference_pb2_grpc.InferenceStub, request: Any) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        stub.Act(request, timeout=30)
    return err.value


def _metric(name: str, labels: dict[str, str]) -> float:
    return REGISTRY.get_sample_value(name, labels) or 0.0


# --------------------------------------------------------------------------- 1: non-finite actions and weights


def test_a_policy_that_produces_nan_gets_an_error_never_the_nan(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub
) -> None:
    """A finite but huge state overflows the MLP to NaN: that robot gets INTERNAL (counted), never an OK with NaN;
    the robot batched with it is answered, and the next ordinary request is served."""
    weights = sac_weights(version=2)
    huge = np.full(15, -3e38, np.float32)  # overflows these seeded weights to inf - inf = NaN
    policy = build_policy(weights.policy, weights.tensors, 2)
    assert np.isnan(policy.act({"state": huge[None]}, deterministic=True)).all()
    service.load_weights(weights)
    before = _metric("user_inference_non_finite_actions_total", {"experiment": "default"})
    err = _refused(stub, _request(state=huge))
    assert err.code() == grpc.StatusCode.INTERNAL and "non-finite" in err.details(), err.details()
    assert _metric("user_inference_non_finite_actions_total", {"experiment": "default"}) == before + 1
    batch = inference_pb2.ActBatchRequest(requests=[_request("arm-0", state=huge), _request("arm-1")])
    results = stub.ActBatch(batch, timeout=30).results
    assert [r.code for r in results] == [grpc.StatusCode.INTERNAL.value[0], 0], [r.message for r in results]
    assert np.isfinite(wire.from_tensor(results[1].response.action)).all()
    assert stub.Act(_request(), timeout=30).policy_version == 2


def test_weights_with_nan_or_inf_are_refused_and_the_old_policy_serves(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub
) -> None:
    service.load_weights(sac_weights(version=1))
    for bad_value in (np.nan, np.inf):
        bad = sac_weights(version=2)
        name = next(iter(bad.tensors))
        bad.tensors[name] = bad.tensors[name].copy()
        bad.tensors[name].flat[0] = bad_value
        with pytest.raises(ValueError, match="non-finite"):
            service.load_weights(bad)
    response = stub.Act(_request(), timeout=30)
    assert response.policy_version == 1 and np.isfinite(wire.from_tensor(response.action)).all()


def test_clip_action_never_maps_nan_to_a_joint_limit() -> None:
    """Position limits [10, 90]: the old NaN -> 0 -> clipped to 10 was a jump to a limit. Where 0 is no position
    within the limits there is no safe substitute: ValueError. Where 0 is in range (velocity control) NaN is 0."""
    position = robot_pb2.RobotSpec(
        robot_id="arm", action=robot_pb2.ActionSpace(shape=[3], low=[10.0] * 3, high=[90.0] * 3)
    )
    with pytest.raises(ValueError, match="non-finite"):
        spec_contract.clip_action(position, np.array([61.0, np.nan, np.inf], np.float32))
    np.testing.assert_array_equal(spec_contract.clip_action(position, np.array([61.0, 5.0, 95.0])), [61, 10, 90])
    velocity = robot_pb2.RobotSpec(robot_id="arm", action=robot_pb2.ActionSpace(shape=[2], low=[-1, -1], high=[1, 1]))
    np.testing.assert_array_equal(spec_contract.clip_action(velocity, np.array([np.nan, 3.0])), [0.0, 1.0])


class RecordingRobot(Robot):
    """A position-controlled arm whose plug-in forgets to clip: records every act() and hold()."""

    def __init__(self) -> None:
        self._spec = robot_pb2.RobotSpec(
            robot_id="pos-0",
            kind="recording",
            action=robot_pb2.ActionSpace(shape=[3], low=[10.0] * 3, high=[90.0] * 3, dtype=tpb.DTYPE_FLOAT32),
            observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[3])],
            control_rate_hz=100.0,
        )
        self.acted: list[np.ndarray] = []
        self.holds = 0

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    def reset(self, seed: int | None = None) -> Observation:
        return self.observe()

    def observe(self) -> Observation:
        return Observation(features={"state": np.full(3, 50.0, np.float32)})

    def act(self, action: np.ndarray) -> np.ndarray:
        self.acted.append(np.array(action, np.float32))
        return np.asarray(action, np.float32)

    def hold(self) -> None:
        self.holds += 1


class ScriptedSource(PolicySource):
    """Answers the given actions in turn, then the last one forever."""

    def __init__(self, actions: list[list[float]]) -> None:
        self.actions, self.asked = actions, 0

    def act(self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float) -> tuple[np.ndarray, int]:
        action = self.actions[min(self.asked, len(self.actions) - 1)]
        self.asked += 1
        return np.asarray(action, np.float32), 7

    @property
    def version(self) -> int:
        return 7


class ScriptedHuman(Teleoperator):
    """Drives with the given actions in turn, then lets the policy drive."""

    def __init__(self, spec: robot_pb2.RobotSpec, actions: list[list[float]]) -> None:
        super().__init__(PluginParams(), spec)
        self.actions = list(actions)

    def poll(self, observation: Observation) -> np.ndarray | None:
        return np.asarray(self.actions.pop(0), np.float32) if self.actions else None


def _run_loop(robot: RecordingRobot, source: PolicySource, teleop: Teleoperator | None, steps: int) -> list[Any]:
    sink = ListSink()
    loop = RobotLoop(robot, source, sink, mode="fast", action_deadline_s=0.0, teleop=teleop)
    loop.start()
    try:
        helpers.wait_for(lambda: len(sink.steps) >= steps, f"{steps} steps")
    finally:
        loop.stop()
    return sink.snapshot()[:steps]


def test_the_edge_holds_on_a_non_finite_policy_action_and_clips_the_others() -> None:
    """[61, nan, inf] from the policy: robot.hold(), a held step, counted; never robot.act with a non-finite value
    (nor the old [61, 10, 10]). A finite action beyond the limits reaches the robot clipped by the agent itself."""
    robot = RecordingRobot()
    source = ScriptedSource([[61.0, np.nan, np.inf], [61.0, np.nan, 50.0], [200.0, 5.0, 50.0]])
    before = _metric("user_edge_non_finite_actions_total", {"robot_id": "pos-0", "source": "policy"})
    steps = _run_loop(robot, source, None, 4)
    assert [s.held for s in steps] == [True, True, False, False]
    assert robot.holds >= 2
    assert all(np.isfinite(a).all() for a in robot.acted)
    np.testing.assert_array_equal(robot.acted[0], [90.0, 10.0, 50.0])  # clipped by the agent
    np.testing.assert_array_equal(wire.from_tensor(steps[2].action), [90.0, 10.0, 50.0])
    assert _metric("user_edge_non_finite_actions_total", {"robot_id": "pos-0", "source": "policy"}) == before + 2


def test_the_edge_holds_on_a_non_finite_teleoperator_action() -> None:
    robot = RecordingRobot()
    human = ScriptedHuman(robot.spec, [[np.nan, 50.0, 50.0], [20.0, 0.0, 95.0]])
    before = _metric("user_edge_non_finite_actions_total", {"robot_id": "pos-0", "source": "teleop"})
    steps = _run_loop(robot, ScriptedSource([[50.0, 50.0, 50.0]]), human, 3)
    assert steps[0].held and not steps[0].intervention
    assert steps[1].intervention and not steps[1].held
    np.testing.assert_array_equal(robot.acted[0], [20.0, 10.0, 90.0])  # the human's action, clipped
    assert all(np.isfinite(a).all() for a in robot.acted)
    assert _metric("user_edge_non_finite_actions_total", {"robot_id": "pos-0", "source": "teleop"}) == before + 1


# --------------------------------------------------------------------------- 2: decompression bombs


def _zstd_zeros(elements: int) -> tpb.Tensor:
    """A 60 M float32 tensor of zeros: ~7 kB on the wire, 240 MB decoded."""
    data = zstandard.ZstdCompressor(level=3).compress(bytes(elements * 4))
    return tpb.Tensor(dtype=tpb.DTYPE_FLOAT32, shape=[elements], data=data, encoding=tpb.ENCODING_ZSTD)


def test_a_small_compressed_request_that_claims_gigabytes_is_refused_before_decoding(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub
) -> None:
    service.load_weights(sac_weights(version=1))
    bomb = _zstd_zeros(60_000_000)
    extras = {f"junk.{i}": bomb for i in range(8)}
    tracemalloc.start()
    try:
        # The policy's own key, claiming 60 M values where it reads 15: refused from the declared shape.
        err = _refused(stub, _request(tensors={"state": bomb}))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "state" in err.details(), err.details()
        # Keys the policy does not read are skipped undecoded (extra keys were always tolerated).
        assert stub.Act(_request(tensors=extras), timeout=30).policy_version == 1
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 100 * 2**20, f"peak {peak / 2**20:.0f} MiB: something was decompressed"


def test_a_request_over_the_decoded_bytes_cap_is_resource_exhausted(monkeypatch: pytest.MonkeyPatch) -> None:
    """A policy that resizes reads frames of any (bounded) size: the request's decoded bytes are capped too."""
    svc = InferenceService(_cfg(), policy_source="manual", start_metrics=False).start()
    try:
        svc.load_weights(WeightSet(version=1, policy=policy_spec(VLA), tensors=random_weights(VLA)))
        stub = inference_pb2_grpc.InferenceStub(make_channel(svc.address, AUTH))
        monkeypatch.setattr(server_module, "MAX_ACT_DECODED_BYTES", 64 * 64 * 3)
        frame = np.zeros((64, 65, 3), np.uint8)
        err = _refused(stub, _request(**{"camera.front": frame, "state": np.zeros(5, np.float32)}))
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, err.details()
        ok = _request(**{"camera.front": frame[:, :60], "state": np.zeros(5, np.float32)})
        assert stub.Act(ok, timeout=30).policy_version == 1
    finally:
        svc.stop()


# --------------------------------------------------------------------------- 3, 4, 11: camera frames


@pytest.fixture
def vla() -> Iterator[tuple[InferenceService, inference_pb2_grpc.InferenceStub]]:
    svc = InferenceService(_cfg(), policy_source="manual", start_metrics=False).start()
    svc.load_weights(WeightSet(version=3, policy=policy_spec(VLA), tensors=random_weights(VLA)))
    yield svc, inference_pb2_grpc.InferenceStub(make_channel(svc.address, AUTH))
    svc.stop()


def test_oversize_and_empty_frames_are_invalid_argument(vla: tuple[InferenceService, Any]) -> None:
    """A 4000x4000 frame would stall every robot's batch in preprocess; a 0x0 one failed the forward (INTERNAL)."""
    _, stub = vla
    state = np.zeros(5, np.float32)
    huge = wire.to_tensor(np.zeros((4000, 4000, 3), np.uint8), tpb.ENCODING_JPEG)
    err = _refused(stub, _request(tensors={"camera.front": huge}, state=state))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "camera.front" in err.details(), err.details()
    for shape in ((0, 0, 3), (0, 64, 3), (64, 0, 3)):
        err = _refused(stub, _request(**{"camera.front": np.zeros(shape, np.uint8), "state": state}))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, (shape, err.code(), err.details())
    edge = MAX_IMAGE_SIDE
    ok = _request(**{"camera.front": np.zeros((edge, 8, 3), np.uint8), "state": state})
    assert stub.Act(ok, timeout=30).policy_version == 3


def test_a_wrong_dtype_camera_is_named_as_sent(vla: tuple[InferenceService, Any]) -> None:
    _, stub = vla
    err = _refused(stub, _request(**{"camera.front": np.zeros((64, 64, 3), bool), "state": np.zeros(5, np.float32)}))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "bool" in err.details() and "float32" not in err.details(), err.details()


# --------------------------------------------------------------------------- 10: robot ids


def test_an_overlong_robot_id_is_invalid_argument(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub
) -> None:
    service.load_weights(sac_weights(version=1))
    err = _refused(stub, _request(robot_id="r" * 20_000))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "robot_id" in err.details(), err.details()
    assert len(err.details()) < 1000


# --------------------------------------------------------------------------- 13: encodings


def test_a_payload_must_match_its_declared_encoding(vla: tuple[InferenceService, Any]) -> None:
    frame = np.zeros((64, 64, 3), np.uint8)
    png_as_jpeg = wire.to_tensor(frame, tpb.ENCODING_PNG)
    png_as_jpeg.encoding = tpb.ENCODING_JPEG
    jpeg_as_png = wire.to_tensor(frame, tpb.ENCODING_JPEG)
    jpeg_as_png.encoding = tpb.ENCODING_PNG
    for tensor in (png_as_jpeg, jpeg_as_png):
        with pytest.raises(wire.WireError, match="magic"):
            wire.from_tensor(tensor)
    _, stub = vla
    before = _metric("user_inference_encoded_frames_total", {"encoding": "jpeg"})
    err = _refused(stub, _request(tensors={"camera.front": png_as_jpeg}, state=np.zeros(5, np.float32)))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert _metric("user_inference_encoded_frames_total", {"encoding": "jpeg"}) == before


# --------------------------------------------------------------------------- 14: per-experiment version


def test_policy_version_and_status_are_per_experiment() -> None:
    svc = InferenceService(
        _cfg([{"name": "reach"}, {"name": "pick"}]), policy_source="manual", start_metrics=False
    ).start()
    try:
        svc.load_weights(sac_weights(version=4), "reach")
        svc.load_weights(sac_weights(version=9), "pick")
        assert _metric("user_inference_policy_version", {"experiment": "reach"}) == 4
        assert _metric("user_inference_policy_version", {"experiment": "pick"}) == 9
        stub = inference_pb2_grpc.InferenceStub(make_channel(svc.address, AUTH))
        status = stub.Status(inference_pb2.InferenceStatusRequest(), timeout=30)
        assert {e.experiment: e.policy_version for e in status.experiments} == {"reach": 4, "pick": 9}
        assert {e.policy_kind for e in status.experiments} == {"sac_mlp"}
    finally:
        svc.stop()


# --------------------------------------------------------------------------- 12: state shapes


def test_a_state_of_the_wrong_shape_is_refused_when_the_robots_spec_is_known() -> None:
    """Routing learns each robot's spec from control: a (3, 5) or (1, 15) state for its (15,) feature is refused
    naming the key (only the total count of 15 was checked), so is a state of another dtype or a key the spec does
    not declare; the declared shape is served."""
    from edge_agent.control_client import ControlClient
    from services.control.server import ControlService
    from tests.test_replay_store import spec
    from user.v1 import control_pb2

    cfg = _cfg([{"name": "reach", "robots": {"ids": ["arm-0"]}}])
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.2
    control = ControlService(cfg, start_metrics=False).start()
    cfg.inference.control_addr = control.address
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    inference.load_weights(sac_weights(version=4))
    status = lambda: [control_pb2.RobotStatus(robot_id="arm-0")]  # noqa: E731
    edge = ControlClient(control.address, AUTH, "pc-1", [spec("arm-0", obs_dim=15)], status, lambda c: (True, ""))
    stub = inference_pb2_grpc.InferenceStub(make_channel(inference.address, AUTH))
    try:
        edge.start()
        assert edge.wait_registered(10)
        inference.router.refresh()  # routes are refreshed in the background: this one now, for a steady answer
        assert helpers.wait_for(lambda: stub.Act(_request(), timeout=30).policy_version == 4, "arm-0 served")
        for shape in ((3, 5), (1, 15)):
            err = _refused(stub, _request(state=np.zeros(shape, np.float32)))
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "'state'" in err.details(), err.details()
        # The dtype too, as replay checks a step's (the same check): a float32 state sent as another dtype.
        for dtype in (np.float64, np.int64, np.bool_, np.uint8):
            err = _refused(stub, _request(state=np.zeros(15, dtype)))
            want = f"observation['state']: dtype {np.dtype(dtype).name}, spec says float32"
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and want in err.details(), err.details()
        # Keys the spec does not declare, small or large, are refused before anything is decoded.
        for extra in (np.zeros(3, np.float32), np.zeros(8 << 20, np.uint8)):
            err = _refused(stub, _request(state=np.zeros(15, np.float32), extra=extra))
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "extra ['extra']" in err.details(), err.details()
        assert stub.Act(_request(), timeout=30).policy_version == 4
    finally:
        edge.close()
        inference.stop()
        control.stop()
