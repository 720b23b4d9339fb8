"""The `userctl up` supervisor starts a child again when a signal kills it while it starts (a native library
aborting), and still reports a child that fails on its own or keeps crashing."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from user.up import START_RESTARTS, Child, Stack

# Aborts (SIGABRT) until it has started `crashes` times, then writes its ready file.
SCRIPT = textwrap.dedent(
    """
    import json, os, signal, sys
    counter, ready, crashes = sys.argv[1], sys.argv[2], int(sys.argv[3])
    n = int(open(counter).read()) if os.path.exists(counter) else 0
    open(counter, "w").write(str(n + 1))
    if n < crashes:
        os.kill(os.getpid(), signal.SIGABRT)
    if crashes < 0:
        sys.exit(3)
    json.dump({"grpc_port": 1}, open(ready, "w"))
    """
)


def _child(tmp_path: Path, crashes: int) -> Child:
    script = tmp_path / "child.py"
    script.write_text(SCRIPT)
    ready = tmp_path / "ready.json"
    cmd = [sys.executable, str(script), str(tmp_path / "starts"), str(ready), str(crashes)]
    child = Child("worker", None, ready, tmp_path / "worker.log", cmd=cmd)  # type: ignore[arg-type]
    child.launch()
    return child


def _starts(tmp_path: Path) -> int:
    return int((tmp_path / "starts").read_text())


def test_a_child_killed_while_starting_is_started_again(tmp_path: Path) -> None:
    child = _child(tmp_path, crashes=1)
    Stack._wait_ready(Stack.__new__(Stack), child)
    assert child.info == {"grpc_port": 1} and child.restarts == 1 and _starts(tmp_path) == 2


def test_a_child_that_keeps_crashing_is_reported(tmp_path: Path) -> None:
    child = _child(tmp_path, crashes=START_RESTARTS + 5)
    with pytest.raises(RuntimeError, match="worker exited with -6"):
        Stack._wait_ready(Stack.__new__(Stack), child)
    assert _starts(tmp_path) == START_RESTARTS + 1


def test_a_child_that_exits_with_an_error_is_not_restarted(tmp_path: Path) -> None:
    child = _child(tmp_path, crashes=-1)  # a config error, say: exit 3, no signal
    with pytest.raises(RuntimeError, match="worker exited with 3"):
        Stack._wait_ready(Stack.__new__(Stack), child)
    assert _starts(tmp_path) == 1
