"""Replay's checks: a step must match the spec its robot registered (the contract in `user.spec`), and
an episode must be steps 0..last (EpisodeGuard, which needs the episodes replay has seen).

validate_step raises StepError (a user.wire.WireError) whose message names the field and whose
`reason` is a short label for the rejected-steps metric.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterable

from user.spec import StepError, check_tensor_map, validate_step
from user.v1 import step_pb2

__all__ = ["EpisodeGuard", "StepError", "check_tensor_map", "validate_step"]


class EpisodeGuard:
    """Episode semantics across steps: an episode is steps 0..last, and only its last step ends it.

    A step after the episode's last step, a second different last step, or a last step below a step
    already seen is rejected. Re-sent steps (same index) pass, so a reconnecting edge is never refused.
    Remembers the most recent `capacity` episodes in RAM; the service seeds it from the store at open
    (seed()), so a restart still knows which stored episodes ended.
    """

    def __init__(self, capacity: int = 100_000) -> None:
        self.capacity = capacity
        self._lock = threading.Lock()
        self._episodes: OrderedDict[tuple[str, str], tuple[int, int | None]] = OrderedDict()  # -> (max index, last)

    def seed(self, bounds: Iterable[tuple[str, str, int, int | None]]) -> None:
        """Remember stored episodes: (robot, episode, highest step index, last step index or None), oldest first."""
        with self._lock:
            for robot, episode, highest, last in bounds:
                self._episodes[(robot, episode)] = (highest, last)
                self._episodes.move_to_end((robot, episode))
                if len(self._episodes) > self.capacity:
                    self._episodes.popitem(last=False)

    def check(self, step: step_pb2.Step) -> None:
        """Raise StepError if `step` breaks its episode; otherwise remember it."""
        key, index = (step.robot_id, step.episode_id), step.step_index
        ends = step.terminated or step.truncated
        with self._lock:
            highest, last = self._episodes.get(key, (index, None))
            if last is not None and index > last:
                raise StepError("episode_order", f"step {index} comes after the episode's last step {last}")
            if ends and last is not None and index != last:
                raise StepError("episode_order", f"step {index} ends an episode that already ended at step {last}")
            if ends and highest > index:
                raise StepError("episode_order", f"step {index} cannot end the episode: step {highest} was seen")
            self._episodes[key] = (max(highest, index), index if ends else last)
            self._episodes.move_to_end(key)
            if len(self._episodes) > self.capacity:
                self._episodes.popitem(last=False)
