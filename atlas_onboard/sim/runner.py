"""``atlas-onboard sim``: run a scenario with real node processes talking real MAVLink over loopback.

Each drone is a real ``atlas-onboard run`` process with its simulated cameras (rendered images,
detected by the real detector), a simulated autopilot (:mod:`atlas_onboard.sim.autopilot`) on its
autopilot link, and one peer link to a hub that stands in for the swarm's mesh. World-fixed cameras
(and the paper's motion-capture system) run in a node for the ``world`` entity, as a ground computer
would. The run is in real time on the wall clock: camera rates and resolutions are chosen per
scenario so that two cores keep up, and the report states them.

Timeline: the runner starts every process, waits until each node has said HEARTBEAT on the mesh,
then writes the start time (``epoch``) to a file the nodes' simulated cameras wait for, so no node
starts its scenario early. At the end every process gets SIGTERM (SIGKILL after a grace period), and
the runner leaves no process and no socket behind, also on Ctrl-C or an error.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from atlas_onboard.config import WORLD
from atlas_onboard.detector.calibration import RMS_KEY
from atlas_onboard.detector.render import LENS_RESIDUAL_PX
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.autopilot import SimAutopilot, recording
from atlas_onboard.sim.camera import frames_path, prerender, replay_folder
from atlas_onboard.sim.context import SIM_ENV
from atlas_onboard.sim.flight import Flight, LandingScore, autopilot_type
from atlas_onboard.sim.hub import Hub
from atlas_onboard.sim.scenario import SIM_KIND, Scenario
from atlas_onboard.sim.world import Intrinsics, SimWorld

_logger = logging.getLogger(__name__)


WORLD_NODE_SYSTEM_ID = 250
NODE_MODULE = "atlas_onboard.sim.launch"  # each node: `atlas-onboard run` with the simulator plugged in
WARMUP_S = 1.0  # scored from this long after the start: the first frames fill the pipelines
LANDED_S = 1.0  # a landing's run ends this long after touchdown


@dataclass
class SimOptions:
    scenario: str = scenarios.DEFAULT
    duration_s: float | None = None
    seed: int = 0
    out_dir: Path | None = None
    keep_dir: bool = False
    ready_timeout_s: float = 60.0
    node_args: tuple[str, ...] = ()
    world_overrides: dict[str, Any] = field(default_factory=dict)  # e.g. {"fusion": {"path": "dijkstra"}}
    # Faults to inject, (seconds after the start, "kill" or "start", entity): a node crashes (SIGKILL)
    # and is started again, to check what its peers do meanwhile.
    faults: tuple[tuple[float, str, str], ...] = ()
    # With ``until``, the run goes on past ``duration_s`` (to at most ``max_duration_s``) until
    # ``until(autopilots, epoch)`` holds: a test waits for an event, not a window a loaded machine may miss.
    until: Callable[[dict[str, SimAutopilot], float], bool] | None = None
    max_duration_s: float = 60.0
    # "realtime" or "every_frame": the drones' cameras replay the run's pre-rendered images from an image
    # folder (the ``camera.source: <folder>`` path, detector.sources), started at the run's epoch.
    replay: str = ""
    # The simulated autopilots' ATTITUDE carries the gyros' angular rates (False: zeros, as an autopilot
    # that does not fill them); their LOCAL_POSITION_NED at this rate carries their EKF's velocity (0: none).
    autopilot_rates: bool = True
    local_position_hz: float = 30.0


@dataclass
class SimRun:
    """What a finished run leaves for scoring: records with times relative to the epoch."""

    scenario: Scenario
    world: SimWorld
    epoch_s: float
    duration_s: float
    run_dir: Path
    autopilots: dict[str, SimAutopilot]
    taps: list[tuple[float, bytes]]
    exit_codes: dict[str, int | None]
    logs: dict[str, str]
    ports: list[int] = field(default_factory=list)  # every UDP port the runner opened (all closed now)
    pids: list[int] = field(default_factory=list)  # every node process it started (all ended now)
    faults_s: list[tuple[float, str, str]] = field(default_factory=list)  # when each fault was injected
    landing: LandingScore | None = None  # a landing scenario's touchdown


def write_calibration(path: Path, intr: Intrinsics) -> None:
    """An OpenCV FileStorage YAML calibration, the format the detector reads."""
    k = intr.camera_matrix.ravel()
    d = intr.distortion
    text = (
        "%YAML:1.0\n---\n"
        f"image_width: {intr.width_px}\nimage_height: {intr.height_px}\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [ {', '.join(f'{v:.10g}' for v in k)} ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
        f"   data: [ {', '.join(f'{v:.10g}' for v in d)} ]\n"
        f"{RMS_KEY}: {LENS_RESIDUAL_PX:g}\n"  # the rendered lens is its model
    )
    path.write_text(text, encoding="utf-8")


def build_run_config(
    scenario: Scenario,
    run_dir: Path,
    hub_port: int,
    autopilot_ports: dict[str, int],
    overrides: dict[str, Any] | None = None,
) -> Path:
    """The world file of the run: the scenario's, plus calibrations and a ``nodes`` section."""
    doc = scenario.world_doc()
    # ``nodes`` overrides are settings for every node (merged into the generated ``nodes.defaults``).
    node_defaults = dict((overrides or {}).get("nodes", {}))
    for key, value in (overrides or {}).items():
        if key != "nodes":
            doc[key] = {**doc.get(key, {}), **value} if isinstance(value, dict) else value
    sim_world = SimWorld(scenario)
    for entity, ent in doc["entities"].items():
        for sensor in (ent or {}).get("sensors", []) or []:
            if "camera" not in sensor:
                continue
            sid = int(sensor["id"])
            cal = run_dir / f"calibration-{entity}-{sensor['name']}.yaml"
            write_calibration(cal, sim_world.cameras[sid][1])
            sensor["camera"]["calibration"] = str(cal)
    if scenario.mocap is not None:  # the motion-capture system reports like a camera of the world node
        for sensor in (doc["entities"].get(WORLD) or {}).get("sensors", []) or []:
            if sensor["name"] == scenario.mocap.sensor:
                sensor.setdefault("camera", {"source": SIM_KIND})
    defaults = {"peers": [f"udpout:127.0.0.1:{hub_port}"], "status_interval_s": 5, **node_defaults}
    nodes: dict[str, Any] = {"defaults": defaults}
    for k, name in enumerate(scenario.drones, start=1):
        nodes[name] = {"system_id": k, "autopilot": {"url": f"udpout:127.0.0.1:{autopilot_ports[name]}"}}
        if scenario.landing is not None and scenario.landing.entity == name:
            ls = scenario.landing
            nodes[name]["landing"] = {"target": ls.target, "marker": ls.marker, "autopilot": ls.form}
    if scenario.needs_world_node:
        nodes[WORLD] = {"system_id": WORLD_NODE_SYSTEM_ID}
    doc["nodes"] = nodes
    path = run_dir / "world.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


@contextlib.contextmanager
def _processes() -> Iterator[dict[str, subprocess.Popen[bytes]]]:
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        yield procs
    finally:
        for p in procs.values():
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 5.0
        for p in procs.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(deadline - time.monotonic(), 0.1))
            if p.poll() is None:
                p.kill()
                p.wait(timeout=5.0)


# Frames rendered in this process, reused by a later run of the same scenario, world file and seed
# that is no longer (frame j is the same image whatever the run's length): the tests run some
# scenarios twice. Oldest dropped beyond the budget; all removed at exit.
_FRAME_CACHE: dict[tuple[str, str, int], tuple[Path, float, int]] = {}
FRAME_CACHE_BYTES = 1_500_000_000


def _rendered_frames(scenario: Scenario, seed: int, duration_s: float, say: Callable[[str], None]) -> Path | None:
    """A directory with every camera's frames for the run (:func:`prerender`), or None without cameras."""
    world_path = scenario.world_path()
    key = (scenario.name, hashlib.sha256(world_path.read_bytes()).hexdigest(), seed)
    cached = _FRAME_CACHE.get(key)
    if cached is not None and cached[1] >= duration_s:
        say("reusing the cameras' images rendered for an earlier run")
        return cached[0]
    # Before any thread of ours starts (the renderer forks its workers).
    say("rendering the cameras' images")
    directory = Path(tempfile.mkdtemp(prefix=f"atlas-sim-frames-{scenario.name}-"))
    try:
        if not prerender(scenario, world_path, seed, duration_s, directory):
            shutil.rmtree(directory, ignore_errors=True)
            return None
    except BaseException:
        shutil.rmtree(directory, ignore_errors=True)
        raise
    if cached is not None:
        shutil.rmtree(_FRAME_CACHE.pop(key)[0], ignore_errors=True)
    _FRAME_CACHE[key] = (directory, duration_s, sum(f.stat().st_size for f in directory.iterdir()))
    while len(_FRAME_CACHE) > 1 and sum(v[2] for v in _FRAME_CACHE.values()) > FRAME_CACHE_BYTES:
        shutil.rmtree(_FRAME_CACHE.pop(next(iter(_FRAME_CACHE)))[0], ignore_errors=True)
    return directory


def _drop_frame_cache() -> None:
    while _FRAME_CACHE:
        shutil.rmtree(_FRAME_CACHE.popitem()[1][0], ignore_errors=True)


atexit.register(_drop_frame_cache)


def write_replay_folders(frames_dir: Path, scenario: Scenario, say: Callable[[str], None]) -> None:
    """The drones' cameras' pre-rendered frames as image folders, once (kept with the frames)."""
    import cv2

    for sid, (sensor, _intr) in SimWorld(scenario).cameras.items():
        folder = replay_folder(frames_dir, sid)
        source = frames_path(frames_dir, sid)
        if sensor.entity not in scenario.drones or folder.exists() or not source.exists():
            continue
        say(f"writing the images of camera {sensor.name} for a replay")
        frames = np.load(source, mmap_mode="r")
        part = folder.with_suffix(".part")
        shutil.rmtree(part, ignore_errors=True)
        part.mkdir()
        for j in range(len(frames)):
            cv2.imwrite(str(part / f"frame{j:05d}.png"), np.asarray(frames[j]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        part.rename(folder)


def run(options: SimOptions, progress: Callable[[str], None] | None = None) -> SimRun:
    """Run one scenario to the end and return its records (scoring is :func:`atlas_onboard.sim.report`)."""
    say = progress or (lambda _msg: None)
    scenario = scenarios.get(options.scenario)
    duration = options.duration_s if options.duration_s is not None else scenario.duration_s
    if not 2.0 <= duration <= 3600.0:
        raise AtlasError(f"--duration: expected 2 to 3600 seconds, got {duration:g}")
    run_dir = Path(tempfile.mkdtemp(prefix=f"atlas-sim-{scenario.name}-"))
    scenario = scenario.with_flights(run_dir)  # flown entities: their truth is written as the run goes
    frames_dir = None
    geometric = bool(os.environ.get("ATLAS_SIM_GEOMETRIC"))  # no images: corners from the geometry plus noise
    if options.replay and (geometric or scenario.flown):
        raise AtlasError("a replay needs images rendered before the run (unset ATLAS_SIM_GEOMETRIC; no landing)")
    if not geometric and not scenario.flown:  # a flown vehicle's cameras render as they go
        try:
            frames_dir = _rendered_frames(scenario, options.seed, duration, say)
            if options.replay:
                write_replay_folders(frames_dir, scenario, say)
        except BaseException:
            shutil.rmtree(run_dir, ignore_errors=True)
            raise
    taps: list[tuple[float, bytes]] = []
    hub = Hub(tap=lambda data, _addr, t: taps.append((t, data))).start()
    sim_world = SimWorld(scenario)
    epoch_at: list[float] = []  # set once the run starts: the autopilots' attitude is the truth from then

    def attitude_of(name: str) -> Callable[[float], Any]:
        return lambda t_wall: sim_world.truth(t_wall - epoch_at[0], (name,))[name].rotation if epoch_at else None

    def rates_of(name: str) -> Callable[[float], Any] | None:
        if not options.autopilot_rates:
            return None
        trajectory = scenario.trajectories[name]
        return lambda t_wall: trajectory.body_rates(np.array([t_wall - epoch_at[0]]))[0] if epoch_at else None

    def velocity_of(name: str) -> Callable[[float], Any]:
        return lambda t: scenario.trajectories[name].velocity(np.array([t - epoch_at[0]]))[0] if epoch_at else None

    autopilots = {
        name: SimAutopilot(system_id=k, attitude=attitude_of(name), attitude_seed=options.seed + k,
                           rates=rates_of(name), autopilot_type=autopilot_type(scenario, name),
                           velocity=velocity_of(name), local_position_hz=options.local_position_hz).start()
        for k, name in enumerate(scenario.drones, start=1)
    }  # fmt: skip
    flight = None if scenario.landing is None else Flight(scenario, autopilots[scenario.landing.entity], max(
        duration, options.max_duration_s))  # fmt: skip
    logs: dict[str, str] = {}
    exit_codes: dict[str, int | None] = {}
    pids: list[int] = []
    epoch = 0.0
    faults_s: list[tuple[float, str, str]] = []
    try:
        world_file = build_run_config(
            scenario, run_dir, hub.port, {n: a.port for n, a in autopilots.items()}, options.world_overrides
        )
        epoch_file = run_dir / "epoch"
        env = dict(os.environ)
        env[SIM_ENV] = json.dumps(
            {
                "scenario": scenario.name,
                "seed": options.seed,
                "epoch_file": str(epoch_file),
                "duration_s": duration,
                "frames_dir": str(frames_dir) if frames_dir is not None else None,
                "geometric": geometric,
                "replay": options.replay,
                "flights_dir": str(run_dir),
            }
        )
        entities = list(scenario.drones) + ([WORLD] if scenario.needs_world_node else [])
        with _processes() as procs, recording():

            def spawn(name: str) -> None:
                with open(run_dir / f"{name}.log", "ab") as log:
                    procs[name] = subprocess.Popen(  # noqa: S603 - our own interpreter and arguments
                        [sys.executable, "-m", NODE_MODULE, *options.node_args, "run", "--config", str(world_file),
                         "--entity", name],
                        stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
                    )  # fmt: skip
                pids.append(procs[name].pid)

            for name in entities:
                spawn(name)
            say(f"started {len(procs)} node processes; waiting for them to come up")
            deadline = time.monotonic() + options.ready_timeout_s
            while len(hub.clients) < len(entities):
                dead = [n for n, p in procs.items() if p.poll() is not None]
                if dead:
                    raise AtlasError(f"node {dead[0]} exited during start-up: {_tail(run_dir / f'{dead[0]}.log')}")
                if time.monotonic() > deadline:
                    raise AtlasError(
                        f"only {len(hub.clients)} of {len(entities)} nodes came up in {options.ready_timeout_s:g} s"
                    )
                time.sleep(0.05)
            epoch = time.time() + 0.3
            epoch_at.append(epoch)
            if flight is not None:
                flight.start(epoch)
            tmp = epoch_file.with_suffix(".tmp")
            tmp.write_text(f"{epoch:.6f}\n", encoding="utf-8")
            tmp.replace(epoch_file)
            say(f"running {scenario.name} for {duration:g} s")
            pending = sorted(options.faults)
            killed: set[str] = set()

            def going_on() -> bool:
                now = time.time()
                if flight is not None and flight.landed_for(now - epoch) > LANDED_S:
                    return False
                if now < epoch + duration:
                    return True
                waiting = options.until is not None and not options.until(autopilots, epoch)
                return waiting and now < epoch + max(duration, options.max_duration_s)

            while going_on():
                while pending and time.time() >= epoch + pending[0][0]:
                    _, action, name = pending.pop(0)
                    faults_s.append((time.time() - epoch, action, name))
                    if action == "kill":
                        procs[name].kill()
                        procs[name].wait()
                        killed.add(name)
                    elif action == "start":
                        spawn(name)
                        killed.discard(name)
                    say(f"fault: {action} {name}")
                dead = [n for n, p in procs.items() if p.poll() is not None and n not in killed]
                if dead:
                    raise AtlasError(f"node {dead[0]} died during the run: {_tail(run_dir / f'{dead[0]}.log')}")
                time.sleep(0.02)
            if options.until is not None or flight is not None:  # the run's length: as long as it went
                duration = time.time() - epoch if flight is not None else max(duration, time.time() - epoch)
        exit_codes = {n: p.returncode for n, p in procs.items()}
        logs = {n: (run_dir / f"{n}.log").read_text(encoding="utf-8", errors="replace") for n in entities}
    finally:
        if flight is not None:
            flight.stop()
        hub.stop()
        for a in autopilots.values():
            a.stop()
        if not options.keep_dir:
            shutil.rmtree(run_dir, ignore_errors=True)
    ports = [hub.port, *(a.port for a in autopilots.values())]
    world = SimWorld(scenario)
    landing = flight.score() if flight is not None else None
    return SimRun(scenario, world, epoch, duration, run_dir, autopilots, taps, exit_codes, logs, ports, pids, faults_s,
                  landing)  # fmt: skip


def _tail(path: Path, lines: int = 3) -> str:
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    except OSError:
        return "(no log)"
    return " | ".join(text[-lines:]) if text else "(empty log)"


def availability_times(duration_s: float, step_s: float = 0.1) -> np.ndarray:
    return np.arange(WARMUP_S, duration_s, step_s)
