"""``atlas-onboard install-service``: the systemd units and an example world file, under a root.

What it writes, all below ``--root`` (default ``/``), nothing outside it:

- ``etc/systemd/system/atlas-onboard.service`` and ``atlas-onboard@.service``: the units shipped in
  the package (``atlas_onboard/data``, the same files as the repository's ``systemd/``), byte for
  byte; rewritten when they differ (an upgrade), so never edit them: use a drop-in;
- ``etc/atlas-onboard/world.yaml``: the annotated example world file, only if there is none (an
  existing one is kept unless ``--force``);
- with ``--entity NAME``: ``etc/atlas-onboard/atlas-onboard.env``, which makes the plain unit run
  that entity's node (kept unless ``--force``, like the world file);
- ``etc/atlas-onboard/swarm.key``: a new random 32-byte MAVLink signing key (mode 0600), only if
  there is none (never replaced, not even with ``--force``: the swarm shares one key; copy the
  first drone's to the others);
- when the world file (as installed) has a network link (udp or tcp to a host other than this one):
  the drop-in ``network-online.conf`` of both units, ordering them after network-online.target. The
  units themselves do not wait for the network: a serial autopilot needs none, and a drone that
  boots without WiFi would wait up to two minutes. Removed again when the world file has none.

``atlas-onboard keygen FILE`` writes such a key anywhere (refusing to replace one without ``--force``).

It then prints the steps that remain (a user, the console script on ``/usr/local/bin``, systemctl,
journalctl), leaving out those already done under the root. It runs no command and touches no
running system; ``--root`` also prepares an image or a mounted SD card.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import sys
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import yaml

from atlas_onboard.errors import AtlasError
from atlas_onboard.fsio import write_atomic

UNITS = ("atlas-onboard.service", "atlas-onboard@.service")
EXAMPLE = "example.yaml"
UNIT_DIR = Path("etc/systemd/system")
CONF_DIR = Path("etc/atlas-onboard")
WORLD_FILE = CONF_DIR / "world.yaml"
ENV_FILE = CONF_DIR / "atlas-onboard.env"
KEY_FILE = CONF_DIR / "swarm.key"
KEY_BYTES = 32  # MAVLink 2 signing keys are 32 bytes
DROP_IN = "network-online.conf"
DROP_IN_TEXT = (
    "# Written by atlas-onboard install-service: the world file has a network link, so the node starts once\n"
    "# the network is up. Removed by install-service when the world file has none.\n"
    "[Unit]\n"
    "Wants=network-online.target\n"
    "After=network-online.target\n"
)
_LOCAL_HOSTS = ("127.", "localhost")
EXEC_PATH = Path("usr/local/bin/atlas-onboard")  # the units' ExecStart
SERVICE_USER = "atlas"
# Entity names as the world file allows them (config/model.py), which are also valid unit instance names.
_ENTITY_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
# What the units' ProtectHome=yes makes inaccessible to the service.
_HIDDEN_HOMES = (Path("/home"), Path("/root"), Path("/run/user"))


@dataclass(frozen=True, slots=True)
class Action:
    """What install-service did to one file: ``wrote`` (new), ``updated``, ``unchanged`` or ``kept``."""

    path: Path
    what: str
    note: str = ""


def shipped(name: str) -> str:
    """The text of a file shipped in ``atlas_onboard/data`` (a unit or the example world file)."""
    return (resources.files("atlas_onboard") / "data" / name).read_text(encoding="utf-8")


def env_text(entity: str) -> str:
    """The environment file that makes ``atlas-onboard.service`` run ``entity``'s node."""
    return (
        "# Read by atlas-onboard.service: options of `atlas-onboard run` (written by install-service).\n"
        f"ATLAS_ONBOARD_ARGS=--entity {entity}\n"
    )


def install_service(root: Path, entity: str | None = None, force: bool = False) -> list[Action]:
    """Write the units, the example world file and (with ``entity``) the environment file under ``root``.

    Raises AtlasError when ``root`` is not a directory, ``entity`` is not a valid entity name, a
    target would resolve outside ``root`` (a symlink), or a file cannot be written.
    """
    if entity is not None and not _ENTITY_RE.match(entity):
        raise AtlasError(
            f"--entity: expected an entity name as in the world file (a letter, then letters, digits, _ or -,"
            f" at most 32), got {entity!r}"
        )
    if not root.is_dir():
        raise AtlasError(f"--root: {root} is not a directory")
    root = root.resolve()
    plan: list[tuple[Path, str, bool]] = [(UNIT_DIR / name, shipped(name), True) for name in UNITS]
    plan.append((WORLD_FILE, shipped(EXAMPLE), force))
    if entity is not None:
        plan.append((ENV_FILE, env_text(entity), force))
    targets = [(_inside(root, rel), text, replace) for rel, text, replace in plan]  # all checked before any write
    key_path = _inside(root, KEY_FILE)
    drop_ins = [_inside(root, UNIT_DIR / f"{name}.d" / DROP_IN) for name in UNITS]
    actions = []
    for path, text, replace in targets:
        if not path.exists():
            _write(root, path, text)
            actions.append(Action(path, "wrote"))
        elif path.read_text(encoding="utf-8") == text:
            actions.append(Action(path, "unchanged"))
        elif replace:
            _write(root, path, text)
            actions.append(Action(path, "updated"))
        else:
            actions.append(Action(path, "kept", "it exists; --force replaces it"))
    if key_path.exists():
        actions.append(Action(key_path, "kept", "the swarm's key: every drone needs the same one"))
    else:
        write_key(key_path)
        actions.append(Action(key_path, "wrote", "a new signing key: copy it to every drone of the swarm"))
    network = has_network_link(root / WORLD_FILE)
    for path in drop_ins:
        if network and not path.exists():
            _write(root, path, DROP_IN_TEXT)
            actions.append(Action(path, "wrote", "the world file has a network link"))
        elif network and path.read_text(encoding="utf-8") != DROP_IN_TEXT:
            _write(root, path, DROP_IN_TEXT)
            actions.append(Action(path, "updated", "the world file has a network link"))
        elif not network and path.exists() and path.read_text(encoding="utf-8") == DROP_IN_TEXT:
            path.unlink()
            actions.append(Action(path, "removed", "the world file has no network link"))
    return actions


def write_key(path: Path, force: bool = False) -> None:
    """A new random 32-byte signing key at ``path``, mode 0600 from its creation (never readable by
    others, not even for a moment). AtlasError if it exists (unless ``force``) or cannot be written."""
    if path.exists() and not force:
        raise AtlasError(f"keygen: {path} exists; give --force to replace it (every drone needs the new key then)")
    try:
        write_atomic(path, secrets.token_bytes(KEY_BYTES), mode=0o600, make_dirs=True)
    except OSError as exc:
        raise AtlasError(f"keygen: cannot write {path}: {exc.strerror}") from None


def has_network_link(world_file: Path) -> bool:
    """Whether any node of the world file has a udp or tcp link (autopilot or peer) to a host other
    than this one (``udpin:0.0.0.0`` listens on the network). False for a file that cannot be read:
    the node refuses it at start anyway."""
    try:
        doc = yaml.safe_load(world_file.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return False
    nodes = doc.get("nodes") if isinstance(doc, dict) else None
    urls: list[str] = []
    for node in (nodes or {}).values() if isinstance(nodes, dict) else ():
        if not isinstance(node, dict):
            continue
        links = [node.get("autopilot"), *(node.get("peers") or [])] if isinstance(node.get("peers") or [], list) else []
        for link in links:
            url = link.get("url") if isinstance(link, dict) else link
            if isinstance(url, str):
                urls.append(url)
    for url in urls:
        scheme, _, rest = url.partition(":")
        host = rest.rpartition(":")[0]
        if scheme.startswith(("udp", "tcp")) and not host.startswith(_LOCAL_HOSTS):
            return True
    return False


def _inside(root: Path, rel: Path) -> Path:
    """``root / rel``, refusing a path that resolves outside ``root`` (e.g. ``root/etc`` -> ``/etc``)."""
    path = root / rel
    if not path.resolve().is_relative_to(root):
        raise AtlasError(f"--root: {path} resolves to {path.resolve()}, outside {root}; nothing was written")
    return path


def _write(root: Path, path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (mode 0644) atomically, creating missing directories (0755) below root."""
    try:
        missing = [p for p in reversed(path.parents) if p.is_relative_to(root) and not p.exists()]
        for directory in missing:
            directory.mkdir(mode=0o755)
        write_atomic(path, text, mode=0o644)
    except OSError as exc:
        hint = " (run it as root, or give --root)" if isinstance(exc, PermissionError) else ""
        raise AtlasError(f"install-service: cannot write {path}: {exc.strerror}{hint}") from None


def console_script() -> str | None:
    """The ``atlas-onboard`` script of this installation (beside the interpreter in a venv), if any."""
    beside = Path(sys.executable).parent / "atlas-onboard"
    if beside.is_file():
        return str(beside)
    return shutil.which("atlas-onboard")


def next_steps(root: Path, entity: str | None, script: str | None) -> list[str]:
    """The commands that remain after install_service, as lines to print, with paths as on the target."""
    steps = []
    if not _has_user(root, SERVICE_USER):
        steps.append(
            f"useradd --system --user-group --groups video,dialout --home-dir /var/lib/atlas-onboard"
            f" --no-create-home --shell /usr/sbin/nologin {SERVICE_USER}"
        )
    if not os.path.lexists(root / EXEC_PATH):
        if script is not None and any(Path(script).resolve().is_relative_to(h) for h in _HIDDEN_HOMES):
            steps.append(
                f"install atlas-onboard into a venv outside /home and /root (docs/deployment.md: /opt/atlas-onboard):"
                f" the service cannot run {script} (ProtectHome=yes)"
            )
            script = None
        steps.append(f"ln -s {script or '/opt/atlas-onboard/bin/atlas-onboard'} /{EXEC_PATH}")
    steps.append(
        f"chown root:{SERVICE_USER} /{KEY_FILE} && chmod 640 /{KEY_FILE}   # the service's group reads it, the"
        " service cannot change it; use one drone's key on every drone (docs/signing.md)"
    )
    steps.append(f"atlas-onboard check-config /{WORLD_FILE}   # after editing it for your swarm and this drone")
    steps.append("systemctl daemon-reload")
    if entity is not None:
        steps.append("systemctl enable --now atlas-onboard.service")
        steps.append("journalctl -u atlas-onboard.service -f")
    else:
        steps.append("systemctl enable --now atlas-onboard@ENTITY.service   # ENTITY: this drone's name in the file")
        steps.append("journalctl -u atlas-onboard@ENTITY.service -f")
    return steps


def _has_user(root: Path, name: str) -> bool:
    try:
        lines = (root / "etc/passwd").read_text(encoding="utf-8").splitlines()
    except OSError:
        return False
    return any(line.split(":", 1)[0] == name for line in lines)
