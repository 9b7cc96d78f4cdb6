"""The robot's URDF geometry as triangle meshes, and a z-buffer rasterizer for it.

Used to find the robot's pixels in a camera without any learned model: the
link meshes (``<visual>`` or ``<collision>``; meshes, boxes, cylinders and
spheres) are posed by FK and rasterized into a depth image with the camera's
own intrinsics, then compared with the measured depth
(:func:`robot_pixels`).

The rasterizer is plain vectorised numpy: every triangle's pixel bounding box is
enumerated, pixel centres (pixel (col, row) has its centre at (col, row): the
convention of sensor_msgs/CameraInfo and OpenCV) are tested against the three edge
functions, depth is interpolated perspective-correctly (1/z linear in the image)
and the nearest surface wins (``np.minimum.at``). Triangles with a vertex
closer than ``near`` are dropped (no clipping). No OpenGL context is needed, so
it runs the same on a headless training machine.

Shapes: a mesh is (V [N, 3] float64 in the link frame, F [M, 3] int64); poses are
[4, 4] float64; a rendered depth image is [H, W] float64 metres, ``inf`` where
the robot is not.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Mapping, Optional, Union

import numpy as np

__all__ = ["load_link_meshes", "render_depth", "robot_pixels", "resolve_mesh_file"]

Mesh = tuple[np.ndarray, np.ndarray]


def _origin(el: Optional[ET.Element]) -> np.ndarray:
    T = np.eye(4)
    if el is None:
        return T
    xyz = [float(v) for v in (el.get("xyz") or "0 0 0").split()]
    r, p, y = [float(v) for v in (el.get("rpy") or "0 0 0").split()]
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T[:3, :3] = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                          [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                          [-sp, cp * sr, cp * cr]])
    T[:3, 3] = xyz
    return T


def resolve_mesh_file(filename: str, urdf_dir: Path) -> Path:
    """A URDF mesh reference (``package://pkg/rel``, ``file://``, relative or absolute) as a file:
    ``package://`` paths are looked up below the URDF's folder and its ancestors."""
    if filename.startswith("file://"):
        cands = [Path(filename[len("file://"):])]
    elif filename.startswith("package://"):
        rel = Path(filename[len("package://"):])
        tails = [rel] + ([Path(*rel.parts[1:])] if len(rel.parts) > 1 else [])
        cands = [anc / t for anc in [urdf_dir, *urdf_dir.parents] for t in tails]
    else:
        p = Path(filename)
        cands = [p if p.is_absolute() else urdf_dir / p]
    for c in cands:
        if c.is_file():
            return c
    raise FileNotFoundError(f"URDF mesh not found: {filename} (searched from {urdf_dir})")


def _geometry_mesh(geom: ET.Element, urdf_dir: Path, src: str) -> Optional[Mesh]:
    import trimesh

    child = next(iter(geom), None)
    if child is None:
        return None
    if child.tag == "mesh":
        path = resolve_mesh_file(child.get("filename", ""), urdf_dir)
        try:
            m = trimesh.load(str(path), force="mesh", process=False)
        except Exception as exc:  # trimesh raises assorted types for unreadable files
            raise ValueError(f"{src}: mesh {path.name} could not be read ({type(exc).__name__})") from None
        V = np.asarray(m.vertices, dtype=np.float64)
        scale = child.get("scale")
        if scale:
            V = V * np.array([float(v) for v in scale.split()])
        return V, np.asarray(m.faces, dtype=np.int64)
    if child.tag == "box":
        m = trimesh.creation.box(extents=[float(v) for v in child.get("size", "0 0 0").split()])
    elif child.tag == "cylinder":
        m = trimesh.creation.cylinder(radius=float(child.get("radius", 0)), height=float(child.get("length", 0)),
                                      sections=24)
    elif child.tag == "sphere":
        m = trimesh.creation.icosphere(subdivisions=2, radius=float(child.get("radius", 0)))
    else:
        return None
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def load_link_meshes(urdf: Union[str, Path], kind: str = "collision") -> dict[str, Mesh]:
    """{link: (V [N, 3] in the link frame, F [M, 3])} of the URDF's ``kind`` ("visual" or "collision")
    geometry, every element of a link merged. Links without such geometry are left out."""
    if kind not in ("visual", "collision"):
        raise ValueError(f"robot mesh kind must be 'visual' or 'collision', got {kind!r}")
    urdf = Path(urdf)
    try:
        root = ET.parse(urdf).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ValueError(f"{urdf}: cannot read the URDF ({exc})") from None
    out: dict[str, Mesh] = {}
    for link in root.findall("link"):
        Vs, Fs, n = [], [], 0
        for el in link.findall(kind):
            geom = el.find("geometry")
            if geom is None:
                continue
            mesh = _geometry_mesh(geom, urdf.parent, urdf.name)
            if mesh is None:
                continue
            T = _origin(el.find("origin"))
            V = mesh[0] @ T[:3, :3].T + T[:3, 3]
            Vs.append(V)
            Fs.append(mesh[1] + n)
            n += len(V)
        if Vs:
            out[link.get("name")] = (np.concatenate(Vs), np.concatenate(Fs))
    return out


def render_depth(meshes: Mapping[str, Mesh], link_to_world: Mapping[str, np.ndarray], K: np.ndarray,
                 cam_to_world: np.ndarray, width: int, height: int, near: float = 0.01,
                 chunk: int = 2_000_000) -> np.ndarray:
    """Depth [H, W] (metres along the optical axis, ``inf`` = no robot) of the meshes posed by
    ``link_to_world`` [4, 4] each, seen by a pinhole camera K [3, 3] at ``cam_to_world`` [4, 4]
    (OpenCV optical frame). Links missing from ``link_to_world`` are skipped."""
    assert K.shape == (3, 3) and cam_to_world.shape == (4, 4), (K.shape, cam_to_world.shape)
    world_to_cam = np.linalg.inv(cam_to_world)
    tris = []
    for link, (V, F) in meshes.items():
        if link not in link_to_world:
            continue
        M = world_to_cam @ link_to_world[link]
        tris.append((V @ M[:3, :3].T + M[:3, 3])[F])  # [M, 3, 3] camera frame
    zbuf = np.full(height * width, np.inf)
    if not tris:
        return zbuf.reshape(height, width)
    P = np.concatenate(tris)
    P = P[(P[:, :, 2] > near).all(axis=1)]
    z = P[:, :, 2]
    u = K[0, 0] * P[:, :, 0] / z + K[0, 2]  # pixel index coordinates (centre of pixel i at i)
    v = K[1, 1] * P[:, :, 1] / z + K[1, 2]
    x0 = np.clip(np.ceil(u.min(1)), 0, width).astype(np.int64)
    x1 = np.clip(np.floor(u.max(1)), -1, width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(v.min(1)), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(v.max(1)), -1, height - 1).astype(np.int64)
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    keep = (nx > 0) & (ny > 0)
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    keep &= np.abs(area) > 1e-12
    idx = np.nonzero(keep)[0]
    counts = (nx * ny)[idx]
    # chunks of triangles bounded by the number of pixel candidates
    cum = np.cumsum(counts)
    start = 0
    while start < len(idx):
        stop = max(int(np.searchsorted(cum, cum[start] - counts[start] + chunk, side="right")), start + 1)
        sel = idx[start:stop]
        start = stop
        c = (nx * ny)[sel]
        tri = np.repeat(np.arange(len(sel)), c)
        off = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        px = x0[sel][tri] + off % nx[sel][tri]
        py = y0[sel][tri] + off // nx[sel][tri]
        uu, vv, zz, aa = u[sel][tri], v[sel][tri], z[sel][tri], area[sel][tri]
        w0 = ((uu[:, 1] - px) * (vv[:, 2] - py) - (uu[:, 2] - px) * (vv[:, 1] - py)) / aa
        w1 = ((uu[:, 2] - px) * (vv[:, 0] - py) - (uu[:, 0] - px) * (vv[:, 2] - py)) / aa
        w2 = 1.0 - w0 - w1
        inv_z = w0 / zz[:, 0] + w1 / zz[:, 1] + w2 / zz[:, 2]
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0) & (inv_z > 0)
        np.minimum.at(zbuf, (py * width + px)[inside], 1.0 / inv_z[inside])
    return zbuf.reshape(height, width)


def robot_pixels(rendered: np.ndarray, measured: np.ndarray, tolerance: float = 0.02) -> np.ndarray:
    """Robot pixels [H, W] bool: the robot renders there and the measured depth [H, W] (0 = invalid)
    does not see anything nearer than the rendered surface minus ``tolerance`` (m)."""
    assert rendered.shape == measured.shape, (rendered.shape, measured.shape)
    hit = np.isfinite(rendered)
    return hit & ((measured <= 0) | (measured >= rendered - tolerance))
