"""LeRobotDataset v3 in and out of the replay buffer, checked by lerobot 0.6.1 itself."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.replay.lerobot_io import _as_declared, export_dataset
from services.replay.store import ReplayStore
from services.replay.tables import Draw
from user import wire
from user.cli import main
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

pytest.importorskip("lerobot.datasets.lerobot_dataset")

FPS = 10
EPISODES = (5, 3)  # frames per episode


def make_dataset(root: Path) -> None:
    """A tiny dataset made with lerobot's own writer: state 4, one 8x8 RGB camera, action 2."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "observation.images.front": {"dtype": "image", "shape": (8, 8, 3), "names": ["height", "width", "channels"]},
        "action": {"dtype": "float32", "shape": (2,), "names": None},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }
    ds = LeRobotDataset.create("local/made", FPS, features, root=root, robot_type="toy", use_videos=False)
    rng = np.random.default_rng(0)
    for e, length in enumerate(EPISODES):
        for t in range(length):
            ds.add_frame(
                {
                    "observation.state": np.full(4, 10 * e + t, np.float32),
                    "observation.images.front": rng.integers(0, 256, (8, 8, 3), dtype=np.uint8),
                    "action": np.array([t / 10, -t / 10], np.float32),
                    "next.reward": np.array([float(t == length - 1)], np.float32),
                    "next.done": np.array([t == length - 1 and e == 0]),
                    "task": "reach",
                }
            )
        ds.save_episode()
    ds.finalize()


def test_lerobot_round_trip(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = tmp_path / "made"
    make_dataset(src)
    buffer = tmp_path / "replay"
    args = ["replay", "import", str(src), "--repo-id", "local/made", "--path", str(buffer), "--robot-id", "toy-0"]
    assert main(args) == 0
    assert "2 episodes, 8 frames" in capsys.readouterr().out
    assert main(["replay", "ls", "--path", str(buffer), "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert (
        listed["tables"]["demos"]["transitions"] == 8 and listed["tables"]["demos"]["robots"]["toy-0"]["episodes"] == 2
    )

    store = ReplayStore(buffer, 64)
    try:
        assert store.transitions_for(tables=["demos"]) == 8 and store.transitions_for(tables=["online"]) == 0
        batch = store.sample(64, np.random.default_rng(0), draw=Draw(batch_size=64, tables={"demos": 1}))
        assert batch["observation"]["camera.front"].shape == (64, 8, 8, 3)
        assert batch["observation"]["camera.front"].dtype == np.uint8
        state = batch["observation"]["state"][:, 0]
        assert set(state) <= {0, 1, 2, 3, 4, 10, 11, 12}
        assert store.get_spec("toy-0").control_rate_hz == FPS
        per_table = store.table_stats()["demos"]
        assert per_table["episodes"] == 2 and per_table["success_rate"] == 0.5
    finally:
        store.close()

    out = tmp_path / "exported"
    args = ["replay", "export", str(out), "--repo-id", "local/exported", "--path", str(buffer), "--table", "demos"]
    assert main([*args, "--task", "reach"]) == 0
    assert "2 episodes, 8 frames" in capsys.readouterr().out
    original = LeRobotDataset("local/made", root=src)
    again = LeRobotDataset("local/exported", root=out)
    assert (again.num_episodes, again.num_frames, again.fps) == (2, 8, FPS)
    per_step = {
        "next.truncated",
        "intervention",
        "held",
        "robot_index",
        "policy_version",
        "observed_at_ns",
        "acted_at_ns",
    }
    assert set(again.features) == set(original.features) | {"next.success"} | per_step  # made without them
    for i in range(8):
        a, b = original[i], again[i]
        for key in ("observation.state", "observation.images.front", "action", "next.reward", "next.done"):
            np.testing.assert_array_equal(np.asarray(a[key]), np.asarray(b[key]), err_msg=key)
        assert int(a["episode_index"]) == int(b["episode_index"]) and b["task"] == "reach"

    # lerobot's training data path accepts it: policy features from its metadata, batches from a DataLoader
    import torch
    from lerobot.configs.types import FeatureType
    from lerobot.utils.feature_utils import dataset_to_policy_features

    kinds = {k: f.type for k, f in dataset_to_policy_features(again.meta.features).items()}
    assert kinds["observation.state"] == FeatureType.STATE and kinds["observation.images.front"] == FeatureType.VISUAL
    assert kinds["action"] == FeatureType.ACTION
    loader = torch.utils.data.DataLoader(again, batch_size=4, shuffle=True)
    first = next(iter(loader))
    assert first["observation.images.front"].shape == (4, 3, 8, 8) and first["action"].shape == (4, 2)

    # an episode range of one table
    one = export_dataset(buffer, tmp_path / "one", "local/one", table="demos", first_episode=1, last_episode=2)
    assert (one.episodes, one.frames) == (1, 3)
    with pytest.raises(ValueError, match="no episodes"):
        export_dataset(buffer, tmp_path / "none", "local/none", table="online")
    assert main(["replay", "ls", "--path", str(tmp_path / "nowhere")]) == 2


# --------------------------------------------------------------------------- export's checks, from the CLI


def robot_spec(robot_id: str, kind: str, state: int, action: int) -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind=kind,
        action=robot_pb2.ActionSpace(shape=[action], low=[-1] * action, high=[1] * action, dtype=tpb.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[state])],
        control_rate_hz=20,
        max_episode_steps=50,
    )


def put_episodes(
    store: ReplayStore, spec: robot_pb2.RobotSpec, lengths: tuple[int, ...], odd_state_at: int = -1
) -> None:
    """Episodes e0, e1, ... of the spec's robot; step odd_state_at of each has one state value too many."""
    state, action = spec.observation[0].shape[0], spec.action.shape[0]
    for e, length in enumerate(lengths):
        steps = [
            step_pb2.Step(
                robot_id=spec.robot_id,
                episode_id=f"{spec.robot_id}-e{e}",
                step_index=t,
                observation=wire.to_tensor_map({"state": np.full(state + (t == odd_state_at), t, np.float32)}),
                action=wire.to_tensor(np.zeros(action, np.float32)),
                terminated=t == length - 1,
            )
            for t in range(length)
        ]
        steps[-1].final_observation.CopyFrom(steps[-1].observation)
        store.put_steps(steps, [spec])


ARM = robot_spec("arm-0", "toy_arm", state=4, action=3)
PANDA = robot_spec("panda-0", "toy_panda", state=5, action=7)


@pytest.fixture
def two_robots(tmp_path: Path) -> Path:
    """A buffer with two embodiments: arm-0 (episodes of 2, 3 and 4 steps) then panda-0 (2 steps)."""
    path = tmp_path / "replay"
    store = ReplayStore(path, 64)
    try:
        put_episodes(store, ARM, (2, 3, 4))
        put_episodes(store, PANDA, (2,))
    finally:
        store.close()
    return path


def export_args(buffer: Path, out: Path, *more: str) -> list[str]:
    return ["replay", "export", str(out), "--repo-id", "local/out", "--path", str(buffer), *more]


def test_export_of_two_shapes_is_refused_before_out_exists(
    two_robots: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out = tmp_path / "out"
    assert main(export_args(two_robots, out)) == 2
    err = capsys.readouterr().err
    assert "--robot" in err and not out.exists()
    assert "arm-0 (toy_arm): action (3,)" in err and "observation.state (4,)" in err
    assert "panda-0 (toy_panda): action (7,)" in err and "observation.state (5,)" in err
    assert main(export_args(two_robots, out, "--robot", "panda-0")) == 0
    assert "1 episodes, 2 frames" in capsys.readouterr().out
    assert LeRobotDataset("local/out", root=out).fps == 20  # --fps not given: the robot's control rate


def test_failed_export_removes_only_the_out_it_created(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    buffer, out = tmp_path / "replay", tmp_path / "out"
    store = ReplayStore(buffer, 64)
    try:
        put_episodes(store, ARM, (3, 3), odd_state_at=2)  # lerobot refuses the third frame of the first episode
    finally:
        store.close()
    assert main(export_args(buffer, out)) == 2
    assert "shape" in capsys.readouterr().err and not out.exists()
    out.mkdir()
    (out / "keep.txt").write_text("not the exporter's")
    assert main(export_args(buffer, out)) == 2
    assert "already exists" in capsys.readouterr().err and (out / "keep.txt").exists()


@pytest.mark.parametrize("fps", ["0", "-5"])
def test_export_refuses_a_non_positive_fps_before_out_exists(
    two_robots: Path, tmp_path: Path, fps: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exited:
        main(export_args(two_robots, out, "--robot", "arm-0", "--fps", fps))
    assert exited.value.code == 2 and "--fps" in capsys.readouterr().err and not out.exists()
    with pytest.raises(ValueError, match="fps must be positive"):
        export_dataset(two_robots, out, "local/out", robot_id="arm-0", fps=int(fps))
    assert not out.exists()


@pytest.mark.parametrize(
    ("episodes", "expected"), [("1", "1 episodes, 3 frames"), ("1:", "2 episodes, 7 frames"), (":2", "2 episodes, 5")]
)
def test_export_episodes_n_is_just_episode_n(
    two_robots: Path, tmp_path: Path, episodes: str, expected: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(export_args(two_robots, tmp_path / "out", "--robot", "arm-0", "--episodes", episodes)) == 0
    assert expected in capsys.readouterr().out


@pytest.mark.parametrize("episodes", ["a:b", "x", "3:1", "-1"])
def test_export_bad_episodes_names_the_option(
    two_robots: Path, tmp_path: Path, episodes: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exited:
        main(export_args(two_robots, tmp_path / "out", f"--episodes={episodes}"))
    err = capsys.readouterr().err
    assert exited.value.code == 2 and "--episodes" in err and "invalid literal" not in err


def test_replay_help_lists_the_buffer_tools(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["replay", "--help"])
    out = capsys.readouterr().out
    assert exited.value.code == 0 and "--ready-file" in out
    for usage in ("userctl replay ls [--json]", "userctl replay export --repo-id", "userctl replay import --repo-id"):
        assert usage in out
    assert "--episodes A:B|N" in out and "--robot ROBOT" in out and "--path" in out


def test_replay_tools_find_the_buffer_where_up_puts_it(
    two_robots: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    runs = tmp_path / "runs"
    (runs / "trial").mkdir(parents=True)
    two_robots.rename(runs / "trial" / "replay")  # where `userctl up` with this config writes it
    config = tmp_path / "stack.yaml"
    config.write_text(f"up:\n  name: trial\n  runs_dir: {runs}\n")
    assert main(["replay", "ls", "-c", str(config), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["path"] == str(runs / "trial" / "replay")

    elsewhere = tmp_path / "elsewhere"
    assert main(["replay", "ls", "-c", str(config), "--json", "--set", f"replay.path={elsewhere}"]) == 2
    hint = f"no replay buffer at {elsewhere} (`userctl up` with this config keeps it in {runs / 'trial' / 'replay'}"
    assert hint in capsys.readouterr().err
    assert main(["replay", "ls", "-c", str(config), "--path", str(elsewhere)]) == 2  # --path wins
    assert f"no replay buffer at {elsewhere}\n" in capsys.readouterr().err


# --------------------------------------------------------------------------- dtypes and success through a round trip


TOKENS = 64


def lang_spec(robot_id: str = "lang-0") -> robot_pb2.RobotSpec:
    """lang_reach_arm's shape: a float32 state and uint8 instruction tokens (not an image)."""
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="lang_reach_arm",
        action=robot_pb2.ActionSpace(shape=[3], low=[-1] * 3, high=[1] * 3, dtype=tpb.DTYPE_FLOAT32),
        observation=[
            robot_pb2.FeatureSpec(name="instruction", dtype=tpb.DTYPE_UINT8, shape=[TOKENS]),
            robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[4]),
        ],
        control_rate_hz=10,
        max_episode_steps=50,
    )


def lang_episode(
    spec: robot_pb2.RobotSpec, name: str, length: int, success: bool, reward: float
) -> list[step_pb2.Step]:
    """Tokens up to 255 (so an int64 copy differs from uint8 in dtype only); the last step ends the episode."""
    steps = []
    for t in range(length):
        tokens = (np.arange(TOKENS) * 7 + 250 + t) % 256
        obs = {"instruction": tokens.astype(np.uint8), "state": np.full(4, t + 0.5, np.float32)}
        last = t == length - 1
        steps.append(
            step_pb2.Step(
                robot_id=spec.robot_id,
                episode_id=name,
                step_index=t,
                observation=wire.to_tensor_map(obs),
                action=wire.to_tensor(np.full(3, t / 10, np.float32)),
                reward=reward if last else 0.0,
                terminated=last,
                success=success and last,
            )
        )
    steps[-1].final_observation.CopyFrom(steps[-1].observation)
    return steps


@pytest.fixture
def lang_buffer(tmp_path: Path) -> Path:
    """Online: a successful episode, then a failed one whose last reward is 0.98."""
    path = tmp_path / "replay"
    spec = lang_spec()
    store = ReplayStore(path, 64)
    try:
        store.put_steps(lang_episode(spec, "won", 4, success=True, reward=1.0), [spec])
        store.put_steps(lang_episode(spec, "lost", 3, success=False, reward=0.98), [spec])
    finally:
        store.close()
    return path


def import_args(src: Path, buffer: Path, *more: str) -> list[str]:
    return ["replay", "import", str(src), "--repo-id", "local/lang", "--path", str(buffer), *more]


def test_round_trip_keeps_dtypes_and_samples_with_the_original(
    lang_buffer: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "lang"
    assert main(export_args(lang_buffer, out, "--table", "online")) == 0
    assert main(import_args(out, lang_buffer, "--table", "demos")) == 0  # under its own robot id
    assert main(import_args(out, lang_buffer, "--table", "again", "--robot-id", "lang-0")) == 0  # the spec's robot
    assert "2 episodes, 7 frames" in capsys.readouterr().out
    store = ReplayStore(lang_buffer, 64)
    try:
        assert store.get_spec("lang-0") == lang_spec()  # kept as registered
        imported = store.get_spec("lerobot-local-lang")
        assert {f.name: (f.dtype, list(f.shape)) for f in imported.observation} == {
            "instruction": (tpb.DTYPE_UINT8, [TOKENS]),
            "state": (tpb.DTYPE_FLOAT32, [4]),
        }
        for tables in ({"demos": 1}, {"online": 1, "demos": 1, "again": 1}):
            batch = store.sample(96, np.random.default_rng(0), draw=Draw(batch_size=96, tables=tables))
            tokens, state = batch["observation"]["instruction"], batch["observation"]["state"]
            assert tokens.dtype == np.uint8 and tokens.shape == (96, TOKENS) and state.dtype == np.float32
            t = np.rint(state[:, 0] - 0.5).astype(np.int64)  # step index
            np.testing.assert_array_equal(tokens, ((np.arange(TOKENS) * 7 + 250 + t[:, None]) % 256).astype(np.uint8))
    finally:
        store.close()


def test_round_trip_keeps_a_failed_episode_with_a_positive_reward_failed(
    lang_buffer: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out = tmp_path / "lang"
    assert main(export_args(lang_buffer, out, "--table", "online")) == 0
    dataset = LeRobotDataset("local/out", root=out)
    assert [bool(dataset[i]["next.success"]) for i in range(7)] == [False] * 3 + [True] + [False] * 3
    assert main(import_args(out, lang_buffer, "--table", "demos")) == 0
    store = ReplayStore(lang_buffer, 0)
    try:
        stats = store.table_stats()
        assert stats["online"]["success_rate"] == 0.5 and stats["demos"]["success_rate"] == 0.5
        assert stats["demos"]["episodes"] == 2
    finally:
        store.close()


def test_import_refuses_steps_that_do_not_match_the_known_spec_before_writing(
    lang_buffer: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = tmp_path / "wide"
    features = {
        "observation.instruction": {"dtype": "int64", "shape": (TOKENS,), "names": None},
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (3,), "names": None},
    }
    ds = LeRobotDataset.create("local/lang", 10, features, root=src, use_videos=False)
    for _ in range(2):
        frame = {"observation.instruction": np.zeros(TOKENS, np.int64), "observation.state": np.zeros(4, np.float32)}
        ds.add_frame({**frame, "action": np.zeros(3, np.float32), "task": "reach"})
    ds.save_episode()
    ds.finalize()
    assert main(import_args(src, lang_buffer, "--robot-id", "lang-0")) == 2
    err = capsys.readouterr().err
    assert "'instruction'" in err and "dtype int64, spec says uint8" in err and "lang-0" in err
    store = ReplayStore(lang_buffer, 0)
    try:
        assert store.stats()["steps"] == 7 and "demos" not in store.table_stats()  # nothing written
    finally:
        store.close()


@pytest.mark.parametrize(
    ("value", "dtype"),
    [(np.array([1, 300]), "uint8"), (np.array([-1, 2]), "uint8"), (np.array([0.5]), "int64"), (np.array([2]), "bool")],
)
def test_import_refuses_a_value_that_does_not_fit_its_declared_dtype(value: np.ndarray, dtype: str) -> None:
    with pytest.raises(ValueError, match=f"feature 'observation.instruction': value .* the dtype {dtype}"):
        _as_declared("observation.instruction", value, np.dtype(dtype), value.shape)
    fits = _as_declared("observation.instruction", np.array([0, 1, 255]), np.dtype("uint8"), (3,))
    assert fits.dtype == np.uint8 and fits.tolist() == [0, 1, 255]
    assert _as_declared("next.reward", np.float32(2.5), np.dtype("float32"), (1,)).shape == (1,)
