"""Load: many simulated robots at a fixed control rate against one stack on loopback, for minutes.

    python -m bench --only load [--duration 600] [--edges 64] [--hz 10]      (= make load)

One real stack on 127.0.0.1 (`userctl up`'s Stack: control, replay, learner, inference, each its own
process, token auth on, the learner training SAC so weights stream to inference) and `--edges`
state-only sim arms (sim_reach_arm, no camera) in edge agent processes of `robots_per_agent` robots
each: the real `userctl edge` code path (registration and heartbeats with control, Inference.Act
within the action deadline, every step spooled on disk and streamed to replay until acked).

After a warm-up (every robot online, first weights published) a window of `--duration` seconds is
measured from the processes' own /metrics (deltas of counters and histograms between the window's
ends) and /proc:

- achieved control rate per robot and the share of held steps (no action within the deadline);
- p50/p99 of Act as the edges see it (`user_edge_action_latency_seconds`) and of insert acks
  (`user_edge_step_ack_seconds`: a step entering the spool -> replay acknowledging its commit);
- gRPC errors the edges saw, by method and status code, and non-OK codes the services answered;
- resident memory of every process at the window's start and end, and its slope over the second half;
- learner updates and weight versions published.

Then every robot is paused, the spools drain, and each robot's steps are counted on both sides:
lost = steps the edge collected (`user_edge_env_steps_total`) - steps replay stores for it
(Stats.steps_per_robot). Replay keys steps by (robot, episode, step), so none is stored twice; re-sends
it deduplicated are reported. Peer column: the control-rate target, or a process's RSS at the start.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import statistics
import time
import urllib.request
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from prometheus_client.parser import text_string_to_metric_families

from bench import Row

SERVICES = ("control", "replay", "learner", "inference")
ROBOT_KIND = "sim_reach_arm"
EXPERIMENT = "reach"
PEER = "target / RSS at start"
ACT_HIST = "user_edge_action_latency_seconds"
ACK_HIST = "user_edge_step_ack_seconds"


@dataclass
class LoadOptions:
    duration_s: float = 600.0
    robots: int = 64
    hz: float = 10.0
    robots_per_agent: int = 8
    action_deadline_ms: float = 40.0
    warmup_s: float = 5.0  # after every robot is online and the first weights are out
    sample_s: float = 5.0  # RSS / progress sampling period
    drain_timeout_s: float = 120.0  # liveness bound on the spools draining after the pause
    wait_for_weights: bool = True
    learner_nice: int = 0  # >0: the learner yields CPU to the control path (it has its own GPU box in production)
    blackhole_agents: int = 0  # test only: the last N agents write to a closed port (their steps are lost)
    overrides: list[str] = field(default_factory=list)

    @property
    def agents(self) -> int:
        return math.ceil(self.robots / self.robots_per_agent)


# --------------------------------------------------------------------------- /proc and /metrics


def _closed_port() -> int:
    """A loopback port nobody listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> tuple[float, float]:
    """(resident MB, of which anonymous MB). File-backed pages (LMDB's map, shared libraries) are the rest:
    a growing LMDB file grows RSS without any allocation, so leaks show in the anonymous part."""
    fields = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "RssAnon"):
                fields[key] = int(value.split()[0]) / 1024
    except (OSError, ValueError):
        pass
    return fields.get("VmRSS", math.nan), fields.get("RssAnon", math.nan)


def cpu_s(pid: int) -> float:
    """utime + stime of the process (all its threads), seconds."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return math.nan


Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def scrape(url: str, timeout: float = 10.0) -> Samples:
    """Every sample of a /metrics page: (name, sorted labels) -> value."""
    with urllib.request.urlopen(url, timeout=timeout) as resp:
        text = resp.read().decode()
    out: Samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = float(s.value)
    return out


def merged(scrapes: list[Samples]) -> Samples:
    """Samples of several processes summed (counters and histogram buckets add up)."""
    out: Samples = defaultdict(float)
    for samples in scrapes:
        for key, value in samples.items():
            out[key] += value
    return dict(out)


def delta(end: Samples, start: Samples) -> Samples:
    return {k: v - start.get(k, 0.0) for k, v in end.items()}


def total(samples: Samples, name: str, **labels: str) -> float:
    want = set(labels.items())
    return sum(v for (n, lab), v in samples.items() if n == name and want <= set(lab))


def by_label(samples: Samples, name: str, *keys: str) -> dict[tuple[str, ...], float]:
    out: dict[tuple[str, ...], float] = defaultdict(float)
    for (n, lab), v in samples.items():
        if n == name:
            d = dict(lab)
            out[tuple(d.get(k, "") for k in keys)] += v
    return dict(out)


def histogram_quantile(samples: Samples, name: str, q: float, **labels: str) -> float:
    """Prometheus' histogram_quantile over the cumulative buckets (linear inside a bucket); NaN if empty.
    A quantile in the +Inf bucket is reported as the largest finite bound."""
    buckets: dict[float, float] = defaultdict(float)
    want = set(labels.items())
    for (n, lab), v in samples.items():
        if n == f"{name}_bucket" and want <= set(lab):
            buckets[float(dict(lab)["le"])] += v
    bounds = sorted(buckets)
    if not bounds or buckets[bounds[-1]] <= 0:
        return math.nan
    rank = q * buckets[bounds[-1]]
    lower, below = 0.0, 0.0
    for bound in bounds:
        count = buckets[bound]
        if count >= rank:
            if math.isinf(bound):
                return lower
            inside = count - below
            return lower + (bound - lower) * ((rank - below) / inside if inside > 0 else 1.0)
        lower, below = bound, count
    return lower


# --------------------------------------------------------------------------- the run


class LoadRun:
    """The stack, the edge agents and their measurements; run() returns the result document."""

    def __init__(self, opts: LoadOptions, workdir: Path, log: Callable[..., None]) -> None:
        from user.config import load_config
        from user.up import Stack

        self.opts, self.workdir, self.log = opts, workdir, log
        workdir.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(workdir / "stack", ignore_errors=True)  # a fresh replay and spools: counts start at 0
        self.config_path = workdir / "load.yaml"
        self.config_path.write_text(yaml.safe_dump(self._config()))
        self.cfg = load_config(self.config_path, opts.overrides)
        self.stack = Stack(self.cfg, str(self.config_path), list(opts.overrides), workdir / "stack")
        self.robot_agent: dict[str, str] = {}
        self.rss: dict[str, list[tuple[float, float, float]]] = defaultdict(list)  # process -> [(t, MB, anon MB)]

    def _config(self) -> dict[str, Any]:
        return {
            "log_level": "INFO",
            "log_json": True,
            "auth": {"enabled": True},  # the Stack makes a fresh token; every process uses it
            "learner": {"torch_threads": 1},
            "experiments": [
                {
                    "name": EXPERIMENT,
                    "robots": {"kinds": [ROBOT_KIND]},
                    "algorithm": {"kind": "sac", "params": {"hidden": [128, 128], "batch_size": 128}},
                }
            ],
            "edge": {
                "mode": "realtime",
                "policy_source": "remote",
                "action_deadline_ms": self.opts.action_deadline_ms,
            },
        }

    # ------------------------------------------------------------------ parts

    def _stubs(self):
        from user.rpc import make_channel
        from user.v1 import control_pb2_grpc, learner_pb2_grpc, replay_pb2_grpc

        auth = self.stack.auth
        return (
            control_pb2_grpc.ControlStub(make_channel(self.stack.child("control").grpc_addr, auth)),
            learner_pb2_grpc.LearnerStub(make_channel(self.stack.child("learner").grpc_addr, auth)),
            replay_pb2_grpc.ReplayStub(make_channel(self.stack.child("replay").grpc_addr, auth)),
        )

    def _start(self) -> None:
        opts = self.opts
        t0 = time.monotonic()
        self.stack.start_services(lambda name: self.log(f"load: starting {name}"))
        if opts.learner_nice > 0:
            os.setpriority(os.PRIO_PROCESS, self.stack.child("learner").proc.pid, opts.learner_nice)
        agents = []
        for a in range(opts.agents):
            ids = range(a * opts.robots_per_agent, min(opts.robots, (a + 1) * opts.robots_per_agent))
            robots = [
                {
                    "id": f"arm-{i}",
                    "kind": ROBOT_KIND,
                    "params": {"control_rate_hz": opts.hz, "max_episode_steps": 50},
                }
                for i in ids
            ]
            name = f"edge-{a}"
            extra = []
            if a >= opts.agents - opts.blackhole_agents:
                extra.append(f"edge.replay_addr=127.0.0.1:{_closed_port()}")
            for r in robots:
                self.robot_agent[r["id"]] = name
            agents.append(self.stack.spawn_edge(name, robots, seed=1000 * a, extra=extra))
        for child in agents:
            self.stack.wait_ready(child)
        self.log(f"load: {opts.robots} robots in {opts.agents} edge processes up in {time.monotonic() - t0:.0f} s")

    @property
    def edges(self):
        return [c for c in self.stack.children if c.name.startswith("edge-")]

    def _scrape_edges(self) -> Samples:
        return self._scrape_edges_timed()[0]

    def _scrape_edges_timed(self) -> tuple[Samples, dict[str, float]]:
        """The edges' samples merged, and when each edge was read (the middle of its request, monotonic)."""
        pages, when = [], {}
        for c in self.edges:
            start = time.monotonic()
            pages.append(scrape(f"http://127.0.0.1:{c.info['metrics_port']}/metrics"))
            when[c.name] = (start + time.monotonic()) / 2
        return merged(pages), when

    def _scrape_services(self) -> dict[str, Samples]:
        return {name: scrape(self.stack.child(name).metrics_url) for name in SERVICES}

    def _sample_rss(self, t: float) -> None:
        for child in self.stack.children:
            self.rss[child.name].append((t, *rss_mb(child.proc.pid)))

    def _cpu(self) -> dict[str, float]:
        return {c.name: cpu_s(c.proc.pid) for c in self.stack.children}

    def _check_alive(self) -> None:
        dead = self.stack.dead_children()
        if dead:
            raise RuntimeError(f"{dead[0].name} exited with {dead[0].proc.returncode}:\n{dead[0].log_tail()}")

    def _warm_up(self, control, learner) -> None:
        from user.v1 import control_pb2, learner_pb2

        deadline = time.monotonic() + 600.0  # liveness bound: something is stuck
        while time.monotonic() < deadline:
            self._check_alive()
            robots = control.ListRobots(control_pb2.ListRobotsRequest(), timeout=10).robots
            online = sum(1 for r in robots if r.online)
            status = learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10)
            version = max((e.weight_version for e in status.experiments), default=0)
            if online >= self.opts.robots and (version >= 1 or not self.opts.wait_for_weights):
                self.log(f"load: {online} robots online, weights v{version}; warming up {self.opts.warmup_s:.0f} s")
                time.sleep(self.opts.warmup_s)
                return
            time.sleep(1.0)
        raise RuntimeError("load: the robots did not all come online, or no weights were published, in 600 s")

    def _learner(self, learner) -> tuple[int, int]:
        from user.v1 import learner_pb2

        status = learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10)
        exp = next((e for e in status.experiments if e.name == EXPERIMENT), None)
        return (int(exp.updates), int(exp.weight_version)) if exp else (0, 0)

    def _pause_and_drain(self, control) -> Samples:
        """PAUSE every robot, wait until the step counts stop and the spools are empty (or the bound
        passes: an agent that cannot reach replay never drains). Returns the edges' final samples."""
        from user.v1 import control_pb2

        cmd = control_pb2.Command(kind=control_pb2.COMMAND_KIND_PAUSE)
        control.SendCommand(control_pb2.SendCommandRequest(command=cmd, wait_result_s=10), timeout=15)
        deadline = time.monotonic() + self.opts.drain_timeout_s
        last, steady = None, 0
        while True:
            samples = self._scrape_edges()
            steps = total(samples, "user_edge_env_steps_total")
            unacked = total(samples, "user_edge_steps_unacked")
            steady = steady + 1 if steps == last else 0
            last = steps
            if steady >= 2 and unacked == 0:
                return samples
            if time.monotonic() > deadline:
                self.log(f"load: spools not drained after {self.opts.drain_timeout_s:.0f} s ({unacked:.0f} unacked)")
                return samples
            time.sleep(0.5)

    # ------------------------------------------------------------------ measurement

    def run(self) -> dict[str, Any]:
        opts = self.opts
        load_start = os.getloadavg()
        try:
            self._start()
            control, learner, replay = self._stubs()
            self._warm_up(control, learner)
            # The window is timed between the two edge scrapes (the counters it divides), per edge: a scrape
            # reads the edges one after another and the first one takes seconds under load, so each robot's
            # rate divides by the time between its own edge's two reads (start-to-end of the scrapes read
            # 1-2 % low, their middles up to 1 % high).
            t0 = time.monotonic()
            edges0, read0 = self._scrape_edges_timed()
            services0, cpu0 = self._scrape_services(), self._cpu()
            updates0, version0 = self._learner(learner)
            self._sample_rss(0.0)
            next_log = t0 + 60
            while (now := time.monotonic()) < t0 + opts.duration_s:
                time.sleep(min(opts.sample_s, t0 + opts.duration_s - now))
                self._check_alive()
                self._sample_rss(time.monotonic() - t0)
                if time.monotonic() >= next_log:
                    next_log += 60
                    self.log(f"load: {time.monotonic() - t0:.0f}/{opts.duration_s:.0f} s, load {os.getloadavg()}")
            t1 = time.monotonic()
            edges1, read1 = self._scrape_edges_timed()
            scrape_s = [max(read0.values()) - t0, time.monotonic() - t1]
            edge_windows = {name: read1[name] - read0[name] for name in read0}
            window = statistics.fmean(edge_windows.values())
            services1, cpu1 = self._scrape_services(), self._cpu()
            updates1, version1 = self._learner(learner)
            load_end = os.getloadavg()
            final = self._pause_and_drain(control)
            from user.v1 import replay_pb2

            stats = replay.Stats(replay_pb2.StatsRequest(), timeout=30)
        finally:
            codes = self.stack.stop()
        result = self._result(edges0, edges1, services0, services1, edge_windows, final, stats)
        result.update(
            cpu_share={k: (cpu1[k] - cpu0[k]) / window for k in cpu1},
            learner={"updates": updates1 - updates0, "versions": version1 - version0, "version_end": version1},
            edge_scrape_s=scrape_s,  # how long each of the window's two edge scrapes took
            cpu_ms_per_step=cpu_per_step(cpu0, cpu1, sum(result["rate_hz"].values()) * window),
            loadavg_start=load_start,
            loadavg_end=load_end,
            exit_codes=codes,
            options=vars(opts),
        )
        return result

    def _result(
        self,
        edges0: Samples,
        edges1: Samples,
        services0: dict[str, Samples],
        services1: dict[str, Samples],
        edge_windows: dict[str, float],
        final: Samples,
        stats: Any,
    ) -> dict[str, Any]:
        d = delta(edges1, edges0)
        steps = by_label(d, "user_edge_env_steps_total", "robot_id")
        held = by_label(d, "user_edge_held_steps_total", "robot_id")
        window = statistics.fmean(edge_windows.values())
        rates = {rid: n / edge_windows.get(self.robot_agent.get(rid, ""), window) for (rid,), n in steps.items()}
        collected = {rid: int(n) for (rid,), n in by_label(final, "user_edge_env_steps_total", "robot_id").items()}
        # with replay.capacity_mb, whole episodes leave by design: stored + evicted is what replay took
        evicted = {rid: int(stats.evicted_steps_per_robot.get(rid, 0)) for rid in collected}
        stored = {rid: int(stats.steps_per_robot.get(rid, 0)) + evicted[rid] for rid in collected}
        lost = {rid: collected[rid] - stored[rid] for rid in collected}
        client = by_label(d, "user_grpc_client_errors_total", "method", "code")
        client_errors = {f"{m} {c}": int(v) for (m, c), v in client.items() if v}
        client = by_label(final, "user_grpc_client_errors_total", "method", "code")
        client_errors_run = {f"{m} {c}": int(v) for (m, c), v in client.items() if v}
        server_errors = {}
        for name in SERVICES:
            sd = delta(services1[name], services0[name])
            for (method, code), v in by_label(sd, "user_grpc_server_handled_total", "method", "code").items():
                if code != "OK" and v:
                    server_errors[f"{name} {method} {code}"] = int(v)
        rss = {}
        for proc, series in self.rss.items():
            ts, mb, anon = (np.array(col) for col in zip(*series, strict=True))
            half = ts >= ts[-1] / 2

            def slope(y: np.ndarray, half: np.ndarray = half, ts: np.ndarray = ts) -> float:
                return float(np.polyfit(ts[half], y[half], 1)[0] * 60) if half.sum() >= 3 else math.nan

            rss[proc] = {
                "start_mb": float(mb[0]),
                "end_mb": float(mb[-1]),
                "slope_mb_per_min": slope(mb),
                "anon_start_mb": float(anon[0]),
                "anon_end_mb": float(anon[-1]),
                "anon_slope_mb_per_min": slope(anon),
                "series": [[round(float(t), 1), round(float(m), 1), round(float(a), 1)] for t, m, a in series],  # s, MB
            }
        return {
            "window_s": window,
            "robots": len(steps),
            "rate_hz": rates,
            "held_share": sum(held.values()) / max(1.0, sum(steps.values())),
            "act_p50_s": histogram_quantile(d, ACT_HIST, 0.5, source="remote"),
            "act_p99_s": histogram_quantile(d, ACT_HIST, 0.99, source="remote"),
            "acts": total(d, f"{ACT_HIST}_count"),
            "ack_p50_s": histogram_quantile(d, ACK_HIST, 0.5),
            "ack_p99_s": histogram_quantile(d, ACK_HIST, 0.99),
            "acks": total(d, f"{ACK_HIST}_count"),
            "overruns": total(d, "user_edge_loop_overruns_total"),
            "client_errors": client_errors,
            "client_errors_whole_run": client_errors_run,  # start-up included (no weights yet: UNAVAILABLE)
            "server_errors": server_errors,
            "collected": sum(collected.values()),
            "acked": int(total(final, "user_edge_steps_acked_total")),
            "unacked": int(total(final, "user_edge_steps_unacked")),
            "stored": sum(stored.values()),
            "evicted": sum(evicted.values()),
            "replay_steps": int(stats.steps),
            "lost": sum(lost.values()),
            "lost_per_robot": lost,
            "collected_per_robot": collected,
            "deduplicated": int(stats.duplicates),
            "rejected": int(stats.rejected),
            "rss": rss,
            "agent_of_robot": dict(self.robot_agent),
            # replay's RAM tier (a cache up to replay.cache_mb) grows with the data: part of its RSS growth
            "replay_hot_mb": [total(s["replay"], "user_replay_hot_bytes") / 2**20 for s in (services0, services1)],
            # share of sampled transitions served from RAM (since start): low = reads from LMDB
            "replay_hot_hit_rate": total(services1["replay"], "user_replay_hot_hit_rate"),
        }


def cpu_per_step(cpu0: dict[str, float], cpu1: dict[str, float], steps: float) -> dict[str, float]:
    """CPU milliseconds per robot step (`steps`: every robot's steps in the window), by process kind (the
    edges summed) and in all: on a CPU-bound machine this, not the rate, says what a tick costs and where."""
    out: dict[str, float] = defaultdict(float)
    for name in cpu1:
        out["edge" if name.startswith("edge-") else name] += 1e3 * (cpu1[name] - cpu0[name]) / max(steps, 1.0)
    out["all"] = sum(out.values())
    return dict(out)


# --------------------------------------------------------------------------- rows


def _fmt_counts(counts: dict[str, int]) -> str:
    return "; ".join(f"{k}: {v}" for k, v in sorted(counts.items())) or "none"


def rows(result: dict[str, Any]) -> list[Row]:
    opts = result["options"]
    agents = math.ceil(opts["robots"] / opts["robots_per_agent"])
    group = f"load {opts['robots']} robots ({agents} edge processes) {opts['hz']:g} Hz {opts['duration_s']:.0f} s"
    if opts.get("overrides"):
        group += ", " + ", ".join(opts["overrides"])
    rates = list(result["rate_hz"].values()) or [0.0]
    la0, la1 = result["loadavg_start"][0], result["loadavg_end"][0]
    ms = 1e3

    def fact(metric: str, ours: float | str, unit: str = "", note: str = "") -> Row:
        return Row(group, metric, ours, "", unit, None, note, PEER)

    out = [
        Row(group, "control rate per robot, median", statistics.median(rates), float(opts["hz"]), "Hz", True,
            f"min {min(rates):.2f}, max {max(rates):.2f} Hz over {result['window_s']:.0f} s; "
            f"{result['overruns']:.0f} ticks skipped; the stack used {sum(result['cpu_share'].values()):.2f} of "
            f"{os.cpu_count()} cores; load avg {la0:.1f} -> {la1:.1f}", PEER),
        fact("CPU per robot step, all processes", result.get("cpu_ms_per_step", {}).get("all", math.nan), "ms",
             ", ".join(f"{k} {v:.3f}" for k, v in sorted(result.get("cpu_ms_per_step", {}).items()) if k != "all")
             + " ms (the learner takes what is left)"),
        fact("steps held (no action in deadline)", 100 * result["held_share"], "%",
             f"deadline {opts['action_deadline_ms']:g} ms"),
        fact("Act p50", result["act_p50_s"] * ms, "ms", f"{result['acts']:.0f} answered, edge histogram"),
        fact("Act p99", result["act_p99_s"] * ms, "ms", "answered requests (late ones held, counted in errors)"),
        fact("insert ack p50", result["ack_p50_s"] * ms, "ms", f"{result['acks']:.0f} acks: spool put -> commit ack"),
        fact("insert ack p99", result["ack_p99_s"] * ms, "ms", "replay.durability fsync"),
        fact("gRPC errors seen by edges", _fmt_counts(result["client_errors"]), note="by method and code, in window"),
        fact("non-OK codes answered by services", _fmt_counts(result["server_errors"])),
        fact("steps lost (collected - stored)", f"{result['lost']} of {result['collected']}",
             note=f"acked {result['acked']}, unacked {result['unacked']}, stored {result['stored']}"
             f" (of which evicted by capacity {result.get('evicted', 0)})"),
        fact("re-sends deduplicated", str(result["deduplicated"]), note="replay keys steps: none stored twice"),
        fact("learner weight versions published", str(result["learner"]["versions"]),
             note=f"{result['learner']['updates']} updates in window"),
    ]  # fmt: skip
    edges = [r for name, r in result["rss"].items() if name.startswith("edge-")]
    procs = [(name, result["rss"][name]) for name in SERVICES if name in result["rss"]]
    if edges:
        procs.append(
            (
                f"{len(edges)} edges (sum)",
                {key: sum(r[key] for r in edges) for key in edges[0] if key != "series"},
            )
        )
    for name, r in procs:
        cpu = result["cpu_share"].get(name)
        if cpu is None:
            cpu = sum(v for k, v in result["cpu_share"].items() if k.startswith("edge-"))
        note = (
            f"2nd half {r['slope_mb_per_min']:+.2f} MB/min; anonymous {r['anon_start_mb']:.0f} -> "
            f"{r['anon_end_mb']:.0f} MB ({r['anon_slope_mb_per_min']:+.2f} MB/min); CPU {100 * cpu:.0f} % of a core"
        )
        if name == "replay":
            hot0, hot1 = result["replay_hot_mb"]
            hits = result.get("replay_hot_hit_rate", 0.0)
            note += f"; RAM tier (cache) {hot0:.1f} -> {hot1:.1f} MB, hit rate {hits:.0%}"
        out.append(Row(group, f"RSS {name}, end", r["end_mb"], r["start_mb"], "MB", False, note, PEER))
        # after warm-up: the slope of anonymous memory (LMDB's map is file-backed) over the window's second half
        out.append(
            Row(group, f"RSS {name}, anonymous slope 2nd half", r["anon_slope_mb_per_min"], "", "MB/min", None,
                f"resident {r['slope_mb_per_min']:+.2f} MB/min; flat = within noise of 0", PEER)
        )  # fmt: skip
    return out


def run(
    quick: bool,
    workdir: Path,
    log: Callable[..., None] = print,
    duration_s: float | None = None,
    robots: int | None = None,
    hz: float | None = None,
    overrides: list[str] | None = None,
) -> list[Row]:
    opts = LoadOptions(overrides=list(overrides or []))
    if quick:
        opts.duration_s, opts.robots, opts.robots_per_agent = 10.0, 4, 2
    opts.duration_s = duration_s if duration_s is not None else opts.duration_s
    opts.robots = robots if robots is not None else opts.robots
    opts.hz = hz if hz is not None else opts.hz
    result = LoadRun(opts, workdir, log).run()
    out = Path("runs/bench/load.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, default=str))
    log(f"load: details in {out}")
    return rows(result)
