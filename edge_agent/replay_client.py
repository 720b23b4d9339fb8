"""Steps to the Replay service without ever blocking the control loop.

send() only hands the step to the outbox (edge_agent/spool.py: an LMDB spool by default, durable
before anything is sent; or RAM) and returns its seq; a background thread owns the Replay.Insert
stream and reads the outbox in seq order. A step leaves the outbox only when an InsertAck lists its
seq, so after a broken stream, a restart of the edge or a kill -9, every unacked step is re-sent
(replay dedupes by key: each step is stored once).

retarget(addr) moves the stream to another replay shard (control's assignment): the current stream
is half-closed so replay commits and acks what it holds, then the unacked rest goes to the new shard.

A step replay refuses for this agent's identity (PERMISSION_DENIED naming its seq: the token may not
write its robot) would end every stream at the same place. That step, and the kept steps of the same
robot after it, are set aside (Outbox.quarantine: a spool keeps them, and tries them again when next
opened) so the other steps go on. The robot's new steps are set aside unsent for a while (DENIED_RETRY_S,
doubling per refusal up to DENIED_RETRY_MAX_S), then one goes out again: tokens files are re-read, and
control and replay may each see a change at another moment. Once replay takes such a step, what was set
aside is sent again at once.

RESOURCE_EXHAUSTED (replay's disk or map is full) ends a stream after replay acked what did commit: the rest
stays kept, and the next stream waits longer each time (FULL_RETRY_S doubling up to FULL_RETRY_MAX_S) instead
of re-sending the whole backlog every second; the wait starts short again once replay acks the backlog.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import grpc
import prometheus_client

from edge_agent.spool import MemoryOutbox, Outbox
from user.config import AuthConfig
from user.log import kv
from user.rpc import CLIENT_ERRORS, Backoff, make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, step_pb2

log = logging.getLogger(__name__)

STEPS_SENT = prometheus_client.Counter(
    "user_edge_steps_sent_total", "Steps written to the replay stream (re-sends too)"
)
STEPS_ACKED = prometheus_client.Counter("user_edge_steps_acked_total", "Steps acknowledged by replay (committed)")
STEPS_UNACKED = prometheus_client.Gauge("user_edge_steps_unacked", "Steps kept in the outbox until replay acks them")
STEPS_REJECTED = prometheus_client.Counter(
    "user_edge_steps_rejected_total", "Steps replay refused with INVALID_ARGUMENT (dropped, never retried)"
)
STEPS_QUARANTINED = prometheus_client.Counter(
    "user_edge_steps_quarantined_total",
    "Steps replay refused for this agent's identity, set aside so later steps go on (a spool keeps them and "
    "sends them again once replay takes the robot's steps, or when next opened; a RAM outbox drops them)",
    ["robot_id", "reason"],
)
RECONNECTS = prometheus_client.Counter("user_edge_replay_reconnects_total", "Replay Insert streams re-opened")
RETARGETS = prometheus_client.Counter("user_edge_replay_retargets_total", "Moves to another replay shard")
ACK_LATENCY = prometheus_client.Histogram(
    "user_edge_step_ack_seconds",
    "Time from a step entering the outbox to replay acknowledging its commit (steps of this process life)",
    buckets=(0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0, 5.0, 10.0, 60.0),
)
INSERT_METHOD = "/user.v1.Replay/Insert"

_SEQ_IN_MESSAGE = re.compile(r"\bseq\s*[=:]?\s*(\d+)")
_POLL_S = 0.2  # how often an idle request iterator re-checks for shutdown or a stream change
_READ_CHUNK = 64  # steps read from the outbox at a time
_BATCH_BYTES = 4 << 20  # an InsertBatch message stays far below gRPC's message limit (camera steps are big)
_ACK_TIMES_KEPT = 200_000  # put times remembered for the ack-latency histogram (dropped steps never ack)
DENIED_RETRY_S = 1.0  # a refused robot's new steps are set aside unsent this long before one is sent again
DENIED_RETRY_MAX_S = 60.0  # that wait doubles per refusal up to this
FULL_RETRY_S = 1.0  # after replay answers RESOURCE_EXHAUSTED (full), wait about this before the next stream
FULL_RETRY_MAX_S = 30.0  # that wait doubles per full answer up to this


@dataclass
class _Denied:
    """A robot whose steps replay refuses for this identity."""

    until: float  # monotonic: its steps are set aside unsent until then
    refusals: int = 1
    probe: int = 0  # seq of its first step sent after `until` (0: none yet); an ack past it means allowed


class ReplaySender:
    def __init__(
        self,
        addr: str,
        auth: AuthConfig,
        max_unacked: int = 100_000,
        backoff: Backoff | None = None,
        start: bool = True,
        outbox: Outbox | None = None,
        full_backoff: Backoff | None = None,
    ) -> None:
        """`outbox` (owned, closed with the sender) defaults to RAM bounded by max_unacked steps.
        `full_backoff`: the wait before a new stream after replay answered RESOURCE_EXHAUSTED."""
        self.addr = addr
        self.outbox = outbox if outbox is not None else MemoryOutbox(max_unacked)
        self._auth = auth
        self._channel = make_channel(addr, auth)
        self._stub = replay_pb2_grpc.ReplayStub(self._channel)
        self._backoff = backoff or Backoff(initial_s=0.1, max_s=2.0)
        self._full_backoff = full_backoff or Backoff(initial_s=FULL_RETRY_S, max_s=FULL_RETRY_MAX_S)
        # while replay is full: the newest seq kept when the stream began (an ack reaching it: room again); else 0
        self._full_until = 0
        self.full_answers = 0  # streams replay ended with RESOURCE_EXHAUSTED
        self._cond = threading.Condition()
        self._stream_gen = 0  # bumped on every (re)connect; stale request iterators exit
        self._next_addr: str | None = None  # set by retarget(), taken between streams
        self._stopping = threading.Event()
        self._call: grpc.Call | None = None
        self._batched = True  # InsertBatch until a replay answers UNIMPLEMENTED
        # per-instance counters (the Prometheus ones are process-wide)
        self.sent = self.acked = self.rejected = self.reconnects = self.retargets = self.quarantined = 0
        self._denied: dict[str, _Denied] = {}  # robots replay refuses for us; touched by both stream threads
        self._resume_now = False  # the stream ended on a step now set aside, or to send released ones: no backoff
        self._put_at: dict[int, float] = {}  # seq -> monotonic time of send(), until its ack
        self._put_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="replay-sender", daemon=True)
        STEPS_UNACKED.set(self.outbox.count)
        if start:
            self.start()

    # ------------------------------------------------------------------ control-loop side

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def send(self, step: step_pb2.Step, table: str = "") -> int:
        """Keep the step in the outbox (a local commit for a spool) and return its seq; never waits on the network.
        `table`: the replay table of the step's episode ("" = "online")."""
        seq = self.outbox.put(step, table)
        with self._put_lock:  # robot threads send at once
            self._put_at[seq] = time.monotonic()
            if len(self._put_at) > _ACK_TIMES_KEPT:  # steps the outbox dropped never ack: forget the oldest
                self._put_at.pop(next(iter(self._put_at)))
        STEPS_UNACKED.set(self.outbox.count)
        with self._cond:
            self._cond.notify_all()
        return seq

    @property
    def unacked(self) -> int:
        return self.outbox.count

    @property
    def dropped(self) -> int:
        return self.outbox.dropped

    @property
    def accepting(self) -> bool:
        """False while a full spool under the pause policy wants the robots to hold."""
        return self.outbox.accepting

    def retarget(self, addr: str) -> None:
        """Write to another replay shard from now on (before start() too). Unacked steps follow."""
        with self._cond:
            if addr == (self._next_addr or self.addr):
                return
            self._next_addr = addr
            if not self._thread.is_alive():
                self._switch_locked()
                return
            self._stream_gen += 1  # the request iterator half-closes: replay acks what it holds
            self._cond.notify_all()

    def flush(self, timeout: float) -> bool:
        """Wait until every kept step is acknowledged (shutdown); False on timeout."""
        end = time.monotonic() + timeout
        with self._cond:
            while self.outbox.count:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, _POLL_S))
        return True

    def close(self) -> None:
        self._stopping.set()
        with self._cond:
            self._stream_gen += 1
            self._cond.notify_all()
            call = self._call
        if call is not None:
            call.cancel()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._channel.close()
        self.outbox.close()

    # ------------------------------------------------------------------ stream side

    def _switch_locked(self) -> None:
        if self._next_addr is None or self._next_addr == self.addr:
            self._next_addr = None
            return
        old, self.addr, self._next_addr = self.addr, self._next_addr, None
        self._channel.close()
        self._channel = make_channel(self.addr, self._auth)
        self._stub = replay_pb2_grpc.ReplayStub(self._channel)
        self.retargets += 1
        RETARGETS.inc()
        log.info("replay shard changed", extra=kv(old=old, new=self.addr, unacked=self.outbox.count))

    def _run(self) -> None:
        first = True
        while not self._stopping.is_set():
            with self._cond:
                moved = self._next_addr is not None
                self._switch_locked()
            if not first and not moved:
                self.reconnects += 1
                RECONNECTS.inc()
            first = False
            self._resume_now = False
            code = self._stream_once()
            if self._stopping.is_set():
                return
            if (
                self._next_addr is not None
                or self._resume_now
                or code in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.UNIMPLEMENTED)
            ):
                continue  # a new shard, the bad or refused step is gone, or one step a message: resume at once
            if code == grpc.StatusCode.UNAUTHENTICATED:
                log.error("replay rejects our token; retrying", extra=kv(addr=self.addr))
            if code == grpc.StatusCode.RESOURCE_EXHAUSTED:  # re-sending at once would only fill its disk again
                self._full_backoff.sleep(self._stopping)
                continue
            self._backoff.sleep(self._stopping)

    def _stream_once(self) -> grpc.StatusCode | None:
        """One Insert stream: re-send every kept step, then follow send(). Returns the end status."""
        with self._cond:
            self._stream_gen += 1
            gen = self._stream_gen
        if self._full_until:  # (this thread alone reads and writes it)
            self._full_until = max(1, self.outbox.last_seq)
        # InsertBatch: several steps a message, one message's overhead per batch on both ends
        call = self._stub.InsertBatch(self._batches(gen)) if self._batched else self._stub.Insert(self._requests(gen))
        with self._cond:
            self._call = call
        try:
            for ack in call:
                self._on_ack(ack)
            return None
        except grpc.RpcError as err:
            code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
            if not self._stopping.is_set():
                CLIENT_ERRORS.labels(INSERT_METHOD, code.name).inc()
            if code == grpc.StatusCode.UNIMPLEMENTED and self._batched:
                log.warning("replay has no InsertBatch; one step a message", extra=kv(addr=self.addr))
                self._batched = False
            elif code == grpc.StatusCode.INVALID_ARGUMENT:
                self._drop_rejected(err.details() or "")
            elif code == grpc.StatusCode.PERMISSION_DENIED and not self._stopping.is_set():
                self._resume_now = self._quarantine_denied(err.details() or "")
            elif code == grpc.StatusCode.RESOURCE_EXHAUSTED and not self._stopping.is_set():
                self._on_full(err.details() or "")
            elif not self._stopping.is_set():
                log.warning(
                    "replay stream broken; will re-send unacked steps",
                    extra=kv(addr=self.addr, code=code.name, details=err.details(), unacked=self.unacked),
                )
            return code
        finally:
            with self._cond:
                self._call = None
                self._stream_gen += 1  # ends this stream's request iterator
                self._cond.notify_all()

    def _on_full(self, details: str) -> None:
        """Replay is full: warn once per run of full answers (each stream ends alike until it has space)."""
        self.full_answers += 1
        if not self._full_until:
            log.warning(
                "replay is full; keeping unacked steps and re-sending them with a growing wait",
                extra=kv(addr=self.addr, details=details, unacked=self.unacked, max_wait_s=self._full_backoff.max_s),
            )
        self._full_until = max(1, self.outbox.last_seq)

    def _not_full(self, top: int) -> None:
        """An ack reached the steps kept when the first stream after a full answer began: replay has room again."""
        if self._full_until and (top >= self._full_until or not self.outbox.count):
            self._full_until = 0
            self._full_backoff.reset()
            log.info("replay takes steps again", extra=kv(addr=self.addr, unacked=self.unacked))

    def _unsent(self, gen: int) -> Iterator[list[replay_pb2.InsertRequest]]:
        """Kept steps in seq order, as many as are waiting (up to _READ_CHUNK) at a time, until the stream changes."""
        cursor = 0  # the newest seq written on this stream
        while True:
            with self._cond:
                while gen == self._stream_gen and self.outbox.last_seq <= cursor:
                    self._cond.wait(_POLL_S)
                if gen != self._stream_gen:
                    return
                last = self.outbox.last_seq
            batch = self.outbox.read(cursor, _READ_CHUNK)
            if not batch:  # everything up to `last` was acked or dropped meanwhile
                cursor = last
                continue
            if gen != self._stream_gen:
                return
            cursor = batch[-1].seq
            if self._denied:
                batch = self._without_denied(batch)
            if batch:
                yield batch

    def _requests(self, gen: int) -> Iterator[replay_pb2.InsertRequest]:
        for batch in self._unsent(gen):
            for req in batch:
                if gen != self._stream_gen:
                    return
                self._count_sent(1)
                yield req

    def _batches(self, gen: int) -> Iterator[replay_pb2.InsertBatchRequest]:
        for batch in self._unsent(gen):
            part: list[replay_pb2.InsertRequest] = []
            size = 0
            for req in batch:
                nbytes = req.ByteSize()
                if part and size + nbytes > _BATCH_BYTES:
                    yield self._batch_message(part)
                    part, size = [], 0
                part.append(req)
                size += nbytes
            yield self._batch_message(part)

    def _batch_message(self, part: list[replay_pb2.InsertRequest]) -> replay_pb2.InsertBatchRequest:
        self._count_sent(len(part))
        return replay_pb2.InsertBatchRequest(requests=part)

    def _count_sent(self, n: int) -> None:
        self.sent += n
        STEPS_SENT.inc(n)

    def _on_ack(self, ack: replay_pb2.InsertAck) -> None:
        if self._denied and ack.seqs:
            self._check_probes(max(ack.seqs))
        n = self.outbox.ack(ack.seqs)
        if self._full_until and ack.seqs:
            self._not_full(max(ack.seqs))
        now = time.monotonic()
        with self._put_lock:
            put_times = [self._put_at.pop(seq, None) for seq in ack.seqs]
        for put_at in put_times:
            if put_at is not None:
                ACK_LATENCY.observe(now - put_at)
        self.acked += n
        STEPS_ACKED.inc(n)
        STEPS_UNACKED.set(self.outbox.count)
        with self._cond:
            self._cond.notify_all()
        self._backoff.reset()

    def _without_denied(self, batch: list[replay_pb2.InsertRequest]) -> list[replay_pb2.InsertRequest]:
        """The batch less the steps of robots replay refuses us, which are set aside unsent. Once a robot's wait
        is over its steps go out again, the first of them noted as the probe (see _check_probes)."""
        now = time.monotonic()
        waiting = set()
        for robot_id, denied in list(self._denied.items()):
            if denied.until > now:
                waiting.add(robot_id)
            elif not denied.probe:
                denied.probe = next((req.seq for req in batch if req.step.robot_id == robot_id), 0)
        refused = [req for req in batch if req.step.robot_id in waiting]
        for robot_id in {req.step.robot_id for req in refused}:
            self._set_aside([req.seq for req in refused if req.step.robot_id == robot_id], robot_id)
        return [req for req in batch if req.step.robot_id not in waiting] if refused else batch

    def _check_probes(self, top: int) -> None:
        """Replay checks who may write a step before anything else and ends the stream at a refused one, acking
        only the steps before it: an ack reaching a robot's probe means replay lets us write it again. What was
        set aside (any robot's) goes back to the outbox and a new stream sends it; still-refused robots' steps
        are set aside again as they come up."""
        allowed = [robot_id for robot_id, d in list(self._denied.items()) if d.probe and top >= d.probe]
        if not allowed:
            return
        for robot_id in allowed:
            self._denied.pop(robot_id, None)
        released = self.outbox.release_quarantined()
        log.info(
            "replay accepts steps of these robots again; steps set aside are sent now",
            extra=kv(addr=self.addr, robots=allowed, released=released),
        )
        if released:
            STEPS_UNACKED.set(self.outbox.count)
            with self._cond:  # their seqs are behind this stream's cursor: half-close it, a new one sends them
                self._resume_now = True
                self._stream_gen += 1
                self._cond.notify_all()

    def _quarantine_denied(self, details: str) -> bool:
        """PERMISSION_DENIED. Naming a kept step's seq, it refuses that step's robot for this identity: set the
        step aside, and the robot's later ones as they come up (True: resume at once). Otherwise replay refuses
        the identity itself (its role): False, retried with backoff like a bad token."""
        match = _SEQ_IN_MESSAGE.search(details)
        named = int(match.group(1)) if match else 0
        found = self.outbox.read(named - 1, 1) if named else []
        if not found or found[0].seq != named:
            log.error(
                "replay refuses this agent's token; retrying. Give the token a role that may insert steps (edge)",
                extra=kv(addr=self.addr, details=details),
            )
            return False
        robot_id = found[0].step.robot_id
        denied = self._denied.get(robot_id)
        refusals = denied.refusals + 1 if denied is not None else 1
        wait = min(DENIED_RETRY_MAX_S, DENIED_RETRY_S * 2 ** min(refusals - 1, 8))
        self._denied[robot_id] = _Denied(until=time.monotonic() + wait, refusals=refusals)
        self._set_aside([named], robot_id)
        if denied is None:  # once per robot until replay takes its steps again: they come up by the thousand
            fate = (
                "dropped (no spool to keep them)"
                if isinstance(self.outbox, MemoryOutbox)
                else "set aside in the spool (sent once replay takes a new step of it, or at the next start)"
            )
            log.error(
                f"replay refuses steps of robot {robot_id!r} for this agent's token; its steps are {fate} so the "
                f"other steps go on. To store them, add a pattern matching {robot_id!r} to this edge token's "
                "`robots` in auth.tokens_file (servers re-read it)",
                extra=kv(addr=self.addr, robot_id=robot_id, details=details),
            )
        return True

    def _set_aside(self, seqs: list[int], robot_id: str) -> None:
        n = self.outbox.quarantine(seqs)
        with self._put_lock:  # set-aside steps never ack here
            for seq in seqs:
                self._put_at.pop(seq, None)
        self.quarantined += n
        STEPS_QUARANTINED.labels(robot_id, "permission_denied").inc(n)
        STEPS_UNACKED.set(self.outbox.count)
        with self._cond:
            self._cond.notify_all()

    def _drop_rejected(self, details: str) -> None:
        """Replay acks every step before the bad one, so the bad one is named or the oldest kept."""
        match = _SEQ_IN_MESSAGE.search(details)
        named = int(match.group(1)) if match else 0
        found = self.outbox.read(named - 1, 1) if named else []
        bad = found[0] if found and found[0].seq == named else next(iter(self.outbox.read(0, 1)), None)
        if bad is not None and self.outbox.ack([bad.seq]):
            self.rejected += 1
            STEPS_REJECTED.inc()
        STEPS_UNACKED.set(self.outbox.count)
        with self._cond:
            self._cond.notify_all()
        log.error(
            "replay rejected a step; dropped it",
            extra=kv(
                seq=bad.seq if bad else None,
                robot_id=bad.step.robot_id if bad else None,
                episode_id=bad.step.episode_id if bad else None,
                step_index=bad.step.step_index if bad else None,
                details=details,
            ),
        )
