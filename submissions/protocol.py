"""The policy worker protocol: raw-array frames, never pickle.

The race and a sandboxed policy exchange *frames*, one at a time each way, through the
shared-memory channel of :mod:`submissions.channel`. Each frame is a fixed 16-byte header,
the array's shape, then the array's raw little-endian bytes:

=======  ========  ==============================================================
offset   type      field
=======  ========  ==============================================================
0        2 bytes   magic ``b"SL"``
2        uint8     kind (:class:`Kind`)
3        uint8     dtype code (:data:`DTYPES`)
4        uint8     ndim (0–:data:`MAX_NDIM`)
5        uint8     reserved, zero
6        uint16    sequence number (a reply carries its request's; wraps at 2¹⁶)
8        uint64    payload length in bytes (≤ the reader's ``max_frame``)
16       ndim × 8  shape, uint64 each
…        payload   ``prod(shape) × itemsize`` bytes, C order
=======  ========  ==============================================================

Text (error messages, the worker's hello) travels as a uint8 array of UTF-8 (JSON where it
is structured). Every field is checked before a byte of payload is trusted: magic, kind,
dtype, ndim, ``payload == prod(shape) × itemsize`` and the size cap; a reader decodes only
its own copy of the bytes (:func:`decode_frame` decodes a copy, or says how much more to
copy: :class:`ShortFrame`), so a peer scribbling in the shared memory meanwhile can at most
produce a wrong or refused frame. Nothing is unpickled, so a
hostile peer can send at most a wrong array, which the receiver then validates.

A session, host → worker: ``RESET`` (int64 ``[seed]``, or empty for no seed) is answered by
``OK``; ``ACT`` (the observation) by ``ACTION``; ``CLOSE`` ends it. The worker opens with
``READY`` (JSON: name, format; sequence 0) once the policy has loaded, and answers anything
with ``ERROR`` (its exception, as text) or ``INVALID`` (an action it could not encode as
numbers). The host numbers its requests 1, 2, 3, … and has at most one outstanding; each
reply carries the number of the request it answers, and the host counts only the reply to
its current request (:mod:`submissions.remote`).
"""

from __future__ import annotations

import enum
import json
import math
import struct
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from submissions.errors import SubmissionError

MAGIC = b"SL"
HEADER = struct.Struct("<2sBBBxHQ")  # magic, kind, dtype code, ndim, sequence, payload bytes
DIM = struct.Struct("<Q")
MAX_NDIM = 8
MAX_FRAME = 16 << 20  # bytes of payload: far above any observation, well below host memory
MAX_TEXT = 4096  # bytes of an error message kept (sent, and kept by the host: dnf_detail)
SEQ_MODULO = 1 << 16
HEAD_MAX = HEADER.size + DIM.size * MAX_NDIM  # the longest header with its shape, bytes

# dtype code → numpy dtype (little-endian). A closed list: anything else is refused.
DTYPES: dict[int, np.dtype[Any]] = {
    1: np.dtype("<f4"),
    2: np.dtype("<f8"),
    3: np.dtype("<i4"),
    4: np.dtype("<i8"),
    5: np.dtype("u1"),
    6: np.dtype("?"),
}
_CODES = {dt.str: code for code, dt in DTYPES.items()}  # keyed by "<f4", "|u1"…: fast
_CODE_OF = {dt: code for code, dt in DTYPES.items()}  # keyed by the dtype itself: faster
_SHAPES = [struct.Struct(f"<{n}Q") for n in range(MAX_NDIM + 1)]  # a shape of n axes
_HEAD_1D = struct.Struct("<2sBBBxHQQ")  # a header and its one axis: most frames
_EMPTY = np.zeros(0, np.uint8)


class Kind(enum.IntEnum):
    """What a frame means (see the module docstring for who sends which)."""

    READY = 1
    RESET = 2
    OK = 3
    ACT = 4
    ACTION = 5
    ERROR = 6
    INVALID = 7
    CLOSE = 8


_KINDS = {int(kind): kind for kind in Kind}


class ProtocolError(SubmissionError):
    """A frame broke the protocol: bad magic, unknown kind or dtype, too large, truncated."""


class ShortFrame(ProtocolError):
    """The bytes hold the start of a valid frame, not all of it.

    Attributes:
        length: the whole frame's length, bytes (from its checked header).
    """

    def __init__(self, length: int, have: int) -> None:
        super().__init__(f"a frame of {length} bytes in {have} bytes")
        self.length = length


def cap_text(text: str, limit: int = MAX_TEXT) -> str:
    """``text`` cut to at most ``limit`` bytes of UTF-8 (a marker says how much was cut)."""
    data = text.encode("utf-8", "replace")
    if len(data) <= limit:
        return text
    marker = f" [… {len(data) - limit} more bytes cut]".encode()
    return data[: max(0, limit - len(marker))].decode("utf-8", "ignore") + marker.decode()


class Frame(NamedTuple):
    """One message: its kind, its array (``shape`` and ``dtype`` from the header), its number.

    (A named tuple: cheap to make, on every step's path.)
    """

    kind: Kind
    array: NDArray[Any]
    seq: int = 0

    @property
    def text(self) -> str:
        """The payload read as UTF-8 text (for ``READY``, ``ERROR`` and ``INVALID``)."""
        return bytes(self.array.astype(np.uint8, copy=False)).decode("utf-8", "replace")


_new_frame = tuple.__new__  # a Frame made without NamedTuple's Python-level __new__


def encode(kind: Kind, array: Any = None, seq: int = 0) -> bytes:
    """The frame for ``kind`` carrying ``array`` (default: an empty uint8 array), numbered ``seq``.

    Other numeric dtypes are widened to the nearest of :data:`DTYPES` (float16 → float32,
    int16/uint16 → int32, uint32/uint64 → int64, big-endian → little-endian).

    Raises:
        ProtocolError: the array is not numeric/bool, has more than ``MAX_NDIM`` axes, or is
            larger than ``MAX_FRAME`` bytes.
    """
    arr = _EMPTY if array is None else np.asarray(array)
    if arr.ndim == 1 and (code := _CODE_OF.get(arr.dtype)) is not None:
        # The usual frame (one axis, a dtype sent as it is): the same bytes, at once.
        payload = arr.tobytes()
        if (n := len(payload)) <= MAX_FRAME:
            return _HEAD_1D.pack(MAGIC, kind, code, 1, seq % SEQ_MODULO, n, arr.shape[0]) + payload
    return _encode_general(kind, arr, seq)


def _encode_general(kind: Kind, arr: NDArray[Any], seq: int) -> bytes:
    """:func:`encode` for any array, step by step (each refusal with its reason)."""
    code = _CODES.get(arr.dtype.str)
    if code is None:  # widen
        wide = arr.dtype.itemsize > 4
        if arr.dtype.kind == "f":
            arr = arr.astype("<f8" if wide else "<f4")
        elif arr.dtype.kind in "iu":
            arr = arr.astype("<i8" if wide else "<i4")
        code = _CODES.get(arr.dtype.str)
        if code is None:
            raise ProtocolError(f"cannot send an array of dtype {arr.dtype}")
    if arr.ndim > MAX_NDIM:
        raise ProtocolError(f"cannot send an array with {arr.ndim} axes (max {MAX_NDIM})")
    payload = arr.tobytes()  # C order, whatever the array's layout
    if len(payload) > MAX_FRAME:
        raise ProtocolError(f"frame of {len(payload)} bytes exceeds {MAX_FRAME}")
    header = HEADER.pack(MAGIC, kind, code, arr.ndim, seq % SEQ_MODULO, len(payload))
    return header + _SHAPES[arr.ndim].pack(*arr.shape) + payload


def encode_text(kind: Kind, text: str, seq: int = 0) -> bytes:
    """A frame carrying ``text`` (UTF-8, cut to ``MAX_TEXT`` bytes)."""
    data = text.encode("utf-8", "replace")[:MAX_TEXT]
    return encode(kind, np.frombuffer(data, dtype=np.uint8), seq)


def encode_json(kind: Kind, value: Any, seq: int = 0) -> bytes:
    """A frame carrying ``value`` as JSON text."""
    return encode_text(kind, json.dumps(value), seq)


def decode_frame(data: bytes, max_frame: int = MAX_FRAME, *, trailing: bool = False) -> Frame:
    """The frame that ``data`` holds: exactly all of ``data``, or with ``trailing`` its
    start (a copy larger than the frame; what follows the frame is ignored).

    Raises:
        ShortFrame: ``data`` holds a valid header but not the whole frame.
        ProtocolError: a bad header, a shape that does not match the payload, an axis or a
            payload over ``max_frame``, or (without ``trailing``) ``data`` longer than the
            frame.
    """
    if len(data) >= _HEAD_1D.size:  # the usual frame (one axis): the same checks, at once
        magic, code_kind, code, ndim, seq, nbytes, n = _HEAD_1D.unpack_from(data)
        kind, dtype = _KINDS.get(code_kind), DTYPES.get(code)
        end = _HEAD_1D.size + nbytes
        if (
            ndim == 1
            and magic == MAGIC
            and kind is not None
            and dtype is not None
            and nbytes <= max_frame  # so the axis is too: n == nbytes / itemsize
            and n * dtype.itemsize == nbytes
            and (len(data) == end or (trailing and len(data) > end))
        ):
            return _new_frame(Frame, (kind, np.frombuffer(data, dtype, n, _HEAD_1D.size), seq))
    # Anything else, every refusal and every short frame included, takes the general path.
    return _decode_general(data, max_frame, trailing)


def _decode_general(data: bytes, max_frame: int, trailing: bool) -> Frame:
    """:func:`decode_frame` for any frame, step by step (each refusal with its reason)."""
    kind, dtype, ndim, seq, nbytes = parse_header(data, max_frame)
    head = HEADER.size + DIM.size * ndim
    if len(data) < head:
        raise ShortFrame(head + nbytes, len(data))
    shape = _SHAPES[ndim].unpack_from(data, HEADER.size)
    # No axis longer than the cap (a zero-size array cannot smuggle in an axis of 2⁶³,
    # which numpy refuses with a ValueError), and the product must match the payload.
    if max(shape, default=0) > max_frame or math.prod(shape) * dtype.itemsize != nbytes:
        raise ProtocolError(f"frame shape {shape} of {dtype} does not match {nbytes} bytes")
    if len(data) < head + nbytes:
        raise ShortFrame(head + nbytes, len(data))
    if len(data) > head + nbytes and not trailing:
        raise ProtocolError(f"a frame of {head + nbytes} bytes in {len(data)} bytes")
    try:
        array = np.frombuffer(data, dtype=dtype, count=math.prod(shape), offset=head)
        if ndim != 1:
            array = array.reshape(shape)
    except ValueError as err:  # belt and braces: never let numpy's error escape
        raise ProtocolError(f"frame shape {shape}: {err}") from None
    return Frame(kind, array, seq)


def parse_header(
    header: bytes, max_frame: int = MAX_FRAME
) -> tuple[Kind, np.dtype[Any], int, int, int]:
    """Check the 16-byte header that ``header`` starts with; return ``(kind, dtype, ndim,
    sequence, payload bytes)``.

    Raises:
        ProtocolError: bad magic, kind, dtype code or ndim, a payload over ``max_frame``, or
            fewer than 16 bytes.
    """
    if len(header) < HEADER.size:
        raise ProtocolError(f"a frame header needs {HEADER.size} bytes, got {len(header)}")
    magic, code_kind, code, ndim, seq, nbytes = HEADER.unpack_from(header)
    if magic != MAGIC:
        raise ProtocolError(f"bad frame magic {magic!r}")
    kind = _KINDS.get(code_kind)
    if kind is None:
        raise ProtocolError(f"unknown frame kind {code_kind}")
    dtype = DTYPES.get(code)
    if dtype is None:
        raise ProtocolError(f"unknown dtype code {code}")
    if ndim > MAX_NDIM:
        raise ProtocolError(f"frame with {ndim} axes (max {MAX_NDIM})")
    if nbytes > max_frame:
        raise ProtocolError(f"frame of {nbytes} bytes exceeds the {max_frame}-byte limit")
    return kind, dtype, ndim, seq, nbytes
