"""The framing fast path: the one place atlas-onboard works around pymavlink's parser, with an off switch.

pymavlink's generated ``decode`` finds each field of a message with arrays by summing the lengths of
the fields before it, for every message it decodes, and its ``parse_buffer`` keeps byte-buffer
bookkeeping per message: for ATLAS_OBSERVATION (20 fields, three arrays) that is most of its time,
and a node in a swarm frames every peer's datagram. :func:`parser` gives the dialect's ``MAVLink``
object either as pymavlink makes it or, with the fast path on (the default), as
:func:`parser_class`'s subclass: the same checks, the same messages, the same parser state
(differential tests in ``tests/mavlink/test_framing.py``), and :class:`Deferred` frames decoded only
when needed.

The fast path subclasses the generated class and writes its parser state (``buf_index``,
``expected_length``, totals) as pymavlink's own parser leaves it: tied to pymavlink's internals, hence
the pinned range in ``pyproject.toml`` (``>=2.4.41,<2.5``). Off switch: ``ATLAS_ONBOARD_FRAMING=pymavlink``
in the environment (read at import) or :data:`FAST` set to False before links open; every message
then comes from pymavlink's own parser, decoded as it arrives.
"""

from __future__ import annotations

import os
import re
import struct
import threading
from types import ModuleType
from typing import Any

FAST = os.environ.get("ATLAS_ONBOARD_FRAMING", "fast") != "pymavlink"
"""Whether links frame with the fast path (else pymavlink's own parser)."""

_lock = threading.Lock()
_cache: dict[str, Any] = {}


def parser(module: ModuleType, conn: Any, system_id: int, component_id: int, deferred_ids: frozenset[int]) -> Any:
    """The dialect's ``MAVLink`` object for a connection: the fast path's, handing back the frames of
    ``deferred_ids`` as :class:`Deferred`, or with :data:`FAST` off pymavlink's own (decoding every
    message as it comes)."""
    if FAST:
        mav = parser_class(module)(conn, srcSystem=system_id, srcComponent=component_id)
        mav.deferred_ids = deferred_ids
    else:
        mav = module.MAVLink(conn, srcSystem=system_id, srcComponent=component_id)
    mav.robust_parsing = True
    return mav


def raise_on_close(conn: Any) -> None:
    """A TCP connection whose peer closed raises ConnectionError on the next read (pymavlink's
    ``mavtcp`` only prints and tries to reconnect by itself), so that the link reopens it with its
    own backoff."""

    def closed() -> None:
        raise ConnectionError("TCP peer closed the connection")

    conn.handle_eof = conn.handle_disconnect = closed


_MAGIC_V2 = 0xFD
_V1_OVERHEAD = 8  # MAVLink 1: 6-byte header, 2-byte checksum
_IFLAG_SIGNED = 0x01
_V2_OVERHEAD = 12  # 10-byte header, 2-byte checksum (unsigned)
_V2_HEADER = 10
_SIGNATURE_LEN = 13  # link id, 6-byte timestamp, 6-byte signature


def reset(mav: Any) -> None:
    """The parser's state as new: nothing of a previous datagram (a partial frame, a prefix error)
    may carry over into the next one. pymavlink's own attributes, as its constructor sets them."""
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = _V1_OVERHEAD
    mav.have_prefix_error = False


def parser_class(module: ModuleType) -> type:
    """The dialect's ``MAVLink`` class, faster for MAVLink 2 frames, with deferred decoding.

    pymavlink's generated ``decode`` finds each field of a message with arrays by summing the lengths
    of the fields before it, for every message it decodes: for ATLAS_OBSERVATION (20 fields, three
    arrays) that is about half of its time, and a node in a swarm decodes every peer's observation.
    This class computes each message type's field layout once and otherwise does what pymavlink
    does: the same checks, the same message object (fields, header, payload, checksum). Its
    ``decode`` (pymavlink's parser calls it for a frame split across reads) leaves to pymavlink's
    own: MAVLink 1, signed frames, any frame while a signing key is set, unknown ids, a wrong length
    or checksum (pymavlink raises its own error for those). Tested equal to pymavlink's on every
    message of the dialect.

    ``parse_buffer`` takes a read that starts at a frame (a UDP datagram holds whole frames) a frame
    at a time, rather than pymavlink's byte-buffer bookkeeping per message, signed or not: the
    signing policy is pymavlink's decode's, step for step (the connection's ``check_signature``, the
    ``allow_unsigned_callback``, the same counts, BAD_DATA "Invalid signature" for a refused frame).
    At the first thing that is not a whole MAVLink 2 frame of a known id with a valid checksum (a
    partial frame of a stream, bad data, MAVLink 1, an unknown flag) it hands the rest of the read to
    pymavlink's ``parse_buffer``, which then parses it exactly as it would have. Frames of the ids in
    ``deferred_ids`` come back as :class:`Deferred`: checked as above (the signature included),
    decoded only when a field is asked for.
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
    """A frame that passed every check of a decode (a MAVLink 2 frame of a known id, its length,
    checksum and signing right), decoded only when needed: :meth:`decoded` gives pymavlink's message
    (the same object the parser would have returned), a scalar field read as an attribute
    (``frame.sensor_id``) is read from the payload alone, any other field decodes. A receiver that
    keeps only the newest of many messages, or needs only their sender, then decodes few. Besides the
    fields it answers pymavlink's header getters, ``get_msgbuf`` and ``to_dict``."""

    __slots__ = ("_build", "_msg", "_msgbuf", "_msgtype", "_sig_ok", "_trailer")

    def __init__(self, build: Any, msgbuf: bytearray, msgtype: Any, trailer: int = 2, sig_ok: bool = False) -> None:
        self._build = build
        self._msgbuf = msgbuf
        self._msgtype = msgtype
        self._trailer = trailer  # bytes after the payload: the checksum, and the signature if signed
        self._sig_ok = sig_ok
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

    def get_signed(self) -> bool:
        return self._sig_ok

    def decoded(self) -> Any:
        """pymavlink's message for this frame (decoded once)."""
        if self._msg is None:
            self._msg = self._build(self._msgbuf, self._msgtype, self._trailer, self._sig_ok)
        return self._msg

    def get_msgbuf(self) -> bytearray:
        return self._msgbuf

    def to_dict(self) -> dict[str, Any]:
        return dict(self.decoded().to_dict())

    def __repr__(self) -> str:
        return f"Deferred({self.get_type()} from {self.get_srcSystem()}/{self.get_srcComponent()})"


def is_signed(msg: Any) -> bool:
    """Whether a message that passed the parser came in a frame whose signature passed the check."""
    return bool(msg.get_signed())


_deferred: dict[Any, type[Deferred]] = {}  # by message class: a regenerated dialect gets its own


def _deferred_class(msgtype: Any) -> type[Deferred]:
    """:class:`Deferred` for ``msgtype``, its scalar number fields as properties that read the payload
    (a field asked for again reads it again: cheaper than keeping what was read)."""
    cls = _deferred.get(msgtype)
    if cls is None:
        readers = _scalar_readers(msgtype)
        # The other fields (arrays, strings, characters) from pymavlink's message, decoded once.
        props = {name: property(_field(readers[name]) if name in readers else _decoded_field(name))
                 for name in msgtype.fieldnames}  # fmt: skip
        cls = _deferred[msgtype] = type(f"Deferred_{msgtype.msgname}", (Deferred,), {"__slots__": (), **props})
    return cls


def _decoded_field(name: str) -> Any:
    return lambda self: getattr(self.decoded(), name)


def _field(read: Any) -> Any:
    return lambda self: read(self._msgbuf, len(self._msgbuf) - self._trailer)


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

    def read(msgbuf: bytearray, end: int) -> Any:  # ``end``: the payload's (the checksum follows)
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
    bad_data = module.MAVLink_bad_data
    layouts: dict[int, tuple[list[tuple[int, int]], list[int]]] = {}
    generic_decode, generic_parse = module.MAVLink.decode, module.MAVLink.parse_buffer

    def checksum_ok(msgbuf: bytearray, msgtype: Any, trailer: int = 2) -> bool:
        crcbuf = msgbuf[1:-trailer]
        crcbuf.append(msgtype.crc_extra)
        return bool(x25crc(crcbuf).crc == msgbuf[-trailer] | msgbuf[1 - trailer] << 8)

    def signing_accepts(mav: Any, msgbuf: bytearray, msg_id: int, signed: bool) -> tuple[bool, bool]:
        """(accepted, signature good): pymavlink's decode's signing policy, with its counts."""
        signing = mav.signing
        sig_ok = False
        if signed:
            signing.sig_count += 1
        if signing.secret_key is None:
            return True, False
        accept = False
        if signed:
            sig_ok = accept = mav.check_signature(msgbuf, msgbuf[5], msgbuf[6])
            if sig_ok:
                signing.goodsig_count += 1
            else:
                signing.badsig_count += 1
        if not accept and signing.allow_unsigned_callback is not None:
            accept = signing.allow_unsigned_callback(mav, msg_id)
            if accept:
                signing.unsigned_count += 1
            else:
                signing.reject_count += 1
        return accept, sig_ok

    def build(msgbuf: bytearray, msgtype: Any, trailer: int = 2, sig_ok: bool = False) -> Any:
        """The message of a frame whose checks have passed (``trailer``: the bytes after its payload)."""
        msg_id = msgtype.id
        layout = layouts.get(msg_id)
        if layout is None:
            layout = layouts[msg_id] = _layout(msgtype)
        fields, strings = layout
        size = msgtype.unpacker.size
        payload = msgbuf[10:-trailer]
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
        m._signed = sig_ok
        if sig_ok:
            m._link_id = msgbuf[-13]
        m._msgbuf = msgbuf
        m._payload = msgbuf[6:-trailer]  # as pymavlink sets it
        m._crc = msgbuf[-trailer] | msgbuf[1 - trailer] << 8
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
        if self.buf_index != len(self.buf) or self.callback is not None:
            return generic_parse(self, s)  # a partial frame is waiting, or a callback: pymavlink's way
        out: list[Any] = []
        deferred = self.deferred_ids
        errors = 0
        i, n = 0, len(s)
        while n - i >= _V2_OVERHEAD and s[i] == _MAGIC_V2 and s[i + 2] in (0, _IFLAG_SIGNED):
            signed = s[i + 2] == _IFLAG_SIGNED
            trailer = 2 + _SIGNATURE_LEN if signed else 2
            end = i + s[i + 1] + _V2_HEADER + trailer
            msgtype = mavlink_map.get(s[i + 7] | s[i + 8] << 8 | s[i + 9] << 16)
            if end > n or msgtype is None:
                break
            msgbuf = bytearray(s[i:end])
            if not checksum_ok(msgbuf, msgtype, trailer):
                break
            i = end
            accepted, sig_ok = signing_accepts(self, msgbuf, msgtype.id, signed)
            if not accepted:
                out.append(bad_data(msgbuf, "Invalid signature"))
                errors += 1
            elif msgtype.id in deferred:
                out.append(_deferred_class(msgtype)(build, msgbuf, msgtype, trailer, sig_ok))
            else:
                out.append(build(msgbuf, msgtype, trailer, sig_ok))
        if out:  # the parser's state as pymavlink leaves it after whole frames
            self.total_bytes_received += i
            self.total_packets_received += len(out)
            self.total_receive_errors += errors
            self.have_prefix_error = False
            self.expected_length = _V2_OVERHEAD
        if i < n:
            rest = generic_parse(self, s[i:] if i else s)
            if rest:
                out.extend(rest)
        return out or None

    return decode, parse_buffer
