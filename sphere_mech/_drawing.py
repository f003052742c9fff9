"""What a picture of a system shows: the fixed points (a chain's pivot, a particle's
centre), a moving base, the links as polylines from a fixed point or the base through the
masses, and the spheres that several masses share. Shared by `plot.png`,
`animation.html` and `sm.animate`."""

import dataclasses

import jax
import numpy as np

from ._scene.scene import Scene


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """`anchors`: `(k, 3)` fixed points; `links`: polylines as indices into the `(k + p,
    3)` array of `points(x)` (anchors first, then the `p` points of `x`: a scene's
    `points(q)`, its base's point first); `spheres`: `(centre, radius)` of each sphere that
    several masses share; `free`: masses on no link; `bases`: the indices into
    `points(x)` of moving bases (drawn as squares)."""

    anchors: np.ndarray
    links: tuple[np.ndarray, ...]
    spheres: tuple[tuple[np.ndarray, float], ...]
    free: np.ndarray
    bases: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=int))

    def points(self, x: np.ndarray) -> np.ndarray:
        """Anchors and masses, `(..., k + n, 3)`, from positions `x` of shape `(..., n, 3)`."""
        anchors = np.broadcast_to(self.anchors, x.shape[:-2] + self.anchors.shape)
        return np.concatenate([anchors, x], axis=-2)

    @property
    def tips(self) -> np.ndarray:
        """Indices into `points` of the masses whose paths tell the motion: the end of
        each link, and every free mass."""
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
    """The skeleton of a `Scene`, for `points(q)`, from what each kinetic term draws
    (`AbstractKinetic.drawing`: chains hang from their pivot, particles from their
    centres, beads on a `SharedSphere` show the sphere); links start from the scene's
    moving `Base` where it has one (a `Chain`'s offset from it is drawn as part of its
    first link). Of any other system, the `n` points on the unit sphere centred at the
    origin."""
    if not isinstance(system, Scene):
        return Skeleton(np.zeros((1, 3)), (), ((np.zeros(3), 1.0),), np.arange(n))
    anchors, links, spheres, free = [], [], [], []
    bases = [] if system.base is None else [0]  # points(q): the base's point first
    offset = len(bases)
    for k in system.kinetic:
        k_links, k_spheres, k_free = k.drawing()
        for support, masses in k_links:
            start = bases or [_anchor(anchors, support)]
            links.append(start + [offset + i for i in masses])
        spheres += [(np.asarray(c, float), float(r)) for c, r in k_spheres]
        free += [offset + i for i in k_free]
        offset += k.n
    anchors = np.asarray(anchors, dtype=float).reshape(-1, 3)
    index = lambda i: i + len(anchors) if i >= 0 else -1 - i
    return Skeleton(
        anchors,
        tuple(np.asarray([index(i) for i in link]) for link in links),
        tuple(spheres),
        np.asarray(free, dtype=int),
        np.asarray(bases, dtype=int) + len(anchors),
    )


def positions(system, q) -> np.ndarray:
    """The points drawn, `(T, p, 3)`: a scene's `points(q)` (its base's point first), else
    `q`."""
    if isinstance(system, Scene):
        return np.asarray(jax.vmap(system.points)(q))
    return np.asarray(q)


def cube(skel: Skeleton, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and half-width of a cube holding every point and sphere (equal aspect)."""
    pts = skel.points(x).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=-1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    for c, r in skel.spheres:
        lo, hi = np.minimum(lo, c - r), np.maximum(hi, c + r)
    half = 0.54 * float(np.max(hi - lo))
    return (lo + hi) / 2, half if half > 0 else 1.0


def equal_axes(ax, skel: Skeleton, x: np.ndarray) -> None:
    """Equal-aspect 3-D axes around the whole motion."""
    centre, half = cube(skel, x)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x [m]", fontsize=8, labelpad=-2)
    ax.set_ylabel("y [m]", fontsize=8, labelpad=-2)
    ax.set_zlabel("z [m]", fontsize=8, labelpad=-2)
    ax.tick_params(labelsize=7, pad=0)


def draw_static(ax, skel: Skeleton) -> list:
    """The spheres (wireframes) and the anchors (black squares; a moving base is drawn
    with the moving parts); returns legend handles."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    for c, r in skel.spheres:
        ax.plot_wireframe(
            c[0] + r * np.cos(u) * np.sin(v),
            c[1] + r * np.sin(u) * np.sin(v),
            c[2] + r * np.cos(v),
            color="0.75",
            lw=0.4,
        )
    if not len(skel.anchors):
        return []
    a, label = skel.anchors, "pivot" if skel.links else "centre"
    return ax.plot(a[:, 0], a[:, 1], a[:, 2], "ks", ms=5, label=label, zorder=5)
