"""Tables, mixing ratios, priorities and per-table stats over real gRPC (127.0.0.1:0, real LMDB)."""

from __future__ import annotations

import grpc
import numpy as np
import pytest

from services.replay.server import ReplayService
from tests.test_replay_service import insert, insert_failing, make_service, requests, service, specs, stats, stub
from tests.test_replay_store import episode, make_step
from user import wire
from user.v1 import replay_pb2

__all__ = ["make_service", "service", "specs"]  # fixtures


def insert_into(svc: ReplayService, steps, table: str, first_seq: int = 0) -> None:
    reqs = requests(steps, first_seq)
    for r in reqs:
        r.table = table
    acked = [s for ack in stub(svc).Insert(iter(reqs), timeout=10) for s in ack.seqs]
    assert acked == [r.seq for r in reqs]


def test_rlpd_mixing_over_grpc(service: ReplayService) -> None:
    insert(service, episode("arm-0", "on", 30, policy_version=1))
    insert_into(service, episode("arm-0", "demo", 8, policy_version=2), "demos")
    steps = episode("arm-0", "hil", 6, policy_version=3)
    steps[2].intervention = True
    insert(service, steps, first_seq=100)
    req = replay_pb2.SampleRequest(batch_size=64, tables={"online": 1, "demos": 1})
    for _ in range(3):  # the second and third may come from the prefetcher: same contract
        resp = stub(service).Sample(req, timeout=5)
        versions = wire.from_tensor(resp.batch.policy_version)
        assert (versions == 2).sum() == 32 and np.isin(versions[versions != 2], [1, 3]).all()
        assert dict(resp.table_transitions) == {"online": 36, "demos": 8}
    hil = stub(service).Sample(
        replay_pb2.SampleRequest(batch_size=16, tables={"interventions": 1}, n_step=3, gamma=0.9), timeout=5
    )
    assert set(wire.from_tensor(hil.batch.indices)) and wire.from_tensor(hil.batch.intervention).all()
    assert set(wire.from_tensor(hil.batch.n_steps)) == {3}
    stacked = stub(service).Sample(replay_pb2.SampleRequest(batch_size=8, frame_stack=4), timeout=5)
    assert wire.from_tensor(stacked.batch.observation.tensors["state"]).shape == (8, 4, 6)
    st = stats(service)
    assert st.tables["online"].transitions == 36 and st.tables["demos"].transitions == 8
    assert st.tables["demos"].episodes == 1 and st.tables["interventions"].transitions == 1
    assert st.tables["online"].robots["arm-0"].episodes == 2
    assert st.hot_hits > 0 and st.hot_transitions == 44


def test_priorities_over_grpc(service: ReplayService) -> None:
    insert(service, episode("arm-0", "e", 10))
    req = replay_pb2.SampleRequest(batch_size=32, sampler=replay_pb2.SAMPLER_PRIORITIZED, priority_alpha=1)
    ids = wire.from_tensor(stub(service).Sample(req, timeout=5).batch.indices)
    chosen = int(ids[0])
    all_ids = sorted(set(range(10)))
    pri = [100.0 if i == chosen else 0.0 for i in all_ids]
    resp = stub(service).UpdatePriorities(
        replay_pb2.UpdatePrioritiesRequest(indices=all_ids, priorities=pri), timeout=5
    )
    assert resp.updated == 10
    req.batch_size = 33  # another request kind: nothing prefetched before the update
    assert set(wire.from_tensor(stub(service).Sample(req, timeout=5).batch.indices)) == {chosen}


@pytest.mark.parametrize(
    "request_",
    [
        replay_pb2.SampleRequest(batch_size=8, tables={"bad/name": 1}),
        replay_pb2.SampleRequest(batch_size=8, tables={"online": 0}),
        replay_pb2.SampleRequest(batch_size=8, tables={"online": float("nan")}),
        replay_pb2.SampleRequest(batch_size=8, sampler=7),
        replay_pb2.SampleRequest(batch_size=8, n_step=3),  # no gamma
        replay_pb2.SampleRequest(batch_size=8, n_step=3, gamma=1.5),
        replay_pb2.SampleRequest(batch_size=8, priority_alpha=float("inf")),
        replay_pb2.SampleRequest(batch_size=8, frame_stack=65),
    ],
    ids=["table-name", "zero-ratio", "nan-ratio", "sampler", "no-gamma", "gamma", "alpha", "frame-stack"],
)
def test_bad_sample_requests_are_invalid_argument(service: ReplayService, request_) -> None:
    insert(service, episode("arm-0", "e", 5))
    with pytest.raises(grpc.RpcError) as err:
        stub(service).Sample(request_, timeout=5)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_bad_priorities_and_table_names_change_nothing(service: ReplayService) -> None:
    insert(service, episode("arm-0", "e", 5))
    before = stats(service)
    for bad in (
        replay_pb2.UpdatePrioritiesRequest(indices=[0, 1], priorities=[1.0]),
        replay_pb2.UpdatePrioritiesRequest(indices=[0], priorities=[float("nan")]),
        replay_pb2.UpdatePrioritiesRequest(indices=[0], priorities=[-1.0]),
        replay_pb2.UpdatePrioritiesRequest(indices=[-1], priorities=[1.0]),
    ):
        with pytest.raises(grpc.RpcError) as err:
            stub(service).UpdatePriorities(bad, timeout=5)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    reqs = requests([make_step("arm-0", "x", 0)], first_seq=5)
    reqs[0].table = "no spaces allowed"
    with pytest.raises(grpc.RpcError) as err:
        list(stub(service).Insert(iter(reqs), timeout=5))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "seq 5" in err.value.details()
    after = stats(service)
    assert (after.steps, after.transitions, dict(after.tables)) == (
        before.steps,
        before.transitions,
        dict(before.tables),
    )
    assert insert_failing  # the shared helper stays importable for other tests


def test_rate_limiter_min_size_and_samples_per_insert(make_service) -> None:
    svc = make_service(min_size_to_sample=8, samples_per_insert=2.0, samples_per_insert_slack=0.0)
    insert(svc, episode("arm-0", "a", 4))
    with pytest.raises(grpc.RpcError) as err:
        stub(svc).Sample(replay_pb2.SampleRequest(batch_size=4), timeout=5)
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "min_size_to_sample" in err.value.details()
    insert(svc, episode("arm-0", "b", 6), first_seq=10)  # 10 inserted: 20 samples allowed
    stub(svc).Sample(replay_pb2.SampleRequest(batch_size=16), timeout=5)
    with pytest.raises(grpc.RpcError) as err:
        stub(svc).Sample(replay_pb2.SampleRequest(batch_size=8), timeout=5)
    assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "rate limited" in err.value.details()
    insert(svc, episode("arm-0", "c", 2), first_seq=20)  # 12 inserted: 24 allowed
    stub(svc).Sample(replay_pb2.SampleRequest(batch_size=8), timeout=5)


def test_one_off_requests_leave_no_feeders_or_state_behind() -> None:
    """What made replay's RSS grow under the fuzz: every distinct Sample request started a feeder thread that
    kept batches (up to 64 MiB each) for 10 s. Now only a repeated kind gets one, and only for small batches."""
    from services.replay.prefetch import Prefetcher

    pre = Prefetcher(2, 1.0, lambda: 0)
    try:
        for i in range(50):  # 50 different one-off requests: no thread
            assert pre.get(f"kind-{i}".encode(), lambda i=i: i) == i
        assert not pre._feeders
        pre.get(b"big", lambda: 1, lambda _: False)
        pre.get(b"big", lambda: 1, lambda _: False)  # repeated, but not worth keeping
        assert not pre._feeders
        pre.get(b"learner", lambda: 7)
        pre.get(b"learner", lambda: 7)  # a learner's repeated request gets its feeder
        assert list(pre._feeders) == [b"learner"]
    finally:
        pre.close()


def test_tables_and_unknown_robots_are_bounded(service: ReplayService, monkeypatch) -> None:
    """A client cannot grow replay's RAM with names: tables are capped (each costs index columns and a metric
    series), and refused steps of unknown robots leave no per-robot entry behind."""
    from services.replay import server as replay_server

    monkeypatch.setattr(replay_server, "MAX_STORE_TABLES", 2)
    for name in ("t1", "t2"):
        insert_into(service, episode("arm-0", name, 3), name)
    before = stats(service)
    reqs = requests(episode("arm-0", "t3", 3))
    for r in reqs:
        r.table = "t3"
    with pytest.raises(grpc.RpcError) as err:
        list(stub(service).Insert(iter(reqs), timeout=10))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "at most 2" in err.value.details()
    insert_into(service, episode("arm-0", "t1b", 3), "t1")  # an existing table still takes steps
    assert stats(service).steps == before.steps + 3 and set(stats(service).tables) == {"t1", "t2"}
    for i in range(20):
        _acked, err = insert_failing(service, [make_step(f"ghost-{i}", "e", 0)])
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert not any(r.startswith("ghost") for r in service.servicer.specs._fetched_at)
