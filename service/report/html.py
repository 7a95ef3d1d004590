"""The calibration report: one HTML page from the stored answer (as `GET /calibrations/{id}` returns it).

Readable on a laptop (a 60-em column) and printable (A4, no navigation, figures and tables kept whole).
Plots are `<img>` of `plots/{name}.png` (relative to the report's URL) or, with `inline`, the PNGs
themselves as data: URIs, so the saved page can be mailed on its own. A small script marks the `<body>`
with `data-images-*` attributes once every image has loaded (used by the browser test).
"""
from __future__ import annotations

import base64
import re
from datetime import datetime, timezone
from html import escape
from typing import Callable

from calib_core.diagnosis import follows_what, is_named, named_joints

from .figures import (accuracy, counted_word, finding_title, joint_size, mm, model_label, step_title,
                      num, observability, pct, plot_list, show_unit, shown, sig, std_str)

CSS = """
:root { --ink: #1d2330; --mute: #5c6475; --line: #d9dde5; --geo: #e08a2c; --fin: #1f5fa8; --ok: #2b8a3e; }
* { box-sizing: border-box; }
body { margin: 0; color: var(--ink); background: #f6f7f9;
       font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; }
main { max-width: 62em; margin: 0 auto; padding: 1.5em 1.5em 3em; background: #fff; }
h1 { font-size: 1.6em; margin: 0 0 .2em; }
h2 { font-size: 1.2em; margin: 1.8em 0 .5em; padding-bottom: .2em; border-bottom: 2px solid var(--line); }
h3 { font-size: 1.05em; margin: 1.2em 0 .3em; }
.sub { color: var(--mute); margin: 0 0 1em; font-size: .92em; }
.cards { display: grid; grid-template-columns: repeat(auto-fit, minmax(10em, 1fr)); gap: .8em; margin: 1em 0; }
.card { border: 1px solid var(--line); border-radius: 6px; padding: .6em .8em; }
.card .k { color: var(--mute); font-size: .82em; }
.card .v { font-size: 1.45em; font-weight: 600; font-variant-numeric: tabular-nums; }
.card .v.cause { font-size: 1.05em; }
.card .v small { font-size: .6em; font-weight: 400; color: var(--mute); }
.explain { background: #f1f5fb; border-left: 4px solid var(--fin); padding: .6em .9em; }
.explain.warn { background: #fdf3e7; border-left-color: #d9822b; }
table { border-collapse: collapse; width: 100%; margin: .4em 0 .8em; font-size: .92em; }
th, td { padding: .3em .55em; border-bottom: 1px solid var(--line); text-align: left; vertical-align: top; }
td.n, th.n { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
thead th { background: #eef0f4; }
tr.final td { font-weight: 600; }
.note { color: var(--mute); font-size: .85em; }
figure { margin: .8em 0 1.2em; }
figure img { display: block; width: 100%; height: auto; border: 1px solid var(--line); border-radius: 4px; }
figcaption { color: var(--mute); font-size: .85em; margin-top: .3em; }
.finding { border: 1px solid var(--line); border-radius: 6px; padding: .2em 1em .6em; margin: .8em 0; }
.finding .gain { color: var(--ok); font-weight: 600; }
.verdict { border: 2px solid var(--fin); border-radius: 6px; padding: .5em 1em; margin: 1em 0; }
.verdict p { margin: .25em 0; }
.verdict b { font-variant-numeric: tabular-nums; }
ol.causes > li, ol.next > li { margin: .35em 0; }
ul.evidence { margin: .3em 0 .6em; padding-left: 1.2em; }
.tag { display: inline-block; padding: 0 .45em; border-radius: 3px; background: #eef0f4; font-size: .85em; }
code { font-size: .9em; }
nav a { margin-right: 1em; }
@page { size: A4; margin: 14mm 12mm; }
@media print {
  body { background: #fff; font-size: 10pt; }
  main { max-width: none; padding: 0; }
  .noprint { display: none !important; }
  h2 { break-after: avoid; }
  figure, .finding, .card, tr { break-inside: avoid; }
  a { color: inherit; text-decoration: none; }
}
"""

SCRIPT = """
(function () {
  function check() {
    var imgs = Array.prototype.slice.call(document.images);
    var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
    document.body.setAttribute("data-images-total", String(imgs.length));
    document.body.setAttribute("data-images-broken", String(broken.length));
    document.body.setAttribute("data-images-checked", "yes");
  }
  if (document.readyState === "complete") { check(); } else { window.addEventListener("load", check); }
})();
"""


def _sentence(text, cap: bool = True) -> str:
    """A clause of the diagnosis as a sentence: capital first letter (`cap`; after a colon, not), a full stop; a
    known cut-off clause completed ("read it as a correction, not as the joint's" ends without its noun)."""
    t = " ".join(str(text or "").split()).strip().rstrip(";,")
    if not t:
        return ""
    if t.endswith("not as the joint's"):
        t += " own size"
    t = (t[0].upper() if cap else t[0]) + t[1:]
    return t if t[-1] in ".!?" else t + "."


_VALUE = re.compile(r"\b([\w$^.]+) = (-?[\d.]+(?:e[-+]?\d+)?) \+/- ([\d.]+(?:e[-+]?\d+)?) "
                    r"(rad/\(N\*m\)|rad/N\*m|rad|1)(?![\w/*(])")


def _units_of(text: str, angle_unit: str) -> str:
    """`NAME = V +/- S UNIT` in a diagnosis text, in the report's units (`show_unit`: angles in the header's unit,
    compliances per 100 N*m, scale in ppm), the number to the precision of its std."""
    def one(mt: re.Match) -> str:
        unit, k = show_unit(mt.group(4), angle_unit)
        v, sd = float(mt.group(2)) * k, float(mt.group(3)) * k
        return f"{mt.group(1)} = {sig(v, sd)} +/- {std_str(sd)} {unit}"
    return _VALUE.sub(one, text)


def _clauses(text) -> list[str]:
    """An evidence string of the diagnosis, split at its semicolons into sentences."""
    return [c for c in (_sentence(part) for part in str(text or "").split("; ")) if c]


def _e(v) -> str:
    return escape("" if v is None else str(v))


def _when(iso: str | None) -> str:
    try:
        return datetime.fromisoformat(iso).astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    except (TypeError, ValueError):
        return iso or ""


def _g3(v) -> str:
    v = num(v)
    return "—" if v is None else f"{v:.3g}"


def _dev(p: dict) -> str:
    """value - nominal, printed like the value."""
    v, n = num(p.get("value")), num(p.get("nominal"))
    if v is None or n is None:
        return "—"
    return ("+" if v - n >= 0 else "") + sig(v - n, p.get("std"))


def _row(cells: list[tuple[str, bool]], cls: str = "") -> str:
    tds = "".join(f'<td class="n">{c}</td>' if n else f"<td>{c}</td>" for c, n in cells)
    return f'<tr class="{cls}">{tds}</tr>' if cls else f"<tr>{tds}</tr>"


def _img(src: str, alt: str, caption: str) -> str:
    return (f'<figure><img src="{_e(src)}" alt="{_e(alt)}" width="880" height="396" loading="eager">'
            f"<figcaption>{caption}</figcaption></figure>")


PLAIN = {
    "backlash": "{j} shift{s} by {its} gear play when {its} load changes sign",
    "joint_compliance": "{j} give{s} way under {its} load like a spring",
    "link_deflection": "the links bend under the load they carry",
    "cyclic_joint_error": "{j} has an angle error that repeats with its turn (gear eccentricity or a reducer stage)",
    "joint_scale": "{j} moves more or less than commanded, in proportion to its travel (gear ratio or encoder scale)",
    "axis_straightness": "the linear axis {j} is not straight: the carriage swerves and tilts as it travels",
    "thermal_drift": "the robot and the tracker drift apart with temperature or time",
    "base_compliance": "the robot's mount (pedestal, platform) tilts under the robot's own overturning moment",
    "mass_data": "the model's mass data are off, so the loads the other causes follow are too",
    "unexplained": "structure no named cause explains, corrected by offsets that follow the joints",
}
NEXT = {
    "backlash": "Check the gear play of {j} (preload, wear); the calibrated model compensates it where the load sign "
                "is known.",
    "joint_compliance": "Keep the payload data in the robot controller right: the compensation of {j} follows the load.",
    "link_deflection": "Keep the payload data right: the compensation of the link bending follows the load.",
    "cyclic_joint_error": "If the error grows over time, have the reducer of {j} inspected; the model compensates it.",
    "joint_scale": "Check the gear ratio or encoder setting of {j} in the controller.",
    "axis_straightness": "Have the guide of {j} checked if the straightness matters beyond the compensation.",
    "thermal_drift": "Calibrate at the production temperature, or keep the temperature recorded with each run.",
    "base_compliance": "Stiffen or re-level the mount if its tilt matters beyond the compensation; keep the payload "
                       "data right: the compensation follows the robot's overturning moment.",
}


def _joints(f: dict) -> str:
    """The joints a cause is named for, in words (its significant ones, `named_joints`)."""
    js, _ = named_joints(f)
    return ", ".join(js[:-1]) + " and " + js[-1] if len(js) > 1 else (js[0] if js else "the robot")


def _few(items: list[str], k: int = 4) -> str:
    return ", ".join(items[:k]) + (f" and {len(items) - k} more (the parameter table)" if len(items) > k else "")


def _by_name(answer: dict) -> dict:
    return {p.get("name"): p for p in answer.get("parameters") or []}


def _cause_sizes(f: dict, table: dict) -> tuple[list[str], list[str], list[str]]:
    """A finding's parameters in plain-words units, quoted from the parameter table (the model in use): the
    significant ones (|value| >= 2 std), the names within 2 std of zero, and notes where the finding's value
    (when it was found) differs from the table's by more than its std."""
    sizes, weak, moved = [], [], []
    for fp in f.get("parameters") or []:
        p = table.get(fp.get("name"), fp)
        v, sd = num(p.get("value")), num(p.get("std"))
        text = joint_size(p)
        if text is None or v is None:
            continue
        fv, fs = num(fp.get("value")), num(fp.get("std"))
        if p is not fp and fv is not None and abs(fv - v) > max(fs or 0.0, sd or 0.0, 1e-300):
            moved.append(f"{p.get('name')} {joint_size(fp)}")
        if sd is not None and abs(v) < 2 * sd:
            weak.append(f"{p.get('name')} {text}")
        else:
            sizes.append(f"{p.get('name')} {text}")
    return sizes, weak, moved


def render(answer: dict, png: Callable[[str], bytes] | None = None) -> str:
    """The report page. `png(name)` gives a plot's bytes to inline them; without it the page links
    `plots/{name}.png` relative to its own URL (`/calibrations/{id}/report`)."""
    def src(name: str) -> str:
        if png is None:
            return f"plots/{name}.png"
        return "data:image/png;base64," + base64.b64encode(png(name)).decode("ascii")

    cid = answer.get("id", "")
    model_json = answer.get("calibrated_model") or {}
    robot = model_json.get("name") or "robot"
    units = model_json.get("units") or {}
    angle_unit = units.get("angle", "deg")
    m = answer.get("metrics") or {}
    d = answer.get("diagnosis") or {}
    acc = answer.get("accuracy") or accuracy(answer)
    plots = {p["name"]: p for p in (answer.get("plots") or plot_list(answer))}
    findings = d.get("findings") or []
    table = _by_name(answer)
    final_label = model_label(answer.get("model") or ["geometric"])
    c = acc.get("counts") or {}
    word = counted_word(c) if c else "poses"
    total = c.get("points", m.get("n_poses"))
    rows = acc.get("models") or []
    geo = rows[0] if len(rows) > 1 else None
    fin = rows[-1] if rows else {"holdout": {}, "fit": {}, "holdout_all": {}}
    fin_all = fin.get("holdout_all") or fin["holdout"]
    head = acc.get("headline") or {}
    cut = d.get("search_complete") is False
    out: list[str] = []
    w = out.append
    w("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
      "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
      f"<title>Calibration report: {_e(robot)} ({_e(cid[:8])})</title><style>{CSS}</style></head><body><main>")
    w(f"<h1>Calibration report: {_e(robot)}</h1>")
    w(f'<p class="sub">Calibration <code>{_e(cid)}</code> · {_e(_when(answer.get("created_at")))} · '
      f'model: <b>{_e(final_label)}</b> · lengths in {_e(units.get("length", "mm"))}, angles in {_e(angle_unit)} '
      f'(sizes at a joint in arc-min) · every error at the tool in mm</p>')
    w('<nav class="noprint"><a href="#verdict">Verdict</a><a href="#causes">Causes</a><a href="#next">Next</a>'
      '<a href="#evidence">Evidence</a><a href="#parameters">Parameters</a><a href="#identifiability">Observability</a>' +
      (f'<a href="../{_e(cid)}">JSON</a>' if png is None else "") + "</nav>")

    # --- the verdict, three lines
    named = [f for f in findings if is_named(f)]
    faded = [f for f in findings if f.get("kind") != "correction" and f.get("significant") is False]
    corrections = [f for f in findings if f not in named and f not in faded]
    w('<div class="verdict" id="verdict">')
    if geo is not None and head.get("geometric_rms_mm") is not None:
        w(f'<p><b>Accuracy:</b> the calibrated robot is off by <b>{mm(head.get("final_rms_mm"))} mm RMS</b> at the tool '
          f'on poses the model did not fit, against <b>{mm(head.get("geometric_rms_mm"))} mm</b> with the geometric '
          f'model alone: <b>{pct(head.get("gain_pct"))} less</b> (held out, all {_e(total)} calibration {word} '
          f'counted).</p>')
    else:
        w(f'<p><b>Accuracy:</b> the calibrated robot is off by <b>{mm(fin_all.get("rms_mm"))} mm RMS</b> at the tool '
          f'on poses the model did not fit (held out, all {_e(total)} calibration {word} counted).</p>')
    if not d:
        w("<p><b>Causes:</b> not looked for (a <code>geometric</code> calibration: run the <code>auto</code> model "
          "to have the residual diagnosed).</p>")
    elif named or corrections or faded:
        parts = [finding_title(f) for f in named] + [f"a correction ({finding_title(f)})" for f in corrections] + [
            f"{finding_title(f)}, explained by the causes after it" for f in faded]
        w(f'<p><b>Cause{"s" if len(parts) > 1 else ""}{" so far" if cut else ""}:</b> {_e("; ".join(parts))}'
          f'{" (the search stopped at its time budget)" if cut else ""}.</p>')
    else:
        w(f"<p><b>Causes:</b> none beyond the geometry ({_e(d.get('verdict') or 'nothing the data can show')}).</p>")
    actions = _next_steps(answer, findings, cid)
    w(f"<p><b>Next:</b> {actions[0]}</p>")
    w("</div>")
    for warning in answer.get("warnings") or []:
        w(f'<p class="explain warn"><b>Caution.</b> {_e(_sentence(warning))}</p>')
    if cut:
        w(f'<p class="explain warn"><b>Caution.</b> {_e(_sentence(d.get("verdict")))[:-1]}: causes not reached were '
          f'never tested (see the notes).</p>')

    # --- before / after, one table
    w('<h2 id="accuracy">Before and after</h2>')
    w(f'<table><thead><tr><th>model</th><th class="n">{word} counted</th><th class="n">held-out mean</th>'
      '<th class="n">held-out RMS</th><th class="n">held-out max</th><th class="n">fit RMS</th></tr></thead><tbody>')
    nominal = d.get("nominal") or {}
    if num(nominal.get("holdout_rms_mm")) is not None:
        w(_row([("before calibration (nominal model, base and tool placed)", False), ("—", True), ("—", True),
                (mm(nominal.get("holdout_rms_mm")), True), (mm(nominal.get("holdout_max_mm")), True),
                (mm(nominal.get("rms_mm")), True)]))
    for r in rows:
        a_ = r.get("holdout_all") or r["holdout"]
        h = r["holdout"]
        same = not h.get("outliers_left_out")
        fit_all = r["fit"].get("rms_mm") if same else (num(m.get("rms_with_outliers_mm")) if r.get("final") else None)
        w(_row([(_e(r["model"]), False), (f'all {_e(a_.get("n"))}', True), (mm(a_.get("mean_mm")), True),
                (mm(a_.get("rms_mm")), True), (mm(a_.get("max_mm")), True), (mm(fit_all), True)],
               "final" if r.get("final") else ""))
        if not same:
            one = h.get("outliers_left_out") == 1
            w(_row([(f'{_e(r["model"])}, the {_e(h.get("outliers_left_out"))} {word[:-1] if one else word} it names '
                     f'{"an outlier" if one else "outliers"} left out',
                     False), (_e(h.get("n")), True), (mm(h.get("mean_mm")), True), (mm(h.get("rms_mm")), True),
                    (mm(h.get("max_mm")), True), (mm(r["fit"].get("rms_mm")), True)]))
    w("</tbody></table>")
    w(f'<p class="note">Held-out: every {word[:-1]} predicted by the model fitted without it (5-fold cross-validation);'
      f' the headline counts every one of the {_e(total)} {word}, the same ones for every model. Rows naming outliers: '
      f'the figure as the fit and the diagnosis score that model. Mean and max are ISO 9283 AP mean and max (one '
      f'measurement per {word[:-1]}). Fit: the {word} the model was fitted on (in-sample), always better than '
      f'held out. Noise floor (what a perfect model would leave): {mm(acc.get("noise_floor_mm"))} mm RMS.</p>'
      if d else
      f'<p class="note">Held-out: every {word[:-1]} predicted by the model fitted without it (5-fold '
      f'cross-validation). Mean and max are ISO 9283 AP mean and max. Fit: in-sample.</p>')

    # --- causes in plain words
    if d:
        w('<h2 id="causes">What the robot gets wrong, in plain words</h2>')
        if not findings:
            why = d.get("verdict") or "nothing the data can show beyond the geometric model"
            w(f"<p>No cause beyond the geometry: {_e(_sentence(why, False))}</p>")
        else:
            w('<ol class="causes">')
            for f in findings:
                kind = str(f.get("kind", ""))
                j = _joints(f)
                what = step_title(f) or PLAIN.get(kind, finding_title(f))
                named, others = named_joints(f)
                one = len(named) <= 1
                title = _sentence(what.format(j=j, s="s" if one else "", its="its" if one else "their"))
                if others:
                    title = title[:-1] + f" ({others})."
                if kind == "correction":
                    title = (f"A correction that follows {follows_what(f)} (not a physical cause: "
                             f"{f.get('bound') or 'its size is not physical'}).")
                elif f.get("physical") is False:
                    title = (f"A correction following {j} (fitted as {kind.replace('_', ' ')}; its size is not "
                             f"physical, so it is not named as that cause).")
                elif f.get("significant") is False:
                    title = title[:-1] + (" — confirmed when it was found, but in the final model its size is within "
                                          "2 std of zero: the causes after it explain it.")
                sizes, weak, moved = _cause_sizes(f, table)
                bits = [f"<b>{_e(title)}</b>"]
                if f.get("physical") is not False and sizes:
                    bits.append("Size: " + _e(_few(sizes)) + ".")
                if weak and f.get("physical") is not False:
                    bits.append(f"In the final model within 2 std of zero (no size the data show): "
                                f"{_e(_few(weak))}.")
                if num(f.get("effect_rms_mm")) is not None:
                    bits.append(f"At the tool: {mm(f.get('effect_rms_mm'))} mm RMS over the calibration {word}.")
                if kind == "unexplained" and f.get("follows"):
                    top = f["follows"][0]
                    share = num(top.get("share_pct"))
                    bits.append(f"It follows {_e(top.get('what'))}" +
                                (f" (explains {share:.0f} % of it)." if share is not None else "."))
                bits.append(f'Held-out error before it {mm(f.get("holdout_rms_before_mm"))} mm, with it '
                            f'{mm(f.get("holdout_rms_after_mm"))} mm: <span class="gain">{pct(f.get("gain_pct"))} '
                            f'less</span>.')
                alt = f.get("indistinguishable_from") or []
                if alt:
                    bits.append("The data fit these as well (within 2 %): " +
                                _e(", ".join(finding_title(a) for a in alt)) + ".")
                if moved:
                    bits.append(_e(f"When the cause was found: {_few(moved)}; the sizes above are the final "
                                   f"model's (the parameter table)."))
                w("<li>" + " ".join(bits) + "</li>")
            w("</ol>")
            w(f'<p class="note">Sizes are the parameter table\'s values: angles at the joint in arc-min (1 deg = 60 '
              f'arc-min), compliances in arc-min per 100 N*m (about 10 kg at 1 m), scale in ppm. "At the tool": the '
              f'RMS displacement of the effect at the tool over the calibration {word}, as the diagnosis measured it '
              f'when it found the cause. Held-out figures per cause chain: each cause is added to the causes above it, '
              f'the first to the geometric model (the {word} each model names outliers left out).</p>')

    # --- next
    w('<h2 id="next">What to do next</h2><ol class="next">')
    for a_ in actions:
        w(f"<li>{a_}</li>")
    w("</ol>")

    # --- evidence
    w('<h2 id="evidence">Evidence</h2>')
    w("<h3>The measurements</h3><ul>")
    if c.get("virtual_points"):
        w(f'<li>{_e(c.get("rows"))} rows uploaded, {_e(c.get("six_d_rows"))} of them 6-D (position and '
          f'orientation): each 6-D row entered the fit as its point and 3 virtual points, so the fit and every figure '
          f'count {_e(total)} points ({_e(c.get("rows"))} + {_e(c.get("virtual_points"))} virtual).</li>')
    if c.get("markers", 1) > 1:
        poses = c.get("poses")
        w(f'<li>{_e(c.get("rows"))} rows from {_e(c.get("markers"))} markers'
          + (f': {_e(poses)} poses x {_e(c.get("markers"))} markers' if poses else "")
          + '; every figure counts rows (points), not poses.</li>')
    if not c.get("virtual_points") and c.get("markers", 1) == 1:
        w(f"<li>{_e(total)} measured poses, one point each.</li>")
    noise = answer.get("noise_model") or d.get("noise_model")
    if noise:
        w(f"<li>Noise model: {_e(_sentence(noise, False))}</li>")
    if d.get("noise_floor_basis"):
        w(f'<li>Noise floor {mm(d.get("noise_floor_mm"))} mm RMS: {_e(_sentence(d.get("noise_floor_basis"), False))}</li>')
    w("</ul>")
    if d.get("explanation"):
        w(f'<p class="explain">{_e(d["explanation"])}</p>')
    for name in ("errors", "distribution"):
        if name in plots:
            w(_img(src(name), plots[name]["title"], _e(plots[name]["title"]) +
                   (f". Orange: the geometric model; blue: the final model; green: the noise floor; the RMS in the "
                    f"legend is the headline's, over all {_e(total)} {word}." if name == "errors" else ".")))
    if d:
        for k, f in enumerate(findings, 1):
            tags = f'<span class="tag">{_e(str(f.get("kind", "")).replace("_", " "))}</span>' + (
                ' <span class="tag">correction, not a physical size</span>' if f.get("physical") is False else "")
            w(f'<div class="finding"><h3>Finding {k}: {_e(finding_title(f))} {tags}</h3>')
            clauses = _clauses(_units_of(str(f.get("evidence") or ""), angle_unit))
            w('<ul class="evidence">' + "".join(f"<li>{_e(x)}</li>" for x in clauses) + "</ul>")
            params = f.get("parameters") or []
            if params:
                w('<table><thead><tr><th>parameter</th><th class="n">value (final model)</th><th class="n">std</th>'
                  '<th>unit</th></tr></thead><tbody>')
                for p in params:
                    q = shown(p, angle_unit)
                    w(_row([(_e(q["name"]), False), (sig(q["value"], q["std"]), True),
                            (std_str(q["std"]), True), (_e(q["unit"]), False)]))
                w("</tbody></table>")
            name = f"finding-{k}"
            if name in plots:
                w(_img(src(name), plots[name]["title"], _e(plots[name]["title"]) +
                       ". Left: grey, what the model before this finding gets wrong at each pose; red, what the "
                       "identified effect predicts there (both along the effect's direction). Right: the two "
                       "against each other."))
            w("</div>")
        rejected = d.get("not_findings") or []
        if rejected:
            groups: dict = {}
            for r in rejected:
                key = (r.get("kind"), tuple(r.get("joints") or []), r.get("harmonic"))
                groups.setdefault(key, []).append(r)
            w("<h3>Candidates tested and not retained</h3><ul>")
            for (kind, joints, harmonic), rs in list(groups.items())[:12]:
                title = finding_title({"kind": kind, "joints": list(joints), "harmonic": harmonic})
                times = f" ({len(rs)} forms tested)" if len(rs) > 1 else ""
                w(f'<li>{_e(title[:1].upper() + title[1:])}{times}: {_e(_sentence(rs[0].get("why"), False))}</li>')
            if len(groups) > 12:
                w(f"<li>… and {len(groups) - 12} more (see the JSON)</li>")
            w("</ul>")
        if d.get("notes"):
            w('<p class="note">' + " ".join(_e(_sentence(n)) for n in d["notes"]) + "</p>")

    # --- parameters
    w('<h2 id="parameters">Parameters</h2>')
    w('<table><thead><tr><th>parameter</th><th class="n">value</th><th class="n">std</th><th class="n">nominal</th>'
      '<th class="n">value − nominal</th><th>unit</th><th>of</th></tr></thead><tbody>')
    for p in answer.get("parameters") or []:
        q = shown(p, angle_unit) if p.get("effect") else {**p, "factor": 1.0}
        nominal = q.get("nominal")
        w(_row([(_e(p.get("name")), False), (sig(q.get("value"), q.get("std")), True), (std_str(q.get("std")), True),
                (sig(nominal) if num(nominal) is not None else "—", True), (_dev(q), True),
                (_e(q.get("unit")), False), (_e(str(p.get("effect") or "geometry").replace("_", " ")), False)]))
    w("</tbody></table>")
    w(f'<p class="note">std: one standard deviation from the covariance of the fit (scaled by the residual). '
      f"Values are printed to the precision their std justifies. Geometry in the model's units; the causes' angles "
      f"in {_e(angle_unit)}, compliances in arc-min per 100 N*m, scale factors in ppm (the JSON keeps rad, "
      f"rad/(N*m) and 1). Base angles are absolute Z-Y-X Euler angles of the robot base in the measurement frame.</p>")

    # --- observability of the measured pose set
    obs = observability(answer)
    if obs:
        w('<h2 id="identifiability">Observability of the measured poses</h2>')
        w('<table class="obs"><tbody>')
        for label, value in (
                ("measured poses", _e(obs["n_poses"])),
                ("parameters identifiable from them", f'{_e(obs["rank"])} of {_e(obs["n_parameters"])}'),
                ("condition number (column-normalised Jacobian)", _g3(obs["condition_number"])),
                ("observability index O1", _g3(obs["observability_index"])),
                ("identifies all the model's structure can",
                 "—" if obs["complete"] is None else ("yes" if obs["complete"] else "<b>no</b>"))):
            w(_row([(label, False), (value, True)]))
        w("</tbody></table>")
        w('<p class="note">The condition number is the ratio of the best- to the worst-observed direction of the '
          "identifiable parameters (1 is ideal; the larger, the more one combination of them is left to the "
          "noise). O1 (Borm &amp; Menq) is the geometric mean of the singular values divided by the square root "
          "of the number of equations: larger is better; compare it between sets of the same size only. "
          "<code>POST /robots/{id}/plan</code> (<code>calib plan</code>) picks poses that observe the geometry "
          "better than random ones.</p>")
        if obs["unidentifiable"] or obs["frozen_joints"]:
            what = []
            if obs["unidentifiable"]:
                what.append(f'{len(obs["unidentifiable"])} parameter{"s" if len(obs["unidentifiable"]) > 1 else ""}'
                            f' the model\'s structure can identify but these poses cannot: '
                            f'{_e(", ".join(obs["unidentifiable"]))} (left at nominal)')
            if obs["frozen_joints"]:
                what.append(f'joints that never moved: {_e(", ".join(obs["frozen_joints"]))}')
            w(f'<p class="explain warn"><b>Not observed.</b> {"; ".join(what)}.</p>')
        least = obs["least_determined"]
        if least:
            w("<h3>Least well determined (largest standard deviation, per unit)</h3>")
            w('<table><thead><tr><th>parameter</th><th class="n">std</th><th>unit</th></tr></thead><tbody>')
            for unit, ps in least.items():
                for p in ps:
                    w(_row([(_e(p.get("name")), False), (std_str(p.get("std")), True), (_e(unit), False)]))
            w("</tbody></table>")
        red = obs["redundant"]
        if red:
            w("<h3>Not identifiable: confounded with others (fixed at nominal)</h3>")
            w('<table><thead><tr><th>parameter</th><th>confounded with</th></tr></thead><tbody>')
            for r in red:
                w(_row([(_e(r.get("name")), False), (_e(", ".join(r.get("confounded_with") or [])), False)]))
            w("</tbody></table>")
        if obs["nonfunctional"]:
            w('<p class="note">Without effect on the measured point: '
              f'{_e(", ".join(map(str, obs["nonfunctional"])))}</p>')
    base = answer.get("base_pose") or {}
    if base.get("position_mm"):
        w('<p class="note">Robot base in the measurement frame: ' +
          ", ".join(mm(v) for v in base["position_mm"]) + " mm.</p>")
    w(f'<p class="note">Every figure on this page comes from the stored calibration answer '
      f'<code>GET /calibrations/{_e(cid)}</code> (its <code>accuracy</code>, <code>diagnosis</code> and '
      f'<code>parameters</code>).</p>')
    w(f"</main><script>{SCRIPT}</script></body></html>")
    return "".join(out)


def _next_steps(answer: dict, findings: list[dict], cid: str) -> list[str]:
    """What to do next, most pressing first (HTML), from the answer's findings, outliers, notes and noise basis."""
    d = answer.get("diagnosis") or {}
    m = answer.get("metrics") or {}
    out = []
    if d.get("search_complete") is False:
        out.append("Run the diagnosis again with a longer time budget: causes not reached were never tested.")
    alts = [f for f in findings if f.get("indistinguishable_from") and f.get("significant") is not False]
    for f in alts:
        # two steps in the session: poses measured from now on come after both (the report asked for poses that
        # tell T1's zero from the target's step apart, as if the plan service could not rebuild a load)
        steps = [a for a in f["indistinguishable_from"] if step_title(f) and step_title(a)]
        if steps:
            others = ", or ".join(f"{_stepped(a)} (at {_e(str(a['form']).split(' @ ')[-1].rstrip(']'))})"
                                  for a in steps)  # step[target @ 108.5]: where in the session's clock
            out.append(f"Check the session's log {_e(_step_place(f))}: {_stepped(f)} stepped there, or {others}; the "
                       f"data fit both equally well, and no pose measured from now on can tell them apart (it comes "
                       f"after both).")
        # the plan service is suggested only for pairs it can rebuild (`plannable`, as the demo asks it)
        for plannable in (True, False):
            rivals = [a for a in f["indistinguishable_from"] if (a.get("plannable") is not False) == plannable
                      and not any(a is b for b in steps)]
            alt = [finding_title(a) for a in rivals]
            if not alt:
                continue
            why = (", as a cause fitted on a load identified from the data is not among its candidates"
                   if all("identified load" in str(a.get("form") or "") for a in rivals) else "")
            how = ("(<code>POST /robots/{id}/plan</code> with <code>purpose: diagnosis</code>)" if plannable else
                   "(chosen by hand: the plan service cannot rebuild "
                   f"{'this pair' if len(alt) == 1 else 'these pairs'} from the stored calibration{why})")
            out.append(f"Measure poses that tell {_e(finding_title(f))} apart from "
                       f"{_e(', '.join(alt)) if len(alt) <= 2 else f'{len(alt)} look-alike causes (listed above)'} "
                       f"{how}, then calibrate again: the data fit them equally well.")
    for f in findings:
        if step_title(f) and not any(step_title(a) for a in f.get("indistinguishable_from") or []):
            out.append(f"Check the session's log {_e(_step_place(f))}: {_stepped(f)} stepped there (a joint re-homed, "
                       f"the tracker, the base or the target moved); the calibrated model takes every new pose to be "
                       f"after it.")
        elif step_title(f):
            continue  # said with its look-alikes above
        elif f.get("kind") == "unexplained":
            top = (f.get("follows") or [{}])[0]
            out.append(f"Look for what the structure no named cause explains follows: "
                       f"{_e(top.get('what') or 'see the finding')}; "
                       f"until then the calibrated model corrects it.")
        elif f.get("physical") is False:
            out.append(f"Read {_e(finding_title(f))} as a correction, not as a property of the joint: do not use its "
                       f"values for maintenance.")
        elif f.get("significant") is False:  # no size in the final model: nothing to maintain or to tell apart
            continue
        elif f.get("kind") in NEXT:
            out.append(_e(NEXT[f["kind"]].format(j=_joints(f))))
    if m.get("outliers"):
        ids = [str(i) for i in m["outliers"]]
        out.append(f"Check or re-measure the {len(ids)} outlier{'s' if len(ids) > 1 else ''}: "
                   f"{_e(', '.join(ids[:10]))}{' …' if len(ids) > 10 else ''}.")
    if d and d.get("noise_floor_source") in ("assumed", "residual"):
        out.append("Measure some poses twice: the noise floor is then measured, not assumed.")
    if not d:
        out.append("Run the <code>auto</code> model to have what the geometry leaves diagnosed.")
    out.append(f"Use the calibrated model: <code>GET /calibrations/{_e(cid)}/model</code> (or <code>/urdf</code>), "
               f"or let the service compensate targets (<code>POST /calibrations/{_e(cid)}/compensate</code>).")
    return list(dict.fromkeys(out))  # once each: two corrections that follow the same thing read the same


def _stepped(f: dict) -> str:
    """What stepped in a step finding (`T1's zero`, `the target on its flange`), escaped."""
    return _e((step_title(f) or "").split(": ", 1)[-1])


def _step_place(f: dict) -> str:
    """Where a step finding sits in the session (`in time order between 85 and 89 (sequence 87)`), or ''."""
    return str(((f.get("follows") or [{}])[0]).get("detail") or "")
