"""The simulated curve over the real one: one PNG per recording (matplotlib, the ``[validate]`` extra)."""

from __future__ import annotations

import errno
import os
import shutil
import stat
import tempfile
from pathlib import Path

import numpy as np

from bioscara_gym.fsutil import atomic_write_bytes, output_problem, replace_problem, replaced_path
from bioscara_gym.validation import Validation
from bioscara_gym.validation.recordings import (
    DATA_DIR,
    HANDLER_TIMES_PREFIX,
    TRACKING_NOT_READ,
    recording_files,
    recording_name,
)

__all__ = ["PNG_KIND", "StagedPlots", "is_png", "plot_names", "plot_problem", "stage_plots", "write_plots"]

#: Each drawn folder of recordings and the start of its pictures' names (``maxAccel_j1_3.png``).
_PREFIX = {
    "maxAccel": "maxAccel",
    "settingMaxVal": "settingMaxVal",
    "high_speed_stall_test": "stall",
    "tracking_error": "tracking",
    "RW_test": "RW",
}
#: What a picture replaces (:func:`~bioscara_gym.fsutil.replace_problem`).
PNG_KIND = "a PNG image"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _name(folder: str, recording: str) -> str:
    return f"{_PREFIX[folder]}_{recording}.png"


def plot_names(root: Path | str | None = None) -> list[str]:
    """The names of the pictures the recordings under ``root`` may get (default: the packaged ones).

    One per recording of a kind that is drawn, whether or not it is replayed
    (known from the file names alone, before any work).
    """
    names = set()
    for path in recording_files(root if root is not None else DATA_DIR):
        folder, recording = path.parent.name, recording_name(path)
        if folder not in _PREFIX:
            continue
        if folder == "tracking_error" and recording.endswith(TRACKING_NOT_READ):
            continue
        if folder == "RW_test" and recording.startswith(HANDLER_TIMES_PREFIX):
            continue
        names.add(_name(folder, recording))
    return sorted(names)


def is_png(path: Path) -> bool:
    """Whether ``path`` starts as a PNG image does (what ``--plots`` may replace).

    Raises:
        OSError: It cannot be read.
    """
    with open(path, "rb") as f:
        return f.read(len(_PNG_SIGNATURE)) == _PNG_SIGNATURE


def plot_problem(path: Path) -> str | None:
    """Why the picture ``path`` cannot be written (replaced, or written through its symlink), or ``None``.

    A picture replaces only nothing, an empty file or a PNG image; a symlink
    is written through to its target (as every output of the package), so
    the target is judged.
    """
    there = "a picture is written there: move it, or give another folder"
    through = f"is a symlink to {os.path.realpath(path)}, which " if path.is_symlink() else ""
    try:
        st = os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a loop of symlinks"
        st = None
    if st is not None and stat.S_ISDIR(st.st_mode):
        return f"{through}is a folder; {there}"
    if st is not None and not stat.S_ISREG(st.st_mode):
        return f"{through}is not a regular file; {there}"
    if through:
        problem = output_problem(replaced_path(path), parents=True)
        if problem is not None:
            return f"{through}{problem}"
    problem = replace_problem(path, PNG_KIND, is_png)
    if problem is not None and problem.startswith("exists and is not"):
        return f"{through}exists and is not {PNG_KIND}; {there}"
    return None if problem is None else f"{through}{problem}"


_REAL = {"color": "black", "lw": 1.2, "label": "real arm"}
_SIM = {"color": "tab:orange", "lw": 1.2, "label": "simulated"}


def _figure(rows: int, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, 1, figsize=(9, 2.6 * rows), sharex=True, squeeze=False)
    fig.suptitle(title, fontsize=10)
    return plt, fig, axes[:, 0]


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp")
    fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    tmp.replace(path)
    return path


def _replayed(v: Validation, kind: str) -> list[tuple]:
    """(recording, its replay) of every recording of ``kind`` that was replayed.

    Not every recording is: a joint that cannot home has none (its
    ``homing/`` row says so), nor a settingMaxVal profile that did not move,
    nor an RW_test file of another host pattern.
    """
    sims = v.replays.get(kind, {})
    return [(r, sims[r.name]) for r in getattr(v.recordings, kind) if r.name in sims]


def _max_accel(v: Validation, out: Path) -> list[Path]:
    paths = []
    for run, sim in _replayed(v, "max_accel"):
        plt, fig, (ax1, ax2) = _figure(
            2,
            f"maxAccel/{run.name}: {run.joint}, {run.max_velocity:g} at "
            f"{run.max_acceleration:g}, {run.current:g} % current",
        )
        ax1.plot(sim.t, run.q - run.q[0], **_REAL)
        ax1.plot(sim.t, sim.q - sim.q[0], **_SIM)
        ax1.set_ylabel("moved")
        ax2.plot(sim.t, run.qd, **_REAL)
        ax2.plot(sim.t, sim.qd, **_SIM)
        ax2.set_ylabel("speed (encoder estimate)")
        ax2.set_xlabel("time, s (the program's sleeps and transactions)")
        ax1.legend(loc="upper left", fontsize=8)
        paths.append(_save(plt, fig, out / _name("maxAccel", run.name)))
    return paths


def _setting_max_val(v: Validation, out: Path) -> list[Path]:
    paths = []
    for run, sim in _replayed(v, "setting_max_val"):
        plt, fig, (ax1, ax2) = _figure(2, f"settingMaxVal/{run.name}")
        ax1.plot(run.t, run.position - run.position[0], **_REAL)
        ax1.plot(sim.t, sim.position, **_SIM)
        ax1.set_ylabel("motor deg")
        ax2.plot(run.t, run.velocity, **_REAL)
        ax2.plot(sim.t, sim.velocity, **_SIM)
        ax2.set_ylabel("deg/s")
        ax2.set_xlabel("time, s")
        ax1.legend(loc="upper left", fontsize=8)
        paths.append(_save(plt, fig, out / _name("settingMaxVal", run.name)))
    return paths


def _stall(v: Validation, out: Path) -> list[Path]:
    paths = []
    for sig, sim in _replayed(v, "stall_signal"):
        t = sig.t - sig.t[0]
        plt, fig, (ax1, ax2, ax3) = _figure(3, f"high_speed_stall_test/{sig.name}")
        ax1.plot(t, np.clip(sig.raw, 0, 500), ".", ms=1.5, color="black", label="real raw |PID error|")
        ax1.plot(sim.t, np.clip(sim.raw, 0, 500), ".", ms=1.5, color="tab:orange", label="simulated raw")
        ax1.set_ylabel("1/256 µsteps")
        ax1.legend(loc="upper left", fontsize=8, markerscale=6)
        ax2.plot(t, sig.filtered, color="black", lw=1, label="real filtered")
        ax2.plot(sim.t, sim.filtered, color="tab:orange", lw=1, label="simulated filtered")
        ax2.plot(t, sig.threshold, color="tab:red", lw=0.8, ls="--", label="threshold")
        for trip in t[sig.stalled > 0]:
            ax2.axvline(trip, color="black", lw=0.8, ls=":")
        for trip in sim.t[sim.stalled > 0]:
            ax2.axvline(trip, color="tab:orange", lw=0.8, ls=":")
        ax2.legend(loc="upper left", fontsize=8)
        ax3.plot(t, sig.speed, **_REAL)
        ax3.plot(sim.t, sim.speed, **_SIM)
        ax3.plot(t, sig.set_speed, color="grey", lw=0.8, ls="--", label="set speed")
        ax3.set_ylabel("motor rad/s")
        ax3.set_xlabel("time, s")
        ax3.legend(loc="upper left", fontsize=8)
        paths.append(_save(plt, fig, out / _name("high_speed_stall_test", sig.name)))
    return paths


def _tracking(v: Validation, out: Path) -> list[Path]:
    paths = []
    for run, sim in _replayed(v, "tracking"):
        plt, fig, (ax1, ax2) = _figure(2, f"tracking_error/{run.name}")
        ax1.plot(run.t, run.reference, color="grey", lw=0.8, ls="--", label="reference")
        ax1.plot(run.t, run.feedback, **_REAL)
        ax1.plot(sim.t, sim.feedback, **_SIM)
        ax1.set_ylabel("j1, rad")
        ax1.legend(loc="upper left", fontsize=8)
        ax2.plot(run.t, (run.reference - run.feedback) / run.ramp_speed, **_REAL)
        ax2.plot(sim.t, (sim.reference - sim.feedback) / run.ramp_speed, **_SIM)
        ax2.set_ylabel("(r - q) / ramp, s")
        ax2.set_xlabel("time, s")
        paths.append(_save(plt, fig, out / _name("tracking_error", run.name)))
    return paths


def _transactions(v: Validation, out: Path) -> list[Path]:
    paths = []
    for tr, sim in _replayed(v, "transactions"):
        plt, fig, (ax1, ax2) = _figure(2, f"RW_test/{tr.name}: time per call")
        for ax, kind, values in ((ax1, "read", tr.read_us), (ax2, "write", tr.write_us)):
            ax.hist(np.clip(values, 0, 3000), bins=80, color="grey", label=f"real {kind} calls")
            ax.axvline(float(np.mean(values)), color="black", lw=1.2, label="real mean")
            ax.axvline(sim[kind], color="tab:orange", lw=1.5, label="simulated")
            ax.legend(loc="upper right", fontsize=8)
        ax2.set_xlabel("µs")
        paths.append(_save(plt, fig, out / _name("RW_test", tr.name)))
    return paths


class StagedPlots:
    """Pictures drawn into a hidden folder of ``out``, not yet in place: :meth:`commit` or :meth:`discard`.

    Lets a command write its other outputs between drawing and committing,
    so that a failure of any leaves none of them behind.
    """

    def __init__(self, out: Path, drawing: Path, drawn: list[Path], made: bool) -> None:
        """Hold what :func:`stage_plots` drew."""
        self.out, self._drawing, self._drawn, self._made = out, drawing, drawn, made

    def problem(self) -> str | None:
        """Why a picture cannot go into place (its path, then :func:`plot_problem`), or ``None``."""
        for p in self._drawn:
            dest = self.out / p.name
            problem = plot_problem(dest)
            if problem is not None:
                return f"{dest} {problem}"
        return None

    def commit(self) -> list[Path]:
        """Move every picture into ``out`` (through a symlink there, to its target); returns their paths.

        Every place is checked first (:meth:`problem`): a picture that cannot go
        into place leaves none moved. An error names the picture's path in
        ``out``, not the hidden one.

        Raises:
            OSError: A picture could not be moved into place (the drawn ones
                are removed, and ``out`` too if it was made for them).
        """
        try:
            problem = self.problem()
            if problem is not None:
                raise OSError(errno.EEXIST, problem)
            paths = []
            for p in self._drawn:
                dest = self.out / p.name
                try:
                    if dest.is_symlink():  # written through, as every output (fsutil.replaced_path)
                        atomic_write_bytes(dest, p.read_bytes())
                        p.unlink()
                    else:
                        p.replace(dest)
                except OSError as e:
                    raise OSError(e.errno, e.strerror, os.fspath(dest)) from e
                paths.append(dest)
        except BaseException:
            self.discard()
            raise
        self._drawing.rmdir()
        return paths

    def discard(self) -> None:
        """Remove the drawn pictures (and ``out``, if it was made for them)."""
        shutil.rmtree(self._drawing, ignore_errors=True)
        if self._made:
            shutil.rmtree(self.out, ignore_errors=True)


def stage_plots(v: Validation, out: Path | str) -> StagedPlots:
    """Draw one PNG per replayed recording into a hidden folder inside ``out`` (created).

    Raises:
        MissingExtraError: matplotlib is not installed (the ``[validate]`` extra).
    """
    from bioscara_gym.hardware.errors import require_extra

    require_extra("matplotlib", "--plots", "validate")
    out = Path(out)
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    drawing = Path(tempfile.mkdtemp(dir=out, prefix=".drawing-"))
    staged = StagedPlots(out, drawing, [], made)
    try:
        for kind, draw in (
            ("max_accel", _max_accel),
            ("setting_max_val", _setting_max_val),
            ("stall_signal", _stall),
            ("tracking", _tracking),
            ("transactions", _transactions),
        ):
            if kind in v.replays:
                staged._drawn += draw(v, drawing)
    except BaseException:
        staged.discard()
        raise
    return staged


def write_plots(v: Validation, out: Path | str) -> list[Path]:
    """One PNG per replayed recording into ``out`` (created); returns the paths.

    All or none: the pictures are drawn into a hidden folder inside ``out``
    and moved into place once every one is drawn (seen: SIGTERM left 4 to 37
    of 41); an interrupted or failed run leaves ``out`` as it was. A
    recording that was not replayed (its joint cannot home) has none.

    Raises:
        MissingExtraError: matplotlib is not installed (the ``[validate]`` extra).
    """
    return stage_plots(v, out).commit()
