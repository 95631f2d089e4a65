"""The 500 Hz flight loop: one tick per IMU sample, written against small interfaces.

One tick (``architecture.md``, "One tick"):

1. wait for the next IMU sample (with a timeout: a silent link is a fault, not a hang);
2. the servo's newest measurement (a lockstep loop runs a synchronous servo cycle every few
   ticks; it also takes the MoCap datagrams that came before the sample off the socket);
3. UKF predict with the IMU sample;
4. flight state machine (health of every input -> continue, land, cut);
5. mission reference, tilt planner and controller (:class:`controller.pipeline.FlightComputer`)
   -> six spin rates, written as one ``w`` frame; the tilt command goes to the servo mailbox;
   then, after the command, a new MoCap pose is decoded (lockstep) and fused at its capture
   time, for the next tick: a frame tick's ~0.1 ms of decode and fusion stays off the path
   from IMU sample to motors (the pose reaches the controller one tick later; the UKF
   compensates its ~10 ms latency either way);
6. one flight-record row (flat values, :func:`groundstation.record.flat_row`) into the telemetry
   ring (never blocks), the tick's timing recorded.

Time: in ``lockstep`` the tick time is the IMU sample counter times the IMU period (the
emulated board's simulated clock, so two runs are identical and row k of the record is IMU
sample k); on hardware and in ``realtime`` it is the sample time rebuilt by the driver on the
host's monotonic clock (the clock the MoCap driver stamps capture times with), from the first
sample on. Nothing in the tick sleeps or blocks on I/O except the
deliberate wait for the IMU sample (and, in lockstep only, the servo cycle).
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from controller.missions import Mission
from controller.params import VehicleParams
from controller.pipeline import ControlTick, FlightComputer, LandHere
from controller.reference import VehicleState, rot_to_quat
from drivers.dynamixel.device import ServoHealth as DxlHealth
from drivers.dynamixel.device import ServoState
from drivers.errors import DeviceLostError, DriverError
from drivers.mikrokopter.device import LinkHealth
from estimator.consistency import Comparison, ConsistencyMonitor
from estimator.ukf import PoseVerdict, Ukf, UkfCheckpoint
from groundstation.console import number
from groundstation.flight import (
    FLYING,
    MOTORS_ON,
    FlightState,
    FlightStateMachine,
    HealthSnapshot,
    ReferenceSource,
    SafetyLimits,
    ServoHealth,
    Transition,
)
from groundstation.interfaces import ImuLink, PoseLink, TiltLink
from groundstation.operator import (
    STATUS_BATTERY,
    STATUS_PREFLIGHT,
    STATUS_STATE,
    post_transition,
)
from groundstation.signals import SUSPEND_REFUSED
from groundstation.timing import LoopTimer, TimingSummary

log = logging.getLogger(__name__)

ZERO6 = (0.0,) * 6
#: ticks between checks of the IMU link's measured rate (the check costs ~20 us)
LINK_CHECK_TICKS = 50
#: below this fraction of the set IMU rate the link is degraded: motors cut (the driver's own
#: ``min_rate_fraction`` on the wall clock; in lockstep the loop counts sequence-number gaps)
IMU_MIN_RATE_FRACTION = 0.8
#: preflight: a measured IMU rate above this fraction of the set rate fails too (real time)
IMU_MAX_RATE_FRACTION = 1.25
#: lockstep: the IMU rate is the samples received over the last this many sample periods of
#: the board's clock (0.5 s at 500 Hz, the driver's ``rate_window_s``), judged every
#: LINK_CHECK_TICKS ticks: a degraded link is cut within one window and one check of its onset,
#: and a single gap shorter than imu_timeout_s leaves the rate above the limit
IMU_RATE_WINDOW_SAMPLES = 250
#: lockstep: a sequence jump counts as at most this many samples in the rate: the driver takes
#: a longer jump as a resynchronisation of its counter (e.g. after a corrupted sequence byte,
#: the loop's clock jumps with it), not as that many samples lost; a long run of lost samples
#: is the IMU timeout's to judge
IMU_RATE_MAX_COUNTED_GAP = 17
#: lockstep: wall time a servo cycle may take before the servo counts as not answering (a
#: healthy servo's cycle may be tried three times: 3 x (502 ms SDK timeout + 100 ms resync))
LOCKSTEP_SERVO_WAIT_S = 4.0
#: landing: O_B within 4 cm of its resting height this long -> touchdown confirmed, disarm
TOUCHDOWN_CONFIRM_S = 0.4
#: the mission over and O_B not within those 4 cm for this long -> failsafe landing here (a
#: planned landing ends at the resting height; a vehicle still above it after this cannot be
#: touching down by itself)
ENDED_ALOFT_S = 1.0
#: landing: the IMU's touchdown, independent of the estimate: the commanded body thrust under
#: this fraction of the weight (the controller pushes down) while the IMU reads the ground's
#: support (specific force within IMU_STILL_ACCEL_M_S2 of g, rates under IMU_STILL_RATE_RAD_S)
#: for IMU_LANDED_S. Airborne, low thrust means falling (specific force well under g), so
#: only a vehicle standing on something passes; the estimate's touchdown (TOUCHDOWN_CONFIRM_S)
#: comes first in a landing it follows.
IMU_LOW_THRUST_FRACTION = 0.6
IMU_STILL_ACCEL_M_S2 = 1.5
IMU_STILL_RATE_RAD_S = 0.2
IMU_LANDED_S = 1.0
#: ... samples that break the stillness for at most this long do not restart it (a link
#: without checksum passes corrupted samples: a 0.5 % corrupted one spikes about every
#: 0.1 s, and one spike restarted the whole second)
IMU_STILL_GRACE_S = 0.02
#: a failsafe landing whose IMU has read the ground's support this long no longer moves
#: horizontally: the reference's horizontal position and velocity follow the estimate
GROUND_CONTACT_S = 0.1
#: A blind landing (MoCap distrusted) feels the touchdown's impact: the body-z specific force
#: above the commanded thrust (lagged as the rotors lag) per mass by IMPACT_EXCESS_M_S2, two
#: samples in a row (the driver holds a one-sample spike; the emulated gear's stop at 0.13 m/s
#: read +5.7 m/s^2 for 6 ms; the blind descent before it read -0.17..-0.44, the thrust model's
#: error). The dead reckoning may still sink after the touchdown at about the reference's
#: speed (0.07 m/s seen on a corrupted link), so the thrust stays at the weight's, never low
#: enough for the IMU's touchdown rule, and a controller chasing the estimate's drift rocks
#: the vehicle on its gear until the IMU rate check cuts it. So the impact presses: the
#: reference goes IMPACT_PRESS_M under the estimate (about 0.75 of the weight's thrust with the
#: position gain) and stops moving horizontally; the rule then reads the ground's support. The
#: press is confirmed by the ground's support (specific force within BLIND_STILL_ACCEL_M_S2 of
#: g at that thrust, IMPACT_SUPPORT_SAMPLES in a row, read from IMPACT_SETTLE_S on: two of the
#: rotors' 30 ms lags, before which the thrust has not fallen yet; the gyro is not asked, the
#: touchdown levels the vehicle at up to 1.1 rad/s). On the ground it is there at once (within
#: 0.19 m/s^2 of g from then on, seen); in the air that thrust reads 2 m/s^2 short of g by
#: then. Unconfirmed at IMPACT_CONFIRM_S, the jolt was not the ground: the landing goes on as
#: before, ~0.1 m/s faster. Seen in 70 blind landings: one impact each, at the touchdown
#: (0.06-0.26 m/s), none in the air.
IMPACT_EXCESS_M_S2 = 3.0
IMPACT_PRESS_M = 0.15
IMPACT_SETTLE_S = 0.06
IMPACT_SUPPORT_SAMPLES = 3
IMPACT_CONFIRM_S = 0.08
#: session time past ``max_flight_s`` after which a landing that has not touched down is cut
TIME_LIMIT_CUT_S = 120.0
#: lockstep: wall time after which a sample counts as lost, and the slice to check the link.
#: A sample lost on the wire shows at once as a receive error; this only catches a silent
#: board, so it is long: on a loaded host a reply can take 100 ms of wall time, and counting
#: it lost would step the emulated board twice and break the run's determinism. It stays
#: below the emulated board's 2 s lockstep grace (after which it free-runs).
LOCKSTEP_LOST_S = 1.0
LOCKSTEP_SLICE_S = 0.003
#: realtime: longest single wait for an IMU sample; a gap is bridged by resending the last
#: command at least this often until it exceeds the session's imu_timeout_s
IMU_GAP_SLICE_S = 0.01
#: take-off, decided on the estimate: lifted off once this far above the resting height; at
#: the take-off height once within the tolerance and slower than the speed for the time
LIFTOFF_MARGIN_M = 0.05
TAKEOFF_TOLERANCE_M = 0.05
TAKEOFF_STEADY_M_S = 0.1
TAKEOFF_STEADY_S = 0.3
#: MoCap inconsistent with the IMU: this many UKF re-seeds within this window
RESEEDS_INCONSISTENT = 3
RESEED_WINDOW_S = 1.0   # (2-3 s caught a tracker frozen late in a climb sooner, but also
#                         took the re-seeds of 0.5 % byte corruption on the IMU link for it)
#: MoCap found inconsistent in flight is not fused again (a frozen or wrong tracker pins the
#: estimate where it says, however the vehicle moves): the landing that follows runs on the
#: IMU alone, its reference sinking this far below the ground so that only the IMU's
#: touchdown ends it (the dead-reckoned height is not trusted to say where the ground is)
BLIND_SINK_M = 1.0
#: ... and from 5 cm under the ground on (where a right estimate has touched down) it sinks at
#: the descent's cruise speed: an estimate there without a touchdown is under the vehicle, and
#: at the touchdown speed (0.12 m/s) a dead reckoning sinking as fast hovered the vehicle 0.27 m
#: up for 8 s, sliding 3 m on its attitude's drift, until the cut dropped it (seen on a 0.5 %
#: corrupted link). The vehicle then descends at least this less the dead reckoning's drift
BLIND_DEEP_M_S = 0.3
#: ... and the estimate goes back this far (the UKF checkpointed every CHECKPOINT_EVERY_S)
#: and runs on the IMU alone from there: a tracker that froze still streams poses the UKF
#: fuses until they disagree too much, pulling the estimate's velocity to zero and its
#: accelerometer bias off (seen: 0.7-1.3 s from a freeze to the failsafe in a climb, 1.4-2.5 s
#: in a hover); dead reckoned from before, a landing 4-8 s later is within centimetres
#: vertically (going back to before the first re-seed instead dead reckoned longer: more
#: drift, a vehicle rocking 25 deg on its gear)
DEAD_RECKON_LOOKBACK_S = 3.0
#: ... but on an IMU link with an anomaly within ANOMALOUS_LINK_S, from a checkpoint this long
#: before the first refused pose (the poses pulled the estimate for the refusal's first frames)
MOCAP_OFF_LEAD_S = 0.5
ANOMALOUS_LINK_S = 1.0
#: a blind landing: below BLIND_THRUST_FRACTION of the weight, the IMU held still within
#: BLIND_STILL_ACCEL_M_S2 of g for IMU_LANDED_S is a touchdown (in the air that thrust reads
#: 0.1 g short of g). A dead reckoning drifting on the ground kept the thrust at 0.75-0.9 of
#: the weight, above the 0.6 of the plain rule, the controller chasing it until the vehicle
#: flipped. (The rule once also waited for the reference to sink 0.3 m under the ground: at
#: the touchdown's 0.12 m/s that is 2.4 s on the ground, and a vehicle rocked on its gear
#: within 2 s, chasing its estimate's drift, never to read still again.)
BLIND_THRUST_FRACTION = 0.9
BLIND_STILL_ACCEL_M_S2 = 0.5
CHECKPOINT_EVERY_S = 0.5
#: a re-seed from MoCap whose refused poses move this much slower or faster than the IMU says
#: (_judge_reset). If the IMU missed no motion around the refusals (no accelerometer at the
#: link's limit, no impact's step: lost or corrupted samples miss none) MoCap changed velocity
#: and the IMU felt no such acceleration, so MoCap is wrong (a tracker that froze while the
#: vehicle climbed at 0.34 m/s showed 0.17 m/s at its first re-seed, 0.25 s after the freeze;
#: before, it was found 5 s later by the repeated re-seeds, 2.3 m up and climbing). If it did,
#: the IMU was wrong (a 1.05 m/s impact left 0.59 m/s). MoCap jumps (a marker swap) and the
#: re-seeds of a 0.5 % corrupted link keep the velocity: seen under 0.06 m/s, the slope's
#: noise; taken for the IMU's, a 0.5 m jump on such a link was chased at 75 deg of tilt.
MOCAP_VELOCITY_GAP_M_S = 0.12
#: a re-seed that moves the estimate less than this on a failing IMU link (samples lost,
#: implausible) is the estimate's own correction, not a MoCap jump (seen on a 0.5 % corrupted
#: link: re-seeds of 1-2 cm about once a second; counted as MoCap jumps, three of them around
#: a real jump within 1 s were taken for MoCap disagreeing and landed the vehicle blind); on
#: the ground, a larger one disarms
MOCAP_JUMP_MIN_M = 0.05
#: MoCap against the IMU alone over estimator.consistency's 1 s horizon: MoCap turned this much
#: more than the gyro felt, or its velocity changed this much more than the accelerometer
#: felt (only over an IMU link without anomalies: a corrupted sample spoils the integral; on
#: one with anomalies the rotation's limit is MONITOR_ROTATION_FAILING_LINK_DEG), for
#: MONITOR_PERSIST_S, in the air: MoCap is wrong. Fault-free flights in the air (20, the
#: paper's three experiments among them; paper-calibrated disturbances) stayed under 0.20 deg
#: (0.35 on a 0.5 % corrupted link) and 0.022 m/s; a tracker frozen in the hover was found a
#: median 0.6-1.4 s after (seeds 1-10; before, by the repeated re-seeds: 1.6-4.4 s, 10 of 40
#: flights cut, drift up to 59 m).
#: Touchdowns are left out (MONITOR_MIN_HEIGHT_M): the contact shows up to 1 deg, 0.15 m/s.
MONITOR_ROTATION_DEG = 0.4
MONITOR_ROTATION_FAILING_LINK_DEG = 0.6
MONITOR_VELOCITY_M_S = 0.05
#: longer than one comparison window: a MoCap jump (a marker swap) spoils the windows holding
#: it for 0.2 s, as it enters the horizon and again as it leaves, and agrees in between
MONITOR_PERSIST_S = 0.25
MONITOR_MIN_HEIGHT_M = 0.15
CHECKPOINT_PHASE = 7  # the tick in each period: not one of the servo's or the link check's
#: ticks between two evaluations of the preflight checks (0.1 s at 500 Hz)
PREFLIGHT_CHECK_TICKS = 50


@dataclass
class LoopResult:
    transitions: list[Transition]
    faults: list[str]
    timing: TimingSummary
    ticks: int
    flight_time_s: float
    end_reason: str
    estimator_poses_rejected: int
    telemetry_dropped: int
    loop_wall_s: float = 0.0  # wall time from the first IMU sample to the end
    estimator_fusion_delay_s: float = 0.0  # how far the UKF ran behind the newest sample
    counters: dict[str, int] = field(default_factory=dict)
    #: the closest each health input came to its safety limit while flying (TAKEOFF, MISSION,
    #: LANDING): mocap_age_max_s, imu_gap_max_s (from sequence numbers), imu_rate_min_fraction,
    #: body_tilt_max_deg, battery_min_v, pos_min_w_m / pos_max_w_m (the estimate, per axis)
    health_extremes: dict[str, Any] = field(default_factory=dict)
    #: compute (ms) of the ticks where a cold path would show (a compile, a first-use cache):
    #: first_after_arming, first_control (the controller's first step, at TAKEOFF)
    first_ticks_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class LoopOptions:
    lockstep: bool
    imu_rate_hz: float
    ground_z_m: float
    servo_sync_every: int = 10  # lockstep: one synchronous servo cycle every N ticks (50 Hz,
    #                              the service rate of the servo process on hardware)
    preflight_timeout_s: float = 15.0
    min_preflight_s: float = 1.0
    max_start_offset_m: float = 0.3  # vehicle vs the mission's start position
    max_flight_s: float = 3600.0
    #: operator requests at given loop times (rehearsals and tests), e.g. ((30.0, "stop"),)
    scripted_requests: tuple[tuple[float, str], ...] = ()


#: a clock drift known no better than this (ppm) is not shown as a value: crystals drift by
#: tens of ppm, and after the preflight's ~1 s of samples the error bar can be 1e4 ppm
DRIFT_SHOWN_SIGMA_PPM = 1000.0


def _drift(drift_ppm: float, sigma_ppm: float) -> str:
    """A clock drift with its error bar (the clock sync has none from its first two blocks),
    or that it is not measured yet."""
    if not math.isfinite(sigma_ppm):
        return f"drift {drift_ppm:+.0f} ppm (first estimate)"
    if sigma_ppm > DRIFT_SHOWN_SIGMA_PPM:
        return f"drift not measured yet (+- {sigma_ppm:.0f} ppm)"
    return f"drift {drift_ppm:+.0f} +- {sigma_ppm:.0f} ppm"


def prepared_computer(params: VehicleParams, mission: Mission) -> FlightComputer:
    """The flight's mission, planner and controller, ready for a first tick that costs no more
    than any other: its caches built at the planner's initial tilt (where the vehicle waits)
    and its functions rehearsed (the interpreter's specialised bytecode)."""
    computer = FlightComputer(params, mission)
    computer.warm_up()
    computer.rehearse()
    return computer


class FlightLoop:
    """Runs one flight session's ticks from the first IMU sample to the end."""

    def __init__(self, *, params: VehicleParams, mission: Mission, imu: ImuLink,
                 tilt: TiltLink, pose: PoseLink, estimator: Ukf, limits: SafetyLimits,
                 options: LoopOptions, row_sink: Callable[[tuple[Any, ...]], bool],
                 event_sink: Callable[[str], None],
                 computer: FlightComputer | None = None) -> None:
        """``computer``: one from :func:`prepared_computer` for this params and mission (a
        session builds it before the IMU streams: its warm-up holds the interpreter for tens of
        milliseconds); by default the loop prepares its own."""
        self.params = params
        self.mission = mission
        self.imu, self.tilt, self.pose = imu, tilt, pose
        self.ukf = estimator
        self.opts = options
        self.sm = FlightStateMachine(limits)
        self.computer = computer if computer is not None else prepared_computer(params,
                                                                                   mission)
        self._measured_interval = mission.measured_interval_s()
        # Take-off: the plan's take-off ends where its measured part starts; it waits there
        # (the mission clock stops) until the estimate is at that height (flight.py decides)
        self._takeoff_end_tm = self._measured_interval[0] if self._measured_interval else 0.0
        self._takeoff_target_z = mission.reference(self._takeoff_end_tm).pos_w_m[2]
        self.row_sink = row_sink
        self.event_sink = event_sink
        #: called once when the mission clock starts (take-off): an emulated vehicle's scenario
        #: is timed from there (sim_backend.scenario)
        self.on_mission_start: Callable[[], None] | None = None
        #: polled every LINK_CHECK_TICKS: None while the flight record is being written, else
        #: why it is not (the telemetry process died): the vehicle then lands (before arming:
        #: the session ends)
        self.record_lost: Callable[[], str | None] | None = None
        self.period_ns = round(1e9 / options.imu_rate_hz)
        self._low_thrust_n = IMU_LOW_THRUST_FRACTION * params.mass_kg * params.gravity_m_s2
        self._blind_thrust_n = BLIND_THRUST_FRACTION * params.mass_kg * params.gravity_m_s2
        self.timer = LoopTimer(1.0 / options.imu_rate_hz)
        #: operator requests from other threads (signal handler, MAVLink): deque is atomic
        self.requests: collections.deque[Literal["arm", "land", "stop", "cut", "disarm"]] = \
            collections.deque()
        #: the current tick's time (ns, loop clock); a lockstep MoCap driver reads it
        self.now_ns = 0
        self.preflight_report: list[tuple[str, bool, str]] = []
        self.status = ""  # one-line live status, refreshed every 50 ticks
        #: optional shared block (state, preflight ok, battery V) for operator surfaces
        self.shared_status: Any = None
        #: optional queue of operator requests from another process (MAVLink)
        self.command_queue: Any = None
        self._c_f = params.rotors.thrust_coeff_n_per_hz2
        self._counters = {"telemetry_dropped": 0, "imu_missing": 0, "poses_fused": 0,
                          "servo_sync_failures": 0, "imu_gap_max_us": 0,
                          "imu_gap_max_at_ms": 0, "reseeds_imu_missed_motion": 0,
                          "reseeds_imu_link": 0, "lockstep_stalls": 0}
        self._rx_errors = 0
        self._stalled = False  # lockstep: the last sample counted lost on the wall clock
        self._faults_told = 0  # faults of the state machine already sent as events
        #: received / expected IMU samples over the last rate window (lockstep: from sequence
        #: numbers, so a degraded link is caught on the simulated clock too)
        self.imu_rate_fraction = 1.0
        self._longest_gap_ns = 0
        #: the UKF's recent re-seeds counted against MoCap (persistent disagreement): their
        #: capture times and those of the first refused pose before each
        self._reseeds: collections.deque[tuple[float, float]] = collections.deque(maxlen=8)
        self._last_frame = -1               # frame number of the newest pose taken
        self._last_pose_t_s = -math.inf     # capture time of the newest valid pose fused
        #: MoCap disagreed with the IMU in flight: its poses are no longer fused (latched)
        self.mocap_distrusted = False
        #: a re-seed found MoCap's velocity off the IMU's, and the IMU had missed no motion
        #: (latched until MoCap is distrusted: MOCAP_VELOCITY_GAP_M_S)
        self._mocap_velocity_off = False
        #: MoCap against the IMU alone (MONITOR_*): since when they disagree, and what made
        #: MoCap distrusted if it did (latched, as the above)
        self._consistency = ConsistencyMonitor(self.ukf.cfg.gravity_m_s2)
        self._monitor_bad_since_s: float | None = None
        self._monitor_verdict: Comparison | None = None
        #: the last fused pose (capture time, position, attitude), compared with the IMU at
        #: the next tick
        self._compare_next: tuple[float, tuple[float, ...], tuple[float, ...]] | None = None
        #: the IMU link's anomaly counts at the last pose (ImuLink.imu_anomalies and
        #: imu_motion_missed)
        self._imu_anomalies = 0
        self._imu_missed = 0
        #: a session limit found after this tick's state machine update, for the next one's
        #: (its transition is acted on in the tick it is made: FlightStateMachine.limit)
        self._limit_next: str | None = None
        #: the sum of the UKF's re-seeds on MoCap since arming (m, world): the mission's
        #: reference moves with them, as an autopilot moves its set-points with an estimator
        #: reset (a room recalibrated or a marker set swapped mid-flight: the vehicle has not
        #: moved, its estimate has; chasing the step lurched it 0.5 m at 42 deg)
        self._ref_offset_w_m: tuple[float, float, float] | None = None
        # UKF checkpoints and the IMU inputs since the oldest, to dead reckon from before a
        # disagreement began (DEAD_RECKON_LOOKBACK_S)
        rate_hz = 1e9 / self.period_ns
        self._checkpoint_ticks = max(1, round(CHECKPOINT_EVERY_S * rate_hz))
        self._checkpoint_phase = CHECKPOINT_PHASE % self._checkpoint_ticks
        kept = math.ceil(DEAD_RECKON_LOOKBACK_S / CHECKPOINT_EVERY_S) + 2
        self._checkpoints: collections.deque[UkfCheckpoint] = collections.deque(maxlen=kept)
        self._imu_inputs: collections.deque[tuple[Any, ...]] = collections.deque(
            maxlen=(kept + 1) * self._checkpoint_ticks)

    # -- the loop --------------------------------------------------------------------------
    def run(self) -> LoopResult:
        opts = self.opts
        sm = self.sm
        t0_s: float | None = None
        t_s = 0.0
        takeoff_t_s: float | None = None
        takeoff_wait_s = 0.0  # mission-clock time held at the take-off end for the vehicle
        lifted_off = False
        armed_tick = control_tick = -1       # tick indices, for first_ticks_ms
        steady_since_s: float | None = None  # at the take-off height and steady since
        land_here: LandHere | None = None
        alpha = 0.0
        servo_state = None
        ground_since_s: float | None = None
        aloft_since_s: float | None = None   # the mission over, the estimate off the ground
        still_since_s: float | None = None   # LANDING: at low thrust, the IMU held still
        unstill_since_s: float | None = None  # ... and since when it is not
        impact_t_s: float | None = None  # a blind landing: pressing since this impact
        impact_run = 0  # ... samples in a row over IMPACT_EXCESS_M_S2
        impact_support = 0  # ... samples in a row with the ground's support, once it presses
        thrust_lag_n = 0.0  # the commanded body-z force as the rotors lag it
        lag_s = self.ukf.cfg.force_cmd_lag_s
        lag_blend = 1.0 - math.exp(-self.period_ns * 1e-9 / lag_s) if lag_s > 0.0 else 1.0
        time_limit_told = 0  # 1: the session time limit landed the vehicle, 2: it cut
        record_lost_why: str | None = None  # the flight record lost: why (acted on once)
        record_lost_told = False
        blind_cut_told = False  # the blind landing's depth reached without a touchdown
        tick: ControlTick | None = None
        force_cmd_b: tuple[float, float, float] = (0.0, 0.0, 0.0)
        est_state = VehicleState((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
                                 (0.0, 0.0, 0.0))
        link_ok = True
        battery_v = math.inf
        prev_state = sm.state
        end_reason = "mission complete"
        n = 0
        timeout_s = self.sm.limits.imu_timeout_s
        scripted = sorted(opts.scripted_requests)
        wall_start = 0.0
        last_spins: tuple[float, ...] = ZERO6
        servo_health = ServoHealth.OK
        # IMU rate on the board's own clock: samples received per sequence numbers elapsed
        # over the last LINK_CHECK_TICKS ticks (in lockstep the wall-clock rate means nothing)
        rate_marks: collections.deque[tuple[int, int]] = collections.deque()  # (expected, n)
        expected = 0  # IMU samples due so far, each jump counted up to IMU_RATE_MAX_COUNTED_GAP
        prev_seq: int | None = None
        extremes = _Extremes()
        missing = 0  # consecutive IMU samples not received (lockstep) or empty waits
        last_arrival_ns = 0  # host monotonic time of the newest IMU sample (realtime)
        # Realtime: wait in short slices, so that during a gap the last command goes out at
        # least every slice (the board's motor watchdog stays fed) and the gap is measured on
        # the host clock; only a gap longer than imu_timeout_s is a lost stream.
        wait_s = timeout_s if opts.lockstep else min(timeout_s, IMU_GAP_SLICE_S)
        while True:
            try:
                imu = self._next_imu(wait_s)
            except DeviceLostError as exc:
                imu = None
                lost_link = str(exc)
            else:
                lost_link = ""
            start_ns = time.perf_counter_ns()
            if imu is None:
                missing += 1
                if self._stalled and t0_s is not None:
                    # nothing on the wire for LOCKSTEP_LOST_S of wall time: a host that stalled
                    # that long (or a silent board) decides which `w` steps the vehicle next,
                    # not the seed; said once, counted each time (before the stream starts the
                    # board waits for its first `w`: no step is lost there)
                    self._counters["lockstep_stalls"] += 1
                    if self._counters["lockstep_stalls"] == 1:
                        self.event_sink(
                            f"{t_s:.3f} s lockstep: no IMU sample for {LOCKSTEP_LOST_S:g} s of "
                            "wall time (a stalled host or a silent board): counted as lost, so "
                            "from here the flight depends on the host's timing, not only on "
                            "its seed")
                self._stalled = False
                if opts.lockstep and not lost_link:
                    # A lost or corrupted sample: the emulated board steps on every `w`, so
                    # answer as a real host would at its control period (hold the output).
                    age = missing * self.period_ns * 1e-9
                elif last_arrival_ns:
                    age = (time.monotonic_ns() - last_arrival_ns) * 1e-9
                else:
                    age = missing * wait_s
                if t0_s is None and not lost_link and age < 2.0:
                    if opts.lockstep:
                        self._command(last_spins)
                    continue  # the stream is starting
                if age <= timeout_s and not lost_link:
                    self._command(last_spins)
                    self._counters["imu_missing"] += 1
                    continue
                h = self._health(age if not lost_link else math.inf, False, math.inf, False,
                                 ServoHealth.OK, battery_v, est_state, False, "mission", False)
                sm.update(t_s, h)
                self._act_on_transitions(prev_state, t_s, est_state)
                prev_state = sm.state
                if sm.state in (FlightState.PREFLIGHT, FlightState.ARMED, FlightState.TAKEOFF,
                                FlightState.MISSION, FlightState.LANDING) and not lost_link:
                    self._command(last_spins)
                    continue
                end_reason = (f"Flight-Ctrl link lost ({lost_link})" if lost_link else
                              "IMU stream lost" if t0_s is not None else "no IMU stream")
                if not lost_link and last_arrival_ns:
                    self._note_gap(round(age * 1e9), t_s)  # the gap that ended the stream
                self.event_sink(f"{t_s:.3f} s {end_reason}: motors stopped (the board's "
                                "watchdog stops them too)")
                if not lost_link:
                    self._stop_motors()
                if sm.state is not FlightState.DISARMED:
                    sm.request(t_s, "cut")
                    sm.update(t_s, h)
                break
            missing = 0
            if not opts.lockstep:
                if last_arrival_ns:
                    self._note_gap(imu.arrival_t_ns - last_arrival_ns, t_s)
                last_arrival_ns = imu.arrival_t_ns
            t_ns = imu.seq * self.period_ns if opts.lockstep else imu.t_ns
            gap_s = 0.0 if prev_seq is None else (imu.seq - prev_seq) * self.period_ns * 1e-9
            if opts.lockstep and gap_s > 1.5 * self.period_ns * 1e-9:
                # lockstep: the wall clock says nothing, the board's missing samples do
                self._note_gap(round(gap_s * 1e9), t_ns * 1e-9 - (t0_s or 0.0))
            expected += 1 if prev_seq is None else min(max(imu.seq - prev_seq, 1),
                                                      IMU_RATE_MAX_COUNTED_GAP)
            prev_seq = imu.seq
            self.now_ns = t_ns
            if t0_s is None:  # lockstep: the board's own clock, sample k at k periods
                wall_start = time.perf_counter()
                t0_s = 0.0 if opts.lockstep else t_ns * 1e-9
            t_s = t_ns * 1e-9 - t0_s

            # 2. servo measurement (and, lockstep, the MoCap datagrams waiting)
            # a faulted servo is retried at 2 Hz only (each failed cycle costs a timeout)
            sync_every = opts.servo_sync_every if servo_health is not ServoHealth.FAULT \
                else 250
            servo_cycle = opts.lockstep and n % sync_every == 0
            if servo_cycle:
                # a wall-clock wait, as the simulated time stands still: a healthy servo gets
                # LOCKSTEP_SERVO_WAIT_S (a loaded host must not fake a fault), one already
                # faulted the short wait of its 2 Hz retries
                servo_wait_s = 0.3 if _servo_health(servo_state) is ServoHealth.FAULT \
                    else LOCKSTEP_SERVO_WAIT_S
                # Lockstep: the servo answers on its bus while this tick computes (the READ
                # goes out first thing, its reply is taken before `w`: the simulated time
                # stands still until then); the measurement is used from the next tick on,
                # as a free-running servo's would be.
                try:
                    self.tilt.begin_cycle(servo_wait_s)
                except Exception as exc:  # a servo fault is a health state, not a crash
                    servo_cycle = False
                    servo_state = self._servo_sync_failed(exc)
            elif not opts.lockstep:
                servo_state = self.tilt.latest()
            if opts.lockstep:  # the frames that came before this sample; fused after `w`
                self.pose.receive()
            servo_health = _servo_health(servo_state)
            if servo_state is not None and math.isfinite(servo_state.tilt_rad):
                alpha = min(max(servo_state.tilt_rad, 0.0), self.params.tilt.max_tilt_rad)

            # 3. (predict part)
            imu_input = (t_s, imu.gyro_rad_s, imu.accel_m_s2,
                         force_cmd_b if tick is not None else None)
            self._imu_inputs.append(imu_input)
            self._consistency.add_imu(t_s, imu.gyro_rad_s, imu.accel_m_s2)
            num_start_ns = time.perf_counter_ns()  # the numerics, timed apart (LoopTimer)
            self.ukf.predict(*imu_input)
            # plain floats and one check, not the full estimate (its covariance copy and
            # health report cost as much as the predict)
            force_ext = None
            if self.ukf.initialized:
                est_state = VehicleState(*self.ukf.output_state())
                force_ext = self.ukf.force_ext_w_n()
            estimator_ok = self.ukf.usable()
            num_ns = time.perf_counter_ns() - num_start_ns

            # the periodic chores on different ticks (a tick carrying both would set the
            # compute p99 at 1 kHz): operator exchange, link check
            if n % LINK_CHECK_TICKS == LINK_CHECK_TICKS // 2:
                self._exchange_with_operators(battery_v)
            if n % LINK_CHECK_TICKS == 0:
                if self.record_lost is not None and record_lost_why is None:
                    record_lost_why = self.record_lost()
                stats = self.imu.link_stats()
                # the newest mark at least a window old is the window's start
                while len(rate_marks) > 1 and \
                        expected - rate_marks[1][0] >= IMU_RATE_WINDOW_SAMPLES:
                    rate_marks.popleft()
                if rate_marks and expected > rate_marks[0][0]:
                    e0, n0 = rate_marks[0]
                    self.imu_rate_fraction = (n - n0) / (expected - e0)
                if n:  # from the second check on: the first sample may follow a free run of
                    # the emulated board (a ground station slow to start), not a lost stretch
                    rate_marks.append((expected, n))
                # in lockstep the loop itself sets the pace: judge the rate on sequence gaps
                link_ok = stats.health is not LinkHealth.LOST and (
                    self.imu_rate_fraction >= IMU_MIN_RATE_FRACTION if opts.lockstep
                    else stats.health is not LinkHealth.RATE_LOW)
                battery = self.imu.battery()
                battery_v = battery.voltage_v if battery is not None else math.inf

            # 4. operator requests, preflight and the state machine
            n_transitions = len(sm.transitions)  # those of this tick: requests, limits, update
            while scripted and scripted[0][0] <= t_s:
                self.requests.append(scripted.pop(0)[1])  # type: ignore[arg-type]
            while self.requests:
                what = self.requests.popleft()
                if what == SUSPEND_REFUSED:  # Ctrl-Z: told, not obeyed (groundstation.signals)
                    self.event_sink(f"{t_s:.3f} s operator Ctrl-Z: refused, the ground station "
                                    "keeps commanding the motors (Ctrl-C or Ctrl-\\ lands)")
                    continue
                _, why = sm.request(t_s, what)
                self.event_sink(f"{t_s:.3f} s operator {what}: {why}")
            # the session's own time limit: land once (a stop request here would count as the
            # operator's second one on the next tick and cut), cut a landing that never ends
            # (before the update: its transition is acted on in this tick, as a request's is)
            if record_lost_why is not None and not record_lost_told:
                # a flight nobody records: land it (before arming: end the session)
                record_lost_told = True
                sm.limit(t_s, f"flight record lost: {record_lost_why}")
            if self._limit_next is not None:
                sm.limit(t_s, self._limit_next)
                self._limit_next = None
            if t_s > opts.max_flight_s and time_limit_told < 1:
                time_limit_told = 1
                sm.limit(t_s, f"session time limit ({opts.max_flight_s:g} s)")
            elif t_s > opts.max_flight_s + TIME_LIMIT_CUT_S and time_limit_told < 2:
                time_limit_told = 2
                sm.limit(t_s, f"no touchdown {TIME_LIMIT_CUT_S:g} s after the session time "
                         "limit", cut=True)
            if self.mocap_distrusted and not blind_cut_told and tick is not None and \
                    tick.ref.segment == -1 and \
                    tick.ref.pos_w_m[2] <= opts.ground_z_m - BLIND_SINK_M + 1e-6:
                # the landing reference has sunk its whole depth below the ground and the IMU
                # felt no touchdown: the dead-reckoned height is wrong, the vehicle may be
                # climbing on it
                blind_cut_told = True
                sm.limit(t_s, f"no touchdown felt by the IMU {BLIND_SINK_M:g} m below the "
                         "ground on the dead-reckoned estimate", cut=True)
            if sm.state is FlightState.PREFLIGHT and n % PREFLIGHT_CHECK_TICKS == 0:
                timed_out = t_s > opts.preflight_timeout_s
                if (t_s >= opts.min_preflight_s and estimator_ok) or timed_out:
                    # the newest pose's age on the host's clock now (realtime): a pose may
                    # have been captured after this tick's IMU sample
                    pose_age_s = t_s - self._last_pose_t_s if opts.lockstep or t0_s is None \
                        else time.monotonic_ns() * 1e-9 - t0_s - self._last_pose_t_s
                    passed = self._preflight(t_s, est_state, servo_state, pose_age_s)
                    if passed or timed_out:
                        self._report_preflight(t_s)
                    if passed:
                        sm.request(t_s, "arm")
                    elif timed_out:
                        end_reason = "preflight checks failed"
                        sm.request(t_s, "stop")
            tm = t_s - takeoff_t_s - takeoff_wait_s if takeoff_t_s is not None else 0.0
            if sm.state is FlightState.TAKEOFF and tm > self._takeoff_end_tm:
                takeoff_wait_s += tm - self._takeoff_end_tm
                tm = self._takeoff_end_tm
            phase = self._mission_phase(tm)
            z = est_state.pos_w_m[2]
            lifted_off = lifted_off or (
                estimator_ok and z > opts.ground_z_m + LIFTOFF_MARGIN_M)
            if (estimator_ok and abs(z - self._takeoff_target_z) < TAKEOFF_TOLERANCE_M
                    and abs(est_state.vel_w_m_s[2]) < TAKEOFF_STEADY_M_S):
                steady_since_s = t_s if steady_since_s is None else steady_since_s
            else:
                steady_since_s = None
            at_height = steady_since_s is not None and t_s - steady_since_s >= TAKEOFF_STEADY_S
            spinning = self.imu.motors().all_spinning if sm.state is FlightState.ARMED else True
            on_ground = (sm.state is FlightState.LANDING and ground_since_s is not None
                         and t_s - ground_since_s > TOUCHDOWN_CONFIRM_S
                         and not self.mocap_distrusted)
            near_ground = self._near_ground(est_state)
            ground_since_s = (ground_since_s or t_s) if near_ground else None
            # a blind landing's touchdown impact (IMPACT_*): from it on, press on the ground
            thrust_lag_n += (force_cmd_b[2] - thrust_lag_n) * lag_blend
            if sm.state is FlightState.LANDING and self.mocap_distrusted and tick is not None \
                    and tick.ref.segment == -1 and impact_t_s is None:
                excess = imu.accel_m_s2[2] - thrust_lag_n / self.params.mass_kg
                impact_run = impact_run + 1 if excess > IMPACT_EXCESS_M_S2 else 0
                if impact_run >= 2:
                    impact_t_s = t_s
                    self.event_sink(f"{t_s:.3f} s the IMU felt an impact ({excess:+.1f} m/s^2 "
                                    "over the thrust): the landing presses on the ground")
            elif impact_t_s is not None and impact_support < IMPACT_SUPPORT_SAMPLES:
                supported = force_cmd_b[2] < self._blind_thrust_n and self._reads_g(
                    imu, BLIND_STILL_ACCEL_M_S2)
                if t_s - impact_t_s >= IMPACT_SETTLE_S:
                    impact_support = impact_support + 1 if supported else 0
                if impact_support < IMPACT_SUPPORT_SAMPLES and \
                        t_s - impact_t_s >= IMPACT_CONFIRM_S:
                    impact_t_s, impact_run, impact_support = None, 0, 0
                    self.event_sink(f"{t_s:.3f} s the IMU did not read the ground's support "
                                    "after the impact: not the ground, the landing goes on")
            # the IMU's own touchdown, whatever the estimate says (a frozen or drifting one
            # never comes near the ground): at low thrust, held still (the ground carries it);
            # a blind landing already below BLIND_THRUST_FRACTION of the weight (a dead
            # reckoning drifting on the ground kept the thrust up)
            if sm.state is FlightState.LANDING and tick is not None and (
                    (force_cmd_b[2] < self._low_thrust_n and self._imu_still(imu))
                    or (self.mocap_distrusted and tick.ref.segment == -1
                        and force_cmd_b[2] < self._blind_thrust_n
                        and self._imu_still(imu, BLIND_STILL_ACCEL_M_S2))):
                still_since_s = t_s if still_since_s is None else still_since_s
                unstill_since_s = None
            elif still_since_s is not None:
                # a lone corrupted sample (a frame without checksum) does not end it
                unstill_since_s = t_s if unstill_since_s is None else unstill_since_s
                if t_s - unstill_since_s > IMU_STILL_GRACE_S:
                    still_since_s = None
            landed_imu = still_since_s is not None and t_s - still_since_s >= IMU_LANDED_S
            mocap_consistent = self._mocap_consistent(t_s)
            if not mocap_consistent and not self.mocap_distrusted and sm.state in FLYING:
                self.mocap_distrusted = True
                back_s = self._dead_reckon(t_s)
                est_state = VehicleState(*self.ukf.output_state())
                force_ext = self.ukf.force_ext_w_n()
                self.event_sink(f"{t_s:.3f} s MoCap disagrees with the IMU: its poses are no "
                                f"longer fused; the estimate runs on the IMU alone from "
                                f"{back_s:.1f} s back, the landing ends on the IMU's touchdown")
                if land_here is not None:  # a landing already under way goes on blind
                    land_here = replace(land_here, sink_m=BLIND_SINK_M, deep_m_s=BLIND_DEEP_M_S)
                on_ground = False
            aloft_since_s = (aloft_since_s or t_s) if phase == "done" and not near_ground \
                else None
            h = self._health(0.0, link_ok, t_s - self._last_pose_t_s, estimator_ok,
                             servo_health,
                             battery_v, est_state, on_ground, phase, spinning,
                             lifted_off=lifted_off, takeoff_reached=at_height,
                             mocap_consistent=mocap_consistent,
                             servo_detail=_servo_detail(servo_state)
                             if servo_health is ServoHealth.FAULT else "",
                             ended_aloft=aloft_since_s is not None
                             and t_s - aloft_since_s >= ENDED_ALOFT_S,
                             landed_imu=landed_imu)
            flying = sm.state in FLYING  # the extremes of this tick, added after the send
            directive = sm.update(t_s, h)
            # a failsafe in a planned landing stays LANDING but is a transition all the same
            if sm.state is not prev_state or len(sm.transitions) != n_transitions:
                if sm.state is FlightState.ARMED and armed_tick < 0:
                    armed_tick = n
                if sm.state is FlightState.TAKEOFF:
                    if takeoff_t_s is None and self.on_mission_start is not None:
                        self.on_mission_start()
                    takeoff_t_s = t_s
                    tm = 0.0
                land_here = self._act_on_transitions(prev_state, t_s, est_state) or land_here
                prev_state = sm.state
            elif len(sm.faults) != self._faults_told:  # a fault that changes no state (hold)
                self._tell_faults()

            # 5. control
            spins = ZERO6
            tick = None
            num_start_ns = time.perf_counter_ns()
            if directive.reference is ReferenceSource.MISSION:
                tick = self.computer.step(tm, est_state, alpha, hold_tilt=directive.hold_tilt,
                                          force_ext_w_n=force_ext,
                                          ref_offset_w_m=self._ref_offset_w_m)
            elif directive.reference is ReferenceSource.LAND_HERE and land_here is not None:
                ref = land_here.reference(t_s, alpha)
                if impact_t_s is not None or (
                        still_since_s is not None and t_s - still_since_s >= GROUND_CONTACT_S):
                    # on the ground: no horizontal chase of the estimate (a dead reckoning
                    # drifts there; the attitude a horizontal force needs rocks it on its gear)
                    p, v = est_state.pos_w_m, est_state.vel_w_m_s
                    z, vz, az = ref.pos_w_m[2], ref.vel_w_m_s[2], ref.acc_w_m_s2[2]
                    if impact_t_s is not None and p[2] - IMPACT_PRESS_M < z:
                        z, vz, az = p[2] - IMPACT_PRESS_M, v[2], 0.0  # IMPACT_*: press
                    ref = replace(ref, pos_w_m=(p[0], p[1], z), vel_w_m_s=(v[0], v[1], vz),
                                  acc_w_m_s2=(0.0, 0.0, az))
                tick = self.computer.step(tm, est_state, alpha, ref=ref, hold_tilt=True,
                                          force_ext_w_n=force_ext)
            num_ns += time.perf_counter_ns() - num_start_ns
            if servo_cycle:  # before set_tilt: the cycle wrote the previous goal
                try:
                    servo_state = self.tilt.finish_cycle(servo_wait_s)
                except Exception as exc:
                    servo_state = self._servo_sync_failed(exc)
            if tick is not None and control_tick < 0:
                control_tick = n
            if tick is not None and directive.motors_on:
                spins = tick.cmd.spin_hz
            elif directive.motors_on:
                spins = (self.params.rotors.min_spin_hz,) * 6  # idle while spinning up
            self._command(spins)
            sent_ns = time.monotonic_ns()
            last_spins = spins
            # after the send, what the motors need not wait for: the tilt goal (the servo
            # takes it at its next cycle) and the health extremes
            if tick is not None and directive.motors_on and not directive.hold_tilt:
                self.tilt.set_tilt(tick.alpha_cmd_rad)
            if flying:
                extremes.add(h, gap_s, self.imu_rate_fraction)
            # 3. (update part) the newest MoCap frame, fused for the next tick: its decode and
            # fusion (~0.1 ms on a frame tick) stay off the path from IMU sample to command.
            # The last frame's comparison with the IMU alone runs a tick later, on a tick
            # without a frame: one frame tick carrying decode, fusion and comparison set the
            # compute p99; in lockstep, a tick without one finishes its work while the board
            # computes the next sample (it waits anyway), so the comparison costs no time.
            if self._compare_next is not None:
                compare, self._compare_next = self._compare_next, None
                if not self.mocap_distrusted:
                    self._compare_with_imu(t_s, *compare, est_state)
            if opts.lockstep:
                self.pose.handle_received()
            num_ns += self._take_pose(t0_s, t_s, est_state)
            eta_f = 1.0
            if tick is not None:  # the commanded body force feeds the UKF's force observer
                force_cmd_b, eta_f = self.computer.thrust_force_b(alpha, tick.cmd.thrusts_n)

            if n % self._checkpoint_ticks == self._checkpoint_phase and self.ukf.initialized \
                    and not self.mocap_distrusted and sm.state is not FlightState.PREFLIGHT:
                self._checkpoints.append(self.ukf.checkpoint())

            # 6. telemetry
            self._push_row(t_s, tick, alpha, est_state, spins, eta_f, directive.state)
            self.timer.record(start_ns, time.perf_counter_ns(), sent_ns - imu.arrival_t_ns,
                              num_ns)
            n += 1
            if n % 50 == 0:
                flight_s = t_s - takeoff_t_s if takeoff_t_s is not None else math.nan
                self.status = self._status_line(flight_s, tick, alpha, est_state, battery_v)
            if sm.finished:
                self._stop_motors()
                # why the flight ended: what sent it into LANDING or CUT (or the last step)
                cause = next((tr.reason for tr in reversed(sm.transitions)
                              if tr.to_state in (FlightState.LANDING, FlightState.CUT)),
                             sm.transitions[-1].reason if sm.transitions else end_reason)
                if end_reason == "mission complete":
                    end_reason = cause
                break
        return LoopResult(
            loop_wall_s=time.perf_counter() - wall_start if wall_start else 0.0,
            transitions=list(sm.transitions), faults=list(sm.faults),
            timing=self.timer.summary(), ticks=n,
            flight_time_s=(t_s - takeoff_t_s) if takeoff_t_s is not None else 0.0,
            end_reason=end_reason,
            estimator_poses_rejected=self.ukf.health().poses_rejected,
            estimator_fusion_delay_s=self.ukf.fusion_delay_s,
            telemetry_dropped=self._counters["telemetry_dropped"],
            counters=dict(self._counters),
            health_extremes=extremes.as_dict(),
            first_ticks_ms={"first_after_arming": self.timer.compute_ms(armed_tick + 1)
                            if armed_tick >= 0 else math.nan,
                            "first_control": self.timer.compute_ms(control_tick)
                            if control_tick >= 0 else math.nan},
        )

    # -- pieces ----------------------------------------------------------------------------
    def _servo_sync_failed(self, exc: Exception) -> ServoState:
        """A lockstep servo cycle that failed: counted; the last measurement stands."""
        self._counters["servo_sync_failures"] += 1
        log.debug("servo sync failed: %s", exc)
        return self.tilt.latest()

    def _exchange_with_operators(self, battery_v: float) -> None:
        """Every 0.1 s: publish the state for operator surfaces, take their requests."""
        status = self.shared_status
        if status is not None:
            status[STATUS_STATE] = float(int(self.sm.state))
            status[STATUS_PREFLIGHT] = float(all(ok for _, ok, _ in self.preflight_report)
                                             and bool(self.preflight_report))
            status[STATUS_BATTERY] = battery_v if math.isfinite(battery_v) else math.nan
        q = self.command_queue
        if q is not None:
            while True:
                try:
                    self.requests.append(q.get_nowait())
                except queue.Empty:
                    break

    def _stop_motors(self) -> None:
        """``x`` to the board; on a lost link the board's own watchdog has stopped them."""
        try:
            self.imu.stop_motors()
        except DriverError as exc:
            log.warning("cannot send the motor stop: %s", exc)

    def _note_gap(self, gap_ns: int, t_s: float) -> None:
        """Keep the longest gap between IMU arrivals (realtime; in lockstep between the board's
        sample times, counted only where samples are missing), and when it happened."""
        if gap_ns > self._longest_gap_ns:
            self._longest_gap_ns = gap_ns
            self._counters["imu_gap_max_us"] = gap_ns // 1000
            self._counters["imu_gap_max_at_ms"] = round(t_s * 1e3)

    def _command(self, spins_hz: tuple[float, ...]) -> None:
        """The rotor command (``w``). In lockstep it also steps the emulated board: the receive
        errors counted so far are noted first, so that those of the reply it triggers are
        told apart from older ones (see :meth:`_next_imu`)."""
        if self.opts.lockstep:
            self._rx_errors = self.imu.rx_errors
        self.imu.send_rotor_speeds_hz(spins_hz)

    def _next_imu(self, timeout_s: float) -> Any:
        """The next IMU sample, or None. In lockstep a lost sample is noticed at once when the
        link reports a receive error (a corrupted frame) since the last command, otherwise
        after ``LOCKSTEP_LOST_S`` of wall time; on hardware after ``timeout_s``.

        Lockstep stays deterministic on a loaded host: a sample that is only late (the
        emulator not yet scheduled) is waited for. Errors older than the last command do not
        count, and once an error is seen one more look for the sample (``wait_next`` takes the
        driver's receive lock, so the chunk that carried the error is filed whole by then)
        finds it if that chunk carried it. (Taking a late sample for lost would send a second
        ``w`` and step the vehicle twice: a different flight.)"""
        if not self.opts.lockstep:
            return self.imu.wait_next(timeout_s)
        waited = 0.0
        while waited < LOCKSTEP_LOST_S:
            imu = self.imu.wait_next(LOCKSTEP_SLICE_S)
            if imu is not None:
                return imu
            waited += LOCKSTEP_SLICE_S
            errors = self.imu.rx_errors
            if errors != self._rx_errors:
                self._rx_errors = errors
                return self.imu.wait_next(0.0)
        self._stalled = True
        return None

    def _take_pose(self, t0_s: float, t_s: float, est: VehicleState) -> int:
        """Fuse the newest pose if it is a new frame. The UKF replays from the capture time; it
        needs one IMU sample first (its clock starts with the first prediction). A re-seed
        from armed on moves the mission's reference by the estimate's step (``est``: this
        tick's estimate, before it). A fused pose is compared with the IMU alone at the next
        tick (``_compare_next``). Returns the UKF update's time (ns; 0 without one), part of
        the tick's numerics."""
        pose = self.pose.latest()
        if pose is None or pose.frame_number == self._last_frame:
            return 0
        self._last_frame = pose.frame_number
        update_ns = 0
        if pose.valid and self.mocap_distrusted:  # received, not fused
            self._last_pose_t_s = pose.t_ns * 1e-9 - t0_s
        elif pose.valid:
            cap_s = pose.t_ns * 1e-9 - t0_s
            anomalies = self.imu.imu_anomalies   # at the pose rate: counters, polled
            if anomalies != self._imu_anomalies:
                missed = self.imu.imu_motion_missed
                self.ukf.note_imu_anomaly(t_s, motion_missed=missed != self._imu_missed)
                self._imu_anomalies, self._imu_missed = anomalies, missed
            num_start_ns = time.perf_counter_ns()
            verdict = self.ukf.update_pose(cap_s, pose.pos_w_m, pose.q_wb) \
                if math.isfinite(self.ukf.t_s) else None
            update_ns = time.perf_counter_ns() - num_start_ns
            if verdict is PoseVerdict.RESET:
                self._judge_reset(t_s, cap_s, est)
            elif verdict is PoseVerdict.ACCEPTED or verdict is PoseVerdict.REJECTED:
                self._compare_next = (cap_s, pose.pos_w_m, pose.q_wb)  # the next tick's
            self._last_pose_t_s = cap_s
            self._counters["poses_fused"] += 1
        return update_ns

    def _act_on_transitions(self, prev: FlightState, t_s: float, est: VehicleState
                            ) -> LandHere | None:
        sm = self.sm
        land: LandHere | None = None
        for tr in sm.transitions:
            if tr.t_s < t_s or tr.from_state is FlightState.DISARMED:
                continue
            self.event_sink(f"{tr.t_s:.3f} s {tr.from_state.name} -> {tr.to_state.name}: "
                            f"{tr.reason}")
            if self.shared_status is not None:  # every change, for the operator surfaces
                post_transition(self.shared_status, tr.t_s, int(tr.to_state))
            if tr.to_state is FlightState.ARMED:
                self.imu.request_motor_start()
            elif tr.to_state in (FlightState.CUT, FlightState.DISARMED):
                self._stop_motors()
            elif tr.to_state is FlightState.LANDING:
                q = est.q_wb
                yaw = math.atan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))
                land = LandHere(t_s, est.pos_w_m, (math.cos(yaw / 2), 0.0, 0.0,
                                                   math.sin(yaw / 2)), self.opts.ground_z_m,
                                **({"sink_m": BLIND_SINK_M, "deep_m_s": BLIND_DEEP_M_S}
                                   if self.mocap_distrusted else {}))
        self._tell_faults()
        return land

    def _tell_faults(self) -> None:
        """Every fault the state machine recorded since the last call, as an event."""
        for fault in self.sm.faults[self._faults_told:]:
            self.event_sink(f"FAULT {fault}")
        self._faults_told = len(self.sm.faults)

    def _preflight(self, t_s: float, est: VehicleState, servo: Any,
                   pose_age_s: float) -> bool:
        """The checks of the architecture page; each with its value. True if all pass."""
        stats = self.imu.link_stats()
        mstats = self.pose.stats()
        start = self.mission.start_pos_w_m
        # every check that reads the estimate fails until the UKF has initialised: before
        # that the state is a placeholder (zeros), not a measurement
        initialized = self.ukf.initialized
        offset = math.dist(est.pos_w_m, start)
        if self.opts.lockstep:  # the loop sets the pace: count the samples that arrived
            imu_ok = self.imu_rate_fraction >= IMU_MIN_RATE_FRACTION
            imu_value = (f"{100 * self.imu_rate_fraction:.0f} % of the samples arrived "
                         "(lockstep: from sequence numbers)")
        else:
            imu_rate = stats.imu.measured_rate_hz
            # above the set rate is no better than below it: a backlog read in one burst, or a
            # board streaming faster than the session plans for (the check repeats: a burst
            # slides out of the rate window)
            imu_ok = (IMU_MIN_RATE_FRACTION * self.opts.imu_rate_hz <= imu_rate
                      <= IMU_MAX_RATE_FRACTION * self.opts.imu_rate_hz)
            imu_value = f"{imu_rate:.0f} Hz of {self.opts.imu_rate_hz:.0f} Hz"
            clk = stats.imu_clock  # the board's sample clock against ours (clock sync)
            if clk.known:
                imu_value += (f"; board clock {clk.rate_hz:.1f} Hz, offset {clk.offset_s:+.3f} s,"
                              f" {_drift(clk.drift_ppm, clk.drift_sigma_ppm)}")
        checks = [
            ("flight-ctrl streaming IMU at 80-125 % of the set rate", imu_ok, imu_value),
            ("servo answers, multi-turn, at the commanded angle",
             servo is not None and servo.ok and abs(servo.tilt_rad - servo.goal_tilt_rad)
             < math.radians(1.0) if servo is not None and math.isfinite(servo.goal_tilt_rad)
             else servo is not None and servo.ok,
             "no reading" if servo is None else
             f"{servo.health.name}, tilt {math.degrees(servo.tilt_rad):.2f} deg"),
            ("MoCap sees the body at >= 80 % of its rate",
             pose_age_s < 0.1 and (mstats.rate_hz >= 80.0 or self.opts.lockstep),
             f"{mstats.rate_hz:.0f} Hz, newest pose {1e3 * pose_age_s:.0f} ms old"
             + (f"; server clock offset {mstats.clock_offset_s:+.3f} s, "
                f"{_drift(mstats.clock_drift_ppm, mstats.clock_drift_sigma_ppm)}"
                if math.isfinite(mstats.clock_drift_ppm)
                else "")),
            ("estimator converged", initialized and self.ukf.health().ok,
             f"flags {self.ukf.health().flags.name or 'none'}"),
            ("vehicle at the mission's start position",
             initialized and offset < self.opts.max_start_offset_m,
             f"{offset * 1e3:.0f} mm away" if initialized else "no estimate yet"),
            ("configuration validated", True, "session, vehicle and mission files"),
        ]
        self.preflight_report = [(name, bool(ok), value) for name, ok, value in checks]
        return all(ok for _, ok, _ in self.preflight_report)

    def _report_preflight(self, t_s: float) -> None:
        for name, ok, value in self.preflight_report:
            self.event_sink(f"{t_s:.3f} s preflight {'PASS' if ok else 'FAIL'}: {name} "
                            f"({value})")

    def _mission_phase(self, tm: float) -> Literal["takeoff", "mission", "land", "done"]:
        if tm >= self.mission.duration_s:
            return "done"
        interval = self._measured_interval
        if interval is None:
            return "mission"
        start, end = interval
        if tm < start:
            return "takeoff"
        return "mission" if tm < end else "land"

    def _imu_still(self, imu: Any, accel_tol_m_s2: float = IMU_STILL_ACCEL_M_S2) -> bool:
        """This IMU sample reads a vehicle at rest: its specific force is g (within
        ``accel_tol_m_s2``), its rates are small."""
        gx, gy, gz = imu.gyro_rad_s
        return (self._reads_g(imu, accel_tol_m_s2) and abs(gx) < IMU_STILL_RATE_RAD_S
                and abs(gy) < IMU_STILL_RATE_RAD_S and abs(gz) < IMU_STILL_RATE_RAD_S)

    def _reads_g(self, imu: Any, accel_tol_m_s2: float) -> bool:
        """This IMU sample's specific force is g within ``accel_tol_m_s2``: something carries
        the vehicle's weight (at rest, or pressed at low thrust on the ground)."""
        ax, ay, az = imu.accel_m_s2
        return abs(math.sqrt(ax * ax + ay * ay + az * az)
                   - self.params.gravity_m_s2) < accel_tol_m_s2

    def _near_ground(self, est: VehicleState) -> bool:
        # height only: the contact's impacts make the estimated vertical speed jumpy, and a
        # bounce that leaves this band restarts the confirmation anyway
        return est.pos_w_m[2] < self.opts.ground_z_m + 0.04

    def _health(self, imu_age_s: float, link_ok: bool, mocap_age_s: float, estimator_ok: bool,
                servo: ServoHealth, battery_v: float, est: VehicleState, on_ground: bool,
                phase: Literal["takeoff", "mission", "land", "done"], spinning: bool,
                lifted_off: bool = True, takeoff_reached: bool = True,
                mocap_consistent: bool = True, servo_detail: str = "",
                ended_aloft: bool = False, landed_imu: bool = False) -> HealthSnapshot:
        q = est.q_wb
        r33 = 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2])
        return HealthSnapshot(
            imu_age_s=imu_age_s, imu_rate_ok=link_ok, mocap_age_s=mocap_age_s,
            estimator_ok=estimator_ok, servo=servo, battery_v=battery_v, pos_w_m=est.pos_w_m,
            body_tilt_deg=math.degrees(math.acos(max(-1.0, min(1.0, r33)))),
            on_ground=on_ground, mission_phase=phase, motors_spinning=spinning,
            lifted_off=lifted_off, takeoff_reached=takeoff_reached,
            mocap_consistent=mocap_consistent, servo_detail=servo_detail,
            ended_aloft=ended_aloft, landed_imu=landed_imu,
        )

    def _judge_reset(self, t_s: float, cap_s: float, est: VehicleState) -> None:
        """The UKF re-seeded on MoCap (``est``: this tick's estimate, before): which sensor was
        wrong? Their velocities differ (MOCAP_VELOCITY_GAP_M_S): the IMU if it surely missed
        motion around the refusals (an accelerometer at the link's limit, an impact's step;
        the UKF took MoCap's velocity: nothing moves), else MoCap (it changed speed without the
        IMU feeling it: the failsafe). They agree: a small step on a failing IMU link is the
        estimate's own (corrupted samples kick it); else MoCap jumped (a marker swap, a
        recalibrated room): the mission's reference moves with the estimate, or, on the
        ground, the flight does not start. MoCap jumps and MoCap found off the IMU count
        towards MoCap disagreeing with the IMU (RESEEDS_INCONSISTENT)."""
        info = self.ukf.last_reset
        if info is None:
            return
        gap = info.velocity_gap_m_s
        step_m = math.dist(est.pos_w_m, self.ukf.output_state()[0])
        if gap > MOCAP_VELOCITY_GAP_M_S and info.imu_missed_motion:
            self._counters["reseeds_imu_missed_motion"] += 1
            if self.sm.state in MOTORS_ON:
                self.event_sink(f"{t_s:.3f} s the IMU missed motion (an impact beyond the "
                                "link's range): the estimate re-seeded on MoCap, velocity "
                                f"included ({gap:.2f} m/s off)")
            return
        if info.imu_suspect and step_m < MOCAP_JUMP_MIN_M and not gap > MOCAP_VELOCITY_GAP_M_S:
            self._counters["reseeds_imu_link"] += 1     # corrupted samples kicked the estimate
            return
        self._reseeds.append((cap_s, info.streak_start_s))
        if self.sm.state not in MOTORS_ON:
            return
        if gap > MOCAP_VELOCITY_GAP_M_S and self.sm.state in FLYING:
            self._mocap_velocity_off = True
            self.event_sink(
                f"{t_s:.3f} s MoCap's velocity is {gap:.2f} m/s off the IMU's, which missed "
                "no motion (MoCap ({:+.2f}, {:+.2f}, {:+.2f}) m/s, IMU ({:+.2f}, {:+.2f}, "
                "{:+.2f}) m/s): a change of velocity the IMU did not feel".format(
                    *(info.vel_mocap_w_m_s or (math.nan,) * 3), *info.vel_est_w_m_s))
            return
        if self.sm.state is FlightState.ARMED:
            # on the ground: MoCap moved a vehicle that did not (a marker set swapped, the
            # room recalibrated); a mission flown in the tracker's new frame goes where
            # nobody planned it to, so it does not start
            if step_m >= MOCAP_JUMP_MIN_M:
                self._limit_next = (f"MoCap jumped {step_m:.2f} m while armed on the ground "
                                    "(check the tracker's rigid body)")
            return
        self._move_reference(t_s, est.pos_w_m)

    def _compare_with_imu(self, t_s: float, cap_s: float, pos_w_m: tuple[float, ...],
                          q_wb: tuple[float, ...], est: VehicleState) -> None:
        """MoCap against the IMU alone (estimator.consistency, MONITOR_*): in the air, a
        disagreement that lasts makes MoCap distrusted."""
        bg, ba = self.ukf.biases()
        cmp = self._consistency.add_pose(cap_s, pos_w_m, q_wb, bg, ba,
                                         accel_clean_since_s=self.ukf.imu_anomaly_t_s)
        if cmp is None:
            return
        if not (self.sm.state in FLYING
                and est.pos_w_m[2] > self.opts.ground_z_m + MONITOR_MIN_HEIGHT_M
                and (cmp.rotation_deg > (MONITOR_ROTATION_DEG
                                         if math.isfinite(cmp.velocity_gap_m_s)
                                         else MONITOR_ROTATION_FAILING_LINK_DEG)
                     or cmp.velocity_gap_m_s > MONITOR_VELOCITY_M_S)):
            self._monitor_bad_since_s = None
            return
        since = self._monitor_bad_since_s
        if since is None:
            self._monitor_bad_since_s = cmp.t_s
            return
        if cmp.t_s - since < MONITOR_PERSIST_S or self._monitor_verdict is not None:
            return
        self._monitor_verdict = cmp
        velocity = (f"changed velocity {cmp.velocity_gap_m_s:.3f} m/s more than the accelerometer "
                    f"felt (limits {MONITOR_ROTATION_DEG:g} deg, {MONITOR_VELOCITY_M_S:g} m/s)"
                    if math.isfinite(cmp.velocity_gap_m_s) else
                    "(the IMU link had anomalies: velocity not compared, rotation's limit "
                    f"{MONITOR_ROTATION_FAILING_LINK_DEG:g} deg)")
        self.event_sink(f"{t_s:.3f} s MoCap disagrees with the IMU alone over the last "
                        f"{cmp.t_s - cmp.start_s:.2f} s: it turned {cmp.rotation_deg:.2f} deg "
                        f"more than the gyro felt and {velocity}")

    def _move_reference(self, t_s: float, before_w_m: tuple[float, float, float]) -> None:
        """The estimate was re-seeded on MoCap: the mission's reference moves by its step."""
        after = self.ukf.output_state()[0]
        step = (after[0] - before_w_m[0], after[1] - before_w_m[1], after[2] - before_w_m[2])
        o = self._ref_offset_w_m or (0.0, 0.0, 0.0)
        self._ref_offset_w_m = (o[0] + step[0], o[1] + step[1], o[2] + step[2])
        self.event_sink(f"{t_s:.3f} s MoCap jumped: the estimate re-seeded on it "
                        f"{math.hypot(*step):.2f} m away; the mission's reference moved with "
                        "it ({:+.2f}, {:+.2f}, {:+.2f}) m".format(*step))
        self.sm.note_fault(t_s, f"MoCap jumped {math.hypot(*step):.2f} m: the mission goes on "
                           "in the tracker's new frame")

    def _dead_reckon(self, t_s: float) -> float:
        """The UKF back to its newest checkpoint at least DEAD_RECKON_LOOKBACK_S old (else its
        oldest), then on the IMU alone to now; how far back it went (s). MoCap found wrong by
        the comparison with the IMU alone (MONITOR_*): only to MOCAP_OFF_LEAD_S before its
        horizon, if that is later (the poses agreed then; a freeze at 4.5 s in the hover, dead
        reckoned from 3 s back, drifted 0.50 m and rocked the vehicle to 23 deg on its gear,
        from 1.7 s back 0.14 m and 2 deg). On an IMU link that
        failed in the last ANOMALOUS_LINK_S (corrupted samples kick a dead reckoning), only to
        MOCAP_OFF_LEAD_S before the refusals of the oldest re-seed counted began, if that is
        later: 3 s of a 0.5 % corrupted link's IMU through a take-off sank the dead reckoning
        10 m under a vehicle that its controller then climbed to 11 m. (Always going back
        that little missed a tracker frozen in the hover on a clean link, found only once the
        landing moved, 3 s later.)"""
        cps = self._checkpoints
        if not cps:
            return 0.0
        before_s = t_s - DEAD_RECKON_LOOKBACK_S
        if self._monitor_verdict is not None:
            before_s = max(before_s, self._monitor_verdict.start_s - MOCAP_OFF_LEAD_S)
        if self.ukf.imu_anomaly_t_s >= t_s - ANOMALOUS_LINK_S:
            before_s = max(before_s, self._refusals_began_s - MOCAP_OFF_LEAD_S)
        cp = cps[0]
        for c in cps:
            if c.t_s <= before_s:
                cp = c
        self.ukf.dead_reckon_from(cp, self._imu_inputs)
        return t_s - cp.t_s

    @property
    def _refusals_began_s(self) -> float:
        """When the refusals of the oldest re-seed counted in the inconsistency window began
        (-inf before any)."""
        newest = self._reseeds[-1][0] if self._reseeds else -math.inf
        return min((s for r, s in self._reseeds if newest - r <= RESEED_WINDOW_S),
                   default=-math.inf)

    def _mocap_consistent(self, t_s: float) -> bool:
        """False while MoCap and the IMU keep disagreeing: MoCap moved as the IMU alone did
        not feel (MONITOR_*, or a re-seed's velocity: latched), or the UKF re-seeded from
        MoCap at least ``RESEEDS_INCONSISTENT`` times within ``RESEED_WINDOW_S`` (one re-seed
        is a marker swap or a recalibrated room; repeated ones are a frozen or wrong
        tracker)."""
        if self._mocap_velocity_off or self._monitor_verdict is not None:
            return False
        n = 0
        for r, _ in self._reseeds:
            if t_s - r <= RESEED_WINDOW_S:
                n += 1
        return n < RESEEDS_INCONSISTENT

    def _push_row(self, t_s: float, tick: ControlTick | None, alpha: float,
                  est: VehicleState, spins: tuple[float, ...], eta_f: float,
                  state: FlightState) -> None:
        nan = math.nan
        row: tuple[Any, ...]  # flat (record.flat_row): the ring packs it without numpy
        if tick is not None:
            ref, cmd = tick.ref, tick.cmd
            row = (t_s, ref.segment, ref.measured and state is FlightState.MISSION,
                   _mask(cmd.saturated), 0, *ref.pos_w_m, *ref.vel_w_m_s, *ref.acc_w_m_s2,
                   *ref.q_wr, tick.alpha_ref_rad, tick.alpha_cmd_rad, alpha,
                   *rot_to_quat(cmd.r_wd), *est.pos_w_m, *est.vel_w_m_s, *est.q_wb,
                   *est.omega_b_rad_s, *est.pos_w_m, *est.q_wb, *spins, *spins, *cmd.thrusts_n,
                   *cmd.f_r_w_n, *cmd.u_f_b_n, *cmd.u_tau_b_n_m, cmd.r_xy_n, cmd.theta_rad,
                   eta_f)
        else:
            zero3 = (0.0, 0.0, 0.0)
            row = (t_s, -1, False, 0, 1, *est.pos_w_m, *zero3, *zero3, 1.0, 0.0, 0.0, 0.0,
                   nan, nan, alpha, 1.0, 0.0, 0.0, 0.0, *est.pos_w_m, *est.vel_w_m_s,
                   *est.q_wb, *est.omega_b_rad_s, *est.pos_w_m, *est.q_wb, *spins, *spins,
                   *(self._c_f * s * s for s in spins), *zero3, *zero3, *zero3, 0.0, 0.0, 1.0)
        if not self.row_sink(row):
            self._counters["telemetry_dropped"] += 1

    def _status_line(self, flight_s: float, tick: ControlTick | None, alpha: float,
                     est: VehicleState, battery_v: float) -> str:
        # "--" until known: no flight time before take-off (flight_s: since take-off, NaN
        # before), no estimate-based error before the controller runs, no battery reading
        # before the board's first B frame
        err = math.dist(est.pos_w_m, tick.ref.pos_w_m) * 1e3 if tick is not None else math.nan
        timing = self.timer.last_compute_s() * 1e3
        # most important first: a narrow terminal cuts the end
        return (f"{self.sm.state.name:<9} {number(flight_s, '5.1f', 's'):>7}  "
                f"pos. error {number(err, '4.1f', 'mm')}"
                f"  tilt {math.degrees(alpha):4.1f} deg  battery {number(battery_v, '5.2f', 'V')}"
                f"  late ticks {self.timer.deadline_misses}  tick {timing:4.2f} ms")


class _Extremes:
    """Running extremes of the health inputs while flying (a few float compares per tick)."""

    def __init__(self) -> None:
        inf = math.inf
        self.mocap_age_max_s = self.imu_gap_max_s = self.body_tilt_max_deg = 0.0
        self.imu_rate_min_fraction = 1.0
        self.battery_min_v = inf
        self.pos_min = [inf, inf, inf]
        self.pos_max = [-inf, -inf, -inf]

    def add(self, h: HealthSnapshot, imu_gap_s: float, imu_rate_fraction: float) -> None:
        self.mocap_age_max_s = max(self.mocap_age_max_s, h.mocap_age_s)
        self.imu_gap_max_s = max(self.imu_gap_max_s, imu_gap_s)
        self.imu_rate_min_fraction = min(self.imu_rate_min_fraction, imu_rate_fraction)
        self.body_tilt_max_deg = max(self.body_tilt_max_deg, h.body_tilt_deg)
        self.battery_min_v = min(self.battery_min_v, h.battery_v)
        lo, hi, p = self.pos_min, self.pos_max, h.pos_w_m
        for i in range(3):
            if p[i] < lo[i]:
                lo[i] = p[i]
            if p[i] > hi[i]:
                hi[i] = p[i]

    def as_dict(self) -> dict[str, Any]:
        return {"mocap_age_max_s": self.mocap_age_max_s, "imu_gap_max_s": self.imu_gap_max_s,
                "imu_rate_min_fraction": self.imu_rate_min_fraction,
                "body_tilt_max_deg": self.body_tilt_max_deg,
                "battery_min_v": self.battery_min_v,
                "pos_min_w_m": tuple(self.pos_min), "pos_max_w_m": tuple(self.pos_max)}


def _mask(flags: tuple[bool, ...]) -> int:
    m = 0
    for i, f in enumerate(flags):
        if f:
            m |= 1 << i
    return m


def _servo_detail(state: Any) -> str:
    """The driver's health of a faulted servo in words ("no reply", "stale", "servo error,
    error bits OVERLOAD"), for the fault line the operator reads."""
    if state is None:
        return "no measurement"
    text = state.health.name.lower().replace("_", " ")
    if state.errors:
        text += f", error bits {state.errors.name or int(state.errors)}"
    return text


def _servo_health(state: Any) -> ServoHealth:
    """The driver's detailed health -> what the state machine acts on: a corrupted reply is a
    degraded link (the next cycle may be fine; a lasting problem becomes NO_REPLY or STALE),
    anything else that is not OK is a fault (no reply, stale, error bits, unplugged, ...)."""
    if state is None or state.health is DxlHealth.OK:
        return ServoHealth.OK
    if state.health is DxlHealth.CORRUPT_REPLY:
        return ServoHealth.DEGRADED
    return ServoHealth.FAULT
