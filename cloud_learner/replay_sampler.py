"""Sampling from several replay shards as if they were one buffer.

Each site writes to its own replay process (control assigns the shard, see ControlConfig.replay_shards);
the learner asks `ShardedSampler.Sample` for a batch like it asks one replay's stub. A batch of n is
split across the live shards by a multinomial draw with probabilities proportional to their sampleable
transitions (so every stored transition is equally likely, whichever shard holds it), the shards are
asked in parallel and their Batch protos concatenated. A shard that fails is marked down and skipped,
re-probed with Stats after a growing backoff, and sampled again as soon as it answers (its data is on
its disk: it is back with it). The part of a batch a shard failed to deliver is re-asked of the others.

A request with table ratios (RLPD's {"online": 1, "demos": 1}) keeps replay's exact rows per table (largest
remainder) and splits each table's rows across the shards that hold that table, in proportion to that table's
transitions there (for the robots asked for that table: table_robot_ids, else robot_ids), so every transition of a
table is equally likely whichever shard holds it. A shard is asked only for the tables it holds (their rows as
ratios); one without a table is not a failed shard, and one holding only another table (imported demos) is asked
for that one. Per-table counts come from each shard's Stats (counts_only), refreshed in the background every
`stats_every_s`, and at once when a shard answers FAILED_PRECONDITION for its tables (stale counts): the batch is
then asked again by the fresh counts, and the shard keeps its other tables.

Errors look like the stub's (grpc.RpcError with code()): FAILED_PRECONDITION when every live shard is
empty, UNAVAILABLE when none is live.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass

import grpc
import numpy as np
import prometheus_client

from cloud_learner.replay_shm import SharedMemoryReplay
from user import rpc, wire
from user.config import AuthConfig, LearnerConfig
from user.log import kv
from user.v1 import replay_pb2, replay_pb2_grpc, robot_pb2, tensor_pb2

log = logging.getLogger(__name__)

SHARD_UP = prometheus_client.Gauge("user_learner_replay_shard_up", "1 while a replay shard answers", ["addr"])
SHARD_TRANSITIONS = prometheus_client.Gauge(
    "user_learner_replay_shard_transitions", "Sampleable transitions last reported by a replay shard", ["addr"]
)
SHARD_SAMPLED = prometheus_client.Counter(
    "user_learner_replay_shard_sampled_total", "Transitions sampled from a replay shard", ["addr"]
)


class SamplerError(grpc.RpcError):
    """What Sample raises, shaped like a stub's error so callers handle both alike."""

    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(details)
        self._code, self._details = code, details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


@dataclass
class Shard:
    addr: str
    channel: grpc.Channel
    stub: replay_pb2_grpc.ReplayStub
    transitions: int = 0
    up: bool = False
    known: bool = False  # answered at least once since it was last down
    retry_at: float = 0.0  # down, or empty: next Stats probe at this time
    probing: bool = False  # a Stats probe is in flight
    backoff_s: float = 0.0
    # table -> robot -> transitions, from the last Stats
    tables: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    tables_at: float = float("-inf")  # when `tables` was last read

    def table_count(self, table: str, robot_ids: Sequence[str]) -> int:
        """Transitions of `table` here for these robots (all when empty), as of the last Stats."""
        robots = self.tables.get(table, {})
        if not robot_ids:
            return sum(robots.values())
        return sum(robots.get(r, 0) for r in robot_ids)


class ShardedSampler:
    """`Sample(request, timeout)` over `addrs`, like ReplayStub.Sample over one replay."""

    def __init__(
        self,
        addrs: list[str],
        auth: AuthConfig,
        timeout_s: float = 10.0,
        seed: int | None = None,
        min_backoff_s: float = 0.2,
        max_backoff_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        stats_every_s: float = 10.0,
    ) -> None:
        if not addrs or len(set(addrs)) != len(addrs):
            raise ValueError(f"need distinct replay addresses, got {addrs}")
        self.timeout_s = timeout_s
        self.min_backoff_s, self.max_backoff_s = min_backoff_s, max_backoff_s
        self.stats_every_s = stats_every_s  # per-table counts of a live shard are this old at most (plus a Stats)
        self._clock = clock
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()  # one Sample at a time: shard state and rng are not shared
        self.shards = []
        for addr in addrs:
            channel = rpc.make_channel(addr, auth)
            self.shards.append(Shard(addr, channel, replay_pb2_grpc.ReplayStub(channel)))
        # A probe of a silent shard may hold a worker for `timeout` while the others are sampled.
        self._pool = ThreadPoolExecutor(max_workers=2 * len(addrs), thread_name_prefix="replay-shard")

    # ------------------------------------------------------------------ the stub's call

    def Sample(self, request: replay_pb2.SampleRequest, timeout: float | None = None) -> replay_pb2.SampleResponse:
        timeout = timeout or self.timeout_s
        with self._lock:
            self._probe(timeout)
            if request.tables:
                return self._sample_tables(request, timeout)
            batches: list[replay_pb2.Batch] = []
            missing, failed = int(request.batch_size), set()
            for _ in range(len(self.shards)):  # a round per shard at most: each failure removes one
                ready = [s for s in self.shards if s.up and s.transitions > 0 and s.addr not in failed]
                if missing <= 0 or not ready:
                    break
                sizes = np.array([s.transitions for s in ready], dtype=float)
                counts = self._rng.multinomial(missing, sizes / sizes.sum())
                asked = [(s, int(c)) for s, c in zip(ready, counts, strict=True) if c > 0]
                futures = [self._pool.submit(self._sample_one, s, request, c, timeout) for s, c in asked]
                for (shard, _), future in zip(asked, futures, strict=True):
                    resp = future.result()
                    if resp is None:
                        failed.add(shard.addr)  # its share goes to the others next round
                    else:
                        batches.append(resp.batch)
                        missing -= _batch_len(resp.batch)
            if not batches:
                raise self._nothing_error()
            return replay_pb2.SampleResponse(
                batch=merge_batches(batches), transitions=sum(s.transitions for s in self.shards if s.up)
            )

    def _sample_tables(self, request: replay_pb2.SampleRequest, timeout: float) -> replay_pb2.SampleResponse:
        """A batch with exact rows per table, each table's rows split over the shards that hold it (caller holds
        the lock). A table no live shard holds: FAILED_PRECONDITION, as one replay answers for an empty table."""
        self._refresh_tables(self.stats_every_s)
        robot_ids = {t: table_robots(request, t) for t in request.tables}  # each table's own robots (table_robot_ids)
        missing = wire.split_rows(int(request.batch_size), dict(request.tables))
        batches: list[replay_pb2.Batch] = []
        counts: dict[str, dict[str, int]] = {}  # addr -> table -> transitions (the shard's answer, else Stats)
        answered: dict[str, int] = {}  # addr -> its SampleResponse.transitions
        failed: set[str] = set()
        refreshed: set[str] = set()  # shards whose per-table counts proved stale this batch (read again)
        for _ in range(2 * len(self.shards)):  # a round per shard at most failing, and per shard found stale
            if not any(missing.values()):
                break
            # which shards hold a table is their per-table counts' business (_plan), not their total: a shard of
            # imported demos alone holds none of the experiment's own robots' transitions
            ready = [s for s in self.shards if s.up and s.addr not in failed]
            asked = self._plan(ready, missing, robot_ids)
            futures = [self._pool.submit(self._sample_one, s, request, rows, timeout) for s, rows in asked]
            for (shard, rows), future in zip(asked, futures, strict=True):
                resp = future.result()
                if resp is None and shard.up and shard.addr not in refreshed:
                    refreshed.add(shard.addr)  # stale counts, read again: asked again by them (its other tables too)
                    continue
                if resp is None:
                    failed.add(shard.addr)  # its rows go to the other holders of their tables next round
                    continue
                batches.append(resp.batch)
                counts[shard.addr] = dict(resp.table_transitions)
                answered[shard.addr] = int(resp.transitions)  # the request's robots' transitions there
                for table, n in rows.items():
                    missing[table] -= n
        short = [t for t, n in missing.items() if n > 0]
        if short:  # every holder of a table failed this time
            raise self._no_table_error(short[0], robot_ids[short[0]])
        return replay_pb2.SampleResponse(
            batch=merge_batches(batches),
            transitions=sum(answered.get(s.addr, s.transitions) for s in self.shards if s.up),
            table_transitions=self._table_totals(request, robot_ids, counts),
        )

    def _plan(
        self, ready: list[Shard], missing: dict[str, int], robot_ids: dict[str, list[str]]
    ) -> list[tuple[Shard, dict[str, int]]]:
        """Rows per shard and table: each table's missing rows drawn over its holders in proportion to their
        transitions of it (a multinomial: every transition of the table equally likely)."""
        plan: dict[str, dict[str, int]] = {}  # addr -> table -> rows
        for table, n in missing.items():
            if n <= 0:
                continue
            holders = [(s, s.table_count(table, robot_ids[table])) for s in ready]
            holders = [(s, c) for s, c in holders if c > 0]
            if not holders:
                raise self._no_table_error(table, robot_ids[table])
            sizes = np.array([c for _, c in holders], dtype=float)
            for (shard, _), k in zip(holders, self._rng.multinomial(n, sizes / sizes.sum()), strict=True):
                if k > 0:
                    plan.setdefault(shard.addr, {})[table] = int(k)
        return [(s, plan[s.addr]) for s in ready if s.addr in plan]

    def _table_totals(
        self, request: replay_pb2.SampleRequest, robot_ids: dict[str, list[str]], answered: dict[str, dict[str, int]]
    ) -> dict[str, int]:
        """Per table asked: its transitions over the live shards (a shard's own answer where it gave one)."""
        out = {}
        for table in request.tables:
            out[table] = sum(
                answered[s.addr][table] if table in answered.get(s.addr, {}) else s.table_count(table, robot_ids[table])
                for s in self.shards
                if s.up
            )
        return out

    def _no_table_error(self, table: str, robot_ids: list[str]) -> SamplerError:
        self._refresh_tables(self.min_backoff_s)  # it may have arrived since the last Stats: look soon
        if not any(s.up for s in self.shards):
            return self._nothing_error()
        robots = f" for robots {sorted(robot_ids)[:8]}" if robot_ids else ""
        return SamplerError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"no sampleable transitions in table {table!r}{robots} on any live replay shard yet",
        )

    def Stats(self, request: replay_pb2.StatsRequest, timeout: float | None = None) -> replay_pb2.StatsResponse:
        """Counts summed over the shards that answer (steps, transitions, episodes, steps per robot: sync mode's
        env-step count; transitions per table and robot), and the specs of StatsRequest.spec_tables' robots (one per
        robot, by id; specs_left_out summed). UNAVAILABLE when none answers."""
        specs: dict[str, robot_pb2.RobotSpec] = {}
        timeout = timeout or self.timeout_s
        futures = [self._pool.submit(s.stub.Stats, request, timeout=timeout) for s in self.shards]
        out, answered = replay_pb2.StatsResponse(), 0
        for future in futures:
            try:
                part = future.result()
            except grpc.RpcError:
                continue
            answered += 1
            out.steps += part.steps
            out.transitions += part.transitions
            out.episodes += part.episodes
            for robot_id, n in part.steps_per_robot.items():
                out.steps_per_robot[robot_id] += n
            for name, table in part.tables.items():  # which robots hold a table's transitions (the learner's demos)
                out.tables[name].transitions += table.transitions
                for robot_id, r in table.robots.items():
                    out.tables[name].robots[robot_id].transitions += r.transitions
            for spec in part.specs:
                specs.setdefault(spec.robot_id, spec)
            out.specs_left_out += part.specs_left_out
        if not answered:
            raise self._nothing_error()
        out.specs.extend(specs[r] for r in sorted(specs))
        return out

    def close(self) -> None:
        self._pool.shutdown(wait=False)
        for shard in self.shards:
            shard.channel.close()

    # ------------------------------------------------------------------ shard health

    def _probe(self, timeout: float) -> None:
        """Stats of every shard not known up with data whose retry time has come. The first probe of a shard
        is waited for (the first batches must see every shard); a re-probe only while no shard can be
        sampled: a shard gone silent (a black-holed link) must not stall the others."""
        now = self._clock()
        due = [s for s in self.shards if not (s.up and s.transitions > 0) and now >= s.retry_at and not s.probing]
        first = [s for s in due if not s.known]
        for shard in due:
            shard.probing = True
        futures = {self._pool.submit(self._stats, s, timeout): s for s in due}
        wait([f for f, s in futures.items() if s in first], timeout=timeout)
        pending = {f for f in futures if not f.done()}
        end = self._clock() + timeout
        while pending and not any(s.up and s.transitions > 0 for s in self.shards) and self._clock() < end:
            _, pending = wait(pending, timeout=max(0.0, end - self._clock()), return_when=FIRST_COMPLETED)

    def _refresh_tables(self, max_age_s: float) -> None:
        """Stats of each live shard whose per-table counts are older than max_age_s, in the background: a
        table that arrives on a shard is sampled there from the next batch on that finds it."""
        now = self._clock()
        for shard in self.shards:
            if shard.up and not shard.probing and now - shard.tables_at >= max_age_s:
                shard.probing = True
                self._pool.submit(self._stats, shard, self.timeout_s)

    def _stats(self, shard: Shard, timeout: float) -> None:
        try:
            # counts_only: per-table robots' transitions from replay's index, not a walk of its every episode
            stats = shard.stub.Stats(replay_pb2.StatsRequest(counts_only=True), timeout=timeout)
        except grpc.RpcError as err:
            self._mark_down(shard, err)
            return
        finally:
            shard.probing = False
        shard.tables = {
            name: {robot: int(r.transitions) for robot, r in t.robots.items()} for name, t in stats.tables.items()
        }
        shard.tables_at = self._clock()
        self._mark_up(shard, int(stats.transitions))
        if not shard.transitions:  # empty: look again later, without hammering it
            shard.retry_at = self._clock() + self.min_backoff_s

    def _sample_one(
        self, shard: Shard, request: replay_pb2.SampleRequest, n: int | dict[str, int], timeout: float
    ) -> replay_pb2.SampleResponse | None:
        """n rows, or rows per table (the tables this shard is asked for, their rows as ratios)."""
        req = replay_pb2.SampleRequest()
        req.CopyFrom(request)  # the same sampler, n-step, frame stack, action horizon and human tables
        tables = isinstance(n, dict)
        if isinstance(n, dict):
            req.ClearField("tables")
            req.tables.update(n)
            for table in [t for t in req.table_robot_ids if t not in n]:  # replay refuses robots of a table not asked
                del req.table_robot_ids[table]
            n = sum(n.values())
        req.batch_size = n
        try:
            resp = shard.stub.Sample(req, timeout=timeout)
        except grpc.RpcError as err:
            if err.code() != grpc.StatusCode.FAILED_PRECONDITION:
                self._mark_down(shard, err)
            elif tables:  # its per-table counts were stale: read again now (its other tables are still there)
                self._stats(shard, timeout)
            else:  # nothing sampleable there (for these robots)
                self._mark_up(shard, 0)
                shard.retry_at = self._clock() + self.min_backoff_s
            return None
        # A table answer's transitions are those of the request's robot_ids only, not the tables' robots (imported
        # demos): the shard keeps the total its Stats gave, or it looked empty and was left out of the next batch.
        self._mark_up(shard, shard.transitions if tables else int(resp.transitions))
        SHARD_SAMPLED.labels(shard.addr).inc(n)
        return resp

    def _mark_up(self, shard: Shard, transitions: int) -> None:
        if not shard.up:
            log.info("replay shard up", extra=kv(addr=shard.addr, transitions=transitions))
        shard.up, shard.known, shard.transitions, shard.backoff_s = True, True, transitions, 0.0
        SHARD_UP.labels(shard.addr).set(1)
        SHARD_TRANSITIONS.labels(shard.addr).set(transitions)

    def _mark_down(self, shard: Shard, err: grpc.RpcError) -> None:
        code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
        if shard.up or not shard.known:
            log.warning("replay shard down; sampling the others", extra=kv(addr=shard.addr, code=str(code)))
        shard.backoff_s = min(self.max_backoff_s, max(self.min_backoff_s, 2 * shard.backoff_s))
        shard.up, shard.known = False, True
        shard.retry_at = self._clock() + shard.backoff_s
        SHARD_UP.labels(shard.addr).set(0)

    def _nothing_error(self) -> SamplerError:
        if any(s.up for s in self.shards):
            return SamplerError(grpc.StatusCode.FAILED_PRECONDITION, "every live replay shard is empty")
        down = ", ".join(s.addr for s in self.shards)
        return SamplerError(grpc.StatusCode.UNAVAILABLE, f"no replay shard answers ({down})")


def replay_source(
    lc: LearnerConfig, auth: AuthConfig, channel: grpc.Channel
) -> replay_pb2_grpc.ReplayStub | ShardedSampler | SharedMemoryReplay:
    """What the learner samples from: the one replay on `channel` (through shared memory where it proves to be on
    this host), or every shard of lc.replay_addrs."""
    if lc.replay_addrs:
        return ShardedSampler(lc.replay_addrs, auth, lc.rpc_timeout_s, seed=lc.seed)
    stub = replay_pb2_grpc.ReplayStub(channel)
    return SharedMemoryReplay(stub, lc.replay_shm_dir) if lc.replay_shm_dir else stub


# --------------------------------------------------------------------------- batches


def table_robots(request: replay_pb2.SampleRequest, table: str) -> list[str]:
    """The robots `table`'s rows are drawn from: its table_robot_ids entry, else robot_ids (empty = all)."""
    if table in request.table_robot_ids:
        return list(request.table_robot_ids[table].ids)
    return list(request.robot_ids)


def _batch_len(batch: replay_pb2.Batch) -> int:
    return int(batch.reward.shape[0]) if batch.reward.shape else 0


def merge_batches(batches: list[replay_pb2.Batch]) -> replay_pb2.Batch:
    """Concatenate batches along the leading dimension, field by field (same keys and dtypes required)."""
    if len(batches) == 1:
        return batches[0]
    out = replay_pb2.Batch()
    for field in replay_pb2.Batch.DESCRIPTOR.fields:
        name = field.name
        present = [b for b in batches if b.HasField(name)]
        if not present:
            continue
        if len(present) != len(batches):
            raise SamplerError(grpc.StatusCode.FAILED_PRECONDITION, f"replay shards disagree: {name} missing in some")
        if field.message_type.name == tensor_pb2.TensorMap.DESCRIPTOR.name:
            keys = set(getattr(present[0], name).tensors)
            if any(set(getattr(b, name).tensors) != keys for b in present):
                raise SamplerError(grpc.StatusCode.FAILED_PRECONDITION, f"replay shards disagree on {name} keys")
            merged = getattr(out, name)
            for k in sorted(keys):
                parts = [getattr(b, name).tensors[k] for b in present]
                kept = _concat_kept(parts)
                merged.tensors[k].CopyFrom(kept if kept is not None else wire.to_tensor(_concat(parts)))
        else:
            getattr(out, name).CopyFrom(wire.to_tensor(_concat([getattr(b, name) for b in present])))
    return out


def _concat_kept(tensors: list[tensor_pb2.Tensor]) -> tensor_pb2.Tensor | None:
    """Shards' encoded frames (Tensor.frame_bytes) of one kind joined as they came, to be decoded once by the
    learner; None when they are not all such frames of one encoding and image shape (then decode and join)."""
    first = tensors[0]
    like = (first.dtype, first.encoding, first.batch_dims, list(first.shape[1:]))
    if any(not t.frame_bytes or (t.dtype, t.encoding, t.batch_dims, list(t.shape[1:])) != like for t in tensors):
        return None
    return tensor_pb2.Tensor(
        dtype=first.dtype,
        shape=[sum(int(t.shape[0]) for t in tensors), *first.shape[1:]],
        data=b"".join(t.data for t in tensors),
        encoding=first.encoding,
        frame_bytes=[n for t in tensors for n in t.frame_bytes],
        batch_dims=first.batch_dims,
    )


def _concat(tensors: list[tensor_pb2.Tensor]) -> np.ndarray:
    try:
        arrays = [wire.from_tensor(t) for t in tensors]
    except wire.WireError as exc:
        raise SamplerError(grpc.StatusCode.INTERNAL, f"a replay shard sent an undecodable tensor: {exc}") from None
    if len({(a.dtype, a.shape[1:]) for a in arrays}) != 1:
        raise SamplerError(grpc.StatusCode.FAILED_PRECONDITION, "replay shards disagree on a tensor's dtype or shape")
    return np.concatenate(arrays)
