"""Action chunks executed at the control rate, the next one fetched before the current runs out.

A chunk policy answers one observation with `horizon` actions, one per control tick from the tick
that observation was taken. The ChunkExecutor serves one action per `tick()`:

- Asynchronous inference: once the newest chunk has `prefetch` ticks or fewer left, the next
  request goes out in the background with the current observation, so the robot keeps moving on
  the old chunk while the network and the model work. `prefetch` grows with the link: it is at
  least the ticks the slowest of the last few answers took, plus two, so a slow link or a big model
  asks earlier instead of letting the chunk run out (one request is in flight at a time, so a chunk
  must cover about twice the round trip for the robot never to hold). A chunk answered late is
  aligned by ticks: its rows for ticks already past are skipped.
- Temporal ensembling (ACT): where chunks overlap, the action is their weighted mean with
  weights exp(-decay * i), i = 0 for the oldest chunk, so a new chunk blends in smoothly.
- Hold: rows older than `max_age_s` (wall time since their observation) are not used; with no
  fresh row left, tick() returns None and the robot holds.
- With no chunk at all (start, or a one-action policy whose "chunk" is used up every tick) the
  request is made synchronously, exactly like a plain per-tick policy.
- Rows follow the control loop's ticks, not the calls of tick(): skip(n) tells of n ticks the loop
  skipped (a step overran), so the next row served is the one meant for the tick that runs. The loop
  calls reset() whenever the policy did not drive its previous tick (a human, a pause, a hold): a chunk
  planned before that must never resume afterwards.

Metrics: request latency, chunk age at use, ticks held, chunks received.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import prometheus_client

CHUNK_AGE = prometheus_client.Histogram(
    "user_edge_chunk_age_seconds",
    "Age of the newest chunk row used for an action (now - its observation time)",
    buckets=(0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28),
)
CHUNK_LATENCY = prometheus_client.Histogram(
    "user_edge_chunk_latency_seconds",
    "Time from sending an observation to having its chunk",
    ["mode"],
    buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.5, 1.0),
)
CHUNK_HOLDS = prometheus_client.Counter("user_edge_chunk_holds_total", "Ticks with no fresh chunk row (robot held)")
CHUNKS = prometheus_client.Counter("user_edge_chunks_total", "Chunks received, by mode", ["mode"])
PREFETCH_TICKS = prometheus_client.Histogram(
    "user_edge_chunk_prefetch_ticks",
    "Ticks left in the newest chunk when the next request went out (the adaptive prefetch)",
    buckets=(1, 2, 3, 4, 6, 8, 12, 16, 32),
)
LATENCY_WINDOW = 8  # answers whose slowest sets the prefetch
PERIOD_EWMA = 0.2  # weight of the newest tick interval in the control period estimate

# observation -> (actions (horizon, A) or (A,), policy version), or None (no answer in time).
FetchFn = Callable[[dict[str, np.ndarray]], "tuple[np.ndarray, int] | None"]
# Runs a fetch job off the control thread (default: a daemon thread per job).
Runner = Callable[[Callable[[], None]], None]


def _thread_runner(job: Callable[[], None]) -> None:
    threading.Thread(target=job, name="chunk-fetch", daemon=True).start()


@dataclass
class _Chunk:
    anchor: int  # tick of the observation it answers: row k is meant for tick anchor + k
    actions: np.ndarray  # (horizon, A) float32
    version: int
    observed_at: float  # clock() when its observation was taken

    def row(self, tick: int) -> np.ndarray | None:
        k = tick - self.anchor
        return self.actions[k] if 0 <= k < len(self.actions) else None


class ChunkExecutor:
    """One robot's chunk queue. tick() is called once per control period from the control loop."""

    def __init__(
        self,
        fetch: FetchFn,
        prefetch: int = 2,
        max_age_s: float = 1.0,
        decay: float = 0.01,
        clock: Callable[[], float] = time.monotonic,
        runner: Runner = _thread_runner,
        adaptive: bool = True,
    ) -> None:
        """adaptive=False keeps `prefetch` fixed whatever the round trip (for comparison)."""
        if prefetch < 0 or max_age_s <= 0:
            raise ValueError("prefetch must be >= 0 and max_age_s > 0")
        self.fetch, self.prefetch, self.max_age_s, self.decay = fetch, int(prefetch), float(max_age_s), float(decay)
        self.clock, self.runner, self.adaptive = clock, runner, adaptive
        self._latencies: deque[float] = deque(maxlen=LATENCY_WINDOW)  # seconds, newest last
        self._period_s = 0.0  # control period, estimated from tick() times; 0 = not known yet
        self._last_tick_at: float | None = None
        self._skipped = 0  # ticks skipped since the last tick(): the interval to it spans this many more periods
        self._lock = threading.Lock()
        self._chunks: list[_Chunk] = []  # oldest first
        self._in_flight = False
        self._episode = 0  # reset() bumps it: a fetch asked before then is dropped when it lands
        self.ticks = 0
        self.holds = 0
        self.received = 0
        self.last_latency_s = 0.0
        self.last_age_s = 0.0

    def tick(self, observation: dict[str, np.ndarray]) -> tuple[np.ndarray, int] | None:
        """The action for this control tick (and the version of the newest chunk used), or None: hold."""
        tick, now = self.ticks, self.clock()
        self.ticks += 1
        self._note_period(now)
        with self._lock:
            self._drop_used(tick, now)
            newest = self._chunks[-1] if self._chunks else None
            left = newest.anchor + len(newest.actions) - tick if newest is not None else 0
            ask = not self._in_flight and left <= self.prefetch_ticks()
            if ask:
                self._in_flight = True
                if newest is not None:
                    PREFETCH_TICKS.observe(left)
            episode = self._episode
        if ask and newest is None:
            self._request(observation, tick, now, "sync", episode)  # nothing to run on meanwhile: ask and wait
            now = self.clock()  # the action goes out after the fetch: its age (and freshness) counts from here
        elif ask:
            self.runner(lambda: self._request(observation, tick, now, "async", episode))
        return self._blend(tick, now)

    def skip(self, ticks: int) -> None:
        """The control loop skipped `ticks` ticks (a step overran): the rows meant for them are past."""
        if ticks < 0:
            raise ValueError(f"ticks must be >= 0, got {ticks}")
        self.ticks += ticks
        self._skipped += ticks

    def reset(self) -> None:
        """A new episode, or the policy did not drive the last tick: forget the old chunks, and a fetch in
        flight (planned from an observation before that, it is dropped when it lands); the next tick asks afresh."""
        with self._lock:
            self._chunks.clear()
            self._episode += 1
            self._in_flight = False

    def prefetch_ticks(self) -> int:
        """Ask for the next chunk when the newest has this many ticks left: the configured `prefetch`, or
        more when recent answers took longer than that many control periods."""
        if not self.adaptive or not self._latencies or self._period_s <= 0:
            return self.prefetch
        periods = max(self._latencies) / self._period_s
        # the answer must land before the tick its chunk would run out; one tick more absorbs jitter
        return max(self.prefetch, math.ceil(periods - 1e-6) + 2)  # (a round trip of exactly 3 periods is 3)

    # ------------------------------------------------------------------ internals

    def _note_period(self, now: float) -> None:
        last, self._last_tick_at = self._last_tick_at, now
        periods, self._skipped = 1 + self._skipped, 0
        if last is None or not 0 < now - last <= 1.0:  # the first tick, or a pause (reset, a held loop)
            return
        interval = (now - last) / periods
        self._period_s = interval if not self._period_s else self._period_s + PERIOD_EWMA * (interval - self._period_s)

    def _request(
        self, observation: dict[str, np.ndarray], tick: int, observed_at: float, mode: str, episode: int
    ) -> None:
        try:
            answer = self.fetch(observation)
        finally:
            with self._lock:
                if self._episode == episode:  # else a request of the new episode may be in flight
                    self._in_flight = False
        if answer is None:
            return
        actions, version = answer
        arr = np.asarray(actions, dtype=np.float32)
        arr = arr[None] if arr.ndim == 1 else arr
        latency = self.clock() - observed_at
        CHUNK_LATENCY.labels(mode).observe(latency)
        CHUNKS.labels(mode).inc()
        with self._lock:
            self.last_latency_s = latency
            self._latencies.append(latency)
            self.received += 1
            if self._episode == episode:
                self._chunks.append(_Chunk(tick, arr, int(version), observed_at))

    def _drop_used(self, tick: int, now: float) -> None:
        self._chunks = [
            c for c in self._chunks if c.anchor + len(c.actions) > tick and now - c.observed_at <= self.max_age_s
        ]

    def _blend(self, tick: int, now: float) -> tuple[np.ndarray, int] | None:
        with self._lock:
            self._drop_used(tick, now)
            live = [(c, row) for c in self._chunks if (row := c.row(tick)) is not None]
        if not live:
            self.holds += 1
            CHUNK_HOLDS.inc()
            return None
        weights = np.exp(-self.decay * np.arange(len(live), dtype=np.float64))
        rows = np.stack([row for _, row in live]).astype(np.float64)
        action = (weights[:, None] * rows).sum(0) / weights.sum()
        newest = live[-1][0]
        self.last_age_s = now - newest.observed_at
        CHUNK_AGE.observe(self.last_age_s)
        return action.astype(np.float32), newest.version
