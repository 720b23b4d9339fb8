"""SmolVLA (lerobot 0.6.1) behind the Policy interface, from a tiny local checkpoint folder built here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot.policies.smolvla.modeling_smolvla")

from user.policies.smolvla import (
    SmolVlaPolicy,
    SmolVlaSpec,
    make_tiny_backbone,
    policy_spec,
    save_checkpoint,
    tiny_smolvla_config,
)
from user.policy import build_policy
from user.text import INSTRUCTION_KEY, encode_instruction

torch.set_num_threads(1)
WORDS = ["reach", "the", "red", "green", "blue", "target"]
H, A, STATE = 4, 3, 9


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    root = tmp_path_factory.mktemp("smolvla")
    backbone = make_tiny_backbone(root / "backbone", WORDS)
    torch.manual_seed(0)
    model = SmolVLAPolicy(tiny_smolvla_config(backbone, ["front"], STATE, A, horizon=H))
    return save_checkpoint(model, root / "checkpoint")


def spec_for(folder: Path) -> SmolVlaSpec:
    return SmolVlaSpec(
        checkpoint=str(folder),
        image_keys={"camera.front": "front"},
        state_keys=["state"],
        action_dim=A,
        action_low=[-1.0] * A,
        action_high=[1.0] * A,
        default_instruction="reach the red target",
    )


def observation(batch: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "camera.front": rng.integers(0, 256, size=(batch, 64, 64, 3), dtype=np.uint8),
        "state": rng.normal(size=(batch, STATE)).astype(np.float32),
    }


def test_folder_round_trips_through_the_checkpoint_path_and_the_tensor_stream(checkpoint: Path, tmp_path: Path) -> None:
    loaded = SmolVlaPolicy.from_checkpoint(checkpoint, spec_for(checkpoint), version=1)
    obs = observation()
    chunk = loaded.act(obs, deterministic=True)
    assert chunk.shape == (2, H, A) and loaded.chunk_horizon == H
    assert np.abs(chunk).max() <= 1.0

    # Streamed as raw named tensors and rebuilt from the folder's architecture: same actions.
    tensors = loaded.tensors()
    assert all(isinstance(v, np.ndarray) for v in tensors.values())
    streamed = build_policy(policy_spec(spec_for(checkpoint)), tensors, version=2)
    np.testing.assert_allclose(streamed.act(obs, deterministic=True), chunk, atol=1e-5)

    # Saved again (as a learner would checkpoint it) and loaded like a downloaded folder: same actions.
    resaved = save_checkpoint(streamed.model, tmp_path / "resaved")
    again = SmolVlaPolicy.from_checkpoint(resaved, spec_for(resaved), version=3)
    np.testing.assert_allclose(again.act(obs, deterministic=True), chunk, atol=1e-5)

    # Different weights give different actions (so the equalities above mean something).
    torch.manual_seed(123)
    other = {k: (v + np.random.default_rng(1).normal(0, 0.5, v.shape)).astype(v.dtype) for k, v in tensors.items()}
    changed = build_policy(policy_spec(spec_for(checkpoint)), other, version=4)
    assert not np.allclose(changed.act(obs, deterministic=True), chunk, atol=1e-3)


def test_instruction_from_request_or_observation(checkpoint: Path) -> None:
    policy = SmolVlaPolicy.from_checkpoint(checkpoint, spec_for(checkpoint))
    obs = observation(1)
    red = policy.forward(policy.preprocess(obs, ["reach the red target"]), True)
    blue = policy.forward(policy.preprocess(obs, ["reach the blue target"]), True)
    assert not np.allclose(red, blue)
    np.testing.assert_allclose(policy.act(obs, deterministic=True), red, atol=1e-6)  # the default
    with_bytes = dict(obs, **{INSTRUCTION_KEY: encode_instruction("reach the blue target")[None]})
    np.testing.assert_allclose(policy.forward(policy.preprocess(with_bytes, [""]), True), blue, atol=1e-6)


def test_bad_folder_or_tensors_are_refused(checkpoint: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no checkpoint folder"):
        build_policy(policy_spec(spec_for(tmp_path / "nowhere")), {}, version=1)
    with pytest.raises(ValueError, match="missing"):
        build_policy(policy_spec(spec_for(checkpoint)), {"x": np.zeros(1, np.float32)}, version=1)
