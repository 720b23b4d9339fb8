"""Safety of the edge control loop: RobotLoop, ChunkExecutor, TickScheduler and LocalPolicy driven for real.

The robot is a one-joint arm under absolute position control (act(target) moves it there, hold() keeps it and
says what it commanded), so a stale command shows as a jump; each observation carries a serial number, so a test
can tell which one a step stored. Loops run on their own threads; tests wait on what the loop did, never on time.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

from edge_agent.agent import TELEOP_LOST_HOLDS, RobotLoop, TickScheduler
from edge_agent.policy_source import LocalPolicy, PolicySource, _Chunked
from edge_agent.robot import Observation, Robot, clip_action
from edge_agent.teleop import Teleoperator
from tests import helpers
from tests.helpers import ListSink, wait_for
from user import wire
from user.config import AuthConfig
from user.registry import PluginParams
from user.v1 import control_pb2, robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

torch.set_num_threads(1)

F32 = tpb.DTYPE_FLOAT32
Answer = tuple[np.ndarray, int] | None  # a policy source's: (action, version), or None (the robot holds)


class PosArm(Robot):
    """One joint: act(target) moves it to the target at once; hold() keeps it there and returns that command."""

    def __init__(self, rate_hz: float = 20.0, limit: float = 1.0, hold_returns: Callable[[float], Any] | None = None):
        self._spec = robot_pb2.RobotSpec(
            robot_id="arm-0",
            kind="posarm",
            action=robot_pb2.ActionSpace(shape=[1], low=[-limit], high=[limit], names=["joint.pos"], dtype=F32),
            observation=[
                robot_pb2.FeatureSpec(name="state", dtype=F32, shape=[1]),
                robot_pb2.FeatureSpec(name="seq", dtype=F32, shape=[1]),
            ],
            control_rate_hz=rate_hz,
        )
        self.q = 0.0
        self.seq = 0  # observations taken
        self.acts = 0
        self.holds = 0
        self.on_act: Callable[[int], None] = lambda n: None  # called with the number of acts so far
        self.hold_returns = hold_returns or (lambda q: np.array([q], np.float32))

    @property
    def spec(self) -> robot_pb2.RobotSpec:
        return self._spec

    def reset(self, seed: int | None = None) -> Observation:
        return self.observe()

    def observe(self) -> Observation:
        self.seq += 1
        return Observation(features={"state": np.array([self.q], np.float32), "seq": np.array([self.seq], np.float32)})

    def act(self, action: np.ndarray) -> np.ndarray:
        applied = clip_action(self._spec, action)
        self.q = float(applied[0])
        self.acts += 1
        self.on_act(self.acts)
        return applied

    def hold(self) -> Any:
        self.holds += 1
        return self.hold_returns(self.q)


class Planner(PolicySource):
    """A chunk policy on the real _Chunked/ChunkExecutor: plan(q) is the chunk (horizon, 1) for the arm observed at
    q, or None (no answer). By default each chunk says "stay where you were observed" for 40 ticks, so any row run
    after the arm moved elsewhere is a jump back."""

    def __init__(self, plan: Callable[[float], np.ndarray | None] | None = None) -> None:
        self.plan = plan or (lambda q: np.full((40, 1), q, np.float32))
        self.planned_on: list[float] = []
        self._chunks = _Chunked(self._fetch)

    def _fetch(self, robot_id: str, obs: dict[str, np.ndarray], deadline_s: float) -> Answer:
        q = float(obs["state"][0])
        self.planned_on.append(q)
        chunk = self.plan(q)
        return None if chunk is None else (chunk, 1)

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        return self._chunks.act(robot_id, observation, deadline_s)

    def reset(self, robot_id: str) -> None:
        self._chunks.reset(robot_id)

    def skip(self, robot_id: str, ticks: int) -> None:
        self._chunks.skip(robot_id, ticks)

    @property
    def version(self) -> int:
        return 1


class Constant(PolicySource):
    """Answers `value` for its first `answers` calls (all of them by default), then never in time."""

    def __init__(self, value: float, answers: int = -1) -> None:
        self.value, self.answers, self.calls = value, answers, 0

    def act(
        self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float
    ) -> tuple[np.ndarray, int] | None:
        self.calls += 1
        if 0 <= self.answers < self.calls:
            return None
        return np.array([self.value], np.float32), 3

    @property
    def version(self) -> int:
        return 3


class Hand(Teleoperator):
    """A scripted teleoperator: script(n) for its n-th poll is an action, None (nobody drives) or an exception."""

    def __init__(self, spec: robot_pb2.RobotSpec, script: Callable[[int], Any]) -> None:
        super().__init__(PluginParams(), spec)
        self.script, self.polls = script, 0
        self.first_poll_at: int | None = None  # steps sent when it was first polled

    def poll(self, observation: Observation) -> np.ndarray | None:
        self.polls += 1
        out = self.script(self.polls)
        if isinstance(out, Exception):
            raise out
        return None if out is None else np.array([out], np.float32)


def kind(step: step_pb2.Step) -> str:
    return "human" if step.intervention else "held" if step.held else "policy"


def value(tensor: Any) -> float:
    return float(wire.from_tensor(tensor).reshape(-1)[0])


def run_loop(loop: RobotLoop, until: Callable[[], bool], what: str) -> None:
    loop.start()
    try:
        wait_for(until, what)
    finally:
        loop.stop()
    assert loop.error is None and loop.failed is None, loop.error


def assert_policy_stays(steps: list[step_pb2.Step]) -> None:
    """Every policy-driven step commanded where the arm was observed: no row planned elsewhere ran."""
    for s in steps:
        if kind(s) == "policy":
            assert value(s.action) == pytest.approx(value(s.observation.tensors["state"])), (
                f"step {s.step_index} ran a chunk planned elsewhere: command {value(s.action)}, "
                f"arm at {value(s.observation.tensors['state'])}"
            )


# --------------------------------------------------------------------------- 1. stale chunks


def test_a_chunk_planned_before_a_human_takeover_never_runs_after_it() -> None:
    """The human moves the arm 0 -> 0.8 and hands back within the old chunk's horizon and max age: the policy's
    next action is planned on where the arm is now, not the old chunk's row (a 0.8 jump back)."""
    arm, sink, policy = PosArm(), ListSink(), Planner()
    human = Hand(arm.spec, lambda n: 0.08 * (n - 4) if 5 <= n < 15 else None)
    loop = RobotLoop(arm, policy, sink, mode="fast", action_deadline_s=0.005, teleop=human)
    run_loop(loop, lambda: len(sink.steps) >= 30, "30 steps")
    steps = sink.snapshot()
    kinds = [kind(s) for s in steps]
    assert kinds[4:14] == ["human"] * 10 and kinds[14:30] == ["policy"] * 16
    assert_policy_stays(steps)
    assert policy.planned_on[0] == 0.0 and policy.planned_on[-1] == pytest.approx(0.8)  # re-planned at the hand-back


@pytest.mark.parametrize("hold_by", ["pause", "lease"])
def test_a_chunk_planned_before_a_pause_or_lease_hold_never_runs_after_it(hold_by: str) -> None:
    """While the loop holds, someone moves the arm to 0.8; after RESUME (or the lease's release) the policy acts
    from a plan made on 0.8, never from the rows planned on 0 before the hold."""
    arm, sink, policy = PosArm(), ListSink(), Planner()
    loop = RobotLoop(arm, policy, sink, mode="fast", action_deadline_s=0.005)
    rid = arm.spec.robot_id

    def hold(n: int) -> None:
        if n == 5:
            loop.pause() if hold_by == "pause" else loop.set_lease(control_pb2.RobotLease(robot_id=rid, hold=True))

    arm.on_act = hold
    loop.start()
    try:
        wait_for(lambda: arm.holds >= 3, "the loop holding")
        arm.q = 0.8  # repositioned by hand while held
        loop.resume() if hold_by == "pause" else loop.set_lease(control_pb2.RobotLease(robot_id=rid))
        wait_for(lambda: len(sink.steps) >= 20, "20 steps")
    finally:
        loop.stop()
    steps = sink.snapshot()
    assert_policy_stays(steps)
    assert policy.planned_on[0] == 0.0 and policy.planned_on[-1] == pytest.approx(0.8)
    assert [kind(s) for s in steps[:5]] == ["policy"] * 5 and "policy" in [kind(s) for s in steps[6:]]


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, delay: float) -> None:
        self.t += delay


def test_chunk_rows_follow_the_ticks_the_scheduler_skipped() -> None:
    """A step overruns and the scheduler skips a tick: the next tick runs the row meant for its own time, not the
    row after the last one served (rows are per control tick, not per call)."""
    clock, period = FakeClock(), 0.05
    rows = np.arange(60, dtype=np.float32)[:, None]  # row k commands k: the action says which row ran
    policy = Planner(lambda q: None if policy.planned_on[1:] else rows)  # one chunk for the whole test
    ticks_at: list[float] = []

    def work(n: int) -> None:  # each step takes 0.01 s of the fake clock; the 6th takes 1.7 periods
        ticks_at.append(clock.t)
        clock.t += 0.085 if n == 6 else 0.01

    arm, sink = PosArm(rate_hz=1 / period, limit=100.0), ListSink()
    arm.on_act = work
    loop = RobotLoop(arm, policy, sink, mode="realtime", action_deadline_s=0.005)
    loop.scheduler = TickScheduler(period, clock=clock, sleep=clock.sleep)
    run_loop(loop, lambda: len(sink.steps) >= 15, "15 steps")
    steps = sink.snapshot()[:15]
    assert loop.scheduler.overruns == 1
    slots = [round((t - ticks_at[0]) / period) for t in ticks_at[:15]]
    assert slots[5:8] == [5, 7, 8]  # the tick of slot 6 was skipped
    assert [value(s.action) for s in steps] == slots


# --------------------------------------------------------------------------- 2. local deadline

ACTOR = {
    "obs_keys": ["state"],
    "obs_dim": 15,
    "action_dim": 3,
    "hidden": [16, 16],
    "action_low": [-1.0, -1.0, -1.0],
    "action_high": [1.0, 1.0, 1.0],
}
OBS = {"state": np.linspace(-1, 1, 15, dtype=np.float32)}


def test_a_local_policy_answers_within_its_deadline_and_drops_the_late_forward() -> None:
    """A forward that outlasts the deadline (a GC pause, a first CUDA call) leaves the robot holding at the deadline
    instead of blocking the control thread; calls meanwhile get no answer at once (not queued behind it); its late
    result is never served; the worker thread is reused."""
    local = LocalPolicy("127.0.0.1:1", AuthConfig(), "edge", deterministic=True, start=False)
    local._on_weights(helpers.random_weights(ACTOR, version=1, seed=1))
    net = local._policy
    assert net is not None
    forward = net.act
    gate, forwards = threading.Event(), []

    def slow(batched: dict[str, np.ndarray], deterministic: bool) -> Any:
        gate.wait(10)  # the stalled forward: it ends when the test opens the gate (10 s: a safety net only)
        forwards.append(1)
        return forward(batched, deterministic)

    net.act = slow  # type: ignore[method-assign]
    try:
        assert local.act("arm-0", OBS, 0.05) is None
        assert not forwards  # act() returned while its forward was still running
        assert local.act("arm-0", OBS, 0.05) is None  # the worker is still busy: no answer, nothing queued
        gate.set()
        answer = wait_for(lambda: local.act("arm-0", OBS, 30.0), "an answer once the worker is free")
        assert answer[1] == 1 and answer[0].shape == (3,)
        assert len(forwards) == 2  # answered by a forward of its own: the late one's result was dropped
        workers = [t for t in threading.enumerate() if t.name == "local-policy-arm-0"]
        assert len(workers) == 1
    finally:
        gate.set()
        local.close()


# --------------------------------------------------------------------------- 3. teleoperator lost mid-intervention


def test_a_teleoperator_failing_while_its_human_drives_leaves_the_robot_held() -> None:
    """The human overrides a policy pushing to +1 with 0.2; the device dies mid-intervention. The robot holds (not
    handed to the policy), also once hot-plug releases the device and while a re-plugged one answers None, until
    a teleoperator sends a human action again; a second loss is ended by an operator's RESUME."""
    arm, sink = PosArm(rate_hz=50.0), ListSink()
    lost_before = TELEOP_LOST_HOLDS.labels("arm-0")._value.get()
    unplugged = OSError("device unplugged")
    first = Hand(arm.spec, lambda n: unplugged if n >= 10 else 0.2 if n >= 5 else None)
    loop = RobotLoop(arm, Constant(1.0), sink, mode="fast", action_deadline_s=0.002, teleop=first)
    loop.start()
    try:
        wait_for(lambda: len(sink.steps) >= 20, "20 steps")
        loop.set_teleop(None)  # hot-plug releases the failing device
        detached_at = len(sink.steps)
        wait_for(lambda: len(sink.steps) >= detached_at + 5, "steps without a teleoperator")
        again_at: list[int] = []  # steps sent when the re-plugged device is first polled
        # Nobody touches it for 5 polls (None: still held), the human sends one action, then lets go.
        replugged = lambda n: again_at.append(len(sink.steps)) if n == 1 else 0.1 if n == 6 else None  # noqa: E731
        loop.set_teleop(Hand(arm.spec, replugged))
        wait_for(lambda: again_at and len(sink.steps) >= again_at[0] + 10, "the policy after the human's action")
        # a second loss, ended by an operator
        second = Hand(arm.spec, lambda n: unplugged if n >= 4 else 0.3)
        loop.set_teleop(second)
        wait_for(lambda: second.polls >= 10, "the second device lost")
        resumed_at = len(sink.steps)
        loop.resume()
        wait_for(lambda: len(sink.steps) >= resumed_at + 5, "steps after RESUME")
    finally:
        loop.stop()
    kinds = [kind(s) for s in sink.snapshot()]
    assert kinds[:4] == ["policy"] * 4 and kinds[4:9] == ["human"] * 5
    released_at = again_at[0] + 5  # the re-plugged device's 6th poll: a human action
    assert set(kinds[9:released_at]) == {"held"}  # from the failure until a human acted again (None polls too)
    assert again_at[0] - 9 >= 11 + 5  # held through the failures, the detach and 5 steps without a device
    assert kinds[released_at : released_at + 2] == ["human", "policy"]
    lost_at = kinds.index("human", released_at + 1) + 3  # the second device drove 3 polls, then failed
    assert kinds[lost_at - 3 : lost_at] == ["human"] * 3
    assert set(kinds[lost_at:resumed_at]) == {"held"}
    assert kinds[-1] == "policy" and not loop.teleop_lost
    held_for_loss = (released_at - 9) + (resumed_at - lost_at)
    assert TELEOP_LOST_HOLDS.labels("arm-0")._value.get() - lost_before >= held_for_loss


# --------------------------------------------------------------------------- 4. scheduler


def test_the_scheduler_never_fires_two_ticks_back_to_back_and_counts_a_late_tick() -> None:
    """A step late by less than a period (1.96 periods long) is followed by a tick a period later, on the grid,
    not by one at once; every grid tick passed over counts as an overrun, for any mix of step lengths."""
    clock, period = FakeClock(), 0.05
    sched = TickScheduler(period, clock=clock, sleep=clock.sleep)
    rng = np.random.default_rng(0)
    work = [0.001, 0.098, 0.001, 0.001, *rng.uniform(0.0, 3.0 * period, 300)]
    fired, slots = [], []
    for w in work:
        slots.append(sched.wait())
        fired.append(clock.t)
        clock.t += w
    assert np.diff(fired)[:4] == pytest.approx([0.05, 0.098, 0.052, 0.05])
    assert sched.overruns >= 1 and min(np.diff(fired)) >= period / 2 - 1e-9
    grid = (np.asarray(slots) - slots[0]) / period
    assert np.allclose(grid, np.round(grid))  # on the grid: robots started together keep ticking together
    assert sched.overruns == round(grid[-1]) + 1 - len(slots)  # every grid tick not run is counted
    assert np.abs(np.asarray(fired) - np.asarray(slots)).max() <= period / 2 + 1e-9  # each the slot nearest it


# --------------------------------------------------------------------------- 5. held steps record the hold


def test_held_steps_record_what_hold_commanded() -> None:
    """An absolute-position robot holds by commanding where it is: the held step says so (not a clipped zero,
    which would teach 'command 0 and the arm stays'); a robot whose hold() does not say gets the clipped zeros;
    a hold() answer outside the spec stops the robot like a bad act() answer."""
    arm, sink = PosArm(), ListSink()
    loop = RobotLoop(arm, Constant(0.5, answers=3), sink, mode="fast", action_deadline_s=0.002)
    run_loop(loop, lambda: len(sink.steps) >= 8, "8 steps")
    steps = sink.snapshot()[:8]
    assert [kind(s) for s in steps] == ["policy"] * 3 + ["held"] * 5
    assert [value(s.action) for s in steps] == [0.5] * 8

    silent, sink = PosArm(hold_returns=lambda q: None), ListSink()
    loop = RobotLoop(silent, Constant(0.5, answers=3), sink, mode="fast", action_deadline_s=0.002)
    run_loop(loop, lambda: len(sink.steps) >= 5, "5 steps")
    assert [value(s.action) for s in sink.snapshot()[3:5]] == [0.0, 0.0]

    wild = PosArm(hold_returns=lambda q: np.array([7.0], np.float32))
    loop = RobotLoop(wild, Constant(0.5, answers=3), ListSink(), mode="fast", action_deadline_s=0.002)
    loop.start()
    wait_for(lambda: not loop.alive, "the loop to stop")
    assert loop.failed is not None and "hold() returned a bad action" in loop.failed


# --------------------------------------------------------------------------- 6. the step before a pause


def test_the_step_before_a_pause_is_paired_with_the_observation_it_was_judged_on() -> None:
    """Replay pairs each step with the next step's observation. After a pause the first step holds on the frame the
    step before the pause was judged on, and only the one after it acts, on a frame taken after the pause: no
    observation taken is left out, so no step is paired with a frame it was not judged on."""
    arm, sink = PosArm(), ListSink()
    loop = RobotLoop(arm, Constant(0.5), sink, mode="fast", action_deadline_s=0.002)
    arm.on_act = lambda n: loop.pause() if n == 5 else None
    loop.start()
    try:
        wait_for(lambda: arm.holds >= 3, "the loop paused")
        loop.resume()
        wait_for(lambda: len(sink.steps) >= 10, "10 steps")
    finally:
        loop.stop()
    steps = sink.snapshot()[:10]
    # A step observes its next frame right after acting: consecutive serials mean each step's successor stored the
    # frame that step was judged on, and no frame taken in between was left out.
    stored = [value(s.observation.tensors["seq"]) for s in steps]
    assert stored == list(range(1, 11))
    assert kind(steps[5]) == "held" and [kind(s) for s in steps[6:]] == ["policy"] * 4
