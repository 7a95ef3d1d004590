"""Random serial chains for property tests: any mix of revolute and prismatic joints."""
import numpy as np

from calib_core.model import parse_model


def random_chain(rng: np.random.Generator, n: int | None = None):
    n = n or int(rng.integers(2, 8))
    joints = []
    for j in range(n):
        prismatic = rng.random() < 0.3
        joints.append({
            "name": f"Q{j + 1}", "type": "prismatic" if prismatic else "revolute",
            "a": float(rng.uniform(0, 500)), "alpha": float(rng.choice([0.0, 90.0, -90.0])),
            "d": float(rng.uniform(0, 400)), "theta": float(rng.uniform(-30, 30)), "beta": 0.0,
            "limits": [0.0, 800.0] if prismatic else [-150.0, 150.0],
        })
    return parse_model({"name": "random", "convention": "mdh", "units": {"length": "mm", "angle": "deg"},
                        "joints": joints, "tool": rng.uniform(-100, 100, 3).tolist()})
