"""Before an experiment's first weight version: state statistics and pretraining, both from replay tables.

- normalize (`experiments[i].normalize`): the learner samples `samples` transitions of a table (e.g. the
  imported demos) and computes each float state feature's mean and std (std floored at `min_std`). They
  become the algorithm's `state_mean` / `state_std` params, so the policy it publishes carries them in its
  PolicySpec (mlp / cnn / flow_vla configs) and inference and edges normalize exactly as training did. The
  statistics are stored in every checkpoint: a restarted learner reuses them, never recomputes them from a
  buffer that has changed meanwhile (the network's inputs would shift under it).
- pretrain (`experiments[i].pretrain`): `steps` updates on one table before version 1 is published.

The learner loop (cloud_learner/learner.py) runs both in the experiment's "prepare" thread; this module
holds what needs no service: the statistics, the params they become, and the start-up checks.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cloud_learner.algorithm import ALGORITHMS, Layout
from user.config import ExperimentConfig
from user.registry import PluginError

STAT_FIELDS = ("state_mean", "state_std")


def check_prepare(experiments: Sequence[ExperimentConfig], where: str = "experiments[{i}]") -> None:
    """normalize needs an algorithm that takes state_mean/state_std, and does not override the user's own."""
    for i, exp in enumerate(experiments):
        if exp.normalize is None:
            continue
        at = where.format(i=i)
        fields = ALGORITHMS.get(exp.algorithm.kind).params.model_fields
        if not all(f in fields for f in STAT_FIELDS):
            raise PluginError(f"{at}.normalize: algorithm {exp.algorithm.kind!r} takes no state_mean/state_std params")
        given = [f for f in STAT_FIELDS if exp.algorithm.params.get(f)]
        if given:
            raise PluginError(
                f"{at}.normalize: algorithm.params.{given[0]} is set too; "
                "use one source of statistics (drop normalize, or the params)"
            )


def normalize_keys(layout: Layout, wanted: Sequence[str]) -> list[str]:
    """The float state features to normalize: `wanted`, or every one; an unknown key is an error."""
    floats = [k for k in layout.state_keys() if layout.observation[k].dtype.startswith("float")]
    unknown = sorted(set(wanted) - set(floats))
    if unknown:
        raise ValueError(f"normalize.keys {unknown} are not float state features of the robots ({floats})")
    return [k for k in floats if not wanted or k in wanted]


def state_stats(rows: Mapping[str, np.ndarray], min_std: float) -> dict[str, dict[str, list[float]]]:
    """{state_mean: {key: [...]}, state_std: {key: [...]}} over rows (n, ...) per key, std >= min_std."""
    mean, std = {}, {}
    for key, values in rows.items():
        flat = np.asarray(values, np.float64).reshape(len(values), -1)
        mean[key] = [float(x) for x in flat.mean(axis=0)]
        std[key] = [float(x) for x in np.maximum(flat.std(axis=0), min_std)]
    return {"state_mean": mean, "state_std": std}


def with_stats(params: Mapping[str, Any], stats: Mapping[str, Any] | None) -> dict[str, Any]:
    """The algorithm's params with the statistics merged in (none: unchanged)."""
    return {**params, **{f: dict(stats[f]) for f in STAT_FIELDS}} if stats else dict(params)
