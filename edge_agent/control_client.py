"""The edge's line to the Control service: register, heartbeat, receive commands, reconnect.

One background thread owns the Control.Connect stream. Heartbeats carry a RobotStatus per robot
from `status_fn()`; the finished-episode summaries inside them are not lost when a stream breaks:
the ones of the last heartbeat written on a broken stream go out again with the next one.
`set_robots` (hot-plug) sends the agent's new robot set on the live stream, and every later
registration carries it. A refusal (`_FATALISH`: control answered, and said no) is kept in `refusal`
and handed to `on_refused` until a registration succeeds: the agent holds its robots meanwhile.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from collections.abc import Callable, Iterator

import grpc
import prometheus_client

import user
from user.config import AuthConfig
from user.log import kv
from user.rpc import CLIENT_ERRORS, Backoff, make_channel
from user.v1 import control_pb2, control_pb2_grpc, robot_pb2

log = logging.getLogger(__name__)

HEARTBEATS = prometheus_client.Counter("user_edge_heartbeats_sent_total", "Heartbeats written to the control stream")
CONTROL_RECONNECTS = prometheus_client.Counter("user_edge_control_reconnects_total", "Control streams re-opened")
COMMANDS = prometheus_client.Counter("user_edge_commands_total", "Commands received from control", ["kind"])
CONNECTED = prometheus_client.Gauge("user_edge_control_connected", "1 while registered with control")

# Refusals that retrying soon will not fix (duplicate robot id, bad spec, bad token): retry slowly.
_FATALISH = (
    grpc.StatusCode.ALREADY_EXISTS,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.UNAUTHENTICATED,
    grpc.StatusCode.PERMISSION_DENIED,
    grpc.StatusCode.FAILED_PRECONDITION,
)
_POLL_S = 0.2

StatusFn = Callable[[], list[control_pb2.RobotStatus]]
CommandFn = Callable[[control_pb2.Command], "tuple[bool, str] | None"]
RegisteredFn = Callable[[control_pb2.Registered], None]
LeasesFn = Callable[[list[control_pb2.RobotLease]], None]
RefusedFn = Callable[[grpc.StatusCode, str], None]


class ControlClient:
    def __init__(
        self,
        addr: str,
        auth: AuthConfig,
        agent_id: str,
        specs: list[robot_pb2.RobotSpec],
        status_fn: StatusFn,
        on_command: CommandFn,
        hostname: str | None = None,
        backoff: Backoff | None = None,
        slow_retry_s: float = 10.0,
        start: bool = True,
        on_registered: RegisteredFn | None = None,
        site: str = "",
        on_leases: LeasesFn | None = None,
        on_refused: RefusedFn | None = None,
    ) -> None:
        self.addr = addr
        self.agent_id = agent_id
        self._register = control_pb2.RegisterRequest(
            agent_id=agent_id,
            hostname=hostname or socket.gethostname(),
            robots=specs,
            software_version=user.__version__,
            site=site,
        )
        self._on_registered = on_registered
        self._on_leases = on_leases
        self._on_refused = on_refused
        self._status_fn = status_fn
        self._on_command = on_command
        self._channel = make_channel(addr, auth)
        self._stub = control_pb2_grpc.ControlStub(self._channel)
        self._backoff = backoff or Backoff(initial_s=0.1, max_s=5.0)
        self._slow_retry_s = slow_retry_s
        self._stopping = threading.Event()
        self._final = threading.Event()
        self._lock = threading.Lock()
        self._results: queue.Queue[control_pb2.CommandResult] = queue.Queue()
        self._carry: dict[str, list[control_pb2.EpisodeSummary]] = {}  # episodes to (re)send next heartbeat
        self._in_flight: dict[str, list[control_pb2.EpisodeSummary]] = {}  # in the last heartbeat written
        self._call: grpc.Call | None = None
        self._stream_gen = 0
        self._registered: control_pb2.Registered | None = None
        self._registered_event = threading.Event()
        self._refusal: tuple[grpc.StatusCode, str] | None = None  # the last refusal, until a registration
        self._answered = threading.Event()  # control registered or refused this agent at least once
        self._robots_changed = threading.Event()  # set_robots since the stream last told control
        self.heartbeats = self.reconnects = 0
        self.last_error: grpc.StatusCode | None = None
        self._thread = threading.Thread(target=self._run, name="control-client", daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    @property
    def registered(self) -> control_pb2.Registered | None:
        return self._registered

    def wait_registered(self, timeout: float) -> bool:
        return self._registered_event.wait(timeout)

    @property
    def refusal(self) -> tuple[grpc.StatusCode, str] | None:
        """(code, details) of control's last refusal of this agent; None once registered (or never refused)."""
        return self._refusal

    def wait_answered(self, timeout: float) -> bool:
        """Wait until control registers or refuses this agent (or `timeout`); True when registered."""
        self._answered.wait(timeout)
        return self._registered is not None

    def set_robots(self, specs: list[robot_pb2.RobotSpec]) -> None:
        """The robots attached now (hot-plug): told to control on the live stream, and on every reconnect."""
        with self._lock:
            del self._register.robots[:]
            self._register.robots.extend(specs)
            self._robots_changed.set()

    def _robot_set(self) -> list[robot_pb2.RobotSpec]:
        with self._lock:
            self._robots_changed.clear()
            return list(self._register.robots)

    def close(self, final_heartbeat_timeout_s: float = 2.0) -> None:
        """Send a last heartbeat (the latest episodes), hang up cleanly, stop the thread."""
        self._stopping.set()
        if self._registered is not None and final_heartbeat_timeout_s > 0 and self._thread.is_alive():
            self._final.set()  # the request iterator sends one more heartbeat, then half-closes
            self._thread.join(final_heartbeat_timeout_s)  # control ends the stream once it has read it
        with self._lock:
            self._stream_gen += 1
            call = self._call
        if call is not None:
            call.cancel()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._channel.close()
        CONNECTED.set(0)

    # ------------------------------------------------------------------ stream

    def _run(self) -> None:
        first = True
        while not self._stopping.is_set():
            if not first:
                self.reconnects += 1
                CONTROL_RECONNECTS.inc()
            first = False
            code = self._stream_once()
            if self._stopping.is_set():
                return
            if code in _FATALISH:
                details = self._refusal[1] if self._refusal is not None else ""
                log.error(
                    "control refused this agent; its robots hold. Fix the config, the token or the duplicate agent. "
                    "Retrying slowly",
                    extra=kv(
                        addr=self.addr,
                        agent_id=self.agent_id,
                        code=code.name,
                        details=details,
                        retry_s=self._slow_retry_s,
                    ),
                )
                self._stopping.wait(self._slow_retry_s)
            else:
                self._backoff.sleep(self._stopping)

    def _stream_once(self) -> grpc.StatusCode | None:
        with self._lock:
            self._stream_gen += 1
            gen = self._stream_gen
        call = self._stub.Connect(self._requests(gen))
        with self._lock:
            self._call = call
        try:
            for msg in call:
                self._on_message(msg)
            code = None
            if not self._stopping.is_set():
                log.warning("control closed the stream", extra=kv(addr=self.addr))
        except grpc.RpcError as err:
            code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
            if not self._stopping.is_set():
                CLIENT_ERRORS.labels("/user.v1.Control/Connect", code.name).inc()
            if not self._stopping.is_set() and code not in _FATALISH:
                log.warning("control stream broken", extra=kv(addr=self.addr, code=code.name, details=err.details()))
            if not self._stopping.is_set() and code in _FATALISH:
                self._refused(code, err.details() or "")
        finally:
            with self._lock:
                self._call = None
                self._stream_gen += 1
                self._requeue_in_flight()
            self._registered = None
            self._registered_event.clear()
            CONNECTED.set(0)
        self.last_error = code
        return code

    def _refused(self, code: grpc.StatusCode, details: str) -> None:
        self._refusal = (code, details)
        if self._on_refused is not None:
            try:
                self._on_refused(code, details)
            except Exception:  # a bad callback must not kill the stream thread
                log.exception("on_refused handler failed", extra=kv(agent_id=self.agent_id))
        self._answered.set()

    def _on_message(self, msg: control_pb2.ControlMessage) -> None:
        kind = msg.WhichOneof("msg")
        if kind == "registered":
            self._registered = msg.registered
            self._refusal = None
            if self._on_registered is not None:  # before wait_registered() returns: the shard is set first
                try:
                    self._on_registered(msg.registered)
                except Exception:  # a bad callback must not kill the stream
                    log.exception("on_registered handler failed", extra=kv(agent_id=self.agent_id))
            self._apply_leases(list(msg.registered.leases))
            self._registered_event.set()
            self._answered.set()
            self._backoff.reset()
            CONNECTED.set(1)
            log.info(
                "registered with control",
                extra=kv(
                    agent_id=self.agent_id,
                    lease_id=msg.registered.lease_id,
                    heartbeat_interval_s=msg.registered.heartbeat_interval_s,
                    replay_addr=msg.registered.replay_addr,
                ),
            )
        elif kind == "command":
            self._dispatch(msg.command)
        elif kind == "leases":
            self._apply_leases(list(msg.leases.leases))

    def _apply_leases(self, leases: list[control_pb2.RobotLease]) -> None:
        """Which experiment each robot works for now; the agent holds the robots told to (before the loops act)."""
        if not leases or self._on_leases is None:
            return
        try:
            self._on_leases(leases)
        except Exception:  # a bad callback must not kill the stream
            log.exception("on_leases handler failed", extra=kv(agent_id=self.agent_id))

    def _dispatch(self, cmd: control_pb2.Command) -> None:
        # proto3 enums are open: a kind this build does not know must not end the stream thread.
        known = cmd.kind in control_pb2.CommandKind.values()
        COMMANDS.labels(
            control_pb2.CommandKind.Name(cmd.kind).removeprefix("COMMAND_KIND_").lower() if known else "unknown"
        ).inc()
        if not known or cmd.kind == control_pb2.COMMAND_KIND_UNSPECIFIED:
            log.warning("unknown command ignored", extra=kv(command_id=cmd.command_id, kind=cmd.kind))
            self._results.put(
                control_pb2.CommandResult(
                    command_id=cmd.command_id, ok=False, message=f"unknown command kind {cmd.kind}"
                )
            )
            return
        try:
            outcome = self._on_command(cmd)
            ok, message = outcome if outcome is not None else (True, "")
        except Exception as exc:  # a bad command must not kill the stream
            log.exception("command handler failed", extra=kv(command_id=cmd.command_id))
            ok, message = False, f"handler error: {exc}"
        self._results.put(control_pb2.CommandResult(command_id=cmd.command_id, ok=ok, message=message))

    def _requests(self, gen: int) -> Iterator[control_pb2.EdgeMessage]:
        with self._lock:  # a copy: set_robots may change the set while gRPC serializes this one
            self._robots_changed.clear()
            register = control_pb2.RegisterRequest()
            register.CopyFrom(self._register)
        announced = {r.robot_id for r in register.robots}  # what control has been told this stream owns
        yield control_pb2.EdgeMessage(register=register)
        seq = 0
        next_beat = 0.0
        while True:
            if gen != self._stream_gen:
                return
            reg = self._registered
            final = self._final.is_set()
            changed = reg is not None and self._robots_changed.is_set() and not final
            if reg is not None and (final or changed or time.monotonic() >= next_beat):
                interval = reg.heartbeat_interval_s if reg.heartbeat_interval_s > 0 else 1.0
                next_beat = time.monotonic() + interval
                seq += 1
                beat = self._heartbeat(seq, announced)
                if gen != self._stream_gen:  # stream ended while building it: keep the episodes
                    with self._lock:
                        self._requeue_in_flight()
                    return
                self.heartbeats += 1
                HEARTBEATS.inc()
                yield control_pb2.EdgeMessage(heartbeat=beat)
                if final:
                    return  # half-close: control sees the end of our stream and closes its side
                if changed:  # after that heartbeat: the last episodes of a robot leaving the set still count
                    robots = self._robot_set()
                    announced = {r.robot_id for r in robots}
                    yield control_pb2.EdgeMessage(robots=control_pb2.RobotsUpdate(robots=robots))
                continue
            wait = _POLL_S if reg is None else max(0.0, min(_POLL_S, next_beat - time.monotonic()))
            try:
                result = self._results.get(timeout=wait)
            except queue.Empty:
                continue
            yield control_pb2.EdgeMessage(command_result=result)

    def _heartbeat(self, seq: int, announced: set[str]) -> control_pb2.Heartbeat:
        """Statuses with fresh episodes plus any carried over from a broken stream. A robot plugged in since
        control was last told the robot set waits for the next heartbeat (its episodes carried): control drops
        the status of a robot the stream has not registered."""
        statuses = self._status_fn()
        sent: list[control_pb2.RobotStatus] = []
        with self._lock:
            self._in_flight = {}
            coming = {r.robot_id for r in self._register.robots}  # the set the next update announces
            for status in statuses:
                carried = self._carry.pop(status.robot_id, [])
                fresh = list(status.new_episodes)
                if status.robot_id not in announced:
                    if status.robot_id in coming:
                        self._carry[status.robot_id] = [*carried, *fresh]
                    continue
                del status.new_episodes[:]
                status.new_episodes.extend([*carried, *fresh])
                self._in_flight[status.robot_id] = list(status.new_episodes)
                sent.append(status)
        return control_pb2.Heartbeat(seq=seq, sent_at_ns=time.time_ns(), robots=sent)

    def _requeue_in_flight(self) -> None:
        """Caller holds the lock. The last heartbeat may not have arrived: send its episodes again."""
        for robot_id, episodes in self._in_flight.items():
            if episodes:
                self._carry[robot_id] = [*episodes, *self._carry.get(robot_id, [])]
        self._in_flight = {}
