"""jaxobs.tuning.box: the flat layout of a ``theta`` (order, shapes, dtypes) and the search box around it."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs.tuning.box import Layout, search_box


def _theta():
    return {"q": jnp.arange(6.0).reshape(2, 3), "r": jnp.asarray(7.0), "k": jnp.asarray([8.0, 9.0], jnp.float32)}


def test_layout_round_trips_one_theta_and_rows():
    theta = _theta()
    layout = Layout(theta)
    assert layout.size == 9 and layout.names == ["q", "r", "k"] and layout.dtype == jnp.float64
    vector = layout.flat(theta)
    np.testing.assert_array_equal(vector, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 8.0, 9.0])  # theta0's order, raveled
    back = layout.unflat(vector)
    assert {k: (v.shape, v.dtype) for k, v in back.items()} == {k: (v.shape, v.dtype) for k, v in theta.items()}
    for k in theta:
        np.testing.assert_array_equal(back[k], theta[k])
    stacked = jax.tree.map(lambda v: jnp.stack([v, 2 * v, -v]), theta)
    rows = layout.flat_rows(stacked)
    assert rows.shape == (3, 9)
    np.testing.assert_array_equal(rows, np.stack([vector, 2 * vector, -vector]))
    np.testing.assert_array_equal(jax.jit(layout.flat_rows)(layout.unflat_rows(rows)), rows)  # under jit too


def test_search_box_spread_or_the_problems_own_bounds():
    theta = _theta()
    layout = Layout(theta)
    low, high = layout.bounds(search_box(theta, None, 2.0))
    np.testing.assert_array_equal(high - low, np.full(9, 4.0))
    np.testing.assert_array_equal((low + high) / 2, layout.flat(theta))
    own = {"q": (0.0, 10.0), "r": (7.0, 7.0), "k": (jnp.asarray([1.0, 2.0]), jnp.asarray([3.0, 4.0]))}
    low, high = layout.bounds(search_box(theta, own, 2.0))  # scalar bounds broadcast; r fixed (low == high)
    np.testing.assert_array_equal(low, [0.0] * 6 + [7.0, 1.0, 2.0])
    np.testing.assert_array_equal(high, [10.0] * 6 + [7.0, 3.0, 4.0])
