"""A fast CDR codec for the two big messages, sensor_msgs/Image and sensor_msgs/CompressedImage.

Why not the IDL classes: cyclonedds' Python serializer turns ``sequence<uint8>`` into a list of Python ints (about
25 ms to write and 9 ms to read one 1080p frame, plus several whole-buffer copies), which alone would eat the frame
budget at 30 Hz. Here the pixels cost one copy to write (into the message buffer) and none to read (a numpy view of
the received bytes). The bytes are exactly what the IDL classes in :mod:`vpengine.ros2.dds_types` produce (and what
rosbags produces), which ``tests/unit/test_ros2_cdr.py`` checks byte for byte.

Wire format (what ROS 2 writes): a 4-byte encapsulation header (``00 01 00 00`` = CDR little-endian, XCDR1), then the
fields in declaration order, each aligned to its own size relative to the end of that header; strings are a uint32
length that counts a terminating NUL, the bytes, and the NUL; ``uint8[]`` is a uint32 count and the bytes. The writer
pads the total to a multiple of 4 (as cyclonedds' DataWriter does). The decoder also accepts big-endian CDR and the
XCDR2 plain encodings: for these two types (no member wider than 4 bytes, final extensibility) the layout is the same.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from vpengine.ros2.messages import Header, ImageOut

#: encapsulation identifier -> struct byte order (CDR_BE, CDR_LE, PLAIN_CDR2_BE, PLAIN_CDR2_LE)
ENCAPSULATIONS = {b"\x00\x00": ">", b"\x00\x01": "<", b"\x00\x06": ">", b"\x00\x07": "<"}
CDR_LE = b"\x00\x01\x00\x00"


class CdrError(ValueError):
    """Bytes that are not a well-formed message of the expected type."""


@dataclass
class CompressedImageView:
    """A decoded sensor_msgs/CompressedImage; ``data`` is a view of the received bytes."""

    header: Header
    format: str
    data: np.ndarray


class _Reader:
    def __init__(self, buf: Any, what: str) -> None:
        self.buf = buf
        self.mv = memoryview(buf).cast("B")
        self.what = what
        if len(self.mv) < 4:
            raise CdrError(f"{what}: {len(self.mv)} bytes is too short for a CDR message")
        enc = bytes(self.mv[:2])
        if enc not in ENCAPSULATIONS:
            raise CdrError(
                f"{what}: encapsulation {enc.hex()} is not plain CDR; accepted: "
                f"{', '.join(k.hex() for k in ENCAPSULATIONS)}"
            )
        self.e = ENCAPSULATIONS[enc]
        self.pos = 4  # alignment counts from the end of the encapsulation header

    def _need(self, n: int, field: str) -> None:
        if self.pos + n > len(self.mv):
            raise CdrError(
                f"{self.what}: truncated at {field} (needs {n} bytes at offset {self.pos}, has {len(self.mv)})"
            )

    def _align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def u32(self, field: str) -> int:
        self._align(4)
        self._need(4, field)
        (v,) = struct.unpack_from(self.e + "I", self.mv, self.pos)
        self.pos += 4
        return int(v)

    def i32(self, field: str) -> int:
        self._align(4)
        self._need(4, field)
        (v,) = struct.unpack_from(self.e + "i", self.mv, self.pos)
        self.pos += 4
        return int(v)

    def u8(self, field: str) -> int:
        self._need(1, field)
        v = self.mv[self.pos]
        self.pos += 1
        return int(v)

    def string(self, field: str) -> str:
        n = self.u32(field)
        if n == 0:  # some writers send an empty string as length 0
            return ""
        self._need(n, field)
        raw = bytes(self.mv[self.pos : self.pos + n])
        self.pos += n
        if raw[-1:] != b"\x00":
            raise CdrError(f"{self.what}: string {field} is not NUL-terminated")
        return raw[:-1].decode("utf-8", errors="replace")

    def octets(self, field: str) -> np.ndarray:
        n = self.u32(field)
        self._need(n, field)
        arr = np.frombuffer(self.buf, dtype=np.uint8, count=n, offset=self.pos)
        self.pos += n
        return arr

    def header(self) -> Header:
        sec = self.i32("header.stamp.sec")
        nanosec = self.u32("header.stamp.nanosec")
        return Header(sec, nanosec, self.string("header.frame_id"))


def decode_image(buf: Any) -> ImageOut:
    """sensor_msgs/Image from CDR bytes (with the encapsulation header); pixels are a view, not a copy."""
    r = _Reader(buf, "sensor_msgs/Image")
    header = r.header()
    height = r.u32("height")
    width = r.u32("width")
    encoding = r.string("encoding")
    big = r.u8("is_bigendian")
    step = r.u32("step")
    return ImageOut(header, height, width, encoding, big, step, r.octets("data"))


def decode_compressed_image(buf: Any) -> CompressedImageView:
    """sensor_msgs/CompressedImage from CDR bytes; data is a view."""
    r = _Reader(buf, "sensor_msgs/CompressedImage")
    header = r.header()
    fmt = r.string("format")
    return CompressedImageView(header, fmt, r.octets("data"))


def _string(out: bytearray, text: str) -> None:
    raw = text.encode("utf-8")
    out += b"\x00" * ((-(len(out) - 4)) % 4)
    out += struct.pack("<I", len(raw) + 1)
    out += raw
    out += b"\x00"


def _prefix_header(header: Header) -> bytearray:
    out = bytearray(CDR_LE)
    out += struct.pack("<iI", header.sec, header.nanosec)
    _string(out, header.frame_id)
    return out


def _finish(prefix: bytearray, data: np.ndarray) -> bytearray:
    """prefix + uint8[] data (count already in prefix) + padding to 4, with one copy of the data."""
    n = int(data.size)
    total = len(prefix) + n
    out = bytearray(total + (-total) % 4)
    out[: len(prefix)] = prefix
    if n:
        np.frombuffer(out, dtype=np.uint8, count=n, offset=len(prefix))[:] = data
    return out


def encode_image(img: ImageOut) -> bytearray:
    """sensor_msgs/Image as CDR little-endian bytes (with encapsulation header and padding to 4)."""
    data = np.ascontiguousarray(img.data).reshape(-1).view(np.uint8)
    if data.size != img.step * img.height:
        raise ValueError(
            f"image data holds {data.size} bytes but step x height = {img.step} x {img.height} = "
            f"{img.step * img.height}"
        )
    out = _prefix_header(img.header)
    out += b"\x00" * ((-(len(out) - 4)) % 4)
    out += struct.pack("<II", img.height, img.width)
    _string(out, img.encoding)
    out += struct.pack("<B", img.is_bigendian)
    out += b"\x00" * ((-(len(out) - 4)) % 4)
    out += struct.pack("<II", img.step, data.size)
    return _finish(out, data)


def encode_compressed_image(header: Header, fmt: str, data: Any) -> bytearray:
    """sensor_msgs/CompressedImage as CDR little-endian bytes."""
    arr = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1).view(np.uint8)
    out = _prefix_header(header)
    _string(out, fmt)
    out += b"\x00" * ((-(len(out) - 4)) % 4)
    out += struct.pack("<I", arr.size)
    return _finish(out, arr)
