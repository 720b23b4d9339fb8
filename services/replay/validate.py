"""Replay's checks: a step must match the spec its robot registered (the contract in `user.spec`), and
an episode must be steps 0..last (EpisodeGuard, which needs the episodes replay has seen).

validate_step raises StepError (a user.wire.WireError) whose message names the field and whose
`reason` is a short label for the rejected-steps metric.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from collections.abc import Iterable

from user.spec import StepError, check_tensor_map, validate_step
from user.v1 import step_pb2

__all__ = ["EpisodeGuard", "StepError", "check_tensor_map", "validate_step"]

_LOW = (1 << 64) - 1


class EpisodeGuard:
    """Episode semantics across steps: an episode is steps 0..last, and only its last step ends it.

    A step after the episode's last step, a second different last step, or a last step below a step
    already seen is rejected. Re-sent steps (same index) pass, so a reconnecting edge is never refused.
    Remembers the most recent `capacity` episodes in RAM; the service seeds it from the store at open
    (seed()), so a restart still knows which stored episodes ended.

    Memory: an entry is a 64-bit keyed hash of (robot, episode) -> one int packing (highest index, last
    index + 1), ~150 B; with the ids as a tuple of strings and a tuple value it was ~600 B, i.e. 60 MB at
    capacity, filling for hours at 64 robots (an episode every 5 s each), which the replay soak showed as
    steady growth. The hash is keyed per process, so ids cannot be chosen to collide (2**-64 otherwise).
    """

    def __init__(self, capacity: int = 100_000) -> None:
        self.capacity = capacity
        self._lock = threading.Lock()
        self._salt = os.urandom(16)
        self._episodes: OrderedDict[int, int] = OrderedDict()  # key -> highest << 64 | (last + 1, 0 = none)

    def __len__(self) -> int:
        return len(self._episodes)

    def _key(self, robot: str, episode: str) -> int:
        h = hashlib.blake2b(robot.encode(), digest_size=8, key=self._salt)
        h.update(b"\0" + episode.encode())
        return int.from_bytes(h.digest(), "little")

    def _remember(self, key: int, highest: int, last: int | None) -> None:
        self._episodes[key] = highest << 64 | (0 if last is None else last + 1)
        self._episodes.move_to_end(key)
        if len(self._episodes) > self.capacity:
            self._episodes.popitem(last=False)

    def seed(self, bounds: Iterable[tuple[str, str, int, int | None]]) -> None:
        """Remember stored episodes: (robot, episode, highest step index, last step index or None), oldest first."""
        with self._lock:
            for robot, episode, highest, last in bounds:
                self._remember(self._key(robot, episode), highest, last)

    def check(self, step: step_pb2.Step) -> None:
        """Raise StepError if `step` breaks its episode; otherwise remember it."""
        key, index = self._key(step.robot_id, step.episode_id), step.step_index
        ends = step.terminated or step.truncated
        with self._lock:
            packed = self._episodes.get(key)
            highest, last = (index, None) if packed is None else (packed >> 64, (packed & _LOW) - 1)
            if last is not None and last < 0:
                last = None
            if last is not None and index > last:
                raise StepError("episode_order", f"step {index} comes after the episode's last step {last}")
            if ends and last is not None and index != last:
                raise StepError("episode_order", f"step {index} ends an episode that already ended at step {last}")
            if ends and highest > index:
                raise StepError("episode_order", f"step {index} cannot end the episode: step {highest} was seen")
            self._remember(key, max(highest, index), index if ends else last)
