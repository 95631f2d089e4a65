"""The numbers behind ``fasthex analyze``: the vehicle model evaluated over the tilt range.

Kept apart from the command so that tests and other tools read the same numbers the command
prints. The JSON layout is documented in the README ("fasthex analyze --json").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from controller.model import VehicleModel, cardan_tilts_rad
from controller.params import VehicleParams

JSON_SCHEMA = "fasthex.analyze"
JSON_VERSION = 1


@dataclass(frozen=True)
class TiltRow:
    """The model at one tilt angle."""

    tilt_deg: float
    rank: int
    condition_number: float
    hover_efficiency: float
    max_rotor_thrust_n: float
    max_lift_n: float
    lateral_force_radius_n: float
    cardan_error_deg: tuple[float, ...]


@dataclass(frozen=True)
class VehicleAnalysis:
    vehicle: str
    mass_kg: float
    weight_n: float
    rows: tuple[TiltRow, ...]
    lateral_bound_coeffs_n: tuple[float, float, float]
    lateral_bound_max_residual_n: float
    cardan_peak_error_deg: tuple[float, ...]
    cardan_peak_error_tilt_deg: tuple[float, ...]

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"schema": JSON_SCHEMA, "version": JSON_VERSION}
        out.update(asdict(self))
        out["rows"] = [
            {**asdict(r), "condition_number": (r.condition_number
                                               if math.isfinite(r.condition_number) else None)}
            for r in self.rows
        ]
        out["lateral_bound_fit"] = {
            "formula": "r_xy_n = c0 + c1 * tilt_deg + c2 * tilt_deg**2",
            "coeffs": list(self.lateral_bound_coeffs_n),
            "max_residual_n": self.lateral_bound_max_residual_n,
        }
        del out["lateral_bound_coeffs_n"], out["lateral_bound_max_residual_n"]
        return out


def analyze(params: VehicleParams, step_deg: float = 5.0, fit_step_deg: float = 0.5,
            cardan_step_deg: float = 0.01) -> VehicleAnalysis:
    """Evaluate the model on a tilt grid ``0, step, ..., max_tilt`` (degrees)."""
    if step_deg <= 0.0:
        raise ValueError("step_deg must be positive")
    model = VehicleModel(params)
    max_tilt = params.tilt.max_tilt_deg
    grid = np.append(np.arange(0.0, max_tilt, step_deg), max_tilt)
    worm, bend = params.tilt.worm_ratio, math.radians(params.tilt.cardan_bend_deg)
    rows = []
    for tilt_deg in grid:
        a = math.radians(float(tilt_deg))
        actual = cardan_tilts_rad(a, worm, bend)
        rows.append(TiltRow(
            tilt_deg=float(tilt_deg),
            rank=model.rank(a),
            condition_number=model.condition_number(a),
            hover_efficiency=model.force_efficiency(a, model.hover_thrusts(a)),
            max_rotor_thrust_n=model.max_thrust_n,
            max_lift_n=model.max_lift_n(a),
            lateral_force_radius_n=model.lateral_force_radius_n(a),
            cardan_error_deg=tuple(float(math.degrees(abs(x) - a)) for x in actual),
        ))
    fit_grid = np.append(np.arange(0.0, max_tilt, fit_step_deg), max_tilt)
    coeffs, residual = model.fit_lateral_bound(fit_grid)
    fine = np.radians(np.append(np.arange(0.0, max_tilt, cardan_step_deg), max_tilt))
    errors = np.degrees(np.abs(cardan_tilts_rad(fine, worm, bend)) - fine[:, None])
    worst = np.argmax(np.abs(errors), axis=0)
    return VehicleAnalysis(
        vehicle=params.name,
        mass_kg=params.mass_kg,
        weight_n=params.weight_n,
        rows=tuple(rows),
        lateral_bound_coeffs_n=(float(coeffs[0]), float(coeffs[1]), float(coeffs[2])),
        lateral_bound_max_residual_n=residual,
        cardan_peak_error_deg=tuple(float(abs(errors[worst[i], i])) for i in range(6)),
        cardan_peak_error_tilt_deg=tuple(float(np.degrees(fine[worst[i]])) for i in range(6)),
    )


def format_table(result: VehicleAnalysis) -> str:
    """The human-readable table printed by ``fasthex analyze``."""
    lines = [
        f"vehicle {result.vehicle}: mass {result.mass_kg:g} kg, weight {result.weight_n:.2f} N",
        "",
        f"{'tilt':>6} {'rank':>4} {'cond(F)':>9} {'eta_hover':>9} {'f_max':>7} {'lift_max':>8} "
        f"{'r_xy':>6}  Cardan error per propeller 1..6 (deg)",
        f"{'deg':>6} {'':>4} {'':>9} {'':>9} {'N':>7} {'N':>8} {'N':>6}",
    ]
    for r in result.rows:
        cond = f"{r.condition_number:9.1f}" if r.condition_number < 1e9 else f"{'inf':>9}"
        errs = " ".join(f"{e:+6.3f}" for e in r.cardan_error_deg)
        lines.append(
            f"{r.tilt_deg:6.1f} {r.rank:4d} {cond} {r.hover_efficiency:9.4f} "
            f"{r.max_rotor_thrust_n:7.2f} {r.max_lift_n:8.2f} {r.lateral_force_radius_n:6.2f}  "
            f"{errs}"
        )
    c0, c1, c2 = result.lateral_bound_coeffs_n
    lines += [
        "",
        f"lateral bound fit: r_xy(alpha) = {c0:+.4f} {c1:+.4f} a {c2:+.6f} a^2  N "
        f"(a in deg; max residual {result.lateral_bound_max_residual_n:.3f} N)",
        "peak Cardan tilt error (deg), propellers 1..6: "
        + " ".join(f"{e:.3f}" for e in result.cardan_peak_error_deg),
    ]
    return "\n".join(lines)


def write_plots(params: VehicleParams, result: VehicleAnalysis, out_dir: str) -> list[str]:
    """PNG figures like the paper's: efficiency vs tilt, lateral-force hexagons, Cardan errors,
    and r_xy(alpha) with its fit. Returns the written paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = VehicleModel(params)
    max_tilt = params.tilt.max_tilt_deg
    tilts = np.linspace(0.0, max_tilt, 141)
    written: list[str] = []

    fig, ax = plt.subplots(figsize=(6, 3.5))
    eff = [model.force_efficiency(math.radians(a), model.hover_thrusts(math.radians(a)))
           for a in tilts]
    ax.plot(tilts, eff, label="eta_f at hover (model)")
    ax.plot(tilts, np.cos(np.radians(tilts)), "--", label="cos(alpha)")
    ax.set(xlabel="tilt alpha (deg)", ylabel="force efficiency eta_f",
           title=f"{params.name}: hover force efficiency")
    ax.grid(True)
    ax.legend()
    written.append(_save(fig, out / "efficiency.png"))

    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    for a in (5.0, 10.0, 20.0, 30.0, max_tilt):
        poly = model.lateral_force_polygon(math.radians(a))
        if len(poly) >= 3:
            closed = np.vstack([poly, poly[:1]])
            line, = ax.plot(closed[:, 0], closed[:, 1], label=f"{a:g} deg")
            r = model.lateral_force_radius_n(math.radians(a))
            phi = np.linspace(0.0, 2.0 * math.pi, 100)
            ax.plot(r * np.cos(phi), r * np.sin(phi), ":", color=line.get_color())
    ax.set(xlabel="f_x body (N)", ylabel="f_y body (N)", aspect="equal",
           title="admissible lateral force at hover (zero torque)\nand inscribed circles")
    ax.grid(True)
    ax.legend(fontsize=8)
    written.append(_save(fig, out / "lateral_force_sets.png"))

    fig, ax = plt.subplots(figsize=(7, 4.2))
    fine = np.radians(np.linspace(0.0, max_tilt, 1401))
    actual = np.degrees(np.abs(cardan_tilts_rad(fine, params.tilt.worm_ratio,
                                                math.radians(params.tilt.cardan_bend_deg))))
    errors = actual - np.degrees(fine)[:, None]
    # propellers at equal places in the chain share a curve: one trace per group, named so
    for group in coinciding_groups(errors, tol=1e-9):
        names = ", ".join(str(i + 1) for i in group)
        label = (f"propellers {names} (same curve)" if len(group) > 1
                 else f"propeller {names}")
        ax.plot(np.degrees(fine), errors[:, group[0]], label=label)
    ax.set(xlabel="desired tilt alpha_des (deg)", ylabel="alpha_i - alpha_des (deg)",
           title="Cardan drive-train tilt error")
    ax.grid(True)
    ax.legend(fontsize=8, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.2),
              frameon=False)  # below the axes: the curves fill the plot
    written.append(_save(fig, out / "cardan_errors.png"))

    fig, ax = plt.subplots(figsize=(6, 3.5))
    radii = [model.lateral_force_radius_n(math.radians(a)) for a in tilts]
    c0, c1, c2 = result.lateral_bound_coeffs_n
    ax.plot(tilts, radii, label="inscribed radius (LP)")
    ax.plot(tilts, c0 + c1 * tilts + c2 * tilts**2, "--", label="least-squares quadratic")
    ax.set(xlabel="tilt alpha (deg)", ylabel="r_xy (N)", title="lateral force bound")
    ax.grid(True)
    ax.legend()
    written.append(_save(fig, out / "lateral_bound_fit.png"))
    return written


def coinciding_groups(curves: npt.NDArray[np.float64], tol: float = 1e-6) -> list[list[int]]:
    """Columns of ``curves`` (N, k) that are equal within ``tol``, grouped (0-based, in order).
    Used to say which traces lie on top of each other."""
    groups: list[list[int]] = []
    for i in range(curves.shape[1]):
        for g in groups:
            if np.allclose(curves[:, i], curves[:, g[0]], atol=tol, rtol=0.0, equal_nan=True):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


def _save(fig: Any, path: Any) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return str(path)
