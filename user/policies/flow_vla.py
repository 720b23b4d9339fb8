"""flow_vla: a small vision-language-action policy that produces action chunks by flow matching.

    cameras (uint8 HxWx3)  --per-camera CNN-->  \
    instruction (words)    --hashed embedding--> +-> context --> action expert v(x_t, t, context)
    state (floats)         --linear-->          /                 x_0 ~ N(0, I) --Euler steps--> chunk

Trained with the flow-matching loss (cloud_learner/algorithms/flow_bc.py): for a demonstrated chunk
a (normalised to [-1, 1]), noise e and t ~ U(0, 1), regress v(t*a + (1-t)*e, t) onto a - e.
Acting integrates dx/dt = v from noise (zeros when deterministic) in `flow_steps` Euler steps.

Small enough to train on two CPU cores (~0.2 M parameters at 64x64). The instruction comes from
the request (ActRequest.instruction), else from the observation's `instruction` feature (UTF-8
bytes, see user/text.py), else from the config's default (e.g. the robot's RobotSpec.task).
Weights travel as named raw tensors like every policy; the spec's JSON holds the architecture.
A policy shared by several embodiments has `action_low`/`action_high` as one list per embodiment (the
layout's order): each row's [-1, 1] maps onto its own robot's range, picked by the one-hot `embodiment`
feature, in training (flow_bc's targets) and in acting alike.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from torch import nn

from user.experiments import EMBODIMENT_KEY
from user.policy import Policy, check_device, load_tensors, module_tensors, register_policy
from user.text import INSTRUCTION_KEY, decode_instruction, word_ids
from user.v1 import learner_pb2

KIND = "flow_vla"


class FlowVlaConfig(BaseModel):
    """Architecture: what the PolicySpec's config_json holds."""

    model_config = ConfigDict(extra="forbid")

    image_keys: list[str] = Field(default_factory=list, description="camera features, uint8 (H, W, 3)")
    state_keys: list[str] = Field(default_factory=list, description="float features, flattened and concatenated")
    state_dim: int = Field(0, ge=0)
    instruction_key: str | None = Field(INSTRUCTION_KEY, description="uint8 observation feature with the instruction")
    default_instruction: str = ""
    action_dim: int = Field(ge=1)
    # One range for every robot, or one row per embodiment of a shared layout (each robot's own range).
    action_low: list[float] | list[list[float]]
    action_high: list[float] | list[list[float]]
    horizon: int = Field(8, ge=1, description="actions per chunk")
    image_size: int = Field(64, ge=16, description="images are resized to this square size")
    vocab_size: int = Field(1024, ge=2)
    max_words: int = Field(16, ge=1)
    embed_dim: int = Field(32, ge=1)
    hidden: int = Field(128, ge=8)
    flow_steps: int = Field(5, ge=1, description="Euler steps from noise to a chunk")
    # State normalization (e.g. the learner's statistics of the demos): (state - mean) / std before the network.
    # Absent in specs published before it existed: those load and see the raw state.
    state_mean: list[float] | None = Field(None, description="one value per flattened state feature")
    state_std: list[float] | None = Field(None, description="one value > 0 per flattened state feature")

    @model_validator(mode="after")
    def _stats_fit(self) -> FlowVlaConfig:
        for name, values in (("state_mean", self.state_mean), ("state_std", self.state_std)):
            if values is not None and len(values) != self.state_dim:
                raise ValueError(f"{name} has {len(values)} values, state_dim is {self.state_dim}")
        if self.state_std is not None and min(self.state_std, default=1.0) <= 0:
            raise ValueError("state_std must be > 0")
        return self

    @property
    def embodiment_rows(self) -> int:
        """Rows of per-embodiment action bounds; 0: one range for every robot."""
        return len(self.action_low) if self.action_low and isinstance(self.action_low[0], list) else 0

    def observation_keys(self) -> list[str]:
        keys = [*self.image_keys, *self.state_keys]
        if self.embodiment_rows and EMBODIMENT_KEY not in keys:  # the bounds' rows are picked by it
            keys.append(EMBODIMENT_KEY)
        return [*keys, self.instruction_key] if self.instruction_key else keys


def policy_spec(config: FlowVlaConfig) -> learner_pb2.PolicySpec:
    return learner_pb2.PolicySpec(kind=KIND, config_json=config.model_dump_json())


def _camera_encoder(out_dim: int) -> nn.Sequential:
    # 64 -> 31 -> 14 -> 6 spatial; a flattened small map keeps where things are (targets' positions).
    return nn.Sequential(
        nn.Conv2d(3, 16, 4, stride=2),
        nn.SiLU(),
        nn.Conv2d(16, 32, 4, stride=2),
        nn.SiLU(),
        nn.Conv2d(32, 16, 3, stride=2),
        nn.SiLU(),
        nn.AdaptiveAvgPool2d(4),
        nn.Flatten(),
        nn.Linear(16 * 4 * 4, out_dim),
        nn.SiLU(),
    )


def _time_embedding(t: torch.Tensor, dim: int = 32) -> torch.Tensor:
    """Sinusoidal features of the flow time t in [0, 1], (B,) -> (B, dim)."""
    freqs = torch.exp(torch.linspace(0.0, math.log(1000.0), dim // 2, device=t.device))
    angles = t[:, None] * freqs[None] * math.pi
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class FlowVla(nn.Module):
    def __init__(self, cfg: FlowVlaConfig) -> None:
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden
        self.cameras = nn.ModuleList(_camera_encoder(h // 2) for _ in cfg.image_keys)
        self.words = nn.Embedding(cfg.vocab_size, cfg.embed_dim, padding_idx=0)
        self.language = nn.Sequential(nn.Linear(cfg.embed_dim, h // 2), nn.SiLU())
        self.state = nn.Sequential(nn.Linear(cfg.state_dim, h // 2), nn.SiLU()) if cfg.state_dim else None
        # FiLM: the instruction scales and shifts the state and image features, so "which target" can
        # select features multiplicatively instead of the MLP having to learn that gating from sums.
        self.film = nn.Linear(h // 2, 2 * (h // 2))
        parts = len(cfg.image_keys) + 1 + (1 if cfg.state_dim else 0)
        self.context = nn.Sequential(nn.Linear(parts * (h // 2), h), nn.SiLU(), nn.Linear(h, h))
        chunk = cfg.horizon * cfg.action_dim
        self.expert = nn.Sequential(
            nn.Linear(chunk + 32 + h, h), nn.SiLU(), nn.Linear(h, h), nn.SiLU(), nn.Linear(h, chunk)
        )
        # The expert after its first layer, as a plain tuple (not registered: no second set of weights).
        self._rest = tuple(self.expert)[1:]

    def encode(self, images: list[torch.Tensor], state: torch.Tensor | None, tokens: torch.Tensor) -> torch.Tensor:
        """images: float (B, 3, S, S) each; state (B, state_dim); tokens (B, max_words) -> context (B, hidden)."""
        mask = (tokens > 0).float()
        words = (self.words(tokens) * mask[..., None]).sum(1) / mask.sum(1, keepdim=True).clamp(min=1.0)
        language = self.language(words)
        feats = [enc(img) for enc, img in zip(self.cameras, images, strict=True)]
        if self.state is not None and state is not None:
            feats.append(self.state(state))
        gamma, beta = self.film(language).chunk(2, dim=-1)
        feats = [f * (1 + gamma) + beta for f in feats]
        return self.context(torch.cat([*feats, language], dim=-1))

    def velocity(self, x: torch.Tensor, t: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """x: (B, horizon, A) noisy chunk at flow time t (B,) -> predicted velocity, same shape."""
        inp = torch.cat([x.flatten(1), _time_embedding(t), context], dim=-1)
        return self.expert(inp).view_as(x)

    def flow_loss(
        self,
        context: torch.Tensor,
        chunk: torch.Tensor,
        weight: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        action_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Flow-matching loss for normalised target chunks (B, horizon, A) in [-1, 1].

        weight (B,): per-row weights; mask (B, horizon) bool: the chunk's real actions (padding past an
        episode's end does not count; the row's loss is the mean over its real ones); action_mask (B, A) bool:
        the real action dims of a layout padded across embodiments: a padded dim's stored filler is neither label
        nor input, its target is 0 (trained too: at sampling it then flows to 0 and feeds the real dims what
        training fed them, instead of drifting untrained)."""
        dims = None if action_mask is None else action_mask.to(chunk.device, chunk.dtype)[:, None, :]
        if dims is not None:
            chunk = chunk * dims
        noise = torch.randn_like(chunk)
        t = torch.rand(chunk.shape[0], device=chunk.device)
        x_t = t[:, None, None] * chunk + (1 - t[:, None, None]) * noise
        sq = (self.velocity(x_t, t, context) - (chunk - noise)).pow(2)  # (B, horizon, A)
        err = sq.mean(dim=2)
        if mask is None:
            err = err.mean(dim=1)
        else:
            m = mask.to(err.dtype)
            err = (err * m).sum(dim=1) / m.sum(dim=1).clamp(min=1.0)
        return (err * weight).sum() / weight.sum().clamp(min=1e-6) if weight is not None else err.mean()

    def sample(self, context: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """Integrate from noise (zeros when deterministic) to a normalised chunk (B, horizon, A)."""
        rows = self.start(context, deterministic)
        for _ in range(self.cfg.flow_steps):
            rows = self.advance(rows)
        return rows.x.clamp(-1.0, 1.0)

    def start(self, context: torch.Tensor, deterministic: bool) -> FlowRows:
        """Rows at flow time 0, ready for `advance`; `sample` is start + flow_steps advances.

        The expert's first layer is split by its inputs (chunk | time | context): the context's share
        is computed here, once per row instead of once per flow step (at the VLA size it is ~46 % of
        the expert's weights, which a batch-1 forward is bound by reading), and the time's share for
        every step in one product."""
        shape = (context.shape[0], self.cfg.horizon, self.cfg.action_dim)
        x = torch.zeros(shape, device=context.device) if deterministic else torch.randn(shape, device=context.device)
        first = self.expert[0]
        w_chunk, w_time, w_context = first.weight.split([x[0].numel(), 32, context.shape[1]], dim=1)
        times = torch.arange(self.cfg.flow_steps, device=context.device) * (1.0 / self.cfg.flow_steps)
        shared = FlowShared(_time_embedding(times) @ w_time.T, w_chunk.T, self._rest)
        step = torch.zeros(shape[0], dtype=torch.long, device=context.device)
        base = nn.functional.linear(context, w_context, first.bias)
        return FlowRows(x, base, step, np.zeros(shape[0], np.int64), shared, at=0)

    def advance(self, rows: FlowRows) -> FlowRows:
        """One Euler step for every row, each at its own flow time (rows may have joined at different steps)."""
        shared = rows.shared
        # Rows all at one step (a plain sample) add that step's time share by broadcast, not by a gather.
        from_time = shared.from_time[rows.step] if rows.at is None else shared.from_time[rows.at]
        hidden = torch.addmm(rows.base + from_time, rows.x.flatten(1), shared.w_chunk_t)
        for layer in shared.rest:
            hidden = layer(hidden)
        x = rows.x + shared.dt * hidden.view_as(rows.x)
        at = None if rows.at is None else rows.at + 1
        return FlowRows(x, rows.base, rows.step + 1, rows.taken + 1, shared, at, rows.embodiment)


class FlowShared:
    """What every row integrated with one set of weights shares."""

    def __init__(self, from_time: torch.Tensor, w_chunk_t: torch.Tensor, rest: tuple[nn.Module, ...]) -> None:
        self.from_time = from_time  # (flow_steps, hidden): each step's time share of the expert's first layer
        self.w_chunk_t = w_chunk_t  # the chunk's share of that layer, transposed for addmm
        self.rest = rest  # the expert after its first layer
        self.steps = int(from_time.shape[0])
        self.dt = 1.0 / self.steps


class FlowRows:
    """Chunks in the middle of their flow integration, each row at its own step.

    What continuous batching in the inference service holds between steps: rows that arrive while
    a batch integrates join it at the next step (`merged`) instead of waiting for the whole batch,
    and leave when their last step is done (`split`)."""

    def __init__(
        self,
        x: torch.Tensor,
        base: torch.Tensor,
        step: torch.Tensor,
        taken: np.ndarray,
        shared: FlowShared,
        at: int | None = None,
        embodiment: torch.Tensor | None = None,
    ) -> None:
        self.x = x  # (B, horizon, A): the noisy chunks
        self.base = base  # (B, hidden): the context's share of the expert's first layer, with its bias
        self.step = step  # (B,): steps taken, on the device (indexes from_time there)
        self.taken = taken  # (B,): steps taken, on the host (done() needs no device sync)
        self.shared = shared
        self.at = at  # the step every row is at, when they all are at one (no gather needed)
        self.embodiment = embodiment  # (B,) each row's embodiment index (per-embodiment action bounds), or None

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def merged(self, other: FlowRows) -> FlowRows:
        """These rows then `other`'s (both from the same weights)."""
        cat = torch.cat
        at = self.at if self.at == other.at else None
        x, base, step = cat([self.x, other.x]), cat([self.base, other.base]), cat([self.step, other.step])
        ids = None if self.embodiment is None or other.embodiment is None else cat([self.embodiment, other.embodiment])
        return FlowRows(x, base, step, np.concatenate([self.taken, other.taken]), self.shared, at, ids)

    def done(self) -> np.ndarray:
        return self.taken >= self.shared.steps

    def split(self, mask: np.ndarray) -> tuple[FlowRows, FlowRows]:
        """(the rows where mask, the others), each in order."""
        if mask.all():  # a batch that began together ends together: no copies
            return self, self._rows(slice(0, 0))
        take = torch.as_tensor(mask, device=self.x.device)
        return self._rows(take, mask), self._rows(~take, ~mask)

    def _rows(self, index: torch.Tensor | slice, host: np.ndarray | slice | None = None) -> FlowRows:
        host = index if host is None else host
        ids = None if self.embodiment is None else self.embodiment[index]
        x, base, step = self.x[index], self.base[index], self.step[index]
        return FlowRows(x, base, step, self.taken[host], self.shared, self.at, ids)


class Prepared:
    """What preprocess hands to forward: device tensors for one batch."""

    def __init__(
        self,
        images: list[torch.Tensor],
        state: torch.Tensor | None,
        tokens: torch.Tensor,
        embodiment: torch.Tensor | None = None,
    ) -> None:
        self.images, self.state, self.tokens = images, state, tokens
        self.embodiment = embodiment  # (B,) indices into per-embodiment action bounds; None with one range

    def __len__(self) -> int:
        return int(self.tokens.shape[0])


class Preprocessor:
    """Numpy batch + instructions -> device tensors: resize/normalise images, tokenize, one copy per key.

    Used by the policy (inference, edge) and by the learner (training), so both see the same inputs.
    """

    def __init__(self, cfg: FlowVlaConfig, device: torch.device) -> None:
        self.cfg, self.device = cfg, device
        self.pinned = device.type == "cuda"  # page-locked host buffers make the copy asynchronous
        dim = cfg.state_dim
        self.shift = None if cfg.state_mean is None and cfg.state_std is None else np.zeros(dim, np.float32)
        self.scale = None if self.shift is None else np.ones(dim, np.float32)
        if cfg.state_mean is not None:
            self.shift = np.asarray(cfg.state_mean, np.float32)
        if cfg.state_std is not None:
            self.scale = 1.0 / np.asarray(cfg.state_std, np.float32)

    def _to_device(self, array: np.ndarray) -> torch.Tensor:
        tensor = torch.from_numpy(np.ascontiguousarray(array))
        if self.pinned:
            return tensor.pin_memory().to(self.device, non_blocking=True)
        return tensor.to(self.device)

    def images(self, batch: torch.Tensor) -> torch.Tensor:
        """uint8 (B, H, W, 3) on the device -> float (B, 3, S, S) in [-1, 1]."""
        x = batch.permute(0, 3, 1, 2).float().div_(127.5).sub_(1.0)
        size = self.cfg.image_size
        if x.shape[-2:] != (size, size):
            x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
        return x

    def tokens(self, texts: Sequence[str]) -> np.ndarray:
        return np.stack([word_ids(t, self.cfg.vocab_size, self.cfg.max_words) for t in texts])

    def instructions(self, observation: Mapping[str, Any], given: Sequence[str] | None, batch: int) -> list[str]:
        """Per row: the given instruction, else the observation's, else the default."""
        key = self.cfg.instruction_key
        from_obs = observation.get(key) if key else None
        texts = []
        for i in range(batch):
            text = given[i] if given is not None and i < len(given) else ""
            if not text and from_obs is not None:
                text = decode_instruction(np.asarray(from_obs[i]))
            texts.append(text or self.cfg.default_instruction)
        return texts

    def __call__(self, observation: Mapping[str, Any], instructions: Sequence[str] | None = None) -> Prepared:
        missing = [k for k in [*self.cfg.image_keys, *self.cfg.state_keys] if k not in observation]
        if missing:
            raise ValueError(f"observation lacks {missing}")
        batch = len(next(iter(observation.values())))
        images = [self.images(self._to_device(np.asarray(observation[k], dtype=np.uint8))) for k in self.cfg.image_keys]
        state = None
        if self.cfg.state_keys:
            parts = [np.asarray(observation[k], dtype=np.float32).reshape(batch, -1) for k in self.cfg.state_keys]
            flat = np.concatenate(parts, axis=1)
            if flat.shape[1] != self.cfg.state_dim:
                raise ValueError(f"state has {flat.shape[1]} features, the policy expects {self.cfg.state_dim}")
            if self.shift is not None:  # the statistics shipped in the spec: learner and actors normalize alike
                flat = (flat - self.shift) * self.scale
            state = self._to_device(flat)
        tokens = self._to_device(self.tokens(self.instructions(observation, instructions, batch)))
        return Prepared(images, state, tokens, self.embodiment(observation, batch))

    def embodiment(self, observation: Mapping[str, Any], batch: int) -> torch.Tensor | None:
        """Each row's embodiment index from the one-hot feature, when the action bounds are per embodiment."""
        rows = self.cfg.embodiment_rows
        if not rows:
            return None
        if EMBODIMENT_KEY not in observation:
            raise ValueError(f"observation lacks {EMBODIMENT_KEY!r}: the policy's action range is per embodiment")
        onehot = np.asarray(observation[EMBODIMENT_KEY], np.float32).reshape(batch, -1)
        if onehot.shape[1] != rows:
            raise ValueError(f"observation {EMBODIMENT_KEY!r} has {onehot.shape[1]} values per row, the policy {rows}")
        return self._to_device(onehot.argmax(axis=1).astype(np.int64))


class ActionScaler:
    """[low, high] <-> [-1, 1] per action dim; with per-embodiment bounds (E, A), each row by its embodiment."""

    def __init__(self, cfg: FlowVlaConfig, device: torch.device) -> None:
        low = torch.tensor(cfg.action_low, dtype=torch.float32, device=device)
        high = torch.tensor(cfg.action_high, dtype=torch.float32, device=device)
        rows = cfg.embodiment_rows
        want = (rows, cfg.action_dim) if rows else (cfg.action_dim,)
        if low.shape != want or high.shape != want or not bool((high > low).all()):
            what = f"{rows} rows of {cfg.action_dim}" if rows else f"{cfg.action_dim}"
            raise ValueError(f"{KIND}: action_low/high need {what} elements each with high > low")
        self.scale, self.bias = (high - low) / 2, (high + low) / 2

    def rows(self, x: torch.Tensor, embodiment: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Scale and bias broadcastable to x, (B, A) or (B, horizon, A): per row by its embodiment when shared."""
        if self.scale.ndim == 1:
            return self.scale, self.bias
        if embodiment is None:
            raise ValueError(f"{KIND}: per-embodiment action bounds need each row's {EMBODIMENT_KEY!r}; none given")
        index = embodiment.to(self.scale.device, torch.long).reshape(-1)
        shape = (index.numel(), *([1] * (x.ndim - 2)), self.scale.shape[-1])
        return self.scale[index].reshape(shape), self.bias[index].reshape(shape)

    def normalize(self, action: torch.Tensor, embodiment: torch.Tensor | None = None) -> torch.Tensor:
        scale, bias = self.rows(action, embodiment)
        return ((action - bias) / scale).clamp(-1.0, 1.0)

    def unnormalize(self, x: torch.Tensor, embodiment: torch.Tensor | None = None) -> torch.Tensor:
        scale, bias = self.rows(x, embodiment)
        return x * scale + bias


def parse_config(spec: learner_pb2.PolicySpec) -> FlowVlaConfig:
    try:
        return FlowVlaConfig.model_validate(json.loads(spec.config_json))
    except (json.JSONDecodeError, ValidationError) as exc:
        raise ValueError(f"{KIND} config_json: {exc}") from None


@register_policy(KIND)
class FlowVlaPolicy(Policy):
    """Chunks (B, horizon, action_dim) from cameras, state and an instruction."""

    def __init__(
        self, spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str = "cpu"
    ) -> None:
        self.spec, self.version = spec, int(version)
        self.config = parse_config(spec)
        self.device = check_device(device)
        self.model = FlowVla(self.config)
        load_tensors(self.model, tensors)
        self.model.to(self.device).eval()
        self.prep = Preprocessor(self.config, self.device)
        self.scaler = ActionScaler(self.config, self.device)
        # What the core's Policy declarations ask for (observation keys, action shape, chunk horizon).
        self._observation_keys = tuple(self.config.observation_keys())
        self.obs_keys = [k for k in self.observation_keys if k != self.config.instruction_key]
        self.optional_obs_keys = [self.config.instruction_key] if self.config.instruction_key else []
        self._action_shape = (self.config.action_dim,)
        self._chunk_horizon = self.config.horizon

    @property
    def observation_keys(self) -> tuple[str, ...]:
        return self._observation_keys

    @property
    def action_shape(self) -> tuple[int, ...]:
        return self._action_shape

    @property
    def embodiment_rows(self) -> int:
        return self.config.embodiment_rows

    @property
    def chunk_horizon(self) -> int:
        return self._chunk_horizon

    @property
    def image_shapes(self) -> dict[str, tuple[int | None, ...]]:
        return {key: (None, None, 3) for key in self.config.image_keys}  # any size: resized to image_size

    def check_observation(self, observation: Mapping[str, np.ndarray]) -> None:
        super().check_observation(observation)
        values = sum(int(np.size(observation[k])) for k in self.config.state_keys if k in observation)
        if values != self.config.state_dim:
            keys, dim = self.config.state_keys, self.config.state_dim
            raise ValueError(f"state {keys} has {values} values, the policy reads {dim}")

    def preprocess(self, observation: Mapping[str, np.ndarray], instructions: Sequence[str]) -> Prepared:
        return self.prep(observation, instructions)

    @torch.inference_mode()  # no autograd bookkeeping at all (a few % faster than no_grad on CPU)
    def forward(self, prepared: Prepared, deterministic: bool = False) -> np.ndarray:
        context = self.model.encode(prepared.images, prepared.state, prepared.tokens)
        chunk = self.scaler.unnormalize(self.model.sample(context, deterministic), prepared.embodiment)
        return chunk.cpu().numpy().astype(np.float32, copy=False)

    # Stepped sampling (user.policy.SteppedSampler): forward() in parts, so the inference service can let
    # rows join and leave a batch at flow-step boundaries.
    @torch.inference_mode()
    def begin(self, prepared: Prepared, deterministic: bool = False) -> FlowRows:
        context = self.model.encode(prepared.images, prepared.state, prepared.tokens)
        rows = self.model.start(context, deterministic)
        rows.embodiment = prepared.embodiment  # finish maps each row onto its embodiment's range
        return rows

    @torch.inference_mode()
    def advance(self, rows: FlowRows) -> FlowRows:
        return self.model.advance(rows)

    @torch.inference_mode()
    def finish(self, rows: FlowRows) -> np.ndarray:
        chunk = self.scaler.unnormalize(rows.x.clamp(-1.0, 1.0), rows.embodiment)
        return chunk.cpu().numpy().astype(np.float32, copy=False)

    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        return self.forward(self.preprocess(observation, []), deterministic)


def random_weights(config: FlowVlaConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """Freshly initialised weights (what a learner publishes before its first update)."""
    torch.manual_seed(seed)
    return module_tensors(FlowVla(config))
