"""Hypothesis strategies that build any message the protos can express, from their descriptors.

`messages(Type)` draws every field kind with its full range: uint64 up to 2**64-1, NaN and Inf floats,
unknown enum numbers (proto3 enums are open), oneofs, maps, repeated and nested messages.
`near(valid)` merges such a random message into a valid one, so checks deep inside a handler are reached
too (a purely random step never gets past "unknown robot").
"""

from __future__ import annotations

from typing import Any

from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import Message
from hypothesis import strategies as st

F = FieldDescriptor
_INTS = {
    F.TYPE_INT32: (-(2**31), 2**31 - 1),
    F.TYPE_SINT32: (-(2**31), 2**31 - 1),
    F.TYPE_SFIXED32: (-(2**31), 2**31 - 1),
    F.TYPE_UINT32: (0, 2**32 - 1),
    F.TYPE_FIXED32: (0, 2**32 - 1),
    F.TYPE_INT64: (-(2**63), 2**63 - 1),
    F.TYPE_SINT64: (-(2**63), 2**63 - 1),
    F.TYPE_SFIXED64: (-(2**63), 2**63 - 1),
    F.TYPE_UINT64: (0, 2**64 - 1),
    F.TYPE_FIXED64: (0, 2**64 - 1),
}
MAX_REPEATED = 4


def _int(lo: int, hi: int) -> st.SearchStrategy[int]:
    # Edges and small values find more than uniform draws over 2**64.
    return st.one_of(
        st.sampled_from(sorted({lo, hi, 0 if lo <= 0 else lo, 1, hi - 1})),
        st.integers(-3, 70).filter(lambda v: lo <= v <= hi),
        st.integers(lo, hi),
    )


def scalar(field: FieldDescriptor) -> st.SearchStrategy[Any]:
    t = field.type
    if t in _INTS:
        return _int(*_INTS[t])
    if t == F.TYPE_BOOL:
        return st.booleans()
    if t == F.TYPE_DOUBLE:
        return st.floats(allow_nan=True, allow_infinity=True)
    if t == F.TYPE_FLOAT:
        return st.floats(width=32, allow_nan=True, allow_infinity=True)
    if t == F.TYPE_STRING:
        return st.one_of(st.text(max_size=12), st.sampled_from(["", "arm-0", "a/b", "x\n", "-" * 300, "\0"]))
    if t == F.TYPE_BYTES:
        return st.binary(max_size=64)
    if t == F.TYPE_ENUM:
        declared = [v.number for v in field.enum_type.values]
        return st.one_of(st.sampled_from(declared), st.integers(-(2**31), 2**31 - 1))
    raise TypeError(f"unhandled field type {t}")


def _is_map(field: FieldDescriptor) -> bool:
    return field.type == F.TYPE_MESSAGE and field.message_type.GetOptions().map_entry


@st.composite
def _fill(draw: st.DrawFn, desc: Descriptor, cls: type[Message], depth: int) -> Message:
    msg = cls()
    chosen_oneof = {o.name: draw(st.sampled_from([None, *o.fields])) for o in desc.oneofs}
    for field in desc.fields:
        oneof = field.containing_oneof
        if oneof is not None and chosen_oneof[oneof.name] is not field:
            continue
        if oneof is None and not draw(st.booleans()):
            continue  # leave unset
        is_repeated = field.is_repeated
        if _is_map(field):
            key_f, val_f = field.message_type.fields_by_name["key"], field.message_type.fields_by_name["value"]
            for _ in range(draw(st.integers(0, MAX_REPEATED))):
                key = draw(scalar(key_f))
                if val_f.type == F.TYPE_MESSAGE:
                    if depth <= 0:
                        continue
                    getattr(msg, field.name)[key].CopyFrom(draw(_sub(val_f, depth - 1)))
                else:
                    getattr(msg, field.name)[key] = draw(scalar(val_f))
        elif field.type == F.TYPE_MESSAGE:
            if depth <= 0:
                continue
            if is_repeated:
                getattr(msg, field.name).extend(draw(st.lists(_sub(field, depth - 1), max_size=MAX_REPEATED)))
            else:
                getattr(msg, field.name).CopyFrom(draw(_sub(field, depth - 1)))
        elif is_repeated:
            getattr(msg, field.name).extend(draw(st.lists(scalar(field), max_size=MAX_REPEATED)))
        else:
            setattr(msg, field.name, draw(scalar(field)))
    return msg


def _sub(field: FieldDescriptor, depth: int) -> st.SearchStrategy[Message]:
    from google.protobuf import message_factory

    cls = message_factory.GetMessageClass(field.message_type)
    return _fill(field.message_type, cls, depth)


def messages(cls: type[Message], depth: int = 5) -> st.SearchStrategy[Message]:
    """Any message of type `cls` (nested up to `depth`)."""
    return _fill(cls.DESCRIPTOR, cls, depth)


def near(valid: Message, depth: int = 5) -> st.SearchStrategy[Message]:
    """`valid` with a random message of its type merged in: mostly-right input with a few wrong fields."""

    def merge(noise: Message) -> Message:
        out = type(valid)()
        out.CopyFrom(valid)
        out.MergeFrom(noise)
        return out

    return st.one_of(st.just(valid), messages(type(valid), depth).map(merge))


def any_or_near(valid: Message, depth: int = 5) -> st.SearchStrategy[Message]:
    return st.one_of(messages(type(valid), depth), near(valid, depth))
