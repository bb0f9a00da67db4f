"""Units, numbers and flags as the console prints them (status table and dashboard alike)."""

from __future__ import annotations

from rich.text import Text

from bioscara_gym.hardware.registers import Flag

#: Style of each flag, in the order flags are listed.
FLAG_STYLES: tuple[tuple[Flag, str], ...] = (
    (Flag.STALL, "bold red"),
    (Flag.BUSY, "yellow"),
    (Flag.NOT_HOMED, "magenta"),
    (Flag.NOT_ENABLED, "dim"),
)


def joint_unit(joint_type: str) -> str:
    """Position unit of a joint type: ``rad`` (revolute) or ``m`` (prismatic)."""
    return "m" if joint_type == "prismatic" else "rad"


def format_position(value: float | None, unit: str) -> str:
    """``"+1.2346 rad"``, or ``"-"`` when unknown (not homed)."""
    return "-" if value is None else f"{_unsigned_zero(value):+.4f} {unit}"


def format_velocity(value: float, unit: str) -> str:
    """``"+0.0300 rad/s"``; values that round to zero show as ``+0.0000``."""
    return f"{_unsigned_zero(value):+.4f} {unit}/s"


def _unsigned_zero(value: float, digits: int = 4) -> float:
    """``value`` rounded to ``digits``, with ``-0.0`` shown as ``0.0``."""
    rounded = round(value, digits)
    return 0.0 if rounded == 0 else rounded


def flags_text(flags: Flag | int) -> Text:
    """The set flags by name, each in its colour; ``OK`` in green when none is set."""
    flags = Flag(flags)
    text = Text()
    for flag, style in FLAG_STYLES:
        if flags & flag:
            if text:
                text.append(" ")
            text.append(str(flag.name), style=style)
    return text if text else Text("OK", style="green")
