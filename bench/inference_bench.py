"""Inference Act round trips: our InferenceService (micro-batching across robots) vs a naive server.

The naive peer serves the same Inference.Act proto on the same gRPC setup (auth, interceptors, thread
pool) but evaluates the policy once per request inside the handler, with no batching: what a
one-call-per-robot server looks like. Same policy object type, same observation bytes, same clients:
the difference is the batching. Each client is one robot on its own channel, calling Act in a loop.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from bench import Row, median
from user import rpc, wire
from user.config import AuthConfig, ServerConfig, StackConfig
from user.v1 import inference_pb2, inference_pb2_grpc

# torch, user.policy and the services are imported inside functions: the robot processes
# (spawned) import this module and need only grpc + numpy.

NAIVE = "naive unary server (no batching)"
RPC_TIMEOUT_S = 10.0
TOKEN = "bench-token"
CONCURRENCY = [1, 8]
START_MARGIN_S = 0.4


def make_weights(config: dict[str, Any]) -> Any:
    import torch

    from user.policy import actor_from_config, module_tensors, policy_spec_for
    from user.weights import WeightSet

    torch.manual_seed(0)
    return WeightSet(1, policy_spec_for(config), module_tensors(actor_from_config(config)))


class NaiveServicer(inference_pb2_grpc.InferenceServicer):
    """One policy forward per request, in the gRPC handler thread."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy

    def Act(self, request: inference_pb2.ActRequest, context: grpc.ServicerContext) -> inference_pb2.ActResponse:
        try:
            obs = {k: v[None] for k, v in wire.from_tensor_map(request.observation).items()}
            action = self.policy.act(obs, request.deterministic)[0]
        except ValueError as exc:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(exc))
        version = self.policy.version
        return inference_pb2.ActResponse(action=wire.to_tensor(action), policy_version=version, batch_size=1)


def start_ours(cfg: StackConfig, weights: Any) -> tuple[str, Callable[[], None]]:
    from services.inference.server import InferenceService

    service = InferenceService(cfg, policy_source="manual", start_metrics=False).start()
    service.load_weights(weights)
    return service.address, service.stop


def serve_peer(cfg: StackConfig, servicer: Any, label: str) -> tuple[str, Callable[[], None]]:
    """A peer Inference servicer on our server bootstrap (same auth and transport), for a fair comparison."""
    name = inference_pb2.DESCRIPTOR.services_by_name["Inference"].full_name
    running = rpc.start_server(
        label,
        lambda s: inference_pb2_grpc.add_InferenceServicer_to_server(servicer, s),
        [name],
        cfg.inference.server,
        cfg.auth,
        start_metrics=False,
    )
    return running.address(), running.stop


def start_naive(cfg: StackConfig, weights: Any) -> tuple[str, Callable[[], None]]:
    from user.policy import build_policy

    return serve_peer(
        cfg, NaiveServicer(build_policy(weights.policy, weights.tensors, weights.version)), "naive-inference"
    )


def _robot(task: tuple[str, str, int, int, float, float]) -> tuple[list[float], list[int]]:
    """One robot in its own process: Act in a loop between start_at and end_at (wall clock)."""
    addr, token, obs_dim, index, start_at, end_at = task
    rng = np.random.default_rng(index)
    latencies, batches = [], []
    with rpc.make_channel(addr, AuthConfig(token=token)) as channel:
        stub = inference_pb2_grpc.InferenceStub(channel)

        def request() -> inference_pb2.ActRequest:
            obs = {"state": rng.standard_normal(obs_dim).astype(np.float32)}
            return inference_pb2.ActRequest(robot_id=f"arm-{index}", observation=wire.to_tensor_map(obs))

        stub.Act(request(), timeout=RPC_TIMEOUT_S)  # connect + warm up outside the timed window
        time.sleep(max(0.0, start_at - time.time()))
        while time.time() < end_at:
            req = request()
            start = time.perf_counter()
            resp = stub.Act(req, timeout=RPC_TIMEOUT_S)
            latencies.append((time.perf_counter() - start) * 1e3)
            batches.append(resp.batch_size)
    return latencies, batches


def _warm(_: int) -> int:
    time.sleep(0.2)  # each worker takes one task: all of them import this module now
    return 0


def drive(pool: Any, addr: str, obs_dim: int, clients: int, seconds: float) -> tuple[int, list[float], list[int]]:
    """One window of `clients` robots calling Act: (calls, latencies in ms, batch sizes reported)."""
    start_at = time.time() + START_MARGIN_S  # every robot connected and warmed up before the window opens
    tasks = [(addr, TOKEN, obs_dim, i, start_at, start_at + seconds) for i in range(clients)]
    results = pool.map(_robot, tasks, chunksize=1)
    lat = [x for per, _ in results for x in per]
    sizes = [b for _, per in results for b in per]
    return len(lat), lat, sizes


def bench_model(
    pool: Any, label: str, config: dict[str, Any], concurrency: list[int], rounds: int, seconds: float
) -> list[Row]:
    """Both servers run side by side; windows alternate ours/naive so background load hits both alike."""
    weights = make_weights(config)
    cfg = StackConfig(auth=AuthConfig(token=TOKEN))
    cfg.inference.server = ServerConfig(host="127.0.0.1", port=0, metrics_port=0, grace_s=0.5)
    n_params = sum(int(v.size) for v in weights.tensors.values())
    servers = {"ours": start_ours(cfg, weights), "naive": start_naive(cfg, weights)}
    rows: list[Row] = []
    try:
        for c in concurrency:
            calls = {side: 0 for side in servers}
            lat: dict[str, list[float]] = {side: [] for side in servers}
            sizes: dict[str, list[int]] = {side: [] for side in servers}
            for _ in range(rounds):
                for side, (addr, _stop) in servers.items():
                    n, window_lat, window_sizes = drive(pool, addr, config["obs_dim"], c, seconds)
                    calls[side] += n
                    lat[side] += window_lat
                    sizes[side] += window_sizes
            group = f"inference {label} ({n_params / 1e6:.2f}M params), {c} robot{'s' if c > 1 else ''}"
            window = rounds * seconds
            rows += [
                Row(
                    group,
                    "Act calls/s",
                    calls["ours"] / window,
                    calls["naive"] / window,
                    "calls/s",
                    True,
                    f"ours: mean batch {np.mean(sizes['ours']):.1f}",
                    peer_name=NAIVE,
                ),
                Row(group, "Act latency p50", median(lat["ours"]), median(lat["naive"]), "ms", False, peer_name=NAIVE),
                Row(
                    group,
                    "Act latency p99",
                    float(np.percentile(lat["ours"], 99)),
                    float(np.percentile(lat["naive"], 99)),
                    "ms",
                    False,
                    peer_name=NAIVE,
                ),
            ]
    finally:
        for _addr, stop in servers.values():
            stop()
    return rows


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    from bench.weights_bench import models

    rows: list[Row] = []
    rounds, seconds = (1, 0.3) if quick else (4, 0.8)
    concurrency = [1, 2] if quick else CONCURRENCY
    # Robots are separate processes (as on real edges), so clients never share the server's GIL.
    with multiprocessing.get_context("spawn").Pool(max(concurrency)) as pool:
        pool.map(_warm, range(max(concurrency)), chunksize=1)
        for label, config in models():
            if quick and label != "SAC actor":
                continue
            log(f"inference: {label}")
            rows += bench_model(pool, label, config, concurrency, rounds, seconds)
    return rows
