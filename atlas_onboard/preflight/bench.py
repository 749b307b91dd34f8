"""``atlas-onboard preflight``: the bench check before the first flight (drone still, propellers off).

It starts the node itself (``atlas-onboard run`` on a copy of the world file whose autopilot link
points at a relay on 127.0.0.1), and relays the node's link to the autopilot unchanged
(:mod:`atlas_onboard.mavlink.relay`): what it judges is what the autopilot receives from the node's
own pipeline. The node's service must be stopped (the relay takes the autopilot's port). For
``--seconds`` after the first pose it collects the poses, the autopilot's ATTITUDE and
LOCAL_POSITION_NED, TIMESYNC, and asks the autopilot for its delay and source parameters and its EKF
origin; then prints one line per check (:mod:`atlas_onboard.preflight.checks`) and exits 0 only when
none failed (1 otherwise). ``--interactive`` then asks for two tilts and checks their signs.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import yaml

from atlas_onboard.config import NodeConfig, WorldConfig, load_node
from atlas_onboard.config.yamlio import read_yaml
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink.relay import Relay
from atlas_onboard.mavlink.samples import Tap
from atlas_onboard.preflight.checks import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    Check,
    Verdict,
    check_attitude,
    check_delay,
    check_local_position,
    check_origin,
    check_peers,
    check_rate,
    check_tilt,
    check_timesync,
    check_yaw,
    optical_axes_frd,
    pair_attitudes,
    yaw_from_vision,
)

EXIT_FAILED = 1
FIRST_POSE_TIMEOUT_S = 30.0
PARAMS = {
    "px4": ["EKF2_EV_DELAY", "EKF2_EV_CTRL", "EKF2_HGT_REF"],
    "ardupilot": ["VISO_DELAY_MS", "EK3_SRC1_YAW", "VISO_TYPE"],
}
TILT_S = 2.0
SETTLE_S = 1.0


def _relayed_world(config: Path, entity: str, port: int) -> Path:
    """A copy of the world file beside it (relative paths keep working), the autopilot link at the relay."""
    doc = read_yaml(config)
    doc["nodes"][entity]["autopilot"]["url"] = f"udpout:127.0.0.1:{port}"
    fd, name = tempfile.mkstemp(prefix=f".preflight-{entity}-", suffix=".yaml", dir=config.parent)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        yaml.safe_dump(doc, f, sort_keys=False)
    return Path(name)


def _wait(tap: Tap, until: Callable[[], bool], timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        with tap.lock:
            if until():
                return True
        time.sleep(0.05)
    return False


def _snapshot(tap: Tap, since_s: float = 0.0) -> Tap:
    """A copy of what the relay saw, the streams from wall time ``since_s`` on."""
    with tap.lock:
        return Tap(
            [v for v in tap.vision if v.arrival_s >= since_s], [a for a in tap.attitude if a.arrival_s >= since_s],
            [p for p in tap.local_position if p.arrival_s >= since_s], dict(tap.params), tap.origin,
            tap.autopilot, tap.autopilot_system, tap.timesync_requests, tap.timesync_answers,
        )  # fmt: skip


def evaluate(tap: Tap, window_s: float, world: WorldConfig, node: NodeConfig, node_log: str) -> list[Check]:
    """Every check on what the relay collected."""
    checks = [check_rate(tap.vision, window_s, tap.autopilot)]
    checks += check_attitude(tap.vision, tap.attitude, optical_axes_frd(world, node.entity))
    checks.append(check_yaw(tap.vision, tap.attitude, yaw_from_vision(tap.params, tap.autopilot)))
    checks.append(check_delay(tap.vision, tap.params, tap.autopilot, tap.timesync_answers > 0))
    checks.append(check_timesync(tap))
    checks.append(check_origin(tap))
    checks.append(check_local_position(tap.vision, tap.local_position))
    checks += check_peers(node, node_log)
    return checks


def _interactive(relay: Relay, ask: Callable[[str], str]) -> list[Check]:
    out = []
    for what, axis, sign in (("nose down", 1, -1.0), ("right side down", 0, 1.0)):
        still = _snapshot(relay.tap)
        ask(f"Tilt the drone {what} by about 20 degrees and hold it; press Enter")
        n_vis, n_att = len(relay.tap.vision), len(relay.tap.attitude)
        time.sleep(TILT_S)
        now = _snapshot(relay.tap)
        a = pair_attitudes(still.vision[-20:], still.attitude)
        b = pair_attitudes(now.vision[n_vis:], now.attitude[n_att:])
        if a is None or b is None:
            out.append(Check(f"tilt {what}", Verdict.SKIP, "too few poses or attitudes"))
        else:
            out.append(check_tilt(what, axis, sign, a, b))
        ask("Put the drone back level; press Enter")
        time.sleep(TILT_S)
    return out


def run_preflight(
    config: Path,
    entity: str,
    seconds: float,
    out: Callable[[str], None],
    ask: Callable[[str], str] | None = None,
) -> int:
    """Run the node behind the relay for ``seconds`` after its first pose; each check's line to ``out``; with
    ``ask`` (it shows a request and waits for the user's answer), then the interactive tilts; 0 when none failed."""
    if not 1.0 <= seconds <= 600.0:
        raise AtlasError(f"--seconds: expected 1-600, got {seconds:g}")
    world, node = load_node(config, entity)
    if node.autopilot is None:
        raise AtlasError(f"nodes.{entity}: no autopilot link to check")
    relay = Relay(node.autopilot.link.url, node.system_id).start()
    relayed = _relayed_world(config, entity, relay.port)
    log = tempfile.NamedTemporaryFile(prefix="atlas-preflight-", suffix=".log", delete=False)
    proc = subprocess.Popen(  # noqa: S603 (this interpreter, this package, a file it wrote)
        [sys.executable, "-m", "atlas_onboard", "run", "--config", str(relayed), "--entity", entity],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    extra: list[Check] = []
    try:
        out(f"preflight: node started (pid {proc.pid}), relaying its autopilot link to {node.autopilot.link.url}")
        if not _wait(relay.tap, lambda: bool(relay.tap.vision) or proc.poll() is not None, FIRST_POSE_TIMEOUT_S):
            out(f"preflight: no pose from the node in {FIRST_POSE_TIMEOUT_S:.0f} s")
        time.sleep(SETTLE_S)  # the node's first frames wait for its start: not its latency
        start, start_wall = time.monotonic(), time.time()
        kind = "px4"
        for k in range(3):  # asked more than once: a datagram may be lost
            time.sleep(max(start + (k + 1) * seconds / 4 - time.monotonic(), 0.0))
            kind = "ardupilot" if relay.tap.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA else "px4"
            relay.request_params(PARAMS[kind])
            relay.request_origin()
        time.sleep(max(start + seconds - time.monotonic(), 0.0))
        window_s = time.monotonic() - start
        tap = _snapshot(relay.tap, start_wall)
        if ask is not None and tap.vision:
            extra = _interactive(relay, ask)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        relay.stop()
        log.close()
        with contextlib.suppress(OSError):
            relayed.unlink()
    node_log = Path(log.name).read_text(errors="replace")
    checks = evaluate(tap, window_s, world, node, node_log) + extra
    for c in checks:
        out(c.line())
    failed = sum(c.verdict is Verdict.FAIL for c in checks)
    out(f"preflight: {failed} failed, node log {log.name}" if failed else f"preflight: nothing failed ({kind})")
    return EXIT_FAILED if failed else 0
