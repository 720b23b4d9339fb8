"""Experiments defined while the stack runs (Control.DefineExperiment, `userctl exp define`): validated as a
config entry, persisted by control, leased to the robots no earlier selector picks, trained by the running
learner and served by the running inference service, with nothing restarted. Real control (SQLite in
tmp_path), replay (LMDB), inference, learner and edge agent with MuJoCo arms."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import grpc
import pytest
import yaml

from services.control.server import ControlService
from tests.helpers import wait_for
from tests.test_control_experiments import AUTH, Edge, experiments, stub_for, team_spec
from user import cli
from user.config import StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc

RUNNING, STOPPED = control_pb2.EXPERIMENT_STATE_RUNNING, control_pb2.EXPERIMENT_STATE_STOPPED
GAMMA = {"name": "gamma", "robots": {"labels": {"team": "c"}}, "algorithm": {"kind": "sac", "params": {"hidden": [16]}}}


def define(stub: control_pb2_grpc.ControlStub, definition: object) -> control_pb2.ExperimentInfo:
    text = definition if isinstance(definition, str) else json.dumps(definition)
    return stub.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=text), timeout=30)


def refused(stub: control_pb2_grpc.ControlStub, definition: object) -> tuple[grpc.StatusCode, str]:
    with pytest.raises(grpc.RpcError) as err:
        define(stub, definition)
    return err.value.code(), err.value.details()


def control_at(tmp_path: Path) -> ControlService:
    cfg = StackConfig(auth=AUTH, experiments=experiments())
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.05
    cfg.control.lease_ttl_s = 0.5
    cfg.control.state_path = tmp_path / "control.sqlite"
    return ControlService(cfg, start_metrics=False).start()


def test_a_defined_experiment_leases_free_robots_and_survives_a_control_restart(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    control = control_at(tmp_path)
    edge: Edge | None = None
    try:
        stub = stub_for(control.address)
        edge = Edge(control.address, "pc-1", [team_spec("a-0", "a"), team_spec("c-0", "c")])
        edge.client.start()
        wait_for(lambda: edge.lease("a-0") == ("alpha", False) and "c-0" in edge.leases, "leases")
        assert edge.lease("c-0") == ("", False)  # no experiment selects it: free
        with caplog.at_level(logging.WARNING, logger="services.control.server"):
            info = define(stub, GAMMA)
        assert info.name == "gamma" and info.state == RUNNING and info.defined_at_runtime
        assert not [r for r in caplog.records if "can get no robot" in r.getMessage()]  # nothing takes its robots
        wait_for(lambda: edge.lease("c-0") == ("gamma", False), "the free robot leased to gamma")
        assert edge.lease("a-0") == ("alpha", False)
        listed = stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5).experiments
        assert [(e.name, e.defined_at_runtime) for e in listed] == [("alpha", False), ("beta", False), ("gamma", True)]
        assert json.loads(listed[2].definition_json)["algorithm"]["params"] == {"hidden": [16]}
        # An experiment that selects robots an earlier one holds takes none of them (the first selector wins).
        define(stub, {**GAMMA, "name": "greedy", "robots": {}})
        assert stub.GetExperiment(control_pb2.GetExperimentRequest(name="greedy"), timeout=5).leased_robots == []
        stub.StopExperiment(control_pb2.StopExperimentRequest(name="gamma"), timeout=5)
    finally:
        if edge is not None:
            edge.client.close()
        control.stop()
    control = control_at(tmp_path)  # the same SQLite file: definitions and their state come back
    try:
        listed = stub_for(control.address).ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5)
        got = [(e.name, e.state, e.defined_at_runtime) for e in listed.experiments]
        assert got == [
            ("alpha", RUNNING, False),
            ("beta", RUNNING, False),
            ("gamma", STOPPED, True),
            ("greedy", RUNNING, True),
        ]
    finally:
        control.stop()


def test_a_stored_definition_that_no_longer_checks_is_skipped_not_fatal(tmp_path: Path) -> None:
    """A definition stored by an older version that this one's config model refuses: control starts without it."""
    from services.control.state import ControlState

    state = ControlState(tmp_path / "control.sqlite")
    state.save_definition("old", json.dumps({**GAMMA, "name": "old", "retired_field": 1}))
    state.save_definition("ok", json.dumps({**GAMMA, "name": "ok"}))
    state.close()
    control = control_at(tmp_path)
    try:
        listed = stub_for(control.address).ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5)
        assert [e.name for e in listed.experiments] == ["alpha", "beta", "ok"]
    finally:
        control.stop()


def test_a_bad_definition_is_refused_naming_the_field_and_changes_nothing(tmp_path: Path) -> None:
    control = control_at(tmp_path)
    try:
        stub = stub_for(control.address)
        cases = {
            "not json": "{",
            "not an object": "[1]",
            "a typo in a field": {**GAMMA, "robot": {}},
            "a typo in a param": {**GAMMA, "algorithm": {"kind": "sac", "params": {"hiden": [16]}}},
            "an unknown algorithm": {**GAMMA, "algorithm": {"kind": "sack"}},
            "a bad name": {**GAMMA, "name": "a/b"},
            "too long": {**GAMMA, "robots": {"labels": {"x": "y" * 70_000}}},
        }
        got = {why: refused(stub, case) for why, case in cases.items()}
        assert {code for code, _ in got.values()} == {grpc.StatusCode.INVALID_ARGUMENT}, got
        assert "definition.robot" in got["a typo in a field"][1]
        assert "definition.algorithm.params" in got["a typo in a param"][1] and "hiden" in got["a typo in a param"][1]
        assert "sack" in got["an unknown algorithm"][1] and "definition.name" in got["a bad name"][1]
        assert refused(stub, {**GAMMA, "name": "alpha"})[0] == grpc.StatusCode.ALREADY_EXISTS
        names = [e.name for e in stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5).experiments]
        assert names == ["alpha", "beta"]
    finally:
        control.stop()


def remove(stub: control_pb2_grpc.ControlStub, name: str) -> control_pb2.ExperimentInfo:
    return stub.RemoveExperiment(control_pb2.RemoveExperimentRequest(name=name), timeout=5)


def test_a_stopped_defined_experiment_is_removed_its_robots_go_on_and_its_name_stays_taken(tmp_path: Path) -> None:
    control = control_at(tmp_path)
    edge: Edge | None = None
    try:
        stub = stub_for(control.address)
        edge = Edge(control.address, "pc-1", [team_spec("c-0", "c")])
        edge.client.start()
        define(stub, GAMMA)
        define(stub, {**GAMMA, "name": "next"})  # selects c-0 too, after gamma: it gets it once gamma is gone
        wait_for(lambda: edge.lease("c-0") == ("gamma", False), "c-0 leased to gamma")

        def code(name: str) -> tuple[grpc.StatusCode, str]:
            with pytest.raises(grpc.RpcError) as err:
                remove(stub, name)
            return err.value.code(), err.value.details()

        assert code("gamma")[0] == grpc.StatusCode.FAILED_PRECONDITION and "stop it first" in code("gamma")[1]
        assert code("alpha")[0] == grpc.StatusCode.FAILED_PRECONDITION and "stack config" in code("alpha")[1]
        assert code("nope")[0] == grpc.StatusCode.NOT_FOUND and code("a/b")[0] == grpc.StatusCode.INVALID_ARGUMENT
        stub.StopExperiment(control_pb2.StopExperimentRequest(name="gamma"), timeout=5)
        wait_for(lambda: edge.lease("c-0") == ("", True), "c-0 held by the stopped gamma")
        assert remove(stub, "gamma").name == "gamma"
        wait_for(lambda: edge.lease("c-0") == ("next", False), "c-0 leased to the next experiment selecting it")
        names = [e.name for e in stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5).experiments]
        assert names == ["alpha", "beta", "next"]
        assert code("gamma")[0] == grpc.StatusCode.NOT_FOUND
        assert refused(stub, GAMMA) == (grpc.StatusCode.ALREADY_EXISTS, refused(stub, GAMMA)[1])
        assert "was removed" in refused(stub, GAMMA)[1]
    finally:
        if edge is not None:
            edge.client.close()
        control.stop()
    control = control_at(tmp_path)  # the same SQLite file: gone for good, the name still taken
    try:
        stub = stub_for(control.address)
        names = [e.name for e in stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5).experiments]
        assert names == ["alpha", "beta", "next"]
        assert "was removed" in refused(stub, GAMMA)[1]
    finally:
        control.stop()


def test_userctl_exp_define_reads_yaml(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    control = control_at(tmp_path)
    try:
        path = tmp_path / "gamma.yaml"
        path.write_text(yaml.safe_dump(GAMMA))
        base = ["--control", control.address, "--set", f"auth.token={AUTH.token}"]
        assert cli.main(["exp", "define", str(path), *base]) == 0
        assert "experiment gamma (defined): running" in capsys.readouterr().out
        assert cli.main(["exp", "define", str(path), *base]) == 1
        assert "ALREADY_EXISTS" in capsys.readouterr().err
        assert cli.main(["exp", "define", str(tmp_path / "missing.yaml"), *base]) == 2
        assert "cannot read" in capsys.readouterr().err
        assert cli.main(["exp", "ls", *base]) == 0
        assert "gamma (defined)" in capsys.readouterr().out
        assert cli.main(["exp", "remove", "gamma", *base]) == 1
        assert "FAILED_PRECONDITION" in capsys.readouterr().err
        assert cli.main(["exp", "stop", "gamma", *base]) == 0
        assert cli.main(["exp", "remove", "gamma", *base]) == 0
        assert "experiment gamma removed" in capsys.readouterr().out
        path.write_text(yaml.safe_dump({**GAMMA, "name": "steal", "robots": {"labels": {"team": "a", "x": "y"}}}))
        assert cli.main(["exp", "define", str(path), *base]) == 0
        assert "note: experiment alpha comes first and selects every robot steal selects" in capsys.readouterr().err
    finally:
        control.stop()


def served(stub: control_pb2_grpc.ControlStub) -> set[str]:
    workers = stub.ListWorkers(control_pb2.ListWorkersRequest(), timeout=5).workers
    return {name for w in workers if w.kind == "inference" for name in w.experiments}


@pytest.mark.parametrize("policy_source", ["remote", "local"])
def test_a_running_stack_trains_and_serves_an_experiment_defined_while_it_runs(
    tmp_path: Path, policy_source: str
) -> None:
    """Two sim arms on one edge; the config's experiments select arm-0 only, so arm-1 holds. Defined while
    everything runs, `late` gets arm-1 leased by control, an algorithm instance in the learner, a policy slot
    and weight stream in inference, and arm-1 acts with `late`'s weights: nothing restarted. With a local
    policy the edge follows control's lease to a copy subscribed to `late` (its config names no `late`)."""
    import torch

    from cloud_learner.server import LearnerService
    from edge_agent.agent import EdgeAgent
    from services.inference.server import InferenceService, report_to_control
    from services.replay.server import ReplayService
    from tests.test_edge_agent import edge_cfg, stack_cfg
    from user.config import ExperimentConfig, PluginChoice, RobotConfig, RobotSelector

    torch.set_num_threads(1)
    cfg = stack_cfg(tmp_path)
    small = PluginChoice(kind="sac", params={"hidden": [16], "batch_size": 32})
    cfg.experiments = [  # two, so inference routes every robot through control (one experiment serves all)
        ExperimentConfig(name="first", robots=RobotSelector(ids=["arm-0"]), algorithm=small),
        ExperimentConfig(name="elsewhere", robots=RobotSelector(ids=["arm-9"]), algorithm=small),
    ]
    cfg.control.state_path = tmp_path / "control.sqlite"
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = cfg.learner.control_addr = cfg.inference.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    lc = cfg.learner
    lc.replay_addr, lc.checkpoint_dir, lc.min_transitions, lc.rpc_timeout_s = replay.address, tmp_path / "ckpt", 50, 2.0
    lc.server.port = lc.server.metrics_port = 0
    learner = LearnerService(cfg, start_metrics=False).start()
    cfg.inference.learner_addr = learner.address
    inference = InferenceService(cfg, start_metrics=False).start()
    edge_cfg(cfg, control, replay, inference)
    cfg.edge.robots = [
        RobotConfig(id=f"arm-{i}", kind="sim_reach_arm", params={"max_episode_steps": 20}) for i in range(2)
    ]
    cfg.edge.policy_source, cfg.edge.learner_addr = policy_source, learner.address
    agent = EdgeAgent(cfg)
    agent.start()
    stub = control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth))
    reporter = report_to_control(inference)  # as `userctl inference` reports what it serves
    reporter.__enter__()
    try:
        first, late = agent.loops["arm-0"], agent.loops["arm-1"]
        wait_for(lambda: first.env_steps > 50 and first.policy_version >= 1, "arm-0 acting", limit_s=120)
        assert late.policy_version == 0  # no experiment selects it: inference routes it nowhere, it holds
        definition = {
            "name": "late",
            "robots": {"ids": ["arm-1"]},
            "algorithm": {"kind": "sac", "params": {"hidden": [16], "batch_size": 32}},
            "table": "late",
        }
        stub.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=json.dumps(definition)), timeout=30)
        wait_for(lambda: "late" in learner.learner.experiment_states, "the learner to hear of it", limit_s=60)
        wait_for(
            lambda: learner.learner.experiment_states["late"].updates > 0 and late.policy_version >= 1,
            "late trained and acting with its own weights",
            limit_s=180,
        )
        if policy_source == "local":
            routes = agent.policy.routes  # type: ignore[attr-defined]
            assert routes["arm-1"]._subscriber.experiment == "late"
            assert routes["arm-0"]._subscriber.experiment == "first"
        wait_for(lambda: "late" in inference.slots, "inference to open a slot for it", limit_s=30)
        slot = inference.slots["late"]
        wait_for(lambda: slot.policy is not None, "late's weights in inference", limit_s=60)
        assert slot.policy is not None and slot.subscriber is not None
        assert inference.router.route("arm-1")[0] == "late" and inference.router.route("arm-0")[0] == "first"
        states = learner.learner.experiment_states
        assert states["late"].robot_ids == ["arm-1"] and states["first"].robot_ids == ["arm-0"]
        assert states["first"].state != "failed" and states["late"].state != "failed"
        info = stub.GetExperiment(control_pb2.GetExperimentRequest(name="late"), timeout=5)
        assert list(info.leased_robots) == ["arm-1"] and info.defined_at_runtime
        wait_for(lambda: served(stub) == {"first", "elsewhere", "late"}, "the worker report to name all", limit_s=30)
        # A name the learner does not train is NOT_FOUND at once, not a weight stream that never delivers.
        weights = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))
        with pytest.raises(grpc.RpcError) as err:
            next(weights.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(experiment="nope"), timeout=30))
        assert err.value.code() == grpc.StatusCode.NOT_FOUND and "late" in err.value.details()
        # Stopped and removed: the learner ends its training (checkpoint kept), inference its slot, arm-1 holds.
        stub.StopExperiment(control_pb2.StopExperimentRequest(name="late"), timeout=5)
        stub.RemoveExperiment(control_pb2.RemoveExperimentRequest(name="late"), timeout=5)
        wait_for(lambda: "late" not in learner.learner.experiment_states, "the learner to drop it", limit_s=60)
        wait_for(lambda: "late" not in inference.slots, "inference to drop it", limit_s=30)
        assert "late" not in learner.learner.runs and (tmp_path / "ckpt" / "late").is_dir()
        wait_for(lambda: slot.batcher._stop.is_set() and slot.subscriber is None, "its batcher and stream to stop")
        wait_for(lambda: served(stub) == {"first", "elsewhere"}, "the worker report to drop it", limit_s=30)
        # Free now: inference refuses it (a local copy holds it at once); actions already on their way may land.
        wait_for(lambda: _steady(late), "arm-1 to stop acting")
        acted, others = _acted(late), first.env_steps
        wait_for(lambda: first.env_steps > others + 40, "arm-0 acting on")
        assert _acted(late) <= acted + 1  # no experiment selects it now: it holds (held steps only)
        assert states["first"].state != "failed" and not learner.learner.failed
    finally:
        reporter.__exit__(None, None, None)
        agent.stop()
        inference.stop()
        learner.stop()
        replay.stop()
        control.stop()
    assert not learner.learner.failed


def _acted(loop: object) -> int:
    """Steps the robot took with an action (not held for want of one)."""
    return int(loop.env_steps - loop.held_steps)  # type: ignore[attr-defined]


def _steady(loop: object, window_s: float = 0.5) -> bool:
    """The loop took no step with an action over window_s."""
    import time

    before = _acted(loop)
    time.sleep(window_s)
    return _acted(loop) == before
