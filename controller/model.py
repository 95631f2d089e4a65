"""The FAST-Hex vehicle model of the paper (Sec. III), pure numpy.

Frames: body frame B with x towards propeller 1 and z along the rotor axes at zero tilt; the
world frame has z up (gravity ``-g e3``). Propeller i (1..6) sits at
``p_i = l Rz((i-1) pi/3) e1`` with attitude ``R_Pi(alpha) = Rz((i-1) pi/3) Rx((-1)^(i-1) alpha)``
(the model equation; Table I's extra ``Ry(beta)`` is a misalignment left to the simulator, see
paper-notes item 1). Its thrust ``f_i = c_f w_i^2`` (w in Hz) acts along ``R_Pi e3`` and its drag
torque is ``(-1)^i c_f^tau f_i R_Pi e3`` when propeller 1 spins counter-clockwise.

``u = [f_1 .. f_6]`` (N) maps to the body force ``F1(alpha) u`` and the body torque
``F2(alpha) u``; ``F = [F1; F2]`` is the 6x6 allocation matrix (body frame: the paper's
``F(R_B, alpha)`` is ``diag(R_B, I) F``).

Also here: the force-efficiency index eta_f, hover thrusts, the admissible lateral-force set at
hover with zero torque (a convex polygon) and its inscribed radius, the maximum lift, the
least-squares fit of the lateral bound r_xy(alpha) and the Cardan drive-train model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.linalg import null_space
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, QhullError

from controller.params import VehicleParams

FloatArray = npt.NDArray[np.float64]

N_ROTORS = 6
#: Number of Cardan joints between the servo and the worm of propeller i (paper Sec. II).
CARDAN_JOINTS_PER_PROPELLER = (1, 3, 5, 5, 3, 1)


def rot_x(angle_rad: float) -> FloatArray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(angle_rad: float) -> FloatArray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class VehicleModel:
    """The paper's simplified FAST-Hex model for one set of :class:`VehicleParams`."""

    def __init__(self, params: VehicleParams) -> None:
        self.params = params
        idx = np.arange(N_ROTORS)
        self.arm_yaw_rad: FloatArray = idx.astype(np.float64) * (math.pi / 3.0)
        l_m = params.geometry.arm_length_m
        self.rotor_positions_b_m: FloatArray = np.stack(
            [l_m * np.cos(self.arm_yaw_rad), l_m * np.sin(self.arm_yaw_rad), np.zeros(N_ROTORS)],
            axis=1,
        )
        #: (-1)^(i-1): adjacent propellers tilt in opposite directions.
        self.tilt_signs: FloatArray = np.where(idx % 2 == 0, 1.0, -1.0)
        #: sign of each drag torque along the propeller axis: (-1)^i if propeller 1 is CCW.
        ccw = 1.0 if params.rotors.first_rotor_ccw else -1.0
        self.drag_signs: FloatArray = -ccw * self.tilt_signs
        self.c_f = params.rotors.thrust_coeff_n_per_hz2
        self.c_tau_m = params.rotors.drag_coeff_m
        self.min_thrust_n = params.rotors.min_thrust_n
        self.max_thrust_n = params.rotors.max_thrust_n

    # -- geometry ---------------------------------------------------------------------------
    def propeller_rotations(self, alpha_rad: float) -> FloatArray:
        """``R_Pi^B(alpha)`` for the six propellers, shape (6, 3, 3)."""
        return self.propeller_rotations_from_tilts(self.tilt_signs * alpha_rad)

    def propeller_rotations_from_tilts(self, tilts_rad: npt.ArrayLike) -> FloatArray:
        """``Rz((i-1) pi/3) Rx(alpha_i)`` for six signed per-propeller tilts, shape (6, 3, 3)."""
        tilts = np.asarray(tilts_rad, dtype=float)
        return np.stack([rot_z(float(y)) @ rot_x(float(a))
                         for y, a in zip(self.arm_yaw_rad, tilts, strict=True)])

    def thrust_axes(self, alpha_rad: float) -> FloatArray:
        """Unit thrust directions ``R_Pi e3`` in B, shape (6, 3)."""
        s = np.sin(self.tilt_signs * alpha_rad)
        c = np.cos(self.tilt_signs * alpha_rad)
        cy, sy = np.cos(self.arm_yaw_rad), np.sin(self.arm_yaw_rad)
        # Rz(y) Rx(a) e3 = Rz(y) [0, -sin a, cos a]
        return np.stack([sy * s, -cy * s, c], axis=1).astype(np.float64, copy=False)

    def allocation_parts(self, alpha_rad: float) -> tuple[FloatArray, FloatArray]:
        """``(F1, F2)``: body force and body torque per unit thrust, each shape (3, 6)."""
        axes = self.thrust_axes(alpha_rad)
        moments = np.cross(self.rotor_positions_b_m, axes) \
            + (self.drag_signs * self.c_tau_m)[:, None] * axes
        return axes.T.copy(), moments.T.copy()

    def allocation(self, alpha_rad: float) -> FloatArray:
        """The 6x6 allocation ``F(alpha) = [F1; F2]`` (body frame)."""
        f1, f2 = self.allocation_parts(alpha_rad)
        return np.vstack([f1, f2])

    def singular_values(self, alpha_rad: float) -> FloatArray:
        return np.linalg.svd(self.allocation(alpha_rad), compute_uv=False).astype(np.float64)

    def rank(self, alpha_rad: float, rel_tol: float = 1e-4) -> int:
        """Numerical rank of F: singular values above ``rel_tol * sigma_max`` (paper-notes 4:
        the loss at -3.56 deg leaves sigma_min ~ 6e-5, not an exact zero)."""
        sv = self.singular_values(alpha_rad)
        return int(np.sum(sv > rel_tol * sv[0]))

    def condition_number(self, alpha_rad: float, rel_tol: float = 1e-4) -> float:
        """sigma_max / sigma_min of F; ``inf`` where F is numerically rank-deficient."""
        sv = self.singular_values(alpha_rad)
        return float(sv[0] / sv[-1]) if sv[-1] > rel_tol * sv[0] else math.inf

    # -- propellers -------------------------------------------------------------------------
    def thrust_from_spin(self, spin_hz: npt.ArrayLike) -> FloatArray:
        """``f = c_f w^2`` (N) for spin rates in Hz."""
        w = np.asarray(spin_hz, dtype=float)
        return self.c_f * w * w

    def spin_from_thrust(self, thrust_n: npt.ArrayLike) -> FloatArray:
        """Inverse of :meth:`thrust_from_spin`; negative thrusts map to 0 Hz."""
        f = np.maximum(np.asarray(thrust_n, dtype=float), 0.0)
        return np.asarray(np.sqrt(f / self.c_f), dtype=np.float64)

    def force_efficiency(self, alpha_rad: float, thrusts_n: npt.ArrayLike) -> float:
        """eta_f = |sum_i f_i^B| / sum_i f_i (paper eq. force_efficiency), in [0, 1]."""
        u = np.asarray(thrusts_n, dtype=float)
        total = float(np.sum(np.abs(u)))
        if total <= 0.0:
            return 1.0
        f1, _ = self.allocation_parts(alpha_rad)
        return float(np.linalg.norm(f1 @ u) / total)

    def hover_thrusts(self, alpha_rad: float) -> FloatArray:
        """Thrusts holding the weight level with zero torque (least-norm solution of F u = w)."""
        wrench = np.array([0.0, 0.0, self.params.weight_n, 0.0, 0.0, 0.0])
        u, *_ = np.linalg.lstsq(self.allocation(alpha_rad), wrench, rcond=None)
        return np.asarray(u, dtype=float)

    # -- admissible sets --------------------------------------------------------------------
    def max_lift_n(self, alpha_rad: float) -> float:
        """Largest vertical body force with zero lateral force and zero torque (N), from the
        thrust limits; an LP over u in [f_min, f_max]^6."""
        f1, f2 = self.allocation_parts(alpha_rad)
        a_eq = np.vstack([f1[:2], f2])
        res = linprog(-f1[2], A_eq=a_eq, b_eq=np.zeros(5),
                      bounds=[(self.min_thrust_n, self.max_thrust_n)] * N_ROTORS, method="highs")
        return float(-res.fun) if res.status == 0 else math.nan

    def lateral_force_polygon(self, alpha_rad: float) -> FloatArray:
        """Vertices (counter-clockwise, shape (k, 2), N) of the admissible lateral body forces
        while holding the weight with zero torque: ``{F1_xy u | F1_z u = m g, F2 u = 0,
        f_min <= u <= f_max}``. Empty (0, 2) if the vehicle cannot hover at this tilt; a single
        point for the collinear configuration (alpha = 0).

        The four equality constraints leave a 2-D family of thrusts ``u = u0 + N z``: the set is
        the image of the polygon cut out of the z-plane by the twelve thrust limits, found by
        enumerating the pairwise intersections of its edges (exact, no direction sampling).
        """
        f1, f2 = self.allocation_parts(alpha_rad)
        a_eq = np.vstack([f2, f1[2:3]])
        b_eq = np.array([0.0, 0.0, 0.0, self.params.weight_n])
        basis = null_space(a_eq)
        if basis.shape[1] != 2:
            return self._lateral_force_polygon_lp(alpha_rad)
        u0, *_ = np.linalg.lstsq(a_eq, b_eq, rcond=None)
        g = np.vstack([basis, -basis])
        h = np.concatenate([self.max_thrust_n - u0, u0 - self.min_thrust_n])
        points = []
        for i in range(len(g)):
            for j in range(i + 1, len(g)):
                m = g[[i, j]]
                if abs(np.linalg.det(m)) < 1e-12:
                    continue
                z = np.linalg.solve(m, h[[i, j]])
                if np.all(g @ z <= h + 1e-9):
                    points.append(f1[:2] @ (u0 + basis @ z))
        return _ccw_hull(np.array(points).reshape(-1, 2))

    def _lateral_force_polygon_lp(self, alpha_rad: float, n_dirs: int = 72) -> FloatArray:
        """Support-function fallback when the constraints are rank-deficient."""
        f1, f2 = self.allocation_parts(alpha_rad)
        a_eq = np.vstack([f2, f1[2:3]])
        b_eq = np.array([0.0, 0.0, 0.0, self.params.weight_n])
        bounds = [(self.min_thrust_n, self.max_thrust_n)] * N_ROTORS
        points = []
        for phi in np.linspace(0.0, 2.0 * math.pi, n_dirs, endpoint=False):
            d = np.array([math.cos(phi), math.sin(phi)])
            res = linprog(-(d @ f1[:2]), A_eq=a_eq, b_eq=b_eq, bounds=bounds, method="highs")
            if res.status == 0:
                points.append(f1[:2] @ res.x)
        return _ccw_hull(np.array(points).reshape(-1, 2))

    def lateral_force_radius_n(self, alpha_rad: float) -> float:
        """Radius of the largest origin-centred disc inside :meth:`lateral_force_polygon` (N):
        the lateral force available in every direction at hover. 0 at alpha = 0."""
        return inscribed_radius(self.lateral_force_polygon(alpha_rad))

    def fit_lateral_bound(self, alphas_deg: npt.ArrayLike) -> tuple[FloatArray, float]:
        """Least-squares 2nd-degree polynomial r_xy(alpha_deg) through the inscribed radii.

        Returns ``(coeffs, max_residual_n)`` with ``coeffs = (c0, c1, c2)``:
        ``r_xy = c0 + c1 alpha_deg + c2 alpha_deg^2`` (N).
        """
        a = np.asarray(alphas_deg, dtype=float)
        r = np.array([self.lateral_force_radius_n(math.radians(x)) for x in a])
        design = np.stack([np.ones_like(a), a, a * a], axis=1)
        coeffs, *_ = np.linalg.lstsq(design, r, rcond=None)
        return coeffs, float(np.max(np.abs(design @ coeffs - r)))


_FITTED_BOUNDS: dict[tuple[object, ...], tuple[float, float, float]] = {}


@dataclass(frozen=True)
class LateralBound:
    """The controller's cylindric bound r_xy(alpha) (paper Sec. IV-C-1): the fitted polynomial,
    scaled by a conservative gain, zero inside a dead zone near alpha = 0."""

    coeffs_n: tuple[float, float, float]
    scale: float
    dead_zone_deg: float

    @classmethod
    def for_model(cls, model: VehicleModel, grid_step_deg: float = 0.5) -> LateralBound:
        p = model.params
        # the fit (71 linear programs, ~0.2 s) depends on the airframe, not on the gains: a
        # campaign that varies gains fits it once per process
        key = (p.mass_kg, p.gravity_m_s2, p.geometry, p.rotors, p.tilt, grid_step_deg)
        coeffs = _FITTED_BOUNDS.get(key)
        if coeffs is None:
            grid = np.arange(0.0, p.tilt.max_tilt_deg + 1e-9, grid_step_deg)
            fitted, _ = model.fit_lateral_bound(grid)
            coeffs = (float(fitted[0]), float(fitted[1]), float(fitted[2]))
            if len(_FITTED_BOUNDS) < 64:
                _FITTED_BOUNDS[key] = coeffs
        return cls(coeffs, p.controller.lateral_bound_scale,
                   p.controller.lateral_bound_dead_zone_deg)

    def radius_n(self, alpha_rad: float) -> float:
        a = math.degrees(alpha_rad)
        if a < self.dead_zone_deg:
            return 0.0
        c0, c1, c2 = self.coeffs_n
        return max(0.0, self.scale * (c0 + c1 * a + c2 * a * a))


def inscribed_radius(polygon: FloatArray) -> float:
    """Distance from the origin to the nearest edge of a CCW convex polygon (0 if the origin is
    outside or the polygon is degenerate)."""
    if len(polygon) < 3:
        return 0.0
    edges = np.roll(polygon, -1, axis=0) - polygon
    lengths = np.linalg.norm(edges, axis=1)
    keep = lengths > 1e-12
    # signed distance of the origin to each edge line, positive inside for a CCW polygon
    cross = edges[keep, 0] * (-polygon[keep, 1]) - edges[keep, 1] * (-polygon[keep, 0])
    return max(0.0, float(np.min(cross / lengths[keep])))


def _ccw_hull(points: FloatArray) -> FloatArray:
    if len(points) == 0:
        return np.zeros((0, 2))
    unique = np.unique(np.round(points, 9), axis=0)
    if len(unique) < 3:
        return unique
    try:
        hull = ConvexHull(unique)
    except QhullError:  # all points on a line: no area
        return unique[:1]
    return unique[hull.vertices]  # 2-D hull vertices come counter-clockwise


def cardan_tilts_rad(alpha_des_rad: npt.ArrayLike, worm_ratio: float, bend_rad: float
                     ) -> FloatArray:
    """Actual signed propeller tilts ``alpha_i`` through the Cardan chains (paper eq. Cardan,
    with the index typo fixed: gamma_j depends on gamma_{j-1}).

    ``gamma_0 = alpha_des / k``; ``gamma_j = atan2(sin g, cos(beta) cos g)`` with
    ``g = gamma_{j-1}``, unwrapped onto the branch of ``g`` (the shafts turn 1/k = 20 times the
    tilt, ~700 deg); ``alpha_i = k (-1)^(i-1) gamma_{n_i}`` with n_i = 1, 3, 5, 5, 3, 1 joints.
    Accepts a scalar or an array of desired tilts; returns shape ``(..., 6)``.
    """
    gamma = np.asarray(alpha_des_rad, dtype=float) / worm_ratio
    stages = [gamma]
    cos_b = math.cos(bend_rad)
    for _ in range(max(CARDAN_JOINTS_PER_PROPELLER)):
        prev = stages[-1]
        out = np.arctan2(np.sin(prev), cos_b * np.cos(prev))
        out = out + 2.0 * math.pi * np.round((prev - out) / (2.0 * math.pi))
        stages.append(out)
    signs = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    return np.stack([worm_ratio * s * stages[n]
                     for s, n in zip(signs, CARDAN_JOINTS_PER_PROPELLER, strict=True)], axis=-1)
