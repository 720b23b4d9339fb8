"""LeRobotDataset v3 in and out of a replay buffer, through lerobot's own API (lerobot 0.6.1).

Names map one to one: our "state" <-> "observation.state", "camera.<cam>" (H, W, 3 uint8) <->
"observation.images.<cam>" (dtype "image", stored losslessly), any other observation feature "<f>"
<-> "observation.<f>", action <-> "action", reward <-> "next.reward", terminated <-> "next.done",
success <-> "next.success" (a dataset without it: success = done and reward > 0).

Import gives every feature the dtype and shape the dataset declares (lerobot hands back int64 tensors
for a uint8 feature, and shape () for a (1,) one), refusing a value that does not fit; when the buffer
already has a spec for the robot id, the steps must match it, checked before anything is written.

A dataset episode of T frames is T steps. A dataset has no observation after its last frame, so on
import the last step's final_observation is its own observation (as lerobot's own
ReplayBuffer.from_lerobot_dataset does); on export a step's final_observation is dropped. Hence
import -> export -> import gives the same steps.

Import writes to the LMDB directly, so it refuses a buffer a replay service holds (the service's
in-memory index would never see the new steps; see store.hold_buffer): stop the service first, or import
into a new path. Steps already in the buffer (the same robot id, episode and index) are not stored again,
and the summary says how many episodes and frames were new and how many were already there.

lerobot is never allowed to reach the Hugging Face hub here: import reads a dataset on disk only (a root
without meta/info.json is refused before lerobot sees it), export writes one; both run with the hub's
offline switch set (_hub_offline).
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import shutil
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.replay.store import (
    BufferHeld,
    ReplayStore,
    arrays_of,
    buffer_holder,
    episode_prefix,
    hold_buffer,
    release_buffer,
    tensor_array,
)
from services.replay.tables import ALL, INTERVENTIONS
from services.replay.validate import StepError, check_tensor_map
from user import wire
from user.config import TABLE_NAME
from user.v1 import robot_pb2, step_pb2

log = logging.getLogger(__name__)
IMAGE_PREFIX = "camera."
CHUNK = 256
CHECK_ROWS = 4096  # frames per read of the columns checked before an import writes


def _dataset_name(ours: str) -> str:
    if ours == "state":
        return "observation.state"
    if ours.startswith(IMAGE_PREFIX):
        return "observation.images." + ours.removeprefix(IMAGE_PREFIX)
    return "observation." + ours


def _our_name(theirs: str) -> str | None:
    if theirs == "observation.state":
        return "state"
    if theirs.startswith("observation.images."):
        return IMAGE_PREFIX + theirs.removeprefix("observation.images.")
    if theirs.startswith("observation."):
        return theirs.removeprefix("observation.")
    return None


def _is_image(array: np.ndarray) -> bool:
    return array.dtype == np.uint8 and array.ndim == 3 and array.shape[-1] in (1, 3)


@dataclass
class Summary:
    episodes: int  # written (import: episodes the buffer did not have before)
    frames: int  # written (import: steps stored now)
    path: str
    present_episodes: int = 0  # import: episodes the buffer already had (re-imported)
    present_frames: int = 0  # import: steps already stored, not stored again


def check_table(table: str) -> None:
    """ValueError unless `table` is a name the config accepts for a replay table (user.config.TABLE_NAME)."""
    if not re.fullmatch(TABLE_NAME, table):
        raise ValueError(f"table {table[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . -")


@contextlib.contextmanager
def _hub_offline() -> Iterator[None]:
    """Around our lerobot calls: huggingface_hub (and datasets) refuse every request to the hub, so lerobot
    cannot download a dataset (it would, for a root it finds incomplete) or look up its versions."""
    from huggingface_hub import constants

    saved: list[tuple[Any, str, Any]] = [(constants, "HF_HUB_OFFLINE", constants.HF_HUB_OFFLINE)]
    datasets_config = sys.modules.get("datasets.config")  # lerobot imports it; only patch what is loaded
    if datasets_config is not None:
        saved += [(datasets_config, n, getattr(datasets_config, n)) for n in ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE")]
    for module, name, _ in saved:
        setattr(module, name, True)
    try:
        yield
    finally:
        for module, name, value in saved:
            setattr(module, name, value)


# --------------------------------------------------------------------------- export


def _episodes(store: ReplayStore, table: str, robot_id: str | None) -> list[bytes]:
    """Episode prefixes of a table (in arrival order); "interventions": episodes with a human step."""
    out = []
    for prefix, ep in store._episodes.items():
        if robot_id and ep.robot != robot_id:
            continue
        if table == ALL or ep.table == table or (table == INTERVENTIONS and ep.interventions):
            out.append(prefix)
    return out


def _steps_of(store: ReplayStore, prefix: bytes) -> Iterator[step_pb2.Step]:
    with store.db.env.begin(db=store.db.steps) as txn:
        cur = txn.cursor()
        if not cur.set_range(prefix):
            return
        for key, raw in cur:
            if not bytes(key).startswith(prefix):
                return
            yield step_pb2.Step.FromString(bytes(raw))


def _features(step: step_pb2.Step) -> dict[str, dict[str, Any]]:
    features: dict[str, dict[str, Any]] = {}
    for name, array in sorted(arrays_of(step.observation).items()):
        if _is_image(array):
            features[_dataset_name(name)] = {
                "dtype": "image",
                "shape": tuple(array.shape),
                "names": ["height", "width", "channels"],
            }
        else:
            features[_dataset_name(name)] = {"dtype": str(array.dtype), "shape": tuple(array.shape), "names": None}
    action = tensor_array(step.action)
    features["action"] = {"dtype": "float32", "shape": tuple(action.shape), "names": None}
    features["next.reward"] = {"dtype": "float32", "shape": (1,), "names": None}
    features["next.done"] = {"dtype": "bool", "shape": (1,), "names": None}
    features["next.success"] = {"dtype": "bool", "shape": (1,), "names": None}
    return features


def _shapes_text(features: dict[str, dict[str, Any]]) -> str:
    """What must match across episodes of one dataset: every feature's shape and dtype."""
    return ", ".join(f"{name} {tuple(f['shape'])} {f['dtype']}" for name, f in sorted(features.items()))


def _check_one_embodiment(store: ReplayStore, prefixes: list[bytes]) -> step_pb2.Step:
    """The first step of the selection; ValueError when its episodes need datasets of different features."""
    robots_by_shapes: dict[str, set[str]] = {}
    for prefix in prefixes:
        step = next(_steps_of(store, prefix))
        robots_by_shapes.setdefault(_shapes_text(_features(step)), set()).add(step.robot_id)
    if len(robots_by_shapes) > 1:
        lines = [f"  {_robots_text(store, robots)}: {shapes}" for shapes, robots in robots_by_shapes.items()]
        raise ValueError(
            "the selected episodes come from robots of different shapes and a dataset holds one; "
            "pick one robot with --robot (or narrow --table/--episodes):\n" + "\n".join(lines)
        )
    return next(_steps_of(store, prefixes[0]))


def _robots_text(store: ReplayStore, robots: set[str]) -> str:
    return ", ".join(f"{robot} ({_kind(store.get_spec(robot)) or 'no spec'})" for robot in sorted(robots))


def _kind(spec: robot_pb2.RobotSpec | None) -> str:
    return spec.kind if spec is not None else ""


def _control_rate(spec: robot_pb2.RobotSpec | None) -> int:
    return int(spec.control_rate_hz) if spec is not None and spec.control_rate_hz else 10


def _write_episodes(ds: Any, store: ReplayStore, prefixes: list[bytes], task: str) -> int:
    """Every step of the episodes as frames of ds; the number of frames."""
    frames = 0
    for prefix in prefixes:
        for step in _steps_of(store, prefix):
            frame: dict[str, Any] = {_dataset_name(n): a for n, a in arrays_of(step.observation).items()}
            frame["action"] = tensor_array(step.action).astype(np.float32)
            frame["next.reward"] = np.array([step.reward], np.float32)
            frame["next.done"] = np.array([step.terminated])
            frame["next.success"] = np.array([step.success])
            frame["task"] = task
            ds.add_frame(frame)
            frames += 1
        ds.save_episode()
    return frames


def export_dataset(
    store_path: str | Path,
    root: str | Path,
    repo_id: str,
    *,
    table: str = ALL,
    robot_id: str | None = None,
    first_episode: int = 0,
    last_episode: int | None = None,
    task: str = "",
    fps: int | None = None,
) -> Summary:
    """Write episodes [first_episode, last_episode) of `table` (arrival order) as a LeRobotDataset at root.

    Everything is checked before root is created; a failure after that removes root again.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if fps is not None and fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if table != ALL:
        check_table(table)
    root = Path(root)
    if root.exists():
        raise FileExistsError(f"{root} already exists: export writes a new dataset directory")
    store = ReplayStore(store_path, cache_mb=0, readonly=True)
    try:
        prefixes = _episodes(store, table, robot_id)[first_episode:last_episode]
        if not prefixes:
            raise ValueError(f"no episodes in table {table or '(all)'!r} for that range/robot")
        first = _check_one_embodiment(store, prefixes)
        spec = store.get_spec(first.robot_id)
        kind = _kind(spec) or "user"
        rate = fps if fps is not None else _control_rate(spec)
        with _hub_offline():
            try:
                ds = LeRobotDataset.create(
                    repo_id, rate, _features(first), root=root, robot_type=kind, use_videos=False
                )
            except FileExistsError:
                raise  # root appeared after the check above: not ours to remove
            except BaseException:
                shutil.rmtree(root, ignore_errors=True)  # create may fail after making root
                raise
            try:
                frames = _write_episodes(ds, store, prefixes, task or kind)
                ds.finalize()
            except BaseException:
                shutil.rmtree(root, ignore_errors=True)  # no half-written dataset left to block a rerun
                raise
        return Summary(len(prefixes), frames, str(root))
    finally:
        store.close()


# --------------------------------------------------------------------------- import


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "-", text)[:100] or "dataset"


def _uint8_image(value: Any) -> np.ndarray:
    """A dataset image (float CHW in [0, 1] as lerobot returns it) back to uint8 HWC."""
    array = value.numpy() if hasattr(value, "numpy") else np.asarray(value)
    if array.dtype != np.uint8:
        array = np.clip(np.rint(array * 255.0), 0, 255).astype(np.uint8)
    if array.ndim == 3 and array.shape[0] in (1, 3) and array.shape[-1] not in (1, 3):
        array = np.moveaxis(array, 0, -1)
    return np.ascontiguousarray(array)


@dataclass(frozen=True)
class _Column:
    """An observation feature of a dataset: our name for it and the dtype and shape it declares (None: an image)."""

    ours: str
    dtype: np.dtype | None
    shape: tuple[int, ...]


def _observation_columns(ds: Any) -> dict[str, _Column]:
    columns = {}
    for theirs, feature in ds.features.items():
        ours = _our_name(theirs)
        if ours is None:
            continue
        if feature["dtype"] in ("image", "video"):
            columns[theirs] = _Column(ours, None, ())
        else:
            columns[theirs] = _Column(ours, _declared_dtype(theirs, feature["dtype"]), tuple(feature["shape"]))
    return columns


def _declared_dtype(name: str, text: str) -> np.dtype:
    try:
        dtype = np.dtype(text)
    except TypeError:
        dtype = np.dtype(object)
    if dtype.kind not in "biuf":
        raise ValueError(f"feature {name!r}: dtype {text!r} in meta/info.json is not a number or bool dtype")
    return dtype


def _cast(name: str, array: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """array as dtype; ValueError naming the feature when a value does not fit (out of range, fractional, NaN)."""
    with np.errstate(invalid="ignore", over="ignore"):
        out = array.astype(dtype)
        lost = np.isfinite(array) & ~np.isfinite(out) if dtype.kind == "f" else out.astype(array.dtype) != array
    if lost.any():
        value = array[lost].flat[0]
        raise ValueError(f"feature {name!r}: value {value!r} does not fit the dtype {dtype} meta/info.json declares")
    return out


def _as_declared(name: str, value: Any, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """One frame's value in the dtype and shape the dataset declares (lerobot returns int64 for uint8, () for (1,))."""
    array = np.asarray(value.numpy() if hasattr(value, "numpy") else value)
    if array.size != math.prod(shape):
        raise ValueError(f"feature {name!r}: {array.size} values where meta/info.json declares shape {shape}")
    return np.ascontiguousarray(_cast(name, array, dtype).reshape(shape))


def _check_columns(ds: Any, columns: dict[str, _Column]) -> None:
    """Every non-image value fits its declared dtype and shape: read column by column, before anything is written."""
    numeric = {theirs: (c.dtype, c.shape) for theirs, c in columns.items() if c.dtype is not None}
    if not numeric:
        return
    table = ds.hf_dataset.select_columns(list(numeric))
    for start in range(0, len(table), CHECK_ROWS):
        rows = table[start : start + CHECK_ROWS]
        for theirs, (dtype, shape) in numeric.items():
            for value in rows[theirs]:
                _as_declared(theirs, value, dtype, shape)


def import_dataset(
    root: str | Path,
    repo_id: str,
    store_path: str | Path,
    *,
    table: str = "demos",
    robot_id: str | None = None,
    map_size_mb: int = 4096,
) -> Summary:
    """Append every episode of the LeRobotDataset at root to `table` of the buffer at store_path.

    Checked before the buffer is created or changed: the table name, that root holds a dataset on disk (never
    fetched from the hub), that no replay service holds the buffer (BufferHeld), every value of the dataset;
    the buffer is held (store.hold_buffer) while the steps are written, so a service cannot start meanwhile.
    """
    check_table(table)
    root = Path(root)
    _check_dataset_root(root)
    holder = buffer_holder(store_path)  # a probe, before the dataset is read; the real hold comes below
    if holder is not None:
        raise BufferHeld(_held_text(store_path, holder), holder)
    with _hub_offline():
        ds = _open_dataset(root, repo_id)
        columns = _observation_columns(ds)
        _check_columns(ds, columns)
        try:
            fd = hold_buffer(store_path, "`userctl replay import`")
        except BufferHeld as exc:  # a service started meanwhile
            raise BufferHeld(_held_text(store_path, exc.holder), exc.holder) from None
        try:
            store = ReplayStore(store_path, map_size_mb, cache_mb=0, max_map_mb=max(map_size_mb, 1 << 20))
            try:
                counts = _import_into(store, ds, repo_id, robot_id or _safe(f"lerobot-{repo_id}"), columns, table)
            finally:
                store.close()
        finally:
            release_buffer(fd)
    return Summary(counts.episodes, counts.frames, str(store_path), counts.present_episodes, counts.present_frames)


def _held_text(store_path: str | Path, holder: str) -> str:
    return (
        f"the buffer {store_path} is held by {holder}, whose index would never see imported steps: "
        "stop it, import, then start it again (or import into another --path)"
    )


def _check_dataset_root(root: Path) -> None:
    """ValueError unless root looks like a LeRobotDataset on disk (lerobot would create it and download one)."""
    if not root.is_dir():
        reason = "not a directory" if root.exists() else "no such directory"
        raise ValueError(f"no LeRobotDataset at {root} ({reason})")
    if not (root / "meta" / "info.json").is_file():
        raise ValueError(f"no LeRobotDataset at {root} (meta/info.json missing)")


def _open_dataset(root: Path, repo_id: str) -> Any:
    """lerobot's LeRobotDataset at root (call inside _hub_offline); ValueError when it cannot be read from disk."""
    from huggingface_hub.errors import OfflineModeIsEnabled
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    try:
        return LeRobotDataset(repo_id, root=root)
    except OfflineModeIsEnabled:  # files lerobot needs are missing: it tried the hub for them
        raise ValueError(
            f"the LeRobotDataset at {root} is incomplete (lerobot would fetch the rest of {repo_id!r} from the "
            "Hugging Face hub; import reads a dataset on disk only)"
        ) from None
    except Exception as exc:  # a damaged dataset: whatever lerobot raised, as one line
        text = str(exc).strip().splitlines()
        raise ValueError(
            f"cannot read the LeRobotDataset at {root}: {type(exc).__name__}: {text[0] if text else ''}"
        ) from None


@dataclass
class _Counts:
    episodes: int = 0  # episodes the buffer did not have
    frames: int = 0  # steps stored
    present_episodes: int = 0  # episodes the buffer had before (an earlier import)
    present_frames: int = 0  # steps it already had


def _import_into(
    store: ReplayStore, ds: Any, repo_id: str, robot_id: str, columns: dict[str, _Column], table: str
) -> _Counts:
    """Every frame of ds as a step of robot_id in `table`; what was new and what the buffer already had."""
    known = store.get_spec(robot_id)
    new_specs: list[robot_pb2.RobotSpec] = []  # registered with the steps; a spec the buffer knows stays as it is
    steps: list[step_pb2.Step] = []
    counts = _Counts()
    frames = 0
    ep_index = np.asarray(ds.hf_dataset["episode_index"])
    bounds = np.flatnonzero(np.diff(ep_index)) + 1
    starts, stops = np.r_[0, bounds].tolist(), np.r_[bounds, len(ep_index)].tolist()

    def put() -> None:
        stored, duplicates = store.put_steps(steps, new_specs, table)
        counts.frames += stored
        counts.present_frames += duplicates
        steps.clear()

    for start, stop in zip(starts, stops, strict=True):
        episode_id = f"{_safe(repo_id)}-{int(ep_index[start]):06d}"
        if episode_prefix(robot_id, episode_id) in store._episodes:  # we are the buffer's only writer
            counts.present_episodes += 1
        else:
            counts.episodes += 1
        for i in range(start, stop):
            step = _step_of(ds[i], columns, robot_id, episode_id, i - start, last=i == stop - 1)
            if frames == 0:  # the first step, before anything is written; the others share its dtypes and shapes
                if known is not None:
                    _check_spec(step, known)
                else:
                    new_specs = [_spec_for(robot_id, repo_id, ds, step)]
            steps.append(step)
            frames += 1
            if len(steps) >= CHUNK:
                put()
    if steps:
        put()
    return counts


def _step_of(
    item: dict[str, Any], columns: dict[str, _Column], robot_id: str, episode_id: str, index: int, last: bool
) -> step_pb2.Step:
    """One dataset frame as a step; the last frame's observation is also its final_observation."""
    obs = {
        c.ours: _uint8_image(item[theirs]) if c.dtype is None else _as_declared(theirs, item[theirs], c.dtype, c.shape)
        for theirs, c in columns.items()
    }
    done = _first(item, "next.done", False)
    reward = float(_first(item, "next.reward", 0.0))
    # a dataset without next.success (recorded elsewhere): a reward at the end is the best guess
    success = bool(_first(item, "next.success", False)) if "next.success" in item else bool(done) and reward > 0
    action = np.asarray(item["action"].numpy() if hasattr(item["action"], "numpy") else item["action"])
    step = step_pb2.Step(
        robot_id=robot_id,
        episode_id=episode_id,
        step_index=index,
        observation=wire.to_tensor_map(obs),
        action=wire.to_tensor(action.astype(np.float32)),
        reward=reward,
        terminated=last and bool(done),
        truncated=last and not done,
        success=success,
    )
    if last:
        step.final_observation.CopyFrom(step.observation)
    return step


def _first(item: dict[str, Any], name: str, default: Any) -> Any:
    """A (1,)-shaped dataset value as a Python scalar (default when the dataset lacks the feature)."""
    if name not in item:
        return default
    return np.asarray(item[name]).reshape(-1)[0].item()


def _check_spec(step: step_pb2.Step, spec: robot_pb2.RobotSpec) -> None:
    """The buffer knows this robot id: its steps must keep the features, dtypes and shapes it registered."""
    hint = f"the dataset does not match the spec the buffer keeps for robot {spec.robot_id!r}"
    try:
        check_tensor_map("observation", step.observation, list(spec.observation))
    except StepError as exc:
        raise ValueError(f"{hint}: {exc} (import under another --robot-id)") from None
    if step.action.dtype != spec.action.dtype or list(step.action.shape) != list(spec.action.shape):
        have = f"{wire.dtype_name(step.action.dtype)} {list(step.action.shape)}"
        want = f"{wire.dtype_name(spec.action.dtype)} {list(spec.action.shape)}"
        raise ValueError(f"{hint}: action {have}, spec says {want} (import under another --robot-id)")


def _spec_for(robot_id: str, repo_id: str, ds: Any, step: step_pb2.Step) -> robot_pb2.RobotSpec:
    """A spec for the imported robot id, so the buffer can validate later steps of it."""
    stats = ds.meta.stats.get("action", {}) if ds.meta.stats else {}
    low = np.asarray(stats.get("min", []), np.float64).reshape(-1).tolist()
    high = np.asarray(stats.get("max", []), np.float64).reshape(-1).tolist()
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind=f"lerobot:{repo_id}"[:128],
        action=robot_pb2.ActionSpace(shape=list(step.action.shape), low=low, high=high, dtype=step.action.dtype),
        observation=[
            robot_pb2.FeatureSpec(name=n, dtype=t.dtype, shape=list(t.shape))
            for n, t in sorted(step.observation.tensors.items())
        ],
        control_rate_hz=float(ds.fps),
        max_episode_steps=0,
    )
