"""The arm-facing half of the safety layer: deadman guard, safe stop, final state.

What a deployment needs from the arm to stop it safely, on every backend,
with nothing but the drivers (no Gymnasium, MuJoCo or torch):

=====================  ==================================================================
piece                  what it does
=====================  ==================================================================
:class:`DeadmanGuard`  the longest silence of each joint on the backend's clock; more than
                       the firmware's deadman (:data:`DEADMAN_S`, docs/firmware.md) raises
                       :class:`SafetyStop` (``deadman``) naming the joint
:func:`safe_stop`      speed 0 to every joint, every joint disabled (currents 0,
                       freewheel), the gripper disabled (its width saved to its state
                       file), the arm shut down and the bus closed
:func:`final_state`    each joint's flags after the stop, from the device side where the
                       backend can see it (the firmware emulator, the mock device)
=====================  ==================================================================

The policy-facing half (NaN check, action clamp) is
:mod:`bioscara_gym.training.deploy_safety`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

from bioscara_gym.hardware.arm import Arm, Lifecycle
from bioscara_gym.hardware.backends import Backend
from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.errors import JointError
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.registers import DEADMAN_S, Flag

#: Where :func:`final_state` reads a joint's flags from, by backend name, when the
#: backend can see the device; otherwise they are the flags of the joint's last reply.
FLAG_SOURCES = {"sim": "emulator", "emulated": "emulator", "mock": "mock device"}
LAST_REPLY = "last reply"


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


# ------------------------------------------------------------- deadman guard
class DeadmanGuard:
    """Longest silence of each joint, on the backend's clock.

    Every exchange the joint's device received counts (a NACK reaches no
    firmware, so it does not feed the deadman). Joints that cannot report
    their exchanges are counted as talked to once per control cycle
    (:meth:`note_cycle`: every cycle reads every joint).

    Args:
        backend: The backend whose joints to watch.
        limit_s: Longest silence allowed, s (the firmware's deadman).
    """

    def __init__(self, backend: Backend, limit_s: float = DEADMAN_S) -> None:
        """Start listening to every joint's exchanges."""
        self.clock = backend.clock
        self.limit_s = float(limit_s)
        self.names = tuple(backend.joints)
        self._last = dict.fromkeys(self.names, self.clock.now())
        self._max = dict.fromkeys(self.names, 0.0)
        self._stop_listening: list[Callable[[], None]] = []
        self._per_cycle: list[str] = []
        for name, joint in backend.joints.items():
            remove = _listen(joint, functools.partial(self._heard, name))
            if remove is None:
                self._per_cycle.append(name)
            else:
                self._stop_listening.append(remove)

    def _heard(self, name: str) -> None:
        """An exchange with ``name`` was delivered now."""
        now = self.clock.now()
        self._max[name] = max(self._max[name], now - self._last[name])
        self._last[name] = now

    def restart(self) -> None:
        """Count every joint as just talked to (after a reset or bring-up)."""
        now = self.clock.now()
        for name in self.names:
            self._last[name] = now
            self._max[name] = 0.0

    def note_cycle(self) -> None:
        """A control cycle talked to every joint (counts for those that cannot report exchanges)."""
        for name in self._per_cycle:
            self._heard(name)

    def silences(self) -> dict[str, float]:
        """Longest silence per joint since the last :meth:`check`, including the current one, s."""
        now = self.clock.now()
        return {name: max(self._max[name], now - self._last[name]) for name in self.names}

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
        self._max = dict.fromkeys(self.names, 0.0)
        return worst

    def detach(self) -> None:
        """Stop listening to the joints."""
        while self._stop_listening:
            self._stop_listening.pop()()


def _listen(joint: BaseJoint, listener: Callable[[], None]) -> Callable[[], None] | None:
    """Call ``listener`` after every exchange ``joint``'s device received.

    Returns:
        A function that stops the calls, or ``None`` if ``joint`` cannot report them.
    """
    on_exchange = getattr(joint, "on_exchange", None)  # TRANSITIONAL: BaseJoint.on_exchange (issue 12)
    if on_exchange is not None:
        return on_exchange(listener)
    if isinstance(joint, Joint):  # TRANSITIONAL: until on_exchange lands, a tap on the joint's bus
        return _BusTap.install(joint, listener)
    return None


class _BusTap:
    """TRANSITIONAL (issue 12): a bus in front of one joint's that calls back per delivered transaction.

    Remove together with the fallback in :func:`_listen` once
    ``BaseJoint.on_exchange`` exists.
    """

    def __init__(self, inner: Any, listener: Callable[[], None]) -> None:
        """Wrap ``inner``."""
        self.inner = inner
        self.listener = listener

    @classmethod
    def install(cls, joint: Joint, listener: Callable[[], None]) -> Callable[[], None]:
        """Put a tap in front of ``joint``'s bus; return what takes it away."""
        tap = cls(joint.bus, listener)
        joint.bus = tap

        def remove() -> None:
            if joint.bus is tap:
                joint.bus = tap.inner

        return remove

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """Forward one transaction; call back if it was delivered."""
        reply = self.inner.transfer(address, data, read_len)
        self.listener()
        return reply

    def close(self) -> None:
        """Close the wrapped bus."""
        self.inner.close()


# ----------------------------------------------------------------- safe stop
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
    problems = _stop_joints(arm)
    gripper = arm.gripper
    was_enabled = gripper.is_enabled
    if arm.state is Lifecycle.ACTIVE:
        try:
            arm.deactivate()
        except JointError as e:
            problems.append(f"deactivate failed: {e}")
    problems += _disable_devices(arm)
    joints = arm.joints
    not_confirmed = [n for n, j in joints.items() if j.initialized and not j.flags & Flag.NOT_ENABLED]
    width = float(gripper.get_position()) if gripper.is_initialized else None
    saved = was_enabled and not gripper.is_enabled and gripper.state_file is not None
    try:
        arm.shutdown()
    except (JointError, OSError) as e:
        problems.append(f"shutdown: {e}")
    return SafeStopReport(problems, not_confirmed, width, saved)


def _stop_joints(arm: Arm) -> list[str]:
    """Speed 0 to every connected joint; the failures."""
    problems = []
    for name, joint in arm.joints.items():
        if joint.initialized:
            try:
                joint.stop()
            except JointError as e:
                problems.append(f"{name}: stop failed: {e}")
    return problems


def _disable_devices(arm: Arm) -> list[str]:
    """Disable every joint not reporting disabled, and the gripper; the failures."""
    problems = []
    for name, joint in arm.joints.items():
        if joint.initialized and not joint.flags & Flag.NOT_ENABLED:
            try:
                joint.disable()
            except JointError as e:
                problems.append(f"{name}: disable failed: {e}")
    if arm.gripper.is_enabled:
        try:
            arm.gripper.disable()
        except (JointError, OSError) as e:
            problems.append(f"gripper: disable failed: {e}")
    return problems


# --------------------------------------------------------------- final state
def flag_names(flags: int) -> str:
    """``"NOT_HOMED|NOT_ENABLED"`` for 12, ``"-"`` for 0."""
    names = [f.name for f in Flag if flags & f and f.name]
    return "|".join(names) if names else "-"


def final_state(backend: Backend) -> dict[str, dict[str, Any]]:
    """Each joint's flags after the stop, from the device side where it can be seen.

    ``sim`` and ``emulated``: the firmware emulator's flags; ``mock``: the
    mock device's; ``i2c``: the flags of the joint's last reply.
    """
    out: dict[str, dict[str, Any]] = {}
    for name, joint in backend.joints.items():
        device = backend.device_flags(name)
        if device is None:
            flags, source = int(joint.flags), LAST_REPLY
        else:
            flags, source = int(device), FLAG_SOURCES.get(backend.name, "device")
        out[name] = {
            "flags": flags,
            "flag_names": flag_names(flags),
            "enabled": not flags & Flag.NOT_ENABLED,
            "source": source,
        }
    return out
