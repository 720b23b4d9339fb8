"""The asynchronous learner: sample from Replay, update SAC, publish weight versions, checkpoint.

Nothing here waits for an episode to end: a sampler thread keeps `prefetch_batches` decoded batches
ready while the training thread updates as fast as it can, bounded by the update-to-data cap
(max_updates_per_transition x sampleable transitions) so a tiny buffer is not overfitted. Every
`publish_every` updates a new weight version goes to the WeightStore (streamed to inference and
edges); every `checkpoint_every` updates, and on shutdown, an atomic checkpoint is written.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import grpc
import numpy as np
import prometheus_client
import torch

from cloud_learner.checkpoint import load_latest, read_version_mark, save_checkpoint, write_version_mark
from cloud_learner.sac import SAC
from user import rpc
from user.config import StackConfig
from user.log import kv
from user.policy import policy_spec_for
from user.v1 import control_pb2, control_pb2_grpc, replay_pb2, replay_pb2_grpc, robot_pb2
from user.weights import WeightStore
from user.wire import WireError, from_tensor

log = logging.getLogger(__name__)

OBS_KEY = "state"

UPDATES = prometheus_client.Counter("user_learner_updates_total", "SAC gradient updates")
UPDATES_PER_S = prometheus_client.Gauge("user_learner_updates_per_second", "SAC updates per second (last ~2 s)")
WEIGHT_VERSION = prometheus_client.Gauge("user_learner_weight_version", "Latest published weight version")
LOSS = prometheus_client.Gauge("user_learner_loss", "Last SAC losses", ["name"])
ALPHA = prometheus_client.Gauge("user_learner_alpha", "SAC entropy temperature")
BATCH_WAIT = prometheus_client.Histogram(
    "user_learner_batch_wait_seconds",
    "Time the training loop waited for a prefetched batch",
    buckets=(0.0001, 0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1, 5),
)
BUFFER_TRANSITIONS = prometheus_client.Gauge("user_learner_buffer_transitions", "Sampleable transitions in Replay")
CHECKPOINT_SECONDS = prometheus_client.Histogram(
    "user_learner_checkpoint_seconds", "Time to write a checkpoint", buckets=(0.01, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10)
)
CAPPED = prometheus_client.Counter(
    "user_learner_capped_total", "Times training paused at the update-to-data cap (max_updates_per_transition)"
)


class LearnerError(RuntimeError):
    """The learner cannot go on (e.g. a checkpoint for a different robot)."""


@dataclass
class RobotShape:
    obs_dim: int
    action_low: np.ndarray
    action_high: np.ndarray


@dataclass
class Prefetched:
    batch: dict[str, torch.Tensor]
    transitions: int


@dataclass
class LearnerState:
    """What GetStatus reports; written by the training thread, read by RPC threads."""

    updates: int = 0
    weight_version: int = 0
    updates_per_s: float = 0.0
    buffer_transitions: int = 0
    losses: dict[str, float] = field(default_factory=dict)
    alpha: float = 0.0
    last_publish_ns: int = 0
    last_update_mono: float = 0.0


def robot_shape(spec: robot_pb2.RobotSpec) -> RobotShape:
    """obs_dim from the "state" feature, flattened action bounds from the action space."""
    feats = {f.name: f for f in spec.observation}
    if OBS_KEY not in feats:
        raise LearnerError(f"robot {spec.robot_id} ({spec.kind}) has no {OBS_KEY!r} observation feature")
    obs_dim = int(math.prod(feats[OBS_KEY].shape))
    low = np.asarray(spec.action.low, dtype=np.float32).reshape(-1)
    high = np.asarray(spec.action.high, dtype=np.float32).reshape(-1)
    if obs_dim < 1 or low.size < 1 or low.shape != high.shape:
        raise LearnerError(
            f"robot {spec.robot_id}: unusable spec (obs_dim {obs_dim}, action bounds {low.size}/{high.size})"
        )
    return RobotShape(obs_dim, low, high)


def decode_batch(batch: replay_pb2.Batch, obs_dim: int, action_dim: int, device: str) -> dict[str, torch.Tensor]:
    """Replay batch -> SAC batch (float32 tensors). Only the "state" features are decoded."""
    if OBS_KEY not in batch.observation.tensors or OBS_KEY not in batch.next_observation.tensors:
        raise WireError(f"batch lacks observation[{OBS_KEY!r}]")
    obs = from_tensor(batch.observation.tensors[OBS_KEY])
    n = obs.shape[0] if obs.ndim else 0
    arrays = {
        "obs": obs.reshape(n, -1),
        "next_obs": from_tensor(batch.next_observation.tensors[OBS_KEY]).reshape(n, -1),
        "action": from_tensor(batch.action).reshape(n, -1),
        "reward": from_tensor(batch.reward).reshape(n),
        "terminated": from_tensor(batch.terminated).reshape(n),
    }
    if n < 1 or arrays["obs"].shape[1] != obs_dim or arrays["next_obs"].shape[1] != obs_dim:
        raise WireError(f"batch observations {arrays['obs'].shape} do not match obs_dim {obs_dim}")
    if arrays["action"].shape[1] != action_dim:
        raise WireError(f"batch actions {arrays['action'].shape} do not match action_dim {action_dim}")
    return {k: torch.from_numpy(v.astype(np.float32, copy=False)).to(device) for k, v in arrays.items()}


def checkpoint_state(sac: Any, weight_version: int, shape: RobotShape) -> dict[str, Any]:
    """What a checkpoint holds: SAC (nets, optimizers, log_alpha, updates) plus what it was trained for."""
    return {
        "sac": sac.state_dict(),
        "weight_version": int(weight_version),
        "updates": int(sac.updates),
        "obs_dim": shape.obs_dim,
        # tensors, not numpy: torch.load(weights_only=True) accepts them without extra globals
        "action_low": torch.from_numpy(shape.action_low.copy()),
        "action_high": torch.from_numpy(shape.action_high.copy()),
    }


def restore_checkpoint(sac: Any, ckpt: dict[str, Any], shape: RobotShape, where: object = "checkpoint") -> int:
    """Load `ckpt` into `sac` after checking it was trained for this robot; returns the weight version."""
    low = np.asarray(ckpt["action_low"], dtype=np.float32).reshape(-1)
    high = np.asarray(ckpt["action_high"], dtype=np.float32).reshape(-1)
    same = (
        int(ckpt["obs_dim"]) == shape.obs_dim
        and low.shape == shape.action_low.shape
        and np.allclose(low, shape.action_low)
        and np.allclose(high, shape.action_high)
    )
    if not same:
        raise LearnerError(
            f"{where} is for obs_dim {int(ckpt['obs_dim'])} and {low.size}-d actions in [{low}, {high}], the robot "
            f"has obs_dim {shape.obs_dim} and {shape.action_low.size}-d actions; use another learner.checkpoint_dir"
        )
    sac.load_state_dict(ckpt["sac"])
    version = max(1, int(ckpt["weight_version"]))
    log.info("resumed", extra=kv(updates=int(sac.updates), weight_version=version))
    return version


class Learner:
    """start() runs setup + training in a thread; stop() ends it and writes the final checkpoint."""

    def __init__(self, cfg: StackConfig, store: WeightStore) -> None:
        self.cfg, self.lc = cfg, cfg.learner
        self.store = store
        self.state = LearnerState()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._queue: queue.Queue[Prefetched] = queue.Queue(maxsize=self.lc.prefetch_batches)
        self._thread: threading.Thread | None = None
        self._sampler: threading.Thread | None = None
        self._sac: Any = None
        self._shape: RobotShape | None = None
        self._last_ckpt_updates = -1

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> Learner:
        self._thread = threading.Thread(target=self._main, name="learner", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 60.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def failed(self) -> bool:
        return self.error is not None

    @property
    def training(self) -> bool:
        last = self.state.last_update_mono
        return last > 0 and time.monotonic() - last < 2.0

    def _main(self) -> None:
        try:
            shape = self._wait_for_robot()
            if shape is None:
                return
            self._setup(shape)
            self._sampler = threading.Thread(target=self._sample_loop, name="learner-sampler", daemon=True)
            self._sampler.start()
            self._train_loop()
        except BaseException as exc:
            self.error = exc
            log.exception("learner failed")
        finally:
            self._stop.set()
            if self._sampler is not None:
                self._sampler.join(self.lc.rpc_timeout_s + 1)
            if self._sac is not None and self.error is None:
                self._checkpoint()

    # ------------------------------------------------------------------ setup

    def _wait_for_robot(self) -> RobotShape | None:
        """Poll Control until a robot of cfg.learner.robot_kind is known; None if stopped first."""
        backoff = rpc.Backoff(initial_s=0.2, max_s=5.0)
        with rpc.make_channel(self.lc.control_addr, self.cfg.auth) as channel:
            stub = control_pb2_grpc.ControlStub(channel)
            while not self._stop.is_set():
                try:
                    resp = stub.ListRobots(
                        control_pb2.ListRobotsRequest(include_offline=True), timeout=self.lc.rpc_timeout_s
                    )
                    for info in resp.robots:
                        if info.spec.kind == self.lc.robot_kind:
                            log.info("robot found", extra=kv(robot_id=info.spec.robot_id, kind=info.spec.kind))
                            return robot_shape(info.spec)
                    log.info("waiting for a robot", extra=kv(kind=self.lc.robot_kind, known=len(resp.robots)))
                except grpc.RpcError as err:
                    log.warning("ListRobots failed", extra=kv(addr=self.lc.control_addr, code=str(err.code())))
                if not backoff.sleep(self._stop):
                    break
        return None

    def _setup(self, shape: RobotShape) -> None:
        torch.manual_seed(self.lc.seed)
        self._shape = shape
        self._sac = SAC(shape.obs_dim, shape.action_low, shape.action_high, self.lc, device=self.lc.device)
        restored = 0
        ckpt = load_latest(self.lc.checkpoint_dir, map_location=self.lc.device)
        if ckpt is not None:
            restored = restore_checkpoint(self._sac, ckpt, shape, self.lc.checkpoint_dir)
            self._last_ckpt_updates = int(ckpt["updates"])
        # Never reuse a published number (the checkpoint may predate the last publishes, e.g. after
        # kill -9): subscribers holding a higher one would reject the new weights.
        version = max(restored, read_version_mark(self.lc.checkpoint_dir)) + 1
        self.state.updates = int(self._sac.updates)
        self.state.alpha = float(self._sac.alpha)
        self._publish(version)  # immediately: actors get a policy before any training

    # ------------------------------------------------------------------ sampling

    def _sample_loop(self) -> None:
        assert self._shape is not None
        backoff = rpc.Backoff(initial_s=0.1, max_s=5.0)
        action_dim = int(self._shape.action_low.size)
        request = replay_pb2.SampleRequest(batch_size=self.lc.batch_size)
        with rpc.make_channel(self.lc.replay_addr, self.cfg.auth) as channel:
            stub = replay_pb2_grpc.ReplayStub(channel)
            while not self._stop.is_set():
                try:
                    resp = stub.Sample(request, timeout=self.lc.rpc_timeout_s)
                except grpc.RpcError as err:
                    if err.code() == grpc.StatusCode.FAILED_PRECONDITION:  # empty buffer: not an error
                        self._set_transitions(0)
                    else:
                        log.warning("Sample failed", extra=kv(addr=self.lc.replay_addr, code=str(err.code())))
                    backoff.sleep(self._stop)
                    continue
                backoff.reset()
                self._set_transitions(int(resp.transitions))
                if resp.transitions < self.lc.min_transitions:
                    self._stop.wait(0.5)
                    continue
                try:
                    batch = decode_batch(resp.batch, self._shape.obs_dim, action_dim, self.lc.device)
                except WireError as exc:
                    log.error("undecodable batch", extra=kv(error=str(exc)))
                    backoff.sleep(self._stop)
                    continue
                self._put(Prefetched(batch, int(resp.transitions)))

    def _set_transitions(self, n: int) -> None:
        self.state.buffer_transitions = n
        BUFFER_TRANSITIONS.set(n)

    def _put(self, item: Prefetched) -> None:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.5)
                return
            except queue.Full:
                continue

    # ------------------------------------------------------------------ training

    def _train_loop(self) -> None:
        rate_t, rate_n = time.monotonic(), self._sac.updates
        while not self._stop.is_set():
            start = time.perf_counter()
            try:
                item = self._queue.get(timeout=0.5)
            except queue.Empty:
                continue
            BATCH_WAIT.observe(time.perf_counter() - start)
            if self._sac.updates >= self.lc.max_updates_per_transition * item.transitions:
                # At the update-to-data cap: drop this (stale) batch and let more data arrive.
                CAPPED.inc()
                self._stop.wait(0.1)
                continue
            self._update(item.batch)
            now = time.monotonic()
            if now - rate_t >= 2.0:
                self.state.updates_per_s = (self._sac.updates - rate_n) / (now - rate_t)
                UPDATES_PER_S.set(self.state.updates_per_s)
                rate_t, rate_n = now, self._sac.updates

    def _update(self, batch: dict[str, torch.Tensor]) -> None:
        losses = self._sac.update(batch)
        updates = int(self._sac.updates)
        st = self.state
        st.updates, st.losses, st.alpha = updates, dict(losses), float(self._sac.alpha)
        st.last_update_mono = time.monotonic()
        UPDATES.inc()
        ALPHA.set(st.alpha)
        for name, value in losses.items():
            LOSS.labels(name).set(value)
        if updates % self.lc.publish_every == 0:
            self._publish(st.weight_version + 1)
        if updates % self.lc.checkpoint_every == 0:
            self._checkpoint()

    def _publish(self, version: int) -> None:
        write_version_mark(self.lc.checkpoint_dir, version)  # before anyone can see it
        actor_config = {"obs_keys": [OBS_KEY], **self._sac.actor_config()}
        self.store.publish(version, policy_spec_for(actor_config), self._sac.actor_tensors(), int(self._sac.updates))
        self.state.weight_version = version
        self.state.last_publish_ns = time.time_ns()
        WEIGHT_VERSION.set(version)
        log.info("weights published", extra=kv(version=version, updates=int(self._sac.updates)))

    def _checkpoint(self) -> None:
        updates = int(self._sac.updates)
        if updates == self._last_ckpt_updates:
            return
        assert self._shape is not None
        start = time.perf_counter()
        save_checkpoint(self.lc.checkpoint_dir, checkpoint_state(self._sac, self.state.weight_version, self._shape))
        self._last_ckpt_updates = updates
        CHECKPOINT_SECONDS.observe(time.perf_counter() - start)
