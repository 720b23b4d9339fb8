"""MicroBatcher: batched preprocessing with instructions, chunk rows, stage timing, swaps under load."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pytest

from services.inference.batcher import MicroBatcher
from tests.helpers import wait_for

HORIZON, ACTION_DIM = 4, 2


class ChunkPolicy:
    """A tiny chunk policy: preprocess records what it saw; the chunk encodes version and instruction length."""

    def __init__(self, version: int) -> None:
        self.version = version
        self.seen: list[list[str]] = []
        self.threads: set[str] = set()

    def preprocess(self, observation: Mapping[str, np.ndarray], instructions: Sequence[str]) -> np.ndarray:
        self.seen.append(list(instructions))
        self.threads.add(threading.current_thread().name)
        lengths = np.array([len(t) for t in instructions], dtype=np.float32)
        return np.asarray(observation["state"], dtype=np.float32)[:, 0] + 100 * lengths

    def forward(self, prepared: np.ndarray, deterministic: bool) -> np.ndarray:
        base = prepared[:, None, None] + 1000 * self.version
        return np.broadcast_to(base, (len(prepared), HORIZON, ACTION_DIM)).copy()


def test_preprocess_runs_batched_in_the_worker_with_each_rows_instruction() -> None:
    policy = ChunkPolicy(version=1)
    batcher = MicroBatcher(max_batch=8, max_wait_ms=200, name="vla-batch").start()
    try:
        batcher.set_policy(policy.forward, 1, policy.preprocess)
        futures = [
            batcher.submit({"state": np.array([float(i), 0.0], np.float32)}, key=f"r{i}", instruction="x" * i)
            for i in range(3)
        ]
        results = [f.result(timeout=10) for f in futures]
    finally:
        batcher.stop()
    assert policy.threads == {"vla-batch"}  # never on the caller's (gRPC) thread
    assert sorted(t for batch in policy.seen for t in batch) == ["", "x", "xx"]
    for i, res in enumerate(results):
        assert res.action.shape == (HORIZON, ACTION_DIM)
        np.testing.assert_allclose(res.action, 1000 + i + 100 * i)  # its own row and its own instruction
        assert res.version == 1
        assert min(res.queue_us, res.preprocess_us, res.compute_us, res.postprocess_us) >= 0


def test_weight_swap_under_load_fails_no_request() -> None:
    batcher = MicroBatcher(max_batch=4, max_wait_ms=1, name="swap-batch").start()
    policies = [ChunkPolicy(version=v) for v in range(1, 11)]
    batcher.set_policy(policies[0].forward, 1, policies[0].preprocess)
    errors: list[BaseException] = []
    versions: list[int] = []
    stop = threading.Event()

    def robot(i: int) -> None:
        while not stop.is_set():
            try:
                res = batcher.submit({"state": np.zeros(2, np.float32)}, key=f"r{i}").result(timeout=10)
                # Each answer is whole: its chunk comes from the version it reports.
                assert np.all(res.action == 1000 * res.version)
                versions.append(res.version)
            except BaseException as exc:
                errors.append(exc)

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()

    def traffic() -> None:
        done = len(versions)
        while len(versions) < done + 4 and not errors:
            threading.Event().wait(0.001)

    try:
        for p in policies[1:]:
            traffic()  # some answers between swaps
            batcher.set_policy(p.forward, p.version, p.preprocess)
        wait_for(lambda: errors or versions[-1] == 10, "an answer from the last version")
    finally:
        stop.set()
        for t in threads:
            t.join(10)
        batcher.stop()
    assert not errors, errors[:3]
    assert max(versions) == 10 and len(set(versions)) > 2


class GatedSteps:
    """A real flow_vla policy whose second step waits for the test: requests can be queued mid-batch."""

    def __init__(self, policy: Any, fail: str = "") -> None:
        self.policy = policy
        self.stepping, self.release = threading.Event(), threading.Event()
        self.advances = 0
        self.fail = fail  # "advance" or "finish": that call raises, once

    def begin(self, prepared: Any, deterministic: bool) -> Any:
        return self.policy.begin(prepared, deterministic)

    def advance(self, rows: Any) -> Any:
        self.advances += 1
        if self.fail == "advance" and self.advances == 1:
            raise RuntimeError("step failed")
        if self.advances == 2:
            self.stepping.set()
            assert self.release.wait(10)
        return self.policy.advance(rows)

    def finish(self, rows: Any) -> np.ndarray:
        if self.fail == "finish":
            raise RuntimeError("step failed")
        return self.policy.finish(rows)


def flow_policy(version: int) -> Any:
    from tests.test_flow_vla import CFG, weights
    from user.policy import build_policy

    cfg = CFG.model_copy(update={"flow_steps": 4})
    w = weights(version, seed=version)
    w.policy.config_json = cfg.model_dump_json()
    return build_policy(w.policy, w.policy_tensors(), version)


def one_row(i: int) -> dict[str, np.ndarray]:
    from tests.test_flow_vla import observation

    return {k: v[0] for k, v in observation(1, seed=i).items()}


def alone(policy: Any, i: int) -> np.ndarray:
    return policy.forward(policy.preprocess({k: v[None] for k, v in one_row(i).items()}, [""]), True)[0]


def one_arrives_mid_batch(
    batcher: MicroBatcher, gated: GatedSteps, meanwhile: Callable[[], None] = lambda: None
) -> tuple[Any, Any]:
    """r0's batch stops between its steps; `meanwhile` runs, r1 arrives and is encoded; then the steps go on."""
    try:
        first = batcher.submit(one_row(0), deterministic=True, key="r0")
        assert gated.stepping.wait(10)
        meanwhile()
        second = batcher.submit(one_row(1), deterministic=True, key="r1")
        wait_for(lambda: batcher._ready.qsize() == 1, "r1 encoded, waiting for the next step")
        gated.release.set()
        return first.result(timeout=10), second.result(timeout=10)
    finally:
        batcher.stop()


def test_a_request_joins_a_continuous_batch_at_the_next_step_with_its_own_answer() -> None:
    policy = flow_policy(1)
    gated = GatedSteps(policy)
    joins: list[int] = []
    batcher = MicroBatcher(max_batch=8, max_wait_ms=0, name="flow-batch", on_join=joins.append).start()
    batcher.set_policy(policy.forward, 1, policy.preprocess, gated)
    a, b = one_arrives_mid_batch(batcher, gated)
    assert batcher.joined == 1 and joins == [1]  # r1 rode r0's steps instead of waiting for them to end
    np.testing.assert_allclose(a.action, alone(policy, 0), atol=1e-5)
    np.testing.assert_allclose(b.action, alone(policy, 1), atol=1e-5)
    assert a.version == b.version == 1
    # Each rode 4 steps, 2 of them together: on average a batch of 1.5, as requests / batches says.
    assert batcher.requests / batcher.batches == pytest.approx(1.5)


def test_after_a_swap_the_old_weights_rows_finish_apart_from_the_new() -> None:
    old, new = flow_policy(1), flow_policy(2)
    gated = GatedSteps(old)
    batcher = MicroBatcher(max_batch=8, max_wait_ms=0, name="flow-swap").start()
    batcher.set_policy(old.forward, 1, old.preprocess, gated)
    a, b = one_arrives_mid_batch(batcher, gated, lambda: batcher.set_policy(new.forward, 2, new.preprocess, new))
    assert (a.version, b.version) == (1, 2) and batcher.joined == 0
    np.testing.assert_allclose(a.action, alone(old, 0), atol=1e-5)
    np.testing.assert_allclose(b.action, alone(new, 1), atol=1e-5)


@pytest.mark.parametrize("fail", ["advance", "finish"])
def test_a_failing_step_fails_its_batch_and_the_worker_serves_on(fail: str) -> None:
    policy = flow_policy(1)
    gated = GatedSteps(policy, fail=fail)
    gated.release.set()
    batcher = MicroBatcher(max_batch=8, max_wait_ms=0, name="flow-fail").start()
    try:
        batcher.set_policy(policy.forward, 1, policy.preprocess, gated)
        with pytest.raises(RuntimeError, match="step failed"):
            batcher.submit(one_row(0), deterministic=True, key="r0").result(timeout=10)
        batcher.set_policy(policy.forward, 1, policy.preprocess, policy)
        res = batcher.submit(one_row(0), deterministic=True, key="r0").result(timeout=10)
    finally:
        batcher.stop()
    np.testing.assert_allclose(res.action, alone(policy, 0), atol=1e-5)


def test_a_row_that_fails_its_groups_encoding_fails_only_itself() -> None:
    """Continuous batching: a group whose preprocess/encode raises is begun again row by row, so only the
    robot whose input broke it gets the error."""
    policy = flow_policy(1)

    def picky(observation: Mapping[str, np.ndarray], instructions: Sequence[str]) -> Any:
        if np.any(np.asarray(observation["state"])[:, 0] == 99.0):
            raise ValueError("row with 99")
        return policy.preprocess(observation, instructions)

    batcher = MicroBatcher(max_batch=3, max_wait_ms=5_000, name="flow-picky").start()  # no keys: closes at 3
    try:
        batcher.set_policy(policy.forward, 1, picky, policy)
        bad = one_row(1)
        bad["state"] = np.full_like(bad["state"], 99.0)
        futures = [batcher.submit(o, deterministic=True) for o in (one_row(0), bad, one_row(2))]
        with pytest.raises(ValueError, match="row with 99"):
            futures[1].result(timeout=10)
        first, last = futures[0].result(timeout=10), futures[2].result(timeout=10)
    finally:
        batcher.stop()
    np.testing.assert_allclose(first.action, alone(policy, 0), atol=1e-5)
    np.testing.assert_allclose(last.action, alone(policy, 2), atol=1e-5)
