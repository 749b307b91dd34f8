"""The world file's reader: a parsed YAML document in, a validated :class:`WorldConfig` out.

Every problem raises :class:`~atlas_onboard.errors.ConfigError` with the field path, e.g.
``entities.drone2.sensors[0].pose.rot: expected a unit quaternion, got norm 1.2``. Unknown keys are
errors (a typo must not silently fall back on a default). Defaults, units and ranges are the
declarations of :mod:`.settings` and :mod:`.model`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from scipy.spatial.transform import RigidTransform

from atlas_onboard.config.fields import (
    declared,
    describe,
    join,
    keys,
    listing,
    mapping,
    number,
    read,
    required,
    vector,
)
from atlas_onboard.config.model import (
    NAME_RE,
    SCHEMA_VERSION,
    WORLD,
    Conventions,
    EntityConfig,
    FileOptions,
    MarkerConfig,
    SensorConfig,
    SensorPose,
    WorldConfig,
)
from atlas_onboard.config.settings import PAPER_FUSION, CameraConfig, FusionConfig
from atlas_onboard.core import frames, geometry
from atlas_onboard.errors import ConfigError, GeometryError

WORLD_KEYS = {"conventions", "fusion", "entities", "nodes"} | keys(FileOptions)


def read_pose(value: Any, path: str) -> RigidTransform:
    """``{pos: [x, y, z]}`` plus at most one of ``rot: {w, x, y, z}`` or ``rpy_deg: [r, p, y]``."""
    m = mapping(value, path, {"pos", "rot", "rpy_deg"})
    pos = vector(m.get("pos", [0.0, 0.0, 0.0]), join(path, "pos"), 3)
    if "rot" in m and "rpy_deg" in m:
        raise ConfigError(path, "give the rotation once: either rot (quaternion) or rpy_deg, not both")
    if "rot" in m:
        rpath = join(path, "rot")
        q = mapping(m["rot"], rpath, {"w", "x", "y", "z"}, {"w", "x", "y", "z"})
        q_wxyz = [number(q[k], join(rpath, k)) for k in ("w", "x", "y", "z")]
        try:
            rotation = geometry.rotation_from_wxyz(q_wxyz)
        except GeometryError as exc:
            raise ConfigError(rpath, str(exc)) from None
    elif "rpy_deg" in m:
        rotation = geometry.rotation_from_rpy_deg(vector(m["rpy_deg"], join(path, "rpy_deg"), 3))
    else:
        rotation = None
    return geometry.make_pose(pos, rotation)


def read_fusion(value: Any, path: str) -> FusionConfig:
    """The ``fusion`` section: each key absent takes the default, or the paper's value with ``method: paper``."""
    if value is None:
        return FusionConfig()
    m = mapping(value, path, keys(FusionConfig))
    base = PAPER_FUSION if read(FusionConfig, "method", m, path) == "paper" else FusionConfig()
    return FusionConfig(
        **{name: read(FusionConfig, name, m, path, getattr(base, name)) for name in declared(FusionConfig)}
    )


def read_camera(value: Any, path: str, base_dir: Path | None) -> CameraConfig:
    m = dict(mapping(value, path, keys(CameraConfig)))
    if isinstance(m.get("source"), int) and not isinstance(m["source"], bool):
        m["source"] = str(m["source"])  # a V4L2 index
    values = {name: read(CameraConfig, name, m, path) for name in declared(CameraConfig)}
    calibration = values["calibration"]
    if calibration is not None and base_dir is not None and not calibration.is_absolute():
        values["calibration"] = base_dir / calibration
    if values["fourcc"] and len(values["fourcc"]) != 4:
        raise ConfigError(join(path, "fourcc"), f"expected four characters, got {values['fourcc']!r}")
    return CameraConfig(**values)


def _read_entity(
    name: str,
    value: Any,
    path: str,
    world: frames.WorldConvention,
    body: frames.BodyConvention,
    default_family: str,
    base_dir: Path | None,
) -> EntityConfig:
    m = mapping(value if value is not None else {}, path, {"sensors", "markers"})

    def to_internal(T: RigidTransform) -> RigidTransform:
        return frames.world_to_enu(T, world) if name == WORLD else frames.body_to_flu(T, body)

    # A world camera's mount frame follows the world axes: ENU is right-handed with z up like FLU,
    # NED with z down like FRD.
    if name == WORLD:
        world_body = frames.BodyConvention.FLU if world is frames.WorldConvention.ENU else frames.BodyConvention.FRD
    else:
        world_body = body

    sensors = []
    for i, raw in enumerate(listing(m.get("sensors"), join(path, "sensors"))):
        spath = join(join(path, "sensors"), i)
        s = mapping(raw, spath, keys(SensorConfig) | keys(SensorPose), required(SensorConfig))
        sname = read(SensorConfig, "name", s, spath)
        if not NAME_RE.match(sname):
            raise ConfigError(join(spath, "name"), f"expected a name of letters, digits, _ or -, got {sname!r}")
        pose_of = read(SensorPose, "pose_of", s, spath)
        T = read_pose(s["pose"], join(spath, "pose"))
        if pose_of == "mount":
            # The mount frame has the axes of the file's convention (FRD in an FRD file: y right, z
            # down), so it becomes the optical frame before the parent frame is re-expressed.
            T = frames.mount_to_optical(T, world_body)
        T = to_internal(T)
        camera = read_camera(s["camera"], join(spath, "camera"), base_dir) if "camera" in s else None
        sensors.append(SensorConfig(sname, read(SensorConfig, "id", s, spath), name, T, camera))

    markers = []
    for i, raw in enumerate(listing(m.get("markers"), join(path, "markers"))):
        mpath = join(join(path, "markers"), i)
        mk = mapping(raw, mpath, keys(MarkerConfig), required(MarkerConfig))
        size = read(MarkerConfig, "size_m", mk, mpath)
        family = read(MarkerConfig, "family", mk, mpath, default_family)
        T = to_internal(read_pose(mk["pose"], join(mpath, "pose")))
        markers.append(MarkerConfig(read(MarkerConfig, "id", mk, mpath), size, family, name, T))
    return EntityConfig(name, tuple(sensors), tuple(markers))


def parse_world(doc: Any, source: Path | None = None, extra_keys: set[str] = frozenset()) -> WorldConfig:  # type: ignore[assignment]
    """Validate a parsed world document; ``extra_keys`` are top-level keys another reader owns."""
    m = mapping(doc, "", WORLD_KEYS | set(extra_keys), {"entities"})
    version = read(FileOptions, "version", m, "")
    if version != SCHEMA_VERSION:
        raise ConfigError("version", f"expected version {SCHEMA_VERSION}, got {version}")
    conv = mapping(m.get("conventions", {}), "conventions", keys(Conventions))
    world = read(Conventions, "world", conv, "conventions")
    body = read(Conventions, "body", conv, "conventions")
    fusion = read_fusion(m.get("fusion"), "fusion")
    family = read(FileOptions, "marker_family", m, "")
    base_dir = source.parent if source is not None else None

    raw_entities = m["entities"]
    if not isinstance(raw_entities, Mapping):
        raise ConfigError("entities", f"expected a mapping of entity name to entity, got {describe(raw_entities)}")
    entities: list[EntityConfig] = []
    if WORLD not in raw_entities:
        entities.append(EntityConfig(WORLD))
    for name, value in raw_entities.items():
        path = join("entities", str(name))
        if not isinstance(name, str) or not NAME_RE.match(name):
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
        epath = join("entities", ent.name)
        names: set[str] = set()
        for i, s in enumerate(ent.sensors):
            spath = join(join(epath, "sensors"), i)
            if s.name in names:
                raise ConfigError(join(spath, "name"), f"duplicate sensor name {s.name!r} in entity {ent.name!r}")
            names.add(s.name)
            if s.id in sensor_ids:
                raise ConfigError(join(spath, "id"), f"duplicate sensor id {s.id} (already used by {sensor_ids[s.id]})")
            sensor_ids[s.id] = f"{ent.name}.{s.name}"
        for i, mk in enumerate(ent.markers):
            mpath = join(join(epath, "markers"), i)
            if mk.id in marker_ids:
                raise ConfigError(
                    join(mpath, "id"), f"duplicate marker id {mk.id} (already used by {marker_ids[mk.id]})"
                )
            marker_ids[mk.id] = f"{ent.name}.markers"
