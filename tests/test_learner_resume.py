"""Resuming a learner never throws training state away: a checkpoint the config cannot resume fails that
experiment (named field, nothing written), an unreadable newest checkpoint falls back to the previous one,
configured learning rates and stored normalization statistics apply after a restore, and an experiment that
cannot be built fails alone. Real control (SQLite), replay (LMDB), learner gRPC service, checkpoints on disk."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import torch

from cloud_learner.algorithm import Feature, Layout
from cloud_learner.checkpoint import LATEST, CheckpointError, list_checkpoints, load_latest, save_checkpoint
from cloud_learner.learner import (
    Learner,
    LearnerError,
    build_algorithm,
    checkpoint_state,
    restore_checkpoint,
    trained_with,
)
from cloud_learner.server import LearnerService
from services.control.server import ControlService
from services.replay.server import ReplayService
from tests.helpers import wait_for
from tests.test_control_experiments import AUTH, Edge, team_spec
from tests.test_learner import sac_batch
from user.config import ExperimentConfig, StackConfig
from user.experiments import layout_for, parse_definition
from user.registry import PluginError
from user.rpc import make_channel
from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc
from user.weights import WeightStore

STATE, ACT = 6, 3
LAYOUT = Layout({"state": Feature((STATE,), "float32")}, -torch.ones(ACT).numpy(), torch.ones(ACT).numpy())
ELSEWHERE = "use another learner.checkpoint_dir or experiment name"


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def exp(name: str = "e", **kw: Any) -> ExperimentConfig:
    return ExperimentConfig.model_validate({"name": name, **kw})


def sac(**params: Any) -> dict[str, Any]:
    return {"kind": "sac", "params": {"batch_size": 16, **params}}


def trained(e: ExperimentConfig, updates: int = 2, stats: dict[str, Any] | None = None, layout: Layout = LAYOUT):
    torch.manual_seed(0)
    algo = build_algorithm(0, e, layout, "cpu", stats)
    for i in range(updates):
        batch = sac_batch(i)
        batch.observation = {"state": batch.observation["state"]}
        batch.next_observation = {"state": batch.next_observation["state"]}
        algo.update(batch)
    return algo


# --------------------------------------------------------------------------- what the checkpoint was trained with


def test_a_checkpoint_of_other_params_or_another_algorithm_is_refused_naming_the_field(tmp_path: Path) -> None:
    old = exp(algorithm=sac(hidden=[64, 64]))
    ckpt = checkpoint_state(trained(old), "sac", 3, LAYOUT, config=trained_with(old))

    def restore(new: ExperimentConfig) -> int:
        algo = build_algorithm(0, new, LAYOUT, "cpu")
        return restore_checkpoint(algo, ckpt, new.algorithm.kind, LAYOUT, tmp_path, trained_with(new), "experiments[0]")

    with pytest.raises(LearnerError) as err:
        restore(exp(algorithm=sac(hidden=[32, 32])))
    assert str(err.value) == (
        f"experiments[0].algorithm.params.hidden: the checkpoint in {tmp_path} was trained with [64, 64], "
        f"the config says [32, 32]; {ELSEWHERE}"
    )
    with pytest.raises(LearnerError, match=r"experiments\[0\]\.algorithm\.kind: .* trained with 'sac', .* 'rlpd'"):
        restore(exp(algorithm={"kind": "rlpd", "params": {"hidden": [64, 64]}}))
    with pytest.raises(LearnerError, match=r"algorithm\.params\.init_alpha: .* 0\.1, the config says 0\.5"):
        restore(exp(algorithm=sac(hidden=[64, 64], init_alpha=0.5)))  # only the init: a resume would ignore it
    # What only steers the next updates may change; spelled-out defaults are no change.
    assert restore(exp(algorithm=sac(hidden=[64, 64], actor_lr=1e-4, utd=2, batch_size=8, gamma=0.95))) == 3


def test_an_old_checkpoint_that_does_not_load_is_a_learner_error(tmp_path: Path) -> None:
    """Checkpoints written before `trained_with` are checked for kind and layout only; one of other widths
    used to raise torch's RuntimeError from load_state_dict, now the message says what to do."""
    old = checkpoint_state(trained(exp(algorithm=sac(hidden=[64, 64]))), "sac", 1, LAYOUT)
    assert "trained_with" not in old
    new = exp(algorithm=sac(hidden=[32, 32]))
    with pytest.raises(LearnerError, match=rf"experiments\[0\]: the checkpoint in .* does not fit .*; {ELSEWHERE}"):
        restore_checkpoint(
            build_algorithm(0, new, LAYOUT, "cpu"), old, "sac", LAYOUT, tmp_path, trained_with(new), "experiments[0]"
        )


# --------------------------------------------------------------------------- unreadable checkpoints


def test_an_unreadable_newest_checkpoint_falls_back_to_the_previous_one_and_nothing_good_is_deleted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    for updates in (100, 200, 300):
        save_checkpoint(tmp_path, {"updates": updates, "w": torch.full((64,), float(updates))})
    newest = tmp_path / "ckpt-000000300.pt"
    with newest.open("r+b") as f:
        f.truncate(1000)
    with caplog.at_level(logging.WARNING, logger="cloud_learner.checkpoint"):
        state = load_latest(tmp_path)
    assert state is not None and state["updates"] == 200
    assert any("checkpoint unreadable" in r.getMessage() for r in caplog.records)
    # The run goes on from 200: its own checkpoints are kept, the skipped file is neither read nor deleted.
    save_checkpoint(tmp_path, {"updates": 210})
    save_checkpoint(tmp_path, {"updates": 220})
    names = [p.name for p in list_checkpoints(tmp_path)]
    assert names == ["ckpt-000000200.pt", "ckpt-000000210.pt", "ckpt-000000220.pt", "ckpt-000000300.pt"]
    assert load_latest(tmp_path)["updates"] == 220  # type: ignore[index]
    (tmp_path / LATEST).write_text("ckpt-000000300.pt\n")  # `latest` names the torn one: the next older below it
    assert load_latest(tmp_path)["updates"] == 220  # type: ignore[index]

    broken = tmp_path / "broken"
    save_checkpoint(broken, {"updates": 1})
    (broken / "ckpt-000000001.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="can be read"):  # never "no checkpoint": that would start over
        load_latest(broken)


# --------------------------------------------------------------------------- learning rates and statistics


@pytest.mark.parametrize(
    ("algorithm", "attr", "optimizers"),
    [
        (sac(actor_lr=1e-3, critic_lr=1e-3, alpha_lr=1e-3), "actor_lr critic_lr alpha_lr", "actor critic alpha"),
        ({"kind": "rlpd", "params": {"actor_lr": 1e-3, "num_critics": 2, "utd": 1}}, "actor_lr", "actor"),
        ({"kind": "bc", "params": {"lr": 1e-3}}, "lr", ""),
        ({"kind": "flow_bc", "params": {"lr": 1e-3, "hidden": 8, "image_size": 16}}, "lr", ""),
    ],
    ids=["sac", "rlpd", "bc", "flow_bc"],
)
def test_the_configured_learning_rate_applies_after_a_restore(
    algorithm: dict[str, Any], attr: str, optimizers: str, caplog: pytest.LogCaptureFixture
) -> None:
    first = exp(algorithm=algorithm)
    algo = build_algorithm(0, first, LAYOUT, "cpu")
    state = algo.state_dict()
    changed = {**algorithm["params"], **{name: 1e-5 for name in attr.split()}}
    again = exp(algorithm={"kind": algorithm["kind"], "params": changed})
    resumed = build_algorithm(0, again, LAYOUT, "cpu")
    with caplog.at_level(logging.INFO, logger="cloud_learner.algorithm"):
        resumed.load_state_dict(state)
    names = [f"{o}_optimizer" for o in optimizers.split()] or ["optimizer"]
    for name in names:
        assert [g["lr"] for g in getattr(resumed, name).param_groups] == [1e-5], name
    assert sum("learning rate from the config" in r.getMessage() for r in caplog.records) == len(names)


# --------------------------------------------------------------------------- config checks at start


BAD = {
    "a policy choice sac does not take": (
        {"algorithm": sac(hidden=[32, 32]), "policy": {"kind": "flow_vla"}},
        r"\.policy: algorithm 'sac' does not take a policy choice",
    ),
    "a zero width": ({"algorithm": sac(hidden=[0])}, r"\.algorithm\.params\.hidden\.0: .*greater than or equal to 1"),
    "a zero std": (
        {"algorithm": sac(state_std={"state": [1.0, 0.0]})},
        r"\.algorithm\.params\.state_std: .*state_std must be > 0",
    ),
    "no features": ({"algorithm": sac(features=[])}, r"\.algorithm\.params\.features: .*leave features out"),
    "channels without strides": (
        {"algorithm": sac(channels=[4, 8], strides=[2])},
        r"\.algorithm\.params: .*channels \[4, 8\] and strides \[2\] differ",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_what_needs_no_robots_is_refused_at_start_and_by_define(case: str, tmp_path: Path) -> None:
    definition, message = BAD[case]
    with pytest.raises(ValueError, match="definition" + message):  # Control.DefineExperiment's check
        parse_definition(json.dumps({"name": "g8", **definition}), "g8")
    cfg = StackConfig.model_validate({"auth": AUTH, "experiments": [{"name": "g8", **definition}]})
    with pytest.raises(PluginError, match=r"experiments\[0\]" + message):
        Learner(cfg, WeightStore())


def test_define_experiment_refuses_a_policy_choice_the_algorithm_does_not_take(tmp_path: Path) -> None:
    """The tester's repro A through control: it used to be accepted and then killed the learner."""
    cfg = stack_cfg(tmp_path, [{"name": "first"}])
    control = ControlService(cfg, start_metrics=False).start()
    try:
        stub = control_pb2_grpc.ControlStub(make_channel(control.address, cfg.auth))
        g8 = {"name": "g8", "robots": {"kinds": ["lang_reach_arm"]}, **BAD["a policy choice sac does not take"][0]}
        with pytest.raises(grpc.RpcError) as err:
            stub.DefineExperiment(control_pb2.DefineExperimentRequest(definition_json=json.dumps(g8)), timeout=30)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "definition.policy: algorithm 'sac' does not take a policy choice" in err.value.details()
        listed = stub.ListExperiments(control_pb2.ListExperimentsRequest(), timeout=5).experiments
        assert [e.name for e in listed] == ["first"]
    finally:
        control.stop()


def test_a_corrupt_pretrained_file_is_refused_at_start(tmp_path: Path) -> None:
    bad = tmp_path / "resnet18.safetensors"
    bad.write_bytes(b"\x00" * 100)
    params = {"backbone": "resnet18", "pretrained": str(bad)}
    with pytest.raises(ValueError, match=r"definition\.algorithm\.params\.pretrained: .*not a readable safetensors"):
        parse_definition(json.dumps({"name": "g8", "algorithm": sac(**params)}), "g8")


# --------------------------------------------------------------------------- a real learner


def stack_cfg(tmp_path: Path, experiments: list[dict[str, Any]]) -> StackConfig:
    cfg = StackConfig.model_validate({"auth": AUTH, "experiments": experiments})
    for section in (cfg.control, cfg.replay, cfg.learner):
        section.server.port = section.server.metrics_port = 0
        section.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.2
    cfg.control.state_path = tmp_path / "control.sqlite"
    cfg.replay.path, cfg.replay.map_size_mb, cfg.replay.commit_max_delay_ms = tmp_path / "replay", 64, 5.0
    cfg.edge.spool_dir = tmp_path / "spool"  # not the repo's runs/default/spool: tests share no outbox
    lc = cfg.learner
    lc.checkpoint_dir, lc.rpc_timeout_s, lc.min_transitions = tmp_path / "ckpt", 5.0, 10**9
    return cfg


@pytest.fixture
def services(tmp_path: Path) -> Iterator[Any]:
    started: list[Any] = []

    def start(experiments: list[dict[str, Any]]) -> StackConfig:
        cfg = stack_cfg(tmp_path, experiments)
        control = ControlService(cfg, start_metrics=False).start()
        started.append(control)
        cfg.replay.control_addr = cfg.learner.control_addr = control.address
        replay = ReplayService(cfg, start_metrics=False).start()
        started.append(replay)
        cfg.learner.replay_addr = replay.address
        return cfg

    yield start
    for service in reversed(started):
        service.stop()


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_experiments_that_cannot_start_fail_alone_and_write_no_checkpoint(services, tmp_path: Path) -> None:
    """The tester's repros in one learner: a run dir of another width (old checkpoints and new), features the
    robots lack, a preparing experiment whose checkpoint does not fit; each fails with its reason, writes
    nothing, and the last experiment resumes: normalize dropped keeps the stored statistics, a changed
    learning rate applies."""
    stats = {"state_mean": {"state": [0.5] * STATE}, "state_std": {"state": [2.0] * STATE}, "from_table": "demos"}
    experiments = [
        {"name": "stale", "robots": {"labels": {"team": "a"}}, "algorithm": sac(hidden=[32, 32])},
        {"name": "changed", "robots": {"labels": {"team": "b"}}, "algorithm": sac(hidden=[32, 32])},
        {"name": "nofeature", "robots": {"labels": {"team": "c"}}, "algorithm": sac(features=["nope"])},
        {
            "name": "norm",
            "robots": {"labels": {"team": "d"}},
            "algorithm": sac(hidden=[16]),
            "normalize": {"from_table": "demos", "min_steps": 10},
        },
        {"name": "ok", "robots": {"labels": {"team": "e"}}, "algorithm": sac(hidden=[16], actor_lr=1e-5)},
    ]
    cfg = services(experiments)
    root = Path(cfg.learner.checkpoint_dir)
    layout = layout_for(exp(), [team_spec("x", "a")])

    def seed(name: str, e: ExperimentConfig, config: bool, stats: dict[str, Any] | None = None) -> None:
        extra = {"pretrain_updates": 0, **({"normalization": stats} if stats else {})}
        algo = trained(e, updates=40, stats=stats, layout=layout)
        state = checkpoint_state(algo, "sac", 4, layout, extra, trained_with(e) if config else None)
        save_checkpoint(root / name, state)

    seed("stale", exp(algorithm=sac(hidden=[64, 64])), config=False)
    seed("changed", exp(algorithm=sac(hidden=[64, 64])), config=True)
    seed("norm", exp(algorithm=sac(hidden=[8])), config=True, stats=stats)
    trained_ok = exp(algorithm=sac(hidden=[16], actor_lr=1e-3), normalize={"from_table": "demos"})
    seed("ok", trained_ok, config=True, stats=stats)
    before = {name: files(root / name) for name in ("stale", "changed", "norm")}

    edge = Edge(cfg.learner.control_addr, "pc-1", [team_spec(f"{t}-0", t) for t in "abcde"])
    edge.client.start()
    learner = LearnerService(cfg, start_metrics=False).start()
    try:
        states = learner.learner.experiment_states
        failing = ("stale", "changed", "nofeature", "norm")
        wait_for(lambda: all(states[n].state == "failed" for n in failing), "four experiments failed", limit_s=60)
        wait_for(lambda: states["ok"].weight_version >= 1, "ok resumed and published", limit_s=60)
        stub = learner_pb2_grpc.LearnerStub(make_channel(learner.address, cfg.auth))
        try:
            reported = stub.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10).experiments
        except grpc.RpcError as err:
            raise AssertionError(err) from None
        errors = {e.name: e.error for e in reported}
        assert "experiments[0]: the checkpoint in" in errors["stale"] and "does not fit" in errors["stale"]
        assert errors["changed"] == (
            f"experiments[1].algorithm.params.hidden: the checkpoint in {root / 'changed'} was trained with "
            f"[64, 64], the config says [32, 32]; {ELSEWHERE}"
        )
        assert errors["nofeature"].startswith("experiments[2].algorithm.params: features ['nope'] are not in")
        assert errors["norm"].startswith("experiments[3].algorithm.params.hidden: the checkpoint in")
        assert not learner.learner.failed and states["ok"].state != "failed" and errors["ok"] == ""

        run = learner.learner.runs["ok"]
        assert run.algo.updates == 40  # resumed, not from scratch
        assert run.normalization == stats  # normalize dropped from the config: the stored statistics stay
        config = json.loads(learner.store.latest("ok").header.policy.config_json)
        assert config["state_mean"] == [0.5] * STATE and config["state_std"] == [2.0] * STATE
        assert [g["lr"] for g in run.algo.actor_optimizer.param_groups] == [1e-5]
    finally:
        learner.stop()
        edge.close()
    for name, kept in before.items():
        assert files(root / name) == kept, f"{name}'s checkpoints changed"
    assert not (root / "nofeature").exists() or not list_checkpoints(root / "nofeature")
    ok = list_checkpoints(root / "ok")
    assert [int(p.name[5:14]) for p in ok] == [40], "nothing trained, nothing new written, and never update 0"
