"""`userctl edge install-service` and `userctl edge discover` on bad input: one line on stderr and an exit code,
never a traceback, and never a unit that could only crash-loop or a config the edge would refuse."""

from __future__ import annotations

import getpass
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from user import cli, edge_setup
from user.config import StackConfig
from user.edge_setup import SerialPort, discover, edge_config_problem, render_unit, simulated_kinds

USERCTL = sys.executable  # any executable file will do for --userctl


def _one_line(err: str) -> str:
    assert err.strip() and "\n" not in err.strip() and "Traceback" not in err, err
    return err.strip()


def _valid_config(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(discover("cloud.lab:50051", ["sim_reach_arm"], serial=list, cameras=list))
    return path


def _install(config: Path | str, unit_dir: Path | str, *extra: str) -> int:
    args = ["edge", "install-service", "-c", str(config), "--unit-dir", str(unit_dir)]
    return cli.main([*args, "--user", getpass.getuser(), "--userctl", USERCTL, *extra])


@pytest.fixture
def tmp_visible(monkeypatch: pytest.MonkeyPatch) -> None:
    """tmp_path is under /tmp, which the unit (PrivateTmp=yes) refuses first; tests/test_k8s.py tests that."""
    monkeypatch.setattr(edge_setup, "_hidden_by_private_tmp", lambda config: "")


# --------------------------------------------------------------------------- the edge config


def test_install_service_refuses_a_missing_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _install("/nonexistent/edge.yaml", tmp_path, "--no-start") == 2
    assert "edge config /nonexistent/edge.yaml does not exist" in _one_line(capsys.readouterr().err)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "text, names",
    [
        ("edge:\n  robots:\n  - {id: arm-0, kind: lerobot}\n", "edge.robots[0].params.type: Field required"),
        ("edge:\n  robots:\n  - {id: arm-0, params: {nope: 1}}\n", "edge.robots[0].params.nope"),
        ("edge:\n  robots:\n  - {id: arm-0, task: {kind: nope}}\n", "edge.robots[0].task.kind: unknown task kind"),
        ("edge:\n  robots:\n  - {id: arm-0, teleop: {kind: nope}}\n", "edge.robots[0].teleop.kind"),
        ("edge:\n  robots:\n  - {id: 'a b'}\n", "edge.robots.0.id"),
        ("edge:\n  robots: [\n  - {id: a", "cannot read config"),  # YAML errors span several lines
        ("- a list\n", "top level must be a mapping"),
    ],
)
def test_install_service_refuses_an_invalid_config_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tmp_visible: None, text: str, names: str
) -> None:
    config = tmp_path / "edge.yaml"
    config.write_text(text)
    unit_dir = tmp_path / "units"
    unit_dir.mkdir()
    assert _install(config, unit_dir, "--no-start") == 2
    err = _one_line(capsys.readouterr().err)
    assert names in err and str(config) in err, err
    assert not list(unit_dir.iterdir())


def test_install_service_writes_the_unit_of_a_valid_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tmp_visible: None
) -> None:
    """What the checks let through: the config discover writes, under the unit name given (".service" optional)."""
    config = _valid_config(tmp_path / "edge.yaml")
    assert _install(config, tmp_path, "--no-start", "--name", "my-edge.service") == 0
    unit = (tmp_path / "my-edge.service").read_text().splitlines()
    assert f"ExecStart={USERCTL} edge --config {config}" in unit


def test_dry_run_warns_of_what_an_install_would_refuse(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--dry-run writes nothing, so, as for a config under /tmp, it prints the unit with a warning, exit 0."""
    assert _install("/nonexistent/edge.yaml", tmp_path / "none", "--dry-run", "--user", "no-such-user-x") == 0
    out = capsys.readouterr().out
    for warning in [
        "# WARNING: edge config /nonexistent/edge.yaml does not exist",
        "# WARNING: user 'no-such-user-x' does not exist",
        f"# WARNING: unit directory {tmp_path / 'none'} does not exist",
    ]:
        assert any(line.startswith(warning) for line in out.splitlines()), warning
    assert not (tmp_path / "none").exists()


# --------------------------------------------------------------------------- unit name, directory, user, userctl


def test_install_service_refuses_a_missing_unit_dir(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tmp_visible: None
) -> None:
    config = _valid_config(tmp_path / "edge.yaml")
    assert _install(config, tmp_path / "nounitdir", "--no-start") == 2
    assert f"unit directory {tmp_path / 'nounitdir'} does not exist" in _one_line(capsys.readouterr().err)


@pytest.mark.parametrize("name", ["my edge/x", "", "-edge", "edge@robot", "a\nb", "e" * 248, "édge"])
def test_install_service_refuses_an_invalid_unit_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tmp_visible: None, name: str
) -> None:
    config = _valid_config(tmp_path / "cfg" / "edge.yaml")
    assert _install(config, tmp_path, "--no-start", f"--name={name}") == 2
    assert "invalid unit name" in _one_line(capsys.readouterr().err)
    assert [p.name for p in tmp_path.iterdir()] == ["cfg"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--user", "no-such-user-x"], "user 'no-such-user-x' does not exist"),
        (["--userctl", "/nonexistent/userctl"], "/nonexistent/userctl is not an executable file (--userctl)"),
        (["--userctl", '/opt/a"b/userctl'], "its path has a quote or backslash"),
        (["--user", "robot\nExecStartPre=/bin/sh"], "--user 'robot\\nExecStartPre=/bin/sh' has a control character"),
    ],
)
def test_install_service_refuses_what_the_unit_could_not_run_as(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tmp_visible: None, extra: list[str], message: str
) -> None:
    """A User= that does not exist or an ExecStart= that is not there fails every start, restarted for ever."""
    config = _valid_config(tmp_path / "cfg" / "edge.yaml")
    assert _install(config, tmp_path, "--no-start", *extra) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert [p.name for p in tmp_path.iterdir()] == ["cfg"]


# --------------------------------------------------------------------------- ExecStart= quoting


def _undouble(text: str, char: str) -> str:
    """systemd turns a doubled `char` into one; a single one it would expand (a %specifier, a $VAR)."""
    parts = text.split(char * 2)
    assert all(char not in part for part in parts), f"systemd would expand {char} in {text!r}"
    return char.join(parts)


def _exec_start_argv(unit: str) -> list[str]:
    """ExecStart= split as systemd does: specifiers, then quotes and escapes, then $VARS in the arguments."""
    line = next(line for line in unit.splitlines() if line.startswith("ExecStart="))
    path, *args = shlex.split(_undouble(line.removeprefix("ExecStart="), "%"))
    return [path, *(_undouble(a, "$") for a in args)]


@pytest.mark.parametrize("userctl", ["/opt/user/bin/userctl", "/opt/user tools/bin/userctl", "/opt/$5 100%/userctl"])
@pytest.mark.parametrize(
    "config",
    [
        "/srv/robot configs/edge.yaml",
        "/srv/q\"uote/e'dge.yaml",
        "/srv/back\\slash",
        "/srv/%i$HOME",
        "/srv/a b/%i $HOME",
    ],
)
def test_exec_start_keeps_a_config_path_one_argument(userctl: str, config: str) -> None:
    assert _exec_start_argv(render_unit(userctl, config, "robot")) == [userctl, "edge", "--config", config]


def test_systemd_runs_an_executable_under_a_path_with_spaces(tmp_path: Path) -> None:
    """systemd itself (verify checks that ExecStart's executable exists): the quoted path is one path."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not installed")
    userctl = tmp_path / "user tools 100%" / "userctl"
    userctl.parent.mkdir()
    shutil.copy(USERCTL, userctl)
    unit = tmp_path / "user-edge.service"
    unit.write_text(render_unit(str(userctl), str(tmp_path / "robot configs" / "edge.yaml"), "root"))
    out = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and not out.stderr.strip(), out.stderr


# --------------------------------------------------------------------------- discover


def test_discover_sim_offers_only_simulators_whose_config_the_edge_takes(tmp_path: Path) -> None:
    kinds = simulated_kinds()
    assert "sim_reach_arm" in kinds and "lerobot" not in kinds
    for kind in kinds:
        config = tmp_path / f"{kind}.yaml"
        config.write_text(discover("x:1", [kind], serial=list, cameras=list))
        assert edge_config_problem(str(config)) == "", kind
    with pytest.raises(ValueError, match="unknown simulated robot kind") as info:
        discover("x:1", ["no_such_robot"], serial=list, cameras=list)
    assert "lerobot" not in str(info.value)


def test_discover_refuses_sim_lerobot_with_a_hint_that_works(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from edge_agent.robot import known_robot_kinds

    if "lerobot" not in known_robot_kinds():
        pytest.skip("the lerobot robot kind needs the lerobot package")
    out = tmp_path / "out.yaml"
    assert cli.main(["edge", "discover", "--sim", "lerobot", "-o", str(out)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "lerobot drives real hardware, not a simulator" in err and not out.exists()
    entry = yaml.safe_load(err[err.index("{id:") : err.index("}}}") + 3])  # the example entry it gives
    config = tmp_path / "edge.yaml"
    config.write_text(yaml.safe_dump({"edge": {"robots": [entry]}}))
    assert edge_config_problem(str(config)) == ""


def test_discover_lists_found_arms_as_lerobot_entries_the_edge_takes(tmp_path: Path) -> None:
    from edge_agent.robot import known_robot_kinds

    if "lerobot" not in known_robot_kinds():
        pytest.skip("the lerobot robot kind needs the lerobot package")
    ports = [SerialPort("/dev/ttyACM0", "1a86", "55d3"), SerialPort("/dev/ttyUSB0", "0403", "6014")]
    camera = {"id": "/dev/video0", "default_stream_profile": {"width": 1280, "height": 720, "fps": 15}}
    text = discover("x:1", [], serial=lambda: ports, cameras=lambda: [camera])
    hints = [line.removeprefix("#   - ") for line in text.splitlines() if line.startswith("#   - ")]
    entries = [yaml.safe_load(hint) for hint in hints]
    assert [(e["params"]["type"], e["params"]["config"]["port"]) for e in entries] == [
        ("so101_follower", "/dev/ttyACM0"),
        ("koch_follower", "/dev/ttyUSB0"),
    ]
    tree = yaml.safe_load(text)
    tree["edge"]["robots"] = entries  # uncommented as they are
    config = tmp_path / "edge.yaml"
    config.write_text(yaml.safe_dump(tree))
    assert StackConfig.model_validate(tree) and edge_config_problem(str(config)) == ""
    from lerobot.robots import RobotConfig

    from edge_agent.lerobot_devices import _config  # lerobot decodes the config (cameras too) as the agent would

    decoded = _config(RobotConfig, "lerobot.robots", "so101_follower", entries[0]["params"]["config"])
    cam0 = decoded.cameras["cam0"]
    assert (str(cam0.index_or_path), cam0.width, cam0.height, cam0.fps) == ("/dev/video0", 1280, 720, 15)


@pytest.mark.parametrize("output", ["/nonexistent/dir/edge.yaml", "."])
def test_discover_output_that_cannot_be_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, output: str
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(edge_setup, "discover", lambda control, sims: "edge: {}\n")  # no camera probe needed
    assert cli.main(["edge", "discover", "-o", output]) == 2
    assert f"cannot write {output}" in _one_line(capsys.readouterr().err)
    assert os.listdir(tmp_path) == []
