"""Experiments as control-plane objects: start/stop, leases by selector, a control restart that loses
nothing, robots going offline and coming back, edges holding and the learner pausing while an experiment
is stopped. Real control (a process where it restarts), real edge ControlClients and EdgeAgent, real
replay, inference and learner, real SQLite in tmp_path."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
import yaml

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from tests import helpers
from tests.helpers import free_port, wait_for
from tests.test_replay_store import spec
from user import cli
from user.config import AuthConfig, ExperimentConfig, RobotSelector, StackConfig
from user.rpc import Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc, robot_pb2

ROOT = Path(__file__).resolve().parents[1]
AUTH = AuthConfig(token="test-token-0123456789")
ALL = control_pb2.ListRobotsRequest(include_offline=True)
RUNNING, STOPPED = control_pb2.EXPERIMENT_STATE_RUNNING, control_pb2.EXPERIMENT_STATE_STOPPED


def team_spec(robot_id: str, team: str) -> robot_pb2.RobotSpec:
    s = spec(robot_id)
    s.labels["team"] = team
    return s


def experiments(max_alpha: int = 0) -> list[ExperimentConfig]:
    return [
        ExperimentConfig(name="alpha", robots=RobotSelector(labels={"team": "a"}), max_robots=max_alpha),
        ExperimentConfig(name="beta", robots=RobotSelector(labels={"team": "b"}), table="lab_b"),
    ]


class Edge:
    """A ControlClient that remembers the last lease control told it per robot."""

    def __init__(self, addr: str, agent_id: str, specs: list[robot_pb2.RobotSpec], statuses: list | None = None):
        self.leases: dict[str, control_pb2.RobotLease] = {}
        self.history: list[control_pb2.RobotLease] = []
        self.commands: list[control_pb2.Command] = []
        self.statuses = statuses if statuses is not None else []
        self.client = ControlClient(
            addr,
            AUTH,
            agent_id,
            specs,
            lambda: [_copy(s) for s in self.statuses],
            self._command,
            backoff=Backoff(0.05, 0.3),
            on_leases=self._on_leases,
        )

    def _on_leases(self, leases: list[control_pb2.RobotLease]) -> None:
        self.history.extend(leases)
        self.leases.update({lease.robot_id: lease for lease in leases})

    def _command(self, cmd: control_pb2.Command) -> tuple[bool, str]:
        self.commands.append(cmd)
        return True, f"did {cmd.kind}"

    def lease(self, robot_id: str) -> tuple[str, bool]:
        lease = self.leases.get(robot_id)
        return (lease.experiment, lease.hold) if lease is not None else ("?", False)

    def close(self) -> None:
        self.client.close()


def _copy(status: control_pb2.RobotStatus) -> control_pb2.RobotStatus:
    out = control_pb2.RobotStatus()
    out.CopyFrom(status)
    return out


def stub_for(addr: str, token: str | None = None) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(addr, AuthConfig(token=token or AUTH.token)))


def robot(stub: control_pb2_grpc.ControlStub, robot_id: str) -> control_pb2.RobotInfo:
    return stub.GetRobot(control_pb2.GetRobotRequest(robot_id=robot_id), timeout=5)


def online(stub: control_pb2_grpc.ControlStub, robot_id: str) -> bool:
    """False while control is not reachable yet (the channel reconnects on its own)."""
    try:
        return robot(stub, robot_id).online
    except grpc.RpcError:
        return False


def experiment(stub: control_pb2_grpc.ControlStub, name: str) -> control_pb2.ExperimentInfo:
    return stub.GetExperiment(control_pb2.GetExperimentRequest(name=name), timeout=5)


# --------------------------------------------------------------------------- a control process, restarted


class ControlProcess:
    """`userctl control` on a fixed port and SQLite file, so it can be killed and started again."""

    def __init__(self, tmp_path: Path) -> None:
        self.port = free_port()
        self.addr = f"127.0.0.1:{self.port}"
        self.config = tmp_path / "stack.yaml"
        self.ready = tmp_path / "ready.json"
        self.config.write_text(
            yaml.safe_dump(
                {
                    "auth": {"token": AUTH.token},
                    "control": {
                        "server": {"port": self.port, "metrics_port": 0, "grace_s": 0.5},
                        "heartbeat_interval_s": 0.05,
                        "lease_ttl_s": 3.0,
                        "state_path": str(tmp_path / "control.sqlite"),
                    },
                    "experiments": [e.model_dump(mode="json") for e in experiments()],
                }
            )
        )
        self.proc: subprocess.Popen | None = None

    def start(self) -> ControlProcess:
        self.ready.unlink(missing_ok=True)
        cmd = [sys.executable, "-m", "user.cli", "control", "-c", str(self.config), "--ready-file", str(self.ready)]
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        wait_for(lambda: self.ready.exists() and self.ready.read_text().strip(), "control ready file", limit_s=60)
        assert json.loads(self.ready.read_text())["grpc_port"] == self.port
        return self

    def kill(self) -> None:
        """kill -9: whatever control acknowledged must already be on disk."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)
        self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(30)
            self.proc = None


@pytest.fixture
def control_proc(tmp_path: Path) -> Iterator[ControlProcess]:
    proc = ControlProcess(tmp_path)
    yield proc
    proc.stop()


def test_a_killed_and_restarted_control_keeps_experiments_leases_episodes_and_commands(
    control_proc: ControlProcess, capsys: pytest.CaptureFixture[str]
) -> None:
    control_proc.start()
    s = stub_for(control_proc.addr)
    base = ["--control", control_proc.addr, "--set", f"auth.token={AUTH.token}"]
    episodes = [
        control_pb2.EpisodeSummary(episode_id=f"ep-{i}", length=10, episode_return=float(i), success=i % 2 == 0)
        for i in range(4)
    ]
    status = control_pb2.RobotStatus(robot_id="arm-0", episodes=4, policy_version=7, new_episodes=episodes)
    pc1 = Edge(control_proc.addr, "lab-pc-1", [team_spec("arm-0", "a"), team_spec("arm-1", "a")], [status])
    pc2 = Edge(control_proc.addr, "lab-pc-2", [team_spec("arm-2", "b")])
    try:
        assert pc1.client.wait_registered(30) and pc2.client.wait_registered(30)
        # Leases by selector, told to the edges in Registered and shown in RobotInfo.
        assert (pc1.lease("arm-0"), pc1.lease("arm-1"), pc2.lease("arm-2")) == (
            ("alpha", False),
            ("alpha", False),
            ("beta", False),
        )
        assert (pc1.leases["arm-0"].table, pc2.leases["arm-2"].table) == ("", "lab_b")  # the experiment's table
        assert [(r.spec.robot_id, r.lease) for r in s.ListRobots(control_pb2.ListRobotsRequest()).robots] == [
            ("arm-0", "alpha"),
            ("arm-1", "alpha"),
            ("arm-2", "beta"),
        ]
        wait_for(lambda: experiment(s, "alpha").episodes == 4, "episodes of alpha")
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESET, robot_id="arm-0")
        sent = s.SendCommand(control_pb2.SendCommandRequest(command=cmd, wait_result_s=10), timeout=15)
        assert [r.ok for r in sent.results] == [True]
        # An operator stops beta: its robot is released and its edge told to hold.
        assert cli.main(["exp", "stop", "beta", *base]) == 0
        assert "experiment beta: stopped; leased -" in capsys.readouterr().out
        wait_for(lambda: pc2.lease("arm-2") == ("", True), "arm-2 held")
        assert robot(s, "arm-2").lease_reason == "experiment beta stopped"

        control_proc.kill()
        control_proc.start()
        wait_for(lambda: online(s, "arm-0") and online(s, "arm-2"), "edges back", limit_s=60)
        # Experiments: beta still stopped, alpha running; the edges got their leases back on registering.
        listed = {e.name: e.state for e in s.ListExperiments(control_pb2.ListExperimentsRequest()).experiments}
        assert listed == {"alpha": RUNNING, "beta": STOPPED}
        assert experiment(s, "beta").stopped_at_ns > 0
        wait_for(lambda: pc2.lease("arm-2") == ("", True) and pc1.lease("arm-0") == ("alpha", False))
        assert list(experiment(s, "alpha").leased_robots) == ["arm-0", "arm-1"]
        # The command history: GetCommand answers for a command sent before the restart.
        got = s.GetCommand(control_pb2.GetCommandRequest(command_id=sent.command_id), timeout=5)
        assert got.command.kind == control_pb2.COMMAND_KIND_RESET
        assert [(r.agent_id, r.ok) for r in got.results] == [("lab-pc-1", True)]
        # Episode history per experiment: re-sent episodes are counted once.
        wait_for(lambda: experiment(s, "alpha").policy_version == 7, "a heartbeat after the restart")
        alpha = experiment(s, "alpha")
        assert (alpha.episodes, alpha.successes, alpha.mean_return, alpha.policy_version) == (4, 2, 1.5, 7)
        assert [(r.robot_id, r.episodes, r.leased) for r in alpha.robots] == [("arm-0", 4, True), ("arm-1", 0, True)]
        assert cli.main(["exp", "status", "alpha", *base]) == 0
        out = capsys.readouterr().out
        assert "experiment alpha: running" in out and "leased 2: arm-0, arm-1" in out
        assert "episodes 4, success 50%, mean return 1.50, policy version 7" in out
        assert cli.main(["exp", "ls", *base]) == 0
        out = capsys.readouterr().out
        assert "alpha" in out and "beta" in out and "stopped" in out
        # Started again: arm-2 is leased and its edge runs it.
        assert cli.main(["exp", "start", "beta", *base]) == 0
        wait_for(lambda: pc2.lease("arm-2") == ("beta", False), "arm-2 leased again")
        assert cli.main(["robots", "ls", *base]) == 0
        assert "beta" in capsys.readouterr().out
    finally:
        pc1.close()
        pc2.close()


# --------------------------------------------------------------------------- leases: offline, max_robots


@pytest.fixture
def make_control(tmp_path: Path) -> Iterator:
    started: list[ControlService] = []

    def make(exps: list[ExperimentConfig], lease_ttl_s: float = 0.5) -> ControlService:
        cfg = StackConfig(auth=AUTH, experiments=exps)
        cfg.control.server.port = cfg.control.server.metrics_port = 0
        cfg.control.server.grace_s = 0.5
        cfg.control.heartbeat_interval_s = 0.05
        cfg.control.lease_ttl_s = lease_ttl_s
        cfg.control.state_path = tmp_path / "control.sqlite"
        svc = ControlService(cfg, start_metrics=False).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


class SilentEdge:
    """Registers, then never heartbeats: its lease times out while the stream stays open."""

    def __init__(self, addr: str, agent_id: str, specs: list[robot_pb2.RobotSpec]) -> None:
        self.up: queue.Queue = queue.Queue()
        self.up.put(control_pb2.EdgeMessage(register=control_pb2.RegisterRequest(agent_id=agent_id, robots=specs)))
        self.call = stub_for(addr).Connect(iter(self.up.get, None), timeout=60)
        self.registered = next(self.call).registered
        self.ended = threading.Event()
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        try:
            for _ in self.call:
                pass
        except grpc.RpcError:
            pass
        self.ended.set()

    def close(self) -> None:
        self.up.put(None)
        self.call.cancel()


def test_a_stream_cut_while_registered_is_sent_releases_its_robots_at_once(make_control) -> None:
    """A client that cancels while `registered` is on its way: gRPC drops the handler's generator at that
    yield (no code after it runs) and runs the RPC's callbacks. Its robots must go offline then, not when the
    lease runs out (CI once waited 30 s here for a max_robots place)."""
    control = make_control(experiments(max_alpha=1), lease_ttl_s=60.0)
    s = stub_for(control.address)
    register = control_pb2.RegisterRequest(agent_id="cut-pc-1", robots=[team_spec("cut-arm-0", "a")])
    ctx = helpers.EndingContext()
    stream = control.servicer.Connect(iter([control_pb2.EdgeMessage(register=register)]), ctx)
    assert [lease.experiment for lease in next(stream).registered.leases] == ["alpha"]
    assert robot(s, "cut-arm-0").online
    stream.close()
    ctx.end()
    assert not robot(s, "cut-arm-0").online
    pc2 = Edge(control.address, "cut-pc-2", [team_spec("cut-arm-1", "a")])
    try:
        wait_for(lambda: pc2.lease("cut-arm-1") == ("alpha", False), "the freed max_robots place")
    finally:
        pc2.close()


def test_a_robot_that_goes_silent_is_released_and_the_experiment_goes_on(make_control) -> None:
    control = make_control(experiments())
    s = stub_for(control.address)
    silent = SilentEdge(control.address, "lab-pc-1", [team_spec("arm-0", "a")])
    pc2 = Edge(control.address, "lab-pc-2", [team_spec("arm-1", "a")])
    try:
        assert [(lease.robot_id, lease.experiment) for lease in silent.registered.leases] == [("arm-0", "alpha")]
        assert pc2.client.wait_registered(10)
        assert list(experiment(s, "alpha").leased_robots) == ["arm-0", "arm-1"]
        # No heartbeat within lease_ttl_s: arm-0 goes offline, its lease is released; alpha keeps arm-1.
        assert silent.ended.wait(30)
        info = experiment(s, "alpha")
        assert info.state == RUNNING and list(info.leased_robots) == ["arm-1"]
        assert robot(s, "arm-0").lease == "" and not robot(s, "arm-0").online
        assert pc2.lease("arm-1") == ("alpha", False)
        # It comes back: leased again.
        back = Edge(control.address, "lab-pc-1", [team_spec("arm-0", "a")])
        try:
            assert back.client.wait_registered(10)
            assert back.lease("arm-0") == ("alpha", False)
            assert list(experiment(s, "alpha").leased_robots) == ["arm-0", "arm-1"]
        finally:
            back.close()
    finally:
        silent.close()
        pc2.close()


def test_max_robots_leases_the_first_and_a_waiting_robot_takes_a_freed_place(make_control) -> None:
    # Robot and agent ids of this test only: a stray edge of another test that finds this control on a reused port
    # must not take the freed place. No lease ends by the clock here.
    control = make_control(experiments(max_alpha=1), lease_ttl_s=30.0)
    s = stub_for(control.address)
    pc1 = Edge(control.address, "mr-pc-1", [team_spec("mr-arm-0", "a")])
    assert pc1.client.wait_registered(10)
    pc2 = Edge(control.address, "mr-pc-2", [team_spec("mr-arm-1", "a")])
    try:
        assert pc2.client.wait_registered(10)
        assert pc1.lease("mr-arm-0") == ("alpha", False)
        assert pc2.lease("mr-arm-1") == ("", True)
        assert robot(s, "mr-arm-1").lease_reason == "experiment alpha at max_robots=1"
        # lab-pc-1 reconnects (a new stream supersedes its old one): arm-0 keeps its place throughout.
        again = SilentEdge(control.address, "mr-pc-1", [team_spec("mr-arm-0", "a")])
        assert [(lease.robot_id, lease.experiment) for lease in again.registered.leases] == [("mr-arm-0", "alpha")]
        assert again.ended.wait(30)  # pc1's client reconnected and superseded it in turn
        again.close()
        assert all(lease.hold for lease in pc2.history)  # arm-1 was never leased meanwhile
        pc1.close()  # hangs up: its place goes to arm-1, told through its stream
        try:
            wait_for(lambda: pc2.lease("mr-arm-1") == ("alpha", False), "arm-1 leased")
        except AssertionError as exc:  # say who holds the place
            held = [(r.spec.robot_id, r.agent_id, r.online, r.lease) for r in s.ListRobots(ALL, timeout=5).robots]
            raise AssertionError(f"{exc}; robots: {held}") from None
        # arm-0 returns: the place stays with the robot holding it.
        pc1 = Edge(control.address, "mr-pc-1", [team_spec("mr-arm-0", "a")])
        assert pc1.client.wait_registered(10)
        assert pc1.lease("mr-arm-0") == ("", True)
        assert list(experiment(s, "alpha").leased_robots) == ["mr-arm-1"]
    finally:
        pc1.close()
        pc2.close()


def test_robots_no_experiment_selects_are_free(make_control) -> None:
    control = make_control(experiments())
    edge = Edge(control.address, "lab-pc-1", [team_spec("arm-9", "z")])
    try:
        assert edge.client.wait_registered(10)
        assert edge.lease("arm-9") == ("", False)  # not held: no experiment wants it
        info = robot(stub_for(control.address), "arm-9")
        assert (info.experiment, info.lease, info.lease_reason) == ("", "", "")
    finally:
        edge.close()


# --------------------------------------------------------------------------- roles and bad input

OPERATOR = "operator-token-0123456789"
READER = "reader-token-0123456789"
EDGE_TOKEN = "edge-token-lab-pc-1-0123456789"


def test_roles_for_the_experiment_rpcs_and_bad_input(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens.yaml"
    tokens.write_text(
        yaml.safe_dump(
            [
                {"token": OPERATOR, "role": "operator", "name": "alice"},
                {"token": READER, "role": "reader", "name": "grafana"},
                {"token": EDGE_TOKEN, "role": "edge", "name": "pc1", "agent_id": "lab-pc-1"},
            ]
        )
    )
    cfg = StackConfig(auth=AuthConfig(token=AUTH.token, tokens_file=tokens), experiments=experiments())
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.5
    control = ControlService(cfg, start_metrics=False).start()
    calls = {
        "list": lambda st: st.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5),
        "get": lambda st: st.GetExperiment(control_pb2.GetExperimentRequest(name="alpha"), timeout=5),
        "stop": lambda st: st.StopExperiment(control_pb2.StopExperimentRequest(name="alpha"), timeout=5),
        "start": lambda st: st.StartExperiment(control_pb2.StartExperimentRequest(name="alpha"), timeout=5),
        "define": lambda st: st.DefineExperiment(
            control_pb2.DefineExperimentRequest(definition_json='{"name": "delta", "robots": {"ids": ["d-0"]}}'),
            timeout=30,
        ),
    }

    def code(token: str, what: str, call=None) -> grpc.StatusCode:
        try:
            (call or calls[what])(stub_for(control.address, token))
        except grpc.RpcError as err:
            return err.code()
        return grpc.StatusCode.OK

    try:
        ok, denied = grpc.StatusCode.OK, grpc.StatusCode.PERMISSION_DENIED
        assert {w: code(READER, w) for w in calls} == {
            "list": ok,
            "get": ok,
            "stop": denied,
            "start": denied,
            "define": denied,
        }
        assert {w: code(OPERATOR, w) for w in calls} == {"list": ok, "get": ok, "stop": ok, "start": ok, "define": ok}
        assert {w: code(EDGE_TOKEN, w) for w in calls} == {w: denied for w in calls}
        assert code("not-a-token-0123456789", "list") == grpc.StatusCode.UNAUTHENTICATED
        assert experiment(stub_for(control.address), "alpha").state == RUNNING  # the refused stops changed nothing
        # Bad input: a malformed name, an unknown one.
        bad = [
            (lambda st: st.GetExperiment(control_pb2.GetExperimentRequest(name=""), timeout=5)),
            (lambda st: st.StopExperiment(control_pb2.StopExperimentRequest(name="a/b"), timeout=5)),
            (lambda st: st.StartExperiment(control_pb2.StartExperimentRequest(name="x" * 300), timeout=5)),
        ]
        assert {code(OPERATOR, "", c) for c in bad} == {grpc.StatusCode.INVALID_ARGUMENT}
        missing = lambda st: st.StopExperiment(control_pb2.StopExperimentRequest(name="gamma"), timeout=5)  # noqa: E731
        assert code(OPERATOR, "", missing) == grpc.StatusCode.NOT_FOUND
        missing = lambda st: st.GetExperiment(control_pb2.GetExperimentRequest(name="gamma"), timeout=5)  # noqa: E731
        assert code(READER, "", missing) == grpc.StatusCode.NOT_FOUND
    finally:
        control.stop()


def test_userctl_exp_names_the_problem(make_control, capsys: pytest.CaptureFixture[str]) -> None:
    control = make_control(experiments())
    base = ["--control", control.address, "--set", f"auth.token={AUTH.token}"]
    assert cli.main(["exp", "stop", *base]) == 2
    assert "name the experiment" in capsys.readouterr().err
    assert cli.main(["exp", "stop", "gamma", *base]) == 1
    err = capsys.readouterr().err
    assert "NOT_FOUND" in err and "known: alpha, beta" in err
    assert cli.main(["exp", "ls", "--json", *base]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [(e["name"], e["state"]) for e in listed["experiments"]] == [
        ("alpha", "EXPERIMENT_STATE_RUNNING"),
        ("beta", "EXPERIMENT_STATE_RUNNING"),
    ]


# --------------------------------------------------------------------------- stop: the edge holds, the learner pauses


def test_a_stopped_experiment_holds_its_robots_and_pauses_the_learner(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import torch

    from cloud_learner.learner import Learner
    from edge_agent.agent import EdgeAgent
    from services.inference.server import InferenceService
    from services.replay.server import ReplayService
    from tests.test_edge_agent import AUTH as EDGE_AUTH
    from tests.test_edge_agent import edge_cfg, random_weights, replay_stats, stack_cfg
    from user.weights import WeightStore

    torch.set_num_threads(1)
    cfg = stack_cfg(tmp_path)  # the default experiment: every sim_reach_arm
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    inference.load_weights(random_weights(5))
    edge_cfg(cfg, control, replay, inference)
    lc = cfg.learner
    lc.control_addr, lc.replay_addr, lc.checkpoint_dir = control.address, replay.address, tmp_path / "ckpt"
    lc.hidden, lc.batch_size, lc.min_transitions, lc.rpc_timeout_s = [16], 32, 50, 2.0
    agent = EdgeAgent(cfg)
    learner = Learner(cfg, WeightStore())
    (state,) = learner.experiment_states.values()
    s = control_pb2_grpc.ControlStub(make_channel(control.address, EDGE_AUTH))
    loop = agent.loops["arm-0"]

    def settle() -> tuple[int, int, int]:
        """Counts after the learner heard control twice more (steps in flight at the stop have landed)."""
        polls = learner.experiment_polls
        wait_for(lambda: learner.experiment_polls >= polls + 2, "learner polls", limit_s=60)
        assert agent.sender.flush(30)
        return loop.env_steps, state.updates, replay_stats(replay.address).steps

    agent.start()
    learner.start()
    try:
        wait_for(lambda: state.updates > 0 and loop.env_steps > 100, "collecting and training", limit_s=120)
        s.StopExperiment(control_pb2.StopExperimentRequest(name="default"), timeout=5)
        wait_for(lambda: loop.held_by_lease and state.state == "stopped", "edge holds, learner stopped", limit_s=60)
        held = settle()
        assert settle() == held  # no steps taken, none sent to replay, no updates
        info = control_pb2.GetRobotRequest(robot_id="arm-0")
        wait_for(lambda: s.GetRobot(info, timeout=5).status.state == control_pb2.ROBOT_STATE_PAUSED)
        assert cli.main(["robots", "ls", "--control", control.address, "--set", "auth.token=test-token"]) == 0
        assert "held (experiment default stopped)" in capsys.readouterr().out
        # An operator's RESUME does not override the stopped experiment.
        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_RESUME, robot_id="arm-0")
        s.SendCommand(control_pb2.SendCommandRequest(command=cmd, wait_result_s=10), timeout=15)
        assert settle() == held
        s.StartExperiment(control_pb2.StartExperimentRequest(name="default"), timeout=5)
        wait_for(
            lambda: loop.env_steps > held[0] and state.updates > held[1], "collecting and training again", limit_s=120
        )
        assert not loop.held_by_lease
    finally:
        learner.stop()
        agent.stop()
        inference.stop()
        replay.stop()
        control.stop()
    assert not learner.failed
