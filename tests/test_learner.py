"""Learner: checkpoints (atomic, pruned, resumable per experiment), generic batch decoding, plug-in
algorithms built from config, and a real in-process stack (control, replay, edge) training two experiments."""

from __future__ import annotations

import logging
from pathlib import Path

import grpc
import numpy as np
import pytest
import torch

from cloud_learner.algorithm import ALGORITHMS, Batch, Feature, Layout
from cloud_learner.checkpoint import LATEST, list_checkpoints, load_latest, save_checkpoint
from cloud_learner.learner import LearnerError, checkpoint_state, decode_batch, restore_checkpoint
from cloud_learner.server import LearnerService
from tests import helpers
from user.config import ConfigError, ServerConfig, StackConfig
from user.policy import build_policy
from user.rpc import make_channel
from user.v1 import learner_pb2, learner_pb2_grpc, replay_pb2, robot_pb2
from user.weights import WeightAssembler, iter_weight_messages
from user.wire import WireError, to_tensor

torch.set_num_threads(1)

OBS_DIM, ACT_DIM = 6, 3
LOW, HIGH = np.full(ACT_DIM, -1.0, np.float32), np.array([1.0, 2.0, 0.5], np.float32)
LAYOUT = Layout(
    {"state": Feature((OBS_DIM,), "float32"), "camera.front": Feature((8, 8, 3), "uint8", is_image=True)}, LOW, HIGH
)
SMALL = {"hidden": [32, 32], "batch_size": 16, "features": ["state"]}  # the 8x8 camera is not learned from


def sac_batch(seed: int) -> Batch:
    raw = helpers.random_sac_batch(OBS_DIM, ACT_DIM, seed)
    n = raw["obs"].shape[0]
    images = torch.zeros((n, 8, 8, 3), dtype=torch.uint8)
    return Batch(
        observation={"state": raw["obs"], "camera.front": images},
        action=raw["action"],
        reward=raw["reward"],
        next_observation={"state": raw["next_obs"], "camera.front": images},
        terminated=raw["terminated"],
        intervention=torch.zeros(n, dtype=torch.bool),
    )


def trained_sac(updates: int = 5, seed: int = 0):
    torch.manual_seed(seed)
    algo = ALGORITHMS.build("sac", SMALL, layout=LAYOUT, device=torch.device("cpu"))
    for i in range(updates):
        algo.update(sac_batch(i))
    return algo


def mean_actions(algo, obs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return algo.actor({"state": obs})[2]


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
    algo = trained_sac(updates=5)
    save_checkpoint(tmp_path, checkpoint_state(algo, "sac", weight_version=3, layout=LAYOUT))

    ckpt = load_latest(tmp_path)
    assert ckpt is not None
    resumed = trained_sac(updates=0, seed=123)  # a different init: everything must come from the checkpoint
    assert restore_checkpoint(resumed, ckpt, "sac", LAYOUT, tmp_path) == 3
    assert resumed.updates == algo.updates == 5

    obs = torch.randn(32, OBS_DIM)
    torch.testing.assert_close(mean_actions(resumed, obs), mean_actions(algo, obs), rtol=0, atol=0)
    # Optimizer moments and targets came back too: the next update is the same on both.
    torch.manual_seed(7)
    a = algo.update(sac_batch(99))
    torch.manual_seed(7)
    b = resumed.update(sac_batch(99))
    assert a == pytest.approx(b)


def test_resume_refuses_checkpoint_of_another_layout_or_algorithm(tmp_path: Path) -> None:
    algo = trained_sac(updates=1)
    ckpt = checkpoint_state(algo, "sac", 1, LAYOUT)
    other = Layout({"state": Feature((OBS_DIM + 1,), "float32")}, LOW, HIGH)
    with pytest.raises(LearnerError, match="layout"):
        restore_checkpoint(algo, ckpt, "sac", other, tmp_path)
    with pytest.raises(LearnerError, match="test_mean"):
        restore_checkpoint(algo, ckpt, "test_mean", LAYOUT, tmp_path)


# --------------------------------------------------------------------------- wire side


def test_published_weights_rebuild_the_same_policy() -> None:
    from user.weights import pack_weights

    algo = trained_sac(updates=3)
    spec, tensors = algo.policy()
    assert spec.kind == "mlp"
    packed = pack_weights(4, spec, tensors, learner_updates=algo.updates)
    asm, weights = WeightAssembler(), None
    for msg in iter_weight_messages(packed, 1024):
        weights = asm.feed(msg) or weights
    assert weights is not None and weights.learner_updates == 3
    policy = build_policy(weights.policy, weights.tensors, weights.version)
    assert policy.observation_keys == ("state",) and policy.action_shape == (ACT_DIM,) and policy.chunk_horizon == 1
    obs = np.random.default_rng(0).standard_normal((8, OBS_DIM)).astype(np.float32)
    expected = mean_actions(algo, torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(policy.act({"state": obs}, deterministic=True), expected, rtol=0, atol=1e-6)


def replay_batch(n: int, obs_dim: int = OBS_DIM) -> replay_pb2.Batch:
    rng = np.random.default_rng(0)
    batch = replay_pb2.Batch(
        action=to_tensor(rng.standard_normal((n, ACT_DIM)).astype(np.float32)),
        reward=to_tensor(rng.standard_normal(n).astype(np.float32)),
        terminated=to_tensor(rng.random(n) < 0.5),
        intervention=to_tensor(np.arange(n) % 2 == 0),
    )
    for tmap in (batch.observation, batch.next_observation):
        tmap.tensors["state"].CopyFrom(to_tensor(rng.standard_normal((n, obs_dim)).astype(np.float32)))
        tmap.tensors["camera.front"].CopyFrom(to_tensor(np.full((n, 8, 8, 3), 7, np.uint8)))
    return batch


def test_decode_batch_keeps_every_feature_images_uint8_and_interventions() -> None:
    out = decode_batch(replay_batch(5), LAYOUT)
    assert out.observation["state"].shape == (5, OBS_DIM) and out.observation["state"].dtype == torch.float32
    assert out.observation["camera.front"].shape == (5, 8, 8, 3)
    assert out.observation["camera.front"].dtype == torch.uint8 and int(out.observation["camera.front"].max()) == 7
    assert out.intervention.dtype == torch.bool and out.intervention.tolist() == [True, False, True, False, True]
    assert out.action.shape == (5, ACT_DIM) and out.reward.shape == (5,) and out.terminated.shape == (5,)
    assert set(out.terminated.tolist()) <= {0.0, 1.0}
    with pytest.raises(WireError, match="layout"):
        decode_batch(replay_batch(5, obs_dim=OBS_DIM + 1), LAYOUT)
    no_camera = replay_batch(5)
    del no_camera.observation.tensors["camera.front"]
    with pytest.raises(WireError, match=r"camera\.front"):
        decode_batch(no_camera, LAYOUT)


def test_decode_batch_decodes_frames_replay_sent_as_kept() -> None:
    """A batch asked for with encoded_frames brings its camera frames as PNG bytes (Tensor.frame_bytes): the
    learner decodes them to the same uint8 frames a raw batch would hold."""
    from user import wire
    from user.v1 import tensor_pb2

    raw, kept = replay_batch(5), replay_batch(5)
    frames = np.random.default_rng(1).integers(0, 256, (5, 8, 8, 3), np.uint8)
    blobs = np.empty(5, object)
    blobs[:] = [wire.encode_image(f, tensor_pb2.ENCODING_PNG) for f in frames]
    for batch, tensor in (
        (raw, to_tensor(frames)),
        (kept, wire.frames_tensor(wire.EncodedFrames(blobs, 2, (8, 8, 3)))),
    ):
        for tmap in (batch.observation, batch.next_observation):
            tmap.tensors["camera.front"].CopyFrom(tensor)
    assert len(kept.observation.tensors["camera.front"].frame_bytes) == 5
    a, b = decode_batch(raw, LAYOUT), decode_batch(kept, LAYOUT)
    for part in ("observation", "next_observation"):
        assert torch.equal(getattr(a, part)["camera.front"], getattr(b, part)["camera.front"])


# --------------------------------------------------------------------------- plug-ins from config


def service_cfg(tmp_path: Path, **extra) -> StackConfig:
    return StackConfig.model_validate(
        {
            "auth": {"token": "test-token"},
            "learner": {
                "server": ServerConfig(port=0, metrics_port=0).model_dump(),
                "control_addr": "127.0.0.1:1",
                "replay_addr": "127.0.0.1:1",
                "checkpoint_dir": str(tmp_path / "ckpt"),
                "rpc_timeout_s": 1.0,
            },
            **extra,
        }
    )


def test_bad_algorithm_params_fail_at_start_naming_the_field(tmp_path: Path) -> None:
    import tests.plugins  # noqa: F401 - registers test_mean

    bad = {"experiments": [{"name": "a", "algorithm": {"kind": "test_mean", "params": {"batch_sise": 3}}}]}
    with pytest.raises(ConfigError, match=r"experiments\[0\]\.algorithm\.params\.batch_sise"):
        LearnerService(service_cfg(tmp_path, **bad), start_metrics=False)
    unknown = {"experiments": [{"name": "a", "algorithm": {"kind": "sacc"}}]}
    with pytest.raises(ConfigError, match=r"experiments\[0\]\.algorithm\.kind: unknown algorithm kind 'sacc'"):
        LearnerService(service_cfg(tmp_path, **unknown), start_metrics=False)
    policy = {"experiments": [{"name": "a", "policy": {"kind": "sac_mlp", "params": {"hiden": [8]}}}]}
    with pytest.raises(ConfigError, match=r"experiments\[0\]\.policy\.params\.hiden"):
        LearnerService(service_cfg(tmp_path, **policy), start_metrics=False)


def test_service_serves_status_while_waiting_for_a_robot(tmp_path: Path) -> None:
    # Control is unreachable: the learner keeps retrying, GetStatus answers, stop() is prompt and clean.
    cfg = service_cfg(tmp_path)
    service = LearnerService(cfg, start_metrics=False).start()
    try:
        with make_channel(service.address, cfg.auth) as channel:
            stub = learner_pb2_grpc.LearnerStub(channel)
            status = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
            assert (status.weight_version, status.updates, status.training) == (0, 0, False)
            assert [(e.name, e.algorithm, e.state) for e in status.experiments] == [
                ("default", "sac", "waiting_for_robots")
            ]
            # No version yet: a subscriber waits (here until its deadline).
            call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="t"), timeout=0.5)
            with pytest.raises(grpc.RpcError) as err:
                next(iter(call))
            assert err.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    finally:
        service.stop()
    assert not service.learner.failed
    assert load_latest(tmp_path / "ckpt" / "default") is None  # no robot, no model, nothing to save


class _Refusal(grpc.RpcError):
    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        self._code, self._details = code, details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


class _RefusingReplay:
    """Stands in for a replay stub's Sample only, to drive the learner's error path (no service is mocked)."""

    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        self.error = _Refusal(code, details)

    def Sample(self, request, timeout):
        raise self.error


def test_refused_samples_are_errors_but_an_empty_buffer_is_not(tmp_path: Path) -> None:
    import tests.plugins  # noqa: F401
    from cloud_learner.learner import ExperimentRun, Learner
    from tests.test_experiments import ARM
    from user.weights import WeightStore

    cfg = service_cfg(tmp_path, experiments=[{"name": "a", "algorithm": {"kind": "test_mean"}}])
    learner = Learner(cfg, WeightStore())
    run = ExperimentRun(learner, 0, cfg.experiments[0], [ARM])
    empty = _RefusingReplay(grpc.StatusCode.FAILED_PRECONDITION, "no sampleable transitions in online yet")
    assert run.sample_once(empty) is None and run.state.sample_errors == 0
    assert run.state.waiting_for == "no sampleable transitions in online yet"  # shown in the console
    layout = _RefusingReplay(grpc.StatusCode.FAILED_PRECONDITION, "sampled transitions have different layouts")
    assert run.sample_once(layout) is None and run.state.sample_errors == 1
    assert run.state.waiting_for.startswith("sample refused: FAILED_PRECONDITION: sampled transitions have")
    broken = _RefusingReplay(grpc.StatusCode.INVALID_ARGUMENT, "batch_size must be in 1..4096")
    assert run.sample_once(broken) is None and run.state.sample_errors == 2


def test_a_robot_that_does_not_fit_is_not_trained_and_logged_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The learner polls control about twice a second: a robot whose spec does not fit the layout is refused
    each time, but logged once per spec (a new spec is logged again)."""
    import tests.plugins  # noqa: F401
    from cloud_learner.learner import ExperimentRun, Learner
    from tests.test_experiments import ARM
    from user.weights import WeightStore

    cfg = service_cfg(tmp_path, experiments=[{"name": "a", "algorithm": {"kind": "test_mean"}}])
    run = ExperimentRun(Learner(cfg, WeightStore()), 0, cfg.experiments[0], [ARM])
    odd = robot_pb2.RobotSpec()
    odd.CopyFrom(ARM)
    odd.robot_id = "odd-0"
    odd.observation[0].shape[:] = [odd.observation[0].shape[0] + 1]
    with caplog.at_level(logging.ERROR, logger="cloud_learner.learner"):
        for _ in range(5):
            run.add_robot(odd)
        odd.observation[0].shape[:] = [odd.observation[0].shape[0] + 1]
        run.add_robot(odd)
    assert "odd-0" not in run.specs
    assert [r.getMessage() for r in caplog.records].count(
        "robot does not fit the experiment's layout; not trained"
    ) == 2
