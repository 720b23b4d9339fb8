"""sac_mlp: the squashed-Gaussian MLP actor over concatenated state features (what SAC publishes)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Annotated

import numpy as np
import torch
from pydantic import Field

from user.policy import POLICIES, SAC_MLP, Policy, actor_from_config, check_device, check_sac_mlp_config, load_tensors
from user.registry import PluginParams
from user.v1 import learner_pb2


@POLICIES.register(SAC_MLP)
class SacMlpPolicy(Policy):
    """MLP squashed-Gaussian actor over concatenated state features (SAC's acting policy)."""

    class Params(PluginParams):
        # the same bounds as the algorithms' `hidden` (cloud_learner.algorithms.sac.Widths)
        hidden: list[Annotated[int, Field(ge=1, le=65536)]] = Field(default=[128, 128], max_length=16)

    def __init__(
        self, spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str = "cpu"
    ) -> None:
        try:
            config = json.loads(spec.config_json)
        except json.JSONDecodeError as exc:
            raise ValueError(f"sac_mlp config_json is not JSON: {exc}") from None
        if not isinstance(config, dict):
            raise ValueError("sac_mlp config_json must be an object")
        cfg = check_sac_mlp_config(config)
        self.spec = spec
        self.version = int(version)
        self.obs_keys: list[str] = list(cfg["obs_keys"])
        self.obs_dim = int(cfg["obs_dim"])
        self.action_dim = int(cfg["action_dim"])
        self.actor = actor_from_config(cfg)
        load_tensors(self.actor, tensors)
        self.device = check_device(device)
        self.actor.to(self.device).eval()

    @property
    def observation_keys(self) -> tuple[str, ...]:
        return tuple(self.obs_keys)

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (self.action_dim,)

    def obs_vector(self, observation: Mapping[str, np.ndarray]) -> np.ndarray:
        """Concatenate obs_keys (each flattened after the batch dim) into (B, obs_dim) float32."""
        missing = [k for k in self.obs_keys if k not in observation]
        if missing:
            raise ValueError(f"observation lacks {missing}")
        parts = [np.asarray(observation[k], dtype=np.float32) for k in self.obs_keys]
        batch = parts[0].shape[0] if parts[0].ndim else 0
        if batch < 1 or any(p.ndim == 0 or p.shape[0] != batch for p in parts):
            raise ValueError("observation values need the same leading batch dimension")
        vec = np.concatenate([p.reshape(batch, -1) for p in parts], axis=1)
        if vec.shape[1] != self.obs_dim:
            raise ValueError(f"observation has {vec.shape[1]} features, the policy expects {self.obs_dim}")
        return vec

    @torch.no_grad()
    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        obs = torch.from_numpy(self.obs_vector(observation)).to(self.device)
        action, _, mean_action = self.actor(obs)
        out = mean_action if deterministic else action
        return out.cpu().numpy().astype(np.float32, copy=False)
