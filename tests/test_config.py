"""Typed stack config: every shipped config validates, bad values fail naming the dotted field,
precedence is file < environment < --set, and userctl exits 2 on a bad config before starting anything."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from user import cli
from user.config import AuthConfig, ConfigError, StackConfig, load_config

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


@pytest.fixture(autouse=True)
def _no_env_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in list(os.environ):
        if key.startswith("USER__"):
            monkeypatch.delenv(key)


@pytest.fixture
def small_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "stack.yaml"
    path.write_text("learner:\n  batch_size: 32\n  gamma: 0.9\ncontrol:\n  server: {port: 6001}\n")
    return path


def test_the_shipped_configs_are_found() -> None:
    assert "compose.yaml" in {p.name for p in CONFIGS}


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_shipped_config_validates(path: Path) -> None:
    cfg = load_config(path, environ={})
    assert isinstance(cfg, StackConfig)
    assert cfg.edge.robots, "a stack without robots learns nothing"


def test_no_file_gives_the_defaults() -> None:
    assert load_config(None, environ={}) == StackConfig()


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("learner.batch_size=-1", "learner.batch_size"),
        ("learner.batch_size=lots", "learner.batch_size"),
        ("learner.gamma=1.5", "learner.gamma"),
        ("control.server.port=70000", "control.server.port"),
        ("replay.map_size_mb=1", "replay.map_size_mb"),
        ("edge.mode=turbo", "edge.mode"),
        ("edge.policy_source=cloud", "edge.policy_source"),
        ("edge.robots=[{id: 'no spaces allowed'}]", "edge.robots.0.id"),
        ("edge.robots=[{id: arm-0}, {kind: sim_reach_arm}]", "edge.robots.1.id"),
        ("log_level=LOUD", "log_level"),
        ("inference.matmul_precision=medium", "inference.matmul_precision"),
        ("inference.continuous_batching=sometimes", "inference.continuous_batching"),
        ("replay.cache_prefault=sometimes", "replay.cache_prefault"),
        ("up.max_restarts=-1", "up.max_restarts"),
        ("edge.replug_s=-1", "edge.replug_s"),
        ("learner.weights_shm_dir=[1]", "learner.weights_shm_dir"),
        ("learner.replay_shm_dir=[1]", "learner.replay_shm_dir"),
        ("learner.replay_encoded_frames=sometimes", "learner.replay_encoded_frames"),
        ("replay.shm_slots=0", "replay.shm_slots"),
        ("replay.shm_max_mb=0", "replay.shm_max_mb"),
        ("experiments=[{name: a, table: 'lab a'}]", "experiments.0.table"),  # replay would refuse every step
    ],
)
def test_a_bad_value_names_its_dotted_field(override: str, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(None, [override], environ={})
    assert f"{field}:" in str(err.value)


def test_a_bad_value_in_the_file_names_its_field(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("edge:\n  robots:\n    - id: arm-0\n    - id: 'arm 1'\n")
    with pytest.raises(ConfigError, match=r"edge\.robots\.1\.id:"):
        load_config(path, environ={})


def test_duplicate_robot_ids_are_rejected() -> None:
    with pytest.raises(ConfigError, match="robot ids must be unique"):
        load_config(None, ["edge.robots=[{id: arm-0}, {id: arm-0}]"], environ={})


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("learner.batch_sise=64", "learner.batch_sise"),
        ("lerner.batch_size=64", "lerner"),
        ("edge.robots=[{id: a, x: 1}]", "edge.robots.0.x"),
    ],
)
def test_an_unknown_field_is_rejected(override: str, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(None, [override], environ={})
    assert f"{field}:" in str(err.value)
    assert "not permitted" in str(err.value)


def test_an_unknown_field_in_the_file_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "typo.yaml"
    path.write_text("replay:\n  pth: /data/replay\n")
    with pytest.raises(ConfigError, match=r"replay\.pth:"):
        load_config(path, environ={})


def test_unreadable_or_malformed_files_fail_clearly(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "missing.yaml", environ={})
    listing = tmp_path / "list.yaml"
    listing.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        load_config(listing, environ={})
    with pytest.raises(ConfigError, match=r"section\.field=value"):
        load_config(None, ["learner.batch_size"], environ={})


def test_precedence_file_then_environment_then_cli(small_yaml: Path) -> None:
    env = {"USER__LEARNER__BATCH_SIZE": "64"}
    assert load_config(small_yaml, environ={}).learner.batch_size == 32
    assert load_config(small_yaml, environ=env).learner.batch_size == 64
    assert load_config(small_yaml, ["learner.batch_size=96"], environ=env).learner.batch_size == 96
    # an override touches only its field: the rest of the section still comes from the file
    cfg = load_config(small_yaml, ["learner.batch_size=96"], environ=env)
    assert cfg.learner.gamma == 0.9
    assert cfg.learner.critic_lr == StackConfig().learner.critic_lr


def test_environment_overrides_are_typed_and_nested(small_yaml: Path) -> None:
    env = {
        "USER__CONTROL__SERVER__PORT": "6002",
        "USER__LOG_JSON": "false",
        "USER__EDGE__ROBOTS": "[{id: arm-7, params: {control_rate_hz: 10}}]",
        "UNRELATED__LEARNER__BATCH_SIZE": "-1",  # only the USER__ prefix is read
    }
    cfg = load_config(small_yaml, environ=env)
    assert cfg.control.server.port == 6002
    assert cfg.control.server.metrics_port == StackConfig().control.server.metrics_port
    assert cfg.log_json is False
    assert [(r.id, r.params) for r in cfg.edge.robots] == [("arm-7", {"control_rate_hz": 10})]
    assert cfg.learner.batch_size == 32


def test_a_partial_server_override_keeps_the_sections_ports() -> None:
    cfg = load_config(None, ["control.server.host=0.0.0.0"], environ={"USER__LEARNER__SERVER__PORT": "6004"})
    assert (cfg.control.server.host, cfg.control.server.port, cfg.control.server.metrics_port) == (
        "0.0.0.0",
        50051,
        9101,
    )
    assert (cfg.learner.server.port, cfg.learner.server.metrics_port) == (6004, 9104)


def test_the_process_environment_is_the_default(small_yaml: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("USER__LEARNER__BATCH_SIZE", "64")
    assert load_config(small_yaml).learner.batch_size == 64
    monkeypatch.setenv("USER__LEARNER__BATCH_SIZE", "0")
    with pytest.raises(ConfigError, match=r"learner\.batch_size:"):
        load_config(small_yaml)


def test_enabled_auth_without_a_token_names_the_field(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("USER_TOKEN", raising=False)
    with pytest.raises(ConfigError, match=r"auth\.token"):
        AuthConfig().resolved_token()
    monkeypatch.setenv("USER_TOKEN", "from-env")
    assert AuthConfig().resolved_token() == "from-env"
    assert AuthConfig(token="explicit").resolved_token() == "explicit"
    assert AuthConfig(enabled=False, token="ignored").resolved_token() is None
    monkeypatch.delenv("USER_TOKEN")
    token_file = tmp_path / "token"
    token_file.write_text("from-file\n")
    assert AuthConfig(token_file=token_file).resolved_token() == "from-file"


@pytest.mark.parametrize("command", ["control", "replay", "inference", "learner", "edge", "up"])
def test_userctl_exits_2_on_a_bad_override(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    config = str(ROOT / "configs" / "compose.yaml")
    assert cli.main([command, "-c", config, "--set", "learner.batch_size=-1"]) == 2
    err = capsys.readouterr().err
    assert "learner.batch_size" in err


@pytest.mark.parametrize(
    ("command", "device", "said"),
    [
        ("inference", "gpu", "should match pattern"),
        ("learner", "cuda:99", "CUDA devices"),
        ("inference", "cuda:99", "CUDA"),
    ],
)
def test_userctl_exits_2_on_a_device_this_machine_lacks(
    command: str, device: str, said: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # userctl sets up logging on pytest's captured stderr before the service refuses the device: put the
    # root handlers back afterwards, or later tests would log into a closed stream.
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", list(root.handlers))
    monkeypatch.setattr(root, "level", root.level)
    overrides = ["--set", f"{command}.device={device}", "--set", "auth.token=t"]
    assert cli.main([command, "-c", str(ROOT / "configs" / "compose.yaml"), *overrides]) == 2
    err = capsys.readouterr().err
    assert f"{command}.device" in err and said in err


def test_userctl_health_exits_2_on_a_bad_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["health", "127.0.0.1:1", "--set", "control.server.port=-5"]) == 2
    assert "control.server.port" in capsys.readouterr().err


def _userctl() -> Path:
    script = Path(sys.executable).with_name("userctl")
    if not script.exists():
        pytest.skip("userctl is not installed in this interpreter's environment")
    return script


def test_the_installed_userctl_exits_2_naming_the_field() -> None:
    proc = subprocess.run(
        [str(_userctl()), "learner", "-c", str(ROOT / "configs" / "compose.yaml"), "--set", "learner.batch_size=-1"],
        capture_output=True,
        text=True,
        timeout=60,
        env={k: v for k, v in os.environ.items() if not k.startswith("USER__")},
    )
    assert proc.returncode == 2, proc.stderr
    assert "learner.batch_size" in proc.stderr
    assert proc.stdout == ""


def test_the_installed_userctl_reads_environment_overrides() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("USER__")}
    env["USER__EDGE__ROBOTS"] = "[{id: 'two words'}]"
    proc = subprocess.run(
        [str(_userctl()), "edge", "-c", str(ROOT / "configs" / "compose.yaml")],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert proc.returncode == 2, proc.stderr
    assert "edge.robots.0.id" in proc.stderr


def test_the_readme_config_reference_matches_the_code() -> None:
    """The README's table is generated from the config classes; regenerate it when a default changes."""
    from user.config import reference_markdown

    readme = (ROOT / "README.md").read_text()
    missing = [row for row in reference_markdown() if row not in readme]
    assert not missing, "README config reference is stale; first stale row: " + missing[0]
