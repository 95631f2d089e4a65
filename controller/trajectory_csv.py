"""Trajectories recorded or planned elsewhere: a CSV file read into smooth splines.

File format (UTF-8 text, comma-separated, one header line naming the columns, any order;
blank lines and lines starting with ``#`` are skipped):

- required: ``t_s, x_m, y_m, z_m`` (time and O_B position, world frame, z up);
- optional attitude, either ``qw, qx, qy, qz`` (body -> world, normalised on load) or
  ``roll_deg, pitch_deg, yaw_deg`` (``R = Rz(yaw) Ry(pitch) Rx(roll)``), never both;
- optional ``alpha_deg``: the tilt reference (linear between rows; the tilt planner
  rate-limits it anyway).

Interpolation: a cubic spline through the positions with clamped ends (zero velocity at the
first and last row, where the vehicle joins and leaves its neighbouring segments at rest), so
position, velocity and acceleration are continuous; v and a are the spline's exact first and
second derivatives (no finite differences). The attitude is splined the same way as unwrapped
ZYX Euler angles; the body angular velocity follows from the angles and their rates.

Checked on load, each error naming file, line and column (``FILE:LINE: column N (NAME):
expectation``): the header (required, unknown and duplicate columns), the number of fields per
row, finite numbers, strictly increasing time, unit-ish quaternions, |pitch| < 85 deg, alpha in
[0, 90] deg, and the speed, acceleration and angular-rate caps of the mission module evaluated on
the spline (the row that starts the offending interval).
"""

from __future__ import annotations

import bisect
import contextlib
import contextvars
import csv
import io
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from config.schema import ConfigError
from controller.reference import Quat, Vec3, euler_zyx_from_rot, quat_from_euler_zyx, quat_to_rot

#: largest CSV read (bytes): ten minutes at 500 Hz with every column is ~30 MB
MAX_CSV_BYTES = 32 * 1024 * 1024
#: a ZYX Euler spline is singular at |pitch| = 90 deg; a multirotor never flies near it
MAX_PITCH_DEG = 85.0
#: evaluation points per spline interval when checking the caps
_CHECK_POINTS = 8

REQUIRED = ("t_s", "x_m", "y_m", "z_m")
QUAT = ("qw", "qx", "qy", "qz")
EULER = ("roll_deg", "pitch_deg", "yaw_deg")
KNOWN = REQUIRED + QUAT + EULER + ("alpha_deg",)

_base_dir: contextvars.ContextVar[Path | None] = contextvars.ContextVar("mission_base_dir",
                                                                       default=None)


@contextlib.contextmanager
def mission_base_dir(directory: Path) -> Iterator[None]:
    """Resolve trajectory files relative to ``directory`` (the mission file's folder) while
    a mission is being loaded."""
    token = _base_dir.set(directory)
    try:
        yield
    finally:
        _base_dir.reset(token)


def resolve_trajectory_path(name: str) -> Path:
    path = Path(name)
    base = _base_dir.get()
    return path if path.is_absolute() or base is None else base / path


@dataclass(frozen=True)
class Limits:
    """The caps a trajectory must respect (the mission module's)."""

    max_speed_m_s: float
    max_accel_m_s2: float
    max_rate_deg_s: float


class _Cubic:
    """A piecewise cubic in plain floats: per interval, per channel, Horner coefficients."""

    def __init__(self, spline: CubicSpline) -> None:
        self.x = [float(v) for v in spline.x]
        c = np.asarray(spline.c)  # (4, n-1, channels): c[k] multiplies (t - x_i)^(3-k)
        self.coeffs = [[tuple(float(c[k, i, ch]) for k in range(4)) for ch in range(c.shape[2])]
                       for i in range(c.shape[1])]

    def eval(self, t: float) -> list[tuple[float, float, float]]:
        """(value, first, second derivative) per channel; clamped to the end rows."""
        t = min(max(t, self.x[0]), self.x[-1])
        i = min(max(bisect.bisect_right(self.x, t) - 1, 0), len(self.coeffs) - 1)
        h = t - self.x[i]
        out = []
        for c3, c2, c1, c0 in self.coeffs[i]:
            out.append((((c3 * h + c2) * h + c1) * h + c0, (3.0 * c3 * h + 2.0 * c2) * h + c1,
                        6.0 * c3 * h + 2.0 * c2))
        return out


class TrajectoryTable:
    """A loaded trajectory: ``eval(t)`` from 0 (the first row) to :attr:`duration_s`."""

    def __init__(self, path: str, t_s: list[float], pos_w_m: list[Vec3],
                 euler_rad: list[Vec3] | None, alpha_deg: list[float] | None) -> None:
        self.path = path
        t0 = t_s[0]
        self.t_s = [t - t0 for t in t_s]
        self.duration_s = self.t_s[-1]
        self.first_w_m = pos_w_m[0]
        self._pos = _Cubic(CubicSpline(self.t_s, np.array(pos_w_m), bc_type="clamped"))
        self._att = None if euler_rad is None else _Cubic(
            CubicSpline(self.t_s, np.unwrap(np.array(euler_rad), axis=0), bc_type="clamped"))
        self.alpha_deg = alpha_deg
        self.has_attitude = euler_rad is not None
        #: the file's line of each row and the alpha column's name, for errors found later
        #: (an alpha beyond a vehicle's tilt: the vehicle is not known when the file is read)
        self.row_lines: list[int] | None = None
        self.alpha_column = "alpha_deg"

    def eval(self, t_s: float) -> tuple[Vec3, Vec3, Vec3]:
        (x, vx, ax), (y, vy, ay), (z, vz, az) = self._pos.eval(t_s)
        return (x, y, z), (vx, vy, vz), (ax, ay, az)

    def attitude(self, t_s: float) -> tuple[Quat, Vec3]:
        """The reference attitude and its body angular velocity (ZYX Euler kinematics)."""
        assert self._att is not None
        (r, dr, _), (p, dp, _), (y, dy, _) = self._att.eval(t_s)
        sr, cr, sp, cp = math.sin(r), math.cos(r), math.sin(p), math.cos(p)
        omega = (dr - dy * sp, dp * cr + dy * sr * cp, -dp * sr + dy * cr * cp)
        return quat_from_euler_zyx(r, p, y), omega

    def alpha_rad(self, t_s: float) -> float | None:
        a = self.alpha_deg
        if a is None:
            return None
        ts = self.t_s
        if t_s <= 0.0:
            return math.radians(a[0])
        if t_s >= ts[-1]:
            return math.radians(a[-1])
        i = bisect.bisect_right(ts, t_s) - 1
        f = (t_s - ts[i]) / (ts[i + 1] - ts[i])
        return math.radians(a[i] + f * (a[i + 1] - a[i]))


def load_trajectory_csv(path: Path, limits: Limits) -> TrajectoryTable:
    """Read and check ``path``; :class:`ConfigError` naming file, line and column."""
    label = str(path)
    try:
        with path.open("rb") as f:
            data = f.read(MAX_CSV_BYTES + 1)
    except OSError as exc:
        raise ConfigError(label, None, None, f"cannot read the trajectory: {exc.strerror}"
                          ) from None
    if len(data) > MAX_CSV_BYTES:
        raise ConfigError(label, 1, None, f"file too large; expected at most "
                          f"{MAX_CSV_BYTES // (1024 * 1024)} MiB of CSV")
    try:
        text = data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise ConfigError(label, line, None, "invalid UTF-8; expected a CSV text file") from None

    rows: list[tuple[int, list[str]]] = []
    for number, fields in enumerate(csv.reader(io.StringIO(text)), 1):
        if not fields or not "".join(fields).strip() or fields[0].lstrip().startswith("#"):
            continue
        rows.append((number, [c.strip() for c in fields]))
    if not rows:
        raise ConfigError(label, 1, None, "empty file; expected a header line "
                          f"({', '.join(REQUIRED)}, ...) and at least two rows")
    header_line, header = rows[0]
    columns: dict[str, int] = {}
    for j, name in enumerate(header):
        where = f"column {j + 1} ({name})"
        if name not in KNOWN:
            raise ConfigError(label, header_line, where,
                              f"unknown column; expected some of: {', '.join(KNOWN)}")
        if name in columns:
            raise ConfigError(label, header_line, where, "duplicate column")
        columns[name] = j
    for group in (REQUIRED, QUAT, EULER):
        present = [c for c in group if c in columns]
        if (present and len(present) != len(group)) or (group is REQUIRED and not present):
            missing = [c for c in group if c not in columns]
            raise ConfigError(label, header_line, f"column {', '.join(missing)}",
                              f"missing column; expected all of {', '.join(group)}")
    if all(c in columns for c in QUAT) and all(c in columns for c in EULER):
        raise ConfigError(label, header_line, "column " + ", ".join(EULER),
                          "give the attitude once: quaternion or Euler columns, not both")
    if len(rows) < 3:
        raise ConfigError(label, rows[-1][0], None, "expected at least two rows after the header")

    def col(name: str) -> str:
        return f"column {columns[name] + 1} ({name})"

    lines: list[int] = []
    values: list[dict[str, float]] = []
    for number, fields in rows[1:]:
        if len(fields) != len(header):
            raise ConfigError(label, number, None, f"{len(fields)} fields; expected "
                              f"{len(header)} as in the header")
        row: dict[str, float] = {}
        for name, j in columns.items():
            try:
                v = float(fields[j])
            except ValueError:
                raise ConfigError(label, number, col(name),
                                  f"expected a number, got {fields[j][:40]!r}") from None
            if not math.isfinite(v):
                raise ConfigError(label, number, col(name),
                                  f"expected a finite number, got {fields[j][:40]!r}")
            row[name] = v
        if values and row["t_s"] <= values[-1]["t_s"]:
            raise ConfigError(label, number, col("t_s"), f"time {row['t_s']:g} s after "
                              f"{values[-1]['t_s']:g} s; expected strictly increasing times")
        if "alpha_deg" in row and not 0.0 <= row["alpha_deg"] <= 90.0:
            raise ConfigError(label, number, col("alpha_deg"),
                              f"expected a tilt in [0, 90] deg, got {row['alpha_deg']:g}")
        lines.append(number)
        values.append(row)

    euler: list[Vec3] | None = None
    if "qw" in columns:
        euler = []
        for number, row in zip(lines, values, strict=True):
            q = (row["qw"], row["qx"], row["qy"], row["qz"])
            n = math.sqrt(sum(c * c for c in q))
            if not 0.9 <= n <= 1.1:  # a recording's rounding, not a different quaternion
                raise ConfigError(label, number, col("qw"),
                                  f"quaternion norm {n:.3g}; expected a unit quaternion")
            r, p, y = euler_zyx_from_rot(quat_to_rot((q[0] / n, q[1] / n, q[2] / n, q[3] / n)))
            euler.append((r, p, y))
    elif "roll_deg" in columns:
        euler = [(math.radians(r["roll_deg"]), math.radians(r["pitch_deg"]),
                  math.radians(r["yaw_deg"])) for r in values]
    if euler is not None:
        for number, e in zip(lines, euler, strict=True):
            if abs(math.degrees(e[1])) >= MAX_PITCH_DEG:
                raise ConfigError(label, number, col("qw" if "qw" in columns else "pitch_deg"),
                                  f"pitch {math.degrees(e[1]):.3g} deg; expected |pitch| < "
                                  f"{MAX_PITCH_DEG:g} deg")

    table = TrajectoryTable(label, [r["t_s"] for r in values],
                            [(r["x_m"], r["y_m"], r["z_m"]) for r in values], euler,
                            [r["alpha_deg"] for r in values] if "alpha_deg" in columns else None)
    _check_caps(table, lines, limits, label, col)
    table.row_lines = list(lines)
    if "alpha_deg" in columns:
        table.alpha_column = col("alpha_deg")
    return table


def _check_caps(table: TrajectoryTable, lines: list[int], limits: Limits, label: str,
                col: Callable[[str], str]) -> None:
    """Speed, acceleration and attitude rate of the splines within the limits; the error
    names the rows where the worst excess is (a jump's overshoot crosses the limit rows
    before the jump: the first crossing named the wrong rows and a fraction of the peak)."""
    pos_cols = ", ".join(col(n) for n in ("x_m", "y_m", "z_m"))
    ts = table.t_s
    worst = {"speed": (0.0, 0), "accel": (0.0, 0), "rate": (0.0, 0)}   # value, row index
    for i in range(len(ts) - 1):
        for k in range(_CHECK_POINTS + 1):
            t = ts[i] + (ts[i + 1] - ts[i]) * k / _CHECK_POINTS
            _, v, a = table.eval(t)
            for name, value in (("speed", math.hypot(*v)), ("accel", math.hypot(*a))):
                if value > worst[name][0]:
                    worst[name] = (value, i)
            if table.has_attitude:
                rate = math.degrees(math.hypot(*table.attitude(t)[1]))
                if rate > worst["rate"][0]:
                    worst["rate"] = (rate, i)

    def where(i: int) -> str:
        return f"rows at lines {lines[i]}..{lines[i + 1]}"

    speed, i = worst["speed"]
    if speed > limits.max_speed_m_s:
        raise ConfigError(label, lines[i], pos_cols,
                          f"the spline through the {where(i)} reaches {speed:.3g} m/s; "
                          f"expected <= {limits.max_speed_m_s:g} m/s")
    accel, i = worst["accel"]
    if accel > limits.max_accel_m_s2:
        raise ConfigError(label, lines[i], pos_cols,
                          f"the spline through the {where(i)} reaches {accel:.3g} m/s^2; "
                          f"expected <= {limits.max_accel_m_s2:g} m/s^2")
    rate, i = worst["rate"]
    if rate > limits.max_rate_deg_s:
        raise ConfigError(label, lines[i], "attitude columns",
                          f"the attitude through the {where(i)} turns at {rate:.3g} "
                          f"deg/s; expected <= {limits.max_rate_deg_s:g} deg/s")
