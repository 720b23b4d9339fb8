"""flow_vla policy and its flow_bc learner: chunks, instructions, serving, and learning from interventions."""

from __future__ import annotations

from collections.abc import Iterator

import grpc
import numpy as np
import pytest
import torch
from prometheus_client import REGISTRY

from cloud_learner.algorithm import ALGORITHMS, Batch, Feature, Layout
from edge_agent.policy_source import RemotePolicy
from services.inference.server import InferenceService
from tests import helpers
from user import wire
from user.config import AuthConfig, StackConfig
from user.policies.flow_vla import FlowVlaConfig, policy_spec, random_weights
from user.policy import build_policy
from user.rpc import make_channel
from user.text import INSTRUCTION_KEY, encode_instruction
from user.v1 import inference_pb2, inference_pb2_grpc, step_pb2
from user.v1 import tensor_pb2 as tpb
from user.weights import WeightSet

torch.set_num_threads(1)
AUTH = AuthConfig(token="test-token")
H, A = 4, 3
CFG = FlowVlaConfig(
    image_keys=["camera.front"],
    state_keys=["state"],
    state_dim=5,
    action_dim=A,
    action_low=[-1.0, -1.0, 0.0],
    action_high=[1.0, 1.0, 0.5],
    horizon=H,
    hidden=32,
    flow_steps=3,
    default_instruction="reach the red target",
)


def observation(batch: int, size: int = 64, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "camera.front": rng.integers(0, 256, size=(batch, size, size, 3), dtype=np.uint8),
        "state": rng.normal(size=(batch, 5)).astype(np.float32),
    }


def weights(version: int, seed: int = 0) -> WeightSet:
    return WeightSet(version=version, policy=policy_spec(CFG), tensors=random_weights(CFG, seed))


def test_sampling_in_parts_is_the_velocity_field_integrated_step_by_step() -> None:
    """sample() splits the expert's first layer (context once per call); the result is the plain Euler loop."""
    from user.policies.flow_vla import FlowVla

    torch.manual_seed(0)
    model = FlowVla(CFG).eval()
    context = torch.randn(6, CFG.hidden)
    for deterministic in (True, False):
        torch.manual_seed(1)
        got = model.sample(context, deterministic)
        torch.manual_seed(1)
        x = torch.zeros(6, H, A) if deterministic else torch.randn(6, H, A)
        dt = 1.0 / CFG.flow_steps
        for i in range(CFG.flow_steps):
            x = x + dt * model.velocity(x, torch.full((6,), i * dt), context)
        torch.testing.assert_close(got, x.clamp(-1.0, 1.0), rtol=1e-5, atol=1e-6)


def test_chunks_in_bounds_and_instruction_matters() -> None:
    policy = build_policy(policy_spec(CFG), random_weights(CFG), version=3)
    assert policy.chunk_horizon == H and policy.action_shape == (A,)
    obs = observation(2)
    chunk = policy.act(obs, deterministic=True)
    assert chunk.shape == (2, H, A) and chunk.dtype == np.float32
    assert (chunk >= np.array(CFG.action_low) - 1e-6).all() and (chunk <= np.array(CFG.action_high) + 1e-6).all()
    red = policy.forward(policy.preprocess(obs, ["reach the red target"] * 2), True)
    blue = policy.forward(policy.preprocess(obs, ["reach the blue target"] * 2), True)
    np.testing.assert_allclose(red, chunk, atol=1e-6)  # "" falls back to the default instruction
    assert not np.allclose(red, blue)
    # The instruction may also ride in the observation as bytes; the request's wins over it.
    with_bytes = dict(obs, **{INSTRUCTION_KEY: np.stack([encode_instruction("reach the blue target")] * 2)})
    np.testing.assert_allclose(policy.forward(policy.preprocess(with_bytes, ["", ""]), True), blue, atol=1e-6)
    np.testing.assert_allclose(policy.forward(policy.preprocess(with_bytes, ["reach the red target"] * 2), True), red)


def test_images_of_another_size_are_resized_and_bad_input_is_refused() -> None:
    policy = build_policy(policy_spec(CFG), random_weights(CFG), version=1)
    assert policy.act(observation(1, size=96)).shape == (1, H, A)
    with pytest.raises(ValueError, match="lacks"):
        policy.act({"state": np.zeros((1, 5), np.float32)})
    with pytest.raises(ValueError, match="features"):
        policy.act(dict(observation(1), state=np.zeros((1, 7), np.float32)))
    tensors = random_weights(CFG)
    tensors.pop(next(iter(tensors)))
    with pytest.raises(ValueError, match="missing"):
        build_policy(policy_spec(CFG), tensors, version=1)
    bad = policy_spec(CFG)
    bad.config_json = '{"action_dim": 0}'
    with pytest.raises(ValueError, match="config_json"):
        build_policy(bad, random_weights(CFG), version=1)


@pytest.fixture
def service(request: pytest.FixtureRequest) -> Iterator[InferenceService]:
    cfg = StackConfig(auth=AUTH)
    cfg.inference.continuous_batching = getattr(request, "param", False)
    cfg.inference.server.port = 0
    cfg.inference.server.metrics_port = 0
    cfg.inference.server.grace_s = 1.0
    svc = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    svc.load_weights(weights(version=5))
    yield svc
    svc.stop()


@pytest.mark.parametrize("service", [False, True], ids=["batched", "continuous"], indirect=True)
def test_served_chunks_with_instruction_and_stage_times(service: InferenceService) -> None:
    stub = inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))
    obs = {k: v[0] for k, v in observation(1).items()}
    answers = {}
    for text in ("reach the red target", "reach the blue target"):
        req = inference_pb2.ActRequest(
            robot_id="arm-0", observation=wire.to_tensor_map(obs), deterministic=True, instruction=text
        )
        resp = stub.Act(req, timeout=10)
        answers[text] = wire.from_tensor(resp.action)
        assert answers[text].shape == (H, A) and resp.horizon == H and resp.policy_version == 5
        assert resp.forward_us > 0 and resp.preprocess_us > 0 and resp.postprocess_us >= 0 and resp.queue_us >= 0
    assert not np.allclose(answers["reach the red target"], answers["reach the blue target"])
    too_long = inference_pb2.ActRequest(robot_id="arm-0", observation=wire.to_tensor_map(obs), instruction="x" * 2000)
    with pytest.raises(grpc.RpcError) as err:
        stub.Act(too_long, timeout=10)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_edge_executes_the_served_chunk_row_by_row(service: InferenceService) -> None:
    source = RemotePolicy(service.address, AUTH, deterministic=True, instruction="reach the red target")
    try:
        obs = {k: v[0] for k, v in observation(1).items()}
        expected = service.policy.forward(service.policy.preprocess({k: v[None] for k, v in obs.items()}, [""]), True)
        first, version = source.act("arm-0", obs, deadline_s=10.0)
        second, _ = source.act("arm-0", obs, deadline_s=10.0)
        np.testing.assert_allclose(first, expected[0, 0], atol=1e-5)
        np.testing.assert_allclose(second, expected[0, 1], atol=1e-5)  # the next row, not a new request's first
        assert version == 5
    finally:
        source.close()


@pytest.mark.parametrize("encoding", [tpb.ENCODING_JPEG, tpb.ENCODING_PNG], ids=["jpeg", "png"])
def test_encoded_camera_frames_reach_the_policy_decoded(service: InferenceService, encoding: int) -> None:
    """An edge with act_image_encoding sends its frames JPEG/PNG-encoded; inference decodes them to the
    declared shape, so the policy acts on exactly the decoded frame (PNG: the raw frame itself)."""
    source = RemotePolicy(
        service.address, AUTH, deterministic=True, frame_plans={"arm-0": {"camera.front": (encoding, 50)}}
    )
    obs = {k: v[0] for k, v in observation(1).items()}
    sent = wire.to_tensor(obs["camera.front"], encoding, jpeg_quality=50)
    seen = {**obs, "camera.front": wire.from_tensor(sent)}

    def forward(o: dict[str, np.ndarray]) -> np.ndarray:
        return service.policy.forward(service.policy.preprocess({k: v[None] for k, v in o.items()}, [""]), True)

    frames = REGISTRY.get_sample_value("user_inference_encoded_frames_total", {"encoding": _ENC[encoding]}) or 0.0
    try:
        action, version = source.act("arm-0", obs, deadline_s=10.0)
    finally:
        source.close()
    assert version == 5
    np.testing.assert_allclose(action, forward(seen)[0, 0], atol=1e-5)
    raw_action = forward(obs)[0, 0]
    if encoding == tpb.ENCODING_JPEG:  # lossy at quality 50 (this small random net barely tells the frames apart)
        assert len(sent.data) < obs["camera.front"].nbytes / 4
        assert not np.array_equal(seen["camera.front"], obs["camera.front"])
    else:
        np.testing.assert_array_equal(seen["camera.front"], obs["camera.front"])
        np.testing.assert_allclose(action, raw_action, atol=1e-5)
    assert REGISTRY.get_sample_value("user_inference_encoded_frames_total", {"encoding": _ENC[encoding]}) == frames + 1


_ENC = {tpb.ENCODING_JPEG: "jpeg", tpb.ENCODING_PNG: "png"}


def test_bad_encoded_frames_are_refused_and_serving_goes_on(service: InferenceService) -> None:
    """A frame of another size, a cut-short scan, a grey image for a colour camera or a batch of frames:
    INVALID_ARGUMENT, counted as no frame, and the next good request is answered."""
    stub = inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))
    obs = {k: v[0] for k, v in observation(1).items()}
    good = wire.to_tensor(obs["camera.front"], tpb.ENCODING_JPEG)
    small = wire.to_tensor(obs["camera.front"][:32, :32], tpb.ENCODING_JPEG)
    small.shape[:] = [64, 64, 3]
    cut = tpb.Tensor()
    cut.CopyFrom(good)
    cut.data = good.data[: len(good.data) // 2] + b"\xff\xd9"
    grey = wire.to_tensor(obs["camera.front"][..., 0], tpb.ENCODING_JPEG)
    grey.shape[:] = [64, 64, 3]
    blobs = np.empty(1, dtype=object)
    blobs[0] = good.data
    batch = wire.frames_tensor(wire.EncodedFrames(blobs, tpb.ENCODING_JPEG, (64, 64, 3)))
    frames = REGISTRY.get_sample_value("user_inference_encoded_frames_total", {"encoding": "jpeg"}) or 0.0
    for bad in (small, cut, grey, batch):
        tmap = wire.to_tensor_map({"state": obs["state"]})
        tmap.tensors["camera.front"].CopyFrom(bad)
        with pytest.raises(grpc.RpcError) as err:
            stub.Act(inference_pb2.ActRequest(robot_id="arm-0", observation=tmap), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, err.value.details()
    assert (REGISTRY.get_sample_value("user_inference_encoded_frames_total", {"encoding": "jpeg"}) or 0.0) == frames
    tmap = wire.to_tensor_map({"state": obs["state"]})
    tmap.tensors["camera.front"].CopyFrom(good)
    resp = stub.Act(inference_pb2.ActRequest(robot_id="arm-0", observation=tmap), timeout=10)
    assert wire.from_tensor(resp.action).shape == (H, A)


def test_a_robot_with_a_wrong_frame_does_not_fail_its_batch_mates(service: InferenceService) -> None:
    """Frames of a shape, channel count or dtype the policy cannot read are refused per request, before
    batching: in one ActBatch the others are answered (their forward used to fail with INTERNAL)."""
    stub = inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))
    obs = {k: v[0] for k, v in observation(1).items()}
    frame = obs["camera.front"]
    wrong = [frame[None], frame[..., 0], np.zeros((64, 64, 4), np.uint8), frame.astype(np.float32)]
    requests = [inference_pb2.ActRequest(robot_id="arm-0", observation=wire.to_tensor_map(obs))]
    for i, bad in enumerate(wrong):
        requests.append(
            inference_pb2.ActRequest(
                robot_id=f"arm-{i + 1}", observation=wire.to_tensor_map({**obs, "camera.front": bad})
            )
        )
    smaller = {**obs, "camera.front": frame[:48, :40]}  # another size is resized, not refused
    requests.append(inference_pb2.ActRequest(robot_id="arm-9", observation=wire.to_tensor_map(smaller)))
    results = stub.ActBatch(inference_pb2.ActBatchRequest(requests=requests), timeout=10).results
    invalid = grpc.StatusCode.INVALID_ARGUMENT.value[0]
    assert [r.code for r in results] == [0, invalid, invalid, invalid, invalid, 0], [r.message for r in results]
    assert "uint8 *x*x3" in results[1].message


# --- flow_bc: the learner side of HG-DAgger ----------------------------------------------------------

LAYOUT = Layout(
    observation={"state": Feature((5,), "float32"), INSTRUCTION_KEY: Feature((64,), "uint8")},
    action_low=np.array([-1.0, -1.0, -1.0], np.float32),
    action_high=np.array([1.0, 1.0, 1.0], np.float32),
)


def human_batch(intervention: bool, n: int = 32) -> tuple[Batch, np.ndarray]:
    rng = np.random.default_rng(1)
    state = torch.from_numpy(rng.normal(size=(n, 5)).astype(np.float32))
    text = torch.from_numpy(np.stack([encode_instruction("reach the green target")] * n))
    target = np.array([0.8, -0.6, 0.4], np.float32)  # what the human did in these states
    obs = {"state": state, INSTRUCTION_KEY: text}
    batch = Batch(
        observation=obs,
        action=torch.from_numpy(np.tile(target, (n, 1))),
        reward=torch.zeros(n),
        next_observation=obs,
        terminated=torch.zeros(n),
        intervention=torch.full((n,), intervention),
    )
    return batch, target


def test_an_intervention_reaches_the_learner_and_changes_the_policy() -> None:
    algo = ALGORITHMS.build(
        "flow_bc", {"batch_size": 32, "lr": 3e-3, "hidden": 64}, layout=LAYOUT, device=torch.device("cpu")
    )
    batch, target = human_batch(intervention=True)
    obs = {k: v[:4].numpy() for k, v in batch.observation.items()}

    def served_action() -> np.ndarray:
        spec, tensors = algo.policy()
        return build_policy(spec, tensors, version=algo.updates).act(obs, deterministic=True)[:, 0]

    before = np.abs(served_action() - target).mean()
    for _ in range(150):
        stats = algo.update(batch)
    after = np.abs(served_action() - target).mean()
    assert stats["human_rows"] == 32 and np.isfinite(stats["flow_loss"])
    assert after < 0.1 < before


def test_the_policys_own_steps_are_not_imitated_from_a_mixed_table() -> None:
    params = {"batch_size": 32, "tables": {"online": 1.0}, "hidden": 32}
    algo = ALGORITHMS.build("flow_bc", params, layout=LAYOUT, device=torch.device("cpu"))
    assert algo.batch_request().tables == {"online": 1.0}
    before = {k: v.copy() for k, v in algo.policy()[1].items()}
    stats = algo.update(human_batch(intervention=False)[0])
    assert stats["human_rows"] == 0
    assert all(np.array_equal(before[k], v) for k, v in algo.policy()[1].items())
    assert algo.update(human_batch(intervention=True)[0])["human_rows"] == 32


def test_chunk_targets_need_chunks() -> None:
    algo = ALGORITHMS.build("flow_bc", {"horizon": 4, "hidden": 32}, layout=LAYOUT, device=torch.device("cpu"))
    assert algo.batch_request().tables == {"demos": 0.5, "interventions": 0.5}
    assert algo.batch_request().action_horizon == 4  # replay assembles the chunks
    batch, _ = human_batch(intervention=True)
    with pytest.raises(ValueError, match="action_chunk"):
        algo.update(batch)
    batch.action_chunk = batch.action[:, None, :].repeat(1, 4, 1)
    assert np.isfinite(algo.update(batch)["flow_loss"])


@pytest.mark.parametrize("service", [False, True], ids=["batched", "continuous"], indirect=True)
def test_weight_swaps_under_grpc_load_fail_no_request(service: InferenceService) -> None:
    import threading

    obs = wire.to_tensor_map({k: v[0] for k, v in observation(1).items()})
    errors: list[str] = []
    versions: list[int] = []
    per_robot: dict[int, list[int]] = {i: [] for i in range(3)}
    stop = threading.Event()

    def robot(i: int) -> None:
        stub = inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))
        while not stop.is_set():
            try:
                resp = stub.Act(inference_pb2.ActRequest(robot_id=f"arm-{i}", observation=obs), timeout=30)
                versions.append(resp.policy_version)
                per_robot[i].append(resp.policy_version)
            except grpc.RpcError as err:
                errors.append(f"{err.code().name}: {err.details()}")

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    try:
        for version in range(6, 12):  # the learner's stream delivers new weights while robots act
            seen = len(versions)
            while len(versions) < seen + 3 and not errors:
                stop.wait(0.005)
            service.load_weights(weights(version, seed=version))
        seen = len(versions)
        while len(versions) < seen + 3 and not errors:
            stop.wait(0.005)
    finally:
        stop.set()
        for t in threads:
            t.join(30)
    assert not errors, errors[:3]
    assert max(versions) == 11
    stepped = [slot.batcher._policy.stepped for slot in service.slots.values() if slot.batcher._policy]
    assert stepped and all((s is not None) == service.cfg.inference.continuous_batching for s in stepped)
    assert all(v == sorted(v) for v in per_robot.values())  # each robot only ever sees newer versions


LANG_CFG = FlowVlaConfig(  # lang_reach_arm's features: a 64x64 camera and 15 floats of state; chunks of 8
    image_keys=["camera.front"],
    state_keys=["state"],
    state_dim=15,
    action_dim=3,
    action_low=[-1.0] * 3,
    action_high=[1.0] * 3,
    horizon=8,
    hidden=32,
    flow_steps=2,
)


def test_robot_loop_runs_served_chunks_at_the_control_rate(service: InferenceService) -> None:
    from edge_agent.agent import RobotLoop
    from edge_agent.robot import make_robot
    from tests.test_edge_agent import ListSink

    service.load_weights(WeightSet(version=9, policy=policy_spec(LANG_CFG), tensors=random_weights(LANG_CFG)))
    served_before = service.batcher.requests
    robot = make_robot("lang_reach_arm", "lang-0", {"control_rate_hz": 20, "max_episode_steps": 1000}, seed=0)
    source = RemotePolicy(service.address, AUTH)
    sink = ListSink()
    loop = RobotLoop(robot, source, sink, mode="realtime", action_deadline_s=2.0)
    loop.start()
    try:
        helpers.wait_for(lambda: len(sink.steps) >= 24, "24 control ticks")
    finally:
        loop.stop()
        source.close()
        robot.close()
    steps = sink.snapshot()
    acted = [s for s in steps if not s.held]
    requests = service.batcher.requests - served_before
    assert acted and all(s.policy_version == 9 for s in acted)
    assert requests < len(steps) / 2  # one request per chunk of 8 (prefetched), not one per tick
    executor = source._chunks.executors["lang-0"]
    assert executor.received == requests and executor.last_latency_s > 0


def test_a_frame_encoded_for_act_is_not_encoded_again_for_its_step(service: InferenceService) -> None:
    """With the same JPEG plan for Act requests and steps, the edge encodes a frame it asked a chunk with once:
    the step of that observation carries the very bytes its own encode would give (a real robot loop, a real
    inference service); frames no Act request sent are still encoded by the step encoder."""
    from edge_agent.agent import RobotLoop
    from edge_agent.encoder import EncodedFrames, FrameEncoder
    from edge_agent.robot import make_robot
    from tests.test_edge_agent import ListSink

    service.load_weights(WeightSet(version=9, policy=policy_spec(LANG_CFG), tensors=random_weights(LANG_CFG)))
    plan = {"camera.front": (tpb.ENCODING_JPEG, 80)}
    frames = EncodedFrames()
    robot = make_robot("lang_reach_arm", "lang-0", {"control_rate_hz": 20, "max_episode_steps": 1000}, seed=0)
    source = RemotePolicy(service.address, AUTH, frame_plans={"lang-0": plan}, frames=frames)
    sink = ListSink()
    encoder = FrameEncoder(sink, {"lang-0": plan}, threads=1, frames=frames)
    raw: list[bytes] = []

    class Tap:  # keeps each step's raw frame before the encoder rewrites it
        def send(self, step: step_pb2.Step, table: str = "") -> int:
            raw.append(step.observation.tensors["camera.front"].data)
            return encoder.send(step, table)

        unacked = 0

    loop = RobotLoop(robot, source, Tap(), mode="realtime", action_deadline_s=2.0)
    loop.start()
    try:
        helpers.wait_for(lambda: len(raw) >= 40, "40 control ticks")
    finally:
        loop.stop()
        source.close()
        robot.close()
    assert encoder.flush(10.0)
    encoder.close()
    steps = sink.snapshot()
    assert len(steps) == len(raw)
    requests = source.chunks_received
    assert 1 <= encoder.reused <= requests < len(steps) / 2  # one Act per chunk of 8, each frame reused at most once
    assert encoder.reused + encoder.encoded == len(steps)
    for step, frame in zip(steps, raw, strict=True):
        tensor = step.observation.tensors["camera.front"]
        assert tensor.encoding == tpb.ENCODING_JPEG
        own = wire.encode_image(np.frombuffer(frame, np.uint8).reshape(tuple(tensor.shape)), tpb.ENCODING_JPEG, 80)
        assert tensor.data == own


def test_encoded_frames_match_bytes_not_objects() -> None:
    """A frame is reused only for the same bytes, shape, encoding and quality: a robot that refills one buffer
    every tick gets a fresh encode."""
    from edge_agent.encoder import EncodedFrames

    frames = EncodedFrames(per_feature=2)
    buffer = np.zeros((8, 8, 3), np.uint8)
    frames.put("r", "camera.front", buffer, tpb.ENCODING_JPEG, 80, b"first")
    same = wire.to_tensor(buffer.copy())
    assert frames.find("r", "camera.front", same, tpb.ENCODING_JPEG, 80) == b"first"
    assert frames.find("r", "camera.front", same, tpb.ENCODING_JPEG, 90) is None  # another quality
    assert frames.find("r", "camera.front", same, tpb.ENCODING_PNG, 80) is None
    assert frames.find("other", "camera.front", same, tpb.ENCODING_JPEG, 80) is None
    assert frames.find("r", "camera.front", wire.to_tensor(buffer.reshape(16, 4, 3)), tpb.ENCODING_JPEG, 80) is None
    buffer[0, 0, 0] = 1  # refilled in place after it was encoded
    assert frames.find("r", "camera.front", wire.to_tensor(buffer), tpb.ENCODING_JPEG, 80) is None
    for i in range(3):  # only the last per_feature frames are kept
        frames.put("r", "camera.front", np.full((8, 8, 3), i, np.uint8), tpb.ENCODING_JPEG, 80, bytes([i]))
    kept = [
        frames.find("r", "camera.front", wire.to_tensor(np.full((8, 8, 3), i, np.uint8)), tpb.ENCODING_JPEG, 80)
        for i in range(3)
    ]
    assert kept == [None, b"\x01", b"\x02"]
