"""The contract's measurement CSV (section 2): all-or-nothing parsing with row/column errors, and writing.

`row` in an error is the line number in the file (the header is on its line, usually 1), so a user
can jump to it in any editor.  Joint columns are matched by the model's joint names, in any order.
"""
from __future__ import annotations

import csv
import io as _io
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from .instruments import INSTRUMENTS, instrument
from .kinematics import Labels
from .model import (LENGTH_TO_MM, MAX_PAYLOAD_KG, MAX_POINT_MM, SIGMA_RANGE_MM, TEMPERATURE_RANGE_C, TIMESTAMP_RANGE_S,
                    TIMESTAMP_RANGE_UTC, RobotModel, name_problem, revolute_bound)

OPTIONAL = ("point", "timestamp", "sequence", "temperature", "payload", "sigma", "target", "setup", "qw", "qx", "qy",
            "qz")
MAX_SEQUENCE = 1e12
"""|sequence|: a measurement's place in the session's order (a count, a pose index), never beyond this."""
QUATERNION = ("qw", "qx", "qy", "qz")
MAX_TAU = 1e6
"""|tau_<joint>|: 1 MN*m or 1 MN, far beyond any robot joint."""
QUATERNION_TOL = 1e-3
"""|norm - 1| allowed for a measured orientation quaternion (it is normalised)."""
MAX_LISTED_ERRORS = 1000
LIMIT_TOL = 1e-9
"""Relative slack on joint limits, so that values written at a limit with rounding still pass."""
LIMIT_MODES = ("reject", "warn")
"""parse_measurements(limits=...): out-of-limit joint values are errors ("reject", the default) or are accepted
and reported in Measurements.out_of_limits ("warn": vendor limits are often conservative)."""
MAX_LISTED_ROWS = 10
COUPLING_TOL = 1e-3
"""A coupled joint's CSV value may differ from its coupling by this much (model joint units: rounding)."""


DISTINCT_DECIMALS = 9
"""Joint vectors equal after rounding to this many decimals (rad / mm) are the same configuration."""


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
    instrument: str | None = None  # noise preset (calib_core.instruments) used where `sigma` is absent
    out_of_limits: list[dict] = field(default_factory=list)  # limits="warn": per joint, the rows beyond its limits
    target: np.ndarray | None = None  # (N,) int index into model.target_names
    setup: np.ndarray | None = None  # (N,) int index into setup_names
    setup_names: tuple[str, ...] = ("",)
    orientation: np.ndarray | None = None  # (N, 4) unit quaternion w, x, y, z of the target frame; NaN: a point row
    tau: np.ndarray | None = None  # (N, n) measured joint torque N*m / force N per model row; NaN where not given
    sigma_source: str | None = None  # where `sigma` came from when not from the CSV (6-D rows: the instrument preset)
    sequence: np.ndarray | None = None  # (N,) the order the poses were measured in (any increasing numbering)

    @property
    def n_poses(self) -> int:
        return len(self.points)

    def noise_sigma_mm(self) -> np.ndarray:
        """Per-pose 1-sigma (mm) per axis: the CSV's `sigma`, else the instrument preset (default laser tracker)."""
        return self.sigma if self.sigma is not None else instrument(self.instrument).sigma_mm(self.points)

    def noise_source(self) -> str:
        """Which noise model the fit weights and the noise floor use, in words."""
        if self.sigma is not None:
            return self.sigma_source or "the CSV's sigma column"
        said = "" if self.instrument else ", assumed: no sigma column and no instrument given"
        return f"the {instrument(self.instrument).describe()} preset{said}"

    def payload_kg(self) -> np.ndarray:
        return np.zeros(self.n_poses) if self.payload is None else self.payload

    @property
    def labels(self) -> Labels | None:
        """Each pose's target and setup for the kinematics; None when every pose measures target 0 in one setup."""
        if self.target is None and self.setup is None:
            return None
        zero = np.zeros(self.n_poses, int)
        return Labels(zero if self.target is None else self.target, zero if self.setup is None else self.setup)

    @property
    def n_setups(self) -> int:
        return len(self.setup_names)

    def pose_index(self) -> np.ndarray:
        """(N,) the independent unit of every row, numbered 0, 1, ... in the order of their first rows: rows measuring
        different targets at the same setup, payload and joint values (to DISTINCT_DECIMALS) are one pose of the
        robot; any other row (one target, or a pose visited again) is its own (so with one target, 0..N-1 in row
        order). Held-out folds and paired tests count these units."""
        out = np.arange(self.n_poses)
        if self.target is None:
            return out
        setup = np.zeros(self.n_poses, int) if self.setup is None else self.setup
        key = np.c_[setup, self.payload_kg(), np.round(self.joints, DISTINCT_DECIMALS)]
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        rows = np.bincount(inverse)
        distinct = np.bincount(np.unique(np.c_[inverse, self.target], axis=0)[:, 0], minlength=len(rows))
        together = (rows > 1) & (distinct == rows)  # each target once: one placement of the robot
        return np.unique(np.where(together[inverse], first[inverse], out), return_inverse=True)[1].ravel()

    def subset(self, idx) -> "Measurements":
        """The poses at integer or boolean index idx."""
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        ids = [self.point_ids[i] for i in np.arange(self.n_poses)[idx]] if self.point_ids else []
        return Measurements(self.joints[idx], self.points[idx], ids, pick(self.timestamp),
                            pick(self.temperature), pick(self.payload), pick(self.sigma), self.instrument,
                            target=pick(self.target), setup=pick(self.setup), setup_names=self.setup_names,
                            orientation=pick(self.orientation), tau=pick(self.tau), sigma_source=self.sigma_source,
                            sequence=pick(self.sequence))


def _decode(data: bytes | str) -> str:
    if isinstance(data, str):
        text = data
        if "\x00" in text:
            raise MeasurementError([{"row": None, "column": None, "value": None,
                                     "message": "the file holds NUL characters: it is binary, not CSV text"}])
    else:
        if b"\x00" in data:
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


NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
"""A plain decimal number in ASCII: no '1_000', no Unicode digits, no hex.  Unambiguous (linear time on any
input: no two parts can match the same digits)."""
NOT_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
MAX_COLUMNS = 1000
"""A header with more columns than this is refused at once (a robot has a handful of joints)."""
MAX_QUOTED_COMMAS = 10 * MAX_COLUMNS
"""A line with quotes is read by csv.reader, whose work grows with the fields it makes (0.25 s of the GIL for 1.8
million): one with this many commas or more is refused unread (quoted commas in a value are rare; thousands in
one row are no measurement)."""
MAX_FIELD_CHARS = 131072
"""csv's own field limit; a longer field is an error naming its row."""


def parse_number(raw: str) -> tuple[float | None, str | None]:
    """(value, None) for a plain finite decimal number, else (None, why in plain words)."""
    if not NUMBER.fullmatch(raw):
        if NOT_FINITE.fullmatch(raw):
            return None, "must be finite (no NaN or inf)"
        if len(raw) <= 64 and not raw.isascii() and all(c.isdigit() or c in "+-.eE_" for c in raw):
            return None, "not a number: write digits 0-9 only"
        if len(raw) <= 64 and "_" in raw:
            return None, "not a number: write it without '_' separators"
        return None, "not a number"
    v = float(raw)
    if not math.isfinite(v):
        return None, "must be finite (the number is too large for a double)"
    return v, None


class _Wide:
    """A line with more than MAX_COLUMNS fields and no quotes: only its field count is kept (`len`), never a list
    of a million empty strings (a 1.8 MB header of commas used to cost 0.25 s of the API's GIL)."""

    __slots__ = ("n",)

    def __init__(self, n: int):
        self.n = n

    def __len__(self) -> int:
        return self.n


class _QuotedWide(csv.Error):
    """A line with quotes and MAX_QUOTED_COMMAS commas or more: refused without reading it field by field."""


def _longest_over(line: str, limit: int) -> bool:
    """Whether some comma-separated piece of `line` is longer than `limit` characters, in O(len / limit) calls
    of str.find: a run of limit + 1 characters without a comma contains a whole aligned block of
    (limit + 1) // 2 characters without one; only such blocks are measured out to their commas."""
    n, b = len(line), (limit + 1) // 2
    k = 0
    while k + b <= n:
        if line.find(",", k, k + b) < 0:
            start = line.rfind(",", 0, k) + 1
            end = line.find(",", k + b)
            end = n if end < 0 else end
            if end - start > limit:
                return True
            k = end + 1
        else:
            k += b
    return False


def _split(line: str) -> list[str] | _Wide:
    """One CSV line into fields (csv.reader with skipinitialspace); raises csv.Error for a field over
    MAX_FIELD_CHARS or bad quoting. Bounded work on hostile lines: a line without quotes is split by str.split
    (what csv.reader does to it, at a fraction of the cost), and one with more than MAX_COLUMNS fields comes back
    as a _Wide (its field count only); a line with quotes and MAX_QUOTED_COMMAS commas or more raises _QuotedWide."""
    if len(line) > MAX_FIELD_CHARS and _longest_over(line, MAX_FIELD_CHARS):
        # csv.Error only after it buffered the field: refuse long lines early
        raise csv.Error(f"a field of more than {MAX_FIELD_CHARS} characters; at most {MAX_FIELD_CHARS} are allowed")
    commas = line.count(",")
    if '"' not in line:
        if commas >= MAX_COLUMNS:
            return _Wide(commas + 1)
        fields = line.split(",")
        if ", " in line or line[:1] == " ":
            fields = [f.lstrip(" ") for f in fields]
        return fields
    if commas >= MAX_QUOTED_COMMAS:
        raise _QuotedWide(f"{commas} commas and quotes")
    return next(csv.reader([line], skipinitialspace=True), [])


_NUMBERS = re.compile(f"(?:{NUMBER.pattern})(?:\n(?:{NUMBER.pattern}))*")
"""Plain numbers, one per line (a field from csv.reader of one line never holds a line break)."""


def _numeric_columns(rows: list, line_numbers: list[int], width: int, col: dict[str, int], numeric: list[str],
                     checks: dict[str, tuple], row_of: dict[str, int], beyond: dict[int, list[int]]
                     ) -> dict[str, np.ndarray] | None:
    """The numeric columns of a CSV without a single problem in them, parsed a column at a time (one regex
    match, float() and vectorised range checks per column instead of per value): the same values as the per
    value loop of parse_measurements. None at the first doubt (a row that is not `width` fields, a value that
    is not a plain number, out of range or not finite): the caller then runs the per value loop, which names
    every problem in its order. `checks[c]` = (lo, hi, out of [lo, hi] is an error, |v| bound of a revolute
    joint or None); with limits="warn" a joint's out-of-limit rows go to `beyond` (line numbers)."""
    if any(f is None or len(f) != width for f in rows):
        return None
    out: dict[str, np.ndarray] = {}
    warned: dict[int, list[int]] = {}
    columns = list(zip(*rows))
    for c in numeric:
        raw = columns[col[c]]
        if not _NUMBERS.fullmatch("\n".join(raw)):  # spaces around a number are allowed: strip, try again
            raw = [x.strip() for x in raw]
            if not _NUMBERS.fullmatch("\n".join(raw)):
                return None
        v = np.fromiter(map(float, raw), float, len(raw))
        if not np.isfinite(v).all():
            return None
        lo, hi, strict, bound = checks[c]
        outside = ~((lo <= v) & (v <= hi))
        if outside.any():
            if strict:
                return None
            if bound is not None and not (np.abs(v) <= bound).all():
                return None
            warned[row_of[c]] = [line_numbers[i] for i in np.flatnonzero(outside)]
        elif bound is not None and not (np.abs(v) <= bound).all():
            return None
        out[c] = v
    beyond.update(warned)
    return out


def parse_measurements(data: bytes | str, model: RobotModel, instrument: str | None = None,
                       limits: str = "reject") -> Measurements:
    """Parse a contract CSV against the model; raises MeasurementError listing every problem.

    `instrument` names the noise preset (calib_core.instruments) for rows without a `sigma` column.
    `limits`: "reject" (default) makes a joint value outside the model's joint limits an error; "warn" accepts
    it (the plausibility bound of 100 turns still holds) and lists the extent per joint in
    `Measurements.out_of_limits`: {joint, unit, limits [lo, hi], rows (how many), min, max (of the column),
    first_rows (line numbers, at most MAX_LISTED_ROWS)}, all in the model's units.

    Every value is checked against the plausibility ranges of calib_core.model (coordinates, sigma, payload,
    temperature, timestamps, joint values), so nothing absurd but finite reaches the numerics.  At most
    MAX_LISTED_ERRORS errors are kept; `total` counts them all."""
    if instrument is not None and instrument not in INSTRUMENTS:
        raise MeasurementError([{"row": None, "column": None, "value": str(instrument)[:100],
                                 "message": f"unknown instrument: one of {', '.join(INSTRUMENTS)}"}])
    if limits not in LIMIT_MODES:
        raise MeasurementError([{"row": None, "column": None, "value": str(limits)[:100],
                                 "message": f"unknown limits mode: one of {', '.join(LIMIT_MODES)}"}])
    text = _decode(data)
    lines, commented = [], []
    for k, ln in enumerate(text.splitlines()):
        if not ln.strip():
            continue
        head = ln.lstrip()
        if head.startswith(("#", "//")):
            marker = 1 if head.startswith("#") else 2
            if head[marker:marker + 1].strip():  # '#P7,...': a point id or a row commented out without a space
                commented.append((k + 1, head, head[marker:]))
            continue
        lines.append((k + 1, ln))
    if not lines:
        raise MeasurementError([{"row": None, "column": None, "value": None, "message": "the file has no header and no data"}])
    errors: list[dict] = []
    total = 0

    def err(row, column, value, message):
        nonlocal total
        total += 1
        if len(errors) < MAX_LISTED_ERRORS:
            if isinstance(value, str) and len(value) > 80:
                value = value[:80] + f"... ({len(value)} characters)"
            errors.append({"row": row, "column": column, "value": value, "message": message})

    def fail():
        raise MeasurementError(errors, total=total)

    rows: list[list[str] | None] = []
    for line, ln in lines:
        try:
            rows.append(_split(ln))
        except csv.Error as exc:
            if "characters" in str(exc) or "field limit" in str(exc):
                why = f"a field is longer than {MAX_FIELD_CHARS} characters; no value of a measurement CSV is"
            elif isinstance(exc, _QuotedWide):
                why = (f"the line has quotes and {ln.count(',')} commas; a line with quotes is read up to "
                       f"{MAX_QUOTED_COMMAS - 1} commas (a measurement CSV has at most {MAX_COLUMNS} columns)")
            else:
                why = "the line cannot be read as CSV (check its quotes)"
            err(line, None, ln[:80], why)
            rows.append(None)
    if rows[0] is None:
        fail()
    header_line = lines[0][0]
    if len(rows[0]) > MAX_COLUMNS:
        n = len(rows[0])
        err(header_line, None, n, f"the header has {n} columns; at most {MAX_COLUMNS} are "
                                  f"allowed (the model has {model.n_joints} joints)")
        fail()
    header = [h.strip() for h in rows[0]]
    act = list(model.actuated_names)
    known = set(act) | {"x", "y", "z"} | set(OPTIONAL)
    for sep, called in ((";", "';'"), ("\t", "tabs")):  # a spreadsheet's export in a locale with decimal commas
        if len(header) == 1 and len(known & {h.strip().strip('"') for h in header[0].split(sep)}) >= 2:
            err(header_line, None, header[0], f"the fields are separated by {called}: the measurement CSV separates "
                                              "them by ',' and writes decimals with '.' (export it as CSV, comma "
                                              "delimited, with '.' as the decimal separator)")
            fail()

    seen = set()
    for h in header:
        if h in seen:
            err(header_line, h, h, "duplicated column")
        seen.add(h)
    coupled = [model.joint_names[j] for j in np.flatnonzero(model.is_coupled)]
    fixed = {model.joint_names[j] for j in np.flatnonzero(model.is_fixed)}
    taus = {f"tau_{model.joint_names[j]}": j for j in np.flatnonzero(model.moving)}
    known |= set(coupled) | set(taus)
    for h in header:
        if h in fixed:
            err(header_line, h, h, "a fixed row of the model has no joint value: leave this column out")
        elif h not in known:
            err(header_line, h, h, f"unknown column; expected the joints {act}, x, y, z and optionally "
                                   f"{list(OPTIONAL)}" + (f", the coupled joints {coupled}" if coupled else "")
                                   + ", tau_<joint>")
    for need in act + ["x", "y", "z"]:
        if need not in header:
            err(header_line, need, None, "missing column" + (" (a joint of the model)" if need in act else ""))
    if model.n_targets > 1 and "target" not in header:
        err(header_line, "target", None, f"missing column: the model has {model.n_targets} targets "
                                         f"({', '.join(model.target_names)}); say which one each row measures")
    quat = [c for c in QUATERNION if c in header]
    if quat and len(quat) < 4:
        err(header_line, None, quat, "an orientation needs all four columns qw, qx, qy, qz")
    if total:
        fail()

    col = {h: k for k, h in enumerate(header)}
    required = act + ["x", "y", "z"]
    for line, head, body in commented:
        try:
            fields = _split(body)
        except csv.Error:
            continue
        if len(fields) == len(header) and all(parse_number(fields[col[c]].strip())[0] is not None for c in required):
            err(line, "point" if "point" in col else None, head.split(",", 1)[0][:80],
                "this line starts with '#' or '//', which makes it a comment (contract section 2), yet it holds a "
                "whole data row; to keep the row, quote its point id (\"#P7\",...); to leave it out, put a space "
                "after the comment mark ('# P7,...')")
    if len(rows) == 1:
        err(header_line, None, None, "no data rows")
        fail()

    js = model.joint_scale()
    lo = model.limits[:, 0] / js
    hi = model.limits[:, 1] / js
    span = hi - lo
    slack = np.where(np.isfinite(span), LIMIT_TOL * np.maximum(1.0, np.abs(span)), 0.0)
    inside = list(zip((lo - slack).tolist(), (hi + slack).tolist()))  # per joint: the limits with their slack
    ls = LENGTH_TO_MM[model.length_unit]
    rev_max = revolute_bound(model.angle_unit)
    point_max = MAX_POINT_MM / ls
    sig_lo, sig_hi = SIGMA_RANGE_MM[0] / ls, SIGMA_RANGE_MM[1] / ls
    t_lo, t_hi = TEMPERATURE_RANGE_C
    unit = model.length_unit
    row_of = {name: j for j, name in enumerate(model.joint_names)}
    joint_cols = act + [c for c in coupled if c in col]
    numeric = joint_cols + ["x", "y", "z"] + [c for c in ("sequence", "temperature", "payload", "sigma") if c in col]
    values = {c: np.empty(len(rows) - 1) for c in numeric}
    optional_numeric = {c: np.full(len(rows) - 1, np.nan) for c in (*QUATERNION, *taus) if c in col}
    target_ix = np.zeros(len(rows) - 1, int) if "target" in col else None
    setup_raw = [""] * (len(rows) - 1) if "setup" in col else None
    target_of = {t: k for k, t in enumerate(model.target_names)}
    stamps = np.empty(len(rows) - 1) if "timestamp" in col else None
    ids: list[str] = []
    beyond: dict[int, list[int]] = {}  # limits="warn": joint -> line numbers of its out-of-limit values
    checks = {c: (inside[row_of[c]][0], inside[row_of[c]][1], limits == "reject",
                  None if model.prismatic[row_of[c]] else rev_max) for c in joint_cols}
    checks.update({c: (-point_max, point_max, True, None) for c in ("x", "y", "z")})
    checks.update({"sigma": (sig_lo, sig_hi, True, None), "payload": (0.0, MAX_PAYLOAD_KG, True, None),
                   "temperature": (t_lo, t_hi, True, None), "sequence": (-MAX_SEQUENCE, MAX_SEQUENCE, True, None)})
    fast = _numeric_columns(rows[1:], [ln for ln, _ in lines[1:]], len(header), col, numeric, checks, row_of, beyond)
    if fast is not None:
        values.update(fast)
    for i, ((line, _), fields) in enumerate(zip(lines[1:], rows[1:])):
        if fields is None:
            continue
        if len(fields) != len(header):
            err(line, None, len(fields), f"expected {len(header)} fields like the header, found {len(fields)}")
            continue
        for c in () if fast is not None else numeric:
            raw = fields[col[c]].strip()
            v, why = parse_number(raw)
            if why:
                err(line, c, raw, why)
                continue
            values[c][i] = v
            j = row_of.get(c)
            if j is not None:
                outside = not inside[j][0] <= v <= inside[j][1]
                if outside and limits == "reject":
                    err(line, c, raw, f"outside the joint limits [{lo[j]:g}, {hi[j]:g}] {model.joint_unit(j)}")
                elif not model.prismatic[j] and not abs(v) <= rev_max:
                    err(line, c, raw, f"implausible joint value: |{c}| must be at most {rev_max:g} "
                                      f"{model.angle_unit} (100 turns)")
                elif outside:
                    beyond.setdefault(j, []).append(line)
            elif c in ("x", "y", "z"):
                if not abs(v) <= point_max:
                    err(line, c, raw, f"implausible coordinate: |{c}| must be at most {point_max:g} {unit}"
                                      + (f" ({MAX_POINT_MM / 1000:g} m)" if unit != "m" else "")
                                      + " from the origin of the measurement frame")
            elif c == "sigma":
                if not sig_lo <= v <= sig_hi:
                    err(line, c, raw, f"sigma must be between {sig_lo:g} and {sig_hi:g} {unit} "
                                      "(the 1-sigma uncertainty of a measured point)")
            elif c == "payload":
                if not 0 <= v <= MAX_PAYLOAD_KG:
                    err(line, c, raw, f"payload must be between 0 and {MAX_PAYLOAD_KG:g} kg")
            elif c == "temperature" and not t_lo <= v <= t_hi:
                err(line, c, raw, f"temperature outside {t_lo:g}..{t_hi:g} deg C")
            elif c == "sequence" and not abs(v) <= MAX_SEQUENCE:
                err(line, c, raw, f"sequence must be at most {MAX_SEQUENCE:g} in size (the measurement's place "
                                  "in the session's order)")
        for c, arr in optional_numeric.items():
            raw = fields[col[c]].strip()
            if not raw:
                continue  # a point row among 6-D rows; a load not measured on this row
            v, why = parse_number(raw)
            if why:
                err(line, c, raw, why)
            elif c in taus and not abs(v) <= MAX_TAU:
                err(line, c, raw, f"implausible joint load: at most {MAX_TAU:g} N*m (or N)")
            else:
                arr[i] = v
        if quat:
            qv = np.array([optional_numeric[c][i] for c in QUATERNION])
            if np.isnan(qv).any() and not np.isnan(qv).all():
                err(line, "qw", None, "give all four of qw, qx, qy, qz or none (a point row)")
            elif not np.isnan(qv).any() and not abs(np.linalg.norm(qv) - 1.0) <= QUATERNION_TOL:
                err(line, "qw", f"|q| = {np.linalg.norm(qv):.6g}", "the orientation must be a unit quaternion "
                                                                   f"(|q| within {QUATERNION_TOL:g} of 1)")
        if target_ix is not None:
            raw = fields[col["target"]].strip()
            if raw not in target_of:
                err(line, "target", raw, f"unknown target: one of {', '.join(model.target_names)}")
            else:
                target_ix[i] = target_of[raw]
        if setup_raw is not None:
            raw = fields[col["setup"]].strip()
            why = name_problem(raw, what="setup name", csv_column=False)
            if why:
                err(line, "setup", raw, why)
            setup_raw[i] = raw
        if stamps is not None:
            raw = fields[col["timestamp"]].strip()
            try:
                stamps[i] = _parse_time(raw)
            except (ValueError, OverflowError):
                err(line, "timestamp", raw, "not an ISO 8601 timestamp (e.g. 2026-11-03T08:00:19+00:00)")
            else:
                if not TIMESTAMP_RANGE_S[0] <= stamps[i] < TIMESTAMP_RANGE_S[1]:
                    err(line, "timestamp", raw, f"timestamp outside {TIMESTAMP_RANGE_UTC[0][:10]} .. "
                                                f"{TIMESTAMP_RANGE_UTC[1][:10]} (UTC)")
        ids.append(fields[col["point"]].strip() if "point" in col else str(i + 1))
    if total:
        fail()
    if "point" in col:
        dup: dict[str, int] = {}
        for (line, _), pid in zip(lines[1:], ids):
            if pid in dup:
                err(line, "point", pid, f"duplicated point id (first on line {dup[pid]})")
            dup.setdefault(pid, line)
        if total:
            fail()

    out_of_limits = []
    for j in sorted(beyond):
        col_j = values[model.joint_names[j]]
        out_of_limits.append({"joint": model.joint_names[j], "unit": model.joint_unit(j),
                              "limits": [float(b) if math.isfinite(b) else None for b in (lo[j], hi[j])],
                              "rows": len(beyond[j]), "min": float(col_j.min()), "max": float(col_j.max()),
                              "first_rows": beyond[j][:MAX_LISTED_ROWS]})
    joints = model.expand_joints(np.column_stack([values[c] * js[row_of[c]] for c in act]))
    for c in joint_cols[len(act):]:  # a coupled joint's column must agree with its coupling
        j = row_of[c]
        off = np.abs(values[c] * js[j] - joints[:, j]) / js[j]
        for k in np.flatnonzero(off > COUPLING_TOL)[:MAX_LISTED_ERRORS]:
            err(lines[1 + k][0], c, f"{values[c][k]:g}", f"disagrees with the coupling by {off[k]:.4g} "
                                                         f"{model.joint_unit(j)} (the model computes "
                                                         f"{joints[k, j] / js[j]:.6g})")
    if total:
        fail()
    setup = setup_names = None
    if setup_raw is not None:
        setup_names = tuple(dict.fromkeys(setup_raw))
        setup = np.array([setup_names.index(v) for v in setup_raw]) if len(setup_names) > 1 else None
    orientation = None
    if quat:
        orientation = np.column_stack([optional_numeric[c] for c in QUATERNION])
        orientation /= np.linalg.norm(orientation, axis=1, keepdims=True)
    tau = None
    if any(c in col for c in taus):
        tau = np.full((len(rows) - 1, model.n_joints), np.nan)
        for c, j in taus.items():
            if c in optional_numeric:
                tau[:, j] = optional_numeric[c]
    points = np.column_stack([values[c] for c in ("x", "y", "z")]) * ls
    return Measurements(
        joints=joints, points=points, point_ids=ids, timestamp=stamps, sequence=values.get("sequence"),
        temperature=values.get("temperature"), payload=values.get("payload"),
        sigma=values["sigma"] * ls if "sigma" in values else None, instrument=instrument,
        out_of_limits=out_of_limits, target=target_ix if model.n_targets > 1 else None, setup=setup,
        setup_names=setup_names if setup is not None else ("",), orientation=orientation, tau=tau,
    )


def write_measurements(meas: Measurements, model: RobotModel) -> str:
    """The measurements as contract CSV in the model's units (actuated joints; section 5 columns when present)."""
    ls = LENGTH_TO_MM[model.length_unit]
    act = model.actuated
    cols = ["point", *model.actuated_names, "x", "y", "z"]
    data = [np.asarray(meas.point_ids or [f"P{i + 1:04d}" for i in range(meas.n_poses)], dtype=object)]
    data += list((meas.joints[:, act] / model.joint_scale()[act]).T) + list((meas.points / ls).T)
    nm = 6 + round(math.log10(ls))  # decimals of 1 nm in the model's length unit (6 in mm, 9 in m)
    fmt = ["{}"] + ["{:.9g}"] * len(act) + [f"{{:.{nm}f}}"] * 3
    if meas.timestamp is not None:
        cols.append("timestamp")
        data.append(np.array([datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="seconds")
                              for t in meas.timestamp], dtype=object))
        fmt.append("{}")
    for name, arr, f in (("sequence", meas.sequence, "{:.15g}"), ("temperature", meas.temperature, "{:.3f}"),
                         ("payload", meas.payload, "{:.4g}"),
                         ("sigma", None if meas.sigma is None else meas.sigma / ls, "{:.6g}")):
        if arr is not None:
            cols.append(name)
            data.append(arr)
            fmt.append(f)
    if meas.target is not None:
        cols.append("target")
        data.append(np.array(model.target_names, dtype=object)[meas.target])
        fmt.append("{}")
    if meas.setup is not None:
        cols.append("setup")
        data.append(np.array(meas.setup_names, dtype=object)[meas.setup])
        fmt.append("{}")
    extra = []
    if meas.orientation is not None:
        extra += [(c, meas.orientation[:, k], "{:.9f}") for k, c in enumerate(QUATERNION)]
    if meas.tau is not None:
        extra += [(f"tau_{model.joint_names[j]}", meas.tau[:, j], "{:.6g}") for j in range(model.n_joints)
                  if not np.isnan(meas.tau[:, j]).all()]
    for name, arr, f in extra:
        cols.append(name)
        data.append(np.array(["" if np.isnan(v) else f.format(v) for v in arr], dtype=object))
        fmt.append("{}")
    out = _io.StringIO()
    out.write(",".join(cols) + "\n")
    for row in zip(*data):
        out.write(",".join(f.format(v) for f, v in zip(fmt, row)) + "\n")
    return out.getvalue()
