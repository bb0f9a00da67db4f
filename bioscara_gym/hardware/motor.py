"""Motor models behind the emulated firmware.

The firmware emits a set-point velocity once per 10 ms tick together with the
torque the driver current allows; the motor integrates the set point and moves
its rotor (the encoder) after it. The PID error the firmware watches is set
point minus encoder. :class:`KinematicStepper` is a cheap model for the
driver tests; the MuJoCo arm provides another (``bioscara_gym.sim``).
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

#: Torque of the NEMA 17 motors at 100 % of the driver's 2.5 A output, N*m.
TORQUE_AT_FULL_CURRENT_NM = 0.5
#: Motor degrees per full step: 200 full steps a turn, the unit of MOVESTEPS
#: (firmware; C++ API).
FULL_STEP_DEG = 1.8


@runtime_checkable
class Motor(Protocol):
    """What the firmware needs from a motor, in motor degrees.

    Positions are absolute motor degrees (the firmware keeps its own encoder
    zero); velocities are deg/s.
    """

    @property
    def setpoint_deg(self) -> float:
        """Where the step generator has put the rotor's target."""
        ...

    @property
    def position_deg(self) -> float:
        """Encoder reading."""
        ...

    @property
    def velocity_dps(self) -> float:
        """Encoder speed."""
        ...

    @property
    def pid_error_deg(self) -> float:
        """Set point minus encoder as the real stepper would show it, motor degrees."""
        ...

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        """Set the set-point velocity and the available torque (0-1 of full current)."""
        ...

    def hold_here(self) -> None:
        """Move the set point onto the encoder (hard stop, zero PID error)."""
        ...

    def advance(self, dt: float) -> None:
        """Advance the model by ``dt`` seconds (no-op where physics runs elsewhere)."""
        ...


class KinematicStepper:
    """A stepper that follows its set point unless blocked.

    The rotor lags the set point by the angle a stepper needs to produce the
    load torque (``asin(load / torque_max)`` of one full step, the stepper's
    torque-angle curve); when the load exceeds what the current allows it
    slips and stays put. End stops clamp the rotor, so a set point driven past
    them builds up PID error, which is how homing finds the end stop.

    Args:
        position_deg: Initial rotor position, absolute motor degrees.
        lower_stop_deg: Lower end stop (motor degrees), ``-inf`` for none.
        upper_stop_deg: Upper end stop (motor degrees), ``inf`` for none.
        load_torque_nm: Constant external torque on the rotor (e.g. gravity
            through the transmission), signed.
        max_speed_dps: The motor cannot turn faster; beyond it the rotor slips.
        torque_at_full_current_nm: Torque at 100 % current.
    """

    def __init__(
        self,
        position_deg: float = 0.0,
        lower_stop_deg: float = -math.inf,
        upper_stop_deg: float = math.inf,
        load_torque_nm: float = 0.0,
        max_speed_dps: float = 6000.0,
        torque_at_full_current_nm: float = TORQUE_AT_FULL_CURRENT_NM,
    ) -> None:
        """Create the motor at rest at ``position_deg``."""
        if lower_stop_deg >= upper_stop_deg:
            raise ValueError(f"end stops: lower {lower_stop_deg} must be below upper {upper_stop_deg}")
        self._setpoint = float(position_deg)
        self._position = float(position_deg)
        self._velocity = 0.0
        self._command_velocity = 0.0
        self._torque_fraction = 0.0
        self.lower_stop_deg = lower_stop_deg
        self.upper_stop_deg = upper_stop_deg
        self.load_torque_nm = load_torque_nm
        self.max_speed_dps = max_speed_dps
        self.torque_at_full_current_nm = torque_at_full_current_nm
        self.blocked = False  # tests set it to hold the rotor (an obstacle)

    @property
    def setpoint_deg(self) -> float:
        """Set point, absolute motor degrees."""
        return self._setpoint

    @property
    def position_deg(self) -> float:
        """Encoder, absolute motor degrees."""
        return self._position

    @property
    def velocity_dps(self) -> float:
        """Encoder speed over the last advance, deg/s."""
        return self._velocity

    @property
    def pid_error_deg(self) -> float:
        """Set point minus encoder, motor degrees."""
        return self._setpoint - self._position

    @property
    def torque_fraction(self) -> float:
        """Available torque as a fraction of full current."""
        return self._torque_fraction

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        """Set the set-point velocity (deg/s) and available torque (0-1)."""
        self._command_velocity = velocity_dps
        self._torque_fraction = torque_fraction

    def hold_here(self) -> None:
        """Set point := encoder."""
        self._setpoint = self._position

    def advance(self, dt: float) -> None:
        """Integrate the set point and move the rotor after it for ``dt`` s."""
        torque_max = self._torque_fraction * self.torque_at_full_current_nm
        if torque_max <= 0.0:
            # Unpowered: the rotor stays where it is, the set point follows it.
            self._setpoint = self._position
            self._velocity = 0.0
            return
        self._setpoint += self._command_velocity * dt
        load = self.load_torque_nm
        if abs(load) >= torque_max or self.blocked:
            target = self._position  # slipping or held: the rotor does not follow
        else:
            lag = math.asin(abs(load) / torque_max) / (math.pi / 2) * FULL_STEP_DEG
            target = self._setpoint + math.copysign(lag, load) if load else self._setpoint
        step_limit = self.max_speed_dps * dt
        target = min(max(target, self._position - step_limit), self._position + step_limit)
        target = min(max(target, self.lower_stop_deg), self.upper_stop_deg)
        self._velocity = (target - self._position) / dt
        self._position = target
