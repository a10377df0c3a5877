"""The shared-memory channel between the race and one sandboxed policy.

One request and one reply at a time, each a frame of :mod:`submissions.protocol`, in a
region of memory the host creates and shares with the worker it starts, plus two pipes
that carry nothing but wake-ups:

=====================  ==================================================================
piece                  what it is, and why the worker cannot hurt the host with it
=====================  ==================================================================
the region             an anonymous ``memfd`` (no name under ``/dev/shm``, nothing another
                       process can open: only the worker inherits it): the request slot
                       (``request_bytes``, fitted to the observation) then the reply slot
                       (:data:`REPLY_BYTES`). Its size is fixed by the host and *sealed*
                       (``F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_SEAL``) before the worker gets
                       it: no ``ftruncate`` can make the host's mapping fault (SIGBUS), no
                       ``fallocate`` grow it. A worker may map it larger than it is (its
                       own SIGBUS) or scribble in it at any time (the host reads copies)
the ring               a pipe, host → worker: one byte after each request, written on the
                       host's own non-blocking end (a full pipe means the worker has a
                       wake-up pending already, so the host never waits on it)
the bell               a pipe, worker → host: one byte after each reply. The host reads it
                       non-blocking, with a deadline, counts the bytes (more rings than
                       requests: the policy woke the host unasked) and sees the worker's
                       end close (end of file) when it dies
=====================  ==================================================================

Pipes, not eventfds, for the wake-ups: an eventfd is *one* open file shared by both sides,
so a worker could clear its ``O_NONBLOCK`` and saturate its counter, and the host's next
write would block for good; each end of a pipe is an open file of its own, whose flags the
other side cannot touch.

The host decodes a reply only from its own copy: one copy of the slot's first
:data:`FIRST_COPY` bytes, which holds any action, OK or short text whole; a longer frame
(the hello, an error's text) is bounded by the slot from that copy's header
(:class:`~submissions.protocol.ShortFrame`) and copied again whole, and everything is
checked again on that second copy (:func:`~submissions.protocol.decode_frame`). A worker
scribbling in the slot meanwhile gets a refused frame or a wrong action (validated like any
other), never a host fault, a read outside the slot or a blocked host.

The worker's side, :class:`WorkerChannel`, waits on the ring and answers in the reply slot.
"""

from __future__ import annotations

import contextlib
import fcntl
import mmap
import os
import struct

from submissions.protocol import (
    HEAD_MAX,
    Frame,
    ProtocolError,
    ShortFrame,
    decode_frame,
)

REPLY_BYTES = 16 << 10  # the reply slot: an action, OK, the hello or ≤ 4 KiB of error text
_SEQ = struct.Struct("<H")  # a frame header's sequence number (protocol.HEADER) …
_SEQ_OFFSET = 6  # … at this offset
_SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL
_ONE = b"\x01"
FIRST_COPY = 512  # bytes a reader copies first: header, shape and any small payload
WAKE_READ = 4096  # bytes of wake-ups read at once (an honest worker has 1 pending)


def request_bytes_for(shape: tuple[int, ...] | list[int]) -> int:
    """The request slot that fits an observation of ``shape`` in any dtype (≤ 8 bytes per
    value) with its header, bytes, rounded up to whole pages."""
    values = 1
    for n in shape:
        values *= int(n)
    return _pages(HEAD_MAX + 8 * values)


def _read_frame(memory: mmap.mmap, start: int, room: int) -> Frame:
    """The frame in ``memory[start : start + room]``, decoded from the reader's own copy.

    One copy of the first :data:`FIRST_COPY` bytes holds a whole action, OK or short text
    frame (decoded from it alone); a longer frame is copied again, whole, and checked again
    on that copy (:func:`decode_frame`), so a slot rewritten between the two copies yields
    a refused frame, never one assembled from both.

    Raises:
        ProtocolError: no valid frame, or one longer than ``room``.
    """
    try:
        return decode_frame(memory[start : start + min(room, FIRST_COPY)], room, trailing=True)
    except ShortFrame as short:
        length = short.length
    if length > room:
        raise ProtocolError(f"a frame of {length} bytes in a {room}-byte slot")
    return decode_frame(memory[start : start + length], room)


def _pages(nbytes: int) -> int:
    return -(-max(nbytes, 1) // mmap.PAGESIZE) * mmap.PAGESIZE


class Channel:
    """The host's side of a channel (see the module docstring).

    Args:
        request_bytes: room for the largest request, bytes (:func:`request_bytes_for`).

    Attributes:
        bell: the read end of the bell (non-blocking; poll it for ``POLLIN``).
        request_bytes: the request slot's size, bytes (whole pages).
    """

    def __init__(self, request_bytes: int) -> None:
        self.request_bytes = _pages(max(request_bytes, HEAD_MAX))
        self._reply_at = self.request_bytes
        size = self.request_bytes + REPLY_BYTES
        opened: list[int] = []
        try:
            memfd = os.memfd_create("slipstream-channel", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
            opened.append(memfd)
            os.ftruncate(memfd, size)
            fcntl.fcntl(memfd, fcntl.F_ADD_SEALS, _SEALS)
            self.memory = mmap.mmap(memfd, size)
            ring_r, self.ring = os.pipe()
            opened += [ring_r, self.ring]
            self.bell, bell_w = os.pipe()
            opened += [self.bell, bell_w]
            os.set_blocking(self.ring, False)
            os.set_blocking(self.bell, False)
        except BaseException:
            for fd in opened:
                os.close(fd)
            raise
        self._worker_fds: tuple[int, ...] = (memfd, ring_r, bell_w)

    @property
    def worker_fds(self) -> tuple[int, ...]:
        """The descriptors the worker inherits: the region, the ring's read end, the bell's
        write end (``--channel`` gives them, :meth:`worker_arg`)."""
        return self._worker_fds

    def worker_arg(self) -> str:
        """The worker's ``--channel`` argument: ``"memfd,ring,bell"``."""
        return ",".join(str(fd) for fd in self._worker_fds)

    def spawned(self) -> None:
        """Close the host's copies of the worker's descriptors (once it has them): the
        bell then ends when the worker does."""
        fds, self._worker_fds = self._worker_fds, ()
        for fd in fds:
            os.close(fd)

    def post(self, frame: bytes) -> None:
        """Put ``frame`` in the request slot and ring (never blocks).

        Raises:
            ProtocolError: ``frame`` is larger than the request slot.
            BrokenPipeError: the worker's end of the ring is closed.
        """
        if len(frame) > self.request_bytes:
            raise ProtocolError(
                f"a request of {len(frame)} bytes does not fit the {self.request_bytes}-byte slot"
            )
        self.memory[: len(frame)] = frame
        try:  # noqa: SIM105 - on every step's path, where suppress() costs a microsecond
            os.write(self.ring, _ONE)
        except BlockingIOError:  # full: a wake-up is pending already
            pass

    def reply_seq(self) -> int:
        """The sequence number the reply slot's header holds now (a peek, nothing checked)."""
        return int(_SEQ.unpack_from(self.memory, self._reply_at + _SEQ_OFFSET)[0])

    def take(self) -> Frame:
        """The reply slot's frame, decoded from the host's own copy.

        Raises:
            ProtocolError: it is not one valid frame within the slot.
        """
        return _read_frame(self.memory, self._reply_at, REPLY_BYTES)

    def drain(self) -> tuple[int, bool]:
        """Read the wake-ups waiting on the bell: one read, so a worker writing without
        end cannot keep the host here (never blocks).

        Returns:
            ``(count, ended)``: bytes read (at most :data:`WAKE_READ`), and whether the
            worker's end is closed.
        """
        while True:
            try:
                data = os.read(self.bell, WAKE_READ)
            except BlockingIOError:
                return 0, False
            except InterruptedError:
                continue
            return len(data), not data

    def close(self) -> None:
        """Close the host's descriptors and unmap the region; idempotent."""
        for fd in (*self._worker_fds, self.ring, self.bell):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._worker_fds, self.ring, self.bell = (), -1, -1
        self.memory.close()


class WorkerChannel:
    """The worker's side: wait for a request, answer it.

    Args:
        spec: ``"memfd,ring,bell"``, the descriptors it inherited (:meth:`Channel.worker_arg`).
    """

    def __init__(self, spec: str) -> None:
        memfd, self.ring, self.bell = (int(fd) for fd in spec.split(","))
        size = os.fstat(memfd).st_size
        self.memory = mmap.mmap(memfd, size)
        os.close(memfd)
        self._reply_at = size - REPLY_BYTES

    def request(self, last: int) -> Frame | None:
        """Block until a request numbered other than ``last`` is in the slot; None once the
        host is gone (the ring ended).

        Raises:
            ProtocolError: the request slot does not hold a valid frame.
        """
        while True:
            try:
                if not os.read(self.ring, WAKE_READ):
                    return None
            except InterruptedError:
                continue
            frame = _read_frame(self.memory, 0, self._reply_at)
            if frame.seq != last:
                return frame

    def reply(self, frame: bytes) -> None:
        """Put ``frame`` in the reply slot and ring the bell.

        Raises:
            ProtocolError: ``frame`` is larger than the reply slot.
        """
        if len(frame) > REPLY_BYTES:
            raise ProtocolError(f"a reply of {len(frame)} bytes exceeds {REPLY_BYTES}")
        start = self._reply_at
        self.memory[start : start + len(frame)] = frame
        os.write(self.bell, _ONE)
