"""The diagnosis plots as PNG, drawn with matplotlib (Agg, object API: no pyplot state) from the stored answer.

Names (see `figures.plot_list`): `errors` (held-out error per pose, geometric and final model, noise floor;
one bar per pose up to BARS_MAX poses, above that the poses in consecutive groups: mean and max per group),
`distribution` (histograms of the same), `finding-k` (the k-th finding's residual against its regressor,
with the fitted effect).

They are drawn once, in the job's process when the calibration finishes (queue/runner.py), and stored
(`calibration_plots`); the API serves the stored PNGs. Only a calibration stored before that (migration 0002)
is drawn by the API, once per process (`png(..., cache_key=...)`). Every text that comes from the user (joint
names, labels) goes through `_tx`, so a `$` is a dollar sign, never matplotlib mathtext.
"""
from __future__ import annotations

import io
import textwrap
import threading
from collections import OrderedDict

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .figures import accuracy, counted_word, finding_title, model_label, num, plot_list

GEO = "#e08a2c"  # geometric model: orange
FINAL = "#1f5fa8"  # final model: blue
FLOOR = "#2b8a3e"  # noise floor: green
RESID = "#8a8f98"
FIT = "#c92a2a"
SIZE = (8.0, 3.6)
DPI = 110

_lock = threading.Lock()  # matplotlib's font and text caches are not thread-safe (API fallback for old rows only)
_cache: OrderedDict[tuple[str, str], bytes] = OrderedDict()
CACHE_SIZE = 64
BARS_MAX = 300  # up to this many poses the error plot has one bar per pose
GROUPS = 150  # above it, this many groups of consecutive poses


def _tx(v) -> str:
    """Text for matplotlib: a `$` is a literal dollar sign (mathtext never parses user text)."""
    return str(v).replace("\\$", "$").replace("$", "\\$")


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
    return _png_bytes(figure(answer, name))


def _png_bytes(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def error_png(name: str, why: str) -> bytes:
    """A PNG that says a plot could not be drawn (the job's result is still stored; the report shows this)."""
    fig = Figure(figsize=SIZE, dpi=DPI)
    FigureCanvasAgg(fig)
    fig.text(0.5, 0.5, _tx(f"the plot {name!r} could not be drawn:\n{why}"[:400]), ha="center", va="center",
             wrap=True, fontsize=9, color=RESID)
    return _png_bytes(fig)


def figure(answer: dict, name: str) -> Figure:
    """The matplotlib figure of plot `name` (not yet rendered)."""
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
        fig.suptitle(_tx(textwrap.shorten(f"Finding {k}: {finding_title(d['findings'][k - 1])}", 110,
                                          placeholder=" ...")), fontsize=10)
    for ax in axes:
        ax.grid(True, alpha=0.3, linewidth=0.6)
        for side in ("top", "right"):
            ax.spines[side].set_visible(False)
    return fig


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
    n = len(geo)
    same = list(answer.get("model") or []) == ["geometric"]
    geo_label, fin_label = _labels(answer, same)
    if n <= BARS_MAX:
        x = np.arange(1, n + 1)
        ax.bar(x, geo, width=1.0, color=GEO, alpha=0.55, label=geo_label)
        if not same:
            ax.bar(x, fin, width=0.6, color=FINAL, label=fin_label)
        ax.set_xlabel("calibration pose (measurement order)")
    else:  # thousands of poses: a bar each is unreadable and slow; groups of consecutive poses, mean and max
        edges = np.linspace(0, n, GROUPS + 1).round().astype(int)
        series = [(geo, GEO, 0.55, geo_label)] + ([] if same else [(fin, FINAL, 0.9, fin_label)])
        top_all = 0.0
        for v, color, alpha, label in series:
            mean, top = _grouped(v, edges)
            top_all = max(top_all, float(top.max()))
            ax.stairs(mean, edges + 0.5, color=color, alpha=alpha, fill=True, label=f"{label}, mean of the group")
            ax.stairs(top, edges + 0.5, color=color, alpha=0.8, linewidth=0.8)
        ax.plot([], [], color=RESID, linewidth=0.8, label="thin lines: the largest error of the group")
        ax.set_ylim(0.0, 1.35 * top_all if top_all > 0 else 1.0)  # room for the legend
        ax.set_xlabel(f"calibration pose (measurement order, {GROUPS} groups of about {n / GROUPS:.0f} poses)")
    _floor(ax, d)
    ax.set_xlim(0.5, n + 0.5)
    ax.set_ylabel("held-out error (mm)")
    ax.set_title("Error per pose, each predicted by a model fitted without it", fontsize=10)
    ax.legend(fontsize=8, loc="upper right", frameon=False)


def _labels(answer: dict, same: bool) -> tuple[str, str]:
    """The legend of the geometric and the final model: RMS over every pose, quoted from the answer's accuracy
    table (`holdout_all`, the figure the report's headline shows), never recomputed here."""
    acc = answer.get("accuracy") or accuracy(answer)
    rows = acc["models"]
    word = counted_word(acc["counts"])

    def label(name: str, row: dict) -> str:
        v = num(row["holdout_all"]["rms_mm"])
        return _tx(name if v is None else f"{name}, RMS {v:.3f} mm over all {row['holdout_all']['n']} {word}")
    geo = label("geometric model", rows[0])
    return geo, ("" if same else label(model_label(answer["model"]), rows[-1]))


def _grouped(v: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and max of v over [edges[k], edges[k+1]) (NaN-aware; an all-NaN group is 0)."""
    mean, top = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)
    for k, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        g = v[a:b]
        g = g[np.isfinite(g)]
        if len(g):
            mean[k], top[k] = g.mean(), g.max()
    return mean, top


def _distribution(ax, answer: dict, d: dict) -> None:
    pp = d["per_pose"]
    geo, fin = _arr(pp["geometric_holdout_mm"]), _arr(pp["final_holdout_mm"])
    both = np.concatenate([geo, fin])
    both = both[np.isfinite(both)]
    top = float(both.max()) if len(both) else 1.0
    bins = np.linspace(0.0, top * 1.02 + 1e-9, 31)
    same = list(answer.get("model") or []) == ["geometric"]
    geo_label, fin_label = _labels(answer, same)
    ax.hist(geo[np.isfinite(geo)], bins=bins, color=GEO, alpha=0.6, label=geo_label)
    if not same:
        ax.hist(fin[np.isfinite(fin)], bins=bins, color=FINAL, alpha=0.75, label=fin_label)
    _floor(ax, d, horizontal=False)
    ax.set_xlabel("held-out error per pose (mm)")
    ax.set_ylabel(counted_word((answer.get("accuracy") or accuracy(answer))["counts"]))
    ax.set_title("How the error is spread over the poses", fontsize=10)
    ax.legend(fontsize=8, loc="upper right", frameon=False)


def _finding(axes, f: dict, k: int) -> None:
    """Left: the residual the finding explains and its fitted displacement, both along the effect's direction
    at each pose, against the effect's regressor. Right: residual against fit (on the diagonal when the
    effect explains it)."""
    ax, ax2 = axes
    p = f["plot"]
    x, r, fit = _arr(p["x"]), _arr(p["residual_mm"]), _arr(p.get("fit_mm"))
    kind = _tx(str(f.get("kind", "")).replace("_", " "))
    x_label = _tx(p.get("x_label") or "regressor")
    fx = x[np.isfinite(x)]
    if len(fx) == 0 or float(np.ptp(fx)) <= 1e-9 * max(1.0, float(np.abs(fx).max())):
        # the regressor does not vary over the poses (every point would sit on one x): by measurement order
        const = f"{fx[0]:.3g}" if len(fx) else "undefined"
        x = np.arange(1, len(r) + 1, dtype=float)
        x_label = _tx(f"calibration pose (measurement order; {p.get('x_label') or 'its regressor'} is {const} at "
                      f"every pose)")
    many = len(x) > 1000
    ax.scatter(x, r, s=3 if many else 14, color=RESID, alpha=0.5 if many else 0.8, linewidths=0,
               label="residual before this finding")
    has_fit = len(fit) == len(x)
    if has_fit:
        ax.scatter(x, fit, s=2 if many else 8, color=FIT, linewidths=0, label=f"fitted {kind}")
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.set_xlabel(textwrap.fill(x_label, 70))
    ax.set_ylabel("along the effect's direction (mm)")
    ax.set_title("Residual and fitted effect", fontsize=9)
    ax.legend(fontsize=8, loc="upper left" if many else "best", frameon=False)  # "best" is O(points)
    if has_fit:
        ok = np.isfinite(r) & np.isfinite(fit)
        lo = float(min(r[ok].min(), fit[ok].min(), 0.0)) if ok.any() else 0.0
        hi = float(max(r[ok].max(), fit[ok].max())) if ok.any() else 1.0
        ax2.plot([lo, hi], [lo, hi], color=FIT, linewidth=1.2, label="residual = fit")
        ax2.scatter(fit, r, s=3 if many else 10, color=RESID, alpha=0.5 if many else 0.8, linewidths=0)
        if ok.sum() > 2 and np.std(fit[ok]) > 0 and np.std(r[ok]) > 0:
            ax2.text(0.04, 0.95, f"R = {np.corrcoef(fit[ok], r[ok])[0, 1]:.2f}", transform=ax2.transAxes,
                     va="top", fontsize=9)
        ax2.set_xlabel(f"fitted {kind} (mm)")
        ax2.set_ylabel("residual (mm)")
        ax2.set_title("Does it explain the residual?", fontsize=9)
        ax2.legend(fontsize=8, loc="lower right", frameon=False)
    else:
        ax2.set_axis_off()
