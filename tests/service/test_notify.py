"""The systemd notify client and the signal pipe: exact datagrams on a real test NOTIFY_SOCKET (a
filesystem socket and an abstract one), watchdog settings, and a child process driven by real signals."""

import logging
import os
import socket
import tempfile
import time
import uuid
from pathlib import Path

import pytest

from atlas_onboard.service.notify import Notifier, ServiceError, socket_address, watchdog_interval_us

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
    with caplog.at_level(logging.WARNING, logger="atlas_onboard.service.notify"):
        notifier = Notifier("relative/notify.sock")
    assert not notifier.enabled
    assert notifier.ready() is False
    assert len(caplog.records) == 1
    assert "NOTIFY_SOCKET='relative/notify.sock'" in caplog.records[0].getMessage()


def test_a_failed_send_is_logged_once_and_never_raised(tmp_path, caplog):
    missing = str(tmp_path / "gone.sock")
    notifier = Notifier(missing)
    assert notifier.enabled
    with caplog.at_level(logging.DEBUG, logger="atlas_onboard.service.notify"):
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
