"""The hot tier: recent transitions in RAM as contiguous columns, laid out for sampling.

One HotGroup per observation layout (robots with the same spec share one). Observations live once
in a ring of frames (one row per observation, uint8 images stay uint8); a transition row names its
observation frame and its next-observation frame by sequence number, so next_obs is never stored
twice. Both rings overwrite their oldest rows; a transition is "hot" while its row still belongs to
it and both its frames are still in the frame ring. Everything else is read from LMDB on demand.
"""

from __future__ import annotations

import functools
import logging
import math
import mmap
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import prometheus_client

from user import wire
from user.v1 import tensor_pb2 as tpb

Feature = tuple[str, np.dtype, tuple[int, ...]]
Layout = tuple[tuple[Feature, ...], tuple[np.dtype, tuple[int, ...]]]
_ROW_OVERHEAD = 3 * 8  # owner tid, older frame seq, frame rows (2 x int32)
ENCODED_GUESS = 8  # an encoded camera frame is assumed 1/8 of its raw size when sizing the rings
_BLOB_OVERHEAD = 33  # a Python bytes object's header
_DECODE_MIN = 16  # fewer frames than this are decoded in the calling thread
_pool: ThreadPoolExecutor | None = None
_WORKERS = 2
log = logging.getLogger(__name__)
UNDECODABLE = prometheus_client.Counter(
    "user_replay_undecodable_frames_total", "Stored JPEG/PNG frames that did not decode when read (read as zeros)"
)


def decode_image(tensor: tpb.Tensor) -> np.ndarray:
    """A stored JPEG/PNG frame, or zeros of its shape (counted) if it does not decode. Insert decodes every frame
    (wire.check_image), so this is a defence (e.g. a store from an older build): one bad frame must not fail
    every batch that draws it."""
    try:
        return wire.from_tensor(tensor)
    except wire.WireError as exc:
        UNDECODABLE.inc()
        log.warning("stored camera frame does not decode; read as zeros", extra={"error": str(exc)})
        return np.zeros(tuple(int(d) for d in tensor.shape), np.uint8)


@functools.cache
def single_threaded_cv2() -> None:
    """Replay decodes and checks frames on its own threads (one frame per thread), so cv2 runs single-threaded
    inside: its own thread pool only added overhead to 128x128 frames here (98 -> 59 ms for 450 decodes
    measured serially; a 1/8-scale check ~47 -> ~34 us)."""
    import cv2

    cv2.setNumThreads(1)


def _decoder_pool() -> ThreadPoolExecutor:
    """cv2 releases the GIL while it decodes: a batch's JPEG/PNG frames are decoded on a few threads."""
    global _pool
    if _pool is None:
        single_threaded_cv2()
        _pool = ThreadPoolExecutor(max_workers=_WORKERS, thread_name_prefix="replay-decode")
    return _pool


def decode_blobs(blobs: np.ndarray, encs: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Stored frames (bytes, each RAW, JPEG or PNG as `encs` says) decoded into one uint8 array, on the decoder
    threads; a frame that does not decode reads as zeros (counted)."""
    out = np.empty((len(blobs), *shape), np.uint8)

    import cv2

    flag = cv2.IMREAD_GRAYSCALE if len(shape) == 2 or shape[-1] == 1 else cv2.IMREAD_COLOR

    def run(lo: int, hi: int) -> None:
        for i in range(lo, hi):
            enc = encs[i]
            if enc == tpb.ENCODING_RAW:
                out[i] = np.frombuffer(blobs[i], np.uint8).reshape(shape)
                continue
            try:  # validated when it was stored
                if enc == tpb.ENCODING_JPEG:
                    wire.decode_jpeg(blobs[i], shape, out[i])
                    continue
                img = cv2.imdecode(np.frombuffer(blobs[i], np.uint8), flag)
                if img is None or img.size != out[i].size:
                    raise wire.WireError("undecodable PNG")
                out[i] = img.reshape(shape)
            except wire.WireError:  # the checked decoder says why, or zeros
                t = tpb.Tensor(dtype=tpb.DTYPE_UINT8, shape=shape, data=blobs[i], encoding=int(enc))
                out[i] = decode_image(t).reshape(shape)

    n = len(blobs)
    if n < _DECODE_MIN:
        run(0, n)
        return out
    pool = _decoder_pool()
    step = -(-n // _WORKERS)
    for f in [pool.submit(run, lo, min(n, lo + step)) for lo in range(0, n, step)]:
        f.result()
    return out


def frame_nbytes(layout: Layout) -> int:
    return sum(np.dtype(dt).itemsize * math.prod(sh) for _, dt, sh in layout[0])


class HotGroup:
    """Frames and transitions of one layout, each a ring of `capacity` rows (pages are touched lazily)."""

    def __init__(
        self,
        layout: Layout,
        max_bytes: int,
        encoded: frozenset[str] = frozenset(),
        max_rows: int | None = None,
        decoded_bytes: int = 0,
    ) -> None:
        features, (act_dtype, act_shape) = layout
        self.layout = layout
        # camera features kept as their stored JPEG/PNG bytes (decoded when sampled): RAM per frame ~1/10
        self.encoded = {name: shape for name, dtype, shape in features if name in encoded and dtype == np.uint8}
        raw = {name: np.dtype(dtype).itemsize * math.prod(shape) for name, dtype, shape in features}
        self.frame_bytes = sum(b for n, b in raw.items() if n not in self.encoded)
        guess = self.frame_bytes + sum(raw[n] // ENCODED_GUESS + _BLOB_OVERHEAD for n in self.encoded)
        self.row_bytes = np.dtype(act_dtype).itemsize * math.prod(act_shape) + _ROW_OVERHEAD
        self.capacity = max(16, int(max_bytes // max(1.0, guess * 9 / 8 + self.row_bytes)))
        if max_rows is not None:  # no more rows than the buffer's capacity can hold transitions
            self.capacity = max(16, min(self.capacity, max_rows))
        cap = self.capacity
        # frames: one per transition plus each episode's final observation, so a little more room
        self.frame_capacity = cap + cap // 8 + 16
        self.frames = {
            name: np.empty((self.frame_capacity, *shape), dtype)
            for name, dtype, shape in features
            if name not in self.encoded
        }
        self.blobs = {name: np.full(self.frame_capacity, b"", object) for name in self.encoded}
        self.blob_enc = {name: np.zeros(self.frame_capacity, np.uint8) for name in self.encoded}
        self.blob_bytes = 0
        # the newest encoded frames also as uint8, once a sample has decoded them (a direct-mapped window: frame
        # seq s lives in slot s % decoded_capacity, tagged s), so draws from the recent window need no decode
        raw_encoded = sum(raw[n] for n in self.encoded)
        dcap = int(decoded_bytes // raw_encoded) if raw_encoded else 0
        self.decoded_capacity = min(dcap, self.frame_capacity) if dcap >= 16 else 0
        self.decoded = {name: np.empty((self.decoded_capacity, *self.encoded[name]), np.uint8) for name in self.encoded}
        self.decoded_tag = {name: np.full(self.decoded_capacity, -1, np.int64) for name in self.encoded}
        self.decoded_bytes = 0  # of slots ever filled (their pages are touched)
        self.decoded_hits = self.decoded_misses = 0  # encoded frames read from the window / decoded
        # the same memory as rows of bytes, so a RAW wire tensor is copied in without decoding
        self._bytes = {name: col.reshape(self.frame_capacity, -1).view(np.uint8) for name, col in self.frames.items()}
        self._codes = {name: wire.dtype_to_proto(dtype) for name, dtype, _ in features}
        self._shapes = {name: list(shape) for name, _, shape in features}
        self.frames_written = 0
        # transition rows, plus one sentinel row at the end that add_many never writes: a hot_row of -1 (never
        # hot) reads it, and its tid (-1) matches no transition, so valid() needs no separate `rows >= 0` test
        self.t_tid = np.full(cap + 1, -1, np.int64)
        self.t_first = np.zeros(cap + 1, np.int64)  # the older of its two frames' sequence numbers
        # ring rows (seq % frame_capacity) of its observation [0] and next observation [1]: one gather gives both
        self.t_rows = np.zeros((2, cap + 1), np.int32 if self.frame_capacity < 2**31 else np.int64)
        self.action = np.empty((cap, *act_shape), act_dtype)
        self.rows_written = 0

    def prefault(self) -> None:
        """Touch every page of the fixed-size columns now: the ring then costs its whole RSS from its first row
        instead of growing into it over hours, so a long-running replay's memory is flat and what an operator
        budgets (np.empty/np.zeros pages are only mapped when first written). Encoded frames' bytes still grow."""
        columns = [*self.frames.values(), *self.decoded.values(), self.t_first, self.t_rows, self.action]
        columns += list(self.blob_enc.values())
        for column in columns:
            column.reshape(-1).view(np.uint8)[:: mmap.PAGESIZE] = 0  # one write per page maps it

    def write_frame(self, arrays: dict[str, np.ndarray]) -> int:
        """Copy one observation in; returns its sequence number."""
        seq = self.frames_written
        row = seq % self.frame_capacity
        for name, column in self.frames.items():
            column[row] = arrays[name]
        for name in self.encoded:
            self._put_blob(name, row, np.ascontiguousarray(arrays[name], np.uint8).tobytes(), tpb.ENCODING_RAW)
        self.frames_written = seq + 1
        return seq

    def _put_blob(self, name: str, row: int, data: bytes, encoding: int) -> None:
        self.blob_bytes += len(data) - len(self.blobs[name][row])
        self.blobs[name][row] = data
        self.blob_enc[name][row] = encoding

    def write_tensors(self, tmap: tpb.TensorMap) -> int:
        """Copy one wire observation in (RAW bytes as they are); ValueError/KeyError if it has another layout."""
        tensors = tmap.tensors
        if len(tensors) != len(self._codes):
            raise ValueError("observation has other features than this group")
        seq = self.frames_written
        row = seq % self.frame_capacity
        for name in self.encoded:
            t = tensors[name]
            if t.dtype != self._codes[name] or t.shape != self._shapes[name]:
                raise ValueError(f"{name}: dtype or shape differs from this group")
        for name in self.encoded:
            t = tensors[name]
            self._put_blob(name, row, t.data, t.encoding)
        for name, rows in self._bytes.items():
            t = tensors[name]
            if t.dtype != self._codes[name] or t.shape != self._shapes[name]:
                raise ValueError(f"{name}: dtype or shape differs from this group")
            if t.encoding == tpb.ENCODING_RAW and len(t.data) == rows.shape[1]:
                rows[row] = np.frombuffer(t.data, np.uint8)
            else:
                self.frames[name][row] = decode_image(t)  # JPEG/PNG from the edge (dtype and shape checked above)
        self.frames_written = seq + 1
        return seq

    def write_many(self, tmaps: list[tpb.TensorMap]) -> np.ndarray | None:
        """Copy several wire observations in at once; their sequence numbers, or None (nothing written)
        when one is not plain RAW of this layout (then write_tensors each)."""
        k = len(tmaps)
        cols: dict[str, list[bytes]] = {name: [] for name in self._bytes}
        blobs: dict[str, list[tuple[bytes, int]]] = {name: [] for name in self.encoded}
        for tmap in tmaps:
            tensors = tmap.tensors
            if len(tensors) != len(self._codes):
                return None
            for name, parts in blobs.items():
                t = tensors.get(name)
                if t is None or t.dtype != self._codes[name] or t.shape != self._shapes[name]:
                    return None
                parts.append((t.data, t.encoding))
            for name, rows in self._bytes.items():
                t = tensors.get(name)
                if t is None or t.dtype != self._codes[name] or t.encoding != tpb.ENCODING_RAW:
                    return None
                if t.shape != self._shapes[name]:
                    return None
                data = t.data
                if len(data) != rows.shape[1]:
                    return None
                cols[name].append(data)
        seqs = self.frames_written + np.arange(k)
        at = seqs % self.frame_capacity
        for name, items in blobs.items():
            for row, (data, enc) in zip(at.tolist(), items, strict=True):
                self._put_blob(name, row, data, enc)
        for name, parts in cols.items():
            rows = self._bytes[name]
            if rows.shape[1] >= 4096:  # camera frames: one copy each, straight into the ring
                for row, data in zip(at.tolist(), parts, strict=True):
                    rows[row] = np.frombuffer(data, np.uint8)
            else:  # small features: one joined copy beats a numpy call per row
                rows[at] = np.frombuffer(b"".join(parts), np.uint8).reshape(k, -1)
        self.frames_written += k
        return seqs

    def actions_of(self, tensors: list[tpb.Tensor]) -> np.ndarray | None:
        """RAW wire actions of this layout as one (k, ...) array without a copy per action; None if one is not."""
        dtype, shape = self.layout[1]
        code, nbytes = wire.dtype_to_proto(dtype), self.action.itemsize * math.prod(shape)
        parts = []
        for t in tensors:
            if t.encoding != tpb.ENCODING_RAW or t.dtype != code or len(t.data) != nbytes:
                return None
            parts.append(t.data)
        return np.frombuffer(b"".join(parts), dtype).reshape(len(parts), *shape)

    def add_many(
        self, tids: list[int], obs_seqs: list[int], next_seqs: list[int], actions: list[np.ndarray] | np.ndarray
    ) -> np.ndarray:
        """Transitions in one go; returns their rows."""
        k = len(tids)
        rows = (self.rows_written + np.arange(k)) % self.capacity
        obs, nxt = np.asarray(obs_seqs, np.int64), np.asarray(next_seqs, np.int64)
        self.t_first[rows] = np.minimum(obs, nxt)
        self.t_rows[0, rows] = obs % self.frame_capacity
        self.t_rows[1, rows] = nxt % self.frame_capacity
        self.t_tid[rows] = tids
        # one (k, ...) array as indexing gives it: assigned whole (np.stack would walk it row by row)
        self.action[rows] = actions if isinstance(actions, np.ndarray) else np.stack(actions)
        self.rows_written += k
        return rows

    def valid(self, rows: np.ndarray, tids: np.ndarray) -> np.ndarray:
        """Which (row, tid) pairs are still hot: the row still holds the tid and both its frames are in the ring
        (a row of -1 reads the sentinel row, which holds no tid)."""
        ok = self.t_tid[rows] == tids
        ok &= self.t_first[rows] >= self.frames_written - self.frame_capacity
        return ok

    def frame_rows(self, rows: np.ndarray, which: str) -> np.ndarray:
        """Ring rows of the observation ("obs") or next observation ("next") of transition rows."""
        return self.t_rows[0 if which == "obs" else 1].take(rows)

    def observations(self, rows: np.ndarray, which: str, skip: frozenset[str] = frozenset()) -> dict[str, np.ndarray]:
        """The observations of transition rows; encoded features in `skip` are left out (the caller takes their
        bytes)."""
        at = self.frame_rows(rows, which)
        # take(axis=0) copies whole rows; fancy indexing of a 2-D+ array walks them element by element (~3x slower)
        out = {name: column.take(at, axis=0) for name, column in self.frames.items()}
        for name in self.encoded:
            if name not in skip:
                out[name] = self._decode(name, at)
        return out

    def observations_pair(
        self, rows: np.ndarray, next_rows: np.ndarray, keep_encoded: bool = False
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """observations(rows, "obs") and observations(next_rows, "next"), decoding each encoded frame once
        (a batch's next observations are often other draws' observations). keep_encoded: encoded features come as
        wire.EncodedFrames (their bytes as kept) where all their frames share one image encoding."""
        if rows is next_rows:  # one-step transitions: both frame rows of each in one gather, both frames in one
            at = self.t_rows.take(rows, axis=1)
            a, b = at[0], at[1]
            pairs = {name: column.take(at, axis=0) for name, column in self.frames.items()}  # (2, k, ...)
            obs: dict[str, Any] = {name: pair[0] for name, pair in pairs.items()}
            nxt: dict[str, Any] = {name: pair[1] for name, pair in pairs.items()}
        else:
            a, b = self.t_rows[0].take(rows), self.t_rows[1].take(next_rows)
            obs = {name: column.take(a, axis=0) for name, column in self.frames.items()}
            nxt = {name: column.take(b, axis=0) for name, column in self.frames.items()}
        names = list(self.encoded)
        if keep_encoded:
            for name in list(names):
                kept = self.encoded_frames(name, np.concatenate([a, b]))
                if kept is not None:
                    obs[name] = wire.EncodedFrames(kept.blobs[: len(a)], kept.encoding, kept.image_shape)
                    nxt[name] = wire.EncodedFrames(kept.blobs[len(a) :], kept.encoding, kept.image_shape)
                    names.remove(name)
        if names:
            uniq, inv = np.unique(np.concatenate([a, b]), return_inverse=True)
            for name in names:
                frames = self._decode(name, uniq)
                obs[name], nxt[name] = frames[inv[: len(a)]], frames[inv[len(a) :]]
        return obs, nxt

    def _decode(self, name: str, at: np.ndarray) -> np.ndarray:
        """Frames of an encoded feature at ring rows, decoded into one array (on the decoder threads); frames of the
        decoded window are copied from it, and decoded frames that belong to it are kept there."""
        shape = self.encoded[name]
        dcap = self.decoded_capacity
        if not dcap:
            return self._decode_blobs(name, at)
        newest = self.frames_written - 1
        seqs = newest - (newest - at) % self.frame_capacity  # the frame each ring row holds now
        slots = seqs % dcap
        hit = self.decoded_tag[name].take(slots) == seqs
        out = np.empty((len(at), *shape), np.uint8)
        out[hit] = self.decoded[name].take(slots[hit], axis=0)
        miss = np.flatnonzero(~hit)
        self.decoded_hits += len(at) - len(miss)
        self.decoded_misses += len(miss)
        if len(miss):
            frames = self._decode_blobs(name, at[miss])
            out[miss] = frames
            keep = seqs[miss] > newest - dcap  # only the newest dcap frames enter the window
            if keep.any():
                kept_slots = slots[miss][keep]
                tags = self.decoded_tag[name]
                self.decoded_bytes += np.unique(kept_slots[tags[kept_slots] < 0]).size * math.prod(shape)
                self.decoded[name][kept_slots] = frames[keep]
                tags[kept_slots] = seqs[miss][keep]
        return out

    def _decode_blobs(self, name: str, at: np.ndarray) -> np.ndarray:
        """Frames of an encoded feature at ring rows, each decoded from its bytes (on the decoder threads)."""
        return decode_blobs(self.blobs[name][at], self.blob_enc[name][at], self.encoded[name])

    def encoded_frames(self, name: str, at: np.ndarray) -> wire.EncodedFrames | None:
        """Frames of an encoded feature at ring rows as they are kept, when all have one image encoding (else None:
        decode them)."""
        encs = self.blob_enc[name][at]
        enc = int(encs[0]) if len(encs) else tpb.ENCODING_RAW
        if enc == tpb.ENCODING_RAW or not (encs == enc).all():
            return None
        return wire.EncodedFrames(self.blobs[name][at], enc, self.encoded[name])

    def resident_bytes(self) -> int:
        frames = min(self.frames_written, self.frame_capacity) * self.frame_bytes
        blobs = self.blob_bytes + len(self.encoded) * min(self.frames_written, self.frame_capacity) * _BLOB_OVERHEAD
        return frames + blobs + self.decoded_bytes + min(self.rows_written, self.capacity) * self.row_bytes

    def hot_transitions(self) -> int:
        return min(self.rows_written, self.capacity)
