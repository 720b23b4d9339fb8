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
