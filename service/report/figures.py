"""The figures of a calibration, from its stored answer JSON only: one source for the API answer, the report
and the plots.

`accuracy(answer)` is the error table (mean, RMS, max; ISO 9283 AP) the service adds to
`GET /calibrations/{id}`; `plot_list(answer)` names the plots that answer can draw; the formatters are the
ones the HTML report uses, so a number in the JSON appears in the page as `mm(value)` / `pct(value)`.
"""
from __future__ import annotations

import math
from typing import Any

from calib_core.diagnosis import named_joints

HOLDOUT_NOTE = ("held-out: every pose predicted by the model fitted without it (5-fold cross-validation), "
                "the poses the model names as outliers left out. "
                "ISO 9283 positional accuracy AP = distance between the command position and the barycentre "
                "of the attained positions; with one measurement per pose the barycentre is that measurement, "
                "so AP per pose is the held-out distance and the table gives its mean and max over the poses.")
ALL_NOTE = ("holdout_all: the same held-out distances over every pose of the calibration, outliers included: the "
            "same poses for every model, what the headline compares.")
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
    and held-out mean / RMS / max in mm, each figure defined once with the poses it counts:

    - `holdout`: the poses that model names as outliers left out (`n` counted of `poses`, `outliers_left_out`),
      as the fit and the diagnosis score it (`metrics.holdout_rms_mm`, `diagnosis.geometric.holdout_rms_mm`);
    - `holdout_all`: every pose of the calibration counted (`n` = `poses`), the same poses for every model:
      the figure the report's headline compares (`headline`: geometric and final RMS over every pose and the
      gain between them).

    Stored scalars are used where the answer has them; means and maxima, and the geometric model's figure over
    every pose, come from the stored per-pose held-out distances. `counts` says what a pose is (rows, markers,
    virtual points of 6-D rows)."""
    m = answer.get("metrics") or {}
    d = answer.get("diagnosis") or {}
    pp = d.get("per_pose") or {}
    c = counts(answer)
    total = c["points"]
    final_fit = {"mean_mm": num(m.get("mean_mm")), "rms_mm": num(m.get("rms_mm")), "max_mm": num(m.get("max_mm"))}
    n_out = len(m.get("outliers") or [])
    fh = _stats(pp.get("final_holdout_mm"), pp.get("final_outlier"))
    fa = _stats(pp.get("final_holdout_mm"))
    final_ho = {"n": fh["n"] if fh else (total - n_out if total is not None else None), "poses": total,
                "outliers_left_out": n_out, "mean_mm": fh and fh["mean_mm"],
                "rms_mm": num(m.get("holdout_rms_mm")), "max_mm": num(m.get("holdout_max_mm"))}
    final_all = {"n": total, "mean_mm": fa["mean_mm"] if fa else (final_ho["mean_mm"] if not n_out else None),
                 "rms_mm": num(m.get("holdout_rms_with_outliers_mm")) if n_out else final_ho["rms_mm"],
                 "max_mm": fa["max_mm"] if fa else (final_ho["max_mm"] if not n_out else None)}
    if final_all["rms_mm"] is None and fa:
        final_all["rms_mm"] = fa["rms_mm"]
    model = list(answer.get("model") or ["geometric"])
    rows = []
    if d.get("geometric") and model != ["geometric"]:
        g = d["geometric"]
        gh = _stats(pp.get("geometric_holdout_mm"), pp.get("geometric_outlier"))
        ga = _stats(pp.get("geometric_holdout_mm"))
        g_out = sum(bool(o) for o in pp.get("geometric_outlier") or [])
        ho = {"n": gh and gh["n"], "poses": total, "outliers_left_out": g_out, "mean_mm": gh and gh["mean_mm"],
              "rms_mm": num(g.get("holdout_rms_mm")), "max_mm": gh and gh["max_mm"]}
        every = ({"n": ga["n"], "mean_mm": ga["mean_mm"], "rms_mm": ga["rms_mm"] if g_out else ho["rms_mm"],
                  "max_mm": ga["max_mm"]} if ga else {"n": total, "mean_mm": None, "rms_mm": None, "max_mm": None})
        rows.append({"model": "geometric", "fit": {"mean_mm": None, "rms_mm": num(g.get("rms_mm")),
                                                   "max_mm": num(g.get("max_mm"))},
                     "holdout": ho, "holdout_all": every})
    rows.append({"model": model_label(model), "final": True, "fit": final_fit, "holdout": final_ho,
                 "holdout_all": final_all})
    out = {"unit": "mm", "models": rows, "counts": c, "note": HOLDOUT_NOTE + " " + FIT_NOTE + " " + ALL_NOTE}
    g_all = num(rows[0]["holdout_all"]["rms_mm"]) if len(rows) > 1 else None
    f_all = num(final_all["rms_mm"])
    out["headline"] = {"poses": total, "geometric_rms_mm": g_all, "final_rms_mm": f_all,
                       "gain_pct": 100.0 * (g_all - f_all) / g_all if g_all and f_all is not None else None}
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


def step_title(f: dict) -> str | None:
    """A step in the session (an `unexplained` finding of form `step[<what> @ <place>]`) in words: what stepped
    (`a step in the session: T1's zero`); None for any other finding."""
    form = str(f.get("form", ""))
    if f.get("kind") != "unexplained" or not form.startswith("step[") or " @ " not in form:
        return None
    what = form[len("step["):form.index(" @ ")]
    said = {"robot": "the robot against the tracker", "target": "the target on its flange"}.get(what, f"{what}'s zero")
    return f"a step in the session: {said}"


def finding_title(f: dict) -> str:
    """`joint compliance on R6`, named for its significant joints (`named_joints`); a correction (kind "correction") by the form it follows, which the prose around it
    calls a correction; a step in the session by what stepped."""
    step = step_title(f)
    if step:
        return step
    kind = str(f.get("follows") if f.get("kind") == "correction" and f.get("follows") else f.get("kind", ""))
    kind = kind.replace("_", " ")
    named, others = named_joints(f)
    joints = ", ".join(named)
    harmonic = f" (harmonic {f['harmonic']})" if f.get("harmonic") is not None else ""
    others = f" ({others})" if others else ""
    return f"{kind} on {joints}{harmonic}{others}" if joints else f"{kind}{harmonic}"


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


# --- counts: what the figures count --------------------------------------------------------------------------

VIRTUAL_MARK = "~"
"""A 6-D row enters the fit as its point and three virtual points named `{point}~x|y|z` (calib_core.orientation)."""


def counts(answer: dict) -> dict:
    """What the answer's figures count, from its per-pose ids and its model: `points` (the rows of the fit, what
    every held-out and fit figure counts), `rows` (the uploaded CSV rows among them), `virtual_points` (the
    three points each 6-D row adds), `six_d_rows`, `markers` (the model's targets) and `poses` (rows / markers
    when a pose measures several markers, None when the rows do not divide evenly). Without per-pose ids (a
    geometric calibration) rows = points."""
    m = answer.get("metrics") or {}
    pp = (answer.get("diagnosis") or {}).get("per_pose") or {}
    ids = [str(i) for i in pp.get("point") or []]
    points = m.get("n_poses") if m.get("n_poses") is not None else (len(ids) or None)
    virtual = sum(VIRTUAL_MARK in i for i in ids)
    targets = [t for t in (answer.get("calibrated_model") or {}).get("targets") or []
               if VIRTUAL_MARK not in str(t.get("name", "") if isinstance(t, dict) else t)]
    markers = max(1, len(targets))
    rows = None if points is None else points - virtual
    poses = rows if markers == 1 else (rows // markers if rows is not None and rows % markers == 0 else None)
    return {"points": points, "rows": rows, "virtual_points": virtual, "six_d_rows": virtual // 3,
            "markers": markers, "poses": poses}


def counted_word(c: dict) -> str:
    """What one held-out or fit figure counts: "poses" when every point is a pose, else "points"."""
    return "poses" if c.get("virtual_points", 0) == 0 and c.get("markers", 1) == 1 else "points"


# --- units: one spelling each, in the units a cell engineer reads -------------------------------------------

RAD_TO_ARCMIN = 60.0 * 180.0 / math.pi
COMPLIANCE_UNIT = "arcmin/(100 N*m)"
"""A joint's compliance: arc-minutes it gives way per 100 N*m (about 10 kg at 1 m) of load."""


def show_unit(unit: Any, angle_unit: str = "deg") -> tuple[str, float]:
    """(the unit the report prints, the factor from the answer's unit to it) for a parameter's unit: angles in
    the model's angle unit (the report's header), compliances in arc-min per 100 N*m, scale factors in ppm;
    every other unit as the answer spells it."""
    u = str(unit or "").replace(" ", "")
    if u == "rad":
        return ("deg", 180.0 / math.pi) if angle_unit == "deg" else ("rad", 1.0)
    if u in ("rad/N*m", "rad/(N*m)", "rad/Nm"):
        return COMPLIANCE_UNIT, RAD_TO_ARCMIN * 100.0
    if u == "1":
        return "ppm", 1e6
    if u.startswith("1/"):
        return f"ppm/{u[2:]}", 1e6
    return str(unit or ""), 1.0


def shown(p: dict, angle_unit: str = "deg") -> dict:
    """A parameter as the report prints it: value, std, nominal in `show_unit`'s unit."""
    label, k = show_unit(p.get("unit"), angle_unit)
    scale = (lambda v: None if num(v) is None else num(v) * k)  # noqa: E731
    return {"name": p.get("name"), "unit": label, "factor": k, "value": scale(p.get("value")),
            "std": scale(p.get("std")), "nominal": scale(p.get("nominal"))}


def joint_size(p: dict) -> str | None:
    """A cause's parameter in the units of the plain-words summary: arc-min at the joint, arc-min per 100 N*m,
    mm, ppm, mm or ppm per deg C (or per hour); None for a unit with no such reading."""
    u = str(p.get("unit") or "").replace(" ", "")
    v, s = num(p.get("value")), num(p.get("std"))
    if v is None:
        return None
    if u == "rad":
        return f"{_plain(v * RAD_TO_ARCMIN, s and s * RAD_TO_ARCMIN)} arc-min"
    if u in ("rad/N*m", "rad/(N*m)", "rad/Nm"):
        return f"{_plain(v * RAD_TO_ARCMIN * 100, s and s * RAD_TO_ARCMIN * 100)} arc-min per 100 N*m"
    if u == "mm":
        return f"{_plain(v, s)} mm"
    if u == "mm/N":
        return f"{_plain(v * 100, s and s * 100)} mm per 100 N"
    if u == "1":
        return f"{_plain(v * 1e6, s and s * 1e6)} ppm"
    per = {"degC": "deg C", "h": "hour"}
    if "/" in u and u.split("/", 1)[1] in per:  # a thermal drift: per degree, or per hour without a temperature
        top, under = u.split("/", 1)
        if top == "mm":
            return f"{_plain(v, s)} mm per {per[under]}"
        if top == "1":
            return f"{_plain(v * 1e6, s and s * 1e6)} ppm per {per[under]}"
    return None


def _plain(v: float, s: float | None) -> str:
    """A size in plain words: to its std's precision (as `sig`), else 3 significant digits."""
    return sig(v, s) if num(s) is not None and s > 0 else f"{v:.3g}"
