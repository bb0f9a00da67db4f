"""Faults of ``bioscara emulate dynamixel`` a hostile tester reproduced: the link, a half packet, an ID.

- a second emulator given the same ``--link`` re-pointed it to its own pty
  (the first could no longer be reached), and the first, once stopped,
  removed the link the second still served;
- a client that closed partway through a packet left the emulator deaf: the
  next packets were taken as the rest of the one cut short;
- a servo whose ID was changed kept answering to its old ID, with its new one
  in the status packets.

The servers run in-process on a pty pair; the only waits are for the line to
go idle, a fraction of a second.
"""

from __future__ import annotations

import os
import select
import signal
import threading
import time
import tty
from pathlib import Path
from types import SimpleNamespace

import pytest

from bioscara_gym.console import emulate
from bioscara_gym.errors import CliError
from bioscara_gym.hardware.dynamixel import control_table as ct
from bioscara_gym.hardware.dynamixel import protocol
from bioscara_gym.hardware.dynamixel import pty_server as pty_module
from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
from bioscara_gym.hardware.dynamixel.pty_server import PtyServer, make_bus


def h(text: str) -> bytes:
    return bytes.fromhex(text)


PING_1 = h("FF FF FD 00 01 03 00 01 19 4E")
#: A header claiming 256 bytes, as a client that closed partway through a packet leaves it.
CUT_SHORT = h("FF FF FD 00 01 00 01 02 00")
ADDR_ID = ct.FIELDS["ID"].address


def ping(dxl_id: int) -> bytes:
    return protocol.instruction_packet(dxl_id, ct.Instruction.PING)


# ------------------------------------------------------------------ the link


def no_serving(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the command stop at its first wait, as Ctrl-C would, so a command that serves returns."""
    monkeypatch.setattr(emulate, "time", SimpleNamespace(sleep=lambda s: signal.raise_signal(signal.SIGINT)))


def test_cli_emulate_refuses_a_link_to_a_pty_another_server_serves(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: the second emulator re-pointed the link; the first kept saying it served it.
    from bioscara_gym.cli import main

    link = tmp_path / "dxl"
    no_serving(monkeypatch)
    with PtyServer(make_bus([1]), link) as first:
        assert main(["emulate", "dynamixel", "--ids", "2", "--link", str(link)]) == 2
        assert capsys.readouterr().err == (
            f"bioscara emulate: error: --link {link}: points at {first.slave_path}, a pseudo-terminal "
            "still in use (another emulator?); not replacing it\n"
        )
        assert os.readlink(link) == first.slave_path


def test_cli_emulate_refuses_a_users_link_to_a_live_terminal(tmp_path: Path) -> None:
    master, slave = os.openpty()
    try:
        link = tmp_path / "tty"
        link.symlink_to(os.ttyname(slave))
        with pytest.raises(CliError, match="a pseudo-terminal still in use"):
            emulate._check_link(str(link))
        assert os.readlink(link) == os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


def test_a_stale_link_to_a_pty_that_is_gone_may_still_be_replaced(tmp_path: Path) -> None:
    master, slave = os.openpty()
    gone = os.ttyname(slave)
    os.close(slave)
    os.close(master)  # the pty of an emulator that was killed: its slave device is gone
    link = tmp_path / "dxl"
    link.symlink_to(gone)
    assert emulate._check_link(str(link)) == link
    with PtyServer(make_bus([1]), link) as server:
        assert os.readlink(link) == server.slave_path


def test_stop_leaves_the_link_when_it_points_at_another_servers_pty(tmp_path: Path) -> None:
    # Seen: the first emulator, stopped, removed the link the second one served.
    link = tmp_path / "dxl"
    first = PtyServer(make_bus([1]), link).start()
    with PtyServer(make_bus([2])) as second:
        os.unlink(link)
        os.symlink(second.slave_path, link)  # as a second emulator re-pointing it would
        first.stop()
        assert os.readlink(link) == second.slave_path and not first.link_removed


def test_stop_removes_its_own_link(tmp_path: Path) -> None:
    link = tmp_path / "dxl"
    with PtyServer(make_bus([1]), link) as server:
        assert os.path.lexists(link)
    assert not os.path.lexists(link) and server.link_removed


# ------------------------------------------------------------ a half packet


def open_client(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    return fd


def reply_to(fd: int, packet: bytes, timeout_s: float = 2.0) -> bytes:
    """Write ``packet`` and collect what comes back until a whole status packet has (or the timeout)."""
    os.write(fd, packet)
    got = bytearray()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not protocol.parse(bytes(got)):
        ready, _, _ = select.select([fd], [], [], 0.05)
        if ready:
            got.extend(os.read(fd, 4096))
    return bytes(got)


@pytest.mark.parametrize("claimed", [256, 1024])
def test_a_packet_cut_short_by_a_closing_client_is_dropped_once_the_line_is_idle(claimed: int) -> None:
    # Seen: the next 25 SDK pings (100 after a 1024-byte claim) got "There is no status packet!".
    with PtyServer(make_bus([1])) as server:
        client = open_client(server.slave_path)
        os.write(client, h("FF FF FD 00 01") + claimed.to_bytes(2, "little") + h("02 00"))
        os.close(client)
        time.sleep(5 * getattr(pty_module, "RX_IDLE_S", 0.02))  # (absent before the fix)
        client = open_client(server.slave_path)
        try:
            (status,) = protocol.parse(reply_to(client, PING_1))
        finally:
            os.close(client)
    assert status.id == 1 and status.crc_ok and status.instruction == ct.Instruction.STATUS


def test_a_half_packet_is_dropped_by_the_idle_line_alone() -> None:
    # The next packet's header drops it too (below); here no byte follows, so only the idle gap can.
    bus = make_bus([1])
    cleared = threading.Event()
    clear = bus.clear_input

    def clear_input() -> None:
        if bus.in_receive:
            cleared.set()
        clear()

    bus.clear_input = clear_input  # type: ignore[method-assign]
    with PtyServer(bus) as server:
        client = open_client(server.slave_path)
        try:
            os.write(client, CUT_SHORT)
            assert cleared.wait(2.0), "the half packet was never dropped"
            assert bus.in_receive == 0
        finally:
            os.close(client)


def test_the_sdk_pings_after_a_client_left_a_half_packet() -> None:
    sdk = pytest.importorskip("dynamixel_sdk")
    with PtyServer(make_bus([1])) as server:
        client = open_client(server.slave_path)
        os.write(client, CUT_SHORT)
        os.close(client)
        time.sleep(5 * getattr(pty_module, "RX_IDLE_S", 0.02))  # (absent before the fix)
        port = sdk.PortHandler(server.slave_path)
        assert port.openPort() and port.setBaudRate(1_000_000)
        try:
            # the SDK's wait is ~34 ms; on a loaded machine the server's thread may miss it once
            results = [sdk.PacketHandler(2.0).ping(port, 1)[1] for _ in range(3)]
        finally:
            port.closePort()
    assert results[0] == 0 or results[1:] == [0, 0], results


def test_the_idle_gap_is_shorter_than_the_sdks_wait_and_longer_than_a_byte() -> None:
    # A client that retries after its wait (2 latency timers of 16 ms + 2 ms) must find the parser clear;
    # at the XL430's slowest baud rate (9600) a byte takes 1.04 ms.
    assert 10 * 1.04e-3 < pty_module.RX_IDLE_S < 2 * 16e-3 + 2e-3


def test_a_packet_cut_short_is_dropped_at_the_next_header() -> None:
    # A header inside a packet's body cannot be the body (byte stuffing puts FD after FF FF FD):
    # a new packet began, and the one before it was cut short.
    (packet,) = protocol.PacketParser().feed(CUT_SHORT + PING_1)
    assert (packet.id, packet.instruction, packet.raw) == (1, ct.Instruction.PING, PING_1)


def test_a_packet_cut_short_is_dropped_at_the_next_header_fed_later() -> None:
    parser = protocol.PacketParser()
    assert parser.feed(CUT_SHORT) == []
    assert [p.raw for p in parser.feed(PING_1[:4])] == []
    assert [p.raw for p in parser.feed(PING_1[4:])] == [PING_1]


def test_a_packet_whose_crc_completes_a_header_pattern_still_parses() -> None:
    # The body ends FF FF and the CRC is FD 00: a header's bytes at the very end, not a new packet.
    raw = h("FF FF FD 00 01 09 00 03 74 00 C0 BC FF FF FD 00")
    (packet,) = protocol.PacketParser().feed(raw)
    assert packet.crc_ok and packet.params == h("74 00 C0 BC FF FF")


def test_a_stuffed_header_pattern_in_a_body_is_not_taken_for_a_new_packet() -> None:
    packet = protocol.instruction_packet(1, ct.Instruction.WRITE, h("74 00 FF FF FD 00 01 02"))
    parser = protocol.PacketParser()
    assert parser.feed(packet[:-3]) == []
    (parsed,) = parser.feed(packet[-3:])
    assert parsed.crc_ok and parsed.params == h("74 00 FF FF FD 00 01 02")


# ------------------------------------------------------------- an ID change


def write_id(bus: EmulatedRS485Bus, to: int, new_id: int) -> bytes:
    return bus.transact(protocol.instruction_packet(to, ct.Instruction.WRITE, bytes((ADDR_ID, 0, new_id))))


def test_a_servo_answers_to_its_new_id_and_no_longer_to_the_old() -> None:
    # Seen: it kept answering to ID 1, with ID 5 in its status packets; pings to 5 got nothing.
    bus = EmulatedRS485Bus.with_ids([1, 2])
    (ack,) = protocol.parse(write_id(bus, 1, 5))
    assert (ack.id, ack.error) == (1, 0)  # acknowledged under the ID it was sent to
    assert bus.transact(ping(1)) == b""
    (status,) = protocol.parse(bus.transact(ping(5)))
    assert status.id == 5 and status.crc_ok
    broadcast = protocol.parse(bus.transact(ping(ct.BROADCAST_ID)))
    assert [p.id for p in broadcast] == [2, 5]


def test_a_servo_with_a_new_id_is_in_sync_read_under_it() -> None:
    bus = EmulatedRS485Bus.with_ids([1])
    write_id(bus, 1, 7)
    params = h("84 00 04 00")  # Present Position, 4 bytes
    assert bus.transact(protocol.instruction_packet(0xFE, ct.Instruction.SYNC_READ, params + h("01"))) == b""
    (status,) = protocol.parse(bus.transact(protocol.instruction_packet(0xFE, 0x82, params + h("07"))))
    assert status.id == 7 and int.from_bytes(status.data, "little") == 2047


def test_the_sdk_changes_an_id() -> None:
    sdk = pytest.importorskip("dynamixel_sdk")
    from bioscara_gym.hardware.dynamixel.port import EmulatedPortHandler

    bus = EmulatedRS485Bus.with_ids([1])
    port = EmulatedPortHandler(bus)
    assert port.openPort()
    ph = sdk.PacketHandler(2.0)
    assert ph.write1ByteTxRx(port, 1, ADDR_ID, 5)[0] == 0
    assert ph.ping(port, 5) == (1060, 0, 0)
    assert ph.ping(port, 1)[1] != 0


def test_two_servos_given_one_id_both_take_a_write_and_their_replies_collide() -> None:
    bus = EmulatedRS485Bus.with_ids([1, 2])
    write_id(bus, 2, 1)
    first, second = bus.servos[1], bus.servos[2]
    assert first.id == second.id == 1
    bus.transact(protocol.instruction_packet(1, ct.Instruction.WRITE, h("41 00 01")))  # LED on
    assert first.get("LED") == second.get("LED") == 1
    first.set("Present Position", 0x0F0F)
    second.set("Present Position", 0x00F0)
    first._pos, second._pos = 0x0F0F, 0x00F0
    got = bus.transact(protocol.instruction_packet(1, ct.Instruction.READ, h("84 00 04 00")))
    assert len(got) == 15  # one packet's length: they answered at once
    assert not any(p.crc_ok for p in protocol.parse(got))


def test_the_bus_still_refuses_two_servos_built_with_one_id() -> None:
    with pytest.raises(ValueError, match="two servos with ID 3"):
        EmulatedRS485Bus([XL430(3), XL430(3)])
