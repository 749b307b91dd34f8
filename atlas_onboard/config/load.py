"""World files in: read, validate and summarise who can move a pose (``check-config``'s warnings)."""

from __future__ import annotations

from pathlib import Path

from atlas_onboard.config.model import WorldConfig
from atlas_onboard.config.read_nodes import check_nodes, parse_node
from atlas_onboard.config.read_world import parse_world
from atlas_onboard.config.settings import NodeConfig
from atlas_onboard.config.yamlio import read_yaml
from atlas_onboard.errors import ConfigError


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


def load_node(path: Path | str, entity: str) -> tuple[WorldConfig, NodeConfig]:
    """Read a world file with a ``nodes`` section and validate both for ``entity``."""
    p = Path(path)
    doc = read_yaml(p)
    try:
        world = parse_world(doc, p, extra_keys={"nodes"})
        return world, parse_node(doc, entity, world, p.parent)
    except ConfigError as exc:
        raise ConfigError(exc.path, exc.problem, str(p)) from None


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
