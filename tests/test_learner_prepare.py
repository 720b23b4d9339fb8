"""The learner's own preparation before version 1: state statistics from a replay table (experiments[].normalize)
and pretraining on a pre-filled table (experiments[].pretrain), with real services: control, replay (demos
through the real Insert RPC), the learner service in-process, and for flow_bc also inference and an edge agent
whose robot holds until the pretrained version exists."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
import torch

from cloud_learner.learner import build_algorithm
from cloud_learner.prepare import state_stats
from cloud_learner.server import LearnerService
from edge_agent.agent import EdgeAgent
from edge_agent.robots.sim_arm import SimReachArm
from edge_agent.teleoperators.scripted_expert import ReachExpert
from services.control.server import ControlService
from services.inference.server import InferenceService
from services.replay.server import ReplayService
from tests import helpers
from tests.test_control import Edge, register_msg
from user import wire
from user.config import ConfigError, ExperimentConfig, RobotConfig, StackConfig
from user.experiments import layout_for
from user.policy import build_policy
from user.rpc import make_channel
from user.v1 import (
    control_pb2,
    control_pb2_grpc,
    inference_pb2,
    inference_pb2_grpc,
    learner_pb2,
    learner_pb2_grpc,
    replay_pb2,
    replay_pb2_grpc,
    step_pb2,
)
from user.worker import report_worker

wait_for = functools.partial(helpers.wait_for, limit_s=180.0, poll_s=0.1)
AUTH = {"token": "test-token"}
EPISODE = 20  # steps per demo episode


# --------------------------------------------------------------------------- demos


def record_demos(episodes: int, robot_id: str = "arm-0") -> tuple[list[step_pb2.Step], np.ndarray, np.ndarray]:
    """The scripted reach expert drives an in-process sim arm: Steps for replay, and (states, actions)."""
    robot = SimReachArm(SimReachArm.Params(max_episode_steps=EPISODE), robot_id, seed=7)
    expert = ReachExpert(robot.spec)
    steps, states, actions = [], [], []
    for ep in range(episodes):
        obs = robot.reset(seed=100 + ep)
        for t in range(EPISODE):
            action = np.asarray(robot.act(expert.action(obs)), np.float32)
            nxt = robot.observe()
            last = t == EPISODE - 1
            step = step_pb2.Step(
                robot_id=robot_id,
                episode_id=f"demo-{ep}",
                step_index=t,
                observation=wire.to_tensor_map(obs.features),
                action=wire.to_tensor(action),
                reward=float(nxt.reward),
                truncated=last,
            )
            if last:
                step.final_observation.CopyFrom(wire.to_tensor_map(nxt.features))
            steps.append(step)
            states.append(obs.features["state"].copy())
            actions.append(action)
            obs = nxt
    robot.close()
    return steps, np.stack(states), np.stack(actions)


def insert_demos(replay_addr: str, cfg: StackConfig, steps: list[step_pb2.Step]) -> None:
    stub = replay_pb2_grpc.ReplayStub(make_channel(replay_addr, cfg.auth))
    reqs = [replay_pb2.InsertRequest(seq=i, step=s, table="demos") for i, s in enumerate(steps)]
    acked = [seq for ack in stub.Insert(iter(reqs), timeout=30) for seq in ack.seqs]
    assert acked == list(range(len(steps)))


def arm_spec() -> Any:
    return SimReachArm(SimReachArm.Params(max_episode_steps=EPISODE), "arm-0", seed=7).spec


def action_error(spec: learner_pb2.PolicySpec, tensors: dict, states: np.ndarray, actions: np.ndarray) -> float:
    """Mean |deterministic action - demonstrated action| of a policy built as inference and edges build it."""
    out = build_policy(spec, tensors, 1).act({"state": states}, deterministic=True)
    return float(np.abs(np.asarray(out).reshape(len(states), -1, actions.shape[1])[:, 0] - actions).mean())


# --------------------------------------------------------------------------- services


def stack_cfg(tmp_path: Path, experiment: dict[str, Any]) -> StackConfig:
    cfg = StackConfig.model_validate({"auth": AUTH, "experiments": [experiment]})
    for section in (cfg.control, cfg.replay, cfg.inference, cfg.learner):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.2
    cfg.replay.path, cfg.replay.map_size_mb, cfg.replay.commit_max_delay_ms = tmp_path / "replay", 64, 5.0
    cfg.edge.spool_dir = tmp_path / "spool"  # not the repo's runs/default/spool: tests share no outbox
    lc = cfg.learner
    lc.checkpoint_dir, lc.rpc_timeout_s = tmp_path / "ckpt", 5.0
    # No online training here: the only version is the pretrained one, so it can be inspected.
    lc.min_transitions, lc.publish_every, lc.checkpoint_every = 10**9, 10**9, 50
    return cfg


@pytest.fixture
def base(tmp_path: Path) -> Iterator[Callable[[dict[str, Any]], tuple[StackConfig, ControlService, ReplayService]]]:
    """start(experiment): control (knowing the experiment) and replay, wired into the config."""
    started: list[Any] = []

    def start(experiment: dict[str, Any]) -> tuple[StackConfig, ControlService, ReplayService]:
        cfg = stack_cfg(tmp_path, experiment)
        control = ControlService(cfg, start_metrics=False).start()
        started.append(control)
        cfg.replay.control_addr = cfg.learner.control_addr = cfg.inference.control_addr = control.address
        replay = ReplayService(cfg, start_metrics=False).start()
        started.append(replay)
        cfg.learner.replay_addr = replay.address
        return cfg, control, replay

    yield start
    for service in reversed(started):
        service.stop()


def status_of(cfg: StackConfig, learner: LearnerService) -> learner_pb2.ExperimentStatus:
    """The experiment's status; an empty one when the call fails (a loaded machine: wait_for asks again)."""
    stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))
    try:
        (exp,) = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10).experiments
    except grpc.RpcError:
        return learner_pb2.ExperimentStatus()
    return exp


# --------------------------------------------------------------------------- flow_bc: the whole path


FLOW = {
    "name": "lang",
    "algorithm": {
        "kind": "flow_bc",
        "params": {"batch_size": 64, "hidden": 64, "lr": 3e-3, "tables": {"demos": 0.5, "interventions": 0.5}},
    },
    "pretrain": {"table": "demos", "steps": 300, "min_size": 200},
    "normalize": {"from_table": "demos", "min_steps": 200, "samples": 4096},
}


def test_flow_bc_pretrains_on_demos_before_version_1_and_ships_its_statistics(base) -> None:
    cfg, control, replay = base(FLOW)
    learner = LearnerService(cfg, start_metrics=False).start()
    # As `userctl learner` does: the learner reports to control, with the experiments it still prepares.
    reporter = report_worker(
        learner, "learner", control.address, cfg.auth, "cpu", lambda: ["lang"], learner.learner.preparing
    )
    reporter.__enter__()
    control_stub = control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth))

    def preparing() -> list[str] | None:
        try:
            workers = control_stub.ListWorkers(control_pb2.ListWorkersRequest(), timeout=10).workers
        except grpc.RpcError:  # a loaded machine: ask again
            return None
        return [name for w in workers for name in w.preparing]

    assert wait_for(lambda: preparing() == ["lang"], "control to know the learner prepares 'lang'")
    cfg.inference.learner_addr = learner.address
    inference = InferenceService(cfg, start_metrics=False).start()
    edge = cfg.edge
    edge.control_addr, edge.replay_addr, edge.inference_addr = control.address, replay.address, inference.address
    edge.mode, edge.metrics_port, edge.spool_dir = "fast", 0, None
    edge.robots = [RobotConfig(id="arm-0", kind="sim_reach_arm", params={"max_episode_steps": EPISODE})]
    agent = EdgeAgent(cfg)
    agent.start()
    try:
        # The robot registered; the learner waits for demos; no version exists, so the robot holds.
        waiting = wait_for(lambda: (s := status_of(cfg, learner)).state == "normalizing" and s, "waiting for demos")
        assert waiting.weight_version == 0 and waiting.scalars["normalize_table_transitions"] == 0
        loop = agent.loops["arm-0"]
        # Control holds the robot while the learner prepares: it neither acts nor records a step.
        robot = wait_for(lambda: (r := robot_info(control_stub)) is not None and r.lease_reason and r, "a lease")
        assert "prepares its first policy" in robot.lease_reason and loop.held_by_lease
        assert loop.env_steps == 0 and loop.policy_version == 0
        steps, states, actions = record_demos(episodes=20)
        insert_demos(replay.address, cfg, steps)

        published = wait_for(lambda: (s := status_of(cfg, learner)).weight_version >= 1 and s, "version 1")
        assert published.updates == 300 and published.scalars["pretrain_updates"] == 300
        assert published.scalars["pretrain_steps"] == 300 and published.sample_errors == 0
        packed = learner.store.latest("lang")
        assert packed.version == published.weight_version and packed.header.learner_updates == 300  # after N

        # The statistics are the demos' (4096 uniform samples of 400 transitions), in the spec and the checkpoint.
        config = json.loads(packed.header.policy.config_json)
        true_mean, true_std = states.mean(0), np.maximum(states.std(0), 1e-2)
        np.testing.assert_allclose(config["state_mean"], true_mean, atol=0.1 * true_std.max())
        np.testing.assert_allclose(config["state_std"], true_std, rtol=0.15, atol=0.01)
        run = learner.learner.runs["lang"]
        assert run.normalization["state_mean"]["state"] == config["state_mean"]
        assert run.normalization["state_std"]["state"] == config["state_std"]

        # Improved on the demos: lower action error than the same algorithm at its (seeded) initialization.
        spec_, tensors = run.algo.policy()
        layout = layout_for(ExperimentConfig.model_validate(FLOW), [arm_spec()])
        init = build_algorithm(0, ExperimentConfig.model_validate(FLOW), layout, "cpu", run.normalization)
        before, after = action_error(*init.policy(), states, actions), action_error(spec_, tensors, states, actions)
        print(f"action error vs demos: init {before:.4f}, pretrained {after:.4f}")
        assert after < 0.6 * before, (before, after)

        # Inference serves the pretrained version and normalizes as the learner does: same actions.
        infer = inference_pb2_grpc.InferenceStub(make_channel(inference.address, cfg.auth))

        def act(state: np.ndarray) -> inference_pb2.ActResponse | None:
            req = inference_pb2.ActRequest(
                robot_id="arm-0", observation=wire.to_tensor_map({"state": state}), deterministic=True
            )
            try:
                return infer.Act(req, timeout=5)
            except Exception:
                return None

        answer = wait_for(lambda: (a := act(states[0])) is not None and a.policy_version >= 1 and a, "inference v1")
        local = build_policy(spec_, tensors, 1).act({"state": states[:1]}, deterministic=True)
        np.testing.assert_allclose(
            wire.from_tensor(answer.action).reshape(-1), np.asarray(local).reshape(-1), atol=1e-5
        )

        # The robot held (no policy) until version 1, then acts with it.
        # Then control releases it and it acts with the pretrained version.
        wait_for(lambda: loop.policy_version >= 1, "the robot to act with the pretrained version")
        assert preparing() == [] and not loop.held_by_lease and robot_info(control_stub).lease == "lang"
    finally:
        agent.stop()
        inference.stop()
        reporter.__exit__(None, None, None)
        learner.stop()
    ckpt = torch.load(latest_ckpt(cfg, "lang"), weights_only=True)
    assert ckpt["pretrain_updates"] == 300 and ckpt["normalization"]["state_mean"]["state"] == config["state_mean"]


def robot_info(stub: control_pb2_grpc.ControlStub) -> control_pb2.RobotInfo | None:
    try:
        robots = stub.ListRobots(control_pb2.ListRobotsRequest(), timeout=10).robots
    except grpc.RpcError:  # a loaded machine: wait_for asks again
        return None
    return robots[0] if robots else None


def latest_ckpt(cfg: StackConfig, experiment: str) -> Path:
    folder = Path(cfg.learner.checkpoint_dir) / experiment
    return folder / (folder / "latest").read_text().strip()


# --------------------------------------------------------------------------- SAC+BC (RLPD): resume, never redo


RLPD = {
    "name": "rl",
    "algorithm": {
        "kind": "rlpd",
        "params": {
            "batch_size": 64,
            "utd": 1,
            "num_critics": 2,
            "hidden": [64, 64],
            "bc_weight": 5.0,
            "actor_lr": 3e-3,
        },
    },
    "pretrain": {"table": "demos", "steps": 400, "min_size": 100},
    "normalize": {"from_table": "demos", "min_steps": 100, "samples": 2048},
}


def test_rlpd_pretraining_resumes_after_a_restart_and_is_not_redone(base) -> None:
    cfg, control, replay = base(RLPD)
    robots = Edge(control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth)), register_msg("e", arm_spec()))
    try:
        assert robots.next_message().WhichOneof("msg") == "registered"
        steps, states, actions = record_demos(episodes=10)
        insert_demos(replay.address, cfg, steps)

        # First learner: stopped mid-pretraining (after its first periodic checkpoint at 50 updates).
        first = LearnerService(cfg, start_metrics=False).start()
        part = wait_for(lambda: (s := status_of(cfg, first)).updates >= 60 and s, "60 pretraining updates")
        assert part.state == "pretraining" and part.weight_version == 0
        first.stop()
        done_before = torch.load(latest_ckpt(cfg, "rl"), weights_only=True)["pretrain_updates"]
        assert 60 <= done_before < 400

        # Second learner: resumes the count and the statistics; version 1 comes after 400 updates in all.
        second = LearnerService(cfg, start_metrics=False).start()
        resumed = second.learner
        published = wait_for(lambda: (s := status_of(cfg, second)).weight_version >= 1 and s, "pretrained version")
        assert published.updates == 400 and second.store.latest("rl").header.learner_updates == 400
        run = resumed.runs["rl"]
        assert (
            run.normalization["state_mean"]
            == torch.load(latest_ckpt(cfg, "rl"), weights_only=True)["normalization"]["state_mean"]
        )
        spec_, tensors = run.algo.policy()
        assert "state_mean" in json.loads(spec_.config_json)  # the mlp policy carries the statistics
        layout = layout_for(ExperimentConfig.model_validate(RLPD), [arm_spec()])
        init = build_algorithm(0, ExperimentConfig.model_validate(RLPD), layout, "cpu", run.normalization)
        before, after = action_error(*init.policy(), states, actions), action_error(spec_, tensors, states, actions)
        print(f"action error vs demos: init {before:.4f}, pretrained {after:.4f}")
        assert after < 0.6 * before, (before, after)
        second.stop()

        # Third learner: pretraining is complete in the checkpoint; it publishes at once, no update redone.
        third = LearnerService(cfg, start_metrics=False).start()
        again = wait_for(lambda: (s := status_of(cfg, third)).weight_version > published.weight_version and s, "v")
        assert again.updates == 400 and third.learner.runs["rl"].pretrain_updates == 400
        third.stop()
    finally:
        robots.close()


# --------------------------------------------------------------------------- config and units


def test_bad_prepare_configs_fail_at_start_naming_the_field(tmp_path: Path) -> None:
    from tests.test_learner import service_cfg

    with pytest.raises(ValueError, match=r"normalize\.from_table"):
        ExperimentConfig.model_validate({"name": "a", "pretrain": {"steps": 5}, "normalize": {"from_table": "online"}})
    with pytest.raises(ValueError, match=r"pretrain\.stps"):
        ExperimentConfig.model_validate({"name": "a", "pretrain": {"stps": 5}})
    with pytest.raises(ValueError, match="shared_embodiment"):
        ExperimentConfig.model_validate({"name": "a", "shared_embodiment": True, "pretrain": {"steps": 5}})
    import tests.plugins  # noqa: F401 - test_mean takes no state statistics

    no_stats = {"experiments": [{"name": "a", "algorithm": {"kind": "test_mean"}, "normalize": {}}]}
    with pytest.raises(ConfigError, match=r"experiments\[0\]\.normalize: algorithm 'test_mean' takes no state_mean"):
        LearnerService(service_cfg(tmp_path, **no_stats), start_metrics=False)
    both = {"experiments": [{"name": "a", "algorithm": {"kind": "sac", "params": {"state_mean": {"s": [1]}}}}]}
    both["experiments"][0]["normalize"] = {}
    with pytest.raises(ConfigError, match=r"experiments\[0\]\.normalize: algorithm\.params\.state_mean is set too"):
        LearnerService(service_cfg(tmp_path, **both), start_metrics=False)


def test_state_stats_floor_the_std_of_constant_features() -> None:
    rows = np.stack([np.arange(10.0), np.full(10, 3.0)], axis=1)
    stats = state_stats({"state": rows}, min_std=0.05)
    assert stats["state_mean"]["state"] == pytest.approx([4.5, 3.0])
    assert stats["state_std"]["state"] == pytest.approx([np.std(np.arange(10.0)), 0.05])


def test_flow_vla_spec_with_statistics_normalizes_and_old_specs_still_load() -> None:
    from user.policies.flow_vla import FlowVlaConfig, Preprocessor, policy_spec, random_weights

    base = {"state_keys": ["state"], "state_dim": 2, "instruction_key": None, "action_dim": 1}
    base |= {"action_low": [-1.0], "action_high": [1.0], "horizon": 1, "hidden": 16}
    with_stats = FlowVlaConfig(**base, state_mean=[1.0, -2.0], state_std=[2.0, 0.5])
    prepared = Preprocessor(with_stats, torch.device("cpu"))({"state": np.array([[3.0, -1.0]], np.float32)})
    np.testing.assert_allclose(prepared.state.numpy(), [[1.0, 2.0]])
    raw = FlowVlaConfig(**base)  # published before statistics existed
    assert Preprocessor(raw, torch.device("cpu"))({"state": np.array([[3.0, -1.0]], np.float32)}).state.tolist() == [
        [3.0, -1.0]
    ]
    build_policy(policy_spec(raw), random_weights(raw), 1)
    with pytest.raises(ValueError, match="state_mean has 1 values"):
        FlowVlaConfig(**base, state_mean=[1.0])


def test_control_holds_the_robots_of_an_experiment_its_learner_prepares(base) -> None:
    """WorkerInfo.preparing -> lease hold with a reason; cleared -> leased; a name it does not serve -> refused."""
    cfg, control, _ = base(FLOW)
    stub = control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth))
    edge = Edge(stub, register_msg("e", arm_spec()))
    try:
        assert edge.next_message().WhichOneof("msg") == "registered"
        assert robot_info(stub).lease == "lang"

        def report(*preparing: str, experiments: tuple[str, ...] = ("lang",)) -> None:
            worker = control_pb2.WorkerInfo(worker_id="learner-1", kind="learner", experiments=experiments)
            worker.preparing.extend(preparing)
            stub.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=worker), timeout=5)

        report("lang")
        held = robot_info(stub)
        assert held.lease == "" and "prepares its first policy" in held.lease_reason
        report()
        assert robot_info(stub).lease == "lang"
        with pytest.raises(grpc.RpcError) as err:
            report("other")
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "other" in err.value.details()
    finally:
        edge.close()


OWN = {
    "name": "own",
    "algorithm": {"kind": "sac", "params": {"batch_size": 32, "hidden": [32, 32]}},
    "normalize": {"from_table": "online", "min_steps": 100, "samples": 1024},
}


def test_statistics_from_the_robots_own_first_steps(base) -> None:
    """normalize from the experiment's own table: the initial policy (no statistics) is published so the robots
    can collect; once min_steps exist the algorithm is rebuilt with their statistics and the next version carries
    them (and the checkpoint keeps them)."""
    cfg, control, replay = base(OWN)
    robots = Edge(control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth)), register_msg("e", arm_spec()))
    learner = LearnerService(cfg, start_metrics=False).start()
    try:
        assert robots.next_message().WhichOneof("msg") == "registered"
        initial = wait_for(lambda: (s := status_of(cfg, learner)).weight_version >= 1 and s, "the initial version")
        assert initial.state == "normalizing" and learner.learner.preparing() == []  # robots act meanwhile
        assert "state_mean" not in json.loads(learner.store.latest("own").header.policy.config_json)

        steps, states, _ = record_demos(episodes=6)  # the robot's own first steps (default table)
        stub = replay_pb2_grpc.ReplayStub(make_channel(replay.address, cfg.auth))
        reqs = [replay_pb2.InsertRequest(seq=i, step=s) for i, s in enumerate(steps)]
        assert len([q for ack in stub.Insert(iter(reqs), timeout=30) for q in ack.seqs]) == len(steps)

        nxt = wait_for(lambda: (s := status_of(cfg, learner)).weight_version > initial.weight_version and s, "v2")
        config = json.loads(learner.store.latest("own").header.policy.config_json)
        true_std = np.maximum(states.std(0), 1e-2)
        np.testing.assert_allclose(config["state_mean"], states.mean(0), atol=0.15 * true_std.max())
        assert nxt.updates == 0 and learner.learner.runs["own"].normalization["samples"] >= 1024
    finally:
        learner.stop()
        robots.close()
    ckpt = torch.load(latest_ckpt(cfg, "own"), weights_only=True)
    assert ckpt["normalization"]["state_mean"]["state"] == config["state_mean"]
