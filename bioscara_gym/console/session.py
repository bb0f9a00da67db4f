"""Operator console: ``bioscara status|ping|enable|disable|home|move|gripper|monitor``.

What the RViz panel of the original stack (arm and gripper up and down, joint
states, homing) and MH5's terminal dashboard (per-joint bars, communication
statistics) did, at a terminal and on every backend. Every subcommand takes

=================== ==========================================================
``--backend NAME``  ``emulated`` (default: the real driver over the emulated
                    bus, so anyone can try it), ``sim``, ``mock`` or ``i2c``
``--config FILE``   arm configuration YAML (default: the packaged one)
``--bus N``         I2C bus number for ``i2c`` (default: the config's)
``--state FILE``    keep the simulated arm's state in FILE between commands
=================== ==========================================================

A command opens a :class:`Session` (backend, :class:`~bioscara_gym.hardware.arm.Arm`
configured, the state file restored), does its one thing and closes it.
Joints and the gripper are named as in the configuration; ``enable`` and
``disable`` also take a group (``all``, ``arm``, ``gripper`` by default;
``groups`` in the configuration).

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
- Any error (a refused request such as an unknown joint, a value outside the
  limits or a busy joint, a stall, a bus failure) and Ctrl-C run the arm
  layer's on-error transition: every joint and the gripper are disabled
  (a running homing is stopped), then the command exits non-zero with one
  line naming the problem.

Joints enabled by an earlier command are adopted as they are
(:meth:`~bioscara_gym.hardware.arm.Arm.attach`): the arm is ``active`` when
any joint or the gripper is enabled, without re-sending SETUP (which would
stop a running homing), and a homing left running is handed back to the arm
(:meth:`~bioscara_gym.hardware.arm.Arm.adopt_homing`).

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
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from rich import box
from rich.console import Console
from rich.table import Table

from bioscara_gym.console.dashboard import flags_text, format_position, format_velocity, joint_unit
from bioscara_gym.console.state import HostFacts, load_state, save_state
from bioscara_gym.errors import ConsoleUsageError
from bioscara_gym.hardware.arm import Arm, ArmStateError, CommandMode, Lifecycle
from bioscara_gym.hardware.backends import BACKENDS, Backend, make_backend
from bioscara_gym.hardware.config import GRIPPER_NAME, ArmConfig, JointConfig, load_config
from bioscara_gym.hardware.errors import (
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
)
from bioscara_gym.hardware.gripper import Gripper
from bioscara_gym.hardware.registers import Flag

#: Period of the arm's read/write cycle while a command waits, s (25 Hz).
CYCLE_S = 0.04
#: How long ``gripper WIDTH`` lets the servo travel, s.
GRIPPER_SETTLE_S = 0.3
#: Backends whose state ``--state`` can keep.
PERSISTENT_BACKENDS = ("emulated", "sim")
#: A move is reached within this many rad (revolute) or m (prismatic), at
#: a tenth of it per s.
MOVE_TOLERANCE = {"revolute": 1e-3, "prismatic": 1e-4}


# ----------------------------------------------------------------- options
@dataclass(frozen=True)
class ConsoleOptions:
    """The options every operator subcommand shares.

    Attributes:
        backend: Backend name (see :data:`~bioscara_gym.hardware.backends.BACKENDS`).
        config: Arm configuration YAML, ``None`` for the packaged default.
        bus: I2C bus number overriding the configuration's.
        state: State file for the simulated backends, ``None`` for none.
    """

    backend: str = "emulated"
    config: Path | None = None
    bus: int | None = None
    state: Path | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ConsoleOptions:
        """Take the common options from parsed arguments."""
        return cls(backend=args.backend, config=args.config, bus=args.bus, state=args.state)


@dataclass(frozen=True)
class Target:
    """Devices a joint or group name stands for.

    Attributes:
        joints: Joint names, in configuration order.
        gripper: Whether the gripper is included.
    """

    joints: tuple[str, ...]
    gripper: bool


def resolve_target(config: ArmConfig, name: str | None) -> Target:
    """Resolve a joint, ``gripper`` or group name.

    Args:
        config: The arm configuration (joints and groups).
        name: A joint name, ``"gripper"``, a group name, or ``None`` for
            the group ``all`` (every joint and the gripper if not configured).

    Returns:
        The joints (configuration order) and whether the gripper is included.

    Raises:
        InvalidArgumentError: Unknown name; the message lists joints and groups.
    """
    if name is None:
        if "all" not in config.groups:
            return Target(config.names, True)
        name = "all"
    if name in config.names:
        return Target((name,), False)
    if name == GRIPPER_NAME:
        return Target((), True)
    members = config.groups.get(name)
    if members is None:
        raise InvalidArgumentError(
            f"unknown joint or group {name!r}; joints: {', '.join((*config.names, GRIPPER_NAME))}; "
            f"groups: {', '.join(config.groups) or 'none'}"
        )
    return Target(tuple(n for n in config.names if n in members), GRIPPER_NAME in members)


def joint_config(config: ArmConfig, name: str) -> JointConfig:
    """The configuration of joint ``name``.

    Raises:
        InvalidArgumentError: Unknown joint; the message lists the joints.
    """
    for joint in config.joints:
        if joint.name == name:
            return joint
    raise InvalidArgumentError(f"unknown joint {name!r}; known joints: {', '.join(config.names)}")


def homing_speed(config: JointConfig, direction: str | None = None) -> float:
    """Signed homing speed: the configured one, its sign set by ``direction``.

    Args:
        config: The joint's configuration.
        direction: ``"+"`` (to the max end stop), ``"-"`` (to min) or
            ``None`` (the configured sign).
    """
    speed = config.homing.speed
    if direction is None:
        return speed
    if direction not in ("+", "-"):
        raise InvalidArgumentError(f"{config.name}: homing direction {direction!r} must be '+' or '-'")
    return abs(speed) if direction == "+" else -abs(speed)


def homing_timeout_s(config: JointConfig, speed: float) -> float:
    """Time a homing may take, s: the whole range at the homing speed, with margin."""
    return 0.5 + 1.2 * (config.max - config.min) / abs(speed) + 5.0


def move_timeout_s(config: JointConfig, distance: float) -> float:
    """Time a move of ``distance`` may take, s: twice the trapezoid profile's, plus 5 s."""
    return 2.0 * (abs(distance) / config.max_velocity + config.max_velocity / config.max_acceleration) + 5.0


def _read_saved_width(path: Path | None) -> float | None:
    """The width in the gripper's own state file (``{"width_m": w}``), or ``None``."""
    if path is None:
        return None
    try:
        value = json.loads(path.read_text(encoding="utf-8")).get("width_m")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return None
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _pwm_output_on(gripper: Gripper) -> bool:
    """Whether the real servo's PWM output is on (sysfs ``enable``); ``False`` if unreadable."""
    try:
        return (gripper.pwm_path / "enable").read_text().strip() == "1"
    except OSError:
        return False


# ----------------------------------------------------------------- session
class Session:
    """One command's hold on the arm: backend, arm layer, state file.

    Use as a context manager. Entering builds the backend, restores the state
    file, configures the arm (``configure=False`` leaves it unconfigured, for
    ``ping``) and adopts what earlier commands left (enabled joints, the
    gripper, homings still running). Leaving after an exception (including
    Ctrl-C) runs the arm layer's on-error transition, disabling everything;
    then the state file is written and the connections released, leaving
    enabled joints enabled.

    Args:
        options: The common command-line options.
        configure: Whether to configure the arm on entering.
    """

    def __init__(self, options: ConsoleOptions, configure: bool = True) -> None:
        """Remember the options; nothing is opened before ``__enter__``."""
        self.options = options
        self._configure = configure
        self.backend: Backend
        self.arm: Arm
        self.facts = HostFacts()
        self._opened = False
        self._attached = False
        self._save = False

    # ------------------------------------------------------------ lifetime
    def __enter__(self) -> Session:
        """Open the backend, restore the state, configure and adopt the arm."""
        try:
            self._open()
        except BaseException as e:
            self._close(e)
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Make the arm safe after an error, save the state, release the connections."""
        self._close(exc)

    def _open(self) -> None:
        o = self.options
        if o.backend not in BACKENDS:
            raise ConsoleUsageError(f"unknown backend {o.backend!r}; expected one of {', '.join(BACKENDS)}")
        if o.state is not None and o.backend not in PERSISTENT_BACKENDS:
            reason = (
                "mock state does not persist" if o.backend == "mock" else "the real arm keeps its own state"
            )
            raise ConsoleUsageError(
                f"--state works with the {' and '.join(PERSISTENT_BACKENDS)} backends; {reason}"
            )
        config = load_config(o.config)
        if o.bus is not None:
            config = dataclasses.replace(config, bus=o.bus)
        self.backend = make_backend(o.backend, config)
        self.arm = Arm(self.backend)  # sends nothing before configure()
        self._opened = True
        if o.state is not None and o.state.exists():
            self.facts = load_state(o.state, self.backend)
        self._save = o.state is not None
        for name, stats in self.backend.comm_stats().items():
            for key, value in self.facts.stats.get(name, {}).items():
                setattr(stats, key, value)
        if self._configure:
            self.arm.configure()
            self._attached = True
            self.arm.attach()
            self._adopt_gripper()
            self._adopt_homings()

    def _close(self, exc: BaseException | None) -> None:
        if not self._opened:
            return
        try:
            if exc is not None:
                self._remember_gripper()
                self.arm.recover()
        finally:
            try:
                if self._save and self.options.state is not None:
                    self._collect_facts(failed=exc is not None)
                    try:
                        save_state(self.options.state, self.backend, self.facts)
                    except OSError:
                        if exc is None:
                            raise
            finally:
                self._detach()

    def _detach(self) -> None:
        """Release the connections; enabled joints and an enabled gripper stay so."""
        for joint in self.arm.joints.values():
            joint.deinit()
        gripper = self.backend.gripper
        if gripper.is_initialized and not gripper.is_enabled:
            gripper.deinit()
        self.backend.close()

    def _remember_gripper(self) -> None:
        gripper = self.backend.gripper
        if gripper.is_initialized and gripper.is_enabled:
            self.facts.gripper_width_m = gripper.get_position()

    def _collect_facts(self, failed: bool) -> None:
        arm = self.arm
        self.facts.stats = {n: dataclasses.asdict(s) for n, s in self.backend.comm_stats().items()}
        if failed:  # the on-error transition disabled everything
            self.facts.gripper_enabled = False
            self.facts.homing = {}
            return
        if not self._attached:
            return  # never configured (ping): what was loaded still holds
        self._remember_gripper()
        self.facts.gripper_enabled = self.backend.gripper.is_enabled
        self.facts.homing = {
            n: arm.commands[n]
            for n in arm.names
            if arm.modes[n] is CommandMode.HOME and arm.joint_states[n].homing
        }

    # ------------------------------------------------------------ adoption
    def _adopt_gripper(self) -> None:
        gripper = self.backend.gripper
        if self.facts.gripper_enabled or (isinstance(gripper, Gripper) and _pwm_output_on(gripper)):
            self.enable_gripper()

    def _adopt_homings(self) -> None:
        """Take over homings an earlier command left running (``home --no-wait``)."""
        for name, speed in self.facts.homing.items():
            if self.arm.joints[name].is_enabled():
                self.arm.adopt_homing(name, speed)
        if self.facts.homing:
            self.arm.read()
            self.finish_homings()

    # ------------------------------------------------------------- queries
    @property
    def config(self) -> ArmConfig:
        """The arm configuration in use."""
        return self.backend.config

    def is_simulated(self) -> bool:
        """Whether the backend runs on simulated time."""
        return self.backend.name in ("sim", "emulated", "mock")

    def gripper_width(self) -> float:
        """Gripper width in m: the commanded one, else the last known, else the backup width."""
        gripper = self.backend.gripper
        if gripper.is_initialized and gripper.is_enabled:
            return gripper.get_position()
        if self.facts.gripper_width_m is not None:
            return self.facts.gripper_width_m
        saved = _read_saved_width(gripper.state_file)
        return saved if saved is not None else self.config.gripper.backup_init_pos

    def _require(self, name: str, *, homed: bool = False) -> None:
        """Refuse a joint that is not enabled, busy, or (``homed``) not homed."""
        joint = self.arm.joints[name]
        if not joint.is_enabled():
            raise NotEnabledError(f"{name}: not enabled; run `bioscara enable {name}` first")
        if joint.is_busy():
            raise IncorrectStateError(
                f"{name}: busy (a homing is running); wait for it in `bioscara monitor` or abort it "
                f"with `bioscara home {name} --abort`"
            )
        if homed and not joint.is_homed():
            raise NotHomedError(f"{name}: not homed; run `bioscara home {name}` first")

    # ------------------------------------------------------------ commands
    def cycle(self, dt: float) -> dict[str, bool]:
        """One control cycle: write (when active), let ``dt`` pass, read, finish homings.

        Returns:
            The homings that ended: joint name to homed.
        """
        arm = self.arm
        if arm.state is Lifecycle.ACTIVE:
            arm.write()
        self.backend.step(dt)
        if arm.state not in (Lifecycle.INACTIVE, Lifecycle.ACTIVE):
            return {}
        arm.read()
        return self.finish_homings()

    def enable(self, target: Target, *, skip_busy: bool = False) -> list[str]:
        """Enable joints (drive/hold current, stall detection, limits) and the gripper.

        Args:
            target: What to enable.
            skip_busy: Leave busy joints alone instead of refusing.

        Returns:
            The names enabled (``gripper`` included).

        Raises:
            IncorrectStateError: A joint is busy (re-enabling would stop its homing).
        """
        arm = self.arm
        joints = [n for n in target.joints if not (skip_busy and arm.joints[n].is_busy())]
        for name in joints:
            if arm.joints[name].is_busy():
                raise IncorrectStateError(
                    f"{name}: busy (a homing is running); enabling it again would stop it; abort it "
                    f"first with `bioscara home {name} --abort`"
                )
        arm.enable(joints)
        if target.gripper:
            self.enable_gripper()
        return [*joints, *([GRIPPER_NAME] if target.gripper else [])]

    def enable_gripper(self) -> None:
        """Drive the servo at its last known width (the state file's, or its own file's)."""
        gripper = self.backend.gripper
        if not gripper.is_enabled:
            self.arm.enable([GRIPPER_NAME])
            if self.facts.gripper_width_m is not None:  # the last width, not the backup one
                gripper.set_position(self.facts.gripper_width_m)
        self.facts.gripper_width_m = gripper.get_position()
        self.arm.set_gripper(gripper.get_position())

    def disable(self, target: Target) -> list[str]:
        """Disable joints (stopped, no current, freewheel) and the gripper; stops a running homing.

        Returns:
            The names disabled.
        """
        names = [*target.joints, *([GRIPPER_NAME] if target.gripper else [])]
        if target.gripper:
            self._remember_gripper()
        self.arm.disable(names)
        self.finish_homings()
        return names

    def disable_all_safely(self) -> None:
        """Disable every joint and the gripper, best effort (the console's on-error rule)."""
        arm = self.arm
        if arm.state in (Lifecycle.INACTIVE, Lifecycle.ACTIVE):
            with contextlib.suppress(JointError):
                self._remember_gripper()
                arm.disable((*arm.names, GRIPPER_NAME))

    def start_homing(self, names: Iterable[str], direction: str | None = None) -> dict[str, float]:
        """Start homing joints through the arm's home command interface; return at once.

        Args:
            names: Joints to home.
            direction: ``"+"``, ``"-"`` or ``None`` for the configured direction.

        Returns:
            Joint name to the signed homing speed used.

        Raises:
            NotEnabledError: A joint is not enabled.
            IncorrectStateError: A joint is busy.
        """
        arm = self.arm
        speeds = {}
        for name in names:
            self._require(name)
            speeds[name] = homing_speed(self.config.joint(name), direction)
        for name, speed in speeds.items():
            if arm.modes[name] is not CommandMode.HOME:
                if arm.modes[name] is not CommandMode.NONE:
                    arm.release(name)
                arm.claim(name, CommandMode.HOME)
            arm.set_command(name, speed)
        if speeds:
            arm.write()
            arm.read()
        return speeds

    def finish_homings(self) -> dict[str, bool]:
        """Release the home interface of joints whose homing ended; name to homed."""
        arm = self.arm
        done = {}
        for name in arm.names:
            if arm.modes[name] is CommandMode.HOME and not arm.joint_states[name].homing:
                arm.release(name)
                done[name] = arm.joint_states[name].homed
        return done

    def homing(self) -> list[str]:
        """Joints homing now (started by the console)."""
        return [n for n in self.arm.names if self.arm.joint_states[n].homing]

    def abort_homing(self, names: Iterable[str]) -> list[str]:
        """Abort homings (home command 0; a STOP for a blocking command the console did not start).

        Returns:
            The joints whose homing was aborted.
        """
        arm = self.arm
        ours, foreign = [], []
        for name in names:
            if arm.joint_states[name].homing:
                ours.append(name)
            elif arm.joints[name].is_busy():
                foreign.append(name)
        for name in ours:
            arm.set_command(name, 0.0)
        if ours:
            arm.write()
        for name in foreign:
            arm.joints[name].stop()
        if ours or foreign:
            arm.read()
            self.finish_homings()
        return [n for n in arm.names if n in ours or n in foreign]

    def home(
        self,
        names: Iterable[str],
        direction: str | None = None,
        timeout_s: float | None = None,
        wait: bool = True,
    ) -> dict[str, float]:
        """Home joints and (``wait``) cycle the arm until every homing ended.

        Returns:
            Joint name to the signed homing speed used.

        Raises:
            NotEnabledError, IncorrectStateError: As :meth:`start_homing`.
            ArmStateError: The timeout passed (the homings are aborted first).
            NotHomedError: A homing ended without the joint homed.
        """
        speeds = self.start_homing(names, direction)
        if not wait:
            return speeds
        if timeout_s is None:
            timeout_s = max(
                (homing_timeout_s(self.config.joint(n), s) for n, s in speeds.items()), default=0.0
            )
        clock = self.backend.clock
        start = clock.now()
        while any(self.arm.joint_states[n].homing for n in speeds):
            if clock.now() - start > timeout_s:
                self.abort_homing(speeds)
                raise ArmStateError(
                    f"homing {', '.join(speeds)} did not finish within {timeout_s:g} s; aborted"
                )
            self.cycle(CYCLE_S)
        failed = [n for n in speeds if not self.arm.joint_states[n].homed]
        if failed:
            raise NotHomedError(f"homing failed for {', '.join(failed)} (aborted or no end stop found)")
        return speeds

    def move(self, name: str, value: float, timeout_s: float | None = None) -> float:
        """Move a joint to ``value`` (rad or m) in position mode and wait until it is there.

        Returns:
            The measured position at the end, rad or m.

        Raises:
            InvalidArgumentError: Unknown joint, or ``value`` outside the limits.
            NotEnabledError, NotHomedError, IncorrectStateError: The joint
                cannot move.
            ArmStateError: Not there within the timeout.
        """
        cfg = joint_config(self.config, name)
        unit = joint_unit(cfg.joint_type)
        if not (math.isfinite(value) and cfg.min <= value <= cfg.max):
            raise InvalidArgumentError(
                f"{name}: {value:g} {unit} is outside the joint limits [{cfg.min:g}, {cfg.max:g}] {unit}"
            )
        self._require(name, homed=True)
        arm = self.arm
        if timeout_s is None:
            timeout_s = move_timeout_s(cfg, value - arm.joint_states[name].position)
        tolerance = MOVE_TOLERANCE[cfg.joint_type]
        arm.claim(name, CommandMode.POSITION)
        arm.set_command(name, value)
        clock = self.backend.clock
        start = clock.now()
        while True:
            self.cycle(CYCLE_S)
            state = arm.joint_states[name]
            if abs(state.position - value) <= tolerance and abs(state.velocity) <= tolerance / 10:
                break
            if clock.now() - start > timeout_s:
                raise ArmStateError(
                    f"{name}: not at {value:g} {unit} within {timeout_s:g} s (at {state.position:.4f} {unit})"
                )
        arm.release(name)
        return arm.joint_states[name].position

    def set_gripper(self, width_m: float) -> float:
        """Drive the gripper to ``width_m`` (enabling it if needed) and let the servo travel.

        Raises:
            InvalidArgumentError: The width is outside the gripper's limits.
        """
        g = self.config.gripper
        if not (math.isfinite(width_m) and g.min <= width_m <= g.max):
            raise InvalidArgumentError(
                f"gripper: width {width_m:g} m is outside the limits [{g.min:g}, {g.max:g}] m"
            )
        self.enable_gripper()
        gripper = self.backend.gripper
        gripper.set_position(width_m)
        self.arm.set_gripper(width_m)
        self.facts.gripper_width_m = width_m
        for _ in range(math.ceil(GRIPPER_SETTLE_S / CYCLE_S)):
            self.cycle(CYCLE_S)
        return gripper.get_position()

    def ping(self) -> list[tuple[str, str, str, Flag | None]]:
        """PING every joint separately (and set up the gripper).

        Returns:
            Per device: name, address (``"-"`` without a bus), ``"OK"`` or the
            error, flags (``None`` if no answer).
        """
        results: list[tuple[str, str, str, Flag | None]] = []
        on_bus = self.backend.name in ("emulated", "i2c")
        for cfg in self.config.joints:
            joint = self.arm.joints[cfg.name]
            address = f"0x{cfg.address:02X}" if on_bus else "-"
            was_open = joint.initialized
            try:
                if was_open:
                    joint.get_flags()
                else:
                    joint.init()
                results.append((cfg.name, address, "OK", joint.flags))
            except JointError as e:
                results.append((cfg.name, address, str(e), None))
            finally:
                if not was_open:
                    joint.deinit()
        gripper = self.backend.gripper
        try:
            if not gripper.is_initialized:
                gripper.init()
                gripper.deinit()
            results.append((GRIPPER_NAME, "-", "OK", None))
        except JointError as e:
            results.append((GRIPPER_NAME, "-", str(e), None))
        return results


# ----------------------------------------------------------------- output
def make_console() -> Console:
    """A console for command output: at least 120 columns when not a terminal (pipes, logs)."""
    con = Console(highlight=False)
    if not con.is_terminal:
        con = Console(highlight=False, width=max(120, con.width))
    return con


def _lifecycle_line(session: Session) -> str:
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
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    for title, justify in (
        ("joint", "left"),
        ("position", "right"),
        ("velocity", "right"),
        ("enabled", "left"),
        ("homed", "left"),
        ("flags", "left"),
        ("bus tx", "right"),
        ("bus errors", "right"),
    ):
        table.add_column(title, justify=justify)  # type: ignore[arg-type]
    for cfg in session.config.joints:
        st = arm.joint_states[cfg.name]
        joint = arm.joints[cfg.name]
        unit = joint_unit(cfg.joint_type)
        homed = "homing…" if st.homing else ("yes" if st.homed else "no")
        s = stats.get(cfg.name)
        table.add_row(
            cfg.name,
            format_position(st.position if st.homed else None, unit),
            format_velocity(st.velocity, unit),
            "yes" if joint.is_enabled() else "no",
            homed,
            flags_text(st.flags),
            "-" if s is None else str(s.total_transactions),
            "-" if s is None else str(s.total_errors),
        )
    gripper = session.backend.gripper
    table.add_row(
        GRIPPER_NAME,
        f"{session.gripper_width():.4f} m",
        "",
        "yes" if gripper.is_enabled else "no",
        "",
        "",
        "",
        "",
    )
    return table


# ---------------------------------------------------------------- commands
def _joint_names(session: Session, name: str | None) -> tuple[str, ...]:
    target = resolve_target(session.config, name)
    if not target.joints:
        raise InvalidArgumentError(f"{name}: the gripper has no homing; name a joint or a group of joints")
    return target.joints


def cmd_status(args: argparse.Namespace) -> int:
    """``bioscara status``."""
    con = make_console()
    with Session(ConsoleOptions.from_args(args)) as session:
        con.print(_lifecycle_line(session))
        con.print(status_table(session))
    return 0


def cmd_ping(args: argparse.Namespace) -> int:
    """``bioscara ping``: exit 1 if any joint did not answer."""
    con = make_console()
    with Session(ConsoleOptions.from_args(args), configure=False) as session:
        results = session.ping()
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    for title in ("device", "address", "reply", "flags"):
        table.add_column(title)
    for name, address, reply, flags in results:
        table.add_row(name, address, reply, "" if flags is None else flags_text(flags))
    con.print(table)
    missing = [r[0] for r in results if r[2] != "OK"]
    if missing:
        con.print(f"no answer from {', '.join(missing)}")
        return 1
    con.print(f"all {len(results)} devices answered")
    return 0


def cmd_enable(args: argparse.Namespace) -> int:
    """``bioscara enable [JOINT|GROUP]``."""
    con = make_console()
    with Session(ConsoleOptions.from_args(args)) as session:
        names = session.enable(resolve_target(session.config, args.target))
        con.print(f"enabled {', '.join(names)}; holding still · arm {session.arm.state.value}")
    return 0


def cmd_disable(args: argparse.Namespace) -> int:
    """``bioscara disable [JOINT|GROUP]``."""
    con = make_console()
    with Session(ConsoleOptions.from_args(args)) as session:
        names = session.disable(resolve_target(session.config, args.target))
        con.print(f"disabled {', '.join(names)} · arm {session.arm.state.value}")
    return 0


def cmd_home(args: argparse.Namespace) -> int:
    """``bioscara home [JOINT|GROUP] [--direction +|-] [--abort] [--no-wait]``."""
    con = make_console()
    options = ConsoleOptions.from_args(args)
    if args.no_wait and options.state is None:
        raise ConsoleUsageError("--no-wait needs --state FILE, so that a later command can finish the homing")
    with Session(options) as session:
        arm = session.arm
        if args.abort:
            aborted = session.abort_homing(_joint_names(session, args.target))
            con.print(
                f"aborted homing of {', '.join(aborted)} (not homed)" if aborted else "no homing is running"
            )
            return 0
        names = _joint_names(session, args.target)
        if args.target is None:
            names = tuple(n for n in names if not arm.joints[n].is_homed())
            if not names:
                con.print("every joint is homed; name a joint to home it again")
                return 0
        clock = session.backend.clock
        start = clock.now()
        label = f"homing {', '.join(names)}"
        status = con.status(label + "…") if con.is_terminal else contextlib.nullcontext()
        with status:
            speeds = session.home(names, args.direction, args.timeout, wait=not args.no_wait)
        for name, speed in speeds.items():
            end = "max" if speed > 0 else "min"
            unit = joint_unit(session.config.joint(name).joint_type)
            if args.no_wait:
                con.print(f"{name} homing toward {end} at {abs(speed):g} {unit}/s (left running)")
            else:
                con.print(f"{name} homed at {end}: {arm.joint_states[name].position:+.4f} {unit}")
        if not args.no_wait:
            con.print(f"{label} took {clock.now() - start:.2f} s")
    return 0


def cmd_move(args: argparse.Namespace) -> int:
    """``bioscara move JOINT VALUE``."""
    con = make_console()
    with Session(ConsoleOptions.from_args(args)) as session:
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
    with Session(ConsoleOptions.from_args(args)) as session:
        width = session.set_gripper(args.width)
        con.print(f"gripper at {width:.4f} m (servo driven)")
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    """``bioscara monitor``."""
    from bioscara_gym.console.dashboard import MonitorApp, key_source, run_monitor

    if args.rate <= 0 or not math.isfinite(args.rate):
        raise ConsoleUsageError(f"--rate {args.rate:g} must be a positive number of refreshes per second")
    if args.duration is not None and not args.duration > 0:
        raise ConsoleUsageError(f"--duration {args.duration:g} must be positive")
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


# ------------------------------------------------------------------ parser
def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--backend", choices=BACKENDS, default="emulated", help="arm backend (default: emulated)"
    )
    parser.add_argument(
        "--config", type=Path, metavar="FILE", help="arm configuration YAML (default: the packaged one)"
    )
    parser.add_argument(
        "--bus", type=int, metavar="N", help="I2C bus number for --backend i2c (default: the config's)"
    )
    parser.add_argument(
        "--state",
        type=Path,
        metavar="FILE",
        help="keep the simulated arm's state in FILE between commands (emulated, sim)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    """Add the operator subcommands: status, ping, enable, disable, home, move, gripper, monitor."""
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
        "--timeout", type=float, metavar="S", help="seconds (default: the whole range at homing speed)"
    )
    _common(p)
    p.set_defaults(func=cmd_home)

    p = sub.add_parser("move", help="move a homed, enabled joint to a position and wait")
    p.add_argument("joint", metavar="JOINT")
    p.add_argument("value", type=float, metavar="VALUE", help="rad (m for the prismatic j2)")
    p.add_argument("--timeout", type=float, metavar="S", help="seconds (default: from the joint's limits)")
    _common(p)
    p.set_defaults(func=cmd_move)

    p = sub.add_parser("gripper", help="set the gripper width (enables the servo)")
    p.add_argument("width", type=float, metavar="WIDTH", help="m")
    _common(p)
    p.set_defaults(func=cmd_gripper)

    p = sub.add_parser("monitor", help="live dashboard; keys e/d enable/disable, h home, a abort, q quit")
    p.add_argument(
        "--rate", type=float, default=10.0, metavar="HZ", help="refreshes per second (default: 10)"
    )
    p.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (needed without a terminal)"
    )
    _common(p)
    p.set_defaults(func=cmd_monitor)
