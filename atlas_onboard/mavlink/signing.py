"""MAVLink 2 signing of a link: the key, pymavlink's signing set up on a connection, the check made
before a frame is decoded, and the outgoing timestamp kept on the wall clock across restarts.

Two fixes over pymavlink's signing, both needed by a swarm:

- pymavlink stores a stream's timestamp *before* it checks the signature, so one forged frame with
  a far-future timestamp (no key needed) would make every later genuine frame of that stream look
  like a replay. Here the signature is checked first, the timestamp only after (pymavlink's
  ``check_signature`` of the connection's parser is replaced by :meth:`LinkSigning.check`).
- pymavlink's outgoing timestamp only counts messages (+1 each), never the clock, so a node that has
  run a while signs far behind real time and a peer that restarts rejects it (more than 60 s behind)
  for good. Here it follows the wall clock, and never goes below the value persisted in ``state_dir``.
- pymavlink adopts any received timestamp as its own: one validly signed frame stamped near 2^48
  (a key holder, or a node with a broken clock) would push every node's timestamp there, wrap it,
  and persist it. Here a frame stamped more than REFUSE_AHEAD_S ahead of the wall clock is refused
  (counted, and said: it is this node's clock that may be behind), and the own timestamp is raised
  by what is received or loaded at most to MAX_AHEAD_S ahead of the wall clock.

The streams' last timestamps (the replay table) belong to the link, not to one connection: a reopened
connection keeps refusing what was seen before.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import stat
import struct
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from atlas_onboard.config import SigningConfig
from atlas_onboard.core.rejection import Rejection
from atlas_onboard.counters import Counters
from atlas_onboard.errors import AtlasError
from atlas_onboard.fsio import write_atomic

_logger = logging.getLogger(__name__)

SIGNING_EPOCH_S = 1420070400  # MAVLink signing timestamps count 10 us units since 2015-01-01
SIGNING_TICKS_PER_S = 100_000
STREAM_MAX_BEHIND_TICKS = 60 * SIGNING_TICKS_PER_S  # a new stream more than 60 s behind is refused
TIMESTAMP_SAVE_EVERY_S = 10.0
MAX_AHEAD_S = 10.0
"""How far ahead of the wall clock the own signing timestamp may be raised by a received or a saved
one (pymavlink raises it to any received value). It covers the save period added at a restart."""
REFUSE_AHEAD_S = 60.0
"""A signed frame stamped further than this ahead of the wall clock is refused (``signature_ahead``):
peers sign at most MAX_AHEAD_S ahead of their clocks, so this leaves 50 s of clock difference, as
pymavlink leaves 60 s behind (STREAM_MAX_BEHIND_TICKS)."""
CLOCK_WARN_EVERY_S = 10.0
PROTECTED = frozenset({"ATLAS_OBSERVATION", "ATLAS_FUSED_POSE", "TUNNEL"})  # never accepted unsigned when required
KEY_LEN = 32


def read_key(path: Path) -> bytes:
    """A 32-byte signing key: 32 raw bytes, or 64 hex characters. Refused if others may read it, or its
    group unless root owns it and the group is another (root:atlas mode 640: the service's group
    reads it, the service cannot change it)."""
    try:
        st = path.stat()
        data = path.read_bytes()
    except OSError as exc:
        raise AtlasError(f"signing key {path}: cannot read: {exc.strerror}") from None
    group_ok = stat.S_IRGRP if st.st_uid == 0 and st.st_gid != 0 else 0
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO) & ~group_ok:
        raise AtlasError(
            f"signing key {path}: readable by group or others (mode {stat.S_IMODE(st.st_mode):o}); chmod 600 it"
            " (or root-owned, chmod 640, group the service's)"
        )
    text = data.strip()
    if len(text) == 2 * KEY_LEN:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(data) == KEY_LEN:
        return data
    raise AtlasError(f"signing key {path}: expected 32 bytes or 64 hex characters, got {len(data)} bytes")


def signing_timestamp(wall_s: float) -> int:
    """A MAVLink signing timestamp (10 us units since 2015-01-01 UTC) from UNIX seconds."""
    return int((max(wall_s, SIGNING_EPOCH_S) - SIGNING_EPOCH_S) * SIGNING_TICKS_PER_S)


class LinkSigning:
    """The signing of one link (one key, one link id), on each connection it opens.

    Args:
        config: the link's signing settings (key file, require, sign_outgoing).
        dialect: the generated dialect module (to name a message id).
        link_id: the MAVLink signing link id of this connection.
        counters: the link's counters (rejections and signature failures are counted there).
        state_path: where the outgoing timestamp persists (None: not persisted).
        wall_clock: UNIX time in seconds.
    """

    def __init__(
        self,
        config: SigningConfig,
        dialect: ModuleType,
        link_id: int,
        counters: Counters,
        state_path: Path | None,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.key = read_key(config.key_file)
        self.dialect = dialect
        self.link_id = link_id
        self.counters = counters
        self.state_path = state_path
        self._wall = wall_clock
        self._bad_signature = False  # the frame being decoded was signed and failed the check
        self._last_save_s = time.monotonic()
        self.streams: dict[tuple[int, int, int], int] = {}  # (link id, system, component) -> last timestamp
        self._timestamp = 0  # the last own timestamp seen on a connection of this link
        self._next_clock_warn_s = 0.0

    def setup(self, conn: Any) -> None:
        """Sign (per ``sign_outgoing``) and check (per ``require``) on ``conn``'s parser."""
        signing = self.config

        def allow_unsigned(_mav: Any, msg_id: int) -> bool:
            """Called by pymavlink for unsigned (or badly signed) messages, before their payload is
            decoded: True lets one through. A protected message that was signed but failed the check
            (another key, a replay) is refused even without ``require``: it is no unsigned peer's."""
            bad_signature, self._bad_signature = self._bad_signature, False
            if not signing.require and not bad_signature:
                return True
            kind = self.dialect.mavlink_map.get(msg_id)  # the generated class; None for an unknown id
            if kind is not None and kind.msgname in PROTECTED:
                self.counters.inc(Rejection.UNSIGNED_OR_BAD_SIGNATURE)
                return False
            return True

        conn.setup_signing(
            self.key,
            sign_outgoing=signing.sign_outgoing,
            allow_unsigned_callback=allow_unsigned,
            initial_timestamp=max(signing_timestamp(self._wall()), self._load_timestamp() + 1, self._timestamp + 1),
            link_id=self.link_id,
        )
        mav = conn.mav
        mav.signing.stream_timestamps = self.streams  # the replay table outlives the connection
        mav.check_signature = lambda buf, src_system, src_component: self.check(mav, buf, src_system, src_component)

    def check(self, mav: Any, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        """pymavlink's check, in the safe order: the signature first, then the stream's timestamp."""
        signing = mav.signing
        link_id = msgbuf[-13]
        low, high = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        timestamp = low + (high << 32)
        digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        self._bad_signature = True  # until it passes: read by the allow_unsigned callback that follows
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            self.counters.inc("signature_mismatch")
            return False
        now_ticks = signing_timestamp(self._wall())
        if timestamp > now_ticks + int(REFUSE_AHEAD_S * SIGNING_TICKS_PER_S):
            self.counters.inc("signature_ahead")
            self._clock_behind(src_system, timestamp - now_ticks)
            return False
        stream = (link_id, src_system, src_component)
        last = signing.stream_timestamps.get(stream)
        if last is not None and timestamp <= last:
            self.counters.inc("signature_replayed")
            return False
        if last is None and timestamp + STREAM_MAX_BEHIND_TICKS < signing.timestamp:
            self.counters.inc("signature_stream_too_old")
            return False
        self._bad_signature = False
        signing.stream_timestamps[stream] = timestamp
        bound = now_ticks + int(MAX_AHEAD_S * SIGNING_TICKS_PER_S)
        if timestamp > bound:
            self._clock_behind(src_system, timestamp - now_ticks)
        signing.timestamp = max(signing.timestamp, min(timestamp, bound))
        return True

    def _clock_behind(self, src_system: int, ahead_ticks: int) -> None:
        """A peer signs ahead of this node's clock by more than MAX_AHEAD_S: counted, and said at most
        every CLOCK_WARN_EVERY_S (the peer's clock may be wrong, or this node's behind the mesh)."""
        self.counters.inc("signing_clock_behind")
        now = time.monotonic()
        if now >= self._next_clock_warn_s:
            self._next_clock_warn_s = now + CLOCK_WARN_EVERY_S
            _logger.warning(
                "signed frames from system %d are stamped %.0f s ahead of this node's clock: this node's clock"
                " may be behind the mesh (sync it: chrony); more than %.0f s ahead is refused",
                src_system, ahead_ticks / SIGNING_TICKS_PER_S, REFUSE_AHEAD_S,
            )  # fmt: skip

    def advance(self, conn: Any) -> None:
        """Keep the signing timestamp at least at the wall clock (it must rise with real time)."""
        signing = conn.mav.signing
        if signing.secret_key is not None:
            signing.timestamp = max(signing.timestamp, signing_timestamp(self._wall()))
            self._timestamp = signing.timestamp

    def save_due(self) -> bool:
        """Whether the timestamp is due to be persisted (every TIMESTAMP_SAVE_EVERY_S)."""
        if time.monotonic() - self._last_save_s > TIMESTAMP_SAVE_EVERY_S:
            self._last_save_s = time.monotonic()
            return True
        return False

    def _load_timestamp(self) -> int:
        path = self.state_path
        if path is None:
            return 0
        try:
            saved = int(json.loads(path.read_text(encoding="utf-8"))["timestamp"])
            saved_at_s = path.stat().st_mtime  # the wall clock when it was written
        except (OSError, ValueError, KeyError, TypeError):
            return 0
        # Never beyond MAX_AHEAD_S ahead of the clock when it was saved (or now, if later): no timestamp
        # this node signed was (see check()); a larger one is a future value adopted by an older version.
        bound = signing_timestamp(max(self._wall(), saved_at_s)) + int(MAX_AHEAD_S * SIGNING_TICKS_PER_S)
        if saved > bound:
            self.counters.inc("signing_state_repaired")
            _logger.warning(
                "signing timestamp in %s is %.0f s ahead of the clock it was saved with (adopted from a peer by an"
                " older version): repaired", path, (saved - bound) / SIGNING_TICKS_PER_S + MAX_AHEAD_S,
            )  # fmt: skip
        # Saved periodically: add the save period so a restart never reuses a timestamp.
        return min(saved, bound) + int(TIMESTAMP_SAVE_EVERY_S * SIGNING_TICKS_PER_S)

    def save(self, conn: Any, name: str) -> None:
        """Persist ``conn``'s signing timestamp (a companion without an RTC restarts with a clock in the past)."""
        path = self.state_path
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._timestamp = max(self._timestamp, int(conn.mav.signing.timestamp))
            write_atomic(path, json.dumps({"timestamp": self._timestamp}))
        except OSError as exc:
            self.counters.inc("signing_state_write_errors")
            _logger.warning("%s: cannot save signing timestamp to %s: %s", name, path, exc.strerror)
