"""Task `classifier`: a trained success classifier judges each step (the learned reward).

Loads a model written by `userctl reward train` (safetensors + JSON, never pickle) from a local
folder. After every step it scores the new camera frame: P(success) >= `threshold` gives
`success_reward` and, by default, ends the episode as a success; anything else gives 0.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field, ValidationError
from safetensors import SafetensorError

from edge_agent.robot import Observation
from edge_agent.task import TASKS, Outcome, ParamError, Task
from user.policy import check_device
from user.registry import PluginParams
from user.reward_model import load_classifier
from user.v1 import robot_pb2


@TASKS.register("classifier", description="reward 1 when a trained success classifier says so (userctl reward train)")
class ClassifierTask(Task):
    class Params(PluginParams):
        model: str = Field(description="folder with model.safetensors + config.json from `userctl reward train`")
        threshold: float = Field(default=0.5, gt=0, lt=1, description="P(success) at or above this is a success")
        success_reward: float = 1.0
        terminate_on_success: bool = True
        device: str = "cpu"

    params: Params

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec) -> None:
        super().__init__(params, spec)
        try:
            device = str(check_device(params.device))
        except ValueError as exc:
            raise ParamError("device", str(exc)) from None
        try:
            self.model = load_classifier(params.model, device)
        except ValidationError as exc:  # config.json that is not a classifier's: one line per wrong field
            wrong = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'config'}: {e['msg']}" for e in exc.errors())
            raise ParamError("model", f"{params.model}/config.json is not a classifier config: {wrong}") from None
        except (ValueError, OSError, SafetensorError) as exc:  # no model there, unreadable, or weights not matching
            raise ParamError("model", str(exc)) from None
        config = self.model.config
        features = {f.name: f for f in spec.observation}
        for key in [config.camera, *([config.state_key] if config.state_key else [])]:
            if key not in features:
                raise ParamError(
                    "model", f"robot {spec.robot_id!r} has no observation {key!r}; the classifier needs it"
                )
        if list(features[config.camera].shape) != config.image_shape:
            raise ParamError(
                "model",
                f"camera {config.camera!r} gives {list(features[config.camera].shape)} frames, "
                f"the classifier was trained on {config.image_shape}",
            )
        self.last_probability = 0.0

    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        self.last_probability = self.model.probability(next_observation.features)
        success = self.last_probability >= self.params.threshold
        return Outcome(
            reward=self.params.success_reward if success else 0.0,
            terminated=success and self.params.terminate_on_success,
            success=success,
        )
