"""The worker protocol: raw-array frames round-trip; malformed frames are refused early."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from submissions.protocol import (
    HEAD_MAX,
    HEADER,
    MAX_FRAME,
    MAX_NDIM,
    MAX_TEXT,
    SEQ_MODULO,
    Kind,
    ProtocolError,
    ShortFrame,
    cap_text,
    decode_frame,
    encode,
    encode_json,
    encode_text,
)

DTYPES = [np.float32, np.float64, np.int32, np.int64, np.uint8, np.bool_]


@given(
    arr=hnp.arrays(
        dtype=st.sampled_from(DTYPES),
        shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5),
    ),
    kind=st.sampled_from(list(Kind)),
)
def test_arrays_round_trip_exactly(arr: np.ndarray, kind: Kind) -> None:
    data = encode(kind, arr)
    if len(data) > HEAD_MAX:  # the head alone tells how much more to copy
        with pytest.raises(ShortFrame) as short:
            decode_frame(data[:HEAD_MAX], trailing=True)
        assert short.value.length == len(data)
    assert decode_frame(data + b"more", trailing=True).array.shape == arr.shape
    frame = decode_frame(data)
    assert frame.kind == kind
    assert frame.array.dtype == arr.dtype and frame.array.shape == arr.shape
    np.testing.assert_array_equal(frame.array, arr)


def test_a_frame_must_span_its_bytes_exactly() -> None:
    """A reader copies the head, then exactly the frame: a copy cut short or padded (the
    peer changed the header in between) is refused, never decoded from what follows."""
    data = encode(Kind.ACT, np.arange(7, dtype=np.float32))
    for cut in (0, 10, HEADER.size, len(data) - 1):
        with pytest.raises(ProtocolError):
            decode_frame(data[:cut])
    with pytest.raises(ProtocolError, match=f"in {len(data) + 3} bytes"):
        decode_frame(data + b"\0" * 3)
    with pytest.raises(ProtocolError, match="needs 16 bytes"):
        decode_frame(data[:15], trailing=True)


def test_other_numeric_dtypes_are_widened_and_text_travels_as_utf8() -> None:
    frame = decode_frame(encode(Kind.ACTION, np.array([1, 2], dtype=np.int16)))
    assert frame.array.dtype == np.int32
    for wide, narrow in (
        (np.float16, np.float32),
        (np.uint16, np.int32),
        (np.uint64, np.int64),
        (np.dtype(">f4"), np.float32),  # big-endian input, little-endian frame
        (np.longdouble, np.float64),
    ):
        frame = decode_frame(encode(Kind.ACTION, np.array([1, 2], dtype=wide)))
        assert frame.array.dtype == narrow and frame.array.tolist() == [1, 2]
    frame = decode_frame(encode(Kind.ACTION, np.arange(6.0).reshape(2, 3).T))  # not C order
    np.testing.assert_array_equal(frame.array, np.arange(6.0).reshape(2, 3).T)
    frame = decode_frame(encode_text(Kind.ERROR, "crash: ünïcode"))
    assert frame.text == "crash: ünïcode"
    frame = decode_frame(encode_json(Kind.READY, {"name": "x"}))
    assert frame.text == '{"name": "x"}'
    frame = decode_frame(encode_text(Kind.ERROR, "x" * (MAX_TEXT * 3)))
    assert len(frame.text) == MAX_TEXT


@pytest.mark.parametrize(
    "value",
    [np.array(["left"]), np.array([object()]), np.array([1 + 2j]), np.zeros((1,) * 9)],
    ids=["text", "object", "complex", "9-dims"],
)
def test_encode_refuses_what_is_not_a_plain_array(value: np.ndarray) -> None:
    with pytest.raises(ProtocolError):
        encode(Kind.ACTION, value)


def _header(
    magic: bytes = b"SL", kind: int = 5, code: int = 1, ndim: int = 1, nbytes: int = 8
) -> bytes:
    return HEADER.pack(magic, kind, code, ndim, 0, nbytes)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (_header(magic=b"PK"), "magic"),
        (_header(kind=99), "kind"),
        (_header(code=42), "dtype"),
        (_header(ndim=9), "axes"),
        (_header(nbytes=MAX_FRAME + 1), "exceeds"),
        (_header(nbytes=1 << 40), "exceeds"),
        (_header(nbytes=12) + struct.pack("<Q", 2), "does not match"),
    ],
    ids=["magic", "kind", "dtype", "ndim", "oversize", "huge", "shape-mismatch"],
)
def test_bad_headers_are_refused_before_any_payload(data: bytes, message: str) -> None:
    if message != "does not match":  # the header alone is bad: refused, not "copy more"
        with pytest.raises(ProtocolError, match=message) as err:
            decode_frame(data[:16], trailing=True)
        assert not isinstance(err.value, ShortFrame)
    with pytest.raises(ProtocolError, match=message):
        decode_frame(data)


def test_a_smaller_cap_is_enforced() -> None:
    with pytest.raises(ProtocolError, match="exceeds"):
        decode_frame(encode(Kind.ACT, np.zeros(5, np.float32)), max_frame=16)


def test_the_frame_cap_is_inclusive() -> None:
    """A payload of exactly ``max_frame`` bytes passes; one byte more is refused unread."""
    exact = encode(Kind.ACT, np.zeros(16, np.uint8))
    assert decode_frame(exact, max_frame=16).array.size == 16
    with pytest.raises(ProtocolError, match="exceeds"):
        decode_frame(encode(Kind.ACT, np.zeros(17, np.uint8))[:16], max_frame=16, trailing=True)
    with pytest.raises(ProtocolError, match="exceeds"):
        encode(Kind.ACT, np.zeros(MAX_FRAME + 1, np.uint8))
    assert len(encode(Kind.ACT, np.zeros(MAX_FRAME, np.uint8))) == HEADER.size + 8 + MAX_FRAME


@pytest.mark.parametrize("seq", [0, 1, 7, 65_535, 65_536, 65_537])
def test_sequence_numbers_travel_in_the_header_and_wrap(seq: int) -> None:
    frame = decode_frame(encode(Kind.ACTION, np.zeros(2, np.float32), seq))
    assert frame.seq == seq % SEQ_MODULO
    frame = decode_frame(encode_text(Kind.ERROR, "boom", seq))
    assert frame.seq == seq % SEQ_MODULO and frame.text == "boom"


@pytest.mark.parametrize(
    "shape",
    [(0, 1 << 63), (0,) + (1 << 24,) * 7, (1 << 62, 0)],
    ids=["zero-by-2^63", "zero-by-huge-axes", "2^62-by-zero"],
)
def test_a_zero_size_frame_with_absurd_axes_is_a_protocol_error(shape: tuple[int, ...]) -> None:
    """The shape of the issue's finding: a header whose shape numpy cannot build (it raised
    ValueError, which killed the host's reader thread) must be a ProtocolError."""
    data = HEADER.pack(b"SL", 5, 1, len(shape), 3, 0) + b"".join(
        struct.pack("<Q", n) for n in shape
    )
    with pytest.raises(ProtocolError, match="shape"):
        decode_frame(data)


def test_cap_text_keeps_short_text_and_cuts_long_text_to_the_byte() -> None:
    assert cap_text("short") == "short"
    long = "é" * 10_000  # two bytes each: the cut must not split a character
    capped = cap_text(long, 4096)
    assert len(capped.encode()) <= 4096 and capped.startswith("é" * 100)
    assert "more bytes cut" in capped


def test_frames_are_numbered_zero_unless_told_and_text_frames_pass_the_number_on() -> None:
    """A frame without a sequence number is number 0 (what a policy's first answer matches);
    the text and JSON encoders carry a given number through."""
    assert decode_frame(encode(Kind.ACT, np.zeros(2, np.float32))).seq == 0
    assert decode_frame(encode_text(Kind.ERROR, "x")).seq == 0
    assert decode_frame(encode_json(Kind.READY, {"a": 1})).seq == 0
    assert decode_frame(encode_json(Kind.READY, {"a": 1}, 7)).seq == 7
    assert decode_frame(encode_text(Kind.ERROR, "x", 9)).seq == 9


def test_no_array_is_an_empty_byte_frame() -> None:
    frame = decode_frame(encode(Kind.RESET))
    assert frame.array.dtype == np.uint8 and frame.array.shape == (0,)


def test_the_axis_cap_is_inclusive_and_refusals_say_why() -> None:
    ok = np.zeros((1,) * MAX_NDIM, np.float32)
    assert decode_frame(encode(Kind.ACT, ok)).array.shape == ok.shape
    with pytest.raises(ProtocolError, match=f"an array with {MAX_NDIM + 1} axes"):
        encode(Kind.ACT, np.zeros((1,) * (MAX_NDIM + 1), np.float32))
    with pytest.raises(ProtocolError, match="cannot send an array of dtype <U1"):
        encode(Kind.ACT, np.array(["a"]))


def test_text_that_is_not_valid_unicode_is_replaced_not_refused() -> None:
    # A policy's error text may hold a lone surrogate (from a bytes-decoding accident):
    # it still travels, the bad character replaced.
    frame = decode_frame(encode_text(Kind.ERROR, "bad \ud800 text"))
    assert bytes(frame.array) == b"bad ? text"


@pytest.mark.parametrize("cut", ["in_shape", "in_payload"])
def test_a_short_frame_says_how_long_the_whole_frame_is(cut: str) -> None:
    """The host reads a frame in pieces: ``ShortFrame.length`` is how many bytes to wait for,
    and the message says how many it has."""
    data = encode(Kind.ACT, np.zeros((3, 4), np.float32))  # 16 + 2*8 shape bytes + 48
    have = HEADER.size + 4 if cut == "in_shape" else len(data) - 5
    with pytest.raises(ShortFrame) as err:
        decode_frame(data[:have])
    assert err.value.length == len(data) == HEADER.size + 16 + 48
    assert str(err.value) == f"a frame of {len(data)} bytes in {have} bytes"


def test_a_frame_with_bytes_after_it_says_both_lengths() -> None:
    data = encode(Kind.ACT, np.zeros(4, np.float32))
    with pytest.raises(
        ProtocolError, match=f"^a frame of {len(data)} bytes in {len(data) + 3} bytes$"
    ):
        decode_frame(data + b"xyz")


def _outcome(decode: object, data: bytes, max_frame: int, trailing: bool) -> object:
    """What a decoder makes of ``data``: the frame's fields, or the refusal's type and text."""
    try:
        frame = decode(data, max_frame, trailing=trailing)  # type: ignore[operator]
    except ProtocolError as err:
        return (type(err).__name__, str(err))
    return (frame.kind, frame.seq, frame.array.dtype.str, frame.array.shape, frame.array.tobytes())


@given(
    arr=hnp.arrays(
        dtype=st.sampled_from(DTYPES),
        shape=hnp.array_shapes(min_dims=0, max_dims=2, min_side=0, max_side=6),
    ),
    flips=st.lists(st.tuples(st.integers(0, 40), st.integers(0, 255)), max_size=3),
    cut=st.integers(-8, 8),
    max_frame=st.sampled_from([MAX_FRAME, 16, 0]),
    trailing=st.booleans(),
)
@settings(max_examples=400)
@example(np.zeros(3, np.float32), [], 4, MAX_FRAME, False)  # padded, not allowed
@example(np.zeros(3, np.float32), [], 4, MAX_FRAME, True)  # padded, allowed
@example(np.zeros(3, np.float32), [], -1, MAX_FRAME, True)  # cut short
@example(np.zeros(5, np.float32), [], 0, 16, False)  # over the cap
@example(np.zeros(3, np.float32), [(16, 4)], 0, MAX_FRAME, False)  # axis and bytes disagree
def test_the_one_axis_shortcut_decodes_exactly_as_the_general_path(
    arr: np.ndarray, flips: list[tuple[int, int]], cut: int, max_frame: int, trailing: bool
) -> None:
    # decode_frame takes a shortcut for one-axis frames (observations, actions, text); on
    # any frame, valid, corrupted, cut short or padded, it must decide as the step-by-step
    # path does: the same frame, or the same refusal.
    from submissions.protocol import _decode_general

    data = bytearray(encode(Kind.ACT, arr, 7))
    for at, value in flips:
        if at < len(data):
            data[at] = value
    data = data[: len(data) + cut] if cut < 0 else data + bytes(cut)
    fast = _outcome(decode_frame, bytes(data), max_frame, trailing)
    general = _outcome(_decode_general, bytes(data), max_frame, trailing)
    assert fast == general


def _encoded(kind: Kind, arr: object, seq: int) -> object:
    """The bytes :func:`encode` makes of ``arr``, or the refusal's type and text."""
    from submissions.protocol import _encode_general

    try:
        return _encode_general(kind, arr, seq)  # type: ignore[arg-type]
    except ProtocolError as err:
        return (type(err).__name__, str(err))


@given(
    arr=hnp.arrays(
        dtype=st.sampled_from(
            [*DTYPES, ">f4", ">f8", "<f2", "<i2", "<u2", "<u4", "<u8", "i1", ">i4", "=f4", "c8"]
        ),
        shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5),
    ),
    seq=st.integers(0, 3 * (1 << 16)),
    kind=st.sampled_from(list(Kind)),
)
@settings(max_examples=400)
@example(np.arange(6, dtype=np.float32)[::2], 3, Kind.ACT)  # a strided view
@example(np.zeros(3, ">f4"), 1, Kind.ACTION)  # big-endian: widened by the general path
@example(np.zeros(3, np.dtype("<f4", metadata={"unit": "m"})), 1, Kind.ACT)  # dtype metadata
def test_the_one_axis_shortcut_encodes_exactly_as_the_general_path(
    arr: np.ndarray, seq: int, kind: Kind
) -> None:
    # encode() takes a shortcut for one-axis arrays of a dtype sent as it is (every
    # observation and action); on any array it must make the same bytes or the same refusal.
    try:
        fast: object = encode(kind, arr, seq)
    except ProtocolError as err:
        fast = (type(err).__name__, str(err))
    assert fast == _encoded(kind, np.asarray(arr), seq)
