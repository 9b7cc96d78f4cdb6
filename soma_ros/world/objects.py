"""Deformable objects of the reference world: geometry, placement and MJCF.

Each object is one MuJoCo flex built from a ``flexcomp type="direct"`` whose
points and elements are generated here, so the vertex layout is known:

* ``rope``  1D discrete elastic rod (capsule chain, edge-length equality),
  a gently curved centre line of ``segments + 1`` vertices.
* ``cloth`` 2D shell (``elastic2d="both"``), a ``count[0] x count[1]`` grid
  with texture coordinates for a checker print.
* ``doll``  3D tetrahedral volume: a plush figure (torso, head, four limbs)
  as the union of ellipsoids, filled with a lattice of points and
  tetrahedralised (scipy Delaunay, tets kept if their centroid is inside).

Shapes: ``points`` [N, 3] world metres, ``elements`` [E, dim + 1] int.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .config import ObjectConfig

__all__ = ["ObjectGeometry", "make_object_geometry", "flexcomp_xml", "OBJECT_FLEX_NAME"]

#: Name of the object's flex in the MuJoCo model (vertex bodies are ``object_<i>``).
OBJECT_FLEX_NAME = "object"


@dataclass
class ObjectGeometry:
    """The object's rest geometry placed in the world (before simulation)."""

    kind: str
    dim: int
    points: np.ndarray  # [N, 3] world, metres
    elements: np.ndarray  # [E, dim + 1]
    texcoords: Optional[np.ndarray] = None  # [N, 2]
    #: Object placement: centre (world xy) and yaw (rad).
    center_xy: np.ndarray = field(default_factory=lambda: np.zeros(2))
    yaw: float = 0.0
    #: Unit vector [3] of the object's main axis in the world (rope tangent, cloth x, doll spine).
    main_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    #: Named key points in the world [3] (e.g. cloth corners, doll head), for task planning.
    keypoints: dict[str, np.ndarray] = field(default_factory=dict)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(local: np.ndarray, center_xy: np.ndarray, yaw: float, z0: float) -> np.ndarray:
    """Rotate local points [N, 3] by yaw about z and move them to (center_xy, z0 + local z)."""
    out = local @ _rot_z(yaw).T
    out[:, 0] += center_xy[0]
    out[:, 1] += center_xy[1]
    out[:, 2] += z0
    return out


# --------------------------------------------------------------------------- rope


def _rope(cfg: ObjectConfig, rng: np.random.Generator, center_xy: np.ndarray, yaw: float, table_z: float) -> ObjectGeometry:
    n = cfg.segments
    if n < 4:
        raise ValueError("rope: segments must be >= 4")
    seg = cfg.length / n
    if seg <= 2.0 * cfg.radius:
        raise ValueError(f"rope: segment length {seg:.4f} m must exceed the diameter {2 * cfg.radius:.4f} m")
    # Curvature along the rope: kappa(s) = c0 + c1 cos(pi s / L); total turning <= max_bend.
    s = (np.arange(n) + 0.5) / n
    c0, c1 = rng.uniform(-1.0, 1.0, size=2) * cfg.max_bend / 2.0
    turn = (c0 + c1 * np.cos(np.pi * s)) / n  # heading change per segment
    heading = np.cumsum(turn) - np.sum(turn) / 2.0
    steps = np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], axis=1) * seg
    local = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)], axis=0)
    local -= local.mean(axis=0)
    pts = _place(local, center_xy, yaw, table_z + cfg.radius + 0.0005)
    elements = np.stack([np.arange(n), np.arange(1, n + 1)], axis=1)
    axis = pts[-1] - pts[0]
    axis /= np.linalg.norm(axis)
    return ObjectGeometry(
        kind="rope",
        dim=1,
        points=pts,
        elements=elements,
        center_xy=center_xy,
        yaw=yaw,
        main_axis=axis,
        keypoints={"end_a": pts[0].copy(), "end_b": pts[-1].copy()},
    )


# --------------------------------------------------------------------------- cloth


def _cloth(cfg: ObjectConfig, rng: np.random.Generator, center_xy: np.ndarray, yaw: float, table_z: float) -> ObjectGeometry:
    nx, ny = (int(c) for c in cfg.count)
    if nx < 3 or ny < 3:
        raise ValueError("cloth: count must be at least 3 x 3")
    sx, sy = cfg.size[0] / (nx - 1), cfg.size[1] / (ny - 1)
    if min(sx, sy) <= 2.0 * cfg.radius:
        raise ValueError(f"cloth: grid spacing {min(sx, sy):.4f} m must exceed the diameter {2 * cfg.radius:.4f} m")
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    local = np.stack([ix * sx - cfg.size[0] / 2, iy * sy - cfg.size[1] / 2, np.zeros_like(ix, float)], -1).reshape(-1, 3)
    idx = lambda i, j: i * ny + j  # noqa: E731 - vertex id of grid node (i, j)
    tris = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            # Counter-clockwise seen from +z; alternate the diagonal for symmetry.
            if (i + j) % 2 == 0:
                tris += [(a, b, c), (a, c, d)]
            else:
                tris += [(a, b, d), (b, c, d)]
    pts = _place(local, center_xy, yaw, table_z + cfg.radius + 0.0005)
    tex = np.stack([ix / (nx - 1), iy / (ny - 1)], -1).reshape(-1, 2).astype(float)
    corners = {
        "corner_00": pts[idx(0, 0)].copy(),
        "corner_10": pts[idx(nx - 1, 0)].copy(),
        "corner_11": pts[idx(nx - 1, ny - 1)].copy(),
        "corner_01": pts[idx(0, ny - 1)].copy(),
    }
    return ObjectGeometry(
        kind="cloth",
        dim=2,
        points=pts,
        elements=np.asarray(tris, dtype=int),
        texcoords=tex,
        center_xy=center_xy,
        yaw=yaw,
        main_axis=_rot_z(yaw) @ np.array([1.0, 0.0, 0.0]),
        keypoints=corners,
    )


# --------------------------------------------------------------------------- doll

#: Plush figure lying on its back, spine along local +x (head at +x), in metres at scale 1.
#: Each part: (centre xyz, radii xyz).
_DOLL_PARTS = (
    ((0.000, 0.000, 0.000), (0.050, 0.038, 0.030)),  # torso
    ((0.078, 0.000, 0.002), (0.034, 0.034, 0.030)),  # head
    ((-0.060, 0.022, -0.004), (0.034, 0.017, 0.017)),  # right leg
    ((-0.060, -0.022, -0.004), (0.034, 0.017, 0.017)),  # left leg
    ((0.018, 0.052, -0.004), (0.017, 0.030, 0.016)),  # right arm
    ((0.018, -0.052, -0.004), (0.017, 0.030, 0.016)),  # left arm
)


def _doll_sdf(p: np.ndarray, scale: float) -> np.ndarray:
    """Approximate signed distance [N] (metres, < 0 inside) of points [N, 3] to the doll."""
    d = np.full(len(p), np.inf)
    for c, r in _DOLL_PARTS:
        c = np.asarray(c) * scale
        r = np.asarray(r) * scale
        k = np.linalg.norm((p - c) / r, axis=1)
        d = np.minimum(d, (k - 1.0) * r.min())
    return d


def _doll(cfg: ObjectConfig, rng: np.random.Generator, center_xy: np.ndarray, yaw: float, table_z: float) -> ObjectGeometry:
    from scipy.spatial import Delaunay

    h = cfg.spacing
    sc = cfg.scale
    lo = np.min([np.asarray(c) * sc - np.asarray(r) * sc for c, r in _DOLL_PARTS], axis=0)
    hi = np.max([np.asarray(c) * sc + np.asarray(r) * sc for c, r in _DOLL_PARTS], axis=0)
    axes = [np.arange(lo[k] + h / 2, hi[k], h) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inner = grid[_doll_sdf(grid, sc) < -0.35 * h]
    # Surface samples: points on each ellipsoid surface (Fibonacci sphere), kept if on the union's surface.
    surf = []
    for c, r in _DOLL_PARTS:
        c = np.asarray(c) * sc
        r = np.asarray(r) * sc
        area = 4.0 * np.pi * ((r[0] * r[1]) ** 1.6 + (r[0] * r[2]) ** 1.6 + (r[1] * r[2]) ** 1.6) ** (1 / 1.6) / 3 ** (1 / 1.6)
        m = max(12, int(area / (0.8 * h * h)))
        k = np.arange(m) + 0.5
        phi = np.arccos(1 - 2 * k / m)
        th = np.pi * (1 + 5**0.5) * k
        u = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)
        s = c + u * r
        surf.append(s[_doll_sdf(s, sc) > -1e-4])
    surf = np.concatenate(surf)
    # Thin surface samples that are closer than 0.6 h to an already kept one.
    kept: list[np.ndarray] = []
    for p in surf:
        if not kept or np.min(np.linalg.norm(np.asarray(kept) - p, axis=1)) > 0.6 * h:
            kept.append(p)
    local = np.concatenate([inner, np.asarray(kept)])
    tets = Delaunay(local).simplices
    cent = local[tets].mean(axis=1)
    tets = tets[_doll_sdf(cent, sc) < 0.0]
    # Drop slivers: quality 6*sqrt(2)*V / rms(edge)^3 is 1 for a regular tetrahedron.
    a, b, c, d = (local[tets[:, k]] for k in range(4))
    vol = np.abs(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)) / 6.0
    e2 = sum(np.sum((x - y) ** 2, axis=1) for x, y in ((a, b), (a, c), (a, d), (b, c), (b, d), (c, d))) / 6.0
    quality = 6.0 * np.sqrt(2.0) * vol / e2**1.5
    tets = tets[quality > 0.2]
    used = np.unique(tets)
    remap = -np.ones(len(local), dtype=int)
    remap[used] = np.arange(len(used))
    local = local[used]
    tets = remap[tets]
    dz = -local[:, 2].min()
    local[:, 2] += dz
    z0 = table_z + cfg.radius + 0.0005
    pts = _place(local, center_xy, yaw, z0)
    R = _rot_z(yaw)
    head_c = np.asarray(_DOLL_PARTS[1][0]) * sc + np.array([0.0, 0.0, dz])
    torso_c = np.asarray(_DOLL_PARTS[0][0]) * sc + np.array([0.0, 0.0, dz])
    key = {nm: _place(c[None, :], center_xy, yaw, z0)[0] for nm, c in (("head", head_c), ("torso", torso_c))}
    # Texture coordinates give the head another colour: (0.75, 0.25) on the head, (0.25, 0.25) elsewhere
    # (the doll's texture is a 2 x 2 checker: body colour in the lower-left cell, head colour beside it).
    hd = np.linalg.norm((local - head_c) / (np.asarray(_DOLL_PARTS[1][1]) * sc), axis=1)
    tex = np.stack([np.where(hd < 1.05, 0.75, 0.25), np.full(len(local), 0.25)], 1)
    return ObjectGeometry(
        kind="doll",
        dim=3,
        points=pts,
        elements=tets.astype(int),
        texcoords=tex,
        center_xy=center_xy,
        yaw=yaw,
        main_axis=R @ np.array([1.0, 0.0, 0.0]),
        keypoints=key,
    )


_BUILDERS = {"rope": _rope, "cloth": _cloth, "doll": _doll}


def make_object_geometry(
    cfg: ObjectConfig, rng: np.random.Generator, table_z: float, center_xy: Optional[np.ndarray] = None, yaw: Optional[float] = None
) -> ObjectGeometry:
    """Draw a placement (centre in the workspace, yaw) and build the object's rest geometry."""
    if cfg.kind not in _BUILDERS:
        raise ValueError(f"unknown object kind '{cfg.kind}' (known: {', '.join(_BUILDERS)})")
    if center_xy is None:
        center_xy = np.array([rng.uniform(*cfg.workspace_x), rng.uniform(*cfg.workspace_y)])
    if yaw is None:
        yaw = float(rng.uniform(-np.pi, np.pi))
    return _BUILDERS[cfg.kind](cfg, rng, np.asarray(center_xy, float), float(yaw), table_z)


def _fmt(a: np.ndarray) -> str:
    return " ".join(f"{v:.6g}" for v in np.asarray(a).ravel())


def flexcomp_xml(geom: ObjectGeometry, cfg: ObjectConfig, young: float, mass: float, material: Optional[str]) -> str:
    """The ``<flexcomp>`` element (a string for the world MJCF) of the object.

    Contact bits: contype 1, conaffinity 3, so it touches the table (1) and the
    gripper (contype 2). Contacts are stiff (solref 0.005 1) to keep fingers
    from passing through ~1 g vertices.
    """
    attrs = [
        f'name="{OBJECT_FLEX_NAME}"',
        'type="direct"',
        f'dim="{geom.dim}"',
        f'point="{_fmt(geom.points)}"',
        f'element="{_fmt(geom.elements)}"',
        f'radius="{cfg.radius:.6g}"',
        f'mass="{mass:.6g}"',
    ]
    if geom.texcoords is not None and material is not None:
        attrs.append(f'texcoord="{_fmt(geom.texcoords)}"')
        attrs.append(f'material="{material}"')
    else:
        attrs.append(f'rgba="{_fmt(np.asarray(cfg.rgba))}"')
    body = []
    if geom.dim == 1:
        body.append('<edge equality="true"/>')
        body.append(f'<elasticity young="{young:.6g}" poisson="{cfg.poisson:.6g}" damping="{cfg.damping:.6g}"/>')
        selfc = "none"
    elif geom.dim == 2:
        body.append(
            f'<elasticity young="{young:.6g}" poisson="{cfg.poisson:.6g}" damping="{cfg.damping:.6g}" '
            f'thickness="{cfg.thickness:.6g}" elastic2d="both"/>'
        )
        selfc = "auto"
    else:
        body.append(f'<elasticity young="{young:.6g}" poisson="{cfg.poisson:.6g}" damping="{cfg.damping:.6g}"/>')
        selfc = "none"
    body.append(
        f'<contact condim="3" friction="{cfg.friction:.6g} 0.005 0.0001" solref="0.005 1" '
        f'solimp="0.95 0.99 0.001" selfcollide="{selfc}" contype="1" conaffinity="3"/>'
    )
    return f"<flexcomp {' '.join(attrs)}>\n  " + "\n  ".join(body) + "\n</flexcomp>"
