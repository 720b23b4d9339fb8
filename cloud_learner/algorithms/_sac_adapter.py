"""sac: cloud_learner.sac.SAC behind the Algorithm interface (interim adapter until algorithms/sac.py lands).

State features (every non-image key of the layout, sorted, flattened) are concatenated into one
vector; images are ignored. Publishes the `sac_mlp` policy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout
from cloud_learner.sac import SAC
from user.policy import SAC_MLP, PolicyChoice, policy_spec_for
from user.registry import PluginError, PluginParams
from user.v1 import learner_pb2


class SacParams(PluginParams):
    hidden: list[int] = [128, 128]
    batch_size: int = 128
    gamma: float = 0.95
    tau: float = 0.005
    actor_lr: float = 1e-3
    critic_lr: float = 1e-3
    alpha_lr: float = 1e-3
    init_alpha: float = 0.1


@ALGORITHMS.register("sac")
class SacAdapter(Algorithm):
    """Soft Actor-Critic on state features (twin critics, auto-tuned entropy); publishes sac_mlp."""

    Params = SacParams

    def __init__(
        self, params: SacParams, layout: Layout, device: torch.device, policy: PolicyChoice | None = None
    ) -> None:
        super().__init__(params, layout, device)
        if policy is not None and policy.kind != SAC_MLP:
            raise PluginError(f"policy.kind: sac publishes {SAC_MLP!r}, not {policy.kind!r}")
        if policy is not None and getattr(policy.params, "hidden", None):
            params = params.model_copy(update={"hidden": list(policy.params.hidden)})  # type: ignore[attr-defined]
        self.params = params
        self.keys = layout.state_keys()
        if not self.keys:
            raise PluginError("sac needs at least one non-image observation feature")
        obs_dim = sum(int(np.prod(layout.observation[k].shape)) for k in self.keys)
        self.sac = SAC(obs_dim, layout.action_low, layout.action_high, params, device=device)  # type: ignore[arg-type]

    def batch_request(self) -> BatchRequest:
        return BatchRequest(batch_size=self.params.batch_size)

    def _vector(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        n = next(iter(obs.values())).shape[0]
        return torch.cat([obs[k].reshape(n, -1).float() for k in self.keys], dim=1)

    def update(self, batch: Batch) -> dict[str, float]:
        scalars = self.sac.update(
            {
                "obs": self._vector(batch.observation),
                "next_obs": self._vector(batch.next_observation),
                "action": batch.action,
                "reward": batch.reward,
                "terminated": batch.terminated,
            }
        )
        self.updates = self.sac.updates
        return scalars

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        config = {**self.sac.actor_config(), "obs_keys": self.keys}
        return policy_spec_for(config), self.sac.actor_tensors()

    def state_dict(self) -> dict[str, Any]:
        return self.sac.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.sac.load_state_dict(state)
        self.updates = self.sac.updates
