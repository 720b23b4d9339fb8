"""SmolVLA HG-DAgger through real processes (configs/smolvla_hgdagger.yaml at small sizes): a tiny SmolVLA
checkpoint folder built here (offline), in place of the config's placeholder, is published as a `smolvla` policy
the inference service serves in chunks; the scripted expert on the edge takes over, its steps reach replay
flagged, the learner fine-tunes SmolVLA on them, and the policy inference serves changes."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from pathlib import Path

import grpc
import numpy as np
import pytest
import yaml

pytest.importorskip("lerobot.policies.smolvla.modeling_smolvla")

from tests import helpers
from user import wire
from user.config import load_config
from user.rpc import make_channel
from user.text import INSTRUCTION_KEY, decode_instruction
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
CONFIG = str(Path(__file__).resolve().parents[1] / "configs" / "smolvla_hgdagger.yaml")
H, SIZE = 4, 32  # SmolVLA's chunk; camera pixels (the robot renders what the checkpoint reads: no resize)


def make_checkpoint(root: Path, state_dim: int, action_dim: int) -> Path:
    """A tiny SmolVLA checkpoint folder (random weights) over a tiny backbone whose words are the instructions'."""
    import torch
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from edge_agent.robots.lang_reach import COLOURS, instruction_for
    from user.policies.smolvla import make_tiny_backbone, save_checkpoint, tiny_smolvla_config

    words = sorted({w for c in COLOURS for w in instruction_for(c).split()})
    backbone = make_tiny_backbone(root / "backbone", words, image_size=SIZE)
    torch.manual_seed(0)
    config = tiny_smolvla_config(backbone, ["front"], state_dim, action_dim, horizon=H, image_size=SIZE)
    return save_checkpoint(SmolVLAPolicy(config), root / "checkpoint")


@pytest.mark.slow
def test_an_intervention_from_the_edge_fine_tunes_the_served_smolvla(tmp_path: Path) -> None:
    from edge_agent.robot import make_robot
    from edge_agent.robots.lang_reach import COLOURS, instruction_for

    # The example config's robot (camera on: SmolVLA needs one, the expert intervening) at a small camera size.
    shipped = yaml.safe_load(Path(CONFIG).read_text())
    robot = shipped["edge"]["robots"][0]
    robot["params"]["camera_size"] = SIZE
    probe_robot = make_robot(robot["kind"], "probe", robot["params"], seed=3)
    spec = probe_robot.spec
    state_dim = sum(int(np.prod(f.shape)) for f in spec.observation if f.name == "state")
    assert [c.name for c in spec.cameras] == ["front"] and state_dim > 0
    probe = wire.to_tensor_map(probe_robot.reset(seed=3).features)  # camera, state and instruction bytes
    probe_robot.close()
    action_dim = int(spec.action.shape[0])
    checkpoint = make_checkpoint(tmp_path / "model", state_dim, action_dim)

    # Its experiment with the tiny checkpoint in place of the placeholder, small batches and a high lr;
    # interventions are the only table the learner samples: any update it makes was trained on them.
    experiment_cfg = shipped["experiments"][0]
    assert experiment_cfg["algorithm"]["kind"] == "smolvla_bc"
    params = experiment_cfg["algorithm"]["params"]
    params.update(checkpoint=str(checkpoint), batch_size=8, lr=0.003, tables={"interventions": 1.0})
    overrides = [
        "up.edge_agents=1",
        "edge.mode=fast",
        "learner.device=cpu",
        "inference.device=cpu",
        "learner.min_transitions=8",
        "learner.publish_every=10",
        "edge.robots=" + json.dumps([robot]),
        "experiments=" + json.dumps([experiment_cfg]),
    ]
    cfg = load_config(CONFIG, overrides)
    stack = Stack(cfg, CONFIG, overrides, tmp_path)
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

        def served(instruction: str = "") -> tuple[int, np.ndarray]:
            req = inference_pb2.ActRequest(
                robot_id="probe", observation=probe, deterministic=True, instruction=instruction
            )
            resp = inference.Act(req, timeout=30)
            return int(resp.policy_version), wire.from_tensor(resp.action)

        # The robot holds while the experiment is stopped: no intervention yet, nothing to train on.
        control.StopExperiment(control_pb2.StopExperimentRequest(name="lang"), timeout=10)
        stack.wait_ready(stack.spawn_edge("edge-0", [stack._edge_robots()[0]], seed=0))
        wait_for(lambda: experiment().weight_version >= 1, "the initial policy published")
        version0, action0 = wait_for(lambda: _try(served), "the initial policy served")
        assert experiment().updates == 0 and action0.shape == (H, action_dim)  # a SmolVLA chunk
        assert np.abs(action0).max() <= 1.0
        assert np.array_equal(_try(served)[1], action0)  # deterministic: the flow starts from zeros
        # The instruction reaches SmolVLA's tokenizer: another colour asked for (the request's text before the
        # observation's bytes), another chunk.
        asked = decode_instruction(wire.from_tensor(probe.tensors[INSTRUCTION_KEY]))
        other = next(instruction_for(c) for c in COLOURS if instruction_for(c) != asked)
        assert not np.allclose(served(other)[1], action0)

        control.StartExperiment(control_pb2.StartExperimentRequest(name="lang"), timeout=10)
        wait_for(lambda: experiment().updates >= 20, "updates on interventions")
        trained = experiment()
        assert trained.sample_errors == 0 and trained.scalars["human_rows"] == params["batch_size"]
        assert np.isfinite(trained.scalars["bc_loss"])
        _, action1 = wait_for(
            lambda: (v := _try(served)) and v[0] > version0 and v, "a newer version served by inference"
        )
        assert action1.shape == (H, action_dim) and not np.allclose(action1, action0)  # the served policy changed

        # What it trained on: the expert's steps, flagged in replay's interventions table, as the edge counted.
        stats = replay.Stats(replay_pb2.StatsRequest(), timeout=10)
        assert stats.tables["interventions"].transitions > 0
        request = replay_pb2.SampleRequest(
            batch_size=8, tables={"interventions": 1.0}, robot_ids=["arm-0"], action_horizon=H
        )
        batch = replay.Sample(request, timeout=10).batch
        assert wire.from_tensor(batch.intervention).all()
        # ... with what SmolVLA reads: the camera frame, the state, the instruction, and chunks of H expert actions.
        rows = {k: wire.from_tensor(v) for k, v in batch.observation.tensors.items()}
        assert rows["camera.front"].shape == (8, SIZE, SIZE, 3) and rows["state"].shape == (8, state_dim)
        assert {decode_instruction(r) for r in rows[INSTRUCTION_KEY]} <= {instruction_for(c) for c in COLOURS}
        assert wire.from_tensor(batch.action_chunk).shape == (8, H, action_dim)

        # The edge's counters reach control with its next heartbeat (later than the steps, on a busy machine):
        # the expert's steps, and the robot acting on SmolVLA chunks from inference in between.
        def counted() -> tuple[int, int] | None:
            robots = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=10).robots
            steps, version = (
                sum(r.status.intervention_steps for r in robots),
                max(r.status.policy_version for r in robots),
            )
            return (steps, version) if steps and version else None

        wait_for(counted, "the edge's intervention count and served policy version in control")
    finally:
        codes = stack.stop()
    assert codes == {name: 0 for name in codes}, f"unclean exits: {codes}"


def _try(served: Callable[[], tuple[int, np.ndarray]]) -> tuple[int, np.ndarray] | None:
    """served(), or None while inference has no policy yet."""
    try:
        return served()
    except grpc.RpcError:
        return None
