"""Benchmarks: one command each (`python -m benchmarks.NAME`), peers measured in the same run."""
import time


def best_time(fn, repeats: int) -> tuple[float, object]:
    """Best wall time (s) of `repeats` calls of fn, and its last result."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out
