"""Per-experiment weights: the store keeps one version sequence per experiment, local edge copies subscribe
to their robot's experiment (by labels), and a real weight server delivers each its own weights."""

from __future__ import annotations

import functools

import numpy as np
import torch

from edge_agent.policy_source import LocalPolicy, RoutedPolicy, make_policy_source
from tests import helpers
from tests.helpers import wait_for
from user import rpc
from user.config import AuthConfig, ServerConfig, StackConfig
from user.v1 import learner_pb2_grpc, robot_pb2
from user.weights import WeightServicer, WeightStore

torch.set_num_threads(1)

AUTH = AuthConfig(token="test-token")


def actor(obs_dim: int, action_dim: int) -> dict:
    return {
        "obs_keys": ["state"],
        "obs_dim": obs_dim,
        "action_dim": action_dim,
        "hidden": [8],
        "action_low": [-1.0] * action_dim,
        "action_high": [1.0] * action_dim,
    }


arm_weights = functools.partial(helpers.random_weights, actor(15, 3))
panda_weights = functools.partial(helpers.random_weights, actor(21, 7))


def test_store_keeps_one_version_sequence_per_experiment() -> None:
    store = WeightStore()
    a1 = arm_weights(1)
    store.publish(1, a1.policy, a1.tensors, experiment="reach")
    for version in (1, 2):
        w = panda_weights(version)
        store.publish(version, w.policy, w.tensors, experiment="pick")
    assert store.latest("reach").version == 1 and store.latest("pick").version == 2
    assert store.latest().version == 1  # "" = the first experiment published
    assert store.wait_newer(0, 0.01, "pick").version == 2
    assert store.wait_newer(1, 0.01, "reach") is None
    assert store.experiments() == ["pick", "reach"]


def test_local_copies_follow_their_robots_experiment() -> None:
    cfg = StackConfig.model_validate(
        {
            "auth": AUTH.model_dump(),
            "experiments": [
                {"name": "reach", "robots": {"labels": {"arm": "sim"}}},
                {"name": "pick", "robots": {"labels": {"arm": "panda"}}},
            ],
        }
    )
    store = WeightStore()
    server = rpc.start_server(
        "learner-weights",
        lambda s: learner_pb2_grpc.add_LearnerServicer_to_server(WeightServicer(store, poll_s=0.1), s),
        ["user.v1.Learner"],
        ServerConfig(port=0, metrics_port=0, grace_s=0.2),
        AUTH,
        start_metrics=False,
    )
    cfg.edge.learner_addr, cfg.edge.policy_source = server.address(), "local"
    specs = [
        robot_pb2.RobotSpec(robot_id="arm-0", kind="sim_reach_arm", labels={"arm": "sim"}),
        robot_pb2.RobotSpec(robot_id="panda-0", kind="gym_hil_panda", labels={"arm": "panda"}),
    ]
    source = make_policy_source(cfg, "edge-0", specs)
    try:
        assert isinstance(source, RoutedPolicy)
        assert {rid: s._subscriber.experiment for rid, s in source.routes.items()} == {  # type: ignore[attr-defined]
            "arm-0": "reach",
            "panda-0": "pick",
        }
        a, p = arm_weights(4), panda_weights(9)
        store.publish(4, a.policy, a.tensors, experiment="reach")
        store.publish(9, p.policy, p.tensors, experiment="pick")
        arm = wait_for(lambda: source.act("arm-0", {"state": np.zeros(15, np.float32)}, 5.0), "arm action")
        panda = wait_for(lambda: source.act("panda-0", {"state": np.zeros(21, np.float32)}, 5.0), "panda action")
        assert (arm[0].shape, arm[1]) == ((3,), 4)
        assert (panda[0].shape, panda[1]) == ((7,), 9)
        assert all(isinstance(s, LocalPolicy) for s in source.routes.values())
    finally:
        source.close()
        store.close()
        server.stop()


def test_a_lease_to_another_experiment_moves_the_robot_to_that_experiments_copy() -> None:
    """Control's lease is the truth: a robot leased to an experiment the edge's config does not name (defined
    while the edge runs) gets a copy subscribed to it; the copy no robot uses any more is closed."""
    cfg = StackConfig.model_validate(
        {"auth": AUTH.model_dump(), "experiments": [{"name": "reach", "robots": {"kinds": ["sim_reach_arm"]}}]}
    )
    store = WeightStore()
    server = rpc.start_server(
        "learner-weights",
        lambda s: learner_pb2_grpc.add_LearnerServicer_to_server(WeightServicer(store, poll_s=0.1), s),
        ["user.v1.Learner"],
        ServerConfig(port=0, metrics_port=0, grace_s=0.2),
        AUTH,
        start_metrics=False,
    )
    cfg.edge.learner_addr, cfg.edge.policy_source = server.address(), "local"
    specs = [robot_pb2.RobotSpec(robot_id=f"arm-{i}", kind="sim_reach_arm") for i in range(2)]
    source = make_policy_source(cfg, "edge-0", specs)
    obs = {"state": np.zeros(15, np.float32)}
    try:
        assert isinstance(source, RoutedPolicy) and set(source.sources) == {"reach"}
        a, late = arm_weights(3), arm_weights(7)
        store.publish(3, a.policy, a.tensors, experiment="reach")
        store.publish(7, late.policy, late.tensors, experiment="late")
        assert wait_for(lambda: source.act("arm-1", obs, 5.0), "reach's weights")[1] == 3
        source.route("arm-1", "late", "sim_reach_arm")  # as the agent does on control's lease
        assert set(source.sources) == {"reach", "late"}
        assert wait_for(lambda: source.act("arm-1", obs, 5.0), "late's weights")[1] == 7
        assert source.act("arm-0", obs, 5.0)[1] == 3  # the other robot stays where it was
        source.route("arm-0", "late")
        source.route("arm-1", "")  # leased to no experiment, and reach has a selector: it holds
        assert source.act("arm-0", obs, 5.0)[1] == 7 and source.act("arm-1", obs, 5.0) is None
        assert set(source.sources) == {"late"}  # reach lost its last robot: closed
        source.route("plugged-later", "other", "sim_reach_arm")
        source.route("plugged-later", "late")
        assert set(source.sources) == {"late"}  # `other` lost its only robot: closed
        assert source.kinds["plugged-later"] == "sim_reach_arm"
    finally:
        source.close()
        store.close()
        server.stop()


def test_a_local_copy_of_an_experiment_taking_every_robot_serves_robots_leased_to_none() -> None:
    """As inference routes: with no `experiments` section (or one experiment without a selector) every robot is
    served by that experiment's copy, a robot control leases to none included (e.g. a Panda on the default config,
    whose implicit selector names learner.robot_kind)."""
    cfg = StackConfig.model_validate({"auth": AUTH.model_dump()})
    cfg.edge.learner_addr, cfg.edge.policy_source = f"127.0.0.1:{helpers.free_port()}", "local"
    source = make_policy_source(cfg, "edge-0", [robot_pb2.RobotSpec(robot_id="panda-0", kind="gym_hil_panda")])
    try:
        assert isinstance(source, RoutedPolicy) and set(source.sources) == {"default"}
        source.route("panda-0", "")
        assert source.routes["panda-0"] is source.sources["default"]
    finally:
        source.close()


def test_inference_routes_by_robot_and_says_why_it_cannot() -> None:
    import grpc
    import pytest

    from services.control.server import ControlService
    from services.inference.server import InferenceService
    from user import wire
    from user.v1 import inference_pb2, inference_pb2_grpc

    cfg = StackConfig.model_validate(
        {
            "auth": AUTH.model_dump(),
            "experiments": [{"name": "reach", "robots": {"kinds": ["sim_reach_arm"]}}, {"name": "pick"}],
        }
    )
    for section in (cfg.control, cfg.inference):
        section.server.port, section.server.metrics_port, section.server.grace_s = 0, 0, 0.2
    cfg.inference.control_addr = f"127.0.0.1:{helpers.free_port()}"  # nothing there yet
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    stub = inference_pb2_grpc.InferenceStub(rpc.make_channel(inference.address, AUTH))
    request = inference_pb2.ActRequest(
        robot_id="arm-0", observation=wire.to_tensor_map({"state": np.zeros(15, np.float32)})
    )
    control = None
    try:
        inference.router.refresh()  # routes are refreshed in the background: this one now, for a steady answer
        with pytest.raises(grpc.RpcError) as err:
            stub.Act(request, timeout=5)
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE and "control unreachable" in err.value.details()
        control = ControlService(cfg, start_metrics=False).start()
        inference.router.cfg.inference.control_addr = control.address
        inference.router._channel = None
        inference.router.refresh()
        with pytest.raises(grpc.RpcError) as err:
            stub.Act(request, timeout=5)
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "no experiment" in err.value.details()
    finally:
        inference.stop()
        if control is not None:
            control.stop()


def test_one_experiment_with_a_selector_serves_only_its_robots() -> None:
    """One configured experiment that selects arm-0: arm-1, which control knows but no selector picks, is
    refused (FAILED_PRECONDITION) instead of acting with reach's policy; arm-0 is served, and so is a probe
    that is no robot of control's."""
    import grpc
    import pytest

    from edge_agent.control_client import ControlClient
    from services.control.server import ControlService
    from services.inference.server import InferenceService
    from tests.helpers import wait_for
    from tests.test_replay_store import spec
    from user import wire
    from user.v1 import control_pb2, inference_pb2, inference_pb2_grpc

    cfg = StackConfig.model_validate(
        {"auth": AUTH.model_dump(), "experiments": [{"name": "reach", "robots": {"ids": ["arm-0"]}}]}
    )
    for section in (cfg.control, cfg.inference):
        section.server.port, section.server.metrics_port, section.server.grace_s = 0, 0, 0.2
    control = ControlService(cfg, start_metrics=False).start()
    cfg.inference.control_addr = control.address
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    actor = {"obs_keys": ["state"], "obs_dim": 15, "action_dim": 3, "hidden": [8], "action_low": [-1.0] * 3}
    actor["action_high"] = [1.0] * 3
    inference.load_weights(helpers.random_weights(actor, 4))
    specs = [spec("arm-0", obs_dim=15), spec("arm-1", obs_dim=15)]  # what the policy reads (inference checks it)
    status = lambda: [control_pb2.RobotStatus(robot_id=s.robot_id) for s in specs]  # noqa: E731
    edge = ControlClient(control.address, AUTH, "pc-1", specs, status, lambda cmd: (True, ""))
    stub = inference_pb2_grpc.InferenceStub(rpc.make_channel(inference.address, AUTH))

    def act(robot_id: str) -> inference_pb2.ActResponse:
        observation = wire.to_tensor_map({"state": np.zeros(15, np.float32)})
        return stub.Act(inference_pb2.ActRequest(robot_id=robot_id, observation=observation), timeout=5)

    try:
        edge.start()
        assert edge.wait_registered(10)
        inference.router.refresh()  # routes are refreshed in the background: this one now, for a steady answer
        assert wait_for(lambda: act("arm-0").policy_version == 4, "arm-0 served")
        with pytest.raises(grpc.RpcError) as err:
            act("arm-1")
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "no experiment" in err.value.details()
        with pytest.raises(grpc.RpcError) as err:  # not routed until a refresh after its first Act
            act("probe")
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE and "not routed yet" in err.value.details()
        inference.router.refresh()
        assert act("probe").policy_version == 4  # a client control does not know (evaluation) is served
    finally:
        edge.close()
        inference.stop()
        control.stop()
