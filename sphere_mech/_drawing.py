"""What a picture of a system shows (for `plot.png`, `animation.html` and `sm.animate`): fixed
points, a moving base, links through the masses, and the spheres several masses share."""

import dataclasses

import jax
import numpy as np

from ._scene.rotorcraft import Rotors
from ._scene.scene import Scene


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """`anchors`: `(k, 3)` fixed points; `links`: polylines as indices into `points(x)`
    (anchors, then the points of `x`); `spheres`: `(centre, radius)` of shared spheres;
    `free`: masses on no link; `bases`: indices into `points(x)` of moving bases; `frame`:
    polylines of a rigid base's arms (indices into `points(x)`); `rotors`: indices into
    `points(x)` of the ends of the arms along `+-e1`, `+-e2`, where `Rotors` sit."""

    anchors: np.ndarray
    links: tuple[np.ndarray, ...]
    spheres: tuple[tuple[np.ndarray, float], ...]
    free: np.ndarray
    bases: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=int))
    frame: tuple[np.ndarray, ...] = ()
    rotors: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=int))

    def points(self, x: np.ndarray) -> np.ndarray:
        """Anchors and masses, `(..., k + n, 3)`, from positions `x` of shape `(..., n, 3)`."""
        anchors = np.broadcast_to(self.anchors, x.shape[:-2] + self.anchors.shape)
        return np.concatenate([anchors, x], axis=-2)

    @property
    def tips(self) -> np.ndarray:
        """Indices into `points` of each link's end and every free mass."""
        ends = [link[-1] for link in self.links]
        return np.asarray(ends + list(self.free + len(self.anchors)), dtype=int)

    def mass(self, i: int) -> int:
        """The number of the mass at index `i` of `points`."""
        return i - len(self.anchors) - len(self.bases)


def _anchor(anchors: list, point) -> int:
    point = np.asarray(point, dtype=float)
    for i, a in enumerate(anchors):
        if np.allclose(a, point):
            return -1 - i
    anchors.append(point)
    return -len(anchors)


def skeleton(system, n: int) -> Skeleton:
    """The skeleton of a `Scene`'s `drawn_points(q)` from its kinetic terms' `drawing()`
    (links from the moving base where it has one: a `RigidBase`'s joint, its arms drawn as
    `frame`, with `Rotors` at the ends of four); of a system on `Spheres`, its `n` points on
    the unit sphere."""
    if not isinstance(system, Scene):
        return Skeleton(np.zeros((1, 3)), (), ((np.zeros(3), 1.0),), np.arange(n))
    anchors, links, spheres, free = [], [], [], []
    bases = [] if system.base is None else [0]  # points(q): the base's point first
    offset = len(bases)
    rigid = system.rigid_body is not None
    joint = 1 + system.n  # drawn_points(q): after points(q), a rigid base's joint and arms
    start_of = lambda support: [joint] if rigid else bases or [_anchor(anchors, support)]
    for k in system.kinetic:
        k_links, k_spheres, k_free = k.drawing()
        for support, masses in k_links:
            start = start_of(support)
            links.append(start + [offset + i for i in masses])
        spheres += [(np.asarray(c, float), float(r)) for c, r in k_spheres]
        free += [offset + i for i in k_free]
        offset += k.n
    anchors = np.asarray(anchors, dtype=float).reshape(-1, 3)
    index = lambda i: i + len(anchors) if i >= 0 else -1 - i
    links = tuple(np.asarray([index(i) for i in link]) for link in links)
    arms = joint + 1 + np.arange(5)  # +e1, -e1, +e2, -e2, e3
    frame = () if not rigid else ((arms[0], 0, arms[1]), (arms[2], 0, arms[3]), (0, arms[4]))
    frame = tuple(np.asarray([index(i) for i in line]) for line in frame)
    bases = np.asarray(bases, dtype=int) + len(anchors)
    free = np.asarray(free, dtype=int)
    flown = rigid and any(isinstance(e, Rotors) for e in system.force_effects)
    rotors = np.asarray([index(i) for i in arms[:4]] if flown else [], dtype=int)
    return Skeleton(anchors, links, tuple(spheres), free, bases, frame, rotors)


def positions(system, q) -> np.ndarray:
    """The points drawn, `(T, p, 3)`: a scene's `drawn_points(q)`, else (a system on
    `Spheres`) `q`."""
    return np.asarray(jax.vmap(system.drawn_points)(q) if isinstance(system, Scene) else q)


def cube(skel: Skeleton, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and half-width of a cube holding every point and sphere (equal aspect)."""
    pts = skel.points(x).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=-1)]
    lo = np.min([pts.min(axis=0), *(c - r for c, r in skel.spheres)], axis=0)
    hi = np.max([pts.max(axis=0), *(c + r for c, r in skel.spheres)], axis=0)
    half = 0.54 * float(np.max(hi - lo))
    return (lo + hi) / 2, half if half > 0 else 1.0


def equal_axes(ax, skel: Skeleton, x: np.ndarray) -> None:
    """Equal-aspect 3-D axes around the whole motion."""
    centre, half = cube(skel, x)
    limits = [(c - half, c + half) for c in centre]
    ax.set(xlim=limits[0], ylim=limits[1], zlim=limits[2], box_aspect=(1, 1, 1))
    for set_label, name in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), "xyz", strict=True):
        set_label(f"{name} [m]", fontsize=8, labelpad=-2)
    ax.tick_params(labelsize=7, pad=0)


def wireframe(centre: np.ndarray, radius: float) -> np.ndarray:
    """A sphere's grid, `(3, 13, 25)`: rows are parallels (pole to pole), columns meridians."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    return np.asarray(centre, float)[:, None, None] + radius * unit


def draw_static(ax, skel: Skeleton) -> list:
    """The spheres (wireframes) and the anchors (black squares); returns legend handles."""
    for c, r in skel.spheres:
        ax.plot_wireframe(*wireframe(c, r), color="0.75", lw=0.4)
    if not len(skel.anchors):
        return []
    a, label = skel.anchors, "pivot" if skel.links else "centre"
    return ax.plot(a[:, 0], a[:, 1], a[:, 2], "ks", ms=5, label=label, zorder=5)
