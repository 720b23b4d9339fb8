"""Experiments: selectors, layouts (incl. shared embodiments), and a real in-process stack (control, replay,
learner, inference, an edge agent with two differently shaped robots) training two experiments at once with
test plug-ins that are one class each plus a config entry."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

import tests.plugins  # noqa: F401 - registers test_mean / test_constant (one class each, nothing else edited)
from cloud_learner.server import LearnerService
from edge_agent.agent import EdgeAgent
from services.control.server import ControlService
from services.inference.server import InferenceService
from services.replay.server import ReplayService
from tests import helpers
from user.config import ExperimentConfig, RobotConfig, StackConfig
from user.experiments import (
    EMBODIMENT_KEY,
    LayoutError,
    assign,
    experiment_for,
    layout_for,
    pad_action,
    pad_observation,
)
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc, robot_pb2
from user.v1 import tensor_pb2 as tpb

wait_for = functools.partial(helpers.wait_for, limit_s=90.0, poll_s=0.1)
AUTH = {"token": "test-token"}


def spec(rid: str, kind: str, state: int, action: int, labels: dict[str, str] | None = None, image: bool = False):
    s = robot_pb2.RobotSpec(robot_id=rid, kind=kind, control_rate_hz=20, labels=labels or {})
    s.action.shape.append(action)
    s.action.low.extend([-1.0] * action)
    s.action.high.extend([1.0] * action)
    s.observation.add(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[state])
    if image:
        s.observation.add(name="camera.front", dtype=tpb.DTYPE_UINT8, shape=[8, 8, 3], is_image=True)
    return s


ARM, PANDA = spec("arm-0", "sim_reach_arm", 15, 3), spec("panda-0", "gym_hil_panda", 25, 7, {"site": "lab"})


def exp(name: str, **kw) -> ExperimentConfig:
    return ExperimentConfig.model_validate({"name": name, **kw})


# --------------------------------------------------------------------------- selectors and layouts


def test_selectors_route_each_robot_to_the_first_matching_experiment() -> None:
    exps = [exp("lab", robots={"labels": {"site": "lab"}}), exp("arms", robots={"kinds": ["sim_reach_arm"]})]
    assert experiment_for(PANDA, exps).name == "lab"
    assert experiment_for(ARM, exps).name == "arms"
    assert experiment_for(spec("x", "other", 2, 1), exps) is None
    assert assign([ARM, PANDA], exps) == {"lab": [PANDA], "arms": [ARM]}
    assert experiment_for(ARM, [exp("only", robots={"ids": ["arm-1"]})]) is None


def test_default_experiment_is_todays_sac_on_the_learners_robot_kind() -> None:
    (default,) = StackConfig().resolved_experiments()
    assert (default.name, default.algorithm.kind, default.robots.kinds, default.table) == (
        "default",
        "sac",
        ["sim_reach_arm"],
        "online",
    )
    with pytest.raises(ValueError, match="unique"):
        StackConfig.model_validate({"experiments": [{"name": "a"}, {"name": "a"}]})
    with pytest.raises(ValueError, match=r"experiments\.0\.robots\.kind"):
        StackConfig.model_validate({"experiments": [{"name": "a", "robots": {"kind": ["x"]}}]})


def test_layout_of_one_embodiment_and_the_error_for_mixed_shapes() -> None:
    layout = layout_for(exp("a"), [ARM, spec("arm-1", "sim_reach_arm", 15, 3)])
    assert layout.observation["state"].shape == (15,) and layout.action_dim == 3 and layout.embodiments == ()
    with pytest.raises(LayoutError, match="shared_embodiment"):
        layout_for(exp("mixed"), [ARM, PANDA])


def test_shared_embodiment_pads_state_and_action_with_masks_and_ids() -> None:
    layout = layout_for(exp("both", shared_embodiment=True), [ARM, PANDA])
    assert layout.embodiments == ("gym_hil_panda", "sim_reach_arm")
    assert layout.observation["state"].shape == (25,) and layout.observation[EMBODIMENT_KEY].shape == (2,)
    assert layout.action_dim == 7
    obs = pad_observation(layout, "sim_reach_arm", {"state": np.ones((4, 15), np.float32)}, 4)
    assert obs["state"].shape == (4, 25) and obs["state"][:, :15].all() and not obs["state"][:, 15:].any()
    np.testing.assert_array_equal(obs[EMBODIMENT_KEY], np.tile([0.0, 1.0], (4, 1)))
    action, mask = pad_action(np.ones((4, 3), np.float32), 7)
    assert action.shape == (4, 7) and mask[:, :3].all() and not mask[:, 3:].any() and not action[:, 3:].any()
    with pytest.raises(LayoutError, match="image"):
        layout_for(exp("img", shared_embodiment=True), [spec("c", "cam", 4, 2, image=True), ARM, PANDA])


# --------------------------------------------------------------------------- a real stack, two experiments


def stack_cfg(tmp_path: Path, experiments: list[dict]) -> StackConfig:
    cfg = StackConfig.model_validate({"auth": AUTH, "experiments": experiments})
    for section in (cfg.control, cfg.replay, cfg.inference, cfg.learner):
        section.server.port = 0
        section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.2
    cfg.replay.path = tmp_path / "replay"
    cfg.replay.map_size_mb = 64
    cfg.replay.commit_max_delay_ms = 5.0
    cfg.edge.spool_dir = tmp_path / "spool"  # not the repo's runs/default/spool: tests share no outbox
    lc = cfg.learner
    lc.checkpoint_dir = tmp_path / "ckpt"
    lc.min_transitions, lc.publish_every, lc.checkpoint_every, lc.prefetch_batches = 20, 5, 50, 2
    lc.max_updates_per_transition = 1.0
    return cfg


@pytest.fixture
def services(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[StackConfig, LearnerService]]:
    experiments, learner_overrides = request.param if isinstance(request.param, tuple) else (request.param, {})
    cfg = stack_cfg(tmp_path, experiments)
    for key, value in learner_overrides.items():
        setattr(cfg.learner, key, value)
    control = ControlService(cfg, start_metrics=False).start()
    cfg.replay.control_addr = cfg.learner.control_addr = cfg.inference.control_addr = control.address
    replay = ReplayService(cfg, start_metrics=False).start()
    cfg.learner.replay_addr = replay.address
    learner = LearnerService(cfg, start_metrics=False).start()
    cfg.inference.learner_addr = learner.address
    inference = InferenceService(cfg, start_metrics=False).start()
    edge = cfg.edge
    edge.control_addr, edge.replay_addr, edge.inference_addr = control.address, replay.address, inference.address
    edge.learner_addr, edge.mode, edge.metrics_port = learner.address, "fast", 0
    edge.robots = [
        RobotConfig(id="arm-0", kind="sim_reach_arm", params={"max_episode_steps": 20}),
        RobotConfig(id="panda-0", kind="gym_hil_panda", params={"max_episode_steps": 20}),
    ]
    agent = EdgeAgent(cfg)
    agent.start()
    try:
        yield cfg, learner
    finally:
        agent.stop()
        inference.stop()
        learner.stop()
        replay.stop()
        control.stop()


TWO = [
    {
        "name": "reach",
        "robots": {"kinds": ["sim_reach_arm"]},
        "algorithm": {"kind": "test_mean", "params": {"batch_size": 8}},
    },
    {"name": "pick", "robots": {"ids": ["panda-0"]}, "algorithm": {"kind": "test_mean"}},
]


@pytest.mark.parametrize("services", [TWO], indirect=True)
def test_two_experiments_train_at_once_each_on_its_own_robots(services) -> None:
    cfg, learner = services
    stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))

    def both_published():
        status = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
        exps = {e.name: e for e in status.experiments}
        return exps if all(e.weight_version >= 3 and e.updates > 0 for e in exps.values()) else None

    exps = wait_for(both_published, "both experiments to train and publish version 3")
    from prometheus_client import REGISTRY

    for phase in ("update", "publish", "wait_batch"):  # async: the training thread's time by phase is counted
        assert REGISTRY.get_sample_value("user_learner_loop_seconds_total", {"experiment": "reach", "phase": phase})
    assert [list(exps[n].robot_ids) for n in ("reach", "pick")] == [["arm-0"], ["panda-0"]]
    assert all(e.sample_errors == 0 and e.policy_kind == "test_constant" for e in exps.values())
    assert "distance" in exps["reach"].scalars

    # Each algorithm saw only its robots' transitions (15-d vs 21-d state, 3-d vs 7-d actions), interventions kept.
    runs = learner.learner.runs
    assert runs["reach"].layout.action_dim == 3 and runs["pick"].layout.action_dim == 7
    assert runs["pick"].layout.observation["state"].shape == (21,)  # gym-hil Panda: agent_pos + environment_state
    assert all(run.algo.seen[-1]["intervention"] == torch.bool for run in runs.values())

    # Control tags each robot with its experiment; both robots act with their experiment's policy.
    control = control_pb2_grpc.ControlStub(make_channel(cfg.learner.control_addr, cfg.auth))

    def acting():
        infos = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
        return infos if len(infos) == 2 and all(i.status.policy_version >= 2 for i in infos) else None

    infos = wait_for(acting, "both robots to act with a published policy")
    assert {i.spec.robot_id: i.experiment for i in infos} == {"arm-0": "reach", "panda-0": "pick"}
    # Per-experiment checkpoints on shutdown.
    learner.stop()
    assert (Path(cfg.learner.checkpoint_dir) / "reach" / "latest").exists()
    assert (Path(cfg.learner.checkpoint_dir) / "pick" / "latest").exists()


@pytest.mark.parametrize("services", [[{"name": "mixed", "algorithm": {"kind": "test_mean"}}]], indirect=True)
def test_robots_of_different_shapes_in_one_experiment_fail_loudly(services) -> None:
    cfg, learner = services
    stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))

    def failed():
        (e,) = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5).experiments
        return e if e.state == "failed" else None

    status = wait_for(failed, "the mixed experiment to report its layout error")
    assert "shared_embodiment" in status.error and status.updates == 0


SHARED = [{"name": "both", "shared_embodiment": True, "algorithm": {"kind": "test_mean", "params": {"batch_size": 8}}}]


@pytest.mark.parametrize("services", [SHARED], indirect=True)
def test_one_policy_shared_by_two_embodiments(services) -> None:
    cfg, learner = services
    stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))

    def trained():
        (e,) = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5).experiments
        return e if e.weight_version >= 3 else None

    status = wait_for(trained, "the shared experiment to publish version 3")
    assert status.sample_errors == 0 and status.policy_kind == "padded" and status.state == "training"
    run = learner.learner.runs["both"]
    assert run.layout.embodiments == ("gym_hil_panda", "sim_reach_arm") and run.layout.action_dim == 7
    seen = run.algo.seen[-1]
    assert sorted(set(seen["embodiment"])) == [0, 1]  # every batch mixes both embodiments
    assert seen["dtypes"] == {"state": torch.float32, EMBODIMENT_KEY: torch.float32}

    # Both robots act through the inference service with the one shared (padded) policy.
    control = control_pb2_grpc.ControlStub(make_channel(cfg.learner.control_addr, cfg.auth))

    def acting():
        infos = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots
        return infos if len(infos) == 2 and all(i.status.policy_version >= 2 for i in infos) else None

    infos = wait_for(acting, "both embodiments to act with the shared policy")
    assert {i.experiment for i in infos} == {"both"}


SYNC = ([TWO[0]], {"mode": "sync", "sync_env_steps": 40, "sync_updates": 7})


@pytest.mark.parametrize("services", [SYNC], indirect=True)
def test_sync_mode_collects_trains_and_publishes_in_turn(services) -> None:
    cfg, learner = services
    stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))

    def rounds():
        (e,) = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5).experiments
        return e if e.weight_version >= 4 else None

    from prometheus_client import REGISTRY

    def commands(kind: str) -> float:
        return REGISTRY.get_sample_value("user_control_commands_total", {"kind": kind}) or 0.0

    def loop_s(phase: str) -> float:
        return (
            REGISTRY.get_sample_value("user_learner_loop_seconds_total", {"experiment": "reach", "phase": phase}) or 0.0
        )

    paused_before = commands("pause")
    waited_batch_before = loop_s("wait_batch")
    status = wait_for(rounds, "three sync rounds")
    # The training thread's time is counted by phase: it idled while the robots collected, sampled inline (no
    # prefetch thread in sync mode) and updated; the async phase (waiting for the sampler's queue) never moved.
    assert loop_s("wait_robots") > 0 and loop_s("sample") > 0 and loop_s("update") > 0
    assert loop_s("wait_batch") == waited_batch_before
    # Weights go out only at the end of a round: sync_updates per published version after v1.
    assert 7 * (status.weight_version - 1) <= status.updates <= 7 * status.weight_version
    assert status.env_steps >= 40 * (status.weight_version - 1)
    # Each round paused the experiment's robot for training and resumed it for collection.
    assert commands("pause") - paused_before >= 2
    assert commands("resume") >= 3


def test_console_shows_one_row_per_robot_and_per_experiment(tmp_path: Path) -> None:
    from rich.console import Console

    from user.config import load_config
    from user.up import Episode, Monitor, Snapshot, _render, write_report

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "demo.yaml")
    mon = object.__new__(Monitor)  # no stack: only its episode bookkeeping is used
    mon.episodes = {("arm-0", f"e{i}"): Episode("arm-0", f"e{i}", i, i > 2, 1.0, 20, 2, "reach") for i in range(5)}
    mon.episodes[("panda-0", "p0")] = Episode("panda-0", "p0", 3.0, False, 0.5, 100, 1, "pick")
    robots = [
        control_pb2.RobotInfo(spec=ARM, online=True, experiment="reach"),
        control_pb2.RobotInfo(spec=PANDA, online=True, experiment="pick"),
    ]
    status = learner_pb2.LearnerStatus(
        experiments=[
            learner_pb2.ExperimentStatus(name="reach", algorithm="sac", state="training", scalars={"alpha": 0.1}),
            learner_pb2.ExperimentStatus(
                name="pick",
                algorithm="sac",
                state="waiting_for_data",
                waiting_for="no sampleable transitions in demos yet",
                sample_errors=3,
            ),
        ]
    )
    console = Console(width=160, record=True)
    console.print(_render(Snapshot(5.0, robots, status, None), mon, cfg, 600))
    text = console.export_text()
    assert all(name in text for name in ("arm-0", "panda-0", "reach", "pick", "alpha=0.1", "waiting_for_data"))
    wide = Console(width=240, record=True)
    wide.print(_render(Snapshot(5.0, robots, status, None), mon, cfg, 600, width=240))
    assert "waiting_for_data: no sampleable transitions in demos yet (3 sample errors)" in wide.export_text()
    # An 80-column terminal: whole headers (the wide columns left out), scalars on lines of their own.
    narrow = Console(width=80, record=True)
    narrow.print(_render(Snapshot(5.0, robots, status, None), mon, cfg, 600, width=80))
    lines = narrow.export_text().splitlines()
    headers = next(line.split() for line in lines if line.split()[:1] == ["robot"])
    assert headers == ["robot", "exp", "state", "eps", "success", "steps/s", "policy", "stale", "spool"]
    headers = next(line.split() for line in lines if line.split()[:1] == ["experiment"])
    assert headers == ["experiment", "algo", "state", "updates", "updates/s", "weights", "success"]
    assert "reach: alpha=0.1" in [line.strip() for line in lines] and max(len(line) for line in lines) <= 80
    assert mon.success_rate(2, "reach") == 1.0 and mon.success_rate(2, "pick") is None
    write_report(tmp_path, mon.ordered(), {"name": "t", "target_success": 0.9, "time_to_target_s": None}, window=2)
    assert (tmp_path / "report.png").exists()


def test_stop_rule_counts_only_episodes_without_interventions(tmp_path: Path) -> None:
    """An expert's rescue is not the policy's success: the stop rule and the report count unhelped episodes."""
    import json

    from rich.console import Console

    from user.config import load_config
    from user.up import Episode, Monitor, Snapshot, _render, _summary, write_report

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "demo.yaml")
    mon = object.__new__(Monitor)
    # 6 episodes the teleoperator drove (all succeed), 4 the policy did alone (1 succeeds).
    helped = [Episode("arm-0", f"h{i}", 2 * i, True, 1.0, 20, 2, "reach", intervention_steps=5) for i in range(6)]
    alone = [Episode("arm-0", f"a{i}", 2 * i + 1, i == 3, 0.0, 20, 2, "reach") for i in range(4)]
    mon.episodes = {(e.robot_id, e.episode_id): e for e in helped + alone}
    assert mon.success_rate(4, "reach") == pytest.approx(0.25)
    assert mon.success_rate(4, "reach", autonomous=False) == 1.0  # h3, a3, h4, h5
    assert mon.success_rate(5, "reach") is None  # only 4 unhelped episodes so far
    assert mon.success_rate(10, "reach", autonomous=False) == pytest.approx(0.7)
    robots = [control_pb2.RobotInfo(spec=ARM, online=True, experiment="reach")]
    status = learner_pb2.LearnerStatus(experiments=[learner_pb2.ExperimentStatus(name="reach", algorithm="sac")])
    console = Console(width=200, record=True)
    console.print(_render(Snapshot(5.0, robots, status, None), mon, cfg, 600))
    assert "25 % (4) [70 % all]" in console.export_text()
    summary = _summary(cfg, "budget exhausted", None, None, mon.ordered(), {}, 10.0)
    assert summary["final_success_rate_autonomous"] == pytest.approx(0.25)
    assert summary["episodes_with_interventions"] == 6
    # The headline rates are the target experiment's: another experiment's episodes do not move them.
    other = {("arm-9", f"o{i}"): Episode("arm-9", f"o{i}", 9.0 + i, True, 1.0, 20, 2, "pick") for i in range(8)}
    mixed = sorted([*mon.ordered(), *other.values()], key=lambda e: e.t)
    assert _summary(cfg, "budget exhausted", None, None, mixed, {}, 10.0)["final_success_rate_autonomous"] == 0.25
    write_report(tmp_path, mon.ordered(), {**summary, "target_success": 0.9}, window=4)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert doc["rolling_success_autonomous"][0] is None  # the first episode was helped: no unhelped one yet
    assert doc["rolling_success_autonomous"][-1] == pytest.approx(0.25)


def test_a_learner_through_the_socket_trains_on_edge_jpegs_it_decodes_itself(tmp_path: Path) -> None:
    """An edge JPEG-encodes its camera; the learner samples through the socket (no shared memory) with
    encoded_frames: replay sends the frames as it keeps them, the learner decodes them into uint8 batches."""
    from prometheus_client import REGISTRY

    def kept() -> float:
        return REGISTRY.get_sample_value("user_replay_sampled_frames_kept_total") or 0.0

    cfg = stack_cfg(tmp_path, [{"name": "cam", "algorithm": {"kind": "test_mean"}}])
    cfg.learner.replay_shm_dir = None
    before = kept()
    with contextlib.ExitStack() as stack:
        control = ControlService(cfg, start_metrics=False).start()
        stack.callback(control.stop)
        cfg.replay.control_addr = cfg.learner.control_addr = cfg.inference.control_addr = control.address
        replay = ReplayService(cfg, start_metrics=False).start()
        stack.callback(replay.stop)
        cfg.learner.replay_addr = replay.address
        learner = LearnerService(cfg, start_metrics=False).start()
        stack.callback(learner.stop)
        cfg.inference.learner_addr = learner.address
        inference = InferenceService(cfg, start_metrics=False).start()
        stack.callback(inference.stop)
        edge = cfg.edge
        edge.control_addr, edge.replay_addr, edge.inference_addr = control.address, replay.address, inference.address
        edge.learner_addr, edge.mode, edge.metrics_port = learner.address, "fast", 0
        jpeg = {"*": "jpeg"}
        edge.robots = [RobotConfig(id="cam-0", kind="lang_reach_arm", params={"camera_size": 32}, image_encoding=jpeg)]
        agent = EdgeAgent(cfg)
        agent.start()
        stack.callback(agent.stop)
        run = wait_for(lambda: learner.learner.runs.get("cam"), "the experiment to start")
        wait_for(lambda: len(run.algo.seen) >= 3, "three updates")
        assert run.algo.seen[-1]["dtypes"]["camera.front"] == torch.uint8
        assert run.state.sample_errors == 0
        assert kept() - before >= 3 * 8 * 2  # every sampled frame came as replay keeps it (obs and next obs)


def test_an_experiment_whose_robots_an_earlier_one_takes_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    """First match wins, so a later experiment whose selector is covered by an earlier one can never train:
    control says so at start (the same selector twice, or after a catch-all)."""
    import logging

    from services.control.server import Registry
    from user.experiments import shadowed

    def exp(name: str, **robots: object) -> ExperimentConfig:
        return ExperimentConfig.model_validate({"name": name, "robots": robots})

    exps = [
        exp("arms", kinds=["sim_reach_arm"]),
        exp("lab-arms", kinds=["sim_reach_arm"], labels={"site": "lab"}),  # every lab arm is an arm: covered
        exp("pandas", kinds=["gym_hil_panda"]),
        exp("two", ids=["p-0", "p-1"]),  # any kind: not covered by the kind selectors
        exp("one", ids=["p-1"], labels={"x": "y"}),  # covered by "two"
        exp("all"),
        exp("after-all", kinds=["so101"]),  # covered by the catch-all
    ]
    assert shadowed(exps) == {"lab-arms": "arms", "one": "two", "after-all": "all"}
    with caplog.at_level(logging.WARNING, logger="services.control.server"):
        Registry(lease_ttl_s=1.0, episodes_kept=10, experiments=exps)
    warned = {r.fields["experiment"] for r in caplog.records if "can get no robot" in r.getMessage()}  # type: ignore[attr-defined]
    assert warned == {"lab-arms", "one", "after-all"}
