"""World file and node settings: YAML -> frozen dataclasses, with errors that name the exact field.

One world file is shared by every drone of a swarm. It states its frame conventions once, the fusion
settings, and the entities (``world`` always exists) with their sensors and markers. Poses written in
NED/FRD are normalised here to the internal ENU/FLU convention (see :mod:`atlas_onboard.core.frames`),
so nothing downstream ever sees the file's convention.

Every problem raises :class:`~atlas_onboard.errors.ConfigError` with the field path, e.g.
``entities.drone2.sensors[0].pose.rot: expected a unit quaternion, got norm 1.2``. Unknown keys are
errors (a typo must not silently fall back on a default), and so are duplicate YAML keys.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any

import yaml
from scipy.spatial.transform import RigidTransform

from atlas_onboard.core import frames, geometry
from atlas_onboard.errors import ConfigError, GeometryError

WORLD = "world"
"""The name of the world entity; it always exists."""

SCHEMA_VERSION = 1

# The families the detector reads: every AprilTag 3 family of the C library (pupil-apriltags), and
# OpenCV's ArUco dictionaries (the config refuses what no node could ever see).
APRILTAG_FAMILIES = (
    "tag36h11", "tag25h9", "tag16h5",
    "tagStandard41h12", "tagStandard52h13", "tagCircle21h7", "tagCircle49h12", "tagCustom48h12",
)  # fmt: skip
ARUCO_DICTIONARIES = (
    *(f"DICT_{bits}X{bits}_{n}" for bits in (4, 5, 6, 7) for n in (50, 100, 250, 1000)),
    "DICT_ARUCO_ORIGINAL",
    "DICT_ARUCO_MIP_36h12",
)
MARKER_FAMILIES = APRILTAG_FAMILIES + ARUCO_DICTIONARIES

MAX_ID = 65535
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")


class Weighting(StrEnum):
    """How fusion weighs candidates."""

    SIGMA_MIN = "sigma_min"  # the paper's eq. 6-7: w_i = sigma_min / sigma_i
    INVERSE_VARIANCE = "inverse_variance"  # w_i = 1 / sigma_i^2


OUTLIER_GATE_SIGMA = 5.0
"""The default gate: a distance between two honest candidates, in units of their combined sigma,
is beyond 5 with probability about 1e-5 (chi with 3 degrees of freedom) if the sigmas are honest, and
still rare where they are twice too small; a lie of 1 m with a claimed sigma of 1 mm against a camera
of 1 cm is 100 sigma out."""


@dataclass(frozen=True, slots=True)
class FusionConfig:
    """Fusion settings shared by every node.

    Attributes:
        edge_timeout_s: an edge not refreshed for this long is removed (the paper: typically 250 ms).
        ema_alpha: EMA smoothing of each edge, eq. 3, in (0, 1]; 1 passes measurements through.
        weighting: candidate weights: ``sigma_min`` (the paper's sigma_min / sigma_i) or ``inverse_variance``.
        path: ``bfs`` (the paper: parents exactly one level lower) or ``dijkstra`` (parents with a
            smaller chain variance, weighted by the whole chain's sigma).
        relative_poses: also evaluate groups of entities with no path to world, relative to their
            first entity (world-file order), and publish those relative poses.
        age_sigma_m_per_s: how fast an edge's information goes stale (about the entities' speed):
            an edge of age a counts with sigma sqrt(sigma^2 + (a * this)^2). 0: the paper's method.
        age_sigma_deg_per_s: the same for the attitude (about the entities' turn rate, degrees per
            second): an edge of age a adds (a * this)^2 to its attitude variance. It changes no
            weight, only the covariance published with the pose. 0: attitudes do not age.
        outlier_gate_sigma: a candidate farther from the consensus of the others than this many
            standard deviations (position or attitude) is rejected and counted; a candidate of a peer
            that contradicts every candidate of the node's own cameras so is rejected whoever sent it.
            0: off (the paper). Default ``OUTLIER_GATE_SIGMA``.
        filter: ``none`` (the paper: the fused pose of the newest observations is the output) or
            ``ekf`` (an error-state EKF per entity fed by the graph's candidates, predicting through
            short gaps and gating outliers by Mahalanobis distance).
        ekf_accel_noise: the EKF's white acceleration noise density, m/s^2 (how hard the drones
            manoeuvre). 0.5: offline, on the simulated scenarios' rendered frames, 2 doubled the
            velocity error (0.16 against 0.09 m/s on paper-test1's oscillating drone) and its
            predictions' covariance was 4 times too cautious.
        ekf_max_predict_s: the EKF holds a pose at most this long past its last update; then the
            pose is lost, as without the filter (it extrapolates only the first 0.2 s of a gap,
            ``EkfBank.predict_horizon_s``).
        method: ``default`` (the defaults above: the best measured combination) or ``paper`` (every
            key the world file does not set takes the paper's value, :data:`PAPER_FUSION`).
    """

    # The defaults are the best combination measured (benchmarks/compare_methods.py, bench_hard.py):
    # accurate and with an honest covariance. PAPER_FUSION is the paper's method.
    edge_timeout_s: float = 0.25
    ema_alpha: float = 1.0
    weighting: Weighting = Weighting.SIGMA_MIN
    path: str = "bfs"
    relative_poses: bool = False
    age_sigma_m_per_s: float = 1.0
    outlier_gate_sigma: float = OUTLIER_GATE_SIGMA
    filter: str = "none"
    ekf_accel_noise: float = 0.5
    ekf_max_predict_s: float = 0.5
    age_sigma_deg_per_s: float = 30.0  # a stale edge's attitude ages too (issue 19: a tight 6x6 otherwise)
    method: str = "default"


# The paper's method exactly: BFS levels, w_i = sigma_min / sigma_i, every live edge as new (no ageing),
# no outlier gate, no filter beyond eq. 3's EMA of each edge. The paper does not state its alpha; 1
# passes each measurement through (eq. 3 with alpha = 1), as the replicas of its tests always ran.
PAPER_FUSION = FusionConfig(
    edge_timeout_s=0.25,
    ema_alpha=1.0,
    weighting=Weighting.SIGMA_MIN,
    path="bfs",
    relative_poses=False,
    age_sigma_m_per_s=0.0,
    outlier_gate_sigma=0.0,
    filter="none",
    age_sigma_deg_per_s=0.0,
    method="paper",
)
FUSION_METHODS = ("default", "paper")


REPLAY_REALTIME = "realtime"
REPLAY_EVERY_FRAME = "every_frame"
REPLAY_MODES = (REPLAY_REALTIME, REPLAY_EVERY_FRAME)


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """How a node reads a sensor's camera. All optional: a sensor fed only by peers needs none.

    Attributes:
        source: V4L2 index or path, video file, image folder, URL, or ``sim``.
        calibration: path of an OpenCV FileStorage or ROS camera_info YAML (resolved against the file).
        width_px, height_px, fps: requested capture format (0: the device's default).
        fourcc: four-character pixel format for V4L2, e.g. ``MJPG`` ("" for the default).
        latency_ms: fixed delay between exposure and the frame's arrival, subtracted from its stamp.
        replay: how a file source plays: ``realtime`` (like a camera: paced on the file's time, frames
            it cannot keep up with dropped) or ``every_frame`` (each frame, in order, falling behind
            if the detector is slow); "" for the default of the source's kind (a video file realtime,
            an image folder every_frame). Ignored for live sources.
    """

    source: str = ""
    calibration: Path | None = None
    width_px: int = 0
    height_px: int = 0
    fps: float = 0.0
    fourcc: str = ""
    latency_ms: float = 0.0
    replay: str = ""


@dataclass(frozen=True, slots=True)
class SensorConfig:
    """A camera attached to an entity.

    ``T_entity_sensor`` is the pose of the camera's OpenCV optical frame (x right, y down, z forward) in
    the entity's FLU body frame (or in ENU for the world entity), already normalised from the file.
    """

    name: str
    id: int
    entity: str
    T_entity_sensor: RigidTransform
    camera: CameraConfig | None = None


@dataclass(frozen=True, slots=True)
class MarkerConfig:
    """A fiducial marker attached to an entity; ``T_entity_marker`` is its OpenCV marker frame's pose."""

    id: int
    size_m: float
    family: str
    entity: str
    T_entity_marker: RigidTransform


@dataclass(frozen=True, slots=True)
class EntityConfig:
    """A vertex of the graph: a drone, an object, or the world; a container of sensors and markers."""

    name: str
    sensors: tuple[SensorConfig, ...] = ()
    markers: tuple[MarkerConfig, ...] = ()


@dataclass(frozen=True, slots=True)
class WorldConfig:
    """A validated world file, in the internal ENU/FLU convention."""

    entities: tuple[EntityConfig, ...]
    fusion: FusionConfig = field(default_factory=FusionConfig)
    world_convention: frames.WorldConvention = frames.WorldConvention.ENU
    body_convention: frames.BodyConvention = frames.BodyConvention.FLU
    source: Path | None = None

    def entity(self, name: str) -> EntityConfig:
        """The entity called ``name``; KeyError if there is none."""
        for ent in self.entities:
            if ent.name == name:
                return ent
        raise KeyError(name)

    @property
    def entity_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.entities)

    @property
    def sensors(self) -> dict[int, SensorConfig]:
        """Every sensor by numeric id."""
        return {s.id: s for e in self.entities for s in e.sensors}

    @property
    def markers(self) -> dict[int, MarkerConfig]:
        """Every marker by id."""
        return {m.id: m for e in self.entities for m in e.markers}

    def fingerprint(self) -> int:
        """A 32-bit digest of the geometry (entities, sensor and marker ids, sizes, poses).

        Two nodes whose world files describe the same geometry have the same fingerprint whatever the
        files' conventions, formatting or fusion settings; a peer with another geometry is refused.
        """

        def pose(T: RigidTransform) -> list[float]:
            p, q = geometry.pose_arrays(T)
            return [round(float(v), 6) + 0.0 for v in (*p, *geometry.canonical_quat(q))]

        doc = [
            [
                e.name,
                [[s.id, s.name, pose(s.T_entity_sensor)] for s in sorted(e.sensors, key=lambda s: s.id)],
                [
                    [m.id, m.family, round(m.size_m, 6), pose(m.T_entity_marker)]
                    for m in sorted(e.markers, key=lambda m: m.id)
                ],
            ]
            for e in sorted(self.entities, key=lambda e: e.name)
        ]
        digest = hashlib.sha256(json.dumps(doc, separators=(",", ":")).encode()).digest()
        return int.from_bytes(digest[:4], "little")


NO_NODES = "missing: `atlas-onboard run` needs a nodes section (see config/example.yaml)"


# --- YAML with duplicate-key detection ---------------------------------------------------------------


def _duplicate_key(node: yaml.Node, path: str = "", seen_nodes: set[int] | None = None) -> tuple[str, str] | None:
    """The field path and description of the first key a mapping repeats, in the composed YAML tree
    (a repeated key would otherwise silently override the first), or None. An alias is the node it
    names: each node is visited once, so a tree of aliases cannot make this walk explode."""
    seen_nodes = set() if seen_nodes is None else seen_nodes
    if id(node) in seen_nodes:
        return None
    seen_nodes.add(id(node))
    if isinstance(node, yaml.MappingNode):
        seen: set[object] = set()
        for key_node, value_node in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else id(key_node)
            child = _join(path, str(key))
            if key in seen:
                return child, f"duplicate key {key!r} (line {key_node.start_mark.line + 1})"
            seen.add(key)
            found = _duplicate_key(value_node, child, seen_nodes)
            if found is not None:
                return found
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            found = _duplicate_key(item, _join(path, i), seen_nodes)
            if found is not None:
                return found
    return None


def read_yaml(path: Path) -> Any:
    """Parse a YAML file; an unreadable or malformed file, or a mapping that repeats a key, is a
    one-line ConfigError."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("", f"cannot read file: {getattr(exc, 'strerror', None) or exc}", str(path)) from None
    try:
        tree = yaml.compose(text, Loader=yaml.SafeLoader)
        if tree is None:
            return None
        duplicate = _duplicate_key(tree)
        if duplicate is not None:
            raise ConfigError(*duplicate, str(path))
        return yaml.SafeLoader(text).construct_document(tree)
    except RecursionError:
        raise ConfigError("", "invalid YAML: nested too deeply", str(path)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError("", f"invalid YAML: {where}{problem}", str(path)) from None


# --- field readers: each names the path of what it reads ----------------------------------------------


def _join(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


def _mapping(value: Any, path: str, allowed: set[str], required: set[str] = frozenset()) -> Mapping[str, Any]:  # type: ignore[assignment]
    if not isinstance(value, Mapping):
        raise ConfigError(path, f"expected a mapping, got {_describe(value)}")
    for key in value:
        if not isinstance(key, str):
            raise ConfigError(path, f"expected string keys, got {key!r}")
        if key not in allowed:
            hint = _closest(key, allowed)
            raise ConfigError(_join(path, key), f"unknown key{hint} (allowed: {', '.join(sorted(allowed))})")
    for key in sorted(required):
        if key not in value:
            raise ConfigError(_join(path, key), "missing required field")
    return value


def _closest(key: str, allowed: set[str]) -> str:
    import difflib

    match = difflib.get_close_matches(key, sorted(allowed), n=1)
    return f" (did you mean {match[0]!r}?)" if match else ""


def _describe(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    return f"{type(value).__name__} {value!r}" if not isinstance(value, (dict, list)) else type(value).__name__


def _number(value: Any, path: str, unit: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(path, f"expected a number{unit and ' in ' + unit}, got {_describe(value)}")
    if not math.isfinite(value):
        raise ConfigError(path, f"expected a finite number, got {value}")
    return float(value)


def _integer(value: Any, path: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(path, f"expected an integer, got {_describe(value)}")
    if not lo <= value <= hi:
        raise ConfigError(path, f"expected an integer in [{lo}, {hi}], got {value}")
    return value


def _string(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(path, f"expected a string, got {_describe(value)}")
    return value


def _choice(value: Any, path: str, choices: tuple[str, ...]) -> str:
    text = _string(value, path)
    if text not in choices:
        raise ConfigError(path, f"expected one of {', '.join(choices)}, got {text!r}")
    return text


def _list(value: Any, path: str) -> list[Any]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise ConfigError(path, f"expected a list, got {_describe(value)}")
    return value


def _vector(value: Any, path: str, n: int) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        raise ConfigError(path, f"expected a list of {n} numbers, got {_describe(value)}")
    return [_number(v, _join(path, i)) for i, v in enumerate(value)]


def _read_pose(value: Any, path: str) -> RigidTransform:
    """``{pos: [x, y, z]}`` plus at most one of ``rot: {w, x, y, z}`` or ``rpy_deg: [r, p, y]``."""
    m = _mapping(value, path, {"pos", "rot", "rpy_deg"})
    pos = _vector(m.get("pos", [0.0, 0.0, 0.0]), _join(path, "pos"), 3)
    if "rot" in m and "rpy_deg" in m:
        raise ConfigError(path, "give the rotation once: either rot (quaternion) or rpy_deg, not both")
    if "rot" in m:
        rpath = _join(path, "rot")
        q = _mapping(m["rot"], rpath, {"w", "x", "y", "z"}, {"w", "x", "y", "z"})
        q_wxyz = [_number(q[k], _join(rpath, k)) for k in ("w", "x", "y", "z")]
        try:
            rotation = geometry.rotation_from_wxyz(q_wxyz)
        except GeometryError as exc:
            raise ConfigError(rpath, str(exc)) from None
    elif "rpy_deg" in m:
        rotation = geometry.rotation_from_rpy_deg(_vector(m["rpy_deg"], _join(path, "rpy_deg"), 3))
    else:
        rotation = None
    return geometry.make_pose(pos, rotation)


def _read_fusion(value: Any, path: str) -> FusionConfig:
    if value is None:
        return FusionConfig()
    keys = {"edge_timeout_s", "ema_alpha", "weighting", "path", "relative_poses", "age_sigma_m_per_s"}
    keys |= {"age_sigma_deg_per_s"}
    keys |= {"outlier_gate_sigma", "filter", "ekf_accel_noise", "ekf_max_predict_s", "method"}
    m = _mapping(value, path, keys)
    method = _choice(m.get("method", "default"), _join(path, "method"), FUSION_METHODS)
    default = PAPER_FUSION if method == "paper" else FusionConfig()
    timeout = _number(m.get("edge_timeout_s", default.edge_timeout_s), _join(path, "edge_timeout_s"), "seconds")
    if not 0.0 < timeout <= 10.0:
        raise ConfigError(_join(path, "edge_timeout_s"), f"expected a timeout in (0, 10] seconds, got {timeout}")
    alpha = _number(m.get("ema_alpha", default.ema_alpha), _join(path, "ema_alpha"))
    if not 0.0 < alpha <= 1.0:
        raise ConfigError(_join(path, "ema_alpha"), f"expected alpha in (0, 1], got {alpha}")
    weighting = _choice(
        m.get("weighting", default.weighting.value), _join(path, "weighting"), tuple(w.value for w in Weighting)
    )
    graph_path = _choice(m.get("path", default.path), _join(path, "path"), ("bfs", "dijkstra"))
    relative = m.get("relative_poses", default.relative_poses)
    if not isinstance(relative, bool):
        raise ConfigError(_join(path, "relative_poses"), f"expected true or false, got {_describe(relative)}")
    age = _number(m.get("age_sigma_m_per_s", default.age_sigma_m_per_s), _join(path, "age_sigma_m_per_s"), "m/s")
    if not 0.0 <= age <= 100.0:
        raise ConfigError(_join(path, "age_sigma_m_per_s"), f"expected a speed in [0, 100] m/s, got {age:g}")
    age_deg = _number(
        m.get("age_sigma_deg_per_s", default.age_sigma_deg_per_s), _join(path, "age_sigma_deg_per_s"), "deg/s"
    )
    if not 0.0 <= age_deg <= 3600.0:
        raise ConfigError(
            _join(path, "age_sigma_deg_per_s"), f"expected a turn rate in [0, 3600] deg/s, got {age_deg:g}"
        )
    gate = _number(m.get("outlier_gate_sigma", default.outlier_gate_sigma), _join(path, "outlier_gate_sigma"))
    if gate != 0.0 and not 2.0 <= gate <= 100.0:
        raise ConfigError(_join(path, "outlier_gate_sigma"), f"expected 0 (off) or a gate in [2, 100], got {gate:g}")
    filt = _choice(m.get("filter", default.filter), _join(path, "filter"), ("none", "ekf"))
    accel = _number(m.get("ekf_accel_noise", default.ekf_accel_noise), _join(path, "ekf_accel_noise"), "m/s^2")
    if not 0.01 <= accel <= 100.0:
        raise ConfigError(_join(path, "ekf_accel_noise"), f"expected a noise in [0.01, 100] m/s^2, got {accel:g}")
    horizon = _number(m.get("ekf_max_predict_s", default.ekf_max_predict_s), _join(path, "ekf_max_predict_s"), "s")
    if not 0.0 < horizon <= 5.0:
        raise ConfigError(_join(path, "ekf_max_predict_s"), f"expected a horizon in (0, 5] s, got {horizon:g}")
    return FusionConfig(
        timeout, alpha, Weighting(weighting), graph_path, relative, age, gate, filt, accel, horizon, age_deg, method
    )


def _read_camera(value: Any, path: str, base_dir: Path | None) -> CameraConfig:
    keys = {"source", "calibration", "width_px", "height_px", "fps", "fourcc", "latency_ms", "replay"}
    m = _mapping(value, path, keys)
    source = m.get("source", "")
    if isinstance(source, int) and not isinstance(source, bool):
        source = str(source)
    source = _string(source, _join(path, "source"))
    calibration = None
    if "calibration" in m:
        calibration = Path(_string(m["calibration"], _join(path, "calibration")))
        if base_dir is not None and not calibration.is_absolute():
            calibration = base_dir / calibration
    width = _integer(m.get("width_px", 0), _join(path, "width_px"), 0, 16384)
    height = _integer(m.get("height_px", 0), _join(path, "height_px"), 0, 16384)
    fps = _number(m.get("fps", 0.0), _join(path, "fps"), "Hz")
    if not 0.0 <= fps <= 1000.0:
        raise ConfigError(_join(path, "fps"), f"expected a frame rate in [0, 1000] Hz, got {fps}")
    fourcc = _string(m.get("fourcc", ""), _join(path, "fourcc"))
    if fourcc and len(fourcc) != 4:
        raise ConfigError(_join(path, "fourcc"), f"expected four characters, got {fourcc!r}")
    latency = _number(m.get("latency_ms", 0.0), _join(path, "latency_ms"), "milliseconds")
    if not 0.0 <= latency <= 1000.0:
        raise ConfigError(_join(path, "latency_ms"), f"expected a latency in [0, 1000] ms, got {latency}")
    replay = _string(m.get("replay", ""), _join(path, "replay"))
    if replay not in ("", *REPLAY_MODES):
        raise ConfigError(_join(path, "replay"), f"expected one of {', '.join(REPLAY_MODES)}, got {replay!r}")
    return CameraConfig(source, calibration, width, height, fps, fourcc, latency, replay)


def _read_entity(
    name: str,
    value: Any,
    path: str,
    world: frames.WorldConvention,
    body: frames.BodyConvention,
    default_family: str,
    base_dir: Path | None,
) -> EntityConfig:
    m = _mapping(value if value is not None else {}, path, {"sensors", "markers"})

    def to_internal(T: RigidTransform) -> RigidTransform:
        return frames.world_to_enu(T, world) if name == WORLD else frames.body_to_flu(T, body)

    # A world camera's mount frame follows the world axes: ENU is right-handed with z up like FLU,
    # NED with z down like FRD.
    if name == WORLD:
        world_body = frames.BodyConvention.FLU if world is frames.WorldConvention.ENU else frames.BodyConvention.FRD
    else:
        world_body = body

    sensors = []
    for i, raw in enumerate(_list(m.get("sensors"), _join(path, "sensors"))):
        spath = _join(_join(path, "sensors"), i)
        s = _mapping(raw, spath, {"name", "id", "pose", "pose_of", "camera"}, {"name", "id", "pose"})
        sname = _string(s["name"], _join(spath, "name"))
        if not _NAME_RE.match(sname):
            raise ConfigError(_join(spath, "name"), f"expected a name of letters, digits, _ or -, got {sname!r}")
        pose_of = _choice(s.get("pose_of", "mount"), _join(spath, "pose_of"), ("mount", "optical"))
        T = _read_pose(s["pose"], _join(spath, "pose"))
        if pose_of == "mount":
            # The mount frame has the axes of the file's convention (FRD in an FRD file: y right, z
            # down), so it becomes the optical frame before the parent frame is re-expressed.
            T = frames.mount_to_optical(T, world_body)
        T = to_internal(T)
        camera = _read_camera(s["camera"], _join(spath, "camera"), base_dir) if "camera" in s else None
        sensors.append(SensorConfig(sname, _integer(s["id"], _join(spath, "id"), 0, MAX_ID), name, T, camera))

    markers = []
    for i, raw in enumerate(_list(m.get("markers"), _join(path, "markers"))):
        mpath = _join(_join(path, "markers"), i)
        mk = _mapping(raw, mpath, {"id", "size_m", "family", "pose"}, {"id", "size_m", "pose"})
        size = _number(mk["size_m"], _join(mpath, "size_m"), "metres")
        if not 0.0 < size <= 10.0:
            raise ConfigError(_join(mpath, "size_m"), f"expected a marker size in (0, 10] metres, got {size}")
        family = _choice(mk.get("family", default_family), _join(mpath, "family"), MARKER_FAMILIES)
        T = to_internal(_read_pose(mk["pose"], _join(mpath, "pose")))
        markers.append(MarkerConfig(_integer(mk["id"], _join(mpath, "id"), 0, MAX_ID), size, family, name, T))
    return EntityConfig(name, tuple(sensors), tuple(markers))


WORLD_KEYS = {"version", "conventions", "fusion", "marker_family", "entities", "nodes"}


def parse_world(doc: Any, source: Path | None = None, extra_keys: set[str] = frozenset()) -> WorldConfig:  # type: ignore[assignment]
    """Validate a parsed world document; ``extra_keys`` are top-level keys another reader owns."""
    m = _mapping(doc, "", WORLD_KEYS | set(extra_keys), {"entities"})
    if "version" in m:
        version = _integer(m["version"], "version", 0, 1 << 16)
        if version != SCHEMA_VERSION:
            raise ConfigError("version", f"expected version {SCHEMA_VERSION}, got {version}")
    conv = _mapping(m.get("conventions", {}), "conventions", {"world", "body"})
    world = frames.WorldConvention(
        _choice(conv.get("world", "ENU"), "conventions.world", tuple(c.value for c in frames.WorldConvention))
    )
    body = frames.BodyConvention(
        _choice(conv.get("body", "FLU"), "conventions.body", tuple(c.value for c in frames.BodyConvention))
    )
    fusion = _read_fusion(m.get("fusion"), "fusion")
    family = _choice(m.get("marker_family", "tag36h11"), "marker_family", MARKER_FAMILIES)
    base_dir = source.parent if source is not None else None

    raw_entities = m["entities"]
    if not isinstance(raw_entities, Mapping):
        raise ConfigError("entities", f"expected a mapping of entity name to entity, got {_describe(raw_entities)}")
    entities: list[EntityConfig] = []
    if WORLD not in raw_entities:
        entities.append(EntityConfig(WORLD))
    for name, value in raw_entities.items():
        path = _join("entities", str(name))
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ConfigError(path, f"expected an entity name of letters, digits, _ or - (max 32), got {name!r}")
        entities.append(_read_entity(name, value, path, world, body, family, base_dir))
    if len(entities) > 255:
        raise ConfigError("entities", f"expected at most 255 entities, got {len(entities)}")

    _check_unique(entities)
    return WorldConfig(tuple(entities), fusion, world, body, source)


def _check_unique(entities: list[EntityConfig]) -> None:
    sensor_ids: dict[int, str] = {}
    marker_ids: dict[int, str] = {}
    for ent in entities:
        epath = _join("entities", ent.name)
        names: set[str] = set()
        for i, s in enumerate(ent.sensors):
            spath = _join(_join(epath, "sensors"), i)
            if s.name in names:
                raise ConfigError(_join(spath, "name"), f"duplicate sensor name {s.name!r} in entity {ent.name!r}")
            names.add(s.name)
            if s.id in sensor_ids:
                raise ConfigError(
                    _join(spath, "id"), f"duplicate sensor id {s.id} (already used by {sensor_ids[s.id]})"
                )
            sensor_ids[s.id] = f"{ent.name}.{s.name}"
        for i, mk in enumerate(ent.markers):
            mpath = _join(_join(epath, "markers"), i)
            if mk.id in marker_ids:
                raise ConfigError(
                    _join(mpath, "id"), f"duplicate marker id {mk.id} (already used by {marker_ids[mk.id]})"
                )
            marker_ids[mk.id] = f"{ent.name}.markers"


def load_world(path: Path | str, extra_keys: set[str] = frozenset()) -> WorldConfig:  # type: ignore[assignment]
    """Read and validate a world file; every problem is a ConfigError naming the file and field."""
    p = Path(path)
    doc = read_yaml(p)
    try:
        world = parse_world(doc, p, extra_keys)
        check_nodes(doc, world, p.parent)
    except ConfigError as exc:
        raise ConfigError(exc.path, exc.problem, str(p)) from None
    return world


def check_nodes(doc: Any, world: WorldConfig, base_dir: Path | None = None) -> tuple[NodeConfig, ...]:
    """Validate every node named in the ``nodes`` section (none if there is no such section)."""
    if not isinstance(doc, Mapping) or doc.get("nodes") is None:
        return ()
    nodes = _mapping(doc["nodes"], "nodes", {"defaults", *world.entity_names})
    parsed = tuple(parse_node(doc, name, world, base_dir) for name in nodes if name != "defaults")
    ids: dict[int, str] = {}
    for n in parsed:
        if n.system_id in ids:
            raise ConfigError(
                f"nodes.{n.entity}.system_id", f"duplicate system id {n.system_id} (also {ids[n.system_id]})"
            )
        ids[n.system_id] = n.entity
    return parsed


def security_notes(path: Path | str) -> list[str]:
    """Warnings about who can move a pose, for ``check-config``: each node's peer links that take
    unsigned observations, and entities with sensors that no node runs (their observations are
    refused). None for a file without a ``nodes`` section (it runs no node)."""
    p = Path(path)
    doc = read_yaml(p)
    world = parse_world(doc, p, extra_keys={"nodes"})
    nodes = check_nodes(doc, world, p.parent)
    notes = []
    for node in nodes:
        for i, link in enumerate(node.peers):
            where = f"nodes.{node.entity}.peers[{i}] ({link.url})"
            if link.signing is None:
                notes.append(f"warning: {where} is not signed: any host on the network can move {node.entity}'s pose")
            elif not link.signing.require:
                notes.append(
                    f"warning: {where} accepts unsigned observations (require: false): any host on the network"
                    f" can move {node.entity}'s pose"
                )
    if nodes:
        run = {n.entity for n in nodes}
        for ent in world.entities:
            if ent.sensors and ent.name not in run:
                notes.append(
                    f"warning: entity {ent.name} has sensors but no node (system id) in the nodes section:"
                    f" every node refuses their observations"
                )
    return notes


def summary(world: WorldConfig) -> str:
    """A human-readable summary: entities, sensors, markers, and which entity can see which."""
    lines = [
        f"world file: {world.source or '(in memory)'}",
        f"conventions: world {world.world_convention.value}, body {world.body_convention.value} (internal ENU/FLU)",
        f"fusion: edge_timeout {world.fusion.edge_timeout_s * 1000:.0f} ms, ema_alpha {world.fusion.ema_alpha:g},"
        f" weighting {world.fusion.weighting.value}",
        f"fingerprint: {world.fingerprint():08x}",
        f"{len(world.entities)} entities, {len(world.sensors)} sensors, {len(world.markers)} markers",
    ]
    for ent in world.entities:
        lines.append(f"  {ent.name}: {len(ent.sensors)} sensors, {len(ent.markers)} markers")
        for s in ent.sensors:
            p = s.T_entity_sensor.translation
            axis = s.T_entity_sensor.rotation.apply([0.0, 0.0, 1.0])
            lines.append(
                f"    sensor {s.name} (id {s.id}) at [{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}] m,"
                f" looking along [{axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}]"
            )
        for mk in ent.markers:
            p = mk.T_entity_marker.translation
            lines.append(
                f"    marker {mk.id} ({mk.family}, {mk.size_m * 1000:.0f} mm) at [{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}] m"
            )
    lines.append("who can see whom (a sensor of the first sees markers of the second):")
    has_markers = [e.name for e in world.entities if e.markers]
    for ent in world.entities:
        if ent.sensors:
            targets = [n for n in has_markers if n != ent.name]
            lines.append(f"  {ent.name} -> {', '.join(targets) if targets else '(no markers elsewhere)'}")
    unseen = [e.name for e in world.entities if e.name != WORLD and not e.sensors and not e.markers]
    if unseen:
        lines.append(f"warning: entities with neither sensors nor markers can never be localized: {', '.join(unseen)}")
    return "\n".join(lines)


# --- node settings: the `nodes:` section ---------------------------------------------------------------


class AutopilotOutput(StrEnum):
    """The message that carries the pose to the autopilot."""

    VISION_POSITION_ESTIMATE = "vision_position_estimate"
    ODOMETRY = "odometry"


@dataclass(frozen=True, slots=True)
class SigningConfig:
    """MAVLink 2 signing of one link.

    Attributes:
        key_file: 32-byte secret key (raw bytes, or 64 hex characters); must not be readable by others.
        sign_outgoing: sign what this node sends on the link.
        require: drop (and count) unsigned or badly signed observations received on the link.
    """

    key_file: Path
    sign_outgoing: bool = True
    require: bool = True


@dataclass(frozen=True, slots=True)
class LinkConfig:
    """One MAVLink connection, written as pymavlink/MAVProxy write them.

    Attributes:
        url: ``/dev/ttyAMA0,921600``, ``udpin:0.0.0.0:14550``, ``udpout:10.0.0.2:14550``,
            ``udpbcast:10.0.0.255:14550`` or ``tcp:127.0.0.1:5760``.
        tunnel: carry observations inside standard TUNNEL messages (for links through a flight
            controller, which drops unknown message ids).
        signing: MAVLink 2 signing, or None for an unsigned link.
        rate_limit_hz: most observations accepted per second from one peer system on this link.
    """

    url: str
    tunnel: bool = False
    signing: SigningConfig | None = None
    rate_limit_hz: float = 1000.0


@dataclass(frozen=True, slots=True)
class GlobalOrigin:
    """The EKF origin given to an autopilot that has none (asked first with MAV_CMD_REQUEST_MESSAGE).

    ``send_to_px4``: PX4 needs no origin to hold position, and v1.16 moves its local height when an
    origin's altitude arrives after height initialisation; it gets one only when this is true, and
    then with altitude 0 m, which leaves its local height alone (docs/px4.md).
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    send_to_px4: bool = False


@dataclass(frozen=True, slots=True)
class AutopilotConfig:
    """The link to this drone's flight controller and what is sent on it.

    Attributes:
        link: the connection (its ``tunnel`` and ``rate_limit_hz`` are unused here).
        output: VISION_POSITION_ESTIMATE (default) or ODOMETRY (LOCAL_FRD / BODY_FRD).
        rate_hz: most pose messages per second (one per new observation of the own entity, capped).
        component_id: MAVLink component id of this node (197: MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).
        reset_jump_m: a jump of the published position larger than this increments reset_counter.
        origin: the EKF origin for an autopilot that reports none (ArduPilot needs one; PX4 only if asked).
    """

    link: LinkConfig
    output: AutopilotOutput = AutopilotOutput.VISION_POSITION_ESTIMATE
    rate_hz: float = 30.0
    component_id: int = 197
    reset_jump_m: float = 0.5
    origin: GlobalOrigin | None = None


# --- record: the node records its cameras as it flies (issue 21; docs/mapping.md) -----------------------
RECORD_FORMATS = ("png", "jpg")


@dataclass(frozen=True, slots=True)
class RecordConfig:
    """``nodes.<entity>.record`` (or ``run --record DIR``): the node records each camera as it flies.

    Attributes:
        dir: where recordings go; each run and camera writes a new subdirectory.
        max_mb: cap on everything under ``dir`` (this run's and earlier runs' recordings), MB;
            past it frames are not recorded (counted, said once). Default 2000.
        image_format: ``png`` (lossless, the default) or ``jpg`` (quality 95: smaller, faster to write).
    """

    dir: Path
    max_mb: float = 2000.0
    image_format: str = "png"


def _read_record(value: Any, path: str, base_dir: Path | None) -> RecordConfig | None:
    if value is None:
        return None
    m = _mapping(value, path, {"dir", "max_mb", "image_format"}, {"dir"})
    directory = Path(_string(m["dir"], _join(path, "dir")))
    if base_dir is not None and not directory.is_absolute():
        directory = base_dir / directory
    max_mb = _number(m.get("max_mb", 2000.0), _join(path, "max_mb"), "MB")
    if not 1.0 <= max_mb <= 10_000_000.0:
        raise ConfigError(_join(path, "max_mb"), f"expected a size in [1, 1e7] MB, got {max_mb:g}")
    fmt = _string(m.get("image_format", "png"), _join(path, "image_format"))
    if fmt not in RECORD_FORMATS:
        raise ConfigError(_join(path, "image_format"), f"expected one of {', '.join(RECORD_FORMATS)}, got {fmt!r}")
    return RecordConfig(directory, max_mb, fmt)


# --- end record ----------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class NodeConfig:
    """The settings of the node that runs for one entity.

    Attributes:
        entity: the entity whose pose this node publishes.
        system_id: this drone's MAVLink system id (the autopilot's SYSID_THISMAV / MAV_SYS_ID);
            it also identifies this node's observations on peer links, so it is unique in the swarm.
        autopilot: the flight-controller link, or None (e.g. a ground node with world cameras).
        peers: links to the other drones and the ground station.
        fused_rate_hz: how often the fused poses of every entity go to peers and the GCS.
        heartbeat_hz: HEARTBEAT rate on every link.
        queue_size: observations waiting for the graph; beyond it the oldest are dropped (counted).
        state_dir: where signing timestamps and the autopilot's reset counter persist across restarts.
        status_interval_s: period of the health log line.
        owners: (entity, system id) of every node the world file's ``nodes`` section names: whose
            observations and fused poses this node accepts from whom (:meth:`owner_system_id`).
        record: record the cameras as the node flies (:class:`RecordConfig`), or None (the default).
    """

    entity: str
    system_id: int
    autopilot: AutopilotConfig | None = None
    peers: tuple[LinkConfig, ...] = ()
    fused_rate_hz: float = 5.0
    heartbeat_hz: float = 1.0
    queue_size: int = 256
    state_dir: Path | None = None
    status_interval_s: float = 10.0
    owners: tuple[tuple[str, int], ...] = ()
    record: RecordConfig | None = None  # issue 21: run --record

    def owner_system_id(self, entity: str) -> int | None:
        """The system id of the node that runs ``entity``, or None if the world file names none."""
        for name, sysid in self.owners:
            if name == entity:
                return sysid
        return None


_NODE_KEYS = {
    "system_id",
    "autopilot",
    "peers",
    "fused_rate_hz",
    "heartbeat_hz",
    "queue_size",
    "state_dir",
    "status_interval_s",
    "record",  # issue 21
}


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def _bool(value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(path, f"expected true or false, got {_describe(value)}")
    return value


def _rate(value: Any, path: str, lo: float = 0.1, hi: float = 1000.0) -> float:
    rate = _number(value, path, "Hz")
    if not lo <= rate <= hi:
        raise ConfigError(path, f"expected a rate in [{lo:g}, {hi:g}] Hz, got {rate:g}")
    return rate


_URL_RE = re.compile(
    r"^(udpin|udpout|udpbcast|udp|tcp|tcpin):[A-Za-z0-9._-]+:\d{1,5}$"  # network: HOST:PORT
    r"|^/\S+?(,\d+)?$|^COM\d+(,\d+)?$"  # serial: /DEVICE/PATH[,BAUD]
)


def _read_link(value: Any, path: str, base_dir: Path | None) -> LinkConfig:
    if isinstance(value, str):
        value = {"url": value}
    m = _mapping(value, path, {"url", "tunnel", "signing", "rate_limit_hz"}, {"url"})
    url = _string(m["url"], _join(path, "url"))
    if not _URL_RE.match(url):
        raise ConfigError(
            _join(path, "url"),
            f"expected a connection string such as udpin:0.0.0.0:14550, udpout:HOST:PORT, tcp:HOST:PORT or"
            f" /dev/ttyAMA0,921600, got {url!r}",
        )
    signing = None
    if "signing" in m:
        spath = _join(path, "signing")
        s = _mapping(m["signing"], spath, {"key_file", "sign_outgoing", "require"}, {"key_file"})
        key = Path(_string(s["key_file"], _join(spath, "key_file")))
        if base_dir is not None and not key.is_absolute():
            key = base_dir / key
        signing = SigningConfig(
            key,
            _bool(s.get("sign_outgoing", True), _join(spath, "sign_outgoing")),
            _bool(s.get("require", True), _join(spath, "require")),
        )
    return LinkConfig(
        url,
        _bool(m.get("tunnel", False), _join(path, "tunnel")),
        signing,
        _rate(m.get("rate_limit_hz", 1000.0), _join(path, "rate_limit_hz"), 1.0, 100000.0),
    )


def _read_autopilot(value: Any, path: str, base_dir: Path | None, partial: bool = False) -> AutopilotConfig | None:
    if value is None:
        return None
    keys = {"url", "signing", "output", "rate_hz", "component_id", "reset_jump_m", "origin"}
    m = dict(_mapping(value, path, keys, set() if partial else {"url"}))
    m.setdefault("url", "udpout:127.0.0.1:1")  # partial: a section that leaves the url to another
    link = _read_link({k: m[k] for k in ("url", "signing") if k in m}, path, base_dir)
    output = AutopilotOutput(
        _choice(
            m.get("output", "vision_position_estimate"), _join(path, "output"), tuple(o.value for o in AutopilotOutput)
        )
    )
    jump = _number(m.get("reset_jump_m", 0.5), _join(path, "reset_jump_m"), "metres")
    if not 0.0 < jump <= 100.0:
        raise ConfigError(_join(path, "reset_jump_m"), f"expected a distance in (0, 100] metres, got {jump:g}")
    origin = None
    if "origin" in m:
        opath = _join(path, "origin")
        o = _mapping(
            m["origin"], opath, {"lat_deg", "lon_deg", "alt_m", "send_to_px4"}, {"lat_deg", "lon_deg", "alt_m"}
        )
        lat, lon = _number(o["lat_deg"], _join(opath, "lat_deg")), _number(o["lon_deg"], _join(opath, "lon_deg"))
        if not -90.0 <= lat <= 90.0:
            raise ConfigError(_join(opath, "lat_deg"), f"expected a latitude in [-90, 90] degrees, got {lat:g}")
        if not -180.0 <= lon <= 180.0:
            raise ConfigError(_join(opath, "lon_deg"), f"expected a longitude in [-180, 180] degrees, got {lon:g}")
        origin = GlobalOrigin(
            lat,
            lon,
            _number(o["alt_m"], _join(opath, "alt_m"), "metres"),
            _bool(o.get("send_to_px4", False), _join(opath, "send_to_px4")),
        )
    return AutopilotConfig(
        link,
        output,
        _rate(m.get("rate_hz", 30.0), _join(path, "rate_hz"), 1.0, 200.0),
        _integer(m.get("component_id", 197), _join(path, "component_id"), 1, 255),
        jump,
        origin,
    )


def _read_node(m: Mapping[str, Any], path: str, entity: str, base_dir: Path | None, partial: bool) -> NodeConfig:
    """Build a node's settings from one mapping; ``partial`` skips required fields (a defaults section)."""
    _mapping(m, path, _NODE_KEYS)
    if "system_id" not in m and not partial:
        raise ConfigError(_join(path, "system_id"), "missing required field (this drone's MAVLink system id)")
    peers_path = _join(path, "peers")
    peers = tuple(
        _read_link(v, _join(peers_path, i), base_dir) for i, v in enumerate(_list(m.get("peers"), peers_path))
    )
    status = _number(m.get("status_interval_s", 10.0), _join(path, "status_interval_s"), "seconds")
    if not 0.5 <= status <= 3600.0:
        raise ConfigError(_join(path, "status_interval_s"), f"expected an interval in [0.5, 3600] s, got {status:g}")
    return NodeConfig(
        entity=entity,
        system_id=_integer(m.get("system_id", 1), _join(path, "system_id"), 1, 255),
        autopilot=_read_autopilot(m.get("autopilot"), _join(path, "autopilot"), base_dir, partial),
        peers=peers,
        fused_rate_hz=_rate(m.get("fused_rate_hz", 5.0), _join(path, "fused_rate_hz"), 0.1, 100.0),
        heartbeat_hz=_rate(m.get("heartbeat_hz", 1.0), _join(path, "heartbeat_hz"), 0.1, 10.0),
        queue_size=_integer(m.get("queue_size", 256), _join(path, "queue_size"), 8, 1_000_000),
        state_dir=Path(_string(m["state_dir"], _join(path, "state_dir"))) if "state_dir" in m else None,
        status_interval_s=status,
        record=_read_record(m.get("record"), _join(path, "record"), base_dir),  # issue 21
    )


def parse_node(doc: Any, entity: str, world: WorldConfig, base_dir: Path | None = None) -> NodeConfig:
    """The settings of ``entity``'s node: ``nodes.defaults`` overridden key by key by ``nodes.<entity>``.

    Each section is validated where it is written (so an error names the section that holds the bad
    value), then the merged settings are built, which only adds the checks for required fields.
    """
    if entity not in world.entity_names:
        raise ConfigError("", f"unknown entity {entity!r} (the world file has {', '.join(world.entity_names)})")
    raw = doc.get("nodes") if isinstance(doc, Mapping) else None
    if raw is None:
        raise ConfigError("nodes", NO_NODES)
    nodes = _mapping(raw, "nodes", {"defaults", *world.entity_names})
    defaults = nodes.get("defaults") or {}
    own = nodes.get(entity) or {}
    path = _join("nodes", entity)
    _read_node(defaults, "nodes.defaults", entity, base_dir, partial=True)
    _read_node(own, path, entity, base_dir, partial=True)
    config = _read_node(_merge(defaults, own), path, entity, base_dir, partial=False)
    return replace(config, owners=_owners(nodes, defaults))


def _owners(nodes: Mapping[str, Any], defaults: Mapping[str, Any]) -> tuple[tuple[str, int], ...]:
    """(entity, system id) of every node named in the ``nodes`` section that has a system id."""
    out = []
    for name, own in nodes.items():
        if name == "defaults":
            continue
        merged = _merge(defaults, own or {})
        if "system_id" in merged:
            out.append((name, _integer(merged["system_id"], _join(_join("nodes", name), "system_id"), 1, 255)))
    return tuple(out)


def load_node(path: Path | str, entity: str) -> tuple[WorldConfig, NodeConfig]:
    """Read a world file with a ``nodes`` section and validate both for ``entity``."""
    p = Path(path)
    doc = read_yaml(p)
    try:
        world = parse_world(doc, p, extra_keys={"nodes"})
        return world, parse_node(doc, entity, world, p.parent)
    except ConfigError as exc:
        raise ConfigError(exc.path, exc.problem, str(p)) from None
