"""Edge agent: the control loop, its scheduler, the replay sender and the control client, against
real Control / Replay / Inference servers and the real MuJoCo sim arm."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from edge_agent.agent import RobotLoop, TickScheduler, apply_command
from edge_agent.control_client import ControlClient
from edge_agent.policy_source import RemotePolicy
from edge_agent.robot import make_robot
from services.control.server import ControlService
from services.inference.server import InferenceService
from user import wire
from user.config import AuthConfig, StackConfig
from user.policy import actor_from_config, policy_spec_for
from user.rpc import Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc, step_pb2
from user.weights import WeightSet

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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(cond: Callable[[], object], timeout: float = 30.0) -> None:
    """Liveness bound only: fails if something is stuck, never on speed."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.02)
    raise AssertionError("condition not reached")


def random_weights(version: int, seed: int = 0) -> WeightSet:
    torch.manual_seed(seed)
    actor = actor_from_config(ACTOR)
    tensors = {k: v.detach().numpy().copy() for k, v in actor.state_dict().items()}
    return WeightSet(version=version, policy=policy_spec_for(ACTOR), tensors=tensors)


class ListSink:
    """Collects steps in memory (a StepSink, for loop tests that do not need replay)."""

    def __init__(self) -> None:
        self.steps: list[step_pb2.Step] = []
        self._lock = threading.Lock()

    def send(self, step: step_pb2.Step) -> int:
        with self._lock:
            self.steps.append(step)
            return len(self.steps)

    @property
    def unacked(self) -> int:
        return 0

    def snapshot(self) -> list[step_pb2.Step]:
        with self._lock:
            return list(self.steps)


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
        wait_until(lambda: len(sink.steps) >= 15)
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


def test_loop_episodes_steps_and_final_observation(inference: InferenceService) -> None:
    inference.load_weights(random_weights(7))
    robot = make_robot("sim_reach_arm", "arm-0", {"control_rate_hz": 20, "max_episode_steps": 8}, seed=2)
    policy = RemotePolicy(inference.address, AUTH)
    sink = ListSink()
    loop = RobotLoop(robot, policy, sink, mode="fast", action_deadline_s=5.0)
    loop.start()
    try:
        wait_until(lambda: loop.status(drain=False).episodes >= 3)
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
        wait_until(lambda: (info := robot_info(control, "arm-0")) is not None and info.online and info.status.env_steps)
        info = robot_info(control, "arm-0")
        assert info is not None and info.agent_id == "edge-t"
        assert info.status.state == control_pb2.ROBOT_STATE_HOLDING

        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE, robot_id="arm-0")
        assert stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5).delivered
        wait_until(lambda: loop.paused)
        wait_until(lambda: robot_info(control, "arm-0").status.state == control_pb2.ROBOT_STATE_PAUSED)
        count = len(sink.snapshot())
        time.sleep(0.2)
        assert len(sink.snapshot()) <= count + 1  # at most the step that was in progress

        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESUME)  # every robot of the agent
        assert stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5).delivered
        wait_until(lambda: not loop.paused and len(sink.snapshot()) > count + 3)

        before = len(sink.snapshot())
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESET, robot_id="arm-0")
        stub.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=5)
        wait_until(lambda: any(s.truncated for s in sink.snapshot()[before:]))
        wait_until(lambda: any(e.length < 1000 for e in robot_info(control, "arm-0").recent_episodes))
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
        wait_until(lambda: episode_ids(svc, "arm-0") == ["ep-1"])
        svc.stop()
        finish(2)  # finished while control is down: must arrive after the reconnect
        svc = ControlService(cfg, start_metrics=False).start()
        # The heartbeat in flight when the stream broke is sent again (consumers dedupe by episode_id).
        wait_until(lambda: "ep-2" in episode_ids(svc, "arm-0"))
        assert set(episode_ids(svc, "arm-0")) <= {"ep-1", "ep-2"}
        assert client.reconnects >= 1
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
        wait_until(lambda: rival.last_error is not None)
        assert rival.registered is None
        assert rival.last_error.name == "ALREADY_EXISTS"
        assert rival._thread.is_alive()  # still retrying, not crashed
        owner.close()  # the robot is free again: the rival's next slow retry takes it
        assert rival.wait_registered(20)
        wait_until(lambda: robot_info(control, "arm-0").agent_id == "edge-b")
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
