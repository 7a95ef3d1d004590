"""The contract's measurement CSV (section 2): all-or-nothing parsing with row/column errors, and writing.

`row` in an error is the line number in the file (the header is on its line, usually 1), so a user
can jump to it in any editor.  Joint columns are matched by the model's joint names, in any order.
"""
from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from .model import LENGTH_TO_MM, RobotModel

OPTIONAL = ("point", "timestamp", "temperature", "payload", "sigma")
MAX_LISTED_ERRORS = 1000
LIMIT_TOL = 1e-9
"""Relative slack on joint limits, so that values written at a limit with rounding still pass."""


class MeasurementError(ValueError):
    """A CSV that cannot be used; `errors` lists problems as {row, column, value, message}."""

    def __init__(self, errors: list[dict], total: int | None = None):
        self.errors = errors
        self.total = len(errors) if total is None else total
        head = "; ".join(f"row {e['row']}, column {e['column']}: {e['message']}" for e in errors[:3])
        more = f" (and {self.total - 3} more)" if self.total > 3 else ""
        super().__init__(head + more)


@dataclass
class Measurements:
    """N measured poses in internal units: joints rad / mm, points mm, sigma mm, payload kg."""

    joints: np.ndarray  # (N, n) in model joint order
    points: np.ndarray  # (N, 3) mm in the measurement frame
    point_ids: list[str] = field(default_factory=list)
    timestamp: np.ndarray | None = None  # (N,) seconds since the epoch
    temperature: np.ndarray | None = None  # (N,) deg C
    payload: np.ndarray | None = None  # (N,) kg
    sigma: np.ndarray | None = None  # (N,) mm, 1-sigma per coordinate

    @property
    def n_poses(self) -> int:
        return len(self.points)

    def payload_kg(self) -> np.ndarray:
        return np.zeros(self.n_poses) if self.payload is None else self.payload

    def subset(self, idx) -> "Measurements":
        """The poses at integer or boolean index idx."""
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        ids = [self.point_ids[i] for i in np.arange(self.n_poses)[idx]] if self.point_ids else []
        return Measurements(self.joints[idx], self.points[idx], ids, pick(self.timestamp),
                            pick(self.temperature), pick(self.payload), pick(self.sigma))


def _decode(data: bytes | str) -> str:
    if isinstance(data, str):
        text = data
    else:
        if b"\x00" in data[:65536]:
            raise MeasurementError([{"row": None, "column": None, "value": None,
                                     "message": "the file is binary, not CSV text"}])
        try:
            text = data.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise MeasurementError([{"row": None, "column": None, "value": repr(data[exc.start:exc.start + 8]),
                                     "message": f"the file is not UTF-8 text (byte {exc.start})"}]) from None
    return text.lstrip("\ufeff")


def _parse_time(value: str) -> float:
    t = datetime.fromisoformat(value.replace("Z", "+00:00"))
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return t.timestamp()


def parse_measurements(data: bytes | str, model: RobotModel) -> Measurements:
    """Parse a contract CSV against the model; raises MeasurementError listing every problem."""
    text = _decode(data)
    lines = [(k + 1, ln) for k, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    if not lines:
        raise MeasurementError([{"row": None, "column": None, "value": None, "message": "the file has no header and no data"}])
    rows = list(csv.reader([ln for _, ln in lines], skipinitialspace=True))
    header_line, header = lines[0][0], [h.strip() for h in rows[0]]
    errors: list[dict] = []

    def err(row, column, value, message):
        errors.append({"row": row, "column": column, "value": value, "message": message})

    seen = set()
    for h in header:
        if h in seen:
            err(header_line, h, h, "duplicated column")
        seen.add(h)
    known = set(model.joint_names) | {"x", "y", "z"} | set(OPTIONAL)
    for h in header:
        if h not in known:
            err(header_line, h, h, f"unknown column; expected the joints {list(model.joint_names)}, "
                                   f"x, y, z and optionally {list(OPTIONAL)}")
    for need in list(model.joint_names) + ["x", "y", "z"]:
        if need not in header:
            err(header_line, need, None, "missing column" + (" (a joint of the model)" if need in model.joint_names else ""))
    if errors:
        raise MeasurementError(errors)
    if len(rows) == 1:
        raise MeasurementError([{"row": header_line, "column": None, "value": None, "message": "no data rows"}])

    col = {h: k for k, h in enumerate(header)}
    js = model.joint_scale()
    lo = model.limits[:, 0] / js
    hi = model.limits[:, 1] / js
    numeric = list(model.joint_names) + ["x", "y", "z"] + [c for c in ("temperature", "payload", "sigma") if c in col]
    values = {c: np.empty(len(rows) - 1) for c in numeric}
    stamps = np.empty(len(rows) - 1) if "timestamp" in col else None
    ids: list[str] = []
    for i, ((line, _), fields) in enumerate(zip(lines[1:], rows[1:])):
        if len(fields) != len(header):
            err(line, None, len(fields), f"expected {len(header)} fields like the header, found {len(fields)}")
            continue
        for c in numeric:
            raw = fields[col[c]].strip()
            try:
                v = float(raw)
            except ValueError:
                err(line, c, raw, "not a number")
                continue
            if not math.isfinite(v):
                err(line, c, raw, "must be finite (no NaN or inf)")
                continue
            values[c][i] = v
            if c in model.joint_names:
                j = model.joint_names.index(c)
                slack = LIMIT_TOL * max(1.0, abs(hi[j] - lo[j]))
                if not lo[j] - slack <= v <= hi[j] + slack:
                    err(line, c, raw, f"outside the joint limits [{lo[j]:g}, {hi[j]:g}] {model.joint_unit(j)}")
            elif c == "sigma" and v <= 0:
                err(line, c, raw, "sigma must be > 0")
            elif c == "payload" and v < 0:
                err(line, c, raw, "payload must be >= 0 kg")
            elif c == "temperature" and not -60.0 <= v <= 200.0:
                err(line, c, raw, "temperature outside -60..200 deg C")
        if stamps is not None:
            raw = fields[col["timestamp"]].strip()
            try:
                stamps[i] = _parse_time(raw)
            except ValueError:
                err(line, "timestamp", raw, "not an ISO 8601 timestamp (e.g. 2026-11-03T08:00:19+00:00)")
        ids.append(fields[col["point"]].strip() if "point" in col else str(i + 1))
    if errors:
        raise MeasurementError(errors[:MAX_LISTED_ERRORS], total=len(errors))
    if "point" in col:
        dup: dict[str, int] = {}
        for (line, _), pid in zip(lines[1:], ids):
            if pid in dup:
                err(line, "point", pid, f"duplicated point id (first on line {dup[pid]})")
            dup.setdefault(pid, line)
        if errors:
            raise MeasurementError(errors[:MAX_LISTED_ERRORS], total=len(errors))

    ls = LENGTH_TO_MM[model.length_unit]
    joints = np.column_stack([values[c] for c in model.joint_names]) * js
    points = np.column_stack([values[c] for c in ("x", "y", "z")]) * ls
    return Measurements(
        joints=joints, points=points, point_ids=ids, timestamp=stamps,
        temperature=values.get("temperature"), payload=values.get("payload"),
        sigma=values["sigma"] * ls if "sigma" in values else None,
    )


def write_measurements(meas: Measurements, model: RobotModel) -> str:
    """The measurements as contract CSV in the model's units."""
    ls = LENGTH_TO_MM[model.length_unit]
    cols = ["point", *model.joint_names, "x", "y", "z"]
    data = [np.asarray(meas.point_ids or [f"P{i + 1:04d}" for i in range(meas.n_poses)], dtype=object)]
    data += list((meas.joints / model.joint_scale()).T) + list((meas.points / ls).T)
    fmt = ["{}"] + ["{:.9g}"] * model.n_joints + ["{:.6f}"] * 3
    if meas.timestamp is not None:
        cols.append("timestamp")
        data.append(np.array([datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="seconds")
                              for t in meas.timestamp], dtype=object))
        fmt.append("{}")
    for name, arr, f in (("temperature", meas.temperature, "{:.3f}"), ("payload", meas.payload, "{:.4g}"),
                         ("sigma", None if meas.sigma is None else meas.sigma / ls, "{:.6g}")):
        if arr is not None:
            cols.append(name)
            data.append(arr)
            fmt.append(f)
    out = _io.StringIO()
    out.write(",".join(cols) + "\n")
    for row in zip(*data):
        out.write(",".join(f.format(v) for f, v in zip(fmt, row)) + "\n")
    return out.getvalue()
