"""A node's start-up and reconfiguration: the blocks a world file gives it (graph, listener, the lookups
of its intake), the world file re-read on SIGHUP, the refined map written at exit, the signal handlers.
The loop that uses them is :class:`atlas_onboard.node.loop.Node`."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from atlas_onboard.config import ConfigError, NodeConfig, Weighting, WorldConfig, load_node
from atlas_onboard.core.graph import TransformGraph
from atlas_onboard.errors import AtlasError
from atlas_onboard.listener import Listener
from atlas_onboard.node.ports import Transport
from atlas_onboard.node.refine import LiveRefinement

_logger = logging.getLogger(__name__)


@dataclass
class WorldBlocks:
    """What one world file gives a node: its graph, its listener and the lookups its intake uses."""

    world: WorldConfig
    graph: TransformGraph
    listener: Listener
    entity_of: tuple[dict[int, str], dict[int, str]]  # the entity of every sensor id, of every marker id
    supersedes: bool  # each observation simply replaces its edge (see :func:`supersedes`)


def make_graph(world: WorldConfig, own_entity: str | None = None) -> TransformGraph:
    """The transform graph a world file describes: its entities and fusion settings. The candidates
    of ``own_entity``'s sensors (the node's own cameras) are the outlier gate's anchor."""
    own = world.entity(own_entity).sensors if own_entity is not None else ()
    f = world.fusion
    return TransformGraph(
        world.entity_names,
        round(f.edge_timeout_s * 1e9),
        inverse_variance=f.weighting is Weighting.INVERSE_VARIANCE,
        path=f.path,
        relative=f.relative_poses,
        age_sigma_m_per_s=f.age_sigma_m_per_s,
        age_sigma_rad_per_s=math.radians(f.age_sigma_deg_per_s),
        outlier_gate_sigma=f.outlier_gate_sigma,
        keep_candidates=f.filter == "ekf",
        anchor_sensors=frozenset(s.id for s in own),
        max_speed_m_s=f.max_speed_m_s,
        align=f.align_edges,
        max_relayed_sigma_m=f.max_relayed_sigma_m,
    )


def wire(world: WorldConfig, config: NodeConfig, transport: Transport) -> WorldBlocks:
    """The blocks of ``world`` for the node ``config``; the autopilot's attitude, if the
    transport keeps one, resolves single tags' flips."""
    graph = make_graph(world, config.entity)
    listener = Listener(world, graph)
    history = transport.attitude
    if history is not None and config.autopilot is not None:
        listener.set_attitude(config.entity, history.up_at)
    entity_of = {s.id: s.entity for s in world.sensors.values()}, {m.id: m.entity for m in world.markers.values()}
    return WorldBlocks(world, graph, listener, entity_of, supersedes(world))


def supersedes(world: WorldConfig) -> bool:
    """Whether each observation simply replaces its edge (the paper's setting: ``ema_alpha`` 1, no
    ``age_sigma_m_per_s``), so that of several waiting observations of an edge only the newest counts."""
    return world.fusion.ema_alpha == 1.0 and world.fusion.age_sigma_m_per_s == 0.0


def reread_world(
    path: Path, world: WorldConfig, config: NodeConfig, notify: Callable[[str], None]
) -> WorldConfig | None:
    """SIGHUP: the re-read world file, or None (said in the log; an invalid file to systemd too through
    ``notify``) when it is invalid or its entities or this node's settings changed."""
    try:
        new_world, new_config = load_node(path, config.entity)
    except ConfigError as exc:
        _logger.error("reload refused, keeping the running configuration: %s", exc)
        notify("STATUS=reload refused: invalid world file")
        return None
    if new_world.entity_names != world.entity_names or new_config != config:
        _logger.error("reload refused: entities or node settings changed; restart the service to apply them")
        return None
    return new_world


def write_refined_map(refinement: LiveRefinement | None) -> None:
    """At exit, the refined world file, if asked (``refine.write_map`` or ``run --write-map``)."""
    if refinement is None or refinement.config.write_map is None:
        return
    path = refinement.config.write_map
    try:
        refinement.write(path)
    except AtlasError as exc:
        _logger.error("%s", exc)
        return
    _logger.info("refined world file written to %s (%d marker(s) refined)", path, len(refinement.markers_refined))
