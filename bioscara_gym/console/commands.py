"""Operator console: ``bioscara status|ping|enable|disable|home|move|gripper|monitor|reboot``.

What the RViz panel of the original stack (arm and gripper up and down, joint
states, homing) and MH5's terminal dashboard (per-joint bars, communication
statistics) did, at a terminal and on every backend. Every subcommand takes

=================== ==========================================================
``--backend NAME``  ``emulated`` (default: the real driver over the emulated
                    bus, so anyone can try it), ``sim``, ``mock`` or ``i2c``
``--config FILE``   arm configuration YAML (default: the packaged one)
``--bus N``         I2C bus number for ``i2c`` (default: the config's; refused
                    on the other backends, which have no numbered bus)
``--state FILE``    keep the simulated arm's state in FILE between commands
``--record FILE``   append every bus transaction to FILE (``i2c``,
                    ``emulated``; ``bioscara replay FILE``, docs/traces.md)
=================== ==========================================================

A command opens a :class:`~bioscara_gym.console.session.Session` (backend,
:class:`~bioscara_gym.hardware.arm.Arm` configured, the state file restored),
does its one thing and closes it. Joints and the gripper are named as in the
configuration; ``enable`` and ``disable`` also take a group (``all``, ``arm``,
``gripper`` by default; ``groups`` in the configuration).

Safe-state policy (what each command leaves behind):

- ``status`` and ``ping`` send nothing that changes the arm.
- ``enable`` leaves the named joints enabled and holding still (no command
  interface active, set points at the measured position): that is its
  purpose. Nothing moves; the console never uses velocity mode, and the
  firmware's deadman covers velocity mode where others use it. ``disable``
  leaves them back-drivable.
- ``home`` and ``move`` wait until the motion is over (homed, or the target
  reached) and the joint holds still; a timeout aborts the motion.
  ``home --no-wait`` (only with ``--state``) leaves the homing running for
  a later ``monitor`` (which finishes it) or ``home --abort``.
- ``gripper WIDTH`` leaves the servo driven at the width (a gripper holding
  an object must keep holding it).
- ``monitor`` aborts any homing still running when it quits; joints stay as
  the operator left them.
- ``reboot`` (Dynamixel joints) sends REBOOT: it clears a hardware error and
  leaves the servo with torque off.

On the ``dynamixel`` backends ``status`` adds the sync loops' statistics
(``pvl_reader``, ``tv_reader``, ``pv_writer``, ``t_writer``: configured and
achieved rate, packets, errors, timeouts) and ``monitor`` lists them with the
joints' bus counters.
- A request refused for its arguments (an unknown joint or group, a value
  outside the limits, a reboot of joints without REBOOT) is refused against
  the configuration before the state file is locked or the bus opened: it
  sends nothing and writes nothing (no state file, no bus trace), and exits 2
  with one line naming the problem. One refused for the state the arm is in
  (a joint not enabled, not homed, busy) sends nothing that changes the arm,
  leaves it as it was and exits 2 as well.
- Any other error (a stall, a bus failure, a ``home`` or ``move`` that
  timed out) and Ctrl-C run the arm layer's on-error transition: every
  joint and the gripper are disabled (a running homing is stopped), then
  the command exits with one line naming the problem: 3 (130, 143 or 129
  after a signal), where a refusal exits 2.

State between invocations (``--state FILE``, ``emulated`` and ``sim`` only):
without it every command starts from a powered-up arm (not homed, not
enabled), so ``enable`` then ``home`` then ``status`` needs it. The file is
written after every command, also a failed one; its format and what it
keeps are described in :mod:`bioscara_gym.console.state`. The ``mock``
backend does not persist (``--state`` is refused), nor does ``i2c``: the
real arm keeps its own state.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import math
import re
from dataclasses import dataclass

from rich import box
from rich.console import Console
from rich.table import Table

from bioscara_gym.console.dashboard import MonitorApp, key_source, run_monitor
from bioscara_gym.console.format import flags_text, format_position, format_velocity, joint_unit
from bioscara_gym.console.session import Session
from bioscara_gym.console.targets import (
    HOMING_DIRECTIONS,
    ConsoleOptions,
    check_gripper_width,
    check_position,
    reboot_joints,
    resolve_joints,
    resolve_target,
)
from bioscara_gym.errors import ConsoleUsageError
from bioscara_gym.fsutil import path_argument
from bioscara_gym.hardware.backends import ALL_BACKENDS
from bioscara_gym.hardware.config import GRIPPER_NAME, ArmConfig
from bioscara_gym.hardware.errors import InvalidArgumentError, JointError, MissingExtraError
from bioscara_gym.hardware.i2c_timing import wire_time_s
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.sitl.build import add_firmware_option

#: One ``ping`` reply: device, address (``"-"`` without a bus), ``"OK"`` or the error, flags.
PingReply = tuple[str, str, str, Flag | None]


# ------------------------------------------------------------------ output
def make_console() -> Console:
    """A console for command output: at least 120 columns when not a terminal (pipes, logs)."""
    con = Console(highlight=False)
    if not con.is_terminal:
        con = Console(highlight=False, width=max(120, con.width))
    return con


def _table(*columns: tuple[str, str]) -> Table:
    """A table in the console's style with the given (title, justify) columns."""
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    for title, justify in columns:
        table.add_column(title, justify=justify)  # type: ignore[arg-type]
    return table


def lifecycle_line(session: Session) -> str:
    """The line above the status table: lifecycle, backend, simulated time, state file."""
    parts = [f"arm {session.arm.state.value}", f"backend {session.backend.name}"]
    if session.is_simulated():
        parts.append(f"simulated time {session.backend.clock.now():.2f} s")
    if session.options.state is not None:
        parts.append(f"state {session.options.state}")
    return " · ".join(parts)


def status_table(session: Session) -> Table:
    """The ``bioscara status`` table: one row per joint and the gripper."""
    arm = session.arm
    stats = session.backend.comm_stats()
    table = _table(
        ("joint", "left"),
        ("position", "right"),
        ("velocity", "right"),
        ("enabled", "left"),
        ("homed", "left"),
        ("flags", "left"),
        ("bus tx", "right"),
        ("bus errors", "right"),
    )
    for cfg in session.config.joints:
        st = arm.joint_states[cfg.name]
        unit = joint_unit(cfg.joint_type)
        s = stats.get(cfg.name)
        table.add_row(
            cfg.name,
            format_position(st.position if st.homed else None, unit),
            format_velocity(st.velocity, unit),
            _yes_no(arm.joints[cfg.name].is_enabled()),
            "homing…" if st.homing else _yes_no(st.homed),
            flags_text(st.flags),
            "-" if s is None else str(s.total_transactions),
            "-" if s is None else str(s.total_errors),
        )
    gripper_enabled = _yes_no(session.backend.gripper.is_enabled)
    table.add_row(GRIPPER_NAME, f"{session.gripper_width():.4f} m", "", gripper_enabled, "", "", "", "")
    return table


def loop_table(session: Session) -> Table | None:
    """The sync loops' statistics (Dynamixel backends), or ``None`` where there are none."""
    loops = session.backend.loop_stats()
    if not loops:
        return None
    table = _table(
        ("loop", "left"),
        ("rate Hz", "right"),
        ("achieved Hz", "right"),
        ("packets", "right"),
        ("errors", "right"),
        ("timeouts", "right"),
        ("total packets", "right"),
        ("total errors", "right"),
    )
    for name, s in loops.items():
        d = s.as_dict()  # type: ignore[attr-defined]
        table.add_row(
            name,
            f"{d['rate_hz']:g}",
            f"{d['achieved_hz']:.1f}",
            str(d["packets"]),
            str(d["errors"]),
            str(d["timeouts"]),
            str(d["total_packets"]),
            str(d["total_errors"]),
        )
    return table


#: Control rate the bus-time budget of ``bioscara status`` is given for, Hz (the envs' default).
BUDGET_RATE_HZ = 25.0


@dataclass(frozen=True)
class BusBudget:
    """The I2C bus time of one control cycle of the envs' loop.

    Attributes:
        transactions: Bus transactions one env step makes (counted on the emulated bus).
        wire_s: Their wire time at ``clock_hz``, s (no latency, no retries).
        clock_hz: The bus clock, Hz.
        period_s: The control period, s.
    """

    transactions: int
    wire_s: float
    clock_hz: float
    period_s: float

    @property
    def share(self) -> float:
        """Fraction of the control period the transactions occupy the bus."""
        return self.wire_s / self.period_s

    def line(self) -> str:
        """One line for ``bioscara status``."""
        return (
            f"bus time per {1.0 / self.period_s:g} Hz cycle: {self.transactions} transactions, "
            f"{self.wire_s * 1000:.2f} ms at {self.clock_hz / 1000:g} kHz = {self.share:.1%} of "
            f"{self.period_s * 1000:g} ms (one Reach env step on the emulated bus)"
        )


@functools.lru_cache(maxsize=4)
def bus_budget(config: ArmConfig, rate_hz: float = BUDGET_RATE_HZ) -> BusBudget:
    """Count the transactions of one Reach env step on the emulated bus and their wire time.

    The env (default control mode) is brought up and stepped once with a
    zero action (on its own emulated arm, keeping no gripper state file);
    the bus's own record gives each transaction's length, and
    :func:`~bioscara_gym.hardware.i2c_timing.wire_time_s` its time at the
    configuration's ``i2c_clock_hz``.

    Raises:
        MissingExtraError: The ``sim`` extra (MuJoCo) is not installed.
    """
    import gymnasium as gym
    import numpy as np

    import bioscara_gym  # noqa: F401 - registers the envs

    quiet = dataclasses.replace(config, gripper=dataclasses.replace(config.gripper, state_file=None))
    env = gym.make("Bioscara-Reach-v0", backend="emulated", config=quiet, control_freq=rate_hz)
    try:
        env.reset(seed=0)
        bus = env.unwrapped.backend.bus
        bus.history = []  # record this step's transactions
        env.step(np.zeros(env.action_space.shape, dtype=env.action_space.dtype))
        lengths = [(len(data), read_len) for _, _, data, read_len in bus.history]
        period_s = env.unwrapped.dt
    finally:
        env.close()
    wire_s = sum(wire_time_s(w, r, config.i2c_clock_hz) for w, r in lengths)
    return BusBudget(len(lengths), wire_s, config.i2c_clock_hz, period_s)


def budget_line(session: Session) -> str | None:
    """The status line with the control cycle's bus-time budget; ``None`` for an arm without I2C joints."""
    config = session.config
    if session.backend.loop_stats() or any(j.type != "i2c" for j in config.joints):
        return None
    try:
        return bus_budget(config).line()
    except MissingExtraError as e:
        return f"bus time per cycle: not counted ({e})"
    except (JointError, ValueError) as e:  # seen: its emulated arm's homing timeout, as status's own error
        return f"bus time per cycle: not counted (the emulated arm it is counted on failed: {e})"


def _yes_no(value: bool) -> str:
    """``yes`` or ``no``."""
    return "yes" if value else "no"


def ping_devices(session: Session) -> list[PingReply]:
    """PING every joint separately (opening and closing the ones not open) and set up the gripper."""
    on_bus = session.backend.name in ("emulated", "i2c")
    replies = [
        _ping_joint(session, cfg.name, f"0x{cfg.address:02X}" if on_bus else "-")
        for cfg in session.config.joints
    ]
    return [*replies, _ping_gripper(session)]


def _ping_joint(session: Session, name: str, address: str) -> PingReply:
    """PING one joint: its flags if it answered, else the error."""
    joint = session.arm.joints[name]
    was_open = joint.initialized
    try:
        if was_open:
            joint.get_flags()
        else:
            joint.init()
        return (name, address, "OK", joint.flags)
    except JointError as e:
        return (name, address, str(e), None)
    finally:
        if not was_open:
            joint.deinit()


def _ping_gripper(session: Session) -> PingReply:
    """Set the gripper up and release it again (the servo has no reply to wait for)."""
    gripper = session.backend.gripper
    try:
        if not gripper.is_initialized:
            gripper.init()
            gripper.deinit()
        return (GRIPPER_NAME, "-", "OK", None)
    except JointError as e:
        return (GRIPPER_NAME, "-", str(e), None)


def ping_table(replies: list[PingReply]) -> Table:
    """The ``bioscara ping`` table: one row per device."""
    table = _table(("device", "left"), ("address", "left"), ("reply", "left"), ("flags", "left"))
    for name, address, reply, flags in replies:
        table.add_row(name, address, reply, "" if flags is None else flags_text(flags))
    return table


# ---------------------------------------------------------------- commands
def current_notes(session: Session) -> list[str]:
    """A line for each homed joint that reports not enabled but may still have current.

    The firmware's deadman sets NOT_ENABLED and keeps the currents
    (docs/firmware.md); a disable cuts them. Where the backend sees the
    device's currents (simulated), only a joint with current is named;
    on the arm the flag cannot tell, so every such joint is.
    """
    notes = []
    for name, st in session.arm.joint_states.items():
        if not (st.homed and st.flags & Flag.NOT_ENABLED):
            continue
        currents = session.backend.device_currents(name)
        if currents is not None and not any(currents):
            continue
        notes.append(
            f"{name}: NOT_ENABLED is a flag: after a deadman trip the current stays on; "
            f"`bioscara disable {name}` cuts it"
        )
    return notes


def cmd_status(args: argparse.Namespace) -> int:
    """``bioscara status``."""
    con = make_console()
    # Printed once the session has closed: a reader that leaves early (| head) is no error of the arm's.
    lines: list[tuple[object, bool]] = []
    with Session(ConsoleOptions.from_args(args)) as session:
        lines += [(lifecycle_line(session), True), (status_table(session), True)]
        lines += [(note, False) for note in current_notes(session)]
        budget = budget_line(session)
        if budget is not None:
            lines.append((budget, False))  # "[sim]" in a missing extra's name is no style tag
        if loop_table(session) is not None:
            session.backend.step(0.0)  # one pass of the loops, so that they have something to show
            lines.append((loop_table(session), True))
    for line, markup in lines:
        con.print(line, markup=markup)
    return 0


def cmd_ping(args: argparse.Namespace) -> int:
    """``bioscara ping``: exit 1 if any joint did not answer."""
    con = make_console()
    with Session(ConsoleOptions.from_args(args), configure=False) as session:
        replies = ping_devices(session)
    con.print(ping_table(replies))
    missing = [name for name, _, reply, _ in replies if reply != "OK"]
    if missing:
        con.print(f"no answer from {', '.join(missing)}")
        return 1
    con.print(f"all {len(replies)} devices answered")
    return 0


def cmd_enable(args: argparse.Namespace) -> int:
    """``bioscara enable [JOINT|GROUP]``."""
    con = make_console()
    check = functools.partial(_check_target, target=args.target)
    with Session(ConsoleOptions.from_args(args), check=check) as session:
        names = session.enable(resolve_target(session.config, args.target))
        con.print(f"enabled {', '.join(names)}; holding still · arm {session.arm.state.value}")
    return 0


def cmd_disable(args: argparse.Namespace) -> int:
    """``bioscara disable [JOINT|GROUP]``."""
    con = make_console()
    check = functools.partial(_check_target, target=args.target)
    with Session(ConsoleOptions.from_args(args), check=check) as session:
        names = session.disable(resolve_target(session.config, args.target))
        con.print(f"disabled {', '.join(names)} · arm {session.arm.state.value}")
    return 0


def _check_target(config: ArmConfig, target: str | None) -> None:
    """Refuse an unknown joint or group (``enable``, ``disable``) before the session opens."""
    resolve_target(config, target)


def cmd_reboot(args: argparse.Namespace) -> int:
    """``bioscara reboot JOINT|GROUP``: REBOOT Dynamixel joints (clears a hardware error; torque off)."""
    con = make_console()
    options = ConsoleOptions.from_args(args)
    check = functools.partial(reboot_joints, backend=options.backend, name=args.target)
    with Session(options, check=check) as session:
        names = reboot_joints(session.config, options.backend, args.target)
        rebooted = []
        for name in names:
            joint = session.arm.joints[name]
            reboot = getattr(joint, "reboot", None)
            if reboot is None:  # (a backend reboot_joints does not know)
                raise InvalidArgumentError(
                    f"{name}: a {type(joint).__name__} has no REBOOT; only Dynamixel joints do "
                    "(power-cycle a Bioscara joint instead)"
                )
            reboot()
            rebooted.append(name)
        session.arm.read()
        con.print(f"rebooted {', '.join(rebooted)}; torque off · arm {session.arm.state.value}")
    return 0


def cmd_home(args: argparse.Namespace) -> int:
    """``bioscara home [JOINT|GROUP] [--direction +|-] [--abort] [--no-wait]``."""
    con = make_console()
    options = ConsoleOptions.from_args(args)
    if args.abort:  # refused, not ignored: the operator meant something by them
        given = {"--direction": args.direction, "--no-wait": args.no_wait or None, "--timeout": args.timeout}
        unused = [option for option, value in given.items() if value is not None]
        if unused:
            raise ConsoleUsageError(f"--abort stops a running homing; it takes no {' or '.join(unused)}")
    if args.no_wait and options.state is None:
        raise ConsoleUsageError("--no-wait needs --state FILE, so that a later command can finish the homing")
    with Session(options, check=functools.partial(resolve_joints, name=args.target)) as session:
        if args.abort:
            _abort_homing(con, session, args.target)
            return 0
        names = _joints_to_home(session, args.target)
        if not names:
            con.print("every joint is homed; name a joint to home it again")
        elif args.no_wait:
            _start_homing(con, session, names, HOMING_DIRECTIONS.get(args.direction))
        else:
            _home_and_wait(con, session, names, HOMING_DIRECTIONS.get(args.direction), args.timeout)
    return 0


def _joints_to_home(session: Session, target: str | None) -> tuple[str, ...]:
    """The joints named, or (no name) every joint not yet homed."""
    names = resolve_joints(session.config, target)
    if target is None:
        names = tuple(n for n in names if not session.arm.joints[n].is_homed())
    return names


def _abort_homing(con: Console, session: Session, target: str | None) -> None:
    """``home --abort``: abort the named joints' homings and say which."""
    aborted = session.arm.abort_homing(resolve_joints(session.config, target))
    con.print(f"aborted homing of {', '.join(aborted)} (not homed)" if aborted else "no homing is running")


def _start_homing(con: Console, session: Session, names: tuple[str, ...], direction: int | None) -> None:
    """``home --no-wait``: start the homings and say where each runs."""
    for name, speed in session.start_homing(names, direction).items():
        unit = joint_unit(session.config.joint(name).joint_type)
        con.print(f"{name} homing toward {_end(speed)} at {abs(speed):g} {unit}/s (left running)")


def _home_and_wait(
    con: Console, session: Session, names: tuple[str, ...], direction: int | None, timeout_s: float | None
) -> None:
    """``home``: home the joints, then say where each homed and how long it took."""
    clock = session.backend.clock
    start = clock.now()
    label = f"homing {', '.join(names)}"
    with con.status(label + "…") if con.is_terminal else contextlib.nullcontext():
        speeds = session.home(names, direction, timeout_s)
    for name, speed in speeds.items():
        unit = joint_unit(session.config.joint(name).joint_type)
        position = session.arm.joint_states[name].position
        con.print(f"{name} homed at {_end(speed)}: {position:+.4f} {unit}")
    con.print(f"{label} took {clock.now() - start:.2f} s")


def _end(speed: float) -> str:
    """The end stop a homing at ``speed`` runs to: ``max`` or ``min``."""
    return "max" if speed > 0 else "min"


def cmd_move(args: argparse.Namespace) -> int:
    """``bioscara move JOINT VALUE``."""
    con = make_console()
    check = functools.partial(check_position, name=args.joint, value=args.value)
    with Session(ConsoleOptions.from_args(args), check=check) as session:
        clock = session.backend.clock
        start = clock.now()
        position = session.move(args.joint, args.value, args.timeout)
        unit = joint_unit(session.config.joint(args.joint).joint_type)
        took = clock.now() - start
        con.print(f"{args.joint} at {position:+.4f} {unit} (target {args.value:+.4f}) after {took:.2f} s")
    return 0


def cmd_gripper(args: argparse.Namespace) -> int:
    """``bioscara gripper WIDTH``."""
    con = make_console()
    check = functools.partial(check_gripper_width, width_m=args.width)
    with Session(ConsoleOptions.from_args(args), check=check) as session:
        width = session.set_gripper(args.width)
        con.print(f"gripper at {width:.4f} m (servo driven)")
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    """``bioscara monitor``."""
    _check_monitor_args(args)
    con = make_console()
    with key_source() as keys:
        if keys is None and args.duration is None:
            raise ConsoleUsageError("monitor reads keys from a terminal; without one pass --duration S")
        with Session(ConsoleOptions.from_args(args)) as session:
            app = MonitorApp(session, rate_hz=args.rate)
            try:
                run_monitor(app, con, keys, duration_s=args.duration)
            finally:
                app.close()
    return 0


#: The slowest ``monitor --rate``, Hz: a refresh every 100 s (the arm is cycled a whole period between two).
MIN_MONITOR_RATE_HZ = 0.01


def _check_monitor_args(args: argparse.Namespace) -> None:
    """Refuse a refresh rate or duration that is not a positive number, or a rate below 0.01 Hz."""
    if args.rate <= 0 or not math.isfinite(args.rate):
        raise ConsoleUsageError(f"--rate {args.rate:g} must be a positive number of refreshes per second")
    if args.rate < MIN_MONITOR_RATE_HZ:
        raise ConsoleUsageError(
            f"--rate {args.rate:g} is too slow; expected at least {MIN_MONITOR_RATE_HZ:g} refreshes "
            "per second (one every 100 s)"
        )
    if args.duration is not None and not args.duration > 0:
        raise ConsoleUsageError(f"--duration {args.duration:g} must be positive")


# ------------------------------------------------------------------ parser
def _seconds(text: str) -> float:
    """A ``--timeout``: a positive, finite number of seconds (NaN never times out)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text} must be a positive, finite number of seconds")
    return value


def _common(parser: argparse.ArgumentParser) -> None:
    """Add the options every operator subcommand takes."""
    parser.add_argument(
        "--backend", choices=ALL_BACKENDS, default="emulated", help="arm backend (default: emulated)"
    )
    add_firmware_option(parser)
    parser.add_argument(
        "--config",
        type=path_argument,
        metavar="FILE",
        help="arm configuration YAML (default: the packaged one)",
    )
    parser.add_argument(
        "--bus", type=int, metavar="N", help="I2C bus number for --backend i2c (default: the config's)"
    )
    parser.add_argument(
        "--state",
        type=path_argument,
        metavar="FILE",
        help="keep the simulated arm's state in FILE between commands (emulated, sim)",
    )
    parser.add_argument(
        "--record",
        type=path_argument,
        metavar="FILE",
        help="append every bus transaction to FILE (i2c, emulated; docs/traces.md)",
    )


def _signed_numbers(parser: argparse.ArgumentParser) -> None:
    """Read ``-5e-1`` as a number, as Python 3.13's argparse does, not as an unknown option.

    Seen: ``move j1 -5e-1`` said "the following arguments are required:
    VALUE" where ``-.5`` worked: Python 3.11's argparse takes for a negative
    number only ``-5`` and ``-.5``. 3.13 takes anything starting with ``-``
    and a digit (its ``_negative_number_matcher``, set here the same way).
    """
    parser._negative_number_matcher = re.compile(r"-\.?\d")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the operator subcommands: status, ping, enable, disable, home, move, gripper, reboot, monitor."""
    p = sub.add_parser("status", help="lifecycle, joint states, gripper and bus statistics")
    _common(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("ping", help="ping every joint (exit 1 if one does not answer)")
    _common(p)
    p.set_defaults(func=cmd_ping)

    for name, verb in (("enable", "enable"), ("disable", "disable")):
        p = sub.add_parser(name, help=f"{verb} a joint, the gripper or a group (default: all)")
        p.add_argument("target", nargs="?", metavar="JOINT|GROUP", help="joint, 'gripper' or group")
        _common(p)
        p.set_defaults(func=cmd_enable if name == "enable" else cmd_disable)

    p = sub.add_parser("home", help="home joints with the configured homing parameters")
    p.add_argument("target", nargs="?", metavar="JOINT|GROUP", help="default: every joint not yet homed")
    p.add_argument(
        "--direction", choices=("+", "-"), help="+ homes to the max end stop, - to min (default: configured)"
    )
    p.add_argument("--abort", action="store_true", help="abort a running homing instead")
    p.add_argument("--no-wait", action="store_true", help="start homing and return (needs --state)")
    p.add_argument(
        "--timeout", type=_seconds, metavar="S", help="seconds (default: the whole range at homing speed)"
    )
    _common(p)
    p.set_defaults(func=cmd_home)

    p = sub.add_parser("move", help="move a homed, enabled joint to a position and wait")
    _signed_numbers(p)
    p.add_argument("joint", metavar="JOINT")
    p.add_argument("value", type=float, metavar="VALUE", help="rad (m for the prismatic j2)")
    p.add_argument("--timeout", type=_seconds, metavar="S", help="seconds (default: from the joint's limits)")
    _common(p)
    p.set_defaults(func=cmd_move)

    p = sub.add_parser("gripper", help="set the gripper width (enables the servo)")
    _signed_numbers(p)
    p.add_argument("width", type=float, metavar="WIDTH", help="m")
    _common(p)
    p.set_defaults(func=cmd_gripper)

    p = sub.add_parser("reboot", help="reboot Dynamixel joints (clears a hardware error; torque off)")
    p.add_argument("target", metavar="JOINT|GROUP", help="joint or group")
    _common(p)
    p.set_defaults(func=cmd_reboot)

    p = sub.add_parser("monitor", help="live dashboard; keys e/d enable/disable, h home, a abort, q quit")
    p.add_argument(
        "--rate", type=float, default=10.0, metavar="HZ", help="refreshes per second, >= 0.01 (default: 10)"
    )
    p.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (needed without a terminal)"
    )
    _common(p)
    p.set_defaults(func=cmd_monitor)
