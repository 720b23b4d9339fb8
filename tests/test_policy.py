"""Policies rebuild from PolicySpec + named tensors and act within bounds."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests import helpers
from user.policy import (
    Policy,
    SquashedGaussianActor,
    build_policy,
    known_policy_kinds,
    policy_spec_for,
)
from user.v1 import learner_pb2

CONFIG = {
    "obs_keys": ["state"],
    "obs_dim": 6,
    "action_dim": 3,
    "hidden": [32, 32],
    "action_low": [-1.0, -2.0, 0.0],
    "action_high": [1.0, 2.0, 0.5],
}


def _tensors(seed: int = 0) -> dict[str, np.ndarray]:
    return helpers.random_weights(CONFIG, 1, seed).tensors


def _obs(batch: int, seed: int = 1) -> dict[str, np.ndarray]:
    return {"state": np.random.default_rng(seed).normal(size=(batch, 6)).astype(np.float32) * 5}


def test_build_and_act_shapes_and_bounds() -> None:
    policy = build_policy(policy_spec_for(CONFIG), _tensors(), version=7)
    assert isinstance(policy, Policy)
    assert policy.version == 7 and policy.spec.kind == "sac_mlp"
    assert "sac_mlp" in known_policy_kinds()
    for deterministic in (True, False):
        act = policy.act(_obs(64), deterministic=deterministic)
        assert act.shape == (64, 3) and act.dtype == np.float32
        assert np.all(act >= np.array(CONFIG["action_low"]) - 1e-6)
        assert np.all(act <= np.array(CONFIG["action_high"]) + 1e-6)


def test_deterministic_is_repeatable_and_matches_actor() -> None:
    tensors = _tensors()
    policy = build_policy(policy_spec_for(CONFIG), tensors, version=1)
    obs = _obs(8)
    a1 = policy.act(obs, deterministic=True)
    a2 = policy.act(obs, deterministic=True)
    np.testing.assert_array_equal(a1, a2)
    # Weights were copied: mutating the source arrays leaves the policy alone.
    for arr in tensors.values():
        arr[...] = 0.0
    np.testing.assert_array_equal(policy.act(obs, deterministic=True), a1)
    stochastic = policy.act(obs, deterministic=False)
    assert not np.allclose(stochastic, a1)


def test_actor_log_prob_is_finite() -> None:
    actor = SquashedGaussianActor(4, 2, [16], [-1, -1], [1, 1])
    action, logp, mean = actor(torch.randn(10, 4) * 100)
    assert action.shape == (10, 2) and logp.shape == (10,) and mean.shape == (10, 2)
    assert torch.isfinite(logp).all()


def test_bad_tensors_raise_value_error() -> None:
    spec = policy_spec_for(CONFIG)
    tensors = _tensors()
    renamed = {("x." + k if i == 0 else k): v for i, (k, v) in enumerate(tensors.items())}
    with pytest.raises(ValueError, match="do not match"):
        build_policy(spec, renamed, version=1)
    missing = dict(list(tensors.items())[1:])
    with pytest.raises(ValueError, match="missing"):
        build_policy(spec, missing, version=1)
    name = next(iter(tensors))
    wrong_shape = {**tensors, name: np.zeros((3, 3), np.float32)}
    with pytest.raises(ValueError, match="shape"):
        build_policy(spec, wrong_shape, version=1)


def test_bad_spec_and_observation_raise_value_error() -> None:
    with pytest.raises(ValueError, match="unknown policy kind"):
        build_policy(learner_pb2.PolicySpec(kind="nope", config_json="{}"), {}, version=1)
    with pytest.raises(ValueError, match="JSON"):
        build_policy(learner_pb2.PolicySpec(kind="sac_mlp", config_json="{"), {}, version=1)
    bad = dict(CONFIG)
    del bad["obs_dim"]
    with pytest.raises(ValueError, match="missing"):
        build_policy(learner_pb2.PolicySpec(kind="sac_mlp", config_json=json.dumps(bad)), _tensors(), version=1)
    policy = build_policy(policy_spec_for(CONFIG), _tensors(), version=1)
    with pytest.raises(ValueError, match="features"):
        policy.act({"state": np.zeros((2, 5), np.float32)})
    with pytest.raises(ValueError, match="lacks"):
        policy.act({"other": np.zeros((2, 6), np.float32)})
