"""systemd integration with the standard library only: the notify protocol and signals as events.

The notify protocol (``man sd_notify``): a service started with ``Type=notify`` finds the address of
systemd's socket in ``$NOTIFY_SOCKET`` and sends it datagrams of newline-separated ``NAME=value``
assignments: ``READY=1`` once it serves, ``WATCHDOG=1`` at least once per ``WatchdogSec``,
``STOPPING=1`` when it begins to shut down, ``RELOADING=1`` (with ``MONOTONIC_USEC``) when it begins
to re-read its configuration, ``STATUS=...`` for ``systemctl status``. The address is a filesystem
path (``/run/systemd/notify``) or, with a leading ``@``, a name in Linux's abstract socket namespace.
Without ``$NOTIFY_SOCKET`` (a shell, a test, another supervisor) every call is a no-op.

Signals (:class:`SignalPipe`): the handlers only write the signal's number, one byte, to a socket
pair; the main loop waits on the other end (``select`` it, or call :meth:`SignalPipe.wait`) and
acts on what arrived, in order, outside signal context. No work ever runs inside a handler.

Only the standard library is used, so that this module costs nothing to import and can be copied.
"""

from __future__ import annotations

import logging
import os
import select
import signal
import socket
import threading
import time
from collections.abc import Iterable, Mapping
from types import FrameType, TracebackType

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


class SignalPipe:
    """Signals delivered to a loop as events: handlers only write the signal number to a socket pair.

    Use from the main thread (Python runs signal handlers there and only there)::

        with SignalPipe() as signals:
            while True:
                for sig in signals.wait(timeout_s=0.5):
                    if sig == signal.SIGHUP:
                        reload()
                    else:
                        return 0      # SIGTERM or SIGINT: leave the loop, clean up, exit 0
                do_periodic_work()

    :meth:`fileno` is the read end for a ``select``/``selectors`` loop that waits on other sockets
    too; after it reports the descriptor readable, :meth:`pending` returns what arrived. Each
    delivered signal is one byte, so two SIGHUPs are two events and their order is kept; should
    the pipe ever fill (thousands undrained), further bytes are dropped, never blocking a handler.
    Leaving the ``with`` block (or :meth:`close`) restores the previous handlers.
    """

    def __init__(self, signals: Iterable[signal.Signals] = SERVICE_SIGNALS) -> None:
        self.signals = tuple(signal.Signals(s) for s in signals)
        if not self.signals:
            raise ValueError("expected at least one signal to handle, got none")
        self._read: socket.socket | None = None
        self._write: socket.socket | None = None
        self._previous: dict[signal.Signals, object] = {}

    def install(self) -> SignalPipe:
        """Create the socket pair and install the handlers; returns self. Main thread only."""
        if threading.current_thread() is not threading.main_thread():
            raise ServiceError("signal handlers can only be installed from the main thread")
        if self._read is not None:
            raise ServiceError("this SignalPipe is already installed")
        self._read, self._write = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        self._read.setblocking(False)
        self._write.setblocking(False)
        try:
            for sig in self.signals:
                self._previous[sig] = signal.signal(sig, self._handler)
        except BaseException:
            self.close()
            raise
        return self

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        # The whole handler: one byte out, nothing else (no locks, no logging, no allocation to speak of).
        write = self._write
        if write is not None:
            try:
                write.send(bytes((signum,)))
            except OSError:  # full (BlockingIOError) or closed: drop rather than block or raise here
                pass

    def fileno(self) -> int:
        """The read end's descriptor (readable when a signal has arrived)."""
        if self._read is None:
            raise ServiceError("SignalPipe is not installed (call install() or use it in a with block)")
        return self._read.fileno()

    def pending(self) -> list[signal.Signals]:
        """The signals that arrived since the last call, oldest first, without waiting."""
        if self._read is None:
            raise ServiceError("SignalPipe is not installed (call install() or use it in a with block)")
        data = b""
        while True:
            try:
                chunk = self._read.recv(4096)
            except (BlockingIOError, InterruptedError):
                break
            if not chunk:
                break
            data += chunk
        return [signal.Signals(b) for b in data]

    def wait(self, timeout_s: float | None = None) -> list[signal.Signals]:
        """Wait up to ``timeout_s`` seconds (None: for ever) for a signal; return every one that arrived.

        Returns as soon as one has arrived (with any others already queued), or [] on timeout.
        """
        if timeout_s is not None and timeout_s < 0:
            raise ValueError(f"expected a timeout >= 0 s or None, got {timeout_s}")
        got = self.pending()
        if got:
            return got
        # A signal interrupting select runs its handler first, then select is retried (PEP 475) and
        # sees the byte the handler wrote: nothing can be lost between pending() and select().
        select.select([self.fileno()], [], [], timeout_s)
        return self.pending()

    def close(self) -> None:
        """Restore the previous handlers and close the socket pair (safe to call twice)."""
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)  # type: ignore[arg-type]
        self._previous.clear()
        for sock in (self._write, self._read):
            if sock is not None:
                sock.close()
        self._read = self._write = None

    def __enter__(self) -> SignalPipe:
        return self.install()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
