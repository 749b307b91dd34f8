"""``atlas-onboard record`` and ``atlas-onboard map``: record what a camera sees; build the marker map.

Both are thin layers over :mod:`atlas_onboard.recording.format` and :mod:`atlas_onboard.mapping.build`.
Nothing is written when the map cannot be built: the world file and the report are written to
temporary files and renamed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import WORLD, CameraConfig, ConfigError, WorldConfig, load_world
from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError
from atlas_onboard.fsio import write_atomic
from atlas_onboard.mapping import motion
from atlas_onboard.mapping.build import MapOptions, MapResult, build_map
from atlas_onboard.mapping.observations import collect
from atlas_onboard.mapping.report import MarkerReport

PLACEHOLDER = "__atlas_mapped_markers__"


def _atomic_write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory (renamed at the end)."""
    try:
        write_atomic(Path(path), text)
    except OSError as exc:
        raise AtlasError(f"{path}: cannot write: {exc.strerror}") from None


def _fmt(v: float, digits: int) -> str:
    return f"{v:.{digits}f}".rstrip("0").rstrip(".") if v != 0 else "0"


def world_text(world: WorldConfig, result: MapResult, header: str, keep_anchors: bool = True) -> str:
    """The world file ``world`` was read from, with its world markers' poses replaced by the map's
    (in the file's own convention), each with its 1-sigma and fit as a comment. ``keep_anchors``: the
    anchors keep their surveyed poses (fixed anchors); otherwise they get the adjusted ones."""
    assert world.source is not None
    doc = yaml.safe_load(Path(world.source).read_text(encoding="utf-8"))
    raw_markers = (doc["entities"].get(WORLD) or {}).get("markers") or []
    mapped = result.mapped()
    lines = []
    for raw in raw_markers:
        mid = int(raw["id"])
        rep = result.markers.get(mid)
        entry: dict[str, Any] = {k: raw[k] for k in ("id", "size_m", "family") if k in raw}
        if mid in mapped and rep is not None and not (keep_anchors and rep.status == "anchor"):
            T = RigidTransform.from_matrix(mapped[mid])
            if world.world_convention is frames.WorldConvention.NED:
                T = frames.T_ENU_NED * T  # ENU -> NED (the rotation is its own inverse)
            p = T.translation
            x, y, z, w = T.rotation.as_quat()
            if w < 0:
                x, y, z, w = -x, -y, -z, -w
            pose = (
                f"{{pos: [{_fmt(p[0], 5)}, {_fmt(p[1], 5)}, {_fmt(p[2], 5)}],"
                f" rot: {{w: {w:.8f}, x: {x:.8f}, y: {y:.8f}, z: {z:.8f}}}}}"
            )
            sm = ", ".join(f"{v * 1000:.2f}" for v in rep.sigma_m or ())
            sd = ", ".join(f"{v:.3f}" for v in rep.sigma_deg or ())
            note = (
                f"# {rep.status}: 1-sigma position [{sm}] mm, rotation [{sd}] deg (world axes); {rep.frames} frames"
                + (f", rms {rep.rms_px:.2f} px" if math.isfinite(rep.rms_px) else "")
            )
        else:
            pose = yaml.safe_dump(raw["pose"], default_flow_style=True, width=1000).strip()
            status = rep.status if rep is not None else "not_seen"
            note = f"# {status}: pose as surveyed" if status == "anchor" else f"# {status}: pose kept from the input"
            if rep is not None and rep.detail:
                note += f" ({rep.detail})"
        inner = ", ".join(f"{k}: {v}" for k, v in entry.items())
        lines.append(f"- {{{inner}, pose: {pose}}}  {note}")
    doc["entities"].setdefault(WORLD, {})
    if doc["entities"][WORLD] is None:
        doc["entities"][WORLD] = {}
    doc["entities"][WORLD]["markers"] = PLACEHOLDER
    text = yaml.safe_dump(doc, sort_keys=False, width=1000)
    out = []
    for line in text.splitlines():
        if line.strip() == f"markers: {PLACEHOLDER}":
            indent = line[: len(line) - len(line.lstrip())]
            out.append(f"{indent}markers:")
            out += [f"{indent}  {entry}" for entry in lines]
        else:
            out.append(line)
    return "".join(f"# {h}\n" for h in header.splitlines()) + "\n".join(out) + "\n"


def refined_world_text(world: WorldConfig, markers: dict[int, MarkerReport], header: str) -> str:
    """:func:`world_text` for a map refined live (``run`` with ``refine``): ``markers`` says of each world
    marker whether it was refined (its pose, 1-sigma and views as frames), kept or an anchor."""
    result = MapResult(markers, np.zeros(0), [], None, math.nan, {}, {}, 0, 0, 0)
    return world_text(world, result, header, keep_anchors=True)


def report_text(result: MapResult) -> str:
    """The map's report as a person reads it."""
    t = result.timings_s
    out = [
        f"map: {result.frames_read} frames read, {result.frames_used} adjusted, {result.observations} marker sightings;"
        f" residual sigma {result.sigma0_px:.3f} px",
        "time: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in t.items()),
        f"{'marker':>6} {'status':<11} {'frames':>6} {'rms_px':>6} {'sigma_mm (x y z)':>22} {'sigma_deg (x y z)':>21}"
        f" {'views_deg':>9}  detail",
    ]
    for mid in sorted(result.markers):
        r = result.markers[mid]
        sm = " ".join(f"{v * 1000:6.2f}" for v in r.sigma_m) if r.sigma_m else "-"
        sd = " ".join(f"{v:6.3f}" for v in r.sigma_deg) if r.sigma_deg else "-"
        rms = f"{r.rms_px:6.2f}" if math.isfinite(r.rms_px) else "-"
        spread = f"{r.view_spread_deg:9.0f}" if math.isfinite(r.view_spread_deg) else "-"
        out.append(f"{mid:>6} {r.status:<11} {r.frames:>6} {rms:>6} {sm:>22} {sd:>21} {spread:>9}  {r.detail}")
    if len(result.frame_rms_px):
        worst = np.argsort(result.frame_rms_px)[::-1][:5]
        out.append(
            "images with the largest reprojection RMS: "
            + ", ".join(f"{result.frame_names[k]} {result.frame_rms_px[k]:.2f} px" for k in worst)
        )
    if result.unknown_ids:
        out.append("ids seen that the world file does not list: " + ", ".join(map(str, sorted(result.unknown_ids))))
    bad = [r for r in result.markers.values() if r.status in ("moved", "duplicated", "wrong_size")]
    for r in bad:
        out.append(f"marker {r.id} does not fit ({r.status}): {r.detail}; left out of the map")
    unanchored = sorted(r.id for r in result.markers.values() if r.status == "unanchored")
    if unanchored:
        out.append(
            f"markers {', '.join(map(str, unanchored))} not mapped: their groups have no anchor"
            " (give one of each group as --anchor, or fly between the groups)"
        )
    return "\n".join(out)


def report_json(result: MapResult) -> str:
    def marker(r: Any) -> dict[str, Any]:
        return {
            "id": r.id, "status": r.status, "size_m": r.size_m, "frames": r.frames,
            "rms_px": r.rms_px if math.isfinite(r.rms_px) else None,
            "sigma_m": list(r.sigma_m) if r.sigma_m else None, "sigma_deg": list(r.sigma_deg) if r.sigma_deg else None,
            "view_spread_deg": r.view_spread_deg if math.isfinite(r.view_spread_deg) else None,
            "T_world_marker": r.M_world_marker.tolist() if r.M_world_marker is not None else None, "detail": r.detail,
        }  # fmt: skip

    doc = {
        "frames_read": result.frames_read, "frames_used": result.frames_used, "observations": result.observations,
        "sigma0_px": result.sigma0_px, "timings_s": result.timings_s,
        "markers": [marker(result.markers[m]) for m in sorted(result.markers)],
        "images": [
            {"image": n, "rms_px": float(v)} for n, v in zip(result.frame_names, result.frame_rms_px, strict=True)
        ],
        "unknown_ids": {str(k): v for k, v in result.unknown_ids.items()},
    }  # fmt: skip
    return json.dumps(doc, indent=1)


def plot_map(path: Path, result: MapResult) -> bool:
    """A top view and a side view of the map (matplotlib, only when installed); False without it."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    colours = {"anchor": "tab:red", "mapped": "tab:blue", "degenerate": "tab:orange"}
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    sol = result.solution
    cams = np.array([np.linalg.inv(M)[:3, 3] for M in sol.M_cam_world]) if sol is not None else np.zeros((0, 3))
    for ax, (i, j, name) in zip(axes, ((0, 1, "top view (x, y)"), (0, 2, "side view (x, z)")), strict=True):
        if len(cams):
            ax.plot(cams[:, i], cams[:, j], ".", ms=2, color="0.7", label="camera")
        for r in result.markers.values():
            if r.M_world_marker is None:
                continue
            p = r.M_world_marker[:3, 3]
            ax.plot(p[i], p[j], "s", color=colours.get(r.status, "k"))
            ax.annotate(str(r.id), (p[i], p[j]), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle("marker map: red anchors, blue mapped, orange degenerate views")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


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
