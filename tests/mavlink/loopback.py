"""Loopback helpers for the MAVLink tests: free ports, links, raw signed frames, polling until a count."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

from atlas_onboard.config import LinkConfig, SigningConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec, dialect
from atlas_onboard.mavlink.link import Link
from atlas_onboard.mavlink.signing import signing_timestamp

D = dialect.load()
FP = 0x1234ABCD
MD = MarkerData(10, 5, 0.01, (0.1, -0.2, 2.0), (1.0, 0.0, 0.0, 0.0), 1_700_000_000_000_000, 0.3, 0.5, 0, 1)


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port on 127.0.0.1 that was free a moment ago (bound to 0 and released)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_link(
    url: str,
    sysid: int,
    key_file: Path | None = None,
    *,
    require: bool = True,
    sign: bool = True,
    state_dir: Path | None = None,
    wall: Callable[[], float] = time.time,
    tunnel: bool = False,
    rate_hz: float = 1000.0,
) -> Link:
    signing = SigningConfig(key_file, sign, require) if key_file is not None else None
    cfg = LinkConfig(url, tunnel=tunnel, signing=signing, rate_limit_hz=rate_hz)
    return Link(cfg, f"link{sysid}", sysid, 197, state_dir, 0, wall_clock=wall)


def write_key(tmp_path: Path, key: bytes, mode: int = 0o600, name: str = "swarm.key") -> Path:
    path = tmp_path / name
    path.write_bytes(key)
    path.chmod(mode)
    return path


class RawSender:
    """A plain UDP socket and a bare pymavlink encoder: exact frames, optionally signed, to a port."""

    def __init__(self, port: int, sysid: int = 250, key: bytes | None = None, timestamp: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.addr = ("127.0.0.1", port)
        self.mav = D.MAVLink(None, srcSystem=sysid, srcComponent=197)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 0
            self.mav.signing.timestamp = signing_timestamp(time.time()) if timestamp is None else timestamp

    def frame(self, msg) -> bytes:
        return bytes(msg.pack(self.mav))

    def observation(self, seq: int = 1, fingerprint: int = FP, **override) -> bytes:
        fields = codec.observation_fields(MD, fingerprint)
        fields["seq"] = seq
        fields.update(override)
        return self.frame(D.MAVLink_atlas_observation_message(**fields))

    def heartbeat(self) -> bytes:
        return self.frame(D.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))

    def raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.addr)

    def close(self) -> None:
        self.sock.close()


def poll_until(link: Link, predicate: Callable[[list], bool], timeout_s: float = 5.0) -> list:
    """Poll ``link`` collecting messages until ``predicate(messages)`` or the timeout; returns them."""
    got: list = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got.extend(link.poll(0.02))
        if predicate(got):
            break
    return got


def drain(link: Link, quiet_s: float = 0.15) -> list:
    """Poll until nothing arrives for ``quiet_s``."""
    got: list = []
    last = time.monotonic()
    while time.monotonic() - last < quiet_s:
        new = link.poll(0.02)
        if new:
            got.extend(new)
            last = time.monotonic()
    return got


def kinds(msgs: list) -> list[str]:
    return [m.get_type() for m in msgs]
