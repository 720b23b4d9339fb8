"""user/spec.py: the one RobotSpec contract (spec, actions, observations, steps)."""

from __future__ import annotations

import numpy as np
import pytest

from user import spec as contract
from user import wire
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb


def arm() -> robot_pb2.RobotSpec:
    s = robot_pb2.RobotSpec(robot_id="arm-0", kind="sim_reach_arm", control_rate_hz=20)
    s.action.shape.append(3)
    s.action.low.extend([-1.0, -2.0, 0.0])
    s.action.high.extend([1.0, 2.0, 0.5])
    s.observation.add(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[4])
    s.observation.add(name="cam", dtype=tpb.DTYPE_UINT8, shape=[2, 2, 3], is_image=True)
    return s


def test_validate_spec_names_the_field() -> None:
    contract.validate_spec(arm())
    bad = arm()
    bad.action.low.append(0.0)
    with pytest.raises(contract.SpecError, match=r"action\.low/high need 3 values"):
        contract.validate_spec(bad)
    bad = arm()
    bad.observation.add(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[1])
    with pytest.raises(contract.SpecError, match="unique"):
        contract.validate_spec(bad)
    with pytest.raises(contract.SpecError, match="robot_id"):
        contract.validate_spec(robot_pb2.RobotSpec(robot_id="a/b"))
    for shape in ([1 << 40], [1] * 9, [16384, 16384, 3]):  # never sendable: too many bytes or dims
        bad = arm()
        bad.observation.add(name="huge", dtype=tpb.DTYPE_UINT8, shape=shape)
        with pytest.raises(contract.SpecError, match=r"'huge'.*could never be sent"):
            contract.validate_spec(bad)


def test_actions_are_clipped_and_non_finite_becomes_hold() -> None:
    spec = arm()
    out = contract.clip_action(spec, np.array([5.0, np.nan, -3.0]))
    np.testing.assert_array_equal(out, np.array([1.0, 0.0, 0.0], np.float32))
    np.testing.assert_array_equal(contract.hold_action(spec), np.zeros(3, np.float32))
    assert contract.action_dim(spec) == 3


def test_layout_and_observation_checks() -> None:
    spec = arm()
    feats = contract.features(spec)
    assert feats["state"] == contract.FeatureInfo((4,), "float32", False)
    assert feats["cam"] == contract.FeatureInfo((2, 2, 3), "uint8", True)
    good = {"state": np.zeros(4, np.float32), "cam": np.zeros((2, 2, 3), np.uint8)}
    contract.check_observation("obs", good, spec.observation)
    with pytest.raises(contract.StepError, match="dtype"):
        contract.check_observation("obs", {**good, "cam": np.zeros((2, 2, 3), np.float32)}, spec.observation)
    with pytest.raises(contract.StepError, match="NaN"):
        contract.check_observation("obs", {**good, "state": np.full(4, np.nan, np.float32)}, spec.observation)
    with pytest.raises(contract.StepError, match="missing"):
        contract.check_observation("obs", {"state": good["state"]}, spec.observation)


def test_validate_step() -> None:
    spec = arm()
    obs = wire.to_tensor_map({"state": np.zeros(4, np.float32), "cam": np.zeros((2, 2, 3), np.uint8)})
    step = step_pb2.Step(
        robot_id="arm-0", episode_id="e1", observation=obs, action=wire.to_tensor(np.zeros(3, np.float32))
    )
    contract.validate_step(step, spec)
    step.action.CopyFrom(wire.to_tensor(np.array([0.0, 3.0, 0.0], np.float32)))
    with pytest.raises(contract.StepError, match="outside") as err:
        contract.validate_step(step, spec)
    assert err.value.reason == "action_bounds"
