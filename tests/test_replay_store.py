"""ReplayStore on a real LMDB in tmp_path, and validate_step."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from services.replay.store import (
    EmptyBufferError,
    LayoutError,
    ReplayError,
    ReplayFullError,
    ReplayStore,
    StoreClosedError,
)
from services.replay.validate import StepError, validate_step
from user import wire
from user.spec import step_check
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

OBS_DIM = 6


def spec(robot_id: str = "arm-0", obs_dim: int = OBS_DIM) -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="test",
        action=robot_pb2.ActionSpace(shape=[3], low=[-1] * 3, high=[1] * 3, dtype=tpb.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[obs_dim])],
        control_rate_hz=20,
        max_episode_steps=50,
    )


def obs(value: float, dim: int = OBS_DIM) -> tpb.TensorMap:
    return wire.to_tensor_map({"state": np.full(dim, value, dtype=np.float32)})


def make_step(
    robot_id: str, episode: str, t: int, *, last: bool = False, terminated: bool = False, dim: int = OBS_DIM, **kw
) -> step_pb2.Step:
    """Observation of step t is t everywhere; the final observation is t + 1."""
    step = step_pb2.Step(
        robot_id=robot_id,
        episode_id=episode,
        step_index=t,
        observation=obs(t, dim),
        action=wire.to_tensor(np.full(3, 0.1 * (t % 10), dtype=np.float32)),
        reward=-float(t),
        terminated=terminated,
        truncated=last and not terminated,
        **{"policy_version": 7, **kw},
    )
    if last or terminated:
        step.final_observation.CopyFrom(obs(t + 1, dim))
    return step


def episode(robot_id: str, name: str, length: int, terminated: bool = False, **kw) -> list[step_pb2.Step]:
    end = length - 1
    return [
        make_step(robot_id, name, t, last=t == end, terminated=terminated and t == end, **kw) for t in range(length)
    ]


@pytest.fixture
def store(tmp_path: Path):
    s = ReplayStore(tmp_path / "replay", 64)
    yield s
    s.close()


def test_sample_shapes_and_next_observation(store: ReplayStore) -> None:
    assert store.put_steps(episode("arm-0", "e1", 5, terminated=True) + episode("arm-0", "e2", 4)) == (9, 0)
    assert store.transitions == 9
    batch = store.sample(512, np.random.default_rng(0))
    state, nxt = batch["observation"]["state"], batch["next_observation"]["state"]
    assert state.shape == nxt.shape == (512, OBS_DIM) and state.dtype == np.float32
    # next_observation is step t+1's observation, or the last step's final_observation
    np.testing.assert_array_equal(nxt, state + 1)
    assert batch["action"].shape == (512, 3) and batch["action"].dtype == np.float32
    np.testing.assert_allclose(batch["action"][:, 0], 0.1 * state[:, 0], rtol=1e-6)
    assert batch["reward"].dtype == np.float32
    np.testing.assert_array_equal(batch["reward"], -state[:, 0])
    assert batch["policy_version"].dtype == np.int64 and (batch["policy_version"] == 7).all()
    for flag in ("terminated", "truncated", "intervention"):
        assert batch[flag].shape == (512,) and batch[flag].dtype == bool
    # e1 ends terminated at t=4, e2 ends truncated at t=3; both kinds of last step were drawn
    assert batch["terminated"].sum() > 0 and batch["truncated"].sum() > 0
    assert not (batch["terminated"] & batch["truncated"]).any()
    assert set(state[batch["terminated"], 0]) == {4.0}
    assert set(state[batch["truncated"], 0]) == {3.0}
    assert not batch["intervention"].any()
    assert store.cache_info()["hits"] > 0  # 512 draws from 9 transitions: decoded once each


def test_open_tail_waits_for_its_successor(store: ReplayStore) -> None:
    store.put_steps([make_step("arm-0", "e", 0), make_step("arm-0", "e", 1)])
    assert store.transitions == 1  # step 1 has no next observation yet
    with pytest.raises(EmptyBufferError):
        store.sample(1, np.random.default_rng(0), robot_ids=["arm-1"])
    store.put_steps([make_step("arm-0", "e", 2, last=True)])
    assert store.transitions == 3


def test_interleaved_robots_complete_their_transitions_in_the_hot_tier(store: ReplayStore) -> None:
    """An edge streams its robots' steps in turn (arm-0 t, arm-1 t, ..., arm-0 t+1): a step's successor in the
    same commit is not its neighbour. Each transition must still be completed in that commit, in RAM: before,
    most steps stayed waiting as tails (memory up to MAX_OPEN_TAILS) and their transitions were read back from
    LMDB, outside the hot tier."""
    robots = [f"arm-{i}" for i in range(4)]
    episodes = [episode(r, "e", 12) for r in robots]
    rng = np.random.default_rng(0)
    t = 0
    while t < 12:  # groups of 1-5 ticks, every robot's step of a tick in turn
        k = int(rng.integers(1, 6))
        store.put_steps([ep[i] for i in range(t, min(12, t + k)) for ep in episodes])
        t += k
        assert len(store._tails) <= len(robots)  # at most each robot's newest step waits
    assert store.transitions == 48
    assert store.cache_info()["entries"] == 48  # every transition hot
    batch = store.sample(256, np.random.default_rng(1))
    np.testing.assert_array_equal(batch["next_observation"]["state"], batch["observation"]["state"] + 1)
    assert store.cache_info()["misses"] == 0


def test_whole_episodes_out_of_key_order_in_one_commit(store: ReplayStore) -> None:
    """Each episode's steps in one run but the runs not in key order (robot z before robot a): committed without a
    sort, every transition completed and hot."""
    assert store.put_steps(episode("arm-z", "e", 6) + episode("arm-a", "e", 5) + episode("arm-m", "f", 4)) == (15, 0)
    assert store.transitions == 15 and store.cache_info()["entries"] == 15 and not store._tails
    batch = store.sample(64, np.random.default_rng(0))
    np.testing.assert_array_equal(batch["next_observation"]["state"], batch["observation"]["state"] + 1)
    assert store.cache_info()["misses"] == 0


def test_resent_steps_are_stored_once(store: ReplayStore) -> None:
    steps = episode("arm-0", "e", 6)
    assert store.put_steps(steps[:4]) == (4, 0)
    before = store.stats()["bytes_on_disk"]
    assert store.put_steps(steps) == (2, 4)
    assert store.put_steps([steps[0], steps[0]]) == (0, 2)
    st = store.stats()
    assert (st["steps"], st["transitions"], st["episodes"], st["duplicates"]) == (6, 6, 1, 6)
    assert st["steps_per_robot"] == {"arm-0": 6}
    assert st["bytes_on_disk"] >= before


def test_out_of_order_arrival(store: ReplayStore) -> None:
    steps = episode("arm-0", "e", 8, terminated=True)
    store.put_steps([steps[5], steps[7], steps[3]])  # 7 is last: sampleable alone
    assert store.transitions == 1
    store.put_steps([steps[6], steps[4]])  # completes 3->4, 4->5, 5->6, 6->7
    assert store.transitions == 5
    store.put_steps(list(reversed(steps[:3])))  # one transaction, reversed
    assert store.transitions == 8
    batch = store.sample(256, np.random.default_rng(3))
    np.testing.assert_array_equal(batch["next_observation"]["state"], batch["observation"]["state"] + 1)
    assert sorted(set(batch["observation"]["state"][:, 0])) == list(range(8))


def test_reopen_rebuilds_the_index(tmp_path: Path) -> None:
    path = tmp_path / "replay"
    store = ReplayStore(path, 64)
    store.put_steps(episode("arm-0", "a", 4) + episode("arm-1", "b", 3, terminated=True, policy_version=2))
    store.put_steps([make_step("arm-1", "c", 0), make_step("arm-0", "a", 0)])  # open tail + a duplicate
    store.put_spec(spec("arm-0"))
    before = store.stats()
    assert before["transitions"] == 7 and before["episodes"] == 3 and before["duplicates"] == 1
    store.close()
    store.close()  # idempotent
    with pytest.raises(StoreClosedError):
        store.sample(1, np.random.default_rng(0))

    again = ReplayStore(path, 64)
    try:
        assert again.stats() == before
        assert again.get_spec("arm-0") == spec("arm-0") and again.get_spec("arm-9") is None
        batch = again.sample(64, np.random.default_rng(1), robot_ids=["arm-1"])
        assert (batch["policy_version"] == 2).all()  # only arm-1's transitions
        np.testing.assert_array_equal(batch["next_observation"]["state"], batch["observation"]["state"] + 1)
        again.put_steps([make_step("arm-1", "c", 1, last=True)])  # the open tail completes after the restart
        assert again.transitions == 9
    finally:
        again.close()


def test_sampling_is_uniform_over_transitions_across_robots(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "a", 30, policy_version=1) + episode("arm-1", "b", 10, policy_version=2))
    versions = store.sample(20_000, np.random.default_rng(0))["policy_version"]
    share = float((versions == 1).mean())
    assert 0.72 < share < 0.78  # 30 of 40 transitions; ~0.003 standard deviation
    assert store.transitions_for(["arm-1"]) == 10 and store.transitions_for(["arm-1", "nobody"]) == 10


def test_robots_with_different_layouts_are_sampled_separately(store: ReplayStore) -> None:
    store.put_steps(episode("arm-0", "a", 3) + episode("big-0", "b", 3, dim=9))
    with pytest.raises(LayoutError, match="robot_ids"):
        for seed in range(20):
            store.sample(16, np.random.default_rng(seed))
    assert store.sample(16, np.random.default_rng(0), robot_ids=["big-0"])["observation"]["state"].shape == (16, 9)


def test_a_cold_layout_mismatch_names_the_odd_step_and_the_feature(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "replay", 64, cache_mb=0)  # no hot tier: every draw is read from LMDB
    try:
        store.put_steps(episode("arm-0", "a", 3) + episode("big-0", "b", 3, dim=9))
        with pytest.raises(LayoutError) as raised:
            for seed in range(20):
                store.sample(16, np.random.default_rng(seed))
    finally:
        store.close()
    found = re.search(
        r"step (\d) of robot '(\S+)' episode '(\w)' has feature 'state' float32 \((\d),\), "
        r"step \d of robot '(\S+)' episode '\w' float32 \((\d),\)",
        str(raised.value),
    )
    assert found is not None, str(raised.value)
    odd_robot, odd_episode, odd_dim, first_robot, first_dim = found[2], found[3], found[4], found[5], found[6]
    dims = {"arm-0": "6", "big-0": "9"}
    assert odd_robot != first_robot and dims[odd_robot] == odd_dim and dims[first_robot] == first_dim
    assert odd_episode == {"arm-0": "a", "big-0": "b"}[odd_robot]


def test_a_full_map_stores_nothing_of_the_batch(tmp_path: Path) -> None:
    store = ReplayStore(tmp_path / "tiny", 1)
    try:
        big = [make_step("arm-0", "e", t, dim=20_000) for t in range(30)]  # ~80 KB each, 2.4 MB > 1 MiB map
        with pytest.raises(ReplayFullError, match="max_map_mb"):
            store.put_steps(big)
        st = store.stats()
        assert st["steps"] == 0 and st["transitions"] == 0
        assert store.put_steps(big[:2]) == (2, 0)  # the store still works
    finally:
        store.close()


def test_a_store_of_another_format_is_refused(tmp_path: Path) -> None:
    import lmdb

    env = lmdb.open(str(tmp_path / "old"), max_dbs=4)
    with env.begin(write=True, db=env.open_db(b"steps")) as txn:
        txn.put(b"arm-0/e/" + bytes(8), b"\x00" + make_step("arm-0", "e", 0).SerializeToString())
    env.close()
    with pytest.raises(ReplayError, match="older replay format"):
        ReplayStore(tmp_path / "old", 64)


# --------------------------------------------------------------------------- validation


def _set_obs(step: step_pb2.Step, array: np.ndarray) -> None:
    step.observation.tensors["state"].CopyFrom(wire.to_tensor(array))


@pytest.mark.parametrize(
    "mutate, reason, message",
    [
        (lambda s: _set_obs(s, np.zeros(5, np.float32)), "shape", "shape"),
        (lambda s: _set_obs(s, np.zeros(6, np.float64)), "dtype", "float64"),
        (lambda s: _set_obs(s, np.full(6, np.nan, np.float32)), "non_finite", "NaN"),
        (lambda s: _set_obs(s, np.array([0, 0, np.inf, 0, 0, 0], np.float32)), "non_finite", "Inf"),
        (lambda s: s.observation.tensors["state"].__setattr__("data", b"\0" * 8), "decode", "bytes"),
        (lambda s: s.observation.tensors["extra"].CopyFrom(wire.to_tensor(np.zeros(1))), "keys", "extra"),
        (lambda s: s.observation.tensors.pop("state"), "keys", "missing"),
        (lambda s: s.action.CopyFrom(wire.to_tensor(np.zeros(3, np.float64))), "dtype", "action"),
        (lambda s: s.action.CopyFrom(wire.to_tensor(np.zeros(4, np.float32))), "shape", "action"),
        (lambda s: s.action.CopyFrom(wire.to_tensor(np.array([0, np.nan, 0], np.float32))), "non_finite", "action"),
        (lambda s: s.action.CopyFrom(wire.to_tensor(np.array([0, 1.01, 0], np.float32))), "action_bounds", "clip"),
        (lambda s: setattr(s, "reward", float("nan")), "non_finite", "reward"),
        (lambda s: setattr(s, "terminated", True), "final_observation", "required"),
        (lambda s: s.final_observation.CopyFrom(obs(1)), "final_observation", "only on the last step"),
        (lambda s: setattr(s, "episode_id", "a/b"), "episode_id", "'/'"),
        (lambda s: setattr(s, "episode_id", "a\0b"), "episode_id", "NUL"),
        (lambda s: setattr(s, "episode_id", ""), "episode_id", "empty"),
        (lambda s: setattr(s, "robot_id", ""), "robot_id", "empty"),
        (lambda s: setattr(s, "robot_id", "arm-1"), "robot_id", "arm-1"),
    ],
)
def test_validation_names_what_does_not_match(mutate, reason: str, message: str) -> None:
    step = make_step("arm-0", "e", 0)
    validate_step(step, spec())
    assert step_check(spec()).passes(step, images_checked=False)  # the compiled fast path says yes to it...
    mutate(step)
    assert not step_check(spec()).passes(step, images_checked=False)  # ...and never to a step the full check refuses
    with pytest.raises(StepError, match=message) as err:
        validate_step(step, spec())
    assert err.value.reason == reason
    assert isinstance(err.value, wire.WireError)


def test_validation_accepts_edges_of_the_contract() -> None:
    last = make_step("arm-0", "e", 9, last=True)
    validate_step(last, spec())
    last.final_observation.tensors["state"].CopyFrom(wire.to_tensor(np.full(6, 2.0, np.float32)))
    validate_step(last, spec())
    step = make_step("arm-0", "e", 0)
    step.action.CopyFrom(wire.to_tensor(np.array([1.00001, -1.00001, 0], np.float32)))  # float noise past the bound
    validate_step(step, spec())
    nan_ok = spec()
    nan_ok.observation[0].allow_nan = True
    _set_obs(step, np.full(6, np.nan, np.float32))
    validate_step(step, nan_ok)


def _resident(arr: np.ndarray) -> float:
    """Share of the array's pages in RAM (mincore(2)): what prefaulting maps, whatever the rest of the process does
    meanwhile (its RSS also moves when the kernel reclaims other pages, e.g. DAMON's kdamond)."""
    import ctypes
    import os

    page = os.sysconf("SC_PAGE_SIZE")
    addr = arr.__array_interface__["data"][0]
    start = addr - addr % page
    length = addr + arr.nbytes - start
    pages = -(-length // page)
    vec = (ctypes.c_ubyte * pages)()
    if ctypes.CDLL(None, use_errno=True).mincore(ctypes.c_void_p(start), ctypes.c_size_t(length), vec) != 0:
        raise OSError(ctypes.get_errno(), "mincore")
    return sum(v & 1 for v in vec) / pages


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs Linux /proc")
def test_hot_group_prefault_maps_its_columns_up_front() -> None:
    """replay.cache_prefault: the RAM tier's columns cost their RSS when the layout arrives, not over hours.
    Run in a fresh interpreter: in this long-lived one, malloc may hand np.empty pages earlier tests touched."""
    import subprocess
    import sys

    code = "from tests.test_replay_store import prefault_check; prefault_check()"
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


def prefault_check() -> None:
    from services.replay.hot import HotGroup

    layout = ((("state", np.dtype(np.float32), (64,)),), (np.dtype(np.float32), (8,)))
    group = HotGroup(layout, 96 << 20)
    columns = [*group.frames.values(), group.action, group.t_rows]
    assert _resident(group.frames["state"]) < 0.2  # np.empty: not mapped until written
    group.prefault()
    for column in columns:
        assert _resident(column) >= 0.8
    seq = group.write_frame({"state": np.ones(64, np.float32)})  # still a working ring afterwards
    assert group.frames["state"][seq % group.frame_capacity].sum() == 64
