"""VLA inference for many robots: our InferenceService (dynamic batching, batched preprocessing)
vs a one-request-at-a-time server of the same flow_vla model.

The peer serves the same Inference.Act proto on the same gRPC setup but runs preprocess + forward
for one request at a time under a lock, the way openpi's websocket policy server and lerobot's
async-inference policy server serve a policy (one observation in, one chunk out, in turn). Each
robot is a separate process sending a 64x64 camera image, its state and an instruction, and
calling Act in a loop (closed loop: the next request after the answer); a robot cycles through
a few observations made before the window, so the robots' own CPU is the gRPC client and nothing
else. Windows alternate ours/peer so background load hits both alike. Both servers run in this
process with one torch thread (as `services.inference.server.run` sets it; on 2 cores a second
intra-op thread only fights the robots and the gRPC threads).

Besides throughput and latency, the CPU spent per Act call is measured: the serving process's
(time.process_time over the window: gRPC, handler, batcher, model) and the robots' (each robot
process's own). On a machine where the robots share the cores with the server, throughput is
capped near cores / (robot CPU + server CPU per call) whatever the batching does, so these rows
say how far batching can move the ratio there. The targets of issue #9 are printed as rows: at 16
robots >= 4x the peer's throughput, with p99 <= 2x our single-robot p99.
"""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from bench import Row, median
from bench.inference_bench import serve_peer, start_ours
from user import rpc, wire
from user.config import AuthConfig, ServerConfig, StackConfig
from user.v1 import inference_pb2, inference_pb2_grpc

PEER = "one-request-at-a-time server (openpi / lerobot policy-server style)"
RPC_TIMEOUT_S = 30.0
OBSERVATIONS_PER_ROBOT = 8  # made before the window and cycled, so the window times serving, not numpy
TOKEN = "bench-token"
CONCURRENCY = [1, 4, 16, 32]
START_MARGIN_S = 1.0
IMAGE, STATE_DIM = 64, 15
INSTRUCTIONS = ["reach the red target", "reach the green target", "reach the blue target"]


def vla_config() -> Any:
    from user.policies.flow_vla import FlowVlaConfig

    return FlowVlaConfig(
        image_keys=["camera.front"],
        state_keys=["state"],
        state_dim=STATE_DIM,
        action_dim=3,
        action_low=[-1.0] * 3,
        action_high=[1.0] * 3,
        horizon=8,
        image_size=IMAGE,
        hidden=128,
        flow_steps=5,
    )


def make_weights() -> Any:
    from user.policies.flow_vla import policy_spec, random_weights
    from user.weights import WeightSet

    cfg = vla_config()
    return WeightSet(1, policy_spec(cfg), random_weights(cfg))


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

    servicer = OneAtATimeServicer(build_policy(weights.policy, weights.tensors, weights.version))
    return serve_peer(cfg, servicer, "one-at-a-time-inference")


def _robot(
    task: tuple[str, int, float, float],
) -> tuple[list[float], list[int], list[list[int]], list[str], float]:
    """One robot process: Act in a loop inside the window; (latencies ms, batch sizes, stage times us,
    errors, CPU seconds this process spent in the window)."""
    addr, index, start_at, end_at = task
    rng = np.random.default_rng(index)
    latencies, batches, stages, errors = [], [], [], []
    requests = [
        inference_pb2.ActRequest(
            robot_id=f"arm-{index}",
            observation=wire.to_tensor_map(
                {
                    "camera.front": rng.integers(0, 256, size=(IMAGE, IMAGE, 3), dtype=np.uint8),
                    "state": rng.standard_normal(STATE_DIM).astype(np.float32),
                }
            ),
            instruction=INSTRUCTIONS[index % len(INSTRUCTIONS)],
        )
        for _ in range(OBSERVATIONS_PER_ROBOT)
    ]
    with rpc.make_channel(addr, AuthConfig(token=TOKEN)) as channel:
        stub = inference_pb2_grpc.InferenceStub(channel)
        try:
            stub.Act(requests[0], timeout=RPC_TIMEOUT_S, wait_for_ready=True)  # connect + warm up before the window
        except grpc.RpcError as err:  # RpcError does not cross processes: say what it was
            return [], [], [], [f"warm-up {err.code().name}: {err.details()}"], 0.0
        time.sleep(max(0.0, start_at - time.time()))
        cpu = time.process_time()
        i = 0
        while time.time() < end_at:
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


def drive(pool: Any, addr: str, clients: int, seconds: float) -> Window:
    start_at = time.time() + START_MARGIN_S + 0.05 * clients
    tasks = [(addr, i, start_at, start_at + seconds) for i in range(clients)]
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


def _rows(
    c: int,
    n_params: int,
    windows: dict[str, list[Window]],
    seconds: float,
    rate: dict[tuple[str, int], float],
    ours_p99: dict[int, float],
) -> list[Row]:
    """Rows for one robot count; fills rate[(side, c)] and ours_p99[c]."""
    calls = {s: sum(w.calls for w in ws) for s, ws in windows.items()}
    lat = {s: [x for w in ws for x in w.latencies] for s, ws in windows.items()}
    cpu = {  # ms of CPU per Act call: (server, robots)
        s: (
            1e3 * sum(w.server_cpu_s for w in ws) / max(calls[s], 1),
            1e3 * sum(w.robots_cpu_s for w in ws) / max(calls[s], 1),
        )
        for s, ws in windows.items()
    }
    for side in windows:
        rate[(side, c)] = calls[side] / seconds
    ours_p99[c] = float(np.percentile(lat["ours"], 99))
    sizes = [b for w in windows["ours"] for b in w.sizes]
    st = np.concatenate([w.stages for w in windows["ours"]]).mean(axis=0) / 1e3
    note = (
        f"mean batch {np.mean(sizes):.1f}; ours stages ms: queue {st[0]:.1f}, preprocess {st[1]:.1f}, "
        f"forward {st[2]:.1f}, postprocess {st[3]:.2f}"
    )
    # With robots and server on the same cores, calls/s <= cores / (robot + server CPU per call).
    ceiling = sum(cpu["peer"]) / sum(cpu["ours"])
    cpu_note = f"ours/peer calls/s can reach about (peer robot+server CPU)/(ours) = {ceiling:.2f}x when CPU-bound"
    group = f"inference flow_vla ({n_params / 1e6:.2f}M params, 64x64 camera, chunk 8x3), {c} robots"
    p99 = float(np.percentile(lat["peer"], 99))
    return [
        Row(group, "Act calls/s", rate[("ours", c)], rate[("peer", c)], "calls/s", True, note, PEER),
        Row(group, "Act latency p50", median(lat["ours"]), median(lat["peer"]), "ms", False, "", PEER),
        Row(group, "Act latency p99", ours_p99[c], p99, "ms", False, "", PEER),
        Row(group, "server CPU per Act", cpu["ours"][0], cpu["peer"][0], "ms", False, cpu_note, PEER),
        Row(group, "robot CPU per Act", cpu["ours"][1], cpu["peer"][1], "ms", False, "the gRPC client", PEER),
    ]


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    rounds, seconds = (1, 0.5) if quick else (2, 2.0)
    concurrency = [1, 4] if quick else CONCURRENCY
    weights = make_weights()
    n_params = sum(int(v.size) for v in weights.tensors.values())
    cfg = StackConfig(auth=AuthConfig(token=TOKEN))
    cfg.inference.server = ServerConfig(host="127.0.0.1", port=0, metrics_port=0, grace_s=0.5, max_workers=64)
    cfg.inference.max_batch = 32
    cfg.inference.max_wait_ms = 5.0
    rows: list[Row] = []
    ours_p99: dict[int, float] = {}
    rate: dict[tuple[str, int], float] = {}
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the inference service's run() does; the same for both servers
    try:
        with multiprocessing.get_context("spawn").Pool(max(concurrency)) as pool:
            pool.map(_warm, range(max(concurrency)), chunksize=1)
            servers = {"ours": start_ours(cfg, weights), "peer": start_peer(cfg, weights)}
            try:
                for c in concurrency:
                    log(f"inference_vla: {c} robots")
                    windows: dict[str, list[Window]] = {s: [] for s in servers}
                    for _ in range(rounds):
                        for side, (addr, _stop) in servers.items():
                            windows[side].append(drive(pool, addr, c, seconds))
                    rows += _rows(c, n_params, windows, rounds * seconds, rate, ours_p99)
            finally:
                for _addr, stop in servers.values():
                    stop()
    finally:
        torch.set_num_threads(threads)
    top = max(c for c in concurrency if c <= 16)
    target = "target >= 4x" if top == 16 else "target at 16 robots >= 4x"
    rows.append(
        Row(
            f"inference flow_vla targets ({top} robots)",
            "throughput ours/peer (x)",
            rate[("ours", top)] / max(rate[("peer", top)], 1e-9),
            4.0,
            "x",
            True,
            f"{target}; peer column = the target",
            "issue #9 target",
        )
    )
    rows.append(
        Row(
            f"inference flow_vla targets ({top} robots)",
            f"p99 at {top} robots / p99 at 1 robot (x)",
            ours_p99[top] / max(ours_p99[1], 1e-9),
            2.0,
            "x",
            False,
            "target <= 2x; peer column = the target",
            "issue #9 target",
        )
    )
    return rows
