"""Dynamixel status packets that are not the reply to the request: short, long, late, from another ID.

A protocol 2.0 status packet does not say which request it answers. The SDK
flushes the port's input before each request (``txPacket`` calls
``clearPort``), which drops what has arrived but not a status packet still on
its way; ``readTxRx`` then takes any packet from the ID and slices it to the
length asked. A reply that came after the SDK stopped waiting for it was so
taken as the reply to the next request: an ``IndexError`` (a late PING reply
read as the 7-byte flags block), "0 is not a valid OperatingMode" (the
flags block's first byte read as the mode), or a wrong value without a word.

:class:`SlowLine` is a serial line on virtual time: the servos answer one
request at a time, each after its own delay, as ``bioscara emulate
dynamixel --faults delay_ms=...`` does on a pseudo-terminal; the SDK's timeouts
and the bus's wait for a quiet line run on the same virtual clock, so the
tests are exact and take no wall-clock time.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import pytest

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.dynamixel import protocol
from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
from bioscara_gym.hardware.errors import CommError
from bioscara_gym.hardware.registers import Flag

sdk = pytest.importorskip("dynamixel_sdk")

from bioscara_gym.hardware.dynamixel import bus as bus_module  # noqa: E402
from bioscara_gym.hardware.dynamixel.bus import DynamixelBus  # noqa: E402
from bioscara_gym.hardware.dynamixel.joint import DynamixelJoint  # noqa: E402
from bioscara_gym.hardware.dynamixel.port import EmulatedPortHandler  # noqa: E402

EXAMPLE = Path(__file__).parents[1] / "bioscara_gym" / "hardware" / "dynamixel" / "dynamixel_arm.yaml"
CHECK = ". Check the cable, power, ID and baud rate"
#: Bytes of a status packet: 11 and the data (a PING's 3, READ 64's 7).
PING_STATUS, FLAGS_STATUS = 14, 18

Mutate = Callable[[protocol.Packet, bytes], bytes]


class VirtualTime:
    """Seconds that pass only when something waits or polls."""

    def __init__(self) -> None:
        self.t = 1000.0

    def monotonic(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += max(s, 0.0)


class SlowLine(sdk.PortHandler):  # type: ignore[misc]
    """A serial line to emulated servos on virtual time (no ``discard_late_replies``: a real port's waits).

    The servos take one request at a time: request k's status packet goes
    out ``delays[k]`` after the servos got to it (0 once the list is used
    up), and a request that comes while they are busy waits its turn, as
    on the pty. ``mutate`` may replace a status packet.
    """

    POLL_S = 0.0001  # a poll of the port takes this long

    def __init__(self, emulated: EmulatedRS485Bus, vt: VirtualTime) -> None:
        super().__init__("slowline")
        self.emulated, self.vt = emulated, vt
        self.delays: list[float] = []
        self.mutate: Mutate | None = None
        self.requests: list[protocol.Packet] = []
        self._queue: list[tuple[float, bytes]] = []
        self._input = bytearray()
        self._free_at = 0.0

    def setupPort(self, cflag_baud: int) -> bool:
        self.is_open = True
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def closePort(self) -> None:
        self.is_open = False

    def getCurrentTime(self) -> float:  # the SDK's timeouts, in ms
        return self.vt.t * 1000.0

    def _arrive(self) -> None:
        while self._queue and self._queue[0][0] <= self.vt.t:
            self._input.extend(self._queue.pop(0)[1])

    def clearPort(self) -> None:
        self._arrive()
        self._input.clear()

    def getBytesAvailable(self) -> int:
        self.vt.t += self.POLL_S
        self._arrive()
        return len(self._input)

    def readPort(self, length: int) -> bytes:
        self.vt.t += self.POLL_S
        self._arrive()
        data = bytes(self._input[:length])
        del self._input[:length]
        return data

    def writePort(self, packet: list[int] | bytes) -> int:
        data = bytes(packet)
        (request,) = protocol.parse(data)
        self.requests.append(request)
        reply = self.emulated.transact(data)
        if self.mutate is not None:
            reply = self.mutate(request, reply)
        delay = self.delays.pop(0) if self.delays else 0.0
        self._free_at = max(self.vt.t, self._free_at) + delay
        if reply:
            self._queue.append((self._free_at, reply))
        return len(data)


@pytest.fixture
def vt(monkeypatch: pytest.MonkeyPatch) -> VirtualTime:
    """Virtual time for the bus's wait for a quiet line too."""
    clock = VirtualTime()
    monkeypatch.setattr(
        bus_module, "time", SimpleNamespace(monotonic=clock.monotonic, sleep=clock.sleep), raising=False
    )
    return clock


def slow_line(vt: VirtualTime) -> tuple[DynamixelJoint, DynamixelBus, SlowLine, EmulatedRS485Bus]:
    emulated = EmulatedRS485Bus.with_ids([1], clock=ManualClock())
    port = SlowLine(emulated, vt)
    bus = DynamixelBus(port, clock=emulated.clock)
    return DynamixelJoint("j1", 1, bus), bus, port, emulated


def read_of(address: int, size: int) -> Callable[[protocol.Packet], bool]:
    def match(p: protocol.Packet) -> bool:
        return p.instruction == 0x02 and p.params == bytes((address, 0, size, 0))

    return match


def replace_reply(match: Callable[[protocol.Packet], bool], reply: bytes) -> Mutate:
    return lambda request, real: reply if match(request) else real


# ------------------------------------------------------------------ late replies


def test_a_late_ping_reply_is_not_read_as_the_flags_block(vt: VirtualTime) -> None:
    # The hostile run: the first PING's reply came 50 ms late (the SDK waits 34 ms), the
    # retry took it, and the retry's own reply was read as READ 64's 7 bytes: IndexError.
    joint, bus, port, _ = slow_line(vt)
    port.delays = [0.05, 0.05]
    joint.init()
    assert joint.flags == Flag.NOT_ENABLED and joint.model_number == 1060
    assert joint.mode == 3 and joint.hardware_error == 0
    assert bus.late_bytes == 2 * PING_STATUS
    assert [p.instruction for p in port.requests[:4]] == [0x01, 0x01, 0x01, 0x02]


def test_a_late_reply_is_not_taken_as_the_next_requests(vt: VirtualTime) -> None:
    # READ 64 (7 bytes) answered late twice: its second reply reached READ 11 (1 byte),
    # whose value was then the Torque Enable byte: "0 is not a valid OperatingMode".
    joint, bus, port, emulated = slow_line(vt)
    joint.init()
    emulated.servos[1].set("Torque Enable", 1)
    port.delays = [0.05, 0.05]
    assert joint.get_flags() == Flag(0)
    assert bus.read(joint, 11, 1) == 3
    assert bus.late_bytes == 2 * FLAGS_STATUS
    assert (joint.stats.total_errors, joint.stats.total_retries) == (2, 2)


def test_a_late_reply_of_the_same_length_is_not_taken_either(vt: VirtualTime) -> None:
    # Present Position (132) and Goal Position (116) are both 4 bytes: only the wait tells them apart.
    joint, bus, port, emulated = slow_line(vt)
    joint.init()
    emulated.servos[1].set("Present Position", 1000)
    port.delays = [0.05, 0.05]
    assert bus.read(joint, 132, 4) == 1000
    assert bus.read(joint, 116, 4) == 2047


def test_replies_that_all_come_late_are_one_comm_error_saying_so(vt: VirtualTime) -> None:
    joint, bus, port, _ = slow_line(vt)
    joint.init()
    port.delays = [0.05] * 3
    with pytest.raises(CommError) as e:
        joint.get_flags()
    assert str(e.value) == (
        "j1: READ 64 failed after 3 attempts: [TxRxResult] There is no status packet!; "
        f"54 bytes came after the wait and were dropped{CHECK}"
    )
    assert bus.read(joint, 11, 1) == 3  # nothing of them is left for the next request


def test_a_reply_the_sdk_waited_for_is_not_waited_for_again(vt: VirtualTime) -> None:
    # 20 ms is within the SDK's 34 ms: no retry, no wait for a quiet line.
    joint, bus, port, _ = slow_line(vt)
    joint.init()
    port.delays = [0.02]
    start = vt.t
    assert joint.get_flags() == Flag.NOT_ENABLED
    assert vt.t - start < 0.025 and bus.late_bytes == 0 and joint.stats.total_retries == 0


# ------------------------------------------------------------------ short, long, another ID


def test_a_short_status_packet_is_a_comm_error_not_an_index_error(vt: VirtualTime) -> None:
    joint, _, port, _ = slow_line(vt)
    joint.init()
    port.mutate = replace_reply(read_of(64, 7), protocol.status_packet(1, 0, bytes((1, 0, 0))))
    with pytest.raises(CommError) as e:
        joint.get_flags()
    assert str(e.value) == (
        "j1: READ 64 failed after 3 attempts: a status packet with 3 data bytes where 7 were expected "
        f"(a late reply to an earlier request?); reply FF FF FD 00 01 07 00 55 00 01 00 00 DE C5{CHECK}"
    )
    assert (joint.stats.total_malformed, joint.stats.total_retries) == (3, 2)


def test_read_block_refuses_fewer_bytes_than_asked(vt: VirtualTime) -> None:
    joint, bus, port, _ = slow_line(vt)
    joint.init()
    port.mutate = replace_reply(read_of(126, 10), protocol.status_packet(1, 0, bytes(4)))
    with pytest.raises(CommError) as e:
        bus.read_block(joint, 126, 10)
    assert str(e.value) == (
        "j1: READ 126 failed after 3 attempts: a status packet with 4 data bytes where 10 were expected "
        f"(a late reply to an earlier request?); reply FF FF FD 00 01 08 00 55 00 00 00 00 00 BF B8{CHECK}"
    )


def test_read_refuses_more_bytes_than_asked_instead_of_taking_the_first(vt: VirtualTime) -> None:
    joint, bus, port, _ = slow_line(vt)
    joint.init()
    port.mutate = replace_reply(read_of(11, 1), protocol.status_packet(1, 0, bytes(7)))
    with pytest.raises(CommError) as e:
        bus.read(joint, 11, 1)
    assert str(e.value) == (
        "j1: READ 11 failed after 3 attempts: a status packet with 7 data bytes where 1 was expected "
        "(a late reply to an earlier request?); "
        f"reply FF FF FD 00 01 0B 00 55 00 00 00 00 00 00 00 00 A9 34{CHECK}"
    )


def test_a_reply_from_another_id_is_named(vt: VirtualTime) -> None:
    joint, _, port, _ = slow_line(vt)
    joint.init()
    port.mutate = replace_reply(read_of(64, 7), protocol.status_packet(2, 0, bytes(7)))
    with pytest.raises(CommError) as e:
        joint.get_flags()
    assert str(e.value) == (
        "j1: READ 64 failed after 3 attempts: no status packet from ID 1, one from ID 2 instead; "
        f"reply FF FF FD 00 02 0B 00 55 00 00 00 00 00 00 00 00 2B F4{CHECK}"
    )


def test_a_short_sync_read_status_is_an_error_of_the_loop_not_a_value(vt: VirtualTime) -> None:
    # The SDK's readRx sliced a 3-byte status to 3 bytes; the PVL decoder took position b"" as 0.
    joint, bus, port, _ = slow_line(vt)
    joint.init()
    bus.start_loops()
    sync_read = 0x82
    port.mutate = replace_reply(lambda p: p.instruction == sync_read, protocol.status_packet(1, 0, bytes(3)))
    bus.read_loops()
    pvl = bus.loop_stats()["pvl_reader"]
    assert (pvl.transactions, pvl.errors, pvl.timeouts) == (1, 1, 0)
    assert joint.position_raw == 2047 and not joint._fresh()


def test_an_operating_mode_an_xl430_has_not_is_a_comm_error_naming_the_joint() -> None:
    clock = ManualClock()
    emulated = EmulatedRS485Bus.with_ids([1], clock=clock)
    emulated.servos[1].set("Operating Mode", 0)
    joint = DynamixelJoint("j1", 1, DynamixelBus(EmulatedPortHandler(emulated), clock=clock))
    with pytest.raises(CommError) as e:
        joint.init()
    assert str(e.value) == (
        "j1: the servo reports Operating Mode 0, which an XL430-W250 does not have "
        "(1 (velocity), 3 (position), 4 (extended position), 16 (pwm))"
    )
    assert not joint.initialized


# ------------------------------------------------------------------ the emulator's timing


def test_an_idle_servo_does_not_step_its_motor_through_the_pause(monkeypatch: pytest.MonkeyPatch) -> None:
    # Stepping 1 ms at a time, a servo left alone for 10 s answered its next request after 50 ms,
    # past the SDK's 34 ms: the cause of the late replies without any fault injected.
    clock = ManualClock()
    servo = XL430(1, clock)
    steps: list[float] = []
    real_step = XL430._step
    monkeypatch.setattr(XL430, "_step", lambda self, h: (steps.append(h), real_step(self, h)))
    clock.sleep(100.0)
    servo.update()
    assert steps == []
    assert servo.get("Present Position") == 2047 and servo.get("Realtime Tick") == 100000 % 32768


def test_a_servo_driven_still_steps_and_one_at_its_goal_does_not(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = ManualClock()
    servo = XL430(1, clock)
    servo.write(64, bytes((1,)))  # torque on
    servo.write(116, (2100).to_bytes(4, "little"))  # 53 units away
    steps: list[float] = []
    real_step = XL430._step
    monkeypatch.setattr(XL430, "_step", lambda self, h: (steps.append(h), real_step(self, h)))
    clock.sleep(1.0)
    servo.update()
    assert len(steps) == 1000 and servo.get("Present Position") == 2100
    clock.sleep(1.0)
    servo.update()
    assert len(steps) == 1000 and servo.get("Present Position") == 2100


# ------------------------------------------------------------------ the console


def test_cli_disable_against_a_late_emulator_is_one_line(tmp_path: Path) -> None:
    # delay_ms=50 is past the SDK's 34 ms: before, the retries took each other's replies and
    # `bioscara disable` ended in a 29-line IndexError traceback, sending nothing.
    link = tmp_path / "ttyDXL"
    config = tmp_path / "dxl.yaml"
    config.write_text(EXAMPLE.read_text().replace("/dev/ttyUSB0", str(link)))
    env = {**os.environ, "HOME": str(tmp_path), "MUJOCO_GL": "egl"}
    emulate = ["emulate", "dynamixel", "--ids", "1-4", "--link", str(link), "--faults", "delay_ms=50"]
    emulator = subprocess.Popen(
        [sys.executable, "-m", "bioscara_gym", *emulate],
        stdout=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env=env,
    )
    try:
        assert emulator.stdout is not None
        assert "XL430 servos 1, 2, 3, 4" in emulator.stdout.readline()
        disable = ["disable", "--backend", "dynamixel", "--config", str(config)]
        cli = subprocess.run(
            [sys.executable, "-m", "bioscara_gym", *disable],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=tmp_path,
            env=env,
        )
    finally:
        emulator.send_signal(signal.SIGTERM)
        try:
            emulator.wait(timeout=10)
        except subprocess.TimeoutExpired:
            emulator.kill()
    assert cli.returncode == 3, cli.stderr  # a bus failure, not a refusal of the request (2)
    assert cli.stdout == ""
    assert re.fullmatch(
        r"bioscara disable: error: j1: PING failed after 5 attempts: \[TxRxResult\] There is no "
        r"status packet!; \d+ bytes came after the wait and were dropped\. "
        r"Check the cable, power, ID and baud rate\n",
        cli.stderr,
    ), cli.stderr


# ------------------------------------------------- status_data, packet by packet
# What the SDK's rxPacket hands over is checked again, byte by byte: a packet it
# let through (its header, CRC and length were right) may still answer another
# request. The packets below are built by the package's own protocol module.
STATUS_3 = protocol.status_packet(1, 0x80, bytes((0x06, 0x04, 0x26)))  # a PING's reply, the Alert bit


def test_status_data_gives_the_data_and_the_error_byte_of_the_servo_asked() -> None:
    assert bus_module.status_data(STATUS_3, 1, 3) == (bytes((0x06, 0x04, 0x26)), 0x80)
    assert bus_module.status_data(list(protocol.status_packet(7, 0, b"")), 7, 0) == (b"", 0)
    long = bytes(range(256)) + bytes(44)  # LEN 304: its high byte counts
    assert bus_module.status_data(protocol.status_packet(1, 0, long), 1, 300) == (long, 0)


@pytest.mark.parametrize(
    ("packet", "dxl_id", "size", "message"),
    [
        (
            STATUS_3[:10],
            1,
            3,
            "a status packet of 10 bytes, shorter than any (11); reply FF FF FD 00 01 07 00 55 80 06",
        ),
        (
            STATUS_3,
            2,
            3,
            "a status packet from ID 1, not ID 2; reply FF FF FD 00 01 07 00 55 80 06 04 26 "
            + STATUS_3[-2:].hex(" ").upper(),
        ),
        (
            protocol.build(1, 0x02, bytes(4)),
            1,
            3,
            "a packet with instruction 0x02, not a status packet (0x55); reply "
            + protocol.build(1, 0x02, bytes(4)).hex(" ").upper(),
        ),
        (
            STATUS_3[:11],
            1,
            3,
            "a truncated status packet (LEN 7, 11 bytes); reply FF FF FD 00 01 07 00 55 80 06 04",
        ),
        (
            STATUS_3[:5] + bytes((3, 0)) + STATUS_3[7:],
            1,
            0,
            "a truncated status packet (LEN 3, 14 bytes); reply FF FF FD 00 01 03 00 55 80 06 04 26 "
            + STATUS_3[-2:].hex(" ").upper(),
        ),
        (
            STATUS_3,
            1,
            1,
            "a status packet with 3 data bytes where 1 was expected (a late reply to an earlier "
            "request?); reply FF FF FD 00 01 07 00 55 80 06 04 26 " + STATUS_3[-2:].hex(" ").upper(),
        ),
        (
            protocol.status_packet(1, 0, b"\x05"),
            1,
            2,
            "a status packet with 1 data byte where 2 were expected (a late reply to an earlier "
            "request?); reply " + protocol.status_packet(1, 0, b"\x05").hex(" ").upper(),
        ),
    ],
    ids=["short", "another-id", "not-a-status", "truncated", "len-below-4", "more-data", "less-data"],
)
def test_status_data_refuses_a_packet_that_is_not_the_reply(
    packet: bytes, dxl_id: int, size: int, message: str
) -> None:
    with pytest.raises(bus_module.BadReply) as e:
        bus_module.status_data(packet, dxl_id, size)
    assert str(e.value) == message
    assert e.value.packet == bytes(packet)
