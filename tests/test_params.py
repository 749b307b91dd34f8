"""``atlas-onboard params``: the values written against the world file they come from, in the formats
QGroundControl and Mission Planner load (the command itself run once, in a real subprocess)."""

import contextlib
import io
import subprocess
import sys

import pytest

from atlas_onboard.cli import main
from tests.e2e.helpers import write_world


def doc(body="FLU", filt="none", output="vision_position_estimate", system_id=7):
    return {
        "conventions": {"world": "ENU", "body": body},
        "fusion": {"filter": filt},
        "entities": {
            "world": {"markers": [{"id": 1, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}}]},
            "d1": {
                "sensors": [{"name": "down", "id": 10, "pose": {"pos": [0.05, 0, -0.03], "rpy_deg": [0, 90, 0]}}],
                "markers": [{"id": 5, "size_m": 0.1, "pose": {"pos": [0, 0, 0.04]}}],
            },
        },
        "nodes": {"d1": {"system_id": system_id, "autopilot": {"url": "/dev/ttyAMA0,921600", "output": output}}},
    }


def run(tmp_path, world, *args, real_process=False):
    """The command's output: through the command line's ``main`` in this process, or as a real process."""
    argv = ["params", "--config", str(write_world(tmp_path, world)), "--entity", "d1", *args]
    if real_process:
        proc = subprocess.run(
            [sys.executable, "-m", "atlas_onboard", *argv], capture_output=True, text=True, check=False
        )
        assert proc.returncode == 0, proc.stderr
        return proc.stdout
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    assert code == 0, err.getvalue()
    return out.getvalue()


def inproc(tmp_path, world, autopilot, vehicle_id=1, **kw):
    """The same file made in this process (the variants; the subprocess runs check the command)."""
    from atlas_onboard.config import load_node
    from atlas_onboard.params import parameters, render

    w, node = load_node(write_world(tmp_path, world), "d1")
    version = kw.get("ardupilot_version", "4.7")
    return render(parameters(w, node, autopilot, **kw), autopilot, node, w, vehicle_id, version)


def qgc(text):
    """QGroundControl's rows (vehicle, component, name, value, type), comments skipped."""
    rows = [line.split("\t") for line in text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 5 for r in rows)
    return {r[2]: (int(r[0]), int(r[1]), float(r[3]), int(r[4])) for r in rows}


def mission_planner(text):
    rows = [line.split(",") for line in text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 2 for r in rows)
    return {name: float(value) for name, value in rows}


def test_px4_values_follow_the_world_file(tmp_path):
    # The centre of gravity 2 cm behind, 1 cm left of and 5 cm below the entity origin (FLU): the
    # origin is 2 cm ahead (FRD x +0.02), 1 cm right (FRD y +0.01) and 5 cm above (FRD z -0.05) of it.
    argv = ("--autopilot", "px4", "--delay-ms", "25", "--cog-m", "-0.02", "0.01", "-0.05")
    p = qgc(run(tmp_path, doc(), *argv, real_process=True))
    # Loaded onto a new flight controller (system id 1): the rows are for vehicle 1, MAV_SYS_ID the node's.
    assert p["MAV_SYS_ID"] == (1, 1, 7.0, 6)
    offset = (p["EKF2_EV_POS_X"][2], p["EKF2_EV_POS_Y"][2], p["EKF2_EV_POS_Z"][2])
    assert offset == pytest.approx((0.02, 0.01, -0.05))
    assert p["EKF2_EV_CTRL"][2:] == (11.0, 6) and p["EKF2_HGT_REF"][2] == 3 and p["EKF2_EV_DELAY"][2:] == (25.0, 9)
    # Velocity fusion only where PX4 can get it: the EKF filter and ODOMETRY output.
    assert qgc(inproc(tmp_path, doc(filt="ekf"), "px4"))["EKF2_EV_CTRL"][2] == 11
    both = qgc(inproc(tmp_path, doc(filt="ekf", output="odometry"), "px4"))
    assert both["EKF2_EV_CTRL"][2] == 15 and both["EKF2_EV_DELAY"][2] == 0.0  # not measured: PX4's default


def test_ardupilot_values_follow_the_world_file(tmp_path):
    # In an FRD world file the same centre of gravity is written (-0.02, -0.01, 0.05).
    a = mission_planner(
        inproc(tmp_path, doc(body="FRD", system_id=3), "ardupilot", cog_m=(-0.02, -0.01, 0.05), ardupilot_version="4.6")
    )
    assert a["SYSID_THISMAV"] == 3 and a["VISO_TYPE"] == 1 and a["EK3_SRC1_POSXY"] == 6 and a["EK3_SRC1_YAW"] == 6
    assert (a["VISO_POS_X"], a["VISO_POS_Y"], a["VISO_POS_Z"]) == pytest.approx((0.02, 0.01, -0.05))
    assert a["EK3_SRC1_VELXY"] == 0 and a["VISO_DELAY_MS"] == 10  # no filter: no velocity; delay not measured
    assert mission_planner(inproc(tmp_path, doc(filt="ekf"), "ardupilot"))["EK3_SRC1_VELXY"] == 6


def test_px4_file_loads_on_the_flight_controller_it_is_for(tmp_path):
    # QGroundControl loads a file only onto the vehicle named in its Vehicle-Id column: every row names
    # the flight controller's id now (1 new, or --vehicle-id), MAV_SYS_ID carries the node's id.
    fresh = qgc(run(tmp_path, doc(system_id=7), "--autopilot", "px4"))
    assert {row[0] for row in fresh.values()} == {1} and fresh["MAV_SYS_ID"][2] == 7.0
    again = qgc(run(tmp_path, doc(system_id=7), "--autopilot", "px4", "--vehicle-id", "7"))
    assert {row[0] for row in again.values()} == {7} and again["MAV_SYS_ID"][2] == 7.0
    other = qgc(inproc(tmp_path, doc(system_id=9), "px4", vehicle_id=4))
    assert {row[0] for row in other.values()} == {4} and other["MAV_SYS_ID"][2] == 9.0


@pytest.mark.parametrize(
    ("version", "sysid", "gps"),
    [("4.5", "SYSID_THISMAV", "GPS_TYPE"), ("4.6", "SYSID_THISMAV", "GPS1_TYPE"),
     ("4.7", "MAV_SYSID", "GPS1_TYPE"), ("4.8", "MAV_SYSID", "GPS1_TYPE")],
)  # fmt: skip
def test_ardupilot_names_are_the_ones_each_release_reads(tmp_path, version, sysid, gps):
    a = mission_planner(run(tmp_path, doc(system_id=5), "--autopilot", "ardupilot", "--ardupilot-version", version))
    assert a[sysid] == 5 and a[gps] == 0
    stale = {"SYSID_THISMAV", "MAV_SYSID", "GPS_TYPE", "GPS1_TYPE"} - {sysid, gps}
    assert not stale & set(a)


def test_ardupilot_default_is_47_names(tmp_path):
    a = mission_planner(run(tmp_path, doc(system_id=5), "--autopilot", "ardupilot"))
    assert a["MAV_SYSID"] == 5 and "SYSID_THISMAV" not in a


def landing_doc(target="world", marker=1, **kw):
    d = doc(**kw)
    d["entities"]["world"]["markers"][0]["id"] = 1
    d["entities"]["rover"] = {"markers": [{"id": 9, "size_m": 0.2, "pose": {"pos": [0, 0, 0.3]}}]}
    d["nodes"]["d1"]["landing"] = {"target": target, "marker": marker, "autopilot": "ardupilot"}
    return d


def test_ardupilot_precision_landing(tmp_path):
    # AC_PrecLand: PLND_TYPE 1 (MAVLink), the body vector used as sent (ORIENT 25, down), from where the
    # node's vector starts (the entity origin: the same offset as VISO_POS_*), the lag from --delay-ms.
    a = mission_planner(inproc(tmp_path, landing_doc(), "ardupilot", cog_m=(-0.02, 0.01, -0.05), delay_ms=35.0))
    assert (a["PLND_ENABLED"], a["PLND_TYPE"], a["PLND_ORIENT"], a["PLND_EST_TYPE"]) == (1, 1, 25, 1)
    assert (a["PLND_CAM_POS_X"], a["PLND_CAM_POS_Y"], a["PLND_CAM_POS_Z"]) == pytest.approx((0.02, 0.01, -0.05))
    assert (a["PLND_CAM_POS_X"], a["PLND_CAM_POS_Z"]) == (a["VISO_POS_X"], a["VISO_POS_Z"])
    assert a["PLND_LAG"] == pytest.approx(0.035) and a["PLND_OPTIONS"] == 0  # a pad of world markers: static
    rover = mission_planner(inproc(tmp_path, landing_doc("rover", 9), "ardupilot"))
    assert rover["PLND_OPTIONS"] == 1 and rover["PLND_LAG"] == pytest.approx(0.02)  # moving; lag not measured
    assert not {n for n in mission_planner(inproc(tmp_path, doc(), "ardupilot")) if n.startswith("PLND_")}


def test_px4_precision_landing(tmp_path):
    p = qgc(run(tmp_path, landing_doc("rover", 9), "--autopilot", "px4"))
    # PX4's precland: the target is lost after PLD_BTOUT; LTEST_MODE 0 (moving) for a rover.
    assert p["PLD_BTOUT"][2:] == (1.0, 9) and p["LTEST_MODE"][2:] == (0.0, 6) and p["PLD_SRCH_ALT"][2] == 2.0
    assert qgc(inproc(tmp_path, landing_doc(), "px4"))["LTEST_MODE"][2] == 1
    assert not {n for n in qgc(inproc(tmp_path, doc(), "px4")) if n.startswith(("PLD_", "LTEST_"))}
