"""One drone's node of a scenario, alone, with a peer link of its own: for tests and benchmarks that
talk to a node (or attack it) while its simulated camera gives it a real pose.

The node is a real ``atlas-onboard run`` process with the scenario's world file, its simulated
cameras (rendered images, or corners from the geometry plus noise with ``geometric``) and a
simulated autopilot; its one peer link is ``udpin`` on a free loopback port (optionally signed), as
a drone on a mesh would listen. The world file's ``nodes`` section is the simulator's (every drone
and the world's node with their system ids), so origins bind as in a real swarm.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WorldConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import codec, dialect
from atlas_onboard.mavlink.signing import signing_timestamp
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.command import autopilot_track
from atlas_onboard.sim.context import SIM_ENV
from atlas_onboard.sim.report import EntityScore, score
from atlas_onboard.sim.runner import NODE_MODULE, WARMUP_S, WORLD_NODE_SYSTEM_ID, _rendered_frames, build_run_config
from atlas_onboard.sim.scenario import Scenario
from atlas_onboard.sim.world import SimWorld


def free_udp_port() -> int:
    """A UDP port free on 127.0.0.1 now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class SoloNode:
    """A running node (see the module's docstring); :meth:`stop` ends it and keeps its log."""

    scenario: Scenario
    entity: str
    system_id: int
    peer_port: int
    autopilot: SimAutopilot
    proc: subprocess.Popen[bytes]
    run_dir: Path
    world_file: Path
    epoch_s: float = 0.0
    log: str = ""
    clock: list[float] = field(default_factory=list)  # the scenario's epoch once started: the autopilot's attitude

    def start_scenario(self, timeout_s: float = 60.0) -> float:
        """Wait until the node says HEARTBEAT to its autopilot, then start the scenario's clock."""
        deadline = time.monotonic() + timeout_s
        while self.autopilot.heartbeats_from.get((self.system_id, 197), 0) == 0:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise AtlasError(f"node {self.entity} did not come up: {self.log[-2000:]}")
            time.sleep(0.05)
        self.epoch_s = time.time() + 0.3
        self.clock[:] = [self.epoch_s]
        tmp = self.run_dir / "epoch.tmp"
        tmp.write_text(f"{self.epoch_s:.6f}\n", encoding="utf-8")
        tmp.replace(self.run_dir / "epoch")
        return self.epoch_s

    def score(self, t0_s: float, t1_s: float) -> EntityScore:
        """The pose at the autopilot against the truth, for estimates that arrived between t0 and t1
        (seconds after the scenario's start)."""
        track = autopilot_track(self.autopilot.snapshot(), self.epoch_s)
        return score(self.entity, "autopilot", track, SimWorld(self.scenario), t0_s, t1_s, 1.0)

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM (SIGKILL after ``timeout_s``), then the autopilot; returns the node's exit status."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            code = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self.autopilot.stop()
        self.log = (self.run_dir / "node.log").read_text(encoding="utf-8", errors="replace")
        shutil.rmtree(self.run_dir, ignore_errors=True)
        return code

    def final_counters(self) -> dict[str, int]:
        """The counters of the node's final status line (after :meth:`stop`)."""
        for line in reversed(self.log.splitlines()):
            if " final " in line:
                pairs = line.split(" final ", 1)[1].split()
                return {k: int(v) for k, v in (p.split("=", 1) for p in pairs)}
        raise AtlasError(f"no final status line in the node's log: {self.log[-2000:]}")


def start_solo(
    scenario_name: str,
    duration_s: float,
    *,
    entity: str | None = None,
    signing: dict[str, Any] | None = None,
    geometric: bool = True,
    seed: int = 0,
    node_args: tuple[str, ...] = (),
    world_node: bool = False,
    edit: Callable[[dict[str, Any]], None] | None = None,
) -> SoloNode:
    """Start the node of ``entity`` (default: the scenario's first drone); the scenario's clock starts
    at :meth:`SoloNode.start_scenario`. ``signing`` is the peer link's ``signing`` section.
    ``world_node``: the world file names a node of the world (system 250), a peer the tests can play.
    ``edit`` changes the run's world file (a parsed YAML document) before the node reads it: a sensor no
    simulated camera feeds (a peer's, played by the caller), another fusion setting."""
    scenario = scenarios.get(scenario_name)
    entity = entity or scenario.drones[0]
    system_id = scenario.drones.index(entity) + 1  # as build_run_config numbers them
    run_dir = Path(tempfile.mkdtemp(prefix=f"atlas-solo-{scenario.name}-"))
    frames_dir = None if geometric else _rendered_frames(scenario, seed, duration_s, lambda _msg: None)
    # The autopilot streams the drone's attitude (noisy, biased, its own heading) as a real one does,
    # from the scenario's start: a node's gravity reference for single tags, its own and its peers'.
    sim_world = SimWorld(scenario)
    clock: list[float] = []  # the scenario's epoch (wall s), set by SoloNode.start_scenario

    def attitude(t_wall: float) -> Rotation | None:
        return sim_world.truth(t_wall - clock[0], (entity,))[entity].rotation if clock else None

    def rates(t_wall: float) -> NDArray[np.float64] | None:  # ATTITUDE's body rates, as a real autopilot's
        return scenario.trajectories[entity].body_rates(np.array([t_wall - clock[0]]))[0] if clock else None

    autopilot = SimAutopilot(
        system_id=system_id, attitude=attitude, attitude_seed=seed + system_id, rates=rates
    ).start()
    port = free_udp_port()
    path = build_run_config(scenario, run_dir, free_udp_port(), {d: autopilot.port for d in scenario.drones})
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    peer: dict[str, Any] = {"url": f"udpin:127.0.0.1:{port}"}
    if signing is not None:
        peer["signing"] = signing
    doc["nodes"][entity].update(peers=[peer], state_dir=str(run_dir / "state"), status_interval_s=1)
    if world_node:
        doc["nodes"].setdefault("world", {"system_id": WORLD_NODE_SYSTEM_ID})
    if edit is not None:
        edit(doc)
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    env = dict(os.environ)
    env[SIM_ENV] = json.dumps(
        {
            "scenario": scenario.name,
            "seed": seed,
            "epoch_file": str(run_dir / "epoch"),
            "duration_s": duration_s,
            "frames_dir": str(frames_dir) if frames_dir is not None else None,
            "geometric": geometric,
        }
    )
    with open(run_dir / "node.log", "ab") as log:
        proc = subprocess.Popen(  # noqa: S603 - our own interpreter and arguments
            [sys.executable, "-m", NODE_MODULE, *node_args, "run", "--config", str(path), "--entity", entity],
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
        )  # fmt: skip
    return SoloNode(scenario, entity, system_id, port, autopilot, proc, run_dir, path, clock=clock)


def forged_view(
    world: WorldConfig,
    sim_world: SimWorld,
    entity: str,
    sensor_id: int,
    marker_id: int,
    t_s: float,
    offset_m: tuple[float, float, float],
    sigma_m: float,
    capture_time_us: int,
) -> MarkerData:
    """What ``sensor_id`` would report of ``marker_id`` at scenario time ``t_s`` if ``entity`` stood
    ``offset_m`` (world frame) from where it is: a consistent lie, with the claimed ``sigma_m``."""
    truth = sim_world.truth(t_s)
    truth[entity] = RigidTransform.from_translation(offset_m) * truth[entity]
    s, m = world.sensors[sensor_id], world.markers[marker_id]
    T_sensor_marker = (truth[s.entity] * s.T_entity_sensor).inv() * (truth[m.entity] * m.T_entity_marker)
    p = T_sensor_marker.translation
    x, y, z, w = T_sensor_marker.rotation.as_quat()
    return MarkerData(
        sensor_id=sensor_id, marker_id=marker_id, sigma_m=sigma_m,
        p_sensor_marker_m=(float(p[0]), float(p[1]), float(p[2])), q_sensor_marker_wxyz=(float(w), float(x),
        float(y), float(z)), capture_time_us=capture_time_us,
    )  # fmt: skip


class Radio:
    """Another host on the node's network: MAVLink frames of the atlas dialect from any system id,
    signed with any key or not at all, and raw bytes, to one UDP port."""

    def __init__(self, port: int) -> None:
        self.addr = ("127.0.0.1", port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.d = dialect.load()
        self._mavs: dict[tuple[int, bytes | None], Any] = {}
        self.sent = 0

    def _mav(self, system_id: int, key: bytes | None) -> Any:
        mav = self._mavs.get((system_id, key))
        if mav is None:
            mav = self._mavs[(system_id, key)] = self.d.MAVLink(None, srcSystem=system_id, srcComponent=197)
            if key is not None:
                mav.signing.secret_key, mav.signing.sign_outgoing = key, True
                mav.signing.timestamp = signing_timestamp(time.time())
        return mav

    def frame(self, msg: Any, system_id: int, key: bytes | None = None) -> bytes:
        """``msg`` packed as ``system_id`` would send it (signed with ``key`` if given)."""
        return bytes(msg.pack(self._mav(system_id, key)))

    def observation(
        self, md: MarkerData, fingerprint: int, system_id: int, key: bytes | None = None, **override: Any
    ) -> bytes:
        fields = codec.observation_fields(md, fingerprint)
        fields.update(override)
        return self.frame(self.d.MAVLink_atlas_observation_message(**fields), system_id, key)

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.addr)
        self.sent += 1

    def close(self) -> None:
        self.sock.close()


__all__ = ["WARMUP_S", "Radio", "SoloNode", "forged_view", "free_udp_port", "start_solo"]
