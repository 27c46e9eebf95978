"""Comparison figures: one colour and marker per algorithm on every panel, one legend outside the panels."""

from __future__ import annotations

import pytest

from spoil_torchrl.eval import figures
from spoil_torchrl.eval.figures import PAPER_ORDER, algorithm_style, plot_learning_curves, plot_tradeoff


def test_nine_algorithms_have_distinct_fixed_styles():
    styles = [algorithm_style(a) for a in PAPER_ORDER]
    assert len({s["color"] for s in styles}) == 9 and len({s["marker"] for s in styles}) == 9
    assert algorithm_style("spoildice") == {"color": "#d62728", "marker": "*"}
    assert algorithm_style("newalgo") == algorithm_style("newalgo")  # unknown ones are stable too


@pytest.fixture
def captured(monkeypatch):
    figs = []
    monkeypatch.setattr(figures, "_save", lambda plt, fig, path: figs.append(fig))
    return figs


def _colours(ax):
    return {line.get_label(): line.get_color() for line in ax.get_lines()}


def test_tradeoff_same_colour_per_algorithm_and_one_outside_legend(captured):
    summary = {
        (d, a): {"normalized_cost": (c, 0.1), "normalized_feasible_return": (0.5 + c / 10, float("nan"))}
        for d in ("d1", "d2", "d3", "d4")
        for a, c in (("bc", 2.0), ("spoildice", 0.3), ("fbc", 0.9))
        if not (d == "d4" and a == "fbc")
    }
    plot_tradeoff(summary, "unused.png", names={"bc": "BC", "spoildice": "SpoilDICE", "fbc": "FBC"})
    (fig,) = captured
    panels = [ax for ax in fig.axes if ax.axison]
    assert len(panels) == 4 and len(fig.axes) == 6  # 2 x 3 grid, two empty slots switched off
    assert all(ax.get_legend() is None for ax in fig.axes) and len(fig.legends) == 1
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == ["BC", "FBC", "SpoilDICE", "safe (cost <= 1)"]  # the paper's order
    for ax in panels:
        colours = {
            c.lines[0].get_color() for c in ax.containers if hasattr(c, "lines") and c.lines[0] is not None
        }
        assert colours <= {algorithm_style(a)["color"] for a in ("bc", "fbc", "spoildice")}
    red = algorithm_style("spoildice")["color"]
    assert all(
        any(c.lines[0].get_color() == red for c in ax.containers if hasattr(c, "lines")) for ax in panels
    )


def test_learning_curves_one_colour_per_algorithm(captured):
    curve = {"steps": [100, 200], "normalized_feasible_return": [(0.5, 0.1), (0.6, 0.1)]}
    curve["normalized_cost"] = [(2.0, 0.5), (1.0, float("nan"))]
    curves = {(d, a): curve for d in ("d1", "d2") for a in ("bc", "spoildice")}
    plot_learning_curves(curves, "unused.png", seeds=lambda d, a: 3)
    (fig,) = captured
    panels = [ax for ax in fig.axes if ax.axison]
    assert len(panels) == 4 and len(fig.legends) == 1
    assert panels[0].get_title() == "d1 (3 seeds)"
    for ax in panels:
        colours = [line.get_color() for line in ax.get_lines() if line.get_linestyle() == "-"]
        assert colours == [algorithm_style("bc")["color"], algorithm_style("spoildice")["color"]]
