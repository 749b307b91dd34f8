"""Regenerate docs/results.md from one run of the benchmarks: never edit that file by hand.

Each benchmark is run as its own command line, one after another, and its whole output is written to
docs/results.md under the command that printed it, with the date, the machine and how long it took;
a table of every ``BAR`` line comes first, and the same lines end its output (named after their
benchmark). A benchmark that fails or is not run says so in the file.

    python benchmarks/results.py                    # every benchmark at its documented length
    python benchmarks/results.py --only graph,node  # some of them (the others keep no old figures)
    python benchmarks/results.py --out /tmp/r.md    # somewhere else

Run it on an otherwise idle machine: the simulations run in real time.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BAR_RE = re.compile(r"^BAR (\S+) (\S+) (\S+) (\S+) (pass|fail)$")


@dataclass(frozen=True)
class Bench:
    name: str
    argv: tuple[str, ...]
    about: str


BENCHES = (
    Bench("sim", ("atlas-onboard", "sim"), "The default simulation: six drones, two ceiling cameras."),
    Bench(
        "methods",
        ("benchmarks/compare_methods.py", "--duration", "10", "--methods", "paper,default,ekf,dijkstra"),
        "The paper's method, the defaults and the EKF in every scenario.",
    ),
    Bench(
        "hard",
        ("benchmarks/bench_hard.py",),
        "The hard scenarios: textured floor, tags across the border, gaps; every fusion setting, the moved"
        " marker (with and without live refinement) and, on hard-near, real-time replays.",
    ),
    Bench("attack", ("benchmarks/attack.py",), "A hostile peer against a node with a live camera path."),
    Bench("detector", ("benchmarks/bench_detector.py",), "The detector against the AprilTag library, per state."),
    Bench("turns", ("benchmarks/bench_turns.py",), "Tracking through turns, with and without the attitude."),
    Bench("graph", ("benchmarks/bench_graph.py",), "The transform graph's evaluation time against a naive anchor."),
    Bench("node", ("benchmarks/bench_node.py",), "The node's overhead from observation to autopilot message."),
    Bench("latency", ("benchmarks/bench_latency.py",), "Latency steadiness with the rate cap at the camera's rate."),
    Bench("pi", ("benchmarks/bench_pi.py",), "Detector and node on one core, scaled to Pi 4 / Pi 5 class cores."),
    Bench("map", ("benchmarks/bench_map.py",), "The marker map from a simulated flight."),
    Bench("refine", ("benchmarks/bench_refine.py",), "Live map refinement: one marker 10 cm off in the world file."),
    Bench("land", ("benchmarks/bench_land.py",), "Precision landing: touchdown error, static pad and moving rover."),
    Bench("moved", ("benchmarks/bench_moved_offline.py",), "A marker moved 10 cm in the world file, scored offline."),
    Bench("startup", ("benchmarks/bench_startup.py",), "The node's start-up CPU against the interpreter's floor."),
)


def command(bench: Bench) -> list[str]:
    """The command line of ``bench``: scripts run with this interpreter, console scripts as installed."""
    first = bench.argv[0]
    if first.endswith(".py"):
        return [sys.executable, str(REPO / first), *bench.argv[1:]]
    return [first, *bench.argv[1:]]


def run(bench: Bench) -> tuple[str, int | None, float]:
    """(output, exit status or None if the script does not exist, seconds)."""
    argv = command(bench)
    if argv[0] == sys.executable and not Path(argv[1]).exists():
        return f"{bench.argv[0]} does not exist in this checkout\n", None, 0.0
    t0 = time.monotonic()
    proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, check=False)
    out = proc.stdout + (f"\n(stderr)\n{proc.stderr}" if proc.returncode != 0 and proc.stderr else "")
    return out, proc.returncode, time.monotonic() - t0


def render(results: list[tuple[Bench, str, int | None, float]], started: str) -> str:
    lines = [
        "# Results",
        "",
        "Written by `python benchmarks/results.py` from one run; do not edit by hand (run it again).",
        f"Run started {started} on {platform.node() or 'this machine'}: {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, {platform.platform()}.",
        "",
        "## Bars",
        "",
        "| benchmark | bar | value | unit | limit | verdict |",
        "|---|---|---:|---|---:|---|",
    ]
    for bench, out, status, _ in results:
        bars = [m.groups() for m in map(BAR_RE.match, out.splitlines()) if m]
        for name, value, unit, limit, verdict in bars:
            lines.append(f"| {bench.name} | {name} | {value} | {unit} | {limit} | {verdict} |")
        if not bars:
            why = "not run: the script is missing" if status is None else f"no BAR line (exit status {status})"
            lines.append(f"| {bench.name} | - | - | - | - | {why} |")
    for bench, out, status, seconds in results:
        lines += ["", f"## {bench.name}", "", bench.about, "", f"    {shlex.join(bench.argv)}", ""]
        state = "not run" if status is None else f"exit status {status}, {seconds:.0f} s"
        lines += [f"({state})", "", "```", out.rstrip("\n"), "```"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="comma-separated names: " + ",".join(b.name for b in BENCHES))
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results.md")
    args = ap.parse_args(argv)
    wanted = [b for b in BENCHES if not args.only or b.name in args.only.split(",")]
    unknown = set(filter(None, args.only.split(","))) - {b.name for b in BENCHES}
    if unknown:
        print(f"results.py: error: unknown benchmark(s): {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    results = []
    for bench in wanted:
        print(f"running {bench.name}: {shlex.join(bench.argv)}", flush=True)
        out, status, seconds = run(bench)
        results.append((bench, out, status, seconds))
        print(f"  done in {seconds:.0f} s (exit status {status})", flush=True)
    args.out.write_text(render(results, started), encoding="utf-8")
    print(f"wrote {args.out}")
    # Every bar the benchmarks measured, as they printed it, named after its benchmark.
    for bench, out, _, _ in results:
        for m in filter(None, map(BAR_RE.match, out.splitlines())):
            name, value, unit, limit, verdict = m.groups()
            print(f"BAR {bench.name}.{name} {value} {unit} {limit} {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
