"""ChunkExecutor: one action per tick, the next chunk fetched in the background and blended, hold when stale."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from edge_agent.chunks import ChunkExecutor

H, A = 5, 2


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class Runner:
    """Holds background fetches until the test lets them finish (the network 'is slow')."""

    def __init__(self) -> None:
        self.jobs: list[Callable[[], None]] = []

    def __call__(self, job: Callable[[], None]) -> None:
        self.jobs.append(job)

    def finish_all(self) -> None:
        jobs, self.jobs = self.jobs, []
        for job in jobs:
            job()


def chunk(base: float) -> np.ndarray:
    """Row k holds base + k in every dim, so a served action tells which chunk and row it came from."""
    return np.repeat((base + np.arange(H, dtype=np.float32))[:, None], A, axis=1)


def make(prefetch: int = 2, decay: float = 0.0, max_age_s: float = 1.0):
    clock, runner = Clock(), Runner()
    answers: list[np.ndarray] = [chunk(0.0), chunk(100.0), chunk(200.0)]
    asked: list[dict[str, np.ndarray]] = []

    def fetch(obs: dict[str, np.ndarray]) -> tuple[np.ndarray, int] | None:
        asked.append(obs)
        return (answers.pop(0), len(asked)) if answers else None

    ex = ChunkExecutor(fetch, prefetch=prefetch, max_age_s=max_age_s, decay=decay, clock=clock, runner=runner)
    ex.answers = answers  # type: ignore[attr-defined] - tests empty it to cut the link
    return ex, clock, runner, asked


def obs(i: int) -> dict[str, np.ndarray]:
    return {"state": np.full(3, i, np.float32)}


def test_chunk_runs_at_the_control_rate_and_blends_with_the_next() -> None:
    ex, clock, runner, asked = make(prefetch=2, decay=0.0)
    served = []
    for i in range(3):  # ticks 0..2: the first chunk, row by row; one synchronous request at the start
        served.append(ex.tick(obs(i)))
        clock.t += 0.05
    assert [a[0][0] for a in served] == [0.0, 1.0, 2.0] and len(asked) == 1
    # Tick 3: 2 rows left (<= prefetch): the next request goes out in the background with this tick's
    # observation, and the robot keeps running on the old chunk meanwhile.
    action, version = ex.tick(obs(3))
    assert action[0] == 3.0 and version == 1 and len(runner.jobs) == 1
    clock.t += 0.05
    runner.finish_all()  # the answer for tick 3 lands before tick 4
    assert asked[-1]["state"][0] == 3.0
    action, version = ex.tick(obs(4))  # old row 4 and new row 1 overlap: mean with decay 0
    np.testing.assert_allclose(action, [(4.0 + 101.0) / 2] * A)
    assert version == 2
    clock.t += 0.05
    action, _ = ex.tick(obs(5))  # the old chunk is used up: the new one alone (row 2)
    np.testing.assert_allclose(action, [102.0] * A)
    assert ex.received == 2 and ex.holds == 0


def test_ensembling_weights_the_older_chunk_more() -> None:
    ex, _clock, runner, _ = make(prefetch=2, decay=np.log(3.0))  # weights 1 and 1/3
    for i in range(4):
        ex.tick(obs(i))
    runner.finish_all()
    action, _ = ex.tick(obs(4))
    np.testing.assert_allclose(action, [(4.0 * 1 + 101.0 / 3) / (4 / 3)] * A, rtol=1e-6)


def test_late_chunk_skips_rows_already_past() -> None:
    ex, _clock, runner, _ = make(prefetch=2, decay=0.0)
    for i in range(5):  # the request from tick 3 is still in flight at tick 4
        ex.tick(obs(i))
    runner.finish_all()  # lands for tick 5: its rows 0 and 1 (ticks 3, 4) are past
    action, _ = ex.tick(obs(5))
    np.testing.assert_allclose(action, [102.0] * A)


def test_holds_when_nothing_fresh_is_left() -> None:
    ex, clock, _runner, _ = make(prefetch=0, max_age_s=0.2)
    assert ex.tick(obs(0)) is not None
    ex.answers.clear()  # the link is gone: requests get no answer
    clock.t = 0.5  # and the chunk in hand is too old to act on
    assert ex.tick(obs(1)) is None
    assert ex.holds == 1


def test_no_answer_holds_and_single_actions_work_per_tick() -> None:
    calls = []

    def fetch(o: dict[str, np.ndarray]) -> tuple[np.ndarray, int] | None:
        calls.append(o)
        return (np.array([len(calls), 0.0], np.float32), 7) if len(calls) != 2 else None

    ex = ChunkExecutor(fetch, prefetch=1, runner=lambda job: pytest.fail("a one-action policy needs no prefetch"))
    results = [ex.tick(obs(i)) for i in range(3)]
    assert results[0][0][0] == 1.0 and results[1] is None and results[2][0][0] == 3.0  # asked every tick
    assert results[0][1] == 7 and len(calls) == 3


def test_bad_params_are_refused() -> None:
    with pytest.raises(ValueError):
        ChunkExecutor(lambda o: None, prefetch=-1)


def test_reset_drops_old_chunks_and_the_fetch_in_flight() -> None:
    """A new episode starts on a chunk asked with its own observation: neither the old chunk's rows nor
    a prefetch asked during the old episode (landing after the reset) act in it."""
    ex, clock, runner, asked = make(prefetch=2, decay=0.0)
    for i in range(4):  # tick 3 sends the background request for the next chunk; the network holds it
        ex.tick(obs(i))
        clock.t += 0.05
    assert len(runner.jobs) == 1
    ex.reset()
    action, _ = ex.tick(obs(10))  # nothing left: a synchronous request with the new episode's observation
    assert asked[-1]["state"][0] == 10.0 and action[0] == 100.0
    runner.finish_all()  # the old episode's prefetch lands now (chunk 200, planned from tick 3)
    assert asked[-1]["state"][0] == 3.0
    clock.t += 0.05
    action, _ = ex.tick(obs(11))
    np.testing.assert_allclose(action, [101.0] * A)  # not blended with the stale chunk (202)
    for i in (12, 13):  # the new chunk (ticks 4-8) has 2 rows left at tick 7
        clock.t += 0.05
        ex.tick(obs(i))
    assert len(runner.jobs) == 1  # the in-flight flag was the new episode's to clear: prefetch works again


class DelayedRunner:
    """Background fetches take `ticks` control periods: a job queued at tick t finishes before tick t + ticks."""

    def __init__(self, ticks: int) -> None:
        self.ticks, self.now = ticks, 0
        self.jobs: list[tuple[int, Callable[[], None]]] = []

    def __call__(self, job: Callable[[], None]) -> None:
        self.jobs.append((self.now + self.ticks, job))

    def advance(self, clock: Clock) -> None:
        """Called before each tick: finish the jobs due by now, with the clock at their answer's time."""
        self.now += 1
        for due, job in [j for j in self.jobs if j[0] <= self.now]:
            self.jobs.remove((due, job))
            job()


@pytest.mark.parametrize("adaptive", [False, True])
def test_a_slow_link_asks_earlier_instead_of_holding(adaptive: bool) -> None:
    """Answers take 3 ticks, chunks have 8 rows: asking with 1 tick left runs the chunk out every time;
    asking as early as the measured round trip needs keeps the robot moving after the first slow answer."""
    clock, runner = Clock(), DelayedRunner(ticks=3)
    rows = 8

    def fetch(o: dict[str, np.ndarray]) -> tuple[np.ndarray, int]:
        return np.zeros((rows, A), np.float32), 1

    ex = ChunkExecutor(fetch, prefetch=1, clock=clock, runner=runner, adaptive=adaptive)
    held = []
    for i in range(60):
        runner.advance(clock)
        held.append(ex.tick(obs(i)) is None)
        clock.t += 0.05  # 20 Hz
    if adaptive:
        assert ex.prefetch_ticks() == 5  # ceil(0.15 s / 0.05 s) + 2
        assert not any(held[20:]), held
    else:
        assert sum(held[20:]) >= 10  # two ticks held per chunk of 8, every time
