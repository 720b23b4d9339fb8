"""`userctl plugins` lists every registered kind; plug-ins are found without an import list."""

from __future__ import annotations

import pytest

from user.cli import main


def test_userctl_plugins_lists_every_interface(capsys: pytest.CaptureFixture[str]) -> None:
    import tests.plugins  # noqa: F401 - a plug-in registered by its own module shows up too

    assert main(["plugins"]) == 0
    lines = capsys.readouterr().out.splitlines()
    kinds = {tuple(line.split(" ", 2)[:2]) for line in lines}
    expected = {
        ("algorithm", "sac"),
        ("algorithm", "test_mean"),
        ("policy", "sac_mlp"),
        ("policy", "padded"),
        ("policy", "test_constant"),
        ("robot", "sim_reach_arm"),
    }
    assert expected <= kinds
    assert all(len(line.split(" ", 2)) == 3 for line in lines), "every line: interface kind description"
    assert lines == sorted(lines)


def test_userctl_plugins_kind_shows_its_params(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins", "algorithm", "sac"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("algorithm sac: ")
    rows = {line.split()[0]: line for line in out[2:]}
    assert "conv | resnet18" in rows["backbone"] and '"conv"' in rows["backbone"]
    assert "[128, 128]" in rows["hidden"] and "MLP widths" in rows["hidden"]
    assert len(rows) == int(out[1].split("(")[1].rstrip("):"))  # every field, one line each
    assert main(["plugins", "robot", "no_such_arm"]) == 2
    err = capsys.readouterr().err
    assert "unknown robot kind 'no_such_arm'" in err and "sim_reach_arm" in err
    assert main(["plugins", "gadget", "x"]) == 2
    assert "known: ['algorithm', 'policy', 'robot', 'task', 'teleoperator']" in capsys.readouterr().err
    assert main(["plugins", "robot"]) == 2
