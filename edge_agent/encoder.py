"""Camera frames JPEG/PNG-encoded on the edge, off the control loop, before a step enters the outbox.

A robot whose config names `image_encoding` (e.g. {"*": "jpeg"}) hands its steps, raw as observed, to a
FrameEncoder: send() only queues them; a background thread takes everything queued, encodes the frames
of the batch on a few threads (cv2 releases the GIL while it encodes) and passes the steps to the
sender (and so to the spool) in the order they were sent. Replay stores the bytes as given, after
checking that each frame decodes to its declared shape, and its sampler decodes them (uint8 as before).

A step is in the spool once its frames are encoded, a few ms after send(): a kill -9 in between loses
the steps still queued (at most `max_pending`), as it would lose a step not yet observed. A graceful stop
drains the queue first (flush). If the encoder falls behind by `max_pending` steps, send() waits for it:
the control loop slows down (its overruns are counted) rather than the edge holding unbounded frames.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import prometheus_client

from user import wire
from user.config import RobotConfig
from user.log import kv
from user.v1 import robot_pb2, step_pb2
from user.v1 import tensor_pb2 as tpb

log = logging.getLogger(__name__)

ENCODINGS = {"raw": tpb.ENCODING_RAW, "jpeg": tpb.ENCODING_JPEG, "png": tpb.ENCODING_PNG}
FRAMES = prometheus_client.Counter(
    "user_edge_frames_encoded_total", "Camera frames JPEG/PNG-encoded on the edge", ["encoding"]
)
FRAME_BYTES = prometheus_client.Counter(
    "user_edge_frame_bytes_total", "Camera frame bytes before (raw) and after (encoded) edge encoding", ["form"]
)
ENCODE_SECONDS = prometheus_client.Counter(
    "user_edge_encode_seconds_total", "Time spent encoding camera frames (summed over encoder threads)"
)
ACT_FRAME_BYTES = prometheus_client.Counter(
    "user_edge_act_frame_bytes_total",
    "Camera frame bytes of Act requests before (raw) and after (encoded) act_image_encoding",
    ["form"],
)
PENDING = prometheus_client.Gauge("user_edge_encode_pending_steps", "Steps waiting for their frames to be encoded")
SEND_WAITS = prometheus_client.Counter(
    "user_edge_encode_send_waits_total", "send() calls that waited because the encoder was max_pending behind"
)
REUSED = prometheus_client.Counter(
    "user_edge_frames_reused_total", "Step camera frames not encoded again: an Act request had encoded the same frame"
)

Plan = dict[str, tuple[int, int]]  # feature -> (encoding, jpeg quality)


def plan_for(spec: robot_pb2.RobotSpec, image_encoding: Mapping[str, str], jpeg_quality: int, where: str) -> Plan:
    """Which features of a robot to encode: "*" = every uint8 image feature named camera.*, a name = that
    feature ("raw" leaves it raw). ValueError naming `where` for a name the spec lacks or a non-image feature."""
    feats = {f.name: f for f in spec.observation}
    plan: Plan = {}
    default = image_encoding.get("*")
    for name, feat in feats.items():
        enc = image_encoding.get(name, default if name.startswith("camera.") else None)
        if enc is None or ENCODINGS[enc] == tpb.ENCODING_RAW:
            continue
        if feat.dtype != tpb.DTYPE_UINT8 or not wire.is_image_shape(tuple(feat.shape)):
            if name not in image_encoding:
                continue  # "*" skips cameras JPEG/PNG cannot hold
            raise ValueError(f"{where}: {name!r} is not a uint8 (H, W), (H, W, 1) or (H, W, 3) image")
        plan[name] = (ENCODINGS[enc], jpeg_quality)
    unknown = sorted(set(image_encoding) - set(feats) - {"*"})
    if unknown:
        raise ValueError(f"{where}: {unknown} are not observation features of robot {spec.robot_id} {sorted(feats)}")
    return plan


def robot_plans(
    robots: Sequence[RobotConfig], specs: Iterable[robot_pb2.RobotSpec], act: bool = False
) -> dict[str, Plan]:
    """Per robot id, the camera features its config entry encodes: `image_encoding` for its steps, or with
    act=True `act_image_encoding` for its Act requests (None there = as image_encoding, so the policy sees
    frames the way the learner does). Robots with nothing to encode are left out."""
    by_id = {rc.id: (i, rc) for i, rc in enumerate(robots)}
    plans: dict[str, Plan] = {}
    for spec in specs:
        if spec.robot_id not in by_id:
            continue
        i, rc = by_id[spec.robot_id]
        field, encoding = "image_encoding", rc.image_encoding
        if act and rc.act_image_encoding is not None:
            field, encoding = "act_image_encoding", rc.act_image_encoding
        plan = plan_for(spec, encoding, rc.jpeg_quality, f"edge.robots[{i}].{field}") if encoding else {}
        if plan:
            plans[spec.robot_id] = plan
    return plans


class EncodedFrames:
    """Camera frames an Act request has encoded, kept so that the step of the same observation reuses them.

    The edge asks for an action chunk with the observation it then sends to replay as a step: with the same
    plan for both, that frame would be encoded twice. RemotePolicy puts what it encoded here; the FrameEncoder
    takes a frame whose raw bytes, shape, encoding and quality all match (bytes, not object identity: a robot
    may refill one buffer every tick), which is exactly what its own encode would have produced. The last
    `per_feature` frames of each (robot, feature) are kept; thread-safe (Act and steps run on other threads)."""

    def __init__(self, per_feature: int = 2) -> None:
        self.per_feature = per_feature
        self._lock = threading.Lock()
        self._frames: dict[tuple[str, str], deque[tuple[bytes, tuple[int, ...], int, int, bytes]]] = {}

    def put(self, robot_id: str, name: str, frame: np.ndarray, encoding: int, quality: int, data: bytes) -> None:
        entry = (np.ascontiguousarray(frame).tobytes(), tuple(frame.shape), encoding, quality, data)
        with self._lock:
            kept = self._frames.setdefault((robot_id, name), deque(maxlen=self.per_feature))
            kept.append(entry)

    def find(self, robot_id: str, name: str, tensor: tpb.Tensor, encoding: int, quality: int) -> bytes | None:
        """The encoded bytes of this RAW frame if an Act request encoded the same frame the same way, else None."""
        with self._lock:
            kept = list(self._frames.get((robot_id, name), ()))
        shape = tuple(tensor.shape)
        for raw, raw_shape, enc, q, data in reversed(kept):
            if enc == encoding and q == quality and raw_shape == shape and raw == tensor.data:
                return data
        return None


def encode_observation(
    observation: Mapping[str, np.ndarray],
    plan: Plan | None,
    robot_id: str = "",
    frames: EncodedFrames | None = None,
) -> tpb.TensorMap:
    """An observation as a TensorMap, the planned camera frames JPEG/PNG-encoded (counted), the rest raw.
    With `frames`, each encoded frame is kept there for the step of the same observation (robot_id's)."""
    if not plan:
        return wire.to_tensor_map(observation)
    out = tpb.TensorMap()
    for name, arr in observation.items():
        enc, quality = plan.get(name, (tpb.ENCODING_RAW, wire.DEFAULT_JPEG_QUALITY))
        tensor = wire.to_tensor(arr, enc, jpeg_quality=quality)
        if enc != tpb.ENCODING_RAW:
            ACT_FRAME_BYTES.labels("raw").inc(arr.nbytes)
            ACT_FRAME_BYTES.labels("encoded").inc(len(tensor.data))
            if frames is not None:
                frames.put(robot_id, name, np.asarray(arr), enc, quality, tensor.data)
        out.tensors[name].CopyFrom(tensor)
    return out


def _encode(tensor: tpb.Tensor, encoding: int, quality: int) -> tuple[bytes, float]:
    """(encoded bytes, seconds) of a RAW uint8 image tensor, read in place (no copy of the frame)."""
    started = time.perf_counter()
    frame = np.frombuffer(tensor.data, np.uint8).reshape(tuple(tensor.shape))
    return wire.encode_image(frame, encoding, quality), time.perf_counter() - started


class FrameEncoder:
    """A StepSink in front of the sender: encodes the planned camera frames of each robot's steps off the
    control loop, then sender.send() in send order. Robots without a plan go straight through."""

    def __init__(
        self,
        sender: object,
        plans: Mapping[str, Plan],
        threads: int = 2,
        max_pending: int = 64,
        frames: EncodedFrames | None = None,
    ) -> None:
        self.sender = sender  # a ReplaySender (not owned: closed by whoever made it)
        self.plans = {rid: plan for rid, plan in plans.items() if plan}
        self.frames = frames  # frames Act requests encoded, reused where a step holds the same one
        self.max_pending = max_pending
        self._queue: deque[tuple[step_pb2.Step, str]] = deque()
        self._busy = 0  # steps taken from the queue, not yet handed to the sender
        self._cond = threading.Condition()
        self._stopping = False
        self.encoded = self.waits = self.reused = 0
        self.encode_s = 0.0
        self.raw_bytes = self.encoded_bytes = 0
        self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="edge-encode") if threads > 1 else None
        self._thread = threading.Thread(target=self._run, name="edge-encoder", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the StepSink the robot loops see

    def send(self, step: step_pb2.Step, table: str = "") -> int:
        """Queue the step (its frames raw) and return at once; 0: its outbox seq is not known yet. Steps of robots
        without a plan go to the sender directly (their seq is returned)."""
        if step.robot_id not in self.plans:
            return self.sender.send(step, table)  # type: ignore[attr-defined,no-any-return]
        with self._cond:
            if len(self._queue) >= self.max_pending and not self._stopping:
                self.waits += 1
                SEND_WAITS.inc()
                while len(self._queue) >= self.max_pending and not self._stopping:
                    self._cond.wait(0.1)
            self._queue.append((step, table))
            PENDING.set(len(self._queue) + self._busy)
            self._cond.notify_all()
        return 0

    @property
    def pending(self) -> int:
        with self._cond:
            return len(self._queue) + self._busy

    @property
    def unacked(self) -> int:
        return self.pending + self.sender.unacked  # type: ignore[attr-defined,no-any-return]

    @property
    def accepting(self) -> bool:
        return bool(getattr(self.sender, "accepting", True))

    def flush(self, timeout: float) -> bool:
        """Wait until every queued step is encoded and in the sender's outbox; False on timeout."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._queue or self._busy:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.1))
        return True

    def close(self, timeout: float = 10.0) -> None:
        """Encode and hand over what is queued (bounded by timeout), then stop the threads."""
        if not self.flush(timeout):
            log.warning("edge encoder closed with steps still queued", extra=kv(pending=self.pending))
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        self._thread.join(timeout=5.0)
        if self._pool is not None:
            self._pool.shutdown(wait=True)

    # ------------------------------------------------------------------ the encoder thread

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stopping:
                    self._cond.wait()
                if not self._queue:
                    return
                batch = list(self._queue)
                self._queue.clear()
                self._busy = len(batch)
                self._cond.notify_all()  # send() may be waiting for room
            try:
                self._encode_batch(batch)
            except Exception:  # never lose a step: what could not be encoded goes raw (replay accepts both)
                log.exception("edge frame encoding failed; sending the batch's frames raw where not encoded")
            for step, table in batch:
                self.sender.send(step, table)  # type: ignore[attr-defined]
            with self._cond:
                self._busy = 0
                PENDING.set(len(self._queue))
                self._cond.notify_all()

    def _count_bytes(self, raw: int, encoded: int) -> None:
        self.raw_bytes += raw
        self.encoded_bytes += encoded
        FRAME_BYTES.labels("raw").inc(raw)
        FRAME_BYTES.labels("encoded").inc(encoded)

    def _reuse(self, robot_id: str, name: str, tensor: tpb.Tensor, encoding: int, quality: int) -> bool:
        """Put the bytes an Act request already encoded for this frame into the step; False if there are none."""
        data = self.frames.find(robot_id, name, tensor, encoding, quality) if self.frames is not None else None
        if data is None:
            return False
        self.reused += 1
        REUSED.inc()
        self._count_bytes(len(tensor.data), len(data))
        tensor.data = data
        tensor.encoding = encoding
        return True

    def _encode_batch(self, batch: list[tuple[step_pb2.Step, str]]) -> None:
        """Every planned frame of the batch encoded (on the pool when it has one), then written into its step
        by this thread alone (protobuf messages are not mutated from several threads)."""
        jobs: list[tuple[tpb.Tensor, int, int]] = []
        for step, _table in batch:
            plan = self.plans[step.robot_id]
            parts = [step.observation] + ([step.final_observation] if step.HasField("final_observation") else [])
            for part in parts:
                for name, (enc, quality) in plan.items():
                    tensor = part.tensors.get(name)
                    if tensor is None or tensor.encoding != tpb.ENCODING_RAW or tensor.dtype != tpb.DTYPE_UINT8:
                        continue
                    if not self._reuse(step.robot_id, name, tensor, enc, quality):
                        jobs.append((tensor, enc, quality))
        if self._pool is not None and len(jobs) > 1:
            results = list(self._pool.map(lambda job: _encode(*job), jobs))
        else:
            results = [_encode(*job) for job in jobs]
        for (tensor, enc, _q), (data, seconds) in zip(jobs, results, strict=True):
            self._count_bytes(len(tensor.data), len(data))
            self.encode_s += seconds
            FRAMES.labels("jpeg" if enc == tpb.ENCODING_JPEG else "png").inc()
            ENCODE_SECONDS.inc(seconds)
            tensor.data = data
            tensor.encoding = enc
        self.encoded += len(jobs)
