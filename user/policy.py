"""Policy networks shared by the learner, the inference service and edge agents.

A policy travels as a PolicySpec (kind + architecture JSON) plus named weight tensors, so any
process can rebuild it without unpickling anything. New kinds are one class in a module of
`user.policies` plus `@POLICIES.register("kind")` (found without an import list).
"""

from __future__ import annotations

import json
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn

from user.registry import PluginError, PluginParams, Registry
from user.v1 import learner_pb2

LOG_STD_MIN = -5.0
LOG_STD_MAX = 2.0
# The largest side of a camera frame a policy that resizes (image_shapes with None) accepts: resizing a 4000x4000
# frame costs ~0.8 s of the batch thread, a stall for every robot batched with it. 2048 takes any usual camera.
MAX_IMAGE_SIDE = 2048


class SquashedGaussianActor(nn.Module):
    """MLP -> (mean, log_std) of a Gaussian, squashed by tanh and rescaled to [low, high]."""

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        hidden: Sequence[int],
        action_low: Sequence[float] | np.ndarray,
        action_high: Sequence[float] | np.ndarray,
    ) -> None:
        super().__init__()
        low = torch.as_tensor(np.asarray(action_low, dtype=np.float32).reshape(-1))
        high = torch.as_tensor(np.asarray(action_high, dtype=np.float32).reshape(-1))
        if low.shape != (action_dim,) or high.shape != (action_dim,):
            raise ValueError(f"action bounds must have {action_dim} elements, got {low.numel()} and {high.numel()}")
        if not bool(torch.all(high > low)):
            raise ValueError("action_high must exceed action_low elementwise")
        self.obs_dim, self.action_dim = int(obs_dim), int(action_dim)
        layers: list[nn.Module] = []
        width = self.obs_dim
        for h in hidden:
            layers += [nn.Linear(width, int(h)), nn.ReLU()]
            width = int(h)
        layers.append(nn.Linear(width, 2 * self.action_dim))
        self.net = nn.Sequential(*layers)
        # Not persistent: the bounds travel in the PolicySpec, the tensors are only learned weights.
        self.register_buffer("action_scale", (high - low) / 2.0, persistent=False)
        self.register_buffer("action_bias", (high + low) / 2.0, persistent=False)

    def distribution(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        # Soft clamp keeps gradients alive at the bounds (a hard clamp would zero them).
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1.0)
        return mean, log_std

    def forward(
        self, obs: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sampled action, its log-prob (B,), deterministic action), all in [low, high].

        `mask` (B, action_dim) bool, for a layout padded across embodiments: only the true dims count
        in the log-prob (a padded dim is never executed, so its entropy is not the policy's)."""
        mean, log_std = self.distribution(obs)
        std = log_std.exp()
        pre = mean + std * torch.randn_like(mean)  # reparameterized sample
        squashed = torch.tanh(pre)
        # Change of variables for tanh and the affine rescale; 1e-6 guards log(0) at saturation.
        per_dim = (-0.5 * ((pre - mean) / std) ** 2 - log_std - 0.5 * np.log(2 * np.pi)) - torch.log(
            self.action_scale * (1 - squashed.pow(2)) + 1e-6
        )
        log_prob = (per_dim if mask is None else per_dim * mask).sum(-1)
        action = squashed * self.action_scale + self.action_bias
        mean_action = torch.tanh(mean) * self.action_scale + self.action_bias
        return action, log_prob, mean_action


class Policy(ABC):
    """A versioned, ready-to-run policy: batched observations in, batched actions out.

    A kind is one class in a module of `user.policies` plus `@POLICIES.register("kind")`. It is
    rebuilt anywhere from the wire as `cls(spec, tensors, version, device)` (see `from_wire`) and
    declares what it reads and returns, so inference and edges can check requests before a forward.
    `Params` types the architecture choices an experiment's `policy.params` may set (widths, encoder).
    """

    Params: type[PluginParams] = PluginParams

    version: int
    spec: learner_pb2.PolicySpec

    @classmethod
    def from_wire(
        cls, spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str
    ) -> Policy:
        """Build from PolicySpec + named tensors; any mismatch raises ValueError."""
        return cls(spec, tensors, version, device)  # type: ignore[call-arg]

    @property
    @abstractmethod
    def observation_keys(self) -> tuple[str, ...]:
        """The observation features `act` reads (others are ignored)."""

    @property
    @abstractmethod
    def action_shape(self) -> tuple[int, ...]:
        """Shape of one action (without batch or chunk dims)."""

    @property
    def chunk_horizon(self) -> int:
        """Actions per forward: 1 = a single action (B, *action_shape); H > 1 = a chunk (B, H, *action_shape)."""
        return 1

    @abstractmethod
    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        """observation values are (B, ...) arrays; returns (B, *action_shape) or (B, H, *action_shape) float32."""

    @property
    def image_shapes(self) -> Mapping[str, tuple[int | None, ...]]:
        """(H, W, C) of each camera feature the policy reads as uint8; None = any size there (it resizes)."""
        return {}

    @property
    def state_sizes(self) -> Mapping[str, int]:
        """Values in each float state feature the policy reads (one observation, flattened); {} = not declared."""
        return {}

    def check_observation(self, observation: Mapping[str, np.ndarray]) -> None:
        """ValueError unless one unbatched observation fits the forward. Inference runs it per request before
        batching, so a robot sending a frame or a state of the wrong shape gets INVALID_ARGUMENT instead of
        failing the forward of every robot batched with it."""
        for key, size in self.state_sizes.items():
            arr = observation.get(key)
            if arr is not None and arr.size != size:
                raise ValueError(f"observation {key!r} has {arr.size} values, the policy reads {size}")
        for key, want in self.image_shapes.items():
            arr = observation.get(key)
            if arr is None:
                continue  # missing keys are the caller's check (observation_keys)
            shape = tuple(arr.shape)
            fits = len(shape) == len(want) and all(w is None or w == g for w, g in zip(want, shape, strict=True))
            if arr.dtype != np.uint8 or not fits:
                expected = "x".join("*" if w is None else str(w) for w in want)
                raise ValueError(f"image {key!r} is {arr.dtype} {shape}, the policy reads uint8 {expected}")
            # A size the policy resizes from: at least 1x1 (0 fails the resize), at most MAX_IMAGE_SIDE a side.
            free = [g for w, g in zip(want, shape, strict=True) if w is None]
            if any(not 1 <= g <= MAX_IMAGE_SIDE for g in free):
                raise ValueError(f"image {key!r} is {shape}: each side must be 1 to {MAX_IMAGE_SIDE} pixels")


class SteppedRows(Protocol):
    """A batch in the middle of a stepped sampler (flow matching, diffusion), each row at its own step."""

    def __len__(self) -> int: ...

    def merged(self, other: Any) -> SteppedRows:
        """These rows followed by `other`'s (made by the same policy object)."""
        ...

    def done(self) -> np.ndarray:
        """Bool per row: its last step is taken."""
        ...

    def split(self, mask: np.ndarray) -> tuple[SteppedRows, SteppedRows]:
        """(the rows where mask, the others), each keeping its order."""
        ...


@runtime_checkable
class SteppedSampler(Protocol):
    """Optional for a Policy that samples in steps: its forward in parts, so the inference service can
    batch continuously (a request that arrives while a batch integrates joins it at the next step and
    leaves when its own steps are done, instead of waiting for the whole batch to finish first).
    `finish(advance^n(begin(p, d)))` must equal `forward(p, d)` row for row."""

    def begin(self, prepared: Any, deterministic: bool) -> SteppedRows:
        """Encode a preprocessed batch: rows at step 0."""
        ...

    def advance(self, rows: Any) -> SteppedRows:
        """One step for every row (rows that are done are never advanced)."""
        ...

    def finish(self, rows: Any) -> np.ndarray:
        """Rows that are done -> their actions, as forward returns them."""
        ...


POLICIES: Registry[Policy] = Registry("policy", Policy, "user.policies")


@dataclass(frozen=True)
class PolicyChoice:
    """An experiment's policy: a registered kind and its validated params (handed to the algorithm)."""

    kind: str
    params: PluginParams


def register_policy(kind: str, description: str | None = None) -> Callable[[type[Policy]], type[Policy]]:
    """`@register_policy("kind")` on a Policy subclass (same as `@POLICIES.register`)."""
    return POLICIES.register(kind, description)


def build_policy(
    spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str = "cpu"
) -> Policy:
    """Rebuild a policy from the wire on `device` (e.g. "cpu", "cuda:0"); any mismatch raises ValueError."""
    try:
        entry = POLICIES.get(spec.kind, "policy.kind")
    except PluginError as exc:
        raise ValueError(str(exc)) from None
    return entry.cls.from_wire(spec, tensors, version, device)


def check_sizes(observation: Mapping[str, np.ndarray], policy: Policy) -> None:
    """ValueError unless the keys the policy reads fit its forward: their total feature count where the policy
    declares one (obs_dim), then the policy's own per-key checks (state sizes, image shapes and dtype)."""
    obs_dim = getattr(policy, "obs_dim", None)
    if obs_dim is not None:
        got = sum(int(a.size) for a in observation.values())
        if got != int(obs_dim):
            shapes = {k: list(a.shape) for k, a in observation.items()}
            raise ValueError(f"observation has {got} features {shapes}, the policy expects {obs_dim}")
    policy.check_observation(observation)


def check_fit(policy: Policy, observation: Mapping[str, np.ndarray], action_dim: int, kind: str = "") -> None:
    """ValueError naming the mismatch unless `policy` can act for robots whose observations look like `observation`
    (placeholders in the robots' shapes and dtypes) and whose actions have `action_dim` values. `kind`: the robot
    kind, for a policy across embodiments (its `action_dims` cut the action per kind, as fit_action does).
    Checked before a policy is published or served, so a misfit fails loudly once instead of robots holding."""
    optional = set(getattr(policy, "optional_obs_keys", ()))
    keys = tuple(policy.observation_keys) or tuple(observation)
    missing = [k for k in keys if k not in observation and k not in optional]
    if missing:
        raise ValueError(f"the policy reads observation keys {missing}; the robots have {sorted(observation)}")
    shape = tuple(policy.action_shape)
    dims = getattr(policy, "action_dims", None) or {}
    served = min(math.prod(shape), int(dims[kind])) if kind in dims else math.prod(shape)
    if served != action_dim:
        raise ValueError(
            f"the policy's action has {served} values (action_shape {list(shape)}); the robots' has {action_dim}"
        )
    horizon = policy.chunk_horizon
    if not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"the policy's chunk_horizon is {horizon!r}; it must be a whole number >= 1")
    check_sizes({k: observation[k] for k in keys if k in observation}, policy)


def placeholders(features: Mapping[str, tuple[Sequence[int], str]]) -> dict[str, np.ndarray]:
    """name -> (shape, numpy dtype name) as zero-cost zero arrays, for check_fit (nothing is allocated)."""
    return {k: np.broadcast_to(np.zeros((), np.dtype(dtype)), tuple(shape)) for k, (shape, dtype) in features.items()}


def check_device(device: str) -> torch.device:
    """Parse a torch device name and make sure this machine has it (fail at start, not at the first request)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"bad device {device!r}: {exc}") from None
    if dev.type == "cuda" and (not torch.cuda.is_available() or (dev.index or 0) >= torch.cuda.device_count()):
        raise ValueError(f"device {device!r} requested but this machine has {torch.cuda.device_count()} CUDA devices")
    return dev


def known_policy_kinds() -> list[str]:
    return POLICIES.kinds()


# --- sac_mlp --------------------------------------------------------------------------------------

SAC_MLP = "sac_mlp"


def check_sac_mlp_config(config: Mapping[str, Any]) -> dict[str, Any]:
    required = ("obs_keys", "obs_dim", "action_dim", "hidden", "action_low", "action_high")
    missing = [k for k in required if k not in config]
    if missing:
        raise ValueError(f"sac_mlp config is missing {missing}")
    cfg = dict(config)
    if not cfg["obs_keys"] or not all(isinstance(k, str) for k in cfg["obs_keys"]):
        raise ValueError("sac_mlp config: obs_keys must be a non-empty list of names")
    if int(cfg["obs_dim"]) < 1 or int(cfg["action_dim"]) < 1:
        raise ValueError("sac_mlp config: obs_dim and action_dim must be >= 1")
    return cfg


def actor_from_config(config: Mapping[str, Any]) -> SquashedGaussianActor:
    cfg = check_sac_mlp_config(config)
    return SquashedGaussianActor(
        int(cfg["obs_dim"]), int(cfg["action_dim"]), list(cfg["hidden"]), cfg["action_low"], cfg["action_high"]
    )


def policy_spec_for(actor_config: Mapping[str, Any]) -> learner_pb2.PolicySpec:
    cfg = check_sac_mlp_config(actor_config)
    return learner_pb2.PolicySpec(kind=SAC_MLP, config_json=json.dumps(cfg, sort_keys=True))


def module_tensors(module: nn.Module) -> dict[str, np.ndarray]:
    """A module's weights as named numpy copies: what a weight set carries (the inverse of load_tensors)."""
    state = module.state_dict()
    if any(v.is_cuda for v in state.values()):
        return _from_gpu(state)
    return {k: v.detach().cpu().numpy().copy() for k, v in state.items()}


def _from_gpu(state: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Every tensor copied into pinned host memory without waiting, then one wait for all of them: `.cpu()` per
    tensor would wait for the GPU once per tensor from a pageable buffer."""
    host = {}
    for name, tensor in state.items():
        if tensor.is_cuda:
            buffer = torch.empty(tensor.shape, dtype=tensor.dtype, pin_memory=True)
            host[name] = buffer.copy_(tensor.detach(), non_blocking=True)
        else:
            host[name] = tensor.detach().clone()
    torch.cuda.synchronize()
    return {name: t.numpy() for name, t in host.items()}


def load_tensors(module: nn.Module, tensors: Mapping[str, np.ndarray]) -> None:
    expected = module.state_dict()
    if set(tensors) != set(expected):
        missing, extra = sorted(set(expected) - set(tensors)), sorted(set(tensors) - set(expected))
        raise ValueError(f"weight tensors do not match the architecture: missing {missing}, unexpected {extra}")
    state = {}
    for name, ref in expected.items():
        arr = np.asarray(tensors[name])
        if tuple(arr.shape) != tuple(ref.shape):
            raise ValueError(f"tensor {name!r} has shape {tuple(arr.shape)}, expected {tuple(ref.shape)}")
        state[name] = torch.from_numpy(np.array(arr, dtype=np.float32, copy=True))
    module.load_state_dict(state, strict=True)
