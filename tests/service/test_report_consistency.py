"""Issue 31, the report for a person: one number per figure. For a demo-like calibration (test_report's twin with a
hidden backlash, outliers named by both models), every number the HTML report prints as a figure of the answer is
that figure of `GET /calibrations/{id}` (its `accuracy` table, metrics, findings, parameters), quoted, never
recomputed; where the answer has two values for one figure (held-out over every pose, or with a model's outliers
left out) the page says which. Plus, on small hand-made answers (no server): counts say what they count, one
spelling per unit, sentences whole and capitalised, rejected causes listed once, a finding plot with a regressor
that does not vary."""
from __future__ import annotations

import math
import re

import pytest

from service.report import decorate, plots as report_plots
from service.report.figures import COMPLIANCE_UNIT, counts, joint_size, mm, pct, shown, sig, std_str
from service.report.html import render

from .test_report import calibrations, run_job, text_of  # noqa: F401  (the module's fixture, its helpers)

NUM = r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?"


def _numbers(obj, out: list) -> list:
    """Every finite number of a JSON value (per-pose arrays and plot data left out: the page prints none)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k not in ("per_pose", "plot", "calibrated_model", "robot_state", "model_selection"):
                _numbers(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _numbers(v, out)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool) and math.isfinite(obj):
        out.append(float(obj))
    return out


def _strings(obj, out: list) -> list:
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k not in ("per_pose", "plot"):
                _strings(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _strings(v, out)
    elif isinstance(obj, str):
        out.append(obj)
    return out


@pytest.fixture(scope="module")
def page(server, calibrations):  # noqa: F811
    a = calibrations["auto"]
    r = server.client.get(a["report_url"])
    assert r.status_code == 200, r.text[:500]
    return a, r.text, text_of(r.text)


def test_headline_and_table_quote_the_accuracy_table(page):
    assert page[0]["metrics"]["outliers"], page[0]["metrics"]  # this page has two values for a figure: both labelled
    headline_and_table_quote_the_accuracy_table(*page)
    figures_chain(page[0])


def test_causes_quote_the_findings_and_the_parameter_table(page):
    assert causes_quote_the_findings_and_the_parameter_table(*page) > 0


def test_every_printed_figure_is_one_of_the_answer(page):
    assert every_printed_figure_is_one_of_the_answer(*page) > 0


def check_report(a: dict, html: str) -> None:
    """Every check of this module's page on another answer's report (the demo's, the Motoman's: test_demo.py)."""
    text = text_of(html)
    headline_and_table_quote_the_accuracy_table(a, html, text)
    causes_quote_the_findings_and_the_parameter_table(a, html, text)
    every_printed_figure_is_one_of_the_answer(a, html, text)
    figures_chain(a)


def figures_chain(a: dict) -> None:
    """Per-cause figures chain: each finding starts where the one before it ends, the first at the geometric
    model's held-out error, and a finding's parameters are the parameter table's."""
    d, table = a["diagnosis"], {p["name"]: p for p in a["parameters"]}
    at = d["geometric"]["holdout_rms_mm"]
    for f in d["findings"]:
        # the same model may be refitted between two steps (to 1e-11 mm: Agile Justin with nothing named)
        assert f["holdout_rms_before_mm"] == pytest.approx(at, rel=1e-9), (f["kind"], f["holdout_rms_before_mm"], at)
        at = f["holdout_rms_after_mm"]
        for p in f["parameters"]:
            assert (p["value"], p["std"]) == (table[p["name"]]["value"], table[p["name"]]["std"]), p


def headline_and_table_quote_the_accuracy_table(a: dict, html: str, text: str) -> None:
    acc = a["accuracy"]
    head, models = acc["headline"], acc["models"]
    geo, fin = models[0], models[-1]  # one row when nothing was found: the geometric model is the final one
    n = a["metrics"]["n_poses"]
    # the answer's accuracy defines each figure once, with the poses it counts
    assert head["poses"] == n == geo["holdout_all"]["n"] == fin["holdout_all"]["n"]
    m = a["metrics"]  # the figures with outliers are given apart only where the model names some
    assert head["final_rms_mm"] == fin["holdout_all"]["rms_mm"] == m.get("holdout_rms_with_outliers_mm",
                                                                         m["holdout_rms_mm"])
    assert fin["holdout"]["rms_mm"] == a["metrics"]["holdout_rms_mm"]
    assert fin["holdout"]["outliers_left_out"] == len(a["metrics"]["outliers"])  # two values: both labelled
    if len(models) > 1:  # a geometric row beside the final one
        assert head["geometric_rms_mm"] == geo["holdout_all"]["rms_mm"]
        assert geo["holdout"]["rms_mm"] == a["diagnosis"]["geometric"]["holdout_rms_mm"]
        assert geo["holdout"]["n"] + geo["holdout"]["outliers_left_out"] == n
        assert head["gain_pct"] == pytest.approx(100 * (1 - head["final_rms_mm"] / head["geometric_rms_mm"]),
                                                 rel=1e-12)

    if len(models) == 1:  # nothing found: the geometric model is the answer, no "against" clause
        v = re.search(rf"Accuracy: the calibrated robot is off by ({NUM}) mm RMS at the tool on poses the model did "
                      rf"not fit(?:, against {NUM} mm with the geometric model alone: {NUM} % less)? \(held out, all "
                      rf"(\d+) calibration poses counted\)", text)
        assert v and v.groups() == (mm(head["final_rms_mm"]), str(n)), text[:1500]
    else:
        v = re.search(rf"Accuracy: the calibrated robot is off by ({NUM}) mm RMS at the tool on poses the model did "
                      rf"not fit, against ({NUM}) mm with the geometric model alone: ({NUM}) % less \(held out, all "
                      rf"(\d+) calibration poses counted\)", text)
        assert v, text[:1500]
        assert v.groups() == (mm(head["final_rms_mm"]), mm(head["geometric_rms_mm"]), f"{head['gain_pct']:.1f}",
                              str(n))

    word = re.search(r'<th class="n">(\w+) counted</th>', html).group(1)
    table = html[html.index('id="accuracy"'):html.index('id="causes"')]
    cells = [[text_of(c).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", tr)]
             for tr in re.findall(r"<tr[^>]*>(.*?)</tr>", table, flags=re.S)[1:]]
    by_label = {c[0]: c[1:] for c in cells}
    nominal = a["diagnosis"]["nominal"]
    assert by_label["before calibration (nominal model, base and tool placed)"][2:] == [
        mm(nominal["holdout_rms_mm"]), mm(nominal["holdout_max_mm"]), mm(nominal["rms_mm"])]
    for row in (geo, fin):
        al, own = row["holdout_all"], row["holdout"]
        assert by_label[row["model"]][:4] == [f"all {n}", mm(al["mean_mm"]), mm(al["rms_mm"]), mm(al["max_mm"])]
        if not own["outliers_left_out"]:
            assert not any(k.startswith(row["model"] + ", the ") for k in by_label), by_label
            continue
        one = own["outliers_left_out"] == 1
        label = (f"{row['model']}, the {own['outliers_left_out']} {word[:-1] if one else word} it names "
                 f"{'an outlier' if one else 'outliers'} left out")
        assert by_label[label] == [str(own["n"]), mm(own["mean_mm"]), mm(own["rms_mm"]), mm(own["max_mm"]),
                                   mm(row["fit"]["rms_mm"])]
    assert by_label[fin["model"]][4] == mm(m.get("rms_with_outliers_mm", m["rms_mm"]))


def causes_quote_the_findings_and_the_parameter_table(a: dict, html: str, text: str) -> int:
    table = {p["name"]: p for p in a["parameters"]}
    angle_unit = ((a.get("calibrated_model") or {}).get("units") or {}).get("angle", "deg")  # as the report prints
    causes = text[text.index("in plain words"):text.index("What to do next")]
    for f in a["diagnosis"]["findings"]:
        assert (f"Held-out error before it {mm(f['holdout_rms_before_mm'])} mm, with it "
                f"{mm(f['holdout_rms_after_mm'])} mm: {pct(f['gain_pct'])} less") in causes
        if "effect_rms_mm" in f:  # not for `unexplained`
            assert f"At the tool: {mm(f['effect_rms_mm'])} mm RMS" in causes
        said = [table[fp["name"]] for fp in f["parameters"]  # the sizes are the table's, in plain-words units
                if joint_size(table[fp["name"]]) is not None]  # (mass data has none)
        for group in ([p for p in said if abs(p["value"]) >= 2 * p["std"]], [p for p in said if abs(p["value"]) <
                                                                           2 * p["std"]]):
            for p in group[:4]:  # the first four of each; the rest "and N more (the parameter table)"
                assert f"{p['name']} {joint_size(p)}" in causes, (p, causes)
            if len(group) > 4:
                assert f"and {len(group) - 4} more (the parameter table)" in causes
    for p in a["parameters"]:  # the parameter table, in the report's units
        q = shown(p, angle_unit) if p.get("effect") else p
        at = [m.start() for m in re.finditer(rf"\b{re.escape(p['name'])} ", text)]
        assert re.search(rf"\b{re.escape(p['name'])} {re.escape(sig(q['value'], q['std']))} ", text), \
            (p, [text[i:i + 80] for i in at])
    return len(a["parameters"])  # rows checked


def every_printed_figure_is_one_of_the_answer(a: dict, html: str, text: str) -> int:
    """Every "<number> mm" and "<number> %" on the page is a figure of the answer formatted as the page formats it,
    or stands in a text of the answer quoted verbatim (the diagnosis's explanation, evidence, notes); the parameter
    table below is checked row by row (test_causes_quote_the_findings_and_the_parameter_table)."""
    text = text[:text.index("Parameters parameter value")]
    values = _numbers(a, [])
    allowed_mm = {mm(v) for v in values} | {f"{v:.3g}" for v in values}
    allowed_mm |= {std_str(p.get("std")) for p in a["parameters"]}  # a finding's table: "value std unit" (a step's mm)
    allowed_mm |= {joint_size(p).split()[0] for p in a["parameters"] if joint_size(p)}  # "0.138 mm per deg C"
    allowed_pct = {f"{v:.1f}" for v in values} | {f"{v:.0f}" for v in values}
    quoted = " ".join(_strings(a, []))
    for x in re.findall(rf"({NUM}) mm\b", text):
        assert x in allowed_mm or re.search(rf"(?<![\d.]){re.escape(x)} mm", quoted), x
    printed = re.findall(rf"({NUM}) mm\b", text) + re.findall(rf"({NUM}) %", text)
    for x in re.findall(rf"({NUM}) %", text):
        assert x in allowed_pct or re.search(rf"(?<![\d.]){re.escape(x)} %", quoted), x
    return len(printed)  # figures checked


def test_plot_legends_quote_the_headline(page):
    a = page[0]
    geo, fin = report_plots._labels(a, False)
    head = a["accuracy"]["headline"]
    assert f"RMS {mm(head['geometric_rms_mm'])} mm over all {head['poses']} poses" in geo
    assert f"RMS {mm(head['final_rms_mm'])} mm over all {head['poses']} poses" in fin


# --- hand-made answers: counts, units, sentences -------------------------------------------------------------

def _answer(ids: list[str] | None = None, **over) -> dict:
    ids = ids or [f"P{i:04d}" for i in range(1, 5)] + [f"P{i:04d}~{a}" for i in range(1, 5) for a in "xyz"]
    finding = {"kind": "joint_compliance", "joints": ["R6"], "holdout_rms_before_mm": 0.4, "holdout_rms_after_mm": 0.3,
               "gain_pct": 25.0, "effect_rms_mm": 0.2,
               "evidence": "R6 gives way under its load: it explains 30 % of the remaining residual; "
                           "R6.compliance = 1e-05 +/- 1e-06 rad/N*m",
               "parameters": [{"name": "R6.compliance", "value": 1e-5, "std": 1e-6, "unit": "rad/N*m",
                               "effect": "joint_compliance"}],
               "plot": {"x": [0.0] * 16, "residual_mm": [0.1] * 16, "fit_mm": [0.1] * 16, "x_label": "load (N*m)"}}
    bad = {"kind": "link_deflection", "joints": ["L7"], "physical": False, "holdout_rms_before_mm": 0.3,
           "holdout_rms_after_mm": 0.25, "gain_pct": 16.7, "parameters": [],
           "evidence": "the links bend; read it as a correction, not as the joint's"}
    a = {"id": "c0ffee", "model": ["geometric", "joint_compliance", "link_deflection"],
         "metrics": {"n_poses": 16, "holdout_rms_mm": 0.25, "rms_mm": 0.2, "outliers": []},
         "noise_model": "the optical preset, assumed: no sigma column and no instrument given",
         "calibrated_model": {"name": "r", "units": {"length": "mm", "angle": "deg"}},
         "parameters": [{"name": "J1.scale", "value": -0.000846, "std": 1e-5, "unit": "1", "effect": "joint_scale"},
                        {"name": "J2.tilt_x_1", "value": 0.001, "std": 1e-4, "unit": "rad", "effect": "link_deflection"},
                        {"name": "L7.lateral_compliance_x", "value": 2e-5, "std": 1e-6, "unit": "rad/(N*m)",
                         "effect": "link_deflection"},
                        {"name": "R6.compliance", "value": 1e-5, "std": 1e-6, "unit": "rad/N*m",
                         "effect": "joint_compliance"}],
         "diagnosis": {"verdict": "causes found", "noise_floor_mm": 0.05, "findings": [finding, bad],
                       "geometric": {"rms_mm": 0.35, "holdout_rms_mm": 0.4},
                       "not_findings": [{"kind": "backlash", "joints": ["J3"], "why": "significant in the fit"}] * 3,
                       "notes": ["the residual looks like noise"],
                       "per_pose": {"point": ids, "geometric_holdout_mm": [0.4] * 16, "final_holdout_mm": [0.25] * 16,
                                    "geometric_outlier": [False] * 16, "final_outlier": [False] * 16}}}
    a.update(over)
    return decorate(a, "/calibrations/c0ffee")


def test_counts_say_what_they_count():
    a = _answer()
    assert counts(a) == {"points": 16, "rows": 4, "virtual_points": 12, "six_d_rows": 4, "markers": 1, "poses": 4}
    text = text_of(render(a))
    assert ("4 rows uploaded, 4 of them 6-D (position and orientation): each 6-D row entered the fit as its point and "
            "3 virtual points, so the fit and every figure count 16 points (4 + 12 virtual)") in text
    assert "all 16 calibration points counted" in text and "16 measured poses" not in text
    assert "Noise model: the optical preset" in text
    two = _answer(ids=[f"P{i}" for i in range(16)],
                  calibrated_model={"name": "justin", "units": {"length": "mm", "angle": "deg"},
                                    "targets": [{"name": "left"}, {"name": "right"}]})
    assert counts(two)["poses"] == 8
    assert "16 rows from 2 markers: 8 poses x 2 markers" in text_of(render(two))


def test_one_spelling_per_unit_and_whole_sentences():
    a = _answer()
    html = render(a)
    text = text_of(html)
    params = html[html.index('id="parameters"'):html.index("</table>", html.index('id="parameters"'))]
    units = re.findall(r"<td>([^<]*)</td><td>[^<]*</td></tr>", params)
    assert units == ["ppm", "deg", COMPLIANCE_UNIT, COMPLIANCE_UNIT]
    assert "rad/N*m" not in text.replace("rad/N*m)", "") and "rad" not in units
    assert "J1.scale -846 10 " in text and "J2.tilt_x_1 0.0573 " in text  # -0.000846 -> ppm; 0.001 rad -> deg
    assert "R6.compliance = 3.44 +/- 0.34 arcmin/(100 N*m)" in text  # the evidence in the page's units
    assert "Size: R6.compliance 3.44 arc-min per 100 N*m" in text
    assert "not as the joint's own size." in text and "not as the joint's." not in text
    assert "The links bend" in text and "The residual looks like noise." in text
    assert text.count("Backlash on J3") == 1 and "Backlash on J3 (3 forms tested): significant in the fit." in text
    assert "A correction following L7 (fitted as link deflection; its size is not physical" in text
    assert "Causes: joint compliance on R6; a correction (link deflection on L7)." in text


def test_finding_plot_of_a_regressor_that_does_not_vary_spreads_its_points():
    a = _answer()
    fig = report_plots.figure(a, "finding-1")
    ax = fig.axes[0]
    lo, hi = ax.get_xlim()
    assert hi - lo > 10 and "is 0 at every pose" in ax.get_xlabel()
    assert fig._suptitle.get_text() == "Finding 1: joint compliance on R6"
    assert ax.get_title() != fig.axes[1].get_title()
