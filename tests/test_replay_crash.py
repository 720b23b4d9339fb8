"""kill -9 of a real replay process mid-stream, restart, re-send: exactly N stored, nothing acked lost."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import grpc

from services.replay.store import ReplayStore
from tests.helpers import wait_for
from tests.test_replay_store import episode, spec
from user.config import AuthConfig
from user.rpc import make_channel
from user.v1 import replay_pb2, replay_pb2_grpc

ROOT = Path(__file__).resolve().parents[1]
AUTH = AuthConfig(token="crash-token")
N_EPISODES, LENGTH = 16, 50  # 800 steps


def start_replay(path: Path, ready: Path) -> tuple[subprocess.Popen, int]:
    ready.unlink(missing_ok=True)
    args = [
        sys.executable, "-m", "user.cli", "replay", "--ready-file", str(ready),
        "--set", f"replay.path={path}", "--set", "replay.server.port=0", "--set", "replay.server.metrics_port=0",
        "--set", "replay.control_addr=127.0.0.1:9", "--set", "replay.rpc_timeout_s=0.5",
        "--set", "replay.commit_max_steps=32", "--set", f"auth.token={AUTH.token}", "--set", "replay.map_size_mb=64",
    ]  # fmt: skip
    proc = subprocess.Popen(args, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    wait_for(lambda: ready.exists() and ready.read_text().strip(), "replay ready file", limit_s=60)
    return proc, int(json.loads(ready.read_text())["grpc_port"])


def test_kill_9_mid_stream_then_restart_stores_exactly_n(tmp_path: Path) -> None:
    path, ready = tmp_path / "replay", tmp_path / "ready.json"
    seed = ReplayStore(path, 64)  # control is unreachable: replay validates with the spec it persisted
    seed.put_spec(spec("arm-0"))
    seed.close()
    steps = [s for e in range(N_EPISODES) for s in episode("arm-0", f"e{e}", LENGTH)]
    proc, port = start_replay(path, ready)
    acked: set[int] = set()
    killed = threading.Event()

    def requests():
        for i, s in enumerate(steps):
            if i == len(steps) // 2:
                killed.wait(60)  # the second half is sent only after the kill: it lands mid-stream
            yield replay_pb2.InsertRequest(seq=i, step=s)

    def stream() -> None:
        stub = replay_pb2_grpc.ReplayStub(make_channel(f"127.0.0.1:{port}", AUTH))
        try:
            for ack in stub.Insert(requests(), timeout=60):
                acked.update(ack.seqs)
        except grpc.RpcError:
            pass  # the server died under us

    t = threading.Thread(target=stream)
    t.start()
    wait_for(lambda: len(acked) >= len(steps) // 4, "a quarter acknowledged", limit_s=60)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    killed.set()
    t.join(timeout=60)
    assert 0 < len(acked) < len(steps)

    proc, port = start_replay(path, ready)
    try:
        stub = replay_pb2_grpc.ReplayStub(make_channel(f"127.0.0.1:{port}", AUTH))
        kept = stub.Stats(replay_pb2.StatsRequest(), timeout=10).steps
        assert kept >= len(acked)  # every acknowledged step survived the kill
        # the edge re-sends what was not acknowledged (here: everything, to test idempotency too)
        resend = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]
        acks = list(stub.Insert(iter(resend), timeout=60))
        assert sorted(s for a in acks for s in a.seqs) == list(range(len(steps)))
        assert sum(a.stored for a in acks) == len(steps) - kept
        st = stub.Stats(replay_pb2.StatsRequest(), timeout=10)
        assert (st.steps, st.transitions, st.episodes) == (len(steps), len(steps), N_EPISODES)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
