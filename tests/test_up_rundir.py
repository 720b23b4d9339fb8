"""`userctl up`'s run directory: one supervisor at a time (a flock, gone with its process), the generated token
for operators' commands, and a resumed run's report covering this session only."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from services.control.server import ControlService
from user.cli import main
from user.config import AuthConfig, StackConfig
from user.up import (
    LOCK_FILE,
    Monitor,
    RunDirBusy,
    Stack,
    _report_title,
    _summary,
    lock_run_dir,
    ops_target,
    run_up,
    write_report,
)
from user.v1 import control_pb2

HOLDER = (
    "import sys; from pathlib import Path; from user.up import lock_run_dir; "
    "lock_run_dir(Path(sys.argv[1])); print('locked', flush=True); sys.stdin.read()"
)


def _cfg(runs_dir: Path) -> StackConfig:
    cfg = StackConfig()
    cfg.up.runs_dir = runs_dir
    return cfg


def _tree(root: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under root with its content and mtime: what `touching nothing` must leave as it was."""
    return {str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}


@pytest.fixture
def holder(tmp_path: Path):
    """Another process holding tmp_path/runs/demo, as a running `userctl up` does."""
    run_dir = tmp_path / "runs" / "demo"
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(run_dir)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    yield proc
    proc.kill()
    proc.wait()


def test_a_second_up_refuses_a_held_run_dir_and_touches_nothing(tmp_path: Path, holder, capsys) -> None:
    run_dir = tmp_path / "runs" / "demo"
    (run_dir / "checkpoints" / "reach").mkdir(parents=True)
    (run_dir / "checkpoints" / "reach" / "latest").write_text("ckpt-7")
    (run_dir / "ready").mkdir()
    (run_dir / "ready" / "control.json").write_text('{"grpc_port": 4242}')
    (run_dir / "control.sqlite").write_bytes(b"live")
    before = _tree(run_dir)
    for fresh in (False, True):  # --fresh must not delete a live run's data either
        assert run_up(_cfg(tmp_path / "runs"), None, [], fresh=fresh) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(run_dir) in err and f"pid {holder.pid}" in err, err
    assert _tree(run_dir) == before


def test_the_lock_goes_with_its_holder_even_on_kill_9(tmp_path: Path, holder) -> None:
    run_dir = tmp_path / "runs" / "demo"
    with pytest.raises(RunDirBusy, match=f"pid {holder.pid}"):
        lock_run_dir(run_dir)
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    fd = lock_run_dir(run_dir)
    try:
        assert (run_dir / LOCK_FILE).read_text().strip() == str(os.getpid())
        with pytest.raises(RunDirBusy):  # a second open of the same file in one process conflicts too
            lock_run_dir(run_dir)
    finally:
        os.close(fd)


def test_the_generated_token_is_written_0600_and_found_by_ops_commands(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("USER_TOKEN", raising=False)
    cfg = _cfg(tmp_path / "runs")
    run_dir = tmp_path / "runs" / "demo"
    stack = Stack(cfg, None, [], run_dir)
    token = stack.env["USER_TOKEN"]
    assert stack.token_path == run_dir / "token"
    assert stat.S_IMODE(stack.token_path.stat().st_mode) == 0o600
    assert stack.token_path.read_text().strip() == token
    (run_dir / "ready").mkdir()
    (run_dir / "ready" / "control.json").write_text('{"grpc_port": 4242}')
    # No `up` holds the run dir: nothing of it is used (a finished run's files are not a live control).
    assert ops_target(cfg, None) == (cfg.edge.control_addr, cfg.auth)
    fd = lock_run_dir(run_dir)
    try:
        for control in (None, "127.0.0.1:4242", "localhost:4242"):
            target, auth = ops_target(cfg, control)
            assert target == (control or "127.0.0.1:4242") and auth.token == token
        assert ops_target(cfg, "cloud.example.org:50051")[1].token is None  # another control gets no run token
        monkeypatch.setenv("USER_TOKEN", "configured")
        assert ops_target(cfg, None)[1].token is None  # a configured token wins ($USER_TOKEN, resolved later)
    finally:
        os.close(fd)


def test_ops_commands_talk_to_a_running_up_with_its_token(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.delenv("USER_TOKEN", raising=False)
    run_dir = tmp_path / "runs" / "demo"
    fd = lock_run_dir(run_dir)
    cfg = StackConfig(auth=AuthConfig(token="per-run-secret"))
    cfg.control.server.port = 0
    service = ControlService(cfg, start_metrics=False).start()
    try:
        (run_dir / "ready").mkdir()
        (run_dir / "ready" / "control.json").write_text(json.dumps({"grpc_port": int(service.address.split(":")[1])}))
        argv = ["robots", "ls", "--set", f"up.runs_dir={tmp_path / 'runs'}"]
        assert main(argv) == 2  # no token configured and none written: a one-line error
        assert capsys.readouterr().err.startswith("userctl robots: auth.token")
        (run_dir / "token").write_text("per-run-secret\n")
        assert main(argv) == 0, capsys.readouterr().err
    finally:
        service.stop()
        os.close(fd)


def _episode(robot: str, episode_id: str, ended_at_ns: int, success: bool) -> control_pb2.EpisodeSummary:
    return control_pb2.EpisodeSummary(robot_id=robot, episode_id=episode_id, ended_at_ns=ended_at_ns, success=success)


def test_a_resumed_run_reports_this_session_and_counts_earlier_episodes(tmp_path: Path) -> None:
    session_start_ns = 2_000_000_000_000
    mon = object.__new__(Monitor)  # no stack: only its episode bookkeeping is used
    mon.episodes, mon.earlier, mon.session_start_ns = {}, set(), session_start_ns
    earlier = [_episode("arm-0", f"old{i}", session_start_ns - 10**9 * (5 - i), True) for i in range(5)]
    now = [_episode("arm-0", f"new{i}", session_start_ns + 10**9 * i, i == 1) for i in range(2)]
    info = control_pb2.RobotInfo(experiment="reach", recent_episodes=[*earlier, *now])
    mon.record_episodes([info], now=3.0)
    mon.record_episodes([info], now=4.0)  # seen again on the next poll: counted once
    assert [e.episode_id for e in mon.ordered()] == ["new0", "new1"] and len(mon.earlier) == 5
    assert mon.success_rate(2, "reach") == 0.5  # the earlier run's successes do not reach this session's target
    assert mon.success_rate(3, "reach") is None
    cfg = _cfg(tmp_path)
    summary = _summary(cfg, "budget exhausted", None, None, mon.ordered(), {}, 10.0, earlier_episodes=5)
    write_report(tmp_path, mon.ordered(), summary, window=2)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert len(doc["episodes"]) == 2 and doc["earlier_episodes"] == 5
    assert "5 episodes of earlier runs not shown" in _report_title({**summary, "time_to_target_s": 12.0})
    assert (tmp_path / "report.png").exists()
