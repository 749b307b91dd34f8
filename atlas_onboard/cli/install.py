"""``atlas-onboard install-service`` and ``atlas-onboard keygen`` (:mod:`atlas_onboard.service.install`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from atlas_onboard.service.install import KEY_BYTES, console_script, install_service, next_steps, write_key


def _cmd_install_service(args: argparse.Namespace) -> int:
    root = Path(args.root)
    actions = install_service(root, args.entity, args.force)
    for a in actions:
        print(f"{a.what:9} {a.path}" + (f" ({a.note})" if a.note else ""))
    print("\nNext, as root:")
    for i, step in enumerate(next_steps(root.resolve(), args.entity, console_script()), start=1):
        print(f"  {i}. {step}")
    return 0


def _cmd_keygen(args: argparse.Namespace) -> int:
    path = Path(args.file)
    write_key(path, args.force)
    print(f"wrote a new {KEY_BYTES}-byte signing key to {path} (mode 600); name it in the peer links' signing.key_file")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``install-service`` and ``keygen``."""
    p = sub.add_parser(
        "keygen",
        help="write a new MAVLink signing key for the swarm",
        description="Write 32 random bytes to FILE with mode 600: the swarm's MAVLink 2 signing key"
        " (docs/signing.md). Refuses to replace an existing file without --force.",
    )
    p.add_argument("file", help="the key file to write, e.g. /etc/atlas-onboard/swarm.key")
    p.add_argument("--force", action="store_true", help="replace an existing key file")
    p.set_defaults(func=_cmd_keygen)

    p = sub.add_parser(
        "install-service",
        help="install the systemd units and an example world file",
        description="Write the systemd units (atlas-onboard.service, atlas-onboard@.service) to ROOT/etc/systemd/system"
        " and the annotated example world file to ROOT/etc/atlas-onboard/world.yaml, then print the remaining steps."
        " Nothing is written outside ROOT and no command is run.",
    )
    p.add_argument("--root", default="/", help="install below this directory (default: /)")
    p.add_argument(
        "--entity",
        help="the entity whose node atlas-onboard.service runs: writes ROOT/etc/atlas-onboard/atlas-onboard.env"
        " (without it, use atlas-onboard@ENTITY.service)",
    )
    p.add_argument(
        "--force", action="store_true", help="replace an existing world.yaml (and atlas-onboard.env) with the example"
    )
    p.set_defaults(func=_cmd_install_service)
