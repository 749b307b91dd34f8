"""The bench checks of ``atlas-onboard preflight``: what the relay saw on the autopilot link, judged.

Each check gives one :class:`Check`: PASS, FAIL (with the likely cause and the fix) or SKIP (with why
it could not be judged). The figures they use come from the autopilots' sources (docs/px4.md,
docs/ardupilot.md): PX4 does not start fusing after gaps over 200 ms, ArduPilot calls vision older
than 300 ms unhealthy; EKF2_EV_DELAY / VISO_DELAY_MS cover the capture-to-arrival latency.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import NodeConfig, WorldConfig
from atlas_onboard.core import frames, mounting
from atlas_onboard.mavlink.autopilot import MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4
from atlas_onboard.mavlink.samples import AttitudeSample, PositionSample, Tap, VisionSample

MIN_RATE_HZ = 10.0  # below this neither EKF holds a position on vision
GAP_S = {MAV_AUTOPILOT_PX4: 0.2, MAV_AUTOPILOT_ARDUPILOTMEGA: 0.3}
MAX_GAP_SHARE = 0.05  # of the window spent in gaps longer than GAP_S
YAW_AGREE_DEG = 5.0
DELAY_MARGIN_MS = 20.0  # and a quarter of the measured latency, whichever is larger
FOLLOW_M = 0.10  # LOCAL_POSITION_NED within this of the vision position: it follows it
MIN_PAIRS = 5


class Verdict(StrEnum):
    PASS = "PASS"  # noqa: S105 (a verdict, not a password)
    FAIL = "FAIL"
    SKIP = "SKIP"


@dataclass(frozen=True, slots=True)
class Check:
    name: str
    verdict: Verdict
    detail: str
    fix: str = ""
    short: str = ""  # the cause in a few words, for a STATUSTEXT

    def line(self) -> str:
        return f"{self.verdict.value}  {self.name}: {self.detail}" + (f"; fix: {self.fix}" if self.fix else "")


def _R(samples: list[VisionSample]) -> Rotation:
    return Rotation.from_quat([(x, y, z, w) for w, x, y, z in (s.q_ned_frd_wxyz for s in samples)])


def _R_att(samples: list[AttitudeSample]) -> Rotation:
    return Rotation.from_euler("ZYX", [(s.yaw_rad, s.pitch_rad, s.roll_rad) for s in samples])


def optical_axes_frd(world: WorldConfig, entity: str) -> dict[str, np.ndarray]:
    """Each of the entity's cameras' optical axis in the body, FRD."""
    return {
        s.name: frames.R_FLU_FRD.inv().apply(s.T_entity_sensor.rotation.apply([0.0, 0.0, 1.0]))
        for s in world.sensors.values()
        if s.entity == entity
    }


def pair_attitudes(vision: list[VisionSample], attitude: list[AttitudeSample]) -> tuple[Rotation, Rotation] | None:
    """(autopilot, vision) attitudes paired by arrival: each vision pose with the autopilot's last before it."""
    if not vision or not attitude:
        return None
    t_att = np.array([a.arrival_s for a in attitude])
    ap, vis = [], []
    for v in vision:
        k = int(np.searchsorted(t_att, v.arrival_s)) - 1
        if k >= 0:
            ap.append(attitude[k])
            vis.append(v)
    if len(vis) < MIN_PAIRS:
        return None
    return _R_att(ap), _R(vis)


def yaw_from_vision(params: dict[str, float], autopilot: int | None) -> bool | None:
    """Whether the autopilot's heading comes from vision (None: its parameters did not say)."""
    if autopilot == MAV_AUTOPILOT_PX4 and "EKF2_EV_CTRL" in params:
        return bool(int(params["EKF2_EV_CTRL"]) & 8)
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA and "EK3_SRC1_YAW" in params:
        return int(params["EK3_SRC1_YAW"]) == 6
    return None


def check_attitude(
    vision: list[VisionSample], attitude: list[AttitudeSample], optical_axes_frd: dict[str, np.ndarray]
) -> list[Check]:
    """Roll and pitch against the autopilot's, and which frame mistake explains a disagreement."""
    pairs = pair_attitudes(vision, attitude)
    if pairs is None:
        why = "no ATTITUDE from the autopilot" if not attitude else "too few vision poses"
        return [Check("attitude", Verdict.SKIP, why, "stream ATTITUDE (PX4 MAV_x_MODE Onboard, ArduPilot SRn_EXTRA1)")]
    R_ap, R_vis = pairs
    cands = mounting.candidates(optical_axes_frd)
    d = mounting.diagnose(R_ap, R_vis, cands)
    best, err = d.ranked[0]
    diff = f"vision minus autopilot: roll {d.roll_diff_deg:+.1f} deg, pitch {d.pitch_diff_deg:+.1f} deg"
    out = []
    if best.name == "correct" and err <= mounting.AGREE_DEG:
        out.append(Check("attitude", Verdict.PASS, f"roll and pitch agree within {err:.1f} deg ({diff})"))
    elif err <= mounting.AGREE_DEG:
        rest = [c.name for c, e in d.ranked[1:] if e <= mounting.AGREE_DEG and c.name != "correct"]
        also = f" (or: {'; '.join(rest)})" if rest else ""
        out.append(Check("attitude", Verdict.FAIL, f"{diff}: likely {best.name}{also}", best.fix, best.short))
    else:
        rotation = Rotation.align_vectors(mounting.up_vectors(R_vis), mounting.up_vectors(R_ap))[0]
        axis = rotation.as_rotvec()
        out.append(
            Check(
                "attitude", Verdict.FAIL,
                f"{diff}; no single known mistake explains it (the nearest, {best.name}, is {err:.1f} deg off;"
                f" rotation between them {np.degrees(np.linalg.norm(axis)):.0f} deg about body FRD"
                f" [{', '.join(f'{v:.2f}' for v in axis / max(np.linalg.norm(axis), 1e-12))}])",
                "check the sensor poses and the conventions of the world file (docs/troubleshooting.md)",
            )
        )  # fmt: skip
    if d.hidden:
        out.append(
            Check(
                "mounting about the vertical", Verdict.SKIP,
                f"the drone is within {d.tilt_deg:.1f} deg of level: a camera turned about a vertical optical axis"
                " looks like a correct one",
                "tilt the drone (--interactive) or stand it on a tilted support",
            )
        )  # fmt: skip
    return out


def check_yaw(vision: list[VisionSample], attitude: list[AttitudeSample], from_vision: bool | None) -> Check:
    if not from_vision:
        why = "the autopilot's heading is its own (not from vision)" if from_vision is False else "yaw source unknown"
        return Check("yaw", Verdict.SKIP, why)
    pairs = pair_attitudes(vision, attitude)
    if pairs is None:
        return Check("yaw", Verdict.SKIP, "no paired attitudes")
    dy = mounting.yaw_difference_deg(*pairs)
    if abs(dy) <= YAW_AGREE_DEG:
        return Check("yaw", Verdict.PASS, f"heading agrees with vision within {abs(dy):.1f} deg")
    return Check(
        "yaw", Verdict.FAIL, f"the autopilot's heading differs from vision's by {dy:+.0f} deg",
        "reboot the flight controller after setting the yaw source; check the world file's yaw of the markers",
    )  # fmt: skip


def check_rate(vision: list[VisionSample], window_s: float, autopilot: int | None) -> Check:
    if len(vision) < 2:
        return Check("pose rate", Verdict.FAIL, f"{len(vision)} poses reached the autopilot link",
                     "see docs/troubleshooting.md, 'Nothing reaches the autopilot'")  # fmt: skip
    t = np.array([v.arrival_s for v in vision])
    rate = (len(t) - 1) / max(t[-1] - t[0], 1e-9)
    gap_limit = GAP_S.get(autopilot or MAV_AUTOPILOT_PX4, 0.2)
    gaps = np.diff(t)
    in_gaps = float(np.sum(gaps[gaps > gap_limit])) / max(window_s, 1e-9)
    detail = f"{rate:.1f} Hz, longest gap {gaps.max() * 1000:.0f} ms"
    if rate < MIN_RATE_HZ or in_gaps > MAX_GAP_SHARE:
        detail += f" ({in_gaps * 100:.0f}% of the time in gaps over {gap_limit * 1000:.0f} ms)"
        short = f"{rate:.0f} Hz, max gap {gaps.max() * 1000:.0f} ms"
        return Check("pose rate", Verdict.FAIL, detail, "more markers in view, a faster camera mode, less load", short)
    return Check("pose rate", Verdict.PASS, detail)


def check_delay(vision: list[VisionSample], params: dict[str, float], autopilot: int | None, synced: bool) -> Check:
    """The capture-to-autopilot latency against the autopilot's vision delay parameter."""
    name = "VISO_DELAY_MS" if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA else "EKF2_EV_DELAY"
    if not vision:
        return Check("delay", Verdict.SKIP, "no pose to measure the latency on")
    lat = np.array([(v.arrival_s - v.usec * 1e-6) * 1000.0 for v in vision])
    med, p95 = float(np.median(lat)), float(np.percentile(lat, 95))
    measured = f"capture to autopilot {med:.0f} ms (p95 {p95:.0f})"
    if name not in params:
        return Check("delay", Verdict.SKIP, f"{measured}; {name} not answered to PARAM_REQUEST_READ")
    value = params[name]
    margin = max(DELAY_MARGIN_MS, 0.25 * med)
    doc = "docs/ardupilot.md section 3" if name == "VISO_DELAY_MS" else "docs/px4.md section 5"
    fix = f"set {name} to about {med:.0f} ms (params --delay-ms {med:.0f}) and measure it ({doc})"
    if value > med + margin:
        return Check("delay", Verdict.FAIL, f"{name} {value:.0f} ms is longer than the whole {measured}", fix)
    if value < med - margin and (name == "VISO_DELAY_MS" or not synced):
        return Check("delay", Verdict.FAIL, f"{name} {value:.0f} ms is much shorter than the {measured}", fix)
    return Check("delay", Verdict.PASS, f"{name} {value:.0f} ms against {measured}")


def check_timesync(tap: Tap) -> Check:
    """PX4 asks (TIMESYNC with tc1 0), the node answers; PX4 uses the node's stamps once that converges."""
    if tap.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return Check("timesync", Verdict.SKIP, "ArduPilot needs no TIMESYNC (jitter correction)")
    if tap.timesync_requests == 0:
        return Check("timesync", Verdict.FAIL, "the autopilot sent no TIMESYNC request: it stamps vision on arrival",
                     "PX4 sends them on a MAVLink instance in Onboard mode (MAV_x_MODE 2)")  # fmt: skip
    if tap.timesync_answers == 0:
        return Check("timesync", Verdict.FAIL, f"{tap.timesync_requests} requests from the autopilot, no answer",
                     "only the node may answer TIMESYNC: check its log (timesync_not_from_autopilot)")  # fmt: skip
    return Check("timesync", Verdict.PASS, f"{tap.timesync_answers} of {tap.timesync_requests} requests answered")


def check_origin(tap: Tap) -> Check:
    if tap.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        if tap.origin is None:
            fix = "set nodes.<entity>.origin so the node sends SET_GPS_GLOBAL_ORIGIN (docs/ardupilot.md section 4)"
            return Check("EKF origin", Verdict.FAIL, "no EKF origin (GPS_GLOBAL_ORIGIN not answered)", fix)
        lat, lon, alt = tap.origin
        return Check("EKF origin", Verdict.PASS, f"lat {lat:.6f} lon {lon:.6f} alt {alt:.1f} m")
    if tap.origin is None:
        return Check("EKF origin", Verdict.PASS, "none: PX4 holds position without one (auto modes need one)")
    vision_height = int(tap.params.get("EKF2_HGT_REF", 3)) == 3
    if vision_height and abs(tap.origin[2]) > 0.5:
        return Check(
            "EKF origin", Verdict.FAIL,
            f"origin altitude {tap.origin[2]:.1f} m with vision height: local z reads the vision height plus it",
            "send no origin or altitude 0 (docs/px4.md section 7)",
        )  # fmt: skip
    return Check("EKF origin", Verdict.PASS, f"altitude {tap.origin[2]:.1f} m")


def _axes_name(P: np.ndarray) -> str:
    names = "xyz"
    parts = []
    for i in range(3):
        j = int(np.argmax(np.abs(P[i])))
        sign = "-" if P[i, j] < 0 else ""
        if j != i or sign:
            parts.append(f"its {names[i]} is vision's {sign}{names[j]}")
    return ", ".join(parts)


def check_local_position(vision: list[VisionSample], local: list[PositionSample]) -> Check:
    """LOCAL_POSITION_NED against the vision position sent just before it (the same NED axes)."""
    if not local:
        return Check("local position", Verdict.SKIP, "the autopilot streams no LOCAL_POSITION_NED")
    t_vis = np.array([v.arrival_s for v in vision]) if vision else np.zeros(0)
    lp, vp = [], []
    for s in local:
        k = int(np.searchsorted(t_vis, s.arrival_s)) - 1
        if k >= 0:
            lp.append(s.xyz_ned_m)
            vp.append(vision[k].xyz_ned_m)
    if len(lp) < MIN_PAIRS:
        return Check("local position", Verdict.SKIP, "too few LOCAL_POSITION_NED after a vision pose")
    L, V = np.array(lp), np.array(vp)
    err = float(np.median(np.linalg.norm(L - V, axis=1)))
    if err <= FOLLOW_M:
        return Check("local position", Verdict.PASS, f"LOCAL_POSITION_NED follows vision within {err * 100:.1f} cm")
    best = min(
        (np.diag(s) @ np.eye(3)[list(p)] for p in itertools.permutations(range(3))
         for s in itertools.product((1.0, -1.0), repeat=3)),
        key=lambda P: float(np.median(np.linalg.norm(L - V @ P.T, axis=1))),
    )  # fmt: skip
    best_err = float(np.median(np.linalg.norm(L - V @ best.T, axis=1)))
    cause = f": {_axes_name(best)}" if best_err <= FOLLOW_M and not np.allclose(best, np.eye(3)) else ""
    return Check(
        "local position", Verdict.FAIL, f"LOCAL_POSITION_NED is {err:.2f} m from vision{cause}",
        "PX4 takes VISION_POSITION_ESTIMATE as NED: check the output frame and the world file's conventions",
    )  # fmt: skip


SKEW_LINE = re.compile(r"peer system (\d+): capture stamps and arrival disagree by (-?\d+) ms")


def check_peers(node: NodeConfig, node_log: str) -> list[Check]:
    """Signing on the peer links (the settings), and the clock skew the node reported in ``node_log``."""
    if not node.peers:
        return [Check(name, Verdict.SKIP, "no peer links") for name in ("peer signing", "peer clocks")]
    bad = [p.url for p in node.peers if p.signing is None or not p.signing.require]
    if bad:
        fix = "give each peer link signing with require: true (docs/signing.md)"
        out = [Check("peer signing", Verdict.FAIL, f"unsigned or unsigned-accepting peer links: {', '.join(bad)}", fix)]
    else:
        out = [Check("peer signing", Verdict.PASS, f"{len(node.peers)} peer links signed, unsigned refused")]
    skews: dict[int, int] = {}
    for m in SKEW_LINE.finditer(node_log):
        skews[int(m.group(1))] = int(m.group(2))
    if skews:
        worst = ", ".join(f"system {k} {v:+d} ms" for k, v in sorted(skews.items()))
        out.append(Check("peer clocks", Verdict.FAIL, f"capture stamps against arrival: {worst}",
                         "synchronise the clocks (chrony) on every companion"))  # fmt: skip
    else:
        why = "the node reported no skew (it warns over 100 ms once it hears a peer)"
        out.append(Check("peer clocks", Verdict.SKIP, why))
    return out


TILT_MIN_DEG = 5.0


def _median_rp_deg(R: Rotation) -> np.ndarray:
    ypr = np.atleast_2d(R.as_euler("ZYX", degrees=True))
    return np.median(ypr[:, [2, 1]], axis=0)  # roll, pitch


def check_tilt(
    what: str, axis: int, sign: float, still: tuple[Rotation, Rotation], tilted: tuple[Rotation, Rotation]
) -> Check:
    """The user tilted the drone (``what``, e.g. "nose down"): ``axis`` 0 roll / 1 pitch should change by
    ``sign`` (FRD: nose down is negative pitch, right side down positive roll) in both attitudes.
    ``still``, ``tilted``: (autopilot, vision) attitudes before and during the tilt."""
    d_ap = _median_rp_deg(tilted[0]) - _median_rp_deg(still[0])
    d_vis = _median_rp_deg(tilted[1]) - _median_rp_deg(still[1])
    names = ("roll", "pitch")
    seen = f"autopilot {names[axis]} {d_ap[axis]:+.0f} deg, vision {names[axis]} {d_vis[axis]:+.0f} deg"
    if sign * d_ap[axis] < TILT_MIN_DEG:
        return Check(f"tilt {what}", Verdict.SKIP, f"the autopilot saw no such tilt ({seen})", f"tilt {what} ~20 deg")
    if sign * d_vis[axis] >= TILT_MIN_DEG:
        return Check(f"tilt {what}", Verdict.PASS, seen)
    other = 1 - axis
    if abs(d_vis[other]) >= TILT_MIN_DEG:
        cause = f"vision moved its {names[other]} ({d_vis[other]:+.0f} deg) instead: a camera turned 90 deg"
    elif sign * d_vis[axis] <= -TILT_MIN_DEG:
        cause = f"vision's {names[axis]} has the opposite sign: an axis flipped (FLU/FRD or ENU/NED)"
    else:
        cause = "vision did not follow the tilt"
    return Check(f"tilt {what}", Verdict.FAIL, f"{seen}: {cause}", "check the sensor pose and conventions")
