"""Tyre forces: the Magic Formula with a friction-dependent curve shape, the Burckhardt curve, combined slip.

:class:`TyreParams` is the Magic Formula (Pacejka 2006), whose slip at the peak shrinks with the friction ``mu``
as measured curves do (Grip 2010, Fig. 2.3); :class:`BurckhardtTyre` is the Burckhardt curve (Burckhardt 1993;
Kiencke & Nielsen 2000, ch. 7) with coefficients per surface in :data:`BURCKHARDT_SURFACES`. :func:`tyre_forces`
combines longitudinal and lateral slip through the theoretical slips, so the forces stay in the friction ellipse.
Elementwise, pure and differentiable (also at zero slip); parameters broadcast, so tyres batch under ``vmap``.
The slip conventions and formulas: docs/theory/vehicle.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = ["TyreParams", "BurckhardtTyre", "BURCKHARDT_SURFACES", "tyre_forces", "pure_force"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TyreParams:
    """Magic Formula tyre (Pacejka 2006) with the friction-dependent stiffness factor ``B = c / (C mu)``.

    Defaults (assumed, a summer tyre of a mid-size passenger car on dry asphalt): peak friction 1.0; cornering
    stiffness 20 per rad of ``tan(alpha)`` per unit load (80 kN/rad at 4 kN); longitudinal slip stiffness 20
    per unit slip per unit load; shape factors 1.3 (lateral) and 1.65 (longitudinal) and curvature -0.5. On
    dry asphalt the lateral peak lies at ``alpha`` of about 8 deg, the longitudinal one at ``kappa`` of about 0.1.

    Attributes:
      mu: peak friction coefficient ``D / F_z`` of the tyre-road pair (> 0); ~1 dry asphalt, ~0.3 snow, ~0.1 ice.
      cornering_stiffness: lateral slip stiffness per unit load ``c_y`` (1/rad, > 0).
      slip_stiffness: longitudinal slip stiffness per unit load ``c_x`` (> 0).
      shape_y, shape_x: shape factors ``C`` (in (0, 2)).
      curvature_y, curvature_x: curvature factors ``E`` (< 1).
    """

    mu: float = 1.0
    cornering_stiffness: float = 20.0
    slip_stiffness: float = 20.0
    shape_y: float = 1.3
    shape_x: float = 1.65
    curvature_y: float = -0.5
    curvature_x: float = -0.5

    def validate(self) -> None:
        """Raise ``ValueError`` naming the bad field (concrete values only; skipped under tracing)."""
        for name in ("mu", "cornering_stiffness", "slip_stiffness"):
            _checks.positive(name, getattr(self, name))
        for name in ("shape_y", "shape_x"):
            _checks.positive(name, getattr(self, name), what="a Magic Formula shape factor in (0, 2)")
            _checks.positive(name, 2.0 - getattr(self, name), what="a shape factor below 2")
        for name in ("curvature_y", "curvature_x"):
            _checks.positive(name, 1.0 - getattr(self, name), what="1 - E: a curvature factor below 1")


BURCKHARDT_SURFACES = {
    "dry_asphalt": (1.2801, 23.99, 0.52),
    "wet_asphalt": (0.857, 33.822, 0.347),
    "dry_cobblestone": (1.3713, 6.4565, 0.6691),
    "wet_cobblestone": (0.4004, 33.708, 0.1204),
    "snow": (0.1946, 94.129, 0.0646),
    "ice": (0.05, 306.39, 0.0),
}
"""Burckhardt coefficients ``(c1, c2, c3)`` per surface (Burckhardt 1993, as tabulated by Kiencke & Nielsen 2000)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BurckhardtTyre:
    """Burckhardt friction curve ``mu(s) = c1 (1 - exp(-c2 s)) - c3 s`` (defaults: dry asphalt).

    Attributes:
      c1: friction scale (> 0).  c2: exponential rate (> 0).  c3: slope of the decrease at large slip (>= 0).
    """

    c1: float = BURCKHARDT_SURFACES["dry_asphalt"][0]
    c2: float = BURCKHARDT_SURFACES["dry_asphalt"][1]
    c3: float = BURCKHARDT_SURFACES["dry_asphalt"][2]

    @classmethod
    def surface(cls, name: str) -> BurckhardtTyre:
        """The tabulated coefficients of the surface ``name`` (a key of :data:`BURCKHARDT_SURFACES`)."""
        if name not in BURCKHARDT_SURFACES:
            raise ValueError(f"name must be one of {sorted(BURCKHARDT_SURFACES)}, got {name!r}")
        return cls(*BURCKHARDT_SURFACES[name])

    def validate(self) -> None:
        """Raise ``ValueError`` naming the bad field (concrete values only; skipped under tracing)."""
        _checks.positive("c1", self.c1)
        _checks.positive("c2", self.c2)
        _checks.positive("c3", self.c3, allow_zero=True)


def _burckhardt(tyre, s, fz):
    """Burckhardt ``F0(s) / s`` for ``s >= 0`` (finite, with finite gradients, at ``s = 0``)."""
    small = s < 1e-12
    s_safe = jnp.where(small, 1.0, s)
    force = fz * (tyre.c1 * (1.0 - jnp.exp(-tyre.c2 * s_safe)) - tyre.c3 * s_safe)
    return jnp.where(small, fz * (tyre.c1 * tyre.c2 - tyre.c3), force / s_safe)


def _magic(s, stiffness, shape, curvature, mu, fz):
    """Magic Formula ``F0(s) / s`` for ``s >= 0`` (finite at 0) with ``B = stiffness / (shape mu)``, ``D = mu fz``."""
    small = s < 1e-12
    s_safe = jnp.where(small, 1.0, s)
    b = stiffness / (shape * mu)
    bs = b * s_safe
    force = mu * fz * jnp.sin(shape * jnp.arctan(bs - curvature * (bs - jnp.arctan(bs))))
    return jnp.where(small, stiffness * fz, force / s_safe)


def pure_force(tyre, slip, fz, *, direction: str = "y"):
    """The pure-slip force ``F0(slip)`` (N) of ``tyre`` at the normal load ``fz`` (N), elementwise.

    Args:
      tyre: a :class:`TyreParams` or :class:`BurckhardtTyre`.
      slip: theoretical slip ``sigma_y = tan(alpha)`` (``direction="y"``) or ``sigma_x = kappa / (1 + kappa)``.
      fz: normal load (N).
      direction: ``"y"`` (lateral) or ``"x"`` (longitudinal).
    """
    if direction not in ("x", "y"):
        raise ValueError(f"direction must be 'x' or 'y', got {direction!r}")
    slip, fz = _checks.float_arrays(slip=slip, fz=fz)
    return _curve_ratio(tyre, jnp.abs(slip), fz, direction) * slip


def _curve_ratio(tyre, s, fz, direction):
    if isinstance(tyre, TyreParams):
        if direction == "y":
            return _magic(s, tyre.cornering_stiffness, tyre.shape_y, tyre.curvature_y, tyre.mu, fz)
        return _magic(s, tyre.slip_stiffness, tyre.shape_x, tyre.curvature_x, tyre.mu, fz)
    if isinstance(tyre, BurckhardtTyre):
        return _burckhardt(tyre, s, fz)
    raise TypeError(f"tyre must be a TyreParams or a BurckhardtTyre, got {type(tyre).__name__}")


def tyre_forces(tyre, kappa, tan_alpha, fz):
    """Longitudinal and lateral tyre forces (wheel frame, N) under combined slip, elementwise.

    Args:
      tyre: a :class:`TyreParams` or :class:`BurckhardtTyre`.
      kappa: longitudinal slip ``(omega R - v_l) / |v_l|`` (> -1).
      tan_alpha: ``tan`` of the slip angle (positive clockwise; a positive value gives a positive ``F_y``).
      fz: normal load (N, >= 0).

    Returns:
      ``(F_x, F_y)``, broadcast to the common shape of the arguments.
    """
    kappa, tan_alpha, fz = _checks.float_arrays(kappa=kappa, tan_alpha=tan_alpha, fz=fz)
    denom = 1.0 + jnp.maximum(kappa, -0.99)
    sx, sy = kappa / denom, tan_alpha / denom
    s2 = sx**2 + sy**2
    small = s2 < 1e-24
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    s = jnp.where(small, 0.0, s)
    return _curve_ratio(tyre, s, fz, "x") * sx, _curve_ratio(tyre, s, fz, "y") * sy
