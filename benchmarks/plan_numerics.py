"""Numerical health of the planner's rank-three updates when the measured set is blind to a parameter.

Per draw: 60 candidate blocks A (3 x 6, standard normal), a measured set of 40 rows that never moves one drawn
parameter (information 1e-6 there, so S ~ 1e6 along it), three candidates added one by one; the state is
compared with one built from scratch on the same information (max |S - S_fresh|), and the swap gains of the
first added pose with the direct log det changes. Counts the draws that raised (LinAlgError) instead.
Run: .venv/bin/python -m benchmarks.plan_numerics [--draws 200]
"""
from __future__ import annotations

import argparse

import numpy as np

from calib_core.plan import _Sequential


def draw(seed: int) -> tuple[float, float]:
    """(max |S - S_fresh|, max |swap gain - direct|) of one draw."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(60, 3, 6))
    J = rng.normal(size=(40, 6))
    J[:, int(rng.integers(6))] = 0.0
    M0 = 1e-6 * np.eye(6) + J.T @ J
    s = _Sequential(A, M0)
    added = rng.choice(60, 3, replace=False)
    for k in added:
        s.add(int(k))
    M = M0 + sum(A[k].T @ A[k] for k in added)
    fresh = _Sequential(A, M)
    k = int(added[0])
    direct = np.array([np.linalg.slogdet(M - A[k].T @ A[k] + A[j].T @ A[j])[1] - np.linalg.slogdet(M)[1]
                       for j in range(60)])
    return float(np.abs(s.S - fresh.S).max()), float(np.abs(fresh.swap_gain(k) - direct).max())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200)
    args = ap.parse_args()
    update, swap, failed = [], [], 0
    for seed in range(args.draws):
        try:
            u, g = draw(seed)
        except np.linalg.LinAlgError:
            failed += 1
            continue
        update.append(u)
        swap.append(g)
    print("| draws | raised | update vs fresh: median / max | swap gain vs direct: median / max |")
    print("|---|---|---|---|")
    print(f"| {args.draws} | {failed} | {np.median(update):.1e} / {max(update):.1e} | "
          f"{np.median(swap):.1e} / {max(swap):.1e} |")


if __name__ == "__main__":
    main()
