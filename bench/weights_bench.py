"""Weight streaming, learner -> actor, over real gRPC servers on 127.0.0.1.

ours: WeightStore.publish (dtype+shape manifest, xxh3-128 checksum, raw chunks) -> WeightServicer.SubscribeWeights
      -> WeightSubscriber/WeightAssembler rebuild numpy arrays from dtype + shape + bytes.
peer: lerobot's own LearnerService.StreamParameters (their servicer class, server options and channel
      options) fed the way their learner does (state_to_bytes = torch.save), received with their
      receive_bytes_in_chunks and decoded with bytes_to_state_dict (torch.load of received bytes).

Latency per version = publish call on the learner side -> decoded state dict on the receiving side,
one version at a time (the next is published once the previous arrived).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from concurrent import futures
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import torch

from bench import Row, median
from user import rpc
from user.config import AuthConfig, LearnerConfig, ServerConfig
from user.policy import actor_from_config, module_tensors, policy_spec_for
from user.v1 import learner_pb2, learner_pb2_grpc
from user.weights import WeightServicer, WeightSet, WeightStore, WeightSubscriber, iter_weight_messages

RECEIVE_TIMEOUT_S = 60.0
STATE_DIM, ACTION_DIM = 15, 3  # the sim arm


def actor_config(obs_dim: int, action_dim: int, hidden: list[int]) -> dict[str, Any]:
    return {
        "obs_keys": ["state"],
        "obs_dim": obs_dim,
        "action_dim": action_dim,
        "hidden": hidden,
        "action_low": [-1.0] * action_dim,
        "action_high": [1.0] * action_dim,
    }


def models() -> list[tuple[str, dict[str, Any]]]:
    """The sim-arm SAC actor exactly as the learner publishes it, and a ~10M-parameter MLP for scale."""
    from cloud_learner.sac import SAC

    ones = np.ones(ACTION_DIM, dtype=np.float32)
    sac = SAC(STATE_DIM, -ones, ones, LearnerConfig()).actor_config()
    big = actor_config(1024, 7, [2048, 2048, 2048])
    return [("SAC actor", sac), ("big MLP", big)]


# --------------------------------------------------------------------------- ours


class OursLink:
    """A real Learner gRPC server (auth on) with our WeightServicer, and one WeightSubscriber."""

    def __init__(self, spec: learner_pb2.PolicySpec, chunk_bytes: int) -> None:
        self.spec = spec
        self.chunk_bytes = chunk_bytes
        self.auth = AuthConfig(token="bench-token")
        self.store = WeightStore()
        servicer = WeightServicer(self.store, default_chunk_bytes=chunk_bytes)
        name = learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name
        self.server = rpc.start_server(
            "bench-learner",
            lambda s: learner_pb2_grpc.add_LearnerServicer_to_server(servicer, s),
            [name],
            ServerConfig(host="127.0.0.1", port=0, metrics_port=0, max_workers=4, grace_s=0.5),
            self.auth,
            start_metrics=False,
        )
        self.received: queue.Queue[tuple[float, WeightSet]] = queue.Queue()
        self.sub = WeightSubscriber(
            self.server.address(), self.auth, "bench", lambda ws: self.received.put((time.perf_counter(), ws))
        ).start()
        self.version = 0

    def send(self, module: torch.nn.Module) -> tuple[float, dict[str, np.ndarray], int]:
        """(seconds publish -> decoded on the subscriber, received tensors, bytes on the wire)."""
        self.version += 1
        start = time.perf_counter()
        tensors = module_tensors(module)  # what the learner hands WeightStore.publish
        packed = self.store.publish(self.version, self.spec, tensors)
        arrived, weights = self.received.get(timeout=RECEIVE_TIMEOUT_S)
        if weights.version != self.version:
            raise RuntimeError(f"expected weight v{self.version}, got v{weights.version}")
        wire = sum(m.ByteSize() for m in iter_weight_messages(packed, self.chunk_bytes))
        return arrived - start, weights.tensors, wire

    def close(self) -> None:
        self.sub.stop()
        self.store.close()
        self.server.stop()


# --------------------------------------------------------------------------- peer


class PeerLink:
    """lerobot's LearnerService on a gRPC server built like their learner's, and their actor-side receiver."""

    def __init__(self) -> None:
        from lerobot.rl.learner_service import MAX_WORKERS, LearnerService
        from lerobot.transport import services_pb2, services_pb2_grpc
        from lerobot.transport import utils as lt

        self.lt, self.pb = lt, services_pb2
        self.shutdown = threading.Event()
        self.params_q: queue.Queue[bytes] = queue.Queue()
        # seconds_between_pushes=0: push as soon as a version is queued (their default waits 4 s).
        service = LearnerService(
            shutdown_event=self.shutdown,
            parameters_queue=self.params_q,
            seconds_between_pushes=0.0,
            transition_queue=queue.Queue(),
            interaction_message_queue=queue.Queue(),
            queue_get_timeout=0.05,
        )
        self.server = grpc.server(
            futures.ThreadPoolExecutor(max_workers=MAX_WORKERS),
            options=[
                ("grpc.max_receive_message_length", lt.MAX_MESSAGE_SIZE),
                ("grpc.max_send_message_length", lt.MAX_MESSAGE_SIZE),
            ],
        )
        services_pb2_grpc.add_LearnerServiceServicer_to_server(service, self.server)
        port = self.server.add_insecure_port("127.0.0.1:0")
        self.server.start()
        self.channel = grpc.insecure_channel(f"127.0.0.1:{port}", lt.grpc_channel_options())
        self.call = services_pb2_grpc.LearnerServiceStub(self.channel).StreamParameters(services_pb2.Empty())
        self.received: queue.Queue[bytes] = queue.Queue()
        self.thread = threading.Thread(target=self._receive, daemon=True, name="peer-receive")
        self.thread.start()

    def _receive(self) -> None:
        try:
            self.lt.receive_bytes_in_chunks(self.call, self.received, self.shutdown, log_prefix="[bench]")
        except grpc.RpcError:
            pass  # cancelled at close()

    def send(self, module: torch.nn.Module) -> tuple[float, dict[str, torch.Tensor], int]:
        start = time.perf_counter()
        blob = self.lt.state_to_bytes(module.state_dict())  # what their learner queues per push
        self.params_q.put(blob)
        data = self.received.get(timeout=RECEIVE_TIMEOUT_S)
        state = self.lt.bytes_to_state_dict(data)  # torch.load of received bytes
        elapsed = time.perf_counter() - start
        wire = sum(m.ByteSize() for m in self.lt.send_bytes_in_chunks(blob, self.pb.Parameters))
        return elapsed, state, wire

    def close(self) -> None:
        self.shutdown.set()
        self.call.cancel()
        self.thread.join(5)
        self.channel.close()
        self.server.stop(0.5).wait()


# --------------------------------------------------------------------------- driver


def _new_version(module: torch.nn.Module) -> None:
    with torch.no_grad():  # weights change between pushes, as they do while training
        for p in module.parameters():
            p.add_(1e-3)


def _check_same(module: torch.nn.Module, received: dict[str, Any]) -> None:
    for name, ref in module.state_dict().items():
        if not np.array_equal(np.asarray(received[name]), ref.numpy()):
            raise AssertionError(f"received weights differ from the sent ones at {name}")


def bench_model(label: str, config: dict[str, Any], versions: int) -> list[Row]:
    torch.manual_seed(0)
    module = actor_from_config(config)
    n_params = sum(p.numel() for p in module.parameters())
    raw_bytes = sum(t.numel() * t.element_size() for t in module.state_dict().values())
    chunk = LearnerConfig().max_chunk_bytes
    # Both links live side by side and take turns per version, so background load hits both alike.
    links: dict[str, Any] = {}
    times: dict[str, list[float]] = {"ours": [], "peer": []}
    wire: dict[str, int] = {}
    try:
        links["ours"] = OursLink(policy_spec_for(config), chunk)
        links["peer"] = PeerLink()
        for link in links.values():
            link.send(module)  # warm-up version: connection set-up, first allocations
        for i in range(versions):
            _new_version(module)
            for side, link in links.items():
                seconds, received, wire[side] = link.send(module)
                times[side].append(seconds)
                if i == versions - 1:
                    _check_same(module, received)
    finally:
        for link in links.values():
            link.close()
    ours_t, peer_t, ours_wire, peer_wire = times["ours"], times["peer"], wire["ours"], wire["peer"]
    ours_ms, peer_ms = median(ours_t) * 1e3, median(peer_t) * 1e3
    group = f"weights {label} ({n_params / 1e6:.2f}M params, {raw_bytes / 2**20:.1f} MiB)"
    return [
        Row(
            group,
            f"latency per version (median of {versions})",
            ours_ms,
            peer_ms,
            "ms",
            False,
            "publish -> decoded on the receiver",
        ),
        Row(
            group,
            "throughput",
            raw_bytes / median(ours_t) / 1e6,
            raw_bytes / median(peer_t) / 1e6,
            "MB/s",
            True,
            "tensor bytes / latency",
        ),
        Row(
            group,
            "bytes on the wire per version",
            float(ours_wire),
            float(peer_wire),
            "B",
            False,
            f"chunks: ours {chunk >> 20} MiB, theirs 2 MiB",
        ),
    ]


def fact_rows() -> list[Row]:
    group = "weights: safety"
    return [
        Row(
            group, "receiver decodes with", "dtype+shape+bytes", "torch.load (pickle)", note="theirs: weights_only=True"
        ),
        Row(group, "integrity check", "xxh3-128 checksum per version (sha256 optional)", "none"),
        Row(group, "auth on the stream", "bearer token", "none"),
    ]


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    rows: list[Row] = []
    for label, config in models():
        versions = 2 if quick else (30 if label == "SAC actor" else 8)
        if quick and label != "SAC actor":
            config = {**config, "obs_dim": 64, "hidden": [256, 256]}
        log(f"weights: {label}, {versions} versions")
        rows += bench_model(label, config, versions)
    return rows + fact_rows()
