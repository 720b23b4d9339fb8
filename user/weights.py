"""Versioned weight streams, learner -> subscribers: encoded once per (version, encoding, base), adapted per link.

Server side: `WeightStore` keeps the last few published versions per experiment (raw, as published)
and a cache of their encodings, each built once by whichever stream asks first and shared by every
stream that wants the same (version, encoding, base, tensor selection). `WeightServicer` serves
  - StreamWeights (bidi, acked): each version is sent, then acked (applied / rejected) before the next;
    from the acks the server measures the link (effective goodput, round trip), knows the base the
    client holds for deltas and the version it acts with (staleness, sync latency), and picks the
    encoding per subscriber to meet a freshness target. Latest wins: versions published while one is
    in flight are skipped. A slow subscriber holds only its own stream: gRPC flow control bounds what
    is buffered for it, and nothing waits for it on the learner.
  - SubscribeWeights (server streaming, unacked): full sets only, as before.
Client side: `WeightSubscriber` (background thread, reconnects, acks, keeps its last payload as the
base for deltas; a rejected version is acked as such and the server resends a full set).
The codec (manifest, encodings, assembler) lives in user.weight_codec.
"""

from __future__ import annotations

import hmac
import logging
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc
import numpy as np
import prometheus_client

from user import rpc
from user.config import AuthConfig
from user.log import RoutineLog, kv
from user.v1 import learner_pb2, learner_pb2_grpc
from user.v1 import tensor_pb2 as tpb
from user.weight_codec import (
    CODECS,
    DEFAULT_CHUNK_BYTES,
    DEFAULT_DIGEST,
    ENCODING_RAW,
    ENCODING_ZSTD,
    FULL_OF,
    MAX_CHUNK_BYTES,
    MAX_WEIGHT_BYTES,
    MIN_CHUNK_BYTES,
    PATCH_FAST_LEVEL,
    WE,
    ZSTD_LEVEL,
    BufferPool,
    PackedWeights,
    PatchError,
    RawChunk,
    StreamedPatch,
    WeightAssembler,
    WeightSet,
    WirePayload,
    encode,
    encode_patch,
    encode_patch_stream,
    encoding_name,
    iter_weight_frames,
    iter_weight_messages,
    pack_weights,
    parse_weight_message,
    patch_body_bytes,
    patch_header,
    selected,
    serialize_weight_message,
    wire_payload,
)
from user.weight_shm import SHM_FALLBACK, ShmWeights, host_id, read_probe
from user.wire import WireError

__all__ = [
    "DEFAULT_CHUNK_BYTES",
    "DEFAULT_DIGEST",
    "ENCODING_RAW",
    "ENCODING_ZSTD",
    "MAX_CHUNK_BYTES",
    "MAX_WEIGHT_BYTES",
    "MIN_CHUNK_BYTES",
    "PackedWeights",
    "WeightAssembler",
    "WeightServicer",
    "WeightSet",
    "WeightStore",
    "WeightSubscriber",
    "iter_weight_messages",
    "pack_weights",
]

log = logging.getLogger(__name__)

DEFAULT_FRESHNESS_S = 1.0
DEFAULT_HISTORY = 4
# A link that applied this many patches in a row gets an exact set next. The error is bounded per patch
# anyway (each is taken against what the subscriber holds); the resync makes it bit-exact again, e.g.
# for evaluation at a known version. At publish_every = 100 updates: one exact set per 3,200 updates.
DEFAULT_KEYFRAME_EVERY = 32
# Above this measured goodput a streamed patch goes out stored (int8 values, not zstd-compressed):
# compressing a body saves ~half its bytes at ~2 ms per MiB plus ~1 ms to decompress, which pays
# only below ~150 MB/s (measured on loopback, docs/notes/weights.md).
FAST_LINK_BPS = 100e6
# What the adaptive choice sends as a patch: streamed (encode, transfer and apply overlap). The one-shot
# FP32_PATCH_ZSTD stays for subscribers that pin it.
PATCH = WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD
SHM = WE.WEIGHT_ENCODING_FP32_SHM
PROBE_TIMEOUT_S = 10.0  # a same-host subscriber answers the shared-memory probe at once; else: the stream
SHM_MAX_FAILURES = 3  # shared-memory versions rejected in a row before a link streams for good

WEIGHTS_RECEIVED = prometheus_client.Counter("user_weights_received_total", "Weight versions received and applied")
WEIGHTS_BYTES = prometheus_client.Counter("user_weights_bytes_total", "Weight payload bytes received (as encoded)")
WEIGHTS_VERSION = prometheus_client.Gauge("user_weights_version", "Last applied weight version")
WEIGHTS_APPLY = prometheus_client.Histogram(
    "user_weights_apply_seconds",
    "Time to apply a received weight set (on_weights callback)",
    buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1, 5),
)
WEIGHTS_REJECTED = prometheus_client.Counter(
    "user_weights_rejected_total", "Weight versions rejected by this client (corrupt, unknown base); re-fetched"
)
WEIGHTS_SENT = prometheus_client.Counter("user_weights_sent_total", "Weight versions streamed to subscribers")
WEIGHTS_SENT_BYTES = prometheus_client.Counter(
    "user_weights_sent_bytes_total", "Encoded weight bytes streamed, by encoding", ["encoding"]
)
WEIGHTS_SUBSCRIBERS = prometheus_client.Gauge("user_weights_subscribers", "Open SubscribeWeights streams")
SYNC_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60)
WEIGHTS_SYNC = prometheus_client.Histogram(
    "user_weights_sync_seconds", "Publish -> applied on a subscriber (acked; learner clock)", buckets=SYNC_BUCKETS
)
# Per-subscriber series, labelled by (client_id, experiment); streams that share both (a client that opened two, or
# two clients named alike) share the series, which shows the worst of them and leaves with the last of them.
SUB_LABELS = ["client_id", "experiment"]
SUB_STALENESS = prometheus_client.Gauge(
    "user_weights_subscriber_staleness",
    "Latest published version - version the subscriber acts with (unacked streams: - version last sent); "
    "the worst of the streams with these labels",
    SUB_LABELS,
)
SUB_SYNC = prometheus_client.Gauge(
    "user_weights_subscriber_sync_seconds",
    "Publish -> applied of the subscriber's last acked version; the worst of the streams with these labels",
    SUB_LABELS,
)
SUB_GOODPUT = prometheus_client.Gauge(
    "user_weights_subscriber_goodput_bytes_per_second",
    "Measured effective goodput of the subscriber's link; the slowest measured of the streams with these labels",
    SUB_LABELS,
)
# Trailing metadata of StreamWeights / SubscribeWeights ending FAILED_PRECONDITION because the subscriber holds a
# version above anything this learner published for the experiment (its versions restarted): the learner's latest.
VERSIONS_RESTARTED_KEY = "user-weights-restarted-at"


# --------------------------------------------------------------------------- server side


class _Once:
    """A value built by the first caller and awaited by the others (fan-out of one encode)."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self.value: Any = None
        self.error: BaseException | None = None


@dataclass
class _EncodingStats:
    """What an encoding has cost lately: encoded/full bytes and encode throughput (for the choice)."""

    ratio: float
    encode_bps: float = 400e6

    def observe(self, ratio: float, full_bytes: int, seconds: float) -> None:
        self.ratio = 0.5 * self.ratio + 0.5 * ratio
        if seconds > 0 and full_bytes > 1 << 16:
            self.encode_bps = 0.5 * self.encode_bps + 0.5 * full_bytes / seconds


_PRIOR_RATIO = {  # measured on SAC actors mid-training (docs/notes/weights.md); replaced as encodes run
    WE.WEIGHT_ENCODING_FP32: 1.0,
    WE.WEIGHT_ENCODING_FP32_ZSTD: 0.93,
    WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD: 0.6,
    WE.WEIGHT_ENCODING_FP16_ZSTD: 0.47,
    WE.WEIGHT_ENCODING_FP16_DELTA_ZSTD: 0.25,
    WE.WEIGHT_ENCODING_BF16_ZSTD: 0.4,
    WE.WEIGHT_ENCODING_BF16_DELTA_ZSTD: 0.15,
    WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD: 0.13,
    PATCH: 0.13,
}


def _log_refused(experiment: str, version: int) -> None:
    log.debug("weights of a removed experiment not published", extra=kv(experiment=experiment, version=version))


class WeightStore:
    """The last `history` published versions per experiment, their shared encodings, and the streams
    waiting for a newer version (thread-safe). publish() packs the raw set on the caller's thread (one
    copy + xxh3); every other encoding is built on a stream's thread, once, and cached.

    Each experiment has its own version sequence. Experiment "" means the first one published, and a
    publisher that names none serves every subscriber: single-experiment clients keep working.
    """

    def __init__(self, encoding: int = ENCODING_RAW, history: int = DEFAULT_HISTORY) -> None:
        self.encoding = encoding  # ZSTD: unacked SubscribeWeights streams get zstd full sets
        self.history = max(1, history)
        self._cond = threading.Condition()
        self._versions: dict[str, OrderedDict[int, PackedWeights]] = {}
        self._default = ""  # the first experiment published: what "" resolves to
        self._cache: dict[tuple[Any, ...], _Once] = {}
        self._cache_lock = threading.Lock()
        self._stats = {enc: _EncodingStats(r) for enc, r in _PRIOR_RATIO.items()}
        # Exact payloads subscribers may hold, by (experiment, digest): fp32 wire payloads of published
        # versions and the states patches lead to. The bases of patches; they leave with their version.
        self._states: dict[tuple[str, bytes], tuple[WirePayload, bool]] = {}  # (state, made by a patch)
        self._state_pool = BufferPool(keep=2)  # buffers of patched states that left: the next ones reuse them
        # Published payloads that left the history: the next publish packs into one of them. A fresh
        # 100 MiB buffer costs up to ~0.4 s of page faults on these machines, more than streaming it.
        self._payload_pool = BufferPool(keep=2)
        self._pool_lock = threading.Lock()  # BufferPool is not thread-safe
        self._body_pool = BufferPool(keep=2)  # uncompressed patch bodies and XORs, reused by the next ones
        self._closed = False
        # Experiments dropped (removed): their streams end NOT_FOUND. A name each, never defined again by control.
        self._gone: set[str] = set()
        self._drop_hooks: list[Callable[[str], None]] = []  # what else holds an experiment's weights (ShmWeights)
        self.publish_log = RoutineLog("weights published")  # the learner's line per version, by experiment

    def publish(
        self,
        version: int,
        policy: learner_pb2.PolicySpec,
        tensors: Mapping[str, np.ndarray],
        learner_updates: int = 0,
        *,
        experiment: str = "",
    ) -> PackedWeights | None:
        """The version packed and served; None for an experiment dropped (removed): a run's thread may still publish
        after the learner dropped it, and that version must not bring it back (control never reuses a name)."""
        if self._refused(experiment, version):  # before packing: no payload buffer (shared-memory file) for it
            return None
        self._make_room(version, experiment)
        packed = pack_weights(  # outside the lock
            version, policy, tensors, learner_updates, experiment=experiment, alloc=self._take_payload_buffer
        )
        return packed if self.publish_packed(packed) else None

    def _refused(self, experiment: str, version: int) -> bool:
        """Whether `experiment` was dropped: its versions are not served again (a DEBUG line each)."""
        with self._cond:
            gone = experiment in self._gone
        if gone:
            _log_refused(experiment, version)
        return gone

    def _make_room(self, version: int, experiment: str) -> None:
        """At capacity, the oldest version leaves before the new one is packed (not after), so the pack
        can reuse its buffer: a fresh 400 MB payload spent ~1.4 s in page faults here, a reused one
        ~0.17 s. The history is one short while packing; the latest version always stays."""
        with self._cond:
            versions = self._versions.get(experiment)
            if not versions or version <= next(reversed(versions)) or len(versions) < max(2, self.history):
                return
            self._evict(experiment, versions, self.history - 1)

    def _evict(self, experiment: str, versions: OrderedDict[int, PackedWeights], keep: int) -> None:
        """Drop all but the newest `keep` versions (caller holds _cond), their encodings and states; their
        payload buffers go to the pool, handed out again once nothing views them."""
        while len(versions) > keep:
            _, gone_packed = versions.popitem(last=False)
            if isinstance(gone_packed.payload, np.ndarray):
                with self._pool_lock:  # reused by a later publish once nothing views it
                    self._payload_pool.give(gone_packed.payload)
        kept = {(experiment, v) for v in versions}
        with self._cache_lock:  # encodings of versions that left the history go with them
            for key in [k for k in self._cache if k[0] == experiment and (k[0], k[1]) not in kept]:
                del self._cache[key]
            gone = [k for k, st in self._states.items() if k[0] == experiment and (k[0], st[0].version) not in kept]
            for key in gone:
                state, patched = self._states.pop(key)
                if patched:
                    with self._pool_lock:
                        self._state_pool.give(state.payload)

    def publish_packed(self, packed: PackedWeights) -> bool:
        """Serve `packed`; False (not served) for a dropped experiment's (see publish)."""
        if packed.header.encoding != ENCODING_RAW:
            raise ValueError("publish raw weight sets; encodings are made per subscriber")
        experiment = packed.header.experiment
        with self._cond:
            if experiment in self._gone:  # dropped, perhaps while publish packed it
                _log_refused(experiment, packed.version)
                return False
            if not self._versions:
                self._default = experiment
            versions = self._versions.setdefault(experiment, OrderedDict())
            if versions and packed.version <= next(reversed(versions)):
                raise ValueError(f"weight version {packed.version} is not newer than {next(reversed(versions))}")
            versions[packed.version] = packed
            self._evict(experiment, versions, self.history)
            self._cond.notify_all()
        return True

    def payload_buffers_from(self, fresh: Callable[[int], np.ndarray | None]) -> None:
        """Pack new payloads into buffers from `fresh` (None from it: ordinary memory), e.g. ShmWeights.buffer,
        so that a same-host subscriber's file is a link to the payload, not a copy of it."""
        with self._pool_lock:
            self._payload_pool.fresh = fresh

    def on_drop(self, hook: Callable[[str], None]) -> None:
        """Call hook(experiment) when an experiment is dropped (e.g. ShmWeights.drop: its files go too)."""
        self._drop_hooks.append(hook)

    def drop(self, experiment: str) -> bool:
        """A removed experiment leaves: its versions, encodings and states go (their payload buffers with the last
        stream that still sends one), streams of it end NOT_FOUND and the on_drop hooks run. Without it they stayed
        until the learner exited (an experiment evicts its versions only when it publishes again). False if no
        version of it was held."""
        with self._cond:
            held = self._versions.pop(experiment, None) is not None
            self._gone.add(experiment)
            self._cond.notify_all()
        with self._cache_lock:
            for key in [k for k in self._cache if k[0] == experiment]:
                del self._cache[key]
            for key in [k for k in self._states if k[0] == experiment]:
                del self._states[key]
        self.publish_log.reset(experiment)
        for hook in list(self._drop_hooks):
            hook(experiment)
        return held

    def dropped(self, experiment: str) -> bool:
        """Whether `experiment` (as a subscriber names it) was dropped (for good: publish refuses its versions)."""
        with self._cond:
            return self._is_gone(experiment)

    def _is_gone(self, experiment: str) -> bool:
        return experiment in self._gone or self._key(experiment) in self._gone

    def _take_payload_buffer(self, nbytes: int) -> np.ndarray:
        with self._pool_lock:
            return self._payload_pool.take(nbytes)

    def _key(self, experiment: str) -> str:
        """Resolve "" to the first experiment published, and any name to "" when the publisher names none."""
        if experiment in self._versions or not self._versions:
            return experiment
        if experiment == "" or set(self._versions) == {""}:
            return self._default
        return experiment

    def latest(self, experiment: str = "") -> PackedWeights | None:
        with self._cond:
            versions = self._versions.get(self._key(experiment))
            return versions[next(reversed(versions))] if versions else None

    def get(self, version: int, experiment: str = "") -> PackedWeights | None:
        """A version still in the history (a delta base), else None."""
        with self._cond:
            return self._versions.get(self._key(experiment), {}).get(version)

    def version_of(self, experiment: str = "") -> int:
        latest = self.latest(experiment)
        return latest.version if latest else 0

    @property
    def version(self) -> int:
        return self.version_of("")

    def experiments(self) -> list[str]:
        with self._cond:
            return sorted(self._versions)

    def wait_newer(
        self, have_version: int, timeout: float | None, experiment: str = "", *, or_older: bool = False
    ) -> PackedWeights | None:
        """The latest set if it is newer than have_version (waiting up to timeout); None on timeout/close.

        or_older: also the latest set if it is older than have_version, i.e. the caller holds a version this store
        never published (the learner's versions restarted below it); only an equal one keeps it waiting."""

        def newer() -> PackedWeights | None:
            versions = self._versions.get(self._key(experiment))
            if self._closed or not versions or self._is_gone(experiment):
                return None
            latest = versions[next(reversed(versions))]
            if latest.version > have_version or (or_older and latest.version < have_version):
                return latest
            return None

        with self._cond:
            self._cond.wait_for(lambda: self._closed or self._is_gone(experiment) or newer() is not None, timeout)
            return newer()

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

    # ------------------------------------------------------------------ shared encodings

    def _once(self, key: tuple[Any, ...], build: Callable[[], Any]) -> Any:
        with self._cache_lock:
            entry = self._cache.get(key)
            owner = entry is None
            if entry is None:
                entry = self._cache[key] = _Once()
        if owner:
            try:
                entry.value = build()
            except BaseException as exc:
                entry.error = exc
                with self._cache_lock:
                    self._cache.pop(key, None)
                raise
            finally:
                entry.done.set()
        entry.done.wait()
        if entry.error is not None:
            raise entry.error
        return entry.value

    def wire(self, full: PackedWeights, wire_dtype: int, prefixes: tuple[str, ...]) -> WirePayload:
        key = (full.header.experiment, full.version, "wire", wire_dtype, prefixes)

        def build() -> WirePayload:
            out = wire_payload(full, wire_dtype, prefixes)
            if wire_dtype == tpb.DTYPE_FLOAT32:
                self._keep_state(full.header.experiment, out, patched=False)
            return out

        return self._once(key, build)

    def _keep_state(self, experiment: str, state: WirePayload, patched: bool) -> None:
        if self.get(state.version, experiment) is None:
            return  # its version left the history (a later publish would drop it anyway)
        with self._cache_lock:
            self._states[(experiment, state.digest)] = (state, patched)

    def state(self, digest: bytes, experiment: str = "") -> WirePayload | None:
        """The exact fp32 payload with this digest, if a subscriber may hold it and it is still kept."""
        found = self._state(digest, experiment)
        return found[0] if found else None

    def is_patched(self, digest: bytes, experiment: str = "") -> bool:
        """Whether the payload with this digest was reached by a patch (not any version's own payload)."""
        found = self._state(digest, experiment)
        return bool(found and found[1])

    def _state(self, digest: bytes, experiment: str) -> tuple[WirePayload, bool] | None:
        if not digest:
            return None
        with self._cond:
            experiment = self._key(experiment)
        with self._cache_lock:
            return self._states.get((experiment, digest))

    def encoded(
        self,
        full: PackedWeights,
        encoding: int,
        prefixes: tuple[str, ...],
        base_version: int = 0,
        base_digest: bytes = b"",
        fast_link: bool = False,
    ) -> PackedWeights | StreamedPatch:
        """`full` in `encoding` (a delta against base_version if nonzero), built once and shared.

        Patches name their base by digest (the exact state the subscriber holds): KeyError if it is no
        longer kept, PatchError if a patch cannot carry this version. fast_link: a streamed patch goes
        out stored (PATCH_FAST_LEVEL), where compressing costs more time than the bytes it saves."""
        experiment = full.header.experiment
        codec = CODECS[encoding]
        fast_link = fast_link and codec.stream
        key = (experiment, full.version, "enc", encoding, prefixes, base_digest if codec.patch else base_version)
        key += ("fast",) if fast_link else ()

        def build() -> PackedWeights | StreamedPatch:
            start = time.perf_counter()
            if codec.stream:
                return self._stream_patch(full, encoding, prefixes, base_digest, fast_link)
            if codec.patch:
                held = self.state(base_digest, experiment)
                if held is None:
                    raise KeyError(base_digest)
                wire = self.wire(full, tpb.DTYPE_FLOAT32, prefixes)
                with self._pool_lock:
                    buf = self._state_pool.take(wire.payload.nbytes)
                    body = self._body_pool.take(patch_body_bytes(wire.tensors))
                out, reached = encode_patch(full, wire, held, buf, body)
                with self._pool_lock:  # the uncompressed body: the next patch encode reuses it
                    self._body_pool.give(body)
                self._keep_state(experiment, reached, patched=True)  # the base of this link's next patch
            else:
                base = None
                if base_version:
                    base_full = self.get(base_version, experiment)
                    if base_full is None:
                        raise KeyError(base_version)
                    base = self.wire(base_full, codec.wire_dtype, prefixes)
                wire = self.wire(full, codec.wire_dtype, prefixes)
                with self._pool_lock:
                    scratch = self._body_pool.take(wire.payload.nbytes) if base is not None else None
                out = encode(full, encoding, wire, base, scratch)
                if scratch is not None:
                    with self._pool_lock:  # XOR scratch: compressed already, the next delta reuses it
                        self._body_pool.give(scratch)
            full_bytes = self.selected_bytes(full, prefixes)
            self._stats[encoding].observe(
                out.encoded_bytes / max(1, full_bytes), full_bytes, time.perf_counter() - start
            )
            return out

        return self._once(key, build)

    def _stream_patch(
        self, full: PackedWeights, encoding: int, prefixes: tuple[str, ...], base_digest: bytes, fast_link: bool
    ) -> StreamedPatch:
        """Start a streamed patch on its own thread and return it at once: every stream that wants it
        sends its pieces as they come, none waits for another subscriber's flow control."""
        experiment = full.header.experiment
        held = self.state(base_digest, experiment)
        if held is None:
            raise KeyError(base_digest)
        wire = self.wire(full, tpb.DTYPE_FLOAT32, prefixes)
        if not held.same_layout(wire.tensors) or held.version >= wire.version:
            raise PatchError("a patch needs an older base of the same layout")
        with self._pool_lock:
            buf = self._state_pool.take(wire.payload.nbytes)
        sink = StreamedPatch(patch_header(full, wire, held))
        full_bytes = self.selected_bytes(full, prefixes)

        def run() -> None:
            start = time.perf_counter()
            try:
                # the reached state is kept before the last chunk goes out: the subscriber's ack may come
                # back at once, naming it as the base of its next patch
                keep = lambda st: self._keep_state(experiment, st, patched=True)  # noqa: E731
                level = PATCH_FAST_LEVEL if fast_link else ZSTD_LEVEL
                encode_patch_stream(full, wire, held, sink, buf, keep, level)
            except PatchError as exc:  # its trailer sends the subscribers back for a full set
                log.warning("no patch for this version", extra=kv(version=full.version, error=str(exc)))
                return
            except Exception:
                log.exception("streamed patch failed; its subscribers get a full set", extra=kv(version=full.version))
                return
            if not fast_link:  # the stats say what a compressed patch costs (slow links' choice)
                ratio = sink.encoded_bytes / max(1, full_bytes)
                self._stats[encoding].observe(ratio, full_bytes, time.perf_counter() - start)

        threading.Thread(target=run, daemon=True, name=f"patch-v{full.version}").start()
        return sink

    def is_cached(self, full: PackedWeights, encoding: int, prefixes: tuple[str, ...], base: int | bytes) -> bool:
        key = (full.header.experiment, full.version, "enc", encoding, prefixes, base)
        with self._cache_lock:
            return key in self._cache

    @staticmethod
    def selected_bytes(full: PackedWeights, prefixes: tuple[str, ...]) -> int:
        return sum(i.nbytes for i in selected(full.header.tensors, prefixes))

    def estimate_s(
        self, full: PackedWeights, encoding: int, prefixes: tuple[str, ...], base: int | bytes, goodput: float
    ) -> float:
        """Expected seconds to get `full` to a subscriber at `goodput` B/s in `encoding` (encode + transfer)."""
        full_bytes = self.selected_bytes(full, prefixes)
        stats = self._stats[encoding]
        encode_s = (
            0.0
            if self.is_cached(full, encoding, prefixes, base) or encoding == WE.WEIGHT_ENCODING_FP32
            else (full_bytes / stats.encode_bps)
        )
        return encode_s + full_bytes * stats.ratio / goodput


@dataclass
class Link:
    """One subscriber's stream as the server sees it (from its request and acks)."""

    client_id: str
    experiment: str
    prefixes: tuple[str, ...]
    allow_lossy: bool
    pinned: int
    freshness_s: float
    acked: bool
    base_version: int = 0  # the payload the client holds for deltas
    base_wire_dtype: int = tpb.DTYPE_FLOAT32
    base_digest: bytes = b""  # its digest, as the client reports it
    base_patched: bool = False  # that payload came from a patch: only a patch or a full set follows it
    patches_in_row: int = 0
    applied_version: int = 0  # as acked: an unacked stream never says, it stays 0
    sent_version: int = 0  # the last version handed whole to the transport
    goodput_bps: float = 0.0  # effective: encoded bytes / (send start -> ack, less the client's apply time)
    # the same, from versions sent whole (not streamed while encoding, which would count encode time):
    # what the link itself moves, for the choice of a streamed patch's compression
    wire_bps: float = 0.0
    rtt_s: float = 0.0
    sync_latency_s: float = 0.0
    encoding: int = 0
    bytes_sent: int = 0
    versions_sent: int = 0
    rejects_in_row: int = 0
    # encoding -> bytes/s the client decodes + applies at (its acks' apply_ns): a delta that saves bytes
    # but costs the client more than it saves on a fast link loses to fp32
    decode_bps: dict[int, float] = field(default_factory=dict)
    shm_host: str = ""  # the host identity the subscriber announced ("" = it reads no shared memory)
    shm: bool = False  # it proved it reads our shared-memory files: versions go there
    shm_skip: bool = False  # its last shared-memory version was rejected: the next goes over the stream
    shm_failures: int = 0  # shared-memory versions rejected in a row
    published_version: Callable[[], int] = field(default=lambda: 0, repr=False)

    @property
    def acting_version(self) -> int:
        """The version the subscriber acts with as far as the server knows: acked, else (unacked streams) at most
        the last one sent. A reader that stopped reading stops the sends once flow control is full: stale."""
        return self.applied_version if self.acked else self.sent_version

    def status(self) -> learner_pb2.SubscriberStatus:
        return learner_pb2.SubscriberStatus(
            client_id=self.client_id,
            experiment=self.experiment,
            applied_version=self.applied_version,
            staleness=max(0, self.published_version() - self.acting_version),
            sync_latency_s=self.sync_latency_s,
            goodput_mbit_s=self.goodput_bps * 8 / 1e6,
            rtt_ms=self.rtt_s * 1e3,
            encoding=self.encoding,
            bytes_sent=self.bytes_sent,
            versions_sent=self.versions_sent,
            acked=self.acked,
            sent_version=self.sent_version,
        )


_SERIES_LOCK = threading.Lock()
_SERIES: dict[tuple[str, str], list[Link]] = {}  # label values -> the open streams that share them


def _series_links(labels: tuple[str, str]) -> list[Link]:
    with _SERIES_LOCK:
        return list(_SERIES.get(labels, ()))


def _series_join(link: Link) -> None:
    """Count the link into its metric series; the first link with these labels creates them. Read at scrape time,
    so a stalled subscriber's staleness grows while nothing is acked."""
    labels = (link.client_id, link.experiment)
    with _SERIES_LOCK:
        links = _SERIES.setdefault(labels, [])
        links.append(link)
        if len(links) > 1:
            return
        SUB_STALENESS.labels(*labels).set_function(
            lambda: max((ln.status().staleness for ln in _series_links(labels)), default=0)
        )
        SUB_SYNC.labels(*labels).set_function(
            lambda: max((ln.sync_latency_s for ln in _series_links(labels)), default=0.0)
        )
        SUB_GOODPUT.labels(*labels).set_function(
            lambda: min((g for ln in _series_links(labels) if (g := ln.goodput_bps) > 0), default=0.0)
        )


def _series_leave(link: Link) -> None:
    """Count the link out; its series go with the last link that has their labels."""
    labels = (link.client_id, link.experiment)
    with _SERIES_LOCK:
        links = _SERIES.get(labels, [])
        links[:] = [ln for ln in links if ln is not link]  # by identity: two links may compare equal
        if links:
            return
        _SERIES.pop(labels, None)
        for gauge in (SUB_STALENESS, SUB_SYNC, SUB_GOODPUT):
            try:
                gauge.remove(*labels)
            except KeyError:
                pass


def choose_encoding(
    store: WeightStore,
    link: Link,
    full: PackedWeights,
    prefixes: tuple[str, ...] | None = None,
    keyframe_every: int = DEFAULT_KEYFRAME_EVERY,
) -> tuple[int, int]:
    """(encoding, base_version) for `full` on this link.

    Pinned encodings are honoured (a delta falls back to its full set where the base is unknown; a
    patch also does every keyframe_every patches: the exact resync). Adaptive: until the link is
    measured, lossless zstd (delta where possible); then the lossless encoding with the least expected
    encode + transfer + client decode time, and a patch (error-bounded, ~13 % of the fp32 bytes mid-training; action
    error measured in the bench) only where the subscriber allows lossy weights, the lossless one would
    miss the freshness target and the patch's base (the exact state the subscriber holds) is kept.
    """

    def base_for(encoding: int) -> int:
        codec = CODECS[encoding]
        if codec.patch:
            held = store.state(link.base_digest, link.experiment)
            ok = held is not None and held.version == link.base_version < full.version
            return link.base_version if ok and link.patches_in_row < keyframe_every else 0
        ok = (
            codec.delta
            and link.base_version
            and not link.base_patched  # the client holds a patched state, not this version's payload
            and link.base_wire_dtype == codec.wire_dtype
            and store.get(link.base_version, link.experiment) is not None
        )
        return link.base_version if ok else 0

    def resolve(encoding: int) -> tuple[int, int]:
        base = base_for(encoding)
        if CODECS[encoding].delta and not base:
            return FULL_OF[encoding], 0
        return encoding, base

    selection = prefixes if prefixes is not None else (link.prefixes or ("",))
    if link.pinned:
        return resolve(link.pinned)
    lossless = [resolve(WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD), (WE.WEIGHT_ENCODING_FP32, 0)]
    if link.goodput_bps <= 0:
        return lossless[0]

    def cost(choice: tuple[int, int]) -> float:
        base: int | bytes = link.base_digest if CODECS[choice[0]].patch else choice[1]
        return store.estimate_s(full, choice[0], selection, base, link.goodput_bps) + decode_s(choice[0])

    def decode_s(encoding: int) -> float:
        """The client's decode + apply, as its acks measured it (0 until measured; a streamed patch's
        decode overlaps its transfer)."""
        bps = link.decode_bps.get(encoding, 0.0)
        return store.selected_bytes(full, selection) / bps if bps > 0 and not CODECS[encoding].stream else 0.0

    best = min(lossless, key=cost)
    if link.allow_lossy and cost(best) > link.freshness_s:
        patch = resolve(PATCH)
        if patch[0] == PATCH and cost(patch) < cost(best):
            return patch
    return best


class WeightServicer(learner_pb2_grpc.LearnerServicer):
    """StreamWeights + SubscribeWeights over a WeightStore; subclass it to add GetStatus."""

    def __init__(
        self,
        store: WeightStore,
        default_chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        poll_s: float = 1.0,
        freshness_s: float = DEFAULT_FRESHNESS_S,
        keyframe_every: int = DEFAULT_KEYFRAME_EVERY,
        shm: ShmWeights | None = None,
    ) -> None:
        """shm: the shared-memory directory for same-host subscribers (None: everything streams); the store's
        payloads are then packed into buffers there."""
        self.store = store
        self.shm = shm
        if shm is not None:
            store.payload_buffers_from(shm.buffer)
            store.on_drop(shm.drop)
        self.default_chunk_bytes = default_chunk_bytes
        self.poll_s = poll_s
        self.freshness_s = freshness_s
        self.keyframe_every = keyframe_every
        self._lock = threading.Lock()
        self._links: dict[int, Link] = {}
        self.frames = False  # set by add_learner_servicer: responses may be serialized chunk frames

    @property
    def subscribers(self) -> int:
        with self._lock:
            return len(self._links)

    def subscriber_status(self) -> list[learner_pb2.SubscriberStatus]:
        with self._lock:
            links = list(self._links.values())
        return [link.status() for link in links]

    # ------------------------------------------------------------------ RPCs

    def SubscribeWeights(
        self, request: learner_pb2.SubscribeWeightsRequest, context: grpc.ServicerContext
    ) -> Iterator[learner_pb2.WeightMessage]:
        link, chunk_bytes = self._open(request, context, acked=False)
        yield from self._serve(link, request.have_version, chunk_bytes, context, None)

    def StreamWeights(
        self, request_iterator: Iterator[learner_pb2.WeightAck], context: grpc.ServicerContext
    ) -> Iterator[learner_pb2.WeightMessage]:
        try:
            first = next(request_iterator)
        except StopIteration:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "StreamWeights: send a subscribe message first")
        if not first.HasField("subscribe"):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "StreamWeights: the first message must carry subscribe")
        link, chunk_bytes = self._open(first.subscribe, context, acked=True)
        acks: queue.Queue[learner_pb2.WeightAck | None] = queue.Queue()

        def read_acks() -> None:
            try:
                for ack in request_iterator:
                    acks.put(ack)
            except grpc.RpcError:
                pass  # the stream ended; the writer side sees it too
            finally:
                acks.put(None)

        threading.Thread(target=read_acks, name=f"weight-acks-{link.client_id}", daemon=True).start()
        yield from self._serve(link, first.subscribe.have_version, chunk_bytes, context, acks)

    def unknown_experiment(self, experiment: str) -> str:
        """Why no weights of `experiment` can ever come from here ("" = they may): a learner says so for a name it
        does not train, so a subscriber's typo is NOT_FOUND at once rather than a stream that never delivers."""
        return ""

    def _removed(self, experiment: str) -> str:
        """Why a dropped experiment's weights never come again ("" = not dropped)."""
        if not self.store.dropped(experiment):
            return ""
        return f"experiment {experiment[:64]!r} was removed: this learner publishes no more weights of it"

    # ------------------------------------------------------------------ one stream

    def _open(
        self, request: learner_pb2.SubscribeWeightsRequest, context: grpc.ServicerContext, acked: bool
    ) -> tuple[Link, int]:
        chunk_bytes = request.max_chunk_bytes or self.default_chunk_bytes
        if not MIN_CHUNK_BYTES <= chunk_bytes <= MAX_CHUNK_BYTES:
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"max_chunk_bytes must be 0 (default) or in [{MIN_CHUNK_BYTES}, {MAX_CHUNK_BYTES}], got {chunk_bytes}",
            )
        if request.encoding and request.encoding not in CODECS:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"unknown weight encoding {request.encoding}")
        if request.encoding and CODECS[request.encoding].shm:  # it needs the probe first: the server's choice
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                "WEIGHT_ENCODING_FP32_SHM cannot be pinned: set shm_host and the learner picks it once the "
                "subscriber proved it reads the learner's shared memory",
            )
        pinned = request.encoding
        if pinned and CODECS[pinned].lossy and not request.allow_lossy:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"{encoding_name(pinned)} is lossy: set allow_lossy")
        if not acked and pinned and CODECS[pinned].delta:
            pinned = FULL_OF[pinned]  # unacked streams cannot know the base
        if not acked and not pinned:
            pinned = WE.WEIGHT_ENCODING_FP32_ZSTD if self.store.encoding == ENCODING_ZSTD else WE.WEIGHT_ENCODING_FP32
        experiment = request.experiment
        unknown = self.unknown_experiment(experiment) or self._removed(experiment)
        if unknown:
            context.abort(grpc.StatusCode.NOT_FOUND, unknown)
        latest = self.store.latest(experiment)
        if latest is not None:  # else checked against the first version published
            self._check_prefixes(tuple(request.prefixes), latest, context)
        link = Link(
            client_id=request.client_id,
            experiment=experiment,
            prefixes=tuple(request.prefixes),
            allow_lossy=request.allow_lossy,
            pinned=pinned,
            freshness_s=request.freshness_target_ms / 1e3 if request.freshness_target_ms else self.freshness_s,
            acked=acked,
            base_version=request.base_version if acked else 0,
            base_digest=request.base_digest if acked else b"",
            base_patched=acked and self.store.is_patched(request.base_digest, experiment),
            shm_host=request.shm_host if acked else "",
            published_version=lambda: self.store.version_of(experiment),
        )
        return link, chunk_bytes

    def _serve(
        self,
        link: Link,
        have: int,
        chunk_bytes: int,
        context: grpc.ServicerContext,
        acks: queue.Queue[learner_pb2.WeightAck | None] | None,
    ) -> Iterator[learner_pb2.WeightMessage]:
        context.add_callback(self.store.wake)  # a client going away wakes its waiting stream promptly
        if acks is not None:
            context.add_callback(lambda: acks.put(None))
        with self._lock:
            self._links[id(link)] = link
        WEIGHTS_SUBSCRIBERS.inc()
        _series_join(link)
        left = rpc.at_stream_end(context, lambda: self._leave(link))  # even if gRPC drops this generator
        log.info("weight subscriber joined", extra=kv(client_id=link.client_id, have_version=have, acked=link.acked))
        # What the subscriber says it holds: this learner must have published it. Versions are monotonic across
        # learner restarts (the high-water mark); one that lost it publishes below, and the subscriber must hear it.
        held = max(have, link.base_version)
        try:
            if acks is not None and link.shm_host and self.shm is not None and self.shm.same_host(link.shm_host):
                yield from self._probe(link, acks, context)
            while context.is_active() and not self.store.closed:
                full = self.store.wait_newer(have, self.poll_s, link.experiment, or_older=True)
                if full is None:
                    if removed := self._removed(link.experiment):  # a clear end, not a stream that never delivers
                        context.abort(grpc.StatusCode.NOT_FOUND, removed)
                    continue
                if full.version < held:
                    self._versions_restarted(link, held, full.version, context)
                self._check_prefixes(link.prefixes, full, context)
                packed = self._encode(link, full)
                start = time.perf_counter()
                yield from (iter_weight_frames if self.frames else iter_weight_messages)(packed, chunk_bytes)
                self._count_sent(link, packed)
                if acks is None:  # nothing says what it applied: its status counts from what was sent
                    have = packed.version
                    continue
                ack = self._wait_ack(acks, packed.version, context)
                if ack is None:
                    return
                if not self._on_ack(link, packed, ack, time.perf_counter() - start):
                    time.sleep(min(2.0, 0.1 * link.rejects_in_row))  # a client rejecting everything: do not spin
                    continue
                have = packed.version
        finally:
            left()

    def _leave(self, link: Link) -> None:
        with self._lock:
            self._links.pop(id(link), None)
        WEIGHTS_SUBSCRIBERS.dec()
        _series_leave(link)
        log.info(
            "weight subscriber left",
            extra=kv(client_id=link.client_id, applied=link.applied_version, sent=link.sent_version),
        )

    def _versions_restarted(self, link: Link, held: int, latest: int, context: grpc.ServicerContext) -> None:
        """End the stream FAILED_PRECONDITION: the subscriber holds `held`, above anything published here (latest
        `latest`), so this learner restarted its numbering; a WeightSubscriber resubscribes from 0 on this."""
        log.warning(
            "weight subscriber holds a version this learner never published: its versions restarted below it",
            extra=kv(client_id=link.client_id, experiment=link.experiment, held=held, latest=latest),
        )
        context.set_trailing_metadata(((VERSIONS_RESTARTED_KEY, str(latest)),))
        context.abort(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"the learner's weight versions restarted below yours: you hold v{held}, its latest for experiment "
            f"{link.experiment!r} is v{latest}; subscribe again with have_version 0 and no base to take its weights",
        )

    @staticmethod
    def _check_prefixes(prefixes: tuple[str, ...], full: PackedWeights, context: grpc.ServicerContext) -> None:
        """INVALID_ARGUMENT if a requested prefix selects no tensor of the published set (it streams empty sets)."""
        names = [info.name for info in full.header.tensors]
        unmatched = [p for p in prefixes if p and not any(name.startswith(p) for name in names)]
        if unmatched:
            shown = ", ".join(names[:20]) + (f", ... ({len(names)} in all)" if len(names) > 20 else "")
            context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"prefixes {unmatched} match no tensor of experiment {full.header.experiment!r}'s weights "
                f"(v{full.version}: {shown})",
            )

    def _probe(
        self, link: Link, acks: queue.Queue[learner_pb2.WeightAck | None], context: grpc.ServicerContext
    ) -> Iterator[learner_pb2.WeightMessage]:
        """Same host by its word: prove it. The subscriber must read back a nonce file we write to our
        shared-memory directory (same filesystem, same user); only then do versions go there."""
        assert self.shm is not None
        try:
            name, nonce = self.shm.new_probe()
        except OSError as exc:
            log.warning("shared-memory probe not written; streaming", extra=kv(error=str(exc)))
            return
        try:
            yield learner_pb2.WeightMessage(shm_probe=learner_pb2.WeightShmProbe(name=name))
            ack = self._wait_ack(acks, 0, context, time.monotonic() + PROBE_TIMEOUT_S)
            link.shm = ack is not None and hmac.compare_digest(ack.shm_proof, nonce)
        finally:
            self.shm.end_probe(name)
        log.info("weight subscriber shared memory", extra=kv(client_id=link.client_id, shm=link.shm))

    def _shm_set(self, full: PackedWeights, prefixes: tuple[str, ...]) -> PackedWeights | None:
        """The version as an FP32_SHM header naming its file (written once for every same-host
        subscriber); None if it could not be written."""
        assert self.shm is not None
        shm = self.shm

        def build() -> PackedWeights | None:
            wire = self.store.wire(full, tpb.DTYPE_FLOAT32, prefixes)
            h = full.header
            name = shm.file_for(h.experiment, full.version, wire.digest, wire.payload)
            if name and self.store.dropped(h.experiment):  # dropped while this was written: its file goes too
                shm.drop(h.experiment)
                return None
            if not name:
                return None
            header = learner_pb2.WeightHeader(
                version=h.version,
                policy=h.policy,
                tensors=wire.tensors,
                total_bytes=wire.payload.nbytes,
                digest=wire.digest,
                encoding=ENCODING_RAW,
                encoded_bytes=0,  # nothing follows on the stream
                created_at_ns=h.created_at_ns,
                learner_updates=h.learner_updates,
                digest_kind=h.digest_kind,
                experiment=h.experiment,
                weight_encoding=SHM,
                shm_name=name,
            )
            return PackedWeights(header, b"")

        return self.store._once((full.header.experiment, full.version, "shm", prefixes), build)

    def _encode(self, link: Link, full: PackedWeights) -> PackedWeights | StreamedPatch:
        prefixes = link.prefixes or (full.header.policy.tensor_prefix,)  # none asked: what the policy needs
        if link.shm and not link.shm_skip:
            shared = self._shm_set(full, prefixes)
            if shared is not None:
                return shared
        encoding, base = choose_encoding(self.store, link, full, prefixes, self.keyframe_every)
        fast = link.wire_bps >= FAST_LINK_BPS
        try:
            return self.store.encoded(full, encoding, prefixes, base, link.base_digest, fast)
        except (KeyError, PatchError):  # the base left the history meanwhile, or no patch fits: full set
            full_encoding = FULL_OF.get(encoding, encoding)
            return self.store.encoded(full, full_encoding, prefixes, 0)

    @staticmethod
    def _count_sent(link: Link, packed: PackedWeights | StreamedPatch) -> None:
        link.encoding = packed.header.weight_encoding
        link.bytes_sent += packed.encoded_bytes
        link.versions_sent += 1
        link.sent_version = packed.version
        WEIGHTS_SENT.inc()
        WEIGHTS_SENT_BYTES.labels(encoding_name(link.encoding)).inc(packed.encoded_bytes)

    def _wait_ack(
        self,
        acks: queue.Queue[learner_pb2.WeightAck | None],
        version: int,
        context: grpc.ServicerContext,
        deadline: float = float("inf"),
    ) -> learner_pb2.WeightAck | None:
        """The ack of `version` (acks of older versions are dropped); None when the stream ends or at
        the deadline (time.monotonic())."""
        while context.is_active() and not self.store.closed and time.monotonic() < deadline:
            try:
                ack = acks.get(timeout=max(1e-3, min(self.poll_s, deadline - time.monotonic())))
            except queue.Empty:
                continue
            if ack is None:
                return None
            if ack.version == version:
                return ack
        return None

    def _on_ack(
        self, link: Link, packed: PackedWeights | StreamedPatch, ack: learner_pb2.WeightAck, elapsed_s: float
    ) -> bool:
        """Update the link from an ack; False if the version was rejected (resend)."""
        shared = packed.header.weight_encoding == SHM
        if ack.rejected:
            if shared:  # its file was gone or did not match: this version goes over the stream
                link.shm_skip, link.shm_failures = True, link.shm_failures + 1
                link.shm = link.shm_failures < SHM_MAX_FAILURES
            link.rejects_in_row += 1
            link.base_version, link.base_digest = 0, b""  # the client dropped its base: a full set next
            log.warning(
                "subscriber rejected a weight version; resending",
                extra=kv(client_id=link.client_id, version=packed.version, error=ack.error),
            )
            return False
        link.rejects_in_row = 0
        link.shm_skip = False
        if shared:
            link.shm_failures = 0
        link.base_version = ack.base_version
        link.base_digest = ack.base_digest
        codec = CODECS[packed.header.weight_encoding or WE.WEIGHT_ENCODING_FP32]
        link.base_wire_dtype = codec.wire_dtype
        link.base_patched = codec.patch
        link.patches_in_row = link.patches_in_row + 1 if codec.patch else 0
        if shared:  # no bytes crossed the link: nothing to measure it by
            self._applied(link, packed, ack)
            return True
        net_s = max(1e-6, elapsed_s - ack.apply_ns / 1e9)
        sample = packed.encoded_bytes / net_s
        link.goodput_bps = sample if link.goodput_bps <= 0 else 0.5 * link.goodput_bps + 0.5 * sample
        if not codec.stream:
            # the client's header -> last chunk time: a small version's send -> ack time is mostly the
            # fixed round trip, which made fast loopback links look slow (and got them compressed patches)
            wire = packed.encoded_bytes / (ack.transfer_ns / 1e9) if ack.transfer_ns > 0 else sample
            link.wire_bps = wire if link.wire_bps <= 0 else 0.5 * link.wire_bps + 0.5 * wire
        link.rtt_s = max(0.0, net_s - ack.transfer_ns / 1e9)
        if ack.apply_ns > 0:
            enc = packed.header.weight_encoding or WE.WEIGHT_ENCODING_FP32
            rate, seen = packed.nbytes / (ack.apply_ns / 1e9), link.decode_bps.get(enc, 0.0)
            link.decode_bps[enc] = rate if seen <= 0 else 0.5 * seen + 0.5 * rate
        self._applied(link, packed, ack)
        return True

    @staticmethod
    def _applied(link: Link, packed: PackedWeights | StreamedPatch, ack: learner_pb2.WeightAck) -> None:
        if ack.applied:
            link.applied_version = int(ack.version)
            link.sync_latency_s = max(0.0, (time.time_ns() - packed.header.created_at_ns) / 1e9)
            WEIGHTS_SYNC.observe(link.sync_latency_s)


class _WeightFrames(grpc.GenericRpcHandler):
    """The generated generic handler, with the weight streams' serializer swapped (see _with_frames)."""

    def __init__(self, inner: grpc.GenericRpcHandler) -> None:
        self.inner = inner

    def service(self, handler_call_details: grpc.HandlerCallDetails) -> grpc.RpcMethodHandler | None:
        return _with_frames(handler_call_details.method, self.inner.service(handler_call_details))


STREAM_WEIGHTS = "/user.v1.Learner/StreamWeights"
_FRAMED = {STREAM_WEIGHTS, "/user.v1.Learner/SubscribeWeights"}


def _with_frames(method: str, handler: grpc.RpcMethodHandler | None) -> grpc.RpcMethodHandler | None:
    if handler is None or method not in _FRAMED:
        return handler
    if handler.stream_stream:
        return grpc.stream_stream_rpc_method_handler(
            handler.stream_stream, handler.request_deserializer, serialize_weight_message
        )
    return grpc.unary_stream_rpc_method_handler(
        handler.unary_stream, handler.request_deserializer, serialize_weight_message
    )


class _FramedRegistration:
    """What add_LearnerServicer_to_server sees as the server: it passes the handlers on with the
    weight streams' response serializer accepting frames (bytes already serialized)."""

    def __init__(self, server: grpc.Server) -> None:
        self.server = server

    def add_generic_rpc_handlers(self, handlers: Sequence[grpc.GenericRpcHandler]) -> None:
        self.server.add_generic_rpc_handlers(tuple(_WeightFrames(h) for h in handlers))

    def add_registered_method_handlers(self, service: str, handlers: dict[str, grpc.RpcMethodHandler]) -> None:
        framed = {name: _with_frames(f"/{service}/{name}", h) for name, h in handlers.items()}
        self.server.add_registered_method_handlers(service, framed)


def add_learner_servicer(servicer: learner_pb2_grpc.LearnerServicer, server: grpc.Server) -> None:
    """learner_pb2_grpc.add_LearnerServicer_to_server, with weight chunks streamed as frames serialized
    straight from the payload (one copy per chunk, as a bare bytes stream makes; no protobuf copies)."""
    learner_pb2_grpc.add_LearnerServicer_to_server(servicer, _FramedRegistration(server))
    if isinstance(servicer, WeightServicer):
        servicer.frames = True


# --------------------------------------------------------------------------- client side


class WeightSubscriber:
    """Keeps a local copy of the learner's weights: a thread streams StreamWeights, calls
    on_weights(WeightSet) for each new version and acks it; on any error it reconnects with backoff
    and asks only for versions newer than the last applied one (deltas against the payload it holds)."""

    def __init__(
        self,
        addr: str,
        auth: AuthConfig,
        client_id: str,
        on_weights: Callable[[WeightSet], None],
        max_chunk_bytes: int = 0,
        have_version: int = 0,
        *,
        experiment: str = "",
        prefixes: Sequence[str] = (),
        allow_lossy: bool = False,
        encoding: int = WE.WEIGHT_ENCODING_ADAPTIVE,
        freshness_target_s: float = 0.0,
        shm_dir: str | None = None,
        shm_host: str | None = None,
    ) -> None:
        """shm_dir: a shared-memory directory this client reads (None: off); a learner on the same host
        (shm_host: this host's identity, default the boot id) that proves it shares it sends versions
        there instead of through the socket."""
        self.addr, self.auth, self.client_id = addr, auth, client_id
        self.shm_dir = shm_dir
        self.shm_host = (host_id() if shm_host is None else shm_host) if shm_dir else ""
        self.on_weights = on_weights
        self.max_chunk_bytes = max_chunk_bytes
        self.experiment, self.prefixes, self.allow_lossy = experiment, list(prefixes), allow_lossy
        self.encoding, self.freshness_target_s = encoding, freshness_target_s
        self._version = have_version
        self._assembler = WeightAssembler(shm_dir)  # outlives streams: its payload is the base for deltas
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._call: grpc.Future | None = None
        self._thread: threading.Thread | None = None
        self.connects = 0  # streams opened (first connect + reconnects)
        self.rejected = 0  # versions rejected (corrupt, unknown base) and re-fetched
        self.shm_fallbacks = 0  # shared-memory versions that could not be used (re-fetched over the stream)
        self.restarts = 0  # learners found to have restarted their versions below ours (resubscribed from 0)
        self.last_sync_s = 0.0  # publish (learner clock) -> applied (ours) of the last version
        self._applied_log = RoutineLog("weights applied")  # INFO for the first version and the first after an error

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
                self._applied_log.reset(self.experiment)
                if self._versions_restarted(err):
                    backoff.reset()
                    continue  # at once, from version 0
                log.warning(
                    "weight stream failed", extra=kv(addr=self.addr, code=str(err.code()), version=self.version)
                )
            except WireError as exc:
                self._applied_log.reset(self.experiment)
                log.error("bad weight stream, reconnecting", extra=kv(addr=self.addr, error=str(exc)))
            if not backoff.sleep(self._stop):
                break

    def _versions_restarted(self, err: grpc.RpcError) -> bool:
        """The learner holds nothing as new as what we applied: its versions restarted (a redeploy that lost its
        high-water mark). Keep acting with what we have until its weights come, and take them: forget our version
        and base (its numbers name other weights now), so the next stream asks from 0. True if that was it."""
        code = err.code() if hasattr(err, "code") else None
        trailing = err.trailing_metadata() if hasattr(err, "trailing_metadata") else None
        latest = dict(trailing or ()).get(VERSIONS_RESTARTED_KEY)
        if code != grpc.StatusCode.FAILED_PRECONDITION or latest is None:
            return False
        with self._cond:
            held, self._version = self._version, 0
        self._assembler.forget_base()
        self.restarts += 1
        log.warning(
            "the learner's weight versions restarted below ours; taking its weights from version 0",
            extra=kv(addr=self.addr, experiment=self.experiment, held=held, learner_latest=latest),
        )
        return True

    def _request(self) -> learner_pb2.SubscribeWeightsRequest:
        return learner_pb2.SubscribeWeightsRequest(
            client_id=self.client_id,
            have_version=self.version,
            max_chunk_bytes=self.max_chunk_bytes,
            experiment=self.experiment,
            prefixes=self.prefixes,
            allow_lossy=self.allow_lossy,
            base_version=self._assembler.base_version,
            base_digest=self._assembler.base_digest,
            encoding=self.encoding,
            freshness_target_ms=int(self.freshness_target_s * 1e3),
            shm_host=self.shm_host,
        )

    def _stream_once(self) -> bool:
        """One StreamWeights stream until it ends; True if it delivered at least one version."""
        got_any = False
        outbox: queue.Queue[learner_pb2.WeightAck | None] = queue.Queue()
        outbox.put(learner_pb2.WeightAck(subscribe=self._request()))

        def requests() -> Iterator[learner_pb2.WeightAck]:
            while (item := outbox.get()) is not None:
                yield item

        with rpc.make_channel(self.addr, self.auth) as channel:
            # The stub's StreamWeights, with a deserializer that reads chunks without protobuf's copies.
            stream = channel.stream_stream(
                STREAM_WEIGHTS,
                request_serializer=learner_pb2.WeightAck.SerializeToString,
                response_deserializer=parse_weight_message,
            )
            self._call = call = stream(requests())
            self.connects += 1
            if self._stop.is_set():  # stop() may have run before the call existed
                call.cancel()
            first_ns, received, version = 0, 0, 0
            try:
                for msg in call:
                    if not isinstance(msg, RawChunk) and msg.HasField("shm_probe"):
                        outbox.put(self._answer_probe(msg.shm_probe.name))
                        continue
                    if not isinstance(msg, RawChunk) and msg.HasField("header"):
                        first_ns, received, version = time.perf_counter_ns(), 0, msg.header.version
                    done_ns = time.perf_counter_ns()
                    try:
                        weights = self._assembler.feed(msg)
                    except WireError as exc:
                        if not isinstance(msg, RawChunk) and msg.header.weight_encoding == SHM:
                            self.shm_fallbacks += 1
                            SHM_FALLBACK.inc()
                        self._reject(outbox, version or (msg if isinstance(msg, RawChunk) else msg.chunk).version, exc)
                        continue
                    finally:  # counted by the assembler: each read of chunk.data copies it (upb)
                        received += self._assembler.chunk_bytes
                        WEIGHTS_BYTES.inc(self._assembler.chunk_bytes)
                    if weights is None:
                        continue
                    applied = self._apply(weights)
                    got_any |= applied
                    if self.encoding and not CODECS[self.encoding].delta:
                        # Never a delta on this stream: holding the base would only keep the last payload
                        # alive, so each version would land in freshly faulted pages.
                        self._assembler.forget_base()
                    outbox.put(
                        learner_pb2.WeightAck(
                            version=weights.version,
                            applied=applied,
                            base_version=self._assembler.base_version,
                            base_digest=self._assembler.base_digest,
                            transfer_ns=done_ns - first_ns,
                            received_bytes=received,
                            apply_ns=time.perf_counter_ns() - done_ns,
                        )
                    )
            finally:
                outbox.put(None)
                self._call = None
                call.cancel()
        return got_any

    def _answer_probe(self, name: str) -> learner_pb2.WeightAck:
        """The learner's same-host proof: the probe file's bytes as we read them (nothing if we cannot)."""
        proof = read_probe(self.shm_dir, name) if self.shm_dir else b""
        return learner_pb2.WeightAck(version=0, shm_proof=proof)

    def _reject(self, outbox: queue.Queue[learner_pb2.WeightAck | None], version: int, exc: WireError) -> None:
        """Drop the version and its base; the server resends a full set."""
        self.rejected += 1
        WEIGHTS_REJECTED.inc()
        self._applied_log.reset(self.experiment)
        self._assembler.forget_base()
        log.warning("weight version rejected; asking for a full set", extra=kv(version=version, error=str(exc)))
        outbox.put(learner_pb2.WeightAck(version=version, rejected=True, error=str(exc)[:500]))

    def _apply(self, weights: WeightSet) -> bool:
        if weights.version <= self.version:
            return False  # a server that ignored have_version; nothing newer here
        start = time.perf_counter()
        try:
            self.on_weights(weights)
        except ValueError as exc:  # a refusal that says why (a misfit policy, non-finite tensors): no traceback
            self._applied_log.reset(self.experiment)
            log.warning(
                "weights refused; keeping the previous version", extra=kv(version=weights.version, error=str(exc))
            )
            return False
        except Exception:
            self._applied_log.reset(self.experiment)
            log.exception("on_weights failed; keeping the previous version", extra=kv(version=weights.version))
            return False
        WEIGHTS_APPLY.observe(time.perf_counter() - start)
        WEIGHTS_RECEIVED.inc()
        WEIGHTS_VERSION.set(weights.version)
        with self._cond:
            self._version = weights.version
            self._cond.notify_all()
        if weights.published_at_ns:
            self.last_sync_s = max(0.0, (time.time_ns() - weights.published_at_ns) / 1e9)
        self._applied_log.log(
            log,
            self.experiment,
            version=weights.version,
            updates=weights.learner_updates,
            encoding=encoding_name(weights.encoding),
        )
        return True
