"""Edge agent: the control loop, its scheduler, the replay sender and the control client, against
real Control / Replay / Inference servers and the real MuJoCo sim arm."""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from edge_agent.agent import EdgeAgent, RobotLoop, TickScheduler, apply_command
from edge_agent.control_client import ControlClient
from edge_agent.policy_source import PolicySource, RemotePolicy, _Chunked
from edge_agent.replay_client import ReplaySender
from edge_agent.robot import make_robot
from services.control.server import ControlService
from services.inference.server import InferenceService
from services.replay.server import ReplayService
from tests import helpers
from tests.helpers import ListSink, free_port, wait_for
from user import wire
from user.config import AuthConfig, RobotConfig, StackConfig
from user.rpc import Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2

torch.set_num_threads(1)

AUTH = AuthConfig(token="test-token")
ACTOR = {
    "obs_keys": ["state"],
    "obs_dim": 15,
    "action_dim": 3,
    "hidden": [16, 16],
    "action_low": [-1.0, -1.0, -1.0],
    "action_high": [1.0, 1.0, 1.0],
}


# --------------------------------------------------------------------------- helpers


random_weights = functools.partial(helpers.random_weights, ACTOR)


def stack_cfg(tmp_path: Path) -> StackConfig:
    cfg = StackConfig(auth=AUTH)
    for section in (cfg.control, cfg.replay, cfg.inference):
        section.server.port = 0
        section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.1
    cfg.control.lease_ttl_s = 2.0
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.commit_max_delay_ms = 5.0
    cfg.edge.spool_dir = tmp_path / "spool"  # not the repo's runs/default/spool: tests share no outbox
    return cfg


@pytest.fixture
def control(tmp_path: Path) -> Iterator[ControlService]:
    svc = ControlService(stack_cfg(tmp_path), start_metrics=False).start()
    yield svc
    svc.stop()


@pytest.fixture
def inference(tmp_path: Path) -> Iterator[InferenceService]:
    svc = InferenceService(stack_cfg(tmp_path), policy_source="manual", start_metrics=False).start()
    yield svc
    svc.stop()


def control_stub(svc: ControlService) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(svc.address, AUTH))


def episode_ids(svc: ControlService, robot_id: str) -> list[str]:
    info = robot_info(svc, robot_id)
    return [e.episode_id for e in info.recent_episodes] if info else []


def robot_info(svc: ControlService, robot_id: str) -> control_pb2.RobotInfo | None:
    robots = control_stub(svc).ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=5).robots
    return next((r for r in robots if r.spec.robot_id == robot_id), None)


def ee(step: step_pb2.Step) -> np.ndarray:
    return wire.from_tensor(step.observation.tensors["state"])[:3]


# --------------------------------------------------------------------------- scheduler


class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, delay: float) -> None:
        self.sleeps.append(delay)
        self.t += delay


def test_scheduler_ticks_on_a_fixed_grid_without_drift() -> None:
    clock = FakeClock()
    sched = TickScheduler(0.05, clock=clock, sleep=clock.sleep)
    ticks = []
    for i in range(1000):
        ticks.append(sched.wait())
        clock.t += 0.01 + 0.03 * (i % 3) / 2  # work of varying length, always shorter than a period
    assert ticks[0] == 100.0
    assert ticks[-1] == pytest.approx(100.0 + 999 * 0.05, abs=1e-9)  # no accumulated drift
    assert np.allclose(np.diff(ticks), 0.05)
    assert sched.ticks == 1000 and sched.overruns == 0


def test_scheduler_started_at_a_common_first_tick() -> None:
    """Loops given one first tick share a grid: their robots ask for actions together."""
    clock = FakeClock()
    a, b = (TickScheduler(0.1, clock=clock, sleep=clock.sleep) for _ in range(2))
    for sched in (a, b):
        sched.start_at(100.5)
    first_a = a.wait()
    clock.t += 0.003  # b's loop gets the CPU a little later
    first_b = b.wait()
    assert first_a == first_b == 100.5 and a.wait() == b.wait() == pytest.approx(100.6)
    assert a.overruns == b.overruns == 0


def test_scheduler_skips_missed_ticks_and_counts_overruns() -> None:
    clock = FakeClock()
    sched = TickScheduler(0.05, clock=clock, sleep=clock.sleep)
    work = [0.01] * 5 + [0.12] + [0.01] * 5  # the sixth step takes 2.4 periods
    ticks = []
    for w in work:
        ticks.append(sched.wait())
        clock.t += w
    # tick 5 runs at 100.25 and ends at 100.37: 100.30 is skipped, 100.35 runs at once (late, no sleep).
    assert ticks[5] == pytest.approx(100.25)
    assert ticks[6] == pytest.approx(100.35)
    assert ticks[7] == pytest.approx(100.40)
    assert sched.overruns == 1
    grid = (np.array(ticks) - 100.0) / 0.05
    assert np.allclose(grid, np.round(grid))  # every tick stays on the original grid
    # Only a late tick runs without sleeping; it never bursts through several ticks at once.
    assert len(clock.sleeps) == len(work) - 2


def test_scheduler_rejects_bad_period() -> None:
    with pytest.raises(ValueError):
        TickScheduler(0.0)


# --------------------------------------------------------------------------- robot loop


def test_loop_holds_when_the_policy_never_answers() -> None:
    robot = make_robot("sim_reach_arm", "arm-0", {"control_rate_hz": 50, "max_episode_steps": 1000}, seed=1)
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)  # nothing listens there
    sink = ListSink()
    loop = RobotLoop(robot, policy, sink, mode="realtime", action_deadline_s=0.005)
    loop.start()
    try:
        wait_for(lambda: len(sink.steps) >= 15)
    finally:
        loop.stop()
        policy.close()
    steps = sink.snapshot()
    assert all(s.held and s.policy_version == 0 for s in steps)
    assert all(np.array_equal(wire.from_tensor(s.action), np.zeros(3, np.float32)) for s in steps)
    assert [s.step_index for s in steps] == list(range(len(steps)))
    assert len({s.episode_id for s in steps}) == 1
    start_ee = ee(steps[0])  # the loop reset the arm before its first step
    moved = max(np.abs(ee(s) - start_ee).max() for s in steps)
    assert moved < 1e-3, f"a holding arm moved {moved} m"
    assert np.abs(robot.ee_pos() - start_ee).max() < 1e-3
    status = loop.status()
    assert status.state == control_pb2.ROBOT_STATE_HOLDING
    assert status.held_steps == status.env_steps == len(steps)
    robot.close()


def test_a_paused_robots_step_rate_falls_to_zero(monkeypatch: pytest.MonkeyPatch) -> None:
    """steps/s is measured up to now: a paused robot reports 0 once its window has passed, not its last rate."""
    from edge_agent import agent as agent_module

    monkeypatch.setattr(agent_module, "RATE_WINDOW_S", 0.5)
    robot = make_robot("sim_reach_arm", "arm-0", {"control_rate_hz": 50, "max_episode_steps": 1000}, seed=1)
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)  # nothing listens there: the arm holds, ticking
    loop = RobotLoop(robot, policy, ListSink(), mode="realtime", action_deadline_s=0.005)
    loop.start()
    try:
        wait_for(lambda: loop.status().env_steps_per_s > 10, "a running rate")
        loop.pause()
        wait_for(lambda: loop.status().state == control_pb2.ROBOT_STATE_PAUSED, "paused")
        paused_at = loop.status().env_steps
        wait_for(lambda: loop.status().env_steps_per_s == 0.0, "the rate to fall to 0 while paused")
        assert loop.status().env_steps <= paused_at + 1
    finally:
        loop.stop()
        policy.close()
        robot.close()


def test_robots_asking_together_share_one_act_batch_call(inference: InferenceService) -> None:
    """RemotePolicy for 3 robots: once each has asked, a round of all three is one ActBatch call, and
    every robot gets the action the policy gives its own observation."""
    inference.load_weights(random_weights(4))
    policy = RemotePolicy(inference.address, AUTH, deterministic=True, robots=3)
    assert policy.batcher is not None
    policy.batcher.window_s = 30.0  # wait for all three however slow this machine is (capped at deadline / 4)
    states = {f"arm-{i}": np.random.default_rng(i).normal(size=15).astype(np.float32) for i in range(3)}
    answers: dict[str, list] = {rid: [] for rid in states}
    barrier = threading.Barrier(3)

    def robot(rid: str) -> None:
        for _ in range(3):
            barrier.wait()
            answers[rid].append(policy.act(rid, {"state": states[rid]}, 20.0))

    threads = [threading.Thread(target=robot, args=(rid,)) for rid in states]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
    finally:
        policy.close()
    # Round 1 may go out in pieces (no robot is known yet); rounds 2 and 3 are one call each.
    assert 3 <= policy.batcher.calls <= 5
    from user.policy import build_policy, policy_spec_for

    reference = build_policy(policy_spec_for(ACTOR), random_weights(4).tensors, 4)
    for rid, got in answers.items():
        assert len(got) == 3 and all(a is not None and a[1] == 4 for a in got)
        want = reference.act({"state": states[rid][None]}, deterministic=True)[0]
        for action, _ in got:
            np.testing.assert_allclose(action, want, rtol=1e-5, atol=1e-6)


def test_act_batch_without_a_server_holds() -> None:
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH, robots=2)  # nothing listens there
    try:
        assert policy.act("arm-0", {"state": np.zeros(15, np.float32)}, 0.2) is None
        assert policy.batcher is not None  # UNAVAILABLE is not UNIMPLEMENTED: still batching
    finally:
        policy.close()


def test_loop_episodes_steps_and_final_observation(inference: InferenceService) -> None:
    inference.load_weights(random_weights(7))
    robot = make_robot("sim_reach_arm", "arm-0", {"control_rate_hz": 20, "max_episode_steps": 8}, seed=2)
    policy = RemotePolicy(inference.address, AUTH)
    sink = ListSink()
    loop = RobotLoop(robot, policy, sink, mode="fast", action_deadline_s=5.0)
    loop.start()
    try:
        wait_for(lambda: loop.status(drain=False).episodes >= 3)
    finally:
        loop.stop()
        policy.close()
        robot.close()
    steps = sink.snapshot()
    episodes: dict[str, list[step_pb2.Step]] = {}
    for s in steps:
        episodes.setdefault(s.episode_id, []).append(s)
    finished = [eps for eps in episodes.values() if eps[-1].terminated or eps[-1].truncated]
    assert len(finished) >= 3
    for eps in finished:
        assert [s.step_index for s in eps] == list(range(len(eps)))
        last = eps[-1]
        assert last.truncated == (len(eps) == 8 and not last.terminated)
        assert last.final_observation.tensors["state"].shape == [15]
        assert all(not s.HasField("final_observation") for s in eps[:-1])
        assert all(not (s.terminated or s.truncated) for s in eps[:-1])
    for s in steps:
        assert not s.held and s.policy_version == 7
        assert s.observed_at_ns <= s.acted_at_ns
        assert np.all(np.abs(wire.from_tensor(s.action)) <= 1.0)
    status = loop.status()
    assert status.policy_version == 7 and status.env_steps == len(steps)
    assert [e.episode_id for e in status.new_episodes] == [eps[0].episode_id for eps in finished]
    assert all(e.length == len(eps) for e, eps in zip(status.new_episodes, finished, strict=True))
    assert list(loop.status().new_episodes) == []  # drained


class ChunkSource(PolicySource):
    """Chunks of 8 actions through the edge's ChunkExecutor; remembers each request's state and each reset."""

    def __init__(self) -> None:
        self.asked: list[np.ndarray] = []
        self.resets: list[str] = []
        self.chunks = _Chunked(self._fetch)

    def _fetch(self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float) -> tuple[np.ndarray, int]:
        self.asked.append(observation["state"].copy())
        return np.full((8, 3), 0.01 * len(self.asked), np.float32), 1

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        return self.chunks.act(robot_id, observation, deadline_s)

    def reset(self, robot_id: str) -> None:
        self.resets.append(robot_id)
        self.chunks.reset(robot_id)

    @property
    def version(self) -> int:
        return 1


def test_each_episode_starts_on_a_chunk_asked_with_its_own_observation() -> None:
    """Episodes of 3 ticks, chunks of 8: without RobotLoop resetting the policy at an episode's start, the
    next episode would run on rows planned from the last one's observation."""
    robot = make_robot("sim_reach_arm", "arm-0", {"control_rate_hz": 20, "max_episode_steps": 3}, seed=4)
    source, sink = ChunkSource(), ListSink()
    loop = RobotLoop(robot, source, sink, mode="fast", action_deadline_s=5.0)
    loop.start()
    try:
        wait_for(lambda: loop.status(drain=False).episodes >= 4)
    finally:
        loop.stop()
        robot.close()
    firsts = [s for s in sink.snapshot() if s.step_index == 0]
    assert len(firsts) >= 4 and source.resets[: len(firsts)] == ["arm-0"] * len(firsts)
    for k, step in enumerate(firsts):  # request k was made at episode k's first tick, with its observation
        np.testing.assert_array_equal(source.asked[k], wire.from_tensor(step.observation.tensors["state"]))
        assert not step.held


# --------------------------------------------------------------------------- replay sender

SIM_SPEC = make_robot("sim_reach_arm", "arm-0").spec


def sim_steps(n: int, episode_len: int = 50, robot_id: str = "arm-0") -> list[step_pb2.Step]:
    """Valid steps for the sim arm's spec: episodes of episode_len, the last one truncated."""
    rng = np.random.default_rng(0)
    steps = []
    for i in range(n):
        index = i % episode_len
        step = step_pb2.Step(
            robot_id=robot_id,
            episode_id=f"{robot_id}-ep{i // episode_len}",
            step_index=index,
            observation=wire.to_tensor_map({"state": rng.normal(size=15).astype(np.float32)}),
            action=wire.to_tensor(rng.uniform(-1, 1, 3).astype(np.float32)),
            reward=float(rng.normal()),
            policy_version=1,
        )
        if index == episode_len - 1:
            step.truncated = True
            step.final_observation.CopyFrom(wire.to_tensor_map({"state": np.zeros(15, np.float32)}))
        steps.append(step)
    return steps


def replay_stats(addr: str) -> replay_pb2.StatsResponse:
    stub = replay_pb2_grpc.ReplayStub(make_channel(addr, AUTH))
    return stub.Stats(replay_pb2.StatsRequest(), timeout=5)


def start_replay(cfg: StackConfig, specs: dict[str, robot_pb2.RobotSpec] | None = None) -> ReplayService:
    return ReplayService(cfg, spec_source=(specs or {"arm-0": SIM_SPEC}).get, start_metrics=False).start()


def test_sender_survives_replay_restart_on_the_same_port_and_dir(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.replay.server.port = free_port()
    replay = start_replay(cfg)
    sender = ReplaySender(replay.address, AUTH, backoff=Backoff(0.05, 0.5))
    steps = sim_steps(300)
    try:
        for step in steps[:100]:
            sender.send(step)
        wait_for(lambda: sender.acked == 100)
        for step in steps[100:200]:
            sender.send(step)
        replay.stop()  # mid-stream: some of these are in flight, none acked yet for sure
        for step in steps[200:]:
            sender.send(step)  # while replay is down: queued, never blocking
        assert sender.unacked > 0
        replay = start_replay(cfg)  # same port, same LMDB dir
        assert sender.flush(60)
        stats = replay_stats(replay.address)
        assert stats.steps == 300 and dict(stats.steps_per_robot) == {"arm-0": 300}  # none lost, each once
        assert stats.rejected == 0
        assert sender.acked == 300 and sender.unacked == 0 and sender.dropped == 0
        assert sender.reconnects >= 1
        assert sender._batched  # this replay has InsertBatch: steps went several a message
    finally:
        sender.close()
        replay.stop()


def test_sender_falls_back_to_insert_for_a_replay_without_insert_batch(tmp_path: Path) -> None:
    """A replay from before InsertBatch (here: the real servicer with only Insert registered) answers
    UNIMPLEMENTED; the sender goes on one step a message and nothing is lost or stored twice."""
    from concurrent import futures

    import grpc

    replay = start_replay(stack_cfg(tmp_path))
    old = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    insert_only = grpc.stream_stream_rpc_method_handler(
        replay.servicer.Insert, replay_pb2.InsertRequest.FromString, replay_pb2.InsertAck.SerializeToString
    )
    old.add_generic_rpc_handlers([grpc.method_handlers_generic_handler("user.v1.Replay", {"Insert": insert_only})])
    port = old.add_insecure_port("127.0.0.1:0")
    old.start()
    sender = ReplaySender(f"127.0.0.1:{port}", AUTH, backoff=Backoff(0.05, 0.5))
    try:
        for step in sim_steps(50):
            sender.send(step)
        assert sender.flush(30)
        assert not sender._batched and sender.acked == 50
        stats = replay_stats(replay.address)
        assert stats.steps == 50 and stats.duplicates == 0
    finally:
        sender.close()
        old.stop(0)
        replay.stop()


def test_sender_drops_a_rejected_step_and_goes_on(tmp_path: Path) -> None:
    replay = start_replay(stack_cfg(tmp_path))
    sender = ReplaySender(replay.address, AUTH, backoff=Backoff(0.05, 0.5))
    steps = sim_steps(100)
    bad = steps[40]
    bad.action.CopyFrom(wire.to_tensor(np.full(3, 5.0, np.float32)))  # outside the spec's [-1, 1]
    try:
        for step in steps:
            sender.send(step)
        assert sender.flush(30)
        stats = replay_stats(replay.address)
        assert stats.steps == 99 and stats.rejected == 1
        assert sender.rejected == 1 and sender.acked == 99
    finally:
        sender.close()
        replay.stop()


def test_sender_bounds_its_memory_by_dropping_the_oldest(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.replay.server.port = free_port()  # nothing listens yet
    sender = ReplaySender(f"127.0.0.1:{cfg.replay.server.port}", AUTH, max_unacked=10, backoff=Backoff(0.05, 0.2))
    steps = sim_steps(25)
    replay = None
    try:
        for step in steps:
            sender.send(step)
        assert sender.unacked == 10 and sender.dropped == 15
        assert not sender.flush(0.05)
        replay = start_replay(cfg)
        assert sender.flush(30)
        stats = replay_stats(replay.address)
        assert stats.steps == 10  # the newest ten
        assert stats.steps_per_robot["arm-0"] == 10
    finally:
        sender.close()
        if replay is not None:
            replay.stop()


# --------------------------------------------------------------------------- control client


def test_control_client_registers_heartbeats_and_obeys_commands(control: ControlService) -> None:
    robot = make_robot("sim_reach_arm", "arm-0", {"max_episode_steps": 1000}, seed=3)
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)
    sink = ListSink()
    loop = RobotLoop(robot, policy, sink, mode="fast", action_deadline_s=0.002)
    client = ControlClient(
        control.address,
        AUTH,
        "edge-t",
        [robot.spec],
        status_fn=lambda: [loop.status()],
        on_command=lambda cmd: apply_command({"arm-0": loop}, cmd),
    )
    loop.start()
    stub = control_stub(control)
    try:
        assert client.wait_registered(10)
        wait_for(lambda: (info := robot_info(control, "arm-0")) is not None and info.online and info.status.env_steps)
        info = robot_info(control, "arm-0")
        assert info is not None and info.agent_id == "edge-t"
        assert info.status.state == control_pb2.ROBOT_STATE_HOLDING

        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id="arm-0")
        assert stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5).delivered
        wait_for(lambda: loop.paused)
        wait_for(lambda: robot_info(control, "arm-0").status.state == control_pb2.ROBOT_STATE_PAUSED)
        count = len(sink.snapshot())
        time.sleep(0.2)
        assert len(sink.snapshot()) <= count + 1  # at most the step that was in progress

        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESUME)  # every robot of the agent
        assert stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5).delivered
        wait_for(lambda: not loop.paused and len(sink.snapshot()) > count + 3)

        before = len(sink.snapshot())
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESET, robot_id="arm-0")
        stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5)
        wait_for(lambda: any(s.truncated for s in sink.snapshot()[before:]))
        wait_for(lambda: any(e.length < 1000 for e in robot_info(control, "arm-0").recent_episodes))
    finally:
        client.close()
        loop.stop()
        policy.close()
        robot.close()
    steps = sink.snapshot()
    truncated = [s for s in steps if s.truncated]
    assert len(truncated) == 1 and truncated[0].HasField("final_observation")
    first_episode = [s for s in steps if s.episode_id == truncated[0].episode_id]
    assert [s.step_index for s in first_episode] == list(range(len(first_episode)))  # pause kept the episode


def test_control_client_reconnects_and_keeps_episodes(tmp_path: Path) -> None:
    cfg = stack_cfg(tmp_path)
    cfg.control.server.port = free_port()
    svc = ControlService(cfg, start_metrics=False).start()
    spec = make_robot("sim_reach_arm", "arm-0").spec
    pending: list[control_pb2.EpisodeSummary] = []
    lock = threading.Lock()

    def status_fn() -> list[control_pb2.RobotStatus]:
        with lock:
            episodes, pending[:] = list(pending), []
        return [control_pb2.RobotStatus(robot_id="arm-0", state=control_pb2.ROBOT_STATE_RUNNING, new_episodes=episodes)]

    def finish(n: int) -> None:
        with lock:
            pending.append(control_pb2.EpisodeSummary(robot_id="arm-0", episode_id=f"ep-{n}", length=n))

    client = ControlClient(svc.address, AUTH, "edge-r", [spec], status_fn, lambda cmd: None, backoff=Backoff(0.05, 0.2))
    try:
        assert client.wait_registered(10)
        finish(1)
        wait_for(lambda: episode_ids(svc, "arm-0") == ["ep-1"])
        svc.stop()
        finish(2)  # finished while control is down: must arrive after the reconnect
        svc = ControlService(cfg, start_metrics=False).start()
        # The heartbeat in flight when the stream broke is sent again (consumers dedupe by episode_id).
        wait_for(lambda: "ep-2" in episode_ids(svc, "arm-0"))
        assert set(episode_ids(svc, "arm-0")) <= {"ep-1", "ep-2"}
        assert client.reconnects >= 1
        finish(3)
        client.close()  # a last heartbeat carries ep-3, then a clean hang-up takes the robot offline
        assert "ep-3" in episode_ids(svc, "arm-0")
        wait_for(lambda: not robot_info(svc, "arm-0").online)
    finally:
        client.close()
        svc.stop()


def test_control_client_refused_registration_retries_slowly(control: ControlService) -> None:
    spec = make_robot("sim_reach_arm", "arm-0").spec
    status_fn = lambda: [control_pb2.RobotStatus(robot_id="arm-0")]  # noqa: E731
    owner = ControlClient(control.address, AUTH, "edge-a", [spec], status_fn, lambda cmd: None)
    assert owner.wait_registered(10)
    rival = ControlClient(control.address, AUTH, "edge-b", [spec], status_fn, lambda cmd: None, slow_retry_s=0.2)
    try:
        wait_for(lambda: rival.last_error is not None)
        assert rival.registered is None
        assert rival.last_error.name == "ALREADY_EXISTS"
        assert rival._thread.is_alive()  # still retrying, not crashed
        owner.close()  # the robot is free again: the rival's next slow retry takes it
        assert rival.wait_registered(20)
        wait_for(lambda: robot_info(control, "arm-0").agent_id == "edge-b")
    finally:
        owner.close()
        rival.close()


def test_unknown_robot_command_is_refused() -> None:
    robot = make_robot("sim_reach_arm", "arm-0")
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)
    loops = {"arm-0": RobotLoop(robot, policy, ListSink())}
    ok, msg = apply_command(loops, control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id="nope"))
    assert not ok and "nope" in msg
    ok, _ = apply_command(loops, control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE))
    assert ok and loops["arm-0"].paused
    ok, _ = apply_command(loops, control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESUME, robot_id="arm-0"))
    assert ok and not loops["arm-0"].paused
    policy.close()
    robot.close()


# --------------------------------------------------------------------------- the whole agent


def edge_cfg(
    cfg: StackConfig, control: ControlService, replay: ReplayService, inference: InferenceService
) -> StackConfig:
    cfg.edge.agent_id = "edge-test"
    cfg.edge.control_addr = control.address
    cfg.edge.replay_addr = replay.address
    cfg.edge.inference_addr = inference.address
    cfg.edge.mode = "fast"
    cfg.edge.metrics_port = 0
    cfg.edge.robots = [RobotConfig(id="arm-0", kind="sim_reach_arm", params={"max_episode_steps": 20})]
    cfg.edge.spool_dir = cfg.replay.path.parent / "spool"
    return cfg


@pytest.fixture
def cloud(tmp_path: Path, control: ControlService, inference: InferenceService) -> Iterator[StackConfig]:
    """Control + replay (validating against control) + inference with random weights, version 5."""
    cfg = stack_cfg(tmp_path)
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    inference.load_weights(random_weights(5))
    yield edge_cfg(cfg, control, replay, inference)
    replay.stop()


def test_edge_agent_fast_mode_end_to_end(cloud: StackConfig, control: ControlService) -> None:
    cloud.edge.robots = [
        RobotConfig(id=rid, kind="sim_reach_arm", params={"max_episode_steps": 20}) for rid in ("arm-0", "arm-1")
    ]
    agent = EdgeAgent(cloud)
    agent.start()
    try:
        for rid in ("arm-0", "arm-1"):
            wait_for(lambda rid=rid: (info := robot_info(control, rid)) is not None and info.status.env_steps >= 200)
            info = robot_info(control, rid)
            assert info.online and info.agent_id == "edge-test"
            assert info.status.state in (control_pb2.ROBOT_STATE_RUNNING, control_pb2.ROBOT_STATE_HOLDING)
            assert info.status.policy_version == 5
        wait_for(lambda: replay_stats(cloud.edge.replay_addr).steps >= 400)
    finally:
        agent.stop()
    stats = replay_stats(cloud.edge.replay_addr)
    assert dict(stats.steps_per_robot) == {rid: loop.env_steps for rid, loop in agent.loops.items()}  # all flushed
    assert stats.rejected == 0
    stub = replay_pb2_grpc.ReplayStub(make_channel(cloud.edge.replay_addr, AUTH))
    batch = stub.Sample(replay_pb2.SampleRequest(batch_size=64), timeout=5).batch
    assert wire.from_tensor(batch.policy_version).max() == 5
    # The last heartbeat reported every finished episode; the clean hang-up took the robots offline.
    for rid, loop in agent.loops.items():
        info = robot_info(control, rid)
        assert not info.online
        assert len({e.episode_id for e in info.recent_episodes}) == loop.episodes >= 10
        assert all(e.length <= 20 and e.robot_id == rid for e in info.recent_episodes)
    # Different seeds: the two arms did not live the same episodes.
    assert agent.loops["arm-0"].robot.target.tolist() != agent.loops["arm-1"].robot.target.tolist()


def test_edge_process_serves_metrics_and_stops_on_sigterm(cloud: StackConfig, tmp_path: Path) -> None:
    ready = tmp_path / "edge.json"
    overrides = {
        "auth.token": AUTH.token,
        "edge.agent_id": "edge-proc",
        "edge.mode": "fast",
        "edge.metrics_port": 0,
        "edge.control_addr": cloud.edge.control_addr,
        "edge.replay_addr": cloud.edge.replay_addr,
        "edge.inference_addr": cloud.edge.inference_addr,
        "edge.spool_dir": str(tmp_path / "spool"),
        "edge.robots": json.dumps([{"id": "arm-0", "kind": "sim_reach_arm", "params": {"max_episode_steps": 20}}]),
        "log_json": "true",
    }
    cmd = [sys.executable, "-m", "user.cli", "edge", "--ready-file", str(ready)]
    for key, value in overrides.items():
        cmd += ["--set", f"{key}={value}"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "MUJOCO_GL": "egl"}
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: ready.exists() or proc.poll() is not None, limit_s=60)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        info = json.loads(ready.read_text())
        url = f"http://127.0.0.1:{info['metrics_port']}/metrics"
        wait_for(lambda: replay_stats(cloud.edge.replay_addr).steps >= 50)
        body = urllib.request.urlopen(url, timeout=5).read().decode()
        for name in ("user_edge_env_steps_total", "user_edge_loop_period_seconds", "user_edge_steps_acked_total"):
            assert name in body
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        logs = proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stopped = [json.loads(line) for line in logs.splitlines() if '"edge agent stopped"' in line]
    assert stopped and stopped[0]["flushed"] is True  # every step acked by replay before exit


# --------------------------------------------------------------------------- gym-hil Panda (optional)


def test_gym_hil_panda_robot() -> None:
    from edge_agent.robots import gym_hil_panda  # registers the kind; sets MUJOCO_GL before mujoco loads
    from services.control.server import validate_spec

    if gym_hil_panda.gymnasium is None:
        pytest.skip("gym-hil is not installed")

    robot = make_robot("gym_hil_panda", "panda-0", {"max_episode_steps": 20}, seed=0)
    try:
        validate_spec(robot.spec)
        assert list(robot.spec.action.shape) == [7] and robot.spec.control_rate_hz == pytest.approx(10.0)
        first = robot.reset().features["state"]
        assert first.shape == (21,) and first.dtype == np.float32
        for _ in range(3):
            robot.hold()
        held = robot.observe().features["state"]
        assert np.abs(held[15:18] - first[15:18]).max() < 5e-3  # the gripper stays where it was
        applied = robot.act(np.array([2.0, 0, 0, 0, 0, 0, -3.0], np.float32))
        assert applied.tolist() == [1.0, 0, 0, 0, 0, 0, -1.0]  # clipped to the spec
        assert np.isfinite(robot.observe().features["state"]).all()
    finally:
        robot.close()
    proprio = make_robot("gym_hil_panda", "panda-1", {"block_in_state": False}, seed=0)
    try:  # proprioception only: the same joints, gripper and TCP, no cube position
        state = proprio.reset().features["state"]
        assert state.shape == (18,) and list(proprio.spec.observation[0].shape) == [18]
        np.testing.assert_allclose(state, first[:18])
        assert "block_pos" in proprio.observe().info  # still there for scripted experts
    finally:
        proprio.close()
