"""Where a stored Step's tensors lie inside its serialized bytes, without parsing it into objects.

The sampler's miss path reads steps from LMDB only for their observation, action and final observation.
Parsing a ~100 kB camera step with protobuf copies it (LMDB -> bytes -> message -> `Tensor.data` bytes ->
array) before the frame reaches the batch. Here the protobuf wire format (varints and length-delimited
fields, https://protobuf.dev/programming-guides/encoding/) is walked over the LMDB page itself
(a zero-copy buffer) to find each tensor's dtype, shape, encoding and data span, so a frame is copied once,
from the page into the batch column. Only steps this process wrote are read here (validated on insert);
anything unexpected raises `Unexpected` (a truncated varint: `WireError`), and the caller falls back
to the protobuf parse.
"""

from __future__ import annotations

from typing import NamedTuple

from user.wire import read_varint

STEP_OBSERVATION, STEP_ACTION, STEP_FINAL = 4, 5, 13  # user.v1.Step field numbers
TENSOR_DTYPE, TENSOR_SHAPE, TENSOR_DATA, TENSOR_ENCODING = 1, 2, 3, 4  # user.v1.Tensor
VARINT, I64, LEN, I32 = 0, 1, 2, 5  # wire types


class Unexpected(ValueError):
    """Bytes this walker does not handle (the caller parses them with protobuf instead)."""


class Span(NamedTuple):
    """A tensor inside the buffer: its data is buf[offset : offset + size]."""

    dtype: int
    shape: tuple[int, ...]
    encoding: int
    offset: int
    size: int


class StepSpans(NamedTuple):
    observation: dict[str, Span]
    action: Span | None
    final: dict[str, Span] | None  # None: the step has no final_observation


def _fields(buf: memoryview, pos: int, end: int) -> list[tuple[int, int, int, int]]:
    """(field number, wire type, value or start of a LEN field, its stop) of the fields in [pos, end)."""
    out = []
    while pos < end:
        tag, pos = read_varint(buf, pos)
        kind = tag & 7
        if kind == VARINT:
            value, pos = read_varint(buf, pos)
            out.append((tag >> 3, kind, value, 0))
        elif kind == LEN:
            size, pos = read_varint(buf, pos)
            out.append((tag >> 3, kind, pos, pos + size))
            pos += size
        elif kind == I64:
            pos += 8
        elif kind == I32:
            pos += 4
        else:
            raise Unexpected(f"wire type {kind}")
    if pos != end:
        raise Unexpected("field runs past its message")
    return out


def _tensor(buf: memoryview, pos: int, end: int) -> Span:
    dtype = encoding = 0
    shape: list[int] = []
    start = stop = end
    for field, kind, value, until in _fields(buf, pos, end):
        if field == TENSOR_DTYPE and kind == VARINT:
            dtype = value
        elif field == TENSOR_ENCODING and kind == VARINT:
            encoding = value
        elif field == TENSOR_DATA and kind == LEN:
            start, stop = value, until
        elif field == TENSOR_SHAPE and kind == LEN:  # packed (proto3's default)
            at = value
            while at < until:
                dim, at = read_varint(buf, at)
                shape.append(dim)
        elif field == TENSOR_SHAPE and kind == VARINT:
            shape.append(value)
    if any(d >= 1 << 63 for d in shape):
        raise Unexpected("negative dimension")
    return Span(dtype, tuple(shape), encoding, start, stop - start)


def _tensor_map(buf: memoryview, pos: int, end: int) -> dict[str, Span]:
    out: dict[str, Span] = {}
    for field, kind, at, until in _fields(buf, pos, end):
        if field != 1 or kind != LEN:
            continue
        name, tensor = None, None
        for f, k, v, u in _fields(buf, at, until):
            if f == 1 and k == LEN:
                name = bytes(buf[v:u]).decode()
            elif f == 2 and k == LEN:
                tensor = _tensor(buf, v, u)
        if name is None or name in out:
            raise Unexpected("map entry without a key, or a key twice")
        out[name] = tensor if tensor is not None else Span(0, (), 0, 0, 0)
    return out


def step_spans(buf: memoryview) -> StepSpans:
    """The observation, action and final observation tensors of a serialized user.v1.Step."""
    obs: dict[str, Span] | None = None
    final: dict[str, Span] | None = None
    action: Span | None = None
    for field, kind, at, until in _fields(buf, 0, len(buf)):
        if kind != LEN:
            continue
        if field == STEP_OBSERVATION:
            if obs is not None:
                raise Unexpected("observation twice")  # protobuf would merge them
            obs = _tensor_map(buf, at, until)
        elif field == STEP_ACTION:
            if action is not None:
                raise Unexpected("action twice")
            action = _tensor(buf, at, until)
        elif field == STEP_FINAL:
            if final is not None:
                raise Unexpected("final_observation twice")
            final = _tensor_map(buf, at, until)
    return StepSpans(obs or {}, action, final)
