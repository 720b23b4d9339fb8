"""CNN + state Gaussian policy (policy kind "cnn"): one small conv encoder per camera.

Each camera image (uint8 (B, H, W, C), or float 0..255 after augmentation) is first area-downsampled
to `image_size` x `image_size` when that is set (0: native size; a 128x128 camera at 64 costs about a
quarter of the conv work), then goes through its own conv stack -> linear -> LayerNorm -> tanh (the
DrQ / SERL encoder shape); the latents and the float state features (standardized with `state_mean` /
`state_std` when given) are concatenated and fed to the same squashed-Gaussian head as the MLP policy.
The algorithms share this encoder between actor and critics (critic gradients train it). Config JSON:

    {"image_keys": ["camera.front"], "image_shapes": [[128, 128, 3]], "image_size": 64,
     "channels": [16, 32, 32], "strides": [2, 2, 2], "latent_dim": 50, "state_keys": ["state"],
     "state_dims": [15], "state_mean": [...], "state_std": [...], "hidden": [256, 256],
     "action_low": [...], "action_high": [...]}

(`image_size`, `state_mean` and `state_std` are optional: specs published without them still load.)

`"backbone": "resnet18"` replaces the per-camera conv stacks with one torchvision ResNet-18 trunk (no
classifier; ImageNet-normalized input) shared by every camera, each camera keeping its own projection.
The learner can start it from a local pretrained file and freeze it (HIL-SERL's frozen pretrained
encoder); its weights travel in the weight set like every other tensor, so edges and the inference
service need no file. Nothing is downloaded: torchvision's hub weights are a file the user provides.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import nn

from user.policies.mlp import ActorPolicy, GaussianActor, StateEncoder
from user.policy import register_policy

KIND = "cnn"


def module_name(key: str) -> str:
    """Camera keys contain dots ("camera.front"); module names may not."""
    return key.replace(".", "_")


def downsample(image: torch.Tensor, size: int) -> torch.Tensor:
    """(B, H, W, C) pixels -> (B, size, size, C) float pixels, area-averaged (integer factors: mean pooling);
    unchanged (not even copied) when already that size or `size` is 0."""
    b, h, w, c = image.shape
    if size <= 0 or (h == size and w == size):
        return image
    if h % size == 0 and w % size == 0:  # mean over f x f blocks: a reshape, no strided pooling kernel
        return image.float().reshape(b, size, h // size, size, w // size, c).mean(dim=(2, 4))
    x = nn.functional.interpolate(image.float().permute(0, 3, 1, 2).contiguous(), size=(size, size), mode="area")
    return x.permute(0, 2, 3, 1)


class CameraEncoder(nn.Module):
    """(B, H, W, C) pixels in 0..255 -> (B, latent_dim) in [-1, 1]; `image_size` > 0 downsamples first."""

    def __init__(
        self,
        shape: Sequence[int],
        channels: Sequence[int],
        strides: Sequence[int],
        latent_dim: int,
        image_size: int = 0,
    ) -> None:
        super().__init__()
        height, width, in_channels = (int(s) for s in shape)
        if len(channels) != len(strides) or not channels:
            raise ValueError(f"channels {list(channels)} and strides {list(strides)} must be non-empty, same length")
        if image_size < 0:
            raise ValueError(f"image_size must be >= 0, got {image_size}")
        self.image_size = int(image_size)
        if self.image_size:
            height = width = self.image_size
        layers: list[nn.Module] = []
        for out_channels, stride in zip(channels, strides, strict=True):
            layers += [nn.Conv2d(in_channels, int(out_channels), 3, stride=int(stride)), nn.ReLU()]
            in_channels = int(out_channels)
        self.convs = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            flat = self.convs(torch.zeros(1, int(shape[2]), height, width)).shape[1]
        self.project = projection(flat, int(latent_dim))

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = downsample(image, self.image_size).float().permute(0, 3, 1, 2) / 255.0  # uint8 stays uint8 until here
        return self.project(self.convs(x - 0.5))


BACKBONES = ("conv", "resnet18")
_IMAGENET_MEAN, _IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


class ResNetTrunk(nn.Module):
    """torchvision's ResNet-18 without its classifier: (B, H, W, 3) pixels in 0..255 -> (B, 512).

    Frozen (freeze()), it never trains: no gradients, and its batch-norm layers stay in eval mode
    whatever mode the module around it is put in, so neither SGD nor batch statistics move it."""

    out_dim = 512

    def __init__(self) -> None:
        super().__init__()
        from torchvision.models import resnet18

        net = resnet18(weights=None)
        net.fc = nn.Identity()  # type: ignore[assignment]
        self.net = net
        self.frozen = False
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def freeze(self) -> ResNetTrunk:
        self.frozen = True
        self.requires_grad_(False)
        return self.train(self.training)

    def train(self, mode: bool = True) -> ResNetTrunk:
        super().train(mode and not self.frozen)
        self.training = mode  # what was asked: the batch-norm layers inside carry the frozen eval mode
        return self

    def load_pretrained(self, path: str) -> None:
        """Weights from a local safetensors file of torchvision's resnet18 state dict (its `fc.*` are ignored).
        ValueError naming what is missing or extra: a file of another architecture must not half-load."""
        from safetensors.torch import load_file

        state = {k: v for k, v in load_file(path).items() if not k.startswith("fc.")}
        try:
            missing, unexpected = self.net.load_state_dict(state, strict=False)
        except RuntimeError as exc:  # a tensor of the wrong shape
            raise ValueError(f"{path} is not a resnet18 state dict: {str(exc).splitlines()[-1].strip()}") from None
        if missing or unexpected:
            first = sorted(missing)[:5], sorted(unexpected)[:5]
            raise ValueError(f"{path} is not a resnet18 state dict: missing {first[0]}, unexpected {first[1]}")

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = (image.float().permute(0, 3, 1, 2) / 255.0 - self.mean) / self.std
        if self.frozen:
            with torch.no_grad():
                return self.net(x)
        return self.net(x)


def projection(in_dim: int, latent_dim: int) -> nn.Module:
    """Features -> latent in [-1, 1] (the DrQ / SERL encoder's last layers)."""
    return nn.Sequential(nn.Linear(in_dim, latent_dim), nn.LayerNorm(latent_dim), nn.Tanh())


class ConvEncoder(nn.Module):
    """Per-camera CNN latents, then the state features, concatenated."""

    def __init__(
        self,
        image_keys: Sequence[str],
        image_shapes: Sequence[Sequence[int]],
        state_keys: Sequence[str] = (),
        state_dims: Sequence[int] = (),
        channels: Sequence[int] = (16, 32, 32),
        strides: Sequence[int] = (2, 2, 2),
        latent_dim: int = 50,
        image_size: int = 0,
        state_mean: Sequence[float] | None = None,
        state_std: Sequence[float] | None = None,
        backbone: str = "conv",
    ) -> None:
        super().__init__()
        if not image_keys or len(image_keys) != len(image_shapes):
            raise ValueError(f"image_keys {list(image_keys)} and image_shapes must be non-empty, same length")
        if (state_mean is not None or state_std is not None) and not state_keys:
            raise ValueError("state_mean/state_std given but the encoder reads no state")
        if backbone not in BACKBONES:
            raise ValueError(f"backbone must be one of {BACKBONES}, got {backbone!r}")
        self.image_keys, self.image_size, self.backbone = list(image_keys), int(image_size), backbone
        # resnet18: one trunk for every camera (held once, so its weights travel once), a projection each
        self.trunk = ResNetTrunk() if backbone == "resnet18" else None
        if self.trunk is not None:
            bad = [list(s) for s in image_shapes if int(s[-1]) != 3]
            if bad:
                raise ValueError(f"backbone resnet18 reads RGB cameras; got shapes {bad}")
            encoders = {module_name(k): projection(ResNetTrunk.out_dim, int(latent_dim)) for k in image_keys}
        else:
            pairs = zip(image_keys, image_shapes, strict=True)
            encoders = {module_name(k): CameraEncoder(s, channels, strides, latent_dim, image_size) for k, s in pairs}
        self.cameras = nn.ModuleDict(encoders)
        self.state = StateEncoder(state_keys, state_dims, state_mean, state_std) if state_keys else None
        self.out_dim = int(latent_dim) * len(self.image_keys) + (self.state.out_dim if self.state else 0)

    def prepare(self, obs: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The images downsampled to what the convs read (others unchanged): done once per batch, before
        the DrQ shift, so augmentation and the convs run on the small frames."""
        return {k: downsample(v, self.image_size) if k in self.image_keys else v for k, v in obs.items()}

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        if self.trunk is None:
            parts = [self.cameras[module_name(k)](obs[k]) for k in self.image_keys]
        else:
            trunk = self.trunk
            parts = [self.cameras[module_name(k)](trunk(downsample(obs[k], self.image_size))) for k in self.image_keys]
        if self.state is not None:
            parts.append(self.state(obs))
        return torch.cat(parts, dim=-1)


def encoder_from_config(config: Mapping[str, Any]) -> ConvEncoder:
    return ConvEncoder(
        config["image_keys"],
        config["image_shapes"],
        config["state_keys"],
        config["state_dims"],
        config["channels"],
        config["strides"],
        int(config["latent_dim"]),
        int(config.get("image_size", 0)),
        config.get("state_mean"),
        config.get("state_std"),
        config.get("backbone", "conv"),
    )


def random_shift(
    image: torch.Tensor, pad: int, offsets: torch.Tensor | None = None, gather: bool | None = None
) -> torch.Tensor:
    """DrQ augmentation: replicate-pad (B, H, W, C) pixels by `pad` and crop back at a random offset per image.

    offsets: (B, 2) row/column offsets in 0..2*pad (default random). On the CPU one slice per image is cheaper
    than a gather over index tensors; on a GPU those B slices are B kernel launches and the offsets a host
    sync, so there (gather None and a CUDA image, or gather=True) two gathers crop every image at once."""
    b, h, w, _ = image.shape
    padded = nn.functional.pad(image.float().permute(0, 3, 1, 2), (pad, pad, pad, pad), mode="replicate")
    if offsets is None:
        offsets = torch.randint(0, 2 * pad + 1, (b, 2), device=image.device)
    if gather if gather is not None else image.is_cuda:
        c, wide = padded.shape[1], padded.shape[3]
        offsets = offsets.to(image.device)
        rows = offsets[:, :1] + torch.arange(h, device=image.device)  # (B, h)
        cols = offsets[:, 1:] + torch.arange(w, device=image.device)  # (B, w)
        picked = padded.gather(2, rows[:, None, :, None].expand(b, c, h, wide))
        return picked.gather(3, cols[:, None, None, :].expand(b, c, h, w)).permute(0, 2, 3, 1)
    crops = [padded[i, :, dy : dy + h, dx : dx + w] for i, (dy, dx) in enumerate(offsets.tolist())]
    return torch.stack(crops).permute(0, 2, 3, 1)


@register_policy(KIND)
class CnnPolicy(ActorPolicy):
    """Per-camera CNN encoders plus state, squashed Gaussian head."""

    kind = KIND
    required = (*ActorPolicy.required, "image_keys", "image_shapes", "channels", "strides", "latent_dim")

    @classmethod
    def build_actor(cls, config: Mapping[str, Any]) -> GaussianActor:
        return GaussianActor(encoder_from_config(config), config["hidden"], config["action_low"], config["action_high"])
