"""Behaviour cloning: regress the policy onto human (or scripted) actions; the supervised baseline.

Batches come from the demonstration and intervention tables (`tables`). The loss is the MSE between
the policy's deterministic action and the demonstrated one, or the negative log-likelihood of the
demonstrated action under the squashed Gaussian (`loss: nll`, which also learns how unsure to be).
With `only_interventions`, rows a human did not choose are masked out (the HG-DAgger rule: learn
from corrections only). From pixels the CNN encoder trains end to end with the head, on randomly
shifted images. The policy is published as the same "mlp" / "cnn" kind SAC and RLPD publish.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
import torch
from pydantic import Field

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout, TableShares, configured_lr
from cloud_learner.algorithms.sac import MAX_BATCH, EncoderParams, Widths, augment, make_encoder, publish, trainable
from user.policies.mlp import GaussianActor, log_prob_of, scale_bias
from user.policy import SquashedGaussianActor
from user.v1 import learner_pb2


class BCParams(EncoderParams):
    hidden: Widths = Field(default=[256, 256], description="MLP widths of the policy head")
    batch_size: int = Field(default=256, ge=1, le=MAX_BATCH)
    lr: float = Field(default=1e-3, gt=0)
    loss: Literal["mse", "nll"] = Field(default="mse", description="mse on the mean action, or Gaussian NLL")
    only_interventions: bool = Field(default=False, description="learn only from rows a human chose")
    tables: TableShares = Field(
        default={"demos": 0.5, "interventions": 0.5}, description="replay table -> share of each batch"
    )


def masked_log_prob(
    head: SquashedGaussianActor,
    features: torch.Tensor,
    action: torch.Tensor,
    mask: torch.Tensor,
    embodiment: torch.Tensor | None = None,
) -> torch.Tensor:
    """log_prob_of summed over the real action dims only (Batch.action_mask, a layout padded across embodiments):
    a padded dim is never executed, so its stored filler is no label (as the head's own log-prob masks it).
    `embodiment` (B,): each row's range when the head's bounds are per embodiment."""
    scale, bias = scale_bias(head, embodiment)
    mean, log_std = head.distribution(features)
    squashed = ((action - bias) / scale).clamp(-1 + 1e-4, 1 - 1e-4)
    pre = torch.atanh(squashed)
    normal = -0.5 * ((pre - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
    per_dim = normal - torch.log(scale * (1 - squashed.pow(2)) + 1e-6)
    return (per_dim * mask.to(per_dim.dtype)).sum(-1)


@ALGORITHMS.register("bc", description="Behaviour cloning on demos and interventions (MSE or Gaussian NLL)")
class BC(Algorithm):
    Params = BCParams
    resumable_params = frozenset({"lr", "batch_size", "loss", "only_interventions", "tables", "image_pad"})

    def __init__(self, params: BCParams, layout: Layout, device: torch.device) -> None:
        super().__init__(params, layout, torch.device(device))
        self.p = params
        low, high = layout.policy_bounds()  # (E, A) when shared: each embodiment's own range
        self.actor = GaussianActor(make_encoder(layout, params), params.hidden, low, high)
        self.actor.to(self.device)
        self.optimizer = torch.optim.Adam(trainable(self.actor), lr=params.lr, fused=self.device.type == "cuda")

    def batch_request(self) -> BatchRequest:
        return BatchRequest(batch_size=self.p.batch_size, tables=dict(self.p.tables))

    def update(self, batch: Batch) -> dict[str, float]:
        features = self.actor.encoder(augment(batch.observation, self.actor.encoder, self.p.image_pad))
        embodiment = batch.embodiment_index()
        if self.p.loss == "mse":
            _, _, mean_action = self.actor.sample(features, embodiment=embodiment)
            error, mask = (mean_action - batch.action).pow(2), batch.action_mask
            per_row = error.mean(dim=-1) if mask is None else (error * mask).sum(-1) / mask.sum(-1).clamp(min=1)
        elif batch.action_mask is None:
            per_row = -log_prob_of(self.actor.head, features, batch.action, embodiment)
        else:
            per_row = -masked_log_prob(self.actor.head, features, batch.action, batch.action_mask, embodiment)
        weight = batch.intervention.float() if self.p.only_interventions else torch.ones_like(per_row)
        loss = (per_row * weight).sum() / weight.sum().clamp(min=1.0)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        return {"bc_loss": float(loss.detach()), "rows": float(weight.sum())}

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        return publish(self.actor, self.layout, self.p)

    def state_dict(self) -> dict[str, Any]:
        return {"actor": self.actor.state_dict(), "optimizer": self.optimizer.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.optimizer.load_state_dict(state["optimizer"])
        configured_lr(self.optimizer, self.p.lr, "policy")
        self.updates = int(state["updates"])
