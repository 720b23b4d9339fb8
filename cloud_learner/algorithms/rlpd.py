"""RLPD (Ball et al. 2023, "Efficient Online RL with Offline Data"): SAC plus three changes, nothing else.

1. Symmetric sampling: every batch is half online transitions, half offline ones (a "demos" or
   "interventions" table; `tables` sets the names and shares).
2. A critic ensemble of `num_critics` heads with LayerNorm; the TD target takes the min over a random
   pair of target heads, the actor maximizes the ensemble mean.
3. A high update-to-data ratio: `utd` critic steps (each on its own minibatch) per actor step.

The update itself is SAC's (cloud_learner.algorithms.sac), from state or from pixels; only the
defaults differ. The published policy is the same "mlp" / "cnn" kind.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from cloud_learner.algorithm import ALGORITHMS
from cloud_learner.algorithms.sac import SAC, SACParams


class RLPDParams(SACParams):
    batch_size: int = Field(default=256, ge=1, description="transitions per critic step (both halves)")
    gamma: float = Field(default=0.99, gt=0, le=1, description="discount")
    actor_lr: float = Field(default=3e-4, gt=0)
    critic_lr: float = Field(default=3e-4, gt=0)
    alpha_lr: float = Field(default=3e-4, gt=0)
    init_alpha: float = Field(default=1.0, gt=0, description="initial entropy temperature (then tuned)")
    target_entropy_scale: float = Field(default=0.5, gt=0, description="target entropy = -scale * action_dim")
    num_critics: int = Field(default=10, ge=2, description="Q heads in the critic ensemble")
    target_subset: int = Field(default=2, ge=1, description="TD target: min over this many random target heads")
    critic_layer_norm: bool = Field(default=True, description="LayerNorm after each critic hidden layer")
    actor_q: Literal["min", "mean"] = Field(default="mean", description="the actor maximizes the ensemble mean")
    utd: int = Field(default=10, ge=1, description="critic steps per actor step (the paper uses 20)")
    tables: dict[str, float] = Field(
        default={"online": 0.5, "demos": 0.5}, description="50/50 online and offline (demos or interventions)"
    )


@ALGORITHMS.register("rlpd", description="RLPD: SAC + 50/50 online/offline, LayerNorm critic ensemble, high UTD")
class RLPD(SAC):
    Params = RLPDParams
