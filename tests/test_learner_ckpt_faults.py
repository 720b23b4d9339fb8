"""The learner's checkpoint directory under faults: one learner per learner.checkpoint_dir (a second one is refused
with one line while the first runs, in-process and through `userctl learner`, and starts once the first stopped or
failed to start), temp files a killed writer left are swept at start, and a disk that refuses checkpoint and
version-mark writes does not stop training. Real control and replay (in-process), a real `userctl learner`
process whose writes the kernel refuses (RLIMIT_FSIZE set on it from here with prlimit: EFBIG, as a full disk
gives ENOSPC), its own metrics and logs."""

from __future__ import annotations

import json
import os
import resource
import signal
import socket
import subprocess
import sys
import threading
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from cloud_learner.checkpoint import LATEST, CheckpointDirInUse, load_latest, read_version_mark, write_version_mark
from cloud_learner.server import LearnerService
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests.helpers import wait_for
from tests.test_control import Edge, register_msg
from tests.test_learner import service_cfg
from tests.test_learner_prepare import arm_spec, record_demos
from user.config import ConfigError, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2_grpc, learner_pb2, learner_pb2_grpc, replay_pb2, replay_pb2_grpc

REPO = Path(__file__).resolve().parents[1]
TOKEN = "test-token"
CKPT_EVERY, PUBLISH_EVERY = 40, 20


def userctl_learner(*args: str, **popen: Any) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "user.cli", "learner", *args]
    return subprocess.Popen(cmd, cwd=REPO, text=True, start_new_session=True, **popen)


# --------------------------------------------------------------------------- one learner per directory


def test_a_second_learner_on_the_checkpoint_dir_is_refused_until_the_first_stops(tmp_path: Path) -> None:
    cfg = service_cfg(tmp_path)  # control unreachable: the learner serves and waits for robots
    in_use = f"learner.checkpoint_dir {cfg.learner.checkpoint_dir} is in use by pid {os.getpid()}"
    first = LearnerService(cfg, start_metrics=False).start()
    try:
        with pytest.raises(CheckpointDirInUse) as refused:
            LearnerService(cfg, start_metrics=False)
        assert str(refused.value) == in_use
        sets = {
            "auth.token": TOKEN,
            "learner.checkpoint_dir": cfg.learner.checkpoint_dir,
            "learner.server.port": 0,
            "learner.server.metrics_port": 0,
            "learner.control_addr": "127.0.0.1:1",
        }
        cli = userctl_learner(*(a for k, v in sets.items() for a in ("--set", f"{k}={v}")), stderr=subprocess.PIPE)
        _, err = cli.communicate(timeout=300)
        assert (cli.returncode, err.strip().splitlines()) == (2, [f"userctl learner: {in_use}"])
    finally:
        first.stop()
    second = LearnerService(cfg, start_metrics=False).start()  # free once the first stopped
    second.stop()
    second.stop()  # safe twice
    LearnerService(cfg, start_metrics=False).start().stop()


def test_a_learner_that_fails_to_start_leaves_the_directory_free(tmp_path: Path) -> None:
    cfg = service_cfg(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        cfg.learner.server.port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=rf"learner\.server\.port {cfg.learner.server.port} is in use"):
            LearnerService(cfg, start_metrics=False).start()
    cfg.learner.server.port = 0
    LearnerService(cfg, start_metrics=False).start().stop()  # not "in use by pid" this process


def test_temp_files_a_killed_learner_left_are_gone_after_start(tmp_path: Path) -> None:
    cfg = service_cfg(tmp_path)
    exp = Path(cfg.learner.checkpoint_dir) / "default"
    exp.mkdir(parents=True)
    stale = [
        exp / ".weight_version.4242.tmp",
        exp / ".ckpt-000000040.pt.k3x_9a2b.tmp",
        exp.parent / ".latest.abcdefgh.tmp",
    ]
    kept = [exp / "notes.tmp", exp / "weight_version"]
    for path in [*stale, *kept]:
        path.write_text("7\n")
    learner = LearnerService(cfg, start_metrics=False)
    try:
        assert [p for p in stale if p.exists()] == [] and all(p.exists() for p in kept)
    finally:
        learner.stop()
    assert read_version_mark(exp) == 7


# --------------------------------------------------------------------------- a disk that refuses writes


class Stack:
    """Control and replay in-process; the sim arm registers and its 200 steps go to replay when the test says."""

    def __init__(self, tmp_path: Path) -> None:
        cfg = StackConfig.model_validate({"auth": {"token": TOKEN}})
        for section in (cfg.control, cfg.replay):
            section.server.port = section.server.metrics_port = 0
            section.server.grace_s = 0.5
        cfg.replay.path, cfg.replay.map_size_mb, cfg.replay.commit_max_delay_ms = tmp_path / "replay", 64, 5.0
        self.control = ControlService(cfg, start_metrics=False).start()
        cfg.replay.control_addr = cfg.learner.control_addr = self.control.address
        self.replay = ReplayService(cfg, start_metrics=False).start()
        cfg.learner.replay_addr = self.replay.address
        self.cfg, self.edge = cfg, None

    def register_robot(self) -> None:
        stub = control_pb2_grpc.ControlStub(make_channel(self.control.address, self.cfg.auth))
        self.edge = Edge(stub, register_msg("e", arm_spec()))
        assert self.edge.next_message().WhichOneof("msg") == "registered"

    def insert_steps(self) -> None:
        steps, _, _ = record_demos(episodes=10)
        stub = replay_pb2_grpc.ReplayStub(make_channel(self.replay.address, self.cfg.auth))
        reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]  # the default (online) table
        acked = [seq for ack in stub.Insert(iter(reqs), timeout=60) for seq in ack.seqs]
        assert acked == list(range(len(steps)))

    def stop(self) -> None:
        if self.edge is not None:
            self.edge.close()
        self.replay.stop()
        self.control.stop()


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[Stack]:
    started = Stack(tmp_path)
    try:
        yield started
    finally:
        started.stop()


class LearnerProcess:
    """`userctl learner` training SAC on the stack's arm; its JSON log lines, status and metrics as it runs."""

    def __init__(self, cfg: StackConfig, tmp_path: Path) -> None:
        self.ckpt = tmp_path / "ckpt"
        config = tmp_path / "learner.yaml"
        learner = {
            "server": {"port": 0, "metrics_port": 0, "grace_s": 0.5},
            "control_addr": cfg.learner.control_addr,
            "replay_addr": cfg.learner.replay_addr,
            "checkpoint_dir": str(self.ckpt),
            "weights_shm_dir": None,  # no files but the checkpoint directory's: the write limit is for those
            "replay_shm_dir": None,
            "rpc_timeout_s": 5.0,
            "min_transitions": 10,
            "max_updates_per_transition": 1e9,
            "publish_every": PUBLISH_EVERY,
            "checkpoint_every": CKPT_EVERY,
        }
        algorithm = {"kind": "sac", "params": {"batch_size": 16, "hidden": [16]}}
        doc = {
            "auth": {"token": TOKEN},
            "log_json": True,
            "log_level": "DEBUG",  # every "weights published" line (after the first they are DEBUG)
            "learner": learner,
            "experiments": [{"name": "reach", "algorithm": algorithm}],
        }
        config.write_text(yaml.safe_dump(doc))
        ready = tmp_path / "learner.ready"
        # stderr is a pipe, which no file-size limit touches, read as it comes so the learner never blocks on it
        self.proc = userctl_learner("-c", str(config), "--ready-file", str(ready), stderr=subprocess.PIPE)
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        wait_for(lambda: ready.exists() or self.proc.poll() is not None, "the learner serving", 300, 0.1)
        assert self.proc.poll() is None, self.tail()
        ports = json.loads(ready.read_text())
        self.status_stub = learner_pb2_grpc.LearnerStub(make_channel(f"127.0.0.1:{ports['grpc_port']}", cfg.auth))
        self.metrics_url = f"http://127.0.0.1:{ports['metrics_port']}/metrics"

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)

    def tail(self) -> str:
        return "".join(self.lines[-40:])

    def logs(self, msg: str) -> list[dict[str, Any]]:
        docs = [json.loads(line) for line in list(self.lines) if line.startswith("{")]
        return [d for d in docs if d["msg"] == msg]

    def status(self) -> learner_pb2.ExperimentStatus:
        try:
            (exp,) = self.status_stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10).experiments
        except grpc.RpcError:  # a loaded machine: the caller's wait_for asks again
            return learner_pb2.ExperimentStatus()
        return exp

    def metric(self, name: str) -> float:
        text = urllib.request.urlopen(self.metrics_url, timeout=10).read().decode()
        samples = [s for f in text_string_to_metric_families(text) for s in f.samples]
        return sum(s.value for s in samples if s.name == name and s.labels.get("experiment") == "reach")

    def limit_writes(self, max_bytes: int) -> None:
        """The kernel refuses the learner's writes past max_bytes of a file (EFBIG); -1 lifts it."""
        hard = resource.prlimit(self.proc.pid, resource.RLIMIT_FSIZE)[1]
        resource.prlimit(self.proc.pid, resource.RLIMIT_FSIZE, (max_bytes, hard))

    def latest(self) -> str:
        return (self.ckpt / "reach" / LATEST).read_text().strip()

    def grows(self, what: Callable[[], float], above: float, label: str) -> float:
        return wait_for(lambda: (v := what()) > above and v, label, 300, 0.05)


def ckpt_failures(learner: LearnerProcess) -> float:
    return learner.metric("user_learner_checkpoint_failures_total")


def mark_failures(learner: LearnerProcess) -> float:
    return learner.metric("user_learner_version_mark_failures_total")


def test_a_disk_that_refuses_writes_does_not_stop_training(stack: Stack, tmp_path: Path) -> None:
    exp = tmp_path / "ckpt" / "reach"
    write_version_mark(exp, 57)  # a previous learner published up to 57: this one starts at 58, whatever happens
    learner = LearnerProcess(stack.cfg, tmp_path)
    try:
        # The first publish refused: not published, tried again while the learner waits for data, never renumbered.
        learner.limit_writes(0)
        stack.register_robot()
        learner.grows(lambda: mark_failures(learner), 1, "the first publish and a retry refused")
        assert (learner.status().weight_version, read_version_mark(exp)) == (0, 57)
        learner.limit_writes(resource.RLIM_INFINITY)
        assert learner.grows(lambda: learner.status().weight_version, 0, "the owed version published") == 58
        stack.insert_steps()
        wait_for(lambda: (exp / LATEST).is_file() and learner.status().weight_version >= 60, "training", 300, 0.1)
        assert ckpt_failures(learner) == 0

        # Checkpoints refused, version marks (a few bytes) still written: training and publishing go on.
        learner.limit_writes(64)
        learner.grows(lambda: ckpt_failures(learner), 0, "a refused checkpoint")
        refused_at, before = learner.latest(), learner.status()
        failures = ckpt_failures(learner)
        learner.grows(lambda: learner.status().updates, before.updates + 3 * CKPT_EVERY, "updates under the fault")
        learner.grows(lambda: ckpt_failures(learner), failures, "the next interval refused too")
        assert learner.status().weight_version > before.weight_version and learner.latest() == refused_at

        # Marks refused too: nothing is published (an unmarked number could be reused after a crash).
        learner.limit_writes(0)
        learner.grows(lambda: mark_failures(learner), mark_failures(learner), "a refused version mark")
        held = learner.status()
        learner.grows(lambda: learner.status().updates, held.updates + 3 * PUBLISH_EVERY, "updates, no publish")
        assert learner.status().weight_version == held.weight_version == read_version_mark(exp)

        # Room again: the next publish and checkpoint succeed.
        learner.limit_writes(resource.RLIM_INFINITY)
        learner.grows(lambda: learner.status().weight_version, held.weight_version, "a publish after the fault")
        wait_for(lambda: learner.latest() != refused_at, "a checkpoint after the fault", 300, 0.05)
        assert load_latest(exp)["updates"] > before.updates  # type: ignore[index]

        # Refused again at SIGTERM: the final checkpoint is an error, the previous one stays, the learner exits 0.
        learner.limit_writes(64)
        learner.grows(lambda: ckpt_failures(learner), ckpt_failures(learner), "a refused checkpoint")
        last_written = learner.latest()
        learner.proc.send_signal(signal.SIGTERM)
        assert learner.proc.wait(120) == 0, learner.tail()
    finally:
        if learner.proc.poll() is None:
            learner.proc.kill()
            learner.proc.wait(60)
    assert learner.latest() == last_written and load_latest(exp)["updates"] == int(last_written[5:14])  # type: ignore[index]
    assert not list(exp.glob(".*.tmp")), "a refused write left its temp file"
    published = [d["version"] for d in learner.logs("weights published")]
    assert len(published) > 1 and published == list(range(58, published[-1] + 1)), "every version once, none reused"
    assert_logged_once_per_run(learner, exp)


def assert_logged_once_per_run(learner: LearnerProcess, exp: Path) -> None:
    """A warning naming path and errno at the start of each run of failures (two of checkpoints, two of marks),
    a line when writes succeed again, and the refused final checkpoint as an error."""
    warned = learner.logs("checkpoint not written; training goes on, retried at the next interval")
    assert [(w["level"], w["errno"], w["experiment"]) for w in warned] == [("WARNING", "EFBIG", "reach")] * 2
    assert all(w["path"].startswith(str(exp / "ckpt-")) for w in warned)
    marks = learner.logs("weight version mark not written; version not published, tried again later")
    assert [(m["level"], m["errno"], m["path"]) for m in marks] == [
        ("WARNING", "EFBIG", str(exp / "weight_version"))
    ] * 2
    assert len(learner.logs("checkpoint written again")) == 1
    assert len(learner.logs("weight version mark written again")) == 2
    (final,) = learner.logs("final checkpoint not written; the previous one stays")
    assert (final["level"], final["errno"]) == ("ERROR", "EFBIG")
