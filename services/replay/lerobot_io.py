"""LeRobotDataset v3 in and out of a replay buffer, through lerobot's own API (lerobot 0.6.1).

Names map one to one: our "state" <-> "observation.state", "camera.<cam>" (H, W, 3 uint8) <->
"observation.images.<cam>" (dtype "image", stored losslessly), any other observation feature "<f>"
<-> "observation.<f>", action <-> "action", reward <-> "next.reward", terminated <-> "next.done".

A dataset episode of T frames is T steps. A dataset has no observation after its last frame, so on
import the last step's final_observation is its own observation (as lerobot's own
ReplayBuffer.from_lerobot_dataset does); on export a step's final_observation is dropped. Hence
import -> export -> import gives the same steps.

Import writes to the LMDB directly: run it while the replay service for that path is stopped (its
in-memory index would not see the new steps), or import into a new path.
"""

from __future__ import annotations

import logging
import re
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.replay.store import ReplayStore, arrays_of, tensor_array
from services.replay.tables import ALL, INTERVENTIONS
from user import wire
from user.v1 import robot_pb2, step_pb2

log = logging.getLogger(__name__)
IMAGE_PREFIX = "camera."
CHUNK = 256


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
    episodes: int
    frames: int
    path: str


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
        try:
            ds = LeRobotDataset.create(repo_id, rate, _features(first), root=root, robot_type=kind, use_videos=False)
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


def import_dataset(
    root: str | Path,
    repo_id: str,
    store_path: str | Path,
    *,
    table: str = "demos",
    robot_id: str | None = None,
    map_size_mb: int = 4096,
) -> Summary:
    """Append every episode of the LeRobotDataset at root to `table` of the buffer at store_path."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=root)
    rid = robot_id or _safe(f"lerobot-{repo_id}")
    obs_names = {k: _our_name(k) for k, f in ds.features.items() if _our_name(k) is not None}
    images = {k for k, f in ds.features.items() if f["dtype"] in ("image", "video")}
    store = ReplayStore(store_path, map_size_mb, cache_mb=0, max_map_mb=max(map_size_mb, 1 << 20))
    try:
        steps: list[step_pb2.Step] = []
        spec: robot_pb2.RobotSpec | None = None
        episodes = frames = 0
        ep_index = np.asarray(ds.hf_dataset["episode_index"])
        bounds = np.flatnonzero(np.diff(ep_index)) + 1
        for start, stop in zip(np.r_[0, bounds], np.r_[bounds, len(ep_index)], strict=True):
            for i in range(int(start), int(stop)):
                item = ds[i]
                obs = {}
                for theirs, ours in obs_names.items():
                    value = item[theirs]
                    if theirs in images:
                        obs[ours] = _uint8_image(value)
                    else:
                        obs[ours] = np.asarray(value.numpy() if hasattr(value, "numpy") else value)
                last = i == stop - 1
                done = bool(np.asarray(item["next.done"]).reshape(-1)[0]) if "next.done" in item else False
                reward = float(np.asarray(item["next.reward"]).reshape(-1)[0]) if "next.reward" in item else 0.0
                action = np.asarray(item["action"].numpy() if hasattr(item["action"], "numpy") else item["action"])
                step = step_pb2.Step(
                    robot_id=rid,
                    episode_id=f"{_safe(repo_id)}-{int(ep_index[start]):06d}",
                    step_index=i - int(start),
                    observation=wire.to_tensor_map(obs),
                    action=wire.to_tensor(action.astype(np.float32)),
                    reward=reward,
                    terminated=last and done,
                    truncated=last and not done,
                    success=done and reward > 0,
                )
                if last:
                    step.final_observation.CopyFrom(step.observation)
                if spec is None:
                    spec = _spec_for(rid, repo_id, ds, step)
                steps.append(step)
                frames += 1
                if len(steps) >= CHUNK:
                    store.put_steps(steps, [spec], table)
                    steps = []
            episodes += 1
        if steps:
            store.put_steps(steps, [spec] if spec is not None else [], table)
        return Summary(episodes, frames, str(store_path))
    finally:
        store.close()


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
