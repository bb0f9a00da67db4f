"""Hostile configuration files: each was accepted, hung or crashed before, now refused in one line.

Each file is the packaged ``default_config.yaml`` with one field changed (as
the hostile tester built them), loaded with :func:`load_config`.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from bioscara_gym.hardware.config import HomingConfig, JointConfig, load_config
from bioscara_gym.hardware.errors import ConfigError

PACKAGED = Path(__file__).parent.parent / "bioscara_gym" / "hardware" / "default_config.yaml"
J1_MAX_VELOCITY = "max_velocity: 1.0             # [URDF] rad/s"
J1_MAX_ACCELERATION = "max_acceleration: 2.0         # [URDF] rad/s^2"
J1_REDUCTION = "reduction: 35.0               # [URDF]"
J1_HOMING_ACCELERATION = "acceleration: 0.01          # [PARAM] rad/s^2"
J1_HOMING_SPEED = "speed: 0.03                 # [PARAM] rad/s, to max; 10.03 RPM at the motor"
GROUP_ALL = "all: [j1, j2, j3, j4, gripper]"


def _refusal(tmp_path: Path, *changes: tuple[str, str]) -> str:
    """The message of the refusal of the packaged file with each ``old`` (first occurrence) made ``new``."""
    text = PACKAGED.read_text(encoding="utf-8")
    for old, new in changes:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / "config.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    return message.removeprefix(f"{path}: ")


def _bomb_yaml() -> str:
    """11 levels of anchors, each 9 aliases of the one before: 10 kB of YAML, 3e10 values."""
    levels = ["&l0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    levels += [f"&l{i} [" + ", ".join([f"*l{i - 1}"] * 9) + "]" for i in range(1, 11)]
    return "[" + ", ".join(levels) + "]"


# --------------------------------------------------------------------------
# 1. An alias bomb ran until killed (the message printed the whole value).
# --------------------------------------------------------------------------


def test_an_alias_bomb_as_a_max_velocity_is_refused_within_a_second(tmp_path: Path) -> None:
    start = time.monotonic()
    message = _refusal(tmp_path, (J1_MAX_VELOCITY, f"max_velocity: {_bomb_yaml()}"))
    assert time.monotonic() - start < 1.0
    assert message == (
        "expands to more than 1,048,576 values through YAML aliases (*name); a file without aliases "
        "has fewer values than bytes, at most 1,048,576 (config.MAX_CONFIG_VALUES)"
    )


def test_a_value_that_contains_itself_is_refused(tmp_path: Path) -> None:
    message = _refusal(tmp_path, (J1_MAX_VELOCITY, "max_velocity: &loop [1, *loop]"))
    assert message == "a value contains itself (a YAML alias inside its own anchor)"


def test_a_huge_value_given_to_a_joint_directly_is_shown_cut_short() -> None:
    bomb: object = [1] * 9
    for _ in range(10):
        bomb = [bomb] * 9
    start = time.monotonic()
    with pytest.raises(ConfigError) as info:
        JointConfig(
            name="j1",
            address=0x11,
            joint_type="revolute",
            reduction=35.0,
            min=-3.0,
            max=3.0,
            max_velocity=bomb,  # type: ignore[arg-type]
            max_acceleration=2.0,
            stall_threshold=6,
            hold_current=20,
            drive_current=20,
            homing=HomingConfig(speed=0.03, threshold=30, current=15, acceleration=0.01),
        )
    assert time.monotonic() - start < 1.0
    assert str(info.value) == (
        "joint j1: max_velocity [[[...], [...], [...], [...], [...], [...], ...], [[...], [...], [...], "
        "[...], [...], [...], ...], [[...], [...], [...], [...], [...], [...], ...], [[...], [...], [...], "
        "[...], [...], [...], ...], [[...], [...], [...], [...], [...], [...], ...], [[...], [...], [...], "
        "[...], [...], [...], ...], ...] (list) must be a number"
    )


def test_an_int_beyond_any_float_is_refused(tmp_path: Path) -> None:
    """Was an OverflowError from float()."""
    message = _refusal(tmp_path, (J1_MAX_VELOCITY, "max_velocity: " + "1" * 400))
    assert (
        message
        == "joint j1: max_velocity 111111111111111111...1111111111111111111 is beyond any float (1.8e+308)"
    )


@pytest.mark.parametrize(
    ("value", "reason"),
    [
        # Was a ValueError from int() inside PyYAML.
        pytest.param(
            "1" * 5000,
            "Exceeds the limit (4300 digits) for integer string conversion: value has 5000 digits; "
            "use sys.set_int_max_str_digits() to increase the limit",
            id="int-of-5000-digits",
        ),
        # Was a ValueError from datetime.date() inside PyYAML.
        pytest.param("2024-13-45", "month must be in 1..12", id="impossible-date"),
    ],
)
def test_a_value_yaml_cannot_build_is_refused(tmp_path: Path, value: str, reason: str) -> None:
    message = _refusal(tmp_path, (J1_MAX_VELOCITY, f"max_velocity: {value}"))
    assert message == f"not valid YAML: a value cannot be read: {reason}"


# --------------------------------------------------------------------------
# 2. Speeds and accelerations too small to mean anything (1e-300: a wait of 1e300 s).
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        pytest.param(
            [(J1_MAX_VELOCITY, "max_velocity: 1.0e-300")],
            "joint j1: max_velocity 1e-300 rad/s crosses the joint's range (6.09294 rad) in 6.09e+300 s; "
            "at least 7.05e-05 rad/s, the range in a day "
            "(config.SLOWEST_MOTION_S: a slower limit is no speed)",
            id="max-velocity-1e-300",
        ),
        pytest.param(
            [(J1_MAX_ACCELERATION, "max_acceleration: 1.0e-300")],
            "joint j1: max_acceleration 1e-300 rad/s² crosses the joint's range (6.09294 rad) in "
            "4.94e+150 s or more; at least 3.26e-09 rad/s², the range in a day "
            "(config.SLOWEST_MOTION_S: a slower ramp is no acceleration)",
            id="max-acceleration-1e-300",
        ),
        pytest.param(
            [(J1_HOMING_ACCELERATION, "acceleration: 1.0e-300")],
            "joint j1: homing.acceleration 1e-300 rad/s² crosses the joint's range (6.09294 rad) in "
            "4.94e+150 s or more; at least 3.26e-09 rad/s², the range in a day "
            "(config.SLOWEST_MOTION_S: a slower ramp is no acceleration)",
            id="homing-acceleration-1e-300",
        ),
        # Within a day, but the driver chip's registers hold 0: the joint would not move.
        pytest.param(
            # (the homing speed made 1.9 RPM at the motor again, so the code before accepted the file)
            [
                (J1_REDUCTION, "reduction: 0.01"),
                (J1_MAX_VELOCITY, "max_velocity: 0.001"),
                (J1_HOMING_SPEED, "speed: 20.0"),
            ],
            "joint j1: max_velocity 0.001 rad/s is 0.000573 deg/s at the motor; the driver chip's speed "
            "register (VMAX, whole steps of 1/238.5 deg/s) holds 0 there and the joint would not move: "
            "at least 0.004193 deg/s (drive.VMAX_PER_DPS)",
            id="max-velocity-below-one-vmax-step",
        ),
        pytest.param(
            [(J1_MAX_ACCELERATION, "max_acceleration: 1.0e-4")],
            "joint j1: max_acceleration 0.0001 rad/s² is 0.2005 deg/s² at the motor; the driver chip's "
            "acceleration register (AMAX, whole steps of 1/3.129 deg/s²) holds 0 there and the joint would "
            "not ramp: at least 0.3196 deg/s² (drive.AMAX_PER_DPS2)",
            id="max-acceleration-below-one-amax-step",
        ),
        pytest.param(
            [(J1_HOMING_ACCELERATION, "acceleration: 1.0e-4")],
            "joint j1: homing.acceleration 0.0001 rad/s² is 0.2005 deg/s² at the motor; the driver chip's "
            "acceleration register (AMAX, whole steps of 1/3.129 deg/s²) holds 0 there and the joint would "
            "not ramp: at least 0.3196 deg/s² (drive.AMAX_PER_DPS2)",
            id="homing-acceleration-below-one-amax-step",
        ),
    ],
)
def test_a_speed_or_acceleration_too_small_to_mean_anything_is_refused(
    tmp_path: Path, changes: list[tuple[str, str]], expected: str
) -> None:
    assert _refusal(tmp_path, *changes) == expected


# --------------------------------------------------------------------------
# 3. bus_timing without an upper bound (1e9 us: 1000 s charged a transaction).
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        pytest.param(
            "host_overhead_us: 70.81",
            "host_overhead_us: 1.0e+9",
            "bus_timing.host_overhead_us 1000000000.0 us is longer than the firmware's deadman, 50000 us "
            '(docs/firmware.md, "Deadman"): a transaction must fit in it',
            id="host-overhead",
        ),
        pytest.param(
            "MOVETOANGLE: 353.1",
            "MOVETOANGLE: 50000.5",
            "bus_timing.handler_us.MOVETOANGLE 50000.5 us is longer than the firmware's deadman, 50000 us "
            '(docs/firmware.md, "Deadman"): a transaction must fit in it',
            id="handler",
        ),
        pytest.param(
            "program_overhead_us: 101.8",
            "program_overhead_us: 1.0e+12",
            "bus_timing.program_overhead_us 1000000000000.0 us is longer than the firmware's deadman, "
            '50000 us (docs/firmware.md, "Deadman"): a transaction must fit in it',
            id="program-overhead",
        ),
        pytest.param(
            "extra_periods: 3.526",
            "extra_periods: 5001",
            "bus_timing.extra_periods 5001.0 clock periods are 50010 us at 100000 Hz, longer than the "
            'firmware\'s deadman, 50000 us (docs/firmware.md, "Deadman"): a transaction must fit in it; '
            "at most 5000",
            id="extra-periods",
        ),
    ],
)
def test_a_bus_timing_part_longer_than_the_deadman_is_refused(
    tmp_path: Path, old: str, new: str, expected: str
) -> None:
    assert _refusal(tmp_path, (old, new)) == expected


# --------------------------------------------------------------------------
# 4. Groups: members that are no names (a TypeError), names that are a joint's.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("new", "expected"),
    [
        pytest.param(
            "all: [[j1]]",
            "groups.all: member ['j1'] (list) must be a joint or group name",
            id="list-member",
        ),
        pytest.param(
            "all: [j1, {j2: 1}]",
            "groups.all: member {'j2': 1} (dict) must be a joint or group name",
            id="mapping-member",
        ),
        pytest.param(
            "all: [j1, 2]",
            "groups.all: member 2 (int) must be a joint or group name",
            id="int-member",
        ),
        pytest.param(
            f"{GROUP_ALL}\n  j1: [j2]",
            "groups.j1: the name 'j1' is joint j1's and means that joint alone; "
            "give the group a name of its own",
            id="group-named-like-a-joint",
        ),
    ],
)
def test_a_group_member_that_is_no_name_or_a_group_named_like_a_joint_is_refused(
    tmp_path: Path, new: str, expected: str
) -> None:
    assert _refusal(tmp_path, (GROUP_ALL, new)) == expected


def test_a_group_named_gripper_must_be_the_gripper_alone(tmp_path: Path) -> None:
    message = _refusal(tmp_path, ("gripper: [gripper]", "gripper: [j1, gripper]"))
    assert message == (
        "groups.gripper: the name 'gripper' means the gripper alone; its group may only be [gripper]; "
        "give the group a name of its own"
    )


# --------------------------------------------------------------------------
# 6. An empty path was reported as ".: ... not a regular file".
# --------------------------------------------------------------------------


def test_an_empty_path_is_named() -> None:
    with pytest.raises(ConfigError) as info:
        load_config("")
    assert str(info.value) == "'': cannot read config file: an empty path; name the configuration file"


DXL_EXAMPLE = Path(__file__).parent.parent / "bioscara_gym" / "hardware" / "dynamixel" / "dynamixel_arm.yaml"


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "max_velocity: 2.3980823922402 # 100 velocity units",
            "max_velocity: 1.0e+6",
            "joint j1: max_velocity 1000000.0 rad/s is 1e+06 rad/s at the servo, beyond its Velocity Limit "
            "(6.355 rad/s: 265 units of 0.229 rev/min, the XL430's default; e-Manual)",
        ),
        (
            "max: 3.067961575772",
            "max: 100.0",
            "joint j1: max 100.0 rad is servo angle 100 rad, beyond the servo's turn (-3.14006..3.14159 rad: "
            "Goal Position 0-4095 about its centre 2047, position mode; e-Manual)",
        ),
        (
            "baudrate: 1000000",
            "baudrate: 1000000000000000000000000000000",
            "dynamixel.baudrate 1000000000000000000000000000000 is none of the servo's 9600, 57600, 115200, "
            "1000000, 2000000, 3000000, 4000000, 4500000 (e-Manual)",
        ),
    ],
    ids=["speed", "range", "baudrate"],
)
def test_a_dynamixel_limit_the_servo_cannot_keep_is_refused(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    # Seen (a hostile test): each loaded; a 2 rad move at 1e6 rad/s took the emulated servo 0.02 s.
    text = DXL_EXAMPLE.read_text(encoding="utf-8")
    assert old in text, old
    path = tmp_path / "dxl.yaml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: {message}"


def test_the_servo_bounds_are_the_control_tables() -> None:
    from bioscara_gym.hardware import config
    from bioscara_gym.hardware.dynamixel import control_table as ct

    velocity_limit = next(f.default for f in ct.CONTROL_TABLE if f.name == "Velocity Limit")
    assert velocity_limit * ct.VELOCITY_RADS_PER_UNIT == config.DXL_SPEED_MAX_RAD_S
    assert pytest.approx(ct.position_from_raw(4095)) == config.DXL_ANGLE_MAX_RAD
    assert pytest.approx(ct.position_from_raw(0)) == config.DXL_ANGLE_MIN_RAD
    assert tuple(ct.BAUD_RATES.values()) == config.DXL_BAUD_RATES


def test_a_joint_named_like_a_default_group_takes_that_name_from_it(tmp_path: Path) -> None:
    # A reviewer's: with no groups section, the loader's own default group "arm" was refused
    # as named like the joint, a group the file never wrote.
    text = PACKAGED.read_text(encoding="utf-8")
    text = text[: text.index("groups:")] + text[text.index("pid_noise:") :]  # no groups section
    path = tmp_path / "config.yaml"
    path.write_text(text.replace("name: j1", "name: arm", 1), encoding="utf-8")
    config = load_config(path)
    assert dict(config.groups) == {"all": ("arm", "j2", "j3", "j4", "gripper"), "gripper": ("gripper",)}
