"""World file and node settings: YAML -> frozen dataclasses, with errors that name the exact field.

One world file is shared by every drone of a swarm. It states its frame conventions once, the fusion
settings, and the entities (``world`` always exists) with their sensors and markers; its ``nodes``
section holds each node's links and autopilot. Modules:

- :mod:`.fields`: how a setting is declared (default, unit, range, doc, once) and the primitive checks;
- :mod:`.model`: the world model (entities, sensors, markers, their poses, the fingerprint);
- :mod:`.settings`: fusion, camera, links, signing, autopilot and node settings;
- :mod:`.read_world`, :mod:`.read_nodes`, :mod:`.yamlio`, :mod:`.load`: the readers;
- :mod:`.reference`: the table of every setting (``docs/settings.md``).
"""

from atlas_onboard.config.fields import defaults
from atlas_onboard.config.load import load_node, load_world, security_notes
from atlas_onboard.config.model import (
    APRILTAG_FAMILIES,
    ARUCO_DICTIONARIES,
    MARKER_FAMILIES,
    MAX_ID,
    SCHEMA_VERSION,
    WORLD,
    EntityConfig,
    MarkerConfig,
    SensorConfig,
    WorldConfig,
)
from atlas_onboard.config.read_nodes import NO_NODES, check_nodes, parse_node
from atlas_onboard.config.read_world import WORLD_KEYS, parse_world
from atlas_onboard.config.settings import (
    FUSION_METHODS,
    OUTLIER_GATE_SIGMA,
    PAPER_FUSION,
    RECORD_FORMATS,
    REPLAY_EVERY_FRAME,
    REPLAY_MODES,
    REPLAY_REALTIME,
    AutopilotConfig,
    AutopilotOutput,
    CameraConfig,
    FusionConfig,
    GlobalOrigin,
    LandingConfig,
    LinkConfig,
    NodeConfig,
    RecordConfig,
    RefineConfig,
    SigningConfig,
    Weighting,
)
from atlas_onboard.config.yamlio import read_yaml
from atlas_onboard.errors import ConfigError, GeometryError

__all__ = [
    "APRILTAG_FAMILIES",
    "ARUCO_DICTIONARIES",
    "FUSION_METHODS",
    "MARKER_FAMILIES",
    "MAX_ID",
    "NO_NODES",
    "OUTLIER_GATE_SIGMA",
    "PAPER_FUSION",
    "RECORD_FORMATS",
    "REPLAY_EVERY_FRAME",
    "REPLAY_MODES",
    "REPLAY_REALTIME",
    "SCHEMA_VERSION",
    "WORLD",
    "WORLD_KEYS",
    "AutopilotConfig",
    "AutopilotOutput",
    "CameraConfig",
    "ConfigError",
    "EntityConfig",
    "FusionConfig",
    "GeometryError",
    "GlobalOrigin",
    "LandingConfig",
    "LinkConfig",
    "MarkerConfig",
    "NodeConfig",
    "RecordConfig",
    "RefineConfig",
    "SensorConfig",
    "SigningConfig",
    "Weighting",
    "WorldConfig",
    "check_nodes",
    "defaults",
    "load_node",
    "load_world",
    "parse_node",
    "parse_world",
    "read_yaml",
    "security_notes",
]
