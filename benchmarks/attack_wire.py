"""The wire's side of benchmarks/attack.py: a witness peer, and the attacks on the link layer; run alone
(``python benchmarks/attack_wire.py [attack.py's options]``), attack.py's runs and BAR lines for these attacks.

- :class:`Witness`: the world's node (system 250) on the attacked peer link, as a real peer would be: a
  HEARTBEAT twice a second (signed when the link is), and everything the node sends it, with the
  signed frames checked as a peer with a right clock checks them (signature, timestamp within 60 s).
- ``future_stamp`` (row 3): one frame signed with the swarm key, stamped 2^48 - 1, as the witness's stream.
- ``sources`` (row 4): one-byte datagrams from SOURCES addresses, each again every second.
- ``partial`` (row 5): a 10-byte partial frame datagram before each of 20 witness datagrams a second.
- ``impostor`` (row 6): behind the autopilot link, system 2's ArduPilot: HEARTBEAT, TIMESYNC requests
  and GPS_GLOBAL_ORIGIN, 10 Hz.
- ``garbage`` (row 7): 1,392-byte datagrams of 116 12-byte frames with bad checksums, 1,200 a second.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from atlas_onboard.mavlink import dialect
from atlas_onboard.mavlink.signing import SIGNING_TICKS_PER_S, signing_timestamp
from atlas_onboard.sim.solo import Radio, SoloNode

WITNESS = 250
SOURCES = 500
TICKS_2_48 = (1 << 48) - 1
AFTER_ROW3_S = 10.0  # signed traffic must still flow this long after the future stamp
D = dialect.load()


def node_cpu_s(pid: int) -> float:
    """The CPU time (user + system) a process has used so far, from /proc."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def node_rss_mb(pid: int) -> tuple[float, float]:
    """A process's peak resident memory so far (VmHWM) and its anonymous resident memory now (RssAnon:
    without mapped files, such as the simulator's memory-mapped pre-rendered frames), in MB."""
    got = {}
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmHWM", "RssAnon"):
                got[key] = int(value.split()[0]) / 1024
    return got.get("VmHWM", math.nan), got.get("RssAnon", math.nan)


def node_threads(pid: int) -> int:
    """A process's threads (systemd's TasksMax counts them)."""
    return len(os.listdir(f"/proc/{pid}/task"))


def _frames(data: bytes) -> list[bytes]:
    """The MAVLink 2 frames of a datagram the node wrote (whole frames, back to back)."""
    out, i = [], 0
    while i + 12 <= len(data) and data[i] == 0xFD:
        end = i + data[i + 1] + 12 + (13 if data[i + 2] & 1 else 0)
        out.append(data[i:end])
        i = end
    return out


class Witness:
    """A real peer on the link (see the module); ``captured`` holds what it received, for replays."""

    def __init__(self, node: SoloNode, key: bytes | None) -> None:
        self.radio = Radio(node.peer_port)
        self.radio.sock.settimeout(0.05)
        self.key = key
        self.heartbeats = 0
        self.received: list[tuple[float, int, int]] = []  # (arrival, frames, frames a right clock accepts)
        self.captured: list[bytes] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> Witness:
        self._thread.start()
        return self

    def heartbeat(self) -> None:
        with self._lock:
            self.radio.send(self.radio.frame(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3), WITNESS, self.key))
            self.heartbeats += 1

    def _accepts(self, frame: bytes, now_ticks: int) -> bool:
        if self.key is None:
            return True
        if not frame[2] & 1:
            return False
        digest = hashlib.sha256(self.key + frame[:-6]).digest()[:6]
        stamp = int.from_bytes(frame[-12:-6], "little")
        return hmac.compare_digest(digest, frame[-6:]) and abs(stamp - now_ticks) < 60 * SIGNING_TICKS_PER_S

    def _run(self) -> None:
        next_s = 0.0
        while not self._stop.is_set():
            if time.time() >= next_s:
                next_s = time.time() + 0.5
                self.heartbeat()
            try:
                data = self.radio.sock.recv(65535)
            except (TimeoutError, BlockingIOError):
                continue
            except OSError:
                return
            frames = _frames(data)
            now_ticks = signing_timestamp(time.time())
            self.received.append((time.time(), len(frames), sum(self._accepts(f, now_ticks) for f in frames)))
            self.captured.append(data)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(2.0)
        self.radio.close()

    def accepted_since(self, t_s: float) -> tuple[int, int]:
        """(frames, frames a right clock accepts) received since ``t_s``."""
        got = [(n, ok) for t, n, ok in self.received if t >= t_s]
        return sum(n for n, _ in got), sum(ok for _, ok in got)


class WireAttack:
    """One of the wire's attacks (see the module): ``plan()`` gives (rate Hz, step); ``close()`` after."""

    def __init__(self, name: str, node: SoloNode, key: bytes | None, witness: Witness) -> None:
        self.name = name
        self.node = node
        self.key = key
        self.witness = witness
        self.radio = Radio(node.peer_port)
        self.what = ""
        self.sources: list[socket.socket] = []
        self.first_s: float | None = None

    def plan(self) -> tuple[float, Callable[[float], None]]:
        radio, name = self.radio, self.name
        if name == "future_stamp":
            self.what = f"one HEARTBEAT signed with the swarm key, as system {WITNESS}, stamped 2^48 - 1"
            mav = D.MAVLink(None, srcSystem=WITNESS, srcComponent=197)
            mav.signing.secret_key = self.key or os.urandom(32)
            mav.signing.sign_outgoing, mav.signing.timestamp = True, TICKS_2_48 - 1
            frame = bytes(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(mav))

            def step(now: float) -> None:
                if self.first_s is None:
                    self.first_s = now
                    radio.send(frame)

            return 10.0, step
        if name == "sources":
            self.what = f"one-byte datagrams from {SOURCES} addresses, each again every second"
            for _ in range(SOURCES):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.bind(("127.0.0.1", 0))
                s.setblocking(False)
                self.sources.append(s)
            k = [0]

            def step(_now: float) -> None:
                for s in self.sources[k[0] % 10 :: 10]:  # a tenth of them every 100 ms
                    s.sendto(b"\x00", radio.addr)
                    radio.sent += 1
                k[0] += 1

            return 10.0, step
        if name == "partial":
            self.what = "a 10-byte partial frame datagram before each of 20 witness HEARTBEAT datagrams a second"
            partial = radio.frame(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3), 77)[:10]

            def step(_now: float) -> None:
                radio.send(partial)
                self.witness.heartbeat()

            return 20.0, step
        if name == "impostor":
            self.what = "system 2's ArduPilot behind the autopilot link: HEARTBEAT, TIMESYNC, GPS_GLOBAL_ORIGIN, 10 Hz"
            ap = self.node.autopilot

            def step(_now: float) -> None:
                ap.send(D.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), source=(2, 1))
                ap.send(D.MAVLink_timesync_message(0, 123_456), source=(2, 1))
                ap.send(D.MAVLink_gps_global_origin_message(1, 2, 3, 0), source=(2, 1))
                radio.sent += 3

            return 10.0, step
        if name == "garbage":
            self.what = "1,392-byte datagrams of 116 12-byte frames with bad checksums, 1,200/s"
            hb = radio.frame(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3), 77)
            bad = (hb[:-2] + bytes([hb[-2] ^ 0xFF, hb[-1]])) * 116

            def step(_now: float) -> None:
                for _ in range(12):
                    radio.send(bad)

            return 100.0, step
        raise ValueError(name)

    def to_sources(self) -> int:
        """Datagrams the node sent to the sources (addresses that never proved themselves)."""
        n = 0
        for s in self.sources:
            while True:
                try:
                    s.recv(65535)
                    n += 1
                except (BlockingIOError, OSError):
                    break
        return n

    def close(self) -> Any:
        self.radio.close()
        for s in self.sources:
            s.close()


def _send_us(run: dict) -> float:
    c = run["counters"]
    return c.get("peer0_tx_cpu_ns", 0) / max(c.get("peer0_tx_calls", 0), 1) / 1e3


def wire_report(attack: str, mode: str, run: dict, clean: dict, bars: list) -> None:
    """The figures and bars of every run (pose rate, CPU) and of the wire's attacks."""
    hb, got, ok = run["witness"]
    print(
        f"    pose messages/s at the autopilot {run['rate_hz']:.1f} (clean {clean['rate_hz']:.1f}); node CPU"
        f" {run['cpu_s']:.2f} s (clean {clean['cpu_s']:.2f}), peak RSS {run['rss_mb'][0]:.0f} MB, anonymous"
        f" {run['rss_mb'][1]:.0f} MB (clean {clean['rss_mb'][0]:.0f}, {clean['rss_mb'][1]:.0f}), {run['threads']}"
        f" threads; send CPU {_send_us(run):.1f} us/call (clean"
        f" {_send_us(clean):.1f}); witness sent {hb} HEARTBEATs, received {got} datagrams, {ok} frames accepted"
    )
    ratio = run["rate_hz"] / clean["rate_hz"] if clean["rate_hz"] else 0.0
    bars.append((f"autopilot_rate_ratio_{attack}_signing_{mode}", ratio, "x", 0.95, ratio >= 0.95))
    c = run["counters"]
    if attack == "partial":
        lost = hb - c.get("peer0_rx_heartbeat", 0)
        print(f"    the witness's HEARTBEAT datagrams lost: {lost} of {hb}")
        bars.append((f"real_frames_lost_partial_signing_{mode}", lost, "count", 0, lost == 0))
    elif attack == "sources":
        ratio = _send_us(run) / max(_send_us(clean), 1e-9)
        to = run["to_sources"]
        print(f"    datagrams the node sent to the sources: {to}; send CPU {ratio:.2f}x clean")
        bars.append((f"send_cpu_ratio_sources_signing_{mode}", ratio, "x", 2.0, ratio <= 2.0))
        bars.append((f"datagrams_to_unproven_sources_signing_{mode}", to, "count", 0, to == 0))
    elif attack == "future_stamp":
        frames, accepted = run.get("after_row3", (0, 0))
        ahead = run.get("state_ahead_s", math.nan)
        print(
            f"    {AFTER_ROW3_S:g} s after it: the witness received {frames} frames, {accepted} of them accepted by a"
            f" right clock; the saved signing timestamp is {ahead:.1f} s ahead of the clock"
        )
        flowing = accepted > 0 and accepted == frames and ahead < 60.0
        bars.append(("signed_traffic_10s_after_future_stamp", accepted, "frames", 1, flowing))
    elif attack == "impostor":
        found = run["autopilots_found"]
        print(
            f"    autopilot found: {', '.join(found)}; SET_GPS_GLOBAL_ORIGIN sent {run['origin_sets']} (clean"
            f" {clean['origin_sets']}); TIMESYNC answers to others {run['timesync_to_others']}"
        )
        changes = len(found) - 1 if found and found[0] == "1" else len(found) + 1
        bars.append((f"autopilot_identity_changes_impostor_signing_{mode}", changes, "count", 0, changes == 0))
    elif attack == "garbage":
        lat, ref = run["lat_ms"], clean["lat_ms"]
        if len(lat) and len(ref):
            print(
                f"    capture->autopilot latency ms: mean {lat.mean():.1f} median {np.median(lat):.1f} p95"
                f" {np.percentile(lat, 95):.1f}; clean mean {ref.mean():.1f} median {np.median(ref):.1f} p95"
                f" {np.percentile(ref, 95):.1f}"
            )


def main() -> int:
    """The wire's rows alone (3-7), signing off and on: attack.py's clean and attacked runs, its report and
    its BAR lines, for those attacks (``--attacks`` and the other options as attack.py takes them)."""
    import attack  # the harness imports this module: loaded here, not at the top

    if "--attacks" not in sys.argv:
        sys.argv += ["--attacks", ",".join(attack.WIRE)]
    return attack.main()


if __name__ == "__main__":
    raise SystemExit(main())
