"""A joint that mirrors its commands, like the original ``MockJoint``.

No physics and no firmware rules beyond the flags: velocity is integrated over
the clock's time, a position command is reached at once, homing completes
after ``homing_time_s`` and puts the joint at its end stop. Stalls and the
deadman never happen. The host rules (refusals, homing bounds, offsets) are
the shared ones of :class:`BaseJoint`.
"""

from __future__ import annotations

from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.registers import (
    ACK,
    FLAG_BUSY,
    FLAG_MASK,
    FLAG_NOT_ENABLED,
    FLAG_NOT_HOMED,
    FLAG_STALL,
    POWER_UP_FLAGS,
    Reg,
)
from bioscara_gym.hardware.transmission import steps_to_degrees


class MockJoint(BaseJoint):
    """Mirror of commands.

    Args:
        name: Joint name.
        reduction: Signed reduction (default 1: joint and motor units agree).
        min: Lower joint limit.
        max: Upper joint limit.
        clock: Time source (a ``ManualClock`` in tests).
        homing_time_s: How long homing takes.
    """

    has_field = False  # it mirrors its commands: no field to run away from the rotor

    def __init__(
        self,
        name: str,
        reduction: float = 1.0,
        min: float = -3.0,  # noqa: A002 - the C++ API's parameter name
        max: float = 3.0,  # noqa: A002
        clock: Clock | None = None,
        homing_time_s: float = 1.0,
    ) -> None:
        """Create the mock, powered up (not homed, not enabled)."""
        super().__init__(name, reduction, min, max, clock)
        self.homing_time_s = homing_time_s
        self.device_flags = int(POWER_UP_FLAGS)
        self._angle_deg = 0.0  # motor degrees since "encoder zero"
        self._rpm = 0.0
        self._t = self.clock.now()
        self._homing_done_at: float | None = None
        self._home_offset = 0.0

    def _advance(self) -> None:
        now = self.clock.now()
        dt = now - self._t
        self._t = now
        if self._homing_done_at is not None and now >= self._homing_done_at:
            self._homing_done_at = None
            self._angle_deg = 0.0
            self.device_flags &= ~(FLAG_BUSY | FLAG_NOT_HOMED) & FLAG_MASK
        if self._rpm and not self.device_flags & (FLAG_NOT_ENABLED | FLAG_BUSY):
            self._angle_deg += self._rpm * 6.0 * dt

    def _command(self, reg: Reg, value: float | int) -> int:
        self._advance()
        f = self.device_flags
        if reg == Reg.SETUP:
            f &= ~(FLAG_NOT_ENABLED | FLAG_STALL) & FLAG_MASK
        elif reg in (Reg.SETCURRENT, Reg.SETHOLDCURRENT, Reg.DISABLECLOSEDLOOP) and value == 0:
            f |= FLAG_NOT_ENABLED
            self._rpm = 0.0
        elif reg == Reg.SETRPM and not f & (FLAG_NOT_ENABLED | FLAG_NOT_HOMED):
            self._rpm = float(value)
        elif reg == Reg.MOVETOANGLE and not f & (FLAG_NOT_ENABLED | FLAG_NOT_HOMED):
            self._rpm = 0.0
            self._angle_deg = float(value)
        elif reg == Reg.MOVESTEPS and not f & FLAG_NOT_ENABLED:
            self._angle_deg += steps_to_degrees(int(value))
        elif reg == Reg.STOP:
            self._rpm = 0.0
            if self._homing_done_at is not None:
                self._homing_done_at = None
                f = (f | FLAG_NOT_HOMED) & ~FLAG_BUSY & FLAG_MASK
        elif reg == Reg.HOME:
            self._rpm = 0.0
            self._homing_done_at = self.clock.now() + self.homing_time_s
            f |= FLAG_BUSY | FLAG_NOT_HOMED
        elif reg == Reg.CHECKORIENTATION:
            pass  # finishes at once: nothing moves
        elif reg == Reg.HOMEOFFSET:
            self._home_offset = float(value)
        self.device_flags = int(f)
        return self.device_flags

    def _query(self, reg: Reg) -> tuple[float | int, int]:
        self._advance()
        if reg == Reg.PING:
            value: float | int = ACK
        elif reg == Reg.ANGLEMOVED:
            value = self._angle_deg
        elif reg == Reg.GETENCODERRPM:
            value = 0.0 if self.device_flags & (FLAG_NOT_ENABLED | FLAG_BUSY) else self._rpm
        elif reg == Reg.HOMEOFFSET:
            value = self._home_offset
        else:
            value = 0
        return value, self.device_flags

    def power_cycle(self) -> None:
        """Emulate a power cycle of the joint: flags and offset reset."""
        self.device_flags = int(POWER_UP_FLAGS)
        self._rpm = 0.0
        self._homing_done_at = None
        self._home_offset = 0.0
