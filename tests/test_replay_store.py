from __future__ import annotations

import numpy as np
import pytest

from services.replay.store import EmptyBufferError, ReplayStore
from services.replay.validate import validate_step
from tests.replay_helpers import episode, make_step, spec
from user import wire


def test_next_observation_comes_from_the_next_step_or_final_observation(tmp_path):
    store = ReplayStore(tmp_path, 64)
    store.put_steps(episode("arm-0", "e1", 5, terminated=True))
    assert store.transitions == 5
    batch = store.sample(512, np.random.default_rng(0))
    state, nxt = batch["observation"]["state"][:, 0], batch["next_observation"]["state"][:, 0]
    np.testing.assert_array_equal(nxt, state + 1)  # obs of step t is t, next is t+1 (final obs on the last)
    assert (batch["terminated"] == (state == 4)).all()
    assert batch["action"].shape == (512, 3) and batch["policy_version"].dtype == np.int64
    store.close()


def test_open_episode_tail_is_not_sampleable_until_its_successor_arrives(tmp_path):
    store = ReplayStore(tmp_path, 64)
    store.put_steps([make_step("arm-0", "e", 0), make_step("arm-0", "e", 1)])
    assert store.transitions == 1  # step 1 has no next observation yet
    store.put_steps([make_step("arm-0", "e", 2, last=True)])
    assert store.transitions == 3
    store.close()


def test_resent_steps_are_stored_once_and_out_of_order_arrival_is_handled(tmp_path):
    store = ReplayStore(tmp_path, 64)
    steps = episode("arm-0", "e", 6)
    assert store.put_steps([steps[3], steps[5], steps[4]]) == (3, 0)
    assert store.put_steps(steps) == (3, 3)
    st = store.stats()
    assert st["steps"] == 6 and st["transitions"] == 6 and st["duplicates"] == 3
    assert st["steps_per_robot"] == {"arm-0": 6} and st["episodes"] == 1
    store.close()


def test_reopen_rebuilds_the_index(tmp_path):
    store = ReplayStore(tmp_path, 64)
    store.put_steps(episode("arm-0", "a", 4) + episode("arm-1", "b", 3, terminated=True) + [make_step("arm-1", "c", 0)])
    store.put_spec(spec("arm-0"))
    before = store.stats()
    store.close()
    again = ReplayStore(tmp_path, 64)
    assert again.stats() == {**before, "duplicates": 0}
    assert again.get_spec("arm-0") == spec("arm-0")
    batch = again.sample(64, np.random.default_rng(1), robot_ids=["arm-1"])
    assert batch["observation"]["state"].shape == (64, 6)
    with pytest.raises(EmptyBufferError):
        again.sample(4, np.random.default_rng(1), robot_ids=["nobody"])
    again.close()


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda s: s.observation.tensors["state"].shape.__setitem__(0, 5), "shape"),
        (lambda s: s.observation.tensors["state"].CopyFrom(wire.to_tensor(np.full(6, np.nan, np.float32))), "NaN"),
        (lambda s: s.action.CopyFrom(wire.to_tensor(np.zeros(3, np.float64))), "dtype"),
        (lambda s: s.action.CopyFrom(wire.to_tensor(np.full(3, 5.0, np.float32))), "limits"),
        (lambda s: setattr(s, "terminated", True), "final_observation"),
        (lambda s: setattr(s, "episode_id", "a/b"), "episode_id"),
        (lambda s: s.observation.tensors["extra"].CopyFrom(wire.to_tensor(np.zeros(1, np.float32))), "features"),
    ],
)
def test_validation_rejects_what_does_not_match_the_spec(mutate, message):
    step = make_step("arm-0", "e", 0)
    validate_step(step, spec())
    mutate(step)
    with pytest.raises(wire.WireError, match=message):
        validate_step(step, spec())
