"""The diagnosis's answer: the Diagnosis record (models, findings, notes, its JSON) and the paragraph that
explains it to a process engineer."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..identify import Calibration
from ..model import RobotModel
from .evidence import model_error_mm
from .findings import follows_what, is_named, named_joints


@dataclass
class Diagnosis:
    calibration: Calibration  # the final (extended) model
    geometric: Calibration
    nominal: Calibration  # the nominal model with only the tracker frame and tool registered
    noise_floor_mm: float
    noise_note: str
    floor_basis: str = "assumed"  # 'given', 'repeats', 'assumed' or 'residual' (re-estimated, no structure)
    findings: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    explanation: str = ""
    loss: str | None = None
    selection: dict = field(default_factory=dict)  # how the geometric model's size was chosen (held out)
    noise_model: str = ""  # which noise model weighted the fit: the CSV's sigma or an instrument preset
    untested: str | None = None  # what the search left untested when its time budget ran out (None: it finished)

    def model_error_mm(self, cal: Calibration) -> float:
        """De-noised model error: the root of held-out mean square distance minus the floor's (mm)."""
        return model_error_mm(cal, self.noise_floor_mm)

    def gaps(self) -> list[str]:
        """Parameters the model's structure identifies but this pose set cannot."""
        ident = self.geometric.identifiability
        return [ident.names[i] if isinstance(i, (int, np.integer)) else i
                for i in getattr(ident, "unidentifiable", [])]

    def verdict(self) -> str:
        """The diagnosis in a few words, for a headline: the same judgement as the explanation and the JSON."""
        if self.untested:
            n = sum(f["kind"] != "unexplained" for f in self.findings)
            return (f"search stopped at its time budget: {n or 'no'} cause(s) confirmed so far, not a complete "
                    f"answer" + ("; structure left" if len(self.findings) > n else ""))
        if self.findings:
            kinds = [f["kind"] for f in self.findings]
            named = sum(is_named(f) for f in self.findings)
            parts = (["causes found"] if named else [])
            if "correction" in kinds:  # a form whose size no real joint has: it corrects, it does not name
                parts.append(f"{kinds.count('correction')} correction(s) of no physical size")
            faded = sum(f.get("significant") is False and f["kind"] != "correction" for f in self.findings)
            if faded:  # confirmed when found, no size in the final model: later causes explain it
                parts.append(f"{faded} cause(s) the later ones explain (no size in the final model)")
            if "unexplained" in kinds:
                parts.append("structure left that no named cause explains")
            return "; ".join(parts) if named else "no physical cause named: " + "; ".join(parts)
        gaps = self.gaps()
        if gaps:
            return f"none found, but this pose set cannot identify {len(gaps)} parameter(s): valid only near it"
        if self.floor_basis == "residual":
            return "none: the residual follows nothing (noise above the assumed floor)"
        return "none: at the noise floor, the geometric model is complete"

    def to_dict(self) -> dict:
        g, f = self.geometric.metrics(), self.calibration.metrics()
        return {
            "verdict": self.verdict(),
            "noise_floor_mm": self.noise_floor_mm,
            "noise_floor_basis": self.noise_note,
            "noise_floor_source": self.floor_basis,
            "noise_model": self.noise_model,
            "search_complete": self.untested is None,
            "nominal": {k: self.nominal.metrics()[k] for k in ("rms_mm", "max_mm", "holdout_rms_mm", "holdout_max_mm")},
            "geometric": {"rms_mm": g["rms_mm"], "holdout_rms_mm": g["holdout_rms_mm"], "max_mm": g["max_mm"],
                          "holdout_max_mm": g["holdout_max_mm"], "model_error_mm": self.model_error_mm(self.geometric)},
            "final": {"holdout_rms_mm": f["holdout_rms_mm"], "holdout_max_mm": f["holdout_max_mm"],
                      "model_error_mm": self.model_error_mm(self.calibration)},
            "findings": self.findings,
            "not_findings": self.rejected,
            "notes": self.notes,
            "explanation": self.explanation,
            "robust_loss": self.loss,
            "model_selection": self.selection,
            "per_pose": {
                "point": list(self.calibration.point_ids),
                "geometric_holdout_mm": self.geometric.holdout_residual_mm.tolist(),
                "final_holdout_mm": self.calibration.holdout_residual_mm.tolist(),
                "geometric_outlier": (~self.geometric.inliers()).tolist(),  # left out of the held-out figures
                "final_outlier": (~self.calibration.inliers()).tolist(),
            },
        }


def explain(d: Diagnosis, model: RobotModel) -> str:
    """One paragraph a process engineer can read; it says what the JSON says."""
    g = d.geometric.metrics()
    n_out = len(g["outliers"])
    out = f" (the {n_out} outlier{'s' if n_out > 1 else ''} left out)" if n_out else ""
    head = (f"After the geometric calibration the robot's held-out error is {g['holdout_rms_mm']:.3f} mm RMS{out} "
            f"against a noise floor of {d.noise_floor_mm:.3f} mm (what a perfect model would leave: {d.noise_note}).")
    gaps = d.gaps()
    caveat = (f" This pose set cannot identify {len(gaps)} parameter(s) ({', '.join(gaps[:6])}"
              f"{', ...' if len(gaps) > 6 else ''}): the model is valid only near the measured poses."
              if gaps else "")
    tail = (" " + " ".join(n if n.endswith(".") else n + "." for n in d.notes)) if d.notes else ""
    if not d.findings and d.untested:
        return head + " No cause was confirmed before the search stopped." + caveat + tail
    if not d.findings:
        if d.floor_basis == "residual":
            return head + " No cause was found and the residual follows nothing." + caveat + tail
        complete = "" if gaps else ", so the geometric model is complete"
        return head + f" No cause was found: the residual is at the noise floor{complete}." + caveat + tail
    parts = []
    for f in d.findings:
        joints, others = named_joints(f)
        who = (f" on {', '.join(joints)}" if joints else "") + (f" ({others})" if others else "")
        odd = ", a size no real joint has: a correction, not the cause" if f.get("physical") is False else (
            "; no size in the final model: the causes after it explain it" if f.get("significant") is False else "")
        name = f"{f['kind'].replace('_', ' ')}{who}"
        if f["kind"] == "correction":
            odd = f"; not a physical cause: {f.get('bound', 'its size is not physical')}"
            name = f"a correction that follows {follows_what(f)}"
        parts.append(f"{name} (held-out {f['holdout_rms_before_mm']:.3f} -> "
                     f"{f['holdout_rms_after_mm']:.3f} mm, {f['gain_pct']:.0f} % better{odd})")
    final = d.calibration.metrics()["holdout_rms_mm"]
    left = ""
    if any(f["kind"] == "unexplained" for f in d.findings):
        left = " Structure no named cause explains is left: see the unexplained finding for what it follows."
    return (head + " The residual still had structure. Found, in order: " + "; ".join(parts) +
            f". With these in the model the held-out error is {final:.3f} mm, "
            f"{final / d.noise_floor_mm:.2f}x the noise floor, a model error of {d.model_error_mm(d.calibration):.3f} mm "
            "beyond it." + left + caveat + tail)
