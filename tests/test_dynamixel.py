"""Dynamixel joints: protocol 2.0 bytes, the XL430 emulator, the driver over the official SDK, sync loops."""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.dynamixel import control_table as ct
from bioscara_gym.hardware.dynamixel import protocol
from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
from bioscara_gym.hardware.dynamixel.pty_server import parse_ids
from bioscara_gym.hardware.emulated_bus import RS485_FAULTS, Fault, FaultPlan
from bioscara_gym.hardware.errors import CommError, MissingExtraError, NotEnabledError, StalledError
from bioscara_gym.hardware.registers import Flag

sdk = pytest.importorskip("dynamixel_sdk")

from bioscara_gym.hardware.dynamixel.bus import DynamixelBus  # noqa: E402
from bioscara_gym.hardware.dynamixel.joint import DynamixelJoint  # noqa: E402
from bioscara_gym.hardware.dynamixel.port import EmulatedPortHandler, RS485PortHandler  # noqa: E402

EXAMPLE = Path(__file__).parents[1] / "bioscara_gym" / "hardware" / "dynamixel" / "dynamixel_arm.yaml"


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# ------------------------------------------------------------------ protocol


def test_ping_instruction_packet_is_the_emanuals() -> None:
    assert protocol.instruction_packet(1, ct.Instruction.PING) == h("FF FF FD 00 01 03 00 01 19 4E")


def test_status_packet_crc_matches_the_emanuals_ping_reply() -> None:
    # the e-Manual's PING reply of an XM430 (model 1030 = 0x0406, firmware 0x26)
    assert protocol.status_packet(1, 0, h("06 04 26")) == h("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")


def test_read_instruction_matches_the_emanual() -> None:
    # READ Present Position (132 = 0x84), 4 bytes, of ID 1
    assert protocol.instruction_packet(1, ct.Instruction.READ, h("84 00 04 00")) == h(
        "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"
    )


def test_crc_table_starts_as_the_protocols() -> None:
    assert protocol.CRC_TABLE[:8] == (0x0000, 0x8005, 0x800F, 0x000A, 0x801B, 0x001E, 0x0014, 0x8011)
    assert protocol.CRC_TABLE[255] == 0x0202


def test_byte_stuffing_inserts_fd_after_a_header_pattern() -> None:
    assert protocol.stuff(h("03 FF FF FD 01")) == h("03 FF FF FD FD 01")
    assert protocol.unstuff(h("03 FF FF FD FD 01")) == h("03 FF FF FD 01")


def test_stuffed_packet_parses_back() -> None:
    packet = protocol.instruction_packet(1, ct.Instruction.WRITE, h("74 00 FF FF FD 00"))
    assert h("FF FF FD FD") in packet
    (parsed,) = protocol.parse(b"\x00\x13" + packet)
    assert parsed.crc_ok and parsed.id == 1 and parsed.params == h("74 00 FF FF FD 00")


def test_parser_waits_for_a_split_packet() -> None:
    parser = protocol.PacketParser()
    packet = protocol.instruction_packet(2, ct.Instruction.PING)
    assert parser.feed(packet[:5]) == []
    (parsed,) = parser.feed(packet[5:])
    assert parsed.id == 2 and parsed.instruction == ct.Instruction.PING


# -------------------------------------------------------------- conversions


def test_mh5_conversions() -> None:
    assert ct.position_from_raw(2047) == 0.0
    assert ct.position_from_raw(3047, 0.5) == pytest.approx(1000 * 0.001533980787886 + 0.5)
    assert ct.velocity_from_raw(-10) == pytest.approx(-10 * 0.023980823922402)
    assert ct.effort_from_raw(500) == pytest.approx(500 * 0.0014)
    assert ct.voltage_from_raw(121) == pytest.approx(1.21)
    assert ct.temperature_from_raw(42) == 42.0
    assert ct.position_to_raw(1000 * 0.001533980787886 + 0.5, 0.5) == 3047


def test_control_table_addresses_are_the_emanuals() -> None:
    expected = {
        "Model Number": (0, 2),
        "ID": (7, 1),
        "Baud Rate": (8, 1),
        "Operating Mode": (11, 1),
        "Homing Offset": (20, 4),
        "Velocity Limit": (44, 4),
        "Max Position Limit": (48, 4),
        "Min Position Limit": (52, 4),
        "Torque Enable": (64, 1),
        "LED": (65, 1),
        "Hardware Error Status": (70, 1),
        "Goal Velocity": (104, 4),
        "Goal Position": (116, 4),
        "Present Load": (126, 2),
        "Present Velocity": (128, 4),
        "Present Position": (132, 4),
        "Present Input Voltage": (144, 2),
        "Present Temperature": (146, 1),
    }
    assert {n: (ct.field(n).address, ct.field(n).size) for n in expected} == expected
    assert ct.field("Torque Enable").eeprom is False and ct.field("Operating Mode").eeprom is True


def test_default_loop_rates_are_the_mh5s() -> None:
    assert ct.DEFAULT_LOOP_RATES == {
        "pvl_reader": 100.0,
        "tv_reader": 1.0,
        "pv_writer": 100.0,
        "t_writer": 2.0,
    }


# ----------------------------------------------------------------- emulator


@pytest.fixture
def bus() -> EmulatedRS485Bus:
    return EmulatedRS485Bus.with_ids([1, 2])


def status(raw: bytes) -> list[protocol.Packet]:
    packets = protocol.parse(raw)
    assert all(p.crc_ok and p.instruction == ct.Instruction.STATUS for p in packets)
    return packets


def test_emulator_answers_ping_with_model_1060(bus: EmulatedRS485Bus) -> None:
    (reply,) = status(bus.transact(h("FF FF FD 00 01 03 00 01 19 4E")))
    assert reply.id == 1 and reply.error == 0 and reply.data == h("24 04 2E")


def test_emulator_broadcast_ping_answers_in_id_order(bus: EmulatedRS485Bus) -> None:
    replies = status(bus.transact(protocol.instruction_packet(0xFE, ct.Instruction.PING)))
    assert [r.id for r in replies] == [1, 2]


def test_emulator_absent_id_is_silent(bus: EmulatedRS485Bus) -> None:
    assert bus.transact(protocol.instruction_packet(9, ct.Instruction.PING)) == b""


def test_emulator_read_present_position(bus: EmulatedRS485Bus) -> None:
    (reply,) = status(bus.transact(h("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")))
    assert reply.data == (2047).to_bytes(4, "little")


def test_emulator_bad_crc_gets_a_crc_error_status(bus: EmulatedRS485Bus) -> None:
    (reply,) = status(bus.transact(h("FF FF FD 00 01 03 00 01 19 4F")))
    assert reply.error == ct.StatusError.CRC


def test_emulator_unknown_instruction_is_an_instruction_error(bus: EmulatedRS485Bus) -> None:
    (reply,) = status(bus.transact(protocol.instruction_packet(1, 0x10)))
    assert reply.error == ct.StatusError.INSTRUCTION


def test_emulator_eeprom_is_locked_while_torque_is_on(bus: EmulatedRS485Bus) -> None:
    write = ct.Instruction.WRITE
    assert status(bus.transact(protocol.instruction_packet(1, write, h("40 00 01"))))[0].error == 0
    (reply,) = status(bus.transact(protocol.instruction_packet(1, write, h("0B 00 01"))))
    assert reply.error == ct.StatusError.ACCESS
    assert bus.servos[1].get("Operating Mode") == 3


def test_emulator_read_only_item_is_an_access_error(bus: EmulatedRS485Bus) -> None:
    (reply,) = status(
        bus.transact(protocol.instruction_packet(1, ct.Instruction.WRITE, h("84 00 00 00 00 00")))
    )
    assert reply.error == ct.StatusError.ACCESS


def test_emulator_sync_write_then_sync_read(bus: EmulatedRS485Bus) -> None:
    # SYNC WRITE LED (65) := 1 on ID 1, 0 on ID 2; then SYNC READ 64-65 of both
    assert (
        bus.transact(
            protocol.instruction_packet(0xFE, ct.Instruction.SYNC_WRITE, h("41 00 01 00 01 01 02 00"))
        )
        == b""
    )
    replies = status(
        bus.transact(protocol.instruction_packet(0xFE, ct.Instruction.SYNC_READ, h("40 00 02 00 01 02")))
    )
    assert [(r.id, r.data) for r in replies] == [(1, h("00 01")), (2, h("00 00"))]


def test_emulator_bulk_write_then_bulk_read(bus: EmulatedRS485Bus) -> None:
    params = h("01 41 00 01 00 01") + h("02 68 00 04 00 0A 00 00 00")  # LED of 1; Goal Velocity of 2
    assert bus.transact(protocol.instruction_packet(0xFE, ct.Instruction.BULK_WRITE, params)) == b""
    replies = status(
        bus.transact(
            protocol.instruction_packet(0xFE, ct.Instruction.BULK_READ, h("01 41 00 01 00 02 68 00 04 00"))
        )
    )
    assert [(r.id, r.data) for r in replies] == [(1, h("01")), (2, h("0A 00 00 00"))]


def test_emulator_overload_sets_hardware_error_turns_torque_off_and_alerts() -> None:
    clock = ManualClock()
    servo = XL430(1, clock)
    bus = EmulatedRS485Bus([servo])
    bus.transact(protocol.instruction_packet(1, ct.Instruction.WRITE, h("40 00 01")))  # torque on
    bus.transact(protocol.instruction_packet(1, ct.Instruction.WRITE, h("74 00 00 0C 00 00")))  # goal 3072
    servo.blocked = True
    clock.sleep(ct.OVERLOAD_TRIP_S + 0.05)
    (reply,) = status(bus.transact(protocol.instruction_packet(1, ct.Instruction.READ, h("40 00 07 00"))))
    assert reply.error == ct.ALERT
    assert reply.data[0] == 0  # Torque Enable
    assert reply.data[6] == ct.HardwareError.OVERLOAD
    # torque cannot come back before a REBOOT
    bus.transact(protocol.instruction_packet(1, ct.Instruction.WRITE, h("40 00 01")))
    assert not servo.torque
    (reply,) = status(bus.transact(protocol.instruction_packet(1, ct.Instruction.REBOOT)))
    assert reply.error == ct.ALERT  # the status is sent before the reboot
    assert bus.transact(protocol.instruction_packet(1, ct.Instruction.PING)) == b""  # rebooting
    clock.sleep(ct.REBOOT_S)
    (reply,) = status(bus.transact(protocol.instruction_packet(1, ct.Instruction.PING)))
    assert reply.error == 0 and servo.hardware_error == 0


def test_emulator_position_mode_reaches_the_goal_at_the_profile_velocity() -> None:
    clock = ManualClock()
    servo = XL430(1, clock)
    servo.set("Profile Velocity", 100)  # 2.398 rad/s
    servo.write(64, b"\x01")
    servo.write(116, (3047).to_bytes(4, "little"))  # +1.534 rad
    clock.sleep(0.2)
    servo.update()
    assert servo.velocity_rads == pytest.approx(100 * ct.VELOCITY_RADS_PER_UNIT, rel=1e-6)
    clock.sleep(1.0)
    servo.update()
    assert servo.get("Present Position") == 3047 and servo.velocity_rads == 0.0


def test_fault_schedule_drops_and_corrupts_status_packets() -> None:
    bus = EmulatedRS485Bus.with_ids([1], faults=FaultPlan(schedule={0: Fault.DROP, 1: Fault.CORRUPT}))
    ping = protocol.instruction_packet(1, ct.Instruction.PING)
    assert bus.transact(ping) == b""
    (bad,) = protocol.parse(bus.transact(ping))
    assert not bad.crc_ok
    assert status(bus.transact(ping))[0].data[:2] == h("24 04")


def test_fault_plan_parse() -> None:
    plan = FaultPlan.parse("drop=0.1, corrupt=0.01, delay_ms=2", kinds=RS485_FAULTS)
    assert (plan.drop, plan.corrupt, plan.latency_s) == (0.1, 0.01, 0.002)
    with pytest.raises(ValueError, match="unknown fault"):
        FaultPlan.parse("nack=1", kinds=RS485_FAULTS)


def test_parse_ids() -> None:
    assert parse_ids("1-4") == [1, 2, 3, 4]
    assert parse_ids("1,3-4,3") == [1, 3, 4]
    with pytest.raises(ValueError, match="0-252"):
        parse_ids("250-253")


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("0-300", r"IDs must be 0-252, got 300 \(in '0-300'\)"),  # said "got 253": the first one past
        ("1-1000000000", r"got 1000000000 \(in '1-1000000000'\)"),  # was expanded first: 22.7 GB, killed
        ("7,400", r"got 400 \(in '400'\)"),
    ],
)
def test_parse_ids_checks_a_range_before_expanding_it(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_ids(spec)


def test_cli_emulate_refuses_a_huge_id_range_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from bioscara_gym.cli import main

    assert main(["emulate", "dynamixel", "--ids", "1-1000000000", "--link", "/nonexistent/dxl"]) == 2
    err = capsys.readouterr().err
    expected = "--ids '1-1000000000': IDs must be 0-252, got 1000000000 (in '1-1000000000')"
    assert err == f"bioscara emulate: error: {expected}\n"


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("", "--faults names no fault; give KEY=VALUE,... e.g. drop=0.01"),
        ("drop=0.1,", "fault specification 'drop=0.1,' has an empty item; expected KEY=VALUE,..."),
    ],
)
def test_cli_emulate_refuses_faults_that_name_none(
    capsys: pytest.CaptureFixture[str], spec: str, expected: str
) -> None:
    # Seen (a hostile test): served the servos without faults.
    from bioscara_gym.cli import main

    assert main(["emulate", "dynamixel", "--ids", "1", "--link", "/nonexistent/dxl", "--faults", spec]) == 2
    assert capsys.readouterr().err == f"bioscara emulate: error: {expected}\n"


@pytest.mark.parametrize(
    ("link", "expected"),
    [
        ("", "--link is empty; give the path of the symlink to make, e.g. /tmp/dxl"),
        ("/nonexistent/dxl", "--link /nonexistent/dxl: the folder /nonexistent does not exist"),
        ("/etc/hostname/dxl", "--link /etc/hostname/dxl: /etc/hostname is not a folder"),
        ("/proc/dxl", "--link /proc/dxl: cannot make the symlink there (No such file or directory)"),
    ],
)
def test_cli_emulate_refuses_a_link_it_cannot_make_naming_it(
    capsys: pytest.CaptureFixture[str], link: str, expected: str
) -> None:
    # Seen (a hostile test): "No such file or directory: /dev/pts/0" (the pty, not the link);
    # '' as "--link .: exists and is not a symlink".
    from bioscara_gym.cli import main

    if link.startswith(("/etc/hostname", "/proc")) and not Path(link).parent.exists():
        pytest.skip(f"no {Path(link).parent}")
    assert main(["emulate", "dynamixel", "--ids", "1", "--link", link]) == 2
    assert capsys.readouterr().err == f"bioscara emulate: error: {expected}\n"


def test_cli_emulate_keeps_a_symlink_that_is_not_to_a_pty(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen (a hostile test): an unrelated symlink replaced, then deleted on exit.
    from bioscara_gym.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "target.json").write_text("{}")
    Path("mylink").symlink_to("target.json")
    assert main(["emulate", "dynamixel", "--ids", "1", "--link", "mylink"]) == 2
    assert capsys.readouterr().err == (
        "bioscara emulate: error: --link mylink: a symlink to target.json, not to a pseudo-terminal "
        "(/dev/pts/*); not replacing it\n"
    )
    assert os.readlink("mylink") == "target.json"


# ---------------------------------------------------- driver over the SDK


def make_joint(
    ids: tuple[int, ...] = (1,), faults: FaultPlan | None = None, retries: int = 2, **kwargs: float
) -> tuple[DynamixelJoint, DynamixelBus, EmulatedRS485Bus, ManualClock]:
    clock = ManualClock()
    emulated = EmulatedRS485Bus.with_ids(ids, clock=clock, faults=faults)
    bus = DynamixelBus(EmulatedPortHandler(emulated), clock=clock, retries=retries)
    joint = DynamixelJoint("j1", ids[0], bus, clock=clock, **kwargs)
    return joint, bus, emulated, clock


def test_joint_init_enable_disable_is_torque() -> None:
    joint, _, emulated, _ = make_joint()
    joint.init()
    assert joint.flags == Flag.NOT_ENABLED and joint.is_homed()
    joint.enable(20, 20)
    assert emulated.servos[1].torque and joint.flags == Flag(0)
    joint.disable()
    assert not emulated.servos[1].torque and not joint.is_enabled()


def test_joint_position_uses_the_mh5_formula_with_offset() -> None:
    joint, _, emulated, clock = make_joint(offset=0.25)
    joint.init()
    assert joint.get_position() == pytest.approx(0.25)
    joint.enable(20, 20)
    joint.set_max_velocity(2.0)
    joint.set_position(0.25 + 500 * 0.001533980787886)
    assert emulated.servos[1].get("Goal Position") == 2547
    clock.sleep(1.0)
    assert joint.get_position() == pytest.approx(0.25 + 500 * 0.001533980787886)


def test_joint_velocity_mode_switches_operating_mode() -> None:
    joint, _, emulated, clock = make_joint()
    joint.init()
    joint.enable(20, 20)
    joint.set_velocity(-20 * 0.023980823922402)
    servo = emulated.servos[1]
    assert servo.get("Operating Mode") == ct.OperatingMode.VELOCITY and servo.torque
    assert servo.get("Goal Velocity") == -20
    clock.sleep(0.5)
    assert joint.get_velocity() == pytest.approx(-20 * 0.023980823922402)


def test_joint_set_position_refused_with_torque_off() -> None:
    joint, *_ = make_joint()
    joint.init()
    with pytest.raises(NotEnabledError):
        joint.set_position(0.1)


def test_joint_overload_is_stall_and_reboot_clears_it() -> None:
    joint, _, emulated, clock = make_joint()
    joint.init()
    joint.enable(20, 20)
    joint.set_velocity(0.5)
    emulated.servos[1].blocked = True
    clock.sleep(ct.OVERLOAD_TRIP_S + 0.05)
    assert joint.get_flags() == Flag.STALL | Flag.NOT_ENABLED
    with pytest.raises(StalledError, match="reboot"):
        joint.set_velocity(0.5)
    with pytest.raises(NotEnabledError, match="reboot"):
        joint.enable(20, 20)
    emulated.servos[1].blocked = False
    joint.reboot()
    assert joint.flags == Flag.NOT_ENABLED
    joint.enable(20, 20)
    assert joint.flags == Flag(0)


def test_joint_ping_retries_through_dropped_status_packets() -> None:
    joint, _, _, _ = make_joint(faults=FaultPlan(schedule={0: Fault.DROP, 1: Fault.CORRUPT}))
    joint.init()  # 5 PING tries, as the MH5
    assert joint.stats.total_errors == 2 and joint.model_number == 1060


def test_joint_absent_servo_is_a_comm_error_naming_it() -> None:
    joint, bus, _, _ = make_joint()
    other = DynamixelJoint("j9", 9, bus)
    with pytest.raises(CommError, match=r"j9: PING failed after 5 attempts.*no status packet"):
        other.init()
    assert joint.stats.total_transactions == 0


def test_missing_sdk_is_one_missing_extra_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "dynamixel_sdk", None)
    from bioscara_gym.hardware.dynamixel.bus import load_sdk

    with pytest.raises(MissingExtraError, match=r"\[dynamixel\] extra"):
        load_sdk()


def test_hardware_imports_without_the_sdk() -> None:
    code = (
        "import sys; sys.modules['dynamixel_sdk'] = None\n"
        "import bioscara_gym.hardware, bioscara_gym.hardware.dynamixel\n"
        "from bioscara_gym.hardware.backends import make_backend\n"
        "from bioscara_gym.hardware.errors import MissingExtraError\n"
        "try:\n    make_backend('dynamixel-emulated')\nexcept MissingExtraError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "pip install 'bioscara-gym[dynamixel]'" in out.stdout


# ----------------------------------------------------------------- loops


def test_loop_called_too_soon_is_skipped_and_counted() -> None:
    joint, bus, _, clock = make_joint()
    joint.init()
    bus.start_loops()
    for _ in range(10):  # every 2 ms for 20 ms: pvl_reader (100 Hz) runs twice, tv_reader (1 Hz) once
        bus.read_loops()
        clock.sleep(0.002)
    stats = bus.loop_stats()
    assert stats["pvl_reader"].transactions == 2 and stats["pvl_reader"].skipped == 8
    assert stats["tv_reader"].transactions == 1
    # 120 is 12.0 V in the e-Manual's 0.1 V unit; the MH5's raw / 100 reads it as 1.2 (docs/dynamixel.md)
    assert joint.voltage_raw == 120 and joint.get_voltage() == pytest.approx(1.2)
    assert joint.get_temperature() == 30.0


def test_loop_stats_achieved_rate_and_reset() -> None:
    joint, bus, _, clock = make_joint()
    joint.init()
    bus.start_loops()
    for _ in range(100):
        bus.read_loops()
        clock.sleep(0.005)  # called at 200 Hz: runs at 100 Hz
    pvl = bus.loop_stats()["pvl_reader"]
    assert pvl.achieved_hz == pytest.approx(100.0, rel=1e-6)
    pvl.reset()
    assert pvl.transactions == 0 and pvl.total_transactions == 50
    pvl.reset_all()
    assert pvl.total_transactions == 0


def test_loop_timeouts_count_when_a_servo_does_not_answer() -> None:
    joint, bus, emulated, clock = make_joint(ids=(1, 2))
    other = DynamixelJoint("j2", 2, bus, clock=clock)
    joint.init()
    other.init()
    bus.start_loops()
    emulated.servos[2].powered = False
    bus.read_loops()
    pvl = bus.loop_stats()["pvl_reader"]
    assert (pvl.transactions, pvl.errors, pvl.timeouts) == (1, 1, 1)
    assert joint._fresh()  # ID 1 answered before ID 2 was missed


def test_synced_joint_commands_go_through_the_pv_writer() -> None:
    joint, bus, emulated, clock = make_joint()
    joint.init()
    joint.enable(20, 20)
    bus.start_loops()
    emulated.keep_log = True
    joint.set_position(0.5)
    assert emulated.log == []  # queued, not sent
    bus.write_loops()
    (packet,) = emulated.log
    assert packet.instruction == ct.Instruction.SYNC_WRITE and packet.params[:4] == h("68 00 10 00")
    clock.sleep(2.0)
    bus.read_loops()
    assert joint.get_position() == pytest.approx(ct.position_from_raw(ct.position_to_raw(0.5)))


def test_t_writer_switches_torque_asynchronously() -> None:
    joint, bus, emulated, _ = make_joint()
    joint.init()
    bus.start_loops()
    joint.request_torque(True)
    assert not emulated.servos[1].torque
    bus.write_loops()
    assert emulated.servos[1].torque and joint.is_enabled()
    assert bus.loop_stats()["t_writer"].transactions == 1


# ------------------------------------------------------- config, backend, console


def test_example_config_describes_a_dynamixel_arm() -> None:
    cfg = load_config(EXAMPLE)
    assert [j.type for j in cfg.joints] == ["dynamixel"] * 4
    assert [j.dynamixel.id for j in cfg.joints] == [1, 2, 3, 4]  # type: ignore[union-attr]
    assert cfg.joints[0].address is None
    assert cfg.groups["arm"] == ("j1", "j2", "j3", "j4")  # nested groups, as in the MH5
    assert cfg.dynamixel is not None and cfg.dynamixel.rates["tv_reader"] == 1.0


def test_arm_drives_dynamixel_joints_with_loop_stats() -> None:
    from bioscara_gym.hardware.arm import Arm
    from bioscara_gym.hardware.backends import make_backend

    backend = make_backend("dynamixel-emulated", EXAMPLE)
    arm = Arm(backend)
    arm.configure()
    arm.activate()
    arm.claim("j3", "position")
    arm.set_command("j3", 1.0)
    for _ in range(150):
        arm.cycle(0.01)
    assert arm.joint_states["j3"].position == pytest.approx(1.0, abs=1e-3)
    loops = backend.loop_stats()
    assert loops["pvl_reader"].total_transactions == 150 and loops["pvl_reader"].achieved_hz == pytest.approx(
        100
    )
    assert loops["pv_writer"].total_transactions >= 1
    assert set(backend.comm_stats()) >= {"j1", "pvl_reader"}
    arm.shutdown()


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "bioscara_gym", *args], capture_output=True, text=True, timeout=60
    )


def test_console_status_shows_loops_and_reboot_works() -> None:
    from bioscara_gym.cli import main

    assert main(["status", "--backend", "dynamixel-emulated", "--config", str(EXAMPLE)]) == 0
    assert main(["reboot", "arm", "--backend", "dynamixel-emulated", "--config", str(EXAMPLE)]) == 0
    assert main(["enable", "shoulder", "--backend", "dynamixel-emulated", "--config", str(EXAMPLE)]) == 0


def test_console_status_prints_loop_table(capsys: pytest.CaptureFixture[str]) -> None:
    from bioscara_gym.cli import main

    main(["status", "--backend", "dynamixel-emulated"])
    out = capsys.readouterr().out
    assert "pvl_reader" in out and "t_writer" in out and "achieved Hz" in out


# ------------------------------------------------------------------ pty


def test_sdk_talks_to_the_pty_emulator(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from bioscara_gym.hardware.dynamixel.pty_server import PtyServer, make_bus

    link = tmp_path / "dxl"
    with PtyServer(make_bus([1, 2, 3]), link):
        port = RS485PortHandler(str(link))
        assert port.openPort() and port.setBaudRate(1_000_000)
        with caplog.at_level(logging.WARNING):
            assert port.set_rs485() is False  # a pty has no RS-485 mode: logged, not fatal
        assert "RS-485 mode not available" in caplog.text
        ph = sdk.PacketHandler(2.0)
        assert ph.ping(port, 2) == (1060, 0, 0)
        group = sdk.GroupSyncRead(port, ph, 132, 4)
        for i in (1, 2, 3):
            group.addParam(i)
        assert group.txRxPacket() == 0
        assert [group.getData(i, 132, 4) for i in (1, 2, 3)] == [2047] * 3
        port.closePort()
    assert not os.path.lexists(link)


def test_driver_over_the_pty(tmp_path: Path) -> None:
    from bioscara_gym.hardware.dynamixel.pty_server import PtyServer, make_bus

    link = tmp_path / "dxl"
    with PtyServer(make_bus([4]), link):
        bus = DynamixelBus(RS485PortHandler(str(link)), rs485=True)
        joint = DynamixelJoint("j4", 4, bus)
        joint.init()
        joint.enable(20, 20)
        joint.set_max_velocity(3.0)
        joint.set_position(0.3)
        deadline = time.monotonic() + 2.0
        while abs(joint.get_position() - 0.3) > 2e-3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert joint.get_position() == pytest.approx(0.3, abs=2e-3)
        joint.disable()
        bus.close()


def test_cli_emulate_serves_until_sigterm_and_removes_the_link(tmp_path: Path) -> None:
    link = tmp_path / "dxl"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bioscara_gym", "emulate", "dynamixel", "--ids", "1-2", "--link", str(link)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert "XL430 servos 1, 2" in proc.stdout.readline()
        port = RS485PortHandler(str(link))
        assert port.openPort()
        # The SDK gives a reply about 34 ms (two 16 ms latency timers); on a loaded
        # machine the emulator's process may not be scheduled that soon, and one
        # such ping failed a full run once. A server that answers at all answers
        # one of several pings within the deadline.
        deadline = time.monotonic() + 20.0
        results = []
        while time.monotonic() < deadline:
            results.append(sdk.PacketHandler(2.0).ping(port, 2)[1])
            if results[-1] == 0:
                break
            time.sleep(0.1)
        assert results[-1] == 0, f"no ping answered in 20 s: {results}"
        port.closePort()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not os.path.lexists(link)


# The emulator's main thread, once serving, with SIGTERM landing at the worst
# moment a lock-based wait has: right after the wait re-took its lock. A
# handler that sets a threading.Event there waits for that lock forever (seen
# in a loaded CI run: SIGTERM ignored for 30 s). A timer sends SIGTERM too,
# for a loop that takes no lock at all.
SIGTERM_INSIDE_A_WAIT = """
import builtins, os, signal, sys, threading
armed, sent = [], []
def send():
    if not sent:
        sent.append(True)
        signal.raise_signal(signal.SIGTERM)
def send_from_elsewhere():
    if not sent:
        sent.append(True)
        os.kill(os.getpid(), signal.SIGTERM)
def trap(frame, event, arg):
    if event == "call":
        return trap if frame.f_code.co_name == "_acquire_restore" else None
    if event == "return" and armed and threading.current_thread() is threading.main_thread():
        send()  # handled here: this thread holds the lock it re-took
    return None
printed = builtins.print
def arm(*args, **kwargs):
    printed(*args, **kwargs)
    if not armed:
        timer = threading.Timer(1.0, send_from_elsewhere)
        timer.daemon = True
        timer.start()  # (its own start waits on a lock: armed only after it)
        armed.append(True)
builtins.print = arm
sys.settrace(trap)
from bioscara_gym.cli import main
sys.exit(main(["emulate", "dynamixel", "--ids", "1", "--link", sys.argv[1]]))
"""


def test_sigterm_stops_the_emulator_whatever_its_main_thread_holds(tmp_path: Path) -> None:
    link = tmp_path / "dxl"
    proc = subprocess.run(
        [sys.executable, "-c", SIGTERM_INSIDE_A_WAIT, str(link)], capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == "stopped; link removed"
    assert not os.path.lexists(link)


def test_math_of_the_example_limits() -> None:
    assert ct.position_to_raw(3.067961575772) == 2047 + 2000
    assert math.isclose(0.2 * 2.3980823922402, 20 * ct.VELOCITY_RADS_PER_UNIT)
