"""rosbags dataclasses <-> rclpy messages, for any message type.

rosbags deserialises a bag into plain dataclasses (numpy arrays for numeric
arrays); rclpy publishes its own generated classes (``array.array`` for
numeric sequences, numpy for fixed-size numeric arrays, ``bytes`` for the
``byte`` type). This module converts between the two, recursively, from the
rclpy class's own field description (``SLOT_TYPES``), so it works for every
type both sides know: sensor_msgs, geometry_msgs, soma_msgs, ...

Per type, the conversion is planned once (a list of per-field converters) and
cached. Numeric arrays are copied as whole buffers (a 640x480 rgb8 image is
one memcpy each way), never element by element.

- :func:`to_rclpy`: rosbags message -> rclpy message (for publishing a bag).
- :func:`to_rosbags`: rclpy message -> rosbags message (for writing a bag).
- :func:`serialize_rclpy`: rclpy message -> CDR bytes as a rosbag2 stores them.
- :func:`rclpy_class`, :func:`msgtype_of`: ``pkg/msg/Name`` <-> rclpy class.
"""

from __future__ import annotations

import array
import importlib
import threading
from typing import Any, Callable, Optional

import numpy as np
from rosidl_parser import definition as idl

__all__ = [
    "MessageTypeError",
    "msgtype_of",
    "rclpy_class",
    "serialize_rclpy",
    "to_rclpy",
    "to_rosbags",
]


class MessageTypeError(LookupError):
    """A message type that rclpy or the rosbags typestore does not know."""


#: rosidl basic type -> (array.array typecode, numpy dtype) for numeric fields.
_NUMERIC: dict[str, tuple[str, type]] = {
    "float": ("f", np.float32),
    "double": ("d", np.float64),
    "int8": ("b", np.int8),
    "uint8": ("B", np.uint8),
    "char": ("B", np.uint8),  # msg ``char`` is uint8 in ROS 2
    "int16": ("h", np.int16),
    "uint16": ("H", np.uint16),
    "int32": ("i", np.int32),
    "uint32": ("I", np.uint32),
    "int64": ("q", np.int64),
    "uint64": ("Q", np.uint64),
}
_FLOATS = {"float", "double"}

Converter = Callable[[Any], Any]

_lock = threading.Lock()
_to_rclpy_plans: dict[type, list[tuple[str, Converter]]] = {}
_to_rosbags_plans: dict[tuple[type, int], list[tuple[str, Converter]]] = {}


# --------------------------------------------------------------------- types
def rclpy_class(msgtype: str) -> type:
    """The rclpy message class of ``pkg/msg/Name`` (MessageTypeError if not importable)."""
    parts = msgtype.split("/")
    if len(parts) == 2:  # tolerate the short ``pkg/Name`` form
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise MessageTypeError(f"not a message type name: {msgtype!r} (expected pkg/msg/Name)")
    pkg, _, name = parts
    try:
        module = importlib.import_module(f"{pkg}.msg")
    except ImportError:
        raise MessageTypeError(
            f"message type {msgtype} is not available to rclpy: no Python package '{pkg}' (build or install it)"
        ) from None
    cls = getattr(module, name, None)
    if cls is None or not hasattr(cls, "SLOT_TYPES"):
        raise MessageTypeError(f"message type {msgtype} is not available to rclpy: '{pkg}.msg' has no '{name}'")
    return cls


def msgtype_of(cls_or_msg: Any) -> str:
    """``pkg/msg/Name`` of an rclpy message class or instance."""
    cls = cls_or_msg if isinstance(cls_or_msg, type) else type(cls_or_msg)
    pkg = cls.__module__.split(".")[0]
    return f"{pkg}/msg/{cls.__name__}"


def _namespaced_name(t: idl.NamespacedType) -> str:
    return "/".join([*t.namespaces, t.name])


def _fields(cls: type) -> list[tuple[str, Any]]:
    names = list(cls.get_fields_and_field_types().keys())
    slots = list(cls.SLOT_TYPES)
    if len(names) != len(slots):  # pragma: no cover - generated code invariant
        raise MessageTypeError(f"{msgtype_of(cls)}: field names and SLOT_TYPES differ in length")
    return list(zip(names, slots))


# ------------------------------------------------------- rosbags -> rclpy
def _octets_to_rclpy(v: Any) -> list[bytes]:
    raw = np.asarray(v).astype(np.uint8, copy=False).tobytes()
    return [raw[i:i + 1] for i in range(len(raw))]


def _scalar_to_rclpy(typename: str) -> Converter:
    if typename == "boolean":
        return bool
    if typename == "octet":
        return lambda v: bytes((int(v) & 0xFF,))
    if typename in _FLOATS:
        return float
    if typename in _NUMERIC:
        return int
    raise MessageTypeError(f"unsupported basic type {typename!r}")


def _numeric_sequence_to_rclpy(typecode: str, dtype: type) -> Converter:
    def convert(v: Any) -> array.array:
        out = array.array(typecode)
        if isinstance(v, (bytes, bytearray, memoryview)) and typecode == "B":
            out.frombytes(v)
        else:
            out.frombytes(np.ascontiguousarray(v, dtype=dtype).reshape(-1).view(np.uint8))
        return out

    return convert


def _value_to_rclpy(slot: Any) -> Converter:
    if isinstance(slot, idl.NamespacedType):
        cls = rclpy_class(_namespaced_name(slot))
        return lambda v: _to_rclpy_as(v, cls)
    if isinstance(slot, (idl.AbstractString, idl.AbstractWString)):
        return str
    if isinstance(slot, idl.BasicType):
        return _scalar_to_rclpy(slot.typename)
    if isinstance(slot, idl.AbstractNestedType):
        vt = slot.value_type
        if isinstance(vt, idl.NamespacedType):
            cls = rclpy_class(_namespaced_name(vt))
            return lambda v: [_to_rclpy_as(x, cls) for x in v]
        if isinstance(vt, (idl.AbstractString, idl.AbstractWString)):
            return lambda v: [str(x) for x in v]
        if isinstance(vt, idl.BasicType):
            tn = vt.typename
            if tn == "boolean":
                return lambda v: [bool(x) for x in v]
            if tn == "octet":
                return _octets_to_rclpy
            if tn in _NUMERIC:
                typecode, dtype = _NUMERIC[tn]
                if isinstance(slot, idl.Array):  # fixed size: numpy in rclpy
                    return lambda v: np.array(v, dtype=dtype)
                return _numeric_sequence_to_rclpy(typecode, dtype)
            raise MessageTypeError(f"unsupported array element type {tn!r}")
    raise MessageTypeError(f"unsupported field type {type(slot).__name__}")


def _to_rclpy_plan(cls: type) -> list[tuple[str, Converter]]:
    plan = _to_rclpy_plans.get(cls)
    if plan is None:
        with _lock:
            plan = _to_rclpy_plans.get(cls)
            if plan is None:
                plan = [(name, _value_to_rclpy(slot)) for name, slot in _fields(cls)]
                _to_rclpy_plans[cls] = plan
    return plan


def _to_rclpy_as(obj: Any, cls: type) -> Any:
    msg = cls()
    for name, convert in _to_rclpy_plan(cls):
        try:
            value = getattr(obj, name)
        except AttributeError:
            raise MessageTypeError(
                f"{msgtype_of(cls)}: field '{name}' missing in {type(obj).__name__} (definitions differ)"
            ) from None
        setattr(msg, name, convert(value))
    return msg


def to_rclpy(obj: Any, cls: Optional[type] = None) -> Any:
    """A rosbags message (dataclass with ``__msgtype__``) as an rclpy message of the same type."""
    if cls is None:
        msgtype = getattr(obj, "__msgtype__", None)
        if not isinstance(msgtype, str):
            raise MessageTypeError(f"{type(obj).__name__} is not a rosbags message (no __msgtype__)")
        cls = rclpy_class(msgtype)
    return _to_rclpy_as(obj, cls)


# ------------------------------------------------------- rclpy -> rosbags
def _scalar_to_rosbags(typename: str) -> Converter:
    if typename == "boolean":
        return bool
    if typename == "octet":  # rosbags models ``byte`` as int8
        return lambda v: int.from_bytes(v, "little", signed=True) if isinstance(v, (bytes, bytearray)) else int(v)
    if typename in _FLOATS:
        return float
    if typename in _NUMERIC:
        return int
    raise MessageTypeError(f"unsupported basic type {typename!r}")


def _value_to_rosbags(slot: Any, store: Any) -> Converter:
    if isinstance(slot, idl.NamespacedType):
        msgtype = _namespaced_name(slot)
        return lambda v: _to_rosbags_as(v, msgtype, store)
    if isinstance(slot, (idl.AbstractString, idl.AbstractWString)):
        return str
    if isinstance(slot, idl.BasicType):
        return _scalar_to_rosbags(slot.typename)
    if isinstance(slot, idl.AbstractNestedType):
        vt = slot.value_type
        if isinstance(vt, idl.NamespacedType):
            msgtype = _namespaced_name(vt)
            return lambda v: [_to_rosbags_as(x, msgtype, store) for x in v]
        if isinstance(vt, (idl.AbstractString, idl.AbstractWString)):
            return lambda v: [str(x) for x in v]
        if isinstance(vt, idl.BasicType):
            tn = vt.typename
            if tn == "boolean":
                return lambda v: np.array([bool(x) for x in v], dtype=np.bool_)
            if tn == "octet":
                return lambda v: np.frombuffer(b"".join(v), dtype=np.int8).copy()
            if tn in _NUMERIC:
                _, dtype = _NUMERIC[tn]
                return lambda v: np.array(v, dtype=dtype)  # buffer copy from array.array / numpy
            raise MessageTypeError(f"unsupported array element type {tn!r}")
    raise MessageTypeError(f"unsupported field type {type(slot).__name__}")


def _rosbags_class(msgtype: str, store: Any) -> type:
    try:
        return store.types[msgtype]
    except KeyError:
        raise MessageTypeError(f"message type {msgtype} is not in the rosbags typestore") from None


def _to_rosbags_plan(cls: type, store: Any) -> list[tuple[str, Converter]]:
    key = (cls, id(store))
    plan = _to_rosbags_plans.get(key)
    if plan is None:
        with _lock:
            plan = _to_rosbags_plans.get(key)
            if plan is None:
                plan = [(name, _value_to_rosbags(slot, store)) for name, slot in _fields(cls)]
                _to_rosbags_plans[key] = plan
    return plan


def _to_rosbags_as(msg: Any, msgtype: str, store: Any) -> Any:
    target = _rosbags_class(msgtype, store)
    kwargs = {name: convert(getattr(msg, name)) for name, convert in _to_rosbags_plan(type(msg), store)}
    try:
        return target(**kwargs)
    except TypeError as exc:
        raise MessageTypeError(f"{msgtype}: rclpy and typestore definitions differ ({exc})") from None


def to_rosbags(msg: Any, store: Any = None) -> Any:
    """An rclpy message as a rosbags dataclass of the same type (soma_msgs typestore by default)."""
    if store is None:
        from ..bagtypes import typestore

        store = typestore()
    return _to_rosbags_as(msg, msgtype_of(msg), store)


# ----------------------------------------------------------- serialisation
def serialize_rclpy(msg: Any, store: Any = None) -> bytes:
    """CDR bytes of an rclpy message, as a rosbag2 stores them (encapsulation header included).

    ``rclpy.serialization.serialize_message`` may report a buffer a few bytes
    longer than the message (Fast CDR's size estimate counts alignment of
    empty sequences, e.g. a JointState without efforts) and leaves those bytes
    uninitialised; strict readers such as rosbags then refuse the message. The
    excess is cut here, using the typestore's decoder to find where the
    message ends, so the result is what a subscriber receives on the wire.
    """
    from rclpy.serialization import serialize_message

    raw = serialize_message(msg)
    if store is None:
        from ..bagtypes import typestore

        store = typestore()
    try:
        msgdef = store.get_msgdef(msgtype_of(msg))
    except Exception:  # a type the typestore lacks: keep rclpy's bytes as they are
        return raw
    little = len(raw) >= 2 and raw[1] == 1
    decode = msgdef.deserialize_cdr_le if little else msgdef.deserialize_cdr_be
    _, pos = decode(memoryview(raw)[4:], 0, msgdef.cls, store)
    end = 4 + pos
    padded = end + (-end) % 4
    if len(raw) <= padded:
        return raw
    return raw[:end] + b"\x00" * (padded - end)
