"""The operator console: ``bioscara status|ping|enable|disable|home|move|gripper|monitor``.

Subcommands run through ``bioscara_gym.cli.main`` on the emulated backend
(one test through a real subprocess); the dashboard is rendered to a
recording console and driven key by key without a terminal.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from rich.console import Console

import bioscara_gym
from bioscara_gym.cli import main
from bioscara_gym.console import commands
from bioscara_gym.console.commands import ping_devices
from bioscara_gym.console.dashboard import (
    BusView,
    DashboardSnapshot,
    JointView,
    MonitorApp,
    handle_key,
    position_bar,
    render_dashboard,
)
from bioscara_gym.console.format import flags_text
from bioscara_gym.console.session import Session
from bioscara_gym.console.state import STATE_FORMAT, lock_path
from bioscara_gym.console.targets import ConsoleOptions, resolve_target
from bioscara_gym.errors import refusal
from bioscara_gym.fsutil import LockFile
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.errors import (
    ArmStateError,
    CommError,
    InvalidArgumentError,
    JointError,
    MissingExtraError,
    NotHomedError,
    StalledError,
)
from bioscara_gym.hardware.registers import Flag

CONFIG = load_config()
DEFAULT_CONFIG = Path(bioscara_gym.__file__).parent / "hardware" / "default_config.yaml"
LIMITS = {j.name: (j.min, j.max) for j in CONFIG.joints}
ROW = re.compile(r"^\s*(j\d|gripper)\s+(.*)$")
#: ``bioscara ARGS`` -> exit code, stdout, stderr (whitespace joined).
Run = Callable[..., tuple[int, str, str]]


@pytest.fixture
def state(tmp_path: Path) -> Path:
    """A state file path (not yet created)."""
    return tmp_path / "arm.json"


def rows(out: str) -> dict[str, list[str]]:
    """The status table's rows: device name to its cells (split on runs of spaces)."""
    table = {}
    for line in out.splitlines():
        m = ROW.match(line)
        if m:
            table[m.group(1)] = re.split(r"\s{2,}", m.group(2).strip())
    return table


def status(bioscara: Run, state: Path) -> dict[str, list[str]]:
    code, out, _ = bioscara("status", "--state", str(state))
    assert code == 0
    return rows(out)


def enabled(table: dict[str, list[str]], name: str) -> str:
    """The ``enabled`` cell of a status row (the gripper row has no velocity)."""
    cells = table[name]
    return cells[2] if name != "gripper" else cells[1]


@pytest.fixture
def session() -> Iterator[Session]:
    """An open emulated session without a state file."""
    with Session(ConsoleOptions()) as s:
        yield s


# ------------------------------------------------------------------ status
def test_status_shows_a_powered_up_arm(bioscara: Run) -> None:
    code, out, _ = bioscara("status")
    assert code == 0
    assert "arm inactive · backend emulated" in out
    table = rows(out)
    for name in CONFIG.names:
        assert table[name][0] == "-"  # position unknown until homed
        assert table[name][2:5] == ["no", "no", "NOT_HOMED NOT_ENABLED"]
    assert table["gripper"] == ["0.0800 m", "no"]


def test_status_runs_as_a_subprocess(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "bioscara_gym.cli", "status"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
        env={"PATH": "/usr/bin:/bin", "COLUMNS": "120", "MUJOCO_GL": "egl"},
    )
    assert result.returncode == 0, result.stderr
    assert "arm inactive" in result.stdout
    assert re.search(r"j4\s+-\s+\+0\.0000 rad/s\s+no\s+no\s+NOT_HOMED NOT_ENABLED", result.stdout)


def test_status_counts_bus_transactions(bioscara: Run) -> None:
    _, out, _ = bioscara("status")
    # configure: PING, then one read of position and velocity per joint
    assert rows(out)["j1"][-2:] == ["3", "0"]


def test_status_names_the_extra_the_bus_budget_needs(bioscara: Run, monkeypatch: pytest.MonkeyPatch) -> None:
    # Without MuJoCo the budget cannot be measured; the line says which extra gives it.
    # Printed as markup, "[sim]" was taken for a style tag and vanished.
    def missing(config: object) -> None:
        raise MissingExtraError("the emulated backend", "sim")

    monkeypatch.setattr(commands, "bus_budget", missing)
    code, out, _ = bioscara("status")
    assert code == 0
    assert (
        "bus time per cycle: not counted (the emulated backend needs the [sim] extra: "
        "pip install 'bioscara-gym[sim]')" in out
    )


# -------------------------------------------------------------------- ping
def test_ping_lists_every_joint_ok(bioscara: Run) -> None:
    code, out, _ = bioscara("ping")
    assert code == 0
    table = rows(out)
    for joint in CONFIG.joints:
        assert table[joint.name][:2] == [f"0x{joint.address:02X}", "OK"]
    assert table["gripper"][:2] == ["-", "OK"]
    assert "all 5 devices answered" in out


def test_ping_reports_a_joint_that_does_not_answer() -> None:
    with Session(ConsoleOptions(), configure=False) as s:
        del s.backend.bus.devices[0x13]  # j3 unplugged
        results = {name: reply for name, _, reply, _ in ping_devices(s)}
        assert s.backend.comm_stats()["j3"].total_errors == 3  # the try and two retries
    assert results["j3"].startswith("j3 (0x13): PING failed after 3 attempts")
    assert [results[n] for n in ("j1", "j2", "j4")] == ["OK"] * 3


# ---------------------------------------------------------- enable/disable
def test_enable_joint_then_status_shows_it_enabled(bioscara: Run, state: Path) -> None:
    code, out, _ = bioscara("enable", "j1", "--state", str(state))
    assert code == 0
    assert "enabled j1; holding still · arm active" in out
    table = status(bioscara, state)
    assert enabled(table, "j1") == "yes"
    assert [enabled(table, n) for n in ("j2", "j3", "j4", "gripper")] == ["no"] * 4


def test_without_state_each_command_starts_powered_up(bioscara: Run) -> None:
    bioscara("enable")
    _, out, _ = bioscara("status")
    assert "arm inactive" in out
    assert enabled(rows(out), "j1") == "no"


def test_disable_group_leaves_the_rest_enabled(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, out, _ = bioscara("disable", "arm", "--state", str(state))
    assert code == 0
    assert "disabled j1, j2, j3, j4 · arm active" in out
    table = status(bioscara, state)
    assert [enabled(table, n) for n in CONFIG.names] == ["no"] * 4
    assert enabled(table, "gripper") == "yes"


def test_disable_all_makes_the_arm_inactive(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, out, _ = bioscara("disable", "--state", str(state))
    assert code == 0
    assert "arm inactive" in out


def test_groups_come_from_the_configuration() -> None:
    assert resolve_target(CONFIG, "arm").joints == ("j1", "j2", "j3", "j4")
    assert not resolve_target(CONFIG, "arm").gripper
    assert resolve_target(CONFIG, None).gripper
    assert resolve_target(CONFIG, "gripper").joints == ()


# -------------------------------------------------------------------- home
def test_enable_home_status_homes_every_joint_at_its_limit(bioscara: Run, state: Path) -> None:
    assert bioscara("enable", "--state", str(state))[0] == 0
    code, out, _ = bioscara("home", "--state", str(state))
    assert code == 0
    homed_at = re.search(r"j1 homed at max: ([+-]\d+\.\d{4}) rad", out)
    assert homed_at is not None
    assert float(homed_at.group(1)) == pytest.approx(3.04647, abs=1e-3)  # j1's max (SPEC table)
    table = status(bioscara, state)
    for name, (_, high) in LIMITS.items():
        position = float(table[name][0].split()[0])
        assert position == pytest.approx(high, abs=1e-3)
        # The seed's stop_homing disables each joint once it is homed.
        assert table[name][3:5] == ["yes", "NOT_ENABLED"]


def test_home_without_enable_is_refused(bioscara: Run) -> None:
    code, _, err = bioscara("home", "j1")
    assert code == 2
    assert "j1: not enabled; run `bioscara enable j1` first" in err


def test_home_direction_minus_homes_to_min() -> None:
    with Session(ConsoleOptions(backend="mock")) as s:
        s.enable(resolve_target(s.config, "j1"))
        s.home(["j1"], direction=-1)
        assert s.arm.joint_states["j1"].position == pytest.approx(LIMITS["j1"][0])


def test_home_direction_option_picks_the_end_stop(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, out, _ = bioscara("home", "j4", "--direction", "-", "--no-wait", "--state", str(state))
    assert code == 0
    assert "j4 homing toward min at 0.1 rad/s (left running)" in out


def test_home_no_wait_leaves_the_homing_running(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, out, _ = bioscara("home", "j4", "--no-wait", "--state", str(state))
    assert code == 0
    assert "j4 homing toward max at 0.1 rad/s (left running)" in out
    assert status(bioscara, state)["j4"][3:5] == ["homing…", "BUSY NOT_HOMED"]


def test_homing_a_joint_busy_homing_is_refused_and_changes_nothing(bioscara: Run, state: Path) -> None:
    # Seen: `home j1` after `home --no-wait` aborted all four homings and disabled
    # the arm while saying "wait for it in bioscara monitor".
    bioscara("enable", "--state", str(state))
    bioscara("home", "--no-wait", "--state", str(state))
    code, _, err = bioscara("home", "j1", "--state", str(state))
    assert code == 2
    assert err == (
        "bioscara home: error: j1: busy (a homing is running); wait for it in `bioscara monitor` "
        "or abort it with `bioscara home j1 --abort`"
    )
    table = status(bioscara, state)
    for name in ("j1", "j2", "j3", "j4"):
        assert table[name][2:5] == ["yes", "homing…", "BUSY NOT_HOMED"], name
    assert enabled(table, "gripper") == "yes"


def test_status_says_a_not_enabled_flag_does_not_mean_no_current(bioscara: Run, state: Path) -> None:
    # Seen (a hostile test): after a deadman trip, currents 20/20, status said "enabled: no".
    bioscara("enable", "--state", str(state))
    bioscara("home", "j4", "--state", str(state))
    j4 = CONFIG.joint("j4")
    with Session(ConsoleOptions(state=state)) as s:
        s.arm.joints["j4"].enable(j4.drive_current, j4.hold_current)
        s.arm.joints["j4"].set_velocity(0.5)
        s.backend.step(0.2)  # the host silent: the deadman trips, the current stays on
        assert s.backend.device_currents("j4") == (j4.drive_current, j4.hold_current)
    code, out, _ = bioscara("status", "--state", str(state))
    assert code == 0
    assert (
        "j4: NOT_ENABLED is a flag: after a deadman trip the current stays on; `bioscara disable j4` cuts it"
        in out
    )
    assert "j1: NOT_ENABLED" not in out  # not homed
    bioscara("disable", "--state", str(state))
    code, out, _ = bioscara("status", "--state", str(state))
    assert "NOT_ENABLED is a flag" not in out  # the emulator shows every current cut


def test_a_ctrl_c_while_the_commands_load_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): Ctrl-C in the first half second printed a 40-line traceback.
    import bioscara_gym.cli as cli

    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["status"]) == 130
    assert capsys.readouterr().err == "bioscara: interrupted\n"


@pytest.mark.parametrize(
    ("error", "line"),
    [
        (OSError(2, "No such file or directory", "/nowhere/x"), "No such file or directory: /nowhere/x"),
        (
            OSError(28, "cannot write the bus trace t.jsonl: No space left"),
            "cannot write the bus trace t.jsonl: No space left",
        ),
        (OSError("the adapter went away"), "the adapter went away"),
    ],
    ids=["file", "errno", "message"],
)
def test_an_os_error_is_one_line_with_its_file_and_without_its_errno(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], error: OSError, line: str
) -> None:
    # Seen: "bioscara ping: error: [Errno 2] cannot write the bus trace ...".
    import bioscara_gym.cli as cli

    def fails(args: argparse.Namespace) -> int:
        raise error

    monkeypatch.setattr(commands, "cmd_status", fails)
    assert cli.main(["status"]) == 2
    assert capsys.readouterr().err == f"bioscara status: error: {line}\n"


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (CommError("j1: no acknowledge after 3 retries"), 3),
        (StalledError("j2: stall detected"), 3),
        (ArmStateError("j3: not at 1 rad within 2 s (at 0.5000 rad)"), 3),
        (InvalidArgumentError("j1: 9 rad is outside [-3.05, 3.05]"), 2),
        (refusal(NotHomedError("j4: not homed; run `bioscara home j4` first")), 2),
    ],
    ids=["bus", "stall", "timeout", "argument", "state"],
)
def test_a_failure_on_the_arm_exits_3_and_a_refusal_2(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], error: JointError, code: int
) -> None:
    # Both used to exit 2, which the README gives refusals (nothing sent): a script
    # could not tell "nothing happened" from "the arm failed and was disabled".
    import bioscara_gym.cli as cli

    def fails(args: argparse.Namespace) -> int:
        raise error

    monkeypatch.setattr(commands, "cmd_move", fails)
    assert cli.main(["move", "j1", "0.1"]) == code
    assert capsys.readouterr().err == f"bioscara move: error: {error}\n"


def test_a_homing_that_times_out_exits_3_with_the_arm_disabled(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, _, err = bioscara("home", "j2", "--timeout", "0.5", "--state", str(state))
    assert (code, err) == (3, "bioscara home: error: homing j2 did not finish within 0.5 s; aborted")
    table = status(bioscara, state)
    assert [enabled(table, name) for name in ("j1", "j2", "j3", "j4", "gripper")] == ["no"] * 5


def test_a_move_that_times_out_exits_3_with_the_arm_disabled(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    assert bioscara("home", "j4", "--state", str(state))[0] == 0
    code, _, err = bioscara("move", "j4", "-2", "--timeout", "0.1", "--state", str(state))
    assert code == 3
    assert err.startswith("bioscara move: error: j4: not at -2 rad within 0.1 s (at ")
    table = status(bioscara, state)
    assert [enabled(table, name) for name in ("j1", "j2", "j3", "j4", "gripper")] == ["no"] * 5


def test_enabling_a_joint_busy_homing_is_refused_and_changes_nothing(bioscara: Run, state: Path) -> None:
    # Seen (a hostile test): refused in words, yet every homing was aborted and the arm disabled.
    bioscara("enable", "--state", str(state))
    bioscara("home", "--no-wait", "--state", str(state))
    code, _, err = bioscara("enable", "j1", "--state", str(state))
    assert code == 2
    assert err == (
        "bioscara enable: error: j1: busy (a homing is running); enabling it again would stop it; "
        "abort it first with `bioscara home j1 --abort`"
    )
    table = status(bioscara, state)
    for name in ("j1", "j2", "j3", "j4"):
        assert table[name][2:5] == ["yes", "homing…", "BUSY NOT_HOMED"], name


@pytest.mark.parametrize("command", [("move", "j1", "0.1"), ("home", "j1")], ids=["move", "home"])
@pytest.mark.parametrize("timeout", ["nan", "inf", "-1", "0"])
def test_a_timeout_that_is_not_a_positive_number_is_refused(
    capsys: pytest.CaptureFixture[str], state: Path, command: tuple[str, ...], timeout: str
) -> None:
    # Seen (a hostile test): nan never timed out; -1 and 0 sent the motion, then disabled the arm.
    with pytest.raises(SystemExit) as done:  # argparse's refusal
        main([*command, "--timeout", timeout, "--state", str(state)])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.endswith(f"argument --timeout: {timeout} must be a positive, finite number of seconds")
    assert not state.exists()  # refused before the arm was brought up


def test_homing_left_running_is_finished_by_a_later_command(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    bioscara("home", "j4", "--no-wait", "--state", str(state))
    with Session(ConsoleOptions(state=state)) as s:
        while s.arm.homing_names():
            s.cycle(0.04)
    table = status(bioscara, state)
    assert float(table["j4"][0].split()[0]) == pytest.approx(LIMITS["j4"][1], abs=1e-3)


def test_home_abort_stops_a_running_homing(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    bioscara("home", "j1", "--no-wait", "--state", str(state))
    code, out, _ = bioscara("home", "--abort", "--state", str(state))
    assert code == 0
    assert "aborted homing of j1 (not homed)" in out
    # stop_homing runs on an abort too: the joint is left disabled.
    assert status(bioscara, state)["j1"][2:5] == ["no", "no", "NOT_HOMED NOT_ENABLED"]


@pytest.mark.parametrize(
    ("options", "unused"),
    [
        (["--direction", "+"], "--direction"),
        (["--timeout", "5"], "--timeout"),
        (["--no-wait"], "--no-wait"),
        (["--no-wait", "--direction", "-"], "--direction or --no-wait"),
    ],
)
def test_home_abort_refuses_the_options_it_does_not_use(
    bioscara: Run, state: Path, options: list[str], unused: str
) -> None:
    # Seen (a hostile test): exit 0, "no homing is running", the options ignored.
    bioscara("enable", "--state", str(state))
    bioscara("home", "j1", "--no-wait", "--state", str(state))
    saved = state.read_text()
    code, _, err = bioscara("home", "--abort", *options, "--state", str(state))
    assert code == 2
    assert err == f"bioscara home: error: --abort stops a running homing; it takes no {unused}"
    assert state.read_text() == saved  # refused before the arm was touched: the homing runs on


def test_home_no_wait_needs_state(bioscara: Run) -> None:
    code, _, err = bioscara("home", "--no-wait")
    assert code == 2
    assert "--no-wait needs --state FILE" in err


# -------------------------------------------------------------------- move
def test_move_waits_until_the_joint_is_there(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    bioscara("home", "j4", "--state", str(state))
    code, out, _ = bioscara("move", "j4", "1.0", "--state", str(state))
    assert code == 0
    # Reached within the arm's move tolerance (1e-3 rad); the drive's load angle shows in
    # the last digit (+1.0001 on the calibrated drive).
    reached = re.match(r"j4 at ([+-]\d+\.\d{4}) rad \(target \+1\.0000\)", out)
    assert reached is not None, out
    assert float(reached.group(1)) == pytest.approx(1.0, abs=1e-3)
    table = status(bioscara, state)
    assert float(table["j4"][0].removesuffix(" rad")) == pytest.approx(1.0, abs=1e-3)
    # The encoder's speed estimate (uStepper's velocity estimator) settles over ~50 ms after the stop.
    assert abs(float(table["j4"][1].split()[0])) <= 0.001
    assert enabled(table, "j4") == "yes"


def test_move_on_an_unhomed_joint_is_refused(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, _, err = bioscara("move", "j1", "1.0", "--state", str(state))
    assert code == 2
    assert "j1: not homed; run `bioscara home j1` first" in err


# ----------------------------------------------------------------- gripper
def test_gripper_width_is_set_and_shown(bioscara: Run, state: Path) -> None:
    code, out, _ = bioscara("gripper", "0.05", "--state", str(state))
    assert code == 0
    assert "gripper at 0.0500 m (servo driven)" in out
    assert status(bioscara, state)["gripper"] == ["0.0500 m", "yes"]


def test_gripper_width_survives_disable_and_enable(bioscara: Run, state: Path) -> None:
    bioscara("gripper", "0.05", "--state", str(state))
    bioscara("disable", "gripper", "--state", str(state))
    bioscara("enable", "--state", str(state))
    assert status(bioscara, state)["gripper"] == ["0.0500 m", "yes"]


# --------------------------------------------------------------- bad input
def all_disabled(table: dict[str, list[str]]) -> bool:
    return all(enabled(table, n) == "no" for n in (*CONFIG.names, "gripper"))


# A request refused for its arguments is refused before a byte is sent: the arm stays as it was.
def test_unknown_joint_is_refused_and_the_arm_left_as_it_was(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, _, err = bioscara("move", "j9", "1.0", "--state", str(state))
    assert code == 2
    assert err == "bioscara move: error: unknown joint 'j9'; known joints: j1, j2, j3, j4"
    assert not any(enabled(status(bioscara, state), n) == "no" for n in (*CONFIG.names, "gripper"))


def test_unknown_group_is_refused_and_the_arm_left_as_it_was(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    code, _, err = bioscara("disable", "legs", "--state", str(state))
    assert code == 2
    assert "unknown joint or group 'legs'; joints: j1, j2, j3, j4, gripper; groups: all, arm, gripper" in err
    assert not any(enabled(status(bioscara, state), n) == "no" for n in (*CONFIG.names, "gripper"))


def test_move_outside_the_limits_is_refused_and_nothing_moves(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    bioscara("home", "j4", "--state", str(state))
    before = status(bioscara, state)
    code, _, err = bioscara("move", "j4", "4", "--state", str(state))
    assert code == 2
    assert "j4: 4 rad is outside the joint limits [-3.01069, 3.01069] rad" in err
    table = status(bioscara, state)  # refused before a byte was sent: the arm is as it was
    # (the held rotor's compliance moves the last digit: 0.1 mrad; the refused move is 1 rad)
    position = float(table["j4"][0].removesuffix(" rad"))
    assert position == pytest.approx(float(before["j4"][0].removesuffix(" rad")), abs=1e-3)
    assert [enabled(table, n) for n in table if n != "gripper"] == [
        enabled(before, n) for n in before if n != "gripper"
    ]
    assert enabled(table, "gripper") == enabled(before, "gripper") == "yes"


def test_gripper_width_outside_the_limits_is_refused(bioscara: Run) -> None:
    code, _, err = bioscara("gripper", "0.2")
    assert code == 2
    assert "gripper: width 0.2 m is outside the limits [0.04, 0.12] m" in err


@pytest.mark.parametrize("backend", ["emulated", "sim"])
def test_a_width_the_servo_cannot_take_is_refused_and_the_gripper_stays_off(
    bioscara: Run, tmp_path: Path, backend: str
) -> None:
    # Seen (a hostile test of the config files, a gripper `min: -1`): the servo was enabled, then
    # the pulse refused, and the refusal left it driven; on emulated the fingers went to -0.5 m, exit 0.
    config = tmp_path / "neg.yaml"
    config.write_text(DEFAULT_CONFIG.read_text().replace("  min: 0.04 ", "  min: -1.0 "))
    state = tmp_path / "arm.json"
    options = ("--backend", backend, "--config", str(config), "--state", str(state))
    assert bioscara("disable", *options)[0] == 0
    code, _, err = bioscara("gripper", "-0.5", *options)
    assert (code, err) == (
        2,
        "bioscara gripper: error: gripper: width -0.5 m: servo angle -1859.98 deg gives a -8833.23 us pulse; "
        "must be between 0 and 20000 us (the 50 Hz period); check the configured limits",
    )
    code, out, _ = bioscara("status", *options)
    assert enabled(rows(out), "gripper") == "no"


def test_a_configured_state_file_naming_the_configuration_keeps_it_and_warns_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): arm.yaml became {"width_m": 0.06}; the warning took two lines.
    config = tmp_path / "arm.yaml"
    text = DEFAULT_CONFIG.read_text().replace("  state_file: null ", f"  state_file: {config} ")
    config.write_text(text)
    state = tmp_path / "arm.json"
    assert main(["gripper", "0.06", "--config", str(config), "--state", str(state)]) == 0
    capsys.readouterr()
    assert main(["disable", "gripper", "--config", str(config), "--state", str(state)]) == 0
    assert config.read_text() == text
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) >= 1 and all(line.startswith("bioscara disable: warning: gripper: ") for line in lines)
    assert "cannot save width 0.06 m to state file" in lines[-1]


def test_status_on_mock_says_the_bus_time_cannot_be_counted_for_an_arm_the_model_has_not(
    bioscara: Run, tmp_path: Path
) -> None:
    # Seen (a hostile test): status on mock failed with its bus budget's emulated arm's error.
    config = tmp_path / "shoulder.yaml"
    config.write_text(re.sub(r"\bj1\b", "shoulder", DEFAULT_CONFIG.read_text()))
    code, out, _ = bioscara("status", "--backend", "mock", "--config", str(config))
    assert code == 0
    assert " ".join(out.split()).endswith(
        "bus time per cycle: not counted (the emulated arm it is counted on failed: joint 'shoulder': the "
        "simulated arm's joints are j1, j2, j3, j4 (assets/scene.xml); a configuration for it names those)"
    )


def test_home_on_a_busy_joint_is_refused_and_the_homing_goes_on(bioscara: Run, state: Path) -> None:
    # Issue #24 item 8: the refusal sends nothing, so the homing it says to wait
    # for is still there (it used to be aborted and the arm disabled).
    bioscara("enable", "--state", str(state))
    bioscara("home", "j1", "--no-wait", "--state", str(state))
    code, _, err = bioscara("home", "j1", "--state", str(state))
    assert code == 2
    assert "j1: busy (a homing is running)" in err
    table = status(bioscara, state)
    assert table["j1"][2:5] == ["yes", "homing…", "BUSY NOT_HOMED"]
    assert [enabled(table, n) for n in ("j2", "j3", "j4")] == ["yes", "yes", "yes"]


def test_interrupt_disables_every_joint(state: Path, bioscara: Run) -> None:
    with pytest.raises(KeyboardInterrupt), Session(ConsoleOptions(state=state)) as s:
        s.enable(resolve_target(s.config, None))
        raise KeyboardInterrupt
    assert all_disabled(status(bioscara, state))


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (
            ["eval", "--episodes", "abc"],
            "bioscara eval: error: argument --episodes: invalid int value: 'abc'",
        ),
        (["move", "j1", "abc"], "bioscara move: error: argument VALUE: invalid float value: 'abc'"),
        ([], "bioscara: error: the following arguments are required: command"),
    ],
)
def test_a_value_argparse_refuses_is_one_line_too(
    argv: list[str], line: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): argparse's usage block, 5-7 lines, above the error.
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == line + "\n"


# -------------------------------------------------------------- state file
def test_state_file_is_the_documented_json(bioscara: Run, state: Path) -> None:
    bioscara("gripper", "0.06", "--state", str(state))
    doc = json.loads(state.read_text())
    assert doc["format"] == STATE_FORMAT
    assert doc["backend"] == "emulated"
    assert set(doc) >= {"version", "config", "time_s", "mujoco", "firmware", "host"}
    assert doc["host"]["gripper"] == {"enabled": True, "width_m": 0.06}


def test_state_from_another_backend_is_refused_and_kept(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    saved = state.read_text()
    code, _, err = bioscara("status", "--backend", "sim", "--state", str(state))
    assert code == 2
    assert "was saved by the emulated backend; use --backend emulated or another file" in err
    assert state.read_text() == saved


def test_corrupt_state_file_is_refused_and_kept(bioscara: Run, state: Path) -> None:
    state.write_text('{"format": "bioscara-console-state", "version": 1')
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert f"state file {state} cannot be read" in err
    assert state.read_text() == '{"format": "bioscara-console-state", "version": 1'


@pytest.mark.parametrize("value", [float("nan"), 10**400, 1e308], ids=["nan", "beyond-float", "beyond-1e9"])
def test_a_state_whose_simulation_is_not_finite_is_refused_and_kept(
    bioscara: Run, state: Path, value: float
) -> None:
    # Seen (a hostile test): NaN in 'mujoco' was restored; the joints then read NaN, the
    # error blamed the wiring, and the file was rewritten though the command failed.
    # (10**400, found by a reviewer, overflowed the first check into a traceback.)
    bioscara("enable", "--state", str(state))
    doc = json.loads(state.read_text())
    doc["mujoco"][1] = value
    state.write_text(json.dumps(doc))
    saved = state.read_text()
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert err.strip().endswith(
        f"state file {state}: 'mujoco' must be a list of {len(doc['mujoco'])} finite numbers, at most 1e+09"
    )
    assert state.read_text() == saved


def test_a_state_file_under_a_file_is_refused_naming_it(bioscara: Run, tmp_path: Path) -> None:
    # Seen (a hostile test): "cannot lock state file notes/s.json: notes/s.json.lock: File exists".
    (tmp_path / "notes").write_text("x")
    code, _, err = bioscara("status", "--state", str(tmp_path / "notes" / "s.json"))
    assert code == 2
    assert err.strip().endswith(
        f"state file {tmp_path}/notes/s.json: {tmp_path}/notes is a file, not a folder"
    )


@pytest.mark.skipif(not Path("/dev/null").exists(), reason="no /dev/null")
def test_a_device_as_state_file_is_refused_without_a_lock_beside_it(bioscara: Run) -> None:
    # Seen (a hostile test): refused, but /dev/null.lock was made.
    if Path("/dev/null.lock").exists():
        pytest.skip("a /dev/null.lock made before")
    code, _, err = bioscara("status", "--state", "/dev/null")
    assert code == 2
    assert "state file /dev/null is not a regular file" in err
    assert not Path("/dev/null.lock").exists()


def test_an_empty_state_path_is_refused(bioscara: Run) -> None:
    with pytest.raises(SystemExit) as caught:
        bioscara("status", "--state", "")
    assert caught.value.code == 2


@pytest.mark.parametrize(
    ("part", "key", "value", "message"),
    [
        ("firmware", "flags", 10**30, "j1.flags 1000000000000000000000000000000 is not a byte (0-255)"),
        ("firmware", "flags", -1, "j1.flags -1 is not a byte (0-255)"),
        ("drive", "_position", float("nan"), "drive state j1._position is NaN"),
        # Seen (a third hostile pass): a traceback from struct or OverflowError at the next
        # monitor, the file rewritten anyway; 1e308 motor current made MuJoCo's state huge.
        (
            "firmware",
            "drive_current",
            -1,
            "firmware.j1.drive_current is -1; expected a current in % (0-100: the firmware caps it)",
        ),
        (
            "firmware",
            "hold_current",
            1e30,
            "firmware.j1.hold_current is 1e+30; expected a current in % (0-100: the firmware caps it)",
        ),
        (
            "firmware",
            "motor_current",
            1e308,
            "firmware.j1.motor_current is 1e+308; expected a current in % (0-255: HOME's current byte "
            "is not capped)",
        ),
        (
            "firmware",
            "max_velocity",
            1e308,
            "firmware.j1.max_velocity is 1e+308; expected a float32 (at most 3.4028235e+38 in size, "
            "or inf or NaN)",
        ),
        ("firmware", "brake_mode", 256, "firmware.j1.brake_mode is 256; expected a byte (0-255)"),
        (
            "firmware",
            "encoder_zero",
            1e308,
            "firmware.j1.encoder_zero is 1e+308; expected a finite number, at most 1e+09 in size",
        ),
        (
            "drive",
            "load_accel",
            1e308,
            "drive.j1.load_accel is 1e+308; expected 0.0, this configuration's (a parameter of the "
            "drive model, not state)",
        ),
        (
            "drive",
            "pole_slips",
            -1,
            "drive.j1.pole_slips is -1; expected a count (a whole number, 0 to 2**63 - 1)",
        ),
        (
            "drive",
            "_swing_deg",
            -1e308,
            "drive.j1._swing_deg is -1e+308; expected a finite number, at most 1e+09 in size",
        ),
    ],
)
def test_a_state_whose_joint_values_cannot_be_is_refused_and_kept(
    bioscara: Run, state: Path, part: str, key: str, value: float, message: str
) -> None:
    # Seen (a second hostile pass): "byte must be in range(0, 256)" naming nothing, from then on
    # every command; a NaN rotor: MuJoCo's warnings, and the wiring blamed.
    bioscara("enable", "--state", str(state))
    doc = json.loads(state.read_text())
    doc[part]["j1"][key] = value
    state.write_text(json.dumps(doc))
    saved = state.read_text()
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert err.strip().endswith(f"state file {state}: {message}")
    assert state.read_text() == saved


def test_a_state_whose_float_registers_hold_inf_or_nan_is_used(bioscara: Run, state: Path) -> None:
    # A float32 register holds them, and the firmware takes them (HOMEOFFSET is NaN until stored).
    bioscara("enable", "--state", str(state))
    doc = json.loads(state.read_text())
    doc["firmware"]["j1"].update(max_velocity=float("inf"), q_set=float("nan"), home_offset=float("nan"))
    state.write_text(json.dumps(doc))
    assert bioscara("monitor", "--duration", "0.1", "--state", str(state))[0] == 0


@pytest.mark.parametrize(
    ("keys", "value", "message"),
    [
        (("time_s",), "x", "'time_s' is 'x'; expected the simulated time in s, 0 to 1e+09"),
        (("time_s",), None, "'time_s' is None; expected the simulated time in s, 0 to 1e+09"),
        (
            ("host", "gripper", "width_m"),
            -1,
            "host.gripper.width_m -1 is outside the gripper's 0.04 to 0.12 m",
        ),
        (
            ("host", "stats", "j1", "errors"),
            -5,
            "host.stats.j1.errors is -5; expected a count (a whole number, 0 to 2**63 - 1)",
        ),
        # Seen (a second hostile pass): all accepted, an unknown key dropped when the file was written.
        (
            ("host", "stats", "j1", "errors"),
            2**63,
            "host.stats.j1.errors is 9223372036854775808; expected a count (a whole number, 0 to 2**63 - 1)",
        ),
        (("host", "homing", "j1"), 1e308, "host.homing must map joint names to non-zero speeds"),
        (
            ("extra",),
            1,
            "has extra, which a state file does not; it has "
            "{backend, config, drive, firmware, format, host, mujoco, time_s, version}",
        ),
        (
            ("host", "notes"),
            "x",
            "has host.notes, which a state file does not; it has host.{gripper, homing, stats}",
        ),
        (
            ("host", "gripper", "speed"),
            1,
            "has host.gripper.speed, which a state file does not; it has host.gripper.{enabled, width_m}",
        ),
    ],
    ids=[
        "time-text",
        "time-null",
        "gripper-width",
        "stats-count",
        "stats-count-past-64-bits",
        "homing-speed-1e308",
        "unknown-key",
        "unknown-host-key",
        "unknown-gripper-key",
    ],
)
def test_a_state_whose_host_values_cannot_be_is_refused_and_kept(
    bioscara: Run, state: Path, keys: tuple[str, ...], value: object, message: str
) -> None:
    # Seen (a hostile test): all accepted; a width of -1 m was shown as 0.0400 m.
    bioscara("gripper", "0.06", "--state", str(state))
    doc = json.loads(state.read_text())
    *parents, last = keys
    part = doc
    for key in parents:
        part = part[key]
    part[last] = value
    state.write_text(json.dumps(doc))
    saved = state.read_text()
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert err == f"bioscara status: error: state file {state}: {message}"
    assert state.read_text() == saved


def test_a_state_of_version_2_0_is_not_version_2(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    doc = json.loads(state.read_text())
    doc["version"] = float(doc["version"])
    state.write_text(json.dumps(doc))
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert err.endswith(f"state file {state} has version 2.0; this console reads 2")


@pytest.mark.parametrize(
    "argv", [("status", "--backend", "sim"), ("ping", "--backend", "mock"), ("status",)], ids=str
)
def test_bus_is_refused_on_a_backend_without_a_numbered_bus(bioscara: Run, argv: tuple[str, ...]) -> None:
    # Seen (a hostile test): exit 0, the bus number ignored.
    backend = argv[2] if len(argv) > 1 else "emulated"
    code, _, err = bioscara(*argv, "--bus", "3")
    assert code == 2
    message = f"--bus 3 needs --backend i2c (a numbered I2C bus); {backend} has none"
    assert err == f"bioscara {argv[0]}: error: {message}"


def test_state_with_the_mock_backend_is_refused(bioscara: Run, state: Path) -> None:
    code, _, err = bioscara("status", "--backend", "mock", "--state", str(state))
    assert code == 2
    assert "mock state does not persist" in err


def test_sim_backend_keeps_state_too(bioscara: Run, state: Path) -> None:
    bioscara("enable", "j2", "--backend", "sim", "--state", str(state))
    code, out, _ = bioscara("status", "--backend", "sim", "--state", str(state))
    assert code == 0
    assert enabled(rows(out), "j2") == "yes"


# -------------------------------------------------------- state file lock
def test_second_command_on_a_held_state_file_is_refused_in_one_line(bioscara: Run, state: Path) -> None:
    bioscara("enable", "--state", str(state))
    with Session(ConsoleOptions(state=state)):
        saved = state.read_text()
        code, out, err = bioscara("move", "j1", "1.0", "--state", str(state))
        assert state.read_text() == saved  # the refused command wrote nothing
    assert code == 2
    assert out == ""
    assert err == (
        f"bioscara move: error: {state} is in use by another bioscara command (pid {os.getpid()}); "
        "wait for it to finish (or stop it), then run this command again"
    )


def test_record_onto_the_state_file_is_refused_before_anything_is_written(bioscara: Run, state: Path) -> None:
    assert bioscara("enable", "--state", str(state))[0] == 0
    saved = state.read_text()
    code, out, err = bioscara("home", "--state", str(state), "--record", str(state))
    assert code == 2 and out == ""
    assert err == f"bioscara home: error: --state and --record name the same file {state}; each needs its own"
    assert state.read_text() == saved


@pytest.mark.parametrize("link", [False, True])
def test_a_state_file_that_is_the_configuration_is_refused_before_anything_is_written(
    bioscara: Run, tmp_path: Path, link: bool
) -> None:
    # Seen (a hostile test): "... cannot be read ...; delete it to start from a powered-up arm".
    config = tmp_path / "arm.yaml"
    config.write_text(DEFAULT_CONFIG.read_text())
    state = tmp_path / "state.json"
    if link:
        state.symlink_to(config)
    else:
        state = config
    code, out, err = bioscara("enable", "--config", str(config), "--state", str(state))
    assert (code, out) == (2, "")
    assert err == (
        f"bioscara enable: error: --state {state} is the --config file; writing it would destroy it"
    )
    assert config.read_text() == DEFAULT_CONFIG.read_text()


def test_a_trace_that_cannot_be_opened_is_one_line_without_errno(tmp_path: Path, bioscara: Run) -> None:
    trace = tmp_path / "missing" / "t.jsonl"
    code, out, err = bioscara("ping", "--backend", "emulated", "--record", str(trace))
    assert code == 2
    assert (
        err
        == f"bioscara ping: error: cannot write the bus trace {trace} (--record): No such file or directory"
    )
    assert out == ""


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/full"])
def test_a_state_file_that_is_a_device_is_refused_not_read_forever(bioscara: Run, device: str) -> None:
    code, _, err = bioscara("status", "--state", device)
    assert code == 2
    assert err == (
        f"bioscara status: error: state file {device} is not a regular file (a directory or a device); "
        "pick another path"
    )


def test_state_file_lock_is_released_after_a_command(bioscara: Run, state: Path) -> None:
    assert bioscara("enable", "j1", "--state", str(state))[0] == 0
    assert bioscara("disable", "j1", "--state", str(state))[0] == 0
    with LockFile(lock_path(state)):  # free again
        pass


def test_state_file_lock_is_released_after_ctrl_c(state: Path) -> None:
    with pytest.raises(KeyboardInterrupt), Session(ConsoleOptions(state=state)):
        raise KeyboardInterrupt
    with Session(ConsoleOptions(state=state)) as s:
        assert s.arm.state.value


def test_state_file_lock_is_released_when_the_file_is_refused(bioscara: Run, state: Path) -> None:
    state.write_text("not json")
    assert bioscara("status", "--state", str(state))[0] == 2
    with LockFile(lock_path(state)):
        pass


def test_state_file_lock_is_held_by_a_subprocess_until_it_ends(bioscara: Run, state: Path) -> None:
    holder = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from bioscara_gym.console.state import lock_state\n"
        "lock = lock_state(Path(sys.argv[1]))\n"
        "print('locked', flush=True)\n"
        "sys.stdin.readline()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", holder, str(state)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "locked\n"
        code, _, err = bioscara("status", "--state", str(state))
        assert code == 2
        assert f"in use by another bioscara command (pid {proc.pid})" in err
    finally:
        proc.communicate("\n", timeout=30)
    assert bioscara("status", "--state", str(state))[0] == 0  # the lock died with its holder


# --------------------------------------------------------------- dashboard
def known_snapshot() -> DashboardSnapshot:
    flags = Flag(0)
    return DashboardSnapshot(
        backend="emulated",
        lifecycle="active",
        time_s=12.5,
        joints=(
            JointView("j1", "rad", -3.0, 3.0, 3.0, 0.0, flags),
            JointView("j2", "m", 0.0, 0.3, None, 0.0, Flag.NOT_HOMED),
            JointView("j3", "rad", -2.0, 2.0, None, 0.05, Flag.BUSY | Flag.NOT_HOMED, True, 2.5),
            JointView("j4", "rad", -3.0, 3.0, -3.0, 0.0, Flag.STALL),
        ),
        gripper_enabled=True,
        gripper_width=0.08,
        gripper_min=0.04,
        gripper_max=0.12,
        bus=(BusView("j1", 100, 2, 400, 3, 75.0, 0.5),),
        message="homing j3",
    )


def rendered(snapshot: DashboardSnapshot) -> str:
    console = Console(record=True, width=120)
    console.print(render_dashboard(snapshot))
    return console.export_text()


def test_dashboard_shows_lifecycle_backend_and_time() -> None:
    assert "lifecycle ACTIVE   backend emulated   t 12.50 s" in rendered(known_snapshot())


def test_dashboard_draws_position_bars_within_the_limits() -> None:
    text = rendered(known_snapshot())
    assert re.search(r"j1\s+\+3\.0000 rad\s+├─+●┤", text)
    assert re.search(r"j4\s+-3\.0000 rad\s+├●─+┤", text)
    assert re.search(r"j2\s+-\s+├┄+┤", text)


def test_dashboard_shows_flags_and_homing_progress() -> None:
    text = rendered(known_snapshot())
    assert re.search(r"j3 .* BUSY NOT_HOMED\s+[⠋-⣿] homing… 2\.5 s", text)
    assert re.search(r"j4 .* STALL\s+homed", text)
    assert re.search(r"j1 .* OK\s+homed", text)


def test_dashboard_shows_bus_statistics_and_rates() -> None:
    assert re.search(r"j1\s+100\s+2\s+400\s+3\s+75\s+0\.5", rendered(known_snapshot()))


def test_dashboard_shows_the_message_and_keys() -> None:
    text = rendered(known_snapshot())
    assert "homing j3" in text
    assert "e enable all   d disable all   h home unhomed   a abort homing" in text


def test_flags_are_coloured() -> None:
    text = flags_text(Flag.STALL | Flag.BUSY | Flag.NOT_HOMED | Flag.NOT_ENABLED)
    styles = {text.plain[s.start : s.end]: str(s.style) for s in text.spans}
    assert styles == {"STALL": "bold red", "BUSY": "yellow", "NOT_HOMED": "magenta", "NOT_ENABLED": "dim"}


def test_position_bar_marks_the_middle() -> None:
    assert position_bar(0.0, -1.0, 1.0, width=7).plain == "├──●──┤"


def test_dashboard_renders_an_arm_homed_in_the_session(session: Session) -> None:
    session.enable(resolve_target(session.config, None))
    session.home(["j4"])
    text = rendered(MonitorApp(session).snapshot())
    assert re.search(r"j4\s+\+3\.010\d rad\s+├─+●┤\s+\S+ rad/s\s+NOT_ENABLED\s+homed", text)
    assert re.search(r"gripper\s+0\.0800 m\s+├─+●─+┤\s+ENABLED", text)


# -------------------------------------------------------------------- keys
def test_key_e_enables_the_arm(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "e")
    assert session.arm.state.value == "active"
    assert all(j.is_enabled() for j in session.arm.joints.values())
    assert app.message == "enabled j1, j2, j3, j4, gripper"


def test_key_d_disables_the_arm(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "e")
    handle_key(app, "d")
    assert session.arm.state.value == "inactive"
    assert not any(j.is_enabled() for j in session.arm.joints.values())


def test_key_h_homes_every_unhomed_joint(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "e")
    handle_key(app, "h")
    assert app.message == "homing j1, j2, j3, j4"
    for _ in range(70):
        app.step(0.1)
    assert all(session.arm.joint_states[n].homed for n in session.arm.names)
    assert not session.arm.homing_names()
    assert app.message.endswith(" homed")


def test_key_h_without_enabled_joints_only_says_so(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "h")
    assert app.message == "nothing to home (enable the arm first: e)"


def test_key_a_aborts_homing(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "e")
    handle_key(app, "h")
    app.step(0.2)
    handle_key(app, "a")
    assert app.message == "aborted homing of j1, j2, j3, j4"
    assert not session.arm.homing_names()
    assert not any(j.is_homed() or j.is_busy() for j in session.arm.joints.values())


def test_key_q_quits(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "Q")
    assert not app.running


def test_bus_rates_are_stats_deltas_over_time(session: Session) -> None:
    app = MonitorApp(session)
    before = session.backend.comm_stats()["j1"].total_transactions
    start = session.backend.clock.now()
    app.step(0.2)  # about 0.2 s: the steps keep to the schedule, the reads take wire time
    after = session.backend.comm_stats()["j1"].total_transactions
    elapsed = session.backend.clock.now() - start
    assert app.rates["j1"] == pytest.approx(((after - before) / elapsed, 0.0))


def test_leaving_the_monitor_aborts_a_running_homing(session: Session) -> None:
    app = MonitorApp(session)
    handle_key(app, "e")
    handle_key(app, "h")
    app.close()
    assert not session.arm.homing_names()


def test_monitor_runs_for_a_duration_without_a_terminal(bioscara: Run) -> None:
    code, out, _ = bioscara("monitor", "--duration", "0.2", "--rate", "20")
    assert code == 0
    assert "bioscara monitor" in out
    assert "lifecycle INACTIVE   backend emulated" in out


def test_monitor_stops_at_its_duration_however_slow_its_rate(bioscara: Run, state: Path) -> None:
    # Seen (a hostile test): --rate 0.05 --duration 1 ran the arm a whole 20 s period (21 s).
    code, _, _ = bioscara("monitor", "--rate", "0.05", "--duration", "0.2", "--state", str(state))
    assert code == 0
    assert json.loads(state.read_text())["time_s"] == pytest.approx(0.2, abs=0.05)


@pytest.mark.parametrize(
    ("rate", "message"),
    [
        (
            "1e-300",
            "--rate 1e-300 is too slow; expected at least 0.01 refreshes per second (one every 100 s)",
        ),
        ("0", "--rate 0 must be a positive number of refreshes per second"),
        ("nan", "--rate nan must be a positive number of refreshes per second"),
        ("inf", "--rate inf must be a positive number of refreshes per second"),
    ],
)
def test_monitor_refuses_a_rate_it_cannot_keep(bioscara: Run, rate: str, message: str) -> None:
    # Seen (a hostile test): --rate 1e-300 --duration 1 ran forever.
    code, _, err = bioscara("monitor", "--rate", rate, "--duration", "1")
    assert code == 2
    assert err == f"bioscara monitor: error: {message}"


def test_monitor_without_a_terminal_needs_a_duration(bioscara: Run) -> None:
    code, _, err = bioscara("monitor")
    assert code == 2
    assert "without one pass --duration S" in err


# ------------------------------------------------------------------ layout
#: The console's modules, each importing only modules before it.
CONSOLE_LAYERS = ("format", "targets", "state", "session", "dashboard", "commands")
#: Until cli.py registers bioscara_gym.console.commands: session.register's shim.
TEMPORARY_IMPORTS: set[tuple[str, str]] = set()


def test_console_modules_import_one_way() -> None:
    package = Path(__file__).resolve().parents[1] / "bioscara_gym" / "console"
    backward = []
    for layer, name in enumerate(CONSOLE_LAYERS):
        tree = ast.parse((package / f"{name}.py").read_text(encoding="utf-8"))
        for node in ast.walk(tree):  # function-local imports included
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("bioscara_gym.console."):
                target = node.module.rsplit(".", 1)[-1]
                if CONSOLE_LAYERS.index(target) >= layer and (name, target) not in TEMPORARY_IMPORTS:
                    backward.append(f"{name} imports {target}")
    assert not backward
