"""The appropriateness model of the synthetic living room, and its simulated raters: the circle
mode counts who is inside the work radius, the arrow mode who is in the corridor ahead (rules
different enough that a model learning arrow after circle forgets circle, for FCL)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fedlgr.shell.data.synth.layout import FACING_CONE, Layout, bearing, distance, faces

# Column order of LABEL_COLUMNS: vacuum, mop, warm food, cold food, drinks, small objects,
# big objects, conversation.
_BASE = np.array([4.6, 4.5, 4.1, 4.3, 4.2, 4.4, 4.3, 2.0])
# How much one adult / child / animal in the zone costs each action.
_ADULT = np.array([0.9, 0.8, 0.5, 0.4, 0.6, 0.4, 1.1, 0.0])
_CHILD = np.array([1.2, 1.0, 1.4, 0.6, 0.9, 0.6, 1.4, 0.0])
_ANIMAL = np.array([0.8, 0.6, 0.4, 0.3, 0.5, 0.8, 1.0, 0.0])
# Room-wide effects, whatever the mode.
_MUSIC = np.array([-0.9, -0.3, 0.0, 0.0, 0.0, 0.0, 0.0, -0.5])
_SOFA = np.array([-0.35, -0.2, 0.0, 0.0, 0.0, 0.0, -0.1, 0.1])  # per person on the sofa
_PEOPLE = np.array([-0.12, -0.1, 0.0, 0.0, 0.0, -0.1, -0.15, 0.0])  # per person in the room
_ROOM_CHILD = np.array([-0.2, -0.1, -0.25, 0.0, -0.1, 0.0, -0.1, 0.0])  # per child in the room
_GROUP = np.array([-0.2, -0.1, 0.0, 0.0, 0.0, 0.0, -0.4, -0.2])  # a group is gathered
# Serving: the closest person is near (< 0.3) and faces the robot.
_SERVE = np.array([0.0, 0.0, 0.3, 0.3, 0.5, 0.1, 0.0, 0.6])
# Someone near (< 0.2) who does not face the robot (may bump into it).
_BLIND = np.array([-0.2, -0.2, -0.3, -0.2, -0.5, -0.1, -0.3, 0.0])
# Arrow mode is for transport: carrying gains, cleaning loses.
_ARROW_SHIFT = np.array([-0.6, -0.6, 0.9, 0.9, 0.9, 0.8, 0.8, 0.3])
# Arrow mode: children and animals in the path are tripping hazards.
_ARROW_CHILD_FACTOR, _ARROW_ANIMAL_FACTOR = 1.5, 1.4
_ARROW_LASTING = 0.2  # arrow mode: weight of music and sofa effects against the circle
_ENGAGED = 0.9  # conversation: per person in the zone who faces the robot


def _sigmoid(z: float) -> float:
    return 1.0 / (1.0 + math.exp(-max(min(z, 50.0), -50.0)))


def exposure(layout: Layout, x: float, y: float, facing: float | None) -> float:
    """How much something at (x, y) is in the robot's zone of operation, 0..~1.6."""
    if layout.mode == "circle":
        return _sigmoid((layout.zone - distance(layout, x, y)) / 0.025)
    dx, dy = x - layout.robot_x, y - layout.robot_y
    hx, hy = math.cos(layout.robot_heading), math.sin(layout.robot_heading)
    along, lateral = dx * hx + dy * hy, abs(dx * hy - dy * hx)
    in_path = (
        _sigmoid((layout.zone + 0.05 - along) / 0.025)
        * _sigmoid(along / 0.02)
        * _sigmoid((0.12 - lateral) / 0.02)
    )
    unaware = facing is None or not faces(facing, x, y, layout.robot_x, layout.robot_y)
    return in_path * (1.6 if unaware else 1.0)


def true_appropriateness(layout: Layout) -> np.ndarray:
    """The noiseless appropriateness of the 8 actions in this scene, clipped to 1..5."""
    arrow = layout.mode == "arrow"
    score = _BASE.copy()
    engaged = 0.0
    for p in layout.people:
        e = exposure(layout, p.x, p.y, p.facing)
        if p.child:
            score -= e * _CHILD * (_ARROW_CHILD_FACTOR if arrow else 1.0)
        else:
            score -= e * _ADULT
        if faces(p.facing, p.x, p.y, layout.robot_x, layout.robot_y):
            engaged += min(e, 1.0)
    for a in layout.animals:
        score -= (
            exposure(layout, a.x, a.y, None) * _ANIMAL * (_ARROW_ANIMAL_FACTOR if arrow else 1.0)
        )
    score[-1] += _ENGAGED * min(engaged, 2.5)

    n_children = sum(p.child for p in layout.people)
    # Working in place lasts: music and people resting on the sofa matter in a circle,
    # much less when the robot only passes through.
    lasting = _ARROW_LASTING if arrow else 1.0
    score += lasting * (_MUSIC * layout.music + _SOFA * sum(p.sitting for p in layout.people))
    score += _PEOPLE * len(layout.people) + _ROOM_CHILD * n_children
    score += _GROUP * (layout.group is not None)
    if layout.people:
        closest = min(layout.people, key=lambda p: distance(layout, p.x, p.y))
        d = distance(layout, closest.x, closest.y)
        facing = faces(closest.facing, closest.x, closest.y, layout.robot_x, layout.robot_y)
        # Serving needs the person in reach; in arrow mode also ahead of the robot.
        reachable = d < 0.3 and (
            not arrow or abs(bearing(layout, closest.x, closest.y)) < FACING_CONE
        )
        score += _SERVE * (reachable and facing) + _BLIND * (d < 0.2 and not facing)
    if arrow:
        score += _ARROW_SHIFT
    return np.clip(score, 1.0, 5.0)


@dataclass(frozen=True)
class RaterPool:
    """Simulated crowd workers: a personal bias each, and noise on every rating."""

    bias: np.ndarray  # (n_raters,)
    noise: float = 0.5

    @classmethod
    def sample(
        cls, rng: np.random.Generator, n_raters: int = 60, bias_sd: float = 0.35
    ) -> RaterPool:
        return cls(bias=rng.normal(0.0, bias_sd, size=n_raters))

    def rate(self, truth: np.ndarray, raters: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Likert ratings (len(raters), 8) of one scene by the given raters."""
        noisy = (
            truth[None, :] + self.bias[raters, None] + rng.normal(0, self.noise, (len(raters), 8))
        )
        return np.clip(np.rint(noisy), 1, 5).astype(np.int64)
