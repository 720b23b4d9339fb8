"""A success classifier on camera frames (+ optional state): the learned reward of the `classifier` task.

Train it from labelled frames with `userctl reward train --frames DIR_OR_NPZ --out DIR`:

- a folder with `success/` and `failure/` subfolders of PNG or JPEG frames (all the same size), or
- an `.npz` with `images` (N, H, W, C) uint8, `labels` (N,) 0/1 and optionally `state` (N, D).

The model is the CNN encoder of the "cnn" policy (user.policies.cnn) plus an MLP giving one logit.
It is saved as `DIR/model.safetensors` (weights) and `DIR/config.json` (architecture, camera key,
training metrics): nothing is pickled, so a model file from elsewhere cannot run code on the edge.
Training holds out a fifth of the frames (at least 10 in all) and reports accuracy on them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from safetensors.torch import load_file, save_file
from torch import nn

from user.policies.cnn import ConvEncoder, random_shift
from user.policies.mlp import mlp

MODEL_FILE, CONFIG_FILE = "model.safetensors", "config.json"
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}


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


def load_frames(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(images uint8 (N, H, W, C), labels float32 (N,), state float32 (N, D) or None)."""
    path = Path(path)
    if path.is_file() and path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            images, labels = np.asarray(data["images"], np.uint8), np.asarray(data["labels"], np.float32)
            state = np.asarray(data["state"], np.float32) if "state" in data else None
    elif path.is_dir():
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
        images, labels, state = np.stack(frames), np.asarray(labels_list, np.float32), None
    else:
        raise ValueError(f"{path} is neither a folder of success/ and failure/ frames nor an .npz")
    if images.ndim != 4 or len(images) != len(labels):
        raise ValueError(f"need images (N, H, W, C) and N labels, got {images.shape} and {labels.shape}")
    if not set(np.unique(labels).tolist()) <= {0.0, 1.0} or len(np.unique(labels)) < 2:
        raise ValueError("labels must be 0/1 and include both success and failure frames")
    return images, labels, state


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
    """Binary cross-entropy on randomly shifted frames, success rows reweighted to balance the classes."""
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
    for _ in range(epochs):
        shuffled = rng.permutation(train)
        for start in range(0, len(shuffled), batch_size):
            idx = shuffled[start : start + batch_size]
            logits = model(obs(idx, True))  # shifted frames: the DrQ augmentation the RL encoders see
            loss = nn.functional.binary_cross_entropy_with_logits(logits, y[idx], pos_weight=pos_weight)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

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


def run_cli(args: argparse.Namespace) -> int:
    try:
        images, labels, state = load_frames(args.frames)
    except (ValueError, OSError, KeyError) as exc:
        print(f"userctl reward train: {exc}", file=sys.stderr)
        return 2
    model = train_classifier(images, labels, state, args.camera, args.epochs, args.batch_size, args.lr, seed=args.seed)
    out = save_classifier(model, args.out)
    summary: dict[str, Any] = {"out": str(out), **model.config.metrics}
    print(json.dumps(summary))
    return 0
