"""Replay alone under a steady insert + sample load, its memory traced: does it level off?

    python -m bench.replay_soak [--minutes 20] [--robots 64] [--rate 640] [--set replay.capacity_mb=32]
                                [--tracemalloc] [--env MALLOC_ARENA_MAX=2]

The real replay service (ReplayService: gRPC server, writer, LMDB store, hot tier, prefetch) runs in its own
process; only its spec source is a fixed table instead of control. The driver streams steps shaped like the
load run's (sim_reach_arm: 15 float32 state, 3 float32 actions, 50-step episodes, `robots_per_stream` robots
per Insert stream like an edge process) at `--rate` steps/s in total, and samples as the learner does
(Sample of 128 over every robot, Stats every 2 s). The service process reports every `--every` seconds
(a JSON line in DIR/mem.jsonl): VmRSS split into RssAnon and RssFile (LMDB's map is file-backed: not a leak),
glibc's mallinfo2 (bytes in use vs. free bytes kept by malloc), Python's own allocator (sys._debugmallocstats
is too slow; tracemalloc's traced bytes with --tracemalloc, plus its top growth sites between the first
report after --trace-from and the last), the store's counts and hot-tier bytes, and its thread count.

The summary gives each series' slope (MB/min) over the second half. No thresholds: this measures.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

STATE_DIM, ACTION_DIM, EPISODE_STEPS = 15, 3, 50  # sim_reach_arm without a camera, as in the load run
TOKEN = "soak-token"


def robot_spec(robot_id: str) -> Any:
    from user.v1 import robot_pb2
    from user.v1 import tensor_pb2 as tpb

    return robot_pb2.RobotSpec(
        robot_id=robot_id,
        kind="sim_reach_arm",
        action=robot_pb2.ActionSpace(shape=[ACTION_DIM], low=[-1.0] * 3, high=[1.0] * 3, dtype=tpb.DTYPE_FLOAT32),
        observation=[robot_pb2.FeatureSpec(name="state", dtype=tpb.DTYPE_FLOAT32, shape=[STATE_DIM])],
        control_rate_hz=10,
        max_episode_steps=EPISODE_STEPS,
    )


# --------------------------------------------------------------------------- /proc and malloc


def proc_status(pid: int | str = "self") -> dict[str, float]:
    """VmRSS, RssAnon, RssFile (MB) and Threads of a process."""
    out: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
            out[key] = int(value.split()[0]) / 1024
        elif key == "Threads":
            out[key] = int(value)
    return out


class _Mallinfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                     "keepcost")
    ]  # fmt: skip


def mallinfo() -> dict[str, float]:
    """glibc's heap over all arenas (MB): `arena` sbrk/mmap'd heap, `hblkhd` mmap'd chunks, `uordblks` in use,
    `fordblks` free but kept. Empty where glibc lacks mallinfo2 (< 2.33)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        fn = libc.mallinfo2
    except (OSError, AttributeError):
        return {}
    fn.restype = _Mallinfo2
    m = fn()
    return {k: getattr(m, k) / 2**20 for k in ("arena", "hblkhd", "uordblks", "fordblks", "keepcost")}


# --------------------------------------------------------------------------- the service process


def structures(store: Any) -> dict[str, int]:
    """Sizes of the store's growable structures (read without its lock: a report, not an invariant)."""
    index = store.index
    return {
        "py_blocks": sys.getallocatedblocks(),
        "writer_queue": len(store._queue),
        "tails": len(store._tails),
        "store_episodes": len(store._episodes),
        "index_rows": index.n_rows,
        "index_slots": len(index.prefixes),
        "index_col_bytes": sum(
            getattr(index, name).a.nbytes for name in vars(index) if hasattr(getattr(index, name), "fill")
        ),
    }


def serve(args: argparse.Namespace) -> int:
    import tracemalloc

    from services.replay.server import ReplayService
    from user.config import load_config

    if args.tracemalloc:
        tracemalloc.start(args.trace_frames)
    base = [f"auth.token={TOKEN}", f"replay.path={Path(args.dir) / 'replay'}", f"replay.server.port={args.port}"]
    cfg = load_config(None, [*base, "replay.server.metrics_port=0", *args.set], environ={})
    specs = {f"arm-{i}": robot_spec(f"arm-{i}") for i in range(args.robots)}
    svc = ReplayService(cfg, spec_source=specs.get, start_metrics=False).start()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    t0, first, trim = time.monotonic(), None, ctypes.CDLL("libc.so.6").malloc_trim if args.trim_every else None
    next_trim, next_objects = args.trim_every, 0.0
    Path(args.dir, "ready").write_text(svc.address)
    with open(Path(args.dir) / "mem.jsonl", "a") as out:
        while not stop.wait(args.every):
            t = time.monotonic() - t0
            if trim is not None and t >= next_trim:
                trim(0)
                next_trim += args.trim_every
            row: dict[str, Any] = {"t": round(t, 1), **proc_status(), **{f"m_{k}": v for k, v in mallinfo().items()}}
            st = svc.store.stats()
            row.update(steps=st["steps"], transitions=st["transitions"], episodes=st["episodes"])
            row["evicted"] = sum(st["evicted_steps_per_robot"].values())
            cache = svc.store.cache_info()
            row.update(hot_mb=cache["bytes"] / 2**20, hot_rows=cache["entries"], hot_capacity=cache["capacity"])
            row.update(hot_hits=cache["hits"], hot_misses=cache["misses"])
            row["guard_episodes"] = len(svc.servicer.episodes._episodes)  # the episode guard's memory grows with it
            row.update(structures(svc.store))
            if args.objects and t >= next_objects:  # gc-tracked objects by type (ints, strs, bytes are not tracked)
                next_objects += args.objects
                row["objects"] = dict(Counter(type(o).__name__ for o in gc.get_objects()).most_common(12))
            if args.tracemalloc:
                row["traced_mb"] = tracemalloc.get_traced_memory()[0] / 2**20
                if t >= args.trace_from:
                    snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
                    if first is None:
                        first = snap
                    else:
                        top = snap.compare_to(first, "traceback")[:12]
                        row["growth"] = [
                            [round(s.size_diff / 2**20, 3), s.count_diff, " <- ".join(
                                f"{Path(f.filename).name}:{f.lineno}" for f in s.traceback[:4])]
                            for s in top
                        ]  # fmt: skip
            out.write(json.dumps(row) + "\n")
            out.flush()
    svc.stop()
    return 0


# --------------------------------------------------------------------------- the driver


def _steps(robots: list[str], rng: np.random.Generator, episode: dict[str, int], index: dict[str, int]):
    """One step of every robot in `robots`, in turn, forever; the 50th step of an episode ends it."""
    from user import wire
    from user.v1 import step_pb2

    while True:
        for rid in robots:
            t = index[rid]
            last = t == EPISODE_STEPS - 1
            step = step_pb2.Step(
                robot_id=rid,
                episode_id=f"ep-{episode[rid]}",
                step_index=t,
                observation=wire.to_tensor_map({"state": rng.standard_normal(STATE_DIM).astype(np.float32)}),
                action=wire.to_tensor(rng.uniform(-1, 1, ACTION_DIM).astype(np.float32)),
                reward=float(rng.standard_normal()),
                truncated=last,
                policy_version=1,
                observed_at_ns=time.time_ns(),
                acted_at_ns=time.time_ns(),
            )
            if last:
                step.final_observation.CopyFrom(
                    wire.to_tensor_map({"state": rng.standard_normal(STATE_DIM).astype(np.float32)})
                )
                episode[rid] += 1
                index[rid] = 0
            else:
                index[rid] += 1
            yield step


def insert_stream(addr: str, robots: list[str], rate: float, stop: threading.Event, counts: dict[str, int]) -> None:
    """One edge's Insert stream: its robots' steps at `rate` steps/s, acks read as they come."""
    import grpc

    from user.config import AuthConfig
    from user.rpc import make_channel
    from user.v1 import replay_pb2, replay_pb2_grpc

    stub = replay_pb2_grpc.ReplayStub(make_channel(addr, AuthConfig(token=TOKEN)))
    rng = np.random.default_rng(abs(hash(robots[0])) % 2**32)
    episode, index = dict.fromkeys(robots, 0), dict.fromkeys(robots, 0)
    source = _steps(robots, rng, episode, index)

    def requests():
        seq, t_next = 0, time.monotonic()
        while not stop.is_set():
            for _ in range(len(robots)):  # one tick: a step of each robot
                yield replay_pb2.InsertRequest(seq=seq, step=next(source))
                seq += 1
            t_next += len(robots) / rate
            time.sleep(max(0.0, t_next - time.monotonic()))

    try:
        for ack in stub.Insert(requests(), timeout=24 * 3600):
            counts["acked"] += len(ack.seqs)
    except grpc.RpcError as err:
        if not stop.is_set():  # at the end the service shuts down under open streams
            counts[f"insert {err.code().name}"] = counts.get(f"insert {err.code().name}", 0) + 1


def sampler(addr: str, robots: list[str], stop: threading.Event, counts: dict[str, int], pause_s: float) -> None:
    """The learner's side: Sample(128) over every robot back to back, Stats every 2 s."""
    import grpc

    from user.config import AuthConfig
    from user.rpc import make_channel
    from user.v1 import replay_pb2, replay_pb2_grpc

    stub = replay_pb2_grpc.ReplayStub(make_channel(addr, AuthConfig(token=TOKEN)))
    next_stats = 0.0
    while not stop.is_set():
        try:
            stub.Sample(replay_pb2.SampleRequest(batch_size=128, robot_ids=robots), timeout=30)
            counts["samples"] += 1
        except grpc.RpcError as err:
            counts[f"sample {err.code().name}"] = counts.get(f"sample {err.code().name}", 0) + 1
            time.sleep(0.5)
        if time.monotonic() >= next_stats:
            stub.Stats(replay_pb2.StatsRequest(), timeout=30)
            next_stats = time.monotonic() + 2.0
        stop.wait(pause_s)


def slope(ts: np.ndarray, ys: np.ndarray) -> float:
    """MB/min fitted over the second half."""
    half = ts >= ts[-1] / 2
    return float(np.polyfit(ts[half], ys[half], 1)[0] * 60) if half.sum() >= 3 else math.nan


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ts = np.array([r["t"] for r in rows])
    keys = ["VmRSS", "RssAnon", "RssFile", "m_arena", "m_hblkhd", "m_uordblks", "m_fordblks", "hot_mb", "traced_mb"]
    out: dict[str, Any] = {}
    for k in keys:
        if k in rows[0]:
            ys = np.array([r[k] for r in rows], float)
            half = ts >= ts[-1] / 2
            out[k] = {
                "start": round(ys[0], 1),
                "mid": round(float(ys[half][0]), 1),
                "end": round(ys[-1], 1),
                "min_2nd_half": round(float(ys[half].min()), 1),
                "max_2nd_half": round(float(ys[half].max()), 1),
                "slope_mb_min_2nd_half": round(slope(ts, ys), 3),
            }
    return out


def drive(args: argparse.Namespace) -> int:
    work = Path(args.dir or tempfile.mkdtemp(prefix="replay-soak-"))
    work.mkdir(parents=True, exist_ok=True)
    for f in ("mem.jsonl", "ready"):
        (work / f).unlink(missing_ok=True)
    env = dict(os.environ)
    for kv in args.env:
        k, _, v = kv.partition("=")
        env[k] = v
    cmd = [
        sys.executable,
        "-m",
        "bench.replay_soak",
        "--serve",
        "--dir",
        str(work),
        "--robots",
        str(args.robots),
        "--every",
        str(args.every),
        "--trace-from",
        str(args.trace_from),
        "--trim-every",
        str(args.trim_every),
        "--trace-frames",
        str(args.trace_frames),
        "--objects",
        str(args.objects),
    ]
    cmd += [a for s in args.set for a in ("--set", s)] + (["--tracemalloc"] if args.tracemalloc else [])  # fmt: skip
    proc = subprocess.Popen(cmd, env=env)
    try:
        while not (work / "ready").exists():
            if proc.poll() is not None:
                raise SystemExit(f"replay exited {proc.returncode}")
            time.sleep(0.2)
        addr = (work / "ready").read_text()
        robots = [f"arm-{i}" for i in range(args.robots)]
        stop, counts = threading.Event(), {"acked": 0, "samples": 0}
        per = args.robots_per_stream
        groups = [robots[i : i + per] for i in range(0, len(robots), per)]
        threads = [
            threading.Thread(target=insert_stream, args=(addr, g, args.rate * len(g) / len(robots), stop, counts))
            for g in groups
        ]
        threads.append(threading.Thread(target=sampler, args=(addr, robots, stop, counts, args.sample_pause)))
        for th in threads:
            th.daemon = True
            th.start()
        t0, end = time.monotonic(), time.monotonic() + args.minutes * 60
        while time.monotonic() < end:
            time.sleep(min(60.0, end - time.monotonic()))
            rows = _rows(work)
            if rows:
                r = rows[-1]
                print(
                    f"[{time.monotonic() - t0:5.0f} s] load {os.getloadavg()[0]:.1f}; acked {counts['acked']}, "
                    f"samples {counts['samples']}; stored {r['steps']} evicted {r['evicted']}; RSS {r['VmRSS']:.1f} "
                    f"anon {r['RssAnon']:.1f} file {r['RssFile']:.1f} MB; hot {r['hot_mb']:.1f} MB; malloc in use "
                    f"{r.get('m_uordblks', math.nan):.1f} free {r.get('m_fordblks', math.nan):.1f} MB; "
                    f"threads {r['Threads']}; guard {r['guard_episodes']} episodes",
                    flush=True,
                )
        stop.set()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    rows = _rows(work)
    result = {"options": vars(args), "counts": counts, "loadavg_end": os.getloadavg(), "summary": summarize(rows)}
    if rows and "growth" in rows[-1]:
        result["tracemalloc_growth_top"] = rows[-1]["growth"]
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps({**result, "series": rows}, indent=1) + "\n")
    return 0


def _rows(work: Path) -> list[dict[str, Any]]:
    path = work / "mem.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)  # the service process
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--dir", default="", help="work directory (LMDB, mem.jsonl); default a fresh temp dir")
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--robots", type=int, default=64)
    ap.add_argument("--robots-per-stream", type=int, default=8, help="robots per Insert stream (an edge process)")
    ap.add_argument("--rate", type=float, default=640.0, help="steps/s over all robots (64 at 10 Hz = 640)")
    ap.add_argument("--sample-pause", type=float, default=0.02, help="seconds between the sampler's calls")
    ap.add_argument("--every", type=float, default=10.0, help="seconds between the service's memory reports")
    ap.add_argument("--set", action="append", default=[], help="config override, e.g. replay.capacity_mb=32")
    ap.add_argument("--env", action="append", default=[], help="environment of the service, e.g. MALLOC_ARENA_MAX=2")
    ap.add_argument("--tracemalloc", action="store_true", help="trace Python allocations in the service (slower)")
    ap.add_argument("--trace-frames", type=int, default=4, help="frames per tracemalloc traceback")
    ap.add_argument("--trace-from", type=float, default=300.0, help="seconds: the tracemalloc baseline")
    ap.add_argument("--objects", type=float, default=0.0, help="seconds between gc object counts; 0 = none")
    ap.add_argument("--trim-every", type=float, default=0.0, help="seconds between malloc_trim(0) calls; 0 = none")
    ap.add_argument("--out", default="", help="write the summary and the series here (JSON)")
    args = ap.parse_args()
    return serve(args) if args.serve else drive(args)


if __name__ == "__main__":
    raise SystemExit(main())
