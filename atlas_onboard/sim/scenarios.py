"""The built-in scenarios: a world file each (in ``scenarios/``) plus the trajectories of its entities,
the simulated camera optics, and which entities run a node.

Rates and resolutions are chosen so that a scenario keeps real time on a two-core machine while every
node, renderer and detector runs (the report states them).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.config import WORLD, WorldConfig, parse_world
from atlas_onboard.config.yamlio import read_yaml
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import trajectories as tj

SIM_KIND = "sim"  # the camera source of the simulator's cameras (``camera.source: sim``)

Trajectory = tj.Quadrotor | tj.Static


@dataclass(frozen=True)
class Optics:
    """Simulated camera optics and image degradation of one sensor."""

    hfov_deg: float = 70.0
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    noise_sigma: float = 2.0  # grey levels of Gaussian pixel noise
    exposure_s: float = 0.004  # for motion blur: blur length = image speed x exposure


@dataclass(frozen=True)
class Room:
    """An axis-aligned box room in world coordinates (ENU, metres) inside which the cameras' images are
    rendered (:mod:`atlas_onboard.sim.room`), and how its camera images look.

    Attributes:
        lo_m, hi_m: opposite corners of the box (x, y, z); the floor is z = lo_m[2].
        floor_px_per_m, wall_px_per_m: texture resolution of the floor and of the walls and ceiling.
        seed: seed of the textures.
        vignetting: relative illumination lost at the image corners (0: none).
        exposure_gain: grey level per unit of reflected light (255 = white paper at the centre).
        black_level: grey level of no light.
        shot_noise: photon noise, variance in grey levels per grey level (read noise is the optics').
        jpeg_quality: JPEG quality of the delivered frame (0: uncompressed).
    """

    lo_m: tuple[float, float, float] = (-3.0, -2.5, 0.0)
    hi_m: tuple[float, float, float] = (3.0, 2.5, 3.0)
    floor_px_per_m: float = 400.0
    wall_px_per_m: float = 200.0
    seed: int = 0
    vignetting: float = 0.3
    exposure_gain: float = 0.85
    black_level: float = 8.0
    shot_noise: float = 0.06
    jpeg_quality: int = 85


@dataclass(frozen=True)
class Mocap:
    """A motion-capture system (the paper's OptiTrack) reporting rigid bodies as observations."""

    sensor: str  # name of the world sensor that stands for the mocap system
    rate_hz: float = 50.0
    sigma_m: float = 0.001
    sigma_deg: float = 0.1


@dataclass(frozen=True)
class Occlusions:
    """Something passes in front of one camera now and then (a rotor arm, a cable, a person walking
    through a ceiling camera's view), hiding every marker it would see: the gaps in detection of a real
    flight. Gaps last ``gap_s`` (uniform between its bounds) and are separated by ``clear_s``; the
    schedule is a pure function of the seed, so every process of a run sees the same one.
    """

    sensor: str  # "entity.sensor"
    gap_s: tuple[float, float] = (0.1, 0.6)
    clear_s: tuple[float, float] = (0.6, 2.0)
    seed: int = 0
    horizon_s: float = 3600.0  # the longest run (the runner's limit)

    def intervals(self) -> NDArray[np.float64]:
        """(K, 2) start and end times (s since the run's start) of the gaps up to ``horizon_s``."""
        rng = np.random.default_rng(self.seed)
        mean = (sum(self.gap_s) + sum(self.clear_s)) / 2.0
        k = int(self.horizon_s / mean * 1.5) + 2
        clear = rng.uniform(*self.clear_s, k)
        gap = rng.uniform(*self.gap_s, k)
        start = np.cumsum(clear + gap) - gap
        return np.column_stack([start, start + gap])[start < self.horizon_s]

    def hidden(self, t_s: float) -> bool:
        """True if the camera's view is blocked at ``t_s``."""
        iv = _occlusion_table(self)
        i = int(np.searchsorted(iv[:, 0], t_s, side="right")) - 1
        return i >= 0 and t_s < iv[i, 1]


@functools.cache
def _occlusion_table(occ: Occlusions) -> NDArray[np.float64]:
    return occ.intervals()


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    world_file: str
    duration_s: float
    trajectories: dict[str, Trajectory]
    drones: tuple[str, ...]  # entities that run a node with an autopilot
    scored: tuple[str, ...]  # entities whose accuracy is reported
    optics: dict[str, Optics] = field(default_factory=dict)  # by sensor name "entity.sensor"
    mocap: Mocap | None = None
    bars: dict[str, float] = field(default_factory=dict)  # e.g. {"drone_c.rmse_m": 0.10}
    occlusions: tuple[Occlusions, ...] = ()
    room: Room | None = None  # render the cameras' images inside this room (see atlas_onboard.sim.room)

    def world(self) -> WorldConfig:
        return parse_world(self.world_doc(), self.world_path())

    def world_doc(self) -> dict[str, Any]:
        """The scenario's world file as a YAML document, its simulated cameras' stamps declared exact:
        the simulator stamps each frame at its middle row's mid-exposure (``stamp_sigma_ms`` 0 where the
        file does not say otherwise)."""
        doc = read_yaml(self.world_path())
        for ent in (doc.get("entities") or {}).values():
            for sensor in (ent or {}).get("sensors", []) or []:
                camera = sensor.get("camera")
                if isinstance(camera, dict) and camera.get("source") == SIM_KIND:
                    camera.setdefault("stamp_sigma_ms", 0.0)
        return doc

    def world_path(self) -> Path:
        return Path(str(resources.files("atlas_onboard.sim") / "scenarios" / self.world_file))

    def optics_of(self, entity: str, sensor: str) -> Optics:
        return self.optics.get(f"{entity}.{sensor}", Optics())

    def occluded(self, entity: str, sensor: str, t_s: float) -> bool:
        """True if the view of camera ``entity.sensor`` is blocked at ``t_s`` (see :class:`Occlusions`)."""
        return any(o.sensor == f"{entity}.{sensor}" and o.hidden(t_s) for o in self.occlusions)

    @property
    def needs_world_node(self) -> bool:
        """A world node runs the world-fixed cameras (and the mocap), like a ground computer would."""
        world = self.world()
        return self.mocap is not None or any(s.camera is not None for s in world.entity(WORLD).sensors)


def _flights(drones: dict[str, tj.Quadrotor], **scenario: Any) -> Scenario:
    """A scenario in which every moving entity is a drone that runs a node and is scored."""
    return Scenario(trajectories=dict(drones), drones=tuple(drones), scored=tuple(drones), **scenario)


def _figure_eight(scale: float) -> tj.Quadrotor:
    """The hard scenes' drone: a figure-eight (x at 1/15 Hz, y at 2/15 Hz: two figures in 30 s, up to
    0.8 m/s at scale 1) with yaw swings of +-70 deg (up to 50 deg/s) and a controller's oscillation and
    vibration, every length times ``scale``."""
    return tj.Quadrotor(
        path=tj.lissajous((0.0, 0.0, 1.35 * scale), (1.8 * scale, 1.0 * scale, 0.2 * scale), (1 / 15, 2 / 15, 0.1)),
        yaw=tj.slow_yaw(0.0, 70.0, 9.0),
        oscillation=tj.Oscillation((0.02 * scale, 0.02 * scale, 0.01 * scale), 1.1, 0.8, seed=60),
    )


# Barrel distortion of a cheap wide-angle lens (about 106 deg across), the blur of a 8 ms exposure and
# a webcam's read noise; the room adds shot noise, vignetting and JPEG.
_HARD_OPTICS = Optics(90.0, (-0.28, 0.08, 0.0, 0.0, 0.0), noise_sigma=2.0, exposure_s=0.008)


def _paper_test1() -> Scenario:
    # The AR.Drone flies arbitrarily over the 13 tags and oscillates heavily (the paper's words).
    drone = tj.Quadrotor(
        path=tj.lissajous((0.0, 0.0, 1.5), (1.5, 0.7, 0.2), (0.071, 0.113, 0.05), (0.0, 1.0, 0.0)),
        yaw=tj.slow_yaw(0.0, 25.0, 17.0),
        oscillation=tj.Oscillation((0.03, 0.03, 0.01), 1.2, 1.0, seed=1),
    )
    return _flights(
        {"ardrone": drone},
        name="paper-test1",
        description="self-localization: 13 floor tags of 18 cm, one AR.Drone 2 with its 720p camera looking down",
        world_file="paper-test1.yaml",
        duration_s=20.0,
        optics={"ardrone.front": Optics(hfov_deg=70.0, distortion=(-0.05, 0.01, 0.0, 0.0, 0.0))},
        bars={"ardrone.rmse_m": 0.02},
    )


def _paper_test2() -> Scenario:
    tag = (-0.004, -0.052, 0.009)
    drones = {
        f"drone{i}": tj.Quadrotor(
            path=tj.circle((tag[0], tag[1], 0.9), 1.5, 30.0, phase_rad=phase),
            yaw=tj.face_point(tag[:2]),
            oscillation=tj.Oscillation((0.02, 0.02, 0.01), 0.8, 0.5, seed=10 + i),
        )
        for i, phase in ((1, 0.0), (2, 3.14159))
    }
    return Scenario(
        name="paper-test2",
        description="entity localization: two drones circle a 12 cm tag at (-4, -52, 9) mm and localize it",
        world_file="paper-test2.yaml",
        duration_s=20.0,
        trajectories={**drones, "tag": tj.Static(tag)},
        drones=("drone1", "drone2"),
        scored=("tag", "drone1", "drone2"),
        optics={f"drone{i}.front": Optics(hfov_deg=70.0) for i in (1, 2)},
        mocap=Mocap(sensor="optitrack"),
        bars={"tag.rmse_m": 0.05},
    )


def _relay() -> Scenario:
    lead = tj.shuttle((1.6, 0.0, 1.2), (3.4, 0.0, 1.2), 16.0)
    osc = {name: tj.Oscillation((0.015, 0.015, 0.01), 0.9 + 0.1 * k, 0.5, seed=20 + k) for k, name in enumerate("abc")}
    trajectories = {
        "drone_a": tj.Quadrotor(lead, tj.constant_yaw(0.0), osc["a"]),
        "drone_b": tj.Quadrotor(tj.offset(lead, (-1.2, 0.0, 0.0)), tj.constant_yaw(0.0), osc["b"]),
        "drone_c": tj.Quadrotor(tj.offset(lead, (-2.4, 0.0, 0.0)), tj.constant_yaw(0.0), osc["c"]),
    }
    return _flights(
        trajectories,
        name="relay",
        description="cooperative localization: A sees the floor tags, B sees only A, C sees only B",
        world_file="relay.yaml",
        duration_s=16.0,
        optics={n: Optics(hfov_deg=70.0) for n in ("drone_a.down", "drone_b.front", "drone_c.front")},
        bars={"drone_c.rmse_m": 0.10, "drone_c.availability": 0.95},
    )


def _relay_follow() -> Scenario:
    # A leader over floor tags, a follower behind it that sees only the tag on the leader's back: its
    # distance (1.2-2.5 m) and bearing from the leader's back (+-45 deg) vary slowly, its nose on the
    # leader. Both vibrate (0.3 deg of roll and pitch jitter at 3-8 Hz).
    lead = tj.lissajous((0.0, 0.0, 1.3), (1.5, 0.75, 0.05), (1 / 24, 1 / 12, 0.07))
    lead_yaw = tj.slow_yaw(0.0, 25.0, 17.0)
    behind = tj.behind(lead, lead_yaw, distance_m=(1.85, 0.65, 23.0), bearing_deg=(45.0, 31.0), dz_m=-0.1)
    trajectories = {
        "leader": tj.Quadrotor(lead, lead_yaw, tj.Oscillation((0.01, 0.01, 0.005), 1.0, 0.3, seed=70)),
        "follower": tj.Quadrotor(behind, tj.face_path(lead), tj.Oscillation((0.01, 0.01, 0.005), 1.3, 0.3, seed=71)),
    }
    return _flights(
        trajectories,
        name="relay-follow",
        description="a follower 1.2-2.5 m behind a moving leader sees only the 20 cm tag on its back; the leader"
        " sees 16 cm floor tags, with short stretches of none",
        world_file="relay-follow.yaml",
        duration_s=30.0,
        optics={
            "leader.down": Optics(hfov_deg=70.0, distortion=(-0.05, 0.01, 0.0, 0.0, 0.0), exposure_s=0.004),
            "follower.front": Optics(hfov_deg=60.0, distortion=(-0.05, 0.01, 0.0, 0.0, 0.0), exposure_s=0.004),
        },
        room=Room(lo_m=(-4.5, -3.5, 0.0), hi_m=(4.0, 3.5, 3.0)),
    )


def _swarm() -> Scenario:
    def osc(k: int) -> tj.Oscillation:
        return tj.Oscillation((0.02, 0.02, 0.01), 0.7 + 0.15 * k, 0.5, seed=30 + k)

    trajectories = {
        "d1": tj.Quadrotor(tj.circle((-1.5, 0.7, 1.5), 0.8, 12.0), tj.slow_yaw(0, 90, 20), osc(1)),
        "d2": tj.Quadrotor(tj.circle((-1.4, -1.2, 1.2), 0.6, 9.0, 2.0), tj.constant_yaw(45), osc(2)),
        "d3": tj.Quadrotor(tj.circle((1.5, 1.0, 1.6), 0.7, 11.0, 1.0), tj.slow_yaw(90, 60, 15), osc(3)),
        "d4": tj.Quadrotor(tj.circle((1.4, -0.9, 1.4), 0.9, 14.0, 4.0), tj.constant_yaw(-30), osc(4)),
        "d5": tj.Quadrotor(
            tj.lissajous((0.0, 0.0, 1.3), (2.2, 1.2, 0.1), (0.05, 0.1, 0.07)), tj.constant_yaw(0), osc(5)
        ),
        # d6 flies a wide circle that leaves both cameras' view for part of each lap.
        "d6": tj.Quadrotor(tj.circle((0.0, 0.0, 1.5), 3.0, 16.0, 0.5), tj.constant_yaw(0), osc(6)),
    }
    return _flights(
        trajectories,
        name="swarm",
        description="6 drones under two ceiling cameras, tags on every drone, some leaving the view",
        world_file="swarm.yaml",
        duration_s=20.0,
        optics={"world.ceiling_west": Optics(hfov_deg=90.0), "world.ceiling_east": Optics(hfov_deg=90.0)},
    )


def _paths() -> Scenario:
    # Holding formation: a slow drift (peak 8 cm/s) plus each vehicle's own oscillation.
    line = tj.shuttle((0.0, 0.0, 1.2), (0.4, 0.0, 1.2), 16.0)
    trajectories = {
        "lead": tj.Quadrotor(line, tj.constant_yaw(0.0), tj.Oscillation((0.015, 0.015, 0.01), 0.9, 0.5, seed=40)),
        "wing": tj.Quadrotor(
            tj.offset(line, (0.0, -1.0, 0.0)),
            tj.constant_yaw(0.0),
            tj.Oscillation((0.015, 0.015, 0.01), 1.1, 0.5, seed=41),
        ),
    }
    return _flights(
        trajectories,
        name="paths",
        description="a short noisy path (a far wall tag) and a long precise one (ceiling -> wing -> lead) for the lead",
        world_file="paths.yaml",
        duration_s=20.0,
        optics={n: Optics(hfov_deg=70.0) for n in ("lead.front", "wing.left", "world.ceiling")},
    )


def _gaps() -> Scenario:
    # Cruising at about 1 m/s over a sparse tag field: tags leave the view between rows, and something
    # (a swinging payload cable) blocks the camera for 0.1-0.6 s every 0.6-2 s.
    drone = tj.Quadrotor(
        path=tj.lissajous((0.0, 0.0, 1.2), (2.0, 1.0, 0.1), (0.08, 0.13, 0.05)),
        yaw=tj.slow_yaw(0.0, 20.0, 13.0),
        oscillation=tj.Oscillation((0.02, 0.02, 0.01), 1.0, 0.8, seed=50),
    )
    return _flights(
        {"drone": drone},
        name="gaps",
        description="detection gaps of 0.1-0.6 s: tags leave the view of a cruising drone, the camera is occluded",
        world_file="gaps.yaml",
        duration_s=20.0,
        optics={"drone.down": Optics(hfov_deg=70.0)},
        occlusions=(Occlusions("drone.down", seed=51),),
    )


def _hard() -> Scenario:
    return _flights(
        {"drone": _figure_eight(1.0)},
        name="hard",
        description="a figure-eight over a concrete floor with few tags, wide-angle 640x480 camera pitched down",
        world_file="hard.yaml",
        duration_s=30.0,
        optics={"drone.front": _HARD_OPTICS},
        room=Room(),
    )


def _hard_near() -> Scenario:
    # hard, every length scaled by NEAR (room, path, oscillation), the tags 30 cm (see hard-near.yaml):
    # the same views and motion in the image, tags resolved about three times better.
    near = 0.63
    return _flights(
        {"drone": _figure_eight(near)},
        name="hard-near",
        description="hard with 30 cm tags and every length x0.63 (a per-frame floor like a real hangar's scene)",
        world_file="hard-near.yaml",
        duration_s=30.0,
        optics={"drone.front": _HARD_OPTICS},
        # The room scaled too, its textures as fine in the image as hard's.
        room=Room(
            lo_m=(-3.0 * near, -2.5 * near, 0.0),
            hi_m=(3.0 * near, 2.5 * near, 3.0 * near),
            floor_px_per_m=400.0 / near,
            wall_px_per_m=200.0 / near,
        ),
    )


def _rolling(name: str, world_file: str, shutter: str) -> Scenario:
    # hard-near's room, tags and camera, flown as the independent scene of the rolling-shutter report: the
    # figure-eight a little slower (its path up to 0.6 m/s, 0.4 median) with yaw swings of +-40 deg, the
    # controller's sway but instead of the 3-8 Hz jitter the airframe's vibration, 0.3 deg and 3 mm at 2 Hz;
    # an 8 ms exposure. The world files differ only in the camera's readout (rolling.yaml: 25 ms, top row
    # first; rolling-global.yaml: 0).
    near = 0.63
    drone = tj.Quadrotor(
        path=tj.lissajous((0.0, 0.0, 1.35 * near), (1.8 * near, 1.0 * near, 0.2 * near), (1 / 18, 2 / 18, 0.1)),
        yaw=tj.slow_yaw(0.0, 40.0, 9.0),
        oscillation=tj.Oscillation((0.02 * near, 0.02 * near, 0.01 * near), 1.1, 0.0, seed=60),
        vibration=tj.Vibration(0.3, 0.003, 2.0, seed=61),
    )
    return _flights(
        {"drone": drone},
        name=name,
        description=f"hard-near's scene in a figure-eight with a 2 Hz vibration, 8 ms exposure, {shutter}",
        world_file=world_file,
        duration_s=30.0,
        optics={"drone.front": _HARD_OPTICS},
        room=Room(
            lo_m=(-3.0 * near, -2.5 * near, 0.0),
            hi_m=(3.0 * near, 2.5 * near, 3.0 * near),
            floor_px_per_m=400.0 / near,
            wall_px_per_m=200.0 / near,
        ),
    )


def _map() -> Scenario:
    # Two drones survey a room (floor and walls) for the mapper; yaw sweeps so every wall is seen.
    def drone(k: int, center: tuple[float, float, float], amp: tuple[float, float, float]) -> tj.Quadrotor:
        return tj.Quadrotor(
            path=tj.lissajous(center, amp, (0.043 + 0.01 * k, 0.067, 0.05), (0.0, k * 1.3, 0.5)),
            yaw=tj.slow_yaw(90.0 * k, 180.0, 40.0 - 7.0 * k),
            oscillation=tj.Oscillation((0.02, 0.02, 0.01), 0.9 + 0.2 * k, 0.5, seed=60 + k),
        )

    cam = Optics(hfov_deg=80.0, distortion=(-0.12, 0.03, 0.0, 0.0, 0.0))
    return _flights(
        {"mapper1": drone(0, (0.0, 0.0, 1.4), (1.6, 1.1, 0.3)), "mapper2": drone(1, (0.1, -0.1, 1.3), (1.5, 1.2, 0.2))},
        name="map",
        description="two drones survey a room of 22 markers on the floor and walls (record, map, fly on the map)",
        world_file="map.yaml",
        duration_s=60.0,
        optics={"mapper1.cam": cam, "mapper2.cam": cam},
    )


SCENARIOS = {
    s.name: s
    for s in (
        _paper_test1(),
        _paper_test2(),
        _relay(),
        _relay_follow(),
        _swarm(),
        _paths(),
        _gaps(),
        _hard(),
        _hard_near(),
        _rolling("rolling", "rolling.yaml", "a rolling shutter read top to bottom in 25 ms"),
        _rolling("rolling-global", "rolling-global.yaml", "a global shutter (rolling's twin)"),
        _map(),
    )
}
DEFAULT = "swarm"


def get(name: str) -> Scenario:
    """The scenario called ``name``, or an AtlasError listing the ones there are."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise AtlasError(f"unknown scenario {name!r} (choose from {', '.join(sorted(SCENARIOS))})") from None
