"""LeRobotDataset v3 in and out of the replay buffer, checked by lerobot 0.6.1 itself."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.replay.lerobot_io import export_dataset
from services.replay.store import ReplayStore
from services.replay.tables import Draw
from user.cli import main

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
    assert set(original.features) == set(again.features)
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
