"""The systemd notify client and the signal pipe: exact datagrams on a real test NOTIFY_SOCKET (a
filesystem socket and an abstract one), watchdog settings, and a child process driven by real signals."""

import logging
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
import uuid
from pathlib import Path

import pytest

from atlas_onboard.service import Notifier, ServiceError, SignalPipe, socket_address, watchdog_interval_us

REPO = Path(__file__).resolve().parents[1]
DEADLINE_S = 20.0  # generous: only a hang reaches it; nothing here measures time


@pytest.fixture
def notify_socket():
    """A bound datagram socket standing in for systemd's; yields (NOTIFY_SOCKET value, socket)."""
    # AF_UNIX paths are limited to 107 bytes: pytest's tmp_path can be longer, so use a short directory.
    with tempfile.TemporaryDirectory(prefix="atlas-notify-") as tmp:
        path = str(Path(tmp) / "notify.sock")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(path)
        sock.settimeout(DEADLINE_S)
        yield path, sock
        sock.close()


def test_each_notification_is_one_exact_datagram(notify_socket):
    path, sock = notify_socket
    notifier = Notifier.from_environ({"NOTIFY_SOCKET": path})
    assert notifier.enabled
    assert notifier.ready("running as drone1")
    assert sock.recv(4096) == b"READY=1\nSTATUS=running as drone1"
    assert notifier.ready()
    assert sock.recv(4096) == b"READY=1"
    assert notifier.watchdog()
    assert sock.recv(4096) == b"WATCHDOG=1"
    assert notifier.status("reload refused:\nworld.yaml: entities.d1: unknown key")
    assert sock.recv(4096) == b"STATUS=reload refused: world.yaml: entities.d1: unknown key"
    assert notifier.reloading(monotonic_usec=1234567)
    assert sock.recv(4096) == b"RELOADING=1\nMONOTONIC_USEC=1234567"
    assert notifier.reloading(monotonic_usec=42, status="re-reading world.yaml")
    assert sock.recv(4096) == b"RELOADING=1\nMONOTONIC_USEC=42\nSTATUS=re-reading world.yaml"
    assert notifier.stopping("SIGTERM")
    assert sock.recv(4096) == b"STOPPING=1\nSTATUS=SIGTERM"
    assert notifier.notify("STATUS=a", "ERRNO=5")
    assert sock.recv(4096) == b"STATUS=a\nERRNO=5"
    notifier.close()
    assert notifier.watchdog()  # a closed notifier reopens its socket
    assert sock.recv(4096) == b"WATCHDOG=1"
    notifier.close()


def test_abstract_namespace_socket():
    name = f"atlas-onboard-test-{os.getpid()}-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(DEADLINE_S)
    try:
        with Notifier.from_environ({"NOTIFY_SOCKET": "@" + name}) as notifier:
            assert notifier.ready("up")
            assert notifier.stopping()
        assert sock.recv(4096) == b"READY=1\nSTATUS=up"
        assert sock.recv(4096) == b"STOPPING=1"
    finally:
        sock.close()


def test_socket_addresses():
    assert socket_address("/run/systemd/notify") == "/run/systemd/notify"
    assert socket_address("@systemd-notify") == "\0systemd-notify"
    assert socket_address("@") is None
    assert socket_address("run/notify") is None
    assert socket_address("vsock:2:1234") is None


def test_reloading_stamps_the_monotonic_clock_in_microseconds(notify_socket):
    path, sock = notify_socket
    before_us = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    assert Notifier(path).reloading()
    after_us = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    first, second = sock.recv(4096).split(b"\n")
    assert first == b"RELOADING=1"
    name, _, value = second.partition(b"=")
    assert name == b"MONOTONIC_USEC"
    assert before_us <= int(value) <= after_us  # the same clock and unit as systemd's, not wall time or ns


@pytest.mark.parametrize("environ", [{}, {"NOTIFY_SOCKET": ""}])
def test_without_notify_socket_every_call_is_a_noop(environ, caplog):
    notifier = Notifier.from_environ(environ)
    assert not notifier.enabled
    assert notifier.ready("x") is False
    assert notifier.watchdog() is False
    assert notifier.stopping() is False
    assert notifier.reloading(monotonic_usec=1) is False
    assert caplog.records == []


def test_an_unusable_address_disables_notifications_with_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="atlas_onboard.service"):
        notifier = Notifier("relative/notify.sock")
    assert not notifier.enabled
    assert notifier.ready() is False
    assert len(caplog.records) == 1
    assert "NOTIFY_SOCKET='relative/notify.sock'" in caplog.records[0].getMessage()


def test_a_failed_send_is_logged_once_and_never_raised(tmp_path, caplog):
    missing = str(tmp_path / "gone.sock")
    notifier = Notifier(missing)
    assert notifier.enabled
    with caplog.at_level(logging.DEBUG, logger="atlas_onboard.service"):
        assert notifier.ready() is False
        assert notifier.watchdog() is False
    levels = [r.levelno for r in caplog.records]
    assert levels == [logging.WARNING, logging.DEBUG]
    assert missing in caplog.records[0].getMessage()
    notifier.close()


@pytest.mark.parametrize("bad", [("READY",), ("READY=1\nWATCHDOG=1",), ()])
def test_malformed_assignments_are_programming_errors(bad):
    with pytest.raises(ValueError, match="NAME=value"):
        Notifier(None).notify(*bad)


@pytest.mark.parametrize(
    ("environ", "expected_us"),
    [
        ({}, None),
        ({"WATCHDOG_USEC": "5000000"}, 2_500_000),
        ({"WATCHDOG_USEC": "3"}, 1),
        ({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "4242"}, 2_500_000),
        ({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "4243"}, None),
        ({"WATCHDOG_PID": "4242"}, None),
    ],
)
def test_watchdog_interval_is_half_the_timeout_for_this_process(environ, expected_us):
    assert watchdog_interval_us(environ, pid=4242) == expected_us


def test_watchdog_pid_defaults_to_this_process():
    env = {"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(os.getpid())}
    assert watchdog_interval_us(env) == 500_000
    env["WATCHDOG_PID"] = str(os.getpid() + 1)
    assert watchdog_interval_us(env) is None


@pytest.mark.parametrize(
    ("environ", "message"),
    [
        ({"WATCHDOG_USEC": "0"}, "WATCHDOG_USEC: expected a positive integer (microseconds), got '0'"),
        ({"WATCHDOG_USEC": "-5"}, "WATCHDOG_USEC: expected a positive integer (microseconds), got '-5'"),
        ({"WATCHDOG_USEC": "5s"}, "WATCHDOG_USEC: expected a positive integer (microseconds), got '5s'"),
        ({"WATCHDOG_USEC": ""}, "WATCHDOG_USEC: expected a positive integer (microseconds), got ''"),
        (
            {"WATCHDOG_USEC": "100", "WATCHDOG_PID": "self"},
            "WATCHDOG_PID: expected a positive integer (a process id), got 'self'",
        ),
    ],
)
def test_malformed_watchdog_settings_are_reported(environ, message):
    with pytest.raises(ServiceError) as info:
        watchdog_interval_us(environ, pid=1)
    assert str(info.value) == message


def test_signal_pipe_queues_each_signal_in_order_and_restores_handlers():
    before = {s: signal.getsignal(s) for s in (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)}
    with SignalPipe([signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2]) as signals:
        assert signals.pending() == []
        assert signals.wait(timeout_s=0) == []
        # Directed at this (the main) thread, each is delivered, and its handler run, before the next.
        for sig in (signal.SIGUSR1, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2):
            signal.pthread_kill(threading.get_ident(), sig)
        assert signals.wait(timeout_s=DEADLINE_S) == [signal.SIGUSR1, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2]
        assert signals.pending() == []
        signal.pthread_kill(threading.get_ident(), signal.SIGHUP)
        readable, _, _ = select.select([signals], [], [], DEADLINE_S)  # usable with select via fileno()
        assert readable == [signals]
        assert signals.pending() == [signal.SIGHUP]
    assert {s: signal.getsignal(s) for s in before} == before


def test_signal_pipe_wakes_a_waiting_loop_from_another_thread():
    with SignalPipe([signal.SIGUSR1]) as signals:
        sender = threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGUSR1))
        sender.start()
        try:
            assert signals.wait(timeout_s=DEADLINE_S) == [signal.SIGUSR1]
        finally:
            sender.join()


def test_signal_pipe_needs_the_main_thread_and_one_install():
    errors = []

    def install():
        try:
            SignalPipe([signal.SIGUSR1]).install()
        except ServiceError as exc:
            errors.append(str(exc))

    t = threading.Thread(target=install)
    t.start()
    t.join()
    assert errors == ["signal handlers can only be installed from the main thread"]
    pipe = SignalPipe([signal.SIGUSR1])
    with pytest.raises(ServiceError, match="not installed"):
        pipe.pending()
    with pipe, pytest.raises(ServiceError, match="already installed"):
        pipe.install()
    with pytest.raises(ValueError, match="timeout"):
        SignalPipe([signal.SIGUSR1]).wait(timeout_s=-1)


# A minimal service in the shape the node takes: READY, WATCHDOG while idle, RELOADING then READY on
# SIGHUP, STOPPING and exit status 0 on SIGTERM or SIGINT. It prints each signal as it handles it.
CHILD = textwrap.dedent(
    """
    import signal
    import sys

    from atlas_onboard.service import Notifier, SignalPipe, watchdog_interval_us


    def main(argv):
        notifier = Notifier.from_environ()
        interval_us = watchdog_interval_us()
        with SignalPipe() as signals:
            notifier.ready("serving")
            print("ready", flush=True)
            while True:
                got = signals.wait(timeout_s=interval_us / 1e6)
                if not got:
                    notifier.watchdog()
                for sig in got:
                    print(sig.name, flush=True)
                    if sig == signal.SIGHUP:
                        notifier.reloading()
                        notifier.ready("reloaded")
                    else:
                        notifier.stopping()
                        return 0


    if __name__ == "__main__":
        sys.exit(main(sys.argv[1:]))
    """
)


def _readline(proc: subprocess.Popen, deadline: float) -> str:
    readable, _, _ = select.select([proc.stdout], [], [], max(deadline - time.monotonic(), 0.0))
    assert readable, "the child printed nothing before the deadline"
    return proc.stdout.readline().strip()


def _next_event(sock: socket.socket) -> bytes:
    """The next datagram that is not a watchdog ping."""
    while True:
        data = sock.recv(4096)
        if data != b"WATCHDOG=1":
            return data


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT])
def test_child_service_lifecycle_under_real_signals(tmp_path, notify_socket, stop):
    path, sock = notify_socket
    script = tmp_path / "child.py"
    script.write_text(CHILD, encoding="utf-8")
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="100000", PYTHONPATH=str(REPO))
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + DEADLINE_S
        assert _readline(proc, deadline) == "ready"
        assert sock.recv(4096) == b"READY=1\nSTATUS=serving"
        assert sock.recv(4096) == b"WATCHDOG=1"  # idle: pings at half of WATCHDOG_USEC
        proc.send_signal(signal.SIGHUP)
        assert _readline(proc, deadline) == "SIGHUP"
        reloading = _next_event(sock).split(b"\n")
        assert reloading[0] == b"RELOADING=1"
        assert reloading[1].startswith(b"MONOTONIC_USEC=")
        assert int(reloading[1].split(b"=")[1]) > 0
        assert len(reloading) == 2
        assert _next_event(sock) == b"READY=1\nSTATUS=reloaded"
        proc.send_signal(stop)
        assert _readline(proc, deadline) == stop.name
        assert proc.wait(timeout=DEADLINE_S) == 0  # handled: the default action would end it with -signal
        assert _next_event(sock) == b"STOPPING=1"
        assert proc.stdout.read() == ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
