"""The RobotSpec contract, in one place: every organ checks robots, steps, observations and actions here.

A RobotSpec (user/v1/robot.proto) is what a robot promises: its action space with limits and its
observation features with dtype and shape. Control validates the spec at registration
(`validate_spec`), replay validates each step against it (`validate_step`), the edge clips every
action to it (`clip_action`), inference checks observations (`check_observation`) and the learner
derives its tensor layout from it (`features`, `action_bounds`). Errors name the field.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from user import wire
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

ROBOT_ID_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")  # always fullmatch: `$` would let a trailing newline in
FLOAT_DTYPES = (tpb.DTYPE_UNSPECIFIED, tpb.DTYPE_FLOAT32, tpb.DTYPE_FLOAT64, tpb.DTYPE_FLOAT16)
# The edge clips every action (and holds on a non-finite one); beyond float noise an out-of-range action is a bug
# upstream.
ACTION_ATOL = 1e-4
ACTION_RTOL = 1e-6
MAX_EPISODE_ID_BYTES = 256  # keys stay well under LMDB's 511-byte limit
MAX_ROBOT_ID_BYTES = 128
MAX_FEATURE_RANK = 8  # (H, W, C) images, (T, ...) stacks: far more than any sensor needs
MAX_NAME_BYTES = 256  # kind, feature/camera/action names, label keys and values: bounded in control's memory
MAX_TASK_BYTES = 4096  # RobotSpec.task: a sentence or a paragraph
MAX_FEATURES = 256  # observation features (a step's tensors)
MAX_CAMERAS = 64
MAX_LABELS = 64
IMAGE_CHANNELS = (1, 3, 4)  # grey, RGB, RGBA: what the learner's image encoders take
SHOWN_CHARS = 64  # an error quotes at most this much of a client's string (status details travel in headers)
# Indices and versions travel as uint64 but are stored and sampled as int64 (and key+1 must not wrap).
MAX_INT64 = (1 << 63) - 1


class SpecError(ValueError):
    """A RobotSpec that breaks the contract (-> INVALID_ARGUMENT at registration)."""


class StepError(wire.WireError):
    """A step or observation that breaks its robot's spec; `reason` labels the rejected-steps metric."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------- the spec itself


def clipped(value: str, limit: int = SHOWN_CHARS) -> str:
    """repr of a client's string cut to `limit` chars: an echoed 20 kB value would overflow gRPC's header limit and
    turn the intended status into RESOURCE_EXHAUSTED."""
    return repr(value[:limit]) + (f"... ({len(value)} chars)" if len(value) > limit else "")


def enum_name(enum: Any, value: int) -> str:
    """The enum's name for value, or the number: proto3 enums are open, so any int32 can arrive."""
    return enum.Name(value) if value in enum.values() else str(value)


def validate_spec(spec: robot_pb2.RobotSpec) -> None:
    """Raise SpecError naming the robot and the offending field."""
    rid = spec.robot_id
    if not ROBOT_ID_RE.fullmatch(rid):
        raise SpecError(f"robot_id {clipped(rid)} must match {ROBOT_ID_RE.pattern}")
    where = f"robot {rid}"
    _check_texts(where, spec)
    act = spec.action
    if not act.shape or any(d <= 0 for d in act.shape):
        raise SpecError(f"{where}: action.shape must be non-empty with positive dims, got {list(act.shape)}")
    size = math.prod(act.shape)
    if len(act.low) != size or len(act.high) != size:
        raise SpecError(
            f"{where}: action.low/high need {size} values for shape {list(act.shape)}, "
            f"got {len(act.low)} and {len(act.high)}"
        )
    for i, (lo, hi) in enumerate(zip(act.low, act.high, strict=True)):
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
            raise SpecError(f"{where}: action bound {i} needs finite low <= high, got low={lo} high={hi}")
    if act.names and len(act.names) != size:
        raise SpecError(f"{where}: action.names has {len(act.names)} entries for {size} action elements")
    if act.dtype not in FLOAT_DTYPES:
        raise SpecError(f"{where}: action.dtype must be a float type, got {enum_name(tpb.DType, act.dtype)}")
    validate_features(where, spec.observation)
    if len(spec.cameras) > MAX_CAMERAS:
        raise SpecError(f"{where}: at most {MAX_CAMERAS} cameras, got {len(spec.cameras)}")
    for cam in spec.cameras:
        if not cam.name or cam.width <= 0 or cam.height <= 0:
            raise SpecError(f"{where}: camera {cam.name!r} needs a name and positive width/height")
    if not (math.isfinite(spec.control_rate_hz) and spec.control_rate_hz > 0):
        raise SpecError(f"{where}: control_rate_hz must be > 0, got {spec.control_rate_hz}")


def _check_texts(where: str, spec: robot_pb2.RobotSpec) -> None:
    """Names and labels are kept by control for every robot it ever saw: each one bounded."""
    if len(spec.labels) > MAX_LABELS:
        raise SpecError(f"{where}: at most {MAX_LABELS} labels, got {len(spec.labels)}")
    names = [
        ("kind", spec.kind),
        *((f"labels key {clipped(k)}", k) for k in spec.labels),
        *((f"labels[{clipped(k)}]", v) for k, v in spec.labels.items()),
        *((f"action.names[{i}]", n) for i, n in enumerate(spec.action.names)),
        *((f"observation[{i}].name", f.name) for i, f in enumerate(spec.observation)),
        *((f"cameras[{i}].name", c.name) for i, c in enumerate(spec.cameras)),
    ]
    for field, value in names:
        if len(value.encode()) > MAX_NAME_BYTES:
            raise SpecError(f"{where}: {field} is longer than {MAX_NAME_BYTES} bytes")
    if len(spec.task.encode()) > MAX_TASK_BYTES:
        raise SpecError(f"{where}: task is longer than {MAX_TASK_BYTES} bytes")


def validate_features(where: str, features: Sequence[robot_pb2.FeatureSpec]) -> None:
    if not features:
        raise SpecError(f"{where}: observation needs at least one feature")
    if len(features) > MAX_FEATURES:
        raise SpecError(f"{where}: at most {MAX_FEATURES} observation features, got {len(features)}")
    seen: set[str] = set()
    for feat in features:
        if not feat.name or feat.name in seen:
            raise SpecError(f"{where}: observation feature names must be non-empty and unique, got {feat.name!r}")
        seen.add(feat.name)
        if not feat.shape or any(d <= 0 for d in feat.shape):
            raise SpecError(
                f"{where}: observation {feat.name!r} needs a non-empty shape with positive dims, got {list(feat.shape)}"
            )
        try:
            itemsize = np.dtype(wire.dtype_from_proto(feat.dtype)).itemsize
        except wire.WireError as exc:
            raise SpecError(f"{where}: observation {feat.name!r}: {exc}") from None
        if len(feat.shape) > MAX_FEATURE_RANK or math.prod(feat.shape) * itemsize > wire.MAX_TENSOR_BYTES:
            raise SpecError(
                f"{where}: observation {feat.name!r} of shape {list(feat.shape)} could never be sent "
                f"(at most {MAX_FEATURE_RANK} dims and {wire.MAX_TENSOR_BYTES} bytes a tensor)"
            )
        if feat.is_image:
            _check_image_feature(where, feat)


def _check_image_feature(where: str, feat: robot_pb2.FeatureSpec) -> None:
    """The learner builds image encoders for is_image features: uint8 (H, W) or (H, W, C), as cameras give them."""
    shape = list(feat.shape)
    if (
        feat.dtype != tpb.DTYPE_UINT8
        or len(shape) not in (2, 3)
        or (len(shape) == 3 and shape[2] not in IMAGE_CHANNELS)
    ):
        raise SpecError(
            f"{where}: observation {feat.name!r} has is_image set, so it must be uint8 of shape (H, W) or (H, W, C) "
            f"with C in {list(IMAGE_CHANNELS)}; got {enum_name(tpb.DType, feat.dtype)} {shape}"
        )


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True)
class FeatureInfo:
    shape: tuple[int, ...]
    dtype: str  # numpy dtype name ("float32", "uint8", ...)
    is_image: bool


def features(spec: robot_pb2.RobotSpec) -> dict[str, FeatureInfo]:
    """The observation layout a spec declares: name -> shape, numpy dtype, image or not."""
    return {
        f.name: FeatureInfo(tuple(int(d) for d in f.shape), wire.dtype_from_proto(f.dtype).name, bool(f.is_image))
        for f in spec.observation
    }


def action_dim(spec: robot_pb2.RobotSpec) -> int:
    return int(math.prod(spec.action.shape)) if spec.action.shape else 0


# --------------------------------------------------------------------------- actions


def action_bounds(spec: robot_pb2.RobotSpec) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 arrays shaped like the action."""
    shape = tuple(spec.action.shape)
    low = np.asarray(spec.action.low, dtype=np.float32).reshape(shape)
    high = np.asarray(spec.action.high, dtype=np.float32).reshape(shape)
    return low, high


def clip_action(spec: robot_pb2.RobotSpec, action: np.ndarray) -> np.ndarray:
    """Clip to declared limits. A NaN/Inf element becomes the hold value 0 where 0 is within its limits (velocity
    or delta control: 0 is "stay"); where it is not (a position-controlled joint), no value is a safe stand-in
    (clipping 0 would command a jump to the limit): ValueError. The edge agent never sends a non-finite action to
    a robot (it holds instead), so this only guards plug-ins' own callers."""
    low, high = action_bounds(spec)
    act = np.asarray(action, dtype=np.float32).reshape(low.shape)
    finite = np.isfinite(act)
    if not finite.all():
        if ((low > 0) | (high < 0))[~finite].any():
            raise ValueError(
                f"robot {spec.robot_id}: non-finite action {act.reshape(-1).tolist()} where 0 is outside the "
                "limits: no safe value to substitute (hold the robot instead)"
            )
        act = np.where(finite, act, 0.0)
    return np.clip(act, low, high).astype(np.float32)


def hold_action(spec: robot_pb2.RobotSpec) -> np.ndarray:
    """The action that keeps the robot still: zero, clipped into range."""
    return clip_action(spec, np.zeros(action_bounds(spec)[0].shape, np.float32))


# --------------------------------------------------------------------------- observations and steps


def _dtype_name(code: int) -> str:
    return wire.dtype_name(code) if code in tpb.DType.values() else str(code)


def check_observation(
    where: str, observation: Mapping[str, np.ndarray], spec_features: Sequence[robot_pb2.FeatureSpec]
) -> None:
    """Decoded arrays (no batch dim) against the spec: same names, dtype, shape; finite unless allowed."""
    wanted = {f.name for f in spec_features}
    if set(observation) != wanted:
        missing, extra = sorted(wanted - set(observation)), sorted(set(observation) - wanted)
        raise StepError("keys", f"{where}: keys do not match the spec (missing {missing}, extra {extra})")
    for feat in spec_features:
        arr = np.asarray(observation[feat.name])
        name = f"{where}[{feat.name!r}]"
        want = wire.dtype_from_proto(feat.dtype)
        if arr.dtype != want:
            raise StepError("dtype", f"{name}: dtype {arr.dtype.name}, spec says {want.name}")
        if tuple(arr.shape) != tuple(feat.shape):
            raise StepError("shape", f"{name}: shape {list(arr.shape)}, spec says {list(feat.shape)}")
        if not feat.allow_nan and arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise StepError("non_finite", f"{name}: NaN or Inf where the spec does not allow it")


def check_tensor_map(
    where: str, tmap: tpb.TensorMap, spec_features: Sequence[robot_pb2.FeatureSpec], images_checked: bool = False
) -> None:
    """Wire tensors against the spec (checked before decoding: names, dtype, shape, then finiteness).
    images_checked: every JPEG/PNG tensor of `tmap` already passed wire.check_image (replay checks them in the
    stream's reader thread, in parallel with this)."""
    given = set(tmap.tensors)
    wanted = {f.name for f in spec_features}
    if given != wanted:
        missing, extra = sorted(wanted - given), sorted(given - wanted)
        raise StepError(
            "keys", f"{where}: keys {sorted(given)} do not match the spec (missing {missing}, extra {extra})"
        )
    for feat in spec_features:
        tensor = tmap.tensors[feat.name]
        name = f"{where}[{feat.name!r}]"
        if tensor.dtype != feat.dtype:
            raise StepError("dtype", f"{name}: dtype {_dtype_name(tensor.dtype)}, spec says {_dtype_name(feat.dtype)}")
        if tuple(tensor.shape) != tuple(feat.shape):
            raise StepError("shape", f"{name}: shape {list(tensor.shape)}, spec says {list(feat.shape)}")
        if tensor.encoding in (tpb.ENCODING_JPEG, tpb.ENCODING_PNG):  # uint8: decodable to its shape is enough
            if images_checked:
                continue
            try:
                wire.check_image(tensor)
            except wire.WireError as exc:
                raise StepError("decode", f"{name}: {exc}") from None
            continue
        array = _decode(name, tensor)
        if not feat.allow_nan and array.dtype.kind == "f" and not np.isfinite(array).all():
            raise StepError("non_finite", f"{name}: NaN or Inf where the spec does not allow it")


def _decode(where: str, tensor: tpb.Tensor) -> np.ndarray:
    try:
        return wire.from_tensor(tensor)  # checks the byte count against dtype x shape
    except wire.WireError as exc:
        raise StepError("decode", f"{where}: {exc}") from None


def _check_id(field: str, value: str, limit: int) -> None:
    if not value:
        raise StepError(field, f"{field} is empty")
    if "/" in value or "\0" in value:
        raise StepError(field, f"{field} {clipped(value)} must not contain '/' or NUL")
    if len(value.encode()) > limit:
        raise StepError(field, f"{field} is longer than {limit} bytes")


class ActionCheck:
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
        self.check_values(_decode("action", tensor).reshape(-1))

    def check_values(self, values: np.ndarray) -> None:
        if not np.isfinite(values).all():
            raise StepError("non_finite", "action: NaN or Inf")
        if self.bounded and ((values < self.low_limit).any() or (values > self.high_limit).any()):
            i = int(np.flatnonzero((values < self.low_limit) | (values > self.high_limit))[0])
            raise StepError(
                "action_bounds",
                f"action[{i}] = {values[i]:.6g} is outside [{self.low[i]:.6g}, {self.high[i]:.6g}] "
                "(the edge must clip)",
            )


_COMPILED_MAX = 256  # specs per cache: a fleet's robots, with room to spare


def _compiled(cache: dict[bytes, Any], key: bytes, build: Callable[[], Any]) -> Any:
    """A check compiled once per serialized spec (or action space), so a spec edited in place is recompiled."""
    check = cache.get(key)
    if check is None:
        if len(cache) >= _COMPILED_MAX:
            cache.clear()
        check = cache[key] = build()
    return check


_ACTION_CHECKS: dict[bytes, ActionCheck] = {}


def action_check(spec: robot_pb2.RobotSpec) -> ActionCheck:
    return _compiled(_ACTION_CHECKS, spec.action.SerializeToString(), lambda: ActionCheck(spec))  # ~0.5 us


class StepCheck:
    """What one spec implies for a step, computed once per spec: a fast yes for a step that matches it.

    `passes` answers True only when every check of validate_step holds; anything it does not prove (an odd
    dtype or encoding, a bad value, an error to name) goes to the full check, which raises with the message.
    It checks the same things without the per-step work of the full one (key sets, messages, generic decode):
    ~27 -> ~10 us for a camera step, where the frames are checked apart.
    """

    _RAW_DTYPES = frozenset((tpb.DTYPE_FLOAT32, tpb.DTYPE_FLOAT64, tpb.DTYPE_UINT8, tpb.DTYPE_INT32, tpb.DTYPE_INT64))
    _IMAGE = (tpb.ENCODING_JPEG, tpb.ENCODING_PNG)

    def __init__(self, spec: robot_pb2.RobotSpec) -> None:
        self.robot_id = spec.robot_id
        # (name, dtype code, shape, numpy dtype or None when only the full check knows it, bytes, check finite)
        self.features = [self._feature(f) for f in spec.observation]
        # duplicate names (validate_spec refuses them): a key count cannot prove the key set, so no fast path
        self.unique = len({f.name for f in spec.observation}) == len(self.features)
        self.action = action_check(spec)
        act = self.action
        self.action_dtype = wire.dtype_from_proto(act.dtype) if act.dtype in self._RAW_DTYPES else None
        size = math.prod(act.shape)  # as wire.from_tensor counts it (a scalar is one value)
        ok = self.action_dtype is not None and all(d >= 0 for d in act.shape)
        self.action_bytes = size * self.action_dtype.itemsize if ok else -1  # type: ignore[union-attr]
        # finite limits: one range test also refuses NaN and Inf
        self.action_limits = (
            (act.low_limit, act.high_limit)
            if act.bounded and np.isfinite(act.low_limit).all() and np.isfinite(act.high_limit).all()
            else None
        )

    @classmethod
    def _feature(cls, f: robot_pb2.FeatureSpec) -> tuple[str, int, tuple[int, ...], np.dtype | None, int, bool]:
        shape = tuple(int(d) for d in f.shape)
        dtype = wire.dtype_from_proto(f.dtype) if f.dtype in cls._RAW_DTYPES else None
        nbytes = math.prod(shape) * dtype.itemsize if dtype is not None else -1
        if min(shape, default=0) < 0 or nbytes > wire.MAX_TENSOR_BYTES:  # what wire.from_tensor refuses
            dtype, nbytes = None, -1
        return f.name, f.dtype, shape, dtype, nbytes, not f.allow_nan and dtype is not None and dtype.kind == "f"

    def _tensors(self, tmap: tpb.TensorMap, images_checked: bool) -> bool:
        tensors = tmap.tensors
        if len(tensors) != len(self.features):
            return False
        for name, code, shape, dtype, nbytes, finite in self.features:
            if name not in tensors:
                return False
            t = tensors[name]
            if t.dtype != code or tuple(t.shape) != shape:
                return False
            enc = t.encoding
            if enc in self._IMAGE:
                if not images_checked:
                    try:
                        wire.check_image(t)
                    except wire.WireError:
                        return False
                continue
            if dtype is None or enc != tpb.ENCODING_RAW or len(t.data) != nbytes or _batched(t):
                return False
            if finite and not np.isfinite(np.frombuffer(t.data, dtype)).all():
                return False
        return True

    def _action(self, tensor: tpb.Tensor) -> bool:
        act = self.action
        if self.action_limits is None or tensor.dtype != act.dtype or tuple(tensor.shape) != act.shape:
            return False
        if tensor.encoding != tpb.ENCODING_RAW or len(tensor.data) != self.action_bytes or _batched(tensor):
            return False
        values = np.frombuffer(tensor.data, self.action_dtype)
        low, high = self.action_limits
        return bool(((values >= low) & (values <= high)).all())  # NaN fails both

    def passes(self, step: step_pb2.Step, images_checked: bool) -> bool:
        rid, eid = step.robot_id, step.episode_id
        if not self.unique or rid != self.robot_id or not id_ok(rid, MAX_ROBOT_ID_BYTES):
            return False
        if not id_ok(eid, MAX_EPISODE_ID_BYTES):
            return False
        if step.step_index >= MAX_INT64 or step.policy_version > MAX_INT64 or not math.isfinite(step.reward):
            return False
        has_final = step.HasField("final_observation")
        if has_final != (step.terminated or step.truncated):
            return False
        if not self._tensors(step.observation, images_checked) or not self._action(step.action):
            return False
        return not has_final or self._tensors(step.final_observation, images_checked)


def _batched(tensor: tpb.Tensor) -> bool:
    """frame_bytes/batch_dims belong to sampled batches of images: a step's tensor with them is for the full
    check to refuse (wire.from_tensor / check_image)."""
    return bool(tensor.batch_dims or tensor.frame_bytes)


def id_ok(value: str, limit: int) -> bool:
    """A robot or episode id as replay keys it: non-empty, no '/' or NUL, at most `limit` UTF-8 bytes."""
    return bool(value) and "/" not in value and "\0" not in value and len(value.encode()) <= limit


_STEP_CHECKS: dict[bytes, StepCheck] = {}


def step_check(spec: robot_pb2.RobotSpec) -> StepCheck:
    return _compiled(_STEP_CHECKS, spec.SerializeToString(), lambda: StepCheck(spec))  # ~1 us


def validate_step(step: step_pb2.Step, spec: robot_pb2.RobotSpec, images_checked: bool = False) -> None:
    """Raise StepError naming the first thing in `step` that does not match `spec` (images_checked: see
    check_tensor_map)."""
    if step_check(spec).passes(step, images_checked):
        return
    _check_id("robot_id", step.robot_id, MAX_ROBOT_ID_BYTES)
    if step.robot_id != spec.robot_id:
        raise StepError("robot_id", f"robot_id {step.robot_id!r} does not match the spec's {spec.robot_id!r}")
    _check_id("episode_id", step.episode_id, MAX_EPISODE_ID_BYTES)
    if step.step_index >= MAX_INT64:
        raise StepError("step_index", f"step_index {step.step_index} must be below 2**63 - 1")
    if step.policy_version > MAX_INT64:
        raise StepError("policy_version", f"policy_version {step.policy_version} must fit in int64")
    check_tensor_map("observation", step.observation, list(spec.observation), images_checked)
    action_check(spec)(step.action)
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
        check_tensor_map("final_observation", step.final_observation, list(spec.observation), images_checked)
