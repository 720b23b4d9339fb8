"""`userctl up` caps each child's log (up.log_max_mb): past the cap it is copied to <log>.1 and emptied while the
child keeps writing to it, so a run of days keeps at most twice the cap per child."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

from tests.helpers import wait_for
from user.up import Child, Stack

# Writes numbered 100-byte lines until its stop file appears.
WRITER = textwrap.dedent(
    """
    import os, sys, time
    stop, i = sys.argv[1], 0
    while not os.path.exists(stop):
        sys.stdout.write(f"{i:09d} " + "x" * 89 + "\\n"); sys.stdout.flush(); i += 1
        time.sleep(0.0005)
    """
)


def test_a_child_log_past_the_cap_is_kept_once_and_written_on_from_the_start(tmp_path: Path) -> None:
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    log_path, stop = tmp_path / "writer.log", tmp_path / "stop"
    child = Child("writer", None, tmp_path / "ready", log_path, cmd=[sys.executable, str(script), str(stop)])  # type: ignore[arg-type]
    child.launch()
    stack = Stack.__new__(Stack)
    stack.children = [child]
    try:
        wait_for(lambda: log_path.stat().st_size > 20_000, "the log passes the cap")
        stack.cap_logs(20_000)
        kept = (tmp_path / "writer.log.1").read_bytes()
        assert len(kept) > 20_000 and kept.startswith(b"000000000 ")
        wait_for(lambda: log_path.read_bytes().count(b"\n") >= 3, "the child writes on")
        stack.cap_logs(20_000)  # under the cap: nothing happens
        assert (tmp_path / "writer.log.1").read_bytes() == kept
    finally:
        stop.touch()
        child.proc.wait(10)
    after = log_path.read_bytes()
    assert b"\0" not in after and len(after) < len(kept) + 20_000  # appended from 0, not a sparse file at the old end
    numbers = [int(line.split()[0]) for line in after.splitlines()[1:]]  # the first may be cut by the truncate
    assert numbers == sorted(numbers) and numbers[0] > int(kept.splitlines()[-1].split()[0])


def test_a_cap_of_0_never_touches_the_log(tmp_path: Path) -> None:
    log_path = tmp_path / "a.log"
    log_path.write_bytes(b"x" * 1000)
    stack = Stack.__new__(Stack)
    stack.children = [Child("a", None, tmp_path / "ready", log_path)]  # type: ignore[arg-type]
    stack.cap_logs(0)
    assert log_path.stat().st_size == 1000 and not (tmp_path / "a.log.1").exists()
