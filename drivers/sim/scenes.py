"""Named scenes: a world, a lighting, a path for the vehicle and its speeds.

Names are stable (runs record them in run.toml). ``build_scene(name, seed)`` returns a
:class:`Scene`; the same (name, seed) always gives the same world.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .world import Obstacle, World, make_waves

SCENES: dict[str, str] = {
    "stubble-day": "broad-acre sorghum stubble by day (sun), obstacle course on the first pass "
                   "of a lawn-mower coverage path",
    "stubble-night": "the same field and obstacles at night, lit only by a strobe at the "
                     "cameras (1/r^2 fall-off, black sky, more sensor noise)",
    "greenhouse": "straight 1.2 m path between rows of ~1 m pepper bushes; crates, buckets, a "
                  "person, a bush-green crate on the path; low leaves overhanging the path",
    "stubble-empty": "the stubble field by day with no obstacles at all (false-positive tests)",
    "stubble-coverage": "the stubble field by day covered lane by lane for long closed-loop runs: "
                        "14 lanes of 250 m, 6 m apart, headland U-turns; the papers' obstacle "
                        "kinds on some lanes and midway between lanes, the rest of the lanes clear",
    "stubble-lookalike": "the stubble-day field and obstacle course with the obstacles that look "
                         "like the field: a person in khaki on the path, the stubble-coloured "
                         "drum and a stubble-textured crate (the learned cue's hard cases)",
}

STUBBLE_CLASSES = ("person", "person-crouching", "vehicle", "drum", "tank", "pole", "barrel",
                   "crate", "look-alike-drum")
# stubble-lookalike: these replace the hi-vis person and the orange crate of the course
LOOKALIKE_CLASSES = ("khaki-person", "look-alike-crate")
_KHAKI = (0.40, 0.56, 0.64)          # BGR: a khaki shirt, close to the straw's hue
_KHAKI_TROUSERS = (0.31, 0.46, 0.55)
GREENHOUSE_CLASSES = ("crate", "bucket", "person", "look-alike-crate", "box")

# colours are BGR in [0, 1]
_STRAW = (0.36, 0.58, 0.74)


@dataclass
class Scene:
    name: str
    seed: int
    world: World
    illumination: str                 # "day" | "night-strobe" | "greenhouse" (diffuse day)
    path: np.ndarray                  # (N, 2) polyline the vehicle follows, world x, y
    cruise_mps: float
    slow_mps: float
    footprint: tuple[float, float, float]   # (rear overhang behind origin, length, width) m
    wheelbase_m: float
    track_m: float
    bounce_deg: float                 # amplitude of the seeded suspension oscillation
    detour_offset_m: float = 0.0      # how far the safety driver steers round (0 = never)

    @property
    def frame_illumination(self) -> str:
        """The run-format value: "day" or "night-strobe"."""
        return "night-strobe" if self.illumination == "night-strobe" else "day"


def _lawnmower(length_m: float, spacing_m: float, passes: int, turn_pts: int = 24) -> np.ndarray:
    """Passes along +x / -x at y = 0, spacing, 2*spacing..., joined by semicircular turns."""
    pts = []
    r = spacing_m / 2
    for p in range(passes):
        y = p * spacing_m
        xs = np.arange(0.0, length_m + 1e-9, 1.0)
        if p % 2:
            xs = xs[::-1]
        pts.extend((x, y) for x in xs)
        if p < passes - 1:
            cx = length_m if p % 2 == 0 else 0.0
            for a in np.linspace(-np.pi / 2, np.pi / 2, turn_pts)[1:-1]:
                if p % 2 == 0:
                    pts.append((cx + r * np.cos(a), y + r + r * np.sin(a)))
                else:
                    pts.append((cx - r * np.cos(a), y + r + r * np.sin(a)))
    return np.array(pts, np.float64)


def _stubble_obstacles(rng: np.random.Generator, path_len: float) -> list[Obstacle]:
    """The papers' obstacle kinds, as an obstacle course at 8-40 m along the first pass, then
    more spread along the pass for long runs. Some stand on the path (a vehicle that never
    stops hits them), the others beside it."""
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731
    obs = [
        Obstacle("o1", "look-alike-drum", "cylinder", 9.0 + j(0.5), -2.2 + j(0.3), 0.0,
                 0.6, 0.6, 0.9, _STRAW, texture="stubble"),
        Obstacle("o2", "person", "person", 13.0 + j(1.0), 0.1 + j(0.2), 90.0 + j(20),
                 0.3, 0.5, 1.8, (0.10, 0.45, 0.95), (0.35, 0.20, 0.12)),       # hi-vis orange
        Obstacle("o3", "drum", "cylinder", 17.0 + j(1.0), 2.4 + j(0.3), 0.0,
                 0.6, 0.6, 0.9, (0.65, 0.30, 0.10), (0.25, 0.12, 0.05)),       # blue steel drum
        Obstacle("o4", "person-crouching", "person-crouching", 20.5 + j(1.0), -1.3 + j(0.3),
                 90.0 + j(30), 0.6, 0.5, 1.0, (0.60, 0.25, 0.30), (0.20, 0.18, 0.15)),
        Obstacle("o5", "pole", "cylinder", 23.0 + j(1.0), -3.5 + j(0.5), 0.0,
                 0.25, 0.25, 8.0, (0.25, 0.30, 0.33)),                       # weathered wood
        Obstacle("o6", "barrel", "cylinder", 26.0 + j(1.0), 0.2 + j(0.2), 0.0,
                 0.56, 0.56, 0.95, (0.10, 0.15, 0.75), (0.9, 0.9, 0.9)),     # red plastic
        Obstacle("o7", "tank", "cylinder", 30.0 + j(1.5), 5.0 + j(0.5), 0.0,
                 2.0, 2.0, 2.0, (0.20, 0.32, 0.18)),                         # dark green poly
        Obstacle("o8", "vehicle", "vehicle", 35.0 + j(1.5), -4.8 + j(0.5), 75.0 + j(20),
                 4.5, 1.8, 1.8, (0.85, 0.85, 0.86), (0.15, 0.12, 0.10)),     # white ute
        Obstacle("o9", "crate", "box", 39.0 + j(1.0), -0.3 + j(0.3), j(30),
                 0.6, 0.5, 0.5, (0.05, 0.45, 0.85), (0.04, 0.30, 0.55)),     # orange crate
    ]
    # more along the pass for long runs: one every ~40 m, a third of them on the path
    x = 75.0
    n = len(obs)
    while x < path_len - 20:
        cls = STUBBLE_CLASSES[int(rng.integers(len(STUBBLE_CLASSES)))]
        proto = next(o for o in obs if o.cls == cls)
        on_path = rng.uniform() < 0.35
        y = j(0.3) if on_path else float(rng.choice([-1, 1]) * rng.uniform(1.8, 5.0))
        n += 1
        obs.append(Obstacle(f"o{n}", cls, proto.shape, x + j(3), y, proto.yaw_deg + j(40),
                            proto.length_m, proto.width_m, proto.height_m, proto.colour,
                            proto.colour2, proto.texture, proto.shiny))
        x += float(rng.uniform(30, 50))
    return obs


# stubble-coverage: lane length, lane spacing, lanes (3.6 km of path: ~24 min at 2.5 m/s)
COVERAGE_LANES = (250.0, 6.0, 14)


def _coverage_obstacles(rng: np.random.Generator, length_m: float, spacing_m: float,
                        passes: int) -> list[Obstacle]:
    """Obstacles for a long coverage run. Each lane gets 0-2 obstacles ON it (centre within
    0.3 m of the lane, so a vehicle that never stops hits them) and the gap to the next lane
    0-2 small ones midway between the lanes (seen from both lanes, hit from neither). Nothing
    within 30 m of the headlands, nothing in the first 60 m of the first lane (the novelty
    model learns the first frame whole), obstacles on a lane at least 40 m apart. The kinds,
    sizes and colours are those of the stubble obstacle course."""
    protos = {o.cls: o for o in _stubble_obstacles(np.random.default_rng(0), 0.0)}
    small = ("person", "person-crouching", "drum", "barrel", "crate", "look-alike-drum", "pole")
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731
    obs: list[Obstacle] = []

    def place(n: int, lo: float, classes, y: float, jitter_y: float) -> None:
        xs: list[float] = []
        for _ in range(50):
            if len(xs) == n:
                break
            x = float(rng.uniform(lo, length_m - 30.0))
            if all(abs(x - q) >= 40.0 for q in xs):
                xs.append(x)
        for x in sorted(xs):
            cls = classes[int(rng.integers(len(classes)))]
            pr = protos[cls]
            obs.append(Obstacle(f"c{len(obs) + 1}", cls, pr.shape, x, y + j(jitter_y),
                                pr.yaw_deg + j(40), pr.length_m, pr.width_m, pr.height_m,
                                pr.colour, pr.colour2, pr.texture, pr.shiny))

    for p in range(passes):
        y = p * spacing_m
        place(int(rng.choice([0, 1, 1, 2])), 60.0 if p == 0 else 30.0, STUBBLE_CLASSES, y, 0.3)
        if p < passes - 1:
            place(int(rng.choice([0, 1, 1, 2])), 30.0, small, y + spacing_m / 2, 0.2)
    return obs


def _greenhouse_obstacles(rng: np.random.Generator) -> list[Obstacle]:
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731
    green = (0.17, 0.27, 0.17)
    return [
        Obstacle("g1", "crate", "box", 4.0 + j(0.3), 0.1 + j(0.1), j(20),
                 0.55, 0.38, 0.30, (0.70, 0.35, 0.10), (0.45, 0.22, 0.05)),    # blue crate
        Obstacle("g2", "bucket", "cylinder", 8.0 + j(0.3), -0.25 + j(0.1), 0.0,
                 0.30, 0.30, 0.32, (0.75, 0.75, 0.78), (0.6, 0.6, 0.6), shiny=True),  # galvanised
        Obstacle("g3", "person", "person", 12.0 + j(0.3), 0.0 + j(0.1), 90.0 + j(20),
                 0.3, 0.5, 1.75, (0.55, 0.35, 0.25), (0.25, 0.20, 0.15)),
        Obstacle("g4", "look-alike-crate", "box", 16.0 + j(0.3), 0.15 + j(0.1), j(20),
                 0.55, 0.38, 0.30, green, (0.12, 0.20, 0.12)),
        Obstacle("g5", "box", "box", 20.0 + j(0.3), -0.2 + j(0.1), j(30),
                 0.40, 0.30, 0.30, (0.35, 0.55, 0.70), (0.25, 0.40, 0.52)),   # cardboard
        Obstacle("g6", "bucket", "cylinder", 24.0 + j(0.3), 0.25 + j(0.1), 0.0,
                 0.30, 0.30, 0.32, (0.15, 0.55, 0.90), (0.10, 0.40, 0.70)),   # yellow plastic
        Obstacle("g7", "crate", "box", 28.0 + j(0.3), -0.1 + j(0.1), 90 + j(20),
                 0.55, 0.38, 0.30, (0.15, 0.15, 0.70), (0.10, 0.10, 0.45)),   # red crate
    ]


def _lookalike(o: Obstacle) -> Obstacle:
    """The course's hi-vis person in khaki and its orange crate stubble-textured, in the same
    places (the same draws of the field's RNG); every other obstacle as it is."""
    from dataclasses import replace
    if o.cls == "person":
        return replace(o, cls="khaki-person", colour=_KHAKI, colour2=_KHAKI_TROUSERS)
    if o.cls == "crate":
        return replace(o, cls="look-alike-crate", colour=_STRAW, colour2=_STRAW,
                       texture="stubble")
    return o


def build_scene(name: str, seed: int = 0) -> Scene:
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(sorted(SCENES))}")
    # one RNG per world (not per scene name) so day / night / empty share the field
    if name == "greenhouse":
        rng = np.random.default_rng([seed, 2])
        waves = make_waves(rng, 0.02, n=4, wavelengths=(3.0, 12.0))
        world = World("greenhouse", seed, _greenhouse_obstacles(rng), waves,
                      sky_bgr=(0.97, 0.98, 0.98), horizon_bgr=(0.93, 0.95, 0.95))
        path = np.array([(x, 0.0) for x in np.arange(0.0, 36.0, 1.0)])
        return Scene(name, seed, world, "greenhouse", path, cruise_mps=0.7, slow_mps=0.3,
                     footprint=(0.1, 1.2, 0.8), wheelbase_m=0.8, track_m=0.6, bounce_deg=0.3)
    rng = np.random.default_rng([seed, 1])
    waves = make_waves(rng, 0.20, n=6, wavelengths=(5.0, 40.0))
    if name == "stubble-coverage":
        length, spacing, passes = COVERAGE_LANES
        path = _lawnmower(length, spacing, passes)
        obstacles = _coverage_obstacles(rng, length, spacing, passes)
    else:
        length, spacing, passes = 300.0, 6.0, 8
        path = _lawnmower(length, spacing, passes)
        obstacles = _stubble_obstacles(rng, length)
    if name == "stubble-empty":
        obstacles = []
    if name == "stubble-lookalike":
        obstacles = [_lookalike(o) for o in obstacles]
    world = World("stubble", seed, obstacles, waves)
    illum = "night-strobe" if name == "stubble-night" else "day"
    return Scene(name, seed, world, illum, path, cruise_mps=2.5, slow_mps=1.0,
                 footprint=(0.4, 2.6, 1.5), wheelbase_m=1.8, track_m=1.2, bounce_deg=1.2,
                 detour_offset_m=3.0)
