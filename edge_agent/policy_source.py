"""Where a robot's actions come from: the Inference service (remote) or a weight-streamed local copy.

Both answer within a deadline or return None, and the robot holds still: the control loop never
waits on the network or the learner. A policy answering with action chunks (horizon, A) has them
executed one action per tick by an edge_agent.chunks.ChunkExecutor per robot, which asks for the
next chunk in the background before the current one runs out and blends overlapping chunks.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import grpc
import numpy as np
import prometheus_client

from edge_agent.chunks import ChunkExecutor
from edge_agent.encoder import EncodedFrames, Plan, encode_observation, robot_plans
from user import wire
from user.config import AuthConfig, RobotSelector, StackConfig
from user.log import kv
from user.rpc import CLIENT_ERRORS, make_channel
from user.v1 import inference_pb2, inference_pb2_grpc, robot_pb2

if TYPE_CHECKING:  # torch is imported only by edges that run a local copy
    from user.policy import Policy
    from user.weights import WeightSet

log = logging.getLogger(__name__)

# Fine around typical deadlines (20-100 ms): bench/load_bench.py reads p50/p99 off these buckets.
_LATENCY_BUCKETS = (0.0005, 0.001, 0.0015, 0.002, 0.003, 0.004, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.025, 0.03)
ACTION_LATENCY = prometheus_client.Histogram(
    "user_edge_action_latency_seconds",
    "Time from asking the policy source for an action to having it (answered requests)",
    ["source"],
    buckets=(*_LATENCY_BUCKETS, 0.04, 0.05, 0.06, 0.08, 0.1, 0.16, 0.5, 1.0, 2.5, 5.0),
)
_REMOTE_LATENCY = ACTION_LATENCY.labels("remote")
ACT_METHOD = "/user.v1.Inference/Act"  # errors of ActBatch calls count here too, per robot: one request each
ACTION_TIMEOUTS = prometheus_client.Counter(
    "user_edge_action_timeouts_total",
    "Action requests without a usable answer in time (the robot held), by reason",
    ["source", "reason"],
)


class PolicySource(ABC):
    """act() answers within deadline_s or returns None; it never raises for transport problems."""

    @abstractmethod
    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        """(action (A,), policy version) for one unbatched observation, or None (robot holds)."""

    @property
    @abstractmethod
    def version(self) -> int:
        """Latest policy version seen (0 = none yet)."""

    def reset(self, robot_id: str) -> None:  # noqa: B027 - optional hook
        """Chunks planned for robot_id so far must not run on: a new episode starts, or the policy did not drive
        its last tick (a human did, or it held or was paused) and the world moved on without it."""

    def skip(self, robot_id: str, ticks: int) -> None:  # noqa: B027 - optional hook
        """The control loop of robot_id skipped `ticks` ticks (a step overran): chunk rows meant for them are past."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release channels and threads."""

    def route(self, robot_id: str, experiment: str, kind: str = "") -> None:  # noqa: B027 - optional hook
        """Control leased robot_id (of `kind`) to `experiment` ("" = to none: the robot holds): a source holding one
        copy per experiment sends its next requests there (inference routes remote requests itself)."""


def _as_chunk(action: np.ndarray) -> np.ndarray:
    """(A,) or (horizon, A) -> (horizon, A) float32; anything else is flattened to one action."""
    arr = np.asarray(action, dtype=np.float32)
    return arr if arr.ndim == 2 else arr.reshape(1, -1)


class _Chunked:
    """A ChunkExecutor per robot around a fetch(robot_id, observation, deadline_s) function."""

    def __init__(
        self,
        fetch: Callable[[str, dict[str, np.ndarray], float], tuple[np.ndarray, int] | None],
        prefetch: int = 2,
        adaptive: bool = True,
    ) -> None:
        self._fetch = fetch
        self.prefetch, self.adaptive = prefetch, adaptive  # see ChunkExecutor
        self.executors: dict[str, ChunkExecutor] = {}
        self._deadline_s: dict[str, float] = {}

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        self._deadline_s[robot_id] = deadline_s
        executor = self.executors.get(robot_id)
        if executor is None:
            executor = self.executors[robot_id] = ChunkExecutor(
                lambda obs: self._fetch(robot_id, obs, self._deadline_s[robot_id]),
                prefetch=self.prefetch,
                adaptive=self.adaptive,
            )
        return executor.tick(observation)

    def reset(self, robot_id: str) -> None:
        executor = self.executors.get(robot_id)
        if executor is not None:
            executor.reset()

    def skip(self, robot_id: str, ticks: int) -> None:
        executor = self.executors.get(robot_id)
        if executor is not None:
            executor.skip(ticks)


ACT_BATCH_WINDOW_S = 0.005  # longest a robot waits for the others of its agent before its batch goes out
ACTIVE_S = 1.0  # a robot that asked this recently is expected in the next batch
# "no action from inference" lines: at most one a minute (an outage flapping at the control rate wrote ~55k a day)
ERROR_LOG_EVERY_S = 60.0
_CODES = {code.value[0]: code for code in grpc.StatusCode}


@dataclass
class _Ask:
    request: inference_pb2.ActRequest
    end: float  # monotonic deadline of this robot's answer
    done: threading.Event = field(default_factory=threading.Event)
    result: inference_pb2.ActResult | None = None


class ActBatcher:
    """One Inference.ActBatch call for the robots of an agent that ask together, instead of a call each.

    The robots of one agent tick on one grid (EdgeAgent starts them at the same instant), so they ask
    within a millisecond or so of each other. The first to ask opens a batch and waits until every
    robot active in the last second is in, or ACT_BATCH_WINDOW_S (at most a quarter of its deadline);
    then it makes the call for all of them and hands each its result. A gRPC call costs the edge and
    inference far more CPU than the observation it carries: one call per tick instead of one per robot
    is most of the control path's CPU on a loaded machine."""

    def __init__(self, stub: inference_pb2_grpc.InferenceStub, window_s: float = ACT_BATCH_WINDOW_S) -> None:
        self._stub, self.window_s = stub, window_s
        self._cond = threading.Condition()
        self._open: list[_Ask] | None = None
        self._asked: dict[str, float] = {}  # robot id -> last ask (monotonic)
        self.calls = 0

    def act(self, request: inference_pb2.ActRequest, deadline_s: float) -> inference_pb2.ActResult:
        """This robot's result (code 0 = answered); DEADLINE_EXCEEDED when it did not come in time."""
        now = time.monotonic()
        ask = _Ask(request, now + deadline_s)
        with self._cond:
            self._asked[request.robot_id] = now
            leader = self._open is None
            if leader:
                self._open = [ask]
            else:
                self._open.append(ask)
                self._cond.notify_all()
        if leader:
            self._send(self._gather(now, deadline_s))
        elif not ask.done.wait(max(0.0, ask.end - time.monotonic())):
            return inference_pb2.ActResult(code=grpc.StatusCode.DEADLINE_EXCEEDED.value[0], message="batch too late")
        assert ask.result is not None
        return ask.result

    def _gather(self, now: float, deadline_s: float) -> list[_Ask]:
        until = now + min(self.window_s, deadline_s / 4)
        with self._cond:
            for rid in [r for r, t in self._asked.items() if now - t > ACTIVE_S]:
                del self._asked[rid]
            expected = len(self._asked)
            while self._open is not None and len(self._open) < expected:
                left = until - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            batch, self._open = self._open or [], None
        return batch

    def _send(self, batch: list[_Ask]) -> None:
        timeout = max(0.0, min(a.end for a in batch) - time.monotonic())
        self.calls += 1
        try:
            resp = self._stub.ActBatch(
                inference_pb2.ActBatchRequest(requests=[a.request for a in batch]), timeout=timeout
            )
            results = list(resp.results)
            if len(results) != len(batch):
                raise ValueError(f"{len(results)} results for {len(batch)} requests")
        except grpc.RpcError as err:
            code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
            failed = inference_pb2.ActResult(code=code.value[0], message=err.details() or "")
            results = [failed] * len(batch)
        except Exception as err:  # a closed channel, a short answer: every robot of the batch holds, none hangs
            results = [inference_pb2.ActResult(code=grpc.StatusCode.INTERNAL.value[0], message=str(err))] * len(batch)
        for ask, result in zip(batch, results, strict=True):
            ask.result = result
            ask.done.set()


class RemotePolicy(PolicySource):
    """Inference.Act with timeout=deadline: DEADLINE_EXCEEDED, UNAVAILABLE ("no policy yet") -> None.

    With `robots` > 1 the robots' requests go out together as ActBatch calls (ActBatcher); an inference
    server without ActBatch (UNIMPLEMENTED) gets one Act per robot from then on. `frame_plans` (robot id ->
    Plan) JPEG/PNG-encodes those robots' camera frames in each request (a tenth of the bytes over Wi-Fi);
    inference decodes them to the declared shapes before the policy sees them; with `frames` (shared with the
    edge's FrameEncoder) each encoded frame is kept so the step of the same observation is not encoded again.
    `chunk_prefetch` and `adaptive_prefetch` go to each robot's ChunkExecutor (when to ask for the next chunk)."""

    def __init__(
        self,
        addr: str,
        auth: AuthConfig,
        deterministic: bool = False,
        instruction: str = "",
        robots: int = 1,
        frame_plans: Mapping[str, Plan] | None = None,
        chunk_prefetch: int = 2,
        adaptive_prefetch: bool = True,
        frames: EncodedFrames | None = None,
    ) -> None:
        self.addr = addr
        self.instruction = instruction  # sent with every request; "" = the policy's default
        self.frame_plans = dict(frame_plans or {})
        self.frames = frames
        self._chunks = _Chunked(self._fetch, chunk_prefetch, adaptive_prefetch)
        self._channel = make_channel(addr, auth)
        self._stub = inference_pb2_grpc.InferenceStub(self._channel)
        self.batcher = ActBatcher(self._stub) if robots > 1 else None
        # Connect now (a cheap Status call, result unused), so the first action does not pay the
        # TCP/HTTP2 handshake inside its deadline.
        self._warmup = self._stub.Status.future(inference_pb2.InferenceStatusRequest(), timeout=5.0)
        self._deterministic = deterministic
        self._version = 0
        self._last_error: grpc.StatusCode | None = None  # of the current run of failed calls; None = answering
        self._logged_code: grpc.StatusCode | None = None  # the code this run's warning named; None = none yet
        self._warned_at = -ERROR_LOG_EVERY_S  # monotonic time of the last warning
        self._unlogged = 0  # failed calls since the last warning

    @property
    def version(self) -> int:
        return self._version

    @property
    def chunks_received(self) -> int:
        """Answers received over all robots (a one-action policy's answers count too)."""
        return sum(executor.received for executor in self._chunks.executors.values())

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        return self._chunks.act(robot_id, observation, deadline_s)

    def _call(self, request: inference_pb2.ActRequest, deadline_s: float) -> inference_pb2.ActResponse | None:
        """The answer, or None after counting and (on a change) logging why there is none."""
        if self.batcher is not None:
            result = self.batcher.act(request, deadline_s)
            if result.code == 0:
                return result.response
            code = _CODES.get(result.code, grpc.StatusCode.UNKNOWN)
            if code == grpc.StatusCode.UNIMPLEMENTED:  # an older inference server: one Act per robot
                log.warning("inference has no ActBatch; one Act per robot", extra=kv(addr=self.addr))
                self.batcher = None
            self._note_error(code, result.message)
            return None
        try:
            return self._stub.Act(request, timeout=deadline_s)
        except grpc.RpcError as err:
            code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
            self._note_error(code, err.details() if hasattr(err, "details") else str(err))
            return None

    def _fetch(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        request = inference_pb2.ActRequest(
            robot_id=robot_id,
            observation=encode_observation(observation, self.frame_plans.get(robot_id), robot_id, self.frames),
            deterministic=self._deterministic,
            instruction=self.instruction,
        )
        start = time.perf_counter()
        resp = self._call(request, deadline_s)
        if resp is None:
            return None
        try:
            action = _as_chunk(wire.from_tensor(resp.action))
        except wire.WireError as err:
            ACTION_TIMEOUTS.labels("remote", "bad_action").inc()
            log.warning("undecodable action from inference", extra=kv(error=str(err)))
            return None
        _REMOTE_LATENCY.observe(time.perf_counter() - start)
        if self._last_error is not None:  # said at INFO only when the run of errors was (else a DEBUG line)
            level = logging.INFO if self._logged_code is not None else logging.DEBUG
            log.log(level, "inference answers again", extra=kv(addr=self.addr, version=resp.policy_version))
            self._last_error = self._logged_code = None
        self._version = int(resp.policy_version)
        return action, self._version

    def reset(self, robot_id: str) -> None:
        self._chunks.reset(robot_id)

    def skip(self, robot_id: str, ticks: int) -> None:
        self._chunks.skip(robot_id, ticks)

    def _note_error(self, code: grpc.StatusCode, details: str) -> None:
        ACTION_TIMEOUTS.labels("remote", code.name.lower()).inc()
        CLIENT_ERRORS.labels(ACT_METHOD, code.name).inc()
        self._last_error, self._unlogged = code, self._unlogged + 1
        now = time.monotonic()
        # A run of errors is said once (and again if its code changes), at most one line a minute however it flaps.
        if code != self._logged_code and now - self._warned_at >= ERROR_LOG_EVERY_S:
            log.warning(
                "no action from inference; holding",
                extra=kv(addr=self.addr, code=code.name, details=details, failed_calls=self._unlogged),
            )
            self._logged_code, self._warned_at, self._unlogged = code, now, 0

    def close(self) -> None:
        self._warmup.cancel()
        self._channel.close()


class _Worker:
    """One robot's forward passes on a thread of their own (reused), so its control loop waits at most a deadline.

    One job at a time: while a late job still runs, a call gets no answer at once (the robot holds) instead of
    queueing behind it, and the late job's result is dropped when it lands."""

    def __init__(self, name: str) -> None:
        self._cond = threading.Condition()
        self._job: Callable[[], object] | None = None
        self._busy = self._closed = False
        self._finished = 0  # jobs run so far; a caller waits for its own number
        self._given_up = 0  # the last job whose caller stopped waiting
        self._result: object = None
        self._error: Exception | None = None
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def call(self, job: Callable[[], object], timeout_s: float) -> tuple[bool, object]:
        """(True, job()) when it finished within timeout_s, else (False, None); what job() raised in time is
        raised here."""
        with self._cond:
            if self._busy or self._closed:
                return False, None
            self._busy, self._job = True, job
            ticket = self._finished + 1
            self._cond.notify_all()
            if not self._cond.wait_for(lambda: self._finished >= ticket, max(0.0, timeout_s)):
                self._given_up = ticket
                return False, None
            result, error, self._result, self._error = self._result, self._error, None, None
        if error is not None:
            raise error
        return True, result

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._job is not None or self._closed)
                if self._job is None:
                    return
                job, self._job = self._job, None
            result: object = None
            error: Exception | None = None
            try:
                result = job()
            except Exception as exc:  # the caller's to raise, or ours to log once it stopped waiting
                error = exc
            with self._cond:
                self._finished += 1
                late = self._given_up == self._finished
                self._result, self._error, self._busy = (None, None, False) if late else (result, error, False)
                self._cond.notify_all()
            if late and error is not None:
                log.warning("a late local forward failed", extra=kv(error=repr(error)))


class LocalPolicy(PolicySource):
    """A local policy copy kept fresh by a WeightSubscriber; new weights swap in atomically.

    Each robot's forward runs on a worker thread of its own and act() waits at most its deadline: a forward that
    misses it (a GC pause, a first CUDA call, a starved CPU) leaves the robot holding, not waiting on it."""

    def __init__(
        self,
        learner_addr: str,
        auth: AuthConfig,
        client_id: str,
        deterministic: bool = False,
        start: bool = True,
        experiment: str = "",
        kinds: dict[str, str] | None = None,
        allow_lossy: bool = False,
        shm_dir: str | None = None,
    ) -> None:
        """shm_dir: read weight versions from this shared-memory directory when the learner proves it shares it."""
        import user.policy  # noqa: F401 - torch loads now, not in the weight thread while robots run
        from user.weights import WeightSubscriber

        self._policy: Policy | None = None  # replaced whole, never mutated: reading it needs no lock
        self._kinds = kinds or {}  # robot id -> kind: a policy shared by embodiments pads by kind
        self._deterministic = deterministic
        self._lock = threading.Lock()  # serialises forward passes of robots sharing this copy
        self._chunks = _Chunked(self._fetch)
        self._workers: dict[str, _Worker] = {}  # robot id -> its forward thread
        self._workers_lock = threading.Lock()
        self._closed = False  # set by close(), read under _workers_lock: no worker thread starts after it
        self._refused: dict[str, int] = {}  # robot id -> version whose refusal of its observations was logged
        self._subscriber = WeightSubscriber(
            learner_addr,
            auth,
            client_id,
            self._on_weights,
            experiment=experiment,
            allow_lossy=allow_lossy,
            shm_dir=shm_dir,
        )
        if start:
            self._subscriber.start()

    @property
    def version(self) -> int:
        policy = self._policy
        return int(policy.version) if policy is not None else 0

    def _on_weights(self, weights: WeightSet) -> None:
        """Build the new network off the control path, then swap the reference. A build error
        propagates to the subscriber, which logs it and keeps the previous version."""
        from user.policy import build_policy

        policy = build_policy(weights.policy, weights.policy_tensors(), weights.version)
        self._policy = policy
        log.info("local policy updated", extra=kv(version=int(policy.version)))

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        if self._closed:  # a copy RoutedPolicy dropped while this robot's loop was still asking it: hold
            return None
        return self._chunks.act(robot_id, observation, deadline_s)

    def _fetch(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        policy = self._policy
        if policy is None:
            ACTION_TIMEOUTS.labels("local", "no_policy").inc()
            return None
        worker = self._worker(robot_id)
        if worker is None:  # closed meanwhile: the robot holds
            return None
        start = time.perf_counter()
        done, answer = worker.call(lambda: self._forward(policy, robot_id, observation), deadline_s)
        if not done:  # a stale action is worse than holding still: the late one is dropped when it lands
            ACTION_TIMEOUTS.labels("local", "late").inc()
            return None
        if answer is not None:
            ACTION_LATENCY.labels("local").observe(time.perf_counter() - start)
        return answer  # type: ignore[return-value] - _forward's

    def _worker(self, robot_id: str) -> _Worker | None:
        """The robot's forward thread, started on its first call; None once closed (a thread started then would
        never be stopped)."""
        worker = self._workers.get(robot_id)
        if worker is None:
            with self._workers_lock:
                if self._closed:
                    return None
                worker = self._workers.get(robot_id)
                if worker is None:
                    worker = self._workers[robot_id] = _Worker(f"local-policy-{robot_id}")
        return worker

    def _forward(
        self, policy: Policy, robot_id: str, observation: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, int] | None:
        """One forward pass on the robot's worker thread."""
        from user.experiments import embodiment_inputs, fit_action

        kind = self._kinds.get(robot_id, "")
        try:
            batched = {name: np.asarray(v)[None] for name, v in embodiment_inputs(policy, kind, observation).items()}
            with self._lock:
                action = fit_action(policy, kind, policy.act(batched, self._deterministic))
        except ValueError as err:  # observation does not fit this policy: hold, say why once a streak and version
            ACTION_TIMEOUTS.labels("local", "bad_observation").inc()
            if self._refused.get(robot_id) != int(policy.version):
                self._refused[robot_id] = int(policy.version)
                log.warning(
                    "local policy refused the observation; holding (logged once until it takes one)",
                    extra=kv(robot_id=robot_id, version=int(policy.version), error=str(err)),
                )
            return None
        if self._refused.pop(robot_id, None) is not None:
            log.info("local policy takes the observations again", extra=kv(robot_id=robot_id))
        return _as_chunk(np.asarray(action)[0]), int(policy.version)

    def reset(self, robot_id: str) -> None:
        self._chunks.reset(robot_id)

    def skip(self, robot_id: str, ticks: int) -> None:
        self._chunks.skip(robot_id, ticks)

    def close(self) -> None:
        self._subscriber.stop()
        with self._workers_lock:
            self._closed = True
            workers, self._workers = list(self._workers.values()), {}
        for worker in workers:
            worker.close()


class RoutedPolicy(PolicySource):
    """Local copies, one per experiment: each robot asks the copy of the experiment it works for.

    Control's leases say which experiment that is (route(), called by the agent on every lease that is not a
    hold), so a robot leased to an experiment defined while the edge runs, or plugged in later, gets that
    experiment's own weights; until its first lease the edge's config decides. A copy no robot routes to any
    more is closed. Robots without a route, or leased to none, ask `default`: the config's only experiment when
    it takes every robot (no `experiments` section, or one without a selector), as inference serves them; else
    they hold."""

    def __init__(
        self,
        make: Callable[[str], PolicySource],
        routes: dict[str, str],
        kinds: dict[str, str] | None = None,
        default: str | None = None,
    ) -> None:
        """make(experiment) builds a copy; routes: robot id -> experiment; kinds: robot id -> kind, shared with
        the copies (a policy shared by embodiments pads by kind) and kept current by route()."""
        self._make = make
        self._lock = threading.Lock()
        self.kinds = kinds if kinds is not None else {}
        self.sources: dict[str, PolicySource] = {}  # experiment -> copy
        self.routes: dict[str, PolicySource | None] = {}  # robot id -> copy (None: holds); replaced whole
        self._experiment_of: dict[str, str] = {}
        self._default = self._source(default) if default is not None else None
        self._default_name = default
        for robot_id, experiment in routes.items():
            self.route(robot_id, experiment)

    def _source(self, experiment: str) -> PolicySource:
        source = self.sources.get(experiment)
        if source is None:
            source = self.sources[experiment] = self._make(experiment)
        return source

    def route(self, robot_id: str, experiment: str, kind: str = "") -> None:
        if kind:
            self.kinds[robot_id] = kind
        with self._lock:
            if robot_id in self.routes and self._experiment_of.get(robot_id, "") == experiment:
                return
            previous = self._experiment_of.pop(robot_id, None)
            # Leased to none: the copy that serves any robot (the config's only experiment, when it selects every
            # robot, as inference routes), else none and the robot holds.
            source = self._source(experiment) if experiment else self._default
            if experiment:
                self._experiment_of[robot_id] = experiment
            self.routes = {**self.routes, robot_id: source}
            stale = None
            if previous not in (None, self._default_name) and previous not in self._experiment_of.values():
                stale = self.sources.pop(previous)
        if previous is not None:
            log.info("robot routed to another experiment's policy", extra=kv(robot_id=robot_id, experiment=experiment))
        if stale is not None:
            stale.close()

    @property
    def version(self) -> int:
        return max((s.version for s in list(self.sources.values())), default=0)

    def _for(self, robot_id: str) -> PolicySource | None:
        return self.routes.get(robot_id, self._default)

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        source = self._for(robot_id)
        return source.act(robot_id, observation, deadline_s) if source is not None else None

    def reset(self, robot_id: str) -> None:
        source = self._for(robot_id)
        if source is not None:
            source.reset(robot_id)

    def skip(self, robot_id: str, ticks: int) -> None:
        source = self._for(robot_id)
        if source is not None:
            source.skip(robot_id, ticks)

    def close(self) -> None:
        with self._lock:
            sources, self.sources = list(self.sources.values()), {}
        for source in sources:
            source.close()


def robot_experiments(cfg: StackConfig, specs: list[robot_pb2.RobotSpec] | None = None) -> dict[str, str]:
    """robot id -> experiment name, from the robots' specs (labels included) or else their configured kinds."""
    from user.experiments import experiment_for

    if specs is None:
        specs = [robot_pb2.RobotSpec(robot_id=r.id, kind=r.kind) for r in cfg.edge.robots]
    out = {}
    for spec in specs:
        exp = experiment_for(spec, cfg.resolved_experiments())
        out[spec.robot_id] = exp.name if exp is not None else ""
    return out


def make_policy_source(
    cfg: StackConfig,
    client_id: str,
    specs: list[robot_pb2.RobotSpec] | None = None,
    frames: EncodedFrames | None = None,
) -> PolicySource:
    """Remote (one Inference address for every robot) or local copies, one per experiment of this agent's robots.
    `frames`: where a remote source keeps the frames it encoded, for the edge's FrameEncoder to reuse."""
    if cfg.edge.policy_source == "local":
        routes = robot_experiments(cfg, specs)
        names = sorted(set(routes.values()))
        lossy, shm = cfg.edge.weights_lossy, cfg.edge.weights_shm_dir or None
        kinds = {s.robot_id: s.kind for s in specs} if specs else {r.id: r.kind for r in cfg.edge.robots}
        sole = names[0] if len(names) <= 1 else None  # "" when no robot is known yet: the learner's default
        experiments = cfg.resolved_experiments()
        takes_any = len(experiments) == 1 and (not cfg.experiments or experiments[0].robots == RobotSelector())
        default = experiments[0].name if takes_any else None  # serves any robot, as inference's router does

        def local_copy(name: str) -> PolicySource:
            return LocalPolicy(
                cfg.edge.learner_addr,
                cfg.auth,
                client_id if name in (sole, default) else f"{client_id}-{name}",
                experiment=name,
                kinds=kinds,
                allow_lossy=lossy,
                shm_dir=shm,
            )

        return RoutedPolicy(local_copy, routes, kinds, default=default)
    return RemotePolicy(
        cfg.edge.inference_addr,
        cfg.auth,
        robots=len(specs) if specs else len(cfg.edge.robots),
        frame_plans=robot_plans(cfg.edge.robots, specs or [], act=True),
        frames=frames,
    )
