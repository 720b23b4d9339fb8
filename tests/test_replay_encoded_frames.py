"""Sample with encoded_frames: JPEG/PNG frames travel as replay keeps them (Tensor.frame_bytes) and the caller
decodes them to exactly the frames replay itself would have decoded; mixed encodings fall back to decoded frames."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest

from services.replay.server import ReplayService
from services.replay.store import ReplayStore
from services.replay.tables import Draw
from tests.test_replay_store import OBS_DIM, episode, spec
from user import wire
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, robot_pb2
from user.v1 import tensor_pb2 as tpb

CAM = "camera.front"
AUTH = AuthConfig(token="test-token")


def _frame(t: int) -> np.ndarray:
    """A smooth 64x64 colour frame that moves with t (compresses like a camera image)."""
    yy, xx = np.mgrid[0:64, 0:64]
    img = (xx * 2 + yy + 4 * t).astype(np.uint8)
    return np.stack([img, img[::-1], 255 - img], axis=-1)


def camera_steps(name: str, n: int, encoding: int = tpb.ENCODING_RAW, raw_every: int = 0) -> list:
    """An episode whose observations carry a camera frame, encoded as an edge would (raw_every k: every k-th raw)."""
    steps = episode("arm-0", name, n)
    for t, s in enumerate(steps):
        enc = tpb.ENCODING_RAW if raw_every and t % raw_every == 0 else encoding
        s.observation.tensors[CAM].CopyFrom(wire.to_tensor(_frame(t), enc, jpeg_quality=90))
        if s.HasField("final_observation"):
            s.final_observation.tensors[CAM].CopyFrom(wire.to_tensor(_frame(t + 1), encoding, jpeg_quality=90))
    return steps


def _same_as_decoded(kept: dict[str, Any], decoded: dict[str, Any]) -> None:
    np.testing.assert_array_equal(kept["indices"], decoded["indices"])
    for part in ("observation", "next_observation"):
        frames = kept[part][CAM]
        assert isinstance(frames, wire.EncodedFrames)
        sent = tpb.Tensor.FromString(wire.frames_tensor(frames).SerializeToString())
        assert len(sent.frame_bytes) == len(kept["indices"]) and sent.ByteSize() < decoded[part][CAM].nbytes / 4
        np.testing.assert_array_equal(wire.from_tensor(sent), decoded[part][CAM])
        np.testing.assert_array_equal(kept[part]["state"], decoded[part]["state"])


@pytest.mark.parametrize("encoding", ["jpeg", "png"])
@pytest.mark.parametrize("hot", ["all", "part", "none"])
def test_kept_frames_decode_to_the_frames_replay_decodes(tmp_path: Path, encoding: str, hot: str) -> None:
    """Frames replay stores as JPEG/PNG: with encoded_frames the batch holds their bytes, which decode to the same
    frames as a plain sample of the same draws; from the hot tier, from LMDB, and from both in one batch."""
    store = ReplayStore(tmp_path / "r", 64, cache_mb=64 if hot == "all" else 0, image_encoding={"*": encoding})
    if hot == "part":
        store.hot_bytes = 80_000  # the hot tier holds the newest ~40 frames
    try:
        store.put_steps(camera_steps("e", 120))
        for seed in range(3):
            kept = store.sample(64, np.random.default_rng(seed), draw=Draw(64, encoded_frames=True))
            plain = store.sample(64, np.random.default_rng(seed))
            _same_as_decoded(kept, plain)
        info = store.cache_info()
        if hot == "part":
            assert info["hits"] > 0 and info["misses"] > 0
    finally:
        store.close()


def test_frames_sent_as_jpeg_by_the_edge_pass_through_as_sent(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "r", 64)  # no image_encoding: replay keeps what the edge sent
    try:
        steps = camera_steps("e", 30, tpb.ENCODING_JPEG)
        store.put_steps(steps)
        sent = {s.step_index: s.observation.tensors[CAM].data for s in steps}
        kept = store.sample(32, np.random.default_rng(0), draw=Draw(32, encoded_frames=True))
        frames = kept["observation"][CAM]
        for t, blob in zip(kept["observation"]["state"][:, 0].astype(int), frames.blobs, strict=True):
            assert blob == sent[t]  # the edge's own bytes: not decoded, not re-encoded
        _same_as_decoded(kept, store.sample(32, np.random.default_rng(0)))
    finally:
        store.close()


def test_mixed_encodings_come_decoded(tmp_path: Path) -> None:
    """Some frames raw, some JPEG (an edge that changed its setting): the feature comes decoded, still right."""
    store = ReplayStore(tmp_path / "r", 64)
    try:
        store.put_steps(camera_steps("e", 40, tpb.ENCODING_JPEG, raw_every=2))
        kept = store.sample(64, np.random.default_rng(0), draw=Draw(64, encoded_frames=True))
        plain = store.sample(64, np.random.default_rng(0))
        for part in ("observation", "next_observation"):
            assert isinstance(kept[part][CAM], np.ndarray)
            np.testing.assert_array_equal(kept[part][CAM], plain[part][CAM])
    finally:
        store.close()


def test_frame_stacks_of_kept_frames(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "r", 64, image_encoding={"*": "jpeg"})
    try:
        store.put_steps(camera_steps("e", 50))
        kept = store.sample(16, np.random.default_rng(1), draw=Draw(16, frame_stack=3, encoded_frames=True))
        plain = store.sample(16, np.random.default_rng(1), draw=Draw(16, frame_stack=3))
        for part in ("observation", "next_observation"):
            frames = kept[part][CAM]
            assert isinstance(frames, wire.EncodedFrames) and frames.blobs.shape == (16, 3)
            tensor = wire.frames_tensor(frames)
            assert list(tensor.shape) == [16, 3, 64, 64, 3] and tensor.batch_dims == 2
            np.testing.assert_array_equal(wire.from_tensor(tensor), plain[part][CAM])
    finally:
        store.close()


def _frames_tensor(n: int = 4) -> tpb.Tensor:
    blobs = np.empty(n, object)
    blobs[:] = [wire.encode_image(_frame(t), tpb.ENCODING_JPEG) for t in range(n)]
    return wire.frames_tensor(wire.EncodedFrames(blobs, tpb.ENCODING_JPEG, (64, 64, 3)))


def _broken(how: str) -> tpb.Tensor:
    t = _frames_tensor()
    if how == "sizes":
        t.frame_bytes[0] += 1
    elif how == "count":
        del t.frame_bytes[-1]
    elif how == "batch_dims":
        t.batch_dims = 3
    elif how == "raw":
        t.encoding = tpb.ENCODING_RAW
    elif how == "shape":
        t.shape[1] = 32
    elif how == "corrupt":
        first = t.frame_bytes[0]
        t.data = t.data[:first] + b"\xff\xd8" + bytes(t.frame_bytes[1] - 2) + t.data[first + t.frame_bytes[1] :]
    elif how == "huge":
        t.shape[0] = 1 << 40
    return t


@pytest.mark.parametrize("how", ["sizes", "count", "batch_dims", "raw", "shape", "corrupt", "huge"])
def test_malformed_frame_batches_are_refused(how: str) -> None:
    assert wire.from_tensor(_frames_tensor()).shape == (4, 64, 64, 3)
    with pytest.raises(wire.WireError):
        wire.from_tensor(_broken(how))


# --------------------------------------------------------------------------- through the service


def camera_spec(robot_id: str) -> robot_pb2.RobotSpec:
    s = spec(robot_id)
    s.observation.append(robot_pb2.FeatureSpec(name=CAM, dtype=tpb.DTYPE_UINT8, shape=[64, 64, 3]))
    return s


@pytest.fixture
def service(tmp_path: Path) -> Iterator[ReplayService]:
    cfg = StackConfig(auth=AUTH)
    rc = cfg.replay
    rc.path, rc.map_size_mb, rc.shm_dir = tmp_path / "replay", 64, None
    rc.server.port = rc.server.metrics_port = 0
    svc = ReplayService(cfg, spec_source={"arm-0": camera_spec("arm-0")}.get, start_metrics=False).start()
    yield svc
    svc.stop()


def test_sample_over_grpc_sends_the_edge_jpegs_and_they_decode_to_the_stored_frames(service: ReplayService) -> None:
    steps = camera_steps("e", 40, tpb.ENCODING_JPEG)
    expected = {s.step_index: wire.from_tensor(s.observation.tensors[CAM]) for s in steps}
    stub = replay_pb2_grpc.ReplayStub(make_channel(service.address, AUTH))
    acks = list(stub.Insert(iter(replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)), timeout=30))
    assert sum(len(a.seqs) for a in acks) == 40
    kept = stub.Sample(replay_pb2.SampleRequest(batch_size=64, encoded_frames=True), timeout=10)
    plain = stub.Sample(replay_pb2.SampleRequest(batch_size=64), timeout=10)
    tensor = kept.batch.observation.tensors[CAM]
    assert tensor.encoding == tpb.ENCODING_JPEG and len(tensor.frame_bytes) == 64 and tensor.batch_dims == 1
    assert plain.batch.observation.tensors[CAM].encoding == tpb.ENCODING_RAW
    assert kept.batch.ByteSize() < plain.batch.ByteSize() / 4
    frames = wire.from_tensor(tensor)
    state = wire.from_tensor(kept.batch.observation.tensors["state"])
    assert frames.shape == (64, 64, 64, 3) and state.shape == (64, OBS_DIM)
    for t, frame in zip(state[:, 0].astype(int), frames, strict=True):
        np.testing.assert_array_equal(frame, expected[t])
    with pytest.raises(grpc.RpcError) as err:  # still validated like any sample request
        stub.Sample(replay_pb2.SampleRequest(batch_size=0, encoded_frames=True), timeout=10)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


@pytest.mark.parametrize("encoding", [tpb.ENCODING_JPEG, tpb.ENCODING_RAW])
def test_a_step_whose_frame_claims_to_be_a_batch_is_refused(service: ReplayService, encoding: int) -> None:
    """frame_bytes/batch_dims belong to sampled batches: a step carrying them is INVALID_ARGUMENT, nothing stored."""
    stub = replay_pb2_grpc.ReplayStub(make_channel(service.address, AUTH))
    step = camera_steps("bad", 2, encoding)[0]
    step.observation.tensors[CAM].frame_bytes.append(len(step.observation.tensors[CAM].data))
    with pytest.raises(grpc.RpcError) as err:
        list(stub.Insert(iter([replay_pb2.InsertRequest(seq=0, step=step)]), timeout=10))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert stub.Stats(replay_pb2.StatsRequest(), timeout=10).steps == 0


def test_shards_kept_frames_are_joined_without_decoding() -> None:
    """The learner's ShardedSampler joins shards' batches: kept JPEG frames stay encoded (decoded once, by the
    learner); mixed with raw frames from another shard they are decoded and joined as raw."""
    from cloud_learner.replay_sampler import merge_batches

    def batch(frames: tpb.Tensor, n: int) -> replay_pb2.Batch:
        b = replay_pb2.Batch(reward=wire.to_tensor(np.zeros(n, np.float32)))
        for tmap in (b.observation, b.next_observation):
            tmap.tensors[CAM].CopyFrom(frames)
        return b

    one, two = _frames_tensor(4), _frames_tensor(3)
    merged = merge_batches([batch(one, 4), batch(two, 3)]).observation.tensors[CAM]
    assert list(merged.frame_bytes) == [*one.frame_bytes, *two.frame_bytes] and merged.shape[0] == 7
    expected = np.concatenate([wire.from_tensor(one), wire.from_tensor(two)])
    np.testing.assert_array_equal(wire.from_tensor(merged), expected)
    raw = wire.to_tensor(wire.from_tensor(two))
    mixed = merge_batches([batch(one, 4), batch(raw, 3)]).observation.tensors[CAM]
    assert not mixed.frame_bytes and mixed.encoding == tpb.ENCODING_RAW
    np.testing.assert_array_equal(wire.from_tensor(mixed), expected)
