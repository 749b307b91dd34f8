"""The link to the own autopilot, held by :class:`~atlas_onboard.mavlink.transport.MavlinkTransport`: the
autopilot's HEARTBEAT, TIMESYNC answers, the EKF origin, its attitude and velocity, and the pose sent to it.

The autopilot is one (system, component), pinned for the link's life: the first autopilot-typed
HEARTBEAT from component 1 of the configured system id (``system_id``, the autopilot's), or, when none
came for AUTOPILOT_WAIT_NS, from another system (a misconfigured id: warned). No other HEARTBEAT
replaces it (behind a router, other vehicles' flight controllers and ground stations talk too), and
ATTITUDE, LOCAL_POSITION_NED (or ODOMETRY), TIMESYNC, GPS_GLOBAL_ORIGIN and the autopilot type count only
from it. On a link with ``signing`` and ``require`` (an autopilot that signs: docs/mavlink-router.md), only
from its signed frames."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from scipy.spatial.transform import Rotation

from atlas_onboard.config import NodeConfig
from atlas_onboard.core.attitude import AttitudeHistory
from atlas_onboard.core.bootclock import BootClock
from atlas_onboard.core.records import AutopilotPose
from atlas_onboard.core.shutter import BodyRate, BodyVelocity, RateHistory
from atlas_onboard.core.velocity import VelocityHistory, level_enu_of_ned
from atlas_onboard.counters import Counters
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import autopilot, codec, framing
from atlas_onboard.mavlink.link import Link

_logger = logging.getLogger(__name__)

NS = 1_000_000_000
MAV_COMP_ID_AUTOPILOT1 = 1
ORIGIN_REQUEST_NS = NS // 2  # GPS_GLOBAL_ORIGIN asked for this often until the autopilot reports one
ORIGIN_UNANSWERED = 2  # requests unanswered before SET_GPS_GLOBAL_ORIGIN (then twice as many each time)
ATTITUDE_INTERVAL_US = 20_000  # ATTITUDE asked for at 50 Hz (MAV_CMD_SET_MESSAGE_INTERVAL) when it does not come
ATTITUDE_WAIT_NS = 2 * NS  # silence after which ATTITUDE is asked for again (at most ATTITUDE_ASKS times)
ATTITUDE_ASKS = 5
AUTOPILOT_WAIT_NS = 3 * NS  # an autopilot of another system id is taken only after this without the configured one
ATTITUDE_LEAD_US = 20_000
"""An ATTITUDE stamped so that it maps this far after its own arrival (plus ATTITUDE_DRIFT of the time
since the last one taken) is refused (``attitude_ahead``): a real one never maps after its arrival
but for the clocks' drift, and one stamped ahead would hold back every real sample after it."""
ATTITUDE_DRIFT = 1e-3
ATTITUDE_REMAP_NS = 2 * NS  # every sample refused as ahead for this long: the wall clock stepped back, remap
LOCAL_POSITION_INTERVAL_US = 33_333  # LOCAL_POSITION_NED asked for at 30 Hz (its velocity: a rolling shutter's)


@dataclass
class _Stream:
    """One timed stream of the autopilot's (ATTITUDE, LOCAL_POSITION_NED): its boot clock mapping, the
    requests sent for it, and the samples refused as mapping after their arrival."""

    clock: BootClock = field(default_factory=BootClock)
    asks: int = 0
    next_ask_ns: int = 0
    taken_ns: int | None = None
    refused_since_ns: int | None = None


def wall_ns(wall_clock: Callable[[], float]) -> int:
    """The wall clock (UNIX epoch) in ns, to the microsecond (the resolution of a float of seconds)."""
    return round(wall_clock() * 1e6) * 1000


class AutopilotLink:
    """The own autopilot's link (``link``, None without ``autopilot`` in the node settings) and everything
    said over it. The transport starts it, ticks it, and hands it the pose to send; the attitude it keeps
    (``attitude``) is what the listener's gravity check reads."""

    def __init__(
        self,
        config: NodeConfig,
        component_id: int,
        wall_clock: Callable[[], float] = time.time,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.settings = config.autopilot
        self.system_id = config.system_id
        self.wall = wall_clock
        self.monotonic_ns = monotonic_ns  # the clock of the arrival stamps
        self.link = (
            Link(self.settings.link, "autopilot", config.system_id, component_id, config.state_dir, link_id=0,
                 wall_clock=wall_clock, origin_ok=self.may_be_autopilot)
            if self.settings is not None
            else None
        )  # fmt: skip
        self.counters = Counters()
        signing = self.settings.link.signing if self.settings is not None else None
        self._signed_only = signing is not None and signing.require
        self.autopilot_system: int | None = None  # from the autopilot's HEARTBEAT
        self.autopilot_component: int | None = None
        self.autopilot_type: int | None = None  # MAV_AUTOPILOT_* (PX4 12, ArduPilot 3)
        self._candidate: tuple[int, int, int] | None = None  # another system's autopilot: (system, type, first ns)
        self._next_origin_ns = 0
        self._origin_unanswered = 0  # origin requests since the last SET_GPS_GLOBAL_ORIGIN, unanswered
        self._origin_sets = 0
        self._origin_skipped = False
        self.origin_known = False
        # --- the autopilot's attitude: gravity for a single tag's ambiguity ---
        self.attitude = AttitudeHistory()
        self.rates = RateHistory()  # ATTITUDE's body rates: a rolling shutter's shear (core.shutter)
        self._attitude_stream = _Stream()
        # --- LOCAL_POSITION_NED's velocity: a rolling shutter's motion over the readout (core.velocity);
        # its own clock mapping, so that the attitude's is the same with or without it ---
        self.velocities = VelocityHistory()
        self._velocity_stream = _Stream()
        self._odometry_stream = _Stream()  # ODOMETRY's velocity, where LOCAL_POSITION_NED's does not come

    def may_be_autopilot(self, msg: Any) -> bool:
        """Whether ``msg`` may prove a UDP source address the autopilot's: from the pinned autopilot's
        system, or before one is pinned from the configured system id or another system's candidate."""
        system_id = msg.get_srcSystem()
        if self.autopilot_system is not None:
            return system_id == self.autopilot_system
        return system_id == self.system_id or (self._candidate is not None and system_id == self._candidate[0])

    def is_autopilot(self, msg: Any) -> bool:
        """Whether ``msg`` comes from the pinned autopilot (signed, where the link requires it)."""
        if self._signed_only and not framing.is_signed(msg):
            return False
        return self.autopilot_system is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == (
            self.autopilot_system,
            self.autopilot_component,
        )

    def start(self) -> None:
        if self.link is not None:
            self.link.start(self._on_message)

    def tick(self, now_ns: int) -> None:
        """The EKF origin and the ATTITUDE and LOCAL_POSITION_NED streams, asked for (or set) when due."""
        self._origin_tick(now_ns)
        self._ask_tick(now_ns, self._attitude_stream, self.attitude.latest_us(), autopilot.MSG_ATTITUDE,
                       ATTITUDE_INTERVAL_US, "attitude_requested")  # fmt: skip
        self._ask_tick(now_ns, self._velocity_stream, self.velocities.latest_us(), autopilot.MSG_LOCAL_POSITION_NED,
                       LOCAL_POSITION_INTERVAL_US, "local_position_requested")  # fmt: skip

    def attitude_at(self, t_us: int) -> Rotation | None:
        """The autopilot's attitude at ``t_us`` (wall clock, us) as a scipy Rotation of the body FLU in a
        level ENU frame of the autopilot's heading, or None (see :meth:`AttitudeHistory.attitude_at`)."""
        return self.attitude.attitude_at(t_us)

    def rate_at(self, t_us: int) -> BodyRate | None:
        """The autopilot's body rate (FLU) at ``t_us`` (wall clock, us), or None (see :class:`RateHistory`)."""
        return self.rates.rate_at(t_us)

    def velocity_at(self, t_us: int) -> BodyVelocity | None:
        """The autopilot's velocity at ``t_us`` (wall clock, us) in the body's FLU axes, turned by its own
        attitude then, or None (see :class:`VelocityHistory`)."""
        return self.velocities.velocity_at(t_us, self.attitude.attitude_at(t_us))

    def send_autopilot(self, pose: AutopilotPose) -> None:
        """VISION_POSITION_ESTIMATE (or ODOMETRY) of the own entity; a non-finite pose is counted, not sent."""
        if self.link is None or self.settings is None:
            return
        d = self.link.dialect
        speed = None
        try:
            if self.settings.output.value == "odometry":
                msg = codec.odometry(d, pose.pose, pose.reset_counter)
            else:
                msg = codec.vision_position_estimate(d, pose.pose, pose.reset_counter)
                speed = codec.vision_speed_estimate(d, pose.pose, pose.reset_counter)
        except AtlasError as exc:
            self.counters.inc("autopilot_pose_refused")
            _logger.debug("pose not sent to the autopilot: %s", exc)
            return
        self.link.send(msg)
        if speed is not None:
            self.link.send(speed)  # the EKF velocity, for ArduPilot (EK3_SRC1_VELXY=6); PX4 ignores it

    def send_landing_target(self, fields: dict[str, Any]) -> None:
        """LANDING_TARGET (#149) to the autopilot, addressed to its system."""
        if self.link is not None:
            self.link.send(self.link.dialect.MAVLink_landing_target_message(**fields))

    def _ask_tick(self, now_ns: int, stream: _Stream, last_us: int | None, msg_id: int, interval_us: int,
                  counter: str) -> None:  # fmt: skip
        """Ask the autopilot for a stream (MAV_CMD_SET_MESSAGE_INTERVAL) when none of it came for
        ATTITUDE_WAIT_NS after its HEARTBEAT; at most ATTITUDE_ASKS times (a link without it works as before)."""
        if self.link is None or self.autopilot_system is None or stream.asks >= ATTITUDE_ASKS:
            return
        if last_us is not None and wall_ns(self.wall) // 1000 - last_us < ATTITUDE_WAIT_NS // 1000:
            return
        if stream.next_ask_ns == 0:
            stream.next_ask_ns = now_ns + ATTITUDE_WAIT_NS  # give the autopilot's own streams a chance
        if now_ns < stream.next_ask_ns:
            return
        stream.next_ask_ns = now_ns + ATTITUDE_WAIT_NS
        stream.asks += 1
        fields = autopilot.set_message_interval_fields(
            self.autopilot_system, self.autopilot_component or 0, msg_id, interval_us
        )
        self.link.send(self.link.dialect.MAVLink_command_long_message(**fields))
        self.counters.inc(counter)

    def _stamp(self, stream: _Stream, msg: Any, arrival_ns: int, name: str, boot_us: int | None = None) -> int | None:
        """The wall time (us) of a sample stamped ``boot_us`` on the autopilot's clock (default: its
        ``time_boot_ms``; see BootClock), or None when refused as mapping after its arrival (counted
        ``<name>_ahead``)."""
        arrival_wall_us = (wall_ns(self.wall) - (self.monotonic_ns() - arrival_ns)) // 1000
        if boot_us is None:
            boot_us = int(msg.time_boot_ms) * 1000
        since_us = (arrival_ns - stream.taken_ns) // 1000 if stream.taken_ns is not None else 0
        if stream.clock.lead_us(boot_us, arrival_wall_us) > ATTITUDE_LEAD_US + ATTITUDE_DRIFT * since_us:
            self.counters.inc(f"{name}_ahead")
            if stream.refused_since_ns is None:
                stream.refused_since_ns = arrival_ns
            if arrival_ns - stream.refused_since_ns < ATTITUDE_REMAP_NS:
                return None
            _logger.warning("every %s for %.0f s maps after its arrival: the clock stepped; mapped anew",
                            msg.get_type(), ATTITUDE_REMAP_NS / NS)  # fmt: skip
            stream.clock = BootClock()
        stream.refused_since_ns = None
        stream.taken_ns = arrival_ns
        return stream.clock.wall_us(boot_us, arrival_wall_us)

    def _on_attitude(self, msg: Any, arrival_ns: int) -> None:
        """ATTITUDE or ATTITUDE_QUATERNION into the history, stamped on the wall clock (see BootClock)."""
        try:
            if msg.get_type() == "ATTITUDE":
                R = autopilot.attitude_level_flu(msg.roll, msg.pitch, msg.yaw)
            else:
                R = autopilot.attitude_quaternion_level_flu((msg.q1, msg.q2, msg.q3, msg.q4))
        except AtlasError:
            self.counters.inc("attitude_rejected")
            return
        t_us = self._stamp(self._attitude_stream, msg, arrival_ns, "attitude")
        if t_us is None:
            return
        rate = autopilot.body_rates_flu(msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        self.attitude.add(t_us, R, rate)
        if rate is not None:  # a sender that fills no rates leaves them all zero
            self.rates.add(t_us, rate)

    def _on_local_position(self, msg: Any, arrival_ns: int) -> None:
        """LOCAL_POSITION_NED's velocity into the history (level ENU), stamped as ATTITUDE is."""
        v = level_enu_of_ned(msg.vx, msg.vy, msg.vz)
        if v is None:  # a sender that fills no velocity leaves it all zero
            return
        t_us = self._stamp(self._velocity_stream, msg, arrival_ns, "local_position")
        if t_us is not None:
            self.velocities.add(t_us, v)

    def _on_odometry(self, msg: Any, arrival_ns: int) -> None:
        """ODOMETRY's velocity into the history (level ENU), for an autopilot that streams it and no
        LOCAL_POSITION_NED velocity (a PX4 set up so); on its own clock mapping, and none while a
        LOCAL_POSITION_NED velocity came within ATTITUDE_WAIT_NS (one stream in the history, not two)."""
        taken_ns = self._velocity_stream.taken_ns
        if taken_ns is not None and arrival_ns - taken_ns < ATTITUDE_WAIT_NS:
            return
        try:
            v_ned = autopilot.odometry_velocity_ned(
                msg.frame_id, msg.child_frame_id, msg.q, (msg.vx, msg.vy, msg.vz), msg.estimator_type
            )
        except AtlasError:
            self.counters.inc("odometry_velocity_rejected")
            return
        v = None if v_ned is None else level_enu_of_ned(*v_ned)
        if v is None:  # a sender that fills no velocity
            return
        t_us = self._stamp(self._odometry_stream, msg, arrival_ns, "odometry", int(msg.time_usec))
        if t_us is not None:
            self.velocities.add(t_us, v)

    def _origin_tick(self, now_ns: int) -> None:
        """The EKF origin: asked for (MAV_CMD_REQUEST_MESSAGE GPS_GLOBAL_ORIGIN) every
        ORIGIN_REQUEST_NS until the autopilot reports one; set (SET_GPS_GLOBAL_ORIGIN) only after
        ORIGIN_UNANSWERED requests went unanswered, each later set after twice as many. ArduPilot
        with an origin ignores SET_GPS_GLOBAL_ORIGIN without a word, so sending it blindly would only
        repeat. PX4 needs no origin to hold position, and v1.16 shifts its local height by a new
        origin's altitude once height is initialised (ekf2 ``setAltOrigin``): it gets one only with
        ``origin.send_to_px4``, and then at altitude 0, where neither branch of that rule moves the
        local frame (an origin altitude of 0 or none)."""
        ap = self.settings
        if ap is None or ap.origin is None or self.origin_known or self.link is None:
            return
        if self.autopilot_type is None or now_ns < self._next_origin_ns:
            return  # the autopilot's HEARTBEAT first: what to send depends on which autopilot it is
        px4 = self.autopilot_type == autopilot.MAV_AUTOPILOT_PX4
        if px4 and not ap.origin.send_to_px4:
            if not self._origin_skipped:
                self._origin_skipped = True
                _logger.info("PX4 needs no EKF origin to hold position: autopilot.origin not sent (see send_to_px4)")
            return
        self._next_origin_ns = now_ns + ORIGIN_REQUEST_NS
        target = self.autopilot_system if self.autopilot_system is not None else self.system_id
        d = self.link.dialect
        if self._origin_unanswered >= ORIGIN_UNANSWERED << min(self._origin_sets, 4):
            alt_m = 0.0 if px4 else ap.origin.alt_m
            fields = autopilot.set_gps_global_origin_fields(
                target, ap.origin.lat_deg, ap.origin.lon_deg, alt_m, int(self.wall() * 1e6)
            )
            self.link.send(d.MAVLink_set_gps_global_origin_message(**fields))
            self.counters.inc("origin_set_sent")
            self._origin_sets += 1
            self._origin_unanswered = 0
            _logger.info("autopilot reports no EKF origin: SET_GPS_GLOBAL_ORIGIN sent (altitude %.1f m)", alt_m)
        fields = autopilot.request_message_fields(
            target, self.autopilot_component or 0, autopilot.MSG_GPS_GLOBAL_ORIGIN
        )
        self.link.send(d.MAVLink_command_long_message(**fields))
        self._origin_unanswered += 1

    def _on_heartbeat(self, msg: Any, arrival_ns: int) -> None:
        """Pin the autopilot (see the module); an autopilot-typed HEARTBEAT from anyone else is counted."""
        if msg.autopilot == autopilot.MAV_AUTOPILOT_INVALID or msg.get_srcComponent() != MAV_COMP_ID_AUTOPILOT1:
            return  # a GCS, a companion, another component of the vehicle: never the autopilot
        if self._signed_only and not framing.is_signed(msg):
            self.counters.inc("heartbeat_not_from_autopilot")
            return
        if self.is_autopilot(msg):
            self.autopilot_type = msg.autopilot
            return
        system = msg.get_srcSystem()
        if self.autopilot_system is not None:
            self.counters.inc("heartbeat_not_from_autopilot")
            return
        if system != self.system_id:
            if self._candidate is None:
                self._candidate = (system, msg.autopilot, arrival_ns)
            if self._candidate[0] != system or arrival_ns - self._candidate[2] < AUTOPILOT_WAIT_NS:
                self.counters.inc("heartbeat_not_from_autopilot")
                return
            _logger.warning(
                "no autopilot of system_id %d in the node settings after %.0f s: taking system %d's (fix system_id)",
                self.system_id, AUTOPILOT_WAIT_NS / NS, system,
            )  # fmt: skip
        self.autopilot_system, self.autopilot_component, self.autopilot_type = system, 1, msg.autopilot
        _logger.info("autopilot found: system %d, component 1, autopilot type %d", system, msg.autopilot)

    def _on_message(self, link: Link, msg: Any, arrival_ns: int) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, arrival_ns)
        elif kind == "TIMESYNC":
            # Answer only the autopilot's own requests (PX4 trusts our usec once this converges), on
            # the wall clock of our usec stamps, addressed to it: behind a router a GCS's or MAVSDK's
            # request also arrives here, and an answer to it would reach PX4 as a bogus reply.
            requester = (msg.get_srcSystem(), msg.get_srcComponent())
            if requester != (self.autopilot_system, self.autopilot_component):
                if msg.tc1 == 0:
                    self.counters.inc("timesync_not_from_autopilot")
                return
            reply = autopilot.timesync_reply(
                msg.tc1, msg.ts1, wall_ns(self.wall), requester, link.system_id, msg.target_system
            )
            if reply is not None:
                link.send(link.dialect.MAVLink_timesync_message(**reply))
        elif kind in ("ATTITUDE", "ATTITUDE_QUATERNION"):
            if self.is_autopilot(msg):
                self._on_attitude(msg, arrival_ns)
            else:
                self.counters.inc("attitude_not_from_autopilot")
        elif kind == "LOCAL_POSITION_NED":
            if self.is_autopilot(msg):
                self._on_local_position(msg, arrival_ns)
            else:
                self.counters.inc("local_position_not_from_autopilot")
        elif kind == "ODOMETRY":
            if self.is_autopilot(msg):
                self._on_odometry(msg, arrival_ns)
            else:
                self.counters.inc("odometry_not_from_autopilot")
        elif kind == "GPS_GLOBAL_ORIGIN":
            if not self.is_autopilot(msg):
                self.counters.inc("origin_not_from_autopilot")
                return
            if not self.origin_known:
                _logger.info(
                    "autopilot reports its EKF origin (%.7f, %.7f, %.1f m): no more requests",
                    msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3,
                )  # fmt: skip
            self.origin_known = True
