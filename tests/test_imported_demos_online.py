"""Imported demonstrations in online training: a LeRobotDataset imported with `userctl replay import` into "demos"
(stored under its dataset's robot id) is half of every RLPD batch beside the experiment's robot's online steps, with
real control, replay (LMDB in tmp) and learner. Replay tells the learner the specs of the robots holding a table
(StatsRequest.spec_tables); the learner samples "demos" over the robots that fit its own (SampleRequest.
table_robot_ids) and the online table over its robots only. A robot in demos that does not fit is left out."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest

from cloud_learner.learner import ExperimentRun, Learner, _TableRobots
from cloud_learner.replay_sampler import ShardedSampler
from cloud_learner.server import LearnerService
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests import helpers
from tests.test_control import Edge, register_msg
from tests.test_learner_prepare import arm_spec, record_demos, stack_cfg, status_of
from user.cli import main
from user.config import StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2_grpc, replay_pb2, replay_pb2_grpc
from user.weights import WeightStore

pytest.importorskip("lerobot.datasets.lerobot_dataset")

IMPORTED = "lerobot-local-arm"  # `replay import --repo-id local/arm`'s default robot id
ODD = "lerobot-local-odd"  # another dataset whose state and action sizes differ from the arm's
DEMO_STATE = 100.0  # every imported state is >= this; the sim arm's are within a few units of 0
DEMO_ACTION = np.array([0.5, -0.5, 0.25], np.float32)
RLPD = {
    "name": "rl",
    "algorithm": {
        "kind": "rlpd",
        "params": {"batch_size": 32, "utd": 1, "num_critics": 2, "hidden": [32, 32], "bc_weight": 1.0},
    },
}
MESSAGE = "robot of a sampled table left out of online training"


def make_dataset(root: Path, repo_id: str, state: int, action: int, episodes: int = 4, length: int = 10) -> None:
    """A LeRobotDataset made with lerobot's own writer: states DEMO_STATE + t, one action for every frame."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (state,), "names": None},
        "action": {"dtype": "float32", "shape": (action,), "names": None},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }
    ds = LeRobotDataset.create(repo_id, 20, features, root=root, robot_type="arm", use_videos=False)
    for _ in range(episodes):
        for t in range(length):
            frame = {
                "observation.state": np.full(state, DEMO_STATE + t, np.float32),
                "action": np.resize(DEMO_ACTION, action),
                "next.reward": np.array([float(t == length - 1)], np.float32),
                "next.done": np.array([t == length - 1]),
                "task": "reach",
            }
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()


def import_demos(tmp_path: Path, buffer: Path) -> None:
    """Both datasets into `buffer`'s demos table, as a user does before starting replay."""
    for repo, state, action in (("local/arm", 15, 3), ("local/odd", 4, 2)):
        root = tmp_path / repo.replace("/", "-")
        make_dataset(root, repo, state, action)
        assert main(["replay", "import", str(root), "--repo-id", repo, "--path", str(buffer), "--table", "demos"]) == 0


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[tuple[StackConfig, ReplayService, Edge]]:
    """Control, with the sim arm arm-0 registered; replay over a buffer holding the imported demos and arm-0's
    online steps (inserted through Replay.Insert, validated against arm-0's spec from control)."""
    cfg = stack_cfg(tmp_path, RLPD)
    cfg.learner.min_transitions, cfg.learner.publish_every = 1, 10
    import_demos(tmp_path, Path(cfg.replay.path))
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = cfg.learner.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    cfg.learner.replay_addr = replay.address
    edge = Edge(control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth)), register_msg("e", arm_spec()))
    try:
        assert edge.next_message().WhichOneof("msg") == "registered"
        steps, _, _ = record_demos(episodes=10)  # arm-0's own steps, into the online table
        reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]
        acked = [q for ack in stub(cfg, replay).Insert(iter(reqs), timeout=30) for q in ack.seqs]
        assert acked == list(range(len(steps)))
        yield cfg, replay, edge
    finally:
        edge.close()
        replay.stop()
        control.stop()


def stub(cfg: StackConfig, replay: ReplayService) -> replay_pb2_grpc.ReplayStub:
    return replay_pb2_grpc.ReplayStub(make_channel(replay.address, cfg.auth))


class Recording:
    """Forwards to a real replay stub, keeping the SampleRequests the learner sent."""

    def __init__(self, stub: replay_pb2_grpc.ReplayStub) -> None:
        self.stub, self.requests = stub, []

    def Sample(self, request: replay_pb2.SampleRequest, timeout: float | None = None) -> replay_pb2.SampleResponse:
        self.requests.append(request)
        return self.stub.Sample(request, timeout=timeout)

    def Stats(self, request: replay_pb2.StatsRequest, timeout: float | None = None) -> replay_pb2.StatsResponse:
        return self.stub.Stats(request, timeout=timeout)


def a_batch(run: ExperimentRun, source: Any) -> Any:
    """The run's first batch (the first samples wait for replay's Stats to name the demo robots)."""
    return helpers.wait_for(lambda: run.sample_once(source), "a batch with the imported demos", limit_s=60.0).batch


def left_out(caplog: pytest.LogCaptureFixture, robot_id: str) -> list[logging.LogRecord]:
    return [
        r for r in caplog.records if r.getMessage() == MESSAGE and getattr(r, "fields", {}).get("robot_id") == robot_id
    ]


def test_rlpd_samples_half_imported_demos_flagged_human_and_leaves_out_a_robot_that_does_not_fit(
    stack: tuple[StackConfig, ReplayService, Edge], caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg, replay, _ = stack
    monkeypatch.setattr(_TableRobots, "REFRESH_S", 0.0)  # a Stats per sample here: the odd robot is still logged once
    run = ExperimentRun(Learner(cfg, WeightStore()), 0, cfg.experiments[0], [arm_spec()])
    source = Recording(stub(cfg, replay))
    with caplog.at_level(logging.INFO, logger="cloud_learner.learner"):
        for _ in range(5):
            batch = a_batch(run, source)
    state, intervention = batch.observation["state"].numpy(), batch.intervention.numpy()
    demo = state[:, 0] >= DEMO_STATE
    assert len(batch.action) == 32 and int(demo.sum()) == 16  # RLPD's exact half
    np.testing.assert_array_equal(intervention, demo)  # demos is a human table: its rows come flagged
    np.testing.assert_allclose(batch.action.numpy()[demo], np.tile(DEMO_ACTION, (16, 1)))
    assert (np.abs(state[~demo]) < DEMO_STATE / 2).all()  # the online half: arm-0's own steps
    assert run.state.sample_errors == 0
    assert len(left_out(caplog, ODD)) == 1 and "differ" in left_out(caplog, ODD)[0].fields["why"]
    assert left_out(caplog, IMPORTED) == []

    # The request that got it: online over arm-0 only, demos over arm-0 and the imported robot (not the odd one).
    request = source.requests[-1]
    assert dict(request.tables) == {"online": 0.5, "demos": 0.5} and list(request.human_tables) == ["demos"]
    assert list(request.robot_ids) == ["arm-0"] and set(request.table_robot_ids) == {"demos"}
    assert list(request.table_robot_ids["demos"].ids) == ["arm-0", IMPORTED]
    # before replay's first answer only arm-0 was asked for, and replay had no demos of it: waiting, not an error
    assert not source.requests[0].table_robot_ids


def test_shards_sample_the_imported_demos_too(stack: tuple[StackConfig, ReplayService, Edge], tmp_path: Path) -> None:
    """Through ShardedSampler (learner.replay_addrs): Stats merges the shards' specs, each table's rows are split by
    that table's robots. The second shard is empty."""
    cfg, replay, _ = stack
    other = stack_cfg(tmp_path / "shard2", RLPD)
    other.replay.control_addr = cfg.replay.control_addr
    second = ReplayService(other, start_metrics=False).start()
    sampler = ShardedSampler([replay.address, second.address], cfg.auth, timeout_s=10.0, seed=0)
    try:
        stats = sampler.Stats(replay_pb2.StatsRequest(spec_tables=["demos"]))
        assert [s.robot_id for s in stats.specs] == [IMPORTED, ODD] and stats.specs_left_out == 0
        run = ExperimentRun(Learner(cfg, WeightStore()), 0, cfg.experiments[0], [arm_spec()])
        batch = a_batch(run, sampler)
        demo = batch.observation["state"].numpy()[:, 0] >= DEMO_STATE
        assert int(demo.sum()) == 16 and (batch.intervention.numpy() == demo).all()
        assert run.state.sample_errors == 0
    finally:
        sampler.close()
        second.stop()


def test_a_learner_trains_rlpd_on_its_robot_and_imported_demos(stack: tuple[StackConfig, ReplayService, Edge]) -> None:
    """The whole service: without the imported robot in demos it would wait for data for ever (arm-0 recorded
    no demos)."""
    cfg, _, _ = stack
    learner = LearnerService(cfg, start_metrics=False).start()
    try:
        trained = helpers.wait_for(
            lambda: (s := status_of(cfg, learner)).updates >= 20 and s, "20 RLPD updates", limit_s=180.0, poll_s=0.1
        )
        assert trained.sample_errors == 0 and trained.weight_version >= 2
    finally:
        learner.stop()


def test_replay_refuses_bad_table_robot_ids_and_spec_tables_naming_the_field(
    stack: tuple[StackConfig, ReplayService, Edge],
) -> None:
    cfg, replay, _ = stack
    replay_stub = stub(cfg, replay)
    tables = {"online": 1.0, "demos": 1.0}

    def sample(table_robot_ids: dict[str, list[str]]) -> replay_pb2.SampleResponse:
        request = replay_pb2.SampleRequest(batch_size=8, tables=tables, robot_ids=["arm-0"])
        for table, ids in table_robot_ids.items():
            request.table_robot_ids[table].ids.extend(ids)
        return replay_stub.Sample(request, timeout=10)

    bad = (
        ({"nope": ["arm-0"]}, "table_robot_ids: 'nope' is not one of tables"),
        ({"demos": [""]}, "table_robot_ids['demos'].ids[0]: a robot id is 1 to 128 bytes"),
        ({"demos": ["x" * 129]}, "table_robot_ids['demos'].ids[0]"),
        ({"demos": [f"r{i}" for i in range(4097)]}, "table_robot_ids['demos'].ids: at most 4096 robots"),
    )
    for ids, field in bad:
        with pytest.raises(grpc.RpcError) as err:
            sample(ids)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and field in err.value.details(), ids
    for names, field in ((["no spaces"], "spec_tables[0]"), ([f"t{i}" for i in range(65)], "spec_tables: at most")):
        with pytest.raises(grpc.RpcError) as err:
            replay_stub.Stats(replay_pb2.StatsRequest(spec_tables=names), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and field in err.value.details()

    # Each table over its own robots: demos over the imported robot alone, online over arm-0; counts per table.
    held = replay_stub.Stats(replay_pb2.StatsRequest(), timeout=10).tables
    resp = sample({"demos": [IMPORTED]})
    assert resp.table_transitions["demos"] == held["demos"].robots[IMPORTED].transitions > 0
    assert resp.table_transitions["online"] == held["online"].robots["arm-0"].transitions > 0
    assert resp.transitions == held["online"].transitions  # robot_ids' (arm-0's) transitions
    with pytest.raises(grpc.RpcError) as err:  # the odd robot's rows beside arm-0's: replay samples what it is asked
        sample({"demos": [ODD]})
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "layouts" in err.value.details()
    with pytest.raises(grpc.RpcError) as err:  # without table_robot_ids demos is arm-0's: it recorded none
        sample({})
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "'demos'" in err.value.details()

    # Stats: the specs of the robots holding transitions in the tables asked for, none otherwise.
    assert [s.robot_id for s in replay_stub.Stats(replay_pb2.StatsRequest(spec_tables=["demos"])).specs] == [
        IMPORTED,
        ODD,
    ]
    assert [s.robot_id for s in replay_stub.Stats(replay_pb2.StatsRequest(spec_tables=["online"])).specs] == ["arm-0"]
    assert not replay_stub.Stats(replay_pb2.StatsRequest()).specs
