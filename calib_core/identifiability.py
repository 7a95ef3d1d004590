"""Which parameters the actual pose set can identify, which are redundant (and with what), which do nothing.

Column-normalised identification Jacobian, rank by SVD, then a greedy pivoted Gram-Schmidt in a
preference order: base pose first (always unknown), then tool, then a, alpha, d, theta of every joint
in chain order, and beta last, so that beta enters only where it is needed, which is at
parallel axes (Hayati; Wang et al. 2023, section 4.2: beta instead of d).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NONFUNCTIONAL_TOL = 1e-9
"""A column whose norm is below this fraction of the largest has no effect on the measured point."""
REDUNDANT_TOL = 1e-3
"""A normalised column whose part orthogonal to the kept ones is below this is redundant: the pose set
cannot tell it from the kept ones (their condition number would pass ~1e3)."""


@dataclass(frozen=True)
class Identifiability:
    names: list[str]
    identifiable: list[int]  # indices into the full vector, in selection order
    redundant: dict[int, list[int]]  # rejected index -> the kept indices it is confounded with
    nonfunctional: list[int]
    rank: int
    condition_number: float  # of the column-normalised Jacobian of the identifiable set
    observability_index: float  # Borm & Menq O1 = (prod sigma)^(1/p) / sqrt(m), normalised columns
    singular_values: np.ndarray

    def to_dict(self) -> dict:
        n = self.names
        return {
            "rank": self.rank,
            "n_parameters": len(n),
            "identifiable": [n[i] for i in self.identifiable],
            "redundant": [{"name": n[i], "confounded_with": [n[k] for k in ks]} for i, ks in self.redundant.items()],
            "nonfunctional": [n[i] for i in self.nonfunctional],
            "condition_number": self.condition_number,
            "observability_index": self.observability_index,
        }


def preference_order(names: list[str]) -> list[int]:
    """Base, tool, then the joint parameters in chain order with every beta last."""
    base = [i for i, s in enumerate(names) if s.startswith("base.")]
    tool = [i for i, s in enumerate(names) if s.startswith("tool.")]
    joint = [i for i, s in enumerate(names) if not s.startswith(("base.", "tool.")) and not s.endswith(".beta")]
    beta = [i for i, s in enumerate(names) if not s.startswith(("base.", "tool.")) and s.endswith(".beta")]
    return base + tool + joint + beta


def analyse(J: np.ndarray, names: list[str], order: list[int] | None = None) -> Identifiability:
    """Identifiability of the parameters from the stacked Jacobian J (m, P) of the real pose set."""
    m, P = J.shape
    norms = np.linalg.norm(J, axis=0)
    nonfunctional = [i for i in range(P) if norms[i] <= NONFUNCTIONAL_TOL * norms.max()]
    A = J / np.where(norms > 0, norms, 1.0)
    order = preference_order(names) if order is None else order
    basis = np.empty((m, P))
    kept: list[int] = []
    rejected: list[int] = []
    for i in order:
        if i in nonfunctional:
            continue
        Q = basis[:, : len(kept)]
        v = A[:, i]
        for _ in range(2):  # re-orthogonalise once: classical Gram-Schmidt twice is stable
            v = v - Q @ (Q.T @ v)
        norm = np.linalg.norm(v)
        if norm > REDUNDANT_TOL:
            basis[:, len(kept)] = v / norm
            kept.append(i)
        else:
            rejected.append(i)
    G = A.T @ A  # the small Gram matrix serves the rest: partners and singular values
    redundant = {}
    if rejected:
        coef = np.linalg.solve(G[np.ix_(kept, kept)], G[np.ix_(kept, rejected)])
        for k, i in enumerate(rejected):
            c = np.abs(coef[:, k])
            redundant[i] = [kept[j] for j in np.argsort(-c) if c[j] > 0.05 * c.max()]
    s = np.sqrt(np.clip(np.linalg.eigvalsh(G[np.ix_(kept, kept)])[::-1], 0.0, None))
    return Identifiability(
        names=names, identifiable=kept, redundant=redundant, nonfunctional=nonfunctional, rank=len(kept),
        condition_number=float(s[0] / s[-1]), observability_index=float(np.exp(np.log(s).mean()) / np.sqrt(m)),
        singular_values=s,
    )
