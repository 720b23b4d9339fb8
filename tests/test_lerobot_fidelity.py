"""LeRobotDataset export and import keep what a step says: ids that never collide across datasets, every per-step
fact, the task, the control rate, the dtypes and grey cameras. Real LMDB buffers in tmp dirs, datasets written and
read by lerobot 0.6.1 itself, the real `userctl replay` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.replay.lerobot_io import _steps_of
from services.replay.store import ReplayStore
from user import wire
from user.cli import main
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

pytest.importorskip("lerobot.datasets.lerobot_dataset")

F32, F64, F16, U8 = tpb.DTYPE_FLOAT32, tpb.DTYPE_FLOAT64, tpb.DTYPE_FLOAT16, tpb.DTYPE_UINT8


def spec_of(
    robot_id: str,
    observation: list[tuple[str, int, list[int], bool]],
    action: int = 3,
    action_dtype: int = F32,
    rate: float = 20.0,
    task: str = "",
    kind: str = "toy_arm",
) -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind=kind,
        task=task,
        action=robot_pb2.ActionSpace(shape=[action], low=[-1] * action, high=[1] * action, dtype=action_dtype),
        observation=[robot_pb2.FeatureSpec(name=n, dtype=d, shape=s, is_image=i) for n, d, s, i in observation],
        control_rate_hz=rate,
        max_episode_steps=50,
    )


def observation(spec: robot_pb2.RobotSpec, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Random values of every feature of the spec (floats with all their digits)."""
    out = {}
    for f in spec.observation:
        dtype, shape = wire.dtype_from_proto(f.dtype), tuple(f.shape)
        out[f.name] = (
            rng.integers(0, 256, shape, np.uint8) if dtype == np.uint8 else rng.normal(size=shape).astype(dtype)
        )
    return out


def episode(
    spec: robot_pb2.RobotSpec, name: str, length: int, end: str, rng: np.random.Generator, **per_step: set[int]
) -> list[step_pb2.Step]:
    """end: "terminated", "truncated" or "open"; per_step: Step bool fields set at those indices."""
    action_dtype = wire.dtype_from_proto(spec.action.dtype)
    steps = []
    for t in range(length):
        last = t == length - 1
        step = step_pb2.Step(
            robot_id=spec.robot_id,
            episode_id=name,
            step_index=t,
            observation=wire.to_tensor_map(observation(spec, rng)),
            action=wire.to_tensor(rng.uniform(-1, 1, spec.action.shape[0]).astype(action_dtype)),
            reward=float(rng.normal()),
            terminated=last and end == "terminated",
            truncated=last and end == "truncated",
            policy_version=100 + t,
            observed_at_ns=1_700_000_000_000_000_000 + t * 133_333_333,
            acted_at_ns=1_700_000_000_000_000_000 + t * 133_333_333 + 7_000_000,
            **{field: t in indices for field, indices in per_step.items()},
        )
        if step.terminated or step.truncated:  # a final observation of its own, not the last step's
            step.final_observation.CopyFrom(wire.to_tensor_map(observation(spec, rng)))
        steps.append(step)
    return steps


def fill(path: Path, episodes: list[tuple[robot_pb2.RobotSpec, list[step_pb2.Step]]]) -> None:
    store = ReplayStore(path, 64)
    try:
        for spec, steps in episodes:
            store.put_steps(steps, [spec])
    finally:
        store.close()


def stored(path: Path) -> tuple[list[step_pb2.Step], dict[str, robot_pb2.RobotSpec]]:
    """Every step of the buffer (episodes in arrival order) and the spec of each robot."""
    store = ReplayStore(path, cache_mb=0, readonly=True)
    try:
        steps = [s for prefix in store._episodes for s in _steps_of(store, prefix)]
        specs = {r: spec for r in {s.robot_id for s in steps} if (spec := store.get_spec(r)) is not None}
        return steps, specs
    finally:
        store.close()


def export(buffer: Path, out: Path, *more: str) -> list[str]:
    return ["replay", "export", str(out), "--repo-id", "local/out", "--path", str(buffer), *more]


def import_(root: Path, buffer: Path, *more: str) -> list[str]:
    return ["replay", "import", str(root), "--repo-id", "local/demos", "--path", str(buffer), *more]


def plain_dataset(root: Path, base: float, lengths: tuple[int, ...], tasks: tuple[str, ...] = ("reach",)) -> None:
    """A dataset of lerobot's own writer (no meta/user_replay.json): state 4 = base + 10 e + t, action 2."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (2,), "names": None},
    }
    ds = LeRobotDataset.create("local/demos", 10, features, root=root, robot_type="toy", use_videos=False)
    for e, length in enumerate(lengths):
        for t in range(length):
            state = np.full(4, base + 10 * e + t, np.float32)
            ds.add_frame({"observation.state": state, "action": np.zeros(2, np.float32), "task": tasks[e % len(tasks)]})
        ds.save_episode()
    ds.finalize()


def states_by_episode(path: Path) -> list[list[float]]:
    steps, _ = stored(path)
    out: dict[tuple[str, str], list[float]] = {}
    for s in steps:
        out.setdefault((s.robot_id, s.episode_id), []).append(
            float(wire.from_tensor(s.observation.tensors["state"])[0])
        )
    return sorted(out.values())


# --------------------------------------------------------------------------- 1: import ids never collide


def test_a_second_dataset_under_the_same_repo_id_is_stored_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plain_dataset(tmp_path / "monday", 0, (5, 5))
    plain_dataset(tmp_path / "tuesday", 1000, (6, 6, 6))
    buffer = tmp_path / "replay"
    assert main(import_(tmp_path / "monday", buffer)) == 0
    assert main(import_(tmp_path / "tuesday", buffer)) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [f"import: 2 episodes, 10 frames -> {buffer}", f"import: 3 episodes, 18 frames -> {buffer}"]
    monday = [[10.0 * e + t for t in range(5)] for e in range(2)]
    tuesday = [[1000 + 10.0 * e + t for t in range(6)] for e in range(3)]
    assert states_by_episode(buffer) == sorted(monday + tuesday)  # nothing dropped, nothing spliced

    assert main(import_(tmp_path / "tuesday", buffer)) == 0  # the same dataset again: idempotent
    again = f"import: 0 episodes, 0 frames -> {buffer} (already there, not stored again: 3 episodes, 18 frames)\n"
    assert capsys.readouterr().out == again
    assert states_by_episode(buffer) == sorted(monday + tuesday)


def test_an_episode_under_the_same_key_with_other_steps_is_refused_not_spliced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plain_dataset(tmp_path / "monday", 0, (5, 5))
    assert main(import_(tmp_path / "monday", tmp_path / "first")) == 0
    steps, specs = stored(tmp_path / "first")
    # another buffer holds, under the ids the import uses, three steps that are not the dataset's
    other = []
    for s in steps[:3]:
        changed = step_pb2.Step()
        changed.CopyFrom(s)
        changed.observation.CopyFrom(wire.to_tensor_map({"state": np.full(4, 77.0, np.float32)}))
        other.append(changed)
    buffer = tmp_path / "replay"
    fill(buffer, [(specs[steps[0].robot_id], other)])
    capsys.readouterr()
    assert main(import_(tmp_path / "monday", buffer)) == 2
    err = capsys.readouterr().err
    assert f"already has episode {steps[0].episode_id!r}" in err and "differs" in err and "nothing written" in err
    assert states_by_episode(buffer) == [[77.0, 77.0, 77.0]]  # nothing spliced in, nothing else written


# --------------------------------------------------------------------------- 2: every per-step fact round trips

CAMERA = [("state", F32, [5], False), ("camera.front", U8, [16, 16, 3], True)]


def test_round_trip_keeps_every_step_fact_and_robot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.utils.feature_utils import dataset_to_policy_features

    rng = np.random.default_rng(1)
    a, b = (spec_of(r, CAMERA, task="pick up the red cube", kind="so101") for r in ("arm.a-1", "arm-b"))
    episodes = [
        (a, episode(a, "e0", 4, "terminated", rng, intervention={1}, success={3}, held={2})),
        (a, episode(a, "e1", 3, "truncated", rng)),
        (a, episode(a, "e2", 2, "open", rng)),  # still running when exported
        (b, episode(b, "d0", 3, "terminated", rng, intervention={0, 1})),
    ]
    buffer, out, again = tmp_path / "replay", tmp_path / "ds", tmp_path / "again"
    fill(buffer, episodes)
    assert main(export(buffer, out)) == 0
    ds = LeRobotDataset("local/out", root=out)
    assert (ds.num_episodes, ds.num_frames) == (4, 12)
    # lerobot's policies see the observations and the action only; its DataLoader batches the extras
    assert set(dataset_to_policy_features(ds.meta.features)) == {
        "observation.state",
        "observation.images.front",
        "action",
    }
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=12)))
    assert batch["intervention"].tolist() == [False, True, False, False] + [False] * 5 + [True, True, False]

    assert main(import_(out, again, "--robot-id", "rt")) == 0
    assert "4 episodes, 12 frames" in capsys.readouterr().out
    got, specs = stored(again)
    robots = {"arm.a-1": "rt.arm.a-1", "arm-b": "rt.arm-b"}  # two robots stay two
    assert len(got) == 12
    for want, have in zip([s for _, steps in episodes for s in steps], got, strict=True):
        assert have.robot_id == robots[want.robot_id]
        same = step_pb2.Step()
        same.CopyFrom(want)
        same.robot_id, same.episode_id = have.robot_id, have.episode_id
        assert have == same, f"{want.episode_id} step {want.step_index}"  # flags, versions, times, final observations
    for original, imported in robots.items():
        kept = robot_pb2.RobotSpec()
        kept.CopyFrom(a if original == "arm.a-1" else b)
        kept.robot_id = imported
        assert specs[imported] == kept  # control rate, bounds, is_image, task


# --------------------------------------------------------------------------- 3: the task text


def test_export_tags_frames_with_the_spec_task_and_import_keeps_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(2)
    spec = spec_of("arm-0", CAMERA, task="把红色方块 pick up the red cube", kind="so101")
    buffer, out = tmp_path / "replay", tmp_path / "ds"
    fill(buffer, [(spec, episode(spec, "e0", 3, "terminated", rng))])
    assert main(export(buffer, out)) == 0
    ds = LeRobotDataset("local/out", root=out)
    assert ds.meta.tasks.index.tolist() == [spec.task] and ds[0]["task"] == spec.task  # not the kind "so101"
    assert main(export(buffer, tmp_path / "told", "--task", "wave")) == 0  # --task still wins
    assert LeRobotDataset("local/out", root=tmp_path / "told")[0]["task"] == "wave"

    assert main(import_(out, tmp_path / "again")) == 0
    assert stored(tmp_path / "again")[1]["lerobot-local-demos"].task == spec.task
    plain_dataset(tmp_path / "two", 0, (2, 2, 2), tasks=("stack the cups", "wipe the table"))
    capsys.readouterr()
    assert main(import_(tmp_path / "two", tmp_path / "mixed")) == 0
    assert stored(tmp_path / "mixed")[1]["lerobot-local-demos"].task == "stack the cups"
    note = capsys.readouterr().err.strip()
    assert note.startswith("userctl replay import: note: the dataset has 2 tasks;") and "'stack the cups'" in note


# --------------------------------------------------------------------------- 4: fps


@pytest.mark.parametrize("rate", [7.5, 0.5])
def test_export_fps_is_the_control_rate_never_truncated(tmp_path: Path, rate: float) -> None:
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(3)
    spec = spec_of("slow-0", [("state", F32, [5], False)], rate=rate)
    buffer, out = tmp_path / "replay", tmp_path / "ds"
    fill(buffer, [(spec, episode(spec, "e0", 4, "terminated", rng))])
    assert main(export(buffer, out)) == 0
    assert json.loads((out / "meta" / "info.json").read_text())["fps"] == rate
    ds = LeRobotDataset("local/out", root=out, delta_timestamps={"action": [0.0, 1 / rate]})
    assert ds.fps == rate and float(ds[1]["timestamp"]) == pytest.approx(1 / rate)
    assert next(iter(torch.utils.data.DataLoader(ds, batch_size=4)))["action"].shape == (4, 2, 3)
    assert main(export(buffer, tmp_path / "given", "--fps", "2.5")) == 0
    assert LeRobotDataset("local/out", root=tmp_path / "given").fps == 2.5


# --------------------------------------------------------------------------- 5: dtypes


def test_float64_and_float16_values_survive_export_and_import(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    rng = np.random.default_rng(4)
    spec = spec_of("f64-0", [("state", F64, [3], False), ("joints", F16, [2], False)], action=2, action_dtype=F64)
    steps = episode(spec, "e0", 3, "terminated", rng)
    buffer, out = tmp_path / "replay", tmp_path / "ds"
    fill(buffer, [(spec, steps)])
    assert main(export(buffer, out)) == 0
    features = json.loads((out / "meta" / "info.json").read_text())["features"]
    assert [features[k]["dtype"] for k in ("observation.state", "observation.joints", "action")] == [
        "float64",
        "float16",
        "float64",
    ]
    table = pq.read_table(next((out / "data").rglob("*.parquet")))
    np.testing.assert_array_equal(
        np.stack(table.column("action").to_pylist()), np.stack([wire.from_tensor(s.action) for s in steps])
    )
    assert main(import_(out, tmp_path / "again")) == 0
    got, specs = stored(tmp_path / "again")
    for want, have in zip(steps, got, strict=True):
        for name in ("state", "joints"):
            a, b = wire.from_tensor(want.observation.tensors[name]), wire.from_tensor(have.observation.tensors[name])
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name  # every bit
        assert wire.from_tensor(have.action).dtype == np.float64
        assert wire.from_tensor(have.action).tobytes() == wire.from_tensor(want.action).tobytes()
    assert specs["lerobot-local-demos"].action.dtype == F64


# --------------------------------------------------------------------------- 6: cameras


GREY = [
    ("state", F32, [2], False),
    ("camera.flat", U8, [8, 8], True),  # no channel axis
    ("camera.one", U8, [8, 8, 1], True),
    ("heat", U8, [4, 4, 3], False),  # uint8 (H, W, 3) that is not a camera
]


def test_grey_cameras_export_as_images_and_come_back_in_their_shape(tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(5)
    spec = spec_of("grey-0", GREY)
    steps = episode(spec, "e0", 3, "terminated", rng)
    buffer, out = tmp_path / "replay", tmp_path / "ds"
    fill(buffer, [(spec, steps)])
    assert main(export(buffer, out)) == 0
    ds = LeRobotDataset("local/out", root=out)
    kinds = {k: (f["dtype"], tuple(f["shape"])) for k, f in ds.features.items() if k.startswith("observation.")}
    assert kinds == {
        "observation.state": ("float32", (2,)),
        "observation.images.flat": ("image", (8, 8, 3)),
        "observation.images.one": ("image", (8, 8, 3)),
        "observation.heat": ("uint8", (4, 4, 3)),
    }
    frame = ds[0]["observation.images.flat"].numpy()  # lerobot's (C, H, W) floats: the grey value in each channel
    grey = wire.from_tensor(steps[0].observation.tensors["camera.flat"])
    np.testing.assert_array_equal(np.rint(frame * 255).astype(np.uint8), np.stack([grey] * 3))

    assert main(import_(out, tmp_path / "again")) == 0
    got, specs = stored(tmp_path / "again")
    for want, have in zip(steps, got, strict=True):
        for name in ("camera.flat", "camera.one", "heat"):
            a, b = wire.from_tensor(want.observation.tensors[name]), wire.from_tensor(have.observation.tensors[name])
            assert a.shape == b.shape and np.array_equal(a, b), name
    assert {f.name: f.is_image for f in specs["lerobot-local-demos"].observation} == {n: i for n, _, _, i in GREY}


def test_an_rgba_camera_is_refused_before_out_exists(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(6)
    spec = spec_of("rgba-0", [("state", F32, [2], False), ("camera.g", U8, [8, 8, 4], True)])
    buffer, out = tmp_path / "replay", tmp_path / "ds"
    fill(buffer, [(spec, episode(spec, "e0", 2, "terminated", rng))])
    assert main(export(buffer, out)) == 2
    err = capsys.readouterr().err
    assert "'camera.g' is an RGBA camera (8, 8, 4)" in err and not out.exists()
