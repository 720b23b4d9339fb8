"""Micro-batching: many robots' single observations in, one policy forward per batch out.

Request handlers `submit()` one observation and wait on the returned future. One worker thread
takes the first waiting request, then collects more until max_batch, or until max_wait_ms after
the first one arrived, or until every robot seen recently has a request in (waiting longer could
only add latency). A robot answered moments ago and not back yet (a robot in a closed loop, on its
round trip) is worth waiting for a little longer: up to RETURN_WAIT_FRACTION of a recent forward,
since sent on without it, it would wait a whole forward for the next batch, and two forwards of
half the robots cost more than one of all (a forward's weight reads are paid once per batch).
Robots that ask at their own rate (answered long ago) are never waited for beyond max_wait.
Requests are grouped by (deterministic, observation shapes), stacked, and the policy runs
once per group; each future gets its own row of the result.

With `workers` > 1 several such threads take batches from the one queue, so a batch can start while
another is still in its forward (on a CPU with one torch thread per forward, a second core serves a
second batch instead of idling); each batch still runs one forward, and a swap of weights reaches
every worker's next batch.

A policy that samples in steps (flow matching, diffusion: `user.policy.SteppedSampler`) can be
batched continuously: the workers then only collect, preprocess and encode (the policy's `begin`),
and a step thread runs the batch one step at a time; groups encoded meanwhile join it at the next
step, and each row is answered when its own steps are done. A request that just missed a batch
waits for its own encode and one step, not a whole forward, and encoding overlaps the steps (a second
core, or the CPU side of a GPU's launches). Rows of different weights never share a step: after a
swap the old weights' rows finish apart, the new ones start anew.

Heavy preprocessing stays off the gRPC threads: a policy that defines
`preprocess(batched observation, instructions)` (resize and normalize images, tokenize
instructions, copy to the device in one go) has it run here, once per group, and its `act` then
receives what preprocess returned. Every answer carries its stage times: queue (submit -> its
group starts), preprocess, forward and postprocess (un-batching).

A policy that raises, or returns a batch or row of the wrong shape, fails only the requests it was
serving (their callers get the exception); it is logged with its traceback once per policy version
and stage (a broken policy fails every request: one traceback each would flood the log) and every
failed request is reported to `on_failure` (the service counts them).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from user.log import kv

if TYPE_CHECKING:
    from user.policy import SteppedRows, SteppedSampler

log = logging.getLogger(__name__)

# Batched observation (values with a leading batch dim) or what preprocess made of it, deterministic
# -> (B, action_dim) or chunks (B, horizon, action_dim).
ActFn = Callable[[Any, bool], np.ndarray]
# (batched observation, one instruction per row, "" = the policy's default) -> the input of ActFn.
PreprocessFn = Callable[[Mapping[str, np.ndarray], Sequence[str]], Any]
# Called once per policy forward: (batch size, compute seconds).
BatchObserver = Callable[[int, float], None]
# Called whenever requests fail in the policy: (stage "forward" | "begin" | "step", requests failed).
FailureObserver = Callable[[str, int], None]
ACTIVE_WINDOW_S = 1.0  # a robot counts as active this long after its last request or answer
RETURN_WAIT_FRACTION = 0.25  # longest wait for returning robots, as a share of a recent forward
FORWARD_EWMA = 0.3  # weight of the newest batch in the recent-forward estimate


class NoPolicyError(RuntimeError):
    """No policy has been loaded yet."""


class BatcherStopped(RuntimeError):
    """The batcher stopped (the service is stopping, or its experiment was removed)."""


@dataclass
class ActResult:
    action: np.ndarray  # this request's row: (action_dim,) or (horizon, action_dim)
    version: int
    queue_us: int  # submit -> start of the forward that served it
    compute_us: int  # the whole forward of its group
    batch_size: int  # requests in that forward
    preprocess_us: int = 0  # batched preprocessing of its group
    postprocess_us: int = 0  # splitting the batch result into rows


@dataclass
class _Request:
    observation: dict[str, np.ndarray]
    deterministic: bool
    key: str
    future: Future
    instruction: str = ""
    submitted: float = field(default_factory=time.perf_counter)

    def group(self) -> tuple:
        shapes = tuple(sorted((k, v.shape, v.dtype.str) for k, v in self.observation.items()))
        return (self.deterministic, shapes)


@dataclass(frozen=True)
class _Served:
    act: ActFn
    version: int
    preprocess: PreprocessFn | None = None
    stepped: SteppedSampler | None = None  # batch continuously: the policy's forward in steps
    row_shapes: frozenset[tuple[int, ...]] = frozenset()  # what one row of its result may be (empty: unchecked)

    def check_rows(self, actions: np.ndarray, rows: int, what: str) -> None:
        """ValueError unless `actions` has one row per request, each of a shape the policy declares."""
        if actions.shape[:1] != (rows,):
            raise ValueError(f"policy {what} shape {actions.shape} for a batch of {rows}")
        if self.row_shapes and tuple(actions.shape[1:]) not in self.row_shapes:
            declared = sorted(list(shape) for shape in self.row_shapes)
            raise ValueError(f"policy {what} rows of shape {list(actions.shape[1:])}; it declares {declared}")


@dataclass
class _Member:
    """One request in a continuous batch."""

    req: _Request
    admitted: float  # when its group left the queue (perf_counter)
    began: float  # when its group's steps could begin (after preprocess and encode)
    preprocess_us: int
    joined_at: tuple[int, int] = (0, 0)  # the batch's (rows stepped, steps) when it joined


@dataclass
class _Rolling:
    """Continuous batching: one policy's rows in their steps, with the request each row answers."""

    served: _Served
    rows: SteppedRows
    members: list[_Member]
    rows_stepped: int = 0  # rows summed over the steps taken: with `steps`, the batch a member shared
    steps: int = 0

    def join(self, other: _Rolling) -> None:
        self.rows = self.rows.merged(other.rows)
        for m in other.members:
            m.joined_at = (self.rows_stepped, self.steps)
        self.members += other.members

    def leave(self, mask: np.ndarray) -> tuple[SteppedRows, list[_Member]]:
        """The rows where mask leave this batch: (their rows, their members)."""
        out_rows, self.rows = self.rows.split(mask)
        out = [m for m, done in zip(self.members, mask, strict=True) if done]
        self.members = [m for m, done in zip(self.members, mask, strict=True) if not done]
        return out_rows, out

    def requests(self) -> list[_Request]:
        return [m.req for m in self.members]

    def shared(self, member: _Member) -> float:
        """The mean batch this member's steps ran in."""
        rows, steps = self.rows_stepped - member.joined_at[0], self.steps - member.joined_at[1]
        return rows / steps if steps else 1.0


class MicroBatcher:
    """Thread-safe; start() the workers, set_policy() whenever new weights arrive, stop() at shutdown."""

    def __init__(
        self,
        max_batch: int,
        max_wait_ms: float,
        on_batch: BatchObserver | None = None,
        name: str = "batcher",
        workers: int = 1,
        on_join: Callable[[int], None] | None = None,
        on_failure: FailureObserver | None = None,
    ) -> None:
        if max_batch < 1:
            raise ValueError("max_batch must be >= 1")
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.workers = workers
        self.max_batch = max_batch
        self.max_wait_s = max(0.0, max_wait_ms) / 1000.0
        self.on_batch = on_batch
        self.on_join = on_join  # called with the size of each group that joins a running continuous batch
        self.on_failure = on_failure
        self._failure_logged: dict[str, int] = {}  # stage -> the policy version whose failure was logged
        self.name = name
        self._queue: queue.Queue[_Request] = queue.Queue()
        self._policy: _Served | None = None
        self._lock = threading.Lock()
        self._active: dict[str, float] = {}  # robot key -> last submit (perf_counter)
        self._answered: dict[str, float] = {}  # robot key -> when its last answer was set
        self._forward_s = 0.0  # recent preprocess + forward seconds per batch (EWMA)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._ready: queue.Queue[_Rolling] = queue.Queue()  # encoded groups, for the step thread
        self.requests = 0  # requests answered by a forward
        # Forwards run; a continuous batch's row adds 1 / the rows it shared its steps with, so that
        # requests / batches stays the mean batch a request rode in.
        self.batches = 0.0
        self.joined = 0  # requests that joined a running continuous batch (at a step boundary)

    # ----------------------------------------------------------------------- public

    def start(self) -> MicroBatcher:
        if not self._threads:
            names = [self.name] if self.workers == 1 else [f"{self.name}-{i}" for i in range(self.workers)]
            self._threads = [threading.Thread(target=self._run, name=n, daemon=True) for n in names]
            self._threads.append(threading.Thread(target=self._run_steps, name=f"{self.name}-steps", daemon=True))
            for thread in self._threads:
                thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout)
        self._threads = []
        self._fail_pending(BatcherStopped("batcher stopped"))
        while True:  # groups encoded after the step thread left
            try:
                self._fail(self._ready.get_nowait().requests(), BatcherStopped("batcher stopped"))
            except queue.Empty:
                break

    def set_policy(
        self,
        act: ActFn,
        version: int,
        preprocess: PreprocessFn | None = None,
        stepped: SteppedSampler | None = None,
        row_shapes: Collection[tuple[int, ...]] = (),
    ) -> None:
        """Swap the policy; a batch in progress finishes with the one it started with (no request fails).

        With `stepped` (the policy's forward in parts) the batch is continuous: requests that arrive
        while it runs join it at its next step, and each leaves when its own steps are done. `row_shapes`:
        the shapes one row of its result may have (an action, or a chunk); a result row of another fails."""
        shapes = frozenset(tuple(int(d) for d in shape) for shape in row_shapes)
        with self._lock:
            self._policy = _Served(act, int(version), preprocess, stepped, shapes)

    @property
    def version(self) -> int | None:
        with self._lock:
            return self._policy.version if self._policy else None

    @property
    def mean_batch_size(self) -> float:
        with self._lock:
            return self.requests / self.batches if self.batches else 0.0

    def submit(
        self, observation: Mapping[str, np.ndarray], deterministic: bool = False, key: str = "", instruction: str = ""
    ) -> Future:
        """Queue one observation (no batch dim); the future resolves to an ActResult.

        `key` names the caller (e.g. robot_id): the batcher closes a batch early once every
        recently active key is in it. `instruction` reaches the policy's preprocess.
        """
        if self._stop.is_set():
            raise BatcherStopped("batcher stopped")
        if self.version is None:
            raise NoPolicyError("no policy yet")
        arrays = {k: np.asarray(v) for k, v in observation.items()}
        req = _Request(arrays, bool(deterministic), key, Future(), instruction)
        if key:
            with self._lock:
                self._active[key] = req.submitted
        self._queue.put(req)
        return req.future

    # ----------------------------------------------------------------------- worker

    def _run(self) -> None:
        """A worker: collects batches; runs a whole forward, or (continuous) preprocesses and encodes a
        group and hands it to the step thread, then collects the next while those rows take their steps."""
        while not self._stop.is_set():
            try:
                first = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            batch = self._collect(first)
            try:
                self._serve(batch)
            except Exception as exc:  # never let one bad batch kill the worker
                log.exception("batch failed", extra=kv(size=len(batch)))
                self._fail(batch, exc)

    def _run_steps(self) -> None:
        """The step thread of continuous batching: encoded groups join the running batch of their
        weights at a step boundary (up to max_batch rows), then every running batch takes one step."""
        rolling: list[_Rolling] = []  # running batches, one per weights
        pending: list[_Rolling] = []  # encoded groups waiting for room
        try:
            while not self._stop.is_set():
                pending += self._ready_groups(wait=not rolling and not pending)
                self._admit(pending, rolling)
                self._step(rolling)
        finally:
            for batch in rolling + pending + self._ready_groups(wait=False):
                self._fail(batch.requests(), BatcherStopped("batcher stopped"))

    def _ready_groups(self, wait: bool) -> list[_Rolling]:
        groups: list[_Rolling] = []
        if not wait and self._ready.empty():  # the common case between two steps: no exception raised
            return groups
        if wait:
            try:
                groups.append(self._ready.get(timeout=0.1))
            except queue.Empty:
                return groups
        while True:
            try:
                groups.append(self._ready.get_nowait())
            except queue.Empty:
                return groups

    def _admit(self, pending: list[_Rolling], rolling: list[_Rolling]) -> None:
        rows = sum(len(r.members) for r in rolling)
        while pending and (rows == 0 or rows + len(pending[0].members) <= self.max_batch):
            group = pending.pop(0)
            rows += len(group.members)
            same = next((r for r in rolling if r.served is group.served), None)  # a swap keeps weights apart
            if same is None:
                rolling.append(group)
                continue
            try:
                same.join(group)
                self.joined += len(group.members)
                if self.on_join is not None:
                    self.on_join(len(group.members))
            except Exception as exc:
                log.exception("joining a running batch failed", extra=kv(size=len(group.members)))
                self._fail(group.requests(), exc)

    @staticmethod
    def _fail(reqs: list[_Request], exc: BaseException) -> None:
        for req in reqs:
            if not req.future.done():
                req.future.set_exception(exc)

    def _expected(self, now: float) -> int:
        """How many distinct callers asked or were answered within the window (at least 1): a robot
        waiting on a forward longer than the window still counts."""
        with self._lock:
            for seen in (self._active, self._answered):
                for k in [k for k, t in seen.items() if now - t > ACTIVE_WINDOW_S]:
                    del seen[k]
            return max(1, len(self._active.keys() | self._answered.keys()))

    def _returning(self, keys: set[str], now: float, patience_s: float) -> bool:
        """Is a robot missing from `keys` that was answered within patience_s and has not asked since?"""
        with self._lock:
            return any(
                now - t <= patience_s and t > self._active.get(k, 0.0)
                for k, t in self._answered.items()
                if k not in keys
            )

    def _collect(self, first: _Request) -> list[_Request]:
        batch = [first]
        keys = {first.key}
        picked = time.perf_counter()
        deadline = first.submitted + self.max_wait_s
        # Returning robots are waited for from when the worker got free, not from when `first` came:
        # `first` may have queued behind the last forward, and the robots that forward answered are
        # the ones about to ask again.
        # With a fast forward (a small MLP) this is a fraction of a millisecond: max_wait alone decides.
        patience = RETURN_WAIT_FRACTION * self._forward_s if self.max_wait_s > 0 else 0.0
        patient_deadline = max(deadline, picked + patience)
        # Anonymous callers give no hint how many are coming: they wait the full max_wait.
        expected = self._expected(picked) if first.key else self.max_batch + 1
        while len(batch) < self.max_batch and len(keys) < expected:
            now = time.perf_counter()
            end = patient_deadline if first.key and self._returning(keys, now, patience) else deadline
            remaining = end - now
            try:
                req = self._queue.get(timeout=remaining) if remaining > 0 else self._queue.get_nowait()
            except queue.Empty:  # (one answered by another worker meanwhile is not waited for: a rare miss)
                break
            batch.append(req)
            if req.key:
                keys.add(req.key)
        # Whatever is already waiting rides along (up to max_batch): it costs no extra latency.
        while len(batch) < self.max_batch:
            try:
                batch.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return batch

    def _serve(self, batch: list[_Request]) -> None:
        live = [r for r in batch if r.future.set_running_or_notify_cancel()]  # drop callers that gave up
        with self._lock:
            policy = self._policy
        if policy is None:
            for req in live:
                req.future.set_exception(NoPolicyError("no policy yet"))
            return
        groups: dict[tuple, list[_Request]] = {}
        for req in live:
            groups.setdefault(req.group(), []).append(req)
        for reqs in groups.values():
            if policy.stepped is None:
                self._forward(policy, reqs)
            else:
                self._begin(policy, reqs)

    def _prepare(self, policy: _Served, reqs: list[_Request]) -> Any:
        stacked = {k: np.stack([r.observation[k] for r in reqs]) for k in reqs[0].observation}
        if policy.preprocess is not None:
            return policy.preprocess(stacked, [r.instruction for r in reqs])
        return stacked

    def _begin(self, policy: _Served, reqs: list[_Request]) -> None:
        """Preprocess and encode a group, for the step thread."""
        assert policy.stepped is not None
        start = time.perf_counter()
        try:
            prepared = self._prepare(policy, reqs)
            encode_start = time.perf_counter()
            rows = policy.stepped.begin(prepared, reqs[0].deterministic)
            if len(rows) != len(reqs):
                raise ValueError(f"policy began {len(rows)} rows for a batch of {len(reqs)}")
            preprocess_us = int((encode_start - start) * 1e6)
            members = [_Member(r, start, encode_start, preprocess_us) for r in reqs]
            self._ready.put(_Rolling(policy, rows, members))
        except Exception as exc:
            self._log_failure("begin", policy.version, len(reqs))
            if len(reqs) > 1:  # as in _forward: each row alone, so one robot's input fails only that robot
                for req in reqs:
                    self._begin(policy, [req])
                return
            self._policy_failed("begin", reqs, exc)

    def _step(self, rolling: list[_Rolling]) -> None:
        """One step for each rolling batch; rows whose steps are done are answered and leave."""
        for batch in list(rolling):
            stepped = batch.served.stepped
            assert stepped is not None
            finished: list[_Member] = []
            try:
                n = len(batch.members)
                batch.rows = stepped.advance(batch.rows)
                batch.rows_stepped += n
                batch.steps += 1
                done = batch.rows.done()
                if done.shape != (n,):
                    raise ValueError(f"policy reported {done.shape} done flags for {n} rows")
                if not done.any():
                    continue
                finish_start = time.perf_counter()
                shared = [batch.shared(m) for m, d in zip(batch.members, done, strict=True) if d]
                finished_rows, finished = batch.leave(done)
                actions = np.asarray(stepped.finish(finished_rows))
                batch.served.check_rows(actions, len(finished), "finished")
            except Exception as exc:
                self._log_failure("step", batch.served.version, len(batch.members) + len(finished))
                self._policy_failed("step", batch.requests() + [m.req for m in finished], exc)
                rolling.remove(batch)
                continue
            if not batch.members:
                rolling.remove(batch)
            self._answer_stepped(batch.served, finished, shared, actions, finish_start)

    def _answer_stepped(
        self, served: _Served, finished: list[_Member], shared: list[float], actions: np.ndarray, finish_start: float
    ) -> None:
        end = time.perf_counter()
        with self._lock:
            self.requests += len(finished)
            self.batches += sum(1.0 / max(s, 1.0) for s in shared)
            spent = finish_start - min(m.admitted for m in finished)
            self._forward_s += FORWARD_EWMA * (spent - self._forward_s) if self._forward_s else spent
            self._answered.update((m.req.key, end) for m in finished if m.req.key)
        if self.on_batch is not None:
            self.on_batch(round(sum(shared) / len(shared)), finish_start - min(m.began for m in finished))
        postprocess_us = int((end - finish_start) * 1e6)
        for m, row, batch in zip(finished, actions, shared, strict=True):
            m.req.future.set_result(
                ActResult(
                    np.array(row, dtype=np.float32),
                    served.version,
                    int((m.admitted - m.req.submitted) * 1e6),
                    int((finish_start - m.began) * 1e6),
                    max(1, round(batch)),
                    m.preprocess_us,
                    postprocess_us,
                )
            )

    def _forward(self, policy: _Served, reqs: list[_Request]) -> None:
        start = time.perf_counter()
        try:
            stacked = self._prepare(policy, reqs)
            forward_start = time.perf_counter()
            actions = np.asarray(policy.act(stacked, reqs[0].deterministic))
            forward_end = time.perf_counter()
            policy.check_rows(actions, len(reqs), "returned")
            rows = [np.array(actions[i], dtype=np.float32) for i in range(len(reqs))]
        except Exception as exc:
            self._log_failure("forward", policy.version, len(reqs))
            if len(reqs) > 1:  # one robot's input may be what failed: each alone, so the others still get answers
                for req in reqs:
                    self._forward(policy, [req])
                return
            self._policy_failed("forward", reqs, exc)
            return
        end = time.perf_counter()
        compute_s = forward_end - forward_start
        with self._lock:
            self.requests += len(reqs)
            self.batches += 1.0
            spent = forward_end - start
            self._forward_s += FORWARD_EWMA * (spent - self._forward_s) if self._forward_s else spent
        if self.on_batch is not None:
            self.on_batch(len(reqs), compute_s)
        preprocess_us, compute_us = int((forward_start - start) * 1e6), int(compute_s * 1e6)
        postprocess_us = int((end - forward_end) * 1e6)
        answered = time.perf_counter()  # before any caller has its answer, so before it can ask again
        with self._lock:
            self._answered.update((r.key, answered) for r in reqs if r.key)
        for req, row in zip(reqs, rows, strict=True):
            queue_us = int((start - req.submitted) * 1e6)
            req.future.set_result(
                ActResult(row, policy.version, queue_us, compute_us, len(reqs), preprocess_us, postprocess_us)
            )

    def _log_failure(self, stage: str, version: int, size: int) -> None:
        """The policy failed at `stage`: its traceback once per version (call it inside the except block)."""
        with self._lock:
            first = self._failure_logged.get(stage) != version
            self._failure_logged[stage] = version
        if first:
            log.exception(
                f"policy {stage} failed; its requests get the error and their robots hold (logged once a version)",
                extra=kv(size=size, version=version),
            )
        else:
            log.debug(f"policy {stage} failed again", extra=kv(size=size, version=version))

    def _policy_failed(self, stage: str, reqs: list[_Request], exc: BaseException) -> None:
        """Answer `reqs` with the policy's error and count them."""
        self._fail(reqs, exc)
        if self.on_failure is not None and reqs:
            self.on_failure(stage, len(reqs))

    def _fail_pending(self, exc: Exception) -> None:
        while True:
            try:
                req = self._queue.get_nowait()
            except queue.Empty:
                return
            if req.future.set_running_or_notify_cancel():
                req.future.set_exception(exc)
