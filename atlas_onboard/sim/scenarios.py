"""The built-in scenarios (:class:`~atlas_onboard.sim.scenario.Scenario`): a world file each (in
``scenarios/``) plus the trajectories of its entities, the simulated camera optics, and which entities run
a node.

Rates and resolutions are chosen so that a scenario keeps real time on a two-core machine while every
node, renderer and detector runs (the report states them).
"""

from __future__ import annotations

from typing import Any

from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import trajectories as tj
from atlas_onboard.sim.scenario import Landing, Mocap, Occlusions, Optics, Room, Scenario


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


def _landings() -> tuple[Scenario, Scenario]:
    """Precision landings, flown closed loop on the node's LANDING_TARGET (:mod:`atlas_onboard.sim.flight`);
    the touchdown bars are the landing's (3 cm on a static pad, 8 cm on a moving rover)."""
    pad = Scenario(
        name="land-pad",
        description="a drone lands (PX4's form) on a static pad of world tags that only its own downward camera sees",
        world_file="land-pad.yaml",
        duration_s=20.0,
        trajectories={"drone": tj.Flown((0.5, -0.4, 1.2), 25.0)},
        drones=("drone",),
        scored=("drone",),
        optics={"drone.down": Optics(hfov_deg=70.0)},
        bars={"drone.touchdown_m": 0.03},
        landing=Landing(entity="drone", target="world", marker=0, form="px4"),
    )
    rover = Scenario(
        name="land-rover",
        description="a drone lands (ArduPilot's form) on a rover driving at 0.3 m/s that only a ceiling camera and"
        " a peer drone see",
        world_file="land-rover.yaml",
        duration_s=20.0,
        trajectories={
            "drone": tj.Flown((0.6, 0.5, 1.6), -30.0),
            "rover": tj.driving((-0.3, 0.0, 0.0), (0.3, 0.0, 0.0)),
            "peer": tj.Static((-1.6, 0.0, 1.1)),
        },
        drones=("drone", "peer"),
        scored=("drone",),
        optics={"world.ceiling": Optics(hfov_deg=90.0), "peer.front": Optics(hfov_deg=60.0)},
        bars={"drone.touchdown_m": 0.08},
        landing=Landing(entity="drone", target="rover", marker=20, form="ardupilot"),
    )
    return pad, rover


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
        *_landings(),
    )
}
DEFAULT = "swarm"


def get(name: str) -> Scenario:
    """The scenario called ``name``, or an AtlasError listing the ones there are."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise AtlasError(f"unknown scenario {name!r} (choose from {', '.join(sorted(SCENARIOS))})") from None
