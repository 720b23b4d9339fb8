"""SO-101 and Panda training at once on one stack: a learning curve per arm.

The whole stack as real processes (`userctl up`'s Stack: control, replay, learner, inference and one
edge agent per robot at its real control rate), two experiments, each its own RLPD instance and
replay table: `so101` (lerobot-env-so101's SO-101 pick-cube, 21-d state, 4-d action) and `pick`
(gym-hil's Panda pick-cube, 21-d state, 7-d action). Both from state with the recipe the in-process
curves use (bench/curves_bench.py): sparse reward, 50/50 batches of the experiment's table and its
interventions, a BC term on human rows, SERL's starting temperature, the state standardized by the
statistics of scripted demos (recorded here in-process, written into each algorithm's params). On
each edge the scripted expert (edge_agent's `scripted_expert` teleoperator) takes over when the
policy stalls, as a human does in HIL-SERL; its steps reach replay flagged as interventions.

Success is counted over the episodes nobody intervened in (an expert's rescue is not the policy's);
the peer is a uniform random policy on the same robot. Curves (success over env steps and over
wall time, per arm) go to runs/bench/two_arms/so101_panda.{json,png}.

    python -m bench --only two_arms            # or: python -m bench.two_arms_bench --minutes 20
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench import Row
from bench.curves_bench import SO101_PARAMS, SO101_PRETRAIN_UPDATES

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"
OUT = Path("runs/bench/two_arms")
PEER = "random policy"
WINDOW = 20
TARGET = 0.8
# experiment name -> (robot kind, robot id, display name)
ARMS = {"so101": ("so101", "so101-0", "SO-101"), "pick": ("gym_hil_panda", "panda-0", "Panda")}
RLPD = {
    "hidden": [256, 256],
    "batch_size": 128,
    "utd": 1,  # cheaper than the in-process recipe (utd 2, 10 critics): one learner trains both arms
    "num_critics": 4,
    "init_alpha": 0.01,
    "bc_weight": 1.0,
}
# SO-101: the in-process curve's warm start (curves_bench.SO101_PARAMS, notes of 2026-11-25): 2,000 BC-only
# actor updates, then 6,000 critic-only ones, no entropy backup, BC weight 5. Without it (1,500 plain RLPD updates)
# its policy stalled so often that the expert rescued nearly every episode and its own success was not measurable.
# Panda keeps the shared params: it reached 80 % unhelped with them on this stack.
ARM_PARAMS: dict[str, dict[str, Any]] = {"so101": SO101_PARAMS}
QUICK_ARM_PARAMS: dict[str, dict[str, Any]] = {
    "so101": {**SO101_PARAMS, "actor_pretrain_updates": 2, "critic_warmup_updates": 3}
}
# experiment -> offline updates on its scripted demos before the stack starts: the whole warm start, so the
# learner resumes in the RL phase (phases follow the checkpointed update count)
PRETRAIN = {"so101": SO101_PRETRAIN_UPDATES}
TELEOP = {"kind": "scripted_expert", "params": {"takeover": "on_stray", "patience": 8, "max_takeover_steps": 40}}
# An SO-101 pick has stretches without 5 mm of progress (aligning above the cube, ~4 ticks closing the jaw): with
# patience 8 its expert took over all 87 episodes of a 10-minute run, leaving the policy none of its own.
PATIENCE = {"so101": 20}


def state_stats(kind: str, episodes: int) -> tuple[dict[str, Any], float, float, Any, Any]:
    """({state_mean, state_std}) from `episodes` successful scripted demos, the expert's success rate, a random
    policy's success rate (the peer) on the same robot, the demos (a Table) and the robot's spec."""
    from bench.curves_bench import panda_pick_expert, random_success, so101_expert
    from cloud_learner.local import Buffer, record_episodes
    from edge_agent.robot import make_robot

    robot = make_robot(kind, f"stats-{kind}", params={"reward_type": "sparse"}, seed=0)
    act = so101_expert(robot) if kind == "so101" else (lambda o, _first: panda_pick_expert(o.features["state"]))
    demos = Buffer().table("demos")
    success = record_episodes(robot, lambda o, s: act(o, s == 0), episodes, demos, seed=1000, only_successes=True)
    peer = random_success(robot, 1000, 0)
    spec = robot.spec
    robot.close()
    state = np.stack(demos.rows["obs/state"])
    stats = {
        "state_mean": {"state": [round(float(x), 5) for x in state.mean(0)]},
        "state_std": {"state": [round(float(x), 5) for x in np.maximum(state.std(0), 1e-2)]},
    }
    return stats, float(np.mean(success)), peer, demos, spec


def pretrain_checkpoint(cfg: Any, name: str, spec: Any, demos: Any, updates: int, ckpt_dir: Path) -> None:
    """`updates` offline updates of experiment `name`'s algorithm on its demos, built as the learner builds it,
    saved as the checkpoint the learner resumes from: the stack's policy starts where the in-process curve's does
    (the SO-101's on_stray expert otherwise rescues nearly every episode of a random policy)."""
    import torch

    from cloud_learner.checkpoint import save_checkpoint
    from cloud_learner.learner import build_algorithm, checkpoint_state
    from cloud_learner.local import Buffer
    from user.experiments import layout_for

    index, exp = next((i, e) for i, e in enumerate(cfg.experiments) if e.name == name)
    layout = layout_for(exp, [spec])
    torch.manual_seed(0)
    algo = build_algorithm(index, exp, layout, "cpu")
    buffer, rng = Buffer({"online": demos}), np.random.default_rng(0)  # every batch from the demos (human rows)
    for _ in range(updates):
        algo.update(buffer.sample(algo.batch_request(), rng, algo.device))
    save_checkpoint(ckpt_dir / name, checkpoint_state(algo, exp.algorithm.kind, 1, layout))


def overrides(stats: dict[str, dict[str, Any]], budget_s: float, quick: bool) -> list[str]:
    params = {"hidden": [32, 32], "batch_size": 16, "utd": 1, "num_critics": 2, "bc_weight": 1.0} if quick else RLPD
    experiments, robots = [], []
    for name, (kind, robot_id, _) in ARMS.items():
        # Each experiment samples only its own robots' rows (replay filters by robot id): its own table in effect.
        arm_params = (QUICK_ARM_PARAMS if quick else ARM_PARAMS).get(name, {})
        algo = {**params, **arm_params, **stats[name], "tables": {"online": 0.5, "interventions": 0.5}}
        experiments.append({"name": name, "robots": {"kinds": [kind]}, "algorithm": {"kind": "rlpd", "params": algo}})
        robot_params = {"reward_type": "sparse", "max_episode_steps": 100}
        teleop = {**TELEOP, "params": {**TELEOP["params"], "patience": PATIENCE.get(name, 8)}}
        robots.append({"id": robot_id, "kind": kind, "params": robot_params, "teleop": teleop})
    return [
        f"experiments={json.dumps(experiments)}",
        f"edge.robots={json.dumps(robots)}",
        "up.edge_agents=1",
        f"up.budget_s={budget_s}",
        "up.target_experiment=so101",
        "learner.min_transitions=200",
        "log_json=true",
    ]


def curve_of(episodes: list[Any], t_end: float) -> dict[str, Any]:
    """Per episode of one experiment: cumulative env steps, wall s, success, interventions, and the
    rolling success over the last WINDOW episodes without interventions."""
    steps, rolling, recent = np.cumsum([e.length for e in episodes]).tolist(), [], []
    for e in episodes:
        if not e.intervention_steps:
            recent = [*recent[-(WINDOW - 1) :], e.success]
        rolling.append(float(np.mean(recent)) if recent else None)
    return {
        "env_steps": steps,
        "wall_s": [round(e.t, 2) for e in episodes],
        "success": [bool(e.success) for e in episodes],
        "intervention_steps": [int(e.intervention_steps) for e in episodes],
        "episode_return": [float(e.episode_return) for e in episodes],
        "rolling_success_unhelped": rolling,
        "wall_end_s": t_end,
    }


def first_reaching(curve: dict[str, Any], target: float) -> tuple[int, float] | None:
    counted = np.cumsum([n == 0 for n in curve["intervention_steps"]])
    for i, r in enumerate(curve["rolling_success_unhelped"]):
        if r is not None and counted[i] >= WINDOW and r >= target:
            return curve["env_steps"][i], curve["wall_s"][i]
    return None


def save(doc: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "so101_panda.json").write_text(json.dumps(doc, indent=1))
    fig, axes = plt.subplots(len(ARMS), 2, figsize=(10, 3.2 * len(ARMS)), sharey=True, squeeze=False)
    for row, name in enumerate(ARMS):
        curve = doc["arms"][name]
        rolling = [np.nan if r is None else r for r in curve["rolling_success_unhelped"]]
        helped = np.asarray([n > 0 for n in curve["intervention_steps"]], float)
        share = [helped[max(0, i - WINDOW + 1) : i + 1].mean() for i in range(len(helped))]
        for ax, x, label in (
            (axes[row][0], curve["env_steps"], "env steps"),
            (axes[row][1], np.asarray(curve["wall_s"]) / 60, "wall time (min)"),
        ):
            ax.plot(x, rolling, label=f"success without help (last {WINDOW})")
            ax.plot(x, share, color="tab:gray", linestyle=":", label=f"share of the last {WINDOW} episodes helped")
            ax.axhline(TARGET, color="gray", linestyle="--", label=f"{TARGET:.0%}")
            ax.set_xlabel(label)
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
        axes[row][0].set_ylabel(f"{ARMS[name][2]} ({name})")
        axes[row][0].legend(loc="upper left", fontsize=8)
    fig.suptitle(f"SO-101 and Panda at once on one stack, RLPD from state (load {doc['load_at_start'][0]:.1f})")
    fig.tight_layout()
    fig.savefig(out / "so101_panda.png", dpi=100)
    plt.close(fig)


def run(quick: bool, workdir: Path, log: Callable[..., None] = print, minutes: float | None = None) -> list[Row]:
    from user.config import load_config
    from user.up import Monitor, Stack

    minutes = minutes if minutes is not None else (1.5 if quick else 20.0)
    load_at_start = os.getloadavg()
    stats, demo_success, peer, demos, specs = {}, {}, {}, {}, {}
    for name, (kind, _, _) in ARMS.items():
        try:
            stats[name], demo_success[name], peer[name], demos[name], specs[name] = state_stats(
                kind, 3 if quick else 20
            )
        except (ValueError, ImportError) as exc:  # lerobot-env-so101 / gym-hil missing
            log(f"two_arms skipped: {exc}")
            return []
    over = overrides(stats, minutes * 60 + 120, quick)
    cfg = load_config(CONFIG, over)
    run_dir = Path(workdir) / "two_arms_stack"
    shutil.rmtree(run_dir, ignore_errors=True)  # a fresh stack: a kept one would resume the last run's policies
    for name, updates in PRETRAIN.items():
        pretrain_checkpoint(cfg, name, specs[name], demos[name], 5 if quick else updates, run_dir / "checkpoints")
        log(f"two_arms: {name} warm start done ({updates} updates), CPU {time.process_time() / 60:.1f} min")
    stack = Stack(cfg, str(CONFIG), over, run_dir)
    mon, snap = None, None
    try:
        stack.start()
        t0 = time.monotonic()
        mon = Monitor(stack, t0)
        while (snap := mon.poll()).t < minutes * 60:
            dead = stack.dead_children()
            if dead:
                raise RuntimeError(f"{dead[0].name} exited with {dead[0].proc.returncode}:\n{dead[0].log_tail()}")
            if int(snap.t) % 60 == 0:
                done = {n: sum(e.experiment == n for e in mon.ordered()) for n in ARMS}
                log(f"two_arms {snap.t / 60:.0f} min: episodes {done}, load {os.getloadavg()[0]:.1f}")
            time.sleep(1.0)
    finally:
        stack.stop()
    episodes = mon.ordered() if mon else []
    statuses = {e.name: e for e in snap.learner.experiments} if snap and snap.learner else {}
    doc: dict[str, Any] = {
        "name": "so101_panda",
        "minutes": minutes,
        "window": WINDOW,
        "target": TARGET,
        "load_at_start": load_at_start,
        "load_at_end": os.getloadavg(),
        "algorithm": "rlpd",
        "params": {k: v for k, v in (RLPD if not quick else {}).items()},
        "arm_params": ARM_PARAMS if not quick else QUICK_ARM_PARAMS,
        "teleop": TELEOP,
        "patience": PATIENCE,
        "demo_success_for_stats": demo_success,
        "pretrain_updates": PRETRAIN,
        "random_policy_success": peer,
        "updates": {n: int(s.updates) for n, s in statuses.items()},
        "arms": {n: curve_of([e for e in episodes if e.experiment == n], snap.t if snap else 0.0) for n in ARMS},
    }
    out = Path(workdir) / "two_arms" if quick else OUT
    save(doc, out)
    log(f"two_arms: curves in {out}")
    return rows(doc)


def rows(doc: dict[str, Any]) -> list[Row]:
    out = []
    for name, (_, _, arm) in ARMS.items():
        curve, peer = doc["arms"][name], doc["random_policy_success"][name]
        group = f"two_arms {arm} ({name}) beside the other arm on one stack, RLPD from state"
        unhelped = [s for s, n in zip(curve["success"], curve["intervention_steps"], strict=True) if n == 0]
        last = float(np.mean(unhelped[-WINDOW:])) if unhelped else 0.0
        reached = first_reaching(curve, TARGET)
        steps = curve["env_steps"][-1] if curve["env_steps"] else 0
        load = doc["load_at_start"][0]
        note = f"{len(unhelped)} of {len(curve['success'])} episodes without interventions; load {load:.1f}"
        out += [
            Row(
                group,
                f"success without intervention, last {WINDOW}",
                f"{last:.2f}",
                f"{peer:.2f}",
                note=note,
                peer_name=PEER,
            ),
            Row(
                group,
                f"first {TARGET:.0%} rolling success",
                f"{reached[0]:,} steps, {reached[1] / 60:.1f} min" if reached else "not reached",
                "never",
                note=f"within {doc['minutes']:g} min, both arms training at once",
                peer_name=PEER,
            ),
            Row(
                group,
                "env steps, updates",
                f"{steps:,}, {doc['updates'].get(name, 0):,}",
                f"{steps:,}, 0",
                note=f"{len(curve['success'])} episodes",
                peer_name=PEER,
            ),
        ]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--minutes", type=float, default=None)
    parser.add_argument("--workdir", default="runs/bench")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    for row in run(args.quick, Path(args.workdir), minutes=args.minutes):
        print(f"{row.group} | {row.metric} | {row.ours} | {row.peer} | {row.note}")


if __name__ == "__main__":
    main()
