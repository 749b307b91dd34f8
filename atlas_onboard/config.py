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
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform

from atlas_onboard.core import frames, geometry
from atlas_onboard.errors import ConfigError, GeometryError

WORLD = "world"
"""The name of the world entity; it always exists."""

SCHEMA_VERSION = 1

APRILTAG_FAMILIES = (
    "tag36h11",
    "tag25h9",
    "tag16h5",
    "tagCircle21h7",
    "tagCircle49h12",
    "tagStandard41h12",
    "tagStandard52h13",
    "tagCustom48h12",
)
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


@dataclass(frozen=True, slots=True)
class FusionConfig:
    """Fusion settings shared by every node.

    Attributes:
        edge_timeout_s: an edge not refreshed for this long is removed (the paper: typically 250 ms).
        ema_alpha: EMA smoothing of each edge, eq. 3, in (0, 1]; 1 passes measurements through.
        weighting: candidate weights (the paper's sigma_min / sigma_i by default).
    """

    edge_timeout_s: float = 0.25
    ema_alpha: float = 1.0
    weighting: Weighting = Weighting.SIGMA_MIN


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """How a node reads a sensor's camera. All optional: a sensor fed only by peers needs none.

    Attributes:
        source: V4L2 index or path, video file, image folder, URL, or ``sim``.
        calibration: path of an OpenCV FileStorage or ROS camera_info YAML (resolved against the file).
        width_px, height_px, fps: requested capture format (0: the device's default).
        fourcc: four-character pixel format for V4L2, e.g. ``MJPG`` ("" for the default).
        latency_ms: fixed delay between exposure and the frame's arrival, subtracted from its stamp.
    """

    source: str = ""
    calibration: Path | None = None
    width_px: int = 0
    height_px: int = 0
    fps: float = 0.0
    fourcc: str = ""
    latency_ms: float = 0.0


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


# --- YAML with duplicate-key detection ---------------------------------------------------------------


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader on which a mapping that repeats a key is an error, not a silent override."""


def _construct_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    seen: dict[Any, Any] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)  # type: ignore[no-untyped-call]
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (line {key_node.start_mark.line + 1})", key_node.start_mark
            )
        seen[key] = True
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def read_yaml(path: Path) -> Any:
    """Parse a YAML file; an unreadable or malformed file is a one-line ConfigError."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("", f"cannot read file: {getattr(exc, 'strerror', None) or exc}", str(path)) from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
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
    m = _mapping(value, path, {"edge_timeout_s", "ema_alpha", "weighting"})
    default = FusionConfig()
    timeout = _number(m.get("edge_timeout_s", default.edge_timeout_s), _join(path, "edge_timeout_s"), "seconds")
    if not 0.0 < timeout <= 10.0:
        raise ConfigError(_join(path, "edge_timeout_s"), f"expected a timeout in (0, 10] seconds, got {timeout}")
    alpha = _number(m.get("ema_alpha", default.ema_alpha), _join(path, "ema_alpha"))
    if not 0.0 < alpha <= 1.0:
        raise ConfigError(_join(path, "ema_alpha"), f"expected alpha in (0, 1], got {alpha}")
    weighting = _choice(
        m.get("weighting", default.weighting.value), _join(path, "weighting"), tuple(w.value for w in Weighting)
    )
    return FusionConfig(edge_timeout_s=timeout, ema_alpha=alpha, weighting=Weighting(weighting))


def _read_camera(value: Any, path: str, base_dir: Path | None) -> CameraConfig:
    m = _mapping(value, path, {"source", "calibration", "width_px", "height_px", "fps", "fourcc", "latency_ms"})
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
    return CameraConfig(source, calibration, width, height, fps, fourcc, latency)


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

    sensors = []
    for i, raw in enumerate(_list(m.get("sensors"), _join(path, "sensors"))):
        spath = _join(_join(path, "sensors"), i)
        s = _mapping(raw, spath, {"name", "id", "pose", "pose_of", "camera"}, {"name", "id", "pose"})
        sname = _string(s["name"], _join(spath, "name"))
        if not _NAME_RE.match(sname):
            raise ConfigError(_join(spath, "name"), f"expected a name of letters, digits, _ or -, got {sname!r}")
        pose_of = _choice(s.get("pose_of", "mount"), _join(spath, "pose_of"), ("mount", "optical"))
        T = to_internal(_read_pose(s["pose"], _join(spath, "pose")))
        if pose_of == "mount":
            # The mount frame is FLU once normalised, whatever the file's body convention.
            T = frames.mount_to_optical(T, frames.BodyConvention.FLU)
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


WORLD_KEYS = {"version", "conventions", "fusion", "marker_family", "entities"}


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
        return parse_world(doc, p, extra_keys)
    except ConfigError as exc:
        raise ConfigError(exc.path, exc.problem, str(p)) from None


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


def as_array(T: RigidTransform) -> np.ndarray:
    """4x4 homogeneous matrix of a pose (for the listener's hot path)."""
    return T.as_matrix()
