"""The ``nodes`` section's reader: each node's settings, ``nodes.defaults`` overridden key by key by
``nodes.<entity>``; defaults, units and ranges are the declarations of :mod:`.settings`."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from atlas_onboard.config.fields import (
    REQUIRED,
    declared,
    integer,
    join,
    keys,
    listing,
    mapping,
    read,
    required,
    vector,
)
from atlas_onboard.config.model import MAX_ID, WORLD, WorldConfig
from atlas_onboard.config.settings import (
    AutopilotConfig,
    GlobalOrigin,
    LandingConfig,
    LinkConfig,
    NodeConfig,
    RecordConfig,
    RefineConfig,
    SigningConfig,
)
from atlas_onboard.errors import ConfigError

NO_NODES = "missing: `atlas-onboard run` needs a nodes section (see config/example.yaml)"

_URL_RE = re.compile(
    r"^(udpin|udpout|udpbcast|udp|tcp|tcpin):[A-Za-z0-9._-]+:\d{1,5}$"  # network: HOST:PORT
    r"|^/\S+?(,\d+)?$|^COM\d+(,\d+)?$"  # serial: /DEVICE/PATH[,BAUD]
)
# An autopilot section that leaves the url to another (nodes.defaults, or an entity's own) is read with
# this stand-in, only to check its other keys.
_PARTIAL_URL = "udpout:127.0.0.1:1"


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def _resolve(path: Path, base_dir: Path | None) -> Path:
    return base_dir / path if base_dir is not None and not path.is_absolute() else path


def read_link(value: Any, path: str, base_dir: Path | None) -> LinkConfig:
    """A link: a connection string, or a mapping with ``url`` and its options."""
    if isinstance(value, str):
        value = {"url": value}
    m = mapping(value, path, keys(LinkConfig), required(LinkConfig))
    url = read(LinkConfig, "url", m, path)
    if not _URL_RE.match(url):
        raise ConfigError(
            join(path, "url"),
            f"expected a connection string such as udpin:0.0.0.0:14550, udpout:HOST:PORT, tcp:HOST:PORT or"
            f" /dev/ttyAMA0,921600, got {url!r}",
        )
    signing = None
    if "signing" in m:
        spath = join(path, "signing")
        s = mapping(m["signing"], spath, keys(SigningConfig), required(SigningConfig))
        values = {name: read(SigningConfig, name, s, spath) for name in declared(SigningConfig)}
        signing = SigningConfig(**{**values, "key_file": _resolve(values["key_file"], base_dir)})
    values = {name: read(LinkConfig, name, m, path) for name in declared(LinkConfig) if name not in ("url", "signing")}
    return LinkConfig(url=url, signing=signing, **values)


def read_autopilot(value: Any, path: str, base_dir: Path | None, partial: bool = False) -> AutopilotConfig | None:
    """The autopilot section: its link's ``url`` and ``signing`` beside what is sent on it."""
    if value is None:
        return None
    m = dict(mapping(value, path, {"url", "signing"} | keys(AutopilotConfig), set() if partial else {"url"}))
    m.setdefault("url", _PARTIAL_URL)
    link = read_link({k: m[k] for k in ("url", "signing") if k in m}, path, base_dir)
    origin = None
    if "origin" in m:
        opath = join(path, "origin")
        o = mapping(m["origin"], opath, keys(GlobalOrigin), required(GlobalOrigin))
        origin = GlobalOrigin(**{name: read(GlobalOrigin, name, o, opath) for name in declared(GlobalOrigin)})
    values = {name: read(AutopilotConfig, name, m, path) for name in declared(AutopilotConfig) if name != "origin"}
    return AutopilotConfig(link=link, origin=origin, **values)


def read_record(value: Any, path: str, base_dir: Path | None) -> RecordConfig | None:
    """The ``record`` section: where and how much the node records as it flies."""
    if value is None:
        return None
    m = mapping(value, path, keys(RecordConfig), required(RecordConfig))
    values = {name: read(RecordConfig, name, m, path) for name in declared(RecordConfig)}
    return RecordConfig(**{**values, "dir": _resolve(values["dir"], base_dir)})


def read_refine(value: Any, path: str, base_dir: Path | None) -> RefineConfig | None:
    """The ``refine`` section: which markers are surveyed, and where the refined map goes at exit."""
    if value is None:
        return None
    m = mapping(value, path, keys(RefineConfig))
    apath = join(path, "anchors")
    anchors = tuple(integer(v, join(apath, i), 0, MAX_ID) for i, v in enumerate(listing(m.get("anchors"), apath)))
    out = read(RefineConfig, "write_map", m, path)
    period = read(RefineConfig, "per_marker_period_s", m, path)
    written = _resolve(out, base_dir) if out is not None else None
    return RefineConfig(anchors=anchors, write_map=written, per_marker_period_s=period)


def read_landing(value: Any, path: str) -> LandingConfig | None:
    """The ``landing`` section: the entity and point to land on, and when a target may be sent."""
    if value is None:
        return None
    m = mapping(value, path, keys(LandingConfig), required(LandingConfig))
    values = {name: read(LandingConfig, name, m, path) for name in declared(LandingConfig) if name != "point_m"}
    point = None
    if m.get("point_m") is not None:
        x, y, z = vector(m["point_m"], join(path, "point_m"), 3)
        point = (x, y, z)
    return LandingConfig(point_m=point, **values)


def _read_node(m: Mapping[str, Any], path: str, entity: str, base_dir: Path | None, partial: bool) -> NodeConfig:
    """Build a node's settings from one mapping; ``partial`` skips required fields (a defaults section)."""
    mapping(m, path, keys(NodeConfig))
    if "system_id" not in m and not partial:
        raise ConfigError(join(path, "system_id"), "missing required field (this drone's MAVLink system id)")
    peers_path = join(path, "peers")
    peers = tuple(
        read_link(v, join(peers_path, i), base_dir) for i, v in enumerate(listing(m.get("peers"), peers_path))
    )
    # A section without system_id is only checked (partial): its stand-in id 0 is never used.
    values = {
        name: read(NodeConfig, name, m, path, 0 if name == "system_id" else REQUIRED)
        for name in declared(NodeConfig)
        if name not in ("autopilot", "peers", "record", "refine", "landing")
    }
    return NodeConfig(
        entity=entity,
        autopilot=read_autopilot(m.get("autopilot"), join(path, "autopilot"), base_dir, partial),
        peers=peers,
        record=read_record(m.get("record"), join(path, "record"), base_dir),
        refine=read_refine(m.get("refine"), join(path, "refine"), base_dir),
        landing=read_landing(m.get("landing"), join(path, "landing")),
        **values,
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
    nodes = mapping(raw, "nodes", {"defaults", *world.entity_names})
    defaults = nodes.get("defaults") or {}
    own = nodes.get(entity) or {}
    path = join("nodes", entity)
    _read_node(defaults, "nodes.defaults", entity, base_dir, partial=True)
    _read_node(own, path, entity, base_dir, partial=True)
    config = _read_node(_merge(defaults, own), path, entity, base_dir, partial=False)
    if config.refine is not None:
        world_ids = {m.id for m in world.entity(WORLD).markers}
        for i, mid in enumerate(config.refine.anchors):
            if mid not in world_ids:
                raise ConfigError(join(path, f"refine.anchors[{i}]"), f"{mid} is not a world marker of the world file")
    if config.landing is not None:
        _check_landing(config.landing, world, join(path, "landing"))
    return replace(config, owners=_owners(nodes, defaults))


def _check_landing(landing: LandingConfig, world: WorldConfig, path: str) -> None:
    """The target is an entity of the world file, and the marker one of its markers."""
    if landing.target not in world.entity_names:
        names = ", ".join(world.entity_names)
        raise ConfigError(join(path, "target"), f"unknown entity {landing.target!r} (the world file has {names})")
    if landing.marker is not None:
        marker = world.markers.get(landing.marker)
        if marker is None or marker.entity != landing.target:
            raise ConfigError(join(path, "marker"), f"{landing.marker} is not a marker of {landing.target}")


def _owners(nodes: Mapping[str, Any], defaults: Mapping[str, Any]) -> tuple[tuple[str, int], ...]:
    """(entity, system id) of every node named in the ``nodes`` section that has a system id."""
    out = []
    for name, own in nodes.items():
        if name == "defaults":
            continue
        merged = _merge(defaults, own or {})
        if "system_id" in merged:
            out.append((name, read(NodeConfig, "system_id", merged, join("nodes", name))))
    return tuple(out)


def check_nodes(doc: Any, world: WorldConfig, base_dir: Path | None = None) -> tuple[NodeConfig, ...]:
    """Validate every node named in the ``nodes`` section (none if there is no such section)."""
    if not isinstance(doc, Mapping) or doc.get("nodes") is None:
        return ()
    nodes = mapping(doc["nodes"], "nodes", {"defaults", *world.entity_names})
    parsed = tuple(parse_node(doc, name, world, base_dir) for name in nodes if name != "defaults")
    ids: dict[int, str] = {}
    for n in parsed:
        if n.system_id in ids:
            raise ConfigError(
                f"nodes.{n.entity}.system_id", f"duplicate system id {n.system_id} (also {ids[n.system_id]})"
            )
        ids[n.system_id] = n.entity
    return parsed
