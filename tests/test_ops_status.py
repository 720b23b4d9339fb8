"""What operators are told is true: a learner's failed experiment shows failed in `userctl exp status` / `exp ls`
and the `up` summary; success there counts only episodes nobody intervened in; config fields that would be
silently ignored (learner SAC shortcuts beside `experiments`, a misspelt up.target_experiment) are refused in one
line; a service without a token says so in one line, no thread traceback. Real control (in process), a real
`userctl learner` process, real edge ControlClients, real SQLite in tmp_path."""

from __future__ import annotations

import io
import json
import os
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from rich.console import Console

from edge_agent.control_client import ControlClient
from services.control.server import ControlService
from services.control.state import ControlState
from tests.helpers import wait_for
from tests.test_replay_store import spec
from user import cli
from user.config import AuthConfig, ConfigError, ExperimentConfig, RobotSelector, StackConfig, load_config
from user.rpc import make_channel
from user.up import Monitor, Snapshot, _print_summary, _summary
from user.v1 import control_pb2, control_pb2_grpc, learner_pb2, learner_pb2_grpc

ROOT = Path(__file__).resolve().parents[1]
AUTH = AuthConfig(token="test-token-0123456789")
BASE = ["--set", f"auth.token={AUTH.token}"]


@pytest.fixture(autouse=True)
def _no_env_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in list(os.environ):
        if key.startswith("USER__"):
            monkeypatch.delenv(key)


def control_service(tmp_path: Path, exps: list[ExperimentConfig]) -> ControlService:
    cfg = StackConfig(auth=AUTH, experiments=exps)
    cfg.control.server.port = cfg.control.server.metrics_port = 0
    cfg.control.server.grace_s = 0.5
    cfg.control.heartbeat_interval_s = 0.05
    cfg.control.state_path = tmp_path / "control.sqlite"
    return ControlService(cfg, start_metrics=False).start()


def stub(control: ControlService) -> control_pb2_grpc.ControlStub:
    return control_pb2_grpc.ControlStub(make_channel(control.address, AUTH))


def get(control: ControlService, name: str) -> control_pb2.ExperimentInfo:
    return stub(control).GetExperiment(control_pb2.GetExperimentRequest(name=name), timeout=5)


def edge(control: ControlService, specs: list, statuses: list) -> ControlClient:
    client = ControlClient(control.address, AUTH, "lab-pc-1", specs, lambda: statuses, lambda c: (True, "done"))
    assert client.wait_registered(10)
    return client


# --------------------------------------------------------------------------- 10: a learner's failed experiment


@pytest.fixture
def learner_proc(tmp_path: Path) -> Iterator[list[subprocess.Popen]]:
    procs: list[subprocess.Popen] = []
    yield procs
    for proc in procs:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def test_an_experiment_the_learner_cannot_train_shows_failed_with_its_error(
    tmp_path: Path, learner_proc: list[subprocess.Popen], capsys: pytest.CaptureFixture[str]
) -> None:
    """One experiment selecting robots of different shapes without shared_embodiment: control holds both
    robots once the learner fails it, and `exp status`, `exp ls` and the up summary must say it failed, and why."""
    both = ExperimentConfig(name="both", robots=RobotSelector(ids=["arm-0", "arm-1"]))
    control = control_service(tmp_path, [both])
    client = edge(control, [spec("arm-0"), spec("arm-1", obs_dim=7)], [])
    config = tmp_path / "learner.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "auth": {"token": AUTH.token},
                "log_json": False,
                "learner": {
                    "server": {"port": 0, "metrics_port": 0, "grace_s": 0.5},
                    "control_addr": control.address,
                    "replay_addr": "127.0.0.1:1",  # never reached: the experiment fails on its robots' layout
                    "checkpoint_dir": str(tmp_path / "ckpt"),
                    "weights_shm_dir": None,
                    "replay_shm_dir": None,
                },
                "experiments": [both.model_dump(mode="json")],
            }
        )
    )
    ready = tmp_path / "learner.json"
    cmd = [sys.executable, "-m", "user.cli", "learner", "-c", str(config), "--ready-file", str(ready)]
    learner_proc.append(
        subprocess.Popen(cmd, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)}, stderr=subprocess.DEVNULL)
    )
    try:
        info = wait_for(lambda: (e := get(control, "both")).learner_failed and e, "learner reports both failed", 120)
        # control holds the robots of an experiment its learner cannot train: they record nothing meanwhile
        assert info.state == control_pb2.EXPERIMENT_STATE_RUNNING and list(info.leased_robots) == []
        assert "different observations or actions" in info.learner_error
        assert [w.startswith("learner@") for w in info.learners] == [True]

        base = ["--control", control.address, *BASE]
        assert cli.main(["exp", "status", "both", *base]) == 0
        out = capsys.readouterr().out
        assert "experiment both: failed (learner)" in out
        assert "learner error: experiment both: robots arm-0 (test) and arm-1 (test) have different" in out
        assert cli.main(["exp", "ls", *base]) == 0
        assert "failed (learner)" in capsys.readouterr().out

        # The up summary reads the learner's own GetStatus: the same failure, not "sac, 0 updates".
        port = json.loads(ready.read_text())["grpc_port"]
        learner = learner_pb2_grpc.LearnerStub(make_channel(f"127.0.0.1:{port}", AUTH))
        status = learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=5)
        robots = list(stub(control).ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots)
        cfg = StackConfig(auth=AUTH, experiments=[both])
        summary = _summary(cfg, "budget exhausted", None, Snapshot(1.0, robots, status, None), [], {}, 1.0)
        row = printed_summary(summary, tmp_path)["experiment both"]
        assert row.startswith("FAILED: experiment both: robots arm-0 (test) and arm-1 (test) have different")
        assert row.endswith("sac, 0 updates, weights v0, success -")
        assert "different observations or actions" in summary["learner"]["experiments"]["both"]["error"]
    finally:
        client.close()
        control.stop()


def test_control_bounds_a_learner_failure_and_clears_it_once_the_learner_reports_it_no_more(tmp_path: Path) -> None:
    control = control_service(tmp_path, [ExperimentConfig(name="reach")])
    s = stub(control)
    worker = control_pb2.WorkerInfo(worker_id="learner@gpu-1:50054", kind="learner", experiments=["reach"])
    worker.failed["reach"] = "x" * 5000  # an exception's text: kept bounded
    s.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=worker), timeout=5)
    try:
        info = get(control, "reach")
        assert info.learner_failed and info.learner_error == "x" * 1024
        worker.failed.clear()
        s.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=worker), timeout=5)
        assert not get(control, "reach").learner_failed
        bad = control_pb2.WorkerInfo(worker_id="learner@gpu-1:50054", kind="learner")
        bad.failed["not a name"] = "?"
        with pytest.raises(Exception, match="INVALID_ARGUMENT"):
            s.RegisterWorker(control_pb2.RegisterWorkerRequest(worker=bad), timeout=5)
    finally:
        control.stop()


# --------------------------------------------------------------------------- 16: success without human help


def helped_status(n: int) -> control_pb2.RobotStatus:
    """n episodes the expert drove steps of, every one a success (HG-DAgger while the policy learns nothing)."""
    eps = [
        control_pb2.EpisodeSummary(
            episode_id=f"ep-{i}", length=50, success=True, policy_version=1, intervention_steps=9
        )
        for i in range(n)
    ]
    return control_pb2.RobotStatus(robot_id="arm-0", episodes=n, successes=n, policy_version=1, new_episodes=eps)


def test_success_counts_only_episodes_without_interventions(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lang = ExperimentConfig(name="lang", robots=RobotSelector(ids=["arm-0"]))
    control = control_service(tmp_path, [lang])
    statuses = [helped_status(31)]
    client = edge(control, [spec("arm-0")], statuses)
    base = ["--control", control.address, *BASE]
    try:
        info = wait_for(lambda: (e := get(control, "lang")).episodes == 31 and e, "31 episodes")
        assert (info.successes, info.unhelped_episodes, info.unhelped_successes) == (31, 0, 0)
        assert cli.main(["exp", "status", "lang", *base]) == 0
        out = capsys.readouterr().out
        assert "episodes 31 (31 with interventions), success - [100% all]," in out
        assert "success 100%" not in out
        assert cli.main(["exp", "ls", *base]) == 0
        assert "- [100% all]" in capsys.readouterr().out

        # Two the policy did alone, one a success: 50 % of the unhelped, 97 % of all.
        alone = [
            control_pb2.EpisodeSummary(episode_id=f"alone-{i}", length=50, success=i == 0, policy_version=2)
            for i in range(2)
        ]
        statuses[0] = control_pb2.RobotStatus(robot_id="arm-0", episodes=33, policy_version=2, new_episodes=alone)
        wait_for(lambda: get(control, "lang").episodes == 33, "33 episodes")
        assert cli.main(["exp", "status", "lang", *base]) == 0
        out = capsys.readouterr().out
        assert "success 50% [97% all]" in out
        assert "  arm-0                    yes     yes           33      50%" in out

        # The up summary: episodes as control lists them, the learner waiting for data at weights v1.
        robots = list(stub(control).ListRobots(control_pb2.ListRobotsRequest(), timeout=5).robots)
        mon = object.__new__(Monitor)
        mon.episodes, mon.earlier, mon.session_start_ns = {}, set(), 0
        mon.record_episodes(robots, 1.0)
        helped_only = [e for e in mon.ordered() if e.intervention_steps]
        learner = learner_pb2.LearnerStatus(
            experiments=[
                learner_pb2.ExperimentStatus(
                    name="lang", algorithm="flow_bc", weight_version=1, state="waiting_for_data"
                )
            ]
        )
        cfg = StackConfig(auth=AUTH, experiments=[lang])
        summary = _summary(cfg, "budget exhausted", None, Snapshot(1.0, robots, learner, None), helped_only, {}, 1.0)
        rows = printed_summary(summary, tmp_path)
        assert rows["experiment lang"] == "flow_bc, 0 updates, weights v1, success - [100 % all]"
        assert rows["success, last episodes of lang"] == "- [100 % all]"
        assert rows["episodes with interventions"] == "31 (left out of success, counted in the all-episodes rate)"
    finally:
        client.close()
        control.stop()

    # A restarted control totals the history from SQLite the same way.
    control = control_service(tmp_path, [lang])
    try:
        info = get(control, "lang")
        assert (info.episodes, info.successes, info.unhelped_episodes, info.unhelped_successes) == (33, 32, 2, 1)
    finally:
        control.stop()


def test_a_state_file_from_before_the_column_counts_its_helped_episodes(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    state = ControlState(path)
    helped = control_pb2.EpisodeSummary(robot_id="arm-0", episode_id="h", success=True, intervention_steps=4)
    alone = control_pb2.EpisodeSummary(robot_id="arm-0", episode_id="a", success=True)
    state.add_episodes([helped, alone], "lang")
    state.close()
    db = sqlite3.connect(path)
    db.execute("ALTER TABLE episodes DROP COLUMN intervention_steps")  # what an older control wrote
    db.commit()
    db.close()
    state = ControlState(path)
    try:
        assert state.episode_totals() == [("lang", "arm-0", 2, 2, 0.0, 1, 1)]
    finally:
        state.close()


def printed_summary(summary: dict, run_dir: Path) -> dict[str, str]:
    """The summary table as the operator reads it: row label -> its text (rows wider than the console fold)."""
    console = Console(width=400, record=True, file=io.StringIO())
    _print_summary(console, summary, run_dir)
    rows = {}
    for line in console.export_text().splitlines():
        cells = [c.strip() for c in line.split("│")]
        if len(cells) == 4:  # "│ label │ text │"
            rows[cells[1]] = cells[2]
    return rows


# --------------------------------------------------------------------------- 5, 6: fields that would be ignored

SHORTCUTS = ["hidden=[16]", "batch_size=32", "gamma=0.5", "tau=0.01", "actor_lr=0.01", "init_alpha=0.2"]


@pytest.mark.parametrize("override", SHORTCUTS)
def test_a_learner_sac_shortcut_beside_experiments_is_refused(override: str) -> None:
    name = override.split("=")[0]
    with pytest.raises(ConfigError) as err:
        load_config(ROOT / "configs" / "demo.yaml", [f"learner.{override}"], environ={})
    message = str(err.value)
    assert f"learner.{name}: ignored because `experiments` is set" in message
    assert f"experiments[i].algorithm.params.{name} instead" in message and "\n" not in message
    # Without experiments it is the default experiment's param, as documented.
    (default,) = load_config(None, [f"learner.{override}"], environ={}).resolved_experiments()
    assert default.algorithm.params[name] == yaml.safe_load(override.split("=")[1])


def test_a_learner_sac_shortcut_is_refused_from_the_file_and_the_environment(tmp_path: Path) -> None:
    path = tmp_path / "stack.yaml"
    path.write_text("learner:\n  gamma: 0.5\nexperiments:\n  - name: reach\n")
    with pytest.raises(ConfigError, match=r"learner\.gamma: ignored"):
        load_config(path, environ={})
    with pytest.raises(ConfigError, match=r"learner\.critic_lr: ignored"):
        load_config(ROOT / "configs" / "hgdagger.yaml", environ={"USER__LEARNER__CRITIC_LR": "0.01"})
    # Its default value changes nothing, so it may stay in a file that gains experiments.
    path.write_text("learner:\n  gamma: 0.95\nexperiments:\n  - name: reach\n")
    assert load_config(path, environ={}).learner.gamma == 0.95


def test_userctl_exits_2_on_an_ignored_shortcut_or_an_unknown_target(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    demo = str(ROOT / "configs" / "demo.yaml")
    assert cli.main(["learner", "-c", demo, "--set", "learner.hidden=[16]"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "learner.hidden:" in err and "experiments[i].algorithm.params.hidden" in err
    runs = tmp_path / "runs"
    argv = ["up", "-c", demo, "--set", "up.target_experiment=reahc", "--set", f"up.runs_dir={runs}"]
    argv += ["--set", "up.budget_s=1", "--set", "up.console=false"]  # were it accepted: a short run, not 10 min
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "up.target_experiment: 'reahc' is not an experiment of this config; known: reach, pick" in err
    assert not runs.exists()  # nothing started


def test_up_target_experiment_names_a_known_experiment() -> None:
    assert load_config(ROOT / "configs" / "demo.yaml", ["up.target_experiment=pick"], environ={}).up.target_experiment
    assert load_config(None, ["up.target_experiment=default"], environ={})  # the implicit one
    with pytest.raises(ConfigError, match=r"up\.target_experiment: 'reach' .* known: default"):
        load_config(None, ["up.target_experiment=reach"], environ={})


# --------------------------------------------------------------------------- 13: no token, one line


@pytest.mark.parametrize("service", ["learner", "inference"])
def test_a_service_without_a_token_says_so_in_one_line(tmp_path: Path, service: str) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("USER__") and k != "USER_TOKEN"}
    env["PYTHONPATH"] = str(ROOT)
    sets = [f"{service}.server.port=0", f"{service}.server.metrics_port=0", f"{service}.weights_shm_dir=null"]
    sets += [f"learner.checkpoint_dir={tmp_path / 'ckpt'}", "learner.replay_shm_dir=null"]
    cmd = [sys.executable, "-m", "user.cli", service, "-c", str(ROOT / "configs" / "compose.yaml")]
    for item in sets:
        cmd += ["--set", item]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        f"userctl {service}: auth.token: auth is enabled but no token is set "
        "(auth.token, $USER_TOKEN or auth.token_file)"
    ], proc.stderr
