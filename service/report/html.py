"""The calibration report: one HTML page from the stored answer (as `GET /calibrations/{id}` returns it).

Readable on a laptop (a 60-em column) and printable (A4, no navigation, figures and tables kept whole).
Plots are `<img>` of `plots/{name}.png` (relative to the report's URL) or, with `inline`, the PNGs
themselves as data: URIs, so the saved page can be mailed on its own. A small script marks the `<body>`
with `data-images-*` attributes once every image has loaded (used by the browser test).
"""
from __future__ import annotations

import base64
from datetime import datetime, timezone
from html import escape
from typing import Callable

from .figures import (FIT_NOTE, HOLDOUT_NOTE, accuracy, finding_title, mm, model_label, num, observability, pct,
                      plot_list, sig, std_str)

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
    m = answer.get("metrics") or {}
    d = answer.get("diagnosis") or {}
    acc = answer.get("accuracy") or accuracy(answer)
    plots = {p["name"]: p for p in (answer.get("plots") or plot_list(answer))}
    findings = d.get("findings") or []
    final_label = model_label(answer.get("model") or ["geometric"])
    out: list[str] = []
    w = out.append
    w("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
      "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
      f"<title>Calibration report: {_e(robot)} ({_e(cid[:8])})</title><style>{CSS}</style></head><body><main>")
    w(f"<h1>Calibration report: {_e(robot)}</h1>")
    w(f'<p class="sub">calibration <code>{_e(cid)}</code> · {_e(_when(answer.get("created_at")))} · '
      f'{_e(m.get("n_poses"))} measured poses · model: <b>{_e(final_label)}</b> · '
      f'units {_e(units.get("length", "mm"))}, {_e(units.get("angle", "deg"))}; every error in mm</p>')
    w('<nav class="noprint"><a href="#accuracy">Accuracy</a><a href="#diagnosis">Diagnosis</a>'
      '<a href="#parameters">Parameters</a><a href="#identifiability">Observability</a>' +
      (f'<a href="../{_e(cid)}">JSON</a>' if png is None else "") + "</nav>")

    # --- in short
    w("<h2>In short</h2><div class=\"cards\">")
    rows = acc.get("models") or []
    geo = rows[0] if len(rows) > 1 else None
    fin = rows[-1] if rows else {"holdout": {}, "fit": {}}
    if geo is not None:
        w(f'<div class="card"><div class="k">held-out error, geometric model</div>'
          f'<div class="v">{mm(geo["holdout"]["rms_mm"])} <small>mm RMS</small></div></div>')
    w(f'<div class="card"><div class="k">held-out error, {_e(final_label)}</div>'
      f'<div class="v">{mm(fin["holdout"].get("rms_mm"))} <small>mm RMS</small></div></div>')
    if geo is not None:
        g, f = num(geo["holdout"]["rms_mm"]), num(fin["holdout"].get("rms_mm"))
        if g and f is not None:
            w(f'<div class="card"><div class="k">gain of the extended model</div>'
              f'<div class="v">{pct(100.0 * (g - f) / g)}</div></div>')
    if acc.get("noise_floor_mm") is not None:
        w(f'<div class="card"><div class="k">noise floor (what a perfect model leaves)</div>'
          f'<div class="v">{mm(acc["noise_floor_mm"])} <small>mm RMS</small></div></div>')
    obs = observability(answer)
    if obs and obs["condition_number"] is not None:
        w(f'<div class="card"><div class="k">condition number of the measured poses (O1 '
          f'{_g3(obs["observability_index"])})</div><div class="v">{_g3(obs["condition_number"])}</div></div>')
    cut = d.get("search_complete") is False
    if d:
        causes = "; ".join(finding_title(f) for f in findings) or d.get("verdict") or "none"
        w(f'<div class="card"><div class="k">cause{"s" if len(findings) > 1 else ""} found'
          f'{" so far (the search stopped at its time budget)" if cut else ""}</div>'
          f'<div class="v cause">{_e(causes)}</div></div>')
    w("</div>")
    for warning in answer.get("warnings") or []:
        w(f'<p class="explain warn"><b>Caution.</b> {_e(warning)}</p>')
    if cut:
        w(f'<p class="explain warn"><b>Caution.</b> {_e(d.get("verdict"))}: causes not reached were never tested '
          f'(see the notes).</p>')
    if d.get("explanation"):
        w(f'<p class="explain">{_e(d["explanation"])}</p>')
    elif not d:
        w('<p class="explain">A <code>geometric</code> calibration: the kinematic parameters were identified; '
          'run the <code>auto</code> model to have the residual diagnosed (causes, evidence, plots).</p>')

    # --- accuracy
    w('<h2 id="accuracy">Accuracy</h2>')
    w('<table><thead><tr><th>model</th><th class="n">poses</th><th class="n">mean (AP mean)</th>'
      '<th class="n">RMS</th><th class="n">max (AP max)</th></tr></thead><tbody>')
    for r in rows:
        h = r["holdout"]
        w(_row([(_e(r["model"]), False), (_e(h.get("n") if h.get("n") is not None else ""), True),
                (mm(h.get("mean_mm")), True), (mm(h.get("rms_mm")), True), (mm(h.get("max_mm")), True)],
               "final" if r.get("final") else ""))
    w("</tbody></table>")
    w(f'<p class="note">Held-out error in mm: {_e(HOLDOUT_NOTE[len("held-out: "):])}</p>')
    w('<h3>On the calibration poses (fit)</h3><table><thead><tr><th>model</th><th class="n">mean</th>'
      '<th class="n">RMS</th><th class="n">max</th></tr></thead><tbody>')
    for r in rows:
        fi = r["fit"]
        w(_row([(_e(r["model"]), False), (mm(fi.get("mean_mm")), True), (mm(fi.get("rms_mm")), True),
                (mm(fi.get("max_mm")), True)], "final" if r.get("final") else ""))
    w("</tbody></table>")
    w(f'<p class="note">Fit: {_e(FIT_NOTE[len("fit: "):])} The held-out figures are the honest ones: '
      "a model always fits its own data better.</p>")
    for name in ("errors", "distribution"):
        if name in plots:
            w(_img(src(name), plots[name]["title"], _e(plots[name]["title"]) +
                   (". Orange: the geometric model; blue: the final model; green: the noise floor."
                    if name == "errors" else ".")))

    # --- diagnosis
    w('<h2 id="diagnosis">Diagnosis</h2>')
    if not d:
        w("<p>Not run (the <code>geometric</code> model was asked for).</p>")
    else:
        gd = d.get("geometric") or {}
        w(f'<p>The geometric model leaves {mm(gd.get("holdout_rms_mm"))} mm RMS on held-out poses '
          f'(fit {mm(gd.get("rms_mm"))} mm RMS) against a noise floor of {mm(d.get("noise_floor_mm"))} mm'
          f'{" (" + _e(d["noise_floor_basis"]) + ")" if d.get("noise_floor_basis") else ""}.</p>')
        if not findings:
            w(f"<p><b>No cause found</b>: {_e(d.get('verdict') or 'nothing the data can show beyond the geometric model')}.</p>")
        for k, f in enumerate(findings, 1):
            tags = f'<span class="tag">{_e(f.get("kind"))}</span>' + (
                ' <span class="tag">not a physical size</span>' if f.get("physical") is False else "")
            w(f'<div class="finding"><h3>Finding {k}: {_e(finding_title(f))} {tags}</h3>')
            w(f'<p>Held-out error {mm(f.get("holdout_rms_before_mm"))} mm → {mm(f.get("holdout_rms_after_mm"))} mm RMS: '
              f'<span class="gain">{pct(f.get("gain_pct"))} better</span>.</p>')
            w(f'<p><b>Evidence.</b> {_e(f.get("evidence"))}</p>')
            params = f.get("parameters") or []
            if params:
                w('<table><thead><tr><th>parameter</th><th class="n">value</th><th class="n">std</th>'
                  '<th>unit</th></tr></thead><tbody>')
                for p in params:
                    w(_row([(_e(p.get("name")), False), (sig(p.get("value"), p.get("std")), True),
                            (std_str(p.get("std")), True), (_e(p.get("unit")), False)]))
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
            w("<h3>Candidates tested and not retained</h3><ul>")
            for r in rejected[:12]:
                joints = ", ".join(r.get("joints") or [])
                w(f'<li>{_e(str(r.get("kind", "")).replace("_", " "))}{" on " + _e(joints) if joints else ""}: '
                  f'{_e(r.get("why"))}</li>')
            if len(rejected) > 12:
                w(f"<li>… and {len(rejected) - 12} more (see the JSON)</li>")
            w("</ul>")
        if d.get("notes"):
            w('<p class="note">' + " ".join(_e(n) for n in d["notes"]) + "</p>")

    # --- parameters
    w('<h2 id="parameters">Parameters</h2>')
    w('<table><thead><tr><th>parameter</th><th class="n">value</th><th class="n">std</th><th class="n">nominal</th>'
      '<th class="n">value − nominal</th><th>unit</th><th>of</th></tr></thead><tbody>')
    for p in answer.get("parameters") or []:
        nominal = p.get("nominal")
        w(_row([(_e(p.get("name")), False), (sig(p.get("value"), p.get("std")), True), (std_str(p.get("std")), True),
                (sig(nominal) if num(nominal) is not None else "—", True), (_dev(p), True),
                (_e(p.get("unit")), False), (_e(str(p.get("effect") or "geometry").replace("_", " ")), False)]))
    w("</tbody></table>")
    w('<p class="note">std: one standard deviation from the covariance of the fit (scaled by the residual). '
      "Values are printed to the precision their std justifies. Base angles are absolute Z-Y-X Euler angles "
      "of the robot base in the measurement frame.</p>")

    # --- observability of the measured pose set
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
