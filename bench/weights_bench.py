"""Weight streaming, learner -> N subscribers, over real gRPC servers on 127.0.0.1.

Measured per (model size, subscribers): seconds from the publish call on the learner side to every
subscriber holding the new version as numpy/torch tensors, for
  ours:    WeightStore.publish -> WeightServicer.StreamWeights (acked) -> WeightSubscriber, pinned fp32 full
           sets, and pinned XOR deltas + zstd against the previous version (versions move as training does:
           Adam steps on the weights);
  lerobot: one lerobot learner per actor, as lerobot serves actors (see PeerFanout): each pushes its
           own state_to_bytes through a torch.multiprocessing Queue to its LearnerService.StreamParameters,
           the actor receives (receive_bytes_in_chunks -> its Queue) and decodes (bytes_to_state_dict);
  ours, patch: error-bounded patches (lossy) against the state each subscriber holds, streamed
           (FP32_PATCH_STREAM_ZSTD: sent while later slices are quantized, applied as they arrive);
  ours, adaptive: the server picks per subscriber and version (lossy allowed); the rows say what it
           picked (on loopback: fp32 for small models, where a patch's CPU costs more than the bytes it saves);
  ours, same host, shared memory: the subscribers prove they share the learner's /dev/shm and get each
           version as a file there (FP32_SHM: written once, a header on the stream, copied out and
           digest-checked by each subscriber). Only for a subscriber on the learner's machine; the peers
           beside it in those rows still go through loopback TCP, as they would on one machine;
  raw:     a bare gRPC server stream of the same fp32 bytes in 1 MiB chunks into a preallocated buffer
           (no manifest, no checksum, no auth): the floor for a full set.
Plus the learner's updates/s with 0, 1 and 8 subscribers, and (bench.weights_link, in a private
network namespace with tc tbf at 20 Mbit/s) time-to-fresh with adaptive encoding vs fp32 resends.
"""

from __future__ import annotations

import multiprocessing
import queue
import shutil
import tempfile
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
from user.policy import actor_from_config, policy_spec_for
from user.v1 import learner_pb2
from user.weight_codec import WE, encoding_name
from user.weight_shm import DEFAULT_KEEP, ShmWeights
from user.weights import WeightServicer, WeightSet, WeightStore, WeightSubscriber, add_learner_servicer

RECEIVE_TIMEOUT_S = 300.0
CHUNK = 1 << 20
RAW = "raw gRPC stream"


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
    sac = actor_config(15, 3, list(LearnerConfig().hidden))  # the sim arm's actor at the learner's default widths
    return [("SAC actor", sac), ("big MLP", actor_config(1024, 7, [2048, 2048, 2048]))]


def sized_config(params: float) -> dict[str, Any]:
    """An MLP actor with about `params` parameters (3 hidden layers of equal width)."""
    width = int((params / 2) ** 0.5)
    return actor_config(64, 7, [width, width, width])


def state_views(module: torch.nn.Module) -> dict[str, np.ndarray]:
    """The module's tensors as numpy views (no copy): what both the raw stream and ours publish from. Safe
    here because nothing trains during a send; pack_weights and tobytes copy them before returning."""
    return {k: v.detach().numpy() for k, v in module.state_dict().items()}


class Trainer:
    """Moves an actor's weights the way training does between two published versions: Adam steps."""

    def __init__(
        self, module: torch.nn.Module, steps: int = 5, lr: float = 3e-4, trainable: tuple[str, ...] = ("",)
    ) -> None:
        """trainable: name prefixes of the parameters that learn; the rest stay frozen (fine-tuning)."""
        self.module, self.steps = module, steps
        params = [p for n, p in module.named_parameters() if n.startswith(trainable)]
        self.opt = torch.optim.Adam(params, lr=lr)
        self.obs = torch.randn(64, 64, generator=torch.Generator().manual_seed(0))

    def step(self) -> None:
        for _ in range(self.steps):
            _, _, mean_action = self.module(self.obs)
            loss = (mean_action - 0.5).square().mean()
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()


# --------------------------------------------------------------------------- ours


class OursFanout:
    """A real learner gRPC server (auth on) with our servicer, and n WeightSubscribers (own channels)."""

    def __init__(
        self,
        spec: learner_pb2.PolicySpec,
        n: int,
        encoding: int,
        allow_lossy: bool = False,
        remote: int = 0,
        shm: bool = False,
    ) -> None:
        """remote: streams the server must also hold for subscribers in other processes; shm: same-host
        shared memory (a private directory under /dev/shm, removed at close)."""
        self.spec, self.auth = spec, AuthConfig(token="bench-token")
        self.store = WeightStore(history=2)
        self.shm_dir = tempfile.mkdtemp(prefix="user-bench-", dir="/dev/shm") if shm else None
        self.shm = ShmWeights(self.shm_dir) if self.shm_dir else None
        self.servicer = servicer = WeightServicer(self.store, shm=self.shm)
        name = learner_pb2.DESCRIPTOR.services_by_name["Learner"].full_name
        self.server = rpc.start_server(
            "bench-learner",
            lambda s: add_learner_servicer(servicer, s),
            [name],
            ServerConfig(host="127.0.0.1", port=0, metrics_port=0, max_workers=4 + 2 * (n + remote), grace_s=0.5),
            self.auth,
            start_metrics=False,
        )
        self.received: queue.Queue[tuple[float, WeightSet]] = queue.Queue()
        self.subs = [
            WeightSubscriber(
                self.server.address(),
                self.auth,
                f"bench-{i}",
                lambda ws: self.received.put((time.perf_counter(), ws)),
                encoding=encoding,
                allow_lossy=allow_lossy,
                shm_dir=self.shm_dir,
            ).start()
            for i in range(n)
        ]
        self.version = 0
        self.wire_bytes = 0
        self.last_encoding = 0
        self.encodings: list[int] = []  # what each subscriber got, last send

    def send(self, module: torch.nn.Module) -> tuple[float, dict[str, Any]]:
        self.version += 1
        start = time.perf_counter()
        self.store.publish(self.version, self.spec, state_views(module))
        last, got = 0.0, None
        self.wire_bytes, self.encodings = 0, []
        for _ in self.subs:
            arrived, got = self.received.get(timeout=RECEIVE_TIMEOUT_S)
            if got.version != self.version:
                raise RuntimeError(f"expected weight v{self.version}, got v{got.version}")
            last = max(last, arrived)
            self.wire_bytes += got.encoded_bytes
            self.last_encoding = got.encoding
            self.encodings.append(got.encoding)
        return last - start, got.tensors

    def close(self) -> None:
        for s in self.subs:
            s.stop()
        self.store.close()
        self.server.stop()
        if self.shm is not None and self.shm_dir is not None:
            self.shm.close()
            shutil.rmtree(self.shm_dir, ignore_errors=True)


# --------------------------------------------------------------------------- lerobot


class PeerFanout:
    """n actors served the way lerobot 0.6.1 serves them: one learner (service + server) per actor.

    One lerobot learner cannot feed several actors: its LearnerService hands each push from its one
    parameters queue to whichever StreamParameters stream drains it first (get_last_item_from_queue),
    and its server has MAX_WORKERS = 3 threads, one actor's three streams. So n actors mean n learners,
    and each learner pushes its own weights as push_actor_policy_to_queue does: state_to_bytes
    (torch.save) of its own state dict, then put on a torch.multiprocessing Queue, which its gRPC
    thread drains. Each actor receives with receive_bytes_in_chunks into its own torch.multiprocessing
    Queue, and its loop takes the latest item and decodes it (bytes_to_state_dict = torch.load), as
    update_policy_parameters does. All in threads of one process (lerobot's default concurrency is
    "threads"; ours runs in one process too); the n pushes start at once, like n learners publishing.
    """

    def __init__(self, n: int) -> None:
        from lerobot.rl.learner_service import MAX_WORKERS, LearnerService
        from lerobot.rl.queue import get_last_item_from_queue
        from lerobot.transport import services_pb2, services_pb2_grpc
        from lerobot.transport import utils as lt
        from torch.multiprocessing import Queue as MpQueue

        self.lt, self.pb, self.latest = lt, services_pb2, get_last_item_from_queue
        self.shutdown = threading.Event()
        self.queues: list[Any] = []
        self.servers, self.channels, self.calls, self.threads = [], [], [], []
        self.handlers: list[futures.ThreadPoolExecutor] = []  # each server's handler threads
        self.received: queue.Queue[tuple[float, dict[str, torch.Tensor]]] = queue.Queue()
        self.pool = futures.ThreadPoolExecutor(max_workers=n, thread_name_prefix="peer-learner")
        for _ in range(n):
            q = MpQueue()
            service = LearnerService(
                shutdown_event=self.shutdown,
                parameters_queue=q,
                seconds_between_pushes=0.0,  # push as soon as a version is queued (their default waits 4 s)
                transition_queue=MpQueue(),
                interaction_message_queue=MpQueue(),
                queue_get_timeout=0.05,
            )
            handlers = futures.ThreadPoolExecutor(max_workers=MAX_WORKERS)
            server = grpc.server(
                handlers,
                options=[
                    ("grpc.max_receive_message_length", lt.MAX_MESSAGE_SIZE),
                    ("grpc.max_send_message_length", lt.MAX_MESSAGE_SIZE),
                ],
            )
            services_pb2_grpc.add_LearnerServiceServicer_to_server(service, server)
            port = server.add_insecure_port("127.0.0.1:0")
            server.start()
            channel = grpc.insecure_channel(f"127.0.0.1:{port}", lt.grpc_channel_options())
            call = services_pb2_grpc.LearnerServiceStub(channel).StreamParameters(services_pb2.Empty())
            thread = threading.Thread(target=self._receive, args=(call,), daemon=True, name="peer-receive")
            thread.start()
            self.queues.append(q)
            self.servers.append(server)
            self.handlers.append(handlers)
            self.channels.append(channel)
            self.calls.append(call)
            self.threads.append(thread)

    def _receive(self, call: Any) -> None:
        from torch.multiprocessing import Queue as MpQueue

        blobs = MpQueue()  # the actor's parameters queue

        def actor_loop() -> None:
            while not self.shutdown.is_set():
                try:
                    data = self.latest(blobs, block=True, timeout=0.1)
                except (OSError, ValueError):
                    return  # the queue went with its stream at close()
                if data is not None:
                    self.received.put((time.perf_counter(), self.lt.bytes_to_state_dict(data)))  # torch.load

        threading.Thread(target=actor_loop, daemon=True).start()
        try:
            self.lt.receive_bytes_in_chunks(call, blobs, self.shutdown, log_prefix="[bench]")
        except grpc.RpcError:
            pass  # cancelled at close()

    def _push(self, q: Any, module: torch.nn.Module) -> None:
        q.put(self.lt.state_to_bytes(module.state_dict()))  # this learner's push_actor_policy_to_queue

    def send(self, module: torch.nn.Module) -> tuple[float, dict[str, Any]]:
        start = time.perf_counter()
        for f in [self.pool.submit(self._push, q, module) for q in self.queues]:
            f.result()
        last, state = 0.0, None
        for _ in self.queues:
            arrived, state = self.received.get(timeout=RECEIVE_TIMEOUT_S)
            last = max(last, arrived)
        return last - start, state

    def close(self) -> None:
        self.shutdown.set()
        for call in self.calls:
            call.cancel()
        for t in self.threads:
            t.join(5)
        for c in self.channels:
            c.close()
        for s in self.servers:
            s.stop(0.5).wait()
        for h in self.handlers:  # StreamParameters returns within its queue timeout once shutdown is set: let it,
            h.shutdown(wait=True)  # or it reads a queue already gone ("handle is closed" logged by grpc)
        self.pool.shutdown()
        for q in self.queues:  # not closed: a stopped service's thread may still be in its get()
            q.cancel_join_thread()


# --------------------------------------------------------------------------- raw stream


def _ident(x: bytes) -> bytes:
    return x


class RawFanout:
    """A bare gRPC server stream of the fp32 bytes (bytes messages, no proto, no checks) to n receivers."""

    def __init__(self, n: int) -> None:
        self.payload: bytes = b""
        self.version = 0
        self.stopped = False
        self.cond = threading.Condition()
        self.server = grpc.server(futures.ThreadPoolExecutor(max_workers=n + 4))
        handler = grpc.method_handlers_generic_handler(
            "bench.Raw", {"Stream": grpc.unary_stream_rpc_method_handler(self._stream, _ident, _ident)}
        )
        self.server.add_generic_rpc_handlers((handler,))
        port = self.server.add_insecure_port("127.0.0.1:0")
        self.server.start()
        self.received: queue.Queue[tuple[float, int]] = queue.Queue()
        self.channels, self.calls = [], []
        for _ in range(n):
            ch = grpc.insecure_channel(f"127.0.0.1:{port}", [("grpc.max_receive_message_length", 64 << 20)])
            call = ch.unary_stream("/bench.Raw/Stream", request_serializer=_ident, response_deserializer=_ident)(b"")
            threading.Thread(target=self._receive, args=(call,), daemon=True).start()
            self.channels.append(ch)
            self.calls.append(call)

    def _stream(self, request: bytes, context: grpc.ServicerContext):  # type: ignore[no-untyped-def]
        have = 0
        while context.is_active() and not self.stopped:
            with self.cond:
                self.cond.wait_for(lambda have=have: self.version > have or self.stopped, 0.5)
                if self.version <= have:
                    continue
                have, payload = self.version, self.payload
            header = len(payload).to_bytes(8, "little")
            yield header
            view = memoryview(payload)
            for i in range(0, len(payload), CHUNK):
                yield bytes(view[i : i + CHUNK])

    def _receive(self, call: Any) -> None:
        try:
            buf, filled, size = None, 0, 0
            for msg in call:
                if buf is None:
                    size = int.from_bytes(msg, "little")
                    buf, filled = np.empty(size, dtype=np.uint8), 0
                    if size == 0:
                        self.received.put((time.perf_counter(), size))
                        buf = None
                    continue
                buf[filled : filled + len(msg)] = np.frombuffer(msg, dtype=np.uint8)
                filled += len(msg)
                if filled == size:
                    self.received.put((time.perf_counter(), size))
                    buf = None
        except grpc.RpcError:
            pass

    def send(self, module: torch.nn.Module) -> tuple[float, None]:
        start = time.perf_counter()
        payload = b"".join(np.ascontiguousarray(t).tobytes() for t in state_views(module).values())
        with self.cond:
            self.payload, self.version = payload, self.version + 1
            self.cond.notify_all()
        last = 0.0
        for _ in self.calls:
            arrived, _size = self.received.get(timeout=RECEIVE_TIMEOUT_S)
            last = max(last, arrived)
        return last - start, None

    def close(self) -> None:
        self.stopped = True
        with self.cond:
            self.cond.notify_all()
        for c in self.calls:
            c.cancel()
        for ch in self.channels:
            ch.close()
        self.server.stop(0.5).wait()


# --------------------------------------------------------------------------- driver


def _check_same(module: torch.nn.Module, received: dict[str, Any]) -> None:
    for name, ref in module.state_dict().items():
        if not np.array_equal(np.asarray(received[name]), ref.numpy()):
            raise AssertionError(f"received weights differ from the sent ones at {name}")


FROZEN_HALF = ("net.4.", "net.6.")  # last hidden layer + head learn; the first layers stay frozen
# Above this the adaptive side's store and buffers would push the 100M group (~13 GB) past free memory.
ADAPTIVE_UP_TO_BYTES = 128 << 20
# Versions more for the shared-memory link before measuring: the first `keep` files are fresh tmpfs pages
# (~5 ms per 4 MiB here); from then on each version reuses the pages of the one that left, as in training.
SHM_WARMUP = DEFAULT_KEEP


def bench_fanout(
    label: str, config: dict[str, Any], n: int, versions: int, log: Callable[..., None], frozen: bool = False
) -> list[Row]:
    torch.manual_seed(0)
    module = actor_from_config(config)
    trainer = Trainer(module, trainable=FROZEN_HALF if frozen else ("",))
    n_params = sum(p.numel() for p in module.parameters())
    raw_bytes = sum(t.numel() * t.element_size() for t in module.state_dict().values())
    spec = policy_spec_for(config)
    makers: dict[str, Callable[[], Any]] = {
        "fp32": lambda: OursFanout(spec, n, WE.WEIGHT_ENCODING_FP32),
        "delta": lambda: OursFanout(spec, n, WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD),
        "patch": lambda: OursFanout(spec, n, WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD, allow_lossy=True),
        "raw": lambda: RawFanout(n),
        "lerobot": lambda: PeerFanout(n),
    }
    if raw_bytes <= ADAPTIVE_UP_TO_BYTES:  # what a subscriber that lets the server choose gets on this link
        makers["adaptive"] = lambda: OursFanout(spec, n, WE.WEIGHT_ENCODING_ADAPTIVE, allow_lossy=True)
        if not frozen:  # same host: the version through /dev/shm (its fallback, if ever: fp32 on the stream)
            makers["shm"] = lambda: OursFanout(spec, n, WE.WEIGHT_ENCODING_FP32, shm=True)
    picked: dict[str, int] = {}
    times: dict[str, list[float]] = {k: [] for k in makers}
    wire: dict[str, int] = {}
    links: dict[str, Any] = {}
    try:
        for side, make in makers.items():
            links[side] = make()
            links[side].send(module)  # warm-up version: connection set-up, first allocations, delta base
        trainer.step()
        for link in links.values():  # a second one: the first delta/patch fills the buffer pools on both ends
            link.send(module)
        if "shm" in links:  # its steady state: each version written over the pages of the file that left
            for _ in range(SHM_WARMUP):
                links["shm"].send(module)
        for i in range(versions):
            trainer.step()
            for side, link in links.items():  # take turns, so background load hits all alike
                seconds, received = link.send(module)
                times[side].append(seconds)
                if side in ("delta", "patch", "adaptive"):
                    wire[side] = link.wire_bytes // n
                if side == "adaptive":
                    for enc in link.encodings:
                        picked[encoding_name(enc)] = picked.get(encoding_name(enc), 0) + 1
                if side == "shm" and any(enc != WE.WEIGHT_ENCODING_FP32_SHM for enc in link.encodings):
                    raise RuntimeError(f"shared-memory subscribers got {link.encodings}, not fp32_shm")
                if i == versions - 1 and side in ("fp32", "delta", "shm"):
                    _check_same(module, received)
    finally:
        for link in links.values():
            link.close()
    ms = {k: median(v) * 1e3 for k, v in times.items()}
    log(f"  {label} x{n}: " + ", ".join(f"{k} {v:.0f} ms" for k, v in ms.items()))
    group = f"weights {label} ({n_params / 1e6:.1f}M params, {raw_bytes / 2**20:.0f} MiB) -> {n} subscriber(s)"
    if frozen:
        group += ", first layers frozen (fine-tuning)"
    what = f"publish -> all {n} hold it (median of {versions})"
    rows = [
        Row(group, f"{what}, fp32 full", ms["fp32"], ms["lerobot"], "ms", False, "ours pinned fp32 vs lerobot"),
        Row(group, f"{what}, fp32 full vs raw", ms["fp32"], ms["raw"], "ms", False, "raw = floor", peer_name=RAW),
        Row(
            group,
            f"{what}, XOR delta+zstd vs raw",
            ms["delta"],
            ms["raw"],
            "ms",
            False,
            f"delta {wire.get('delta', 0) / 2**20:.1f} MiB of {raw_bytes / 2**20:.0f}",
            peer_name=RAW,
        ),
        Row(
            group,
            f"{what}, error-bounded patch vs raw",
            ms["patch"],
            ms["raw"],
            "ms",
            False,
            f"lossy (2^-10 x block RMS); {wire.get('patch', 0) / 2**20:.1f} MiB of {raw_bytes / 2**20:.0f}",
            peer_name=RAW,
        ),
        Row(group, f"{what}, error-bounded patch vs lerobot", ms["patch"], ms["lerobot"], "ms", False, "lossy"),
    ]
    if "adaptive" in ms:
        chose = ", ".join(f"{k} x{v}" for k, v in sorted(picked.items()))
        note = (
            f"server's choice per subscriber and version (lossy allowed): {chose}; {wire['adaptive'] / 2**20:.1f} MiB"
        )
        rows.append(Row(group, f"{what}, adaptive encoding vs raw", ms["adaptive"], ms["raw"], "ms", False, note, RAW))
    if "shm" in ms:
        shm_group = f"{group}, SAME HOST (shared memory)"
        note = (
            "same host only: ours via /dev/shm (digest-checked; steady state, each version over the pages of the"
            " file that left), the peer over loopback TCP"
        )
        rows += [
            Row(shm_group, f"{what}, fp32 via shared memory vs lerobot", ms["shm"], ms["lerobot"], "ms", False, note),
            Row(shm_group, f"{what}, fp32 via shared memory vs raw", ms["shm"], ms["raw"], "ms", False, note, RAW),
        ]
    return rows


# --------------------------------------------------------------------------- learner updates/s


def _subscribe_elsewhere(addr: str, token: str, n: int, stop: Any) -> None:
    """n WeightSubscribers in this (spawned) process: edges and inference servers live elsewhere."""
    subs = [WeightSubscriber(addr, AuthConfig(token=token), f"remote-{i}", lambda ws: None).start() for i in range(n)]
    stop.wait()
    for sub in subs:
        sub.stop()


class RemoteSubscribers:
    """n subscribers in another process (sharing the same CPU cores, not the learner's GIL)."""

    def __init__(self, addr: str, token: str, n: int) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self.n, self.stop = n, ctx.Event()
        self.proc = ctx.Process(target=_subscribe_elsewhere, args=(addr, token, n, self.stop), daemon=True)
        if n:
            self.proc.start()

    def wait_ready(self, fan: OursFanout, timeout: float) -> bool:
        """True once all n subscribers hold the first version (acked)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status = fan.servicer.subscriber_status()
            if len(status) == self.n and all(st.applied_version >= 1 for st in status):
                return True
            time.sleep(0.1)
        return False

    def close(self) -> None:
        if self.n:
            self.stop.set()
            self.proc.join(10)
            if self.proc.is_alive():
                self.proc.kill()


def _sac_batch() -> tuple[Any, Any, Any]:
    """A SAC on the sim-arm shapes with the learner's default widths, its layout and one training batch."""
    from cloud_learner.algorithm import Batch, Feature, Layout
    from tests.helpers import random_sac_batch

    obs_dim, act_dim = 15, 3
    lc = LearnerConfig()
    ones = np.ones(act_dim, dtype=np.float32)
    layout = Layout({"state": Feature((obs_dim,), "float32")}, -ones, ones)
    raw = random_sac_batch(obs_dim, act_dim, seed=0, n=lc.batch_size)
    batch = Batch(
        observation={"state": raw["obs"]},
        action=raw["action"],
        reward=raw["reward"],
        next_observation={"state": raw["next_obs"]},
        terminated=raw["terminated"],
        intervention=torch.zeros(lc.batch_size, dtype=torch.bool),
    )
    return lc, layout, batch


def bench_learner_rate(
    subscriber_counts: list[int], seconds: float, log: Callable[..., None], windows: int = 25
) -> list[Row]:
    """Real SAC updates on the sim-arm shapes, publishing every publish_every updates into a served store,
    with n acked subscribers in another process (where edges and inference servers are: not in the
    learner's process, so they cost it CPU time, not its GIL).

    One SAC trains throughout; every subscriber count has its own server and subscriber process, set up
    once, and the counts take turns in short windows (order rotated each turn), so load that comes and
    goes on a shared machine hits every count alike. Rates are medians over the windows; the spread
    (min-max of the windows, and of the per-turn ratios) says whether a difference is real."""
    from cloud_learner.algorithm import ALGORITHMS

    lc, layout, batch = _sac_batch()
    torch.manual_seed(0)
    sac = ALGORITHMS.build("sac", {"hidden": list(lc.hidden)}, layout=layout, device=torch.device("cpu"))
    spec, _ = sac.policy()
    setups: dict[int, tuple[OursFanout, RemoteSubscribers]] = {}
    versions = dict.fromkeys(subscriber_counts, 1)
    samples: dict[int, list[float]] = {n: [] for n in subscriber_counts}
    try:
        for n in subscriber_counts:
            fan = OursFanout(spec, 0, WE.WEIGHT_ENCODING_ADAPTIVE, remote=n)
            setups[n] = (fan, RemoteSubscribers(fan.server.address(), fan.auth.token, n))
            fan.store.publish(1, spec, sac.policy()[1])
        for n, (fan, subs) in setups.items():
            if n and not subs.wait_ready(fan, 120):
                raise RuntimeError(f"{n} subscriber processes did not connect")
        for _ in range(20):  # warm-up: the first updates of a fresh SAC take ~100x longer
            sac.update(batch)
        window, total = max(0.2, seconds / windows), 0
        for turn in range(windows):
            order = (
                subscriber_counts[turn % len(subscriber_counts) :] + subscriber_counts[: turn % len(subscriber_counts)]
            )
            for n in order:
                store, updates = setups[n][0].store, 0
                start = time.perf_counter()
                while time.perf_counter() - start < window or updates < 5:  # a rate > 0 under load
                    sac.update(batch)
                    updates, total = updates + 1, total + 1
                    if total % lc.publish_every == 0:  # counted across windows: each count gets its share
                        versions[n] += 1
                        spec, tensors = sac.policy()
                        store.publish(versions[n], spec, tensors, total)
                samples[n].append(updates / (time.perf_counter() - start))
    finally:
        for fan, subs in setups.values():
            subs.close()
            fan.close()
    rates = {n: median(v) for n, v in samples.items()}
    for n in subscriber_counts:
        lo, hi = min(samples[n]), max(samples[n])
        log(
            f"  learner with {n} subscribers: median {rates[n]:.0f} updates/s over {windows} windows of {window:.1f} s"
            f" (min {lo:.0f}, max {hi:.0f}; windows {[round(x) for x in samples[n]]})"
        )
    group = f"learner updates/s while publishing (SAC sim arm, publish every {lc.publish_every})"
    rows = []
    for n in subscriber_counts:
        if not n:
            continue
        turns = sorted(a / b for a, b in zip(samples[n], samples[0], strict=True))  # same turn: same load
        note = (
            f"medians of {windows} interleaved windows; per-turn ratio {median(turns):.2f}x"
            f" (min {turns[0]:.2f}, max {turns[-1]:.2f}); windows {round(min(samples[n]))}-{round(max(samples[n]))}"
            f" vs {round(min(samples[0]))}-{round(max(samples[0]))}"
        )
        rows.append(Row(group, f"updates/s with {n} subscribers", rates[n], rates[0], "1/s", True, note, "no subs"))
    return rows


def fact_rows() -> list[Row]:
    group = "weights: safety"
    return [
        Row(
            group, "receiver decodes with", "dtype+shape+bytes", "torch.load (pickle)", note="theirs: weights_only=True"
        ),
        Row(group, "integrity check", "xxh3-128 checksum per version (sha256 optional)", "none"),
        Row(group, "auth on the stream", "bearer token", "none"),
        Row(group, "version after learner kill -9", "never reused (high-water mark)", "n/a (no versions)"),
        Row(
            group,
            "weights off a GPU learner",
            "pinned host copies, one wait per version (no side stream); timed by `make gpu` (publish rows)",
            "n/a",
        ),
    ]


def _fanout_child(label: str, params: float, n: int, versions: int, frozen: bool) -> tuple[list[Row], list[str]]:
    torch.set_num_threads(1)
    lines: list[str] = []
    rows = bench_fanout(label, sized_config(params), n, versions, lines.append, frozen)
    return rows, lines


def _fanout_in_child(
    label: str, params: float, n: int, versions: int, frozen: bool, log: Callable[..., None]
) -> list[Row]:
    """One fan-out group in a fresh process: a 100M model's five links (ours x3, raw, lerobot) peak near 13 GB,
    and memory the groups before it freed inside this process is not returned to the OS in time."""
    ctx = multiprocessing.get_context("spawn")
    with futures.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
        rows, lines = pool.submit(_fanout_child, label, params, n, versions, frozen).result()
    for line in lines:
        log(line)
    return rows


def run(quick: bool, workdir: Path, log: Callable[..., None] = print) -> list[Row]:
    from bench import weights_link

    rows: list[Row] = []
    if quick:
        plan = [("1M", 1e6 / 16, [1, 2], 1, False)]
    else:
        plan = [
            ("1M", 1e6, [1, 8], 3, False),
            ("25M", 25e6, [1, 8], 2, False),
            ("25M", 25e6, [8], 2, True),
            ("100M", 100e6, [1], 1, False),
        ]
    for label, params, fanouts, versions, frozen in plan:
        for n in fanouts:
            log(f"weights: {label} params, {n} subscriber(s), {versions} versions" + (", frozen" if frozen else ""))
            rows += _fanout_in_child(label, params, n, versions, frozen, log)
    rows += bench_learner_rate([0, 1, 2] if quick else [0, 1, 8], 2.0 if quick else 15.0, log, 5 if quick else 25)
    rows += weights_link.run(quick, log)
    return rows + fact_rows()
