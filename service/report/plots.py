"""The diagnosis plots as PNG, drawn with matplotlib (Agg, object API: no pyplot state) from the stored answer.

Names (see `figures.plot_list`): `errors` (held-out error per pose, geometric and final model, noise floor),
`distribution` (histograms of the same), `finding-k` (the k-th finding's residual against its regressor,
with the fitted effect).
"""
from __future__ import annotations

import io
import threading
from collections import OrderedDict

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .figures import finding_title, model_label, num, plot_list

GEO = "#e08a2c"  # geometric model: orange
FINAL = "#1f5fa8"  # final model: blue
FLOOR = "#2b8a3e"  # noise floor: green
RESID = "#8a8f98"
FIT = "#c92a2a"
SIZE = (8.0, 3.6)
DPI = 110

_lock = threading.Lock()  # matplotlib's font and text caches are not thread-safe
_cache: OrderedDict[tuple[str, str], bytes] = OrderedDict()
CACHE_SIZE = 64


class UnknownPlot(KeyError):
    pass


def names(answer: dict) -> list[str]:
    return [p["name"] for p in plot_list(answer)]


def png(answer: dict, name: str, cache_key: str | None = None) -> bytes:
    """The plot `name` of this answer as PNG bytes; raises UnknownPlot if the answer has no such plot.
    A stored answer never changes, so PNGs are cached by (cache_key, name)."""
    if name not in names(answer):
        raise UnknownPlot(name)
    key = (cache_key, name) if cache_key else None
    with _lock:
        if key is not None and key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
        data = _render(answer, name)
        if key is not None:
            _cache[key] = data
            while len(_cache) > CACHE_SIZE:
                _cache.popitem(last=False)
    return data


def _render(answer: dict, name: str) -> bytes:
    fig = Figure(figsize=SIZE, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    d = answer.get("diagnosis") or {}
    if name == "errors":
        axes = [fig.add_subplot()]
        _errors(axes[0], answer, d)
    elif name == "distribution":
        axes = [fig.add_subplot()]
        _distribution(axes[0], answer, d)
    else:
        k = int(name.split("-", 1)[1])
        axes = fig.subplots(1, 2, width_ratios=[2.2, 1])
        _finding(axes, d["findings"][k - 1], k)
    for ax in axes:
        ax.grid(True, alpha=0.3, linewidth=0.6)
        for side in ("top", "right"):
            ax.spines[side].set_visible(False)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _arr(values) -> np.ndarray:
    return np.array([np.nan if num(v) is None else float(v) for v in values or []], float)


def _floor(ax, d: dict, horizontal: bool = True) -> None:
    floor = num(d.get("noise_floor_mm"))
    if floor is None:
        return
    line = ax.axhline if horizontal else ax.axvline
    line(floor, color=FLOOR, linestyle="--", linewidth=1.2, label=f"noise floor {floor:.3f} mm")


def _errors(ax, answer: dict, d: dict) -> None:
    pp = d["per_pose"]
    geo, fin = _arr(pp["geometric_holdout_mm"]), _arr(pp["final_holdout_mm"])
    x = np.arange(1, len(geo) + 1)
    same = list(answer.get("model") or []) == ["geometric"]
    ax.bar(x, geo, width=1.0, color=GEO, alpha=0.55,
           label=f"geometric model, RMS {np.sqrt(np.nanmean(geo**2)):.3f} mm")
    if not same:
        ax.bar(x, fin, width=0.6, color=FINAL,
               label=f"{model_label(answer['model'])}, RMS {np.sqrt(np.nanmean(fin**2)):.3f} mm")
    _floor(ax, d)
    ax.set_xlim(0.5, len(geo) + 0.5)
    ax.set_xlabel("calibration pose (measurement order)")
    ax.set_ylabel("held-out error (mm)")
    ax.set_title("Error per pose, each predicted by a model fitted without it", fontsize=10)
    ax.legend(fontsize=8, loc="upper right", frameon=False)


def _distribution(ax, answer: dict, d: dict) -> None:
    pp = d["per_pose"]
    geo, fin = _arr(pp["geometric_holdout_mm"]), _arr(pp["final_holdout_mm"])
    both = np.concatenate([geo, fin])
    both = both[np.isfinite(both)]
    top = float(both.max()) if len(both) else 1.0
    bins = np.linspace(0.0, top * 1.02 + 1e-9, 31)
    same = list(answer.get("model") or []) == ["geometric"]
    ax.hist(geo[np.isfinite(geo)], bins=bins, color=GEO, alpha=0.6, label="geometric model")
    if not same:
        ax.hist(fin[np.isfinite(fin)], bins=bins, color=FINAL, alpha=0.75, label=model_label(answer["model"]))
    _floor(ax, d, horizontal=False)
    ax.set_xlabel("held-out error per pose (mm)")
    ax.set_ylabel("poses")
    ax.set_title("How the error is spread over the poses", fontsize=10)
    ax.legend(fontsize=8, loc="upper right", frameon=False)


def _finding(axes, f: dict, k: int) -> None:
    """Left: the residual the finding explains and its fitted displacement, both along the effect's direction
    at each pose, against the effect's regressor. Right: residual against fit (on the diagonal when the
    effect explains it)."""
    ax, ax2 = axes
    p = f["plot"]
    x, r, fit = _arr(p["x"]), _arr(p["residual_mm"]), _arr(p.get("fit_mm"))
    kind = str(f.get("kind", "")).replace("_", " ")
    ax.scatter(x, r, s=14, color=RESID, alpha=0.8, label="residual before this finding")
    has_fit = len(fit) == len(x)
    if has_fit:
        ax.scatter(x, fit, s=8, color=FIT, label=f"fitted {kind}")
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.set_xlabel(p.get("x_label") or "regressor")
    ax.set_ylabel("along the effect's direction (mm)")
    ax.set_title(f"Finding {k}: {finding_title(f)}", fontsize=10)
    ax.legend(fontsize=8, loc="best", frameon=False)
    if has_fit:
        ok = np.isfinite(r) & np.isfinite(fit)
        lo = float(min(r[ok].min(), fit[ok].min(), 0.0)) if ok.any() else 0.0
        hi = float(max(r[ok].max(), fit[ok].max())) if ok.any() else 1.0
        ax2.plot([lo, hi], [lo, hi], color=FIT, linewidth=1.2, label="residual = fit")
        ax2.scatter(fit, r, s=10, color=RESID, alpha=0.8)
        if ok.sum() > 2 and np.std(fit[ok]) > 0 and np.std(r[ok]) > 0:
            ax2.text(0.04, 0.95, f"R = {np.corrcoef(fit[ok], r[ok])[0, 1]:.2f}", transform=ax2.transAxes,
                     va="top", fontsize=9)
        ax2.set_xlabel(f"fitted {kind} (mm)")
        ax2.set_ylabel("residual (mm)")
        ax2.set_title("Does the effect explain it?", fontsize=10)
        ax2.legend(fontsize=8, loc="lower right", frameon=False)
    else:
        ax2.set_axis_off()
