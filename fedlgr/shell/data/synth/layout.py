"""Random living-room layouts in the unit square seen from above (y down, angles as
``atan2(dy, dx)``), and the 27 MANNERS-DB descriptors computed from them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

WALL = 0.04  # wall thickness; the floor is [WALL, 1 - WALL]^2
DISTANCE_SCALE = 1.2  # distances are divided by this (a bit more than the room diagonal)
FACING_CONE = math.pi / 4  # "facing" means within +-45 degrees
MAX_PEOPLE = 10  # 3 on the sofa + a group of 4 + 3 others
MAX_GROUP = 4
MAX_GROUP_RADIUS = 0.15
MAX_ZONE = 0.5  # largest work radius / arrow length
MAX_CHILDREN = 3
MAX_ANIMALS = 2
MAX_SOFA = 3
MAX_AGENTS = MAX_PEOPLE + MAX_ANIMALS + 1  # people, animals and the robot


@dataclass(frozen=True)
class Person:
    x: float
    y: float
    facing: float
    child: bool = False
    sitting: bool = False  # on the sofa
    in_group: bool = False


@dataclass(frozen=True)
class Animal:
    x: float
    y: float
    facing: float
    kind: str  # "dog" | "cat"


@dataclass(frozen=True)
class Group:
    x: float
    y: float
    radius: float


@dataclass(frozen=True)
class Style:
    """Colours and textures: varied so that a CNN has to look at the layout."""

    floor: tuple[int, int, int]
    floor_pattern: str  # "plain" | "planks" | "tiles"
    wall: tuple[int, int, int]
    sofa: tuple[int, int, int]
    table: tuple[int, int, int]
    rug: tuple[float, float, float, float, tuple[int, int, int]] | None
    plant: tuple[float, float] | None
    clothes: tuple[tuple[int, int, int], ...]  # one per person


@dataclass(frozen=True)
class Layout:
    robot_x: float
    robot_y: float
    robot_heading: float
    mode: str  # "circle" | "arrow"
    zone: float  # work radius (circle) or arrow length (arrow)
    sofa: tuple[float, float, float, float]  # x0, y0, x1, y1
    sofa_side: str  # the wall the sofa's back touches: "top" | "bottom" | "left" | "right"
    table: tuple[float, float, float, float]
    speaker: tuple[float, float]
    music: bool
    people: tuple[Person, ...] = ()
    animals: tuple[Animal, ...] = ()
    group: Group | None = None
    style: Style | None = field(default=None, compare=False)


def wrap(angle: float) -> float:
    """Angle folded into (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))


def bearing(layout: Layout, x: float, y: float) -> float:
    """Angle of (x, y) relative to the robot's heading, in (-pi, pi] (0 = straight ahead)."""
    return wrap(math.atan2(y - layout.robot_y, x - layout.robot_x) - layout.robot_heading)


def faces(facing: float, from_x: float, from_y: float, to_x: float, to_y: float) -> bool:
    """Does something at ``from`` looking along ``facing`` face the point ``to``?"""
    return abs(wrap(math.atan2(to_y - from_y, to_x - from_x) - facing)) < FACING_CONE


def distance(layout: Layout, x: float, y: float) -> float:
    return math.hypot(x - layout.robot_x, y - layout.robot_y)


# --------------------------------------------------------------------------- sampling


def _colour(rng: np.random.Generator, base: tuple[int, int, int], jitter: int) -> tuple[int, ...]:
    return tuple(int(np.clip(c + rng.integers(-jitter, jitter + 1), 0, 255)) for c in base)


_FLOORS = ((196, 164, 120), (170, 170, 165), (222, 206, 180), (150, 115, 85), (200, 200, 190))
_WALLS = ((235, 230, 220), (200, 210, 220), (225, 215, 200), (180, 180, 180))
_SOFAS = ((120, 60, 60), (60, 80, 120), (90, 110, 80), (110, 110, 110), (150, 120, 90))
_TABLES = ((120, 85, 50), (160, 120, 80), (90, 60, 40), (200, 200, 200))
_CLOTHES = (
    (200, 40, 40),
    (40, 90, 200),
    (230, 170, 30),
    (40, 150, 70),
    (150, 60, 170),
    (240, 120, 40),
    (30, 30, 30),
    (230, 230, 230),
    (120, 200, 220),
    (200, 90, 150),
)


def _style(rng: np.random.Generator, n_people: int) -> Style:
    pick = lambda options, jitter: _colour(rng, options[rng.integers(len(options))], jitter)  # noqa: E731
    rug = None
    if rng.random() < 0.5:
        x, y = rng.uniform(0.15, 0.55, size=2)
        w, h = rng.uniform(0.2, 0.35, size=2)
        rug = (float(x), float(y), float(w), float(h), pick(_SOFAS, 40))
    plant = (
        tuple(float(v) for v in rng.choice([0.09, 0.91], size=2)) if rng.random() < 0.5 else None
    )
    return Style(
        floor=pick(_FLOORS, 20),
        floor_pattern=str(rng.choice(["plain", "planks", "tiles"])),
        wall=pick(_WALLS, 10),
        sofa=pick(_SOFAS, 25),
        table=pick(_TABLES, 20),
        rug=rug,
        plant=plant,  # type: ignore[arg-type]
        clothes=tuple(pick(_CLOTHES, 25) for _ in range(n_people)),
    )


def _sofa(rng: np.random.Generator) -> tuple[tuple[float, float, float, float], str]:
    side = str(rng.choice(["top", "bottom", "left", "right"]))
    length, depth = 0.32, 0.11
    start = float(rng.uniform(0.12, 0.88 - length))
    lo, hi = (WALL, WALL + depth) if side in ("top", "left") else (1 - WALL - depth, 1 - WALL)
    if side in ("top", "bottom"):
        return (start, lo, start + length, hi), side
    return (lo, start, hi, start + length), side


def _inside(rect: tuple[float, float, float, float], x: float, y: float, margin: float) -> bool:
    x0, y0, x1, y1 = rect
    return x0 - margin <= x <= x1 + margin and y0 - margin <= y <= y1 + margin


def _free_spot(rng, taken, obstacles, spacing=0.07, lo=0.1, hi=0.9, tries=40):
    """A point at least ``spacing`` from every taken point and off the furniture."""
    for _ in range(tries):
        x, y = (float(v) for v in rng.uniform(lo, hi, size=2))
        if all(math.hypot(x - a, y - b) >= spacing for a, b in taken) and not any(
            _inside(r, x, y, 0.02) for r in obstacles
        ):
            return x, y
    return x, y  # crowded room: accept the last draw


def sample_layout(rng: np.random.Generator) -> Layout:
    """Draw one living-room scene from ``rng``; a seed's scenes depend on the order of the draws
    (furniture, robot, people on the sofa, group, people standing, animals, speaker, music)."""
    sofa, sofa_side = _sofa(rng)
    tx, ty = rng.uniform(0.3, 0.6, size=2)
    table = (float(tx), float(ty), float(tx) + 0.16, float(ty) + 0.1)
    furniture = (sofa, table)
    robot_x, robot_y, heading, mode, zone = _robot(rng, furniture)
    taken = [(robot_x, robot_y)]  # where everyone stands so far; each step adds its own
    people = _sofa_people(rng, sofa, sofa_side, taken)
    group, members = _group(rng, robot_x, robot_y, furniture, taken)
    people += members
    people += _standing_people(rng, furniture, taken)
    animals = _animals(rng, furniture, taken)
    speaker = (float(rng.choice([0.08, 0.92])), float(rng.choice([0.08, 0.92])))
    music = bool(rng.random() < 0.35)
    return Layout(
        robot_x=robot_x,
        robot_y=robot_y,
        robot_heading=heading,
        mode=mode,
        zone=zone,
        sofa=sofa,
        sofa_side=sofa_side,
        table=table,
        speaker=speaker,
        music=music,
        people=tuple(people),
        animals=tuple(animals),
        group=group,
        style=_style(rng, len(people)),
    )


def _robot(rng: np.random.Generator, furniture) -> tuple[float, float, float, str, float]:
    """The robot's place, heading, mode and zone (work radius or arrow length)."""
    robot_x, robot_y = _free_spot(rng, [], furniture, lo=0.15, hi=0.85)
    mode = "circle" if rng.random() < 0.5 else "arrow"
    zone = float(rng.uniform(0.12, 0.32) if mode == "circle" else rng.uniform(0.2, 0.45))
    for _ in range(30):  # an arrow points into the room (a few tries, then take what comes)
        heading = float(rng.uniform(-math.pi, math.pi))
        tip_x, tip_y = robot_x + zone * math.cos(heading), robot_y + zone * math.sin(heading)
        if mode == "circle" or (0.08 <= tip_x <= 0.92 and 0.08 <= tip_y <= 0.92):
            break
    return robot_x, robot_y, heading, mode, zone


def _sofa_people(rng: np.random.Generator, sofa, sofa_side: str, taken: list) -> list[Person]:
    """0-3 people on the sofa, facing into the room."""
    into_room = {"top": math.pi / 2, "bottom": -math.pi / 2, "left": 0.0, "right": math.pi}[
        sofa_side
    ]
    people = []
    n_sofa = int(rng.choice(4, p=[0.4, 0.3, 0.2, 0.1]))
    for k in range(n_sofa):
        t = (k + 0.5) / 3
        x0, y0, x1, y1 = sofa
        x, y = (
            (x0 + t * (x1 - x0), (y0 + y1) / 2)
            if sofa_side in ("top", "bottom")
            else ((x0 + x1) / 2, y0 + t * (y1 - y0))
        )
        facing = into_room + float(rng.normal(0, 0.3))
        people.append(Person(x, y, facing, sitting=True, child=bool(rng.random() < 0.2)))
        taken.append((x, y))
    return people


def _group(
    rng: np.random.Generator, robot_x: float, robot_y: float, furniture, taken: list
) -> tuple[Group | None, list[Person]]:
    """Maybe a conversation group: a cluster with a radius, everyone facing its centre."""
    if rng.random() >= 0.45:
        return None, []
    size = int(rng.integers(2, MAX_GROUP + 1))
    radius = float(rng.uniform(0.06, 0.14))
    if rng.random() < 0.25:  # sometimes the robot stands inside the group
        a, r = rng.uniform(-math.pi, math.pi), rng.uniform(0, 0.6 * radius)
        gx, gy = robot_x + r * math.cos(a), robot_y + r * math.sin(a)
    else:
        gx, gy = _free_spot(rng, taken, furniture, spacing=radius + 0.06, lo=0.2, hi=0.8)
    group = Group(float(np.clip(gx, 0.18, 0.82)), float(np.clip(gy, 0.18, 0.82)), radius)
    members = []
    start = rng.uniform(-math.pi, math.pi)
    for k in range(size):
        a = start + 2 * math.pi * k / size + rng.normal(0, 0.2)
        x, y = group.x + radius * math.cos(a), group.y + radius * math.sin(a)
        facing = wrap(a + math.pi + rng.normal(0, 0.2))
        members.append(Person(x, y, facing, in_group=True, child=bool(rng.random() < 0.15)))
        taken.append((x, y))
    return group, members


def _standing_people(rng: np.random.Generator, furniture, taken: list) -> list[Person]:
    """0-3 people standing about, some of them children."""
    people = []
    for _ in range(int(rng.choice(4, p=[0.3, 0.3, 0.25, 0.15]))):
        x, y = _free_spot(rng, taken, furniture)
        people.append(
            Person(x, y, float(rng.uniform(-math.pi, math.pi)), child=bool(rng.random() < 0.35))
        )
        taken.append((x, y))
    return people


def _animals(rng: np.random.Generator, furniture, taken: list) -> list[Animal]:
    """0-2 dogs or cats."""
    animals = []
    for _ in range(int(rng.choice(3, p=[0.5, 0.3, 0.2]))):
        x, y = _free_spot(rng, taken, furniture, spacing=0.06)
        animals.append(
            Animal(x, y, float(rng.uniform(-math.pi, math.pi)), str(rng.choice(["dog", "cat"])))
        )
        taken.append((x, y))
    return animals


# --------------------------------------------------------------------------- descriptors


def descriptors(layout: Layout) -> np.ndarray:
    """The 27 MANNERS-DB descriptors in ``DESCRIPTOR_COLUMNS`` order, each in 0..1; absent
    things read as far away (distance 1), behind (direction 1) and not facing (flags 0)."""
    lx, ly = layout.robot_x, layout.robot_y
    by_distance = sorted(layout.people, key=lambda p: distance(layout, p.x, p.y))
    nearest = (by_distance + [None] * 3)[:3]

    def dist(p):  # a person, a group or an animal
        return 1.0 if p is None else min(distance(layout, p.x, p.y) / DISTANCE_SCALE, 1.0)

    def direction(p):
        return 1.0 if p is None else abs(bearing(layout, p.x, p.y)) / math.pi

    def robot_faces(p):  # a person or a group
        return 0.0 if p is None else float(abs(bearing(layout, p.x, p.y)) < FACING_CONE)

    def faces_robot(p):
        return 0.0 if p is None else float(faces(p.facing, p.x, p.y, lx, ly))

    closest = nearest[0]
    from_closest = (
        1.0
        if closest is None
        else abs(wrap(math.atan2(ly - closest.y, lx - closest.x) - closest.facing)) / math.pi
    )
    g = layout.group
    children = [p for p in layout.people if p.child]
    closest_child = min(children, key=lambda p: distance(layout, p.x, p.y), default=None)
    closest_animal = min(layout.animals, key=lambda a: distance(layout, a.x, a.y), default=None)
    values = [
        len(layout.people) / MAX_PEOPLE,
        sum(p.in_group for p in layout.people) / MAX_GROUP,
        0.0 if g is None else g.radius / MAX_GROUP_RADIUS,
        dist(g),
        0.0 if g is None else float(distance(layout, g.x, g.y) < g.radius),
        robot_faces(g),
        layout.zone / MAX_ZONE,
        *(dist(p) for p in nearest),
        *(direction(p) for p in nearest),
        from_closest,
        *(robot_faces(p) for p in nearest),
        *(faces_robot(p) for p in nearest),
        len(children) / MAX_CHILDREN,
        dist(closest_child),
        len(layout.animals) / MAX_ANIMALS,
        dist(closest_animal),
        sum(p.sitting for p in layout.people) / MAX_SOFA,
        float(layout.music),
        (len(layout.people) + len(layout.animals) + 1) / MAX_AGENTS,
    ]
    return np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
