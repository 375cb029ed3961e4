"""The report figures read at a glance: plain tick labels, a one-strategy sweep drawn as lines, every output of a
tuning problem's responses on an axis of its own."""

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np

from jaxobs.papers import _output, tune_job
from jaxobs.papers.cortesao import force_sweep


def _capture(monkeypatch, module) -> list:
    """Make ``module.save_figure`` keep the figure (drawn, not written) instead of writing it."""
    kept = []

    def keep(fig, out_dir, name):
        _output.plain_ticks(fig)
        fig.canvas.draw()
        kept.append(fig)
        return f"{name}.png"

    monkeypatch.setattr(module, "save_figure", keep)
    return kept


def test_tick_labels_have_no_offset_and_log_axes_read_plain():
    plt = _output.pyplot()
    fig, (ax, bx, cx) = plt.subplots(1, 3)
    ax.plot([0, 1], [-1.5 - 1e-9, -1.5 + 1e-9])
    bx.plot([0, 1], [43.4, 45.0])
    cx.plot([0, 1], [8.5e-5, 2e-4])
    for log in (bx, cx):
        log.set_yscale("log")
    _output.plain_ticks(fig)
    fig.canvas.draw()
    assert ax.yaxis.get_offset_text().get_text() == ""
    for log in (bx, cx):
        labels = [t.get_text() for t in (*log.get_yticklabels(), *log.get_yticklabels(minor=True)) if t.get_text()]
        assert labels and not any("times" in label or "^" in label for label in labels), labels
    plt.close(fig)


def test_a_sweep_of_one_strategy_is_drawn_as_lines(monkeypatch, tmp_path):
    kept = _capture(monkeypatch, force_sweep)
    n = 40
    cols = {
        "param.stiffness": np.geomspace(0.3, 30.0, 2 * n),
        "param.active_variance": np.full(2 * n, 1e-3),
        "param.R": np.full(2 * n, 0.03),
        "param.order": np.repeat([1, 0], n),
        "metric.stable": np.arange(2 * n) % 3 != 0,
    }
    force_sweep._plot_stability_maps(cols, [1, 0], tmp_path)
    (fig,) = kept
    (ax,) = [a for a in fig.axes if a.get_label() != "<colorbar>"]
    assert not ax.collections  # no heat map
    assert [line.get_label() for line in ax.get_lines() if not line.get_label().startswith("_")] == ["AOB-1", "CKF"]


def test_responses_give_every_output_a_row_of_axes(monkeypatch, tmp_path):
    kept = _capture(monkeypatch, tune_job)
    t = np.linspace(0.0, 1.0, 11)

    def responses(theta, plants):
        return {
            "t": t,
            "output": theta["gain"] * jnp.ones((3, t.size, 2)),
            "desired": np.zeros((t.size, 2)),
            "labels": ["a", "b", "c"],
            "ylabel": ["cart (m)", "angle (rad)"],
            "setpoint": np.array([0.5, np.nan]),
        }

    problem = SimpleNamespace(responses=responses, heldout={"plant": jnp.arange(5)})
    designs = {"hand-set": {"gain": 1.0}, "tuned": {"gain": 2.0}}
    tune_job._plot_responses(problem, designs, np.arange(5.0), tmp_path)
    (fig,) = kept
    axes = np.asarray(fig.axes).reshape(2, 3)
    assert [axes[j, 0].get_ylabel() for j in range(2)] == ["cart (m)", "angle (rad)"]
    assert len(axes[0, 0].get_lines()) == 4 and len(axes[1, 0].get_lines()) == 3  # set-point of the tracked row
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["hand-set", "tuned", "desired", "set-point"]
