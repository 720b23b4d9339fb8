"""Review fixes on the edge and inference routing, one test per defect: the spool's read leaves `put` free while it
loads large steps; inference's route refresher survives a refresh that raises and keeps robots control still lists
(a control restart unroutes none); a teleoperator hold ends only on a human action (or RESUME); a closed LocalPolicy
starts no worker thread; a wrong-size policy action or a refused observation is one log line per run and version.
Real LMDB in tmp dirs, real control and inference gRPC services on 127.0.0.1 ephemeral ports (TLS where said),
real RobotLoops and LocalPolicy; tests wait on what happened, never on time."""

from __future__ import annotations

import logging
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
import torch

from edge_agent.agent import RobotLoop
from edge_agent.control_client import ControlClient
from edge_agent.policy_source import LocalPolicy, PolicySource
from edge_agent.spool import LmdbSpool
from services.control.server import ControlService
from services.inference.server import InferenceService
from tests import helpers
from tests.helpers import ListSink, wait_for
from tests.test_auth import make_pki
from tests.test_edge_agent import sim_steps
from tests.test_inference_longrun import OBS_DIM, TWO, _call, _cfg, _code, _edge, _sac, _served
from tests.test_loop_safety import ACTOR, OBS, Constant, Hand, PosArm, kind
from tests.test_replay_store import spec
from user import wire
from user.config import AuthConfig, StackConfig
from user.rpc import make_channel
from user.v1 import control_pb2, inference_pb2_grpc

torch.set_num_threads(1)
TOKEN = "test-token"  # tests.test_inference_longrun's AUTH


# --------------------------------------------------------------------------- 1: the spool's read and put


class SlowDisk(LmdbSpool):
    """A spool whose disk reads stop half-way until released: a drain of large steps caught in the act."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, max_bytes=64 << 20)
        self.reading, self.release = threading.Event(), threading.Event()

    def _read_disk(self, after_seq: int, limit: int) -> list[Any]:
        out = super()._read_disk(after_seq, limit)
        self.reading.set()
        self.release.wait()
        return out


def test_a_put_is_not_blocked_while_the_sender_reads_large_steps(tmp_path: Path) -> None:
    """While the sender's read loads and parses large (1 MB camera) steps, the spool's lock is free, so a robot's
    put goes on; the read returns what it read, and the step put meanwhile comes with the next read."""
    steps = sim_steps(4)
    for step in steps:
        step.observation.tensors["camera"].CopyFrom(wire.to_tensor(np.ones((576, 576, 3), np.uint8)))
    spool = SlowDisk(tmp_path / "spool")
    try:
        seqs = [spool.put(s) for s in steps[:3]]
        read: list[Any] = []
        reader = threading.Thread(target=lambda: read.extend(spool.read(0, 64)))
        reader.start()
        try:
            assert spool.reading.wait(30), "the read never reached the disk"
            assert not spool._lock.locked(), "the read holds the lock that every put needs"
            late = spool.put(steps[3])  # a robot's control thread, mid-read
        finally:
            spool.release.set()
            reader.join()
        assert [r.seq for r in read] == seqs and read[0].step == steps[0]
        assert [r.seq for r in spool.read(seqs[-1], 64)] == [late]
    finally:
        spool.release.set()
        spool.close()


# --------------------------------------------------------------------------- 2 and 3: inference routing


def _tls_cfg(auth: dict[str, Any]) -> StackConfig:
    cfg = _cfg(TWO)
    return cfg.model_copy(update={"auth": AuthConfig(token=TOKEN, **auth)})


@pytest.fixture
def running() -> Iterator[list[Any]]:
    """Services and edges a test started, stopped after it (newest first)."""
    started: list[Any] = []
    yield started
    for thing in reversed(started):
        if isinstance(thing, ControlClient):
            thing.close()
        else:
            thing.stop()


def test_a_refresh_that_raises_keeps_the_refresher_and_fixing_its_cause_routes_the_robot(
    tmp_path: Path, running: list[Any], caplog: pytest.LogCaptureFixture
) -> None:
    """Inference reaches control over TLS with a CA file not there yet (make_channel raises ConfigError in the
    refresher): an Act is refused UNAVAILABLE naming auth.tls_ca, logged once with its traceback, and once the
    file is in place the refresher, still alive, routes the robot."""
    pki = make_pki(tmp_path)
    control = ControlService(_tls_cfg({"tls_cert": pki["server"], "tls_key": pki["server_key"]}), False).start()
    running.append(control)
    ca = tmp_path / "later" / "ca.pem"
    cfg = _tls_cfg({"tls_ca": ca})
    cfg.inference.control_addr = control.address
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    running.append(inference)
    inference.load_weights(_sac(1))
    specs = [spec("arm-0", obs_dim=OBS_DIM)]
    edge = ControlClient(
        control.address, AuthConfig(token=TOKEN, tls_ca=pki["ca"]), "pc-1", specs, list, lambda c: (True, "")
    )
    edge.start()
    running.append(edge)
    assert edge.wait_registered(10)
    stub = inference_pb2_grpc.InferenceStub(make_channel(inference.address, AuthConfig(token=TOKEN)))

    def refused_naming_the_ca() -> bool:
        answer = _call(stub, "arm-0")
        assert isinstance(answer, grpc.RpcError) and answer.code() == grpc.StatusCode.UNAVAILABLE, answer
        return "auth.tls_ca" in answer.details()  # not "not routed yet: waiting for control" for ever

    wait_for(refused_naming_the_ca, "the refresh failure recorded")
    lines = [r for r in caplog.records if r.getMessage().startswith("robot routes not refreshed")]
    assert len(lines) == 1 and lines[0].exc_info is not None
    ca.parent.mkdir()
    shutil.copy(pki["ca"], ca)
    wait_for(lambda: _served(stub, "arm-0", 1), "arm-0 routed once the CA file is there")


def test_a_control_restart_keeps_the_routes_of_robots_it_lists_offline(tmp_path: Path, running: list[Any]) -> None:
    """Control restarts (SQLite state, same port) and arm-0's edge has not reconnected: control lists it offline,
    and a refresh keeps its route, so its Acts are still served (not FAILED_PRECONDITION "in no experiment")."""
    cfg = _cfg(TWO)
    cfg.control.state_path = tmp_path / "control.sqlite"
    control = ControlService(cfg, start_metrics=False).start()
    running.append(control)
    cfg.control.server.port = int(control.address.rsplit(":", 1)[1])  # the restart binds the same port
    cfg.inference.control_addr = control.address
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    running.append(inference)
    inference.load_weights(_sac(1))
    edge = _edge(control, "arm-0")
    stub = inference_pb2_grpc.InferenceStub(make_channel(inference.address, AuthConfig(token=TOKEN)))
    wait_for(lambda: _served(stub, "arm-0", 1), "arm-0 served")
    control.stop()
    edge.close()  # its edge has not reconnected yet
    control = ControlService(cfg, start_metrics=False).start()
    running.append(control)
    listed = control_stub(control).ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=5)
    assert [(r.spec.robot_id, r.online) for r in listed.robots] == [("arm-0", False)]
    inference.router.refresh()
    assert inference.router._error == "" and inference.router.spec("arm-0") is not None
    assert _code(stub, "arm-0") == grpc.StatusCode.OK


def control_stub(control: ControlService) -> Any:
    from user.v1 import control_pb2_grpc

    return control_pb2_grpc.ControlStub(make_channel(control.address, AuthConfig(token=TOKEN)))


# --------------------------------------------------------------------------- 4: a teleoperator's hold


def test_a_teleoperator_back_from_a_glitch_answering_none_keeps_the_robot_held() -> None:
    """The human drives (polls 5-9), the gamepad glitches (poll 10 raises) and comes back without lerobot's
    intervention state (None from then on): the robot keeps holding, never handed to the policy the human was
    overriding, until an operator's RESUME."""
    arm, sink = PosArm(rate_hz=50.0), ListSink()
    hand = Hand(arm.spec, lambda n: OSError("glitch") if n == 10 else 0.2 if 5 <= n < 10 else None)
    loop = RobotLoop(arm, Constant(1.0), sink, mode="fast", action_deadline_s=0.002, teleop=hand)
    loop.start()
    try:
        wait_for(lambda: hand.polls >= 30, "20 polls answering None after the glitch")
        assert loop.teleop_lost
        resumed_at = len(sink.steps)
        loop.resume()
        wait_for(lambda: len(sink.steps) >= resumed_at + 5, "steps after RESUME")
    finally:
        loop.stop()
    assert loop.error is None and loop.failed is None, loop.error
    kinds = [kind(s) for s in sink.snapshot()]
    assert kinds[:4] == ["policy"] * 4 and kinds[4:9] == ["human"] * 5
    assert set(kinds[9:resumed_at]) == {"held"}  # the glitch, then every None poll
    assert kinds[-1] == "policy" and not loop.teleop_lost


# --------------------------------------------------------------------------- 5: a closed LocalPolicy


def test_a_closed_local_policy_answers_none_and_starts_no_worker_thread() -> None:
    """RoutedPolicy closes a stale copy while a robot loop may still be inside act: from then on the robot holds
    (None at once) and no forward thread is started that nothing would ever stop."""
    local = LocalPolicy("127.0.0.1:1", AuthConfig(), "edge", deterministic=True, start=False)
    local._on_weights(helpers.random_weights(ACTOR, version=1, seed=1))
    assert local.act("arm-open", OBS, 30.0) is not None  # a working copy before close
    local.close()
    assert local.act("arm-late", OBS, 30.0) is None
    assert local._fetch("arm-late", OBS, 30.0) is None  # a loop already past act's check when close() ran
    assert not [t for t in threading.enumerate() if t.name == "local-policy-arm-late"]


# --------------------------------------------------------------------------- 6: one line per run and version


class WrongSize(PolicySource):
    """Answers a 2-value action for the 1-joint arm: version 3 for its first `switch` calls, then version 4."""

    def __init__(self, switch: int) -> None:
        self.switch, self.calls, self.resets = switch, 0, 0

    def act(self, robot_id: str, observation: dict[str, np.ndarray], deadline_s: float) -> tuple[np.ndarray, int]:
        self.calls += 1
        return np.zeros(2, np.float32), 3 if self.calls <= self.switch else 4

    def reset(self, robot_id: str) -> None:
        self.resets += 1

    @property
    def version(self) -> int:
        return 3 if self.calls <= self.switch else 4


def test_a_wrong_size_policy_action_is_one_line_and_one_replan_per_run_and_version(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Every answer has the wrong size: the robot holds every tick, but says so once per policy version (not 50
    lines a second) and drops its plan once per version (not a reset and a synchronous fetch every tick)."""
    arm, sink, policy = PosArm(rate_hz=50.0), ListSink(), WrongSize(switch=20)
    loop = RobotLoop(arm, policy, sink, mode="fast", action_deadline_s=0.002)
    with caplog.at_level(logging.WARNING, logger="edge_agent.agent"):
        loop.start()
        try:
            wait_for(lambda: policy.calls >= 45, "45 wrong-size answers over two versions")
        finally:
            loop.stop()
    assert loop.error is None and loop.failed is None, loop.error
    assert {kind(s) for s in sink.snapshot()} == {"held"}
    lines = [r for r in caplog.records if "wrong size" in r.getMessage()]
    assert [r.fields.get("version") for r in lines] == [3, 4], [r.getMessage() for r in lines]
    assert policy.resets <= 3  # the episode's start, then once per version


def test_a_refused_observation_is_one_line_per_run_and_version(caplog: pytest.LogCaptureFixture) -> None:
    """A local policy refusing a robot's observations (a missing key) says so once, not every tick; once it takes
    one again, the next refusal is a new run and logged again."""
    local = LocalPolicy("127.0.0.1:1", AuthConfig(), "edge", deterministic=True, start=False)
    local._on_weights(helpers.random_weights(ACTOR, version=1, seed=1))
    try:
        with caplog.at_level(logging.WARNING, logger="edge_agent.policy_source"):
            for _ in range(20):
                local.reset("arm-0")
                assert local.act("arm-0", {"wrong": OBS["state"]}, 30.0) is None
            assert local.act("arm-0", OBS, 30.0) is not None
            local.reset("arm-0")
            assert local.act("arm-0", {"wrong": OBS["state"]}, 30.0) is None
    finally:
        local.close()
    lines = [r for r in caplog.records if "refused the observation" in r.getMessage()]
    assert len(lines) == 2
