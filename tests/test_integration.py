"""The whole stack as real processes: control, replay, learner, inference and three edge agents: two sim
arms (one acting through the inference service, one through its weight-streamed local copy) in the reach
experiment and a gym-hil Panda in the pick experiment, two embodiments training at once."""

from __future__ import annotations

import functools
import json
import os
import urllib.request
from pathlib import Path

import grpc
import numpy as np
import pytest

from tests import helpers
from user import wire
from user.config import load_config
from user.rpc import check_health, make_channel
from user.up import Episode, Stack, write_report
from user.v1 import (
    control_pb2,
    control_pb2_grpc,
    learner_pb2,
    learner_pb2_grpc,
    replay_pb2,
    replay_pb2_grpc,
)

# Whole processes on 2 busy cores: a generous liveness bound, polled gently.
wait_for = functools.partial(helpers.wait_for, limit_s=120.0, poll_s=0.25)
CONFIG = str(Path(__file__).resolve().parents[1] / "configs" / "demo.yaml")
OVERRIDES = [
    "edge.mode=fast",
    "learner.min_transitions=200",
    "learner.publish_every=20",
    "learner.checkpoint_every=200",
    "up.edge_agents=2",
    "log_json=true",
]


@pytest.mark.slow
def test_stack_learns_through_all_services(tmp_path: Path) -> None:
    cfg = load_config(CONFIG, OVERRIDES)
    stack = Stack(
        cfg,
        CONFIG,
        OVERRIDES,
        tmp_path,
        per_edge_overrides={0: ["edge.policy_source=remote"], 1: ["edge.policy_source=local"]},
    )
    try:
        stack.start()
        auth = stack.auth
        control = control_pb2_grpc.ControlStub(make_channel(stack.child("control").grpc_addr, auth))
        learner = learner_pb2_grpc.LearnerStub(make_channel(stack.child("learner").grpc_addr, auth))
        replay = replay_pb2_grpc.ReplayStub(make_channel(stack.child("replay").grpc_addr, auth))

        def online_robots():
            try:
                robots = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
            except grpc.RpcError as err:  # the first connection can time out on 2 saturated cores: poll again
                if err.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                    return None
                raise
            return [r for r in robots if r.online] if len(robots) == 3 else None

        robots = wait_for(online_robots, "three robots online")
        assert {r.spec.robot_id: r.experiment for r in robots} == {
            "arm-0": "reach",
            "arm-1": "reach",
            "panda-0": "pick",
        }

        # Both experiments train and publish, each sampling only its own robots (no layout errors).
        def both_published():
            status = learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
            exps = {e.name: e for e in status.experiments}
            return exps if all(e.weight_version >= 4 and e.updates > 0 for e in exps.values()) else None

        exps = wait_for(both_published, "both experiments to publish weight version 4")
        assert set(exps) == {"reach", "pick"}
        assert all(e.sample_errors == 0 and e.state == "training" for e in exps.values())
        assert sorted(exps["reach"].robot_ids) == ["arm-0", "arm-1"] and list(exps["pick"].robot_ids) == ["panda-0"]
        assert "alpha" in exps["reach"].scalars and "critic_loss" in exps["pick"].scalars

        def edge_versions():
            infos = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
            versions = {r.spec.robot_id: r.status.policy_version for r in infos}
            return versions if len(versions) == 3 and min(versions.values()) >= 3 else None

        versions = wait_for(edge_versions, "every edge (remote and local policy, both embodiments) at version >= 3")
        assert min(versions.values()) >= 3

        # Every weight stream shows in GetStatus (the console's sync column): inference and the local-policy
        # edge, with what they applied; on this host they prove the shared /dev/shm and get versions there.
        subs = list(learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5).subscriber_status)
        inference_subs = [s for s in subs if s.client_id.startswith("inference-")]
        assert inference_subs and len(subs) > len(inference_subs), [s.client_id for s in subs]
        assert all(s.applied_version >= 1 and s.versions_sent >= 1 for s in subs)
        if os.access("/dev/shm", os.W_OK):
            assert all(s.encoding == learner_pb2.WEIGHT_ENCODING_FP32_SHM for s in inference_subs)

        # Steps reached replay, stamped with the versions that produced them.
        stats = replay.Stats(replay_pb2.StatsRequest(), timeout=5)
        assert set(stats.steps_per_robot) == {"arm-0", "arm-1", "panda-0"}
        assert stats.steps > 200
        batch = replay.Sample(replay_pb2.SampleRequest(batch_size=256, robot_ids=["arm-0", "arm-1"]), timeout=5).batch
        versions_in_batch = wire.from_tensor(batch.policy_version)
        assert versions_in_batch.max() >= 2
        assert wire.from_tensor(batch.action).shape == (256, 3)
        assert np.isfinite(wire.from_tensor(batch.observation.tensors["state"])).all()

        # Every process serves /metrics with its own metrics and answers health checks.
        expected = {
            "control": "user_control_",
            "replay": "user_replay_",
            "learner": "user_learner_",
            "inference": "user_inference_",
            "edge-0": "user_edge_",
            "edge-1": "user_edge_",
            "edge-2": "user_edge_",
        }
        for name, prefix in expected.items():
            body = urllib.request.urlopen(stack.child(name).metrics_url, timeout=5).read().decode()
            assert prefix in body, f"{name} /metrics lacks {prefix}*"
            if "grpc_port" in stack.child(name).info:
                assert check_health(stack.child(name).grpc_addr, auth)

        # The token is enforced on the running stack.
        no_token = cfg.auth.model_copy(update={"enabled": False})
        anonymous = control_pb2_grpc.ControlStub(make_channel(stack.child("control").grpc_addr, no_token))
        with pytest.raises(grpc.RpcError) as err:
            anonymous.ListRobots(control_pb2.ListRobotsRequest(), timeout=5)
        assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    finally:
        codes = stack.stop()
    assert codes == {name: 0 for name in codes}, f"unclean exits: {codes}"
    # The learner wrote its final checkpoint on SIGTERM.
    assert (tmp_path / "checkpoints" / "reach" / "latest").exists()
    assert (tmp_path / "checkpoints" / "pick" / "latest").exists()
    # Each edge spooled its steps on disk and every one was acknowledged before its clean exit.
    from edge_agent.spool import LmdbSpool

    spools = sorted(p for p in (tmp_path / "spool").iterdir() if p.is_dir())
    assert spools, "no edge spool was written"
    for path in spools:
        spool = LmdbSpool(path, 1 << 20)
        assert spool.count == 0 and spool.last_seq > 0, path  # steps went through it, none left
        spool.close()
    # Every log line is structured JSON.
    for log_file in (tmp_path / "logs").glob("*.log"):
        for line in log_file.read_text().splitlines()[:50]:
            if line.startswith("{"):
                json.loads(line)


def test_report_files(tmp_path: Path) -> None:
    episodes = [Episode("arm-0", f"e{i}", float(i), i > 10, -5.0 + i, 50, i) for i in range(30)]
    write_report(tmp_path, episodes, {"name": "t", "target_success": 0.9, "time_to_target_s": 29.0}, window=20)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert len(doc["episodes"]) == 30
    assert doc["rolling_success"][-1] == pytest.approx(19 / 20)
    assert (tmp_path / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
