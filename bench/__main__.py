"""`python -m bench [--quick] [--only replay,weights,inference] [--json out.json] [--markdown out.md]`

`python -m bench --only load [--duration 600] [--edges 64] [--hz 10]` (`make load`): the load test,
run only when named (it takes the whole --duration, 10 minutes by default).

Runs each benchmark against its real peer in this process and prints one table. Without --json/--markdown the
rows also go to runs/bench/latest.json|md, where a run replaces only its own benches' rows: the files keep every
bench's last figures, each row with its bench and when it was measured.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
import tempfile
import time
import traceback
from dataclasses import fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from bench import Row, fmt_advantage, fmt_value

BENCHES = {
    "replay": "bench.replay_bench",
    "weights": "bench.weights_bench",
    "inference": "bench.inference_bench",
    "learning": "bench.learning_bench",
    "inference_vla": "bench.inference_vla_bench",
    "hg_dagger": "bench.hg_dagger_bench",
    "hgdagger_stack": "bench.hgdagger_stack_bench",
    "spool": "bench.spool_bench",
    "edge": "bench.edge_bench",
    "curves": "bench.curves_bench",
    "load": "bench.load_bench",
    "two_arms": "bench.two_arms_bench",
    "gpu": "bench.gpu_bench",
}
SLOW = {"learning"}  # whole stacks as processes: minutes, not part of the --quick smoke run unless named
# run only when named in --only: 10-20 minutes of whole stacks each (load; two HG-DAgger stacks; two arms at once)
OPT_IN = {"load", "hgdagger_stack", "two_arms", "gpu"}
TAKES_OVERRIDES = {"load", "inference_vla", "learning"}  # --set reaches their stack config (e.g. inference.device=cuda)


DEFAULT_OUT = Path("runs/bench")
LEGEND = {
    "replay": "replay: ours services.replay.store.ReplayStore (LMDB, durable commits) vs "
    "lerobot.rl.buffer.ReplayBuffer built as their learner builds it (CPU, optimize_memory=True), DrQ off; "
    "both fed the same transitions, taking turns.",
    "weights": "weights: ours user.weights (WeightStore/WeightServicer.StreamWeights -> WeightSubscriber, acked, "
    "token auth) vs lerobot's LearnerService.StreamParameters + transport.utils (state_to_bytes, "
    "receive_bytes_in_chunks, bytes_to_state_dict, torch.multiprocessing queues; one lerobot learner per actor, "
    "each serializing its own state, as lerobot serves actors) and a bare gRPC stream of the same bytes; "
    "real gRPC servers on 127.0.0.1 (the 20 Mbit/s rows: tc tbf in a private netns), versions alternate.",
    "inference": "inference: ours InferenceService (micro-batching) vs the same Act proto served one forward per "
    "request in the handler; each robot is a separate process, windows alternate.",
    "learning": "learning: the whole stack as processes, learner.mode=async (ours) vs learner.mode=sync (collect, "
    "pause robots, train, publish in turn) on the same config; both stacks up at once, windows alternate (A S S A, "
    "the other stack's experiment stopped); env steps/s and updates/s per pair of windows, the learner's CPU and "
    "its training thread's time by phase. Configs: CNN+SAC (quick), HG-DAgger flow_bc (full; "
    "USER_LEARNING_CONFIGS=cnn,state,hgdagger picks).",
    "inference_vla": "inference_vla: ours InferenceService (dynamic batching, batched preprocess) vs the same flow_vla "
    "model served one request at a time (openpi / lerobot policy-server style), at two sizes (0.16M toy, 13.9M with "
    "two 128x128 cameras); robots are separate processes, closed loop or paced at a chunk's control rate; windows "
    "alternate. Tiny SmolVLA from a local folder, 1 robot: ours vs lerobot's async-inference PolicyServer (offline, "
    "loopback, its own pickle protocol). Over 20 Mbit/s (tc tbf in a private netns): the VLA with real gym-hil "
    "Panda frames, 1 and 8 robots paced at 3.75 Hz, frames JPEG-encoded by the edge vs raw (ours) and vs the "
    "one-at-a-time server (raw). Edge chunks: 16 robot processes at 30 Hz through RemotePolicy + ChunkExecutor, ticks "
    "held and chunks asked under ours (adaptive), the fixed 2-tick rule and lerobot's half-chunk rule.",
    "hg_dagger": "hg_dagger: flow_vla on lang_reach_arm (real MuJoCo, scripted expert), in one process with in-memory "
    "tables: HG-DAgger (demos + interventions) vs BC given the same expert steps as more demos; async vs sync learner.",
    "hgdagger_stack": "hgdagger_stack: configs/hgdagger.yaml as processes (control, replay, learner, inference, "
    "lang_reach_arm edges with the scripted expert as teleoperator, flow_vla chunks via Inference.Act); flow_bc "
    "pretrained on demos, then corrected online from interventions; before/after on fixed evaluation episodes through "
    "the inference service, interventions off; learner.mode=async (ours) vs sync on the same config, same window.",
    "spool": "spool: ours edge_agent.spool.LmdbSpool (steps on disk until replay acks) vs the same edge agent with "
    "edge.spool_dir null (RAM outbox); real edge processes, kill -9 during a replay outage, restart; lost = "
    "collected - stored.",
    "edge": "edge: ours Robot.act + observe + env task (the edge loop's per-tick work minus the network), "
    "cameras rendered without shadows/MSAA, vs the bare gym env.step (gym-hil's image_obs renderer for cameras); "
    "the same random actions, rounds alternate.",
    "curves": "curves: success curves of the in-process trainer (cloud_learner.local) vs a uniform random policy "
    "on the same robot: reach (SAC, state; target 90% in 5 min), gym-hil Panda pick-cube from state (RLPD + scripted "
    "demos and interventions; target 80% in 30 min) and from its two cameras + proprioception (success rising within "
    "30 min), SO-101 pick-cube from state (RLPD; 80% in 30 min); curves in runs/bench/curves/*.json|png.",
    "two_arms": "two_arms: SO-101 and Panda pick-cube training at once on one stack (processes, one edge agent per "
    "robot at its control rate), two experiments each with its own RLPD instance and replay table, from state, "
    "scripted expert taking over stalled episodes; success without help per arm vs a uniform random policy; curves in "
    "runs/bench/two_arms/so101_panda.json|png.",
    "gpu": "gpu: on a CUDA machine, the learner's algorithms (update rate through the learner's own batch path, "
    "host-to-device copies included) and flow_vla's forward on the GPU vs the same code on all the machine's CPU "
    "cores; rows say 'not run' where torch sees no GPU.",
    "load": "load: one stack as processes on 127.0.0.1 (control, replay, learner training SAC, inference; token auth) "
    "and state-only sim arms in edge agent processes of 8 robots (the real `userctl edge`: registration, heartbeats, "
    "Inference.Act within 40 ms, LMDB spool -> Replay.Insert); window after warm-up; latencies from the edges' "
    "/metrics histograms, RSS from /proc; lost = steps the edges collected - steps replay stores (after a pause and "
    "drain); peer column = the rate target or the RSS at the window's start; details in runs/bench/load.json.",
}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    p.add_argument("--quick", action="store_true", help="tiny sizes (smoke test); numbers are not meaningful")
    p.add_argument(
        "--only",
        default=None,
        help=f"comma-separated subset of {list(BENCHES)} (default all but {sorted(OPT_IN)}; --quick skips "
        f"{sorted(SLOW)})",
    )
    p.add_argument(
        "--json",
        dest="json_path",
        help="rows as JSON (default runs/bench/latest.json, not with --quick: there the benches that ran replace "
        "their own rows and every other bench's last rows stay)",
    )
    p.add_argument(
        "--markdown", dest="md_path", help="table as Markdown (default runs/bench/latest.md, not with --quick)"
    )
    p.add_argument("--workdir", help="where LMDB files go (default: a temporary directory)")
    load = p.add_argument_group("load (only with --only load)")
    load.add_argument("--duration", type=float, help="measured window, seconds (default 600; --quick 10)")
    load.add_argument("--edges", type=int, help="simulated robots, 8 per edge process (default 64; --quick 4)")
    load.add_argument("--hz", type=float, help="control rate of every robot (default 10)")
    load.add_argument(
        "--set", dest="overrides", action="append", default=[], help="stack config override, e.g. replay.capacity_mb=64"
    )
    return p


def render(rows: list[Row], title: str) -> Table:
    table = Table(title=title, show_lines=False, header_style="bold")
    table.add_column("benchmark", style="cyan", no_wrap=True)
    table.add_column("metric")
    table.add_column("USER (ours)", justify="right")
    table.add_column("peer", justify="right")
    table.add_column("ours vs peer", justify="right", style="bold")
    table.add_column("note", style="dim")
    last_group = None
    for row in rows:
        group = f"{row.group}\n[dim]vs {row.peer_name}[/dim]" if row.group != last_group else ""
        last_group = row.group
        table.add_row(
            group,
            row.metric,
            fmt_value(row.ours, row.unit),
            fmt_value(row.peer, row.unit),
            fmt_advantage(row.advantage),
            row.note,
        )
    return table


def merged(path: Path, fresh: list[dict[str, Any]], ran: list[str]) -> list[dict[str, Any]]:
    """The rows kept at `path` from earlier runs of benches not in `ran`, then `fresh`: `--only x` replaces x's
    rows in runs/bench/latest.json and keeps every other bench's last figures (each row says when it was
    measured). Rows without a bench name (files from before it was recorded) or an unreadable file are dropped."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        old = []
    if not isinstance(old, list):
        old = []
    kept = [r for r in old if isinstance(r, dict) and r.get("bench") in BENCHES and r["bench"] not in ran]
    order = {name: i for i, name in enumerate(BENCHES)}
    return sorted(kept + fresh, key=lambda r: order[r["bench"]])  # stable: rows keep their order within a bench


def row_of(doc: dict[str, Any]) -> Row:
    """A Row back from its JSON (the fields Row has; bench, measured_at and advantage are derived)."""
    return Row(**{f.name: doc[f.name] for f in fields(Row) if f.name in doc})


def markdown(rows: list[Row]) -> str:
    lines = [
        "| benchmark | metric | USER (ours) | peer | ours vs peer | note |",
        "|---|---|---:|---:|---:|---|",
    ]
    last_group = None
    for r in rows:
        group = f"{r.group} vs {r.peer_name}" if r.group != last_group else ""
        last_group = r.group
        cells = [group, r.metric, fmt_value(r.ours, r.unit), fmt_value(r.peer, r.unit), fmt_advantage(r.advantage)]
        cells.append(r.note)
        lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def selected(only: str | None, quick: bool) -> list[str]:
    """The groups to run: those named, else all but the opt-in ones (and, with --quick, the slow ones)."""
    if only:
        return [n.strip() for n in only.split(",") if n.strip()]
    return [n for n in BENCHES if n not in OPT_IN and not (quick and n in SLOW)]


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    # default files (not --quick): this run's benches replace their own rows there and the others' stay
    default_json, default_md = (not args.quick and p is None for p in (args.json_path, args.md_path))
    if not args.quick:
        args.json_path = args.json_path or str(DEFAULT_OUT / "latest.json")
        args.md_path = args.md_path or str(DEFAULT_OUT / "latest.md")
    names = selected(args.only, args.quick)
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; known: {list(BENCHES)}", file=sys.stderr)
        return 2
    import torch

    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)
    console = Console(stderr=True)
    rows: list[Row] = []
    docs: list[dict[str, Any]] = []  # rows as JSON, each with its bench and when it was measured
    failed: list[str] = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="user-bench-") as tmp:
        workdir = Path(args.workdir or tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        for name in names:
            t0 = time.perf_counter()
            console.log(f"bench {name} ...")
            try:
                module = importlib.import_module(BENCHES[name])
                extra: dict = {"overrides": args.overrides} if name in TAKES_OVERRIDES else {}
                if name == "load":
                    extra |= {"duration_s": args.duration, "robots": args.edges, "hz": args.hz}
                got = module.run(quick=args.quick, workdir=workdir / name, log=console.log, **extra)
                rows += got
                at = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
                docs += [{"bench": name, "measured_at": at, **r.to_json()} for r in got]
            except Exception:
                failed.append(name)
                console.print(f"[red]bench {name} failed[/red]\n{traceback.format_exc()}")
            console.log(f"bench {name} done in {time.perf_counter() - t0:.1f} s")
    cpus = os.cpu_count()
    title = (
        f"USER vs peers{' (--quick: sizes too small to mean anything)' if args.quick else ''}\n"
        f"{cpus} CPUs, torch threads 1, loopback gRPC; 'ours vs peer' > 1 means ours is better"
    )
    Console(width=max(160, Console().width)).print(render(rows, title))
    for name in names:
        print(LEGEND[name])
    print(f"total {time.perf_counter() - start:.1f} s")
    for out in (args.json_path, args.md_path):
        if out:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
    ran = [n for n in names if n not in failed]  # a failed bench keeps its last rows in the default files
    kept = merged(DEFAULT_OUT / "latest.json", docs, ran) if default_json or default_md else docs
    if args.json_path:
        Path(args.json_path).write_text(json.dumps(kept if default_json else docs, indent=1, default=str))
    if args.md_path:
        shown = kept if default_md else docs
        when: dict[str, str] = {}
        for d in shown:
            when.setdefault(d["bench"], d["measured_at"])
        legend = "".join(f"\n- ({when[n]}) {LEGEND[n]}" for n in when)
        table = markdown([row_of(d) for d in shown])
        Path(args.md_path).write_text(f"{title.replace(chr(10), '; ')}\n\n{table}{legend}\n")
    if args.json_path or args.md_path:
        print(f"wrote {', '.join(p for p in (args.json_path, args.md_path) if p)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
