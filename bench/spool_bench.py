"""Edge outbox: kill -9 of the edge during a replay outage, ours (LMDB spool) vs a naive in-memory outbox.

Both sides run the same scenario with the real edge agent as a process (sim arm, fast mode, held
actions: no policy is needed to count steps), real Control and Replay servers on 127.0.0.1:

  1. online: the edge streams steps to replay;
  2. outage: replay stops; the edge keeps collecting;
  3. control PAUSEs the robot, so the count of collected steps is exact (heartbeats settle);
  4. kill -9 of the edge;
  5. replay comes back (same LMDB dir) and the edge restarts (same agent id and spool dir), collects
     a little more and stops with SIGTERM (flushes; its final heartbeat gives its exact count).

Then every step collected in both lives is either stored in replay or lost: lost = collected - stored.
Replay keys steps by (robot, episode, step), so a step can never be stored twice; re-sends it
deduplicated are counted. The peer is the same agent with `edge.spool_dir: null` (RAM outbox, the
behaviour before the spool). A micro-benchmark adds the price of durability: one put per step.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench import Row, median
from edge_agent.spool import LmdbSpool, MemoryOutbox, Outbox
from services.control.server import ControlService
from services.replay.server import ReplayService
from user import wire
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, step_pb2

PEER_NAME = "in-memory outbox (spool_dir: null)"
TOKEN = "bench-token"
ROBOT = "arm-0"
AGENT = "edge-bench"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(predicate: Callable[[], Any], what: str, limit_s: float = 120.0) -> Any:
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise RuntimeError(f"spool bench: timed out waiting for {what}")


class Scenario:
    """Control (in-process), replay (in-process, restartable on a fixed port and dir), edge processes."""

    def __init__(self, workdir: Path, spool: bool) -> None:
        self.workdir = workdir
        self.spool = spool
        cfg = StackConfig(auth=AuthConfig(token=TOKEN))
        for section in (cfg.control, cfg.replay):
            section.server.metrics_port = 0
            section.server.grace_s = 0.5
        cfg.control.server.port = 0
        cfg.control.heartbeat_interval_s = 0.1
        cfg.replay.server.port = _free_port()
        cfg.replay.path = workdir / "replay"
        cfg.replay.map_size_mb = 256
        cfg.replay.commit_max_delay_ms = 5.0
        self.cfg = cfg
        self.control = ControlService(cfg, start_metrics=False).start()
        cfg.replay.control_addr = self.control.address
        self.replay_addr = f"127.0.0.1:{cfg.replay.server.port}"
        self.replay: ReplayService | None = None
        auth = AuthConfig(token=TOKEN)
        self._control_stub = control_pb2_grpc.ControlStub(make_channel(self.control.address, auth))
        self._replay_stub = replay_pb2_grpc.ReplayStub(make_channel(self.replay_addr, auth))
        self.edge: subprocess.Popen | None = None
        self._lives = 0

    # ------------------------------------------------------------------ parts

    def replay_up(self) -> None:
        self.replay = ReplayService(self.cfg, start_metrics=False).start()

    def replay_down(self) -> None:
        if self.replay is not None:
            self.replay.stop()
            self.replay = None

    def edge_up(self) -> None:
        self._lives += 1
        ready = self.workdir / f"edge-{self._lives}.json"
        overrides = {
            "auth.token": TOKEN,
            "log_level": "WARNING",
            "edge.agent_id": AGENT,
            "edge.mode": "fast",
            "edge.metrics_port": 0,
            "edge.control_addr": self.control.address,
            "edge.replay_addr": self.replay_addr,
            "edge.inference_addr": f"127.0.0.1:{_free_port()}",  # no policy: held steps, counted all the same
            "edge.action_deadline_ms": 2,
            "edge.spool_dir": str(self.workdir / "spool") if self.spool else "null",
            "edge.robots": json.dumps([{"id": ROBOT, "kind": "sim_reach_arm", "params": {"max_episode_steps": 50}}]),
        }
        cmd = [sys.executable, "-m", "user.cli", "edge", "--ready-file", str(ready)]
        for key, value in overrides.items():
            cmd += ["--set", f"{key}={value}"]
        root = str(Path(__file__).resolve().parents[1])
        env = {**os.environ, "PYTHONPATH": root, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        self.edge = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=root)
        _wait(lambda: ready.exists() or self.edge.poll() is not None, "the edge to start")
        if self.edge.poll() is not None:
            raise RuntimeError("spool bench: the edge process died at start")

    def robot(self) -> control_pb2.RobotInfo | None:
        req = control_pb2.ListRobotsRequest(include_offline=True)
        robots = self._control_stub.ListRobots(req, timeout=5).robots
        return next((r for r in robots if r.spec.robot_id == ROBOT), None)

    def env_steps(self) -> int:
        info = self.robot()
        return int(info.status.env_steps) if info else 0

    def stored(self) -> replay_pb2.StatsResponse:
        return self._replay_stub.Stats(replay_pb2.StatsRequest(), timeout=5)

    def pause_and_count(self) -> int:
        """PAUSE the robot and return its step count once three heartbeats agree."""
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE)
        self._control_stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5)
        beats: dict[int, int] = {}

        def settled() -> int | None:
            info = self.robot()
            if info is None or info.status.state != control_pb2.ROBOT_STATE_PAUSED:
                return None
            beats[info.last_heartbeat_ns] = info.status.env_steps
            last = [beats[k] for k in sorted(beats)[-3:]]
            return last[0] if len(last) == 3 and len(set(last)) == 1 else None

        return _wait(settled, "the paused robot's count to settle")

    def close(self) -> None:
        if self.edge is not None and self.edge.poll() is None:
            self.edge.kill()
            self.edge.wait()
        self.replay_down()
        self.control.stop()

    # ------------------------------------------------------------------ the scenario

    def run(self, online: int, outage: int, after: int) -> dict[str, Any]:
        self.replay_up()
        self.edge_up()
        _wait(lambda: self.stored().steps >= online, "steps to reach replay")
        self.replay_down()
        outage_start = self.env_steps()
        _wait(lambda: self.env_steps() >= outage_start + outage, "steps collected during the outage")
        first_life = self.pause_and_count()
        assert self.edge is not None
        self.edge.send_signal(signal.SIGKILL)
        self.edge.wait()
        self.replay_up()
        self.edge_up()
        _wait(lambda: self.env_steps() >= after, "the restarted edge to collect")
        self.edge.send_signal(signal.SIGTERM)
        self.edge.wait(timeout=60)
        second_life = self.env_steps()  # the final heartbeat, after its loops stopped
        stats = self.stored()
        collected = first_life + second_life
        return {
            "collected": collected,
            "stored": int(stats.steps),
            "lost": collected - int(stats.steps),
            "deduplicated": int(stats.duplicates),
        }


def kill9_rows(quick: bool, workdir: Path, log: Callable[..., None]) -> list[Row]:
    online, outage, after = (100, 200, 50) if quick else (1000, 2000, 300)
    results = {}
    for name, spool in (("ours", True), ("peer", False)):
        log(f"spool: kill -9 during an outage, {name} ({'LMDB spool' if spool else 'RAM outbox'})")
        scenario = Scenario(workdir / name, spool)
        try:
            results[name] = scenario.run(online, outage, after)
        finally:
            scenario.close()
    ours, peer = results["ours"], results["peer"]
    group = f"spool kill -9 during outage (~{online} online, ~{outage} offline)"

    def of(r: dict[str, Any], key: str) -> str:
        return f"{r[key]} of {r['collected']}"

    return [
        Row(group, "steps lost", of(ours, "lost"), of(peer, "lost"), peer_name=PEER_NAME,
            note="collected in both lives, never stored"),
        Row(group, "steps stored", of(ours, "stored"), of(peer, "stored"), peer_name=PEER_NAME,
            note="replay keys (robot, episode, step): none twice"),
        Row(group, "re-sends deduplicated", str(ours["deduplicated"]), str(peer["deduplicated"]),
            peer_name=PEER_NAME, note="sent again after a lost ack, stored once"),
    ]  # fmt: skip


def _put_us(outbox: Outbox, steps: list[step_pb2.Step]) -> float:
    times = []
    for step in steps:
        start = time.perf_counter()
        outbox.put(step)
        times.append((time.perf_counter() - start) * 1e6)
    outbox.close()
    return median(times)


def put_rows(quick: bool, workdir: Path) -> list[Row]:
    n = 300 if quick else 3000
    rng = np.random.default_rng(0)
    steps = [
        step_pb2.Step(
            robot_id=ROBOT,
            episode_id="e",
            step_index=i,
            observation=wire.to_tensor_map({"state": rng.standard_normal(15).astype(np.float32)}),
            action=wire.to_tensor(rng.uniform(-1, 1, 3).astype(np.float32)),
        )
        for i in range(n)
    ]
    group = f"spool put, sim-arm step ({steps[0].ByteSize()} B, N={n})"
    rows = []
    for label, fsync in (("no fsync (default)", False), ("fsync", True)):
        ours = _put_us(LmdbSpool(workdir / f"put-{fsync}", 1 << 28, fsync=fsync), steps)
        peer = _put_us(MemoryOutbox(n), steps)
        note = "survives kill -9" if not fsync else "survives power loss too"
        rows.append(Row(group, f"median put, {label}", ours, peer, "us", False, note, peer_name=PEER_NAME))
    return rows


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    workdir.mkdir(parents=True, exist_ok=True)
    return kill9_rows(quick, workdir, log) + put_rows(quick, workdir)
