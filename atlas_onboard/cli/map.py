"""``atlas-onboard record`` and ``atlas-onboard map``: record what a camera sees; build the marker map.

Both are thin layers over :mod:`atlas_onboard.recording.format`, :mod:`atlas_onboard.mapping.build` and
:mod:`atlas_onboard.mapping.output`. Nothing is written when the map cannot be built: the world file
and the report are written to temporary files and renamed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from dataclasses import replace
from pathlib import Path

from atlas_onboard.config import CameraConfig, ConfigError, load_world
from atlas_onboard.errors import AtlasError
from atlas_onboard.fsio import write_atomic
from atlas_onboard.mapping import motion
from atlas_onboard.mapping.build import MapOptions, build_map
from atlas_onboard.mapping.observations import collect
from atlas_onboard.mapping.output import plot_map, report_json, report_text, world_text


def _atomic_write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory (renamed at the end)."""
    try:
        write_atomic(Path(path), text)
    except OSError as exc:
        raise AtlasError(f"{path}: cannot write: {exc.strerror}") from None


def _cmd_map(args: argparse.Namespace) -> int:
    world = load_world(args.config)
    if args.gravity_anchor is not None and args.anchor:
        raise AtlasError("--gravity-anchor: give either surveyed anchors (--anchor) or one gravity anchor, not both")
    for p in args.inputs:
        if not Path(p).exists():
            raise AtlasError(f"{p}: no such file or directory")
    if args.stride < 1:
        raise AtlasError(f"--stride: expected a positive number of frames, got {args.stride}")
    out_dir = Path(args.out).parent
    if not out_dir.is_dir():
        raise AtlasError(f"--out: {out_dir} is not a directory")
    say = (lambda m: print(f"atlas-onboard map: {m}", file=sys.stderr)) if args.verbose_progress else None
    if args.decimate not in (1.0, 2.0):
        raise AtlasError(f"--decimate: expected 1 (full resolution) or 2 (the node's), got {args.decimate:g}")
    obs = collect(list(args.inputs), world, args.calibration, args.fps, args.stride, say, args.decimate)
    corrected = motion.correct(obs)  # a rolling shutter's rows to their frames' stamps, where attitudes allow
    if say and corrected:
        say(f"{corrected} detections' rolling-shutter rows moved to their frames' stamps")
    options = MapOptions(
        anchors=tuple(args.anchor or ()), anchor_sigma_m=args.anchor_sigma_mm / 1000.0,
        anchor_sigma_deg=args.anchor_sigma_deg, gravity_anchor=args.gravity_anchor,
        loss_scale_px=args.loss_scale_px, min_frames=args.min_frames,
    )  # fmt: skip
    result = build_map(obs, world, options)
    anchors = f"gravity anchor {args.gravity_anchor}" if args.gravity_anchor is not None else (
        "anchors " + ", ".join(map(str, options.anchors)))  # fmt: skip
    header = (
        "Markers of the world entity mapped by atlas-onboard map on "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
        f"\nfrom {', '.join(str(p) for p in args.inputs)} ({anchors})"
    )
    fixed = args.gravity_anchor is None and (args.anchor_sigma_mm <= 0 or args.anchor_sigma_deg <= 0)
    text = world_text(world, result, header, keep_anchors=fixed)
    report = report_text(result)
    if args.report is not None:
        try:
            Path(args.report).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise AtlasError(f"--report: cannot create {args.report}: {exc.strerror}") from None
        _atomic_write(Path(args.report) / "report.json", report_json(result))
        _atomic_write(Path(args.report) / "report.txt", report + "\n")
        if not args.no_plot:
            plot_map(Path(args.report) / "map.png", result)
    # The world file last: it is what a user flies on, and it must be whole.
    tmp = Path(args.out).with_name(f".{Path(args.out).name}.check")
    try:
        tmp.write_text(text, encoding="utf-8")
        load_world(tmp)
    except ConfigError as exc:
        raise AtlasError(f"the mapped world file does not load ({exc}); nothing written") from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    _atomic_write(Path(args.out), text)
    print(report)
    print(f"wrote {args.out}" + (f" and the report in {args.report}" if args.report is not None else ""))
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from atlas_onboard.detector.calibration import load as load_calibration
    from atlas_onboard.detector.pipeline import Detector
    from atlas_onboard.detector.sources import SourceError, open_source
    from atlas_onboard.recording.format import BackgroundRecorder, RecordingWriter, disk_free_bytes

    world = load_world(args.config)
    sensor = next((s for s in world.sensors.values() if args.sensor in (s.name, str(s.id))), None)
    if sensor is None:
        names = ", ".join(f"{s.entity}.{s.name}" for s in world.sensors.values()) or "none"
        raise AtlasError(f"--sensor: no sensor {args.sensor!r} in {args.config} (there are: {names})")
    cam = sensor.camera or CameraConfig()
    if args.source is not None:
        cam = replace(cam, source=str(args.source))
    if not cam.source or cam.source == "sim":
        raise AtlasError(f"sensor {sensor.name}: no camera source to record (give --source)")
    cal_path = args.calibration or cam.calibration
    if cal_path is None:
        raise AtlasError(f"sensor {sensor.name}: no calibration (give --calibration or camera.calibration)")
    cal = load_calibration(cal_path)
    if args.max_mb <= 0:
        raise AtlasError(f"--max-mb: expected a positive size, got {args.max_mb:g}")
    out = Path(args.out)
    parent = out.parent if not out.exists() else out
    if parent.is_dir() and disk_free_bytes(parent) < args.max_mb * 1e6:
        print(
            f"atlas-onboard record: warning: {disk_free_bytes(parent) / 1e6:.0f} MB free, less than --max-mb",
            file=sys.stderr,
        )
    p, q = sensor.T_entity_sensor.translation, sensor.T_entity_sensor.rotation.as_quat()
    writer = RecordingWriter(
        out, cal, sensor_name=sensor.name, sensor_id=sensor.id, entity=sensor.entity,
        p_body_camera_m=tuple(float(v) for v in p), q_body_camera_wxyz=(q[3], q[0], q[1], q[2]),  # type: ignore[arg-type]
        max_bytes=int(args.max_mb * 1e6), image_format="jpg" if args.jpeg else "png",
    )  # fmt: skip
    recorder = BackgroundRecorder(writer)
    detector = Detector(sensor, world, cal, decimate=2.0)
    try:
        source = open_source(cam, fast=True)
    except SourceError as exc:
        recorder.close()
        raise AtlasError(str(exc)) from None
    t0 = time.monotonic()
    n = 0
    try:
        for frame in source.frames():
            found = detector.detect(frame.gray, frame.capture_time_us)
            recorder.offer(frame.gray, frame.capture_time_us, found, None)
            n += 1
            if recorder.error is not None or writer.frames_dropped:
                break
            if (args.frames and n >= args.frames) or (args.duration and time.monotonic() - t0 >= args.duration):
                break
    except SourceError as exc:
        print(f"atlas-onboard record: {exc}", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        source.close()
        recorder.close()
    stop = "" if not writer.frames_dropped else f"; stopped at --max-mb {args.max_mb:g}"
    print(
        f"wrote {writer.frames_written} frames ({writer.bytes_written / 1e6:.1f} MB) to {out};"
        f" {recorder.dropped_queue_full} dropped (disk slower than the camera){stop}"
    )
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``record`` and ``map``."""
    p = sub.add_parser("record", help="record what a camera sees (frames, stamps, MarkerData) for `map`")
    p.add_argument("--config", required=True, type=Path, help="world file")
    p.add_argument("--sensor", required=True, help="sensor name or id (its camera source and calibration)")
    p.add_argument("--source", help="camera source instead of the sensor's (device, video, image folder, URL)")
    p.add_argument("--calibration", type=Path, help="calibration file (default: the sensor's camera.calibration)")
    p.add_argument("--out", required=True, type=Path, help="new directory for the recording")
    p.add_argument("--max-mb", type=float, default=2000.0, help="stop recording at this size (MB, default 2000)")
    p.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: no limit)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: no limit)")
    p.add_argument("--jpeg", action="store_true", help="JPEG frames (quality 95) instead of lossless PNG")
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser(
        "map", help="build the marker map from recordings, videos or image folders (bundle adjustment)",
        description="Solve the poses of the world file's world markers from every corner seen, anchored on"
        " surveyed markers (--anchor) or on one marker and gravity (--gravity-anchor), and write the world file"
        " with the mapped poses and their 1-sigma, and a report.",
    )  # fmt: skip
    p.add_argument("inputs", nargs="+", type=Path, help="recordings, videos or image folders")
    p.add_argument("--config", required=True, type=Path, help="world file: marker ids, sizes, families, anchors")
    p.add_argument("--out", required=True, type=Path, help="the world file to write, with the mapped markers")
    p.add_argument("--anchor", type=int, action="append", help="id of a surveyed marker (its pose in --config)")
    p.add_argument("--anchor-sigma-mm", type=float, default=0.0, help="the survey's 1-sigma (0: anchors fixed)")
    p.add_argument("--anchor-sigma-deg", type=float, default=0.0, help="the survey's 1-sigma in rotation")
    p.add_argument("--gravity-anchor", type=int, help="this marker defines the world frame; up from the attitude")
    p.add_argument("--calibration", type=Path, help="calibration of videos and image folders")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of image folders (stamps), default 30")
    p.add_argument("--stride", type=int, default=1, help="use every n-th frame (default 1)")
    p.add_argument(
        "--decimate", type=float, default=1.0,
        help="1 (default): every frame whole at full resolution; 2: search as the node does, tracking markers"
        " from frame to frame (cheaper only with few markers in view; consecutive frames)",
    )  # fmt: skip
    p.add_argument("--loss-scale-px", type=float, default=1.0, help="robust loss scale, pixels (default 1)")
    p.add_argument("--min-frames", type=int, default=5, help="markers seen with another in fewer frames are left out")
    p.add_argument("--report", type=Path, help="directory for report.json, report.txt and map.png")
    p.add_argument("--no-plot", action="store_true", help="no map.png")
    p.add_argument("--progress", dest="verbose_progress", action="store_true", help="say what is being read")
    p.set_defaults(func=_cmd_map)
