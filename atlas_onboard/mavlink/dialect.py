"""The atlas dialect, generated from ``atlas.xml`` by pymavlink's mavgen at first use.

Generated code is never committed: the module is written once into a cache directory keyed by the
hash of the XML (and pymavlink's version), atomically, and imported from there. Generation takes
well under a second and needs no network.

Importing runs the cached file's code, so the cache is used only where nobody else could have
written it: the directory, the module and its bytecode owned by the running user and writable by
nobody else (:func:`private`). Otherwise (a cache directory of another user, a shared /tmp) the
module is generated again into a fresh private temporary directory and imported from there.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import logging
import os
import py_compile
import re
import shutil
import stat
import sys
import tempfile
import threading
from pathlib import Path
from types import ModuleType

import pymavlink
from pymavlink.generator import mavgen

from atlas_onboard.errors import AtlasError

_logger = logging.getLogger(__name__)
XML = Path(__file__).with_name("atlas.xml")
_lock = threading.Lock()
_cache: dict[str, ModuleType] = {}


def cache_dir() -> Path:
    """``$ATLAS_ONBOARD_CACHE``, else ``$XDG_CACHE_HOME/atlas-onboard``, else ``~/.cache/atlas-onboard``
    (falling back to the temp directory where home is read-only, e.g. under systemd's ProtectHome)."""
    env = os.environ.get("ATLAS_ONBOARD_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "atlas-onboard"


def private(path: Path) -> bool:
    """Whether ``path`` (if it exists) is owned by the running user and writable by nobody else."""
    try:
        st = path.lstat()
    except FileNotFoundError:
        return True
    except OSError:
        return False
    return st.st_uid == os.getuid() and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not stat.S_ISLNK(st.st_mode)


def _usable(base: Path, path: Path) -> bool:
    """Whether the cache directory ``base`` may hold ``path``: it, the module and its bytecode private
    (the directory created, mode 0700, if missing)."""
    try:
        base.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError:
        return False
    pyc = Path(importlib.util.cache_from_source(str(path)))
    return all(private(p) for p in (base, path, pyc.parent, pyc))


def definitions_dir() -> Path:
    """The directory of pymavlink's ``common.xml``: the wheel ships it beside the generated dialects in
    ``pymavlink/dialects/v20``; a source checkout has it in ``message_definitions/v1.0``."""
    root = Path(pymavlink.__file__).parent
    for candidate in (
        root / "dialects" / "v20",
        root / "message_definitions" / "v1.0",
        root.parent / "message_definitions" / "v1.0",
    ):
        if (candidate / "common.xml").is_file():
            return candidate
    raise AtlasError(f"pymavlink {pymavlink.__version__} ships no common.xml (looked under {root})")


def _generate(target: Path) -> None:
    """Run mavgen on atlas.xml (and the common.xml it includes) and move the result to ``target`` atomically."""
    definitions = definitions_dir()
    with tempfile.TemporaryDirectory(prefix="atlas-mavgen-") as tmp:
        work = Path(tmp)
        for name in _INCLUDED:
            if (definitions / name).exists():
                shutil.copy(definitions / name, work / name)
        common = work / "common.xml"
        common.write_text(patch_common(common.read_text(encoding="utf-8")), encoding="utf-8")
        shutil.copy(XML, work / "atlas.xml")
        out = work / "atlas_dialect.py"
        opts = mavgen.Opts(str(out), wire_protocol="2.0", language="Python3", validate=True)
        with contextlib.redirect_stdout(io.StringIO()) as chatter:  # mavgen narrates with print()
            ok = mavgen.mavgen(opts, [str(work / "atlas.xml")])
        if not ok or not out.exists():
            _logger.error("mavgen output: %s", chatter.getvalue())
            raise AtlasError("mavgen failed to generate the atlas dialect from atlas.xml")
        target.parent.mkdir(parents=True, exist_ok=True)
        # Copy beside the target, then rename: another process never sees a half-written module.
        staged = target.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        shutil.copy(out, staged)
        os.replace(staged, target)


_INCLUDED = ("development.xml", "common.xml", "standard.xml", "minimal.xml")  # each includes the next

# Messages of common.xml that PX4 sends on every link and pymavlink 2.4.x's copy lacks (they would
# count as unknown ids): TIME_ESTIMATE_TO_TARGET (1 Hz), EVENT and CURRENT_EVENT_SEQUENCE (every
# 3 s). Added where the shipped file has no message of that id; CRC extras 232, 160, 106 (tested).
_COMMON_ADDITIONS = {
    380: """<message id="380" name="TIME_ESTIMATE_TO_TARGET">
      <description>Time estimates for events and actions given the current vehicle state.</description>
      <field type="int32_t" name="safe_return" units="s">Time to complete the safe return (-1: none).</field>
      <field type="int32_t" name="land" units="s">Time to complete LAND (-1: none).</field>
      <field type="int32_t" name="mission_next_item" units="s">Time for the active mission item (-1: none).</field>
      <field type="int32_t" name="mission_end" units="s">Time for the current mission (-1: none).</field>
      <field type="int32_t" name="commanded_action" units="s">Time for the commanded action (-1: none).</field>
    </message>
  """,
    410: """<message id="410" name="EVENT">
      <description>Event message (the events interface).</description>
      <field type="uint8_t" name="destination_component">Component ID</field>
      <field type="uint8_t" name="destination_system">System ID</field>
      <field type="uint32_t" name="id">Event ID (as defined in the component metadata)</field>
      <field type="uint32_t" name="event_time_boot_ms" units="ms">Time since boot when the event happened.</field>
      <field type="uint16_t" name="sequence">Sequence number.</field>
      <field type="uint8_t" name="log_levels">Log levels (internal, external).</field>
      <field type="uint8_t[40]" name="arguments">Arguments (depend on event ID).</field>
    </message>
  """,
    411: """<message id="411" name="CURRENT_EVENT_SEQUENCE">
      <description>Regular broadcast of the current event sequence number.</description>
      <field type="uint16_t" name="sequence">Sequence number.</field>
      <field type="uint8_t" name="flags">Flag bitset.</field>
    </message>
  """,
}

# TIMESYNC's extension fields (common.xml since 2023; pymavlink 2.4.x ships the description without
# them): a reply names the requester. Extensions leave the CRC extra unchanged, so a peer without
# them reads the same message.
_TIMESYNC_TARGETS = (
    '<extensions/><field type="uint8_t" name="target_system">Target system id.</field>'
    '<field type="uint8_t" name="target_component">Target component id.</field>'
)
_TIMESYNC_RE = re.compile(r'(<message id="111" name="TIMESYNC">.*?)(</message>)', re.S)


def patch_common(text: str) -> str:
    """common.xml as the node needs it: TIMESYNC with its target fields and the messages of
    _COMMON_ADDITIONS, where the shipped file lacks them."""
    m = _TIMESYNC_RE.search(text)
    if m is not None and 'name="target_system"' not in m.group(1):
        text = text[: m.start(2)] + _TIMESYNC_TARGETS + text[m.start(2) :]
    for msg_id, xml in _COMMON_ADDITIONS.items():
        if f'<message id="{msg_id}"' not in text and "</messages>" in text:
            end = text.rindex("</messages>")
            text = text[:end] + xml + text[end:]
    return text


def known_elsewhere() -> frozenset[int]:
    """Message ids that some dialect shipped with pymavlink defines (ardupilotmega.xml's AHRS,
    EKF_STATUS_REPORT, ...): what an autopilot of that dialect sends and ours does not decode. An
    unknown id outside them is one no public dialect of this pymavlink defines. Read once."""
    with _lock:
        known = _cache.get("known_elsewhere")
        if known is None:
            ids: set[int] = set()
            for path in definitions_dir().glob("*.xml"):
                with contextlib.suppress(OSError, UnicodeDecodeError):
                    ids.update(int(i) for i in re.findall(r'<message id="(\d+)"', path.read_text(encoding="utf-8")))
            known = _cache["known_elsewhere"] = frozenset(ids)
    return known


def digest() -> str:
    """The cache key: atlas.xml, common.xml (as patched) and pymavlink's version (any change regenerates)."""
    h = hashlib.sha256(XML.read_bytes())
    h.update(_TIMESYNC_TARGETS.encode() + "".join(_COMMON_ADDITIONS.values()).encode())
    h.update((definitions_dir() / "development.xml").read_bytes())
    h.update((definitions_dir() / "common.xml").read_bytes())
    h.update(pymavlink.__version__.encode())
    return h.hexdigest()[:16]


def _compile(path: Path) -> None:
    """Write the module's bytecode beside it (``__pycache__``), as the interpreter would unless told
    not to (PYTHONDONTWRITEBYTECODE): compiling 1.8 MB of generated Python costs every process that
    starts about 0.4 s. A stale or missing file only costs that time again, never correctness: the
    loader checks the source's size and time against it."""
    pyc = Path(importlib.util.cache_from_source(str(path)))
    try:
        if not pyc.exists() or pyc.stat().st_mtime < path.stat().st_mtime:
            py_compile.compile(str(path), cfile=str(pyc), doraise=True)
    except (OSError, py_compile.PyCompileError) as exc:
        _logger.debug("no bytecode cache for %s: %s", path, exc)


def _import(path: Path, name: str) -> ModuleType:
    _compile(path)
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load() -> ModuleType:
    """The generated dialect module (``MAVLink``, ``MAVLink_atlas_observation_message``, ...).

    Generated at the first call into ``cache_dir()`` (or, when that is not private to the running user
    or not writable, into a fresh private temporary directory) and imported from there; later calls
    return the same module.
    """
    with _lock:
        if "module" in _cache:
            return _cache["module"]
        key = digest()
        name = f"atlas_onboard_mavlink_dialect_{key}"
        last_error: Exception | None = None
        for base in (cache_dir(), None):
            if base is not None and not _usable(base, base / f"atlas_dialect_{key}.py"):
                _logger.warning("MAVLink dialect cache %s is not private to this user: not used", base)
                continue
            if base is None:
                base = Path(tempfile.mkdtemp(prefix="atlas-onboard-dialect-"))  # mode 0700, a new name
            path = base / f"atlas_dialect_{key}.py"
            try:
                if not path.exists():
                    _generate(path)
                try:
                    module = _import(path, name)
                except (SyntaxError, ImportError, AttributeError, ValueError):
                    # A damaged cache file (a full disk, a hand edit): generate it again, once.
                    _logger.warning("cached MAVLink dialect %s is damaged; generating it again", path)
                    _generate(path)
                    module = _import(path, name)
                sys.modules[name] = module
                _cache["module"] = module
                return module
            except (OSError, SyntaxError, ImportError) as exc:
                last_error = exc
        raise AtlasError(f"cannot write the generated MAVLink dialect to a cache directory: {last_error}")
