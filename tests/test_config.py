"""The world file: normalisation of conventions, and one test per kind of bad input, each asserting the
field path in the message and (through the CLI) exit status 2 with one line and no traceback."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from atlas_onboard.cli import main
from atlas_onboard.config import WORLD, ConfigError, Weighting, load_world, parse_world
from atlas_onboard.core.geometry import rpy_deg

REPO = Path(__file__).resolve().parents[1]

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


def test_base_loads_with_defaults_and_world():
    w = parse_world(yaml.safe_load(BASE))
    assert w.entity_names == (WORLD, "drone1", "drone2")
    assert w.fusion.ema_alpha == 0.5 and w.fusion.weighting is Weighting.SIGMA_MIN
    assert sorted(w.sensors) == [1, 2] and sorted(w.markers) == [0, 10]
    assert w.markers[10].family == "tag36h11"


def test_world_entity_always_exists():
    w = parse_world({"entities": {"a": {}}})
    assert w.entity_names == (WORLD, "a")


def test_ned_frd_file_is_normalised_to_enu_flu():
    doc = {
        "conventions": {"world": "NED", "body": "FRD"},
        "entities": {
            "world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [1, 2, 3], "rpy_deg": [0, 0, 90]}}]},
            "d": {"markers": [{"id": 1, "size_m": 0.1, "pose": {"pos": [0.1, 0.2, 0.3]}}]},
        },
    }
    w = parse_world(doc)
    m0 = w.markers[0].T_entity_marker
    np.testing.assert_allclose(m0.translation, [2, 1, -3], atol=1e-12)  # NED (1, 2, 3) -> ENU (2, 1, -3)
    # The marker's x axis points NED-east (yaw 90 from north) = ENU x.
    np.testing.assert_allclose(m0.rotation.apply([1, 0, 0]), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(w.markers[1].T_entity_marker.translation, [0.1, -0.2, -0.3], atol=1e-12)


def test_same_world_in_ned_and_enu_has_same_fingerprint():
    enu = {"entities": {"world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [2, 1, -3]}}]}}}
    ned = {
        "conventions": {"world": "NED"},
        "entities": {
            "world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [1, 2, 3], "rpy_deg": [180, 0, 90]}}]}
        },
    }
    a, b = parse_world(enu), parse_world(ned)
    np.testing.assert_allclose(
        a.markers[0].T_entity_marker.as_matrix(), b.markers[0].T_entity_marker.as_matrix(), atol=1e-12
    )
    assert a.fingerprint() == b.fingerprint()
    moved = {"entities": {"world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [2, 1, -3.01]}}]}}}
    assert parse_world(moved).fingerprint() != a.fingerprint()


def test_sensor_mount_pose_becomes_optical_frame():
    w = parse_world(
        {"entities": {"d": {"sensors": [{"name": "down", "id": 1, "pose": {"pos": [0, 0, 0], "rpy_deg": [0, 90, 0]}}]}}}
    )
    np.testing.assert_allclose(w.sensors[1].T_entity_sensor.rotation.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)


def test_quaternion_and_rpy_agree():
    a = parse_world({"entities": {"d": {"markers": [{"id": 1, "size_m": 0.1, "pose": {"rpy_deg": [10, 20, 30]}}]}}})
    q = Rotation.from_euler("ZYX", [30, 20, 10], degrees=True).as_quat()
    b = parse_world(
        {
            "entities": {
                "d": {
                    "markers": [{"id": 1, "size_m": 0.1, "pose": {"rot": {"w": q[3], "x": q[0], "y": q[1], "z": q[2]}}}]
                }
            }
        }
    )
    np.testing.assert_allclose(rpy_deg(a.markers[1].T_entity_marker.rotation), [10, 20, 30], atol=1e-9)
    np.testing.assert_allclose(
        a.markers[1].T_entity_marker.as_matrix(), b.markers[1].T_entity_marker.as_matrix(), atol=1e-12
    )


def test_calibration_path_is_relative_to_the_file(tmp_path):
    f = tmp_path / "w.yaml"
    sensor = "{name: c, id: 1, pose: {}, camera: {calibration: cal/c.yaml, fps: 30}}"
    f.write_text(f"entities:\n  d:\n    sensors:\n      - {sensor}\n")
    assert load_world(f).sensors[1].camera.calibration == tmp_path / "cal" / "c.yaml"


# One case per kind of bad input: (description, edit of BASE, expected field path, expected words).
BAD = [
    ("duplicate entity", BASE + "  drone1: {}\n", "entities.drone1", "duplicate key 'drone1' (line 18)"),
    (
        "duplicate key in a list item",
        BASE.replace("{id: 0, size_m: 0.18,", "{id: 0, size_m: 0.18, size_m: 0.2,"),
        "entities.world.markers[0].size_m",
        "duplicate key 'size_m'",
    ),
    ("duplicate sensor id", BASE.replace("id: 2,", "id: 1,"), "entities.drone2.sensors[0].id", "duplicate sensor id 1"),
    (
        "duplicate sensor name",
        BASE.replace(
            "      - {name: front, id: 2, pose: {pos: [0.1, 0, 0]}}",
            "      - {name: a, id: 2, pose: {}}\n      - {name: a, id: 3, pose: {}}",
        ),
        "entities.drone2.sensors[1].name",
        "duplicate sensor name 'a'",
    ),
    (
        "marker id used twice",
        BASE.replace("id: 10,", "id: 0,"),
        "entities.drone1.markers[0].id",
        "duplicate marker id 0",
    ),
    ("unknown key (typo)", BASE.replace("ema_alpha", "ema_alhpa"), "fusion.ema_alhpa", "did you mean 'ema_alpha'"),
    ("unknown top-level key", BASE + "enities: {}\n", "enities", "unknown key"),
    (
        "unknown sensor key",
        BASE.replace("id: 2, pose", "id: 2, poes: {}, pose"),
        "entities.drone2.sensors[0].poes",
        "unknown key",
    ),
    (
        "missing field",
        BASE.replace("{id: 10, size_m: 0.1, ", "{id: 10, "),
        "entities.drone1.markers[0].size_m",
        "missing required field",
    ),
    ("missing entities", "version: 1\n", "entities", "missing required field"),
    (
        "wrong type",
        BASE.replace("id: 2,", "id: two,"),
        "entities.drone2.sensors[0].id",
        "expected an integer, got str 'two'",
    ),
    (
        "wrong type bool",
        BASE.replace("size_m: 0.18", "size_m: true"),
        "entities.world.markers[0].size_m",
        "expected a number",
    ),
    (
        "wrong type list",
        BASE.replace("pos: [0.1, 0, 0], rot", "pos: [0.1, 0], rot"),
        "entities.drone1.sensors[0].pose.pos",
        "list of 3 numbers",
    ),
    (
        "non-unit quaternion",
        BASE.replace("w: 1, x: 0", "w: 1, x: 0.5"),
        "entities.drone1.sensors[0].pose.rot",
        "unit quaternion, got norm 1.118",
    ),
    (
        "zero quaternion",
        BASE.replace("w: 1, x: 0", "w: 0, x: 0"),
        "entities.drone1.sensors[0].pose.rot",
        "zero quaternion",
    ),
    ("negative size", BASE.replace("size_m: 0.1,", "size_m: -0.1,"), "entities.drone1.markers[0].size_m", "got -0.1"),
    ("zero size", BASE.replace("size_m: 0.18", "size_m: 0"), "entities.world.markers[0].size_m", "(0, 10] metres"),
    ("alpha zero", BASE.replace("ema_alpha: 0.5", "ema_alpha: 0"), "fusion.ema_alpha", "alpha in (0, 1], got 0.0"),
    ("alpha above one", BASE.replace("ema_alpha: 0.5", "ema_alpha: 1.5"), "fusion.ema_alpha", "got 1.5"),
    (
        "non-finite nan",
        BASE.replace("pos: [0.1, 0, 0], rot", "pos: [.nan, 0, 0], rot"),
        "entities.drone1.sensors[0].pose.pos[0]",
        "finite",
    ),
    ("non-finite inf", BASE.replace("edge_timeout_s: 0.25", "edge_timeout_s: .inf"), "fusion.edge_timeout_s", "finite"),
    ("bad timeout", BASE.replace("edge_timeout_s: 0.25", "edge_timeout_s: -1"), "fusion.edge_timeout_s", "(0, 10]"),
    (
        "bad turn rate",
        BASE.replace("weighting: sigma_min}", "weighting: sigma_min, age_sigma_deg_per_s: -5}"),
        "fusion.age_sigma_deg_per_s",
        "[0, 3600] deg/s",
    ),
    ("bad convention", BASE.replace("world: ENU", "world: NWU"), "conventions.world", "one of ENU, NED"),
    (
        "bad family",
        BASE.replace("{id: 0, size_m: 0.18,", "{id: 0, family: tag99h1, size_m: 0.18,"),
        "entities.world.markers[0].family",
        "tag36h11",
    ),
    ("bad entity name", BASE.replace("drone2:", "'drone 2':"), "entities.drone 2", "entity name"),
    ("id out of range", BASE.replace("id: 2,", "id: 70000,"), "entities.drone2.sensors[0].id", "[0, 65535]"),
    (
        "rot and rpy together",
        BASE.replace("rot: {w: 1, x: 0, y: 0, z: 0}", "rot: {w: 1, x: 0, y: 0, z: 0}, rpy_deg: [0, 0, 0]"),
        "entities.drone1.sensors[0].pose",
        "either rot",
    ),
    (
        "quaternion component missing",
        BASE.replace("w: 1, x: 0, ", ""),
        "entities.drone1.sensors[0].pose.rot.w",
        "missing required field",
    ),
    ("entities not a mapping", "entities: [a, b]\n", "entities", "expected a mapping"),
    ("bad version", "version: 2\n" + BASE.replace("version: 1\n", ""), "version", "expected version 1"),
    ("yaml syntax", BASE.replace("fusion: {", "fusion: {{"), "", "invalid YAML"),
]


@pytest.mark.parametrize(("what", "text", "path", "words"), BAD, ids=[b[0] for b in BAD])
def test_bad_config_names_the_field(tmp_path, what, text, path, words):
    f = tmp_path / "world.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_world(f)
    assert info.value.path == path, str(info.value)
    assert words in str(info.value)
    assert str(f) in str(info.value)
    assert "\n" not in str(info.value)


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


@pytest.mark.parametrize(("what", "text", "path", "words"), BAD, ids=[b[0] for b in BAD])
def test_cli_bad_config_exits_2_with_one_line(capsys, tmp_path, what, text, path, words):
    f = tmp_path / "world.yaml"
    f.write_text(text)
    code, out, err = cli(capsys, "check-config", str(f))
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert (path + ":" if path else "") in lines[0] and words in lines[0]
    assert out == ""


def test_the_command_in_its_own_process_gives_one_line_and_the_exit_status(tmp_path):
    f = tmp_path / "world.yaml"
    f.write_text(BASE + "  drone1: {}\n")
    proc = run_cli("check-config", str(f))
    assert proc.returncode == 2 and proc.stdout == ""
    line = f"atlas-onboard: error: {f}: entities.drone1: duplicate key 'drone1' (line 18)"
    assert proc.stderr.strip().splitlines() == [line]
    proc = run_cli("run", "--config", str(f))  # what systemd starts: RestartPreventExitStatus=2
    assert proc.returncode == 2 and proc.stderr.strip().splitlines()[-1] == line, proc.stderr
    assert "Traceback" not in proc.stderr
    proc = run_cli("check-config")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "Traceback" not in proc.stderr
    proc = run_cli("check-config", str(REPO / "config" / "example.yaml"))
    assert proc.returncode == 0 and "fingerprint" in proc.stdout, proc.stderr


@pytest.mark.parametrize(("what", "text", "path", "words"), BAD, ids=[b[0] for b in BAD])
def test_run_with_a_bad_config_exits_2_with_one_line(capsys, tmp_path, what, text, path, words):
    f = tmp_path / "world.yaml"
    f.write_text(text)
    code, out, err = cli(capsys, "run", "--config", str(f), "--entity", "drone1")
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert (path + ":" if path else "") in lines[0] and words in lines[0]


def test_run_without_node_settings_names_what_is_missing(capsys, tmp_path):
    f = tmp_path / "world.yaml"
    f.write_text(BASE)
    code, _, err = cli(capsys, "run", "--config", str(f))
    missing = f"atlas-onboard: error: {f}: nodes: missing: `atlas-onboard run` needs a nodes section"
    assert code == 2 and err.strip().splitlines() == [missing + " (see config/example.yaml)"], err
    code, _, err = cli(capsys, "run", "--config", str(f), "--entity", "drone1")
    assert code == 2 and err.strip().splitlines() == [missing + " (see config/example.yaml)"], err
    f.write_text(BASE + "nodes: [drone1]\n")
    code, _, err = cli(capsys, "run", "--config", str(f))
    assert code == 2 and err.strip().splitlines() == [
        f"atlas-onboard: error: {f}: nodes: expected a mapping of entity names, got list"
    ], err
    f.write_text(NODES)  # two entities with node settings: which one is this?
    code, _, err = cli(capsys, "run", "--config", str(f))
    assert code == 2 and err.strip().splitlines() == [
        f"atlas-onboard: error: {f}: nodes: give --entity: the file has node settings for drone1, drone2"
    ], err


@pytest.mark.parametrize("kind", ["missing", "directory", "binary", "permission"])
def test_unreadable_file(capsys, monkeypatch, tmp_path, kind):
    f = tmp_path / "world.yaml"
    words = {"missing": "No such file", "directory": "Is a directory", "binary": "cannot read file"}.get(kind)
    if kind == "directory":
        f.mkdir()
    elif kind == "binary":
        f.write_bytes(b"\xff\xfe\x00\x01garbage")
    elif kind == "permission":
        f.write_text(BASE)
        f.chmod(0)
        words = "Permission denied"
        if os.geteuid() == 0:  # root reads it anyway: make the read fail as it does for anyone else
            real = Path.read_text

            def denied(self, *args, **kwargs):
                if self == f:
                    raise PermissionError(13, "Permission denied", str(self))
                return real(self, *args, **kwargs)

            monkeypatch.setattr(Path, "read_text", denied)
    code, out, err = cli(capsys, "check-config", str(f))
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert str(f) in err and words in err, err


@pytest.mark.parametrize("name", ["paper-test1.yaml", "paper-test2.yaml", "example.yaml"])
def test_shipped_configs_check_ok(capsys, name):
    code, out, err = cli(capsys, "check-config", str(REPO / "config" / name))
    assert code == 0, err
    world = load_world(REPO / "config" / name)
    assert f"{len(world.markers)} markers" in out
    assert f"fingerprint: {world.fingerprint():08x}" in out


def test_paper_replicas_match_the_paper():
    t1 = load_world(REPO / "config" / "paper-test1.yaml")
    world_markers = t1.entity(WORLD).markers
    assert len(world_markers) == 13 and all(m.size_m == 0.18 and m.family == "tag36h11" for m in world_markers)
    assert all(abs(m.T_entity_marker.translation[2]) < 1e-12 for m in world_markers)  # on the floor
    cam = t1.entity("ardrone").sensors[0]
    np.testing.assert_allclose(cam.T_entity_sensor.rotation.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)  # looks down
    t2 = load_world(REPO / "config" / "paper-test2.yaml")
    assert [m.size_m for m in t2.entity("tag").markers] == [0.12]
    assert sum(1 for e in t2.entities if e.name.startswith("drone")) == 2


def test_usage_error_is_one_line_exit_2(capsys):
    code, _, err = cli(capsys, "check-config")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    code, _, err = cli(capsys, "check-config", "a.yaml", "--no-such-option")
    assert code == 2 and len(err.strip().splitlines()) == 1, err


# --- node settings ----------------------------------------------------------------------------------

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


def test_node_settings_merge_defaults_and_entity(tmp_path):
    from atlas_onboard.config import AutopilotOutput, load_node

    f = tmp_path / "w.yaml"
    f.write_text(NODES)
    _, n1 = load_node(f, "drone1")
    assert n1.system_id == 11 and n1.fused_rate_hz == 5.0
    assert n1.autopilot.link.url == "udpout:127.0.0.1:14540"  # from defaults
    assert n1.autopilot.output is AutopilotOutput.ODOMETRY and n1.autopilot.rate_hz == 20  # merged
    assert [p.url for p in n1.peers] == ["udpin:0.0.0.0:14600", "udpout:127.0.0.1:14601"]
    assert [p.tunnel for p in n1.peers] == [False, True]
    _, n2 = load_node(f, "drone2")
    assert n2.autopilot.output is AutopilotOutput.VISION_POSITION_ESTIMATE and n2.fused_rate_hz == 2.0


BAD_NODES = [
    (
        "unknown node key",
        NODES.replace("fused_rate_hz: 2", "fused_rate_hz: 2\n    autopilt: {}"),
        "nodes.drone2.autopilt",
        "did you mean 'autopilot'",
    ),
    (
        "bad url",
        NODES.replace("udpout:127.0.0.1:14540", "udp://127.0.0.1:14540"),
        "nodes.defaults.autopilot.url",
        "connection string",
    ),
    (
        "bad peer url",
        NODES.replace('"udpin:0.0.0.0:14600"', '"udpin:0.0.0.0"'),
        "nodes.defaults.peers[0].url",
        "connection string",
    ),
    ("missing system id", NODES.replace("    system_id: 12\n", ""), "nodes.drone2.system_id", "missing required field"),
    (
        "duplicate system id",
        NODES.replace("system_id: 12", "system_id: 11"),
        "nodes.drone2.system_id",
        "duplicate system id 11",
    ),
    ("unknown entity", NODES + "  drone9: {system_id: 3}\n", "nodes.drone9", "unknown key"),
    (
        "bad output",
        NODES.replace("output: odometry", "output: odom"),
        "nodes.drone1.autopilot.output",
        "vision_position_estimate",
    ),
    ("bad rate", NODES.replace("rate_hz: 20", "rate_hz: 0"), "nodes.defaults.autopilot.rate_hz", "rate in [1, 200] Hz"),
    (
        "tunnel not bool",
        NODES.replace("tunnel: true", "tunnel: yes please"),
        "nodes.defaults.peers[1].tunnel",
        "true or false",
    ),
]


@pytest.mark.parametrize(("what", "text", "path", "words"), BAD_NODES, ids=[b[0] for b in BAD_NODES])
def test_bad_node_settings_name_the_field(capsys, tmp_path, what, text, path, words):
    f = tmp_path / "world.yaml"
    f.write_text(text)
    code, _, err = cli(capsys, "check-config", str(f))
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert f"{path}: " in err and words in err, err


def test_mounted_cameras_are_the_same_whether_written_in_flu_or_frd():
    # The same physical cameras: a drone's forward camera rolled 30 deg, a down camera, and a world
    # camera on the ceiling looking down. FLU pitch +90 (nose down) is FRD pitch -90; y and z flip.
    flu = {
        "entities": {
            "world": {"sensors": [{"name": "ceil", "id": 9, "pose": {"pos": [1, 2, 3], "rpy_deg": [0, 90, 0]}}]},
            "d": {
                "sensors": [
                    {"name": "fwd", "id": 1, "pose": {"pos": [0.1, 0.02, -0.03], "rpy_deg": [30, 0, 0]}},
                    {"name": "down", "id": 2, "pose": {"pos": [0.05, 0.0, -0.03], "rpy_deg": [0, 90, 0]}},
                ]
            },
        }
    }
    frd = {
        "conventions": {"world": "NED", "body": "FRD"},
        "entities": {
            "world": {"sensors": [{"name": "ceil", "id": 9, "pose": {"pos": [2, 1, -3], "rpy_deg": [0, -90, 90]}}]},
            "d": {
                "sensors": [
                    {"name": "fwd", "id": 1, "pose": {"pos": [0.1, -0.02, 0.03], "rpy_deg": [30, 0, 0]}},
                    {"name": "down", "id": 2, "pose": {"pos": [0.05, 0.0, 0.03], "rpy_deg": [0, -90, 0]}},
                ]
            },
        },
    }
    a, b = parse_world(flu), parse_world(frd)
    for sid in (1, 2, 9):
        np.testing.assert_allclose(
            a.sensors[sid].T_entity_sensor.as_matrix(), b.sensors[sid].T_entity_sensor.as_matrix(), atol=1e-12
        )
    # The forward camera rolled 30 deg right-side down: it looks along +x and the image's right
    # (optical x) points to the drone's right (FLU -y), lowered by 30 deg.
    R = b.sensors[1].T_entity_sensor.rotation
    np.testing.assert_allclose(R.apply([0, 0, 1]), [1, 0, 0], atol=1e-12)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    np.testing.assert_allclose(R.apply([1, 0, 0]), [0, -c, -s], atol=1e-12)
    # The down camera: optical axis down, image top (optical -y) towards the nose.
    R = b.sensors[2].T_entity_sensor.rotation
    np.testing.assert_allclose(R.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R.apply([0, -1, 0]), [1, 0, 0], atol=1e-12)


def test_check_config_says_who_can_move_a_pose(capsys, tmp_path):
    doc = {
        "entities": {
            "world": {"sensors": [{"name": "cam", "id": 10, "pose": {"pos": [0, 0, 4], "rpy_deg": [0, 90, 0]}}]},
            "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
        },
        "nodes": {
            "d1": {
                "system_id": 1,
                "peers": [
                    "udpin:0.0.0.0:14600",
                    {"url": "udpout:10.0.0.2:14600", "signing": {"key_file": "k", "require": False}},
                    {"url": "udpout:10.0.0.3:14600", "signing": {"key_file": "k"}},
                ],
            }
        },
    }
    f = tmp_path / "w.yaml"
    f.write_text(yaml.safe_dump(doc))
    code, out, err = cli(capsys, "check-config", str(f))
    assert code == 0, err
    assert [line for line in out.splitlines() if line.startswith("warning:")] == [
        "warning: nodes.d1.peers[0] (udpin:0.0.0.0:14600) is not signed: any host on the network can move d1's pose",
        "warning: nodes.d1.peers[1] (udpout:10.0.0.2:14600) accepts unsigned observations (require: false): any"
        " host on the network can move d1's pose",
        "warning: entity world has sensors but no node (system id) in the nodes section: every node refuses their"
        " observations",
    ]
    doc["nodes"]["d1"]["peers"] = doc["nodes"]["d1"]["peers"][2:]
    doc["nodes"]["world"] = {"system_id": 250}
    f.write_text(yaml.safe_dump(doc))
    code, out, err = cli(capsys, "check-config", str(f))
    assert code == 0 and "warning:" not in out, (out, err)
