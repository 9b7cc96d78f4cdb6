"""What effect terms ask of a physics prior: :class:`PhysicsMods`.

An effect that has a physical handle inside the prior (:mod:`.physics`) returns a
``PhysicsMods`` from ``physics_modifier``; the effect set sums them and the prior
applies the sum. Kept apart from both so that neither imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

__all__ = ["PhysicsMods"]


@dataclass
class PhysicsMods:
    """Changes of the physics prior asked by other effect terms (all zero = nominal). Tensors
    are 0-d (scalars) or [3]; None = absent."""

    accel: Optional[torch.Tensor] = None  # [3] m/s^2, uniform
    pressure: Optional[torch.Tensor] = None  # [3] m/s^2, the field whose cross / normal part acts
    linear_drag: Optional[torch.Tensor] = None  # 1/s
    quadratic_drag: Optional[torch.Tensor] = None  # 1/m
    friction: Optional[torch.Tensor] = None  # added to the table's mu
    grip: Optional[torch.Tensor] = None  # > 0: a compliant grip, time constant GRIP_TAU0 (e^(2 grip) - 1); < 0: tighter
    mass: Optional[torch.Tensor] = None  # the object is (1 + mass) times heavier (> -0.9)
    stiffness: Optional[torch.Tensor] = None  # stretch and bending compliances / exp(stiffness)
    release: Optional[torch.Tensor] = None  # != 0: the grip lets go once the load off the table exceeds e^(-release) x the weight

    def add(self, other: "PhysicsMods") -> "PhysicsMods":
        """The sum of two sets of changes (fields present in either)."""
        out = PhysicsMods()
        for name in self.__dataclass_fields__:
            a, b = getattr(self, name), getattr(other, name)
            setattr(out, name, a if b is None else (b if a is None else a + b))
        return out

    def pushes(self) -> bool:
        """Whether a change here can move an object at rest (a field, not a drag or a scale)."""
        return any(v is not None and bool((v != 0).any()) for v in (self.accel, self.pressure))
