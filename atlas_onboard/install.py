"""``atlas-onboard install-service``: the systemd unit(s) and an example world file, under a root."""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path

from atlas_onboard.errors import AtlasError

UNITS = ("atlas-onboard.service", "atlas-onboard@.service")


def unit_text(name: str, python: str = sys.executable) -> str:
    """A shipped unit with ExecStart pointing at this installation's interpreter."""
    text = (resources.files("atlas_onboard") / "data" / name).read_text(encoding="utf-8")
    return text.replace("ExecStart=/usr/local/bin/atlas-onboard ", f"ExecStart={python} -m atlas_onboard ")


def install(root: Path, force: bool = False, python: str = sys.executable) -> list[Path]:
    """Write the units to ROOT/etc/systemd/system and an example world file to ROOT/etc/atlas-onboard."""
    written = []
    unit_dir = root / "etc" / "systemd" / "system"
    conf_dir = root / "etc" / "atlas-onboard"
    try:
        unit_dir.mkdir(parents=True, exist_ok=True)
        conf_dir.mkdir(parents=True, exist_ok=True)
        for name in UNITS:
            path = unit_dir / name
            path.write_text(unit_text(name, python), encoding="utf-8")
            written.append(path)
        world = conf_dir / "world.yaml"
        if world.exists() and not force:
            print(f"kept {world} (it exists; --force replaces it)")
        else:
            world.write_text((resources.files("atlas_onboard") / "data" / "example.yaml").read_text(), encoding="utf-8")
            written.append(world)
    except OSError as exc:
        raise AtlasError(f"install-service: cannot write under {root}: {exc.strerror} ({exc.filename})") from None
    return written


def _cmd(args: argparse.Namespace) -> int:
    for path in install(Path(args.root), args.force):
        print(f"wrote {path}")
    print(
        "next:\n"
        "  useradd --system --home /var/lib/atlas-onboard --groups video,dialout atlas\n"
        "  edit /etc/atlas-onboard/world.yaml (entities, nodes.<entity>.system_id, autopilot url, peers)\n"
        "  atlas-onboard check-config /etc/atlas-onboard/world.yaml\n"
        "  systemctl daemon-reload\n"
        "  systemctl enable --now atlas-onboard        # one node (the file's only node section)\n"
        "  systemctl enable --now atlas-onboard@drone1 # or one unit per entity on this computer\n"
        "  journalctl -u atlas-onboard -f"
    )
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("install-service", help="install the systemd unit(s) and an example world file")
    p.add_argument("--root", default="/", help="install under this root (default /)")
    p.add_argument("--force", action="store_true", help="replace an existing /etc/atlas-onboard/world.yaml")
    p.set_defaults(func=_cmd)
