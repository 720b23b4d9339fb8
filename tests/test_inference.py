"""Inference service and its micro-batcher, with a real sac_mlp policy built from random weights.

Weights are loaded with InferenceService.load_weights (what the weight subscriber calls); the path
through a real learner weight stream is covered by the integration test.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Iterator

import grpc
import numpy as np
import pytest
import torch

from services.inference import batcher as batcher_module
from services.inference.batcher import MicroBatcher, NoPolicyError
from services.inference.server import InferenceService
from tests import helpers
from user import wire
from user.config import AuthConfig, StackConfig
from user.policy import build_policy, policy_spec_for
from user.rpc import check_health, make_channel
from user.v1 import inference_pb2, inference_pb2_grpc
from user.v1 import tensor_pb2 as tpb

torch.set_num_threads(1)

AUTH = AuthConfig(token="test-token")
CONFIG = {
    "obs_keys": ["state"],
    "obs_dim": 6,
    "action_dim": 3,
    "hidden": [32, 32],
    "action_low": [-1.0, -2.0, 0.0],
    "action_high": [1.0, 2.0, 0.5],
}
LOW, HIGH = np.array(CONFIG["action_low"]), np.array(CONFIG["action_high"])


weight_set = functools.partial(helpers.random_weights, CONFIG)


def obs(seed: int) -> dict[str, np.ndarray]:
    return {"state": np.random.default_rng(seed).normal(size=6).astype(np.float32)}


def act_request(seed: int, robot_id: str = "arm-0", deterministic: bool = True, **arrays) -> inference_pb2.ActRequest:
    observation = arrays or obs(seed)
    return inference_pb2.ActRequest(
        robot_id=robot_id, observation=wire.to_tensor_map(observation), deterministic=deterministic
    )


@pytest.fixture
def service() -> Iterator[InferenceService]:
    cfg = StackConfig(auth=AUTH)
    cfg.inference.server.port = 0
    cfg.inference.server.metrics_port = 0
    cfg.inference.server.grace_s = 1.0
    cfg.inference.max_wait_ms = 50.0  # generous: the batch closes early once every active robot is in
    svc = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    yield svc
    svc.stop()


@pytest.fixture
def stub(service: InferenceService) -> inference_pb2_grpc.InferenceStub:
    return inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))


def test_no_policy_is_unavailable(service: InferenceService, stub: inference_pb2_grpc.InferenceStub) -> None:
    with pytest.raises(grpc.RpcError) as err:
        stub.Act(act_request(0), timeout=5)
    assert err.value.code() == grpc.StatusCode.UNAVAILABLE
    assert err.value.details() == "no policy yet"
    status = stub.Status(inference_pb2.InferenceStatusRequest(), timeout=5)
    assert status.policy_version == 0 and status.policy_kind == ""


def test_act_shape_bounds_and_version(service: InferenceService, stub: inference_pb2_grpc.InferenceStub) -> None:
    service.load_weights(weight_set(version=3))
    reference = build_policy(policy_spec_for(CONFIG), weight_set(3).tensors, 3)
    for seed in range(5):
        resp = stub.Act(act_request(seed), timeout=5)
        action = wire.from_tensor(resp.action)
        assert action.shape == (3,) and action.dtype == np.float32
        assert np.all(action >= LOW - 1e-6) and np.all(action <= HIGH + 1e-6)
        assert resp.policy_version == 3 and resp.batch_size >= 1
        assert resp.queue_us >= 0 and resp.compute_us >= 0
        expected = reference.act({"state": obs(seed)["state"][None]}, deterministic=True)[0]
        np.testing.assert_allclose(action, expected, rtol=1e-5, atol=1e-6)
    sampled = [wire.from_tensor(stub.Act(act_request(0, deterministic=False), timeout=5).action) for _ in range(3)]
    assert all(np.all(a >= LOW - 1e-6) and np.all(a <= HIGH + 1e-6) for a in sampled)
    assert not np.allclose(sampled[0], sampled[1])  # a sample, not the mean

    # A new weight version is served as soon as it is loaded.
    service.load_weights(weight_set(version=4, seed=1))
    assert stub.Act(act_request(0), timeout=5).policy_version == 4
    status = stub.Status(inference_pb2.InferenceStatusRequest(), timeout=5)
    assert status.policy_version == 4 and status.policy_kind == "sac_mlp"
    assert status.requests == 9 and status.mean_batch_size >= 1.0


def test_bad_weights_keep_the_old_policy(service: InferenceService, stub: inference_pb2_grpc.InferenceStub) -> None:
    service.load_weights(weight_set(version=1))
    bad = weight_set(version=2)
    bad.tensors.pop(next(iter(bad.tensors)))
    with pytest.raises(ValueError):
        service.load_weights(bad)
    assert stub.Act(act_request(0), timeout=5).policy_version == 1


@pytest.mark.parametrize(
    "observation",
    [
        {"state": np.zeros(5, np.float32)},  # wrong size
        {"joints": np.zeros(6, np.float32)},  # wrong key
        {"state": np.array([0, 0, np.nan, 0, 0, 0], np.float32)},
    ],
    ids=["shape", "key", "nan"],
)
def test_bad_observation_is_invalid_argument(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub, observation: dict[str, np.ndarray]
) -> None:
    service.load_weights(weight_set(version=1))
    with pytest.raises(grpc.RpcError) as err:
        stub.Act(act_request(0, **observation), timeout=5)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert err.value.details().startswith("bad observation")
    assert stub.Act(act_request(0), timeout=5).policy_version == 1  # still serving


def test_act_batch_answers_each_robot_in_order(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub
) -> None:
    """One ActBatch: each robot gets its own action or its own status; one bad observation fails only itself."""
    batch = inference_pb2.ActBatchRequest(
        requests=[act_request(0, "arm-0"), act_request(1, "arm-1", state=np.zeros(5, np.float32)), act_request(2)]
    )
    results = stub.ActBatch(batch, timeout=5).results  # no policy yet: every robot is told so
    assert [r.code for r in results] == [grpc.StatusCode.UNAVAILABLE.value[0]] * 3
    service.load_weights(weight_set(version=2))
    reference = build_policy(policy_spec_for(CONFIG), weight_set(2).tensors, 2)
    results = stub.ActBatch(batch, timeout=5).results
    assert [r.code for r in results] == [0, grpc.StatusCode.INVALID_ARGUMENT.value[0], 0]
    assert results[1].message.startswith("bad observation") and not results[1].HasField("response")
    for result, seed in ((results[0], 0), (results[2], 2)):
        expected = reference.act({"state": obs(seed)["state"][None]}, deterministic=True)[0]
        assert result.response.policy_version == 2
        np.testing.assert_allclose(wire.from_tensor(result.response.action), expected, rtol=1e-5, atol=1e-6)
    for bad in (inference_pb2.ActBatchRequest(), inference_pb2.ActBatchRequest(requests=[act_request(0)] * 257)):
        with pytest.raises(grpc.RpcError) as err:
            stub.ActBatch(bad, timeout=5)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_undecodable_tensor_is_invalid_argument(
    service: InferenceService, stub: inference_pb2_grpc.InferenceStub
) -> None:
    service.load_weights(weight_set(version=1))
    req = inference_pb2.ActRequest(robot_id="arm-0")
    req.observation.tensors["state"].CopyFrom(tpb.Tensor(dtype=tpb.DTYPE_FLOAT32, shape=[6], data=b"\0" * 7))
    with pytest.raises(grpc.RpcError) as err:
        stub.Act(req, timeout=5)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_concurrent_requests_are_batched(service: InferenceService, stub: inference_pb2_grpc.InferenceStub) -> None:
    service.load_weights(weight_set(version=7))
    clients, rounds = 8, 20
    barrier = threading.Barrier(clients)
    sizes: list[int] = []
    errors: list[BaseException] = []
    lock = threading.Lock()

    def robot(i: int) -> None:
        try:
            barrier.wait(timeout=10)
            for r in range(rounds):
                resp = stub.Act(act_request(r, robot_id=f"arm-{i}", deterministic=r % 2 == 0), timeout=10)
                action = wire.from_tensor(resp.action)
                assert action.shape == (3,) and resp.policy_version == 7
                assert np.all(action >= LOW - 1e-6) and np.all(action <= HIGH + 1e-6)
                with lock:
                    sizes.append(resp.batch_size)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert len(sizes) == clients * rounds
    print(f"batch sizes seen by {clients} clients: mean {np.mean(sizes):.2f}, max {max(sizes)}")
    assert np.mean(sizes) > 1.0 and max(sizes) <= clients
    status = stub.Status(inference_pb2.InferenceStatusRequest(), timeout=5)
    assert status.requests == clients * rounds and status.mean_batch_size > 1.0


def test_client_deadline_is_honored(service: InferenceService, stub: inference_pb2_grpc.InferenceStub) -> None:
    service.load_weights(weight_set(version=1))
    release = threading.Event()

    def stuck(observation, deterministic):  # a forward that outlives the caller's deadline
        release.wait(5)
        return np.zeros((len(observation["state"]), 3), np.float32)

    service.batcher.set_policy(stuck, 1)
    try:
        with pytest.raises(grpc.RpcError) as err:
            stub.Act(act_request(0), timeout=0.2)
        assert err.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    finally:
        release.set()


def test_auth_and_health(service: InferenceService) -> None:
    anonymous = inference_pb2_grpc.InferenceStub(make_channel(service.address, AuthConfig(enabled=False)))
    with pytest.raises(grpc.RpcError) as err:
        anonymous.Act(act_request(0), timeout=5)
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert check_health(service.address, AuthConfig(enabled=False), service="user.v1.Inference")


# --------------------------------------------------------------------------- the batcher alone


@pytest.fixture
def policy():
    return build_policy(policy_spec_for(CONFIG), weight_set(1).tensors, 1)


def test_batcher_stacks_and_splits(policy) -> None:
    batcher = MicroBatcher(max_batch=64, max_wait_ms=200.0).start()
    try:
        with pytest.raises(NoPolicyError):
            batcher.submit(obs(0), True)
        batcher.set_policy(policy.act, policy.version)
        # Anonymous callers wait the full max_wait, so everything submitted at once rides in one forward,
        # split by the deterministic flag.
        futures = [batcher.submit(obs(i), deterministic=i < 10) for i in range(16)]
        results = [f.result(timeout=10) for f in futures]
        assert {r.batch_size for r in results[:10]} == {10} and {r.batch_size for r in results[10:]} == {6}
        for i, r in enumerate(results[:10]):
            expected = policy.act({"state": obs(i)["state"][None]}, deterministic=True)[0]
            np.testing.assert_allclose(r.action, expected, rtol=1e-5, atol=1e-6)
            assert r.version == 1 and r.queue_us >= 0
        assert batcher.requests == 16 and batcher.batches == 2 and batcher.mean_batch_size == 8.0
    finally:
        batcher.stop()


def test_batcher_respects_max_batch_and_survives_errors(policy) -> None:
    batcher = MicroBatcher(max_batch=4, max_wait_ms=50.0).start()
    try:
        batcher.set_policy(policy.act, 2)
        results = [f.result(timeout=10) for f in [batcher.submit(obs(i), True, key=f"r{i}") for i in range(10)]]
        assert all(1 <= r.batch_size <= 4 for r in results)

        def broken(observation, deterministic):
            raise RuntimeError("boom")

        batcher.set_policy(broken, 3)
        with pytest.raises(RuntimeError, match="boom"):
            batcher.submit(obs(0), True, key="r0").result(timeout=10)
        batcher.set_policy(policy.act, 4)  # the worker is still alive
        assert batcher.submit(obs(0), True, key="r0").result(timeout=10).version == 4
    finally:
        batcher.stop()


def test_a_row_that_fails_the_forward_fails_only_itself(policy) -> None:
    """A batch whose forward raises is retried row by row: the robot whose input broke it gets the error,
    its batch-mates their actions."""
    batcher = MicroBatcher(max_batch=3, max_wait_ms=5_000.0).start()  # no keys: the batch closes at 3 rows

    def picky(observation, deterministic):
        if np.any(observation["state"][:, 0] == 99.0):
            raise ValueError("row with 99")
        return policy.act(observation, deterministic)

    try:
        batcher.set_policy(picky, 1)
        bad = {"state": np.full(6, 99.0, np.float32)}
        futures = [batcher.submit(o, True) for o in (obs(0), bad, obs(2))]
        with pytest.raises(ValueError, match="row with 99"):
            futures[1].result(timeout=10)
        good = [futures[0].result(timeout=10), futures[2].result(timeout=10)]
        assert [r.batch_size for r in good] == [1, 1]  # answered alone, after the batch of 3 failed
        expected = policy.act({"state": obs(0)["state"][None]}, deterministic=True)[0]
        np.testing.assert_allclose(good[0].action, expected, rtol=1e-5, atol=1e-6)
    finally:
        batcher.stop()


def test_batcher_closes_early_when_every_robot_is_in(policy) -> None:
    """With one known robot, a request does not wait out max_wait (a 10 s wait would fail result(timeout=5))."""
    batcher = MicroBatcher(max_batch=64, max_wait_ms=10_000.0).start()
    try:
        batcher.set_policy(policy.act, 1)
        for i in range(3):
            assert batcher.submit(obs(i), True, key="solo").result(timeout=5).batch_size == 1
    finally:
        batcher.stop()


def test_weights_arrive_through_a_weight_stream() -> None:
    """The default policy source subscribes to the learner address (here a bare WeightServicer)."""
    from user.rpc import start_server
    from user.v1 import learner_pb2_grpc
    from user.weights import WeightServicer, WeightStore

    cfg = StackConfig(auth=AUTH)
    cfg.inference.server.port = 0
    cfg.inference.server.grace_s = 1.0
    store = WeightStore()
    learner = start_server(
        "learner-weights",
        lambda server: learner_pb2_grpc.add_LearnerServicer_to_server(WeightServicer(store, poll_s=0.2), server),
        ["user.v1.Learner"],
        cfg.learner.server.model_copy(update={"port": 0, "grace_s": 0.5}),
        AUTH,
        start_metrics=False,
    )
    cfg.inference.learner_addr = learner.address()
    svc = InferenceService(cfg, start_metrics=False).start()
    try:
        ws = weight_set(version=5)
        store.publish(ws.version, ws.policy, ws.tensors)
        assert svc.subscriber is not None and svc.subscriber.wait_version(5, timeout=20)
        stub = inference_pb2_grpc.InferenceStub(make_channel(svc.address, AUTH))
        assert stub.Act(act_request(0), timeout=5).policy_version == 5
    finally:
        store.close()
        svc.stop()
        learner.stop()


class SlowFirstForward:
    """Wraps a policy's act: the first forward takes `first_s` (a VLA-sized forward), the rest are fast."""

    def __init__(self, act, first_s: float) -> None:
        self.act, self.first_s, self.sizes = act, first_s, []

    def __call__(self, observation, deterministic):
        self.sizes.append(len(observation["state"]))
        if len(self.sizes) == 1:
            time.sleep(self.first_s)
        return self.act(observation, deterministic)


def test_batcher_waits_for_a_robot_on_its_round_trip(policy) -> None:
    """Two closed-loop robots answered together come back a little apart: with a slow forward the batcher
    waits (a share of that forward) for the second instead of sending the first alone after max_wait."""
    act = SlowFirstForward(policy.act, first_s=2.0)  # patience after it: RETURN_WAIT_FRACTION * 2 s = 0.5 s
    batcher = MicroBatcher(max_batch=64, max_wait_ms=1.0)
    try:
        batcher.set_policy(act, 1)
        first = [batcher.submit(obs(i), True, key=f"r{i}") for i in range(2)]
        batcher.start()  # after both are queued: the slow first forward answers them together
        assert [f.result(timeout=10).batch_size for f in first] == [2, 2]
        a = batcher.submit(obs(0), True, key="r0")
        time.sleep(0.05)  # r1's round trip: far over max_wait, far under the patience
        b = batcher.submit(obs(1), True, key="r1")
        assert (a.result(timeout=10).batch_size, b.result(timeout=10).batch_size) == (2, 2)
        assert act.sizes == [2, 2]
    finally:
        batcher.stop()


def test_batcher_does_not_wait_for_a_robot_pacing_itself(policy, monkeypatch: pytest.MonkeyPatch) -> None:
    """A robot answered longer ago than the patience asks at its own rate: the other goes after max_wait,
    not held for it (held, the two would share a forward)."""
    monkeypatch.setattr(batcher_module, "ACTIVE_WINDOW_S", 30.0)  # r1 stays a known, active robot throughout
    act = SlowFirstForward(policy.act, first_s=3.0)  # patience RETURN_WAIT_FRACTION * 3 s = 0.75 s
    batcher = MicroBatcher(max_batch=64, max_wait_ms=1.0)
    try:
        batcher.set_policy(act, 1)
        first = [batcher.submit(obs(i), True, key=f"r{i}") for i in range(2)]
        batcher.start()  # after both are queued: the slow first forward answers them together
        assert [f.result(timeout=20).batch_size for f in first] == [2, 2]
        time.sleep(1.0)  # over the patience: r1 is pacing itself, not on a round trip
        a = batcher.submit(obs(0), True, key="r0")
        time.sleep(0.5)  # under the patience: a batcher holding r0 for r1 would batch them together
        b = batcher.submit(obs(1), True, key="r1")
        assert (a.result(timeout=10).batch_size, b.result(timeout=10).batch_size) == (1, 1)
        assert act.sizes == [2, 1, 1]
    finally:
        batcher.stop()


def test_batcher_workers_run_forwards_side_by_side(policy) -> None:
    """Two workers: each forward waits at a barrier for a second one to start, which one worker
    (forwards in turn) can never reach; both answers come back."""
    barrier = threading.Barrier(2, timeout=10)

    def act(observation, deterministic):
        barrier.wait()
        return policy.act(observation, deterministic)

    batcher = MicroBatcher(max_batch=1, max_wait_ms=1.0, workers=2).start()
    try:
        batcher.set_policy(act, 1)
        futures = [batcher.submit(obs(i), True, key=f"r{i}") for i in range(2)]
        assert [f.result(timeout=20).batch_size for f in futures] == [1, 1]
        assert batcher.batches == 2
    finally:
        batcher.stop()
    with pytest.raises(ValueError, match="workers"):
        MicroBatcher(max_batch=1, max_wait_ms=1.0, workers=0)


def test_a_state_of_the_wrong_size_is_invalid_argument_for_its_robot_only(service: InferenceService) -> None:
    """The learner's "mlp" policy declares its state sizes: a robot sending 14 values where the policy reads 15
    gets INVALID_ARGUMENT before batching, and the robots batched beside it are answered."""
    from user.policies.mlp import MlpPolicy, policy_spec
    from user.policy import module_tensors
    from user.weights import WeightSet

    config = {"state_keys": ["state"], "state_dims": [15], "hidden": [16], "action_low": [-1.0], "action_high": [1.0]}
    actor = MlpPolicy.build_actor(config)
    service.load_weights(WeightSet(version=3, policy=policy_spec("mlp", config), tensors=module_tensors(actor)))
    stub = inference_pb2_grpc.InferenceStub(make_channel(service.address, AUTH))
    good = np.zeros(15, np.float32)
    for bad in (np.zeros(14, np.float32), np.zeros(16, np.float64)):
        with pytest.raises(grpc.RpcError) as err:
            stub.Act(act_request(0, state=bad), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "reads 15" in err.value.details()
    batch = inference_pb2.ActBatchRequest(
        requests=[act_request(0, f"arm-{i}", state=s) for i, s in enumerate([good, np.zeros(14, np.float32), good])]
    )
    results = stub.ActBatch(batch, timeout=10).results
    assert [r.code for r in results] == [0, grpc.StatusCode.INVALID_ARGUMENT.value[0], 0]
    assert stub.Act(act_request(0, state=good), timeout=10).policy_version == 3
