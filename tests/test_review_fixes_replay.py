"""Review fixes around replay's tables and removed experiments, against real parts (replay services on 127.0.0.1,
LMDB in tmp dirs, a real weight server with its shared-memory directory):

1. ShardedSampler samples a table held by a shard of its own (imported demos, no online step of the experiment's
   robots) every batch, not every other one; a shard's stale per-table counts refresh it, never empty it;
2. Stats(spec_tables) lists the specs of an attached buffer's robots (kept in that buffer, not this one);
3. a version published after its experiment was dropped is refused: not served, no shared-memory file, its
   streams stay NOT_FOUND, and the learner's run does not count it;
4. Stats(counts_only) answers the per-table per-robot transitions from the index, the same as the full answer.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest

from cloud_learner.replay_sampler import ShardedSampler
from services.replay.server import ReplayService
from tests.helpers import free_port
from tests.test_edge_agent import stack_cfg
from tests.test_learner_semantics import AUTH, DEMO, ONLINE, _run, _spec, demo_steps, insert, online_steps, stub
from tests.test_replay_service import _cfg
from tests.test_replay_store import episode, spec
from tests.test_weight_streams import SPEC, Server, tensors
from user import wire
from user.rpc import make_channel
from user.v1 import learner_pb2, learner_pb2_grpc, replay_pb2
from user.weight_shm import ShmWeights
from user.weights import WeightServicer, WeightStore

RLPD = {"online": 1.0, "demos": 1.0}
IMPORTED = "lerobot-local-arm"  # the demos' robot: on shard B only


def replay(tmp_path: Path, name: str) -> ReplayService:
    cfg = stack_cfg(tmp_path / name)
    cfg.replay.server.port = free_port()
    specs = {r: _spec(r) for r in ("arm-0", "arm-b", IMPORTED)}
    return ReplayService(cfg, spec_source=specs.get, start_metrics=False).start()


@pytest.fixture
def split(tmp_path: Path) -> Iterator[tuple[ReplayService, ReplayService]]:
    """Shard A: arm-0's online steps alone; shard B: imported demos (another robot id) alone."""
    a, b = replay(tmp_path, "a"), replay(tmp_path, "b")
    insert(a, online_steps("arm-0", 10))
    insert(b, demo_steps(IMPORTED, 10), "demos")
    yield a, b
    a.stop()
    b.stop()


def _rlpd(batch_size: int = 32) -> replay_pb2.SampleRequest:
    """What the learner asks for: online from its robot, demos from the imported robot that fits it."""
    request = replay_pb2.SampleRequest(batch_size=batch_size, tables=RLPD, robot_ids=["arm-0"])
    request.table_robot_ids["demos"].ids.append(IMPORTED)
    return request


def _marks(resp: replay_pb2.SampleResponse) -> np.ndarray:
    return wire.from_tensor(resp.batch.observation.tensors["state"])[:, 0]


# --------------------------------------------------------------------------- 1. a shard of demos alone


def test_a_shard_holding_only_the_demos_serves_every_batch(split: tuple[ReplayService, ReplayService]) -> None:
    """B holds none of arm-0's transitions: its table answer says transitions=0. Before, that made B look empty,
    the next batch found no holder of demos (FAILED_PRECONDITION) and a re-probe brought B back: ok, error, ok..."""
    a, b = split
    sampler = ShardedSampler([a.address, b.address], AUTH, timeout_s=10, seed=0)
    try:
        for i in range(20):
            resp = sampler.Sample(_rlpd(), timeout=10)
            marks = _marks(resp)
            assert int((marks == DEMO).sum()) == 16 and int((marks == ONLINE).sum()) == 16, i
            assert dict(resp.table_transitions) == {"online": 100, "demos": 100}
            assert resp.transitions == 100  # arm-0's, as one replay answers: B holds none of them
        shard_b = sampler.shards[1]
        assert shard_b.up and shard_b.transitions == 100 and shard_b.table_count("demos", [IMPORTED]) == 100
    finally:
        sampler.close()


def test_stale_table_counts_refresh_the_shard_and_keep_its_other_rows(
    split: tuple[ReplayService, ReplayService],
) -> None:
    """A's counts say it holds demos it does not (stale): its FAILED_PRECONDITION reads A's counts again and the
    batch is asked again by them: A's online rows from A, the demos from B. A stays a live shard with its online
    transitions (before, it was zeroed and left out, and this batch had no holder of online rows)."""
    a, b = split
    sampler = ShardedSampler([a.address, b.address], AUTH, timeout_s=10, seed=0)
    try:
        sampler.Sample(_rlpd(), timeout=10)  # the first batch reads both shards' counts
        shard_a = sampler.shards[0]
        shard_a.tables["demos"] = {IMPORTED: 1_000_000}  # as a Stats before its demos left would have said
        for _ in range(5):
            marks = _marks(sampler.Sample(_rlpd(), timeout=10))
            assert int((marks == DEMO).sum()) == 16 and int((marks == ONLINE).sum()) == 16
        assert shard_a.up and shard_a.transitions == 100 and shard_a.table_count("demos", []) == 0
    finally:
        sampler.close()


# --------------------------------------------------------------------------- 2. specs of an attached buffer


def test_stats_lists_the_specs_of_an_attached_buffers_robots(tmp_path: Path) -> None:
    old = ReplayService(_cfg(tmp_path / "old"), spec_source={IMPORTED: spec(IMPORTED)}.get, start_metrics=False).start()
    try:
        reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(episode(IMPORTED, "d1", 5))]
        assert sum(ack.stored for ack in stub(old).Insert(iter(reqs), timeout=30)) == 5
    finally:
        old.stop()
    # this replay knows nothing of IMPORTED: its spec is in the attached buffer alone
    svc = ReplayService(
        _cfg(tmp_path / "new", attach={"demos": tmp_path / "old"}),
        spec_source={"arm-0": spec("arm-0")}.get,
        start_metrics=False,
    ).start()
    try:
        stats = stub(svc).Stats(replay_pb2.StatsRequest(spec_tables=["demos"]), timeout=10)
        assert [s.robot_id for s in stats.specs] == [IMPORTED] and stats.specs_left_out == 0
        assert stats.specs[0] == spec(IMPORTED)
        assert stats.tables["demos"].robots[IMPORTED].transitions == 5
    finally:
        svc.stop()


# --------------------------------------------------------------------------- 3. a late publish of a removed experiment


def _buffers(shm_dir: Path) -> list[str]:
    return [n for n in os.listdir(shm_dir) if "-buf-" in n or "-gone-v" in n]


def test_a_version_published_after_the_drop_is_refused(tmp_path: Path) -> None:
    shm_dir = tmp_path / "shm"
    shm_dir.mkdir()
    store = WeightStore()
    shm = ShmWeights(str(shm_dir), keep=2, host="test-host")
    srv = Server(store, WeightServicer(store, poll_s=0.1, shm=shm))
    big = tensors(0, n=1 << 19)  # a 4 MiB payload: packed into a shared-memory buffer
    try:
        assert store.publish(1, SPEC, big, experiment="gone") is not None
        assert _buffers(shm_dir)  # there was a file to write
        store.drop("gone")
        gc.collect()
        assert _buffers(shm_dir) == []
        assert store.publish(2, SPEC, tensors(1, n=1 << 19), experiment="gone") is None  # the run's late version
        gc.collect()
        assert _buffers(shm_dir) == []  # not packed into shared memory
        assert store.latest("gone") is None and "gone" not in store.experiments() and store.dropped("gone")
        call = learner_pb2_grpc.LearnerStub(make_channel(srv.addr, AUTH)).SubscribeWeights(
            learner_pb2.SubscribeWeightsRequest(experiment="gone"), timeout=10
        )
        with pytest.raises(grpc.RpcError) as err:
            next(call)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND
        assert store.publish(1, SPEC, tensors(2), experiment="other") is not None  # other experiments publish on
    finally:
        srv.close()
        shm.close()


def test_a_runs_late_publish_of_a_removed_experiment_is_not_counted(tmp_path: Path) -> None:
    run = _run(tmp_path, "bc", {"batch_size": 8, "hidden": [16]})
    store = run.learner.store
    run.publish(1)
    assert store.latest("a") is not None and run.state.weight_version == 1
    store.drop("a")
    run.publish(2)  # its training thread, still running after the learner dropped it
    assert store.latest("a") is None and "a" not in store.experiments()
    assert run.state.weight_version == 1


# --------------------------------------------------------------------------- 4. Stats' counts alone


def test_counts_only_stats_match_the_full_counts(tmp_path: Path) -> None:
    svc = replay(tmp_path, "r")
    try:
        insert(svc, online_steps("arm-0", 3))
        insert(svc, demo_steps("arm-b", 2), "demos", first_seq=1000)
        insert(svc, online_steps("arm-b", 1, mark=3.0), first_seq=2000)
        full = stub(svc).Stats(replay_pb2.StatsRequest(spec_tables=["demos"]), timeout=10)
        cheap = stub(svc).Stats(replay_pb2.StatsRequest(spec_tables=["demos"], counts_only=True), timeout=10)
        assert cheap.transitions == full.transitions == 60 and list(cheap.specs) == list(full.specs)
        counts = {t: {r: c.transitions for r, c in s.robots.items()} for t, s in cheap.tables.items()}
        assert counts == {t: {r: c.transitions for r, c in s.robots.items()} for t, s in full.tables.items()}
        assert counts == {"online": {"arm-0": 30, "arm-b": 10}, "demos": {"arm-b": 20}}
        assert {t: s.transitions for t, s in cheap.tables.items()} == {"online": 40, "demos": 20}
        assert full.tables["online"].episodes == 4 and cheap.tables["online"].episodes == 0  # not walked
    finally:
        svc.stop()
