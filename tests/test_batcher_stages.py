"""MicroBatcher: batched preprocessing with instructions, chunk rows, stage timing, swaps under load."""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence

import numpy as np

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
