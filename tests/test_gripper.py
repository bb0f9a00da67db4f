"""Tests of the gripper drivers (docs/arm.md, "The gripper").

Duty cycles are worked out by hand from the gripper numbers in docs/model.md
(reduction 3333.3 deg/m, offset 0.058 m, limits 0.04-0.12 m, backup 0.08 m):
``alpha = 3333.3 * (w - 0.058)`` deg, ``on_us = alpha / 90 * 500 + 1500``,
``duty_ns = round(on_us * 1000)``, period 20 ms.

The real :class:`Gripper` runs against a fake sysfs tree under ``tmp_path``;
the fake kernel creates ``pwm0`` when the driver, having written the channel
to ``export``, waits on its clock.
"""

from __future__ import annotations

import errno
import json
import math
import os
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.errors import (
    CommError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotInitError,
)
from bioscara_gym.hardware.gripper import (
    PWM_PERIOD_NS,
    BaseGripper,
    Gripper,
    GripperStateWarning,
    MockGripper,
    read_saved_width,
    save_width,
    servo_duty_cycle_ns,
    servo_pulse_us,
)

SPEC = {
    "reduction": 3333.3,
    "offset": 0.058,
    "min": 0.04,
    "max": 0.12,
    "backup_init_pos": 0.08,
}

#: (width in m, duty_cycle in ns), by hand from the formulas above.
KNOWN_DUTIES = [
    (0.058, 1_500_000),  # alpha 0 deg -> 1500 us
    (0.08, 1_907_403),  # alpha 73.3326 deg -> 1907.403 us
    (0.10, 2_277_770),  # alpha 139.9986 deg -> 2277.770 us
    (0.04, 1_166_670),  # alpha -59.9994 deg -> 1166.670 us (min)
    (0.12, 2_648_137),  # alpha 206.6646 deg -> 2648.137 us (max)
]
DUTY_BY_WIDTH = dict(KNOWN_DUTIES)


class FakePwmKernel(ManualClock):
    """A sysfs PWM tree plus a clock; the "kernel" acts while the driver sleeps.

    After ``N`` is written to ``pwmchipC/export``, the next ``sleep`` creates
    ``pwmchipC/pwmN`` with ``period``, ``duty_cycle`` and ``enable`` at 0,
    as the kernel does, unless ``responsive`` is False.
    """

    def __init__(self, root: Path, chip: int = 0, responsive: bool = True) -> None:
        """Create ``root/pwmchip{chip}`` with its ``export`` and ``npwm`` files."""
        super().__init__()
        self.root = root
        self.chip = root / f"pwmchip{chip}"
        self.chip.mkdir(parents=True)
        (self.chip / "export").write_text("")
        (self.chip / "unexport").write_text("")
        (self.chip / "npwm").write_text("2\n")
        self.responsive = responsive

    def create_channel(self, channel: int) -> Path:
        """Create ``pwm{channel}`` as the kernel does on export."""
        pwm = self.chip / f"pwm{channel}"
        pwm.mkdir()
        for attr in ("period", "duty_cycle", "enable"):
            (pwm / attr).write_text("0\n")
        return pwm

    def sleep(self, dt: float) -> None:
        """Advance time; create the exported channel if the driver asked for it."""
        super().sleep(dt)
        requested = (self.chip / "export").read_text().strip()
        if self.responsive and requested and not (self.chip / f"pwm{requested}").exists():
            self.create_channel(int(requested))

    def attr(self, name: str, channel: int = 0) -> int:
        """Read an attribute of ``pwm{channel}`` as an integer."""
        return int((self.chip / f"pwm{channel}" / name).read_text())


@pytest.fixture
def kernel(tmp_path: Path) -> FakePwmKernel:
    """Return a fake sysfs PWM tree with chip 0 and no exported channel."""
    return FakePwmKernel(tmp_path / "sys" / "class" / "pwm")


@pytest.fixture
def state_file(tmp_path: Path) -> Path:
    """Path of the gripper state file (not created)."""
    return tmp_path / "state" / "gripper.json"


@pytest.fixture(params=["mock", "sysfs"])
def make_gripper(
    request: pytest.FixtureRequest, kernel: FakePwmKernel, state_file: Path
) -> Callable[..., BaseGripper]:
    """Return a factory of new gripper objects of one backend sharing a state file."""

    def make(**overrides: object) -> BaseGripper:
        kwargs: dict = {**SPEC, "state_file": state_file, **overrides}
        if request.param == "mock":
            return MockGripper(**kwargs)
        return Gripper(**kwargs, sysfs_root=kernel.root, clock=kernel)

    return make


@pytest.fixture
def gripper(make_gripper: Callable[..., BaseGripper]) -> BaseGripper:
    """Return a gripper of each backend, not initialised."""
    return make_gripper()


@pytest.fixture
def enabled(gripper: BaseGripper) -> Iterator[BaseGripper]:
    """Yield a gripper of each backend, initialised and enabled (no state file)."""
    gripper.init()
    with pytest.warns(GripperStateWarning):
        gripper.enable()
    yield gripper
    gripper.deinit()


@pytest.fixture
def sysfs_gripper(kernel: FakePwmKernel, state_file: Path) -> Gripper:
    """Return the real driver on the fake sysfs tree, not initialised."""
    return Gripper(**SPEC, state_file=state_file, sysfs_root=kernel.root, clock=kernel)


def commanded_duty_ns(gripper: BaseGripper, kernel: FakePwmKernel) -> int:
    """Return the duty cycle in ns the backend was last told to output."""
    if isinstance(gripper, MockGripper):
        assert gripper.servo_angle_deg is not None
        return servo_duty_cycle_ns(gripper.servo_angle_deg)
    return kernel.attr("duty_cycle")


def output_on(gripper: BaseGripper, kernel: FakePwmKernel) -> bool:
    """Whether the backend's servo signal is on."""
    if isinstance(gripper, MockGripper):
        return gripper.output_enabled
    return kernel.attr("enable") == 1


def saved_width(state_file: Path) -> float:
    """Return the width in m stored in the state file."""
    return json.loads(state_file.read_text())["width_m"]


def leftover_files(directory: Path) -> list[str]:
    """Names in ``directory`` other than the state file."""
    return sorted(p.name for p in directory.iterdir() if p.name != "gripper.json")


# -- pure conversions -----------------------------------------------------------


@pytest.mark.parametrize(
    ("angle_deg", "duty_ns"),
    [(0.0, 1_500_000), (90.0, 2_000_000), (-90.0, 1_000_000), (45.0, 1_750_000)],
)
def test_servo_duty_cycle_ns_for_known_angles(angle_deg: float, duty_ns: int) -> None:
    """Pulse = angle/90 * 500 + 1500 us, written in ns."""
    assert servo_duty_cycle_ns(angle_deg) == duty_ns


@pytest.mark.parametrize(("angle_deg", "percent"), [(0.0, 7.5), (90.0, 10.0), (-90.0, 5.0)])
def test_servo_duty_percent_for_known_angles(angle_deg: float, percent: float) -> None:
    """Duty percent = on-time / 20 ms period * 100."""
    assert servo_duty_cycle_ns(angle_deg) / PWM_PERIOD_NS * 100.0 == pytest.approx(percent)


@pytest.mark.parametrize("angle_deg", [-270.0, 3400.0, math.nan, math.inf])
def test_servo_angle_outside_pulse_range_raises(angle_deg: float) -> None:
    """Angles whose pulse is not within (0, 20 ms), or non-finite, are refused."""
    with pytest.raises(InvalidArgumentError, match="servo angle"):
        servo_duty_cycle_ns(angle_deg)


def test_pwm_period_is_50_hz() -> None:
    """The servo PWM period is 1e9 / 50 ns."""
    assert PWM_PERIOD_NS == 20_000_000


# -- construction --------------------------------------------------------------


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ({"reduction": 0.0}, "reduction must be non-zero"),
        ({"reduction": math.nan}, "reduction nan is not finite"),
        ({"min": 0.12, "max": 0.04}, "min must be less than max"),
        ({"backup_init_pos": 0.2}, "backup initial width 0.2 m is outside"),
        ({"offset": "wide"}, "offset 'wide' is not a number"),
    ],
)
def test_invalid_parameters_raise(override: dict, match: str) -> None:
    """Bad constructor parameters raise InvalidArgumentError naming the field."""
    with pytest.raises(InvalidArgumentError, match=match):
        MockGripper(**{**SPEC, **override})


@pytest.mark.parametrize("override", [{"pwm_chip": -1}, {"pwm_channel": 1.5}])
def test_invalid_pwm_numbers_raise(kernel: FakePwmKernel, override: dict) -> None:
    """PWM chip and channel must be non-negative integers."""
    with pytest.raises(InvalidArgumentError, match="non-negative integer"):
        Gripper(**SPEC, sysfs_root=kernel.root, **override)


# -- life cycle ------------------------------------------------------------------


@pytest.mark.parametrize(
    "call",
    [
        lambda g: g.enable(),
        lambda g: g.disable(),
        lambda g: g.set_position(0.08),
        lambda g: g.get_position(),
        lambda g: g.set_servo_position(0.0),
    ],
    ids=["enable", "disable", "set_position", "get_position", "set_servo_position"],
)
def test_use_before_init_raises_not_init(gripper: BaseGripper, call: Callable[[BaseGripper], object]) -> None:
    """Every call but init()/deinit() needs init() first."""
    with pytest.raises(NotInitError, match="gripper: not initialized"):
        call(gripper)


def test_use_after_deinit_raises_not_init(enabled: BaseGripper) -> None:
    """deinit() returns the gripper to the not-initialised state."""
    enabled.deinit()
    with pytest.raises(NotInitError):
        enabled.get_position()


def test_set_position_while_disabled_raises_not_enabled(gripper: BaseGripper) -> None:
    """Positions are only accepted while enabled."""
    gripper.init()
    with pytest.raises(NotEnabledError, match="call enable"):
        gripper.set_position(0.1)


def test_deinit_before_init_does_nothing(gripper: BaseGripper) -> None:
    """deinit() is safe in clean-up code."""
    gripper.deinit()
    assert not gripper.is_initialized


def test_enable_switches_output_on(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """enable() turns the servo signal on."""
    assert enabled.is_enabled
    assert output_on(enabled, kernel)


def test_disable_switches_output_off(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """disable() turns the servo signal off."""
    enabled.disable()
    assert not enabled.is_enabled
    assert not output_on(enabled, kernel)


def test_deinit_disables_an_enabled_gripper(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """deinit() on an enabled gripper disables it first."""
    enabled.deinit()
    assert not enabled.is_enabled
    assert not output_on(enabled, kernel)


def test_context_manager_leaves_gripper_disabled(gripper: BaseGripper, kernel: FakePwmKernel) -> None:
    """Leaving the with block disables and deinitialises."""
    with gripper as g, pytest.warns(GripperStateWarning):
        g.enable()
        g.set_position(0.1)
    assert not gripper.is_enabled
    assert not gripper.is_initialized
    assert not output_on(gripper, kernel)


def test_context_manager_disables_when_the_block_raises(gripper: BaseGripper, kernel: FakePwmKernel) -> None:
    """An exception in the with block still leaves the servo off."""
    with pytest.raises(RuntimeError, match="policy crashed"), gripper as g:
        with pytest.warns(GripperStateWarning):
            g.enable()
        raise RuntimeError("policy crashed")
    assert not output_on(gripper, kernel)


def test_context_manager_returns_initialized_gripper(gripper: BaseGripper) -> None:
    """__enter__ initialises but does not enable."""
    with gripper as g:
        assert g is gripper
        assert g.is_initialized
        assert not g.is_enabled


# -- width, clamping, transmission ------------------------------------------------


@pytest.mark.parametrize(("width_m", "duty_ns"), KNOWN_DUTIES)
def test_duty_cycle_for_known_widths(
    enabled: BaseGripper, kernel: FakePwmKernel, width_m: float, duty_ns: int
) -> None:
    """Widths map to the hand-computed duty cycles."""
    enabled.set_position(width_m)
    assert commanded_duty_ns(enabled, kernel) == duty_ns


def test_width_is_clamped_to_max(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """Widths above max are commanded and reported as max."""
    enabled.set_position(0.5)
    assert enabled.get_position() == 0.12
    assert commanded_duty_ns(enabled, kernel) == DUTY_BY_WIDTH[0.12]


def test_width_is_clamped_to_min(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """Widths below min are commanded and reported as min."""
    enabled.set_position(-1.0)
    assert enabled.get_position() == 0.04
    assert commanded_duty_ns(enabled, kernel) == DUTY_BY_WIDTH[0.04]


@pytest.mark.parametrize("width_m", [math.nan, math.inf, -math.inf])
def test_non_finite_width_raises_and_keeps_last_command(
    enabled: BaseGripper, kernel: FakePwmKernel, width_m: float
) -> None:
    """NaN/inf widths raise, naming gripper and value; nothing moves."""
    enabled.set_position(0.1)
    with pytest.raises(InvalidArgumentError, match=rf"gripper: width \(m\) {width_m!r}"):
        enabled.set_position(width_m)
    assert enabled.get_position() == 0.1
    assert commanded_duty_ns(enabled, kernel) == DUTY_BY_WIDTH[0.10]


def test_invalid_argument_error_is_a_value_error(enabled: BaseGripper) -> None:
    """Bad input can be caught as ValueError."""
    with pytest.raises(ValueError):
        enabled.set_position(math.nan)


def test_get_position_returns_last_command(enabled: BaseGripper) -> None:
    """Without feedback the last commanded width is reported."""
    enabled.set_position(0.1)
    assert enabled.get_position() == 0.1


def test_get_position_before_enable_is_backup_width(gripper: BaseGripper) -> None:
    """Before enable() the backup initial width is reported."""
    gripper.init()
    assert gripper.get_position() == 0.08


def test_set_offset_moves_the_servo_zero(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """set_offset changes the width at which the servo is at 0 deg."""
    enabled.set_offset(0.1)
    enabled.set_position(0.1)
    assert commanded_duty_ns(enabled, kernel) == 1_500_000


def test_set_reduction_scales_the_angle(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """set_reduction changes degrees per m."""
    enabled.set_reduction(3000.0)
    enabled.set_position(0.088)  # 3000 * (0.088 - 0.058) = 90 deg
    assert commanded_duty_ns(enabled, kernel) == 2_000_000


def test_set_servo_position_does_not_change_reported_width(
    enabled: BaseGripper, kernel: FakePwmKernel
) -> None:
    """Direct servo angles (calibration) do not change get_position()."""
    enabled.set_servo_position(90.0)
    assert commanded_duty_ns(enabled, kernel) == 2_000_000
    assert enabled.get_position() == 0.08


def test_mock_gripper_mirrors_servo_angle() -> None:
    """MockGripper stores the angle reduction * (w - offset)."""
    g = MockGripper(**SPEC, state_file=None)
    g.init()
    g.enable()
    g.set_position(0.1)
    assert g.servo_angle_deg == pytest.approx(3333.3 * (0.1 - 0.058))


# -- persistence -------------------------------------------------------------------


def test_disable_saves_width_as_json(enabled: BaseGripper, state_file: Path) -> None:
    """The state file is {"width_m": <float>}."""
    enabled.set_position(0.1)
    enabled.disable()
    assert json.loads(state_file.read_text()) == {"width_m": 0.1}


def _at_width_over(gripper: BaseGripper, state_file: Path, content: str) -> None:
    """``gripper`` enabled over a state file holding ``content`` (it warns), then commanded to 0.1 m."""
    state_file.parent.mkdir(parents=True)
    state_file.write_text(content)
    gripper.init()
    with pytest.warns(GripperStateWarning):
        gripper.enable()
    gripper.set_position(0.1)


@pytest.mark.parametrize(
    "content", ["my notes\n", '{"colour": "red"}\n', "# an arm configuration\ngripper:\n  min: 0.04\n"]
)
def test_a_state_file_that_holds_something_else_is_not_replaced(
    gripper: BaseGripper, state_file: Path, content: str
) -> None:
    # Seen (a hostile test): a configuration whose gripper.state_file named the configuration
    # itself was replaced by {"width_m": 0.06}; notes.txt was too, after a warning.
    _at_width_over(gripper, state_file, content)
    with pytest.warns(GripperStateWarning) as record:
        gripper.disable()
    assert str(record[0].message) == (
        f"gripper: cannot save width 0.1 m to state file {state_file} (exists and is not a gripper state "
        'file ({"width_m": ...}); give a new file, or a gripper state file ({"width_m": ...}) to replace '
        "(or delete it)); the next enable() will not know where the fingers are"
    )
    assert state_file.read_text() == content


@pytest.mark.parametrize("content", ['{"width_m": "x"}', '{"width_m": NaN}', '{"width_m": 5}', ""])
def test_a_damaged_state_file_is_mended_by_the_next_save(
    gripper: BaseGripper, state_file: Path, content: str
) -> None:
    _at_width_over(gripper, state_file, content)
    gripper.disable()
    assert json.loads(state_file.read_text()) == {"width_m": 0.1}


def test_width_persists_across_disable_enable(enabled: BaseGripper, kernel: FakePwmKernel) -> None:
    """enable() restores and re-commands the width saved by disable()."""
    enabled.set_position(0.1)
    enabled.disable()
    enabled.set_servo_position(0.0)  # scribble, so enable must re-command
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        enabled.enable()
    assert enabled.get_position() == 0.1
    assert commanded_duty_ns(enabled, kernel) == DUTY_BY_WIDTH[0.10]


def test_width_persists_across_new_gripper_object(
    enabled: BaseGripper,
    make_gripper: Callable[..., BaseGripper],
    kernel: FakePwmKernel,
) -> None:
    """A new object (a new process) restores the saved width."""
    enabled.set_position(0.1)
    enabled.deinit()
    with make_gripper() as fresh, warnings.catch_warnings():
        warnings.simplefilter("error")
        fresh.enable()
        assert fresh.get_position() == 0.1
        assert commanded_duty_ns(fresh, kernel) == DUTY_BY_WIDTH[0.10]


def test_missing_state_file_uses_backup_and_warns(
    gripper: BaseGripper, kernel: FakePwmKernel, state_file: Path
) -> None:
    """No state file: backup width, with a warning naming the file."""
    gripper.init()
    with pytest.warns(GripperStateWarning, match=rf"{state_file.name} does not exist"):
        gripper.enable()
    assert gripper.get_position() == 0.08
    assert commanded_duty_ns(gripper, kernel) == DUTY_BY_WIDTH[0.08]


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"", "not valid JSON"),
        (b'{"width_m": 0.1', "not valid JSON"),
        (b"\xff\xfe", "cannot read"),
        (b"[0.1]", "does not hold"),
        (b'{"width": 0.1}', "does not hold"),
        (b'{"width_m": "0.1"}', "does not hold"),
        (b'{"width_m": true}', "does not hold"),
        (b'{"width_m": NaN}', "outside"),
        (b'{"width_m": 0.5}', "outside"),
        (b'{"width_m": 0.01}', "outside"),
    ],
    ids=[
        "empty",
        "truncated",
        "not-utf8",
        "list",
        "wrong-key",
        "string",
        "bool",
        "nan",
        "above-max",
        "below-min",
    ],
)
def test_corrupt_state_file_uses_backup_and_warns(
    gripper: BaseGripper,
    kernel: FakePwmKernel,
    state_file: Path,
    content: bytes,
    reason: str,
) -> None:
    """Unusable contents: backup width, warning naming file and reason."""
    state_file.parent.mkdir(parents=True)
    state_file.write_bytes(content)
    gripper.init()
    with pytest.warns(GripperStateWarning) as record:
        gripper.enable()
    message = str(record[0].message)
    assert str(state_file) in message
    assert reason in message
    assert gripper.get_position() == 0.08
    assert commanded_duty_ns(gripper, kernel) == DUTY_BY_WIDTH[0.08]


def test_unreadable_state_file_uses_backup_and_warns(gripper: BaseGripper, state_file: Path) -> None:
    """A state file that cannot be read: backup width and a warning."""
    state_file.mkdir(parents=True)  # a directory where the file should be
    gripper.init()
    with pytest.warns(GripperStateWarning, match="cannot read state file"):
        gripper.enable()
    assert gripper.get_position() == 0.08


def test_no_state_file_uses_backup_without_warning(
    make_gripper: Callable[..., BaseGripper],
) -> None:
    """state_file=None means no persistence and no warning."""
    g = make_gripper(state_file=None)
    g.init()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g.enable()
        g.disable()
    assert g.get_position() == 0.08


def test_disable_without_enable_keeps_saved_width(
    make_gripper: Callable[..., BaseGripper], state_file: Path
) -> None:
    """A never-enabled gripper does not overwrite the saved width."""
    state_file.parent.mkdir(parents=True)
    state_file.write_text('{"width_m": 0.1}\n')
    g = make_gripper()
    g.init()
    g.disable()
    g.deinit()
    assert saved_width(state_file) == 0.1


def test_release_of_an_enabled_gripper_disables_it_saving_its_width(
    enabled: BaseGripper, kernel: FakePwmKernel, state_file: Path
) -> None:
    """release() is disable() for a gripper this driver enabled."""
    enabled.set_position(0.05)
    enabled.release()
    assert not enabled.is_enabled
    assert not output_on(enabled, kernel)
    assert saved_width(state_file) == 0.05


def test_release_switches_off_a_servo_an_earlier_process_left_driven(
    sysfs_gripper: Gripper, kernel: FakePwmKernel, state_file: Path
) -> None:
    """The output goes off; the width saved before stays (this process does not know the servo's)."""
    state_file.parent.mkdir(parents=True)
    state_file.write_text('{"width_m": 0.1}\n')
    kernel.create_channel(0)
    (kernel.chip / "pwm0" / "enable").write_text("1\n")
    sysfs_gripper.init()
    assert sysfs_gripper.output_enabled and not sysfs_gripper.is_enabled
    sysfs_gripper.release()
    assert kernel.attr("enable") == 0
    assert saved_width(state_file) == 0.1


def test_release_of_a_servo_switched_off_writes_nothing(
    sysfs_gripper: Gripper, kernel: FakePwmKernel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Nothing to switch off: no sysfs write (the output may belong to no one)."""
    sysfs_gripper.init()
    written: list[tuple[Path, int]] = []
    monkeypatch.setattr(sysfs_gripper, "_write", lambda path, value: written.append((path, value)))
    sysfs_gripper.release()
    assert written == []


def test_atomic_write_leaves_no_temp_files(enabled: BaseGripper, state_file: Path) -> None:
    """Saving leaves only the state file in its directory."""
    for width_m in (0.05, 0.1, 0.07):
        enabled.set_position(width_m)
        enabled.disable()
        enabled.enable()
    assert leftover_files(state_file.parent) == []
    assert saved_width(state_file) == 0.07


def test_save_width_then_read_saved_width_round_trips(state_file: Path) -> None:
    """The public pair writes and reads the gripper's own state-file format."""
    save_width(state_file, 0.095)
    assert json.loads(state_file.read_text()) == {"width_m": 0.095}
    assert read_saved_width(state_file) == 0.095


def test_read_saved_width_reads_what_disable_saved(enabled: BaseGripper, state_file: Path) -> None:
    enabled.set_position(0.1)
    enabled.disable()
    assert read_saved_width(state_file) == 0.1


@pytest.mark.parametrize("content", [None, b"", b"[0.08]", b'{"width": 0.08}', b'{"width_m": true}'])
def test_read_saved_width_is_none_without_a_usable_file(state_file: Path, content: bytes | None) -> None:
    """Missing or unusable state files give None, without a warning."""
    if content is not None:
        state_file.parent.mkdir(parents=True)
        state_file.write_bytes(content)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_saved_width(state_file) is None


def test_read_saved_width_of_no_file_is_none() -> None:
    assert read_saved_width(None) is None


def test_failed_replace_keeps_previous_file(
    enabled: BaseGripper,
    state_file: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A save that fails mid-way leaves the previous file intact."""
    enabled.set_position(0.1)
    enabled.disable()
    enabled.enable()
    enabled.set_position(0.05)

    def fail_replace(src: object, dst: object) -> None:
        raise OSError(errno.EIO, "simulated I/O error")

    monkeypatch.setattr(os, "replace", fail_replace)
    with pytest.warns(GripperStateWarning, match="simulated I/O error"):
        enabled.disable()
    assert saved_width(state_file) == 0.1
    assert leftover_files(state_file.parent) == []


def _disk_full(src: object, dst: object) -> None:
    """``os.replace`` on a full disk."""
    raise OSError(errno.ENOSPC, "No space left on device")


def test_failed_save_still_switches_output_off(
    enabled: BaseGripper, kernel: FakePwmKernel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A failed save warns but the servo is still switched off."""

    monkeypatch.setattr(os, "replace", _disk_full)
    with pytest.warns(GripperStateWarning, match="cannot save width"):
        enabled.disable()
    assert not enabled.is_enabled
    assert not output_on(enabled, kernel)


def test_a_failed_save_is_reported_in_words_with_its_reason(
    enabled: BaseGripper, state_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """save_status() says the width was NOT saved, and why."""

    monkeypatch.setattr(os, "replace", _disk_full)
    with pytest.warns(GripperStateWarning):
        enabled.disable()
    assert enabled.save_status() == f"NOT saved to {state_file}: No space left on device"


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda g: g.set_offset(float("nan")), "gripper: offset nan is not finite"),
        (lambda g: g.set_offset("x"), "gripper: offset 'x' is not a number"),
        (lambda g: g.set_reduction(float("inf")), "gripper: reduction inf is not finite"),
        (lambda g: g.set_position(0.05), "gripper: set_position(0.05) while disabled; call enable() first"),
    ],
    ids=["offset-nan", "offset-text", "reduction-inf", "position-disabled"],
)
def test_a_refusal_names_the_gripper_and_the_parameter(
    call: Callable[[BaseGripper], None], message: str
) -> None:
    g = MockGripper(**SPEC)
    g.init()
    with pytest.raises(JointError) as err:
        call(g)
    assert str(err.value) == message
    assert err.value.joint == "gripper"


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("offset", math.nan, "gripper: offset nan is not finite"),
        ("min", "a", "gripper: min width 'a' is not a number"),
        ("max", math.inf, "gripper: max width inf is not finite"),
        ("backup_init_pos", -math.inf, "gripper: backup initial width -inf is not finite"),
        ("reduction", "r", "gripper: reduction 'r' is not a number"),
        ("min", 0.2, "gripper: width limits [0.2, 0.12] m; min must be less than max"),
        ("min", 0.12, "gripper: width limits [0.12, 0.12] m; min must be less than max"),
    ],
)
def test_a_bad_parameter_is_refused_naming_the_gripper_and_the_parameter(
    field: str, value: object, message: str
) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        MockGripper(**{**SPEC, field: value})
    assert str(err.value) == message
    assert err.value.joint == "gripper"


@pytest.mark.parametrize("backup", [0.04, 0.12], ids=["at-min", "at-max"])
def test_a_backup_width_at_a_limit_is_taken(backup: float) -> None:
    assert MockGripper(**{**SPEC, "backup_init_pos": backup}).backup_init_pos == backup


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("pwm_channel", -1, "gripper: pwm_channel -1 must be a non-negative integer"),
        ("pwm_chip", True, "gripper: pwm_chip True must be a non-negative integer"),
        ("export_timeout_s", math.nan, "gripper: export_timeout_s nan must be finite and >= 0"),
    ],
)
def test_a_bad_pwm_setting_is_refused_naming_it(field: str, value: object, message: str) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        Gripper(**SPEC, **{field: value})
    assert str(err.value) == message
    assert err.value.joint == "gripper"


def test_a_gripper_never_enabled_says_it_saved_nothing(state_file: Path) -> None:
    g = MockGripper(**SPEC, state_file=state_file)
    assert g.save_status() == f"not saved (the gripper was not enabled; {state_file} unchanged)"


def test_a_pulse_just_above_zero_is_taken() -> None:
    # -269.91 deg: -269.91 / 90 * 500 + 1500 = 0.5 us, inside (0, 20000) us.
    assert servo_pulse_us(-269.91) == pytest.approx(0.5)


def test_a_pulse_beyond_the_period_names_the_period() -> None:
    # 10000 deg: 10000 / 90 * 500 + 1500 = 57055.6 us (mGripper.cpp's mapping), past the 20 ms period.
    with pytest.raises(InvalidArgumentError) as err:
        servo_duty_cycle_ns(1e4)
    assert str(err.value) == (
        "servo angle 10000 deg gives a 57055.6 us pulse; must be between 0 and 20000 us (the 50 Hz period)"
    )


# -- sysfs PWM backend ----------------------------------------------------------------


def test_init_exports_missing_channel(sysfs_gripper: Gripper, kernel: FakePwmKernel) -> None:
    """init() writes the channel number to export when pwmM is missing."""
    sysfs_gripper.init()
    assert (kernel.chip / "export").read_text() == "0"
    assert sysfs_gripper.pwm_path == kernel.chip / "pwm0"
    assert sysfs_gripper.pwm_path.is_dir()


def test_init_does_not_export_an_exported_channel(sysfs_gripper: Gripper, kernel: FakePwmKernel) -> None:
    """An already exported channel is not exported again."""
    kernel.create_channel(0)
    sysfs_gripper.init()
    assert (kernel.chip / "export").read_text() == ""


def test_init_sets_50_hz_period(sysfs_gripper: Gripper, kernel: FakePwmKernel) -> None:
    """init() writes period = 20 ms."""
    sysfs_gripper.init()
    assert kernel.attr("period") == 20_000_000


def test_init_does_not_enable_output(sysfs_gripper: Gripper, kernel: FakePwmKernel) -> None:
    """init() leaves the output off."""
    sysfs_gripper.init()
    assert kernel.attr("enable") == 0


def test_uses_configured_chip_and_channel(tmp_path: Path) -> None:
    """pwm_chip and pwm_channel select the sysfs directory."""
    kernel = FakePwmKernel(tmp_path / "pwm", chip=2)
    g = Gripper(**SPEC, pwm_chip=2, pwm_channel=1, sysfs_root=kernel.root, clock=kernel)
    g.init()
    assert (kernel.chip / "export").read_text() == "1"
    assert kernel.attr("period", channel=1) == 20_000_000


def test_export_timeout_raises_comm_error(tmp_path: Path) -> None:
    """A channel that never becomes writable raises after the timeout."""
    kernel = FakePwmKernel(tmp_path / "pwm", responsive=False)
    g = Gripper(**SPEC, sysfs_root=kernel.root, clock=kernel, export_timeout_s=0.5)
    with pytest.raises(CommError, match=r"^gripper: .*pwm0/period is not writable 0.5 s after"):
        g.init()
    assert kernel.now() == pytest.approx(0.5, abs=0.02)


def test_missing_chip_raises_with_overlay_hint(tmp_path: Path) -> None:
    """A missing pwmchipN raises CommError with the overlay hint."""
    g = Gripper(**SPEC, sysfs_root=tmp_path / "no-pwm")
    with pytest.raises(
        CommError, match=r"^gripper: PWM chip .*pwmchip0 does not exist.*dtoverlay=pwm"
    ) as info:
        g.init()
    assert isinstance(info.value, JointError)
    cause = info.value.__cause__
    assert isinstance(cause, FileNotFoundError)
    assert (cause.errno, cause.strerror, cause.filename) == (
        errno.ENOENT,
        "No such file or directory",
        str(tmp_path / "no-pwm" / "pwmchip0"),
    )


def test_an_export_timeout_of_zero_does_not_wait(tmp_path: Path) -> None:
    """The deadline is met at once: no poll past it."""
    kernel = FakePwmKernel(tmp_path / "pwm", responsive=False)
    g = Gripper(**SPEC, sysfs_root=kernel.root, clock=kernel, export_timeout_s=0.0)
    with pytest.raises(CommError, match=r"pwm0/period is not writable 0 s after"):
        g.init()
    assert kernel.now() == 0.0


@pytest.fixture
def failing_attr(monkeypatch: pytest.MonkeyPatch) -> Callable[[str, OSError], None]:
    """Make opening one sysfs attribute fail, as the kernel or the VFS would."""

    def install(attr: str, error: OSError) -> None:
        real_open = os.open

        def fake_open(path: object, flags: int, *args: object, **kwargs: object) -> int:
            if Path(os.fspath(path)).name == attr and flags & os.O_WRONLY:
                raise error
            return real_open(path, flags, *args, **kwargs)

        monkeypatch.setattr(os, "open", fake_open)

    return install


def test_permission_error_names_file_with_hint(
    sysfs_gripper: Gripper,
    failing_attr: Callable[[str, OSError], None],
) -> None:
    """Permission errors name the file and hint at the gpio group."""
    failing_attr("period", PermissionError(errno.EACCES, "Permission denied"))
    expected = r"^gripper: permission denied writing 20000000 to .*pwm0/period"
    with pytest.raises(CommError, match=expected) as info:
        sysfs_gripper.init()
    assert "group 'gpio'" in str(info.value)
    assert isinstance(info.value.__cause__, PermissionError)


def test_kernel_rejecting_a_write_raises_comm_error(
    sysfs_gripper: Gripper,
    failing_attr: Callable[[str, OSError], None],
) -> None:
    """A write the kernel rejects raises CommError; enable fails."""
    sysfs_gripper.init()
    failing_attr("duty_cycle", OSError(errno.EINVAL, "Invalid argument"))
    with (
        pytest.raises(CommError, match=r"^gripper: writing \d+ to .*duty_cycle failed: Invalid argument"),
        pytest.warns(GripperStateWarning),
    ):
        sysfs_gripper.enable()
    assert not sysfs_gripper.is_enabled


def test_unexported_channel_raises_comm_error(sysfs_gripper: Gripper, kernel: FakePwmKernel) -> None:
    """A channel unexported behind our back raises a clear CommError."""
    sysfs_gripper.init()
    for attr in sysfs_gripper.pwm_path.iterdir():
        attr.unlink()
    sysfs_gripper.pwm_path.rmdir()
    with (
        pytest.raises(
            CommError, match=r"^gripper: .*pwm0/duty_cycle does not exist; was the channel unexported"
        ),
        pytest.warns(GripperStateWarning),
    ):
        sysfs_gripper.enable()


def test_enable_writes_duty_cycle_before_enable(
    sysfs_gripper: Gripper, kernel: FakePwmKernel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """enable() sets the duty cycle, then enable=1 (no stray pulse)."""
    sysfs_gripper.init()
    written: list[str] = []
    real_open = os.open

    def recording_open(path: object, flags: int, *args: object, **kwargs: object) -> int:
        if flags & os.O_WRONLY:
            written.append(Path(os.fspath(path)).name)
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", recording_open)
    with pytest.warns(GripperStateWarning):
        sysfs_gripper.enable()
    pwm_writes = [name for name in written if name in ("duty_cycle", "enable")]
    assert pwm_writes == ["duty_cycle", "enable"]


def test_disable_saves_width_before_switching_off(
    sysfs_gripper: Gripper, monkeypatch: pytest.MonkeyPatch
) -> None:
    """disable() saves the width, then writes enable=0."""
    sysfs_gripper.init()
    with pytest.warns(GripperStateWarning):
        sysfs_gripper.enable()
    events: list[str] = []
    real_open, real_replace = os.open, os.replace

    def recording_open(path: object, flags: int, *args: object, **kwargs: object) -> int:
        if flags & os.O_WRONLY and Path(os.fspath(path)).name == "enable":
            events.append("enable")
        return real_open(path, flags, *args, **kwargs)

    def recording_replace(src: object, dst: object) -> None:
        events.append("save")
        real_replace(src, dst)

    monkeypatch.setattr(os, "open", recording_open)
    monkeypatch.setattr(os, "replace", recording_replace)
    sysfs_gripper.disable()
    assert events == ["save", "enable"]
