"""The algorithm interface: the only thing the learner loop knows about how a policy is trained.

The learner samples what `batch_request()` asks for (tables and their shares, e.g. RLPD's 50/50
online/demos), decodes it into a `Batch`, calls `update(batch)` and logs the scalars it returns,
publishes `policy()` as a weight version and checkpoints `state_dict()`. It never names an
algorithm. New algorithms are one class plus `@ALGORITHMS.register("kind")` in a module of
`cloud_learner.algorithms`, readable top to bottom like CleanRL.

Resuming: a checkpoint records the params it was trained with. A restart whose config differs in a param is
refused (naming it) unless the algorithm lists the param in `resumable_params`: those only steer how the next
updates are made (learning rates, batch size, utd, table shares, loss weights, ...) and take effect on resume;
the rest shape the networks or their inputs, or only the initialization, which a resume would ignore.
Learning rates are the config's after a restore, not the checkpoint optimizer's (see `configured_lr`).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar

import numpy as np
import torch
from pydantic import Field, StringConstraints

from user.experiments import EMBODIMENT_KEY
from user.log import kv
from user.registry import PluginParams, Registry
from user.v1 import learner_pb2

log = logging.getLogger(__name__)

# Replay tables an algorithm samples and each one's share of a batch: at least one, every share > 0 (finite),
# names as replay takes them. Checked with the rest of the params at start, naming the table.
TableShares = Annotated[
    dict[
        Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")],
        Annotated[float, Field(gt=0, allow_inf_nan=False)],
    ],
    Field(min_length=1),
]


@dataclass(frozen=True)
class Feature:
    shape: tuple[int, ...]
    dtype: str  # numpy dtype name as it arrives from replay ("float32", "uint8", ...)
    is_image: bool = False


@dataclass(frozen=True)
class Layout:
    """What an experiment's transitions look like, derived from its robots' specs.

    For an experiment spanning several embodiments, features and actions are padded to the largest
    robot's size and `embodiments` lists the robot kinds (the index is the embodiment id in batches).
    `action_low`/`action_high` are then the union of every robot's range per dim, and `embodiment_low`/
    `embodiment_high` (E, action_dim) hold each robot kind's own range, row i for embodiments[i]: what a
    policy maps its [-1, 1] onto, so each robot's actions span its range, not the union.
    """

    observation: dict[str, Feature]
    action_low: np.ndarray
    action_high: np.ndarray
    embodiments: tuple[str, ...] = ()
    embodiment_low: np.ndarray | None = None
    embodiment_high: np.ndarray | None = None

    def __post_init__(self) -> None:
        if (self.embodiment_low is None) != (self.embodiment_high is None):
            raise ValueError("Layout.embodiment_low and embodiment_high: give both or neither")
        want = (len(self.embodiments), self.action_dim)
        for name in ("embodiment_low", "embodiment_high"):
            table = getattr(self, name)
            if table is not None and np.shape(table) != want:
                raise ValueError(f"Layout.{name} is {np.shape(table)}, one row per embodiment needs {want}")

    @property
    def action_dim(self) -> int:
        return int(self.action_low.size)

    @property
    def per_embodiment(self) -> bool:
        """Each embodiment has its own action range (a shared layout)."""
        return self.embodiment_low is not None

    def policy_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The range a policy maps [-1, 1] onto: (E, A) rows per embodiment when shared, else (A,)."""
        if self.embodiment_low is not None and self.embodiment_high is not None:
            return np.asarray(self.embodiment_low), np.asarray(self.embodiment_high)
        return np.asarray(self.action_low).reshape(-1), np.asarray(self.action_high).reshape(-1)

    def bounds_json(self) -> tuple[list, list]:
        """policy_bounds as PolicySpec JSON values: flat lists, or one list per embodiment when shared."""
        low, high = self.policy_bounds()
        return _floats(low), _floats(high)

    def state_keys(self) -> list[str]:
        return sorted(k for k, f in self.observation.items() if not f.is_image)

    def image_keys(self) -> list[str]:
        return sorted(k for k, f in self.observation.items() if f.is_image)


def _floats(values: np.ndarray) -> list:
    """Python floats, nested as the array is (a flat array gives what `[float(x) for x in a]` always gave)."""
    return [_floats(row) for row in values] if values.ndim > 1 else [float(x) for x in values]


@dataclass(frozen=True)
class BatchRequest:
    batch_size: int
    tables: dict[str, float] = field(default_factory=lambda: {"online": 1.0})  # table -> share of the batch
    n_step: int = 1
    gamma: float = 1.0  # the discount replay sums n-step rewards with (used when n_step > 1)
    action_horizon: int = 1  # > 1: Batch.action_chunk holds each row's next H actions of its episode
    # Tables whose every action is a demonstrator's: replay flags their rows Batch.intervention (imported demos are
    # stored without the flag), so BC terms and human-only rules count them. The learner leaves out the pretrain
    # table of an experiment with pretrain.human false (its rows are no demonstrator's).
    human_tables: tuple[str, ...] = ("demos",)


@dataclass
class Batch:
    """Decoded transitions on the algorithm's device; images stay uint8 (B, H, W, C) until the encoder."""

    observation: dict[str, torch.Tensor]
    action: torch.Tensor  # (B, action_dim) float32
    reward: torch.Tensor  # (B,) float32 (n-step discounted sum when n_step > 1)
    next_observation: dict[str, torch.Tensor]
    terminated: torch.Tensor  # (B,) float32 0/1: no bootstrapping
    intervention: torch.Tensor  # (B,) bool: a human chose the action (every row of BatchRequest.human_tables)
    discount: torch.Tensor | None = None  # (B,) gamma**n per row when n-step; None = gamma
    embodiment: torch.Tensor | None = None  # (B,) int64 index into Layout.embodiments
    action_mask: torch.Tensor | None = None  # (B, action_dim) bool: real (not padded) action dims
    # BatchRequest.action_horizon > 1: actions t..t+H-1 of each row's episode, (B, H, action_dim) float32,
    # the last real one repeated past the episode's end, where chunk_mask (B, H) bool is false.
    action_chunk: torch.Tensor | None = None
    chunk_mask: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.action.shape[0])

    def embodiment_index(self) -> torch.Tensor | None:
        """Each row's index into Layout.embodiments (which action range is its robot's): `embodiment`, else
        the one-hot embodiment feature of a shared layout's observation; None when the batch has neither."""
        if self.embodiment is not None:
            return self.embodiment
        onehot = self.observation.get(EMBODIMENT_KEY)
        return None if onehot is None else onehot.argmax(dim=-1)


class Algorithm(ABC):
    """update(batch) -> scalars; policy() -> what to publish; state_dict() -> what to checkpoint."""

    Params: type[PluginParams] = PluginParams
    # Params a resume may change (see the module docstring); none unless an algorithm says so.
    resumable_params: ClassVar[frozenset[str]] = frozenset()

    def __init__(self, params: PluginParams, layout: Layout, device: torch.device) -> None:
        self.params, self.layout, self.device = params, layout, device
        self.updates = 0

    def batch_request(self) -> BatchRequest:
        """What to sample for the next update (default: uniform from the online table)."""
        return BatchRequest(batch_size=int(getattr(self.params, "batch_size", 256)))

    @abstractmethod
    def update(self, batch: Batch) -> dict[str, float]:
        """One gradient step; returns named scalars (losses, temperature, ...) for status and metrics."""

    @abstractmethod
    def policy(self) -> tuple[learner_pb2.PolicySpec, dict[str, np.ndarray]]:
        """The acting policy to publish: its spec and named tensors (only what actors need)."""

    @abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed run needs (networks, optimizers, counters); tensors only, no pickled objects."""

    @abstractmethod
    def load_state_dict(self, state: dict[str, Any]) -> None: ...


def configured_lr(optimizer: torch.optim.Optimizer, lr: float, name: str) -> None:
    """After optimizer.load_state_dict, which brings back the checkpoint's learning rate: the config's again
    (a changed rate would be silently ignored otherwise), with a log line when they differ."""
    before = sorted({float(group["lr"]) for group in optimizer.param_groups})
    for group in optimizer.param_groups:
        group["lr"] = lr
    if before != [lr]:
        log.info(
            "learning rate from the config, not the checkpoint", extra=kv(optimizer=name, checkpoint=before, config=lr)
        )


ALGORITHMS: Registry[Algorithm] = Registry("algorithm", Algorithm, "cloud_learner.algorithms")
