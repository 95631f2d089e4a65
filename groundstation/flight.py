"""The flight state machine: preflight, arm, take off, fly the mission, land, disarm; and the
failsafes that cut a flight short.

Pure logic, no I/O and no clock of its own: the loop calls :meth:`FlightStateMachine.update`
once per tick with the tick's time and a :class:`HealthSnapshot`, and operator requests arrive
through :meth:`FlightStateMachine.request`. The machine answers with what the loop must do
(:class:`Directive`): whether motors spin, which reference source flies (mission, landing on
the estimate, none). Every transition is recorded with its time and reason.

States and transitions::

    PREFLIGHT --checks pass + arm--> ARMED --idle spin-up done--> TAKEOFF --at start pose--> MISSION
    MISSION --mission done--> LANDING --touchdown--> DISARMED
    ARMED --IMU/link lost--> CUT (the other failsafes need the vehicle in the air)
    any flying state --MoCap lost > timeout | geofence | body tilt | battery low | servo fault
                       (action land) | operator stop--> LANDING (on the estimate)
    LANDING (mission's) --any of the failsafes above--> LANDING (on the estimate)
    any flying state --IMU/link lost | second operator stop | failsafe action cut--> CUT
    CUT --> DISARMED (motors stopped; the Flight-Ctrl watchdog also stops them on link loss)
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Literal

from controller.values import tick_value


class FlightState(enum.IntEnum):
    """Numbered so the state fits a telemetry column and a MAVLink custom mode."""

    PREFLIGHT = 0
    ARMED = 1
    TAKEOFF = 2
    MISSION = 3
    LANDING = 4
    DISARMED = 5
    CUT = 6


FLYING = frozenset({FlightState.TAKEOFF, FlightState.MISSION, FlightState.LANDING})
MOTORS_ON = frozenset({FlightState.ARMED, FlightState.TAKEOFF, FlightState.MISSION,
                       FlightState.LANDING})


class ServoHealth(enum.IntEnum):
    OK = 0
    DEGRADED = 1  # answering with warning bits (e.g. overload), still moving
    FAULT = 2     # not answering, or an error that stops it (overheating, voltage)


class ReferenceSource(enum.IntEnum):
    NONE = 0      # motors off or idle: the controller does not fly
    MISSION = 1   # takeoff, mission and planned landing segments
    LAND_HERE = 2  # failsafe landing from the current estimate


@tick_value
class HealthSnapshot:
    """What the loop measured this tick. Ages in seconds on the loop's clock."""

    imu_age_s: float
    imu_rate_ok: bool
    mocap_age_s: float
    estimator_ok: bool
    servo: ServoHealth
    battery_v: float
    pos_w_m: tuple[float, float, float]
    body_tilt_deg: float
    on_ground: bool
    mission_phase: Literal["takeoff", "mission", "land", "done"]
    motors_spinning: bool
    #: the estimate has left the ground (above the resting height by the lift-off margin)
    lifted_off: bool = True
    #: the estimate is at the take-off height within its tolerance, and steady
    takeoff_reached: bool = True
    #: MoCap and the IMU agree (MoCap moves as the IMU feels; the estimator is not
    #: re-seeding from MoCap again and again)
    mocap_consistent: bool = True
    #: what the servo driver says is wrong, named in a servo fault ("no reply", "stale", ...)
    servo_detail: str = ""
    #: the mission (its planned landing with it) is over and the estimate has stayed off the
    #: ground since: a planned landing that cannot end (the loop waits ENDED_ALOFT_S first)
    ended_aloft: bool = False
    #: LANDING: the IMU reads the vehicle standing still at low thrust (IMU_LANDED_S), whatever
    #: the estimate says: a touchdown the estimate did not see (frozen, drifting)
    landed_imu: bool = False


@dataclass(frozen=True)
class SafetyLimits:
    """The flight's safety envelope (from the session file)."""

    geofence_min_m: tuple[float, float, float]
    geofence_max_m: tuple[float, float, float]
    max_body_tilt_deg: float
    mocap_timeout_s: float
    imu_timeout_s: float
    min_battery_v: float
    failsafe_action: Literal["land", "cut"]
    servo_fault_action: Literal["hold", "land"]
    spin_up_s: float = 1.0
    #: TAKEOFF without lift-off this long (at the take-off thrust) -> abort: idle, disarm
    liftoff_timeout_s: float = 5.0
    #: the planned take-off is over but the take-off height is not reached this long -> land
    takeoff_settle_timeout_s: float = 10.0
    #: bench with props off: arm, spin at idle this long after the spin-up, disarm; no take-off
    props_off_spin_s: float | None = None


@dataclass(frozen=True, slots=True)
class Transition:
    t_s: float
    from_state: FlightState
    to_state: FlightState
    reason: str


@tick_value
class Directive:
    """What the loop does this tick."""

    state: FlightState
    motors_on: bool
    reference: ReferenceSource
    hold_tilt: bool  # servo fault with action "hold": keep the measured tilt, stop commanding


@dataclass
class FlightStateMachine:
    limits: SafetyLimits
    state: FlightState = FlightState.PREFLIGHT
    transitions: list[Transition] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)
    _armed_at_s: float = 0.0
    _takeoff_at_s: float = 0.0
    _takeoff_over_at_s: float | None = None  # when the planned take-off ended, if not reached
    _stop_requests: int = 0
    _hold_tilt: bool = False
    _land_here: bool = False

    # -- operator -----------------------------------------------------------------------
    def request(self, t_s: float, what: Literal["arm", "land", "stop", "cut", "disarm"]
                ) -> tuple[bool, str]:
        """An operator request (CLI, Ctrl-C, MAVLink). Returns (accepted, reason)."""
        if what == "arm":
            if self.state is not FlightState.PREFLIGHT:
                return False, f"cannot arm in {self.state.name}"
            self._go(t_s, FlightState.ARMED, "operator: arm")
            self._armed_at_s = t_s
            return True, "armed"
        if what == "disarm":
            if self.state in FLYING:
                return False, f"cannot disarm while {self.state.name}; land first"
            if self.state is FlightState.DISARMED:
                return False, "already disarmed"
            self._go(t_s, FlightState.DISARMED, "operator: disarm")
            return True, "disarmed"
        if what == "cut":
            if self.state in MOTORS_ON:
                self._cut(t_s, "operator: emergency stop")
                return True, "motors cut"
            return False, f"motors are not running ({self.state.name})"
        if what == "stop":  # Ctrl-C: first lands, second cuts
            self._stop_requests += 1
            if self._stop_requests >= 2 and self.state in MOTORS_ON:
                self._cut(t_s, "operator: second stop request")
                return True, "motors cut"
            what = "land"
        # land
        if self.state in (FlightState.TAKEOFF, FlightState.MISSION):
            self._land(t_s, "operator: land", here=True)
            return True, "landing"
        if self.state is FlightState.ARMED:
            self._go(t_s, FlightState.DISARMED, "operator: land before takeoff")
            return True, "disarmed"
        if self.state is FlightState.PREFLIGHT:
            self._go(t_s, FlightState.DISARMED, "operator: stop before arming")
            return True, "session ended"
        return False, f"already {self.state.name}"

    def limit(self, t_s: float, reason: str, *, cut: bool = False) -> None:
        """A limit of the session itself (not an operator's request, not a health input): a
        fault, then land where the vehicle is (``cut``: stop the motors). On the ground at idle
        (ARMED) it disarms, in PREFLIGHT it ends the session; after a flight, nothing."""
        if self.state is FlightState.PREFLIGHT:
            self._fault(t_s, reason)
            self._go(t_s, FlightState.DISARMED, f"{reason}: session ended before arming")
            return
        if self.state not in MOTORS_ON:
            return
        self._fault(t_s, reason)
        if self.state is FlightState.ARMED:
            self._go(t_s, FlightState.DISARMED, f"{reason}: disarmed before take-off")
        elif cut:
            self._cut(t_s, f"failsafe (cut): {reason}")
        else:
            self._land(t_s, f"failsafe: {reason}", here=True)

    # -- per tick -----------------------------------------------------------------------
    def update(self, t_s: float, h: HealthSnapshot) -> Directive:
        start = self.state
        if start in MOTORS_ON:
            self._check_failsafes(t_s, h)
        s = self.state
        lim = self.limits
        if s is FlightState.ARMED and lim.props_off_spin_s is not None:
            self._bench_spin(t_s, h, lim.props_off_spin_s)
        elif s is FlightState.ARMED and t_s - self._armed_at_s >= lim.spin_up_s \
                and h.motors_spinning:  # every BL-Ctrl reports `spinning`
            self._go(t_s, FlightState.TAKEOFF, "motors at idle speed")
            self._takeoff_at_s, self._takeoff_over_at_s = t_s, None
        elif s is FlightState.TAKEOFF:
            self._takeoff(t_s, h)
        elif s is FlightState.MISSION and h.mission_phase in ("land", "done"):
            self._land(t_s, "mission complete", here=False)
        elif s is FlightState.LANDING and h.on_ground:
            self._go(t_s, FlightState.DISARMED, "touchdown")
        elif s is FlightState.LANDING and h.landed_imu:
            z = h.pos_w_m[2]
            self._fault(t_s, f"touchdown seen by the IMU only (the estimate at z = {z:.2f} m)")
            self._go(t_s, FlightState.DISARMED, "touchdown (IMU: still at low thrust)")
        elif s is FlightState.LANDING and h.ended_aloft and not self._land_here:
            # mission files are checked to end on the ground: this is the last line of defence
            # (a hover at the mission's last reference would last until the battery runs out)
            what = "the mission ended with the vehicle in the air"
            self._fault(t_s, what)
            self._land(t_s, f"failsafe: {what}: landing here", here=True)
        elif s is FlightState.CUT and start is FlightState.CUT:  # one tick with motors off
            self._go(t_s, FlightState.DISARMED, "motors stopped")
        s = self.state
        if s in (FlightState.TAKEOFF, FlightState.MISSION):
            ref = ReferenceSource.MISSION
        elif s is FlightState.LANDING:
            ref = ReferenceSource.LAND_HERE if self._land_here else ReferenceSource.MISSION
        else:
            ref = ReferenceSource.NONE
        return Directive(s, s in MOTORS_ON, ref, self._hold_tilt)

    @property
    def finished(self) -> bool:
        return self.state is FlightState.DISARMED

    # -- internals ----------------------------------------------------------------------
    def _takeoff(self, t_s: float, h: HealthSnapshot) -> None:
        """TAKEOFF is decided on the estimate, not on the mission's clock: MISSION once the
        planned take-off is over *and* the vehicle is at its height; no lift-off in time
        aborts (the rotors, the props or the estimate are not what the plan assumed)."""
        lim = self.limits
        if not h.lifted_off:
            if t_s - self._takeoff_at_s >= lim.liftoff_timeout_s:
                reason = (f"no lift-off within {lim.liftoff_timeout_s:g} s at the take-off "
                          "thrust: take-off aborted")
                self._fault(t_s, reason)
                self._go(t_s, FlightState.DISARMED, reason)
            return
        if h.mission_phase == "takeoff":
            return
        if h.takeoff_reached:
            self._go(t_s, FlightState.MISSION, "takeoff complete")
            return
        if self._takeoff_over_at_s is None:
            self._takeoff_over_at_s = t_s
        elif t_s - self._takeoff_over_at_s >= lim.takeoff_settle_timeout_s:
            reason = (f"take-off height not reached {lim.takeoff_settle_timeout_s:g} s after "
                      "the planned take-off")
            self._fault(t_s, reason)
            self._land(t_s, f"failsafe: {reason}", here=True)

    def _bench_spin(self, t_s: float, h: HealthSnapshot, spin_s: float) -> None:
        """Props-off bench: the motors run at idle, nothing takes off; the test passes when
        every BL-Ctrl reports spinning after the spin-up, and ends after ``spin_s`` more."""
        since = t_s - self._armed_at_s
        if since < self.limits.spin_up_s + spin_s:
            return
        if h.motors_spinning:
            self._go(t_s, FlightState.DISARMED,
                     f"props-off bench test complete: every motor spun at idle for {spin_s:g} s")
        else:
            self._fault(t_s, "props-off bench test: not every motor reports spinning")
            self._go(t_s, FlightState.DISARMED,
                     "props-off bench test failed: not every motor reports spinning")

    def _check_failsafes(self, t_s: float, h: HealthSnapshot) -> None:
        lim = self.limits
        if h.imu_age_s > lim.imu_timeout_s or not h.imu_rate_ok:
            if h.imu_age_s == float("inf"):
                what = "Flight-Ctrl link lost"
            elif h.imu_age_s > lim.imu_timeout_s:
                what = f"IMU stream lost (age {h.imu_age_s * 1e3:.0f} ms)"
            else:
                what = "IMU rate below 80 % of the set rate"
            self._fault(t_s, what)
            self._cut(t_s, "IMU/link lost: motors stop")
            return
        if self.state is FlightState.ARMED:
            return  # on the ground, idle: nothing else can go wrong that landing would fix
        reason = None
        detail = ""     # the driver's word, in the fault only (the transition keeps the reason)
        if h.mocap_age_s > lim.mocap_timeout_s:
            reason = f"MoCap lost for {h.mocap_age_s:.2f} s (> {lim.mocap_timeout_s:g} s)"
        elif not h.estimator_ok:
            reason = "estimator unhealthy"
        elif not h.mocap_consistent:
            reason = ("MoCap and IMU disagree (MoCap turned or changed velocity without the IMU "
                      "feeling it, or the estimator re-seeds from MoCap again and again)")
        elif any(p < lo or p > hi for p, lo, hi in
                 zip(h.pos_w_m, lim.geofence_min_m, lim.geofence_max_m, strict=True)):
            reason = "geofence breached at ({:.2f}, {:.2f}, {:.2f}) m".format(*h.pos_w_m)
        elif h.body_tilt_deg > lim.max_body_tilt_deg:
            reason = f"body tilt {h.body_tilt_deg:.1f} deg > {lim.max_body_tilt_deg:g} deg"
        elif h.battery_v < lim.min_battery_v:
            reason = f"battery low ({h.battery_v:.2f} V < {lim.min_battery_v:g} V)"
        elif h.servo is ServoHealth.FAULT and not self._hold_tilt:
            detail = f" ({h.servo_detail})" if h.servo_detail else ""
            if lim.servo_fault_action == "hold":
                self._fault(t_s, f"tilt servo fault: holding the measured tilt{detail}")
                self._hold_tilt = True
            else:
                reason = "tilt servo fault"
        if reason is None:
            return
        if self.state is FlightState.LANDING and self._land_here:
            return  # already doing the safe thing
        self._fault(t_s, reason + detail)
        if lim.failsafe_action == "cut":
            self._cut(t_s, f"failsafe (cut): {reason}")
        else:
            self._land(t_s, f"failsafe: {reason}", here=True)

    def note_fault(self, t_s: float, what: str) -> None:
        """A fault the flight goes on through (the loop already acted on it): listed with
        the others, no transition."""
        self._fault(t_s, what)

    def _fault(self, t_s: float, what: str) -> None:
        self.faults.append(f"{t_s:.3f} s: {what}")

    def _land(self, t_s: float, reason: str, *, here: bool) -> None:
        if here and self.state is FlightState.LANDING and not self._land_here:
            # a failsafe during the mission's own landing: give up the planned path and land
            # where the vehicle is, recorded as a LANDING -> LANDING transition so that the
            # loop takes the landing reference from this tick's estimate
            self._land_here = True
            self.transitions.append(Transition(t_s, self.state, self.state, reason))
            return
        self._land_here = here
        self._go(t_s, FlightState.LANDING, reason)

    def _cut(self, t_s: float, reason: str) -> None:
        self._go(t_s, FlightState.CUT, reason)

    def _go(self, t_s: float, to: FlightState, reason: str) -> None:
        if to is not self.state:
            self.transitions.append(Transition(t_s, self.state, to, reason))
            self.state = to
