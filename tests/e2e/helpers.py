"""Helpers for end-to-end tests: free loopback ports, a node process, a peer that speaks our dialect."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml
from pymavlink import mavutil

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec, dialect


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_world(tmp: Path, doc: dict) -> Path:
    path = tmp / "world.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class NodeProcess:
    """``python -m atlas_onboard run`` in a subprocess, with its log captured."""

    def __init__(self, config: Path, entity: str, env: dict | None = None, args: tuple[str, ...] = ()) -> None:
        self.log_path = config.parent / f"{entity}.log"
        self._log = open(self.log_path, "wb")
        full_env = {**os.environ, **(env or {})}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "atlas_onboard", "-v", "run", "--config", str(config), "--entity", entity, *args],
            stdout=self._log, stderr=subprocess.STDOUT, env=full_env,
        )  # fmt: skip

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self._log.close()
        return code

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def final_counters(self) -> dict[str, int]:
        """The counters of the node's final status line (logged at a clean exit)."""
        for line in reversed(self.log().splitlines()):
            if " final " in line:
                pairs = line.split(" final ", 1)[1].split()
                return {k: int(v) for k, v in (p.split("=", 1) for p in pairs)}
        raise AssertionError(f"no final status line in the log:\n{self.log()[-3000:]}")


class Peer:
    """A MAVLink endpoint standing in for another drone: sends observations to a node's udpin port."""

    def __init__(self, port: int, system_id: int = 42, key: bytes | None = None) -> None:
        self.d = dialect.load()
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=system_id, source_component=197
        )
        self.conn.mav = self.d.MAVLink(self.conn, srcSystem=system_id, srcComponent=197)
        self.conn.WIRE_PROTOCOL_VERSION, self.conn.first_byte = "2.0", False
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True)
        self.seq = 0

    def send(self, md: MarkerData, fingerprint: int, **override) -> bytes:
        self.seq += 1
        fields = codec.observation_fields(md, fingerprint)
        fields["seq"] = override.pop("seq", self.seq)
        fields.update(override)
        msg = self.d.MAVLink_atlas_observation_message(**fields)
        buf = msg.pack(self.conn.mav)
        self.conn.write(buf)
        return buf

    def raw(self, data: bytes) -> None:
        self.conn.write(data)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.conn.close()


def wait_for(predicate, timeout: float = 20.0, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return False


def start_node_with_peer(tmp: Path, doc_for, entity: str = "d1"):
    """A simulated autopilot, a world file from ``doc_for(peer_port, autopilot_port)``, the node of
    ``entity`` and a peer (system 250) on its udpin port, once the node's heartbeat reached the
    autopilot. Returns (world, autopilot, node, peer); the caller stops them."""
    from atlas_onboard.config import load_world
    from atlas_onboard.sim.autopilot import SimAutopilot

    ap = SimAutopilot(system_id=1).start()
    port = free_udp_port()
    path = write_world(tmp, doc_for(port, ap.port))
    world = load_world(path)
    node = NodeProcess(path, entity)
    peer = Peer(port, system_id=250)
    assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
    return world, ap, node, peer
