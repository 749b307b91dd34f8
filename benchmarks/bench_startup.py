"""Node start-up: what every end-to-end test, every simulated drone and every systemd restart pays.

Three states, interleaved in one run on the same machine (no camera, one peer link, a simulated
autopilot on 127.0.0.1):

- ``floor``: the interpreter importing numpy and ``scipy.spatial.transform`` (which the configuration
  needs for every pose) and exiting: what no node start can avoid;
- ``full-parser``: a node started after building the parser of every subcommand (what ``run`` did
  before it built only the built-in commands): ``cli.build_parser()`` then ``cli.main(run ...)``;
- ``node``: ``python -m atlas_onboard run``, as systemd and the tests start it;
- ``source`` and ``bytecode``: the same node from a copy of the package without its bytecode and with
  it (compiled beforehand), bytecode never written (PYTHONDONTWRITEBYTECODE): what each start costs
  where nothing may write ``__pycache__`` (containers, the test suite's processes) and what it costs
  once the package is compiled (what tests/conftest.py does before the suite's processes start).

Per state: wall time from spawn to the first heartbeat at the autopilot (the floor: to its exit) and
the process's CPU time over its whole life (it is stopped right after that heartbeat). Ratios against
the floor, mean, median and p95. Usage: ``python benchmarks/bench_startup.py [--runs N]``.
"""

from __future__ import annotations

import argparse
import compileall
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from atlas_onboard.sim.autopilot import SimAutopilot

FLOOR = "import numpy, scipy.spatial.transform"
FULL_PARSER = "import sys\nfrom atlas_onboard import cli\ncli.build_parser()\nsys.exit(cli.main(sys.argv[1:]))\n"
BAR_CPU_RATIO = 1.5  # proposed: the node's own modules and start within half of what no start can avoid


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _world(path: Path, autopilot_port: int) -> Path:
    doc = {
        "entities": {
            "world": {"sensors": [{"name": "ceiling", "id": 10, "pose": {"pos": [0, 0, 4]}}]},
            "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
        },
        "nodes": {
            "d1": {
                "system_id": 1,
                "autopilot": {"url": f"udpout:127.0.0.1:{autopilot_port}"},
                "peers": [f"udpin:127.0.0.1:{_free_udp_port()}"],
            },
            "world": {"system_id": 250},
        },
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


PACKAGE = Path(__file__).resolve().parents[1] / "atlas_onboard"
COPIES = ("source", "bytecode")  # the states that run a copy of the package


def _copies(tmp: Path) -> None:
    """``tmp``/source/atlas_onboard without bytecode, ``tmp``/bytecode/atlas_onboard compiled."""
    for name in COPIES:
        shutil.copytree(PACKAGE, tmp / name / "atlas_onboard", ignore=shutil.ignore_patterns("__pycache__"))
    compileall.compile_dir(tmp / "bytecode" / "atlas_onboard", quiet=1)


def one(state: str, tmp: Path) -> tuple[float, float]:
    """(wall s to the first heartbeat or exit, process CPU s) of one start in ``state``."""
    cpu0 = _children_cpu_s()
    if state == "floor":
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", FLOOR], check=True)
        return time.perf_counter() - t0, _children_cpu_s() - cpu0
    ap = SimAutopilot(system_id=1).start()
    try:
        world = _world(tmp / "world.yaml", ap.port)
        run = ["run", "--config", str(world), "--entity", "d1"]
        head = ["-c", FULL_PARSER] if state == "full-parser" else ["-m", "atlas_onboard"]
        # A copy runs from its directory (``-m`` puts the working directory first on the path).
        cwd, env = (tmp / state, {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}) if state in COPIES else (None, None)
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, *head, *run], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=cwd, env=env
        )
        while ap.heartbeats_from.get((1, 197), 0) == 0:
            if proc.poll() is not None or time.perf_counter() - t0 > 60:
                raise SystemExit(f"{state}: the node did not come up (exit {proc.poll()})")
            time.sleep(0.005)
        wall = time.perf_counter() - t0
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    finally:
        ap.stop()
    return wall, _children_cpu_s() - cpu0


def _stats(x: list[float]) -> str:
    a = np.array(x)
    return f"mean {a.mean():.3f} median {np.median(a):.3f} p95 {np.percentile(a, 95):.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="starts per state (interleaved)")
    args = parser.parse_args()
    states = ("floor", "full-parser", "node", *COPIES)
    wall: dict[str, list[float]] = {s: [] for s in states}
    cpu: dict[str, list[float]] = {s: [] for s in states}
    with tempfile.TemporaryDirectory(prefix="atlas-bench-startup-") as tmp:
        _copies(Path(tmp))
        for _ in range(args.runs):
            for s in states:
                w, c = one(s, Path(tmp))
                wall[s].append(w)
                cpu[s].append(c)
    print(f"node start-up, {args.runs} starts per state, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    floor_cpu = float(np.median(cpu["floor"]))
    for s in states:
        print(f"{s:12s} wall s: {_stats(wall[s])}")
        ratio = np.median(cpu[s]) / floor_cpu
        print(f"{s:12s} CPU s:  {_stats(cpu[s])}  (median {ratio:.2f} x the floor)")
    saved = np.median(cpu["full-parser"]) - np.median(cpu["node"])
    print(f"CPU a start saves against building every command's parser: {saved:.3f} s (median)")
    saved = np.median(cpu["source"]) - np.median(cpu["bytecode"])
    print(f"CPU a start saves with the package compiled beforehand: {saved:.3f} s (median)")
    ratio = float(np.median(cpu["node"]) / floor_cpu)
    print(
        f"BAR node_start_cpu_over_floor {ratio:.2f} x {BAR_CPU_RATIO:g} {'pass' if ratio <= BAR_CPU_RATIO else 'fail'}"
    )


if __name__ == "__main__":
    main()
