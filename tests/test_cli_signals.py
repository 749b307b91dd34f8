"""The command line in a real subprocess: a reader that closes the pipe early and Ctrl-C end any
subcommand with one line at most and a conventional status, never a traceback."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.deadlines  # commands' processes and their signals, little CPU

EXAMPLE = Path(__file__).resolve().parents[1] / "atlas_onboard" / "data" / "example.yaml"


@pytest.mark.parametrize(("args", "status"), [(["check-config", str(EXAMPLE)], 141)])
def test_a_closed_pipe_ends_the_command_quietly(args, status):
    proc = subprocess.Popen(
        [sys.executable, "-m", "atlas_onboard", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.close()  # the reader is gone before the command writes anything (as `| head -0`)
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == status, err
    assert "Traceback" not in err and "BrokenPipeError" not in err and err == "", err


def test_ctrl_c_is_one_line_and_status_130():
    # A subcommand that blocks (check-config made to wait), interrupted as a terminal's Ctrl-C would.
    code = (
        "import sys, time\n"
        "import atlas_onboard.cli as cli\n"
        "def wait(args):\n"
        "    sys.stderr.write('ready\\n'); sys.stderr.flush(); time.sleep(60)\n"
        "cli._cmd_check_config = wait\n"
        "sys.exit(cli.main(['check-config', 'x.yaml']))\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stderr.readline() == b"ready\n"
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert err.decode() == "atlas-onboard: interrupted\n" and out == b""


def test_the_service_starts_without_the_other_commands_modules():
    """``run`` (every node's start, under systemd and in the simulator) builds only the built-in commands:
    the other commands' modules and what they import (OpenCV, scipy.optimize) stay out of its start-up;
    ``--help`` still lists every command."""
    code = (
        "import sys\n"
        "import atlas_onboard.cli as cli\n"
        "cli._cmd_run = lambda args: print(' '.join(sorted(sys.modules))) or 0\n"
        "sys.exit(cli.main(['-v', 'run', '--config', 'x.yaml']))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    loaded = set(done.stdout.split())
    assert "atlas_onboard.cli" in loaded
    heavy = ("cv2", "scipy.optimize", "atlas_onboard.sim", "atlas_onboard.mapping", "atlas_onboard.cli.detect")
    assert loaded.isdisjoint(heavy), sorted(loaded.intersection(heavy))
    helped = subprocess.run(
        [sys.executable, "-m", "atlas_onboard", "--help"], capture_output=True, text=True, timeout=60, check=False
    )
    assert helped.returncode == 0, helped.stderr
    for command in ("check-config", "run", "sim", "demo", "detect", "markers", "params", "record", "map"):
        assert command in helped.stdout, command


@pytest.mark.realtime  # a simulation's rendering and node processes
def test_a_terminated_sim_stops_its_nodes_and_leaves_no_folders(tmp_path):
    """SIGTERM (systemd, a CI timeout, ``kill``) mid-run: the nodes stopped, the run's and the rendered
    frames' temporary folders removed, status 143, one line; the default action left both folders."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "atlas_onboard", "sim", "--scenario", "paper-test1", "--duration", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    try:
        for line in proc.stderr:  # the progress lines: signal once the nodes run
            if b"starting" in line or b"running" in line:
                break
        runs = list(tmp_path.glob("atlas-sim-paper-test1-*"))
        assert runs and list(tmp_path.glob("atlas-sim-frames-*")), sorted(p.name for p in tmp_path.iterdir())
        logs = sorted(runs[0].glob("*.log"))
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err.decode()
    assert "Traceback" not in err.decode() and "terminated" in err.decode()
    assert list(tmp_path.iterdir()) == [], sorted(p.name for p in tmp_path.iterdir())
    assert logs, "no node had started"
    alive = [c for c in Path("/proc").glob("[0-9]*/cmdline") if _reads(c).find(str(runs[0]).encode()) >= 0]
    assert alive == [], "node processes left running"


def _reads(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError:  # a process that ended meanwhile
        return b""
