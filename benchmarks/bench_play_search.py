"""The search for a gear play's switch: refits spent (each a linearised joint refit) and fit reached, stopping where the
switch has settled (diagnosis.plays.PLAY_SETTLED) against running every pass, on plays hidden in the independent world.

Run: .venv/bin/python -m benchmarks.bench_play_search [--seeds 40] [--settled 0.002]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from calib_core.diagnosis import plays as P  # noqa: E402
from calib_core.diagnosis.fitter import _Fitter  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.robots import spray7  # noqa: E402
from calib_world import World  # noqa: E402
from calib_world.scenarios import hide  # noqa: E402

MIN_SWITCHED = 0.1
"""Only plays whose joint's load takes each sign on at least this share of the poses (else no switch to find)."""


def _world(model, kind: str, seed: int):
    """150 measured poses of a world hiding a play of 3-8x the noise on a joint whose load changes sign."""
    size = float(np.exp(np.random.default_rng((seed, 2)).uniform(np.log(3.0), np.log(8.0))))
    for attempt in range(20):
        world = World(model, seed + attempt)
        info = hide(world, kind, size, np.random.default_rng((seed, attempt, 1)))
        tau = world.robot.joint_loads(info["q"], None)[:, model.joint_names.index(info["joints"][0])]
        if min((tau > 0).mean(), (tau < 0).mean()) >= MIN_SWITCHED:
            break
    return info, world.measure(info["q"], payload_kg=info["payload_kg"], temperature=info["temperature"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--settled", type=float, default=P.PLAY_SETTLED)
    args = ap.parse_args(argv)
    model = parse_model(spray7())
    fits, ratios = {args.settled: 0, -1.0: 0}, []
    for seed in range(1, args.seeds + 1):
        for kind in ("hard_backlash", "soft_backlash"):
            info, meas = _world(model, kind, seed)
            fit = _Fitter(model, meas, None, 5, None, 1.0)
            geo = fit()
            j = model.joint_names.index(info["joints"][0])
            found = []
            for settled in fits:  # the threshold, then every pass (never settled)
                P.PLAY_SETTLED = settled
                n, refit = [0], P._with_play_refitted

                def counted(*a, **k):
                    n[0] += 1
                    return refit(*a, **k)

                P._with_play_refitted = counted
                found.append(P._identified_backlash(geo, meas, geo.sigma_mm, geo.x, [j]))
                P._with_play_refitted = refit
                fits[settled] += n[0]
            rss = lambda p: float(np.sum(fit((p,), geo.x, folds=0).solution.residual ** 2))  # noqa: E731
            ratios += [rss(a) / rss(b) for a, b in zip(*found)]
    r = np.array(ratios)
    print(f"| worlds (hard, soft play) | refits, settled at {args.settled:g} | refits, every pass | fewer | rss ratio min / mean / max |")
    print("|---|---|---|---|---|")
    print(f"| {2 * args.seeds} | {fits[args.settled]} | {fits[-1.0]} | {100 * (1 - fits[args.settled] / fits[-1.0]):.0f} % "
          f"| {r.min():.3f} / {r.mean():.4f} / {r.max():.3f} |")


if __name__ == "__main__":
    main()
