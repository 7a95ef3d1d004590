"""The calibration report and its plots, from the stored answer JSON only (calib_core never imports this).

`figures`: the error table and the plot list added to the API answer, and the number formats of the page;
`plots`: matplotlib PNGs; `html`: the report page.
"""
from __future__ import annotations

from .figures import accuracy, plot_list

__all__ = ["accuracy", "plot_list", "decorate"]


def decorate(answer: dict, base: str) -> dict:
    """Add what the service derives from a stored answer: `accuracy`, `plots` (name, title, url), `report_url`,
    and `plot_url` on each finding that has a plot. `base` is the calibration's path, `/calibrations/{id}`.
    Works on (and returns) a copy-safe dict: findings are replaced, not mutated."""
    answer["accuracy"] = accuracy(answer)
    plots = [dict(p, url=f"{base}/plots/{p['name']}.png") for p in plot_list(answer)]
    answer["plots"] = plots
    answer["report_url"] = f"{base}/report"
    d = answer.get("diagnosis")
    if isinstance(d, dict) and d.get("findings"):
        urls = {p["name"]: p["url"] for p in plots}
        d = dict(d)
        d["findings"] = [dict(f, plot_url=urls.get(f"finding-{k}")) for k, f in enumerate(d["findings"], 1)]
        answer["diagnosis"] = d
    return answer
