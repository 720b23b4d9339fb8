"""The edge agent: the daemon on each robot PC.

One RobotLoop thread per robot runs observe -> act -> observe at the robot's control rate and
ships every step to replay; the policy source answers within a deadline or the robot holds still,
so nothing here ever waits on the learner. Each robot's task judges every step (reward, termination,
success); its teleoperator, if any, is polled every tick and, when it answers, drives instead of the
policy: the step goes to replay with `intervention = true` and the human action as the action. A
teleoperator that fails while its human drives leaves the robot holding, not to the policy the human
was overriding, until a teleoperator sends a human action again or an operator RESUMEs it (a poll that
answers None is not enough: a device back from a glitch may have lost that its human was driving).
Whenever the policy did not drive a tick (a human did, or the robot held or was paused) its planned
chunks are dropped: it plans afresh from the robot's current observation before it acts again.
A ControlClient registers the robots, heartbeats their status and delivers PAUSE / RESUME / RESET
commands.

    userctl edge --config configs/demo.yaml [--ready-file F]
"""

from __future__ import annotations

import logging
import math
import numbers
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import grpc
import numpy as np
import prometheus_client

from edge_agent.control_client import ControlClient
from edge_agent.encoder import EncodedFrames, FrameEncoder, Plan, robot_plans
from edge_agent.policy_source import PolicySource, make_policy_source
from edge_agent.replay_client import ReplaySender
from edge_agent.robot import ROBOTS, Observation, Robot, action_bounds, clip_action, make_robot
from edge_agent.spool import open_outbox
from edge_agent.task import TASKS, Outcome, ParamError, Task
from edge_agent.teleop import TELEOPERATORS, Teleoperator
from user import rpc, wire
from user.config import ConfigError, RobotConfig, StackConfig
from user.log import kv
from user.registry import PluginError, Registry
from user.spec import SpecError, StepError, action_check, check_observation, validate_spec
from user.v1 import control_pb2, robot_pb2, step_pb2

log = logging.getLogger(__name__)

LOOP_PERIOD = prometheus_client.Histogram(
    "user_edge_loop_period_seconds",
    "Time between consecutive control ticks",
    ["robot_id"],
    buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.08, 0.1, 0.15, 0.2, 0.5, 1.0, 2.5, 5.0),
)
LOOP_JITTER = prometheus_client.Histogram(
    "user_edge_loop_jitter_seconds",
    "|actual tick period - target period| in realtime mode",
    ["robot_id"],
    buckets=(0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0),
)
LOOP_OVERRUNS = prometheus_client.Counter(
    "user_edge_loop_overruns_total", "Control ticks skipped because a step took longer than the period", ["robot_id"]
)
ENV_STEPS = prometheus_client.Counter("user_edge_env_steps_total", "Control steps taken (held ones too)", ["robot_id"])
EPISODES = prometheus_client.Counter("user_edge_episodes_total", "Finished episodes", ["robot_id", "success"])
HELD_STEPS = prometheus_client.Counter(
    "user_edge_held_steps_total", "Steps where no action came in time and the robot held still", ["robot_id"]
)
INTERVENTION_STEPS = prometheus_client.Counter(
    "user_edge_intervention_steps_total", "Steps where a teleoperator drove instead of the policy", ["robot_id"]
)
NON_FINITE_ACTIONS = prometheus_client.Counter(
    "user_edge_non_finite_actions_total",
    "Actions with NaN/Inf from the policy or the teleoperator: never sent to the robot, which held instead",
    ["robot_id", "source"],
)
TELEOP_ERRORS = prometheus_client.Counter(
    "user_edge_teleop_errors_total", "Teleoperator polls that raised or answered a wrong-sized action", ["robot_id"]
)
POLICY_VERSION = prometheus_client.Gauge(
    "user_edge_policy_version", "Policy version of the latest applied action", ["robot_id"]
)
EPISODE_RETURN = prometheus_client.Gauge("user_edge_last_episode_return", "Return of the latest episode", ["robot_id"])

ATTACHED = prometheus_client.Gauge(
    "user_edge_robot_attached", "1 while the robot is connected and its loop runs; 0 while absent", ["robot_id"]
)
DETACHES = prometheus_client.Counter(
    "user_edge_robot_detaches_total",
    "Robots taken offline because their loop failed (unplugged, bus error)",
    ["robot_id"],
)
TELEOP_ATTACHED = prometheus_client.Gauge(
    "user_edge_teleop_attached", "1 while the robot's teleoperator is connected; 0 while absent", ["robot_id"]
)
TELEOP_LOST_HOLDS = prometheus_client.Counter(
    "user_edge_teleop_lost_holds_total",
    "Steps held because the teleoperator failed while its human drove (until a human action again or a RESUME)",
    ["robot_id"],
)
TELEOP_DETACHES = prometheus_client.Counter(
    "user_edge_teleop_detaches_total",
    "Teleoperators released and reconnected because their polls kept failing (unplugged)",
    ["robot_id"],
)
ROBOT_FAILED = prometheus_client.Gauge(
    "user_edge_robot_failed",
    "1 once a plug-in error (a bad observation, action, outcome or spec; a task that raised) stopped the robot's "
    "loop for good: it holds and is not retried",
    ["robot_id"],
)
ROBOT_FAILING = prometheus_client.Gauge(
    "user_edge_robot_failing",
    "1 while the robot's loop failed soon after each of its last attaches (hot-plug keeps retrying it)",
    ["robot_id"],
)
ROBOT_FAULT = prometheus_client.Info(
    "user_edge_robot_fault", "Why the robot failed or keeps failing: state (failed, failing) and error", ["robot_id"]
)

RATE_WINDOW_S = 5.0
PERIOD_WINDOW = 1000  # recent tick periods kept for percentiles
PAUSED_POLL_S = 0.05  # fast mode: how often a paused loop re-checks
WATCH_POLL_S = 0.25  # hot-plug: how often the agent looks for failed loops and retries absent robots
REPLUG_MAX_S = 60.0  # hot-plug: the longest wait between connect tries of an absent robot
TELEOP_DETACH_S = 1.0  # hot-plug: a teleoperator whose polls fail this long is released and reconnected
TELEOP_ERRORS_REMEMBERED = 8  # distinct teleoperator errors whose traceback a loop logged (not logged again)
START_ALIGN_S = 0.1  # realtime: the robots' common first tick, this long after the agent starts them
REFUSED = "control refused this agent"  # the reason of the hold a refusal puts on every robot
FAILING_AFTER = 3  # hot-plug: loops in a row failing soon after attaching mark a robot failing (still retried)


class PluginFault(Exception):
    """A robot or task plug-in broke its contract (a bad observation, action or outcome; a task that raised).
    Retrying cannot fix code, so unlike a hardware fault (hot-plug's detach and reconnect) the robot holds and
    its loop stops for good."""


def _kind_of(registry: Registry[Any], plugin: object) -> str:
    """The registered kind of a plug-in instance (its class name when it was not built from the registry)."""
    return next((e.kind for e in registry.entries() if e.cls is type(plugin)), type(plugin).__name__)


def _report_fault(robot_id: str, state: str, error: str) -> None:
    """The edge's metrics say which robots failed and why (`userctl up` reads them for its console and summary)."""
    (ROBOT_FAILED if state == "failed" else ROBOT_FAILING).labels(robot_id).set(1)
    ROBOT_FAULT.labels(robot_id).info({"state": state, "error": error})


class _RobotMetrics:
    """One robot's labelled metric children, looked up once: labels() per tick costs a dict lookup under a lock."""

    def __init__(self, robot_id: str) -> None:
        self.period = LOOP_PERIOD.labels(robot_id)
        self.jitter = LOOP_JITTER.labels(robot_id)
        self.overruns = LOOP_OVERRUNS.labels(robot_id)
        self.steps = ENV_STEPS.labels(robot_id)
        self.held = HELD_STEPS.labels(robot_id)
        self.interventions = INTERVENTION_STEPS.labels(robot_id)
        self.version = POLICY_VERSION.labels(robot_id)
        self.teleop_lost = TELEOP_LOST_HOLDS.labels(robot_id)


class StepSink(Protocol):
    """Where finished steps go (ReplaySender); send() must not block."""

    def send(self, step: step_pb2.Step, table: str = "") -> int: ...

    @property
    def unacked(self) -> int: ...


class TickScheduler:
    """Fixed-rate ticks on a grid t0 + k*period: sleeping to an absolute time never drifts, and a
    step that overruns skips the ticks it missed instead of bursting to catch up.

    A late tick runs at once, standing for the grid tick nearest to it; the tick after it is the first grid tick
    at least half a period later, so two ticks are never closer than half a period (a late step is not followed
    by a doubled one), the grid keeps its phase (loops started together keep ticking together), and every grid
    tick passed over counts as an overrun."""

    def __init__(
        self,
        period_s: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], object] = time.sleep,
    ) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be > 0")
        self.period = period_s
        self._clock, self._sleep = clock, sleep
        self._next: float | None = None
        self.ticks = 0
        self.overruns = 0  # grid ticks skipped

    def start_at(self, first: float) -> None:
        """Put the grid's first tick at `first` (clock time) instead of the first wait(): loops started
        at one `first` tick together, so their robots' Acts can go out as one call."""
        self._next = first

    def wait(self) -> float:
        """Sleep until the next tick and return its scheduled time (the first tick is now)."""
        now = self._clock()
        if self._next is None:
            self._next = now
        late = now - self._next
        if late > 0:  # runs now; the grid ticks it passed over (those nearer to now than the next) are skipped
            skipped = max(0, math.ceil(late / self.period + 0.5) - 1)
            self._next += skipped * self.period
            self.overruns += skipped
        elif late < 0:
            self._sleep(-late)
        tick = self._next
        self._next += self.period
        self.ticks += 1
        return tick


class RobotLoop:
    """observe -> teleop or policy (deadline) -> act or hold -> observe -> task; one step per tick, to the sink."""

    def __init__(
        self,
        robot: Robot,
        policy: PolicySource,
        sink: StepSink,
        mode: str = "realtime",
        action_deadline_s: float = 0.04,
        task: Task | None = None,
        teleop: Teleoperator | None = None,
        where: str = "",
    ) -> None:
        """`where`: the robot's config entry (edge.robots[2]), named by the error of a plug-in breaking its contract."""
        if mode not in ("realtime", "fast"):
            raise ValueError(f"mode must be realtime or fast, got {mode!r}")
        self.robot, self.policy, self.sink = robot, policy, sink
        self.spec = robot.spec
        self.task = task if task is not None else TASKS.build("env", spec=self.spec)
        self.teleop = teleop  # replaced whole by the agent's hot-plug watcher; read once per use
        self.teleop_failing_since: float | None = None  # monotonic start of the current streak of failed polls
        self.teleop_error: str | None = None  # the latest failed poll's error, for the detach line
        self._human_at: float | None = None  # monotonic time of the teleoperator's latest action
        self.teleop_lost = False  # it failed while its human drove: hold until a human action or a RESUME
        self._plan_stale = True  # the policy did not drive the last tick: its chunks must not run on
        # Errors whose traceback was logged: the same error again (the next streak, a re-attached instance that
        # fails alike) is one debug line, so a teleoperator that always fails does not repeat its traceback.
        self._teleop_errors_logged: deque[str] = deque(maxlen=TELEOP_ERRORS_REMEMBERED)
        self.robot_id = self.spec.robot_id
        self.where = where or f"robot {self.robot_id}"
        self.mode = mode
        self.deadline_s = action_deadline_s
        rate = self.spec.control_rate_hz or 20.0
        self.period_s = 1.0 / rate
        self.max_episode_steps = int(self.spec.max_episode_steps) or 0
        self._low, self._high = action_bounds(self.spec)
        self._hold_action = clip_action(self.spec, np.zeros(self._low.shape, np.float32))
        self._action_check = action_check(self.spec)  # replay's check of a step's action, run here first
        self._action_dtype = wire.dtype_from_proto(self._action_check.dtype)
        self._non_finite = {src: NON_FINITE_ACTIONS.labels(self.robot_id, src) for src in ("policy", "teleop")}
        self._non_finite_run = 0  # non-finite actions since the last applied one (logged once a run)
        self._wrong_size_version: int | None = None  # policy version of the current wrong-size run (logged once)
        self._wrong_size_run = 0  # wrong-size policy answers since the last right-size one
        self._stop = threading.Event()
        self._paused = threading.Event()
        self._lease_hold = threading.Event()  # control: no running experiment for this robot (see set_lease)
        self.lease = control_pb2.RobotLease(robot_id=self.robot_id)
        self._table = ""  # replay table of the running episode ("" = "online")
        self._reset_requested = threading.Event()
        self._lock = threading.Lock()  # guards the stats below against status() from the control thread
        self._thread: threading.Thread | None = None
        self.scheduler = TickScheduler(self.period_s, sleep=self._stop.wait)
        # stats
        self.env_steps = self.held_steps = self.episodes = self.successes = self.intervention_steps = 0
        self.policy_version = 0
        self.last_held = False
        self.error: str | None = None
        self.failed: str | None = None  # the plug-in error that stopped the loop for good (not retried)
        ROBOT_FAILED.labels(self.robot_id).set(0)
        self._overruns_seen = 0
        self._periods: deque[float] = deque(maxlen=PERIOD_WINDOW)
        self._jitters: deque[float] = deque(maxlen=PERIOD_WINDOW)
        self._rate_samples: deque[tuple[float, int]] = deque()
        self._new_episodes: list[control_pb2.EpisodeSummary] = []
        self._labels = {"robot_id": self.robot_id}
        self._metrics = _RobotMetrics(self.robot_id)
        # Replay keys steps by (robot, episode, step) and the spool re-sends an earlier life's steps after a
        # restart: a per-life tag keeps episode ids unique even if the wall clock steps back meanwhile.
        self._life = secrets.token_hex(3)

    # ------------------------------------------------------------------ lifecycle and commands

    def start(self, first_tick: float | None = None) -> None:
        """`first_tick` (time.monotonic()): the realtime grid's first tick; default: when the loop is ready."""
        if first_tick is not None:
            self.scheduler.start_at(first_tick)
        self._thread = threading.Thread(target=self._run, name=f"loop-{self.robot_id}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0, wait: bool = True) -> None:
        """Graceful: the step in progress completes, then the robot holds."""
        self._stop.set()
        if wait and self._thread is not None:
            self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def pause(self) -> None:
        self._paused.set()

    def resume(self) -> None:
        """An operator's RESUME: a pause ends, and so does the hold of a robot whose teleoperator failed while its
        human drove (the operator hands it to the policy)."""
        if self.teleop_lost:
            self._human_at = None  # first: a poll failing meanwhile must not take the robot back
            self.teleop_lost = False
            log.info("operator resumed: the policy drives again", extra=kv(robot_id=self.robot_id))
        self._paused.clear()

    def set_teleop(self, teleop: Teleoperator | None) -> None:
        """Swap the teleoperator (hot-plug); None lets the policy drive from the next tick, unless the old one
        failed while its human drove (teleop_lost): then the robot holds until a teleoperator sends a human action
        (answering None is not enough) or a RESUME."""
        self.teleop_failing_since = None
        self.teleop = teleop

    def set_lease(self, lease: control_pb2.RobotLease) -> None:
        """Control's lease: hold (no actions, no steps) while the robot's experiment is stopped or full.
        Separate from PAUSE: an operator's RESUME does not override a stopped experiment."""
        self.lease = lease
        if lease.hold:
            self._lease_hold.set()
        else:
            self._lease_hold.clear()

    @property
    def held_by_lease(self) -> bool:
        return self._lease_hold.is_set()

    def request_reset(self) -> None:
        """End the current episode: the next step is marked truncated and a new episode starts."""
        self._reset_requested.set()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    # ------------------------------------------------------------------ loop

    def _run(self) -> None:
        try:
            self._loop()
        except PluginFault as fault:
            self._fail(fault)
        except Exception as exc:  # the robot's hardware (unplugged, bus error): hot-plug reconnects it
            self.error = repr(exc)
            log.exception("robot loop failed; holding", extra=kv(robot_id=self.robot_id))
        finally:
            try:
                self.robot.hold()
            except Exception:
                log.exception("robot hold failed", extra=kv(robot_id=self.robot_id))

    def _loop(self) -> None:
        obs, self._obs_ns = self._checked(self.robot.reset(), "reset()"), time.time_ns()
        self._begin_episode(obs)
        # After a pause or hold the first step holds: its observation is the one the last step was judged on (replay
        # pairs that step with it), its next is taken after the pause, and only the step after that acts on it.
        was_held = False
        last_tick: float | None = None
        while not self._stop.is_set():
            tick_start = self._wait_tick()
            if self._stop.is_set():
                break
            last_tick = self._record_period(last_tick, tick_start)
            if skipped := self._new_overruns():
                self.policy.skip(self.robot_id, skipped)  # chunk rows are per tick: the skipped ticks' are past
            if self._paused.is_set() or self._lease_hold.is_set() or not self._sink_accepting():
                self.robot.hold()
                was_held = self._plan_stale = True
                if self.mode == "fast":
                    self._stop.wait(PAUSED_POLL_S)
                    last_tick = None  # a paused gap is not a loop period
                continue
            obs, was_held = self._step(obs, hold=was_held), False

    def _fail(self, fault: PluginFault) -> None:
        """One error line naming the plug-in, its config entry and the field; the traceback only when it raised."""
        self.error = self.failed = str(fault)
        _report_fault(self.robot_id, "failed", self.failed)
        cause = fault.__cause__
        log.error(
            "robot failed: a plug-in broke its contract; the robot holds and its loop stops (not retried)",
            exc_info=(type(cause), cause, cause.__traceback__) if cause is not None else None,
            extra=kv(robot_id=self.robot_id, error=self.failed),
        )

    # ------------------------------------------------------------------ plug-in contract checks

    def robot_named(self) -> str:
        """The robot as errors name it: its config entry, kind and id."""
        return f"{self.where} (robot {_kind_of(ROBOTS, self.robot)}, id {self.robot_id})"

    def _robot_fault(self, what: str) -> PluginFault:
        return PluginFault(f"{self.robot_named()}: {what}")

    def _task_fault(self, what: str) -> PluginFault:
        where = f"{self.where}.task" if self.where.startswith("edge.") else f"the task of {self.where}"
        return PluginFault(f"{where} (task {_kind_of(TASKS, self.task)}, robot {self.robot_id}): {what}")

    def _checked(self, obs: object, call: str) -> Observation:
        """The robot's observation if it is what the spec declares (replay's check: keys, dtype, shape, finite), else
        a PluginFault. Nothing is converted (a list, float64 for float32): the plug-in's author must hear of it."""
        if not isinstance(obs, Observation) or not isinstance(obs.features, Mapping):
            raise self._robot_fault(f"{call} returned {type(obs).__name__}, not an Observation with a features dict")
        for name, value in obs.features.items():
            if not isinstance(value, np.ndarray | np.generic):
                raise self._robot_fault(
                    f"{call} returned observation[{name!r}] as a {type(value).__name__}, not a numpy array"
                )
        try:
            check_observation("observation", obs.features, self.spec.observation)
        except StepError as exc:
            raise self._robot_fault(f"{call} returned {exc}") from None
        return obs

    def _checked_action(self, applied: object, call: str = "act()") -> np.ndarray:
        """What act() (or hold()) reports it applied, if it is of the spec's shape and within its limits (replay's
        check), else a PluginFault: steps of actions the robot did not take, or out of its declared range, would
        teach nothing."""
        if applied is None:
            raise self._robot_fault(f"{call} returned None; it must return the action it applied")
        try:
            action = np.asarray(applied, self._action_dtype)
            self._action_check(wire.to_tensor(action))
        except (TypeError, ValueError) as exc:  # StepError and WireError are ValueErrors
            why = str(exc).removesuffix(" (the edge must clip)")  # the edge did: the robot reports another action
            raise self._robot_fault(f"{call} returned a bad action: {why}") from None
        return action

    def _held(self) -> np.ndarray:
        """Hold the robot; a held step records what hold() says it commanded (checked like act()'s answer), or,
        from a robot whose hold() returns None (it does not say), the spec's clipped zeros."""
        applied = self.robot.hold()
        if applied is None:
            return self._hold_action
        return self._checked_action(applied, "hold()")

    def _judge(self, obs: Observation, applied: np.ndarray, nxt: Observation) -> Outcome:
        """The task's outcome, if it is an Outcome with a finite reward; a task that raises is a PluginFault too."""
        try:
            outcome = self.task.evaluate(obs, applied, nxt)
        except Exception as exc:
            raise self._task_fault(f"evaluate() raised {type(exc).__name__}: {_one_line(exc)}") from exc
        if not isinstance(outcome, Outcome):
            raise self._task_fault(f"evaluate() returned {type(outcome).__name__}, not an Outcome")
        reward = outcome.reward
        if not isinstance(reward, numbers.Real) or not math.isfinite(reward):
            raise self._task_fault(f"evaluate() returned reward {reward!r}; it must be a finite number")
        return outcome

    def _sink_accepting(self) -> bool:
        """A full spool under the pause policy: hold still, collect nothing, until acks free space."""
        return getattr(self.sink, "accepting", True)

    def _wait_tick(self) -> float:
        if self.mode == "realtime":
            self.scheduler.wait()
        return time.monotonic()

    def _record_period(self, last_tick: float | None, now: float) -> float:
        if last_tick is not None:
            period = now - last_tick
            self._metrics.period.observe(period)
            with self._lock:
                self._periods.append(period)
                if self.mode == "realtime":
                    jitter = abs(period - self.period_s)
                    self._jitters.append(jitter)
                    self._metrics.jitter.observe(jitter)
        return now

    def _new_overruns(self) -> int:
        """Ticks the scheduler skipped since the last call (counted in the metric)."""
        overruns = self.scheduler.overruns - self._overruns_seen
        if overruns:
            self._metrics.overruns.inc(overruns)
            self._overruns_seen = self.scheduler.overruns
        return overruns

    def _begin_episode(self, obs: Observation) -> None:
        start_ns = time.time_ns()
        self.episode_id = f"{self.robot_id}-{start_ns}-{self._life}"
        self.step_index = 0
        self._return = 0.0
        self._success = False
        self._episode_version = 0
        self._episode_interventions = 0
        self.policy.reset(self.robot_id)  # a chunk left from the last episode must not act in this one
        self._plan_stale = False
        try:
            self.task.reset(obs)
        except Exception as exc:
            raise self._task_fault(f"reset() raised {type(exc).__name__}: {_one_line(exc)}") from exc
        if (teleop := self.teleop) is not None:
            teleop.reset(obs)

    def _poll_teleop(self, obs: Observation) -> np.ndarray | None:
        """The teleoperator's action this tick, or None. A device failing while nobody drives lets the policy drive,
        loudly. One failing while its human drives (an action within TELEOP_DETACH_S, the detach window) sets
        teleop_lost: the robot holds instead of going back to the policy the human was overriding, through the
        detach and after it, until a poll returns a finite human action (this device, or a fresh one hot-plug
        attaches) or an operator RESUMEs it. A poll answering None does not release it: a device back from a glitch
        may have lost that its human was driving (lerobot's intervention state), and the policy must not drive."""
        if (teleop := self.teleop) is None:
            return None
        try:
            human = teleop.poll(obs)
        except Exception as exc:
            TELEOP_ERRORS.labels(**self._labels).inc()
            now = time.monotonic()
            if not self.teleop_lost and self._human_at is not None and now - self._human_at <= TELEOP_DETACH_S:
                self.teleop_lost = True
                log.warning(
                    "teleoperator failed while its human drove: the robot holds until it answers again or an "
                    "operator resumes",
                    extra=kv(robot_id=self.robot_id, error=f"{type(exc).__name__}: {exc}"),
                )
            if self.teleop_failing_since is None:  # once per failure streak, not at the control rate
                self.teleop_failing_since = now
                self._log_teleop_error(exc)
            return None
        self.teleop_failing_since = None
        if human is None:
            return None
        human = np.asarray(human, np.float32)
        if human.size != self._hold_action.size:
            TELEOP_ERRORS.labels(**self._labels).inc()
            log.warning(
                "teleoperator action has the wrong size; ignored",
                extra=kv(robot_id=self.robot_id, got=int(human.size), want=self._hold_action.size),
            )
            return None
        self._human_at = time.monotonic()
        if self.teleop_lost and np.isfinite(human).all():  # its human drives again: the hold ends
            self.teleop_lost = False
            log.info("teleoperator sends actions again: the robot is released", extra=kv(robot_id=self.robot_id))
        return human.reshape(self._hold_action.shape)

    def _log_teleop_error(self, exc: Exception) -> None:
        """A failed poll starting a streak: its traceback the first time this error is seen, one debug line after."""
        self.teleop_error = error = f"{type(exc).__name__}: {exc}"
        if error in self._teleop_errors_logged:
            log.debug("teleoperator poll failed again", extra=kv(robot_id=self.robot_id, error=error))
            return
        self._teleop_errors_logged.append(error)
        if self.teleop_lost:
            log.exception("teleoperator poll failed; the robot holds", extra=kv(robot_id=self.robot_id))
        else:
            log.exception("teleoperator poll failed; the policy drives", extra=kv(robot_id=self.robot_id))

    def _decide(self, obs: Observation, hold: bool = False) -> tuple[np.ndarray, int, bool, bool]:
        """(applied action, policy version, held, intervention). A human action wins; no answer in time -> hold.
        An action with a NaN or Inf is never sent to the robot (it holds); every other is clipped to the spec's
        limits here, whatever the robot plug-in does. `hold`: hold whatever (the first step after a pause).

        A tick the policy does not drive marks its plan stale: the next tick it drives starts from a chunk planned
        on that tick's observation, never from rows planned before the human, the hold or the pause. A tick it
        drove but had no answer for keeps its chunks: their rows follow the ticks, and the one in flight ends
        the hold."""
        if hold:
            return self._hold_step()
        human = self._poll_teleop(obs)
        if human is not None:
            self._plan_stale = True
            if not self._finite(human, "teleop"):
                return self._held(), 0, True, False
            return self._checked_action(self.robot.act(self._clip(human))), 0, False, True
        if self.teleop_lost:  # its human drove when it failed: not handed back to the policy they overrode
            self._metrics.teleop_lost.inc()
            return self._hold_step()
        if self._plan_stale:
            self.policy.reset(self.robot_id)
            self._plan_stale = False
        answer = self.policy.act(self.robot_id, obs.features, self.deadline_s)
        if answer is None:
            return self._held(), 0, True, False
        if np.asarray(answer[0]).size != self._hold_action.size:
            return self._wrong_size(int(np.asarray(answer[0]).size), int(answer[1]))
        if self._wrong_size_run:
            log.info("policy actions have the right size again", extra=kv(robot_id=self.robot_id))
            self._wrong_size_version, self._wrong_size_run = None, 0
        action, version = answer
        action = np.asarray(action, np.float32).reshape(self._hold_action.shape)
        if not self._finite(action, "policy", int(version)):
            return self._hold_step()  # the rest of a chunk with a NaN is not run either
        applied = self._checked_action(self.robot.act(self._clip(action)))
        return applied, int(version), False, False

    def _wrong_size(self, got: int, version: int) -> tuple[np.ndarray, int, bool, bool]:
        """A policy answer of the wrong size: the robot holds. Logged, and the plan dropped, once per run and policy
        version: every row of a chunk has that size, and re-planning every tick would fetch synchronously at the
        control rate while nothing it answers can be run."""
        self._wrong_size_run += 1
        if version == self._wrong_size_version:
            return self._held(), 0, True, False
        self._wrong_size_version = version
        log.warning(
            "policy action has the wrong size; holding (logged once until a right-size one or another version)",
            extra=kv(robot_id=self.robot_id, got=got, want=self._hold_action.size, version=version),
        )
        return self._hold_step()

    def _hold_step(self) -> tuple[np.ndarray, int, bool, bool]:
        """A held step the policy did not drive: its plan is stale."""
        self._plan_stale = True
        return self._held(), 0, True, False

    def _clip(self, action: np.ndarray) -> np.ndarray:
        """A finite action clipped to the spec's limits (as clip_action, bounds computed once): the README's
        promise holds whatever a robot plug-in's act() does."""
        return np.clip(action, self._low, self._high).astype(np.float32)

    def _finite(self, action: np.ndarray, source: str, version: int = 0) -> bool:
        """Is every value finite? A non-finite action is counted; the first of a run of them is logged (and the
        run's end, with its length)."""
        if np.isfinite(action).all():
            if self._non_finite_run:
                log.info(
                    "finite actions again; the robot acts",
                    extra=kv(robot_id=self.robot_id, non_finite_actions=self._non_finite_run),
                )
                self._non_finite_run = 0
            return True
        self._non_finite[source].inc()
        if not self._non_finite_run:
            log.warning(
                "non-finite action (NaN/Inf); the robot holds instead (logged once until a finite one comes)",
                extra=kv(robot_id=self.robot_id, source=source, version=version, action=action.reshape(-1).tolist()),
            )
        self._non_finite_run += 1
        return False

    def _step(self, obs: Observation, hold: bool = False) -> Observation:
        started = time.monotonic()
        applied, version, held, human = self._decide(obs, hold)
        acted_ns = time.time_ns()
        nxt = self._checked(self.robot.observe(), "observe()")
        next_ns = time.time_ns()
        outcome = self._judge(obs, applied, nxt)
        last_index = self.max_episode_steps > 0 and self.step_index + 1 >= self.max_episode_steps
        reset = self._reset_requested.is_set()
        truncated = not outcome.terminated and (last_index or reset)
        done = outcome.terminated or truncated
        step = step_pb2.Step(
            robot_id=self.robot_id,
            episode_id=self.episode_id,
            step_index=self.step_index,
            observation=wire.to_tensor_map(obs.features),
            action=wire.to_tensor(np.asarray(applied, self._action_dtype)),
            reward=float(outcome.reward),
            terminated=bool(outcome.terminated),
            truncated=bool(truncated),
            success=bool(outcome.success),
            intervention=human,
            policy_version=version,
            held=held,
            observed_at_ns=self._obs_ns,
            acted_at_ns=acted_ns,
        )
        if done:
            step.final_observation.CopyFrom(wire.to_tensor_map(nxt.features))
        if self.step_index == 0:  # the lease's table at its first step holds the whole episode
            self._table = self.lease.table
        self.sink.send(step, self._table)
        self._count(outcome, version, held, human)
        if held and self.mode == "fast":
            # Unthrottled holding would flood replay with still frames: a held tick lasts a deadline.
            self._stop.wait(max(0.0, self.deadline_s - (time.monotonic() - started)))
        if not done:
            self.step_index += 1
            self._obs_ns = next_ns
            return nxt
        self._end_episode(step)
        if reset:
            self._reset_requested.clear()
        obs, self._obs_ns = self._checked(self.robot.reset(), "reset()"), time.time_ns()
        self._begin_episode(obs)
        return obs

    def _count(self, outcome: Outcome, version: int, held: bool, human: bool) -> None:
        self._return += float(outcome.reward)
        self._success = self._success or bool(outcome.success)
        self._episode_interventions += int(human)
        self._metrics.steps.inc()
        if held:
            self._metrics.held.inc()
        elif human:
            self._metrics.interventions.inc()
        else:
            self._episode_version = max(self._episode_version, version)
            self._metrics.version.set(version)
        now = time.monotonic()
        with self._lock:
            self.env_steps += 1
            self.held_steps += int(held)
            self.intervention_steps += int(human)
            self.last_held = held
            if not (held or human):
                self.policy_version = version
            if not self._rate_samples or now - self._rate_samples[-1][0] >= 0.1:
                self._rate_samples.append((now, self.env_steps))
                while now - self._rate_samples[0][0] > RATE_WINDOW_S:
                    self._rate_samples.popleft()

    def _end_episode(self, last: step_pb2.Step) -> None:
        summary = control_pb2.EpisodeSummary(
            robot_id=self.robot_id,
            episode_id=self.episode_id,
            length=self.step_index + 1,
            episode_return=self._return,
            success=self._success,
            ended_at_ns=time.time_ns(),
            policy_version=self._episode_version,
            intervention_steps=self._episode_interventions,
        )
        EPISODES.labels(robot_id=self.robot_id, success=str(self._success).lower()).inc()
        EPISODE_RETURN.labels(**self._labels).set(self._return)
        with self._lock:
            self.episodes += 1
            self.successes += int(self._success)
            self._new_episodes.append(summary)
        log.debug(
            "episode finished",
            extra=kv(robot_id=self.robot_id, episode_id=self.episode_id, length=summary.length, success=self._success),
        )

    # ------------------------------------------------------------------ reporting

    def status(self, drain: bool = True) -> control_pb2.RobotStatus:
        """This robot's heartbeat status; drain=True hands over the episodes finished since the last call."""
        with self._lock:
            episodes = self._new_episodes
            if drain:
                self._new_episodes = []
            periods = list(self._periods)
            rate = self._rate_locked()
            status = control_pb2.RobotStatus(
                robot_id=self.robot_id,
                state=self._state_locked(),
                episodes=self.episodes,
                successes=self.successes,
                env_steps=self.env_steps,
                env_steps_per_s=rate,
                policy_version=self.policy_version,
                loop_period_p99_ms=float(np.percentile(periods, 99) * 1000) if periods else 0.0,
                held_steps=self.held_steps,
                new_episodes=episodes,
                intervention_steps=self.intervention_steps,
            )
        status.steps_unacked = self.sink.unacked
        return status

    def _rate_locked(self) -> float:
        """Env steps per second over the last RATE_WINDOW_S up to now, so a paused robot falls to 0 (samples
        are only taken when steps happen)."""
        now = time.monotonic()
        while self._rate_samples and now - self._rate_samples[0][0] > RATE_WINDOW_S:
            self._rate_samples.popleft()
        if len(self._rate_samples) < 2:
            return 0.0
        t0, n0 = self._rate_samples[0]
        return (self.env_steps - n0) / (now - t0)

    def _state_locked(self) -> int:
        if self._paused.is_set() or self._lease_hold.is_set() or not self._sink_accepting():
            return control_pb2.ROBOT_STATE_PAUSED
        if self.error is not None:
            return control_pb2.ROBOT_STATE_OFFLINE
        return control_pb2.ROBOT_STATE_HOLDING if self.last_held else control_pb2.ROBOT_STATE_RUNNING

    def loop_stats(self) -> dict[str, float]:
        """Percentiles of recent tick periods and jitter (seconds), for reports and benchmarks."""
        with self._lock:
            periods, jitters = np.asarray(self._periods), np.asarray(self._jitters)
        out: dict[str, float] = {"ticks": float(len(periods)), "overruns": float(self.scheduler.overruns)}
        for name, arr in (("period", periods), ("jitter", jitters)):
            if arr.size:
                out[f"{name}_p50_s"] = float(np.percentile(arr, 50))
                out[f"{name}_p99_s"] = float(np.percentile(arr, 99))
        return out


def encoding_plans(cfg: StackConfig, robots: list[Robot]) -> dict[str, Plan]:
    """Per robot, the camera features its config (edge.robots[i].image_encoding) encodes on the edge."""
    return robot_plans(cfg.edge.robots, [robot.spec for robot in robots])


@dataclass
class _Absent[D: (Robot, Teleoperator)]:
    """A configured device that is not connected (not plugged in at start, or unplugged since)."""

    device: D
    failures: int = 0
    next_try: float = 0.0  # monotonic


class EdgeAgent:
    """Robots from cfg.edge.robots, one RobotLoop each, plus the replay sender, policy source and control client.

    Hot-plug (edge.replug_s > 0): a robot that does not connect at start, or whose loop fails later (a
    pulled USB cable ends in a bus error), is absent: control hears the agent's new robot set (it goes
    offline there and its lease is released) and the agent retries connecting it, with backoff, on a
    fresh instance built from its config entry. When it connects it gets a new loop and registers again.
    """

    def __init__(
        self,
        cfg: StackConfig,
        robots: list[Robot] | None = None,
        policy: PolicySource | None = None,
        sender: ReplaySender | None = None,
    ) -> None:
        self.cfg = cfg
        edge = cfg.edge
        self.robots = robots if robots is not None else self._build_robots(cfg)
        if robots is not None:  # handed in, not built from their entries: their specs are checked here
            for robot in robots:
                check_robot_spec(robot, _entry_where(self._entry_index(robot.spec.robot_id), robot.spec.robot_id))
        self.tasks, self.teleops = build_judges_and_teleops(cfg, self.robots)
        self.sender = sender or ReplaySender(edge.replay_addr, cfg.auth, start=False, outbox=open_outbox(edge))
        # robots with image_encoding: frames encoded off their loops, before the spool (edge_agent/encoder.py)
        plans = encoding_plans(cfg, self.robots)
        frames = EncodedFrames() if plans else None  # frames Act requests encoded, reused by the steps
        self.encoder = FrameEncoder(self.sender, plans, edge.encode_threads, frames=frames) if plans else None
        self.sink: StepSink = self.encoder if self.encoder is not None else self.sender
        self.policy = policy or make_policy_source(cfg, edge.agent_id, [r.spec for r in self.robots], frames)
        self._absent_teleops: dict[str, _Absent[Teleoperator]] = {}  # not connected yet, by their robot's id
        # Robots attached now. Replaced whole on every hot-plug change, never mutated: other threads iterate it.
        self.loops = {r.spec.robot_id: self._make_loop(r) for r in self.robots}
        self._absent: dict[str, _Absent[Robot]] = {}  # touched by start() and then the watcher thread only
        self._leaving: list[RobotLoop] = []  # detached loops whose last status goes out with the next heartbeat
        self._leaving_lock = threading.Lock()
        self._grid0: float | None = None  # the realtime grid's first tick, for robots that attach later
        self._attached_at: dict[str, float] = {}  # robot_id -> when its loop started (monotonic)
        self._flaps: dict[str, int] = {}  # robot_id -> loops in a row that failed within REPLUG_MAX_S
        self._teleop_attached_at: dict[str, float] = {}  # robot_id -> when its teleoperator connected (monotonic)
        self._teleop_flaps: dict[str, int] = {}  # robot_id -> teleoperators in a row that failed within REPLUG_MAX_S
        self.failed: dict[str, str] = {}  # robot_id -> the plug-in error that stopped it for good (never retried)
        self._failing: set[str] = set()  # robots whose last FAILING_AFTER loops failed soon after attaching
        self._watch_stop = threading.Event()
        self._watcher: threading.Thread | None = None
        self.control = ControlClient(
            edge.control_addr,
            cfg.auth,
            edge.agent_id,
            [r.spec for r in self.robots],
            status_fn=self.status,
            on_command=self.on_command,
            on_registered=self.on_registered,
            site=edge.site,
            start=False,
            on_leases=self.on_leases,
            on_refused=self.on_refused,
        )

    @staticmethod
    def _build_robots(cfg: StackConfig) -> list[Robot]:
        robots: list[Robot] = []
        try:
            for index, rc in enumerate(cfg.edge.robots):
                robots.append(_build_robot(cfg, index, rc))
        except Exception:
            for robot in robots:
                robot.close()
            raise
        return robots

    def _make_loop(self, robot: Robot) -> RobotLoop:
        edge, rid = self.cfg.edge, robot.spec.robot_id
        return RobotLoop(
            robot,
            self.policy,
            self.sink,
            edge.mode,
            edge.action_deadline_ms / 1000.0,
            task=self.tasks[rid],
            teleop=None if rid in self._absent_teleops else self.teleops.get(rid),
            where=_entry_where(self._entry_index(rid), rid),
        )

    def start(self) -> None:
        for robot in self.robots:
            self._connect_at_start(robot)
        for rid, teleop in self.teleops.items():
            self._connect_teleop_at_start(rid, teleop)
        self.control.set_robots(self._attached_specs())
        self.control.start()
        # Control names this agent's replay shard on registration: wait briefly so the first steps go there
        # (a refusal ends the wait: the robots start held, see on_refused).
        self.control.wait_answered(self.cfg.edge.rpc_timeout_s)
        self.sender.start()
        # One grid for every robot: they tick together (their Acts share a call) and the first tick
        # leaves each loop time to reset its robot.
        self._grid0 = first_tick = time.monotonic() + START_ALIGN_S
        for loop in self.loops.values():
            loop.start(first_tick)
        if self.cfg.edge.replug_s > 0:
            self._watcher = threading.Thread(target=self._watch, name="edge-hotplug", daemon=True)
            self._watcher.start()
        log.info(
            "edge agent started",
            extra=kv(
                agent_id=self.cfg.edge.agent_id,
                robots=list(self.loops),
                absent=list(self._absent),
                mode=self.cfg.edge.mode,
                policy_source=self.cfg.edge.policy_source,
            ),
        )

    # ------------------------------------------------------------------ hot-plug

    def _first_connect[D: (Robot, Teleoperator)](self, rid: str, device: D, what: str) -> _Absent[D] | None:
        """Connect a device at start. With hot-plug on, one that is not there comes back absent (retried later)."""
        if self.cfg.edge.replug_s <= 0:
            device.connect()  # no hot-plug: a device that is not there stops the agent
            return None
        try:
            device.connect()
        except Exception as exc:
            log.warning(
                f"{what} not connected at start; retrying in the background",
                extra=kv(robot_id=rid, error=repr(exc), retry_s=self.cfg.edge.replug_s),
            )
            return _Absent(device, failures=1, next_try=time.monotonic() + self.cfg.edge.replug_s)
        return None

    def _connect_at_start(self, robot: Robot) -> None:
        rid = robot.spec.robot_id
        absent = self._first_connect(rid, robot, "robot")
        if absent is not None:
            self.loops = {k: v for k, v in self.loops.items() if k != rid}
            self._absent[rid] = absent
        else:
            self._attached_at[rid] = time.monotonic()
        ATTACHED.labels(rid).set(int(absent is None))

    def _connect_teleop_at_start(self, rid: str, teleop: Teleoperator) -> None:
        """A teleoperator not plugged in yet (a gamepad) leaves its robot to the policy until it connects."""
        absent = self._first_connect(rid, teleop, "teleoperator")
        if absent is not None:
            self._absent_teleops[rid] = absent
            if rid in self.loops:
                self.loops[rid].set_teleop(None)
        else:
            self._teleop_attached_at[rid] = time.monotonic()
        TELEOP_ATTACHED.labels(rid).set(int(absent is None))

    def _try_attach_teleop(self, rid: str, absent: _Absent[Teleoperator]) -> None:
        try:
            absent.device.connect()
        except Exception as exc:
            absent.failures += 1
            absent.next_try = time.monotonic() + self._retry_s(absent.failures)
            log.info("teleoperator still absent", extra=kv(robot_id=rid, error=repr(exc)))
            return
        del self._absent_teleops[rid]
        loop = self.loops.get(rid)
        if loop is not None:
            loop.set_teleop(self.teleops[rid])
        self._teleop_attached_at[rid] = time.monotonic()
        TELEOP_ATTACHED.labels(rid).set(1)
        log.info("teleoperator attached", extra=kv(robot_id=rid, tries=absent.failures + 1))

    def _detach_teleop(self, rid: str, loop: RobotLoop) -> None:
        """Its polls kept failing (unplugged): the policy drives (or, when it failed while its human drove, the robot
        holds), and a fresh instance is connected when it can be."""
        old, error = loop.teleop, loop.teleop_error
        if old is None:
            return
        loop.set_teleop(None)
        TELEOP_DETACHES.labels(rid).inc()
        TELEOP_ATTACHED.labels(rid).set(0)
        log.warning(
            "teleoperator detached: its polls kept failing; "
            + (
                "the robot holds (it failed while its human drove) until its human drives again or an operator resumes"
                if loop.teleop_lost
                else "the policy drives until it connects again"
            ),
            extra=kv(robot_id=rid, error=error, retry_s=self.cfg.edge.replug_s),
        )
        wait = self._backoff_after_detach(rid, self._teleop_attached_at, self._teleop_flaps)
        self._absent_teleops[rid] = _Absent(self._fresh_teleop(rid, old), next_try=time.monotonic() + wait)

    def _fresh_teleop(self, rid: str, old: Teleoperator) -> Teleoperator:
        """A new instance from the config entry (the old device handle may be dead even once re-plugged), the
        old one released and the robot's task re-attached to it; without an entry the old one is retried."""
        index = self._entry_index(rid)
        entry = self.cfg.edge.robots[index].teleop if index is not None else None
        if entry is None:
            return old
        try:
            fresh = TELEOPERATORS.build(
                entry.kind, entry.params, where=f"edge.robots[{index}].teleop.params", spec=old.spec
            )
            attach = getattr(self.tasks.get(rid), "attach_teleop", None)
            if attach is not None:
                attach(fresh)
        except Exception:  # keep trying the old instance rather than lose the teleoperator
            log.exception(
                "rebuilding a detached teleoperator failed; retrying its old instance", extra=kv(robot_id=rid)
            )
            return old
        try:
            old.disconnect()
        except Exception as exc:  # expected after an unplug: the device is gone
            log.debug("release of a detached teleoperator failed", extra=kv(robot_id=rid, error=repr(exc)))
        self.teleops[rid] = fresh
        return fresh

    def _attached_specs(self) -> list[robot_pb2.RobotSpec]:
        return [r.spec for r in self.robots if r.spec.robot_id in self.loops]

    def _watch(self) -> None:
        while not self._watch_stop.wait(WATCH_POLL_S):
            try:
                now = time.monotonic()
                for rid, loop in list(self.loops.items()):
                    if not loop.alive and loop.failed is not None:
                        self._retire(rid, loop, loop.failed)
                    elif not loop.alive and loop.error is not None:
                        self._detach(rid, loop)
                    elif rid in self._flaps and now - self._attached_at.get(rid, now) >= REPLUG_MAX_S:
                        self._steady(rid)
                    elif (since := loop.teleop_failing_since) is not None and now - since >= TELEOP_DETACH_S:
                        self._detach_teleop(rid, loop)
                for rid, absent in list(self._absent.items()):
                    if now >= absent.next_try and not self._watch_stop.is_set():
                        self._try_attach(rid, absent)
                for rid, absent in list(self._absent_teleops.items()):
                    if now >= absent.next_try and not self._watch_stop.is_set():
                        self._try_attach_teleop(rid, absent)
            except Exception:  # the watcher must outlive any one robot's trouble
                log.exception("hot-plug watcher step failed")

    def _retire(self, rid: str, loop: RobotLoop | None, error: str) -> None:
        """A plug-in error stopped the robot (it holds): control hears it left, freeing its place; never retried."""
        self.failed[rid] = error
        ATTACHED.labels(rid).set(0)
        self._attached_at.pop(rid, None)
        if loop is not None:  # its last status (episodes it finished) goes out with the next heartbeat
            with self._leaving_lock:
                self._leaving.append(loop)
            self.loops = {k: v for k, v in self.loops.items() if k != rid}
            self.control.set_robots(self._attached_specs())
        self.policy.reset(rid)

    def _mark_failing(self, rid: str, loop: RobotLoop) -> None:
        """Its loop failed soon after each of its last FAILING_AFTER attaches (a reset that always raises, a broken
        arm): still retried, since hardware may come back, but shown as failing, not as a robot that comes and goes."""
        self._failing.add(rid)
        error = (
            f"{loop.robot_named()}: its loop failed {FAILING_AFTER} times in a row soon after attaching: {loop.error}"
        )
        _report_fault(rid, "failing", error)
        log.error(
            "robot keeps failing: its loop failed soon after each of its last attaches; hot-plug keeps retrying",
            extra=kv(robot_id=rid, failures=FAILING_AFTER, error=error),
        )

    def _steady(self, rid: str) -> None:
        """A loop ran REPLUG_MAX_S since it attached: the failures in a row are over."""
        del self._flaps[rid]
        if rid in self._failing:
            self._failing.discard(rid)
            ROBOT_FAILING.labels(rid).set(0)
            ROBOT_FAULT.remove(rid)
            log.info("robot runs steadily again after failing", extra=kv(robot_id=rid))

    def _detach(self, rid: str, loop: RobotLoop) -> None:
        """The loop failed (unplugged, bus error): release the robot, tell control, retry it later."""
        DETACHES.labels(rid).inc()
        ATTACHED.labels(rid).set(0)
        log.warning(
            "robot detached: its loop failed; it goes offline until it connects again",
            extra=kv(robot_id=rid, error=loop.error, retry_s=self.cfg.edge.replug_s),
        )
        with self._leaving_lock:
            self._leaving.append(loop)
        self.loops = {k: v for k, v in self.loops.items() if k != rid}
        self.control.set_robots(self._attached_specs())
        self.policy.reset(rid)  # chunks planned for the lost episode must not run after it comes back
        # A loop that fails soon after every attach (a bug, a broken arm) backs off like a failed connect.
        wait = self._backoff_after_detach(rid, self._attached_at, self._flaps)
        if self._flaps[rid] == FAILING_AFTER:
            self._mark_failing(rid, loop)
        self._absent[rid] = _Absent(self._fresh_instance(loop.robot), next_try=time.monotonic() + wait)

    def _backoff_after_detach(self, rid: str, attached_at: dict[str, float], flaps: dict[str, int]) -> float:
        """Seconds before the first retry of a detached device: longer each time it failed again within
        REPLUG_MAX_S of attaching (`attached_at`, `flaps`: the robots' or the teleoperators' books)."""
        quick = time.monotonic() - attached_at.pop(rid, 0.0) < REPLUG_MAX_S
        flaps[rid] = flaps.get(rid, 0) + 1 if quick else 0
        return self._retry_s(flaps[rid] + 1)

    def _entry_index(self, rid: str) -> int | None:
        """The index of the robot's entry in edge.robots (None: handed to the agent without one)."""
        return next((i for i, rc in enumerate(self.cfg.edge.robots) if rc.id == rid), None)

    def _retry_s(self, failures: int) -> float:
        return min(REPLUG_MAX_S, self.cfg.edge.replug_s * 2 ** min(failures - 1, 8))

    def _fresh_instance(self, robot: Robot) -> Robot:
        """A new instance from the robot's config entry (a device object after a bus error may be stuck
        half-open), the old one released; a robot handed to the agent without an entry is retried as it is."""
        rid = robot.spec.robot_id
        index = self._entry_index(rid)
        if index is None:
            return robot
        rc = self.cfg.edge.robots[index]
        try:
            fresh = make_robot(
                rc.kind, rc.id, rc.params, seed=self.cfg.edge.seed + index, where=f"edge.robots[{index}].params"
            )
        except Exception:  # keep trying the old instance rather than lose the robot
            log.exception("rebuilding a detached robot failed; retrying its old instance", extra=kv(robot_id=rid))
            return robot
        for closer in (robot.disconnect, robot.close):
            try:
                closer()
            except Exception as exc:  # expected after an unplug: the device is gone
                log.debug("release of a detached robot failed", extra=kv(robot_id=rid, error=repr(exc)))
        self.robots = [fresh if r is robot else r for r in self.robots]
        return fresh

    def _try_attach(self, rid: str, absent: _Absent[Robot]) -> None:
        try:
            absent.device.connect()
        except Exception as exc:
            absent.failures += 1
            wait = self._retry_s(absent.failures)
            absent.next_try = time.monotonic() + wait
            log.info("robot still absent", extra=kv(robot_id=rid, error=repr(exc), retry_s=round(wait, 2)))
            return
        where = _entry_where(self._entry_index(rid), rid)
        try:
            check_robot_spec(absent.device, where)
        except PluginError as exc:  # a spec read from the device it connected to: no retry can fix it
            self._fail_at_attach(rid, absent.device, str(exc))
            return
        loop = self._make_loop(absent.device)
        if self.control.registered is not None:  # act only once control has leased it (its experiment may be stopped)
            loop.set_lease(control_pb2.RobotLease(robot_id=rid, hold=True, reason="attached; waiting for a lease"))
        del self._absent[rid]
        self.loops = {**self.loops, rid: loop}  # before control hears of it: its lease must find the loop
        if (refusal := self.control.refusal) is not None:  # after the swap: a refusal from now on finds it too
            loop.set_lease(_refused_lease(rid, *refusal))
        self.control.set_robots(self._attached_specs())
        loop.start(self._next_tick(loop.period_s))
        self._attached_at[rid] = time.monotonic()
        ATTACHED.labels(rid).set(1)
        log.info("robot attached", extra=kv(robot_id=rid, tries=absent.failures + 1))

    def _fail_at_attach(self, rid: str, robot: Robot, error: str) -> None:
        """A robot plugged in with a spec that can never be valid: it holds and is marked failed, not retried."""
        del self._absent[rid]
        try:
            robot.hold()
        except Exception:
            log.exception("robot hold failed", extra=kv(robot_id=rid))
        _report_fault(rid, "failed", error)
        log.error("robot failed: its spec is invalid; it holds and is not retried", extra=kv(robot_id=rid, error=error))
        self._retire(rid, None, error)

    def _next_tick(self, period_s: float) -> float:
        """The next tick of the agent's grid a little ahead: a late robot ticks with the others."""
        earliest = time.monotonic() + START_ALIGN_S
        if self._grid0 is None or self.cfg.edge.mode != "realtime":
            return earliest
        return self._grid0 + math.ceil((earliest - self._grid0) / period_s) * period_s

    def stop(self, flush_timeout_s: float = 10.0) -> None:
        """Finish the current steps, hold, flush unacked steps to replay (bounded), close everything."""
        self._watch_stop.set()
        if self._watcher is not None:
            self._watcher.join(10.0)
        for loop in self.loops.values():
            loop.stop(wait=False)  # every robot finishes its step at once
        for loop in self.loops.values():
            loop.stop()
        end = time.monotonic() + flush_timeout_s
        if self.encoder is not None:  # queued steps into the spool first
            self.encoder.close(flush_timeout_s)
        flushed = self.sender.flush(max(0.0, end - time.monotonic()))
        if not flushed:
            log.warning("replay did not acknowledge every step before shutdown", extra=kv(unacked=self.sender.unacked))
        self.control.close()
        self.sender.close()
        self.policy.close()
        for name, closer in [
            *((f"teleop {rid}", t.disconnect) for rid, t in self.teleops.items()),
            *((f"task {rid}", t.close) for rid, t in self.tasks.items()),
            *((f"robot {r.spec.robot_id}", r.disconnect) for r in self.robots),
        ]:
            try:
                closer()
            except Exception:
                log.exception("close failed", extra=kv(what=name))
        log.info("edge agent stopped", extra=kv(agent_id=self.cfg.edge.agent_id, flushed=flushed))

    def status(self) -> list[control_pb2.RobotStatus]:
        with self._leaving_lock:  # episodes a robot finished before it was unplugged still reach control
            leaving, self._leaving = self._leaving, []
        statuses = [loop.status() for loop in [*leaving, *self.loops.values()]]
        outbox = self.sender.outbox
        for st in statuses:  # one outbox per agent: every robot reports it
            st.spool_steps, st.spool_bytes, st.spool_dropped = outbox.count, outbox.nbytes, outbox.dropped
            st.spool_full = outbox.full
        return statuses

    def on_registered(self, registered: control_pb2.Registered) -> None:
        if registered.replay_addr:
            self.sender.retarget(registered.replay_addr)
        # Registered after a refusal: a robot with a lease in this message gets it next, in place of the
        # refusal's hold; one without (an older control) acts as it did before the refusal.
        leased = {lease.robot_id for lease in registered.leases}
        for rid, loop in self.loops.items():
            if rid not in leased and loop.lease.hold and loop.lease.reason.startswith(REFUSED):
                loop.set_lease(control_pb2.RobotLease(robot_id=rid))
                log.info("robot no longer held: control registered this agent", extra=kv(robot_id=rid))

    def on_refused(self, code: grpc.StatusCode, details: str) -> None:
        """Control refused this agent (a token that may not register these robots, a robot id another agent holds,
        a bad spec). Replay would refuse their steps too, or mix them with another agent's: every robot holds (no
        actions, no steps) while the control client retries, and acts again once control registers and leases it.
        Not an exit: tokens files are re-read by the servers, so an operator's fix needs no restart here."""
        for rid, loop in self.loops.items():
            if not (loop.lease.hold and loop.lease.reason.startswith(REFUSED)):
                log.warning(
                    "robot holds: control refused this agent; it acts again once control registers it",
                    extra=kv(robot_id=rid, code=code.name, details=details),
                )
            loop.set_lease(_refused_lease(rid, code, details))

    def on_command(self, cmd: control_pb2.Command) -> tuple[bool, str]:
        return apply_command(self.loops, cmd)

    def on_leases(self, leases: list[control_pb2.RobotLease]) -> None:
        for lease in leases:
            loop = self.loops.get(lease.robot_id)
            if loop is None:
                continue
            if not lease.hold:  # a hold names no experiment; the robot keeps its route for when it is released
                self.policy.route(lease.robot_id, lease.experiment, loop.robot.spec.kind)
            if loop.lease.hold != lease.hold:
                log.info(
                    "robot holds: no running experiment" if lease.hold else "robot leased: running",
                    extra=kv(robot_id=lease.robot_id, experiment=lease.experiment, reason=lease.reason),
                )
            loop.set_lease(lease)


def _refused_lease(robot_id: str, code: grpc.StatusCode, details: str) -> control_pb2.RobotLease:
    return control_pb2.RobotLease(robot_id=robot_id, hold=True, reason=f"{REFUSED} ({code.name}): {details}")


def _entry_where(index: int | None, robot_id: str) -> str:
    """A robot's config entry, as errors name it (edge.robots[2]), or its id when it was handed in without one."""
    return f"edge.robots[{index}]" if index is not None else f"robot {robot_id}"


def check_robot_spec(robot: Robot, where: str) -> None:
    """Control's registration check (validate_spec), run on the edge: a spec that can never be valid (low > high)
    is a PluginError naming the entry, at start, not a registration control refuses for the whole run."""
    try:
        validate_spec(robot.spec)
    except SpecError as exc:
        raise PluginError(f"{where} (robot {_kind_of(ROBOTS, robot)}): its spec is invalid: {exc}") from None


def _build_robot(cfg: StackConfig, index: int, rc: RobotConfig) -> Robot:
    """One edge.robots entry's robot. One that cannot be built is a config error naming the entry (one line, exit
    2), not an absent robot: hot-plug retries connecting an instance, whose spec (features, cameras) the tasks,
    frame encoders and policy source are set up from at start; and lerobot remembers a missing driver package for
    the life of the process, so retrying the build could not see it installed. A device that is not there fails in
    connect(), which hot-plug retries while the other robots run."""
    where = f"edge.robots[{index}]"
    try:
        robot = make_robot(rc.kind, rc.id, rc.params, seed=cfg.edge.seed + index, where=f"{where}.params")
    except PluginError:
        raise
    except ImportError as exc:
        log.debug("robot build failed", exc_info=True, extra=kv(robot_id=rc.id))
        raise PluginError(f"{where} (robot {rc.id!r}, kind {rc.kind}): a driver it needs is missing: {exc}") from None
    except ValueError as exc:  # params valid one by one but not together (e.g. action limits vs. the device's joints)
        log.debug("robot build failed", exc_info=True, extra=kv(robot_id=rc.id))
        raise PluginError(f"{where}.params (robot {rc.id!r}): {exc}") from None
    except OSError as exc:
        log.debug("robot build failed", exc_info=True, extra=kv(robot_id=rc.id))
        raise PluginError(f"{where} (robot {rc.id!r}, kind {rc.kind}): cannot build the robot: {exc}") from None
    try:
        if robot.spec.robot_id != rc.id:  # the agent finds entries, leases and steps by this id
            raise PluginError(
                f"{where} (robot {rc.kind}): its spec says robot_id {robot.spec.robot_id!r}, not {rc.id!r}"
            )
        check_robot_spec(robot, where)
    except PluginError:
        robot.close()
        raise
    return robot


def build_judges_and_teleops(cfg: StackConfig, robots: list[Robot]) -> tuple[dict[str, Task], dict[str, Teleoperator]]:
    """Each robot's task (its config's, else the robot's default) and teleoperator (if configured).

    Params are validated here, at start, and errors name the dotted field (edge.robots[1].task.params.x); so do
    a task or teleoperator that refuses its robot (a classifier trained on a camera the robot lacks, a scripted
    expert for another robot kind): a PluginError, one line at `userctl edge`, not a traceback or a failing loop.
    """
    entries = {rc.id: (i, rc) for i, rc in enumerate(cfg.edge.robots)}
    tasks: dict[str, Task] = {}
    teleops: dict[str, Teleoperator] = {}
    for robot in robots:
        spec = robot.spec
        index, rc = entries.get(spec.robot_id, (None, RobotConfig(id=spec.robot_id, kind=spec.kind)))
        where = f"edge.robots[{index}]" if index is not None else f"robot {spec.robot_id}"
        task_kind, task_params = (rc.task.kind, rc.task.params) if rc.task is not None else (robot.default_task, {})
        tasks[spec.robot_id] = _build_plugin(TASKS, task_kind, task_params, f"{where}.task", spec)
        if rc.teleop is not None:
            entry = TELEOPERATORS.get(rc.teleop.kind, f"{where}.teleop.kind")
            if (why := entry.cls.unsupported(spec)) is not None:
                raise PluginError(
                    f"{where}.teleop.kind: {rc.teleop.kind} cannot drive robot {spec.robot_id!r} "
                    f"(kind {spec.kind}): {why}"
                )
            teleops[spec.robot_id] = _build_plugin(
                TELEOPERATORS, rc.teleop.kind, rc.teleop.params, f"{where}.teleop", spec
            )
        attach = getattr(tasks[spec.robot_id], "attach_teleop", None)  # a task judged from the teleop's events
        if attach is not None:
            try:
                attach(teleops.get(spec.robot_id))
            except ValueError as exc:
                raise PluginError(f"{where}.task: {_one_line(exc)}") from None
    return tasks, teleops


def _build_plugin[T](
    registry: Registry[T], kind: str, params: Mapping[str, Any], where: str, spec: robot_pb2.RobotSpec
) -> T:
    """A task or teleoperator of a robot entry (`where`: edge.robots[i].task). What its constructor refuses (a model
    folder without a model, a device that is not there) is a PluginError naming the entry, or with a ParamError the
    param (edge.robots[i].task.params.model), with the traceback at debug level."""
    try:
        return registry.build(kind, params, where=f"{where}.params", spec=spec)
    except PluginError:
        raise
    except ParamError as exc:
        log.debug("%s build failed", registry.interface, exc_info=True, extra=kv(robot_id=spec.robot_id))
        raise PluginError(f"{where}.params.{exc.field}: {_one_line(exc)}") from None
    except (ValueError, OSError, ImportError, RuntimeError) as exc:
        log.debug("%s build failed", registry.interface, exc_info=True, extra=kv(robot_id=spec.robot_id))
        raise PluginError(f"{where} ({registry.interface} {kind}, robot {spec.robot_id!r}): {_one_line(exc)}") from None


def _one_line(exc: BaseException) -> str:
    """An error's message on one line (a torch or pydantic message spans several)."""
    return "; ".join(line.strip() for line in str(exc).splitlines() if line.strip()) or type(exc).__name__


_COMMANDS: dict[int, Callable[[RobotLoop], None]] = {
    control_pb2.COMMAND_KIND_PAUSE: RobotLoop.pause,
    control_pb2.COMMAND_KIND_RESUME: RobotLoop.resume,
    control_pb2.COMMAND_KIND_RESET: RobotLoop.request_reset,
}


def apply_command(loops: dict[str, RobotLoop], cmd: control_pb2.Command) -> tuple[bool, str]:
    """PAUSE / RESUME / RESET one robot (cmd.robot_id) or all of them (empty robot_id)."""
    if cmd.robot_id and cmd.robot_id not in loops:
        return False, f"unknown robot {cmd.robot_id!r} on this agent"
    if cmd.kind not in _COMMANDS:
        return False, f"unsupported command kind {cmd.kind}"
    targets = [loops[cmd.robot_id]] if cmd.robot_id else list(loops.values())
    for loop in targets:
        _COMMANDS[cmd.kind](loop)
    name = control_pb2.CommandKind.Name(cmd.kind)
    log.info("command applied", extra=kv(command_id=cmd.command_id, kind=name, robots=[t.robot_id for t in targets]))
    return True, f"{name} applied to {len(targets)} robot(s)"


def run(cfg: StackConfig, ready_file: str | None) -> int:
    """Process entry (`userctl edge`): blocks until SIGTERM/SIGINT, then stops gracefully."""
    stop = rpc.install_signal_handlers()
    if cfg.edge.policy_source == "local":
        import torch

        torch.set_num_threads(1)  # one small forward per tick: extra threads only contend with the loop
    try:
        agent = EdgeAgent(cfg)
    except PluginError as exc:  # a robot, task or teleoperator entry of the config: one line, exit 2
        raise ConfigError(str(exc)) from None
    httpd, metrics_port = rpc.start_metrics_http(
        cfg.edge.metrics_host, cfg.edge.metrics_port, "edge.metrics_host", "edge.metrics_port"
    )
    try:
        agent.start()
        rpc.write_ready_file(
            ready_file, metrics_port=metrics_port, agent_id=cfg.edge.agent_id, robots=list(agent.loops)
        )
        while not stop.wait(0.5):  # wake now and then: a signal taken by another thread runs its handler here
            pass
    finally:
        agent.stop()
        httpd.shutdown()
        httpd.server_close()
    return 0
