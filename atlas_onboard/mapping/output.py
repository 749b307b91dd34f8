"""What ``atlas-onboard map`` writes: the world file with the mapped markers (its other parts kept as the
user wrote them), the refined world file of a node's live refinement, the report (text, JSON) and the
map's plot."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import WORLD, WorldConfig
from atlas_onboard.core import frames
from atlas_onboard.mapping.build import MapResult
from atlas_onboard.mapping.report import MarkerReport

PLACEHOLDER = "__atlas_mapped_markers__"


def _fmt(v: float, digits: int) -> str:
    return f"{v:.{digits}f}".rstrip("0").rstrip(".") if v != 0 else "0"


def world_text(world: WorldConfig, result: MapResult, header: str, keep_anchors: bool = True) -> str:
    """The world file ``world`` was read from, with its world markers' poses replaced by the map's
    (in the file's own convention), each with its 1-sigma and fit as a comment. ``keep_anchors``: the
    anchors keep their surveyed poses (fixed anchors); otherwise they get the adjusted ones."""
    assert world.source is not None
    doc = yaml.safe_load(Path(world.source).read_text(encoding="utf-8"))
    raw_markers = (doc["entities"].get(WORLD) or {}).get("markers") or []
    mapped = result.mapped()
    lines = []
    for raw in raw_markers:
        mid = int(raw["id"])
        rep = result.markers.get(mid)
        entry: dict[str, Any] = {k: raw[k] for k in ("id", "size_m", "family") if k in raw}
        if mid in mapped and rep is not None and not (keep_anchors and rep.status == "anchor"):
            T = RigidTransform.from_matrix(mapped[mid])
            if world.world_convention is frames.WorldConvention.NED:
                T = frames.T_ENU_NED * T  # ENU -> NED (the rotation is its own inverse)
            p = T.translation
            x, y, z, w = T.rotation.as_quat()
            if w < 0:
                x, y, z, w = -x, -y, -z, -w
            pose = (
                f"{{pos: [{_fmt(p[0], 5)}, {_fmt(p[1], 5)}, {_fmt(p[2], 5)}],"
                f" rot: {{w: {w:.8f}, x: {x:.8f}, y: {y:.8f}, z: {z:.8f}}}}}"
            )
            sm = ", ".join(f"{v * 1000:.2f}" for v in rep.sigma_m or ())
            sd = ", ".join(f"{v:.3f}" for v in rep.sigma_deg or ())
            note = (
                f"# {rep.status}: 1-sigma position [{sm}] mm, rotation [{sd}] deg (world axes); {rep.frames} frames"
                + (f", rms {rep.rms_px:.2f} px" if math.isfinite(rep.rms_px) else "")
            )
        else:
            pose = yaml.safe_dump(raw["pose"], default_flow_style=True, width=1000).strip()
            status = rep.status if rep is not None else "not_seen"
            note = f"# {status}: pose as surveyed" if status == "anchor" else f"# {status}: pose kept from the input"
            if rep is not None and rep.detail:
                note += f" ({rep.detail})"
        inner = ", ".join(f"{k}: {v}" for k, v in entry.items())
        lines.append(f"- {{{inner}, pose: {pose}}}  {note}")
    doc["entities"].setdefault(WORLD, {})
    if doc["entities"][WORLD] is None:
        doc["entities"][WORLD] = {}
    doc["entities"][WORLD]["markers"] = PLACEHOLDER
    text = yaml.safe_dump(doc, sort_keys=False, width=1000)
    out = []
    for line in text.splitlines():
        if line.strip() == f"markers: {PLACEHOLDER}":
            indent = line[: len(line) - len(line.lstrip())]
            out.append(f"{indent}markers:")
            out += [f"{indent}  {entry}" for entry in lines]
        else:
            out.append(line)
    return "".join(f"# {h}\n" for h in header.splitlines()) + "\n".join(out) + "\n"


def refined_world_text(world: WorldConfig, markers: dict[int, MarkerReport], header: str) -> str:
    """:func:`world_text` for a map refined live (``run`` with ``refine``): ``markers`` says of each world
    marker whether it was refined (its pose, 1-sigma and views as frames), kept or an anchor."""
    result = MapResult(markers, np.zeros(0), [], None, math.nan, {}, {}, 0, 0, 0)
    return world_text(world, result, header, keep_anchors=True)


def report_text(result: MapResult) -> str:
    """The map's report as a person reads it."""
    t = result.timings_s
    out = [
        f"map: {result.frames_read} frames read, {result.frames_used} adjusted, {result.observations} marker sightings;"
        f" residual sigma {result.sigma0_px:.3f} px",
        "time: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in t.items()),
        f"{'marker':>6} {'status':<11} {'frames':>6} {'rms_px':>6} {'sigma_mm (x y z)':>22} {'sigma_deg (x y z)':>21}"
        f" {'views_deg':>9}  detail",
    ]
    for mid in sorted(result.markers):
        r = result.markers[mid]
        sm = " ".join(f"{v * 1000:6.2f}" for v in r.sigma_m) if r.sigma_m else "-"
        sd = " ".join(f"{v:6.3f}" for v in r.sigma_deg) if r.sigma_deg else "-"
        rms = f"{r.rms_px:6.2f}" if math.isfinite(r.rms_px) else "-"
        spread = f"{r.view_spread_deg:9.0f}" if math.isfinite(r.view_spread_deg) else "-"
        out.append(f"{mid:>6} {r.status:<11} {r.frames:>6} {rms:>6} {sm:>22} {sd:>21} {spread:>9}  {r.detail}")
    if len(result.frame_rms_px):
        worst = np.argsort(result.frame_rms_px)[::-1][:5]
        out.append(
            "images with the largest reprojection RMS: "
            + ", ".join(f"{result.frame_names[k]} {result.frame_rms_px[k]:.2f} px" for k in worst)
        )
    if result.unknown_ids:
        out.append("ids seen that the world file does not list: " + ", ".join(map(str, sorted(result.unknown_ids))))
    bad = [r for r in result.markers.values() if r.status in ("moved", "duplicated", "wrong_size")]
    for r in bad:
        out.append(f"marker {r.id} does not fit ({r.status}): {r.detail}; left out of the map")
    unanchored = sorted(r.id for r in result.markers.values() if r.status == "unanchored")
    if unanchored:
        out.append(
            f"markers {', '.join(map(str, unanchored))} not mapped: their groups have no anchor"
            " (give one of each group as --anchor, or fly between the groups)"
        )
    return "\n".join(out)


def report_json(result: MapResult) -> str:
    def marker(r: Any) -> dict[str, Any]:
        return {
            "id": r.id, "status": r.status, "size_m": r.size_m, "frames": r.frames,
            "rms_px": r.rms_px if math.isfinite(r.rms_px) else None,
            "sigma_m": list(r.sigma_m) if r.sigma_m else None, "sigma_deg": list(r.sigma_deg) if r.sigma_deg else None,
            "view_spread_deg": r.view_spread_deg if math.isfinite(r.view_spread_deg) else None,
            "T_world_marker": r.M_world_marker.tolist() if r.M_world_marker is not None else None, "detail": r.detail,
        }  # fmt: skip

    doc = {
        "frames_read": result.frames_read, "frames_used": result.frames_used, "observations": result.observations,
        "sigma0_px": result.sigma0_px, "timings_s": result.timings_s,
        "markers": [marker(result.markers[m]) for m in sorted(result.markers)],
        "images": [
            {"image": n, "rms_px": float(v)} for n, v in zip(result.frame_names, result.frame_rms_px, strict=True)
        ],
        "unknown_ids": {str(k): v for k, v in result.unknown_ids.items()},
    }  # fmt: skip
    return json.dumps(doc, indent=1)


def plot_map(path: Path, result: MapResult) -> bool:
    """A top view and a side view of the map (matplotlib, only when installed); False without it."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    colours = {"anchor": "tab:red", "mapped": "tab:blue", "degenerate": "tab:orange"}
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    sol = result.solution
    cams = np.array([np.linalg.inv(M)[:3, 3] for M in sol.M_cam_world]) if sol is not None else np.zeros((0, 3))
    for ax, (i, j, name) in zip(axes, ((0, 1, "top view (x, y)"), (0, 2, "side view (x, z)")), strict=True):
        if len(cams):
            ax.plot(cams[:, i], cams[:, j], ".", ms=2, color="0.7", label="camera")
        for r in result.markers.values():
            if r.M_world_marker is None:
                continue
            p = r.M_world_marker[:3, 3]
            ax.plot(p[i], p[j], "s", color=colours.get(r.status, "k"))
            ax.annotate(str(r.id), (p[i], p[j]), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle("marker map: red anchors, blue mapped, orange degenerate views")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True
