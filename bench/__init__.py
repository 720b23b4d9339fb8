"""Benchmarks of USER's parts against a real peer (lerobot 0.6.1) run side by side in one process.

Every row is one metric measured on both sides in the same run; `advantage` is how many times better
ours is (>1: ours better), whichever direction "better" is for the metric (time: lower, rate: higher).
Fact rows (durability, serialization format) carry text and no ratio.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

PEER = "lerobot 0.6.1"


@dataclass
class Row:
    group: str  # e.g. "replay sim-arm (N=20000)"
    metric: str
    ours: float | str
    peer: float | str
    unit: str = ""
    higher_is_better: bool | None = None  # None: a fact row, no ratio
    note: str = ""
    peer_name: str = PEER
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def advantage(self) -> float | None:
        """How many times better ours is; None for fact rows."""
        if self.higher_is_better is None:
            return None
        ours, peer = float(self.ours), float(self.peer)  # type: ignore[arg-type]
        num, den = (ours, peer) if self.higher_is_better else (peer, ours)
        if den == 0:
            return math.inf if num > 0 else math.nan
        return num / den

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        doc["advantage"] = self.advantage
        return doc


def timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    """(seconds, result) of one call."""
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def repeat_ms(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> list[float]:
    """Milliseconds of `repeats` calls after `warmup` untimed ones."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        out.append((time.perf_counter() - start) * 1e3)
    return out


def median(values: list[float]) -> float:
    """NaN for no values: a window in which a slow model answered nothing still makes its row."""
    return float(statistics.median(values)) if values else float("nan")


def fmt_value(value: float | str, unit: str) -> str:
    if isinstance(value, str):
        return value
    if value == 0 or not math.isfinite(value):
        text = f"{value:g}"
    elif abs(value) >= 100:
        text = f"{value:,.0f}"
    elif abs(value) >= 10:
        text = f"{value:.1f}"
    elif abs(value) >= 1:
        text = f"{value:.2f}"
    else:
        text = f"{value:.3g}"
    return f"{text} {unit}".rstrip()


def fmt_advantage(adv: float | None) -> str:
    if adv is None:
        return "-"
    if not math.isfinite(adv):
        return str(adv)
    return f"{adv:.2f}x" if adv < 10 else f"{adv:.0f}x"
