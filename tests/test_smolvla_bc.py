"""smolvla_bc: lerobot's SmolVLA fine-tuned online (HG-DAgger) from a local checkpoint folder, tiny models only.

The kind is a plug-in whose params refuse a folder that is no SmolVLA checkpoint; the experiment's layout is
checked against the checkpoint; human rows train (the loss at fixed noise falls, the actor's tensors move),
the policy's own rows from a mixed table do not; padded chunk steps do not count; the batch is mapped as
inference maps observations; the published `smolvla` policy acts exactly like the trained model; a
checkpoint resumes to the identical next update.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot.policies.smolvla.modeling_smolvla")

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, Feature, Layout
from cloud_learner.learner import checkpoint_state, restore_checkpoint
from user.policies.smolvla import (
    SmolVlaPolicy,
    load_checkpoint,
    make_tiny_backbone,
    save_checkpoint,
    tiny_smolvla_config,
)
from user.policy import build_policy
from user.registry import PluginError
from user.text import INSTRUCTION_KEY, encode_instruction

WORDS = ["reach", "the", "red", "green", "blue", "target"]
H, A, STATE, SIZE, N = 4, 3, 5, 32, 8  # chunk, action dim, state dim, camera pixels, rows per batch
CAMERAS = ["top", "wrist"]  # the checkpoint's; the robots' camera.front / camera.wrist map onto them in order
TARGET = np.array([0.6, -0.5, 0.3], np.float32)  # what the human did
CPU = torch.device("cpu")


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    root = tmp_path_factory.mktemp("smolvla_bc")
    backbone = make_tiny_backbone(root / "backbone", WORDS, image_size=SIZE)
    torch.manual_seed(0)
    model = SmolVLAPolicy(tiny_smolvla_config(backbone, CAMERAS, STATE, A, horizon=H, image_size=SIZE))
    return save_checkpoint(model, root / "checkpoint")


def layout(cameras: int = 2, state: int = STATE, action: int = A) -> Layout:
    obs = {"state": Feature((state,), "float32"), INSTRUCTION_KEY: Feature((64,), "uint8")}
    for name in ["camera.front", "camera.wrist", "camera.side"][:cameras]:
        obs[name] = Feature((SIZE, SIZE, 3), "uint8", is_image=True)
    return Layout(obs, np.full(action, -1.0, np.float32), np.ones(action, np.float32), ("lang_reach_arm",))


def build(folder: Path, seed: int = 0, **params: object) -> Algorithm:
    raw = {"checkpoint": str(folder), "batch_size": N, "lr": 1e-3, "seed": seed, **params}
    return ALGORITHMS.build("smolvla_bc", raw, layout=layout(), device=CPU)


def observation(n: int = N, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "camera.front": torch.randint(0, 256, (n, SIZE, SIZE, 3), generator=g, dtype=torch.uint8),
        "camera.wrist": torch.randint(0, 256, (n, SIZE, SIZE, 3), generator=g, dtype=torch.uint8),
        "state": torch.randn(n, STATE, generator=g),
        INSTRUCTION_KEY: torch.from_numpy(np.stack([encode_instruction("reach the green target")] * n)),
    }


def human_batch(intervention: bool | list[bool] = True, n: int = N, seed: int = 0) -> Batch:
    obs = observation(n, seed)
    chunk = torch.from_numpy(np.tile(TARGET, (n, H, 1)))
    flags = torch.tensor(intervention if isinstance(intervention, list) else [intervention] * n)
    return Batch(
        observation=obs,
        action=chunk[:, 0].clone(),
        reward=torch.zeros(n),
        next_observation=obs,
        terminated=torch.zeros(n),
        intervention=flags,
        action_chunk=chunk,
        chunk_mask=torch.ones(n, H, dtype=torch.bool),
    )


def fixed_noise_loss(algo: Algorithm, batch: Batch) -> float:
    """The flow-matching loss at one fixed draw of noise and time (lerobot samples both per call)."""
    raw = algo.lerobot_batch(batch.observation)  # type: ignore[attr-defined]
    raw["action"], raw["action_is_pad"] = algo.targets(batch)  # type: ignore[attr-defined]
    with torch.no_grad():
        torch.manual_seed(1234)
        loss, _ = algo.model.forward(algo.pre(raw))  # type: ignore[attr-defined]
    return float(loss)


def numpy_obs(obs: dict[str, torch.Tensor], n: int = 2) -> dict[str, np.ndarray]:
    return {k: v[:n].numpy() for k, v in obs.items()}


# --- the plug-in and its params ---------------------------------------------------------------------------


def test_kind_is_a_plugin_whose_params_refuse_a_folder_that_is_no_smolvla_checkpoint(
    checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from user.cli import main

    assert "smolvla_bc" in ALGORITHMS.kinds()
    assert main(["plugins", "algorithm", "smolvla_bc"]) == 0
    rows = {line.split()[0] for line in capsys.readouterr().out.splitlines()[2:]}
    assert {"checkpoint", "lr", "batch_size", "tables", "human_only", "demo_tables", "image_keys"} <= rows
    assert {"default_instruction", "train_expert_only", "freeze_vision"} <= rows

    where = "experiments[0].algorithm.params"
    with pytest.raises(PluginError, match=r"params\.checkpoint: Field required"):
        ALGORITHMS.params("smolvla_bc", {}, where)
    with pytest.raises(PluginError, match=r"params\.checkpoint: .*not a folder"):
        ALGORITHMS.params("smolvla_bc", {"checkpoint": str(tmp_path / "nowhere")}, where)
    with pytest.raises(PluginError, match=r"params\.checkpoint: .*no config\.json"):
        ALGORITHMS.params("smolvla_bc", {"checkpoint": str(tmp_path)}, where)
    (tmp_path / "config.json").write_text(json.dumps({"type": "act"}))
    with pytest.raises(PluginError, match=r"params\.checkpoint: .*'act' policy, not 'smolvla'"):
        ALGORITHMS.params("smolvla_bc", {"checkpoint": str(tmp_path)}, where)
    with pytest.raises(PluginError, match=r"params\.lr"):
        ALGORITHMS.params("smolvla_bc", {"checkpoint": str(checkpoint), "lr": 0}, where)
    params = ALGORITHMS.params("smolvla_bc", {"checkpoint": str(checkpoint)}, where)
    assert params.tables == {"demos": 0.5, "interventions": 0.5} and params.human_only  # type: ignore[attr-defined]


def test_the_layout_must_fit_the_checkpoint(checkpoint: Path) -> None:
    def make(lay: Layout, **params: object) -> Algorithm:
        return ALGORITHMS.build("smolvla_bc", {"checkpoint": str(checkpoint), **params}, layout=lay, device=CPU)

    with pytest.raises(ValueError, match=r"action_dim: .* 4 values, the checkpoint 3"):
        make(layout(action=4))
    with pytest.raises(ValueError, match=r"state_keys: .* 7 values, the checkpoint's observation.state 5"):
        make(layout(state=7))
    with pytest.raises(ValueError, match=r"image_keys: the robots have 3 cameras"):
        make(layout(cameras=3))
    with pytest.raises(ValueError, match=r"image_keys: \['side'\] are not cameras of the checkpoint"):
        make(layout(), image_keys={"camera.front": "side"})
    with pytest.raises(ValueError, match=r"image_keys: \['camera.back'\] are not camera features"):
        make(layout(), image_keys={"camera.back": "top"})
    with pytest.raises(ValueError, match=r"state_keys: \['joints'\] are not state features"):
        make(layout(), state_keys=["joints"])
    # Three robot cameras, two chosen by name (one left out); one camera of two is fine too (SmolVLA masks the other).
    assert make(layout(cameras=3), image_keys={"camera.side": "top", "camera.front": "wrist"}).image_keys == {  # type: ignore[attr-defined]
        "camera.side": "top",
        "camera.front": "wrist",
    }
    assert make(layout(cameras=1)).image_keys == {"camera.front": "top"}  # type: ignore[attr-defined]


# --- learning from humans -----------------------------------------------------------------------------------


def test_human_rows_train_the_expert_and_the_policys_own_rows_are_skipped(checkpoint: Path) -> None:
    algo = build(checkpoint, tables={"online": 1.0})  # a mixed table: intervention flags decide
    request = algo.batch_request()
    assert request.tables == {"online": 1.0} and request.action_horizon == H and request.batch_size == N
    before = {k: v.copy() for k, v in algo.policy()[1].items()}

    stats = algo.update(human_batch(intervention=False))
    assert stats["human_rows"] == 0 and algo.updates == 0
    assert all(np.array_equal(before[k], v) for k, v in algo.policy()[1].items())

    assert algo.update(human_batch([True, False] * (N // 2)))["human_rows"] == N // 2
    batch = human_batch(intervention=True)
    start = fixed_noise_loss(algo, batch)
    for _ in range(25):
        stats = algo.update(batch)
    assert stats["human_rows"] == N and np.isfinite(stats["bc_loss"]) and np.isfinite(stats["grad_norm"])
    assert algo.updates == 26
    assert fixed_noise_loss(algo, batch) < 0.7 * start

    # The checkpoint's recipe (train_expert_only): the expert and projections moved, the VLM did not.
    after = algo.policy()[1]
    moved = {k for k in after if not np.array_equal(before[k], after[k])}
    assert any("lm_expert" in k for k in moved) and any("action_out_proj" in k for k in moved)
    assert not any(".vlm." in k for k in moved), sorted(k for k in moved if ".vlm." in k)[:3]


def test_freeze_flags_override_the_checkpoints(checkpoint: Path) -> None:
    def trainable(algo: Algorithm) -> set[str]:
        return {k for k, q in algo.model.named_parameters() if q.requires_grad}  # type: ignore[attr-defined]

    default = trainable(build(checkpoint))
    assert default and not any(".vlm." in k for k in default)
    whole = trainable(build(checkpoint, train_expert_only=False, freeze_vision=False))
    assert any(".vlm.model.text_model." in k for k in whole) and any("vision_model" in k for k in whole)
    no_vision = trainable(build(checkpoint, train_expert_only=False, freeze_vision=True))
    assert any(".vlm.model.text_model." in k for k in no_vision) and not any("vision_model" in k for k in no_vision)
    assert default < no_vision < whole


def test_chunks_come_from_replay_and_padded_steps_do_not_count(checkpoint: Path) -> None:
    algo = build(checkpoint)
    batch = human_batch()
    batch.action_chunk, batch.chunk_mask = None, None
    with pytest.raises(ValueError, match="action_chunk"):
        algo.update(batch)

    batch = human_batch()
    batch.chunk_mask[:, 2:] = False  # the episode ended (or the human handed back) after two steps
    loss = fixed_noise_loss(algo, batch)
    batch.action_chunk[:, 2:] = 5.0  # whatever stands past the end: not a target
    assert fixed_noise_loss(algo, batch) == pytest.approx(loss, rel=1e-6)
    batch.chunk_mask[:, 2:] = True
    assert fixed_noise_loss(algo, batch) > loss + 1.0
    batch.action_chunk = batch.action_chunk[:, :2]
    with pytest.raises(ValueError, match="does not match the checkpoint's chunk"):
        algo.update(batch)


# --- what reaches inference -------------------------------------------------------------------------------


def test_batches_are_mapped_as_inference_maps_observations(checkpoint: Path) -> None:
    algo = build(checkpoint, default_instruction="reach the red target")
    spec, _ = algo.policy()
    served = SmolVlaPolicy(spec, None, 0, model=algo.model)  # type: ignore[attr-defined]
    obs = observation(3)
    obs[INSTRUCTION_KEY][2] = 0  # no instruction: the default
    ours = algo.pre(algo.lerobot_batch(obs))  # type: ignore[attr-defined]
    theirs = served.preprocess(numpy_obs(obs, 3), [])
    keys = [k for k, v in theirs.items() if isinstance(v, torch.Tensor)]
    assert {"observation.images.top", "observation.images.wrist", "observation.state"} <= set(keys)
    assert any("language" in k for k in keys)
    for key in keys:
        torch.testing.assert_close(ours[key], theirs[key], msg=key)
    assert ours["task"] == ["reach the green target\n"] * 2 + ["reach the red target\n"]


def test_the_published_policy_acts_like_the_trained_model(checkpoint: Path) -> None:
    algo = build(checkpoint, default_instruction="reach the green target")
    obs = numpy_obs(observation(seed=5))
    untrained = build_policy(*algo.policy(), version=1).act(obs, deterministic=True)
    batch = human_batch()
    for _ in range(5):
        algo.update(batch)

    spec, tensors = algo.policy()
    assert spec.kind == "smolvla"
    config = json.loads(spec.config_json)
    assert config["checkpoint"] == str(checkpoint) and config["action_dim"] == A
    assert config["image_keys"] == {"camera.front": "top", "camera.wrist": "wrist"}
    assert config["state_keys"] == ["state"]
    assert all(isinstance(t, np.ndarray) for t in tensors.values())
    served = build_policy(spec, tensors, version=algo.updates)
    assert served.chunk_horizon == H and served.action_shape == (A,)
    assert set(served.observation_keys) == {"camera.front", "camera.wrist", "state", INSTRUCTION_KEY}
    actions = served.act(obs, deterministic=True)
    assert actions.shape == (2, H, A) and np.abs(actions).max() <= 1.0

    trained = SmolVlaPolicy(spec, None, algo.updates, model=algo.model)  # type: ignore[attr-defined]
    np.testing.assert_allclose(actions, trained.act(obs, deterministic=True), atol=1e-5)
    assert not np.allclose(actions, untrained, atol=1e-3)  # the learner's weights, not the folder's


def test_checkpoint_round_trip_resumes_identically(checkpoint: Path, tmp_path: Path) -> None:
    algo = build(checkpoint, seed=0)
    for i in range(2):
        algo.update(human_batch(seed=i))
    buf = io.BytesIO()
    torch.save(checkpoint_state(algo, "smolvla_bc", 3, layout()), buf)  # as the learner writes it
    buf.seek(0)
    restored = build(checkpoint, seed=1)  # the folder's weights: everything trained must come from the checkpoint
    assert restore_checkpoint(restored, torch.load(buf, weights_only=True), "smolvla_bc", layout(), "test") == 3
    assert restored.updates == 2
    batch = human_batch(seed=9)
    torch.manual_seed(7)
    a = algo.update(batch)
    torch.manual_seed(7)
    b = restored.update(batch)
    assert a == pytest.approx(b, rel=1e-5, abs=1e-6)
    ours, theirs = algo.policy()[1], restored.policy()[1]
    for name, x in ours.items():
        np.testing.assert_allclose(x, theirs[name], atol=1e-6, err_msg=name)
    slower = build(checkpoint, lr=2e-4)  # a resume takes the config's learning rate (lr is resumable)
    slower.load_state_dict(restored.state_dict())
    assert {g["lr"] for g in slower.optimizer.param_groups} == {2e-4}  # type: ignore[attr-defined]
    assert "lr" in type(algo).resumable_params and "checkpoint" not in type(algo).resumable_params

    # The trained weights saved as a lerobot folder load through the same path a downloaded checkpoint does.
    model, _, _ = load_checkpoint(save_checkpoint(algo.model, tmp_path / "resaved"))  # type: ignore[attr-defined]
    torch.testing.assert_close(model.state_dict(), algo.model.state_dict())  # type: ignore[attr-defined]
