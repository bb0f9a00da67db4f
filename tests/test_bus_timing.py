"""Bus timing: the I2C wire time, latency, jitter and drift, and one deadline scheduler on every backend.

Expected wire times are counted by hand from the I2C specification (NXP
UM10204), one clock period per bit (docs/protocol.md, "Wire time"):

- ANGLEMOVED writes ``[REG]`` and reads 4 payload bytes and the flags:
  START 1 + address/W and ACK 9 + REG 9 + repeated START 1 + address/R 9 +
  5 bytes × 9 + STOP 1 = 75 periods; the joint's handler runs after the
  first 29.
- SETRPM writes ``[REG]`` and a float32, reads the flags: 1 + 9 + 5 × 9 + 1
  + 9 + 9 + 1 = 75 periods; handler after 1 + 9 + 45 + 1 + 9 = 65.
- PING reads 'O' and the flags: 1 + 9 + 9 + 1 + 9 + 2 × 9 + 1 = 48 periods.

75 periods are 750 us at 100 kHz and 187.5 us at 400 kHz.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from rich.console import Console

from bioscara_gym.cli import main
from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import Backend, make_backend
from bioscara_gym.hardware.clock import DeadlineScheduler, ManualClock
from bioscara_gym.hardware.config import config_from_dict, config_to_dict, load_config
from bioscara_gym.hardware.emulated_bus import RS485_FAULTS, EmulatedI2CBus, FaultPlan
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.i2c_timing import wire_time_s
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import Reg

CONFIG = load_config()
J1 = CONFIG.joint("j1")
PERIOD_S = 0.04

ANGLEMOVED = (bytes([Reg.ANGLEMOVED]), 5)
SETRPM = (bytes([Reg.SETRPM]) + struct.pack("<f", 0.0), 1)


def bus_on_manual_clock(faults: FaultPlan | None = None, clock_hz: float | None = 100_000) -> EmulatedI2CBus:
    """An emulated bus with one joint (j1's address) on a manual clock at t = 0."""
    clock = ManualClock()
    firmware = JointFirmware(KinematicStepper(0.0), clock)
    return EmulatedI2CBus({J1.address: firmware}, faults, clock=clock, clock_hz=clock_hz)


def ready_arm(backend: Backend) -> Arm:
    """The arm on ``backend`` configured, activated, homed and in velocity mode at 0."""
    arm = Arm(backend)
    arm.bring_up("velocity")
    for name in arm.names:
        arm.set_command(name, 0.0)
    return arm


def cycle_starts(arm: Arm, cycles: int) -> np.ndarray:
    """Backend time at the start of each of ``cycles`` control cycles (write, step, read)."""
    starts = []
    for _ in range(cycles):
        starts.append(arm.backend.clock.now())
        arm.cycle(PERIOD_S)
    return np.array(starts)


# ---------------------------------------------------------------- wire time


@pytest.mark.parametrize(("clock_hz", "expected_s"), [(100_000, 750e-6), (400_000, 187.5e-6)])
@pytest.mark.parametrize("frame", [ANGLEMOVED, SETRPM], ids=["ANGLEMOVED", "SETRPM"])
def test_wire_time_of_a_transaction_counts_75_bit_periods(
    frame: tuple[bytes, int], clock_hz: int, expected_s: float
) -> None:
    data, read_len = frame
    assert wire_time_s(len(data), read_len, clock_hz) == pytest.approx(expected_s, rel=1e-12)


@pytest.mark.parametrize("frame", [ANGLEMOVED, SETRPM], ids=["ANGLEMOVED", "SETRPM"])
def test_emulated_bus_advances_the_clock_by_wire_time_plus_latency(frame: tuple[bytes, int]) -> None:
    bus = bus_on_manual_clock(FaultPlan(latency_s=0.002))
    data, read_len = frame
    bus.transfer(J1.address, data, read_len)
    assert bus.clock.now() == pytest.approx(0.002 + 750e-6, abs=1e-12)


@pytest.mark.parametrize(
    ("frame", "handler_bits"), [(ANGLEMOVED, 29), (SETRPM, 65)], ids=["ANGLEMOVED", "SETRPM"]
)
def test_the_joint_handles_a_transaction_at_the_repeated_starts_address(
    frame: tuple[bytes, int], handler_bits: int
) -> None:
    bus = bus_on_manual_clock(FaultPlan(latency_s=0.001))
    data, read_len = frame
    bus.transfer(J1.address, data, read_len)
    assert bus.devices[J1.address].core.last_rx == pytest.approx(0.001 + handler_bits * 1e-5, abs=1e-12)


def test_a_nack_takes_start_address_and_stop() -> None:
    bus = bus_on_manual_clock()
    with pytest.raises(OSError):
        bus.transfer(0x20, *ANGLEMOVED)
    assert bus.clock.now() == pytest.approx(11e-5, abs=1e-12)  # 1 + 9 + 1 periods at 100 kHz


def test_the_bare_bus_takes_no_wire_time_without_a_clock() -> None:
    bus = bus_on_manual_clock(clock_hz=None)
    bus.transfer(J1.address, *ANGLEMOVED)
    assert bus.clock.now() == 0.0


def test_jitter_is_a_seeded_uniform_extra_time_per_transaction() -> None:
    def extras(seed: int) -> np.ndarray:
        bus = bus_on_manual_clock(FaultPlan(latency_s=0.002, jitter_s=0.003, seed=seed))
        times = []
        for _ in range(200):
            t = bus.clock.now()
            bus.transfer(J1.address, *ANGLEMOVED)
            times.append(bus.clock.now() - t - 0.002 - 750e-6)
        return np.array(times)

    first = extras(seed=5)
    assert first.min() >= -1e-12 and first.max() <= 0.003 + 1e-12
    assert first.mean() == pytest.approx(0.0015, abs=0.0003)  # uniform in [0, 3 ms]
    assert first.max() - first.min() > 0.0025
    np.testing.assert_array_equal(first, extras(seed=5))
    assert not np.array_equal(first, extras(seed=6))


# ------------------------------------------------ sim backend: same staleness


def test_sim_readings_are_as_old_as_on_the_emulated_bus() -> None:
    backends = {name: make_backend(name) for name in ("sim", "emulated")}
    seen: dict[str, list[tuple[float, float]]] = {name: [] for name in backends}
    for name, backend in backends.items():
        j1 = backend.joints["j1"]
        core = backend.sim.cores["j1"]  # type: ignore[union-attr]
        for call in (
            j1.init,
            j1.get_position,
            j1.get_velocity,
            lambda j1=j1: j1.enable(J1.drive_current, J1.hold_current),
            lambda j1=j1: j1.set_max_velocity(J1.max_velocity),
            j1.get_flags,
            j1.get_position,
        ):
            call()
            seen[name].append((backend.clock.now(), core.last_rx))
    np.testing.assert_allclose(seen["sim"], seen["emulated"], rtol=0, atol=1e-12)
    first_read = seen["sim"][1][0] - seen["sim"][0][0]
    assert first_read == pytest.approx(750e-6, abs=1e-12)  # ANGLEMOVED at the default 100 kHz


def test_sim_backend_at_400_khz_takes_a_quarter_of_the_time() -> None:
    backend = make_backend("sim", i2c_clock_hz=400_000)
    j1 = backend.joints["j1"]
    j1.init()
    t = backend.clock.now()
    j1.get_position()
    assert backend.clock.now() - t == pytest.approx(187.5e-6, abs=1e-12)


def test_sim_clock_counts_the_part_of_a_tick_not_yet_run() -> None:
    backend = make_backend("sim")
    backend.clock.sleep(0.0042)
    assert backend.clock.now() == pytest.approx(0.0042, abs=1e-12)
    assert backend.sim.data.time == 0.0  # type: ignore[union-attr]  # the 10 ms tick has not run


# ----------------------------------------------------------- the deadlines


def test_scheduler_returns_one_period_after_the_previous_deadline() -> None:
    clock = ManualClock(1000.0)
    schedule = DeadlineScheduler(clock)
    for k in range(1, 101):
        clock.sleep(0.013)  # the cycle's own work
        assert schedule.wait(PERIOD_S)
        assert clock.now() == pytest.approx(1000.0 + k * PERIOD_S, abs=1e-9)
    assert schedule.overruns == 0


def test_a_cycle_longer_than_the_period_is_an_overrun_and_the_schedule_restarts() -> None:
    clock = ManualClock()
    schedule = DeadlineScheduler(clock)
    clock.sleep(0.1)  # two and a half periods of work
    assert not schedule.wait(PERIOD_S)
    assert clock.now() == pytest.approx(0.1)  # no wait
    assert schedule.overruns == 1
    clock.sleep(0.01)
    assert schedule.wait(PERIOD_S)
    assert clock.now() == pytest.approx(0.1 + PERIOD_S)  # one period after the restart, no catch-up


def test_emulated_cycle_whose_bus_time_exceeds_the_period_is_an_overrun() -> None:
    backend = make_backend("emulated", faults=FaultPlan(latency_s=0.005))
    arm = ready_arm(backend)
    arm.cycle(PERIOD_S)
    overruns = backend.schedule.overruns
    arm.write()  # 4 commands
    arm.read()  # 8 reads: 12 x (5 + 0.75) ms = 69 ms > 40 ms
    late = backend.clock.now()
    backend.step(PERIOD_S)
    assert backend.clock.now() == late  # no time left to wait for
    assert backend.schedule.overruns == overruns + 1
    backend.bus.faults = FaultPlan()  # type: ignore[attr-defined]
    arm.write()  # 3 ms
    backend.step(PERIOD_S)
    assert backend.clock.now() == pytest.approx(late + PERIOD_S, abs=1e-9)  # restarted from the overrun


def test_emulated_loop_with_half_a_millisecond_latency_keeps_40_ms_periods() -> None:
    backend = make_backend("emulated", faults=FaultPlan(latency_s=0.0005))
    arm = ready_arm(backend)
    arm.cycle(PERIOD_S)
    overruns = backend.schedule.overruns
    periods = np.diff(cycle_starts(arm, 101))
    np.testing.assert_allclose(periods, PERIOD_S, rtol=0, atol=1e-9)
    assert backend.schedule.overruns == overruns


@pytest.mark.parametrize("name", ["sim", "emulated", "mock"])
def test_every_simulated_backend_steps_on_the_same_deadlines(name: str) -> None:
    backend = make_backend(name)
    arm = ready_arm(backend)
    arm.cycle(PERIOD_S)
    np.testing.assert_allclose(np.diff(cycle_starts(arm, 21)), PERIOD_S, rtol=0, atol=1e-9)


def test_drift_ppm_scales_the_period_on_the_emulated_backend() -> None:
    backend = make_backend("emulated", faults=FaultPlan(drift_ppm=500))
    backend.step(PERIOD_S)
    start = backend.clock.now()
    backend.step(PERIOD_S)
    assert backend.clock.now() - start == pytest.approx(0.04002, abs=1e-12)  # 40 ms x (1 + 500e-6)


def test_deploy_with_2_ms_latency_and_3_ms_jitter_has_no_deadman_trip(tmp_path: Path) -> None:
    from bioscara_gym.training.deploy import DeployArgs, Deployment

    log = tmp_path / "run.jsonl"
    args = DeployArgs(
        expert=True,
        env="Bioscara-Reach-v0",
        backend="emulated",
        faults="latency_ms=2,jitter_ms=3",
        episodes=2,
        log=log,
        state_file=tmp_path / "gripper.json",
    )
    summary = Deployment(args, console=Console(quiet=True)).run()
    assert summary["stop_reason"] == "completed"
    cycles = [r for r in map(json.loads, log.read_text().splitlines()) if r["type"] == "cycle"]
    assert len(cycles) == 100
    assert max(c["silence_s"] for c in cycles) < 0.05


# -------------------------------------------------------- faults and clock


def test_fault_spec_takes_jitter_and_drift() -> None:
    plan = FaultPlan.parse("latency_ms=2,jitter_ms=3,drift_ppm=-20")
    assert plan == FaultPlan(latency_s=0.002, jitter_s=0.003, drift_ppm=-20.0)
    assert plan.period_scale == pytest.approx(0.99998, abs=1e-15)


def test_unknown_fault_name_lists_the_known_ones() -> None:
    known = "nack, short_read, corrupt, latency_ms, latency_s, jitter_ms, jitter_s, drift_ppm"
    with pytest.raises(ValueError, match=rf"^unknown fault 'drop'; expected {known}$"):
        FaultPlan.parse("drop=0.1")


def test_the_dynamixel_fault_spec_still_lists_its_own_keys() -> None:
    with pytest.raises(
        ValueError, match=r"^unknown fault 'nack'; expected drop, corrupt, delay_ms, delay_s$"
    ):
        FaultPlan.parse("nack=0.1", kinds=RS485_FAULTS)
    assert FaultPlan.parse("delay_ms=2", kinds=RS485_FAULTS) == FaultPlan(latency_s=0.002)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("jitter_ms=-1", "fault 'jitter_ms': -1 must be >= 0"),
        ("latency_ms=-0.5", "fault 'latency_ms': -0.5 must be >= 0"),
        ("drift_ppm=-1e6", r"drift_ppm=-1e\+06 must be within ±10000"),
        ("drift_ppm=1e7", r"drift_ppm=1e\+07 must be within ±10000"),
        ("latency_ms=1,latency_s=0.002", "fault 'latency_s' given twice"),
    ]
)
def test_bad_jitter_or_drift_is_refused(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FaultPlan.parse(spec)


@pytest.mark.parametrize("clock_hz", [0, -100_000, math.inf, 1, 9_999, 1_000_001, 1e12])
@pytest.mark.parametrize("where", ["backend", "config", "bus"])
def test_a_bad_i2c_clock_is_refused_in_one_line(where: str, clock_hz: float) -> None:
    with pytest.raises(ValueError, match="i2c_clock_hz") as caught:
        if where == "backend":
            make_backend("emulated", i2c_clock_hz=clock_hz)
        elif where == "config":
            data = config_to_dict(CONFIG)
            data["i2c_clock_hz"] = clock_hz
            config_from_dict(data)
        else:
            bus_on_manual_clock(clock_hz=clock_hz)
    assert "\n" not in str(caught.value)


def test_the_default_bus_clock_is_100_khz() -> None:
    assert CONFIG.i2c_clock_hz == 100_000


# ------------------------------------------------------------------- status


def test_status_prints_the_cycle_bus_budget(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--backend", "mock"]) == 0
    out = capsys.readouterr().out
    # 4 joints x (ANGLEMOVED, GETENCODERRPM, SETRPM), 75 periods each at 100 kHz
    assert "bus time per 25 Hz cycle: 12 transactions, 9.00 ms at 100 kHz = 22.5% of 40 ms" in out


def test_status_budget_follows_the_configured_bus_clock(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = config_to_dict(CONFIG)
    data["i2c_clock_hz"] = 400_000
    path = tmp_path / "fast.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert main(["status", "--backend", "mock", "--config", str(path)]) == 0
    assert "12 transactions, 2.25 ms at 400 kHz = 5.6% of 40 ms" in capsys.readouterr().out
