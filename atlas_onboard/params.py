"""``atlas-onboard params``: the autopilot's parameter file for one entity, derived from the world file.

PX4: a QGroundControl parameter file (``Vehicle-Id Component-Id Name Value Type``, tab separated,
``#`` comments; Vehicle Setup > Parameters > Tools > Load from file). ArduPilot: a Mission Planner
``.param`` file (``NAME,VALUE``, ``#`` comments; Config > Full Parameter List > Load from file).
Every value carries a comment saying where it comes from; docs/px4.md and docs/ardupilot.md explain
each parameter.

Derived from the world file: the system id, the sources (vision position, height and yaw; velocity
only with ``fusion.filter: ekf``, and on PX4 only with ODOMETRY, the one message whose velocity PX4
reads) and the vision sensor's offset (``EKF2_EV_POS_*`` / ``VISO_POS_*``). The node sends the pose
of the *entity frame*, not a camera's, so the offset is where the entity frame's origin lies relative
to the centre of gravity: zero when the world file's body frame is centred there, else ``cog_m`` (the
centre of gravity in the entity frame, in the world file's body axes). The delay cannot be derived:
it is ``delay_ms`` as measured (docs/px4.md section 5, docs/ardupilot.md section 3), or the
autopilot's default with a comment saying so.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from atlas_onboard.config import WORLD, AutopilotOutput, NodeConfig, WorldConfig
from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError

AUTOPILOTS = ("px4", "ardupilot")
# ArduPilot releases whose parameter names differ: the file names what the chosen one reads.
ARDUPILOT_VERSIONS = ("4.5", "4.6", "4.7", "4.8")
ARDUPILOT_DEFAULT_VERSION = "4.7"
PX4_FRESH_SYSTEM_ID = 1  # MAV_SYS_ID of a new (or reset) PX4 flight controller
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
PX4_EV_DELAY_DEFAULT_MS = 0.0  # EKF2_EV_DELAY's default
ARDUPILOT_VISO_DELAY_DEFAULT_MS = 10.0  # VISO_DELAY_MS's default
ARDUPILOT_PLND_LAG_DEFAULT_S = 0.02  # PLND_LAG's default (AC_PrecLand: 0.02-0.25 s)
PX4_PLD_BTOUT_S = 1.0  # the landing target's timeout the file writes (PX4's default: 5 s)
PX4_PLD_SRCH_ALT_M = 2.0  # the search altitude above home the file writes (PX4's default 10 m: a ceiling indoors)


@dataclass(frozen=True, slots=True)
class Param:
    """One parameter: name, value, whether it is an integer, and the comment written above it."""

    name: str
    value: float
    integer: bool
    comment: str


def vision_offset_frd_m(world: WorldConfig, cog_m: Sequence[float]) -> np.ndarray:
    """Position of the entity frame's origin relative to the centre of gravity, body FRD, m, shape (3,).

    ``cog_m``: the centre of gravity in the entity frame, in the world file's body axes (FLU or FRD).
    """
    cog = np.asarray(cog_m, dtype=float)
    if cog.shape != (3,) or not np.all(np.isfinite(cog)):
        raise AtlasError(f"--cog-m: expected three finite numbers (metres), got {list(cog_m)!r}")
    cog_flu = cog if world.body_convention is frames.BodyConvention.FLU else frames.R_FLU_FRD.apply(cog)
    return frames.R_FLU_FRD.inv().apply(-cog_flu)


def parameters(
    world: WorldConfig,
    node: NodeConfig,
    autopilot: str,
    delay_ms: float | None = None,
    cog_m: Sequence[float] = (0.0, 0.0, 0.0),
    ardupilot_version: str = ARDUPILOT_DEFAULT_VERSION,
) -> list[Param]:
    """The parameters of ``node``'s autopilot (``px4`` or ``ardupilot``) for vision-only flight indoors.

    ``ardupilot_version``: the ArduPilot release the names are for (4.7 moved SYSID_THISMAV to
    MAV_SYSID; 4.6 renamed GPS_TYPE to GPS1_TYPE).
    """
    if autopilot not in AUTOPILOTS:
        raise AtlasError(f"--autopilot: expected one of {', '.join(AUTOPILOTS)}, got {autopilot!r}")
    if ardupilot_version not in ARDUPILOT_VERSIONS:
        raise AtlasError(
            f"--ardupilot-version: expected one of {', '.join(ARDUPILOT_VERSIONS)}, got {ardupilot_version!r}"
        )
    if delay_ms is not None and not 0.0 <= delay_ms <= (300.0 if autopilot == "px4" else 250.0):
        raise AtlasError(f"--delay-ms: expected 0-{300 if autopilot == 'px4' else 250} ms, got {delay_ms:g}")
    ekf = world.fusion.filter == "ekf"
    odometry = node.autopilot is not None and node.autopilot.output is AutopilotOutput.ODOMETRY
    x, y, z = (round(float(v), 4) + 0.0 for v in vision_offset_frd_m(world, cog_m))  # + 0.0: never "-0"
    where = "the entity frame's origin relative to the centre of gravity, FRD, m"
    measured = "measured (--delay-ms)" if delay_ms is not None else "NOT MEASURED: the default; measure it"
    landing = _landing(world, node, autopilot, delay_ms, (x, y, z))
    if autopilot == "px4":
        vel = ekf and odometry
        return [
            Param(
                "MAV_SYS_ID", node.system_id, True,
                "the node's system_id (nodes section of the world file); PX4 reads it at boot: reboot",
            ),
            Param(
                "EKF2_EV_CTRL", 15 if vel else 11, True,
                "vision horizontal position (1) + vertical position (2) + yaw (8)"
                + (" + velocity (4): fusion.filter ekf with ODOMETRY output" if vel else
                   "; no velocity (4): sent only with fusion.filter ekf, and PX4 reads it only from ODOMETRY"),
            ),
            Param("EKF2_HGT_REF", 3, True, "height from vision (reboot required)"),
            Param("EKF2_GPS_CTRL", 0, True, "no GNSS indoors"),
            Param("EKF2_MAG_TYPE", 5, True, "no magnetometer: yaw from vision (reboot required)"),
            Param("SYS_HAS_MAG", 0, True, "so that the preflight checks do not require a magnetometer"),
            Param("EKF2_EV_NOISE_MD", 0, True, "use the variances the node sends, EKF2_EVP/EVA_NOISE as floors"),
            Param("EKF2_EV_QMIN", 0, True, "accept every quality (VISION_POSITION_ESTIMATE has none)"),
            Param(
                "EKF2_EV_DELAY", PX4_EV_DELAY_DEFAULT_MS if delay_ms is None else delay_ms, False,
                f"ms, {measured} (docs/px4.md section 5; reboot required)",
            ),
            Param("EKF2_EV_POS_X", x, False, where),
            Param("EKF2_EV_POS_Y", y, False, where),
            Param("EKF2_EV_POS_Z", z, False, where),
            *landing,
        ]  # fmt: skip
    release = tuple(int(v) for v in ardupilot_version.split("."))
    sysid_name = "MAV_SYSID" if release >= (4, 7) else "SYSID_THISMAV"
    gps_name = "GPS1_TYPE" if release >= (4, 6) else "GPS_TYPE"
    return [
        Param(
            sysid_name, node.system_id, True,
            f"the node's system_id ({ardupilot_version}: {sysid_name}; SYSID_THISMAV up to 4.6, MAV_SYSID from 4.7)",
        ),
        Param("AHRS_EKF_TYPE", 3, True, "EKF3"),
        Param("EK3_ENABLE", 1, True, "EKF3"),
        Param("VISO_TYPE", 1, True, "MAVLink visual odometry (reboot required)"),
        Param("EK3_SRC1_POSXY", 6, True, "horizontal position from external nav"),
        Param("EK3_SRC1_POSZ", 6, True, "height from external nav"),
        Param(
            "EK3_SRC1_VELXY", 6 if ekf else 0, True,
            "velocity from external nav (fusion.filter ekf sends it)" if ekf else "no velocity: the node sends none",
        ),
        Param("EK3_SRC1_VELZ", 0, True, "no vertical velocity source"),
        Param("EK3_SRC1_YAW", 6, True, "yaw from external nav"),
        Param("COMPASS_USE", 0, True, "no compass: yaw from vision"),
        Param("COMPASS_USE2", 0, True, "no compass: yaw from vision"),
        Param("COMPASS_USE3", 0, True, "no compass: yaw from vision"),
        Param(gps_name, 0, True, "no GNSS indoors (GPS_TYPE up to 4.5, GPS1_TYPE from 4.6)"),
        Param("VISO_SCALE", 1, False, "metric positions"),
        Param("VISO_QUAL_MIN", 0, True, "VISION_POSITION_ESTIMATE arrives with quality 0 (unknown)"),
        Param(
            "VISO_DELAY_MS", ARDUPILOT_VISO_DELAY_DEFAULT_MS if delay_ms is None else round(delay_ms), True,
            f"ms, {measured} (docs/ardupilot.md section 3)",
        ),
        Param("VISO_POS_X", x, False, where),
        Param("VISO_POS_Y", y, False, where),
        Param("VISO_POS_Z", z, False, where),
        *landing,
    ]  # fmt: skip


def _landing(
    world: WorldConfig, node: NodeConfig, autopilot: str, delay_ms: float | None, offset_frd_m: tuple[float, ...]
) -> list[Param]:
    """Precision landing on the node's LANDING_TARGET (``nodes.<entity>.landing``; none without it)."""
    landing = node.landing
    if landing is None:
        return []
    moving = landing.target != WORLD
    if autopilot == "px4":
        # The node's MAV_FRAME_LOCAL_NED target goes straight to landing_target_pose (PLD_*, navigator
        # precland); landing_target_estimator (LTEST_*) only reads the IR-lock path (angles, no position).
        return [
            Param("PLD_BTOUT", PX4_PLD_BTOUT_S, False,
                  "s: the target is lost after this long without LANDING_TARGET (default 5; the node sends only"
                  " fresh targets, at landing.rate_hz)"),
            Param("PLD_SRCH_ALT", PX4_PLD_SRCH_ALT_M, False,
                  "m above home to climb to when the target is lost (default 10): CHECK it is below your ceiling"),
            Param("LTEST_MODE", 0 if moving else 1, True,
                  f"{'moving' if moving else 'stationary'} target ({landing.target}); used only by the IR-lock path"),
        ]  # fmt: skip
    x, y, z = offset_frd_m
    lag_s = ARDUPILOT_PLND_LAG_DEFAULT_S if delay_ms is None else min(max(delay_ms / 1000.0, 0.02), 0.25)
    measured = "measured (--delay-ms)" if delay_ms is not None else "NOT MEASURED: the default; measure it"
    where = "the entity frame's origin (where the node's vector starts) relative to the centre of gravity, FRD, m"
    return [
        Param("PLND_ENABLED", 1, True, "precision landing on (reboot required)"),
        Param("PLND_TYPE", 1, True, "MAVLink: LANDING_TARGET from the companion (reboot required)"),
        Param("PLND_EST_TYPE", 1, True, "Kalman filter (it also estimates a moving target's velocity)"),
        Param("PLND_ORIENT", 25, True, "down (the default): the node's BODY_FRD vector is used as it is"),
        Param("PLND_YAW_ALIGN", 0, True, "cdeg: none, the vector is in the body's own axes"),
        Param("PLND_CAM_POS_X", x, False, where),
        Param("PLND_CAM_POS_Y", y, False, where),
        Param("PLND_CAM_POS_Z", z, False, where),
        Param("PLND_LAG", round(lag_s, 3), False, f"s, capture to arrival: {measured} (0.02-0.25; reboot required)"),
        Param("PLND_OPTIONS", 1 if moving else 0, True,
              f"{'moving target (bit 0)' if moving else 'static target'}: {landing.target}"),
        Param("PLND_ALT_MIN", 0, False, "m: no rangefinder needed, the node sends the distance (0: no limit)"),
        Param("PLND_ALT_MAX", 0, False, "m: no rangefinder needed, the node sends the distance (0: no limit)"),
    ]  # fmt: skip


def _number(p: Param) -> str:
    return str(int(p.value)) if p.integer else f"{float(p.value):.6g}"


def render(
    params: list[Param],
    autopilot: str,
    node: NodeConfig,
    world: WorldConfig,
    vehicle_id: int = PX4_FRESH_SYSTEM_ID,
    ardupilot_version: str = ARDUPILOT_DEFAULT_VERSION,
) -> str:
    """The file's text: QGroundControl's format for PX4, Mission Planner's for ArduPilot.

    ``vehicle_id``: QGroundControl's Vehicle-Id column, the system id the flight controller has *when
    the file is loaded* (QGroundControl refuses a file written for another id): 1 on a new one. The
    node's system id reaches it as MAV_SYS_ID, in force after the reboot.
    """
    if not 1 <= vehicle_id <= 255:
        raise AtlasError(f"--vehicle-id: expected 1-255, got {vehicle_id}")
    what = autopilot if autopilot == "px4" else f"ardupilot {ardupilot_version}"
    head = [
        f"# atlas-onboard parameters for {what}, entity {node.entity} (system {node.system_id}),"
        f" from {world.source or 'the world file'}",
        "# Check each value before loading; reboot the flight controller afterwards.",
    ]
    if autopilot == "px4":
        head += [
            f"# For a flight controller now at system id {vehicle_id} (QGroundControl loads a file only onto the"
            " vehicle whose id is in its Vehicle-Id column);",
            f"# MAV_SYS_ID becomes {node.system_id} after the reboot. Later files for it: --vehicle-id"
            f" {node.system_id}.",
        ]
    else:
        head.append(
            f"# Parameter names of ArduPilot {ardupilot_version} (--ardupilot-version): Mission Planner reports"
            " a name the firmware does not know."
        )
    cams = [s for s in world.sensors.values() if s.entity == node.entity]
    for s in cams:  # for reference: the node accounts for the cameras' offsets itself
        p = s.T_entity_sensor.translation
        head.append(f"# camera {s.name} at [{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}] m in the entity frame (FLU)")
    lines = list(head)
    if autopilot == "px4":
        lines += ["#", "# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
        for p in params:
            kind = MAV_PARAM_TYPE_INT32 if p.integer else MAV_PARAM_TYPE_REAL32
            lines += [f"# {p.name}: {p.comment}", f"{vehicle_id}\t1\t{p.name}\t{_number(p)}\t{kind}"]
    else:
        for p in params:
            lines += [f"# {p.name}: {p.comment}", f"{p.name},{_number(p)}"]
    return "\n".join(lines) + "\n"
