"""What the figure tests share: the figures drawn (instead of saved), and what makes a figure readable."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from cosim.evaluation import plots


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    drawn: list[Figure] = []
    monkeypatch.setattr(plots, "save", lambda fig, path: drawn.append(fig) or path)
    return drawn


@pytest.fixture
def readable() -> Callable[..., None]:
    return _readable


def _readable(fig: Figure, caption: str, runs_on_x: bool = False) -> None:
    """What every figure has: a title, x and y labels (one with a unit; `runs_on_x`: the x axis names runs
    instead), legends clear of every panel, the caption at its foot."""
    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert fig.get_suptitle() or all(ax.get_title() for ax in panels)
    for ax in panels:
        assert ax.get_xlabel() or runs_on_x or ax.get_shared_x_axes().get_siblings(ax) != [ax], ax.get_title()
        assert ax.get_ylabel(), ax.get_title()
        assert "[" in ax.get_xlabel() + ax.get_ylabel() or ax.get_ylabel() in ("action", "return per AV and episode")
    legends = [leg for leg in [*fig.legends, *(ax.get_legend() for ax in panels)] if leg is not None]
    assert legends or runs_on_x  # the bars name their runs under them
    for leg in legends:
        box = leg.get_window_extent(renderer)
        for ax in panels:
            assert not box.overlaps(ax.get_window_extent(renderer)), f"legend over the panel {ax.get_title()!r}"
    assert " ".join(fig.get_supxlabel().split()) == caption  # wrapped to the figure's width
