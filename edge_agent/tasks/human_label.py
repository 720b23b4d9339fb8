"""A human labels the outcome: a key marks success (HIL-SERL's "s"), another marks failure.

Reward is sparse: `success_reward` on the step the success key arrives (which ends the episode),
`failure_reward` on a failure key (which ends it too), 0 otherwise; `add_env_reward` adds the
robot's own reward on every step. Keys come from a `KeySource`: by default (`source: keyboard`) a
pynput keyboard listener; with `source: teleop`, the robot's teleoperator's label events (lerobot's
TeleopEvents: SUCCESS -> success, FAILURE/TERMINATE_EPISODE -> failure, RERECORD_EPISODE -> failure:
the episode ends unlabelled as a success), so the s/q/r keys of lerobot's keyboard teleop or a
gamepad's success/failure buttons label episodes; tests and other front ends inject their own.
"""

from __future__ import annotations

import threading
from typing import Literal, Protocol

import numpy as np
from pydantic import Field

from edge_agent.robot import Observation
from edge_agent.task import TASKS, Outcome, Task
from edge_agent.teleop import Teleoperator
from user.registry import PluginParams
from user.v1 import robot_pb2


class KeySource(Protocol):
    """Key presses since the last call, as characters ("s") or pynput key names ("space")."""

    def drain(self) -> list[str]: ...

    def close(self) -> None: ...


class QueueKeys:
    """A thread-safe key source fed by `press` (tests, a web console, a foot pedal driver)."""

    def __init__(self) -> None:
        self._keys: list[str] = []
        self._lock = threading.Lock()

    def press(self, key: str) -> None:
        with self._lock:
            self._keys.append(key)

    def drain(self) -> list[str]:
        with self._lock:
            keys, self._keys = self._keys, []
        return keys

    def close(self) -> None:
        pass


class PynputKeys(QueueKeys):
    """The local keyboard through pynput; needs a display (X11/Wayland) or a console on the robot PC."""

    def __init__(self) -> None:
        super().__init__()
        from pynput import keyboard  # optional: only a human at this machine needs it

        def on_press(key: object) -> None:
            char = getattr(key, "char", None)
            self.press(char if char else getattr(key, "name", str(key)))

        self._listener = keyboard.Listener(on_press=on_press)
        self._listener.start()

    def close(self) -> None:
        self._listener.stop()


class TeleopLabels:
    """A teleoperator's label events as keys: "success" -> the success key, "failure"/"rerecord" -> the failure key."""

    def __init__(self, teleop: Teleoperator, success_key: str, failure_key: str) -> None:
        self.teleop = teleop
        self.keys = {"success": success_key, "failure": failure_key, "rerecord": failure_key}

    def drain(self) -> list[str]:
        return [self.keys[e] for e in self.teleop.events() if e in self.keys]

    def close(self) -> None:
        pass  # the edge agent disconnects the teleoperator


@TASKS.register("human_label")
class HumanLabelTask(Task):
    """A human presses a key to mark success (or failure); sparse reward."""

    class Params(PluginParams):
        success_key: str = Field(default="s", min_length=1)
        failure_key: str = Field(default="f", min_length=1)
        success_reward: float = 1.0
        failure_reward: float = 0.0
        add_env_reward: bool = Field(default=False, description="also add the robot's own reward each step")
        source: Literal["keyboard", "teleop"] = Field(
            default="keyboard", description="keyboard: pynput keys; teleop: the robot's teleoperator's events"
        )

    params: Params

    def __init__(self, params: Params, spec: robot_pb2.RobotSpec, keys: KeySource | None = None) -> None:
        super().__init__(params, spec)
        self.keys: KeySource = keys if keys is not None else QueueKeys()
        if keys is None and params.source == "keyboard":
            try:
                self.keys = PynputKeys()
            except Exception as exc:  # no display, no input device
                raise RuntimeError(f"human_label task: no keyboard available ({exc}); inject a key source") from exc

    def attach_teleop(self, teleop: Teleoperator | None) -> None:
        """The edge agent hands over the robot's teleoperator; `source: teleop` labels from its events."""
        if self.params.source != "teleop":
            return
        if teleop is None:
            raise ValueError("human_label task with source: teleop needs a teleop on the same robot")
        self.keys = TeleopLabels(teleop, self.params.success_key, self.params.failure_key)

    def reset(self, observation: Observation) -> None:
        self.keys.drain()  # a key pressed between episodes labels nothing

    def evaluate(self, observation: Observation, action: np.ndarray, next_observation: Observation) -> Outcome:
        keys = set(self.keys.drain())
        success = self.params.success_key in keys
        failure = not success and self.params.failure_key in keys
        reward = self.params.success_reward if success else self.params.failure_reward if failure else 0.0
        if self.params.add_env_reward:
            reward += float(next_observation.reward)
        return Outcome(reward=reward, terminated=success or failure, success=success)

    def close(self) -> None:
        self.keys.close()
