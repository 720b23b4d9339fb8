"""The learner: one Algorithm per experiment, each sampling only its robots (and, in tables other than its own,
imported robots that fit them), publishing its own weights.

The loop knows no algorithm by name. For each experiment of the stack config it waits until Control
knows robots the experiment's selector picks, derives the `Layout` from their specs, builds the
algorithm (`ALGORITHMS.build`, params checked against its typed model), resumes it from the
experiment's checkpoint directory and publishes version 1 at once (actors get a policy before any
training). An experiment that cannot start (robots of different layouts, params that do not fit them, a
checkpoint this config cannot resume, a published policy that does not fit its robots: checked before the
first publish) is reported failed and writes no checkpoint; the others train. Then:

- async (default): a sampler thread keeps `prefetch_batches` decoded batches ready while the training
  thread updates as fast as it can, bounded by the update-to-data cap (max_updates_per_transition x
  sampleable transitions) so a tiny buffer is not overfitted;
- sync: collect `sync_env_steps` new transitions, pause the experiment's robots (Control PAUSE),
  run `sync_updates` updates, publish, resume; the baseline the asynchronous pipeline is measured against.
  It samples and counts env steps over every replay shard (learner.replay_addrs) as async does.

Control may stop an experiment (`userctl exp stop`): the learner sees it in Control.ListExperiments, polled
with the robots, and pauses that experiment's sampling and training (checkpoint written, state "stopped")
until it is started again. Control unreachable or too old to know experiments: the last answer stands,
and with none every configured experiment trains.

Every `publish_every` updates a weight version goes to the WeightStore under the experiment's name;
every `checkpoint_every` updates, and on shutdown, an atomic checkpoint is written to
`checkpoint_dir/<experiment>/`. A write the disk refuses (ENOSPC) does not stop training: a checkpoint is tried
again at the next interval, a publish whose version mark is refused is skipped (an unmarked number could be reused
after a crash) and tried again at the next one, or while training waits; both are logged once per run of failures
and counted. A sample replay refuses (e.g. robots of different shapes) is an
error: logged, counted and reported in the experiment's status, never read as an empty buffer.
"""

from __future__ import annotations

import ctypes
import dataclasses
import errno
import json
import logging
import queue
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import prometheus_client
import torch

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, BatchRequest, Layout
from cloud_learner.checkpoint import (
    CheckpointError,
    CheckpointWriteError,
    keep_final_checkpoint,
    load_latest,
    read_version_mark,
    save_checkpoint,
    write_version_mark,
)
from cloud_learner.prepare import STAT_FIELDS, check_prepare, normalize_keys, state_stats, with_stats
from cloud_learner.replay_sampler import ShardedSampler, replay_source
from cloud_learner.replay_shm import SharedArrays
from user import rpc
from user.config import ExperimentConfig, StackConfig
from user.experiments import (
    EMBODIMENT_KEY,
    LayoutError,
    assign,
    check_plugins,
    layout_for,
    pad_action,
    parse_definition,
    ready,
    takes_policy,
)
from user.log import kv
from user.policy import POLICIES, PolicyChoice, build_policy, check_fit, placeholders
from user.registry import PluginError
from user.spec import action_dim
from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, replay_pb2, replay_pb2_grpc, robot_pb2
from user.weights import WeightStore
from user.wire import WireError, from_tensor

log = logging.getLogger(__name__)

UPDATES = prometheus_client.Counter("user_learner_updates_total", "Gradient updates", ["experiment"])
UPDATES_PER_S = prometheus_client.Gauge(
    "user_learner_updates_per_second", "Updates per second (last ~2 s)", ["experiment"]
)
WEIGHT_VERSION = prometheus_client.Gauge(
    "user_learner_weight_version", "Latest published weight version", ["experiment"]
)
SCALARS = prometheus_client.Gauge("user_learner_scalar", "Last update's scalars (losses, ...)", ["experiment", "name"])
# A failed experiment trains no more while the others go on: an alert needs a series, not a log line.
EXPERIMENT_FAILED = prometheus_client.Gauge(
    "user_learner_experiment_failed",
    "1 when the learner marked the experiment failed (GetStatus says why), 0 while it runs",
    ["experiment"],
)
BATCH_WAIT = prometheus_client.Histogram(
    "user_learner_batch_wait_seconds",
    "Time the training loop waited for a prefetched batch",
    buckets=(0.0001, 0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1, 5),
)
BUFFER_TRANSITIONS = prometheus_client.Gauge(
    "user_learner_buffer_transitions", "Sampleable transitions of the experiment's robots", ["experiment"]
)
SAMPLE_ERRORS = prometheus_client.Counter(
    "user_learner_sample_errors_total", "Samples replay refused or that did not decode", ["experiment", "reason"]
)
CHECKPOINT_SECONDS = prometheus_client.Histogram(
    "user_learner_checkpoint_seconds", "Time to write a checkpoint", buckets=(0.01, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10)
)
CHECKPOINT_FAILURES = prometheus_client.Counter(
    "user_learner_checkpoint_failures_total",
    "Checkpoints the disk refused (ENOSPC, ...): training goes on, the next interval tries again",
    ["experiment"],
)
VERSION_MARK_FAILURES = prometheus_client.Counter(
    "user_learner_version_mark_failures_total",
    "Publishes skipped because the weight-version mark could not be written (tried again at the next publish)",
    ["experiment"],
)
PRETRAIN_UPDATES = prometheus_client.Gauge(
    "user_learner_pretrain_updates", "Pretraining updates done (experiments[].pretrain)", ["experiment"]
)
PRETRAIN_TARGET = prometheus_client.Gauge(
    "user_learner_pretrain_steps", "Pretraining updates asked for (experiments[].pretrain.steps)", ["experiment"]
)
LOOP_SECONDS = prometheus_client.Counter(
    "user_learner_loop_seconds_total",
    "Wall time of the training thread by phase: update (the algorithm's step), publish, wait_batch (async: "
    "waiting for the sampler), capped (async: at the update-to-data cap), sample (sync: sampling in the loop), "
    "wait_robots (sync: collecting a round while the learner idles)",
    ["experiment", "phase"],
)
CAPPED = prometheus_client.Counter(
    "user_learner_capped_total", "Times training paused at the update-to-data cap (max_updates_per_transition)"
)
# Replay's FAILED_PRECONDITION details that mean "not enough data yet" (waiting, not an error); any other
# FAILED_PRECONDITION (e.g. transitions of different layouts) is an error.
EMPTY_DETAILS = ("no sampleable transitions", "min_size_to_sample")
MAX_MISFIT_ROBOTS = 1024  # WorkerInfo.misfit_robots entries control accepts from one learner
MAX_MISFIT_REASON_CHARS = 200  # of each reason: control sends it down in the robot's hold lease


class LearnerError(RuntimeError):
    """An experiment cannot go on (e.g. a checkpoint for different robots)."""


# --------------------------------------------------------------------------- decoding


def _decode(tensor: Any, what: str) -> np.ndarray:
    try:
        return from_tensor(tensor)
    except WireError as exc:
        raise WireError(f"{what}: {exc}") from None


def _getter(batch: replay_pb2.Batch | SharedArrays) -> Any:
    """name ("action", "observation/<key>", ...) -> decoded array, or None where the batch has none."""
    if isinstance(batch, SharedArrays):  # copied out of a shared-memory slot already
        return batch.get

    def get(name: str) -> np.ndarray | None:
        part, _, key = name.partition("/")
        if key:
            tensors = getattr(batch, part).tensors
            return _decode(tensors[key], f"{part}[{key!r}]") if key in tensors else None
        return _decode(getattr(batch, name), name) if batch.HasField(name) else None

    return get


def decode_arrays(batch: replay_pb2.Batch | SharedArrays, keys: list[str]) -> dict[str, Any]:
    """Replay batch (its proto, or the arrays of a shared-memory slot) -> numpy arrays: observation/next_observation
    dicts for `keys`, action (n, a), reward, terminated, intervention (n,). Images keep their dtype (uint8)."""
    get = _getter(batch)

    def need(name: str) -> np.ndarray:
        arr = get(name)
        if arr is None:
            raise WireError(f"batch lacks {name}")
        return arr

    obs, nxt = {}, {}
    for key in keys:
        now, then = get(f"observation/{key}"), get(f"next_observation/{key}")
        if now is None or then is None:
            raise WireError(f"batch lacks observation[{key!r}]")
        obs[key], nxt[key] = now, then
    action = need("action")
    n = action.shape[0] if action.ndim else 0
    if n < 1:
        raise WireError("empty batch")
    intervention = get("intervention")
    out = {
        "observation": obs,
        "next_observation": nxt,
        "action": action.reshape(n, -1).astype(np.float32, copy=False),
        "reward": need("reward").reshape(n).astype(np.float32, copy=False),
        "terminated": need("terminated").reshape(n).astype(np.float32, copy=False),
        "intervention": intervention.reshape(n).astype(bool) if intervention is not None else np.zeros(n, bool),
    }
    n_steps = get("n_steps")
    if n_steps is not None:  # n-step rows: bootstrap with gamma ** n_steps (fewer at an episode's end)
        out["n_steps"] = n_steps.reshape(n).astype(np.float32, copy=False)
    chunk = get("action_chunk")
    if chunk is not None:  # the next H actions per row (SampleRequest.action_horizon > 1)
        mask = get("chunk_mask")
        if chunk.ndim < 2 or chunk.shape[0] != n or mask is None or mask.shape != chunk.shape[:2]:
            raise WireError(f"action_chunk {list(chunk.shape)} and chunk_mask do not match a batch of {n}")
        out["action_chunk"] = chunk.reshape(n, chunk.shape[1], -1).astype(np.float32, copy=False)
        out["chunk_mask"] = mask.astype(bool, copy=False)
    for key in keys:
        for part in (obs[key], nxt[key]):
            if part.shape[:1] != (n,):
                raise WireError(f"observation[{key!r}] has {part.shape[:1]} rows, the batch has {n}")
    return out


def _check_layout(arrays: dict[str, Any], layout: Layout) -> None:
    n = arrays["action"].shape[0]
    for key, feat in layout.observation.items():
        for part in (arrays["observation"][key], arrays["next_observation"][key]):
            if tuple(part.shape[1:]) != feat.shape:
                raise WireError(
                    f"observation[{key!r}] rows are {list(part.shape[1:])}, the layout has {list(feat.shape)}"
                )
    if arrays["action"].shape != (n, layout.action_dim):
        raise WireError(f"actions are {list(arrays['action'].shape)}, the layout has {layout.action_dim} dims")
    chunk = arrays.get("action_chunk")
    if chunk is not None and chunk.shape[2:] != (layout.action_dim,):
        raise WireError(f"action chunks are {list(chunk.shape)}, the layout has {layout.action_dim} dims")


def _pad(arrays: dict[str, Any], layout: Layout, kind: str) -> dict[str, Any]:
    """One embodiment's arrays -> the shared layout (padded state, one-hot embodiment, action mask)."""
    from user.experiments import pad_observation

    n = arrays["action"].shape[0]
    action, mask = pad_action(arrays["action"], layout.action_dim)
    chunk = arrays.get("action_chunk")
    if chunk is not None:  # pad each action of the chunk alike
        padded, _ = pad_action(chunk.reshape(-1, chunk.shape[-1]), layout.action_dim)
        arrays = {**arrays, "action_chunk": padded.reshape(n, chunk.shape[1], layout.action_dim)}
    return {
        **arrays,
        "observation": pad_observation(layout, kind, arrays["observation"], n),
        "next_observation": pad_observation(layout, kind, arrays["next_observation"], n),
        "action": action,
        "action_mask": mask,
        "embodiment": np.full(n, layout.embodiments.index(kind), np.int64),
    }


def _concat(parts: list[dict[str, Any]]) -> dict[str, Any]:
    if len(parts) == 1:
        return parts[0]
    out: dict[str, Any] = {}
    for key, value in parts[0].items():
        if isinstance(value, dict):
            out[key] = {k: np.concatenate([p[key][k] for p in parts]) for k in value}
        else:
            out[key] = np.concatenate([p[key] for p in parts])
    return out


def to_batch(arrays: dict[str, Any], device: str | torch.device, gamma: float = 1.0) -> Batch:
    """Arrays -> Batch; n-step rows (replay's `n_steps`) get discount gamma ** n_steps for bootstrapping."""

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(device)

    return Batch(
        observation={k: t(v) for k, v in arrays["observation"].items()},
        action=t(arrays["action"]),
        reward=t(arrays["reward"]),
        next_observation={k: t(v) for k, v in arrays["next_observation"].items()},
        terminated=t(arrays["terminated"]),
        intervention=t(arrays["intervention"]),
        embodiment=t(arrays["embodiment"]) if "embodiment" in arrays else None,
        action_mask=t(arrays["action_mask"]) if "action_mask" in arrays else None,
        action_chunk=t(arrays["action_chunk"]) if "action_chunk" in arrays else None,
        chunk_mask=t(arrays["chunk_mask"]) if "chunk_mask" in arrays else None,
        discount=t(np.power(gamma, arrays["n_steps"]).astype(np.float32)) if "n_steps" in arrays else None,
    )


def decode_batch(batch: replay_pb2.Batch, layout: Layout, device: str | torch.device = "cpu") -> Batch:
    """A replay batch of one layout (one embodiment, or robots of equal shape) -> Batch on `device`."""
    arrays = decode_arrays(batch, sorted(layout.observation))
    _check_layout(arrays, layout)
    return to_batch(arrays, device)


# --------------------------------------------------------------------------- checkpoints


def layout_fingerprint(layout: Layout) -> str:
    return json.dumps(_layout_fields(layout), sort_keys=True)


def _layout_fields(layout: Layout) -> dict[str, Any]:
    fields = {
        "observation": {k: [list(f.shape), f.dtype, f.is_image] for k, f in sorted(layout.observation.items())},
        "action_low": [round(float(x), 6) for x in layout.action_low],
        "action_high": [round(float(x), 6) for x in layout.action_high],
        "embodiments": list(layout.embodiments),
    }
    if layout.per_embodiment:  # absent from single-embodiment layouts: their fingerprint is what it always was
        low, high = layout.policy_bounds()
        fields["embodiment_low"] = [[round(float(x), 6) for x in row] for row in low]
        fields["embodiment_high"] = [[round(float(x), 6) for x in row] for row in high]
    return fields


def layout_difference(recorded: object, layout: Layout) -> str:
    """The layout fields a checkpoint's fingerprint differs in from `layout`'s, e.g. "embodiment_low (absent in the
    checkpoint)": a shared experiment checkpointed before per-embodiment action ranges lacks those fields."""
    try:
        old = json.loads(recorded) if isinstance(recorded, str) else {}
    except json.JSONDecodeError:
        old = {}
    new = json.loads(json.dumps(_layout_fields(layout)))  # compared as the checkpoint's JSON reads back
    names = [
        f"{k} (absent in the checkpoint)" if k not in old else f"{k} (absent now)" if k not in new else k
        for k in sorted(set(old) | set(new))
        if old.get(k) != new.get(k)
    ]
    return ", ".join(names) or "the fingerprint"


def trained_with(exp: ExperimentConfig) -> dict[str, Any]:
    """What a checkpoint records of the experiment's config: the algorithm's kind and params and the policy
    choice, each with every default filled in (so `{}` and the defaults spelled out compare equal). Plain JSON
    values: torch.load(weights_only=True) reads them back. The normalization statistics are stored apart."""
    params = ALGORITHMS.params(exp.algorithm.kind, exp.algorithm.params).model_dump(mode="json")
    policy = None
    if exp.policy is not None:
        policy_params = POLICIES.params(exp.policy.kind, exp.policy.params).model_dump(mode="json")
        policy = {"kind": exp.policy.kind, "params": policy_params}
    return {"algorithm": {"kind": exp.algorithm.kind, "params": params}, "policy": policy}


def checkpoint_state(
    algo: Algorithm,
    kind: str,
    weight_version: int,
    layout: Layout,
    extra: dict[str, Any] | None = None,
    config: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Tensors, ints, floats, strings, lists and dicts only, so torch.load(weights_only=True) reads it back.
    `extra`: the learner's own state beside the algorithm's (pretrain progress, normalization statistics);
    `config`: trained_with(experiment), checked against the config on restore."""
    state = {
        "algorithm": algo.state_dict(),
        "kind": kind,
        "weight_version": int(weight_version),
        "updates": int(algo.updates),
        "layout": layout_fingerprint(layout),
        **(extra or {}),
    }
    if config is not None:
        state["trained_with"] = config
    return state


_ELSEWHERE = "use another learner.checkpoint_dir or experiment name"


def _config_differences(stored: dict[str, Any], now: dict[str, Any], at: str, where: object) -> list[str]:
    """One `field: the checkpoint ... the config says ...` per difference that a resume cannot take: the
    algorithm's params outside its `resumable_params`, and the policy choice. Params only one side knows
    (added or retired by a code update) are not compared."""

    def differs(field: str, old: Any, new: Any) -> str:
        return f"{at}.{field}: the checkpoint in {where} was trained with {old!r}, the config says {new!r}"

    out = []
    kind = now["algorithm"]["kind"]
    resumable = ALGORITHMS.get(kind).cls.resumable_params
    old_params, new_params = stored.get("algorithm", {}).get("params", {}), now["algorithm"]["params"]
    for name in sorted(set(old_params) & set(new_params) - resumable):
        if old_params[name] != new_params[name]:
            out.append(differs(f"algorithm.params.{name}", old_params[name], new_params[name]))
    old_policy, new_policy = stored.get("policy"), now["policy"]
    if (old_policy is None) != (new_policy is None) or (old_policy and old_policy["kind"] != new_policy["kind"]):
        out.append(differs("policy", old_policy and old_policy["kind"], new_policy and new_policy["kind"]))
    elif old_policy is not None:
        old_pp, new_pp = old_policy.get("params", {}), new_policy["params"]
        for name in sorted(set(old_pp) & set(new_pp)):
            if old_pp[name] != new_pp[name]:
                out.append(differs(f"policy.params.{name}", old_pp[name], new_pp[name]))
    return out


def check_checkpoint(
    ckpt: dict[str, Any],
    kind: str,
    layout: Layout,
    where: object,
    config: dict[str, Any] | None = None,
    at: str = "experiment",
) -> None:
    """LearnerError naming the field when `ckpt` was not trained by this algorithm, for this layout, with a
    config the experiment's (`config`: trained_with(exp)) may resume from. Checkpoints written before
    `trained_with` was recorded are checked for kind and layout only."""
    if ckpt.get("kind") != kind:
        raise LearnerError(
            f"{at}.algorithm.kind: the checkpoint in {where} was trained with {ckpt.get('kind')!r}, "
            f"the config says {kind!r}; {_ELSEWHERE}"
        )
    if ckpt.get("layout") != layout_fingerprint(layout):
        raise LearnerError(
            f"{at}: the checkpoint in {where} was trained for robots of another layout (differing: "
            f"{layout_difference(ckpt.get('layout'), layout)}): the checkpoint's {ckpt.get('layout')}, the "
            f"experiment's robots give {layout_fingerprint(layout)}; {_ELSEWHERE}"
        )
    stored = ckpt.get("trained_with")
    if stored is not None and config is not None:
        differences = _config_differences(stored, config, at, where)
        if differences:
            raise LearnerError("; ".join([*differences, _ELSEWHERE]))


def restore_checkpoint(
    algo: Algorithm,
    ckpt: dict[str, Any],
    kind: str,
    layout: Layout,
    where: object,
    config: dict[str, Any] | None = None,
    at: str = "experiment",
) -> int:
    """Load `ckpt` after check_checkpoint; returns the weight version. LearnerError when it does not load into
    `algo` (e.g. an old checkpoint of other network widths): nothing of it is half-trained on."""
    check_checkpoint(ckpt, kind, layout, where, config, at)
    try:
        algo.load_state_dict(ckpt["algorithm"])
    except (RuntimeError, KeyError, ValueError, TypeError) as exc:
        first = str(exc).strip().splitlines()
        raise LearnerError(
            f"{at}: the checkpoint in {where} does not fit the {kind!r} the config builds "
            f"({type(exc).__name__}: {' '.join(line.strip() for line in first[:3])}); {_ELSEWHERE}"
        ) from None
    algo.updates = int(ckpt["updates"])
    return max(1, int(ckpt["weight_version"]))


# --------------------------------------------------------------------------- one experiment


@dataclass
class ExperimentState:
    """What GetStatus reports for one experiment; written by its threads, read by RPC threads."""

    name: str
    algorithm: str
    policy_kind: str = ""
    state: str = "waiting_for_robots"
    error: str = ""
    updates: int = 0
    weight_version: int = 0
    updates_per_s: float = 0.0
    buffer_transitions: int = 0
    scalars: dict[str, float] = field(default_factory=dict)
    robot_ids: list[str] = field(default_factory=list)
    sample_errors: int = 0
    env_steps: int = 0
    last_publish_ns: int = 0
    last_update_mono: float = 0.0
    waiting_for: str = ""  # why the last sample gave no batch (replay's words); "" once one does


@dataclass
class Prefetched:
    batch: Batch
    transitions: int


def build_algorithm(
    index: int, exp: ExperimentConfig, layout: Layout, device: str, stats: dict[str, Any] | None = None
) -> Algorithm:
    """ALGORITHMS.build with the experiment's params (plus normalization `stats` as state_mean/state_std);
    the policy choice goes to algorithms that take one."""
    where = f"experiments[{index}]"
    context: dict[str, Any] = {"layout": layout, "device": torch.device(device)}
    entry = ALGORITHMS.get(exp.algorithm.kind, f"{where}.algorithm.kind")
    if exp.policy is not None:
        choice = PolicyChoice(
            exp.policy.kind, POLICIES.params(exp.policy.kind, exp.policy.params, f"{where}.policy.params")
        )
        if not takes_policy(entry.cls):
            raise LearnerError(f"{where}.policy: algorithm {exp.algorithm.kind!r} does not take a policy choice")
        context["policy"] = choice
    params = with_stats(exp.algorithm.params, stats)
    try:
        return ALGORITHMS.build(exp.algorithm.kind, params, where=f"{where}.algorithm.params", **context)
    except (PluginError, LearnerError):
        raise
    except Exception as exc:  # what the params cannot say alone: they do not fit these robots (e.g. features)
        raise LearnerError(
            f"{where}.algorithm.params: {exc}" if isinstance(exc, ValueError) else f"{where}.algorithm: {exc!r}"
        ) from exc


class _WriteFaults:
    """Writes of one kind (checkpoints, version marks) the disk refused: each counted, a run of them logged once
    (a full disk refuses every interval; one line says so, another when a write succeeds again)."""

    def __init__(self, experiment: str, what: str, counter: prometheus_client.Counter) -> None:
        self.experiment, self.what, self.counter = experiment, what, counter
        self.failing = 0  # failures since the last write that succeeded

    def failed(self, exc: CheckpointWriteError, message: str, level: int = logging.WARNING) -> None:
        """Count it; log `message` for the first of a run (and for every error: nothing retries those)."""
        self.counter.labels(self.experiment).inc()
        self.failing += 1
        if self.failing == 1 or level >= logging.ERROR:
            code = errno.errorcode.get(exc.errno, str(exc.errno)) if exc.errno is not None else ""
            fields = kv(experiment=self.experiment, path=str(exc.path), errno=code, error=exc.strerror)
            log.log(level, message, extra=fields)

    def succeeded(self) -> None:
        if self.failing:
            log.info(f"{self.what} written again", extra=kv(experiment=self.experiment, failures=self.failing))
            self.failing = 0


class ExperimentRun:
    """One experiment's algorithm, sampler and training thread."""

    def __init__(self, learner: Learner, index: int, exp: ExperimentConfig, specs: list[robot_pb2.RobotSpec]) -> None:
        self.learner, self.index, self.exp = learner, index, exp
        self.lc = learner.lc
        self.state = learner.experiment_states[exp.name]
        EXPERIMENT_FAILED.labels(exp.name).set(0)
        self.layout = layout_for(exp, specs)
        self.specs = {s.robot_id: s for s in specs}
        self.state.robot_ids = sorted(self.specs)
        self.ckpt_dir = Path(self.lc.checkpoint_dir) / exp.name
        self.at = f"experiments[{index}]"
        self.config = trained_with(exp)  # recorded in each checkpoint, checked against the config on restore
        self.algo = build_algorithm(index, exp, self.layout, self.lc.device)
        # Set once the checkpoint (if any) is in self.algo: before that a checkpoint would save a fresh network
        # over the trained one (`latest` would name it), and after a failed restore it must never be written.
        self._resumed = False
        self._stop = threading.Event()  # this run's threads end (set by the learner's stop, a failure, a removal)
        self._queue: queue.Queue[Prefetched] = queue.Queue(maxsize=self.lc.prefetch_batches)
        self._threads: list[threading.Thread] = []
        self._last_ckpt_updates = -1
        self._lock = threading.Lock()  # robot set changes vs. sampling
        self._tables_warned = False
        self._misfits: dict[str, bytes] = {}  # robot_id -> the spec that did not fit (logged once)
        self._misfit_reasons: dict[str, str] = {}  # robot_id -> why (WorkerInfo.misfit_robots; under _lock)
        self.stopped = threading.Event()  # control stopped the experiment: no sampling, no updates
        self.pretrain_updates = 0  # updates done on experiments[].pretrain.table (checkpointed)
        self.normalization: dict[str, Any] | None = None  # state_mean/state_std the algorithm was built with
        self._fit_checked = False  # the published policy was checked against the layout (before the first publish)
        self._ckpt_faults = _WriteFaults(exp.name, "checkpoint", CHECKPOINT_FAILURES)
        self._mark_faults = _WriteFaults(exp.name, "weight version mark", VERSION_MARK_FAILURES)
        self._owed_version = 0  # a version whose mark the disk refused: published under this number once it can be
        self._retry_at = 0.0  # monotonic time of the next retry of the owed version while training waits

    def set_stopped(self, stopped: bool) -> None:
        if stopped == self.stopped.is_set():
            return
        if stopped:
            self.stopped.set()
            log.info("experiment stopped by control; training pauses", extra=kv(experiment=self.exp.name))
        else:
            self.stopped.clear()
            log.info("experiment started by control; training resumes", extra=kv(experiment=self.exp.name))
        if self.state.state != "failed":
            self.state.state = "stopped" if stopped else "waiting_for_data"

    def _wait_while_stopped(self, checkpoint: bool = True) -> bool:
        """Block while control has the experiment stopped; True if it was stopped. The training thread
        checkpoints at the stop (it is the one updating, so the state is consistent)."""
        if not self.stopped.is_set():
            return False
        if checkpoint:
            self.checkpoint()
        while self.stopped.is_set() and not self._stop.is_set():
            self._stop.wait(0.1)
        return True

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """LearnerError (raised here or, when preparing, reported as this experiment's failure) when the
        checkpoint cannot be resumed with this config: the experiment fails, nothing is overwritten."""
        if self.exp.pretrain is None and self.exp.normalize is None:
            ckpt = self._load_checkpoint()
            stats = self._checkpoint_stats(ckpt)
            if stats is not None:  # normalize dropped from the config: the trained network still needs its inputs
                log.info(
                    "normalization statistics reused from the checkpoint",
                    extra=kv(experiment=self.exp.name, from_table=stats.get("from_table", "")),
                )
                self._rebuild(stats)
            self._run(self._restore(ckpt))
        else:  # statistics and pretraining wait for replay: off the discovery thread
            self.state.state = "preparing"
            self._spawn(self._prepare, "prepare")

    def _load_checkpoint(self) -> dict[str, Any] | None:
        """The newest readable checkpoint, checked against the config before anything is built or computed
        from it (LearnerError naming the field that differs)."""
        try:
            ckpt = load_latest(self.ckpt_dir, map_location=self.lc.device)
        except CheckpointError as exc:
            raise LearnerError(f"{self.at}: {exc}") from None
        if ckpt is not None:
            check_checkpoint(ckpt, self.exp.algorithm.kind, self.layout, self.ckpt_dir, self.config, self.at)
        return ckpt

    def _checkpoint_stats(self, ckpt: dict[str, Any] | None) -> dict[str, Any] | None:
        """The normalization statistics the checkpoint's networks were trained with (None: none). They stay
        whether or not the config still says normalize; statistics given as params too would be two sources."""
        stats = ckpt.get("normalization") if ckpt is not None else None
        given = [f for f in STAT_FIELDS if self.exp.algorithm.params.get(f)]
        if stats is not None and given:
            raise LearnerError(
                f"{self.at}.algorithm.params.{given[0]}: the checkpoint in {self.ckpt_dir} holds the normalization "
                f"statistics its networks were trained with; drop the param or {_ELSEWHERE}"
            )
        return stats

    def _rebuild(self, stats: dict[str, Any]) -> None:
        """The algorithm again, with the normalization statistics as its state_mean/state_std params."""
        self.normalization = stats
        self._resumed = False  # the new algorithm holds nothing of the checkpoint until _restore
        self.algo = build_algorithm(self.index, self.exp, self.layout, self.lc.device, stats)

    def _restore(self, ckpt: dict[str, Any] | None) -> int:
        """Load the checkpoint (if any) into the algorithm; returns the weight version it had published."""
        restored = 0
        if ckpt is not None:
            restored = restore_checkpoint(
                self.algo, ckpt, self.exp.algorithm.kind, self.layout, self.ckpt_dir, self.config, self.at
            )
            self._last_ckpt_updates = int(ckpt["updates"])
            # A checkpoint without pretrain progress but with updates predates pretraining: it is past that.
            past = self._pretrain_steps() if int(ckpt["updates"]) > 0 else 0
            self.pretrain_updates = int(ckpt.get("pretrain_updates", past))
            log.info("resumed", extra=kv(experiment=self.exp.name, updates=self.algo.updates, weight_version=restored))
        self._resumed = True
        self.state.updates = int(self.algo.updates)
        return restored

    def _run(self, restored: int) -> None:
        """Publish the first version of this run and start sampling and training."""
        # Never reuse a published number (the checkpoint may predate the last publishes, e.g. after
        # kill -9): subscribers holding a higher one would reject the new weights.
        self.publish(max(restored, self.state.weight_version, read_version_mark(self.ckpt_dir)) + 1)
        self.state.state = "stopped" if self.stopped.is_set() else "waiting_for_data"
        if self.lc.mode == "async":
            self._spawn(self._sample_loop, "sampler")
            self._spawn(self._train_async, "train")
        else:
            self._spawn(self._train_sync, "train")

    # ------------------------------------------------------------------ before the first version

    def _pretrain_steps(self) -> int:
        return self.exp.pretrain.steps if self.exp.pretrain is not None else 0

    def _prepare(self) -> None:
        """Statistics, then pretraining, then version 1 and the training loops. Until version 1 exists the
        inference service answers "no policy yet" and the robots hold (see docs/notes/core.md). A checkpoint
        this config cannot resume fails this experiment only, as it would at start."""
        try:
            self._prepare_and_run()
        except LearnerError as exc:
            self.fail(exc, stop_learner=False)

    def _prepare_and_run(self) -> None:
        ckpt = self._load_checkpoint()
        stats = self._checkpoint_stats(ckpt)
        norm = self.exp.normalize
        if ckpt is not None and stats is None and norm is not None and int(ckpt["updates"]) > 0:
            raise LearnerError(
                f"{self.ckpt_dir} was trained without normalization statistics; with experiments[{self.index}]."
                "normalize set its networks would see other inputs: use another checkpoint_dir or drop normalize"
            )
        with rpc.make_channel(self.lc.replay_addr, self.learner.cfg.auth) as channel:
            replay = replay_source(self.lc, self.learner.cfg.auth, channel)
            try:
                if stats is None and norm is not None:
                    if norm.from_table == self.exp.table:  # the robots' own steps: they act with the initial policy
                        self._run_initial(ckpt)
                    stats = self._compute_stats(replay)
                    if stats is None:  # stopping
                        return
                if stats is not None:
                    self._rebuild(stats)
                restored = self._restore(ckpt)
                if self.pretrain_updates < self._pretrain_steps():
                    self._pretrain(replay)
            finally:
                if isinstance(replay, ShardedSampler):
                    replay.close()
        if not self._stop.is_set():
            self._run(restored)

    def _run_initial(self, ckpt: dict[str, Any] | None) -> None:
        """normalize from the robots' own table: publish the initial policy so they can collect min_steps."""
        self.publish(max(self._restore(ckpt), read_version_mark(self.ckpt_dir)) + 1)

    def _human_tables(self, req: BatchRequest) -> list[str]:
        """The tables whose rows replay flags intervention: req's, less the pretrain table of an experiment that
        says its rows are no demonstrator's (pretrain.human: false, e.g. policy rollouts kept in "demos")."""
        pre = self.exp.pretrain
        if pre is None or pre.human:
            return list(req.human_tables)
        return [t for t in req.human_tables if t != pre.table]

    def _table_request(self, table: str, req: BatchRequest) -> replay_pb2.SampleRequest:
        """A sample of one table: the experiment's own (its robots) or a pre-filled one (every row of it:
        imported demos carry their dataset's robot id)."""
        request = replay_pb2.SampleRequest(batch_size=req.batch_size, encoded_frames=self.lc.replay_encoded_frames)
        if table == self.exp.table:
            with self._lock:
                request.robot_ids.extend(sorted(self.specs))
        if table != "online":
            request.tables[table] = 1.0
        request.human_tables.extend(self._human_tables(req))
        if req.n_step > 1:
            request.n_step, request.gamma = req.n_step, req.gamma
        if req.action_horizon > 1:
            request.action_horizon = req.action_horizon
        return request

    def _sample_table(
        self, replay: Any, table: str, req: BatchRequest, keys: list[str]
    ) -> tuple[dict[str, Any] | None, int]:
        """(decoded arrays of `keys`, transitions the table holds); (None, 0) while empty or on an error."""
        try:
            resp = replay.Sample(self._table_request(table, req), timeout=self.lc.rpc_timeout_s)
        except grpc.RpcError as err:
            details = err.details() if hasattr(err, "details") else ""
            if not (
                err.code() == grpc.StatusCode.FAILED_PRECONDITION and any(d in (details or "") for d in EMPTY_DETAILS)
            ):
                self._sample_error(err.code().name.lower(), f"{err.code().name}: {details}")
            return None, 0
        size = int(resp.table_transitions.get(table, resp.transitions))
        try:
            arrays = decode_arrays(resp.batch, keys)
            _check_layout(arrays, self._sub_layout(keys))
        except WireError as exc:
            self._sample_error("decode", f"{table}: {exc}")
            return None, size
        return arrays, size

    def _sub_layout(self, keys: list[str]) -> Layout:
        return Layout({k: self.layout.observation[k] for k in keys}, self.layout.action_low, self.layout.action_high)

    def _compute_stats(self, replay: Any) -> dict[str, Any] | None:
        """Mean and std of the float state features over `samples` transitions of normalize.from_table."""
        norm = self.exp.normalize
        assert norm is not None
        keys = normalize_keys(self.layout, norm.keys)
        self.state.state = "normalizing"
        rows: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        got, backoff = 0, rpc.Backoff(initial_s=0.1, max_s=2.0)
        req = BatchRequest(batch_size=min(256, norm.samples))
        while got < norm.samples:
            if self._stop.is_set():
                return None
            arrays, size = self._sample_table(replay, norm.from_table, req, keys)
            self.state.scalars = {"normalize_samples": float(got), "normalize_table_transitions": float(size)}
            if arrays is None or size < norm.min_steps:
                self._retry_owed()  # the robots' own steps need the initial policy
                backoff.sleep(self._stop)
                continue
            backoff.reset()
            for k in keys:
                rows[k].append(arrays["observation"][k])
            got += len(arrays["action"])
        stats = state_stats({k: np.concatenate(v)[: norm.samples] for k, v in rows.items()}, norm.min_std)
        log.info(
            "normalization statistics",
            extra=kv(experiment=self.exp.name, table=norm.from_table, samples=got, **{"keys": keys}),
        )
        return {**stats, "from_table": norm.from_table, "samples": int(got)}

    def _pretrain(self, replay: Any) -> None:
        """pretrain.steps updates on pretrain.table; checkpointed every checkpoint_every and at the end, so a
        restart resumes the count and a finished pretraining is never redone."""
        pre = self.exp.pretrain
        assert pre is not None
        # human: replay flags every row intervention, so SAC's/RLPD's BC term and BC's only_interventions count them
        human = (pre.table,) if pre.human else ()
        req = dataclasses.replace(self.algo.batch_request(), tables={pre.table: 1.0}, human_tables=human)
        keys = sorted(self.layout.observation)
        PRETRAIN_TARGET.labels(self.exp.name).set(pre.steps)
        backoff = rpc.Backoff(initial_s=0.1, max_s=2.0)
        log.info(
            "pretraining",
            extra=kv(experiment=self.exp.name, table=pre.table, done=self.pretrain_updates, steps=pre.steps),
        )
        while self.pretrain_updates < pre.steps and not self._stop.is_set():
            if self._wait_while_stopped():
                continue
            arrays, size = self._sample_table(replay, pre.table, req, keys)
            if arrays is None or size < pre.min_size:
                self.state.state = "pretraining"
                self.state.scalars = {**self._pretrain_scalars(), "pretrain_table_transitions": float(size)}
                backoff.sleep(self._stop)
                continue
            backoff.reset()
            self.pretrain_updates += 1
            self.update(to_batch(arrays, self.lc.device, req.gamma), publish=False, state="pretraining")
            PRETRAIN_UPDATES.labels(self.exp.name).set(self.pretrain_updates)
        if self.pretrain_updates >= pre.steps:
            log.info(
                "pretraining done", extra=kv(experiment=self.exp.name, updates=self.algo.updates, **self.state.scalars)
            )
            self.checkpoint()

    def _pretrain_scalars(self) -> dict[str, float]:
        if self.exp.pretrain is None:
            return {}
        return {"pretrain_updates": float(self.pretrain_updates), "pretrain_steps": float(self.exp.pretrain.steps)}

    def _spawn(self, target: Any, what: str) -> None:
        def run() -> None:
            _name_os_thread(what)  # per-thread CPU and run-queue time in /proc/<pid>/task (benchmarks, top -H)
            try:
                target()
            except BaseException as exc:
                self.fail(exc)

        thread = threading.Thread(target=run, name=f"learner-{self.exp.name}-{what}", daemon=True)
        thread.start()
        self._threads.append(thread)

    def fail(self, exc: BaseException, stop_learner: bool = True) -> None:
        """This experiment fails. While training, the learner stops too (the service reports it failed); one that
        cannot start (`stop_learner` False: its checkpoint does not fit the config) fails alone, as at start."""
        self.state.state = "failed"
        self.state.error = str(exc) if isinstance(exc, LearnerError) else f"{type(exc).__name__}: {exc}"
        EXPERIMENT_FAILED.labels(self.exp.name).set(1)
        self._stop.set()
        if not stop_learner:
            log.error("experiment cannot start", extra=kv(experiment=self.exp.name, error=self.state.error))
            return
        log.error("experiment failed", exc_info=exc, extra=kv(experiment=self.exp.name))
        self.learner.error = self.learner.error or exc
        self.learner._stop.set()

    def halt(self) -> None:
        """End this run's threads (join() waits for them)."""
        self._stop.set()

    def join(self, timeout: float) -> None:
        for thread in self._threads:
            thread.join(timeout)

    def alive(self) -> bool:
        """Whether a thread of this run still runs (and may still write a checkpoint or version mark)."""
        return any(thread.is_alive() for thread in self._threads)

    def add_robot(self, spec: robot_pb2.RobotSpec) -> None:
        """A robot joined after the layout was fixed: it trains here only if it fits the layout."""
        why = (
            f"robot {spec.robot_id} ({spec.kind}) does not fit the layout the learner fixed for it (other "
            "observations, actions or embodiments); nothing trains on its steps"
        )
        try:
            fits = layout_fingerprint(layout_for(self.exp, [*self.specs.values(), spec])) == layout_fingerprint(
                self.layout
            )
        except LayoutError as exc:
            fits, why = False, str(exc).removeprefix(f"experiment {self.exp.name}: ")
        if not fits:
            with self._lock:  # control holds the robot while the report names it (its steps would be wasted)
                self._misfit_reasons[spec.robot_id] = why[:MAX_MISFIT_REASON_CHARS]
            seen = spec.SerializeToString(deterministic=True)
            if self._misfits.get(spec.robot_id) != seen:  # once per robot and spec, not at every poll
                self._misfits[spec.robot_id] = seen
                log.error(
                    "robot does not fit the experiment's layout; not trained",
                    extra=kv(experiment=self.exp.name, robot_id=spec.robot_id, kind=spec.kind),
                )
            return
        with self._lock:
            self.specs[spec.robot_id] = spec
            self.state.robot_ids = sorted(self.specs)
            self._misfit_reasons.pop(spec.robot_id, None)  # its spec changed to one that fits
        log.info("robot joined", extra=kv(experiment=self.exp.name, robot_id=spec.robot_id))

    def keep_misfits(self, selected: set[str]) -> None:
        """Forget misfits this experiment's selector no longer takes (removed, or now another experiment's)."""
        with self._lock:
            self._misfit_reasons = {rid: why for rid, why in self._misfit_reasons.items() if rid in selected}

    def misfit_robots(self) -> dict[str, str]:
        """robot_id -> why it does not fit this experiment's layout (WorkerInfo.misfit_robots)."""
        with self._lock:
            return dict(self._misfit_reasons)

    # ------------------------------------------------------------------ sampling

    _table_robots: _TableRobots | None = None  # made by the first sample asking for other tables (demos)

    def _groups(self) -> list[tuple[str, list[str]]]:
        """(embodiment kind, robot ids) to sample separately: one group unless the embodiment is shared."""
        with self._lock:
            specs = list(self.specs.values())
        if not self.exp.shared_embodiment:
            return [("", sorted(s.robot_id for s in specs))]
        kinds: dict[str, list[str]] = {}
        for s in specs:
            kinds.setdefault(s.kind, []).append(s.robot_id)
        return sorted((k, sorted(v)) for k, v in kinds.items())

    def _request_tables(self, req: BatchRequest) -> dict[str, float]:
        """The request's table shares. An algorithm's "online" share (its default, or RLPD's half) is the
        experiment's own table, the one its robots fill; "online" alone is no tables at all (uniform over every
        transition)."""
        tables = dict(req.tables)
        if "online" in tables and self.exp.table != "online":
            share = tables.pop("online")
            tables[self.exp.table] = tables.get(self.exp.table, 0.0) + share
        return {} if tables == {"online": 1.0} else tables

    def _request(
        self, batch_size: int, robot_ids: list[str], req: BatchRequest, demo_robots: list[str] | tuple[str, ...] = ()
    ) -> replay_pb2.SampleRequest:
        """One group's sample: its robots; the request's other tables (demos, interventions) also over
        `demo_robots`, robots of theirs that fit the group (imported demos under their dataset's robot id)."""
        request = replay_pb2.SampleRequest(
            batch_size=batch_size, robot_ids=robot_ids, encoded_frames=self.lc.replay_encoded_frames
        )
        if req.n_step > 1:  # replay sums the discounted rewards; the batch says how many steps each row holds
            request.n_step, request.gamma = req.n_step, req.gamma
        if req.action_horizon > 1:  # replay assembles each row's next H actions (action-chunking policies)
            request.action_horizon = req.action_horizon
        request.human_tables.extend(self._human_tables(req))  # replay flags their rows intervention (imported demos)
        if "tables" in replay_pb2.SampleRequest.DESCRIPTOR.fields_by_name:  # replay with tables (RLPD's shares)
            try:
                request.tables.update(self._request_tables(req))  # type: ignore[attr-defined]
            except (AttributeError, TypeError, ValueError) as exc:
                if not self._tables_warned:
                    self._tables_warned = True
                    log.warning("replay tables not requested", extra=kv(experiment=self.exp.name, error=str(exc)))
            if demo_robots:  # the own table stays the group's robots'
                ids = sorted({*robot_ids, *demo_robots})
                for table in request.tables:
                    if table != self.exp.table:
                        request.table_robot_ids[table].ids.extend(ids)
        return request

    def _demo_robots(self, stub: Any, req: BatchRequest, groups: list[tuple[str, list[str]]]) -> dict[str, list[str]]:
        """kind -> robots of the request's other tables whose stored spec fits that group as its robots do (imported
        demos under their dataset's robot id), as of replay's last Stats: read in the background every ~10 s."""
        other = tuple(sorted(t for t in self._request_tables(req) if t != self.exp.table))
        if not other:
            return {}
        if self._table_robots is None:
            self._table_robots = _TableRobots(self.exp.name)
        return self._table_robots.fitting(stub, other, lambda: self._fit_context(groups), self.lc.rpc_timeout_s)

    def _fit_context(
        self, groups: list[tuple[str, list[str]]]
    ) -> tuple[dict[str, robot_pb2.RobotSpec], set[str], dict[str, str]]:
        """(kind -> a spec of that group's robots, this experiment's robots, robot -> the other experiment it is in)."""
        with self._lock:
            mine = dict(self.specs)
        runs = [(name, list(run.specs)) for name, run in list(self.learner.runs.items()) if name != self.exp.name]
        others = {rid: name for name, ids in runs for rid in ids}
        return {kind: mine[ids[0]] for kind, ids in groups}, set(mine), others

    def sample_once(self, stub: replay_pb2_grpc.ReplayStub) -> Prefetched | None:
        """One batch for the algorithm, or None (empty buffer or an error, already logged and counted)."""
        req = self.algo.batch_request()
        groups = [g for g in self._groups() if g[1]]
        if not groups:
            return None
        demos = self._demo_robots(stub, req, groups)
        share = -(-req.batch_size // len(groups))  # equal share per embodiment (ceil)
        parts, transitions = [], 0
        for kind, robot_ids in groups:
            try:
                request = self._request(share, robot_ids, req, demos.get(kind, ()))
                resp = stub.Sample(request, timeout=self.lc.rpc_timeout_s)
            except grpc.RpcError as err:
                details = err.details() if hasattr(err, "details") else ""
                if err.code() == grpc.StatusCode.FAILED_PRECONDITION and any(
                    d in (details or "") for d in EMPTY_DETAILS
                ):
                    self.state.waiting_for = details or "data"
                    return None
                self._sample_error(err.code().name.lower(), f"{err.code().name}: {details}")
                return None
            transitions += int(resp.transitions)
            try:
                arrays = decode_arrays(resp.batch, sorted(k for k in self.layout.observation if k != EMBODIMENT_KEY))
                if self.exp.shared_embodiment:
                    arrays = _pad(arrays, self.layout, kind)
                _check_layout(arrays, self.layout)
            except (WireError, LayoutError) as exc:
                self._sample_error("decode", str(exc))
                return None
            parts.append(arrays)
        self._set_transitions(transitions)
        self.state.waiting_for = ""
        return Prefetched(to_batch(_concat(parts), self.lc.device, req.gamma), transitions)

    def _sample_error(self, reason: str, message: str) -> None:
        self.state.waiting_for = f"sample refused: {message}"
        self.state.sample_errors += 1
        SAMPLE_ERRORS.labels(self.exp.name, reason).inc()
        log.error("sample failed", extra=kv(experiment=self.exp.name, reason=reason, error=message))

    def _set_transitions(self, n: int) -> None:
        self.state.buffer_transitions = n
        BUFFER_TRANSITIONS.labels(self.exp.name).set(n)

    def _sample_loop(self) -> None:
        backoff = rpc.Backoff(initial_s=0.1, max_s=5.0)
        with rpc.make_channel(self.lc.replay_addr, self.learner.cfg.auth) as channel:
            stub = replay_source(self.lc, self.learner.cfg.auth, channel)  # one replay, or shards
            while not self._stop.is_set():
                if self._wait_while_stopped(checkpoint=False):
                    continue
                item = self.sample_once(stub)
                if item is None:
                    backoff.sleep(self._stop)
                    continue
                backoff.reset()
                if item.transitions < self.lc.min_transitions:
                    self._stop.wait(0.5)
                    continue
                while not self._stop.is_set():
                    try:
                        self._queue.put(item, timeout=0.5)
                        break
                    except queue.Full:
                        continue

    # ------------------------------------------------------------------ training

    def _train_async(self) -> None:
        rate = _Rate(self.algo.updates)
        while not self._stop.is_set():
            if self._wait_while_stopped():
                self._drain()  # batches sampled before the stop are stale
                continue
            start = time.perf_counter()
            try:
                item = self._queue.get(timeout=0.5)
            except queue.Empty:
                self._phase("wait_batch", start)
                self._retry_owed()
                continue
            BATCH_WAIT.observe(self._phase("wait_batch", start))
            if self.algo.updates - self.pretrain_updates >= self.lc.max_updates_per_transition * item.transitions:
                CAPPED.inc()  # at the update-to-data cap: drop this (stale) batch and let more data arrive
                start = time.perf_counter()
                self._stop.wait(0.1)
                self._phase("capped", start)
                continue
            self.update(item.batch)
            self._rate(rate)

    def _drain(self) -> None:
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                return

    def _train_sync(self) -> None:
        """Collect K new transitions, pause the robots, U updates, publish, resume: in turn."""
        rate = _Rate(self.algo.updates)
        with (
            rpc.make_channel(self.lc.replay_addr, self.learner.cfg.auth) as rch,
            rpc.make_channel(self.lc.control_addr, self.learner.cfg.auth) as cch,
        ):
            replay = replay_source(self.lc, self.learner.cfg.auth, rch)  # one replay, or every shard
            try:
                self._sync_rounds(replay, control_pb2_grpc.ControlStub(cch), rate)
            finally:
                if isinstance(replay, ShardedSampler):
                    replay.close()

    def _sync_rounds(
        self, replay: replay_pb2_grpc.ReplayStub | ShardedSampler, control: control_pb2_grpc.ControlStub, rate: _Rate
    ) -> None:
        seen = 0
        while not self._stop.is_set():
            if self._wait_while_stopped():
                seen = self._env_steps(replay)  # steps taken before the stop are not this round's
                continue
            self._command(control, control_pb2.COMMAND_KIND_RESUME)
            target = max(seen + self.lc.sync_env_steps, self.lc.min_transitions)
            start = time.perf_counter()
            while not self._stop.is_set() and not self.stopped.is_set() and self._env_steps(replay) < target:
                self._retry_owed()
                self._stop.wait(0.05)
            self._command(control, control_pb2.COMMAND_KIND_PAUSE)
            seen = self._env_steps(replay)
            self._phase("wait_robots", start)
            done = 0
            while done < self.lc.sync_updates and not self._stop.is_set() and not self.stopped.is_set():
                start = time.perf_counter()
                item = self.sample_once(replay)
                if item is None:
                    self._stop.wait(0.1)
                    self._phase("sample", start)
                    continue
                self._phase("sample", start)
                self.update(item.batch, publish=False)
                done += 1
                self._rate(rate)
            if not self._stop.is_set():
                self.publish(self._next_version())
        self._command(control, control_pb2.COMMAND_KIND_RESUME)

    def _env_steps(self, replay: replay_pb2_grpc.ReplayStub | ShardedSampler) -> int:
        try:
            stats = replay.Stats(replay_pb2.StatsRequest(), timeout=self.lc.rpc_timeout_s)
        except grpc.RpcError:
            return self.state.env_steps
        with self._lock:
            ids = list(self.specs)
        self.state.env_steps = int(sum(stats.steps_per_robot.get(r, 0) for r in ids))
        return self.state.env_steps

    def _command(self, control: control_pb2_grpc.ControlStub, kind: int) -> None:
        with self._lock:
            ids = list(self.specs)
        for rid in ids:
            cmd = control_pb2.Command(command_id=f"{self.exp.name}-{time.time_ns()}", kind=kind, robot_id=rid)
            try:
                control.SendCommand(control_pb2.SendCommandRequest(command=cmd), timeout=self.lc.rpc_timeout_s)
            except grpc.RpcError as err:
                log.warning("command failed", extra=kv(robot_id=rid, code=str(err.code())))

    def _rate(self, rate: _Rate) -> None:
        value = rate.tick(self.algo.updates)
        if value is not None:
            self.state.updates_per_s = value
            UPDATES_PER_S.labels(self.exp.name).set(value)

    def _phase(self, phase: str, start: float) -> float:
        """Count the wall time since `start` to the training thread's `phase`; returns it."""
        seconds = time.perf_counter() - start
        LOOP_SECONDS.labels(self.exp.name, phase).inc(seconds)
        return seconds

    def update(self, batch: Batch, publish: bool = True, state: str = "training") -> None:
        start = time.perf_counter()
        scalars = self.algo.update(batch)
        self._phase("update", start)
        st = self.state
        st.updates = int(self.algo.updates)
        st.scalars = {**{k: float(v) for k, v in scalars.items()}, **self._pretrain_scalars()}
        st.state, st.last_update_mono = "stopped" if self.stopped.is_set() else state, time.monotonic()
        UPDATES.labels(self.exp.name).inc()
        for name, value in st.scalars.items():
            SCALARS.labels(self.exp.name, name).set(value)
        if publish and st.updates % self.lc.publish_every == 0:
            self.publish(self._next_version())
        if st.updates % self.lc.checkpoint_every == 0:
            self.checkpoint()

    def publish(self, version: int) -> None:
        start = time.perf_counter()
        try:
            self._publish(version)
        finally:
            self._phase("publish", start)

    def _publish(self, version: int) -> None:
        if self.learner.store.dropped(self.exp.name):  # removed by control while this thread ran: nothing to publish
            return
        spec, tensors = self.algo.policy()
        if self.exp.shared_embodiment:  # actors pad per robot kind; see user/policies/padded.py
            from user.policies.padded import padded_spec

            widths = {
                k: int(f.shape[0]) for k, f in self.layout.observation.items() if not f.is_image and k != EMBODIMENT_KEY
            }
            with self._lock:
                dims = {s.kind: action_dim(s) for s in self.specs.values()}
            spec = padded_spec(spec, widths, {kind: dims[kind] for kind in self.layout.embodiments})
        if not self._fit_checked:  # a policy that cannot drive these robots fails the experiment, never published
            self._check_fit(spec, tensors, version)
            self._fit_checked = True
        try:
            write_version_mark(self.ckpt_dir, version)  # before anyone can see it
        except CheckpointWriteError as exc:
            # Unmarked, a restart could give this number to other weights: not published, tried again later.
            self._owed_version = version
            self._mark_faults.failed(exc, "weight version mark not written; version not published, tried again later")
            return
        self._mark_faults.succeeded()
        self._owed_version = 0
        if self.learner.store.publish(version, spec, tensors, int(self.algo.updates), experiment=self.exp.name) is None:
            return  # removed meanwhile: refused, and its metric series stay gone
        st = self.state
        st.weight_version, st.policy_kind, st.last_publish_ns = version, spec.kind, time.time_ns()
        WEIGHT_VERSION.labels(self.exp.name).set(version)
        # INFO for the first version, then DEBUG and a line a minute: one per version was ~110 MB a day per experiment
        self.learner.store.publish_log.log(
            log, self.exp.name, experiment=self.exp.name, version=version, updates=self.algo.updates
        )

    def _check_fit(self, spec: learner_pb2.PolicySpec, tensors: dict[str, np.ndarray], version: int) -> None:
        """LearnerError naming the experiment and the mismatch unless the policy the algorithm returns reads only
        features of this experiment's layout and acts with its action size (built once, on the CPU)."""
        features = {k: (f.shape, f.dtype) for k, f in self.layout.observation.items()}
        try:
            policy = build_policy(spec, tensors, version, "cpu")
            check_fit(policy, placeholders(features), self.layout.action_dim)
        except Exception as exc:  # a plug-in policy that cannot even be built from its spec fits nothing either
            why = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
            raise LearnerError(
                f"experiment {self.exp.name}: the {spec.kind!r} policy that algorithm {self.exp.algorithm.kind!r} "
                f"publishes does not fit its robots: {why}"
            ) from None

    def _next_version(self) -> int:
        """The number the next publish takes: one the mark refused (never seen by anyone), else the next one."""
        return self._owed_version or self.state.weight_version + 1

    def _retry_owed(self) -> None:
        """While training waits (e.g. for robots that have no policy because the first publish was refused), try
        the owed version again about once a second: without it no update may ever come to publish it."""
        now = time.monotonic()
        if self._owed_version and now >= self._retry_at:
            self._retry_at = now + 1.0
            self.publish(self._next_version())

    def checkpoint(self, final: bool = False) -> None:
        """Write a checkpoint unless nothing changed. One the disk refuses is logged (an error if `final`: the run
        ends on the previous one, which stays loadable) and counted; training goes on."""
        updates = int(self.algo.updates)
        if not self._resumed or updates == self._last_ckpt_updates:
            return
        start = time.perf_counter()
        extra: dict[str, Any] = {"pretrain_updates": int(self.pretrain_updates)}
        if self.normalization is not None:
            extra["normalization"] = self.normalization
        kind, version = self.exp.algorithm.kind, self.state.weight_version
        state = checkpoint_state(self.algo, kind, version, self.layout, extra, self.config)
        try:
            save_checkpoint(self.ckpt_dir, state)
        except CheckpointWriteError as exc:
            # _last_ckpt_updates stays: the next interval (or stop) tries again.
            if final:
                self._ckpt_faults.failed(exc, "final checkpoint not written; the previous one stays", logging.ERROR)
            else:
                self._ckpt_faults.failed(exc, "checkpoint not written; training goes on, retried at the next interval")
            return
        self._ckpt_faults.succeeded()
        self._last_ckpt_updates = updates
        CHECKPOINT_SECONDS.observe(time.perf_counter() - start)


def _name_os_thread(name: str) -> None:
    """Give the calling thread its name at the OS level too (Linux; 15 bytes), where ps/top/proc show it."""
    if sys.platform != "linux":
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)  # 15 = PR_SET_NAME
    except (OSError, AttributeError):
        pass


class _Rate:
    """Updates per second over windows of >= 2 s."""

    def __init__(self, count: int) -> None:
        self.t, self.n = time.monotonic(), count

    def tick(self, count: int) -> float | None:
        now = time.monotonic()
        if now - self.t < 2.0:
            return None
        value = (count - self.n) / (now - self.t)
        self.t, self.n = now, count
        return value


# --------------------------------------------------------------------------- the learner


class Learner:
    """start() finds robots and runs every experiment in threads; stop() ends them and writes final checkpoints."""

    def __init__(self, cfg: StackConfig, store: WeightStore) -> None:
        self.cfg, self.lc = cfg, cfg.learner
        self.store = store
        self.experiments = cfg.resolved_experiments()
        check_plugins(self.experiments)  # a typo in a param fails here, naming experiments[i]...
        check_prepare(self.experiments)
        self.experiment_states = {
            e.name: ExperimentState(e.name, e.algorithm.kind, policy_kind=e.policy.kind if e.policy else "")
            for e in self.experiments
        }
        self.runs: dict[str, ExperimentRun] = {}
        self.stopped_experiments: set[str] = set()  # by control (Control.ListExperiments)
        self.defined: set[str] = set()  # experiments added from control's definitions (Control.DefineExperiment)
        self.experiment_polls = 0  # answers from control so far
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> Learner:
        self._thread = threading.Thread(target=self._main, name="learner", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 60.0) -> bool:
        """End training and write the final checkpoints. True once no thread of this learner runs any more, so
        none can write to checkpoint_dir (False: one is still stuck after `timeout`)."""
        self._stop.set()
        deadline = time.monotonic() + timeout
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                return False
        for run in self.runs.values():  # the main thread gave each rpc_timeout_s + 1; a slow update may take longer
            run.join(max(0.0, deadline - time.monotonic()))
        return not any(run.alive() for run in self.runs.values())

    def preparing(self) -> list[str]:
        """Experiments whose robots should hold (WorkerInfo.preparing): no version published yet while
        normalizing from, or pretraining on, a pre-filled table. Control leases them a hold till then."""
        return sorted(
            e.name
            for e in self.experiments
            if (e.pretrain is not None or (e.normalize is not None and e.normalize.from_table != e.table))
            and self.experiment_states[e.name].weight_version == 0
            and self.experiment_states[e.name].state != "failed"
            and not self._stop.is_set()
        )

    def misfit_robots(self) -> dict[str, str]:
        """Robots an experiment's selector takes that do not fit the layout fixed for it, with why
        (WorkerInfo.misfit_robots): control holds them, as nothing trains on their steps. Bounded, by id."""
        out: dict[str, str] = {}
        for run in list(self.runs.values()):  # replaced, not mutated, by the discover thread
            if isinstance(run, ExperimentRun):
                out.update(run.misfit_robots())
        return dict(sorted(out.items())[:MAX_MISFIT_ROBOTS])

    @property
    def failed(self) -> bool:
        return self.error is not None

    @property
    def training(self) -> bool:
        now = time.monotonic()
        return any(s.last_update_mono > 0 and now - s.last_update_mono < 2.0 for s in self.experiment_states.values())

    def _main(self) -> None:
        torch.manual_seed(self.lc.seed)
        try:
            self._discover_loop()
        except BaseException as exc:
            self.error = exc
            log.exception("learner failed")
        finally:
            self._stop.set()
            for run in self.runs.values():
                run.halt()
            for run in self.runs.values():
                run.join(self.lc.rpc_timeout_s + 1)
            for run in self.runs.values():
                if run.state.state != "failed":
                    run.checkpoint(final=True)

    def _discover_loop(self) -> None:
        """Poll Control: start each experiment once its robots are known; add robots that join later."""
        backoff = rpc.Backoff(initial_s=0.2, max_s=2.0)
        with rpc.make_channel(self.lc.control_addr, self.cfg.auth) as channel:
            stub = control_pb2_grpc.ControlStub(channel)
            while not self._stop.is_set():
                try:
                    resp = stub.ListRobots(
                        control_pb2.ListRobotsRequest(include_offline=True, without_episodes=True),
                        timeout=self.lc.rpc_timeout_s,
                    )
                except grpc.RpcError as err:
                    log.warning("ListRobots failed", extra=kv(addr=self.lc.control_addr, code=str(err.code())))
                    backoff.sleep(self._stop)
                    continue
                self._on_robots([info.spec for info in resp.robots])
                self._poll_experiments(stub)
                if not backoff.sleep(self._stop):
                    break

    def _poll_experiments(self, stub: control_pb2_grpc.ControlStub) -> None:
        """Which experiments control has stopped; any failure keeps the last answer (none: all train)."""
        try:
            resp = stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=self.lc.rpc_timeout_s)
        except grpc.RpcError as err:
            if err.code() != grpc.StatusCode.UNIMPLEMENTED:  # an older control has no experiments
                log.warning("ListExperiments failed", extra=kv(addr=self.lc.control_addr, code=str(err.code())))
            return
        self._add_defined([e for e in resp.experiments if e.defined_at_runtime])
        self._drop_removed({e.name for e in resp.experiments})
        self.stopped_experiments = {e.name for e in resp.experiments if e.state == control_pb2.EXPERIMENT_STATE_STOPPED}
        self.experiment_polls += 1
        for name, run in self.runs.items():
            if isinstance(run, ExperimentRun):
                run.set_stopped(name in self.stopped_experiments)

    def _add_defined(self, infos: list[control_pb2.ExperimentInfo]) -> None:
        """Experiments defined at run time (Control.DefineExperiment) join after the config's, in control's order;
        one whose definition does not check here is reported failed, never trained."""
        for info in infos:
            if info.name in self.experiment_states:
                continue
            try:
                exp = parse_definition(info.definition_json, info.name)
            except ValueError as exc:
                log.error("a defined experiment cannot train", extra=kv(experiment=info.name, error=str(exc)))
                failed = ExperimentState(info.name, "", state="failed", error=str(exc))
                EXPERIMENT_FAILED.labels(info.name).set(1)
                self.experiment_states = {**self.experiment_states, info.name: failed}
                self.defined.add(info.name)
                continue
            log.info("experiment defined at run time", extra=kv(experiment=exp.name, algorithm=exp.algorithm.kind))
            state = ExperimentState(exp.name, exp.algorithm.kind, policy_kind=exp.policy.kind if exp.policy else "")
            # Both replaced, not mutated (RPC and report threads iterate them); the state first, as runs look it up.
            self.experiment_states = {**self.experiment_states, exp.name: state}
            self.experiments = [*self.experiments, exp]
            self.defined.add(exp.name)

    def _drop_removed(self, listed: set[str]) -> None:
        """Experiments defined at run time that control lists no more (Control.RemoveExperiment) stop here: their
        threads end and their final checkpoint alone stays on disk (the name is never defined again). Nothing else of
        them stays till the learner exits: their weights leave memory and shared memory (their weight streams end
        NOT_FOUND) and their metric series go."""
        series = [UPDATES, UPDATES_PER_S, WEIGHT_VERSION, SCALARS, EXPERIMENT_FAILED, BUFFER_TRANSITIONS, SAMPLE_ERRORS]
        series += [CHECKPOINT_FAILURES, VERSION_MARK_FAILURES, PRETRAIN_UPDATES, PRETRAIN_TARGET, LOOP_SECONDS]
        for name in sorted(self.defined - listed):
            self.defined.discard(name)
            run = self.runs.get(name)
            if run is not None:
                run.halt()
                run.join(self.lc.rpc_timeout_s + 1)
                if run.state.state != "failed":
                    run.checkpoint(final=True)
                    keep_final_checkpoint(run.ckpt_dir)
            # Replaced, not mutated: RPC and report threads iterate them.
            self.runs = {n: r for n, r in self.runs.items() if n != name}
            self.experiments = [e for e in self.experiments if e.name != name]
            self.experiment_states = {n: st for n, st in self.experiment_states.items() if n != name}
            self.store.drop(name)  # after experiment_states: a stream that asks again is NOT_FOUND as well
            for family in series:  # every label set of it: gone, not failed or stale (a stale 1 would alert for ever)
                rpc.remove_series(family, "experiment", name)
            log.info("experiment removed by control; training ends", extra=kv(experiment=name))

    def _on_robots(self, specs: list[robot_pb2.RobotSpec]) -> None:
        assigned = assign(specs, self.experiments)
        for index, exp in enumerate(self.experiments):
            mine = assigned[exp.name]
            run = self.runs.get(exp.name)
            if run is not None:
                for spec in mine:
                    if spec.robot_id not in run.specs:
                        run.add_robot(spec)
                if isinstance(run, ExperimentRun):
                    run.keep_misfits({s.robot_id for s in mine})
                continue
            if not ready(exp, mine):
                continue
            log.info("experiment starts", extra=kv(experiment=exp.name, robots=[s.robot_id for s in mine]))
            run = None
            try:
                run = ExperimentRun(self, index, exp, mine)
                run.set_stopped(exp.name in self.stopped_experiments)
                run.start()
            except (LearnerError, ValueError) as exc:  # this experiment cannot train (robots, params, checkpoint)
                if run is not None:
                    run.halt()
                self._cannot_start(exp, mine, exc)
                continue
            self.runs[exp.name] = run

    def _cannot_start(self, exp: ExperimentConfig, specs: list[robot_pb2.RobotSpec], exc: Exception) -> None:
        """Report the experiment failed with why (GetStatus, the console) while the others train; never retried
        silently, never checkpointed (its checkpoint directory stays as it was)."""
        ours = isinstance(exc, LearnerError | LayoutError | PluginError)  # their messages name the field or robots
        state = self.experiment_states[exp.name]
        state.state, state.error = "failed", str(exc)
        EXPERIMENT_FAILED.labels(exp.name).set(1)
        log.error(
            "experiment cannot start", exc_info=None if ours else exc, extra=kv(experiment=exp.name, error=str(exc))
        )
        self.runs[exp.name] = _FailedRun(exp, specs)  # type: ignore[assignment]


class _FailedRun:
    """Placeholder for an experiment that cannot start: robots that cannot share a layout, params that do not fit
    them, a checkpoint the config cannot resume (reported, never retried silently)."""

    def __init__(self, exp: ExperimentConfig, specs: list[robot_pb2.RobotSpec]) -> None:
        self.exp, self.specs = exp, {s.robot_id: s for s in specs}
        self.state = ExperimentState(exp.name, exp.algorithm.kind, state="failed")

    def add_robot(self, spec: robot_pb2.RobotSpec) -> None:
        self.specs[spec.robot_id] = spec

    def join(self, timeout: float) -> None:
        pass

    def alive(self) -> bool:
        return False

    def halt(self) -> None:
        pass

    def checkpoint(self, final: bool = False) -> None:
        pass


def _same_shapes(spec: robot_pb2.RobotSpec, like: robot_pb2.RobotSpec) -> bool:
    """Whether replay stores and samples `spec`'s steps as `like`'s: the same observation features (names, shapes,
    dtypes, images) and action shape and dtype. Bounds may differ (an imported dataset's come from its statistics)."""
    from user.spec import features

    same_action = list(spec.action.shape) == list(like.action.shape) and spec.action.dtype == like.action.dtype
    return same_action and features(spec) == features(like)


def _group_of(spec: robot_pb2.RobotSpec, like: dict[str, robot_pb2.RobotSpec]) -> str | None:
    """The group (kind -> a spec of its robots) `spec` fits, its own kind first; None: none."""
    return next((k for k in sorted(like, key=lambda k: k != spec.kind) if _same_shapes(spec, like[k])), None)


class _TableRobots:
    """The robots of the tables an experiment samples besides its own (imported demos under their dataset's robot
    id, another robot's interventions) that fit a sampling group. Replay's Stats(spec_tables) is read in a thread of
    its own every REFRESH_S, never per sample; until the first answer only the experiment's robots are sampled. A
    robot that fits no group, has no stored spec or is another experiment's is left out, logged once (INFO)."""

    REFRESH_S = 10.0
    RETRY_S = 1.0  # after a failed Stats

    def __init__(self, experiment: str) -> None:
        self.experiment = experiment
        self._lock = threading.Lock()
        self._tables: tuple[str, ...] = ()  # the tables `_fits` is for
        self._fits: dict[str, list[str]] = {}  # kind -> robot ids
        self._due = 0.0  # monotonic time of the next refresh
        self._busy = False
        self._failing = False
        self._left_out: dict[str, str] = {}  # robot -> why (logged)

    def fitting(self, stub: Any, tables: tuple[str, ...], context: Any, timeout: float) -> dict[str, list[str]]:
        """kind -> the robots of `tables` that fit that group; starts a refresh when due. context() -> (kind -> a
        spec of the group, the experiment's robots, robot -> another experiment), taken when a refresh starts."""
        with self._lock:
            start = not self._busy and (time.monotonic() >= self._due or tables != self._tables)
            self._busy = self._busy or start
            fits = self._fits if tables == self._tables else {}
        if start:
            args = (stub, tables, *context(), timeout)
            name = f"learner-{self.experiment}-demo-robots"
            threading.Thread(target=self._refresh, args=args, name=name, daemon=True).start()
        return fits

    def _refresh(
        self,
        stub: Any,
        tables: tuple[str, ...],
        like: dict[str, robot_pb2.RobotSpec],
        mine: set[str],
        others: dict[str, str],
        timeout: float,
    ) -> None:
        fits = None
        try:
            # counts_only: the specs and per-robot transitions, not replay's walk of every episode (every REFRESH_S)
            stats = stub.Stats(replay_pb2.StatsRequest(spec_tables=tables, counts_only=True), timeout=timeout)
            fits = self._fit(stats, tables, like, mine, others)
        except Exception as exc:  # RpcError, or the stub's channel closed as the run stops: asked again later
            if not self._failing:
                log.warning(
                    "replay stats for the robots of other tables failed; asked again",
                    extra=kv(experiment=self.experiment, tables=list(tables), error=str(exc)[:200]),
                )
        with self._lock:
            self._busy, self._failing = False, fits is None
            self._due = time.monotonic() + (self.REFRESH_S if fits is not None else self.RETRY_S)
            if fits is not None:
                self._tables, self._fits = tables, fits

    def _fit(
        self,
        stats: replay_pb2.StatsResponse,
        tables: tuple[str, ...],
        like: dict[str, robot_pb2.RobotSpec],
        mine: set[str],
        others: dict[str, str],
    ) -> dict[str, list[str]]:
        specs = {s.robot_id: s for s in stats.specs}
        held = {r for t in tables if t in stats.tables for r, c in stats.tables[t].robots.items() if c.transitions}
        out: dict[str, list[str]] = {}
        for rid in sorted((held | set(specs)) - mine):
            spec = specs.get(rid)
            kind = _group_of(spec, like) if spec is not None and rid not in others else None
            if kind is not None:
                out.setdefault(kind, []).append(rid)
                self._left_out.pop(rid, None)  # logged again should it stop fitting
                continue
            if rid in others:
                why = f"a robot of experiment {others[rid]!r}"
            elif spec is None:
                why = "replay holds no spec of it" + (" (past the 1024 a Stats lists)" if stats.specs_left_out else "")
            else:
                why = "its observations or actions differ from the experiment's robots'"
            if self._left_out.get(rid) != why:
                self._left_out[rid] = why
                log.info(
                    "robot of a sampled table left out of online training",
                    extra=kv(experiment=self.experiment, robot_id=rid, tables=list(tables), why=why),
                )
        return out
