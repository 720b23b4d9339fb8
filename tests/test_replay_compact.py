"""Index compaction: a replay that evicts far more than it keeps holds index rows for what it keeps only.

Real ReplayStore on LMDB in tmp dirs, and the real replay gRPC service on 127.0.0.1.
"""

from __future__ import annotations

import re
import threading
import urllib.request
from collections.abc import Callable
from pathlib import Path

import grpc
import numpy as np
import pytest

from services.replay.disk import episode_prefix
from services.replay.server import ReplayService
from services.replay.store import ReplayStore
from services.replay.tables import Draw
from tests.test_replay_chunks import check_chunks
from tests.test_replay_service import _cfg, make_service, specs, stub
from tests.test_replay_store import episode, spec
from user import wire
from user.v1 import replay_pb2

__all__ = ["make_service", "specs"]  # fixtures

LENGTH, DIM = 10, 2000  # ~8 KB a step: ~12 episodes fit in 1 MiB


def fill(put: Callable[[list], object], episodes: int, first: int = 0) -> None:
    """Episodes e of LENGTH steps (policy_version e), terminated when e is even, truncated when odd; every
    third one arrives in two halves, the second half first (the out-of-order indexing path)."""
    for e in range(first, first + episodes):
        steps = episode("arm-0", f"e{e:04d}", LENGTH, terminated=e % 2 == 0, dim=DIM, policy_version=e)
        if e % 3 == 2:
            put(steps[LENGTH // 2 :])
            put(steps[: LENGTH // 2])
        else:
            put(steps)


def index_rows(store: ReplayStore) -> list[int]:
    idx = store.index
    cols = [idx.episode, idx.step, idx.robot, idx.group, idx.hot_row, idx.reward, idx.terminated, idx.truncated,
            idx.intervention, idx.policy_version, idx.next_tid, idx.prev_tid, idx.alive, idx.priority,
            idx.ids]  # fmt: skip
    return [len(idx.slot_of), sum(map(len, idx.episode_rows)), *(c.n for c in cols)]


def check_n_step(batch: dict, gamma: float, n_step: int) -> None:
    t = batch["observation"]["state"][:, 0].astype(int)
    version = batch["policy_version"]
    n = np.minimum(n_step, LENGTH - t)
    np.testing.assert_array_equal(batch["n_steps"], n)
    expected = [sum(-(t0 + k) * gamma**k for k in range(k_n)) for t0, k_n in zip(t, n, strict=True)]
    np.testing.assert_allclose(batch["reward"], expected, rtol=1e-5)
    np.testing.assert_array_equal(batch["next_observation"]["state"][:, 0], t + n)
    ends = t + n == LENGTH
    np.testing.assert_array_equal(batch["terminated"], ends & (version % 2 == 0))
    np.testing.assert_array_equal(batch["truncated"], ends & (version % 2 == 1))
    np.testing.assert_allclose(batch["action"][:, 0], 0.1 * (t % 10), rtol=1e-6)


def test_compaction_keeps_the_index_proportional_to_what_is_stored(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    store.index.compact_min = 16
    try:
        fill(store.put_steps, 150)  # ~12x what capacity holds
        live = store.transitions
        assert 0 < live <= 20 * LENGTH
        assert max(index_rows(store)) <= 2 * live  # without compaction: a row per transition ever indexed
        assert store.compactions > 0
        assert store.index.n_rows == store.index.alive.n == live + store.index.dead
        assert len(store.index.alive.a) <= max(1024, 4 * live)  # capacity shrank with the rows
        # the hot tier is at most twice capacity_mb (not cache_mb's 256 MB of evicted transitions)
        assert store.hot_bytes == 2 << 20 and store.cache_info()["bytes"] <= (2 << 20) * 9 // 8  # (frame ring slack)
        # and its ring has no more rows than capacity holds steps (+25%): not 2 MB of rows for 1 MB of steps
        step_bytes = episode("arm-0", "e0000", 2, dim=DIM)[0].ByteSize()
        assert live <= store.cache_info()["capacity"] <= (1 << 20) * 1.25 / step_bytes
        rows = store.index.episode_rows
        assert sum(map(len, rows)) == live == len(store.index.slot_of) * LENGTH  # whole episodes, live rows only
        survivors = set(range(150 - store.stats()["episodes"], 150))
        misses = store.cache_info()["misses"]
        batch = store.sample(2000, np.random.default_rng(0), draw=Draw(2000, n_step=3, gamma=0.5))
        assert set(batch["policy_version"].tolist()) == survivors  # the oldest left, whole
        check_n_step(batch, 0.5, 3)
        # hot rows still validate against renumbered rows (only out-of-order completions may be cold)
        cold = int((batch["policy_version"] % 3 == 2).sum())
        assert store.cache_info()["misses"] - misses <= cold < 1000
        stacked = store.sample(256, np.random.default_rng(1), draw=Draw(256, frame_stack=3))
        t = stacked["observation"]["state"][:, :, 0]
        np.testing.assert_array_equal(t, np.maximum(t[:, 2:] + np.array([-2, -1, 0]), 0))
        nxt = np.maximum(t[:, 2:] + np.array([-1, 0, 1]), 0)  # an episode's first observation repeats
        np.testing.assert_array_equal(stacked["next_observation"]["state"][:, :, 0], nxt)
    finally:
        store.close()


def test_priorities_and_ids_survive_compaction(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    store.index.compact_min = 16
    try:
        fill(store.put_steps, 40)
        first = store.compactions
        assert first > 0
        before = store.sample(4000, np.random.default_rng(0))
        ids = np.unique(before["indices"])
        assert len(ids) == store.transitions and ids.min() >= LENGTH  # public ids are not renumbered rows
        chosen = int(ids[len(ids) // 2])
        obs = before["observation"]["state"][before["indices"] == chosen][0, 0]
        assert store.update_priorities(ids, np.where(ids == chosen, 100.0, 0.0)) == len(ids)
        assert store.update_priorities(np.array([0, LENGTH - 1]), np.ones(2)) == 0  # evicted ids are skipped
        batch = store.sample(256, np.random.default_rng(1), draw=Draw(256, sampler="prioritized", alpha=1.0))
        assert set(batch["indices"].tolist()) == {chosen}
        assert set(batch["observation"]["state"][:, 0].tolist()) == {obs}
        fill(store.put_steps, 40, first=40)  # evicts `chosen` and compacts again
        assert store.compactions > first
        again = store.sample(512, np.random.default_rng(2), draw=Draw(512, sampler="prioritized", n_step=2))
        assert chosen not in set(again["indices"].tolist()) and again["indices"].min() > ids.max()
        check_n_step(again, 0.99, 2)
        newest = store.sample(64, np.random.default_rng(3), draw=Draw(64, sampler="recency", window=LENGTH))
        assert (newest["policy_version"] == 79).all()
        assert store.update_priorities(newest["indices"], np.full(64, 5.0)) == 64
        top = store.sample(64, np.random.default_rng(4), draw=Draw(64, sampler="prioritized", alpha=1.0))
        assert top["weights"].min() > 0
    finally:
        store.close()


def test_chunks_and_priorities_over_grpc_after_compaction(make_service: Callable[..., ReplayService]) -> None:
    service = make_service(spec_source=lambda robot: spec(robot, obs_dim=DIM), capacity_mb=1)
    service.store.index.compact_min = 16
    seq = 0

    def put(steps: list) -> None:
        nonlocal seq
        reqs = [replay_pb2.InsertRequest(seq=seq + i, step=s) for i, s in enumerate(steps)]
        seq += len(steps)
        assert [s for ack in stub(service).Insert(iter(reqs), timeout=60) for s in ack.seqs] == [r.seq for r in reqs]

    fill(put, 60)
    assert service.store.compactions > 0
    stats = stub(service).Stats(replay_pb2.StatsRequest(), timeout=60)
    evicted = sum(stats.evicted_steps_per_robot.values())
    assert evicted > 0  # capacity evicted whole episodes, and Stats accounts for every acked step
    assert sum(stats.steps_per_robot.values()) + evicted == seq
    assert service.store.index.n_rows <= 2 * service.store.transitions
    req = replay_pb2.SampleRequest(batch_size=256, action_horizon=4)
    batch = stub(service).Sample(req, timeout=60).batch
    assert check_chunks(batch, 4, lambda version, t: LENGTH - 1) > 0
    chosen = int(wire.from_tensor(batch.indices)[0])
    idx = service.store.index
    ids = idx.ids.view()[idx.alive.view()]  # every live transition: all but `chosen` get priority 0
    pri = np.where(ids == chosen, 50.0, 0.0).tolist()
    updated = stub(service).UpdatePriorities(
        replay_pb2.UpdatePrioritiesRequest(indices=ids.tolist(), priorities=pri), timeout=60
    )
    assert updated.updated == len(ids)
    draw = replay_pb2.SampleRequest(
        batch_size=64, sampler=replay_pb2.SAMPLER_PRIORITIZED, priority_alpha=1.0, action_horizon=2
    )
    for _ in range(2):  # the second may come from the prefetcher
        got = stub(service).Sample(draw, timeout=60).batch
        assert set(wire.from_tensor(got.indices).tolist()) == {chosen}
        check_chunks(got, 2, lambda version, t: LENGTH - 1)


def test_samples_never_read_steps_that_eviction_removed(tmp_path: Path) -> None:
    """Eviction leaves the index before LMDB: a sample drawing while a writer evicts never finds a step gone
    (it did: ReplayError, seen as UNKNOWN by the learner in the 64-robot load test)."""
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1, cache_mb=0)  # cache off: every read goes to LMDB
    store.index.compact_min = 16
    fill(store.put_steps, 2)
    done = threading.Event()

    def writer() -> None:
        fill(store.put_steps, 300, first=2)
        done.set()

    thread = threading.Thread(target=writer, daemon=True)
    thread.start()
    rng = np.random.default_rng(0)
    samples = 0
    try:
        while not done.is_set() or samples < 100:
            store.sample(64, rng, draw=Draw(64, n_step=3, gamma=0.5))  # raised ReplayError before the fix
            samples += 1
        thread.join()
        assert store.stats()["evicted_steps_per_robot"]["arm-0"] > 0
    finally:
        done.wait()
        store.close()


def scrape(service: ReplayService, name: str) -> float:
    """A counter's value as the service's /metrics serves it."""
    url = f"http://127.0.0.1:{service.running.metrics_port}/metrics"  # type: ignore[union-attr]
    body = urllib.request.urlopen(url, timeout=10).read().decode()
    found = re.search(rf"^{name} (\S+)$", body, re.MULTILINE)
    assert found is not None, f"/metrics lacks {name}"
    return float(found.group(1))


def test_metrics_count_compactions_and_aborted_samples(tmp_path: Path) -> None:
    """/metrics counts index compactions and Samples answered ABORTED because the buffer changed under them."""
    cfg = _cfg(tmp_path / "replay", capacity_mb=1, cache_mb=0)  # cache off: a sample reads LMDB
    service = ReplayService(cfg, spec_source=lambda robot: spec(robot, obs_dim=DIM)).start()
    try:
        compactions, aborted = (
            scrape(service, f"user_replay_{m}_total") for m in ("index_compactions", "sample_aborted")
        )
        service.store.index.compact_min = 16
        fill(service.store.put_steps, 60)
        assert service.store.compactions > 0
        assert scrape(service, "user_replay_index_compactions_total") - compactions == service.store.compactions
        # What the eviction race leaves behind: the index still lists an episode LMDB no longer has
        # (the old eviction order). Its steps are gone from LMDB only; a sample drawing them is ABORTED.
        newest = service.store.sample(1, np.random.default_rng(0), draw=Draw(1, sampler="recency", window=1))
        version = int(newest["policy_version"][0])
        assert service.store.db.delete_episodes([episode_prefix("arm-0", f"e{version:04d}")]) == LENGTH
        req = replay_pb2.SampleRequest(batch_size=1, sampler=replay_pb2.SAMPLER_RECENCY, recency_window=1)
        with pytest.raises(grpc.RpcError) as err:
            stub(service).Sample(req, timeout=60)
        assert err.value.code() == grpc.StatusCode.ABORTED
        assert scrape(service, "user_replay_sample_aborted_total") - aborted == 1
    finally:
        service.stop()
