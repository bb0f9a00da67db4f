"""Shared fixtures of the test suite, and the ``--hw`` / ``--i2c-bus N`` options.

``pytest --hw`` runs the conformance suite (``test_conformance.py``) against
the joints of a real arm on ``/dev/i2c-N`` in place of the emulated, mock and
simulated rigs; docs/hardware_tests.md lists what each test moves and what
must be clear first. Without ``--hw`` nothing here opens a real bus.
"""

from __future__ import annotations

import os

# Headless rendering; must be set before anything imports mujoco.
os.environ.setdefault("MUJOCO_GL", "egl")

import contextlib
import dataclasses
import signal
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from rigs import J1, NEAR_END_STOPS, RIG_FACTORIES, EmulatedJoint, JointRig, MakeBackend, build_emulated

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import Backend, make_backend
from bioscara_gym.hardware.base_joint import ABORT_SETTLE_S, BUSY_POLL_S
from bioscara_gym.hardware.bus import I2CBus, SMBusI2C
from bioscara_gym.hardware.clock import ManualClock, WallClock
from bioscara_gym.hardware.config import ArmConfig, load_config
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import JointError
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import BLOCKING_PICKUP_S, Flag, Reg
from bioscara_gym.hardware.sim import ArmSim

# ------------------------------------------------------------- pytest --hw

#: Rig ids of the real arm's joints under ``--hw`` (``i2c_<joint>``).
HARDWARE_RIGS = ("i2c_j1", "i2c_j2", "i2c_j3", "i2c_j4")
#: How long the start of a homing runs before the hardware rig aborts it, s.
RESET_HOMING_S = 0.2


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("bioscara", "Bioscara hardware")
    group.addoption(
        "--hw",
        action="store_true",
        help="run the conformance suite against the real arm's joints (docs/hardware_tests.md)",
    )
    group.addoption(
        "--i2c-bus", type=int, default=1, metavar="N", help="the arm's bus, /dev/i2c-N (default 1)"
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "hw_moves: travels the joint on hardware beyond the rig's reset (docs/hardware_tests.md)"
    )


@pytest.fixture(autouse=True, scope="session")
def _sb3_logs_in_a_temporary_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """stable-baselines3 makes a ``SB3-<date>`` folder in the system's temp dir for every model
    that learns without a TensorBoard log (rl-zoo3's runs, the tests' short ones); keep them here."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3")))
        yield


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """The ``rig`` fixture's ids: the real arm's joints with ``--hw``, else every rig of ``rigs.py``."""
    if "rig" in metafunc.fixturenames:
        ids = HARDWARE_RIGS if metafunc.config.getoption("--hw") else sorted(RIG_FACTORIES)
        metafunc.parametrize("rig", ids, indirect=True)


def pytest_runtest_setup(item: pytest.Item) -> None:
    """A test on a hardware rig starts only under ``--hw`` (nothing is asked interactively)."""
    callspec = getattr(item, "callspec", None)
    on_hardware = callspec is not None and callspec.params.get("rig") in HARDWARE_RIGS
    if on_hardware and not item.config.getoption("--hw"):
        pytest.skip("moves the real arm: run with --hw (docs/hardware_tests.md)")


def _hardware_joint(name: str, bus: I2CBus, clock: WallClock) -> Joint:
    """A driver for the packaged configuration's joint ``name`` on ``bus``."""
    p = load_config().joint(name)
    return Joint(p.name, p.address, p.reduction, p.min, p.max, bus, clock=clock)


def _reset_to_power_up(name: str, bus: I2CBus, clock: WallClock) -> None:
    """Leave the joint as after power-up without a power cycle: not homed, not enabled, no offset.

    Starts a homing (HOMEOFFSET := NaN, NOTHOMED set), lets it run
    :data:`RESET_HOMING_S`, stops it, waits until the aborted homing has
    returned, then disables the joint: flags NOTHOMED | NOTENABLED, as at
    power-up. The joint travels ``RESET_HOMING_S`` at its homing speed.
    """
    p = load_config().joint(name)
    joint = _hardware_joint(name, bus, clock)
    joint.init()
    joint.enable(p.drive_current, p.hold_current)
    joint.start_homing(p.homing.speed, p.homing.threshold, p.homing.current)
    clock.sleep(max(RESET_HOMING_S, BLOCKING_PICKUP_S))
    joint.stop()
    clock.sleep(ABORT_SETTLE_S)
    joint.disable()
    joint.deinit()


def _make_safe(name: str, bus: I2CBus, clock: WallClock) -> None:
    """Disable the joint (stopped, no current, freewheel), best effort."""
    joint = _hardware_joint(name, bus, clock)
    with contextlib.suppress(JointError):
        joint.init()
        joint.disable()


def hardware_rig(rig_id: str, bus: I2CBus, clock: WallClock) -> JointRig:
    """Joint ``rig_id`` (``i2c_j1`` ...) of the real arm, reset to its power-up state.

    Time is the wall clock; ``device_flags`` is a PING (the only way to look
    into a real joint). No ``stall`` (nothing holds the joint), ``power_cycle``
    or ``power_up_at``: those tests skip with the reason.
    """
    name = rig_id.removeprefix("i2c_")
    p = load_config().joint(name)
    _reset_to_power_up(name, bus, clock)
    return JointRig(
        name=rig_id,
        joint=_hardware_joint(name, bus, clock),
        params=p,
        clock=clock,
        advance=clock.sleep,
        device_flags=lambda: Flag(bus.transfer(p.address, bytes((Reg.PING,)), 2)[-1]),
        restart_host=lambda: _hardware_joint(name, bus, clock),
        features=frozenset({"deadman", "host_restart", "physics"}),
    )


class ScriptedBus:
    """A fake I2C bus at the byte boundary: records every transfer, replies from a script.

    Each transfer is logged as ``(address, bytes(data), read_len)`` and answered
    with the next queued reply; a queued exception instance is raised instead
    (e.g. ``OSError`` for a NACK). A transfer with nothing queued fails the test.
    """

    def __init__(self) -> None:
        self.log: list[tuple[int, bytes, int]] = []
        self.replies: deque[bytes | BaseException] = deque()
        self.closed = False

    def queue(self, *replies: bytes | BaseException) -> None:
        """Append canned replies (bytes) or faults (exception instances)."""
        self.replies.extend(replies)

    def clear_log(self) -> None:
        """Forget the transfers so far (after putting a joint into a state)."""
        self.log.clear()

    def writes(self) -> list[bytes]:
        """The bytes written by every logged transfer, in order."""
        return [data for _, data, _ in self.log]

    def transfer(self, address: int, data: Iterable[int], read_len: int) -> bytes:
        data = bytes(data)
        self.log.append((address, data, read_len))
        if not self.replies:
            raise AssertionError(f"unscripted transfer to {address:#04x}: {data.hex()} read {read_len}")
        reply = self.replies.popleft()
        if isinstance(reply, BaseException):
            raise reply
        return bytes(reply)

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def scripted_bus() -> Iterator[ScriptedBus]:
    """A :class:`ScriptedBus`; the test fails if it leaves replies unconsumed."""
    bus = ScriptedBus()
    yield bus
    assert not bus.replies, f"scripted replies left unconsumed: {list(bus.replies)!r}"


# ------------------------------------------------------- joint rigs and firmware


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[JointRig]:
    """Every joint backend of ``rigs.RIG_FACTORIES``, fresh, its joint not ``init()``-ed.

    With ``--hw``: each joint of the real arm on ``/dev/i2c-N``, reset to its
    power-up state first and disabled afterwards, whatever the test did.
    """
    if request.param not in HARDWARE_RIGS:
        yield RIG_FACTORIES[request.param]()
        return
    clock = WallClock()
    bus = SMBusI2C(request.config.getoption("--i2c-bus"))
    name = request.param.removeprefix("i2c_")
    try:
        yield hardware_rig(request.param, bus, clock)
    finally:
        try:
            _make_safe(name, bus, clock)
        finally:
            bus.close()


@pytest.fixture
def manual_clock() -> ManualClock:
    """A manual clock at t = 0."""
    return ManualClock()


@pytest.fixture
def free_motor() -> KinematicStepper:
    """A kinematic stepper at 0 deg with no end stops and no load."""
    return KinematicStepper(0.0)


@pytest.fixture
def firmware(free_motor: KinematicStepper, manual_clock: ManualClock) -> JointFirmware:
    """Joint firmware, just powered up, in front of :func:`free_motor`."""
    return JointFirmware(free_motor, manual_clock)


@pytest.fixture
def emulated_j1() -> EmulatedJoint:
    """SPEC j1 as Joint -> EmulatedI2CBus -> JointFirmware -> KinematicStepper, at q = 2.9 rad."""
    return build_emulated(J1, start_q=2.9)


@pytest.fixture
def make_emulated_j1() -> Callable[..., EmulatedJoint]:
    """Factory of :func:`emulated_j1` with a fault plan: ``make(faults=FaultPlan(...), retries=2)``."""

    def make(faults: FaultPlan | None = None, retries: int = 2) -> EmulatedJoint:
        return build_emulated(J1, start_q=2.9, faults=faults, retries=retries)

    return make


# ------------------------------------------------------------ arm backends

#: Backends an :class:`~bioscara_gym.hardware.arm.Arm` runs on without hardware.
ARM_BACKENDS = ("mock", "sim", "emulated")


@pytest.fixture
def gripper_state_file(tmp_path: Path) -> Path:
    """The gripper's state file under ``tmp_path``, holding the backup width 0.08 m."""
    path = tmp_path / "state" / "gripper.json"
    path.parent.mkdir()
    path.write_text('{"width_m": 0.08}\n', encoding="utf-8")
    return path


@pytest.fixture
def datasets(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Minari's datasets folder (``$MINARI_DATASETS_PATH``) under ``tmp_path``, not yet made."""
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


@pytest.fixture
def sighup_default() -> Iterator[None]:
    """SIGHUP at its default, as under a terminal (a test runner may itself run under ``nohup``)."""
    before = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGHUP, before)


@pytest.fixture
def pwm_tree(tmp_path: Path) -> Path:
    """A sysfs PWM tree with ``pwmchip0/pwm0`` exported; returns the ``sysfs_root``."""
    root = tmp_path / "sys" / "class" / "pwm"
    pwm = root / "pwmchip0" / "pwm0"
    pwm.mkdir(parents=True)
    for name in ("export", "unexport"):
        (pwm.parent / name).write_text("")
    for attr in ("period", "duty_cycle", "enable"):
        (pwm / attr).write_text("0\n")
    return root


@pytest.fixture
def make_arm_backend(gripper_state_file: Path) -> Iterator[Callable[..., Backend]]:
    """Factory ``make(name, **options)`` of backends keeping the gripper width in ``tmp_path``.

    ``state_file`` defaults to :func:`gripper_state_file`; every backend built
    is closed at teardown.
    """
    built: list[Backend] = []

    def make(name: str, **options: object) -> Backend:
        options.setdefault("state_file", gripper_state_file)
        backend = make_backend(name, **options)
        built.append(backend)
        return backend

    yield make
    for backend in built:
        backend.close()


# ------------------------------------------------------------------ gym envs


@pytest.fixture
def make_env() -> Iterator[Callable[..., gym.Env]]:
    """Factory ``make(env_id="Bioscara-Reach-v0", **kwargs)`` of ``gym.make`` envs, closed at teardown."""
    made: list[gym.Env] = []

    def make(env_id: str = "Bioscara-Reach-v0", **kwargs: object) -> gym.Env:
        env = gym.make(env_id, **kwargs)
        made.append(env)
        return env

    yield make
    for env in made:
        env.close()


def expert_success(env_id: str, episodes: int, **kwargs: object) -> tuple[float, int]:
    """The task's scripted expert over ``episodes`` seeded episodes (seeds 0...): success rate, stalls."""
    from bioscara_gym.experts import expert_for
    from bioscara_gym.training.evaluate import run_episodes

    env = gym.make(env_id, **kwargs)
    try:
        stats = run_episodes(env, expert_for(env.unwrapped), episodes, seed=0)
        return stats.success_rate, stats.stalls
    finally:
        env.close()


# ------------------------------------------------------------- MuJoCo arm (test_sim)

#: Names of the backends with MuJoCo behind them.
MUJOCO_BACKENDS = ("sim", "emulated")


def homing_config(direction: int) -> ArmConfig:
    """The packaged configuration with every joint homing towards ``max`` (+1) or ``min`` (-1)."""
    config = load_config()
    joints = tuple(
        dataclasses.replace(j, homing=dataclasses.replace(j.homing, speed=direction * abs(j.homing.speed)))
        for j in config.joints
    )
    return dataclasses.replace(config, joints=joints)


def ready_arm(backend: Backend) -> Backend:
    """``init`` and enable every joint with its configured currents and limits, as the arm layer does."""
    for name, joint in backend.joints.items():
        j = backend.config.joint(name)
        joint.init()
        joint.enable(j.drive_current, j.hold_current)
        joint.set_max_velocity(j.max_velocity)
        joint.set_max_acceleration(j.max_acceleration)
    return backend


def near_max_pose(config: ArmConfig, margin: float = 0.005) -> dict[str, float]:
    """Every joint ``margin`` of its range inside ``max``: homing there takes ~1 s of simulated time."""
    return {j.name: j.max - margin * (j.max - j.min) for j in config.joints}


@pytest.fixture(params=MUJOCO_BACKENDS)
def mujoco_arm(request: pytest.FixtureRequest) -> Iterator[Backend]:
    """A ``sim`` or ``emulated`` backend at :func:`near_max_pose`, every joint enabled, none homed."""
    with make_backend(request.param, initial_qpos=near_max_pose(load_config())) as backend:
        yield ready_arm(backend)


@dataclass
class HomingRun:
    """One joint homed in the MuJoCo arm from 2 % of its range inside the end stop.

    Attributes:
        backend: The ``sim`` backend, left as homing left it.
        name: The joint homed.
        direction: +1 homed to ``max``, -1 to ``min``.
        limit: The end stop homed to (rad or m).
        start: True position when homing started.
        elapsed_s: Simulated time ``home`` took (start, wait while BUSY, post).
        times: Simulated time of each 10 ms poll while BUSY, from the start.
        qpos: True joint position at each poll.
    """

    backend: Backend
    name: str
    direction: int
    limit: float
    start: float
    elapsed_s: float
    times: np.ndarray
    qpos: np.ndarray


@pytest.fixture(
    scope="module",
    params=[(n, d) for n in ("j1", "j2", "j3", "j4") for d in (1, -1)],
    ids=lambda p: f"{p[0]}-{'max' if p[1] > 0 else 'min'}",
)
def homing_run(request: pytest.FixtureRequest) -> HomingRun:
    """Each joint homed to each end stop in physics, recorded poll by poll.

    The arm powers up at :meth:`ArmSim.parked_pose` of a configuration whose
    homing speeds all point the chosen way, i.e. 2 % of each range inside the
    end stop homing drives to; every joint is enabled (so the others hold).
    Homing is ``BaseJoint.home`` spelled out so every poll can be recorded.
    """
    name, direction = request.param
    config = homing_config(direction)
    backend = ready_arm(make_backend("sim", config))
    sim: ArmSim = backend.sim  # type: ignore[assignment]
    joint, j = backend.joints[name], config.joint(name)
    qadr = sim.model.joint(name).qposadr[0]
    start, t0 = float(sim.data.qpos[qadr]), backend.clock.now()
    times, qpos = [], []
    joint.set_max_acceleration(j.homing.acceleration)  # as the arm layer (and the seed) home
    joint.start_homing(j.homing.speed, j.homing.threshold, j.homing.current)
    while joint.get_flags() & Flag.BUSY:
        times.append(backend.clock.now() - t0)
        qpos.append(float(sim.data.qpos[qadr]))
        backend.step(BUSY_POLL_S)
    joint.post_homing()
    return HomingRun(
        backend=backend,
        name=name,
        direction=direction,
        limit=j.max if direction > 0 else j.min,
        start=start,
        elapsed_s=backend.clock.now() - t0,
        times=np.array(times),
        qpos=np.array(qpos),
    )


# --------------------------------------------------------- arms (test_arm_*.py)


@pytest.fixture(params=ARM_BACKENDS)
def backend(request: pytest.FixtureRequest, make_arm_backend: MakeBackend) -> Backend:
    """Each backend an arm runs on without hardware, fresh (joints powered up, unhomed).

    The simulated arms power up at :data:`NEAR_END_STOPS`.
    """
    if request.param == "mock":
        return make_arm_backend("mock")
    return make_arm_backend(request.param, initial_qpos=NEAR_END_STOPS)


@pytest.fixture
def arm(backend: Backend) -> Arm:
    """An unconfigured arm on :func:`backend`."""
    return Arm(backend)


@pytest.fixture
def active_arm(arm: Arm) -> Arm:
    """:func:`arm` configured and activated; its joints are not homed."""
    arm.configure()
    arm.activate()
    return arm


@pytest.fixture
def homed_arm(active_arm: Arm) -> Arm:
    """:func:`active_arm` with every joint homed (at its max end stop)."""
    active_arm.home()
    return active_arm


@pytest.fixture
def mock_arm(make_arm_backend: MakeBackend) -> Arm:
    """An unconfigured arm on the mock backend (for rules that involve no joint behaviour)."""
    return Arm(make_arm_backend("mock"))


@pytest.fixture
def homed_mock_arm(mock_arm: Arm) -> Arm:
    """:func:`mock_arm` active with every joint homed (at its max end stop)."""
    mock_arm.configure()
    mock_arm.activate()
    mock_arm.home()
    return mock_arm


@pytest.fixture
def emulated_homed_arm(make_arm_backend: MakeBackend) -> Arm:
    """An active, homed arm on the emulated backend (its bus is ``arm.backend.bus``)."""
    arm = Arm(make_arm_backend("emulated", initial_qpos=NEAR_END_STOPS))
    arm.configure()
    arm.activate()
    arm.home()
    return arm


@pytest.fixture
def bioscara(capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, str, str]]:
    """Run ``bioscara ARGS`` in-process; return the exit code, stdout and stderr (whitespace joined)."""
    from bioscara_gym.cli import main

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(list(argv))
        out, err = capsys.readouterr()
        return code, out, " ".join(err.split())

    return run


# ------------------------------------------------------- deploy's refusals
@pytest.fixture(scope="module")
def sac_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny trained Reach policy (cartesian) with its metadata; tests copy it before editing."""
    from rigs import train_tiny_sac

    return train_tiny_sac(tmp_path_factory.mktemp("sac")).parent


@pytest.fixture(scope="module")
def onnx_path(sac_dir: Path) -> Path:
    """``sac_dir``'s policy exported to ONNX (unchecked)."""
    from bioscara_gym.training.export import export_onnx

    return export_onnx(sac_dir / "model.zip", sac_dir / "policy.onnx", check_samples=0).path


@pytest.fixture
def bus_traffic(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, bytes]]:
    """Every transaction any emulated bus carries during the test."""
    from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus

    sent: list[tuple[int, bytes]] = []
    original = EmulatedI2CBus.transfer

    def transfer(self: EmulatedI2CBus, address: int, data: bytes, read_len: int) -> bytes:
        sent.append((address, bytes(data)))
        return original(self, address, data, read_len)

    monkeypatch.setattr(EmulatedI2CBus, "transfer", transfer)
    return sent
