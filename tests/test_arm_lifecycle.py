"""The arm's lifecycle (docs/arm.md, "The arm layer") and how errors send it back to a safe state.

Covers configure, activate, deactivate, cleanup, shutdown and the context manager; transitions
refused from the wrong state, naming both states; and error recovery: a failed configure,
activate, deactivate, read or write (or a stall) leaves the arm inactive or unconfigured, and it
configures again once the bus is healthy. Behaviour every backend shares is parametrized over the
``mock``, ``sim`` and ``emulated`` backends; register traffic is observed at each joint's
``_command`` / ``_query`` primitives and, for the ``emulated`` backend, on the bus itself.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from rigs import CONFIG, DT, NAMES, NEAR_END_STOPS, MakeBackend, cycle_until, motor_rate_deg, spy

from bioscara_gym.hardware.arm import Arm, ArmStateError, CommandMode, Lifecycle
from bioscara_gym.hardware.backends import EmulatedBackend
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import (
    CommError,
    IncorrectStateError,
    StalledError,
)
from bioscara_gym.hardware.gripper import Gripper
from bioscara_gym.hardware.registers import Flag, Reg
from bioscara_gym.hardware.safety import safe_stop

# ---------------------------------------------------------------- lifecycle


def test_arm_starts_unconfigured_with_no_interface_claimed(arm: Arm) -> None:
    assert arm.state is Lifecycle.UNCONFIGURED
    assert arm.names == NAMES
    assert set(arm.modes.values()) == {CommandMode.NONE}
    assert not any(j.initialized for j in arm.joints.values())


def test_configure_pings_every_joint_first_and_goes_inactive(
    arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    traffic = spy(monkeypatch, arm)
    arm.configure()
    assert arm.state is Lifecycle.INACTIVE
    for name in NAMES:
        assert traffic.regs(name)[0] is Reg.PING
        assert arm.joints[name].initialized
    assert arm.gripper.is_initialized
    assert not arm.gripper.is_enabled


def test_configure_pings_every_address_on_the_emulated_bus(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    sent: list[tuple[int, bytes]] = []
    transfer = backend.bus.transfer

    def recording_transfer(address: int, data: bytes, read_len: int) -> bytes:
        sent.append((address, bytes(data)))
        return transfer(address, data, read_len)

    monkeypatch.setattr(backend.bus, "transfer", recording_transfer)
    Arm(backend).configure()
    pinged = [address for address, data in sent if data == bytes([Reg.PING])]
    assert pinged == [0x11, 0x12, 0x13, 0x14]
    assert all(device.transactions > 0 for device in backend.devices.values())


def test_configure_does_not_enable_the_joints(arm: Arm) -> None:
    arm.configure()
    assert not any(j.is_enabled() for j in arm.joints.values())


def test_activate_enables_every_joint_and_goes_active(arm: Arm) -> None:
    arm.configure()
    arm.activate()
    assert arm.state is Lifecycle.ACTIVE
    for name, joint in arm.joints.items():
        assert joint.is_enabled(), name
        assert not arm.joint_states[name].flags & Flag.NOT_ENABLED


def test_activate_enables_stall_detection_and_sets_limits(arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    arm.configure()
    traffic = spy(monkeypatch, arm)
    arm.activate()
    for name in NAMES:
        cfg = CONFIG.joint(name)
        assert traffic.regs(name)[:4] == [
            Reg.SETUP,
            Reg.ENABLESTALLGUARD,
            Reg.SETMAXVELOCITY,
            Reg.SETMAXACCELERATION,
        ]
        assert traffic.values(name, Reg.ENABLESTALLGUARD) == [cfg.stall_threshold]
        assert traffic.values(name, Reg.SETMAXVELOCITY) == [
            pytest.approx(motor_rate_deg(name, cfg.max_velocity))
        ]
        assert traffic.values(name, Reg.SETMAXACCELERATION) == [
            pytest.approx(motor_rate_deg(name, cfg.max_acceleration))
        ]


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_activate_leaves_stall_detection_and_limits_in_the_firmware(
    make_arm_backend: MakeBackend, name: str
) -> None:
    backend = make_arm_backend(name)
    arm = Arm(backend)
    arm.configure()
    arm.activate()
    for joint in NAMES:
        cfg = CONFIG.joint(joint)
        core = backend.sim.cores[joint]  # type: ignore[union-attr]
        assert core.stallguard
        assert core.stall_sensitivity == cfg.stall_threshold
        assert core.max_velocity == pytest.approx(motor_rate_deg(joint, cfg.max_velocity), rel=1e-6)
        assert core.max_acceleration == pytest.approx(motor_rate_deg(joint, cfg.max_acceleration), rel=1e-6)


def test_activate_holds_the_measured_position_with_no_interface_claimed(homed_arm: Arm) -> None:
    arm = homed_arm
    arm.claim("j1", "position")
    arm.deactivate()
    arm.activate()
    assert set(arm.modes.values()) == {CommandMode.NONE}
    for name in NAMES:
        assert arm.commands[name] == arm.joint_states[name].position
        assert arm.joint_states[name].position == pytest.approx(CONFIG.joint(name).max, abs=1e-3)


def test_nothing_moves_over_cycles_after_activate(homed_arm: Arm) -> None:
    arm = homed_arm
    arm.deactivate()
    arm.activate()
    before = {n: s.position for n, s in arm.read().items()}
    for _ in range(5):
        arm.cycle(DT)
    for name in NAMES:
        assert arm.joint_states[name].position == pytest.approx(before[name], abs=1e-4), name
        assert arm.joint_states[name].velocity == pytest.approx(0.0, abs=1e-3), name


def test_deactivate_disables_every_joint_and_goes_inactive(active_arm: Arm) -> None:
    active_arm.deactivate()
    assert active_arm.state is Lifecycle.INACTIVE
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert all(j.initialized for j in active_arm.joints.values())


def test_deactivate_releases_every_interface(homed_arm: Arm) -> None:
    homed_arm.claim("j1", "position")
    homed_arm.claim("j2", "velocity")
    homed_arm.deactivate()
    assert set(homed_arm.modes.values()) == {CommandMode.NONE}


def test_state_keeps_updating_while_inactive(active_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    active_arm.deactivate()
    traffic = spy(monkeypatch, active_arm)
    states = active_arm.read()
    assert set(states) == set(NAMES)
    assert all(s.flags & Flag.NOT_ENABLED for s in states.values())
    assert traffic.regs("j1") == [Reg.ANGLEMOVED, Reg.GETENCODERRPM]


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_deactivated_joint_is_back_drivable_and_its_state_updates(
    make_arm_backend: MakeBackend, name: str
) -> None:
    backend = make_arm_backend(name, initial_qpos=NEAR_END_STOPS)
    arm = Arm(backend)
    arm.configure()
    arm.activate()
    arm.home()
    arm.deactivate()
    backend.sim.set_joint_state({"j3": 1.0})  # type: ignore[union-attr]
    arm.read()
    assert arm.joint_states["j3"].position == pytest.approx(1.0, abs=1e-3)


def test_cleanup_goes_unconfigured_and_deinits_the_joints(active_arm: Arm) -> None:
    active_arm.deactivate()
    active_arm.cleanup()
    assert active_arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in active_arm.joints.values())
    assert not active_arm.gripper.is_initialized


def test_arm_can_be_configured_again_after_cleanup(active_arm: Arm) -> None:
    active_arm.deactivate()
    active_arm.cleanup()
    active_arm.configure()
    active_arm.activate()
    assert active_arm.state is Lifecycle.ACTIVE


def test_shutdown_from_active_finalizes_with_joints_disabled(active_arm: Arm) -> None:
    active_arm.shutdown()
    assert active_arm.state is Lifecycle.FINALIZED
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert not any(j.initialized for j in active_arm.joints.values())
    assert not active_arm.gripper.is_initialized


def test_shutdown_from_inactive_finalizes_with_joints_disabled(active_arm: Arm) -> None:
    active_arm.deactivate()
    active_arm.shutdown()
    assert active_arm.state is Lifecycle.FINALIZED
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert not any(j.initialized for j in active_arm.joints.values())


def test_shutdown_from_unconfigured_finalizes(arm: Arm) -> None:
    arm.shutdown()
    assert arm.state is Lifecycle.FINALIZED


def test_shutdown_closes_the_emulated_bus(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    with Arm(backend) as arm:
        assert arm.state is Lifecycle.ACTIVE
    assert arm.state is Lifecycle.FINALIZED
    assert backend.bus.closed


def test_arm_as_context_manager_is_active_inside_and_finalized_after(arm: Arm) -> None:
    with arm:
        assert arm.state is Lifecycle.ACTIVE
    assert arm.state is Lifecycle.FINALIZED
    assert not any(j.is_enabled() for j in arm.joints.values())


def _to(arm: Arm, state: Lifecycle) -> None:
    if state is not Lifecycle.UNCONFIGURED:
        arm.configure()
    if state is Lifecycle.ACTIVE:
        arm.activate()
    if state is Lifecycle.FINALIZED:
        arm.shutdown()


WRONG_STATE = [
    (Lifecycle.UNCONFIGURED, "activate", "cannot activate while unconfigured; the arm must be inactive"),
    (Lifecycle.UNCONFIGURED, "deactivate", "cannot deactivate while unconfigured; the arm must be active"),
    (Lifecycle.UNCONFIGURED, "cleanup", "cannot clean up while unconfigured; the arm must be inactive"),
    (Lifecycle.UNCONFIGURED, "read", "cannot read while unconfigured; the arm must be inactive or active"),
    (Lifecycle.UNCONFIGURED, "write", "cannot write while unconfigured; the arm must be active"),
    (Lifecycle.UNCONFIGURED, "home", "cannot home while unconfigured; the arm must be active"),
    (Lifecycle.INACTIVE, "configure", "cannot configure while inactive; the arm must be unconfigured"),
    (Lifecycle.INACTIVE, "deactivate", "cannot deactivate while inactive; the arm must be active"),
    (Lifecycle.INACTIVE, "write", "cannot write while inactive; the arm must be active"),
    (Lifecycle.INACTIVE, "home", "cannot home while inactive; the arm must be active"),
    (Lifecycle.ACTIVE, "configure", "cannot configure while active; the arm must be unconfigured"),
    (Lifecycle.ACTIVE, "activate", "cannot activate while active; the arm must be inactive"),
    (Lifecycle.ACTIVE, "cleanup", "cannot clean up while active; the arm must be inactive"),
    (Lifecycle.FINALIZED, "configure", "cannot configure while finalized; the arm must be unconfigured"),
    (Lifecycle.FINALIZED, "activate", "cannot activate while finalized; the arm must be inactive"),
    (Lifecycle.FINALIZED, "read", "cannot read while finalized; the arm must be inactive or active"),
]


@pytest.mark.parametrize(
    ("state", "action", "message"), WRONG_STATE, ids=[f"{s.value}-{a}" for s, a, _ in WRONG_STATE]
)
def test_transition_from_the_wrong_state_is_refused_naming_both_states(
    mock_arm: Arm, state: Lifecycle, action: str, message: str
) -> None:
    _to(mock_arm, state)
    with pytest.raises(ArmStateError, match=f"^{message}$"):
        getattr(mock_arm, action)()
    assert mock_arm.state is state


@pytest.mark.parametrize("state", [Lifecycle.UNCONFIGURED, Lifecycle.INACTIVE])
def test_claim_is_refused_unless_active(mock_arm: Arm, state: Lifecycle) -> None:
    _to(mock_arm, state)
    message = f"cannot claim home on j1 while {state.value}; the arm must be active"
    with pytest.raises(ArmStateError, match=message):
        mock_arm.claim("j1", "home")


def test_arm_state_error_is_an_incorrect_state_error(mock_arm: Arm) -> None:
    with pytest.raises(IncorrectStateError):
        mock_arm.activate()


# ----------------------------------------------------------- error recovery


def test_configure_with_a_joint_missing_raises_comm_error_and_stays_unconfigured(
    make_arm_backend: MakeBackend,
) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    del backend.bus.devices[0x13]
    arm = Arm(backend)
    with pytest.raises(CommError, match=r"j3 \(0x13\): PING failed"):
        arm.configure()
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())
    assert not arm.gripper.is_initialized


def arm_left_enabled(make_arm_backend: MakeBackend) -> EmulatedBackend:
    """The emulated arm as an earlier process left it: configured and active, then let go, still enabled."""
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    Arm(backend).__enter__()
    for joint in backend.joints.values():
        joint.deinit()  # the process ends; the firmware stays enabled
    return backend


def test_a_configure_failed_on_one_joint_disables_the_joints_that_answered(
    make_arm_backend: MakeBackend,
) -> None:
    # An earlier process left the arm enabled; now j1 does not answer. Seen: the
    # configure stopped at j1 and its on-error cleanup disabled nothing, so
    # `bioscara disable` left j2-j4 holding torque.
    backend = arm_left_enabled(make_arm_backend)
    firmware = backend.bus.devices
    assert not any(firmware[a].flags & Flag.NOT_ENABLED for a in (0x11, 0x12, 0x13, 0x14))
    del firmware[0x11]
    arm = Arm(backend)
    with pytest.raises(CommError, match=r"j1 \(0x11\): PING failed"):
        arm.configure()
    assert all(firmware[a].flags & Flag.NOT_ENABLED for a in (0x12, 0x13, 0x14))
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())


def test_a_configure_cut_short_by_ctrl_c_still_disables_every_joint(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    # An earlier process left the arm enabled; Ctrl-C lands while j2 is connected.
    # The cleanup disables only the joints connected, so j2-j4 kept their torque.
    backend = arm_left_enabled(make_arm_backend)
    firmware = backend.bus.devices
    j2 = backend.joints["j2"]
    connect = j2.init

    def cut_short() -> None:
        monkeypatch.setattr(j2, "init", connect)  # once
        raise KeyboardInterrupt

    monkeypatch.setattr(j2, "init", cut_short)
    arm = Arm(backend)
    with pytest.raises(KeyboardInterrupt):
        arm.configure()
    assert all(firmware[a].flags & Flag.NOT_ENABLED for a in (0x11, 0x12, 0x13, 0x14))
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())


def backend_with_a_servo_left_driven(
    make_arm_backend: MakeBackend, pwm_tree: Path, state_file: Path
) -> tuple[EmulatedBackend, Gripper]:
    """The emulated joints with the real gripper driver, whose PWM output an earlier process left on."""
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    g = CONFIG.gripper
    gripper = Gripper(g.reduction, g.offset, g.min, g.max, g.backup_init_pos, state_file, sysfs_root=pwm_tree)
    (pwm_tree / "pwmchip0" / "pwm0" / "enable").write_text("1\n")
    backend.gripper = gripper
    return backend, gripper


def test_a_configure_failed_on_one_joint_switches_off_a_servo_left_driven(
    make_arm_backend: MakeBackend, pwm_tree: Path, gripper_state_file: Path
) -> None:
    # An earlier command left the gripper driven (`bioscara gripper WIDTH`);
    # now j1 does not answer. The failed configure never set the gripper up,
    # so its cleanup left the servo's PWM output on.
    backend, gripper = backend_with_a_servo_left_driven(make_arm_backend, pwm_tree, gripper_state_file)
    enable = pwm_tree / "pwmchip0" / "pwm0" / "enable"
    del backend.bus.devices[0x11]
    arm = Arm(backend)
    with pytest.raises(CommError, match=r"j1 \(0x11\): PING failed"):
        arm.configure()
    assert enable.read_text().strip() == "0"
    assert not gripper.is_initialized
    assert gripper_state_file.read_text() == '{"width_m": 0.08}\n'  # its width is not this process's to save


def test_the_safe_stop_switches_off_a_servo_left_driven(
    make_arm_backend: MakeBackend, pwm_tree: Path, gripper_state_file: Path
) -> None:
    # The arm configured, the gripper set up but never enabled by this process.
    backend, gripper = backend_with_a_servo_left_driven(make_arm_backend, pwm_tree, gripper_state_file)
    arm = Arm(backend)
    arm.configure()
    assert gripper.output_enabled and not gripper.is_enabled
    report = safe_stop(arm)
    assert (pwm_tree / "pwmchip0" / "pwm0" / "enable").read_text().strip() == "0"
    assert report.problems == []


def test_configure_on_a_dead_bus_names_the_first_joint(make_arm_backend: MakeBackend) -> None:
    arm = Arm(make_arm_backend("emulated", faults=FaultPlan(nack=1.0)))
    with pytest.raises(CommError, match=r"j1 \(0x11\): PING failed after 3 attempts"):
        arm.configure()
    assert arm.state is Lifecycle.UNCONFIGURED


def test_arm_configures_once_the_bus_is_healthy_again(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated", faults=FaultPlan(nack=1.0))
    assert isinstance(backend, EmulatedBackend)
    arm = Arm(backend)
    with pytest.raises(CommError):
        arm.configure()
    backend.bus.faults = FaultPlan()
    arm.configure()
    assert arm.state is Lifecycle.INACTIVE


def test_recover_from_active_disables_the_joints_and_goes_unconfigured(active_arm: Arm) -> None:
    active_arm.recover()
    assert active_arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert not any(j.initialized for j in active_arm.joints.values())
    assert not active_arm.gripper.is_initialized


def test_recover_leaves_a_finalized_arm_finalized(mock_arm: Arm) -> None:
    mock_arm.shutdown()
    mock_arm.recover()
    assert mock_arm.state is Lifecycle.FINALIZED


# Seed 000, on_error: an error in any state deactivates and cleans up: unconfigured.
def test_failed_read_raises_and_returns_the_arm_to_unconfigured(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.claim("j1", "position")
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError, match=r"j1 \(0x11\): ANGLEMOVED failed"):
        arm.read()
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())
    assert set(arm.modes.values()) == {CommandMode.NONE}


def test_failed_write_raises_and_returns_the_arm_to_unconfigured(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.claim("j2", "position")
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError, match=r"j2 \(0x12\): MOVETOANGLE failed"):
        arm.write()
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())


def test_arm_comes_back_after_a_failed_read_once_the_bus_recovers(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError):
        arm.read()
    arm.backend.bus.faults = FaultPlan()  # type: ignore[attr-defined]
    arm.configure()  # ping again; the homing offsets are read back from the joints
    assert arm.joint_states["j1"].position == pytest.approx(CONFIG.joint("j1").max, abs=1e-3)
    arm.activate()
    assert arm.state is Lifecycle.ACTIVE


def test_failed_activate_falls_back_to_unconfigured(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    arm = Arm(backend)
    arm.configure()
    backend.bus.faults = FaultPlan(nack=1.0)
    with pytest.raises(CommError, match=r"j1 \(0x11\): SETUP failed"):
        arm.activate()
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())
    assert not arm.gripper.is_initialized


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_stall_in_velocity_mode_raises_on_write_and_returns_the_arm_to_unconfigured(
    make_arm_backend: MakeBackend, name: str
) -> None:
    arm = Arm(make_arm_backend(name, initial_qpos=NEAR_END_STOPS))
    arm.configure()
    arm.activate()
    arm.home()
    arm.claim("j1", "velocity")
    arm.set_command("j1", 0.5)  # into the max end stop it homed against
    with pytest.raises(StalledError, match="j1: joint stalled"):
        cycle_until(arm, lambda: False, max_s=2.0)
    assert arm.state is Lifecycle.UNCONFIGURED


def test_failed_deactivate_falls_back_to_unconfigured(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError, match=r"j1 \(0x11\): STOP failed"):
        arm.deactivate()
    assert arm.state is Lifecycle.UNCONFIGURED


def test_docs_arm_md_says_what_the_code_does() -> None:
    # docs/arm.md said claiming a claimed interface is a no-op (it raises) and that a
    # failed cycle leaves the arm INACTIVE (the seed's on_error leaves it UNCONFIGURED).
    text = (Path(__file__).parent.parent / "docs" / "arm.md").read_text(encoding="utf-8")
    rows = text.splitlines()
    row = next(line for line in rows if line.startswith("| claiming the interface already claimed"))
    assert "ArmStateError" in row and "no-op" not in row
    assert "failed read/write (ACTIVE) --> (disable all, deinit all) --> UNCONFIGURED" in text
    assert "the arm goes INACTIVE" not in text
