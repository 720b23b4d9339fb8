"""Streams against a server's handler threads, and the statuses of bad input, over real gRPC on 127.0.0.1:0:
cancelled and idle streams give their thread back, open streams leave threads for unary calls and health
checks, cancellations are counted as CANCELLED, and status details stay within gRPC's metadata limit."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import grpc
import numpy as np
import prometheus_client
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from services.control.server import ControlService
from services.replay.server import MAX_SAMPLE_ROBOTS, ReplayService
from tests.helpers import wait_for
from tests.test_control import _cfg as control_cfg
from tests.test_replay_service import AUTH, insert, make_service, requests, specs, stats, stub
from tests.test_replay_store import episode
from tests.test_replay_tables_service import insert_into
from user import rpc, wire
from user.config import AuthConfig, ServerConfig
from user.v1 import control_pb2_grpc, replay_pb2
from user.wire import split_rows as _split

__all__ = ["make_service", "specs"]  # fixtures

INSERT = "/user.v1.Replay/Insert"
MAX_WORKERS = 6  # stream_limit(6) == 2: two streams, four threads kept for unary calls and health


def _count(method: str, code: str) -> float:
    labels = {"method": method, "code": code}
    return prometheus_client.REGISTRY.get_sample_value("user_grpc_server_handled_total", labels) or 0.0


def _open_streams(method: str) -> float:
    return prometheus_client.REGISTRY.get_sample_value("user_grpc_open_streams", {"method": method}) or 0.0


class IdleStream:
    """An Insert stream that sends what the test gives it and otherwise stays open and silent."""

    def __init__(self, svc: ReplayService) -> None:
        self._up: queue.Queue = queue.Queue()
        self.call = stub(svc).Insert(iter(self._up.get, None))

    def send(self, req: replay_pb2.InsertRequest) -> None:
        self._up.put(req)

    def cancel(self) -> None:
        self.call.cancel()
        self._up.put(None)  # lets the client's sending thread end too


@pytest.fixture
def small(make_service: Callable[..., ReplayService]) -> ReplayService:
    """A replay with MAX_WORKERS handler threads."""
    return make_service(server=ServerConfig(port=0, metrics_port=0, max_workers=MAX_WORKERS, grace_s=1.0))


def _open(svc: ReplayService, held: list[IdleStream]) -> IdleStream:
    """One more stream, once the server has either taken it in or refused it."""
    stream = IdleStream(svc)
    wait_for(lambda: stream.call.done() or svc.servicer._streams == len(held) + 1, "the stream taken in or refused")
    return stream


def _accepted(svc: ReplayService, held: list[IdleStream]) -> IdleStream:
    """One more stream taken in (a slot given back by a stream that just ended may take a moment to free up)."""

    def attempt() -> IdleStream | None:
        stream = _open(svc, held)
        if stream.call.done():  # refused
            stream.cancel()
            return None
        return stream

    stream = wait_for(attempt, "a stream taken in")
    held.append(stream)
    return stream


def _insert_when_free(svc: ReplayService, name: str) -> bool:
    """A short episode through a fresh stream; False while the server refuses it for want of a stream slot."""
    try:
        acks = insert(svc, episode("arm-0", name, 3))
    except grpc.RpcError as err:
        if err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
            return False
        raise
    return sorted(s for a in acks for s in a.seqs) == [0, 1, 2]


def _health(svc: ReplayService) -> int:
    channel = rpc.make_channel(svc.address, AUTH)
    return health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10).status


def _readers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "replay-insert-reader"]


# --------------------------------------------------------------------------- stream slots


def test_open_streams_leave_threads_for_unary_calls_and_health(small: ReplayService) -> None:
    limit = rpc.stream_limit(MAX_WORKERS)
    assert limit == 2
    before = _open_streams(INSERT)
    held: list[IdleStream] = []
    refused: list[IdleStream] = []
    for _ in range(MAX_WORKERS + 2):  # more streams than handler threads: without the limit Stats would starve
        stream = _open(small, held)
        (refused if stream.call.done() else held).append(stream)
    assert len(held) == limit and len(refused) == MAX_WORKERS + 2 - limit
    assert _open_streams(INSERT) - before == limit
    err = refused[0].call
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "replay.server.max_workers" in err.details() and f"{limit} streams" in err.details()
    assert _health(small) == health_pb2.HealthCheckResponse.SERVING
    assert stats(small).steps == 0
    held.pop().cancel()  # a slot comes back: a new stream is taken in and its steps acknowledged
    wait_for(lambda: _insert_when_free(small, "after-cancel"), "a stream accepted after one was cancelled")
    for stream in held + refused:
        stream.cancel()
    wait_for(lambda: _open_streams(INSERT) == before, "every stream slot given back")


def test_cancelled_streams_give_their_thread_back(small: ReplayService) -> None:
    """More rounds of cancelled streams than handler threads: each round's handlers end, so a fresh Insert and
    Stats are still served (before, each cancelled stream's handler polled forever and replay went deaf)."""
    for rnd in range(2 * MAX_WORKERS):
        held: list[IdleStream] = []
        _accepted(small, held)  # never sends a step
        busy = _accepted(small, held)
        busy.send(requests(episode("arm-0", f"sent-{rnd}", 2))[0])  # one step sent, then silence
        sent = 4 * rnd + 1
        wait_for(lambda n=sent: small.servicer.store.stats()["steps"] == n, "the sent step committed")
        for stream in held:
            stream.cancel()
        wait_for(lambda name=f"fresh-{rnd}": _insert_when_free(small, name), f"an Insert served after round {rnd}")
        assert stats(small).steps == sent + 3
    wait_for(lambda: small.servicer._streams == 0 and not _readers(), "every handler and reader thread ended")


def test_a_cancelled_stream_is_counted_cancelled(small: ReplayService) -> None:
    before = {code: _count(INSERT, code) for code in ("CANCELLED", "OK", "UNKNOWN")}
    stream = _open(small, [])
    stream.cancel()
    wait_for(lambda: _count(INSERT, "CANCELLED") == before["CANCELLED"] + 1, "the cancelled stream counted")
    wait_for(lambda: small.servicer._streams == 0, "the handler ended")
    assert _count(INSERT, "OK") == before["OK"] and _count(INSERT, "UNKNOWN") == before["UNKNOWN"]


# --------------------------------------------------------------------------- a bare server of rpc.py


def _probe_handlers(held: threading.Event) -> dict[str, grpc.RpcMethodHandler]:
    def fail(request: bytes, context: grpc.ServicerContext) -> bytes:
        context.abort(grpc.StatusCode.INVALID_ARGUMENT, "bad value " + request.decode())
        return b""

    def hold(request: bytes, context: grpc.ServicerContext) -> Iterator[bytes]:
        yield b"open"
        held.set()
        while context.is_active():  # a well-behaved handler: ends once the client has gone
            time.sleep(0.01)

    return {
        "Fail": grpc.unary_unary_rpc_method_handler(fail),
        "Hold": grpc.unary_stream_rpc_method_handler(hold),
    }


@pytest.fixture
def probe() -> Iterator[tuple[rpc.RunningServer, threading.Event]]:
    """start_server's plumbing (metrics, stream slots, health) around two plain handlers."""
    held = threading.Event()
    generic = grpc.method_handlers_generic_handler("test.Probe", _probe_handlers(held))
    running = rpc.start_server(
        "probe",
        lambda server: server.add_generic_rpc_handlers((generic,)),
        ["test.Probe"],
        ServerConfig(port=0, metrics_port=0, max_workers=MAX_WORKERS, grace_s=0.2),
        AuthConfig(enabled=False),
        start_metrics=False,
    )
    yield running, held
    running.stop()


@pytest.mark.parametrize("char", ["x", "\u00e9", "\U0001f916"])
def test_long_status_details_are_cut_not_dropped(probe: tuple[rpc.RunningServer, threading.Event], char: str) -> None:
    """Details past gRPC's metadata limit used to turn into RESOURCE_EXHAUSTED "Stream removed"."""
    running, _ = probe
    with grpc.insecure_channel(running.address()) as channel, pytest.raises(grpc.RpcError) as err:
        channel.unary_unary("/test.Probe/Fail")((char * 20_000).encode(), timeout=10)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    details = err.value.details()
    assert details.startswith("bad value " + char) and details.endswith("more characters)")
    assert len(details.encode()) <= rpc.MAX_DETAILS_BYTES + 40


def test_bounded_details() -> None:
    assert rpc.bounded_details("short") == "short"
    assert rpc.bounded_details("a" * rpc.MAX_DETAILS_BYTES) == "a" * rpc.MAX_DETAILS_BYTES
    cut = rpc.bounded_details("\u00e9" * 5000)  # 2 bytes each: cut on a character boundary
    assert cut == "\u00e9" * (rpc.MAX_DETAILS_BYTES // 2) + f"... ({5000 - rpc.MAX_DETAILS_BYTES // 2} more characters)"


def test_server_streams_take_slots_and_cancellation_is_counted(
    probe: tuple[rpc.RunningServer, threading.Event],
) -> None:
    running, _ = probe
    method = "/test.Probe/Hold"
    cancelled = _count(method, "CANCELLED")
    with grpc.insecure_channel(running.address()) as channel:
        hold = channel.unary_stream(method)
        calls = [hold(b"") for _ in range(rpc.stream_limit(MAX_WORKERS))]
        assert [next(c) for c in calls] == [b"open"] * len(calls)  # every slot is taken now
        with pytest.raises(grpc.RpcError) as err:
            next(hold(b"", timeout=10))
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "probe.server.max_workers" in err.value.details()
        assert _count(method, "RESOURCE_EXHAUSTED") >= 1
        status = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10).status
        assert status == health_pb2.HealthCheckResponse.SERVING
        calls.pop().cancel()
        wait_for(lambda: _count(method, "CANCELLED") == cancelled + 1, "the cancelled stream counted CANCELLED")
        again = wait_for(lambda: _next_or_none(hold(b"", timeout=10)), "a stream accepted after one was cancelled")
        assert again == b"open"
        for call in calls:
            call.cancel()


def _next_or_none(call: Any) -> bytes | None:
    try:
        return next(call)
    except grpc.RpcError as err:
        if err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
            return None
        raise
    finally:
        call.cancel()


# --------------------------------------------------------------------------- replay's own bad input


def test_table_ratios_whose_sum_overflows(make_service: Callable[..., ReplayService]) -> None:
    assert _split(4, {"a": 1e308, "b": 1e308}) == {"a": 2, "b": 2}
    assert _split(4, {"a": 1e308, "b": 1e-308}) == {"a": 4, "b": 0}
    svc = make_service()
    insert(svc, episode("arm-0", "on", 3))
    insert_into(svc, episode("arm-0", "t2", 3), "t2", first_seq=10)
    for tables in ({"online": 1e308, "t2": 1e308}, {"online": 1e308, "t2": 1e-308}):
        resp = stub(svc).Sample(replay_pb2.SampleRequest(batch_size=4, tables=tables), timeout=10)
        assert wire.from_tensor(resp.batch.reward).shape == (4,)
        assert dict(resp.table_transitions) == {"online": 3, "t2": 3}


def test_sample_robot_ids_are_bounded(make_service: Callable[..., ReplayService]) -> None:
    svc = make_service()
    for robot_ids, where in (
        (["g" * 20_000], "robot_ids[0]"),
        (["arm-0", ""], "robot_ids[1]"),
        ([f"r{k}" for k in range(MAX_SAMPLE_ROBOTS + 1)], f"at most {MAX_SAMPLE_ROBOTS}"),
    ):
        with pytest.raises(grpc.RpcError) as err:
            stub(svc).Sample(replay_pb2.SampleRequest(batch_size=4, robot_ids=robot_ids), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and where in err.value.details()
    # thousands of unknown robots: the intended status, naming a few of them
    with pytest.raises(grpc.RpcError) as err:
        stub(svc).Sample(replay_pb2.SampleRequest(batch_size=4, robot_ids=[f"robot-{k}" for k in range(3000)]))
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert "no sampleable transitions" in err.value.details() and "and 2992 more" in err.value.details()


def test_priorities_up_to_float32_max(make_service: Callable[..., ReplayService]) -> None:
    """Any finite priority is taken (3e38 used to be refused as "not finite"); sampling at the largest alpha
    stays finite, and inserting after such a priority still works (p**alpha overflowed float64 there)."""
    svc = make_service()
    insert(svc, episode("arm-0", "a", 6))
    req = replay_pb2.SampleRequest(batch_size=8, sampler=replay_pb2.SAMPLER_PRIORITIZED, priority_alpha=10)
    indices = wire.from_tensor(stub(svc).Sample(req, timeout=10).batch.indices)
    top = float(np.finfo(np.float32).max)
    resp = stub(svc).UpdatePriorities(
        replay_pb2.UpdatePrioritiesRequest(indices=indices[:2].tolist(), priorities=[3e38, top]), timeout=10
    )
    assert resp.updated == 2
    insert(svc, episode("arm-0", "b", 4), first_seq=100)
    weights = wire.from_tensor(stub(svc).Sample(req, timeout=10).batch.weights)
    assert np.isfinite(weights).all() and (weights > 0).all() and (weights <= 1).all()
    with pytest.raises(grpc.RpcError) as err:
        stub(svc).UpdatePriorities(
            replay_pb2.UpdatePrioritiesRequest(indices=[int(indices[0])], priorities=[float("inf")]), timeout=10
        )
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_an_empty_insert_batch_is_refused(make_service: Callable[..., ReplayService]) -> None:
    svc = make_service()
    batches = [
        replay_pb2.InsertBatchRequest(requests=requests(episode("arm-0", "e", 3))),
        replay_pb2.InsertBatchRequest(),
    ]
    acked: list[int] = []
    with pytest.raises(grpc.RpcError) as err:
        for ack in stub(svc).InsertBatch(iter(batches), timeout=10):
            acked += ack.seqs
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "no steps" in err.value.details()
    assert sorted(acked) == [0, 1, 2] and stats(svc).steps == 3  # what came before is committed and acknowledged


def test_a_held_step_cannot_be_an_intervention(make_service: Callable[..., ReplayService]) -> None:
    svc = make_service()
    steps = episode("arm-0", "e", 3)
    steps[1].held = steps[1].intervention = True
    with pytest.raises(grpc.RpcError) as err:
        list(stub(svc).Insert(iter(requests(steps)), timeout=10))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "seq 1" in err.value.details() and "held and intervention" in err.value.details()
    st = stats(svc)
    assert st.steps == 1 and "interventions" not in st.tables


def test_a_control_connect_cancelled_before_register_is_counted_cancelled() -> None:
    """It was counted UNKNOWN: the handler's read of the cancelled request stream raised."""
    method = "/user.v1.Control/Connect"
    before = {code: _count(method, code) for code in ("CANCELLED", "UNKNOWN")}
    opened = _open_streams(method)
    control = ControlService(control_cfg()).start()
    try:
        up: queue.Queue = queue.Queue()
        call = control_pb2_grpc.ControlStub(rpc.make_channel(control.address, AUTH)).Connect(iter(up.get, None))
        wait_for(lambda: _open_streams(method) > opened, "the Connect stream open")
        call.cancel()
        up.put(None)
        wait_for(lambda: _count(method, "CANCELLED") == before["CANCELLED"] + 1, "the cancelled Connect counted")
        assert _count(method, "UNKNOWN") == before["UNKNOWN"]
    finally:
        control.stop()
