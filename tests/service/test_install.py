"""The systemd units and install-service: the shipped units are the repository's, their service
contract line by line, what install-service writes under a root (and nothing else), what it keeps,
the steps it prints, and systemd-analyze's verdict on the installed result (verify, security)."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from atlas_onboard.errors import AtlasError
from atlas_onboard.service import install
from atlas_onboard.service.install import UNITS, install_service, next_steps, shipped

REPO = Path(__file__).resolve().parents[2]
UNIT_FILES = {"etc/systemd/system/atlas-onboard.service", "etc/systemd/system/atlas-onboard@.service"}
# The example world file has network links (udpin:0.0.0.0 peers): both units get the drop-in.
DROP_INS = {
    f"etc/systemd/system/{u}.d/network-online.conf" for u in ("atlas-onboard.service", "atlas-onboard@.service")
}
WORLD = "etc/atlas-onboard/world.yaml"
ENV = "etc/atlas-onboard/atlas-onboard.env"
KEY = "etc/atlas-onboard/swarm.key"
SCRIPT = "/opt/atlas-onboard/bin/atlas-onboard"


def files_under(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if not p.is_dir()}


def directives(text: str) -> dict[str, list[str]]:
    """Each KEY=value of a unit file, in order (a key may repeat), ignoring comments and sections."""
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key, []).append(value)
    return out


@pytest.mark.parametrize("name", UNITS)
def test_the_package_ships_the_repository_units(name):
    assert shipped(name) == (REPO / "systemd" / name).read_text(encoding="utf-8")


def test_the_package_ships_the_repository_example():
    assert shipped("example.yaml") == (REPO / "config" / "example.yaml").read_text(encoding="utf-8")


@pytest.mark.parametrize(
    ("name", "exec_start", "environment_file"),
    [
        (
            "atlas-onboard.service",
            ["/usr/local/bin/atlas-onboard run --config /etc/atlas-onboard/world.yaml $ATLAS_ONBOARD_ARGS"],
            ["-/etc/atlas-onboard/atlas-onboard.env"],
        ),
        (
            "atlas-onboard@.service",
            ["/usr/local/bin/atlas-onboard run --config /etc/atlas-onboard/world.yaml --entity %i"],
            None,
        ),
    ],
)
def test_unit_contract(name, exec_start, environment_file):
    d = directives(shipped(name))
    assert d["ExecStart"] == exec_start
    assert d.get("EnvironmentFile") == environment_file
    expected = {
        "Type": ["notify"],
        "NotifyAccess": ["main"],
        "ExecReload": ["/bin/kill -HUP $MAINPID"],
        "WatchdogSec": ["5"],
        "Restart": ["on-failure"],
        "RestartPreventExitStatus": ["2"],
        "StartLimitIntervalSec": ["0"],
        "User": ["atlas"],
        "Group": ["atlas"],
        "SupplementaryGroups": ["video dialout"],
        "StateDirectory": ["atlas-onboard"],
        "ConfigurationDirectory": ["atlas-onboard"],
        "CacheDirectory": ["atlas-onboard"],
        "MemoryMax": ["512M"],
        "TasksMax": ["64"],
        "Environment": ["ATLAS_ONBOARD_CACHE=%C/atlas-onboard", "PYTHONUNBUFFERED=1"],
        "NoNewPrivileges": ["yes"],
        "ProtectSystem": ["strict"],
        "ProtectHome": ["yes"],
        "PrivateTmp": ["yes"],
        "ProtectKernelTunables": ["yes"],
        "ProtectKernelModules": ["yes"],
        "RestrictAddressFamilies": ["AF_UNIX AF_INET AF_INET6 AF_NETLINK"],
        "CapabilityBoundingSet": [""],
        "DevicePolicy": ["closed"],
        "WantedBy": ["multi-user.target"],
    }
    assert {k: d.get(k) for k in expected} == expected
    # Cameras and serial ports stay reachable: no private /dev, and their device classes are allowed.
    assert "PrivateDevices" not in d
    for cls in ("video4linux", "ttyAMA", "ttyS", "ttyUSB", "ttyACM", "ttyTHS"):
        assert f"char-{cls} rw" in d["DeviceAllow"], cls


def test_the_units_load_device_modules_first_and_do_not_wait_for_the_network():
    for name in UNITS:
        d = directives(shipped(name))
        modules = ["modprobe@videodev.service", "modprobe@mc.service", "modprobe@cdc_acm.service",
                   "modprobe@usbserial.service"]  # fmt: skip
        assert d["Wants"] == [" ".join(modules)] and d["After"] == ["time-sync.target", " ".join(modules)]
        assert "network-online.target" not in " ".join(d["Wants"] + d["After"])


@pytest.mark.parametrize(
    ("links", "network"),
    [
        ({"autopilot": {"url": "/dev/ttyAMA0,921600"}}, False),
        ({"autopilot": "/dev/ttyACM0", "peers": ["udpout:127.0.0.1:14600"]}, False),
        ({"autopilot": {"url": "tcp:localhost:5760"}}, False),
        ({"autopilot": {"url": "/dev/ttyAMA0,921600"}, "peers": [{"url": "udpin:0.0.0.0:14600"}]}, True),
        ({"peers": ["udpout:10.0.0.2:14550"]}, True),
    ],
)
def test_the_network_drop_in_follows_the_world_files_links(tmp_path, links, network):
    (tmp_path / "etc/atlas-onboard").mkdir(parents=True)
    (tmp_path / WORLD).write_text(
        yaml.safe_dump({"entities": {"d1": {}}, "nodes": {"d1": {"system_id": 1, **links}}}), encoding="utf-8"
    )
    install_service(tmp_path)
    assert files_under(tmp_path) == UNIT_FILES | {WORLD, KEY} | (DROP_INS if network else set())


def test_the_two_units_differ_only_in_how_they_name_the_entity():
    plain, template = (directives(shipped(n)) for n in UNITS)
    differing = {k for k in plain.keys() | template.keys() if plain.get(k) != template.get(k)}
    assert differing == {"Description", "EnvironmentFile", "ExecStart"}


def test_install_service_writes_the_shipped_files_and_nothing_else(tmp_path):
    actions = install_service(tmp_path)
    assert [(a.path, a.what) for a in actions] == [
        (tmp_path / "etc/systemd/system/atlas-onboard.service", "wrote"),
        (tmp_path / "etc/systemd/system/atlas-onboard@.service", "wrote"),
        (tmp_path / WORLD, "wrote"),
        (tmp_path / KEY, "wrote"),
        *((tmp_path / f"etc/systemd/system/{u}.d/network-online.conf", "wrote") for u in UNITS),
    ]
    assert files_under(tmp_path) == UNIT_FILES | {WORLD, KEY} | DROP_INS
    for name in DROP_INS:
        assert (tmp_path / name).read_text(encoding="utf-8") == install.DROP_IN_TEXT
    for name in UNITS:
        assert (tmp_path / "etc/systemd/system" / name).read_bytes() == (REPO / "systemd" / name).read_bytes()
    assert (tmp_path / WORLD).read_text(encoding="utf-8") == shipped("example.yaml")
    for rel in files_under(tmp_path):
        assert (tmp_path / rel).stat().st_mode & 0o777 == (0o600 if rel == KEY else 0o644), rel
    assert len((tmp_path / KEY).read_bytes()) == 32
    assert (tmp_path / "etc/atlas-onboard").stat().st_mode & 0o777 == 0o755


def test_install_service_keeps_the_world_file_and_updates_the_units(tmp_path):
    install_service(tmp_path)
    world = tmp_path / WORLD
    unit = tmp_path / "etc/systemd/system/atlas-onboard.service"
    key = (tmp_path / KEY).read_bytes()
    assert [a.what for a in install_service(tmp_path)] == ["unchanged"] * 3 + ["kept"]
    world.write_text("entities: {mine: {}}\n", encoding="utf-8")
    unit.write_text("[Service]\nExecStart=/bin/true\n", encoding="utf-8")
    actions = {a.path: (a.what, a.note) for a in install_service(tmp_path)}
    assert actions[world] == ("kept", "it exists; --force replaces it")
    assert actions[unit] == ("updated", "")
    assert files_under(tmp_path) == UNIT_FILES | {WORLD, KEY}  # a world without network links: no drop-in
    assert world.read_text(encoding="utf-8") == "entities: {mine: {}}\n"
    assert unit.read_text(encoding="utf-8") == shipped("atlas-onboard.service")
    actions = {a.path: (a.what, a.note) for a in install_service(tmp_path, force=True)}
    assert actions[world] == ("updated", "")
    assert world.read_text(encoding="utf-8") == shipped("example.yaml")
    assert (tmp_path / KEY).read_bytes() == key  # the swarm's key is never replaced, not even by --force
    assert files_under(tmp_path) == UNIT_FILES | {WORLD, KEY} | DROP_INS  # no staging files left behind


def test_entity_environment_file(tmp_path):
    env = tmp_path / ENV
    install_service(tmp_path, entity="drone1")
    assert files_under(tmp_path) == UNIT_FILES | {WORLD, ENV, KEY} | DROP_INS
    assert env.read_text(encoding="utf-8").splitlines()[-1] == "ATLAS_ONBOARD_ARGS=--entity drone1"
    assert {a.path: a.what for a in install_service(tmp_path, entity="drone2")}[env] == "kept"
    assert env.read_text(encoding="utf-8").splitlines()[-1] == "ATLAS_ONBOARD_ARGS=--entity drone1"
    assert {a.path: a.what for a in install_service(tmp_path, entity="drone2", force=True)}[env] == "updated"
    assert env.read_text(encoding="utf-8").splitlines()[-1] == "ATLAS_ONBOARD_ARGS=--entity drone2"


def test_nothing_is_written_through_a_symlink_out_of_the_root(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    (root / "etc").symlink_to(outside)
    with pytest.raises(AtlasError) as info:
        install_service(root)
    assert str(info.value) == (
        f"--root: {root}/etc/systemd/system/atlas-onboard.service resolves to"
        f" {outside}/systemd/system/atlas-onboard.service, outside {root}; nothing was written"
    )
    assert list(outside.iterdir()) == []


@pytest.mark.parametrize(
    ("entity", "message"),
    [
        ("1drone", "--entity: expected an entity name as in the world file (a letter, then letters, digits, _ or -, at most 32), got '1drone'"),  # noqa: E501
        ("drone one", "--entity: expected an entity name as in the world file (a letter, then letters, digits, _ or -, at most 32), got 'drone one'"),  # noqa: E501
        ("d" * 33, f"--entity: expected an entity name as in the world file (a letter, then letters, digits, _ or -, at most 32), got '{'d' * 33}'"),  # noqa: E501
    ],
)  # fmt: skip
def test_bad_entity_names_are_refused(tmp_path, entity, message):
    with pytest.raises(AtlasError) as info:
        install_service(tmp_path, entity=entity)
    assert str(info.value) == message
    assert files_under(tmp_path) == set()


def test_a_missing_root_is_refused(tmp_path):
    with pytest.raises(AtlasError) as info:
        install_service(tmp_path / "nowhere")
    assert str(info.value) == f"--root: {tmp_path / 'nowhere'} is not a directory"


CHOWN_KEY = (
    "chown root:atlas /etc/atlas-onboard/swarm.key && chmod 640 /etc/atlas-onboard/swarm.key   # the service's group"
    " reads it, the service cannot change it; use one drone's key on every drone (docs/signing.md)"
)


def test_next_steps_leave_out_what_is_done(tmp_path):
    assert next_steps(tmp_path, "drone1", SCRIPT) == [
        "useradd --system --user-group --groups video,dialout --home-dir /var/lib/atlas-onboard --no-create-home"
        " --shell /usr/sbin/nologin atlas",
        f"ln -s {SCRIPT} /usr/local/bin/atlas-onboard",
        CHOWN_KEY,
        "atlas-onboard check-config /etc/atlas-onboard/world.yaml   # after editing it for your swarm and this drone",
        "systemctl daemon-reload",
        "systemctl enable --now atlas-onboard.service",
        "journalctl -u atlas-onboard.service -f",
    ]
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc/passwd").write_text(
        "root:x:0:0::/root:/bin/sh\natlas:x:998:998::/var/lib/atlas-onboard:/usr/sbin/nologin\n", encoding="utf-8"
    )
    (tmp_path / "usr/local/bin").mkdir(parents=True)
    (tmp_path / "usr/local/bin/atlas-onboard").symlink_to(SCRIPT)  # dangling here, present on the target
    assert next_steps(tmp_path, None, SCRIPT) == [
        CHOWN_KEY,
        "atlas-onboard check-config /etc/atlas-onboard/world.yaml   # after editing it for your swarm and this drone",
        "systemctl daemon-reload",
        "systemctl enable --now atlas-onboard@ENTITY.service   # ENTITY: this drone's name in the file",
        "journalctl -u atlas-onboard@ENTITY.service -f",
    ]


def test_a_script_under_home_cannot_be_the_service(tmp_path):
    steps = next_steps(tmp_path, "d1", "/home/pi/venv/bin/atlas-onboard")
    assert steps[1] == (
        "install atlas-onboard into a venv outside /home and /root (docs/deployment.md: /opt/atlas-onboard):"
        " the service cannot run /home/pi/venv/bin/atlas-onboard (ProtectHome=yes)"
    )
    assert steps[2] == "ln -s /opt/atlas-onboard/bin/atlas-onboard /usr/local/bin/atlas-onboard"


def test_the_cli_installs_a_world_file_that_validates_and_reports_errors_in_one_line(tmp_path):
    run = [sys.executable, "-m", "atlas_onboard"]
    proc = subprocess.run(
        [*run, "install-service", "--root", str(tmp_path)], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert files_under(tmp_path) == UNIT_FILES | {WORLD, KEY} | DROP_INS
    proc = subprocess.run([*run, "check-config", str(tmp_path / WORLD)], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    proc = subprocess.run(
        [*run, "install-service", "--root", str(tmp_path / "nowhere")], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 2
    assert proc.stderr == f"atlas-onboard: error: --root: {tmp_path / 'nowhere'} is not a directory\n"


def _systemd_analyze() -> tuple[str, int] | None:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        return None
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, check=False).stdout
    match = re.match(r"systemd (\d+)", out)
    return exe, int(match.group(1)) if match else 0


@pytest.fixture
def installed_root(tmp_path):
    """install-service's output plus what systemd-analyze needs to load it offline: the host's own
    unit directory (targets such as sysinit.target) and stand-ins for the two programs the units run."""
    found = _systemd_analyze()
    if found is None:
        pytest.skip("systemd-analyze is not installed here (Debian/Ubuntu: apt-get install systemd)")
    host_units = Path("/usr/lib/systemd/system")
    if not (host_units / "sysinit.target").exists():
        pytest.skip("no /usr/lib/systemd/system/sysinit.target to load the units against")
    install_service(tmp_path, entity="drone1")
    shutil.copytree(host_units, tmp_path / "usr/lib/systemd/system", symlinks=True)
    for program in ("usr/local/bin/atlas-onboard", "bin/kill"):
        (tmp_path / program).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / program).write_text("#!/bin/sh\n")
        (tmp_path / program).chmod(0o755)
    return found, tmp_path


def test_systemd_analyze_verify(installed_root):
    (exe, _), root = installed_root
    proc = subprocess.run(
        [exe, "verify", f"--root={root}", "atlas-onboard.service", "atlas-onboard@drone1.service"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert (proc.returncode, proc.stdout + proc.stderr) == (0, "")


def test_systemd_analyze_security_exposure_is_ok(installed_root):
    (exe, version), root = installed_root
    if version < 250:
        pytest.skip(f"systemd-analyze {version} has no offline security check (needs 250)")
    for unit in ("atlas-onboard.service", "atlas-onboard@drone1.service"):
        # --threshold=20: fail above an exposure of 2.0, the top of systemd's "OK" band.
        proc = subprocess.run(
            [exe, "security", "--offline=true", f"--root={root}", "--threshold=20", "--no-pager", unit],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert re.search(r"Overall exposure level for \S+: [01]\.\d OK", proc.stdout), proc.stdout
