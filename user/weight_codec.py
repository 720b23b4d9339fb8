"""Weight sets on the wire: pack once, encode per (version, encoding, base), reassemble and verify.

A weight set travels as one WeightHeader (manifest: name, dtype, wire dtype, shape, offset, nbytes per
tensor, a checksum of the decoded wire payload) followed by WeightChunks of the encoded payload.

Layers, sender side (the receiver undoes them in reverse order):
  1. select:   the tensors whose names start with one of the subscriber's prefixes;
  2. cast:     float32 tensors to fp16/bf16 for lossy encodings (user.wire.to_wire_dtype);
  3. concat:   raw little-endian bytes, offsets in the manifest -> the "wire payload" (what the digest covers);
  4. delta:    XOR with the base version's wire payload of the same layout (unchanged bits become zeros);
  5. compress: zstd (level 1: the link is the bottleneck only where compression pays).
Patches (FP32_PATCH_ZSTD, lossy) replace 4: per block of PATCH_BLOCK float32 elements, the difference
new - base is quantized to int8 steps with an error bound of PATCH_REL_TOL x the block's RMS; the
receiver adds the steps to the exact payload it holds (named by its digest), and the sender computes the
same sum with the same float32 operations, so both hold bit-identical results and the digest still covers
what the receiver acts with. Each patch is taken against the receiver's state, so the error never grows.
Nothing is pickled: a receiver only trusts dtype + shape + bytes after checking sizes and the digest.
A delta names its base; a receiver that does not hold exactly that base (version and layout) rejects it
and asks for a full set, and a wrong base can never decode silently: the digest covers the result.
"""

from __future__ import annotations

import hashlib
import math
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xxhash

from user.v1 import learner_pb2
from user.v1 import tensor_pb2 as tpb
from user.weight_shm import read_payload, valid_name
from user.wire import (
    WireError,
    dtype_from_proto,
    dtype_to_proto,
    from_wire_dtype,
    read_varint,
    to_wire_dtype,
    wire_itemsize,
)

ENCODING_RAW = tpb.ENCODING_RAW
ENCODING_ZSTD = tpb.ENCODING_ZSTD
DEFAULT_CHUNK_BYTES = 1 << 20
MIN_CHUNK_BYTES = 1024
MAX_CHUNK_BYTES = 16 << 20
MAX_WEIGHT_BYTES = 1 << 30  # refuse manifests that would make us allocate more than this
ZSTD_LEVEL = 1  # level 3 is ~2x slower for a few % on float bits
# zstd's fast (negative) levels leave literals uncompressed: a patch body goes out as its int8 values
# (25 % of the fp32 bytes instead of ~13 %) for ~0.15 ms per MiB instead of ~2 ms (and a cheaper
# decode). Still a zstd frame, so receivers need nothing new; for links where bytes are cheap.
PATCH_FAST_LEVEL = -1
# xxh3-128 hashes ~30 GB/s, sha256 ~2 GB/s here: on a 40 MiB model sha256 cost 22 ms on each side.
DEFAULT_DIGEST = learner_pb2.DIGEST_XXH3_128
_HASHERS: dict[int, tuple[Callable[[], Any], int]] = {
    learner_pb2.DIGEST_SHA256: (hashlib.sha256, 32),
    learner_pb2.DIGEST_XXH3_128: (xxhash.xxh3_128, 16),
}

WE = learner_pb2.WeightEncoding


@dataclass(frozen=True)
class Codec:
    """One WeightEncoding unpacked: wire dtype of float32 tensors, delta or full, zstd or raw, patch."""

    wire_dtype: int
    delta: bool
    zstd: bool
    patch: bool = False  # quantized difference against the receiver's exact state (lossy)
    stream: bool = False  # sent while it is computed: the digest and size come last (StreamedPatch)
    shm: bool = False  # same host: the raw payload lies in a shared-memory file (user.weight_shm)

    @property
    def lossy(self) -> bool:
        return self.wire_dtype != tpb.DTYPE_FLOAT32 or self.patch


CODECS: dict[int, Codec] = {
    WE.WEIGHT_ENCODING_FP32: Codec(tpb.DTYPE_FLOAT32, False, False),
    WE.WEIGHT_ENCODING_FP32_ZSTD: Codec(tpb.DTYPE_FLOAT32, False, True),
    WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD: Codec(tpb.DTYPE_FLOAT32, True, True),
    WE.WEIGHT_ENCODING_FP16_ZSTD: Codec(tpb.DTYPE_FLOAT16, False, True),
    WE.WEIGHT_ENCODING_FP16_DELTA_ZSTD: Codec(tpb.DTYPE_FLOAT16, True, True),
    WE.WEIGHT_ENCODING_BF16_ZSTD: Codec(tpb.DTYPE_BFLOAT16, False, True),
    WE.WEIGHT_ENCODING_BF16_DELTA_ZSTD: Codec(tpb.DTYPE_BFLOAT16, True, True),
    WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD: Codec(tpb.DTYPE_FLOAT32, True, True, patch=True),
    WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD: Codec(tpb.DTYPE_FLOAT32, True, True, patch=True, stream=True),
    WE.WEIGHT_ENCODING_FP32_SHM: Codec(tpb.DTYPE_FLOAT32, False, False, shm=True),
}
FULL_OF: dict[int, int] = {  # the full-set fallback of each delta encoding
    WE.WEIGHT_ENCODING_FP32_DELTA_ZSTD: WE.WEIGHT_ENCODING_FP32_ZSTD,
    WE.WEIGHT_ENCODING_FP16_DELTA_ZSTD: WE.WEIGHT_ENCODING_FP16_ZSTD,
    WE.WEIGHT_ENCODING_BF16_DELTA_ZSTD: WE.WEIGHT_ENCODING_BF16_ZSTD,
    WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD: WE.WEIGHT_ENCODING_FP32_ZSTD,  # also the exact resync (keyframe)
    WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD: WE.WEIGHT_ENCODING_FP32_ZSTD,
}
PATCHES = (WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD, WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD)
PATCH_BLOCK = 4096  # float32 elements per quantization step (4 bytes of step per 4 KiB of int8)
# Error bound of a patch per element, relative to the RMS of the new weights in its block. Measured on a
# 1M-parameter actor, 5 Adam steps (lr 3e-4) between versions: 2^-10 -> 13 % of the fp32 bytes and a max
# action deviation of 5.7e-4 on 256 fixed observations (bf16: 5.1e-4); 2^-9 -> 10 % and 4.6e-3.
PATCH_REL_TOL = 2.0**-10


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


class BufferPool:
    """Reuses big numpy buffers nobody else references any more.

    A fresh 100 MiB buffer spends ~0.5 s here in page faults (a reused one ~10-20 ms), more than the
    transfer itself on loopback. A buffer given back is handed out again only once no array views it
    (tensors of a weight set are views into its payload, so a set still in use keeps its buffer).
    """

    def __init__(self, keep: int = 2) -> None:
        """keep: spare buffers held at most (each as big as a payload: memory traded for page faults)."""
        self.keep = keep
        self._free: list[np.ndarray] = []
        # where fresh buffers come from when not np.empty (None from it: np.empty after all), e.g. shared memory
        self.fresh: Callable[[int], np.ndarray | None] | None = None

    def take(self, nbytes: int) -> np.ndarray:
        for i in range(len(self._free)):
            # refs: the list and getrefcount's argument; every view of it would add one
            if nbytes <= self._free[i].nbytes <= nbytes + (nbytes >> 2) + 4096 and sys.getrefcount(self._free[i]) <= 2:
                return self._free.pop(i)[:nbytes]
        fresh = self.fresh(nbytes) if self.fresh is not None else None
        return fresh if fresh is not None else np.empty(nbytes, dtype=np.uint8)

    def give(self, arr: np.ndarray) -> None:
        """Offer arr's buffer for reuse (it is reused only once nothing views it)."""
        base = arr
        while isinstance(base.base, np.ndarray):  # the array that views a foreign buffer (mmap) counts as its owner
            base = base.base
        if base.nbytes < 1 << 20 or not base.flags.writeable or any(b is base for b in self._free):
            return
        self._free.append(base)
        del self._free[: -self.keep]


ZSTD_THREADS_FROM = 4 << 20  # bigger inputs are compressed by zstd's worker threads (one per core)


def _compress(data: np.ndarray) -> bytes:
    import zstandard

    threads = -1 if data.nbytes >= ZSTD_THREADS_FROM else 0  # -1: as many as cores; the GIL is released
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL, threads=threads).compress(data)


# --------------------------------------------------------------------------- pack / encode


def pack_weights(
    version: int,
    policy: learner_pb2.PolicySpec,
    tensors: Mapping[str, np.ndarray],
    learner_updates: int = 0,
    encoding: int = ENCODING_RAW,
    digest: int = DEFAULT_DIGEST,
    experiment: str = "",
    alloc: Callable[[int], np.ndarray] | None = None,
) -> PackedWeights:
    """The full-precision set as published: every tensor, raw (or zstd), with its digest.

    alloc(nbytes) -> 1-D uint8 buffer for the raw payload (e.g. a BufferPool's take: no fresh pages)."""
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
    raw_payload = alloc(offset) if alloc is not None and encoding == ENCODING_RAW else np.empty(offset, np.uint8)
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


def encode(
    full: PackedWeights,
    encoding: int,
    wire: WirePayload,
    base: WirePayload | None = None,
    xor_buf: np.ndarray | None = None,
) -> PackedWeights:
    """One encoded version for every subscriber that wants (encoding, base): delta if base is given.

    xor_buf: a reused uint8 buffer of the payload's size for the XOR (freed pages cost more than the XOR)."""
    codec = CODECS[encoding]
    src = full.header
    data = wire.payload
    if base is not None:
        if not codec.delta or not base.same_layout(wire.tensors):
            raise ValueError("a delta needs a delta encoding and a base of the same layout")
        out = xor_buf if xor_buf is not None and xor_buf.nbytes == data.nbytes and codec.zstd else None
        data = np.bitwise_xor(data, base.payload, out=out)  # compressed below: the buffer is free again
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


class PatchError(ValueError):
    """A patch cannot represent this version (non-finite values, other layout): send an exact set."""


def _f32_segments(tensors: Sequence[learner_pb2.TensorInfo]) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(offset, nbytes) of the float32 tensors and of the others, in payload order."""
    f32, other = [], []
    for info in tensors:
        is_f32 = info.dtype == tpb.DTYPE_FLOAT32 and info.wire_dtype in (0, tpb.DTYPE_FLOAT32)
        (f32 if is_f32 else other).append((int(info.offset), int(info.nbytes)))
    return f32, other


def _f32_run(segments: list[tuple[int, int]]) -> tuple[int, int] | None:
    """(offset, nbytes) of the float32 segments when they lie back to back (the usual layout), else None."""
    if not segments:
        return None
    start = end = segments[0][0]
    for o, n in segments:
        if o != end:
            return None
        end += n
    return start, end - start


def _gather_f32(payload: np.ndarray, segments: list[tuple[int, int]]) -> np.ndarray:
    """The float32 elements of `payload`, concatenated: a view when they lie back to back (no copy)."""
    run = _f32_run(segments)
    if run is not None:
        return payload[run[0] : run[0] + run[1]].view("<f4")
    if not segments:
        return np.empty(0, dtype="<f4")
    return np.concatenate([payload[o : o + n].view("<f4") for o, n in segments])


def patch_body_bytes(tensors: Sequence[learner_pb2.TensorInfo]) -> int:
    """Decoded size of a patch: one float32 step per block, int8 per padded element, other tensors raw."""
    f32, other = _f32_segments(tensors)
    blocks = -(-sum(n for _, n in f32) // 4 // PATCH_BLOCK)
    return blocks * 4 + blocks * PATCH_BLOCK + sum(n for _, n in other)


PATCH_SLICE_BLOCKS = 64  # blocks per slice of work: 1 MiB of float32 scratch, reused (stays in cache)


def _apply_blocks(base: np.ndarray, steps: np.ndarray, q: np.ndarray, out: np.ndarray, scratch: np.ndarray) -> None:
    """out = base + q * step of its block, in float32: the one computation both sides run, so sender
    and receiver hold the same bits. base/out: the slice's elements (the last block may be partial);
    steps: one per block; q: int8, whole blocks. The int8 -> float32 cast inside the mixed multiply is
    exact, so the product has the bits of a float32 multiply."""
    blocks, m = steps.size, base.size
    tmp = scratch[: blocks * PATCH_BLOCK].reshape(blocks, PATCH_BLOCK)
    np.multiply(q.reshape(blocks, PATCH_BLOCK), steps[:, None], out=tmp)
    np.add(base, tmp.reshape(-1)[:m], out=out)


def _apply_slice(
    base: np.ndarray, steps: np.ndarray, q: np.ndarray, out: np.ndarray, lo: int, hi: int, scratch: np.ndarray
) -> None:
    """out[lo:hi] = base + q * step of its blocks (_apply_blocks on whole-payload arrays); lo is a
    multiple of PATCH_BLOCK."""
    blocks = -(-(hi - lo) // PATCH_BLOCK)
    b0 = lo // PATCH_BLOCK
    _apply_blocks(base[lo:hi], steps[b0 : b0 + blocks], q[lo : lo + blocks * PATCH_BLOCK], out[lo:hi], scratch)


def _apply_steps(base: np.ndarray, steps: np.ndarray, q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = base + q * step per block (the receiver's side), slice by slice with one small scratch
    buffer, so no big temporary is allocated (page faults)."""
    n, step = base.size, PATCH_SLICE_BLOCKS * PATCH_BLOCK
    scratch = np.empty(step, dtype=np.float32)
    for lo in range(0, n, step):
        _apply_slice(base, steps, q, out, lo, min(n, lo + step), scratch)
    return out


def _quantize_blocks(
    new: np.ndarray,
    old: np.ndarray,
    steps: np.ndarray,
    q: np.ndarray,
    out: np.ndarray,
    d: np.ndarray,
    scratch: np.ndarray,
) -> None:
    """Fill steps (one per block) and q (int8, whole blocks) for new - old of one slice, and out with
    the state the receiver will compute (_apply_blocks), while the slice is in cache.

    Only the sender quantizes (steps travel), so its arithmetic need not match the receiver's: sums of
    squares accumulate in float32 (einsum), and q needs no clipping: step >= max|diff| / 127 keeps
    |diff / step| <= 127 (plus rounding), which rint keeps at 127. d, scratch: float32 of whole blocks."""
    m, blocks = new.size, steps.size
    size = blocks * PATCH_BLOCK
    if m < size:  # the last, partial block: zero padding (the receiver ignores it)
        d[m:size] = 0
        w = np.zeros(size, dtype=np.float32)
        w[:m] = new
    else:
        w = new
    np.subtract(new, old, out=d[:m])
    d2, w2 = d[:size].reshape(blocks, PATCH_BLOCK), w.reshape(blocks, PATCH_BLOCK)
    rms = np.sqrt(np.einsum("ij,ij->i", w2, w2) / np.float32(PATCH_BLOCK))
    peak = np.maximum(d2.max(axis=1), -d2.min(axis=1))
    s = np.maximum(np.float32(2 * PATCH_REL_TOL) * rms, peak / np.float32(127))  # |error| <= step / 2
    if not np.isfinite(s).all():
        raise PatchError("non-finite weights or differences")
    s[s == 0] = 1.0  # an unchanged all-zero block
    steps[...] = s
    d2 /= s[:, None]
    np.rint(d2, out=q.reshape(blocks, PATCH_BLOCK), casting="unsafe")  # into int8
    _apply_blocks(old, steps, q, out, scratch)


def _quantize(new: np.ndarray, old: np.ndarray, steps: np.ndarray, q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """_quantize_blocks over whole payloads (steps | q layout of FP32_PATCH_ZSTD), slice by slice."""
    n, step = new.size, PATCH_SLICE_BLOCKS * PATCH_BLOCK
    d = np.zeros(step, dtype=np.float32)
    scratch = np.empty(step, dtype=np.float32)
    for lo in range(0, n, step):
        hi = min(n, lo + step)
        b0, blocks = lo // PATCH_BLOCK, -(-(hi - lo) // PATCH_BLOCK)
        q_s = q[lo : lo + blocks * PATCH_BLOCK]
        _quantize_blocks(new[lo:hi], old[lo:hi], steps[b0 : b0 + blocks], q_s, out[lo:hi], d, scratch)
    return out


def _write_state(
    out: np.ndarray, f32: list[tuple[int, int]], values: np.ndarray, other: list[tuple[int, int]], rest: np.ndarray
) -> np.ndarray:
    """Fill payload `out` with the float32 segments from `values` (unless _state_values put them there
    already) and the other tensors from `rest`."""
    if _f32_run(f32) is None:
        pos = 0
        for o, n in f32:
            out[o : o + n] = values[pos // 4 : (pos + n) // 4].view(np.uint8)
            pos += n
    pos = 0
    for o, n in other:
        out[o : o + n] = rest[pos : pos + n]
        pos += n
    return out


def _state_values(out: np.ndarray, f32: list[tuple[int, int]], size: int) -> np.ndarray:
    """Where the new float32 values go: straight into the payload `out` when they lie back to back."""
    run = _f32_run(f32)
    if run is not None:
        return out[run[0] : run[0] + run[1]].view("<f4")
    return np.empty(size, dtype=np.float32)


def encode_patch(
    full: PackedWeights,
    wire: WirePayload,
    base: WirePayload,
    buf: np.ndarray | None = None,
    body_buf: np.ndarray | None = None,
) -> tuple[PackedWeights, WirePayload]:
    """A patch taking `base` (the receiver's exact state) towards `wire`, and the state it leads to
    (written into `buf`, uint8 of the payload's size, when given: a reused buffer faults no pages).
    body_buf: a reused buffer of at least patch_body_bytes for the uncompressed body."""
    if not base.same_layout(wire.tensors) or base.version >= wire.version:
        raise PatchError("a patch needs an older base of the same layout")
    f32, other = _f32_segments(wire.tensors)
    new, old = _gather_f32(wire.payload, f32), _gather_f32(base.payload, f32)
    blocks = -(-new.size // PATCH_BLOCK)
    body_bytes = patch_body_bytes(wire.tensors)  # steps | q | other tensors
    reuse = body_buf is not None and body_buf.nbytes >= body_bytes
    body = body_buf[:body_bytes] if reuse else np.empty(body_bytes, dtype=np.uint8)
    steps = body[: blocks * 4].view("<f4")
    q = body[blocks * 4 : blocks * 4 + blocks * PATCH_BLOCK].view(np.int8)
    size = wire.payload.nbytes
    out = buf if buf is not None and buf.nbytes == size else np.empty(size, dtype=np.uint8)
    values = _quantize(new, old, steps, q, _state_values(out, f32, new.size))
    rest = body[blocks * 4 + blocks * PATCH_BLOCK :]
    pos = 0
    for o, nb in other:  # non-float tensors travel raw
        rest[pos : pos + nb] = wire.payload[o : o + nb]
        pos += nb
    state_payload = _write_state(out, f32, values, other, rest)
    digest = _HASHERS[full.header.digest_kind][0](state_payload).digest()
    state = WirePayload(wire.version, wire.tensors, state_payload, digest)
    payload = _compress(body)
    header = patch_header(full, wire, base, WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD)
    header.digest, header.encoded_bytes = digest, len(payload)
    return PackedWeights(header, payload), state


def apply_patch(
    base: WirePayload, tensors: Sequence[learner_pb2.TensorInfo], body: np.ndarray, pool: BufferPool | None = None
) -> np.ndarray:
    """The payload a decoded patch body leads to from `base` (sizes checked by the caller)."""
    f32, other = _f32_segments(tensors)
    old = _gather_f32(base.payload, f32)
    blocks = -(-old.size // PATCH_BLOCK)
    steps = body[: blocks * 4].view("<f4")
    q = body[blocks * 4 : blocks * 4 + blocks * PATCH_BLOCK].view(np.int8)
    if not np.isfinite(steps).all():
        raise WireError("weight patch: non-finite step")
    rest = body[blocks * 4 + blocks * PATCH_BLOCK :]
    size = base.payload.nbytes
    out = pool.take(size) if pool else np.empty(size, np.uint8)  # a reused buffer: no fresh pages
    values = _apply_steps(old, steps, q, _state_values(out, f32, old.size))
    return _write_state(out, f32, values, other, rest)


# --------------------------------------------------------------------------- streamed patches
# FP32_PATCH_STREAM_ZSTD: the same quantization and the same float32 apply as FP32_PATCH_ZSTD, but the
# body is interleaved per slice (its steps, then its int8 values), so the sender compresses and sends
# slice k while it quantizes slice k + 1, and the receiver applies slice k while later ones are still on
# the way. Encode, transfer and decode overlap (on loopback they were three serial stages of similar
# length). The header cannot carry the digest or the compressed size: the last chunk does.

PATCH_FLUSH_BYTES = 1 << 20  # body bytes between zstd flushes: what goes out ahead of the rest


def _slice_elements(n: int) -> Iterator[tuple[int, int, int]]:
    """(lo, hi, blocks) of each slice of n float32 elements, in body order."""
    step = PATCH_SLICE_BLOCKS * PATCH_BLOCK
    for lo in range(0, n, step):
        hi = min(n, lo + step)
        yield lo, hi, -(-(hi - lo) // PATCH_BLOCK)


class StreamedPatch:
    """A streamed patch as the server fans it out: the header now, compressed pieces as they are
    made (by encode_patch_stream, on its own thread), then the digest. Every subscriber that wants this
    (version, base) reads the same pieces; none waits for another's flow control."""

    def __init__(self, header: learner_pb2.WeightHeader) -> None:
        self.header = header  # encoded_bytes 0 and no digest: both are known at the end
        self._pieces: list[bytes] = []
        self._cond = threading.Condition()
        self.done = False
        self.error: BaseException | None = None
        self.digest = b""
        self._encoded = 0

    @property
    def version(self) -> int:
        return self.header.version

    @property
    def nbytes(self) -> int:
        return self.header.total_bytes

    @property
    def encoded_bytes(self) -> int:
        """Compressed bytes so far (all of them once done)."""
        return self._encoded

    def add(self, piece: bytes) -> None:
        if piece:
            with self._cond:
                self._pieces.append(piece)
                self._encoded += len(piece)
                self._cond.notify_all()

    def finish(self, digest: bytes) -> None:
        with self._cond:
            self.digest, self.done = digest, True
            self._cond.notify_all()

    def fail(self, exc: BaseException) -> None:
        with self._cond:
            self.error, self.done = exc, True
            self._cond.notify_all()

    def wait(self, timeout: float | None = None) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self.done, timeout)

    def _chunks(self, max_chunk_bytes: int) -> Iterator[tuple[int, memoryview]]:
        """(offset, data) of the compressed stream as it grows, in chunks of at most max_chunk_bytes."""
        i = offset = 0
        while True:
            with self._cond:
                self._cond.wait_for(lambda i=i: i < len(self._pieces) or self.done)
                new, done = self._pieces[i:], self.done
            i += len(new)
            for piece in new:
                view = memoryview(piece)
                for start in range(0, len(view), max_chunk_bytes):
                    part = view[start : start + max_chunk_bytes]
                    yield offset, part
                    offset += len(part)
            if done and i == len(self._pieces):
                return

    def _trailer(self, offset: int) -> learner_pb2.WeightMessage:
        digest = self.digest if self.error is None else b""  # empty: given up, the receiver asks for a full set
        chunk = learner_pb2.WeightChunk(version=self.version, offset=offset, last=True, digest=digest)
        return learner_pb2.WeightMessage(chunk=chunk)

    def frames(self, max_chunk_bytes: int) -> Iterator[bytes]:
        yield learner_pb2.WeightMessage(header=self.header).SerializeToString()
        end = 0
        for offset, data in self._chunks(max_chunk_bytes):
            yield chunk_frame(self.version, offset, data)
            end = offset + len(data)
        yield self._trailer(end).SerializeToString()

    def messages(self, max_chunk_bytes: int) -> Iterator[learner_pb2.WeightMessage]:
        yield learner_pb2.WeightMessage(header=self.header)
        end = 0
        for offset, data in self._chunks(max_chunk_bytes):
            chunk = learner_pb2.WeightChunk(version=self.version, offset=offset, data=bytes(data))
            yield learner_pb2.WeightMessage(chunk=chunk)
            end = offset + len(data)
        yield self._trailer(end)


def patch_header(
    full: PackedWeights,
    wire: WirePayload,
    base: WirePayload,
    weight_encoding: int = WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD,
) -> learner_pb2.WeightHeader:
    """The header of a patch from `base` towards `wire` (a one-shot patch adds its digest and size; a
    streamed one sends its digest on the last chunk)."""
    src = full.header
    return learner_pb2.WeightHeader(
        version=src.version,
        policy=src.policy,
        tensors=wire.tensors,
        total_bytes=int(wire.payload.nbytes),
        encoding=ENCODING_ZSTD,
        created_at_ns=src.created_at_ns,
        learner_updates=src.learner_updates,
        digest_kind=src.digest_kind,
        base_version=base.version,
        base_digest=base.digest,
        experiment=src.experiment,
        weight_encoding=weight_encoding,
    )


class _Compressor:
    """The zstd half of a streamed patch encode: compresses bodies in order and hands `sink` one flushed
    piece per body. Pipelined, on its own thread (zstd releases the GIL), it compresses body k while the
    caller quantizes body k+1 into another of `buffers`; otherwise it compresses in the caller's thread
    (a small patch: one or two bodies, where a thread hand-off costs more than it overlaps)."""

    def __init__(
        self, sink: StreamedPatch, buffers: list[np.ndarray], pipelined: bool, level: int = ZSTD_LEVEL
    ) -> None:
        import zstandard

        self.sink, self.pipelined = sink, pipelined
        self.comp = zstandard.ZstdCompressor(level=level).compressobj()
        self.flush_block, self.flush_end = zstandard.COMPRESSOBJ_FLUSH_BLOCK, zstandard.COMPRESSOBJ_FLUSH_FINISH
        self.free: queue.Queue[np.ndarray] = queue.Queue()
        for buf in buffers:
            self.free.put(buf)
        self.todo: queue.Queue[tuple[np.ndarray, int, bool] | None] = queue.Queue()
        self.error: BaseException | None = None
        self.thread: threading.Thread | None = None
        if pipelined:
            self.thread = threading.Thread(target=self._run, daemon=True, name="patch-zstd")
            self.thread.start()

    def buffer(self) -> np.ndarray:
        """A free body buffer (waits while the compressor holds all of them)."""
        if self.error is not None:
            raise self.error
        return self.free.get()

    def put(self, buf: np.ndarray, nbytes: int, last: bool = False) -> None:
        """Compress buf[:nbytes] next (the last one ends the frame); buf returns to the free ones after."""
        if self.pipelined:
            self.todo.put((buf, nbytes, last))
        else:
            self._compress(buf, nbytes, last)

    def _compress(self, buf: np.ndarray, nbytes: int, last: bool) -> None:
        piece = self.comp.compress(buf[:nbytes]) + self.comp.flush(self.flush_end if last else self.flush_block)
        self.free.put(buf)  # zstd copied what it needs: the quantizer may refill it
        self.sink.add(piece)

    def _run(self) -> None:
        while (job := self.todo.get()) is not None:
            if self.error is None:
                try:
                    self._compress(*job)
                    continue
                except BaseException as exc:  # the caller raises it at its next buffer() or close()
                    self.error = exc
            self.free.put(job[0])

    def stop(self) -> None:
        """Wait until everything put is compressed (and handed to the sink) and the thread has ended."""
        if self.thread is not None and self.thread.is_alive():
            self.todo.put(None)
            self.thread.join()

    def close(self) -> None:
        """stop(), then raise what failed."""
        self.stop()
        if self.error is not None:
            raise self.error


PATCH_PIPELINE_BUFFERS = 3  # bodies in flight between the quantizer and the compressor
PATCH_PIPELINE_FROM = 3  # pieces: smaller patches quantize and compress in one thread (no hand-offs)


def encode_patch_stream(
    full: PackedWeights,
    wire: WirePayload,
    base: WirePayload,
    sink: StreamedPatch,
    buf: np.ndarray | None = None,
    reached: Callable[[WirePayload], None] | None = None,
    level: int = ZSTD_LEVEL,
) -> WirePayload:
    """Quantize, compress (zstd `level`; PATCH_FAST_LEVEL: stored) and hand `sink` the patch slice by
    slice; returns the state it leads to (in `buf` when given, uint8 of the payload's size) and
    finishes `sink` with its digest. On
    PatchError (non-finite values) `sink` fails: its trailer tells the receiver to ask for a full set.
    reached(state) runs before `sink` finishes: a subscriber acking it may ask for a patch on it next.

    The body goes out in pieces of about PATCH_FLUSH_BYTES (one zstd flush each); past two pieces the
    quantizer (this thread) and zstd (a _Compressor thread) work on consecutive pieces at once."""
    compressor: _Compressor | None = None
    try:
        if not base.same_layout(wire.tensors) or base.version >= wire.version:
            raise PatchError("a patch needs an older base of the same layout")
        f32, other = _f32_segments(wire.tensors)
        new, old = _gather_f32(wire.payload, f32), _gather_f32(base.payload, f32)
        size = wire.payload.nbytes
        out = buf if buf is not None and buf.nbytes == size else np.empty(size, dtype=np.uint8)
        values = _state_values(out, f32, new.size)
        slice_elems, slice_body = PATCH_SLICE_BLOCKS * PATCH_BLOCK, PATCH_SLICE_BLOCKS * (4 + PATCH_BLOCK)
        # slices per flushed piece; stored, every slice goes out at once (a flush costs next to nothing),
        # so the receiver applies slice k while this thread quantizes slice k + 1
        per_piece = max(1, -(-PATCH_FLUSH_BYTES // slice_body)) if level > 0 else 1
        slices = -(-new.size // slice_elems)
        pipelined = slices >= PATCH_PIPELINE_FROM * per_piece and level > 0  # a stored body needs no zstd thread
        bodies = [
            np.empty(per_piece * slice_body, dtype=np.uint8) for _ in range(PATCH_PIPELINE_BUFFERS if pipelined else 1)
        ]
        compressor = _Compressor(sink, bodies, pipelined, level)
        d, scratch = np.zeros(slice_elems, np.float32), np.empty(slice_elems, np.float32)
        body, filled, in_body = compressor.buffer(), 0, 0
        for lo, hi, blocks in _slice_elements(new.size):
            steps = body[filled : filled + blocks * 4].view("<f4")
            q = body[filled + blocks * 4 : filled + blocks * (4 + PATCH_BLOCK)].view(np.int8)
            _quantize_blocks(new[lo:hi], old[lo:hi], steps, q, values[lo:hi], d, scratch)
            filled += blocks * (4 + PATCH_BLOCK)
            in_body += 1
            if in_body == per_piece:
                compressor.put(body, filled)
                body, filled, in_body = compressor.buffer(), 0, 0
        if filled:
            compressor.put(body, filled)
        rest = np.empty(sum(n for _, n in other), dtype=np.uint8)
        pos = 0
        for o, nb in other:  # non-float tensors travel raw, after the slices
            rest[pos : pos + nb] = wire.payload[o : o + nb]
            pos += nb
        compressor.put(rest, rest.size, last=True)
        compressor.close()
        state_payload = _write_state(out, f32, values, other, rest)
        digest = _HASHERS[full.header.digest_kind][0](state_payload).digest()
        state = WirePayload(wire.version, wire.tensors, state_payload, digest)
        if reached is not None:
            reached(state)
    except BaseException as exc:
        if compressor is not None:
            compressor.stop()  # before the sink fails: no piece is added after its end
        sink.fail(exc)
        raise
    sink.finish(digest)
    return state


class _PatchStreamDecoder:
    """Applies a streamed patch as it arrives: zstd output (bounded: write_size at a time, checked
    against the manifest's sizes) fills one slice of the body; a full slice is applied to the held base
    at once, while later chunks are still on the way."""

    WRITE_SIZE = 1 << 18

    def __init__(self, base: WirePayload, tensors: Sequence[learner_pb2.TensorInfo], out: np.ndarray) -> None:
        import zstandard

        self.f32, self.other = _f32_segments(tensors)
        self.old = _gather_f32(base.payload, self.f32)
        self.out = out
        self.values = _state_values(out, self.f32, self.old.size)
        self.slices = _slice_elements(self.old.size)
        self.rest = np.empty(sum(n for _, n in self.other), dtype=np.uint8)
        self.body = np.empty(PATCH_SLICE_BLOCKS * (4 + PATCH_BLOCK), dtype=np.uint8)
        self.scratch = np.empty(PATCH_SLICE_BLOCKS * PATCH_BLOCK, dtype=np.float32)
        self._next_slice()
        self.rest_filled = 0
        self.writer = zstandard.ZstdDecompressor().stream_writer(self, write_size=self.WRITE_SIZE)
        self._error = zstandard.ZstdError

    def _next_slice(self) -> None:
        self.current = next(self.slices, None)
        self.need = self.current[2] * (4 + PATCH_BLOCK) if self.current else 0
        self.filled = 0

    def feed(self, data: memoryview) -> None:
        try:
            self.writer.write(data)
        except self._error as exc:
            raise WireError(f"weight patch: bad zstd stream: {exc}") from exc

    def write(self, data: bytes) -> int:
        """zstd's output (the stream_writer's writer)."""
        view, pos = memoryview(data), 0
        while pos < len(view):
            if self.current is None:  # the non-float tensors
                take = len(view) - pos
                if self.rest_filled + take > self.rest.size:
                    raise WireError("weight patch: decoded body longer than the manifest says")
                self.rest[self.rest_filled : self.rest_filled + take] = np.frombuffer(view[pos:], np.uint8)
                self.rest_filled += take
                break
            take = min(self.need - self.filled, len(view) - pos)
            self.body[self.filled : self.filled + take] = np.frombuffer(view[pos : pos + take], np.uint8)
            self.filled += take
            pos += take
            if self.filled == self.need:
                self._apply()
        return len(data)

    def _apply(self) -> None:
        assert self.current is not None
        lo, hi, blocks = self.current
        steps = self.body[: blocks * 4].view("<f4")
        if not np.isfinite(steps).all():
            raise WireError("weight patch: non-finite step")
        q = self.body[blocks * 4 : blocks * (4 + PATCH_BLOCK)].view(np.int8)
        _apply_blocks(self.old[lo:hi], steps, q, self.values[lo:hi], self.scratch)
        self._next_slice()

    def finish(self) -> np.ndarray:
        if self.current is not None or self.rest_filled != self.rest.size:
            raise WireError("weight patch: the stream ended before the body was complete")
        out = _write_state(self.out, self.f32, self.values, self.other, self.rest)
        self.close()
        return out

    def close(self) -> None:
        """Break the cycle with zstd's writer (it holds us): otherwise the payload buffer stays referenced
        until the garbage collector runs, and the pool cannot hand it out again (fresh pages instead)."""
        self.writer = None
        self.values = self.old = _EMPTY


def iter_weight_messages(
    packed: PackedWeights | StreamedPatch, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> Iterator[learner_pb2.WeightMessage]:
    """Header, then the payload in chunks of at most max_chunk_bytes (messages cached per chunk size)."""
    if max_chunk_bytes <= 0:
        raise ValueError("max_chunk_bytes must be positive")
    if isinstance(packed, StreamedPatch):
        yield from packed.messages(max_chunk_bytes)
        return
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


# --------------------------------------------------------------------------- chunk frames
# A chunk message serialized by hand, straight from the payload: protobuf (upb) would copy each chunk
# into a message, again to serialize it per subscriber, and the receiver's parse and every read of
# .data copy it again (~30 us per MiB each, under the GIL). The bytes are exactly the protobuf
# encoding of WeightMessage{chunk: WeightChunk{version = 1, offset = 2, data = 3}} (proto/user/v1/
# learner.proto), so any protobuf peer reads them; the parser below takes that one shape and hands
# anything else to protobuf.

_CHUNK_TAG = b"\x12"  # WeightMessage.chunk: field 2, length-delimited


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append(n & 0x7F | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def chunk_frame(version: int, offset: int, data: memoryview) -> bytes:
    """The serialized WeightMessage of one chunk (as SerializeToString writes it: zero fields omitted)."""
    head = (b"\x08" + _varint(version) if version else b"") + (b"\x10" + _varint(offset) if offset else b"")
    head += (b"\x1a" + _varint(len(data))) if len(data) else b""
    return b"".join((_CHUNK_TAG, _varint(len(head) + len(data)), head, data))


def iter_weight_frames(
    packed: PackedWeights | StreamedPatch, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> Iterator[bytes]:
    """iter_weight_messages, serialized: one copy per chunk straight from the payload, nothing cached."""
    if max_chunk_bytes <= 0:
        raise ValueError("max_chunk_bytes must be positive")
    if isinstance(packed, StreamedPatch):
        yield from packed.frames(max_chunk_bytes)
        return
    yield learner_pb2.WeightMessage(header=packed.header).SerializeToString()
    view = memoryview(packed.payload).cast("B")
    for start in range(0, len(view), max_chunk_bytes):
        yield chunk_frame(packed.version, start, view[start : start + max_chunk_bytes])


def serialize_weight_message(msg: learner_pb2.WeightMessage | bytes) -> bytes:
    """Response serializer of the weight streams: frames pass as they are, messages are serialized."""
    return msg if isinstance(msg, bytes) else msg.SerializeToString()


@dataclass(frozen=True, slots=True)
class RawChunk:
    """A WeightChunk read without protobuf's copies: data is a view into the received message."""

    version: int
    offset: int
    data: memoryview
    last: bool = False  # frames never carry these (the trailer of a stream goes through protobuf)
    digest: bytes = b""


def parse_weight_message(buf: bytes) -> learner_pb2.WeightMessage | RawChunk:
    """Response deserializer of the weight streams: a lone chunk as a RawChunk (no copy of its data),
    anything else (a header, unknown or repeated fields) by protobuf."""
    try:
        if buf[:1] == _CHUNK_TAG:
            size, pos = read_varint(buf, 1)
            if pos + size == len(buf):
                version = offset = 0
                data = memoryview(b"")
                while pos < len(buf):
                    tag, pos = read_varint(buf, pos)
                    if tag == 0x08:
                        version, pos = read_varint(buf, pos)
                    elif tag == 0x10:
                        offset, pos = read_varint(buf, pos)
                    elif tag == 0x1A:
                        n, pos = read_varint(buf, pos)
                        if pos + n > len(buf):
                            raise WireError("truncated bytes field")
                        data, pos = memoryview(buf)[pos : pos + n], pos + n
                    else:
                        break  # another field: protobuf's parse below decides
                else:
                    return RawChunk(version & (2**64 - 1), offset & (2**64 - 1), data)
    except WireError:
        pass  # malformed: protobuf's parse raises the proper error
    return learner_pb2.WeightMessage.FromString(buf)


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
    if h.weight_encoding == WE.WEIGHT_ENCODING_FP32_SHM:
        # the payload is in a file: nothing follows on the stream, and the name cannot leave the shm dir
        if h.encoding != ENCODING_RAW or h.encoded_bytes or h.base_version or not valid_name(h.shm_name):
            raise WireError("weight header: a shared-memory set is raw, whole, with a weight file name")
        if any(i.wire_dtype not in (0, i.dtype) for i in h.tensors):
            raise WireError("weight header: a shared-memory set carries full-precision tensors only")
    elif h.shm_name:
        raise WireError("weight header: a shared-memory file name outside FP32_SHM")
    elif h.encoding == ENCODING_RAW and h.encoded_bytes != h.total_bytes:
        raise WireError(
            f"weight header: raw payload with encoded_bytes {h.encoded_bytes} != total_bytes {h.total_bytes}"
        )
    streamed = h.weight_encoding == WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD
    if h.weight_encoding in PATCHES:
        if not h.base_version or not h.base_digest or h.encoding != ENCODING_ZSTD:
            raise WireError("weight header: a patch needs a base version, a base digest and zstd")
        if any(i.wire_dtype not in (0, i.dtype) for i in h.tensors):
            raise WireError("weight header: a patch carries full-precision tensors only")
    if streamed and (h.digest or h.encoded_bytes):
        raise WireError("weight header: a streamed patch's digest and size come with its last chunk")
    if h.base_version >= h.version:
        raise WireError(f"weight header: v{h.version} is a delta against a base v{h.base_version} that is not older")
    if h.digest_kind not in _HASHERS:
        raise WireError(f"weight header: unsupported digest kind {h.digest_kind}")
    want = _HASHERS[h.digest_kind][1]
    if len(h.digest) != want and not streamed:
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

    def __init__(self, shm_dir: str | None = None) -> None:
        """shm_dir: where FP32_SHM files are read (None: this client reads no shared memory)."""
        self.shm_dir = shm_dir
        self.held: WirePayload | None = None
        self._header: learner_pb2.WeightHeader | None = None
        self._skip_version = 0  # chunks of a rejected version still in flight
        self._buf = _EMPTY
        self._filled = 0
        self._hash: Any = None  # running digest of raw full payloads, updated as chunks arrive
        # receive, decoded patch body and payload buffers cycle through here: keep one spare of each
        self._pool = BufferPool(keep=3)
        self.chunk_bytes = 0  # data bytes of the last chunk fed (0 for a header or a skipped chunk)
        self._stream: _PatchStreamDecoder | None = None  # a streamed patch being applied

    @property
    def in_progress(self) -> bool:
        return self._header is not None

    @property
    def base_version(self) -> int:
        return self.held.version if self.held is not None else 0

    @property
    def base_digest(self) -> bytes:
        return self.held.digest if self.held is not None else b""

    def reset(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._pool.give(self._stream.out)  # a streamed patch that failed: its state buffer is free
        self._header, self._buf, self._filled, self._hash, self._stream = None, _EMPTY, 0, None, None

    def forget_base(self) -> None:
        if self.held is not None:
            self._pool.give(self.held.payload)  # reused once the set's tensors are gone
        self.held = None

    def feed(self, msg: learner_pb2.WeightMessage | RawChunk) -> WeightSet | None:
        self.chunk_bytes = 0
        raw = isinstance(msg, RawChunk)
        kind = "chunk" if raw else msg.WhichOneof("msg")
        chunk = msg if raw else msg.chunk
        if kind == "chunk" and self._header is None and chunk.version == self._skip_version != 0:
            return None  # the rest of a version already rejected
        try:
            if kind == "header":
                return self._on_header(msg.header)
            if kind == "chunk":
                return self._on_chunk(chunk)
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
            patch = header.weight_encoding in PATCHES
            wrong = held is None or held.version != header.base_version or not held.same_layout(header.tensors)
            if wrong or (patch and held is not None and held.digest != header.base_digest):
                have = f"v{held.version}" if held is not None else "none"
                raise WireError(
                    f"weight v{header.version}: delta against v{header.base_version}, this client holds {have}"
                )
        if header.weight_encoding == WE.WEIGHT_ENCODING_FP32_PATCH_STREAM_ZSTD:
            assert self.held is not None  # checked above
            self._filled = 0
            self._stream = _PatchStreamDecoder(self.held, header.tensors, self._pool.take(header.total_bytes))
            return None
        if header.weight_encoding == WE.WEIGHT_ENCODING_FP32_SHM:
            if self.shm_dir is None:
                raise WireError(f"weight v{header.version}: shared memory was not asked for")
            # one copy out of the file into a reused buffer; _finish checks the digest like any full set
            out = self._pool.take(header.total_bytes)
            self._buf = read_payload(self.shm_dir, header.shm_name, header.total_bytes, out)
            self._hash = None
            return self._finish()
        # Preallocated (the header passed the size limit): one copy per chunk, no regrowth; numpy for
        # huge pages (see pack_weights).
        self._buf, self._filled = self._pool.take(header.encoded_bytes), 0
        streaming = header.encoding == ENCODING_RAW and not header.base_version
        self._hash = _HASHERS[header.digest_kind][0]() if streaming else None
        return self._finish() if header.encoded_bytes == 0 else None

    def _on_chunk(self, chunk: learner_pb2.WeightChunk | RawChunk) -> WeightSet | None:
        h = self._header
        if h is None:
            raise WireError("weight chunk without a header")
        if chunk.version != h.version:
            raise WireError(f"weight chunk of v{chunk.version} inside v{h.version}")
        start, data = self._filled, chunk.data  # read once: each read copies the bytes (upb)
        self.chunk_bytes = len(data)
        if chunk.offset != start:
            raise WireError(f"weight chunk at offset {chunk.offset}, expected {start}")
        if self._stream is not None:
            return self._on_stream_chunk(h, data, chunk.last, chunk.digest)
        if chunk.last or chunk.digest:
            raise WireError("a last chunk or a chunk digest outside a streamed payload")
        if not data:
            raise WireError("empty weight chunk")
        if start + len(data) > h.encoded_bytes:
            raise WireError(f"weight chunks exceed the declared {h.encoded_bytes} encoded bytes")
        self._buf[start : start + len(data)] = np.frombuffer(data, dtype=np.uint8)
        self._filled += len(data)
        if self._hash is not None:
            self._hash.update(data)
        return self._finish() if self._filled == h.encoded_bytes else None

    def _on_stream_chunk(self, h: learner_pb2.WeightHeader, data: Any, last: bool, digest: bytes) -> WeightSet | None:
        assert self._stream is not None
        if not data and not last:
            raise WireError("empty weight chunk")
        if self._filled + len(data) > MAX_WEIGHT_BYTES:
            raise WireError(f"weight v{h.version}: streamed patch exceeds {MAX_WEIGHT_BYTES} bytes")
        if data:
            self._stream.feed(data)
            self._filled += len(data)
        if not last:
            return None
        if not digest:
            raise WireError(f"weight v{h.version}: the sender gave up on this patch (non-finite weights?)")
        h.digest, h.encoded_bytes = digest, self._filled  # what the header could not carry
        return self._finish()

    def _finish(self) -> WeightSet:
        h = self._header
        assert h is not None
        patch = h.weight_encoding == WE.WEIGHT_ENCODING_FP32_PATCH_ZSTD
        if self._stream is not None:
            raw, self._stream = self._stream.finish(), None  # applied slice by slice as it arrived
        elif patch:
            assert self.held is not None  # checked on the header
            body = self._decode(h, self._buf, patch_body_bytes(h.tensors))
            raw = apply_patch(self.held, h.tensors, body, self._pool)
            self._pool.give(body)
        else:
            raw = self._decode(h, self._buf)  # the buffer is handed over, not copied: reset() starts a new one
        if h.encoding != ENCODING_RAW:
            self._pool.give(self._buf)
        if h.base_version and h.weight_encoding not in PATCHES:
            assert self.held is not None  # checked on the header
            np.bitwise_xor(raw, self.held.payload, out=raw)  # raw is ours (received or decoded here)
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
        if self.held is not None:
            self._pool.give(self.held.payload)  # reused once the old set's tensors are gone
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

    def _decode(self, h: learner_pb2.WeightHeader, data: np.ndarray, size: int = -1) -> np.ndarray:
        """The decoded bytes: `size` of them (default: the header's total_bytes), in a reused buffer."""
        size = h.total_bytes if size < 0 else size
        if h.encoding == ENCODING_RAW:
            return data
        import zstandard

        out = self._pool.take(size)  # writable, so tensors can be views
        filled = 0
        try:
            with zstandard.ZstdDecompressor().stream_reader(data) as reader:
                while filled < size and (got := reader.readinto(out[filled:])):
                    filled += got
                extra = reader.read(1)
        except zstandard.ZstdError as exc:
            raise WireError(f"weight v{h.version}: bad zstd payload: {exc}") from exc
        if filled != size or extra:
            raise WireError(f"weight v{h.version}: decoded {filled + len(extra)}+ bytes, expected {size}")
        return out
