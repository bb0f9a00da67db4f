"""Byte-exact emulation of XL430-W250 servos on an RS-485 bus (protocol 2.0).

:class:`XL430` is one servo: its control table (``control_table.py``), the
rules of the EEPROM and RAM areas, a kinematic motor (position mode with the
profile velocity and acceleration, velocity mode), Present Load, overload
detection that sets the Hardware Error Status and turns torque off, and
REBOOT. :class:`EmulatedRS485Bus` is the wire: bytes go in
(:meth:`~EmulatedRS485Bus.write`), status packets come out
(:meth:`~EmulatedRS485Bus.read`), with fault injection (a lost status packet,
a flipped bit, a delay). The official SDK talks to it through
:class:`~bioscara_gym.hardware.dynamixel.port.EmulatedPortHandler` in
memory, or through a pseudo-terminal (:mod:`~bioscara_gym.hardware.dynamixel.pty_server`)
as it would to a USB-RS485 adapter.

What is emulated and what is not is listed in ``docs/dynamixel.md``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Mapping

import numpy as np

from bioscara_gym.hardware.clock import Clock, ManualClock
from bioscara_gym.hardware.dynamixel import protocol
from bioscara_gym.hardware.dynamixel.control_table import (
    ACCELERATION_RADS2_PER_UNIT,
    ADDR_GOAL_POSITION,
    ADDR_HARDWARE_ERROR,
    ADDR_OPERATING_MODE,
    ADDR_TORQUE_ENABLE,
    ALERT,
    BROADCAST_ID,
    CONTROL_TABLE,
    FIELDS,
    MAX_ID,
    MODEL_NUMBER,
    OVERLOAD_TRIP_S,
    REBOOT_S,
    TABLE_SIZE,
    VELOCITY_RADS_PER_UNIT,
    HardwareError,
    Instruction,
    OperatingMode,
    StatusError,
    to_signed,
    to_unsigned,
)
from bioscara_gym.hardware.dynamixel.protocol import Packet, PacketParser
from bioscara_gym.hardware.emulated_bus import RS485_FAULTS, Fault, FaultPlan

#: rad per position unit of the emulated motor (2*pi / 4096).
_RAD_PER_UNIT = 2 * math.pi / 4096
#: Integration step of the motor model, s (our choice: 1 ms, the servo's control period).
STEP_S = 0.001
#: Acceleration used when Profile Acceleration is 0 ("unlimited"), rad/s^2 (our choice).
UNLIMITED_ACCELERATION = 1000.0
#: Present Load while the rotor is held against a commanded motion, 0.1 % (our choice: 110 %).
HELD_LOAD = 1100


class XL430:
    """One emulated XL430-W250 servo.

    Args:
        dxl_id: The servo's ID (written to its EEPROM).
        clock: Time source; the motor catches up with it whenever the servo is addressed.
        position: Initial Present Position, raw (2047 is the centre).
        baud_rate: Baud Rate item (3 = 1 Mbps).
    """

    def __init__(self, dxl_id: int = 1, clock: Clock | None = None, position: int = 2047, baud_rate: int = 3):
        """Power the servo up."""
        if not 0 <= dxl_id <= MAX_ID:
            raise ValueError(f"ID {dxl_id} must be 0-{MAX_ID}")
        self.clock: Clock = clock if clock is not None else ManualClock()
        self.table = bytearray(TABLE_SIZE)
        for f in CONTROL_TABLE:
            if f.default is not None and f.eeprom:
                self._store(f.address, f.size, f.default)
        self._store(FIELDS["ID"].address, 1, dxl_id)
        self._store(FIELDS["Baud Rate"].address, 1, baud_rate)
        self.blocked = False  # the rotor is held (an obstacle): load rises, overload trips
        self.powered = True
        self._pos = float(position)  # raw units, float
        self._vel = 0.0  # rad/s
        self._registered: tuple[int, bytes] | None = None
        self._power_up()

    # ------------------------------------------------------------ table
    def _store(self, address: int, size: int, value: int) -> None:
        self.table[address : address + size] = to_unsigned(int(value), size).to_bytes(size, "little")

    def get(self, name: str) -> int:
        """The value of a control-table item (signed items as signed)."""
        f = FIELDS[name]
        raw = int.from_bytes(self.table[f.address : f.address + f.size], "little")
        return to_signed(raw, f.size) if f.signed else raw

    def set(self, name: str, value: int) -> None:
        """Set an item directly (the emulator's back door; no access rules)."""
        f = FIELDS[name]
        self._store(f.address, f.size, value)

    @property
    def id(self) -> int:
        """The ID item."""
        return self.table[FIELDS["ID"].address]

    @property
    def torque(self) -> bool:
        """Torque Enable."""
        return bool(self.table[ADDR_TORQUE_ENABLE])

    @property
    def hardware_error(self) -> int:
        """Hardware Error Status."""
        return self.table[ADDR_HARDWARE_ERROR]

    def _power_up(self) -> None:
        """RAM to its defaults (power-up and REBOOT); Goal Position := Present Position."""
        for f in CONTROL_TABLE:
            if not f.eeprom and f.default is not None:
                self._store(f.address, f.size, f.default)
        self._vel = 0.0
        self._registered = None
        self._overload_s = 0.0
        self._t = self.clock.now()
        self._silent_until = self._t
        self._publish()
        self._store(ADDR_GOAL_POSITION, 4, round(self._pos))

    def power_cycle(self) -> None:
        """Cut and restore the power: RAM reset, torque off, errors cleared; EEPROM and the rotor stay."""
        self._power_up()

    # ------------------------------------------------------------ motor
    def update(self) -> None:
        """Run the motor model up to the clock's time, in steps of :data:`STEP_S`."""
        now = self.clock.now()
        dt = now - self._t
        if dt <= 0:
            return
        if self._at_rest():
            # Every step would leave it as it is: skip them. Stepping a servo left alone for
            # 10 s took 50 ms, longer than the SDK waits for a status packet (34 ms at 1 Mbps),
            # so the first request after a pause timed out and its reply came late.
            self._store(FIELDS["Present Load"].address, 2, 0)
            self._overload_s = 0.0
            self._t = now
            self._publish()
            return
        steps = min(math.ceil(dt / STEP_S - 1e-9), 100_000)
        h = dt / steps
        for _ in range(steps):
            self._step(h)
        self._t = now
        self._publish()

    def _at_rest(self) -> bool:
        """Whether the rotor stands and nothing drives it: a step of :meth:`_step` changes nothing.

        Still, and torque off, or in velocity mode with Goal Velocity 0, or
        in a position mode within half a unit of the goal (where
        :meth:`_step` asks for no speed), or in another mode (PWM: not modelled).
        """
        if self._vel != 0.0:
            return False
        if not self.torque:
            return True
        mode = self.table[ADDR_OPERATING_MODE]
        if mode == OperatingMode.VELOCITY:
            return self.get("Goal Velocity") == 0
        if mode in (OperatingMode.POSITION, OperatingMode.EXTENDED_POSITION):
            err = (self.get("Goal Position") - self._pos) * _RAD_PER_UNIT
            return abs(err) < 0.5 * _RAD_PER_UNIT  # as _step: no speed asked for
        return True

    def _step(self, h: float) -> None:
        mode = self.table[ADDR_OPERATING_MODE]
        acc_units = self.get("Profile Acceleration")
        acc = acc_units * ACCELERATION_RADS2_PER_UNIT if acc_units else UNLIMITED_ACCELERATION
        vlimit = self.get("Velocity Limit") * VELOCITY_RADS_PER_UNIT
        target_v = 0.0
        if self.torque:
            if mode == OperatingMode.VELOCITY:
                target_v = self.get("Goal Velocity") * VELOCITY_RADS_PER_UNIT
            elif mode in (OperatingMode.POSITION, OperatingMode.EXTENDED_POSITION):
                pv = self.get("Profile Velocity") * VELOCITY_RADS_PER_UNIT
                vmax = min(pv, vlimit) if pv > 0 else vlimit
                err = (self.get("Goal Position") - self._pos) * _RAD_PER_UNIT
                # the fastest speed from which the servo still stops at the goal
                target_v = math.copysign(min(vmax, math.sqrt(2 * acc * abs(err))), err)
                if abs(err) < 0.5 * _RAD_PER_UNIT:
                    target_v = 0.0
            target_v = max(-vlimit, min(vlimit, target_v))
        else:
            acc = UNLIMITED_ACCELERATION  # unpowered: friction stops it at once
        dv = max(-acc * h, min(acc * h, target_v - self._vel))
        self._vel += dv
        wants_to_move = self.torque and abs(target_v) > 0.0
        if self.blocked:
            self._vel = 0.0
        else:
            new = self._pos + self._vel * h / _RAD_PER_UNIT
            if self.torque and mode == OperatingMode.POSITION:
                goal = float(self.get("Goal Position"))
                if (self._pos - goal) * (new - goal) <= 0:  # reached or crossed the goal: stop on it
                    new, self._vel = goal, 0.0
            self._pos = min(max(new, -(2.0**31)), 2.0**31 - 1)
        load = 0
        if self.blocked and wants_to_move:
            load = int(math.copysign(HELD_LOAD, target_v))
        self._store(FIELDS["Present Load"].address, 2, load)
        if abs(load) > 1000 and self.torque:
            self._overload_s += h
            if self._overload_s >= OVERLOAD_TRIP_S:
                self._trip(HardwareError.OVERLOAD)
        else:
            self._overload_s = 0.0

    def _trip(self, error: HardwareError) -> None:
        """A hardware error: set its bit; shut down (torque off) if the Shutdown item says so (e-Manual)."""
        self.table[ADDR_HARDWARE_ERROR] |= int(error)
        if self.get("Shutdown") & int(error):
            self.table[ADDR_TORQUE_ENABLE] = 0
            self._vel = 0.0
            self._store(FIELDS["Present Load"].address, 2, 0)

    def _publish(self) -> None:
        """Present Position, Velocity, Moving and Realtime Tick from the motor state."""
        self._store(FIELDS["Present Position"].address, 4, round(self._pos))
        self._store(FIELDS["Present Velocity"].address, 4, round(self._vel / VELOCITY_RADS_PER_UNIT))
        moving = abs(self._vel) > self.get("Moving Threshold") * VELOCITY_RADS_PER_UNIT
        self.table[FIELDS["Moving"].address] = int(moving)
        self._store(FIELDS["Realtime Tick"].address, 2, int(self.clock.now() * 1000) % 32768)

    @property
    def position_rad(self) -> float:
        """Rotor angle from the centre (2047), rad, unrounded."""
        return (self._pos - 2047) * _RAD_PER_UNIT

    @property
    def velocity_rads(self) -> float:
        """Rotor speed, rad/s."""
        return self._vel

    # ------------------------------------------------------------ packets
    def responsive(self) -> bool:
        """Whether the servo is powered and not rebooting."""
        return self.powered and self.clock.now() >= self._silent_until

    def _alert(self) -> int:
        return ALERT if self.hardware_error else 0

    def _status(self, error: int = 0, data: bytes = b"", dxl_id: int | None = None) -> bytes:
        return protocol.status_packet(self.id if dxl_id is None else dxl_id, error | self._alert(), data)

    def _check_read(self, address: int, length: int) -> int:
        if length < 1 or address < 0 or address + length > TABLE_SIZE:
            return StatusError.ACCESS
        return StatusError.NONE

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """READ: (error number, data)."""
        self.update()
        error = self._check_read(address, length)
        if error:
            return error, b""
        return StatusError.NONE, bytes(self.table[address : address + length])

    def write(self, address: int, data: bytes) -> int:
        """WRITE (and the data of SYNC/BULK WRITE): the error number; nothing is written on an error."""
        self.update()
        end = address + len(data)
        if not data or address < 0 or end > TABLE_SIZE:
            return StatusError.ACCESS
        touched = [f for f in CONTROL_TABLE if f.address < end and address < f.address + f.size]
        for f in touched:
            if not f.writable:
                return StatusError.ACCESS
            if f.address < address or f.address + f.size > end:
                return StatusError.DATA_LENGTH  # a partial item (our choice of error)
            if f.eeprom and self.torque:
                return StatusError.ACCESS  # EEPROM is locked while torque is on (e-Manual)
        covered = sum(f.size for f in touched)
        if covered != len(data):
            return StatusError.ACCESS  # reserved bytes in the range
        values = {
            f.name: int.from_bytes(data[f.address - address : f.address - address + f.size], "little")
            for f in touched
        }
        error = self._check_values(values)
        if error:
            return error
        for f in touched:
            if f.name == "Torque Enable" and values[f.name] and self.hardware_error:
                continue  # a servo with a hardware error keeps torque off until REBOOT (e-Manual)
            if f.name == "Torque Enable" and values[f.name] and not self.torque:
                self._store(ADDR_GOAL_POSITION, 4, round(self._pos))  # hold where it is
            self._store(f.address, f.size, values[f.name])
        return StatusError.NONE

    def _check_values(self, values: Mapping[str, int]) -> int:
        """Data range and limit checks of the items the driver writes (e-Manual ranges)."""
        if "Goal Position" in values:
            goal = to_signed(values["Goal Position"], 4)
            mode = values.get("Operating Mode", self.table[ADDR_OPERATING_MODE])
            if mode == OperatingMode.POSITION and not self.get("Min Position Limit") <= goal <= self.get(
                "Max Position Limit"
            ):
                return StatusError.DATA_LIMIT
        velocity = to_signed(values.get("Goal Velocity", 0), 4)
        if abs(velocity) > self.get("Velocity Limit"):
            return StatusError.DATA_LIMIT
        if "Operating Mode" in values and values["Operating Mode"] not in (0, 1, 3, 4, 5, 16):
            return StatusError.DATA_RANGE
        if "Torque Enable" in values and values["Torque Enable"] > 1:
            return StatusError.DATA_RANGE
        if "ID" in values and values["ID"] > MAX_ID:
            return StatusError.DATA_RANGE
        return StatusError.NONE

    def reboot(self) -> None:
        """REBOOT: RAM back to defaults, errors cleared, silent for :data:`REBOOT_S`."""
        self.update()
        self._power_up()
        self._silent_until = self.clock.now() + REBOOT_S

    def handle(self, packet: Packet) -> bytes | None:
        """Execute one instruction addressed to this servo (or broadcast); return the status packet."""
        inst, p = packet.instruction, packet.params
        level = self.get("Status Return Level")
        broadcast = packet.id == BROADCAST_ID
        # The WRITE that changes the ID is acknowledged under the ID it was sent to (our choice: the
        # SDK's write1ByteTxRx, and DynamixelWorkbench's changeID with it, waits for that ID).
        answering_id = self.id

        def reply(error: int = 0, data: bytes = b"", read: bool = False) -> bytes | None:
            if broadcast and inst != Instruction.PING:
                return None
            if inst != Instruction.PING and (level == 0 or (level == 1 and not read)):
                return None
            return self._status(error, data, answering_id)

        if not packet.crc_ok:
            return reply(StatusError.CRC)
        if inst == Instruction.PING:
            self.update()
            return reply(data=bytes((MODEL_NUMBER & 0xFF, MODEL_NUMBER >> 8, self.get("Firmware Version"))))
        if inst == Instruction.READ:
            if len(p) != 4:
                return reply(StatusError.DATA_LENGTH, read=True)
            error, data = self.read(p[0] | p[1] << 8, p[2] | p[3] << 8)
            return reply(error, data, read=True)
        if inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(p) < 3:
                return reply(StatusError.DATA_LENGTH)
            if inst == Instruction.REG_WRITE:
                self._registered = (p[0] | p[1] << 8, bytes(p[2:]))
                self.table[FIELDS["Registered Instruction"].address] = 1
                return reply()
            return reply(self.write(p[0] | p[1] << 8, bytes(p[2:])))
        if inst == Instruction.ACTION:
            if self._registered is None:
                return reply(StatusError.RESULT_FAIL)
            address, data = self._registered
            self._registered = None
            self.table[FIELDS["Registered Instruction"].address] = 0
            return reply(self.write(address, data))
        if inst == Instruction.REBOOT:
            status = reply()
            self.reboot()
            return status
        return reply(StatusError.INSTRUCTION)


class EmulatedRS485Bus:
    """Servos on one half-duplex RS-485 bus, seen as a byte stream.

    :meth:`write` takes what the host transmits; every complete instruction
    packet is executed at once by the servo it addresses (or, broadcast, by
    every servo), and the status packets are queued for :meth:`read`. A
    SYNC READ or BULK READ is answered by each listed servo in turn. Packets
    for absent IDs get no answer (the host times out).

    A servo is addressed by its ID item as it is now: after a WRITE of a new
    ID it answers to that one and no longer to the old (as a real servo, whose
    ID is in EEPROM). :attr:`servos` stays keyed by the ID each servo was built
    with (the tests' handle on it). Two servos given one ID are both addressed,
    as on a real bus: both execute the instruction and answer at once, and
    their status packets collide on the wire (:meth:`_collide`).

    Args:
        servos: The servos (IDs must be unique when attached).
        faults: Faults injected into status packets.
        clock: Time source; defaults to the first servo's.
    """

    def __init__(
        self, servos: Iterable[XL430], faults: FaultPlan | None = None, clock: Clock | None = None
    ) -> None:
        """Attach the servos."""
        self.servos: dict[int, XL430] = {}
        for servo in servos:
            if servo.id in self.servos:
                raise ValueError(f"two servos with ID {servo.id}")
            self.servos[servo.id] = servo
        self.faults = faults or FaultPlan()
        self.faults.check_for(RS485_FAULTS)
        self._rng = np.random.default_rng(self.faults.seed)
        if clock is None:
            clock = next(iter(self.servos.values())).clock if self.servos else ManualClock()
        self.clock = clock
        self._parser = PacketParser()
        self._out = bytearray()
        self.lock = threading.RLock()
        self.instructions = 0  # instruction packets received
        self.statuses = 0  # status packets produced (the fault schedule's index)
        self.log: list[Packet] = []  # every instruction packet received, for tests
        self.keep_log = False
        self.pending_delay_s = 0.0  # delay the pty server must apply before the next reply

    @classmethod
    def with_ids(cls, ids: Iterable[int], clock: Clock | None = None, **kwargs: object) -> EmulatedRS485Bus:
        """A bus with one fresh XL430 per ID, all on ``clock``."""
        clock = clock if clock is not None else ManualClock()
        return cls([XL430(i, clock) for i in ids], clock=clock, **kwargs)  # type: ignore[arg-type]

    # ------------------------------------------------------------ stream
    @property
    def in_receive(self) -> int:
        """Bytes of an instruction packet received in part (the pty server drops them when the line idles)."""
        return self._parser.pending

    def clear_input(self) -> None:
        """Drop a partly received packet: what comes next starts a new one."""
        with self.lock:
            self._parser.clear()

    def write(self, data: bytes) -> int:
        """Receive bytes from the host; execute every complete instruction packet."""
        with self.lock:
            for packet in self._parser.feed(bytes(data)):
                self.instructions += 1
                if self.keep_log:
                    self.log.append(packet)
                self._out.extend(self._execute(packet))
            return len(data)

    def read(self, size: int = -1) -> bytes:
        """Take up to ``size`` (all with -1) bytes the servos have sent."""
        with self.lock:
            n = len(self._out) if size < 0 else min(size, len(self._out))
            data = bytes(self._out[:n])
            del self._out[:n]
            return data

    @property
    def in_waiting(self) -> int:
        """Bytes ready for :meth:`read`."""
        return len(self._out)

    def clear_output(self) -> None:
        """Drop unread status bytes (the host flushed its input)."""
        with self.lock:
            self._out.clear()

    def transact(self, data: bytes) -> bytes:
        """Write an instruction packet and return everything sent back (tests)."""
        self.write(data)
        return self.read()

    def update(self) -> None:
        """Let every servo's motor catch up with the clock."""
        with self.lock:
            for servo in self.servos.values():
                servo.update()

    # ------------------------------------------------------------ execution
    def _addressed(self, dxl_id: int) -> list[XL430]:
        """The responsive servos whose ID item is ``dxl_id`` now (one, unless two were given one ID)."""
        return [s for s in self.servos.values() if s.id == dxl_id and s.responsive()]

    @staticmethod
    def _collide(replies: list[bytes]) -> bytes:
        """What the host receives when servos answer at once: their bytes superimposed.

        Our model of the collision: a 0 bit from either driver wins (the bytes
        AND-ed), and the longer packet's tail comes through alone. Identical
        replies (two servos acknowledging one WRITE) so look like one, as they
        would on the wire; different ones reach the host garbled (a bad CRC).
        """
        replies = [r for r in replies if r]
        if len(replies) < 2:
            return replies[0] if replies else b""
        out = bytearray(max(replies, key=len))
        for r in replies:
            for i, b in enumerate(r):
                out[i] &= b
        return bytes(out)

    def _execute(self, packet: Packet) -> bytes:
        if packet.instruction == Instruction.STATUS:
            return b""  # another device's status packet: not for us
        targets: list[XL430]
        if packet.id == BROADCAST_ID:
            targets = [s for s in self.servos.values() if s.responsive()]
        else:
            targets = self._addressed(packet.id)
        if not packet.crc_ok:
            # a corrupted packet: a servo whose ID is intact answers with a CRC error
            if packet.id == BROADCAST_ID:
                return b""
            return self._collide([self._fault(r) for s in targets if (r := s.handle(packet))])
        inst = packet.instruction
        if packet.id == BROADCAST_ID and inst in (
            Instruction.SYNC_READ,
            Instruction.SYNC_WRITE,
            Instruction.BULK_READ,
            Instruction.BULK_WRITE,
        ):
            return self._group(packet)
        # a broadcast PING is answered in ID order (each servo waits its turn); servos sharing an
        # ID answer at once.
        replies: dict[int, list[bytes]] = {}
        for servo in sorted(targets, key=lambda s: s.id):
            answering_id = servo.id
            status = servo.handle(packet)
            if status is not None:
                replies.setdefault(answering_id, []).append(self._fault(status))
        return b"".join(self._collide(r) for _, r in sorted(replies.items()))

    def _group(self, packet: Packet) -> bytes:
        """SYNC READ/WRITE and BULK READ/WRITE (protocol: broadcast, parameters per servo)."""
        p, inst = packet.params, packet.instruction
        out = bytearray()

        def answer(i: int, address: int, length: int) -> None:
            """Servo ``i``'s turn to answer: absent, the host times out waiting for it."""
            replies = []
            for s in self._addressed(i):
                error, data = s.read(address, length)
                replies.append(self._fault(s._status(error, data)))
            out.extend(self._collide(replies))

        if inst in (Instruction.SYNC_READ, Instruction.SYNC_WRITE):
            if len(p) < 4:
                return b""
            address, length = p[0] | p[1] << 8, p[2] | p[3] << 8
            if inst == Instruction.SYNC_READ:
                for i in p[4:]:
                    answer(i, address, length)
            else:
                chunk = 1 + length
                body = p[4:]
                for k in range(0, len(body) - chunk + 1, chunk):
                    for s in self._addressed(body[k]):
                        s.write(address, bytes(body[k + 1 : k + chunk]))
            return bytes(out)
        if inst == Instruction.BULK_READ:
            for k in range(0, len(p) - 4, 5):
                answer(p[k], p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8)
            return bytes(out)
        k = 0  # BULK WRITE
        while k + 5 <= len(p):
            address, length = p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8
            for s in self._addressed(p[k]):
                s.write(address, bytes(p[k + 5 : k + 5 + length]))
            k += 5 + length
        return b""

    def _fault(self, status: bytes) -> bytes:
        """Apply the fault plan to one status packet."""
        index = self.statuses
        self.statuses += 1
        plan = self.faults
        scheduled = plan.schedule.get(index)
        delay = plan.latency_s + (0.001 if scheduled is Fault.LATENCY and not plan.latency_s else 0.0)
        if delay:
            self.pending_delay_s += delay
            if isinstance(self.clock, ManualClock):
                self.clock.sleep(delay)
        if scheduled is Fault.DROP or (plan.drop > 0 and self._rng.random() < plan.drop):
            return b""
        if scheduled is Fault.CORRUPT or (plan.corrupt > 0 and self._rng.random() < plan.corrupt):
            data = bytearray(status)
            i = int(self._rng.integers(7, len(data)))  # body or CRC: the host must see a bad CRC
            data[i] ^= 1 << int(self._rng.integers(0, 8))
            return bytes(data)
        return status
