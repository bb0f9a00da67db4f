"""The arm layer: what ros2_control's hardware interface did on the original stack.

Lifecycle (docs/arm.md, "The arm layer")::

    UNCONFIGURED --configure--> INACTIVE --activate--> ACTIVE
    ACTIVE --deactivate--> INACTIVE --cleanup--> UNCONFIGURED
    any --shutdown--> FINALIZED;  an error in a transition --> UNCONFIGURED

:meth:`Arm.enable` and :meth:`Arm.disable` do the same per device (a joint
name or ``"gripper"``): the arm is ACTIVE while any device is enabled.
:meth:`Arm.attach` goes ACTIVE over devices an earlier process enabled
without sending anything that stops them, and :meth:`Arm.adopt_homing` takes
over a homing such a process left running.

Every joint has three command interfaces, position, velocity and home, of
which at most one is active, and three state values read in the order
position, velocity, home. :meth:`Arm.read` and :meth:`Arm.write` are one
control cycle's I/O; a failure in either deactivates the arm.
"""

from __future__ import annotations

import contextlib
import math
import numbers
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any, Protocol

from bioscara_gym.hardware.backends import Backend
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.config import GRIPPER_NAME, ArmConfig, JointConfig
from bioscara_gym.hardware.errors import (
    ArmStateError,
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotHomedError,
)
from bioscara_gym.hardware.field_watch import FieldLostError, FieldWatch
from bioscara_gym.hardware.registers import DEADMAN_S, TICK_S, Flag, Reg
from bioscara_gym.hardware.safety import (
    REST_RPM,
    DeadmanGuard,
    SafeStopReport,
    final_state,
    safe_stop,
    wait_for_rest,
)
from bioscara_gym.hardware.stats import CommStats
from bioscara_gym.hardware.transmission import velocity_to_rpm

#: The firmware's deadman stops a joint after 50 ms of silence: 20 Hz is the floor of a
#: control loop's rate.
MIN_CONTROL_FREQ = 20.0
#: The firmware runs its loop (stall detection, deadman) once per 10 ms tick, and
#: one cycle's bus traffic takes milliseconds: 100 Hz is the ceiling.
MAX_CONTROL_FREQ = 1.0 / TICK_S


def _as_given(number: float) -> str:
    """``number`` in the fewest significant digits that read back as it (``1e+09``, ``100.0000001``).

    Seen: ``--rate 100.0000001`` was refused as "--rate 100 Hz must be within 20-100 Hz".
    """
    for digits in range(6, 18):  # 6: what :g gives
        text = f"{number:.{digits}g}"
        if float(text) == number:
            return text
    return repr(number)  # NaN


def check_control_freq(control_freq: object, name: str = "control_freq") -> float:
    """``control_freq`` as a float, if it is a rate the arm can be commanded at.

    Raises:
        ValueError: Not a number, or outside ``MIN_CONTROL_FREQ``-``MAX_CONTROL_FREQ``; the
            message names ``name``.
    """
    if isinstance(control_freq, bool) or not isinstance(control_freq, numbers.Real):
        raise ValueError(f"{name} must be a rate in Hz, got {control_freq!r}")
    if not MIN_CONTROL_FREQ <= control_freq <= MAX_CONTROL_FREQ:  # NaN fails both
        why = (
            "the joint firmware's loop runs every 10 ms"
            if control_freq > MAX_CONTROL_FREQ
            else "the joints' 50 ms deadman would stop them between commands"
        )
        raise ValueError(
            f"{name} {_as_given(control_freq)} Hz must be within "
            f"{MIN_CONTROL_FREQ:g}-{MAX_CONTROL_FREQ:g} Hz: {why}"
        )
    return float(control_freq)


class PhaseObserver(Protocol):
    """Told about each step of :meth:`Arm.bring_up` and :meth:`Arm.shut_down` (a display, a run log)."""

    def starting(self, phase: str, detail: str) -> None:
        """A step starts (it may take seconds: a homing)."""
        ...

    def done(self, phase: str, detail: str) -> None:
        """A step is done."""
        ...


class _Unobserved:
    """A :class:`PhaseObserver` that is told nothing."""

    def starting(self, phase: str, detail: str) -> None:
        """Nothing."""

    def done(self, phase: str, detail: str) -> None:
        """Nothing."""


class Lifecycle(Enum):
    """Lifecycle states of the arm (ros2_control's managed-node states)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"


class CommandMode(Enum):
    """The command interface a joint is claimed for."""

    NONE = "none"
    POSITION = "position"
    VELOCITY = "velocity"
    HOME = "home"


@dataclass
class JointState:
    """State interfaces of one joint, as of the last :meth:`Arm.read`.

    Attributes:
        position: rad or m (0.0 while not homed).
        velocity: rad/s or m/s.
        homed: Whether the joint reports homed.
        homing: Whether a homing started by the arm is running.
        flags: Flags of the joint's last transaction.
    """

    position: float = 0.0
    velocity: float = 0.0
    homed: bool = False
    homing: bool = False
    flags: Flag = Flag.NOT_HOMED | Flag.NOT_ENABLED


def check_joint_targets(config: ArmConfig, targets: Mapping[str, float]) -> None:
    """Refuse unknown joints and positions not finite or outside the joint's limits.

    Needs only the configuration, so a command can refuse its arguments
    before it opens the bus (the console's ``move``).

    Raises:
        InvalidArgumentError: Naming the joint, the value and the limits.
    """
    for name, value in targets.items():
        if name not in config.names:
            raise InvalidArgumentError(f"unknown joint {name!r}; known joints: {', '.join(config.names)}")
        cfg = config.joint(name)
        if not (math.isfinite(value) and cfg.min <= value <= cfg.max):
            unit = _unit(config, name)
            raise InvalidArgumentError(
                f"{name}: {value:g} {unit} is outside the joint limits [{cfg.min:g}, {cfg.max:g}] {unit}"
            )


def _unit(config: ArmConfig, name: str) -> str:
    """``m`` for the prismatic joint, ``rad`` for the others."""
    return "m" if config.joint(name).joint_type == "prismatic" else "rad"


class Arm:
    """Lifecycle, command modes and homing over a backend's joints and gripper.

    Args:
        backend: The joints, gripper and clock to drive.
        config: Configuration (the backend's by default).
    """

    def __init__(self, backend: Backend, config: ArmConfig | None = None) -> None:
        """Wrap ``backend``; nothing is sent before :meth:`configure`."""
        self.backend = backend
        self.config = config or backend.config
        self.joints = backend.joints
        self.gripper = backend.gripper
        self.names = tuple(self.joints)
        self.state = Lifecycle.UNCONFIGURED
        self.modes: dict[str, CommandMode] = dict.fromkeys(self.names, CommandMode.NONE)
        self.commands: dict[str, float] = dict.fromkeys(self.names, 0.0)
        self.joint_states: dict[str, JointState] = {n: JointState() for n in self.names}
        self.gripper_command = self.config.gripper.backup_init_pos
        #: Bus time of the last :meth:`cycle` (its write and its read, on the
        #: backend's clock): how old a reading is, at most, when the next
        #: cycle's command reaches the joint.
        self.cycle_bus_s = 0.0
        self._homing: set[str] = set()
        #: Each stepper joint's field watch (docs/arm.md, "The field watch"), and the
        #: position or velocity command the last write sent it.
        self.watches: dict[str, FieldWatch] = {}
        for name in self.names:
            if self.joints[name].has_field:
                j = self.config.joint(name)
                unit = f"{self._unit(name)}/s"
                self.watches[name] = FieldWatch(name, j.reduction, j.max_velocity, j.max_acceleration, unit)
        self._sent: dict[str, float] = {}

    # ------------------------------------------------------------ lifecycle
    def _require(self, *states: Lifecycle, action: str) -> None:
        if self.state not in states:
            allowed = " or ".join(s.value for s in states)
            raise ArmStateError(f"cannot {action} while {self.state.value}; the arm must be {allowed}")

    def _transition(self, body: Callable[[], None]) -> None:
        """Run a transition; on failure fall back to UNCONFIGURED and re-raise."""
        try:
            body()
        except BaseException:
            self._on_error()
            raise

    def configure(self) -> None:
        """Connect and ping every joint (restoring homing offsets) and the gripper.

        A joint that does not answer does not stop the others from being
        connected: the failed configure then disables every joint that did
        answer (an earlier process may have left them enabled; seen: with
        j1 unpowered, ``bioscara disable`` left j2-j4 holding torque), and a
        configure cut short (Ctrl-C) connects the rest before it raises, for
        the same cleanup. It reads their speeds first, so one left turning
        is braked to rest before its current is cut, as :meth:`disable`
        does, and it switches off a gripper servo left driven
        (:meth:`~bioscara_gym.hardware.gripper.BaseGripper.release`).

        Raises:
            CommError: A joint did not answer (the first; the arm stays
                unconfigured, the joints that answered disabled).
        """
        self._require(Lifecycle.UNCONFIGURED, action="configure")

        def body() -> None:
            first: JointError | None = None
            try:
                for device in (*self.joints.values(), self.gripper):
                    try:
                        device.init()
                    except JointError as e:
                        first = first or e
            except BaseException:  # cut short (Ctrl-C): the rest too, so that the cleanup reaches them
                self._connect_the_rest()
                self._read_speeds()
                raise
            if first is not None:
                self._read_speeds()  # for the cleanup: brake what an earlier process left turning
                raise first
            self.state = Lifecycle.INACTIVE
            self.read()

        self._transition(body)

    def activate(self) -> None:
        """Enable the joints, stall detection and limits; hold the measured position.

        The same as :meth:`enable` of every joint and the gripper. Command set
        points are set to the measured state, and no command mode is active,
        so nothing moves.

        Raises:
            ArmStateError: The arm is not inactive.
            JointError: A joint could not be enabled (the arm falls back to
                unconfigured).
        """
        self._require(Lifecycle.INACTIVE, action="activate")
        self.enable((*self.names, GRIPPER_NAME))

    def enable(self, names: Iterable[str]) -> None:
        """Enable joints (and ``"gripper"``) as :meth:`activate` does; hold them still.

        Each joint gets its configured drive and hold current (percent), stall
        detection, max velocity and max acceleration; the gripper is driven
        at its saved width. An inactive arm becomes active (the devices not
        named stay disabled). The named joints' command interfaces are
        released and their set points set to the measured position, so
        nothing moves; a joint already enabled is enabled again, which
        clears a stall and stops whatever it was doing.

        Args:
            names: Joint names and ``"gripper"``; none does nothing.

        Raises:
            ArmStateError: The arm is not configured (inactive or active), or
                a named joint is homing (abort it with a home command of 0
                first: enabling would stop it).
            InvalidArgumentError: An unknown name.
            JointError: A device could not be enabled; the arm falls back to
                unconfigured, every device disabled.
        """
        self._require(Lifecycle.INACTIVE, Lifecycle.ACTIVE, action="enable")
        joints, gripper = self._split(names)
        for name in joints:
            self._refuse_setup_while_busy(name, "enabling")
        if not joints and not gripper:
            return
        was_active = self.state is Lifecycle.ACTIVE

        def body() -> None:
            for name in joints:
                self._enable_joint(name)
            if gripper:
                self.gripper.enable()
                self.gripper_command = self.gripper.get_position()
            self.state = Lifecycle.ACTIVE
            self.read()
            if was_active:
                for name in joints:
                    self.modes[name] = CommandMode.NONE
                    self.commands[name] = self.joint_states[name].position
            else:
                self._hold_measured()

        self._transition(body)

    def _refuse_setup_while_busy(self, name: str, action: str) -> None:
        """Refuse to send SETUP to a joint that runs a blocking command.

        The firmware's SETUP stops the motor but leaves BUSY set, so a homing
        would wait forever for its end stop (docs/firmware.md, SETUP). Checked
        on the arm's own homings and on the joint's last flags, before any
        byte is sent.

        Raises:
            ArmStateError: The joint is homing or busy.
        """
        if name in self._homing or self.joints[name].is_busy():
            raise ArmStateError(
                f"{name}: a homing (or another blocking command) is running and {action} would hang it; "
                "abort it (home command 0) first"
            )

    def _enable_joint(self, name: str) -> None:
        """SETUP with the configured currents, stall detection, max velocity and acceleration."""
        self._refuse_setup_while_busy(name, "enabling")
        cfg = self.config.joint(name)
        joint = self.joints[name]
        joint.enable(cfg.drive_current, cfg.hold_current)
        joint.enable_stallguard(cfg.stall_threshold)
        joint.set_max_velocity(cfg.max_velocity)
        joint.set_max_acceleration(cfg.max_acceleration)

    def disable(self, names: Iterable[str]) -> None:
        """Disable joints (stopped, no current, back-drivable) and ``"gripper"``.

        A running homing on a named joint is stopped and finished by the
        read that follows (aborted: the joint reports not homed). The named
        joints' command interfaces
        are released. When no joint reports enabled and the gripper is not
        driven afterwards, an active arm becomes inactive (as after
        :meth:`deactivate`). Every named device is tried even if one fails.

        Args:
            names: Joint names and ``"gripper"``; none does nothing.

        Raises:
            ArmStateError: The arm is not configured (inactive or active).
            InvalidArgumentError: An unknown name.
            JointError: A device could not be disabled, or the state could
                not be read afterwards; every device is disabled (best
                effort) and the arm left unconfigured (the on-error rule).
        """
        self._require(Lifecycle.INACTIVE, Lifecycle.ACTIVE, action="disable")
        joints, gripper = self._split(names)
        if not joints and not gripper:
            return
        try:
            self._disable_devices(joints, gripper)
        except JointError:
            self._fail()
            raise
        self.read()
        for name in joints:
            self.modes[name] = CommandMode.NONE
            self._homing.discard(name)
            self.joint_states[name].homing = False
        if self.state is Lifecycle.ACTIVE and not self._any_enabled():
            self.state = Lifecycle.INACTIVE

    def attach(self) -> bool:
        """Become active over devices an earlier process enabled, without enabling them.

        :meth:`activate` and :meth:`enable` send SETUP, which stops a running
        blocking command, such as a homing another process left running. This
        sends nothing: if any joint reported enabled in the last
        :meth:`read` (:meth:`configure` ends with one; read again first if
        time has passed) or the gripper is driven, the arm becomes active
        holding the measured positions, with no command interface claimed
        (as after :meth:`activate`); joints that reported disabled stay so.
        A running homing keeps running; hand it to the arm with
        :meth:`adopt_homing`.

        Returns:
            Whether the arm became active (``False``: nothing is enabled and
            the arm stays inactive).

        Raises:
            ArmStateError: The arm is not inactive.
        """
        self._require(Lifecycle.INACTIVE, action="attach")
        if not self._any_enabled():
            return False
        self.state = Lifecycle.ACTIVE
        self.gripper_command = self.gripper.get_position()
        self._hold_measured()
        return True

    def adopt_homing(self, name: str, speed: float) -> None:
        """Track a homing that another process started on the joint, as if :meth:`write` had.

        The joint's home interface becomes active with ``speed`` as its
        command (nothing is sent: the homing already runs); :meth:`read`
        finishes it once BUSY clears (offset stored, max acceleration
        restored, home command reset to 0), and a home command of 0 aborts
        it. A homing that already ended is finished by the next
        :meth:`read`. See :meth:`BaseJoint.adopt_homing` for why the speed
        is needed.

        Args:
            name: The joint.
            speed: Signed homing speed the homing was started with, rad/s or
                m/s; its sign says which end stop it runs to (positive: max).

        Raises:
            ArmStateError: The arm is not active, or another command
                interface is active on the joint (release it first).
            InvalidArgumentError: Unknown joint, or ``speed`` zero or not finite.
            IncorrectStateError: The joint driver runs another blocking command.
        """
        self._require(Lifecycle.ACTIVE, action=f"adopt a homing on {name}")
        mode = self._mode(name)
        if mode not in (CommandMode.NONE, CommandMode.HOME):
            raise ArmStateError(
                f"{name}: {mode.value} interface is active; release it before adopting a homing"
            )
        speed = float(speed)
        if not math.isfinite(speed) or speed == 0.0:
            raise InvalidArgumentError(f"{name}: homing speed {speed} must be finite and non-zero")
        self.joints[name].adopt_homing(speed)
        self.modes[name] = CommandMode.HOME
        self.commands[name] = speed
        self._homing.add(name)
        self.joint_states[name].homing = True

    def _split(self, names: Iterable[str]) -> tuple[list[str], bool]:
        """Joint names (configuration order) and whether ``"gripper"`` is among ``names``."""
        if isinstance(names, str):
            names = (names,)
        wanted = set()
        for name in names:
            if name != GRIPPER_NAME and name not in self.modes:
                raise InvalidArgumentError(
                    f"unknown joint {name!r}; known: {', '.join((*self.names, GRIPPER_NAME))}"
                )
            wanted.add(name)
        return [n for n in self.names if n in wanted], GRIPPER_NAME in wanted

    def _any_enabled(self) -> bool:
        """Whether any joint reports enabled (last flags) or the gripper is driven."""
        return any(j.is_enabled() for j in self.joints.values()) or self.gripper.is_enabled

    def _hold_measured(self) -> None:
        for name in self.names:
            self.modes[name] = CommandMode.NONE
            self.commands[name] = self.joint_states[name].position
        self._homing.clear()

    def deactivate(self) -> None:
        """Disable every joint (back-drivable) and the gripper; state keeps updating."""
        self._require(Lifecycle.ACTIVE, action="deactivate")

        def body() -> None:
            self._disable_all()
            self.state = Lifecycle.INACTIVE

        self._transition(body)

    def _disable_all(self) -> None:
        """Best effort: try every device even if one fails, then raise the first error."""
        try:
            self._disable_devices(self.names, True)
        finally:
            self.modes = dict.fromkeys(self.names, CommandMode.NONE)
            self._homing.clear()

    def _disable_devices(self, joints: Iterable[str], gripper: bool) -> None:
        """Best effort: try every named device even if one fails, then raise the first error.

        If a joint moved at the last read, the joints are stopped and braked
        to rest first (:func:`~bioscara_gym.hardware.safety.wait_for_rest`):
        with its current cut, a moving joint coasts, and one joint's braking
        can push another.
        """
        first: BaseException | None = None
        joints = tuple(joints)
        live = {n: self.joints[n] for n in joints if self.joints[n].initialized}
        if any(self._moving(n) for n in live):
            for joint in live.values():
                try:
                    joint.stop()
                except JointError as e:
                    first = first or e
            wait_for_rest(live)
        for name in joints:
            joint = self.joints[name]
            try:
                if joint.initialized:
                    joint.disable()
            except JointError as e:
                first = first or e
        try:
            if gripper and self.gripper.is_initialized:
                self.gripper.release()  # also a servo an earlier process left driven
        except JointError as e:
            first = first or e
        if first is not None:
            raise first

    def _connect_the_rest(self) -> None:
        """Connect the joints and the gripper not connected yet, best effort."""
        for joint in self.joints.values():
            if not joint.initialized:
                with contextlib.suppress(JointError):
                    joint.init()
        if not self.gripper.is_initialized:
            with contextlib.suppress(JointError):
                self.gripper.init()

    def _read_speeds(self) -> None:
        """Read the connected joints' speeds into :attr:`joint_states`, best effort."""
        for name, joint in self.joints.items():
            if joint.initialized:
                with contextlib.suppress(JointError):
                    self.joint_states[name].velocity = joint.get_velocity()

    def _moving(self, name: str) -> bool:
        """Whether the joint moved at the last read (faster than the rest speed)."""
        rpm = velocity_to_rpm(self.joint_states[name].velocity, self.joints[name].reduction)
        return abs(rpm) >= REST_RPM

    def cleanup(self) -> None:
        """Disconnect the joints and the gripper."""
        self._require(Lifecycle.INACTIVE, action="clean up")
        for joint in self.joints.values():
            joint.deinit()
        self.gripper.deinit()
        self.state = Lifecycle.UNCONFIGURED

    def shutdown(self) -> None:
        """Finalize from any state, leaving the hardware disabled and disconnected."""
        try:
            if self.state is Lifecycle.ACTIVE:
                self._disable_all()
        finally:
            for joint in self.joints.values():
                joint.deinit()
            if self.gripper.is_initialized:
                self.gripper.deinit()
            self.backend.close()
            self.state = Lifecycle.FINALIZED

    def _on_error(self) -> None:
        """Error in any state: deactivate and clean up (best effort), back to UNCONFIGURED."""
        with contextlib.suppress(JointError):
            self._disable_all()
        for joint in self.joints.values():
            joint.deinit()
        if self.gripper.is_initialized:
            self.gripper.deinit()
        self.state = Lifecycle.UNCONFIGURED

    def recover(self) -> None:
        """Handle an error reported from outside (ros2_control's on_error)."""
        if self.state is not Lifecycle.FINALIZED:
            self._on_error()

    def __enter__(self) -> Arm:
        """Configure and activate."""
        self.configure()
        self.activate()
        return self

    def __exit__(self, *exc: object) -> None:
        """Shut down: joints disabled, gripper width saved, bus closed."""
        self.shutdown()

    # -------------------------------------------------------- command modes
    def claim(self, name: str, mode: CommandMode | str) -> None:
        """Make ``mode`` the joint's active command interface.

        Position or velocity on a homed joint that is disabled (after a
        homing, :meth:`disable` or a deadman trip) enables it again first:
        SETUP, stall detection, limits. The set point starts at the measured
        position (position) or 0 (velocity and home), so nothing moves.

        Raises:
            ArmStateError: The arm is not active, the interface is already
                active, or another one is (release it first; the seed's
                prepare_command_mode_switch refuses both).
            NotHomedError: Position or velocity on an unhomed joint.
        """
        try:
            mode = CommandMode(mode)
        except ValueError:
            modes = ", ".join(m.value for m in CommandMode if m is not CommandMode.NONE)
            raise InvalidArgumentError(f"{name}: unknown command mode {mode!r}; expected {modes}") from None
        self._require(Lifecycle.ACTIVE, action=f"claim {mode.value} on {name}")
        current = self._mode(name)
        if current is mode:
            raise ArmStateError(f"{name}: the {mode.value} interface is already active")
        if current is not CommandMode.NONE:
            raise ArmStateError(
                f"{name}: {current.value} interface is active; release it before claiming {mode.value}"
            )
        joint = self.joints[name]
        if mode in (CommandMode.POSITION, CommandMode.VELOCITY):
            if not joint.is_homed():
                raise NotHomedError(f"{name}: cannot command {mode.value} on an unhomed joint; home it first")
            if not joint.is_enabled():  # after a homing, a disable or a deadman trip: enable it again
                self._guarded(lambda: self._enable_joint(name))
                self._read_joint(name)
        state = self.joint_states[name]
        self._restart_watch(name)  # the chip runs on at about the speed the encoder reads
        self.commands[name] = {
            CommandMode.POSITION: state.position,
            CommandMode.VELOCITY: 0.0,
            CommandMode.HOME: 0.0,
            CommandMode.NONE: 0.0,
        }[mode]
        self.modes[name] = mode

    def release(self, name: str) -> None:
        """Release the joint's command interface; the joint holds still.

        Raises:
            ArmStateError: Releasing home while the joint is homing (abort it
                with a home command of 0 first).
        """
        mode = self._mode(name)
        if mode is CommandMode.HOME and name in self._homing:
            raise ArmStateError(f"{name}: homing is running; abort it (home command 0) before releasing")
        self.modes[name] = CommandMode.NONE
        self._sent.pop(name, None)
        if name in self.watches:
            self.watches[name].stop()
        joint = self.joints[name]
        if mode is CommandMode.VELOCITY and self.state is Lifecycle.ACTIVE and joint.is_enabled():
            self._guarded(lambda: joint.set_velocity(0.0))

    def _mode(self, name: str) -> CommandMode:
        try:
            return self.modes[name]
        except KeyError:
            raise InvalidArgumentError(
                f"unknown joint {name!r}; known joints: {', '.join(self.names)}"
            ) from None

    def set_command(self, name: str, value: float) -> None:
        """Set the value of the joint's active command interface.

        Position and velocity commands are clamped to the joint's limits
        (position range, ±max velocity). Of a home command only the sign
        counts (docs/arm.md, "Home command"): +1 homes to the max end stop, -1 to
        the min one, with the speed, sensitivity, current and acceleration of
        the joint's configuration; 0 aborts a running homing.

        Raises:
            ArmStateError: No interface is active on the joint.
            InvalidArgumentError: ``value`` is not finite.
        """
        mode = self._mode(name)
        if mode is CommandMode.NONE:
            raise ArmStateError(f"{name}: no command interface is active; claim one first")
        value = float(value)
        if not math.isfinite(value):
            raise InvalidArgumentError(f"{name}: {mode.value} command {value} must be finite")
        cfg = self.config.joint(name)
        if mode is CommandMode.POSITION:
            value = min(max(value, cfg.min), cfg.max)
        elif mode is CommandMode.VELOCITY:
            value = min(max(value, -cfg.max_velocity), cfg.max_velocity)
        elif mode is CommandMode.HOME:
            value = math.copysign(1.0, value) if value else 0.0
        self.commands[name] = value

    def set_gripper(self, width_m: float) -> None:
        """Command the gripper opening in m (clamped to its limits)."""
        if not math.isfinite(width_m):
            raise InvalidArgumentError(f"gripper: width {width_m} must be finite")
        g = self.config.gripper
        self.gripper_command = min(max(float(width_m), g.min), g.max)

    # ------------------------------------------------------------------ I/O
    def read(self) -> Mapping[str, JointState]:
        """Read every joint: position, velocity, then the homing state.

        A running homing whose BUSY flag has cleared is finished here
        (post_homing), and its home command reset to 0.

        Raises:
            JointError: A read failed; the arm is deactivated first.
        """
        self._require(Lifecycle.INACTIVE, Lifecycle.ACTIVE, action="read")
        for name in self.names:
            self._guarded(lambda name=name: self._read_joint(name))
            self._guarded(lambda name=name: self._watch(name))
        return self.joint_states

    def _watch(self, name: str) -> None:
        """Feed the joint's field watch this reading (docs/arm.md, "The field watch").

        Only while the position or velocity interface has sent a command and
        the joint's flags say it runs it (enabled, homed, not stalled, not
        busy); otherwise the watch starts over.

        Raises:
            FieldLostError: The rotor stayed behind its field; the joint is
                disabled at once (the caller's on-error transition stops the rest).
        """
        watch = self.watches.get(name)
        if watch is None:
            return
        mode, st = self.modes[name], self.joint_states[name]
        halted = Flag.STALL | Flag.NOT_ENABLED | Flag.NOT_HOMED | Flag.BUSY
        now = self.backend.clock.now()
        if st.flags & halted or self.joints[name].picking_up:
            if st.flags & (Flag.STALL | Flag.NOT_ENABLED):  # stopped hard, or unpowered: at rest
                watch.start(now, 0.0, st.velocity, st.position)
            else:
                watch.stop()
            return
        if mode not in (CommandMode.POSITION, CommandMode.VELOCITY) or name not in self._sent:
            return  # nothing sent since the watch last started
        try:
            if mode is CommandMode.VELOCITY:
                watch.velocity(now, self._sent[name], st.velocity)
            else:
                watch.position(now, self._sent[name], st.position, st.velocity)
        except FieldLostError:
            # Its field first, at once: the rotor stands, and a ramped stop would keep the
            # field slipping over it for as long as the ramp takes (0.5 s for j1).
            with contextlib.suppress(JointError):
                self.joints[name].disable()
            raise

    def _restart_watch(self, name: str) -> None:
        """The joint's field watch starts now at the measured speed (not exact), with nothing sent yet."""
        self._sent.pop(name, None)
        if name in self.watches:
            st, now = self.joint_states[name], self.backend.clock.now()
            self.watches[name].start(now, st.velocity, st.velocity, st.position, exact=False)

    def forget_motion(self) -> None:
        """Every field watch starts over with the joints at rest: they were placed, not driven.

        For a simulation's reset: the encoders' speed estimates read the jump
        for a while, and the last positions read are stale.
        """
        now = self.backend.clock.now()
        for watch in self.watches.values():
            watch.start(now, 0.0, 0.0)

    def _read_joint(self, name: str) -> None:
        """Position, velocity, then the home state of one joint (a finished homing is stopped).

        A joint whose blocking command the firmware may not have picked up
        yet is left alone this cycle: a transaction now would have to wait
        (:attr:`BaseJoint.picking_up`), longer than the other joints' deadman.
        """
        joint, st = self.joints[name], self.joint_states[name]
        if joint.picking_up:  # the last reply's flags (the blocking command's own) still hold
            st.flags, st.homed, st.homing = joint.flags, joint.is_homed(), name in self._homing
            return
        st.position = joint.get_position()
        st.velocity = joint.get_velocity()
        st.flags = joint.flags
        st.homed = joint.is_homed()
        if name in self._homing and joint.current_blocking_command is Reg.HOME and not joint.is_busy():
            self._stop_homing(name)
        st.homing = name in self._homing

    def _stop_homing(self, name: str) -> None:
        """A homing ended (BUSY cleared): the seed's stop_homing.

        Stop, restore the max acceleration and velocity, post_homing (store
        the offset on the joint), then disable the joint; its home command
        goes back to 0. Claiming position or velocity enables it again.
        """
        joint, st, cfg = self.joints[name], self.joint_states[name], self.config.joint(name)
        self._homing.discard(name)
        self.commands[name] = 0.0
        joint.stop()
        joint.set_max_acceleration(cfg.max_acceleration)
        joint.set_max_velocity(cfg.max_velocity)
        with contextlib.suppress(NotHomedError):  # aborted or failed: the state says not homed
            joint.post_homing()
        joint.disable()
        st.flags = joint.flags
        st.homed = joint.is_homed()
        st.position = joint.get_position() if st.homed else 0.0
        st.velocity = 0.0

    def write(self) -> None:
        """Send every active command interface's value to its joint.

        Raises:
            JointError: A write failed (e.g. :class:`StalledError`); the arm
                is deactivated first.
        """
        self._require(Lifecycle.ACTIVE, action="write")
        self._guarded(self._write_commands)

    def _write_commands(self) -> None:
        for name, joint in self.joints.items():
            mode = self.modes[name]
            if mode is CommandMode.POSITION:
                joint.set_position(self.commands[name])
                self._sent[name] = self.commands[name]
            elif mode is CommandMode.VELOCITY:
                joint.set_velocity(self.commands[name])
                self._sent[name] = self.commands[name]
            elif mode is CommandMode.HOME:
                self._write_home(name)
        if self.gripper.is_enabled and self.gripper_command != self.gripper.get_position():
            self.gripper.set_position(self.gripper_command)

    def _write_home(self, name: str) -> None:
        """Start (a non-zero command: its sign is the direction) or abort (0) a homing."""
        joint = self.joints[name]
        command = self.commands[name]
        if command != 0.0 and name not in self._homing:
            if joint.is_busy():
                running = joint.current_blocking_command
                what = running.name if running is not Reg.NONE else "a blocking command"
                raise IncorrectStateError(f"{name}: {what} is running; cannot start homing")
            cfg = self.config.joint(name).homing
            self._enable_joint(name)  # the seed's start_homing: activate, homing acceleration, home
            joint.set_max_acceleration(cfg.acceleration)
            joint.start_homing(math.copysign(abs(cfg.speed), command), cfg.threshold, cfg.current)
            self._homing.add(name)
        elif command == 0.0 and name in self._homing:
            joint.stop()  # aborts; read() finishes it (post_homing reports not homed)

    def _guarded(self, operation: Callable[[], None]) -> None:
        """Run a read or write; a failure runs the on-error transition, then re-raises."""
        try:
            operation()
        except JointError:
            self._fail()
            raise

    def _fail(self) -> None:
        """A failed read or write: the seed's on_error (deactivate, clean up: unconfigured)."""
        if self.state in (Lifecycle.INACTIVE, Lifecycle.ACTIVE):
            self._on_error()

    # ------------------------------------------------------- homing, moving
    def homing_names(self) -> list[str]:
        """Joints whose homing, started or adopted by this arm, is running."""
        return [n for n in self.names if n in self._homing]

    def start_homing(self, names: Iterable[str], direction: int | None = None) -> dict[str, float]:
        """Start homing joints through their home command interface; return at once.

        Each joint homes with its configured speed, sensitivity, current and
        acceleration; ``direction`` picks the end stop (the home command's
        sign, as a panel's +1/-1). A joint with another interface claimed is
        released first. :meth:`read` finishes each homing when its BUSY flag
        clears; :meth:`finish_homings` then releases the home interface.

        Args:
            names: Joints to home.
            direction: ``+1`` (the max end stop), ``-1`` (min), or ``None``
                for the sign of the configured homing speed.

        Returns:
            Joint name to the signed homing speed used, rad/s or m/s.

        Raises:
            InvalidArgumentError: Unknown joint or a direction other than +1/-1
                (nothing is sent).
            ArmStateError: The arm is not active.
        """
        self._require(Lifecycle.ACTIVE, action="home")
        if direction not in (None, 1, -1):
            raise InvalidArgumentError(f"homing direction {direction!r} must be +1 or -1")
        speeds = {}
        for name in names:
            self._mode(name)  # unknown names: InvalidArgumentError listing the joints
            speed = self.config.joint(name).homing.speed
            speeds[name] = speed if direction is None else math.copysign(speed, direction)
        for name, speed in speeds.items():
            if self.modes[name] is not CommandMode.HOME:
                self.release(name)
                self.claim(name, CommandMode.HOME)
            self.set_command(name, math.copysign(1.0, speed))
        if speeds:
            self.write()
            self.read()
        return speeds

    def finish_homings(self) -> dict[str, bool]:
        """Release the home interface of joints whose homing ended.

        Returns:
            Joint name to whether it is homed now.
        """
        done = {}
        for name in self.names:
            if self.modes[name] is CommandMode.HOME and name not in self._homing:
                self.modes[name] = CommandMode.NONE
                done[name] = self.joint_states[name].homed
        return done

    def abort_homing(self, names: Iterable[str]) -> list[str]:
        """Abort homings: a home command of 0, or a STOP for a blocking command the arm did not start.

        Returns:
            The joints whose homing was aborted, in configuration order.
        """
        names = set(names)
        ours = [n for n in self.names if n in names and n in self._homing]
        foreign = [n for n in self.names if n in names and n not in ours and self.joints[n].is_busy()]
        for name in ours:
            self.commands[name] = 0.0
        try:
            if ours:
                self.write()
            for name in foreign:
                self.joints[name].stop()
        except JointError:
            self._fail()
            raise
        if ours or foreign:
            self.read()
            self.finish_homings()
        return [n for n in self.names if n in ours or n in foreign]

    def home(
        self,
        names: Iterable[str] | None = None,
        direction: int | None = None,
        *,
        period_s: float = 0.04,
        timeout_s: float | None = None,
        only_unhomed: bool = True,
    ) -> dict[str, float]:
        """Home joints through the home command interface and wait until every homing ended.

        Joints home together; the arm keeps cycling read/write every
        ``period_s`` so no deadman trips. Afterwards a position or velocity
        interface that was claimed before is claimed again (holding the
        homed position, or at 0); the others stay released.

        Args:
            names: Joints to home (default: all).
            direction: As :meth:`start_homing`.
            period_s: Control period while waiting, s.
            timeout_s: Give up (and abort the homings) after this long;
                default: the whole joint range at the homing speed, with
                margin (:func:`homing_timeout_s`).
            only_unhomed: Skip joints that already report homed (the default).

        Returns:
            Joint name to the signed homing speed used.

        Raises:
            NotHomedError: A homing ended without the joint homed.
            ArmStateError: Not active, or the timeout passed (homings aborted).
        """
        names = self.names if names is None else tuple(names)
        for name in names:
            self._mode(name)
        todo = [n for n in names if not (only_unhomed and self.joints[n].is_homed())]
        previous = {n: self.modes[n] for n in todo}
        speeds = self.start_homing(todo, direction)
        if timeout_s is None:
            timeout_s = max(
                (homing_timeout_s(self.config.joint(n), v) for n, v in speeds.items()), default=0.0
            )
        clock = self.backend.clock
        start = clock.now()
        while any(n in self._homing for n in speeds):
            if clock.now() - start > timeout_s:
                self.abort_homing(speeds)
                raise ArmStateError(
                    f"homing {', '.join(speeds)} did not finish within {timeout_s:g} s; aborted"
                )
            self.cycle(period_s)
        self.finish_homings()
        for name, mode in previous.items():  # give back a motion interface claimed before
            if mode in (CommandMode.POSITION, CommandMode.VELOCITY) and self.joint_states[name].homed:
                self.claim(name, mode)
        failed = [n for n in speeds if not self.joint_states[n].homed]
        if failed:
            raise NotHomedError(f"homing failed for {', '.join(failed)} (aborted or no end stop found)")
        return speeds

    def move_to(
        self,
        targets: Mapping[str, float],
        *,
        period_s: float = 0.04,
        timeout_s: float | None = None,
    ) -> dict[str, float]:
        """Move joints to positions in position mode and wait until they are there, at rest.

        Every target is checked against its joint's limits before anything
        is sent. A joint counts as there within :data:`MOVE_TOLERANCE` of its
        target and moving slower than a tenth of that per second. Afterwards
        each joint's command interface is what it was before (a position
        interface stays claimed at the target; a velocity one is claimed
        again at 0).

        Args:
            targets: Joint name to position, rad or m.
            period_s: Control period while waiting, s.
            timeout_s: Give up after this long; default: twice the slowest
                joint's trapezoid profile plus 5 s (:func:`move_timeout_s`).

        Returns:
            Joint name to the measured position at the end.

        Raises:
            InvalidArgumentError: Unknown joint, or a target not finite or
                outside the joint's limits (nothing is sent).
            NotHomedError: A joint is not homed.
            ArmStateError: Not active, or not there within the timeout.
        """
        self._require(Lifecycle.ACTIVE, action="move")
        self.check_targets(targets)
        for name in targets:
            if not self.joints[name].is_homed():
                raise NotHomedError(f"{name}: not homed; home it before moving it")
        if timeout_s is None:
            timeout_s = max(
                (
                    move_timeout_s(self.config.joint(n), v - self.joint_states[n].position)
                    for n, v in targets.items()
                ),
                default=0.0,
            )
        previous = {n: self.modes[n] for n in targets}
        for name, value in targets.items():
            if previous[name] is not CommandMode.POSITION:
                self.release(name)
                self.claim(name, CommandMode.POSITION)
            self.set_command(name, value)
        clock = self.backend.clock
        start = clock.now()
        while not all(self._at(name, value) for name, value in targets.items()):
            if clock.now() - start > timeout_s:
                late = [n for n, v in targets.items() if not self._at(n, v)]
                raise ArmStateError(
                    "; ".join(
                        f"{n}: not at {targets[n]:g} {self._unit(n)} within {timeout_s:g} s "
                        f"(at {self.joint_states[n].position:.4f} {self._unit(n)})"
                        for n in late
                    )
                )
            self.cycle(period_s)
        for name, mode in previous.items():
            if mode is not CommandMode.POSITION:
                self.release(name)
                if mode is not CommandMode.NONE:
                    self.claim(name, mode)
        return {n: self.joint_states[n].position for n in targets}

    def check_targets(self, targets: Mapping[str, float]) -> None:
        """Refuse unknown joints and positions not finite or outside the joint's limits.

        Raises:
            InvalidArgumentError: Naming the joint, the value and the limits.
        """
        check_joint_targets(self.config, targets)

    def _unit(self, name: str) -> str:
        """``m`` for the prismatic joint, ``rad`` for the others."""
        return _unit(self.config, name)

    def _at(self, name: str, target: float) -> bool:
        """Whether the joint is within :data:`MOVE_TOLERANCE` of ``target`` and at rest."""
        tol = MOVE_TOLERANCE[self.config.joint(name).joint_type]
        st = self.joint_states[name]
        return abs(st.position - target) <= tol and abs(st.velocity) <= tol / 10

    def bring_up(
        self,
        mode: CommandMode | str,
        names: Iterable[str] | None = None,
        observer: PhaseObserver | None = None,
    ) -> None:
        """Configure, activate and home the arm as needed, then claim ``mode`` on the joints.

        Each step runs only if needed: a configured arm is not configured
        again, an active one not re-enabled, homed joints not homed again
        (a joint homed before a host restart kept its offset, read back from
        HOMEOFFSET on configure). ``observer`` is told each step: configure,
        activate, home.

        Args:
            mode: The command interface to claim (position or velocity).
            names: The joints (default: all).
            observer: Told when each step starts and ends.

        Raises:
            JointError: A step failed; the arm fell back as the step's
                transition says (see the module docstring).
        """
        mode = CommandMode(mode)
        names = self.names if names is None else tuple(names)
        tell = observer or _Unobserved()
        if self.state is Lifecycle.UNCONFIGURED:
            tell.starting("configure", f"connecting and pinging {self.describe_joints()}")
            self.configure()
            tell.done("configure", "every joint answered")
        if self.state is Lifecycle.INACTIVE:
            tell.starting("activate", "enabling joints, stall detection and limits")
            self.activate()
            tell.done("activate", "joints enabled, stall detection and limits set")
        self._home_unhomed(names, tell)
        for name in names:
            if self.modes[name] is not mode:
                self.release(name)
                self.claim(name, mode)

    def _home_unhomed(self, names: tuple[str, ...], tell: PhaseObserver) -> None:
        """Home the joints of ``names`` not homed yet, telling ``tell`` which were and how long it took."""
        for name in names:
            self._mode(name)  # unknown names: InvalidArgumentError listing the joints
        homed = [n for n in names if self.joints[n].is_homed()]
        todo = [n for n in names if n not in homed]
        if homed:
            tell.done("home", f"{', '.join(homed)} homed before: offset restored from HOMEOFFSET")
        if todo:
            start = self.clock.now()
            tell.starting("home", f"homing {', '.join(todo)}")
            self.home(todo)
            tell.done("home", f"{', '.join(todo)} homed in {self.clock.now() - start:.1f} s")

    def shut_down(self, observer: PhaseObserver | None = None) -> float | None:
        """The orderly end of a session: deactivate, clean up, finalize, each step only if needed.

        ``observer`` is told each step (deactivate, with the gripper's width
        and where it was saved; cleanup). A failure leaves the arm as the
        step's transition says: make it safe with :meth:`safe_stop`.

        Returns:
            The gripper's width after deactivating, m (``None`` if the arm was not active).

        Raises:
            JointError: A joint's disable was not acknowledged.
        """
        tell = observer or _Unobserved()
        width = None
        if self.state is Lifecycle.ACTIVE:
            self.deactivate()
            width = self.gripper.get_position()
            saved = self.gripper.save_status()
            tell.done("deactivate", f"joints disabled, gripper width {width:.3f} m {saved}")
        if self.state is Lifecycle.INACTIVE:
            self.cleanup()
            tell.done("cleanup", "joints and gripper disconnected")
        if self.state is not Lifecycle.FINALIZED:
            self.shutdown()
        return width

    # ------------------------------------------------- what a deployment reads
    @property
    def clock(self) -> Clock:
        """The backend's time source: simulated on sim, mock and emulated; the wall clock on the arm."""
        return self.backend.clock

    def comm_stats(self) -> dict[str, CommStats]:
        """Each joint's bus statistics (transactions, retries, errors by kind); empty without a bus."""
        return self.backend.comm_stats()

    def describe_joints(self) -> str:
        """The joints, each with its bus address where it has one: ``"j1 0x11, j2 0x12, ..."``."""
        return ", ".join(n if j.address is None else f"{n} {j.address:#04x}" for n, j in self.joints.items())

    def watch_deadman(self, limit_s: float = DEADMAN_S) -> DeadmanGuard:
        """A :class:`~bioscara_gym.hardware.safety.DeadmanGuard` on every joint (``detach()`` it after)."""
        return DeadmanGuard(self.backend, limit_s)

    def safe_stop(self) -> SafeStopReport:
        """After a failure: every joint stopped and disabled whatever its flags say, the arm finalized.

        See :func:`~bioscara_gym.hardware.safety.safe_stop`; best effort, never raises a driver error.
        """
        return safe_stop(self)

    def final_state(self) -> dict[str, dict[str, Any]]:
        """Each joint's flags (and currents) from the device side where it can be seen.

        See :func:`~bioscara_gym.hardware.safety.final_state`.
        """
        return final_state(self.backend)

    def cycle(self, dt: float) -> Mapping[str, JointState]:
        """One control cycle: write the commands, let ``dt`` pass, read the state."""
        clock = self.backend.clock
        start = clock.now()
        self.write()
        written = clock.now()
        self.backend.step(dt)
        stepped = clock.now()
        states = self.read()
        self.cycle_bus_s = (written - start) + (clock.now() - stepped)
        return states


#: A move is reached within this many rad (revolute) or m (prismatic), at rest.
MOVE_TOLERANCE = {"revolute": 1e-3, "prismatic": 1e-4}


def homing_timeout_s(config: JointConfig, speed: float) -> float:
    """Time a homing may take, s: 0.5 s pause, the whole range at ``speed`` with 20 % margin, 5 s."""
    return 0.5 + 1.2 * (config.max - config.min) / abs(speed) + 5.0


def move_timeout_s(config: JointConfig, distance: float) -> float:
    """Time a move of ``distance`` may take, s: twice the trapezoid profile's, plus 5 s."""
    return 2.0 * (abs(distance) / config.max_velocity + config.max_velocity / config.max_acceleration) + 5.0
