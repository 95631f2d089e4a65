"""The tilt planner: the mission's alpha reference -> the tilt command sent to the servo.

The command stays inside ``[min_tilt, max_tilt]`` (``[0, 35]`` deg on the paper's vehicle; a
single value on a fixed-tilt airframe, whose ``max_rate_deg_s`` is 0) and moves at most
``max_rate_deg_s`` (paper: 10 deg/s) towards its target. The target is the mission's
``alpha_r``, or in ``auto`` mode (the paper leaves alpha to "a high-level planner or a human
operator") the smallest tilt whose lateral-force capability covers the lateral force the
reference needs over a look-ahead horizon, plus a margin: the vehicle is only as fully actuated
as the task requires and wastes the least internal force.

Capability in ``auto`` is the controller's own lateral bound r_xy(alpha) (the fitted
inscribed radius of the vehicle model times the conservative scale, zero in the dead zone): the
planner picks the tilt at which the controller will actually deliver the demand, so R_d does
not leave R_r where more tilt was available. (Planning on the unscaled radius would stop about
20 % short, and position priority would then tilt R_d at every demand peak.) Beyond the bound at
the maximum tilt the planner stays at the maximum and R_d gives way, as on the paper's vehicle.
"""

from __future__ import annotations

import bisect
import math

from controller.model import LateralBound, VehicleModel
from controller.params import VehicleParams

AUTO_GRID_STEP_DEG = 0.05


class TiltPlanner:
    """Rate-limited tilt command with an optional ``auto`` target. Explicit state, no I/O."""

    def __init__(self, params: VehicleParams, *, model: VehicleModel | None = None,
                 capability: LateralBound | None = None, initial_alpha_rad: float = 0.0
                 ) -> None:
        self.max_tilt_rad = params.tilt.max_tilt_rad
        self.min_tilt_rad = params.tilt.min_tilt_rad
        self.max_rate_rad_s = math.radians(params.tilt.max_rate_deg_s)
        if capability is None:
            capability = LateralBound.for_model(model if model is not None
                                                else VehicleModel(params))
        self.capability = capability
        n = int(params.tilt.max_tilt_deg / AUTO_GRID_STEP_DEG) + 1
        self._grid_rad = [math.radians(i * AUTO_GRID_STEP_DEG) for i in range(n)]
        # running maximum keeps the table monotone even if the fitted quadratic bends down
        radii: list[float] = []
        for a in self._grid_rad:
            radii.append(max(capability.radius_n(a), radii[-1] if radii else 0.0))
        self._radii_n = radii
        self.alpha_cmd_rad = min(max(initial_alpha_rad, self.min_tilt_rad), self.max_tilt_rad)
        self.target_rad = self.alpha_cmd_rad
        self._last_t_s: float | None = None

    def alpha_for_lateral_force(self, force_n: float) -> float:
        """Smallest tilt (rad) whose capability covers ``force_n``; the maximum tilt if none."""
        if force_n <= 0.0:
            return self.min_tilt_rad
        i = bisect.bisect_left(self._radii_n, force_n)
        alpha = self._grid_rad[i] if i < len(self._grid_rad) else self.max_tilt_rad
        return max(alpha, self.min_tilt_rad)

    def step(self, t_s: float, alpha_ref_rad: float | None, demand_n: float | None = None,
             margin_n: float = 0.0) -> float:
        """Advance to ``t_s`` and return the tilt command (rad).

        ``alpha_ref_rad`` is the mission's reference, or ``None`` for ``auto``; then
        ``demand_n`` (the lateral force the reference needs, N) updates the target when given,
        otherwise the last auto target is kept.
        """
        dt = 0.0 if self._last_t_s is None else max(0.0, t_s - self._last_t_s)
        self._last_t_s = t_s
        if alpha_ref_rad is not None:
            self.target_rad = alpha_ref_rad
        elif demand_n is not None:
            self.target_rad = self.alpha_for_lateral_force(demand_n + margin_n)
        target = min(max(self.target_rad, self.min_tilt_rad), self.max_tilt_rad)
        step = self.max_rate_rad_s * dt
        delta = target - self.alpha_cmd_rad
        self.alpha_cmd_rad += step if delta > step else (-step if delta < -step else delta)
        return self.alpha_cmd_rad
