"""A step must match the spec its robot registered; anything else is rejected before storage.

validate_step raises StepError (a user.wire.WireError) whose message names the field and whose
`reason` is a short label for the rejected-steps metric.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from user import wire
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

# The edge clips every action; beyond float noise an out-of-range action is a bug upstream.
ACTION_ATOL = 1e-4
ACTION_RTOL = 1e-6
MAX_EPISODE_ID_BYTES = 256  # keys stay well under LMDB's 511-byte limit
MAX_ROBOT_ID_BYTES = 128
# Indices and versions travel as uint64 but are stored and sampled as int64 (and key+1 must not wrap).
MAX_INT64 = (1 << 63) - 1


class StepError(wire.WireError):
    """A step that breaks its robot's contract (-> INVALID_ARGUMENT)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _check_id(field: str, value: str, limit: int) -> None:
    if not value:
        raise StepError(field, f"{field} is empty")
    if "/" in value or "\0" in value:
        raise StepError(field, f"{field} {value!r} must not contain '/' or NUL")
    if len(value.encode()) > limit:
        raise StepError(field, f"{field} is longer than {limit} bytes")


def _decode(where: str, tensor: tpb.Tensor) -> np.ndarray:
    try:
        return wire.from_tensor(tensor)  # checks the byte count against dtype x shape
    except wire.WireError as exc:
        raise StepError("decode", f"{where}: {exc}") from None


def check_tensor_map(where: str, tmap: tpb.TensorMap, features: list[robot_pb2.FeatureSpec]) -> None:
    """Same names as the spec, and per feature the declared dtype, shape and finiteness."""
    given = set(tmap.tensors)
    wanted = {f.name for f in features}
    if given != wanted:
        missing, extra = sorted(wanted - given), sorted(given - wanted)
        raise StepError(
            "keys", f"{where}: keys {sorted(given)} do not match the spec (missing {missing}, extra {extra})"
        )
    for feat in features:
        tensor = tmap.tensors[feat.name]
        name = f"{where}[{feat.name!r}]"
        if tensor.dtype != feat.dtype:
            raise StepError(
                "dtype",
                f"{name}: dtype {_dtype_name(tensor.dtype)}, spec says {_dtype_name(feat.dtype)}",
            )
        if tuple(tensor.shape) != tuple(feat.shape):
            raise StepError("shape", f"{name}: shape {list(tensor.shape)}, spec says {list(feat.shape)}")
        array = _decode(name, tensor)
        if not feat.allow_nan and array.dtype.kind == "f" and not np.isfinite(array).all():
            raise StepError("non_finite", f"{name}: NaN or Inf where the spec does not allow it")


def _dtype_name(code: int) -> str:
    return wire.dtype_name(code) if code in tpb.DType.values() else str(code)


class _ActionCheck:
    """What one spec implies for actions, computed once per spec instead of once per step."""

    def __init__(self, spec: robot_pb2.RobotSpec) -> None:
        act = spec.action
        self.dtype = act.dtype or tpb.DTYPE_FLOAT32
        self.shape = tuple(act.shape)
        size = math.prod(self.shape) if self.shape else 0
        self.bounded = len(act.low) == size and len(act.high) == size
        self.low = np.asarray(act.low, np.float64)
        self.high = np.asarray(act.high, np.float64)
        self.low_limit = self.low - (ACTION_ATOL + ACTION_RTOL * np.abs(self.low))
        self.high_limit = self.high + (ACTION_ATOL + ACTION_RTOL * np.abs(self.high))

    def __call__(self, tensor: tpb.Tensor) -> None:
        if tensor.dtype != self.dtype:
            raise StepError("dtype", f"action: dtype {_dtype_name(tensor.dtype)}, spec says {_dtype_name(self.dtype)}")
        if tuple(tensor.shape) != self.shape:
            raise StepError("shape", f"action: shape {list(tensor.shape)}, spec says {list(self.shape)}")
        values = _decode("action", tensor).reshape(-1)
        if not np.isfinite(values).all():
            raise StepError("non_finite", "action: NaN or Inf")
        if self.bounded and ((values < self.low_limit).any() or (values > self.high_limit).any()):
            i = int(np.flatnonzero((values < self.low_limit) | (values > self.high_limit))[0])
            raise StepError(
                "action_bounds",
                f"action[{i}] = {values[i]:.6g} is outside [{self.low[i]:.6g}, {self.high[i]:.6g}] "
                "(the edge must clip)",
            )


# Compiled checks keyed by the serialized action space (~0.5 us), so a spec edited in place is recompiled.
_COMPILED: dict[bytes, _ActionCheck] = {}
_COMPILED_MAX = 256


def _action_check(spec: robot_pb2.RobotSpec) -> _ActionCheck:
    key = spec.action.SerializeToString()
    check = _COMPILED.get(key)
    if check is None:
        if len(_COMPILED) >= _COMPILED_MAX:
            _COMPILED.clear()
        check = _COMPILED[key] = _ActionCheck(spec)
    return check


def validate_step(step: step_pb2.Step, spec: robot_pb2.RobotSpec) -> None:
    """Raise StepError naming the first thing in `step` that does not match `spec`."""
    _check_id("robot_id", step.robot_id, MAX_ROBOT_ID_BYTES)
    if step.robot_id != spec.robot_id:
        raise StepError("robot_id", f"robot_id {step.robot_id!r} does not match the spec's {spec.robot_id!r}")
    _check_id("episode_id", step.episode_id, MAX_EPISODE_ID_BYTES)
    if step.step_index >= MAX_INT64:
        raise StepError("step_index", f"step_index {step.step_index} must be below 2**63 - 1")
    if step.policy_version > MAX_INT64:
        raise StepError("policy_version", f"policy_version {step.policy_version} must fit in int64")
    check_tensor_map("observation", step.observation, list(spec.observation))
    _action_check(spec)(step.action)
    if not math.isfinite(step.reward):
        raise StepError("non_finite", "reward: NaN or Inf")
    last = step.terminated or step.truncated
    has_final = step.HasField("final_observation")
    if last and not has_final:
        raise StepError("final_observation", "final_observation is required on the last step (terminated or truncated)")
    if has_final:
        if not last:
            raise StepError(
                "final_observation",
                "final_observation is set only on the last step of an episode (terminated or truncated)",
            )
        check_tensor_map("final_observation", step.final_observation, list(spec.observation))


class EpisodeGuard:
    """Episode semantics across steps: an episode is steps 0..last, and only its last step ends it.

    A step after the episode's last step, a second different last step, or a last step below a step
    already seen is rejected. Re-sent steps (same index) pass, so a reconnecting edge is never refused.
    Remembers the most recent `capacity` episodes (in RAM; after a restart the store's dedup still holds).
    """

    def __init__(self, capacity: int = 100_000) -> None:
        self.capacity = capacity
        self._lock = threading.Lock()
        self._episodes: OrderedDict[tuple[str, str], tuple[int, int | None]] = OrderedDict()  # -> (max index, last)

    def check(self, step: step_pb2.Step) -> None:
        """Raise StepError if `step` breaks its episode; otherwise remember it."""
        key, index = (step.robot_id, step.episode_id), step.step_index
        ends = step.terminated or step.truncated
        with self._lock:
            highest, last = self._episodes.get(key, (index, None))
            if last is not None and index > last:
                raise StepError("episode_order", f"step {index} comes after the episode's last step {last}")
            if ends and last is not None and index != last:
                raise StepError("episode_order", f"step {index} ends an episode that already ended at step {last}")
            if ends and highest > index:
                raise StepError("episode_order", f"step {index} cannot end the episode: step {highest} was seen")
            self._episodes[key] = (max(highest, index), index if ends else last)
            self._episodes.move_to_end(key)
            if len(self._episodes) > self.capacity:
                self._episodes.popitem(last=False)
