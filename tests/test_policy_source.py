"""Policy sources against real servers: the Inference service (remote) and a learner weight stream (local)."""

from __future__ import annotations

import functools
from collections.abc import Iterator

import grpc
import numpy as np
import pytest
import torch

from edge_agent.policy_source import LocalPolicy, RemotePolicy, RoutedPolicy, make_policy_source
from services.inference.server import InferenceService
from tests import helpers
from tests.helpers import free_port, wait_for
from user import rpc
from user.config import AuthConfig, ServerConfig, StackConfig
from user.policy import policy_spec_for
from user.v1 import learner_pb2_grpc
from user.weights import WeightServicer, WeightStore

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
OBS = {"state": np.linspace(-1, 1, 15, dtype=np.float32)}
DEADLINE_S = 5.0  # generous: these tests check answers, not latency


random_weights = functools.partial(helpers.random_weights, ACTOR)


@pytest.fixture
def inference() -> Iterator[InferenceService]:
    cfg = StackConfig(auth=AUTH)
    cfg.inference.server.port = 0
    cfg.inference.server.grace_s = 0.5
    svc = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    yield svc
    svc.stop()


def test_remote_nothing_listening_returns_none() -> None:
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AUTH)
    try:
        assert policy.act("arm-0", OBS, deadline_s=0.05) is None
        assert policy.version == 0
    finally:
        policy.close()


def test_remote_no_policy_yet_then_actions(inference: InferenceService) -> None:
    policy = RemotePolicy(inference.address, AUTH)
    try:
        assert policy.act("arm-0", OBS, DEADLINE_S) is None  # UNAVAILABLE "no policy yet"
        inference.load_weights(random_weights(3))
        answer = policy.act("arm-0", OBS, DEADLINE_S)
        assert answer is not None
        action, version = answer
        assert action.shape == (3,) and action.dtype == np.float32
        assert version == 3 == policy.version
        assert np.all(np.abs(action) <= 1.0)
    finally:
        policy.close()


def test_remote_bad_observation_returns_none(inference: InferenceService) -> None:
    inference.load_weights(random_weights(1))
    policy = RemotePolicy(inference.address, AUTH)
    try:
        assert policy.act("arm-0", {"state": np.zeros(4, np.float32)}, DEADLINE_S) is None  # INVALID_ARGUMENT
    finally:
        policy.close()


def test_remote_wrong_token_returns_none(inference: InferenceService) -> None:
    inference.load_weights(random_weights(1))
    policy = RemotePolicy(inference.address, AuthConfig(token="wrong"))
    try:
        assert policy.act("arm-0", OBS, DEADLINE_S) is None  # UNAUTHENTICATED: hold, do not crash
    finally:
        policy.close()


def test_local_policy_follows_weight_stream() -> None:
    store = WeightStore()
    servicer = WeightServicer(store, poll_s=0.2)
    server = rpc.start_server(
        "learner-test",
        lambda s: learner_pb2_grpc.add_LearnerServicer_to_server(servicer, s),
        ["user.v1.Learner"],
        ServerConfig(host="127.0.0.1", port=0, grace_s=0.5),
        AUTH,
        start_metrics=False,
    )
    policy = LocalPolicy(server.address(), AUTH, client_id="edge-test")
    try:
        assert policy.act("arm-0", OBS, DEADLINE_S) is None  # no weights yet
        assert policy.version == 0
        store.publish(1, policy_spec_for(ACTOR), random_weights(1, seed=1).tensors)
        assert wait_for(lambda: policy.version == 1)
        first = policy.act("arm-0", OBS, DEADLINE_S)
        assert first is not None and first[0].shape == (3,) and first[1] == 1

        store.publish(2, policy_spec_for(ACTOR), random_weights(2, seed=2).tensors)
        assert wait_for(lambda: policy.version == 2)
        second = policy.act("arm-0", OBS, DEADLINE_S)
        assert second is not None and second[1] == 2
        assert policy.act("arm-0", {"state": np.zeros(4, np.float32)}, DEADLINE_S) is None  # wrong size: hold
    finally:
        policy.close()
        store.close()
        server.stop()


def test_make_policy_source_chooses_by_config() -> None:
    cfg = StackConfig(auth=AUTH)
    cfg.edge.inference_addr = cfg.edge.learner_addr = f"127.0.0.1:{free_port()}"
    remote = make_policy_source(cfg, "edge-0")
    cfg.edge.policy_source = "local"
    local = make_policy_source(cfg, "edge-0")
    try:
        assert isinstance(remote, RemotePolicy)
        assert isinstance(local, RoutedPolicy) and isinstance(local.sources["default"], LocalPolicy)
        assert local.act("arm-0", OBS, 0.05) is None
    finally:
        remote.close()
        local.close()


def test_inference_errors_are_logged_once_a_minute_however_they_flap(caplog: pytest.LogCaptureFixture) -> None:
    """A robot whose inference keeps failing (nothing listens here) or flaps between codes writes one warning, not
    one per held tick or per change of code (that was ~55k lines a day per robot); a minute on, the next says how
    many calls failed meanwhile."""
    policy = RemotePolicy(f"127.0.0.1:{free_port()}", AuthConfig(token="test-token-0123456789"))
    obs = {"state": np.zeros(3, np.float32)}
    try:
        with caplog.at_level("INFO", logger="edge_agent.policy_source"):
            for _ in range(20):
                assert policy.act("arm-0", obs, 0.05) is None
            for code in [grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.FAILED_PRECONDITION] * 50:
                policy._note_error(code, "flapping")
            warnings = [r for r in caplog.records if r.getMessage() == "no action from inference; holding"]
            assert len(warnings) == 1
            policy._warned_at -= 61  # a minute later
            policy._note_error(grpc.StatusCode.RESOURCE_EXHAUSTED, "busy")
            warnings = [r for r in caplog.records if r.getMessage() == "no action from inference; holding"]
            assert len(warnings) == 2 and warnings[1].fields["failed_calls"] >= 101  # type: ignore[attr-defined]
    finally:
        policy.close()
