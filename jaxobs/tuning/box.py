"""The search box of a tuning problem and the flat layout of ``theta`` (a dict of arrays) the exploration works in:
coordinates in the order of ``theta0``'s entries, each entry raveled."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["Layout", "search_box"]


def search_box(theta0: dict, box: dict | None, spread: float) -> dict:
    """``{name: (low, high)}``: ``box`` (a problem's ``search_box``) as arrays, else ``theta0 +- spread`` per
    unconstrained coordinate."""
    if box is not None:
        return {k: (jnp.asarray(lo), jnp.asarray(hi)) for k, (lo, hi) in box.items()}
    return {k: (jnp.asarray(v) - spread, jnp.asarray(v) + spread) for k, v in theta0.items()}


class Layout:
    """How a ``theta`` shaped like ``theta0`` maps to a flat vector of ``size`` coordinates and back (static: shapes
    and dtypes only). Methods ending in ``_rows`` take and give a leading axis of candidates."""

    def __init__(self, theta0: dict):
        """The layout of ``theta0``'s entries (a dict of arrays)."""
        self.names = list(theta0)
        self.shapes = [tuple(np.shape(v)) for v in theta0.values()]
        self.dtypes = [jnp.asarray(v).dtype for v in theta0.values()]
        self.sizes = [int(np.prod(s, dtype=int)) for s in self.shapes]
        self.size = sum(self.sizes)
        self.dtype = jnp.result_type(*self.dtypes) if self.dtypes else jnp.float32

    def flat(self, theta: dict):
        """``theta`` as one vector (size,)."""
        return jnp.concatenate([jnp.ravel(jnp.asarray(theta[k], self.dtype)) for k in self.names])

    def flat_rows(self, stacked: dict):
        """Stacked ``theta``s (N, ...) as rows (N, size)."""
        count = jnp.shape(stacked[self.names[0]])[0]
        return jnp.concatenate([jnp.reshape(jnp.asarray(stacked[k], self.dtype), (count, -1)) for k in self.names], 1)

    def unflat_rows(self, rows) -> dict:
        """Rows (N, size) as stacked ``theta``s (N, ...) of ``theta0``'s dtypes."""
        out, offset = {}, 0
        for name, shape, dtype, size in zip(self.names, self.shapes, self.dtypes, self.sizes, strict=True):
            out[name] = jnp.reshape(rows[:, offset : offset + size], (rows.shape[0], *shape)).astype(dtype)
            offset += size
        return out

    def unflat(self, vector) -> dict:
        """A vector (size,) as a ``theta``."""
        return {k: v[0] for k, v in self.unflat_rows(vector[None]).items()}

    def bounds(self, box: dict):
        """``(low, high)`` (size,) of a box ``{name: (low, high)}`` (bounds broadcast to each entry's shape)."""
        low = {
            k: jnp.broadcast_to(jnp.asarray(box[k][0], d), s)
            for k, d, s in zip(self.names, self.dtypes, self.shapes, strict=True)
        }
        high = {
            k: jnp.broadcast_to(jnp.asarray(box[k][1], d), s)
            for k, d, s in zip(self.names, self.dtypes, self.shapes, strict=True)
        }
        return self.flat(low), self.flat(high)
