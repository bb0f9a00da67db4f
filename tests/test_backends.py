"""Backends: joints, gripper and clock bundled by name (``bioscara_gym.hardware.backends``).

The ``i2c`` backend is built without hardware: a scripted bus at the byte
boundary (:class:`conftest.ScriptedBus`) and a sysfs PWM tree under
``tmp_path``; its wall clock is replaced by a fake that records the sleeps.
"""

from __future__ import annotations

import dataclasses
import re
import struct
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import ARM_BACKENDS, ScriptedBus
from rigs import sitl_source

from bioscara_gym.hardware import backends
from bioscara_gym.hardware.arm import Arm, Lifecycle
from bioscara_gym.hardware.backends import (
    BACKENDS,
    Backend,
    EmulatedBackend,
    I2CBackend,
    default_state_dir,
    make_backend,
)
from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.errors import AlreadyInitializedError, ConfigError, InvalidArgumentError
from bioscara_gym.hardware.gripper import BaseGripper, Gripper, MockGripper
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.registers import ACK, TICK_S, Flag, Reg
from bioscara_gym.hardware.sim import SimClock, SimGripper, SimJoint
from bioscara_gym.hardware.stats import CommStats

MakeBackend = Callable[..., Backend]
NAMES = ("j1", "j2", "j3", "j4")
ADDRESSES = (0x11, 0x12, 0x13, 0x14)
CONFIG = load_config()


class FakeWallClock:
    """A wall clock that records sleeps; ``work(dt)`` is time the control loop spends."""

    def __init__(self, start: float = 1000.0) -> None:
        self.t = start
        self.sleeps: list[float] = []

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        if dt > 0:
            self.t += dt

    def work(self, dt: float) -> None:
        self.t += dt


@pytest.fixture
def wall_clock(monkeypatch: pytest.MonkeyPatch) -> FakeWallClock:
    """The clock every ``i2c`` backend built from now on uses instead of the wall clock."""
    clock = FakeWallClock()
    monkeypatch.setattr(backends, "WallClock", lambda: clock)
    return clock


@pytest.fixture
def i2c_backend(
    scripted_bus: ScriptedBus, pwm_tree: Path, gripper_state_file: Path, wall_clock: FakeWallClock
) -> I2CBackend:
    """The ``i2c`` backend over :func:`scripted_bus` and :func:`pwm_tree`, on :func:`wall_clock`."""
    backend = make_backend("i2c", bus=scripted_bus, sysfs_root=pwm_tree, state_file=gripper_state_file)
    assert isinstance(backend, I2CBackend)
    return backend


def reply(flags: Flag, fmt: str | None = None, value: float | int = 0) -> bytes:
    """A joint's reply: the payload (if ``fmt``) then the flags byte."""
    payload = struct.pack(fmt, value) if fmt else b""
    return payload + bytes([int(flags)])


# ------------------------------------------------------------- make_backend

JOINT_CLASSES = {"sim": SimJoint, "mock": MockJoint, "emulated": Joint, "i2c": Joint, "sitl": Joint}
GRIPPER_CLASSES = {
    "sim": SimGripper,
    "mock": MockGripper,
    "emulated": SimGripper,
    "i2c": Gripper,
    "sitl": SimGripper,
}


@pytest.fixture(params=BACKENDS)
def any_backend(
    request: pytest.FixtureRequest,
    make_arm_backend: MakeBackend,
    scripted_bus: ScriptedBus,
    pwm_tree: Path,
    wall_clock: FakeWallClock,
) -> Backend:
    """Every backend by name; ``i2c`` over a scripted bus and a fake sysfs tree."""
    if request.param == "i2c":
        return make_arm_backend("i2c", bus=scripted_bus, sysfs_root=pwm_tree)
    if request.param == "sitl":
        return make_arm_backend("sitl", firmware=sitl_source())
    return make_arm_backend(request.param)


def test_backend_names_are_sim_mock_emulated_i2c_sitl() -> None:
    assert BACKENDS == ("sim", "mock", "emulated", "i2c", "sitl")


def test_make_backend_builds_joints_j1_to_j4_and_a_gripper(any_backend: Backend) -> None:
    assert tuple(any_backend.joints) == NAMES
    assert all(isinstance(j, BaseJoint) for j in any_backend.joints.values())
    assert isinstance(any_backend.gripper, BaseGripper)


def test_make_backend_builds_the_backends_own_parts(any_backend: Backend) -> None:
    name = any_backend.name
    assert all(type(j) is JOINT_CLASSES[name] for j in any_backend.joints.values())
    assert type(any_backend.gripper) is GRIPPER_CLASSES[name]


def test_make_backend_joints_follow_the_configuration(any_backend: Backend) -> None:
    for name, joint in any_backend.joints.items():
        cfg = CONFIG.joint(name)
        assert (joint.name, joint.reduction, joint.min, joint.max) == (name, cfg.reduction, cfg.min, cfg.max)


def test_make_backend_uses_the_packaged_configuration_by_default() -> None:
    assert make_backend("mock").config == CONFIG


def test_make_backend_passes_the_state_file_to_the_gripper(
    make_arm_backend: MakeBackend, tmp_path: Path
) -> None:
    path = tmp_path / "width.json"
    assert make_arm_backend("mock", state_file=path).gripper.state_file == path


@pytest.mark.parametrize("name", ARM_BACKENDS)
def test_gripper_width_is_not_kept_unless_a_state_file_is_given(name: str) -> None:
    assert make_backend(name).gripper.state_file is None


@pytest.mark.parametrize("name", ARM_BACKENDS)
def test_gripper_state_file_from_the_configuration_is_used(name: str, tmp_path: Path) -> None:
    path = tmp_path / "width.json"
    config = dataclasses.replace(CONFIG, gripper=dataclasses.replace(CONFIG.gripper, state_file=str(path)))
    assert make_backend(name, config).gripper.state_file == path


def test_unknown_backend_name_is_refused_listing_the_names() -> None:
    with pytest.raises(ValueError, match="unknown backend 'real'; expected one of sim, mock, emulated, i2c"):
        make_backend("real")


def test_default_state_dir_follows_xdg_state_home(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert default_state_dir() == tmp_path / "bioscara"


def test_default_state_dir_falls_back_to_local_state(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("XDG_STATE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert default_state_dir() == tmp_path / ".local" / "state" / "bioscara"


# ---------------------------------------------------------------------- i2c


def test_i2c_backend_builds_without_touching_the_bus(
    i2c_backend: I2CBackend, scripted_bus: ScriptedBus
) -> None:
    assert i2c_backend.bus is scripted_bus
    assert scripted_bus.log == []
    assert [j.address for j in i2c_backend.joints.values()] == list(ADDRESSES)  # type: ignore[attr-defined]


def test_i2c_gripper_uses_the_sysfs_tree(i2c_backend: I2CBackend, pwm_tree: Path) -> None:
    assert i2c_backend.gripper.pwm_path == pwm_tree / "pwmchip0" / "pwm0"  # type: ignore[attr-defined]


def test_i2c_arm_configures_and_activates_over_the_bus(
    i2c_backend: I2CBackend, scripted_bus: ScriptedBus, pwm_tree: Path
) -> None:
    powered_up, enabled = Flag.NOT_HOMED | Flag.NOT_ENABLED, Flag.NOT_HOMED
    pings = [reply(powered_up, "<B", ACK) for _ in NAMES]
    reads = [reply(f, "<f", 0.0) for f in (powered_up, enabled) for _ in NAMES for _ in range(2)]
    setup = [reply(enabled) for _ in NAMES for _ in range(4)]
    scripted_bus.queue(*pings, *reads[:8], *setup, *reads[8:])
    arm = Arm(i2c_backend)
    arm.configure()
    arm.activate()
    assert arm.state is Lifecycle.ACTIVE
    sent = [(address, data[0]) for address, data, _ in scripted_bus.log]
    assert sent[:4] == [(a, Reg.PING) for a in ADDRESSES]
    assert sent[4:12] == [(a, r) for a in ADDRESSES for r in (Reg.ANGLEMOVED, Reg.GETENCODERRPM)]
    assert sent[12:28] == [
        (a, r)
        for a in ADDRESSES
        for r in (Reg.SETUP, Reg.ENABLESTALLGUARD, Reg.SETMAXVELOCITY, Reg.SETMAXACCELERATION)
    ]
    pwm = pwm_tree / "pwmchip0" / "pwm0"
    assert int((pwm / "period").read_text()) == 20_000_000
    assert int((pwm / "enable").read_text()) == 1


def test_i2c_backend_close_closes_the_bus(i2c_backend: I2CBackend, scripted_bus: ScriptedBus) -> None:
    with i2c_backend:
        pass
    assert scripted_bus.closed


def test_i2c_step_waits_out_the_rest_of_the_period(
    i2c_backend: I2CBackend, wall_clock: FakeWallClock
) -> None:
    start = wall_clock.now()
    wall_clock.work(0.01)
    i2c_backend.step(0.04)
    assert wall_clock.sleeps == [pytest.approx(0.03)]
    assert wall_clock.now() == pytest.approx(start + 0.04)


def test_i2c_step_keeps_a_fixed_rate_without_drift(
    i2c_backend: I2CBackend, wall_clock: FakeWallClock
) -> None:
    start = wall_clock.now()
    for _ in range(100):
        wall_clock.work(0.013)
        i2c_backend.step(0.04)
    assert wall_clock.now() == pytest.approx(start + 4.0, abs=1e-9)
    assert wall_clock.sleeps == [pytest.approx(0.027)] * 100


def test_i2c_step_after_an_overrun_does_not_sleep(i2c_backend: I2CBackend, wall_clock: FakeWallClock) -> None:
    wall_clock.work(0.1)
    i2c_backend.step(0.04)
    assert wall_clock.sleeps == []


def test_i2c_step_after_an_overrun_restarts_the_schedule_from_now(
    i2c_backend: I2CBackend, wall_clock: FakeWallClock
) -> None:
    wall_clock.work(0.1)  # overran two and a half periods
    i2c_backend.step(0.04)
    late = wall_clock.now()
    wall_clock.work(0.01)
    i2c_backend.step(0.04)
    assert wall_clock.sleeps == [pytest.approx(0.03)]  # no burst of catch-up steps
    assert wall_clock.now() == pytest.approx(late + 0.04)


# ---------------------------------------------------------------- comm_stats


@pytest.mark.parametrize("name", ["mock", "sim"])
def test_comm_stats_are_empty_without_a_bus(make_arm_backend: MakeBackend, name: str) -> None:
    backend = make_arm_backend(name)
    Arm(backend).configure()
    assert backend.comm_stats() == {}


def test_comm_stats_count_each_joints_transactions_on_the_emulated_bus(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    Arm(backend).configure()
    stats = backend.comm_stats()
    assert tuple(stats) == NAMES
    assert all(isinstance(s, CommStats) for s in stats.values())
    for name, address in zip(NAMES, ADDRESSES, strict=True):
        assert stats[name].transactions == backend.devices[address].transactions > 0
        assert stats[name].errors == 0


def test_comm_stats_are_per_joint_on_the_i2c_backend(i2c_backend: I2CBackend) -> None:
    stats = i2c_backend.comm_stats()
    assert tuple(stats) == NAMES
    assert all(s.transactions == 0 for s in stats.values())


# ---------------------------------------------------------------- simulation


def count_ticks(backend: Backend, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the firmware ticks of the simulated arm's first core: ``[n]``."""
    core = backend.sim.cores["j1"]  # type: ignore[union-attr]
    ticks = [0]
    tick = core.tick

    def counting_tick() -> None:
        ticks[0] += 1
        tick()

    monkeypatch.setattr(core, "tick", counting_tick)
    return ticks


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_sim_step_advances_simulated_time_by_exactly_dt(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    backend = make_arm_backend(name)
    ticks = count_ticks(backend, monkeypatch)
    start = backend.clock.now()
    backend.step(0.04)
    assert backend.clock.now() - start == pytest.approx(0.04, abs=1e-12)
    assert ticks == [4]


def test_sim_step_carries_a_part_tick_to_the_next_step(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend = make_arm_backend("sim")
    ticks = count_ticks(backend, monkeypatch)
    backend.step(0.015)
    assert ticks == [1]
    backend.step(0.015)
    assert ticks == [3]
    assert backend.clock.now() == pytest.approx(3 * TICK_S, abs=1e-12)


def test_sim_time_after_many_steps_does_not_drift(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("sim")
    for _ in range(250):
        backend.step(0.04)
    assert backend.clock.now() == pytest.approx(10.0, abs=1e-9)


def test_sim_clock_sleep_advances_physics(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend = make_arm_backend("sim")
    assert isinstance(backend.clock, SimClock)
    ticks = count_ticks(backend, monkeypatch)
    backend.clock.sleep(0.1)
    assert backend.clock.now() == pytest.approx(0.1, abs=1e-12)
    assert backend.sim.time == backend.clock.now()  # type: ignore[union-attr]
    assert ticks == [10]


def test_blocking_homing_on_the_sim_clock_moves_the_arm_to_its_end_stop(
    make_arm_backend: MakeBackend,
) -> None:
    backend = make_arm_backend("sim")
    j1, cfg = backend.joints["j1"], CONFIG.joint("j1")
    true_start = backend.sim.joint_positions()[0]  # type: ignore[union-attr]
    j1.init()
    j1.enable(cfg.drive_current, cfg.hold_current)
    j1.home(cfg.homing.speed, cfg.homing.threshold, cfg.homing.current)  # waits with clock.sleep
    assert backend.clock.now() > 0.5
    assert true_start < cfg.max - 0.05
    assert backend.sim.joint_positions()[0] == pytest.approx(cfg.max, abs=2e-3)  # type: ignore[union-attr]
    assert j1.get_position() == pytest.approx(cfg.max, abs=2e-3)


def test_mock_backend_step_advances_its_manual_clock(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("mock")
    backend.step(0.25)
    assert backend.clock.now() == 0.25


# ----------------------------------------------------------- device flags
@pytest.mark.parametrize("name", ["sim", "emulated", "mock"])
def test_device_flags_are_the_devices_own_at_power_up(make_arm_backend: Callable, name: str) -> None:
    backend = make_arm_backend(name)
    assert backend.device_flags("j2") == Flag.NOT_HOMED | Flag.NOT_ENABLED  # 0b00001100 at power-up


def test_device_flags_follow_the_emulated_firmware_not_the_last_reply(make_arm_backend: Callable) -> None:
    backend = make_arm_backend("emulated")
    joint = backend.joints["j1"]
    joint.init()
    joint.enable(20, 20)  # SETUP clears NOT_ENABLED in the firmware and in the reply
    assert backend.device_flags("j1") == Flag.NOT_HOMED
    backend.sim.cores["j1"].flags |= int(Flag.STALL)  # the device changed; no reply has said so
    assert backend.device_flags("j1") == Flag.NOT_HOMED | Flag.STALL
    assert joint.flags == Flag.NOT_HOMED


def test_device_flags_cannot_be_seen_on_hardware(i2c_backend: I2CBackend) -> None:
    assert i2c_backend.device_flags("j1") is None


# ------------------------------------------------------------- guarded state
@pytest.mark.parametrize("name", ARM_BACKENDS)
def test_init_twice_is_refused_with_a_named_error_and_sends_nothing(
    make_arm_backend: MakeBackend, name: str
) -> None:
    backend = make_arm_backend(name)
    joint = backend.joints["j1"]
    joint.init()
    before = backend.comm_stats().get("j1")
    sent = None if before is None else before.total_transactions
    with pytest.raises(AlreadyInitializedError, match=r"^j1: joint already initialized; call deinit\(\)"):
        joint.init()
    after = backend.comm_stats().get("j1")
    assert (None if after is None else after.total_transactions) == sent
    assert joint.initialized  # still usable
    joint.get_flags()
    joint.deinit()
    joint.init()  # after deinit() it connects again
    assert joint.initialized


@pytest.mark.parametrize(
    ("name", "options", "message"),
    [
        (
            "emulated",
            {"bogus": 1},
            "the emulated backend takes no option bogus; its options: faults, i2c_clock_hz, initial_qpos, "
            "model_path, record, retries, seed, state_file",
        ),
        (
            "sim",
            {"faults": None, "retries": 1},
            "the sim backend takes no option faults, retries; its options: i2c_clock_hz, initial_qpos, "
            "model_path, seed, state_file",
        ),
    ],
)
def test_an_option_the_backend_does_not_take_is_named_with_those_it_takes(
    name: str, options: dict, message: str
) -> None:
    # Seen (a hostile test of the env API): "TypeError: ArmSim.__init__() got an unexpected keyword
    # argument 'bogus'", from gym.make(..., backend_options={"bogus": 1}).
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        make_backend(name, **options)


def test_the_options_a_backend_passes_on_are_taken() -> None:
    backend = make_backend("sim", seed=3, initial_qpos={"j1": 0.5})  # ArmSim's, through SimBackend's **kwargs
    try:
        assert backend.sim.data.qpos[backend.sim.model.joint("j1").qposadr[0]] == pytest.approx(0.5)
    finally:
        backend.close()


def test_the_simulated_servo_refuses_the_pulses_the_real_driver_refuses() -> None:
    # Seen (a hostile test): the emulated gripper went to -0.5 m where mock and the real driver refuse.
    backend = make_backend("sim")
    try:
        gripper = backend.gripper
        gripper.init()
        with pytest.raises(InvalidArgumentError, match=r"^servo angle -1860 deg gives a -8833\.33 us pulse"):
            gripper.set_servo_position(-1860.0)
        gripper.set_servo_position(-60.0)  # the packaged 4 cm: a 1166.67 us pulse
    finally:
        backend.close()


@pytest.mark.parametrize("backend", ["sim", "emulated"])
def test_a_configuration_naming_joints_the_model_has_not_is_one_line(tmp_path: Path, backend: str) -> None:
    # Seen (a hostile test): KeyError: "Invalid name 'shoulder'" from deep in the MuJoCo arm.
    default = Path(backends.__file__).parent / "default_config.yaml"
    path = tmp_path / "shoulder.yaml"
    path.write_text(re.sub(r"\bj1\b", "shoulder", default.read_text()))
    message = (
        "joint 'shoulder': the simulated arm's joints are j1, j2, j3, j4 (assets/scene.xml); "
        "a configuration for it names those"
    )
    with pytest.raises(ConfigError, match=f"^{re.escape(message)}$"):
        make_backend(backend, str(path))


def test_a_configuration_whose_joint_type_is_not_the_models_is_one_line(tmp_path: Path) -> None:
    # Seen (a hostile test): j2 as revolute "homed at max: +0.3380 rad".
    text = (Path(backends.__file__).parent / "default_config.yaml").read_text()
    j2 = text.index("name: j2")
    at = text.index("joint_type: prismatic", j2)
    path = tmp_path / "revolute_j2.yaml"
    path.write_text(text[:at] + "joint_type: revolute " + text[at + len("joint_type: prismatic") :])
    message = "joint j2: joint_type revolute where the simulated arm's is prismatic (assets/scene.xml)"
    with pytest.raises(ConfigError, match=f"^{re.escape(message)}$"):
        make_backend("sim", str(path))
