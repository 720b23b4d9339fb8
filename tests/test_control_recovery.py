"""Control when something around it fails: a learner that failed an experiment, a second control on the same
state file, a disk that fills under the state file, an edge that restarts. Real Control over gRPC on 127.0.0.1:0,
the real edge ControlClient and learner WorkerReporter, real SQLite; the full disk is a real tmpfs (root only)."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import prometheus_client
import pytest
import yaml

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from tests.helpers import fill, wait_for
from tests.test_replay_store import spec
from user.config import AuthConfig, ConfigError, ExperimentConfig, RobotSelector, StackConfig
from user.rpc import Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc
from user.worker import WorkerReporter

ROOT = Path(__file__).resolve().parents[1]
AUTH = AuthConfig(token="test-token")
REACH = ExperimentConfig(name="reach", robots=RobotSelector(kinds=["test"]))  # the kind of spec()


def control_cfg(state_path: Path | None, worker_ttl_s: float = 30.0) -> StackConfig:
    cfg = StackConfig(auth=AUTH, experiments=[REACH])
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.05
    cfg.control.worker_ttl_s = worker_ttl_s
    cfg.control.state_path = state_path
    return cfg


@pytest.fixture
def make_control() -> Iterator[Callable[..., ControlService]]:
    started: list[ControlService] = []

    def make(state_path: Path | None, **kw: float) -> ControlService:
        svc = ControlService(control_cfg(state_path, **kw), start_metrics=False).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


def stub(svc: ControlService) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(svc.address, AUTH))


def robot(svc: ControlService, robot_id: str = "arm-0") -> control_pb2.RobotInfo:
    return stub(svc).GetRobot(control_pb2.GetRobotRequest(robot_id=robot_id), timeout=5)


def metric(name: str) -> float:
    return prometheus_client.REGISTRY.get_sample_value(name) or 0.0


class Edge:
    """The real edge ControlClient; `finish(n)` queues n finished episodes for the next heartbeat, as the agent
    drains its loops' episodes; `leases` is what control last told it per robot."""

    def __init__(
        self, svc: ControlService, agent_id: str = "lab-pc-1", robot_id: str = "arm-0", first: int = 0
    ) -> None:
        self.robot_id = robot_id
        self.next_id, self.counter = first, 0  # counter: the edge process's own, reset when it restarts
        self.queued: list[control_pb2.EpisodeSummary] = []
        self.leases: dict[str, control_pb2.RobotLease] = {}
        self.client = ControlClient(
            svc.address,
            AUTH,
            agent_id,
            [spec(robot_id)],
            self._statuses,
            lambda cmd: (True, "done"),
            backoff=Backoff(0.05, 0.3),
            on_leases=lambda leases: self.leases.update({lease.robot_id: lease for lease in leases}),
        )
        assert self.client.wait_registered(30)

    def _statuses(self) -> list[control_pb2.RobotStatus]:
        fresh, self.queued = self.queued, []
        self.counter += len(fresh)
        return [control_pb2.RobotStatus(robot_id=self.robot_id, episodes=self.counter, new_episodes=fresh)]

    def finish(self, n: int = 1) -> int:
        """Queue n episodes (every other one a success); returns how many this edge has finished in all."""
        for _ in range(n):
            i, self.next_id = self.next_id, self.next_id + 1
            self.queued.append(control_pb2.EpisodeSummary(episode_id=f"ep-{i}", length=10, success=i % 2 == 0))
        return self.next_id

    def close(self) -> None:
        self.client.close()


# --------------------------------------------------------------------------- 1: a failed experiment holds its robots


def test_robots_of_an_experiment_its_learner_failed_hold_until_it_reports_it_trains(make_control) -> None:
    """WorkerInfo.failed (sent by the learner's real WorkerReporter) -> the same hold as while preparing, nothing
    recorded; the learner no longer reporting it failed (a restart fixed it) -> leased again; a learner that stops
    reporting at all -> no longer holds them after worker_ttl_s."""
    control = make_control(None, worker_ttl_s=1.0)
    edge = Edge(control)
    failed: dict[str, str] = {}

    def info() -> control_pb2.WorkerInfo:  # as user.worker.report_worker builds it for the learner
        return control_pb2.WorkerInfo(
            worker_id="learner@gpu-1:1", kind="learner", address="gpu-1:1", experiments=["reach"], failed=dict(failed)
        )

    reporter = WorkerReporter(control.address, AUTH, info).start()
    try:
        assert robot(control).lease == "reach" and edge.leases["arm-0"].experiment == "reach"
        assert wait_for(reporter.reported.is_set, "the learner's first report")
        failed["reach"] = "replay table 'online' has no steps of the expected shape"
        held = wait_for(lambda: (r := robot(control)).lease == "" and r, "the failed experiment's robots to hold")
        assert "its learner failed it" in held.lease_reason and "expected shape" in held.lease_reason
        lease = wait_for(lambda: (x := edge.leases["arm-0"]).hold and x, "the edge to be told to hold")
        assert lease.experiment == "" and lease.reason == held.lease_reason
        exp = stub(control).GetExperiment(control_pb2.GetExperimentRequest(name="reach"), timeout=5)
        assert exp.learner_failed and exp.leased_robots == []

        failed.clear()  # restarted, trains again
        wait_for(lambda: robot(control).lease == "reach", "the robots leased again")
        assert wait_for(lambda: not (x := edge.leases["arm-0"]).hold and x).experiment == "reach"

        failed["reach"] = "boom"
        wait_for(lambda: robot(control).lease == "", "held again")
        reporter.stop()  # the failed learner is gone: it holds nothing once it is offline
        wait_for(lambda: robot(control).lease == "reach", "leased once the learner is offline")
    finally:
        reporter.stop()
        edge.close()


# --------------------------------------------------------------------------- 2: one control per state file


def userctl_control(tmp_path: Path, state_path: Path, *extra: str, **popen: object) -> subprocess.Popen:
    config = tmp_path / "stack.yaml"
    config.write_text(yaml.safe_dump({"log_level": "WARNING", "auth": {"token": AUTH.token}}))
    env = {k: v for k, v in os.environ.items() if not k.startswith("USER__") and k != "USER_TOKEN"}
    env["PYTHONPATH"] = str(ROOT)
    sets = [f"control.state_path={state_path}", "control.server.port=0", "control.server.metrics_port=0"]
    argv = [sys.executable, "-m", "user.cli", "control", "-c", str(config), *(a for s in sets for a in ("--set", s))]
    return subprocess.Popen([*argv, *extra], cwd=tmp_path, env=env, text=True, **popen)  # type: ignore[call-overload]


def test_a_second_control_on_the_same_state_file_is_refused_until_the_first_dies(tmp_path: Path) -> None:
    state_path = tmp_path / "control.sqlite"
    ready = tmp_path / "ready.json"
    holder = userctl_control(tmp_path, state_path, "--ready-file", str(ready), stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: ready.is_file() or holder.poll() is not None, "the first control to serve", 120)
        assert holder.poll() is None and json.loads(ready.read_text())["grpc_port"] > 0
        second = userctl_control(tmp_path, state_path, stderr=subprocess.PIPE)
        try:
            _, err = second.communicate(timeout=120)
        finally:
            second.kill()  # a no-op once it exited; ends one that would serve beside the first
            second.wait()
        lines = [line for line in err.splitlines() if not line.startswith("{")]
        assert (second.returncode, lines) == (
            2,
            [f"userctl control: control.state_path {state_path} is in use by pid {holder.pid}"],
        )
        with pytest.raises(ConfigError, match=f"^control.state_path {state_path} is in use by pid {holder.pid}$"):
            ControlService(control_cfg(state_path), start_metrics=False)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    control = ControlService(control_cfg(state_path), start_metrics=False).start()  # the kernel dropped the lock
    control.stop()


# --------------------------------------------------------------------------- 3: a disk that fills under the state


def test_a_full_disk_under_the_state_file_ends_no_stream_and_is_written_once_space_returns(
    tiny_disk: Callable[[str], Path], make_control, caplog: pytest.LogCaptureFixture
) -> None:  # tiny_disk first: its unmount runs after the controls stop
    disk = tiny_disk("1m")
    state_path = disk / "control.sqlite"
    control = make_control(state_path)
    edge = Edge(control)
    lease_id = edge.client.registered.lease_id
    s = stub(control)
    try:
        edge.finish(3)
        wait_for(lambda: robot(control).status.episodes == 3, "the first episodes stored")
        assert metric("user_control_persist_failing") == 0
        failures = metric("user_control_persist_failures_total")

        filler = fill(disk)
        caplog.set_level(logging.WARNING, logger="services.control.state")

        def failing() -> bool:  # the WAL reuses the space it holds: episodes go on until one needs a new block
            edge.finish()
            return metric("user_control_persist_failing") == 1

        wait_for(failing, "a write to fail", 60)
        n = edge.finish(5)
        wait_for(lambda: robot(control).status.episodes == n, "episodes served from memory")
        wait_for(lambda: metric("user_control_persist_failures_total") >= failures + 2, "the writes tried again")
        warned = [r for r in caplog.records if r.name == "services.control.state"]
        assert len(warned) == 1 and "lost if control stops" in warned[0].getMessage()
        # Every RPC that writes still answers: no stream ended, nothing UNKNOWN, and a new edge registers.
        late = Edge(control, "lab-pc-2", "arm-1")
        late.close()
        worker = control_pb2.WorkerInfo(worker_id="learner@gpu-1:1", kind="learner", experiments=["reach"])
        s.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=worker), timeout=5)
        s.StopExperiment(control_pb2.StopExperimentRequest(name="reach"), timeout=5)
        wait_for(lambda: edge.leases["arm-0"].hold, "the stop relayed down the same stream")
        s.StartExperiment(control_pb2.StartExperimentRequest(name="reach"), timeout=5)
        wait_for(lambda: robot(control).lease == "reach", "leased again")
        assert edge.client.reconnects == 0 and edge.client.registered.lease_id == lease_id
        assert metric("user_control_persist_failing") == 1

        filler.unlink()
        wait_for(lambda: metric("user_control_persist_failing") == 0, "the waiting writes written")
        n = edge.finish(2)  # after space returned
        wait_for(lambda: robot(control).status.episodes == n, "the last episodes stored")
        assert metric("user_control_persist_failing") == 0 and metric("user_control_persist_pending") == 0
        assert edge.client.reconnects == 0
    finally:
        edge.close()
        control.stop()

    control = make_control(state_path)  # a restart reads all of it back from the file
    after = robot(control)
    kept = control.cfg.control.episodes_kept
    assert after.status.episodes == n
    assert [e.episode_id for e in after.recent_episodes] == [f"ep-{i}" for i in range(n)][-kept:]
    assert robot(control, "arm-1").agent_id == "lab-pc-2"  # registered while the disk was full
    workers = stub(control).ListWorkers(control_pb2.ListWorkersRequest(include_offline=True), timeout=5).workers
    assert [w.worker_id for w in workers] == ["learner@gpu-1:1"]


def test_a_state_file_that_cannot_be_created_is_one_config_error(tiny_disk: Callable[[str], Path]) -> None:
    disk = tiny_disk("1m")
    fill(disk)
    state_path = disk / "control.sqlite"
    with pytest.raises(ConfigError) as refused:
        ControlService(control_cfg(state_path), start_metrics=False)
    assert str(refused.value).startswith(f"control.state_path {state_path}: cannot ")
    assert "full" in str(refused.value) or "No space" in str(refused.value)
    assert "\n" not in str(refused.value)


# --------------------------------------------------------------------------- 4: counts that survive an edge restart


def test_a_robots_episode_count_is_controls_stored_one_across_edge_restarts(make_control, tmp_path: Path) -> None:
    """GetRobot/ListRobots (`robots ls`) count what control stored, as `exp status` sums it; the edge's own
    counter restarts with the edge process."""
    control = make_control(tmp_path / "control.sqlite")
    edge = Edge(control)
    try:
        edge.finish(3)
        wait_for(lambda: robot(control).status.episodes == 3, "the first session's episodes")
    finally:
        edge.close()
    edge = Edge(control, first=3)  # a restarted edge: its counter starts at 0 again
    try:
        edge.finish(2)
        info = wait_for(lambda: (r := robot(control)).status.episodes == 5 and r, "the second session's episodes")
        assert edge.counter == 2 and info.status.successes == 3  # ep-0, ep-2, ep-4
        exp = stub(control).GetExperiment(control_pb2.GetExperimentRequest(name="reach"), timeout=5)
        assert [(r.robot_id, r.episodes, r.successes) for r in exp.robots] == [("arm-0", 5, 3)]
        listed = stub(control).ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
        assert [(r.spec.robot_id, r.status.episodes) for r in listed] == [("arm-0", 5)]
    finally:
        edge.close()
