"""LeRobotDataset v3 in and out of a replay buffer, through lerobot's own API (lerobot 0.6.1).

Names map one to one: our "state" <-> "observation.state", "camera.<cam>" <-> "observation.images.<cam>" (dtype
"image", stored losslessly), any other observation feature "<f>" <-> "observation.<f>", action <-> "action",
reward <-> "next.reward", terminated <-> "next.done", truncated <-> "next.truncated", success <-> "next.success"
(a dataset without it: success = done and reward > 0). The other per-step facts travel as features lerobot's
policies ignore (neither "observation." nor "action"): "intervention", "held", "policy_version", "observed_at_ns",
"acted_at_ns", and "robot_index", an index into the robot ids listed in meta/user_replay.json.

Every feature keeps its stored dtype (a float64 action stays float64; import reads the parquet columns through
arrow, not through lerobot's float32 tensors) and is checked against the dtype and shape meta/info.json declares,
refusing a value that does not fit. A camera is what the robot's spec marks is_image (without a spec: uint8
(H, W, 3) or (H, W, 1)). lerobot stores 3-channel images only, so a grey camera ((H, W) or (H, W, 1)) is exported
with its channel repeated and meta/user_replay.json records its shape, which import restores; an RGBA camera is
refused. Export's fps is --fps, else the robot's control rate (10 without a spec), never rounded: a float where
it is not a whole number (lerobot 0.6.1 writes, loads and trains on those). Frames are tagged with --task, else
the robot spec's task, else its kind.

meta/user_replay.json also keeps each exported robot's RobotSpec, and meta/user_final_observations.npz each ended
episode's final_observation (a dataset has no observation after its last frame). Import of such a dataset gives
the same steps back: the same flags, versions, times and final observations; an episode that was still open
(neither done nor truncated) stays open. Its robots keep their specs (control rate, bounds, task) under the
imported robot id: the --robot-id (default "lerobot-<repo id>") for a dataset of one robot, "<that>.<robot>" for
each robot of a dataset of several. A plain LeRobotDataset (no meta/user_replay.json) imports as one robot whose
spec comes from the dataset (action bounds from its stats, task from its first episode; a note says so when the
dataset has several tasks, since a step carries none), and the last step of each episode ends it: terminated
when next.done, else truncated (its final_observation is its own observation, as lerobot's
ReplayBuffer.from_lerobot_dataset does).

Import writes to the LMDB directly, so it refuses a buffer a replay service holds (the service's in-memory index
would never see the new steps; see store.hold_buffer): stop the service first, or import into a new path. An
imported episode's id is "<repo id>-<episode index>-<digest>", the digest a hash of the dataset's features and fps
and that episode's frames, so another dataset under the same --repo-id never lands on the same keys. Importing the
same dataset again stores nothing again (the summary says how many episodes and frames were new and how many were
already there); a buffer episode under the same key whose steps differ from the dataset's is refused before
anything is written.

lerobot is never allowed to reach the Hugging Face hub here: import reads a dataset on disk only (a root
without meta/info.json is refused before lerobot sees it), export writes one; both run with the hub's
offline switch set (_hub_offline).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import re
import shutil
import sys
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf import json_format

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
from user.spec import ROBOT_ID_RE
from user.v1 import robot_pb2, step_pb2

log = logging.getLogger(__name__)
IMAGE_PREFIX = "camera."
CHUNK = 256  # steps per put_steps of an import
READ_ROWS = 64  # dataset frames decoded at once (images: 64 frames of 480x640x3 are 59 MB)
DEFAULT_FPS = 10  # a robot without a spec (or a rate) and no --fps
META_FILE = "user_replay.json"  # in the dataset's meta/: robot ids and specs, grey cameras, final observations
FINALS_FILE = "user_final_observations.npz"  # in meta/: each ended episode's final_observation (np.load, no pickle)
META_FORMAT = 1
MAX_INT64 = (1 << 63) - 1
# Per-step facts beyond lerobot's own features: dataset name -> (dtype, Step field; robot_index: see META_FILE)
EXTRAS = {
    "next.truncated": ("bool", "truncated"),
    "intervention": ("bool", "intervention"),
    "held": ("bool", "held"),
    "robot_index": ("int64", ""),
    "policy_version": ("int64", "policy_version"),
    "observed_at_ns": ("int64", "observed_at_ns"),
    "acted_at_ns": ("int64", "acted_at_ns"),
}
NOT_HASHED = ("index", "episode_index", "task_index")  # positions in the dataset (the task text is hashed instead)


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


@dataclass
class Summary:
    episodes: int  # written (import: episodes the buffer did not have before)
    frames: int  # written (import: steps stored now)
    path: str
    present_episodes: int = 0  # import: episodes the buffer already had (re-imported)
    present_frames: int = 0  # import: steps already stored, not stored again
    notes: list[str] = field(default_factory=list)  # import: what the buffer cannot keep of the dataset (one line each)


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


def _is_camera(name: str, array: np.ndarray, spec: robot_pb2.RobotSpec | None) -> bool:
    """Exported as an image: what the spec marks is_image (without one: uint8 (H, W, 3) or (H, W, 1));
    ValueError for an RGBA camera, which lerobot 0.6.1 cannot store (its image writer takes 1 or 3 channels)."""
    marked = next((f.is_image for f in spec.observation if f.name == name), None) if spec is not None else None
    if marked is None:
        marked = array.dtype == np.uint8 and array.ndim == 3 and array.shape[-1] in (1, 3)
    if marked and array.ndim == 3 and array.shape[-1] == 4:
        raise ValueError(
            f"observation {name!r} is an RGBA camera {tuple(array.shape)}: a LeRobotDataset image has 3 channels "
            "(lerobot 0.6.1 cannot store 4), so it cannot be exported"
        )
    return bool(marked)


def _rgb(array: np.ndarray) -> np.ndarray:
    """A camera frame as lerobot stores images: (H, W, 3); a grey one has its channel repeated."""
    if array.ndim == 2:
        array = array[..., None]
    return np.ascontiguousarray(np.repeat(array, 3, axis=-1) if array.shape[-1] == 1 else array)


def _data_features(step: step_pb2.Step, spec: robot_pb2.RobotSpec | None) -> dict[str, dict[str, Any]]:
    """Observation and action features of the robot's dataset, each in its stored dtype."""
    features: dict[str, dict[str, Any]] = {}
    for name, array in sorted(arrays_of(step.observation).items()):
        if _is_camera(name, array, spec):
            shape = (*array.shape[:2], 3)
            features[_dataset_name(name)] = {"dtype": "image", "shape": shape, "names": ["height", "width", "channels"]}
        else:
            features[_dataset_name(name)] = {"dtype": str(array.dtype), "shape": tuple(array.shape), "names": None}
    action = tensor_array(step.action)
    features["action"] = {"dtype": str(action.dtype), "shape": tuple(action.shape), "names": None}
    return features


def _features(step: step_pb2.Step, spec: robot_pb2.RobotSpec | None) -> dict[str, dict[str, Any]]:
    features = _data_features(step, spec)
    features["next.reward"] = {"dtype": "float32", "shape": (1,), "names": None}
    features["next.done"] = {"dtype": "bool", "shape": (1,), "names": None}
    features["next.success"] = {"dtype": "bool", "shape": (1,), "names": None}
    for name, (dtype, _) in EXTRAS.items():
        features[name] = {"dtype": dtype, "shape": (1,), "names": None}
    return features


def _shapes_text(features: dict[str, dict[str, Any]]) -> str:
    """What must match across episodes of one dataset: every feature's shape and dtype."""
    return ", ".join(f"{name} {tuple(f['shape'])} {f['dtype']}" for name, f in sorted(features.items()))


def _check_one_embodiment(store: ReplayStore, prefixes: list[bytes]) -> step_pb2.Step:
    """The first step of the selection; ValueError when its episodes need datasets of different features."""
    robots_by_shapes: dict[str, set[str]] = {}
    for prefix in prefixes:
        step = next(_steps_of(store, prefix))
        shapes = _shapes_text(_data_features(step, store.get_spec(step.robot_id)))
        robots_by_shapes.setdefault(shapes, set()).add(step.robot_id)
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


def _fps(fps: float | None, spec: robot_pb2.RobotSpec | None) -> int | float:
    """--fps, else the robot's control rate: never rounded (lerobot 0.6.1 takes a float fps), an int when whole."""
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    rate = fps if fps is not None else spec.control_rate_hz if spec is not None and spec.control_rate_hz > 0 else 0
    rate = float(rate or DEFAULT_FPS)
    return int(rate) if rate.is_integer() else rate


@dataclass
class _Export:
    """What every frame of one export shares: the robots (robot_index), their tasks, the cameras."""

    robots: list[str]
    tasks: dict[str, str]
    cameras: frozenset[str]  # our names of the observations written as images
    grey: dict[str, list[int]]  # dataset name -> the shape of a camera written with its channel repeated


def _export_plan(store: ReplayStore, prefixes: list[bytes], first: step_pb2.Step, task: str) -> _Export:
    robots = list(dict.fromkeys(store._episodes[p].robot for p in prefixes))
    tasks = {}
    for robot in robots:
        spec = store.get_spec(robot)
        tasks[robot] = task or (spec.task if spec is not None else "") or _kind(spec) or "user"
    spec = store.get_spec(first.robot_id)
    observation = arrays_of(first.observation)
    cameras = frozenset(n for n, a in observation.items() if _is_camera(n, a, spec))
    grey = {_dataset_name(n): list(observation[n].shape) for n in cameras if observation[n].shape[2:] != (3,)}
    return _Export(robots, tasks, cameras, grey)


def _frame(step: step_pb2.Step, plan: _Export) -> dict[str, Any]:
    """One step as a frame of lerobot's add_frame."""
    frame: dict[str, Any] = {
        _dataset_name(n): _rgb(a) if n in plan.cameras else a for n, a in arrays_of(step.observation).items()
    }
    frame["action"] = tensor_array(step.action)
    frame["next.reward"] = np.array([step.reward], np.float32)
    frame["next.done"] = np.array([step.terminated])
    frame["next.success"] = np.array([step.success])
    if step.policy_version > MAX_INT64:
        raise ValueError(f"policy_version {step.policy_version} of {step.robot_id}/{step.episode_id} exceeds int64")
    for name, (dtype, attr) in EXTRAS.items():
        value = getattr(step, attr) if attr else plan.robots.index(step.robot_id)
        frame[name] = np.array([value], dtype)
    frame["task"] = plan.tasks[step.robot_id]
    return frame


class _FinalsWriter:
    """meta/user_final_observations.npz, one array at a time (np.savez would hold every episode's in RAM)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.zip: zipfile.ZipFile | None = None
        self.listed: dict[str, dict[str, str]] = {}  # dataset episode -> observation name -> array name
        self.arrays = 0

    def add(self, episode: int, observation: dict[str, np.ndarray]) -> None:
        if self.zip is None:
            self.zip = zipfile.ZipFile(self.path, "w", zipfile.ZIP_DEFLATED)
        names = self.listed[str(episode)] = {}
        for name, array in sorted(observation.items()):
            names[name] = key = f"a{self.arrays}"
            self.arrays += 1
            with self.zip.open(key + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.ascontiguousarray(array), allow_pickle=False)

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()


def _write_episodes(ds: Any, store: ReplayStore, prefixes: list[bytes], plan: _Export, finals: _FinalsWriter) -> int:
    """Every step of the episodes as frames of ds, and their final observations; the number of frames."""
    frames = 0
    for e, prefix in enumerate(prefixes):
        for step in _steps_of(store, prefix):
            ds.add_frame(_frame(step, plan))
            frames += 1
            if step.HasField("final_observation"):
                finals.add(e, arrays_of(step.final_observation))
        ds.save_episode()
    return frames


def _write_meta(root: Path, store: ReplayStore, plan: _Export, finals: dict[str, dict[str, str]]) -> None:
    """meta/user_replay.json: the robots (by robot_index) and their specs, grey cameras, the final observations."""
    specs = {r: json_format.MessageToDict(s) for r in plan.robots if (s := store.get_spec(r)) is not None}
    meta = {
        "format": META_FORMAT,
        "robots": plan.robots,
        "specs": specs,
        "grey": plan.grey,
        "final_observations": finals,
    }
    (root / "meta" / META_FILE).write_text(json.dumps(meta, indent=1) + "\n")


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
    fps: float | None = None,
) -> Summary:
    """Write episodes [first_episode, last_episode) of `table` (arrival order) as a LeRobotDataset at root.

    Everything is checked before root is created; a failure after that removes root again.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    _fps(fps, None)  # a bad --fps before anything is read
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
        plan = _export_plan(store, prefixes, first, task)
        features = _features(first, spec)
        with _hub_offline():
            try:
                ds = LeRobotDataset.create(
                    repo_id, _fps(fps, spec), features, root=root, robot_type=_kind(spec) or "user", use_videos=False
                )
            except FileExistsError:
                raise  # root appeared after the check above: not ours to remove
            except BaseException:
                shutil.rmtree(root, ignore_errors=True)  # create may fail after making root
                raise
            try:
                finals = _FinalsWriter(root / "meta" / FINALS_FILE)
                try:
                    frames = _write_episodes(ds, store, prefixes, plan, finals)
                finally:
                    finals.close()
                ds.finalize()
                _write_meta(root, store, plan, finals.listed)
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
    """A video frame (float CHW in [0, 1] as lerobot decodes it) back to uint8 HWC."""
    array = value.numpy() if hasattr(value, "numpy") else np.asarray(value)
    if array.dtype != np.uint8:
        array = np.clip(np.rint(array * 255.0), 0, 255).astype(np.uint8)
    if array.ndim == 3 and array.shape[0] in (1, 3) and array.shape[-1] not in (1, 3):
        array = np.moveaxis(array, 0, -1)
    return np.ascontiguousarray(array)


@dataclass(frozen=True)
class _Column:
    """A feature of a dataset: our name for it and the dtype and shape it declares (dtype None: an image; video:
    its frames are not in the parquet files, lerobot decodes them)."""

    ours: str
    dtype: np.dtype | None
    shape: tuple[int, ...]
    video: bool = False


def _observation_columns(ds: Any) -> dict[str, _Column]:
    columns = {}
    for theirs, feature in ds.features.items():
        ours = _our_name(theirs)
        if ours is None:
            continue
        if feature["dtype"] in ("image", "video"):
            columns[theirs] = _Column(ours, None, (), feature["dtype"] == "video")
        else:
            columns[theirs] = _Column(ours, _declared_dtype(theirs, feature["dtype"]), tuple(feature["shape"]))
    return columns


def _scalar_columns(ds: Any) -> dict[str, _Column]:
    """action, lerobot's next.* and our per-step extras, where the dataset has them."""
    if "action" not in ds.features:
        raise ValueError("the dataset has no 'action' feature")
    names = ("action", "next.reward", "next.done", "next.success", *EXTRAS)
    columns = {}
    for name in (n for n in names if n in ds.features):
        feature = ds.features[name]
        columns[name] = _Column(name, _declared_dtype(name, feature["dtype"]), tuple(feature["shape"]))
        if name != "action" and math.prod(columns[name].shape) != 1:
            raise ValueError(f"feature {name!r}: shape {tuple(feature['shape'])} in meta/info.json, not one value")
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


def _flat(name: str, column: Any, shape: tuple[int, ...]) -> Any:
    """An arrow column's values with every list level flattened (slices respected); ValueError for a frame whose
    list length is not the declared one, or a missing value."""
    import pyarrow as pa
    import pyarrow.compute as pc

    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if isinstance(arr, pa.ExtensionArray):  # datasets' Array2D..5D
        arr = arr.storage
    level = 0
    while pa.types.is_list(arr.type) or pa.types.is_large_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
        lengths = pc.list_value_length(arr).to_numpy(zero_copy_only=False)
        if level < len(shape) and (lengths != shape[level]).any():
            raise ValueError(f"feature {name!r}: a frame has a list of other length than the shape {shape} declared")
        arr, level = arr.flatten(), level + 1
    if arr.null_count:
        raise ValueError(f"feature {name!r}: {arr.null_count} values missing")
    return arr


def _values(name: str, column: Any, dtype: np.dtype, shape: tuple[int, ...], n: int) -> np.ndarray:
    """n frames of a numeric column, (n, *shape) in the declared dtype, read from arrow (lerobot's own reading turns
    float64 into float32 tensors)."""
    values = _flat(name, column, shape).to_numpy(zero_copy_only=False)
    if values.size != n * math.prod(shape):
        raise ValueError(f"feature {name!r}: {values.size} values in {n} frames where meta/info.json declares {shape}")
    return np.ascontiguousarray(_cast(name, values, dtype).reshape(n, *shape))


def _images(name: str, column: Any, grey: tuple[int, ...] | None) -> list[np.ndarray]:
    """The frames of an image column as uint8 (H, W) / (H, W, C) arrays; a grey camera back in its own shape."""
    from datasets.features import Image

    decoder = Image()
    out = []
    for value in column.to_pylist():
        if value is None:
            raise ValueError(f"feature {name!r}: a frame has no image")
        image = decoder.decode_example(value)
        if image.mode not in ("L", "RGB", "RGBA"):
            raise ValueError(f"feature {name!r}: image mode {image.mode!r} is not a uint8 grey, RGB or RGBA camera")
        array = np.asarray(image)
        if grey is not None:
            if array.ndim != 3 or not (array == array[..., :1]).all():
                raise ValueError(f"feature {name!r}: meta/{META_FILE} says it is a grey camera, its channels differ")
            array = array[..., 0].reshape(grey)
        out.append(np.ascontiguousarray(array))
    return out


def _check_robot_id(robot_id: str) -> None:
    if not ROBOT_ID_RE.fullmatch(robot_id):
        raise ValueError(f"robot id {robot_id[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . - (see --robot-id)")


@dataclass
class _Episode:
    """A dataset episode and the robot and episode ids its steps are stored under."""

    index: int  # the dataset's episode_index
    start: int  # its frames [start, stop) of the dataset
    stop: int
    robot: str
    episode_id: str
    tasks: list[str]  # the task texts of its frames, first seen first

    @property
    def task(self) -> str:
        return self.tasks[0] if self.tasks else ""


@dataclass
class _Plan:
    """How a dataset becomes steps, worked out (and every value checked) before the buffer is touched."""

    columns: dict[str, _Column]  # observations
    scalars: dict[str, _Column]  # action, next.*, extras
    grey: dict[str, tuple[int, ...]]  # dataset name -> shape of a grey camera exported as RGB
    finals: _Finals
    robots: list[str]  # robot ids, by the dataset's robot_index
    specs: dict[str, robot_pb2.RobotSpec]  # robot id -> the spec the dataset keeps for it
    episodes: list[_Episode] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


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

    Checked before the buffer is created or changed: the table name, the robot id, that root holds a dataset on disk
    (never fetched from the hub), that no replay service holds the buffer (BufferHeld), every value of the dataset;
    the buffer is held (store.hold_buffer) while the steps are written, so a service cannot start meanwhile.
    """
    check_table(table)
    if robot_id is not None:
        _check_robot_id(robot_id)
    root = Path(root)
    _check_dataset_root(root)
    holder = buffer_holder(store_path)  # a probe, before the dataset is read; the real hold comes below
    if holder is not None:
        raise BufferHeld(_held_text(store_path, holder), holder)
    with _hub_offline():
        ds = _open_dataset(root, repo_id)
        plan = _plan(ds, root, repo_id, robot_id or _safe(f"lerobot-{repo_id}")[:64])
        with contextlib.closing(plan.finals):
            counts = _import_held(store_path, map_size_mb, ds, plan, repo_id, table)
    return Summary(
        counts.episodes, counts.frames, str(store_path), counts.present_episodes, counts.present_frames, plan.notes
    )


def _import_held(store_path: str | Path, map_size_mb: int, ds: Any, plan: _Plan, repo_id: str, table: str) -> _Counts:
    """_import_into the buffer at store_path, held (hold_buffer) while the steps are written."""
    try:
        fd = hold_buffer(store_path, "`userctl replay import`")
    except BufferHeld as exc:  # a service started meanwhile
        raise BufferHeld(_held_text(store_path, exc.holder), exc.holder) from None
    try:
        store = ReplayStore(store_path, map_size_mb, cache_mb=0, max_map_mb=max(map_size_mb, 1 << 20))
        try:
            return _import_into(store, ds, plan, repo_id, table)
        finally:
            store.close()
    finally:
        release_buffer(fd)


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


# --------------------------------------------------------------------------- import: meta/user_replay.json


def _read_meta(root: Path) -> dict[str, Any]:
    """meta/user_replay.json of a dataset we exported ({} for a plain one); ValueError when it is damaged."""
    path = root / "meta" / META_FILE
    if not path.is_file():
        return {}
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    kinds = {"robots": list, "specs": dict, "grey": dict, "final_observations": dict}
    if not isinstance(meta, dict) or meta.get("format") != META_FORMAT:
        raise ValueError(f"{path}: not a format {META_FORMAT} file of this exporter")
    for key, kind in kinds.items():
        if not isinstance(meta.get(key), kind):
            raise ValueError(f"{path}: {key!r} is missing or not a {kind.__name__}")
    if not all(isinstance(r, str) and ROBOT_ID_RE.fullmatch(r) for r in meta["robots"]):
        raise ValueError(f"{path}: 'robots' must be robot ids")
    for episode, names in meta["final_observations"].items():
        if not (episode.isdigit() and isinstance(names, dict) and all(isinstance(k, str) for k in names.values())):
            raise ValueError(f"{path}: 'final_observations' must map episode indices to observation names to arrays")
    return meta


def _meta_specs(root: Path, meta: dict[str, Any], robots: list[str]) -> dict[str, robot_pb2.RobotSpec]:
    """The specs meta/user_replay.json keeps, under the robot ids the steps are stored under."""
    specs = {}
    for original, robot in zip(meta.get("robots", []), robots, strict=False):
        if original not in meta["specs"]:
            continue
        try:
            spec = json_format.ParseDict(meta["specs"][original], robot_pb2.RobotSpec())
        except json_format.ParseError as exc:
            raise ValueError(f"{root / 'meta' / META_FILE}: the spec of robot {original!r}: {exc}") from None
        spec.robot_id = robot
        specs[robot] = spec
    return specs


def _grey(root: Path, meta: dict[str, Any], columns: dict[str, _Column]) -> dict[str, tuple[int, ...]]:
    grey = {}
    for theirs, shape in meta.get("grey", {}).items():
        ok = isinstance(shape, list) and len(shape) in (2, 3) and all(isinstance(d, int) and d > 0 for d in shape)
        if theirs not in columns or columns[theirs].dtype is not None or not ok:
            raise ValueError(f"{root / 'meta' / META_FILE}: 'grey' names {theirs!r}, not an image feature and shape")
        grey[theirs] = tuple(shape)
    return grey


class _Finals:
    """The final observations meta/user_final_observations.npz keeps, read one episode at a time from the archive
    opened once per import: an open parses the zip's whole directory (an entry per episode and camera), so one per
    read was O(episodes^2), and np.load's NpzFile finds a name by scanning a list. close() when the import is done."""

    def __init__(self, root: Path, meta: dict[str, Any], columns: dict[str, _Column]) -> None:
        self.path = root / "meta" / FINALS_FILE
        self.listed: dict[str, Any] = meta.get("final_observations", {})
        self.ours = {c.ours: c for c in columns.values()}
        self._zip: zipfile.ZipFile | None = None  # opened at the first get(); names looked up in its dict

    def _array(self, key: str) -> np.ndarray:
        """Array `key` of the archive (the .npy member _FinalsWriter wrote; never a pickle)."""
        if self._zip is None:
            self._zip = zipfile.ZipFile(self.path)
        with self._zip.open(key + ".npy") as f:
            return np.lib.format.read_array(f, allow_pickle=False)

    def close(self) -> None:
        if self._zip is not None:
            self._zip.close()
            self._zip = None

    def get(self, episode: int) -> dict[str, np.ndarray] | None:
        """Episode's final observation (None: the dataset keeps none); ValueError when it is damaged."""
        names = self.listed.get(str(episode))
        if names is None:
            return None
        try:
            obs = {name: self._array(key) for name, key in names.items()}
        except (OSError, ValueError, KeyError, TypeError, AttributeError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{self.path} (named by meta/{META_FILE}): {type(exc).__name__}: {exc}") from None
        for name, array in obs.items():
            c = self.ours.get(name)
            fits = c is not None and (
                array.dtype == np.uint8 if c.dtype is None else (array.dtype, array.shape) == (c.dtype, c.shape)
            )
            if not fits or set(obs) != set(self.ours):
                raise ValueError(f"{self.path}: the final observation of episode {episode} does not match the features")
        return obs


# --------------------------------------------------------------------------- import: the plan


def _plan(ds: Any, root: Path, repo_id: str, base: str) -> _Plan:
    """Robot and episode id of every dataset episode, every value checked; nothing written yet."""
    meta = _read_meta(root)
    columns = _observation_columns(ds)
    originals = meta.get("robots", [])
    robots = [base] if len(originals) <= 1 else [f"{base}.{r}" for r in originals]
    for robot in robots:
        _check_robot_id(robot)
    plan = _Plan(columns, _scalar_columns(ds), _grey(root, meta, columns), _Finals(root, meta, columns), robots, {})
    plan.specs = _meta_specs(root, meta, robots)
    if "robot_index" in plan.scalars and not originals:
        plan.notes.append(f"robot_index is not used: the dataset has no meta/{META_FILE} naming its robots")
        del plan.scalars["robot_index"]
    head = json.dumps(
        {"features": ds.meta.features, "fps": ds.fps, "robots": originals, "grey": meta.get("grey", {})},
        sort_keys=True,
        default=str,
    ).encode()
    arrow = ds.hf_dataset.with_format("arrow")
    positions = ds.hf_dataset.select_columns(["episode_index", "task_index"]).with_format("arrow")[0 : len(arrow)]
    ep_index = np.asarray(positions.column("episode_index").to_numpy())
    task_index = np.asarray(positions.column("task_index").to_numpy())
    texts = {int(i): str(t) for t, i in ds.meta.tasks["task_index"].items()}
    bounds = np.flatnonzero(np.diff(ep_index)) + 1
    starts, stops = (np.r_[0, bounds].tolist(), np.r_[bounds, len(ep_index)].tolist()) if len(ep_index) else ([], [])
    try:
        for start, stop in zip(starts, stops, strict=True):
            tasks = [texts.get(int(i), "") for i in dict.fromkeys(task_index[start:stop].tolist())]
            plan.episodes.append(_episode(plan, arrow[start:stop], head, repo_id, int(ep_index[start]), start, tasks))
    except BaseException:
        plan.finals.close()  # the caller closes it once it has the plan
        raise
    _note_tasks(plan)
    return plan


def _episode(plan: _Plan, frames: Any, head: bytes, repo_id: str, index: int, start: int, tasks: list[str]) -> _Episode:
    """One dataset episode: its values checked, its robot, and an id that hashes its content."""
    n, robot = frames.num_rows, plan.robots[0]
    for theirs, c in {**plan.columns, **plan.scalars}.items():
        if c.dtype is None:
            continue
        values = _values(theirs, frames.column(theirs), c.dtype, c.shape, n)
        if theirs == "robot_index":
            if values.min() < 0 or values.max() >= len(plan.robots) or values.min() != values.max():
                raise ValueError(f"feature 'robot_index' of episode {index}: not one of the {len(plan.robots)} robots")
            robot = plan.robots[int(values.flat[0])]
    digest = _digest(head, frames, tasks, plan.finals.get(index) or {})
    return _Episode(index, start, start + n, robot, f"{_safe(repo_id)}-{index:06d}-{digest}", tasks)


def _digest(head: bytes, frames: Any, tasks: list[str], final: dict[str, np.ndarray]) -> str:
    """16 hex digits of a hash of the dataset's features and fps and one episode's frames, tasks and final
    observation: what keys its steps, so another dataset under the same repo id never lands on them."""
    h = hashlib.blake2b(head, digest_size=8)
    for name in sorted(set(frames.column_names) - set(NOT_HASHED)):
        h.update(name.encode() + b"\0")
        for part in _column_bytes(frames.column(name)):
            h.update(len(part).to_bytes(8, "little") + part)
    for text in tasks:
        h.update(b"task\0" + text.encode())
    for name, array in sorted(final.items()):
        h.update(f"final\0{name}\0{array.dtype.str}\0{array.shape}".encode() + array.tobytes())
    return h.hexdigest()


def _column_bytes(column: Any) -> Iterator[bytes]:
    """An arrow column's content as bytes, independent of how it is chunked."""
    import pyarrow as pa
    import pyarrow.compute as pc

    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if isinstance(arr, pa.ExtensionArray):
        arr = arr.storage
    if arr.null_count:
        yield np.asarray(arr.is_null()).tobytes()
    if pa.types.is_struct(arr.type):  # an image: {bytes, path}
        for child in arr.flatten():
            yield from _column_bytes(child)
    elif pa.types.is_list(arr.type) or pa.types.is_large_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
        yield pc.list_value_length(arr).to_numpy(zero_copy_only=False).tobytes()
        yield from _column_bytes(arr.flatten())
    elif pa.types.is_binary(arr.type) or pa.types.is_string(arr.type) or pa.types.is_large_binary(arr.type):
        for value in arr.to_pylist():
            yield b"" if value is None else value if isinstance(value, bytes) else value.encode()
    else:
        yield arr.to_numpy(zero_copy_only=False).tobytes()


def _note_tasks(plan: _Plan) -> None:
    """A step carries no task: a robot's spec keeps its first episode's; say so where the dataset has more."""
    for robot in plan.robots:
        tasks = list(dict.fromkeys(t for e in plan.episodes if e.robot == robot for t in e.tasks))
        if len(tasks) > 1:
            name = f"robot {robot}: " if len(plan.robots) > 1 else ""
            plan.notes.append(
                f"{name}the dataset has {len(tasks)} tasks; the robot spec's task is the first episode's, {tasks[0]!r} "
                "(a step carries no task of its own)"
            )


# --------------------------------------------------------------------------- import: the steps


@dataclass
class _Counts:
    episodes: int = 0  # episodes the buffer did not have
    frames: int = 0  # steps stored
    present_episodes: int = 0  # episodes the buffer had before (an earlier import)
    present_frames: int = 0  # steps it already had


def _import_into(store: ReplayStore, ds: Any, plan: _Plan, repo_id: str, table: str) -> _Counts:
    """Every episode of the plan as steps in `table`; what was new and what the buffer already had. The specs and
    the episodes the buffer already has are checked before the first step is written."""
    arrow = ds.hf_dataset.with_format("arrow")
    new_specs = _specs_to_register(store, ds, arrow, plan, repo_id)
    stored = _check_present(store, ds, arrow, plan)
    counts = _Counts()
    steps: list[step_pb2.Step] = []
    for ep in plan.episodes:
        had = stored.get(episode_prefix(ep.robot, ep.episode_id))
        counts.present_episodes += had is not None
        counts.episodes += had is None
        if had == ep.stop - ep.start:  # all there: nothing to read again
            counts.present_frames += had
            continue
        for step in _episode_steps(ds, arrow, plan, ep):
            steps.append(step)
            if len(steps) >= CHUNK:
                _put(store, steps, new_specs, table, counts)
    if steps:
        _put(store, steps, new_specs, table, counts)
    for spec in new_specs:  # a robot with no new step (its episodes were all there) still gets its spec
        if store.get_spec(spec.robot_id) is None:
            store.put_spec(spec)
    return counts


def _put(
    store: ReplayStore, steps: list[step_pb2.Step], specs: list[robot_pb2.RobotSpec], table: str, counts: _Counts
) -> None:
    new, duplicates = store.put_steps(steps, specs, table)
    counts.frames += new
    counts.present_frames += duplicates
    steps.clear()


def _specs_to_register(store: ReplayStore, ds: Any, arrow: Any, plan: _Plan, repo_id: str) -> list[robot_pb2.RobotSpec]:
    """A spec for each robot id the buffer does not know (the dataset's own where it keeps one); a robot id the
    buffer knows must keep the features, dtypes and shapes it registered. Checked on each robot's first step."""
    new, seen = [], set()
    for ep in plan.episodes:
        if ep.robot in seen:
            continue
        seen.add(ep.robot)
        step = next(_episode_steps(ds, arrow, plan, ep))
        known = store.get_spec(ep.robot)
        if known is not None:
            hint = f"the dataset does not match the spec the buffer keeps for robot {ep.robot!r}"
            _check_spec(step, known, hint, "import under another --robot-id")
            continue
        spec = plan.specs.get(ep.robot)
        if spec is None:
            spec = _spec_for(ep.robot, repo_id, ds, step, ep.task, plan)
        else:
            spec.task = ep.task
            hint = f"the dataset's frames do not match the spec meta/{META_FILE} keeps for its robot"
            _check_spec(step, spec, hint, f"was meta/{META_FILE} changed?")
        new.append(spec)
    return new


def _check_present(store: ReplayStore, ds: Any, arrow: Any, plan: _Plan) -> dict[bytes, int]:
    """Steps the buffer already has of each dataset episode (by prefix); ValueError when an episode the buffer has
    under the same key holds other steps (something other than this dataset wrote it): never spliced."""
    stored = {}
    for ep in plan.episodes:
        prefix = episode_prefix(ep.robot, ep.episode_id)
        if prefix not in store._episodes:  # we are the buffer's only writer
            continue
        ours = _episode_steps(ds, arrow, plan, ep)
        count = 0
        for theirs in _steps_of(store, prefix):
            step = next((s for s in ours if s.step_index >= theirs.step_index), None)
            if step is None or step != theirs:
                raise ValueError(
                    f"the buffer already has episode {ep.episode_id!r} of robot {ep.robot!r} and its step "
                    f"{theirs.step_index} differs from frame {theirs.step_index} of the dataset's episode {ep.index}: "
                    "not imported (nothing written); import under another --robot-id or --repo-id"
                )
            count += 1
        stored[prefix] = count
    return stored


def _episode_steps(ds: Any, arrow: Any, plan: _Plan, ep: _Episode) -> Iterator[step_pb2.Step]:
    for start in range(ep.start, ep.stop, READ_ROWS):
        stop = min(start + READ_ROWS, ep.stop)
        rows = _read(ds, arrow, plan, start, stop)
        for j in range(stop - start):
            yield _step_of(plan, rows, j, ep, start + j - ep.start)


def _read(ds: Any, arrow: Any, plan: _Plan, start: int, stop: int) -> dict[str, Any]:
    """Frames [start, stop), column by column: numbers in their declared dtypes, images as uint8 arrays."""
    frames = arrow[start:stop]
    out: dict[str, Any] = {}
    for theirs, c in {**plan.columns, **plan.scalars}.items():
        if c.video:
            out[theirs] = [_uint8_image(ds[i][theirs]) for i in range(start, stop)]
        elif c.dtype is None:
            out[theirs] = _images(theirs, frames.column(theirs), plan.grey.get(theirs))
        else:
            out[theirs] = _values(theirs, frames.column(theirs), c.dtype, c.shape, stop - start)
    return out


def _step_of(plan: _Plan, rows: dict[str, Any], j: int, ep: _Episode, index: int) -> step_pb2.Step:
    """Frame j of rows as step `index` of the episode."""
    obs = wire.to_tensor_map({c.ours: rows[theirs][j] for theirs, c in plan.columns.items()})
    one = {name: rows[name][j].flat[0].item() for name in plan.scalars if name != "action"}
    last = index == ep.stop - ep.start - 1
    done, reward = bool(one.get("next.done", False)), float(one.get("next.reward", 0.0))
    # a dataset without next.success (recorded elsewhere): a reward at the end is the best guess
    success = bool(one["next.success"]) if "next.success" in one else done and reward > 0
    # ours says truncated (neither: an episode still open when exported); elsewhere the last frame ends it
    truncated = bool(one["next.truncated"]) if "next.truncated" in one else not done
    if one.get("policy_version", 0) < 0:
        raise ValueError(f"feature 'policy_version': value {one['policy_version']} is negative")
    step = step_pb2.Step(
        robot_id=ep.robot,
        episode_id=ep.episode_id,
        step_index=index,
        observation=obs,
        action=wire.to_tensor(_action(rows["action"][j])),
        reward=reward,
        terminated=last and done,
        truncated=last and truncated,
        success=success,
        intervention=bool(one.get("intervention", False)),
        held=bool(one.get("held", False)),
        policy_version=int(one.get("policy_version", 0)),
        observed_at_ns=int(one.get("observed_at_ns", 0)),
        acted_at_ns=int(one.get("acted_at_ns", 0)),
    )
    if step.terminated or step.truncated:
        final = plan.finals.get(ep.index)
        step.final_observation.CopyFrom(wire.to_tensor_map(final) if final is not None else obs)
    return step


def _action(array: np.ndarray) -> np.ndarray:
    """An action keeps a float dtype; an integer or bool one becomes float32 where every value fits."""
    return array if array.dtype.kind == "f" else _cast("action", array, np.dtype(np.float32))


def _check_spec(step: step_pb2.Step, spec: robot_pb2.RobotSpec, hint: str, fix: str) -> None:
    """The steps must keep the features, dtypes and shapes the spec names."""
    try:
        check_tensor_map("observation", step.observation, list(spec.observation))
    except StepError as exc:
        raise ValueError(f"{hint}: {exc} ({fix})") from None
    if step.action.dtype != spec.action.dtype or list(step.action.shape) != list(spec.action.shape):
        have = f"{wire.dtype_name(step.action.dtype)} {list(step.action.shape)}"
        want = f"{wire.dtype_name(spec.action.dtype)} {list(spec.action.shape)}"
        raise ValueError(f"{hint}: action {have}, spec says {want} ({fix})")


def _spec_for(robot_id: str, repo_id: str, ds: Any, step: step_pb2.Step, task: str, plan: _Plan) -> robot_pb2.RobotSpec:
    """A spec for the imported robot id of a plain dataset, so the buffer can validate later steps of it."""
    stats = ds.meta.stats.get("action", {}) if ds.meta.stats else {}
    low = np.asarray(stats.get("min", []), np.float64).reshape(-1).tolist()
    high = np.asarray(stats.get("max", []), np.float64).reshape(-1).tolist()
    cameras = {c.ours for c in plan.columns.values() if c.dtype is None}
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind=f"lerobot:{repo_id}"[:128],
        action=robot_pb2.ActionSpace(shape=list(step.action.shape), low=low, high=high, dtype=step.action.dtype),
        observation=[
            robot_pb2.FeatureSpec(name=n, dtype=t.dtype, shape=list(t.shape), is_image=n in cameras)
            for n, t in sorted(step.observation.tensors.items())
        ],
        control_rate_hz=float(ds.fps),
        max_episode_steps=0,
        task=task,
    )
