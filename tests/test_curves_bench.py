"""The learning bench's --quick path writes its curves, and the in-process trainer's plumbing:
expert steps become interventions in their own table, demos are recorded, the scripted pick works."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from bench import curves_bench
from cloud_learner.local import Buffer, make_algorithm, record_episodes, train_local
from edge_agent.robot import known_robot_kinds, make_robot


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def test_quick_reach_curve_is_written(tmp_path: Path) -> None:
    rows = curves_bench.run(quick=True, workdir=tmp_path, log=lambda *a: None, only=["reach"])
    assert {r.metric for r in rows} >= {"success without intervention, last 20", "first 90% rolling success"}
    assert all(r.higher_is_better is None for r in rows)  # facts, no ratio against a 0 % peer
    doc = json.loads((tmp_path / "curves" / "reach_sac_state.json").read_text())
    assert doc["target"] == 0.9 and len(doc["env_steps"]) == len(doc["success"]) == len(doc["wall_s"]) > 0
    assert doc["env_steps"] == sorted(doc["env_steps"]) and doc["env_steps"][-1] <= 200
    assert (tmp_path / "curves" / "reach_sac_state.png").stat().st_size > 1000


def test_expert_steps_are_stored_as_interventions() -> None:
    robot = make_robot("sim_reach_arm", "t", seed=0)
    algorithm = make_algorithm("sac", {"hidden": [16], "batch_size": 8}, robot.spec)
    calls = []

    def expert(obs, ep_step):  # takes over the second half of every episode, pushing +x
        calls.append(ep_step)
        return np.array([1.0, 0.0, 0.0], np.float32) if ep_step >= 25 else None

    out = train_local(robot, algorithm, 120, min_transitions=10, expert=expert)
    buffer: Buffer = out["buffer"]
    online, interventions = buffer.tables["online"], buffer.tables["interventions"]
    assert online.size == 120 and interventions.size == sum(1 for s in calls if s >= 25) > 0
    flags = np.array(online.rows["intervention"])
    assert flags.sum() == interventions.size
    np.testing.assert_allclose(np.stack(interventions.rows["action"])[:, 0], 1.0)
    assert out["curve"].interventions[0] == 25 and out["updates"] == 111


def test_evaluation_episodes_act_alone_and_helped_episodes_do_not_count() -> None:
    robot = make_robot("sim_reach_arm", "t", seed=0)
    algorithm = make_algorithm("rlpd", {"hidden": [16], "batch_size": 8, "num_critics": 2, "utd": 1}, robot.spec)
    expert = lambda obs, ep_step: np.zeros(3, np.float32) if ep_step >= 40 else None  # noqa: E731
    buffer = Buffer()
    record_episodes(robot, lambda obs, ep_step: np.zeros(3, np.float32), 1, buffer.table("demos"))
    out = train_local(
        robot, algorithm, 300, min_transitions=10, expert=expert, eval_every=2, pretrain_updates=3, buffer=buffer
    )
    robot.close()
    curve = out["curve"]
    assert curve.evaluation[:4] == [False, True, False, True]
    assert all(n == 0 for n, e in zip(curve.interventions, curve.evaluation, strict=True) if e)  # no expert
    assert out["updates"] == 3 + 300 - 10 + 1
    # Helped episodes count as failures of nobody and as successes of nobody: only unhelped ones count.
    curve.success = [True, False, True, True, True, False]
    curve.interventions = [5, 0, 5, 0, 5, 0]
    rolling = curves_bench.rolling_success(curve)
    assert np.isnan(rolling[0]) and list(rolling[1:]) == pytest.approx([0.0, 0.0, 0.5, 0.5, 1 / 3])
    assert list(curves_bench.rolling_success(curve, autonomous=False))[-1] == pytest.approx(4 / 6)


def test_curve_records_what_the_learner_did_per_episode_and_cpu_budget_stops() -> None:
    """Per episode the mean of the update scalars during it (alpha, Q, the BC term: why a curve moves), none
    before updates start; the offline phase's last scalars come back; a CPU budget ends the run."""
    robot = make_robot("sim_reach_arm", "t", params={"max_episode_steps": 20}, seed=0)
    params = {"hidden": [16], "batch_size": 8, "num_critics": 2, "utd": 1, "bc_weight": 1.0}
    algorithm = make_algorithm("rlpd", {**params, "actor_pretrain_updates": 2, "critic_warmup_updates": 1}, robot.spec)
    buffer = Buffer()
    record_episodes(robot, lambda obs, ep_step: np.zeros(3, np.float32), 1, buffer.table("demos"))
    out = train_local(robot, algorithm, 100, min_transitions=30, pretrain_updates=3, buffer=buffer)
    curve = out["curve"]
    assert len(curve.learner) == len(curve.success) == 5
    assert curve.learner[0] == {}  # 20 steps, updates start at 30
    assert {"alpha", "q", "q_pi", "bc_term", "bc_loss"} <= set(curve.learner[-1])
    assert curve.learner[-1]["bc_term"] == pytest.approx(curve.learner[-1]["bc_loss"])  # weight 1
    assert set(out["pretrain_last"]) == {"critic_loss", "q", "alpha"}  # the last offline update warmed the critics
    assert json.loads(json.dumps(curve.to_json()))["learner"][-1]["alpha"] == curve.learner[-1]["alpha"]
    stopped = train_local(robot, algorithm, 100, min_transitions=30, max_cpu_seconds=0.0)
    robot.close()
    assert stopped["env_steps"] == 1
    curve.interventions = [0, 3, 0, 0, 0]
    curve.evaluation = [False, False, False, True, False]
    curve.success = [True, True, False, True, False]
    assert [b.split(" (")[0] for b in curves_bench.blocks(curve, size=3)] == ["1/2", "1/2"]
    assert "eval 1/1" in curves_bench.blocks(curve, size=3)[1]


@pytest.mark.skipif("gym_hil_panda" not in known_robot_kinds(), reason="gym-hil not installed")
def test_scripted_pick_expert_succeeds_and_records_demos() -> None:
    robot = make_robot("gym_hil_panda", "t", params={"reward_type": "sparse"}, seed=0)
    demos = Buffer().table("demos")
    successes = record_episodes(robot, lambda o, _: curves_bench.panda_pick_expert(o.features["state"]), 3, demos)
    robot.close()
    assert sum(successes) >= 2
    assert demos.size > 0 and all(np.array(demos.rows["intervention"]))
    assert float(np.sum(demos.rows["reward"])) == sum(successes)  # sparse: 1 only on the lifting step


def test_so101_expert_records_demos_and_takes_over_mid_episode() -> None:
    """The SO-101 curve's expert (edge_agent's stateless scripted expert): demos from reset succeed, and it
    takes over after 30 random steps and still lifts the cube."""
    if "so101" not in known_robot_kinds():
        pytest.skip("lerobot-env-so101 not installed")
    robot = make_robot("so101", "t", params={"reward_type": "sparse"}, seed=0)
    act = curves_bench.so101_expert(robot)
    demos = Buffer().table("demos")
    successes = record_episodes(robot, lambda o, s: act(o, s == 0), 2, demos, seed=1000)
    assert sum(successes) >= 1 and float(np.sum(demos.rows["reward"])) == sum(successes)
    helper = curves_bench.ScriptedInterventions(start_share=1.0, after_steps=30, decay_steps=10**6, seed=0, act=act)
    rng = np.random.default_rng(0)
    obs, helped = robot.reset(seed=7), 0
    for step in range(int(robot.spec.max_episode_steps)):
        action = helper(obs, step)
        helped += action is not None
        robot.act(rng.uniform([-1.0, -1.0, -1.0, 0.0], 1.0).astype(np.float32) if action is None else action)
        obs = robot.observe()
        if obs.terminated:
            break
    robot.close()
    assert helped > 0 and obs.success


def test_only_successful_demos_are_kept() -> None:
    """`only_successes`: a failed expert episode leaves no rows; tries go on until enough succeed (at most 3x),
    and every try is reported, so the expert's own success rate stays visible."""
    from edge_agent.teleoperators.scripted_expert import ReachExpert

    robot = make_robot("sim_reach_arm", "t", params={"max_episode_steps": 30}, seed=0)
    reach, starts = ReachExpert(robot.spec), [0]

    def every_other(obs, ep_step):  # odd episodes: the expert; even ones: stand still (fail)
        starts[0] += ep_step == 0
        return reach.action(obs) if starts[0] % 2 else np.zeros(3, np.float32)

    kept, everything = Buffer().table("kept"), Buffer().table("all")
    assert record_episodes(robot, every_other, 2, kept, only_successes=True) == [True, False, True]
    assert int(np.sum(kept.rows["terminated"])) == 2 and all(np.array(kept.rows["intervention"]))
    starts[0] = 0
    assert record_episodes(robot, every_other, 2, everything) == [True, False]
    # without the filter the failed try's 30 (truncated, not terminated) rows are there too
    assert int(np.sum(everything.rows["terminated"])) == 1 and everything.size >= 31
    none = Buffer().table("none")
    assert record_episodes(robot, lambda o, s: np.zeros(3, np.float32), 2, none, only_successes=True) == [False] * 6
    robot.close()
    assert none.size == 0
