"""The settings: fusion (shared by every node), a sensor's camera, and each node's links and autopilot.

Every setting is declared here once, with :func:`~atlas_onboard.config.fields.setting`: its default,
unit, range and meaning. The readers (:mod:`.read_world`, :mod:`.read_nodes`), the settings reference
(``docs/settings.md``, :mod:`.reference`) and the check of ``config/example.yaml`` all read these
declarations. To add a setting: one field here (plus its reading where it is not a plain value, and its
line in ``atlas_onboard/data/example.yaml``; the tests say what is missing).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from atlas_onboard.config.fields import REQUIRED, declared, spec


class Weighting(StrEnum):
    """How fusion weighs candidates."""

    SIGMA_MIN = "sigma_min"  # the paper's eq. 6-7: w_i = sigma_min / sigma_i
    INVERSE_VARIANCE = "inverse_variance"  # w_i = 1 / sigma_i^2


OUTLIER_GATE_SIGMA = 5.0
"""The default gate: a distance between two honest candidates, in units of their combined sigma,
is beyond 5 with probability about 1e-5 (chi with 3 degrees of freedom) if the sigmas are honest, and
still rare where they are twice too small; a lie of 1 m with a claimed sigma of 1 mm against a camera
of 1 cm is 100 sigma out."""

FUSION_METHODS = ("default", "paper")


@dataclass(frozen=True, slots=True)
class FusionConfig:
    """Fusion settings shared by every node (the world file's ``fusion`` section).

    The defaults are the best combination measured (benchmarks/compare_methods.py, bench_hard.py):
    accurate and with an honest covariance. ``paper`` is the paper's value (:data:`PAPER_FUSION`).
    """

    edge_timeout_s: float = field(default=0.25, metadata=spec(
        "an edge not refreshed for this long is removed (the paper: typically 250 ms)",
        unit="s", within="(0, 10]", noun="a timeout", paper=0.25))  # fmt: skip
    ema_alpha: float = field(default=1.0, metadata=spec(
        "EMA smoothing of each edge, eq. 3; 1 passes measurements through (best with an autopilot EKF)",
        within="(0, 1]", noun="alpha", paper=1.0))  # fmt: skip
    weighting: Weighting = field(default=Weighting.SIGMA_MIN, metadata=spec(
        "candidate weights: sigma_min (the paper's w_i = sigma_min / sigma_i, eq. 6-7) or inverse_variance"
        " (w_i = 1 / sigma_i^2)", paper=Weighting.SIGMA_MIN))  # fmt: skip
    path: str = field(default="bfs", metadata=spec(
        "bfs (the paper: parents exactly one level lower) or dijkstra (parents with a smaller chain variance,"
        " weighted by the whole chain's sigma)", choices=("bfs", "dijkstra"), paper="bfs"))  # fmt: skip
    relative_poses: bool = field(default=False, metadata=spec(
        "also evaluate groups of entities with no path to world, relative to their first entity (world-file"
        " order), and publish those relative poses", paper=False))  # fmt: skip
    age_sigma_m_per_s: float = field(default=1.0, metadata=spec(
        "how fast an edge's information goes stale (about the entities' speed): an edge of age a counts with"
        " sigma sqrt(sigma^2 + (a * this)^2); 0: the paper's method",
        unit="m/s", within="[0, 100]", noun="a speed", paper=0.0))  # fmt: skip
    outlier_gate_sigma: float = field(default=OUTLIER_GATE_SIGMA, metadata=spec(
        "a candidate farther than this many sigma from the consensus of the others is rejected and counted,"
        " and a peer's that contradicts the node's own cameras so, whoever sent it; 0: off (the paper)",
        within="[2, 100]", off=0.0, noun="a gate", paper=0.0))  # fmt: skip
    max_speed_m_s: float = field(default=5.0, metadata=spec(
        "the speed bound: a candidate resting on peers' observations (anything but the own cameras' direct"
        " views of the world's markers) that would place its entity farther from its last estimate than that"
        " estimate's uncertainty plus this speed times the time since is refused and counted (too_fast); after"
        " no accepted candidate for edge_timeout_s the next is taken (a re-acquisition). An indoor drone's"
        " top speed; 0: off (the paper)",
        unit="m/s", within="[0.1, 100]", off=0.0, noun="a speed", paper=0.0))  # fmt: skip
    filter: str = field(default="none", metadata=spec(
        "none (the paper: the fused pose of the newest observations) or ekf (an error-state EKF per entity"
        " predicts through short gaps and gates outliers by Mahalanobis distance)",
        choices=("none", "ekf"), paper="none"))  # fmt: skip
    ekf_accel_noise: float = field(default=0.5, metadata=spec(
        "the EKF's white acceleration noise density (how hard the drones manoeuvre)",
        unit="m/s^2", within="[0.01, 100]", noun="a noise"))  # fmt: skip
    ekf_max_predict_s: float = field(default=0.5, metadata=spec(
        "the EKF holds a pose at most this long past its last update (it extrapolates only the first 0.2 s"
        " of a gap); then the pose is lost, as without the filter",
        unit="s", within="(0, 5]", noun="a horizon"))  # fmt: skip
    age_sigma_deg_per_s: float = field(default=30.0, metadata=spec(
        "the same for the attitude (about the entities' turn rate): an edge of age a adds (a * this)^2 to its"
        " attitude variance; no weight changes, only the published covariance",
        unit="deg/s", within="[0, 3600]", noun="a turn rate", paper=0.0))  # fmt: skip
    align_edges: bool = field(default=True, metadata=spec(
        "a pose through another entity (a drone seen by a drone) takes that entity's pose at its own"
        " image's capture time, interpolated or extrapolated from its recent poses, the step's uncertainty"
        " in the covariance; false: its newest pose, whenever that was taken (the paper)", paper=False))  # fmt: skip
    max_relayed_sigma_m: float = field(default=0.0, metadata=spec(
        "a pose through another entity is used only while its position sigma (largest axis) stays under"
        " this: a leader with no fresh view of its own places its follower for as long as that holds, then"
        " the follower's pose is lost; 0: no limit (the paper)",
        unit="m", within="[0.001, 10]", off=0.0, noun="a limit", paper=0.0))  # fmt: skip
    method: str = field(default="default", metadata=spec(
        "default: every key not set takes its default (the best measured method); paper: every key not set"
        " takes the paper's value", choices=FUSION_METHODS, paper="paper"))  # fmt: skip


# The paper's method exactly: BFS levels, w_i = sigma_min / sigma_i, every live edge as new (no ageing),
# no outlier gate, no filter beyond eq. 3's EMA of each edge (the paper does not state its alpha; 1
# passes each measurement through, as the replicas of its tests always ran). Each value is the field's
# ``paper`` declaration above; the EKF settings, unused by the paper, keep their defaults.
PAPER_FUSION = FusionConfig(
    **{n: f.metadata["paper"] for n, f in declared(FusionConfig).items() if f.metadata["paper"] is not REQUIRED}
)


REPLAY_REALTIME = "realtime"
REPLAY_EVERY_FRAME = "every_frame"
REPLAY_MODES = (REPLAY_REALTIME, REPLAY_EVERY_FRAME)
READOUT_TOP_DOWN = "top_down"
READOUT_BOTTOM_UP = "bottom_up"
READOUT_ORDERS = (READOUT_TOP_DOWN, READOUT_BOTTOM_UP)
"""A frame's stamp (arrival less ``latency_ms``) is the middle of the exposure of its middle row."""


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """How a node reads a sensor's camera. All optional: a sensor fed only by peers needs none."""

    source: str = field(default="", metadata=spec(
        "V4L2 index or path, video file, image folder, rtsp:// or http:// URL, or a kind a plug-in registers"
        " (the simulator's sim)"))  # fmt: skip
    calibration: Path | None = field(default=None, metadata=spec(
        "OpenCV FileStorage or ROS camera_info YAML, relative to the world file"))  # fmt: skip
    width_px: int = field(default=0, metadata=spec(
        "requested image width (0: the device's default)", unit="px", within="[0, 16384]"))  # fmt: skip
    height_px: int = field(default=0, metadata=spec(
        "requested image height (0: the device's default)", unit="px", within="[0, 16384]"))  # fmt: skip
    fps: float = field(default=0.0, metadata=spec(
        "requested frame rate (0: the device's default)",
        unit="Hz", within="[0, 1000]", noun="a frame rate"))  # fmt: skip
    fourcc: str = field(default="", metadata=spec(
        'V4L2 pixel format, four characters, e.g. MJPG ("": the device\'s default)'))  # fmt: skip
    latency_ms: float = field(default=0.0, metadata=spec(
        "fixed delay between exposure and the frame's arrival, subtracted from its stamp",
        unit="ms", within="[0, 1000]", noun="a latency"))  # fmt: skip
    readout_ms: float = field(default=0.0, metadata=spec(
        "rolling shutter: time from the start of the first row's exposure to the start of the last row's"
        " (0: a global shutter)", unit="ms", within="[0, 200]", noun="a readout time"))  # fmt: skip
    readout_order: str = field(default=READOUT_TOP_DOWN, metadata=spec(
        "which row a rolling shutter reads first: top_down (row 0 first) or bottom_up (a sensor mounted upside"
        " down)", choices=READOUT_ORDERS))  # fmt: skip
    exposure_ms: float = field(default=0.0, metadata=spec(
        "exposure time of each row: a moving camera blurs over it (0: short enough to ignore)",
        unit="ms", within="[0, 1000]", noun="an exposure time"))  # fmt: skip
    stamp_sigma_ms: float = field(default=2.0, metadata=spec(
        "how far a frame's stamp may be from its middle row's mid-exposure (latency_ms's own error); a moving"
        " camera's corners get its image motion times this as noise (0: stamps exact; docs/cameras.md)",
        unit="ms", within="[0, 100]", noun="a stamp uncertainty"))  # fmt: skip
    rate_bound_dps: float = field(default=30.0, metadata=spec(
        "the angular rate a frame may have when neither the autopilot's rates nor the node's recent poses"
        " tell it (1 sigma per axis): the uncorrected shear's noise", unit="deg/s", within="[0, 2000]",
        noun="an angular rate"))  # fmt: skip
    replay: str = field(default="", metadata=spec(
        "file sources: realtime (paced on the file's time, frames it cannot keep up with dropped) or"
        " every_frame (each frame in order, late if the detector is slow); empty: the kind's own (realtime"
        " for a video file, every_frame for an image folder)", choices=("", *REPLAY_MODES)))  # fmt: skip


class AutopilotOutput(StrEnum):
    """The message that carries the pose to the autopilot."""

    VISION_POSITION_ESTIMATE = "vision_position_estimate"
    ODOMETRY = "odometry"


@dataclass(frozen=True, slots=True)
class SigningConfig:
    """MAVLink 2 signing of one link."""

    key_file: Path = field(metadata=spec(
        "32-byte secret key (raw, or 64 hex characters), the same file on every drone, not readable by"
        " others; relative to the world file"))  # fmt: skip
    sign_outgoing: bool = field(default=True, metadata=spec("sign what this node sends on the link"))
    require: bool = field(default=True, metadata=spec(
        "drop (and count) unsigned or badly signed messages received on the link"))  # fmt: skip


@dataclass(frozen=True, slots=True)
class LinkConfig:
    """One MAVLink connection, written as pymavlink/MAVProxy write them."""

    url: str = field(metadata=spec(
        "/dev/ttyAMA0,921600, udpin:0.0.0.0:14550, udpout:10.0.0.2:14550, udpbcast:10.0.0.255:14550 or"
        " tcp:127.0.0.1:5760"))  # fmt: skip
    tunnel: bool = field(default=False, metadata=spec(
        "carry observations inside standard TUNNEL messages (links through a flight controller)"))  # fmt: skip
    signing: SigningConfig | None = field(default=None, metadata=spec("MAVLink 2 signing of the link (none: unsigned)"))
    rate_limit_hz: float = field(default=1000.0, metadata=spec(
        "most observations accepted per second from one peer system on this link",
        unit="Hz", within="[1, 100000]", noun="a rate"))  # fmt: skip


@dataclass(frozen=True, slots=True)
class GlobalOrigin:
    """The EKF origin given to an autopilot that has none (asked first with MAV_CMD_REQUEST_MESSAGE)."""

    lat_deg: float = field(metadata=spec("latitude", unit="degrees", within="[-90, 90]", noun="a latitude"))
    lon_deg: float = field(metadata=spec("longitude", unit="degrees", within="[-180, 180]", noun="a longitude"))
    alt_m: float = field(metadata=spec("altitude above mean sea level", unit="metres"))
    send_to_px4: bool = field(default=False, metadata=spec(
        "PX4 needs no origin to hold position, and v1.16 moves its local height when an origin's altitude"
        " arrives late: it gets one only when this is true, then at altitude 0 m (docs/px4.md)"))  # fmt: skip


@dataclass(frozen=True, slots=True)
class AutopilotConfig:
    """The link to this drone's flight controller and what is sent on it (``url`` and ``signing`` are
    its link's; the link's ``tunnel`` and ``rate_limit_hz`` are unused here)."""

    link: LinkConfig
    output: AutopilotOutput = field(default=AutopilotOutput.VISION_POSITION_ESTIMATE, metadata=spec(
        "vision_position_estimate or odometry (LOCAL_FRD / BODY_FRD, estimator VISION)"))  # fmt: skip
    rate_hz: float = field(default=30.0, metadata=spec(
        "most pose messages per second (one per new observation of the own entity, capped)",
        unit="Hz", within="[1, 200]", noun="a rate"))  # fmt: skip
    component_id: int = field(default=197, metadata=spec(
        "MAVLink component id of this node (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY)", within="[1, 255]"))  # fmt: skip
    reset_jump_m: float = field(default=0.5, metadata=spec(
        "a jump of the published position larger than this increments reset_counter",
        unit="metres", within="(0, 100]", noun="a distance"))  # fmt: skip
    origin: GlobalOrigin | None = field(default=None, metadata=spec(
        "the EKF origin for an autopilot that reports none (ArduPilot needs one; PX4 only if asked)"))  # fmt: skip


@dataclass(frozen=True, slots=True)
class RecordConfig:
    """``nodes.<entity>.record`` (or ``run --record DIR``): the node records each camera as it flies
    (docs/mapping.md); each run and camera writes a new subdirectory of ``dir``."""

    dir: Path = field(metadata=spec("where recordings go; relative to the world file"))
    max_mb: float = field(default=2000.0, metadata=spec(
        "cap on everything under dir (this run's and earlier runs' recordings); past it frames are not"
        " recorded (counted, said once)", unit="MB", within="[1, 10000000]", noun="a size"))  # fmt: skip
    image_format: str = field(default="png", metadata=spec(
        "png (lossless) or jpg (quality 95: smaller, faster to write)", choices=("png", "jpg")))  # fmt: skip


RECORD_FORMATS = ("png", "jpg")


@dataclass(frozen=True, slots=True)
class RefineConfig:
    """``nodes.<entity>.refine``: the node refines the world markers' poses live from its own and its
    peers' observations of them (docs/mapping.md); its cameras then report each world marker on its own."""

    anchors: tuple[int, ...] = field(default=(), metadata=spec(
        "ids of surveyed world markers (the anchors `map` was given): never moved"))  # fmt: skip
    write_map: Path | None = field(default=None, metadata=spec(
        "at exit, write the refined world file here, in the format `map` writes (relative to the world"
        " file; `run --write-map PATH` also sets it); none: not written"))  # fmt: skip
    per_marker_period_s: float = field(default=0.5, metadata=spec(
        "each camera reports one image this often marker by marker (the evidence), the others as joint solves"
        " (the better pose); 0: every image that shows three or more world markers (faster evidence, a noisier"
        " pose)", unit="s", within="[0, 10]", noun="a period"))  # fmt: skip


LANDING_AUTOPILOTS = ("px4", "ardupilot")


@dataclass(frozen=True, slots=True)
class LandingConfig:
    """``nodes.<entity>.landing``: the node tells its autopilot where to land (LANDING_TARGET), on a point
    of any entity the graph places, while that point's pose is fresh and certain enough (docs/landing.md)."""

    target: str = field(metadata=spec(
        "the entity to land on: world (a pad of world markers), a rover, another drone"))  # fmt: skip
    autopilot: str = field(metadata=spec(
        "the form the autopilot takes: px4 (MAV_FRAME_LOCAL_NED position and orientation, v1.16) or ardupilot"
        " (PLND_TYPE 1: MAV_FRAME_BODY_FRD position, distance and angles)", choices=LANDING_AUTOPILOTS))  # fmt: skip
    marker: int | None = field(default=None, metadata=spec(
        "land on this marker of the target (its centre, or point_m in its frame)", within="[0, 65535]"))  # fmt: skip
    point_m: tuple[float, float, float] | None = field(default=None, metadata=spec(
        "the landing point: with marker, in the marker's frame (x right, y up, z out of its face); without,"
        " in the target's frame, in the world file's body axes (world: its axes); none: the marker's centre,"
        " or the target's origin", unit="m"))  # fmt: skip
    rate_hz: float = field(default=20.0, metadata=spec(
        "most LANDING_TARGET messages per second (ArduPilot needs one every 0.5 s while its estimator starts"
        " and calls the target lost after 2 s without one; MAVLink suggests 10-50 Hz)",
        unit="Hz", within="[2, 50]", noun="a rate"))  # fmt: skip
    max_age_s: float = field(default=0.3, metadata=spec(
        "no LANDING_TARGET when the newest observation behind the target's pose relative to the drone is older",
        unit="s", within="(0, 2]", noun="an age"))  # fmt: skip
    max_sigma_m: float = field(default=0.05, metadata=spec(
        "no LANDING_TARGET when the landing point's horizontal position sigma relative to the drone (largest"
        " horizontal axis, with the target's motion since its capture when a filter knows its velocity) exceeds"
        " this",
        unit="m", within="(0, 1]", noun="a sigma"))  # fmt: skip


@dataclass(frozen=True, slots=True)
class NodeConfig:
    """The settings of the node that runs for one entity (``nodes.defaults`` merged with ``nodes.<entity>``).

    ``entity`` is the entity whose pose this node publishes; ``owners`` the (entity, system id) of every
    node the world file's ``nodes`` section names: whose observations and fused poses this node accepts
    from whom (:meth:`owner_system_id`).
    """

    entity: str
    system_id: int = field(metadata=spec(
        "this drone's MAVLink system id (= the autopilot's SYSID_THISMAV / MAV_SYS_ID); it also identifies"
        " this node's observations on peer links, so it is unique in the swarm", within="[1, 255]"))  # fmt: skip
    autopilot: AutopilotConfig | None = field(default=None, metadata=spec(
        "the flight-controller link (none: e.g. a ground node with world cameras)"))  # fmt: skip
    peers: tuple[LinkConfig, ...] = field(default=(), metadata=spec(
        "links to the other drones and the ground station; a plain string is a link with default options"))  # fmt: skip
    fused_rate_hz: float = field(default=5.0, metadata=spec(
        "how often the fused poses of every entity go to peers and the GCS",
        unit="Hz", within="[0.1, 100]", noun="a rate"))  # fmt: skip
    heartbeat_hz: float = field(default=1.0, metadata=spec(
        "HEARTBEAT rate on every link", unit="Hz", within="[0.1, 10]", noun="a rate"))  # fmt: skip
    queue_size: int = field(default=256, metadata=spec(
        "observations waiting for the graph; beyond it the oldest are dropped (counted)",
        within="[8, 1000000]"))  # fmt: skip
    state_dir: Path | None = field(default=None, metadata=spec(
        "where signing timestamps and the autopilot's reset counter persist across restarts"))  # fmt: skip
    status_interval_s: float = field(default=10.0, metadata=spec(
        "period of the health log line", unit="s", within="[0.5, 3600]", noun="an interval"))  # fmt: skip
    cores: int = field(default=0, metadata=spec(
        "processor cores the node's cameras may use for detection: 1 detects in each camera's own thread; more"
        " spread each camera's frames over worker processes, in order; 0: the cores the node may run on (its CPU"
        " affinity: taskset, systemd's CPUAffinity) less one for the autopilot link and the system, at least 1",
        within="[0, 1024]"))  # fmt: skip
    record: RecordConfig | None = field(default=None, metadata=spec(
        "record the cameras as the node flies (none: not recorded)"))  # fmt: skip
    refine: RefineConfig | None = field(default=None, metadata=spec(
        "refine the world markers' poses from the swarm's observations (none: the world file as written)"))  # fmt: skip
    landing: LandingConfig | None = field(default=None, metadata=spec(
        "send the autopilot a landing target (none: no LANDING_TARGET)"))  # fmt: skip
    owners: tuple[tuple[str, int], ...] = ()

    def owner_system_id(self, entity: str) -> int | None:
        """The system id of the node that runs ``entity``, or None if the world file names none."""
        for name, sysid in self.owners:
            if name == entity:
                return sysid
        return None
