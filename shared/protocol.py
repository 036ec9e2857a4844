"""Robion's wire protocol: a msgpack header frame plus raw array frames.

A message is a list of ZeroMQ frames. Frame 0 is a msgpack map (the header). An array
travels as ``{"dtype": str, "shape": [int, ...], "frame": int}`` pointing at a later frame
holding its raw C-order bytes, or, when small, inline as ``{"dtype", "shape", "data": bin}``.
Arrays only appear at the places each message kind defines, so decoding never walks
untrusted structure looking for them. No pickle anywhere. docs/protocol.md is the
language-neutral description of the same thing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Sequence

import msgpack
import numpy as np

PROTOCOL_VERSION = 1
INLINE_ARRAY_BYTES = 1024  # arrays up to this size travel inside the header
MAX_HEADER_BYTES = 64 * 1024
MAX_ARRAY_DIMS = 8
MAX_MAP_LEN = 1024  # entries in any one header map, so also the most cameras a request can name
MAX_ID_CHARS = 256  # a longer string id is refused, never cut: the echo must be the id that was sent
# The most frames any valid message has: an infer request's header, one frame per camera image
# (the images map holds at most MAX_MAP_LEN) and one for the state. See max_frames() per kind.
MAX_FRAMES = 1 + MAX_MAP_LEN + 1
ALLOWED_DTYPES = frozenset({"uint8", "int8", "int32", "int64", "float16", "float32", "float64", "bool"})


class ErrorCode(str, Enum):
    BAD_REQUEST = "BAD_REQUEST"  # malformed message, wrong field types, missing fields
    UNKNOWN_MODEL = "UNKNOWN_MODEL"  # no such model is served
    SHAPE_MISMATCH = "SHAPE_MISMATCH"  # array shape or dtype differs from the model's declared input
    TOO_LARGE = "TOO_LARGE"  # message beyond the configured size limit
    OVERLOADED = "OVERLOADED"  # the model's queue is full
    DEADLINE_EXCEEDED = "DEADLINE_EXCEEDED"  # the deadline passed before the request could run
    UNAVAILABLE = "UNAVAILABLE"  # no executor can take the request now
    INTERNAL = "INTERNAL"  # a server fault; the request may be retried


class ProtocolError(Exception):
    """A request that cannot be served; becomes an error reply with a stable code."""

    def __init__(self, code: ErrorCode, message: str):
        super().__init__(f"{code.value}: {message}")
        self.code = code
        self.message = message


def shown(value: Any, limit: int = 60) -> str:
    """A value off the wire, quoted for an error message: a string or number as repr, cut to ``limit``
    characters; anything else by its type's name. repr of a list nested a thousand deep (about 1 KB of
    msgpack) raises RecursionError, which escaped the decoders' ProtocolError handling: the router answered
    nothing and the SDK raised out of poll()."""
    if value is None or isinstance(value, (str, int, float)):  # bool is an int
        text = repr(value)
        return text if len(text) <= limit else text[:limit] + "..."
    return f"a {type(value).__name__}"


Frame = bytes | memoryview
RequestId = str | int  # echoed with its wire type: 7 and "7" are two different requests


# ----------------------------------------------------------------------------- arrays

def encode_array(arr: np.ndarray, frames: list[Frame]) -> dict[str, Any]:
    """Describe ``arr`` in the header; large arrays are appended to ``frames`` without copying."""
    if not isinstance(arr, np.ndarray):
        raise TypeError(f"expected a numpy array, got {type(arr).__name__}")
    if arr.dtype.name not in ALLOWED_DTYPES:
        raise TypeError(f"dtype {arr.dtype.name} cannot travel; allowed: {sorted(ALLOWED_DTYPES)}")
    # The wire is little-endian and names dtypes without a byte order: a big-endian array (">f8") went out
    # under its name ("float64") with its bytes unswapped, and arrived as other numbers.
    arr = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
    ref: dict[str, Any] = {"dtype": arr.dtype.name, "shape": list(arr.shape)}
    if arr.nbytes <= INLINE_ARRAY_BYTES:
        ref["data"] = arr.tobytes()
    else:
        ref["frame"] = len(frames)
        frames.append(memoryview(arr).cast("B"))
    return ref


def decode_array(ref: Any, frames: Sequence[Frame], where: str, used: set[int] | None = None) -> np.ndarray:
    """Rebuild an array from its header reference; zero-copy for frame-borne arrays.

    Every declared size is checked against the bytes actually present, so an absurd shape
    costs nothing and never allocates.
    """
    if not isinstance(ref, dict):
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}: expected an array object {{dtype, shape, frame|data}}")
    dtype, shape = ref.get("dtype"), ref.get("shape")
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}.dtype: expected one of {sorted(ALLOWED_DTYPES)}, got {shown(dtype)}")
    if (not isinstance(shape, (list, tuple)) or len(shape) > MAX_ARRAY_DIMS
            or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**31 for d in shape)):
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}.shape: expected a list of at most {MAX_ARRAY_DIMS} non-negative integers")
    np_dtype = np.dtype(dtype)
    nbytes = math.prod(shape) * np_dtype.itemsize
    if "frame" in ref:
        idx = ref["frame"]
        if not isinstance(idx, int) or isinstance(idx, bool) or not 1 <= idx < len(frames):
            raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}.frame: {shown(idx)} does not name one of the {len(frames) - 1} array frames")
        if used is not None:
            if idx in used:
                raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}.frame: frame {idx} is referenced twice")
            used.add(idx)
        buf = frames[idx]
    elif "data" in ref:
        buf = ref["data"]
        if not isinstance(buf, (bytes, bytearray)):
            raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}.data: expected binary")
    else:
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}: needs 'frame' or 'data'")
    if len(buf) != nbytes:
        raise ProtocolError(ErrorCode.BAD_REQUEST,
                            f"{where}: shape {list(shape)} of {dtype} needs {nbytes} bytes, got {len(buf)}")
    try:
        return np.frombuffer(buf, dtype=np_dtype).reshape(shape)
    except ValueError:  # a zero dim beside dims numpy cannot hold, e.g. [0, 2**31-1, 2**31-1, 2**31-1]: 0 bytes match
        raise ProtocolError(ErrorCode.BAD_REQUEST,
                            f"{where}: shape {list(shape)} is beyond what an array can hold") from None


# ----------------------------------------------------------------------------- messages

@dataclass
class ModelInfo:
    """What a robot must send to a model and what it gets back (part of the metadata reply)."""

    cameras: list[str]
    image_shape: list[int]  # [H, W, 3], uint8
    state_dim: int
    horizon: int
    action_dim: int
    deadline_ms: float
    arch: str = ""

    def to_wire(self) -> dict[str, Any]:
        return {"cameras": list(self.cameras), "image_shape": list(self.image_shape), "state_dim": self.state_dim,
                "horizon": self.horizon, "action_dim": self.action_dim, "deadline_ms": self.deadline_ms,
                "arch": self.arch}

    @classmethod
    def from_wire(cls, d: dict[str, Any]) -> "ModelInfo":
        """Raises ValueError, naming what failed, for a description of the wrong shape or with a wrong value.

        One error type for every caller (the SDK's decode, the control plane's register, the router's
        routing table): the conversions below raise KeyError (a missing field), TypeError or
        AttributeError (not a map), ValueError (int("x")) and OverflowError (int(inf))."""
        try:
            return cls(cameras=list(d["cameras"]), image_shape=list(d["image_shape"]), state_dim=int(d["state_dim"]),
                       horizon=int(d["horizon"]), action_dim=int(d["action_dim"]),
                       deadline_ms=float(d["deadline_ms"]), arch=str(d.get("arch", "")))
        except (KeyError, TypeError, AttributeError, ValueError, OverflowError) as exc:
            raise ValueError(f"{type(exc).__name__}: {exc}") from None


@dataclass
class Timings:
    queue_ms: float = 0.0
    vlm_ms: float = 0.0
    action_ms: float = 0.0
    server_ms: float = 0.0

    def to_wire(self) -> dict[str, float]:
        return {"queue_ms": self.queue_ms, "vlm_ms": self.vlm_ms, "action_ms": self.action_ms, "server_ms": self.server_ms}


@dataclass
class InferRequest:
    id: RequestId
    robot: str
    model: str
    images: dict[str, np.ndarray]  # camera name -> uint8 [H, W, 3]
    state: np.ndarray  # float32 [state_dim]
    instruction: str = ""


@dataclass
class InferReply:
    id: RequestId
    model: str
    actions: np.ndarray  # float32 [horizon, action_dim]
    timings: Timings = field(default_factory=Timings)


@dataclass
class ErrorReply:
    id: RequestId
    code: ErrorCode
    message: str


@dataclass
class Hello:
    id: RequestId


@dataclass
class Metadata:
    id: RequestId
    models: dict[str, ModelInfo]
    protocol: int = PROTOCOL_VERSION


@dataclass
class Ping:
    id: RequestId


@dataclass
class Pong:
    id: RequestId


Message = InferRequest | InferReply | ErrorReply | Hello | Metadata | Ping | Pong


def pack_header(header: dict[str, Any]) -> bytes:
    return msgpack.packb(header, use_bin_type=True)


def unpack_header(frame: Frame) -> dict[str, Any]:
    """Decode frame 0 with hard limits, so hostile input cannot make msgpack allocate much."""
    return unpack_map(frame, max_bytes=MAX_HEADER_BYTES, max_map_len=MAX_MAP_LEN, max_array_len=4096, what="header")


# An answer's header may be larger than a request's: a `metadata` answer describes every served model (about
# 140 bytes each, past 64 KiB at some 450 models). A client still bounds what the router can make it allocate.
MAX_ANSWER_HEADER_BYTES = 16 * 1024 * 1024
MAX_ANSWER_LEN = 1 << 20  # entries in any one map or array of an answer's header


def unpack_answer_header(frame: Frame) -> dict[str, Any]:
    """Decode frame 0 of an answer from the router (a client's side), with the answer limits above."""
    return unpack_map(frame, max_bytes=MAX_ANSWER_HEADER_BYTES, max_map_len=MAX_ANSWER_LEN,
                      max_array_len=MAX_ANSWER_LEN, what="header")


def unpack_map(frame: Frame, max_bytes: int, max_map_len: int, max_array_len: int, what: str) -> dict[str, Any]:
    """Decode one msgpack map of at most ``max_bytes`` bytes and ``max_*_len`` entries per map / array.

    ProtocolError TOO_LARGE beyond ``max_bytes``, BAD_REQUEST for anything that is not such a map.
    Robots' headers use the limits above (unpack_header); the services' own control messages,
    which grow with the cluster, use larger ones (shared.control.unpack).
    """
    if len(frame) > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"{what} is {len(frame)} bytes; the limit is {max_bytes}")
    try:
        header = msgpack.unpackb(frame, raw=False, strict_map_key=True,
                                 max_str_len=max_bytes, max_bin_len=max_bytes,
                                 max_array_len=max_array_len, max_map_len=max_map_len, max_ext_len=0)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{what} is not valid msgpack ({type(exc).__name__})") from None
    if not isinstance(header, dict):
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{what} must be a msgpack map")
    return header


def valid_id(rid: Any) -> bool:
    """A str of at most MAX_ID_CHARS characters or an int; msgpack true/false is not an int here."""
    if isinstance(rid, str):
        return len(rid) <= MAX_ID_CHARS
    return isinstance(rid, int) and not isinstance(rid, bool)


def header_id(header: dict[str, Any]) -> RequestId:
    """The request id exactly as sent, or "" when absent or unusable (errors still get a reply)."""
    rid = header.get("id", "")
    return rid if valid_id(rid) else ""


def check_header(header: dict[str, Any]) -> RequestId:
    """Check what every message kind shares, ``v`` and ``id``; returns the id.

    ``v`` must be exactly the int 1: True compares equal to 1 in Python but is msgpack's
    true, which no client means as a version.
    """
    version = header.get("v", PROTOCOL_VERSION)
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise ProtocolError(ErrorCode.BAD_REQUEST,
                            f"v: protocol version {shown(version)} is not supported (this server speaks {PROTOCOL_VERSION})")
    rid = header.get("id", "")
    if not valid_id(rid):
        raise ProtocolError(ErrorCode.BAD_REQUEST,
                            f"id: expected a str of at most {MAX_ID_CHARS} characters or an int, got "
                            f"{type(rid).__name__}{f' of {len(rid)} characters' if isinstance(rid, str) else ''}")
    return rid


def max_frames(kind: Any, cameras: int | None = None) -> int:
    """The most frames a valid message of ``kind`` can have: the header plus one per array it carries.

    Arrays sit only where a kind defines them (an infer request's camera images and state, a
    reply's actions), and each may also travel inline, so this is an upper bound. With the
    model's camera count known the bound for a request is exact; without it, the images map
    is still capped at MAX_MAP_LEN entries by the header decoder.
    """
    if kind == "infer":
        return 1 + (MAX_MAP_LEN if cameras is None else cameras) + 1
    if kind == "reply":
        return 2
    if kind in ("hello", "metadata", "error", "ping", "pong"):
        return 1
    return MAX_FRAMES  # an unknown kind is refused on its own account


def encode(msg: Message) -> list[Frame]:
    frames: list[Frame] = [b""]
    if isinstance(msg, InferRequest):
        # What the router's header decoder refuses (strict string keys, at most MAX_MAP_LEN entries) could only
        # be answered with id "": refused here instead, so a client learns now rather than at its timeout.
        if not all(isinstance(cam, str) for cam in msg.images):
            raise TypeError("images: camera names must be strings")
        if len(msg.images) > MAX_MAP_LEN:
            raise ValueError(f"images: at most {MAX_MAP_LEN} cameras, got {len(msg.images)}")
        header = {"v": PROTOCOL_VERSION, "kind": "infer", "id": msg.id, "robot": msg.robot, "model": msg.model,
                  "obs": {"images": {cam: encode_array(img, frames) for cam, img in msg.images.items()},
                          "state": encode_array(np.asarray(msg.state, dtype=np.float32), frames),
                          "instruction": msg.instruction}}
    elif isinstance(msg, InferReply):
        header = {"v": PROTOCOL_VERSION, "kind": "reply", "id": msg.id, "model": msg.model,
                  "actions": encode_array(np.asarray(msg.actions, dtype=np.float32), frames),
                  "timings": msg.timings.to_wire()}
    elif isinstance(msg, ErrorReply):
        header = {"v": PROTOCOL_VERSION, "kind": "error", "id": msg.id, "code": ErrorCode(msg.code).value,
                  "message": msg.message}
    elif isinstance(msg, Hello):
        header = {"v": PROTOCOL_VERSION, "kind": "hello", "id": msg.id}
    elif isinstance(msg, Metadata):
        header = {"v": PROTOCOL_VERSION, "kind": "metadata", "id": msg.id, "protocol": msg.protocol,
                  "models": {name: info.to_wire() for name, info in msg.models.items()}}
    elif isinstance(msg, Ping):
        header = {"v": PROTOCOL_VERSION, "kind": "ping", "id": msg.id}
    elif isinstance(msg, Pong):
        header = {"v": PROTOCOL_VERSION, "kind": "pong", "id": msg.id}
    else:
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    frames[0] = pack_header(header)
    return frames


def _field(header: dict[str, Any], name: str, typ: type | tuple[type, ...], where: str = "") -> Any:
    if name not in header:
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}{name}: missing")
    value = header[name]
    types = typ if isinstance(typ, tuple) else (typ,)
    # bool is an int subclass in Python, but msgpack true/false is never a valid number here.
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
        names = "/".join(t.__name__ for t in types)
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"{where}{name}: expected {names}, got {type(value).__name__}")
    return value


def decode(frames: Sequence[Frame], header: dict[str, Any] | None = None) -> Message:
    """Decode a whole message; raises ProtocolError(BAD_REQUEST) on anything malformed."""
    if not frames:
        raise ProtocolError(ErrorCode.BAD_REQUEST, "empty message")
    if header is None:
        header = unpack_header(frames[0])
    rid = check_header(header)
    kind = _field(header, "kind", str)
    used: set[int] = set()
    msg: Message
    if kind == "infer":
        robot = _field(header, "robot", str)
        model = _field(header, "model", str)
        obs = _field(header, "obs", dict)
        images_ref = _field(obs, "images", dict, "obs.")
        images = {}
        for cam, ref in images_ref.items():
            if not isinstance(cam, str):
                raise ProtocolError(ErrorCode.BAD_REQUEST, "obs.images: camera names must be strings")
            images[cam] = decode_array(ref, frames, f"obs.images.{cam}", used)
        state = decode_array(_field(obs, "state", dict, "obs."), frames, "obs.state", used)
        instruction = obs.get("instruction", "")
        if not isinstance(instruction, str):
            raise ProtocolError(ErrorCode.BAD_REQUEST, f"obs.instruction: expected str, got {type(instruction).__name__}")
        msg = InferRequest(id=rid, robot=robot, model=model, images=images, state=state, instruction=instruction)
    elif kind == "reply":
        timings = header.get("timings", {})
        # Checked like any other field: a bad value used to escape as AttributeError / TypeError / ValueError,
        # which callers that catch ProtocolError (the SDK fails the request a garbled reply answers) did not expect.
        if not isinstance(timings, dict) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool)
                for k, v in timings.items() if k in Timings.__dataclass_fields__):
            raise ProtocolError(ErrorCode.BAD_REQUEST, "timings: expected a map of numbers")
        msg = InferReply(id=rid, model=str(header.get("model", "")),
                         actions=decode_array(_field(header, "actions", dict), frames, "actions", used),
                         timings=Timings(**{k: float(v) for k, v in timings.items() if k in Timings.__dataclass_fields__}))
    elif kind == "error":
        code = _field(header, "code", str)
        try:
            code_enum = ErrorCode(code)
        except ValueError:
            code_enum = ErrorCode.INTERNAL
        msg = ErrorReply(id=rid, code=code_enum, message=str(header.get("message", "")))
    elif kind == "hello":
        msg = Hello(id=rid)
    elif kind == "metadata":
        models = _field(header, "models", dict)
        try:
            infos = {name: ModelInfo.from_wire(info) for name, info in models.items()}
        except ValueError as exc:
            raise ProtocolError(ErrorCode.BAD_REQUEST, f"models: malformed model description ({exc})") from None
        protocol = header.get("protocol", PROTOCOL_VERSION)
        if type(protocol) is not int:
            raise ProtocolError(ErrorCode.BAD_REQUEST, f"protocol: expected int, got {type(protocol).__name__}")
        msg = Metadata(id=rid, protocol=protocol, models=infos)
    elif kind == "ping":
        msg = Ping(id=rid)
    elif kind == "pong":
        msg = Pong(id=rid)
    else:
        raise ProtocolError(ErrorCode.BAD_REQUEST, f"kind: unknown message kind {shown(kind)}")
    if len(used) != len(frames) - 1:
        raise ProtocolError(ErrorCode.BAD_REQUEST,
                            f"message has {len(frames) - 1} array frames but the header references {len(used)}")
    return msg


def error_frames(request_id: RequestId, code: ErrorCode, message: str) -> list[Frame]:
    return encode(ErrorReply(id=request_id, code=code, message=message[:1024]))


def message_bytes(frames: Sequence[Frame]) -> int:
    return sum(len(f) for f in frames)
