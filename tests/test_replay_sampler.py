"""ShardedSampler against real replay shards (in-process servers, LMDB in tmp dirs): proportional split,
a shard down then back, errors shaped like the stub's."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest

from cloud_learner.replay_sampler import SamplerError, ShardedSampler, merge_batches, replay_source
from edge_agent.replay_client import ReplaySender
from services.replay.server import ReplayService
from tests.helpers import free_port, wait_for
from tests.test_edge_agent import AUTH, SIM_SPEC, replay_stats, sim_steps, stack_cfg
from user import wire
from user.config import LearnerConfig, StackConfig
from user.rpc import Backoff, make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, robot_pb2

MARKS = {"a": 100.0, "b": 200.0}  # state[0] of every step tells which shard a sample came from


def spec_for(robot_id: str) -> robot_pb2.RobotSpec:
    spec = robot_pb2.RobotSpec()
    spec.CopyFrom(SIM_SPEC)
    spec.robot_id = robot_id
    return spec


SPECS = {f"arm-{name}": spec_for(f"arm-{name}") for name in MARKS}


class Shard:
    """One replay process on a fixed port and LMDB dir, so it can go down and come back."""

    def __init__(self, tmp_path: Path, name: str) -> None:
        self.cfg: StackConfig = stack_cfg(tmp_path / name)
        self.cfg.replay.server.port = free_port()
        self.addr = f"127.0.0.1:{self.cfg.replay.server.port}"
        self.svc: ReplayService | None = None

    def up(self) -> Shard:
        self.svc = ReplayService(self.cfg, spec_source=SPECS.get, start_metrics=False).start()
        return self

    def down(self) -> None:
        if self.svc is not None:
            self.svc.stop()
            self.svc = None


def fill(shard: Shard, name: str, n: int) -> None:
    sender = ReplaySender(shard.addr, AUTH, backoff=Backoff(0.05, 0.2))
    try:
        for step in sim_steps(n, robot_id=f"arm-{name}"):
            state = np.full(15, MARKS[name], np.float32)
            step.observation.CopyFrom(wire.to_tensor_map({"state": state}))
            if step.HasField("final_observation"):
                step.final_observation.CopyFrom(wire.to_tensor_map({"state": state}))
            sender.send(step)
        assert sender.flush(60)
    finally:
        sender.close()


def origins(resp: replay_pb2.SampleResponse) -> dict[str, int]:
    marks = wire.from_tensor(resp.batch.observation.tensors["state"])[:, 0]
    return {name: int((marks == mark).sum()) for name, mark in MARKS.items()}


@pytest.fixture
def shards(tmp_path: Path) -> Iterator[dict[str, Shard]]:
    out = {name: Shard(tmp_path, name).up() for name in MARKS}
    fill(out["a"], "a", 300)
    fill(out["b"], "b", 100)
    yield out
    for shard in out.values():
        shard.down()


def sampler_for(shards: dict[str, Shard], seed: int = 0) -> ShardedSampler:
    return ShardedSampler([s.addr for s in shards.values()], AUTH, timeout_s=5, seed=seed, max_backoff_s=0.5)


def test_batches_are_split_in_proportion_to_each_shards_transitions(shards: dict[str, Shard]) -> None:
    sizes = {name: replay_stats(s.addr).transitions for name, s in shards.items()}
    assert sizes["a"] > 2 * sizes["b"] > 0
    sampler = sampler_for(shards)
    try:
        counts = {"a": 0, "b": 0}
        for _ in range(10):
            resp = sampler.Sample(replay_pb2.SampleRequest(batch_size=500))
            assert resp.transitions == sizes["a"] + sizes["b"]
            got = origins(resp)
            assert sum(got.values()) == 500  # nothing but the two shards' steps, every row filled
            assert wire.from_tensor(resp.batch.action).shape == (500, 3)
            for name in counts:
                counts[name] += got[name]
    finally:
        sampler.close()
    share_a = counts["a"] / 5000
    expected = sizes["a"] / (sizes["a"] + sizes["b"])
    assert abs(share_a - expected) < 0.03, (share_a, expected)  # 5000 draws: std of the share ~0.006


def test_a_shard_down_is_skipped_and_its_data_returns_with_it(shards: dict[str, Shard]) -> None:
    sampler = sampler_for(shards)
    request = replay_pb2.SampleRequest(batch_size=200)
    try:
        assert origins(sampler.Sample(request))["b"] > 0
        shards["b"].down()
        for _ in range(3):  # sampling goes on, whole batches, from the live shard only
            resp = sampler.Sample(request)
            assert origins(resp) == {"a": 200, "b": 0}
            assert resp.transitions == replay_stats(shards["a"].addr).transitions
        assert [s.up for s in sampler.shards] == [True, False]
        shards["b"].up()  # same port, same LMDB dir
        wait_for(lambda: origins(sampler.Sample(request))["b"] > 0, "shard b sampled again")
        assert sampler.shards[1].transitions == replay_stats(shards["b"].addr).transitions  # all of it is back
    finally:
        sampler.close()


def test_a_silent_shard_does_not_stop_sampling(shards: dict[str, Shard]) -> None:
    """A shard that accepts connections and never answers (a black-holed link): batches come from the others."""
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen()
    addrs = [shards["a"].addr, f"127.0.0.1:{silent.getsockname()[1]}"]
    sampler = ShardedSampler(addrs, AUTH, timeout_s=1, seed=0, max_backoff_s=0.5)
    try:
        for _ in range(3):
            assert origins(sampler.Sample(replay_pb2.SampleRequest(batch_size=64)))["a"] == 64
        wait_for(lambda: sampler.shards[1].known and not sampler.shards[1].up, "the silent shard marked down")
    finally:
        sampler.close()
        silent.close()


def test_errors_look_like_the_stubs(tmp_path: Path) -> None:
    empty = Shard(tmp_path, "a").up()
    gone = Shard(tmp_path, "b")  # never started
    sampler = ShardedSampler([empty.addr, gone.addr], AUTH, timeout_s=2, seed=0)
    try:
        with pytest.raises(grpc.RpcError) as err:
            sampler.Sample(replay_pb2.SampleRequest(batch_size=8))
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION  # live but empty: wait, as for one replay
        empty.down()
        sampler.shards[0].retry_at = 0.0  # re-probe now rather than after the empty-shard pause
        with pytest.raises(SamplerError) as err:
            sampler.Sample(replay_pb2.SampleRequest(batch_size=8))
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        sampler.close()
        empty.down()


def test_merge_refuses_batches_that_disagree(shards: dict[str, Shard]) -> None:
    stub = replay_pb2_grpc.ReplayStub(make_channel(shards["a"].addr, AUTH))
    one = stub.Sample(replay_pb2.SampleRequest(batch_size=4), timeout=5).batch
    two = replay_pb2.Batch()
    two.CopyFrom(one)
    merged = merge_batches([one, two])
    assert wire.from_tensor(merged.reward).shape == (8,)
    assert set(merged.next_observation.tensors) == {"state"}
    two.observation.tensors["camera"].CopyFrom(wire.to_tensor(np.zeros((4, 2), np.uint8)))
    with pytest.raises(SamplerError) as err:
        merge_batches([one, two])
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION


def test_learner_uses_the_sampler_only_for_several_shards(shards: dict[str, Shard]) -> None:
    with make_channel(shards["a"].addr, AUTH) as channel:
        single = LearnerConfig(replay_shm_dir=None)
        assert isinstance(replay_source(single, AUTH, channel), replay_pb2_grpc.ReplayStub)
        sharded = replay_source(LearnerConfig(replay_addrs=[s.addr for s in shards.values()]), AUTH, channel)
        assert isinstance(sharded, ShardedSampler)
        sharded.close()
    with pytest.raises(ValueError):
        ShardedSampler([shards["a"].addr, shards["a"].addr], AUTH)


def test_the_learner_trains_from_every_shard_and_through_a_shard_outage(
    tmp_path: Path, shards: dict[str, Shard]
) -> None:
    import torch

    from cloud_learner.learner import Learner
    from edge_agent.control_client import ControlClient
    from services.control.server import ControlService
    from user.weights import WeightStore

    torch.set_num_threads(1)
    control = ControlService(stack_cfg(tmp_path / "control"), start_metrics=False).start()
    edge = ControlClient(control.address, AUTH, "edge-a", [SPECS["arm-a"]], status_fn=list, on_command=lambda c: None)
    cfg = stack_cfg(tmp_path)
    lc = cfg.learner
    lc.control_addr, lc.replay_addrs = control.address, [s.addr for s in shards.values()]
    lc.checkpoint_dir, lc.hidden, lc.batch_size, lc.min_transitions = tmp_path / "ckpt", [16], 32, 50
    lc.max_updates_per_transition, lc.rpc_timeout_s = 1000.0, 2.0
    learner = Learner(cfg, WeightStore())
    (exp_state,) = learner.experiment_states.values()  # the default experiment: one robot kind
    total = sum(replay_stats(s.addr).transitions for s in shards.values())
    only_a = replay_stats(shards["a"].addr).transitions
    try:
        assert edge.wait_registered(30)
        learner.start()
        # Liveness bounds only (this machine may be crowded): nothing here measures speed.
        both = lambda: exp_state.updates > 0 and exp_state.buffer_transitions == total  # noqa: E731
        wait_for(both, "training on both", limit_s=120)
        shards["b"].down()
        wait_for(lambda: exp_state.buffer_transitions == only_a, "shard b skipped", limit_s=120)
        updates = exp_state.updates
        wait_for(lambda: exp_state.updates > updates + 5, "training on shard a alone", limit_s=120)
        shards["b"].up()
        wait_for(lambda: exp_state.buffer_transitions == total, "shard b back", limit_s=120)
    finally:
        learner.stop()
        edge.close()
        control.stop()
    assert not learner.failed


def test_n_step_batches_reach_the_algorithm_with_their_discount(shards: dict[str, Shard]) -> None:
    """A real replay sums n-step rewards; the learner's decode turns n_steps into gamma ** n per row."""
    from cloud_learner.learner import decode_arrays, to_batch

    with make_channel(shards["a"].addr, AUTH) as channel:
        stub = replay_pb2_grpc.ReplayStub(channel)
        resp = stub.Sample(replay_pb2.SampleRequest(batch_size=64, n_step=3, gamma=0.9), timeout=10)
    arrays = decode_arrays(resp.batch, ["state"])
    assert "n_steps" in arrays and set(arrays["n_steps"].tolist()) <= {1.0, 2.0, 3.0}
    batch = to_batch(arrays, "cpu", gamma=0.9)
    assert batch.discount is not None
    np.testing.assert_allclose(batch.discount.numpy(), 0.9 ** arrays["n_steps"], rtol=1e-6)
    assert 3.0 in arrays["n_steps"].tolist()  # most rows are whole n-step windows
