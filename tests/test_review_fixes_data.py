"""Review fixes of the data path: capacity eviction never acks-and-drops an episode's tail that is only late; a
LeRobotDataset import opens meta/user_final_observations.npz once, however many episodes it has.

Real ReplayStore on LMDB in tmp dirs; datasets written and read by lerobot itself through the real `userctl replay`
CLI.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.replay.lerobot_io import FINALS_FILE
from services.replay.store import ReplayStore
from tests.test_replay_eviction_attach import DIM, _episodes, _indices
from tests.test_replay_store import episode, make_step
from user.cli import main

# ---------------------------------------------------------------------- 1: eviction of open episodes


def test_an_open_episode_whose_robot_only_began_the_next_is_not_evicted(tmp_path: Path) -> None:
    """E1's tail is late (set aside at the edge after PERMISSION_DENIED, or behind a slow spool drain) while E2's
    first step already came: over capacity, E1 stays and its tail is stored when it comes (before: E1 counted as
    abandoned, was evicted, and its tail was answered as a duplicate, so the edge deleted it)."""
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        store.put_steps([make_step("arm-0", "E1", t, dim=DIM) for t in range(10)])
        store.put_steps([make_step("arm-0", "E2", 0, dim=DIM)])
        for e in range(20):  # another robot's ended episodes, ~1.6 MB: past capacity_mb
            store.put_steps(episode("arm-1", f"f{e}", 10, dim=DIM))
        assert store.cache_info()["evicted_episodes"] > 0
        assert {("arm-0", "E1"), ("arm-0", "E2")} <= _episodes(store)
        tail = [make_step("arm-0", "E1", t, dim=DIM, last=t == 12) for t in range(10, 13)]
        assert store.put_steps(tail) == (3, 0)  # stored, not refused
        assert _indices(store, "arm-0", "E1") == list(range(13))
    finally:
        store.close()


def test_an_open_episode_is_abandoned_once_its_robot_completed_a_later_one(tmp_path: Path) -> None:
    """Once E2 is whole (every step up to its last), E1's tail would have come before it: E1 may go, and a stray
    step of it is refused rather than stored without its start."""
    store = ReplayStore(tmp_path / "replay", 64, capacity_mb=1)
    try:
        store.put_steps([make_step("arm-0", "E1", t, dim=DIM) for t in range(10)])
        store.put_steps(episode("arm-0", "E2", 5, dim=DIM))
        for e in range(20):
            store.put_steps(episode("arm-1", f"f{e}", 10, dim=DIM))
        assert ("arm-0", "E1") not in _episodes(store)  # evicted (E2, ended, went too as the oldest)
        assert store.put_steps([make_step("arm-0", "E1", 10, dim=DIM, last=True)]) == (0, 1)
    finally:
        store.close()


# ---------------------------------------------------------------------- 2: import reads the finals archive once


def test_import_opens_the_final_observations_archive_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every episode's final observation comes back, read from one open of the archive, closed at the end (before:
    np.load per read, several per episode, each parsing the whole zip directory: O(episodes^2))."""
    pytest.importorskip("lerobot.datasets.lerobot_dataset")
    from tests.test_lerobot_fidelity import CAMERA, export, fill, import_, spec_of, stored
    from tests.test_lerobot_fidelity import episode as demo_episode

    rng = np.random.default_rng(3)
    arm = spec_of("arm-0", CAMERA)
    episodes = [(arm, demo_episode(arm, f"e{e}", 3, "terminated", rng)) for e in range(6)]
    buffer, out, again = tmp_path / "replay", tmp_path / "ds", tmp_path / "again"
    fill(buffer, episodes)
    assert main(export(buffer, out)) == 0

    opened: list[zipfile.ZipFile] = []
    real = zipfile.ZipFile

    class Counting(real):  # type: ignore[misc,valid-type]
        def __init__(self, file: Any, mode: str = "r", *args: Any, **kw: Any) -> None:
            super().__init__(file, mode, *args, **kw)
            if mode == "r" and str(getattr(file, "name", file)).endswith(FINALS_FILE):  # a path, or np.load's file
                opened.append(self)

    monkeypatch.setattr(zipfile, "ZipFile", Counting)
    assert main(import_(out, again, "--robot-id", "rt")) == 0
    monkeypatch.undo()
    assert len(opened) == 1
    assert opened[0].fp is None  # closed when the import ended
    got, _ = stored(again)
    finals = [s.final_observation for s in got if s.terminated]
    assert finals == [s.final_observation for _, steps in episodes for s in steps if s.terminated]
    assert len(finals) == 6
