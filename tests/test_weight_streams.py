"""Acked weight streams: lossy and delta encodings, base fallbacks, per-link isolation, corrupt chunks,
tensor selection, experiments, and versions that stay unique across a learner kill -9."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest

from tests import helpers
from user import rpc, wire
from user.config import AuthConfig, ServerConfig, StackConfig
from user.v1 import learner_pb2, learner_pb2_grpc
from user.v1 import tensor_pb2 as tpb
from user.weight_codec import WE, WeightAssembler, encode, iter_weight_messages, pack_weights, wire_payload
from user.weights import (
    Link,
    WeightServicer,
    WeightSet,
    WeightStore,
    WeightSubscriber,
    add_learner_servicer,
    choose_encoding,
)

AUTH = AuthConfig(token="test-token")
SPEC = learner_pb2.PolicySpec(kind="test", config_json="{}")
SERVICE = learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name


def tensors(seed: int = 0, n: int = 4096) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "actor.w": rng.standard_normal((n // 64, 64)).astype(np.float32) * 0.1,
        "actor.b": rng.standard_normal(64).astype(np.float32),
        "actor.steps": np.arange(5, dtype=np.int64),  # non-float tensors travel exactly in every encoding
        "critic.w": rng.standard_normal((n // 64, 64)).astype(np.float32),
    }


def trained(prev: dict[str, np.ndarray], seed: int, lr: float = 1e-4) -> dict[str, np.ndarray]:
    """The next version as training makes it: every float weight moves a little."""
    rng = np.random.default_rng(seed)
    out = {}
    for k, v in prev.items():
        out[k] = (v + lr * rng.standard_normal(v.shape).astype(np.float32)) if v.dtype == np.float32 else v.copy()
    return out


def decode(packed, assembler: WeightAssembler | None = None) -> WeightSet:
    assembler = assembler or WeightAssembler()
    out = None
    for msg in iter_weight_messages(packed, 4096):
        out = assembler.feed(msg)
    assert out is not None
    return out


# --------------------------------------------------------------------------- codec


@pytest.mark.parametrize(
    ("code", "bound"), [(tpb.DTYPE_BFLOAT16, 2.0**-8), (tpb.DTYPE_FLOAT16, 2.0**-11)], ids=["bf16", "fp16"]
)
def test_half_precision_round_trip_within_stated_error(code: int, bound: float) -> None:
    x = (np.random.default_rng(0).standard_normal(10_000) * 10).astype(np.float32)
    x = x[np.abs(x) > 1e-3]  # normal range of both formats: relative error is half a unit in the last place
    for y in (wire.from_wire_dtype(wire.to_wire_dtype(x, code), code), wire.from_tensor(wire.to_tensor(x, 0, code))):
        y = y.astype(np.float32)  # bf16 decodes to float32; an fp16 Tensor stays float16
        assert np.max(np.abs(y - x) / np.abs(x)) <= bound
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan], dtype=np.float32)
    back = wire.from_wire_dtype(wire.to_wire_dtype(special, code), code)
    assert np.array_equal(back[:4], special[:4]) and np.isnan(back[4])


def test_bf16_rounds_to_nearest_even() -> None:
    # 1 + 2^-8 lies halfway between bf16 neighbours 1 and 1 + 2^-7: ties go to the even one (1.0).
    x = np.array([1 + 2**-8, 1 + 3 * 2**-8, 1 + 2**-8 + 2**-20], dtype=np.float32)
    back = wire.from_wire_dtype(wire.to_wire_dtype(x, tpb.DTYPE_BFLOAT16), tpb.DTYPE_BFLOAT16)
    assert back.tolist() == [1.0, 1 + 2 * 2**-7, 1 + 2**-7]


@pytest.mark.parametrize(
    "encoding",
    [WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD, WE.WEIGHT_ENCODING_FP16_DELTA_ZSTD, WE.WEIGHT_ENCODING_BF16_DELTA_ZSTD],
)
def test_delta_round_trip_equals_the_full_set(encoding: int) -> None:
    from user.weight_codec import CODECS, FULL_OF

    v1, v2 = tensors(0), None
    v2 = trained(v1, 1)
    full1, full2 = pack_weights(1, SPEC, v1), pack_weights(2, SPEC, v2)
    wd, prefixes = CODECS[encoding].wire_dtype, ("",)
    receiver = WeightAssembler()
    decode(encode(full1, FULL_OF[encoding], wire_payload(full1, wd, prefixes)), receiver)
    delta = encode(full2, encoding, wire_payload(full2, wd, prefixes), wire_payload(full1, wd, prefixes))
    assert delta.header.base_version == 1
    got = decode(delta, receiver).tensors
    want = decode(encode(full2, FULL_OF[encoding], wire_payload(full2, wd, prefixes))).tensors
    for name in v2:
        assert np.array_equal(got[name], want[name]), name  # the delta loses nothing beyond the wire dtype
    if wd == tpb.DTYPE_FLOAT32:
        assert all(np.array_equal(got[k], v2[k]) for k in v2)
    # training moves weights a little: most high bits stay, so the XOR compresses
    assert delta.encoded_bytes < 0.8 * wire_payload(full2, wd, prefixes).payload.nbytes


def test_delta_against_missing_or_wrong_base_is_rejected() -> None:
    v1, v2 = tensors(0), trained(tensors(0), 1)
    full1, full2 = pack_weights(1, SPEC, v1), pack_weights(2, SPEC, v2)
    fp32, prefixes = tpb.DTYPE_FLOAT32, ("",)
    delta = encode(
        full2,
        WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD,
        wire_payload(full2, fp32, prefixes),
        wire_payload(full1, fp32, prefixes),
    )
    with pytest.raises(wire.WireError, match="this client holds none"):
        decode(delta, WeightAssembler())
    # A base with the right number but other bits (e.g. from another learner): the digest catches it.
    impostor = WeightAssembler()
    decode(pack_weights(1, SPEC, tensors(7)), impostor)
    with pytest.raises(wire.WireError, match="mismatch"):
        decode(delta, impostor)
    # ...and the assembler carries on: the full set decodes.
    assert decode(pack_weights(2, SPEC, v2), impostor).version == 2


def test_server_falls_back_to_a_full_set_when_the_base_left_the_history() -> None:
    store = WeightStore(history=2)
    t = tensors(0)
    for v in (1, 2, 3):
        t = trained(t, v)
        store.publish(v, SPEC, t)
    link = Link("c", "", ("",), False, WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD, 1.0, True, base_version=1)
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32_ZSTD, 0)
    link.base_version = 2
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD, 2)
    link.base_wire_dtype = tpb.DTYPE_FLOAT16  # the client holds an fp16 payload: no fp32 delta against it
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32_ZSTD, 0)


def test_adaptive_choice_follows_the_link() -> None:
    store = WeightStore()
    t = tensors(0, n=1 << 16)
    store.publish(1, SPEC, t)
    store.publish(2, SPEC, trained(t, 2))
    link = Link("c", "", ("",), True, 0, 1.0, True, base_version=1)
    assert choose_encoding(store, link, store.latest())[0] == WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD  # unmeasured
    link.goodput_bps = 10e9  # faster than zstd: raw
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32, 0)
    link.goodput_bps = 1e3  # far too slow for lossless within 1 s, but the client's exact state is unknown
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD, 1)
    link.base_digest = store.wire(store.get(1), tpb.DTYPE_FLOAT32, ("",)).digest  # it holds v1 exactly: a patch
    patch = WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD  # streamed: encode, transfer and apply overlap
    assert choose_encoding(store, link, store.latest()) == (patch, 1)
    link.patches_in_row = 16  # the periodic exact resync
    assert choose_encoding(store, link, store.latest(), keyframe_every=16)[0] != patch
    link.patches_in_row = 0
    link.allow_lossy = False
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD, 1)
    link.base_patched = True  # its payload came from a patch: no XOR delta against v1's own payload
    assert choose_encoding(store, link, store.latest()) == (WE.WEIGHT_ENCODING_FP32_ZSTD, 0)


def test_adaptive_choice_counts_the_clients_measured_decode_time() -> None:
    store = WeightStore()
    t = tensors(0, n=1 << 16)
    store.publish(1, SPEC, t)
    store.publish(2, SPEC, trained(t, 2))
    delta, fp32 = WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD, WE.WEIGHT_ENCODING_FP32
    link = Link("c", "", ("",), False, 0, 1.0, True, base_version=1, goodput_bps=200e6)
    store.encoded(store.latest(), delta, ("",), 1)  # encoded once already (another subscriber): no encode cost
    assert choose_encoding(store, link, store.latest()) == (delta, 1)  # fewer bytes, decode not measured yet
    link.decode_bps[delta] = 50e6  # the client's acks: decompress + XOR is slower than the link
    assert choose_encoding(store, link, store.latest()) == (fp32, 0)
    link.goodput_bps = 1e6  # a slow link: the bytes saved matter more than the client's decode
    assert choose_encoding(store, link, store.latest()) == (delta, 1)


def _patch_bound(new: dict[str, np.ndarray], old: dict[str, np.ndarray]) -> np.ndarray:
    """Per float32 element (in payload order) the error a patch from `old` to `new` may make."""
    from user.weight_codec import PATCH_BLOCK, PATCH_REL_TOL

    n = np.concatenate([v.ravel() for v in new.values() if v.dtype == np.float32]).astype(np.float64)
    o = np.concatenate([v.ravel() for v in old.values() if v.dtype == np.float32]).astype(np.float64)
    blocks = -(-n.size // PATCH_BLOCK)
    pad = blocks * PATCH_BLOCK - n.size
    nb, db = np.pad(n, (0, pad)).reshape(blocks, -1), np.pad(n - o, (0, pad)).reshape(blocks, -1)
    step = np.maximum(2 * PATCH_REL_TOL * np.sqrt((nb * nb).mean(axis=1)), np.abs(db).max(axis=1) / 127)
    rounding = np.spacing(np.abs(n).astype(np.float32)).astype(np.float64)  # of the float32 sum
    # 1e-4: the sender accumulates the RMS in float32
    return np.repeat(step / 2, PATCH_BLOCK)[: n.size] * (1 + 1e-4) + rounding


def _f32(ts: dict[str, np.ndarray]) -> np.ndarray:
    return np.concatenate([v.ravel() for v in ts.values() if v.dtype == np.float32])


def test_patch_round_trip_stays_within_its_error_bound_and_does_not_accumulate() -> None:
    from user.weight_codec import encode_patch

    fp32, prefixes = tpb.DTYPE_FLOAT32, ("",)
    t = tensors(0, n=1 << 14)
    full = pack_weights(1, SPEC, t)
    receiver = WeightAssembler()
    decode(encode(full, WE.WEIGHT_ENCODING_FP32, wire_payload(full, fp32, prefixes)), receiver)
    state = wire_payload(full, fp32, prefixes)
    held = dict(t)
    for v in range(2, 8):
        t = trained(t, v, lr=1e-3)
        full = pack_weights(v, SPEC, t)
        patch, state = encode_patch(full, wire_payload(full, fp32, prefixes), state)
        assert patch.header.base_digest == receiver.base_digest
        got = decode(patch, receiver)  # the digest check passing = both sides hold the same bits
        assert got.encoding == WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD and receiver.base_digest == state.digest
        err = np.abs(_f32(got.tensors).astype(np.float64) - _f32(t))
        assert (err <= _patch_bound(t, held)).all()  # bounded by this patch's steps: nothing carried over
        assert np.array_equal(got.tensors["actor.steps"], t["actor.steps"])  # non-float tensors exact
        assert err.max() > 0  # lossy indeed (a test that cannot fail is a defect)
        held = got.tensors
    assert patch.encoded_bytes < 0.3 * full.nbytes


def test_patch_against_a_wrong_or_missing_base_and_corrupt_patches_are_rejected() -> None:
    from user.weight_codec import encode_patch

    fp32, prefixes = tpb.DTYPE_FLOAT32, ("",)
    v1, v2 = tensors(0), trained(tensors(0), 1)
    full1, full2 = pack_weights(1, SPEC, v1), pack_weights(2, SPEC, v2)
    patch, _ = encode_patch(full2, wire_payload(full2, fp32, prefixes), wire_payload(full1, fp32, prefixes))
    with pytest.raises(wire.WireError, match="this client holds none"):
        decode(patch, WeightAssembler())
    impostor = WeightAssembler()  # v1 by number, other bits: its digest is not the patch's base
    decode(pack_weights(1, SPEC, tensors(7)), impostor)
    with pytest.raises(wire.WireError, match="holds v1"):
        decode(patch, impostor)
    assert decode(pack_weights(2, SPEC, v2), impostor).version == 2  # carries on with a full set
    for flip in (20, patch.encoded_bytes - 20):  # in the steps / the int8 body or zstd's frame
        good = WeightAssembler()
        decode(pack_weights(1, SPEC, v1), good)
        data = bytearray(bytes(patch.payload))
        data[flip] ^= 0x55
        bad = type(patch)(patch.header, bytes(data))
        with pytest.raises(wire.WireError):
            decode(bad, good)
        assert good.base_version == 1  # the held payload survives for the full-set fallback


@pytest.mark.parametrize(
    "patch", [WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD, WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD], ids=["oneshot", "stream"]
)
def test_patches_flow_with_periodic_exact_resyncs_and_fall_back_on_a_lost_base(patch: int) -> None:
    store = WeightStore()
    srv = Server(store, WeightServicer(store, poll_s=0.1, keyframe_every=2))
    sub, got = subscribe(srv, "edge-1", encoding=patch, allow_lossy=True)
    try:
        t = tensors(0)
        for v in range(1, 6):
            store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            t = trained(t, v, lr=1e-3)
        full = WE.WEIGHT_ENCODING_FP32_ZSTD
        assert [w.encoding for w in got] == [full, patch, patch, full, patch]  # keyframe after 2 patches
        helpers.wait_for(lambda: srv.servicer.subscriber_status()[0].applied_version == 5, "ack of v5")
        sub._assembler.forget_base()  # a client that lost its state: the patch is rejected, a full set follows
        store.publish(6, SPEC, t)
        assert sub.wait_version(6, 30)
        assert sub.rejected == 1 and sub.connects == 1 and got[-1].encoding == full
        assert all(np.array_equal(got[-1].tensors[k], t[k]) for k in t)
    finally:
        sub.stop()
        srv.close()


def _streamed(full, wire, base, chunk: int = 4096, level: int = 1) -> tuple[list[bytes], object]:
    """A streamed patch's frames as a subscriber receives them, and the state the sender reached."""
    from user.weight_codec import StreamedPatch, encode_patch_stream, iter_weight_frames, patch_header

    sink = StreamedPatch(patch_header(full, wire, base))
    reached = []
    encode = lambda: reached.append(encode_patch_stream(full, wire, base, sink, level=level))  # noqa: E731
    encoder = threading.Thread(target=encode)
    encoder.start()  # frames are read while later slices are still being quantized
    frames = list(iter_weight_frames(sink, chunk))
    encoder.join()
    return frames, reached[0]


def _feed(frames: list[bytes], receiver: WeightAssembler) -> WeightSet | None:
    from user.weight_codec import parse_weight_message

    out = None
    for frame in frames:
        out = receiver.feed(parse_weight_message(frame))
    return out


@pytest.mark.parametrize(
    ("pipelined", "level"), [(False, 1), (True, 1), (False, -1)], ids=["one-thread", "pipelined", "stored"]
)
def test_streamed_patch_leads_to_the_same_bits_as_the_one_shot_patch_within_its_bound(
    pipelined: bool, level: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """stored: zstd's fast level (PATCH_FAST_LEVEL, for fast links), every slice its own piece."""
    from user import weight_codec
    from user.weight_codec import PATCH_BLOCK, PATCH_SLICE_BLOCKS, encode_patch, patch_body_bytes

    # one slice per flushed piece: with 4 slices the quantizer and zstd take turns on their own threads
    monkeypatch.setattr(weight_codec, "PATCH_FLUSH_BYTES", 1)
    monkeypatch.setattr(weight_codec, "PATCH_PIPELINE_FROM", 3 if pipelined else 1 << 30)

    fp32, prefixes = tpb.DTYPE_FLOAT32, ("",)
    n = 3 * PATCH_SLICE_BLOCKS * PATCH_BLOCK + 1000  # several slices, the last one partial
    v1 = tensors(0, n=n)
    v2 = trained(v1, 1, lr=1e-3)
    full1, full2 = pack_weights(1, SPEC, v1), pack_weights(2, SPEC, v2)
    base, wire2 = wire_payload(full1, fp32, prefixes), wire_payload(full2, fp32, prefixes)
    receiver = WeightAssembler()
    decode(full1, receiver)
    frames, reached = _streamed(full2, wire2, base, level=level)
    assert len(frames) > 3  # header, chunks, trailer
    got = _feed(frames, receiver)
    assert got is not None and got.version == 2 and got.encoding == WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD
    _, state = encode_patch(full2, wire2, base)
    # Lossless where it must be: receiver, streaming sender and one-shot sender hold the same bits.
    assert np.array_equal(receiver.held.payload, state.payload) and np.array_equal(reached.payload, state.payload)
    assert receiver.base_digest == reached.digest == state.digest
    err = np.abs(_f32(got.tensors).astype(np.float64) - _f32(v2))
    assert (err <= _patch_bound(v2, v1)).all() and err.max() > 0
    assert np.array_equal(got.tensors["actor.steps"], v2["actor.steps"])
    assert got.encoded_bytes < (0.5 if level > 0 else 1.01) * patch_body_bytes(wire2.tensors)


def test_streamed_patch_corrupt_truncated_aborted_or_on_a_wrong_base_is_rejected() -> None:
    from user.weight_codec import (
        PatchError,
        StreamedPatch,
        encode_patch_stream,
        iter_weight_frames,
        patch_header,
    )

    fp32, prefixes = tpb.DTYPE_FLOAT32, ("",)
    v1, v2 = tensors(0, n=1 << 16), trained(tensors(0, n=1 << 16), 1)
    full1, full2 = pack_weights(1, SPEC, v1), pack_weights(2, SPEC, v2)
    base, wire2 = wire_payload(full1, fp32, prefixes), wire_payload(full2, fp32, prefixes)
    frames, _ = _streamed(full2, wire2, base)

    def holding_v1() -> WeightAssembler:
        r = WeightAssembler()
        decode(full1, r)
        return r

    for i in (1, len(frames) // 2, len(frames) - 2):  # a flipped byte in the first, a middle, the last data chunk
        bad = bytearray(frames[i])
        bad[-3] ^= 0x55
        r = holding_v1()
        with pytest.raises(wire.WireError):
            _feed([*frames[:i], bytes(bad), *frames[i + 1 :]], r)
        assert r.base_version == 1  # the held payload survives for the full-set fallback
    trailer = learner_pb2.WeightMessage.FromString(frames[-1])
    assert trailer.chunk.last and len(trailer.chunk.digest) == 16
    dropped = sum(len(learner_pb2.WeightMessage.FromString(f).chunk.data) for f in frames[-2:-1])
    trailer.chunk.offset -= dropped  # the stream ends one chunk early
    with pytest.raises(wire.WireError, match="ended before"):
        _feed([*frames[:-2], trailer.SerializeToString()], holding_v1())
    trailer.chunk.digest = b""  # the sender gave up (non-finite weights): ask for a full set
    with pytest.raises(wire.WireError, match="gave up"):
        _feed([*frames[:-2], trailer.SerializeToString()], holding_v1())
    with pytest.raises(wire.WireError, match="this client holds none"):
        _feed(frames, WeightAssembler())
    impostor = WeightAssembler()  # v1 by number, other bits
    decode(pack_weights(1, SPEC, tensors(7, n=1 << 16)), impostor)
    with pytest.raises(wire.WireError, match="holds v1"):
        _feed(frames, impostor)
    # A sender that hits non-finite weights mid-stream ends it with an empty digest.
    v3 = trained(v2, 2)
    v3["critic.w"][-1, -1] = np.inf
    full3 = pack_weights(3, SPEC, v3)
    sink = StreamedPatch(patch_header(full3, wire_payload(full3, fp32, prefixes), base))
    with pytest.raises(PatchError, match="non-finite"):
        encode_patch_stream(full3, wire_payload(full3, fp32, prefixes), base, sink)
    with pytest.raises(wire.WireError, match="gave up"):
        _feed(list(iter_weight_frames(sink, 4096)), holding_v1())


def test_pipelined_streamed_patch_that_meets_non_finite_weights_late_gives_up_and_stops_its_compressor(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from user import weight_codec
    from user.weight_codec import PATCH_BLOCK, PATCH_SLICE_BLOCKS, PatchError, StreamedPatch, encode_patch_stream

    monkeypatch.setattr(weight_codec, "PATCH_FLUSH_BYTES", 1)  # a piece per slice: pipelined from 3 slices
    fp32, prefixes = tpb.DTYPE_FLOAT32, ("",)
    v1 = tensors(0, n=2 * PATCH_SLICE_BLOCKS * PATCH_BLOCK)  # 4 slices and a bit of float32
    v2 = trained(v1, 1)
    v2["critic.w"][-1, -1] = np.nan  # in the last slice: earlier pieces are out already
    full1, full2 = pack_weights(1, SPEC, v1), pack_weights(2, SPEC, v2)
    base, wire2 = wire_payload(full1, fp32, prefixes), wire_payload(full2, fp32, prefixes)
    sink = StreamedPatch(weight_codec.patch_header(full2, wire2, base))
    before = threading.active_count()
    with pytest.raises(PatchError, match="non-finite"):
        encode_patch_stream(full2, wire2, base, sink)
    assert sink.done and sink.error is not None
    helpers.wait_for(lambda: threading.active_count() <= before, "the compressor thread ends")
    receiver = WeightAssembler()
    decode(full1, receiver)
    with pytest.raises(wire.WireError, match="gave up"):
        _feed(list(weight_codec.iter_weight_frames(sink, 4096)), receiver)


@pytest.mark.parametrize("framed", [True, False], ids=["frames", "protobuf"])
def test_one_streamed_patch_fans_out_to_every_subscriber_holding_its_base(framed: bool) -> None:
    store = WeightStore()
    srv = Server(store, framed=framed)
    stream = WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD
    subs = [subscribe(srv, f"edge-{i}", encoding=stream, allow_lossy=True) for i in range(2)]
    encodes = []
    real = store._stream_patch
    store._stream_patch = lambda *a: encodes.append(a[0].version) or real(*a)  # count the encoder threads
    try:
        t = tensors(0, n=1 << 16)
        for v in range(1, 4):
            store.publish(v, SPEC, t)
            for sub, _ in subs:
                assert sub.wait_version(v, 30)
            helpers.wait_for(
                lambda v=v: all(st.applied_version == v for st in srv.servicer.subscriber_status()), f"acks of v{v}"
            )
            t = trained(t, v, lr=1e-3)
        (_, a), (_, b) = subs
        assert [w.encoding for w in a] == [WE.WEIGHT_ENCODING_FP32_ZSTD, stream, stream]
        assert [w.encoding for w in b] == [w.encoding for w in a]
        assert all(np.array_equal(a[-1].tensors[k], b[-1].tensors[k]) for k in t)  # the same bits on both
        assert encodes == [2, 3]  # one encode per (version, base), shared by both streams
    finally:
        for sub, _ in subs:
            sub.stop()
        srv.close()


@pytest.mark.parametrize("fast", [True, False], ids=["fast-link", "slow-link"])
def test_streamed_patch_is_stored_on_a_fast_link_and_compressed_on_a_slow_one(
    fast: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The link's goodput measured on whole versions decides; both decode to the sender's exact state."""
    from user import weights as weights_mod

    monkeypatch.setattr(weights_mod, "FAST_LINK_BPS", 0.0 if fast else float("inf"))
    store = WeightStore()
    srv = Server(store)
    stream = WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD
    sub, got = subscribe(srv, "edge", encoding=stream, allow_lossy=True)
    calls: list[bool] = []
    real = store._stream_patch
    store._stream_patch = lambda *a: calls.append(a[-1]) or real(*a)  # fast_link, per encode
    try:
        t = tensors(0, n=1 << 16)
        for v in range(1, 4):
            store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            helpers.wait_for(lambda v=v: srv.servicer.subscriber_status()[0].applied_version == v, f"ack of v{v}")
            t = trained(t, v, lr=1e-3)
        assert [w.encoding for w in got] == [WE.WEIGHT_ENCODING_FP32_ZSTD, stream, stream]
        assert calls == [fast, fast]
        held = store.state(sub._assembler.base_digest)
        assert held is not None and np.array_equal(held.payload, sub._assembler.held.payload)
    finally:
        sub.stop()
        srv.close()


def test_one_encode_per_version_encoding_and_base() -> None:
    store = WeightStore()
    store.publish(1, SPEC, tensors(0))
    full = store.latest()
    a = store.encoded(full, WE.WEIGHT_ENCODING_FP16_ZSTD, ("actor.",))
    assert store.encoded(full, WE.WEIGHT_ENCODING_FP16_ZSTD, ("actor.",)) is a
    assert store.encoded(full, WE.WEIGHT_ENCODING_FP16_ZSTD, ("",)) is not a
    assert [i.name for i in a.header.tensors] == ["actor.w", "actor.b", "actor.steps"]


def test_chunk_frames_are_the_protobuf_encoding_and_parse_without_copies() -> None:
    from google.protobuf.message import DecodeError

    from user.weight_codec import RawChunk, chunk_frame, iter_weight_frames, parse_weight_message

    data = bytes(range(256)) * 40
    for version, offset, part in [(1, 0, data), (2**40 + 3, 2**33, data[:1]), (7, 300, data[:129]), (0, 0, b"")]:
        want = learner_pb2.WeightMessage(chunk=learner_pb2.WeightChunk(version=version, offset=offset, data=part))
        frame = chunk_frame(version, offset, memoryview(part))
        assert frame == want.SerializeToString()
        got = parse_weight_message(frame)
        assert isinstance(got, RawChunk) and (got.version, got.offset, bytes(got.data)) == (version, offset, part)
    packed = pack_weights(3, SPEC, tensors(0))
    frames = list(iter_weight_frames(packed, 4096))
    assert frames == [m.SerializeToString() for m in iter_weight_messages(packed, 4096)]
    header = parse_weight_message(frames[0])  # anything but a lone chunk goes through protobuf
    assert isinstance(header, learner_pb2.WeightMessage) and header.header == packed.header
    extra = frames[1] + learner_pb2.WeightMessage(chunk=learner_pb2.WeightChunk(version=9)).SerializeToString()
    assert parse_weight_message(extra) == learner_pb2.WeightMessage.FromString(extra)  # merged: last one wins
    with pytest.raises(DecodeError):
        parse_weight_message(frames[1][:-1])  # truncated
    receiver = WeightAssembler()
    out = [receiver.feed(parse_weight_message(f)) for f in frames]
    assert out[-1] is not None and out[-1].version == 3


# --------------------------------------------------------------------------- streams


class Server:
    def __init__(
        self, store: WeightStore, servicer: WeightServicer | None = None, port: int = 0, framed: bool = True
    ) -> None:
        """framed: chunks go out as frames serialized straight from the payload (as the learner serves
        them); False: as protobuf messages (the generated registration)."""
        self.store = store
        self.servicer = servicer or WeightServicer(store, poll_s=0.1)
        register = add_learner_servicer if framed else learner_pb2_grpc.add_LearnerServicer_to_server
        self.running = rpc.start_server(
            "test-learner",
            lambda s: register(self.servicer, s),
            [SERVICE],
            ServerConfig(port=port, metrics_port=0, max_workers=16, grace_s=0.2),
            AUTH,
            start_metrics=False,
        )
        self.addr = self.running.address()

    def close(self) -> None:
        self.store.close()
        self.running.stop()


@pytest.fixture
def server() -> Iterator[Server]:
    srv = Server(WeightStore())
    yield srv
    srv.close()


def subscribe(srv: Server, client_id: str, **kw) -> tuple[WeightSubscriber, list[WeightSet]]:
    got: list[WeightSet] = []
    return WeightSubscriber(srv.addr, AUTH, client_id, got.append, max_chunk_bytes=4096, **kw).start(), got


def test_deltas_flow_and_acks_report_the_applied_version(server: Server) -> None:
    sub, got = subscribe(server, "edge-1", encoding=WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD)
    try:
        t = tensors(0)
        for v in (1, 2, 3):
            server.store.publish(v, SPEC, t)
            assert sub.wait_version(v, 30)
            t = trained(t, v)
        helpers.wait_for(lambda: server.servicer.subscriber_status()[0].applied_version == 3, "ack of v3")
        st = server.servicer.subscriber_status()[0]
        assert (st.client_id, st.staleness, st.versions_sent) == ("edge-1", 0, 3)
        assert st.goodput_mbit_s > 0 and st.sync_latency_s > 0
        assert [w.encoding for w in got] == [
            WE.WEIGHT_ENCODING_FP32_ZSTD,  # no base yet
            WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD,
            WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD,
        ]
        # default selection: what the PolicySpec needs (all tensors here; no tensor_prefix)
        assert set(got[-1].tensors) == set(t)
    finally:
        sub.stop()


def test_client_without_the_base_rejects_the_delta_and_gets_a_full_set(server: Server) -> None:
    sub, got = subscribe(server, "edge-1", encoding=WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD)
    try:
        v1 = tensors(0)
        server.store.publish(1, SPEC, v1)
        assert sub.wait_version(1, 30)
        helpers.wait_for(lambda: server.servicer.subscriber_status()[0].applied_version == 1, "ack of v1")
        sub._assembler.forget_base()  # e.g. a client that dropped its payload: the server still thinks v1
        v2 = trained(v1, 2)
        server.store.publish(2, SPEC, v2)
        assert sub.wait_version(2, 30)
        assert sub.rejected == 1 and sub.connects == 1  # re-fetched on the same stream
        assert got[-1].encoding == WE.WEIGHT_ENCODING_FP32_ZSTD
        assert all(np.array_equal(got[-1].tensors[k], v2[k]) for k in v2)
    finally:
        sub.stop()


class CorruptOnce(WeightServicer):
    """Flips a byte in the first payload chunk of the first version sent (a bad link or buggy proxy)."""

    def __init__(self, store: WeightStore) -> None:
        super().__init__(store, poll_s=0.1)
        self.corrupted = 0

    def _encode(self, link, full):  # type: ignore[no-untyped-def]
        packed = super()._encode(link, full)
        if self.corrupted:
            return packed
        self.corrupted += 1
        msgs = list(iter_weight_messages(packed, 4096))
        bad = learner_pb2.WeightMessage()
        bad.CopyFrom(msgs[1])
        data = bytearray(bad.chunk.data)
        data[10] ^= 0xFF
        bad.chunk.data = bytes(data)
        out = type(packed)(packed.header, packed.payload)
        out._chunk_cache[4096] = [msgs[0], bad, *msgs[2:]]
        return out


def test_corrupt_chunk_is_rejected_and_refetched() -> None:
    store = WeightStore()
    srv = Server(store, CorruptOnce(store), framed=False)  # corrupts a cached protobuf chunk message
    sub, got = subscribe(srv, "edge-1")
    try:
        v1 = tensors(0)
        store.publish(1, SPEC, v1)
        assert sub.wait_version(1, 30)
        assert srv.servicer.corrupted == 1 and sub.rejected == 1 and sub.connects == 1
        assert len(got) == 1 and all(np.array_equal(got[0].tensors[k], v1[k]) for k in v1)
    finally:
        sub.stop()
        srv.close()


def test_stalled_subscriber_does_not_delay_another_or_the_publisher(server: Server) -> None:
    # The stalled one subscribes and never reads or acks: gRPC flow control holds its stream, and only its.
    channel = rpc.make_channel(server.addr, AUTH)
    stub = learner_pb2_grpc.LearnerStub(channel)
    first = learner_pb2.WeightAck(subscribe=learner_pb2.SubscribeWeightsRequest(client_id="stalled"))
    hold = threading.Event()

    def requests() -> Iterator[learner_pb2.WeightAck]:
        yield first
        hold.wait(120)  # never acks

    stalled = stub.StreamWeights(requests())
    sub, _ = subscribe(server, "healthy")
    try:
        helpers.wait_for(lambda: server.servicer.subscribers == 2, "both streams open")
        big = {"w": np.random.default_rng(0).standard_normal(4 << 20).astype(np.float32)}  # 16 MiB
        for v in range(1, 6):
            server.store.publish(v, SPEC, trained(big, v))  # never waits for subscribers
            assert sub.wait_version(v, 60)

        def by_id() -> dict[str, learner_pb2.SubscriberStatus]:
            return {s.client_id: s for s in server.servicer.subscriber_status()}

        helpers.wait_for(lambda: by_id()["healthy"].applied_version == 5, "healthy ack of v5")
        assert by_id()["stalled"].applied_version == 0 and by_id()["stalled"].versions_sent <= 1
        assert by_id()["stalled"].staleness == 5
    finally:
        hold.set()
        sub.stop()
        stalled.cancel()
        channel.close()


def test_prefix_selection_and_policy_tensors(server: Server) -> None:
    spec = learner_pb2.PolicySpec(kind="test", config_json="{}", tensor_prefix="actor.")
    edge, edge_got = subscribe(server, "edge")  # default: what the PolicySpec needs
    mirror, mirror_got = subscribe(server, "mirror", prefixes=[""])
    try:
        t = tensors(0)
        server.store.publish(1, spec, t)
        assert edge.wait_version(1, 30) and mirror.wait_version(1, 30)
        assert set(edge_got[0].tensors) == {"actor.w", "actor.b", "actor.steps"}
        assert set(edge_got[0].policy_tensors()) == {"w", "b", "steps"}
        assert set(mirror_got[0].tensors) == set(t)
    finally:
        edge.stop()
        mirror.stop()


def test_experiments_are_separate_streams(server: Server) -> None:
    a, a_got = subscribe(server, "a", experiment="pick")
    b, b_got = subscribe(server, "b", experiment="place")
    try:
        server.store.publish(1, SPEC, tensors(1), experiment="pick")
        server.store.publish(7, SPEC, tensors(2), experiment="place")
        assert a.wait_version(1, 30) and b.wait_version(7, 30)
        assert (a_got[0].experiment, b_got[0].experiment) == ("pick", "place")
        assert np.array_equal(b_got[0].tensors["actor.w"], tensors(2)["actor.w"])
        # "" resolves to the first experiment published (pick): single-experiment clients keep working.
        assert server.store.version_of("pick") == 1 and server.store.version == 1
    finally:
        a.stop()
        b.stop()


def test_lossy_needs_consent(server: Server) -> None:
    with rpc.make_channel(server.addr, AUTH) as channel:
        stub = learner_pb2_grpc.LearnerStub(channel)
        req = learner_pb2.SubscribeWeightsRequest(client_id="x", encoding=WE.WEIGHT_ENCODING_BF16_ZSTD)
        call = stub.StreamWeights(iter([learner_pb2.WeightAck(subscribe=req)]), timeout=10)
        with pytest.raises(grpc.RpcError) as err:
            next(call)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        call = stub.StreamWeights(iter([learner_pb2.WeightAck(version=1)]), timeout=10)
        with pytest.raises(grpc.RpcError) as err:
            next(call)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


# --------------------------------------------------------------------------- learner kill -9


def _spawn_learner(tmp_path: Path, control_addr: str, port: int) -> subprocess.Popen:
    ready = tmp_path / "learner.ready"
    ready.unlink(missing_ok=True)
    sets = {
        "auth.token": AUTH.token,
        "learner.control_addr": control_addr,
        "learner.replay_addr": "127.0.0.1:1",  # no replay: the learner publishes at setup and never trains
        "learner.checkpoint_dir": str(tmp_path / "ckpt"),
        "learner.server.port": str(port),
        "learner.server.metrics_port": "0",
        "learner.rpc_timeout_s": "1.0",
    }
    cmd = [sys.executable, "-m", "user.cli", "learner", "--ready-file", str(ready)]
    for k, v in sets.items():
        cmd += ["--set", f"{k}={v}"]
    log = open(tmp_path / "learner.log", "ab")  # noqa: SIM115 - the child owns it
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy(), start_new_session=True)

    def ready_or_exited() -> bool:
        if proc.poll() is not None:
            tail = (tmp_path / "learner.log").read_text(errors="replace")[-3000:]
            raise AssertionError(f"learner exited with {proc.returncode} before serving:\n{tail}")
        return ready.exists()

    helpers.wait_for(ready_or_exited, "learner serving", 120, 0.1)
    return proc


@pytest.mark.slow
def test_versions_stay_unique_across_a_learner_kill_9(tmp_path: Path) -> None:
    from services.control.server import ControlService
    from services.inference.server import InferenceService
    from tests.test_control import Edge, register_msg, spec
    from user.v1 import control_pb2_grpc

    ccfg = StackConfig(auth=AUTH)
    ccfg.control.server.port = 0
    ccfg.control.server.metrics_port = 0
    control = ControlService(ccfg, start_metrics=False).start()
    edge = Edge(control_pb2_grpc.ControlStub(rpc.make_channel(control.address, AUTH)), register_msg("a", spec()))
    port = helpers.free_port()
    learner_addr = f"127.0.0.1:{port}"
    # Serving before anyone dials it: a client retrying a free loopback port can, rarely, take it as its own
    # source port (TCP self-connect) and keep the learner from binding it.
    proc = _spawn_learner(tmp_path, control.address, port)
    icfg = StackConfig(auth=AUTH)
    icfg.inference.server.port = 0
    icfg.inference.server.metrics_port = 0
    icfg.inference.learner_addr = learner_addr
    inference = InferenceService(icfg, start_metrics=False).start()
    from edge_agent.policy_source import LocalPolicy

    local = LocalPolicy(learner_addr, AUTH, "edge-local")
    try:
        helpers.wait_for(lambda: local.version >= 1 and inference.policy is not None, "first weights", 120, 0.2)
        first = local.version
        proc.send_signal(signal.SIGKILL)  # no final checkpoint, no goodbye
        proc.wait(30)
        proc = _spawn_learner(tmp_path, control.address, port)
        # The restarted learner publishes a number never used before, so both subscribers move to it.
        helpers.wait_for(lambda: local.version > first, "local edge on the new weights", 120, 0.2)
        helpers.wait_for(
            lambda: inference.policy is not None and inference.policy.version > first, "inference on new weights", 120
        )
        assert (tmp_path / "ckpt" / "default" / "weight_version").read_text().strip() == str(local.version)
    finally:
        proc.terminate()  # a graceful stop removes its shared-memory weight files (a kill -9 leaves them to a sweeper)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(30)
        local.close()
        inference.stop()
        edge.close()
        control.stop()
        time.sleep(0)


# --------------------------------------------------------------------------- safe point


def test_local_policy_swaps_between_actions_never_mid_forward() -> None:
    from edge_agent.policy_source import LocalPolicy

    config = {
        "obs_keys": ["state"],
        "obs_dim": 6,
        "action_dim": 3,
        "hidden": [16],
        "action_low": [-1.0] * 3,
        "action_high": [1.0] * 3,
    }
    local = LocalPolicy("127.0.0.1:1", AUTH, "edge", deterministic=True, start=False)
    local._on_weights(helpers.random_weights(config, version=1, seed=1))
    v1 = local._policy
    assert v1 is not None
    inside, release = threading.Event(), threading.Event()
    real_act = v1.act

    def slow_act(obs, deterministic):  # type: ignore[no-untyped-def]
        inside.set()
        release.wait(30)
        return real_act(obs, deterministic)

    v1.act = slow_act  # type: ignore[method-assign]
    obs = {"state": np.zeros(6, dtype=np.float32)}
    out: list = []
    t = threading.Thread(target=lambda: out.append(local.act("r", obs, deadline_s=60.0)))
    t.start()
    assert inside.wait(30)
    local._on_weights(helpers.random_weights(config, version=2, seed=2))  # arrives mid-forward
    release.set()
    t.join(30)
    assert out[0] is not None and out[0][1] == 1  # the forward in flight finished on the weights it started with
    action, version = local.act("r", obs, deadline_s=60.0)
    assert version == 2 and not np.allclose(action, out[0][0])


def test_buffer_pool_reuses_a_buffer_only_once_nothing_views_it() -> None:
    from user.weight_codec import BufferPool

    pool = BufferPool()
    buf = pool.take(2 << 20)
    owner = id(buf if buf.base is None else buf.base)  # no reference: holding one would keep it busy
    tensor = buf[64:128].view(np.float32)  # a weight set's tensor still in use
    pool.give(buf)
    del buf
    fresh = pool.take(2 << 20)
    assert id(fresh.base) != owner  # still viewed: never handed out again while in use
    del tensor
    assert id(pool.take(2 << 20).base) == owner


def test_read_varint_matches_protobuf_and_refuses_truncated_or_overlong_bytes() -> None:
    for value in (1, 127, 128, 300, 2**32, 2**63 - 1, 2**64 - 1):
        msg = learner_pb2.WeightChunk(version=value).SerializeToString()  # tag 0x08, then the varint
        assert wire.read_varint(msg, 1) == (value, len(msg))
    with pytest.raises(wire.WireError, match="truncated"):
        wire.read_varint(b"\x80\x80", 0)
    with pytest.raises(wire.WireError, match="10 bytes"):
        wire.read_varint(b"\xff" * 11 + b"\x01", 0)


def test_link_rate_for_patch_compression_leaves_out_the_round_trip() -> None:
    """A small full set's send -> ack time is mostly the fixed round trip and the client's apply: the link's
    wire rate (which picks stored vs compressed streamed patches) comes from the client's transfer time."""
    store = WeightStore()
    store.publish(1, SPEC, tensors(0, n=1 << 18))
    full = store.latest()
    servicer = WeightServicer(store)
    link = Link("c", "", ("",), True, 0, 1.0, True)
    ack = learner_pb2.WeightAck(version=1, applied=True, transfer_ns=1_000_000, apply_ns=1_000_000)
    assert servicer._on_ack(link, full, ack, elapsed_s=0.1)
    assert link.wire_bps == pytest.approx(full.encoded_bytes / 1e-3)  # 1 MiB in 1 ms of transfer
    assert link.goodput_bps == pytest.approx(full.encoded_bytes / 0.099)  # end to end, less the apply
    store.close()


def test_a_subscriber_whose_stream_is_dropped_mid_message_leaves_when_the_rpc_ends() -> None:
    """gRPC may drop a handler's generator at a yield (the client cancelled while that message was being sent)
    and never resume nor close it: the subscriber must still leave the learner's status when the RPC ends."""
    store = WeightStore()
    servicer = WeightServicer(store, poll_s=0.1)
    store.publish(1, SPEC, tensors())
    ctx = helpers.EndingContext()
    stream = servicer.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="dropped"), ctx)
    assert next(stream).header.version == 1
    assert [s.client_id for s in servicer.subscriber_status()] == ["dropped"]
    ctx.end()  # `stream` stays suspended and referenced, as gRPC leaves it
    assert servicer.subscribers == 0 and servicer.subscriber_status() == []
    stream.close()  # its own end afterwards changes nothing
    assert servicer.subscribers == 0
