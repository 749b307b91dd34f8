"""Shared cases of the config tests: a small world file, its node settings, and the command's entry point."""

import subprocess
import sys
from pathlib import Path

from atlas_onboard.cli import main

REPO = Path(__file__).resolve().parents[2]

BASE = """\
version: 1
conventions: {world: ENU, body: FLU}
fusion: {edge_timeout_s: 0.25, ema_alpha: 0.5, weighting: sigma_min}
entities:
  world:
    markers:
      - {id: 0, size_m: 0.18, pose: {pos: [0, 0, 0]}}
  drone1:
    sensors:
      - name: front
        id: 1
        pose: {pos: [0.1, 0, 0], rot: {w: 1, x: 0, y: 0, z: 0}}
    markers:
      - {id: 10, size_m: 0.1, pose: {pos: [0, 0, 0.05]}}
  drone2:
    sensors:
      - {name: front, id: 2, pose: {pos: [0.1, 0, 0]}}
"""


def run_cli(*args, cwd=None):
    """The installed command in its own interpreter (as a user runs it)."""
    return subprocess.run(
        [sys.executable, "-m", "atlas_onboard", *args], capture_output=True, text=True, timeout=60, cwd=cwd, check=False
    )


def cli(capsys, *args):
    """The command's entry point in this process (the same ``main`` as the console script): exit
    status, stdout, stderr. An uncaught exception would fail the test, as a traceback would."""
    try:
        code = main(list(args))
    except SystemExit as exc:  # argparse's own exits
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


NODES = (
    BASE
    + """\
nodes:
  defaults:
    autopilot: {url: "udpout:127.0.0.1:14540", rate_hz: 20}
    peers: ["udpin:0.0.0.0:14600", {url: "udpout:127.0.0.1:14601", tunnel: true}]
  drone1:
    system_id: 11
    autopilot: {output: odometry}
  drone2:
    system_id: 12
    fused_rate_hz: 2
"""
)
