"""The success classifier: `userctl reward train` on a few labelled frames, then the `classifier` task
rewards and ends episodes by it. Frames: a green square (success) or a red one (failure) on noise."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from edge_agent.robot import Observation
from edge_agent.task import TASKS
from user.cli import main as userctl
from user.registry import PluginError
from user.reward_model import load_classifier, load_frames, save_classifier, train_classifier
from user.v1 import robot_pb2, tensor_pb2

SIZE = 24


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _frame(rng: np.random.Generator, success: bool) -> np.ndarray:
    image = rng.integers(0, 60, size=(SIZE, SIZE, 3), dtype=np.uint8)
    r, c = rng.integers(2, SIZE - 8, size=2)
    image[r : r + 6, c : c + 6] = (30, 220, 30) if success else (220, 30, 30)
    return image


def _write_frames(root: Path, per_class: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    for label, success in (("success", True), ("failure", False)):
        (root / label).mkdir(parents=True)
        for i in range(per_class):
            Image.fromarray(_frame(rng, success)).save(root / label / f"{i:03d}.png")


def _spec(camera_shape: list[int]) -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id="arm-0",
        kind="test",
        action=robot_pb2.ActionSpace(shape=[1], low=[-1.0], high=[1.0]),
        observation=[
            robot_pb2.FeatureSpec(name="state", dtype=tensor_pb2.DTYPE_FLOAT32, shape=[3]),
            robot_pb2.FeatureSpec(name="camera.front", dtype=tensor_pb2.DTYPE_UINT8, shape=camera_shape, is_image=True),
        ],
    )


def _obs(image: np.ndarray) -> Observation:
    return Observation(features={"state": np.zeros(3, np.float32), "camera.front": image}, reward=-7.0)


def test_reward_train_then_classifier_task_changes_the_reward(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _write_frames(tmp_path / "frames", per_class=12, seed=0)
    out = tmp_path / "model"
    assert userctl(["reward", "train", "--frames", str(tmp_path / "frames"), "--out", str(out), "--epochs", "40"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 24 and summary["train_accuracy"] == 1.0
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "model.safetensors"]  # no pickle anywhere

    task = TASKS.build("classifier", {"model": str(out)}, where="task.params", spec=_spec([SIZE, SIZE, 3]))
    rng = np.random.default_rng(123)  # frames the classifier never saw
    outcomes = {
        success: [task.evaluate(_obs(_frame(rng, False)), np.zeros(1), _obs(_frame(rng, success))) for _ in range(10)]
        for success in (True, False)
    }
    # The robot's own reward (-7) is replaced by the classifier's verdict.
    assert sum(o.reward == 1.0 and o.terminated and o.success for o in outcomes[True]) >= 9
    assert sum(o.reward == 0.0 and not o.terminated and not o.success for o in outcomes[False]) >= 9
    strict = TASKS.build(
        "classifier",
        {"model": str(out), "threshold": 0.999999, "terminate_on_success": False},
        spec=_spec([SIZE, SIZE, 3]),
    )
    assert strict.evaluate(_obs(_frame(rng, True)), np.zeros(1), _obs(_frame(rng, True))).terminated is False


def test_classifier_from_npz_with_state_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    labels = np.array([1, 0] * 6, np.float32)
    images = np.stack([_frame(rng, bool(y)) for y in labels])
    np.savez(tmp_path / "frames.npz", images=images, labels=labels, state=rng.normal(size=(12, 3)).astype(np.float32))
    loaded = load_frames(tmp_path / "frames.npz")
    assert loaded[2] is not None and loaded[2].shape == (12, 3)
    model = train_classifier(*loaded, epochs=2)
    save_classifier(model, tmp_path / "m")
    again = load_classifier(tmp_path / "m")
    features = {"camera.front": images[0], "state": np.zeros(3, np.float32)}
    assert again.probability(features) == pytest.approx(model.probability(features), abs=1e-6)
    with pytest.raises(ValueError, match="lacks"):
        again.probability({"camera.front": images[0]})


def test_bad_inputs_fail_with_clear_errors(tmp_path: Path) -> None:
    _write_frames(tmp_path / "frames", per_class=3, seed=0)
    (tmp_path / "only_success").mkdir()
    (tmp_path / "only_success" / "success").symlink_to(tmp_path / "frames" / "success")
    assert userctl(["reward", "train", "--frames", str(tmp_path / "only_success"), "--out", str(tmp_path / "x")]) == 2
    with pytest.raises(ValueError, match="neither"):
        load_frames(tmp_path / "missing")
    model = train_classifier(*load_frames(tmp_path / "frames"), epochs=1)
    save_classifier(model, tmp_path / "m")
    with pytest.raises(ValueError, match="trained on"):
        TASKS.build("classifier", {"model": str(tmp_path / "m")}, spec=_spec([SIZE * 2, SIZE, 3]))
    with pytest.raises(ValueError, match=r"needs model\.safetensors"):
        TASKS.build("classifier", {"model": str(tmp_path)}, spec=_spec([SIZE, SIZE, 3]))
    with pytest.raises(PluginError, match="model"):
        TASKS.params("classifier", {})


def _npz(root: Path, **overrides: np.ndarray | None) -> Path:
    """12 labelled SIZE x SIZE frames with a 3-float state, any array replaced (or dropped, with None)."""
    rng = np.random.default_rng(2)
    labels = np.array([1, 0] * 6, np.float32)
    arrays: dict[str, np.ndarray | None] = {
        "images": np.stack([_frame(rng, bool(y)) for y in labels]),
        "labels": labels,
        "state": rng.normal(size=(12, 3)).astype(np.float32),
        **overrides,
    }
    np.savez(root / "frames.npz", **{k: v for k, v in arrays.items() if v is not None})
    return root / "frames.npz"


def _nan_state() -> np.ndarray:
    state = np.zeros((12, 3), np.float32)
    state[4, 1] = np.nan
    return state


def _existing_file(root: Path) -> Path:
    (root / "taken").write_text("")
    return root / "taken"


# case: (writes the --frames input under tmp_path, extra flags, what the stderr line must say)
BadInput = tuple[Callable[[Path], Path], list[str], str]
BAD_INPUTS: dict[str, BadInput] = {
    "fewer state rows than images": (
        lambda t: _npz(t, state=np.zeros((5, 3), np.float32)),
        [],
        r"state in .* \(5, 3\)",
    ),
    "frames smaller than the convs read": (
        lambda t: _npz(t, images=np.zeros((12, 4, 4, 3), np.uint8)),
        [],
        r"4x4, .* need at least \d+x\d+",
    ),
    "float images in [0, 1]": (lambda t: _npz(t, images=np.full((12, SIZE, SIZE, 3), 0.5)), [], "float64, need uint8"),
    "four-channel images": (lambda t: _npz(t, images=np.zeros((12, SIZE, SIZE, 4), np.uint8)), [], "C in"),
    "NaN in the state": (lambda t: _npz(t, state=_nan_state()), [], "state in .* NaN"),
    "state beyond float32": (lambda t: _npz(t, state=np.full((12, 3), 1e300)), [], "float32's range"),
    "no labels": (lambda t: _npz(t, labels=None), [], "lacks labels"),
    "labels not 0/1": (lambda t: _npz(t, labels=np.array([0, 2] * 6)), [], "must be 0/1"),
    "labels of strings": (lambda t: _npz(t, labels=np.array(["yes", "no"] * 6)), [], "labels in .* need one 0/1"),
    "one label per two frames": (lambda t: _npz(t, labels=np.array([0, 1] * 3)), [], r"\(12,\)"),
    "--batch-size 0": (_npz, ["--batch-size", "0"], "--batch-size must be a positive integer, got 0"),
    "--epochs -5": (_npz, ["--epochs", "-5"], "--epochs must be a positive integer, got -5"),
    "--lr nan": (_npz, ["--lr", "nan"], "--lr must be a finite number > 0"),
    "--seed -1": (_npz, ["--seed", "-1"], "--seed must be an integer >= 0"),
    "--out an existing file": (_npz, ["--out", "{taken}"], "--out .*taken is a file"),
    "--out under a file": (_npz, ["--out", "{taken}/model"], "--out .* under .*taken, which is a file"),
    "--frames absent": (lambda t: t / "absent", [], "neither a folder"),
    "loss diverges": (_npz, ["--lr", "1e30", "--epochs", "5"], "training loss stopped being finite"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_reward_train_refuses_bad_input_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture, case: str) -> None:
    write_frames, flags, message = BAD_INPUTS[case]
    frames, taken = write_frames(tmp_path), _existing_file(tmp_path)
    out_flags = [] if "--out" in flags else ["--out", str(tmp_path / "model")]
    argv = ["reward", "train", "--frames", str(frames), *out_flags, *(f.format(taken=taken) for f in flags)]
    assert userctl(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and len(captured.err.splitlines()) == 1, captured.err
    assert re.match(rf"userctl reward train: .*{message}", captured.err), captured.err
    assert not list(tmp_path.rglob("*.safetensors")) and not list(tmp_path.rglob("config.json"))
