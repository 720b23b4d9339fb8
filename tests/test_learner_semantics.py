"""What the learner's batches mean, against real replay services (gRPC on 127.0.0.1, LMDB in tmp dirs):

- imported demos (stored without the intervention flag) come flagged as human actions from the tables a
  BatchRequest names in human_tables, on every sample path, so SAC's/RLPD's BC term, BC's only_interventions,
  flow_bc's human rows and pretraining count them;
- with several replay shards, a request with table ratios splits each table's rows over the shards that hold it,
  in proportion to that table's transitions there;
- with a layout padded across embodiments, the padded action dims are no label (BC's NLL, flow_bc's loss).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest
import torch

from cloud_learner.algorithm import Batch, Feature, Layout
from cloud_learner.algorithms.bc import BC, BCParams, masked_log_prob
from cloud_learner.algorithms.flow_bc import FlowBc, FlowBcParams
from cloud_learner.algorithms.sac import bc_mse
from cloud_learner.learner import ExperimentRun, Learner, decode_arrays
from cloud_learner.replay_sampler import ShardedSampler
from cloud_learner.replay_shm import SharedMemoryReplay
from services.replay import server as replay_server
from services.replay.server import ReplayService
from tests.helpers import free_port, wait_for
from tests.test_edge_agent import AUTH, SIM_SPEC, stack_cfg
from tests.test_experiments import ARM
from tests.test_learner import service_cfg
from user import wire
from user.policies.mlp import log_prob_of
from user.rpc import make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, robot_pb2, step_pb2
from user.weights import WeightStore

EPISODE = 10  # steps per episode: each step is one sampleable transition
ONLINE, DEMO = 1.0, 2.0  # state[0] of every stored step: which table a sampled row came from
DEMO_ACTION = np.array([0.5, -0.5, 0.25], np.float32)


def replay(tmp_path: Path, name: str, shm_dir: Path | None = None) -> ReplayService:
    cfg = stack_cfg(tmp_path / name)
    cfg.replay.server.port = free_port()
    if shm_dir is not None:
        cfg.replay.shm_dir, cfg.replay.shm_slots = str(shm_dir), 2
    specs = {r: _spec(r) for r in ("arm-0", "arm-b")}
    return ReplayService(cfg, spec_source=specs.get, start_metrics=False).start()


def _spec(robot_id: str) -> robot_pb2.RobotSpec:
    spec = robot_pb2.RobotSpec()
    spec.CopyFrom(SIM_SPEC)
    spec.robot_id = robot_id
    return spec


def stub(svc: ReplayService) -> replay_pb2_grpc.ReplayStub:
    return replay_pb2_grpc.ReplayStub(make_channel(svc.address, AUTH))


def online_steps(robot_id: str, episodes: int, mark: float = ONLINE) -> list[step_pb2.Step]:
    """The policy's own steps (intervention false), state[0] = mark, action 0."""
    out = []
    for e in range(episodes):
        for t in range(EPISODE):
            obs = wire.to_tensor_map({"state": np.full(15, mark, np.float32)})
            step = step_pb2.Step(
                robot_id=robot_id,
                episode_id=f"{robot_id}-online-{mark}-{e}",
                step_index=t,
                observation=obs,
                action=wire.to_tensor(np.zeros(3, np.float32)),
                truncated=t == EPISODE - 1,
            )
            if t == EPISODE - 1:
                step.final_observation.CopyFrom(obs)
            out.append(step)
    return out


def demo_steps(robot_id: str, episodes: int, mark: float = DEMO) -> list[step_pb2.Step]:
    """Demo steps as `userctl replay import` stores a dataset recorded elsewhere: no intervention flag (a
    LeRobotDataset has none), the demonstrator's action DEMO_ACTION, state[0] = mark."""
    out = online_steps(robot_id, episodes, mark)
    for step in out:
        step.episode_id = step.episode_id.replace("online", "demo")
        step.action.CopyFrom(wire.to_tensor(DEMO_ACTION))
    return out


def insert(svc: ReplayService, steps: list[step_pb2.Step], table: str = "", first_seq: int = 0) -> None:
    reqs = [replay_pb2.InsertRequest(seq=first_seq + i, step=s, table=table) for i, s in enumerate(steps)]
    acks = list(stub(svc).Insert(iter(reqs), timeout=30))
    assert sum(len(a.seqs) for a in acks) == len(reqs)


def marks(arrays_or_batch) -> np.ndarray:
    if isinstance(arrays_or_batch, Batch):
        return arrays_or_batch.observation["state"][:, 0].cpu().numpy()
    return arrays_or_batch["observation"]["state"][:, 0]


@pytest.fixture
def mixed(tmp_path: Path) -> Iterator[ReplayService]:
    """One replay: 20 online episodes of arm-0, 20 imported demo episodes of arm-0 in "demos"."""
    shm = tmp_path / "shm"
    shm.mkdir()
    svc = replay(tmp_path, "mixed", shm_dir=shm)
    demos = demo_steps("arm-0", 20)
    assert not any(s.intervention for s in demos)  # what the import stores: no flag
    insert(svc, online_steps("arm-0", 20))
    insert(svc, demos, "demos", first_seq=10_000)
    yield svc
    svc.stop()


# --------------------------------------------------------------------------- 1. demos are human actions


def test_rows_of_human_tables_come_flagged_on_every_sample_path(
    mixed: ReplayService, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    keys = ["state"]
    both = {"online": 1.0, "demos": 1.0}
    paths = {
        "tables": replay_pb2.SampleRequest(batch_size=200, tables=both, human_tables=["demos"]),
        "union": replay_pb2.SampleRequest(batch_size=200, human_tables=["demos"]),
        "encoded_frames": replay_pb2.SampleRequest(
            batch_size=200, tables=both, human_tables=["demos"], encoded_frames=True
        ),
        "n_step_and_chunks": replay_pb2.SampleRequest(
            batch_size=200, tables=both, human_tables=["demos"], n_step=3, gamma=0.9, action_horizon=4
        ),
    }
    for name, request in paths.items():
        arrays = decode_arrays(stub(mixed).Sample(request, timeout=10).batch, keys)
        is_demo = marks(arrays) == DEMO
        assert is_demo.any() and (~is_demo).any(), name
        np.testing.assert_array_equal(arrays["intervention"], is_demo, err_msg=name)
    monkeypatch.setattr(replay_server, "SHM_MIN_BYTES", 0)  # these small batches through shared memory too
    client = SharedMemoryReplay(stub(mixed), str(tmp_path / "shm"))
    shared = client.Sample(paths["tables"], timeout=10)
    assert not isinstance(shared, replay_pb2.SampleResponse)  # a shared-memory batch
    arrays = decode_arrays(shared.batch, keys)
    np.testing.assert_array_equal(arrays["intervention"], marks(arrays) == DEMO)
    # without human_tables a row keeps its stored flag; a table this replay lacks marks nothing
    for human in ([], ["nope"]):
        request = replay_pb2.SampleRequest(batch_size=100, tables=both, human_tables=human)
        assert not decode_arrays(stub(mixed).Sample(request, timeout=10).batch, keys)["intervention"].any()


def test_bad_human_tables_are_refused_naming_the_field(mixed: ReplayService) -> None:
    for human, field in ((["no spaces"], "human_tables[0]"), (["demos", ""], "human_tables[1]"),
                         ([f"t{i}" for i in range(65)], "human_tables: at most 64")):  # fmt: skip
        with pytest.raises(grpc.RpcError) as err:
            stub(mixed).Sample(replay_pb2.SampleRequest(batch_size=8, human_tables=human), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert field in err.value.details()


def _run(tmp_path: Path, kind: str, params: dict, **exp) -> ExperimentRun:
    cfg = service_cfg(tmp_path, experiments=[{"name": "a", "algorithm": {"kind": kind, "params": params}, **exp}])
    return ExperimentRun(Learner(cfg, WeightStore()), 0, cfg.experiments[0], [ARM])


def test_the_learners_algorithms_count_imported_demos_as_human_actions(mixed: ReplayService, tmp_path: Path) -> None:
    half = {"online": 0.5, "demos": 0.5}
    sac = _run(tmp_path / "sac", "rlpd", {"tables": half, "bc_weight": 1.0, "batch_size": 64, "hidden": [16]})
    batch = sac.sample_once(stub(mixed)).batch
    is_demo = marks(batch) == DEMO
    assert int(is_demo.sum()) == len(batch) // 2  # RLPD's exact half (of its utd minibatches' rows)
    np.testing.assert_array_equal(batch.intervention.cpu().numpy(), is_demo)
    # the BC term: the demo rows' squared error to a zero action (the online rows' actions are 0: no term)
    expected = float((DEMO_ACTION**2).mean())
    assert float(bc_mse(torch.zeros(len(batch), 3), batch)) == pytest.approx(expected, rel=1e-5)

    bc = _run(tmp_path / "bc", "bc", {"tables": half, "only_interventions": True, "batch_size": 64, "hidden": [16]})
    assert bc.algo.update(bc.sample_once(stub(mixed)).batch)["rows"] == 32.0

    flow = _run(tmp_path / "flow", "flow_bc", {"tables": half, "batch_size": 64, "hidden": 16, "image_size": 16})
    batch = flow.sample_once(stub(mixed)).batch
    weights = flow.algo.row_weights(batch)
    assert weights is not None
    np.testing.assert_array_equal(weights.cpu().numpy(), (marks(batch) == DEMO).astype(np.float32))


@pytest.mark.parametrize("human", [True, False])
def test_pretraining_on_a_demo_table_flags_its_rows_only_when_human(
    mixed: ReplayService, tmp_path: Path, human: bool
) -> None:
    pretrain = {"table": "demos", "steps": 1, "min_size": 1, "human": human}
    params = {"tables": {"demos": 1.0}, "only_interventions": True, "batch_size": 32, "hidden": [16]}
    run = _run(tmp_path, "bc", params, pretrain=pretrain)
    run._pretrain(stub(mixed))
    assert run.pretrain_updates == 1
    assert run.state.scalars["rows"] == (32.0 if human else 0.0)  # only_interventions counted the flagged rows


# --------------------------------------------------------------------------- 2. tables over shards


@pytest.fixture
def two_shards(tmp_path: Path) -> Iterator[tuple[ReplayService, ReplayService]]:
    a, b = replay(tmp_path, "a"), replay(tmp_path, "b")
    yield a, b
    a.stop()
    b.stop()


def _draw(sampler: ShardedSampler, tables: dict[str, float], batches: int = 20) -> dict[float, int]:
    counts: dict[float, int] = {}
    for _ in range(batches):
        resp = sampler.Sample(replay_pb2.SampleRequest(batch_size=500, tables=tables), timeout=10)
        got = wire.from_tensor(resp.batch.observation.tensors["state"])[:, 0]
        values, n = np.unique(got, return_counts=True)
        for v, k in zip(values.tolist(), n.tolist(), strict=True):
            counts[v] = counts.get(v, 0) + k
    return counts


def test_each_tables_rows_are_split_over_the_shards_that_hold_it(
    two_shards: tuple[ReplayService, ReplayService],
) -> None:
    """A: 100 online + 100 demo transitions; B: 1000 online, no demos. B must not be dropped for lacking demos,
    and the online half splits 100:1000; then with demos on both (10 on A, 1000 on B), A's demos are ~1%."""
    a, b = two_shards
    insert(a, online_steps("arm-0", 10, mark=1.0))
    insert(a, demo_steps("arm-0", 10, mark=2.0), "demos", first_seq=10_000)
    insert(b, online_steps("arm-b", 100, mark=3.0))
    # stats_every_s=0: each batch refreshes the shards' per-table counts in the background (demos added below)
    sampler = ShardedSampler([a.address, b.address], AUTH, timeout_s=10, seed=0, stats_every_s=0.0)
    try:
        rlpd = {"online": 1.0, "demos": 1.0}
        counts = _draw(sampler, rlpd)
        assert counts[2.0] == 5000  # exact half of every batch: the only demos, all on A
        assert counts[1.0] + counts[3.0] == 5000
        # B holds 1000 of 1100 online transitions: ~4545 of 5000 (std ~20); before, B was never asked
        assert abs(counts[3.0] - 5000 * 1000 / 1100) < 150, counts
        assert all(s.up and s.transitions > 0 for s in sampler.shards)  # B lacks demos: not a failed shard
        resp = sampler.Sample(replay_pb2.SampleRequest(batch_size=8, tables=rlpd), timeout=10)
        assert dict(resp.table_transitions) == {"online": 1100, "demos": 100}
        # demos on B too, 10x A's: a demo row comes from A 1 time in 11 (it was ~1 in 2, by total transitions)
        insert(b, demo_steps("arm-b", 100, mark=4.0), "demos", first_seq=10_000)
        one = replay_pb2.SampleRequest(batch_size=1, tables={"demos": 1.0})
        wait_for(lambda: sampler.Sample(one, timeout=10) and sampler.shards[1].table_count("demos", []), "B's demos")
        counts = _draw(sampler, {"demos": 1.0}, batches=10)
        assert counts.get(2.0, 0) + counts.get(4.0, 0) == 5000
        assert abs(counts.get(2.0, 0) - 5000 * 100 / 1100) < 120, counts
    finally:
        sampler.close()


def test_a_table_no_shard_holds_is_an_empty_buffer(two_shards: tuple[ReplayService, ReplayService]) -> None:
    a, b = two_shards
    insert(a, online_steps("arm-0", 2))
    insert(b, online_steps("arm-b", 2))
    sampler = ShardedSampler([a.address, b.address], AUTH, timeout_s=10, seed=0)
    try:
        with pytest.raises(grpc.RpcError) as err:
            sampler.Sample(replay_pb2.SampleRequest(batch_size=8, tables={"online": 1, "demos": 1}), timeout=10)
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "no sampleable transitions in table 'demos'" in err.value.details()  # the learner waits for data
        assert all(s.up for s in sampler.shards)
    finally:
        sampler.close()


# --------------------------------------------------------------------------- 3. padded action dims


def _padded_batch(pad: float) -> Batch:
    """8 rows of a 4-dim padded action whose last two dims are padding (filled with `pad`)."""
    n = 8
    obs = {"state": torch.randn(n, 3, generator=torch.Generator().manual_seed(0))}
    action = torch.full((n, 4), 0.3)
    action[:, 2:] = pad
    return Batch(
        observation=obs,
        action=action,
        reward=torch.zeros(n),
        next_observation=obs,
        terminated=torch.zeros(n),
        intervention=torch.ones(n, dtype=torch.bool),
        action_mask=torch.tensor([[True, True, False, False]] * n),
    )


LAYOUT = Layout({"state": Feature((3,), "float32")}, -np.ones(4, np.float32), np.ones(4, np.float32))


@pytest.mark.parametrize("loss", ["mse", "nll"])
def test_bc_losses_ignore_padded_action_dims(loss: str) -> None:
    out = []
    for pad in (0.0, 0.9):
        torch.manual_seed(0)
        algo = BC(BCParams(loss=loss, hidden=[16]), LAYOUT, torch.device("cpu"))
        out.append(algo.update(_padded_batch(pad))["bc_loss"])
    assert out[0] == pytest.approx(out[1], rel=1e-6)
    # every dim real: the masked NLL is the plain one
    torch.manual_seed(0)
    head = BC(BCParams(hidden=[16]), LAYOUT, torch.device("cpu")).actor.head
    features, action = torch.randn(5, 3), torch.rand(5, 4) * 1.8 - 0.9
    full = masked_log_prob(head, features, action, torch.ones(5, 4, dtype=torch.bool))
    torch.testing.assert_close(full, log_prob_of(head, features, action))


def test_flow_bc_loss_ignores_padded_action_dims() -> None:
    out = []
    for pad in (0.0, 0.9):
        algo = FlowBc(FlowBcParams(tables={"demos": 1.0}, image_size=16, hidden=16), LAYOUT, torch.device("cpu"))
        torch.manual_seed(1)  # the same noise and flow times for both batches
        out.append(algo.update(_padded_batch(pad))["flow_loss"])
    assert out[0] == pytest.approx(out[1], rel=1e-6)


def test_online_batches_leave_rows_of_a_pretrain_table_unflagged_when_not_human(
    mixed: ReplayService, tmp_path: Path
) -> None:
    """pretrain: {table: demos, human: false} (its demos table holds policy rollouts): the online batches, which
    every algorithm asks to flag "demos" (BatchRequest.human_tables), leave its rows unflagged too."""
    pretrain = {"table": "demos", "steps": 1, "min_size": 1, "human": False}
    half = {"online": 0.5, "demos": 0.5}
    params = {"tables": half, "only_interventions": True, "batch_size": 64, "hidden": [16]}
    run = _run(tmp_path, "bc", params, pretrain=pretrain)
    batch = run.sample_once(stub(mixed)).batch
    assert int((marks(batch) == DEMO).sum()) > 0 and not batch.intervention.any()
    assert run.algo.update(batch)["rows"] == 0.0
