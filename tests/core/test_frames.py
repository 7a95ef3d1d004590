"""calib_core.frames: chains of arbitrary rigid transforms folded exactly into contract MD-H rows.

The reference point is computed here with plain 4x4 products of the original links; the folded
model goes through the contract JSON, calib_core.model.parse_model and calib_core.kinematics.forward.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from calib_core import frames
from calib_core.kinematics import forward, nominal_vector
from calib_core.model import parse_model

TOL_MM = 1e-8
"""Rounding only: the median chain folds to 6e-13 mm, but a nearly parallel pair of axes (alpha 1e-8 rad) amplifies
it; 1.5e-9 mm on a 2 m chain (CI seed 1763102935, k = 28), 7e-10 at most on 2400 other drawn chains. A folding
error shows in millimetres."""


# --- independent reference --------------------------------------------------------------

def rand_rot(rng: np.random.Generator) -> np.ndarray:
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def rz3(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rx3(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def hom(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


RELATIONS = ("general", "parallel", "antiparallel", "intersecting", "coincident", "nearly_parallel",
             "perpendicular_intersecting")


def link_transform(rng: np.random.Generator, relation: str) -> np.ndarray:
    """A fixed transform whose z axis has the given relation to the previous joint's z axis."""
    off = rng.uniform(-400, 400, 3)
    phi = rng.uniform(-math.pi, math.pi)
    if relation == "general":
        return hom(rand_rot(rng), off)
    if relation == "parallel":
        return hom(rz3(phi), off)
    if relation == "antiparallel":
        return hom(rz3(phi) @ rx3(math.pi), off)
    if relation == "intersecting":
        return hom(rand_rot(rng), [0.0, 0.0, off[2]])
    if relation == "coincident":
        return hom(rz3(phi), [0.0, 0.0, off[2]])
    if relation == "nearly_parallel":  # tilted by 1e-8 rad: below PARALLEL_SIN, Hayati's beta takes it
        return hom(rz3(phi) @ rx3(1e-8), off)
    if relation == "perpendicular_intersecting":
        return hom(rz3(phi) @ rx3(math.pi / 2), [0.0, 0.0, off[2]])
    raise AssertionError(relation)


def reference_point(links: list[frames.Link], q: np.ndarray, tool: np.ndarray) -> np.ndarray:
    """Plain 4x4 products of the original chain, written without calib_core."""
    out = []
    for qi in q:
        T, j = np.eye(4), 0
        for link in links:
            T = T @ np.asarray(link.transform)
            if link.type == "revolute":
                T = T @ hom(rz3(qi[j]), [0, 0, 0])
                j += 1
            elif link.type == "prismatic":
                T = T @ hom(np.eye(3), [0, 0, qi[j]])
                j += 1
        out.append((T @ np.r_[tool, 1.0])[:3])
    return np.array(out)


def random_links(rng: np.random.Generator, n: int, relations=None, base_relation="general"):
    links = []
    for k in range(n):
        rel = base_relation if k == 0 else (relations[k - 1] if relations else rng.choice(RELATIONS))
        typ = "prismatic" if rng.random() < 0.3 else "revolute"
        links.append(frames.Link(link_transform(rng, rel), typ, f"Q{k + 1}",
                                 (-1000.0, 1000.0) if typ == "prismatic" else None))
        if relations is None and rng.random() < 0.2:  # sometimes a fixed frame between joints
            links.append(frames.Link(hom(rand_rot(rng), rng.uniform(-200, 200, 3)), "fixed"))
    return links


def random_q(rng, links, N=20):
    types = [lk.type for lk in links if lk.type != "fixed"]
    return np.column_stack([rng.uniform(-500, 500, N) if t == "prismatic" else rng.uniform(-math.pi, math.pi, N)
                            for t in types])


def folded_point(folded: frames.Folded, q: np.ndarray, angle_unit="deg") -> np.ndarray:
    """Through contract JSON -> parse_model -> kinematics.forward, then into the original base frame."""
    model = parse_model(folded.model_dict("folded", length_unit="mm", angle_unit=angle_unit))
    p = forward(model, nominal_vector(model), q)
    return p @ folded.base[:3, :3].T + folded.base[:3, 3]


def check(links, tool, rng, N=20):
    folded = frames.fold_links(links, tool)
    q = random_q(rng, links, N)
    ref = reference_point(links, q, tool)
    for unit in ("deg", "rad"):
        err = np.abs(folded_point(folded, q, unit) - ref).max()
        assert err < TOL_MM, (unit, err)
    assert np.abs(folded.forward(q) - ref).max() < TOL_MM
    # the base transform is rigid
    R = folded.base[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12
    return folded


# --- tests ------------------------------------------------------------------------------

@pytest.mark.parametrize("k", range(40))
def test_random_chains_fold_exactly(seed, k):
    rng = np.random.default_rng([seed, k])
    n = int(rng.integers(1, 9))
    links = random_links(rng, n)
    tool = rng.uniform(-150, 150, 3)
    check(links, tool, rng)


@pytest.mark.parametrize("relation", RELATIONS)
def test_every_relation_between_consecutive_axes(seed, relation):
    rng = np.random.default_rng([seed, RELATIONS.index(relation)])
    links = random_links(rng, 6, relations=[relation] * 5)
    folded = check(links, rng.uniform(-150, 150, 3), rng)
    rows = folded.rows
    if relation in ("parallel", "antiparallel", "coincident"):
        assert np.all(rows[1:, 4] == 0.0)  # exactly parallel: beta = 0
        assert np.all(rows[:-1, 2] == 0.0)  # Hayati: d_i = 0 instead of a far-away common normal
        assert np.allclose(np.abs(rows[1:, 1]), 0.0 if relation != "antiparallel" else math.pi)
    if relation == "coincident":
        assert np.all(rows[1:, 0] == 0.0) and np.all(rows[:, 3] == 0.0)
    if relation == "nearly_parallel":
        assert np.all(np.abs(rows[:-1, 4]) < 2e-8) and np.any(rows[:-1, 4] != 0.0)
        assert np.all(np.abs(rows[:, 2]) < 1e3)  # no common normal kilometres away
    if relation in ("intersecting", "perpendicular_intersecting"):
        assert np.all(rows[1:, 0] == 0.0) and np.all(rows[:, 4] == 0.0)
    if relation == "perpendicular_intersecting":
        assert np.allclose(np.abs(rows[1:, 1]), math.pi / 2)


def test_prismatic_only_and_single_joint(seed):
    rng = np.random.default_rng(seed)
    for types in (["prismatic"] * 4, ["revolute"], ["prismatic"]):
        links = [frames.Link(link_transform(rng, "general"), t,
                             limits=(-1000.0, 1000.0) if t == "prismatic" else (-3.0, 3.0)) for t in types]
        check(links, rng.uniform(-150, 150, 3), rng)


def test_base_kept_when_first_axis_is_base_z():
    # a z-up base whose z is the first joint axis: the MD-H base is the original one, gravity unchanged
    links = [frames.Link(frames.trans(z=300.0) @ frames.rot_z(0.3), name="A"),
             frames.Link(frames.trans(50.0, 0, 0) @ frames.rot_x(-math.pi / 2), name="B")]
    folded = frames.fold_links(links, (100.0, 20.0, 5.0), gravity=(0, 0, -9.81))
    assert np.array_equal(folded.base, np.eye(4))
    assert folded.gravity.tolist() == [0.0, 0.0, -9.81]
    assert folded.rows[0].tolist() == [0.0, 0.0, 300.0, 0.3, 0.0]
    # a base offset along the first axis, or a parallel first axis: still z-up
    links2 = [frames.Link(frames.trans(120.0, -40.0, 300.0) @ frames.rot_z(0.3))] + links[1:]
    f2 = frames.fold_links(links2, (100.0, 20.0, 5.0))
    assert np.allclose(f2.base[:3, 2], [0, 0, 1], atol=0) and np.allclose(f2.gravity, [0, 0, -9.81], atol=0)


def test_gravity_rotated_into_the_folded_base(seed):
    rng = np.random.default_rng(seed)
    links = random_links(rng, 4)
    g = np.array([0.0, 0.0, -9.81])
    folded = frames.fold_links(links, np.zeros(3), gravity=g)
    assert np.allclose(folded.base[:3, :3] @ folded.gravity, g, atol=1e-12)


def test_fold_axes_matches_fold_links(seed):
    rng = np.random.default_rng(seed)
    links = random_links(rng, 5)
    tool = rng.uniform(-100, 100, 3)
    axes, tool_base = frames.links_to_axes(links, tool)
    a = frames.fold_axes(axes, tool_base)
    b = frames.fold_links(links, tool)
    assert np.array_equal(a.rows, b.rows) and np.array_equal(a.tool, b.tool)
    # Axis.from_frame and unnormalised directions give the same fold
    T = np.eye(4)
    frames_ = []
    for lk in links:
        T = T @ np.asarray(lk.transform)
        if lk.type != "fixed":
            frames_.append(frames.Axis.from_frame(T, lk.type, lk.name, lk.limits))
    c = frames.fold_axes(frames_, tool_base)
    assert np.allclose(c.rows, b.rows, atol=1e-12)
    scaled = [frames.Axis(ax.point, 3.0 * np.asarray(ax.direction), ax.type, ax.name, ax.limits) for ax in axes]
    assert np.allclose(frames.fold_axes(scaled, tool_base).rows, b.rows, atol=1e-9)


def test_model_dict_contract_and_errors():
    links = [frames.Link(frames.trans(z=100.0), "prismatic", "Z", (0.0, 500.0)),
             frames.Link(frames.rot_x(math.pi / 2) @ frames.trans(30.0), "revolute", "R", (-2.0, 2.0))]
    folded = frames.fold_links(links, (10.0, 0.0, 0.0))
    doc = folded.model_dict("demo", length_unit="mm", angle_unit="deg")
    assert doc["convention"] == "mdh" and doc["units"] == {"length": "mm", "angle": "deg"}
    assert [j["name"] for j in doc["joints"]] == ["Z", "R"]
    assert doc["joints"][0]["limits"] == [0.0, 500.0]
    assert doc["joints"][1]["limits"] == pytest.approx([math.degrees(-2.0), math.degrees(2.0)])
    assert doc["joints"][1]["alpha"] == pytest.approx(90.0)
    parse_model(doc)
    with pytest.raises(ValueError, match="prismatic"):
        folded.model_dict("x", limits=[None, None])
    with pytest.raises(ValueError, match="rigid"):
        frames.fold_links([frames.Link(np.diag([1.0, 1.0, 1.1, 1.0]))])
    rounded = np.array([[-0.866, 0, 0.5, 0.19], [0, 1, 0, 0.088], [-0.5, 0, -0.866, -0.256], [0, 0, 0, 1]])
    with pytest.raises(ValueError, match="nearest_rotation"):
        frames.fold_links([frames.Link(rounded)])
    fixed = frames.nearest_rotation(rounded)
    assert np.abs(fixed[:3, :3].T @ fixed[:3, :3] - np.eye(3)).max() < 1e-14
    assert np.abs(fixed - rounded).max() < 1e-4
    frames.fold_links([frames.Link(fixed)])
