"""``atlas-onboard detect`` and ``atlas-onboard markers``: the detector on an image, a video or a device, and the
configured markers as SVG files to print."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

from atlas_onboard.config import CameraConfig, load_world
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.detector.calibration import load as load_calibration
from atlas_onboard.detector.images import marker_svg, read_gray, write_annotated
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.sources import SourceError, open_source
from atlas_onboard.errors import AtlasError


def _cmd_detect(args: argparse.Namespace) -> int:
    world = load_world(args.config)
    sensor = next((s for s in world.sensors.values() if s.name == args.sensor or str(s.id) == args.sensor), None)
    if sensor is None:
        names = ", ".join(f"{s.entity}.{s.name}" for s in world.sensors.values())
        raise AtlasError(f"--sensor: no sensor {args.sensor!r} in {args.config} (there are: {names})")
    cam = sensor.camera or CameraConfig()
    cal_path = args.calibration or cam.calibration
    if cal_path is None:
        raise AtlasError(f"sensor {sensor.name}: no calibration (give --calibration or camera.calibration)")
    detector = Detector(
        sensor, world, load_calibration(cal_path), decimate=1.0 if args.image else 2.0, track=not args.image
    )
    if args.image:
        img = read_gray(Path(args.image))
        if img is None:
            raise AtlasError(f"--image: cannot read {args.image}")
        frames = [(img, int(time.time() * 1e6))]
    else:
        source = open_source(replace(cam, source=str(args.video or args.device)), fast=True)
        try:
            frames = ((f.gray, f.capture_time_us) for f in source.frames())
        except SourceError as exc:
            raise AtlasError(str(exc)) from None
    for k, (gray, stamp) in enumerate(frames):
        found = detector.detect(gray, stamp)
        for md in found:
            print(json.dumps(_as_dict(md, k)) if args.json else _as_line(md, k), flush=True)
        report = detector.report
        if not found or report.dropped:  # say why nothing, or not everything, was printed (JSON: on stderr)
            print(f"frame {k}: {report.explain()}", file=sys.stderr if args.json else sys.stdout, flush=True)
        if args.annotate and k == 0:
            write_annotated(Path(args.annotate), gray, found, detector)
        if args.frames and k + 1 >= args.frames:
            break
    return 0


def _as_dict(md: MarkerData, frame: int) -> dict[str, object]:
    return {
        "frame": frame, "sensor_id": md.sensor_id, "marker_id": md.marker_id, "sigma_m": md.sigma_m,
        "p_sensor_marker_m": list(md.p_sensor_marker_m), "q_sensor_marker_wxyz": list(md.q_sensor_marker_wxyz),
        "capture_time_us": md.capture_time_us, "reprojection_error_px": md.reprojection_error_px,
        "ambiguity_ratio": None if math.isnan(md.ambiguity_ratio) else md.ambiguity_ratio,
    }  # fmt: skip


def _as_line(md: MarkerData, frame: int) -> str:
    p = md.p_sensor_marker_m
    w, x, y, z = md.q_sensor_marker_wxyz
    return (
        f"frame {frame} marker {md.marker_id}: p [{p[0]:+.4f} {p[1]:+.4f} {p[2]:+.4f}] m"
        f" q_wxyz [{w:+.4f} {x:+.4f} {y:+.4f} {z:+.4f}] sigma {md.sigma_m * 1000:.1f} mm"
        f" reproj {md.reprojection_error_px:.2f} px"
    )


def _cmd_markers(args: argparse.Namespace) -> int:
    world = load_world(args.config)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise AtlasError(f"--out: cannot create {out}: {exc.strerror}") from None
    for m in sorted(world.markers.values(), key=lambda m: m.id):
        path = out / f"{m.family}-{m.id}.svg"
        path.write_text(marker_svg(m.family, m.id, m.size_m), encoding="utf-8")
        print(f"{path}: {m.family} id {m.id}, black square {m.size_m * 1000:g} mm ({m.entity})")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``detect`` and ``markers``."""
    p = sub.add_parser("detect", help="run the detector on an image, a video or a device and print MarkerData")
    p.add_argument("--config", required=True, type=Path, help="world file")
    p.add_argument("--sensor", required=True, help="sensor name or id")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--image", type=Path)
    src.add_argument("--video", type=Path)
    src.add_argument("--device", help="V4L2 index or path, or a stream URL")
    p.add_argument("--calibration", type=Path, help="calibration file (default: the sensor's camera.calibration)")
    p.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: all)")
    p.add_argument("--json", action="store_true", help="one JSON object a line")
    p.add_argument("--annotate", type=Path, help="write the first frame with markers and axes drawn")
    p.set_defaults(func=_cmd_detect)
    p = sub.add_parser("markers", help="one SVG per configured marker, at its exact printed size")
    p.add_argument("--config", required=True, type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.set_defaults(func=_cmd_markers)
