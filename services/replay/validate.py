"""A step must match the spec its robot registered; anything else is rejected before storage."""

from __future__ import annotations

import numpy as np

from user import wire
from user.v1 import robot_pb2, step_pb2, tensor_pb2

ACTION_TOLERANCE = 1e-4  # the edge clips; beyond float noise an out-of-range action is a bug


def _check_features(where: str, tmap: tensor_pb2.TensorMap, spec: robot_pb2.RobotSpec) -> None:
    expected = {f.name: f for f in spec.observation}
    given = set(tmap.tensors)
    if given != set(expected):
        raise wire.WireError(f"{where}: features {sorted(given)} do not match the spec's {sorted(expected)}")
    for name, feature in expected.items():
        tensor = tmap.tensors[name]
        if tensor.dtype != feature.dtype:
            raise wire.WireError(
                f"{where}.{name}: dtype {wire.dtype_name(tensor.dtype)}, spec says {wire.dtype_name(feature.dtype)}"
            )
        if tuple(tensor.shape) != tuple(feature.shape):
            raise wire.WireError(f"{where}.{name}: shape {tuple(tensor.shape)}, spec says {tuple(feature.shape)}")
        array = wire.from_tensor(tensor)  # checks the byte count against dtype x shape
        if not feature.allow_nan and array.dtype.kind == "f" and not np.isfinite(array).all():
            raise wire.WireError(f"{where}.{name}: NaN or Inf where the spec does not allow it")


def validate_step(step: step_pb2.Step, spec: robot_pb2.RobotSpec) -> None:
    """Raise WireError naming the first thing that does not match `spec`."""
    if not step.robot_id or step.robot_id != spec.robot_id:
        raise wire.WireError(f"robot_id {step.robot_id!r} does not match spec {spec.robot_id!r}")
    if not step.episode_id or "/" in step.episode_id or "\0" in step.episode_id or len(step.episode_id) > 128:
        raise wire.WireError(f"episode_id {step.episode_id!r} must be 1-128 chars without '/' or NUL")
    _check_features("observation", step.observation, spec)
    if step.action.dtype != tensor_pb2.DTYPE_FLOAT32:
        raise wire.WireError(f"action: dtype {wire.dtype_name(step.action.dtype)}, expected float32")
    if tuple(step.action.shape) != tuple(spec.action.shape):
        raise wire.WireError(f"action: shape {tuple(step.action.shape)}, spec says {tuple(spec.action.shape)}")
    action = wire.from_tensor(step.action).reshape(-1)
    if not np.isfinite(action).all():
        raise wire.WireError("action: NaN or Inf")
    low = np.asarray(spec.action.low, dtype=np.float32)
    high = np.asarray(spec.action.high, dtype=np.float32)
    if low.size == action.size and (
        np.any(action < low - ACTION_TOLERANCE) or np.any(action > high + ACTION_TOLERANCE)
    ):
        raise wire.WireError("action: outside the declared limits (the edge must clip)")
    if not np.isfinite(step.reward):
        raise wire.WireError("reward: NaN or Inf")
    last = step.terminated or step.truncated
    if last and not step.final_observation.tensors:
        raise wire.WireError("final_observation is required on the last step (terminated or truncated)")
    if step.final_observation.tensors:
        if not last:
            raise wire.WireError("final_observation is only allowed on the last step of an episode")
        _check_features("final_observation", step.final_observation, spec)
