"""The world model: entities (``world`` always exists) with their sensors and markers, their poses in the
internal ENU/FLU convention, and the world file's keys that say how to read it.

Poses written in NED/FRD are normalised by the reader (:mod:`.read_world`) to ENU/FLU (see
:mod:`atlas_onboard.core.frames`), so nothing downstream ever sees the file's convention.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from scipy.spatial.transform import RigidTransform

from atlas_onboard.config.fields import spec
from atlas_onboard.config.settings import CameraConfig, FusionConfig
from atlas_onboard.core import frames, geometry

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
NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
"""An entity or sensor name: letters, digits, _ and -, at most 32 characters."""


@dataclass(frozen=True, slots=True)
class FileOptions:
    """Top-level keys that say how to read the file (they are not part of the model)."""

    version: int = field(default=SCHEMA_VERSION, metadata=spec(
        "schema version of the file", within="[0, 65536]"))  # fmt: skip
    marker_family: str = field(default="tag36h11", metadata=spec(
        "the family of a marker that does not name its own: an AprilTag family or an OpenCV ArUco dictionary"
        " (docs/markers.md)", choices=MARKER_FAMILIES))  # fmt: skip


@dataclass(frozen=True, slots=True)
class Conventions:
    """The ``conventions`` section: the axes of everything written in the file."""

    world: frames.WorldConvention = field(default=frames.WorldConvention.ENU, metadata=spec(
        "ENU (x east, y north, z up; ROS REP-103) or NED (x north, y east, z down)"))  # fmt: skip
    body: frames.BodyConvention = field(default=frames.BodyConvention.FLU, metadata=spec(
        "FLU (x forward, y left, z up) or FRD (x forward, y right, z down)"))  # fmt: skip


POSE_DOC = "pos: [x, y, z] (metres) and at most one of rot: {w, x, y, z} or rpy_deg: [roll, pitch, yaw]"


@dataclass(frozen=True, slots=True)
class SensorConfig:
    """A camera attached to an entity.

    ``T_entity_sensor`` is the pose of the camera's OpenCV optical frame (x right, y down, z forward) in
    the entity's FLU body frame (or in ENU for the world entity), already normalised from the file.
    """

    name: str = field(metadata=spec("unique within the entity; letters, digits, _ and -"))
    id: int = field(metadata=spec("unique in the file; travels in every observation", within=f"[0, {MAX_ID}]"))
    entity: str
    T_entity_sensor: RigidTransform = field(metadata=spec(POSE_DOC, key="pose"))
    camera: CameraConfig | None = field(default=None, metadata=spec(
        "how this node reads the camera; none for sensors fed by peers"))  # fmt: skip


@dataclass(frozen=True, slots=True)
class SensorPose:
    """How a sensor's pose is written (read into ``T_entity_sensor``, not kept)."""

    pose_of: str = field(default="mount", metadata=spec(
        "mount: the pose of the camera's mount frame, a body frame whose x axis is the optical axis;"
        " optical: the pose of OpenCV's optical frame (x right, y down, z forward)",
        choices=("mount", "optical")))  # fmt: skip


@dataclass(frozen=True, slots=True)
class MarkerConfig:
    """A fiducial marker attached to an entity; ``T_entity_marker`` is its OpenCV marker frame's pose."""

    id: int = field(metadata=spec("marker id within its family; unique in the file", within=f"[0, {MAX_ID}]"))
    size_m: float = field(metadata=spec(
        "side of the black square, without the white border",
        unit="metres", within="(0, 10]", noun="a marker size"))  # fmt: skip
    family: str = field(metadata=spec(
        "this marker's family", choices=MARKER_FAMILIES, fallback="marker_family"))  # fmt: skip
    entity: str
    T_entity_marker: RigidTransform = field(metadata=spec(POSE_DOC, key="pose"))


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
