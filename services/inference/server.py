"""Inference service: observations in, actions out, batched across robots.

The policy is whatever the learner published last: a WeightSubscriber streams weight sets from
Learner.SubscribeWeights and `load_weights` rebuilds the policy from PolicySpec + tensors (no code
and no pickle from the wire). Act requests are validated, queued on a MicroBatcher and answered
from one policy forward per batch. Until the first weights arrive Act answers UNAVAILABLE and the
edges hold their robots still.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Collection, Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, Literal

import grpc
import numpy as np
import prometheus_client
import torch

from services.inference.batcher import ActResult, BatcherStopped, MicroBatcher, NoPolicyError
from user import rpc, wire
from user import spec as contract
from user.config import ConfigError, ExperimentConfig, RobotSelector, StackConfig
from user.experiments import EMBODIMENT_KEY, embodiment_inputs, fit_action
from user.log import kv
from user.policy import (
    Policy,
    SteppedSampler,
    build_policy,
    check_device,
    check_fit,
    check_sizes,
    placeholders,
)
from user.spec import MAX_ROBOT_ID_BYTES
from user.v1 import inference_pb2, inference_pb2_grpc, robot_pb2
from user.v1 import tensor_pb2 as tpb
from user.weights import WeightSet, WeightSubscriber
from user.worker import WorkerReporter, report_worker

log = logging.getLogger(__name__)

SERVICE_NAME = inference_pb2.DESCRIPTOR.services_by_name["Inference"].full_name
MAX_INSTRUCTION_CHARS = 1024  # a task in words, not a document
MAX_ACT_BATCH = 256  # robots in one ActBatch: an edge process's robots, with room to spare
MAX_ACT_WAIT_S = 10.0  # a caller without a deadline still gets an answer (or an error) in bounded time
EXPERIMENTS_POLL_S = 2.0  # how often control is asked for experiments defined at run time
LOADS_SUMMARY_S = 60.0  # after a slot's first load (INFO), versions loaded are summed up at INFO at most this often
MAX_FIT_VERDICTS = 4096  # (robot, policy version) fit verdicts kept per slot: robots come and go, ids are not reused
MISFIT_STAGES = ("load", "act")  # POLICY_MISFITS' `at` labels
# What one Act's observation may decode to, over all the keys the policy reads (checked from the declared dtypes
# and shapes before anything is decoded): several cameras at MAX_IMAGE_SIDE, with room to spare. A request's keys
# are also checked against what the policy reads first, so this bounds policies that resize or declare no sizes.
MAX_ACT_DECODED_BYTES = 64 * 2**20

REQUESTS = prometheus_client.Counter("user_inference_requests_total", "Act requests by status code", ["code"])
_REQUESTS_OK = REQUESTS.labels("OK")  # looked up once: every answered Act counts here
BATCH_SIZE = prometheus_client.Histogram(
    "user_inference_batch_size", "Requests per policy forward", buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256)
)
QUEUE_SECONDS = prometheus_client.Histogram(
    "user_inference_queue_seconds",
    "Time an Act request waited to be batched",
    buckets=(0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
)
JOINED = prometheus_client.Counter(
    "user_inference_joined_total",
    "Requests that joined a running continuous batch at a flow step (inference.continuous_batching)",
)
COMPUTE_SECONDS = prometheus_client.Histogram(
    "user_inference_compute_seconds",
    "Policy forward time per batch",
    buckets=(0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
)
ENCODED_FRAMES = prometheus_client.Counter(
    "user_inference_encoded_frames_total",
    "Camera frames that came JPEG/PNG-encoded in Act requests (edge act_image_encoding), decoded here",
    ["encoding"],
)
_FRAME_LABELS = {tpb.ENCODING_JPEG: ENCODED_FRAMES.labels("jpeg"), tpb.ENCODING_PNG: ENCODED_FRAMES.labels("png")}
POLICY_VERSION = prometheus_client.Gauge(
    "user_inference_policy_version", "Version of the policy being served, per experiment", ["experiment"]
)
WEIGHT_UPDATES = prometheus_client.Counter("user_inference_weight_updates_total", "Weight sets loaded")
FORWARD_FAILURES = prometheus_client.Counter(
    "user_inference_forward_failures_total",
    "Acts answered INTERNAL because the policy raised or returned a batch or action of the wrong shape",
    ["experiment", "stage"],
)
POLICY_MISFITS = prometheus_client.Counter(
    "user_inference_policy_misfits_total",
    "Policies that do not fit the robots they would serve: versions refused at load, Acts refused (never acted on)",
    ["experiment", "at"],
)
NON_FINITE_ACTIONS = prometheus_client.Counter(
    "user_inference_non_finite_actions_total",
    "Acts answered INTERNAL because the policy produced NaN/Inf actions (never sent to a robot)",
    ["experiment"],
)


def _observe_batch(size: int, compute_s: float) -> None:
    BATCH_SIZE.observe(size)
    COMPUTE_SECONDS.observe(compute_s)


class RequestTooLarge(ValueError):
    """An observation whose declared tensors would decode to more than MAX_ACT_DECODED_BYTES (-> RESOURCE_EXHAUSTED)."""


def _read_keys(policy: Policy, observation: Collection[str]) -> list[str]:
    """The keys of `observation` the policy reads (every key when it does not say); ValueError if one it needs
    is missing. Other keys are ignored (an edge sends its robot's whole observation)."""
    # A feature the policy can do without (e.g. the instruction, which may come in the request instead).
    optional = list(getattr(policy, "optional_obs_keys", ()))
    keys: list[str] = [k for k in (policy.observation_keys or observation) if k not in optional]
    keys += [k for k in optional if k in observation and k not in keys]
    missing = [k for k in keys if k not in observation]
    if missing:
        raise ValueError(f"observation lacks {missing}; the policy reads {keys}")
    return keys


def validate_observation(observation: Mapping[str, np.ndarray], policy: Policy) -> dict[str, np.ndarray]:
    """Keep the keys the policy reads, as float32 (uint8 stays uint8; an image keeps the dtype it came in, for the
    policy's check to name); ValueError on a mismatch."""
    images = policy.image_shapes
    out: dict[str, np.ndarray] = {}
    for k in _read_keys(policy, observation):
        arr = observation[k]
        if arr.dtype != np.uint8 and k not in images:
            arr = arr.astype(np.float32, copy=False)
            if not np.isfinite(arr).all():
                raise ValueError(f"observation {k!r} has NaN or Inf")
        out[k] = arr
    check_sizes(out, policy)
    return out


def decode_observation(
    tmap: tpb.TensorMap, policy: Policy, kind: str = "", spec: robot_pb2.RobotSpec | None = None
) -> dict[str, np.ndarray]:
    """An Act's observation, checked before anything is decoded. Where the robot's spec is known, first against it
    as replay checks a step's (its keys and no others, each of its dtype and shape, finite). Then the keys the policy
    reads are checked from their declared dtype and shape (as zero-cost placeholders: keys, feature counts, image
    sizes), their declared bytes are capped (RequestTooLarge), and only then are those keys decoded; keys the policy
    does not read are never decoded. ValueError (WireError) on a mismatch."""
    tensors = tmap.tensors
    if spec is not None:  # the edge checks its observations against this spec: it sends no others
        _cap_bytes(tensors, list(tensors))  # before the check decodes them
        contract.check_tensor_map("observation", tmap, spec.observation)
    # A policy across embodiments gets EMBODIMENT_KEY from the robot's kind (embodiment_inputs), never from the wire.
    added = [EMBODIMENT_KEY] if getattr(policy, "embodiments", None) else []
    keys = [k for k in _read_keys(policy, [*tensors, *added]) if k not in added]
    images = policy.image_shapes
    shaped: dict[str, np.ndarray] = {}
    for key in keys:
        tensor = tensors[key]
        try:
            dtype = wire.decoded_dtype(tensor.dtype)
        except wire.WireError as exc:
            raise wire.WireError(f"observation {key!r}: {exc}") from None
        if dtype != np.uint8 and key not in images:
            dtype = np.dtype(np.float32)  # as validate_observation casts it
        shaped[key] = np.broadcast_to(np.zeros((), dtype), tuple(int(d) for d in tensor.shape))
    check_sizes(embodiment_inputs(policy, kind, shaped), policy)
    _cap_bytes(tensors, keys)
    raw = wire.from_tensor_map(tmap, strict=True, keys=keys)
    return validate_observation(embodiment_inputs(policy, kind, raw), policy)


def _cap_bytes(tensors: Mapping[str, tpb.Tensor], keys: Collection[str]) -> None:
    """RequestTooLarge when `keys` would decode to more than MAX_ACT_DECODED_BYTES (from their declared shapes)."""
    total = 0
    for key in keys:
        try:
            total += wire.declared_nbytes(tensors[key])
        except wire.WireError as exc:
            raise wire.WireError(f"observation {key!r}: {exc}") from None
    if total > MAX_ACT_DECODED_BYTES:
        raise RequestTooLarge(f"observation would decode to {total} bytes, over the {MAX_ACT_DECODED_BYTES} of an Act")


class RoutingError(LookupError):
    """An Act for a robot no experiment trains (-> FAILED_PRECONDITION), or Control unreachable (-> UNAVAILABLE)."""

    def __init__(self, code: grpc.StatusCode, message: str) -> None:
        super().__init__(message)
        self.code = code


class PolicySlot:
    """One experiment's served policy: its weight subscriber, its micro-batcher and the current policy."""

    def __init__(self, service: InferenceService, experiment: str) -> None:
        icfg = service.cfg.inference
        self.service, self.experiment = service, experiment
        self.batcher = MicroBatcher(
            icfg.max_batch,
            icfg.max_wait_ms,
            on_batch=_observe_batch,
            name=f"inference-batch-{experiment}",
            workers=icfg.batch_workers,
            on_join=JOINED.inc,
            on_failure=self._count_failure,
        )
        self.policy: Policy | None = None
        self.subscriber: WeightSubscriber | None = None
        self._load_lock = threading.Lock()
        self._non_finite_logged = -1  # the policy version whose non-finite actions were logged (once a version)
        self.non_finite = NON_FINITE_ACTIONS.labels(experiment)
        # robot_id -> (policy version, spec, why the policy cannot drive it or ""): checked once per version and spec.
        # The version, never the policy: a robot that left must not keep the weights it last saw alive.
        self._fits: dict[str, tuple[int, robot_pb2.RobotSpec, str]] = {}
        self._misfit_logged: dict[str, int] = {}  # robot kind -> the policy version whose misfit was logged
        self._failure_stages: set[str] = set()  # FORWARD_FAILURES label sets of this experiment (removed with it)
        self._loads_unlogged = 0  # versions loaded since the last INFO line about loads
        self._loads_logged_at: float | None = None  # monotonic time of that line; None before the first load
        self.closed = False  # no longer served: its metric series are gone and must not come back

    def _count_failure(self, stage: str, count: int) -> None:
        if not self.closed:
            self._failure_stages.add(stage)
            FORWARD_FAILURES.labels(self.experiment, stage).inc(count)

    def load_weights(self, weights: WeightSet) -> Policy:
        """Rebuild the policy from a weight set and serve it; raises ValueError (keeping the old one) if bad,
        weights with NaN/Inf values included (the weight subscriber logs it and keeps the previous version)."""
        start = time.perf_counter()
        tensors = weights.policy_tensors()
        check_finite_weights(tensors, weights.version)
        policy = build_policy(weights.policy, tensors, weights.version, self.service.cfg.inference.device)
        self._check_fits_some(policy)
        shape = tuple(policy.action_shape)
        with self._load_lock:
            self.policy = policy
            # A policy with its own batched preprocess gets it run in the batcher thread, not per request.
            preprocess = getattr(policy, "preprocess", None)
            act = policy.forward if preprocess is not None else policy.act  # type: ignore[attr-defined]
            continuous = self.service.cfg.inference.continuous_batching and isinstance(policy, SteppedSampler)
            rows = [shape, (policy.chunk_horizon, *shape)]  # an action, or a chunk of them
            self.batcher.set_policy(act, policy.version, preprocess, policy if continuous else None, rows)
            self._fits = {}  # verdicts of older versions are never asked again
        WEIGHT_UPDATES.inc()
        if not self.closed:
            POLICY_VERSION.labels(self.experiment).set(policy.version)
        self._log_load(policy.version, weights.policy.kind, round((time.perf_counter() - start) * 1e3, 2))
        return policy

    def _log_load(self, version: int, kind: str, build_ms: float) -> None:
        """Every load at DEBUG; at INFO the first one, then at most every LOADS_SUMMARY_S how many were loaded (a
        learner publishing every few updates would otherwise write hundreds of lines a minute)."""
        fields = kv(experiment=self.experiment, version=version, kind=kind, build_ms=build_ms)
        now = time.monotonic()
        if self._loads_logged_at is None:
            self._loads_logged_at = now
            log.info("policy loaded", extra=fields)
            return
        log.debug("policy loaded", extra=fields)
        self._loads_unlogged += 1
        if now - self._loads_logged_at >= LOADS_SUMMARY_S:
            log.info(
                "policy versions loaded",
                extra=kv(
                    experiment=self.experiment,
                    loaded=self._loads_unlogged,
                    version=version,
                    since_s=round(now - self._loads_logged_at, 1),
                ),
            )
            self._loads_logged_at, self._loads_unlogged = now, 0

    def _check_fits_some(self, policy: Policy) -> None:
        """PolicyMisfit (counted; the caller keeps the previous policy) when robots are routed here and the policy
        fits none of them. One that fits some is served: the others are refused per Act (misfit)."""
        specs = self.service.router.specs_in(self.experiment)
        reasons = [f"{s.robot_id} ({s.kind}): {why}" for s in specs if (why := policy_misfit(policy, s))]
        if specs and len(reasons) == len(specs):
            if not self.closed:
                POLICY_MISFITS.labels(self.experiment, "load").inc()
            served = self.policy.version if self.policy is not None else None
            raise PolicyMisfit(
                f"experiment {self.experiment}: policy version {policy.version} ({policy.spec.kind}) fits none of its "
                f"robots, refused (still serving version {served}): {reasons[0]}"
            )

    def misfit(self, policy: Policy, spec: robot_pb2.RobotSpec) -> str:
        """Why `policy` cannot drive this robot ("" when it can): checked once per policy and robot spec, counted
        per Act refused, logged once per policy version and robot kind."""
        fits = self._fits  # replaced whole at a load: read once
        cached = fits.get(spec.robot_id)
        if cached is not None and cached[0] == policy.version and cached[1] is spec:
            why = cached[2]
        else:
            why = policy_misfit(policy, spec)
            if len(fits) >= MAX_FIT_VERDICTS:  # bounded: drop the oldest verdict (a robot that left, likely)
                fits.pop(next(iter(fits), ""), None)
            fits[spec.robot_id] = (policy.version, spec, why)  # a race between RPC threads stores the same answer
        if why:
            if not self.closed:
                POLICY_MISFITS.labels(self.experiment, "act").inc()
            if self._misfit_logged.get(spec.kind) != policy.version:
                self._misfit_logged[spec.kind] = policy.version
                log.error(
                    "the policy does not fit a robot it serves; that robot gets FAILED_PRECONDITION and holds "
                    "(logged once a version and robot kind)",
                    extra=kv(experiment=self.experiment, version=policy.version, robot_id=spec.robot_id, error=why),
                )
        return why

    def forget_metrics(self) -> None:
        """Remove this experiment's labelled series (it is no longer served): frozen values would outlive it."""
        self.closed = True
        name = self.experiment
        for family, labels in [
            (POLICY_VERSION, [(name,)]),
            (NON_FINITE_ACTIONS, [(name,)]),
            (FORWARD_FAILURES, [(name, stage) for stage in sorted(self._failure_stages)]),
            (POLICY_MISFITS, [(name, at) for at in MISFIT_STAGES]),
        ]:
            for label_values in labels:
                with contextlib.suppress(KeyError):  # never set
                    family.remove(*label_values)

    def note_non_finite(self, version: int) -> None:
        """The policy of `version` produced a NaN/Inf action: counted always, logged once per version."""
        self.non_finite.inc()
        if self._non_finite_logged != version:
            self._non_finite_logged = version
            log.error(
                "the policy produced non-finite actions; those robots get INTERNAL and hold (logged once a version)",
                extra=kv(experiment=self.experiment, version=version),
            )


class PolicyMisfit(ValueError):
    """A policy that does not fit the robots it would serve (its observation keys, feature sizes or action size)."""


def policy_misfit(policy: Policy, spec: robot_pb2.RobotSpec) -> str:
    """Why `policy` cannot act for a robot of `spec` ("" when it can), from the spec's declared features."""
    features = contract.features(spec)
    observation = placeholders({k: (f.shape, f.dtype) for k, f in features.items()})
    try:
        check_fit(policy, embodiment_inputs(policy, spec.kind, observation), contract.action_dim(spec), spec.kind)
    except Exception as exc:  # a plug-in's declarations may raise anything: a clear status, never UNKNOWN
        return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
    return ""


def check_finite_weights(tensors: Mapping[str, np.ndarray], version: int) -> None:
    """ValueError naming the first float tensor with a NaN or Inf (min/max: no temporary the tensor's size)."""
    for name, tensor in tensors.items():
        arr = np.asarray(tensor)
        if arr.size and arr.dtype.kind in "fc" and not (np.isfinite(arr.min()) and np.isfinite(arr.max())):
            raise ValueError(f"weight version {version}: tensor {name!r} has non-finite values (NaN or Inf); refused")


class Router:
    """robot_id -> experiment: from Control's ListRobots (every robot it knows, online or not) and the experiments'
    selectors. A background thread rebuilds the routes from each answer (robots control forgot are dropped; one
    offline keeps its route, so a control restart unroutes no robot), every POLL_S and, at most every REFRESH_S,
    when an Act names a robot not routed; an Act never waits on control. One experiment that selects every robot
    (or the implicit default one) needs no Control. A robot not routed yet gets UNAVAILABLE
    until a refresh begun after its first Act has answered; then a robot control knows and no selector picks gets
    FAILED_PRECONDITION, and so does one control does not know, except with one experiment, where such a client (an
    evaluation probe) is served, as is every robot no selector refused while control is unreachable."""

    REFRESH_S = 1.0  # at most this often when an Act names a robot not routed
    POLL_S = 5.0  # otherwise this often: robots control forgot are pruned, changed specs picked up
    LIST_TIMEOUT_S = 2.0
    MAX_ASKED = 4096  # robots not routed that asked, remembered (bounded: probes may use any id)

    def __init__(self, cfg: StackConfig) -> None:
        self.cfg = cfg
        self.experiments = cfg.resolved_experiments()
        self._routes: dict[str, tuple[str, str]] = {}  # robot_id -> (experiment, robot kind)
        self._specs: dict[str, robot_pb2.RobotSpec] = {}  # robot_id -> its spec, as control lists it
        self._lock = threading.Lock()
        self._refreshed = 0.0  # monotonic time the last refresh began
        self._channel: grpc.Channel | None = None
        self._refused: set[str] = set()  # defined experiments whose definition did not check here
        self._unselected: set[str] = set()  # robots control knows that no experiment selects (last refresh)
        self._asked: dict[str, int] = {}  # robot not routed -> refreshes begun when it first asked
        self._begun = 0  # refreshes begun
        self._answered = 0  # the number of the last refresh that ended (answered or failed)
        self._error = ""  # why the last refresh failed; "" when control answered it
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Refresh in the background from now on (a first refresh at once)."""
        if self._thread is None:
            self._wake.set()
            self._thread = threading.Thread(target=self._run, name="inference-routes", daemon=True)
            self._thread.start()

    def takes_any(self) -> bool:
        """One experiment of one embodiment that selects every robot: routing needs no control."""
        experiments = self.experiments
        single = len(experiments) == 1 and not experiments[0].shared_embodiment
        return single and (not self.cfg.experiments or experiments[0].robots == RobotSelector())

    def route(self, robot_id: str) -> tuple[str, str]:
        """(experiment, robot kind); the kind is "" when one experiment of one embodiment needs no lookup. From
        the current routes only: a robot not routed wakes the refresher and is answered at once (RoutingError)."""
        experiments = self.experiments
        if self.takes_any():
            return experiments[0].name, ""  # it takes any robot (the implicit default always has)
        single = len(experiments) == 1 and not experiments[0].shared_embodiment
        with self._lock:
            route = self._routes.get(robot_id)
            if route is not None:
                return route
            if robot_id not in self._asked and len(self._asked) >= self.MAX_ASKED:
                self._asked.pop(next(iter(self._asked)))
            checked = self._answered > self._asked.setdefault(robot_id, self._begun)
            unselected, error = robot_id in self._unselected, self._error
        if unselected:  # until its spec or the experiments change (POLL_S, or add() wakes the refresher)
            raise RoutingError(
                grpc.StatusCode.FAILED_PRECONDITION, f"robot {robot_id!r} is in no experiment (no selector picks it)"
            )
        if error or not checked:
            self._wake.set()  # paced by the refresher: at most one ListRobots every REFRESH_S
        if error:
            if single:
                return experiments[0].name, ""  # control down: one experiment's robots keep being served
            raise RoutingError(grpc.StatusCode.UNAVAILABLE, f"robot {robot_id!r} not routed: {error}")
        if not checked:
            raise RoutingError(
                grpc.StatusCode.UNAVAILABLE, f"robot {robot_id!r} not routed yet: waiting for control's robot list"
            )
        if single:
            return experiments[0].name, ""  # a client control does not know (an evaluation probe): served
        raise RoutingError(
            grpc.StatusCode.FAILED_PRECONDITION, f"robot {robot_id!r} is in no experiment (unknown to control?)"
        )

    def _run(self) -> None:
        """The refresher: woken by route() or every POLL_S; at most one refresh every REFRESH_S."""
        while not self._stop.is_set():
            self._wake.wait(self.POLL_S)
            if self._stop.is_set():
                return
            if self.takes_any():  # nothing to ask control (an experiment defined at run time may change this)
                self._wake.clear()
                continue
            pause = self._refreshed + self.REFRESH_S - time.monotonic()
            if pause > 0 and self._stop.wait(pause):
                return
            self._wake.clear()
            self.refresh()

    def refresh(self) -> None:
        """Rebuild the routes from every robot control knows, online or not (in the refresher thread; tests may
        call it): a control restart, after which robots are offline until their edges reconnect, keeps them
        routed; only a robot control no longer lists (forgotten) is pruned. Any failure (an unreadable TLS file
        for the channel, a bug) is recorded like control being unreachable: the refresher never dies of it."""
        with self._lock:
            self._begun += 1
            number, experiments = self._begun, self.experiments
        self._refreshed = time.monotonic()
        try:
            self._refresh(number, experiments)
        except Exception as exc:
            self._failed(number, f"routing refresh failed: {exc}", exc)

    def _refresh(self, number: int, experiments: list[ExperimentConfig]) -> None:
        from user.v1 import control_pb2

        request = control_pb2.ListRobotsRequest(include_offline=True, without_episodes=True)
        try:
            resp = self._stub().ListRobots(request, timeout=self.LIST_TIMEOUT_S)
        except grpc.RpcError as err:
            self._failed(number, f"control unreachable for routing: {err.code().name}")
            return
        routes, specs, unselected = self._rebuild(resp.robots, experiments)
        with self._lock:
            if number < self._answered:  # a later refresh (a caller's, beside the refresher's) already answered
                return
            if self.experiments is not experiments:  # added or removed meanwhile: this answer is stale
                self._wake.set()
                return
            self._routes, self._specs, self._unselected = routes, specs, unselected
            self._asked = {r: n for r, n in self._asked.items() if r not in routes and r not in unselected}
            self._answered, error, self._error = number, self._error, ""
        if error:
            log.info("control answers routing again", extra=kv(robots=len(routes)))

    def _failed(self, number: int, error: str, exc: BaseException | None = None) -> None:
        """A refresh that got no answer; `exc` when it raised something other than an RPC error (its traceback is
        logged, once per outage like the rest)."""
        with self._lock:
            if number < self._answered:
                return
            self._answered, previous, self._error = number, self._error, error
        if not previous and not self._stop.is_set():  # once per outage: routed robots keep being served meanwhile
            log.warning("robot routes not refreshed; keeping the last ones", extra=kv(error=error), exc_info=exc)

    def _rebuild(
        self, robots: Collection[Any], experiments: list[ExperimentConfig]
    ) -> tuple[dict[str, tuple[str, str]], dict[str, robot_pb2.RobotSpec], set[str]]:
        """(routes, specs, unselected) of control's robots. A spec equal to the one held is kept, the same object:
        a slot's fit verdict for it stays valid."""
        from user.experiments import experiment_for

        with self._lock:
            held = self._specs
        routes, specs, unselected = {}, {}, set()
        for info in robots:
            exp = experiment_for(info.spec, experiments)
            rid = info.spec.robot_id
            if exp is None:
                unselected.add(rid)
                continue
            routes[rid] = (exp.name, info.spec.kind)
            old = held.get(rid)
            specs[rid] = old if old is not None and old == info.spec else info.spec
        return routes, specs, unselected

    def spec(self, robot_id: str) -> robot_pb2.RobotSpec | None:
        """The robot's spec, when routing learned it from control (else None)."""
        with self._lock:
            return self._specs.get(robot_id)

    def specs_in(self, experiment: str) -> list[robot_pb2.RobotSpec]:
        """The specs of the robots routed to `experiment` so far."""
        with self._lock:
            return [self._specs[r] for r, route in self._routes.items() if route[0] == experiment and r in self._specs]

    def _stub(self) -> Any:
        from user.v1 import control_pb2_grpc

        with self._lock:
            if self._channel is None:
                self._channel = rpc.make_channel(self.cfg.inference.control_addr, self.cfg.auth)
            return control_pb2_grpc.ControlStub(self._channel)

    def defined_experiments(self) -> tuple[list[ExperimentConfig], set[str] | None]:
        """(experiments defined at run time (Control.DefineExperiment) that this router does not know yet, in
        control's order; every name control lists, None when control cannot say). One whose definition does not
        check is logged, skipped."""
        from user.experiments import parse_definition
        from user.v1 import control_pb2

        try:
            resp = self._stub().ListExperiments(control_pb2.ListExperimentsRequest(), timeout=2.0)
        except grpc.RpcError as err:
            log.debug("ListExperiments failed", extra=kv(code=err.code().name))
            return [], None
        known = {e.name for e in self.experiments}
        new = []
        for info in resp.experiments:
            if not info.defined_at_runtime or info.name in known or info.name in self._refused:
                continue
            try:
                exp = parse_definition(info.definition_json, info.name)
            except ValueError as exc:
                self._refused.add(info.name)
                log.error("a defined experiment cannot be served", extra=kv(experiment=info.name, error=str(exc)))
                continue
            new.append(exp)
        return new, {info.name for info in resp.experiments}

    def add(self, exp: ExperimentConfig) -> None:
        """Route to `exp` too (after the others: the first matching selector wins, as everywhere)."""
        with self._lock:
            self.experiments = [*self.experiments, exp]  # replaced, not mutated: route() reads it unlocked
            self._refreshed = 0.0
        self._wake.set()  # its robots are routed by the next refresh

    def remove(self, name: str) -> None:
        """Route to `name` no more (Control.RemoveExperiment): its robots are looked up again."""
        with self._lock:
            self.experiments = [e for e in self.experiments if e.name != name]
            self._routes = {rid: route for rid, route in self._routes.items() if route[0] != name}
            self._refreshed = 0.0
        self._wake.set()

    def close(self) -> None:
        """Stop the refresher (a ListRobots in flight is cancelled with the channel) and close the channel."""
        self._stop.set()
        self._wake.set()
        for _ in range(2):  # again after the join: a refresh that was starting may have opened one
            with self._lock:
                channel, self._channel = self._channel, None
            if channel is not None:
                channel.close()
            if self._thread is not None:
                self._thread.join(self.LIST_TIMEOUT_S + 3.0)
                self._thread = None


class _ActError(Exception):
    """One robot's Act failed with this status (Act aborts with it; ActBatch answers it in that robot's slot)."""

    def __init__(self, code: grpc.StatusCode, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


# A queued Act: its future, the policy it was validated against, robot kind, its experiment's slot.
_Pending = tuple[Future, Policy, str, "PolicySlot"]


class InferenceServicer(inference_pb2_grpc.InferenceServicer):
    def __init__(self, service: InferenceService) -> None:
        self.service = service

    @staticmethod
    def _abort(context: grpc.ServicerContext, code: grpc.StatusCode, message: str) -> None:
        REQUESTS.labels(code.name).inc()
        context.abort(code, message)

    @staticmethod
    def _wait_s(context: grpc.ServicerContext) -> float:
        remaining = context.time_remaining()
        return MAX_ACT_WAIT_S if remaining is None else max(0.0, min(remaining, MAX_ACT_WAIT_S))

    def _queue(self, request: inference_pb2.ActRequest) -> _Pending:
        """Route, validate and queue one robot's observation on its experiment's batcher."""
        size = len(request.robot_id.encode())
        if size > MAX_ROBOT_ID_BYTES:  # before routing: control's lookups and every message would echo it
            raise _ActError(
                grpc.StatusCode.INVALID_ARGUMENT, f"robot_id too long: {size} bytes, at most {MAX_ROBOT_ID_BYTES}"
            )
        if len(request.instruction) > MAX_INSTRUCTION_CHARS:
            raise _ActError(grpc.StatusCode.INVALID_ARGUMENT, f"instruction over {MAX_INSTRUCTION_CHARS} chars")
        try:
            experiment, kind = self.service.router.route(request.robot_id)
        except RoutingError as exc:
            raise _ActError(exc.code, str(exc)) from None
        slot = self.service.slots.get(experiment)
        if slot is None:  # removed between routing and here (Control.RemoveExperiment)
            raise _ActError(grpc.StatusCode.FAILED_PRECONDITION, f"experiment {experiment!r} is no longer served")
        policy = slot.policy
        if policy is None:
            raise _ActError(grpc.StatusCode.UNAVAILABLE, "no policy yet")
        spec = self.service.router.spec(request.robot_id)
        why = slot.misfit(policy, spec) if spec is not None else ""
        if why:
            raise _ActError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"the policy (version {policy.version}) does not fit robot {request.robot_id!r}: {why}",
            )
        try:
            obs = decode_observation(request.observation, policy, kind, spec)
        except RequestTooLarge as exc:
            raise _ActError(grpc.StatusCode.RESOURCE_EXHAUSTED, f"bad observation: {exc}") from None
        except ValueError as exc:  # WireError is a ValueError
            raise _ActError(grpc.StatusCode.INVALID_ARGUMENT, f"bad observation: {exc}") from None
        tensors = request.observation.tensors
        for key in obs:  # the frames decoded (keys the policy does not read are not)
            counter = _FRAME_LABELS.get(tensors[key].encoding) if key in tensors else None
            if counter is not None:
                counter.inc()
        try:
            future = slot.batcher.submit(
                obs, request.deterministic, key=request.robot_id, instruction=request.instruction
            )
        except NoPolicyError:
            raise _ActError(grpc.StatusCode.UNAVAILABLE, "no policy yet") from None
        except BatcherStopped:
            raise _ActError(grpc.StatusCode.UNAVAILABLE, f"experiment {experiment!r} is no longer served") from None
        return future, policy, kind, slot

    @staticmethod
    def _answer(pending: _Pending, wait_s: float) -> inference_pb2.ActResponse:
        """Wait up to wait_s for the queued Act's row of its batch and build the response. An action with a NaN
        or Inf is never answered: INTERNAL (the policy's fault, not the client's), counted, and the robot holds."""
        future, policy, kind, slot = pending
        try:
            result: ActResult = future.result(timeout=wait_s)
        except FutureTimeout:
            future.cancel()  # the worker skips it if it has not started
            raise _ActError(grpc.StatusCode.DEADLINE_EXCEEDED, f"no action within {wait_s * 1000:.0f} ms") from None
        except NoPolicyError:
            raise _ActError(grpc.StatusCode.UNAVAILABLE, "no policy yet") from None
        except BatcherStopped:
            raise _ActError(grpc.StatusCode.UNAVAILABLE, "the policy stopped serving (shutdown or removal)") from None
        except Exception as exc:
            raise _ActError(grpc.StatusCode.INTERNAL, f"policy forward failed: {exc}") from None
        QUEUE_SECONDS.observe(result.queue_us / 1e6)
        action = np.asarray(result.action, dtype=np.float32)
        if not np.isfinite(action).all():
            slot.note_non_finite(result.version)
            raise _ActError(
                grpc.StatusCode.INTERNAL, f"the policy (version {result.version}) produced non-finite actions"
            )
        return inference_pb2.ActResponse(
            action=wire.to_tensor(np.asarray(fit_action(policy, kind, result.action), dtype=np.float32)),
            policy_version=result.version,
            queue_us=result.queue_us,
            compute_us=result.compute_us,
            batch_size=result.batch_size,
            preprocess_us=result.preprocess_us,
            forward_us=result.compute_us,
            postprocess_us=result.postprocess_us,
            horizon=action.shape[0] if action.ndim == 2 else 1,
        )

    def Act(self, request: inference_pb2.ActRequest, context: grpc.ServicerContext) -> inference_pb2.ActResponse:
        try:
            response = self._answer(self._queue(request), self._wait_s(context))
        except _ActError as exc:
            self._abort(context, exc.code, exc.message)
        _REQUESTS_OK.inc()
        return response

    def ActBatch(
        self, request: inference_pb2.ActBatchRequest, context: grpc.ServicerContext
    ) -> inference_pb2.ActBatchResponse:
        count = len(request.requests)
        if not 0 < count <= MAX_ACT_BATCH:
            self._abort(context, grpc.StatusCode.INVALID_ARGUMENT, f"ActBatch takes 1 to {MAX_ACT_BATCH} requests")
        # Every robot is queued before any is waited for, so they can share one forward.
        queued: list[_Pending | _ActError] = []
        for req in request.requests:
            try:
                queued.append(self._queue(req))
            except _ActError as exc:
                queued.append(exc)
        end = time.monotonic() + self._wait_s(context)
        results = []
        for item in queued:
            try:
                if isinstance(item, _ActError):
                    raise item
                response = self._answer(item, max(0.0, end - time.monotonic()))
            except _ActError as exc:
                REQUESTS.labels(exc.code.name).inc()
                results.append(inference_pb2.ActResult(code=exc.code.value[0], message=exc.message))
                continue
            _REQUESTS_OK.inc()
            results.append(inference_pb2.ActResult(code=0, response=response))
        return inference_pb2.ActBatchResponse(results=results)

    def Status(
        self, request: inference_pb2.InferenceStatusRequest, context: grpc.ServicerContext
    ) -> inference_pb2.InferenceStatus:
        policy = self.service.policy
        slots = list(self.service.slots.values())
        requests = sum(s.batcher.requests for s in slots)
        batches = sum(s.batcher.batches for s in slots)
        experiments = []
        for slot in slots:
            served, asked, ran = slot.policy, slot.batcher.requests, slot.batcher.batches
            experiments.append(
                inference_pb2.InferenceExperimentStatus(
                    experiment=slot.experiment,
                    policy_version=served.version if served else 0,
                    policy_kind=served.spec.kind if served else "",
                    requests=asked,
                    mean_batch_size=asked / ran if ran else 0.0,
                )
            )
        return inference_pb2.InferenceStatus(
            policy_version=policy.version if policy else 0,
            policy_kind=policy.spec.kind if policy else "",
            requests=requests,
            mean_batch_size=requests / batches if batches else 0.0,
            experiments=experiments,
        )


class InferenceService(rpc.GrpcService):
    """In-process inference server: start() binds (port 0 works), stop() drains and shuts down.

    One policy per experiment of the stack config, each with its own weight stream and batcher; an
    Act goes to its robot's experiment. policy_source: "learner" (default, also None) streams weights
    from cfg.inference.learner_addr; "manual" waits for load_weights() calls (tests, or a caller with
    its own weight source). `policy`, `batcher` and `load_weights` without an experiment are the first
    experiment's.
    """

    def __init__(
        self,
        cfg: StackConfig,
        policy_source: Literal["learner", "manual"] | None = None,
        start_metrics: bool = True,
    ) -> None:
        self.cfg = cfg
        self.policy_source = policy_source or "learner"
        if self.policy_source not in ("learner", "manual"):
            raise ValueError(f"policy_source must be 'learner' or 'manual', got {policy_source!r}")
        self.start_metrics = start_metrics
        self.router = Router(cfg)
        # Replaced whole when an experiment defined at run time joins (RPC threads read it without a lock).
        self.slots = {e.name: PolicySlot(self, e.name) for e in self.router.experiments}
        self._watch_stop = threading.Event()
        self._defined: set[str] = set()  # experiments added from control's definitions (removable)
        self._watcher: threading.Thread | None = None
        self._first = next(iter(self.slots.values()))
        self.running: rpc.RunningServer | None = None
        try:
            check_device(cfg.inference.device)
        except ValueError as exc:
            raise ConfigError(f"inference.device: {exc}") from None
        torch.set_float32_matmul_precision(cfg.inference.matmul_precision)  # process-wide, as torch keeps it

    @property
    def policy(self) -> Policy | None:
        return self._first.policy

    @property
    def batcher(self) -> MicroBatcher:
        return self._first.batcher

    @property
    def subscriber(self) -> WeightSubscriber | None:
        return self._first.subscriber

    def slot_for(self, robot_id: str) -> PolicySlot:
        return self.slots[self.router.route(robot_id)[0]]

    def load_weights(self, weights: WeightSet, experiment: str = "") -> Policy:
        slot = self.slots[experiment] if experiment else self._first
        return slot.load_weights(weights)

    def start(self) -> InferenceService:
        for slot in self.slots.values():
            slot.batcher.start()
        self.running = rpc.start_server(
            "inference",
            lambda server: inference_pb2_grpc.add_InferenceServicer_to_server(InferenceServicer(self), server),
            [SERVICE_NAME],
            self.cfg.inference.server,
            self.cfg.auth,
            start_metrics=self.start_metrics,
        )
        for slot in self.slots.values():
            self._subscribe(slot)
        self.router.start()
        self._watcher = threading.Thread(target=self._watch_experiments, name="inference-experiments", daemon=True)
        self._watcher.start()
        return self

    def _subscribe(self, slot: PolicySlot) -> None:
        if self.policy_source != "learner" or self.running is None:
            return
        slot.subscriber = WeightSubscriber(
            self.cfg.inference.learner_addr,
            self.cfg.auth,
            client_id=f"inference-{socket.gethostname()}-{self.running.port}-{slot.experiment}",
            on_weights=slot.load_weights,
            experiment=slot.experiment,
            allow_lossy=self.cfg.inference.weights_lossy,
            shm_dir=self.cfg.inference.weights_shm_dir or None,
        ).start()

    def add_experiment(self, exp: ExperimentConfig) -> PolicySlot:
        """Serve an experiment defined at run time: its own batcher and weight stream, then its robots' routes."""
        slot = PolicySlot(self, exp.name)
        slot.batcher.start()
        self._subscribe(slot)
        self.slots = {**self.slots, exp.name: slot}
        self._defined.add(exp.name)
        self.router.add(exp)
        log.info("serving an experiment defined at run time", extra=kv(experiment=exp.name))
        return slot

    def remove_experiment(self, name: str) -> None:
        """Serve a removed experiment no more: routes first, then its slot, weight stream and batcher."""
        self.router.remove(name)
        slot = self.slots.get(name)
        self.slots = {n: s for n, s in self.slots.items() if n != name}
        self._defined.discard(name)
        if slot is not None:
            if slot.subscriber is not None:
                slot.subscriber.stop()
                slot.subscriber = None
            slot.batcher.stop()
            slot.forget_metrics()  # after the batcher: no forward of it is left to count a failure
        log.info("experiment removed by control; no longer served", extra=kv(experiment=name))

    def _watch_experiments(self) -> None:
        """Every EXPERIMENTS_POLL_S, ask control for experiments defined at run time: serve the new ones, drop
        the removed ones (Control.RemoveExperiment)."""
        while not self._watch_stop.wait(EXPERIMENTS_POLL_S):
            new, listed = self.router.defined_experiments()
            for exp in new:
                if exp.name not in self.slots and not self._watch_stop.is_set():
                    self.add_experiment(exp)
            for name in sorted(self._defined - listed) if listed is not None else []:
                if not self._watch_stop.is_set():
                    self.remove_experiment(name)

    def stop(self) -> None:
        self._watch_stop.set()
        if self._watcher is not None:
            self._watcher.join(5.0)
        # Calls in flight finish (the batcher still runs during the server's grace), then the workers go.
        if self.running is not None:
            self.running.stop()
            self.running = None
        for slot in self.slots.values():
            if slot.subscriber is not None:
                slot.subscriber.stop()
                slot.subscriber = None
            slot.batcher.stop()
        self.router.close()


def run(cfg: StackConfig, ready_file: str | None) -> int:
    import torch

    # Per-robot MLP forwards are latency-bound; extra intra-op threads only contend with the learner.
    torch.set_num_threads(1)
    service = InferenceService(cfg)
    with report_to_control(service):
        rpc.serve_until_signal(service, "inference", ready_file)
    return 0


def report_to_control(service: InferenceService) -> contextlib.AbstractContextManager[WorkerReporter]:
    """The worker report run() keeps sending: device and the experiments this process serves a policy for
    (one slot each, the names `userctl exp status` and ListWorkers show)."""
    cfg, ic = service.cfg, service.cfg.inference
    return report_worker(service, "inference", ic.control_addr, cfg.auth, ic.device, lambda: list(service.slots))
