"""The edge spool (LMDB outbox) and shard assignment: real LMDB in a tmp dir, real Control / Replay
servers, the real edge agent as a process killed with SIGKILL."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from edge_agent.agent import EdgeAgent, RobotLoop
from edge_agent.policy_source import RemotePolicy
from edge_agent.replay_client import ReplaySender
from edge_agent.robot import make_robot
from edge_agent.spool import LmdbSpool, MemoryOutbox, SpoolInUse, open_outbox
from services.control.server import ControlService, replay_shard_for
from services.replay.server import ReplayService
from tests.helpers import free_port, wait_for
from tests.test_edge_agent import (
    AUTH,
    SIM_SPEC,
    control_stub,
    replay_stats,
    robot_info,
    sim_steps,
    stack_cfg,
    start_replay,
)
from user.config import EdgeConfig, ReplayShard, RobotConfig
from user.rpc import Backoff
from user.v1 import control_pb2


@pytest.fixture
def control(tmp_path: Path) -> Iterator[ControlService]:
    svc = ControlService(stack_cfg(tmp_path), start_metrics=False).start()
    yield svc
    svc.stop()


# --------------------------------------------------------------------------- the spool itself


def test_spool_keeps_steps_across_reopen_and_never_reuses_a_seq(tmp_path: Path) -> None:
    steps = sim_steps(5)
    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    seqs = [spool.put(s) for s in steps]
    assert seqs == [1, 2, 3, 4, 5]
    assert spool.ack([1, 2, 99]) == 2
    spool.close()

    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    kept = spool.read(0, 100)
    assert [r.seq for r in kept] == [3, 4, 5]
    assert [r.step for r in kept] == steps[2:]
    assert spool.count == 3 and spool.nbytes == sum(s.ByteSize() for s in steps[2:])
    assert [r.seq for r in spool.read(3, 1)] == [4]
    spool.ack([3, 4, 5])
    spool.close()

    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    assert spool.count == 0 and spool.nbytes == 0
    assert spool.put(steps[0]) == 6  # seqs go on after everything was acked
    spool.close()


def test_each_steps_replay_table_is_kept_across_reopen_ack_and_drop(tmp_path: Path) -> None:
    steps = sim_steps(6)
    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    for step, table in zip(steps, ["", "lab", "lab", "", "demos", "lab"], strict=True):
        spool.put(step, table)
    spool.ack([2])
    spool.close()
    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    assert [(r.seq, r.table) for r in spool.read(0, 100)] == [(1, ""), (3, "lab"), (4, ""), (5, "demos"), (6, "lab")]
    spool.ack([1, 3, 4, 5, 6])
    with spool._env.begin() as txn:  # nothing left behind for acked steps
        assert txn.stat(spool._tables)["entries"] == 0
    spool.close()
    size = steps[0].ByteSize()
    dropping = LmdbSpool(tmp_path / "drop", max_bytes=2 * size + size // 2, policy="drop_oldest")
    for step in steps:
        dropping.put(step, "lab")
    assert [(r.seq, r.table) for r in dropping.read(0, 100)] == [(5, "lab"), (6, "lab")]
    with dropping._env.begin() as txn:
        assert txn.stat(dropping._tables)["entries"] == 2
    dropping.close()
    box = MemoryOutbox()
    box.put(steps[0], "lab")
    assert box.read(0, 1)[0].table == "lab"


def test_a_spool_has_one_owner_at_a_time(tmp_path: Path) -> None:
    spool = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    with pytest.raises(SpoolInUse, match=f"edge.spool_dir: spool .* is in use by pid {os.getpid()} "):
        LmdbSpool(tmp_path / "spool", max_bytes=1 << 20)
    spool.close()
    LmdbSpool(tmp_path / "spool", max_bytes=1 << 20).close()  # free again once closed


def test_spool_drop_oldest_keeps_the_newest_under_the_cap(tmp_path: Path) -> None:
    steps = sim_steps(10)
    size = steps[0].ByteSize()
    spool = LmdbSpool(tmp_path / "spool", max_bytes=3 * size + size // 2, policy="drop_oldest")
    for step in steps:
        spool.put(step)
    assert spool.count == 3 and spool.dropped == 7
    assert [r.seq for r in spool.read(0, 100)] == [8, 9, 10]
    assert spool.accepting  # drop_oldest never pauses collection
    spool.close()
    reopened = LmdbSpool(tmp_path / "spool", max_bytes=1 << 20, policy="drop_oldest")
    assert reopened.dropped == 7 and reopened.count == 3
    reopened.close()


def test_spool_pause_policy_keeps_everything_and_stops_accepting_until_acked(tmp_path: Path) -> None:
    steps = sim_steps(4)
    size = max(s.ByteSize() for s in steps)  # step 0 is a little smaller (step_index 0 is not written)
    spool = LmdbSpool(tmp_path / "spool", max_bytes=2 * size, policy="pause")
    spool.put(steps[0])
    assert spool.accepting and not spool.full
    spool.put(steps[1])
    assert spool.full and not spool.accepting
    spool.put(steps[2])  # a step already in progress is still kept: nothing collected is lost
    assert spool.count == 3 and spool.dropped == 0
    spool.ack([1, 2])
    assert spool.accepting
    spool.close()


def test_memory_outbox_reads_in_order_across_gaps() -> None:
    box = MemoryOutbox(max_steps=5)
    for step in sim_steps(8):
        box.put(step)
    assert box.dropped == 3 and [r.seq for r in box.read(0, 10)] == [4, 5, 6, 7, 8]
    box.ack([5, 7])
    assert [r.seq for r in box.read(4, 10)] == [6, 8]
    assert box.read(8, 10) == []


def test_open_outbox_follows_the_config(tmp_path: Path) -> None:
    edge = EdgeConfig(agent_id="edge-x", spool_dir=tmp_path, spool_max_mb=1, spool_full_policy="drop_oldest")
    spool = open_outbox(edge)
    assert isinstance(spool, LmdbSpool) and spool.path == tmp_path / "edge-x"
    assert spool.max_bytes == 1 << 20 and spool.policy == "drop_oldest"
    spool.close()
    assert isinstance(open_outbox(EdgeConfig(spool_dir=None)), MemoryOutbox)


# --------------------------------------------------------------------------- sender + spool + replay


def test_sender_resends_what_a_previous_sender_left_in_the_spool(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.replay.server.port = free_port()  # replay is down while the first sender runs
    addr = f"127.0.0.1:{cfg.replay.server.port}"
    first = ReplaySender(addr, AUTH, outbox=LmdbSpool(tmp_path / "spool", 1 << 24), backoff=Backoff(0.05, 0.2))
    steps = sim_steps(120)
    for step in steps:
        first.send(step)
    assert not first.flush(0.05)
    first.close()  # the process ends without replay ever answering
    replay = start_replay(cfg)
    second = ReplaySender(addr, AUTH, outbox=LmdbSpool(tmp_path / "spool", 1 << 24), backoff=Backoff(0.05, 0.2))
    try:
        assert second.unacked == 120
        assert second.flush(60)
        stats = replay_stats(replay.address)
        assert stats.steps == 120 and stats.duplicates == 0
    finally:
        second.close()
        replay.stop()


def test_full_spool_with_pause_policy_holds_the_robot_until_replay_acks(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.replay.server.port = free_port()  # replay down: nothing is acked
    size = sim_steps(1)[0].ByteSize()
    spool = LmdbSpool(tmp_path / "spool", max_bytes=20 * size, policy="pause")
    sender = ReplaySender(f"127.0.0.1:{cfg.replay.server.port}", AUTH, outbox=spool, backoff=Backoff(0.05, 0.2))
    robot = make_robot("sim_reach_arm", "arm-0", {"max_episode_steps": 1000}, seed=1)
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)  # never answers: held steps, still steps
    loop = RobotLoop(robot, policy, sender, mode="fast", action_deadline_s=0.002)
    replay = None
    loop.start()
    try:
        wait_for(lambda: loop.status(drain=False).state == control_pb2.ROBOT_STATE_PAUSED, limit_s=120)
        collected = loop.status(drain=False).env_steps
        assert spool.full and collected == spool.count and spool.dropped == 0  # every collected step is on disk
        replay = start_replay(cfg)
        # acks freed space: it goes on
        wait_for(lambda: loop.status(drain=False).env_steps > collected + 40, limit_s=120)
        loop.stop()
        assert sender.flush(30)
        assert replay_stats(replay.address).steps == loop.env_steps
    finally:
        loop.stop()
        sender.close()
        policy.close()
        robot.close()
        if replay is not None:
            replay.stop()


def test_a_robots_steps_reach_the_replay_table_of_its_lease(tmp_path: Path) -> None:
    """Control's lease names the experiment's table; the loop sends each episode there, through the spool."""
    cfg = stack_cfg(tmp_path)
    replay = start_replay(cfg)
    sender = ReplaySender(replay.address, AUTH, outbox=LmdbSpool(tmp_path / "spool", 1 << 24))
    robot = make_robot("sim_reach_arm", "arm-0", {"max_episode_steps": 10}, seed=1)
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)  # no policy: held steps, still steps
    loop = RobotLoop(robot, policy, sender, mode="fast", action_deadline_s=0.002)
    loop.set_lease(control_pb2.RobotLease(robot_id="arm-0", experiment="lab-exp", table="lab"))
    loop.start()
    try:
        wait_for(lambda: loop.status(drain=False).env_steps >= 30, limit_s=120)
        loop.stop()
        assert sender.flush(30)
        stats = replay_stats(replay.address)
        assert stats.tables["lab"].steps == loop.env_steps and stats.tables["lab"].episodes >= 3
        assert stats.tables["online"].steps == 0 if "online" in stats.tables else True
    finally:
        loop.stop()
        sender.close()
        policy.close()
        robot.close()
        replay.stop()


# --------------------------------------------------------------------------- kill -9 of the edge


def _edge_proc(cfg, spool_dir: Path, replay_addr: str, ready: Path) -> subprocess.Popen:
    overrides = {
        "auth.token": AUTH.token,
        "edge.agent_id": "edge-k9",
        "edge.mode": "fast",
        "edge.metrics_port": 0,
        "edge.control_addr": cfg.edge.control_addr,
        "edge.replay_addr": replay_addr,
        "edge.inference_addr": f"127.0.0.1:{free_port()}",  # no policy: the arm holds, steps still flow
        "edge.action_deadline_ms": 2,
        "edge.spool_dir": str(spool_dir),
        "edge.robots": json.dumps([{"id": "arm-0", "kind": "sim_reach_arm", "params": {"max_episode_steps": 20}}]),
    }
    cmd = [sys.executable, "-m", "user.cli", "edge", "--ready-file", str(ready)]
    for key, value in overrides.items():
        cmd += ["--set", f"{key}={value}"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "MUJOCO_GL": "egl"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for(lambda: ready.exists() or proc.poll() is not None, "edge ready", limit_s=120)
    assert proc.poll() is None, "edge process died at start"
    return proc


def _settled_env_steps(svc: ControlService, robot_id: str) -> int:
    """env_steps once two heartbeats after the pause agree (the loop is holding, nothing moves)."""
    seen: list[tuple[int, int]] = []

    def settled() -> int | None:
        info = robot_info(svc, robot_id)
        if info is None or info.status.state != control_pb2.ROBOT_STATE_PAUSED:
            return None
        seen.append((info.last_heartbeat_ns, info.status.env_steps))
        beats = sorted(set(seen))
        if len(beats) >= 3 and beats[-1][1] == beats[-2][1] == beats[-3][1]:
            return beats[-1][1] or None
        return None

    return wait_for(settled, "a paused robot's settled step count", limit_s=120)


@pytest.mark.parametrize("online_first", [False, True], ids=["outage-from-start", "online-then-outage"])
def test_kill_9_during_an_outage_then_restart_stores_every_step_exactly_once(
    tmp_path: Path, control: ControlService, online_first: bool
) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.edge.control_addr = control.address
    cfg.replay.control_addr = control.address  # replay validates steps against the registered spec
    cfg.replay.server.port = free_port()  # fixed: replay goes away and comes back on the same port and dir
    replay_addr = f"127.0.0.1:{cfg.replay.server.port}"
    spool_dir = tmp_path / "spool"
    replay = ReplayService(cfg, start_metrics=False).start() if online_first else None
    edge = _edge_proc(cfg, spool_dir, replay_addr, tmp_path / "edge1.json")
    try:
        if replay is not None:  # some steps acked and gone from the spool, then the outage
            wait_for(lambda: replay_stats(replay_addr).steps >= 100, limit_s=120)
            replay.stop()
            replay = None
        outage_start = robot_info(control, "arm-0").status.env_steps
        wait_for(lambda: robot_info(control, "arm-0").status.env_steps >= outage_start + 150, limit_s=120)
        control_stub(control).SendCommand(
            control_pb2.SendCommandRequest(command=control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE)), timeout=5
        )
        collected = _settled_env_steps(control, "arm-0")
        reported = robot_info(control, "arm-0").status.spool_steps  # the console's number
        edge.send_signal(signal.SIGKILL)
        edge.wait(timeout=30)
        replay = ReplayService(cfg, start_metrics=False).start()  # the link is back
        stored_before = replay_stats(replay_addr).steps  # acked steps are among these
        spool = LmdbSpool(spool_dir / "edge-k9", 1 << 30)  # what the killed edge left on disk
        assert spool.count == reported and spool.dropped == 0
        assert spool.count >= collected - stored_before > 0  # every step not in replay is in the spool
        assert spool.count == collected or online_first
        keys = {(r.step.episode_id, r.step.step_index) for r in spool.read(0, collected + 1)}
        assert len(keys) == spool.count
        spool.close()
        edge = _edge_proc(cfg, spool_dir, replay_addr, tmp_path / "edge2.json")  # the edge restarts
        wait_for(lambda: replay_stats(replay_addr).steps >= collected + 50, limit_s=120)
        edge.send_signal(signal.SIGTERM)
        assert edge.wait(timeout=60) == 0
        after_restart = robot_info(control, "arm-0").status.env_steps  # the final heartbeat's count
        stats = replay_stats(replay_addr)
        assert stats.steps == collected + after_restart  # exactly every step of both lives, each once
        assert stats.rejected == 0
        leftover = LmdbSpool(spool_dir / "edge-k9", 1 << 30)
        assert leftover.count == 0
        leftover.close()
    finally:
        if edge.poll() is None:
            edge.kill()
            edge.wait()
        if replay is not None:
            replay.stop()


# --------------------------------------------------------------------------- shards


def test_shard_rules_first_match_by_site_or_agent_pattern() -> None:
    shards = [
        ReplayShard(addr="a:1", sites=["lab-a"]),
        ReplayShard(addr="b:1", agents=["lab-b-*"], sites=["lab-b"]),
    ]
    assert replay_shard_for(shards, "edge-0", "lab-a") == "a:1"
    assert replay_shard_for(shards, "lab-b-7", "") == "b:1"
    assert replay_shard_for(shards, "lab-b-7", "lab-a") == "a:1"  # first match wins
    assert replay_shard_for(shards, "edge-0", "elsewhere") == ""  # the edge keeps its own replay_addr
    assert replay_shard_for([], "edge-0", "lab-a") == ""


def test_control_sends_each_edge_to_its_sites_shard(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    specs = {"arm-0": SIM_SPEC}
    cfg.replay.path = tmp_path / "near"
    near = ReplayService(cfg.model_copy(deep=True), spec_source=specs.get, start_metrics=False).start()
    cfg.replay.path = tmp_path / "far"
    far = ReplayService(cfg.model_copy(deep=True), spec_source=specs.get, start_metrics=False).start()
    cfg.control.replay_shards = [ReplayShard(addr=near.address, sites=["lab-a"])]
    control_svc = ControlService(cfg, start_metrics=False).start()
    cfg.edge.agent_id, cfg.edge.site = "edge-a", "lab-a"
    cfg.edge.control_addr, cfg.edge.replay_addr = control_svc.address, far.address  # its default is far away
    cfg.edge.inference_addr = f"127.0.0.1:{free_port()}"
    cfg.edge.mode, cfg.edge.action_deadline_ms, cfg.edge.metrics_port = "fast", 2, 0
    cfg.edge.spool_dir = tmp_path / "spool"
    cfg.edge.robots = [RobotConfig(id="arm-0", params={"max_episode_steps": 20})]
    agent = EdgeAgent(cfg)
    agent.start()
    try:
        assert agent.sender.addr == near.address
        wait_for(lambda: replay_stats(near.address).steps >= 50, limit_s=120)
    finally:
        agent.stop()
        stats = replay_stats(near.address)
        far_steps = replay_stats(far.address).steps
        control_svc.stop()
        near.stop()
        far.stop()
    assert stats.steps == agent.loops["arm-0"].env_steps and far_steps == 0


def test_retarget_mid_stream_moves_unacked_steps_without_duplicates(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.replay.path = tmp_path / "a"
    a = start_replay(cfg.model_copy(deep=True))
    cfg.replay.path = tmp_path / "b"
    b = start_replay(cfg.model_copy(deep=True))
    sender = ReplaySender(a.address, AUTH, outbox=LmdbSpool(tmp_path / "spool", 1 << 24), backoff=Backoff(0.05, 0.2))
    steps = sim_steps(400)
    try:
        for step in steps[:300]:
            sender.send(step)
        sender.retarget(b.address)  # while many are still in flight to a
        for step in steps[300:]:
            sender.send(step)
        assert sender.flush(60)
        on_a, on_b = replay_stats(a.address).steps, replay_stats(b.address).steps
        assert on_a + on_b == 400  # every step on exactly one shard
        assert on_b >= 100 and sender.addr == b.address and sender.retargets == 1
    finally:
        sender.close()
        a.stop()
        b.stop()


@pytest.mark.parametrize("policy", ["pause", "drop_oldest"])
def test_heartbeat_reports_the_spool(tmp_path: Path, control: ControlService, policy: str) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.edge.control_addr = control.address
    cfg.edge.replay_addr = f"127.0.0.1:{free_port()}"  # down: the spool fills
    cfg.edge.inference_addr = f"127.0.0.1:{free_port()}"
    cfg.edge.mode, cfg.edge.action_deadline_ms, cfg.edge.metrics_port = "fast", 2, 0
    cfg.edge.spool_dir, cfg.edge.spool_full_policy, cfg.edge.spool_max_mb = tmp_path / "spool", policy, 1
    cfg.edge.robots = [RobotConfig(id="arm-0", params={"max_episode_steps": 20})]
    agent = EdgeAgent(cfg)
    agent.sender.outbox.max_bytes = 40 * sim_steps(1)[0].ByteSize()  # a tiny cap, so it fills fast
    agent.start()
    try:
        full = lambda: (i := robot_info(control, "arm-0")) is not None and i.status.spool_full and i  # noqa: E731
        info = wait_for(full, "a full spool in the heartbeat", limit_s=120)
        st = info.status
        assert st.spool_steps > 0 and st.spool_bytes > 0 and st.steps_unacked == st.spool_steps
        if policy == "pause":
            assert st.state == control_pb2.ROBOT_STATE_PAUSED and st.spool_dropped == 0
        else:
            wait_for(lambda: robot_info(control, "arm-0").status.spool_dropped > 0, limit_s=120)
    finally:
        agent.stop(flush_timeout_s=0.1)


# --------------------------------------------------------------------------- a disk smaller than the cap


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real 2 MiB filesystem (tmpfs), so the disk is smaller than the spool's configured cap."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True)
    if mount.returncode != 0:
        pytest.skip("mounting a tmpfs needs root")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


@pytest.mark.parametrize("policy", ["pause", "drop_oldest"])
def test_a_small_disk_lowers_the_cap_so_the_policy_applies_before_the_disk_fills(small_disk: Path, policy: str) -> None:
    steps = sim_steps(200)
    spool = LmdbSpool(small_disk / "spool", max_bytes=100 << 20, policy=policy)
    try:
        assert spool.max_bytes <= 1 << 20  # half of the 2 MiB disk at most
        i = 0
        while spool.accepting and spool.dropped == 0:
            spool.put(steps[i % len(steps)])
            i += 1
        assert spool.full
        if policy == "pause":
            assert spool.dropped == 0 and not spool.accepting
        for _ in range(500):  # at the cap: drop_oldest goes on; pause keeps the steps still in progress
            spool.put(steps[0])
        kept = spool.count
        assert spool.dropped == (0 if policy == "pause" else i + 500 - kept)
        assert spool.ack([r.seq for r in spool.read(0, kept // 2)]) == kept // 2  # deletes work on the full disk
        assert spool.accepting and not spool.full
        for step in steps:
            spool.put(step)
        assert spool.count == kept - kept // 2 + len(steps)
    finally:
        spool.close()
