"""smolvla_bc: HG-DAgger's learner for lerobot's SmolVLA, fine-tuned online from a local checkpoint folder.

The same method as flow_bc (demos + intervention steps, imitated with SmolVLA's own flow-matching
loss; the policy's own steps from mixed tables skipped when `human_only`), but the model is a
pretrained lerobot SmolVLA: `checkpoint` is the folder `user.policies.smolvla.load_checkpoint`
loads (config.json, model.safetensors, processor pipelines), so

    algorithm: {kind: smolvla_bc, params: {checkpoint: /models/smolvla_base, lr: 1.0e-5}}

improves a downloaded (or earlier saved) SmolVLA on the experiment's robots, and the policy it
publishes is the existing `smolvla` kind (the same folder + the trained tensors): inference and
local edges rebuild it exactly as they serve a checkpoint today.

Batch -> lerobot: each camera feature (uint8 B,H,W,3) becomes `observation.images.<camera>` floats
in [0, 1] (robot camera -> checkpoint camera through `image_keys`; by default the layout's cameras in
order onto the checkpoint's), the state features are concatenated into `observation.state`, the
instruction bytes become the `task` text (`default_instruction` where empty), the targets are the
row's next `chunk_size` actions (replay assembles them: BatchRequest.action_horizon) as `action`
(B, chunk, A) with `action_is_pad` = not chunk_mask (past an episode's end or where the human handed
back). The checkpoint's preprocessor (newline + tokenizer, normalisation of state and action with the
checkpoint's statistics) runs on that, then `SmolVLAPolicy.forward` gives the loss.

What trains is what the checkpoint's config says (SmolVLA's recipe: `train_expert_only` freezes the
whole VLM, `freeze_vision_encoder` its vision tower; `train_state_proj`); `train_expert_only` /
`freeze_vision` override them. AdamW with the config's betas, eps and weight decay, its lr unless
`lr` is given, and its grad-clip norm; constant lr (online: no schedule to a fixed end).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import Field, field_validator

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout, TableShares, configured_lr
from cloud_learner.algorithms.sac import MAX_BATCH
from user.policies.smolvla import KIND as SMOLVLA
from user.policies.smolvla import SmolVlaSpec, load_checkpoint, policy_spec
from user.policy import module_tensors
from user.registry import PluginParams
from user.text import INSTRUCTION_KEY, decode_instruction
from user.v1 import learner_pb2

IMAGES = "observation.images."
STATE = "observation.state"


def checkpoint_type(folder: str | Path) -> str:
    """The policy type a lerobot checkpoint folder's config.json declares; ValueError if it is no such folder."""
    path = Path(folder)
    if not path.is_dir():
        raise ValueError(f"{str(folder)!r} is not a folder (a local lerobot SmolVLA checkpoint folder is needed)")
    config = path / "config.json"
    if not config.is_file():
        raise ValueError(f"{str(folder)!r} holds no config.json (not a lerobot checkpoint folder)")
    try:
        kind = json.loads(config.read_text()).get("type")
    except (OSError, ValueError, AttributeError) as exc:
        raise ValueError(f"{config} is not a readable lerobot config: {exc}") from None
    return str(kind)


class SmolVlaBcParams(PluginParams):
    checkpoint: str = Field(description="local lerobot SmolVLA checkpoint folder (config.json, weights, processors)")
    batch_size: int = Field(32, ge=1, le=MAX_BATCH, description="rows per update")
    lr: float | None = Field(None, gt=0, description="AdamW learning rate; unset: the checkpoint's optimizer_lr")
    tables: TableShares = Field(
        default_factory=lambda: {"demos": 0.5, "interventions": 0.5}, description="replay tables and their shares"
    )
    human_only: bool = Field(True, description="skip rows the policy chose (intervention false) from mixed tables")
    demo_tables: list[str] = Field(default_factory=lambda: ["demos"], description="tables whose rows are all human")
    image_keys: dict[str, str] = Field(
        default={},
        description="robot camera feature -> checkpoint camera name; unset: the layout's cameras in order",
    )
    state_keys: list[str] = Field(
        default=[], description="state features concatenated into observation.state; unset: all (sorted)"
    )
    default_instruction: str = Field("", description="the task text for rows without an instruction")
    train_expert_only: bool | None = Field(None, description="freeze the whole VLM; unset: the checkpoint's setting")
    freeze_vision: bool | None = Field(None, description="freeze the vision encoder; unset: the checkpoint's setting")
    seed: int = 0

    @field_validator("checkpoint")
    @classmethod
    def _smolvla_folder(cls, value: str) -> str:
        kind = checkpoint_type(value)
        if kind != SMOLVLA:
            raise ValueError(f"{value!r} holds a {kind!r} policy, not {SMOLVLA!r}")
        return value


def camera_names(config: Any) -> list[str]:
    """The checkpoint's cameras (lerobot's `observation.images.<name>`), lerobot's empty padding cameras left out."""
    names = [k.removeprefix(IMAGES) for k in config.image_features]
    return [n for n in names if not n.startswith("empty_camera_")]


def feature_mapping(layout: Layout, params: SmolVlaBcParams, config: Any) -> tuple[dict[str, str], list[str]]:
    """(robot camera -> checkpoint camera, state keys) for the experiment's layout; ValueError naming the
    field where the layout does not fit the checkpoint (cameras, state size, action size)."""
    cameras = camera_names(config)
    robot_cameras = layout.image_keys()
    if params.image_keys:
        unknown = sorted(set(params.image_keys) - set(robot_cameras))
        if unknown:
            raise ValueError(f"image_keys: {unknown} are not camera features of the robots ({robot_cameras})")
        wrong = sorted(set(params.image_keys.values()) - set(cameras))
        if wrong:
            raise ValueError(f"image_keys: {wrong} are not cameras of the checkpoint ({cameras})")
        if len(set(params.image_keys.values())) != len(params.image_keys):
            raise ValueError(f"image_keys: two robot cameras map onto one checkpoint camera ({params.image_keys})")
        image_keys = dict(params.image_keys)
    else:
        if len(robot_cameras) > len(cameras):
            raise ValueError(
                f"image_keys: the robots have {len(robot_cameras)} cameras {robot_cameras}, the checkpoint takes "
                f"{len(cameras)} {cameras}; map the ones to use in image_keys"
            )
        image_keys = dict(zip(robot_cameras, cameras, strict=False))
    if not image_keys:
        raise ValueError(f"image_keys: SmolVLA needs at least one camera; the robots have none ({robot_cameras})")

    candidates = [k for k in layout.state_keys() if k != INSTRUCTION_KEY]
    if params.state_keys:
        unknown = sorted(set(params.state_keys) - set(candidates))
        if unknown:
            raise ValueError(f"state_keys: {unknown} are not state features of the robots ({candidates})")
        state_keys = list(params.state_keys)
    else:
        state_keys = candidates
    state_dim = sum(int(np.prod(layout.observation[k].shape)) for k in state_keys)
    state_feature = config.robot_state_feature
    expected_state = int(np.prod(state_feature.shape)) if state_feature is not None else 0
    if state_dim != expected_state:
        raise ValueError(
            f"state_keys: the robots' state {state_keys} has {state_dim} values, the checkpoint's {STATE} "
            f"{expected_state}"
        )
    expected_action = int(np.prod(config.action_feature.shape))
    if layout.action_dim != expected_action:
        raise ValueError(
            f"action_dim: the robots act with {layout.action_dim} values, the checkpoint {expected_action}"
        )
    return image_keys, state_keys


def apply_freezing(model: Any, train_expert_only: bool | None, freeze_vision: bool | None) -> None:
    """Override the checkpoint config's freeze flags (None keeps them) and redo lerobot's requires_grad pass."""
    if train_expert_only is None and freeze_vision is None:
        return  # SmolVLAPolicy's constructor already applied the checkpoint's flags
    config, vlm = model.config, model.model.vlm_with_expert
    if train_expert_only is not None:
        config.train_expert_only = vlm.train_expert_only = bool(train_expert_only)
    if freeze_vision is not None:
        config.freeze_vision_encoder = vlm.freeze_vision_encoder = bool(freeze_vision)
    for param in model.parameters():
        param.requires_grad_(True)
    vlm.set_requires_grad()  # lerobot's own rules for these flags (plus the parts it never trains)
    model.model.set_requires_grad()  # state_proj follows train_state_proj


@ALGORITHMS.register(
    "smolvla_bc",
    description="HG-DAgger learner: fine-tunes a local lerobot SmolVLA checkpoint on demos + interventions",
)
class SmolVlaBc(Algorithm):
    Params = SmolVlaBcParams
    # What a resume may change (cloud_learner.algorithm's resuming rule, as flow_bc): the rest picks the model,
    # what of it trains (the optimizer's parameter groups) or what it sees.
    resumable_params = frozenset({"lr", "batch_size", "tables", "human_only", "demo_tables"})

    def __init__(self, params: SmolVlaBcParams, layout: Layout, device: torch.device) -> None:
        super().__init__(params, layout, device)
        self.p = params
        torch.manual_seed(params.seed)
        try:
            self.model, self.pre, _post = load_checkpoint(params.checkpoint, str(device))
        except (OSError, KeyError, TypeError, RuntimeError) as exc:  # smolvla.py raises ValueError itself
            raise ValueError(f"checkpoint: cannot load {params.checkpoint!r}: {exc}") from None
        self.config = self.model.config
        self.image_keys, self.state_keys = feature_mapping(layout, params, self.config)
        self.published = self.spec()  # what inference rebuilds: checked now, not at the first publish
        self.chunk_size = int(self.config.chunk_size)
        apply_freezing(self.model, params.train_expert_only, params.freeze_vision)
        self.trainable = [q for q in self.model.parameters() if q.requires_grad]
        if not self.trainable:
            raise ValueError("train_expert_only/freeze_vision: nothing of the checkpoint's model is left to train")
        cfg = self.config
        self.lr = params.lr if params.lr is not None else float(cfg.optimizer_lr)
        self.optimizer = torch.optim.AdamW(
            self.trainable,
            lr=self.lr,
            betas=tuple(cfg.optimizer_betas),
            eps=float(cfg.optimizer_eps),
            weight_decay=float(cfg.optimizer_weight_decay),
        )
        clip = getattr(cfg, "optimizer_grad_clip_norm", None)
        self.grad_clip = float(clip) if clip else None

    def batch_request(self) -> BatchRequest:
        return BatchRequest(
            batch_size=self.p.batch_size,
            tables=dict(self.p.tables),
            action_horizon=self.chunk_size,
            human_tables=tuple(self.p.demo_tables),  # replay flags their rows intervention
        )

    # --- batch -> lerobot --------------------------------------------------------------------------

    def human_rows(self, batch: Batch) -> torch.Tensor | None:
        """Bool (B,) of the rows to imitate; None = all of them (as flow_bc decides)."""
        if not self.p.human_only:
            return None
        if set(self.p.tables) <= {"interventions", *self.p.demo_tables}:
            return None  # human-only tables: every row is a human action
        return batch.intervention.bool()  # demo_tables' rows come flagged (BatchRequest.human_tables)

    def targets(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, chunk, A) target actions and (B, chunk) action_is_pad (true past an episode's end / a hand-back)."""
        chunk, mask = batch.action_chunk, batch.chunk_mask
        if chunk is None:
            if self.chunk_size != 1:
                raise ValueError(
                    f"smolvla_bc chunk_size {self.chunk_size} needs batch.action_chunk (replay's action_horizon); "
                    "this batch has none"
                )
            chunk = batch.action[:, None, :]
        if tuple(chunk.shape[1:]) != (self.chunk_size, self.layout.action_dim):
            raise ValueError(
                f"action_chunk shape {tuple(chunk.shape)} does not match the checkpoint's chunk "
                f"({self.chunk_size}, {self.layout.action_dim})"
            )
        pad = ~mask.bool() if mask is not None else torch.zeros(chunk.shape[:2], dtype=torch.bool)
        return chunk.float(), pad

    def lerobot_batch(self, observation: dict[str, torch.Tensor]) -> dict[str, Any]:
        """Our observation rows as lerobot's raw batch, mapped as `SmolVlaPolicy.preprocess` maps them for
        inference (a private copy: that method takes numpy and runs the preprocessor itself)."""
        n = int(next(iter(observation.values())).shape[0])
        out: dict[str, Any] = {}
        for key, camera in self.image_keys.items():
            img = observation[key].to(self.device)
            out[f"{IMAGES}{camera}"] = img.permute(0, 3, 1, 2).float().div_(255.0)
        state = [observation[k].to(self.device).float().reshape(n, -1) for k in self.state_keys]
        out[STATE] = torch.cat(state, dim=1) if state else torch.zeros(n, 0, device=self.device)
        texts = [self.p.default_instruction] * n
        if INSTRUCTION_KEY in observation:
            raw = observation[INSTRUCTION_KEY].cpu().numpy()
            texts = [decode_instruction(raw[i]) or self.p.default_instruction for i in range(n)]
        out["task"] = texts
        return out

    # --- the update --------------------------------------------------------------------------------

    def update(self, batch: Batch) -> dict[str, float]:
        keep = self.human_rows(batch)
        chunk, pad = self.targets(batch)
        observation = batch.observation
        if keep is not None:
            keep = keep.cpu()
            if not bool(keep.any()):
                return {"bc_loss": float("nan"), "human_rows": 0.0}
            if not bool(keep.all()):
                observation = {k: v[keep.to(v.device)] for k, v in observation.items()}
                chunk, pad = chunk[keep.to(chunk.device)], pad[keep.to(pad.device)]
        raw = self.lerobot_batch(observation)
        raw["action"] = chunk.to(self.device)
        raw["action_is_pad"] = pad.to(self.device)
        prepared = self.pre(raw)
        prepared["action_is_pad"] = prepared["action_is_pad"].to(self.device)
        self.model.train()  # lerobot keeps the frozen parts in eval mode
        loss, _info = self.model.forward(prepared)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        clip = self.grad_clip if self.grad_clip is not None else float("inf")  # inf: measure, do not clip
        norm = torch.nn.utils.clip_grad_norm_(self.trainable, clip)
        self.optimizer.step()
        self.updates += 1
        return {"bc_loss": float(loss.detach()), "human_rows": float(len(raw["task"])), "grad_norm": float(norm)}

    # --- publishing and checkpoints ----------------------------------------------------------------

    def spec(self) -> SmolVlaSpec:
        return SmolVlaSpec(
            checkpoint=self.p.checkpoint,
            image_keys=self.image_keys,
            state_keys=self.state_keys,
            action_dim=self.layout.action_dim,
            action_low=[float(x) for x in self.layout.action_low.reshape(-1)],
            action_high=[float(x) for x in self.layout.action_high.reshape(-1)],
            default_instruction=self.p.default_instruction,
        )

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        return policy_spec(self.published), module_tensors(self.model)

    def state_dict(self) -> dict[str, Any]:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": torch.tensor(self.updates),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        configured_lr(self.optimizer, self.lr, "policy")  # the config's learning rate, not the checkpoint's
        self.updates = int(state["updates"])
