"""systemd integration with the standard library only: the notify protocol and signals as events.

The notify protocol (``man sd_notify``): a service started with ``Type=notify`` finds the address of
systemd's socket in ``$NOTIFY_SOCKET`` and sends it datagrams of newline-separated ``NAME=value``
assignments: ``READY=1`` once it serves, ``WATCHDOG=1`` at least once per ``WatchdogSec``,
``STOPPING=1`` when it begins to shut down, ``RELOADING=1`` (with ``MONOTONIC_USEC``) when it begins
to re-read its configuration, ``STATUS=...`` for ``systemctl status``. The address is a filesystem
path (``/run/systemd/notify``) or, with a leading ``@``, a name in Linux's abstract socket namespace.
Without ``$NOTIFY_SOCKET`` (a shell, a test, another supervisor) every call is a no-op.

Only the standard library is used, so that this module costs nothing to import and can be copied.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import time
from collections.abc import Mapping

from atlas_onboard.errors import AtlasError

_logger = logging.getLogger(__name__)

#: The signals a service handles: stop (SIGTERM from systemd, SIGINT from a terminal) and reload (SIGHUP).
SERVICE_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)

# systemd reads each datagram whole; a send that cannot complete within this is abandoned (and
# logged) rather than stalling the caller's loop.
_SEND_TIMEOUT_S = 1.0


class ServiceError(AtlasError):
    """The environment systemd gave the process is malformed (``WATCHDOG_USEC``, ``WATCHDOG_PID``),
    or signal handling cannot be set up (for instance from a thread other than the main thread)."""


def socket_address(notify_socket: str) -> str | None:
    """The ``AF_UNIX`` address for a ``$NOTIFY_SOCKET`` value, or None when it names none.

    ``/path`` is a filesystem socket; ``@name`` an abstract one (the ``@`` becomes a NUL byte).
    Anything else (a relative path, systemd's ``vsock:`` addresses for virtual machines) is not an
    ``AF_UNIX`` address this module can use.
    """
    if notify_socket.startswith("/"):
        return notify_socket
    if notify_socket.startswith("@") and len(notify_socket) > 1:
        return "\0" + notify_socket[1:]
    return None


class Notifier:
    """A client of systemd's notify protocol: sends datagrams to ``$NOTIFY_SOCKET``.

    Construct with :meth:`from_environ`. Every method returns True when the datagram was sent and
    False when notifications are disabled or the send failed; a failure is logged (a warning the
    first time, then at debug level) and never raised: a service must keep running if systemd's
    socket goes away. Not thread-safe; call it from the main loop.
    """

    def __init__(self, notify_socket: str | None) -> None:
        """``notify_socket`` is the value of ``$NOTIFY_SOCKET``; None or "" disables notifications."""
        self.notify_socket = notify_socket or None
        self._address: str | None = None
        self._sock: socket.socket | None = None
        self._failures = 0
        if self.notify_socket is not None:
            self._address = socket_address(self.notify_socket)
            if self._address is None:
                _logger.warning(
                    "NOTIFY_SOCKET=%r is neither an absolute path nor an @abstract name: systemd notifications off",
                    self.notify_socket,
                )

    @classmethod
    def from_environ(cls, environ: Mapping[str, str] | None = None) -> Notifier:
        """A notifier for ``environ["NOTIFY_SOCKET"]`` (default: ``os.environ``); disabled when unset."""
        env = os.environ if environ is None else environ
        return cls(env.get("NOTIFY_SOCKET"))

    @property
    def enabled(self) -> bool:
        """True when there is a socket address to send to."""
        return self._address is not None

    def notify(self, *assignments: str) -> bool:
        """Send one datagram of ``NAME=value`` assignments, one a line, e.g. ``notify("READY=1")``.

        Raises ValueError for an assignment without ``=`` or containing a newline (a newline would
        smuggle in another assignment); this is a programming error, not a runtime condition.
        """
        for a in assignments:
            if "=" not in a or "\n" in a:
                raise ValueError(f"expected one NAME=value assignment without a newline, got {a!r}")
        if not assignments:
            raise ValueError("expected at least one NAME=value assignment, got none")
        if self._address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                self._sock.settimeout(_SEND_TIMEOUT_S)
            self._sock.sendto("\n".join(assignments).encode("utf-8"), self._address)
        except OSError as exc:
            self._failures += 1
            level = logging.WARNING if self._failures == 1 else logging.DEBUG
            _logger.log(
                level, "systemd notification to %s failed (%d so far): %s", self.notify_socket, self._failures, exc
            )
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up is complete (systemd then runs units ordered after this one)."""
        return self.notify("READY=1", *self._status(status))

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the keep-alive ping; send it every :func:`watchdog_interval_us`."""
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        return self.notify("STOPPING=1", *self._status(status))

    def reloading(self, monotonic_usec: int | None = None, status: str | None = None) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC``: a reload has begun; send :meth:`ready` when it ends.

        ``monotonic_usec`` is ``CLOCK_MONOTONIC`` in microseconds when the reload began (systemd
        uses it to match the notification to its reload request); default: now.
        """
        if monotonic_usec is None:
            monotonic_usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify("RELOADING=1", f"MONOTONIC_USEC={int(monotonic_usec)}", *self._status(status))

    def status(self, text: str) -> bool:
        """``STATUS=text``: one line shown by ``systemctl status`` (newlines become spaces)."""
        return self.notify(*self._status(text))

    @staticmethod
    def _status(text: str | None) -> tuple[str, ...]:
        if text is None:
            return ()
        return ("STATUS=" + " ".join(text.splitlines()),)

    def close(self) -> None:
        """Close the socket (a later call opens a new one)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def watchdog_interval_us(environ: Mapping[str, str] | None = None, pid: int | None = None) -> int | None:
    """How often to send ``WATCHDOG=1``, in microseconds: half of ``$WATCHDOG_USEC``, as systemd advises.

    None when the watchdog is off (``WATCHDOG_USEC`` unset) or meant for another process
    (``WATCHDOG_PID`` set to a pid other than ``pid``, default: this process; systemd sets it so
    that children which inherit the environment do not answer for their parent).

    Raises ServiceError when either variable is not a positive integer.
    """
    env = os.environ if environ is None else environ
    raw_usec = env.get("WATCHDOG_USEC")
    if raw_usec is None:
        return None
    usec = _positive_int(raw_usec, "WATCHDOG_USEC", "microseconds")
    raw_pid = env.get("WATCHDOG_PID")
    if raw_pid is not None:
        owner = _positive_int(raw_pid, "WATCHDOG_PID", "a process id")
        if owner != (os.getpid() if pid is None else pid):
            return None
    return usec // 2


def _positive_int(raw: str, name: str, what: str) -> int:
    try:
        value = int(raw, 10)
    except ValueError:
        value = 0
    if value <= 0:
        raise ServiceError(f"{name}: expected a positive integer ({what}), got {raw!r}")
    return value
