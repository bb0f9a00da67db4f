"""One console command's hold on the arm: backend, :class:`~bioscara_gym.hardware.arm.Arm`, state file.

A command opens a :class:`Session`, does its one thing and closes it.
Opening first checks the options and the request's arguments against the
configuration (``check``: joint names, positions against the limits,
widths), so a request refused for its arguments sends nothing and writes
nothing (no state file, no lock file, no bus trace); then it builds the
backend, restores the ``--state`` file, configures the arm and adopts
what earlier commands left: joints enabled by an earlier command are
adopted as they are (:meth:`~bioscara_gym.hardware.arm.Arm.attach`: the arm
is ``active`` when any joint or the gripper is enabled, without re-sending
SETUP, which would stop a running homing), and a homing left running is
handed back to the arm (:meth:`~bioscara_gym.hardware.arm.Arm.adopt_homing`).
Closing after an error (Ctrl-C included) runs the arm layer's on-error
transition, then writes the state file and releases the connections,
leaving enabled joints enabled. The state file is locked from before it is read until after it
is written (:func:`~bioscara_gym.console.state.lock_state`), so a second
command on the same file is refused instead of losing an update. A request
refused later, for the state the arm is in (a joint not enabled, not homed,
busy), writes the state file only if it was there before.

Homing and moving are the Arm's (:meth:`~bioscara_gym.hardware.arm.Arm.home`,
:meth:`~bioscara_gym.hardware.arm.Arm.move_to`); the session adds the
console's preconditions, whose errors tell the operator which command to
run first.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable, Iterable
from types import TracebackType

from bioscara_gym.console.state import HostFacts, load_state, lock_state, save_state
from bioscara_gym.console.targets import ConsoleOptions, Target, check_gripper_width
from bioscara_gym.errors import is_refusal, refusal
from bioscara_gym.fsutil import LockFile, read_json
from bioscara_gym.hardware.arm import Arm, Lifecycle
from bioscara_gym.hardware.backends import Backend, make_backend
from bioscara_gym.hardware.config import GRIPPER_NAME, ArmConfig
from bioscara_gym.hardware.errors import (
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
)
from bioscara_gym.hardware.gripper import Gripper, read_saved_width
from bioscara_gym.hardware.recording import note_signal
from bioscara_gym.hardware.registers import BLOCKING_PICKUP_S
from bioscara_gym.stop_signals import held

#: Period of the arm's read/write cycle while a command waits, s (25 Hz).
CYCLE_S = 0.04
#: How long ``gripper WIDTH`` lets the servo travel, s.
GRIPPER_SETTLE_S = 0.3


class Session:
    """One command's hold on the arm: backend, arm layer, state file.

    Use as a context manager (see the module docstring for what entering
    and leaving do).

    Args:
        options: The common command-line options.
        configure: Whether to configure the arm on entering (``False`` for ``ping``).
        check: The request's own check of its arguments against the configuration
            (:mod:`~bioscara_gym.console.targets`), run before the state file is
            locked or the backend built; what it raises refuses the request.
    """

    def __init__(
        self,
        options: ConsoleOptions,
        configure: bool = True,
        check: Callable[[ArmConfig], object] | None = None,
    ) -> None:
        """Remember the options; nothing is opened before ``__enter__``."""
        self.options = options
        self._configure = configure
        self._check = check
        self.backend: Backend
        self.arm: Arm
        self.facts = HostFacts()
        self._opened = False
        self._attached = False
        self._save = False
        self._state_existed = False
        self._lock: LockFile | None = None

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

    # ------------------------------------------------------------- opening
    def _open(self) -> None:
        """Check the options and arguments, build the backend, restore the state, configure and adopt."""
        self.options.check()
        config = self.options.arm_config()
        if self._check is not None:
            self._check(config)  # refused here: no lock, no state file, no byte on the bus
        self._lock_state()
        self._build_backend(config)
        self._restore_state()
        if self._configure:
            self._configure_arm()
            self._adopt_gripper()
            self._adopt_homings()

    def _lock_state(self) -> None:
        """Hold the state file, if any, until :meth:`_close` has written it (a second command is refused)."""
        if self.options.state is not None:
            self._lock = lock_state(self.options.state)

    def _build_backend(self, config: ArmConfig) -> None:
        """Make the backend and the arm of the configuration (``--bus`` applied)."""
        self.backend = make_backend(self.options.backend, config, **self._backend_options())
        self.arm = Arm(self.backend)  # sends nothing before configure()
        self._opened = True

    def _backend_options(self) -> dict[str, object]:
        """The options' backend options, and ``--record`` with the state file this command starts from."""
        options = dict(self.options.backend_options)
        if self.options.backend == "sitl":
            options.setdefault("firmware", self.options.firmware)  # None: $BIOSCARA_FIRMWARE
        record, path = self.options.record, self.options.state
        if record is not None:
            context: dict[str, object] = {}
            if path is not None and path.exists():
                with contextlib.suppress(OSError, ValueError):  # the restore says what is wrong
                    context["state"] = read_json(path)
            options["record"] = dataclasses.replace(record, context=context)
        return options

    def _restore_state(self) -> None:
        """Restore the simulated arm, host facts and bus counters from the state file, if any."""
        path = self.options.state
        if path is not None:
            if path.exists():
                self._state_existed = True
                self.facts = load_state(path, self.backend)
            self._save = True  # not before: a file that cannot be loaded is kept as it is
        for name, stats in self.backend.comm_stats().items():
            for key, value in self.facts.stats.get(name, {}).items():
                setattr(stats, key, value)

    def _configure_arm(self) -> None:
        """Configure the arm and go active over the devices an earlier command left enabled."""
        self.arm.configure()
        self._attached = True
        self.arm.attach()

    def _adopt_gripper(self) -> None:
        """Drive the gripper again if an earlier command left it driven."""
        gripper = self.backend.gripper
        if self.facts.gripper_enabled or (isinstance(gripper, Gripper) and gripper.output_enabled):
            self.enable_gripper()

    def _adopt_homings(self) -> None:
        """Take over homings an earlier command left running (``home --no-wait``)."""
        for name, command in self.facts.homing.items():
            if self.arm.joints[name].is_enabled():
                self.arm.adopt_homing(name, command)
        if self.facts.homing:
            self.arm.read()
            self.arm.finish_homings()

    # ------------------------------------------------------------- closing
    def _close(self, exc: BaseException | None) -> None:
        """After an error the on-error transition; always save the state and release.

        A request refused for its arguments (:class:`InvalidArgumentError`:
        an unknown joint, a position outside the limits) or for the state the
        arm is in (:meth:`require`: a joint busy homing, not enabled, not
        homed) was refused before any byte was sent, so it leaves the arm as
        it was: only something that went wrong on the arm makes it safe.
        """
        if not self._opened:
            self._unlock()
            return
        refused = exc is not None and is_refusal(exc)
        failed = exc is not None and not refused
        # A stop signal now does not cut the safe stop or the state's write short: the command ends as
        # it would have (seen: exit 143 after enable's result line, the state file not written).
        with held():
            try:
                if failed:
                    note_signal(self.backend, exc)  # a Ctrl-C: where, in the bus trace, for its replay
                    self._on_error()
                else:
                    self._let_blocking_commands_start()
            finally:
                try:
                    self._save_state(failed=failed, refused=refused)
                finally:
                    try:
                        self._release()
                    finally:
                        self._unlock()

    def _on_error(self) -> None:
        """The arm layer's on-error transition: every joint and the gripper disabled."""
        self._remember_gripper()
        self.arm.recover()

    def _save_state(self, failed: bool, refused: bool = False) -> None:
        """Write the state file, if any; a write error is raised only when nothing else failed.

        A refused request (nothing sent that changes the arm) creates no state file.
        """
        if not self._save or self.options.state is None:
            return
        if refused and not self._state_existed:
            return
        self._collect_facts(failed)
        try:
            save_state(self.options.state, self.backend, self.facts)
        except OSError:
            if not failed:
                raise

    def _collect_facts(self, failed: bool) -> None:
        """Update the host facts: bus counters, gripper, homings left running."""
        self.facts.stats = {n: dataclasses.asdict(s) for n, s in self.backend.comm_stats().items()}
        if failed:  # the on-error transition disabled everything
            self.facts.gripper_enabled = False
            self.facts.homing = {}
            return
        if not self._attached:
            return  # never configured (ping): what was loaded still holds
        self._remember_gripper()
        self.facts.gripper_enabled = self.backend.gripper.is_enabled
        self.facts.homing = {n: self.arm.commands[n] for n in self.arm.homing_names()}

    def _remember_gripper(self) -> None:
        """Keep the driven gripper's width (the servo has no feedback)."""
        gripper = self.backend.gripper
        if gripper.is_initialized and gripper.is_enabled:
            self.facts.gripper_width_m = gripper.get_position()

    def _let_blocking_commands_start(self) -> None:
        """Before leaving, let the firmware pick up a homing just started (``home --no-wait``).

        The next command's first transaction to that joint would cancel a
        blocking command the firmware's main loop has not taken yet, leaving
        the joint BUSY until a STOP (docs/firmware.md).
        """
        if any(joint.picking_up for joint in self.arm.joints.values()):
            self.backend.step(BLOCKING_PICKUP_S)

    def _release(self) -> None:
        """Release the connections; enabled joints and an enabled gripper stay so."""
        for joint in self.arm.joints.values():
            joint.deinit()
        gripper = self.backend.gripper
        if gripper.is_initialized and not gripper.is_enabled:
            gripper.deinit()
        self.backend.close()

    def _unlock(self) -> None:
        """Let the next command have the state file."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

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
        saved = read_saved_width(gripper.state_file)
        return saved if saved is not None else self.config.gripper.backup_init_pos

    def require(self, name: str, *, homed: bool = False) -> None:
        """Refuse a joint of an arm that is not enabled, a busy joint, or (``homed``) an unhomed one.

        A joint the arm disabled at the end of its homing (the seed's
        stop_homing) is fine: claiming its command interface enables it again.

        Nothing is sent: the refusal leaves the arm as it was (homings keep
        running, nothing is disabled), so the message's advice holds.

        Raises:
            NotEnabledError, IncorrectStateError, NotHomedError: The joint
                cannot take the command; the message names the command to run first.
        """
        joint = self.arm.joints[name]
        if self.arm.state is not Lifecycle.ACTIVE:
            raise refusal(NotEnabledError(f"{name}: not enabled; run `bioscara enable {name}` first"))
        if joint.is_busy():
            raise refusal(
                IncorrectStateError(
                    f"{name}: busy (a homing is running); wait for it in `bioscara monitor` or abort it "
                    f"with `bioscara home {name} --abort`"
                )
            )
        if homed and not joint.is_homed():
            raise refusal(NotHomedError(f"{name}: not homed; run `bioscara home {name}` first"))

    # ---------------------------------------------------------- operations
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
        return arm.finish_homings()

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
        joints = [n for n in target.joints if not (skip_busy and self.arm.joints[n].is_busy())]
        for name in joints:
            if self.arm.joints[name].is_busy():  # refused before any byte: the homings go on
                raise refusal(
                    IncorrectStateError(
                        f"{name}: busy (a homing is running); enabling it again would stop it; abort it "
                        f"first with `bioscara home {name} --abort`"
                    )
                )
        self.arm.enable(joints)
        if target.gripper:
            self.enable_gripper()
        return Target(tuple(joints), target.gripper).names

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
        if target.gripper:
            self._remember_gripper()
        self.arm.disable(target.names)
        self.arm.finish_homings()
        return target.names

    def disable_all_safely(self) -> None:
        """Disable every joint and the gripper, best effort (the console's on-error rule)."""
        if self.arm.state in (Lifecycle.INACTIVE, Lifecycle.ACTIVE):
            with contextlib.suppress(JointError):
                self._remember_gripper()
                self.arm.disable((*self.arm.names, GRIPPER_NAME))

    def start_homing(self, names: Iterable[str], direction: int | None = None) -> dict[str, float]:
        """Start homing enabled, idle joints (:meth:`Arm.start_homing`); return at once.

        Returns:
            Joint name to the signed homing speed used; empty for no names,
            whatever the arm's state.
        """
        names = tuple(names)
        for name in names:
            self.require(name)
        return self.arm.start_homing(names, direction) if names else {}

    def home(
        self, names: Iterable[str], direction: int | None = None, timeout_s: float | None = None
    ) -> dict[str, float]:
        """Home enabled, idle joints, homed or not, and wait (:meth:`Arm.home`).

        Returns:
            Joint name to the signed homing speed used.
        """
        names = tuple(names)
        for name in names:
            self.require(name)
        return self.arm.home(names, direction, period_s=CYCLE_S, timeout_s=timeout_s, only_unhomed=False)

    def move(self, name: str, value: float, timeout_s: float | None = None) -> float:
        """Move an enabled, idle, homed joint to ``value`` and wait (:meth:`Arm.move_to`).

        Returns:
            The measured position at the end, rad or m.
        """
        self.arm.check_targets({name: value})  # unknown joint, outside the limits: nothing sent
        self.require(name, homed=True)
        return self.arm.move_to({name: value}, period_s=CYCLE_S, timeout_s=timeout_s)[name]

    def set_gripper(self, width_m: float) -> float:
        """Drive the gripper to ``width_m`` (enabling it if needed) and let the servo travel.

        Raises:
            InvalidArgumentError: The width is outside the gripper's limits.
        """
        check_gripper_width(self.config, width_m)
        try:  # the pulse too, before the servo is driven (seen: left enabled)
            self.backend.gripper.check_width(width_m)
        except InvalidArgumentError as e:
            problem = f"gripper: width {width_m:g} m: {e}; check the configured limits"
            raise InvalidArgumentError(problem) from e
        self.enable_gripper()
        self.backend.gripper.set_position(width_m)
        self.arm.set_gripper(width_m)
        self.facts.gripper_width_m = width_m
        for _ in range(math.ceil(GRIPPER_SETTLE_S / CYCLE_S)):
            self.cycle(CYCLE_S)
        return self.backend.gripper.get_position()
