"""VLA inference for many robots: our InferenceService (dynamic batching, batched preprocessing)
vs a one-request-at-a-time server of the same flow_vla model, and (one robot, tiny SmolVLA) vs
lerobot's own async-inference PolicyServer (bench/inference_lerobot_peer.py).

The peer serves the same Inference.Act proto on the same gRPC setup but runs preprocess + forward
for one request at a time under a lock, the way openpi's websocket policy server and lerobot's
async-inference policy server serve a policy (one observation in, one chunk out, in turn). Each
robot is a separate process sending its camera images, its state and an instruction; a robot
cycles through a few observations made before the window, so the robots' own CPU is the gRPC
client and nothing else. Windows alternate ours/peer so background load hits both alike. Both
servers run in this process with one torch thread (as `services.inference.server.run` sets it; on
2 cores a second intra-op thread only fights the robots and the gRPC threads).

Two model sizes (PROFILES): the issue's toy (0.16M params, one 64x64 camera, forward ~1 ms: the
per-call gRPC/Python path dominates) and a VLA-sized one (13.9M params, two 128x128 cameras, chunks
of 16x7 in 10 flow steps: the forward dominates, and at batch 1 it is bound by reading the action
expert's weights, which a batch shares, as a real VLA's is).

Two ways of driving: closed loop (each robot sends its next request when the answer is in: the
server's saturation throughput, where latency is queueing by construction) and paced (each robot
asks at a fixed rate, as a robot executing chunks at its control rate does, from a random phase:
does each side keep up, and what are p50/p99 against its own single-robot latency?).

Besides throughput and latency, the CPU spent per Act call is measured for the closed loop: the
serving process's (time.process_time over the window: gRPC, handler, batcher, model) and the
robots' (each robot process's own). On a machine where the robots share the cores with the server,
throughput is capped near cores / (robot CPU + server CPU per call) whatever the batching does. The
targets of issue #9 are printed as rows: at 16 robots >= 4x the peer's throughput, with p99 <= 2x
our single-robot p99. For flow_vla, a second server of ours in the other `inference.continuous_batching`
mode is driven at 16 robots too (closed loop and paced, alternating windows): the "continuous batching
vs batch by batch" rows.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from bench import Row, median
from bench.inference_bench import serve_peer, start_ours
from user import rpc, wire
from user.config import AuthConfig, ServerConfig, StackConfig, load_config
from user.v1 import inference_pb2, inference_pb2_grpc
from user.v1 import tensor_pb2 as tpb

PEER = "one-request-at-a-time server (openpi / lerobot policy-server style)"
RPC_TIMEOUT_S = 60.0
OBSERVATIONS_PER_ROBOT = 8  # made before the window and cycled, so the window times serving, not numpy
TOKEN = "bench-token"
START_MARGIN_S = 1.0
STATE_DIM = 15
INSTRUCTIONS = ["reach the red target", "reach the green target", "reach the blue target"]
CONTROL_HZ = 30.0
TOP = 16  # the robot count the targets name


@dataclass(frozen=True)
class Profile:
    """One model size and how it is driven."""

    label: str  # what the group names say about the model
    cameras: tuple[str, ...]
    image: int  # square camera images, uint8
    action_dim: int
    horizon: int
    hidden: int
    flow_steps: int
    seconds: float  # per window
    paced_every: tuple[int, ...]  # paced rows: a robot asks for a chunk every this many control ticks
    concurrency: tuple[int, ...] = (1, 4, 16, 32)
    model: str = "flow_vla"  # or "smolvla": lerobot's SmolVLA at smolvla_base's size, random weights


# The toy: forward ~1 ms, so the per-call gRPC/Python path is most of the cost.
TOY = Profile("64x64 camera, chunk 8x3", ("camera.front",), 64, 3, 8, 128, 5, 2.0, (8, 1))
# VLA-sized: two 128x128 cameras, a wide context and action expert, chunks of 16 7-d actions in 10
# flow steps (pi0 uses 10); the forward (tens of ms on CPU) dominates the per-call path, and at
# batch 1 it is bound by reading the expert's weights, which a batch shares.
VLA = Profile(
    "two 128x128 cameras, chunk 16x7, 10 flow steps", ("camera.front", "camera.wrist"), 128, 7, 16, 1536, 10, 4.0, (8,)
)
# lerobot's SmolVLA at its real size (450M: SmolVLM2-500M's architecture cut to 16 layers, chunks of
# 50 in 10 flow steps, images resized to 512 px) from a local folder built here with random weights:
# a GPU-class model (10 s per chunk on 2 CPU cores), so it is only run where asked for by name.
SMOLVLA = Profile(
    "smolvla_base size, two 128x128 cameras, chunk 50x7",
    ("camera.front", "camera.wrist"),
    128,
    7,
    50,
    0,
    10,
    4.0,
    (8,),
    (1, 4, 16),
    "smolvla",
)
PROFILES = {"toy": TOY, "vla": VLA, "smolvla": SMOLVLA}
DEFAULT_PROFILES = "toy,vla"


def vla_config(profile: Profile) -> Any:
    from user.policies.flow_vla import FlowVlaConfig

    return FlowVlaConfig(
        image_keys=list(profile.cameras),
        state_keys=["state"],
        state_dim=STATE_DIM,
        action_dim=profile.action_dim,
        action_low=[-1.0] * profile.action_dim,
        action_high=[1.0] * profile.action_dim,
        horizon=profile.horizon,
        image_size=profile.image,
        hidden=profile.hidden,
        flow_steps=profile.flow_steps,
    )


def make_weights(profile: Profile, workdir: Path | None = None) -> Any:
    from user.weights import WeightSet

    if profile.model == "smolvla":
        if workdir is None:
            raise ValueError("the smolvla profile builds its checkpoint folder in a workdir")
        return smolvla_weights(profile, workdir / "smolvla")
    from user.policies.flow_vla import policy_spec, random_weights

    cfg = vla_config(profile)
    return WeightSet(1, policy_spec(cfg), random_weights(cfg))


def smolvla_weights(profile: Profile, folder: Path) -> Any:
    """A smolvla_base-sized checkpoint folder (random weights) and its weight set, as a learner streams it."""
    import torch
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from user.policies.smolvla import SmolVlaSpec, make_backbone, policy_spec, save_checkpoint, smolvla_base_config
    from user.policy import module_tensors
    from user.weights import WeightSet

    words = {w for text in INSTRUCTIONS for w in text.split()}
    backbone = make_backbone(folder / "backbone", sorted(words), image_size=512, size="smolvlm2_500m")
    cameras = {key: key.split(".")[-1] for key in profile.cameras}
    torch.manual_seed(0)
    model = SmolVLAPolicy(smolvla_base_config(backbone, list(cameras.values()), STATE_DIM, profile.action_dim))
    save_checkpoint(model, folder / "checkpoint")
    spec = SmolVlaSpec(
        checkpoint=str(folder / "checkpoint"),
        image_keys=cameras,
        state_keys=["state"],
        action_dim=profile.action_dim,
        action_low=[-1.0] * profile.action_dim,
        action_high=[1.0] * profile.action_dim,
    )
    return WeightSet(1, policy_spec(spec), module_tensors(model))


class OneAtATimeServicer(inference_pb2_grpc.InferenceServicer):
    """Preprocess + forward for one request at a time, in the handler thread."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self._lock = threading.Lock()

    def Act(self, request: inference_pb2.ActRequest, context: grpc.ServicerContext) -> inference_pb2.ActResponse:
        try:
            obs = {k: v[None] for k, v in wire.from_tensor_map(request.observation).items()}
            with self._lock:
                chunk = self.policy.forward(self.policy.preprocess(obs, [request.instruction]), request.deterministic)
        except ValueError as exc:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        return inference_pb2.ActResponse(
            action=wire.to_tensor(chunk[0]), policy_version=self.policy.version, batch_size=1, horizon=chunk.shape[1]
        )


def start_peer(cfg: StackConfig, weights: Any) -> tuple[str, Callable[[], None]]:
    from user.policy import build_policy

    device = cfg.inference.device  # the same device as ours
    servicer = OneAtATimeServicer(build_policy(weights.policy, weights.tensors, weights.version, device))
    return serve_peer(cfg, servicer, "one-at-a-time-inference")


@dataclass(frozen=True)
class RobotTask:
    addr: str
    index: int
    start_at: float  # wall clock
    end_at: float
    period_s: float  # 0: closed loop (next call when the answer is in); else one call per period
    cameras: tuple[str, ...]
    image: int
    frames: tuple[dict[str, np.ndarray], ...] = ()  # camera frames to cycle through; () = random noise frames
    jpeg_quality: int = 0  # > 0: frames go JPEG-encoded, as an edge with act_image_encoding sends them


def _requests(task: RobotTask) -> list[inference_pb2.ActRequest]:
    from edge_agent.encoder import encode_observation

    rng = np.random.default_rng(task.index)
    plan = {k: (tpb.ENCODING_JPEG, task.jpeg_quality) for k in task.cameras} if task.jpeg_quality else None
    requests = []
    for i in range(OBSERVATIONS_PER_ROBOT):
        if task.frames:
            images = task.frames[(task.index + i) % len(task.frames)]
        else:
            images = {k: rng.integers(0, 256, size=(task.image, task.image, 3), dtype=np.uint8) for k in task.cameras}
        obs = {**images, "state": rng.standard_normal(STATE_DIM).astype(np.float32)}
        requests.append(
            inference_pb2.ActRequest(
                robot_id=f"arm-{task.index}",
                observation=encode_observation(obs, plan),
                instruction=INSTRUCTIONS[task.index % len(INSTRUCTIONS)],
            )
        )
    return requests


def _robot(task: RobotTask) -> tuple[list[float], list[int], list[list[int]], list[str], float]:
    """One robot process: Act inside the window; (latencies ms, batch sizes, stage times us, errors,
    CPU seconds this process spent in the window).

    Paced (period_s > 0): call k is due at a random phase + k periods, as a robot asking for its next
    chunk at a fixed control rate; a call due while the previous one is still out goes as soon as it
    returns (a robot that falls behind does not skip requests) until the window ends, so a server that
    cannot keep up serves fewer calls than offered and its latencies grow."""
    latencies, batches, stages, errors = [], [], [], []
    requests = _requests(task)
    with rpc.make_channel(task.addr, AuthConfig(token=TOKEN)) as channel:
        stub = inference_pb2_grpc.InferenceStub(channel)
        try:
            stub.Act(requests[0], timeout=RPC_TIMEOUT_S, wait_for_ready=True)  # connect + warm up before the window
        except grpc.RpcError as err:  # RpcError does not cross processes: say what it was
            return [], [], [], [f"warm-up {err.code().name}: {err.details()}"], 0.0
        phase = float(np.random.default_rng(1000 + task.index).uniform(0.0, task.period_s))
        time.sleep(max(0.0, task.start_at - time.time()))
        cpu = time.process_time()
        i = 0
        while True:
            due = task.start_at + phase + i * task.period_s if task.period_s else time.time()
            if due >= task.end_at or time.time() >= task.end_at:  # a robot that fell behind stops at the end too
                break
            time.sleep(max(0.0, due - time.time()))
            req = requests[i % len(requests)]
            i += 1
            start = time.perf_counter()
            try:
                resp = stub.Act(req, timeout=RPC_TIMEOUT_S)
            except grpc.RpcError as err:  # counted, not raised: RpcError does not cross processes
                errors.append(f"{err.code().name}: {err.details()}")
                continue
            latencies.append((time.perf_counter() - start) * 1e3)
            batches.append(resp.batch_size)
            stages.append([resp.queue_us, resp.preprocess_us, resp.forward_us, resp.postprocess_us])
        cpu = time.process_time() - cpu
    return latencies, batches, stages, errors, cpu


def _warm(_: int) -> int:
    time.sleep(0.3)
    return 0


@dataclass
class Window:
    calls: int
    latencies: list[float]
    sizes: list[int]
    stages: np.ndarray  # (calls, 4) us: queue, preprocess, forward, postprocess
    server_cpu_s: float  # this process (the server being driven) during the window
    robots_cpu_s: float  # all robot processes during the window


def drive(
    pool: Any,
    addr: str,
    profile: Profile,
    clients: int,
    seconds: float,
    period_s: float = 0.0,
    frames: tuple[dict[str, np.ndarray], ...] = (),
    jpeg_quality: int = 0,
) -> Window:
    start_at = time.time() + START_MARGIN_S + 0.05 * clients
    tasks = [
        RobotTask(addr, i, start_at, start_at + seconds, period_s, profile.cameras, profile.image, frames, jpeg_quality)
        for i in range(clients)
    ]
    pending = pool.map_async(_robot, tasks, chunksize=1)
    time.sleep(max(0.0, start_at - time.time()))
    cpu = time.process_time()  # the window's serving work (the robots' warm-up calls come before it)
    results = pending.get()
    server_cpu = time.process_time() - cpu
    lat = [x for r in results for x in r[0]]
    sizes = [b for r in results for b in r[1]]
    stages = np.array([s for r in results for s in r[2]], dtype=np.float64).reshape(-1, 4)
    errors = [e for r in results for e in r[3]]
    if errors:
        raise RuntimeError(f"{len(errors)} Act calls failed at {clients} robots, e.g. {errors[:3]}")
    return Window(len(lat), lat, sizes, stages, server_cpu, sum(r[4] for r in results))


def _p99(values: list[float]) -> float:
    return float(np.percentile(values, 99)) if values else float("nan")


def _batch_note(windows: list[Window]) -> str:
    sizes = [b for w in windows for b in w.sizes]
    st = np.concatenate([w.stages for w in windows]).mean(axis=0) / 1e3
    return (
        f"mean batch {np.mean(sizes):.1f}; ours stages ms: queue {st[0]:.1f}, preprocess {st[1]:.1f}, "
        f"forward {st[2]:.1f}, postprocess {st[3]:.2f}"
    )


def _group(profile: Profile, n_params: int, what: str, device: str = "cpu") -> str:
    on = "" if device == "cpu" else f" on {_device_name(device)}"
    return f"inference {profile.model} ({n_params / 1e6:.2f}M params, {profile.label}){on}, {what}"


def _device_name(device: str) -> str:
    import torch

    return f"{device} ({torch.cuda.get_device_name(torch.device(device))})" if device.startswith("cuda") else device


def _closed_rows(group: str, windows: dict[str, list[Window]], seconds: float) -> list[Row]:
    calls = {s: sum(w.calls for w in ws) for s, ws in windows.items()}
    lat = {s: [x for w in ws for x in w.latencies] for s, ws in windows.items()}
    cpu = {  # ms of CPU per Act call: (server, robots)
        s: (
            1e3 * sum(w.server_cpu_s for w in ws) / max(calls[s], 1),
            1e3 * sum(w.robots_cpu_s for w in ws) / max(calls[s], 1),
        )
        for s, ws in windows.items()
    }
    # With robots and server on the same cores, calls/s <= cores / (robot + server CPU per call).
    ceiling = sum(cpu["peer"]) / sum(cpu["ours"])
    cpu_note = f"ours/peer calls/s can reach about (peer robot+server CPU)/(ours) = {ceiling:.2f}x when CPU-bound"
    return [
        Row(
            group,
            "Act calls/s",
            calls["ours"] / seconds,
            calls["peer"] / seconds,
            "calls/s",
            True,
            _batch_note(windows["ours"]),
            PEER,
        ),
        Row(group, "Act latency p50", median(lat["ours"]), median(lat["peer"]), "ms", False, "", PEER),
        Row(group, "Act latency p99", _p99(lat["ours"]), _p99(lat["peer"]), "ms", False, "", PEER),
        Row(group, "server CPU per Act", cpu["ours"][0], cpu["peer"][0], "ms", False, cpu_note, PEER),
        Row(group, "robot CPU per Act", cpu["ours"][1], cpu["peer"][1], "ms", False, "the gRPC client", PEER),
    ]


def _paced_rows(
    group: str,
    windows: dict[str, list[Window]],
    seconds: float,
    offered: float,
    single_p99: dict[str, float],
    period_ms: float,
) -> list[Row]:
    lat = {s: [x for w in ws for x in w.latencies] for s, ws in windows.items()}
    rate = {s: sum(w.calls for w in ws) / seconds for s, ws in windows.items()}
    p99 = {s: _p99(v) for s, v in lat.items()}
    kept = {s: rate[s] >= 0.95 * offered and p99[s] <= period_ms for s in windows}
    verdict = {s: f"{'yes' if kept[s] else 'no'} ({100 * rate[s] / offered:.0f} % of offered)" for s in windows}
    return [
        Row(
            group,
            f"Act calls/s served (offered {offered:.0f})",
            rate["ours"],
            rate["peer"],
            "calls/s",
            True,
            _batch_note(windows["ours"]),
            PEER,
        ),
        Row(group, "Act latency p50", median(lat["ours"]), median(lat["peer"]), "ms", False, "", PEER),
        Row(
            group,
            "Act latency p99",
            p99["ours"],
            p99["peer"],
            "ms",
            False,
            f"a chunk is due every {period_ms:.0f} ms",
            PEER,
        ),
        Row(
            group,
            "p99 / own 1-robot closed-loop p99 (x)",
            p99["ours"] / single_p99["ours"],
            p99["peer"] / single_p99["peer"],
            "x",
            False,
            "each side against its own single-robot p99",
            PEER,
        ),
        Row(
            group,
            "keeps up (>= 95 % served, p99 within the period)",
            verdict["ours"],
            verdict["peer"],
            "",
            None,
            "",
            PEER,
        ),
    ]


def _targets(
    profile: Profile,
    n_params: int,
    rate: dict[tuple[str, int], float],
    p99: dict[int, float],
    paced_p99: float | None,
    top: int,
    device: str = "cpu",
) -> list[Row]:
    group = _group(profile, n_params, f"issue #9 targets at {top} robots", device)
    note = "target >= 4x" if top == TOP else f"target at {TOP} robots >= 4x"
    rows = [
        Row(
            group,
            "closed-loop throughput ours/peer (x)",
            rate[("ours", top)] / max(rate[("peer", top)], 1e-9),
            4.0,
            "x",
            True,
            f"{note}; peer column = the target",
            "issue #9 target",
        ),
        Row(
            group,
            f"closed-loop p99 at {top} robots / p99 at 1 robot (x)",
            p99[top] / max(p99[1], 1e-9),
            2.0,
            "x",
            False,
            "target <= 2x; peer column = the target; a saturated closed loop queues by design",
            "issue #9 target",
        ),
    ]
    if paced_p99 is not None:
        rows.append(
            Row(
                group,
                f"paced p99 at {top} robots / closed-loop p99 at 1 robot (x)",
                paced_p99 / max(p99[1], 1e-9),
                2.0,
                "x",
                False,
                "target <= 2x; chunks requested at the control rate",
                "issue #9 target",
            )
        )
    return rows


def run_profile(
    pool: Any, profile: Profile, cfg: StackConfig, quick: bool, log: Callable[..., None], workdir: Path
) -> list[Row]:
    rounds, seconds = (1, min(1.0, profile.seconds)) if quick else (2, profile.seconds)
    concurrency = [1, 4] if quick else list(profile.concurrency)
    paced_every = profile.paced_every[:1] if quick else profile.paced_every
    if quick:  # the smoke run checks the rows' shape: a small stand-in keeps it inside the suite's time limit
        profile = replace(profile, hidden=min(profile.hidden, 256), image=min(profile.image, 64))
    top = max(c for c in concurrency if c <= TOP)
    weights = make_weights(profile, workdir)
    n_params = sum(int(v.size) for v in weights.tensors.values())
    rows: list[Row] = []
    rate: dict[tuple[str, int], float] = {}
    p99: dict[int, float] = {}
    single_p99: dict[str, float] = {}
    servers = {"ours": start_ours(cfg, weights), "peer": start_peer(cfg, weights)}
    other = _other_batching(cfg, profile)
    if other is not None:  # ours in the other batching mode, at the top robot count only
        servers[OTHER] = start_ours(other, weights)
    compared: dict[str, tuple[list[Window], list[Window], float]] = {}  # how -> (ours, other mode, seconds)
    paced_p99 = None
    try:
        for c in concurrency:
            log(f"inference_vla {profile.label}: {c} robots, closed loop")
            windows: dict[str, list[Window]] = {s: [] for s in servers if s != OTHER}
            for _ in range(rounds):
                for side, (addr, _stop) in servers.items():
                    if side != OTHER or c == top:
                        windows.setdefault(side, []).append(drive(pool, addr, profile, c, seconds))
            if OTHER in windows:
                compared["closed loop"] = (windows["ours"], windows.pop(OTHER), rounds * seconds)
            rows += _closed_rows(
                _group(profile, n_params, f"closed loop, {c} robots", cfg.inference.device), windows, rounds * seconds
            )
            for side, ws in windows.items():
                rate[(side, c)] = sum(w.calls for w in ws) / (rounds * seconds)
                if c == 1:
                    single_p99[side] = _p99([x for w in ws for x in w.latencies])
            p99[c] = _p99([x for w in windows["ours"] for x in w.latencies])
        for every in paced_every:
            hz = CONTROL_HZ / every
            why = (
                f"a chunk every {every} ticks at {CONTROL_HZ:.0f} Hz"
                if every > 1
                else f"every tick at {CONTROL_HZ:.0f} Hz"
            )
            log(f"inference_vla {profile.label}: {top} robots paced at {hz:.2f} Hz")
            windows = {s: [] for s in servers}
            paced_s = seconds if quick else 2 * seconds  # one window, long enough for a few calls per robot
            for side, (addr, _stop) in servers.items():
                windows[side].append(drive(pool, addr, profile, top, paced_s, 1.0 / hz))
            if OTHER in windows:
                compared[f"paced at {hz:.2f} Hz"] = (windows["ours"], windows.pop(OTHER), paced_s)
            group = _group(profile, n_params, f"paced, {top} robots x {hz:.2f} Hz ({why})", cfg.inference.device)
            rows += _paced_rows(group, windows, paced_s, top * hz, single_p99, 1e3 / hz)
            if paced_p99 is None:
                paced_p99 = _p99([x for w in windows["ours"] for x in w.latencies])
    finally:
        for _addr, stop in servers.values():
            stop()
    rows += _batching_rows(
        _group(profile, n_params, f"{top} robots, continuous batching vs batch by batch", cfg.inference.device),
        compared,
        cfg.inference.continuous_batching,
    )
    return rows + _targets(profile, n_params, rate, p99, paced_p99, top, cfg.inference.device)


OTHER = "ours, other batching mode"


def _other_batching(cfg: StackConfig, profile: Profile) -> StackConfig | None:
    """Ours with continuous batching switched the other way, for a policy that samples in steps."""
    if profile.model != "flow_vla":
        return None
    other = cfg.model_copy(deep=True)
    other.inference.continuous_batching = not cfg.inference.continuous_batching
    return other


def _batching_rows(
    group: str, compared: dict[str, tuple[list[Window], list[Window], float]], continuous_is_ours: bool
) -> list[Row]:
    """Continuous batching (a request joins a running batch at its next flow step) against batch by
    batch, both ours, in alternating windows of the same run."""
    peer = "ours, batch by batch (inference.continuous_batching: false)"
    rows = []
    for how, (ours, other, seconds) in compared.items():
        cont, batched = (ours, other) if continuous_is_ours else (other, ours)
        lat_c, lat_b = [x for w in cont for x in w.latencies], [x for w in batched for x in w.latencies]
        rate_c, rate_b = sum(w.calls for w in cont) / seconds, sum(w.calls for w in batched) / seconds
        rows += [
            Row(group, f"{how}: Act calls/s", rate_c, rate_b, "calls/s", True, _batch_note(cont), peer),
            Row(group, f"{how}: Act latency p50", median(lat_c), median(lat_b), "ms", False, "", peer),
            Row(group, f"{how}: Act latency p99", _p99(lat_c), _p99(lat_b), "ms", False, "", peer),
        ]
    return rows


@dataclass(frozen=True)
class EdgeTask:
    """One robot process running the edge's own chunk path (RemotePolicy -> ChunkExecutor) at a control rate."""

    addr: str
    index: int
    start_at: float  # wall clock; ticks before warm_s past it are not counted
    end_at: float
    hz: float
    prefetch: int
    adaptive: bool
    warm_s: float = 2.0


def _edge_robot(task: EdgeTask) -> tuple[int, int, int, str]:
    """(ticks counted, ticks held, chunks received, error or "")."""
    from edge_agent.policy_source import RemotePolicy

    request = _requests(RobotTask(task.addr, task.index, 0.0, 0.0, 0.0, VLA.cameras, VLA.image))[0]
    obs = wire.from_tensor_map(request.observation)
    source = RemotePolicy(
        task.addr,
        AuthConfig(token=TOKEN),
        deterministic=True,
        chunk_prefetch=task.prefetch,
        adaptive_prefetch=task.adaptive,
        instruction=request.instruction,
    )
    rid, period, counted, held = f"arm-{task.index}", 1.0 / task.hz, 0, 0
    try:
        phase = float(np.random.default_rng(task.index).uniform(0.0, period))
        i = 0
        while (due := task.start_at + phase + i * period) < task.end_at:
            time.sleep(max(0.0, due - time.time()))
            action = source.act(rid, obs, deadline_s=0.5)
            if due >= task.start_at + task.warm_s:
                counted, held = counted + 1, held + (action is None)
            i += 1
        return counted, held, source.chunks_received, ""
    except Exception as exc:  # reported: the error does not cross processes as is
        return counted, held, 0, f"{type(exc).__name__}: {exc}"
    finally:
        source.close()


# When each robot asks for its next chunk: ours (adaptive, at least 2 ticks left), ours before (2 ticks left,
# fixed) and lerobot's async client (chunk_size_threshold 0.5: when half the chunk is left).
EDGE_RULES = {"ours": (2, True), "fixed": (2, False), "lerobot": (VLA.horizon // 2, False)}


def edge_chunk_rows(pool: Any, cfg: StackConfig, quick: bool, log: Callable[..., None]) -> list[Row]:
    """Robots executing VLA chunks at 30 Hz through the inference service: ticks held and requests made under
    each rule for asking the next chunk."""
    robots, seconds = (2, 3.0) if quick else (TOP, 17.0)
    profile = replace(VLA, hidden=256) if quick else VLA
    addr, stop = start_ours(cfg, make_weights(profile))
    counts: dict[str, tuple[int, int, int]] = {}
    try:
        for rule, (prefetch, adaptive) in EDGE_RULES.items():
            log(f"inference_vla: edge chunks, {robots} robots at {CONTROL_HZ:.0f} Hz, rule {rule}")
            start_at = time.time() + START_MARGIN_S + 0.05 * robots
            tasks = [
                EdgeTask(addr, i, start_at, start_at + seconds, CONTROL_HZ, prefetch, adaptive) for i in range(robots)
            ]
            results = pool.map(_edge_robot, tasks, chunksize=1)
            errors = [r[3] for r in results if r[3]]
            if errors:
                raise RuntimeError(f"edge robots failed under rule {rule}: {errors[:3]}")
            counts[rule] = tuple(sum(r[k] for r in results) for k in range(3))  # type: ignore[assignment]
    finally:
        stop()
    group = (
        f"edge chunk execution: {robots} robots x {CONTROL_HZ:.0f} Hz, flow_vla chunks of {profile.horizon} "
        "through the inference service (loopback), robots as processes"
    )
    acted = {r: 100.0 * (n - h) / max(n, 1) for r, (n, h, _) in counts.items()}
    per_robot_s = {r: received / (robots * seconds) for r, (_, _, received) in counts.items()}  # warm-up included
    names = {"fixed": "ours before: next chunk asked with 2 ticks left", "lerobot": LEROBOT_RULE}
    rows = []
    for rule in ("fixed", "lerobot"):
        (n, h, _), (pn, ph, _) = counts["ours"], counts[rule]
        note = f"ticks held: ours {h} of {n}, {rule} {ph} of {pn}"
        rows.append(
            Row(
                group,
                f"ticks acting on a fresh chunk row (%) vs {rule}",
                acted["ours"],
                acted[rule],
                "%",
                True,
                note,
                names[rule],
            )
        )
    rows.append(
        Row(
            group,
            "chunks received per robot-second (load on inference)",
            per_robot_s["ours"],
            per_robot_s["lerobot"],
            "/s",
            False,
            f"ours before: {per_robot_s['fixed']:.2f}",
            LEROBOT_RULE,
        )
    )
    return rows


LEROBOT_RULE = "lerobot async client's rule (chunk_size_threshold 0.5: ask with half the chunk left)"


def lerobot_peer_rows(pool: Any, cfg: StackConfig, workdir: Path, quick: bool, log: Callable[..., None]) -> list[Row]:
    group = "inference SmolVLA (tiny, local folder), 1 robot, lerobot's own protocol"
    if (
        quick
    ):  # its server process imports lerobot + transformers: minutes on a busy machine, too long for the smoke run
        return [Row(group, "lerobot async_inference PolicyServer", "not run in --quick", "", "", None)]
    try:
        import lerobot.async_inference.policy_server  # noqa: F401 - is lerobot's server here at all?
    except ImportError as exc:
        return [Row(group, "lerobot async_inference PolicyServer", "not run", f"cannot import: {exc}", "", None)]
    from bench import inference_lerobot_peer

    return inference_lerobot_peer.run(pool, cfg, TOKEN, workdir, quick, log)


def run(quick: bool, workdir: Path, log: Callable[..., None] = print, overrides: list[str] | None = None) -> list[Row]:
    """`overrides` (`--set`) reach the inference section, e.g. inference.device=cuda on a GPU machine (both sides)."""
    cfg = load_config(None, list(overrides or []))
    cfg.auth = AuthConfig(token=TOKEN)
    cfg.inference.server = ServerConfig(host="127.0.0.1", port=0, metrics_port=0, grace_s=0.5, max_workers=64)
    cfg.inference.max_batch = 32
    cfg.inference.max_wait_ms = 5.0
    rows: list[Row] = []
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the inference service's run() does; the same for both servers
    workers = 4 if quick else max(max(p.concurrency) for p in PROFILES.values())  # quick drives 1 and 4 robots
    try:
        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            pool.map(_warm, range(workers), chunksize=1)
            for name in os.environ.get("USER_INFERENCE_VLA_PROFILES", DEFAULT_PROFILES).split(","):
                rows += run_profile(pool, PROFILES[name.strip()], cfg, quick, log, workdir)
            if os.environ.get("USER_INFERENCE_VLA_LEROBOT_PEER", "1") != "0":  # 0: skip it (a short device run)
                rows += lerobot_peer_rows(pool, cfg, workdir, quick, log)
            if os.environ.get("USER_INFERENCE_VLA_EDGE", "1") != "0":
                rows += edge_chunk_rows(pool, cfg, quick, log)
        if os.environ.get("USER_INFERENCE_VLA_LINK", "1") != "0" and cfg.inference.device == "cpu":
            from bench.inference_link import run as link_rows

            rows += link_rows(quick, log)  # its own servers and robots, inside a private network namespace
    finally:
        torch.set_num_threads(threads)
    return rows
