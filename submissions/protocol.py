"""The policy worker protocol: length-prefixed raw-array frames over pipes, never pickle.

The race and a sandboxed policy exchange *frames*. Each frame is a fixed 16-byte header, the
array's shape, then the array's raw little-endian bytes:

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
dtype, ndim, ``payload == prod(shape) × itemsize`` and the size cap. Nothing is unpickled,
so a hostile peer can send at most a wrong array, which the receiver then validates.

A session, host → worker: ``RESET`` (int64 ``[seed]``, or empty for no seed) is answered by
``OK``; ``ACT`` (the observation) by ``ACTION``; ``CLOSE`` ends it. The worker opens with
``READY`` (JSON: name, format; sequence 0) once the policy has loaded, and answers anything
with ``ERROR`` (its exception, as text) or ``INVALID`` (an action it could not encode as
numbers). The host numbers its requests 1, 2, 3, … and has at most one outstanding; each
reply carries the number of the request it answers. The host counts only the reply to its
current request: any other (sent ahead, stale, unprompted) is a protocol violation and
retires the policy as ``invalid`` (:mod:`submissions.remote`); it never waits for one.
"""

from __future__ import annotations

import enum
import errno
import json
import math
import os
import struct
from dataclasses import dataclass
from typing import Any

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

# dtype code → numpy dtype (little-endian). A closed list: anything else is refused.
DTYPES: dict[int, np.dtype[Any]] = {
    1: np.dtype("<f4"),
    2: np.dtype("<f8"),
    3: np.dtype("<i4"),
    4: np.dtype("<i8"),
    5: np.dtype("u1"),
    6: np.dtype("?"),
}
_CODES = {dt: code for code, dt in DTYPES.items()}


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


class ProtocolError(SubmissionError):
    """A frame broke the protocol: bad magic, unknown kind or dtype, too large, truncated."""


def cap_text(text: str, limit: int = MAX_TEXT) -> str:
    """``text`` cut to at most ``limit`` bytes of UTF-8 (a marker says how much was cut)."""
    data = text.encode("utf-8", "replace")
    if len(data) <= limit:
        return text
    marker = f" [… {len(data) - limit} more bytes cut]".encode()
    return data[: max(0, limit - len(marker))].decode("utf-8", "ignore") + marker.decode()


@dataclass(frozen=True)
class Frame:
    """One message: its kind, its array (``shape`` and ``dtype`` from the header), its number."""

    kind: Kind
    array: NDArray[Any]
    seq: int = 0

    @property
    def text(self) -> str:
        """The payload read as UTF-8 text (for ``READY``, ``ERROR`` and ``INVALID``)."""
        return bytes(self.array.astype(np.uint8, copy=False)).decode("utf-8", "replace")


def encode(kind: Kind, array: Any = None, seq: int = 0) -> bytes:
    """The frame for ``kind`` carrying ``array`` (default: an empty uint8 array), numbered ``seq``.

    Raises:
        ProtocolError: the array is not numeric/bool, has more than ``MAX_NDIM`` axes, or is
            larger than ``MAX_FRAME`` bytes.
    """
    arr = np.zeros(0, np.uint8) if array is None else np.asarray(array)
    if arr.dtype.kind == "f":
        arr = arr.astype("<f8" if arr.dtype.itemsize > 4 else "<f4", copy=False)
    elif arr.dtype.kind in "iu" and arr.dtype != np.uint8:
        arr = arr.astype("<i8" if arr.dtype.itemsize > 4 else "<i4", copy=False)
    code = _CODES.get(arr.dtype)
    if code is None:
        raise ProtocolError(f"cannot send an array of dtype {arr.dtype}")
    if arr.ndim > MAX_NDIM:
        raise ProtocolError(f"cannot send an array with {arr.ndim} axes (max {MAX_NDIM})")
    payload = np.ascontiguousarray(arr).tobytes()
    if len(payload) > MAX_FRAME:
        raise ProtocolError(f"frame of {len(payload)} bytes exceeds {MAX_FRAME}")
    dims = b"".join(DIM.pack(n) for n in arr.shape)
    header = HEADER.pack(MAGIC, int(kind), code, arr.ndim, seq % SEQ_MODULO, len(payload))
    return header + dims + payload


def encode_text(kind: Kind, text: str, seq: int = 0) -> bytes:
    """A frame carrying ``text`` (UTF-8, cut to ``MAX_TEXT`` bytes)."""
    data = text.encode("utf-8", "replace")[:MAX_TEXT]
    return encode(kind, np.frombuffer(data, dtype=np.uint8), seq)


def encode_json(kind: Kind, value: Any, seq: int = 0) -> bytes:
    """A frame carrying ``value`` as JSON text."""
    return encode_text(kind, json.dumps(value), seq)


class FrameDecoder:
    """Turns a byte stream into frames, incrementally; validates each header first.

    Args:
        max_frame: the largest payload accepted, in bytes.
    """

    def __init__(self, max_frame: int = MAX_FRAME) -> None:
        self.max_frame = max_frame
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        """Bytes received that do not yet make a whole frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add ``data``; return the frames it completes (possibly none).

        Raises:
            ProtocolError: the stream is not a valid frame sequence (then the decoder is
                spent: a stream that broke once is not read further).
        """
        self._buf.extend(data)
        frames: list[Frame] = []
        while True:
            frame = self._next()
            if frame is None:
                return frames
            frames.append(frame)

    def _next(self) -> Frame | None:
        if len(self._buf) < HEADER.size:
            return None
        kind, dtype, ndim, seq, nbytes = parse_header(
            bytes(self._buf[: HEADER.size]), self.max_frame
        )
        head = HEADER.size + DIM.size * ndim
        if len(self._buf) < head:
            return None
        shape = tuple(
            DIM.unpack_from(self._buf, HEADER.size + DIM.size * i)[0] for i in range(ndim)
        )
        # No axis longer than the cap (a zero-size array cannot smuggle in an axis of 2⁶³,
        # which numpy refuses with a ValueError), and the product must match the payload.
        if any(n > self.max_frame for n in shape) or math.prod(shape) * dtype.itemsize != nbytes:
            raise ProtocolError(f"frame shape {shape} of {dtype} does not match {nbytes} bytes")
        if len(self._buf) < head + nbytes:
            return None
        payload = bytes(self._buf[head : head + nbytes])
        del self._buf[: head + nbytes]
        try:
            array = np.frombuffer(payload, dtype=dtype).reshape(shape)
        except ValueError as err:  # belt and braces: never let numpy's error escape
            raise ProtocolError(f"frame shape {shape}: {err}") from None
        return Frame(kind, array, seq)


def parse_header(
    header: bytes, max_frame: int = MAX_FRAME
) -> tuple[Kind, np.dtype[Any], int, int, int]:
    """Check a 16-byte header; return ``(kind, dtype, ndim, sequence, payload bytes)``.

    Raises:
        ProtocolError: bad magic, kind, dtype code or ndim, or a payload over ``max_frame``.
    """
    magic, kind, code, ndim, seq, nbytes = HEADER.unpack(header)
    if magic != MAGIC:
        raise ProtocolError(f"bad frame magic {magic!r}")
    if kind not in Kind.__members__.values():
        raise ProtocolError(f"unknown frame kind {kind}")
    if code not in DTYPES:
        raise ProtocolError(f"unknown dtype code {code}")
    if ndim > MAX_NDIM:
        raise ProtocolError(f"frame with {ndim} axes (max {MAX_NDIM})")
    if nbytes > max_frame:
        raise ProtocolError(f"frame of {nbytes} bytes exceeds the {max_frame}-byte limit")
    return Kind(kind), DTYPES[code], ndim, seq, nbytes


def write_all(fd: int, data: bytes) -> None:
    """Write all of ``data`` to a blocking file descriptor."""
    view = memoryview(data)
    while view:
        try:
            n = os.write(fd, view)
        except InterruptedError:
            continue
        view = view[n:]


def read_frame(fd: int, decoder: FrameDecoder) -> Frame | None:
    """Block until the next frame arrives on ``fd``; None at end of stream.

    Used by the worker, which has nothing else to do while it waits.

    Raises:
        ProtocolError: the stream is invalid, or ends inside a frame.
    """
    frames = decoder.feed(b"")
    while not frames:
        try:
            data = os.read(fd, 1 << 16)
        except OSError as err:
            if err.errno == errno.EINTR:
                continue
            raise
        if not data:
            if decoder.pending:
                raise ProtocolError("stream ended inside a frame")
            return None
        frames = decoder.feed(data)
    if len(frames) > 1:  # a well-behaved host never pipelines requests
        raise ProtocolError("more than one request at once")
    return frames[0]
