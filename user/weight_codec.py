"""Weight sets on the wire: pack once, encode per (version, encoding, base), reassemble and verify.

A weight set travels as one WeightHeader (manifest: name, dtype, wire dtype, shape, offset, nbytes per
tensor, a checksum of the decoded wire payload) followed by WeightChunks of the encoded payload.

Layers, sender side (the receiver undoes them in reverse order):
  1. select:   the tensors whose names start with one of the subscriber's prefixes;
  2. cast:     float32 tensors to fp16/bf16 for lossy encodings (user.wire.to_wire_dtype);
  3. concat:   raw little-endian bytes, offsets in the manifest -> the "wire payload" (what the digest covers);
  4. delta:    XOR with the base version's wire payload of the same layout (unchanged bits become zeros);
  5. compress: zstd (level 1: the link is the bottleneck only where compression pays).
Nothing is pickled: a receiver only trusts dtype + shape + bytes after checking sizes and the digest.
A delta names its base; a receiver that does not hold exactly that base (version and layout) rejects it
and asks for a full set, and a wrong base can never decode silently: the digest covers the result.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xxhash

from user.v1 import learner_pb2
from user.v1 import tensor_pb2 as tpb
from user.wire import WireError, dtype_from_proto, dtype_to_proto, from_wire_dtype, to_wire_dtype, wire_itemsize

ENCODING_RAW = tpb.ENCODING_RAW
ENCODING_ZSTD = tpb.ENCODING_ZSTD
DEFAULT_CHUNK_BYTES = 1 << 20
MIN_CHUNK_BYTES = 1024
MAX_CHUNK_BYTES = 16 << 20
MAX_WEIGHT_BYTES = 1 << 30  # refuse manifests that would make us allocate more than this
ZSTD_LEVEL = 1  # level 3 is ~2x slower for a few % on float bits
# xxh3-128 hashes ~30 GB/s, sha256 ~2 GB/s here: on a 40 MiB model sha256 cost 22 ms on each side.
DEFAULT_DIGEST = learner_pb2.DIGEST_XXH3_128
_HASHERS: dict[int, tuple[Callable[[], Any], int]] = {
    learner_pb2.DIGEST_SHA256: (hashlib.sha256, 32),
    learner_pb2.DIGEST_XXH3_128: (xxhash.xxh3_128, 16),
}

WE = learner_pb2.WeightEncoding


@dataclass(frozen=True)
class Codec:
    """One WeightEncoding unpacked: wire dtype of float32 tensors, delta or full, zstd or raw."""

    wire_dtype: int
    delta: bool
    zstd: bool

    @property
    def lossy(self) -> bool:
        return self.wire_dtype != tpb.DTYPE_FLOAT32


CODECS: dict[int, Codec] = {
    WE.WEIGHT_ENCODING_FP32: Codec(tpb.DTYPE_FLOAT32, False, False),
    WE.WEIGHT_ENCODING_FP32_ZSTD: Codec(tpb.DTYPE_FLOAT32, False, True),
    WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD: Codec(tpb.DTYPE_FLOAT32, True, True),
    WE.WEIGHT_ENCODING_FP16_ZSTD: Codec(tpb.DTYPE_FLOAT16, False, True),
    WE.WEIGHT_ENCODING_FP16_DELTA_ZSTD: Codec(tpb.DTYPE_FLOAT16, True, True),
    WE.WEIGHT_ENCODING_BF16_ZSTD: Codec(tpb.DTYPE_BFLOAT16, False, True),
    WE.WEIGHT_ENCODING_BF16_DELTA_ZSTD: Codec(tpb.DTYPE_BFLOAT16, True, True),
}
FULL_OF: dict[int, int] = {  # the full-set fallback of each delta encoding
    WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD: WE.WEIGHT_ENCODING_FP32_ZSTD,
    WE.WEIGHT_ENCODING_FP16_DELTA_ZSTD: WE.WEIGHT_ENCODING_FP16_ZSTD,
    WE.WEIGHT_ENCODING_BF16_DELTA_ZSTD: WE.WEIGHT_ENCODING_BF16_ZSTD,
}


def encoding_name(encoding: int) -> str:
    return WE.Name(encoding).removeprefix("WEIGHT_ENCODING_").lower()


@dataclass
class WeightSet:
    version: int
    policy: learner_pb2.PolicySpec
    tensors: dict[str, np.ndarray]
    learner_updates: int = 0
    experiment: str = ""
    encoding: int = WE.WEIGHT_ENCODING_FP32
    encoded_bytes: int = 0
    published_at_ns: int = 0

    def policy_tensors(self) -> dict[str, np.ndarray]:
        """The tensors the PolicySpec builds from, named without its tensor_prefix."""
        prefix = self.policy.tensor_prefix
        if not prefix:
            return self.tensors
        return {k[len(prefix) :]: v for k, v in self.tensors.items() if k.startswith(prefix)}


@dataclass
class PackedWeights:
    """A weight set ready to stream: the header and the (encoded) payload, built once and shared."""

    header: learner_pb2.WeightHeader
    payload: bytes | np.ndarray  # 1-D uint8 when raw; never mutated once packed
    _chunk_cache: dict[int, list[learner_pb2.WeightMessage]] = field(default_factory=dict, repr=False)

    @property
    def version(self) -> int:
        return self.header.version

    @property
    def nbytes(self) -> int:
        """Decoded wire payload size."""
        return self.header.total_bytes

    @property
    def encoded_bytes(self) -> int:
        return self.header.encoded_bytes


@dataclass(frozen=True)
class WirePayload:
    """A decoded wire payload and its layout: what a delta is taken against (sender and receiver)."""

    version: int
    tensors: tuple[learner_pb2.TensorInfo, ...]
    payload: np.ndarray  # 1-D uint8
    digest: bytes

    def same_layout(self, tensors: Sequence[learner_pb2.TensorInfo]) -> bool:
        return len(tensors) == len(self.tensors) and all(
            a.name == b.name
            and a.dtype == b.dtype
            and a.wire_dtype == b.wire_dtype
            and a.offset == b.offset
            and a.nbytes == b.nbytes
            and list(a.shape) == list(b.shape)
            for a, b in zip(tensors, self.tensors, strict=True)
        )


def _compress(data: np.ndarray) -> bytes:
    import zstandard

    return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data)


# --------------------------------------------------------------------------- pack / encode


def pack_weights(
    version: int,
    policy: learner_pb2.PolicySpec,
    tensors: Mapping[str, np.ndarray],
    learner_updates: int = 0,
    encoding: int = ENCODING_RAW,
    digest: int = DEFAULT_DIGEST,
    experiment: str = "",
) -> PackedWeights:
    """The full-precision set as published: every tensor, raw (or zstd), with its digest."""
    if version <= 0:
        raise ValueError("weight versions start at 1")
    if encoding not in (ENCODING_RAW, ENCODING_ZSTD):
        raise ValueError(f"unsupported weight encoding {encoding}")
    if digest not in _HASHERS:
        raise ValueError(f"unsupported weight digest {digest}")
    header = learner_pb2.WeightHeader(
        version=version,
        policy=policy,
        encoding=encoding,
        learner_updates=learner_updates,
        digest_kind=digest,
        experiment=experiment,
        weight_encoding=WE.WEIGHT_ENCODING_FP32 if encoding == ENCODING_RAW else WE.WEIGHT_ENCODING_FP32_ZSTD,
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
    payload = _compress(raw_payload) if encoding == ENCODING_ZSTD else raw_payload
    header.encoded_bytes = len(payload)
    header.created_at_ns = time.time_ns()
    return PackedWeights(header, payload)


def selected(infos: Sequence[learner_pb2.TensorInfo], prefixes: Sequence[str]) -> list[learner_pb2.TensorInfo]:
    """Tensors whose names start with one of `prefixes` ("" selects all)."""
    return [i for i in infos if any(i.name.startswith(p) for p in prefixes)]


def wire_payload(full: PackedWeights, wire_dtype: int, prefixes: Sequence[str]) -> WirePayload:
    """The selected tensors of a raw full-precision set, float32 ones cast to wire_dtype, concatenated."""
    h = full.header
    if h.encoding != ENCODING_RAW:
        raise ValueError("wire payloads are cut from a raw packed set")
    chosen = selected(h.tensors, prefixes)
    src = full.payload if isinstance(full.payload, np.ndarray) else np.frombuffer(full.payload, dtype=np.uint8)
    if wire_dtype == tpb.DTYPE_FLOAT32 and len(chosen) == len(h.tensors):
        infos = tuple(learner_pb2.TensorInfo(**_info_kwargs(i, i.offset, i.dtype)) for i in chosen)
        return WirePayload(h.version, infos, src, h.digest)
    out_infos, parts, offset = [], [], 0
    for info in chosen:
        part = src[info.offset : info.offset + info.nbytes]
        code = info.dtype
        if info.dtype == tpb.DTYPE_FLOAT32 and wire_dtype != tpb.DTYPE_FLOAT32:
            part = to_wire_dtype(part.view("<f4"), wire_dtype).view(np.uint8)
            code = wire_dtype
        out_infos.append(learner_pb2.TensorInfo(**_info_kwargs(info, offset, code)))
        parts.append(part)
        offset += part.nbytes
    payload = np.empty(offset, dtype=np.uint8)
    for info, part in zip(out_infos, parts, strict=True):
        payload[info.offset : info.offset + info.nbytes] = part
    return WirePayload(h.version, tuple(out_infos), payload, _HASHERS[h.digest_kind][0](payload).digest())


def _info_kwargs(info: learner_pb2.TensorInfo, offset: int, wire_dtype: int) -> dict[str, Any]:
    nbytes = math.prod(info.shape) * wire_itemsize(wire_dtype)
    wd = wire_dtype if wire_dtype != info.dtype else 0
    return dict(name=info.name, dtype=info.dtype, shape=list(info.shape), offset=offset, nbytes=nbytes, wire_dtype=wd)


def encode(full: PackedWeights, encoding: int, wire: WirePayload, base: WirePayload | None = None) -> PackedWeights:
    """One encoded version for every subscriber that wants (encoding, base): delta if base is given."""
    codec = CODECS[encoding]
    src = full.header
    data = wire.payload
    if base is not None:
        if not codec.delta or not base.same_layout(wire.tensors):
            raise ValueError("a delta needs a delta encoding and a base of the same layout")
        data = np.bitwise_xor(data, base.payload)
    elif codec.delta:
        raise ValueError("a delta encoding needs a base")
    payload: bytes | np.ndarray = _compress(data) if codec.zstd else data
    header = learner_pb2.WeightHeader(
        version=src.version,
        policy=src.policy,
        tensors=wire.tensors,
        total_bytes=int(wire.payload.nbytes),
        digest=wire.digest,
        encoding=ENCODING_ZSTD if codec.zstd else ENCODING_RAW,
        encoded_bytes=len(payload),
        created_at_ns=src.created_at_ns,
        learner_updates=src.learner_updates,
        digest_kind=src.digest_kind,
        base_version=base.version if base is not None else 0,
        experiment=src.experiment,
        weight_encoding=encoding,
    )
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
    if h.base_version >= h.version:
        raise WireError(f"weight header: v{h.version} is a delta against a base v{h.base_version} that is not older")
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
        dtype_from_proto(info.dtype)  # known dtype, or WireError
        lossy_ok = info.dtype == tpb.DTYPE_FLOAT32 and info.wire_dtype in (tpb.DTYPE_FLOAT16, tpb.DTYPE_BFLOAT16)
        if info.wire_dtype and info.wire_dtype != info.dtype and not lossy_ok:
            raise WireError(f"weight header: {info.name} cannot travel as wire dtype {info.wire_dtype}")
        if any(d < 0 for d in info.shape):
            raise WireError(f"weight header: {info.name} has a negative dimension {list(info.shape)}")
        need = math.prod(info.shape) * wire_itemsize(info.wire_dtype or info.dtype)
        if info.nbytes != need:
            raise WireError(f"weight header: {info.name} declares {info.nbytes} bytes, {list(info.shape)} needs {need}")
        if info.offset + info.nbytes > h.total_bytes:
            raise WireError(
                f"weight header: {info.name} [{info.offset}, +{info.nbytes}) exceeds payload of {h.total_bytes}"
            )


_EMPTY = np.empty(0, dtype=np.uint8)


class WeightAssembler:
    """Feed WeightMessages in stream order; returns a verified WeightSet when one is complete.

    Keeps the last complete wire payload (`held`) as the base for the next delta. Any inconsistency
    raises WireError; the version in progress is dropped (its remaining chunks are skipped) and `held`
    is kept, so the caller can ack a rejection and carry on with the same stream.
    """

    def __init__(self) -> None:
        self.held: WirePayload | None = None
        self._header: learner_pb2.WeightHeader | None = None
        self._skip_version = 0  # chunks of a rejected version still in flight
        self._buf = _EMPTY
        self._filled = 0
        self._hash: Any = None  # running digest of raw full payloads, updated as chunks arrive

    @property
    def in_progress(self) -> bool:
        return self._header is not None

    @property
    def base_version(self) -> int:
        return self.held.version if self.held is not None else 0

    def reset(self) -> None:
        self._header, self._buf, self._filled, self._hash = None, _EMPTY, 0, None

    def forget_base(self) -> None:
        self.held = None

    def feed(self, msg: learner_pb2.WeightMessage) -> WeightSet | None:
        kind = msg.WhichOneof("msg")
        if kind == "chunk" and self._header is None and msg.chunk.version == self._skip_version != 0:
            return None  # the rest of a version already rejected
        try:
            if kind == "header":
                return self._on_header(msg.header)
            if kind == "chunk":
                return self._on_chunk(msg.chunk)
            raise WireError("empty weight message")
        except WireError:
            if self._header is not None:
                self._skip_version = self._header.version
            self.reset()
            raise

    def _on_header(self, header: learner_pb2.WeightHeader) -> WeightSet | None:
        if self._header is not None:
            raise WireError(f"weight header v{header.version} before v{self._header.version} was complete")
        self._skip_version = 0
        self._header = header
        _check_header(header)
        if header.base_version:
            held = self.held
            if held is None or held.version != header.base_version or not held.same_layout(header.tensors):
                have = f"v{held.version}" if held is not None else "none"
                raise WireError(
                    f"weight v{header.version}: delta against v{header.base_version}, this client holds {have}"
                )
        # Preallocated (the header passed the size limit): one copy per chunk, no regrowth; numpy for
        # huge pages (see pack_weights).
        self._buf, self._filled = np.empty(header.encoded_bytes, dtype=np.uint8), 0
        streaming = header.encoding == ENCODING_RAW and not header.base_version
        self._hash = _HASHERS[header.digest_kind][0]() if streaming else None
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
        if h.base_version:
            assert self.held is not None  # checked on the header
            raw = np.bitwise_xor(raw, self.held.payload)
        digest = self._hash.digest() if self._hash is not None else _HASHERS[h.digest_kind][0](raw).digest()
        if digest != h.digest:
            base = f" (delta against v{h.base_version})" if h.base_version else ""
            raise WireError(f"weight v{h.version}: {learner_pb2.Digest.Name(h.digest_kind)} mismatch{base}")
        tensors = {}
        for info in h.tensors:
            stored_code = info.wire_dtype or info.dtype
            stored = raw[info.offset : info.offset + info.nbytes].view(dtype_from_proto(stored_code))
            stored = stored.reshape(tuple(info.shape))
            if stored_code != info.dtype:
                arr = from_wire_dtype(stored, stored_code)  # lossy wire dtype -> float32
            elif stored.flags.aligned and stored.flags.writeable and stored.dtype.isnative:
                arr = stored  # a view into the payload; the payload is never written again
            else:
                arr = stored.astype(stored.dtype.newbyteorder("="), copy=True)
            tensors[info.name] = arr
        self.held = WirePayload(int(h.version), tuple(h.tensors), raw, bytes(h.digest))
        out = WeightSet(
            int(h.version),
            h.policy,
            tensors,
            int(h.learner_updates),
            h.experiment,
            int(h.weight_encoding) or WE.WEIGHT_ENCODING_FP32,
            int(h.encoded_bytes),
            int(h.created_at_ns),
        )
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
