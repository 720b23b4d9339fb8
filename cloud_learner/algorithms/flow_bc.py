"""flow_bc: behaviour cloning of a flow_vla policy with the flow-matching loss (HG-DAgger's learner).

HG-DAgger (Kelly et al. 2019): the robot runs the policy, a human takes over when it errs, and the
learner imitates only what humans did: the demonstrations plus the intervention steps. Here that
is a batch drawn half from the `demos` table and half from `interventions` (configurable), and
one gradient step on the flow-matching loss per update. Rows the policy chose itself (not an
intervention) are skipped when they come from a table that mixes both (e.g. `online`).

Chunks: with `horizon` H > 1 the batch request asks replay for each row's next H actions of its
episode (BatchRequest.action_horizon -> SampleRequest.action_horizon); the target is
`batch.action_chunk` (B, H, A) and the loss skips the padding past an episode's end
(`batch.chunk_mask`). An intervention row's chunk holds only the human's actions (replay ends it
where the human handed back). A batch without chunks trains horizon 1 only: guessing the rest of
a chunk would teach the wrong thing.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from pydantic import Field

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout, TableShares, configured_lr
from cloud_learner.algorithms.sac import MAX_BATCH, MAX_IMAGE_SIZE, StateMean, StateStd
from user.policies.flow_vla import ActionScaler, FlowVla, FlowVlaConfig, Preprocessor, policy_spec
from user.policy import module_tensors
from user.registry import PluginParams
from user.text import INSTRUCTION_KEY
from user.v1 import learner_pb2


class FlowBcParams(PluginParams):
    batch_size: int = Field(64, ge=1, le=MAX_BATCH, description="rows per update")
    lr: float = Field(3e-4, gt=0, description="Adam learning rate")
    horizon: int = Field(1, ge=1, le=256, description="actions per chunk; > 1 asks replay for action chunks")
    tables: TableShares = Field(
        default_factory=lambda: {"demos": 0.5, "interventions": 0.5}, description="replay tables and their shares"
    )
    human_only: bool = Field(True, description="skip rows the policy chose (intervention false) from mixed tables")
    demo_tables: list[str] = Field(default_factory=lambda: ["demos"], description="tables whose rows are all human")
    image_size: int = Field(64, ge=16, le=MAX_IMAGE_SIZE)
    hidden: int = Field(128, ge=8, le=8192, description="width of the context and expert networks (~5 hidden x hidden)")
    flow_steps: int = Field(5, ge=1, le=1000, description="Euler steps per chunk (each a forward pass)")
    default_instruction: str = ""
    seed: int = 0
    state_mean: StateMean = Field(
        default={}, description="per state feature, values subtracted before the network (learner.normalize sets it)"
    )
    state_std: StateStd = Field(default={}, description="per state feature, divisors (> 0) after state_mean")


def config_for(layout: Layout, params: FlowBcParams) -> FlowVlaConfig:
    """The policy architecture for an experiment's observation layout."""
    has_instruction = INSTRUCTION_KEY in layout.observation
    state_keys = [k for k in layout.state_keys() if k != INSTRUCTION_KEY]
    dims = {k: int(np.prod(layout.observation[k].shape)) for k in state_keys}
    for name, stats in (("state_mean", params.state_mean), ("state_std", params.state_std)):
        bad = {k: len(v) for k, v in stats.items() if dims.get(k) != len(v)}
        if bad:
            raise ValueError(f"{name}: {bad} are not state features of the right size ({dims})")
    mean = std = None
    if params.state_mean or params.state_std:
        mean = [x for k in state_keys for x in params.state_mean.get(k, [0.0] * dims[k])]
        std = [x for k in state_keys for x in params.state_std.get(k, [1.0] * dims[k])]
    low, high = layout.bounds_json()  # one list per embodiment when shared: each robot's own range
    return FlowVlaConfig(
        state_mean=mean,
        state_std=std,
        image_keys=layout.image_keys(),
        state_keys=state_keys,
        state_dim=sum(int(np.prod(layout.observation[k].shape)) for k in state_keys),
        instruction_key=INSTRUCTION_KEY if has_instruction else None,
        default_instruction=params.default_instruction,
        action_dim=layout.action_dim,
        action_low=low,
        action_high=high,
        horizon=params.horizon,
        image_size=params.image_size,
        hidden=params.hidden,
        flow_steps=params.flow_steps,
    )


@ALGORITHMS.register("flow_bc", description="HG-DAgger learner: flow-matching BC of flow_vla on demos + interventions")
class FlowBc(Algorithm):
    Params = FlowBcParams
    resumable_params = frozenset({"lr", "batch_size", "tables", "human_only", "demo_tables"})

    def __init__(self, params: FlowBcParams, layout: Layout, device: torch.device) -> None:
        super().__init__(params, layout, device)
        self.p = params
        torch.manual_seed(params.seed)
        self.config = config_for(layout, params)
        self.model = FlowVla(self.config).to(device)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=params.lr, fused=torch.device(device).type == "cuda"
        )
        self.prep = Preprocessor(self.config, device)
        self.scaler = ActionScaler(self.config, device)

    def batch_request(self) -> BatchRequest:
        return BatchRequest(
            batch_size=self.p.batch_size,
            tables=dict(self.p.tables),
            action_horizon=self.config.horizon,
            human_tables=tuple(self.p.demo_tables),  # replay flags their rows intervention
        )

    def targets(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(B, horizon, A) target chunks normalised to [-1, 1] (each row by its embodiment's range when shared)
        and their (B, horizon) mask of real actions (None: all)."""
        chunk, mask = batch.action_chunk, batch.chunk_mask
        if chunk is None:
            if self.config.horizon != 1:
                raise ValueError(f"flow_bc horizon {self.config.horizon} needs batch.action_chunk; this batch has none")
            chunk = batch.action[:, None, :]
        if tuple(chunk.shape[1:]) != (self.config.horizon, self.config.action_dim):
            raise ValueError(f"action_chunk shape {tuple(chunk.shape)} does not match the policy's chunk")
        mask = mask.to(self.device).bool() if mask is not None else None
        return self.scaler.normalize(chunk.to(self.device).float(), batch.embodiment_index()), mask

    def row_weights(self, batch: Batch) -> torch.Tensor | None:
        """1 for human rows, 0 for the policy's own; None = every row counts."""
        if not self.p.human_only:
            return None
        if set(self.p.tables) <= {"interventions", *self.p.demo_tables}:
            return None  # human-only tables: every row is a human action
        return batch.intervention.to(self.device).float()  # demo_tables' rows come flagged (BatchRequest.human_tables)

    def update(self, batch: Batch) -> dict[str, float]:
        observation = {k: v.cpu().numpy() for k, v in batch.observation.items()}
        prepared = self.prep(observation)
        weight = self.row_weights(batch)
        if weight is not None and float(weight.sum()) == 0.0:
            return {"flow_loss": float("nan"), "human_rows": 0.0}
        self.model.train()
        context = self.model.encode(prepared.images, prepared.state, prepared.tokens)
        target, mask = self.targets(batch)
        dims = batch.action_mask.to(self.device) if batch.action_mask is not None else None
        loss = self.model.flow_loss(context, target, weight, mask, dims)  # padded action dims are no label
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        rows = float(weight.sum()) if weight is not None else float(len(batch))
        return {"flow_loss": float(loss.detach()), "human_rows": rows}

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        return policy_spec(self.config), module_tensors(self.model)

    def state_dict(self) -> dict[str, Any]:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": torch.tensor(self.updates),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        configured_lr(self.optimizer, self.p.lr, "policy")
        self.updates = int(state["updates"])
