"""Shared fixtures of the test suite."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator

import pytest
from rigs import J1, RIG_FACTORIES, EmulatedJoint, JointRig, build_emulated

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.motor import KinematicStepper


class ScriptedBus:
    """A fake I2C bus at the byte boundary: records every transfer, replies from a script.

    Each transfer is logged as ``(address, bytes(data), read_len)`` and answered
    with the next queued reply; a queued exception instance is raised instead
    (e.g. ``OSError`` for a NACK). A transfer with nothing queued fails the test.
    """

    def __init__(self) -> None:
        self.log: list[tuple[int, bytes, int]] = []
        self.replies: deque[bytes | BaseException] = deque()
        self.closed = False

    def queue(self, *replies: bytes | BaseException) -> None:
        """Append canned replies (bytes) or faults (exception instances)."""
        self.replies.extend(replies)

    def clear_log(self) -> None:
        """Forget the transfers so far (after putting a joint into a state)."""
        self.log.clear()

    def writes(self) -> list[bytes]:
        """The bytes written by every logged transfer, in order."""
        return [data for _, data, _ in self.log]

    def transfer(self, address: int, data: Iterable[int], read_len: int) -> bytes:
        data = bytes(data)
        self.log.append((address, data, read_len))
        if not self.replies:
            raise AssertionError(f"unscripted transfer to {address:#04x}: {data.hex()} read {read_len}")
        reply = self.replies.popleft()
        if isinstance(reply, BaseException):
            raise reply
        return bytes(reply)

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def scripted_bus() -> Iterator[ScriptedBus]:
    """A :class:`ScriptedBus`; the test fails if it leaves replies unconsumed."""
    bus = ScriptedBus()
    yield bus
    assert not bus.replies, f"scripted replies left unconsumed: {list(bus.replies)!r}"


# ------------------------------------------------------- joint rigs and firmware


@pytest.fixture(params=sorted(RIG_FACTORIES))
def rig(request: pytest.FixtureRequest) -> JointRig:
    """Every joint backend of ``rigs.RIG_FACTORIES``, fresh, its joint not ``init()``-ed."""
    return RIG_FACTORIES[request.param]()


@pytest.fixture
def manual_clock() -> ManualClock:
    """A manual clock at t = 0."""
    return ManualClock()


@pytest.fixture
def free_motor() -> KinematicStepper:
    """A kinematic stepper at 0 deg with no end stops and no load."""
    return KinematicStepper(0.0)


@pytest.fixture
def firmware(free_motor: KinematicStepper, manual_clock: ManualClock) -> JointFirmware:
    """Joint firmware, just powered up, in front of :func:`free_motor`."""
    return JointFirmware(free_motor, manual_clock)


@pytest.fixture
def emulated_j1() -> EmulatedJoint:
    """SPEC j1 as Joint -> EmulatedI2CBus -> JointFirmware -> KinematicStepper, at q = 2.9 rad."""
    return build_emulated(J1, start_q=2.9)


@pytest.fixture
def make_emulated_j1() -> Callable[..., EmulatedJoint]:
    """Factory of :func:`emulated_j1` with a fault plan: ``make(faults=FaultPlan(...), retries=2)``."""

    def make(faults: FaultPlan | None = None, retries: int = 2) -> EmulatedJoint:
        return build_emulated(J1, start_q=2.9, faults=faults, retries=retries)

    return make
