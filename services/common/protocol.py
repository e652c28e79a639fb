"""The handkse wire protocol, version 1 (see docs/protocol.md): messages, array codec, validation.

Every payload is one msgpack map with string keys carrying the envelope ``schema``, ``seq``,
``stamp_ns`` and ``frame_id`` plus the message's own fields. n-d arrays travel as
``{"dtype": "<f8", "shape": [4, 4], "data": bin}`` (C order, explicit byte order).

Each message is a frozen dataclass with ``to_msgpack()`` and ``from_msgpack(payload)``; decoding
validates everything and raises one exception type, :class:`ProtocolError`, whose message names
the offending field (``"HandBody.landmarks.status: ..."``). Unknown extra keys are ignored.
Equality of two messages is equality of their wire bytes.

This is the only module that imports msgpack. It stays one module past the house limit of about
450 lines on purpose: the messages and the field reader that validates them are one contract,
read side by side with docs/protocol.md.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np
from numpy.typing import NDArray

from services.common.se3 import check_pose

PROTOCOL_MAJOR = 1
FRAME_IDS = ("camera", "world")
JOINT_TYPES = ("rigid", "prismatic", "revolute", "disconnected")
MODEL_TYPES = (*JOINT_TYPES, "unknown")
PHASES = ("contact", "free")  # KinematicModel.phase: what the hand does at stamp_ns
MOTION_MODELS = ("static", "constant_velocity", "kinematic")
ROBOT_MODES = ("idle", "articulating", "fault")
NUM_LANDMARKS = 21
_UNIT_TOLERANCE = 1e-6
_PROBABILITY_TOLERANCE = 1e-6


class ProtocolError(ValueError):
    """A payload that is not a valid handkse message; the text names the field and the problem.

    ``reason`` is a short, stable label for counting (``"bad_msgpack"``, ``"wrong_schema"``,
    ``"bad_field"``, ...).
    """

    def __init__(self, message: str, reason: str = "bad_field") -> None:
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------------------------
# Generic codec: python values <-> msgpack-ready values


def encode_array(a: NDArray[Any]) -> dict[str, Any]:
    """Array codec map ``{dtype, shape, data}``; C order, dtype string with byte order."""
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _to_wire(value: Any) -> Any:
    """Turn arrays (and nested containers of them) into codec maps."""
    if isinstance(value, np.ndarray):
        return encode_array(value)
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _to_json(value: Any) -> Any:
    """Turn arrays into nested lists and bytes into lists of ints, for JSON."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {k: _to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_json(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return list(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _wire_default(value: Any) -> Any:
    """msgpack hook for types it does not know: arrays become codec maps, numpy scalars items."""
    if isinstance(value, np.ndarray):
        return encode_array(value)
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot encode {type(value).__name__}")


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True, default=_wire_default)


def _unpack(payload: bytes | bytearray | memoryview, what: str) -> Any:
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises many types for garbage; all mean the same here
        raise ProtocolError(f"{what}: payload is not valid msgpack ({exc})", "bad_msgpack") from exc


def pack_document(obj: Any) -> bytes:
    """Pack a nested structure of dicts, lists, scalars, bytes and numpy arrays (state files)."""
    return _pack(_to_wire(obj))


def unpack_document(payload: bytes) -> Any:
    """Inverse of :func:`pack_document`: codec maps come back as (writable) numpy arrays."""

    def restore(value: Any) -> Any:
        if isinstance(value, dict):
            if set(value) == {"dtype", "shape", "data"}:
                return _decode_array_map(value, "document").copy()
            return {k: restore(v) for k, v in value.items()}
        if isinstance(value, list):
            return [restore(v) for v in value]
        return value

    return restore(_unpack(payload, "document"))


def peek_envelope(payload: bytes) -> tuple[str | None, int | None]:
    """``(schema, stamp_ns)`` of a payload without validating it; None for what is missing."""
    try:
        obj = _unpack(payload, "payload")
    except ProtocolError:
        return None, None
    if not isinstance(obj, dict):
        return None, None
    schema, stamp = obj.get("schema"), obj.get("stamp_ns")
    return (schema if isinstance(schema, str) else None,
            stamp if isinstance(stamp, int) and not isinstance(stamp, bool) else None)


def restamp(payload: bytes, offset_ns: int) -> bytes:
    """``payload`` with its envelope ``stamp_ns`` moved by ``offset_ns`` (replays onto the wall
    clock); every other key is kept as it was, unknown ones included.

    A payload that is not a msgpack map, has no integer ``stamp_ns``, or has the placeholder
    stamp 0 (``Ack``, ``ServiceStats``, the empty model) comes back unchanged, as does one whose
    new stamp would leave msgpack's unsigned 64-bit range.
    """
    try:
        obj = _unpack(payload, "payload")
    except ProtocolError:
        return payload
    if not isinstance(obj, dict):
        return payload
    stamp = obj.get("stamp_ns")
    if isinstance(stamp, bool) or not isinstance(stamp, int) or stamp <= 0 \
            or not 0 <= stamp + offset_ns < 2**64:
        return payload
    obj["stamp_ns"] = stamp + offset_ns
    return _pack(obj)


_DTYPES: dict[str, np.dtype[Any]] = {}


def _dtype(text: str) -> np.dtype[Any]:
    dt = _DTYPES.get(text)
    if dt is None:
        dt = _DTYPES[text] = np.dtype(text)
    return dt


# dtype strings the codec accepts: optional byte order, kind (bool, int, uint, float), item size.
_DTYPE_TEXT = re.compile(r"[<>|=]?[biuf][1248]")
_MAX_DIMENSIONS = 8
_MAX_ELEMENTS = 1 << 31


def _decode_array_map(value: Any, path: str) -> NDArray[Any]:
    if not isinstance(value, dict):
        raise ProtocolError(f"{path}: expected an array map {{dtype, shape, data}}, got "
                            f"{type(value).__name__}")
    missing = [k for k in ("dtype", "shape", "data") if k not in value]
    if missing:
        raise ProtocolError(f"{path}: malformed array map (missing {', '.join(missing)})")
    text, shape_in, data = value["dtype"], value["shape"], value["data"]
    # Checked as text before numpy parses it: np.dtype raises SyntaxError or TypeError on some
    # strings and accepts structured and object types the codec does not carry.
    if not isinstance(text, str) or len(text) > 3 or not _DTYPE_TEXT.fullmatch(text):
        shown = text[:16] if isinstance(text, str) else type(text).__name__
        raise ProtocolError(f"{path}: unsupported dtype {shown!r} (expected e.g. '<f8', '|u1')")
    dtype = _dtype(text)
    if (not isinstance(shape_in, list) or len(shape_in) > _MAX_DIMENSIONS
            or not all(isinstance(s, int) and not isinstance(s, bool) for s in shape_in)):
        raise ProtocolError(f"{path}: shape must be a list of at most {_MAX_DIMENSIONS} ints")
    shape = tuple(shape_in)
    if any(s < 0 for s in shape):
        raise ProtocolError(f"{path}: negative dimension in shape {list(shape)}")
    if math.prod(shape) > _MAX_ELEMENTS:
        raise ProtocolError(f"{path}: shape {list(shape)} has more than {_MAX_ELEMENTS} elements")
    if not isinstance(data, bytes):
        raise ProtocolError(f"{path}: data must be bin, got {type(data).__name__}")
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise ProtocolError(f"{path}: data has {len(data)} bytes, shape {list(shape)} of "
                            f"{dtype.str} needs {expected}")
    return np.frombuffer(data, dtype).reshape(shape)


# --------------------------------------------------------------------------------------------
# Field reader: extraction with validation and field-naming errors


class _Fields:
    """Typed access to one msgpack map; every error names ``path.key``.

    ``lists``: arrays may also be nested lists, as :meth:`Message.to_json_obj` writes them (JSON
    documents only; the wire always carries array maps).
    """

    def __init__(self, obj: Any, path: str, lists: bool = False) -> None:
        if not isinstance(obj, dict):
            raise ProtocolError(f"{path}: expected a map, got {type(obj).__name__}")
        self.obj = obj
        self.path = path
        self.lists = lists

    def _get(self, key: str, optional: bool = False) -> Any:
        if key not in self.obj or (optional and self.obj[key] is None):
            if optional:
                return None
            raise ProtocolError(f"{self.path}.{key}: missing")
        return self.obj[key]

    def int(self, key: str, minimum: int | None = None) -> int:
        v = self._get(key)
        if isinstance(v, bool) or not isinstance(v, int):
            raise ProtocolError(f"{self.path}.{key}: expected int, got {type(v).__name__}")
        if minimum is not None and v < minimum:
            raise ProtocolError(f"{self.path}.{key}: {v} is below {minimum}")
        return v

    def float(self, key: str, lo: float = -math.inf, hi: float = math.inf,
              default: float | None = None) -> float:
        if default is not None and key not in self.obj:
            return default
        v = self._get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ProtocolError(f"{self.path}.{key}: expected a number, got {type(v).__name__}")
        v = float(v)
        if not math.isfinite(v):
            raise ProtocolError(f"{self.path}.{key}: must be finite, got {v}")
        if not lo <= v <= hi:
            raise ProtocolError(f"{self.path}.{key}: {v} outside [{lo}, {hi}]")
        return v

    def bool(self, key: str, default: bool | None = None) -> bool:
        if default is not None and key not in self.obj:
            return default
        v = self._get(key)
        if not isinstance(v, bool):
            raise ProtocolError(f"{self.path}.{key}: expected bool, got {type(v).__name__}")
        return v

    def str(self, key: str, choices: Iterable[str] | None = None) -> str:
        v = self._get(key)
        if not isinstance(v, str):
            raise ProtocolError(f"{self.path}.{key}: expected str, got {type(v).__name__}")
        if choices is not None and v not in (allowed := tuple(choices)):
            raise ProtocolError(f"{self.path}.{key}: {v!r} is not one of {list(allowed)}")
        return v

    def bin(self, key: str) -> bytes:
        v = self._get(key)
        if not isinstance(v, bytes):
            raise ProtocolError(f"{self.path}.{key}: expected bin, got {type(v).__name__}")
        return v

    def map(self, key: str, optional: bool = False) -> _Fields | None:
        v = self._get(key, optional)
        return None if v is None else _Fields(v, f"{self.path}.{key}", self.lists)

    def req_map(self, key: str) -> _Fields:
        return _Fields(self._get(key), f"{self.path}.{key}", self.lists)

    def array(self, key: str, dtype: str, shape: tuple[int, ...], *, finite: bool = True,
              optional: bool = False) -> NDArray[Any] | None:
        v = self._get(key, optional)
        if v is None:
            if optional:
                return None
            raise ProtocolError(f"{self.path}.{key}: expected an array map, got nil")
        path = f"{self.path}.{key}"
        # Fast path: the expected dtype and shape, checked before any general parsing.
        if (isinstance(v, dict) and v.get("dtype") == dtype and v.get("shape") == list(shape)
                and isinstance(data := v.get("data"), bytes)):
            dt = _dtype(dtype)
            if len(data) != math.prod(shape) * dt.itemsize:
                raise ProtocolError(f"{path}: data has {len(data)} bytes, shape {list(shape)} "
                                    f"of {dtype} needs {math.prod(shape) * dt.itemsize}")
            a = np.frombuffer(data, dt).reshape(shape)
        else:
            a = (_array_from_lists(v, dtype, path) if self.lists and isinstance(v, list)
                 else _decode_array_map(v, path))
            if a.dtype.str != dtype:
                raise ProtocolError(f"{path}: dtype must be {dtype}, got {a.dtype.str}")
            if a.shape != shape:
                raise ProtocolError(f"{path}: shape must be {list(shape)}, got {list(a.shape)}")
        if finite and a.dtype.kind == "f" and not _all_finite(a):
            raise ProtocolError(f"{path}: contains NaN or infinity")
        return a

    def req_array(self, key: str, dtype: str, shape: tuple[int, ...],
                  finite: bool = True) -> NDArray[Any]:
        a = self.array(key, dtype, shape, finite=finite)
        assert a is not None
        return a


def _array_from_lists(value: list[Any], dtype: str, path: str) -> NDArray[Any]:
    """A JSON array (nested lists of numbers) as an array of ``dtype``; null is not a number."""
    try:
        a = np.asarray(value, dtype=_dtype(dtype))
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"{path}: expected nested lists of numbers ({exc})") from exc
    if a.size > _MAX_ELEMENTS:
        raise ProtocolError(f"{path}: more than {_MAX_ELEMENTS} elements")
    return a


def _optional_int(f: _Fields, key: str, minimum: int) -> int | None:
    """An int field that may be absent or nil (None then)."""
    return None if f.obj.get(key) is None else f.int(key, minimum)


def _all_finite(a: NDArray[Any]) -> bool:
    """True when no element is NaN or infinite; one reduction in the common case."""
    if math.isfinite(float(a.sum())):
        return True
    return bool(np.isfinite(a).all())  # the sum may overflow with huge but finite values


def _check_unit(v: NDArray[Any], path: str) -> None:
    n = float(np.linalg.norm(v))
    if abs(n - 1.0) > _UNIT_TOLERANCE:
        raise ProtocolError(f"{path}: axis must be unit length, has norm {n:.9g}")


def _require_pose(T: NDArray[Any], path: str) -> None:
    if (problem := check_pose(T)) is not None:
        raise ProtocolError(f"{path}: not a rigid transform: {problem}")


def _check_covariance(P: NDArray[Any], path: str) -> None:
    if np.abs(P - P.T).max() > 1e-9 * max(1.0, float(np.abs(P).max())):
        raise ProtocolError(f"{path}: covariance is not symmetric")
    if (np.diag(P) < 0.0).any():
        raise ProtocolError(f"{path}: covariance has a negative variance")


# --------------------------------------------------------------------------------------------
# Messages

M = TypeVar("M", bound="Message")


@dataclass(frozen=True, kw_only=True, eq=False)
class Message:
    """Envelope shared by every message. Subclasses set ``SCHEMA`` and add fields."""

    SCHEMA: ClassVar[str] = ""
    seq: int = 0
    stamp_ns: int = 0
    frame_id: str = "camera"

    def _fields(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def _parse(cls: type[M], f: _Fields, envelope: dict[str, Any]) -> M:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """Envelope plus fields; arrays stay numpy arrays."""
        d: dict[str, Any] = {"schema": self.SCHEMA, "seq": self.seq, "stamp_ns": self.stamp_ns,
                             "frame_id": self.frame_id}
        d.update(self._fields())
        return d

    def to_msgpack(self) -> bytes:
        return _pack(self.to_dict())

    def to_json_obj(self) -> dict[str, Any]:
        """A JSON-ready dict (arrays as nested lists, non-finite floats as null)."""
        result: dict[str, Any] = _to_json(self.to_dict())
        return result

    @classmethod
    def from_msgpack(cls: type[M], payload: bytes | bytearray | memoryview) -> M:
        """Decode and validate; every failure is a :class:`ProtocolError` naming the field."""
        name = cls.__name__
        obj = _unpack(payload, name)
        try:
            return cls.from_obj(obj, name)
        except ProtocolError:
            raise
        except Exception as exc:  # a check this module missed: still bad input, not a crash
            raise ProtocolError(f"{name}: invalid message ({type(exc).__name__}: "
                                f"{str(exc)[:200]})", "bad_field") from exc

    @classmethod
    def from_json_obj(cls: type[M], obj: Any) -> M:
        """Decode and validate the JSON form (:meth:`to_json_obj`, e.g. ``handkse get model
        --json``): arrays as nested lists; every failure is a :class:`ProtocolError`."""
        try:
            return cls.from_obj(obj, cls.__name__, lists=True)
        except ProtocolError:
            raise
        except Exception as exc:  # as in from_msgpack: bad input, not a crash
            raise ProtocolError(f"{cls.__name__}: invalid message ({type(exc).__name__}: "
                                f"{str(exc)[:200]})", "bad_field") from exc

    @classmethod
    def from_obj(cls: type[M], obj: Any, path: str | None = None, lists: bool = False) -> M:
        """Validate an already unpacked msgpack map (used for nested messages); ``lists``:
        arrays may be nested lists (the JSON form)."""
        path = path or cls.__name__
        f = _Fields(obj, path, lists)
        schema = f.str("schema")
        kind, _, version = schema.partition("/")
        expected_kind = cls.SCHEMA.partition("/")[0]
        if kind != expected_kind:
            raise ProtocolError(f"{path}.schema: expected {expected_kind!r}, got {kind!r}",
                                "wrong_schema")
        # Length first: int() of thousands of digits raises ValueError (and costs time).
        if not (version.isdigit() and len(version) <= 9) or int(version) != PROTOCOL_MAJOR:
            raise ProtocolError(f"{path}.schema: unknown major version in {schema!r} (this "
                                f"build speaks version {PROTOCOL_MAJOR})", "wrong_version")
        envelope = {"seq": f.int("seq", 0), "stamp_ns": f.int("stamp_ns", 0),
                    "frame_id": f.str("frame_id", FRAME_IDS)}
        return cls._parse(f, envelope)

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and self.to_msgpack() == other.to_msgpack()  # type: ignore[attr-defined]

    def __hash__(self) -> int:
        return hash(self.to_msgpack())


# --- RgbdFrame ---


@dataclass(frozen=True, kw_only=True, eq=False)
class CameraIntrinsics:
    """Pinhole intrinsics of the colour camera, pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def to_dict(self) -> dict[str, Any]:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}

    @classmethod
    def parse(cls, f: _Fields) -> CameraIntrinsics:
        return cls(fx=f.float("fx", 1e-9), fy=f.float("fy", 1e-9), cx=f.float("cx"),
                   cy=f.float("cy"), width=f.int("width", 1), height=f.int("height", 1))


COLOR_ENCODINGS = ("jpeg", "png", "bgr8")
DEPTH_ENCODINGS = ("png16", "u16")


@dataclass(frozen=True, kw_only=True, eq=False)
class ColorImage:
    encoding: str
    width: int
    height: int
    data: bytes


@dataclass(frozen=True, kw_only=True, eq=False)
class DepthImage:
    """Depth registered to the colour image; ``scale_m`` metres per unit; 0 = no reading."""

    encoding: str
    width: int
    height: int
    scale_m: float
    data: bytes


def _parse_image(f: _Fields, encodings: tuple[str, ...], raw: str, channels: int
                 ) -> tuple[str, int, int, bytes]:
    encoding = f.str("encoding", encodings)
    width, height, data = f.int("width", 1), f.int("height", 1), f.bin("data")
    if encoding == raw:
        need = width * height * channels
        if len(data) != need:
            raise ProtocolError(f"{f.path}.data: {len(data)} bytes, {encoding} "
                                f"{width}x{height} needs {need}")
    elif not data:
        raise ProtocolError(f"{f.path}.data: empty {encoding} image")
    return encoding, width, height, data


@dataclass(frozen=True, kw_only=True, eq=False)
class RgbdFrame(Message):
    """Colour + registered depth from a camera source (``handkse/{rig}/camera/rgbd``)."""

    SCHEMA: ClassVar[str] = "handkse.RgbdFrame/1"
    color: ColorImage
    depth: DepthImage
    intrinsics: CameraIntrinsics
    T_world_camera: NDArray[np.float64] | None = None

    def _fields(self) -> dict[str, Any]:
        c, d = self.color, self.depth
        out: dict[str, Any] = {
            "color": {"encoding": c.encoding, "width": c.width, "height": c.height,
                      "data": c.data},
            "depth": {"encoding": d.encoding, "width": d.width, "height": d.height,
                      "scale_m": d.scale_m, "data": d.data},
            "intrinsics": self.intrinsics.to_dict(),
        }
        if self.T_world_camera is not None:
            out["T_world_camera"] = self.T_world_camera
        return out

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> RgbdFrame:
        cf, df = f.req_map("color"), f.req_map("depth")
        ce, cw, ch, cd = _parse_image(cf, COLOR_ENCODINGS, "bgr8", 3)
        de, dw, dh, dd = _parse_image(df, DEPTH_ENCODINGS, "u16", 2)
        T = f.array("T_world_camera", "<f8", (4, 4), optional=True)
        if T is not None:
            _require_pose(T, f"{f.path}.T_world_camera")
        return cls(**envelope, color=ColorImage(encoding=ce, width=cw, height=ch, data=cd),
                   depth=DepthImage(encoding=de, width=dw, height=dh,
                                    scale_m=df.float("scale_m", 1e-9), data=dd),
                   intrinsics=CameraIntrinsics.parse(f.req_map("intrinsics")),
                   T_world_camera=T)


# --- HandLandmarks ---


@dataclass(frozen=True, kw_only=True, eq=False)
class Hand:
    """One detected hand: 21 landmarks in MediaPipe order, metres in the message's frame."""

    handedness: str
    score: float
    points: NDArray[np.float32]
    visibility: NDArray[np.float32]
    pixels: NDArray[np.float32] | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"handedness": self.handedness, "score": self.score,
                             "points": self.points, "visibility": self.visibility}
        if self.pixels is not None:
            d["pixels"] = self.pixels
        return d

    @classmethod
    def parse(cls, f: _Fields) -> Hand:
        points = f.req_array("points", "<f4", (NUM_LANDMARKS, 3), finite=False)
        if np.isinf(points).any():
            raise ProtocolError(f"{f.path}.points: infinite coordinate (NaN marks no depth)")
        visibility = f.req_array("visibility", "<f4", (NUM_LANDMARKS,), finite=False)
        if not (visibility.min() >= 0.0 and visibility.max() <= 1.0):  # NaN fails too
            raise ProtocolError(f"{f.path}.visibility: values must lie in [0, 1]")
        return cls(handedness=f.str("handedness", ("left", "right")),
                   score=f.float("score", 0.0, 1.0), points=points, visibility=visibility,
                   pixels=f.array("pixels", "<f4", (NUM_LANDMARKS, 2), optional=True,
                                  finite=False))


@dataclass(frozen=True, kw_only=True, eq=False)
class HandLandmarks(Message):
    """Detected hands of one camera frame (``handkse/{rig}/hand/landmarks``).

    With a moving camera the points are in "world" and ``T_world_camera`` is the camera pose of
    the frame (the tracker needs it for the viewing rays of its depth noise model).
    """

    SCHEMA: ClassVar[str] = "handkse.HandLandmarks/1"
    hands: tuple[Hand, ...] = ()
    T_world_camera: NDArray[np.float64] | None = None

    def _fields(self) -> dict[str, Any]:
        out: dict[str, Any] = {"hands": [h.to_dict() for h in self.hands]}
        if self.T_world_camera is not None:
            out["T_world_camera"] = self.T_world_camera
        return out

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> HandLandmarks:
        raw = f._get("hands")
        if not isinstance(raw, list) or len(raw) > 2:
            raise ProtocolError(f"{f.path}.hands: expected a list of at most 2 hands")
        T = f.array("T_world_camera", "<f8", (4, 4), optional=True)
        if T is not None:
            _require_pose(T, f"{f.path}.T_world_camera")
        return cls(**envelope,
                   hands=tuple(Hand.parse(_Fields(h, f"{f.path}.hands[{i}]"))
                               for i, h in enumerate(raw)), T_world_camera=T)


# --- HandBody ---


@dataclass(frozen=True, kw_only=True, eq=False)
class LandmarkStates:
    """Per-landmark filter output; status 0 untracked, 1 used, 2 outlier this step, 3 excluded."""

    points: NDArray[np.float32]
    variance: NDArray[np.float32]
    status: NDArray[np.uint8]


@dataclass(frozen=True, kw_only=True, eq=False)
class HandBody(Message):
    """Hand rigid-body estimate (``handkse/{rig}/hand/body``).

    ``covariance`` is 12x12 over [pose left-perturbation (v, w), twist (v, w)], in ``frame_id``.
    ``body_epoch`` (int >= 0; 0 when absent on the wire) names the hand body frame ``pose`` is
    in: it changes whenever the tracker defines the body frame anew without re-acquiring the
    old one, and a consumer must never compare poses of two epochs (docs/protocol.md).
    """

    SCHEMA: ClassVar[str] = "handkse.HandBody/1"
    initialized: bool
    pose: NDArray[np.float64]
    twist: NDArray[np.float64]
    covariance: NDArray[np.float64]
    motion_model: str
    landmarks: LandmarkStates
    body_epoch: int = 0

    def _fields(self) -> dict[str, Any]:
        lm = self.landmarks
        return {"initialized": self.initialized, "pose": self.pose, "twist": self.twist,
                "covariance": self.covariance, "motion_model": self.motion_model,
                "landmarks": {"points": lm.points, "variance": lm.variance,
                              "status": lm.status},
                "body_epoch": self.body_epoch}

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> HandBody:
        pose = f.req_array("pose", "<f8", (4, 4))
        _require_pose(pose, f"{f.path}.pose")
        cov = f.req_array("covariance", "<f8", (12, 12))
        _check_covariance(cov, f"{f.path}.covariance")
        lf = f.req_map("landmarks")
        status = lf.req_array("status", "|u1", (NUM_LANDMARKS,))
        if (status > 3).any():
            raise ProtocolError(f"{lf.path}.status: values must be 0..3")
        landmarks = LandmarkStates(
            points=lf.req_array("points", "<f4", (NUM_LANDMARKS, 3), finite=False),
            variance=lf.req_array("variance", "<f4", (NUM_LANDMARKS,), finite=False),
            status=status)
        body_epoch = 0 if f._get("body_epoch", optional=True) is None else f.int("body_epoch", 0)
        return cls(**envelope, initialized=f.bool("initialized"), pose=pose,
                   twist=f.req_array("twist", "<f8", (6,)), covariance=cov,
                   motion_model=f.str("motion_model", MOTION_MODELS), landmarks=landmarks,
                   body_epoch=body_epoch)


# --- KinematicModel ---


@dataclass(frozen=True, kw_only=True, eq=False)
class PrismaticParams:
    """Prismatic joint in the model's frame.

    ``axis`` (3,) unit direction; ``q`` [m] joint value (hand displacement along ``axis`` from the
    reference pose); ``dq`` [m/s]; ``covariance`` (4x4) of ``(b1, b2, q, dq)``, where ``(b1, b2)``
    [rad] are axis coordinates in ``tangent_basis(axis)`` (``services.kinematics.filters``).
    """

    axis: NDArray[np.float64]
    q: float
    dq: float
    covariance: NDArray[np.float64]


@dataclass(frozen=True, kw_only=True, eq=False)
class RevoluteParams:
    """Revolute joint in the model's frame.

    ``axis`` (3,) unit direction; ``point`` (3,) [m] the point of the axis closest to the frame
    origin; ``q`` [rad] unbounded joint value (right-handed rotation about ``axis`` from the
    reference pose); ``dq`` [rad/s]; ``covariance`` (7x7) of ``(b1, b2, px, py, pz, q, dq)``, the
    axis coordinates in ``tangent_basis(axis)``.
    """

    axis: NDArray[np.float64]
    point: NDArray[np.float64]
    q: float
    dq: float
    covariance: NDArray[np.float64]


@dataclass(frozen=True, kw_only=True, eq=False)
class KinematicModel(Message):
    """The kinematics service's belief (``handkse/{rig}/kinematics/model``), the one kinematic
    model type of handkse: :class:`services.kinematics.estimator.KinematicEstimator` returns it
    too. ``stamp_ns`` is that of the last hand body absorbed; ``updates`` 0 is the empty model,
    before any (docs/protocol.md). The hand pose at joint value q is
    ``Exp(q * screw) @ reference_pose``, screw ``(axis, 0)`` or ``(point x axis, axis)``
    (:mod:`services.kinematics.prediction`).

    Contact phases (docs/protocol.md#contact-phases): ``segment`` is the index of the contact
    phase the estimate describes within the demonstration, ``segment_start_ns`` /
    ``segment_end_ns`` the stamps of its first and last frame (None before the first phase /
    while it is open), ``phase`` ("contact" or "free") what the hand does at ``stamp_ns`` (None:
    the producer does not segment), ``first_segment`` the phase whose estimate a re-grasp of the
    same joint continues (None: this phase's own)."""

    SCHEMA: ClassVar[str] = "handkse.KinematicModel/1"
    type: str
    probabilities: Mapping[str, float]
    prismatic: PrismaticParams | None = None
    revolute: RevoluteParams | None = None
    reference_pose: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    updates: int = 0
    segment: int = 0
    segment_start_ns: int | None = None
    segment_end_ns: int | None = None
    phase: str | None = None
    first_segment: int | None = None

    def _fields(self) -> dict[str, Any]:
        p, r = self.prismatic, self.revolute
        out: dict[str, Any] = {
            "type": self.type,
            "probabilities": {k: float(self.probabilities[k]) for k in JOINT_TYPES},
            "prismatic": None if p is None else {"axis": p.axis, "q": float(p.q),
                                                 "dq": float(p.dq), "covariance": p.covariance},
            "revolute": None if r is None else {"axis": r.axis, "point": r.point,
                                                "q": float(r.q), "dq": float(r.dq),
                                                "covariance": r.covariance},
            "reference_pose": self.reference_pose,
            "updates": self.updates,
            "segment": self.segment,
        }
        for key in ("segment_start_ns", "segment_end_ns", "phase", "first_segment"):
            if (value := getattr(self, key)) is not None:
                out[key] = value
        return out

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> KinematicModel:
        pf = f.req_map("probabilities")
        probabilities = {k: pf.float(k, 0.0, 1.0) for k in JOINT_TYPES}
        total = sum(probabilities.values())
        if abs(total - 1.0) > _PROBABILITY_TOLERANCE:
            raise ProtocolError(f"{pf.path}: probabilities sum to {total:.9g}, not 1")
        prismatic = revolute = None
        if (m := f.map("prismatic", optional=True)) is not None:
            axis = m.req_array("axis", "<f8", (3,))
            _check_unit(axis, f"{m.path}.axis")
            cov = m.req_array("covariance", "<f8", (4, 4))
            _check_covariance(cov, f"{m.path}.covariance")
            prismatic = PrismaticParams(axis=axis, q=m.float("q"), dq=m.float("dq"),
                                        covariance=cov)
        if (m := f.map("revolute", optional=True)) is not None:
            axis = m.req_array("axis", "<f8", (3,))
            _check_unit(axis, f"{m.path}.axis")
            cov = m.req_array("covariance", "<f8", (7, 7))
            _check_covariance(cov, f"{m.path}.covariance")
            revolute = RevoluteParams(axis=axis, point=m.req_array("point", "<f8", (3,)),
                                      q=m.float("q"), dq=m.float("dq"), covariance=cov)
        reference = f.req_array("reference_pose", "<f8", (4, 4))
        _require_pose(reference, f"{f.path}.reference_pose")
        model_type = f.str("type", MODEL_TYPES)
        if model_type == "prismatic" and prismatic is None:
            raise ProtocolError(f"{f.path}.prismatic: type is prismatic but parameters are nil")
        if model_type == "revolute" and revolute is None:
            raise ProtocolError(f"{f.path}.revolute: type is revolute but parameters are nil")
        segment = 0 if f.obj.get("segment") is None else f.int("segment", 0)
        start = _optional_int(f, "segment_start_ns", 0)
        end = _optional_int(f, "segment_end_ns", 0)
        if end is not None and (start is None or end < start):
            raise ProtocolError(f"{f.path}.segment_end_ns: {end} needs a segment_start_ns at or "
                                f"before it, got {start}")
        first = _optional_int(f, "first_segment", 0)
        if first is not None and first > segment:
            raise ProtocolError(f"{f.path}.first_segment: {first} is after segment {segment}")
        phase = None if f.obj.get("phase") is None else f.str("phase", PHASES)
        return cls(**envelope, type=model_type, probabilities=probabilities,
                   prismatic=prismatic, revolute=revolute, reference_pose=reference,
                   updates=f.int("updates", 0), segment=segment, segment_start_ns=start,
                   segment_end_ns=end, phase=phase, first_segment=first)


@dataclass(frozen=True, kw_only=True, eq=False)
class KinematicModelList(Message):
    """Every contact phase's model of the current demonstration, oldest first
    (``handkse/{rig}/kinematics/models``; docs/protocol.md#contact-phases)."""

    SCHEMA: ClassVar[str] = "handkse.KinematicModelList/1"
    models: tuple[KinematicModel, ...] = ()

    def _fields(self) -> dict[str, Any]:
        return {"models": [m.to_dict() for m in self.models]}

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> KinematicModelList:
        raw = f._get("models")
        if not isinstance(raw, list):
            raise ProtocolError(f"{f.path}.models: expected a list, got {type(raw).__name__}")
        return cls(**envelope, models=tuple(
            KinematicModel.from_obj(m, f"{f.path}.models[{i}]", f.lists)
            for i, m in enumerate(raw)))


# --- Robot ---


@dataclass(frozen=True, kw_only=True, eq=False)
class RobotState(Message):
    """Robot state (``handkse/{rig}/robot/state``); ``wrench`` = force then torque, base frame.

    ``T_base_target`` (optional): the end-effector pose commanded at this tick while articulating.
    """

    SCHEMA: ClassVar[str] = "handkse.RobotState/1"
    q: NDArray[np.float64]
    dq: NDArray[np.float64]
    T_base_ee: NDArray[np.float64]
    wrench: NDArray[np.float64]
    mode: str
    backend: str
    T_base_target: NDArray[np.float64] | None = None

    def _fields(self) -> dict[str, Any]:
        out = {"q": self.q, "dq": self.dq, "T_base_ee": self.T_base_ee, "wrench": self.wrench,
               "mode": self.mode, "backend": self.backend}
        if self.T_base_target is not None:
            out["T_base_target"] = self.T_base_target
        return out

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> RobotState:
        T = f.req_array("T_base_ee", "<f8", (4, 4))
        _require_pose(T, f"{f.path}.T_base_ee")
        target = f.array("T_base_target", "<f8", (4, 4), optional=True)
        if target is not None:
            _require_pose(target, f"{f.path}.T_base_target")
        return cls(**envelope, q=f.req_array("q", "<f8", (7,)),
                   dq=f.req_array("dq", "<f8", (7,)), T_base_ee=T,
                   wrench=f.req_array("wrench", "<f8", (6,)),
                   mode=f.str("mode", ROBOT_MODES), backend=f.str("backend"),
                   T_base_target=target)


@dataclass(frozen=True, kw_only=True, eq=False)
class ArticulateRequest(Message):
    """Ask the robot bridge to articulate: ``amount`` rad (revolute) or m (prismatic).

    ``timeout_s`` (optional): how long the caller waits for the result (its query timeout); the
    bridge starts nothing it could not answer within it (docs/protocol.md). ``segment``
    (optional): the contact phase whose model to articulate (``KinematicModel.segment``; absent:
    the latest with a verdict).
    """

    SCHEMA: ClassVar[str] = "handkse.ArticulateRequest/1"
    amount: float
    duration_s: float
    force_limit_n: float = 70.0
    model: KinematicModel | None = None
    dry_run: bool = False
    timeout_s: float | None = None
    segment: int | None = None

    def _fields(self) -> dict[str, Any]:
        d: dict[str, Any] = {"amount": self.amount, "duration_s": self.duration_s,
                             "force_limit_n": self.force_limit_n, "dry_run": self.dry_run}
        if self.model is not None:
            d["model"] = self.model.to_dict()
        if self.timeout_s is not None:
            d["timeout_s"] = self.timeout_s
        if self.segment is not None:
            d["segment"] = self.segment
        return d

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> ArticulateRequest:
        raw = f.obj.get("model")
        model = None if raw is None else KinematicModel.from_obj(raw, f"{f.path}.model", f.lists)
        timeout = (None if f.obj.get("timeout_s") is None
                   else f.float("timeout_s", 1e-3, 86400.0))
        return cls(**envelope, amount=f.float("amount"),
                   duration_s=f.float("duration_s", 1e-3, 3600.0),
                   force_limit_n=f.float("force_limit_n", 1e-3, 1e4, default=70.0),
                   model=model, dry_run=f.bool("dry_run", default=False), timeout_s=timeout,
                   segment=_optional_int(f, "segment", 0))


@dataclass(frozen=True, kw_only=True, eq=False)
class ArticulatePlan:
    """The motion a request planned and the limits it runs under (robot base frame, SI units).

    ``axis`` (3,) unit joint axis and ``point`` (3,) [m] on it (revolute) or the grasp point
    (prismatic), both in the robot base frame; ``amount`` rad or m, signed about / along
    ``axis``; ``duration_s`` of the motion, then ``hold_s``; the plan's peak TCP speeds; the
    force limit in effect (the request's, capped by the bridge's), the wrist torque limit and the
    bridge's Cartesian speed limits.
    """

    joint_type: str
    axis: NDArray[np.float64]
    point: NDArray[np.float64]
    amount: float
    duration_s: float
    hold_s: float
    peak_linear_speed_m_per_s: float
    peak_angular_speed_rad_per_s: float
    force_limit_n: float
    wrist_torque_limit_nm: float
    max_linear_speed_m_per_s: float
    max_angular_speed_rad_per_s: float

    def to_dict(self) -> dict[str, Any]:
        return {"joint_type": self.joint_type, "axis": self.axis, "point": self.point,
                "amount": float(self.amount), "duration_s": float(self.duration_s),
                "hold_s": float(self.hold_s),
                "peak_linear_speed_m_per_s": float(self.peak_linear_speed_m_per_s),
                "peak_angular_speed_rad_per_s": float(self.peak_angular_speed_rad_per_s),
                "force_limit_n": float(self.force_limit_n),
                "wrist_torque_limit_nm": float(self.wrist_torque_limit_nm),
                "max_linear_speed_m_per_s": float(self.max_linear_speed_m_per_s),
                "max_angular_speed_rad_per_s": float(self.max_angular_speed_rad_per_s)}

    @classmethod
    def parse(cls, f: _Fields) -> ArticulatePlan:
        axis = f.req_array("axis", "<f8", (3,))
        _check_unit(axis, f"{f.path}.axis")
        return cls(joint_type=f.str("joint_type", ("revolute", "prismatic")), axis=axis,
                   point=f.req_array("point", "<f8", (3,)), amount=f.float("amount"),
                   duration_s=f.float("duration_s", 0.0), hold_s=f.float("hold_s", 0.0),
                   peak_linear_speed_m_per_s=f.float("peak_linear_speed_m_per_s", 0.0),
                   peak_angular_speed_rad_per_s=f.float("peak_angular_speed_rad_per_s", 0.0),
                   force_limit_n=f.float("force_limit_n", 0.0),
                   wrist_torque_limit_nm=f.float("wrist_torque_limit_nm", 0.0),
                   max_linear_speed_m_per_s=f.float("max_linear_speed_m_per_s", 0.0),
                   max_angular_speed_rad_per_s=f.float("max_angular_speed_rad_per_s", 0.0))


@dataclass(frozen=True, kw_only=True, eq=False)
class ArticulateResult(Message):
    """Outcome of an articulation; ``reason`` names why it stopped (``"ok"`` on success).

    ``detail`` (optional on the wire): one sentence for the operator, what happened or what to
    do about a refusal; ``plan`` (optional): the plan the request got, when it got that far
    (dry runs, executions, refusals at the start gate).
    """

    SCHEMA: ClassVar[str] = "handkse.ArticulateResult/1"
    success: bool
    reason: str
    articulated: float
    peak_force_n: float
    mean_force_n: float
    duration_s: float
    detail: str = ""
    plan: ArticulatePlan | None = None

    def _fields(self) -> dict[str, Any]:
        d: dict[str, Any] = {"success": self.success, "reason": self.reason,
                             "articulated": self.articulated, "peak_force_n": self.peak_force_n,
                             "mean_force_n": self.mean_force_n, "duration_s": self.duration_s,
                             "detail": self.detail}
        if self.plan is not None:
            d["plan"] = self.plan.to_dict()
        return d

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> ArticulateResult:
        detail = "" if f.obj.get("detail") is None else f.str("detail")
        plan_map = f.map("plan", optional=True)
        return cls(**envelope, success=f.bool("success"), reason=f.str("reason"),
                   articulated=f.float("articulated"), peak_force_n=f.float("peak_force_n", 0.0),
                   mean_force_n=f.float("mean_force_n", 0.0),
                   duration_s=f.float("duration_s", 0.0), detail=detail,
                   plan=None if plan_map is None else ArticulatePlan.parse(plan_map))


# --- Service control ---


@dataclass(frozen=True, kw_only=True, eq=False)
class Ack(Message):
    """Reply to a control call (``reset``); its envelope is placeholders (docs/protocol.md)."""

    SCHEMA: ClassVar[str] = "handkse.Ack/1"
    ok: bool
    message: str = ""

    def _fields(self) -> dict[str, Any]:
        return {"ok": self.ok, "message": self.message}

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> Ack:
        return cls(**envelope, ok=f.bool("ok"), message=f.str("message"))


@dataclass(frozen=True, kw_only=True, eq=False)
class ServiceStats(Message):
    """Counters of one service; ``latency_ms`` maps a stage to ``{"p50": ms, "p99": ms}``;
    ``skipped`` (optional) counts valid inputs that produced no output, by reason. The envelope
    is placeholders (seq and stamp_ns 0, frame_id "camera"; docs/protocol.md)."""

    SCHEMA: ClassVar[str] = "handkse.ServiceStats/1"
    service: str
    uptime_s: float
    received: int = 0
    published: int = 0
    dropped: int = 0
    rejected: Mapping[str, int] = field(default_factory=dict)
    latency_ms: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    skipped: Mapping[str, int] = field(default_factory=dict)

    def _fields(self) -> dict[str, Any]:
        out = {"service": self.service, "uptime_s": self.uptime_s, "received": self.received,
               "published": self.published, "dropped": self.dropped,
               "rejected": dict(self.rejected),
               "latency_ms": {k: dict(v) for k, v in self.latency_ms.items()}}
        if self.skipped:
            out["skipped"] = dict(self.skipped)
        return out

    @classmethod
    def _parse(cls, f: _Fields, envelope: dict[str, Any]) -> ServiceStats:
        rejected_map = f.req_map("rejected")
        rejected = {str(k): rejected_map.int(k, 0) for k in rejected_map.obj}
        latency_map = f.req_map("latency_ms")
        latency = {}
        for stage in latency_map.obj:
            sf = latency_map.req_map(stage)
            latency[str(stage)] = {"p50": sf.float("p50", 0.0), "p99": sf.float("p99", 0.0)}
        skipped = {}
        if f._get("skipped", optional=True) is not None:
            skipped_map = f.req_map("skipped")
            skipped = {str(k): skipped_map.int(k, 0) for k in skipped_map.obj}
        return cls(**envelope, service=f.str("service"), uptime_s=f.float("uptime_s", 0.0),
                   received=f.int("received", 0), published=f.int("published", 0),
                   dropped=f.int("dropped", 0), rejected=rejected, latency_ms=latency,
                   skipped=skipped)


MESSAGE_TYPES: tuple[type[Message], ...] = (RgbdFrame, HandLandmarks, HandBody, KinematicModel,
                                            KinematicModelList,
                                            RobotState, ArticulateRequest, ArticulateResult,
                                            Ack, ServiceStats)
