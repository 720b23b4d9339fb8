"""The simulated reach arm: spec, safety clipping, reachability, determinism, holding still."""

from __future__ import annotations

import numpy as np

from edge_agent.robot import make_robot
from user.v1 import tensor_pb2


def _scripted(obs_state: np.ndarray) -> np.ndarray:
    delta = obs_state[6:9]  # target - ee
    return (delta / max(float(np.linalg.norm(delta)), 1e-6)).astype(np.float32)


def test_spec_and_observation_match() -> None:
    robot = make_robot("sim_reach_arm", "arm-7", seed=3)
    try:
        spec = robot.spec
        assert spec.robot_id == "arm-7" and spec.kind == "sim_reach_arm"
        assert list(spec.action.shape) == [3]
        assert list(spec.action.low) == [-1.0] * 3 and list(spec.action.high) == [1.0] * 3
        assert spec.control_rate_hz == 20.0 and spec.max_episode_steps == 50 and spec.task
        (feature,) = spec.observation
        assert feature.name == "state" and feature.dtype == tensor_pb2.DTYPE_FLOAT32 and not feature.allow_nan
        obs = robot.reset()
        state = obs.features["state"]
        assert state.dtype == np.float32 and list(state.shape) == list(feature.shape)
        assert np.all(np.isfinite(state)) and not obs.terminated and obs.reward == 0.0
    finally:
        robot.close()


def test_out_of_range_and_nan_actions_are_clipped() -> None:
    robot = make_robot("sim_reach_arm", "a", seed=0)
    robot.reset()
    applied = robot.act(np.array([5.0, -7.0, 0.5]))
    np.testing.assert_array_equal(applied, np.array([1.0, -1.0, 0.5], np.float32))
    applied = robot.act(np.array([np.nan, np.inf, -np.inf]))
    np.testing.assert_array_equal(applied, np.zeros(3, np.float32))
    assert np.all(np.isfinite(robot.observe().features["state"]))
    # Joint limits hold even when pushed hard in one direction for a long time.
    for _ in range(200):
        robot.act(np.array([0.0, 0.0, 1.0]))
    low, high = robot.model.jnt_range[:, 0], robot.model.jnt_range[:, 1]
    assert np.all(robot.data.qpos >= low - 0.05) and np.all(robot.data.qpos <= high + 0.05)


def test_scripted_reach_succeeds() -> None:
    robot = make_robot("sim_reach_arm", "a", seed=1)
    successes = []
    for _ in range(10):
        obs = robot.reset()
        start = robot.distance()
        for _ in range(robot.spec.max_episode_steps):
            robot.act(_scripted(obs.features["state"]))
            obs = robot.observe()
            if obs.terminated:
                break
        successes.append(obs.success)
        assert obs.success == obs.terminated
        if obs.success:
            assert obs.info["distance"] < 0.02 < start
            assert obs.reward > 0
    assert all(successes)


def test_same_seed_same_episodes() -> None:
    def rollout(seed: int) -> np.ndarray:
        robot = make_robot("sim_reach_arm", "a", seed=seed)
        actions = np.random.default_rng(0).uniform(-1, 1, size=(20, 3))
        states = [robot.reset().features["state"]]
        for a in actions:
            robot.act(a)
            states.append(robot.observe().features["state"])
        states.append(robot.reset().features["state"])
        return np.stack(states)

    np.testing.assert_array_equal(rollout(5), rollout(5))
    assert not np.allclose(rollout(5), rollout(6))


def test_reset_seed_overrides_and_targets_vary() -> None:
    robot = make_robot("sim_reach_arm", "a", seed=0)
    t1 = robot.reset(seed=42).features["state"]
    t2 = robot.reset(seed=42).features["state"]
    np.testing.assert_array_equal(t1, t2)
    targets = np.stack([robot.reset().features["state"][3:6] for _ in range(20)])
    assert np.all(targets[:, 0] > 0.0)  # in front of the arm
    assert np.all(targets[:, 2] > 0.0)  # above the floor
    assert targets.std(axis=0).min() > 0.01


def test_hold_keeps_end_effector_still() -> None:
    robot = make_robot("sim_reach_arm", "a", seed=2)
    robot.reset()
    start = robot.ee_pos()
    for _ in range(10):
        robot.hold()
    assert np.linalg.norm(robot.ee_pos() - start) < 1e-3
    for _ in range(5):
        robot.act(np.array([1.0, 0.0, 0.0]))  # moving at full speed: 15 mm per period
    moving = robot.ee_pos()
    robot.hold()
    assert np.linalg.norm(robot.ee_pos() - moving) < 5e-3  # stops within a few millimetres
    robot.hold()
    settled = robot.ee_pos()
    for _ in range(10):
        robot.hold()
    assert np.linalg.norm(robot.ee_pos() - settled) < 1e-3
    assert robot.observe().reward == 0.0


def test_camera_feature() -> None:
    robot = make_robot("sim_reach_arm", "cam", {"camera": True}, seed=0)
    try:
        names = [f.name for f in robot.spec.observation]
        assert names == ["state", "camera.front"]
        image = robot.reset().features["camera.front"]
        assert image.dtype == np.uint8 and image.shape == (64, 64, 3)
        assert image.std() > 0  # rendered something, not a blank frame
        assert robot.spec.cameras[0].name == "front"
    finally:
        robot.close()
