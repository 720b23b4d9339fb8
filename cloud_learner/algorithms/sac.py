"""Soft Actor-Critic behind the Algorithm interface, from state or from pixels; reads top to bottom.

From state, the float observation features are concatenated in sorted key order. From pixels, each
camera has a small CNN (user.policies.cnn) shared by the actor and the critics: critic gradients train
it, the actor sees its features detached (DrQ, SERL); with `bc_encoder` the BC term on the rows a
human or script chose trains it too (added to each critic step's loss, on the same features). Every
sampled image is first downsampled to `image_size` (when set) and then randomly shifted by up to
`image_pad` pixels (DrQ augmentation).
Each critic step runs the convs twice, not three times: once with gradients on the observations, once
(target encoder, no gradients) on the next observations, whose features serve both the next action
and the target heads; the actor step reuses the critic step's features. The critic is an ensemble of
`num_critics` Q heads; the TD target takes the min over a random subset of `target_subset` target
heads, so plain SAC (2 and 2) and RLPD (10 and 2, see rlpd.py) share this file. `utd` critic steps
run per actor step on a batch of utd * batch_size rows, split in utd minibatches.

The actor is user.policies' GaussianActor, published as policy kind "mlp" or "cnn", so the inference
service and the edges rebuild it from spec + tensors (no pickle).
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
from pydantic import AfterValidator, Field, field_validator, model_validator
from torch import nn

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout, TableShares, configured_lr
from user.policies.cnn import KIND as CNN_KIND
from user.policies.cnn import ConvEncoder, random_shift
from user.policies.mlp import KIND as MLP_KIND
from user.policies.mlp import GaussianActor, StateEncoder, policy_spec, scale_bias
from user.policy import MAX_IMAGE_SIDE, module_tensors
from user.registry import PluginParams
from user.v1 import learner_pb2

# Size bounds: a definition is checked when control accepts it, so an absurd size (hidden: [1e12]) is refused
# there instead of failing the learner's allocation later while the experiment's robots stay leased.
MAX_WIDTH = 65536  # units of one MLP layer
MAX_LAYERS = 16  # MLP layers, conv layers
MAX_CHANNELS = 4096  # conv channels of one layer
MAX_STRIDE = 16
MAX_IMAGE_SIZE = MAX_IMAGE_SIDE  # square side images are resized to: the largest frame a policy takes
MAX_BATCH = 65536  # rows per update: replay's most rows per SampleRequest
MAX_ENSEMBLE = 64  # critic heads
MAX_N_STEP = 1000  # replay's most steps per n-step return
MAX_UTD = 1000  # critic steps per actor step
MAX_MLP_WEIGHTS = 1 << 28  # between hidden layers of one network: 1 GiB in float32


def _mlp_fits(widths: list[int]) -> list[int]:
    """Adjacent hidden layers are a width x width matrix each: bound their total, not only each width."""
    weights = sum(a * b for a, b in itertools.pairwise(widths))
    if weights > MAX_MLP_WEIGHTS:
        raise ValueError(f"{widths} holds {weights} weights between hidden layers; at most {MAX_MLP_WEIGHTS}")
    return widths


# Layer widths, conv channels and strides: a 0 builds no network (a division by zero deep in the init).
Widths = Annotated[
    list[Annotated[int, Field(ge=1, le=MAX_WIDTH)]], Field(max_length=MAX_LAYERS), AfterValidator(_mlp_fits)
]
Channels = Annotated[list[Annotated[int, Field(ge=1, le=MAX_CHANNELS)]], Field(min_length=1, max_length=MAX_LAYERS)]
Strides = Annotated[list[Annotated[int, Field(ge=1, le=MAX_STRIDE)]], Field(min_length=1, max_length=MAX_LAYERS)]


def _positive_std(std: dict[str, list[float]]) -> dict[str, list[float]]:
    bad = {k: v for k, values in std.items() for v in values if not (math.isfinite(v) and v > 0)}
    if bad:
        raise ValueError(f"state_std must be > 0 and finite (a divisor); got {bad}")
    return std


# Per state feature, one finite value per dim; a std of 0 would divide by zero.
StateMean = dict[str, list[Annotated[float, Field(allow_inf_nan=False)]]]
StateStd = Annotated[dict[str, list[float]], AfterValidator(_positive_std)]


def readable_safetensors(path: str) -> str:
    """`path` is a file whose safetensors header reads (checked at start, not when the learner builds)."""
    if not path:
        return path
    if not Path(path).is_file():
        raise ValueError(f"no such file: {path}")
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(path, "pt") as f:
            f.keys()
    except (SafetensorError, OSError) as exc:
        raise ValueError(f"{path} is not a readable safetensors file: {exc}") from None
    return path


class EncoderParams(PluginParams):
    """How observations are encoded: shared by every algorithm that trains a GaussianActor."""

    features: list[str] | None = Field(
        default=None, description="observation keys the networks see (default all; e.g. leave out privileged state)"
    )

    channels: Channels = Field(default=[16, 32, 32], description="conv channels per camera encoder layer")
    strides: Strides = Field(default=[2, 2, 2], description="conv strides per camera encoder layer")
    latent_dim: int = Field(default=50, ge=1, le=MAX_WIDTH, description="per-camera latent size")
    image_pad: int = Field(default=4, ge=0, le=256, description="DrQ random shift in pixels; 0 turns augmentation off")
    image_size: int = Field(
        default=0,
        ge=0,
        le=MAX_IMAGE_SIZE,
        description="cameras are area-downsampled to this square size before the convs (0: native)",
    )
    state_mean: StateMean = Field(
        default={}, description="per state feature, values subtracted before the networks (cameras or not)"
    )
    state_std: StateStd = Field(
        default={}, description="per state feature, divisors (> 0) after state_mean (e.g. from the demos' statistics)"
    )
    backbone: Literal["conv", "resnet18"] = Field(
        default="conv",
        description="camera encoder: small conv stacks per camera, or one torchvision ResNet-18 trunk for all",
    )
    pretrained: str = Field(
        default="",
        description="local safetensors file of torchvision resnet18 weights the trunk starts from (no download)",
    )
    freeze_backbone: bool = Field(
        default=False, description="the ResNet trunk never trains (weights and batch-norm statistics stay)"
    )

    @field_validator("pretrained")
    @classmethod
    def _pretrained_file(cls, path: str) -> str:
        return readable_safetensors(path)

    @field_validator("features")
    @classmethod
    def _some_features(cls, features: list[str] | None) -> list[str] | None:
        if features is not None and not features:
            raise ValueError("an empty list leaves the networks no input; leave features out to use every feature")
        return features

    @model_validator(mode="after")
    def _backbone_options(self) -> EncoderParams:
        if self.backbone != "resnet18" and (self.pretrained or self.freeze_backbone):
            raise ValueError("pretrained and freeze_backbone need backbone: resnet18")
        if len(self.channels) != len(self.strides):
            raise ValueError(f"channels {self.channels} and strides {self.strides} differ in length (one per layer)")
        return self


class SACParams(EncoderParams):
    hidden: Widths = Field(default=[128, 128], description="MLP widths of the actor and critic heads")
    batch_size: int = Field(default=128, ge=1, le=MAX_BATCH, description="transitions per critic step")
    gamma: float = Field(default=0.95, gt=0, le=1, description="discount (replaced by gamma**n rows when n-step)")
    tau: float = Field(default=0.005, gt=0, le=1, description="Polyak rate of the target critics (and encoder)")
    actor_lr: float = Field(default=1e-3, gt=0)
    critic_lr: float = Field(default=1e-3, gt=0)
    alpha_lr: float = Field(default=1e-3, gt=0)
    init_alpha: float = Field(default=0.1, gt=0, description="initial entropy temperature (then tuned)")
    target_entropy_scale: float = Field(default=1.0, gt=0, description="target entropy = -scale * action_dim")
    num_critics: int = Field(default=2, ge=1, le=MAX_ENSEMBLE, description="Q heads in the critic ensemble")
    target_subset: int = Field(default=2, ge=1, description="TD target: min over this many random target heads")
    critic_layer_norm: bool = Field(default=False, description="LayerNorm after each critic hidden layer")
    actor_q: Literal["min", "mean"] = Field(default="min", description="how the actor aggregates the ensemble")
    utd: int = Field(default=1, ge=1, le=MAX_UTD, description="critic steps per actor step (update-to-data ratio)")
    tables: TableShares = Field(default={"online": 1.0}, description="replay table -> share of each batch")
    n_step: int = Field(default=1, ge=1, le=MAX_N_STEP, description="n-step returns, summed by the replay service")
    backup_entropy: bool = Field(
        default=True,
        description="TD targets include the entropy bonus -alpha*log pi (off: a near-deterministic policy's large "
        "log-densities do not swamp a 0/1 reward; off is SERL's SAC default)",
    )
    bc_weight: float = Field(
        default=0.0, ge=0, description="weight of a BC term (MSE to the human action) on intervention/demo rows"
    )
    bc_decay_updates: int = Field(
        default=0, ge=0, description="the BC weight decays linearly to 0 over this many updates (0: constant)"
    )
    bc_encoder: bool = Field(
        default=False,
        description="the BC term also trains the shared encoder (added to each critic step's loss on its features); "
        "off: critic gradients only",
    )

    @model_validator(mode="after")
    def _subset_fits(self) -> SACParams:
        if self.target_subset > self.num_critics:
            raise ValueError(f"target_subset {self.target_subset} exceeds num_critics {self.num_critics}")
        return self


# --- networks -----------------------------------------------------------------------------------


class EnsembleLinear(nn.Module):
    """N independent linear layers applied in one batched matmul: (N, B, in) -> (N, B, out)."""

    def __init__(self, num: int, in_dim: int, out_dim: int) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(in_dim)  # nn.Linear's default init, per member
        self.weight = nn.Parameter(torch.empty(num, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(num, 1, out_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class Critic(nn.Module):
    """Q_i(features, action) for i in 1..num_critics; `encoder` is the one the actor shares."""

    def __init__(
        self, encoder: nn.Module, action_dim: int, hidden: list[int], num_critics: int, layer_norm: bool
    ) -> None:
        super().__init__()
        self.encoder, self.num_critics, self.layer_norm = encoder, num_critics, layer_norm
        widths = [encoder.out_dim + action_dim, *hidden]
        self.layers = nn.ModuleList(EnsembleLinear(num_critics, a, b) for a, b in itertools.pairwise(widths))
        self.out = EnsembleLinear(num_critics, widths[-1], 1)

    def forward(self, features: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(B, F) features and (B, A) actions -> (num_critics, B) values."""
        x = torch.cat([features, action], dim=-1).expand(self.num_critics, -1, -1)
        for layer in self.layers:
            x = layer(x)
            x = torch.relu(nn.functional.layer_norm(x, x.shape[-1:]) if self.layer_norm else x)
        return self.out(x).squeeze(-1)


def make_encoder(layout: Layout, p: EncoderParams) -> nn.Module:
    """State-only: concatenate the float features (sorted keys). With cameras: per-camera CNN + state."""
    unknown = sorted(set(p.features or []) - set(layout.observation))
    if unknown:
        raise ValueError(f"features {unknown} are not in the observation {sorted(layout.observation)}")
    wanted = set(layout.observation if p.features is None else p.features)
    state_keys = [k for k in layout.state_keys() if layout.observation[k].dtype.startswith("float") and k in wanted]
    state_dims = [int(np.prod(layout.observation[k].shape)) for k in state_keys]
    image_keys = [k for k in layout.image_keys() if k in wanted]
    if not image_keys and not state_keys:
        raise ValueError(f"no float or image features to learn from in {sorted(wanted)}")
    for name, stats in (("state_mean", p.state_mean), ("state_std", p.state_std)):
        bad = {k: len(v) for k, v in stats.items() if k not in state_keys or len(v) != state_dims[state_keys.index(k)]}
        if bad:
            sizes = dict(zip(state_keys, state_dims, strict=True))
            raise ValueError(f"{name}: {bad} are not state features of the right size ({sizes})")
    mean, std = None, None
    if p.state_mean or p.state_std:
        mean = [x for k, d in zip(state_keys, state_dims, strict=True) for x in p.state_mean.get(k, [0.0] * d)]
        std = [x for k, d in zip(state_keys, state_dims, strict=True) for x in p.state_std.get(k, [1.0] * d)]
    if not image_keys:
        return StateEncoder(state_keys, state_dims, mean, std)
    shapes = [list(layout.observation[k].shape) for k in image_keys]
    args = (p.channels, p.strides, p.latent_dim, p.image_size, mean, std, p.backbone)
    encoder = ConvEncoder(image_keys, shapes, state_keys, state_dims, *args)
    if encoder.trunk is not None and p.pretrained:
        try:
            encoder.trunk.load_pretrained(p.pretrained)
        except ValueError:
            raise
        except Exception as exc:  # safetensors' own error type (e.g. the file changed since the start check)
            raise ValueError(f"pretrained: {p.pretrained} cannot be read: {exc}") from None
    if encoder.trunk is not None and p.freeze_backbone:
        encoder.trunk.freeze()
    return encoder


def trainable(module: nn.Module) -> list[nn.Parameter]:
    """The parameters an optimizer owns: a frozen backbone's are left out."""
    return [q for q in module.parameters() if q.requires_grad]


def masked(action: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Padded action dims (a shared multi-embodiment layout) zeroed: the critic sees only real dims,
    whatever the actor sampled there or a sampler stored."""
    return action if mask is None else action * mask


def augment(obs: Mapping[str, torch.Tensor], encoder: nn.Module, pad: int) -> dict[str, torch.Tensor]:
    """The images the encoder reads downsampled to its input size, then randomly shifted (DrQ; no shift
    when pad is 0); state features unchanged."""
    prepare = getattr(encoder, "prepare", None)
    obs = prepare(obs) if prepare is not None else dict(obs)
    images = set(getattr(encoder, "image_keys", [])) if pad > 0 else set()
    return {k: random_shift(v, pad) if k in images else v for k, v in obs.items()}


def split(batch: Batch, parts: int) -> list[Batch]:
    """Deal a batch into `parts` minibatches, row i to minibatch i % parts (the UTD loop's critic steps).

    Dealt, not cut in blocks: a sampler returns each table's rows together (demos, then online), and
    blocks would give RLPD pure-demo and pure-online steps instead of a 50/50 mix in every step."""
    if parts == 1:
        return [batch]
    parts = min(parts, len(batch))

    def cut(x: Any, i: int) -> Any:
        if x is None:
            return None
        if isinstance(x, Mapping):
            return {k: v[i::parts] for k, v in x.items()}
        return x[i::parts]

    return [Batch(**{f: cut(getattr(batch, f), i) for f in Batch.__dataclass_fields__}) for i in range(parts)]


def bc_mse(mean_action: torch.Tensor, batch: Batch) -> torch.Tensor:
    """MSE of the deterministic action to the stored one, over the rows a human or script chose (real
    action dims only with a padded layout); 0 when the batch has none."""
    mask, human = batch.action_mask, batch.intervention.float()
    error = (mean_action - batch.action).pow(2)
    per_row = error.mean(dim=-1) if mask is None else (error * mask).sum(-1) / mask.sum(-1).clamp(min=1)
    return (per_row * human).sum() / human.sum().clamp(min=1.0)


def publish(
    actor: GaussianActor, layout: Layout, p: EncoderParams
) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
    """The actor as policy kind "mlp" (state only) or "cnn" (cameras): spec JSON + named tensors."""
    enc = actor.encoder
    state = enc if isinstance(enc, StateEncoder) else enc.state
    low, high = layout.bounds_json()  # one list per embodiment when shared: each robot's own range
    config: dict[str, Any] = {
        "state_keys": state.keys if state is not None else [],
        "state_dims": state.dims if state is not None else [],
        "hidden": [m.out_features for m in actor.head.net if isinstance(m, nn.Linear)][:-1],
        "action_low": low,
        "action_high": high,
    }
    if state is not None and (state.mean is not None or state.std is not None):
        config |= {"state_mean": state.mean, "state_std": state.std}
    if isinstance(enc, ConvEncoder):
        config |= {
            "image_keys": enc.image_keys,
            "image_shapes": [list(layout.observation[k].shape) for k in enc.image_keys],
            "channels": list(p.channels),
            "strides": list(p.strides),
            "latent_dim": p.latent_dim,
        }
        if enc.image_size:
            config["image_size"] = enc.image_size
        if enc.backbone != "conv":
            config["backbone"] = enc.backbone
    return policy_spec(CNN_KIND if isinstance(enc, ConvEncoder) else MLP_KIND, config), module_tensors(actor)


# --- the algorithm ------------------------------------------------------------------------------


@ALGORITHMS.register("sac", description="Soft Actor-Critic from state or pixels (DrQ shift, shared CNN encoder)")
class SAC(Algorithm):
    Params = SACParams
    # What the next updates do, not what the networks are: a resume may change these (see cloud_learner.algorithm).
    resumable_params = frozenset(
        {
            "actor_lr",
            "critic_lr",
            "alpha_lr",
            "batch_size",
            "utd",
            "tables",
            "n_step",
            "gamma",
            "tau",
            "target_entropy_scale",
            "target_subset",
            "actor_q",
            "backup_entropy",
            "bc_weight",
            "bc_decay_updates",
            "bc_encoder",
            "image_pad",
        }
    )

    def __init__(self, params: SACParams, layout: Layout, device: torch.device) -> None:
        super().__init__(params, layout, torch.device(device))
        p = self.p = params
        # (A,), or (E, A) per embodiment of a shared layout: the actor squashes each row into its robot's range
        low, high = layout.policy_bounds()
        self.low, self.high = np.asarray(low, np.float32), np.asarray(high, np.float32)
        action_dim = layout.action_dim

        # One encoder object, held by both the actor and the critic; the target critic gets a copy.
        self.encoder = make_encoder(layout, p)
        self.actor = GaussianActor(self.encoder, p.hidden, self.low, self.high).to(self.device)
        self.critic = Critic(self.encoder, action_dim, p.hidden, p.num_critics, p.critic_layer_norm).to(self.device)
        # A frozen backbone is shared with the target, not copied: it is the same function either way
        trunk = getattr(self.encoder, "trunk", None)
        shared = {id(trunk): trunk} if trunk is not None and trunk.frozen else {}
        self.critic_target = copy.deepcopy(self.critic, shared).requires_grad_(False)

        self.target_entropy = -p.target_entropy_scale * float(action_dim)
        self.log_alpha = torch.tensor(math.log(p.init_alpha), device=self.device, requires_grad=True)
        # The actor optimizer owns only the head: the encoder learns from the critic loss (and with bc_encoder
        # the BC term), stepped by the critic optimizer.
        # On a GPU the fused Adam is one kernel per step instead of several per parameter (the small MLPs of
        # state-based SAC are bound by kernel launches there, not by arithmetic).
        fused = self.device.type == "cuda"
        self.actor_optimizer = torch.optim.Adam(self.actor.head.parameters(), lr=p.actor_lr, fused=fused)
        self.critic_optimizer = torch.optim.Adam(trainable(self.critic), lr=p.critic_lr, fused=fused)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=p.alpha_lr, fused=fused)
        # Polyak-averaged pairs; a frozen backbone's copy is already equal and stays so (11M params skipped)
        pairs = zip(self.critic.parameters(), self.critic_target.parameters(), strict=True)
        moving = [(q, t) for q, t in pairs if q.requires_grad]
        self._critic_params, self._target_params = [q for q, _ in moving], [t for _, t in moving]

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    def batch_request(self) -> BatchRequest:
        return BatchRequest(
            batch_size=self.p.batch_size * self.p.utd,
            tables=dict(self.p.tables),
            n_step=self.p.n_step,
            gamma=self.p.gamma,
        )

    @torch.no_grad()
    def td_target(self, batch: Batch, next_obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """r + discount * (min over a random subset of target heads - alpha * log pi), unless terminated
        (without the entropy term when backup_entropy is off).

        Only termination stops bootstrapping; a truncated episode still has a future. The target
        encoder's features of the next observations serve both the next action and the target heads
        (one conv pass instead of two; the target encoder trails the online one by Polyak averaging)."""
        next_features = self.critic_target.encoder(next_obs)
        next_action, next_log_prob, _ = self.actor.sample(next_features, batch.action_mask, batch.embodiment_index())
        target_q = self.critic_target(next_features, masked(next_action, batch.action_mask))
        subset = torch.randperm(self.p.num_critics, device=self.device)[: self.p.target_subset]
        next_v = target_q[subset].min(dim=0).values
        if self.p.backup_entropy:
            next_v = next_v - self.log_alpha.exp() * next_log_prob
        discount = batch.discount if batch.discount is not None else self.p.gamma
        return batch.reward + discount * (1.0 - batch.terminated) * next_v

    def update_critic(self, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One critic (and encoder) step; returns the batch's features, detached, for the actor."""
        pad = self.p.image_pad
        obs, next_obs = (
            augment(batch.observation, self.encoder, pad),
            augment(batch.next_observation, self.encoder, pad),
        )
        target = self.td_target(batch, next_obs)
        features = self.encoder(obs)
        q = self.critic(features, masked(batch.action, batch.action_mask))
        critic_loss = (q - target).pow(2).mean(dim=1).sum()  # each head regresses on the same target
        info = {"critic_loss": critic_loss.detach(), "q": q.detach().mean()}
        loss = critic_loss
        if self.p.bc_encoder:  # the same conv pass carries the BC gradient into the encoder
            encoder_bc = bc_mse(self.frozen_head_mean(features, batch.embodiment_index()), batch)
            loss = loss + self.bc_weight() * encoder_bc
            info["encoder_bc_loss"] = encoder_bc.detach()
        self.step_encoder(loss)
        return features.detach(), info

    def step_encoder(self, loss: torch.Tensor) -> None:
        """One step of the critic optimizer (critics and the shared encoder; parameters the loss did not
        reach keep their values), then Polyak averaging of every target parameter in one batched call."""
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._target_params, self._critic_params, self.p.tau)

    def frozen_head_mean(self, features: torch.Tensor, embodiment: torch.Tensor | None = None) -> torch.Tensor:
        """The actor's mean action with its head's parameters detached: a loss on it trains only what
        produced `features` (the encoder); the head learns in the actor step."""
        head = self.actor.head
        params = {name: x.detach() for name, x in head.net.named_parameters()}
        mean = torch.func.functional_call(head.net, params, (features,)).chunk(2, dim=-1)[0]
        scale, bias = scale_bias(head, embodiment)
        return torch.tanh(mean) * scale + bias  # the head's deterministic action

    def bc_weight(self) -> float:
        """The BC term's weight now: bc_weight, decaying linearly to 0 over bc_decay_updates updates."""
        if self.p.bc_decay_updates == 0:
            return self.p.bc_weight
        return self.p.bc_weight * max(0.0, 1.0 - self.updates / self.p.bc_decay_updates)

    def update_actor(self, features: torch.Tensor, batch: Batch | None = None) -> dict[str, torch.Tensor]:
        """Maximize Q minus the entropy cost of fresh samples (plus a BC term on rows a human or script
        chose, when bc_weight > 0: SAC+BC / IBRL-style use of demos); then tune alpha toward the target entropy."""
        alpha = self.log_alpha.detach().exp()
        mask = batch.action_mask if batch is not None else None
        embodiment = batch.embodiment_index() if batch is not None else None
        action, log_prob, mean_action = self.actor.sample(features, mask, embodiment)
        q = self.critic(features, masked(action, mask))
        q_pi = q.min(dim=0).values if self.p.actor_q == "min" else q.mean(dim=0)
        actor_loss = (alpha * log_prob - q_pi).mean()
        bc_weight, bc_loss = self.bc_weight(), torch.zeros((), device=self.device)
        if bc_weight > 0 and batch is not None:
            bc_loss = bc_mse(mean_action, batch)
            actor_loss = actor_loss + bc_weight * bc_loss
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()  # also leaves grads on the critic; its optimizer clears them before its step
        self.actor_optimizer.step()

        # Raise alpha when the entropy is below target, lower it when above. With padded actions each
        # row's target counts its embodiment's real dims only.
        target_entropy = self.target_entropy
        if mask is not None:
            target_entropy = -self.p.target_entropy_scale * mask.sum(-1).float()
        alpha_loss = -(self.log_alpha * (log_prob.detach() + target_entropy)).mean()
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_optimizer.step()
        return {
            "actor_loss": actor_loss.detach(),
            "bc_loss": bc_loss.detach(),
            # the two pulls on the actor, for curves: how big the Q term is against the weighted BC term
            "q_pi": q_pi.detach().mean(),
            "bc_term": bc_loss.detach() * bc_weight,
            "alpha_loss": alpha_loss.detach(),
            "alpha": self.log_alpha.detach().exp(),
            "entropy": -log_prob.detach().mean(),
        }

    def update(self, batch: Batch) -> dict[str, float]:
        for minibatch in split(batch, self.p.utd):
            features, critic_info = self.update_critic(minibatch)
        info = {**critic_info, **self.update_actor(features, minibatch)}
        self.updates += 1
        # One device-to-host copy for all scalars: each float() of a GPU tensor would wait for the GPU.
        return dict(zip(info, torch.stack(list(info.values())).tolist(), strict=True))

    # --- what the learner publishes and checkpoints ---------------------------------------------

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        return publish(self.actor, self.layout, self.p)

    def state_dict(self) -> dict[str, Any]:
        """Tensors, ints and plain dicts only, so torch.load(weights_only=True) reads it back."""
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "alpha_optimizer": self.alpha_optimizer.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "updates": int(self.updates),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.critic_target.load_state_dict(state["critic_target"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        with torch.no_grad():
            self.log_alpha.copy_(torch.as_tensor(state["log_alpha"], device=self.device))
        self.updates = int(state["updates"])
        configured_lr(self.actor_optimizer, self.actor_lr(), "actor")
        configured_lr(self.critic_optimizer, self.p.critic_lr, "critic")
        configured_lr(self.alpha_optimizer, self.p.alpha_lr, "alpha")

    def actor_lr(self) -> float:
        """The actor's learning rate at the current update (RLPD's warm start uses another)."""
        return self.p.actor_lr
