"""Property-based fuzzing of every RPC of every service, streams included, with messages built from the
proto descriptors (tests/fuzz_messages.py).

Properties: every call ends with a defined status (never UNKNOWN or INTERNAL, counted on the server side
too), nothing invalid reaches an edge, rejected steps leave the store unchanged, and every service still
answers health checks afterwards. Seeded and short in the normal run; `make fuzz` sets
USER_FUZZ_EXAMPLES=10000 for the long run and reports resident memory before and after.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import prometheus_client
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cloud_learner.server import LearnerService
from services.control.server import ControlService
from services.inference.server import InferenceService
from services.replay.server import ReplayService
from tests import helpers
from tests.fuzz_messages import any_or_near, near
from user import wire
from user.config import AuthConfig, StackConfig
from user.policy import policy_spec_for
from user.rpc import check_health, make_channel
from user.shm_files import host_id
from user.v1 import (
    control_pb2,
    control_pb2_grpc,
    inference_pb2,
    inference_pb2_grpc,
    learner_pb2,
    learner_pb2_grpc,
    replay_pb2,
    replay_pb2_grpc,
    robot_pb2,
    step_pb2,
)
from user.v1 import tensor_pb2 as tpb

pytestmark = [
    pytest.mark.timeout(3600),
    # The learner's retry loop (a background thread) draws from `random` while hypothesis generates.
    pytest.mark.filterwarnings("ignore::hypothesis.errors.HypothesisDeprecationWarning"),
]

EXAMPLES = int(os.environ.get("USER_FUZZ_EXAMPLES", "40"))
LONG = EXAMPLES >= 1000
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize=True,  # seeded: the same messages every run
    database=None,
    deadline=None,
    suppress_health_check=list(HealthCheck),
)
# Statuses our code may end a call with; UNKNOWN and INTERNAL mean an exception escaped a handler.
BAD = {grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL}
AUTH = AuthConfig(token="fuzz-token")
ROBOT = "arm-0"
CALL_S = 5.0
ACTOR = {
    "obs_keys": ["state"],
    "obs_dim": 6,
    "action_dim": 3,
    "hidden": [8],
    "action_low": [-1.0] * 3,
    "action_high": [1.0] * 3,
}


def robot_spec(robot_id: str = ROBOT) -> robot_pb2.RobotSpec:
    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="sim_reach_arm",
        action=robot_pb2.ActionSpace(shape=[3], low=[-1, -1, -1], high=[1, 1, 1], dtype=tpb.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[6])],
        control_rate_hz=10.0,
        max_episode_steps=50,
    )


def valid_step(index: int = 0, last: bool = False) -> step_pb2.Step:
    state = wire.to_tensor_map({"state": np.zeros(6, np.float32)})
    step = step_pb2.Step(
        robot_id=ROBOT,
        episode_id="ep-fuzz",
        step_index=index,
        observation=state,
        action=wire.to_tensor(np.zeros(3, np.float32)),
        terminated=last,
    )
    if last:
        step.final_observation.CopyFrom(state)
    return step


def server_errors() -> dict[str, float]:
    """UNKNOWN + INTERNAL endings by method, counted by the servers' metrics interceptor (in-process)."""
    counts: dict[str, float] = {}
    for metric in prometheus_client.REGISTRY.collect():
        if metric.name == "user_grpc_server_handled":
            for s in metric.samples:
                if s.name.endswith("_total") and s.labels.get("code") in ("UNKNOWN", "INTERNAL") and s.value:
                    key = f"{s.labels['method']} {s.labels['code']}"
                    counts[key] = counts.get(key, 0.0) + s.value
    return counts


def rss_mb() -> float:
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class Edge:
    """A registered edge on a Connect stream that records every command control forwards to it."""

    def __init__(self, stub: control_pb2_grpc.ControlStub) -> None:
        self.up: queue.Queue = queue.Queue()
        reg = control_pb2.RegisterRequest(agent_id="fuzz-edge", hostname="h", robots=[robot_spec()])
        self.up.put(control_pb2.EdgeMessage(register=reg))
        self.commands: list[control_pb2.Command] = []
        # the stream lives for the whole run: `make fuzz` took 75 min on a loaded 2-core machine (1 h ended it)
        self.call = stub.Connect(iter(self.up.get, None), timeout=3600 if EXAMPLES <= 1000 else 86400)
        assert next(self.call).WhichOneof("msg") == "registered"
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            for msg in self.call:
                if msg.WhichOneof("msg") == "command":
                    self.commands.append(msg.command)
                    result = control_pb2.CommandResult(command_id=msg.command.command_id, ok=True)
                    self.up.put(control_pb2.EdgeMessage(command_result=result))
        except grpc.RpcError:
            pass

    def close(self) -> None:
        self.up.put(None)
        self.call.cancel()


def serve_stack(conn: Any, tmp: Path) -> None:
    """The four services in a child process, so its memory is measured apart from hypothesis' own (which grows
    by itself: ~50 MB per 1000 examples of these strategies). Answers "probe" with (server errors, RSS MB)."""
    logging.disable(logging.WARNING)  # the learner's "control unreachable" retries (by design here)
    cfg = StackConfig(auth=AUTH)
    for section in (cfg.control, cfg.replay, cfg.inference, cfg.learner):
        section.server.port = 0
        section.server.metrics_port = 0
        section.server.grace_s = 0.5
    # the recording edge sends no heartbeats: its lease must outlive the run, like its stream's deadline (the
    # 10,000-example run took 80 min at load 20-85 and control dropped it after the 1 h this was)
    cfg.control.lease_ttl_s = 86400.0 if LONG else 3600.0
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.path = tmp / "replay"
    cfg.replay.control_addr = control.address
    cfg.replay.commit_max_delay_ms = 1.0
    cfg.replay.cache_mb = 16  # replay's decode cache is meant to fill (256 MB by default): keep it out of the RSS
    replay = ReplayService(cfg, start_metrics=False).start()
    inference = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    inference.load_weights(helpers.random_weights(ACTOR, version=1))
    cfg.learner.control_addr = cfg.learner.replay_addr = "127.0.0.1:1"
    cfg.learner.checkpoint_dir = tmp / "ckpt"
    cfg.learner.rpc_timeout_s = 0.5
    learner = LearnerService(cfg, start_metrics=False).start()
    weights = helpers.random_weights(ACTOR, version=1)
    learner.store.publish(1, policy_spec_for(ACTOR), {k: np.asarray(v) for k, v in weights.tensors.items()})
    services = {"control": control, "replay": replay, "inference": inference, "learner": learner}
    conn.send({name: svc.address for name, svc in services.items()})
    while conn.recv() == "probe":
        conn.send((server_errors(), rss_mb()))
    for svc in (learner, inference, replay, control):
        svc.stop()
    conn.send("stopped")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    child = ctx.Process(target=serve_stack, args=(there, tmp_path_factory.mktemp("fuzz")), daemon=True)
    # the services' environment as deployed (Dockerfile, systemd unit, userctl up): glibc reads it at start
    previous = os.environ.get("MALLOC_ARENA_MAX")
    os.environ["MALLOC_ARENA_MAX"] = "2"
    try:
        child.start()
    finally:
        if previous is None:
            os.environ.pop("MALLOC_ARENA_MAX")
        else:
            os.environ["MALLOC_ARENA_MAX"] = previous
    assert here.poll(120), "the services did not start"
    addresses = here.recv()
    channels = {name: make_channel(addr, AUTH) for name, addr in addresses.items()}
    edge = Edge(control_pb2_grpc.ControlStub(channels["control"]))
    here.send("probe")
    errors_before, rss_before = here.recv()
    env = {
        "addresses": addresses,
        "probe": lambda: (here.send("probe"), here.recv())[1],
        "control": control_pb2_grpc.ControlStub(channels["control"]),
        "replay": replay_pb2_grpc.ReplayStub(channels["replay"]),
        "inference": inference_pb2_grpc.InferenceStub(channels["inference"]),
        "learner": learner_pb2_grpc.LearnerStub(channels["learner"]),
        "edge": edge,
        "errors_before": errors_before,
        "rss_before": rss_before,
    }
    yield env
    edge.close()
    for ch in channels.values():
        ch.close()
    here.send("stop")
    assert here.poll(60) and here.recv() == "stopped"
    child.join(timeout=30)


@pytest.fixture(autouse=True)
def report_memory(stack: dict[str, Any], request: pytest.FixtureRequest) -> Iterator[None]:
    """Print the services' resident memory after each test (`make fuzz` shows where growth happens)."""
    _, before = stack["probe"]()
    yield
    _, after = stack["probe"]()
    print(f"\n  {request.node.name}: services' RSS {before:.0f} -> {after:.0f} MB", end="")


def assert_defined(err: grpc.RpcError) -> None:
    assert err.code() not in BAD, f"{err.code()}: {err.details()}"


def unary(method: Any, request: Any) -> None:
    try:
        method(request, timeout=CALL_S)
    except grpc.RpcError as err:
        assert_defined(err)


# --------------------------------------------------------------------------- Control


def edge_messages() -> st.SearchStrategy[control_pb2.EdgeMessage]:
    reg = control_pb2.RegisterRequest(agent_id="fuzz-agent", hostname="h", robots=[robot_spec("fuzz-arm")])
    beat = control_pb2.Heartbeat(seq=1, robots=[control_pb2.RobotStatus(robot_id="fuzz-arm")])
    plugged = control_pb2.RobotsUpdate(robots=[robot_spec("fuzz-arm"), robot_spec("fuzz-arm-2")])  # hot-plug
    return st.one_of(
        any_or_near(control_pb2.EdgeMessage(register=reg)),
        any_or_near(control_pb2.EdgeMessage(heartbeat=beat)),
        any_or_near(control_pb2.EdgeMessage(robots=plugged)),
    )


@FUZZ
@given(msgs=st.lists(edge_messages(), min_size=1, max_size=5))
def test_control_connect(stack: dict[str, Any], msgs: list[control_pb2.EdgeMessage]) -> None:
    before = robot_records(stack)
    registered = False
    try:
        for reply in stack["control"].Connect(iter(msgs), timeout=CALL_S):
            registered |= reply.WhichOneof("msg") == "registered"
    except grpc.RpcError as err:
        assert_defined(err)
    if not registered:  # a refused registration changed nothing
        assert robot_records(stack) == before


def worker_records(stack: dict[str, Any]) -> list[bytes]:
    """What control stored about workers (`online` left out: it follows the clock)."""
    listed = stack["control"].ListWorkers(control_pb2.ListWorkersRequest(include_offline=True), timeout=CALL_S)
    out = []
    for w in listed.workers:
        w.online = False
        out.append(w.SerializeToString())
    return out


def robot_records(stack: dict[str, Any]) -> list[tuple[str, str, str]]:
    robots = stack["control"].ListRobots(control_pb2.ListRobotsRequest(include_offline=True), timeout=CALL_S).robots
    return [(r.spec.robot_id, r.agent_id, r.spec.SerializeToString().hex()) for r in robots]


@FUZZ
@given(req=any_or_near(control_pb2.SendCommandRequest(command=control_pb2.Command(kind=1, robot_id=ROBOT))))
def test_control_send_command(stack: dict[str, Any], req: control_pb2.SendCommandRequest) -> None:
    unary(stack["control"].SendCommand, req)


@FUZZ
@given(
    list_req=any_or_near(control_pb2.ListRobotsRequest()),
    get_req=any_or_near(control_pb2.GetRobotRequest(robot_id=ROBOT)),
)
def test_control_unary(stack: dict[str, Any], list_req: Any, get_req: Any) -> None:
    unary(stack["control"].ListRobots, list_req)
    unary(stack["control"].GetRobot, get_req)


def experiment_states(stack: dict[str, Any]) -> dict[str, int]:
    # the test's own bookkeeping, not a fuzzed call: a loaded machine must not fail it (5 s ran out once)
    listed = stack["control"].ListExperiments(control_pb2.ListExperimentsRequest(), timeout=60).experiments
    return {e.name: e.state for e in listed}


@FUZZ
@given(
    ls=any_or_near(control_pb2.ListExperimentsRequest()),
    get=any_or_near(control_pb2.GetExperimentRequest(name="default")),
    start=any_or_near(control_pb2.StartExperimentRequest(name="default")),
    stop=any_or_near(control_pb2.StopExperimentRequest(name="default")),
)
def test_control_experiments(stack: dict[str, Any], ls: Any, get: Any, start: Any, stop: Any) -> None:
    control = stack["control"]
    try:
        unary(control.ListExperiments, ls)
        unary(control.GetExperiment, get)
        for method, req in ((control.StopExperiment, stop), (control.StartExperiment, start)):
            before = experiment_states(stack)
            try:
                method(req, timeout=CALL_S)
            except grpc.RpcError as err:
                assert err.code() in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND), err.details()
                assert experiment_states(stack) == before  # refused: nothing changed
    finally:  # the other tests' edge keeps its lease
        control.StartExperiment(control_pb2.StartExperimentRequest(name="default"), timeout=CALL_S)


WORKER = control_pb2.WorkerInfo(worker_id="learner@h:1", kind="learner", devices=[control_pb2.DeviceInfo(name="cpu")])


@FUZZ
@given(
    worker=any_or_near(control_pb2.RegisterWorkerRequest(worker=WORKER)),
    workers=any_or_near(control_pb2.ListWorkersRequest()),
    command=any_or_near(control_pb2.GetCommandRequest(command_id="x")),
)
def test_control_workers_and_commands(stack: dict[str, Any], worker: Any, workers: Any, command: Any) -> None:
    before = worker_records(stack)
    try:
        stack["control"].RegisterWorker(worker, timeout=CALL_S)
    except grpc.RpcError as err:
        assert_defined(err)
        assert worker_records(stack) == before  # refused: nothing stored
    unary(stack["control"].ListWorkers, workers)
    unary(stack["control"].GetCommand, command)


# --------------------------------------------------------------------------- Replay


def insert_requests() -> st.SearchStrategy[replay_pb2.InsertRequest]:
    return st.one_of(
        any_or_near(replay_pb2.InsertRequest(seq=1, step=valid_step())),
        near(replay_pb2.InsertRequest(seq=2, step=valid_step(5, last=True))),
    )


@FUZZ
@given(reqs=st.lists(insert_requests(), min_size=1, max_size=6))
def test_replay_insert(stack: dict[str, Any], reqs: list[replay_pb2.InsertRequest]) -> None:
    stub = stack["replay"]
    before = stub.Stats(replay_pb2.StatsRequest(), timeout=CALL_S).steps
    stored = 0
    try:
        for ack in stub.Insert(iter(reqs), timeout=CALL_S):
            stored += ack.stored
    except grpc.RpcError as err:
        assert_defined(err)
    # Only acknowledged steps changed the store: a rejected one left nothing behind.
    assert stub.Stats(replay_pb2.StatsRequest(), timeout=CALL_S).steps == before + stored
    # The same steps through InsertBatch (all in one message, then an empty one): the same rule.
    before, stored = before + stored, 0
    try:
        batches = [replay_pb2.InsertBatchRequest(requests=reqs), replay_pb2.InsertBatchRequest()]
        for ack in stub.InsertBatch(iter(batches), timeout=CALL_S):
            stored += ack.stored
    except grpc.RpcError as err:
        assert_defined(err)
    assert stub.Stats(replay_pb2.StatsRequest(), timeout=CALL_S).steps == before + stored


@FUZZ
@given(
    sample=any_or_near(replay_pb2.SampleRequest(batch_size=4)),
    stats=any_or_near(replay_pb2.StatsRequest()),
    shm=any_or_near(replay_pb2.SharedMemoryRequest(host_id=host_id())),
)
def test_replay_unary(stack: dict[str, Any], sample: Any, stats: Any, shm: Any) -> None:
    unary(stack["replay"].Sample, sample)
    unary(stack["replay"].Stats, stats)
    unary(stack["replay"].OpenSharedMemory, shm)


# --------------------------------------------------------------------------- Inference


@FUZZ
@given(
    act=any_or_near(
        inference_pb2.ActRequest(robot_id=ROBOT, observation=wire.to_tensor_map({"state": np.zeros(6, np.float32)}))
    ),
    status=any_or_near(inference_pb2.InferenceStatusRequest()),
)
def test_inference(stack: dict[str, Any], act: Any, status: Any) -> None:
    unary(stack["inference"].Act, act)
    unary(stack["inference"].Status, status)
    try:  # the same request inside ActBatch: a defined status for the call, and for each robot in it
        batch = inference_pb2.ActBatchRequest(requests=[act, act])
        results = stack["inference"].ActBatch(batch, timeout=CALL_S).results
        assert len(results) == 2 and all(r.code != grpc.StatusCode.UNKNOWN.value[0] for r in results)
    except grpc.RpcError as err:
        assert_defined(err)


# --------------------------------------------------------------------------- Learner


@FUZZ
@given(
    sub=any_or_near(learner_pb2.SubscribeWeightsRequest(client_id="fuzz")),
    status=any_or_near(learner_pb2.LearnerStatusRequest()),
)
def test_learner(stack: dict[str, Any], sub: Any, status: Any) -> None:
    unary(stack["learner"].GetStatus, status)
    # A subscriber that has the newest version waits for the next: the deadline ends it.
    call = stack["learner"].SubscribeWeights(sub, timeout=0.1)
    got, want = 0, None
    try:
        for msg in call:
            if msg.WhichOneof("msg") == "header":
                want = msg.header.encoded_bytes
            else:
                got += len(msg.chunk.data)
            if want is not None and got >= want:
                call.cancel()
                break
    except grpc.RpcError as err:
        assert_defined(err)


# --------------------------------------------------------------------------- afterwards (runs last in file order)


def test_zz_everything_still_up_and_nothing_invalid_forwarded(stack: dict[str, Any]) -> None:
    for name, addr in stack["addresses"].items():
        assert check_health(addr, AUTH), f"{name} stopped serving"
    errors, rss = stack["probe"]()
    assert errors == stack["errors_before"], "a handler ended with UNKNOWN or INTERNAL"
    edge: Edge = stack["edge"]
    assert edge.thread.is_alive(), "the edge stream ended"
    for cmd in edge.commands:
        assert cmd.kind in (1, 2, 3) and cmd.robot_id in ("", ROBOT), cmd
    # The edge's robot is still online: no input took it off the fleet.
    info = stack["control"].GetRobot(control_pb2.GetRobotRequest(robot_id=ROBOT), timeout=CALL_S)
    assert info.online
    grown = rss - stack["rss_before"]
    print(
        f"fuzz: {EXAMPLES} examples per test; services' resident memory {stack['rss_before']:.0f} MB, +{grown:.0f} MB"
    )
    if LONG:
        assert grown < 256, f"the services' resident memory grew {grown:.0f} MB over the run"
