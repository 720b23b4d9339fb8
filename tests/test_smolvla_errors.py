"""SmolVLA: a bad checkpoint folder or a spec that does not fit the model is a ValueError naming the file or field
when the policy is built; a request whose state does not fit is refused by check_observation, not in the forward."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot.policies.smolvla.modeling_smolvla")

from user.policies.smolvla import (
    PROCESSOR_FILES,
    SmolVlaPolicy,
    SmolVlaSpec,
    make_tiny_backbone,
    policy_spec,
    save_checkpoint,
    tiny_smolvla_config,
)
from user.policy import build_policy, module_tensors
from user.v1 import learner_pb2

torch.set_num_threads(1)
H, A, STATE = 2, 3, 9


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """A tiny SmolVLA checkpoint folder (one camera "front", a state of 9, actions of 3) and its weight set."""
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    root = tmp_path_factory.mktemp("smolvla_errors")
    backbone = make_tiny_backbone(root / "backbone", ["reach", "the", "red", "target"])
    torch.manual_seed(0)
    model = SmolVLAPolicy(tiny_smolvla_config(backbone, ["front"], STATE, A, horizon=H))
    return save_checkpoint(model, root / "checkpoint"), module_tensors(model)


def spec_dict(folder: Path, **changes: Any) -> dict[str, Any]:
    spec = {
        "checkpoint": str(folder),
        "image_keys": {"camera.front": "front"},
        "state_keys": ["state"],
        "action_dim": A,
        "action_low": [-1.0] * A,
        "action_high": [1.0] * A,
        "default_instruction": "reach the red target",
    }
    return {**spec, **changes}


def wire(folder: Path, **changes: Any) -> learner_pb2.PolicySpec:
    """The PolicySpec as it travels (raw JSON: fields SmolVlaSpec itself would refuse get through to the policy)."""
    return learner_pb2.PolicySpec(kind="smolvla", config_json=json.dumps(spec_dict(folder, **changes)))


def copy_of(folder: Path, dest: Path) -> Path:
    shutil.copytree(folder, dest)
    return dest


def test_missing_backbone_folder_is_named(tiny: tuple[Path, dict[str, np.ndarray]], tmp_path: Path) -> None:
    folder, tensors = tiny
    moved = copy_of(folder, tmp_path / "checkpoint")
    config = json.loads((moved / "config.json").read_text())
    config["vlm_model_name"] = str(tmp_path / "gone")
    (moved / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=r"backbone folder .*gone.* does not exist"):
        build_policy(wire(moved), tensors, version=1)
    with pytest.raises(ValueError, match=r"backbone folder .*gone.* does not exist"):
        SmolVlaPolicy.from_checkpoint(moved, SmolVlaSpec(**spec_dict(moved)))


def test_another_lerobot_policy_type_is_refused(tiny: tuple[Path, dict[str, np.ndarray]], tmp_path: Path) -> None:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    config = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (STATE,)),
            "observation.images.front": PolicyFeature(FeatureType.VISUAL, (3, 64, 64)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (A,))},
        dim_model=16,
        n_heads=2,
        dim_feedforward=16,
        n_encoder_layers=1,
        n_decoder_layers=1,
        chunk_size=H,
        n_action_steps=H,
        pretrained_backbone_weights=None,
        device="cpu",
    )
    act = save_checkpoint(ACTPolicy(config), tmp_path / "act")
    with pytest.raises(ValueError, match="type 'act', not 'smolvla'"):
        SmolVlaPolicy.from_checkpoint(act, SmolVlaSpec(**spec_dict(act)))
    with pytest.raises(ValueError, match="type 'act', not 'smolvla'"):
        build_policy(wire(act), tiny[1], version=1)


def test_broken_checkpoint_files_are_named(tiny: tuple[Path, dict[str, np.ndarray]], tmp_path: Path) -> None:
    folder, tensors = tiny
    truncated = copy_of(folder, tmp_path / "truncated")
    weights = (truncated / "model.safetensors").read_bytes()
    (truncated / "model.safetensors").write_bytes(weights[: len(weights) // 2])
    with pytest.raises(ValueError, match=r"model\.safetensors is not a readable safetensors file"):
        SmolVlaPolicy.from_checkpoint(truncated, SmolVlaSpec(**spec_dict(truncated)))

    no_weights = copy_of(folder, tmp_path / "no_weights")
    (no_weights / "model.safetensors").unlink()
    with pytest.raises(ValueError, match=r"model\.safetensors missing"):
        SmolVlaPolicy.from_checkpoint(no_weights, SmolVlaSpec(**spec_dict(no_weights)))

    only_config = tmp_path / "only_config"
    only_config.mkdir()
    shutil.copy(folder / "config.json", only_config)
    with pytest.raises(ValueError, match=re.escape(PROCESSOR_FILES[0])):
        SmolVlaPolicy.from_checkpoint(only_config, SmolVlaSpec(**spec_dict(only_config)))
    with pytest.raises(ValueError, match=re.escape(PROCESSOR_FILES[0])):
        build_policy(wire(only_config), tensors, version=1)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"action_dim": 7, "action_low": [-1.0] * 7, "action_high": [1.0] * 7}, "action_dim is 7"),
        ({"action_dim": 2, "action_low": [-1.0] * 2, "action_high": [1.0] * 2}, "action_dim is 2"),
        ({"action_low": [-1.0] * 5}, "action_low has 5 values"),
        ({"action_high": [1.0] * 2}, "action_high has 2 values"),
        ({"action_low": [1.0] * A, "action_high": [-1.0] * A}, "action_low must not exceed action_high"),
        ({"image_keys": {"camera.front": "side"}}, r"image_keys names cameras \['side'\]"),
        ({"image_keys": {}}, "image_keys is empty"),
        ({"state_keys": []}, "state_keys is empty"),
    ],
)
def test_spec_that_does_not_fit_the_model_is_refused_at_build(
    tiny: tuple[Path, dict[str, np.ndarray]], changes: dict[str, Any], field: str
) -> None:
    folder, tensors = tiny
    with pytest.raises(ValueError, match=field):
        build_policy(wire(folder, **changes), tensors, version=1)


def test_state_of_the_wrong_size_is_refused_per_request(tiny: tuple[Path, dict[str, np.ndarray]]) -> None:
    folder, tensors = tiny
    policy = build_policy(policy_spec(SmolVlaSpec(**spec_dict(folder))), tensors, version=1)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, size=(64, 64, 3), dtype=np.uint8)
    policy.check_observation({"camera.front": frame, "state": np.zeros(STATE, np.float32)})
    for size in (5, 12):  # lerobot pads a short state silently; a long one fails the whole batch's forward
        obs = {"camera.front": frame, "state": np.zeros(size, np.float32)}
        with pytest.raises(ValueError, match=f"has {size} values, the policy reads {STATE}"):
            policy.check_observation(obs)
        with pytest.raises(ValueError, match=f"has {size} values, the policy reads {STATE}"):
            policy.act({k: v[None] for k, v in obs.items()}, deterministic=True)
