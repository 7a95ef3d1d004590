"""The figures of a calibration, from its stored answer JSON only: one source for the API answer, the report
and the plots.

`accuracy(answer)` is the error table (mean, RMS, max; ISO 9283 AP) the service adds to
`GET /calibrations/{id}`; `plot_list(answer)` names the plots that answer can draw; the formatters are the
ones the HTML report uses, so a number in the JSON appears in the page as `mm(value)` / `pct(value)`.
"""
from __future__ import annotations

import math
from typing import Any

HOLDOUT_NOTE = ("held-out: every pose predicted by the model fitted without it (5-fold cross-validation), "
                "the poses the model names as outliers left out. "
                "ISO 9283 positional accuracy AP = distance between the command position and the barycentre "
                "of the attained positions; with one measurement per pose the barycentre is that measurement, "
                "so AP per pose is the held-out distance and the table gives its mean and max over the poses.")
FIT_NOTE = ("fit: distance of each calibration pose to the model fitted on all of them (in-sample), the outliers "
            "left out too.")


def num(v: Any) -> float | None:
    """A finite float or None (stored answers carry null where a number was not finite)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def mm(v: Any, digits: int = 3) -> str:
    """A length in mm as the report prints it."""
    v = num(v)
    return "—" if v is None else f"{v:.{digits}f}"


def pct(v: Any) -> str:
    v = num(v)
    return "—" if v is None else f"{v:.1f} %"


def sig(v: Any, std: Any = None) -> str:
    """A parameter value with as many decimals as its standard deviation justifies (two significant digits
    of the std, at most 6 decimals); without a usable std, 6 significant digits."""
    v, s = num(v), num(std)
    if v is None:
        return "—"
    if s is None or s <= 0:
        return f"{v:.6g}"
    decimals = max(0, min(6, 1 - math.floor(math.log10(s))))
    return f"{v:.{decimals}f}"


def std_str(std: Any) -> str:
    s = num(std)
    return "—" if s is None else f"{s:.2g}"


def _stats(values, outlier=None) -> dict | None:
    """n, mean, RMS and max of the finite values that are not flagged in `outlier` (the figures' poses)."""
    out = outlier or [False] * len(values or [])
    vals = [num(v) for v, o in zip(values or [], out) if not o]
    vals = [v for v in vals if v is not None]
    if not vals:
        return None
    return {"n": len(vals), "mean_mm": sum(vals) / len(vals),
            "rms_mm": math.sqrt(sum(v * v for v in vals) / len(vals)), "max_mm": max(vals)}


def model_label(model: list[str]) -> str:
    return " + ".join(k.replace("_", " ") for k in model) or "geometric"


def accuracy(answer: dict) -> dict:
    """The error table of the answer: per model (geometric; final when the diagnosis extended it), the fit
    and held-out mean / RMS / max in mm. Stored scalars are used where the answer has them; the held-out
    mean (and max of the geometric model) come from the stored per-pose held-out distances."""
    m = answer.get("metrics") or {}
    d = answer.get("diagnosis") or {}
    pp = d.get("per_pose") or {}
    final_fit = {"mean_mm": num(m.get("mean_mm")), "rms_mm": num(m.get("rms_mm")), "max_mm": num(m.get("max_mm"))}
    fh = _stats(pp.get("final_holdout_mm"), pp.get("final_outlier"))
    final_ho = {"n": fh["n"] if fh else m.get("n_poses"), "mean_mm": fh and fh["mean_mm"],
                "rms_mm": num(m.get("holdout_rms_mm")), "max_mm": num(m.get("holdout_max_mm"))}
    model = list(answer.get("model") or ["geometric"])
    rows = []
    if d.get("geometric") and model != ["geometric"]:
        g = d["geometric"]
        gh = _stats(pp.get("geometric_holdout_mm"), pp.get("geometric_outlier"))
        rows.append({"model": "geometric", "fit": {"mean_mm": None, "rms_mm": num(g.get("rms_mm")),
                                                   "max_mm": num(g.get("max_mm"))},
                     "holdout": {"n": gh and gh["n"], "mean_mm": gh and gh["mean_mm"],
                                 "rms_mm": num(g.get("holdout_rms_mm")), "max_mm": gh and gh["max_mm"]}})
    rows.append({"model": model_label(model), "final": True, "fit": final_fit, "holdout": final_ho})
    out = {"unit": "mm", "models": rows, "note": HOLDOUT_NOTE + " " + FIT_NOTE}
    if d:
        out["noise_floor_mm"] = num(d.get("noise_floor_mm"))
    return out


def plot_list(answer: dict) -> list[dict]:
    """The plots this answer can draw: [{"name", "title"}]; `finding-k` is the k-th finding (1-based), present
    only for findings that carry a regressor plot."""
    d = answer.get("diagnosis") or {}
    pp = d.get("per_pose") or {}
    out = []
    if pp.get("geometric_holdout_mm") and pp.get("final_holdout_mm"):
        out.append({"name": "errors", "title": "Held-out error per pose, geometric model and final model"})
        out.append({"name": "distribution", "title": "Distribution of the held-out error per pose"})
    for k, f in enumerate(d.get("findings") or [], 1):
        p = f.get("plot") or {}
        if p.get("x") and p.get("residual_mm"):
            out.append({"name": f"finding-{k}",
                        "title": f"Finding {k}, {finding_title(f)}: residual against {p.get('x_label', 'its regressor')}"})
    return out


def finding_title(f: dict) -> str:
    kind = str(f.get("kind", "")).replace("_", " ")
    joints = ", ".join(f.get("joints") or [])
    harmonic = f" (harmonic {f['harmonic']})" if f.get("harmonic") is not None else ""
    return f"{kind} on {joints}{harmonic}" if joints else f"{kind}{harmonic}"


LEAST_DETERMINED = 3
"""How many geometric parameters per unit the report lists as the least well determined (largest std)."""


def observability(answer: dict) -> dict | None:
    """What the measured pose set observes, from the answer's `identifiability`, `metrics` and `parameters`:
    size, rank of the identifiable set, condition number and observability index O1 (column-normalised
    Jacobian), whether it identifies all the model's structure can, what it cannot (unidentifiable, frozen
    joints, redundant, without effect), and per unit the LEAST_DETERMINED geometric parameters with the
    largest std. None without an identifiability block."""
    ident = answer.get("identifiability")
    if not isinstance(ident, dict) or not ident:
        return None
    geometric = [p for p in answer.get("parameters") or [] if not p.get("effect") and num(p.get("std")) is not None]
    least: dict[str, list[dict]] = {}
    for p in geometric:
        least.setdefault(str(p.get("unit") or ""), []).append(p)
    least = {u: sorted(ps, key=lambda p: -num(p["std"]))[:LEAST_DETERMINED] for u, ps in least.items()}
    return {"n_poses": (answer.get("metrics") or {}).get("n_poses"), "rank": ident.get("rank"),
            "n_parameters": ident.get("n_parameters"), "condition_number": num(ident.get("condition_number")),
            "observability_index": num(ident.get("observability_index")), "complete": ident.get("complete"),
            "unidentifiable": list(ident.get("unidentifiable") or []),
            "frozen_joints": list(ident.get("frozen_joints") or []),
            "redundant": list(ident.get("redundant") or []), "nonfunctional": list(ident.get("nonfunctional") or []),
            "least_determined": least}
