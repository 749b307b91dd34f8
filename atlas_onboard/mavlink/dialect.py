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
from typing import Any

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


# --- a faster decode -----------------------------------------------------------------------------------

_MAGIC_V2 = 0xFD
_IFLAG_SIGNED = 0x01
_V2_OVERHEAD = 12  # 10-byte header, 2-byte checksum (unsigned)


def parser_class(module: ModuleType) -> type:
    """The dialect's ``MAVLink`` class with a faster :meth:`decode` for unsigned MAVLink 2 frames.

    pymavlink's generated ``decode`` finds each field of a message with arrays by summing the lengths
    of the fields before it, for every message it decodes: for ATLAS_OBSERVATION (20 fields, three
    arrays) that is about half of its time, and a node in a swarm decodes every peer's observation.
    This class computes each message type's field layout once and otherwise does what pymavlink
    does: the same checks, the same message object (fields, header, payload, checksum). Anything
    else goes to pymavlink's own ``decode`` unchanged: MAVLink 1, signed frames, any frame while a
    signing key is set (unsigned frames are then the signing callback's to judge), unknown ids, a
    wrong length or checksum (pymavlink raises its own error for those). Tested equal to pymavlink's
    on every message of the dialect.
    """
    with _lock:
        cls = _cache.get("parser")
        if cls is None or cls.__bases__[0] is not module.MAVLink:
            cls = _cache["parser"] = type("AtlasMAVLink", (module.MAVLink,), {"decode": _decoder(module)})
    return cls


def _layout(msgtype: Any) -> tuple[list[tuple[int, int]], list[int]]:
    """Each field's (position in the unpacked tuple, array length or 0 for a scalar or a string), in
    the message's field order, and which fields are strings (their NUL padding is stripped)."""
    zero = msgtype.unpacker.unpack(bytes(msgtype.unpacker.size))
    lengths = msgtype.lengths
    fields, strings = [], []
    for i, order in enumerate(msgtype.orders):
        tip, n = sum(lengths[:order]), lengths[order]
        text = isinstance(zero[tip], bytes)
        fields.append((tip, 0 if n == 1 or text else n))
        if text:
            strings.append(i)
    return fields, strings


def _decoder(module: ModuleType) -> Any:
    mavlink_map, header, x25crc = module.mavlink_map, module.MAVLink_header, module.x25crc
    layouts: dict[int, tuple[list[tuple[int, int]], list[int]]] = {}
    generic = module.MAVLink.decode

    def decode(self: Any, msgbuf: bytearray) -> Any:
        n = len(msgbuf)
        if n < _V2_OVERHEAD or msgbuf[0] != _MAGIC_V2 or msgbuf[2] or self.signing.secret_key is not None:
            return generic(self, msgbuf)
        msg_id = msgbuf[7] | msgbuf[8] << 8 | msgbuf[9] << 16
        msgtype = mavlink_map.get(msg_id)
        crc = msgbuf[-2] | msgbuf[-1] << 8
        if msgtype is None or msgbuf[1] != n - _V2_OVERHEAD:
            return generic(self, msgbuf)
        crcbuf = msgbuf[1:-2]
        crcbuf.append(msgtype.crc_extra)
        if x25crc(crcbuf).crc != crc:
            return generic(self, msgbuf)
        layout = layouts.get(msg_id)
        if layout is None:
            layout = layouts[msg_id] = _layout(msgtype)
        fields, strings = layout
        size = msgtype.unpacker.size
        payload = msgbuf[10:-2]
        if len(payload) < size:  # MAVLink 2 drops the payload's trailing zeros
            payload.extend(bytes(size - len(payload)))
        t = msgtype.unpacker.unpack(payload[:size])
        values = [t[tip] if k == 0 else list(t[tip : tip + k]) for tip, k in fields]
        for i in strings:
            values[i] = values[i].rstrip(b"\x00")
        try:
            m = msgtype(*values)
        except Exception as exc:
            raise module.MAVError(f"Unable to instantiate MAVLink message of type {msgtype} : {exc}") from exc
        m._signed = False
        m._msgbuf = msgbuf
        m._payload = msgbuf[6:-2]  # as pymavlink sets it
        m._crc = crc
        m._header = header(msg_id, msgbuf[2], msgbuf[3], msgbuf[1], msgbuf[4], msgbuf[5], msgbuf[6])
        return m

    return decode
