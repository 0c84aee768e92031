"""Minimal little-endian XCDR1 (ROS 2 "cdr") writer and reader on numpy, for big messages.

Building large ROS messages as Python objects costs hundreds of ms (see docs/ros-on-pip.md);
writing the bytes with numpy costs about a millisecond. ROS-free: used by the nodes (publishing
raw bytes), by headless runs (MCAP files) and by the analysis (decoding recorded runs).

Alignment is relative to the first byte after the 4-byte encapsulation header, as in ROS 2.
"""
from __future__ import annotations

import struct

import numpy as np

ENCAPSULATION_LE = b'\x00\x01\x00\x00'


class CdrError(ValueError):
    """Malformed or truncated CDR data."""


class CdrWriter:
    """Append-only CDR serialiser. ``bytes()`` returns header + payload."""

    __slots__ = ('_parts', '_pos')

    def __init__(self):
        self._parts = [ENCAPSULATION_LE]
        self._pos = 0                     # payload offset (alignment origin)

    def _align(self, n: int):
        pad = (-self._pos) % n
        if pad:
            self._parts.append(b'\x00' * pad)
            self._pos += pad

    def _raw(self, b: bytes):
        self._parts.append(b)
        self._pos += len(b)

    def _prim(self, fmt: str, size: int, v):
        self._align(size)
        self._raw(struct.pack('<' + fmt, v))

    def bool(self, v): self._prim('?', 1, bool(v))
    def uint8(self, v): self._prim('B', 1, v)
    def int8(self, v): self._prim('b', 1, v)
    def uint16(self, v): self._prim('H', 2, v)
    def int16(self, v): self._prim('h', 2, v)
    def uint32(self, v): self._prim('I', 4, v)
    def int32(self, v): self._prim('i', 4, v)
    def uint64(self, v): self._prim('Q', 8, v)
    def int64(self, v): self._prim('q', 8, v)
    def float32(self, v): self._prim('f', 4, v)
    def float64(self, v): self._prim('d', 8, v)

    def string(self, s: str):
        b = s.encode('utf-8')
        self.uint32(len(b) + 1)
        self._raw(b + b'\x00')

    def string_seq(self, items):
        self.uint32(len(items))
        for s in items:
            self.string(s)

    def array(self, a, dtype, with_length: bool = True):
        """A sequence (with_length) or fixed array of a primitive numpy dtype."""
        a = np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder('<'))
        if with_length:
            self.uint32(a.size)
        if a.size:
            self._align(a.dtype.itemsize)
            self._raw(a.tobytes())

    def header(self, stamp_ns: int, frame_id: str):
        """std_msgs/Header (builtin_interfaces/Time stamp, string frame_id)."""
        self.int32(int(stamp_ns // 1_000_000_000))
        self.uint32(int(stamp_ns % 1_000_000_000))
        self.string(frame_id)

    def raw_aligned(self, b: bytes, align: int):
        """Pre-encoded bytes that start at an `align` boundary and end at payload offset pos+len(b)."""
        self._align(align)
        self._raw(b)

    @property
    def offset(self) -> int:
        return self._pos

    def bytes(self) -> bytes:
        return b''.join(self._parts)


class CdrReader:
    """Sequential CDR deserialiser over bytes (checks the encapsulation header)."""

    __slots__ = ('_buf', '_pos')

    def __init__(self, data):
        data = memoryview(data).cast('B')
        if len(data) < 4:
            raise CdrError('CDR data shorter than its 4-byte header')
        if bytes(data[:2]) != b'\x00\x01':
            raise CdrError(f'unsupported CDR encapsulation {bytes(data[:4]).hex()} (expected little-endian CDR)')
        self._buf = data[4:]
        self._pos = 0

    def _align(self, n: int):
        self._pos += (-self._pos) % n

    def _take(self, n: int) -> memoryview:
        if self._pos + n > len(self._buf):
            raise CdrError(f'CDR data truncated at byte {self._pos + 4} (need {n} more)')
        m = self._buf[self._pos:self._pos + n]
        self._pos += n
        return m

    def _prim(self, fmt: str, size: int):
        self._align(size)
        return struct.unpack('<' + fmt, self._take(size))[0]

    def bool(self): return self._prim('?', 1)
    def uint8(self): return self._prim('B', 1)
    def int8(self): return self._prim('b', 1)
    def uint16(self): return self._prim('H', 2)
    def int16(self): return self._prim('h', 2)
    def uint32(self): return self._prim('I', 4)
    def int32(self): return self._prim('i', 4)
    def uint64(self): return self._prim('Q', 8)
    def int64(self): return self._prim('q', 8)
    def float32(self): return self._prim('f', 4)
    def float64(self): return self._prim('d', 8)

    def string(self) -> str:
        n = self.uint32()
        if n == 0:
            return ''
        return bytes(self._take(n)[:-1]).decode('utf-8')

    def string_seq(self) -> list:
        return [self.string() for _ in range(self.uint32())]

    def array(self, dtype, count: int | None = None) -> np.ndarray:
        """A sequence (count None: read its length) or fixed array; returns a copy."""
        if count is None:
            count = self.uint32()
        dt = np.dtype(dtype).newbyteorder('<')
        if count == 0:
            return np.zeros(0, dtype=dt.newbyteorder('='))
        self._align(dt.itemsize)
        return np.frombuffer(self._take(count * dt.itemsize), dtype=dt).astype(dt.newbyteorder('='))

    def header(self) -> tuple[int, str]:
        sec = self.int32()
        nsec = self.uint32()
        return sec * 1_000_000_000 + nsec, self.string()

    @property
    def remaining(self) -> int:
        return len(self._buf) - self._pos
