"""padded: one policy for robots of different shapes (an experiment with shared_embodiment: true).

The learner trains on a padded layout (state features zero-padded to the widest robot, a one-hot
`embodiment` feature, actions padded with a mask) and publishes the algorithm's policy wrapped in
this kind. Callers add the robot's embodiment index (`user.experiments.embodiment_inputs`) to its
raw observation and cut the padded action back to the robot's size (`fit_action`); this class pads
and one-hots in between, so any inner policy kind works unchanged. An inner policy with per-embodiment
action bounds (one row per embodiment: mlp, cnn, flow_vla) maps each row onto its own robot's range by that
one-hot; its rows must be these embodiments, in this order.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np

from user.experiments import EMBODIMENT_KEY
from user.policy import POLICIES, Policy, build_policy
from user.v1 import learner_pb2

PADDED = "padded"


def padded_spec(
    inner: learner_pb2.PolicySpec, widths: dict[str, int], embodiments: dict[str, int]
) -> learner_pb2.PolicySpec:
    """Wrap `inner`: widths = padded size per state feature; embodiments = kind -> action dims, in id order."""
    config = {
        "inner": {"kind": inner.kind, "config_json": inner.config_json},
        "widths": widths,
        "embodiments": [[kind, int(dims)] for kind, dims in embodiments.items()],
    }
    return learner_pb2.PolicySpec(kind=PADDED, config_json=json.dumps(config, sort_keys=True))


@POLICIES.register(PADDED)
class PaddedPolicy(Policy):
    """Wraps any policy trained on a padded multi-embodiment layout: pads state, adds the one-hot embodiment."""

    def __init__(
        self, spec: learner_pb2.PolicySpec, tensors: Mapping[str, np.ndarray], version: int, device: str = "cpu"
    ) -> None:
        try:
            config = json.loads(spec.config_json)
            inner = learner_pb2.PolicySpec(kind=config["inner"]["kind"], config_json=config["inner"]["config_json"])
            self.widths = {str(k): int(v) for k, v in config["widths"].items()}
            pairs = [(str(k), int(d)) for k, d in config["embodiments"]]
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"padded config_json is malformed: {exc}") from None
        if inner.kind == PADDED or not pairs:
            raise ValueError("padded policy needs an inner kind other than padded and at least one embodiment")
        self.spec, self.version = spec, int(version)
        self.embodiments = [k for k, _ in pairs]
        self.action_dims = dict(pairs)
        self.inner = build_policy(inner, tensors, version, device)
        rows = int(getattr(self.inner, "embodiment_rows", 0) or 0)
        if rows and rows != len(self.embodiments):
            raise ValueError(
                f"padded: the inner {inner.kind!r} policy has action bounds for {rows} embodiments, "
                f"the config lists {len(self.embodiments)} ({self.embodiments})"
            )

    @property
    def observation_keys(self) -> tuple[str, ...]:
        raw = [k for k in self.inner.observation_keys if k != EMBODIMENT_KEY]
        return (*raw, EMBODIMENT_KEY)

    @property
    def action_shape(self) -> tuple[int, ...]:
        return self.inner.action_shape

    @property
    def chunk_horizon(self) -> int:
        return self.inner.chunk_horizon

    @property
    def image_shapes(self) -> Mapping[str, tuple[int | None, ...]]:
        return self.inner.image_shapes

    def check_observation(self, observation: Mapping[str, np.ndarray]) -> None:
        """Images as the inner policy reads them; a state may be narrower than its padded width, never wider."""
        super().check_observation(observation)
        for key, width in self.widths.items():
            arr = observation.get(key)
            if arr is not None and arr.size > width:
                raise ValueError(f"observation {key!r} has {arr.size} values, the policy pads to {width}")

    def act(self, observation: Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        ids = np.asarray(observation[EMBODIMENT_KEY]).astype(np.int64).reshape(-1)
        batch = ids.size
        if ids.min() < 0 or ids.max() >= len(self.embodiments):
            raise ValueError(f"embodiment index out of range 0..{len(self.embodiments) - 1}")
        inputs: dict[str, np.ndarray] = {}
        for key in self.inner.observation_keys:
            if key == EMBODIMENT_KEY:
                onehot = np.zeros((batch, len(self.embodiments)), np.float32)
                onehot[np.arange(batch), ids] = 1.0
                inputs[key] = onehot
            elif key in self.widths:
                flat = np.asarray(observation[key], np.float32).reshape(batch, -1)
                if flat.shape[1] > self.widths[key]:
                    raise ValueError(
                        f"observation {key!r} has {flat.shape[1]} values, the policy pads to {self.widths[key]}"
                    )
                padded = np.zeros((batch, self.widths[key]), np.float32)
                padded[:, : flat.shape[1]] = flat
                inputs[key] = padded
            else:
                inputs[key] = np.asarray(observation[key])
        return self.inner.act(inputs, deterministic)
