"""The atlas dialect, generated from ``atlas.xml`` by pymavlink's mavgen at first use.

Generated code is never committed: the module is written once into a cache directory keyed by the
hash of the XML (and pymavlink's version), atomically, and imported from there. Generation takes
well under a second and needs no network.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import logging
import os
import py_compile
import shutil
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
        for name in ("common.xml", "standard.xml", "minimal.xml"):  # common.xml includes the other two
            if (definitions / name).exists():
                shutil.copy(definitions / name, work / name)
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


def digest() -> str:
    """The cache key: atlas.xml, common.xml and pymavlink's version (any change regenerates)."""
    h = hashlib.sha256(XML.read_bytes())
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

    Generated at the first call into ``cache_dir()`` (or a per-user temp directory when that is not
    writable) and imported from there; later calls return the same module.
    """
    with _lock:
        if "module" in _cache:
            return _cache["module"]
        key = digest()
        name = f"atlas_onboard_mavlink_dialect_{key}"
        candidates = [cache_dir(), Path(tempfile.gettempdir()) / f"atlas-onboard-{os.getuid()}"]
        last_error: Exception | None = None
        for base in candidates:
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
