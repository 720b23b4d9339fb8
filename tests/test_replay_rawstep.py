"""rawstep: tensor spans found in serialized Steps agree with protobuf's own parse, and odd bytes are declined."""

from __future__ import annotations

import numpy as np
import pytest

from services.replay.rawstep import Unexpected, step_spans
from services.replay.tables import Draw
from user import wire
from user.v1 import step_pb2
from user.v1 import tensor_pb2 as tpb


def check(step: step_pb2.Step) -> None:
    raw = step.SerializeToString()
    spans = step_spans(memoryview(raw))
    parsed = step_pb2.Step.FromString(raw)
    for tmap, got in ((parsed.observation, spans.observation), (parsed.final_observation, spans.final or {})):
        assert set(got) == set(tmap.tensors)
        for name, tensor in tmap.tensors.items():
            sp = got[name]
            assert (sp.dtype, sp.shape, sp.encoding) == (tensor.dtype, tuple(tensor.shape), tensor.encoding)
            assert raw[sp.offset : sp.offset + sp.size] == tensor.data
    assert (spans.final is not None) == parsed.HasField("final_observation")
    if parsed.HasField("action"):
        assert spans.action is not None
        assert raw[spans.action.offset : spans.action.offset + spans.action.size] == parsed.action.data
        assert spans.action.shape == tuple(parsed.action.shape)


@pytest.mark.parametrize("seed", range(8))
def test_spans_match_protobuf(seed: int) -> None:
    rng = np.random.default_rng(seed)
    obs = {"state": rng.standard_normal(int(rng.integers(0, 300))).astype(np.float32)}
    obs["camera.fr\u00f6nt"] = rng.integers(0, 256, (int(rng.integers(1, 200)), 7, 3), dtype=np.uint8)
    obs["empty"] = np.zeros((0, 3), np.float32)  # no data field on the wire
    step = step_pb2.Step(
        robot_id="r" * int(rng.integers(0, 300)),  # long strings: multi-byte length varints
        episode_id="e",
        step_index=int(rng.integers(0, 1 << 40)),
        observation=wire.to_tensor_map(obs),
        action=wire.to_tensor(rng.uniform(-1, 1, 3).astype(np.float32)),
        reward=float(rng.standard_normal()),
        policy_version=int(rng.integers(0, 1 << 62)),
        observed_at_ns=-int(rng.integers(1, 1 << 60)),  # negative int64: a 10-byte varint
        terminated=bool(seed % 2),
    )
    if seed % 2:
        step.final_observation.CopyFrom(wire.to_tensor_map(obs))
    check(step)
    step.observation.tensors["camera.jpeg"].CopyFrom(
        wire.to_tensor(rng.integers(0, 256, (16, 16, 3), dtype=np.uint8), tpb.ENCODING_JPEG)
    )
    check(step)


def test_odd_bytes_are_declined() -> None:
    step = step_pb2.Step(robot_id="r", observation=wire.to_tensor_map({"state": np.ones(3, np.float32)}))
    raw = step.SerializeToString()
    with pytest.raises(Unexpected):
        step_spans(memoryview(raw + raw))  # observation twice: protobuf would merge, the walker declines
    with pytest.raises((Unexpected, IndexError)):
        step_spans(memoryview(raw[:-1]))  # truncated
    with pytest.raises(Unexpected):
        step_spans(memoryview(bytes([0x0B]) + raw))  # a group (wire type 3)


def camera_episode(name: str, length: int, rng: np.random.Generator) -> list[step_pb2.Step]:
    steps = []
    for t in range(length):
        obs = {"state": np.full(4, t, np.float32), "camera.front": rng.integers(0, 256, (48, 48, 3), dtype=np.uint8)}
        step = step_pb2.Step(robot_id="cam-0", episode_id=name, step_index=t, observation=wire.to_tensor_map(obs),
                             action=wire.to_tensor(np.full(2, t, np.float32)), reward=float(t))  # fmt: skip
        if t == length - 1:
            step.truncated = True
            step.final_observation.CopyFrom(wire.to_tensor_map({**obs, "state": np.full(4, t + 1, np.float32)}))
        steps.append(step)
    return steps


@pytest.mark.parametrize("cache_mb", [0, 1])
def test_cold_camera_reads_equal_the_protobuf_path(tmp_path, monkeypatch, cache_mb: int) -> None:
    """Camera-sized steps read from LMDB pages (rawstep) give the batch protobuf parsing gives, with the hot
    tier off (all cold) and small (mixed hot and cold rows)."""
    from services.replay import store as store_mod
    from services.replay.store import ReplayStore

    rng = np.random.default_rng(0)
    store = ReplayStore(tmp_path / "replay", 64, cache_mb=cache_mb)
    try:
        for e in range(30):
            store.put_steps(camera_episode(f"e{e:02d}", 20, rng))
        walked = []
        monkeypatch.setattr(store_mod, "step_spans", lambda buf: walked.append(1) or step_spans(buf))
        fast = store.sample(512, np.random.default_rng(1), draw=Draw(512, n_step=3, gamma=0.9))
        assert walked  # the cold rows came through rawstep
        info = store.cache_info()
        assert info["misses"] > 0 and (info["hits"] > 0) == bool(cache_mb)
        monkeypatch.setattr(store_mod, "RAW_READ_MIN_BYTES", 1 << 40)  # force the protobuf path
        slow = store.sample(512, np.random.default_rng(1), draw=Draw(512, n_step=3, gamma=0.9))
    finally:
        store.close()
    for part in ("observation", "next_observation"):
        for name in ("state", "camera.front"):
            np.testing.assert_array_equal(fast[part][name], slow[part][name])
    np.testing.assert_array_equal(fast["action"], slow["action"])
    t = fast["observation"]["state"][:, 0]
    np.testing.assert_array_equal(fast["next_observation"]["state"][:, 0], t + fast["n_steps"])
    np.testing.assert_array_equal(fast["action"][:, 0], t)
