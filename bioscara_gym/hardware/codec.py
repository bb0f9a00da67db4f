"""Little-endian payload encoding of the joint protocol.

Every payload is at most four bytes: ``float32``, ``int32``, ``uint32`` or
``uint8``, little-endian (the joints are ARM Cortex-M, the host memcpy's them).
"""

from __future__ import annotations

import math
import struct

from bioscara_gym.hardware.errors import InvalidArgumentError

_F32 = struct.Struct("<f")
_I32 = struct.Struct("<i")
_U32 = struct.Struct("<I")
_F32_MAX = 3.4028234663852886e38


def encode_f32(value: float) -> bytes:
    """Encode a float32, little-endian.

    Raises:
        InvalidArgumentError: ``value`` is NaN, infinite or beyond float32 range.
    """
    if not math.isfinite(value) or abs(value) > _F32_MAX:
        raise InvalidArgumentError(f"{value!r} cannot be sent as a finite float32")
    return _F32.pack(value)


def decode_f32(data: bytes) -> float:
    """Decode a little-endian float32 from exactly four bytes."""
    return _F32.unpack(data)[0]


def encode_i32(value: int) -> bytes:
    """Encode a signed 32-bit integer, little-endian.

    Raises:
        InvalidArgumentError: ``value`` does not fit in int32.
    """
    if not -(2**31) <= value < 2**31:
        raise InvalidArgumentError(f"{value} does not fit in int32")
    return _I32.pack(value)


def decode_i32(data: bytes) -> int:
    """Decode a little-endian int32 from exactly four bytes."""
    return _I32.unpack(data)[0]


def encode_u32(value: int) -> bytes:
    """Encode an unsigned 32-bit integer, little-endian.

    Raises:
        InvalidArgumentError: ``value`` does not fit in uint32.
    """
    if not 0 <= value < 2**32:
        raise InvalidArgumentError(f"{value} does not fit in uint32")
    return _U32.pack(value)


def decode_u32(data: bytes) -> int:
    """Decode a little-endian uint32 from exactly four bytes."""
    return _U32.unpack(data)[0]


def encode_u8(value: int) -> bytes:
    """Encode one unsigned byte.

    Raises:
        InvalidArgumentError: ``value`` is outside 0-255.
    """
    if not 0 <= value <= 255:
        raise InvalidArgumentError(f"{value} does not fit in uint8 (0-255)")
    return bytes((value,))


def decode_u8(data: bytes) -> int:
    """Decode one unsigned byte."""
    (value,) = data
    return value


def pack_bytes(b0: int, b1: int = 0, b2: int = 0, b3: int = 0) -> int:
    """Pack four bytes into the uint32 the firmware reads (byte0 least significant).

    Used by SETUP (byte0 drive current, byte1 hold current) and HOME (byte0
    direction, byte1 speed RPM, byte2 sensitivity, byte3 current).
    """
    for i, b in enumerate((b0, b1, b2, b3)):
        if not 0 <= b <= 255:
            raise InvalidArgumentError(f"byte{i} = {b} does not fit in uint8 (0-255)")
    return b0 | (b1 << 8) | (b2 << 16) | (b3 << 24)


def unpack_bytes(value: int) -> tuple[int, int, int, int]:
    """Split a uint32 into its four bytes, least significant first."""
    return value & 0xFF, (value >> 8) & 0xFF, (value >> 16) & 0xFF, (value >> 24) & 0xFF
