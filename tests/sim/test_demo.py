"""The README's first run: `atlas-onboard demo DIR`, a simulated autopilot and `atlas-onboard run` on the
demo's world file, as real processes over 127.0.0.1; the poses the autopilot receives are checked
against the ground truth of the rendered hover (DIR/truth.tum)."""

import math
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from atlas_onboard import cli
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.command import autopilot_track
from atlas_onboard.sim.demo import ENTITY, FPS_HZ, SYSTEM_ID, read_truth
from tests.e2e.helpers import NodeProcess, free_udp_port, wait_for

pytestmark = pytest.mark.deadlines  # one node replaying a folder, or an autopilot alone: little CPU

SECONDS = 3.0


def _demo(directory, *args):
    return subprocess.run(
        [sys.executable, "-m", "atlas_onboard", "demo", str(directory), *args],
        check=False, capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def _quiet_since(autopilot):
    """Seconds since the last pose reached the autopilot (0 before the first)."""
    records = autopilot.snapshot()
    return time.time() - records[-1].arrival_s if records else 0.0


def test_demo_world_runs_and_the_autopilot_gets_the_rendered_hover(tmp_path):
    autopilot = SimAutopilot(system_id=SYSTEM_ID).start()
    demo = tmp_path / "demo"
    done = _demo(demo, "--seconds", str(SECONDS), "--autopilot-port", str(autopilot.port))
    assert done.returncode == 0, done.stderr
    world = demo / "world.yaml"
    assert f"atlas-onboard sim-autopilot --port {autopilot.port}" in done.stdout
    assert f"atlas-onboard run --config {world} --entity {ENTITY}" in done.stdout
    n_frames = len(list((demo / "frames").glob("*.png")))
    assert n_frames == math.floor(SECONDS * FPS_HZ)

    node = NodeProcess(world, ENTITY)
    try:
        # The image folder plays once in real time: wait until the node says it reached its end, then
        # until the poses stopped (the last images' poses on their way).
        ended = wait_for(lambda: "end of" in node.log(), timeout=SECONDS + 20)
        ended = ended and wait_for(lambda: _quiet_since(autopilot) > 0.5, timeout=20)
    finally:
        node.stop()
        autopilot.stop()
    assert ended, node.log()[-3000:]
    records = [r for r in autopilot.snapshot() if r.kind == "VISION_POSITION_ESTIMATE"]
    assert len(records) >= 0.8 * n_frames, node.log()[-3000:]
    assert {(r.src_system, r.src_component) for r in records} == {(SYSTEM_ID, 197)}

    track = autopilot_track(records, 0.0)  # back in ENU/FLU
    # Each pose carries its image's capture stamp: the folder's first image plus k / fps.
    k_rel = (track.capture_s - track.capture_s[0]) * FPS_HZ
    assert np.allclose(k_rel, np.round(k_rel), atol=1e-3)
    k_rel = np.round(k_rel).astype(int)
    t_truth, p_truth, q_truth = read_truth(demo / "truth.tum")
    assert len(t_truth) == n_frames
    # Which image the first pose came from is the one unknown (the node's first frames may find no
    # tag yet): take the offset, among the first few images, that best matches the truth.
    best = None
    for k0 in range(0, min(10, n_frames - k_rel[-1])):
        err = np.linalg.norm(track.p_m - p_truth[k0 + k_rel], axis=1)
        if best is None or np.sqrt(np.mean(err**2)) < best[0]:
            best = (float(np.sqrt(np.mean(err**2))), k0, err)
    rmse_m, k0, err_m = best
    # The hover moves far more than the tolerance: a pose that did not follow it could not pass.
    assert np.ptp(p_truth[k0 + k_rel], axis=0)[:2].max() > 0.06
    assert rmse_m < 0.01, (rmse_m, k0)
    assert err_m.max() < 0.03, err_m.max()
    angle_deg = np.degrees(
        (Rotation.from_quat(track.q_xyzw).inv() * Rotation.from_quat(q_truth[k0 + k_rel])).magnitude()
    )
    assert np.median(angle_deg) < 1.0 and angle_deg.max() < 3.0, (np.median(angle_deg), angle_deg.max())


def test_demo_refuses_a_non_empty_directory_in_one_line(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert cli.main(["demo", str(tmp_path), "--seconds", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not empty" in err and "--force" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_sim_autopilot_on_a_busy_port_is_one_line(capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        assert cli.main(["sim-autopilot", "--port", str(port), "--seconds", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"127.0.0.1:{port}" in err, err


def test_sim_autopilot_prints_what_it_receives_and_ends_on_ctrl_c():
    port = free_udp_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "atlas_onboard", "sim-autopilot", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert "listening on udp 127.0.0.1:" in proc.stdout.readline()
        mav = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=197)
        covariance = [0.0] * 21
        covariance[0], covariance[6], covariance[11] = 0.02**2, 0.03**2, 0.05**2
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            heartbeat = mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4
            )
            sock.sendto(heartbeat.pack(mav), ("127.0.0.1", port))
            for k in range(12):
                x_m = 1.0 + 0.01 * k
                msg = mav.vision_position_estimate_encode(1_000_000 + k, x_m, -0.5, -2.0, 0.1, -0.2, 0.3, covariance, 7)
                sock.sendto(msg.pack(mav), ("127.0.0.1", port))
        lines, total, heartbeats = [], 0, 0
        deadline = time.monotonic() + 10
        while total < 12 and time.monotonic() < deadline:
            lines.append(proc.stdout.readline())
            total += int(lines[-1].split("poses")[1].split("/s")[0])
            heartbeats += int(lines[-1].split("heartbeats")[1].split("/s")[0])
        assert total == 12 and heartbeats == 1, lines
        last = next(line for line in reversed(lines) if "NED" in line)
        assert "NED x +1.110 y -0.500 z -2.000 m" in last, last
        assert "roll +5.7 pitch -11.5 yaw +17.2 deg" in last, last
        assert "sigma 20.0/30.0/50.0 mm" in last and "reset_counter 7" in last, last
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130
    assert err == "atlas-onboard: interrupted\n", err


def test_sim_autopilot_lands_on_what_it_receives():
    # With a lander (--land), the vehicle takes LANDING_TARGET in its autopilot's form (PX4: LOCAL_NED)
    # and says where it believes the target is: NED (2, 1, -0.3) is ENU (1, 2, 0.3).
    import io
    import threading

    import numpy as np

    from atlas_onboard.mavlink.landing import px4_landing_target_fields
    from atlas_onboard.sim.demo import run_sim_autopilot
    from atlas_onboard.sim.lander import Lander, LanderSettings

    port, out = free_udp_port(), io.StringIO()
    lander = Lander(LanderSettings("px4"), np.zeros(3))
    runner = threading.Thread(target=run_sim_autopilot, args=(port, 3.0, out, {"lander": lander}))
    runner.start()
    mav = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=197)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for k in range(15):  # over 1.5 s: the listener binds its port when it has started
            time.sleep(0.1)
            fields = px4_landing_target_fields(1_000_000 + k, 2.0, 1.0, -0.3, (1.0, 0.0, 0.0, 0.0))
            sock.sendto(mavlink.MAVLink_landing_target_message(**fields).pack(mav), ("127.0.0.1", port))
    runner.join(timeout=10)
    last = [line for line in out.getvalue().splitlines() if "landing:" in line][-1]
    assert " LANDING_TARGET (0 in another form)" in last and "target ENU (1.000, 2.000, 0.300) m" in last, last
    assert int(last.split("landing: ")[1].split()[0]) > 0, last
