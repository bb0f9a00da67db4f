"""The I2C bus abstraction and the real bus over smbus2."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from bioscara_gym.hardware.errors import CommError


@runtime_checkable
class I2CBus(Protocol):
    """A bus that performs combined write-then-read transactions."""

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """Write ``data`` to ``address``, then read ``read_len`` bytes (repeated start).

        Raises:
            OSError: On a bus fault (NACK, absent device, arbitration loss).
        """
        ...

    def close(self) -> None:
        """Release the bus."""
        ...


#: The Linux I2C adapter device of bus N (i2c-dev).
DEVICE_PATH = "/dev/i2c-{bus}"


class SMBusI2C:
    """The Linux I2C bus ``/dev/i2c-N`` through smbus2's ``i2c_rdwr``.

    Each transfer is one ``I2C_RDWR`` ioctl with a write message and a read
    message, so the kernel issues a repeated start between them as the joint
    firmware expects.

    Args:
        bus: The bus number N of ``/dev/i2c-N`` (1 on a Raspberry Pi).

    Raises:
        CommError: The device file is missing or not accessible, with a hint.
    """

    def __init__(self, bus: int = 1) -> None:
        """Open ``/dev/i2c-{bus}``."""
        from smbus2 import SMBus

        path = self.path = DEVICE_PATH.format(bus=bus)
        try:
            self._smbus = SMBus(path)
        except FileNotFoundError as e:
            raise CommError(
                f"{path} does not exist: enable I2C (Raspberry Pi: raspi-config > Interface "
                "Options > I2C, or dtparam=i2c_arm=on in config.txt) and check the bus number"
            ) from e
        except PermissionError as e:
            raise CommError(
                f"no permission to open {path}: add your user to the 'i2c' group "
                "(sudo usermod -aG i2c $USER, then log in again)"
            ) from e
        except OSError as e:  # e.g. ENOTTY: the file is not an I2C adapter (a regular file)
            raise CommError(
                f"{path}: {e.strerror or e}: not an I2C adapter; check the bus number "
                "(ls -l /dev/i2c-*) and that I2C is enabled"
            ) from e
        self.bus = bus

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """One combined write-then-read transaction (see :class:`I2CBus`)."""
        from smbus2 import i2c_msg

        write = i2c_msg.write(address, data)
        read = i2c_msg.read(address, read_len)
        try:
            self._smbus.i2c_rdwr(write, read)
        except OSError as e:  # the driver names joint and register; this names the device and address
            raise OSError(e.errno, f"{e.strerror or e} ({self.path}, address {address:#04x})") from e
        return bytes(read)

    def close(self) -> None:
        """Close the device file."""
        self._smbus.close()

    def __enter__(self) -> SMBusI2C:
        """Use as a context manager."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Close on leaving the ``with`` block."""
        self.close()
