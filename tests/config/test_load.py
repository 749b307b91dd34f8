"""Reading a world file from disk and the commands that do (check-config, run): one test per kind of bad
input, each asserting the field path in the message and (through the CLI) exit status 2 with one line
and no traceback; the shipped files; and check-config's warnings about who can move a pose."""

import os
from pathlib import Path

import pytest
import yaml

from atlas_onboard.config import ConfigError, load_world
from tests.config.common import BASE, NODES, REPO, cli, run_cli

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


def test_usage_error_is_one_line_exit_2(capsys):
    code, _, err = cli(capsys, "check-config")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    code, _, err = cli(capsys, "check-config", "a.yaml", "--no-such-option")
    assert code == 2 and len(err.strip().splitlines()) == 1, err


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
