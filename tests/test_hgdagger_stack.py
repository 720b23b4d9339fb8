"""HG-DAgger through real processes (configs/hgdagger.yaml at small sizes): the scripted expert on the edge
takes over, its steps reach replay flagged, the learner trains flow_bc on them, and the policy the inference
service serves changes."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from pathlib import Path

import grpc
import numpy as np
import pytest

from tests import helpers
from user import wire
from user.config import load_config
from user.rpc import make_channel
from user.up import Stack
from user.v1 import (
    control_pb2,
    control_pb2_grpc,
    inference_pb2,
    inference_pb2_grpc,
    learner_pb2,
    learner_pb2_grpc,
    replay_pb2,
    replay_pb2_grpc,
)

wait_for = functools.partial(helpers.wait_for, limit_s=180.0, poll_s=0.25)  # whole processes on 2 busy cores
CONFIG = str(Path(__file__).resolve().parents[1] / "configs" / "hgdagger.yaml")
# Interventions are the only table the learner samples: any update it makes was trained on them.
PARAMS = {"batch_size": 16, "lr": 0.003, "horizon": 4, "hidden": 32, "flow_steps": 2, "tables": {"interventions": 1.0}}
OVERRIDES = [
    "up.edge_agents=1",
    "edge.mode=fast",
    "learner.min_transitions=8",
    "learner.publish_every=10",
    "log_json=true",
    "experiments=" + json.dumps([{"name": "lang", "robots": {"kinds": ["lang_reach_arm"]},
                                  "algorithm": {"kind": "flow_bc", "params": PARAMS}}]),
]  # fmt: skip


@pytest.mark.slow
def test_an_intervention_from_the_edge_changes_the_served_policy(tmp_path: Path) -> None:
    from edge_agent.robot import make_robot

    cfg = load_config(CONFIG, OVERRIDES)
    stack = Stack(cfg, CONFIG, OVERRIDES, tmp_path)
    probe_robot = make_robot("lang_reach_arm", "probe", cfg.edge.robots[0].params, seed=3)
    probe = wire.to_tensor_map(probe_robot.reset(seed=3).features)
    probe_robot.close()
    try:
        stack.start_services()
        auth = stack.auth
        control = control_pb2_grpc.ControlStub(make_channel(stack.child("control").grpc_addr, auth))
        learner = learner_pb2_grpc.LearnerStub(make_channel(stack.child("learner").grpc_addr, auth))
        replay = replay_pb2_grpc.ReplayStub(make_channel(stack.child("replay").grpc_addr, auth))
        inference = inference_pb2_grpc.InferenceStub(make_channel(stack.child("inference").grpc_addr, auth))

        def experiment() -> learner_pb2.ExperimentStatus:
            status = learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10)
            return next(e for e in status.experiments if e.name == "lang")

        def served() -> tuple[int, np.ndarray]:
            req = inference_pb2.ActRequest(robot_id="probe", observation=probe, deterministic=True)
            resp = inference.Act(req, timeout=30)
            return int(resp.policy_version), wire.from_tensor(resp.action)

        # The robot holds while the experiment is stopped: no intervention yet, nothing to train on.
        control.StopExperiment(control_pb2.StopExperimentRequest(name="lang"), timeout=10)
        stack.wait_ready(stack.spawn_edge("edge-0", [stack._edge_robots()[0]], seed=0))
        wait_for(lambda: experiment().weight_version >= 1, "the initial policy published")
        version0, action0 = wait_for(lambda: _try(served), "the initial policy served")
        assert experiment().updates == 0 and action0.shape == (4, 3)

        control.StartExperiment(control_pb2.StartExperimentRequest(name="lang"), timeout=10)
        wait_for(lambda: experiment().updates >= 30, "updates on interventions")
        trained = experiment()
        assert trained.sample_errors == 0 and trained.scalars["human_rows"] == PARAMS["batch_size"]
        _, action1 = wait_for(
            lambda: (v := _try(served)) and v[0] > version0 and v, "a newer version served by inference"
        )
        assert not np.allclose(action1, action0)  # the served policy changed

        # What it trained on: the expert's steps, flagged in replay's interventions table, as the edge counted.
        stats = replay.Stats(replay_pb2.StatsRequest(), timeout=10)
        assert stats.tables["interventions"].transitions > 0
        batch = replay.Sample(
            replay_pb2.SampleRequest(batch_size=32, tables={"interventions": 1.0}, robot_ids=["arm-0"]), timeout=10
        ).batch
        assert wire.from_tensor(batch.intervention).all()
        # The edge's counters reach control with its next heartbeat (later than the steps, on a busy machine).

        def counted() -> int:
            robots = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=10).robots
            return sum(r.status.intervention_steps for r in robots)

        assert wait_for(counted, "the edge's intervention count in control") > 0
    finally:
        codes = stack.stop()
    assert codes == {name: 0 for name in codes}, f"unclean exits: {codes}"


def _try(served: Callable[[], tuple[int, np.ndarray]]) -> tuple[int, np.ndarray] | None:
    """served(), or None while inference has no policy yet."""
    try:
        return served()
    except grpc.RpcError:
        return None
