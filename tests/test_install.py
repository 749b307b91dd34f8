"""The systemd units: the shipped copies match systemd/, install-service writes them with this
installation's interpreter, keeps an existing world file, and systemd-analyze accepts the result."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from atlas_onboard.install import UNITS, install, unit_text

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", UNITS)
def test_shipped_units_equal_the_repository_copies(name):
    assert (REPO / "systemd" / name).read_text() == (REPO / "atlas_onboard" / "data" / name).read_text()


@pytest.mark.parametrize("name", UNITS)
def test_unit_contract(name):
    text = (REPO / "systemd" / name).read_text()
    required = (
        "Type=notify", "WatchdogSec=", "Restart=on-failure", "RestartPreventExitStatus=2", "NoNewPrivileges=yes",
        "ProtectSystem=strict", "ProtectHome=yes", "PrivateTmp=yes", "SupplementaryGroups=video dialout",
        "StateDirectory=atlas-onboard", "ExecReload=/bin/kill -HUP $MAINPID",
    )  # fmt: skip
    for line in required:
        assert line in text, line
    assert ("--entity %i" in text) == name.endswith("@.service")


def test_install_service_writes_units_and_keeps_an_existing_world(tmp_path):
    written = install(tmp_path)
    unit = tmp_path / "etc/systemd/system/atlas-onboard.service"
    assert unit in written and f"ExecStart={sys.executable} -m atlas_onboard run" in unit.read_text()
    world = tmp_path / "etc/atlas-onboard/world.yaml"
    world.write_text("mine")
    assert world not in install(tmp_path)
    assert world.read_text() == "mine"
    install(tmp_path, force=True)
    assert "entities:" in world.read_text()
    proc = subprocess.run(
        [sys.executable, "-m", "atlas_onboard", "check-config", str(world)], capture_output=True, check=False
    )
    assert proc.returncode == 0, proc.stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
@pytest.mark.parametrize("name", ["atlas-onboard.service", "atlas-onboard@drone1.service"])
def test_systemd_analyze_verify(tmp_path, name):
    template = "atlas-onboard@.service" if "@" in name else name
    path = tmp_path / name
    path.write_text(unit_text(template))
    proc = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "warning" not in proc.stderr.lower(), proc.stderr
