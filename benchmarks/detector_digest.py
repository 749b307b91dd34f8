"""Every output of ``Detector.detect`` over a fixed set of frames, this tree against a base git revision.

The frames: the demo scene (640x480, lens distortion, ten floor tags in view) with 1, 2, 5 and 10 tags in
the world file (10 also without the joint solve: every marker's own pose), and bench_detector's sequences
(640x480 and 1280x720, four distances, sharp and blurred, markers leaving the view and coming back). Each
tree's detector runs in a child process over the same frames; every MarkerData field (poses, alternative
poses, sigmas, errors, covariances) and the detector's counters and frame reports are compared: a SHA-256 of
each tree's outputs, whether they are identical bit for bit, and otherwise the largest difference per field
(absolute; relative for sigma and for the covariances, to each matrix's largest element).

    python benchmarks/detector_digest.py [--base main] [--frames 12] [--seconds 2]

Exit status 0 when the outputs agree within the stated tolerances (``TOLERANCE``), 1 otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_per_marker import export_revision

ROOT = Path(__file__).resolve().parents[1]
DEMO_TAGS = (1, 2, 5, 10)
FIELDS = (
    "p_sensor_marker_m",
    "q_sensor_marker_wxyz",
    "p_sensor_marker_alt_m",
    "q_sensor_marker_alt_wxyz",
    "sigma_m",
    "reprojection_error_px",
    "ambiguity_ratio",
    "covariance",
)
# Largest difference allowed where the arithmetic differs (far below every sigma: mm and mrad sigmas).
TOLERANCE = {
    "p_sensor_marker_m": 1e-9,  # m
    "q_sensor_marker_wxyz": 1e-9,
    "p_sensor_marker_alt_m": 1e-9,
    "q_sensor_marker_alt_wxyz": 1e-9,
    "sigma_m": 1e-9,  # relative
    "reprojection_error_px": 1e-9,
    "ambiguity_ratio": 1e-9,
    "covariance": 1e-9,  # relative to the largest element of each matrix
}


def _runs(tree: Path, scene_root: Path, frames: int):
    """(name, detector, frames) of every frame set, built with ``tree``'s code."""
    import cv2
    import yaml

    from atlas_onboard.config import parse_world
    from atlas_onboard.detector.calibration import Calibration
    from atlas_onboard.detector.calibration import load as load_calibration
    from atlas_onboard.detector.pipeline import Detector

    scene = scene_root / "demo"
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted((scene / "frames").iterdir())]
    cal = load_calibration(scene / "calibration.yaml")
    for n in DEMO_TAGS:
        doc = yaml.safe_load((scene / "world.yaml").read_text())
        doc["entities"]["world"]["markers"] = doc["entities"]["world"]["markers"][:n]
        world = parse_world(doc)
        sensor = world.sensors[next(iter(world.sensors))]
        yield f"demo {n} tags", Detector(sensor, world, cal, decimate=2.0), images
        if n == max(DEMO_TAGS):  # every marker's own solve reported
            yield f"demo {n} tags alone", Detector(sensor, world, cal, decimate=2.0, joint=False), images
    spec = importlib.util.spec_from_file_location("bench_detector_of_tree", tree / "benchmarks" / "bench_detector.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    for res in ((640, 480), (1280, 720)):
        for name, K, _cam, seq in bench.sequences(*res, frames):
            markers = [{"id": i, "size_m": bench.SIZE, "pose": {"pos": [float(i), 0, 0]}} for i in bench.IDS]
            sensor = {"sensors": [{"name": "c", "id": 1, "pose": {}}]}
            world = parse_world({"entities": {"world": {"markers": markers}, "cam": sensor}})
            det = Detector(world.sensors[1], world, Calibration(res[0], res[1], K, np.zeros(5)), decimate=2.0)
            yield f"{res[0]}x{res[1]} {name}", det, [img for img, _views in seq]


def child(tree: Path, scene_root: Path, frames: int, out: Path) -> None:
    """Write every output of ``tree``'s detector over the frame sets to ``out`` (a pickle of plain values)."""
    sys.path.insert(0, str(tree))
    import cv2

    cv2.setNumThreads(1)
    results = []
    for name, det, images in _runs(tree, scene_root, frames):
        for k, img in enumerate(images):
            mds = det.detect(img, 33_333 * k)
            rep = det.report
            results.append(
                (
                    name,
                    k,
                    [
                        (
                            md.marker_id,
                            md.sensor_id,
                            md.capture_time_us,
                            {f: np.asarray(getattr(md, f), float) for f in FIELDS},
                        )
                        for md in mds
                    ],
                    (tuple(rep.found), tuple(rep.reported), tuple(sorted(rep.dropped.items()))),
                )
            )
        results.append((name, -1, sorted(det.counters.items()), tuple(det.take_status())))
    out.write_bytes(pickle.dumps(results))


def _digest(results) -> str:
    h = hashlib.sha256()
    for name, k, mds, extra in results:
        h.update(repr((name, k, extra)).encode())
        if k < 0:
            h.update(repr(mds).encode())
            continue
        for mid, sid, t, fields in mds:
            h.update(repr((mid, sid, t)).encode())
            for f in FIELDS:
                h.update(np.ascontiguousarray(fields[f]).tobytes())
    return h.hexdigest()


def compare(a, b) -> tuple[bool, dict[str, float], list[str]]:
    """(identical structure, largest difference per field, structural differences)."""
    worst = dict.fromkeys(FIELDS, 0.0)
    problems = []
    if len(a) != len(b):
        return False, worst, [f"{len(a)} against {len(b)} records"]
    for ra, rb in zip(a, b, strict=True):
        name, k = ra[0], ra[1]
        if ra[1] < 0:
            if ra[2:] != rb[2:]:
                problems.append(f"{name}: counters or status differ: {ra[2:]} != {rb[2:]}")
            continue
        if ra[3] != rb[3]:
            problems.append(f"{name} frame {k}: report differs: {ra[3]} != {rb[3]}")
        if [m[:3] for m in ra[2]] != [m[:3] for m in rb[2]]:
            problems.append(f"{name} frame {k}: markers differ")
            continue
        for (_, _, _, fa), (_, _, _, fb) in zip(ra[2], rb[2], strict=True):
            for f in FIELDS:
                x, y = fa[f], fb[f]
                if x.shape != y.shape or not np.array_equal(np.isnan(x), np.isnan(y)):
                    problems.append(f"{name} frame {k}: {f} shape or NaNs differ")
                    continue
                d = np.abs(np.nan_to_num(x) - np.nan_to_num(y))
                if d.size == 0:
                    continue
                if f == "covariance":
                    d = d / max(float(np.abs(x).max()), 1e-300)
                elif f == "sigma_m":
                    d = d / max(float(np.abs(x).max()), 1e-300)
                worst[f] = max(worst[f], float(d.max()))
    return not problems, worst, problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="main", help="git revision to compare against (default main)")
    ap.add_argument("--frames", type=int, default=12, help="frames per bench_detector sequence (default 12)")
    ap.add_argument("--seconds", type=float, default=2.0, help="demo camera time, s (default 2: 60 frames)")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)  # tree, scene root, frames, out
    args = ap.parse_args()
    if args.child:
        child(Path(args.child[0]), Path(args.child[1]), int(args.child[2]), Path(args.child[3]))
        return 0
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        base = tmp / "base"
        try:
            export_revision(args.base, base)
        except (OSError, subprocess.CalledProcessError) as exc:
            print(f"detector_digest: cannot export {args.base!r} with git archive: {exc}", file=sys.stderr)
            return 2
        sys.path.insert(0, str(ROOT))
        from atlas_onboard.sim.demo import write_demo

        write_demo(tmp / "demo", seconds=args.seconds, n_tags=max(DEMO_TAGS))
        got = {}
        for name, tree in ((f"base {args.base}", base), ("this tree", ROOT)):
            out = tmp / f"{len(got)}.pickle"
            cmd = [sys.executable, __file__, "--child", str(tree), str(tmp), str(args.frames), str(out)]
            subprocess.run(cmd, check=True)
            got[name] = pickle.loads(out.read_bytes())
    (na, a), (_, b) = got.items()
    n_md = sum(len(r[2]) for r in a if r[1] >= 0)
    n_frames = sum(1 for r in a if r[1] >= 0)
    print(f"{n_frames} frames, {n_md} MarkerData from {na}")
    for name, res in got.items():
        print(f"  {name:16} sha256 {_digest(res)}")
    same, worst, problems = compare(a, b)
    identical = _digest(a) == _digest(b)
    print(f"bit-identical: {'yes' if identical else 'no'}")
    print(f"{'field':26} {'max difference':>15} {'tolerance':>10}")
    ok = same
    for f in FIELDS:
        within = worst[f] <= TOLERANCE[f]
        ok &= within
        print(f"  {f:24} {worst[f]:>15.3e} {TOLERANCE[f]:>10.0e} {'' if within else 'OVER'}")
    for p in problems[:20]:
        print(f"  {p}")
    print(f"counters, reports and ids: {'identical' if same else f'{len(problems)} differences'}")
    print(f"BAR detector_outputs_within_tolerance {int(ok)} bool 1 {'pass' if ok else 'fail'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
