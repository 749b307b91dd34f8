"""Soak: N node processes (default 10) on loopback for a set time, fed 30 Hz observations of every
drone (``--markers`` per frame, default 4) through a hub, each node with a simulated autopilot.
Every node receives every drone's observations, as on a real mesh. The load generator and the hub
(the mesh) run in processes of their own, the autopilots in this one (they timestamp arrivals in
the kernel). Prints resident memory of every node over time,
dropped-message counters, the longest gap between autopilot messages while observations flow, and
CPU per node.

    python benchmarks/soak.py [--nodes 10] [--minutes 10]

Also prints each node's 99th percentile wait, and the seconds of the run in which waits over the
bar began, with how many nodes had one then.

Bars: memory growth < 5 % (first sample after warm-up to the last), no autopilot gap > 100 ms,
no observation dropped from a bounded queue (the node's queues, and its sockets' receive buffers,
whose drops the kernel counts).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform, Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import itertools

from atlas_onboard.config import load_world
from atlas_onboard.core.markerdata import MarkerData, matrix_to_upper
from atlas_onboard.detector import pose
from atlas_onboard.mavlink import codec, dialect
from atlas_onboard.sim.autopilot import SimAutopilot, recording
from atlas_onboard.sim.hub import Hub

RATE_HZ = 30
WORLD_SYSTEM_ID = 100  # the world's node: the ceiling cameras' observations come from it
DRONE_MARKERS = 300  # drone k's markers are DRONE_MARKERS + per * k + j


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def detection_covariance(T_sensor_marker: RigidTransform, size_m: float) -> tuple[float, ...]:
    """The 6x6 covariance a camera's detector reports with such a view (a 640x480 camera, 0.1 px
    corners), so that the load carries what real observations carry on the wire."""
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    seen = pose.CornerFit(
        T_sensor_marker.rotation.as_matrix(), T_sensor_marker.translation, pose.object_corners(size_m), K
    )
    C = pose.pose_covariance(seen, 0.1, 0.05)
    return matrix_to_upper(C) if C is not None else ()


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def load(path: Path, hub_port: int, n: int, per: int, stop: Any, sent: Any, log: Path) -> None:
    """Send every drone's observations of its ``per`` markers at 30 Hz until ``stop`` is set; the
    wall-clock time each drone's frame went out is saved to ``log`` (frames x drones)."""
    world = load_world(path)
    d = dialect.load()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # Drone k is seen by ceiling camera k, run by the world's node (system 100): a node accepts no
    # observation of its own cameras from the network, so its own pose comes from another's camera.
    mavs = [d.MAVLink(None, srcSystem=WORLD_SYSTEM_ID, srcComponent=197)] * n
    fp = world.fingerprint()
    period = 1.0 / RATE_HZ
    # The drones hover: what each camera sees is computed once (computing it for every frame made
    # the generator, not the nodes, the bottleneck: it sent under 100 observations/s).
    # Each message is encoded once; a frame only stamps the capture time, the sequence number and
    # how many of the drone's image follow (as a node sends them).
    views = []
    for k in range(n):
        T_wd = RigidTransform.from_components([1.0 + k % 5, 1.0 + k // 5, 1.5], Rotation.identity())
        T_sw = world.sensors[k + 1].T_entity_sensor.inv()
        for j in range(per):
            m = world.markers[DRONE_MARKERS + per * k + j]
            T = T_sw * T_wd * m.T_entity_marker
            x, y, z, w = T.rotation.as_quat()
            md = MarkerData(k + 1, m.id, 0.01, tuple(T.translation), (w, x, y, z), 0, frame_remaining=per - 1 - j,
                            covariance=detection_covariance(T, m.size_m))  # fmt: skip
            views.append((k, codec.encode_observation(d, md, fp)))
    nxt = time.time()
    seq = 0
    times: list[list[float]] = []
    while not stop.is_set():
        times.append([0.0] * n)
        for k in range(n):
            # One datagram per image, as a node sends its accepted detections (Link.send_many).
            image, t_us = b"", int(time.time() * 1e6)
            for _, msg in views[k * per : (k + 1) * per]:
                seq = (seq + 1) & 0xFFFF
                msg.time_usec, msg.seq = t_us, seq
                image += msg.pack(mavs[k])
            sock.sendto(image, ("127.0.0.1", hub_port))
            times[-1][k] = time.time()
        with sent.get_lock():
            sent.value += len(views)
        nxt += period
        time.sleep(max(nxt - time.time(), 0.0))
    np.save(log, np.array(times))


def run_hub(port: Any, clients: Any, stop: Any) -> None:
    """The mesh (:class:`Hub`) in a process of its own: in this one it shared the interpreter with
    the ten autopilots and the sampling, and stalled now and then for up to 75 ms, holding every
    node's input at once (seen as simultaneous gaps of all nodes while the generator kept sending).
    On drones the network does this work, not their computers. ``clients`` counts the nodes it knows."""
    hub = Hub().start()
    port.value = hub.port
    while not stop.is_set():
        clients.value = len(hub.clients)
        time.sleep(0.05)
    hub.stop()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=10)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--markers", type=int, default=4, help="markers each drone's camera sees per frame")
    args = ap.parse_args()
    sys.setswitchinterval(0.0002)
    n = args.nodes
    hub_port, hub_clients, hub_stop = (
        multiprocessing.Value("i", 0),
        multiprocessing.Value("i", 0),
        multiprocessing.Event(),
    )
    hub = multiprocessing.Process(target=run_hub, args=(hub_port, hub_clients, hub_stop), daemon=True)
    hub.start()  # before this process has threads of its own
    while not hub_port.value:
        time.sleep(0.01)
    aps = [SimAutopilot(system_id=k + 1).start() for k in range(n)]
    per = args.markers
    markers = [{"id": i, "size_m": 0.2, "pose": {"pos": [float(i % 8), float(i // 8), 0.0]}} for i in range(per * n)]
    ceilings = [{"name": f"ceiling{k}", "id": k + 1, "pose": {"pos": [1.0 + k % 5, 1.0 + k // 5, 4.0],
                 "rpy_deg": [0, 90, 0]}} for k in range(n)]  # fmt: skip
    ents: dict = {"world": {"markers": markers, "sensors": ceilings}}
    for k in range(n):
        on_top = [{"id": DRONE_MARKERS + per * k + j, "size_m": 0.1, "pose": {"pos": [0.12 * j - 0.2, 0.0, 0.05]}}
                  for j in range(per)]  # fmt: skip
        ents[f"d{k}"] = {"markers": on_top}
    nodes = {f"d{k}": {"system_id": k + 1, "autopilot": {"url": f"udpout:127.0.0.1:{aps[k].port}"}} for k in range(n)}
    nodes["world"] = {"system_id": WORLD_SYSTEM_ID}
    # Every camera's observations come from the one world node: its rate is every drone's together.
    peer = {"url": f"udpout:127.0.0.1:{hub_port.value}", "rate_limit_hz": 10 * RATE_HZ * per * n}
    nodes["defaults"] = {"peers": [peer], "status_interval_s": 30, "queue_size": 256}
    with tempfile.TemporaryDirectory() as tmp, recording():
        path = Path(tmp) / "world.yaml"
        path.write_text(yaml.safe_dump({"entities": ents, "nodes": nodes}))
        load_world(path)  # a bad world file fails here, before any process starts
        procs = {
            name: subprocess.Popen(
                [sys.executable, "-m", "atlas_onboard", "run", "--config", str(path), "--entity", name],
                stdout=open(Path(tmp) / f"{name}.log", "wb"), stderr=subprocess.STDOUT,
            )
            for name in (f"d{k}" for k in range(n))
        }  # fmt: skip
        while hub_clients.value < n:
            time.sleep(0.1)
        # The load: every drone's camera sees its markers at 30 Hz, sent into the mesh by a "camera"
        # peer in a process of its own, so the measuring threads here never stall it.
        stop = multiprocessing.Event()
        sent = multiprocessing.Value("q", 0)
        sends_log = Path(tmp) / "sends.npy"
        gen = multiprocessing.Process(
            target=load, args=(path, hub_port.value, n, per, stop, sent, sends_log), daemon=True
        )
        gen.start()
        t0 = time.time()
        cpu0 = sum(os.times()[:2])
        duration = args.minutes * 60
        samples = []
        print(f"{'t s':>6} " + " ".join(f"{name:>7}" for name in procs) + "   (resident MB)")
        warm = None
        while time.time() - t0 < duration:
            time.sleep(min(30.0, max(duration / 20, 2.0)))
            row = [rss_kb(p.pid) / 1024 for p in procs.values()]
            samples.append(row)
            if warm is None and time.time() - t0 > min(60, duration / 5):
                warm = row
            print(f"{time.time() - t0:>6.0f} " + " ".join(f"{v:>7.1f}" for v in row), flush=True)
        stop.set()
        gen.join(timeout=10)
        elapsed = time.time() - t0
        cpu = {name: cpu_s(p.pid) / elapsed * 100 for name, p in procs.items()}
        hub_cpu = cpu_s(hub.pid) / elapsed * 100
        own_cpu = (sum(os.times()[:2]) - cpu0) / elapsed * 100
        for p in procs.values():
            p.send_signal(signal.SIGTERM)
        for p in procs.values():
            p.wait(timeout=20)
        finals = {}
        for name in procs:
            lines = [ln for ln in (Path(tmp) / f"{name}.log").read_text().splitlines() if " final " in ln]
            finals[name] = dict(x.split("=", 1) for x in lines[-1].split(" final ", 1)[1].split()) if lines else {}
        sends = np.load(sends_log)
    # Two figures per node, over [t0 + 5 s, end - 1 s]: the longest gap between autopilot messages,
    # and the longest gap while observations flow: the longest an observation of the drone waited
    # for the next autopilot message. A stall of the load generator (or of the whole machine before
    # anything was sent) shows in the first and not in the second; a node that sits on its input
    # shows in both.
    gaps, waits, p99s, late = [], [], [], []
    lo, hi = t0 + 5, t0 + elapsed - 1
    for k, a in enumerate(aps):
        t = np.array(sorted(r.arrival_s for r in a.snapshot() if lo < r.arrival_s < hi))
        gaps.append(max((b - x for x, b in itertools.pairwise(t)), default=float("inf")))
        s_k = sends[:, k][(sends[:, k] > lo) & (sends[:, k] < hi - 0.5)]
        nxt = np.searchsorted(t, s_k)
        w = t[nxt] - s_k if len(s_k) and nxt.max() < len(t) else np.array([np.inf])
        waits.append(float(np.max(w)))
        p99s.append(float(np.percentile(w, 99)))
        late += [(round(float(x) - t0, 1), k) for x in s_k[w > 0.1]] if len(w) == len(s_k) else []
        a.stop()
    hub_stop.set()
    hub.join(timeout=5)
    warm = warm or samples[0]
    growth = max((last - first) / first * 100 for first, last in zip(warm, samples[-1], strict=True))
    dropped = sum(int(f.get("inbox_dropped", 0)) for f in finals.values())
    kernel = sum(int(f.get("peer0_kernel_drops", 0)) for f in finals.values())
    print(
        f"load: {sent.value / elapsed:.0f} observations/s into the mesh for {elapsed:.0f} s;"
        " each node receives them all"
    )
    print(f"the hub: {hub_cpu:.1f} % CPU; the autopilots (this process): {own_cpu:.1f} % CPU")
    print("node   cpu %  received  kernel_drops  accepted  superseded  rejected  inbox_dropped  longest AP gap ms"
          "  longest wait ms  p99 wait ms")  # fmt: skip
    for (name, f), gap, wait, p99 in zip(finals.items(), gaps, waits, p99s, strict=True):
        acc, drop, sup = f.get("accepted", "?"), f.get("inbox_dropped", "?"), f.get("superseded", "?")
        rx, lost = f.get("peer0_rx_atlas_observation", "?"), f.get("peer0_kernel_drops", "0")
        rej = sum(int(v) for k, v in f.items() if "rejected_" in k)
        print(f"{name:>5} {cpu[name]:>6.1f} {rx:>9} {lost:>13} {acc:>9} {sup:>11} {rej:>9} {drop:>14}"
              f" {gap * 1000:>18.1f} {wait * 1000:>16.1f} {p99 * 1000:>12.1f}")  # fmt: skip
    reasons: dict[str, int] = {}
    for f in finals.values():
        for k, v in f.items():
            if "rejected_" in k and int(v):
                reasons[k] = reasons.get(k, 0) + int(v)
    print("rejections, all nodes:", " ".join(f"{k}={v}" for k, v in sorted(reasons.items())) or "none")
    print(f"longest gap between autopilot messages, any cause: {max(gaps) * 1000:.1f} ms")
    # Waits over the bar, by the second they began in: how many nodes had one then (all of them at
    # once points at the machine or the mesh, one alone at that node).
    when: dict[int, set[int]] = {}
    for t, k in late:
        when.setdefault(int(t), set()).add(k)
    print("waits over 100 ms, by second of the run (nodes):",
          " ".join(f"{t}s({len(ks)})" for t, ks in sorted(when.items())) or "none")  # fmt: skip
    worst_gap = max(waits) * 1000
    print(f"BAR soak_memory_growth {growth:.2f} percent 5 {'pass' if growth < 5 else 'fail'}")
    print(f"BAR soak_longest_output_gap {worst_gap:.1f} ms 100 {'pass' if worst_gap <= 100 else 'fail'}")
    print(f"BAR soak_inbox_dropped {dropped} count 0 {'pass' if dropped == 0 else 'fail'}")
    print(f"BAR soak_socket_dropped {kernel} count 0 {'pass' if kernel == 0 else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
