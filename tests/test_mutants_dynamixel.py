"""Tests that kill mutmut's survivors in hardware/dynamixel/ (docs/mutation.md, issue #24 item 11).

Expected bytes are literals from the DYNAMIXEL Protocol 2.0 e-Manual page
(header ``FF FF FD 00``, LEN = INST + parameters + CRC, byte stuffing
``FF FF FD`` -> ``FF FF FD FD`` inside INST..PARAMS, instruction codes) with
CRCs computed by the official ``dynamixel_sdk`` (``updateCRC``), or the SDK
itself at run time; control-table values are the XL430-W250 e-Manual's.
"""

from __future__ import annotations

import math
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from bioscara_gym.hardware.clock import ManualClock, WallClock
from bioscara_gym.hardware.dynamixel import control_table as ct
from bioscara_gym.hardware.dynamixel import protocol
from bioscara_gym.hardware.dynamixel.emulator import EmulatedRS485Bus
from bioscara_gym.hardware.emulated_bus import Fault, FaultPlan
from bioscara_gym.hardware.errors import (
    CommError,
    InvalidArgumentError,
    JointError,
    MissingExtraError,
    NotEnabledError,
    StalledError,
)
from bioscara_gym.hardware.registers import Flag, Reg

sdk = pytest.importorskip("dynamixel_sdk")

from bioscara_gym.hardware.dynamixel.bus import DynamixelBus, LoopStats, SyncLoop, load_sdk  # noqa: E402
from bioscara_gym.hardware.dynamixel.joint import DynamixelJoint  # noqa: E402
from bioscara_gym.hardware.dynamixel.port import EmulatedPortHandler  # noqa: E402


def h(text: str) -> bytes:
    return bytes.fromhex(text)


@contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Fail (TimeoutError) instead of hanging when the body runs longer than ``seconds``."""

    def expire(signum: int, frame: object) -> None:
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


# ================================================================== protocol.py
# ------------------------------------------------------------------ CRC


def test_crc_table_is_the_sdks_for_every_byte() -> None:
    # CRC_TABLE is built at import, before mutmut switches a mutant on; build it again.
    table = protocol._crc_table()
    handler = sdk.PacketHandler(2.0)
    # the CRC of one byte from 0 is that byte's table entry (the SDK's crc_table)
    assert table == tuple(handler.updateCRC(0, [i], 1) for i in range(256))
    assert (table[0], table[1], table[8], table[64], table[128], table[200], table[255]) == (
        0x0000,
        0x8005,
        0x8033,
        0x8183,
        0x8303,
        0x82B3,
        0x0202,
    )


# ------------------------------------------------------------------ stuffing (transmit)


def test_stuffing_leaves_a_lone_fd_alone() -> None:
    assert protocol.stuff(h("03 74 00 FD 01")) == h("03 74 00 FD 01")
    # the SDK sends this WRITE unstuffed too
    assert protocol.instruction_packet(1, ct.Instruction.WRITE, h("74 00 FD 01")) == h(
        "FF FF FD 00 01 07 00 03 74 00 FD 01 44 43"
    )


def test_stuffing_needs_both_ff_before_the_fd() -> None:
    assert protocol.stuff(h("03 74 00 FF 00 FD 01")) == h("03 74 00 FF 00 FD 01")
    assert protocol.instruction_packet(1, ct.Instruction.WRITE, h("74 00 FF 00 FD 01")) == h(
        "FF FF FD 00 01 09 00 03 74 00 FF 00 FD 01 C0 8B"
    )


def test_stuffing_a_body_that_starts_with_ff_ff_fd() -> None:
    # the pattern anywhere in INST..PARAMS, its first three bytes included
    assert protocol.stuff(h("FF FF FD 01")) == h("FF FF FD FD 01")
    assert protocol.unstuff(h("FF FF FD FD 01")) == h("FF FF FD 01")


def test_stuffed_status_packet_counts_the_stuffing_in_len_and_crc() -> None:
    # as the SDK's addStuffing + updateCRC: LEN 8 -> 9, CRC over the stuffed bytes
    stuffed = h("FF FF FD 00 01 09 00 55 00 FF FF FD FD 00 D8 9C")
    assert protocol.status_packet(1, 0, h("FF FF FD 00")) == stuffed


# ------------------------------------------------------------------ stuffing (receive)


def test_received_status_with_stuffed_ff_ff_fd_is_unstuffed() -> None:
    (packet,) = protocol.parse(h("FF FF FD 00 01 09 00 55 00 FF FF FD FD 00 D8 9C"))
    assert packet.crc_ok and packet.error == 0 and packet.data == h("FF FF FD 00")


def test_received_status_with_a_lone_fd_keeps_the_byte_after_it() -> None:
    # Present Position 253 = FD 00 00 00: nothing was stuffed
    (packet,) = protocol.parse(h("FF FF FD 00 01 08 00 55 00 FD 00 00 00 94 1C"))
    assert packet.crc_ok and packet.data == h("FD 00 00 00")


def test_received_status_with_ff_00_fd_keeps_the_byte_after_it() -> None:
    (packet,) = protocol.parse(h("FF FF FD 00 01 08 00 55 00 FF 00 FD 01 9E 3A"))
    assert packet.crc_ok and packet.data == h("FF 00 FD 01")


def test_unstuffing_a_long_body_ends() -> None:
    with deadline(1.0):
        assert protocol.unstuff(h("55 00 01 02 03 04")) == h("55 00 01 02 03 04")


# ------------------------------------------------------------------ building


def test_build_without_parameters_is_a_bare_instruction() -> None:
    assert protocol.build(1, 0x01) == h("FF FF FD 00 01 03 00 01 19 4E")  # the e-Manual's PING


def test_status_packet_without_parameters_is_the_error_byte_alone() -> None:
    # e.g. the reply to a WRITE: LEN 4 (INST, ERR, CRC)
    assert protocol.status_packet(1, 0) == h("FF FF FD 00 01 04 00 55 00 A1 0C")


LONG_STATUS = h("FF FF FD 00 01 01 01 55 00") + bytes(253) + h("79 97")  # LEN 257 = 0x0101


def test_a_status_of_257_length_has_len_h_1() -> None:
    assert protocol.status_packet(1, 0, bytes(253)) == LONG_STATUS


def test_a_received_packet_longer_than_255_uses_len_h() -> None:
    packet, ping = protocol.parse(LONG_STATUS + h("FF FF FD 00 01 03 00 01 19 4E"))
    assert packet.crc_ok and packet.data == bytes(253) and packet.raw == LONG_STATUS
    assert ping.instruction == ct.Instruction.PING


# ------------------------------------------------------------------ parser

PING_1 = h("FF FF FD 00 01 03 00 01 19 4E")


@pytest.mark.parametrize("split", [1, 2, 3])
def test_parser_keeps_a_partial_header_at_the_end_of_noise(split: int) -> None:
    parser = protocol.PacketParser()
    assert parser.feed(h("00 13") + PING_1[:split]) == []
    (packet,) = parser.feed(PING_1[split:])
    assert packet.id == 1 and packet.instruction == ct.Instruction.PING and packet.crc_ok


@pytest.mark.parametrize("length", ["00 00", "02 00", "01 04"])
def test_parser_skips_a_header_with_an_implausible_length(length: str) -> None:
    # LEN below 3 (INST + CRC) or above the SDK's RXPACKET_MAX_LEN, 1024
    bogus = h("FF FF FD 00 01") + h(length)
    packets = protocol.PacketParser().feed(bogus + PING_1)
    assert [(p.id, p.instruction, p.raw) for p in packets] == [(1, 0x01, PING_1)]


def test_parser_accepts_len_1024() -> None:
    # the SDK's rxPacket refuses LEN > RXPACKET_MAX_LEN (1024), not LEN 1024
    raw = h("FF FF FD 00 01 00 04 55 00") + bytes(1020) + h("83 5F")
    (packet,) = protocol.parse(raw)
    assert packet.crc_ok and packet.data == bytes(1020)


def test_parsed_packet_keeps_its_raw_bytes() -> None:
    (packet,) = protocol.parse(h("13") + PING_1)
    assert packet.raw == PING_1


# ================================================================== control_table.py
# _f runs at import, before mutmut switches a mutant on; these call it again.


def test_an_item_at_address_64_is_ram_and_63_is_eeprom() -> None:
    # e-Manual: EEPROM area 0-63, RAM from 64
    assert ct._f("Torque Enable", 64, 1, "RW") == ct.Field("Torque Enable", 64, 1, True, False, 0, False)
    assert ct._f("Shutdown", 63, 1, "RW", 52) == ct.Field("Shutdown", 63, 1, True, True, 52, False)


def test_a_read_only_item_is_not_writable() -> None:
    assert ct._f("Present Position", 132, 4, "R", None, signed=True) == ct.Field(
        "Present Position", 132, 4, False, False, None, True
    )


def test_an_item_defaults_to_0_and_unsigned() -> None:
    assert ct._f("LED", 65, 1, "RW") == ct.Field("LED", 65, 1, True, False, 0, False)


def test_the_table_as_the_e_manual_lists_it() -> None:
    # e-Manual rows: name, address, size, access, default
    assert ct.field("Homing Offset") == ct.Field("Homing Offset", 20, 4, True, True, 0, True)
    assert ct.field("Goal Position") == ct.Field("Goal Position", 116, 4, True, False, None, True)
    assert ct.field("Model Number") == ct.Field("Model Number", 0, 2, False, True, 1060, False)


def test_an_unknown_item_is_named_with_the_known_ones() -> None:
    # Goal Current exists on the XM430, not on the XL430-W250
    with pytest.raises(KeyError) as e:
        ct.field("Goal Current")
    message = e.value.args[0]
    assert message.startswith("no control-table item 'Goal Current'; known: Model Number, Model Information,")
    assert message.endswith(", Present Input Voltage, Present Temperature")


def test_two_s_complement_sign_bit_is_the_top_bit() -> None:
    assert ct.to_signed(0x8000, 2) == -32768
    assert ct.to_signed(0x4000, 2) == 16384
    assert ct.to_signed(0xFFFFFFFF, 4) == -1
    assert ct.to_signed(0x40000000, 4) == 0x40000000


# ================================================================== bus.py

#: The SDK's texts (protocol2_packet_handler.getTxRxResult / getRxPacketError).
NO_STATUS = "[TxRxResult] There is no status packet!"
LIMIT = "[RxPacketError] The data value exceeds the limit value!"
CHECK = ". Check the cable, power, ID and baud rate"


class SpyPort(EmulatedPortHandler):
    """An emulated port that counts openPort and set_rs485, and can fail to open."""

    def __init__(
        self, emulated: EmulatedRS485Bus, opens: bool = True, error: Exception | None = None
    ) -> None:
        super().__init__(emulated)
        self.opens, self.error = opens, error
        self.open_calls = self.rs485_calls = 0

    def openPort(self) -> bool:
        self.open_calls += 1
        if self.error is not None:
            raise self.error
        return super().openPort() and self.opens

    def set_rs485(self) -> bool:
        self.rs485_calls += 1
        return True


def rig(
    ids: tuple[int, ...] = (1,), **bus_kwargs: object
) -> tuple[DynamixelBus, EmulatedRS485Bus, ManualClock]:
    clock = ManualClock()
    emulated = EmulatedRS485Bus.with_ids(ids, clock=clock)
    bus = DynamixelBus(EmulatedPortHandler(emulated), clock=clock, **bus_kwargs)  # type: ignore[arg-type]
    return bus, emulated, clock


# ------------------------------------------------------------------ load_sdk


class _FailingImport:
    """A meta-path finder: importing dynamixel_sdk fails because ``missing`` is missing."""

    def __init__(self, missing: str) -> None:
        self.missing = missing

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == "dynamixel_sdk":
            raise ModuleNotFoundError(f"No module named {self.missing!r}", name=self.missing)


def _import_fails_on(monkeypatch: pytest.MonkeyPatch, missing: str) -> None:
    monkeypatch.delitem(sys.modules, "dynamixel_sdk")
    monkeypatch.setattr(sys, "meta_path", [_FailingImport(missing), *sys.meta_path])


@pytest.mark.parametrize("missing", ["dynamixel_sdk", "serial", "serial.tools.list_ports"])
def test_a_missing_sdk_or_pyserial_is_the_dynamixel_extra(
    monkeypatch: pytest.MonkeyPatch, missing: str
) -> None:
    _import_fails_on(monkeypatch, missing)
    with pytest.raises(MissingExtraError) as e:
        load_sdk()
    assert str(e.value) == (
        "Dynamixel joints (the dynamixel-sdk package) needs the [dynamixel] extra: "
        "pip install 'bioscara-gym[dynamixel]'"
    )


def test_another_missing_module_inside_the_sdk_is_not_hidden(monkeypatch: pytest.MonkeyPatch) -> None:
    _import_fails_on(monkeypatch, "numpy")
    with pytest.raises(ModuleNotFoundError) as e:
        load_sdk()
    assert not isinstance(e.value, MissingExtraError) and e.value.name == "numpy"


# ------------------------------------------------------------------ LoopStats


def test_loop_stats_count_every_error_and_timeout() -> None:
    stats = LoopStats()
    stats.record(1.0, ok=False)  # a corrupt status: an error, not a timeout
    stats.record(2.0, ok=False, timeout=True)
    stats.record(3.0, ok=False, timeout=True)
    assert (stats.errors, stats.total_errors, stats.timeouts, stats.total_timeouts) == (3, 3, 2, 2)
    stats.reset()
    stats.record(4.0, ok=False, timeout=True)
    assert (stats.errors, stats.total_errors, stats.timeouts, stats.total_timeouts) == (1, 4, 1, 3)


def test_loop_stats_rate_starts_anew_after_a_reset() -> None:
    stats = LoopStats()
    stats.record(1.0, ok=True)
    stats.reset()
    stats.record(10.0, ok=True)
    stats.record(10.5, ok=True)
    assert stats.first_s == 10.0 and stats.achieved_hz == 2.0


def test_loop_stats_reset_all_forgets_the_last_execution() -> None:
    stats = LoopStats()
    stats.record(1.0, ok=True)
    stats.reset_all()
    assert stats.first_s is None and stats.last_s is None


def test_loop_stats_as_dict_names_every_counter() -> None:
    stats = LoopStats(rate_hz=100.0)
    stats.record(0.0, ok=True)
    stats.record(0.5, ok=False, timeout=True)
    stats.skipped = 7
    assert stats.as_dict() == {
        "rate_hz": 100.0,
        "achieved_hz": 2.0,
        "packets": 2,
        "errors": 1,
        "timeouts": 1,
        "skipped": 7,
        "total_packets": 2,
        "total_errors": 1,
        "total_timeouts": 1,
        "error_rate": 0.5,
    }


# ------------------------------------------------------------------ SyncLoop


def counting_loop(rate_hz: float, result: int | None = 0) -> tuple[SyncLoop, list[int]]:
    calls: list[int] = []

    def communicate() -> int | None:
        calls.append(1)
        return result

    return SyncLoop("pvl_reader", rate_hz, communicate), calls


def test_a_loop_at_0_hz_never_runs() -> None:
    loop, calls = counting_loop(0.0)
    assert loop.execute(0.0) is None and loop.execute(100.0) is None
    assert calls == [] and loop.stats.transactions == 0


def test_a_loop_keeps_its_schedule_when_a_call_is_a_little_late() -> None:
    # 100 Hz from t = 1 s: runs at 1.0, 1.012 (due 1.01), then 1.02 is due again (MH5: last += period)
    loop, calls = counting_loop(100.0)
    for t in (1.0, 1.012, 1.02):
        assert loop.execute(t) is True
    assert len(calls) == 3 and loop.stats.skipped == 0


@pytest.mark.parametrize("late", [0.025, 0.035])
def test_a_loop_restarts_from_now_after_a_gap_and_does_not_burst(late: float) -> None:
    # 100 Hz: a call 2.5 or 3.5 periods late restarts the schedule, the next one is a period later
    loop, calls = counting_loop(100.0)
    loop.execute(0.0)
    loop.execute(late)
    assert loop.execute(late + 0.005) is None  # half a period after the restart: skipped
    assert len(calls) == 2 and loop.stats.skipped == 1


def test_a_loop_with_nothing_to_send_succeeds_without_a_packet() -> None:
    loop, calls = counting_loop(100.0, result=None)
    assert loop.execute(0.0) is True
    assert calls == [1] and loop.stats.transactions == 0


def test_a_successful_run_is_not_an_error() -> None:
    loop, _ = counting_loop(100.0, result=0)  # COMM_SUCCESS
    assert loop.execute(0.0) is True
    assert (loop.stats.transactions, loop.stats.errors) == (1, 0)


# ------------------------------------------------------------------ DynamixelBus: construction, port


def test_bus_defaults_rs485_off_two_retries_and_the_wall_clock() -> None:
    emulated = EmulatedRS485Bus.with_ids([1])
    port = SpyPort(emulated)
    bus = DynamixelBus(port)
    assert isinstance(bus.clock, WallClock) and bus.retries == 2
    bus.open()
    assert port.rs485_calls == 0


def test_bus_with_rs485_switches_the_port_on_open() -> None:
    port = SpyPort(EmulatedRS485Bus.with_ids([1]))
    DynamixelBus(port, rs485=True).open()
    assert port.rs485_calls == 1


def test_bus_refuses_an_unknown_loop_naming_the_known_ones() -> None:
    with pytest.raises(ValueError) as e:
        DynamixelBus(EmulatedPortHandler(EmulatedRS485Bus.with_ids([1])), rates={"pvt_reader": 5.0})
    assert str(e.value) == "unknown loops ['pvt_reader']; known: pvl_reader, tv_reader, pv_writer, t_writer"


def test_bus_loops_carry_the_mh5_names() -> None:
    bus, _, _ = rig()
    assert [(key, loop.name) for key, loop in bus.loops.items()] == [
        ("pvl_reader", "pvl_reader"),
        ("tv_reader", "tv_reader"),
        ("pv_writer", "pv_writer"),
        ("t_writer", "t_writer"),
    ]


def test_open_is_idempotent_and_close_then_open_reopens() -> None:
    port = SpyPort(EmulatedRS485Bus.with_ids([1]))
    bus = DynamixelBus(port)
    bus.open()
    bus.open()
    assert port.open_calls == 1 and port.is_open
    bus.close()
    assert not port.is_open
    bus.open()
    assert port.open_calls == 2 and port.is_open


def test_a_port_that_does_not_open_is_a_comm_error() -> None:
    bus = DynamixelBus(SpyPort(EmulatedRS485Bus.with_ids([1]), opens=False))
    with pytest.raises(CommError) as e:
        bus.open()
    assert str(e.value) == "cannot open emulated at 1000000 bps"


def test_a_port_that_raises_on_open_is_a_comm_error_with_the_reason() -> None:
    bus = DynamixelBus(SpyPort(EmulatedRS485Bus.with_ids([1]), error=OSError("no such device")))
    with pytest.raises(CommError) as e:
        bus.open()
    assert str(e.value) == "cannot open emulated: no such device"


def test_two_joints_with_one_id_are_refused() -> None:
    bus, _, _ = rig()
    DynamixelJoint("j1", 1, bus)
    with pytest.raises(ValueError) as e:
        DynamixelJoint("j2", 1, bus)
    assert str(e.value) == "ID 1 is used by j1 and j2"


# ------------------------------------------------------------------ DynamixelBus: transactions


def test_a_failing_write_is_tried_retries_plus_one_times_and_names_the_sdk_reason() -> None:
    bus, emulated, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    before = emulated.instructions
    # Goal Position 5000 in position mode is beyond Max Position Limit 4095: Data Limit Error (e-Manual)
    with pytest.raises(CommError) as e:
        bus.write(joint, 116, 4, 5000)
    assert emulated.instructions - before == 3
    assert str(e.value) == f"j1: WRITE 116 failed after 3 attempts: {LIMIT}{CHECK}"
    assert (joint.stats.total_errors, joint.stats.total_retries) == (3, 2)


def test_an_attempt_after_a_failed_one_counts_as_a_retry() -> None:
    # Seen: a Dynamixel joint's retries stayed 0 whatever the bus did (the I2C joint counts them).
    bus, _, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    before = (joint.stats.total_transactions, joint.stats.total_retries)
    results = iter([(0, -3001, 0), (7, 0, 0)])  # COMM_TX_FAIL, then COMM_SUCCESS
    assert bus.transact(joint, "READ 132", lambda: next(results)) == (7, 0)
    stats = joint.stats
    assert (stats.total_transactions - before[0], stats.total_retries - before[1]) == (2, 1)


@pytest.mark.parametrize("retries", [0, 1, 4])
def test_a_failing_read_is_tried_retries_plus_one_times(retries: int) -> None:
    bus, emulated, _ = rig(retries=retries)
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    emulated.servos[1].powered = False
    before = emulated.instructions
    with pytest.raises(CommError) as e:
        bus.read(joint, 132, 4)
    assert emulated.instructions - before == retries + 1
    assert str(e.value) == f"j1: READ 132 failed after {retries + 1} attempts: {NO_STATUS}{CHECK}"


def test_read_block_and_reboot_failures_name_the_instruction() -> None:
    bus, emulated, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    emulated.servos[1].powered = False
    with pytest.raises(CommError, match=r"^j1: READ 126 failed after 3 attempts"):
        bus.read_block(joint, 126, 10)
    with pytest.raises(CommError, match=r"^j1: REBOOT failed after 3 attempts"):
        bus.reboot(joint)


def test_read_is_unsigned_unless_asked() -> None:
    bus, _, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    bus.write(joint, 20, 4, -1)  # Homing Offset, signed 4 bytes (EEPROM, torque is off)
    assert bus.read(joint, 20, 4) == 0xFFFFFFFF
    assert bus.read(joint, 20, 4, signed=True) == -1


# ------------------------------------------------------------------ DynamixelBus: loops


def test_read_loops_take_the_time_given() -> None:
    bus, _, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    bus.start_loops()
    bus.read_loops(now=0.0)
    bus.read_loops(now=0.5)  # the clock stands at 0: the time given counts
    pvl = bus.loop_stats()["pvl_reader"]
    assert (pvl.transactions, pvl.last_s) == (2, 0.5)


def test_write_loops_take_the_clock_or_the_time_given() -> None:
    bus, _, clock = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    joint.enable(20, 20)
    bus.start_loops()
    clock.sleep(1.0)
    joint.set_position(0.1)
    joint.request_torque(True)
    bus.write_loops()
    stats = bus.loop_stats()
    assert (stats["pv_writer"].last_s, stats["t_writer"].last_s) == (1.0, 1.0)
    joint.set_position(0.2)
    joint.request_torque(True)
    bus.write_loops(now=5.0)  # the clock stands at 1 s: the time given counts
    assert (stats["pv_writer"].last_s, stats["t_writer"].last_s) == (5.0, 5.0)


def test_after_stop_loops_a_command_goes_out_at_once() -> None:
    bus, emulated, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    joint.enable(20, 20)
    bus.start_loops()
    bus.stop_loops()
    emulated.keep_log = True
    joint.set_position(0.1)
    assert ct.Instruction.WRITE in [p.instruction for p in emulated.log]
    assert emulated.servos[1].get("Goal Position") == 2047 + 65  # round(0.1 / 0.001533980787886)


def test_a_corrupt_sync_read_status_does_not_hide_the_next_servos() -> None:
    bus, emulated, _ = rig(ids=(1, 2))
    first, second = DynamixelJoint("j1", 1, bus), DynamixelJoint("j2", 2, bus)
    first.init()
    second.init()
    bus.start_loops()
    emulated.faults = FaultPlan(schedule={emulated.statuses: Fault.CORRUPT})  # ID 1's next status
    emulated.servos[2].set("Present Position", 3000)
    bus.read_loops()
    assert second.position_raw == 3000 and second._fresh() and not first._fresh()
    pvl = bus.loop_stats()["pvl_reader"]
    assert (pvl.transactions, pvl.errors, pvl.timeouts) == (1, 1, 0)


def test_pvl_reader_decodes_signed_load_velocity_and_position() -> None:
    # PVL block 126-135 (MH5's PVLReader): Present Load (2 bytes), Velocity (4), Position (4), all signed
    bus, emulated, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    joint.init()
    bus.start_loops()
    servo = emulated.servos[1]
    servo.set("Present Load", -100)  # 9C FF
    servo.set("Present Velocity", -20)  # EC FF FF FF
    servo.set("Present Position", -5000)  # 78 EC FF FF
    bus.read_loops()  # the clock has not moved: the servo does not overwrite them
    assert (joint.load_raw, joint.velocity_raw, joint.position_raw) == (-100, -20, -5000)


def test_sync_reads_ask_for_the_pvl_and_tv_blocks_by_length() -> None:
    # MH5's PVLReader: start 126, length 10; TVReader: start 144, length 3 (SYNC READ 0x82 to 0xFE)
    bus, emulated, _ = rig(ids=(1, 2))
    DynamixelJoint("j1", 1, bus).init()
    DynamixelJoint("j2", 2, bus).init()
    bus.start_loops()
    emulated.keep_log = True
    bus.read_loops()
    assert [(p.id, p.instruction, p.params) for p in emulated.log] == [
        (0xFE, 0x82, h("7E 00 0A 00 01 02")),
        (0xFE, 0x82, h("90 00 03 00 01 02")),
    ]


# ================================================================== joint.py

#: MH5 / e-Manual units: rad per position unit, rad/s per velocity unit, rad/s^2 per acceleration unit.
RAD = 0.001533980787886
RADS = 0.023980823922402
RADS2 = 214.577 * 2 * 3.141592653589793 / 3600.0


def dxl(
    ids: tuple[int, ...] = (1,), faults: FaultPlan | None = None, **joint_kwargs: float
) -> tuple[DynamixelJoint, DynamixelBus, EmulatedRS485Bus, ManualClock]:
    """An initialized joint on ID ``ids[0]`` of an emulated bus."""
    clock = ManualClock()
    emulated = EmulatedRS485Bus.with_ids(ids, clock=clock, faults=faults)
    bus = DynamixelBus(EmulatedPortHandler(emulated), clock=clock)
    joint = DynamixelJoint("j1", ids[0], bus, clock=clock, **joint_kwargs)
    joint.init()
    return joint, bus, emulated, clock


def synced(**joint_kwargs: float) -> tuple[DynamixelJoint, DynamixelBus, EmulatedRS485Bus, ManualClock]:
    """:func:`dxl`, enabled at 20 %, its commands going through the bus's loops."""
    joint, bus, emulated, clock = dxl(**joint_kwargs)
    joint.enable(20, 20)
    bus.start_loops()
    return joint, bus, emulated, clock


def writers_send_nothing(bus: DynamixelBus, emulated: EmulatedRS485Bus, clock: ManualClock) -> bool:
    """Whether the writer loops, due again a second later, put nothing on the bus."""
    clock.sleep(1.0)
    emulated.keep_log = True
    bus.write_loops()
    return emulated.log == []


def refused(error: type[Exception], call: object, *args: object) -> str:
    """The message of the error ``call(*args)`` raises (its joint checked to be j1)."""
    with pytest.raises(error) as e:
        call(*args)  # type: ignore[operator]
    assert getattr(e.value, "joint", "j1") == "j1"
    return str(e.value)


# ------------------------------------------------------------------ construction


def test_a_joint_takes_the_clock_given_or_the_bus_s() -> None:
    bus, _, clock = rig()
    other = ManualClock()
    assert DynamixelJoint("j1", 1, bus).clock is clock
    assert DynamixelJoint("j2", 2, bus, clock=other).clock is other


@pytest.mark.parametrize("dxl_id", [0, 252])
def test_ids_0_and_252_are_accepted(dxl_id: int) -> None:
    bus, _, _ = rig()
    assert DynamixelJoint("j1", dxl_id, bus).dxl_id == dxl_id


@pytest.mark.parametrize(("dxl_id", "shown"), [(253, "253"), (-1, "-1"), (True, "True"), (1.0, "1.0")])
def test_an_id_beyond_0_252_or_not_an_int_is_refused(dxl_id: object, shown: str) -> None:
    bus, _, _ = rig()
    message = refused(InvalidArgumentError, DynamixelJoint, "j1", dxl_id, bus)
    assert message == f"j1: Dynamixel ID {shown} must be 0-252"


def test_a_non_finite_offset_is_refused() -> None:
    bus, _, _ = rig()
    with pytest.raises(InvalidArgumentError) as e:
        DynamixelJoint("j1", 1, bus, offset=math.inf)
    assert str(e.value) == "j1: offset inf must be finite" and e.value.joint == "j1"


def test_effort_voltage_and_temperature_are_0_before_any_loop_ran() -> None:
    joint, *_ = dxl()
    assert (joint.get_effort(), joint.get_voltage(), joint.get_temperature()) == (0.0, 0.0, 0.0)


def test_nothing_is_sent_by_the_writers_after_init() -> None:
    joint, bus, emulated, _ = dxl()
    bus.start_loops()
    emulated.keep_log = True
    bus.write_loops()
    assert emulated.log == [] and not joint.has_pv_command() and not joint.has_torque_request()


# ------------------------------------------------------------------ init


def test_init_refuses_another_model_and_stays_uninitialized(monkeypatch: pytest.MonkeyPatch) -> None:
    bus, _, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    monkeypatch.setattr(bus, "ping", lambda joint, tries=None: 1030)  # an XM430-W350 (e-Manual)
    message = refused(CommError, joint.init)
    assert message == "j1: ID 1 is model 1030, expected XL430-W250 (1060)"
    assert not joint.initialized


def test_init_that_fails_after_the_ping_leaves_the_joint_uninitialized() -> None:
    clock = ManualClock()
    # status 0 answers the PING; the three tries of the flags' READ get no answer
    emulated = EmulatedRS485Bus.with_ids(
        [1], clock=clock, faults=FaultPlan(schedule={1: Fault.DROP, 2: Fault.DROP, 3: Fault.DROP})
    )
    joint = DynamixelJoint("j1", 1, DynamixelBus(EmulatedPortHandler(emulated), clock=clock))
    with pytest.raises(CommError):
        joint.init()
    assert not joint.initialized


def test_init_takes_the_servo_s_profile_for_the_pv_writer() -> None:
    clock = ManualClock()
    emulated = EmulatedRS485Bus.with_ids([1], clock=clock)
    servo = emulated.servos[1]
    servo.set("Profile Acceleration", 5)
    servo.set("Profile Velocity", 7)
    bus = DynamixelBus(EmulatedPortHandler(emulated), clock=clock)
    joint = DynamixelJoint("j1", 1, bus, clock=clock)
    joint.init()
    joint.enable(20, 20)
    bus.start_loops()
    joint.set_position(0.1)
    bus.write_loops()
    assert (servo.get("Profile Acceleration"), servo.get("Profile Velocity")) == (5, 7)
    assert servo.get("Goal Position") == 2047 + 65  # round(0.1 / RAD)


# ------------------------------------------------------------------ status and flags


def test_an_alert_in_any_status_is_stall_and_torque_off() -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    servo = emulated.servos[1]
    servo.table[70] = int(ct.HardwareError.OVERLOAD)  # Hardware Error Status, behind the driver
    servo.table[64] = 0
    joint.get_position()  # one READ; its status has the Alert bit
    assert joint.flags == Flag.STALL | Flag.NOT_ENABLED


def test_a_status_without_alert_clears_only_stall() -> None:
    joint, _, emulated, _ = dxl()
    servo = emulated.servos[1]
    servo.table[70] = int(ct.HardwareError.OVERLOAD)
    joint.get_position()
    assert joint.flags == Flag.STALL | Flag.NOT_ENABLED
    servo.table[70] = 0  # cleared (as a REBOOT does)
    joint.get_position()
    assert joint.flags == Flag.NOT_ENABLED


def test_disable_of_a_stalled_joint_keeps_stall() -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    emulated.servos[1].table[70] = int(ct.HardwareError.OVERLOAD)
    joint.disable()
    assert joint.flags == Flag.STALL | Flag.NOT_ENABLED


def test_a_stall_names_the_servo_s_hardware_error() -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    emulated.servos[1].table[70] = int(ct.HardwareError.INPUT_VOLTAGE)
    joint.get_flags()
    message = refused(StalledError, joint.set_position, 0.1)
    assert message == "j1: hardware error <HardwareError.INPUT_VOLTAGE: 1>; reboot the joint to clear it"


def test_a_disabled_joint_refuses_motion_as_not_enabled() -> None:
    joint, *_ = dxl()
    assert refused(NotEnabledError, joint.set_position, 0.1) == "j1: joint not enabled; call enable() first"


def test_enable_refused_by_the_servo_without_a_hardware_error(monkeypatch: pytest.MonkeyPatch) -> None:
    joint, _, emulated, _ = dxl()
    monkeypatch.setattr(emulated.servos[1], "write", lambda address, data: 0)  # acknowledged, not taken
    assert refused(NotEnabledError, joint.enable, 20, 20) == "j1: failed to enable: the servo kept torque off"


@pytest.mark.parametrize(
    ("drive", "hold", "message"), [(101, 20, "drive current 101"), (20, -1, "hold current -1")]
)
def test_enable_names_the_current_refused(drive: int, hold: int, message: str) -> None:
    joint, *_ = dxl()
    assert (
        refused(InvalidArgumentError, joint.enable, drive, hold)
        == f"j1: {message} must be an integer percent 0-100"
    )


def test_torque_and_mode_writes_touch_only_their_own_item() -> None:
    # Torque Enable (64) and Operating Mode (11) are 1 byte: LED (65) and Secondary ID (12) stay
    joint, _, emulated, _ = dxl()
    servo = emulated.servos[1]
    servo.set("LED", 1)
    joint.enable(20, 20)
    joint.set_velocity(0.1)  # torque off, Operating Mode 1, torque on
    joint.disable()
    assert (servo.get("LED"), servo.get("Secondary ID")) == (1, 255)
    assert servo.get("Operating Mode") == ct.OperatingMode.VELOCITY


# ------------------------------------------------------------------ loops and the joint


def test_pv_and_torque_requests_are_sent_once() -> None:
    joint, bus, emulated, clock = synced()
    joint.set_position(0.1)
    joint.request_torque(True)
    bus.write_loops()
    assert not joint.has_pv_command() and not joint.has_torque_request()
    assert writers_send_nothing(bus, emulated, clock)


def test_a_torque_off_request_marks_the_joint_not_enabled() -> None:
    joint, bus, emulated, _ = synced()
    joint.request_torque(False)
    bus.write_loops()
    assert joint.flags == Flag.NOT_ENABLED and not emulated.servos[1].torque


def test_synced_velocity_sends_the_signed_goal_velocity_and_keeps_the_goal_position() -> None:
    joint, bus, emulated, _ = synced()
    joint.set_velocity(-20 * RADS)
    bus.write_loops()
    servo = emulated.servos[1]
    assert (servo.get("Goal Velocity"), servo.get("Goal Position")) == (-20, 2047)


def test_synced_position_after_velocity_sends_goal_velocity_0() -> None:
    joint, bus, emulated, clock = synced()
    joint.set_velocity(0.5)
    bus.write_loops()
    clock.sleep(0.02)
    joint.set_position(0.1)
    bus.write_loops()
    assert emulated.servos[1].get("Goal Velocity") == 0


@pytest.mark.parametrize("drop", ["disable", "reboot"])
def test_commands_pending_for_the_writers_are_dropped_by_disable_and_reboot(drop: str) -> None:
    joint, bus, emulated, clock = synced()
    joint.set_position(0.1)
    joint.request_torque(True)
    getattr(joint, drop)()
    assert writers_send_nothing(bus, emulated, clock)


def test_a_position_pending_for_the_pv_writer_is_dropped_by_stop() -> None:
    joint, bus, emulated, clock = synced()
    joint.set_position(0.1)
    joint.stop()
    assert writers_send_nothing(bus, emulated, clock)


def test_fresh_loop_values_are_used_for_three_periods_then_read_again() -> None:
    joint, bus, emulated, clock = dxl()
    bus.start_loops()
    clock.sleep(1.0)
    bus.read_loops()  # pvl_reader at 1.0 s: Present Position 2047, velocity 0
    servo = emulated.servos[1]
    servo.set("Present Position", 2147)
    servo.set("Present Velocity", 10)
    emulated.keep_log = True
    assert (joint.get_position(), joint.get_velocity()) == (0.0, 0.0)
    assert (joint.get_position(), joint.get_velocity()) == (0.0, 0.0)  # still fresh
    assert emulated.log == []
    clock.sleep(0.05)  # five 100 Hz periods: stale
    servo.update()  # the motor model catches up with the clock, then the position changes behind it
    servo.set("Present Position", 2147)
    assert joint.get_position() == pytest.approx(100 * RAD)


def test_effort_is_the_pvl_reader_s_load() -> None:
    joint, bus, emulated, _ = dxl()
    bus.start_loops()
    emulated.servos[1].set("Present Load", -100)
    bus.read_loops()
    assert joint.get_effort() == pytest.approx(-100 * 0.0014)


# ------------------------------------------------------------------ units and reduction


def test_reduction_scales_position_velocity_and_profiles() -> None:
    # q = ((raw - 2047) * RAD) / reduction + offset (MH5), the same for velocities and profiles
    joint, _, emulated, clock = dxl(reduction=2.0)
    servo = emulated.servos[1]
    joint.enable(20, 20)
    joint.set_max_acceleration(10.0)
    joint.set_max_velocity(1.0)
    assert (servo.get("Profile Acceleration"), servo.get("Profile Velocity")) == (53, 83)  # 20/RADS2, 2/RADS
    joint.set_position(0.1)
    assert servo.get("Goal Position") == 2047 + 130  # round(0.2 / RAD)
    clock.sleep(5.0)
    assert joint.get_position() == pytest.approx(130 * RAD / 2)
    joint.set_velocity(0.5)
    assert servo.get("Goal Velocity") == 42  # round(1.0 / RADS)
    clock.sleep(1.0)
    assert joint.get_velocity() == pytest.approx(42 * RADS / 2)


def test_a_negative_present_position_reads_negative() -> None:
    joint, _, emulated, _ = dxl()
    emulated.servos[1].set("Present Position", -5000)  # extended position range (e-Manual)
    assert joint.get_position() == pytest.approx((-5000 - 2047) * RAD)


@pytest.mark.parametrize("raw", [0, 4095])
def test_goal_positions_0_and_4095_are_accepted(raw: int) -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    joint.set_position((raw - 2047) * RAD)
    assert emulated.servos[1].get("Goal Position") == raw


@pytest.mark.parametrize(("raw", "shown"), [(-1, "-3.14159"), (4096, "3.14313")])
def test_goal_positions_beyond_0_4095_are_refused(raw: int, shown: str) -> None:
    joint, *_ = dxl()
    joint.enable(20, 20)
    message = refused(InvalidArgumentError, joint.set_position, (raw - 2047) * RAD)
    assert message == f"j1: position {shown} is outside the servo's range"


def test_profiles_are_at_least_1_unit() -> None:
    joint, _, emulated, _ = dxl()
    joint.set_max_acceleration(0.1)  # 0.27 units
    joint.set_max_velocity(0.001)  # 0.04 units
    servo = emulated.servos[1]
    assert (servo.get("Profile Acceleration"), servo.get("Profile Velocity")) == (1, 1)


def test_profiles_of_0_are_refused_and_below_1_accepted() -> None:
    joint, _, emulated, _ = dxl()
    assert (
        refused(InvalidArgumentError, joint.set_max_acceleration, 0) == "j1: max acceleration 0.0 must be > 0"
    )
    assert refused(InvalidArgumentError, joint.set_max_velocity, 0) == "j1: max velocity 0.0 must be > 0"
    joint.set_max_velocity(0.5)
    assert emulated.servos[1].get("Profile Velocity") == 21  # round(0.5 / RADS)


@pytest.mark.parametrize(
    ("method", "args", "what"),
    [
        ("set_position", (math.nan,), "position nan"),
        ("set_velocity", (math.inf,), "velocity inf"),
        ("set_max_acceleration", (math.nan,), "max acceleration nan"),
        ("set_max_velocity", (math.nan,), "max velocity nan"),
        ("start_homing", (math.nan, 10, 20), "homing velocity nan"),
        ("check_orientation", (math.nan,), "orientation angle nan"),
    ],
)
def test_a_non_finite_argument_is_named(method: str, args: tuple[float, ...], what: str) -> None:
    joint, *_ = dxl()
    joint.enable(20, 20)
    assert refused(InvalidArgumentError, getattr(joint, method), *args) == f"j1: {what} must be finite"


# ------------------------------------------------------------------ move_steps, stop


def test_move_steps_goes_from_the_present_position() -> None:
    joint, bus, emulated, _ = dxl()
    servo = emulated.servos[1]
    joint.enable(20, 20)
    servo.set("Present Position", 3000)
    joint.move_steps(-100)
    assert servo.get("Goal Position") == 2900
    bus.start_loops()
    joint.set_velocity(0.1)  # the next pv block keeps the move's goal
    bus.write_loops()
    assert servo.get("Goal Position") == 2900


def test_move_steps_from_velocity_mode_switches_to_position_mode() -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    joint.set_velocity(0.1)
    joint.move_steps(10)
    assert emulated.servos[1].get("Operating Mode") == ct.OperatingMode.POSITION


@pytest.mark.parametrize(("steps", "shown"), [(True, "True"), (1.5, "1.5")])
def test_move_steps_refuses_what_is_not_an_int(steps: object, shown: str) -> None:
    joint, *_ = dxl()
    joint.enable(20, 20)
    assert refused(InvalidArgumentError, joint.move_steps, steps) == f"j1: steps {shown} must be an integer"


def test_stop_in_position_mode_holds_the_present_position() -> None:
    joint, bus, emulated, _ = dxl()
    servo = emulated.servos[1]
    joint.enable(20, 20)
    joint.set_position(1.0)
    servo.set("Present Position", 2100)  # on the way
    joint.stop()
    assert servo.get("Goal Position") == 2100
    bus.start_loops()
    joint.set_velocity(0.1)
    bus.write_loops()
    assert servo.get("Goal Position") == 2100


# ------------------------------------------------------------------ currents, brake, homing, repr


@pytest.mark.parametrize("method", ["set_drive_current", "set_hold_current"])
def test_current_0_turns_torque_off_and_others_are_only_checked(method: str) -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    getattr(joint, method)(1)
    getattr(joint, method)(100)
    assert emulated.servos[1].torque
    getattr(joint, method)(0)
    assert not emulated.servos[1].torque and joint.flags == Flag.NOT_ENABLED
    what = method.removeprefix("set_").replace("_", " ")
    message = refused(InvalidArgumentError, getattr(joint, method), 101)
    assert message == f"j1: {what} 101 must be an integer percent 0-100"


def test_brake_modes_0_to_2_are_accepted_and_3_refused() -> None:
    joint, *_ = dxl()
    for mode in (0, 1, 2):
        joint.set_brake_mode(mode)
    assert refused(InvalidArgumentError, joint.set_brake_mode, 3) == "j1: brake mode 3 must be 0, 1 or 2"


def test_homing_and_stall_detection_name_the_argument_refused() -> None:
    joint, *_ = dxl()
    joint.enable(20, 20)
    assert (
        refused(InvalidArgumentError, joint.start_homing, 0.0, 10, 20)
        == "j1: homing velocity must be non-zero"
    )
    assert (
        refused(InvalidArgumentError, joint.start_homing, 1.0, 256, 20)
        == "j1: homing sensitivity 256 must be 0-255"
    )
    message = refused(InvalidArgumentError, joint.start_homing, 1.0, 10, 101)
    assert message == "j1: homing current 101 must be an integer percent 0-100"
    assert (
        refused(InvalidArgumentError, joint.enable_stallguard, 256)
        == "j1: stall sensitivity 256 must be 0-255"
    )


def test_homing_states_are_the_blocking_command() -> None:
    joint, *_ = dxl()
    joint.enable(20, 20)
    joint.start_homing(1.0, 10, 20)
    assert joint.current_blocking_command is Reg.HOME
    joint.post_homing()
    assert joint.current_blocking_command is Reg.NONE
    joint.adopt_homing(1.0)
    assert joint.current_blocking_command is Reg.HOME


def test_bioscara_registers_are_refused_by_name() -> None:
    joint, *_ = dxl()
    assert (
        refused(JointError, joint._command, Reg.SETRPM, 1)
        == "j1: SETRPM: a Dynamixel joint has no Bioscara registers"
    )
    assert refused(JointError, joint._query, Reg.GETMOTORSTATE) == (
        "j1: GETMOTORSTATE: a Dynamixel joint has no Bioscara registers"
    )


def test_repr_names_the_joint_its_id_and_flags() -> None:
    joint, *_ = dxl()
    assert repr(joint) == "DynamixelJoint('j1', id=1, flags=<Flag.NOT_ENABLED: 8>)"


def test_reboot_pings_five_times_and_keeps_the_operating_mode() -> None:
    joint, _, emulated, _ = dxl()
    joint.enable(20, 20)
    joint.set_velocity(0.1)
    n = emulated.statuses  # the REBOOT's status; the next three PING replies are lost
    emulated.faults = FaultPlan(schedule={n + 1: Fault.DROP, n + 2: Fault.DROP, n + 3: Fault.DROP})
    joint.reboot()
    assert joint.mode == ct.OperatingMode.VELOCITY and joint.flags == Flag.NOT_ENABLED


def test_a_joint_found_with_torque_on_holds_the_present_position() -> None:
    # a host restart: the servo kept torque on, so no enable() re-reads the goal before a synced command
    clock = ManualClock()
    emulated = EmulatedRS485Bus.with_ids([1], clock=clock)
    servo = emulated.servos[1]
    servo.set("Torque Enable", 1)
    servo.set("Present Position", 3000)
    bus = DynamixelBus(EmulatedPortHandler(emulated), clock=clock)
    joint = DynamixelJoint("j1", 1, bus, clock=clock)
    joint.init()
    bus.start_loops()
    joint.set_velocity(0.1)
    bus.write_loops()
    assert servo.get("Goal Position") == 3000


def test_no_model_number_before_a_servo_answered() -> None:
    bus, emulated, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    emulated.servos[1].powered = False
    with pytest.raises(CommError):
        joint.init()
    assert joint.model_number is None


# ------------------------------------------------------------------ stuffing what the driver sends


def test_a_write_whose_data_holds_ff_ff_fd_arrives_stuffed_and_whole() -> None:
    # Homing Offset 0x00FDFFFF: data bytes FF FF FD 00, which the protocol stuffs to
    # FF FF FD FD 00 (LEN 10, not 9). dynamixel-sdk's txPacket drops addStuffing's result
    # and sent it unstuffed: the servo read 3 data bytes and answered a Data Length Error.
    bus, emulated, _ = rig()
    joint = DynamixelJoint("j1", 1, bus)
    assert bus.write(joint, 20, 4, 0x00FDFFFF) == 0
    assert emulated.servos[1].get("Homing Offset") == 0x00FDFFFF


def test_the_packet_handler_sends_the_stuffed_packet() -> None:
    sent: list[bytes] = []

    class Port:
        is_using = False

        def clearPort(self) -> None:
            pass

        def writePort(self, packet: list[int]) -> int:
            sent.append(bytes(packet))
            return len(packet)

    from bioscara_gym.hardware.dynamixel.bus import packet_handler

    handler = packet_handler(sdk)
    assert handler.writeTxOnly(Port(), 1, 20, 4, [0xFF, 0xFF, 0xFD, 0x00]) == sdk.COMM_SUCCESS
    # e-Manual: INST 03, address 14 00, data FF FF FD FD 00 (stuffed), LEN 0A 00 (INST, 7
    # parameter bytes, CRC); the CRC over all of it.
    body = h("FF FF FD 00 01 0A 00 03 14 00 FF FF FD FD 00")
    crc = sdk.PacketHandler(2.0).updateCRC(0, list(body), len(body))
    assert sent == [body + bytes((crc & 0xFF, crc >> 8))]
