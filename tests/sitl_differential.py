"""Differential testing of the emulator against the real firmware in the loop (issue #25).

The same command sequence goes to two joints on one clock: the emulator
(:class:`~bioscara_gym.hardware.firmware.JointFirmware`, i.e. ``FirmwareCore``)
and the joint firmware's own source built for the host
(:class:`~bioscara_gym.hardware.sitl.SitlFirmware`), each in front of its own
copy of the same motor model. Every reply is compared byte by byte where
the two must agree (the flags byte, PING's ACK, HOMEOFFSET's value, the
0xFF padding); positions where both models move the motor alike.

Where the two legitimately differ, the comparison of a sequence stops at
the first difference the documented cause explains (docs/firmware.md,
"Firmware in the loop: differences"), and the cause is counted:

``loop_phase``
    The firmware's loop runs ``delay(10)`` after its body, so a blocking
    command that returns between two passes (a homing's 1 ms polls, the
    library's waits) moves every later pass; the emulator's passes stay on
    a 10 ms grid.
``orientation``
    CHECKORIENTATION is the library's check (out and back until two runs
    agree, each waiting for POSITION_REACHED every millisecond); the
    emulator moves once out and back at its own ramp: BUSY ends at another
    time.
``handler_end``
    The library's ``stop()`` waits until the driver stands still (polled
    each millisecond here; at AMAX 0xFFFE about 1 ms from a homing speed,
    up to 0.1 s from full speed), so the firmware's blocking command (a
    homing's end, a stall's stop) returns later than the emulator's, whose
    hard stop is instant; a command in between meets a busy main loop in one
    and an idle one in the other.
``quantization``
    The firmware's PID error comes from the 15-bit encoder against the
    driver's microsteps and is 0-2 microsteps with the rotor following
    exactly; the emulator's is 0: a homing sensitivity below 2 or a stall
    threshold of 0 trips only in the firmware.

Run as a script for a census: ``python tests/sitl_differential.py N`` runs
N random sequences of each family and prints what they found.
"""

from __future__ import annotations

import collections
import copy
import struct
from dataclasses import dataclass, field
from typing import Any

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import TICK_S, Reg
from bioscara_gym.hardware.sitl import SitlFirmware

#: Registers whose reply carries a value before the flags, and its size.
ANSWER_SIZE = {Reg.PING: 1, Reg.ANGLEMOVED: 4, Reg.GETENCODERRPM: 4}
#: Answers that depend on the motor (compared within a tolerance, or not at all).
MOTION_ANSWERS = frozenset({Reg.ANGLEMOVED, Reg.GETENCODERRPM})
#: Causes a divergence may be explained by (see the module docstring).
CAUSES = ("loop_phase", "orientation", "handler_end", "quantization")


class FollowingMotor:
    """A rotor that follows its coils exactly, whatever the current: PID error 0, never slips.

    With it neither model ever sees a PID error (beyond the firmware's
    encoder quantization), so homing ends only by STOP and nothing stalls:
    the flags depend on the firmware's rules alone.
    """

    def __init__(self) -> None:
        self.setpoint_deg = 0.0
        self._velocity = 0.0
        self.velocity_dps = 0.0

    @property
    def position_deg(self) -> float:
        return self.setpoint_deg

    @property
    def pid_error_deg(self) -> float:
        return 0.0

    @property
    def pid_jitter_usteps(self) -> float:
        return 0.0

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        self._velocity = velocity_dps

    def hold_here(self) -> None:
        pass

    def advance(self, dt: float) -> None:
        self.setpoint_deg += self._velocity * dt
        self.velocity_dps = self._velocity


@dataclass(frozen=True)
class Tx:
    """One transaction: the bytes written (``b""``: no write phase) and the bytes read."""

    data: bytes
    read_len: int

    def __str__(self) -> str:
        if not self.data:
            return f"read {self.read_len} (no write phase)"
        reg = self.data[0]
        name = Reg(reg).name if reg in Reg._value2member_map_ else f"0x{reg:02x}"
        return f"{name} [{self.data[1:].hex()}] read {self.read_len}"


@dataclass(frozen=True)
class Wait:
    """Time passing with no traffic, s."""

    seconds: float

    def __str__(self) -> str:
        return f"wait {self.seconds * 1000:.1f} ms"


Step = Tx | Wait


class Mismatch(AssertionError):
    """The two joints answered differently with no documented cause."""


@dataclass
class Outcome:
    """What running one sequence on both joints found."""

    transactions: int = 0
    compared_positions: int = 0
    cause: str | None = None  # the documented cause that ended the comparison, if one did
    at_step: int | None = None


@dataclass
class Census:
    """Counts over many sequences."""

    sequences: int = 0
    transactions: int = 0
    compared_positions: int = 0
    causes: collections.Counter[str] = field(default_factory=collections.Counter)
    mismatches: list[str] = field(default_factory=list)

    def add(self, outcome: Outcome) -> None:
        self.sequences += 1
        self.transactions += outcome.transactions
        self.compared_positions += outcome.compared_positions
        if outcome.cause:
            self.causes[outcome.cause] += 1


class Pair:
    """The emulator and the firmware in the loop on one clock, each with its own motor.

    The firmware's loop passes fall at power-up + 10 ms·k (its ``setup()``
    runs on its own time before the first transaction); the emulator is
    powered up 10 ms earlier so that its ticks fall on the same instants.
    One booted firmware is reused: :meth:`reset` restores its image.

    Args:
        source: The firmware's folder.
        motor: ``"following"`` (:class:`FollowingMotor`) or ``"kinematic"``
            (a free ``KinematicStepper``).
    """

    def __init__(self, source: str, motor: str = "following") -> None:
        self.kind = motor
        self.clock = ManualClock(0.0)
        self.sitl = SitlFirmware(source, "j1", self._motor(), self.clock)
        self._booted = self.sitl.snapshot()
        self._booted_motor = copy.deepcopy(self.sitl.motor)  # where setup()'s orientation check left it
        self.reset()

    def _motor(self) -> Any:
        return FollowingMotor() if self.kind == "following" else KinematicStepper(0.0)

    def reset(self) -> None:
        """Both joints just powered up at 0 degrees, the clock at 10 ms."""
        self.clock = ManualClock(0.0)
        self.ref = JointFirmware(self._motor(), self.clock)
        self.clock.sleep(TICK_S)
        self.sitl.clock = self.clock
        self.sitl.restore(self._booted)
        self.sitl.bridge.motor = copy.deepcopy(self._booted_motor)
        self._boot_us = round(self.sitl.device_time * 1e6)
        self._last_reg = 0
        self._rx_len = 0
        self.orientation_seen = False
        self.low_sensitivity = False
        self.handler_outlasted = False

    # ------------------------------------------------------------- running
    def run(self, steps: list[Step], position_tol: float | None = None) -> Outcome:
        """Run ``steps`` on both joints; raise :class:`Mismatch` on an unexplained difference.

        Args:
            steps: The sequence.
            position_tol: Compare ANGLEMOVED within this many degrees
                (``None``: positions are not compared).
        """
        outcome = Outcome()
        trace: list[str] = []
        for i, step in enumerate(steps):
            trace.append(f"{self.clock.now() * 1000:9.1f} ms  {step}")
            if isinstance(step, Wait):
                self._wait(step.seconds)
                continue
            if step.data:
                self._last_reg = step.data[0]
                self._rx_len = len(step.data) - 1
                if self._last_reg == Reg.CHECKORIENTATION and step.read_len > 0:
                    self.orientation_seen = True
            ref = self.ref.transfer(step.data, step.read_len)
            sitl = self.sitl.transfer(step.data, step.read_len)
            self._note_homing()
            outcome.transactions += 1
            trace[-1] += f"  -> emulator {ref.hex()} firmware {sitl.hex()}"
            problem = self._compare(ref, sitl, step.read_len, position_tol, outcome)
            if problem is None:
                continue
            cause = self.explain()
            if cause is None:
                listing = "\n".join(trace if len(trace) <= 60 else [*trace[:8], "...", *trace[-50:]])
                raise Mismatch(f"{problem} at step {i}, no documented cause; the sequence:\n{listing}")
            outcome.cause, outcome.at_step = cause, i
            return outcome
        problem = self._compare_device_flags()
        if problem is not None:
            cause = self.explain()
            if cause is None:
                listing = "\n".join(trace if len(trace) <= 60 else [*trace[:8], "...", *trace[-50:]])
                raise Mismatch(f"{problem} at the end, no documented cause; the sequence:\n{listing}")
            outcome.cause, outcome.at_step = cause, len(steps)
        return outcome

    def _wait(self, seconds: float) -> None:
        """Let time pass in 1 ms steps, noting the sensitivity of every homing the emulator runs."""
        end = self.clock.now() + seconds
        while self.clock.now() < end - 1e-12:
            self.clock.sleep(min(0.001, end - self.clock.now()))
            self.ref.update()
            self._note_homing()
        self.sitl.update()

    def _note_homing(self) -> None:
        core = self.ref.core
        if core.busy and core._homing[2] < 2 and core._pending_reg == Reg.HOME:
            self.low_sensitivity = True
        # The firmware still waits inside a blocking command (its 1 ms and 500 ms waits)
        # when the emulator's has ended.
        _, _, _, wait = self.sitl.loop_passes()
        if round(wait * 1000) in (1, 500) and not core.busy and not core.pending:
            self.handler_outlasted = True

    def _compare(
        self, ref: bytes, sitl: bytes, read_len: int, position_tol: float | None, outcome: Outcome
    ) -> str | None:
        if len(ref) != len(sitl):
            return f"reply lengths {len(ref)} and {len(sitl)}"
        reg = self._last_reg
        size = ANSWER_SIZE.get(reg, 0)
        if reg == Reg.HOMEOFFSET and self._rx_len == 0:
            size = 4
        for k in range(min(read_len, size)):
            if reg in MOTION_ANSWERS:
                break
            if ref[k] != sitl[k]:
                name = Reg(reg).name
                return f"{name} value byte {k}: emulator {ref[:size].hex()}, firmware {sitl[:size].hex()}"
        if reg == Reg.ANGLEMOVED and position_tol is not None and read_len >= 4:
            a = struct.unpack("<f", ref[:4])[0]
            b = struct.unpack("<f", sitl[:4])[0]
            outcome.compared_positions += 1
            if not abs(a - b) <= position_tol:
                return f"ANGLEMOVED {a:.4f} vs {b:.4f} degrees (tolerance {position_tol:.4f})"
        if read_len > size and ref[size] != sitl[size]:
            return f"flags: emulator {ref[size]:#04x}, firmware {sitl[size]:#04x}"
        if ref[size + 1 :] != sitl[size + 1 :]:
            return f"padding: emulator {ref[size + 1:].hex()}, firmware {sitl[size + 1:].hex()}"
        return None

    def _compare_device_flags(self) -> str | None:
        a, b = int(self.ref.flags), int(self.sitl.flags)
        return None if a == b else f"device flags: emulator {a:#04x}, firmware {b:#04x}"

    def explain(self) -> str | None:
        """The documented cause of a difference seen now, if one applies (module docstring)."""
        _, began, wakes, wait = self.sitl.loop_passes()
        in_loop_delay = round(wait * 1000) == 10  # the loop's delay(10), its only 10 ms wait
        if (round(began * 1e6) - self._boot_us) % 10_000 != 0 or (
            in_loop_delay and (round(wakes * 1e6) - self._boot_us) % 10_000 != 0
        ):
            return "loop_phase"
        if self.orientation_seen:
            return "orientation"
        if self.handler_outlasted:
            return "handler_end"
        core = self.ref.core
        if (core.stallguard and core.stall_sensitivity == 0) or self.low_sensitivity:
            return "quantization"
        return None


# ------------------------------------------------------------------ census
def _runner(check: Any) -> Any:
    def run_case(case: Any) -> None:
        check(case)

    return run_case


def _census(n: int) -> None:  # pragma: no cover - a report, run by hand
    import os
    import sys
    import time

    from hypothesis import HealthCheck, given, settings

    sys.path.insert(0, os.path.dirname(__file__))
    from test_sitl_differential import motion_sequences, protocol_sequences

    source = os.environ["BIOSCARA_FIRMWARE"]
    for name, strategy, kind in (
        ("protocol", protocol_sequences().map(lambda steps: (steps, None)), "following"),
        ("motion", motion_sequences(), "kinematic"),
    ):
        pair = Pair(source, kind)
        census = Census()
        start = time.perf_counter()

        def check(case: Any, pair: Pair = pair, census: Census = census) -> None:
            steps, position_tol = case
            pair.reset()
            try:
                census.add(pair.run(steps, position_tol))
            except Mismatch as e:
                census.sequences += 1
                census.mismatches.append(str(e).splitlines()[0])

        run = settings(
            max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck)
        )(given(strategy)(_runner(check)))
        run()
        elapsed = time.perf_counter() - start
        print(
            f"{name}: {census.sequences} sequences, {census.transactions} transactions, "
            f"{census.compared_positions} positions compared, {elapsed:.1f} s"
        )
        print(f"  ended early by documented causes: {dict(census.causes)}")
        for line, count in collections.Counter(census.mismatches).most_common():
            print(f"  MISMATCH x{count}: {line}")


if __name__ == "__main__":  # pragma: no cover
    import os
    import sys

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import sitl_differential  # the module itself, so its classes are the tests' classes

    sitl_differential._census(int(sys.argv[1]) if len(sys.argv) > 1 else 200)


__all__ = ["CAUSES", "Census", "FollowingMotor", "Mismatch", "Outcome", "Pair", "Step", "Tx", "Wait"]
