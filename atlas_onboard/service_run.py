"""``atlas-onboard run``: build a node from the world file and run it as a service."""

from __future__ import annotations

import gc
import logging
import os
import sys
from dataclasses import replace
from pathlib import Path

from atlas_onboard.config import (
    NO_NODES,
    WORLD,
    ConfigError,
    NodeConfig,
    RecordConfig,
    WorldConfig,
    load_node,
    read_yaml,
)
from atlas_onboard.errors import AtlasError
from atlas_onboard.node import Camera, Node, install_signal_handlers
from atlas_onboard.service import Notifier, watchdog_interval_us

_logger = logging.getLogger(__name__)


def choose_entity(path: Path, entity: str | None) -> str:
    """``--entity``, or the only entity with node settings in the file."""
    if entity is not None:
        return entity
    doc = read_yaml(path)
    nodes = doc.get("nodes") if isinstance(doc, dict) else None
    if not nodes:
        raise ConfigError("nodes", NO_NODES, str(path))
    if not isinstance(nodes, dict):
        raise ConfigError("nodes", f"expected a mapping of entity names, got {type(nodes).__name__}", str(path))
    names = [n for n in nodes if n != "defaults"]
    if len(names) != 1:
        raise ConfigError(
            "nodes", f"give --entity: the file has node settings for {', '.join(names) or 'no entity'}", str(path)
        )
    return names[0]


def build_cameras(world: WorldConfig, config: NodeConfig) -> list[Camera]:
    """The camera workers of this node's entity (simulated ones when the source is ``sim``)."""
    cameras: list[Camera] = []
    for sensor in world.entity(config.entity).sensors:
        cam = sensor.camera
        if cam is None or not cam.source:
            continue
        if cam.source == "sim":
            from atlas_onboard.sim.camera import SimCameraWorker, camera_seed, geometric_detector, rendered_detector
            from atlas_onboard.sim.sources import MocapWorker, SimContext
            from atlas_onboard.sim.world import SimWorld

            context = SimContext.from_env()
            mocap = context.scenario.mocap
            if mocap is not None and config.entity == WORLD and sensor.name == mocap.sensor:
                cameras.append(MocapWorker(context, world, sensor.id))
                continue
            seed = camera_seed(context.seed, sensor.id)
            if os.environ.get("ATLAS_SIM_GEOMETRIC"):  # no images: corners from geometry plus noise
                intr = SimWorld(context.scenario, world).cameras[sensor.id][1]
                detect = geometric_detector(context, sensor, intr, seed)
            else:
                detect = rendered_detector(context, world, sensor, seed)
            cameras.append(SimCameraWorker(context, world, sensor, detect))
        else:
            from atlas_onboard.detector.calibration import load as load_calibration
            from atlas_onboard.detector.pipeline import Detector
            from atlas_onboard.detector.sources import CameraWorker
            from atlas_onboard.mapping.recording import is_recording, read_info

            if cam.calibration is not None:
                calibration = load_calibration(cam.calibration)
            elif is_recording(Path(cam.source)):  # a recording carries its camera's calibration
                calibration = read_info(Path(cam.source)).calibration
            else:
                raise AtlasError(
                    f"sensor {config.entity}.{sensor.name}: camera.calibration is required for {cam.source!r}"
                )
            detector = Detector(sensor, world, calibration, decimate=2.0)
            cameras.append(CameraWorker(sensor.name, cam, detector))
    if config.entity == WORLD:
        # The motion-capture "sensor" has no camera block: it is a world sensor named by the scenario.
        if os.environ.get("ATLAS_SIM"):
            from atlas_onboard.sim.sources import MocapWorker, SimContext

            context = SimContext.from_env()
            mocap = context.scenario.mocap
            if mocap is not None and not any(c.name == "mocap" for c in cameras):
                sensor = next(s for s in world.entity(WORLD).sensors if s.name == mocap.sensor)
                cameras.append(MocapWorker(context, world, sensor.id))
    return cameras


def run_node(
    config_path: Path, entity: str | None, record_dir: Path | None = None, record_max_mb: float | None = None
) -> int:
    """Load, build and run the node; returns its exit status. ``record_dir``, ``record_max_mb``:
    ``run --record``, over the node settings' ``record`` block."""
    name = choose_entity(config_path, entity)
    world, config = load_node(config_path, name)
    # The command line's --record goes beside the settings, not into them: a reload (SIGHUP) compares
    # the re-read settings with the running ones.
    record = config.record
    if record_dir is not None or record_max_mb is not None:
        if record_dir is None and record is None:
            raise AtlasError("--record-max-mb: give --record DIR too (or nodes.<entity>.record in the world file)")
        if record_max_mb is not None and record_max_mb <= 0:
            raise AtlasError(f"--record-max-mb: expected a positive size, got {record_max_mb:g}")
        base = record or RecordConfig(dir=record_dir or Path("."))
        record = replace(base, dir=record_dir or base.dir, max_mb=record_max_mb or base.max_mb)
    if os.environ.get("ATLAS_SIM"):
        from atlas_onboard.sim.runner import die_with_parent

        die_with_parent()
    from atlas_onboard.mavlink.transport import MavlinkTransport

    transport = MavlinkTransport(world, config)
    cameras = build_cameras(world, config)
    node = Node(world, config, transport, cameras, notifier=Notifier.from_environ(), config_path=config_path)
    if record is not None:
        from atlas_onboard.mapping import onboard

        for recorder in onboard.start(cameras, world, name, record):
            recorder.attitude_at = None  # LEAD (branch attitude): = node.attitude_at, as q_wxyz (FLU body, level frame)
    interval_us = watchdog_interval_us()  # half of systemd's WatchdogSec, when meant for this process
    if interval_us is not None:
        node.watchdog_interval_ns = interval_us * 1000
    install_signal_handlers(node)
    # Link threads decode bursts of datagrams while holding the GIL; with Python's default 5 ms switch
    # interval the main loop would wait up to that long for its turn. Latency matters more here.
    sys.setswitchinterval(0.0002)
    # Everything built so far (modules, the world, the dialect) lives as long as the process: keep it
    # out of the cyclic collector's scans, which otherwise grow with it and stall the loop now and then.
    gc.collect()
    gc.freeze()
    _logger.info(
        "world %s (fingerprint %08x), entity %s, %d camera(s), %d peer link(s)",
        config_path, world.fingerprint(), name, len(cameras), len(config.peers),
    )  # fmt: skip
    return node.run()
