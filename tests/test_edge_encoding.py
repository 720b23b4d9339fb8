"""Camera frames JPEG-encoded on the edge (edge_agent/encoder.py), kept as sent by a real replay (gRPC, LMDB),
decoded by its sampler back into the uint8 frames the learner expects."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest

from edge_agent.agent import EdgeAgent, RobotLoop, encoding_plans
from edge_agent.encoder import FrameEncoder, plan_for
from edge_agent.policy_source import PolicySource, RemotePolicy, make_policy_source
from edge_agent.replay_client import ReplaySender
from edge_agent.robot import Robot, make_robot
from edge_agent.spool import open_outbox
from services.replay.disk import step_key
from services.replay.server import _END, ReplayService, _Inbox
from tests.helpers import ListSink, wait_for
from user import wire
from user.config import AuthConfig, RobotConfig, StackConfig
from user.rpc import make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

AUTH = AuthConfig(token="test-token")
MAX_MEAN_ABS_ERROR = 3.0  # JPEG quality 90 on rendered 64x64 MuJoCo frames, per frame, in uint8 levels


class RandomPolicy(PolicySource):
    def __init__(self) -> None:
        self._rng = np.random.default_rng(0)

    def act(self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float) -> tuple[np.ndarray, int]:
        return self._rng.uniform(-1, 1, 3).astype(np.float32), 1

    @property
    def version(self) -> int:
        return 1


class Recorder:
    """A StepSink in front of the encoder: keeps a raw copy of each step as the robot loop built it."""

    def __init__(self, inner: FrameEncoder) -> None:
        self.inner = inner
        self.raw: list[step_pb2.Step] = []
        self._lock = threading.Lock()

    def send(self, step: step_pb2.Step, table: str = "") -> int:
        copy = step_pb2.Step()
        copy.CopyFrom(step)  # the encoder rewrites the step's frames in place
        with self._lock:
            self.raw.append(copy)
        return self.inner.send(step, table)

    @property
    def unacked(self) -> int:
        return self.inner.unacked

    def count(self) -> int:
        with self._lock:
            return len(self.raw)


def _cfg(tmp_path: Path) -> StackConfig:
    cfg = StackConfig(auth=AUTH)
    cfg.replay.server.port = 0
    cfg.replay.server.metrics_port = 0
    cfg.replay.server.grace_s = 0.5
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.commit_max_delay_ms = 5.0
    cfg.edge.spool_dir = tmp_path / "spool"
    return cfg


@pytest.fixture
def camera_arm() -> Iterator[Robot]:
    robot = make_robot("sim_reach_arm", "cam-0", {"camera": True, "max_episode_steps": 4}, seed=0)
    yield robot
    robot.close()


@pytest.fixture
def replay(tmp_path: Path, camera_arm: Robot) -> Iterator[ReplayService]:
    svc = ReplayService(_cfg(tmp_path), spec_source={"cam-0": camera_arm.spec}.get, start_metrics=False).start()
    yield svc
    svc.stop()


def stub(svc: ReplayService) -> replay_pb2_grpc.ReplayStub:
    return replay_pb2_grpc.ReplayStub(make_channel(svc.address, AUTH))


def test_edge_encoded_jpeg_steps_sample_back_from_a_real_replay(
    tmp_path: Path, camera_arm: Robot, replay: ReplayService
) -> None:
    sender = ReplaySender(replay.address, AUTH, outbox=open_outbox(_cfg(tmp_path).edge))  # the LMDB spool
    plan = plan_for(camera_arm.spec, {"*": "jpeg"}, 90, "test")
    assert plan == {"camera.front": (tpb.ENCODING_JPEG, 90)}
    encoder = FrameEncoder(sender, {"cam-0": plan}, threads=2)
    recorder = Recorder(encoder)
    loop = RobotLoop(camera_arm, RandomPolicy(), recorder, mode="fast")  # type: ignore[arg-type]
    loop.start()
    try:
        wait_for(lambda: recorder.count() >= 10, "10 steps", limit_s=300)
    finally:
        loop.stop()
        encoder.close()
    assert sender.flush(30.0)
    sender.close()
    raw = recorder.raw
    n = len(raw)
    assert replay.store.stats()["steps"] == n
    assert encoder.encoded == n + sum(s.HasField("final_observation") for s in raw)  # every camera frame
    assert encoder.encoded_bytes < encoder.raw_bytes / 3  # rendered frames compress (noise would not)

    # LMDB keeps the bytes the edge sent: JPEG, with the declared uint8 shape
    stored = [step_pb2.Step.FromString(b) for b in replay.store.db.get_many([step_key("cam-0", raw[0].episode_id, 0)])]
    cam = stored[0].observation.tensors["camera.front"]
    assert cam.encoding == tpb.ENCODING_JPEG and list(cam.shape) == [64, 64, 3] and cam.dtype == tpb.DTYPE_UINT8

    # frames by the observation's state (unique per observation), raw as the robot saw them
    frames = {}
    for step in raw:
        for part in (step.observation, step.final_observation):
            if "state" in part.tensors:
                frames[part.tensors["state"].data] = wire.from_tensor(part.tensors["camera.front"])
    batch = stub(replay).Sample(replay_pb2.SampleRequest(batch_size=64), timeout=10).batch
    for tmap in (batch.observation, batch.next_observation):
        got = tmap.tensors["camera.front"]
        assert got.encoding == tpb.ENCODING_RAW and got.dtype == tpb.DTYPE_UINT8  # what the learner decodes
        images, states = wire.from_tensor(got), wire.from_tensor(tmap.tensors["state"])
        assert images.shape == (64, 64, 64, 3)
        for image, state in zip(images, states, strict=True):
            original = frames[state.tobytes()]
            error = np.abs(image.astype(np.int16) - original.astype(np.int16)).mean()
            assert error <= MAX_MEAN_ABS_ERROR, error
            assert original.std() > 5  # a real rendered scene, not a blank frame


def _step(frame: tpb.Tensor, index: int = 0) -> step_pb2.Step:
    step = step_pb2.Step(robot_id="cam-0", episode_id="bad", step_index=index, observed_at_ns=1, acted_at_ns=2)
    step.observation.tensors["state"].CopyFrom(wire.to_tensor(np.zeros(15, np.float32)))
    step.observation.tensors["camera.front"].CopyFrom(frame)
    step.action.CopyFrom(wire.to_tensor(np.zeros(3, np.float32)))
    return step


@pytest.mark.parametrize(
    "fault", ["wrong_size", "truncated", "not_an_image", "damaged_inside", "grey_as_colour", "garbage"]
)
def test_a_bad_edge_jpeg_is_invalid_argument_and_stores_nothing(replay: ReplayService, fault: str) -> None:
    rng = np.random.default_rng(1)
    frame = wire.to_tensor(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), tpb.ENCODING_JPEG)
    if fault == "wrong_size":  # a valid 32x32 JPEG declared 64x64
        frame.data = wire.to_tensor(rng.integers(0, 256, (32, 32, 3), dtype=np.uint8), tpb.ENCODING_JPEG).data
    elif fault == "truncated":
        frame.data = frame.data[: len(frame.data) // 2]
    elif fault == "damaged_inside":  # header, shape and end marker intact; garbage in the first Huffman table
        data = bytearray(frame.data)
        table = data.find(b"\xff\xc4")
        data[table + 5 : table + 25] = b"\xff" * 20
        frame.data = bytes(data)
    elif fault == "grey_as_colour":  # a valid 64x64 one-component JPEG declared (64, 64, 3)
        frame.data = wire.to_tensor(rng.integers(0, 256, (64, 64), dtype=np.uint8), tpb.ENCODING_JPEG).data
    elif fault == "garbage":
        frame.data = rng.integers(0, 256, 2000, dtype=np.uint8).tobytes()
    else:
        frame.data = b"\xff\xd8" + bytes(100)
    good = _step(wire.to_tensor(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), tpb.ENCODING_JPEG))
    requests = [replay_pb2.InsertRequest(seq=1, step=good), replay_pb2.InsertRequest(seq=2, step=_step(frame, 1))]
    with pytest.raises(grpc.RpcError) as err:
        list(stub(replay).Insert(iter(requests), timeout=10))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "camera.front" in (err.value.details() or "")
    assert replay.store.stats()["steps"] == 1  # the good step before it only


def test_insert_frame_checks_on_two_threads_keep_stream_order_and_verdicts() -> None:
    """The Insert reader shares the frame checks with a helper thread: items still come out in stream order,
    each with its own step's verdict (every 7th step has a truncated frame), and the helper took part."""
    rng = np.random.default_rng(2)
    requests, bad = [], set()
    for seq in range(40):
        frame = wire.to_tensor(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), tpb.ENCODING_JPEG)
        if seq % 7 == 3:
            frame.data = frame.data[: len(frame.data) // 2]
            bad.add(seq)
        requests.append(replay_pb2.InsertRequest(seq=seq, step=_step(frame, seq)))
    inbox = _Inbox(iter(requests), maxsize=4)  # small: the reader also waits for the stream thread
    items = []
    while (item := inbox.get(timeout=10)) is not _END:
        assert item is not None, "the inbox stalled"
        items.append(item)
    inbox.close()
    assert [req.seq for req, _ in items] == list(range(40))
    assert {req.seq for req, passed in items if not passed} == bad
    assert all(passed in (True, False) for _, passed in items)
    assert inbox._handed >= 1  # the first step with frames always goes to the idle helper


def _spec() -> robot_pb2.RobotSpec:
    spec = robot_pb2.RobotSpec(robot_id="r")
    for name, dtype, shape in [
        ("state", tpb.DTYPE_FLOAT32, [15]),
        ("camera.front", tpb.DTYPE_UINT8, [64, 64, 3]),
        ("camera.wrist", tpb.DTYPE_UINT8, [32, 32]),
        ("camera.depth", tpb.DTYPE_FLOAT32, [32, 32]),
    ]:
        spec.observation.add(name=name, dtype=dtype, shape=shape)
    return spec


def test_the_plan_names_the_cameras_a_config_encodes() -> None:
    spec = _spec()
    jpeg, png = tpb.ENCODING_JPEG, tpb.ENCODING_PNG
    assert plan_for(spec, {"*": "jpeg"}, 80, "w") == {"camera.front": (jpeg, 80), "camera.wrist": (jpeg, 80)}
    assert plan_for(spec, {"*": "jpeg", "camera.wrist": "png", "camera.front": "raw"}, 80, "w") == {
        "camera.wrist": (png, 80)
    }
    with pytest.raises(ValueError, match=r"edge.robots\[0\].image_encoding: \['camera.back'\] are not"):
        plan_for(spec, {"camera.back": "jpeg"}, 90, "edge.robots[0].image_encoding")
    with pytest.raises(ValueError, match=r"'camera\.depth' is not a uint8"):
        plan_for(spec, {"camera.depth": "png"}, 90, "w")


def test_robot_config_image_encoding_reaches_the_plan(camera_arm: Robot) -> None:
    cfg = StackConfig()
    cfg.edge.robots = [RobotConfig(id="cam-0", params={"camera": True}, image_encoding={"*": "png"}, jpeg_quality=70)]
    assert encoding_plans(cfg, [camera_arm]) == {"cam-0": {"camera.front": (tpb.ENCODING_PNG, 70)}}
    cfg.edge.robots = [RobotConfig(id="cam-0")]
    assert encoding_plans(cfg, [camera_arm]) == {}


def test_act_frames_follow_image_encoding_unless_set(camera_arm: Robot) -> None:
    """Remote Act requests encode a robot's frames as its steps are (the policy sees what the learner saw)
    unless act_image_encoding says otherwise; a name that is not a camera fails at start, naming the field."""
    cfg = StackConfig(auth=AuthConfig(token="t"))
    cfg.edge.policy_source = "remote"
    cfg.edge.inference_addr = "127.0.0.1:9"  # nothing is called here
    jpeg, png = {"camera.front": (tpb.ENCODING_JPEG, 60)}, {"camera.front": (tpb.ENCODING_PNG, 60)}
    cases = [({"*": "jpeg"}, None, jpeg), ({"*": "jpeg"}, {}, {}), ({}, {"*": "png"}, png), ({}, None, {})]
    for steps, act, plan in cases:
        cfg.edge.robots = [
            RobotConfig(
                id="cam-0", params={"camera": True}, image_encoding=steps, act_image_encoding=act, jpeg_quality=60
            )
        ]
        source = make_policy_source(cfg, "edge-0", [camera_arm.spec])
        try:
            assert isinstance(source, RemotePolicy)
            assert source.frame_plans == ({"cam-0": plan} if plan else {}), (steps, act)
        finally:
            source.close()
    cfg.edge.robots = [RobotConfig(id="cam-0", act_image_encoding={"state": "jpeg"})]
    with pytest.raises(ValueError, match=r"edge.robots\[0\].act_image_encoding: 'state' is not a uint8"):
        make_policy_source(cfg, "edge-0", [camera_arm.spec])


def test_the_agent_shares_act_encoded_frames_with_its_step_encoder(camera_arm: Robot) -> None:
    """The edge agent hands its remote policy source and its step encoder one EncodedFrames, so a frame sent
    with an Act request is not encoded again for its step (tests/test_flow_vla.py runs that path)."""
    cfg = StackConfig(auth=AuthConfig(token="t"))
    cfg.edge.policy_source = "remote"
    cfg.edge.inference_addr = "127.0.0.1:9"  # nothing is called here
    cfg.edge.robots = [RobotConfig(id="cam-0", params={"camera": True}, image_encoding={"*": "jpeg"})]
    agent = EdgeAgent(cfg, robots=[camera_arm], sender=ListSink())  # type: ignore[arg-type]
    try:
        assert isinstance(agent.policy, RemotePolicy) and agent.encoder is not None
        assert agent.policy.frames is not None and agent.policy.frames is agent.encoder.frames
    finally:
        agent.policy.close()
        agent.encoder.close()


def test_the_encoder_keeps_send_order_and_passes_unplanned_robots_through() -> None:
    spec = _spec()
    sink = ListSink()
    encoder = FrameEncoder(sink, {"r": plan_for(spec, {"*": "jpeg"}, 90, "w")}, threads=2, max_pending=4)
    rng = np.random.default_rng(0)
    try:
        for i in range(40):
            step = step_pb2.Step(robot_id="r", episode_id="e", step_index=i)
            step.observation.tensors["camera.front"].CopyFrom(
                wire.to_tensor(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
            )
            step.observation.tensors["camera.depth"].CopyFrom(wire.to_tensor(np.zeros((32, 32), np.float32)))
            encoder.send(step)
        assert encoder.send(step_pb2.Step(robot_id="other")) >= 1  # no plan: straight to the sink, its seq back
        assert encoder.flush(30.0)
    finally:
        encoder.close()
    mine = [s for s in sink.steps if s.robot_id == "r"]
    assert [s.step_index for s in mine] == list(range(40))
    assert all(s.observation.tensors["camera.front"].encoding == tpb.ENCODING_JPEG for s in mine)
    assert all(s.observation.tensors["camera.depth"].encoding == tpb.ENCODING_RAW for s in mine)
    assert encoder.encoded == 40 and encoder.pending == 0


def test_a_jpeg_cut_short_with_an_end_marker_appended_is_refused() -> None:
    """A JPEG whose entropy-coded scan is cut short but still ends in FF D9 decodes with only a libjpeg warning
    (cv2 and PIL fill the rest with grey): the check treats the warning as an error."""
    rng = np.random.default_rng(3)
    frame = wire.to_tensor(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), tpb.ENCODING_JPEG)
    frame.data = frame.data[: len(frame.data) // 2] + b"\xff\xd9"
    with pytest.raises(wire.WireError):
        wire.check_image(frame)
