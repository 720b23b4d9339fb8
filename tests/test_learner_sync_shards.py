"""Sync mode over several replay shards: it counts env steps and samples across every shard, as async does
(it once read only the first shard). Real replay shards, control and learner; in-process servers."""

from __future__ import annotations

from pathlib import Path

from cloud_learner.replay_sampler import SHARD_SAMPLED
from tests.helpers import wait_for
from tests.test_edge_agent import AUTH, replay_stats, stack_cfg
from tests.test_replay_sampler import SPECS, Shard, shards  # noqa: F401  (the fixture)


def sampled(addr: str) -> float:
    return SHARD_SAMPLED.labels(addr)._value.get()


def test_sync_mode_counts_and_samples_every_shard(tmp_path: Path, shards: dict[str, Shard]) -> None:  # noqa: F811
    import torch

    from cloud_learner.learner import Learner
    from edge_agent.control_client import ControlClient
    from services.control.server import ControlService
    from user.weights import WeightStore

    torch.set_num_threads(1)
    control = ControlService(stack_cfg(tmp_path / "control"), start_metrics=False).start()
    specs = list(SPECS.values())
    edge = ControlClient(control.address, AUTH, "edge-a", specs, status_fn=list, on_command=lambda c: None)
    cfg = stack_cfg(tmp_path)
    lc = cfg.learner
    lc.mode, lc.sync_env_steps, lc.sync_updates = "sync", 100, 10
    lc.control_addr, lc.replay_addr = control.address, shards["a"].addr
    lc.replay_addrs = [s.addr for s in shards.values()]
    lc.checkpoint_dir, lc.hidden, lc.batch_size, lc.min_transitions = tmp_path / "ckpt", [16], 64, 50
    lc.rpc_timeout_s = 2.0
    learner = Learner(cfg, WeightStore())
    (state,) = learner.experiment_states.values()
    steps = {name: replay_stats(s.addr).steps for name, s in shards.items()}
    before = {name: sampled(s.addr) for name, s in shards.items()}
    try:
        assert edge.wait_registered(30)
        learner.start()
        wait_for(lambda: state.updates >= 10, "a sync round", limit_s=120)
    finally:
        learner.stop()
        edge.close()
        control.stop()
    assert not learner.failed
    assert state.env_steps == steps["a"] + steps["b"]  # both shards' robots counted
    assert all(sampled(s.addr) > before[name] for name, s in shards.items())  # both shards sampled
