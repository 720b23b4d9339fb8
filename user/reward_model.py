"""A success classifier on camera frames (+ optional state): the learned reward of the `classifier` task.

Train it from labelled frames with `userctl reward train --frames DIR_OR_NPZ --out DIR`:

- a folder with `success/` and `failure/` subfolders of PNG or JPEG frames (all the same size), or
- an `.npz` with `images` (N, H, W, C) uint8 (C 1 or 3), `labels` (N,) 0/1 and optionally `state` (N, D) finite.

Bad inputs (wrong shapes or dtypes, float pixels, frames smaller than the convolutions read, non-finite state,
out-of-range flags, an --out that is a file) are refused before training, and a run whose loss stops being finite
saves nothing: `userctl reward train` reports either in one line and exits 2.

The model is the CNN encoder of the "cnn" policy (user.policies.cnn) plus an MLP giving one logit.
It is saved as `DIR/model.safetensors` (weights) and `DIR/config.json` (architecture, camera key,
training metrics): nothing is pickled, so a model file from elsewhere cannot run code on the edge.
Training holds out a fifth of the frames (at least 10 in all) and reports accuracy on them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from safetensors.torch import load_file, save_file
from torch import nn

from user.arg_types import non_negative_int, positive_float, positive_int
from user.policies.cnn import CameraEncoder, ConvEncoder, random_shift
from user.policies.mlp import mlp

MODEL_FILE, CONFIG_FILE = "model.safetensors", "config.json"
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}
IMAGE_CHANNELS = (1, 3)
_PROBE_SIDE = 256  # a frame side the default conv stack accepts, so an encoder can be built and its convs read


class TrainingDiverged(RuntimeError):
    """The loss or the weights stopped being finite: the model would be useless, so it is not saved."""


class ClassifierConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: str = Field(default="camera.front", description="observation key of the frames")
    image_shape: list[int] = Field(description="(H, W, C) of the frames")
    state_key: str | None = Field(default=None, description="float feature fed beside the image, if any")
    state_dim: int = 0
    channels: list[int] = [16, 32, 32]
    strides: list[int] = [2, 2, 2]
    latent_dim: int = 32
    hidden: list[int] = [64]
    metrics: dict[str, float] = {}


class SuccessClassifier(nn.Module):
    """obs dict -> success logit (B,)."""

    def __init__(self, config: ClassifierConfig) -> None:
        super().__init__()
        self.config = config
        state_keys = [config.state_key] if config.state_key else []
        state_dims = [config.state_dim] if config.state_key else []
        self.encoder = ConvEncoder(
            [config.camera],
            [config.image_shape],
            state_keys,
            state_dims,
            config.channels,
            config.strides,
            config.latent_dim,
        )
        self.head = mlp(self.encoder.out_dim, config.hidden, 1)

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.head(self.encoder(obs)).squeeze(-1)

    @torch.no_grad()
    def probability(self, features: dict[str, np.ndarray]) -> float:
        """P(success) of one observation (unbatched feature arrays, as a robot returns them)."""
        keys = [self.config.camera, *([self.config.state_key] if self.config.state_key else [])]
        missing = [k for k in keys if k not in features]
        if missing:
            raise ValueError(f"observation lacks {missing} needed by the success classifier")
        image = np.asarray(features[self.config.camera])
        if list(image.shape) != self.config.image_shape:
            raise ValueError(
                f"frame {self.config.camera!r} is {image.shape}, the classifier expects {self.config.image_shape}"
            )
        obs = {self.config.camera: torch.from_numpy(np.ascontiguousarray(image, dtype=np.uint8))[None]}
        if self.config.state_key:
            obs[self.config.state_key] = torch.as_tensor(features[self.config.state_key], dtype=torch.float32)[None]
        device = next(self.parameters()).device
        return float(torch.sigmoid(self({k: v.to(device) for k, v in obs.items()}))[0])


# --- labelled frames ------------------------------------------------------------------------------


def smallest_frame(channels: Sequence[int], strides: Sequence[int]) -> tuple[int, int]:
    """The least (H, W) the classifier's convolutions accept: one output pixel after the last conv, walked back
    through each conv's kernel, stride, padding and dilation (read from the layers, so it follows the model)."""
    encoder = CameraEncoder((_PROBE_SIDE, _PROBE_SIDE, 1), channels, strides, latent_dim=1)
    convs = [m for m in encoder.convs if isinstance(m, nn.Conv2d)]
    sides = [1, 1]
    for conv in reversed(convs):
        padding = (0, 0) if isinstance(conv.padding, str) else conv.padding  # a string mode ("valid") pads nothing
        for dim in (0, 1):
            reach = conv.dilation[dim] * (conv.kernel_size[dim] - 1) + 1
            sides[dim] = max(1, (sides[dim] - 1) * conv.stride[dim] + reach - 2 * padding[dim])
    return sides[0], sides[1]


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in ("images", "labels", "state") if key in data}
    # empty, truncated or pickled files, object arrays, or a bare .npy (no archive to open as a context)
    except (ValueError, EOFError, TypeError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path} is not a readable .npz of arrays: {exc}") from None
    missing = [key for key in ("images", "labels") if key not in arrays]
    if missing:
        raise ValueError(f"{path} lacks {' and '.join(missing)} (it has {sorted(arrays)})")
    return arrays["images"], arrays["labels"], arrays.get("state")


def _read_folder(path: Path) -> tuple[np.ndarray, np.ndarray, None]:
    from PIL import Image

    frames, labels_list = [], []
    for label, folder in ((1.0, "success"), (0.0, "failure")):
        files = sorted(p for p in (path / folder).glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
        for file in files:
            with Image.open(file) as img:
                frames.append(np.asarray(img.convert("RGB"), np.uint8))
            labels_list.append(label)
    if not frames:
        raise ValueError(f"{path} has no PNG/JPEG frames in success/ or failure/")
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"frames in {path} differ in size: {sorted(shapes)}")
    return np.stack(frames), np.asarray(labels_list, np.float32), None


def _check_images(images: np.ndarray, source: Path) -> np.ndarray:
    if images.dtype != np.uint8:
        hint = " (scale [0, 1] floats by 255 and cast them to uint8 yourself)" if images.dtype.kind == "f" else ""
        raise ValueError(f"images in {source} are {images.dtype}, need uint8 pixels 0..255{hint}")
    if images.ndim != 4 or images.shape[-1] not in IMAGE_CHANNELS:
        raise ValueError(f"images in {source} are {images.shape}, need (N, H, W, C) with C in {IMAGE_CHANNELS}")
    default = ClassifierConfig(image_shape=list(images.shape[1:]))
    least = smallest_frame(default.channels, default.strides)
    if images.shape[1] < least[0] or images.shape[2] < least[1]:
        raise ValueError(
            f"frames in {source} are {images.shape[1]}x{images.shape[2]}, the classifier's convolutions "
            f"need at least {least[0]}x{least[1]}"
        )
    return images


def _check_labels(labels: np.ndarray, frames: int, source: Path) -> np.ndarray:
    if labels.dtype.kind not in "biuf" or labels.shape != (frames,):
        raise ValueError(
            f"labels in {source} are {labels.dtype} {labels.shape}, need one 0/1 number per frame ({frames},)"
        )
    values = set(np.unique(labels).tolist())
    if not values <= {0, 1} or len(values) < 2:
        raise ValueError(f"labels in {source} must be 0/1 and include both success and failure frames")
    return labels.astype(np.float32)


def _check_state(state: np.ndarray, frames: int, source: Path) -> np.ndarray:
    if state.dtype.kind not in "biuf" or state.ndim != 2 or len(state) != frames:
        raise ValueError(
            f"state in {source} is {state.dtype} {state.shape}, need numbers (N, D) with one row per "
            f"frame (N = {frames})"
        )
    with np.errstate(over="ignore"):  # overflow is what the check below reports
        state = state.astype(np.float32)
    if not np.isfinite(state).all():  # after the cast: float64 beyond float32's range becomes inf here
        raise ValueError(f"state in {source} has values that are NaN, infinite or beyond float32's range")
    return state


def check_frames(
    images: np.ndarray, labels: np.ndarray, state: np.ndarray | None, source: Path
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The arrays as training needs them, or ValueError naming `source` and what is wrong."""
    images = _check_images(np.asarray(images), source)
    labels = _check_labels(np.asarray(labels), len(images), source)
    return images, labels, None if state is None else _check_state(np.asarray(state), len(images), source)


def load_frames(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(images uint8 (N, H, W, C), labels float32 (N,), state float32 (N, D) or None), checked by check_frames."""
    path = Path(path)
    if path.is_file() and path.suffix == ".npz":
        images, labels, state = _read_npz(path)
    elif path.is_dir():
        images, labels, state = _read_folder(path)
    else:
        raise ValueError(f"{path} is neither a folder of success/ and failure/ frames nor an .npz")
    return check_frames(images, labels, state, path)


# --- training -------------------------------------------------------------------------------------


def train_classifier(
    images: np.ndarray,
    labels: np.ndarray,
    state: np.ndarray | None = None,
    camera: str = "camera.front",
    epochs: int = 30,
    batch_size: int = 32,
    lr: float = 1e-3,
    image_pad: int = 2,
    seed: int = 0,
) -> SuccessClassifier:
    """Binary cross-entropy on randomly shifted frames, success rows reweighted to balance the classes.

    Takes arrays as load_frames returns them; raises TrainingDiverged when the loss or the weights stop being finite."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    config = ClassifierConfig(
        camera=camera,
        image_shape=list(images.shape[1:]),
        state_key="state" if state is not None else None,
        state_dim=int(state.shape[1]) if state is not None else 0,
    )
    model = SuccessClassifier(config)
    order = rng.permutation(len(labels))
    n_val = len(labels) // 5 if len(labels) >= 10 else 0
    val, train = order[:n_val], order[n_val:]

    def obs(idx: np.ndarray, shift: bool) -> dict[str, torch.Tensor]:
        image = torch.from_numpy(images[idx])
        out = {camera: random_shift(image, image_pad) if shift and image_pad else image}
        if state is not None:
            out["state"] = torch.from_numpy(state[idx])
        return out

    y = torch.from_numpy(labels)
    positives = float(y[train].sum())
    pos_weight = torch.tensor((len(train) - positives) / max(positives, 1.0))
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    loss = torch.zeros(())
    for epoch in range(epochs):
        shuffled = rng.permutation(train)
        for start in range(0, len(shuffled), batch_size):
            idx = shuffled[start : start + batch_size]
            logits = model(obs(idx, True))  # shifted frames: the DrQ augmentation the RL encoders see
            loss = nn.functional.binary_cross_entropy_with_logits(logits, y[idx], pos_weight=pos_weight)
            if not torch.isfinite(loss):
                raise TrainingDiverged(
                    f"the training loss stopped being finite ({loss.item()}) in epoch {epoch + 1}; "
                    "lower the learning rate (--lr) or rescale the state"
                )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

    if not all(torch.isfinite(p).all() for p in model.parameters()):  # the last step can overflow the weights
        raise TrainingDiverged("the weights stopped being finite after training; lower the learning rate (--lr)")
    model.eval()
    with torch.no_grad():
        metrics = {"train_loss": float(loss.detach()), "frames": float(len(labels))}
        for name, idx in (("train_accuracy", train), ("val_accuracy", val)):
            if len(idx):
                predicted = (model(obs(idx, False)) > 0).float()
                metrics[name] = float((predicted == y[idx]).float().mean())
    model.config = config.model_copy(update={"metrics": metrics})
    return model


# --- files ----------------------------------------------------------------------------------------


def save_classifier(model: SuccessClassifier, out: str | Path) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, str(out / MODEL_FILE))
    (out / CONFIG_FILE).write_text(model.config.model_dump_json(indent=1))
    return out


def load_classifier(path: str | Path, device: str = "cpu") -> SuccessClassifier:
    """Rebuild from config.json + model.safetensors; a mismatch between them raises ValueError."""
    path = Path(path)
    if not (path / MODEL_FILE).is_file() or not (path / CONFIG_FILE).is_file():
        raise ValueError(f"{path} needs {MODEL_FILE} and {CONFIG_FILE} (written by `userctl reward train`)")
    config = ClassifierConfig.model_validate_json((path / CONFIG_FILE).read_text())
    model = SuccessClassifier(config)
    tensors = load_file(str(path / MODEL_FILE))
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{path / MODEL_FILE} does not match {CONFIG_FILE}: {exc}") from None
    return model.to(torch.device(device)).eval()


# --- `userctl reward train` -----------------------------------------------------------------------


# The ranges of `userctl reward train`'s numeric flags (attribute, flag, argparse type).
FLAG_TYPES: tuple[tuple[str, str, Callable[[str], Any]], ...] = (
    ("epochs", "--epochs", positive_int),
    ("batch_size", "--batch-size", positive_int),
    ("lr", "--lr", positive_float),
    ("seed", "--seed", non_negative_int),
)


def check_flags(args: argparse.Namespace) -> None:
    """Re-apply the argparse types, so a parser that declared plain int/float still gets the ranges enforced."""
    for attribute, flag, parse in FLAG_TYPES:
        try:
            parse(str(getattr(args, attribute)))
        except (argparse.ArgumentTypeError, ValueError) as exc:
            raise ValueError(f"{flag} {exc}") from None
    if not args.camera:
        raise ValueError("--camera must name an observation key, got an empty string")


def check_out_folder(out: Path) -> None:
    """Refuse before training an --out that cannot become a writable folder: a file, or a path through one."""
    existing = next(p for p in (out, *out.parents) if p.exists())
    if existing == out and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    if not existing.is_dir():
        raise ValueError(f"--out {out} lies under {existing}, which is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out}: {existing} is not writable")


def _train_and_save(args: argparse.Namespace) -> SuccessClassifier:
    check_flags(args)
    check_out_folder(Path(args.out))
    images, labels, state = load_frames(args.frames)
    model = train_classifier(images, labels, state, args.camera, args.epochs, args.batch_size, args.lr, seed=args.seed)
    save_classifier(model, args.out)
    return model


def run_cli(args: argparse.Namespace) -> int:
    """`userctl reward train`: 0 and a JSON summary on stdout, or 2 and one line on stderr saying what is wrong."""
    try:
        model = _train_and_save(args)
    except (ValueError, OSError, TrainingDiverged) as exc:
        message = " ".join(str(exc).split())  # one line, whatever the exception's text
        print(f"userctl reward train: {message}", file=sys.stderr)
        return 2
    summary: dict[str, Any] = {"out": str(Path(args.out)), **model.config.metrics}
    print(json.dumps(summary))
    return 0
