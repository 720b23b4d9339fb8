"""Steps to the Replay service without ever blocking the control loop.

send() only numbers the step and appends it to a bounded in-memory outbox; a background thread owns
the Replay.Insert stream. A step stays in memory until an InsertAck lists its seq, so after a broken
stream every unacked step is re-sent in order (replay dedupes by key, re-sends are harmless).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterator

import grpc
import prometheus_client

from user.config import AuthConfig
from user.log import kv
from user.rpc import Backoff, make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, step_pb2

log = logging.getLogger(__name__)

STEPS_SENT = prometheus_client.Counter(
    "user_edge_steps_sent_total", "Steps written to the replay stream (re-sends too)"
)
STEPS_ACKED = prometheus_client.Counter("user_edge_steps_acked_total", "Steps acknowledged by replay (committed)")
STEPS_UNACKED = prometheus_client.Gauge(
    "user_edge_steps_unacked", "Steps kept in memory until replay acknowledges them"
)
STEPS_DROPPED = prometheus_client.Counter(
    "user_edge_steps_dropped_total", "Oldest unacked steps dropped because max_unacked_steps was exceeded"
)
STEPS_REJECTED = prometheus_client.Counter(
    "user_edge_steps_rejected_total", "Steps replay refused with INVALID_ARGUMENT (dropped, never retried)"
)
RECONNECTS = prometheus_client.Counter("user_edge_replay_reconnects_total", "Replay Insert streams re-opened")

_SEQ_IN_MESSAGE = re.compile(r"\bseq\s*[=:]?\s*(\d+)")
_POLL_S = 0.2  # how often an idle request iterator re-checks for shutdown or a stream change


class ReplaySender:
    def __init__(
        self,
        addr: str,
        auth: AuthConfig,
        max_unacked: int = 100_000,
        backoff: Backoff | None = None,
        start: bool = True,
    ) -> None:
        self.addr = addr
        self.max_unacked = max_unacked
        self._channel = make_channel(addr, auth)
        self._stub = replay_pb2_grpc.ReplayStub(self._channel)
        self._backoff = backoff or Backoff(initial_s=0.1, max_s=2.0)
        self._cond = threading.Condition()
        self._unacked: OrderedDict[int, replay_pb2.InsertRequest] = OrderedDict()
        self._outbox: deque[int] = deque()  # seqs still to write on the current stream
        self._next_seq = 1
        self._stream_gen = 0  # bumped on every (re)connect; stale request iterators exit
        self._stopping = threading.Event()
        self._call: grpc.Call | None = None
        # per-instance counters (the Prometheus ones are process-wide)
        self.sent = self.acked = self.dropped = self.rejected = self.reconnects = 0
        self._thread = threading.Thread(target=self._run, name="replay-sender", daemon=True)
        if start:
            self.start()

    # ------------------------------------------------------------------ control-loop side

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def send(self, step: step_pb2.Step) -> int:
        """Queue a step; returns its seq. O(1), never waits on the network."""
        with self._cond:
            seq = self._next_seq
            self._next_seq += 1
            self._unacked[seq] = replay_pb2.InsertRequest(seq=seq, step=step)
            self._outbox.append(seq)
            while len(self._unacked) > self.max_unacked:
                self._unacked.popitem(last=False)
                self.dropped += 1
                STEPS_DROPPED.inc()
            if len(self._outbox) > 2 * self.max_unacked:  # dropped seqs linger while disconnected
                self._outbox = deque(s for s in self._outbox if s in self._unacked)
            STEPS_UNACKED.set(len(self._unacked))
            self._cond.notify_all()
        return seq

    @property
    def unacked(self) -> int:
        return len(self._unacked)

    def flush(self, timeout: float) -> bool:
        """Wait until every queued step is acknowledged (shutdown); False on timeout."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._unacked:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
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

    # ------------------------------------------------------------------ stream side

    def _run(self) -> None:
        first = True
        while not self._stopping.is_set():
            if not first:
                self.reconnects += 1
                RECONNECTS.inc()
            first = False
            code = self._stream_once()
            if self._stopping.is_set():
                return
            if code == grpc.StatusCode.INVALID_ARGUMENT:
                continue  # the bad step is gone; resume at once with the rest
            if code == grpc.StatusCode.UNAUTHENTICATED:
                log.error("replay rejects our token; retrying", extra=kv(addr=self.addr))
            self._backoff.sleep(self._stopping)

    def _stream_once(self) -> grpc.StatusCode | None:
        """One Insert stream: re-send every unacked step, then follow send(). Returns the end status."""
        with self._cond:
            self._stream_gen += 1
            gen = self._stream_gen
            self._outbox = deque(self._unacked)
        call = self._stub.Insert(self._requests(gen))
        with self._cond:
            self._call = call
        try:
            for ack in call:
                self._on_ack(ack)
            return None
        except grpc.RpcError as err:
            code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
            if code == grpc.StatusCode.INVALID_ARGUMENT:
                self._drop_rejected(err.details() or "")
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

    def _requests(self, gen: int) -> Iterator[replay_pb2.InsertRequest]:
        while True:
            with self._cond:
                while not self._outbox and gen == self._stream_gen:
                    self._cond.wait(_POLL_S)
                if gen != self._stream_gen:
                    return
                req = self._unacked.get(self._outbox.popleft())
            if req is not None:  # None: dropped or acked meanwhile
                self.sent += 1
                STEPS_SENT.inc()
                yield req

    def _on_ack(self, ack: replay_pb2.InsertAck) -> None:
        with self._cond:
            n = sum(self._unacked.pop(seq, None) is not None for seq in ack.seqs)
            self.acked += n
            STEPS_ACKED.inc(n)
            STEPS_UNACKED.set(len(self._unacked))
            self._cond.notify_all()
        self._backoff.reset()

    def _drop_rejected(self, details: str) -> None:
        """Replay acks every step before the bad one, so the bad one is named or the oldest unacked."""
        with self._cond:
            match = _SEQ_IN_MESSAGE.search(details)
            seq = int(match.group(1)) if match and int(match.group(1)) in self._unacked else None
            if seq is None and self._unacked:
                seq = next(iter(self._unacked))
            bad = self._unacked.pop(seq, None) if seq is not None else None
            STEPS_UNACKED.set(len(self._unacked))
            self._cond.notify_all()
        if bad is not None:
            self.rejected += 1
            STEPS_REJECTED.inc()
        log.error(
            "replay rejected a step; dropped it",
            extra=kv(
                seq=seq,
                robot_id=bad.step.robot_id if bad else None,
                episode_id=bad.step.episode_id if bad else None,
                step_index=bad.step.step_index if bad else None,
                details=details,
            ),
        )
