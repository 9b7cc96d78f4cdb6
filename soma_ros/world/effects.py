"""Switchable physical effects of the reference world (all off by default).

=================  ==========================================================
effect             what changes (magnitudes in ``config/world/effects.yaml``)
=================  ==========================================================
``wind``           steady wind: aerodynamic pressure drag of the object's
                   elements against the wind velocity ``w``
``air_drag``       the same drag in still air (``w = 0``) with an
                   exaggerated air density
``table_friction`` the table's sliding friction is lowered
``slip``           while carrying, most held vertices let go and the rest are
                   held softly
``stiff``          Young's modulus x ``young_scale``
``heavy``          object mass x ``mass_scale``
=================  ==========================================================

Drag (:class:`AeroModel`) uses the flow velocity relative to each element,
``u = w - v_element``, and only its component that pushes on the element:

* rope edges (capsules of diameter ``2 r``, length ``L``):
  ``F = 1/2 rho Cd (2 r L) |u_perp| u_perp`` with ``u_perp`` normal to the edge;
* cloth triangles (area ``A``, normal ``n``): ``F = 1/2 rho Cd A |u.n| (u.n) n``,
  so a cloth lying flat in a horizontal wind feels nothing;
* doll surface triangles (outward normal ``n``), windward side only:
  ``F = -1/2 rho Cd A max(0, -u.n)^2 n``.

Each element's force is shared equally by its vertices and applied through
the vertex slide dofs (``qfrc_applied``), so only the object feels it and the
robot's commanded trajectory never changes. Effects act from the first
recorded frame; the settling before it sees only the material effects.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .config import EFFECTS, EffectsConfig, ObjectConfig, TableConfig
from .scene import Scene

__all__ = ["ActiveEffects", "AeroModel", "parse_effects", "surface_triangles"]


def parse_effects(spec: str | list[str] | None) -> list[str]:
    """``"wind,slip"`` (or a list) -> validated, de-duplicated, ordered effect names."""
    if spec is None:
        return []
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    names = [s.strip() for s in items if s and s.strip() and s.strip() != "none"]
    for n in names:
        if n not in EFFECTS:
            raise ValueError(f"unknown effect '{n}' (known: {', '.join(EFFECTS)})")
    return [e for e in EFFECTS if e in names]


def surface_triangles(tets: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Boundary faces [F, 3] of a tetrahedral mesh, ordered so their normals point outwards."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    opposite = np.concatenate([tets[:, 0], tets[:, 1], tets[:, 2], tets[:, 3]])
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = counts[inv.ravel()] == 1
    f, o = faces[boundary], opposite[boundary]
    a, b, c = points[f[:, 0]], points[f[:, 1]], points[f[:, 2]]
    n = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", n, points[o] - a) > 0
    f[inward] = f[inward][:, [0, 2, 1]]
    return f


class AeroModel:
    """Per-element pressure drag of the object (see the module docstring). Forces are [N, 3] per vertex."""

    def __init__(self, dim: int, elements: np.ndarray, rest_points: np.ndarray, radius: float) -> None:
        self.dim = dim
        self.radius = radius
        if dim == 1:
            self.elems = np.asarray(elements, int)
        elif dim == 2:
            self.elems = np.asarray(elements, int)
        elif dim == 3:
            self.elems = surface_triangles(np.asarray(elements, int), rest_points)
        else:
            raise ValueError(f"no drag model for dim {dim}")
        self.n_vert = len(rest_points)

    def forces(self, pos: np.ndarray, vel: np.ndarray, wind: np.ndarray, rho_cd: float) -> np.ndarray:
        """Vertex forces [N, 3] for vertex positions/velocities [N, 3], wind [3], rho * Cd."""
        e = self.elems
        k = e.shape[1]
        u = wind[None, :] - vel[e].mean(axis=1)  # flow relative to each element
        if self.dim == 1:
            t = pos[e[:, 1]] - pos[e[:, 0]]
            length = np.linalg.norm(t, axis=1, keepdims=True)
            t = t / np.maximum(length, 1e-12)
            u_perp = u - np.sum(u * t, axis=1, keepdims=True) * t
            f = 0.5 * rho_cd * (2.0 * self.radius * length) * np.linalg.norm(u_perp, axis=1, keepdims=True) * u_perp
        else:
            a, b, c = pos[e[:, 0]], pos[e[:, 1]], pos[e[:, 2]]
            cr = np.cross(b - a, c - a)
            area2 = np.linalg.norm(cr, axis=1, keepdims=True)
            n = cr / np.maximum(area2, 1e-15)
            un = np.sum(u * n, axis=1, keepdims=True)
            if self.dim == 2:
                f = 0.5 * rho_cd * (0.5 * area2) * np.abs(un) * un * n
            else:
                f = -0.5 * rho_cd * (0.5 * area2) * np.minimum(un, 0.0) ** 2 * n
        out = np.zeros((self.n_vert, 3))
        for j in range(k):
            np.add.at(out, e[:, j], f / k)
        return out


@dataclass
class ActiveEffects:
    names: list[str]
    cfg: EffectsConfig
    slipped: bool = False
    log: dict = field(default_factory=dict)
    _aero: Optional[AeroModel] = None

    def __post_init__(self) -> None:
        self.names = parse_effects(self.names)

    def __contains__(self, name: str) -> bool:
        return name in self.names

    # ---------------------------------------------------------------- model-time parameters
    def young(self, obj: ObjectConfig) -> float:
        return obj.young * (self.cfg.stiff.young_scale if "stiff" in self else 1.0)

    def mass(self, obj: ObjectConfig) -> float:
        return obj.mass * (self.cfg.heavy.mass_scale if "heavy" in self else 1.0)

    def table_friction(self, table: TableConfig) -> float:
        return self.cfg.table_friction.friction if "table_friction" in self else table.friction

    def magnitudes(self) -> dict[str, dict]:
        return self.cfg.magnitudes(self.names)

    # ---------------------------------------------------------------- per-step forces
    def wind_blows(self, step: int, carry: tuple[int, int]) -> bool:
        """Whether the wind blows at ``step`` (its ``onset``: a fraction of the carrying steps ``carry``)."""
        if "wind" not in self:
            return False
        onset = self.cfg.wind.onset
        if onset is None:
            return True
        c0, c1 = carry
        return step >= c0 + int(round(float(onset) * (c1 - c0)))

    def apply_forces(self, scene: Scene, step: int, carry: tuple[int, int]) -> None:
        """Set the object's external forces for the next step (call before every mj_step)."""
        wind = self.wind_blows(step, carry)
        if not wind and "air_drag" not in self:
            if "wind" in self:  # before the wind's onset: no force on the object
                self.clear_forces(scene)
            return
        if self._aero is None:
            g = scene.geometry
            self._aero = AeroModel(g.dim, g.elements, g.points, scene.obj_cfg.radius)
        pos = scene.vertex_positions()
        vel = scene.vertex_velocities()
        force = np.zeros_like(vel)
        if wind:
            w = self.cfg.wind
            force += self._aero.forces(pos, vel, np.asarray(w.velocity, float), w.air_density * w.drag_coefficient)
        if "air_drag" in self:
            a = self.cfg.air_drag
            force += self._aero.forces(pos, vel, np.zeros(3), a.density * a.drag_coefficient)
        scene.data.qfrc_applied[scene.vert_dadr.ravel()] = force.ravel()

    def clear_forces(self, scene: Scene) -> None:
        scene.data.qfrc_applied[scene.vert_dadr.ravel()] = 0.0

    # ---------------------------------------------------------------- grasp slip
    def maybe_slip(self, scene: Scene, step: int, carry: tuple[int, int], held: list[int]) -> list[int]:
        """At the slip onset, release most held vertices; returns the vertices still held."""
        if "slip" not in self or self.slipped or not held:
            return held
        c0, c1 = carry
        onset = c0 + int(round(self.cfg.slip.onset * (c1 - c0)))
        if step < onset:
            return held
        m, d = scene.model, scene.data
        keep_n = max(1, int(round(self.cfg.slip.keep_fraction * len(held))))
        # Keep the vertices nearest the TCP: the grip loosens from its edges.
        hand_p = d.xpos[scene.hand_body]
        hand_R = d.xmat[scene.hand_body].reshape(3, 3)
        tcp = hand_p + hand_R @ np.asarray(scene.robot.tcp_offset)
        pos = scene.vertex_positions()
        order = sorted(held, key=lambda i: float(np.linalg.norm(pos[i] - tcp)))
        kept, dropped = order[:keep_n], order[keep_n:]
        for i in dropped:
            d.eq_active[scene.grasp_eq[i]] = 0
        for i in kept:
            m.eq_solref[scene.grasp_eq[i]] = self.cfg.slip.solref
        self.slipped = True
        self.log["slip"] = {"time_step": int(step), "kept_vertices": [int(i) for i in kept], "released_vertices": [int(i) for i in dropped]}
        return kept

