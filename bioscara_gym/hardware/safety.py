"""The arm-facing half of the safety layer: deadman guard, safe stop, final state.

What a deployment needs from the arm to stop it safely, on every backend,
with nothing but the drivers (no Gymnasium, MuJoCo or torch):

=====================  ==================================================================
piece                  what it does
=====================  ==================================================================
:class:`DeadmanGuard`  the longest silence of each joint on the backend's clock; more than
                       the firmware's deadman (:data:`DEADMAN_S`, docs/firmware.md) raises
                       :class:`~bioscara_gym.hardware.errors.DeadmanError` naming the joint
:func:`safe_stop`      speed 0 to every joint, every joint disabled (currents 0,
                       freewheel) whatever its flags say, the gripper disabled (its width
                       saved to its state file), the arm shut down and the bus closed; a
                       joint counts as safe only when its own disable was acknowledged,
                       and each other joint is named with why (no answer, no valid answer)
:func:`final_state`    each joint's flags after the stop, from the device side where the
                       backend can see it (the firmware emulator, the mock device), and its
                       currents where the emulator holds them
=====================  ==================================================================

The :class:`~bioscara_gym.hardware.arm.Arm` offers each of them
(:meth:`~bioscara_gym.hardware.arm.Arm.watch_deadman`,
:meth:`~bioscara_gym.hardware.arm.Arm.safe_stop`,
:meth:`~bioscara_gym.hardware.arm.Arm.final_state`), so a deployment needs
nothing but the arm. The policy-facing half (NaN check, action clamp, why a
run stopped) is :mod:`bioscara_gym.training.deploy_safety`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from bioscara_gym.hardware.backends import Backend
from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.errors import CommError, DeadmanError, JointError
from bioscara_gym.hardware.gripper import BaseGripper
from bioscara_gym.hardware.registers import DEADMAN_S, Flag
from bioscara_gym.hardware.transmission import velocity_to_rpm

#: Where :func:`final_state` reads a joint's flags from, by backend name, when the
#: backend can see the device; otherwise they are the flags of the joint's last reply.
FLAG_SOURCES = {
    "sim": "emulator",
    "emulated": "emulator",
    "sitl": "firmware in the loop",
    "mock": "mock device",
}
LAST_REPLY = "last reply"


# ------------------------------------------------------------- deadman guard
class DeadmanGuard:
    """Longest silence of each joint, on the backend's clock.

    Every exchange the joint's device received counts (a NACK reaches no
    firmware, so it does not feed the deadman), as the joints report them
    (:meth:`BaseJoint.on_exchange`).

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
        self._stop_listening = [
            joint.on_exchange(functools.partial(self._heard, name)) for name, joint in backend.joints.items()
        ]

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

    def silences(self) -> dict[str, float]:
        """Longest silence per joint since the last :meth:`check`, including the current one, s."""
        now = self.clock.now()
        return {name: max(self._max[name], now - self._last[name]) for name in self.names}

    def check(self) -> float:
        """Raise if a joint was silent too long; return the longest silence and start anew.

        Raises:
            DeadmanError: Naming the joint silent the longest.
        """
        silences = self.silences()
        name = max(silences, key=silences.__getitem__)
        worst = silences[name]
        if worst > self.limit_s + 1e-9:
            raise DeadmanError(name, worst, self.limit_s)
        self._max = dict.fromkeys(self.names, 0.0)
        return worst

    def detach(self) -> None:
        """Stop listening to the joints."""
        while self._stop_listening:
            self._stop_listening.pop()()


# ----------------------------------------------------------------- safe stop
@dataclass
class SafeStopReport:
    """What :func:`safe_stop` did.

    Attributes:
        problems: Steps that failed (empty: every joint confirmed disabled).
        not_confirmed: Joints whose disable was not acknowledged (current maybe still on).
        gripper_width_m: The gripper's last width, m (``None`` if it was never initialized).
        gripper_saved: Whether the width went to the gripper's state file.
        why_not_confirmed: Joint to why its disable was not acknowledged, in a few
            words: ``no answer`` (the bus raised: NACK, no device), ``no valid
            answer`` (replies came back malformed or implausible), or the error.
    """

    problems: list[str]
    not_confirmed: list[str]
    gripper_width_m: float | None
    gripper_saved: bool
    why_not_confirmed: dict[str, str] = field(default_factory=dict)

    def warnings(self) -> list[str]:
        """One line per joint not confirmed disabled.

        E.g. ``j2: no answer, still powered as far as we know: cut the power``.
        """
        return [
            f"{name}: {self.why_not_confirmed.get(name, 'disable not acknowledged')}, "
            "still powered as far as we know: cut the power"
            for name in self.not_confirmed
        ]


class StoppableArm(Protocol):
    """What :func:`safe_stop` needs of an :class:`~bioscara_gym.hardware.arm.Arm`."""

    joints: Mapping[str, BaseJoint]
    gripper: BaseGripper
    names: tuple[str, ...]

    def shutdown(self) -> None:
        """Finalize: every device disabled and disconnected, the bus closed."""
        ...


#: A stopped joint counts as at rest once its encoder reads below this motor
#: speed, RPM (12 deg/s at the motor: 0.5 deg/s at j3's 24:1).
REST_RPM = 2.0
#: The longest a stop waits for the joints to come to rest before their
#: current is cut, s. The firmware's STOP ramps the speed down at the joint's
#: max acceleration, and braking takes the current: j3 from 5 rad/s at its
#: 14 rad/s² takes 0.36 s, and the encoder's speed estimate settles some
#: 0.15 s after (a 53 ms time constant).
REST_TIMEOUT_S = 1.0
#: How often the waiting stop reads the speeds, s (each reading feeds the joint's deadman).
REST_POLL_S = 0.02


def wait_for_rest(joints: Mapping[str, BaseJoint]) -> list[str]:
    """Read the stopped joints' speeds until all are at rest together, at most :data:`REST_TIMEOUT_S`.

    The joints were sent STOP; cutting their current before they have
    braked lets a moving arm coast on, unbraked (a j3 at 4.5 rad/s turned
    0.9 rad further, and swung j1 up to 2 rad/s). Every joint is read each
    round, and all must read at rest in the same round: one joint's braking
    pushes on the others. A joint whose speed cannot be read is not waited
    for. Returns the joints still moving at the end.
    """
    watched = dict(joints)
    if not watched:
        return []
    clock = next(iter(watched.values())).clock
    end = clock.now() + REST_TIMEOUT_S
    while True:
        moving = []
        for name, joint in list(watched.items()):
            try:
                rpm = velocity_to_rpm(joint.get_velocity(), joint.reduction)
            except JointError:
                del watched[name]  # cannot be watched; its disable follows
                continue
            if abs(rpm) >= REST_RPM:
                moving.append(name)
        if not moving or clock.now() >= end:
            return moving
        clock.sleep(REST_POLL_S)


def safe_stop(arm: StoppableArm) -> SafeStopReport:
    """Speed 0 to every joint, cut every joint's current, disable the gripper, shut the arm down.

    Best effort: each step is tried on every device even if another failed.
    The order stops all motion first (one STOP per joint), waits for the
    joints to brake to rest (:func:`wait_for_rest`: braking takes current),
    then disables each joint (stop, currents 0, freewheel), so a slow or
    failing bus delays no joint's stop behind another's disable. Every joint is
    disabled whatever its flags say: a deadman trip sets NOT_ENABLED but
    leaves the currents on (docs/firmware.md, deadman). Joints the arm's
    on-error transition disconnected are connected again first, so their
    current can still be cut. A joint counts as confirmed disabled only when
    its own disable went through.
    """
    gripper = arm.gripper
    was_enabled = gripper.is_enabled
    why: dict[str, str] = {}
    problems = _reconnect_joints(arm, why)
    problems += _stop_joints(arm)
    still = wait_for_rest({n: j for n, j in arm.joints.items() if j.initialized})
    problems += [f"{n}: still moving {REST_TIMEOUT_S:g} s after STOP; current cut anyway" for n in still]
    disabled, failures = _disable_joints(arm, why)
    problems += failures + _disable_gripper(arm)
    not_confirmed = [n for n in arm.names if n not in disabled]
    width = float(gripper.get_position()) if gripper.is_initialized else None
    saved = was_enabled and not gripper.is_enabled and gripper.state_file is not None
    try:
        arm.shutdown()
    except (JointError, OSError) as e:
        problems.append(f"shutdown: {e}")
    why = {n: why[n] for n in not_confirmed if n in why}
    return SafeStopReport(problems, not_confirmed, width, saved, why)


def _why(error: JointError) -> str:
    """Why a joint's disable was not acknowledged, in a few words.

    ``no answer`` when the bus itself raised for it (NACK, no device at the
    address), ``no valid answer`` when replies came back but were malformed
    or implausible (a joint that stopped sending reads 0xFF), else the error.
    """
    failures = getattr(error, "failures", None) or [("", error)]
    causes = []
    for _, e in failures:
        cause: BaseException | None = e
        while cause is not None and not isinstance(cause, OSError) and cause.__cause__ is not None:
            cause = cause.__cause__
        causes.append(cause)
    if all(isinstance(c, OSError) for c in causes):
        return "no answer"
    if all(isinstance(e, CommError) for _, e in failures):
        return "no valid answer"
    return f"disable not acknowledged ({error})"


def _reconnect_joints(arm: StoppableArm, why: dict[str, str]) -> list[str]:
    """Connect again the joints an on-error transition disconnected; the failures."""
    problems = []
    for name, joint in arm.joints.items():
        if not joint.initialized:
            try:
                joint.init()
            except JointError as e:
                why[name] = _why(e)
                problems.append(f"{name}: not reachable, its current could not be cut: {e}")
    return problems


def _stop_joints(arm: StoppableArm) -> list[str]:
    """Speed 0 to every connected joint; the failures."""
    problems = []
    for name, joint in arm.joints.items():
        if joint.initialized:
            try:
                joint.stop()
            except JointError as e:
                problems.append(f"{name}: stop failed: {e}")
    return problems


def _disable_joints(arm: StoppableArm, why: dict[str, str]) -> tuple[set[str], list[str]]:
    """Disable every connected joint; the joints whose disable was acknowledged, and the failures."""
    disabled, problems = set(), []
    for name, joint in arm.joints.items():
        if joint.initialized:
            try:
                joint.disable()
            except JointError as e:
                why[name] = _why(e)
                problems.append(f"{name}: disable failed: {e}")
            else:
                disabled.add(name)
    return disabled, problems


def _disable_gripper(arm: StoppableArm) -> list[str]:
    """Switch the gripper's servo off if it is driven, by this process or an earlier one; the failure."""
    if not arm.gripper.is_initialized:
        return []
    try:
        arm.gripper.release()
    except (JointError, OSError) as e:
        return [f"gripper: disable failed: {e}"]
    return []


# --------------------------------------------------------------- final state
def flag_names(flags: int) -> str:
    """``"NOT_HOMED|NOT_ENABLED"`` for 12, ``"-"`` for 0."""
    names = [f.name for f in Flag if flags & f and f.name]
    return "|".join(names) if names else "-"


def final_state(backend: Backend) -> dict[str, dict[str, Any]]:
    """Each joint's flags after the stop, from the device side where it can be seen.

    ``sim`` and ``emulated``: the firmware emulator's flags and its drive and
    hold currents (percent); ``sitl``: the firmware's own flags, as it held
    them when the arm was closed (no currents); ``mock``: the mock device's
    flags; ``i2c``: the flags of the joint's last reply. The currents are ``None`` where the
    device cannot be looked into. NOT_ENABLED alone does not mean safe: the
    firmware's deadman sets it and keeps the currents (docs/firmware.md).
    """
    out: dict[str, dict[str, Any]] = {}
    for name, joint in backend.joints.items():
        device = backend.device_flags(name)
        if device is None:
            flags, source = int(joint.flags), LAST_REPLY
        else:
            flags, source = int(device), FLAG_SOURCES.get(backend.name, "device")
        currents = backend.device_currents(name)
        out[name] = {
            "flags": flags,
            "flag_names": flag_names(flags),
            "enabled": not flags & Flag.NOT_ENABLED,
            "drive_current": None if currents is None else currents[0],
            "hold_current": None if currents is None else currents[1],
            "source": source,
        }
    return out
