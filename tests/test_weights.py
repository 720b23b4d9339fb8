"""Weight sets on the wire: pack/stream/reassemble, corruption detection, and a real gRPC stream."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import grpc
import numpy as np
import pytest

from tests.helpers import wait_for
from user import rpc
from user.config import AuthConfig, ServerConfig
from user.v1 import learner_pb2, learner_pb2_grpc
from user.weights import (
    ENCODING_RAW,
    ENCODING_ZSTD,
    WeightAssembler,
    WeightServicer,
    WeightSet,
    WeightStore,
    WeightSubscriber,
    iter_weight_messages,
    pack_weights,
)
from user.wire import WireError

AUTH = AuthConfig(token="test-token")
SPEC = learner_pb2.PolicySpec(kind="sac_mlp", config_json='{"hidden": [8]}')


def make_tensors(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "net.0.weight": rng.standard_normal((64, 17)).astype(np.float32),
        "net.0.bias": rng.standard_normal(64).astype(np.float32),
        "half": rng.standard_normal((3, 5)).astype(np.float16),
        "steps": np.arange(7, dtype=np.int64),
        "mask": np.array([True, False, True]),
        "scalar": np.array(2.5, dtype=np.float64),
        "empty": np.zeros((0, 4), dtype=np.float32),
        "bytes": np.arange(13, dtype=np.uint8),
    }


def assemble(msgs: Iterator[learner_pb2.WeightMessage]) -> WeightSet:
    asm, out = WeightAssembler(), None
    for msg in msgs:
        got = asm.feed(msg)
        if got is not None:
            assert out is None, "one weight set per header"
            out = got
    assert out is not None
    return out


def assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert list(a) == list(b)
    for name in a:
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        np.testing.assert_array_equal(a[name], b[name])


@pytest.mark.parametrize("digest", [learner_pb2.DIGEST_XXH3_128, learner_pb2.DIGEST_SHA256])
@pytest.mark.parametrize("encoding", [ENCODING_RAW, ENCODING_ZSTD])
@pytest.mark.parametrize("chunk", [1, 1024, 4096, 1 << 20])
def test_round_trip(encoding: int, chunk: int, digest: int) -> None:
    tensors = make_tensors()
    packed = pack_weights(5, SPEC, tensors, learner_updates=123, encoding=encoding, digest=digest)
    assert packed.header.digest_kind == digest
    msgs = list(iter_weight_messages(packed, chunk))
    assert msgs[0].HasField("header") and all(m.HasField("chunk") for m in msgs[1:])
    assert all(len(m.chunk.data) <= chunk for m in msgs[1:])
    out = assemble(iter(msgs))
    assert (out.version, out.learner_updates, out.policy) == (5, 123, SPEC)
    assert_same(tensors, out.tensors)
    assert all(t.flags.writeable for t in out.tensors.values())


def test_big_endian_and_noncontiguous_inputs_are_normalized() -> None:
    base = np.arange(24, dtype=">f4").reshape(4, 6)
    tensors = {"be": base, "strided": np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2]}
    out = assemble(iter_weight_messages(pack_weights(1, SPEC, tensors), 1024))
    np.testing.assert_array_equal(out.tensors["be"], base.astype(np.float32))
    np.testing.assert_array_equal(out.tensors["strided"], tensors["strided"])


def test_zstd_shrinks_compressible_payload() -> None:
    tensors = {"zeros": np.zeros((256, 256), dtype=np.float32)}
    raw = pack_weights(1, SPEC, tensors)
    packed = pack_weights(1, SPEC, tensors, encoding=ENCODING_ZSTD)
    assert packed.header.encoded_bytes < raw.header.encoded_bytes == packed.header.total_bytes


def test_empty_weight_set_completes_on_header() -> None:
    out = assemble(iter_weight_messages(pack_weights(1, SPEC, {}), 1024))
    assert out.tensors == {}


def _messages(encoding: int = ENCODING_RAW) -> list[learner_pb2.WeightMessage]:
    return list(iter_weight_messages(pack_weights(2, SPEC, make_tensors(), encoding=encoding), 1024))


def _corrupt_chunk_byte(msgs: list[learner_pb2.WeightMessage]) -> None:
    data = bytearray(msgs[2].chunk.data)
    data[10] ^= 0xFF
    msgs[2].chunk.data = bytes(data)


def _tensor_beyond_payload(msgs: list[learner_pb2.WeightMessage]) -> None:
    msgs[0].header.tensors[0].offset = msgs[0].header.total_bytes


CORRUPTIONS: dict[str, Callable[[list[learner_pb2.WeightMessage]], None]] = {
    "flipped byte": _corrupt_chunk_byte,
    "wrong digest": lambda m: setattr(m[0].header, "digest", bytes(16)),
    "short digest": lambda m: setattr(m[0].header, "digest", b"abc"),
    "unspecified digest kind": lambda m: setattr(m[0].header, "digest_kind", learner_pb2.DIGEST_UNSPECIFIED),
    "unknown digest kind": lambda m: setattr(m[0].header, "digest_kind", 77),
    "digest kind swapped": lambda m: setattr(m[0].header, "digest_kind", learner_pb2.DIGEST_SHA256),
    "chunk offset gap": lambda m: setattr(m[2].chunk, "offset", m[2].chunk.offset + 1),
    "chunk of another version": lambda m: setattr(m[3].chunk, "version", 9),
    "missing chunk": lambda m: m.pop(2),
    "duplicated chunk": lambda m: m.insert(2, m[2]),
    "extra bytes": lambda m: setattr(m[-1].chunk, "data", m[-1].chunk.data + b"x" * 2000),
    "tensor beyond payload": _tensor_beyond_payload,
    "nbytes mismatch": lambda m: setattr(m[0].header.tensors[0], "nbytes", 4),
    "unknown dtype": lambda m: setattr(m[0].header.tensors[0], "dtype", 99),
    "unspecified dtype": lambda m: setattr(m[0].header.tensors[0], "dtype", 0),
    "duplicate name": lambda m: setattr(m[0].header.tensors[1], "name", m[0].header.tensors[0].name),
    "negative dim": lambda m: m[0].header.tensors[0].shape.__setitem__(0, -64),
    "raw size mismatch": lambda m: setattr(m[0].header, "encoded_bytes", m[0].header.total_bytes + 1),
    "version 0": lambda m: setattr(m[0].header, "version", 0),
    "unknown encoding": lambda m: setattr(m[0].header, "encoding", 1),
    "chunk before header": lambda m: m.pop(0),
    "second header mid-set": lambda m: m.insert(3, m[0]),
    "empty message": lambda m: m.insert(1, learner_pb2.WeightMessage()),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_corruption_raises_wire_error(name: str) -> None:
    msgs = _messages()
    CORRUPTIONS[name](msgs)
    with pytest.raises(WireError):
        assemble(iter(msgs))


def test_corrupted_zstd_payload_raises_wire_error() -> None:
    msgs = _messages(ENCODING_ZSTD)
    _corrupt_chunk_byte(msgs)
    with pytest.raises(WireError):
        assemble(iter(msgs))


def test_assembler_recovers_after_error() -> None:
    asm = WeightAssembler()
    bad = _messages()
    bad[0].header.digest = bytes(16)
    with pytest.raises(WireError):
        for msg in bad:
            asm.feed(msg)
    assert not asm.in_progress
    good = [asm.feed(m) for m in _messages()]
    assert good[-1] is not None and good[-1].version == 2


def test_store_skips_to_latest_and_rejects_old_versions() -> None:
    store = WeightStore()
    assert store.wait_newer(0, timeout=0.01) is None
    store.publish(1, SPEC, make_tensors())
    store.publish(2, SPEC, make_tensors(1))
    store.publish(3, SPEC, make_tensors(2))
    got = store.wait_newer(1, timeout=0)
    assert got is not None and got.version == 3
    assert store.wait_newer(3, timeout=0.01) is None
    with pytest.raises(ValueError):
        store.publish(3, SPEC, make_tensors())
    # A waiter is woken by publish; close() releases every waiter with None.
    result: list[object] = []
    waiter = threading.Thread(target=lambda: result.append(store.wait_newer(3, timeout=30)))
    waiter.start()
    store.publish(4, SPEC, make_tensors())
    waiter.join(30)
    assert result[0].version == 4  # type: ignore[union-attr]
    waiter = threading.Thread(target=lambda: result.append(store.wait_newer(4, timeout=30)))
    waiter.start()
    store.close()
    waiter.join(30)
    assert result[1] is None


def test_publish_at_capacity_packs_into_the_departing_buffer() -> None:
    """The oldest version leaves before the new one is packed, so its buffer is reused (no fresh pages);
    one still in use (a stream sending it) is not."""
    big = {"w": np.arange(1 << 19, dtype=np.float32)}  # 2 MiB: pooled
    store = WeightStore(history=2)
    store.publish(1, SPEC, big)
    first = store.get(1)
    assert first is not None
    address = first.payload.__array_interface__["data"][0]  # type: ignore[union-attr]
    del first
    store.publish(2, SPEC, {"w": big["w"] + 1})
    store.publish(3, SPEC, {"w": big["w"] + 2})
    third = store.get(3)
    assert third is not None and third.payload.__array_interface__["data"][0] == address  # type: ignore[union-attr]
    assert [store.get(v) is not None for v in (1, 2, 3)] == [False, True, True]
    np.testing.assert_array_equal(np.frombuffer(third.payload, np.float32), big["w"] + 2)
    held = store.get(2)  # a stream still sending v2: v4 must not land in its buffer
    store.publish(4, SPEC, {"w": big["w"] + 3})
    assert held is not None
    np.testing.assert_array_equal(np.frombuffer(held.payload, np.float32), big["w"] + 1)


# --------------------------------------------------------------------------- real gRPC


def start_weight_server(store: WeightStore, port: int = 0) -> tuple[rpc.RunningServer, WeightServicer]:
    servicer = WeightServicer(store, poll_s=0.2)
    server = rpc.start_server(
        "weights-test",
        lambda s: learner_pb2_grpc.add_LearnerServicer_to_server(servicer, s),
        ["user.v1.Learner"],
        ServerConfig(host="127.0.0.1", port=port, metrics_port=0, grace_s=1.0),
        AUTH,
        start_metrics=False,
    )
    return server, servicer


def stop_weight_server(store: WeightStore, server: rpc.RunningServer) -> None:
    store.close()
    server.stop()


def test_stream_skip_and_reconnect_after_restart() -> None:
    store = WeightStore()
    store.publish(1, SPEC, make_tensors(1))
    server, servicer = start_weight_server(store)
    port = server.port
    received: list[WeightSet] = []
    sub = WeightSubscriber(server.address(), AUTH, "test-client", received.append, max_chunk_bytes=1024).start()
    try:
        assert sub.wait_version(1, timeout=20)
        assert_same(received[0].tensors, make_tensors(1))
        assert wait_for(lambda: servicer.subscribers == 1)

        # Two quick versions: the subscriber may skip v2 but must end on v3.
        store.publish(2, SPEC, make_tensors(2))
        store.publish(3, SPEC, make_tensors(3), learner_updates=30)
        assert sub.wait_version(3, timeout=20)
        assert received[-1].version == 3 and received[-1].learner_updates == 30
        assert_same(received[-1].tensors, make_tensors(3))

        # The learner restarts on the same port (resumed at v3): the subscriber reconnects
        # and receives only versions newer than the one it has.
        stop_weight_server(store, server)
        store = WeightStore()
        store.publish(3, SPEC, make_tensors(3))
        server, servicer = start_weight_server(store, port=port)
        assert server.port == port
        assert wait_for(lambda: servicer.subscribers == 1)
        store.publish(4, SPEC, make_tensors(4))
        assert sub.wait_version(4, timeout=20)
        versions = [w.version for w in received]
        assert versions == sorted(set(versions)), versions
        assert versions[0] == 1 and versions[-2:] == [3, 4]
        assert sub.connects >= 2
    finally:
        sub.stop()
        # The server notices the client going away and ends its stream.
        assert wait_for(lambda: servicer.subscribers == 0)
        stop_weight_server(store, server)


def test_callback_error_keeps_previous_version() -> None:
    store = WeightStore()
    store.publish(1, SPEC, make_tensors())
    server, _ = start_weight_server(store)
    calls: list[int] = []

    def on_weights(ws: WeightSet) -> None:
        calls.append(ws.version)
        if ws.version == 2:
            raise ValueError("incompatible weights")

    sub = WeightSubscriber(server.address(), AUTH, "picky", on_weights).start()
    try:
        assert sub.wait_version(1, timeout=20)
        store.publish(2, SPEC, make_tensors())
        assert wait_for(lambda: 2 in calls)
        assert sub.version == 1
        store.publish(3, SPEC, make_tensors())
        assert sub.wait_version(3, timeout=20)
    finally:
        sub.stop()
        stop_weight_server(store, server)


def test_stream_rejects_bad_chunk_size_and_missing_token() -> None:
    store = WeightStore()
    store.publish(1, SPEC, make_tensors())
    server, _ = start_weight_server(store)
    try:
        with rpc.make_channel(server.address(), AUTH) as channel:
            stub = learner_pb2_grpc.LearnerStub(channel)
            for size in (100, (16 << 20) + 1):
                call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(max_chunk_bytes=size), timeout=10)
                with pytest.raises(grpc.RpcError) as err:
                    next(iter(call))
                assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            # have_version >= latest: nothing is sent until a newer version exists.
            call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(have_version=1), timeout=0.5)
            with pytest.raises(grpc.RpcError) as err:
                next(iter(call))
            assert err.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        anonymous = AUTH.model_copy(update={"enabled": False})
        with rpc.make_channel(server.address(), anonymous) as channel:
            call = learner_pb2_grpc.LearnerStub(channel).SubscribeWeights(
                learner_pb2.SubscribeWeightsRequest(), timeout=10
            )
            with pytest.raises(grpc.RpcError) as err:
                next(iter(call))
            assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    finally:
        stop_weight_server(store, server)
