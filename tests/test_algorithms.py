"""SAC, RLPD and BC behind the Algorithm interface, from state and from tiny pixels.

Each algorithm: updates give finite scalars, a weights-only checkpoint resumes to the identical next
update, the published policy rebuilds through build_policy and acts like the trained actor. Plus the
parts that carry the method: termination stops bootstrapping, only critic gradients reach a shared
image encoder, DrQ shifts stay inside the padding, RLPD asks for 50/50 batches, BC fits demos.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import torch

from cloud_learner.algorithm import ALGORITHMS, Algorithm, Batch, Feature, Layout
from cloud_learner.algorithms.sac import SAC
from cloud_learner.local import Buffer, Table
from user.policies.cnn import random_shift
from user.policy import build_policy
from user.registry import PluginError

STATE_DIM, ACTION_DIM, IMAGE = 5, 2, (12, 12, 3)
LOW, HIGH = np.array([-1.0, -2.0], np.float32), np.array([1.0, 2.0], np.float32)
TINY = {"hidden": [16, 16], "batch_size": 8}
PIXEL = {"channels": [4, 8], "strides": [2, 2], "latent_dim": 8, "image_pad": 2}
SMALL = {"sac": TINY, "rlpd": {**TINY, "num_critics": 4, "utd": 2}, "bc": TINY}


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _layout(pixels: bool) -> Layout:
    obs = {"state": Feature((STATE_DIM,), "float32")}
    if pixels:
        obs["camera.front"] = Feature(IMAGE, "uint8", is_image=True)
    return Layout(obs, LOW, HIGH, ("test_arm",))


def _algorithm(kind: str, pixels: bool, seed: int = 0, **extra: object) -> Algorithm:
    torch.manual_seed(seed)
    params = {**SMALL[kind], **(PIXEL if pixels else {}), **extra}
    return ALGORITHMS.build(kind, params, layout=_layout(pixels), device=torch.device("cpu"))


def _obs(g: torch.Generator, n: int, pixels: bool) -> dict[str, torch.Tensor]:
    obs = {"state": torch.randn(n, STATE_DIM, generator=g)}
    if pixels:
        obs["camera.front"] = torch.randint(0, 256, (n, *IMAGE), generator=g, dtype=torch.uint8)
    return obs


def _batch(seed: int, n: int, pixels: bool) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(
        observation=_obs(g, n, pixels),
        action=(torch.rand(n, ACTION_DIM, generator=g) * 2 - 1) * torch.from_numpy(HIGH),
        reward=torch.randn(n, generator=g),
        next_observation=_obs(g, n, pixels),
        terminated=(torch.rand(n, generator=g) < 0.3).float(),
        intervention=torch.rand(n, generator=g) < 0.5,
    )


def _request_batch(algo: Algorithm, seed: int, pixels: bool) -> Batch:
    return _batch(seed, algo.batch_request().batch_size, pixels)


CASES = [(kind, pixels) for kind in ("sac", "rlpd", "bc") for pixels in (False, True)]
IDS = [f"{k}-{'pixels' if p else 'state'}" for k, p in CASES]


@pytest.mark.parametrize(("kind", "pixels"), CASES, ids=IDS)
def test_update_returns_finite_scalars(kind: str, pixels: bool) -> None:
    algo = _algorithm(kind, pixels)
    for i in range(3):
        scalars = algo.update(_request_batch(algo, i, pixels))
    assert algo.updates == 3
    assert scalars and all(np.isfinite(v) for v in scalars.values()), scalars
    expected = {"bc_loss"} if kind == "bc" else {"critic_loss", "actor_loss", "alpha_loss", "alpha", "entropy"}
    assert expected <= set(scalars)


@pytest.mark.parametrize(("kind", "pixels"), CASES, ids=IDS)
def test_checkpoint_round_trip_resumes_identically(kind: str, pixels: bool) -> None:
    algo = _algorithm(kind, pixels, seed=0)
    for i in range(2):
        algo.update(_request_batch(algo, i, pixels))
    buf = io.BytesIO()
    torch.save(algo.state_dict(), buf)
    buf.seek(0)
    restored = _algorithm(kind, pixels, seed=1)  # different init: everything must come from the checkpoint
    restored.load_state_dict(torch.load(buf, weights_only=True))
    assert restored.updates == 2
    batch = _request_batch(algo, 9, pixels)
    torch.manual_seed(7)
    a = algo.update(batch)
    torch.manual_seed(7)
    b = restored.update(batch)
    assert a == pytest.approx(b, rel=1e-5, abs=1e-6)
    restored_actor = restored.state_dict()["actor"]
    for name, x in algo.state_dict()["actor"].items():
        torch.testing.assert_close(x, restored_actor[name], msg=name)


@pytest.mark.parametrize(("kind", "pixels"), CASES, ids=IDS)
def test_published_policy_rebuilds_and_acts(kind: str, pixels: bool) -> None:
    algo = _algorithm(kind, pixels)
    algo.update(_request_batch(algo, 0, pixels))
    spec, tensors = algo.policy()
    assert spec.kind == ("cnn" if pixels else "mlp")
    assert all(isinstance(t, np.ndarray) for t in tensors.values())
    policy = build_policy(spec, tensors, version=5)
    assert policy.version == 5 and policy.action_shape == (ACTION_DIM,) and policy.chunk_horizon == 1
    assert set(policy.observation_keys) == ({"state", "camera.front"} if pixels else {"state"})
    obs = {k: v.numpy() for k, v in _obs(torch.Generator().manual_seed(3), 4, pixels).items()}
    acted = policy.act(obs, deterministic=True)
    with torch.no_grad():
        expected = algo.actor({k: torch.from_numpy(v) for k, v in obs.items()})[2].numpy()
    np.testing.assert_allclose(acted, expected, rtol=1e-5, atol=1e-6)
    sampled = policy.act(obs)
    assert sampled.shape == (4, ACTION_DIM) and np.all(sampled >= LOW) and np.all(sampled <= HIGH)
    with pytest.raises(ValueError, match="lacks"):
        policy.act({"other": obs["state"]})
    with pytest.raises(ValueError, match="expects"):
        policy.act({**obs, "state": np.zeros((4, STATE_DIM + 1), np.float32)})


def test_termination_stops_bootstrapping_truncation_does_not() -> None:
    algo = _algorithm("sac", pixels=False)
    assert isinstance(algo, SAC)
    batch = _batch(0, 8, pixels=False)
    batch.terminated = torch.ones(8)
    torch.testing.assert_close(algo.td_target(batch, batch.next_observation), batch.reward)
    batch.terminated = torch.zeros(8)  # truncated or running: the discounted future stays
    assert not torch.allclose(algo.td_target(batch, batch.next_observation), batch.reward)


@pytest.mark.parametrize("backup_entropy", [True, False])
def test_backup_entropy_puts_the_entropy_bonus_in_the_td_target_or_not(backup_entropy: bool) -> None:
    """Off, the target is r + discount * min Q whatever alpha is (a peaked actor's log-densities of ~+10 per
    step would otherwise drive the soft value of a 0/1 task far below 0)."""
    algo = _algorithm("rlpd", pixels=False, backup_entropy=backup_entropy)
    batch = _batch(0, 8, pixels=False)
    batch.terminated = torch.zeros(8)

    def target(alpha: float) -> torch.Tensor:
        with torch.no_grad():
            algo.log_alpha.fill_(float(np.log(alpha)))
        torch.manual_seed(3)  # the same next actions and target heads both times
        return algo.td_target(batch, batch.next_observation)

    assert torch.allclose(target(0.01), target(5.0)) is not backup_entropy


def test_only_the_critic_trains_the_shared_image_encoder() -> None:
    algo = _algorithm("sac", pixels=True)
    assert isinstance(algo, SAC) and algo.actor.encoder is algo.critic.encoder
    before = {k: v.clone() for k, v in algo.encoder.state_dict().items()}
    features, _ = algo.update_critic(_batch(0, 8, pixels=True))
    after_critic = {k: v.clone() for k, v in algo.encoder.state_dict().items()}
    assert any(not torch.equal(before[k], after_critic[k]) for k in before)
    head_before = [p.clone() for p in algo.actor.head.parameters()]
    algo.update_actor(features)
    assert all(torch.equal(after_critic[k], v) for k, v in algo.encoder.state_dict().items())
    assert any(not torch.equal(a, b) for a, b in zip(head_before, algo.actor.head.parameters(), strict=True))
    # The target critic has its own copy of the encoder, moved by Polyak averaging only.
    assert algo.critic_target.encoder is not algo.encoder


@pytest.mark.parametrize("bc_encoder", [False, True])
def test_bc_encoder_lets_the_bc_term_train_the_shared_image_encoder(bc_encoder: bool) -> None:
    """With bc_encoder the critic step's loss carries the BC term into the encoder (same features, one conv
    pass), and RLPD's BC-only warm start steps the encoder; without, neither reaches it. A critic step is
    compared with a copy that skipped the BC term (zero weight) from the same start and random draws."""
    batch = _batch(0, 8, pixels=True)

    def after_critic_steps(bc_weight: float) -> list[torch.Tensor]:
        algo = _algorithm("rlpd", True, bc_weight=bc_weight, bc_encoder=bc_encoder, utd=1)
        torch.manual_seed(1)  # the same DrQ shifts and target subsets in both copies
        for _ in range(3):
            algo.update_critic(batch)
        return _snapshot(algo.encoder)

    with_bc, without_bc = after_critic_steps(3.0), after_critic_steps(0.0)
    assert any(not torch.equal(a, b) for a, b in zip(with_bc, without_bc, strict=True)) is bc_encoder

    algo = _algorithm("rlpd", True, bc_weight=1.0, bc_encoder=bc_encoder, utd=1, actor_pretrain_updates=1)
    encoder, critic_heads = _snapshot(algo.encoder), _snapshot(algo.critic.layers)
    assert algo.phase() == "actor_bc"
    algo.update(batch)
    assert _moved(encoder, algo.encoder) is bc_encoder and not _moved(critic_heads, algo.critic.layers)
    _, info = algo.update_critic(batch)
    assert ("encoder_bc_loss" in info) is bc_encoder
    # The target encoder still follows by Polyak averaging only.
    assert algo.critic_target.encoder is not algo.encoder


def test_random_shift_moves_images_within_the_padding() -> None:
    torch.manual_seed(0)
    image = torch.zeros(64, 9, 9, 1, dtype=torch.uint8)
    image[:, 4, 4] = 255
    shifted = random_shift(image, pad=2)
    assert shifted.shape == image.shape and shifted.dtype == torch.float32
    positions = {tuple(torch.nonzero(s[..., 0])[0].tolist()) for s in shifted}
    assert len(positions) > 5  # different offsets per image
    assert all(2 <= r <= 6 and 2 <= c <= 6 for r, c in positions)


def test_random_shift_by_gather_crops_exactly_as_the_slices_do() -> None:
    """The GPU path (two gathers, no host sync) is the CPU path's crop, pixel for pixel, at every offset."""
    g = torch.Generator().manual_seed(0)
    image = torch.randint(0, 256, (50, 10, 7, 3), generator=g, dtype=torch.uint8)
    offsets = torch.randint(0, 7, (50, 2), generator=g)  # pad 3: every offset, edges included
    sliced = random_shift(image, pad=3, offsets=offsets, gather=False)
    gathered = random_shift(image, pad=3, offsets=offsets, gather=True)
    assert torch.equal(sliced, gathered) and gathered.shape == (50, 10, 7, 3)
    assert not torch.equal(sliced, image.float())


def test_rlpd_defaults_are_the_paper_recipe() -> None:
    algo = ALGORITHMS.build("rlpd", {}, layout=_layout(False), device=torch.device("cpu"))
    request = algo.batch_request()
    assert request.tables == {"online": 0.5, "demos": 0.5}
    assert request.batch_size == 256 * algo.params.utd and algo.params.utd > 1
    assert algo.critic.num_critics == 10 and algo.critic.layer_norm
    q = algo.critic(torch.zeros(3, STATE_DIM), torch.zeros(3, ACTION_DIM))
    assert q.shape == (10, 3)
    custom = ALGORITHMS.build(
        "rlpd", {"tables": {"online": 0.5, "interventions": 0.5}}, layout=_layout(False), device=torch.device("cpu")
    )
    assert custom.batch_request().tables == {"online": 0.5, "interventions": 0.5}


def test_params_are_validated_by_name() -> None:
    assert {"sac", "rlpd", "bc"} <= set(ALGORITHMS.kinds())
    with pytest.raises(PluginError, match=r"algorithm\.params\.batch_sise"):
        ALGORITHMS.params("sac", {"batch_sise": 3}, where="algorithm.params")
    with pytest.raises(PluginError, match="loss"):
        ALGORITHMS.params("bc", {"loss": "l1"})
    with pytest.raises(PluginError, match=r"algorithm\.params: .*target_subset 3 exceeds num_critics 2"):
        ALGORITHMS.params("sac", {"num_critics": 2, "target_subset": 3}, where="algorithm.params")
    # Table shares are checked with the params at start (they used to fail the learner when it built the algorithm).
    bad_tables = [
        ({"online": 1.0, "demos": 0.0}, r"tables\.demos: Input should be greater than 0"),
        ({"online": -1}, r"tables\.online: Input should be greater than 0"),
        ({}, r"tables: .*at least 1 item"),
        ({"a/b": 1.0}, r"tables\.a/b\.\[key\]: String should match pattern"),
        ({"online": float("inf")}, r"tables\.online: Input should be a finite number"),
    ]
    for kind in ("sac", "rlpd", "bc", "flow_bc"):
        for tables, message in bad_tables:
            with pytest.raises(PluginError, match=r"algorithm\.params\." + message):
                ALGORITHMS.params(kind, {"tables": tables}, where="algorithm.params")
    with pytest.raises(ValueError, match="not in the observation"):
        _algorithm("sac", False, features=["camera.back"])


def test_features_select_what_the_networks_see() -> None:
    algo = _algorithm("sac", pixels=True, features=["camera.front"])  # pixels only: the state is left out
    spec, tensors = algo.policy()
    policy = build_policy(spec, tensors, version=1)
    assert policy.observation_keys == ("camera.front",)
    image = _obs(torch.Generator().manual_seed(0), 2, pixels=True)["camera.front"].numpy()
    assert policy.act({"camera.front": image}).shape == (2, ACTION_DIM)
    scalars = algo.update(_request_batch(algo, 0, pixels=True))
    assert np.isfinite(scalars["critic_loss"])


@pytest.mark.parametrize("loss", ["mse", "nll"])
def test_bc_fits_a_demonstrator(loss: str) -> None:
    algo = _algorithm("bc", pixels=False, loss=loss, lr=3e-3, batch_size=64)
    weights = torch.randn(STATE_DIM, ACTION_DIM, generator=torch.Generator().manual_seed(0))

    def demo_batch(seed: int) -> Batch:
        batch = _batch(seed, 64, pixels=False)
        batch.action = 0.5 * torch.tanh(0.5 * batch.observation["state"] @ weights) * torch.from_numpy(HIGH)
        return batch

    probe = demo_batch(999)

    def error() -> float:
        with torch.no_grad():
            mean = algo.actor(probe.observation)[2]
        return float((mean - probe.action).pow(2).mean())

    start = error()
    for i in range(300):
        algo.update(demo_batch(i))
    assert error() < 0.25 * start, (start, error())


def test_bc_only_interventions_ignores_autonomous_rows() -> None:
    algo = _algorithm("bc", pixels=False, only_interventions=True)
    batch = _batch(0, 8, pixels=False)
    batch.intervention = torch.zeros(8, dtype=torch.bool)
    before = [p.clone() for p in algo.actor.parameters()]
    scalars = algo.update(batch)
    assert scalars["rows"] == 0 and scalars["bc_loss"] == 0
    assert all(torch.equal(a, b) for a, b in zip(before, algo.actor.parameters(), strict=True))


def test_local_buffer_mixes_tables_by_share() -> None:
    buffer = Buffer()
    for name, value in (("online", 0.0), ("demos", 1.0)):
        table = buffer.table(name)
        for _ in range(20):
            table.add({"state": np.zeros(3, np.float32)}, np.zeros(2), value, {"state": np.zeros(3)}, False)
    request = _algorithm("rlpd", False).batch_request()
    batch = buffer.sample(request, np.random.default_rng(0), torch.device("cpu"))
    assert len(batch) == request.batch_size
    assert float(batch.reward.mean()) == pytest.approx(0.5)
    # An empty offline table gives its share to the online one instead of failing.
    only_online = Buffer({"online": buffer.tables["online"], "demos": Table()})
    assert float(only_online.sample(request, np.random.default_rng(0), torch.device("cpu")).reward.sum()) == 0.0


def test_utd_minibatches_each_mix_the_tables() -> None:
    """A sampler returns demos then online rows; every critic step must still see both (RLPD's 50/50)."""
    from cloud_learner.algorithms.sac import split

    batch = _batch(0, 16, pixels=False)
    batch.intervention = torch.arange(16) < 8  # rows 0-7 "demos", 8-15 "online", as a sampler lays them out
    parts = split(batch, 4)
    assert [len(p) for p in parts] == [4, 4, 4, 4]
    assert all(int(p.intervention.sum()) == 2 for p in parts)
    assert sorted(float(x) for p in parts for x in p.reward) == sorted(float(x) for x in batch.reward)


def test_bc_term_pulls_the_rlpd_actor_to_human_actions_and_decays() -> None:
    target = torch.tensor([0.5, -1.0])

    def trained(bc_weight: float) -> float:
        algo = _algorithm("rlpd", pixels=False, bc_weight=bc_weight, actor_lr=3e-3, init_alpha=0.01)
        for i in range(150):
            batch = _request_batch(algo, i, pixels=False)
            batch.action[batch.intervention] = target
            algo.update(batch)
        probe = _batch(999, 64, pixels=False)
        with torch.no_grad():
            mean = algo.actor(probe.observation)[2]
        return float((mean - target).pow(2).mean())

    assert trained(5.0) < 0.25 * trained(0.0)
    algo = _algorithm("rlpd", pixels=False, bc_weight=2.0, bc_decay_updates=10)
    assert algo.bc_weight() == 2.0
    algo.updates = 5
    assert algo.bc_weight() == pytest.approx(1.0)
    algo.updates = 20
    assert algo.bc_weight() == 0.0
    scalars = algo.update(_request_batch(algo, 0, pixels=False))
    assert scalars["bc_loss"] == 0.0  # decayed away: no BC term


def _snapshot(module: torch.nn.Module) -> list[torch.Tensor]:
    return [x.detach().clone() for x in module.parameters()]


def _moved(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(a, b) for a, b in zip(before, module.parameters(), strict=True))


def test_rlpd_warm_start_clones_the_demos_then_warms_the_critics_then_runs_rl() -> None:
    """actor_pretrain_updates: BC alone (critics and alpha untouched, the actor's mean reaches the demo
    actions at actor_pretrain_lr); critic_warmup_updates: critics alone (actor and alpha frozen); then RLPD,
    with the BC decay counted from there."""
    target = torch.tensor([0.5, -1.0])
    warm = {"actor_pretrain_updates": 60, "critic_warmup_updates": 5, "actor_pretrain_lr": 3e-3}
    algo = _algorithm("rlpd", False, **warm, init_alpha=0.1, bc_weight=2.0, bc_decay_updates=10)
    probe = _batch(999, 64, pixels=False)

    def bc_error() -> float:
        with torch.no_grad():
            return float((algo.actor(probe.observation)[2] - target).pow(2).mean())

    def demo_batch(i: int) -> Batch:
        batch = _request_batch(algo, i, pixels=False)
        batch.intervention[:] = True
        batch.action[:] = target
        return batch

    start, critic, log_alpha = bc_error(), _snapshot(algo.critic), algo.log_alpha.detach().clone()
    assert algo.phase() == "actor_bc" and algo.bc_weight() == 2.0  # no decay before RL starts
    for i in range(60):
        scalars = algo.update(demo_batch(i))
    assert algo.actor_optimizer.param_groups[0]["lr"] == 3e-3
    assert set(scalars) == {"bc_loss", "alpha"} and bc_error() < 0.05 * start, (start, bc_error())
    assert not _moved(critic, algo.critic) and torch.equal(algo.log_alpha.detach(), log_alpha)

    assert algo.phase() == "critic_warmup"
    actor = _snapshot(algo.actor)
    for i in range(5):
        scalars = algo.update(demo_batch(100 + i))
    assert "critic_loss" in scalars and "actor_loss" not in scalars
    assert _moved(critic, algo.critic) and not _moved(actor, algo.actor)
    assert torch.equal(algo.log_alpha.detach(), log_alpha)

    assert algo.phase() == "rl" and algo.bc_weight() == 2.0  # the decay starts here, not at update 0
    scalars = algo.update(demo_batch(200))
    assert algo.actor_optimizer.param_groups[0]["lr"] == algo.p.actor_lr
    assert {"actor_loss", "q_pi", "bc_term"} <= set(scalars) and _moved(actor, algo.actor)
    assert not torch.equal(algo.log_alpha.detach(), log_alpha)
    algo.updates = 65 + 5
    assert algo.bc_weight() == pytest.approx(1.0)


def test_rlpd_warm_start_resumes_in_its_phase() -> None:
    """The phase follows the checkpointed update count: a learner resumed mid-warm-start stays in it."""
    algo = _algorithm("rlpd", False, actor_pretrain_updates=2, critic_warmup_updates=2)
    for i in range(3):
        algo.update(_request_batch(algo, i, pixels=False))
    buf = io.BytesIO()  # through bytes, as a checkpoint goes: a live state_dict shares Adam's moment tensors
    torch.save(algo.state_dict(), buf)
    buf.seek(0)
    restored = _algorithm("rlpd", False, seed=1, actor_pretrain_updates=2, critic_warmup_updates=2)
    restored.load_state_dict(torch.load(buf, weights_only=True))
    assert restored.phase() == algo.phase() == "critic_warmup"
    batch = _request_batch(algo, 9, pixels=False)
    torch.manual_seed(7)
    a = algo.update(batch)
    torch.manual_seed(7)
    assert restored.update(batch) == pytest.approx(a, rel=1e-5, abs=1e-6)
    assert restored.phase() == "rl"
    with pytest.raises(PluginError, match="actor_pretrain_updates"):
        ALGORITHMS.params("rlpd", {"actor_pretrain_updates": -1})


def test_state_normalization_is_published_and_checked() -> None:
    mean, std = [1.0, 2.0, 3.0, 4.0, 5.0], [0.5, 1.0, 2.0, 1.0, 0.1]
    algo = _algorithm("sac", pixels=False, state_mean={"state": mean}, state_std={"state": std})
    spec, tensors = algo.policy()
    policy = build_policy(spec, tensors, version=1)
    obs = _obs(torch.Generator().manual_seed(0), 3, pixels=False)
    with torch.no_grad():
        expected = algo.actor(obs)[2].numpy()
        raw = algo.actor.head(obs["state"])[2].numpy()  # the head without the standardization
    np.testing.assert_allclose(policy.act({"state": obs["state"].numpy()}, deterministic=True), expected, atol=1e-5)
    assert not np.allclose(expected, raw, atol=1e-3)
    with pytest.raises(ValueError, match="state_std"):
        _algorithm("sac", pixels=False, state_std={"state": [1.0, 2.0]})
    with pytest.raises(ValueError, match="state_std must be > 0"):
        _algorithm("sac", pixels=False, state_std={"state": [1.0, 0.0, 1.0, 1.0, 1.0]})


def _padded_batch(seed: int, n: int, real_dims: int, junk: float) -> Batch:
    """A shared-embodiment batch: 4-d actions, the first `real_dims` real, `junk` in the padded rest."""
    g = torch.Generator().manual_seed(seed)
    action = torch.rand(n, 4, generator=g) * 2 - 1
    mask = torch.zeros(n, 4, dtype=torch.bool)
    mask[:, :real_dims] = True
    return Batch(
        observation={"state": torch.randn(n, STATE_DIM, generator=g)},
        action=torch.where(mask, action, torch.full_like(action, junk)),
        reward=torch.randn(n, generator=g),
        next_observation={"state": torch.randn(n, STATE_DIM, generator=g)},
        terminated=torch.zeros(n),
        intervention=torch.ones(n, dtype=torch.bool),
        embodiment=torch.zeros(n, dtype=torch.int64),
        action_mask=mask,
    )


def _padded_sac(**extra: object) -> SAC:
    torch.manual_seed(0)
    layout = Layout({"state": Feature((STATE_DIM,), "float32")}, -np.ones(4, np.float32), np.ones(4, np.float32))
    params = {**TINY, "bc_weight": 1.0, **extra}
    return ALGORITHMS.build("sac", params, layout=layout, device=torch.device("cpu"))


def test_sac_honours_the_action_mask_of_a_padded_layout() -> None:
    """Padded action dims (a 2-d arm in a 4-d shared layout) take no part in SAC: what a sampler left
    there does not reach the critic, and the actor's outputs for them get no gradient from the
    log-prob, the critic or the BC term, so their weights stay as initialised."""
    a, b = _padded_sac(), _padded_sac()
    torch.manual_seed(1)
    info_a = a.update(_padded_batch(0, 16, real_dims=2, junk=0.0))
    torch.manual_seed(1)
    info_b = b.update(_padded_batch(0, 16, real_dims=2, junk=0.9))
    assert info_a["critic_loss"] == info_b["critic_loss"] and info_a["q"] == info_b["q"]
    for pa, pb in zip(a.critic.parameters(), b.critic.parameters(), strict=True):
        assert torch.equal(pa, pb)

    sac = _padded_sac()
    last = sac.actor.head.net[-1]  # outputs: 4 means, then 4 log-stds
    before = last.weight.detach().clone()
    for step in range(5):
        sac.update(_padded_batch(step, 16, real_dims=2, junk=0.5))
    padded_rows = [2, 3, 6, 7]
    assert torch.equal(last.weight.detach()[padded_rows], before[padded_rows])
    assert not torch.equal(last.weight.detach()[[0, 1, 4, 5]], before[[0, 1, 4, 5]])


def test_pixels_plus_state_downsampled_and_standardized_publish_the_same_policy() -> None:
    """The cnn policy carries image_size and the state statistics: the edge computes what the learner does."""
    mean, std = [1.0, 2.0, 3.0, 4.0, 5.0], [0.5, 1.0, 2.0, 1.0, 0.1]
    stats = {"state_mean": {"state": mean}, "state_std": {"state": std}}
    algo = _algorithm("rlpd", pixels=True, image_size=6, channels=[4], strides=[1], image_pad=1, **stats)
    spec, tensors = algo.policy()
    config = json.loads(spec.config_json)
    assert (config["image_size"], config["state_mean"], config["state_std"]) == (6, mean, std)
    assert config["image_shapes"] == [list(IMAGE)]  # the policy still takes the camera's own frames
    policy = build_policy(spec, tensors, version=1)
    obs = _obs(torch.Generator().manual_seed(0), 3, pixels=True)
    with torch.no_grad():
        expected = algo.actor(obs)[2].numpy()
        unscaled = algo.actor.head(
            torch.cat([algo.encoder.cameras["camera_front"](obs["camera.front"]), obs["state"]], dim=-1)
        )[2].numpy()
    np.testing.assert_allclose(
        policy.act({k: v.numpy() for k, v in obs.items()}, deterministic=True), expected, atol=1e-5
    )
    assert not np.allclose(expected, unscaled, atol=1e-3)
    # the convs see 6x6 frames: prepare() gives them, and the 12x12 frame equals its 2x2 mean-pooled version
    small = algo.encoder.prepare(obs)["camera.front"]
    assert tuple(small.shape) == (3, 6, 6, 3)
    pooled = obs["camera.front"].float().reshape(3, 6, 2, 6, 2, 3).mean(dim=(2, 4))
    torch.testing.assert_close(small, pooled)
    with torch.no_grad():
        torch.testing.assert_close(algo.encoder({**obs, "camera.front": pooled}), algo.encoder(obs))
    assert np.isfinite(list(algo.update(_request_batch(algo, 0, pixels=True)).values())).all()
