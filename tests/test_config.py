"""Tests of the arm configuration: packaged defaults, round trips, validation."""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from bioscara_gym.hardware.config import (
    ArmConfig,
    GripperConfig,
    HomingConfig,
    JointConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)
from bioscara_gym.hardware.drive import velocity_mode_acceleration
from bioscara_gym.hardware.errors import ConfigError, InvalidArgumentError
from bioscara_gym.hardware.registers import MOTOR_ACCELERATION_MAX_DPS2

# docs/model.md tables, row by row: address, type, reduction, (min, max), max vel,
# max acc, stall threshold, hold current, drive current,
# homing (speed, threshold, current, acceleration).
SPEC_JOINTS: dict[str, dict[str, Any]] = {
    "j1": dict(
        address=0x11,
        joint_type="revolute",
        reduction=35.0,
        limits=(-3.04647, 3.04647),
        max_velocity=1.0,
        max_acceleration=2.0,
        stall_threshold=6,
        hold_current=20,
        drive_current=20,
        homing=(0.03, 30, 15, 0.01),
    ),
    "j2": dict(
        address=0x12,
        joint_type="prismatic",
        reduction=-2 * math.pi / 0.004,
        limits=(-0.0016, 0.338),
        max_velocity=0.03,
        max_acceleration=0.2,
        stall_threshold=12,
        hold_current=40,
        drive_current=40,
        homing=(0.003, 50, 30, 0.001),
    ),
    "j3": dict(
        address=0x13,
        joint_type="revolute",
        reduction=24.0,
        limits=(-2.62672, 2.62672),
        max_velocity=5.0,
        max_acceleration=14.0,
        stall_threshold=6,
        hold_current=20,
        drive_current=20,
        homing=(0.05, 25, 10, 0.01),
    ),
    "j4": dict(
        address=0x14,
        joint_type="revolute",
        reduction=12.0,
        limits=(-3.01069, 3.01069),
        max_velocity=10.0,
        max_acceleration=30.0,
        stall_threshold=6,
        hold_current=20,
        drive_current=20,
        homing=(0.1, 30, 10, 0.1),
    ),
}


@pytest.fixture(scope="module")
def default_config() -> ArmConfig:
    """Return the packaged default configuration."""
    return load_config()


@pytest.fixture
def default_dict(default_config: ArmConfig) -> dict[str, Any]:
    """Return a fresh plain-data copy of the default configuration."""
    return config_to_dict(default_config)


# --------------------------------------------------------------------------
# Packaged defaults equal docs/model.md.
# --------------------------------------------------------------------------


def test_default_config_has_joints_j1_to_j4_in_order(
    default_config: ArmConfig,
) -> None:
    """The default arm has j1..j4 in order on bus 1."""
    assert default_config.names == ("j1", "j2", "j3", "j4")
    assert default_config.bus == 1


@pytest.mark.parametrize("name", sorted(SPEC_JOINTS))
def test_default_joint_matches_spec(default_config: ArmConfig, name: str) -> None:
    """Every default joint field equals the docs/model.md tables."""
    spec = SPEC_JOINTS[name]
    joint = default_config.joint(name)
    assert joint.name == name
    assert joint.address == spec["address"]
    assert joint.joint_type == spec["joint_type"]
    assert joint.reduction == pytest.approx(spec["reduction"], rel=1e-12)
    assert (joint.min, joint.max) == spec["limits"]
    assert joint.max_velocity == spec["max_velocity"]
    assert joint.max_acceleration == spec["max_acceleration"]
    assert joint.stall_threshold == spec["stall_threshold"]
    assert joint.hold_current == spec["hold_current"]
    assert joint.drive_current == spec["drive_current"]
    assert dataclasses.astuple(joint.homing) == spec["homing"]


def test_default_homing_speeds_home_to_the_max_end_stop(
    default_config: ArmConfig,
) -> None:
    """All default homing speeds are positive (home to max)."""
    assert all(joint.homing.speed > 0 for joint in default_config.joints)


def test_default_gripper_matches_spec(default_config: ArmConfig) -> None:
    """The default gripper equals the docs/model.md gripper table."""
    assert default_config.gripper == GripperConfig(
        reduction=3333.3,
        offset=0.058,
        min=0.04,
        max=0.12,
        max_velocity=1.0,
        backup_init_pos=0.08,
        pwm_chip=0,
        pwm_channel=0,
        state_file=None,
    )


def test_default_groups(default_config: ArmConfig) -> None:
    """The default groups are all, arm and gripper."""
    assert dict(default_config.groups) == {
        "all": ("j1", "j2", "j3", "j4", "gripper"),
        "arm": ("j1", "j2", "j3", "j4"),
        "gripper": ("gripper",),
    }


def test_default_float_fields_are_floats(default_config: ArmConfig) -> None:
    """Float fields hold floats even when YAML gives ints."""
    joint = default_config.joint("j1")
    for value in (joint.reduction, joint.max_velocity, joint.homing.speed):
        assert type(value) is float


@pytest.mark.parametrize(
    ("name", "rpm"),
    [
        ("j1", math.degrees(35 * 0.03) / 6),  # 10.03 RPM
        ("j2", -45.0),  # negative reduction: the motor turns backwards
        ("j3", math.degrees(24 * 0.05) / 6),  # 11.46 RPM
        ("j4", math.degrees(12 * 0.1) / 6),  # 11.46 RPM
    ],
)
def test_homing_rpm(default_config: ArmConfig, name: str, rpm: float) -> None:
    """homing_rpm() is rad2deg(reduction * speed) / 6, signed."""
    assert default_config.joint(name).homing_rpm() == pytest.approx(rpm, rel=1e-9)


def test_homing_rpm_j1_is_about_10_rpm(default_config: ArmConfig) -> None:
    """j1 homes at about 10.03 RPM at the motor."""
    assert default_config.joint("j1").homing_rpm() == pytest.approx(10.03, abs=0.01)


# --------------------------------------------------------------------------
# Round trips and files.
# --------------------------------------------------------------------------


def test_round_trip_through_dict(default_config: ArmConfig) -> None:
    """config_to_dict then config_from_dict gives an equal config."""
    assert config_from_dict(config_to_dict(default_config)) == default_config


def test_config_to_dict_is_plain_yaml_data(default_config: ArmConfig) -> None:
    """config_to_dict output survives yaml.safe_dump/safe_load."""
    data = config_to_dict(default_config)
    assert yaml.safe_load(yaml.safe_dump(data)) == data


def test_load_config_from_yaml_file(tmp_path: Path, default_config: ArmConfig) -> None:
    """A YAML file written to disk loads to the same config."""
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config_to_dict(default_config)), encoding="utf-8")
    assert load_config(path) == default_config
    assert load_config(str(path)) == default_config


def test_load_config_from_yaml_file_with_changes(tmp_path: Path, default_dict: dict[str, Any]) -> None:
    """Changed values in a YAML file are loaded."""
    default_dict["bus"] = 3
    default_dict["joints"][0]["hold_current"] = 25
    default_dict["gripper"]["state_file"] = "/tmp/gripper_width"
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(default_dict), encoding="utf-8")
    cfg = load_config(path)
    assert cfg.bus == 3
    assert cfg.joint("j1").hold_current == 25
    assert cfg.gripper.state_file == "/tmp/gripper_width"


def test_groups_and_bus_and_gripper_extras_are_optional(
    default_dict: dict[str, Any], default_config: ArmConfig
) -> None:
    """groups, bus and the gripper's PWM/state fields have defaults."""
    del default_dict["groups"], default_dict["bus"]
    for key in ("pwm_chip", "pwm_channel", "state_file"):
        del default_dict["gripper"][key]
    assert config_from_dict(default_dict) == default_config


def test_hex_addresses_in_yaml_are_read_as_integers(tmp_path: Path, default_dict: dict[str, Any]) -> None:
    """YAML hex literals such as 0x11 are integers."""
    text = yaml.safe_dump(default_dict).replace("address: 17", "address: 0x11")
    path = tmp_path / "config.yaml"
    path.write_text(text, encoding="utf-8")
    assert load_config(path).joint("j1").address == 0x11


# --------------------------------------------------------------------------
# Immutability and lookups.
# --------------------------------------------------------------------------


def test_config_is_frozen(default_config: ArmConfig) -> None:
    """Configs, nested parts and groups cannot be modified."""
    with pytest.raises(dataclasses.FrozenInstanceError):
        default_config.bus = 2  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        default_config.joint("j1").homing.speed = 1.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        default_config.groups["arm"] = ("j1",)  # type: ignore[index]


def test_config_is_hashable(default_config: ArmConfig) -> None:
    """Equal configs hash equal."""
    assert hash(default_config) == hash(load_config())


def test_unknown_joint_lookup_names_known_joints(default_config: ArmConfig) -> None:
    """ArmConfig.joint() of an unknown name lists the known joints."""
    with pytest.raises(ConfigError, match=r"unknown joint 'j9'; known joints: j1, j2"):
        default_config.joint("j9")


def test_unknown_joint_lookup_is_also_an_invalid_argument(default_config: ArmConfig) -> None:
    """A caller of the driver layer may catch it as InvalidArgumentError, as the console does."""
    with pytest.raises(InvalidArgumentError, match=r"unknown joint 'j9'; known joints: j1, j2"):
        default_config.joint("j9")


def test_direct_construction_is_validated() -> None:
    """Building a JointConfig directly validates it too."""
    homing = HomingConfig(speed=0.03, threshold=30, current=15, acceleration=0.01)
    with pytest.raises(ConfigError, match=r"joint j1: hold_current 101 is outside"):
        JointConfig(
            name="j1",
            address=0x11,
            joint_type="revolute",
            reduction=35,
            min=-3.0,
            max=3.0,
            max_velocity=1.0,
            max_acceleration=2.0,
            stall_threshold=6,
            hold_current=101,
            drive_current=20,
            homing=homing,
        )


def test_direct_construction_coerces_int_to_float() -> None:
    """Ints given for float fields are stored as floats."""
    homing = HomingConfig(speed=1, threshold=30, current=15, acceleration=1)
    assert type(homing.speed) is float
    assert type(homing.acceleration) is float


@given(speed=st.floats(min_value=-10.0, max_value=10.0, allow_nan=False))
def test_homing_speed_accepted_iff_rpm_strictly_between_1_and_250(
    speed: float,
) -> None:
    """A homing speed is valid exactly when 1 < |RPM| < 250."""
    rpm = math.degrees(12.0 * speed) / 6
    try:
        homing = HomingConfig(speed=speed, threshold=30, current=10, acceleration=0.1)
        JointConfig(
            name="j4",
            address=0x14,
            joint_type="revolute",
            reduction=12.0,
            min=-3.0,
            max=3.0,
            max_velocity=10.0,
            max_acceleration=30.0,
            stall_threshold=6,
            hold_current=20,
            drive_current=20,
            homing=homing,
        )
    except ConfigError:
        accepted = False
    else:
        accepted = True
    assert accepted == (1.0 < abs(rpm) < 250.0)


# --------------------------------------------------------------------------
# Invalid configurations: every case names the source, the joint and field.
# --------------------------------------------------------------------------

Mutation = Callable[[dict[str, Any]], None]


def _joint(data: dict[str, Any], name: str) -> dict[str, Any]:
    return next(j for j in data["joints"] if j["name"] == name)


def _set_joint(name: str, key: str, value: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        _joint(data, name)[key] = value

    return mutate


def _set_homing(name: str, key: str, value: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        _joint(data, name)["homing"][key] = value

    return mutate


def _set_drive(name: str, key: str, value: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        _joint(data, name)["drive"][key] = value

    return mutate


def _del_joint(name: str, key: str) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        del _joint(data, name)[key]

    return mutate


def _del_homing(name: str, key: str) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        del _joint(data, name)["homing"][key]

    return mutate


def _rename_joint_field(name: str, old: str, new: str) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        joint = _joint(data, name)
        joint[new] = joint.pop(old)

    return mutate


def _set_gripper(key: str, value: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        data["gripper"][key] = value

    return mutate


def _del_gripper(key: str) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        del data["gripper"][key]

    return mutate


def _set_top(key: str, value: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        data[key] = value

    return mutate


def _del_top(key: str) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        del data[key]

    return mutate


def _set_group(group: str, members: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        data["groups"][group] = members

    return mutate


INVALID_CASES = [
    # The drive model's fields.
    pytest.param(
        _set_drive("j1", "slip_corner", 0),
        r"config\.yaml: joint j1: drive: slip_corner=0 must be > 0$",
        id="drive-slip-corner-zero",
    ),
    pytest.param(
        _set_drive("j3", "corner_speed", 0.0),
        r"config\.yaml: joint j3: drive: corner_speed=0 must be > 0$",
        id="drive-corner-speed-zero",
    ),
    pytest.param(
        _set_drive("j2", "slip_corner", -5.0),
        r"config\.yaml: joint j2: drive: slip_corner=-5\.0 must be a number >= 0$",
        id="drive-slip-corner-negative",
    ),
    pytest.param(
        _set_drive("j2", "self_locking", "yes"),
        r"config\.yaml: joint j2: drive: self_locking='yes' must be true or false$",
        id="drive-self-locking-not-a-bool",
    ),
    pytest.param(
        _set_drive("j2", "self_locking", 1),
        r"config\.yaml: joint j2: drive: self_locking=1 must be true or false$",
        id="drive-self-locking-a-number",
    ),
    # Seen (a hostile test): 1e308 passed, and the motor model's state went NaN.
    pytest.param(
        _set_drive("j1", "pullout_accel", 1.0000001e9),
        r"config\.yaml: joint j1: drive: pullout_accel=1000000100\.0 is beyond 1e\+09; inf is no limit$",
        id="drive-pullout-beyond-any-motor",
    ),
    pytest.param(
        _set_drive("j3", "friction_coulomb", 1e308),
        r"joint j3: drive: friction_coulomb=1e\+308 is beyond 1e\+09; inf is no limit$",
        id="drive-friction-1e308",
    ),
    # Missing and unknown fields.
    pytest.param(
        _del_joint("j2", "hold_current"),
        r"config\.yaml: joint j2: missing field 'hold_current'$",
        id="missing-joint-field",
    ),
    pytest.param(
        _del_joint("j4", "joint_type"),
        r"config\.yaml: joint j4: missing field 'joint_type'$",
        id="missing-joint-type",
    ),
    pytest.param(
        _del_homing("j1", "current"),
        r"config\.yaml: joint j1: missing field 'homing\.current'$",
        id="missing-homing-field",
    ),
    pytest.param(
        _del_joint("j3", "homing"),
        r"config\.yaml: joint j3: missing field 'homing'$",
        id="missing-homing-block",
    ),
    pytest.param(
        _del_joint("j2", "name"),
        r"config\.yaml: joints\[1\]: missing field 'name'$",
        id="missing-joint-name",
    ),
    pytest.param(
        _del_gripper("offset"),
        r"config\.yaml: gripper: missing field 'offset'$",
        id="missing-gripper-field",
    ),
    pytest.param(
        _del_top("joints"),
        r"config\.yaml: missing field 'joints'$",
        id="missing-joints",
    ),
    pytest.param(
        _rename_joint_field("j3", "max_velocity", "max_vel"),
        r"config\.yaml: joint j3: unknown field 'max_vel' "
        r"\(did you mean 'max_velocity'\?\)",
        id="unknown-joint-field-typo",
    ),
    pytest.param(
        _set_homing("j1", "sped", 0.03),
        r"config\.yaml: joint j1: unknown field 'homing\.sped' "
        r"\(did you mean 'homing\.speed'\?\)",
        id="unknown-homing-field",
    ),
    pytest.param(
        _set_gripper("colour", "red"),
        r"config\.yaml: gripper: unknown field 'colour'; allowed: reduction",
        id="unknown-gripper-field",
    ),
    pytest.param(
        _set_top("jionts", []),
        r"config\.yaml: unknown field 'jionts' \(did you mean 'joints'\?\)",
        id="unknown-top-level-field",
    ),
    # Wrong types and non-finite numbers.
    pytest.param(
        _set_joint("j1", "reduction", "thirty-five"),
        r"config\.yaml: joint j1: reduction 'thirty-five' \(str\) must be a number$",
        id="string-for-float",
    ),
    pytest.param(
        _set_homing("j1", "acceleration", "1e-3"),
        r"config\.yaml: joint j1: homing\.acceleration '1e-3' \(str\) must be a "
        r"number \(YAML reads an exponent without a dot and a sign",
        id="yaml-exponent-string-hint",
    ),
    pytest.param(
        _set_joint("j2", "max", True),
        r"config\.yaml: joint j2: max True \(bool\) must be a number",
        id="bool-for-float",
    ),
    pytest.param(
        _set_joint("j1", "stall_threshold", True),
        r"config\.yaml: joint j1: stall_threshold True \(bool\) must be an integer",
        id="bool-for-int",
    ),
    pytest.param(
        _set_joint("j1", "hold_current", 20.5),
        r"config\.yaml: joint j1: hold_current 20\.5 \(float\) must be an integer",
        id="float-for-int",
    ),
    pytest.param(
        _set_joint("j1", "address", "0x11"),
        r"config\.yaml: joint j1: address '0x11' \(str\) must be an integer",
        id="string-for-address",
    ),
    pytest.param(
        _set_joint("j3", "min", float("nan")),
        r"config\.yaml: joint j3: min nan must be finite",
        id="nan",
    ),
    pytest.param(
        _set_homing("j4", "speed", float("inf")),
        r"config\.yaml: joint j4: homing\.speed inf must be finite",
        id="inf",
    ),
    pytest.param(
        _set_gripper("offset", float("-inf")),
        r"config\.yaml: gripper: offset -inf must be finite",
        id="gripper-inf",
    ),
    pytest.param(
        _set_joint("j2", "name", 2),
        r"config\.yaml: joints\[1\]: name 2 \(int\) must be a non-empty string",
        id="name-not-string",
    ),
    pytest.param(
        _set_joint("j2", "homing", [0.003, 50, 30, 0.001]),
        r"config\.yaml: joint j2: homing must be a mapping, got list",
        id="homing-not-mapping",
    ),
    pytest.param(
        _set_top("joints", {"j1": {}}),
        r"config\.yaml: joints must be a list of joint mappings, got dict",
        id="joints-not-list",
    ),
    pytest.param(
        _set_top("gripper", None),
        r"config\.yaml: gripper: section must be a mapping, got NoneType",
        id="gripper-not-mapping",
    ),
    pytest.param(
        _set_top("bus", "1"),
        r"config\.yaml: bus '1' \(str\) must be an integer",
        id="bus-not-int",
    ),
    # Addresses and names.
    pytest.param(
        _set_joint("j4", "address", 0x78),
        r"config\.yaml: joint j4: address 0x78 is outside the 7-bit I2C range "
        r"0x03-0x77",
        id="address-too-high",
    ),
    pytest.param(
        _set_joint("j4", "address", 0x80),
        r"config\.yaml: joint j4: address 0x80 is outside the 7-bit I2C range",
        id="address-beyond-7-bits",
    ),
    pytest.param(
        _set_joint("j1", "address", 0x02),
        r"config\.yaml: joint j1: address 0x02 is outside the 7-bit I2C range",
        id="address-reserved-low",
    ),
    pytest.param(
        _set_joint("j3", "address", 0x11),
        r"config\.yaml: joint j3: address 0x11 is already used by joint j1",
        id="duplicate-address",
    ),
    pytest.param(
        _set_joint("j3", "name", "j1"),
        r"config\.yaml: joint j1: defined more than once",
        id="duplicate-name",
    ),
    pytest.param(
        _set_joint("j4", "name", "gripper"),
        r"config\.yaml: joint gripper: the name 'gripper' is reserved",
        id="joint-named-gripper",
    ),
    pytest.param(
        _set_joint("j1", "joint_type", "linear"),
        r"config\.yaml: joint j1: joint_type 'linear' must be one of 'revolute', "
        r"'prismatic'",
        id="joint-type",
    ),
    # Limits.
    pytest.param(
        _set_joint("j2", "min", 0.338),
        r"config\.yaml: joint j2: min 0\.338 m must be less than max 0\.338 m",
        id="joint-min-equals-max",
    ),
    # The firmware's position is a float32 of motor degrees (joint.ino: float q = angleMoved()):
    # whole degrees to 2^24 = 16,777,216, which j1 (35:1) reaches at 8366.3 rad.
    # Seen (a hostile test): max 1e308 passed, and MuJoCo's state went NaN.
    pytest.param(
        _set_joint("j1", "max", 8367.0),
        r"config\.yaml: joint j1: max 8367\.0 rad is 1\.678e\+07 deg at the motor; the firmware keeps the "
        r"motor's angle in a float \(angleMoved\), whole to a degree up to 16,777,216$",
        id="joint-max-beyond-the-firmwares-float",
    ),
    pytest.param(
        _set_joint("j2", "min", -187.0),  # 4 mm a motor turn: 186.4 m of travel
        r"joint j2: min -187\.0 m is 1\.683e\+07 deg at the motor",
        id="joint-min-beyond-the-firmwares-float",
    ),
    pytest.param(
        _set_joint("j1", "max", -3.5),
        r"config\.yaml: joint j1: min -3\.04647 rad must be less than max -3\.5 rad",
        id="joint-min-above-max",
    ),
    pytest.param(
        _set_gripper("min", 0.2),
        r"config\.yaml: gripper: min 0\.2 m must be less than max 0\.12 m",
        id="gripper-min-above-max",
    ),
    pytest.param(
        _set_gripper("backup_init_pos", 0.2),
        r"config\.yaml: gripper: backup_init_pos 0\.2 m must be within "
        r"\[min, max\] = \[0\.04, 0\.12\] m",
        id="gripper-backup-init-pos-above-max",
    ),
    pytest.param(
        _set_gripper("backup_init_pos", 0.0),
        r"config\.yaml: gripper: backup_init_pos 0\.0 m must be within",
        id="gripper-backup-init-pos-below-min",
    ),
    # Homing speed.
    pytest.param(
        _set_homing("j2", "speed", 0.00005),
        r"config\.yaml: joint j2: homing\.speed 5e-05 m/s is -0\.75 RPM at the "
        r"motor; \|RPM\| must be strictly between 1 and 250",
        id="homing-speed-too-slow",
    ),
    pytest.param(
        _set_homing("j1", "speed", -8.0),
        r"config\.yaml: joint j1: homing\.speed -8\.0 rad/s is -2673\.80 RPM at the "
        r"motor; \|RPM\| must be strictly between 1 and 250",
        id="homing-speed-too-fast",
    ),
    pytest.param(
        _set_homing("j4", "speed", math.radians(1500) / 12),
        r"config\.yaml: joint j4: homing\.speed .* rad/s is 250\.00 RPM",
        id="homing-speed-exactly-250-rpm",
    ),
    pytest.param(
        _set_homing("j3", "speed", 0.0),
        r"config\.yaml: joint j3: homing\.speed must be non-zero",
        id="homing-speed-zero",
    ),
    # Currents and thresholds.
    pytest.param(
        _set_joint("j1", "hold_current", -1),
        r"config\.yaml: joint j1: hold_current -1 is outside 0-100 %",
        id="hold-current-negative",
    ),
    pytest.param(
        _set_joint("j2", "drive_current", 101),
        r"config\.yaml: joint j2: drive_current 101 is outside 0-100 %",
        id="drive-current-too-high",
    ),
    pytest.param(
        _set_homing("j3", "current", 150),
        r"config\.yaml: joint j3: homing\.current 150 is outside 0-100 %",
        id="homing-current-too-high",
    ),
    pytest.param(
        _set_joint("j4", "stall_threshold", 256),
        r"config\.yaml: joint j4: stall_threshold 256 is outside 0-255",
        id="stall-threshold-too-high",
    ),
    pytest.param(
        _set_homing("j1", "threshold", -1),
        r"config\.yaml: joint j1: homing\.threshold -1 is outside 0-255",
        id="homing-threshold-negative",
    ),
    # Values the motor and the firmware cannot honour (issue #24; registers.py has their sources).
    pytest.param(
        _set_joint("j4", "max_velocity", 1.0e6),
        r"config\.yaml: joint j4: max_velocity 1000000\.0 rad/s is 1\.146e\+08 RPM at the motor; the "
        r"motors were measured to 1639 RPM, so at most 2000 RPM \(17\.453292519943293 rad/s\)$",
        id="max-velocity-beyond-the-motor",
    ),
    pytest.param(
        _set_joint("j2", "max_velocity", 0.14),
        r"config\.yaml: joint j2: max_velocity 0\.14 m/s is 2100 RPM at the motor; .* at most 2000 RPM",
        id="lift-max-velocity-beyond-the-motor",
    ),
    pytest.param(
        _set_joint("j1", "max_acceleration", 15.0),
        r"config\.yaml: joint j1: max_acceleration 15\.0 rad/s² is 3\.008e\+04 deg/s² at the motor; the "
        r"driver chip's 16-bit acceleration register wraps above 20,945 deg/s², so at most 20900 "
        r"\(10\.4221[0-9]* rad/s²\)$",
        id="max-acceleration-beyond-the-motor",
    ),
    pytest.param(
        _set_homing("j4", "acceleration", 31.0),
        r"config\.yaml: joint j4: homing\.acceleration 31\.0 rad/s² is 2\.131e\+04 deg/s² at the motor; the "
        r"driver chip's 16-bit acceleration register wraps above 20,945 deg/s², so at most 20900",
        id="homing-acceleration-past-the-chip-wrap",
    ),
    # maxAccel/j4_4: the real j4 set to 34 rad/s² (23,377 deg/s²) ramped at 2,431 and reached
    # 1.9 rad/s of 10. 30.5 rad/s² (20,970 deg/s²) is just past the wrap: it would ramp at 8 deg/s².
    pytest.param(
        _set_joint("j4", "max_acceleration", 30.5),
        r"config\.yaml: joint j4: max_acceleration 30\.5 rad/s² is 2\.097e\+04 deg/s² at the motor; the "
        r"driver chip's 16-bit acceleration register wraps",
        id="max-acceleration-past-the-chip-wrap",
    ),
    pytest.param(
        _set_homing("j1", "threshold", 0),
        r"config\.yaml: joint j1: homing\.threshold 0 is below 20: a free joint's PID error at rest "
        r"reaches 17, so the homing would stop where the joint stands",
        id="homing-threshold-zero",
    ),
    pytest.param(
        _set_homing("j3", "threshold", 19),
        r"config\.yaml: joint j3: homing\.threshold 19 is below 20",
        id="homing-threshold-19",
    ),
    # Seen (a hostile test): accepted, and the deploy then stopped on a stall standing still.
    pytest.param(
        _set_joint("j1", "stall_threshold", 0),
        r"config\.yaml: joint j1: stall_threshold 0 is below 2: its threshold \(0 at standstill\) lies "
        r"under a free joint's PID error at rest \(17\), so it would trip standing still",
        id="stall-threshold-zero",
    ),
    pytest.param(
        _set_joint("j4", "stall_threshold", 1),
        r"config\.yaml: joint j4: stall_threshold 1 is below 2",
        id="stall-threshold-1",
    ),
    pytest.param(
        _set_homing("j2", "current", 0),
        r"config\.yaml: joint j2: homing\.current 0 % gives the motor no torque: the homing would stop",
        id="homing-current-zero",
    ),
    pytest.param(
        _set_joint("j4", "drive_current", 0),
        r"config\.yaml: joint j4: drive_current 0 % gives the motor no torque: the joint could not move$",
        id="drive-current-zero",
    ),
    # Velocity, acceleration, reduction.
    pytest.param(
        _set_joint("j3", "max_velocity", 0.0),
        r"config\.yaml: joint j3: max_velocity 0\.0 rad/s must be > 0",
        id="max-velocity-zero",
    ),
    pytest.param(
        _set_joint("j2", "max_acceleration", -0.2),
        r"config\.yaml: joint j2: max_acceleration -0\.2 m/s² must be > 0",
        id="max-acceleration-negative",
    ),
    pytest.param(
        _set_homing("j4", "acceleration", 0),
        r"config\.yaml: joint j4: homing\.acceleration 0\.0 must be > 0",
        id="homing-acceleration-zero",
    ),
    pytest.param(
        _set_joint("j1", "reduction", 0),
        r"config\.yaml: joint j1: reduction must be non-zero",
        id="reduction-zero",
    ),
    pytest.param(
        _set_gripper("reduction", 0.0),
        r"config\.yaml: gripper: reduction must be non-zero",
        id="gripper-reduction-zero",
    ),
    pytest.param(
        _set_gripper("max_velocity", -1.0),
        r"config\.yaml: gripper: max_velocity -1\.0 must be > 0",
        id="gripper-max-velocity-negative",
    ),
    pytest.param(
        _set_gripper("state_file", ""),
        r"config\.yaml: gripper: state_file '' \(str\) must be a non-empty string",
        id="gripper-state-file-empty",
    ),
    pytest.param(
        _set_gripper("pwm_channel", -1),
        r"config\.yaml: gripper: pwm_channel -1 must be >= 0",
        id="gripper-pwm-channel-negative",
    ),
    # Groups.
    pytest.param(
        _set_group("arm", ["j1", "j5"]),
        r"config\.yaml: groups\.arm: unknown joint 'j5'; known: j1, j2, j3, j4, "
        r"gripper",
        id="group-unknown-joint",
    ),
    pytest.param(
        _set_group("wrist", "j4"),
        r"config\.yaml: groups\.wrist: 'j4' must be a list of joint names",
        id="group-not-list",
    ),
    pytest.param(
        _set_group("wrist", ["j4", "j4"]),
        r"config\.yaml: groups\.wrist: lists a joint more than once",
        id="group-duplicate-member",
    ),
    pytest.param(
        _set_group("empty", []),
        r"config\.yaml: groups\.empty: must name at least one joint",
        id="group-empty",
    ),
    pytest.param(
        _set_top("groups", ["all"]),
        r"config\.yaml: groups must be a mapping",
        id="groups-not-mapping",
    ),
]


@pytest.mark.parametrize(("mutate", "message"), INVALID_CASES)
def test_invalid_config_raises_config_error_naming_joint_and_field(
    default_dict: dict[str, Any], mutate: Mutation, message: str
) -> None:
    """Each invalid case raises ConfigError naming source, joint and field."""
    mutate(default_dict)
    with pytest.raises(ConfigError, match=message):
        config_from_dict(default_dict, source="config.yaml")


def test_limits_within_the_firmwares_float_and_drive_values_up_to_the_bound_are_accepted(
    default_dict: dict[str, Any],
) -> None:
    _set_joint("j1", "max", 8366.0)(default_dict)  # 16,776,578 motor degrees
    _set_joint("j2", "min", -186.0)(default_dict)
    _set_drive("j1", "pullout_accel", 1e9)(default_dict)
    _set_drive("j3", "corner_speed", float("inf"))(default_dict)
    config = config_from_dict(default_dict, source="config.yaml")
    assert (config.joint("j1").max, config.joint("j2").min) == (8366.0, -186.0)
    assert config.joint("j1").drive.pullout_accel == 1e9


def test_config_error_is_a_value_error(default_dict: dict[str, Any]) -> None:
    """ConfigError is a ValueError; the default source is <dict>."""
    default_dict["bus"] = -1
    with pytest.raises(ValueError, match=r"<dict>: bus -1 must be >= 0"):
        config_from_dict(default_dict)


def test_top_level_not_a_mapping_in_dict_names_source() -> None:
    """config_from_dict refuses a non-mapping, naming the source."""
    with pytest.raises(ConfigError, match=r"^cfg: the top level must be a mapping"):
        config_from_dict(["joints"], source="cfg")  # type: ignore[arg-type]


# --------------------------------------------------------------------------
# File errors: named by path and chained.
# --------------------------------------------------------------------------


def test_missing_file_names_path_and_chains_os_error(tmp_path: Path) -> None:
    """A missing file raises ConfigError naming it, from the OSError."""
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=re.escape(str(path))) as info:
        load_config(path)
    assert "cannot read config file" in str(info.value)
    assert isinstance(info.value.__cause__, FileNotFoundError)


def test_directory_is_unreadable_config(tmp_path: Path) -> None:
    """A directory path raises ConfigError from the OSError."""
    with pytest.raises(ConfigError, match="cannot read config file") as info:
        load_config(tmp_path)
    assert isinstance(info.value.__cause__, OSError)


def test_a_device_is_refused_before_it_is_read() -> None:
    """/dev/zero never ends: read whole, it filled the memory (a MemoryError after 3 GB)."""
    with pytest.raises(ConfigError, match=r"^/dev/zero: cannot read config file: not a regular file$"):
        load_config("/dev/zero")


def test_a_huge_file_is_refused(tmp_path: Path) -> None:
    """A configuration is some 10 kB; one of more than a megabyte is not one."""
    path = tmp_path / "huge.yaml"
    path.write_bytes(b"#" * (1024 * 1024 + 1))
    with pytest.raises(ConfigError, match=r"cannot read config file: larger than 1048576 bytes$"):
        load_config(path)


def test_invalid_yaml_names_path_and_chains_yaml_error(tmp_path: Path) -> None:
    """Broken YAML raises ConfigError naming the path, from the YAMLError."""
    path = tmp_path / "broken.yaml"
    path.write_text("joints: [\n  - name: j1\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=re.escape(f"{path}: not valid YAML")) as info:
        load_config(path)
    assert isinstance(info.value.__cause__, yaml.YAMLError)


def test_non_utf8_file_names_path(tmp_path: Path) -> None:
    """A file that is not UTF-8 text raises ConfigError naming it."""
    path = tmp_path / "binary.yaml"
    path.write_bytes(b"\xff\xfe\x00bus: 1")
    with pytest.raises(ConfigError, match=re.escape(str(path))) as info:
        load_config(path)
    assert info.value.__cause__ is not None


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("- j1\n- j2\n", "found list"),
        ("", "found an empty document"),
        ("42\n", "found int"),
    ],
)
def test_top_level_not_a_mapping_names_path(tmp_path: Path, text: str, found: str) -> None:
    """A YAML file whose top level is not a mapping is refused."""
    path = tmp_path / "config.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(
        ConfigError,
        match=re.escape(f"{path}: top level must be a mapping with 'joints' and "),
    ) as info:
        load_config(path)
    assert found in str(info.value)


def test_duplicate_yaml_key_is_refused(tmp_path: Path, default_dict: dict[str, Any]) -> None:
    """A key given twice in one YAML mapping is an error."""
    text = yaml.safe_dump(default_dict).replace("address: 18\n", "address: 18\n  address: 19\n", 1)
    assert "address: 19" in text
    path = tmp_path / "config.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match="duplicate key 'address'") as info:
        load_config(path)
    assert isinstance(info.value.__cause__, yaml.YAMLError)


def test_value_error_in_file_names_path_and_joint(tmp_path: Path, default_dict: dict[str, Any]) -> None:
    """A bad value in a file is reported with the file's path."""
    _joint(default_dict, "j2")["homing"]["speed"] = 0.00005
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(default_dict), encoding="utf-8")
    with pytest.raises(ConfigError, match=re.escape(f"{path}: joint j2: homing.speed 5e-05 m/s")):
        load_config(path)


# --------------------------------------------------------------------------
# The bounds of what the arm can honour: the limits themselves are accepted.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("joint", "field", "value"),
    [
        ("j1", "homing.threshold", 20),  # registers.HOMING_THRESHOLD_MIN
        ("j2", "homing.current", 1),
        ("j4", "drive_current", 1),
        ("j4", "max_velocity", 2000.0 * 6.0 / math.degrees(12.0)),  # 2000 RPM at the motor exactly
        ("j3", "max_acceleration", 20_900.0 / math.degrees(24.0)),  # 20,900 deg/s^2 at the motor exactly
        ("j3", "homing.acceleration", 20_900.0 / math.degrees(24.0)),
    ],
)
def test_the_bounds_of_what_the_arm_can_honour_are_themselves_accepted(
    default_dict: dict[str, Any], joint: str, field: str, value: float
) -> None:
    spec = next(j for j in default_dict["joints"] if j["name"] == joint)
    if field.startswith("homing."):
        spec["homing"][field.removeprefix("homing.")] = value
    else:
        spec[field] = value
    config_from_dict(default_dict, source="config.yaml")


def test_the_acceleration_bound_is_one_the_driver_chip_holds_and_just_past_it_the_chip_wraps() -> None:
    # The chip's AMAX field has 16 bits (drive.velocity_mode_acceleration): 20,900 deg/s^2
    # is ramped as set; 20,946 wraps to 0.32 deg/s^2, a joint that barely moves.
    assert velocity_mode_acceleration(MOTOR_ACCELERATION_MAX_DPS2) == pytest.approx(20_900.0, rel=1e-4)
    assert velocity_mode_acceleration(20_946.0) < 1.0


def test_a_dynamixel_joint_is_not_bound_by_the_steppers_limits() -> None:
    # An XL430 is not the Bioscara's stepper: its limits are the servo's.
    path = Path(__file__).parent.parent / "bioscara_gym" / "hardware" / "dynamixel" / "dynamixel_arm.yaml"
    data = yaml.safe_load(path.read_text())
    data["joints"][0]["max_acceleration"] = 1000.0  # 57,296 deg/s² at reduction 1: past the stepper's 20,900
    config_from_dict(data, source="dynamixel_arm.yaml")
    data["joints"][0]["max_velocity"] = 300.0  # 2865 RPM: past the servo's Velocity Limit (61 RPM)
    with pytest.raises(ConfigError, match=r"beyond its Velocity Limit \(6\.355 rad/s"):
        config_from_dict(data, source="dynamixel_arm.yaml")
