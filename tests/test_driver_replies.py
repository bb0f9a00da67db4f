"""The driver's reply checks and retry policy (docs/protocol.md, "What the host can detect").

The protocol has no checksum: the driver checks each reply against what the
joint can have sent (finite values, positions within the end stops plus a
margin, speeds the motor can reach, flags the command cannot leave) and
retries only reads and idempotent commands. Byte-level, on ``scripted_bus``
(``conftest.py``), plus the emulated firmware where the joint's own state
tells whether a command ran once or twice.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Any

import pytest
from rigs import J1, build_emulated

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.emulated_bus import Fault, FaultPlan
from bioscara_gym.hardware.errors import CommError, StalledError
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.registers import (
    BLOCKING_PICKUP_S,
    IDEMPOTENT_COMMANDS,
    MAX_PLAUSIBLE_RPM,
    READ_REGISTERS,
    Flag,
    Reg,
)
from bioscara_gym.hardware.stats import CommStats

# docs/model.md: j1 reduction 35, limits +-3.04647 rad; j2 the lift.
J1_LIMIT = 3.04647
READY, STALL, BUSY, NOT_HOMED, NOT_ENABLED = 0x00, 0x01, 0x02, 0x04, 0x08


def f32(value: float) -> bytes:
    return struct.pack("<f", value)


def flags(value: int) -> bytes:
    return bytes((value,))


def ack(value: int) -> bytes:
    return b"O" + flags(value)


def j1_degrees(q: float, offset: float = J1_LIMIT) -> float:
    """ANGLEMOVED of j1 at ``q`` homed against ``offset``: rad2deg(35 (q - offset))."""
    return math.degrees(35.0 * (q - offset))


@pytest.fixture
def make_j1(scripted_bus: Any) -> Callable[..., Joint]:
    """j1 on the scripted bus, ``init()``-ed into ``state`` (homed: offset ``max``), log cleared."""

    def make(state: int = READY, retries: int = 2, offset: float = J1_LIMIT) -> Joint:
        joint = Joint(
            "j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, retries=retries, clock=ManualClock()
        )
        scripted_bus.queue(ack(state))
        if not state & NOT_HOMED:
            scripted_bus.queue(f32(offset) + flags(state))
        joint.init()
        scripted_bus.clear_log()
        joint.stats.reset()
        return joint

    return make


# ----------------------------------------------- the 40 single-bit flips


class _Bus:
    """A bus answering from a list, for the bit-flip experiment (no fixture checks).

    A PING that is not in the list (the driver confirming a sticky flag) is
    answered with the joint's true flags, READY.
    """

    def __init__(self, replies: list[bytes]) -> None:
        self.replies = list(replies)

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        if data == bytes((Reg.PING,)) and len(self.replies) < 3:
            return ack(READY)
        return self.replies.pop(0)

    def close(self) -> None:
        pass


def detected_flips(q: float) -> int:
    """Of the 40 single-bit flips of j1's ANGLEMOVED reply at ``q`` (homed, ready), how many are caught.

    Caught: the driver rejects the reply (counts an error) and reads again.
    """
    good = f32(j1_degrees(q)) + flags(READY)
    caught = 0
    for bit in range(8 * len(good)):
        bad = bytearray(good)
        bad[bit // 8] ^= 1 << (bit % 8)
        bus = _Bus([ack(READY), f32(J1_LIMIT) + flags(READY), bytes(bad), good])
        joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, bus, clock=ManualClock())
        joint.init()
        q_read = joint.get_position()
        if joint.stats.total_errors:
            caught += 1
            assert q_read == pytest.approx(q, abs=1e-5)  # the second, good reply was used
    return caught


def test_bit_flip_experiment_detects_at_least_12_of_40() -> None:
    # Before the plausibility checks only the 4 reserved flag bits were caught;
    # the sticky flags' confirmation catches STALL, NOTENABLED and NOTHOMED too.
    assert detected_flips(1.0) >= 12


@pytest.mark.parametrize("q", [-2.0, 0.0, 3.0])
def test_bit_flip_experiment_beats_the_reserved_bits_alone(q: float) -> None:
    assert detected_flips(q) >= 11


# ------------------------------------------------------- implausible values


def test_huge_angle_is_read_again(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    scripted_bus.queue(f32(-3.8e19) + flags(READY), f32(j1_degrees(1.0)) + flags(READY))
    assert joint.get_position() == pytest.approx(1.0, abs=1e-5)
    assert (joint.stats.transactions, joint.stats.retries, joint.stats.implausible) == (2, 1, 1)


def test_implausible_angle_twice_raises_comm_error_with_joint_register_and_bytes(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(retries=1)
    bad = f32(-3.8e19) + flags(READY)
    scripted_bus.queue(bad, bad)
    with pytest.raises(CommError, match=r"ANGLEMOVED.*end stops") as info:
        joint.get_position()
    assert info.value.joint == "j1"
    assert info.value.register is Reg.ANGLEMOVED
    assert bad.hex(" ") in str(info.value)
    assert joint.stats.errors_by_kind == {"bus": 0, "malformed": 0, "implausible": 2}


@pytest.mark.parametrize(
    ("q", "plausible"),
    [(J1_LIMIT, True), (-J1_LIMIT, True), (J1_LIMIT + 0.6, True), (J1_LIMIT + 0.7, False), (-3.8, False)],
)
def test_homed_position_margin_is_a_tenth_of_the_range(
    scripted_bus: Any, make_j1: Callable[..., Joint], q: float, plausible: bool
) -> None:
    joint = make_j1(retries=0)
    scripted_bus.queue(f32(j1_degrees(q)) + flags(READY))
    if plausible:
        assert joint.get_position() == pytest.approx(q, abs=1e-5)
    else:
        with pytest.raises(CommError, match="end stops"):
            joint.get_position()


@pytest.mark.parametrize(("deg", "plausible"), [(12_000.0, True), (-12_000.0, True), (15_000.0, False)])
def test_unhomed_angle_must_lie_within_the_travel(
    scripted_bus: Any, make_j1: Callable[..., Joint], deg: float, plausible: bool
) -> None:
    # j1's travel is rad2deg(35 * 6.09) = 12218 deg; 1.1 ranges plus one turn is 13800 deg.
    joint = make_j1(state=NOT_HOMED, retries=0)
    scripted_bus.queue(f32(deg) + flags(NOT_HOMED))
    if plausible:
        assert joint.get_position() == 0.0
    else:
        with pytest.raises(CommError, match="travel"):
            joint.get_position()


@pytest.mark.parametrize(
    ("rpm", "plausible"), [(1146.0, True), (-4400.0, True), (4600.0, False), (-1e9, False)]
)
def test_encoder_speed_beyond_the_motor_is_implausible(
    scripted_bus: Any, make_j1: Callable[..., Joint], rpm: float, plausible: bool
) -> None:
    joint = make_j1(retries=0)
    scripted_bus.queue(f32(rpm) + flags(READY))
    if plausible:
        assert joint.get_velocity() == pytest.approx(math.radians(rpm) / 35.0 * 6.0, rel=1e-6)
    else:
        with pytest.raises(CommError, match=f"{MAX_PLAUSIBLE_RPM:g} RPM"):
            joint.get_velocity()


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_non_finite_speed_is_malformed(
    scripted_bus: Any, make_j1: Callable[..., Joint], value: float
) -> None:
    joint = make_j1()
    scripted_bus.queue(f32(value) + flags(READY), f32(0.0) + flags(READY))
    assert joint.get_velocity() == 0.0
    assert joint.stats.malformed == 1


def test_home_offset_beyond_the_limits_is_read_again(scripted_bus: Any) -> None:
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    scripted_bus.queue(ack(READY), f32(-1.9e16) + flags(READY), f32(J1_LIMIT) + flags(READY))
    joint.init()
    assert joint.offset == pytest.approx(J1_LIMIT)
    assert joint.stats.implausible == 1


def test_home_offset_infinity_is_malformed_but_nan_is_the_no_offset_mark(scripted_bus: Any) -> None:
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    scripted_bus.queue(ack(READY), f32(math.inf) + flags(READY), f32(math.nan) + flags(READY))
    joint.init()
    assert joint.stats.malformed == 1
    assert not joint.is_homed()  # NaN: homed with no stored offset -> home again


# ------------------------------------------------------------ impossible flags


@pytest.mark.parametrize(
    ("command", "bad", "good"),
    [
        pytest.param(lambda j: j.stop(), BUSY, READY, id="STOP_leaves_BUSY"),
        pytest.param(lambda j: j.enable(20, 20), STALL, READY, id="SETUP_leaves_STALL"),
        pytest.param(lambda j: j.enable_stallguard(6), STALL, READY, id="ENABLESTALLGUARD_leaves_STALL"),
        pytest.param(
            lambda j: j.set_drive_current(0), READY, NOT_ENABLED, id="SETCURRENT_0_without_NOTENABLED"
        ),
        pytest.param(
            lambda j: j.set_hold_current(0), READY, NOT_ENABLED, id="SETHOLDCURRENT_0_without_NOTENABLED"
        ),
        pytest.param(lambda j: j.set_velocity(0.1), READY | 0x40, READY, id="reserved_bit6"),
    ],
)
def test_reply_flags_the_command_cannot_leave_are_read_again(
    scripted_bus: Any, make_j1: Callable[..., Joint], command: Callable[[Joint], None], bad: int, good: int
) -> None:
    joint = make_j1()
    scripted_bus.queue(flags(bad), flags(good))
    command(joint)
    assert len(scripted_bus.log) == 2
    assert scripted_bus.log[0] == scripted_bus.log[1]  # the same command again
    assert joint.stats.errors == 1
    assert joint.flags == Flag(good)


def test_nonzero_current_reply_is_not_checked_for_not_enabled(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(flags(READY))
    joint.set_drive_current(30)
    assert joint.stats.errors == 0


def test_a_stall_in_a_motion_reply_is_confirmed_by_reading_the_flags_again(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(flags(STALL), ack(STALL))
    with pytest.raises(StalledError, match="stalled"):
        joint.set_velocity(0.1)
    assert joint.stats.errors == 0
    assert [data[0] for _, data, _ in scripted_bus.log] == [Reg.SETRPM, Reg.PING]


@pytest.mark.parametrize(
    ("bit", "name"), [(STALL, "STALL"), (NOT_ENABLED, "NOT_ENABLED"), (NOT_HOMED, "NOT_HOMED")]
)
def test_a_sticky_flag_the_second_reading_lacks_was_corrupted(
    scripted_bus: Any, make_j1: Callable[..., Joint], bit: int, name: str
) -> None:
    # One flipped bit used to stop a deploy on a stall that never happened.
    joint = make_j1()
    scripted_bus.queue(flags(bit), ack(READY), flags(READY))
    joint.set_velocity(0.1)  # no StalledError / NotEnabledError
    assert joint.stats.implausible == 1 and joint.stats.retries == 1
    assert [data[0] for _, data, _ in scripted_bus.log] == [Reg.SETRPM, Reg.PING, Reg.SETRPM]
    assert joint.flags == Flag(READY) and name not in repr(joint.flags)


def test_a_flag_the_command_sets_itself_is_not_read_again(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(flags(NOT_ENABLED))  # SETCURRENT 0 sets NOTENABLED in its own reply
    joint.set_drive_current(0)
    assert [data[0] for _, data, _ in scripted_bus.log] == [Reg.SETCURRENT]
    assert joint.stats.errors == 0


# ----------------------------------------------------------------- stats


def test_stats_count_retries_and_errors_by_kind(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    scripted_bus.queue(
        OSError(121, "Remote I/O error"),
        f32(90.0),  # short
        f32(-3.8e19) + flags(READY),  # implausible
    )
    with pytest.raises(CommError):
        joint.get_position()
    s = joint.stats
    assert (s.transactions, s.retries, s.errors) == (3, 2, 3)
    assert s.errors_by_kind == {"bus": 1, "malformed": 1, "implausible": 1}
    assert (s.total_retries, s.total_bus_errors, s.total_malformed, s.total_implausible) == (2, 1, 1, 1)
    s.reset()
    assert (s.retries, s.bus_errors, s.total_retries) == (0, 0, 2)
    d = s.as_dict()
    assert d["total_errors"] >= 3 and d["retries"] == 0


def test_stats_fields_are_all_ints() -> None:
    # The console saves the counters in its state file and checks they are ints.
    s = CommStats()
    s.record(ok=False, kind="implausible", retry=True)
    assert all(isinstance(v, int) for v in vars(s).values())


def test_stats_reject_an_unknown_kind() -> None:
    with pytest.raises(ValueError, match="unknown error kind"):
        CommStats().record(ok=False, kind="gremlin")


# ------------------------------------------------------------ retry policy


def test_idempotency_table() -> None:
    never = {Reg.MOVESTEPS, Reg.HOME, Reg.CHECKORIENTATION}
    assert not never & IDEMPOTENT_COMMANDS
    assert {Reg.SETUP, Reg.SETRPM, Reg.MOVETOANGLE, Reg.STOP, Reg.HOMEOFFSET} <= IDEMPOTENT_COMMANDS
    assert not READ_REGISTERS - {Reg.HOMEOFFSET} & IDEMPOTENT_COMMANDS  # reads are retried as reads


@pytest.mark.parametrize(
    "command",
    [
        pytest.param(lambda j: j.enable(20, 20), id="SETUP"),
        pytest.param(lambda j: j.set_velocity(0.1), id="SETRPM"),
        pytest.param(lambda j: j.set_position(0.1), id="MOVETOANGLE"),
        pytest.param(lambda j: j.set_drive_current(20), id="SETCURRENT"),
        pytest.param(lambda j: j.set_hold_current(20), id="SETHOLDCURRENT"),
        pytest.param(lambda j: j.set_max_velocity(1.0), id="SETMAXVELOCITY"),
        pytest.param(lambda j: j.set_max_acceleration(1.0), id="SETMAXACCELERATION"),
        pytest.param(lambda j: j.enable_stallguard(6), id="ENABLESTALLGUARD"),
        pytest.param(lambda j: j.set_brake_mode(0), id="SETBRAKEMODE"),
        pytest.param(lambda j: j.stop(), id="STOP"),
        pytest.param(lambda j: j.disable_closed_loop(), id="DISABLECLOSEDLOOP"),
    ],
)
def test_idempotent_command_is_sent_again_after_a_lost_reply(
    scripted_bus: Any, make_j1: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_j1()
    scripted_bus.queue(b"", flags(READY))
    command(joint)
    assert len(scripted_bus.log) == 2
    assert scripted_bus.log[0] == scripted_bus.log[1]


@pytest.mark.parametrize(
    "lost", [b"", OSError(121, "Remote I/O error"), flags(0x80)], ids=["short", "nack", "bad"]
)
def test_move_steps_is_never_sent_twice(scripted_bus: Any, make_j1: Callable[..., Joint], lost: Any) -> None:
    joint = make_j1()
    scripted_bus.queue(lost)
    with pytest.raises(CommError, match=r"MOVESTEPS failed.*Not sent again") as info:
        joint.move_steps(200)
    assert len(scripted_bus.log) == 1
    assert info.value.register is Reg.MOVESTEPS


def test_move_steps_with_a_lost_reply_moves_the_emulated_motor_once() -> None:
    emu = build_emulated(J1, start_q=0.0, faults=FaultPlan(schedule={4: Fault.SHORT_READ}))
    j = emu.joint
    j.init()  # 0: PING
    j.enable(J1.drive_current, J1.hold_current)  # 1: SETUP
    # The host's limits, as the arm sets them on enable (the power-up 18 deg/s
    # would take 10 s for the move): j1 1 rad/s, 2 rad/s^2, at the motor 2005 deg/s,
    # 4011 deg/s^2 (docs/model.md).
    j.set_max_velocity(1.0)  # 2: SETMAXVELOCITY
    j.set_max_acceleration(2.0)  # 3: SETMAXACCELERATION
    start = emu.motor.position_deg
    with pytest.raises(CommError):
        j.move_steps(25600)  # 4: delivered, reply cut short (microsteps: half a turn)
    emu.advance(2.0)
    assert emu.motor.position_deg - start == pytest.approx(180.0, abs=0.5)  # half a turn once, not twice


def test_lost_reply_of_home_that_started_counts_as_started(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(state=NOT_HOMED)
    # HOMEOFFSET := NaN; HOME's reply lost; the PING finds BUSY
    scripted_bus.queue(flags(NOT_HOMED), b"", ack(BUSY | NOT_HOMED))
    joint.start_homing(0.03, 30, 15)
    sent = [data[0] for _, data, _ in scripted_bus.log]
    assert sent == [Reg.HOMEOFFSET, Reg.HOME, Reg.PING]  # HOME never sent again
    assert joint.current_blocking_command is Reg.HOME
    assert joint.is_busy()


def test_lost_reply_of_check_orientation_that_started_waits_for_its_end(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(OSError(121, "Remote I/O error"), ack(BUSY), ack(BUSY), ack(READY))
    joint.check_orientation(2.0)
    sent = [data[0] for _, data, _ in scripted_bus.log]
    assert sent == [Reg.CHECKORIENTATION, Reg.PING, Reg.PING, Reg.PING]
    assert joint.current_blocking_command is Reg.NONE


def test_lost_reply_of_home_reads_the_flags_only_after_the_pickup_window(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(state=NOT_HOMED)
    times: list[float] = []
    transfer = scripted_bus.transfer

    def timed(address: int, data: bytes, read_len: int) -> bytes:
        times.append(joint.clock.now())
        return transfer(address, data, read_len)

    scripted_bus.transfer = timed
    scripted_bus.queue(flags(NOT_HOMED), OSError(121, "x"), ack(BUSY | NOT_HOMED))
    joint.start_homing(0.03, 30, 15)
    assert times[2] - times[1] >= BLOCKING_PICKUP_S - 1e-12


def test_lost_reply_of_a_blocking_command_that_did_not_start_is_sent_again(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(state=NOT_HOMED)
    # HOMEOFFSET (NaN) ok; HOME lost; PING: not busy, so it did not start; HOME again: taken.
    scripted_bus.queue(flags(NOT_HOMED), OSError(121, "x"), ack(NOT_HOMED), flags(BUSY | NOT_HOMED))
    joint.start_homing(0.03, 30, 15)
    assert [data[0] for _, data, _ in scripted_bus.log] == [Reg.HOMEOFFSET, Reg.HOME, Reg.PING, Reg.HOME]
    assert joint.current_blocking_command is Reg.HOME
    assert (joint.stats.transactions, joint.stats.retries, joint.stats.bus_errors) == (4, 1, 1)


def test_lost_reply_of_a_blocking_command_that_never_starts_raises_after_the_retries(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(state=NOT_HOMED, retries=1)
    lost, idle = OSError(121, "Remote I/O error"), ack(NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED), lost, idle, lost, idle)
    with pytest.raises(CommError, match=r"HOME: the reply was lost and the joint is not busy") as info:
        joint.start_homing(0.03, 30, 15)
    assert info.value.joint == "j1" and "sent 2 time(s)" in str(info.value)
    assert [data[0] for _, data, _ in scripted_bus.log].count(Reg.HOME) == 2
    assert joint.current_blocking_command is Reg.NONE


def test_lost_reply_of_a_blocking_command_is_not_resent_when_the_flags_are_lost_too(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(state=NOT_HOMED, retries=2)
    lost = OSError(121, "Remote I/O error")
    scripted_bus.queue(flags(NOT_HOMED), lost, lost, lost, lost)
    with pytest.raises(CommError, match=r"HOME failed"):
        joint.start_homing(0.03, 30, 15)
    assert [data[0] for _, data, _ in scripted_bus.log].count(Reg.HOME) == 1
    assert joint.current_blocking_command is Reg.NONE


def test_home_reply_without_busy_is_implausible_and_not_resent(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1(state=NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED), flags(NOT_HOMED), ack(BUSY | NOT_HOMED))
    joint.start_homing(0.03, 30, 15)
    assert joint.stats.implausible == 1
    assert [data[0] for _, data, _ in scripted_bus.log].count(Reg.HOME) == 1
    assert joint.current_blocking_command is Reg.HOME


def test_home_with_a_lost_reply_on_the_emulated_bus_homes_once() -> None:
    # 0 PING, 1 SETUP, 2 HOMEOFFSET, 3 HOME (reply cut short), 4 PING (BUSY: started)
    emu = build_emulated(J1, start_q=3.0, faults=FaultPlan(schedule={3: Fault.SHORT_READ}))
    j = emu.joint
    j.init()
    j.enable(J1.drive_current, J1.hold_current)
    j.home(J1.homing.speed, J1.homing.threshold, J1.homing.current, timeout_s=30.0)
    assert j.is_homed()
    assert j.get_position() == pytest.approx(J1.max, abs=0.01)
    assert j.stats.retries == 0
