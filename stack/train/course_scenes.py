"""Stage 3 of ``stack-train drl`` (ours, issue 19): training scenes cut from generated courses, with a curriculum
over obstacle density and robot count.

Bai's stages scatter cuboids, cylinders and short walls round one or four robots. A user's site has long walls
with one gap, narrow passages the formation must reshape for, and 3-8 robots in many formation families: what
:mod:`stack.fleet.courses` generates. A stage-3 scene is a stretch of such a course (training seeds only, never
the held-out range): the course's corridor, walls and obstacles; its formation moved to a random point of the
corridor (every robot at least ``clear`` off every obstacle); each robot's target its own place translated
5-14 m down the corridor (stage 2's common shift, so the targets keep the formation's shape), every target
reachable by a disc of the robot's radius (the flood fill of :func:`.drlworld.reachable`). Robots beyond the
course's count are parked far away and inactive (:meth:`.drlworld.DrlWorld.reset`).

``follow`` scenes (``stack-train drl --stage 3 --follow``, :class:`.drlworld.WorldConfig`'s ``follow``): the same
stretches, the targets :data:`SHIFT_FOLLOW` on, the leader's moving and the followers' slots moving with it.

Curriculum (``progress`` = episodes done / episodes): below 1/3 only ``low`` courses of 3-4 robots, below 2/3
``low`` and ``medium`` of 3-6 robots, then every density and 3-8 robots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stack.fleet.courses import DENSITIES, HELDOUT_SEEDS, generate_course
from stack.policies.qlearn import reachable as flood_fill
from stack.scenario import parse_scenario

from .drlworld import FAR, obstacle_distance, reachable, scene_arrays

MAX_ROBOTS = 8
LEVELS = ((("low",), 4), (("low", "medium"), 6), (tuple(DENSITIES), MAX_ROBOTS))
"""The curriculum's thirds: (densities, most robots)."""
REACH_CELL = 0.2
"""[m] the reachability flood fill's cell (coarse: a scene is drawn at every episode's start)."""
REACH_MARGIN = 0.05
"""[m] clearance beyond the robot's radius that a free cell needs (:func:`.drlworld.reachable`'s default)."""
SHIFT = (5.0, 14.0)
"""[m] how far down the corridor the targets lie from the starts (stage 2's common shift)."""
SHIFT_FOLLOW = (10.0, 25.0)
"""[m] the same in ``follow`` scenes: a longer way beside the neighbours, as in a fleet run."""


def heldout_clash(first_seed: int, n: int) -> str | None:
    """Why courses ``first_seed`` .. ``first_seed + n - 1`` may not be trained on (None: they may)."""
    last = first_seed + n - 1
    if first_seed <= HELDOUT_SEEDS.stop - 1 and last >= HELDOUT_SEEDS.start:
        return (f"course seeds {first_seed}..{last} reach the held-out range {HELDOUT_SEEDS.start}..{HELDOUT_SEEDS.stop - 1}"
                " (no training uses them)")
    return None


def level(progress: float) -> tuple[tuple[str, ...], int]:
    """The curriculum's densities and most robots at ``progress`` (0..1) of the training."""
    return LEVELS[min(len(LEVELS) - 1, int(max(progress, 0.0) * len(LEVELS)))]


@dataclass
class PoolCourse:
    density: str
    robots: int
    length: float
    half_width: float
    offsets: np.ndarray  # (n, 2) the robots' starts relative to the leader's
    yaws: np.ndarray  # (n,)
    circles: np.ndarray
    boxes: np.ndarray
    radius: float
    free: tuple | None = None  # (origin (2,), grid): the reachability fill's free cells, made once (CourseScenes._reach)


class CourseScenes:
    """A pool of generated courses (seeds ``first_seed`` ..), and scenes cut from them (:meth:`__call__`)."""

    def __init__(self, n: int, first_seed: int = 0, *, max_circles: int = 24, max_boxes: int = 24,
                 clear: float = 0.3, robots: int = MAX_ROBOTS, follow: bool = False):
        if heldout_clash(first_seed, n):
            raise ValueError(heldout_clash(first_seed, n))
        self.R, self.clear, self.progress = robots, clear, 0.0
        self.shift = SHIFT_FOLLOW if follow else SHIFT
        self.pool = [self._course(first_seed + k, k, max_circles, max_boxes) for k in range(n)]

    def _course(self, seed: int, k: int, max_circles: int, max_boxes: int) -> PoolCourse:
        """Course ``seed``: the densities in turn, the robot count cycling 3..R (so every level has courses)."""
        dens = tuple(DENSITIES)[k % len(DENSITIES)]
        n = 3 + (k // len(DENSITIES)) % (self.R - 2)
        c = generate_course(seed, robots=n, density=dens)
        sc = parse_scenario(c.scenario)
        p = np.array([r.pose for r in sc.robots], float)
        circles, boxes = scene_arrays(sc.obstacles, max_circles, max_boxes)
        if len(circles) > max_circles or len(boxes) > max_boxes:
            raise ValueError(f"course {seed}: {len(circles)} cylinders, {len(boxes)} boxes; the world holds "
                             f"{max_circles} and {max_boxes}")
        return PoolCourse(dens, n, c.length, c.half_width, p[:, :2] - p[0, :2], p[:, 2], circles, boxes,
                          sc.robots[0].radius)

    def __call__(self, rng: np.random.Generator):
        """A scene (starts (R, 2), yaws (R,), goals (R, 2), circles, boxes) at the current ``progress``."""
        dens, most = level(self.progress)
        fits = [c for c in self.pool if c.density in dens and c.robots <= most]
        c = fits[int(rng.integers(len(fits)))]
        starts, goals = self._place(rng, c)
        yaws = c.yaws + rng.normal(0.0, 0.3, c.robots)
        pad = self.R - c.robots  # parked far away, apart, inactive (DrlWorld.reset)
        park = np.column_stack([FAR + 100.0 * (1 + np.arange(pad)), np.full(pad, FAR)])
        return (np.vstack([starts, park]), np.concatenate([yaws, np.zeros(pad)]), np.vstack([goals, park]),
                c.circles, c.boxes)

    def _place(self, rng: np.random.Generator, c: PoolCourse, tries: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """The formation at a random point of the corridor, the targets ``shift`` (5-14 m) on; where no try fits,
        the course's own start (its field begins 6 m ahead) with the targets the shortest shift on."""
        for _ in range(tries):
            starts = c.offsets + [float(rng.uniform(0.0, max(c.length - self.shift[1], 0.0))), 0.0]
            goals = starts + [float(rng.uniform(*self.shift)), 0.0]
            if self._fits(c, starts, goals):
                return starts, goals
        return c.offsets.copy(), c.offsets + [self.shift[0], 0.0]

    def _fits(self, c: PoolCourse, starts: np.ndarray, goals: np.ndarray) -> bool:
        pts = np.vstack([starts, goals])
        if np.abs(pts[:, 1]).max() > c.half_width - c.radius - self.clear:
            return False
        if obstacle_distance(pts[:, 0], pts[:, 1], c.circles, c.boxes).min() < c.radius + self.clear:
            return False
        return all(self._reach(c, s, g) for s, g in zip(starts, goals))

    def _reach(self, c: PoolCourse, start: np.ndarray, goal: np.ndarray) -> bool:
        """:func:`.drlworld.reachable` on the course's free cells, computed once for the whole corridor (a scene is
        drawn at every episode's start); the fill keeps to 5 m round ``start`` and ``goal`` as there."""
        if c.free is None:
            lo = np.array([c.offsets[:, 0].min() - 10.0, -c.half_width - 5.0])
            X, Y = np.meshgrid(np.arange(lo[0], c.length + self.shift[1] + 10.0, REACH_CELL),
                               np.arange(lo[1], c.half_width + 5.0, REACH_CELL), indexing="ij")
            c.free = (lo, obstacle_distance(X, Y, c.circles, c.boxes) > c.radius + REACH_MARGIN)
        lo, free = c.free
        i0 = np.floor((np.minimum(start, goal) - 5.0 - lo) / REACH_CELL).astype(int)
        i1 = np.ceil((np.maximum(start, goal) + 5.0 - lo) / REACH_CELL).astype(int)
        if (i0 < 0).any() or (i1 > free.shape).any():  # beyond the cached cells: the window's own grid
            return reachable(start, goal, c.circles, c.boxes, c.radius, cell=REACH_CELL, margin=REACH_MARGIN)
        window = free[i0[0]:i1[0], i0[1]:i1[1]]
        cell = lambda p: tuple(int(k) for k in np.floor((p - lo) / REACH_CELL).astype(int) - i0)  # noqa: E731
        return flood_fill(~window, cell(start), cell(goal))


def parked(starts: np.ndarray) -> np.ndarray:
    """Which robots of a scene are parked (not in it)."""
    return np.asarray(starts)[..., 0] >= FAR / 2


__all__ = ["CourseScenes", "heldout_clash", "level", "parked", "LEVELS", "MAX_ROBOTS"]

