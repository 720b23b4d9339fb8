"""An experiment removed while the stack runs (Control.RemoveExperiment) leaves nothing behind in the learner: its
weight versions leave the WeightStore and the shared-memory directory (version files and the mapped payload
buffers, with their fds), its weight streams end NOT_FOUND, its metric series go, its checkpoint directory keeps the
final checkpoint alone; and the per-version log lines of a long run are INFO once, then DEBUG and a summary a minute.

One scenario, run once for the module: real control and replay (in process, gRPC on 127.0.0.1, LMDB in a tmp dir),
a real LearnerService training SAC (1 MiB+ actor: its payloads are packed into shared-memory buffers) on steps a
MuJoCo arm recorded, a same-host WeightSubscriber (shared memory) and an unacked SubscribeWeights stream."""

from __future__ import annotations

import gc
import logging
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import prometheus_client
import pytest

from cloud_learner.checkpoint import LATEST, list_checkpoints
from cloud_learner.server import LearnerService
from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests.helpers import wait_for
from tests.test_learner_prepare import arm_spec, record_demos
from user.config import AuthConfig, ExperimentConfig, RobotSelector, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc, replay_pb2, replay_pb2_grpc
from user.weights import WeightSubscriber

AUTH = AuthConfig(token="test-token-0123456789")
GONE = "gamma"  # defined at run time, trained, stopped, removed
# Wide enough that its actor's payload (> 1 MiB) is packed into a mapped shared-memory buffer; small enough to train.
GAMMA = {
    "name": GONE,
    "robots": {"ids": ["arm-0"]},
    "algorithm": {"kind": "sac", "params": {"hidden": [640, 640], "batch_size": 16}},
}
LOGGERS = ("cloud_learner.learner", "cloud_learner.checkpoint", "user.weights")


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@dataclass
class Removed:
    """What the scenario saw before and after the removal."""

    shm_dir: Path
    ckpt_dir: Path
    checkpoints_before: int = 0
    buffers_before: int = 0
    shm_files_before: int = 0
    series_before: list[str] = field(default_factory=list)
    stream_code: list[grpc.StatusCode] = field(default_factory=list)
    learner: LearnerService | None = None
    records: list[logging.LogRecord] = field(default_factory=list)
    applied_versions: list[int] = field(default_factory=list)


def _buffers(shm_dir: Path) -> list[str]:
    return [n for n in os.listdir(shm_dir) if "-buf-" in n]


def _version_files(shm_dir: Path) -> list[str]:
    return [n for n in os.listdir(shm_dir) if f"-{GONE}-v" in n]


def _mapped_fds(shm_dir: Path) -> list[str]:
    """This process's fds on the learner's payload buffers (a live mmap holds a dup of its file's fd)."""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(shm_dir)) and "-buf-" in target:
            found.append(target)
    return found


def _series(name: str) -> list[str]:
    """Learner and weight-stream metric samples labelled with experiment `name`."""
    return [
        f"{s.name}{s.labels}"
        for family in prometheus_client.REGISTRY.collect()
        if family.name.startswith(("user_learner_", "user_weights_"))
        for s in family.samples
        if s.labels.get("experiment") == name
    ]


def _unacked_stream(addr: str, codes: list[grpc.StatusCode]) -> threading.Thread:
    """A SubscribeWeights stream of GONE read to its end; its status code lands in `codes`."""

    def read() -> None:
        with make_channel(addr, AUTH) as channel:
            stub = learner_pb2_grpc.LearnerStub(channel)
            call = stub.SubscribeWeights(learner_pb2.SubscribeWeightsRequest(client_id="plain", experiment=GONE))
            try:
                for _ in call:
                    pass
                codes.append(grpc.StatusCode.OK)
            except grpc.RpcError as err:
                codes.append(err.code())

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def _config(tmp: Path, control: ControlService, replay: ReplayService) -> StackConfig:
    cfg = StackConfig(auth=AUTH, experiments=[ExperimentConfig(name="base", robots=RobotSelector(ids=["nobody"]))])
    lc = cfg.learner
    lc.server.port = lc.server.metrics_port = 0
    lc.server.grace_s = 0.5
    lc.control_addr, lc.replay_addr = control.address, replay.address
    lc.checkpoint_dir, lc.weights_shm_dir, lc.replay_shm_dir = tmp / "ckpt", str(tmp / "shm"), None
    lc.min_transitions, lc.max_updates_per_transition, lc.rpc_timeout_s = 10, 1e9, 5.0
    lc.publish_every, lc.checkpoint_every = 2, 4
    (tmp / "shm").mkdir()
    return cfg


def _services(tmp: Path) -> tuple[ControlService, ReplayService]:
    cfg = StackConfig(auth=AUTH, experiments=[ExperimentConfig(name="base", robots=RobotSelector(ids=["nobody"]))])
    for section in (cfg.control, cfg.replay):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.1
    cfg.control.state_path = tmp / "control.sqlite"
    cfg.replay.path, cfg.replay.map_size_mb, cfg.replay.commit_max_delay_ms = tmp / "replay", 64, 5.0
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = control.address
    return control, ReplayService(cfg, start_metrics=False).start()


def _insert_steps(replay: ReplayService) -> None:
    steps, _, _ = record_demos(episodes=5)
    stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, AUTH))
    reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]
    acked = [seq for ack in stub.Insert(iter(reqs), timeout=60) for seq in ack.seqs]
    assert acked == list(range(len(steps)))


def _train_then_remove(tmp: Path, control: ControlService, replay: ReplayService, seen: Removed) -> None:
    import json

    cfg = _config(tmp, control, replay)
    stub = control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))
    edge = ControlClient(control.address, AUTH, "pc-1", [arm_spec()], lambda: [], lambda c: (True, "done"))
    assert edge.wait_registered(10)
    service = seen.learner = LearnerService(cfg, start_metrics=False).start()
    subscriber = None
    try:
        stub.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=json.dumps(GAMMA)), timeout=30)
        wait_for(lambda: service.store.version_of(GONE) >= 1, "the first version of the defined experiment", 120)
        subscriber = WeightSubscriber(
            service.address,
            AUTH,
            "same-host",
            lambda w: seen.applied_versions.append(w.version),
            experiment=GONE,
            shm_dir=str(seen.shm_dir),
        ).start()
        stream = _unacked_stream(service.address, seen.stream_code)
        _insert_steps(replay)
        ckpt = seen.ckpt_dir
        wait_for(lambda: len(list_checkpoints(ckpt)) >= 3 and subscriber.version >= 5, "training on gamma", 300, 0.1)
        wait_for(lambda: _version_files(seen.shm_dir), "a version in shared memory", 60)
        seen.checkpoints_before = len(list_checkpoints(ckpt))
        seen.buffers_before, seen.shm_files_before = len(_buffers(seen.shm_dir)), len(_version_files(seen.shm_dir))
        seen.series_before = _series(GONE)
        stub.StopExperiment(control_pb2.StopExperimentRequest(name=GONE), timeout=5)
        run = service.learner.runs[GONE]
        wait_for(lambda: run.stopped.is_set(), "the learner to hear it stopped", 60)
        stub.RemoveExperiment(control_pb2.RemoveExperimentRequest(name=GONE), timeout=5)
        wait_for(lambda: GONE not in service.learner.experiment_states, "the learner to drop it", 60)
        stream.join(30)
    finally:
        if subscriber is not None:
            subscriber.stop()
        edge.close()


@pytest.fixture(scope="module")
def removed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Removed]:
    tmp = tmp_path_factory.mktemp("removed")
    seen = Removed(shm_dir=tmp / "shm", ckpt_dir=tmp / "ckpt" / GONE)
    handler = _Records()
    loggers = [logging.getLogger(name) for name in LOGGERS]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.addHandler(handler)
        lg.setLevel(logging.DEBUG)
    control, replay = _services(tmp)
    try:
        _train_then_remove(tmp, control, replay, seen)
        seen.records = handler.records
        yield seen
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.removeHandler(handler)
            lg.setLevel(level)
        if seen.learner is not None:
            seen.learner.stop()
        replay.stop()
        control.stop()


# --------------------------------------------------------------------------- 1: weights in memory and shared memory


def test_a_removed_experiments_weights_leave_the_store_and_shared_memory(removed: Removed) -> None:
    assert removed.learner is not None
    store = removed.learner.store
    assert removed.shm_files_before >= 1 and removed.buffers_before >= 1  # there was something to leave
    wait_for(lambda: GONE not in store.experiments() and store.latest(GONE) is None, "its versions to leave", 10)
    wait_for(lambda: not _version_files(removed.shm_dir), "its version files to go", 10)

    def buffers_gone() -> bool:
        gc.collect()  # what a stream's ended frame still held
        return not _buffers(removed.shm_dir) and not _mapped_fds(removed.shm_dir)

    wait_for(buffers_gone, "its payload buffers (files, maps, fds) to go", 10)


def test_a_stream_of_a_removed_experiment_ends_not_found(removed: Removed) -> None:
    assert removed.applied_versions, "the same-host subscriber got versions before the removal"
    assert removed.stream_code == [grpc.StatusCode.NOT_FOUND]
    assert removed.learner is not None
    channel = make_channel(removed.learner.address, AUTH)
    call = learner_pb2_grpc.LearnerStub(channel).SubscribeWeights(
        learner_pb2.SubscribeWeightsRequest(experiment=GONE), timeout=30
    )
    with pytest.raises(grpc.RpcError) as err:
        next(call)
    assert err.value.code() == grpc.StatusCode.NOT_FOUND


# --------------------------------------------------------------------------- 2: per-version log lines


def _lines(removed: Removed, message: str, *, key: str, value: Any) -> list[logging.LogRecord]:
    return [r for r in removed.records if r.getMessage() == message and getattr(r, "fields", {}).get(key) == value]


def _at_most_one_info_a_minute(lines: list[logging.LogRecord]) -> None:
    """The first line at INFO; then DEBUG, with at most one INFO line (saying how many since the last) a minute."""
    assert len(lines) >= 4, [r.levelname for r in lines]
    info = [r for r in lines if r.levelno == logging.INFO]
    assert lines[0].levelno == logging.INFO and "since_last_info" not in lines[0].fields  # type: ignore[attr-defined]
    assert all("since_last_info" in r.fields for r in info[1:])  # type: ignore[attr-defined]
    assert {r.levelno for r in lines} <= {logging.INFO, logging.DEBUG}
    span_min = int((lines[-1].created - lines[0].created) // 60)
    assert len(info) <= 1 + span_min, [(r.levelname, r.created) for r in lines]


def test_weights_published_is_info_once_then_debug(removed: Removed) -> None:
    lines = _lines(removed, "weights published", key="experiment", value=GONE)
    assert [r.fields["version"] for r in lines] == list(range(1, len(lines) + 1))  # type: ignore[attr-defined]
    _at_most_one_info_a_minute(lines)


def test_weights_applied_is_info_once_then_debug(removed: Removed) -> None:
    lines = [r for r in removed.records if r.getMessage() == "weights applied"]
    assert [r.fields["version"] for r in lines] == removed.applied_versions  # type: ignore[attr-defined]
    _at_most_one_info_a_minute(lines)


def test_checkpoint_saved_is_info_once_then_debug(removed: Removed) -> None:
    lines = [
        r
        for r in removed.records
        if r.getMessage() == "checkpoint saved" and r.fields["path"].startswith(str(removed.ckpt_dir))  # type: ignore[attr-defined]
    ]
    _at_most_one_info_a_minute(lines)


# --------------------------------------------------------------------------- 3: metric series


def test_a_removed_experiments_metric_series_go(removed: Removed) -> None:
    names = {s.split("{")[0] for s in removed.series_before}
    assert {"user_learner_updates_total", "user_learner_scalar", "user_learner_weight_version"} <= names
    assert {"user_learner_loop_seconds_total", "user_learner_buffer_transitions"} <= names
    wait_for(lambda: not _series(GONE), "its series to go", 10)


# --------------------------------------------------------------------------- 4: checkpoints


def test_a_removed_experiment_keeps_its_final_checkpoint_alone(removed: Removed) -> None:
    assert removed.checkpoints_before >= 2
    kept = list_checkpoints(removed.ckpt_dir)
    assert len(kept) == 1 and (removed.ckpt_dir / LATEST).read_text().strip() == kept[0].name


def test_the_other_experiments_and_the_learner_go_on(removed: Removed) -> None:
    assert removed.learner is not None and not removed.learner.learner.failed
    assert "base" in removed.learner.learner.experiment_states


# --------------------------------------------------------------------------- the routine log itself


def test_routine_log_first_info_then_debug_then_a_summary_a_minute(caplog: pytest.LogCaptureFixture) -> None:
    from user.log import RoutineLog

    now = [100.0]
    routine = RoutineLog("tick", every_s=60.0, clock=lambda: now[0])
    logger = logging.getLogger("tests.routine")
    with caplog.at_level(logging.DEBUG, logger="tests.routine"):
        for step in range(5):
            now[0] += 20.0 * (step > 0)
            routine.log(logger, "a", n=step)
        routine.log(logger, "b", n=0)
        routine.reset("a")  # an error: the next line says the routine is back
        routine.log(logger, "a", n=5)
    got = [(r.levelname, r.fields["n"], r.fields.get("since_last_info")) for r in caplog.records]  # type: ignore[attr-defined]
    assert got == [
        ("INFO", 0, None),
        ("DEBUG", 1, None),
        ("DEBUG", 2, None),
        ("INFO", 3, 3),  # 60 s after the first: the summary, counting itself
        ("DEBUG", 4, None),
        ("INFO", 0, None),  # another key: its own first line
        ("INFO", 5, None),
    ]
