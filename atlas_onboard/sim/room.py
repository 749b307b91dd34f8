"""A room rendered through the camera: a textured concrete floor, walls and a ceiling in world space.

The default simulated cameras draw their markers over a texture fixed to the image. A real camera
sees a floor that moves, turns and foreshortens with it, full of edges and near-quads for the detector
to reject. :class:`RoomRenderer` renders the whole scene a camera sees in an axis-aligned box room:

- every pixel's ray (through the lens distortion) is intersected with the room's six faces and reads
  the face's texture, low-passed to about the size of a pixel's footprint so that it does not alias;
- every marker in front of the camera is drawn, also those cut by the image border, at grazing
  angles, or too small to decode (a real camera does not leave them out);
- motion blur is the average of the sharp image sampled along each pixel's own image motion over
  the exposure (the motion of the room point it sees: rotation blurs the edges more than the centre);
- a rolling shutter (:class:`RowPoses`) exposes each row at its own instant: the room and the markers
  are drawn with each row's own pose, and each row blurs over its own exposure;
- the illumination falls off towards the corners (vignetting), the sensor adds read and shot noise,
  and the frame is JPEG-compressed as an MJPEG webcam delivers it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import SensorConfig, WorldConfig
from atlas_onboard.detector.render import Camera, MarkerView, concrete_texture, draw_marker, prepare
from atlas_onboard.sim.scenario import Room

FLOW_STEP_PX = 8  # image motion is smooth: computed on every 8th pixel, interpolated between
TEXTURE_BLUR_TEXELS = 1.0  # the textures' low-pass (Gaussian sigma): a pixel sees 2-4 texels of floor
MARKER_SUPERSAMPLE = 3  # marker samples a pixel along each axis (as the simulator's other cameras)


class _Atlas:
    """The six faces' textures stacked in one image, and where each face starts in it."""

    def __init__(self, room: Room) -> None:
        lo, hi = np.asarray(room.lo_m), np.asarray(room.hi_m)
        size = hi - lo
        faces = []  # (texture, px_per_m)
        floor = concrete_texture(*_px(size[0], size[1], room.floor_px_per_m), room.seed, room.floor_px_per_m)
        faces.append((floor, room.floor_px_per_m))
        # Painted walls and ceiling: lighter, with fewer joints (a coarser concrete texture, brightened).
        ppm = room.wall_px_per_m
        for k, (a, b) in enumerate(((size[1], size[2]), (size[1], size[2]), (size[0], size[2]), (size[0], size[2]))):
            wall = concrete_texture(*_px(a, b, ppm), room.seed + 1 + k, ppm, mean=165.0)
            faces.append((wall, ppm))
        ceiling = concrete_texture(*_px(size[0], size[1], ppm / 4), room.seed + 9, ppm / 4, mean=190.0)
        faces.append((ceiling, ppm / 4))
        faces = [(cv2.GaussianBlur(t, (0, 0), TEXTURE_BLUR_TEXELS), p) for t, p in faces]
        width = max(t.shape[1] for t, _ in faces)
        pad = 4
        self.rows: list[int] = []
        self.px_per_m: list[float] = [ppm_ for _, ppm_ in faces]
        blocks = []
        row = 0
        for tex, _ in faces:
            self.rows.append(row)
            block = np.full((tex.shape[0] + pad, width), float(tex.mean()), np.float32)
            block[: tex.shape[0], : tex.shape[1]] = tex
            blocks.append(block)
            row += block.shape[0]
        self.image = np.ascontiguousarray(np.vstack(blocks))


@dataclass(frozen=True)
class RowPoses:
    """A rolling shutter's frame: the camera's pose (optical frame in the world) at each image row's
    mid-exposure (``mid``), and when its exposure opened and closed; each (height, 4, 4)."""

    mid: NDArray[np.float64]
    open: NDArray[np.float64]
    close: NDArray[np.float64]


_atlases: dict[Room, _Atlas] = {}
ATLAS_CACHE = 2  # atlases kept per process (tens of MB each)


def atlas(room: Room) -> _Atlas:
    """The room's textures (made once per process and room: every camera in the room reads the same,
    and no renderer writes to them)."""
    if room not in _atlases:
        while len(_atlases) >= ATLAS_CACHE:
            del _atlases[next(iter(_atlases))]
        _atlases[room] = _Atlas(room)
    return _atlases[room]


def _px(a_m: float, b_m: float, px_per_m: float) -> tuple[int, int]:
    return max(math.ceil(a_m * px_per_m), 8), max(math.ceil(b_m * px_per_m), 8)


class RoomRenderer:
    """The image camera ``sensor`` takes in ``room`` at a given pose (see the module docstring).

    ``intr`` is the camera's :class:`atlas_onboard.sim.world.Intrinsics`; ``noise_sigma`` the read
    noise (grey levels). The exposure comes with each frame, as the camera's poses when it opened and
    closed (see :meth:`render`).
    """

    def __init__(self, room: Room, world: WorldConfig, sensor: SensorConfig, intr: object, noise_sigma: float) -> None:
        self.room = room
        self.intr = intr
        self.noise_sigma = noise_sigma
        w, h = intr.width_px, intr.height_px  # type: ignore[attr-defined]
        self.cam = Camera(w, h, intr.camera_matrix, np.array(intr.distortion))  # type: ignore[attr-defined]
        self.atlas = atlas(room)
        self.lo = np.asarray(room.lo_m, dtype=np.float64)
        self.hi = np.asarray(room.hi_m, dtype=np.float64)
        self.rays = _rays(self.cam, np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))  # (h, w, 3)
        fx = np.arange(0, w + FLOW_STEP_PX, FLOW_STEP_PX, dtype=np.float64)
        fy = np.arange(0, h + FLOW_STEP_PX, FLOW_STEP_PX, dtype=np.float64)
        self.flow_px = np.stack(np.meshgrid(fx, fy), axis=-1)  # (ny, nx, 2)
        self.flow_rays = _rays(self.cam, fx, fy).reshape(-1, 3).astype(np.float64)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        cx, cy = intr.cx, intr.cy  # type: ignore[attr-defined]
        r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (cx**2 + cy**2)
        self.illumination = (room.exposure_gain * (1.0 - room.vignetting * r2)).astype(np.float32)
        self.pixel_x, self.pixel_y = xx, yy
        self.markers = [m for m in world.markers.values() if m.entity != sensor.entity]
        prepare(self.cam, MARKER_SUPERSAMPLE)

    def render(
        self,
        M_world_sensor: NDArray[np.float64],
        M_world_sensor_open: NDArray[np.float64],
        M_world_sensor_close: NDArray[np.float64],
        M_world_entity: dict[str, NDArray[np.float64]],
        seed: int,
        rows: RowPoses | None = None,
    ) -> NDArray[np.uint8]:
        """The frame (h, w) uint8 of a camera at ``M_world_sensor`` (4x4, optical frame, mid-exposure),
        which was at ``M_world_sensor_open`` when the exposure opened and ``..._close`` when it closed;
        ``M_world_entity``: 4x4 poses of the entities whose markers may be seen (at the frame's stamp:
        a rolling shutter moves the camera between rows, not those entities). ``rows``: a rolling
        shutter's poses per row (the three single poses are then the middle row's)."""
        if rows is None:
            img = self._background(M_world_sensor)
        else:
            img = self._background(rows.mid)
        M_sensor_world = np.linalg.inv(M_world_sensor)
        rows_sensor_world = None if rows is None else np.linalg.inv(rows.mid)
        views = []
        for m in self.markers:
            M_world_marker = M_world_entity[m.entity] @ m.T_entity_marker.as_matrix()
            M = M_sensor_world @ M_world_marker
            T = RigidTransform(M, normalize=False, copy=False)  # a product of rigid matrices
            per_row = None if rows_sensor_world is None else rows_sensor_world @ M_world_marker
            views.append((float(np.linalg.norm(M[:3, 3])), MarkerView(m.family, m.id, m.size_m, T, per_row)))
        for _, view in sorted(views, key=lambda v: -v[0]):
            draw_marker(img, self.cam, view, MARKER_SUPERSAMPLE)
        if rows is None:
            img = self._blur(img, M_world_sensor, M_world_sensor_open, M_world_sensor_close)
        else:
            rows_at = np.clip(self.flow_px[:, 0, 1].round().astype(int), 0, len(rows.mid) - 1)  # flow grid rows
            img = self._blur(img, rows.mid[rows_at], rows.open[rows_at], rows.close[rows_at])
        img = self.room.black_level + img * self.illumination
        rng = np.random.default_rng(seed)
        sigma = np.sqrt(self.noise_sigma**2 + self.room.shot_noise * np.maximum(img, 0.0))
        img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        if self.room.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(self.room.jpeg_quality)])
            if ok:
                out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        return out

    def _hits(self, M_world_sensor: NDArray[np.float64], rays: NDArray[np.floating]) -> tuple[NDArray, NDArray]:
        """Where each ray (..., 3, camera frame) leaves the room: the world point (..., 3) and the face
        (..., 0 floor, 1 east, 2 west, 3 north, 4 south, 5 ceiling). ``M_world_sensor``: one pose (4, 4),
        or one per row of ``rays`` (rows, cols, 3) as (rows, 4, 4)."""
        if M_world_sensor.ndim == 2:
            R = M_world_sensor[:3, :3].astype(rays.dtype)
            o = M_world_sensor[:3, 3]
            d = rays @ R.T
        else:
            R = M_world_sensor[:, :3, :3].astype(rays.dtype)
            o = M_world_sensor[:, None, :3, 3]  # (rows, 1, 3)
            d = np.einsum("rcj,rij->rci", rays, R)
        lam = np.full(d.shape[:-1], np.inf)  # float64: the pose's origin is
        face = np.zeros(d.shape[:-1], dtype=np.int8)
        # face index by (axis, towards hi): x: west/east, y: south/north, z: floor/ceiling
        codes = {(0, True): 1, (0, False): 2, (1, True): 3, (1, False): 4, (2, True): 5, (2, False): 0}
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in range(3):
                da = d[..., a]
                up = da > 0
                la = np.where(up, self.hi[a] - o[..., a], self.lo[a] - o[..., a]) / da  # one division a ray
                la[da == 0] = np.inf
                closer = la < lam
                np.copyto(lam, la, where=closer)
                np.copyto(face, np.where(up, np.int8(codes[(a, True)]), np.int8(codes[(a, False)])), where=closer)
        hit = o.astype(rays.dtype) + lam[..., None] * d
        return hit, face

    def _background(self, M_world_sensor: NDArray[np.float64]) -> NDArray[np.float32]:
        """The room's image through every pixel: at one pose (4, 4) or at each row's own (rows, 4, 4)."""
        hit, face = self._hits(M_world_sensor, self.rays)
        x, y, z = hit[..., 0], hit[..., 1], hit[..., 2]
        lo, hi, at = self.lo, self.hi, self.atlas
        # Texture coordinates (pixel-centre convention) of each face, as seen from inside the room.
        u = np.empty(face.shape, np.float32)
        v = np.empty(face.shape, np.float32)
        table = (
            lambda x, y, z: (x - lo[0], hi[1] - y),  # floor: x right, north up in the texture
            lambda x, y, z: (y - lo[1], hi[2] - z),  # east wall
            lambda x, y, z: (hi[1] - y, hi[2] - z),  # west wall
            lambda x, y, z: (hi[0] - x, hi[2] - z),  # north wall
            lambda x, y, z: (x - lo[0], hi[2] - z),  # south wall
            lambda x, y, z: (x - lo[0], y - lo[1]),  # ceiling
        )
        for k, coordinates in enumerate(table):
            sel = face == k
            a, b = coordinates(x[sel], y[sel], z[sel])  # only the pixels that see this face
            u[sel] = a * at.px_per_m[k] - 0.5
            v[sel] = b * at.px_per_m[k] - 0.5 + at.rows[k]
        return cv2.remap(at.image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def _blur(
        self,
        img: NDArray[np.float32],
        M_world_sensor: NDArray[np.float64],
        M_open: NDArray[np.float64],
        M_close: NDArray[np.float64],
    ) -> NDArray[np.float32]:
        """Average of the sharp image along each pixel's image motion during the exposure. The poses:
        one each (4, 4), or one per row of the flow grid each (rows, 4, 4) for a rolling shutter."""
        if M_world_sensor.ndim == 2:
            hit, _ = self._hits(M_world_sensor, self.flow_rays)
        else:
            grid = self.flow_rays.reshape(*self.flow_px.shape[:2], 3)
            hit = self._hits(M_world_sensor, grid)[0].reshape(-1, 3)
        ends = []
        for M in (M_open, M_close):
            if M.ndim == 2:
                R, t = M[:3, :3], M[:3, 3]
                p_cam = (hit - t) @ R  # = R^T (hit - t)
            else:  # each flow row's point with its own row's pose
                n_cols = self.flow_px.shape[1]
                rel = hit.reshape(len(M), n_cols, 3) - M[:, None, :3, 3]
                p_cam = np.einsum("rci,rij->rcj", rel, M[:, :3, :3]).reshape(-1, 3)
            ends.append(self.intr.project(p_cam))  # type: ignore[attr-defined]
        flow = (ends[1] - ends[0]).reshape(*self.flow_px.shape[:2], 2).astype(np.float32)
        length = float(np.abs(flow).max()) if flow.size else 0.0
        if not np.isfinite(length) or length < 0.3:
            return img
        w, h = self.cam.width_px, self.cam.height_px
        # Flow grid point j sits at pixel j * FLOW_STEP_PX: scale the grid's resize to align them.
        gx = self.pixel_x / FLOW_STEP_PX
        gy = self.pixel_y / FLOW_STEP_PX
        fx = cv2.remap(flow[..., 0], gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        fy = cv2.remap(flow[..., 1], gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        n = min(math.ceil(length) + 1, 16)
        acc = np.zeros((h, w), np.float32)
        for s in np.linspace(-0.5, 0.5, n, dtype=np.float32):
            acc += cv2.remap(img, self.pixel_x - s * fx, self.pixel_y - s * fy, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        return acc / n


def _rays(cam: Camera, xs: NDArray[np.float64], ys: NDArray[np.float64]) -> NDArray[np.float32]:
    """Unit-depth ray directions (len(ys), len(xs), 3) in the camera's optical frame through pixels
    (xs, ys), through the lens distortion."""
    pts = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
    norm = cv2.undistortPoints(pts, cam.K, cam.dist, None, None, criteria=crit).reshape(len(ys), len(xs), 2)
    return np.concatenate([norm, np.ones((len(ys), len(xs), 1))], axis=-1).astype(np.float32)
