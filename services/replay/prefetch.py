"""Batches assembled ahead, off the gRPC threads, so a learner's Sample rarely waits for assembly.

One feeder thread per kind of request (its serialized SampleRequest) keeps up to `depth` ready
responses. A feeder starts on the second request of a kind (a learner repeats its request; a one-off
one, as a fuzzer sends, never gets a thread that holds batches) and only for results `worth` keeping.
A ready batch is served while no insert landed since it was built, or while it is younger than
max_age_s; older ones are dropped. A feeder nobody asked for in IDLE_S stops.
Prioritized draws from a feeder see priorities as of when the batch was built (a batch or two old).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from user.log import kv

log = logging.getLogger(__name__)
IDLE_S = 10.0
MAX_FEEDERS = 16
MAX_ASKED = 256  # request kinds remembered to notice a repeat
RETRY_S = 0.05


class _Feeder:
    def __init__(self, build: Callable[[], Any], depth: int, generation: Callable[[], int]) -> None:
        self.build = build
        self.generation = generation
        self.ready: queue.Queue[tuple[int, float, Any]] = queue.Queue(maxsize=depth)
        self.last_asked = time.monotonic()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="replay-prefetch", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set() and time.monotonic() - self.last_asked < IDLE_S:
            gen, built_at = self.generation(), time.monotonic()
            try:
                item = self.build()
            except Exception as exc:  # empty table, store closing...: the caller's own build reports it
                log.debug("prefetch build failed", extra=kv(error=str(exc)))
                self.stop.wait(RETRY_S)
                continue
            while not self.stop.is_set():
                try:
                    self.ready.put((gen, built_at, item), timeout=0.1)
                    break
                except queue.Full:
                    if time.monotonic() - self.last_asked >= IDLE_S:
                        return


class Prefetcher:
    """get(key, build) returns a prefetched result of build() when a fresh one is ready, else builds now."""

    def __init__(self, depth: int, max_age_s: float, generation: Callable[[], int]) -> None:
        self.depth = depth
        self.max_age_s = max_age_s
        self.generation = generation
        self._feeders: dict[bytes, _Feeder] = {}
        self._asked: OrderedDict[bytes, float] = OrderedDict()  # kind -> when first asked (bounded)
        self._lock = threading.Lock()
        self.served = self.built = 0

    def get(self, key: bytes, build: Callable[[], Any], worth: Callable[[Any], bool] = lambda _: True) -> Any:
        if self.depth <= 0:
            return build()
        with self._lock:
            feeder = self._feeders.get(key)
        if feeder is not None and feeder.thread.is_alive():
            feeder.last_asked = time.monotonic()
            gen = self.generation()
            while True:
                try:
                    built_gen, built_at, item = feeder.ready.get_nowait()
                except queue.Empty:
                    break
                if built_gen == gen or time.monotonic() - built_at <= self.max_age_s:
                    self.served += 1
                    return item
        item = build()  # raises what the caller maps to a status; a feeder starts only after a success
        self.built += 1
        if (feeder is None or not feeder.thread.is_alive()) and self._repeated(key) and worth(item):
            self._start(key, build)
        return item

    def _repeated(self, key: bytes) -> bool:
        """True when this kind was asked before, within IDLE_S."""
        now = time.monotonic()
        with self._lock:
            first = self._asked.pop(key, None)
            if first is not None and now - first <= IDLE_S:
                return True
            self._asked[key] = now
            if len(self._asked) > MAX_ASKED:
                self._asked.popitem(last=False)
            return False

    def _start(self, key: bytes, build: Callable[[], Any]) -> None:
        with self._lock:
            old = self._feeders.get(key)
            if old is not None and old.thread.is_alive():
                return
            if len(self._feeders) >= MAX_FEEDERS:
                for k in [k for k, f in self._feeders.items() if not f.thread.is_alive()]:
                    del self._feeders[k]
                if len(self._feeders) >= MAX_FEEDERS:
                    return
            self._feeders[key] = _Feeder(build, self.depth, self.generation)

    def close(self) -> None:
        with self._lock:
            feeders = list(self._feeders.values())
            self._feeders.clear()
        for f in feeders:
            f.stop.set()
        for f in feeders:
            f.thread.join(timeout=2.0)
