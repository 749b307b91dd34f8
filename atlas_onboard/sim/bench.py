"""The demo's drone standing still on a bench, for ``atlas-onboard preflight`` without hardware.

:func:`write_bench` renders the demo's downward camera over the demo's floor tags with the drone at
rest at a given attitude, and writes the world file, optionally with one of the frame mistakes
users make planted in it (the images stay those of the true setup):

- ``mount90``: the camera's mounting turned 90 deg about its optical axis;
- ``flu_as_frd``: the sensor pose written in FLU, the file declaring FRD;
- ``ned_as_enu``: the marker poses written in NED, the file declaring ENU.

``sim-autopilot`` takes the matching options (:func:`atlas_onboard.sim.demo.add_autopilot_options`): the attitude the
autopilot reports, its parameters (answered to PARAM_REQUEST_READ) and LOCAL_POSITION_NED.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from atlas_onboard.config import load_world
from atlas_onboard.core import frames, geometry
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import demo
from atlas_onboard.sim import trajectories as tj
from atlas_onboard.sim.scenario import Scenario

MISTAKES = ("mount90", "flu_as_frd", "ned_as_enu")
BENCH_POSITION_M = (0.03, -0.02, 0.9)  # ENU, above the tags
# On a bench the drone stands at rest; tilted a little, so that rotations about the vertical show.
BENCH_RPY_DEG = (4.0, -7.0, 20.0)  # roll, pitch, yaw; world ENU, body FLU
# A smaller, slower camera than the demo's (the same field of view): the check's figures do not need
# more, and the node keeps up with it on a loaded machine.
WIDTH_PX, HEIGHT_PX, FPS_HZ = 320, 240, 15


def _quat(R: Rotation) -> dict[str, float]:
    x, y, z, w = R.as_quat()
    return {"w": float(w), "x": float(x), "y": float(y), "z": float(z)}


def bench_world_doc(frames_dir: Path, autopilot_port: int, mistake: str | None = None) -> dict[str, Any]:
    """The demo's world file for the bench images in ``frames_dir``, with ``mistake`` planted (or none)."""
    if mistake is not None and mistake not in MISTAKES:
        raise AtlasError(f"unknown mistake {mistake!r}: expected one of {', '.join(MISTAKES)}")
    doc = demo.world_doc(frames_dir, autopilot_port)
    sensor = doc["entities"][demo.ENTITY]["sensors"][0]
    sensor["camera"].update(width_px=WIDTH_PX, height_px=HEIGHT_PX, fps=FPS_HZ)
    if mistake == "mount90":
        R_true = geometry.rotation_from_rpy_deg(sensor["pose"]["rpy_deg"])
        # The mount frame's x axis is the optical axis: turning about it is a right-multiplied Rx.
        R_file = R_true * Rotation.from_euler("x", 90, degrees=True)
        sensor["pose"] = {"pos": sensor["pose"]["pos"], "rot": _quat(R_file)}
    elif mistake == "flu_as_frd":
        doc["conventions"]["body"] = "FRD"  # the numbers stay the FLU ones
    elif mistake == "ned_as_enu":
        for m in doc["entities"]["world"]["markers"]:
            R_enu = geometry.rotation_from_rpy_deg(m["pose"]["rpy_deg"])
            p_enu = np.asarray(m["pose"]["pos"], dtype=float)
            p_ned = frames.R_ENU_NED.inv().apply(p_enu)
            m["pose"] = {"pos": [float(v) + 0.0 for v in p_ned], "rot": _quat(frames.R_ENU_NED.inv() * R_enu)}
    return doc


def write_bench_frames(frames_dir: Path, seconds: float, rpy_deg: tuple[float, float, float] = BENCH_RPY_DEG) -> Path:
    """Render ``seconds`` of the bench at the demo's frame rate into ``frames_dir`` and write the true world
    and calibration beside it; returns the calibration's path."""
    from atlas_onboard.sim.camera import FrameRenderer
    from atlas_onboard.sim.runner import write_calibration
    from atlas_onboard.sim.world import Intrinsics

    frames_dir.mkdir(parents=True, exist_ok=True)
    directory = frames_dir.parent
    calibration = directory / "calibration.yaml"
    write_calibration(calibration, Intrinsics.from_fov(WIDTH_PX, HEIGHT_PX, demo.OPTICS))
    truth_path = directory / ".bench-truth.yaml"
    truth_path.write_text(yaml.safe_dump(bench_world_doc(frames_dir, 14550), sort_keys=False))
    world = load_world(truth_path)
    scenario = Scenario(
        name="bench", description="the demo drone at rest", world_file="", duration_s=seconds,
        trajectories={demo.ENTITY: tj.Static(BENCH_POSITION_M, tuple(rpy_deg))}, drones=(demo.ENTITY,),
        scored=(demo.ENTITY,), optics={f"{demo.ENTITY}.{demo.SENSOR}": demo.OPTICS},
    )  # fmt: skip
    renderer = FrameRenderer(scenario, world, world.sensors[demo.SENSOR_ID], seed=2)
    for k in range(max(1, math.floor(seconds * FPS_HZ))):
        if not cv2.imwrite(str(frames_dir / demo.FRAME_PATTERN.format(k)), renderer(k)):
            raise AtlasError(f"{frames_dir}: cannot write image {k}")
    truth_path.unlink()
    return calibration


def write_bench(directory: Path, frames_dir: Path, autopilot_port: int, mistake: str | None = None) -> Path:
    """Write ``directory``/world.yaml for the bench images in ``frames_dir`` (calibration.yaml beside
    them), with ``mistake`` planted; returns its path."""
    directory.mkdir(parents=True, exist_ok=True)
    doc = bench_world_doc(frames_dir, autopilot_port, mistake)
    cal = (frames_dir.parent / "calibration.yaml").resolve()
    camera = doc["entities"][demo.ENTITY]["sensors"][0]["camera"]
    camera["calibration"] = str(cal)
    camera["replay"] = "realtime"  # as a live camera: a frame the detector had no time for is dropped
    path = directory / "world.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None), encoding="utf-8")
    return path
