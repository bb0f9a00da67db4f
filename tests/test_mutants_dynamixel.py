"""Tests that kill mutmut's survivors in hardware/dynamixel/ (docs/mutation.md, issue #24 item 11).

Expected bytes are literals from the DYNAMIXEL Protocol 2.0 e-Manual page
(header ``FF FF FD 00``, LEN = INST + parameters + CRC, byte stuffing
``FF FF FD`` -> ``FF FF FD FD`` inside INST..PARAMS, instruction codes) with
CRCs computed by the official ``dynamixel_sdk`` (``updateCRC``), or the SDK
itself at run time; control-table values are the XL430-W250 e-Manual's.
"""

from __future__ import annotations

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
from bioscara_gym.hardware.errors import CommError, MissingExtraError

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
    assert joint.stats.total_errors == 3


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
