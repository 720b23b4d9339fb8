"""runs/bench/latest.json keeps every bench's last rows: a `--only x` run replaces x's rows and no other's."""

from __future__ import annotations

import json
import sys
import types
from pathlib import Path

import pytest

import bench.__main__ as bench_main
from bench import Row


def _stub(name: str, value: float) -> types.ModuleType:
    """A bench module whose run() returns one row; stands in for a real bench so the test runs in milliseconds."""
    module = types.ModuleType(f"stub_bench_{name}")

    def run(quick: bool, workdir: Path, log: object = print, **_: object) -> list[Row]:
        return [Row(f"{name} group", "rate", value, 1.0, unit="/s", higher_is_better=True)]

    module.run = run  # type: ignore[attr-defined]
    return module


@pytest.fixture
def stub_benches(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, float]:
    values = {"alpha": 2.0, "beta": 3.0}
    benches = {name: f"stub_bench_{name}" for name in values}
    for name, value in values.items():
        monkeypatch.setitem(sys.modules, benches[name], _stub(name, value))
    monkeypatch.setattr(bench_main, "BENCHES", benches)
    monkeypatch.setattr(bench_main, "OPT_IN", set())
    monkeypatch.setattr(bench_main, "LEGEND", {name: f"{name}: a stub" for name in values})
    monkeypatch.setattr(bench_main, "DEFAULT_OUT", tmp_path / "runs")
    return values


def _rows(tmp_path: Path) -> list[dict]:
    return json.loads((tmp_path / "runs" / "latest.json").read_text())


def test_an_only_run_replaces_its_own_rows_and_keeps_the_others(tmp_path: Path, stub_benches: dict) -> None:
    assert bench_main.main([]) == 0
    first = _rows(tmp_path)
    assert [(r["bench"], r["ours"]) for r in first] == [("alpha", 2.0), ("beta", 3.0)]
    assert all(r["measured_at"].endswith("UTC") and r["advantage"] == r["ours"] for r in first)

    sys.modules["stub_bench_alpha"] = _stub("alpha", 5.0)  # the fixture's monkeypatch restores the entry
    assert bench_main.main(["--only", "alpha"]) == 0
    second = _rows(tmp_path)
    assert [(r["bench"], r["ours"]) for r in second] == [("alpha", 5.0), ("beta", 3.0)]
    md = (tmp_path / "runs" / "latest.md").read_text()
    assert "| alpha group vs" in md and "| beta group vs" in md
    assert md.count(": a stub") == 2  # one legend line per bench in the file, with when it ran


def test_explicit_outputs_hold_only_that_run(tmp_path: Path, stub_benches: dict) -> None:
    assert bench_main.main([]) == 0
    out = tmp_path / "one.json"
    assert bench_main.main(["--only", "beta", "--json", str(out)]) == 0
    assert [r["bench"] for r in json.loads(out.read_text())] == ["beta"]
    assert [r["bench"] for r in _rows(tmp_path)] == ["alpha", "beta"]  # the default file is left alone
    md = tmp_path / "one.md"
    assert bench_main.main(["--only", "alpha", "--markdown", str(md)]) == 0
    assert "beta" not in md.read_text()
    assert [r["bench"] for r in _rows(tmp_path)] == ["alpha", "beta"]  # the default JSON still keeps beta


def test_unreadable_or_unattributed_rows_are_dropped(tmp_path: Path, stub_benches: dict) -> None:
    latest = tmp_path / "runs" / "latest.json"
    latest.parent.mkdir(parents=True)
    latest.write_text(json.dumps([{"group": "from before bench names", "metric": "m", "ours": 1, "peer": 1}]))
    assert bench_main.main(["--only", "beta"]) == 0
    assert [r["bench"] for r in _rows(tmp_path)] == ["beta"]
    latest.write_text("{not json")
    assert bench_main.main(["--only", "alpha"]) == 0
    assert [r["bench"] for r in _rows(tmp_path)] == ["alpha"]


def test_a_failed_bench_keeps_its_last_rows(tmp_path: Path, stub_benches: dict) -> None:
    assert bench_main.main([]) == 0
    broken = types.ModuleType("stub_bench_beta")

    def run(**_: object) -> list[Row]:
        raise RuntimeError("the peer did not start")

    broken.run = run  # type: ignore[attr-defined]
    sys.modules["stub_bench_beta"] = broken
    assert bench_main.main([]) == 1
    assert [(r["bench"], r["ours"]) for r in _rows(tmp_path)] == [("alpha", 2.0), ("beta", 3.0)]
