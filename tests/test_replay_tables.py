"""Tables, samplers, n-step, hot/cold tiers, eviction and map growth of ReplayStore on a real LMDB."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.replay.store import EmptyBufferError, ReplayStore
from services.replay.tables import Draw
from tests.test_replay_store import OBS_DIM, episode, make_step


@pytest.fixture
def store(tmp_path: Path):
    s = ReplayStore(tmp_path / "replay", 64)
    yield s
    s.close()


def draw(n: int, **kw) -> Draw:
    return Draw(batch_size=n, **kw)


def test_tables_and_exact_mixing_ratios(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "on", 40, policy_version=1))
    store.put_steps(episode("arm-0", "demo", 10, policy_version=2), table="demos")
    assert store.tables() == ["demos", "online"]
    assert store.transitions == 50
    assert store.transitions_for(tables=["demos"]) == 10
    for n in (256, 7):
        batch = store.sample(n, np.random.default_rng(n), draw=draw(n, tables={"online": 1, "demos": 1}))
        versions = batch["policy_version"]
        counts = sorted([int((versions == 1).sum()), int((versions == 2).sum())])
        assert counts == [n // 2, n - n // 2]  # 50/50 exactly, not binomial
    quarter = store.sample(400, np.random.default_rng(0), draw=draw(400, tables={"online": 3, "demos": 1}))
    assert (quarter["policy_version"] == 2).sum() == 100
    with pytest.raises(EmptyBufferError, match="'nothing'"):
        store.sample(8, np.random.default_rng(0), draw=draw(8, tables={"online": 1, "nothing": 1}))


def test_intervention_steps_are_also_in_the_interventions_table(store: ReplayStore) -> None:
    steps = episode("arm-0", "e", 10)
    for s in steps[3:6]:
        s.intervention = True
    store.put_steps(steps)
    assert store.transitions_for(tables=["online"]) == 10
    assert store.transitions_for(tables=["interventions"]) == 3
    batch = store.sample(64, np.random.default_rng(0), draw=draw(64, tables={"interventions": 1}))
    assert batch["intervention"].all() and set(batch["observation"]["state"][:, 0]) == {3.0, 4.0, 5.0}
    stats = store.table_stats()
    assert stats["interventions"]["transitions"] == 3 and stats["interventions"]["episodes"] == 1


def test_interventions_table_stats_count_the_episodes_a_human_stepped_into(tmp_path: Path) -> None:
    """Per robot rows add up to the table's; success is the episode's outcome, as the online table counts it."""
    path = tmp_path / "replay"
    store = ReplayStore(path, 64)
    try:
        rescued = episode("arm-0", "rescued", 6, terminated=True)  # a human took over at step 2, and it succeeded
        for s in rescued[2:4]:
            s.intervention = True
        rescued[-1].success = True
        failed = episode("arm-1", "failed", 4)  # a human stepped in once; the episode still failed
        failed[1].intervention = True
        alone = episode("arm-0", "alone", 5, terminated=True)  # no human step: not in "interventions"
        alone[-1].success = True
        store.put_steps(rescued + failed + alone)
        teleop = episode("arm-0", "teleop", 3, terminated=True, intervention=True)  # inserted there whole
        teleop[-1].success = True
        store.put_steps(teleop, table="interventions")
        before = store.table_stats()
    finally:
        store.close()
    again = ReplayStore(path, 64)  # the index rebuilt from LMDB counts the same
    try:
        assert again.table_stats() == before
    finally:
        again.close()
    human = before["interventions"]
    assert (human["episodes"], human["successes"], human["steps"], human["transitions"]) == (3, 2, 6, 6)
    assert human["success_rate"] == 2 / 3 and human["bytes"] == before["interventions"]["robots"]["arm-0"]["bytes"]
    robots = human["robots"]
    assert {r: (v["episodes"], v["successes"], v["steps"]) for r, v in robots.items()} == {
        "arm-0": (2, 2, 5),
        "arm-1": (1, 0, 1),
    }
    for key in ("episodes", "successes", "steps", "transitions", "bytes"):
        assert sum(r[key] for r in robots.values()) == human[key], key
    online = before["online"]
    assert (online["episodes"], online["successes"], online["steps"]) == (3, 2, 15)


def test_tables_survive_reopen_in_arrival_order(tmp_path: Path) -> None:
    path = tmp_path / "replay"
    store = ReplayStore(path, 64)
    store.put_steps(episode("arm-0", "z-old", 5))
    store.put_steps(episode("arm-0", "a-new", 5, policy_version=9), table="demos")
    store.close()
    again = ReplayStore(path, 64)
    try:
        assert again.transitions_for(tables=["demos"]) == 5 and again.transitions_for(tables=["online"]) == 5
        # recency follows arrival, not key order: the newest 5 are episode a-new
        batch = again.sample(64, np.random.default_rng(0), draw=draw(64, sampler="recency", window=5))
        assert (batch["policy_version"] == 9).all()
        assert again.cache_info()["hits"] == 64  # the newest transitions were read back into RAM at open
    finally:
        again.close()


def test_recency_window_draws_only_the_newest(store: ReplayStore) -> None:
    for e in range(5):
        store.put_steps(episode("arm-0", f"e{e}", 10, policy_version=e))
    batch = store.sample(500, np.random.default_rng(0), draw=draw(500, sampler="recency", window=10))
    assert set(batch["policy_version"]) == {4}


def test_prioritized_sampling_follows_priorities(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "e", 20))
    first = store.sample(64, np.random.default_rng(0), draw=draw(64, sampler="prioritized"))
    assert (first["weights"] == 1).all()  # new transitions get the max priority: uniform at first
    tids = np.arange(20)
    priorities = np.where(tids == 7, 100.0, 0.0)
    assert store.update_priorities(tids, priorities) == 20
    batch = store.sample(256, np.random.default_rng(1), draw=draw(256, sampler="prioritized", alpha=1.0))
    assert set(batch["indices"]) == {7} and set(batch["observation"]["state"][:, 0]) == {7.0}
    assert store.update_priorities(np.array([999]), np.array([1.0])) == 0  # unknown ids are skipped


def test_importance_weights_are_normalised(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "e", 10))
    store.update_priorities(np.arange(10), np.array([1.0] * 9 + [9.0]))
    batch = store.sample(2000, np.random.default_rng(2), draw=draw(2000, sampler="prioritized", alpha=1.0, beta=1.0))
    w, ids = batch["weights"], batch["indices"]
    assert w.max() == pytest.approx(1.0)
    assert w[ids == 9].max() == pytest.approx(1 / 9, rel=1e-5)  # (N P)^-beta / max


def test_n_step_returns(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "e", 6, terminated=True))  # rewards -t, observations t, final 6
    batch = store.sample(512, np.random.default_rng(0), draw=draw(512, n_step=3, gamma=0.5))
    t = batch["observation"]["state"][:, 0].astype(int)
    n = np.minimum(3, 6 - t)
    np.testing.assert_array_equal(batch["n_steps"], n)
    expected = [sum(-(t0 + k) * 0.5**k for k in range(k_n)) for t0, k_n in zip(t, n, strict=True)]
    np.testing.assert_allclose(batch["reward"], expected, rtol=1e-6)
    np.testing.assert_array_equal(batch["next_observation"]["state"][:, 0], t + n)
    np.testing.assert_array_equal(batch["terminated"], t + n == 6)


def test_cold_reads_equal_hot_reads(tmp_path: Path) -> None:
    """A hot tier far smaller than the buffer: misses read LMDB and give the same transitions."""
    small = ReplayStore(tmp_path / "small", 64, cache_mb=0)
    small.hot_bytes = 64 * (OBS_DIM * 4 + 40)  # 64 rows of frames and transitions
    big = ReplayStore(tmp_path / "big", 64)
    try:
        for e in range(10):
            steps = episode("arm-0", f"e{e}", 30, policy_version=e)
            small.put_steps(steps)
            big.put_steps(steps)
        assert small.cache_info()["entries"] < small.transitions == big.transitions == 300
        a = small.sample(256, np.random.default_rng(5))
        b = big.sample(256, np.random.default_rng(5))
        for key in ("reward", "terminated", "truncated", "policy_version", "action", "indices"):
            np.testing.assert_array_equal(a[key], b[key])
        np.testing.assert_array_equal(a["observation"]["state"], b["observation"]["state"])
        np.testing.assert_array_equal(a["next_observation"]["state"], b["next_observation"]["state"])
        assert small.cache_info()["misses"] > 0 and big.cache_info()["misses"] == 0
        recent = small.sample(64, np.random.default_rng(1), draw=draw(64, sampler="recency", window=30))
        np.testing.assert_array_equal(recent["next_observation"]["state"], recent["observation"]["state"] + 1)
        assert small.cache_info()["hits"] >= 64  # the freshness window is served from RAM
    finally:
        small.close()
        big.close()


def test_all_hot_batches_equal_lmdb_reads_and_own_their_columns(tmp_path: Path) -> None:
    """The all-hot gather (obs and next frames in one take, validity from the ring's records) gives what LMDB
    gives, one-step and n-step, and a batch's columns do not alias each other or the ring."""
    hot = ReplayStore(tmp_path / "hot", 64)
    cold = ReplayStore(tmp_path / "cold", 64, cache_mb=0)  # no hot tier: every draw read from LMDB
    try:
        for e in range(4):
            steps = episode("arm-0", f"e{e}", 20, policy_version=e, terminated=e % 2 == 0)
            hot.put_steps(steps)
            cold.put_steps(steps)
        for n_step in (1, 3):
            req = {"draw": draw(128, n_step=n_step, gamma=0.5)} if n_step > 1 else {}
            before = hot.cache_info()["hits"]
            a = hot.sample(128, np.random.default_rng(n_step), **req)
            b = cold.sample(128, np.random.default_rng(n_step), **req)
            assert hot.cache_info()["hits"] - before == 128 and hot.cache_info()["misses"] == 0
            for key in ("reward", "terminated", "truncated", "policy_version", "action", "indices", "n_steps"):
                np.testing.assert_array_equal(a[key], b[key])
            for part in ("observation", "next_observation"):
                np.testing.assert_array_equal(a[part]["state"], b[part]["state"])
            next_before = a["next_observation"]["state"].copy()
            a["observation"]["state"][:] = -1  # a learner may normalise in place
            a["action"][:] = -1
            np.testing.assert_array_equal(a["next_observation"]["state"], next_before)
            again = hot.sample(128, np.random.default_rng(n_step), **req)
            np.testing.assert_array_equal(again["observation"]["state"], b["observation"]["state"])
            np.testing.assert_array_equal(again["action"], b["action"])
    finally:
        hot.close()
        cold.close()


def test_capacity_evicts_whole_episodes_oldest_first(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        for e in range(12):  # ~8 KB per step x 20 steps = ~160 KB per episode, 12 episodes > 1 MiB
            store.put_steps(episode("arm-0", f"e{e:02d}", 20, dim=2000, policy_version=e))
        info = store.cache_info()
        assert info["evicted_episodes"] > 0 and info["stored_bytes"] <= 1 << 20
        st = store.stats()
        assert st["episodes"] == 12 - info["evicted_episodes"] and st["transitions"] == 20 * st["episodes"]
        versions = set(store.sample(2000, np.random.default_rng(0))["policy_version"])
        assert versions == set(range(info["evicted_episodes"], 12))  # the oldest left, whole
    finally:
        store.close()
    again = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        assert again.stats()["episodes"] == st["episodes"]  # evicted from LMDB too
    finally:
        again.close()


def test_the_map_grows_instead_of_failing(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "grow", 1, max_map_mb=16)
    try:
        big = [make_step("arm-0", "e", t, dim=20_000, last=t == 29) for t in range(30)]  # 2.4 MB > 1 MiB
        assert store.put_steps(big) == (30, 0)
        assert store.db.map_bytes > 1 << 20
        assert store.sample(4, np.random.default_rng(0))["observation"]["state"].shape == (4, 20_000)
    finally:
        store.close()


def _camera_episode(n: int) -> list:
    """Smooth 64x64 frames (a moving gradient, like a camera sees) with the test's state layout."""
    from user import wire

    yy, xx = np.mgrid[0:64, 0:64]
    steps = episode("arm-0", "cam", n)
    for t, s in enumerate(steps):
        img = (xx * 2 + yy + 4 * t).astype(np.uint8)  # at most 233: no wrap-around edges
        frame = np.stack([img, img[::-1], 255 - img], axis=-1)
        s.observation.tensors["camera.front"].CopyFrom(wire.to_tensor(frame))
        if s.HasField("final_observation"):
            s.final_observation.tensors["camera.front"].CopyFrom(wire.to_tensor(frame))
    return steps


@pytest.mark.parametrize(("encoding", "max_mean_abs_error"), [("png", 0.0), ("jpeg", 4.0)])
def test_camera_frames_round_trip_through_lmdb(tmp_path: Path, encoding: str, max_mean_abs_error: float) -> None:
    """Frames stored JPEG/PNG in LMDB and decoded by the sampler: PNG exact, JPEG within 4/255 mean abs error."""
    from user import wire

    steps = _camera_episode(12)
    originals = {s.step_index: wire.from_tensor(s.observation.tensors["camera.front"]) for s in steps}
    raw = ReplayStore(tmp_path / "raw", 64, cache_mb=0)
    enc = ReplayStore(tmp_path / encoding, 64, cache_mb=0, image_encoding={"*": encoding})
    try:
        raw.put_steps(steps)
        enc.put_steps(steps)
        assert steps[0].observation.tensors["camera.front"].encoding == 0  # the caller's steps are untouched
        assert enc.stats()["bytes_on_disk"] < raw.stats()["bytes_on_disk"]
        batch = enc.sample(64, np.random.default_rng(0))  # no hot tier: every frame decoded from LMDB
        frames = batch["observation"]["camera.front"]
        assert frames.dtype == np.uint8 and frames.shape == (64, 64, 64, 3)
        for t, frame in zip(batch["observation"]["state"][:, 0].astype(int), frames, strict=True):
            err = np.abs(frame.astype(np.int16) - originals[t].astype(np.int16)).mean()
            assert err <= max_mean_abs_error
    finally:
        raw.close()
        enc.close()


def test_a_previous_buffer_is_sampled_read_only_as_a_table(tmp_path: Path) -> None:
    old = ReplayStore(tmp_path / "old", 64)
    old.put_steps(episode("arm-0", "e0", 10, policy_version=5))  # same robot and episode ids as below
    old.put_steps(episode("arm-0", "d0", 4, policy_version=6), table="demos")
    before = old.stats()
    old.close()
    store = ReplayStore(tmp_path / "new", 64)
    try:
        store.put_steps(episode("arm-0", "e0", 6, policy_version=1))
        assert store.attach(tmp_path / "old", "prior") == 14
        with pytest.raises(ValueError, match="exists"):
            store.attach(tmp_path / "old", "online")
        batch = store.sample(
            256, np.random.default_rng(0), draw=draw(256, tables={"online": 1, "prior": 1}, n_step=2, gamma=1.0)
        )
        versions = batch["policy_version"]
        assert (versions == 1).sum() == 128 and set(versions[versions != 1]) == {5, 6}
        first = batch["observation"]["state"][:, 0]
        np.testing.assert_array_equal(batch["next_observation"]["state"][:, 0], first + batch["n_steps"])
        assert store.table_stats()["prior"]["episodes"] == 2 and store.stats()["steps"] == 6  # not ours to count
        legacy = store.sample(64, np.random.default_rng(1))  # no tables named: this buffer's own only
        assert set(legacy["policy_version"]) == {1}
    finally:
        store.close()
    again = ReplayStore(tmp_path / "old", 64)
    try:
        assert again.stats() == before  # untouched
    finally:
        again.close()


def test_frame_stacking(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "e", 6, terminated=True))  # observations t, final 6
    batch = store.sample(256, np.random.default_rng(0), draw=draw(256, frame_stack=3, n_step=2, gamma=1.0))
    obs, nxt = batch["observation"]["state"], batch["next_observation"]["state"]
    assert obs.shape == (256, 3, OBS_DIM) and nxt.shape == (256, 3, OBS_DIM)
    t = obs[:, -1, 0].astype(int)
    np.testing.assert_array_equal(obs[:, :, 0], np.maximum(0, t[:, None] + np.array([-2, -1, 0])))
    end = t + batch["n_steps"]
    np.testing.assert_array_equal(nxt[:, -1, 0], end)
    # the next stack is the stack the policy would see at t + n: the episode's first observation repeats
    np.testing.assert_array_equal(nxt[:, :, 0], np.maximum(0, end[:, None] + np.array([-2, -1, 0])))


def test_a_restart_warms_the_hot_tier_with_the_newest(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "replay", 64)
    for e in range(10):
        store.put_steps(episode("arm-0", f"e{e}", 30, policy_version=e))
    store.close()
    again = ReplayStore(tmp_path / "replay", 64, cache_mb=0)
    again.hot_bytes = 100 * (OBS_DIM * 4 * 9 // 8 + 12 + 24)  # room for ~100 transitions
    again._warm()
    try:
        info = again.cache_info()
        assert 0 < info["entries"] < 300
        recent = again.sample(256, np.random.default_rng(0), draw=draw(256, sampler="recency", window=60))
        assert again.cache_info()["misses"] == 0 and set(recent["policy_version"]) == {8, 9}
        np.testing.assert_array_equal(recent["next_observation"]["state"], recent["observation"]["state"] + 1)
        old = again.sample(256, np.random.default_rng(1))  # uniform: old ones come from LMDB, same values
        np.testing.assert_array_equal(old["next_observation"]["state"], old["observation"]["state"] + 1)
        assert again.cache_info()["misses"] > 0
    finally:
        again.close()


def test_an_evicted_open_episode_that_goes_on_is_not_sampled_from_nothing(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        store.put_steps([make_step("arm-0", "open", t, dim=2000) for t in range(10)])  # no end yet
        for e in range(8):  # push it out
            store.put_steps(episode("arm-0", f"e{e}", 20, dim=2000))
        assert "open" not in {k.split(b"/")[1].decode() for k in store._episodes}
        store.put_steps([make_step("arm-0", "open", 10, dim=2000, last=True)])  # the robot goes on
        for seed in range(5):
            batch = store.sample(256, np.random.default_rng(seed))
            np.testing.assert_array_equal(batch["next_observation"]["state"], batch["observation"]["state"] + 1)
    finally:
        store.close()


def test_a_robot_whose_layout_changes_gets_a_new_hot_group(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "a", 5))
    store.put_steps(episode("arm-0", "b", 5, dim=9))  # re-registered with another observation size
    first = store.sample(8, np.random.default_rng(0), draw=draw(8, tables={"online": 1}, sampler="recency", window=5))
    assert first["observation"]["state"].shape == (8, 9)  # the newest 5 are episode b
    assert store.cache_info()["misses"] == 0


def test_prioritized_draws_are_proportional_to_the_sum_tree(store: ReplayStore) -> None:
    """Draw frequencies follow p^alpha (chi-square-like bound); updates land in O(log n) sum-tree leaves."""
    store.put_steps(episode("arm-0", "a", 40))
    store.put_steps(episode("arm-1", "b", 24))  # two robots: two trees, shares by their totals
    n = store.transitions
    rng = np.random.default_rng(3)
    pri = rng.uniform(0.0, 4.0, n)
    pri[5] = 0.0  # never drawn
    assert store.update_priorities(np.arange(n), pri) == n
    for alpha in (1.0, 0.5):
        k = 40_000
        got = store.sample(k, np.random.default_rng(4), draw=draw(k, sampler="prioritized", alpha=alpha))["indices"]
        counts = np.bincount(got, minlength=n)
        expect = pri**alpha / (pri**alpha).sum() * k
        assert counts[5] == 0
        assert np.abs(counts - expect).max() < 5 * np.sqrt(expect.max()) + 5
    # an update after the trees exist moves the draws: only tid 9 left with mass
    store.update_priorities(np.arange(n), np.where(np.arange(n) == 9, 2.0, 0.0))
    got = store.sample(500, np.random.default_rng(5), draw=draw(500, sampler="prioritized", alpha=0.5))["indices"]
    assert set(got.tolist()) == {9}
    # new transitions enter with the max priority seen (4.0 here) and are drawn
    store.put_steps(episode("arm-0", "c", 10))
    got = store.sample(2000, np.random.default_rng(6), draw=draw(2000, sampler="prioritized", alpha=1.0))["indices"]
    assert set(got.tolist()) <= {9, *range(n, n + 10)} and len(set(got.tolist())) == 11
    one = store.sample(256, np.random.default_rng(7), draw=draw(256, sampler="prioritized", robot_ids=["arm-1"]))
    assert set(one["indices"].tolist()) <= set(range(40, 64))


@pytest.mark.parametrize("encoding", ["jpeg", "png"])
def test_the_decoded_window_serves_the_newest_frames_like_lmdb(tmp_path: Path, encoding: str) -> None:
    """decoded_mb keeps the newest encoded frames as uint8 once sampled: later batches take them from there (no
    decode), equal frame for frame to LMDB reads, also after newer frames pushed older ones out of the window."""
    hot = ReplayStore(tmp_path / "hot", 64, image_encoding={"*": encoding}, decoded_mb=1)  # 85 frames of 64x64x3
    cold = ReplayStore(tmp_path / "cold", 64, cache_mb=0, image_encoding={"*": encoding})
    try:
        for n, (first, second) in enumerate([(_camera_episode(120), None), (_camera_episode(60), "cam2")]):
            if second:
                for s in first:
                    s.episode_id = second
            for s in (hot, cold):
                s.put_steps(first)
            for seed in range(3):
                a = hot.sample(64, np.random.default_rng(10 * n + seed))
                b = cold.sample(64, np.random.default_rng(10 * n + seed))
                np.testing.assert_array_equal(a["indices"], b["indices"])
                for part in ("observation", "next_observation"):
                    np.testing.assert_array_equal(a[part]["camera.front"], b[part]["camera.front"])
            group = hot._groups[0]
            assert group.decoded_capacity == (1 << 20) // (64 * 64 * 3) < group.frames_written
            kept = group.decoded_tag["camera.front"]
            assert kept.max() == group.frames_written - 1  # the newest frames are kept decoded
        assert hot.cache_info()["decoded_hits"] > 0
        assert group.decoded_bytes == np.count_nonzero(kept >= 0) * 64 * 64 * 3 <= (1 << 20)  # bounded
    finally:
        hot.close()
        cold.close()


@pytest.mark.parametrize("encoding", ["jpeg", "png"])
def test_the_hot_tier_keeps_encoded_frames_and_decodes_them_like_lmdb(tmp_path: Path, encoding: str) -> None:
    """With image_encoding the hot tier holds the stored JPEG/PNG bytes (far less RAM than raw frames) and the
    sampler decodes them: a hot batch equals the same batch read from LMDB (cache off), frame for frame."""
    steps = _camera_episode(40)
    raw = ReplayStore(tmp_path / "raw", 64)
    hot = ReplayStore(tmp_path / "hot", 64, image_encoding={"*": encoding})
    cold = ReplayStore(tmp_path / "cold", 64, cache_mb=0, image_encoding={"*": encoding})
    try:
        for s in (raw, hot, cold):
            s.put_steps(steps)
        assert hot.cache_info()["entries"] == 40
        assert hot.cache_info()["bytes"] < raw.cache_info()["bytes"] / 3  # smooth camera-like frames compress
        a = hot.sample(64, np.random.default_rng(0))
        b = cold.sample(64, np.random.default_rng(0))
        assert hot.cache_info()["hits"] == 64 and cold.cache_info()["misses"] == 64
        np.testing.assert_array_equal(a["indices"], b["indices"])
        for part in ("observation", "next_observation"):
            for name in a[part]:
                np.testing.assert_array_equal(a[part][name], b[part][name])
    finally:
        for s in (raw, hot, cold):
            s.close()
