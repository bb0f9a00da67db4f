"""The real joint firmware as a device of the emulated bus (docs/firmware.md, "Firmware in the loop").

:class:`SitlFirmware` loads a private copy of the firmware built for the
host (:mod:`~bioscara_gym.hardware.sitl.build`), powers it up in front of a
:class:`~bioscara_gym.hardware.motor.Motor` and serves
:class:`~bioscara_gym.hardware.emulated_bus.EmulatedI2CBus` transactions
exactly as :class:`~bioscara_gym.hardware.firmware.JointFirmware` does:
bytes in, bytes out, on the bus's clock.

Time runs in 1 ms steps (the library's closed-loop timer): the stand-in
driver's ramp generator turns the coils, :class:`MotorBridge` passes that
and the current to the motor model and advances it, the encoder reads the
motor back, then the firmware's own code runs if its ``delay()`` is over. A
transaction at time ``t`` first runs every step up to ``t``, then the
firmware's receive and request handlers at ``t``; ``millis()`` is then
``t`` in whole milliseconds.

One loaded copy of the library is one joint: the firmware's globals and the
stand-ins' state are the copy's writable memory. The image of it taken
right after loading is the power-up state (:meth:`SitlFirmware.power_cycle`
restores it and runs ``setup()`` again); :meth:`SitlFirmware.snapshot` and
:meth:`SitlFirmware.restore` save and restore it later.
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import tempfile
import weakref
from pathlib import Path

from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.errors import SitlError
from bioscara_gym.hardware.motor import Motor
from bioscara_gym.hardware.registers import Flag, Reg
from bioscara_gym.hardware.sitl.build import build_firmware, firmware_dir

__all__ = ["BOOT_LIMIT_S", "STEP_S", "MotorBridge", "SitlFirmware", "SitlState"]

#: One step of the chip: the library's 1 kHz closed-loop timer, seconds.
STEP_S = 0.001
_STEP_US = 1000
#: How long ``setup()`` may take before the device counts as not booting, s.
BOOT_LIMIT_S = 10.0
#: Interface version the native runtime must report.
_API_VERSION = 1


class SitlState(ctypes.Structure):
    """The stand-in chip's and library's state (``SitlState`` in ``UstepperS32.h``), for tests and docs.

    Attributes:
        xactual: TMC5130 XACTUAL, microsteps (51,200 a turn).
        xtarget: XTARGET, microsteps.
        vactual: VACTUAL, the driver's velocity unit (fCLK/2^24 microsteps/s).
        vmax: VMAX register.
        amax: AMAX register.
        dmax: DMAX register.
        rampmode: 0 positioning, 1 velocity +, 2 velocity -.
        irun: Run current, of 31.
        ihold: Hold current, of 31.
        mode: The library's mode (0 normal, 2 closed loop).
        pid_error: ``getPidError()``: XACTUAL minus the encoder, microsteps.
        angle_moved: Encoder counts since home (32,768 a turn).
        rpm: ``encoder.getRPM()``.
    """

    _fields_ = [
        ("xactual", ctypes.c_int32),
        ("xtarget", ctypes.c_int32),
        ("vactual", ctypes.c_int32),
        ("vmax", ctypes.c_uint32),
        ("amax", ctypes.c_uint16),
        ("dmax", ctypes.c_uint16),
        ("rampmode", ctypes.c_uint8),
        ("irun", ctypes.c_uint8),
        ("ihold", ctypes.c_uint8),
        ("mode", ctypes.c_uint8),
        ("pid_error", ctypes.c_float),
        ("angle_moved", ctypes.c_int32),
        ("rpm", ctypes.c_float),
    ]


class MotorBridge:
    """The host's motor model behind the stand-in driver: the coils' motion in, the encoder out.

    The only place the SITL runtime meets the :class:`~bioscara_gym.hardware.motor.Motor`
    protocol. Each 1 ms step the driver's ramp generator turns the coils by
    some angle at some current; the motor is commanded that angle's rate and
    the current as its torque fraction, then advanced; its ``position_deg``
    is what the encoder reads. The chip keeps turning the coils whatever
    the rotor does; the drive model decides whether the rotor keeps up or
    loses steps (:mod:`bioscara_gym.hardware.drive`).

    Args:
        motor: The motor model (e.g. ``KinematicStepper``, or the MuJoCo arm's
            ``MujocoMotor``, whose physics the arm steps itself).
    """

    def __init__(self, motor: Motor) -> None:
        """Stand between the driver and ``motor``."""
        self.motor = motor

    def power_up(self) -> None:
        """The driver powers up: no current, the coils where the rotor is."""
        self.motor.command(0.0, 0.0)
        self.motor.hold_here()

    def drive(self, coils_deg: float, torque_fraction: float, dt: float) -> None:
        """Command the motor for the next ``dt`` s: the coils turn ``coils_deg`` at ``torque_fraction``."""
        self.motor.command(coils_deg / dt, torque_fraction)

    def advance(self, dt: float) -> None:
        """Advance the motor model by ``dt`` s (a no-op where physics runs elsewhere)."""
        self.motor.advance(dt)

    def encoder_deg(self) -> float:
        """The rotor's angle as the encoder sees it, motor degrees."""
        return self.motor.position_deg


class _Library:
    """One private, loaded copy of a built firmware library and its power-up image."""

    def __init__(self, path: Path) -> None:
        """Load a copy of the cached library ``path``.

        Raises:
            SitlError: The cached file is not a library of this runtime (another
                library, cut short, another version): one line naming it, and
                saying to delete it. It is not deleted here: the build writes
                the cache only by an atomic rename of a linked library, so a
                file that fails here was changed by something else (or the
                loader itself fails), and that is for the user to see.
        """
        fd, copy = tempfile.mkstemp(prefix="bioscara-sitl-", suffix=".so")
        try:
            with os.fdopen(fd, "wb") as out, open(path, "rb") as src:
                shutil.copyfileobj(src, out)  # failing (a full /tmp) is no fault of the cached file
            # A copy of its own (a new inode): dlopen gives each copy its own globals.
            try:
                lib = ctypes.CDLL(copy, mode=os.RTLD_NOW | os.RTLD_LOCAL)
            except OSError as e:  # the loader's message names the copy, which is gone
                raise _damaged(path, str(e).replace(f"{copy}: ", "").replace(copy, "the copy")) from e
        finally:
            os.unlink(copy)  # the mapping stays; nothing is left on disk
        try:
            _declare(lib)
            version = lib.sitl_api_version()
        except AttributeError as e:  # another shared library: "<copy>: undefined symbol: sitl_..."
            _unload(lib._handle)
            raise _damaged(path, str(e).replace(f"{copy}: ", "")) from e
        if version != _API_VERSION:
            _unload(lib._handle)
            raise _damaged(path, f"built for runtime version {version}, this is version {_API_VERSION}")
        self.path = path
        self.lib = lib
        self.image_size = int(lib.sitl_image_size())
        self.power_up_image = self.save()
        self._finalizer = weakref.finalize(self, _unload, lib._handle)

    def save(self) -> bytes:
        buffer = ctypes.create_string_buffer(self.image_size)
        self.lib.sitl_image_save(buffer)
        return buffer.raw

    def load(self, image: bytes) -> None:
        if len(image) != self.image_size:
            raise ValueError(f"image of {len(image)} bytes; this firmware's state is {self.image_size}")
        self.lib.sitl_image_load(image)

    def close(self) -> None:
        self._finalizer()


def _damaged(path: Path, reason: str) -> SitlError:
    """A cached library that cannot be loaded: the file to delete (the next run builds it again)."""
    return SitlError(
        f"the cached firmware library {path} cannot be loaded ({reason}); delete it and the next run "
        "builds it again"
    )


def _unload(handle: int) -> None:
    """Unload a copy (nothing of it is referenced any more)."""
    import _ctypes

    _ctypes.dlclose(handle)


def _declare(lib: ctypes.CDLL) -> None:
    """The native runtime's C signatures (``native/src/runtime.cpp``)."""
    c = ctypes
    lib.sitl_api_version.restype = c.c_int
    lib.sitl_image_size.restype = c.c_size_t
    lib.sitl_image_save.argtypes = [c.c_void_p]
    lib.sitl_image_save.restype = None
    lib.sitl_image_load.argtypes = [c.c_char_p]
    lib.sitl_image_load.restype = None
    lib.sitl_power_on.argtypes = [c.c_double]
    lib.sitl_power_on.restype = c.c_int
    lib.sitl_booted.restype = c.c_int
    lib.sitl_now_us.restype = c.c_int64
    lib.sitl_tick_begin.argtypes = [c.POINTER(c.c_double)]
    lib.sitl_tick_begin.restype = c.c_double
    lib.sitl_tick_end.argtypes = [c.c_double]
    lib.sitl_tick_end.restype = c.c_int
    lib.sitl_transfer.argtypes = [c.c_int64, c.c_char_p, c.c_int, c.c_char_p, c.c_int]
    lib.sitl_transfer.restype = c.c_int
    lib.sitl_address.restype = c.c_int
    lib.sitl_loops.argtypes = [c.POINTER(c.c_int64), c.POINTER(c.c_int64), c.POINTER(c.c_uint32)]
    lib.sitl_loops.restype = c.c_uint64
    lib.sitl_capture_serial.argtypes = [c.c_int]
    lib.sitl_capture_serial.restype = None
    lib.sitl_read_serial.argtypes = [c.c_char_p, c.c_size_t]
    lib.sitl_read_serial.restype = c.c_size_t
    lib.sitl_serial_dropped.restype = c.c_uint64
    lib.sitl_fault.restype = c.c_char_p
    lib.sitl_teleport.argtypes = [c.c_double]
    lib.sitl_teleport.restype = None
    lib.sitl_state.argtypes = [c.POINTER(SitlState)]
    lib.sitl_state.restype = c.c_int


class SitlFirmware:
    """One joint's real firmware, built for the host, behind its I2C address: bytes in, bytes out.

    A device of :class:`~bioscara_gym.hardware.emulated_bus.EmulatedI2CBus`
    like :class:`~bioscara_gym.hardware.firmware.JointFirmware`, with the
    same ``transfer``/``update``/``power_cycle``/``flags``/``motor`` surface.

    Args:
        source_dir: The firmware's folder (``Arduino/joint/``); ``None``:
            ``$BIOSCARA_FIRMWARE``.
        joint: ``"j1"`` ... ``"j4"``, the configuration the firmware is built
            with (its I2C address among it).
        motor: The motor model behind the driver (e.g. ``KinematicStepper``).
        clock: The bus's clock.
        serial: Keep the firmware's serial output (:meth:`read_serial`).
        owns_ticks: Advance the motor and run the steps up to the clock
            before each transaction (a motor of its own). ``False`` when an
            arm steps physics and calls :meth:`tick_begin`/:meth:`tick_end`
            itself (the MuJoCo arm, ``hardware/sitl/arm.py``).

    The device powers up at construction: ``setup()`` runs (its orientation
    check moves the motor out and back, about 0.6 s of the device's own
    time, which the bus clock does not see) before the first transaction.

    Raises:
        SitlError: No firmware source, no compiler, a build error, or the
            firmware did not finish ``setup()`` within :data:`BOOT_LIMIT_S`.
    """

    def __init__(
        self,
        source_dir: str | os.PathLike[str] | None,
        joint: str,
        motor: Motor,
        clock: Clock,
        *,
        serial: bool = False,
        owns_ticks: bool = True,
    ) -> None:
        """Build (or find in the cache) the firmware, load a copy and power it up."""
        source = firmware_dir(source_dir)
        self.joint = joint
        self.clock = clock
        self.bridge = MotorBridge(motor)
        self.owns_ticks = owns_ticks
        self.serial = serial
        self.transactions = 0
        self._library = _Library(build_firmware(source, joint))
        self.source_dir = source
        self._lib = self._library.lib
        self._torque = ctypes.c_double()
        self._torque_ref = ctypes.byref(self._torque)
        self._reply = ctypes.create_string_buffer(64)
        self._serial_chunks: list[str] = []
        self._offset_us = 0
        self._closed = False
        self._final_flags: Flag | None = None
        self.power_cycle()

    # ------------------------------------------------------------------ state
    @property
    def motor(self) -> Motor:
        """The motor model behind the firmware."""
        return self.bridge.motor

    @property
    def address(self) -> int:
        """The I2C address the firmware joined the bus with (``Wire.begin``, from ``configuration.h``)."""
        return int(self._lib.sitl_address())

    @property
    def device_time(self) -> float:
        """The device's own time since power-up, s (its ``millis()``, in whole ms steps)."""
        return self._lib.sitl_now_us() / 1e6

    @property
    def flags(self) -> Flag:
        """The flags byte as it stands now, looked at without disturbing the firmware.

        The firmware keeps its flags in static variables; they are read by
        answering a PING on a saved image of the joint, which is then put
        back (so nothing the handler does, such as feeding the deadman,
        stays). Once closed, the flags it held when its copy was unloaded:
        nothing changes them after that (a deployment's summary reads them
        after the arm is shut down).

        Raises:
            OSError: Closed, and its flags could not be read when it was.
        """
        final = self._final_flags
        if self._closed and final is not None:
            return final
        self._check_open()
        image = self._library.save()
        try:
            reply = ctypes.create_string_buffer(2)
            if self._lib.sitl_transfer(self._lib.sitl_now_us(), bytes((Reg.PING,)), 1, reply, 2):
                self._raise_fault()  # no flags to read: not padding taken for them
            return Flag(reply.raw[1])
        finally:
            self._library.load(image)

    def loop_passes(self) -> tuple[int, float, float, float]:
        """The firmware's main loop: passes begun, the latest one's start, the current wait's end and length.

        Returns:
            ``(passes, began_s, wakes_s, wait_s)`` in device time.
        """
        began, wake, wait = ctypes.c_int64(), ctypes.c_int64(), ctypes.c_uint32()
        count = int(self._lib.sitl_loops(ctypes.byref(began), ctypes.byref(wake), ctypes.byref(wait)))
        return count, began.value / 1e6, wake.value / 1e6, wait.value / 1e3

    def state(self) -> SitlState:
        """The stand-in chip's registers and the library's closed-loop state now."""
        out = SitlState()
        if self._lib.sitl_state(ctypes.byref(out)) != 0:
            raise SitlError(f"{self.joint}: the firmware has no stepper object")
        return out

    def snapshot(self) -> tuple[bytes, int, int]:
        """The whole joint's state (firmware and chip), for :meth:`restore`; the motor is not included."""
        return self._library.save(), self._offset_us, self.transactions

    def restore(self, snapshot: tuple[bytes, int, int]) -> None:
        """Return to a :meth:`snapshot` of this device."""
        image, self._offset_us, self.transactions = snapshot
        self._library.load(image)

    def close(self) -> None:
        """Unload the firmware's copy; the device answers no more transactions (an ``OSError``).

        Its flags as they stand are kept (:attr:`flags`).
        """
        if self._closed:
            return
        try:
            self._final_flags = self.flags
        except (OSError, SitlError):
            self._final_flags = None  # not known: looking at them after raises
        self._closed = True
        self._library.close()

    def _check_open(self) -> None:
        if self._closed:
            raise OSError(errno.ENODEV, f"{self.joint}: the firmware in the loop was closed")

    # ------------------------------------------------------------------- time
    def _device_us(self, t: float) -> int:
        return round(t * 1e6) + self._offset_us

    def power_cycle(self) -> None:
        """Cut and restore the joint's power: the firmware starts over with ``setup()``.

        The motor keeps its physical position; the encoder counts from there.
        The bus clock does not move while the firmware boots.
        """
        self._check_open()
        if self.owns_ticks:
            self.update()
        lib = self._lib
        self._library.load(self._library.power_up_image)
        lib.sitl_capture_serial(1 if self.serial else 0)
        self.bridge.power_up()
        if lib.sitl_power_on(self.bridge.encoder_deg()):
            self._raise_fault()
        limit = round(BOOT_LIMIT_S / STEP_S)
        steps = 0
        while not lib.sitl_booted():
            if steps >= limit:
                limit_s = f"{BOOT_LIMIT_S:g} s"
                raise SitlError(f"{self.joint}: the firmware's setup() did not return within {limit_s}")
            self.tick(advance_motor=self.owns_ticks)
            steps += 1
        self._offset_us = lib.sitl_now_us() - round(self.clock.now() * 1e6)
        self._drain_serial()

    def update(self) -> None:
        """Run the device's steps up to the clock's current time (when it owns its ticks)."""
        if not self.owns_ticks:
            return
        self._check_open()
        target = self._device_us(self.clock.now())
        now_us = self._lib.sitl_now_us
        tick = self.tick
        while now_us() + _STEP_US <= target:
            tick()
        if self.serial:
            self._drain_serial()

    def tick(self, advance_motor: bool = True) -> None:
        """One 1 ms step: the driver's ramp, the motor (advanced when ``advance_motor``), timer, firmware."""
        self.tick_begin()
        if advance_motor:
            self.bridge.advance(STEP_S)
        self.tick_end()

    def tick_begin(self) -> None:
        """First half of a step: the ramp generator's motion over the next ms goes to the motor."""
        coils = self._lib.sitl_tick_begin(self._torque_ref)
        self.bridge.drive(coils, self._torque.value, STEP_S)

    def tick_end(self) -> None:
        """Second half: the encoder reads the motor; the 1 kHz timer, then the firmware if it is due."""
        if self._lib.sitl_tick_end(self.bridge.encoder_deg()):
            self._raise_fault()

    def teleport(self, delta_deg: float) -> None:
        """The motor was moved by ``delta_deg`` outside physics: encoder and driver follow without a jump."""
        self._lib.sitl_teleport(delta_deg)

    # -------------------------------------------------------------------- bus
    def transfer(self, data: bytes, read_len: int) -> bytes:
        """Serve one combined write-then-read transaction (see ``JointFirmware.transfer``).

        The write phase runs the firmware's ``receiveEvent`` (when ``data``
        is not empty), the read phase its ``requestEvent`` (when ``read_len``
        > 0); the reply is what the firmware wrote, padded with 0xFF.
        """
        self._check_open()
        self.update()
        self.transactions += 1
        at = self._device_us(self.clock.now())
        n = max(int(read_len), 0)
        reply = self._reply if n <= len(self._reply) else ctypes.create_string_buffer(n)
        if self._lib.sitl_transfer(at, bytes(data), len(data), reply, n):
            self._raise_fault()
        return reply.raw[:n]

    # ----------------------------------------------------------------- serial
    def _drain_serial(self) -> None:
        buffer = ctypes.create_string_buffer(4096)
        while True:
            n = self._lib.sitl_read_serial(buffer, len(buffer))
            if not n:
                return
            self._serial_chunks.append(buffer.raw[:n].decode("latin-1"))

    def read_serial(self) -> str:
        """The firmware's serial output since the last call (``serial=True``; else empty)."""
        self._drain_serial()
        text = "".join(self._serial_chunks)
        self._serial_chunks.clear()
        return text

    @property
    def serial_dropped(self) -> int:
        """Bytes of serial output lost because they were not read in time."""
        return int(self._lib.sitl_serial_dropped())

    def _raise_fault(self) -> None:
        message = self._lib.sitl_fault().decode("utf-8", "replace")
        raise SitlError(f"{self.joint} firmware ({self.source_dir}): {message}")
