"""The safety layer between a policy and the arm, the same on every backend.

``bioscara deploy`` sends every action through :class:`SafetyLayer`:

========================  ==================================================================
check                     what happens
========================  ==================================================================
NaN or inf in an action   :class:`SafetyStop` (``nan_action``) *before* the env sees it
action out of range       clamped to the action space; the arm clamps each joint command to
                          its configured limits (position range, +-max velocity)
a joint stalls            ``stall``, naming the joint (the env has already deactivated)
bus error after retries   ``comm_error`` (:class:`CommError`, naming joint and register)
a joint reports disabled  ``joint_error`` (firmware deadman, power loss) while the arm is active
silence > 50 ms           ``deadman``: a joint went longer than the firmware's deadman
                          (SPEC.md) without a transaction, on the backend's clock
SIGINT / SIGTERM          :class:`Interrupted` (exit code 130 / 143), via :class:`SignalGuard`
========================  ==================================================================

Every stop ends in :func:`safe_stop`: speed 0 to every joint, every joint
disabled (currents 0, freewheel), the gripper disabled (its width saved to
its state file), the arm shut down and the bus closed. :func:`final_state`
then reports each joint's flags, from the emulator where there is one.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum
from types import FrameType
from typing import Any

import numpy as np

from bioscara_gym.hardware.arm import Arm, Lifecycle
from bioscara_gym.hardware.backends import Backend
from bioscara_gym.hardware.bus import I2CBus
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.errors import CommError, JointError, StalledError
from bioscara_gym.hardware.firmware import DEADMAN_S
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.registers import Flag

#: A joint silent for longer than this is stopped by its firmware (SPEC.md "Deadman"), s.
DEADMAN_LIMIT_S = DEADMAN_S


class StopReason(Enum):
    """Why a deployment ended."""

    COMPLETED = "completed"
    NAN_ACTION = "nan_action"
    STALL = "stall"
    COMM_ERROR = "comm_error"
    JOINT_ERROR = "joint_error"
    DEADMAN = "deadman"
    INTERRUPTED = "interrupted"
    TERMINATED = "terminated"
    ERROR = "error"


class SafetyStop(Exception):
    """The safety layer stopped the run; the message names the cause.

    Attributes:
        reason: What tripped.
        joint: The joint concerned, if one is.
    """

    def __init__(self, reason: StopReason, message: str, joint: str | None = None) -> None:
        """Record the reason, the message and the joint."""
        super().__init__(message)
        self.reason = reason
        self.joint = joint


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int) -> None:
        """Remember the signal."""
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)

    @property
    def exit_code(self) -> int:
        """130 for SIGINT, 143 for SIGTERM."""
        return 128 + self.signum

    @property
    def reason(self) -> StopReason:
        """``interrupted`` for SIGINT, ``terminated`` otherwise."""
        return StopReason.INTERRUPTED if self.signum == signal.SIGINT else StopReason.TERMINATED


class SignalGuard:
    """SIGINT and SIGTERM become :class:`Interrupted` for the duration of a ``with`` block.

    By default the exception is raised where the signal lands (bring-up,
    homing and resets can block for seconds). Inside :meth:`deferred` the
    signal is only recorded and :meth:`check` raises it at the next cycle
    boundary, so no log line or bus exchange is cut in half; a second signal
    there raises at once. Inside :meth:`shielded` (the safe stop) signals are
    only recorded. Outside the main thread nothing is installed.
    """

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        """Choose the signals to catch."""
        self.signals = signals
        self.pending: int | None = None
        self._mode = "raise"
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        """Install the handlers."""
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        """Restore the previous handlers."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        repeated = self.pending is not None
        if self.pending is None:
            self.pending = signum
        if self._mode == "raise" or (self._mode == "defer" and repeated):
            raise Interrupted(self.pending)

    @contextlib.contextmanager
    def _in_mode(self, mode: str) -> Iterator[None]:
        previous, self._mode = self._mode, mode
        try:
            yield
        finally:
            self._mode = previous

    def deferred(self) -> contextlib.AbstractContextManager[None]:
        """Record signals; :meth:`check` raises them (a repeated signal raises at once)."""
        return self._in_mode("defer")

    def shielded(self) -> contextlib.AbstractContextManager[None]:
        """Record signals only (while the arm is being made safe)."""
        return self._in_mode("shield")

    def check(self) -> None:
        """Raise :class:`Interrupted` if a signal has arrived."""
        if self.pending is not None:
            raise Interrupted(self.pending)


class TransactionMonitor:
    """An :class:`I2CBus` in front of another that notes when each address was last reached.

    Only delivered transactions count (a NACK reaches no firmware, so it does
    not feed the deadman); times come from ``clock``.

    Args:
        bus: The bus to forward to.
        clock: The backend's clock.
    """

    def __init__(self, bus: I2CBus, clock: Clock) -> None:
        """Wrap ``bus``."""
        self.inner = bus
        self.clock = clock
        self.last: dict[int, float] = {}
        self.max_gap: dict[int, float] = {}

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """Forward one transaction and note its time if it was delivered."""
        reply = self.inner.transfer(address, data, read_len)
        now = self.clock.now()
        previous = self.last.get(address)
        if previous is not None and now - previous > self.max_gap.get(address, 0.0):
            self.max_gap[address] = now - previous
        self.last[address] = now
        return reply

    def close(self) -> None:
        """Close the wrapped bus."""
        self.inner.close()


class DeadmanGuard:
    """Longest silence of each joint, on the backend's clock.

    Joints on a bus (``emulated``, ``i2c``) are watched per transaction
    through a :class:`TransactionMonitor` put in front of their bus; the
    others (``sim``, ``mock``) are talked to at least once per control cycle
    (every cycle reads every joint), so :meth:`note_cycle` marks them.

    Args:
        backend: The backend whose joints to watch.
        limit_s: Longest silence allowed, s.
    """

    def __init__(self, backend: Backend, limit_s: float = DEADMAN_LIMIT_S) -> None:
        """Put monitors in front of the joints' buses."""
        self.clock = backend.clock
        self.limit_s = float(limit_s)
        self.names = tuple(backend.joints)
        self._joints = dict(backend.joints)
        self._monitored: dict[str, tuple[TransactionMonitor, int]] = {}
        monitors: dict[int, TransactionMonitor] = {}
        for name, joint in backend.joints.items():
            if isinstance(joint, Joint):
                monitor = monitors.setdefault(id(joint.bus), TransactionMonitor(joint.bus, self.clock))
                joint.bus = monitor
                self._monitored[name] = (monitor, joint.address)
        self._last: dict[str, float] = {}
        self._max: dict[str, float] = {}
        self.restart()

    def restart(self) -> None:
        """Count every joint as just talked to (after a reset or bring-up)."""
        now = self.clock.now()
        for name in self.names:
            self._last[name] = now
            self._max[name] = 0.0
        for monitor, address in self._monitored.values():
            monitor.last[address] = now
            monitor.max_gap[address] = 0.0

    def note_cycle(self) -> None:
        """A control cycle talked to every joint without a monitor."""
        now = self.clock.now()
        for name in self.names:
            if name not in self._monitored:
                self._max[name] = max(self._max[name], now - self._last[name])
                self._last[name] = now

    def silences(self) -> dict[str, float]:
        """Longest silence per joint since the last :meth:`check`, including the current one, s."""
        now = self.clock.now()
        out = {}
        for name in self.names:
            if name in self._monitored:
                monitor, address = self._monitored[name]
                last, gap = monitor.last.get(address, now), monitor.max_gap.get(address, 0.0)
            else:
                last, gap = self._last[name], self._max[name]
            out[name] = max(gap, now - last)
        return out

    def check(self) -> float:
        """Raise if a joint was silent too long; return the longest silence and start anew.

        Raises:
            SafetyStop: ``deadman``, naming the joint silent the longest.
        """
        silences = self.silences()
        name = max(silences, key=silences.__getitem__)
        worst = silences[name]
        if worst > self.limit_s + 1e-9:
            raise SafetyStop(
                StopReason.DEADMAN,
                f"deadman guard: {name} went {worst * 1000:.1f} ms without a transaction "
                f"(limit {self.limit_s * 1000:.0f} ms); its firmware would stop it",
                joint=name,
            )
        for monitor, address in self._monitored.values():
            monitor.max_gap[address] = 0.0
        for n in self.names:
            self._max[n] = 0.0
        return worst

    def detach(self) -> None:
        """Give the joints their own buses back."""
        for name, (monitor, _) in self._monitored.items():
            joint = self._joints[name]
            if isinstance(joint, Joint) and joint.bus is monitor:
                joint.bus = monitor.inner


def joint_named_in(error: BaseException, names: tuple[str, ...]) -> str | None:
    """The joint a driver error's message starts with (``"j2 (0x12): ..."``), if any."""
    text = str(error)
    return next((n for n in names if text.startswith((f"{n}:", f"{n} "))), None)


@dataclass(frozen=True)
class CycleCheck:
    """What the safety layer saw in one cycle.

    Attributes:
        action: The action sent to the env (clamped).
        clamped: Whether the policy's action was outside the action space.
        silence_s: Longest silence of any joint in the cycle, s.
    """

    action: np.ndarray
    clamped: bool
    silence_s: float


class SafetyLayer:
    """Checks every action before it reaches the arm and every cycle after.

    Args:
        env: The Gymnasium env (wrapped as made); its ``unwrapped`` is a
            Bioscara env with an ``arm``.
        guard: The deadman guard over the env's backend.
    """

    def __init__(self, env: Any, guard: DeadmanGuard) -> None:
        """Bind to ``env`` and its arm."""
        self.env = env
        self.arm: Arm = env.unwrapped.arm
        self.guard = guard
        self.low = np.asarray(env.action_space.low, dtype=np.float64)
        self.high = np.asarray(env.action_space.high, dtype=np.float64)
        self.shape = tuple(env.action_space.shape)
        self.clamped = 0

    def filter_action(self, action: Any) -> tuple[np.ndarray, bool]:
        """The action to send: finite and inside the action space.

        Raises:
            SafetyStop: ``nan_action`` if any element is NaN or infinite.
            ValueError: The action has the wrong shape (a policy for another env).
        """
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.shape:
            raise ValueError(f"policy returned an action of shape {a.shape}; the env expects {self.shape}")
        if not np.all(np.isfinite(a)):
            shown = np.array2string(a, precision=3, separator=", ")
            raise SafetyStop(StopReason.NAN_ACTION, f"policy returned a non-finite action {shown} (NaN/inf)")
        clipped = np.clip(a, self.low, self.high)
        clamped = bool(np.any(clipped != a))
        self.clamped += clamped
        return clipped, clamped

    def step(self, action: Any) -> tuple[tuple[Any, float, bool, bool, dict[str, Any]], CycleCheck]:
        """Check ``action``, step the env, check the outcome.

        Returns:
            The env's ``(obs, reward, terminated, truncated, info)`` and the checks.

        Raises:
            SafetyStop: See the module docstring for the reasons.
        """
        safe, clamped = self.filter_action(action)
        self.guard.check()  # the policy's own time counts on the wall clock
        names = self.arm.names
        try:
            result = self.env.step(safe)
        except StalledError as e:
            joint = joint_named_in(e, names)
            raise SafetyStop(StopReason.STALL, f"{joint or 'a joint'} stalled: {e}", joint) from e
        except CommError as e:
            raise SafetyStop(
                StopReason.COMM_ERROR, f"communication error: {e}", joint_named_in(e, names)
            ) from e
        except JointError as e:
            raise SafetyStop(StopReason.JOINT_ERROR, f"joint error: {e}", joint_named_in(e, names)) from e
        self.guard.note_cycle()
        silence = self.guard.check()
        info = result[4]
        if info.get("stalled"):
            joint = info.get("stalled_joint")
            raise SafetyStop(
                StopReason.STALL, f"{joint} stalled (stall detection tripped); every joint stopped", joint
            )
        if self.arm.state is Lifecycle.ACTIVE:
            for name, state in self.arm.joint_states.items():
                if state.flags & Flag.NOT_ENABLED:
                    raise SafetyStop(
                        StopReason.JOINT_ERROR,
                        f"{name} reports not enabled while the arm is active (firmware deadman, power loss)",
                        name,
                    )
        return result, CycleCheck(safe, clamped, silence)


@dataclass
class SafeStopReport:
    """What :func:`safe_stop` did.

    Attributes:
        problems: Steps that failed (empty: every joint confirmed disabled).
        not_confirmed: Joints whose last reply did not say not enabled.
        gripper_width_m: The gripper's last width, m (``None`` if it was never initialized).
        gripper_saved: Whether the width went to the gripper's state file.
    """

    problems: list[str]
    not_confirmed: list[str]
    gripper_width_m: float | None
    gripper_saved: bool


def safe_stop(arm: Arm) -> SafeStopReport:
    """Speed 0 to every joint, disable every joint and the gripper, shut the arm down.

    Best effort: each step is tried on every device even if another failed.
    The order stops all motion first (one STOP per joint), then disables
    (stop, currents 0, freewheel), so a slow or failing bus delays no joint's
    stop behind another's disable.
    """
    problems: list[str] = []
    joints = arm.joints
    for name, joint in joints.items():
        if joint.initialized:
            try:
                joint.stop()
            except JointError as e:
                problems.append(f"{name}: stop failed: {e}")
    gripper = arm.gripper
    was_enabled = gripper.is_enabled
    if arm.state is Lifecycle.ACTIVE:
        try:
            arm.deactivate()
        except JointError as e:
            problems.append(f"deactivate failed: {e}")
    for name, joint in joints.items():
        if joint.initialized and not joint.flags & Flag.NOT_ENABLED:
            try:
                joint.disable()
            except JointError as e:
                problems.append(f"{name}: disable failed: {e}")
    if gripper.is_enabled:
        try:
            gripper.disable()
        except (JointError, OSError) as e:
            problems.append(f"gripper: disable failed: {e}")
    not_confirmed = [n for n, j in joints.items() if j.initialized and not j.flags & Flag.NOT_ENABLED]
    width = float(gripper.get_position()) if gripper.is_initialized else None
    saved = was_enabled and not gripper.is_enabled and gripper.state_file is not None
    try:
        arm.shutdown()
    except (JointError, OSError) as e:
        problems.append(f"shutdown: {e}")
    return SafeStopReport(problems, not_confirmed, width, saved)


def flag_names(flags: int) -> str:
    """``"NOT_HOMED|NOT_ENABLED"`` for 12, ``"-"`` for 0."""
    names = [f.name for f in Flag if flags & f and f.name]
    return "|".join(names) if names else "-"


def final_state(backend: Backend) -> dict[str, dict[str, Any]]:
    """Each joint's flags after the stop, from the device side where it can be seen.

    ``sim`` and ``emulated``: the firmware emulator's flags; ``mock``: the
    mock device's; ``i2c``: the flags of the joint's last reply.
    """
    cores = getattr(backend.sim, "cores", None)
    out: dict[str, dict[str, Any]] = {}
    for name, joint in backend.joints.items():
        if cores is not None and name in cores:
            flags, source = int(cores[name].flags), "emulator"
        elif hasattr(joint, "device_flags"):
            flags, source = int(joint.device_flags), "mock device"
        else:
            flags, source = int(joint.flags), "last reply"
        out[name] = {
            "flags": flags,
            "flag_names": flag_names(flags),
            "enabled": not flags & Flag.NOT_ENABLED,
            "source": source,
        }
    return out
