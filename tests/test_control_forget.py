"""Control forgets what it would otherwise keep for good: robots (Control.ForgetRobot, `userctl robots forget`,
control.forget_offline_after_days), the metric series of removed experiments and workers long offline. Real
control (in process, gRPC on 127.0.0.1, SQLite in tmp_path) and real edge ControlClients."""

from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path

import grpc
import prometheus_client
import pytest
import yaml

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from tests.helpers import wait_for
from tests.test_replay_store import spec
from user import cli
from user.config import AuthConfig, ExperimentConfig, RobotSelector, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc
from user.worker import WorkerReporter, worker_info

ADMIN = "test-admin-token-0123456789"
OPERATOR = "test-operator-token-0123456789"
READER = "test-reader-token-0123456789"
REACH = ExperimentConfig(name="reach", robots=RobotSelector(ids=["arm-0", "arm-1"]))


def auth_for(tmp_path: Path) -> AuthConfig:
    tokens = tmp_path / "tokens.yaml"
    entries = [{"token": OPERATOR, "role": "operator", "name": "op"}, {"token": READER, "role": "reader", "name": "rd"}]
    tokens.write_text(yaml.safe_dump(entries))
    return AuthConfig(token=ADMIN, tokens_file=tokens)


def control_cfg(tmp_path: Path) -> StackConfig:
    cfg = StackConfig(auth=auth_for(tmp_path), experiments=[REACH])
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.05
    cfg.control.state_path = tmp_path / "control.sqlite"
    return cfg


def stub(control: ControlService, token: str = ADMIN) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(control.address, AuthConfig(token=token)))


class Robots:
    """The edge's status_fn: each robot's finished episodes go up once, in the next heartbeat."""

    def __init__(self, *robot_ids: str) -> None:
        self._lock = threading.Lock()
        self._new: dict[str, list[control_pb2.EpisodeSummary]] = {rid: [] for rid in robot_ids}
        self._done = dict.fromkeys(robot_ids, 0)

    def finish(self, robot_id: str, n: int, successes: int) -> None:
        with self._lock:
            for i in range(n):
                self._done[robot_id] += 1
                ep_id = f"{robot_id}-e{self._done[robot_id]}"
                ep = control_pb2.EpisodeSummary(episode_id=ep_id, length=10, episode_return=i + 1.0)
                ep.success = i < successes
                self._new[robot_id].append(ep)

    def status(self) -> list[control_pb2.RobotStatus]:
        with self._lock:
            out = [
                control_pb2.RobotStatus(robot_id=rid, state=control_pb2.ROBOT_STATE_RUNNING, new_episodes=eps)
                for rid, eps in self._new.items()
            ]
            self._new = {rid: [] for rid in self._new}
        return out


def edge(control: ControlService, agent_id: str, robots: Robots, *robot_ids: str) -> ControlClient:
    client = ControlClient(
        control.address, AuthConfig(token=ADMIN), agent_id, [spec(r) for r in robot_ids], robots.status, lambda c: None
    )
    assert client.wait_registered(10)
    return client


def robot_ids(control: ControlService) -> dict[str, bool]:
    """robot_id -> online, of every robot control knows."""
    req = control_pb2.ListRobotsRequest(include_offline=True, without_episodes=True)
    return {r.spec.robot_id: r.online for r in stub(control).ListRobots(req, timeout=5).robots}


def reach(control: ControlService) -> control_pb2.ExperimentInfo:
    return stub(control).GetExperiment(control_pb2.GetExperimentRequest(name="reach"), timeout=5)


def totals(info: control_pb2.ExperimentInfo) -> tuple[int, int, float, int, int]:
    return info.episodes, info.successes, round(info.mean_return, 6), info.unhelped_episodes, info.unhelped_successes


def forget_error(control: ControlService, robot_id: str, token: str = ADMIN) -> tuple[grpc.StatusCode, str]:
    with pytest.raises(grpc.RpcError) as err:
        stub(control, token).ForgetRobot(control_pb2.ForgetRobotRequest(robot_id=robot_id), timeout=5)
    return err.value.code(), err.value.details()


def rows(path: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(path)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


def episode_samples() -> dict[tuple[tuple[str, str], ...], float]:
    """Every sample of user_control_episodes_total, by its label set."""
    return {
        tuple(sorted(s.labels.items())): s.value
        for metric in prometheus_client.REGISTRY.collect()
        for s in metric.samples
        if s.name == "user_control_episodes_total"
    }


def test_a_forgotten_robot_leaves_ram_sqlite_and_restarts_but_its_experiment_keeps_its_episodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = control_cfg(tmp_path)
    control = ControlService(cfg, start_metrics=False).start()
    robots = Robots("arm-0", "arm-1")
    client = edge(control, "lab-pc-1", robots, "arm-0", "arm-1")
    try:
        successes_before = episode_samples().get((("success", "true"),), 0.0)
        robots.finish("arm-0", 3, successes=2)
        robots.finish("arm-1", 2, successes=1)
        wait_for(lambda: reach(control).episodes == 5, "5 episodes counted")
        before = totals(reach(control))
        # Control's episode counter has no robot label (edges export user_edge_episodes_total{robot_id}).
        samples = episode_samples()
        assert all("robot_id" not in dict(labels) for labels in samples), samples
        assert samples[(("success", "true"),)] - successes_before == 3

        assert forget_error(control, "arm-0")[0] == grpc.StatusCode.FAILED_PRECONDITION  # online
        assert forget_error(control, "arm-7")[0] == grpc.StatusCode.NOT_FOUND
        code, details = forget_error(control, "a/b")
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "robot_id" in details
        assert forget_error(control, "arm-0", READER)[0] == grpc.StatusCode.PERMISSION_DENIED

        client.set_robots([spec("arm-1")])  # arm-0 unplugged: offline
        wait_for(lambda: robot_ids(control) == {"arm-0": False, "arm-1": True}, "arm-0 offline")
        token = f"auth.token={OPERATOR}"
        assert cli.main(["robots", "forget", "arm-0", "--control", control.address, "--set", token]) == 0
        assert "robot arm-0 forgotten (3 episodes" in capsys.readouterr().out
        assert robot_ids(control) == {"arm-1": True}
        assert forget_error(control, "arm-0")[0] == grpc.StatusCode.NOT_FOUND
        after = reach(control)
        assert totals(after) == before  # the experiment's episodes do not drop
        assert [r.robot_id for r in after.robots] == ["arm-1"]
        robots.finish("arm-1", 1, successes=1)  # its experiment still counts on
        wait_for(lambda: reach(control).episodes == 6, "arm-1's next episode counted")
        before = totals(reach(control))
    finally:
        client.close()
        control.stop()

    db = cfg.control.state_path
    for table in ("robots", "episodes", "leases"):
        assert rows(db, f"SELECT DISTINCT robot_id FROM {table} ORDER BY robot_id") == [("arm-1",)], table
    control = ControlService(cfg, start_metrics=False).start()
    try:
        assert robot_ids(control) == {"arm-1": False}
        assert totals(reach(control)) == before
        assert [r.robot_id for r in reach(control).robots] == ["arm-1"]
    finally:
        control.stop()


def test_robots_offline_for_forget_offline_after_days_are_forgotten_online_ones_never(tmp_path: Path) -> None:
    cfg = control_cfg(tmp_path)
    cfg.control.forget_offline_after_days = 0.5 / 86400  # half a second
    control = ControlService(cfg, start_metrics=False).start()
    robots = Robots("arm-0")
    stays = edge(control, "lab-pc-2", Robots("arm-1"), "arm-1")
    goes = edge(control, "lab-pc-1", robots, "arm-0")
    try:
        robots.finish("arm-0", 2, successes=1)
        wait_for(lambda: reach(control).episodes == 2, "arm-0's episodes counted")
        before = totals(reach(control))
        forgotten = (
            prometheus_client.REGISTRY.get_sample_value("user_control_robots_forgotten_total", {"how": "offline"})
            or 0.0
        )
        goes.close()
        wait_for(lambda: "arm-0" not in robot_ids(control), "offline arm-0 forgotten")
        assert robot_ids(control) == {"arm-1": True}
        after = prometheus_client.REGISTRY.get_sample_value("user_control_robots_forgotten_total", {"how": "offline"})
        assert after == forgotten + 1
        assert totals(reach(control)) == before
    finally:
        goes.close()
        stays.close()
        control.stop()
    assert rows(cfg.control.state_path, "SELECT robot_id FROM episodes") == []


def test_a_removed_experiment_leaves_no_metric_series(tmp_path: Path) -> None:
    control = ControlService(control_cfg(tmp_path), start_metrics=False).start()
    robots = Robots("arm-9")
    client = edge(control, "lab-pc-1", robots, "arm-9")
    labels = {"experiment": "fleeting"}
    try:
        definition = {"name": "fleeting", "robots": {"ids": ["arm-9"]}}
        req = control_pb2.DefineExperimentRequest(definition_json=json.dumps(definition))
        stub(control).DefineExperiment(req, timeout=30)
        leased = prometheus_client.REGISTRY.get_sample_value
        wait_for(lambda: leased("user_control_robots_leased", labels) == 1, "arm-9 leased to fleeting")
        assert leased("user_control_experiment_running", labels) == 1
        stub(control).StopExperiment(control_pb2.StopExperimentRequest(name="fleeting"), timeout=5)
        stub(control).RemoveExperiment(control_pb2.RemoveExperimentRequest(name="fleeting"), timeout=5)
        for name in ("user_control_robots_leased", "user_control_experiment_running"):
            assert prometheus_client.REGISTRY.get_sample_value(name, labels) is None, name
    finally:
        client.close()
        control.stop()


def test_workers_offline_for_long_are_deleted_from_ram_and_sqlite(tmp_path: Path) -> None:
    cfg = control_cfg(tmp_path)
    cfg.control.worker_ttl_s = 0.2  # deleted after services.control.server.WORKER_FORGET_TTLS x 0.2 s offline
    control = ControlService(cfg, start_metrics=False).start()
    old = worker_info("inference", "127.0.0.1:1", "cpu", [])  # a restart on another port leaves this one behind
    live = worker_info("inference", "127.0.0.1:2", "cpu", [])
    reporter = WorkerReporter(control.address, AuthConfig(token=ADMIN), lambda: live).start()
    try:
        stub(control).RegisterWorker(control_pb2.RegisterWorkerRequest(worker=old), timeout=5)

        def listed() -> list[str]:
            req = control_pb2.ListWorkersRequest(include_offline=True)
            return [w.worker_id for w in stub(control).ListWorkers(req, timeout=5).workers]

        assert old.worker_id in listed()
        wait_for(lambda: old.worker_id not in listed(), f"{old.worker_id} deleted")
        wait_for(lambda: listed() == [live.worker_id], "the reporting worker listed")
    finally:
        reporter.stop()
        control.stop()
    assert old.worker_id not in [w for (w,) in rows(cfg.control.state_path, "SELECT worker_id FROM workers")]
