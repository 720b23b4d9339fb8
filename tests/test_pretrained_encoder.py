"""A ResNet-18 camera trunk: started from a local pretrained file, frozen or fine-tuned, shipped with the policy.

The "pretrained" file is a torchvision resnet18 state dict with random weights and batch-norm statistics
made here (no model hub), saved as safetensors the way a user would keep downloaded weights.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import torch
import torchvision
from safetensors.torch import load_file, save_file

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, Feature, Layout
from user.policy import build_policy
from user.registry import PluginError

IMAGE, STATE_DIM = (16, 16, 3), 4
LOW, HIGH = np.array([-1.0, -1.0], np.float32), np.array([1.0, 1.0], np.float32)
SMALL = {"hidden": [16, 16], "batch_size": 6, "latent_dim": 8, "image_pad": 2}


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


@pytest.fixture
def weights_file(tmp_path: Path) -> Path:
    torch.manual_seed(123)
    net = torchvision.models.resnet18(weights=None)
    with torch.no_grad():  # statistics no fresh network has, so a load that skips them shows
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
    path = tmp_path / "resnet18.safetensors"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(path))
    return path


def _layout() -> Layout:
    obs = {"state": Feature((STATE_DIM,), "float32"), "camera.front": Feature(IMAGE, "uint8", is_image=True)}
    return Layout(obs, LOW, HIGH, ("test_arm",))


def _build(kind: str, **params: object) -> Algorithm:
    torch.manual_seed(0)
    return ALGORITHMS.build(kind, {**SMALL, **params}, layout=_layout(), device=torch.device("cpu"))


def _obs(g: torch.Generator, n: int) -> dict[str, torch.Tensor]:
    return {
        "state": torch.randn(n, STATE_DIM, generator=g),
        "camera.front": torch.randint(0, 256, (n, *IMAGE), generator=g, dtype=torch.uint8),
    }


def _batch(seed: int, n: int) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(
        observation=_obs(g, n),
        action=torch.rand(n, 2, generator=g) * 2 - 1,
        reward=torch.randn(n, generator=g),
        next_observation=_obs(g, n),
        terminated=torch.zeros(n),
        intervention=torch.ones(n, dtype=torch.bool),
    )


def _trunk_state(algo: Algorithm) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in algo.actor.encoder.trunk.net.state_dict().items()}


@pytest.mark.parametrize("kind", ["sac", "bc"])
def test_a_frozen_pretrained_trunk_never_moves_and_ships_with_the_policy(kind: str, weights_file: Path) -> None:
    algo = _build(kind, backbone="resnet18", pretrained=str(weights_file), freeze_backbone=True)
    stored = load_file(str(weights_file))
    start = _trunk_state(algo)
    assert all(torch.equal(start[k], stored[k]) for k in start)  # every weight and statistic from the file
    head = [p.clone() for p in algo.actor.head.parameters()]
    for i in range(3):
        algo.update(_batch(i, algo.batch_request().batch_size))
    after = _trunk_state(algo)
    assert all(torch.equal(after[k], start[k]) for k in start)  # no SGD step, no batch-norm statistics
    assert any(not torch.equal(a, b) for a, b in zip(head, algo.actor.head.parameters(), strict=True))

    spec, tensors = algo.policy()
    assert '"backbone": "resnet18"' in spec.config_json
    assert np.array_equal(tensors["encoder.trunk.net.bn1.running_mean"], stored["bn1.running_mean"].numpy())
    policy = build_policy(spec, tensors, version=1)  # what an edge or the inference service builds
    obs = _obs(torch.Generator().manual_seed(9), 3)
    with torch.no_grad():
        expected = algo.actor(obs)[2].numpy()
    acted = policy.act({k: v.numpy() for k, v in obs.items()}, deterministic=True)
    np.testing.assert_allclose(acted, expected, rtol=1e-5, atol=1e-6)


def test_an_unfrozen_trunk_is_fine_tuned(weights_file: Path) -> None:
    algo = _build("sac", backbone="resnet18", pretrained=str(weights_file))
    start = _trunk_state(algo)
    for i in range(2):
        algo.update(_batch(i, algo.batch_request().batch_size))
    after = _trunk_state(algo)
    assert not torch.equal(after["conv1.weight"], start["conv1.weight"])


def test_the_frozen_trunk_is_left_out_of_optimizers_and_polyak_averaging(weights_file: Path) -> None:
    frozen = _build("sac", backbone="resnet18", freeze_backbone=True)
    tuned = _build("sac", backbone="resnet18")
    trunk = sum(p.numel() for p in frozen.actor.encoder.trunk.parameters())
    owned = [sum(p.numel() for g in a.critic_optimizer.param_groups for p in g["params"]) for a in (frozen, tuned)]
    assert owned[1] - owned[0] == trunk
    assert sum(p.numel() for p in frozen._critic_params) == owned[0]
    assert frozen.critic_target.encoder.trunk is frozen.actor.encoder.trunk  # shared, not a second copy
    assert tuned.critic_target.encoder.trunk is not tuned.actor.encoder.trunk


def test_bad_backbone_options_fail_at_build_naming_the_field(tmp_path: Path) -> None:
    with pytest.raises(PluginError, match="pretrained"):
        _build("sac", backbone="resnet18", pretrained=str(tmp_path / "missing.safetensors"))
    with pytest.raises(PluginError, match="backbone"):
        _build("sac", backbone="resnet50")
    with pytest.raises(PluginError, match="need backbone: resnet18"):
        _build("sac", freeze_backbone=True)
    other = tmp_path / "other.safetensors"
    save_file({"conv1.weight": torch.zeros(8, 3, 3, 3)}, str(other))
    with pytest.raises(ValueError, match="not a resnet18 state dict"):
        _build("sac", backbone="resnet18", pretrained=str(other))


def test_a_checkpoint_of_a_frozen_trunk_resumes_without_the_file(weights_file: Path) -> None:
    algo = _build("sac", backbone="resnet18", pretrained=str(weights_file), freeze_backbone=True)
    algo.update(_batch(0, algo.batch_request().batch_size))
    buf = io.BytesIO()
    torch.save(algo.state_dict(), buf)
    buf.seek(0)
    restored = _build("sac", backbone="resnet18", freeze_backbone=True)  # no file: the checkpoint holds the trunk
    restored.load_state_dict(torch.load(buf, weights_only=True))
    batch = _batch(5, algo.batch_request().batch_size)
    torch.manual_seed(7)
    a = algo.update(batch)
    torch.manual_seed(7)
    b = restored.update(batch)
    assert a == pytest.approx(b, rel=1e-5, abs=1e-6)
    ours, theirs = _trunk_state(algo), _trunk_state(restored)
    assert all(torch.equal(ours[k], theirs[k]) for k in ours)
