"""Versioned weight sets on the wire: pack once, stream to many, reassemble and verify.

A weight set travels as one WeightHeader (manifest: name, dtype, shape, offset, nbytes per tensor,
a checksum of the raw payload) followed by WeightChunks of the (optionally zstd) payload. The payload is
the tensors' raw little-endian bytes concatenated; nothing is pickled, so a receiver only trusts
dtype + shape + bytes after checking sizes and the checksum.

Server side: `WeightStore` (latest packed version, waiters) + `WeightServicer` (SubscribeWeights).
Client side: `WeightSubscriber` (background thread, reconnects, only asks for newer versions).
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import grpc
import numpy as np
import prometheus_client
import xxhash

from user import rpc
from user.config import AuthConfig
from user.log import kv
from user.v1 import learner_pb2, learner_pb2_grpc
from user.v1 import tensor_pb2 as tpb
from user.wire import WireError, dtype_from_proto, dtype_to_proto

log = logging.getLogger(__name__)

ENCODING_RAW = tpb.ENCODING_RAW
ENCODING_ZSTD = tpb.ENCODING_ZSTD
DEFAULT_CHUNK_BYTES = 1 << 20
MIN_CHUNK_BYTES = 1024
MAX_CHUNK_BYTES = 16 << 20
MAX_WEIGHT_BYTES = 1 << 30  # refuse manifests that would make us allocate more than this
# xxh3-128 hashes ~30 GB/s, sha256 ~2 GB/s here: on a 40 MiB model sha256 cost 22 ms on each side.
DEFAULT_DIGEST = learner_pb2.DIGEST_XXH3_128
_HASHERS: dict[int, tuple[Callable[[], Any], int]] = {
    learner_pb2.DIGEST_SHA256: (hashlib.sha256, 32),
    learner_pb2.DIGEST_XXH3_128: (xxhash.xxh3_128, 16),
}

WEIGHTS_RECEIVED = prometheus_client.Counter("user_weights_received_total", "Weight versions received and applied")
WEIGHTS_BYTES = prometheus_client.Counter("user_weights_bytes_total", "Weight payload bytes received (as encoded)")
WEIGHTS_VERSION = prometheus_client.Gauge("user_weights_version", "Last applied weight version")
WEIGHTS_APPLY = prometheus_client.Histogram(
    "user_weights_apply_seconds",
    "Time to apply a received weight set (on_weights callback)",
    buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1, 5),
)
WEIGHTS_SENT = prometheus_client.Counter("user_weights_sent_total", "Weight versions streamed to subscribers")
WEIGHTS_SUBSCRIBERS = prometheus_client.Gauge("user_weights_subscribers", "Open SubscribeWeights streams")


@dataclass
class WeightSet:
    version: int
    policy: learner_pb2.PolicySpec
    tensors: dict[str, np.ndarray]
    learner_updates: int = 0


@dataclass
class PackedWeights:
    """A weight set ready to stream: the header and the (encoded) payload, built once per version."""

    header: learner_pb2.WeightHeader
    payload: bytes | np.ndarray  # 1-D uint8 when raw; never mutated once packed
    _chunk_cache: dict[int, list[learner_pb2.WeightMessage]] = field(default_factory=dict, repr=False)

    @property
    def version(self) -> int:
        return self.header.version

    @property
    def nbytes(self) -> int:
        """Raw (decoded) payload size."""
        return self.header.total_bytes


# --------------------------------------------------------------------------- pack / stream


def pack_weights(
    version: int,
    policy: learner_pb2.PolicySpec,
    tensors: Mapping[str, np.ndarray],
    learner_updates: int = 0,
    encoding: int = ENCODING_RAW,
    digest: int = DEFAULT_DIGEST,
) -> PackedWeights:
    if version <= 0:
        raise ValueError("weight versions start at 1")
    if encoding not in (ENCODING_RAW, ENCODING_ZSTD):
        raise ValueError(f"unsupported weight encoding {encoding}")
    if digest not in _HASHERS:
        raise ValueError(f"unsupported weight digest {digest}")
    header = learner_pb2.WeightHeader(
        version=version, policy=policy, encoding=encoding, learner_updates=learner_updates, digest_kind=digest
    )
    arrays: list[np.ndarray] = []
    offset = 0
    for name, value in tensors.items():
        arr = np.asarray(value)
        code = dtype_to_proto(arr.dtype)
        arr = np.asarray(arr, dtype=dtype_from_proto(code))  # little-endian, as the wire says
        header.tensors.add(name=name, dtype=code, shape=list(arr.shape), offset=offset, nbytes=arr.nbytes)
        arrays.append(arr)
        offset += arr.nbytes
    # One copy of each tensor straight into a numpy buffer: numpy maps big buffers with huge pages,
    # where a fresh 40 MB bytes/bytearray spends ~20 ms in page faults (tobytes + join paid it twice).
    raw_payload = np.empty(offset, dtype=np.uint8)
    for info, arr in zip(header.tensors, arrays, strict=True):
        raw_payload[info.offset : info.offset + info.nbytes].view(arr.dtype)[...] = arr.reshape(-1)
    header.total_bytes = offset
    header.digest = _HASHERS[digest][0](raw_payload).digest()
    if encoding == ENCODING_ZSTD:
        import zstandard

        payload = zstandard.ZstdCompressor(level=3).compress(raw_payload)
    else:
        payload = raw_payload
    header.encoded_bytes = len(payload)
    header.created_at_ns = time.time_ns()
    return PackedWeights(header, payload)


def iter_weight_messages(
    packed: PackedWeights, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> Iterator[learner_pb2.WeightMessage]:
    """Header, then the payload in chunks of at most max_chunk_bytes (messages cached per chunk size)."""
    if max_chunk_bytes <= 0:
        raise ValueError("max_chunk_bytes must be positive")
    msgs = packed._chunk_cache.get(max_chunk_bytes)
    if msgs is None:
        msgs = [learner_pb2.WeightMessage(header=packed.header)]
        view = memoryview(packed.payload).cast("B")
        for start in range(0, len(view), max_chunk_bytes):
            chunk = learner_pb2.WeightChunk(
                version=packed.version, offset=start, data=bytes(view[start : start + max_chunk_bytes])
            )
            msgs.append(learner_pb2.WeightMessage(chunk=chunk))
        # A few chunk sizes at most in practice; caching keeps many subscribers from re-slicing.
        if len(packed._chunk_cache) < 4:
            packed._chunk_cache[max_chunk_bytes] = msgs
    yield from msgs


# --------------------------------------------------------------------------- reassembly


def _check_header(h: learner_pb2.WeightHeader) -> None:
    if h.version == 0:
        raise WireError("weight header: version 0 is not a weight version")
    if h.encoding not in (ENCODING_RAW, ENCODING_ZSTD):
        raise WireError(f"weight header: unsupported encoding {h.encoding}")
    if h.total_bytes > MAX_WEIGHT_BYTES or h.encoded_bytes > MAX_WEIGHT_BYTES:
        raise WireError(
            f"weight header: payload of {max(h.total_bytes, h.encoded_bytes)} bytes exceeds {MAX_WEIGHT_BYTES}"
        )
    if h.encoding == ENCODING_RAW and h.encoded_bytes != h.total_bytes:
        raise WireError(
            f"weight header: raw payload with encoded_bytes {h.encoded_bytes} != total_bytes {h.total_bytes}"
        )
    if h.digest_kind not in _HASHERS:
        raise WireError(f"weight header: unsupported digest kind {h.digest_kind}")
    want = _HASHERS[h.digest_kind][1]
    if len(h.digest) != want:
        name = learner_pb2.Digest.Name(h.digest_kind)
        raise WireError(f"weight header: a {name} digest is {want} bytes, got {len(h.digest)}")
    names: set[str] = set()
    for info in h.tensors:
        if not info.name or info.name in names:
            raise WireError(f"weight header: empty or duplicate tensor name {info.name!r}")
        names.add(info.name)
        dtype = dtype_from_proto(info.dtype)
        if any(d < 0 for d in info.shape):
            raise WireError(f"weight header: {info.name} has a negative dimension {list(info.shape)}")
        need = math.prod(info.shape) * dtype.itemsize
        if info.nbytes != need:
            raise WireError(
                f"weight header: {info.name} declares {info.nbytes} bytes, {dtype} x {list(info.shape)} needs {need}"
            )
        if info.offset + info.nbytes > h.total_bytes:
            raise WireError(
                f"weight header: {info.name} [{info.offset}, +{info.nbytes}) exceeds payload of {h.total_bytes}"
            )


_EMPTY = np.empty(0, dtype=np.uint8)


class WeightAssembler:
    """Feed WeightMessages in stream order; returns a verified WeightSet when one is complete.

    Any inconsistency raises WireError; the assembler then resets, so the caller should drop the stream.
    """

    def __init__(self) -> None:
        self._header: learner_pb2.WeightHeader | None = None
        self._buf = _EMPTY
        self._filled = 0
        self._hash: Any = None  # running digest of raw payloads, updated as chunks arrive

    @property
    def in_progress(self) -> bool:
        return self._header is not None

    def reset(self) -> None:
        self._header, self._buf, self._filled, self._hash = None, _EMPTY, 0, None

    def feed(self, msg: learner_pb2.WeightMessage) -> WeightSet | None:
        try:
            kind = msg.WhichOneof("msg")
            if kind == "header":
                return self._on_header(msg.header)
            if kind == "chunk":
                return self._on_chunk(msg.chunk)
            raise WireError("empty weight message")
        except WireError:
            self.reset()
            raise

    def _on_header(self, header: learner_pb2.WeightHeader) -> WeightSet | None:
        if self._header is not None:
            raise WireError(f"weight header v{header.version} before v{self._header.version} was complete")
        _check_header(header)
        self._header = header
        # Preallocated (the header passed the size limit): one copy per chunk, no regrowth; numpy for
        # huge pages (see pack_weights).
        self._buf, self._filled = np.empty(header.encoded_bytes, dtype=np.uint8), 0
        self._hash = _HASHERS[header.digest_kind][0]() if header.encoding == ENCODING_RAW else None
        return self._finish() if header.encoded_bytes == 0 else None

    def _on_chunk(self, chunk: learner_pb2.WeightChunk) -> WeightSet | None:
        h = self._header
        if h is None:
            raise WireError("weight chunk without a header")
        if chunk.version != h.version:
            raise WireError(f"weight chunk of v{chunk.version} inside v{h.version}")
        start, data = self._filled, chunk.data
        if chunk.offset != start:
            raise WireError(f"weight chunk at offset {chunk.offset}, expected {start}")
        if not data:
            raise WireError("empty weight chunk")
        if start + len(data) > h.encoded_bytes:
            raise WireError(f"weight chunks exceed the declared {h.encoded_bytes} encoded bytes")
        self._buf[start : start + len(data)] = np.frombuffer(data, dtype=np.uint8)
        self._filled += len(data)
        if self._hash is not None:
            self._hash.update(data)
        return self._finish() if self._filled == h.encoded_bytes else None

    def _finish(self) -> WeightSet:
        h = self._header
        assert h is not None
        raw = self._decode(h, self._buf)  # the buffer is handed over, not copied: reset() starts a new one
        digest = self._hash.digest() if self._hash is not None else _HASHERS[h.digest_kind][0](raw).digest()
        if digest != h.digest:
            raise WireError(f"weight v{h.version}: {learner_pb2.Digest.Name(h.digest_kind)} mismatch")
        tensors = {}
        for info in h.tensors:
            dtype = dtype_from_proto(info.dtype)
            arr = raw[info.offset : info.offset + info.nbytes].view(dtype).reshape(tuple(info.shape))
            # Views into the payload when usable as is (writable, aligned, native order); else a copy.
            if not (arr.flags.aligned and arr.flags.writeable and arr.dtype.isnative):
                arr = arr.astype(dtype.newbyteorder("="), copy=True)
            tensors[info.name] = arr
        out = WeightSet(int(h.version), h.policy, tensors, int(h.learner_updates))
        self.reset()
        return out

    @staticmethod
    def _decode(h: learner_pb2.WeightHeader, data: np.ndarray) -> np.ndarray:
        if h.encoding == ENCODING_RAW:
            return data
        import zstandard

        try:
            raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=h.total_bytes)
        except zstandard.ZstdError as exc:
            raise WireError(f"weight v{h.version}: bad zstd payload: {exc}") from exc
        if len(raw) != h.total_bytes:
            raise WireError(f"weight v{h.version}: decoded {len(raw)} bytes, header says {h.total_bytes}")
        out = np.empty(len(raw), dtype=np.uint8)  # writable, so tensors can be views
        out[:] = np.frombuffer(raw, dtype=np.uint8)
        return out


# --------------------------------------------------------------------------- server side


class WeightStore:
    """The latest packed weight set per experiment and the streams waiting for a newer one (thread-safe).

    Each experiment has its own version sequence. Experiment "" means the first one published, and a
    publisher that names none serves every subscriber: single-experiment clients keep working.
    """

    def __init__(self, encoding: int = ENCODING_RAW) -> None:
        self.encoding = encoding
        self._cond = threading.Condition()
        self._latest: dict[str, PackedWeights] = {}
        self._default = ""
        self._closed = False

    def publish(
        self,
        version: int,
        policy: learner_pb2.PolicySpec,
        tensors: Mapping[str, np.ndarray],
        learner_updates: int = 0,
        experiment: str = "",
    ) -> PackedWeights:
        packed = pack_weights(version, policy, tensors, learner_updates, self.encoding)  # outside the lock
        self.publish_packed(packed, experiment)
        return packed

    def publish_packed(self, packed: PackedWeights, experiment: str = "") -> None:
        with self._cond:
            if not self._latest:
                self._default = experiment
            key = self._key(experiment)
            latest = self._latest.get(key)
            if latest is not None and packed.version <= latest.version:
                raise ValueError(f"weight version {packed.version} is not newer than {latest.version}")
            self._latest[key] = packed
            self._cond.notify_all()

    def latest(self, experiment: str = "") -> PackedWeights | None:
        with self._cond:
            return self._latest.get(self._key(experiment))

    def _key(self, experiment: str) -> str:
        if experiment in self._latest or not self._latest:
            return experiment
        if experiment == "" or set(self._latest) == {""}:
            return self._default
        return experiment

    def experiments(self) -> list[str]:
        with self._cond:
            return sorted(self._latest)

    @property
    def version(self) -> int:
        latest = self.latest()
        return latest.version if latest else 0

    def wait_newer(self, have_version: int, timeout: float | None, experiment: str = "") -> PackedWeights | None:
        """The latest set if it is newer than have_version (waiting up to timeout); None on timeout/close."""
        with self._cond:
            self._cond.wait_for(lambda: self._closed or self._newer(have_version, experiment), timeout)
            return (
                self._latest.get(self._key(experiment))
                if self._newer(have_version, experiment) and not self._closed
                else None
            )

    def _newer(self, have_version: int, experiment: str = "") -> bool:
        latest = self._latest.get(self._key(experiment))
        return latest is not None and latest.version > have_version

    def wake(self) -> None:
        """Wake waiters so they re-check their stream (e.g. a client went away)."""
        with self._cond:
            self._cond.notify_all()

    def close(self) -> None:
        """Shutdown: every open stream ends cleanly; clients reconnect elsewhere or later."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed


class WeightServicer(learner_pb2_grpc.LearnerServicer):
    """SubscribeWeights over a WeightStore; subclass it to add GetStatus."""

    def __init__(self, store: WeightStore, default_chunk_bytes: int = DEFAULT_CHUNK_BYTES, poll_s: float = 1.0) -> None:
        self.store = store
        self.default_chunk_bytes = default_chunk_bytes
        self.poll_s = poll_s
        self._lock = threading.Lock()
        self._subscribers = 0

    @property
    def subscribers(self) -> int:
        with self._lock:
            return self._subscribers

    def _add_subscriber(self, delta: int) -> None:
        with self._lock:
            self._subscribers += delta
        WEIGHTS_SUBSCRIBERS.inc(delta)

    def SubscribeWeights(
        self, request: learner_pb2.SubscribeWeightsRequest, context: grpc.ServicerContext
    ) -> Iterator[learner_pb2.WeightMessage]:
        chunk_bytes = request.max_chunk_bytes or self.default_chunk_bytes
        if not MIN_CHUNK_BYTES <= chunk_bytes <= MAX_CHUNK_BYTES:
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"max_chunk_bytes must be 0 (default) or in [{MIN_CHUNK_BYTES}, {MAX_CHUNK_BYTES}], got {chunk_bytes}",
            )
        have = request.have_version
        context.add_callback(self.store.wake)  # a client going away wakes its waiting stream promptly
        self._add_subscriber(1)
        log.info("weight subscriber joined", extra=kv(client_id=request.client_id, have_version=have))
        try:
            while context.is_active() and not self.store.closed:
                packed = self.store.wait_newer(have, self.poll_s, request.experiment)
                if packed is None:
                    continue
                yield from iter_weight_messages(packed, chunk_bytes)
                have = packed.version
                WEIGHTS_SENT.inc()
        finally:
            self._add_subscriber(-1)
            log.info("weight subscriber left", extra=kv(client_id=request.client_id, have_version=have))


# --------------------------------------------------------------------------- client side


class WeightSubscriber:
    """Keeps a local copy of the learner's weights: a thread streams SubscribeWeights and calls
    on_weights(WeightSet) for each new version; on any error it reconnects with backoff and asks
    only for versions newer than the last applied one."""

    def __init__(
        self,
        addr: str,
        auth: AuthConfig,
        client_id: str,
        on_weights: Callable[[WeightSet], None],
        max_chunk_bytes: int = 0,
        have_version: int = 0,
        experiment: str = "",
    ) -> None:
        self.addr, self.auth, self.client_id = addr, auth, client_id
        self.experiment = experiment
        self.on_weights = on_weights
        self.max_chunk_bytes = max_chunk_bytes
        self._version = have_version
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._call: grpc.Future | None = None
        self._thread: threading.Thread | None = None
        self.connects = 0  # streams opened (first connect + reconnects)

    @property
    def version(self) -> int:
        with self._cond:
            return self._version

    def start(self) -> WeightSubscriber:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"weights-{self.client_id}", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        call = self._call
        if call is not None:
            call.cancel()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def wait_version(self, min_version: int, timeout: float) -> bool:
        """Block until a version >= min_version has been applied (False on timeout)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._version >= min_version, timeout)

    def _run(self) -> None:
        backoff = rpc.Backoff(initial_s=0.1, max_s=5.0)
        while not self._stop.is_set():
            try:
                if self._stream_once():
                    backoff.reset()
            except grpc.RpcError as err:
                if self._stop.is_set():
                    break
                log.warning(
                    "weight stream failed", extra=kv(addr=self.addr, code=str(err.code()), version=self.version)
                )
            except WireError as exc:
                log.error("bad weight stream, reconnecting", extra=kv(addr=self.addr, error=str(exc)))
            if not backoff.sleep(self._stop):
                break

    def _stream_once(self) -> bool:
        """One SubscribeWeights stream until it ends; True if it delivered at least one version."""
        got_any = False
        with rpc.make_channel(self.addr, self.auth) as channel:
            stub = learner_pb2_grpc.LearnerStub(channel)
            request = learner_pb2.SubscribeWeightsRequest(
                client_id=self.client_id,
                have_version=self.version,
                max_chunk_bytes=self.max_chunk_bytes,
                experiment=self.experiment,
            )
            self._call = call = stub.SubscribeWeights(request)
            self.connects += 1
            if self._stop.is_set():  # stop() may have run before the call existed
                call.cancel()
            assembler = WeightAssembler()
            try:
                for msg in call:
                    if msg.HasField("chunk"):
                        WEIGHTS_BYTES.inc(len(msg.chunk.data))
                    weights = assembler.feed(msg)
                    if weights is not None and self._apply(weights):
                        got_any = True
            finally:
                self._call = None
                call.cancel()
        return got_any

    def _apply(self, weights: WeightSet) -> bool:
        if weights.version <= self.version:
            return False  # a server that ignored have_version; nothing newer here
        start = time.perf_counter()
        try:
            self.on_weights(weights)
        except Exception:
            log.exception("on_weights failed; keeping the previous version", extra=kv(version=weights.version))
            return False
        WEIGHTS_APPLY.observe(time.perf_counter() - start)
        WEIGHTS_RECEIVED.inc()
        WEIGHTS_VERSION.set(weights.version)
        with self._cond:
            self._version = weights.version
            self._cond.notify_all()
        log.info("weights applied", extra=kv(version=weights.version, updates=weights.learner_updates))
        return True
