"""A policy that cannot drive its experiment's robots is never acted on: the learner fails the experiment before its
first publish (one error naming it and the mismatch), inference refuses a version that fits none of the robots it
routes and answers FAILED_PRECONDITION for a robot the served policy does not fit, and a policy whose forward returns
a mis-shaped batch fails its requests with a clear status, logged once a version and counted every time. Real
control (SQLite), replay (LMDB), learner and inference gRPC services on 127.0.0.1 ephemeral ports."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, Literal

import grpc
import numpy as np
import pytest
import torch
from prometheus_client import REGISTRY

from cloud_learner.algorithm import ALGORITHMS
from cloud_learner.server import LearnerService
from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from services.inference.server import InferenceService, PolicyMisfit
from services.replay.server import ReplayService
from tests import helpers
from tests.plugins import ConstantPolicy, MeanAction
from tests.test_learner_resume import stack_cfg
from tests.test_replay_store import spec
from user import wire
from user.config import AuthConfig, StackConfig
from user.policy import POLICIES, build_policy, check_fit, placeholders
from user.rpc import make_channel
from user.v1 import control_pb2, inference_pb2, inference_pb2_grpc, learner_pb2, learner_pb2_grpc, robot_pb2
from user.weights import WeightSet

AUTH = AuthConfig(token="test-token-0123456789")
SAC = {"obs_keys": ["state"], "obs_dim": 6, "action_dim": 3, "hidden": [8]}


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


@ALGORITHMS.register("test_misfit", description="test: publishes a constant policy that may not fit its robots")
class MisfitAction(MeanAction):
    class Params(MeanAction.Params):
        misfit: Literal["none", "keys", "action"] = "none"

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        spec, tensors = super().policy()
        if self.params.misfit == "keys":  # type: ignore[attr-defined]
            spec.config_json = json.dumps({"obs_keys": ["joint_pos"]})
        elif self.params.misfit == "action":  # type: ignore[attr-defined]
            tensors = {"action": np.zeros(self.layout.action_dim + 1, np.float32)}
        return spec, tensors


@POLICIES.register("test_broken_rows", description="test: a constant policy whose forward returns a bad batch")
class BrokenRows(ConstantPolicy):
    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        batch = super().act(observation, deterministic)
        if json.loads(self.spec.config_json)["broken"] == "unbatched":
            return batch[0]
        return np.concatenate([batch, batch], axis=1)  # rows of twice the declared action


def sac(version: int, **config: Any) -> WeightSet:
    cfg = {**SAC, **config}
    dims = int(cfg["action_dim"])
    return helpers.random_weights({**cfg, "action_low": [-1.0] * dims, "action_high": [1.0] * dims}, version)


def _metric(name: str, labels: dict[str, str]) -> float:
    return REGISTRY.get_sample_value(name, labels) or 0.0


def _errors(caplog: pytest.LogCaptureFixture, fragment: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.levelno >= logging.ERROR and fragment in r.getMessage()]


# --------------------------------------------------------------------------- the check itself


def test_check_fit_names_keys_sizes_and_action_size() -> None:
    weights = sac(1)
    policy = build_policy(weights.policy, weights.tensors, 1)
    state = placeholders({"state": ((6,), "float32")})
    check_fit(policy, state, 3)
    with pytest.raises(ValueError, match=r"reads observation keys \['state'\]; the robots have \['joint_pos'\]"):
        check_fit(policy, placeholders({"joint_pos": ((6,), "float32")}), 3)
    with pytest.raises(ValueError, match=r"action has 3 values \(action_shape \[3\]\); the robots' has 2"):
        check_fit(policy, state, 2)
    with pytest.raises(ValueError, match="observation has 5 features"):
        check_fit(policy, placeholders({"state": ((5,), "float32")}), 3)


# --------------------------------------------------------------------------- the learner


@pytest.fixture
def learner_stack(tmp_path: Path) -> Iterator[StackConfig]:
    experiments = [
        {"name": "keys", "robots": {"labels": {"team": "a"}}, "algorithm": misfit("keys")},
        {"name": "action", "robots": {"labels": {"team": "b"}}, "algorithm": misfit("action")},
        {"name": "ok", "robots": {"labels": {"team": "c"}}, "algorithm": misfit("none")},
    ]
    cfg = stack_cfg(tmp_path, experiments)
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = cfg.learner.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    cfg.learner.replay_addr = replay.address
    specs = [_labelled(f"{team}-0", team) for team in "abc"]
    edge = ControlClient(control.address, cfg.auth, "pc-1", specs, lambda: [], lambda c: (True, ""))
    edge.start()
    try:
        yield cfg
    finally:
        edge.close()
        replay.stop()
        control.stop()


def misfit(kind: str) -> dict[str, Any]:
    return {"kind": "test_misfit", "params": {"misfit": kind}}


def _labelled(robot_id: str, team: str) -> robot_pb2.RobotSpec:
    s = spec(robot_id)
    s.labels["team"] = team
    return s


def test_a_policy_that_does_not_fit_fails_its_experiment_before_any_publish(
    learner_stack: StackConfig, caplog: pytest.LogCaptureFixture
) -> None:
    """The repros: a policy reading `joint_pos` the robots lack, and one acting with 4 values for 3-dim robots.
    Each fails its experiment alone (GetStatus names it and the mismatch), nothing is published for it, one error
    line each; the experiment whose policy fits publishes and trains on."""
    learner = LearnerService(learner_stack, start_metrics=False).start()
    try:
        states = learner.learner.experiment_states
        helpers.wait_for(lambda: states["keys"].state == states["action"].state == "failed", "two failed")
        helpers.wait_for(lambda: states["ok"].weight_version >= 1, "ok published")
        stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, learner_stack.auth))
        reported = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10).experiments
        errors = {e.name: e.error for e in reported}
        assert errors["keys"].startswith("experiment keys: the 'test_constant' policy that algorithm 'test_misfit'")
        assert "reads observation keys ['joint_pos']; the robots have ['state']" in errors["keys"]
        assert "experiment action:" in errors["action"] and "action has 4 values" in errors["action"]
        assert "the robots' has 3" in errors["action"]
        assert errors["ok"] == "" and not learner.learner.failed
        assert learner.store.latest("keys") is None and learner.store.latest("action") is None
        for name in ("keys", "action"):
            lines = [
                r for r in _errors(caplog, "experiment cannot start") if r.__dict__["fields"]["experiment"] == name
            ]
            assert [r.__dict__["fields"]["error"] for r in lines] == [errors[name]]
    finally:
        learner.stop()


# --------------------------------------------------------------------------- inference


@pytest.fixture
def routed() -> Iterator[tuple[InferenceService, inference_pb2_grpc.InferenceStub]]:
    """Inference routing two robots through control: arm-0 acts with 3 values, arm-1 with 2."""
    reach = {"name": "reach", "robots": {"ids": ["arm-0", "arm-1"]}}
    cfg = StackConfig.model_validate({"auth": AUTH.model_dump(), "experiments": [reach]})
    for section in (cfg.control, cfg.inference):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.2
    control = ControlService(cfg, start_metrics=False).start()
    cfg.inference.control_addr = control.address
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    two = spec("arm-1")
    two.action.CopyFrom(robot_pb2.ActionSpace(shape=[2], low=[-1] * 2, high=[1] * 2, dtype=two.action.dtype))
    status = lambda: [control_pb2.RobotStatus(robot_id=r) for r in ("arm-0", "arm-1")]  # noqa: E731
    edge = ControlClient(control.address, AUTH, "pc-1", [spec("arm-0"), two], status, lambda c: (True, ""))
    edge.start()
    try:
        assert edge.wait_registered(10)
        inference.router.refresh()  # routes are refreshed in the background: this one now, for a steady answer
        yield inference, inference_pb2_grpc.InferenceStub(make_channel(inference.address, AUTH))
    finally:
        edge.close()
        inference.stop()
        control.stop()


def _act(robot_id: str) -> inference_pb2.ActRequest:
    return inference_pb2.ActRequest(
        robot_id=robot_id, observation=wire.to_tensor_map({"state": np.zeros(6, np.float32)})
    )


def _refused(stub: inference_pb2_grpc.InferenceStub, robot_id: str) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        stub.Act(_act(robot_id), timeout=30)
    return err.value


def test_inference_never_acts_with_a_policy_that_does_not_fit_the_robot(
    routed: tuple[InferenceService, inference_pb2_grpc.InferenceStub], caplog: pytest.LogCaptureFixture
) -> None:
    """Version 1 (3 actions) arrived before any robot asked: arm-0 is served, arm-1 (2 actions) gets
    FAILED_PRECONDITION naming the mismatch every time (counted), logged once. Versions that fit none of the routed
    robots (a key they lack, 4 actions) are refused at load, counted, and version 1 keeps serving."""
    inference, stub = routed
    inference.load_weights(sac(1))
    assert helpers.wait_for(lambda: stub.Act(_act("arm-0"), timeout=30).policy_version == 1, "arm-0 served")
    acts = {"experiment": "reach", "at": "act"}
    before = _metric("user_inference_policy_misfits_total", acts)
    for _ in range(3):
        err = _refused(stub, "arm-1")
        assert err.code() == grpc.StatusCode.FAILED_PRECONDITION, err.details()
        assert "does not fit robot 'arm-1'" in err.details() and "the robots' has 2" in err.details()
    assert _metric("user_inference_policy_misfits_total", acts) == before + 3
    assert len(_errors(caplog, "the policy does not fit a robot it serves")) == 1

    loads = {"experiment": "reach", "at": "load"}
    before = _metric("user_inference_policy_misfits_total", loads)
    with pytest.raises(PolicyMisfit, match=r"version 2 \(sac_mlp\) fits none of its robots.*\['joint_pos'\]"):
        inference.load_weights(sac(2, obs_keys=["joint_pos"]))
    with pytest.raises(PolicyMisfit, match=r"still serving version 1.*action has 4 values"):
        inference.load_weights(sac(3, action_dim=4))
    assert _metric("user_inference_policy_misfits_total", loads) == before + 2
    assert stub.Act(_act("arm-0"), timeout=30).policy_version == 1


@pytest.mark.parametrize(
    ("broken", "message"),
    [("unbatched", "policy returned shape (3,) for a batch of 1"), ("wide", "returned rows of shape [6]")],
)
def test_a_forward_of_the_wrong_shape_is_logged_once_a_version_and_counted_every_time(
    broken: str, message: str, caplog: pytest.LogCaptureFixture
) -> None:
    cfg = StackConfig.model_validate({"auth": AUTH.model_dump()})
    cfg.inference.server.port = cfg.inference.server.metrics_port = 0
    cfg.inference.server.grace_s = 0.2
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    stub = inference_pb2_grpc.InferenceStub(make_channel(inference.address, AUTH))
    labels = {"experiment": "default", "stage": "forward"}
    before = _metric("user_inference_forward_failures_total", labels)
    try:
        for version in (1, 2):
            config = json.dumps({"obs_keys": ["state"], "broken": broken})
            policy = learner_pb2.PolicySpec(kind="test_broken_rows", config_json=config)
            inference.load_weights(WeightSet(version=version, policy=policy, tensors={"action": np.zeros(3)}))
            for _ in range(4):
                err = _refused(stub, "arm-0")
                assert err.code() == grpc.StatusCode.INTERNAL and message in err.details(), err.details()
    finally:
        inference.stop()
    assert _metric("user_inference_forward_failures_total", labels) == before + 8
    logged = _errors(caplog, "policy forward failed")
    assert [r.__dict__["fields"]["version"] for r in logged] == [1, 2]  # once a version, not once a request
