"""The CUDA paths (`learner.device` / `inference.device` = cuda): skipped where torch sees no GPU, as in CI.

Run on a GPU machine: the flow_vla policy acts as on the CPU, the inference service serves and hot-swaps weights
on the GPU under concurrent load, algorithms train on the GPU and their checkpoints resume on the CPU, and a
learner service on the GPU trains from a real replay service and publishes weights that inference (on the GPU)
picks up from the learner's stream."""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from tests import helpers

# USER_TEST_GPU=cpu runs the same checks on the CPU (to check the tests themselves where no GPU is)
DEVICE = os.environ.get("USER_TEST_GPU", "cuda")
pytestmark = pytest.mark.skipif(DEVICE.startswith("cuda") and not torch.cuda.is_available(), reason="no CUDA device")

CAMERAS = ("camera.front", "camera.wrist")
wait_for = functools.partial(helpers.wait_for, limit_s=120.0, poll_s=0.1)


def vla_config(hidden: int = 128, image: int = 64):
    from user.policies.flow_vla import FlowVlaConfig

    return FlowVlaConfig(
        image_keys=list(CAMERAS),
        state_keys=["state"],
        state_dim=6,
        action_dim=3,
        action_low=[-1.0, -2.0, 0.0],
        action_high=[1.0, 2.0, 0.5],
        horizon=8,
        image_size=image,
        hidden=hidden,
        flow_steps=5,
    )


def vla_weights(version: int, seed: int = 0):
    from user.policies.flow_vla import policy_spec, random_weights
    from user.weights import WeightSet

    cfg = vla_config()
    return WeightSet(version, policy_spec(cfg), random_weights(cfg, seed))


def observation(seed: int, batch: int | None = None) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    lead = () if batch is None else (batch,)
    obs = {k: rng.integers(0, 256, size=(*lead, 64, 64, 3), dtype=np.uint8) for k in CAMERAS}
    obs["state"] = rng.normal(size=(*lead, 6)).astype(np.float32)
    return obs


def test_flow_vla_acts_on_the_gpu_as_on_the_cpu() -> None:
    from user.policy import build_policy

    weights = vla_weights(1)
    cpu = build_policy(weights.policy, weights.tensors, 1, "cpu")
    gpu = build_policy(weights.policy, weights.tensors, 1, DEVICE)
    obs = observation(0, batch=4)
    a_cpu = cpu.act(obs, deterministic=True)
    a_gpu = gpu.act(obs, deterministic=True)
    assert a_gpu.shape == a_cpu.shape == (4, 8, 3)
    # cuDNN may run the convolutions in TF32: close, not bit-equal; the action ranges are 1-4 wide
    np.testing.assert_allclose(a_gpu, a_cpu, atol=2e-2)
    assert np.isfinite(a_gpu).all()


@pytest.fixture
def inference() -> Iterator:
    from services.inference.server import InferenceService
    from user.config import AuthConfig, StackConfig

    cfg = StackConfig(auth=AuthConfig(token="test-token"))
    cfg.inference.device = DEVICE
    cfg.inference.server.port = 0
    cfg.inference.server.metrics_port = 0
    cfg.inference.server.grace_s = 1.0
    cfg.inference.max_wait_ms = 5.0
    svc = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    yield svc
    svc.stop()


def test_inference_on_the_gpu_serves_chunks_and_swaps_weights_under_load(inference) -> None:
    from user import wire
    from user.rpc import make_channel
    from user.v1 import inference_pb2, inference_pb2_grpc

    inference.load_weights(vla_weights(1))
    stub = inference_pb2_grpc.InferenceStub(make_channel(inference.address, inference.cfg.auth))
    versions: list[int] = []
    errors: list[BaseException] = []
    stop = threading.Event()

    def robot(i: int) -> None:
        request = inference_pb2.ActRequest(
            robot_id=f"arm-{i}", observation=wire.to_tensor_map(observation(i)), deterministic=True
        )
        try:
            while not stop.is_set():
                resp = stub.Act(request, timeout=30)
                chunk = wire.from_tensor(resp.action)
                assert chunk.shape == (8, 3) and np.isfinite(chunk).all()
                assert resp.forward_us > 0
                versions.append(resp.policy_version)
        except BaseException as exc:  # surfaced below: a failed request fails the test
            errors.append(exc)

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    wait_for(lambda: len(versions) > 50, "requests served with version 1")
    for version in range(2, 6):  # swaps while 8 robots keep asking
        inference.load_weights(vla_weights(version, seed=version))
        wait_for(lambda v=version: versions and versions[-1] == v, f"version {version} served")
    stop.set()
    for t in threads:
        t.join(30)
    assert not errors, errors[:3]
    assert max(versions) == 5
    status = stub.Status(inference_pb2.InferenceStatusRequest(), timeout=5)
    assert status.mean_batch_size > 1.0  # the 8 robots were batched on the GPU


def _sac_layout():
    from cloud_learner.algorithm import Feature, Layout

    observation = {"state": Feature((6,), "float32"), **{k: Feature((64, 64, 3), "uint8", True) for k in CAMERAS}}
    return Layout(observation, -np.ones(3, np.float32), np.ones(3, np.float32), ("arm",))


def _arrays(layout, n: int, seed: int, horizon: int = 0) -> dict:
    rng = np.random.default_rng(seed)

    def obs() -> dict[str, np.ndarray]:
        return {
            k: (
                rng.integers(0, 256, (n, *f.shape), dtype=np.uint8) if f.is_image else rng.normal(size=(n, *f.shape))
            ).astype(f.dtype)
            for k, f in layout.observation.items()
        }

    out = {
        "observation": obs(),
        "next_observation": obs(),
        "action": rng.uniform(-1, 1, (n, layout.action_dim)).astype(np.float32),
        "reward": rng.normal(size=n).astype(np.float32),
        "terminated": (rng.random(n) < 0.1).astype(np.float32),
        "intervention": rng.random(n) < 0.5,
    }
    if horizon:
        out["action_chunk"] = rng.uniform(-1, 1, (n, horizon, layout.action_dim)).astype(np.float32)
        out["chunk_mask"] = np.ones((n, horizon), bool)
    return out


def _tensors(tree) -> list[torch.Tensor]:
    if isinstance(tree, torch.Tensor):
        return [tree]
    items = tree.values() if isinstance(tree, dict) else tree if isinstance(tree, list | tuple) else []
    return [t for item in items for t in _tensors(item)]


def _to_cpu(tree):
    """A checkpoint as torch.load(map_location="cpu") gives it back."""
    if isinstance(tree, torch.Tensor):
        return tree.cpu()
    if isinstance(tree, dict):
        return {k: _to_cpu(v) for k, v in tree.items()}
    if isinstance(tree, list | tuple):
        return type(tree)(_to_cpu(v) for v in tree)
    return tree


@pytest.mark.parametrize(
    ("kind", "params", "horizon"),
    [
        ("sac", {"batch_size": 32, "hidden": [64, 64], "num_critics": 4}, 0),
        ("flow_bc", {"batch_size": 16, "horizon": 8, "hidden": 64, "tables": {"online": 1.0}}, 8),
    ],
)
def test_algorithms_train_on_the_gpu_and_resume_on_the_cpu(kind: str, params: dict, horizon: int) -> None:
    from cloud_learner.algorithm import ALGORITHMS
    from cloud_learner.learner import checkpoint_state, restore_checkpoint, to_batch
    from user.policy import build_policy

    layout = _sac_layout()
    gpu = ALGORITHMS.build(kind, params, layout=layout, device=torch.device(DEVICE))
    for seed in range(5):
        batch = to_batch(_arrays(layout, params["batch_size"], seed, horizon), DEVICE)
        scalars = gpu.update(batch)
        assert all(np.isfinite(v) for v in scalars.values()), scalars
    state = checkpoint_state(gpu, kind, 3, layout)
    assert any(t.device.type == torch.device(DEVICE).type for t in _tensors(state))
    cpu = ALGORITHMS.build(kind, params, layout=layout, device=torch.device("cpu"))
    assert restore_checkpoint(cpu, _to_cpu(state), kind, layout, "test") == 3
    # What each side publishes is the same policy (tensors leave the GPU as numpy).
    spec_gpu, tensors_gpu = gpu.policy()
    spec_cpu, tensors_cpu = cpu.policy()
    assert spec_gpu == spec_cpu and tensors_gpu.keys() == tensors_cpu.keys()
    for name, value in tensors_gpu.items():
        assert isinstance(value, np.ndarray), name
        np.testing.assert_allclose(value, tensors_cpu[name], rtol=0, atol=0)
    policy = build_policy(spec_cpu, tensors_cpu, 3, "cpu")
    assert np.isfinite(policy.act({k: v[:2] for k, v in _arrays(layout, 2, 9)["observation"].items()}, True)).all()


def test_learner_on_the_gpu_trains_from_replay_and_inference_on_the_gpu_follows(tmp_path: Path) -> None:
    from cloud_learner.server import LearnerService
    from services.control.server import ControlService
    from services.inference.server import InferenceService
    from services.replay.server import ReplayService
    from tests.test_replay_service import _Edge
    from tests.test_replay_store import episode, spec
    from user.config import StackConfig
    from user.rpc import make_channel
    from user.v1 import (
        control_pb2,
        control_pb2_grpc,
        inference_pb2,
        inference_pb2_grpc,
        learner_pb2,
        learner_pb2_grpc,
        replay_pb2,
        replay_pb2_grpc,
    )
    from user.worker import report_worker

    cfg = StackConfig.model_validate(
        {
            "auth": {"token": "test-token"},
            "experiments": [
                {
                    "name": "reach",
                    "robots": {"kinds": ["test"]},
                    "algorithm": {"kind": "sac", "params": {"batch_size": 64, "hidden": [64, 64]}},
                }
            ],
        }
    )
    for section in (cfg.control, cfg.replay, cfg.inference, cfg.learner):
        section.server.port = 0
        section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.replay.path, cfg.replay.map_size_mb, cfg.replay.commit_max_delay_ms = tmp_path / "replay", 64, 5.0
    lc = cfg.learner
    lc.device, cfg.inference.device = DEVICE, DEVICE
    lc.checkpoint_dir = tmp_path / "ckpt"
    lc.min_transitions, lc.publish_every, lc.checkpoint_every, lc.prefetch_batches = 50, 5, 50, 2
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = cfg.learner.control_addr = cfg.inference.control_addr = control.address
    edge = _Edge(control.address, spec("arm-0"))
    replay = ReplayService(cfg, start_metrics=False).start()
    cfg.learner.replay_addr = replay.address
    learner = None
    inference = None
    try:
        stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, cfg.auth))
        steps = [s for e in range(8) for s in episode("arm-0", f"e{e}", 20, terminated=e % 2 == 0)]
        requests = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]
        acks = list(stub.Insert(iter(requests), timeout=30))
        assert max(s for a in acks for s in a.seqs) == len(steps) - 1
        learner = LearnerService(cfg, start_metrics=False).start()
        cfg.inference.learner_addr = learner.address
        inference = InferenceService(cfg, start_metrics=False).start()
        status_stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))

        def published():
            st = status_stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
            exps = {e.name: e for e in st.experiments}
            return exps["reach"] if exps and exps["reach"].weight_version >= 3 else None

        exp = wait_for(published, "the GPU learner to publish version 3")
        assert exp.sample_errors == 0 and exp.updates > 0
        assert all(np.isfinite(v) for v in exp.scalars.values())
        act = inference_pb2_grpc.InferenceStub(make_channel(inference.address, cfg.auth))
        request = inference_pb2.ActRequest(robot_id="arm-0", observation=steps[0].observation, deterministic=True)

        def served():
            try:
                return act.Act(request, timeout=5)
            except Exception:  # UNAVAILABLE until the first weights arrive from the stream
                return None

        resp = wait_for(served, "inference on the GPU to serve the learner's weights")
        assert resp.policy_version >= 1
        # The learner reports the device it computes on to control, with the machine's GPUs as resources.
        control_stub = control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth))
        with report_worker(learner, "learner", control.address, cfg.auth, lc.device, lambda: ["reach"]):

            def registered():
                listed = control_stub.ListWorkers(control_pb2.ListWorkersRequest(), timeout=5).workers
                return listed[0] if listed else None

            worker = wait_for(registered, "the learner to register as a worker")
        assert worker.kind == "learner" and worker.device == DEVICE and worker.online
        if DEVICE.startswith("cuda"):
            gpus = [d for d in worker.devices if d.name.startswith("cuda")]
            assert gpus and gpus[0].memory_bytes > 0 and gpus[0].model, worker
    finally:
        for svc in (inference, learner, replay):
            if svc is not None:
                svc.stop()
        edge.close()
        control.stop()
    from cloud_learner.checkpoint import load_latest

    ckpt = load_latest(tmp_path / "ckpt" / "reach", map_location="cpu")
    assert ckpt is not None and ckpt["updates"] > 0  # a GPU run's checkpoint opens on a CPU-only machine
