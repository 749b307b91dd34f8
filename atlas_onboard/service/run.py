"""``atlas-onboard run``: build a node from the world file and run it as a service."""

from __future__ import annotations

import gc
import logging
import signal
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from atlas_onboard.config import (
    NO_NODES,
    ConfigError,
    NodeConfig,
    RecordConfig,
    RefineConfig,
    SensorConfig,
    WorldConfig,
    load_node,
    read_yaml,
)
from atlas_onboard.errors import AtlasError
from atlas_onboard.node.loop import Node
from atlas_onboard.node.ports import Camera
from atlas_onboard.service.cores import node_cores, processes_per_camera
from atlas_onboard.service.notify import Notifier, watchdog_interval_us
from atlas_onboard.worker import SensorWorker

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


DECIMATE = 2.0  # the detector's search decimation (with region tracking)

CameraFactory = Callable[[WorldConfig, NodeConfig, SensorConfig], Camera]
"""Makes the camera worker of a sensor whose ``camera.source`` is a registered kind."""

CAMERA_KINDS: dict[str, CameraFactory] = {}
"""Camera sources that are not devices or files, by the ``camera.source`` that names them; a plug-in
(the simulator's launcher) registers its kind before the node starts."""


def register_camera_kind(kind: str, factory: CameraFactory) -> None:
    """Let ``camera.source: KIND`` make its camera with ``factory`` in this process."""
    CAMERA_KINDS[kind] = factory


def build_cameras(world: WorldConfig, config: NodeConfig, refine: RefineConfig | None = None) -> list[Camera]:
    """The camera workers of this node's entity: a registered kind's, or a device or file read by the detector.
    ``refine``: live map refinement is on, and the detector reports some images marker by marker, not an
    entity's markers as one joint solve (it needs each world marker's own pose; core/refine/sampling.py)."""
    cameras: list[Camera] = []
    sensors = [s for s in world.entity(config.entity).sensors if s.camera is not None and s.camera.source]
    detected = [s for s in sensors if s.camera is not None and s.camera.source not in CAMERA_KINDS]
    cores = node_cores(config.cores)
    processes = processes_per_camera(cores, len(detected))
    if detected:
        _logger.info(
            "%d core(s) for detection: %s", cores,
            f"{processes} worker process(es) per camera" if processes else "each camera detects in its own thread",
        )  # fmt: skip
    for sensor in sensors:
        cam = sensor.camera
        assert cam is not None
        factory = CAMERA_KINDS.get(cam.source)
        if factory is not None:
            cameras.append(factory(world, config, sensor))
            continue
        from atlas_onboard.detector.calibration import load as load_calibration
        from atlas_onboard.detector.camera import CameraWorker
        from atlas_onboard.detector.workers import CameraDetectorSpec
        from atlas_onboard.recording.format import is_recording, read_info

        if cam.calibration is not None:
            calibration = load_calibration(cam.calibration)
        elif is_recording(Path(cam.source)):  # a recording carries its camera's calibration
            calibration = read_info(Path(cam.source)).calibration
        else:
            raise AtlasError(f"sensor {config.entity}.{sensor.name}: camera.calibration is required for {cam.source!r}")
        spec = CameraDetectorSpec(sensor, world, calibration, DECIMATE, refine)
        if processes:  # each worker process makes its own detector
            cameras.append(CameraWorker(sensor.name, cam, None, spec=spec, processes=processes))
            continue
        cameras.append(CameraWorker(sensor.name, cam, spec.build()))
    return cameras


def run_node(
    config_path: Path,
    entity: str | None,
    record_dir: Path | None = None,
    record_max_mb: float | None = None,
    write_map: Path | None = None,
) -> int:
    """Load, build and run the node; returns its exit status. ``record_dir``, ``record_max_mb``:
    ``run --record``, over the node settings' ``record`` block; ``write_map``: ``run --write-map``, the
    refined world file written at exit (refinement on, over the settings' ``refine`` block)."""
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
    from atlas_onboard.service.startup_check import CheckedTransport

    refine = config.refine
    if write_map is not None:  # like --record, beside the settings (a reload compares those)
        refine = replace(refine or RefineConfig(), write_map=write_map)
    transport = CheckedTransport(world, config)  # the node's transport, with the bench checks once at start
    cameras = build_cameras(world, config, refine)
    for camera in cameras:  # a turn the autopilot reports moves the markers in the image: cameras predict it
        if isinstance(camera, SensorWorker):
            camera.attitude_at = transport.attitude_at
            camera.rate_at = transport.rate_at
            camera.velocity_at = transport.velocity_at
    node = Node(world, config, transport, cameras, notifier=Notifier.from_environ(), config_path=config_path)
    if refine is not None:
        node.enable_refinement(refine)
    if record is not None:
        from atlas_onboard.recording import onboard

        for recorder in onboard.start(cameras, world, name, record):
            recorder.attitude_at = _attitude_wxyz(transport)
    interval_us = watchdog_interval_us()  # half of systemd's WatchdogSec, when meant for this process
    if interval_us is not None:
        node.watchdog_interval_ns = interval_us * 1000
    _install_signal_handlers(node)
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


def _attitude_wxyz(transport: object) -> Callable[[int], tuple[float, float, float, float] | None]:
    """The autopilot's attitude at a capture stamp, as a recording keeps it: q_wxyz of the body FLU in
    a level ENU frame of the autopilot's heading, or None when the autopilot has sent none near it."""

    def at(t_us: int) -> tuple[float, float, float, float] | None:
        R = transport.attitude_at(t_us)  # type: ignore[attr-defined]
        if R is None:
            return None
        x, y, z, w = (float(v) for v in R.as_quat())
        return (w, x, y, z)

    return at


def _install_signal_handlers(node: Node) -> None:
    """SIGTERM/SIGINT stop the loop; SIGHUP asks for a reload. Handlers only set flags."""
    signal.signal(signal.SIGTERM, lambda *_: node.stop())
    signal.signal(signal.SIGINT, lambda *_: node.stop())
    signal.signal(signal.SIGHUP, lambda *_: node.request_reload())
