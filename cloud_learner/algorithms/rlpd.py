"""RLPD (Ball et al. 2023, "Efficient Online RL with Offline Data"): SAC plus three changes, nothing else.

1. Symmetric sampling: every batch is half online transitions, half offline ones (a "demos" or
   "interventions" table; `tables` sets the names and shares).
2. A critic ensemble of `num_critics` heads with LayerNorm; the TD target takes the min over a random
   pair of target heads, the actor maximizes the ensemble mean.
3. A high update-to-data ratio: `utd` critic steps (each on its own minibatch) per actor step.

The update itself is SAC's (cloud_learner.algorithms.sac), from state or from pixels; only the
defaults differ. The published policy is the same "mlp" / "cnn" kind.

Optional warm start from demos (both off by default), phases counted in updates:
- `actor_pretrain_updates`: the first updates train the actor by BC alone (MSE of its mean action on
  the rows a human or script chose, at `actor_pretrain_lr`), nothing else (with `bc_encoder`, the
  shared encoder too): RL starts from the clone.
  An RLPD actor trained on the demos with its Q term from the start did not become the clone
  (SO-101: 0 of 15 picks after 1,500 such updates, where plain BC picks 16 of 20).
- `critic_warmup_updates`: then the critics alone train (actor and alpha frozen): they evaluate the
  clone on the demos before its Q term may pull it anywhere, so the first online updates follow a
  critic that has seen the rewards rather than a random one.
The BC weight's decay (`bc_decay_updates`) counts from the end of these phases.
"""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field

from cloud_learner.algorithm import ALGORITHMS, Batch, TableShares
from cloud_learner.algorithms.sac import MAX_BATCH, MAX_ENSEMBLE, MAX_UTD, SAC, SACParams, augment, bc_mse, split


class RLPDParams(SACParams):
    batch_size: int = Field(default=256, ge=1, le=MAX_BATCH, description="transitions per critic step (both halves)")
    gamma: float = Field(default=0.99, gt=0, le=1, description="discount")
    actor_lr: float = Field(default=3e-4, gt=0)
    critic_lr: float = Field(default=3e-4, gt=0)
    alpha_lr: float = Field(default=3e-4, gt=0)
    init_alpha: float = Field(default=1.0, gt=0, description="initial entropy temperature (then tuned)")
    target_entropy_scale: float = Field(default=0.5, gt=0, description="target entropy = -scale * action_dim")
    num_critics: int = Field(default=10, ge=2, le=MAX_ENSEMBLE, description="Q heads in the critic ensemble")
    target_subset: int = Field(default=2, ge=1, description="TD target: min over this many random target heads")
    critic_layer_norm: bool = Field(default=True, description="LayerNorm after each critic hidden layer")
    actor_q: Literal["min", "mean"] = Field(default="mean", description="the actor maximizes the ensemble mean")
    utd: int = Field(default=10, ge=1, le=MAX_UTD, description="critic steps per actor step (the paper uses 20)")
    tables: TableShares = Field(
        default={"online": 0.5, "demos": 0.5}, description="50/50 online and offline (demos or interventions)"
    )
    actor_pretrain_updates: int = Field(
        default=0, ge=0, description="first updates: the actor by BC alone on demo/intervention rows (0: none)"
    )
    actor_pretrain_lr: float = Field(default=1e-3, gt=0, description="the actor's learning rate in that BC phase")
    critic_warmup_updates: int = Field(
        default=0, ge=0, description="then updates of the critics alone, actor and alpha frozen (0: none)"
    )


@ALGORITHMS.register("rlpd", description="RLPD: SAC + 50/50 online/offline, LayerNorm critic ensemble, high UTD")
class RLPD(SAC):
    Params = RLPDParams
    p: RLPDParams
    # The warm start's phases are counted in updates: changing them moves where a resumed run switches phase.
    resumable_params = SAC.resumable_params | {"actor_pretrain_updates", "critic_warmup_updates", "actor_pretrain_lr"}

    @property
    def warm_updates(self) -> int:
        """Updates spent on the warm start (actor BC, then critics alone) before RL proper."""
        return self.p.actor_pretrain_updates + self.p.critic_warmup_updates

    def phase(self) -> Literal["actor_bc", "critic_warmup", "rl"]:
        if self.updates < self.p.actor_pretrain_updates:
            return "actor_bc"
        return "critic_warmup" if self.updates < self.warm_updates else "rl"

    def actor_lr(self) -> float:
        return self.p.actor_pretrain_lr if self.phase() == "actor_bc" else self.p.actor_lr

    def bc_weight(self) -> float:
        """As SAC's, with the decay counted from the end of the warm start."""
        if self.p.bc_decay_updates == 0:
            return self.p.bc_weight
        rl_updates = max(0, self.updates - self.warm_updates)
        return self.p.bc_weight * max(0.0, 1.0 - rl_updates / self.p.bc_decay_updates)

    def update(self, batch: Batch) -> dict[str, float]:
        phase = self.phase()
        # One actor optimizer for both phases (a checkpoint holds it); only its step size differs.
        lr = self.actor_lr()
        for group in self.actor_optimizer.param_groups:
            group["lr"] = lr
        if phase == "rl":
            return super().update(batch)
        if phase == "actor_bc":
            info = self.pretrain_actor(batch)
        else:
            for minibatch in split(batch, self.p.utd):
                _, critic = self.update_critic(minibatch)
            info = {k: float(v) for k, v in critic.items()}
        self.updates += 1
        return {**info, "alpha": self.alpha}

    def pretrain_actor(self, batch: Batch) -> dict[str, float]:
        """One BC step on the whole batch (all utd minibatches' rows): the actor's mean toward the
        demonstrated actions; the critics and alpha are left alone, and so is the encoder unless
        bc_encoder (then the critic optimizer, which owns it, steps it on the BC loss too)."""
        obs = augment(batch.observation, self.encoder, self.p.image_pad)
        with torch.set_grad_enabled(self.p.bc_encoder):
            features = self.encoder(obs)
        _, _, mean_action = self.actor.sample(features, batch.action_mask, batch.embodiment_index())
        loss = bc_mse(mean_action, batch)
        self.actor_optimizer.zero_grad(set_to_none=True)
        if self.p.bc_encoder:
            self.step_encoder(loss)  # backward, the encoder's step (critic heads get no gradient), Polyak
        else:
            loss.backward()
        self.actor_optimizer.step()
        return {"bc_loss": float(loss.detach())}
