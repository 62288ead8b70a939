"""The sweep report's own figures (rates and flow over the SVO angle) are readable: titles, units, legends
clear of the panels, the caption; series that coincide stay visible."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.evaluation import plots, report
from cosim.evaluation.stats import summarize

CAPTION = plots.caption_text("sumo_net/dilemma/dilemma.net.xml", "configs/default.yaml",
                             "AVs trained at each SVO angle (training seeds 0, 1, 2); baselines idle, courteous")


def _rows(crash: float, merge: float, n: int = 100) -> list[dict[str, str]]:
    rng = np.random.default_rng(0)
    return [{"crashed": str(c), "cause_av": str(c), "cause_hv_into_av": "False", "cause_merger": "False",
             "merged": str(bool(rng.random() < merge)), "throughput_vph": str(3000 + 100 * rng.normal()),
             "time_loss": str(4 + rng.normal())} for c in (rng.random(n) < crash)]


PHI_ROWS = {0.0: _rows(0.07, 0.4), 0.7854: _rows(0.12, 0.8)}
BASE_ROWS = {"idle": _rows(0.76, 0.1), "courteous": _rows(0.0, 0.95)}


def test_rates_over_phi(figures, readable, tmp_path: Path) -> None:
    report._rates_vs_phi(tmp_path / "rates.png", PHI_ROWS, BASE_ROWS, CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
    crash = fig.axes[0]
    # Every crash is an AV's fault here: the total and that cause are equal, and drawn apart along phi.
    series = {c.get_label(): c[0] for c in crash.containers}  # errorbar containers: (data line, caps, bars)
    total, av = series["crash"], series["crash, AV at fault"]
    assert np.array_equal(total.get_ydata(), av.get_ydata())
    assert (np.asarray(total.get_xdata()) < np.asarray(av.get_xdata())).all()


def test_flow_over_phi(figures, readable, tmp_path: Path) -> None:
    table = {**{b: summarize(r) for b, r in BASE_ROWS.items()},
             **{report.phi_label(p): summarize(r) for p, r in PHI_ROWS.items()}}
    report._flow_vs_phi(tmp_path / "flow.png", table, list(PHI_ROWS), list(BASE_ROWS), CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
    assert [ax.get_ylabel() for ax in fig.axes] == list(report.FLOW)
