"""Steps and specs for replay tests: a 6-float "state" and a 3-d action."""

from __future__ import annotations

import numpy as np

from user import wire
from user.v1 import robot_pb2, step_pb2, tensor_pb2

OBS_DIM = 6


def spec(robot_id: str = "arm-0") -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="test",
        action=robot_pb2.ActionSpace(shape=[3], low=[-1] * 3, high=[1] * 3, dtype=tensor_pb2.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[OBS_DIM])],
        control_rate_hz=20,
        max_episode_steps=50,
    )


def obs(value: float) -> dict[str, np.ndarray]:
    return {"state": np.full(OBS_DIM, value, dtype=np.float32)}


def make_step(
    robot_id: str, episode: str, index: int, last: bool = False, terminated: bool = False, **kw
) -> step_pb2.Step:
    fields = {
        "observation": wire.to_tensor_map(obs(float(index))),
        "action": wire.to_tensor(np.full(3, 0.1 * (index % 10), dtype=np.float32)),
        "reward": -float(index),
        "policy_version": 7,
        **kw,
    }
    step = step_pb2.Step(
        robot_id=robot_id,
        episode_id=episode,
        step_index=index,
        terminated=terminated,
        truncated=last and not terminated,
        **fields,
    )
    if last or terminated:
        step.final_observation.CopyFrom(wire.to_tensor_map(obs(float(index + 1))))
    return step


def episode(robot_id: str, name: str, length: int, terminated: bool = False) -> list[step_pb2.Step]:
    return [
        make_step(robot_id, name, i, last=i == length - 1, terminated=terminated and i == length - 1)
        for i in range(length)
    ]
