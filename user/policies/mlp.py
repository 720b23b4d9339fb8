"""MLP Gaussian policy over state features (policy kind "mlp"), and the parts the CNN policy reuses.

An actor is `GaussianActor(encoder, head)`: the encoder turns an observation dict into one feature
vector (here: the float features concatenated in sorted key order; in `cnn.py`: per-camera CNNs plus
state), the head is `user.policy.SquashedGaussianActor` over those features. SAC, RLPD and BC train
the same module and publish it unchanged, so the learner, the inference service and the edges run
identical code. Config JSON of kind "mlp":

    {"state_keys": ["state"], "state_dims": [15], "hidden": [256, 256],
     "action_low": [...], "action_high": [...]}

A policy shared by several embodiments (user/policies/padded.py) has `action_low`/`action_high` as one
list per embodiment, in the layout's embodiment order: each row's squashed Gaussian spans its own robot's
range (not the union of all robots'), picked by the observation's one-hot `embodiment` feature.

Tensors are `GaussianActor.state_dict()` (names "head.net.0.weight", ...).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from user.experiments import EMBODIMENT_KEY
from user.policy import Policy, SquashedGaussianActor, check_device, load_tensors, register_policy
from user.v1 import learner_pb2

KIND = "mlp"


def mlp(in_dim: int, hidden: Sequence[int], out_dim: int, layer_norm: bool = False) -> nn.Sequential:
    """Linear -> (LayerNorm) -> ReLU per hidden width, then a linear output layer."""
    layers: list[nn.Module] = []
    width = int(in_dim)
    for h in hidden:
        layers += [nn.Linear(width, int(h)), *([nn.LayerNorm(int(h))] if layer_norm else []), nn.ReLU()]
        width = int(h)
    layers.append(nn.Linear(width, int(out_dim)))
    return nn.Sequential(*layers)


class StateEncoder(nn.Module):
    """Concatenate the float features `keys` (each flattened after the batch dim); no weights.

    `mean`/`std` (one float per concatenated value, fixed, part of the published config) standardize
    the state: raw robot state mixes metres, radians and velocities, and a few-cm cube-to-gripper
    offset drowns in it unscaled."""

    def __init__(
        self,
        keys: Sequence[str],
        dims: Sequence[int],
        mean: Sequence[float] | None = None,
        std: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        if len(keys) != len(dims):
            raise ValueError(f"state_keys {list(keys)} and state_dims {list(dims)} differ in length")
        self.keys, self.dims = list(keys), [int(d) for d in dims]
        self.out_dim = sum(self.dims)
        self.mean = None if mean is None else [float(x) for x in mean]
        self.std = None if std is None else [float(x) for x in std]
        for name, values in (("state_mean", self.mean), ("state_std", self.std)):
            if values is not None and len(values) != self.out_dim:
                raise ValueError(f"{name} has {len(values)} values, the state has {self.out_dim}")
        if self.std is not None and min(self.std) <= 0:
            raise ValueError("state_std must be > 0")
        # Plain attributes, not buffers: the published tensors stay the weights alone.
        self._shift = torch.tensor(self.mean or [0.0] * self.out_dim)
        self._scale = 1.0 / torch.tensor(self.std or [1.0] * self.out_dim)

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        parts = [obs[k].reshape(obs[k].shape[0], -1).float() for k in self.keys]
        if not parts:
            raise ValueError("StateEncoder has no state keys")
        x = torch.cat(parts, dim=-1)
        if self.mean is None and self.std is None:
            return x
        return (x - self._shift.to(x.device)) * self._scale.to(x.device)


class EmbodiedSquashedGaussian(SquashedGaussianActor):
    """A SquashedGaussianActor whose [low, high] is per row: bounds (E, A), row e the range of embodiment e of a
    shared layout, so each robot's samples, log-probs and entropy are over its own range, not the union's."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int], low: np.ndarray, high: np.ndarray) -> None:
        if low.ndim != 2 or high.shape != low.shape or low.shape[1] != action_dim or not low.shape[0]:
            raise ValueError(
                f"per-embodiment action bounds must be (embodiments, {action_dim}); got {low.shape} and {high.shape}"
            )
        super().__init__(obs_dim, action_dim, hidden, low[0], high[0])  # the network, and row 0 checked
        if not bool(np.all(high > low)):
            raise ValueError("action_high must exceed action_low elementwise (every embodiment's row)")
        self.action_scale = torch.as_tensor((high - low) / 2.0)  # replaces the buffers, still not persistent
        self.action_bias = torch.as_tensor((high + low) / 2.0)

    @property
    def embodiments(self) -> int:
        return int(self.action_scale.shape[0])

    def rows(self, embodiment: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, A) scale and bias of each row's embodiment (indices (B,) into the bound rows)."""
        if embodiment is None:
            raise ValueError(f"per-embodiment action bounds need each row's {EMBODIMENT_KEY!r} index; none given")
        index = embodiment.to(self.action_scale.device, torch.long).reshape(-1)
        return self.action_scale[index], self.action_bias[index]

    def forward(
        self, obs: torch.Tensor, mask: torch.Tensor | None = None, embodiment: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SquashedGaussianActor.forward with each row's own scale and bias (its embodiment's range)."""
        scale, bias = self.rows(embodiment)
        mean, log_std = self.distribution(obs)
        std = log_std.exp()
        pre = mean + std * torch.randn_like(mean)
        squashed = torch.tanh(pre)
        per_dim = (-0.5 * ((pre - mean) / std) ** 2 - log_std - 0.5 * np.log(2 * np.pi)) - torch.log(
            scale * (1 - squashed.pow(2)) + 1e-6
        )
        log_prob = (per_dim if mask is None else per_dim * mask).sum(-1)
        return squashed * scale + bias, log_prob, torch.tanh(mean) * scale + bias


def scale_bias(
    head: SquashedGaussianActor, embodiment: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The head's affine map from [-1, 1] to actions: per row for per-embodiment bounds, else its (A,) buffers."""
    if isinstance(head, EmbodiedSquashedGaussian):
        return head.rows(embodiment)
    return head.action_scale, head.action_bias


def embodiment_of(obs: Mapping[str, torch.Tensor]) -> torch.Tensor | None:
    """Each row's embodiment index from the observation's `embodiment` feature (one-hot (B, E), or indices (B,))."""
    value = obs.get(EMBODIMENT_KEY)
    if value is None:
        return None
    return value.argmax(dim=-1) if value.ndim > 1 else value.long()


class GaussianActor(nn.Module):
    """encoder(obs) -> squashed Gaussian over actions. `detach_encoder` stops actor gradients reaching
    a shared encoder (DrQ / SERL: only the critic trains the image encoder). Bounds of shape (E, A) (a
    layout shared by E embodiments) give each row its embodiment's range (EmbodiedSquashedGaussian)."""

    def __init__(self, encoder: nn.Module, hidden: Sequence[int], action_low: Any, action_high: Any) -> None:
        super().__init__()
        low = np.asarray(action_low, dtype=np.float32)
        self.encoder = encoder
        if low.ndim == 2:
            high = np.asarray(action_high, dtype=np.float32)
            self.head = EmbodiedSquashedGaussian(encoder.out_dim, low.shape[1], list(hidden), low, high)
        else:
            low = low.reshape(-1)
            self.head = SquashedGaussianActor(encoder.out_dim, low.size, list(hidden), low, action_high)

    @property
    def per_embodiment(self) -> bool:
        return isinstance(self.head, EmbodiedSquashedGaussian)

    def forward(
        self, obs: Mapping[str, torch.Tensor], detach_encoder: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        features = self.encoder(obs)
        features = features.detach() if detach_encoder else features
        return self.sample(features, embodiment=embodiment_of(obs) if self.per_embodiment else None)

    def sample(
        self, features: torch.Tensor, mask: torch.Tensor | None = None, embodiment: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The head on encoded features: (action, log-prob, mean action). `embodiment` (B,) picks each row's
        range when the bounds are per embodiment; one range for all rows otherwise (then it is not read)."""
        if isinstance(self.head, EmbodiedSquashedGaussian):
            return self.head(features, mask, embodiment)
        return self.head(features, mask)


def log_prob_of(
    head: SquashedGaussianActor,
    features: torch.Tensor,
    action: torch.Tensor,
    embodiment: torch.Tensor | None = None,
) -> torch.Tensor:
    """log pi(action | features) under the squashed Gaussian (BC's NLL loss); actions at the bounds are
    pulled in by 1e-4 of the half-range so atanh stays finite. `embodiment`: per-embodiment bounds' rows."""
    scale, bias = scale_bias(head, embodiment)
    mean, log_std = head.distribution(features)
    squashed = ((action - bias) / scale).clamp(-1 + 1e-4, 1 - 1e-4)
    pre = torch.atanh(squashed)
    normal_logp = (-0.5 * ((pre - mean) / log_std.exp()) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
    return normal_logp - torch.log(scale * (1 - squashed.pow(2)) + 1e-6).sum(-1)


# --- the published policy ---------------------------------------------------------------------------


def parse_config(spec: learner_pb2.PolicySpec, required: Sequence[str]) -> dict[str, Any]:
    try:
        config = json.loads(spec.config_json)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{spec.kind} config_json is not JSON: {exc}") from None
    if not isinstance(config, dict):
        raise ValueError(f"{spec.kind} config_json must be an object")
    missing = [k for k in required if k not in config]
    if missing:
        raise ValueError(f"{spec.kind} config is missing {missing}")
    return config


def batch_tensors(observation: Mapping[str, np.ndarray], keys: Sequence[str], device: torch.device) -> dict:
    """The needed keys as tensors with one shared leading batch dimension; uint8 images stay uint8."""
    missing = [k for k in keys if k not in observation]
    if missing:
        raise ValueError(f"observation lacks {missing}")
    arrays = {k: np.asarray(observation[k]) for k in keys}
    sizes = {a.shape[0] if a.ndim else 0 for a in arrays.values()}
    if len(sizes) != 1 or 0 in sizes:
        raise ValueError("observation values need the same leading batch dimension")
    out = {}
    for k, a in arrays.items():
        a = a if a.dtype == np.uint8 else a.astype(np.float32, copy=False)
        out[k] = torch.from_numpy(np.ascontiguousarray(a)).to(device)
    return out


class ActorPolicy(Policy):
    """A published GaussianActor: subclasses say how to rebuild the encoder from the config."""

    kind = ""
    required: tuple[str, ...] = ("state_keys", "state_dims", "hidden", "action_low", "action_high")

    def __init__(
        self, spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str = "cpu"
    ) -> None:
        self.spec, self.version = spec, int(version)
        self.config = parse_config(spec, self.required)
        self.actor = self.build_actor(self.config)
        load_tensors(self.actor, tensors)
        self.device = check_device(device)
        self.actor.to(self.device).eval()

    @classmethod
    def build_actor(cls, config: Mapping[str, Any]) -> GaussianActor:
        raise NotImplementedError

    @property
    def embodiment_rows(self) -> int:
        """Rows of per-embodiment action bounds (the embodiments the policy spans); 0: one range for every robot."""
        head = self.actor.head
        return head.embodiments if isinstance(head, EmbodiedSquashedGaussian) else 0

    @property
    def observation_keys(self) -> tuple[str, ...]:
        keys = (*sorted(self.config["state_keys"]), *sorted(self.config.get("image_keys", [])))
        # Per-embodiment bounds read the embodiment even where the networks do not (features left it out).
        return (*keys, EMBODIMENT_KEY) if self.embodiment_rows and EMBODIMENT_KEY not in keys else keys

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (int(np.shape(self.config["action_low"])[-1]),)

    @property
    def chunk_horizon(self) -> int:
        return 1

    @property
    def state_sizes(self) -> dict[str, int]:
        return {key: int(dim) for key, dim in zip(self.config["state_keys"], self.config["state_dims"], strict=True)}

    @property
    def image_shapes(self) -> dict[str, tuple[int | None, ...]]:
        pairs = zip(self.config.get("image_keys", []), self.config.get("image_shapes", []), strict=True)
        return {key: tuple(int(d) for d in shape) for key, shape in pairs}

    def _check_shapes(self, obs: Mapping[str, torch.Tensor]) -> None:
        for key, dim in zip(self.config["state_keys"], self.config["state_dims"], strict=True):
            if obs[key][0].numel() != int(dim):
                raise ValueError(f"observation {key!r} has {obs[key][0].numel()} values, the policy expects {dim}")
        for key, shape in zip(self.config.get("image_keys", []), self.config.get("image_shapes", []), strict=True):
            if tuple(obs[key].shape[1:]) != tuple(shape):
                raise ValueError(f"image {key!r} has shape {tuple(obs[key].shape[1:])}, the policy expects {shape}")
        rows = self.embodiment_rows
        if rows and tuple(obs[EMBODIMENT_KEY].shape[1:]) != (rows,):
            got = tuple(obs[EMBODIMENT_KEY].shape[1:])
            raise ValueError(f"observation {EMBODIMENT_KEY!r} is {got} per row; the policy needs a one-hot of {rows}")

    @torch.no_grad()
    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        obs = batch_tensors(observation, self.observation_keys, self.device)
        self._check_shapes(obs)
        action, _, mean_action = self.actor(obs)
        return (mean_action if deterministic else action).cpu().numpy().astype(np.float32, copy=False)


@register_policy(KIND)
class MlpPolicy(ActorPolicy):
    """MLP Gaussian actor over the concatenated float features."""

    kind = KIND

    @classmethod
    def build_actor(cls, config: Mapping[str, Any]) -> GaussianActor:
        encoder = StateEncoder(
            config["state_keys"], config["state_dims"], config.get("state_mean"), config.get("state_std")
        )
        return GaussianActor(encoder, config["hidden"], config["action_low"], config["action_high"])


def policy_spec(kind: str, config: Mapping[str, Any]) -> learner_pb2.PolicySpec:
    return learner_pb2.PolicySpec(kind=kind, config_json=json.dumps(dict(config), sort_keys=True))
