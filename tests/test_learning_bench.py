"""The async-vs-sync learning benchmark runs end to end (two whole stacks as processes, interleaved windows) and
yields its rows.

No thresholds on the numbers (a --quick run under contention means nothing); the rows' shape is checked, both modes
must have collected and trained, and the learner's training-thread phases must have been counted.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest


@pytest.mark.slow
def test_learning_bench_quick(tmp_path: Path) -> None:
    from bench.learning_bench import measure, rows_for

    windows, window_s = measure("cnn", quick=True, workdir=tmp_path, log=print)
    assert sorted(w.mode for w in windows) == ["async", "sync"]
    by_mode = {w.mode: w for w in windows}
    assert by_mode["async"].phases_s.get("update", 0) > 0 and "wait_batch" in by_mode["async"].phases_s
    assert by_mode["sync"].phases_s.get("wait_robots", 0) > 0  # sync idles while its robots collect
    assert "train" in by_mode["async"].threads and "sampler" in by_mode["async"].threads
    rows = rows_for("cnn", windows, window_s)
    assert [r.metric for r in rows[:2]] == ["env steps/s", "updates/s"]
    for row in rows[:2]:
        assert float(row.ours) > 0 and float(row.peer) > 0, row
        assert row.advantage is not None and math.isfinite(row.advantage)
