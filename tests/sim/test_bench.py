"""The bench of ``atlas-onboard preflight`` scored offline: the bench frames through the node's own
detector, listener and graph, each pose judged with the autopilot's attitude by the service's start-up
check (:class:`~atlas_onboard.service.startup_check.StartupCheck`, the attitude check preflight runs
too). The right setup passes and each frame mistake planted in the world file is named. End to end
(processes, the relay, MAVLink) in ``tests/e2e/test_preflight.py``."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest

from atlas_onboard.config import load_world
from atlas_onboard.core.geometry import rotation_from_rpy_deg
from atlas_onboard.core.records import AutopilotPose
from atlas_onboard.detector.calibration import load as load_calibration
from atlas_onboard.detector.workers import CameraDetectorSpec
from atlas_onboard.listener import Listener
from atlas_onboard.node.setup import make_graph
from atlas_onboard.preflight.checks import Check, Verdict
from atlas_onboard.service.run import DECIMATE
from atlas_onboard.service.startup_check import StartupCheck
from atlas_onboard.sim import demo
from atlas_onboard.sim.bench import BENCH_RPY_DEG, FPS_HZ, write_bench, write_bench_frames

WINDOW_S = 3.0  # of poses judged (preflight's end-to-end test judges 4 s; the service 10 s)


@pytest.fixture(scope="module")
def frames_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    frames = tmp_path_factory.mktemp("bench") / "frames"
    write_bench_frames(frames, seconds=WINDOW_S + 1.0)
    return frames


def _judged(tmp: Path, frames: Path, mistake: str | None) -> list[Check]:
    """The start-up check's verdicts on the poses the node's pipeline gives for the bench frames under
    the world file with ``mistake`` planted, the autopilot reporting the bench's true attitude."""
    world = load_world(write_bench(tmp, frames, 14550, mistake))
    sensor = world.entity(demo.ENTITY).sensors[0]
    assert sensor.camera is not None and sensor.camera.calibration is not None
    detector = CameraDetectorSpec(sensor, world, load_calibration(sensor.camera.calibration), DECIMATE).build()
    graph = make_graph(world, demo.ENTITY)
    listener = Listener(world, graph)
    check = StartupCheck(world, demo.ENTITY, window_s=WINDOW_S)
    R_true = rotation_from_rpy_deg(BENCH_RPY_DEG)  # the autopilot's attitude: body FLU in level ENU
    for k, path in enumerate(sorted(frames.iterdir())):
        t_s = k / FPS_HZ
        now_ns, capture_us = round(t_s * 1e9), round(t_s * 1e6)
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        listener.accept_many([(md, now_ns) for md in detector.detect(gray, capture_us)])
        result = graph.evaluate(now_ns)
        listener.set_estimates(result.poses)
        pose = result.poses.get(demo.ENTITY)
        if pose is None or pose.capture_time_us != capture_us:
            continue
        checks = check.add(AutopilotPose(pose, 0), R_true, t_s)
        if checks is not None:
            return checks
    raise AssertionError(f"fewer than {WINDOW_S:g} s of poses from {len(list(frames.iterdir()))} frames")


def _attitude(checks: list[Check]) -> Check:
    (line,) = [c for c in checks if c.name == "attitude"]
    return line


def test_the_right_setup_passes(tmp_path: Path, frames_dir: Path) -> None:
    assert _attitude(_judged(tmp_path, frames_dir, None)).verdict is Verdict.PASS


@pytest.mark.parametrize(
    ("mistake", "named"),
    [
        ("mount90", "likely the world file turns camera down +90 deg about its optical axis"),
        ("flu_as_frd", "likely body axes written in FLU but declared FRD"),
        ("ned_as_enu", "likely world file written in NED but declared ENU"),
    ],
)
def test_each_frame_mistake_is_named(tmp_path: Path, frames_dir: Path, mistake: str, named: str) -> None:
    line = _attitude(_judged(tmp_path, frames_dir, mistake)).line()
    assert line.startswith("FAIL") and named in line and "(or:" not in line, line
