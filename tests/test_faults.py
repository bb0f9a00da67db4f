"""Fault injection: the real :class:`Joint` driver over a faulty :class:`EmulatedI2CBus`.

Faults are scheduled at bus-wide transaction indices (deterministic) or drawn
at seeded rates. Whatever the bus does, the driver raises nothing but
:class:`JointError` subclasses, and a burst shorter than its retries is
invisible to the caller. The emulated firmware itself answers any bytes with
exactly the number of bytes read (property tests at the end).
"""

from __future__ import annotations

import errno
import math
import re
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rigs import J1, J2, EmulatedJoint, FlipsNextReply, build_emulated

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus, Fault, FaultPlan
from bioscara_gym.hardware.errors import CommError, ErrType, JointError, NotInitError
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import TICK_S, Flag, Reg

MakeJ1 = Callable[..., EmulatedJoint]


def nacks(*indices: int) -> FaultPlan:
    return FaultPlan(schedule=dict.fromkeys(indices, Fault.NACK))


# ------------------------------------------------------------- NACK bursts


def test_nack_burst_shorter_than_retries_is_recovered(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(0, 1), retries=2)
    emu.joint.init()
    assert emu.joint.initialized


def test_nack_burst_mid_session_is_recovered(make_emulated_j1: MakeJ1) -> None:
    # init = PING (index 0), enable = SETUP (1); the next call gets two NACKs.
    emu = make_emulated_j1(faults=nacks(2, 3), retries=2)
    emu.joint.init()
    emu.joint.enable(J1.drive_current, J1.hold_current)
    assert emu.joint.get_flags() == Flag.NOT_HOMED


def test_nack_burst_as_long_as_all_attempts_raises_comm_error(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(0, 1, 2), retries=2)
    with pytest.raises(CommError):
        emu.joint.init()


def test_nacked_command_is_not_delivered(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(1), retries=0)
    emu.joint.init()
    with pytest.raises(CommError):
        emu.joint.enable(J1.drive_current, J1.hold_current)
    assert emu.firmware.flags & Flag.NOT_ENABLED


def test_persistent_nack_names_joint_address_and_register(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(nack=1.0))
    with pytest.raises(CommError, match=r"j1 \(0x11\): PING failed after 3 attempts"):
        emu.joint.init()


def test_persistent_nack_on_a_command_names_the_register(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(1, 2, 3))
    emu.joint.init()
    with pytest.raises(CommError, match="SETUP"):
        emu.joint.enable(J1.drive_current, J1.hold_current)


def test_comm_error_has_the_comm_error_code(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(nack=1.0))
    with pytest.raises(CommError) as info:
        emu.joint.init()
    assert info.value.code == ErrType.COMM_ERROR


def test_comm_error_chains_the_bus_error(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(nack=1.0))
    with pytest.raises(CommError) as info:
        emu.joint.init()
    assert isinstance(info.value.__cause__, OSError)
    assert info.value.__cause__.errno == errno.EREMOTEIO


def test_failed_init_leaves_the_joint_uninitialized(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(nack=1.0))
    with pytest.raises(CommError):
        emu.joint.init()
    with pytest.raises(NotInitError):
        emu.joint.get_position()


def test_zero_retries_fail_on_the_first_nack(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(0), retries=0)
    with pytest.raises(CommError, match="after 1 attempt: "):
        emu.joint.init()


# ------------------------------------------------------- short and corrupt


def test_short_read_is_retried(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(schedule={0: Fault.SHORT_READ}))
    emu.joint.init()
    assert (emu.joint.stats.transactions, emu.joint.stats.errors) == (2, 1)


def test_short_read_command_is_delivered(make_emulated_j1: MakeJ1) -> None:
    # The bus cuts the reply after the firmware took the command.
    emu = make_emulated_j1(faults=FaultPlan(schedule={1: Fault.SHORT_READ}), retries=0)
    emu.joint.init()
    with pytest.raises(CommError):
        emu.joint.enable(J1.drive_current, J1.hold_current)
    assert not emu.firmware.flags & Flag.NOT_ENABLED


def test_every_reply_corrupted_raises_only_joint_errors(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(corrupt=1.0, seed=3))
    session(emu, seed=3, calls=200)


@pytest.mark.parametrize("read", ["get_position", "get_flags"])
def test_a_flipped_busy_bit_does_not_end_a_homing(read: str) -> None:
    # Seen (benchmarks/fault_matrix.py, corrupt=0.05): j3's reply flags
    # BUSY | NOT_HOMED came back as NOT_HOMED alone; the arm took the homing for
    # aborted and stopped the joint on its way. The firmware clears BUSY once,
    # at the end of HOME or on STOP (joint.ino), so the end is read again.
    emu = build_emulated(J1, 2.9)
    j = emu.joint
    j.init()
    j.enable(J1.drive_current, J1.hold_current)
    j.start_homing(J1.homing.speed, J1.homing.threshold, J1.homing.current)
    emu.advance(0.1)
    # the next reply's flags byte with BUSY (bit 1) flipped: ANGLEMOVED's 5th byte, PING's 2nd
    flipped = (33, Reg.ANGLEMOVED) if read == "get_position" else (9, Reg.PING)
    emu.bus.devices[J1.address] = FlipsNextReply(emu.firmware, *flipped)
    getattr(j, read)()
    assert j.is_busy() and not j.is_homed()
    assert j.stats.total_implausible == 1
    for _ in range(500):
        if not j.get_flags() & Flag.BUSY:
            break
        emu.advance(0.04)
    j.post_homing()  # homed: no NotHomedError
    assert j.is_homed()


@pytest.mark.parametrize("bit", [0, 3], ids=["STALL", "NOT_ENABLED"])
@pytest.mark.parametrize("command", ["home", "check_orientation"])
def test_a_flipped_flag_in_a_blocking_commands_reply_does_not_cancel_it(command: str, bit: int) -> None:
    # Seen (a hostile test): the PINGs confirming a flag that a flipped bit set in
    # HOME's reply went out at once, inside the pick-up window; the firmware
    # dropped the pending HOME, BUSY stayed set, and the driver waited 30 s.
    emu = build_emulated(J1, 2.9)
    j = emu.joint
    j.init()
    j.enable(J1.drive_current, J1.hold_current)
    if command == "home":
        emu.bus.devices[J1.address] = FlipsNextReply(emu.firmware, bit, Reg.HOME)
        j.home(J1.homing.speed, J1.homing.threshold, J1.homing.current, timeout_s=30.0)
        assert j.is_homed()
    else:  # not homed: a homed j1 rests against its end stop
        emu.bus.devices[J1.address] = FlipsNextReply(emu.firmware, bit, Reg.CHECKORIENTATION)
        start = emu.motor.position_deg
        j.check_orientation(2.0)
        assert emu.motor.position_deg == pytest.approx(start, abs=0.5)  # there and back
        assert emu.firmware.core.time > 0.2  # it ran: out and back at its speed
    assert j.stats.total_implausible == 1 and not j.is_busy()


def test_a_homing_the_driver_can_no_longer_watch_is_stopped() -> None:
    # Seen (a hostile test): three NACKs in a row while home() polled raised
    # CommError and left the homing running: the motor turned 600 degrees in
    # the next 10 s with nobody watching.
    emu = build_emulated(J1, 0.0)  # mid-range: the homing has some 3 rad to go
    j = emu.joint
    j.init()
    j.enable(J1.drive_current, J1.hold_current)
    transfer, count = emu.bus.transfer, [0]

    def nack_burst(address: int, data: bytes, read_len: int) -> bytes:
        count[0] += 1
        if 100 <= count[0] < 103:  # retries 2: three attempts lost
            raise OSError(errno.EREMOTEIO, "Remote I/O error")
        return transfer(address, data, read_len)

    emu.bus.transfer = nack_burst
    with pytest.raises(CommError):
        j.home(J1.homing.speed, J1.homing.threshold, J1.homing.current)
    emu.bus.transfer = transfer
    at = emu.motor.position_deg
    emu.advance(10.0)
    assert emu.motor.position_deg == pytest.approx(at, abs=1.0)  # motor degrees: it stays


def test_a_flipped_not_enabled_bit_in_setups_reply_does_not_fail_enable() -> None:
    # Seen (a hostile test, corrupt=0.05 over 120 fault seeds): 7 bring-ups ended
    # in "failed to enable; the joint still reports not enabled". SETUP clears it.
    emu = build_emulated(J1, 2.9)
    j = emu.joint
    j.init()
    emu.bus.devices[J1.address] = FlipsNextReply(emu.firmware, 3, Reg.SETUP)  # NOT_ENABLED is bit 3
    j.enable(J1.drive_current, J1.hold_current)
    assert j.is_enabled() and j.stats.total_implausible == 1
    assert emu.firmware.core.drive_current == J1.drive_current


def test_a_flipped_busy_bit_in_a_reading_is_not_believed_while_nothing_runs() -> None:
    # Seen (the same sweep): 3 bring-ups refused to enable or home a joint a
    # flipped bit had shown busy ("a homing ... is running and enabling would hang it").
    emu = build_emulated(J1, 2.9)
    j = emu.joint
    j.init()
    j.enable(J1.drive_current, J1.hold_current)
    emu.bus.devices[J1.address] = FlipsNextReply(emu.firmware, 33, Reg.ANGLEMOVED)  # BUSY in the flags byte
    j.get_position()
    assert not j.is_busy() and j.stats.total_implausible == 1


# ------------------------------------------------------------ absent joint


def test_absent_joint_fails_init_with_comm_error_naming_the_address(emulated_j1: EmulatedJoint) -> None:
    ghost = Joint("j3", 0x13, 24.0, -2.62672, 2.62672, emulated_j1.bus, clock=emulated_j1.clock)
    with pytest.raises(CommError, match="0x13"):
        ghost.init()


def test_absent_joint_does_not_disturb_the_present_one(emulated_j1: EmulatedJoint) -> None:
    ghost = Joint("j3", 0x13, 24.0, -2.62672, 2.62672, emulated_j1.bus, clock=emulated_j1.clock)
    with pytest.raises(CommError):
        ghost.init()
    emulated_j1.joint.init()
    assert emulated_j1.joint.initialized


def test_closed_bus_raises_comm_error(emulated_j1: EmulatedJoint) -> None:
    emulated_j1.joint.init()
    emulated_j1.bus.close()
    with pytest.raises(CommError):
        emulated_j1.joint.get_position()


def test_bus_rejects_reserved_device_address(firmware: JointFirmware) -> None:
    with pytest.raises(ValueError, match="0x78"):
        EmulatedI2CBus({0x78: firmware})


# ------------------------------------------------------------------ stats


def test_stats_count_attempts_and_errors(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(0, 2))
    emu.joint.init()
    emu.joint.get_flags()
    s = emu.joint.stats
    assert (s.transactions, s.errors, s.error_rate) == (4, 2, 0.5)


def test_stats_reset_keeps_totals(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=nacks(0))
    emu.joint.init()
    emu.joint.stats.reset()
    emu.joint.get_flags()
    s = emu.joint.stats
    assert (s.transactions, s.errors, s.total_transactions, s.total_errors) == (1, 0, 3, 1)


def test_stats_match_the_bus_count(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(nack=0.2, short_read=0.1, seed=5))
    session(emu, seed=5, calls=100)
    assert emu.joint.stats.total_transactions == emu.bus.transactions


# ---------------------------------------------------------------- latency


def test_latency_fault_advances_the_clock(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(latency_s=0.002))
    emu.joint.init()
    for _ in range(9):
        emu.joint.get_flags()
    assert emu.clock.now() == pytest.approx(10 * 0.002)


def test_scheduled_latency_fault_advances_the_clock_by_1ms(make_emulated_j1: MakeJ1) -> None:
    emu = make_emulated_j1(faults=FaultPlan(schedule={0: Fault.LATENCY}))
    emu.joint.init()
    assert emu.clock.now() == pytest.approx(0.001)


def _velocity_mode_with_latency(latency_s: float) -> EmulatedJoint:
    emu = build_emulated(J1, start_q=2.9, faults=FaultPlan(latency_s=latency_s))
    j = emu.joint
    j.init()
    j.enable(J1.drive_current, J1.hold_current)
    j.home(J1.homing.speed, J1.homing.threshold, J1.homing.current)
    j.set_velocity(-0.2)
    for _ in range(10):
        j.get_velocity()  # the host talks back to back; latency alone spaces the calls
    return emu


def test_latency_below_the_deadman_period_keeps_the_joint_enabled() -> None:
    emu = _velocity_mode_with_latency(0.02)
    assert not emu.firmware.flags & Flag.NOT_ENABLED


def test_latency_above_the_deadman_period_trips_it() -> None:
    emu = _velocity_mode_with_latency(0.06)
    assert emu.firmware.flags & Flag.NOT_ENABLED


# -------------------------------------------------------------- FaultPlan


def test_fault_plan_parse() -> None:
    assert FaultPlan.parse("nack=0.01,latency_ms=2") == FaultPlan(nack=0.01, latency_s=0.002)


def test_fault_plan_parse_all_keys_with_spaces() -> None:
    plan = FaultPlan.parse(" nack = 0.5 , short_read=0.25, corrupt=0.125 ,latency_ms=0 ")
    assert plan == FaultPlan(nack=0.5, short_read=0.25, corrupt=0.125)


def test_fault_plan_parse_empty_is_no_faults() -> None:
    assert FaultPlan.parse("") == FaultPlan()


def test_fault_plan_parse_passes_the_seed() -> None:
    assert FaultPlan.parse("nack=0.1", seed=42).seed == 42


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("nack", r"fault 'nack': expected KEY=VALUE"),
        ("nack=abc", r"fault 'nack': 'abc' is not a number"),
        ("nack=", r"fault 'nack': '' is not a number"),
        ("drop=0.1", r"unknown fault 'drop'; expected nack, short_read, corrupt, latency_ms"),
        ("nack=2", r"fault rate nack=2.0 must be within 0-1"),
        ("corrupt=-0.5", r"fault rate corrupt=-0.5 must be within 0-1"),
        ("latency_ms=-1", r"fault 'latency_ms': -1 must be >= 0"),
        ("latency_ms=nan", r"latency_ms.*must be finite"),
        ("latency_ms=inf", r"latency_ms.*must be finite"),
        ("nack=0.1,nack=0.2", r"given twice"),
        (",", r"^fault specification ',' has an empty item; expected KEY=VALUE,\.\.\.$"),
        ("nack=0.1,", r"^fault specification 'nack=0\.1,' has an empty item"),
        ("nack=0.1,,corrupt=0", r"^fault specification 'nack=0\.1,,corrupt=0' has an empty item"),
        ("seed=3,", r"^fault specification 'seed=3,' has an empty item"),
    ],
)
def test_fault_plan_parse_rejects_bad_specs(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FaultPlan.parse(spec)


@pytest.mark.parametrize("name", ["nack", "short_read", "corrupt"])
@pytest.mark.parametrize("rate", [-0.01, 1.01, math.nan])
def test_fault_plan_rejects_rates_outside_0_1(name: str, rate: float) -> None:
    with pytest.raises(ValueError, match=f"fault rate {name}="):
        FaultPlan(**{name: rate})


@pytest.mark.parametrize("name", ["nack", "short_read", "corrupt"])
@pytest.mark.parametrize("rate", [0.0, 1.0])
def test_fault_plan_accepts_rates_0_and_1(name: str, rate: float) -> None:
    assert getattr(FaultPlan(**{name: rate}), name) == rate


def test_fault_plan_rejects_negative_latency() -> None:
    with pytest.raises(ValueError, match="latency_s"):
        FaultPlan(latency_s=-0.001)


def test_a_fault_spec_may_name_its_own_seed() -> None:
    # Seen (a hostile test): --seed seeds the episodes, not the faults, so the
    # fault stream could not be varied; the spec names it (default 0).
    assert FaultPlan.parse("corrupt=0.05,seed=7").seed == 7
    assert FaultPlan.parse("seed=3, nack=0.1") == FaultPlan(nack=0.1, seed=3)
    assert FaultPlan.parse("corrupt=0.05").seed == 0


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("corrupt=0.05,seed=-1", "fault 'seed': '-1' must be a whole number >= 0"),
        ("seed=1.5", "fault 'seed': '1.5' must be a whole number >= 0"),
        ("seed=1,seed=2", "fault 'seed' given twice"),
    ],
)
def test_a_bad_fault_seed_is_one_line(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        FaultPlan.parse(spec)


def test_same_seed_gives_the_same_faults() -> None:
    plan = FaultPlan(nack=0.1, short_read=0.1, corrupt=0.1, seed=11)
    stats = []
    for _ in range(2):
        emu = build_emulated(J1, start_q=2.9, faults=plan)
        session(emu, seed=11, calls=100)
        stats.append(emu.joint.stats.as_dict())
    assert stats[0] == stats[1]


# ------------------------------------------------------ random driver calls


def session(emu: EmulatedJoint, seed: int, calls: int) -> dict[str, int]:
    """Make ``calls`` seeded-random driver calls, 10 ms apart; count the JointErrors by class.

    Anything but a :class:`JointError` propagates and fails the test.
    """
    rng = np.random.default_rng(seed)
    j, p = emu.joint, emu.params
    h = p.homing
    ops: list[Callable[[], object]] = [
        lambda: j.enable(p.drive_current, p.hold_current),
        lambda: j.enable_stallguard(p.stall_threshold),
        lambda: j.home(h.speed, h.threshold, h.current, timeout_s=30.0),
        lambda: j.start_homing(-h.speed, h.threshold, h.current),
        j.post_homing,
        j.get_position,
        j.get_velocity,
        j.get_flags,
        j.stop,
        lambda: j.set_velocity(float(rng.uniform(-1.0, 1.0)) * p.max_velocity),
        lambda: j.set_position(float(rng.uniform(p.min, p.max))),
        lambda: j.move_steps(int(rng.integers(-50, 50))),
        lambda: j.set_max_velocity(p.max_velocity),
        lambda: j.set_max_acceleration(p.max_acceleration),
        j.disable,
    ]
    weights = np.array([3, 1, 1, 1, 1, 6, 6, 6, 1, 4, 3, 1, 1, 1, 0.5])
    errors: dict[str, int] = {}
    for _ in range(calls):
        op = ops[int(rng.choice(len(ops), p=weights / weights.sum()))]
        try:
            if not j.initialized:
                j.init()
            op()
        except JointError as e:
            errors[type(e).__name__] = errors.get(type(e).__name__, 0) + 1
        emu.advance(TICK_S)
    return errors


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_faults_over_500_calls_raise_only_joint_errors(seed: int) -> None:
    plan = FaultPlan(nack=0.05, short_read=0.05, corrupt=0.05, seed=seed)
    emu = build_emulated(J1, start_q=2.9, faults=plan)
    errors = session(emu, seed=seed, calls=500)
    assert emu.joint.stats.total_errors > 0
    assert sum(errors.values()) > 0


def test_random_faults_on_the_lift_raise_only_joint_errors() -> None:
    plan = FaultPlan(nack=0.05, short_read=0.05, corrupt=0.05, seed=7)
    emu = build_emulated(J2, start_q=0.3, faults=plan)
    session(emu, seed=7, calls=500)
    assert emu.joint.stats.total_errors > 0


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    nack=st.floats(0.0, 1.0),
    short_read=st.floats(0.0, 1.0),
    corrupt=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_any_fault_plan_raises_only_joint_errors(
    nack: float, short_read: float, corrupt: float, seed: int
) -> None:
    plan = FaultPlan(nack=nack, short_read=short_read, corrupt=corrupt, seed=seed)
    emu = build_emulated(J1, start_q=2.9, faults=plan)
    session(emu, seed=seed, calls=60)


# ------------------------------------------------- firmware under any bytes

_registers = st.sampled_from([int(r) for r in Reg])
_frames = st.one_of(
    st.binary(max_size=8),
    st.tuples(_registers, st.binary(max_size=6)).map(lambda t: bytes((t[0],)) + t[1]),
)


def _firmware() -> JointFirmware:
    motor = KinematicStepper(0.0, lower_stop_deg=-1000.0, upper_stop_deg=1000.0)
    return JointFirmware(motor, ManualClock())


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=16), read_len=st.integers(0, 16))
def test_firmware_answers_any_bytes_with_exactly_read_len_bytes(data: bytes, read_len: int) -> None:
    assert len(_firmware().transfer(data, read_len)) == read_len


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(_frames, st.integers(0, 8), st.integers(0, 10)), max_size=30))
def test_firmware_survives_any_transaction_sequence(steps: list[tuple[bytes, int, int]]) -> None:
    fw = _firmware()
    for data, read_len, idle_ticks in steps:
        fw.clock.sleep(idle_ticks * TICK_S)
        reply = fw.transfer(data, read_len)
        assert len(reply) == read_len
        assert fw.core.flags & 0xF0 == 0


@pytest.mark.parametrize("seed", [1, 2, 6, 9])
def test_host_restart_with_a_corrupted_first_reply_still_restores_the_offset(seed: int) -> None:
    emu = build_emulated(J1, 2.9)
    emu.joint.init()
    emu.joint.enable(J1.drive_current, J1.hold_current)
    emu.joint.home(J1.homing.speed, J1.homing.threshold, J1.homing.current)
    expected = emu.joint.get_position()
    bus = EmulatedI2CBus(
        {J1.address: emu.firmware}, faults=FaultPlan(schedule={0: Fault.CORRUPT}, seed=seed), clock=emu.clock
    )
    joint = Joint(J1.name, J1.address, J1.reduction, J1.min, J1.max, bus, clock=emu.clock)
    joint.init()
    assert joint.get_position() == pytest.approx(expected, abs=1e-6)


# ------------------------------------------------------- one plan, two buses
def test_one_fault_plan_serves_both_emulated_buses_and_each_refuses_what_it_cannot_inject() -> None:
    from bioscara_gym.hardware.dynamixel.emulator import EmulatedRS485Bus
    from bioscara_gym.hardware.emulated_bus import RS485_FAULTS, Fault

    dxl = FaultPlan.parse("drop=0.1,delay_ms=2", kinds=RS485_FAULTS)
    assert (dxl.drop, dxl.latency_s) == (0.1, 0.002)
    EmulatedRS485Bus.with_ids([1], faults=dxl)  # taken
    with pytest.raises(ValueError, match=r"^the emulated RS-485 bus cannot inject nack; it injects drop"):
        EmulatedRS485Bus.with_ids([1], faults=FaultPlan(nack=0.1))
    with pytest.raises(ValueError, match=r"^the emulated I2C bus cannot inject drop; it injects nack"):
        EmulatedI2CBus({}, FaultPlan(drop=0.1))
    with pytest.raises(ValueError, match="cannot inject schedule drop"):
        EmulatedI2CBus({}, FaultPlan(schedule={0: Fault.DROP}))
    with pytest.raises(ValueError, match=r"schedule\[3\] = 'drop': expected one of Fault\.NACK"):
        FaultPlan(schedule={3: "drop"})  # type: ignore[dict-item]
