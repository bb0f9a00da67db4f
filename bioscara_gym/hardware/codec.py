"""Payload encoding of the joint protocol, driven by :data:`~.registers.PAYLOAD_FORMAT`.

Every payload is at most four bytes, ``float32``, ``int32``, ``uint32`` or
``uint8``, little-endian (the joints are ARM Cortex-M; both sides ``memcpy``
the bytes). The driver (:class:`~bioscara_gym.hardware.joint.Joint`) and the
firmware emulation (:class:`~bioscara_gym.hardware.firmware.JointFirmware`)
both encode and decode through :func:`encode` and :func:`decode`, so each
register's format is written once, in the register table.

SETUP and HOME carry four separate bytes in their ``uint32``;
:func:`pack_bytes` and :func:`unpack_bytes` build and split it.
"""

from __future__ import annotations

import struct

from bioscara_gym.hardware.errors import InvalidArgumentError
from bioscara_gym.hardware.registers import PAYLOAD_FORMAT, Reg

#: How the firmware reads a register that has no entry in the table: its
#: four-byte value buffer, as a uint32.
_RAW = struct.Struct("<I")
_STRUCTS: dict[int, struct.Struct] = {int(reg): struct.Struct(fmt) for reg, fmt in PAYLOAD_FORMAT.items()}


def payload_size(reg: Reg | int) -> int:
    """Size in bytes of the payload of ``reg`` (4 for a register without a format)."""
    return _STRUCTS.get(reg, _RAW).size


def encode(reg: Reg, value: float | int, *, joint: str | None = None) -> bytes:
    """Encode ``value`` in the payload format of ``reg``.

    Args:
        reg: A register of :data:`~.registers.PAYLOAD_FORMAT`.
        value: The payload value (a float for float32, an int otherwise).
        joint: Name of the joint, for the error message.

    Returns:
        The payload bytes, little-endian.

    Raises:
        InvalidArgumentError: ``value`` does not fit the format (out of range,
            or a float where an integer is expected); carries ``joint`` and
            ``register``.
    """
    try:
        return _STRUCTS[reg].pack(value)
    except (struct.error, OverflowError) as e:
        raise InvalidArgumentError(f"{reg.name} payload {value!r}: {e}", joint=joint, register=reg) from e


def decode(reg: Reg | int, data: bytes) -> float | int:
    """Decode the payload of ``reg`` from exactly :func:`payload_size` bytes.

    A register without a format decodes as the firmware's raw uint32.

    Raises:
        struct.error: ``data`` has the wrong length.
    """
    return _STRUCTS.get(reg, _RAW).unpack(data)[0]


def pack_bytes(b0: int, b1: int = 0, b2: int = 0, b3: int = 0) -> int:
    """Pack four bytes into the uint32 the firmware reads (byte0 least significant).

    Used by SETUP (byte0 drive current, byte1 hold current) and HOME (byte0
    direction, byte1 speed RPM, byte2 sensitivity, byte3 current).

    Raises:
        InvalidArgumentError: A byte is outside 0-255.
    """
    for i, b in enumerate((b0, b1, b2, b3)):
        if not 0 <= b <= 255:
            raise InvalidArgumentError(f"byte{i} = {b} does not fit in uint8 (0-255)")
    return b0 | (b1 << 8) | (b2 << 16) | (b3 << 24)


def unpack_bytes(value: int) -> tuple[int, int, int, int]:
    """Split a uint32 into its four bytes, least significant first."""
    return value & 0xFF, (value >> 8) & 0xFF, (value >> 16) & 0xFF, (value >> 24) & 0xFF
