"""The node as a systemd service: the notify protocol (READY, WATCHDOG, STOPPING) against a test
NOTIFY_SOCKET, a clean exit on SIGTERM that leaves no child process or socket behind, SIGHUP with a
broken file, and an autopilot on a serial port that vanishes and returns."""

import os
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common

from atlas_onboard.config import load_world
from tests.e2e.helpers import NodeProcess, Peer, free_udp_port, wait_for, write_world
from tests.e2e.test_autopilot import TRUTH, world_doc
from tests.helpers import observe

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group


def test_notify_protocol(tmp_path):
    addr = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(addr)
    sock.settimeout(0.2)
    path = write_world(tmp_path, world_doc(free_udp_port(), free_udp_port()))
    node = NodeProcess(path, "d1", env={"NOTIFY_SOCKET": addr, "WATCHDOG_USEC": "2000000"})
    got = []
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and sum("WATCHDOG=1" in g for g in got) < 3:
        try:
            got.append(sock.recv(4096).decode())
        except TimeoutError:
            pass
    code = node.stop()
    sock.settimeout(1.0)
    try:
        while True:
            got.append(sock.recv(4096).decode())
    except TimeoutError:
        pass
    sock.close()
    assert code == 0
    assert got[0].splitlines()[0] == "READY=1" and "STATUS=running as d1" in got[0]
    assert sum("WATCHDOG=1" in g for g in got) >= 3
    assert got[-1] == "STOPPING=1"


def pty_autopilot(link_path):
    """A pseudo-terminal whose slave end appears at ``link_path``, like /dev/ttyAMA0 would."""
    master, slave = os.openpty()
    if os.path.lexists(link_path):
        os.unlink(link_path)
    os.symlink(os.ttyname(slave), link_path)
    return master, slave


def test_serial_autopilot_vanishes_and_returns(tmp_path):
    dev = str(tmp_path / "ttyFC")
    master, slave = pty_autopilot(dev)
    os.set_blocking(master, False)
    port = free_udp_port()
    doc = world_doc(port, 1)
    doc["nodes"]["d1"]["autopilot"]["url"] = f"{dev},921600"
    path = write_world(tmp_path, doc)
    world = load_world(path)
    node = NodeProcess(path, "d1")
    peer = Peer(port, 250)
    parser = common.MAVLink(None)
    parser.robust_parsing = True

    def read_vision(fd):
        out = []
        try:
            data = os.read(fd, 65536)
        except (BlockingIOError, OSError):
            return out
        for m in parser.parse_buffer(data) or []:
            if m.get_type() == "VISION_POSITION_ESTIMATE":
                out.append(m)
        return out

    def feed_until(fd, n, seconds):
        got = []
        end = time.time() + seconds
        while time.time() < end and len(got) < n:
            peer.send(observe(world, TRUTH, 10, 5, capture_time_us=int(time.time() * 1e6)), world.fingerprint())
            time.sleep(0.03)
            got += read_vision(fd)
        return got

    try:
        first = feed_until(master, 5, 20)
        assert len(first) >= 5, node.log()[-2000:]
        np.testing.assert_allclose([first[-1].x, first[-1].y, first[-1].z], [2.0, 1.0, -3.0], atol=1e-5)
        # The flight controller's USB cable is pulled: the device disappears.
        os.close(master)
        os.close(slave)
        os.unlink(dev)
        feed_until(-1, 1, 1.5)
        assert node.proc.poll() is None, "the node died with its serial device"
        master, slave = pty_autopilot(dev)  # plugged back in
        os.set_blocking(master, False)
        again = feed_until(master, 5, 20)
        assert len(again) >= 5, node.log()[-2000:]
    finally:
        peer.close()
        assert node.stop() == 0
        for fd in (master, slave):
            try:
                os.close(fd)
            except OSError:
                pass
    c = node.final_counters()
    assert c["autopilot_read_errors"] >= 1 and c["autopilot_reconnects"] >= 1


def test_sighup_with_a_broken_file_keeps_the_running_config(tmp_path):
    import signal

    from atlas_onboard.sim.autopilot import SimAutopilot

    ap = SimAutopilot(system_id=1).start()
    port = free_udp_port()
    path = write_world(tmp_path, world_doc(port, ap.port))
    world = load_world(path)
    node = NodeProcess(path, "d1")
    peer = Peer(port, 250)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        good = path.read_text()
        path.write_text(good.replace("size_m: 0.2", "size_m: -1"))  # broken: a negative marker size
        node.proc.send_signal(signal.SIGHUP)
        assert wait_for(lambda: "reload refused" in node.log(), 10), node.log()
        assert "size_m" in node.log()
        # Still running on the old file: observations of the old world are used.
        for _ in range(5):
            peer.send(observe(world, TRUTH, 10, 5, capture_time_us=int(time.time() * 1e6)), world.fingerprint())
            time.sleep(0.03)
        assert wait_for(lambda: len(ap.snapshot()) >= 1, 5)
        np.testing.assert_allclose(ap.snapshot()[-1].xyz_m, [2.0, 1.0, -3.0], atol=1e-5)
        path.write_text(good)
        node.proc.send_signal(signal.SIGHUP)
        assert wait_for(lambda: "reloaded" in node.log(), 10), node.log()
    finally:
        peer.close()
        assert node.stop() == 0
        ap.stop()


def _socket_inodes(pid):
    out = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            out.add(int(target[8:-1]))
    return out


def _children(pid):
    kids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(stat[1]) == pid:
                kids.append(int(entry))
    return kids


def _live_socket_inodes():
    inodes = set()
    for table in ("udp", "udp6", "tcp", "tcp6", "unix"):
        try:
            lines = open(f"/proc/net/{table}").read().splitlines()[1:]
        except OSError:
            continue
        col = 6 if table == "unix" else 9
        inodes |= {int(line.split()[col]) for line in lines if len(line.split()) > col}
    return inodes


def test_sigterm_leaves_no_child_process_or_socket_behind(tmp_path):
    from atlas_onboard.sim.autopilot import SimAutopilot

    ap = SimAutopilot(system_id=1).start()
    port = free_udp_port()
    path = write_world(tmp_path, world_doc(port, ap.port))
    node = NodeProcess(path, "d1")
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        pid = node.proc.pid
        sockets = _socket_inodes(pid)
        children = _children(pid)
        assert sockets, "the node holds its link sockets while running"
        assert node.stop() == 0
        assert not [k for k in children if os.path.exists(f"/proc/{k}")]  # no child outlives it
        assert not sockets & _live_socket_inodes()  # none of its sockets is left open
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", port))  # its listening port is free again at once
        s.close()
    finally:
        ap.stop()
