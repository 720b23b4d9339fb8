"""The async-vs-sync learning benchmark runs end to end (two whole stacks as processes) and yields its rows.

No thresholds on the numbers (a --quick run under contention means nothing); the rows' shape is checked and
both modes must have collected and trained.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest


@pytest.mark.slow
def test_learning_bench_quick(tmp_path: Path) -> None:
    from bench.learning_bench import run

    rows = run(quick=True, workdir=tmp_path)
    assert [r.metric for r in rows] == ["env steps/s", "updates/s"]
    for row in rows:
        assert float(row.ours) > 0 and float(row.peer) > 0, row
        assert row.advantage is not None and math.isfinite(row.advantage)
