"""The simulated arm judged by the real arm's own recordings.

``bioscara validate`` and ``bioscara calibrate`` are thin commands on this
package (:mod:`~bioscara_gym.validation.commands`):

* :mod:`~.recordings`: a reader per recording kind, in the layout of the
  arm repository's ``test/`` folder (the packaged recordings, or a user's);
* :mod:`~.rig`: one simulated joint behind the real driver on the emulated
  bus, driven as the arm's test programs drove the real one;
* :mod:`~.experiments`: a replay and a comparison per kind (``maxAccel``,
  ``settingMaxVal``, the stall signal, tracking, bus timing);
* :mod:`~.report`: the table of rows (what, real, simulated, error, bound,
  verdict) and its JSON;
* :mod:`~.plots`: the simulated curve over the real one, a PNG per recording;
* :mod:`~.calibrate`: the fit of the model's free parameters.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from bioscara_gym.hardware.config import ArmConfig, load_config
from bioscara_gym.validation.recordings import Recordings, find_recordings
from bioscara_gym.validation.report import Row

__all__ = ["Validation", "validate"]


@dataclass
class Validation:
    """Everything a validation produced: the rows, and each replay by kind and name (for the plots)."""

    recordings: Recordings
    rows: list[Row] = field(default_factory=list)
    replays: dict[str, dict[str, object]] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        """Whether every row passed."""
        return all(r.passed for r in self.rows)


def _without_unhomable_joints(rec: Recordings, config: ArmConfig, rows: list[Row]) -> Recordings:
    """``rec`` less the recordings of joints whose drive cannot home; a failing row for each of those.

    Every program homed its joint first; a drive that cannot (a calibration
    gone wrong, a hand-edited drive block) has nothing to replay.
    """
    from bioscara_gym.validation.rig import JointRig, RigError

    joints = {r.joint for kind in (rec.max_accel, rec.stall_signal) for r in kind}
    if rec.tracking or rec.transactions:
        joints.add("j1")  # tracking_error/ and RW_test/ replay on j1
    failed = set()
    for joint in sorted(joints & set(config.names)):
        try:
            JointRig(config, joint)
        except RigError as e:
            failed.add(joint)
            rows.append(
                Row.verdict(
                    f"homing/{joint}", "homes at its configured homing parameters", "yes", str(e), False
                )
            )
    if not failed:
        return rec
    keep = {
        name: [r for r in value if not (isinstance(getattr(r, "joint", None), str) and r.joint in failed)]
        for name, value in vars(rec).items()
        if name != "root"
    }
    if "j1" in failed:
        keep["tracking"], keep["transactions"], keep["handler_times"] = [], [], []
    return dataclasses.replace(rec, **keep)


def validate(root: Path | str | None = None, config: ArmConfig | None = None) -> Validation:
    """Replay every recording under ``root`` (default: the packaged ones) on the simulated arm.

    Args:
        root: A folder laid out like the arm repository's ``test/``.
        config: The arm configuration whose drive models and bus timing to
            judge (default: the packaged, calibrated one).

    Raises:
        RecordingError: ``root`` holds no recordings, or one cannot be read.
    """
    from bioscara_gym.validation.experiments import max_accel, rw, setting_max_val, stall, tracking

    config = config or load_config()
    rec = find_recordings(root)
    out = Validation(rec)
    rec = _without_unhomable_joints(rec, config, out.rows)
    if rec.max_accel:
        rows, sims = max_accel.run_all(rec.max_accel, config)
        out.rows += rows
        out.replays["max_accel"] = sims
    if rec.setting_max_val:
        rows, sims = setting_max_val.run_all(rec.setting_max_val)
        out.rows += rows
        out.replays["setting_max_val"] = sims
    if rec.stall_signal:
        rows, sims = stall.run_all(rec.stall_signal, config)
        out.rows += rows
        out.replays["stall_signal"] = sims
    if rec.tracking:
        rows, sims = tracking.run_all(rec.tracking, config)
        out.rows += rows
        out.replays["tracking"] = sims
    if rec.transactions or rec.handler_times:
        rows, sims = rw.run_all(rec.transactions, rec.handler_times, config)
        out.rows += rows
        out.replays["transactions"] = sims
    return out
