"""The firmware in the loop: the joint firmware's own source built for the host and run behind the bus.

Expected values come from the firmware source (joint.ino, configuration.h)
and the uStepper S32 library's public source; the SITL tests skip without
``BIOSCARA_FIRMWARE`` (the reason says how to run them).
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from rigs import SITL_SKIP_REASON, run_blocked, sitl_source

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.drive import IDEAL_DRIVE, DriveParams
from bioscara_gym.hardware.errors import SitlError
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import Flag, Reg
from bioscara_gym.hardware.sitl import SitlFirmware, build_firmware, firmware_dir
from bioscara_gym.hardware.sitl.build import CACHE_ENV, FIRMWARE_ENV

#: What the firmware answers a PING with at power-up: ACK 'O', NOTHOMED | NOTENABLED (joint.ino).
POWER_UP_PING = b"O" + bytes([Flag.NOT_HOMED | Flag.NOT_ENABLED])


@pytest.fixture(scope="module")
def source() -> str:
    """The firmware's folder, or skip (``BIOSCARA_FIRMWARE``)."""
    return sitl_source()


def make(source: str, joint: str = "j1", motor: KinematicStepper | None = None, **kw: object) -> SitlFirmware:
    return SitlFirmware(source, joint, motor or KinematicStepper(0.0), ManualClock(), **kw)  # type: ignore[arg-type]


def command(fw: SitlFirmware, reg: Reg, payload: bytes = b"") -> int:
    """One command; the flags byte of its reply."""
    return fw.transfer(bytes([reg]) + payload, 1)[0]


def run(fw: SitlFirmware, seconds: float, poll_s: float = 0.01) -> None:
    """Let ``seconds`` pass, pinging every ``poll_s`` (the deadman stays fed)."""
    for _ in range(round(seconds / poll_s)):
        fw.clock.sleep(poll_s)
        fw.transfer(bytes([Reg.PING]), 2)


def f32(value: float) -> bytes:
    return struct.pack("<f", value)


# ------------------------------------------------------------------ source
def test_no_firmware_source_is_one_line_saying_how_to_give_one(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(FIRMWARE_ENV, raising=False)
    with pytest.raises(SitlError, match=r"^no firmware source: pass --firmware DIR or set BIOSCARA_FIRMWARE"):
        firmware_dir(None)


def test_a_firmware_folder_that_is_not_one_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SitlError, match="not a folder"):
        firmware_dir(tmp_path / "missing")
    with pytest.raises(SitlError, match=r"no \.ino sketch"):
        firmware_dir(tmp_path)


def test_the_skip_reason_says_how_to_run_the_sitl_tests() -> None:
    assert "BIOSCARA_FIRMWARE" in SITL_SKIP_REASON and "Arduino/joint/" in SITL_SKIP_REASON


# ------------------------------------------------------------------- build
def test_no_compiler_is_one_line_saying_what_to_install(
    source: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    tried = r"^no C\+\+ compiler found \(tried g\+\+, c\+\+, clang\+\+\).*install g\+\+"
    with pytest.raises(SitlError, match=tried):
        build_firmware(source, "j1")


def _broken_copy(source: str, tmp_path: Path, extra: str, where: str = "end") -> Path:
    """The firmware copied into ``tmp_path`` (never into the repository) with ``extra`` added to joint.ino."""
    copy = tmp_path / "joint"
    shutil.copytree(source, copy)
    sketch = copy / "joint.ino"
    text = sketch.read_text(encoding="utf-8")
    text = text + extra if where == "end" else text.replace(where, where + extra)
    sketch.write_text(text, encoding="utf-8")
    return copy


def test_a_firmware_that_does_not_build_is_one_line_naming_file_and_line(
    source: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    broken = _broken_copy(source, tmp_path, "\nthis is not C++;\n")
    lines = (broken / "joint.ino").read_text(encoding="utf-8").count("\n")
    with pytest.raises(SitlError) as info:
        build_firmware(broken, "j1")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("the firmware does not build: ")
    assert f"joint.ino:{lines}:" in message


def test_the_build_is_cached_by_source(source: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    first = build_firmware(source, "j2")
    built = first.stat().st_mtime_ns
    assert build_firmware(source, "j2") == first
    assert first.stat().st_mtime_ns == built
    changed = _broken_copy(source, tmp_path, "\n// a comment changes the hash\n")
    assert build_firmware(changed, "j2") != first


def test_two_processes_building_at_once_make_one_library(source: str, tmp_path: Path) -> None:
    code = textwrap.dedent(
        f"""
        from bioscara_gym.hardware.sitl import build_firmware
        print(build_firmware({source!r}, "j3"))
        """
    )
    env = {**os.environ, CACHE_ENV: str(tmp_path / "cache")}
    procs = [
        subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    paths = [p.communicate(timeout=300)[0].strip() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    assert paths[0] == paths[1]
    assert [p.name for p in (tmp_path / "cache").rglob("*.so")] == ["joint_j3.so"]


def test_importing_the_sitl_package_needs_no_compiler() -> None:
    env = {**os.environ, "PATH": "/nonexistent"}
    env.pop("CXX", None)
    done = run_blocked("import bioscara_gym.hardware, bioscara_gym.hardware.sitl; print('ok')", env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok"


# ------------------------------------------------------------------ device
@pytest.mark.parametrize(("joint", "address"), [("j1", 0x11), ("j2", 0x12), ("j3", 0x13), ("j4", 0x14)])
def test_each_joint_joins_the_bus_at_its_configuration_address(source: str, joint: str, address: int) -> None:
    # configuration.h: ADR 0x11 ... 0x14 for J1 ... J4 (the sketch itself defines J1).
    assert make(source, joint).address == address


def test_power_up_answers_ack_not_homed_not_enabled(source: str) -> None:
    assert make(source).transfer(bytes([Reg.PING]), 2) == POWER_UP_PING


def test_setup_checks_the_orientation_before_the_first_transaction(source: str) -> None:
    # setup(): checkOrientation(1) at MAXVEL 10 and MAXACCEL 100 steps/s (configuration.h):
    # the library's check moves 1 degree out and back twice, 0.15 s a move.
    motor = KinematicStepper(10.0)
    fw = make(source, motor=motor)
    assert 0.5 < fw.device_time < 0.7
    assert motor.position_deg == pytest.approx(10.0, abs=360 / 51200)


def test_serial_output_is_kept_when_asked(source: str) -> None:
    fw = make(source, serial=True)
    fw.read_serial()
    fw.transfer(bytes([Reg.PING]), 2)
    assert fw.read_serial() == "Executing PING\n"


def test_deadman_trips_after_more_than_50_ms_of_silence(source: str) -> None:
    fw = make(source)
    command(fw, Reg.SETUP, bytes([20, 20, 0, 0]))
    command(fw, Reg.SETRPM, f32(10.0))
    fw.clock.sleep(0.05)
    assert not fw.transfer(bytes([Reg.PING]), 2)[1] & Flag.NOT_ENABLED
    fw.clock.sleep(0.065)
    fw.update()
    assert fw.flags & Flag.NOT_ENABLED


def test_setrpm_is_not_held_to_the_max_velocity(source: str) -> None:
    # setRPM() writes VMAX = |rpm x rpmToVelocity| whatever setMaxVelocity set
    # (UstepperS32.cpp); the emulator clamps to the max velocity (open, issue #23).
    fw = make(source)
    command(fw, Reg.SETUP, bytes([50, 50, 0, 0]))
    command(fw, Reg.SETMAXVELOCITY, f32(18.0))
    command(fw, Reg.SETMAXACCELERATION, f32(10_000.0))
    command(fw, Reg.SETRPM, f32(10.0))  # 60 deg/s
    run(fw, 0.5)
    start = fw.motor.position_deg
    run(fw, 0.5)
    assert fw.motor.position_deg - start == pytest.approx(30.0, rel=0.01)


def test_max_acceleration_keeps_only_its_low_16_bits(source: str) -> None:
    # 10,000,000 deg/s^2 x 200/360 x 256 x 0.022 = 31,288,888 AMAX units; the
    # library's 16-bit AMAX keeps 31,288,888 mod 65,536 = 28,216 (9,018 deg/s^2).
    fw = make(source)
    command(fw, Reg.SETMAXACCELERATION, f32(10_000_000.0))
    assert fw.state().amax == 28_216


def test_pid_error_of_a_held_rotor_is_one_millisecond_of_travel(source: str) -> None:
    # 60 RPM = 51,200 microsteps/s: 51.2 each millisecond; the closed loop moves the
    # driver's position onto the encoder at every error of 15 or more. (A rotor
    # that is not thrown back at its pole slips: the closed loop's rule alone.)
    errors, _ = _held_rotor_errors(source, DriveParams(kick_accel=0.0), passes=20)
    assert set(errors[2:]) <= {51.0, 52.0}


def test_pole_slips_of_a_held_rotor_show_in_the_encoder(source: str) -> None:
    # The field passes a pole (two full steps, 512 microsteps, then every 1024)
    # every 20 ms at 51.2 microsteps a millisecond; each throws the rotor back,
    # and the firmware's error then exceeds the arm's homing thresholds (25-50)
    # and stall thresholds: the real joints' homing relies on it.
    errors, motor = _held_rotor_errors(source, IDEAL_DRIVE, passes=100)
    assert motor.pole_slips == 5
    assert max(errors) > 200.0
    assert sum(e > 50.0 for e in errors) >= 10


def _held_rotor_errors(source: str, drive: DriveParams, passes: int) -> tuple[list[float], KinematicStepper]:
    """The firmware's PID error each millisecond of a rotor held while its field turns at 60 RPM."""
    motor = KinematicStepper(0.0, drive=drive)
    fw = make(source, motor=motor)
    command(fw, Reg.SETUP, bytes([50, 50, 0, 0]))
    command(fw, Reg.SETMAXACCELERATION, f32(100_000.0))
    command(fw, Reg.SETMAXVELOCITY, f32(1000.0))
    command(fw, Reg.SETRPM, f32(60.0))
    run(fw, 0.1)
    motor.blocked = True
    errors = []
    for _ in range(passes):
        fw.clock.sleep(0.001)
        fw.transfer(bytes([Reg.PING]), 2)
        errors.append(fw.state().pid_error)
    return errors, motor


def test_velocity_reading_lags_behind_the_motor(source: str) -> None:
    # encoder.getRPM() is the velocity estimator's integrator (KP 120, KI 1900 at 1 kHz).
    fw = make(source)
    command(fw, Reg.SETUP, bytes([50, 50, 0, 0]))
    command(fw, Reg.SETMAXACCELERATION, f32(1e6))
    command(fw, Reg.SETMAXVELOCITY, f32(1000.0))
    command(fw, Reg.SETRPM, f32(60.0))
    fw.clock.sleep(0.02)
    early = struct.unpack("<f", fw.transfer(bytes([Reg.GETENCODERRPM]), 5)[:4])[0]
    run(fw, 0.5)
    late = struct.unpack("<f", fw.transfer(bytes([Reg.GETENCODERRPM]), 5)[:4])[0]
    assert fw.motor.field_velocity_dps == pytest.approx(360.0, rel=1e-4)  # VMAX is a whole number
    assert early < 0.9 * 60.0
    assert late == pytest.approx(60.0, rel=1e-3)


def test_a_wait_in_an_interrupt_handler_is_a_one_line_error(
    source: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    waits = _broken_copy(source, tmp_path, "\n  delay(5);", where="void requestEvent() {")
    fw = make(str(waits))
    with pytest.raises(SitlError, match=r"^j1 firmware \(.*\): a wait of 5 ms outside the main loop"):
        fw.transfer(bytes([Reg.PING]), 2)


def test_snapshot_and_restore_return_the_joint_to_where_it_was(source: str) -> None:
    fw = make(source)
    saved = fw.snapshot()
    command(fw, Reg.SETUP, bytes([20, 20, 0, 0]))
    assert fw.flags == Flag.NOT_HOMED
    fw.restore(saved)
    assert fw.flags == Flag.NOT_HOMED | Flag.NOT_ENABLED


def test_power_cycle_starts_the_firmware_over(source: str) -> None:
    fw = make(source)
    command(fw, Reg.SETUP, bytes([20, 20, 0, 0]))
    command(fw, Reg.HOMEOFFSET, f32(1.5))
    fw.power_cycle()
    assert fw.transfer(bytes([Reg.PING]), 2) == POWER_UP_PING
    assert fw.transfer(bytes([Reg.HOMEOFFSET]), 5)[:4] == f32(0.0)


def test_a_closed_device_answers_no_more(source: str) -> None:
    fw = make(source)
    fw.close()
    with pytest.raises(OSError, match="closed"):
        fw.transfer(bytes([Reg.PING]), 2)


def test_looking_at_the_flags_does_not_feed_the_deadman(source: str) -> None:
    fw = make(source)
    command(fw, Reg.SETUP, bytes([20, 20, 0, 0]))
    command(fw, Reg.SETRPM, f32(10.0))
    for _ in range(10):
        fw.clock.sleep(0.01)
        fw.update()
        fw.flags  # noqa: B018 - the property is what is tested
    assert fw.flags & Flag.NOT_ENABLED


# ----------------------------------------------------------------- backend
def test_sitl_backend_homes_the_arm_and_runs_reach(source: str) -> None:
    import gymnasium as gym

    import bioscara_gym  # noqa: F401 - registers the tasks

    env = gym.make("Bioscara-Reach-v0", backend="sitl", backend_options={"firmware": source})
    try:
        obs, _ = env.reset(seed=0)
        assert all(j.is_homed() for j in env.unwrapped.arm.joints.values())
        for _ in range(5):
            obs, *_ = env.step(env.action_space.sample() * 0.0)
        assert env.observation_space.contains(obs)
    finally:
        env.close()


def test_sitl_arm_homes_at_the_configured_thresholds(source: str) -> None:
    # j1 homes at 10 RPM (8.5 microsteps a millisecond) with threshold 30: only
    # the rotor thrown back at its first pole slip shows more than 15 + 8.5
    # under the library's closed loop.
    from bioscara_gym.hardware.backends import make_backend

    config = load_config()
    backend = make_backend("sitl", config, firmware=source)
    try:
        for j in config.joints:
            joint = backend.joints[j.name]
            joint.init()
            joint.enable(j.drive_current, j.hold_current)
            joint.set_max_acceleration(j.homing.acceleration)
            joint.home(j.homing.speed, j.homing.threshold, j.homing.current)
            assert joint.is_homed(), j.name
    finally:
        backend.close()


def test_sitl_backend_refuses_an_address_its_firmware_does_not_answer_at(source: str) -> None:
    import dataclasses

    from bioscara_gym.hardware.backends import make_backend

    config = load_config()
    joints = tuple(dataclasses.replace(j, address=0x15) if j.name == "j1" else j for j in config.joints)
    with pytest.raises(SitlError, match=r"^j1: the configuration's address 0x15 is not the firmware's 0x11"):
        make_backend("sitl", dataclasses.replace(config, joints=joints), firmware=source)


def test_sitl_arm_teleport_moves_the_encoder_without_a_velocity_spike(source: str) -> None:
    from bioscara_gym.hardware.backends import make_backend

    backend = make_backend("sitl", firmware=source)
    try:
        joint = backend.joints["j3"]
        joint.init()
        before = backend.sim.devices["j3"].transfer(bytes([Reg.ANGLEMOVED]), 5)[:4]
        backend.sim.set_joint_state({"j3": 0.5})
        backend.step(0.02)
        after = struct.unpack("<f", backend.sim.devices["j3"].transfer(bytes([Reg.ANGLEMOVED]), 5)[:4])[0]
        rpm = struct.unpack("<f", backend.sim.devices["j3"].transfer(bytes([Reg.GETENCODERRPM]), 5)[:4])[0]
        moved = after - struct.unpack("<f", before)[0]
        reduction = backend.config.joint("j3").reduction
        start = backend.sim.initial_qpos["j3"]
        assert moved == pytest.approx(math.degrees(reduction * (0.5 - start)), abs=0.05)
        assert abs(rpm) < 1.0
    finally:
        backend.close()


def test_the_final_state_after_the_arm_is_closed_is_the_firmwares_own(source: str) -> None:
    # `bioscara deploy --backend sitl` reads the joints' final flags for its
    # summary after the arm's shutdown has unloaded the firmware copies: it
    # failed there ("the firmware in the loop was closed", exit 2) after a
    # run that had gone well.
    from bioscara_gym.hardware.backends import make_backend
    from bioscara_gym.hardware.safety import final_state

    backend = make_backend("sitl", firmware=source)
    try:
        joint = backend.joints["j1"]
        joint.init()
        joint.enable(20, 10)
    finally:
        backend.close()
    state = final_state(backend)
    assert state["j1"]["enabled"] and not state["j2"]["enabled"]  # j1's SETUP cleared NOT_ENABLED
    assert {s["source"] for s in state.values()} == {"firmware in the loop"}
    # The firmware's currents are variables no register reads back.
    assert {(s["drive_current"], s["hold_current"]) for s in state.values()} == {(None, None)}


# --------------------------------------------------------------------- cli
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["eval", "--expert", "--backend", "emulated", "--firmware", "x"], "--firmware needs --backend sitl"),
        (["status", "--backend", "mock", "--firmware", "x"], "--firmware needs --backend sitl"),
        (
            ["deploy", "--expert", "--env", "Bioscara-Reach-v0", "--backend", "mock", "--firmware", "x"],
            "--firmware needs --backend sitl",
        ),
    ],
)
def test_firmware_option_needs_the_sitl_backend(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from bioscara_gym.cli import main

    assert main(argv) != 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert message in err


def test_cli_without_firmware_source_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from bioscara_gym.cli import main

    monkeypatch.delenv(FIRMWARE_ENV, raising=False)
    assert main(["status", "--backend", "sitl"]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("bioscara status: error: no firmware source")
    assert "\n" not in err
