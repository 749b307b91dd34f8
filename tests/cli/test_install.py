"""``atlas-onboard install-service`` and ``keygen`` as a user types them: what they write and print."""

import argparse

import pytest

from atlas_onboard.cli import install as install_cli
from atlas_onboard.errors import AtlasError
from atlas_onboard.service.install import next_steps
from tests.service.test_install import DROP_INS, ENV, KEY, SCRIPT, WORLD, files_under


def test_install_service_command(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(install_cli, "console_script", lambda: SCRIPT)
    parser = argparse.ArgumentParser(prog="atlas-onboard")
    install_cli.add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["install-service", "--root", str(tmp_path), "--entity", "drone1"])
    assert args.func(args) == 0
    steps = next_steps(tmp_path, "drone1", SCRIPT)
    assert capsys.readouterr().out.splitlines() == [
        f"wrote     {tmp_path}/etc/systemd/system/atlas-onboard.service",
        f"wrote     {tmp_path}/etc/systemd/system/atlas-onboard@.service",
        f"wrote     {tmp_path}/{WORLD}",
        f"wrote     {tmp_path}/{ENV}",
        f"wrote     {tmp_path}/{KEY} (a new signing key: copy it to every drone of the swarm)",
        *(f"wrote     {tmp_path}/{d} (the world file has a network link)" for d in sorted(DROP_INS)),
        "",
        "Next, as root:",
        *(f"  {i}. {step}" for i, step in enumerate(steps, start=1)),
    ]
    assert len(steps) == 7


def test_keygen_writes_a_private_key_and_never_replaces_one_unasked(tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="atlas-onboard")
    install_cli.add_commands(parser.add_subparsers(dest="command", required=True))
    path = tmp_path / "keys" / "swarm.key"
    args = parser.parse_args(["keygen", str(path)])
    assert args.func(args) == 0
    first = path.read_bytes()
    assert len(first) == 32 and path.stat().st_mode & 0o777 == 0o600
    from atlas_onboard.mavlink.signing import read_key

    assert read_key(path) == first  # what a node accepts
    with pytest.raises(AtlasError, match="exists; give --force"):
        args.func(args)
    assert path.read_bytes() == first
    args = parser.parse_args(["keygen", "--force", str(path)])
    assert args.func(args) == 0
    assert path.read_bytes() != first and path.stat().st_mode & 0o777 == 0o600
    assert files_under(tmp_path) == {"keys/swarm.key"}  # no staging file left
