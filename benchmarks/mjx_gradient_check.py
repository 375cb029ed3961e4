"""Gradients through MJX's constraint solver, differentiated implicitly (``jaxobs.mjx.common.step``), against central
differences, on segments with and without contact changes.

The shipped arm on a table (``jaxobs/mjx/assets/arm_on_table.xml``, its solver set to 50 iterations and a tolerance of
1e-10 so that the solve is exact to rounding), under a constant torque ``gain * (-3.5, -0.6)`` N m:

* ``impact``: 0.8 s from rest: the hand strikes the wall after about 0.37 s and slides on it, the contact rows
  switching on and off; the loss is the sum of the squared shoulder angles. Swept over ``--gains`` gains in
  [0.9, 1.1]: the reverse-mode gradient (implicit solve), forward mode, the 4-iteration fixed count's reverse-mode
  gradient, and central differences with steps 1e-3, 1e-5 and 1e-7, each as a relative difference to the reverse-
  mode gradient; the step at which the contact first switches on marks where the loss's smoothness changes.
* ``limit``: 0.3 s with the elbow held on its joint limit (one constraint row active throughout, no change).
* ``free``: 0.8 s of a swing that touches neither the wall nor the limit (rows present, none active).

    python benchmarks/mjx_gradient_check.py --out DIR [--gains 41]

Writes ``DIR/mjx_gradient_check.json`` and ``DIR/mjx_gradient_check.png``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from jaxobs.mjx import common  # noqa: E402
from jaxobs.papers.shipped import ROBOTS  # noqa: E402

TORQUE = jnp.array([-3.5, -0.6])
SEGMENTS = {  # name: (initial qpos, torque at gain 1, physics steps)
    "impact": (jnp.zeros(2), TORQUE, 160),
    "limit": (jnp.array([0.0, -0.31]), jnp.array([0.5, -2.0]), 60),
    "free": (jnp.array([0.3, 0.2]), jnp.array([0.8, 0.3]), 160),
}
STEPS_FD = (1e-3, 1e-5, 1e-7)


def arm_model():
    xml = (ROBOTS / "arm_on_table.xml").read_text()
    xml = xml.replace('iterations="20"', 'iterations="50" tolerance="1e-10"')
    return common.put_model(mujoco.MjModel.from_xml_string(xml))


def losses(model, segment: str, solver_iterations=None):
    """``gain -> (loss, first step with an active constraint row or -1, active rows at the end)``."""
    qpos0, torque, steps = SEGMENTS[segment]

    def loss(gain):
        def body(data, _):
            data = common.step(model, data.replace(ctrl=gain * torque), solver_iterations)
            return data, (data.qpos[0] ** 2, jnp.sum(data._impl.efc_force != 0))

        start = common.initial_data(model, jnp.float64).replace(qpos=qpos0)
        _, (angles, active) = jax.lax.scan(body, start, None, length=steps)
        first = jnp.where(jnp.any(active > 0), jnp.argmax(active > 0), -1)
        return jnp.sum(angles), (first, active[-1])

    return loss


def check(model, segment: str, gains) -> dict:
    """Gradients of every kind and central differences at ``gains`` (one ``vmap`` each)."""
    loss = losses(model, segment)
    value = jax.jit(jax.vmap(lambda g: loss(g)[0]))
    reverse = jax.jit(jax.vmap(jax.grad(lambda g: loss(g)[0])))(gains)
    forward = jax.jit(jax.vmap(jax.jacfwd(lambda g: loss(g)[0])))(gains)
    fixed_loss = losses(model, segment, 4)
    fixed = jax.jit(jax.vmap(jax.grad(lambda g: fixed_loss(g)[0])))(gains)
    first, active = jax.jit(jax.vmap(lambda g: loss(g)[1]))(gains)
    central = {f"{h:g}": (value(gains + h) - value(gains - h)) / (2 * h) for h in STEPS_FD}

    def relative(x):
        return np.abs(np.asarray(x) - np.asarray(reverse)) / np.maximum(np.abs(np.asarray(reverse)), 1e-300)

    return {
        "gains": np.asarray(gains).tolist(),
        "loss": np.asarray(value(gains)).tolist(),
        "reverse": np.asarray(reverse).tolist(),
        "first_active_step": np.asarray(first).tolist(),
        "active_rows_at_end": np.asarray(active).tolist(),
        "relative_difference": {
            "forward mode": relative(forward).tolist(),
            "4 fixed iterations": relative(fixed).tolist(),
            **{f"central differences, step {h}": relative(c).tolist() for h, c in central.items()},
        },
    }


def _print(name: str, result: dict) -> None:
    rows = result["relative_difference"]
    changes = len(set(result["first_active_step"]))
    print(f"{name}: {len(result['gains'])} gains, first active step takes {changes} values; relative difference to "
          "the reverse-mode gradient, median [max]:")  # fmt: skip
    for label, diffs in rows.items():
        print(f"   {label:34s} {np.median(diffs):.1e} [{np.max(diffs):.1e}]")


def plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    impact = results["segments"]["impact"]
    gains = np.asarray(impact["gains"])
    fig, (loss, a, b) = pyplot().subplots(1, 3, figsize=(16, 4.6))
    loss.plot(gains, impact["loss"], "o-", ms=3)
    loss.set_xlabel("torque gain (dotted: the contact's first step changes)")
    loss.set_ylabel("loss: sum of squared shoulder angles (rad^2)")
    loss.set_title("hand striking the wall: the loss at each gain", fontsize=9)
    a.plot(gains, impact["reverse"], "o-", ms=3, label="reverse mode (implicit solve)")
    a.plot(gains, (np.asarray(impact["reverse"]) * (1 + np.asarray(impact["relative_difference"]
           ["central differences, step 1e-05"]))), "x", ms=4, label="central differences, step 1e-5")  # fmt: skip
    a.set_xlabel("torque gain")
    a.set_ylabel("d loss / d gain (rad^2)")
    a.set_title("hand striking the wall: gradient of the sum of squared shoulder angles", fontsize=9)
    a.legend(fontsize=8)
    for label, diffs in impact["relative_difference"].items():
        b.semilogy(gains, np.maximum(diffs, 1e-17), ".-", ms=3, label=label)
    first = np.asarray(impact["first_active_step"])
    for g in gains[1:][np.diff(first) != 0]:
        for ax in (loss, b):
            ax.axvline(g, color="0.7", lw=0.8, ls=":")
    b.set_xlabel("torque gain (dotted: the contact's first step changes)")
    b.set_ylabel("relative difference to the reverse-mode gradient")
    b.set_title("agreement per gain (values below 1e-17 drawn at 1e-17)", fontsize=9)
    b.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    save_figure(fig, path.parent, path.stem)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--gains", type=int, default=41)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    model = arm_model()
    results = {"segments": {}}
    for name in SEGMENTS:
        gains = jnp.linspace(0.9, 1.1, args.gains) if name == "impact" else jnp.linspace(0.95, 1.05, 5)
        results["segments"][name] = check(model, name, gains)
        _print(name, results["segments"][name])
    (args.out / "mjx_gradient_check.json").write_text(json.dumps(results, indent=2) + "\n")
    plot(results, args.out / "mjx_gradient_check.png")
    return results


if __name__ == "__main__":
    main()
