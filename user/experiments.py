"""Experiments: which robot trains what, and the tensor layout an experiment's robots imply.

Control, the learner, inference and edges all answer "which experiment is this robot in?" the same
way: the first experiment in the config whose selector (kinds, labels, ids) holds for the robot's
spec. The learner derives each experiment's `Layout` from its robots' specs; robots of different
shapes share one policy only when the experiment says `shared_embodiment: true`: state features and
actions are then padded to the largest robot's size, an `embodiment` one-hot feature says which
robot kind a row came from, and an action mask marks the real action dims (RLinf-USER's approach).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from user import spec as contract
from user.config import ExperimentConfig, RobotSelector, StackConfig
from user.v1 import robot_pb2

if TYPE_CHECKING:  # torch-free for control and edges
    from cloud_learner.algorithm import Layout

EMBODIMENT_KEY = "embodiment"  # the one-hot feature a shared-embodiment layout adds


class LayoutError(ValueError):
    """An experiment's robots cannot share one layout (different shapes without shared_embodiment)."""


def matches(selector: RobotSelector, spec: robot_pb2.RobotSpec) -> bool:
    if selector.kinds and spec.kind not in selector.kinds:
        return False
    if selector.ids and spec.robot_id not in selector.ids:
        return False
    return all(spec.labels.get(k) == v for k, v in selector.labels.items())


def experiment_for(spec: robot_pb2.RobotSpec, experiments: Sequence[ExperimentConfig]) -> ExperimentConfig | None:
    """The first experiment whose selector holds for `spec` (None: the robot is not trained)."""
    return next((e for e in experiments if matches(e.robots, spec)), None)


def covers(earlier: RobotSelector, later: RobotSelector) -> bool:
    """Every robot `later` selects is selected by `earlier` too (so, coming first, it takes them all)."""

    def within(wide: list[str], narrow: list[str]) -> bool:  # an empty list holds for any value
        return not wide or (bool(narrow) and set(narrow) <= set(wide))

    labels = all(later.labels.get(k) == v for k, v in earlier.labels.items())
    return within(earlier.kinds, later.kinds) and within(earlier.ids, later.ids) and labels


def shadowed(experiments: Sequence[ExperimentConfig]) -> dict[str, str]:
    """experiment name -> the earlier experiment that takes every robot it selects (it can never train)."""
    out = {}
    for i, exp in enumerate(experiments):
        first = next((e for e in experiments[:i] if covers(e.robots, exp.robots)), None)
        if first is not None:
            out[exp.name] = first.name
    return out


def experiment_name(spec: robot_pb2.RobotSpec, cfg: StackConfig) -> str:
    exp = experiment_for(spec, cfg.resolved_experiments())
    return exp.name if exp is not None else ""


def assign(
    specs: Iterable[robot_pb2.RobotSpec], experiments: Sequence[ExperimentConfig]
) -> dict[str, list[robot_pb2.RobotSpec]]:
    """experiment name -> its robots' specs (every experiment present, possibly with no robots)."""
    out: dict[str, list[robot_pb2.RobotSpec]] = {e.name: [] for e in experiments}
    for spec in specs:
        exp = experiment_for(spec, experiments)
        if exp is not None:
            out[exp.name].append(spec)
    return out


def ready(exp: ExperimentConfig, specs: Sequence[robot_pb2.RobotSpec]) -> bool:
    """Enough robots to fix the layout: one at least, and for a shared embodiment one of every listed kind."""
    if not specs:
        return False
    if exp.shared_embodiment and exp.robots.kinds:
        return set(exp.robots.kinds) <= {s.kind for s in specs}
    return True


def _flat(shape: Sequence[int]) -> int:
    return int(math.prod(shape)) if shape else 1


def layout_for(exp: ExperimentConfig, specs: Sequence[robot_pb2.RobotSpec]) -> Layout:
    """The Layout of `exp`'s transitions; LayoutError names the robots that do not fit."""
    from cloud_learner.algorithm import Feature, Layout

    if not specs:
        raise LayoutError(f"experiment {exp.name}: no robots")
    first = specs[0]
    feats0 = contract.features(first)
    low0, high0 = (a.reshape(-1) for a in contract.action_bounds(first))
    if not exp.shared_embodiment:
        for spec in specs[1:]:
            low, high = (a.reshape(-1) for a in contract.action_bounds(spec))
            same = contract.features(spec) == feats0 and low.shape == low0.shape
            if not same or not (np.allclose(low, low0) and np.allclose(high, high0)):
                raise LayoutError(
                    f"experiment {exp.name}: robots {first.robot_id} ({first.kind}) and {spec.robot_id} ({spec.kind}) "
                    "have different observations or actions; put them in separate experiments or set "
                    "shared_embodiment: true"
                )
        observation = {k: Feature(f.shape, f.dtype, f.is_image) for k, f in feats0.items()}
        return Layout(observation, low0.astype(np.float32), high0.astype(np.float32))

    kinds = sorted({s.kind for s in specs})
    state: dict[str, int] = {}
    images: dict[str, tuple[tuple[int, ...], str]] = {}
    action_dim = 0
    for spec in specs:
        for name, f in contract.features(spec).items():
            if f.is_image:
                if images.setdefault(name, (f.shape, f.dtype)) != (f.shape, f.dtype):
                    raise LayoutError(
                        f"experiment {exp.name}: image {name!r} of {spec.robot_id} is {f.shape} {f.dtype}, "
                        f"others have {images[name]}; shared embodiments pad state, not images"
                    )
            else:
                state[name] = max(state.get(name, 0), _flat(f.shape))
        action_dim = max(action_dim, contract.action_dim(spec))
    for spec in specs:
        lacking = sorted(set(images) - set(contract.features(spec)))
        if lacking:
            raise LayoutError(
                f"experiment {exp.name}: {spec.robot_id} has no image {lacking}; shared embodiments pad state, "
                "every robot needs the same images"
            )
    if EMBODIMENT_KEY in state or EMBODIMENT_KEY in images:
        raise LayoutError(f"experiment {exp.name}: feature name {EMBODIMENT_KEY!r} is reserved")
    observation = {k: Feature((n,), "float32") for k, n in state.items()}
    observation.update({k: Feature(shape, dtype, True) for k, (shape, dtype) in images.items()})
    observation[EMBODIMENT_KEY] = Feature((len(kinds),), "float32")
    rows_low, rows_high = embodiment_bounds(exp, specs, kinds, action_dim)
    # The union of the rows per dim (what clips any robot's action); the policy maps onto each row's own.
    low, high = rows_low.min(axis=0), rows_high.max(axis=0)
    return Layout(observation, low, high, tuple(kinds), rows_low, rows_high)


def embodiment_bounds(
    exp: ExperimentConfig, specs: Sequence[robot_pb2.RobotSpec], kinds: Sequence[str], action_dim: int
) -> tuple[np.ndarray, np.ndarray]:
    """(E, action_dim) float32 low and high, row i the action range of robot kind kinds[i]; the padded dims a kind
    lacks get [-1, 1] (masked out of every loss). LayoutError when two robots of one kind differ in their actions:
    a kind is one embodiment row, and either robot's range would be wrong for the other."""
    low = np.tile(np.float32(-1.0), (len(kinds), action_dim))
    high = np.tile(np.float32(1.0), (len(kinds), action_dim))
    first: dict[str, robot_pb2.RobotSpec] = {}
    for spec in specs:
        lo, hi = (a.reshape(-1).astype(np.float32) for a in contract.action_bounds(spec))
        seen = first.setdefault(spec.kind, spec)
        if seen is not spec:
            lo0, hi0 = (a.reshape(-1).astype(np.float32) for a in contract.action_bounds(seen))
            if lo.shape != lo0.shape or not (np.array_equal(lo, lo0) and np.array_equal(hi, hi0)):
                raise LayoutError(
                    f"experiment {exp.name}: robots {seen.robot_id} and {spec.robot_id} are both kind {spec.kind} but "
                    "have different action bounds; a shared embodiment has one action range per kind"
                )
        row = kinds.index(spec.kind)
        low[row, : lo.size], high[row, : hi.size] = lo, hi
    return low, high


# --------------------------------------------------------------------------- padding (shared embodiment)


def pad_observation(
    layout: Layout, kind: str, observation: Mapping[str, np.ndarray], batch: int
) -> dict[str, np.ndarray]:
    """A robot's batched features (B, ...) -> the layout's: state flattened and zero-padded, one-hot embodiment."""
    out: dict[str, np.ndarray] = {}
    for name, feat in layout.observation.items():
        if name == EMBODIMENT_KEY:
            onehot = np.zeros((batch, feat.shape[0]), np.float32)
            onehot[:, layout.embodiments.index(kind)] = 1.0
            out[name] = onehot
        elif feat.is_image:
            if name not in observation:
                raise LayoutError(f"robot kind {kind} has no image {name!r} the layout needs")
            out[name] = np.asarray(observation[name])
        else:
            padded = np.zeros((batch, feat.shape[0]), np.float32)
            if name in observation:
                flat = np.asarray(observation[name], np.float32).reshape(batch, -1)
                padded[:, : flat.shape[1]] = flat
            out[name] = padded
    return out


def pad_action(action: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(B, a) -> (B, width) zero-padded actions and the (B, width) bool mask of real dims."""
    batch, a = action.shape[0], int(np.prod(action.shape[1:])) if action.ndim > 1 else 1
    padded = np.zeros((batch, width), np.float32)
    padded[:, :a] = action.reshape(batch, a)
    mask = np.zeros((batch, width), bool)
    mask[:, :a] = True
    return padded, mask


# --------------------------------------------------------------------------- acting with a shared policy


def embodiment_inputs(policy: object, kind: str, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One robot's unbatched observation, plus its embodiment index when the policy spans embodiments."""
    embodiments = getattr(policy, "embodiments", None)
    if not embodiments:
        return dict(observation)
    if kind not in embodiments:
        raise ValueError(f"robot kind {kind!r} is not one of the policy's embodiments {list(embodiments)}")
    return {**observation, EMBODIMENT_KEY: np.asarray(embodiments.index(kind), np.int64)}


def fit_action(policy: object, kind: str, action: np.ndarray) -> np.ndarray:
    """Cut a padded action (or chunk) back to this robot kind's action dims."""
    dims = getattr(policy, "action_dims", None)
    if not dims or kind not in dims:
        return action
    return np.asarray(action)[..., : dims[kind]]


# --------------------------------------------------------------------------- plug-in checks at start


def check_plugins(experiments: Sequence[ExperimentConfig], where: str = "experiments[{i}]") -> None:
    """Validate every experiment's algorithm and policy params, and that its algorithm takes a policy choice
    if it makes one (PluginError names experiments[i]..., or `where` with {i} filled in). What needs the robots'
    layout (feature names, statistics sizes) is checked when the learner builds the experiment."""
    from cloud_learner.algorithm import ALGORITHMS
    from user.policy import POLICIES
    from user.registry import PluginError

    for i, exp in enumerate(experiments):
        at = where.format(i=i)
        ALGORITHMS.params(exp.algorithm.kind, exp.algorithm.params, where=f"{at}.algorithm.params")
        if exp.policy is not None:
            POLICIES.params(exp.policy.kind, exp.policy.params, where=f"{at}.policy.params")
            if not takes_policy(ALGORITHMS.get(exp.algorithm.kind).cls):
                raise PluginError(
                    f"{at}.policy: algorithm {exp.algorithm.kind!r} does not take a policy choice "
                    "(drop policy: the algorithm publishes its own)"
                )


def takes_policy(algorithm: type) -> bool:
    """An algorithm takes the experiment's policy choice when its __init__ has a `policy` argument."""
    import inspect

    return "policy" in inspect.signature(algorithm.__init__).parameters


MAX_DEFINITION_BYTES = 64 * 1024


def parse_definition(text: str, name: str | None = None) -> ExperimentConfig:
    """An experiment defined at run time (one `experiments` entry as JSON), checked as the config's are:
    fields, plug-in params, normalize/pretrain, and where given that it is named `name` (as control listed
    it). ValueError names the dotted field under `definition`. Imports the learner's registries (torch)."""
    from pydantic import ValidationError

    from cloud_learner.prepare import check_prepare

    if len(text.encode()) > MAX_DEFINITION_BYTES:
        raise ValueError(f"definition: over {MAX_DEFINITION_BYTES} bytes")
    try:
        exp = ExperimentConfig.model_validate_json(text)
    except ValidationError as exc:
        where = [".".join(["definition", *(str(p) for p in err["loc"])]) + f": {err['msg']}" for err in exc.errors()]
        raise ValueError("; ".join(where)) from None
    if name is not None and exp.name != name:
        raise ValueError(f"definition.name {exp.name!r} is not the experiment's name {name!r}")
    check_plugins([exp], where="definition")
    check_prepare([exp], where="definition")
    return exp
