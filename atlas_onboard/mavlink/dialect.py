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


def _generate(target: Path) -> None:
    definitions = Path(pymavlink.__file__).parent / "dialects" / "v20"
    with tempfile.TemporaryDirectory(prefix="atlas-mavgen-") as tmp:
        work = Path(tmp)
        for name in ("common.xml", "standard.xml", "minimal.xml"):
            if (definitions / name).exists():
                shutil.copy(definitions / name, work / name)
        shutil.copy(XML, work / "atlas.xml")
        out = work / "atlas_dialect.py"
        opts = mavgen.Opts(str(out), wire_protocol="2.0", language="Python3", validate=True)
        with contextlib.redirect_stdout(io.StringIO()) as chatter:  # mavgen narrates with print()
            ok = mavgen.mavgen(opts, [str(work / "atlas.xml")])
        if not ok:
            _logger.error("mavgen output: %s", chatter.getvalue())
            raise AtlasError("mavgen failed to generate the atlas dialect")
        target.parent.mkdir(parents=True, exist_ok=True)
        staged = target.with_suffix(f".{os.getpid()}.tmp")
        shutil.copy(out, staged)
        os.replace(staged, target)


def load() -> ModuleType:
    """The generated dialect module (``MAVLink``, ``MAVLink_atlas_observation_message``, ...)."""
    with _lock:
        if "module" in _cache:
            return _cache["module"]
        digest = hashlib.sha256(XML.read_bytes() + pymavlink.__version__.encode()).hexdigest()[:16]
        candidates = [cache_dir(), Path(tempfile.gettempdir()) / f"atlas-onboard-{os.getuid()}"]
        last_error: OSError | None = None
        for base in candidates:
            path = base / f"atlas_dialect_{digest}.py"
            try:
                if not path.exists():
                    _generate(path)
                spec = importlib.util.spec_from_file_location("atlas_onboard_mavlink_dialect", path)
                assert spec is not None and spec.loader is not None
                module = importlib.util.module_from_spec(spec)
                sys.modules[spec.name] = module
                spec.loader.exec_module(module)
                _cache["module"] = module
                return module
            except OSError as exc:
                last_error = exc
        raise AtlasError(f"cannot write the generated MAVLink dialect to a cache directory: {last_error}")
