"""Latency and throughput of one node process, on loopback.

A load generator plays 10 drones x 30 Hz x 4 markers (1200 observations/s) to one node (drone d0);
a simulated autopilot receives its VISION_POSITION_ESTIMATE. Latency is from the moment an
observation of d0 is written to the node's socket to the moment its pose arrives at the autopilot
(the observation's capture stamp is its send time, and VISION_POSITION_ESTIMATE.usec carries it).
The anchor, measured in the same run under the same load: a process that decodes every observation
with pymavlink, as a node's link does, and forwards d0's image at once as one message when its last
observation is in (peer -> endpoint -> autopilot, no graph), as the node sends one pose per image.
Overhead = node - anchor: what the listener, graph and publisher add. Node and anchor take the load
in alternate blocks (2.5 s each by default), so that a drift of the machine's speed falls on both
alike; the first 0.5 s of each block is not counted.

    python benchmarks/bench_node.py [--seconds S] [--block S] [--split]

Bar: overhead <= 2 ms median at 10 drones x 30 Hz x 4 markers.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform, Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from soak import cpu_s, detection_covariance  # the benchmarks folder is on the path when run as a script

from atlas_onboard.config import load_world
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec, dialect
from atlas_onboard.sim.autopilot import SimAutopilot, recording

N_DRONES, RATE_HZ, MARKERS = 10, 30, 4
WARMUP_S = 0.5


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def world_doc(peer_port: int, ap_port: int) -> dict:
    """Drones d1..d9 see world markers with their cameras (sensors 2..10, nodes 51..59); d0, the node
    under test, is seen by a ceiling camera (sensor 1, the world's node 50): a node accepts no
    observation of its own cameras from the network, so d0's views come from another's camera."""
    markers = [{"id": i, "size_m": 0.2, "pose": {"pos": [float(i % 8), float(i // 8), 0.0]}} for i in range(40)]
    ceiling = {"name": "ceiling", "id": 1, "pose": {"pos": [1.0, 1.0, 4.0], "rpy_deg": [0, 90, 0]}}
    ents: dict = {"world": {"markers": markers, "sensors": [ceiling]}}
    ents["d0"] = {"markers": [{"id": 100 + j, "size_m": 0.1, "pose": {"pos": [0.1 * (j % 2), 0.1 * (j // 2), 0.05]}}
                              for j in range(MARKERS)]}  # fmt: skip
    for k in range(1, N_DRONES):
        ents[f"d{k}"] = {"sensors": [{"name": "down", "id": k + 1, "pose": {"rpy_deg": [0, 90, 0]}}]}
    nodes: dict = {"d0": {"system_id": 1, "autopilot": {"url": f"udpout:127.0.0.1:{ap_port}"},
                          "peers": [f"udpin:127.0.0.1:{peer_port}"], "status_interval_s": 60},
                   "world": {"system_id": 50}}  # fmt: skip
    nodes.update({f"d{k}": {"system_id": 50 + k} for k in range(1, N_DRONES)})
    return {"entities": ents, "nodes": nodes}


def views(world, k: int) -> list[MarkerData]:
    """Drone k's view of its 4 world markers (constant: the drones hover), capture time and seq 0."""
    T_world_drone = RigidTransform.from_components([1.0 + k % 5, 1.0 + k // 5, 1.5], Rotation.identity())
    s = world.sensors[k + 1]
    out = []
    for j in range(MARKERS):
        if k == 0:  # the ceiling camera sees d0's markers
            m = world.markers[100 + j]
            T = s.T_entity_sensor.inv() * T_world_drone * m.T_entity_marker
        else:
            m = world.markers[(4 * k + j) % 40]
            T = (T_world_drone * s.T_entity_sensor).inv() * m.T_entity_marker
        x, y, z, w = T.rotation.as_quat()
        p = T.translation
        cov = detection_covariance(T, m.size_m)
        out.append(MarkerData(k + 1, m.id, 0.01, (p[0], p[1], p[2]), (w, x, y, z), 0, origin=50 + k, covariance=cov))
    return out


def load(port: int, world, seconds: float, fingerprint: int, stop: threading.Event, split: bool = False) -> int:
    """Send 10 drones x 30 Hz x 4 markers; each drone its own system id. Returns observations sent.

    The views are computed once (the drones hover) and encoded once: each frame only stamps the
    capture time (now, just before sending) and the sequence number, so the generator measures the
    node and not its own geometry. Each drone's image goes in one datagram, as nodes send them
    (``split``: one datagram per observation, as nodes sent them before).
    """
    d = dialect.load()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mavs = [d.MAVLink(None, srcSystem=50 + k, srcComponent=197) for k in range(N_DRONES)]
    msgs = [[codec.encode_observation(d, md, fingerprint) for md in views(world, k)] for k in range(N_DRONES)]
    period = 1.0 / RATE_HZ
    sent = 0
    t_end = time.time() + seconds
    frame = 0
    next_t = time.time()
    while time.time() < t_end and not stop.is_set():
        for k in range(N_DRONES):
            t_us = int(time.time() * 1e6)
            image = b""
            for j, msg in enumerate(msgs[k]):
                # As a node sends an image's observations: each says how many of the image follow.
                msg.time_usec, msg.seq, msg.frame_remaining = t_us, (frame * MARKERS + j) & 0xFFFF, MARKERS - 1 - j
                packed = msg.pack(mavs[k], force_mavlink1=False)
                if split:
                    sock.sendto(packed, ("127.0.0.1", port))
                else:
                    image += packed
                sent += 1
            if image:
                sock.sendto(image, ("127.0.0.1", port))
        frame += 1
        next_t += period
        time.sleep(max(next_t - time.time(), 0))
    sock.close()
    return sent


def relay_process(in_port: int, ap_port: int, ready: Any, stop: Any) -> None:
    """The anchor: a process that decodes every observation of the same load with pymavlink (as a
    node's link does) and forwards each image of d0 to the autopilot at once, one message when its
    last observation is in (the node sends one pose per image), with no graph in between."""
    d = dialect.load()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", in_port))
    sock.settimeout(0.05)
    rx = d.MAVLink(None)
    tx = d.MAVLink(None, srcSystem=1, srcComponent=197)
    ready.set()
    while not stop.is_set():
        try:
            data = sock.recv(65535)
        except TimeoutError:
            continue
        for msg in rx.parse_buffer(data) or []:
            if msg.get_type() == "ATLAS_OBSERVATION" and msg.sensor_id == 1 and msg.frame_remaining == 0:
                out = d.MAVLink_vision_position_estimate_message(msg.time_usec, 0, 0, 0, 0, 0, 0, [0.0] * 21, 0)
                sock.sendto(out.pack(tx), ("127.0.0.1", ap_port))


def latencies_ms(recs: list, windows: list[tuple[float, float]]) -> np.ndarray:
    """Capture-to-arrival latency (ms) of the autopilot messages that arrived within the windows."""
    return np.array([(r.arrival_s * 1e6 - r.usec) / 1e3 for r in recs if any(a <= r.arrival_s < b for a, b in windows)])


def summary(lat_ms: np.ndarray) -> tuple[float, float, float, float]:
    """Mean, median, p95 and p99 (ms) of latencies, NaN for none."""
    if lat_ms.size == 0:
        return (float("nan"),) * 4
    return float(lat_ms.mean()), *(float(v) for v in np.percentile(lat_ms, [50, 95, 99]))


def main() -> int:
    ap_ = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap_.add_argument("--seconds", type=float, default=12.5, help="load time for each of node and anchor")
    ap_.add_argument("--block", type=float, default=2.5, help="seconds per block (node and anchor alternate)")
    ap_.add_argument("--split", action="store_true", help="one datagram per observation (default: per image)")
    args = ap_.parse_args()
    # The load generator and the autopilots' receivers share this process: keep the GIL hand-over short
    # (arrivals are stamped by the kernel anyway; both node and anchor are measured the same way).
    sys.setswitchinterval(0.0002)
    with tempfile.TemporaryDirectory() as tmp, recording():
        peer_port, relay_port = free_port(), free_port()
        ap = SimAutopilot(system_id=1).start()
        ap_anchor = SimAutopilot(system_id=1).start()
        path = Path(tmp) / "world.yaml"
        path.write_text(yaml.safe_dump(world_doc(peer_port, ap.port)))
        world = load_world(path)
        log = open(Path(tmp) / "node.log", "wb")
        node = subprocess.Popen(
            [sys.executable, "-m", "atlas_onboard", "run", "--config", str(path), "--entity", "d0"],
            stdout=log, stderr=subprocess.STDOUT, env={**os.environ},
        )  # fmt: skip
        ctx = mp.get_context("spawn")
        ready, stop_relay = ctx.Event(), ctx.Event()
        relay = ctx.Process(target=relay_process, args=(relay_port, ap_anchor.port, ready, stop_relay))
        relay.start()
        deadline = time.time() + 30
        while not ap.heartbeats_from and time.time() < deadline:
            time.sleep(0.05)
        ready.wait(30)
        # Node and anchor take the load in alternate blocks, so that both see the machine in the same
        # state (this machine's speed drifts by up to 2x within minutes); the first WARMUP_S of each
        # block is not counted (the node has just lost its pose for want of observations).
        windows: dict[str, list[tuple[float, float]]] = {"node": [], "anchor": []}
        sent = {"node": 0, "anchor": 0}
        cpu = 0.0
        n_blocks = max(1, round(args.seconds / args.block))
        stop = threading.Event()
        for _ in range(n_blocks):
            for who, port in (("node", peer_port), ("anchor", relay_port)):
                t0 = time.time()
                cpu0 = cpu_s(node.pid)
                sent[who] += load(port, world, args.block, world.fingerprint(), stop, args.split)
                t1 = time.time()
                if who == "node":
                    cpu += cpu_s(node.pid) - cpu0
                windows[who].append((t0 + WARMUP_S, t1 + 0.1))
                time.sleep(0.15)  # the last messages of the block arrive
        stop_relay.set()
        relay.join(5)
        node.send_signal(signal.SIGTERM)
        node.wait(timeout=10)
        log.close()
        recs, recs_anchor = ap.snapshot(), ap_anchor.snapshot()
        ap.stop()
        ap_anchor.stop()
        final = [ln for ln in (Path(tmp) / "node.log").read_text().splitlines() if " final " in ln]
    counters = dict(p.split("=", 1) for p in final[-1].split(" final ", 1)[1].split()) if final else {}
    lat, anchor = latencies_ms(recs, windows["node"]), latencies_ms(recs_anchor, windows["anchor"])
    accepted = int(counters.get("accepted", 0))
    stats, a_stats = summary(lat), summary(anchor)
    overhead = stats[1] - a_stats[1]
    node_s = n_blocks * args.block
    rate = sent["node"] / node_s
    node_cpu = cpu / node_s * 100
    print(f"load: {N_DRONES} drones x {RATE_HZ} Hz x {MARKERS} markers = {rate:.0f} observations/s,"
          f" {n_blocks} blocks of {args.block:.1f} s each for node and anchor, alternating;"
          f" {'a datagram per observation' if args.split else 'a datagram per image'}")  # fmt: skip
    dropped = counters.get("inbox_dropped", "?")
    superseded = int(counters.get("superseded", 0))
    print(f"node received {counters.get('peer0_rx_atlas_observation', '?')} of {sent['node']}: accepted {accepted},"
          f" superseded {superseded} (a newer one of the same edge came first), inbox dropped {dropped};"
          f" autopilot messages {len(recs)} ({len(recs) / node_s:.1f}/s); node CPU {node_cpu:.0f} %")  # fmt: skip
    print(f"{'':28} {'mean ms':>8} {'median ms':>10} {'p95 ms':>8} {'p99 ms':>8} {'samples':>8}")
    print(f"{'node (observation -> AP)':28} {stats[0]:>8.3f} {stats[1]:>10.3f} {stats[2]:>8.3f} {stats[3]:>8.3f}"
          f" {lat.size:>8}")  # fmt: skip
    print(f"{'anchor (decode all, resend)':28} {a_stats[0]:>8.3f} {a_stats[1]:>10.3f} {a_stats[2]:>8.3f}"
          f" {a_stats[3]:>8.3f} {anchor.size:>8}")  # fmt: skip
    d = [n - a for n, a in zip(stats, a_stats, strict=True)]
    print(f"{'overhead (node - anchor)':28} {d[0]:>8.3f} {d[1]:>10.3f} {d[2]:>8.3f} {d[3]:>8.3f}")
    print(f"BAR node_overhead_median {overhead:.3f} ms 2.0 {'pass' if overhead <= 2.0 else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
