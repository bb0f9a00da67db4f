"""An I2C bus in memory that serves emulated joint firmware, with fault injection.

:class:`FaultPlan` is the one fault plan of the emulated buses: this I2C bus
and the Dynamixel servos' RS-485 bus
(:class:`~bioscara_gym.hardware.dynamixel.emulator.EmulatedRS485Bus`) take it,
each refusing the faults it cannot inject (:data:`I2C_FAULTS`,
:data:`RS485_FAULTS`).

It plays the role of pyserial's ``loop://``: the real :class:`Joint` driver
runs unchanged against it, byte for byte. With a bus clock, every transaction
takes its time on the wire (:mod:`~bioscara_gym.hardware.i2c_timing`) plus
the plan's latency and jitter, on the bus's clock.
"""

from __future__ import annotations

import errno
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType

import numpy as np

from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.i2c_timing import WIRE_ONLY, TransactionTiming, check_clock_hz, nack_time_s
from bioscara_gym.hardware.registers import I2C_ADDRESS_MAX, I2C_ADDRESS_MIN

#: Largest host clock drift the fault plan accepts, ppm: 1 % (a quartz is off by
#: tens of ppm, an RC oscillator by up to about 1 %).
MAX_DRIFT_PPM = 10_000.0
#: Longest extra time per transaction the fault plan accepts, for its latency and for its
#: jitter each, s. The Pi's I2C adapter (Linux ``i2c-bcm2835``: ``BCM2835_I2C_TIMEOUT``,
#: 1000 ms; the I2C core's default is one second too) ends a transaction that takes longer
#: with ETIMEDOUT, which the driver sees as a bus error: the ``nack`` fault. The Dynamixel
#: SDK's packet timeouts are tens of ms. (Seen: ``latency_ms=1e308`` hung deploy at 100 % CPU,
#: deaf to SIGTERM; ``latency_ms=100000`` took 85 s to act on it, each disable of the safe
#: stop simulating 100 s.)
MAX_EXTRA_S = 1.0


class Fault(Enum):
    """A fault an emulated bus can inject into one transaction."""

    NACK = "nack"  # the address is not acknowledged: OSError, nothing delivered
    SHORT_READ = "short_read"  # the command is delivered, the reply comes back short
    CORRUPT = "corrupt"  # the command is delivered, one reply bit is flipped
    LATENCY = "latency"  # the transaction takes ``latency_s`` longer
    DROP = "drop"  # the command is delivered and executed, its reply lost (a status packet)


@dataclass(frozen=True)
class FaultKinds:
    """The faults one emulated bus injects, and how its ``--faults`` specification names them.

    Attributes:
        bus: The bus, for messages.
        rates: The :class:`FaultPlan` rates it injects (``nack``, ``drop``, ...).
        durations: The specification's time names to :class:`FaultPlan`'s
            (``NAME_ms``/``NAME_s`` in the specification; ``delay`` is the
            RS-485 bus's name for ``latency``).
        numbers: Further fields taken as they are (``drift_ppm``).
        scheduled: The faults a schedule may name.
    """

    bus: str
    rates: tuple[str, ...]
    durations: Mapping[str, str]
    numbers: tuple[str, ...]
    scheduled: frozenset[Fault]


#: What the emulated I2C bus injects.
I2C_FAULTS = FaultKinds(
    "I2C",
    ("nack", "short_read", "corrupt"),
    MappingProxyType({"latency": "latency", "jitter": "jitter"}),
    ("drift_ppm",),
    frozenset({Fault.NACK, Fault.SHORT_READ, Fault.CORRUPT, Fault.LATENCY}),
)
#: What the emulated RS-485 bus of Dynamixel servos injects (into status packets).
RS485_FAULTS = FaultKinds(
    "RS-485",
    ("drop", "corrupt"),
    MappingProxyType({"delay": "latency"}),
    (),
    frozenset({Fault.DROP, Fault.CORRUPT, Fault.LATENCY}),
)
#: Every rate of a plan.
_RATES = ("nack", "short_read", "corrupt", "drop")
#: Why a latency or jitter has a bound (:data:`MAX_EXTRA_S`), for messages.
_WHY_EXTRA = " (the bus's timeout: a longer transaction is a lost one, the nack or drop fault)"


@dataclass(frozen=True)
class FaultPlan:
    """What faults to inject, by rate and/or by schedule.

    Attributes:
        nack: Probability that a transaction is not acknowledged.
        short_read: Probability that a reply is cut short.
        corrupt: Probability that one bit of a reply is flipped.
        drop: Probability that a reply is lost after the command was executed
            (a Dynamixel status packet).
        latency_s: Extra time every transaction takes, seconds, within 0-:data:`MAX_EXTRA_S`.
        jitter_s: Further extra time per transaction, drawn uniformly from
            ``[0, jitter_s]`` by the fault generator, seconds, within 0-:data:`MAX_EXTRA_S`.
        drift_ppm: Host clock drift: the control loop's periods last
            ``1 + drift_ppm * 1e-6`` times their nominal length on the
            emulated backend (> 0: the host's clock runs slow), within
            ±:data:`MAX_DRIFT_PPM`.
        schedule: Transaction index (bus-wide, from 0) to the fault injected
            there, for deterministic tests.
        seed: Seed of the fault generator.
    """

    nack: float = 0.0
    short_read: float = 0.0
    corrupt: float = 0.0
    drop: float = 0.0
    latency_s: float = 0.0
    jitter_s: float = 0.0
    drift_ppm: float = 0.0
    schedule: Mapping[int, Fault] = field(default_factory=dict)
    seed: int | None = 0

    def __post_init__(self) -> None:
        """Validate rates, latency, jitter, drift and the schedule's faults."""
        for index, kind in self.schedule.items():
            if not isinstance(kind, Fault):
                known = ", ".join(f"Fault.{f.name}" for f in Fault)
                raise ValueError(f"schedule[{index}] = {kind!r}: expected one of {known}")
        for name in _RATES:
            rate = getattr(self, name)
            if not 0.0 <= rate <= 1.0:
                raise ValueError(f"fault rate {name}={rate} must be within 0-1")
        for name in ("latency_s", "jitter_s"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name}={getattr(self, name)} must be >= 0")
            if not getattr(self, name) <= MAX_EXTRA_S:
                raise ValueError(
                    f"{name}={getattr(self, name):g} must be within 0-{MAX_EXTRA_S:g} s{_WHY_EXTRA}"
                )
        if not abs(self.drift_ppm) <= MAX_DRIFT_PPM:
            raise ValueError(
                f"drift_ppm={self.drift_ppm:g} must be within ±{MAX_DRIFT_PPM:g} (a host clock off by "
                "more than 1 % is not drift)"
            )

    @property
    def period_scale(self) -> float:
        """How long a nominal second of the host's loop lasts: ``1 + drift_ppm * 1e-6``."""
        return 1.0 + self.drift_ppm * 1e-6

    @classmethod
    def parse(cls, spec: str, seed: int | None = 0, kinds: FaultKinds = I2C_FAULTS) -> FaultPlan:
        """Parse a ``--faults`` specification in ``kinds``' names.

        The I2C bus's: ``"nack=0.01,short_read=0.001,corrupt=0,latency_ms=2,jitter_ms=3,drift_ppm=50"``;
        the RS-485 bus's (:data:`RS485_FAULTS`): ``"drop=0.01,corrupt=0.001,delay_ms=2"``.
        Either may end with ``seed=N`` (a whole number >= 0): the faults' own
        random stream, in place of ``seed``.

        Raises:
            ValueError: Unknown key (the message lists the known ones) or a
                value that is not a number.
        """
        items = fault_items(spec)
        seeds = [item for item in items if item.partition("=")[0].strip() == "seed"]
        if seeds:
            if len(seeds) > 1:
                raise ValueError("fault 'seed' given twice")
            text = seeds[0].partition("=")[2].strip()
            if not text.isdigit():
                raise ValueError(f"fault 'seed': {text!r} must be a whole number >= 0")
            seed = int(text)
            spec = ",".join(item for item in items if item not in seeds)
        kwargs = parse_fault_spec(spec, kinds.rates, tuple(kinds.durations), numbers=kinds.numbers)
        for name, stem in kinds.durations.items():
            if f"{name}_s" in kwargs:
                kwargs[f"{stem}_s"] = kwargs.pop(f"{name}_s")
        return cls(seed=seed, **kwargs)

    def check_for(self, kinds: FaultKinds) -> None:
        """Refuse a fault the bus of ``kinds`` cannot inject (it would be silently ignored).

        Raises:
            ValueError: One line naming the fault and what the bus injects.
        """
        given = [n for n in _RATES if getattr(self, n)] + [
            n for n in ("latency", "jitter") if getattr(self, f"{n}_s")
        ]
        given += ["drift_ppm"] if self.drift_ppm else []
        given += [f"schedule {f.value}" for f in self.schedule.values() if f not in kinds.scheduled]
        known = (*kinds.rates, *kinds.durations.values(), *kinds.numbers)
        for name in given:
            if name not in known:
                injects = ", ".join(known)
                raise ValueError(f"the emulated {kinds.bus} bus cannot inject {name}; it injects {injects}")


def fault_items(spec: str) -> list[str]:
    """The stripped ``KEY=VALUE`` items of a fault specification; none if it is blank.

    Raises:
        ValueError: An empty item (``"nack=0.1,"``, ``","``).
    """
    items = [item.strip() for item in spec.split(",")] if spec.strip() else []
    if "" in items:
        raise ValueError(f"fault specification {spec!r} has an empty item; expected KEY=VALUE,...")
    return items


def parse_fault_spec(
    spec: str, rates: tuple[str, ...], duration: str | tuple[str, ...], numbers: tuple[str, ...] = ()
) -> dict[str, float]:
    """Parse ``"KEY=VALUE,..."`` into keyword arguments of a fault plan.

    Args:
        spec: The specification, e.g. ``"nack=0.01,latency_ms=2"``.
        rates: The keys that are probabilities.
        duration: The time faults' names: for each NAME, ``NAME_ms`` and
            ``NAME_s`` are accepted and both give ``NAME_s`` in seconds.
        numbers: Further keys taken as they are (e.g. ``drift_ppm``).

    Raises:
        ValueError: Not KEY=VALUE, an empty item (``"nack=0.1,"``), a value
            that is not a finite number, an unknown key (the message lists the
            known ones), a time outside 0-:data:`MAX_EXTRA_S` or a key given
            twice. A blank ``spec`` is no faults.
    """
    durations = (duration,) if isinstance(duration, str) else duration
    known = (*rates, *(f"{d}{unit}" for d in durations for unit in ("_ms", "_s")), *numbers)
    durations_s = {f"{d}_s" for d in durations}
    kwargs: dict[str, float] = {}
    for item in fault_items(spec):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep:
            raise ValueError(f"fault '{item}': expected KEY=VALUE")
        try:
            number = float(value)
        except ValueError as e:
            raise ValueError(f"fault '{key}': '{value}' is not a number") from e
        if not math.isfinite(number):
            raise ValueError(f"fault '{key}': {value} must be finite")
        if key not in known:
            raise ValueError(f"unknown fault '{key}'; expected {', '.join(known)}")
        given = key
        if key.endswith("_ms") and key[: -len("_ms")] in durations:
            key, number = f"{key[: -len('_ms')]}_s", number / 1000.0
        if key in durations_s and number < 0:
            raise ValueError(f"fault '{given}': {value} must be >= 0 (an extra time)")
        if key in durations_s and number > MAX_EXTRA_S:
            most = f"{MAX_EXTRA_S * 1000:g} ms" if given.endswith("_ms") else f"{MAX_EXTRA_S:g} s"
            raise ValueError(f"fault '{given}': {value.strip()} must be within 0-{most}{_WHY_EXTRA}")
        if key in kwargs:
            stem = key.removesuffix("_s")
            raise ValueError(f"fault '{given}' given twice (counting {stem}_ms and {stem}_s as one)")
        kwargs[key] = number
    return kwargs


class EmulatedI2CBus:
    """Routes transfers to :class:`JointFirmware` devices by 7-bit address.

    Args:
        devices: Address to firmware.
        faults: Faults to inject (none by default).
        clock: Clock that transactions advance; defaults to the first
            device's clock.
        record: Keep every transaction in :attr:`history`.
        clock_hz: Bus clock, Hz: every transaction then takes its wire time
            (:func:`~bioscara_gym.hardware.i2c_timing.wire_time_s`; the
            ``emulated`` backend passes the configuration's ``i2c_clock_hz``).
            ``None``: transactions take only the plan's latency and jitter.
        timing: What a transaction costs beyond its bits: the host's call and
            the joint's handler (the configuration's ``bus_timing``); default
            none.

    A transaction advances the clock by the plan's latency and jitter and
    the wire time up to the repeated START's address byte, lets the device
    handle it, then advances by the reply's bits and the STOP; a NACK takes
    START, address and STOP. An absent address raises
    ``OSError(EREMOTEIO)``, as Linux i2c-dev does when no device
    acknowledges it.
    """

    def __init__(
        self,
        devices: Mapping[int, JointFirmware],
        faults: FaultPlan | None = None,
        clock: Clock | None = None,
        record: bool = False,
        clock_hz: float | None = None,
        timing: TransactionTiming = WIRE_ONLY,
    ) -> None:
        """Attach the devices.

        Raises:
            ValueError: A device address outside 0x03-0x77, or a bus clock
                that is not a number > 0.
        """
        for address in devices:
            if not I2C_ADDRESS_MIN <= address <= I2C_ADDRESS_MAX:
                raise ValueError(
                    f"device address {address:#04x} is outside {I2C_ADDRESS_MIN:#04x}-{I2C_ADDRESS_MAX:#04x}"
                )
        self.devices = dict(devices)
        self.faults = faults or FaultPlan()
        self.faults.check_for(I2C_FAULTS)
        self._rng = np.random.default_rng(self.faults.seed)
        if clock is None and self.devices:
            clock = next(iter(self.devices.values())).clock
        self.clock = clock
        self.clock_hz = None if clock_hz is None else check_clock_hz(clock_hz)
        self.timing = timing
        self._phases: dict[tuple[int, int, int], tuple[float, float]] = {}
        self.transactions = 0
        self.closed = False
        #: With ``record``: every transaction as ``(time, address, bytes
        #: written, read length)``, the time taken before any latency fault.
        self.history: list[tuple[float, int, bytes, int]] | None = [] if record else None

    def _error(self, address: int) -> OSError:
        return OSError(errno.EREMOTEIO, f"{os.strerror(errno.EREMOTEIO)} (address {address:#04x})")

    def _draw(self, rate: float) -> bool:
        return rate > 0.0 and self._rng.random() < rate

    def _wire(self, write_len: int, read_len: int, reg: int) -> tuple[float, float]:
        """Time before the device's handler and after it, s: wire, host call and handler."""
        key = (write_len, read_len, reg)
        phases = self._phases.get(key)
        if phases is None:
            phases = self._phases[key] = self.timing.phases_s(write_len, read_len, self.clock_hz, reg)
        return phases

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """One combined write-then-read transaction (see ``I2CBus``)."""
        if self.closed:
            raise OSError(errno.EBADF, "emulated bus is closed")
        index = self.transactions
        self.transactions += 1
        if self.history is not None:
            self.history.append((self.clock.now() if self.clock else 0.0, address, bytes(data), read_len))
        plan = self.faults
        scheduled = plan.schedule.get(index)
        extra = plan.latency_s
        if scheduled is Fault.LATENCY:
            extra += max(plan.latency_s, 0.001)
        if plan.jitter_s:
            extra += plan.jitter_s * float(self._rng.random())
        clock = self.clock
        device = self.devices.get(address)
        if device is None or scheduled is Fault.NACK or self._draw(plan.nack):
            if clock is not None:
                clock.sleep(extra + (nack_time_s(self.clock_hz) if self.clock_hz else 0.0))
            raise self._error(address)
        reg = data[0] if data else getattr(device, "last_register", 0)
        before, after = self._wire(len(data), read_len, reg)
        if clock is not None:
            clock.sleep(extra + before)
        reply = bytearray(device.transfer(bytes(data), read_len))
        if clock is not None and after:
            clock.sleep(after)
        if (scheduled is Fault.SHORT_READ or self._draw(plan.short_read)) and reply:
            return bytes(reply[: int(self._rng.integers(0, len(reply)))])
        if (scheduled is Fault.CORRUPT or self._draw(plan.corrupt)) and reply:
            i = int(self._rng.integers(0, len(reply)))
            reply[i] ^= 1 << int(self._rng.integers(0, 8))
        return bytes(reply)

    def close(self) -> None:
        """Mark the bus closed; later transfers raise ``OSError(EBADF)``."""
        self.closed = True

    def update(self) -> None:
        """Let every device's main loop catch up with the clock."""
        for device in self.devices.values():
            device.update()
