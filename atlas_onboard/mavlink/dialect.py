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
import re
import shutil
import struct
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
_V2_HEADER = 10


def parser_class(module: ModuleType) -> type:
    """The dialect's ``MAVLink`` class, faster for unsigned MAVLink 2 frames, with deferred decoding.

    pymavlink's generated ``decode`` finds each field of a message with arrays by summing the lengths
    of the fields before it, for every message it decodes: for ATLAS_OBSERVATION (20 fields, three
    arrays) that is about half of its time, and a node in a swarm decodes every peer's observation.
    This class computes each message type's field layout once and otherwise does what pymavlink
    does: the same checks, the same message object (fields, header, payload, checksum). Anything
    else goes to pymavlink's own ``decode`` unchanged: MAVLink 1, signed frames, any frame while a
    signing key is set (unsigned frames are then the signing callback's to judge), unknown ids, a
    wrong length or checksum (pymavlink raises its own error for those). Tested equal to pymavlink's
    on every message of the dialect.

    ``parse_buffer`` takes a read that starts at a frame (a UDP datagram holds whole frames) a frame
    at a time, rather than pymavlink's byte-buffer bookkeeping per message; at the first thing that
    is not a whole, valid, unsigned MAVLink 2 frame of a known id (a partial frame of a stream, bad
    data, MAVLink 1, a signed frame) it hands the rest of the read to pymavlink's ``parse_buffer``,
    which then parses it exactly as it would have. Frames of the ids in ``deferred_ids`` come back as
    :class:`Deferred`: checked as above, decoded only when a field is asked for.
    """
    with _lock:
        cls = _cache.get("parser")
        if cls is None or cls.__bases__[0] is not module.MAVLink:
            decode, parse_buffer = _decoder(module)
            cls = _cache["parser"] = type(
                "AtlasMAVLink",
                (module.MAVLink,),
                {"decode": decode, "parse_buffer": parse_buffer, "deferred_ids": frozenset()},
            )
    return cls


class Deferred:
    """A frame that passed every check of a decode (an unsigned MAVLink 2 frame of a known id, its
    length and checksum right), decoded only when needed: :meth:`decoded` gives pymavlink's message
    (the same object the parser would have returned), a scalar field read as an attribute
    (``frame.sensor_id``) is read from the payload alone, any other attribute decodes. A receiver
    that keeps only the newest of many messages, or needs only their sender, then decodes few."""

    __slots__ = ("_build", "_msg", "_msgbuf", "_msgtype")

    def __init__(self, build: Any, msgbuf: bytearray, msgtype: Any) -> None:
        self._build = build
        self._msgbuf = msgbuf
        self._msgtype = msgtype
        self._msg: Any = None

    def get_type(self) -> str:
        return str(self._msgtype.msgname)

    def get_msgId(self) -> int:  # pymavlink's names, from here on
        return int(self._msgtype.id)

    def get_srcSystem(self) -> int:
        return self._msgbuf[5]

    def get_srcComponent(self) -> int:
        return self._msgbuf[6]

    def get_seq(self) -> int:
        return self._msgbuf[4]

    def decoded(self) -> Any:
        """pymavlink's message for this frame (decoded once)."""
        if self._msg is None:
            self._msg = self._build(self._msgbuf, self._msgtype)
        return self._msg

    def __getattr__(self, name: str) -> Any:
        return getattr(self.decoded(), name)

    def __repr__(self) -> str:
        return f"Deferred({self.get_type()} from {self.get_srcSystem()}/{self.get_srcComponent()})"


_deferred: dict[Any, type[Deferred]] = {}  # by message class: a regenerated dialect gets its own


def _deferred_class(msgtype: Any) -> type[Deferred]:
    """:class:`Deferred` for ``msgtype``, its scalar number fields as properties that read the payload
    (a field asked for again reads it again: cheaper than keeping what was read)."""
    cls = _deferred.get(msgtype)
    if cls is None:
        props = {name: property(_field(read)) for name, read in _scalar_readers(msgtype).items()}
        cls = _deferred[msgtype] = type(f"Deferred_{msgtype.msgname}", (Deferred,), {"__slots__": (), **props})
    return cls


def _field(read: Any) -> Any:
    return lambda self: read(self._msgbuf)


def _scalar_readers(msgtype: Any) -> dict[str, Any]:
    """For each scalar number field of ``msgtype``: a function reading it from a frame, as pymavlink's
    decode would (a payload shortened by MAVLink 2's trailing-zero truncation reads as zeros)."""
    starts: list[tuple[int, str]] = []  # each item of the unpacked tuple: its payload offset and code
    at = 0
    for count, code in re.findall(r"(\d*)([a-zA-Z])", msgtype.unpacker.format):
        n, size = int(count or 1), struct.calcsize("<" + code)
        if code == "s":
            starts.append((at, code))
        else:
            starts.extend((at + k * size, code) for k in range(n))
        at += n * size
    fields, strings = _layout(msgtype)
    readers = {}
    for i, (tip, k) in enumerate(fields):
        offset, code = starts[tip]
        if k == 0 and i not in strings and code not in "cs":
            readers[msgtype.fieldnames[i]] = _reader(struct.Struct("<" + code), _V2_HEADER + offset)
    return readers


def _reader(unpacker: struct.Struct, start: int) -> Any:
    size = unpacker.size

    def read(msgbuf: bytearray) -> Any:
        end = len(msgbuf) - 2  # the payload's end (the checksum follows)
        if start + size <= end:
            return unpacker.unpack_from(msgbuf, start)[0]
        return unpacker.unpack(bytes(msgbuf[start:end]).ljust(size, b"\x00"))[0]

    return read


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


def _decoder(module: ModuleType) -> tuple[Any, Any]:
    """The parser's ``decode`` and ``parse_buffer`` (see :func:`parser_class`)."""
    mavlink_map, header, x25crc = module.mavlink_map, module.MAVLink_header, module.x25crc
    layouts: dict[int, tuple[list[tuple[int, int]], list[int]]] = {}
    generic_decode, generic_parse = module.MAVLink.decode, module.MAVLink.parse_buffer

    def checksum_ok(msgbuf: bytearray, msgtype: Any) -> bool:
        crcbuf = msgbuf[1:-2]
        crcbuf.append(msgtype.crc_extra)
        return bool(x25crc(crcbuf).crc == msgbuf[-2] | msgbuf[-1] << 8)

    def build(msgbuf: bytearray, msgtype: Any) -> Any:
        """The message of a frame whose checks have passed."""
        msg_id = msgtype.id
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
        m._crc = msgbuf[-2] | msgbuf[-1] << 8
        m._header = header(msg_id, msgbuf[2], msgbuf[3], msgbuf[1], msgbuf[4], msgbuf[5], msgbuf[6])
        return m

    def decode(self: Any, msgbuf: bytearray) -> Any:
        n = len(msgbuf)
        if n < _V2_OVERHEAD or msgbuf[0] != _MAGIC_V2 or msgbuf[2] or self.signing.secret_key is not None:
            return generic_decode(self, msgbuf)
        msgtype = mavlink_map.get(msgbuf[7] | msgbuf[8] << 8 | msgbuf[9] << 16)
        if msgtype is None or msgbuf[1] != n - _V2_OVERHEAD or not checksum_ok(msgbuf, msgtype):
            return generic_decode(self, msgbuf)
        return build(msgbuf, msgtype)

    def parse_buffer(self: Any, s: Any) -> list[Any] | None:
        if self.buf_index != len(self.buf) or self.signing.secret_key is not None or self.callback is not None:
            return generic_parse(self, s)  # a partial frame is waiting, or signing: pymavlink's way
        out: list[Any] = []
        deferred = self.deferred_ids
        i, n = 0, len(s)
        while n - i >= _V2_OVERHEAD and s[i] == _MAGIC_V2 and not s[i + 2]:
            end = i + s[i + 1] + _V2_OVERHEAD
            msgtype = mavlink_map.get(s[i + 7] | s[i + 8] << 8 | s[i + 9] << 16)
            if end > n or msgtype is None:
                break
            msgbuf = bytearray(s[i:end])
            if not checksum_ok(msgbuf, msgtype):
                break
            if msgtype.id in deferred:
                out.append(_deferred_class(msgtype)(build, msgbuf, msgtype))
            else:
                out.append(build(msgbuf, msgtype))
            i = end
        if out:  # the parser's state as pymavlink leaves it after whole frames
            self.total_bytes_received += i
            self.total_packets_received += len(out)
            self.have_prefix_error = False
            self.expected_length = _V2_OVERHEAD
        if i < n:
            rest = generic_parse(self, s[i:] if i else s)
            if rest:
                out.extend(rest)
        return out or None

    return decode, parse_buffer
