"""The load harness (bench/load_bench.py) counts lost steps right: a real stack, two edge agents of two
robots each, one of them writing to a port nobody listens on. Its steps are collected but never stored,
and the harness must report exactly those as lost, and none of the other agent's.

No timing thresholds: rates and latencies of a few seconds on a shared machine mean nothing here.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from bench.load_bench import LoadOptions, LoadRun, histogram_quantile, rows


@pytest.mark.slow
def test_load_harness_counts_lost_steps(tmp_path: Path) -> None:
    opts = LoadOptions(
        duration_s=3.0,
        robots=4,
        robots_per_agent=2,
        warmup_s=0.5,
        sample_s=1.0,
        drain_timeout_s=10.0,  # the black-holed agent never drains: this bound ends the wait
        wait_for_weights=False,
        blackhole_agents=1,
    )
    result = LoadRun(opts, tmp_path, print).run()

    agents = result["agent_of_robot"]
    good = [r for r, a in agents.items() if a == "edge-0"]
    dark = [r for r, a in agents.items() if a == "edge-1"]
    assert sorted(good) == ["arm-0", "arm-1"] and sorted(dark) == ["arm-2", "arm-3"]
    collected, lost = result["collected_per_robot"], result["lost_per_robot"]
    for rid in good:
        assert collected[rid] > 0 and lost[rid] == 0, (rid, collected[rid], lost[rid])
    for rid in dark:
        assert collected[rid] > 0 and lost[rid] == collected[rid], (rid, collected[rid], lost[rid])
    dark_steps = sum(collected[r] for r in dark)
    assert result["lost"] == dark_steps
    assert result["collected"] == result["stored"] + dark_steps
    assert result["unacked"] == dark_steps  # still in the black-holed agent's spool
    assert result["acked"] == result["stored"] == result["replay_steps"]
    assert result["deduplicated"] == 0
    assert any(k.startswith("/user.v1.Replay/Insert UNAVAILABLE") for k in result["client_errors_whole_run"])
    assert all(code == 0 for code in result["exit_codes"].values()), str(result["exit_codes"])
    # every service and edge process was measured
    assert {"control", "replay", "learner", "inference", "edge-0", "edge-1"} <= set(result["rss"])
    assert all(r["start_mb"] > 0 and r["end_mb"] > 0 for r in result["rss"].values())

    table = {r.metric: r for r in rows(result)}
    assert table["steps lost (collected - stored)"].ours == f"{dark_steps} of {result['collected']}"
    for name in ("control", "replay", "learner", "inference"):  # slope after warm-up, per service, in the table
        assert table[f"RSS {name}, anonymous slope 2nd half"].unit == "MB/min"
        assert len(result["rss"][name]["series"]) >= 3
    assert 0.0 <= result["replay_hot_hit_rate"] <= 1.0 and "hit rate" in table["RSS replay, end"].note


def test_histogram_quantile_reads_cumulative_buckets() -> None:
    def h(le: str, n: float):
        return ("lat_bucket", (("le", le),)), n

    samples = dict([h("0.01", 50), h("0.02", 90), h("0.04", 100), h("+Inf", 100)])
    assert histogram_quantile(samples, "lat", 0.5) == pytest.approx(0.01)
    assert histogram_quantile(samples, "lat", 0.7) == pytest.approx(0.015)  # halfway through (0.01, 0.02]
    assert histogram_quantile(samples, "lat", 0.95) == pytest.approx(0.03)
    over = dict([h("0.01", 1), h("+Inf", 10)])
    assert histogram_quantile(over, "lat", 0.99) == pytest.approx(0.01)  # in +Inf: the largest finite bound
    assert math.isnan(histogram_quantile({}, "lat", 0.5))


def test_load_runs_only_when_named() -> None:
    from bench.__main__ import selected

    assert "load" not in selected(None, quick=False) and "load" not in selected(None, quick=True)
    assert selected("load", quick=False) == ["load"]
