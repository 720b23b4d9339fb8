"""Learner checkpoints (atomic, pruned, resumable), batch decoding, published weights, service lifecycle."""

from __future__ import annotations

import functools
from pathlib import Path

import grpc
import numpy as np
import pytest
import torch

from cloud_learner.checkpoint import LATEST, list_checkpoints, load_latest, save_checkpoint
from cloud_learner.learner import (
    LearnerError,
    RobotShape,
    checkpoint_state,
    decode_batch,
    restore_checkpoint,
    robot_shape,
)
from cloud_learner.sac import SAC
from cloud_learner.server import LearnerService
from tests import helpers
from user.config import LearnerConfig, ServerConfig, StackConfig
from user.policy import build_policy, policy_spec_for
from user.rpc import make_channel
from user.v1 import learner_pb2, learner_pb2_grpc, replay_pb2, robot_pb2
from user.weights import WeightAssembler, iter_weight_messages, pack_weights
from user.wire import WireError, to_tensor

torch.set_num_threads(1)

OBS_DIM, ACT_DIM = 6, 3
SHAPE = RobotShape(OBS_DIM, np.full(ACT_DIM, -1.0, np.float32), np.array([1.0, 2.0, 0.5], np.float32))
SMALL = LearnerConfig(hidden=[32, 32], batch_size=16)


random_batch = functools.partial(helpers.random_sac_batch, OBS_DIM, ACT_DIM)


def trained_sac(updates: int = 5) -> SAC:
    torch.manual_seed(0)
    sac = SAC(OBS_DIM, SHAPE.action_low, SHAPE.action_high, SMALL)
    for i in range(updates):
        sac.update(random_batch(i))
    return sac


def mean_actions(sac: SAC, obs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return sac.actor(obs)[2]


# --------------------------------------------------------------------------- checkpoint files


def test_save_load_round_trip_and_latest_pointer(tmp_path: Path) -> None:
    state = {"updates": 7, "weight_version": 2, "w": torch.arange(5.0), "nested": {"x": torch.ones(2, 2), "n": 3}}
    path = save_checkpoint(tmp_path / "ckpt", state)
    assert path.name == "ckpt-000000007.pt"
    assert (tmp_path / "ckpt" / LATEST).read_text().strip() == path.name
    loaded = load_latest(tmp_path / "ckpt")
    assert loaded is not None and loaded["updates"] == 7 and loaded["nested"]["n"] == 3
    torch.testing.assert_close(loaded["w"], state["w"])
    assert not list((tmp_path / "ckpt").glob("*.tmp")), "temp files are renamed, not left behind"


def test_load_latest_without_checkpoints(tmp_path: Path) -> None:
    assert load_latest(tmp_path / "missing") is None
    (tmp_path / "empty").mkdir()
    assert load_latest(tmp_path / "empty") is None


def test_prunes_to_last_three(tmp_path: Path) -> None:
    for updates in (100, 200, 300, 400, 500):
        save_checkpoint(tmp_path, {"updates": updates})
    assert [p.name for p in list_checkpoints(tmp_path)] == [
        "ckpt-000000300.pt",
        "ckpt-000000400.pt",
        "ckpt-000000500.pt",
    ]
    assert load_latest(tmp_path)["updates"] == 500  # type: ignore[index]


def test_stale_tmp_files_are_ignored(tmp_path: Path) -> None:
    save_checkpoint(tmp_path, {"updates": 10})
    # A crash mid-write leaves temp files with higher update counts: never loaded, never listed.
    (tmp_path / ".ckpt-000000020.pt.abc123.tmp").write_bytes(b"half a checkpoint")
    (tmp_path / "ckpt-000000030.pt.tmp").write_bytes(b"garbage")
    (tmp_path / ".latest.xyz.tmp").write_text("ckpt-000000030.pt.tmp\n")
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt-000000010.pt"]
    assert load_latest(tmp_path)["updates"] == 10  # type: ignore[index]


def test_missing_or_stale_pointer_falls_back_to_newest(tmp_path: Path) -> None:
    save_checkpoint(tmp_path, {"updates": 1})
    save_checkpoint(tmp_path, {"updates": 2})
    (tmp_path / LATEST).write_text("ckpt-000000999.pt\n")
    assert load_latest(tmp_path)["updates"] == 2  # type: ignore[index]
    (tmp_path / LATEST).unlink()
    assert load_latest(tmp_path)["updates"] == 2  # type: ignore[index]


# --------------------------------------------------------------------------- resume


def test_resume_gives_identical_actor_and_training(tmp_path: Path) -> None:
    sac = trained_sac(updates=5)
    save_checkpoint(tmp_path, checkpoint_state(sac, weight_version=3, shape=SHAPE))

    ckpt = load_latest(tmp_path)
    assert ckpt is not None
    torch.manual_seed(123)  # a different init: everything must come from the checkpoint
    resumed = SAC(OBS_DIM, SHAPE.action_low, SHAPE.action_high, SMALL)
    assert restore_checkpoint(resumed, ckpt, SHAPE) == 3
    assert resumed.updates == sac.updates == 5
    assert resumed.alpha == pytest.approx(sac.alpha)

    obs = torch.randn(32, OBS_DIM)
    torch.testing.assert_close(mean_actions(resumed, obs), mean_actions(sac, obs), rtol=0, atol=0)
    for name, arr in sac.actor_tensors().items():
        np.testing.assert_array_equal(resumed.actor_tensors()[name], arr)

    # Optimizer moments and targets came back too: the next update is the same on both.
    torch.manual_seed(7)
    a = sac.update(random_batch(99))
    torch.manual_seed(7)
    b = resumed.update(random_batch(99))
    assert a == pytest.approx(b)
    torch.testing.assert_close(mean_actions(resumed, obs), mean_actions(sac, obs))


def test_resume_refuses_checkpoint_of_another_robot(tmp_path: Path) -> None:
    sac = trained_sac(updates=1)
    ckpt = checkpoint_state(sac, 1, SHAPE)
    other = RobotShape(OBS_DIM + 1, SHAPE.action_low, SHAPE.action_high)
    with pytest.raises(LearnerError, match="obs_dim"):
        restore_checkpoint(sac, ckpt, other)


# --------------------------------------------------------------------------- wire side


def test_published_weights_rebuild_the_same_policy() -> None:
    sac = trained_sac(updates=3)
    packed = pack_weights(4, policy_spec_for(sac.actor_config()), sac.actor_tensors(), learner_updates=sac.updates)
    asm, weights = WeightAssembler(), None
    for msg in iter_weight_messages(packed, 1024):
        weights = asm.feed(msg) or weights
    assert weights is not None and weights.learner_updates == 3
    policy = build_policy(weights.policy, weights.tensors, weights.version)
    obs = np.random.default_rng(0).standard_normal((8, OBS_DIM)).astype(np.float32)
    expected = mean_actions(sac, torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(policy.act({"state": obs}, deterministic=True), expected, rtol=0, atol=1e-6)


def robot_spec(obs_shape: list[int]) -> robot_pb2.RobotSpec:
    spec = robot_pb2.RobotSpec(robot_id="arm-0", kind="sim_reach_arm")
    spec.action.shape.append(ACT_DIM)
    spec.action.low.extend(SHAPE.action_low.tolist())
    spec.action.high.extend(SHAPE.action_high.tolist())
    spec.observation.add(name="state", dtype=1, shape=obs_shape)
    spec.observation.add(name="camera.front", dtype=5, shape=[8, 8, 3], is_image=True)
    return spec


def test_robot_shape_from_spec() -> None:
    shape = robot_shape(robot_spec([2, 3]))
    assert shape.obs_dim == 6
    np.testing.assert_array_equal(shape.action_high, SHAPE.action_high)
    spec = robot_spec([6])
    del spec.observation[0]
    with pytest.raises(LearnerError):
        robot_shape(spec)


def replay_batch(n: int, obs_dim: int = OBS_DIM) -> replay_pb2.Batch:
    rng = np.random.default_rng(0)
    batch = replay_pb2.Batch(
        action=to_tensor(rng.standard_normal((n, ACT_DIM)).astype(np.float32)),
        reward=to_tensor(rng.standard_normal(n).astype(np.float32)),
        terminated=to_tensor(rng.random(n) < 0.5),
    )
    batch.observation.tensors["state"].CopyFrom(to_tensor(rng.standard_normal((n, obs_dim)).astype(np.float32)))
    batch.observation.tensors["camera.front"].CopyFrom(to_tensor(np.zeros((n, 8, 8, 3), np.uint8)))
    batch.next_observation.tensors["state"].CopyFrom(to_tensor(rng.standard_normal((n, obs_dim)).astype(np.float32)))
    return batch


def test_decode_batch() -> None:
    out = decode_batch(replay_batch(5), OBS_DIM, ACT_DIM, "cpu")
    assert {k: tuple(v.shape) for k, v in out.items()} == {
        "obs": (5, OBS_DIM),
        "next_obs": (5, OBS_DIM),
        "action": (5, ACT_DIM),
        "reward": (5,),
        "terminated": (5,),
    }
    assert all(v.dtype == torch.float32 for v in out.values())
    assert set(out["terminated"].tolist()) <= {0.0, 1.0}
    with pytest.raises(WireError):
        decode_batch(replay_batch(5, obs_dim=OBS_DIM + 1), OBS_DIM, ACT_DIM, "cpu")
    no_state = replay_batch(5)
    del no_state.observation.tensors["state"]
    with pytest.raises(WireError):
        decode_batch(no_state, OBS_DIM, ACT_DIM, "cpu")


# --------------------------------------------------------------------------- service lifecycle


def test_service_serves_status_while_waiting_for_a_robot(tmp_path: Path) -> None:
    # Control is unreachable: the learner keeps retrying, GetStatus answers, stop() is prompt and clean.
    cfg = StackConfig.model_validate(
        {
            "auth": {"token": "test-token"},
            "learner": {
                "server": ServerConfig(port=0, metrics_port=0).model_dump(),
                "control_addr": "127.0.0.1:1",
                "replay_addr": "127.0.0.1:1",
                "checkpoint_dir": str(tmp_path / "ckpt"),
                "rpc_timeout_s": 1.0,
            },
        }
    )
    service = LearnerService(cfg, start_metrics=False).start()
    try:
        with make_channel(service.address, cfg.auth) as channel:
            stub = learner_pb2_grpc.LearnerStub(channel)
            status = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
            assert (status.weight_version, status.updates, status.training) == (0, 0, False)
            # No version yet: a subscriber waits (here until its deadline).
            call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="t"), timeout=0.5)
            with pytest.raises(grpc.RpcError) as err:
                next(iter(call))
            assert err.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    finally:
        service.stop()
    assert not service.learner.failed
    assert load_latest(tmp_path / "ckpt") is None  # no robot, no model, nothing to save
