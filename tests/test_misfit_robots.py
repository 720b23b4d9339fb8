"""A robot its learner cannot train (its spec does not fit the layout fixed for its experiment) is held by control
with the learner's reason, not leased to record steps nothing trains on: WorkerInfo.misfit_robots. Real control
(in process, gRPC on 127.0.0.1), the learner's real worker reporter, real edge ControlClients; at the end a real
LearnerService whose experiment's layout a late robot of another shape does not fit."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

from cloud_learner.learner import ExperimentRun
from cloud_learner.server import LearnerService, failed_experiments
from edge_agent.control_client import ControlClient
from services.control.server import MAX_MISFIT_ROBOTS, ControlService
from tests.helpers import wait_for
from tests.test_replay_store import spec
from user import cli
from user.config import AuthConfig, ExperimentConfig, RobotSelector, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc
from user.worker import WorkerReporter, report_worker, worker_info

AUTH = AuthConfig(token="test-token-0123456789")
BOTH = ExperimentConfig(name="both", robots=RobotSelector(ids=["arm-0", "arm-1"]))
WHY = "robot arm-1 (test) does not fit the layout the learner fixed for it"


def control_service(tmp_path: Path) -> ControlService:
    cfg = StackConfig(auth=AUTH, experiments=[BOTH])
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.05
    cfg.control.state_path = tmp_path / "control.sqlite"
    return ControlService(cfg, start_metrics=False).start()


@pytest.fixture
def control(tmp_path: Path) -> Iterator[ControlService]:
    service = control_service(tmp_path)
    yield service
    service.stop()


def stub(control: ControlService) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))


def edge(control: ControlService, agent_id: str, specs: list) -> ControlClient:
    client = ControlClient(control.address, AUTH, agent_id, specs, lambda: [], lambda c: (True, "done"))
    assert client.wait_registered(10)
    return client


def leases(control: ControlService) -> dict[str, tuple[str, str]]:
    """robot_id -> (experiment it is leased to, why it holds), as `userctl robots ls` reads them."""
    robots = stub(control).ListRobots(control_pb2.ListRobotsRequest(without_episodes=True), timeout=5).robots
    return {r.spec.robot_id: (r.lease, r.lease_reason) for r in robots}


def test_a_misfit_robot_holds_with_the_reason_while_its_learner_reports_it(
    control: ControlService, capsys: pytest.CaptureFixture[str]
) -> None:
    client = edge(control, "lab-pc-1", [spec("arm-0"), spec("arm-1")])
    misfits: dict[str, str] = {}
    lock = threading.Lock()

    def info() -> control_pb2.WorkerInfo:  # as report_worker builds the learner's report
        out = worker_info("learner", "127.0.0.1:1", "cpu", ["both"])
        with lock:
            out.misfit_robots.update(misfits)
        return out

    reporter = WorkerReporter(control.address, AUTH, info).start()
    try:
        wait_for(lambda: leases(control) == {"arm-0": ("both", ""), "arm-1": ("both", "")}, "both leased")
        with lock:
            misfits["arm-1"] = WHY
        held = wait_for(lambda: (ls := leases(control))["arm-1"][0] == "" and ls, "arm-1 held")
        assert held == {"arm-0": ("both", ""), "arm-1": ("", f"experiment both: {WHY}")}
        assert cli.main(["robots", "ls", "--control", control.address, "--set", f"auth.token={AUTH.token}"]) == 0
        assert "held (experiment both: robot arm-1 (test) does not fit" in capsys.readouterr().out.replace("\n", "")
        token = f"auth.token={AUTH.token}"
        assert cli.main(["exp", "status", "both", "--control", control.address, "--set", token]) == 0
        status = capsys.readouterr().out
        assert f"held 1 (online, selected, not acting):\n    arm-1: experiment both: {WHY}" in status, status

        with lock:
            misfits.clear()  # the report no longer names it: its normal lease comes back
        wait_for(lambda: leases(control) == {"arm-0": ("both", ""), "arm-1": ("both", "")}, "arm-1 leased again")
    finally:
        reporter.stop()
        client.close()


def test_a_misfit_report_of_a_learner_serving_another_experiment_holds_nothing(control: ControlService) -> None:
    """The hold applies in the experiments the reporting learner serves, not to a robot another learner trains."""
    client = edge(control, "lab-pc-1", [spec("arm-0"), spec("arm-1")])
    try:
        wait_for(lambda: leases(control)["arm-1"] == ("both", ""), "arm-1 leased")
        other = worker_info("learner", "127.0.0.1:2", "cpu", ["elsewhere"])
        other.misfit_robots["arm-1"] = WHY
        stub(control).RegisterWorker(control_pb2.RegisterWorkerRequest(worker=other), timeout=5)
        mine = worker_info("learner", "127.0.0.1:1", "cpu", ["both"])
        mine.misfit_robots["arm-0"] = "x" * 1000  # cut, as every hold reason sent down to a robot
        stub(control).RegisterWorker(control_pb2.RegisterWorkerRequest(worker=mine), timeout=5)
        got = leases(control)
        assert got["arm-1"] == ("both", "")
        assert got["arm-0"][0] == "" and got["arm-0"][1] == "experiment both: " + "x" * 200 + "..."
    finally:
        client.close()


@pytest.mark.parametrize(
    ("misfits", "problem"),
    [
        ({f"arm-{i}": "why" for i in range(MAX_MISFIT_ROBOTS + 1)}, f"at most {MAX_MISFIT_ROBOTS} entries"),
        ({"bad id " + "y" * 500: "why"}, "must match"),
    ],
)
def test_a_misfit_report_out_of_bounds_is_refused(
    control: ControlService, misfits: dict[str, str], problem: str
) -> None:
    info = worker_info("learner", "127.0.0.1:1", "cpu", ["both"])
    info.misfit_robots.update(misfits)
    with pytest.raises(grpc.RpcError) as err:
        stub(control).RegisterWorker(control_pb2.RegisterWorkerRequest(worker=info), timeout=5)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert problem in (err.value.details() or "")
    assert len(err.value.details() or "") < 400  # the id is clipped in the error, not echoed whole
    assert stub(control).ListWorkers(control_pb2.ListWorkersRequest(), timeout=5).workers == []


def test_a_late_robot_of_another_shape_is_held_by_control_end_to_end(control: ControlService, tmp_path: Path) -> None:
    """The learner fixes `both`'s layout with arm-0; arm-1 (7-dim observations) joins later: the learner does not
    train it, reports it, and control holds it with the learner's reason while arm-0 keeps its lease."""
    cfg = StackConfig(auth=AUTH, experiments=[BOTH])
    lc = cfg.learner
    lc.server.port = lc.server.metrics_port = 0
    lc.server.grace_s = 0.5
    lc.control_addr, lc.replay_addr = control.address, "127.0.0.1:1"  # replay never reached: nothing is sampled
    lc.checkpoint_dir = tmp_path / "ckpt"
    lc.weights_shm_dir = lc.replay_shm_dir = None
    first = edge(control, "lab-pc-1", [spec("arm-0")])
    service = LearnerService(cfg, start_metrics=False)
    late = None
    # The wiring of cloud_learner.server.run: the learner's real report, with its misfit robots.
    with report_worker(
        service,
        "learner",
        control.address,
        AUTH,
        "cpu",
        lambda: [e.name for e in service.learner.experiments],
        service.learner.preparing,
        lambda: failed_experiments(service.learner),
        service.learner.misfit_robots,
    ):
        service.start()
        try:
            run = wait_for(lambda: service.learner.runs.get("both"), "the learner starts both with arm-0", 60)
            assert isinstance(run, ExperimentRun) and sorted(run.specs) == ["arm-0"]
            late = edge(control, "lab-pc-2", [spec("arm-1", obs_dim=7)])
            held = wait_for(lambda: (ls := leases(control)).get("arm-1", ("?", ""))[0] == "" and ls, "arm-1 held", 60)
            assert held["arm-0"] == ("both", "")
            assert "arm-1" in held["arm-1"][1] and "different observations or actions" in held["arm-1"][1]
            assert sorted(run.specs) == ["arm-0"]  # not trained
        finally:
            if late is not None:
                late.close()
            first.close()
            service.stop()
