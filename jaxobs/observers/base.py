"""The observer protocol and the helper that runs an observer over time.

Like optax's ``GradientTransformation``, an observer is a pair of pure functions::

    state = init(params)
    state, outputs = step(params, state, inputs)

``params`` and ``state`` are pytrees. Running over time is ``lax.scan`` (:func:`run`); batching is
``vmap`` over params, inputs or both; the user composes the two.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax

__all__ = ["Observer", "run"]


class Observer(NamedTuple):
    """An observer (or observer-based controller) as a pair of pure functions."""

    init: Callable[[Any], Any]
    step: Callable[[Any, Any, Any], tuple[Any, Any]]


def run(observer: Observer, params, inputs, state=None):
    """Run ``observer`` over ``inputs`` (a pytree whose leaves have a leading time axis).

    Returns ``(final_state, outputs)`` with ``outputs`` stacked over time. ``state`` defaults to
    ``observer.init(params)``.
    """
    if state is None:
        state = observer.init(params)

    def body(carry, inp):
        return observer.step(params, carry, inp)

    return jax.lax.scan(body, state, inputs)
