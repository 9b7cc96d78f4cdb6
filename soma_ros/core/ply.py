"""Splat file I/O: standard 3DGS ``.ply`` and the 32-byte ``.splat`` layout.

``.ply`` (what the reference 3DGS trainer and most tools write)
--------------------------------------------------------------
One ``vertex`` element, ``format binary_little_endian 1.0``, float32 properties::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3K-1}
    opacity  scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

* ``f_rest_*`` are channel-major: ``f_rest[c * K + k]`` is band coefficient k
  of colour channel c (3DGS writes ``features_rest.transpose(1, 2).flatten``),
  so ``sh_rest [N, K, 3] = f_rest.reshape(N, 3, K).transpose(1, 2)``.
* ``opacity`` is the logit of the [0, 1] opacity, ``scale_*`` the natural log
  of the standard deviations, ``rot_*`` a (w, x, y, z) quaternion (normalised
  on read), ``nx ny nz`` are unused (written as 0).
* soma extras that round-trip: ``mass`` (kg) and ``attr_0 .. attr_{A-1}``.

:func:`read_ply` also accepts ``binary_big_endian`` and ``ascii`` files, any
numeric property types, and plain point clouds (``x y z`` with optional
``red green blue``) which become isotropic splats
(:meth:`Splats.from_points`). Errors name the missing properties.

``.splat`` (antimatter15 web-viewer layout), 32 bytes per splat, little endian::

    float32 x, y, z | float32 scale_0..2 (linear std devs) |
    uint8 r, g, b, a (colour and opacity * 255) |
    uint8 rot w, x, y, z encoded as clip(q * 128 + 128, 0, 255)

Only SH degree 0 survives ``.splat``; mass and attrs are not stored.

Reading and writing go through ``plyfile``. Before any vertex data is read,
the header is parsed here with bounds (at most 64 KiB, a vertex count within
``max_splats`` when given) and checked against the file's length: a binary
file must hold exactly the bytes its header announces, an ASCII file at least
two bytes per announced value. So a 400-byte file that claims 10^8 vertices is
refused at once, before anything is allocated. Written headers follow the
graphdeco layout that the SIBR viewer expects (``format`` on line 2, ``element
vertex N`` on line 3, no comments), at SH degree 0 to 3.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import BinaryIO, Optional, Union

import numpy as np
import plyfile
import torch

from .splats import SH_C0, Splats, rgb_to_sh_dc

__all__ = ["read_ply", "write_ply", "read_splat", "write_splat", "load_splats", "PlyError", "PlyHeader",
           "read_ply_header", "sh_degree_of", "MAX_HEADER_BYTES"]

PathLike = Union[str, os.PathLike]

_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}

_GS_REQUIRED = (
    ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
_GS_MARKERS = ("f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
               "rot_0", "rot_1", "rot_2", "rot_3")


class PlyError(ValueError):
    """A .ply / .splat file that cannot be read as splats (message names the problem)."""


# ------------------------------------------------------------------ PLY parsing
MAX_HEADER_BYTES = 65536
_FLOAT_TYPES = ("f4", "f8")


class PlyHeader:
    """A parsed, bounded PLY header: format, elements [(name, count, [(prop, dtype | ('list', ct, it))])],
    the header's byte length and the file's total size."""

    def __init__(self, fmt: str, elements: list, header_bytes: int, file_bytes: int) -> None:
        self.format = fmt
        self.elements = elements
        self.header_bytes = header_bytes
        self.file_bytes = file_bytes

    def element(self, name: str):
        for e in self.elements:
            if e[0] == name:
                return e
        return None

    @property
    def vertex_count(self) -> int:
        e = self.element("vertex")
        return 0 if e is None else e[1]

    def property_types(self, name: str = "vertex") -> dict[str, object]:
        e = self.element(name)
        return {} if e is None else dict(e[2])


def _parse_header(f: BinaryIO, path) -> PlyHeader:
    """Parse the header of the open file ``f`` (positioned at 0) without reading past it."""
    head = f.read(MAX_HEADER_BYTES)
    if not head.startswith(b"ply\n") and not head.startswith(b"ply\r\n"):
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic line)")
    end = head.find(b"end_header")
    if end < 0:
        raise PlyError(f"{path}: PLY header has no end_header within {MAX_HEADER_BYTES} bytes")
    nl = head.find(b"\n", end)
    if nl < 0:
        raise PlyError(f"{path}: PLY header has no end_header line")
    header_bytes = nl + 1
    fmt = None
    elements: list = []
    for no, raw in enumerate(head[:header_bytes].split(b"\n")[1:], start=2):
        tok = raw.decode("ascii", errors="replace").strip().split()
        if not tok:
            continue
        key = tok[0]
        if key == "format":
            if len(tok) < 2 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise PlyError(f"{path}: unsupported PLY format on header line {no}")
            fmt = tok[1]
        elif key in ("comment", "obj_info"):
            continue
        elif key == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise PlyError(f"{path}: bad element line (header line {no})")
            elements.append((tok[1], int(tok[2]), []))
        elif key == "property":
            if not elements:
                raise PlyError(f"{path}: property before any element (header line {no})")
            if len(tok) >= 2 and tok[1] == "list":
                if len(tok) != 5 or tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
                    raise PlyError(f"{path}: bad list property (header line {no})")
                elements[-1][2].append((tok[4], ("list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]])))
            else:
                if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                    raise PlyError(f"{path}: unknown property type (header line {no})")
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        elif key == "end_header":
            break
        else:
            raise PlyError(f"{path}: unexpected PLY header line {no}")
    if fmt is None:
        raise PlyError(f"{path}: PLY header has no format line")
    for name, _, props in elements:
        names = [q[0] for q in props]
        if len(set(names)) != len(names):
            raise PlyError(f"{path}: element '{name}' declares a property twice")
    return PlyHeader(fmt, elements, header_bytes, os.fstat(f.fileno()).st_size)


def _check_sizes(h: PlyHeader, path, max_splats: Optional[int]) -> None:
    """The header's counts against the limit and against the bytes the file really holds."""
    if h.element("vertex") is None:
        raise PlyError(f"{path}: PLY has no 'vertex' element (elements: {[e[0] for e in h.elements]})")
    n = h.vertex_count
    if max_splats is not None and n > max_splats:
        raise PlyError(f"{path}: header announces {n} vertices, more than the limit of {max_splats}")
    body = h.file_bytes - h.header_bytes
    if h.format == "ascii":
        values = sum(count * max(1, len(props)) for _, count, props in h.elements)
        if 2 * values > body:
            raise PlyError(f"{path}: truncated PLY: the header announces {values} ASCII values, the file holds "
                           f"{body} bytes after the header (at least {2 * values} needed)")
        return
    need, exact = 0, True
    for _, count, props in h.elements:
        fixed = sum(np.dtype(t).itemsize for _, t in props if not isinstance(t, tuple))
        lists = [t for _, t in props if isinstance(t, tuple)]
        need += count * (fixed + sum(np.dtype(t[1]).itemsize for t in lists))  # lists: their length bytes at least
        exact = exact and not lists
    if body < need or (exact and body != need):
        raise PlyError(f"{path}: truncated PLY: the header announces {need} bytes of data, the file holds {body}"
                       if body < need else
                       f"{path}: PLY length does not match its header: {need} bytes of data announced, {body} present")


def read_ply_header(path: PathLike, max_splats: Optional[int] = None) -> PlyHeader:
    """The checked header of a PLY file (counts against ``max_splats`` and the file length)."""
    with open(path, "rb") as f:
        h = _parse_header(f, path)
    _check_sizes(h, path, max_splats)
    return h


def _read_vertex_table(path: PathLike, max_splats: Optional[int] = None,
                       file: Optional[BinaryIO] = None) -> tuple[dict[str, np.ndarray], PlyHeader]:
    """Read the ``vertex`` element of a PLY file into {property name: [N] array} (and its header)."""
    f = file if file is not None else open(path, "rb")
    try:
        f.seek(0)
        h = _parse_header(f, path)
        _check_sizes(h, path, max_splats)
        _, _, props = h.element("vertex")
        if any(isinstance(t, tuple) for _, t in props):
            raise PlyError(f"{path}: list properties in 'vertex' are not supported")
        f.seek(0)
        try:
            ply = plyfile.PlyData.read(f, mmap=False)
        except (plyfile.PlyParseError, plyfile.PlyHeaderParseError, ValueError, EOFError) as exc:
            raise PlyError(f"{path}: unreadable PLY data ({type(exc).__name__})") from None
        data = ply["vertex"].data
        return {q: np.asarray(data[q]).astype(np.dtype(data.dtype[q]).newbyteorder("=")) for q in data.dtype.names}, h
    finally:
        if file is None:
            f.close()


def _indexed(props: dict, prefix: str) -> list[str]:
    pat = re.compile(re.escape(prefix) + r"(\d+)$")
    found = sorted(((int(m.group(1)), k) for k in props for m in [pat.match(k)] if m))
    idx = [i for i, _ in found]
    if idx != list(range(len(idx))):
        raise PlyError(f"'{prefix}*' properties are not numbered 0..{len(idx) - 1}: {idx}")
    return [k for _, k in found]


def _estimate_point_scale(xyz: np.ndarray) -> float:
    """Median nearest-neighbour distance of a point cloud (isotropic splat size)."""
    if xyz.shape[0] < 2:
        return 0.005
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xyz).query(xyz, k=2)
    med = float(np.median(d[:, 1]))
    return med if med > 0 else 0.005


def read_ply(
    path: PathLike,
    dtype: torch.dtype = torch.float32,
    point_scale: Optional[float] = None,
    point_opacity: float = 0.9,
    max_splats: Optional[int] = None,
    file: Optional[BinaryIO] = None,
) -> Splats:
    """Read a 3DGS ``.ply`` (or a plain point-cloud ``.ply``) into :class:`Splats`.

    Point clouds (``x y z`` [``red green blue``], no 3DGS properties) become
    isotropic splats of std ``point_scale`` (default: the median nearest-neighbour
    distance) and opacity ``point_opacity``; uchar colours are divided by 255,
    ushort by 65535, float colours are taken as [0, 1].

    ``max_splats``: refuse a header that announces more vertices (before reading them).
    ``file``: an already opened binary file to read instead of opening ``path`` (which then
    only names the file in messages). 3DGS properties must be float or double.
    """
    props, header = _read_vertex_table(path, max_splats, file)
    missing_xyz = [k for k in ("x", "y", "z") if k not in props]
    if missing_xyz:
        raise PlyError(f"{path}: PLY vertex element lacks properties {missing_xyz}")
    xyz = np.stack([props["x"], props["y"], props["z"]], axis=1).astype(np.float64)
    n = xyz.shape[0]

    def T(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

    is_gs = any(k in props for k in _GS_MARKERS)
    if not is_gs:
        if any(k in props for k in ("red", "green", "blue")):
            miss = [k for k in ("red", "green", "blue") if k not in props]
            if miss:
                raise PlyError(f"{path}: point-cloud PLY colour lacks properties {miss}")
            cols = []
            for k in ("red", "green", "blue"):
                a = props[k]
                if a.dtype == np.uint8:
                    cols.append(a / 255.0)
                elif a.dtype == np.uint16:
                    cols.append(a / 65535.0)
                elif np.issubdtype(a.dtype, np.floating):
                    cols.append(a.astype(np.float64))
                else:
                    cols.append(a / 255.0)
            rgb = np.clip(np.stack(cols, axis=1), 0.0, 1.0)
        else:
            rgb = np.full((n, 3), 0.5)
        scale = point_scale if point_scale is not None else _estimate_point_scale(xyz)
        sp = Splats.from_points(T(xyz), T(rgb), scale=scale, opacity=point_opacity)
        if "mass" in props:
            sp.mass = T(props["mass"])
        return sp

    missing = [k for k in _GS_REQUIRED if k not in props]
    if missing:
        raise PlyError(f"{path}: 3DGS PLY lacks required properties {missing}")
    types = header.property_types()
    not_float = [k for k, t in types.items() if (k in _GS_REQUIRED or k.startswith("f_rest_")) and t not in _FLOAT_TYPES]
    if not_float:
        raise PlyError(f"{path}: 3DGS properties must be float or double, not integers: {not_float[:6]}")
    rest_names = _indexed(props, "f_rest_")
    if len(rest_names) % 3:
        raise PlyError(f"{path}: number of f_rest_* properties ({len(rest_names)}) is not a multiple of 3")
    k_rest = len(rest_names) // 3
    if rest_names:
        f_rest = np.stack([props[k] for k in rest_names], axis=1).astype(np.float64)
        sh_rest = f_rest.reshape(n, 3, k_rest).transpose(0, 2, 1)
    else:
        sh_rest = np.zeros((n, 0, 3))
    sh_dc = np.stack([props[f"f_dc_{i}"] for i in range(3)], axis=1)
    logit = props["opacity"].astype(np.float64)
    opac = 1.0 / (1.0 + np.exp(-logit))
    scales = np.exp(np.stack([props[f"scale_{i}"] for i in range(3)], axis=1).astype(np.float64))
    q = np.stack([props[f"rot_{i}"] for i in range(4)], axis=1).astype(np.float64)
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    bad = qn[:, 0] < 1e-12
    # Rows that are already unit length (to float32 precision) are kept verbatim, so that
    # a file read and written again is byte-identical; the others are normalised.
    unit = np.abs(qn - 1.0) < 1e-6
    q = np.where(bad[:, None], np.array([1.0, 0.0, 0.0, 0.0]), np.where(unit, q, q / np.where(qn > 0, qn, 1.0)))
    mass = T(props["mass"]) if "mass" in props else None
    attr_names = _indexed(props, "attr_")
    attrs = T(np.stack([props[k] for k in attr_names], axis=1)) if attr_names else None
    return Splats(
        means=T(xyz),
        quats=T(q),
        scales=T(scales),
        opacities=T(opac),
        sh_dc=T(sh_dc),
        sh_rest=T(sh_rest),
        mass=mass,
        attrs=attrs,
    )


def sh_degree_of(k_rest: int) -> int:
    """The SH degree whose higher bands have ``k_rest`` coefficients per channel (0, 3, 8, 15 -> 0..3)."""
    for d in range(4):
        if (d + 1) ** 2 - 1 == k_rest:
            return d
    raise ValueError(f"{k_rest} higher SH coefficients per channel is no SH degree 0-3 (expected 0, 3, 8 or 15)")


def write_ply(path: PathLike, splats: Splats, extras: bool = True, sh_degree: Optional[int] = None) -> None:
    """Write :class:`Splats` as a binary little-endian 3DGS ``.ply`` (float32), graphdeco layout.

    ``extras``: also write ``mass`` and ``attr_*`` after the 3DGS properties (``plyfile``-based
    loaders such as graphdeco's ignore them; the SIBR viewer's fixed-record reader needs
    ``extras=False``). ``sh_degree`` (0-3, default: the splats' own): the higher bands are
    zero-padded up to it, or cut down to it. Opacities are clamped to [1e-7, 1 - 1e-7] before
    the logit (finite values). The header has no comment (SIBR reads the count on line 3).
    """
    n = len(splats)
    sp = splats.detach().to("cpu")

    def np64(t):
        return t.detach().cpu().to(torch.float64).numpy()

    rest3 = np64(sp.sh_rest)  # [N, K, 3]
    own = sh_degree_of(rest3.shape[1])
    degree = own if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= 3:
        raise ValueError(f"write_ply: sh_degree must be 0..3, got {sh_degree}")
    k_rest = (degree + 1) ** 2 - 1
    if k_rest > rest3.shape[1]:
        rest3 = np.concatenate([rest3, np.zeros((n, k_rest - rest3.shape[1], 3))], axis=1)
    rest3 = rest3[:, :k_rest]
    cols: list[tuple[str, np.ndarray]] = []
    xyz = np64(sp.means)
    for i, k in enumerate("xyz"):
        cols.append((k, xyz[:, i]))
    for k in ("nx", "ny", "nz"):
        cols.append((k, np.zeros(n)))
    dc = np64(sp.sh_dc)
    for i in range(3):
        cols.append((f"f_dc_{i}", dc[:, i]))
    rest = rest3.transpose(0, 2, 1).reshape(n, 3 * k_rest)  # channel-major
    for i in range(3 * k_rest):
        cols.append((f"f_rest_{i}", rest[:, i]))
    o = np.clip(np64(sp.opacities), 1e-7, 1.0 - 1e-7)
    cols.append(("opacity", np.log(o) - np.log1p(-o)))
    sc = np64(sp.scales)
    if (sc <= 0).any():
        raise ValueError("write_ply: Splats.scales must be > 0 (stored as log)")
    for i in range(3):
        cols.append((f"scale_{i}", np.log(sc[:, i])))
    q = np64(sp.quats)
    for i in range(4):
        cols.append((f"rot_{i}", q[:, i]))
    if extras:
        cols.append(("mass", np64(sp.mass)))
        at = np64(sp.attrs)
        for i in range(at.shape[1]):
            cols.append((f"attr_{i}", at[:, i]))
    arr = np.empty(n, dtype=np.dtype([(name, "<f4") for name, _ in cols]))
    for name, v in cols:
        arr[name] = v.astype(np.float32)
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))


# ------------------------------------------------------------------ .splat
_SPLAT_DTYPE = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert _SPLAT_DTYPE.itemsize == 32


def read_splat(path: PathLike, dtype: torch.dtype = torch.float32, max_splats: Optional[int] = None,
               file: Optional[BinaryIO] = None) -> Splats:
    """Read a 32-byte-per-splat ``.splat`` file (layout in the module docstring).

    The size is checked before reading: a multiple of 32 bytes, at most ``max_splats`` records.
    ``file``: an open binary file to read instead of opening ``path``."""
    path = Path(path)
    f = file if file is not None else open(path, "rb")
    try:
        size = os.fstat(f.fileno()).st_size
        if size % 32:
            raise PlyError(f"{path}: .splat size {size} is not a multiple of 32 bytes")
        if max_splats is not None and size // 32 > max_splats:
            raise PlyError(f"{path}: holds {size // 32} splats, more than the limit of {max_splats}")
        f.seek(0)
        raw = f.read(size)
    finally:
        if file is None:
            f.close()
    if len(raw) != size:
        raise PlyError(f"{path}: .splat changed while it was read")
    arr = np.frombuffer(raw, dtype=_SPLAT_DTYPE)
    rgba = arr["rgba"].astype(np.float64) / 255.0
    q = (arr["rot"].astype(np.float64) - 128.0) / 128.0
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    bad = qn[:, 0] < 1e-12
    q = np.where(bad[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q / np.where(qn > 0, qn, 1.0))

    def T(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

    return Splats(
        means=T(arr["pos"].astype(np.float64)),
        quats=T(q),
        scales=T(arr["scale"].astype(np.float64)),
        opacities=T(rgba[:, 3]),
        sh_dc=rgb_to_sh_dc(T(rgba[:, :3])),
    )


def write_splat(path: PathLike, splats: Splats) -> None:
    """Write :class:`Splats` as a ``.splat`` file (SH degree 0, 8-bit colour/rotation)."""
    sp = splats.detach().to("cpu")
    n = len(sp)
    arr = np.empty(n, dtype=_SPLAT_DTYPE)
    arr["pos"] = sp.means.to(torch.float32).numpy()
    arr["scale"] = sp.scales.to(torch.float32).numpy()
    rgb = np.clip(0.5 + SH_C0 * sp.sh_dc.to(torch.float64).numpy(), 0.0, 1.0)
    a = np.clip(sp.opacities.to(torch.float64).numpy(), 0.0, 1.0)
    arr["rgba"] = np.round(np.concatenate([rgb, a[:, None]], axis=1) * 255.0).astype(np.uint8)
    q = sp.quats.to(torch.float64).numpy()
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    q = q / np.where(qn > 0, qn, 1.0)
    arr["rot"] = np.clip(np.round(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    Path(path).write_bytes(arr.tobytes())


def load_splats(path: PathLike, dtype: torch.dtype = torch.float32, max_splats: Optional[int] = None,
                file: Optional[BinaryIO] = None) -> Splats:
    """Load ``.ply`` or ``.splat`` by extension (``max_splats`` and ``file`` as for :func:`read_ply`)."""
    p = Path(path)
    if file is None and not p.exists():
        raise FileNotFoundError(f"splat file not found: {p}")
    ext = p.suffix.lower()
    if ext == ".ply":
        return read_ply(p, dtype=dtype, max_splats=max_splats, file=file)
    if ext == ".splat":
        return read_splat(p, dtype=dtype, max_splats=max_splats, file=file)
    raise PlyError(f"{p}: unknown splat file extension {ext!r} (expected .ply or .splat)")
