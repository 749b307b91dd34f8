"""A first run without hardware: ``atlas-onboard demo DIR`` and ``atlas-onboard sim-autopilot``.

``demo`` writes a complete world file for one drone hovering over a few floor tags, the drone's
camera calibration, and the images its downward camera takes (rendered by the simulator's
:class:`~atlas_onboard.sim.camera.FrameRenderer`) as an image folder, plus the ground truth of the
hover. ``atlas-onboard run`` then reads that folder as it would a camera and sends its pose to the
autopilot URL, where ``sim-autopilot`` (the simulator's :class:`SimAutopilot`) prints what arrives.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from atlas_onboard.config import load_world
from atlas_onboard.core import geometry
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import trajectories as tj
from atlas_onboard.sim.lander import Lander, LanderSettings
from atlas_onboard.sim.scenario import Optics, Scenario

if TYPE_CHECKING:
    from atlas_onboard.sim.autopilot import Received, SimAutopilot

ENTITY = "drone"
SENSOR = "down"
SENSOR_ID = 1
SYSTEM_ID = 1
WIDTH_PX, HEIGHT_PX, FPS_HZ = 640, 480, 20
HOVER_HEIGHT_M = 1.0
# Floor tags (tag36h11, 16 cm): id, x, y, yaw deg. All of them fit in the view from the hover.
TAGS = ((0, 0.0, 0.0, 0.0), (1, 0.25, 0.4, 10.0), (2, -0.25, 0.4, -5.0), (3, -0.25, -0.4, 0.0), (4, 0.25, -0.4, 20.0))
# Five more between them, for a view of ten (the detector's cost per marker in view).
MORE_TAGS = (
    (5, 0.0, 0.4, 5.0),
    (6, 0.0, -0.4, -10.0),
    (7, 0.25, 0.0, 15.0),
    (8, -0.25, 0.0, -15.0),
    (9, 0.0, 0.2, 30.0),
)
TAG_SIZE_M = 0.16
OPTICS = Optics(hfov_deg=70.0, distortion=(-0.05, 0.01, 0.0, 0.0, 0.0))
FRAME_PATTERN = "frame-{:05d}.png"  # no 10-digit number: the image folder stamps frames at the camera's fps

WORLD_HEADER = """\
# The demo world written by `atlas-onboard demo`: {n_tags} AprilTags (tag36h11, {tag_cm:g} cm) on the floor and
# one drone `{entity}` hovering {height_m:g} m above them with a downward camera. The camera's source is the
# folder of images the simulator rendered for that hover ({seconds:g} s at {fps} Hz, played once in real time);
# truth.tum beside this file is the hover's ground truth (TUM: t_s x y z qx qy qz qw, ENU/FLU, t from
# the first image). The node sends its pose to the autopilot URL below: `atlas-onboard sim-autopilot
# --port {port}` listens there. A real drone's world file looks the same with `source: /dev/video0`.
"""


def demo_scenario(seconds: float) -> Scenario:
    """The demo's hover: a slow 8 cm circle at 1 m, a gentle yaw sway and a small controller wobble."""
    drone = tj.Quadrotor(
        path=tj.circle((0.03, -0.02, HOVER_HEIGHT_M), 0.08, 12.0),
        yaw=tj.slow_yaw(5.0, 8.0, 15.0),
        oscillation=tj.Oscillation((0.01, 0.01, 0.005), 0.7, 0.3, seed=3),
    )
    return Scenario(
        name="demo",
        description="one drone hovering over five floor tags",
        world_file="",  # the world is the file demo writes
        duration_s=seconds,
        trajectories={ENTITY: drone},
        drones=(ENTITY,),
        scored=(ENTITY,),
        optics={f"{ENTITY}.{SENSOR}": OPTICS},
    )


def floor_tags(n_tags: int) -> tuple[tuple[int, float, float, float], ...]:
    """The first ``n_tags`` (1-10) floor tags: id, x m, y m, yaw deg; all in view from the hover."""
    return (TAGS + MORE_TAGS)[:n_tags]


def world_doc(frames_dir: Path, autopilot_port: int, n_tags: int = len(TAGS)) -> dict[str, Any]:
    """The demo's world file as a YAML document (the calibration file name is relative to it)."""
    markers = [
        {"id": i, "size_m": TAG_SIZE_M, "pose": {"pos": [x, y, 0.0], "rpy_deg": [0, 0, yaw]}}
        for i, x, y, yaw in floor_tags(n_tags)
    ]
    camera = {
        "source": str(frames_dir),
        "calibration": "calibration.yaml",
        "width_px": WIDTH_PX,
        "height_px": HEIGHT_PX,
        "fps": FPS_HZ,
    }
    sensor = {"name": SENSOR, "id": SENSOR_ID, "pose": {"pos": [0.0, 0.0, -0.03], "rpy_deg": [0, 90, 0]}}
    return {
        "version": 1,
        "conventions": {"world": "ENU", "body": "FLU"},
        "marker_family": "tag36h11",
        "entities": {"world": {"markers": markers}, ENTITY: {"sensors": [{**sensor, "camera": camera}]}},
        "nodes": {
            ENTITY: {
                "system_id": SYSTEM_ID,
                "autopilot": {"url": f"udpout:127.0.0.1:{autopilot_port}"},
                "status_interval_s": 5,
            }
        },
    }


def _prepare_dir(directory: Path, force: bool) -> Path:
    if directory.exists() and not directory.is_dir():
        raise AtlasError(f"{directory}: exists and is not a directory")
    if directory.is_dir() and any(directory.iterdir()):
        if not force:
            raise AtlasError(f"{directory}: directory is not empty (use --force to write the demo into it)")
    frames_dir = directory / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    for old in frames_dir.glob("frame-*.png"):  # a longer earlier demo's images would be played too
        old.unlink()
    return frames_dir


def write_demo(
    directory: Path, seconds: float = 20.0, autopilot_port: int = 14550, force: bool = False, n_tags: int = len(TAGS)
) -> Path:
    """Write the demo into ``directory``: world.yaml, calibration.yaml, frames/ and truth.tum, with ``n_tags``
    (1-10) floor tags in view.

    Returns the path of the world file. Raises :class:`AtlasError` for a non-empty directory
    without ``force``, for arguments out of range and for a directory it cannot write."""
    if not (math.isfinite(seconds) and 0 < seconds <= 600):
        raise AtlasError(f"--seconds: expected 0 < seconds <= 600, got {seconds:g}")
    if not 1 <= autopilot_port <= 65535:
        raise AtlasError(f"--autopilot-port: expected a UDP port 1..65535, got {autopilot_port}")
    if not 1 <= n_tags <= len(TAGS) + len(MORE_TAGS):
        raise AtlasError(f"expected 1 to {len(TAGS) + len(MORE_TAGS)} demo tags, got {n_tags}")
    directory = directory.resolve()
    try:
        return _write(directory, _prepare_dir(directory, force), seconds, autopilot_port, n_tags)
    except OSError as exc:
        raise AtlasError(f"{directory}: cannot write the demo ({exc.strerror or exc})") from exc


def _write(directory: Path, frames_dir: Path, seconds: float, autopilot_port: int, n_tags: int) -> Path:
    from atlas_onboard.sim.camera import FrameRenderer
    from atlas_onboard.sim.runner import write_calibration
    from atlas_onboard.sim.world import Intrinsics

    write_calibration(directory / "calibration.yaml", Intrinsics.from_fov(WIDTH_PX, HEIGHT_PX, OPTICS))
    header = WORLD_HEADER.format(
        n_tags=n_tags, tag_cm=TAG_SIZE_M * 100, entity=ENTITY, height_m=HOVER_HEIGHT_M, seconds=seconds,
        fps=FPS_HZ, port=autopilot_port,
    )  # fmt: skip
    world_path = directory / "world.yaml"
    world_path.write_text(
        header
        + yaml.safe_dump(world_doc(frames_dir, autopilot_port, n_tags), sort_keys=False, default_flow_style=None),
        encoding="utf-8",
    )
    world = load_world(world_path)  # the file a user will run: it must load as written
    scenario = demo_scenario(seconds)
    renderer = FrameRenderer(scenario, world, world.sensors[SENSOR_ID], seed=1)
    n = max(1, math.floor(seconds * FPS_HZ))
    t_s = np.arange(n) / FPS_HZ
    for k in range(n):
        if not cv2.imwrite(str(frames_dir / FRAME_PATTERN.format(k)), renderer(k)):
            raise AtlasError(f"{frames_dir}: cannot write image {k}")
    p, q = scenario.trajectories[ENTITY].pose(t_s)
    lines = [" ".join(f"{v:.6f}" for v in (t, *pk, *qk)) for t, pk, qk in zip(t_s, p, q, strict=True)]
    (directory / "truth.tum").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return world_path


def read_truth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A TUM file: times (N,) s, positions (N, 3) m and quaternions xyzw (N, 4)."""
    data = np.loadtxt(path, ndmin=2)
    return data[:, 0], data[:, 1:4], data[:, 4:8]


def _cmd_demo(args: argparse.Namespace) -> int:
    t0 = time.monotonic()
    world_path = write_demo(args.dir, args.seconds, args.autopilot_port, args.force)
    n = max(1, math.floor(args.seconds * FPS_HZ))
    elapsed_s = time.monotonic() - t0
    print(f"wrote {world_path}, its camera calibration, {n} camera images and truth.tum in {elapsed_s:.0f} s")
    print(f"next, in two terminals (the images play once, {args.seconds:g} s in real time; Ctrl-C ends each):")
    print(f"  atlas-onboard sim-autopilot --port {args.autopilot_port}")
    print(f"  atlas-onboard run --config {world_path} --entity {ENTITY}")
    return 0


def _sigmas_mm(covariance: tuple[float, ...]) -> str:
    """Position sigmas x/y/z in mm of a MAVLink upper-triangle covariance (variances at 0, 6, 11)."""
    var = [covariance[i] for i in (0, 6, 11)] if len(covariance) == 21 else []
    if not var or not all(math.isfinite(v) and v >= 0 for v in var):
        return "sigma unknown"
    return "sigma " + "/".join(f"{1000 * math.sqrt(v):.1f}" for v in var) + " mm"


def autopilot_line(elapsed_s: float, new: list[Received], heartbeats: int) -> str:
    """One status line of the simulated autopilot: the poses and heartbeats received in the last second."""
    head = f"{elapsed_s:4.0f} s  heartbeats {heartbeats}/s  poses {len(new):3d}/s"
    if not new:
        return head + "  (no pose)"
    r = new[-1]
    x, y, z = r.xyz_m
    if r.rpy_rad is not None:
        roll, pitch, yaw = (math.degrees(a) for a in r.rpy_rad)
    else:
        w, qx, qy, qz = r.q_wxyz or (1.0, 0.0, 0.0, 0.0)
        yaw, pitch, roll = Rotation.from_quat([qx, qy, qz, w]).as_euler("ZYX", degrees=True)
    return (
        f"{head}  NED x {x:+.3f} y {y:+.3f} z {z:+.3f} m  roll {roll:+.1f} pitch {pitch:+.1f} yaw {yaw:+.1f} deg"
        f"  {_sigmas_mm(r.covariance)}  reset_counter {r.reset_counter}"
    )


def run_sim_autopilot(
    port: int, seconds: float | None, out: TextIO = sys.stdout, bench: dict[str, Any] | None = None
) -> int:
    """Listen on 127.0.0.1:``port`` as a flight controller would and print once a second what arrived.

    ``bench``: further :class:`SimAutopilot` settings (parameters, a static attitude, LOCAL_POSITION_NED)."""
    from atlas_onboard.sim.autopilot import SimAutopilot

    if not 1 <= port <= 65535:
        raise AtlasError(f"--port: expected a UDP port 1..65535, got {port}")
    try:
        autopilot = SimAutopilot(system_id=SYSTEM_ID, port=port, **(bench or {}))
    except OSError as exc:
        raise AtlasError(f"127.0.0.1:{port}: cannot listen ({exc.strerror})") from exc
    autopilot.start()
    print(f"simulated autopilot (system id {SYSTEM_ID}) listening on udp 127.0.0.1:{port}; Ctrl-C ends", file=out)
    out.flush()
    t0 = time.monotonic()
    seen = heartbeats_seen = 0
    try:
        k = 1
        while seconds is None or k <= seconds:
            time.sleep(max(t0 + k - time.monotonic(), 0.0))
            records = autopilot.snapshot()
            heartbeats = sum(autopilot.heartbeats_from.values())
            print(autopilot_line(k, records[seen:], heartbeats - heartbeats_seen), file=out)
            if autopilot.lander is not None:
                print(landing_line(autopilot), file=out)
            out.flush()
            seen, heartbeats_seen = len(records), heartbeats
            k += 1
    finally:
        autopilot.stop()
    return 0


def landing_line(autopilot: SimAutopilot) -> str:
    """What the simulated vehicle makes of the LANDING_TARGETs received: how many, its phase, the target."""
    lander = autopilot.lander
    if lander is None:
        return ""
    where = "none" if lander.target_m is None else "ENU ({:.3f}, {:.3f}, {:.3f}) m".format(*lander.target_m)
    return (f"  landing: {len(autopilot.landing_targets)} LANDING_TARGET ({lander.refused} in another form),"
            f" {lander.phase.value}, target {where}, vehicle at {lander.p_m[2]:.2f} m")  # fmt: skip


def _cmd_sim_autopilot(args: argparse.Namespace) -> int:
    return run_sim_autopilot(args.port, args.seconds, bench=autopilot_settings(args))


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``demo`` and ``sim-autopilot``."""
    p = sub.add_parser(
        "demo",
        help="write a demo world file and rendered camera images for `run`, no hardware needed",
        description="Write DIR/world.yaml (one drone hovering over five floor tags), its camera calibration,"
        " the images of its downward camera rendered by the simulator (DIR/frames) and the ground truth"
        " (DIR/truth.tum), then print the two commands that run the node against a simulated autopilot.",
    )
    p.add_argument("dir", type=Path, help="directory to write (created; must be empty unless --force)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of the hover, s (default 20)")
    p.add_argument("--autopilot-port", type=int, default=14550, help="UDP port of the autopilot (default 14550)")
    p.add_argument("--force", action="store_true", help="write into a non-empty directory")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "sim-autopilot",
        help="a simulated flight controller that prints the poses it receives",
        description="Listen on 127.0.0.1:PORT as a flight controller (HEARTBEAT, TIMESYNC) and print once a"
        " second the external-vision messages received: rate, latest position (NED) and attitude, position"
        " sigmas from the covariance, reset_counter.",
    )
    p.add_argument("--port", type=int, default=14550, help="UDP port to listen on (default 14550)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    add_autopilot_options(p)
    p.set_defaults(func=_cmd_sim_autopilot)


MAV_AUTOPILOT_PX4, MAV_AUTOPILOT_ARDUPILOTMEGA = 12, 3  # MAVLink's MAV_AUTOPILOT values


def add_autopilot_options(p: argparse.ArgumentParser) -> None:
    """``sim-autopilot``'s bench options."""
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4", help="which one to imitate")
    p.add_argument(
        "--param", action="append", default=[], metavar="NAME=VALUE",
        help="a parameter answered to PARAM_REQUEST_READ (repeatable), e.g. EKF2_EV_DELAY=200",
    )  # fmt: skip
    p.add_argument(
        "--attitude-rpy-deg", type=float, nargs=3, metavar=("ROLL", "PITCH", "YAW"),
        help="stream ATTITUDE of a drone at rest at this attitude (world ENU, body FLU, deg)",
    )  # fmt: skip
    p.add_argument("--timesync-hz", type=float, default=0.0, help="send TIMESYNC requests at this rate (PX4: 10 Hz)")
    p.add_argument(
        "--land", action="store_true",
        help="fly on LANDING_TARGET (in --autopilot's form) as a simulated vehicle and print what it does",
    )  # fmt: skip
    p.add_argument(
        "--local-position-hz", type=float, default=0.0,
        help="stream LOCAL_POSITION_NED (the last vision position received) at this rate",
    )  # fmt: skip


def autopilot_settings(args: argparse.Namespace) -> dict[str, Any]:
    """:class:`SimAutopilot` keyword arguments from :func:`add_autopilot_options`'s options."""
    params: dict[str, float] = {}
    for item in args.param:
        name, _, value = item.partition("=")
        try:
            params[name.strip()] = float(value)
        except ValueError:
            raise AtlasError(f"--param: expected NAME=VALUE with a number, got {item!r}") from None
    out: dict[str, Any] = {
        "params": params,
        "local_position_hz": args.local_position_hz,
        "timesync_hz": args.timesync_hz,
        "autopilot_type": MAV_AUTOPILOT_PX4 if args.autopilot == "px4" else MAV_AUTOPILOT_ARDUPILOTMEGA,
    }
    if args.land:
        out["lander"] = Lander(LanderSettings(args.autopilot), np.zeros(3))
    if args.attitude_rpy_deg is not None:
        R = geometry.rotation_from_rpy_deg(args.attitude_rpy_deg)
        out["attitude"] = lambda _t: R
    return out
