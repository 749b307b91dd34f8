"""``atlas-onboard preflight`` end to end: the command (a process) starts the node (a process) behind
its relay, the simulated autopilot (a process) reports the bench attitude and answers the parameters;
the right setup passes (exit status 0), and a frame mistake planted in the world file and a delay
parameter far from the latency are each named (exit status 1); the service judges its first seconds
at start. Every frame mistake, and the right setup, judged on the node's own pipeline offline:
``tests/sim/test_bench.py``."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from atlas_onboard.sim.bench import BENCH_RPY_DEG, write_bench, write_bench_frames
from tests.e2e.helpers import free_udp_port

WINDOW_S = 4


@pytest.fixture(scope="module")
def frames_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    frames = tmp_path_factory.mktemp("bench") / "frames"
    write_bench_frames(frames, seconds=12.0)
    return frames


def _preflight(tmp: Path, frames: Path, mistake: str | None, params: dict[str, float]) -> tuple[int, str]:
    port = free_udp_port()
    world = write_bench(tmp, frames, port, mistake)
    autopilot = subprocess.Popen(
        [sys.executable, "-m", "atlas_onboard", "sim-autopilot", "--port", str(port), "--seconds", "60",
         "--attitude-rpy-deg", *map(str, BENCH_RPY_DEG), "--local-position-hz", "10", "--timesync-hz", "10",
         *[a for k, v in params.items() for a in ("--param", f"{k}={v:g}")]],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "atlas_onboard", "preflight", "--config", str(world), "--entity", "drone",
             "--seconds", str(WINDOW_S)],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
    finally:
        autopilot.send_signal(signal.SIGINT)
        try:
            autopilot.wait(timeout=10)
        except subprocess.TimeoutExpired:
            autopilot.kill()
            autopilot.wait()
    return proc.returncode, proc.stdout + proc.stderr


def _line(out: str, name: str) -> str:
    lines = [ln for ln in out.splitlines() if ln[6:].startswith(name + ":")]
    assert len(lines) == 1, out
    return lines[0]


@dataclass(frozen=True)
class Service:
    checked: bool  # the node logged its startup check's attitude line in time
    poses_before: int  # poses the autopilot had received by then
    log: str
    statustexts: list[bytes]


def _service(tmp: Path, frames: Path) -> Service:
    """``run`` on the world file with the frame mistake, until its startup check is logged."""
    from atlas_onboard.core.geometry import rotation_from_rpy_deg
    from atlas_onboard.sim.autopilot import SimAutopilot
    from tests.e2e.helpers import NodeProcess, wait_for

    R = rotation_from_rpy_deg(BENCH_RPY_DEG)
    autopilot = SimAutopilot(system_id=1, attitude=lambda _t: R).start()
    node = NodeProcess(write_bench(tmp, frames, autopilot.port, "mount90"), "drone")
    try:
        checked = wait_for(lambda: "startup check:" in node.log(), timeout=60.0)
        checked = checked and wait_for(
            lambda: "startup check: " in node.log() and "attitude" in node.log(), timeout=10.0
        )
        poses_before = len(autopilot.snapshot())
    finally:
        node.stop()
        autopilot.stop()
    return Service(checked, poses_before, node.log(), list(autopilot.statustexts))


# Runs at the same time: each is a node replaying the bench's frames at 15 Hz, its autopilot and the
# command, waiting on the clock for most of the window; on one core three still keep the pose rate.
AT_ONCE = 3


@pytest.fixture(scope="module")
def runs(frames_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Future[Any]]:
    """The right setup's and the mistakes' preflight, and the service's startup check, AT_ONCE at a
    time; each test reads its own (a run that failed fails its test)."""
    plans: dict[str, Callable[[Path], Any]] = {
        "right": lambda tmp: _preflight(tmp, frames_dir, None, {"EKF2_EV_DELAY": 20, "EKF2_EV_CTRL": 3}),
        "mistakes": lambda tmp: _preflight(tmp, frames_dir, "mount90", {"EKF2_EV_DELAY": 200}),
        "service": lambda tmp: _service(tmp, frames_dir),
    }
    with ThreadPoolExecutor(AT_ONCE) as pool:
        futures = {name: pool.submit(plan, tmp_path_factory.mktemp(name)) for name, plan in plans.items()}
        for f in futures.values():
            f.exception()  # all done before the first test reads one
    return futures


def test_right_setup_passes(runs: dict[str, Future[Any]]) -> None:
    code, out = runs["right"].result()
    assert _line(out, "attitude").startswith("PASS"), out
    for name in ("delay", "timesync", "EKF origin", "local position"):
        assert _line(out, name).startswith("PASS"), out
    assert code == 0, out


def test_a_frame_mistake_and_a_delay_far_over_the_latency_are_each_named(runs: dict[str, Future[Any]]) -> None:
    # Independent checks on one run: the attitude check reads the poses, the delay check their latency.
    code, out = runs["mistakes"].result()
    line = _line(out, "attitude")
    named = "likely the world file turns camera down +90 deg about its optical axis"
    assert line.startswith("FAIL") and named in line and "(or:" not in line, out
    line = _line(out, "delay")
    assert line.startswith("FAIL  delay: EKF2_EV_DELAY 200 ms is longer than the whole capture to autopilot"), out
    assert code == 1


def test_the_service_checks_once_at_start(runs: dict[str, Future[Any]]) -> None:
    """``run`` judges its first seconds of poses against the autopilot's attitude, in its log and as
    STATUSTEXT, without holding the poses back."""
    run: Service = runs["service"].result()
    assert run.checked, run.log
    log = [ln for ln in run.log.splitlines() if "startup check:" in ln]
    attitude = [ln for ln in log if "attitude:" in ln]
    assert len(attitude) == 1, log
    assert run.poses_before > 50  # the poses went out meanwhile
    assert "FAIL  attitude" in attitude[0] and "+90 deg about its optical axis" in attitude[0]
    assert b"atlas FAIL attitude: down mount +90deg about axis" in run.statustexts, run.statustexts
