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


@pytest.mark.slow
def test_a_learner_killed_mid_run_comes_back_on_its_port_and_resumes_from_its_checkpoint(tmp_path: Path) -> None:
    """Real processes: control, replay, learner, inference and one sim arm. SIGKILL the learner after a
    checkpoint; the supervisor starts it again on the same port, it resumes from the checkpoint (no version
    reused, updates counted on from the checkpoint's) and the arm's new weights keep coming."""
    import os
    import signal

    import grpc

    from tests import helpers
    from user.config import load_config
    from user.rpc import make_channel
    from user.v1 import learner_pb2, learner_pb2_grpc

    config = str(Path(__file__).resolve().parents[1] / "configs" / "demo.yaml")
    overrides = [
        "experiments=[{name: reach, robots: {kinds: [sim_reach_arm]}, algorithm: {kind: sac}}]",
        "edge.mode=fast",
        "learner.min_transitions=100",
        "learner.publish_every=20",
        "learner.checkpoint_every=40",
        "up.edge_agents=1",
    ]
    cfg = load_config(config, overrides)
    stack = Stack(cfg, config, overrides, tmp_path)
    try:
        stack.start()
        learner_child = stack.child("learner")
        port = learner_child.info["grpc_port"]
        stub = learner_pb2_grpc.LearnerStub(make_channel(learner_child.grpc_addr, stack.auth))

        def status(min_version: int) -> learner_pb2.LearnerStatus | None:
            try:
                st = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
            except grpc.RpcError:  # down while it restarts
                return None
            exp = st.experiments[0] if st.experiments else None
            return exp if exp is not None and exp.weight_version >= min_version else None

        helpers.wait_for(lambda: status(4), "weight version 4 (checkpoints every 40 updates)", limit_s=180)
        checkpoints = list((tmp_path / "checkpoints").rglob("*"))
        assert checkpoints, "no checkpoint written before the kill"
        before = status(0)
        os.kill(learner_child.proc.pid, signal.SIGKILL)
        learner_child.proc.wait()
        assert stack.restart_dead(max_restarts=1) is None
        assert learner_child.info["grpc_port"] == port and learner_child.crashes == 1
        after = helpers.wait_for(lambda: status(before.weight_version + 1), "a version after the restart", limit_s=180)
        assert after.updates >= 40, "the restarted learner started from zero instead of its checkpoint"
        assert not [c for c in stack.dead_children() if c is not learner_child]
        os.kill(learner_child.proc.pid, signal.SIGKILL)  # a second death beyond max_restarts stops the run
        learner_child.proc.wait()
        assert stack.restart_dead(max_restarts=1) is learner_child
    finally:
        stack.stop()


# Writes its ready file, then runs until SIGTERM, which it exits on cleanly (as a service does).
SERVE = textwrap.dedent(
    """
    import json, signal, sys, time
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    json.dump({"grpc_port": 1}, open(sys.argv[1], "w"))
    while True:
        time.sleep(1)
    """
)


def test_the_summary_counts_a_child_killed_and_restarted_mid_run(tmp_path: Path) -> None:
    """A kill -9 the supervisor recovered from is not "all clean": the summary names the restart and its code."""
    import os
    import signal

    from user.up import exits_text

    script = tmp_path / "serve.py"
    script.write_text(SERVE)
    ready = tmp_path / "ready.json"
    cmd = [sys.executable, str(script), str(ready)]
    child = Child("worker", None, ready, tmp_path / "worker.log", cmd=cmd)  # type: ignore[arg-type]
    child.launch()
    stack = Stack.__new__(Stack)
    stack.children = [child]
    try:
        stack.wait_ready(child)
        os.kill(child.proc.pid, signal.SIGKILL)
        child.proc.wait()
        assert stack.restart_dead(max_restarts=3) is None
        assert stack.restarts() == {"worker": [-9]}
    finally:
        codes = stack.stop()
    assert codes == {"worker": 0}
    assert exits_text(codes, stack.restarts()) == "worker restarted 1x (exit -9)"
    assert exits_text({"worker": 0, "edge-0": None}, {}) == "all clean"
    assert exits_text({"worker": 1}, {"worker": [-6, -9]}) == "worker restarted 2x (exit -6, -9); worker exited with 1"
