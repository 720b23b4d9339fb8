"""Tiny test plug-ins: each is one class and one decorator, used from a config entry with nothing else edited.

Importing this module registers them (a real plug-in lives in its interface's package or an installed
package's `user.plugins` entry point; tests register from here).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import Field

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout
from edge_agent.robot import ROBOTS, Observation
from edge_agent.robots.sim_arm import SimReachArm
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from user.policy import POLICIES, Policy
from user.registry import PluginParams
from user.v1 import learner_pb2


@POLICIES.register("test_constant", description="test: the same action for every observation")
class ConstantPolicy(Policy):
    def __init__(
        self, spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str = "cpu"
    ) -> None:
        config = json.loads(spec.config_json)
        self.spec, self.version = spec, int(version)
        self.keys = tuple(config["obs_keys"])
        self.action = np.asarray(tensors["action"], np.float32).reshape(-1)

    @property
    def observation_keys(self) -> tuple[str, ...]:
        return self.keys

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (int(self.action.size),)

    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        batch = len(next(iter(observation.values())))
        return np.repeat(self.action[None], batch, axis=0)


@ALGORITHMS.register("test_mean", description="test: moves a constant action toward the batch mean")
class MeanAction(Algorithm):
    class Params(PluginParams):
        batch_size: int = 8
        rate: float = 0.5

    def __init__(self, params: Params, layout: Layout, device: torch.device) -> None:
        super().__init__(params, layout, device)
        self.action = torch.zeros(layout.action_dim)
        self.seen: list[dict[str, Any]] = []  # what each batch looked like, for assertions

    def batch_request(self) -> BatchRequest:
        return BatchRequest(batch_size=self.params.batch_size)  # type: ignore[attr-defined]

    def update(self, batch: Batch) -> dict[str, float]:
        self.seen.append(
            {
                "n": len(batch),
                "dtypes": {k: v.dtype for k, v in batch.observation.items()},
                "intervention": batch.intervention.dtype,
                "embodiment": None if batch.embodiment is None else batch.embodiment.tolist(),
            }
        )
        self.action += self.params.rate * (batch.action.float().mean(0) - self.action)  # type: ignore[attr-defined]
        self.updates += 1
        return {"distance": float(batch.action.float().mean(0).sub(self.action).norm())}

    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        config = {"obs_keys": self.layout.state_keys()}
        spec = learner_pb2.PolicySpec(kind="test_constant", config_json=json.dumps(config))
        return spec, {"action": self.action.numpy().copy()}

    def state_dict(self) -> dict[str, Any]:
        return {"action": self.action.clone(), "updates": self.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.action = state["action"].clone()
        self.updates = int(state["updates"])


@ROBOTS.register("test_pluggable", description="test: a sim arm on a cable (a file): it is there while the file is")
class PluggableArm(SimReachArm):
    """Hot-plug stand-in for a USB arm: connect fails and the bus calls raise while the cable file is missing."""

    class Params(SimReachArm.Params):
        cable: str = Field(min_length=1, description="a file that exists while the arm is plugged in")

    def __init__(self, params: Params, robot_id: str, seed: int = 0) -> None:
        self.cable = Path(params.cable)
        self._built = False  # building touches no hardware (a lerobot robot's constructor does not either)
        super().__init__(params, robot_id, seed)
        self._built = True

    def _bus(self) -> None:
        if self._built and not self.cable.exists():
            raise ConnectionError(f"{self.robot_id}: no device (cable {self.cable} pulled)")

    def connect(self) -> None:
        self._bus()

    def observe(self) -> Observation:
        self._bus()
        return super().observe()

    def act(self, action: np.ndarray) -> np.ndarray:
        self._bus()
        return super().act(action)

    def hold(self) -> None:  # a real arm's hold writes to its bus too
        self._bus()
        super().hold()


@TELEOPERATORS.register("test_pluggable", description="test: a gamepad on a cable (a file) that always holds still")
class PluggableGamepad(Teleoperator):
    """Connect fails while the cable file is missing; once connected the "human" drives every tick (zero action).
    Like a USB handle, a connection lost to a pulled cable stays dead after re-plugging: only a new connect works."""

    class Params(PluginParams):
        cable: str = Field(min_length=1, description="a file that exists while the gamepad is plugged in")

    connected = False

    def connect(self) -> None:
        if not Path(self.params.cable).exists():  # type: ignore[attr-defined]
            raise ConnectionError("no gamepad")
        self.connected = True

    def poll(self, observation: Observation) -> np.ndarray | None:
        if not Path(self.params.cable).exists():  # type: ignore[attr-defined]
            self.connected = False
        if not self.connected:
            raise ConnectionError("gamepad handle lost (cable pulled)")
        return np.zeros(len(self.spec.action.low), np.float32)
