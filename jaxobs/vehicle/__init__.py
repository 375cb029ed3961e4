"""A planar vehicle simulator for the sideslip observers of Grip 2010 (ch. 2-4): tyres, a two-track model,
ESC-type sensors and manoeuvres modelled on the thesis's test drives.

``tyres``: Magic Formula and Burckhardt tyre curves with combined slip in the friction ellipse.

Every parameter set is a registered dataclass pytree, so a batch of vehicles is a dataclass of arrays under
``vmap``; everything is pure and works under ``jit``, ``vmap`` and ``grad``. ``import jaxobs`` does not import
this package.
"""

from jaxobs.vehicle.tyres import BURCKHARDT_SURFACES, BurckhardtTyre, TyreParams, pure_force, tyre_forces

__all__ = ["BURCKHARDT_SURFACES", "BurckhardtTyre", "TyreParams", "pure_force", "tyre_forces"]
