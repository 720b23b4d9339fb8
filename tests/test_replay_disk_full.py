"""Replay on a full disk: a real ReplayService (real gRPC, real LMDB) on a tiny tmpfs that the test fills, then
enlarges (remount). Needs root to mount; skipped otherwise."""

from __future__ import annotations

import logging
import os
import subprocess
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import prometheus_client
import pytest

from edge_agent.replay_client import ReplaySender
from services.replay.server import ReplayService
from services.replay.store import ReplayStore
from tests.helpers import wait_for
from tests.test_replay_store import episode, spec
from user.config import AuthConfig, StackConfig
from user.rpc import Backoff, make_channel
from user.v1 import replay_pb2, replay_pb2_grpc, step_pb2

AUTH = AuthConfig(token="test-token")
DIM = 2048  # 8 KiB observations: a 2 MiB disk holds about 150 steps
CHUNK = 16  # steps per Insert call, one commit each (commit_max_steps)
SMALL, LARGE = "2m", "64m"


def _mount(point: Path, size: str, remount: bool = False) -> None:
    opts = f"remount,size={size}" if remount else f"size={size}"
    subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(point)], check=True, capture_output=True)


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[tuple[Path, Callable[[], None]]]:
    """A 2 MiB tmpfs, and a function that enlarges it to 64 MiB in place."""
    point = tmp_path / "disk"
    point.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    try:
        _mount(point, SMALL)
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"cannot mount a tmpfs here: {getattr(exc, 'stderr', b'') or exc}")
    try:
        yield point, lambda: _mount(point, LARGE, remount=True)
    finally:
        subprocess.run(["umount", str(point)], check=False)


@pytest.fixture
def service(tiny_disk: tuple[Path, Callable[[], None]]) -> Iterator[ReplayService]:
    cfg = StackConfig(auth=AUTH)
    cfg.replay.path = tiny_disk[0] / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.commit_max_steps = CHUNK
    cfg.replay.server.port = 0
    cfg.replay.server.metrics_port = 0
    cfg.replay.server.grace_s = 1.0
    svc = ReplayService(cfg, spec_source={"arm-0": spec("arm-0", DIM)}.get, start_metrics=False).start()
    yield svc
    svc.stop()


def _steps(n: int) -> list[step_pb2.Step]:
    eps = [episode("arm-0", f"ep{e}", 40, dim=DIM) for e in range(-(-n // 40))]
    return [s for ep in eps for s in ep][:n]


def _metric(name: str, **labels: str) -> float:
    return prometheus_client.REGISTRY.get_sample_value(name, labels) or 0.0


def _insert(stub: replay_pb2_grpc.ReplayStub, steps: list[step_pb2.Step], first_seq: int) -> list[int]:
    """One Insert call (one commit); the acked seqs. Raises the RpcError that ended it."""
    reqs = [replay_pb2.InsertRequest(seq=first_seq + i, step=s) for i, s in enumerate(steps)]
    return [seq for ack in stub.Insert(iter(reqs), timeout=30) for seq in ack.seqs]


def _stats(stub: replay_pb2_grpc.ReplayStub) -> replay_pb2.StatsResponse:
    return stub.Stats(replay_pb2.StatsRequest(), timeout=10)


def test_a_full_disk_ends_inserts_resource_exhausted_and_recovers_when_space_returns(
    service: ReplayService, tiny_disk: tuple[Path, Callable[[], None]], caplog: pytest.LogCaptureFixture
) -> None:
    stub = replay_pb2_grpc.ReplayStub(make_channel(service.address, AUTH))
    steps = _steps(1000)  # ~8 MB for a 2 MiB disk
    failed_before = _metric("user_replay_failed_commits_total", reason="disk_full")
    acked: list[int] = []
    error: grpc.RpcError | None = None
    with caplog.at_level(logging.WARNING, logger="services.replay.store"):
        for at in range(0, len(steps), CHUNK):  # a call at a time: only one commit is ever in flight
            try:
                acked += _insert(stub, steps[at : at + CHUNK], at + 1)
            except grpc.RpcError as exc:
                error = exc
                break
        assert error is not None, "the disk never filled"
        assert error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, error.details()
        assert "replay's disk is full" in error.details() and "re-sent" in error.details()
        # the same steps again: refused alike, with no second warning
        with pytest.raises(grpc.RpcError) as again:
            _insert(stub, steps[len(acked) : len(acked) + CHUNK], len(acked) + 1)
        assert again.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert sorted(acked) == list(range(1, len(acked) + 1))
    assert _stats(stub).steps == len(acked)  # nothing of a failed commit is acked or stored
    assert _metric("user_replay_disk_full") == 1
    assert _metric("user_replay_failed_commits_total", reason="disk_full") - failed_before >= 2
    full_warnings = [r for r in caplog.records if "disk is full" in r.getMessage()]
    assert len(full_warnings) == 1 and not any(r.exc_info for r in caplog.records)
    assert stub.Sample(replay_pb2.SampleRequest(batch_size=4), timeout=10).batch.reward.shape  # sampling goes on

    tiny_disk[1]()  # space returns: the edge re-sends everything it kept, and the acked steps again
    for at in range(0, len(steps), CHUNK):
        assert len(_insert(stub, steps[at : at + CHUNK], at + 1)) == len(steps[at : at + CHUNK])
    st = _stats(stub)
    assert (st.steps, st.duplicates) == (len(steps), len(acked))  # every step once
    assert _metric("user_replay_disk_full") == 0

    service.stop()  # what committed survives a reopen intact
    reopened = ReplayStore(tiny_disk[0] / "replay", 64, readonly=True)
    try:
        assert reopened.stats()["steps"] == len(steps)
    finally:
        reopened.close()


class _Counted(Backoff):
    """A real Backoff that counts its waits and resets."""

    def __init__(self) -> None:
        super().__init__(initial_s=0.05, max_s=0.2)
        self.sleeps = self.resets = 0

    def sleep(self, stop: threading.Event | None = None) -> bool:
        self.sleeps += 1
        return super().sleep(stop)

    def reset(self) -> None:
        self.resets += 1
        super().reset()


def test_the_edge_backs_off_while_replay_is_full_and_delivers_every_step_once_after(
    service: ReplayService, tiny_disk: tuple[Path, Callable[[], None]]
) -> None:
    stub = replay_pb2_grpc.ReplayStub(make_channel(service.address, AUTH))
    full, broken = _Counted(), _Counted()
    sender = ReplaySender(service.address, AUTH, backoff=broken, full_backoff=full)
    try:
        steps = _steps(600)
        for step in steps:
            sender.send(step)
        wait_for(lambda: sender.full_answers >= 2, "replay to answer RESOURCE_EXHAUSTED twice")
        assert full.sleeps >= 2 and broken.sleeps == 0  # full answers wait on the full backoff, not the other
        assert _metric("user_replay_disk_full") == 1
        acked = sender.acked
        assert _stats(stub).steps >= acked  # every acked step is stored
        resets = full.resets

        tiny_disk[1]()
        wait_for(lambda: sender.unacked == 0, "every kept step acked once replay has space")
        assert _stats(stub).steps == len(steps)  # every step stored exactly once
        assert _metric("user_replay_disk_full") == 0
        assert full.resets > resets  # the wait starts short again
    finally:
        sender.close()
