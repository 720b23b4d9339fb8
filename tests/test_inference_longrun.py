"""Inference over a long run: nothing kept per robot or per experiment outlives it, and routing never makes an Act
wait on control. A policy version a robot last acted with is released once a newer one serves; routes are rebuilt
in the background from every robot control lists (one it forgot is dropped; an Act for one not routed is answered
at once, even while control is stuck); policy loads are one INFO line, then a summary at most once a minute; an
experiment removed at run time leaves no metric series behind. Real control and inference gRPC services on
127.0.0.1 ephemeral ports, edges registered through a real ControlClient."""

from __future__ import annotations

import gc
import json
import logging
import weakref
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import grpc
import numpy as np
import pytest
import torch
from prometheus_client import REGISTRY

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from services.inference import server as inference_server
from services.inference.server import InferenceService
from tests import helpers
from tests.plugins import ConstantPolicy
from tests.test_replay_store import spec
from user import wire
from user.config import AuthConfig, StackConfig
from user.policy import POLICIES
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, inference_pb2, inference_pb2_grpc, learner_pb2
from user.weights import WeightSet

AUTH = AuthConfig(token="test-token")
OBS_DIM = 15  # these seeded weights overflow to NaN on a huge state (as in test_serving_safety)
SAC = {
    "obs_keys": ["state"],
    "obs_dim": OBS_DIM,
    "action_dim": 3,
    "hidden": [16, 16],
    "action_low": [-1.0] * 3,
    "action_high": [1.0] * 3,
}
HUGE = np.full(OBS_DIM, -3e38, np.float32)
ONE = [{"name": "reach", "robots": {"ids": ["arm-0"]}}]
TWO = [{"name": "reach", "robots": {"ids": ["arm-0"]}}, {"name": "pick", "robots": {"ids": ["arm-1"]}}]
Stack = tuple[ControlService, InferenceService, inference_pb2_grpc.InferenceStub]
Started = Callable[[list[dict[str, Any]]], Stack]


@POLICIES.register("test_longrun_unbatched", description="test: a constant policy whose forward drops the batch axis")
class Unbatched(ConstantPolicy):
    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        return super().act(observation, deterministic)[0]


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _cfg(experiments: list[dict[str, Any]]) -> StackConfig:
    cfg = StackConfig.model_validate({"auth": AUTH.model_dump(), "experiments": experiments})
    for section in (cfg.control, cfg.inference):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.2
    return cfg


@pytest.fixture
def started() -> Iterator[Started]:
    """Starts control and inference (weights loaded by hand) routing `experiments`; stops them after the test."""
    running: list[Any] = []

    def start(experiments: list[dict[str, Any]]) -> Stack:
        cfg = _cfg(experiments)
        control = ControlService(cfg, start_metrics=False).start()
        running.append(control)
        cfg.inference.control_addr = control.address
        inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
        running.append(inference)
        return control, inference, inference_pb2_grpc.InferenceStub(make_channel(inference.address, AUTH))

    yield start
    for service in reversed(running):
        service.stop()


def _edge(control: ControlService, *robot_ids: str) -> ControlClient:
    """A registered edge with robots of OBS_DIM states and 3 actions."""
    specs = [spec(rid, obs_dim=OBS_DIM) for rid in robot_ids]
    status = lambda: [control_pb2.RobotStatus(robot_id=rid) for rid in robot_ids]  # noqa: E731
    edge = ControlClient(control.address, AUTH, "pc-1", specs, status, lambda cmd: (True, ""))
    edge.start()
    assert edge.wait_registered(10)
    return edge


def _request(robot_id: str, state: np.ndarray | None = None) -> inference_pb2.ActRequest:
    state = np.zeros(OBS_DIM, np.float32) if state is None else state
    return inference_pb2.ActRequest(robot_id=robot_id, observation=wire.to_tensor_map({"state": state}))


def _call(stub: inference_pb2_grpc.InferenceStub, robot_id: str, state: np.ndarray | None = None) -> Any:
    """The response, or the RpcError it was refused with."""
    try:
        return stub.Act(_request(robot_id, state), timeout=30)
    except grpc.RpcError as err:
        return err


def _served(stub: inference_pb2_grpc.InferenceStub, robot_id: str, version: int) -> bool:
    """True once `robot_id` is answered by `version` (refusals while it is not routed yet are retried)."""
    answer = _call(stub, robot_id)
    if isinstance(answer, grpc.RpcError):
        assert answer.code() == grpc.StatusCode.UNAVAILABLE, answer.details()
        return False
    return answer.policy_version == version


def _code(stub: inference_pb2_grpc.InferenceStub, robot_id: str) -> grpc.StatusCode:
    answer = _call(stub, robot_id)
    return answer.code() if isinstance(answer, grpc.RpcError) else grpc.StatusCode.OK


def _sac(version: int) -> WeightSet:
    return helpers.random_weights(SAC, version)


# --------------------------------------------------------------------------- 1: fit verdicts pin no policy


def test_a_robot_that_left_keeps_no_policy_version_alive(started: Started) -> None:
    """arm-0 acts with version 1 (its fit checked against its spec) and leaves; version 2 serves: version 1 is
    released (a VLA's weights are GBs), and version 2 still serves a robot that comes."""
    control, inference, stub = started(ONE)
    edge = _edge(control, "arm-0")
    inference.load_weights(_sac(1))
    helpers.wait_for(lambda: _served(stub, "arm-0", 1), "arm-0 served by version 1")
    first = weakref.ref(inference.slots["reach"].policy)
    edge.close()
    inference.load_weights(_sac(2))
    gc.collect()
    assert first() is None, f"version 1 still referenced by {[type(r).__name__ for r in gc.get_referrers(first())]}"
    edge = _edge(control, "arm-0")
    try:
        helpers.wait_for(lambda: _served(stub, "arm-0", 2), "arm-0 served by version 2")
    finally:
        edge.close()


# --------------------------------------------------------------------------- 2: routing never waits on control


def test_an_act_for_a_robot_not_routed_is_answered_while_control_is_stuck(started: Started) -> None:
    """With control's registry locked (every ListRobots stuck inside control), a routed robot is served and one not
    routed is answered UNAVAILABLE "not routed" by the Act itself, never after a ListRobots of its own."""
    control, inference, stub = started(TWO)
    edge = _edge(control, "arm-0")
    try:
        inference.load_weights(_sac(1))
        helpers.wait_for(lambda: _served(stub, "arm-0", 1), "arm-0 served")
        helpers.wait_for(lambda: _code(stub, "stranger") == grpc.StatusCode.FAILED_PRECONDITION, "stranger checked")
        with control.registry._lock:  # control is up but answers nothing until released
            answer = _call(stub, "arm-7")
            assert isinstance(answer, grpc.RpcError)
            assert answer.code() == grpc.StatusCode.UNAVAILABLE and "not routed" in answer.details(), answer.details()
            assert _call(stub, "arm-0").policy_version == 1  # the routes held keep serving
        helpers.wait_for(lambda: _code(stub, "arm-7") == grpc.StatusCode.FAILED_PRECONDITION, "arm-7 checked")
    finally:
        edge.close()


def test_a_robot_control_forgot_is_dropped_from_the_routes(started: Started) -> None:
    """Routes are rebuilt from every robot control lists: arm-0's edge hangs up, an operator forgets its robots
    (Control.ForgetRobot) and they are no longer routed (spec and route dropped) with no Act asking; arm-0 is
    routed again when it comes back. (An offline robot control still lists keeps its route: test_review_fixes_edge.)"""
    control, inference, stub = started(TWO)
    inference.load_weights(_sac(1))
    edge = _edge(control, "arm-0", "arm-1")
    router = inference.router
    helpers.wait_for(lambda: _served(stub, "arm-0", 1), "arm-0 served")
    helpers.wait_for(lambda: router.spec("arm-1") is not None, "arm-1 routed")
    assert [s.robot_id for s in router.specs_in("reach")] == ["arm-0"]
    edge.close()
    operator = control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))
    for rid in ("arm-0", "arm-1"):  # refused (FAILED_PRECONDITION) until control has seen the edge go
        helpers.wait_for(lambda rid=rid: _forgotten(operator, rid), f"{rid} forgotten")
    helpers.wait_for(lambda: router.spec("arm-0") is None and router.spec("arm-1") is None, "both pruned")
    assert router.specs_in("reach") == [] and router.specs_in("pick") == []
    assert _code(stub, "arm-0") in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.FAILED_PRECONDITION)
    edge = _edge(control, "arm-0")
    try:
        helpers.wait_for(lambda: _served(stub, "arm-0", 1), "arm-0 served again")
    finally:
        edge.close()


def _forgotten(operator: control_pb2_grpc.ControlStub, robot_id: str) -> bool:
    """Control.ForgetRobot; False while control still has the robot online."""
    try:
        operator.ForgetRobot(control_pb2.ForgetRobotRequest(robot_id=robot_id), timeout=10)
    except grpc.RpcError as err:
        assert err.code() == grpc.StatusCode.FAILED_PRECONDITION, err.details()
        return False
    return True


# --------------------------------------------------------------------------- 3: policy loads are not one INFO each


def test_policy_loads_log_the_first_at_info_then_a_summary(
    started: Started, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Five versions within the minute: one INFO line (the first), every load at DEBUG. With the summary due at
    each load, each later load writes one INFO summary counting the versions since the last."""
    _, inference, _ = started(ONE)
    caplog.set_level(logging.DEBUG, logger=inference_server.__name__)

    def lines(message: str, level: int) -> list[logging.LogRecord]:
        return [r for r in caplog.records if r.getMessage() == message and r.levelno == level]

    for version in range(1, 6):
        inference.load_weights(_sac(version))
    assert [r.__dict__["fields"]["version"] for r in lines("policy loaded", logging.INFO)] == [1]
    assert [r.__dict__["fields"]["version"] for r in lines("policy loaded", logging.DEBUG)] == [2, 3, 4, 5]
    assert lines("policy versions loaded", logging.INFO) == []
    monkeypatch.setattr(inference_server, "LOADS_SUMMARY_S", 0.0)
    inference.load_weights(_sac(6))
    inference.load_weights(_sac(7))
    summaries = [r.__dict__["fields"] for r in lines("policy versions loaded", logging.INFO)]
    assert [(s["loaded"], s["version"]) for s in summaries] == [(5, 6), (1, 7)]
    assert len(lines("policy loaded", logging.INFO)) == 1


# --------------------------------------------------------------------------- 4: a removed experiment's series go


def _series(experiment: str) -> list[str]:
    """Every inference sample labelled with `experiment`."""
    return [
        f"{sample.name}{sample.labels}"
        for family in REGISTRY.collect()
        if family.name.startswith("user_inference_")
        for sample in family.samples
        if sample.labels.get("experiment") == experiment
    ]


def test_an_experiment_removed_at_run_time_leaves_no_metric_series(
    started: Started, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An experiment defined at run time is served (version, a non-finite action, a forward failure and a misfit
    counted under its name), then stopped and removed through control: none of its series remain."""
    monkeypatch.setattr(inference_server, "EXPERIMENTS_POLL_S", 0.1)
    control, inference, stub = started(TWO)
    name = "late-longrun"
    ctl = control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))
    definition = {"name": name, "robots": {"ids": ["arm-5"]}}
    ctl.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=json.dumps(definition)), timeout=30)
    helpers.wait_for(lambda: name in inference.slots, "inference to serve it")
    edge = _edge(control, "arm-5")
    try:
        inference.load_weights(_sac(1), name)
        helpers.wait_for(lambda: _served(stub, "arm-5", 1), "arm-5 served")
        assert _code(stub, "arm-5") == grpc.StatusCode.OK
        answer = _call(stub, "arm-5", HUGE)
        assert answer.code() == grpc.StatusCode.INTERNAL and "non-finite" in answer.details()
        broken = learner_pb2.PolicySpec(kind="test_longrun_unbatched", config_json=json.dumps({"obs_keys": ["state"]}))
        inference.load_weights(WeightSet(version=2, policy=broken, tensors={"action": np.zeros(3)}), name)
        assert _code(stub, "arm-5") == grpc.StatusCode.INTERNAL
        with pytest.raises(ValueError, match="fits none of its robots"):
            inference.load_weights(WeightSet(version=3, policy=broken, tensors={"action": np.zeros(4)}), name)
        kept = _series(name)
        for family in ("policy_version", "non_finite_actions", "forward_failures", "policy_misfits"):
            assert any(family in s for s in kept), (family, kept)
        ctl.StopExperiment(control_pb2.StopExperimentRequest(name=name), timeout=5)
        ctl.RemoveExperiment(control_pb2.RemoveExperimentRequest(name=name), timeout=5)
        helpers.wait_for(lambda: name not in inference.slots, "inference to drop it")
        helpers.wait_for(lambda: not _series(name), "its series to go (removed after its batcher stops)")
    finally:
        edge.close()
