"""Ports of the official ``dynamixel-sdk``: RS-485 serial set-up, and an in-memory port.

This module imports the SDK; import it through :func:`sdk_port_module` (or
:func:`bioscara_gym.hardware.dynamixel.require_sdk`) so that a missing SDK is
one :class:`~bioscara_gym.hardware.errors.MissingExtraError` line.

* :class:`RS485PortHandler` is the MH5's ``PortHandlerMH5``: the SDK's
  serial port, plus :meth:`~RS485PortHandler.set_rs485` that puts the UART in
  RS-485 mode with the ``TIOCSRS485`` ioctl (the MH5's interface board has
  SC16IS762 UARTs that drive the transceiver's direction in hardware once so
  configured). A port that does not support it (a USB adapter that switches
  direction itself, a pseudo-terminal) logs a warning and carries on.
* :class:`EmulatedPortHandler` hands the SDK's bytes to an
  :class:`~bioscara_gym.hardware.dynamixel.emulator.EmulatedRS485Bus` in
  memory: the SDK's packet handler runs unchanged, byte for byte, without a
  serial device and without waiting on wall-clock timeouts.
"""

from __future__ import annotations

import fcntl
import logging
import struct

from dynamixel_sdk import PortHandler

from bioscara_gym.hardware.dynamixel.emulator import EmulatedRS485Bus

log = logging.getLogger(__name__)

#: Linux ``TIOCSRS485`` ioctl request (``asm-generic/ioctls.h``).
TIOCSRS485 = 0x542F
#: ``struct serial_rs485`` flags (``linux/serial.h``).
SER_RS485_ENABLED = 1 << 0
SER_RS485_RTS_ON_SEND = 1 << 1
SER_RS485_RTS_AFTER_SEND = 1 << 2


def rs485_struct(flags: int = SER_RS485_ENABLED | SER_RS485_RTS_ON_SEND) -> bytes:
    """``struct serial_rs485``: flags, RTS delays before and after send (0 ms), 5 padding words.

    The MH5 sets ENABLED and RTS_ON_SEND, clears RTS_AFTER_SEND, no delays.
    """
    return struct.pack("<8I", flags, 0, 0, 0, 0, 0, 0, 0)


class RS485PortHandler(PortHandler):
    """The SDK's serial port, optionally switched to RS-485 mode (the MH5's port handler).

    Args:
        port_name: Device path, e.g. ``/dev/ttySC0`` or ``/dev/ttyUSB0``.
    """

    rs485_enabled = False

    def set_rs485(self) -> bool:
        """Put the open port in RS-485 mode with ``TIOCSRS485``; False (logged) where unsupported."""
        if self.ser is None:
            raise RuntimeError("set_rs485: open the port first")
        try:
            fcntl.ioctl(self.ser.fileno(), TIOCSRS485, rs485_struct())
        except OSError as e:
            log.warning(
                "%s: RS-485 mode not available (%s); carrying on as a plain serial port "
                "(fine for USB adapters that switch direction themselves, and pseudo-terminals)",
                self.port_name,
                e.strerror or e,
            )
            self.rs485_enabled = False
            return False
        self.rs485_enabled = True
        return True


class EmulatedPortHandler(PortHandler):
    """An SDK port whose other end is an :class:`EmulatedRS485Bus` in memory.

    ``writePort`` delivers the instruction packet to the emulated servos,
    which answer at once; ``readPort`` hands their status bytes back. A wait
    for an answer that never comes times out at once (a missing servo, a
    dropped status packet), so tests do not wait on the wall clock.
    """

    def __init__(self, bus: EmulatedRS485Bus, port_name: str = "emulated") -> None:
        """Attach to ``bus``; call ``openPort()`` as for a real port."""
        super().__init__(port_name)
        self.emulated_bus = bus

    def setupPort(self, cflag_baud: int) -> bool:
        """No serial device: mark the port open."""
        self.is_open = True
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def closePort(self) -> None:
        """Mark the port closed."""
        self.is_open = False

    def clearPort(self) -> None:
        """Drop unread status bytes, as flushing a serial port's input does."""
        self.emulated_bus.clear_output()

    def discard_late_replies(self) -> int:
        """Drop unread status bytes at once: the servos answer at once, so none can still be on its way.

        What :class:`~bioscara_gym.hardware.dynamixel.bus.DynamixelBus` calls
        after a failed exchange instead of waiting for the line to go quiet
        (a serial port's ``drain_port``). Returns the bytes dropped.
        """
        dropped = self.emulated_bus.in_waiting
        self.emulated_bus.clear_output()
        return dropped

    def getBytesAvailable(self) -> int:
        """Status bytes waiting."""
        return self.emulated_bus.in_waiting

    def readPort(self, length: int) -> bytes:
        """Up to ``length`` status bytes."""
        return self.emulated_bus.read(length)

    def writePort(self, packet: list[int] | bytes) -> int:
        """Deliver an instruction packet to the servos."""
        return self.emulated_bus.write(bytes(packet))

    def isPacketTimeout(self) -> bool:
        """Everything was answered at once: no bytes waiting means none will come."""
        return self.emulated_bus.in_waiting == 0

    def set_rs485(self) -> bool:
        """Nothing to configure in memory."""
        return True
