"""What a simulated scenario is: its world file, the trajectories of its entities, which run a node and
which are scored, the simulated cameras' optics, the room their images are rendered in, the motion
capture and the occlusions. The built-in ones are :mod:`atlas_onboard.sim.scenarios`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.config import WORLD, WorldConfig, parse_world
from atlas_onboard.config.yamlio import read_yaml
from atlas_onboard.sim import trajectories as tj

SIM_KIND = "sim"  # the camera source of the simulator's cameras (``camera.source: sim``)

Trajectory = tj.Quadrotor | tj.Static | tj.Flown


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
class Landing:
    """A precision landing: ``entity`` (flown by its autopilot, :class:`~atlas_onboard.sim.trajectories.Flown`)
    lands on marker ``marker`` of entity ``target`` (``world``: a pad of world markers), its node sending
    LANDING_TARGET in the form of autopilot ``form`` (px4 or ardupilot)."""

    entity: str
    target: str
    marker: int
    form: str


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
    landing: Landing | None = None

    @property
    def flown(self) -> tuple[str, ...]:
        """The entities flown closed loop (their truth exists only as the run goes: nothing pre-rendered)."""
        return tuple(n for n, t in self.trajectories.items() if isinstance(t, tj.Flown))

    def with_flights(self, directory: Path) -> Scenario:
        """This scenario in a run whose flight files are in ``directory`` (one per flown entity)."""
        bound = {n: t.bound(flight_path(directory, n)) if isinstance(t, tj.Flown) else t
                 for n, t in self.trajectories.items()}  # fmt: skip
        return replace(self, trajectories=bound)

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


def flight_path(directory: Path, entity: str) -> Path:
    """The flight file of a flown entity in a run's directory."""
    return directory / f"flight-{entity}.f64"
