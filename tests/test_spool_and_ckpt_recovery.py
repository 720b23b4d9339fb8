"""A disk that fills for a while under the edge spool or the learner's checkpoints, and two learners on one
checkpoint_dir: recovered from, reported cleanly, or refused. Real filesystems (a small tmpfs, root only) and
real processes; os.statvfs is faked only to move the free disk both ways without root."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from cloud_learner.checkpoint import (
    LATEST,
    OWNER_LOCK,
    CheckpointDirInUse,
    CheckpointWriteError,
    _write_atomic,
    list_checkpoints,
    load_latest,
    lock_checkpoint_dir,
    read_version_mark,
    save_checkpoint,
    sweep_temp_files,
    write_version_mark,
)
from edge_agent.spool import LmdbSpool
from tests.helpers import fill, wait_for
from tests.test_edge_agent import sim_steps
from user import wire
from user.config import ConfigError
from user.v1 import step_pb2

REPO = Path(__file__).resolve().parents[1]


def put_until_paused(spool: LmdbSpool, steps: list, limit: int = 2000) -> list[int]:
    """What the robot loop does: collect while the spool accepts."""
    seqs = []
    while spool.accepting and len(seqs) < limit:
        seqs.append(spool.put(steps[len(seqs) % len(steps)]))
    assert not spool.accepting, f"still accepting after {limit} steps"
    return seqs


# --------------------------------------------------------------------------- the edge spool


def test_a_short_disk_full_pauses_without_losing_a_step_and_resumes_once_space_returns(
    tiny_disk: Callable[[str], Path], caplog: pytest.LogCaptureFixture
) -> None:
    mnt = tiny_disk("512k")
    steps = sim_steps(50)
    spool = LmdbSpool(mnt / "spool", 1 << 30, policy="pause")
    try:
        spool.ack([spool.put(steps[0])])
        filler = fill(mnt)
        seqs = put_until_paused(spool, steps)
        late = big_step("arm-0")  # in progress as the robot paused: kept too, in RAM as the disk has no page for it
        seqs.append(spool.put(late))
        assert spool.dropped == 0 and spool.count == len(seqs)
        assert [r.seq for r in spool.read(0, len(seqs) + 10)] == seqs  # all sendable, in order, RAM or disk
        assert not any("dropping" in r.getMessage() for r in caplog.records)  # pause drops nothing
        assert spool.max_bytes < spool.asked_bytes
        filler.unlink()
        wait_for(lambda: spool.accepting, "the spool to accept again once the disk has room")
        more = spool.put(steps[1])
        assert spool.dropped == 0 and spool.count == len(seqs) + 1
    finally:
        spool.close()
    reopened = LmdbSpool(mnt / "spool", 1 << 30, policy="pause")  # every step reached the disk
    try:
        kept = reopened.read(0, len(seqs) + 10)
        assert [r.seq for r in kept] == [*seqs, more]
        assert [r.step for r in kept[: len(seqs)]] == [*(steps[i % len(steps)] for i in range(len(seqs) - 1)), late]
    finally:
        reopened.close()


def test_acks_on_a_disk_that_stays_full_let_the_spool_accept_again(tiny_disk: Callable[[str], Path]) -> None:
    mnt = tiny_disk("512k")
    steps = sim_steps(50)
    spool = LmdbSpool(mnt / "spool", 1 << 30, policy="pause")
    try:
        for step in steps[:20]:
            spool.put(step)
        fill(mnt)  # and it stays full
        seqs = put_until_paused(spool, steps[20:])
        assert spool.ack([r.seq for r in spool.read(0, 1000)]) == 20 + len(seqs)
        assert spool.accepting and spool.count == 0 and spool.dropped == 0  # its own freed pages hold steps
        spool.put(steps[0])
        assert spool.count == 1 and spool.dropped == 0
    finally:
        spool.close()


def test_drop_oldest_keeps_new_steps_again_once_a_short_disk_full_is_over(tiny_disk: Callable[[str], Path]) -> None:
    mnt = tiny_disk("512k")
    steps = sim_steps(50)
    spool = LmdbSpool(mnt / "spool", 1 << 30, policy="drop_oldest")
    try:
        for step in steps[:10]:
            spool.put(step)
        filler = fill(mnt)
        for step in steps * 4:  # on a full disk drop_oldest drops (counted) and never pauses
            spool.put(step)
            assert spool.accepting
        filler.unlink()
        wait_for(lambda: spool.max_bytes > spool.nbytes + 100 * steps[1].ByteSize(), "the cap to come back")
        count, dropped = spool.count, spool.dropped
        for step in steps:
            spool.put(step)
        assert spool.dropped == dropped and spool.count == count + len(steps)
    finally:
        spool.close()


def big_step(robot_id: str) -> step_pb2.Step:
    """A step no free page of the spool's file holds: on a full disk it cannot be written at all."""
    frame = wire.to_tensor_map({"image": np.zeros(64 << 10, dtype=np.uint8)})
    return step_pb2.Step(robot_id=robot_id, episode_id=f"{robot_id}-ep0", observation=frame)


def test_a_refused_step_waiting_in_ram_is_set_aside_or_dropped_never_holding_the_robots(
    tiny_disk: Callable[[str], Path],
) -> None:
    mnt = tiny_disk("512k")
    spool = LmdbSpool(mnt / "spool", 1 << 30, policy="pause")
    try:
        filler = fill(mnt)
        refused = spool.put(big_step("arm-1"))  # waits in RAM, sendable from there
        assert spool.full and spool.count == 1 and [r.seq for r in spool.read(0, 10)] == [refused]
        assert spool.quarantine([refused]) == 1  # no room to set it aside: dropped, as refused steps go first
        assert spool.count == 0 and spool.dropped == 1 and spool.read(0, 10) == []
        kept = spool.put(big_step("arm-2"))
        filler.unlink()
        assert spool.quarantine([kept]) == 1  # room now: set aside on disk
        assert spool.count == 0 and spool.quarantined == 1 and spool.dropped == 1
        wait_for(lambda: spool.accepting, "the spool to accept again")
    finally:
        spool.close()
    reopened = LmdbSpool(mnt / "spool", 1 << 30, policy="pause")  # tried again at the next open
    try:
        assert [(r.seq, r.step.robot_id) for r in reopened.read(0, 10)] == [(kept, "arm-2")]
    finally:
        reopened.close()


class FakeStatvfs:
    """What os.statvfs reports, with the free blocks a test sets."""

    def __init__(self, free: int) -> None:
        self.f_frsize = self.f_bsize = 4096
        self.f_blocks = 1 << 30
        self.set_free(free)

    def set_free(self, free: int) -> None:
        self.f_bavail = self.f_bfree = free // 4096


def test_the_cap_follows_the_free_disk_both_ways_up_to_the_configured_cap(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = FakeStatvfs(free=1 << 20)
    monkeypatch.setattr(os, "statvfs", lambda path: disk)
    steps = sim_steps(5)
    spool = LmdbSpool(tmp_path / "spool", 4 << 20, policy="pause")
    try:
        assert 256 << 10 < spool.max_bytes < 768 << 10  # about half of the 1 MiB free (plus its file's free pages)
        spool.put(steps[0])
        disk.set_free(0)  # another process filled the disk: the spool pauses before its writes fail
        wait_for(lambda: not spool.accepting, "the cap to drop to what the spool holds")
        assert spool.count == 1 and spool.max_bytes >= spool.nbytes  # never below what it holds
        disk.set_free(100 << 20)  # freed: back, but never past the configured 4 MiB
        wait_for(lambda: spool.max_bytes == 4 << 20, "the cap to come back up to the configured one")
        assert spool.accepting
    finally:
        spool.close()


# --------------------------------------------------------------------------- one learner per checkpoint_dir


def _python(code: str, **kwargs: object) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, text=True, **kwargs)  # type: ignore[call-overload]


def test_a_checkpoint_dir_has_one_learner_at_a_time(tmp_path: Path) -> None:
    lock = lock_checkpoint_dir(tmp_path)
    with pytest.raises(CheckpointDirInUse) as refused:  # a second lock, even in this process
        lock_checkpoint_dir(tmp_path)
    assert str(refused.value) == f"learner.checkpoint_dir {tmp_path} is in use by pid {os.getpid()}"
    assert isinstance(refused.value, ConfigError)  # `userctl learner` prints it in one line, exit 2
    other = _python(
        f"from cloud_learner.checkpoint import lock_checkpoint_dir; lock_checkpoint_dir({str(tmp_path)!r})",
        stderr=subprocess.PIPE,
    )
    _, err = other.communicate(timeout=120)
    assert other.returncode != 0 and f"is in use by pid {os.getpid()}" in err
    lock.release()
    with lock_checkpoint_dir(tmp_path):  # free again once released
        pass


def test_the_lock_goes_with_a_learner_killed_9(tmp_path: Path) -> None:
    holder = _python(
        f"""
        import time
        from cloud_learner.checkpoint import lock_checkpoint_dir
        lock = lock_checkpoint_dir({str(tmp_path)!r})
        time.sleep(3600)
        """
    )
    try:
        lock_file = tmp_path / OWNER_LOCK
        wait_for(
            lambda: lock_file.is_file() and lock_file.read_text().strip() == str(holder.pid), "the child's lock", 120
        )
        with pytest.raises(CheckpointDirInUse, match=f"in use by pid {holder.pid}$"):
            lock_checkpoint_dir(tmp_path)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    lock_checkpoint_dir(tmp_path).release()


# --------------------------------------------------------------------------- temp files a killed writer left


def test_the_sweep_removes_a_killed_writers_temp_files_and_nothing_else(tmp_path: Path) -> None:
    exp = tmp_path / "reach"
    save_checkpoint(exp, {"updates": 1})
    write_version_mark(exp, 4)
    writer = _python(  # killed in the middle of writing a checkpoint
        f"""
        import time
        from pathlib import Path
        from cloud_learner.checkpoint import _write_atomic
        def write(f):
            f.write(b"x" * 65536)
            f.flush()
            time.sleep(3600)
        _write_atomic(Path({str(exp)!r}) / "ckpt-000000002.pt", write)
        """
    )
    try:
        wait_for(lambda: list(exp.glob(".ckpt-000000002.pt.*.tmp")), "the writer's temp file", 120)
    finally:
        writer.send_signal(signal.SIGKILL)
        writer.wait()
    ours = [*exp.glob(".ckpt-000000002.pt.*.tmp"), exp / ".weight_version.4242.tmp", tmp_path / ".latest.ab_c12yz.tmp"]
    (exp / ".weight_version.4242.tmp").write_text("5\n")  # an older build's version-mark temp
    (tmp_path / ".latest.ab_c12yz.tmp").write_text("ckpt-000000002.pt\n")
    others = [
        exp / "ckpt-000000030.pt.tmp",
        exp / ".ckpt-000000020.pt.abc123.tmp",  # not mkstemp's 8 characters
        exp / ".latest.abcdefgh.tmp.bak",
        exp / "notes.tmp",
        exp / ".weight_version.tmp",
        tmp_path / ".other.abcdefgh.tmp",
    ]
    for path in others:
        path.write_text("not ours")
    (exp / ".weight_version.abcdefgh.tmp").mkdir()  # a directory is never ours
    assert sorted(sweep_temp_files(tmp_path)) == sorted(ours)
    assert all(p.exists() for p in others) and (exp / ".weight_version.abcdefgh.tmp").is_dir()
    assert load_latest(exp)["updates"] == 1 and read_version_mark(exp) == 4
    assert sweep_temp_files(tmp_path / "missing") == []


# --------------------------------------------------------------------------- a save the disk refuses


def _no_temp_files(path: Path) -> bool:
    return not [p.name for p in path.iterdir() if p.name.endswith(".tmp")]


def test_a_full_disk_fails_a_save_cleanly_and_the_previous_checkpoint_stays(tiny_disk: Callable[[str], Path]) -> None:
    exp = tiny_disk("256k") / "reach"
    save_checkpoint(exp, {"updates": 1, "w": torch.zeros(1000)})
    write_version_mark(exp, 3)
    with pytest.raises(CheckpointWriteError) as failed:
        save_checkpoint(exp, {"updates": 2, "w": torch.zeros(200_000)})  # 800 kB
    assert failed.value.errno == errno.ENOSPC and failed.value.path == exp / "ckpt-000000002.pt"
    assert _no_temp_files(exp) and list_checkpoints(exp) == [exp / "ckpt-000000001.pt"]
    assert (exp / LATEST).read_text().strip() == "ckpt-000000001.pt" and load_latest(exp)["updates"] == 1
    filler = fill(exp.parent)
    with pytest.raises(CheckpointWriteError) as failed:
        write_version_mark(exp, 4)
    assert failed.value.errno == errno.ENOSPC and _no_temp_files(exp) and read_version_mark(exp) == 3
    filler.unlink()  # room again: the next try succeeds
    write_version_mark(exp, 4)
    save_checkpoint(exp, {"updates": 2, "w": torch.zeros(1000)})
    assert load_latest(exp)["updates"] == 2 and read_version_mark(exp) == 4


def test_a_write_limit_fails_a_save_cleanly_without_root(tmp_path: Path) -> None:
    """RLIMIT_FSIZE makes the kernel refuse the write (EFBIG) as a full disk would, in a child of its own."""
    child = _python(
        f"""
        import errno, resource, signal, sys, torch
        from pathlib import Path
        from cloud_learner.checkpoint import CheckpointWriteError, load_latest, save_checkpoint
        exp = Path({str(tmp_path)!r})
        save_checkpoint(exp, {{"updates": 1, "w": torch.zeros(1000)}})
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, resource.RLIM_INFINITY))
        try:
            save_checkpoint(exp, {{"updates": 2, "w": torch.zeros(200_000)}})
        except CheckpointWriteError as exc:
            assert exc.errno == errno.EFBIG and exc.path == exp / "ckpt-000000002.pt", exc
            print("refused", load_latest(exp)["updates"])
        """,
        stdout=subprocess.PIPE,
    )
    out, _ = child.communicate(timeout=120)
    assert child.returncode == 0 and out.strip() == "refused 1"
    assert _no_temp_files(tmp_path) and list_checkpoints(tmp_path) == [tmp_path / "ckpt-000000001.pt"]


def test_a_failed_write_removes_its_temp_file(tmp_path: Path) -> None:
    def broken(f: object) -> None:
        raise OSError(errno.EIO, "Input/output error")

    with pytest.raises(CheckpointWriteError) as failed:
        _write_atomic(tmp_path / "latest", broken)
    assert failed.value.errno == errno.EIO and list(tmp_path.iterdir()) == []
