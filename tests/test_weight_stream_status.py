"""What weight streams tell subscribers and operators: a learner whose versions restarted below a subscriber's, the
status of unacked streams, per-stream metric series, tensor prefixes that select nothing, and edge chunk ages."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import grpc
import numpy as np
import prometheus_client
import pytest

from edge_agent.chunks import ChunkExecutor
from tests import helpers
from user import rpc
from user.config import AuthConfig, ServerConfig
from user.v1 import learner_pb2, learner_pb2_grpc
from user.weights import (
    VERSIONS_RESTARTED_KEY,
    WeightServicer,
    WeightSet,
    WeightStore,
    WeightSubscriber,
    add_learner_servicer,
)

AUTH = AuthConfig(token="test-token")
SPEC = learner_pb2.PolicySpec(kind="test", config_json="{}")
SERVICE = learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name


def tensors(seed: int = 0, n: int = 4096) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "actor.w": rng.standard_normal((n // 64, 64)).astype(np.float32),
        "actor.b": rng.standard_normal(64).astype(np.float32),
        "critic.w": rng.standard_normal((n // 64, 64)).astype(np.float32),
    }


class Server:
    def __init__(self, store: WeightStore, port: int = 0) -> None:
        self.store = store
        self.servicer = WeightServicer(store, poll_s=0.1)
        self.running = rpc.start_server(
            "test-learner",
            lambda s: add_learner_servicer(self.servicer, s),
            [SERVICE],
            ServerConfig(port=port, metrics_port=0, max_workers=16, grace_s=0.2),
            AUTH,
            start_metrics=False,
        )
        self.addr = self.running.address()
        self.port = self.running.port

    def close(self) -> None:
        self.store.close()
        self.running.stop()


@pytest.fixture
def server() -> Iterator[Server]:
    srv = Server(WeightStore())
    yield srv
    srv.close()


@pytest.fixture
def stub(server: Server) -> Iterator[learner_pb2_grpc.LearnerStub]:
    channel = rpc.make_channel(server.addr, AUTH)
    yield learner_pb2_grpc.LearnerStub(channel)
    channel.close()


class HeldStream:
    """A hand-made StreamWeights that subscribes and then sends nothing more (never acks) until closed."""

    def __init__(self, stub: learner_pb2_grpc.LearnerStub, **subscribe: object) -> None:
        self._done = threading.Event()
        first = learner_pb2.WeightAck(subscribe=learner_pb2.SubscribeWeightsRequest(**subscribe))

        def requests() -> Iterator[learner_pb2.WeightAck]:
            yield first
            self._done.wait(120)

        self.call = stub.StreamWeights(requests(), timeout=120)

    def close(self) -> None:
        self._done.set()
        self.call.cancel()


def statuses(srv: Server) -> dict[str, learner_pb2.SubscriberStatus]:
    return {s.client_id: s for s in srv.servicer.subscriber_status()}


# --------------------------------------------------------------------------- 5: versions restarted below a subscriber


def test_a_subscriber_takes_the_weights_of_a_learner_whose_versions_restarted_below_its_own() -> None:
    first = Server(WeightStore())
    got: list[WeightSet] = []
    sub = WeightSubscriber(first.addr, AUTH, "edge-1", got.append, max_chunk_bytes=4096).start()
    second: Server | None = None
    try:
        for v in (40, 41, 42):
            first.store.publish(v, SPEC, tensors(v))
        helpers.wait_for(lambda: sub.version == 42, "v42 applied")
        port = first.port
        first.close()
        # A redeploy without the learner's high-water mark: same address, numbering from 1 again. Until it
        # publishes, the subscriber has nothing to learn (and keeps waiting, like an up-to-date one).
        second = Server(WeightStore(), port=port)
        helpers.wait_for(lambda: second.servicer.subscribers == 1, "the subscriber reconnected")
        assert sub.version == 42 and sub.restarts == 0
        fresh = {v: tensors(100 + v) for v in (1, 2, 3, 4)}
        for v, t in fresh.items():
            second.store.publish(v, SPEC, t)
        helpers.wait_for(lambda: sub.version == 4, "the new learner's v4 applied")
        assert sub.restarts == 1
        assert all(np.array_equal(got[-1].tensors[k], fresh[4][k]) for k in fresh[4])
        helpers.wait_for(lambda: statuses(second)["edge-1"].applied_version == 4, "ack of v4")
        # the next version flows as usual, on the same stream
        second.store.publish(5, SPEC, tensors(105))
        helpers.wait_for(lambda: sub.version == 5, "v5 applied")
        assert sub.restarts == 1
    finally:
        sub.stop()
        first.close()
        if second is not None:
            second.close()


def test_a_version_above_the_learners_latest_is_failed_precondition_and_an_equal_one_waits(
    server: Server, stub: learner_pb2_grpc.LearnerStub
) -> None:
    for v in (1, 2, 3):
        server.store.publish(v, SPEC, tensors(v))
    for call in (
        stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="x", have_version=10**9), timeout=30),
        stub.StreamWeights(
            iter([learner_pb2.WeightAck(subscribe=learner_pb2.SubscribeWeightsRequest(client_id="x", have_version=7))]),
            timeout=30,
        ),
        stub.StreamWeights(  # the base it holds for deltas is above too
            iter([learner_pb2.WeightAck(subscribe=learner_pb2.SubscribeWeightsRequest(client_id="x", base_version=9))]),
            timeout=30,
        ),
    ):
        with pytest.raises(grpc.RpcError) as err:
            next(call)
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION, err.value.details()
        assert "restarted" in err.value.details()
        assert dict(err.value.trailing_metadata())[VERSIONS_RESTARTED_KEY] == "3"
    # Up to date is not restarted: it waits for the next version (here: until its deadline).
    call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="y", have_version=3), timeout=1)
    with pytest.raises(grpc.RpcError) as err:
        next(call)
    assert err.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED


def test_a_subscriber_waiting_above_an_empty_learner_hears_of_its_first_version(
    server: Server, stub: learner_pb2_grpc.LearnerStub
) -> None:
    call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="x", have_version=42), timeout=60)
    helpers.wait_for(lambda: server.servicer.subscribers == 1, "the stream open")
    server.store.publish(1, SPEC, tensors(1))
    with pytest.raises(grpc.RpcError) as err:
        next(call)
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert dict(err.value.trailing_metadata())[VERSIONS_RESTARTED_KEY] == "1"


# --------------------------------------------------------------------------- 6: unacked streams


def test_an_unacked_stream_reports_what_was_sent_not_applied_and_a_stalled_reader_as_stale(
    server: Server, stub: learner_pb2_grpc.LearnerStub
) -> None:
    server.store.publish(1, SPEC, tensors(1))
    call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="ra"), timeout=120)
    try:
        assert next(call).header.version == 1  # then it stops reading
        helpers.wait_for(lambda: statuses(server)["ra"].sent_version == 1, "v1 handed to the transport")
        st = statuses(server)["ra"]
        # the server cannot know what an unacked client applied: it says so rather than claim v1
        assert (st.acked, st.applied_version, st.versions_sent) == (False, 0, 1)
        assert st.staleness == 0
        # Versions keep coming; the reader does not read them. Once flow control is full nothing more is
        # sent and the stream shows as stale (16 MiB versions: a handful fill any window).
        v = 1
        big = np.random.default_rng(0).standard_normal(4 << 20).astype(np.float32)

        def stale() -> tuple[learner_pb2.SubscriberStatus, float] | None:
            nonlocal v
            v += 1
            server.store.publish(v, SPEC, {"actor.w": big + v})
            scraped = prometheus_client.REGISTRY.get_sample_value(
                "user_weights_subscriber_staleness", {"client_id": "ra", "experiment": ""}
            )
            st = statuses(server)["ra"]
            return (st, scraped) if st.staleness >= 3 and scraped is not None and scraped >= 3 else None

        st, _ = helpers.wait_for(stale, "the stalled reader stale, in the status and the metric", poll_s=0.05)
        assert not st.acked and st.applied_version == 0 and 1 <= st.sent_version < server.store.version
        assert st.staleness == server.store.version - st.sent_version
    finally:
        call.cancel()


# --------------------------------------------------------------------------- 7: per-stream metric series


def _series(client_id: str, experiment: str, name: str = "user_weights_subscriber_staleness") -> float | None:
    return prometheus_client.REGISTRY.get_sample_value(name, {"client_id": client_id, "experiment": experiment})


def test_staleness_series_are_per_client_and_experiment_and_leave_with_their_last_stream(
    server: Server, stub: learner_pb2_grpc.LearnerStub
) -> None:
    server.store.publish(1, SPEC, tensors(1), experiment="ra")
    server.store.publish(1, SPEC, tensors(2), experiment="rb")
    got: list[WeightSet] = []
    acking = WeightSubscriber(server.addr, AUTH, "dup", got.append, experiment="ra").start()
    silent_ra = HeldStream(stub, client_id="dup", experiment="ra")  # never acks: 1 behind
    silent_rb = HeldStream(stub, client_id="dup", experiment="rb")
    try:
        helpers.wait_for(lambda: server.servicer.subscribers == 3, "three streams open")
        helpers.wait_for(
            lambda: any(st.applied_version == 1 for st in server.servicer.subscriber_status()), "ack of ra v1"
        )
        assert _series("dup", "ra") == 1  # the worst of the two ra streams
        assert _series("dup", "rb") == 1
        for name in ("user_weights_subscriber_sync_seconds", "user_weights_subscriber_goodput_bytes_per_second"):
            assert _series("dup", "ra", name) is not None and _series("dup", "rb", name) is not None

        silent_rb.close()  # rb's series leaves with its only stream; ra's stays
        helpers.wait_for(lambda: server.servicer.subscribers == 2, "the rb stream gone")
        assert _series("dup", "rb") is None and _series("dup", "ra") == 1

        silent_ra.close()  # one of two ra streams: the series stays, showing the one left (applied v1)
        helpers.wait_for(lambda: server.servicer.subscribers == 1, "one ra stream gone")
        assert _series("dup", "ra") == 0
        helpers.wait_for(lambda: (_series("dup", "ra", "user_weights_subscriber_sync_seconds") or 0) > 0, "sync")

        acking.stop()
        helpers.wait_for(lambda: server.servicer.subscribers == 0, "every stream gone")
        for name in (
            "user_weights_subscriber_staleness",
            "user_weights_subscriber_sync_seconds",
            "user_weights_subscriber_goodput_bytes_per_second",
        ):
            assert _series("dup", "ra", name) is None, name
    finally:
        silent_ra.close()
        silent_rb.close()
        acking.stop()


# --------------------------------------------------------------------------- 9: prefixes selecting nothing


def test_prefixes_that_select_no_tensor_are_invalid_argument(
    server: Server, stub: learner_pb2_grpc.LearnerStub
) -> None:
    server.store.publish(240, SPEC, tensors(0))
    for prefixes in (["zzz"], ["actor.", "zzz"]):
        req = learner_pb2.SubscribeWeightsRequest(client_id="x", prefixes=prefixes)
        for call in (
            stub.SubscribeWeights(req, timeout=30),
            stub.StreamWeights(iter([learner_pb2.WeightAck(subscribe=req)]), timeout=30),
        ):
            with pytest.raises(grpc.RpcError) as err:
                next(call)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "'zzz'" in err.value.details() and "'actor.'" not in err.value.details()
    # a prefix that selects something still streams just those tensors
    call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="y", prefixes=["actor."]), timeout=30)
    header = next(call).header
    call.cancel()
    assert {t.name for t in header.tensors} == {"actor.w", "actor.b"}


def test_prefixes_are_checked_against_the_first_version_published(
    server: Server, stub: learner_pb2_grpc.LearnerStub
) -> None:
    call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="x", prefixes=["zzz"]), timeout=60)
    helpers.wait_for(lambda: server.servicer.subscribers == 1, "accepted while nothing is published")
    server.store.publish(1, SPEC, tensors(0))
    with pytest.raises(grpc.RpcError) as err:
        next(call)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "'zzz'" in err.value.details()


# --------------------------------------------------------------------------- 15: edge chunk age


def test_chunk_age_of_a_synchronous_fetch_counts_the_fetch() -> None:
    clock = [0.0]
    horizon = 4

    def fetch(obs: dict[str, np.ndarray]) -> tuple[np.ndarray, int]:
        clock[0] += 0.05  # the blocking round trip
        return np.zeros((horizon, 2), np.float32), 1

    held: list[object] = []  # background fetches (none expected: the chunk lasts)
    ex = ChunkExecutor(fetch, prefetch=0, clock=lambda: clock[0], runner=held.append, adaptive=False)
    before = prometheus_client.REGISTRY.get_sample_value("user_edge_chunk_age_seconds_sum") or 0.0
    assert ex.tick({"state": np.zeros(3, np.float32)}) is not None  # no chunk yet: fetched synchronously
    assert ex.last_age_s == pytest.approx(0.05)
    clock[0] += 0.1
    assert ex.tick({"state": np.zeros(3, np.float32)}) is not None  # its next row, a tick later
    assert ex.last_age_s == pytest.approx(0.15)
    after = prometheus_client.REGISTRY.get_sample_value("user_edge_chunk_age_seconds_sum")
    assert after - before == pytest.approx(0.2) and held == []
