"""Other cars: parked cars along the parking lanes, moving cars in the other lanes and an optional lead
car ahead of the ego car, each an oriented box standing on the road, and the ray/box intersection that
lets them occlude the road for the cameras and the Lidar."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.world.ego_trajectory import EgoTrajectory
from sim.world.linear_maps import apply_matrix
from sim.world.road_atlas import lane_centre, lane_forward
from sim.world.road_world import RoadWorld, centreline_frame, height_st, road_point

CAR_COLOURS = np.array([
    [0.80, 0.80, 0.80], [0.04, 0.04, 0.05], [0.45, 0.46, 0.48], [0.55, 0.06, 0.05], [0.06, 0.15, 0.45],
    [0.25, 0.25, 0.27], [0.70, 0.62, 0.45], [0.10, 0.30, 0.15],
], np.float32)


@dataclass
class Traffic:
    """N cars: box sizes, paint, and their motion along the road."""

    size: np.ndarray  # (N, 3) length, width, height (m)
    colour: np.ndarray  # (N, 3) linear RGB albedo
    s0: np.ndarray  # (N,) arc length at time 0 (for the lead car: its gap ahead of the ego car)
    t: np.ndarray  # (N,) lateral position
    speed: np.ndarray  # (N,) signed speed along s (0 parked)
    forward: np.ndarray  # (N,) bool, facing +s
    follows_ego: np.ndarray  # (N,) bool: s = ego s + s0


@dataclass
class CarBoxes:
    """The cars at one instant: box centres, rotations (box -> ENU) and half extents."""

    centre: np.ndarray  # (N, 3)
    rotation: np.ndarray  # (N, 3, 3)
    half: np.ndarray  # (N, 3)
    colour: np.ndarray  # (N, 3)


def place_traffic(world: RoadWorld, ego: EgoTrajectory, seconds: float, rng: np.random.Generator) -> Traffic:
    sc = world.scenario
    road, traffic = sc.road, sc.traffic
    length = world.length_m
    sizes, colours, s0, t, speed, forward, follows = [], [], [], [], [], [], []

    def add(s_start: float, lat: float, v: float, fwd: bool, follow: bool = False) -> None:
        van = rng.random() < 0.12
        sizes.append([rng.uniform(5.0, 5.6) if van else rng.uniform(4.1, 4.9), rng.uniform(1.75, 1.95),
                      rng.uniform(1.9, 2.3) if van else rng.uniform(1.4, 1.65)])
        colours.append(CAR_COLOURS[rng.integers(len(CAR_COLOURS))])
        s0.append(s_start)
        t.append(lat)
        speed.append(v)
        forward.append(fwd)
        follows.append(follow)

    for lane in traffic.parking_lanes:
        toward_curb = -0.35 if lane_forward(road, lane) else 0.35
        gap = 100.0 / traffic.parked_cars_per_100m if traffic.parked_cars_per_100m > 0 else np.inf
        s = rng.uniform(0, gap)
        while s < length - 3:
            if rng.random() > 0.15:  # some places stay free
                add(s, lane_centre(road, lane) + toward_curb + rng.normal(0, 0.08), 0.0, lane_forward(road, lane))
            s += gap * rng.uniform(0.8, 1.3)

    moving_lanes = [k for k in range(road.lanes) if k not in traffic.parking_lanes and k != sc.drive.ego_lane]
    if moving_lanes and traffic.moving_cars:
        lane_speed = {k: rng.uniform(0.8, 1.2) * sc.drive.speed_mps for k in moving_lanes}
        per_lane = np.array_split(np.arange(traffic.moving_cars), len(moving_lanes))
        ego_end = float(ego.s[-1])
        for lane, cars in zip(moving_lanes, per_lane, strict=True):
            fwd = lane_forward(road, lane)
            v = lane_speed[lane] if fwd else -lane_speed[lane]
            # Spread the cars over the stretch of road they will cross while the ego car drives.
            lo = sc.drive.start_s_m - 40 - (v * seconds if v > 0 else 0)
            hi = ego_end + 80 - (v * seconds if v < 0 else 0)
            slots = np.sort(rng.choice(np.arange(lo, hi, 12.0), size=min(len(cars), int((hi - lo) / 12)),
                                       replace=False))
            for s in slots:
                add(float(s), lane_centre(road, lane) + rng.normal(0, 0.1), v, fwd)
    if traffic.lead_car_gap_m is not None:
        add(traffic.lead_car_gap_m, lane_centre(road, sc.drive.ego_lane), 0.0, True, follow=True)
    n = len(sizes)
    return Traffic(size=np.array(sizes, np.float64).reshape(n, 3), colour=np.array(colours, np.float32).reshape(n, 3),
                   s0=np.array(s0, np.float64), t=np.array(t, np.float64), speed=np.array(speed, np.float64),
                   forward=np.array(forward, bool), follows_ego=np.array(follows, bool))


def car_boxes(world: RoadWorld, traffic: Traffic, ego: EgoTrajectory, time_s: float) -> CarBoxes:
    """The boxes of the cars on the road at one true time."""
    ego_s = float(ego.sample("s", np.array([time_s]))[0])
    s = np.where(traffic.follows_ego, ego_s + traffic.s0, traffic.s0 + traffic.speed * time_s)
    on_road = (s > 2.0) & (s < world.length_m - 2.0)
    s, lat = s[on_road], traffic.t[on_road]
    size, colour, fwd = traffic.size[on_road], traffic.colour[on_road], traffic.forward[on_road]
    xy = road_point(world, s, lat)
    _, _, tx, ty = centreline_frame(world, s)
    ahead = height_st(world, s + 1.0, lat) - height_st(world, s - 1.0, lat)
    sign = np.where(fwd, 1.0, -1.0)
    yaw = np.arctan2(ty, tx) + np.where(fwd, 0.0, np.pi)
    pitch = -np.arctan2(ahead * sign, 2.0)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    rot = np.zeros((len(s), 3, 3))
    rot[:, 0] = np.stack([cy * cp, -sy, cy * sp], axis=1)
    rot[:, 1] = np.stack([sy * cp, cy, sy * sp], axis=1)
    rot[:, 2] = np.stack([-sp, np.zeros_like(sp), cp], axis=1)
    half = size / 2
    ground = np.column_stack([xy, height_st(world, s, lat)])
    centre = ground + rot[:, :, 2] * half[:, 2:3]
    return CarBoxes(centre=centre, rotation=rot, half=half, colour=colour)


def ray_box_hits(origin: np.ndarray, directions: np.ndarray, centre: np.ndarray, rotation: np.ndarray,
                 half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray to one box (inf where missed) and the hit face's normal in the box frame.

    origin (3,) or (N, 3), directions (N, 3) (any length: the distance is in units of the direction)."""
    rt = rotation.T
    o = apply_matrix(np.atleast_2d(np.asarray(origin, np.float32) - centre.astype(np.float32)), rt)
    d = apply_matrix(directions, rt)
    h = half.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.float32(1.0) / d
        t1 = (-h - o) * inv
        t2 = (h - o) * inv
    near = np.minimum(t1, t2)
    far = np.maximum(t1, t2)
    t_enter = near.max(axis=-1)
    hit = (t_enter <= far.min(axis=-1)) & (t_enter > 0)
    rows = np.flatnonzero(hit)
    normal = np.zeros(directions.shape, np.float32)
    axis = near[rows].argmax(axis=-1)
    normal[rows, axis] = -np.sign(d[rows, axis])
    return np.where(hit, t_enter, np.float32(np.inf)), normal
