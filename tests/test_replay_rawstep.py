"""rawstep: tensor spans found in serialized Steps agree with protobuf's own parse, and odd bytes are declined."""

from __future__ import annotations

import numpy as np
import pytest

from services.replay.rawstep import Unexpected, step_spans
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
