"""`userctl replay import|export` refusals: a root that holds no dataset (never fetched from the hub), a buffer
a running replay service holds, a table name the config would refuse; and what a re-import really adds.

Real LMDB in tmp dirs, real LeRobotDatasets made by lerobot's own writer, a real replay service in-process."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest

from services.replay.server import ReplayService
from services.replay.store import HOLDER_FILE, ReplayStore, buffer_holder, hold_buffer, release_buffer
from tests.test_replay_lerobot import EPISODES, make_dataset
from tests.test_replay_service import _cfg, stub
from user.cli import main
from user.config import ConfigError
from user.v1 import replay_pb2

pytest.importorskip("lerobot.datasets.lerobot_dataset")

FRAMES = sum(EPISODES)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("datasets") / "made"
    make_dataset(root)
    return root


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every name lookup and connect of this process fails (and is recorded): no test may reach the hub, even
    where the code under test would try."""
    tries: list[str] = []

    def refuse(*args: Any, **kwargs: Any) -> Any:
        tries.append(repr(args[:2]))
        raise OSError("network blocked by the test")

    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    return tries


def import_args(root: Path, buffer: Path, *extra: str) -> list[str]:
    return ["replay", "import", str(root), "--repo-id", "local/made", "--path", str(buffer), *extra]


def stored_steps(buffer: Path) -> int:
    store = ReplayStore(buffer, cache_mb=0, readonly=True)
    try:
        return int(store.stats()["steps"])
    finally:
        store.close()


# --------------------------------------------------------------------------- a root without a dataset


@pytest.mark.parametrize("kind", ["missing", "empty", "file"])
def test_import_of_a_root_without_a_dataset_is_one_line_and_creates_nothing(
    tmp_path: Path, kind: str, no_network: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "x" / "nothere"
    if kind == "empty":
        root.mkdir(parents=True)
    if kind == "file":
        root.parent.mkdir(parents=True)
        root.write_text("not a dataset")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert main(import_args(root, tmp_path / "x" / "rep")) == 2
    err = capsys.readouterr().err
    reason = {"missing": "no such directory", "empty": "meta/info.json missing", "file": "not a directory"}[kind]
    assert err == f"userctl replay import: no LeRobotDataset at {root} ({reason})\n"
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # no root, no buffer
    assert no_network == []


def test_import_of_an_incomplete_dataset_never_asks_the_hub(
    dataset: Path, tmp_path: Path, no_network: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """meta/ is there but the frames are not: lerobot would fetch them (from `local/made` on the hub)."""
    from huggingface_hub import constants

    root = tmp_path / "partial"
    shutil.copytree(dataset, root)
    shutil.rmtree(root / "data")
    offline_before = constants.HF_HUB_OFFLINE
    capsys.readouterr()
    assert main(import_args(root, tmp_path / "rep")) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"userctl replay import: the LeRobotDataset at {root} is incomplete"), last
    assert no_network == []  # refused before any lookup, not by the blocked socket
    assert offline_before == constants.HF_HUB_OFFLINE  # the offline switch was set only around our calls
    assert not (tmp_path / "rep").exists() and not (root / "data").exists()


# --------------------------------------------------------------------------- a buffer a replay service holds


def test_import_into_a_buffer_a_running_service_holds_is_refused(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    buffer = tmp_path / "replay"
    service = ReplayService(_cfg(buffer), spec_source=lambda robot: None, start_metrics=False).start()
    try:
        capsys.readouterr()
        assert main(import_args(dataset, buffer)) == 2
        err = capsys.readouterr().err
        assert err == (
            f"userctl replay import: the buffer {buffer} is held by the replay service (pid {os.getpid()}), "
            "whose index would never see imported steps: stop it, import, then start it again "
            "(or import into another --path)\n"
        )
        request = replay_pb2.SampleRequest(batch_size=1, tables={"demos": 1})
        with pytest.raises(grpc.RpcError) as failed:
            stub(service).Sample(request, timeout=10)
        assert failed.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    finally:
        service.stop()
    assert stored_steps(buffer) == 0  # nothing written behind the service

    # stopped: the service let go of the buffer, the import goes in, and the next service samples it
    assert main(import_args(dataset, buffer)) == 0
    assert f"import: {len(EPISODES)} episodes, {FRAMES} frames -> {buffer}\n" in capsys.readouterr().out
    service = ReplayService(_cfg(buffer), spec_source=lambda robot: None, start_metrics=False).start()
    try:
        sampled = stub(service).Sample(replay_pb2.SampleRequest(batch_size=4, tables={"demos": 1}), timeout=10)
        assert list(sampled.batch.action.shape) == [4, 2] and sampled.table_transitions["demos"] == FRAMES
    finally:
        service.stop()


def test_a_service_does_not_start_on_a_buffer_another_process_holds(tmp_path: Path) -> None:
    buffer = tmp_path / "replay"
    fd = hold_buffer(buffer, "`userctl replay import`")
    try:
        with pytest.raises(ConfigError, match=r"replay\.path: .* is held by `userctl replay import` \(pid \d+\)"):
            ReplayService(_cfg(buffer), spec_source=lambda robot: None, start_metrics=False)
        assert not (buffer / "data.mdb").exists()  # refused before LMDB was opened
    finally:
        release_buffer(fd)
    ReplayService(_cfg(buffer), spec_source=lambda robot: None, start_metrics=False).start().stop()


def test_a_killed_holder_leaves_no_stale_hold(tmp_path: Path) -> None:
    buffer = tmp_path / "replay"
    code = (
        "import sys, time; from services.replay.store import hold_buffer; "
        "hold_buffer(sys.argv[1], 'the replay service'); print('held', flush=True); time.sleep(600)"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code, str(buffer)], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parents[1]
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        assert buffer_holder(buffer) == f"the replay service (pid {holder.pid})"
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    assert buffer_holder(buffer) is None and (buffer / HOLDER_FILE).exists()
    release_buffer(hold_buffer(buffer, "test"))


# --------------------------------------------------------------------------- what a re-import adds


def test_a_second_import_reports_that_nothing_new_was_stored(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    buffer = tmp_path / "replay"
    assert main(import_args(dataset, buffer)) == 0
    first = capsys.readouterr().out
    assert first == f"import: {len(EPISODES)} episodes, {FRAMES} frames -> {buffer}\n"
    assert main(import_args(dataset, buffer)) == 0
    again = capsys.readouterr().out
    assert again == (
        f"import: 0 episodes, 0 frames -> {buffer} "
        f"(already there, not stored again: {len(EPISODES)} episodes, {FRAMES} frames)\n"
    )
    assert stored_steps(buffer) == FRAMES
    # the same frames under another robot id are new steps
    assert main(import_args(dataset, buffer, "--robot-id", "other")) == 0
    assert capsys.readouterr().out == f"import: {len(EPISODES)} episodes, {FRAMES} frames -> {buffer}\n"
    assert stored_steps(buffer) == 2 * FRAMES


# --------------------------------------------------------------------------- table names


@pytest.mark.parametrize("table", ["a b", "", "x" * 65, "demos\n", "dé"])
def test_import_refuses_a_table_name_the_config_refuses(
    dataset: Path, tmp_path: Path, table: str, capsys: pytest.CaptureFixture[str]
) -> None:
    buffer = tmp_path / "replay"
    assert main(import_args(dataset, buffer, "--table", table)) == 2
    err = capsys.readouterr().err
    assert err == f"userctl replay import: table {table[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . -\n"
    assert not buffer.exists()


def test_export_refuses_a_table_name_the_config_refuses(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    buffer = tmp_path / "replay"
    assert main(import_args(dataset, buffer)) == 0
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["replay", "export", str(out), "--repo-id", "local/x", "--path", str(buffer), "--table", "a b"]) == 2
    err = capsys.readouterr().err
    assert err == "userctl replay export: table 'a b' must be 1-64 characters of A-Z a-z 0-9 _ . -\n"
    assert not out.exists()


@pytest.fixture(autouse=True)
def _hub_stays_online_outside_our_calls() -> Iterator[None]:
    from huggingface_hub import constants

    before = constants.HF_HUB_OFFLINE
    yield
    assert before == constants.HF_HUB_OFFLINE
