"""Recorded trials of joint angles, read for `jitdyn replay`: OpenSim's .mot and .sto, C3D (the
angle outputs Vicon's Plug-in Gait stores as points, through ezc3d) and CSV with a header::

    trial = read_trial(Path("walk.mot"))   # Trial: column names, times (T,), values (T, C)

A file that is not what its name says is refused with one line naming the file and what is wrong.
Every column keeps its file's name; a Plug-in Gait angle's component is also known by the motion
it measures (`RKneeAngles.x` is `knee_flexion_r`, PLUG_IN_GAIT), so that it maps by name.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from jitdyn.cli.extras import require_extra
from jitdyn.errors import InvalidArgument

__all__ = ["FORMATS", "PLUG_IN_GAIT", "Trial", "read_trial"]

# Plug-in Gait's angle outputs, a point each (x, y, z = its three Cardan angles, in degrees), and
# the motion each component measures, positive as named (Vicon's "Lower body angles as output
# from Plug-in Gait"); a side's point is L... or R..., its motion ends _l or _r.
PLUG_IN_GAIT: Final = {
    "PelvisAngles": ("pelvis_tilt", "pelvis_obliquity", "pelvis_rotation"),  # anterior, upward, internal
    "HipAngles": ("hip_flexion", "hip_adduction", "hip_rotation"),  # rotation: internal
    "KneeAngles": ("knee_flexion", "knee_varus", "knee_rotation"),  # rotation: internal
    "AnkleAngles": ("ankle_flexion", "ankle_inversion", "ankle_rotation"),  # flexion: dorsiflexion
}
_AXES: Final = ("x", "y", "z")


@dataclass(frozen=True)
class Trial:
    """One recording: `values` (T, C) of `columns` at `times` (T,) in seconds. `degrees`: whether
    its rotations are in degrees (`units` says what made it so); `aliases` are other names of
    columns (a Plug-in Gait component's motion); `ignored` says what of the file is not a column."""

    path: Path
    columns: tuple[str, ...]
    times: np.ndarray
    values: np.ndarray
    degrees: bool
    units: str
    aliases: dict[str, str] = field(default_factory=dict)
    ignored: str = ""

    def between(self, start: float | None, end: float | None) -> Trial:
        """The samples from `start` to `end` (seconds on the file's clock, None: its first or last);
        InvalidArgument when fewer than 2 remain."""
        keep = np.ones(self.times.shape, dtype=bool)
        if start is not None:
            keep &= self.times >= start - 1e-9
        if end is not None:
            keep &= self.times <= end + 1e-9
        if keep.sum() < 2:
            raise InvalidArgument(
                f"{self.path}: {keep.sum()} samples between {start if start is not None else self.times[0]:g} s "
                f"and {end if end is not None else self.times[-1]:g} s; its samples run from "
                f"{self.times[0]:g} s to {self.times[-1]:g} s"
            )
        return dataclasses.replace(self, times=self.times[keep], values=self.values[keep])

    def find(self, name: str) -> int | None:
        """The index of the column called `name`, or known by it; None when there is none."""
        for i, column in enumerate(self.columns):
            if name in (column, self.aliases.get(column)):
                return i
        return None


def read_trial(path: Path) -> Trial:
    """The trial in `path`, read by its extension (FORMATS); InvalidArgument when it is not one."""
    reader = FORMATS.get(path.suffix.lower())
    if reader is None:
        raise InvalidArgument(
            f"{path}: replay reads {', '.join(FORMATS)} files, not {path.suffix or 'a file without an extension'!r}"
        )
    if not path.is_file():
        raise InvalidArgument(f"{path}: no such file")
    trial = reader(path)
    if trial.values.shape[0] < 2:
        raise InvalidArgument(f"{path}: {trial.values.shape[0]} samples; replay needs at least 2")
    if trial.values.shape[1] == 0:
        raise InvalidArgument(f"{path}: no column of angles besides time")
    if not np.all(np.isfinite(trial.times)) or np.any(np.diff(trial.times) <= 0):
        raise InvalidArgument(f"{path}: its times must increase from sample to sample")
    return trial


def _text(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as error:
        raise InvalidArgument(f"{path}: not a text file (byte {error.start} is not UTF-8)") from None


def _numbers(path: Path, rows: list[tuple[int, list[str]]], *, width: int) -> np.ndarray:
    """(T, width) floats of `rows` (line number, cells); InvalidArgument naming the line of the
    first that is not a row of `width` numbers."""
    values = np.empty((len(rows), width))
    for i, (line, cells) in enumerate(rows):
        if len(cells) != width:
            raise InvalidArgument(
                f"{path}, line {line}: {len(cells)} values where the header names {width} columns"
            )
        try:
            values[i] = [float(cell) for cell in cells]
        except ValueError:
            shown = " ".join(cells)[:80]
            raise InvalidArgument(f"{path}, line {line}: not a row of numbers: {shown!r}") from None
    return values


def _time_first(path: Path, names: list[str], values: np.ndarray, *, units: str, degrees: bool) -> Trial:
    lowered = [name.strip().lower() for name in names]
    where = next((lowered.index(name) for name in ("time", "t") if name in lowered), None)
    if where is None:
        raise InvalidArgument(f"{path}: no time column (a column named time or t, in seconds)")
    keep = [i for i in range(len(names)) if i != where]
    return Trial(
        path=path,
        columns=tuple(names[i].strip() for i in keep),
        times=values[:, where],
        values=values[:, keep],
        degrees=degrees,
        units=units,
    )


def _read_storage(path: Path) -> Trial:
    """OpenSim's storage format (.mot, .sto): `key=value` lines up to `endheader`, a line of
    column labels, then rows of numbers separated by tabs or spaces."""
    lines = _text(path)
    end = next((i for i, line in enumerate(lines) if line.strip().lower() == "endheader"), None)
    if end is None:
        raise InvalidArgument(
            f"{path}: no 'endheader' line; an OpenSim .mot or .sto file has a header that ends with one"
        )
    header = dict(line.strip().partition("=")[::2] for line in lines[:end] if "=" in line)
    in_degrees = header.get("inDegrees", "").strip().lower()
    if in_degrees not in ("yes", "no", ""):
        raise InvalidArgument(f"{path}: inDegrees={header['inDegrees']}: expected yes or no")
    body = [(number, line) for number, line in enumerate(lines[end + 1 :], end + 2) if line.strip()]
    if not body:
        raise InvalidArgument(f"{path}: no column labels after 'endheader'")
    labels = body[0][1]
    names = labels.split("\t") if "\t" in labels else labels.split()
    values = _numbers(path, [(number, line.split()) for number, line in body[1:]], width=len(names))
    units = (
        f"inDegrees={in_degrees}" if in_degrees else "no inDegrees in the header: radians, OpenSim's default"
    )
    return _time_first(path, names, values, units=units, degrees=in_degrees == "yes")


def _read_csv(path: Path) -> Trial:
    """CSV with a header row: a time column (`time` or `t`, seconds) and one column per angle."""
    rows = [
        (number, row)
        for number, row in enumerate(csv.reader(_text(path)), 1)
        if any(cell.strip() for cell in row)
    ]
    if not rows:
        raise InvalidArgument(f"{path}: empty; replay needs a header row and rows of numbers")
    names = rows[0][1]
    if all(_is_number(cell) for cell in names):
        raise InvalidArgument(
            f"{path}: the first row is numbers; a CSV needs a header row naming its columns"
        )
    values = _numbers(path, rows[1:], width=len(names))
    return _time_first(
        path, names, values, units="radians, a CSV's default (--angles deg if not)", degrees=False
    )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_c3d(path: Path) -> Trial:
    """The angle outputs of a C3D (`_angle_points`); each point is three columns, NAME.x, NAME.y,
    NAME.z, in POINT:ANGLE_UNITS (degrees when it is not given, as Plug-in Gait writes them). The
    markers and other points are left out, and said so."""
    require_extra("ezc3d", what="ezc3d (C3D files)", extra="lab")
    import ezc3d

    try:
        c3d = ezc3d.c3d(str(path))
    except (OSError, RuntimeError, ValueError, IndexError) as error:  # its C++ errors, as Python's
        raise InvalidArgument(f"{path}: not a C3D file ezc3d reads ({error})") from None
    point = c3d["parameters"]["POINT"]
    labels = [str(label).strip() for label in point["LABELS"]["value"]]
    names = _angle_points(point, labels)
    if not names:
        raise InvalidArgument(
            f"{path}: no angle outputs among its {len(labels)} points (POINT:ANGLES, labels ending in "
            "'Angles' such as Plug-in Gait's LKneeAngles, or Vicon's modeled angles)"
        )
    units = [str(u).strip().lower() for u in point.get("ANGLE_UNITS", {}).get("value", [])]
    if units and units[0] not in ("deg", "rad"):
        raise InvalidArgument(f"{path}: POINT:ANGLE_UNITS is {units[0]!r}; expected deg or rad")
    data = np.asarray(c3d["data"]["points"])  # (4, points, frames)
    columns: list[str] = []
    aliases: dict[str, str] = {}
    for name in names.values():
        for axis, component in enumerate(_AXES):
            columns.append(f"{name}.{component}")
            if _plug_in_gait(name, axis):
                aliases[columns[-1]] = _plug_in_gait(name, axis)
    rate = float(c3d["header"]["points"]["frame_rate"])
    first = int(c3d["header"]["points"]["first_frame"])
    others = len(labels) - len(names)
    return Trial(
        path=path,
        columns=tuple(columns),
        times=(first + np.arange(data.shape[2])) / rate,
        values=np.hstack([data[:3, i, :].T for i in names]),
        degrees=not units or units[0] == "deg",
        units=f"POINT:ANGLE_UNITS {units[0]}"
        if units
        else "no POINT:ANGLE_UNITS: degrees, as Plug-in Gait writes them",
        aliases=aliases,
        ignored=f"{others} point{'s' if others > 1 else ''} not angles (markers, forces, moments, ...)"
        if others
        else "",
    )


def _angle_points(point: dict[str, Any], labels: list[str]) -> dict[int, str]:
    """{point index: name} of the angle outputs: the points POINT:ANGLES lists, those whose label
    ends in `Angles` (Plug-in Gait's), and Vicon's modeled outputs whose type (the POINT parameter
    named as the label) is an angle. A point's name is the one its description gives Vicon's
    outputs (`AngArtHip_R[0]:...`), else its label without a subject's prefix (`S03:`)."""
    listed = {str(a).strip() for a in point.get("ANGLES", {}).get("value", [])}
    descriptions = [str(d) for d in point.get("DESCRIPTIONS", {}).get("value", [])]
    found = {}
    for i, label in enumerate(labels):
        kind = " ".join(str(v) for v in point.get(label, {}).get("value", [])) if label in point else ""
        if label in listed or label.endswith("Angles") or ":Angle" in kind:
            described = descriptions[i].partition("[")[0] if i < len(descriptions) else ""
            found[i] = described if described and "[" in descriptions[i] else label.rpartition(":")[2]
    return found


def _plug_in_gait(label: str, axis: int) -> str:
    """The motion of component `axis` of a Plug-in Gait angle output ('' for another point)."""
    side, rest = label[:1], label[1:]
    if side not in ("L", "R") or rest not in PLUG_IN_GAIT:
        return ""
    return f"{PLUG_IN_GAIT[rest][axis]}_{side.lower()}"


FORMATS: Final[dict[str, Callable[[Path], Trial]]] = {
    ".mot": _read_storage,
    ".sto": _read_storage,
    ".c3d": _read_c3d,
    ".csv": _read_csv,
}


def rate_of(trial: Trial) -> float:
    """Samples a second, from the median step; InvalidArgument when the steps are not even."""
    steps = np.diff(trial.times)
    step = float(np.median(steps))
    worst = int(np.argmax(np.abs(steps - step)))
    if abs(steps[worst] - step) > 0.01 * step:
        raise InvalidArgument(
            f"{trial.path}: its samples are not evenly spaced (a step of {steps[worst]:g} s after "
            f"t = {trial.times[worst]:g} s, where most are {step:g} s); replay needs a constant rate"
        )
    return 1.0 / step if math.isfinite(step) and step > 0 else math.nan
