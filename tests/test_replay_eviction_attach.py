"""Capacity eviction never cuts an episode still being written; attach never writes into nor races its buffer's
owner; the edge spool counts as dropped only the steps replay never got.

Real ReplayStore on LMDB in tmp dirs, the real replay gRPC service on 127.0.0.1, a real owner process, the real
edge sender and spool.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import prometheus_client
import pytest

from edge_agent.replay_client import ReplaySender
from edge_agent.spool import LmdbSpool
from services.replay.server import ReplayService
from services.replay.store import ReplayStore
from tests.helpers import wait_for
from tests.test_replay_service import AUTH, _cfg, stub
from tests.test_replay_store import episode, make_step, spec
from user.config import ConfigError
from user.v1 import replay_pb2, step_pb2

DIM = 2000  # ~8 KB a step: 1 MiB holds ~125 steps


def _service(path: Path, robots: tuple[str, ...] = ("arm-0",), **replay: object) -> ReplayService:
    specs = {r: spec(r, obs_dim=DIM) for r in robots}
    return ReplayService(_cfg(path, **replay), spec_source=specs.get, start_metrics=False).start()


def _insert(svc: ReplayService, steps: list[step_pb2.Step], first_seq: int) -> int:
    reqs = [replay_pb2.InsertRequest(seq=first_seq + i, step=s) for i, s in enumerate(steps)]
    return sum(ack.stored for ack in stub(svc).Insert(iter(reqs), timeout=60))


def _indices(store: ReplayStore, robot: str, name: str) -> list[int]:
    return [t for r, e, t in _stored_steps(store) if (r, e) == (robot, name)]


def _episodes(store: ReplayStore) -> set[tuple[str, str]]:
    """(robot, episode) of the episodes the store holds (evicted ones leave LMDB with its next commit)."""
    return {(robot, name) for robot, name, _, _ in store.episode_bounds()}


def _stored_steps(store: ReplayStore) -> list[tuple[str, str, int]]:
    out = []
    for key, _ in store.db.scan():
        robot, name, rest = key.split(b"/", 2)
        out.append((robot.decode(), name.decode(), int.from_bytes(rest, "big")))
    return out


def _over_capacity() -> float | None:
    return prometheus_client.REGISTRY.get_sample_value("user_replay_over_capacity")


# ---------------------------------------------------------------------- 1: eviction


def test_capacity_eviction_keeps_an_episode_its_robot_still_writes(tmp_path: Path) -> None:
    """A long episode written while another robot fills the buffer keeps every step: only ended episodes go (before:
    its steps 0-9 were evicted as the oldest, steps 10-14 then stored as an episode without a start)."""
    svc = _service(tmp_path / "replay", ("long", "short"), capacity_mb=1)
    try:
        assert _insert(svc, [make_step("long", "L", t, dim=DIM) for t in range(10)], 1) == 10
        for e in range(40):  # 200 steps, ~1.6 MB: past capacity_mb
            _insert(svc, episode("short", f"S{e}", 5, terminated=True, dim=DIM), 11 + 5 * e)
        tail = [make_step("long", "L", t, dim=DIM, terminated=t == 14) for t in range(10, 15)]
        assert _insert(svc, tail, 211) == 5
        st = stub(svc).Stats(replay_pb2.StatsRequest(), timeout=10)
        assert st.evicted_episodes > 0
        assert "long" not in st.evicted_steps_per_robot and st.steps_per_robot["long"] == 15
        assert _indices(svc.store, "long", "L") == list(range(15))
        # every transition of L can be drawn, 9 -> 10 included (it was lost)
        batch = svc.store.sample(4096, np.random.default_rng(0), robot_ids=["long"])
        t = batch["observation"]["state"][:, 0].astype(int)
        assert set(t) == set(range(15))
        np.testing.assert_array_equal(batch["next_observation"]["state"][:, 0], t + 1)
    finally:
        svc.stop()


def test_over_capacity_with_only_open_episodes_evicts_nothing_until_they_end(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Above capacity with only episodes still being written: none is cut (warned once, gauge 1); once they
    end, the oldest goes whole and the gauge is 0 again."""
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        with caplog.at_level(logging.WARNING, logger="services.replay.store"):
            for t in range(90):  # two robots, one open episode each, ~1.4 MB together
                store.put_steps([make_step(r, "open", t, dim=DIM) for r in ("arm-0", "arm-1")])
        assert store.stats()["episodes"] == 2 and store.stats()["steps"] == 180
        assert store.cache_info()["evicted_episodes"] == 0
        assert _over_capacity() == 1
        assert sum("only episodes still being written" in r.getMessage() for r in caplog.records) == 1
        store.put_steps([make_step("arm-0", "open", 90, dim=DIM, last=True)])  # arm-0's ends: it may go now
        assert store.cache_info()["evicted_episodes"] == 1 and _indices(store, "arm-1", "open") == list(range(90))
        assert _episodes(store) == {("arm-1", "open")} and _over_capacity() == 0
    finally:
        store.close()


def test_steps_of_an_evicted_episode_are_refused(tmp_path: Path) -> None:
    """An open episode its robot abandoned (it started a later one) may be evicted; a step of it that comes later
    is refused (answered as a duplicate) instead of being stored as an episode without a start."""
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        store.put_steps([make_step("arm-0", "left", t, dim=DIM) for t in range(10)])  # never ended
        for e in range(8):  # the same robot goes on with new episodes: "left" is abandoned, then evicted
            store.put_steps(episode("arm-0", f"e{e}", 20, dim=DIM))
        assert ("arm-0", "left") not in _episodes(store)
        assert store.put_steps([make_step("arm-0", "left", 10, dim=DIM, last=True)]) == (0, 1)
        assert store.put_steps([make_step("arm-0", "left", 3, dim=DIM), *episode("arm-0", "e8", 2, dim=DIM)]) == (
            2,
            1,
        )
        assert ("arm-0", "left") not in _episodes(store) and _indices(store, "arm-0", "e8") == [0, 1]
        assert _indices(store, "arm-0", "left") == []  # nothing of it in LMDB (its eviction committed with e8)
    finally:
        store.close()


# ---------------------------------------------------------------------- 2: attach

OWNER = """
import sys
from services.replay.store import ReplayStore, hold_buffer
fd = hold_buffer(sys.argv[1], "the replay service")
store = ReplayStore(sys.argv[1], 64)
print("ready", flush=True)
sys.stdin.read()
store.close()
"""


def _old_buffer(path: Path) -> None:
    svc = _service(path)
    try:
        _insert(svc, episode("arm-0", "o1", 5, dim=DIM), 1)
    finally:
        svc.stop()


def _files(path: Path) -> dict[str, tuple[int, int]]:
    return {f: (os.stat(path / f).st_mtime_ns, os.stat(path / f).st_size) for f in sorted(os.listdir(path))}


def test_attach_refuses_a_buffer_its_owner_still_runs_on(tmp_path: Path) -> None:
    """Another process writing the buffer (and evicting) would leave the attached index pointing at steps gone:
    every Sample of that table ABORTED. Attach refuses it, naming the setting and the holder."""
    _old_buffer(tmp_path / "old")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    owner = subprocess.Popen(
        [sys.executable, "-c", OWNER, str(tmp_path / "old")], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env
    )
    try:
        assert owner.stdout is not None and owner.stdout.readline().strip() == b"ready"
        held = rf"replay\.attach\.prior: .* held by the replay service \(pid {owner.pid}\)"
        with pytest.raises(ConfigError, match=held):
            _service(tmp_path / "new", attach={"prior": tmp_path / "old"})
    finally:
        owner.communicate(b"", timeout=60)
    svc = _service(tmp_path / "new", attach={"prior": tmp_path / "old"})  # once it stopped: fine
    svc.stop()


def test_an_attached_buffer_is_left_untouched_and_its_owner_waits(tmp_path: Path) -> None:
    """Attaching creates nothing in the buffer (no lock.mdb in a copy of data.mdb alone), and while it is attached
    its owner refuses to start, saying why; after the attacher stops the owner starts."""
    _old_buffer(tmp_path / "old")
    for name in ("lock.mdb", "holder.lock"):
        (tmp_path / "old" / name).unlink()  # a copy of data.mdb alone (rsync)
    before = _files(tmp_path / "old")
    svc = _service(tmp_path / "new", attach={"prior": tmp_path / "old"})
    try:
        batch = stub(svc).Sample(replay_pb2.SampleRequest(batch_size=8, tables={"prior": 1}), timeout=30)
        assert batch.table_transitions["prior"] == 5
        assert _files(tmp_path / "old") == before
    finally:
        svc.stop()
    assert _files(tmp_path / "old") == before
    # a buffer with its holder.lock: the attacher keeps the owner out
    _old_buffer(tmp_path / "old2")
    svc = _service(tmp_path / "new2", attach={"prior": tmp_path / "old2"})
    try:
        with pytest.raises(ConfigError, match=r"replay\.path: .* attached it read-only \(replay\.attach\)"):
            _service(tmp_path / "old2")
    finally:
        svc.stop()
    _service(tmp_path / "old2").stop()


# ---------------------------------------------------------------------- 3: spool drops


def test_spool_drops_count_only_steps_replay_never_got(tmp_path: Path) -> None:
    """drop_oldest while replay holds every step uncommitted: each dropped step was already sent, replay stores and
    acks all of them, so none is lost (before: every drop counted, 200 of 300 while replay stored 300)."""
    n = 300
    svc = _service(tmp_path / "replay", commit_max_steps=n, commit_max_delay_ms=600_000.0)  # acks once all came
    spool = LmdbSpool(tmp_path / "spool", max_bytes=100 * 8100, policy="drop_oldest")
    sender = ReplaySender(svc.address, AUTH, outbox=spool)
    try:
        for t in range(n):
            sender.send(make_step("arm-0", "E", t, dim=DIM, last=t == n - 1))
            wait_for(lambda t=t: sender.sent > t, "the sender sent the step")  # so every drop is of a sent step
        assert wait_for(lambda: sender.flush(1.0), "every kept step acknowledged")
        stored = stub(svc).Stats(replay_pb2.StatsRequest(), timeout=10).steps
        assert stored == n and sender.dropped == 0
    finally:
        sender.close()
        svc.stop()


def test_spool_counts_unsent_and_never_acked_drops_and_logs_their_range(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A step dropped before it was sent is lost at once; one sent is lost only if its stream ends without its ack.
    Lost steps are logged per episode with their step range; the count survives a reopen."""
    size = make_step("arm-0", "E", 0, dim=DIM).ByteSize()
    spool = LmdbSpool(tmp_path / "spool", max_bytes=4 * size + size // 2, policy="drop_oldest")
    with caplog.at_level(logging.WARNING, logger="edge_agent.spool"):
        for t in range(10):  # nothing read: steps 0-5 (seqs 1-6) go unsent
            spool.put(make_step("arm-0", "E", t, dim=DIM))
        assert spool.dropped == 6
        assert [r.seq for r in spool.read(0, 100)] == [7, 8, 9, 10]  # sent on a stream
        for t in range(10, 12):  # drops seqs 7 and 8, in flight: not lost yet
            spool.put(make_step("arm-0", "E", t, dim=DIM))
        assert spool.dropped == 6
        spool.ack([7])  # replay stored 7 after all
        assert spool.dropped == 6
        spool.read(0, 100)  # a new stream: 8 was never acked
        assert spool.dropped == 7
        spool.close()
    # one line per burst and episode (the first burst may be logged apart if a second passed before the next put)
    lines = [r.fields for r in caplog.records if "never acknowledged" in r.getMessage()]
    assert 1 <= len(lines) <= 2 and sum(f["count"] for f in lines) == 7
    assert {(f["robot_id"], f["episode_id"]) for f in lines} == {("arm-0", "E")}
    assert lines[0]["steps"].startswith("0-") and lines[-1]["steps"].endswith("-7")
    again = LmdbSpool(tmp_path / "spool", max_bytes=4 * size + size // 2, policy="drop_oldest")
    try:
        assert again.dropped == 7
    finally:
        again.close()
