"""One MAVLink connection: opened from a pymavlink connection string with the atlas dialect, read by
its own thread, reopened with backoff when it fails, optionally signed.

A link knows nothing of the graph: it hands every decoded message to a callback and counts what it
drops (bad CRC or signature, unsigned where signing is required, unknown ids, read errors).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import stat
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from atlas_onboard.config import LinkConfig, SigningConfig
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import dialect

_logger = logging.getLogger(__name__)

SIGNING_EPOCH_S = 1420070400  # MAVLink signing timestamps count 10 us units since 2015-01-01
BACKOFF_S = (0.2, 0.5, 1.0, 2.0, 5.0)
PROTECTED = {"ATLAS_OBSERVATION", "ATLAS_FUSED_POSE", "TUNNEL"}  # never accepted unsigned when required

Handler = Callable[["Link", Any, int], None]


def read_key(path: Path) -> bytes:
    """A 32-byte signing key: 32 raw bytes, or 64 hex characters. Refused if others may read it."""
    try:
        st = path.stat()
        data = path.read_bytes()
    except OSError as exc:
        raise AtlasError(f"signing key {path}: cannot read: {exc.strerror}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise AtlasError(
            f"signing key {path}: readable by group or others (mode {stat.S_IMODE(st.st_mode):o}); chmod 600 it"
        )
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(data) == 32:
        return data
    raise AtlasError(f"signing key {path}: expected 32 bytes or 64 hex characters, got {len(data)} bytes")


def _now_signing_ts() -> int:
    return int((max(time.time(), SIGNING_EPOCH_S) - SIGNING_EPOCH_S) * 100_000)


class Link:
    """A MAVLink connection with a receive thread, reconnects, counters and optional signing."""

    def __init__(
        self,
        config: LinkConfig,
        name: str,
        system_id: int,
        component_id: int,
        state_dir: Path | None = None,
        link_id: int = 0,
    ) -> None:
        self.config = config
        self.name = name
        self.system_id = system_id
        self.component_id = component_id
        self.state_dir = state_dir
        self.link_id = link_id
        self.counters: Counter[str] = Counter()
        self.dialect = dialect.load()
        self._key = read_key(config.signing.key_file) if config.signing is not None else None
        self._conn: Any = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._handler: Handler | None = None
        self._backoff = 0
        self._last_ts_save = 0.0
        self.connected = threading.Event()

    # --- connection ---------------------------------------------------------------------------------

    def _open(self) -> None:
        url = self.config.url
        kwargs: dict[str, Any] = {"source_system": self.system_id, "source_component": self.component_id}
        if url.startswith(("/", "COM")):
            device, _, baud = url.partition(",")
            conn = mavutil.mavlink_connection(device, baud=int(baud or 57600), **kwargs)
        elif url.startswith("tcp:"):
            conn = mavutil.mavlink_connection(url, retries=0, **kwargs)  # one attempt: we do the backoff

            def closed() -> None:  # mavutil only prints on EOF/reset; make it an error we reopen on
                raise ConnectionError("TCP peer closed the connection")

            conn.handle_eof = conn.handle_disconnect = closed
        else:
            conn = mavutil.mavlink_connection(url, **kwargs)
        # Our dialect (common.xml plus the atlas messages) on this connection only.
        conn.mav = self.dialect.MAVLink(conn, srcSystem=self.system_id, srcComponent=self.component_id)
        conn.mav.robust_parsing = True
        # Our dialect speaks MAVLink 2 only; without this, mavutil's protocol auto-switch would replace
        # conn.mav with its global dialect on the first MAVLink 2 byte.
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        conn.first_byte = False
        if self._key is not None:
            self._setup_signing(conn, self.config.signing)  # type: ignore[arg-type]
        self._conn = conn
        self.connected.set()

    def _setup_signing(self, conn: Any, signing: SigningConfig) -> None:
        def allow_unsigned(_mav: Any, msg_id: int) -> bool:
            """Called by pymavlink for unsigned (or badly signed) messages: True lets one through."""
            if not signing.require:
                return True
            if getattr(self.dialect.mavlink_map.get(msg_id), "msgname", "") in PROTECTED:
                self.counters["rejected_unsigned_or_bad_signature"] += 1
                return False
            return True

        conn.setup_signing(
            self._key,
            sign_outgoing=signing.sign_outgoing,
            allow_unsigned_callback=allow_unsigned,
            initial_timestamp=max(_now_signing_ts(), self._load_timestamp() + 1),
            link_id=self.link_id,
        )

    def _ts_path(self) -> Path | None:
        if self.state_dir is None:
            return None
        digest = hashlib.sha256(f"{self.config.url}|{self.system_id}|{self.component_id}".encode()).hexdigest()[:12]
        return self.state_dir / f"signing-{digest}.json"

    def _load_timestamp(self) -> int:
        path = self._ts_path()
        if path is None:
            return 0
        try:
            # Saved periodically: add the save period so a restart never reuses a timestamp.
            return int(json.loads(path.read_text(encoding="utf-8"))["timestamp"]) + 10 * 100_000
        except (OSError, ValueError, KeyError, TypeError):
            return 0

    def save_timestamp(self) -> None:
        """Persist the signing timestamp (a companion without an RTC restarts with a clock in the past)."""
        path = self._ts_path()
        if path is None or self._conn is None or self._key is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps({"timestamp": int(self._conn.mav.signing.timestamp)}), encoding="utf-8")
            os.replace(tmp, path)
        except OSError as exc:
            self.counters["signing_state_write_errors"] += 1
            _logger.warning("%s: cannot save signing timestamp to %s: %s", self.name, path, exc.strerror)

    # --- threads ------------------------------------------------------------------------------------

    def start(self, handler: Handler) -> None:
        self._handler = handler
        with contextlib.suppress(Exception):
            self._open()
        self._thread = threading.Thread(target=self._run, name=f"link-{self.name}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.save_timestamp()
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
        self._conn = None

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._conn is None:
                delay = BACKOFF_S[min(self._backoff, len(BACKOFF_S) - 1)]
                if self._stop.wait(delay):
                    return
                try:
                    self._open()
                    self._backoff = 0
                    self.counters["reconnects"] += 1
                    _logger.info("%s: link %s open again", self.name, self.config.url)
                except Exception as exc:  # serial device gone, port in use, peer down: retry with backoff
                    self._backoff += 1
                    self.counters["open_errors"] += 1
                    _logger.debug("%s: cannot open %s: %s", self.name, self.config.url, exc)
                continue
            try:
                # Raw bytes and pymavlink's parser, not mavutil's recv_match: that one also keeps
                # per-message bookkeeping for interactive tools, which costs more than the decode.
                if not self._conn.select(0.05):
                    continue
                data = self._conn.recv(4096)
                msgs = self._conn.mav.parse_buffer(data) if data else None
            except Exception as exc:  # the device vanished or the peer went away: reopen with backoff
                self.counters["read_errors"] += 1
                _logger.warning("%s: link %s failed (%s); reopening", self.name, self.config.url, exc)
                self._drop()
                continue
            for msg in msgs or ():
                self._dispatch(msg)
            if self._key is not None and time.monotonic() - self._last_ts_save > 10.0:
                self._last_ts_save = time.monotonic()
                self.save_timestamp()

    def _drop(self) -> None:
        self.connected.clear()
        conn, self._conn = self._conn, None
        with contextlib.suppress(Exception):
            conn.close()

    def _dispatch(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(msg, "reason", ""))
            self.counters["rejected_bad_signature" if "signature" in reason else "rejected_bad_data"] += 1
            return
        if kind == "UNKNOWN" or type(msg).__name__ == "MAVLink_unknown":
            self.counters["rejected_unknown_id"] += 1
            return
        self.counters[f"rx_{kind.lower()}"] += 1
        if self._handler is not None:
            try:
                self._handler(self, msg, time.monotonic_ns())
            except Exception:  # a bug in a handler must not kill the link's thread
                self.counters["handler_errors"] += 1
                _logger.exception("%s: handler failed on %s", self.name, kind)

    # --- sending ------------------------------------------------------------------------------------

    def send(self, msg: Any) -> bool:
        """Send one message; False (counted) when the link is down or the write fails."""
        conn = self._conn
        if conn is None:
            self.counters["tx_dropped_link_down"] += 1
            return False
        try:
            with self._send_lock:
                conn.mav.send(msg)
        except Exception as exc:  # a write error is a dead link: the reader thread reopens it
            self.counters["tx_errors"] += 1
            _logger.debug("%s: send failed: %s", self.name, exc)
            return False
        self.counters[f"tx_{msg.get_type().lower()}"] += 1
        return True

    @property
    def mav(self) -> Any:
        """The dialect's MAVLink object of the current connection (for building messages), or None."""
        return self._conn.mav if self._conn is not None else None
