"""DYNAMIXEL Protocol 2.0 packets: CRC-16, byte stuffing, building and parsing.

Pure functions over bytes, no SDK: the emulator speaks through them, and the
tests check them against packets printed in the protocol's e-Manual page
(e.g. PING of ID 1 is ``FF FF FD 00 01 03 00 01 19 4E``).

Layout (protocol): ``FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS… | CRC_L CRC_H``
where LEN counts INST, the (stuffed) parameters and the CRC. A status packet's
INST is 0x55 followed by an error byte. Inside INST..PARAMS every ``FF FF FD``
is followed by a stuffing ``FD`` so that no header appears in the body.
"""

from __future__ import annotations

from dataclasses import dataclass

from bioscara_gym.hardware.dynamixel.control_table import CRC_POLYNOMIAL, HEADER, Instruction


def _crc_table() -> tuple[int, ...]:
    """The 256-entry table of the non-reflected CRC-16 with polynomial 0x8005."""
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLYNOMIAL) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


#: The CRC table (the protocol's ``crc_table``: 0x0000, 0x8005, 0x800F, 0x000A, …).
CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 of protocol 2.0 over ``data`` (header through last parameter), initial value 0."""
    for byte in data:
        crc = ((crc << 8) ^ CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` of a packet body (INST and parameters).

    The two bytes before the body (``LEN_H`` and ``ID``, never ``FF FF`` in
    a valid header) are not part of the pattern, as in the SDK.
    """
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the stuffing ``FD`` after every ``FF FF FD`` of a received body."""
    out = bytearray()
    i = 0
    while i < len(body):
        b = body[i]
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            i += 1  # skip the stuffing byte
        i += 1
    return bytes(out)


def build(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A complete packet (instruction or status): header, ID, length, stuffed body, CRC."""
    body = stuff(bytes((instruction,)) + bytes(params))
    length = len(body) + 2
    packet = HEADER + bytes((dxl_id, length & 0xFF, length >> 8)) + body
    crc = crc16(packet)
    return packet + bytes((crc & 0xFF, crc >> 8))


def instruction_packet(dxl_id: int, instruction: Instruction | int, params: bytes = b"") -> bytes:
    """An instruction packet."""
    return build(dxl_id, int(instruction), params)


def status_packet(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet: INST 0x55, the error byte, then the parameters."""
    return build(dxl_id, int(Instruction.STATUS), bytes((error & 0xFF,)) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A received packet, body unstuffed.

    Attributes:
        id: Device ID (0xFE broadcast).
        instruction: Instruction byte (0x55 for a status packet).
        params: Parameters (for a status packet: the error byte first).
        crc_ok: Whether the CRC matched.
        raw: The packet's bytes as received.
    """

    id: int
    instruction: int
    params: bytes
    crc_ok: bool
    raw: bytes

    @property
    def error(self) -> int:
        """A status packet's error byte."""
        return self.params[0] if self.params else 0

    @property
    def data(self) -> bytes:
        """A status packet's parameters after the error byte."""
        return self.params[1:]


#: Largest LEN the parser accepts (the SDK's RXPACKET_MAX_LEN is 1024 bytes in all).
MAX_LENGTH = 1024


class PacketParser:
    """Splits a byte stream into packets, as a device's receiver does.

    Bytes before a header are discarded (noise, a half packet); a header whose
    length is implausible is skipped one byte at a time. A header inside a
    packet still arriving ends that packet: byte stuffing keeps ``FF FF FD 00``
    out of a body, so a new packet began and the one before was cut short (a
    client that closed partway through); waiting for its claimed length would
    swallow the packets that follow. Only the last four bytes (body ending
    ``FF FF``, CRC ``FD 00``) may look like a header.
    """

    def __init__(self) -> None:
        """Start with an empty buffer."""
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Packet]:
        """Add received bytes; return every complete packet now in the buffer."""
        self._buf.extend(data)
        packets: list[Packet] = []
        while True:
            start = self._buf.find(HEADER)
            if start < 0:
                # keep a possible partial header at the end
                keep = next((k for k in (3, 2, 1) if self._buf.endswith(HEADER[:k])), 0)
                del self._buf[: len(self._buf) - keep]
                return packets
            del self._buf[:start]
            if len(self._buf) < 7:
                return packets
            length = self._buf[5] | (self._buf[6] << 8)
            if length < 3 or length > MAX_LENGTH:
                del self._buf[0]
                continue
            total = 7 + length
            restart = self._buf.find(HEADER, 7, min(len(self._buf), total - 1))
            if restart >= 0:
                del self._buf[:restart]  # cut short: a new packet starts there
                continue
            if len(self._buf) < total:
                return packets
            raw = bytes(self._buf[:total])
            del self._buf[:total]
            crc_ok = crc16(raw[:-2]) == (raw[-2] | (raw[-1] << 8))
            body = unstuff(raw[7:-2])
            packets.append(Packet(raw[4], body[0] if body else -1, body[1:], crc_ok, raw))

    @property
    def pending(self) -> int:
        """Bytes held: a packet (or header) not complete yet."""
        return len(self._buf)

    def clear(self) -> None:
        """Drop buffered bytes."""
        self._buf.clear()


def parse(data: bytes) -> list[Packet]:
    """Every complete packet in ``data``."""
    return PacketParser().feed(data)
