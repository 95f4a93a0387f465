"""Draw a layout as a top-down living-room picture with Pillow: drawn at twice the requested
size and box-filtered down, which softens edges."""

from __future__ import annotations

import math

from PIL import Image, ImageDraw

from fedlgr.shell.data.synth.layout import WALL, Layout

SUPERSAMPLE = 2
AGENT_SCALE = 1.5  # people and animals: large enough for a small CNN to count them at 128 px
ZONE_COLOUR = (0, 190, 255)
ROBOT_COLOUR = (250, 250, 250)
OUTLINE = (40, 40, 40)
SKIN = (235, 195, 160)
_ANIMAL_COLOURS = {"dog": (140, 95, 50), "cat": (235, 150, 60)}


def _darker(colour: tuple[int, ...], by: int = 40) -> tuple[int, ...]:
    return tuple(max(c - by, 0) for c in colour)


class _Canvas:
    """Drawing in unit-square coordinates on a square Pillow image."""

    def __init__(self, size: int, background: tuple[int, ...]):
        self.px = size * SUPERSAMPLE
        self.image = Image.new("RGB", (self.px, self.px), background)
        self.draw = ImageDraw.Draw(self.image)

    def p(self, x: float, y: float) -> tuple[float, float]:
        return x * self.px, y * self.px

    def w(self, width: float) -> int:
        return max(1, round(width * self.px))

    def rect(self, box, fill, outline=None, width=0.004, shape="rectangle"):
        x0, y0, x1, y1 = box
        getattr(self.draw, shape)(
            (*self.p(x0, y0), *self.p(x1, y1)),
            fill=fill,
            outline=outline,
            width=self.w(width) if outline else 0,
        )

    def disc(self, x, y, r, fill, outline=None, width=0.004):
        self.rect((x - r, y - r, x + r, y + r), fill, outline, width, "ellipse")

    def line(self, points, colour, width):
        self.draw.line([self.p(x, y) for x, y in points], fill=colour, width=self.w(width))

    def polygon(self, points, fill, outline=None):
        self.draw.polygon([self.p(x, y) for x, y in points], fill=fill, outline=outline)

    def oval(self, x, y, along, across, angle, fill, outline=None):
        """An ellipse with half-axes ``along`` (in direction ``angle``) and ``across``."""
        c, s = math.cos(angle), math.sin(angle)
        pts = []
        for k in range(16):
            t = 2 * math.pi * k / 16
            a, b = along * math.cos(t), across * math.sin(t)
            pts.append((x + a * c - b * s, y + a * s + b * c))
        self.polygon(pts, fill, outline)


def _at(x: float, y: float, r: float, angle: float) -> tuple[float, float]:
    """The point ``r`` away from (x, y) in the direction ``angle``."""
    return x + r * math.cos(angle), y + r * math.sin(angle)


def _floor(cv: _Canvas, layout: Layout) -> None:
    st = layout.style
    cv.rect((WALL, WALL, 1 - WALL, 1 - WALL), st.floor)
    seam = _darker(st.floor, 25)
    if st.floor_pattern == "planks":
        y, row = WALL, 0
        while y < 1 - WALL:
            cv.line([(WALL, y), (1 - WALL, y)], seam, 0.003)
            for x in (0.2, 0.5, 0.8):
                xj = x + (0.12 if row % 2 else 0.0)
                if WALL < xj < 1 - WALL:
                    cv.line([(xj, y), (xj, min(y + 0.06, 1 - WALL))], seam, 0.003)
            y, row = y + 0.06, row + 1
    elif st.floor_pattern == "tiles":
        v = WALL
        while v < 1 - WALL:
            cv.line([(WALL, v), (1 - WALL, v)], seam, 0.004)
            cv.line([(v, WALL), (v, 1 - WALL)], seam, 0.004)
            v += 0.1
    if st.rug is not None:
        x, y, w, h, colour = st.rug
        cv.rect((x, y, x + w, y + h), colour, outline=_darker(colour), width=0.008)


def _furniture(cv: _Canvas, layout: Layout) -> None:
    st = layout.style
    x0, y0, x1, y1 = layout.sofa
    cv.rect(layout.sofa, st.sofa, outline=_darker(st.sofa, 60), width=0.005)
    back = 0.035  # the backrest along the wall
    band = {
        "top": (x0, y0, x1, y0 + back),
        "bottom": (x0, y1 - back, x1, y1),
        "left": (x0, y0, x0 + back, y1),
        "right": (x1 - back, y0, x1, y1),
    }[layout.sofa_side]
    cv.rect(band, _darker(st.sofa, 35))
    cv.rect(layout.table, st.table, outline=_darker(st.table, 50), width=0.005)
    if st.plant is not None:
        px, py = st.plant
        cv.disc(px, py, 0.035, (50, 120, 50))
        for k in range(5):
            a = 2 * math.pi * k / 5
            cv.disc(px + 0.018 * math.cos(a), py + 0.018 * math.sin(a), 0.014, (80, 160, 70))


def _speaker(cv: _Canvas, layout: Layout) -> None:
    sx, sy = layout.speaker
    cv.rect((sx - 0.025, sy - 0.025, sx + 0.025, sy + 0.025), (35, 35, 40), outline=(10, 10, 10))
    cv.disc(sx, sy, 0.012, (90, 90, 100))
    if not layout.music:
        return
    towards = math.atan2(0.5 - sy, 0.5 - sx)  # waves spread into the room
    deg = math.degrees(towards)
    for r in (0.05, 0.075, 0.1):
        box = (*cv.p(sx - r, sy - r), *cv.p(sx + r, sy + r))
        cv.draw.arc(box, deg - 35, deg + 35, fill=(20, 20, 20), width=cv.w(0.008))
    nx, ny = _at(sx, sy, 0.13, towards)
    for dx in (0.0, 0.035):  # two quavers
        cv.disc(nx + dx, ny + 0.02, 0.011, (20, 20, 20))
        cv.line([(nx + dx + 0.009, ny + 0.02), (nx + dx + 0.009, ny - 0.025)], (20, 20, 20), 0.006)
    cv.line([(nx + 0.009, ny - 0.025), (nx + 0.044, ny - 0.025)], (20, 20, 20), 0.008)


def _zone(cv: _Canvas, layout: Layout) -> None:
    x, y = layout.robot_x, layout.robot_y
    if layout.mode == "circle":
        cv.disc(x, y, layout.zone, None, outline=ZONE_COLOUR, width=0.012)
        return
    h = layout.robot_heading
    ex, ey = _at(x, y, layout.zone, h)
    cv.line([(x, y), (ex, ey)], ZONE_COLOUR, 0.016)
    tip = _at(ex, ey, 0.04, h)
    left, right = _at(ex, ey, 0.035, h + math.pi / 2), _at(ex, ey, 0.035, h - math.pi / 2)
    cv.polygon([tip, left, right], ZONE_COLOUR)


def _person(cv: _Canvas, person, clothes) -> None:
    k = (0.65 if person.child else 1.0) * AGENT_SCALE
    f = person.facing
    cv.oval(person.x, person.y, 0.026 * k, 0.04 * k, f, clothes, outline=OUTLINE)
    hx, hy = _at(person.x, person.y, 0.01 * k, f)
    cv.disc(hx, hy, 0.017 * k, SKIN, outline=OUTLINE, width=0.003)
    side = 0.008 * k
    nose = _at(hx, hy, 0.024 * k, f)
    cv.polygon([nose, _at(hx, hy, side, f + 1.6), _at(hx, hy, side, f - 1.6)], OUTLINE)


def _animal(cv: _Canvas, animal) -> None:
    colour = _ANIMAL_COLOURS[animal.kind]
    k = (1.0 if animal.kind == "dog" else 0.75) * AGENT_SCALE
    f = animal.facing
    tail = _at(animal.x, animal.y, -0.045 * k, f)
    cv.line([(animal.x, animal.y), tail], _darker(colour), 0.007)
    cv.oval(animal.x, animal.y, 0.03 * k, 0.016 * k, f, colour, outline=_darker(colour, 60))
    head = _at(animal.x, animal.y, 0.03 * k, f)
    cv.disc(*head, 0.013 * k, _darker(colour, 20), outline=_darker(colour, 60), width=0.003)


def _robot(cv: _Canvas, layout: Layout) -> None:
    x, y, h = layout.robot_x, layout.robot_y, layout.robot_heading
    cv.disc(x, y, 0.035, ROBOT_COLOUR, outline=OUTLINE, width=0.006)
    back_l, back_r = _at(x, y, 0.018, h + 2.3), _at(x, y, 0.018, h - 2.3)
    cv.polygon([_at(x, y, 0.03, h), back_l, back_r], (30, 30, 30))


def render(layout: Layout, size: int = 128) -> Image.Image:
    """A ``size`` x ``size`` RGB picture of the scene."""
    cv = _Canvas(size, layout.style.wall)
    _floor(cv, layout)
    _furniture(cv, layout)
    _speaker(cv, layout)
    _zone(cv, layout)
    for animal in layout.animals:
        _animal(cv, animal)
    for person, clothes in zip(layout.people, layout.style.clothes, strict=True):
        _person(cv, person, clothes)
    _robot(cv, layout)
    return cv.image.reduce(SUPERSAMPLE)
