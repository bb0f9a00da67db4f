"""The ``bioscara monitor`` dashboard: MH5's terminal UI for the Bioscara arm, with rich.

Three layers, so each can be tested without a terminal:

* :class:`DashboardSnapshot` is plain data (lifecycle, per-joint state,
  gripper, bus statistics and rates, a message), and
  :func:`render_dashboard` turns it into a rich renderable: a header, a joint
  table with a position bar between the limits, velocity, flags in colour
  (STALL red, BUSY yellow, NOT_HOMED magenta, NOT_ENABLED dim) and homing
  progress, a bus table, and the keys.
* :class:`MonitorApp` holds a console :class:`~bioscara_gym.console.session.Session`,
  cycles the arm (read/write at :data:`~bioscara_gym.console.session.CYCLE_S` or
  faster, so the firmware deadman never trips; the simulation advances in
  step), computes bus rates from :class:`~bioscara_gym.hardware.stats.CommStats`
  deltas and builds snapshots. :func:`handle_key` applies one key to it.
* :func:`run_monitor` is the live loop: keys from a terminal in cbreak mode
  (:func:`key_source`, restored on exit), a refresh at the set rate, paced
  on the wall clock; without a terminal it runs for a set duration.

Keys: ``e`` enable all, ``d`` disable all, ``h`` home every enabled joint not
yet homed, ``a`` abort homing, ``r`` reset the since-reset bus counters,
``q`` quit (a homing still running is aborted).
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TextIO

from rich import box
from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from bioscara_gym.console.format import flags_text, format_position, format_velocity, joint_unit
from bioscara_gym.console.session import CYCLE_S, Session
from bioscara_gym.console.targets import resolve_target
from bioscara_gym.hardware.clock import Clock, WallClock
from bioscara_gym.hardware.errors import JointError
from bioscara_gym.hardware.registers import Flag

#: Keys of the dashboard and what they do.
KEYS: dict[str, str] = {
    "e": "enable all",
    "d": "disable all",
    "h": "home unhomed",
    "a": "abort homing",
    "r": "reset stats",
    "q": "quit",
}
#: Spinner frames of a running homing.
SPINNER = "⠋⠙⠹⠸⠼⠴⠦⠧⠇⠏"
#: Width of a position bar in characters, ends included.
BAR_WIDTH = 21


# ---------------------------------------------------------------- pieces
def position_bar(value: float | None, low: float, high: float, width: int = BAR_WIDTH) -> Text:
    """A marker ``●`` on a track from ``low`` to ``high``; a dotted track when unknown.

    Args:
        value: Position (clamped to the track), ``None`` when not known.
        low: Value at the left end.
        high: Value at the right end.
        width: Characters in all, the end marks ``├`` and ``┤`` included.
    """
    inner = max(width - 2, 1)
    if value is None or not math.isfinite(value):
        return Text("├" + "┄" * inner + "┤", style="dim")
    fraction = min(max((value - low) / (high - low), 0.0), 1.0)
    at = round(fraction * (inner - 1))
    text = Text("├", style="dim")
    text.append("─" * at, style="cyan")
    text.append("●", style="bold")
    text.append("─" * (inner - 1 - at), style="dim")
    text.append("┤", style="dim")
    return text


# -------------------------------------------------------------- snapshot
@dataclass(frozen=True)
class JointView:
    """One joint as the dashboard shows it.

    Attributes:
        name: Joint name.
        unit: ``rad`` or ``m``.
        min: Lower limit (left end of the bar).
        max: Upper limit (right end of the bar).
        position: Position, ``None`` while not homed.
        velocity: Velocity in unit/s.
        flags: Flags of the last transaction.
        homing: Whether a homing runs.
        homing_s: Seconds since the homing started (``None``: unknown).
    """

    name: str
    unit: str
    min: float
    max: float
    position: float | None
    velocity: float
    flags: Flag
    homing: bool = False
    homing_s: float | None = None


@dataclass(frozen=True)
class BusView:
    """Bus statistics of one joint.

    Attributes:
        name: Joint name.
        transactions: Transactions since the last reset.
        errors: Errors since the last reset.
        total_transactions: Transactions in all.
        total_errors: Errors in all.
        tx_per_s: Transactions per second over the last refresh.
        errors_per_s: Errors per second over the last refresh.
    """

    name: str
    transactions: int
    errors: int
    total_transactions: int
    total_errors: int
    tx_per_s: float
    errors_per_s: float


@dataclass(frozen=True)
class DashboardSnapshot:
    """Everything the dashboard shows at one refresh.

    Attributes:
        backend: Backend name.
        lifecycle: Lifecycle state of the arm (``active``...).
        time_s: Backend time, s (simulated on the simulated backends).
        joints: The joints in order.
        gripper_enabled: Whether the servo is driven.
        gripper_width: Gripper width, m.
        gripper_min: Smallest width, m.
        gripper_max: Largest width, m.
        bus: Bus statistics per joint (empty without a bus).
        message: The last action's result or error.
        rate_hz: Refresh rate.
    """

    backend: str
    lifecycle: str
    time_s: float
    joints: tuple[JointView, ...]
    gripper_enabled: bool
    gripper_width: float
    gripper_min: float
    gripper_max: float
    bus: tuple[BusView, ...] = ()
    message: str = ""
    rate_hz: float = 10.0


def _homing_text(j: JointView) -> Text:
    if j.homing:
        frame = SPINNER[int((j.homing_s or 0.0) * 10) % len(SPINNER)]
        elapsed = "" if j.homing_s is None else f" {j.homing_s:.1f} s"
        return Text(f"{frame} homing…{elapsed}", style="yellow")
    if not j.flags & Flag.NOT_HOMED:
        return Text("homed", style="green")
    return Text("not homed", style="magenta")


def render_dashboard(snap: DashboardSnapshot) -> RenderableType:
    """The dashboard for one snapshot: header, joints, bus statistics, keys and message."""
    lifecycle_style = {"active": "bold green", "inactive": "yellow"}.get(snap.lifecycle, "red")
    header = Text.assemble(
        ("Bioscara arm  ", "bold"),
        ("lifecycle ", "dim"),
        (snap.lifecycle.upper(), lifecycle_style),
        ("   backend ", "dim"),
        (snap.backend, "bold"),
        ("   t ", "dim"),
        f"{snap.time_s:.2f} s",
        ("   refresh ", "dim"),
        f"{snap.rate_hz:g} Hz",
    )

    joints = Table(box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    for title, justify in (
        ("joint", "left"),
        ("position", "right"),
        ("min … max", "center"),
        ("velocity", "right"),
        ("flags", "left"),
        ("homing", "left"),
    ):
        joints.add_column(title, justify=justify, no_wrap=True)  # type: ignore[arg-type]
    for j in snap.joints:
        joints.add_row(
            j.name,
            format_position(j.position, j.unit),
            position_bar(j.position, j.min, j.max),
            format_velocity(j.velocity, j.unit),
            flags_text(j.flags),
            _homing_text(j),
        )
    joints.add_row(
        "gripper",
        f"{snap.gripper_width:.4f} m",
        position_bar(snap.gripper_width, snap.gripper_min, snap.gripper_max),
        "",
        Text("ENABLED", style="green") if snap.gripper_enabled else Text("NOT_ENABLED", style="dim"),
        "",
    )

    parts: list[RenderableType] = [header, Text(), joints]
    if snap.bus:
        bus = Table(box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
        for title in ("bus", "tx", "errors", "tx total", "errors total", "tx/s", "errors/s"):
            bus.add_column(title, justify="left" if title == "bus" else "right")
        for b in snap.bus:
            bus.add_row(
                b.name,
                str(b.transactions),
                Text(str(b.errors), style="red" if b.errors else ""),
                str(b.total_transactions),
                str(b.total_errors),
                f"{b.tx_per_s:.0f}",
                Text(f"{b.errors_per_s:.1f}", style="red" if b.errors_per_s else ""),
            )
        parts += [Text(), bus]
    keys = Text("keys  ", style="dim")
    for key, what in KEYS.items():
        keys.append(key, style="bold")
        keys.append(f" {what}   ")
    parts += [Text(), keys]
    if snap.message:
        parts.append(Text(snap.message, style="red" if snap.message.startswith("error") else "cyan"))
    return Panel(Group(*parts), title="bioscara monitor", border_style="blue", expand=False)


# ------------------------------------------------------------------- app
@dataclass
class MonitorApp:
    """The dashboard's state: the session it drives, rates, homing timers, the message.

    Attributes:
        session: An open console session.
        rate_hz: Refresh rate; the arm is cycled at least at 25 Hz between refreshes.
        running: False once ``q`` was pressed.
        message: The last action's result or error, shown under the keys.
        homing_since: Joints homing, to the backend time the homing started
            (``None``: started by an earlier command).
        rates: Joint name to (transactions/s, errors/s) over the last step.
    """

    session: Session
    rate_hz: float = 10.0
    running: bool = True
    message: str = ""
    homing_since: dict[str, float | None] = field(default_factory=dict)
    rates: dict[str, tuple[float, float]] = field(default_factory=dict)
    _last: dict[str, tuple[int, int]] = field(default_factory=dict, init=False, repr=False)
    _last_t: float = field(default=0.0, init=False, repr=False)

    def __post_init__(self) -> None:
        """Pick up homings already running and the bus counters to rate against."""
        self.homing_since = dict.fromkeys(self.session.arm.homing_names())
        self._mark()

    def _totals(self) -> dict[str, tuple[int, int]]:
        return {
            n: (s.total_transactions, s.total_errors) for n, s in self.session.backend.comm_stats().items()
        }

    def _mark(self) -> None:
        self._last = self._totals()
        self._last_t = self.session.backend.clock.now()

    def now(self) -> float:
        """Backend time, s."""
        return self.session.backend.clock.now()

    def step(self, dt: float) -> None:
        """Cycle the arm for ``dt`` seconds (in cycles of at most 40 ms), then update the rates."""
        n = max(1, math.ceil(dt / CYCLE_S - 1e-9))
        finished: dict[str, bool] = {}
        error = ""
        try:
            for _ in range(n):
                finished.update(self.session.cycle(dt / n))
        except JointError as e:
            self.session.disable_all_safely()
            error = f"error: {e}; everything disabled"
        self._note_finished(finished)
        self.message = error or self.message
        self._update_rates()

    def _note_finished(self, finished: dict[str, bool]) -> None:
        for name in finished:
            self.homing_since.pop(name, None)
        for name in list(self.homing_since):
            if not self.session.arm.joint_states[name].homing:
                self.homing_since.pop(name)
        homed = [n for n, ok in finished.items() if ok]
        failed = [n for n, ok in finished.items() if not ok]
        notes = [f"{', '.join(homed)} homed"] if homed else []
        notes += [f"{', '.join(failed)} homing aborted (not homed)"] if failed else []
        if notes:
            self.message = "; ".join(notes)

    def _update_rates(self) -> None:
        totals, now = self._totals(), self.now()
        dt = now - self._last_t
        if dt > 0:
            for name, (tx, err) in totals.items():
                tx0, err0 = self._last.get(name, (tx, err))
                self.rates[name] = ((tx - tx0) / dt, (err - err0) / dt)
        self._last, self._last_t = totals, now

    def reset_stats(self) -> None:
        """Zero the since-reset bus counters (totals are kept)."""
        for stats in self.session.backend.comm_stats().values():
            stats.reset()

    def start_homing(self) -> list[str]:
        """Start homing every enabled, idle joint that is not homed; return their names."""
        arm = self.session.arm
        names = [
            n
            for n, j in arm.joints.items()
            if j.is_enabled() and not j.is_homed() and not j.is_busy() and not arm.joint_states[n].homing
        ]
        self.session.start_homing(names)
        now = self.now()
        for name in names:
            self.homing_since[name] = now
        return names

    def snapshot(self) -> DashboardSnapshot:
        """The dashboard's data as of now."""
        session = self.session
        arm = session.arm
        now = self.now()
        joints = []
        for cfg in session.config.joints:
            st = arm.joint_states[cfg.name]
            since = self.homing_since.get(cfg.name)
            joints.append(
                JointView(
                    name=cfg.name,
                    unit=joint_unit(cfg.joint_type),
                    min=cfg.min,
                    max=cfg.max,
                    position=st.position if st.homed else None,
                    velocity=st.velocity,
                    flags=st.flags,
                    homing=st.homing,
                    homing_s=None if since is None else now - since,
                )
            )
        bus = tuple(
            BusView(
                name,
                s.transactions,
                s.errors,
                s.total_transactions,
                s.total_errors,
                *self.rates.get(name, (0.0, 0.0)),
            )
            for name, s in session.backend.comm_stats().items()
        )
        g = session.config.gripper
        return DashboardSnapshot(
            backend=session.backend.name,
            lifecycle=arm.state.value,
            time_s=now,
            joints=tuple(joints),
            gripper_enabled=session.backend.gripper.is_enabled,
            gripper_width=session.gripper_width(),
            gripper_min=g.min,
            gripper_max=g.max,
            bus=bus,
            message=self.message,
            rate_hz=self.rate_hz,
        )

    def close(self) -> None:
        """Leaving the dashboard: abort homings still running (best effort)."""
        with contextlib.suppress(JointError):
            running = self.session.arm.homing_names()
            if running:
                self.session.arm.abort_homing(running)


def handle_key(app: MonitorApp, key: str) -> None:
    """Apply one key to the dashboard (see :data:`KEYS`); unknown keys are ignored.

    Requests that do not apply (nothing to home, nothing homing) only set the
    message. An error from the arm disables everything (the console's
    on-error rule) and is shown in the message; the dashboard keeps running.
    """
    action = _KEY_ACTIONS.get(key.lower())
    if action is None:
        return
    try:
        action(app)
    except (JointError, ValueError) as e:
        app.session.disable_all_safely()
        app.homing_since.clear()
        app.message = f"error: {e}; everything disabled"


def _quit(app: MonitorApp) -> None:
    """``q``: leave the dashboard."""
    app.running = False


def _enable_all(app: MonitorApp) -> None:
    """``e``: enable every joint and the gripper, leaving busy joints as they are."""
    session = app.session
    busy = [n for n, j in session.arm.joints.items() if j.is_busy()]
    names = session.enable(resolve_target(session.config, None), skip_busy=True)
    app.message = f"enabled {', '.join(names)}" + (f"; {', '.join(busy)} busy, left as is" if busy else "")


def _disable_all(app: MonitorApp) -> None:
    """``d``: disable every joint and the gripper (running homings stop)."""
    names = app.session.disable(resolve_target(app.session.config, None))
    app.homing_since.clear()
    app.message = f"disabled {', '.join(names)}"


def _home_unhomed(app: MonitorApp) -> None:
    """``h``: start homing every enabled, idle joint not yet homed."""
    names = app.start_homing()
    app.message = f"homing {', '.join(names)}" if names else "nothing to home (enable the arm first: e)"


def _abort_homing(app: MonitorApp) -> None:
    """``a``: abort every running homing."""
    aborted = app.session.arm.abort_homing(app.session.arm.names)
    for name in aborted:
        app.homing_since.pop(name, None)
    app.message = f"aborted homing of {', '.join(aborted)}" if aborted else "no homing is running"


def _reset_stats(app: MonitorApp) -> None:
    """``r``: zero the since-reset bus counters."""
    app.reset_stats()
    app.message = "bus statistics reset"


#: What each key of :data:`KEYS` does.
_KEY_ACTIONS: dict[str, Callable[[MonitorApp], None]] = {
    "e": _enable_all,
    "d": _disable_all,
    "h": _home_unhomed,
    "a": _abort_homing,
    "r": _reset_stats,
    "q": _quit,
}


# ------------------------------------------------------------------ loop
class TerminalKeys:
    """Keys typed at a terminal, read without waiting (cbreak mode while open).

    Args:
        stream: The terminal's input (``sys.stdin``).
    """

    def __init__(self, stream: TextIO) -> None:
        """Put the terminal into cbreak mode (restored by :meth:`close`)."""
        import termios
        import tty

        self._fd = stream.fileno()
        self._saved = termios.tcgetattr(self._fd)
        tty.setcbreak(self._fd, termios.TCSANOW)  # keep keys typed ahead

    def read(self) -> str:
        """The keys typed since the last call ("" if none)."""
        keys = ""
        while select.select([self._fd], [], [], 0)[0]:
            chunk = os.read(self._fd, 64)
            if not chunk:
                break
            keys += chunk.decode(errors="ignore")
        return keys

    def close(self) -> None:
        """Restore the terminal's mode, if the terminal is still there (after a SIGHUP it is not)."""
        import termios

        with contextlib.suppress(termios.error):
            termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)


@contextlib.contextmanager
def key_source(stream: TextIO | None = None) -> Iterator[TerminalKeys | None]:
    """:class:`TerminalKeys` on ``stream`` (stdin) if it is a terminal, else ``None``."""
    stream = sys.stdin if stream is None else stream
    try:
        interactive = stream.isatty()
    except (AttributeError, ValueError, OSError):
        interactive = False
    if not interactive:
        yield None
        return
    keys = TerminalKeys(stream)
    try:
        yield keys
    finally:
        keys.close()


def run_monitor(
    app: MonitorApp,
    console: Console,
    keys: TerminalKeys | None,
    duration_s: float | None = None,
    clock: Clock | None = None,
) -> None:
    """Refresh the dashboard at ``app.rate_hz`` until ``q`` or ``duration_s`` wall seconds.

    Args:
        app: The dashboard's state.
        console: Where to draw.
        keys: Key source, ``None`` without a terminal.
        duration_s: Stop after this long (``None``: until ``q``).
        clock: Wall clock for pacing (injectable for tests).
    """
    clock = clock or WallClock()
    period = 1.0 / app.rate_hz
    start = clock.now()
    end = math.inf if duration_s is None else start + duration_s
    deadline = start + period
    with Live(render_dashboard(app.snapshot()), console=console, auto_refresh=False) as live:
        while app.running:
            for key in keys.read() if keys is not None else "":
                handle_key(app, key)
            if not app.running:
                break
            app.step(min(period, max(end - clock.now(), 0.0)))  # a slow rate's period ends at the end
            live.update(render_dashboard(app.snapshot()), refresh=True)
            now = clock.now()
            if now >= end:
                break
            if deadline > now:
                clock.sleep(min(deadline, end) - now)
                deadline += period
            else:
                deadline = now + period
    if not console.is_terminal:
        console.line()  # Live leaves the last frame without a newline when not a terminal
