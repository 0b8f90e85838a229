"""The material's viscous damping β (s) estimated by profiling a fit's cost over β.

β enters the simulation as a declared property (capture.toml [material] damping; Kelvin–Voigt on the Green strain,
stages.sim.materials.viscous_density).  Where a capture does not declare it, ``rsl adapt --damping auto`` takes
the β whose fit explains the first frames best: for each candidate β the estimator runs over those frames with
E and ν fitted as usual, and c(β) is the mean loss of its newest frames at the windows' estimates.  This is the
profile of the cost over β (E and ν minimised out), searched on a log grid of half decades, extended where the
minimum lies at its edge, and refined by one parabola in log β through the lowest point and its neighbours.

Nothing here reads files or simulates: :func:`profile_damping` calls the cost it is given.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

DAMPING_GRID = (1e-3, 10 ** -2.5, 1e-2, 10 ** -1.5)
"""The positive β (s) tried first (half decades), beside β = 0.  At the bar's first bending mode (≈ 8 Hz) they are
damping ratios ζ = βω/2 of 2.5, 8, 25 and 80 %."""
DAMPING_LIMITS = (1e-4, 10 ** -0.5)
"""The grid is extended by half decades beyond its edge while the lowest cost lies there, within these bounds (s):
up to two more points, so 1e-4 and 0.32 s are the farthest tried."""
FLAT_PROFILE = 0.05
"""A profile whose cost varies by less than this fraction of its lowest value does not determine β (the frames
hardly move, or move too slowly for the damping to show): :attr:`DampingProfile.flat`."""


@dataclass
class DampingProfile:
    """β (s) with the lowest cost, every (β, cost) tried in the order tried, and whether the profile was flat."""
    beta: float
    tried: list = field(default_factory=list)
    flat: bool = False

    def within(self, fraction: float = FLAT_PROFILE) -> tuple[float, float]:
        """(smallest, largest) β tried whose cost is within ``fraction`` of the lowest: how well the frames pin β."""
        lowest = min(c for _, c in self.tried)
        near = [b for b, c in self.tried if c <= (1 + fraction) * lowest]
        return min(near), max(near)

    def as_record(self) -> dict:
        return {"beta": self.beta, "tried": [[b, c] for b, c in self.tried], "flat": self.flat,
                "within_5_percent": list(self.within())}


def profile_damping(cost: Callable[[float], float], grid: tuple = DAMPING_GRID, limits: tuple = DAMPING_LIMITS,
                    flat: float = FLAT_PROFILE, on_try: Callable[[float, float], None] | None = None
                    ) -> DampingProfile:
    """The β ≥ 0 minimising ``cost`` (β in s -> a cost ≥ 0) by the search of the module docstring: β = 0 and the
    log grid (equally spaced in log β), the grid extended by one spacing beyond an edge that holds the lowest
    cost (up to twice, inside ``limits``), then the vertex of the parabola in log β through the lowest grid point
    and its two neighbours.  A cost that fails (inf or nan) counts as the worst.  ``on_try(β, c)`` sees each
    evaluation."""
    tried: dict[float, float] = {}

    def f(b: float) -> float:
        if b not in tried:
            c = float(cost(b))
            tried[b] = c if math.isfinite(c) else math.inf
            if on_try is not None:
                on_try(b, tried[b])
        return tried[b]

    f(0.0)
    xs = [math.log10(b) for b in grid]
    h = xs[1] - xs[0]
    for x in xs:
        f(10 ** x)
    for _ in range(2):  # the lowest at an edge: one more spacing that way
        i = min(range(len(xs)), key=lambda k: f(10 ** xs[k]))
        if i == 0 and xs[0] - h >= math.log10(limits[0]) - 1e-9:
            xs.insert(0, xs[0] - h)
        elif i == len(xs) - 1 and xs[-1] + h <= math.log10(limits[1]) + 1e-9:
            xs.append(xs[-1] + h)
        else:
            break
        f(10 ** xs[0] if i == 0 else 10 ** xs[-1])
    i = min(range(len(xs)), key=lambda k: f(10 ** xs[k]))
    if 0 < i < len(xs) - 1:
        lo, mid, hi = (f(10 ** xs[k]) for k in (i - 1, i, i + 1))
        curv = lo - 2 * mid + hi
        if math.isfinite(curv) and curv > 0:
            f(10 ** (xs[i] - 0.5 * h * (hi - lo) / curv))  # inside (x_{i−1}, x_{i+1}): mid is the lowest of the three
    beta = min(tried, key=lambda b: (tried[b], b))
    finite = [c for c in tried.values() if math.isfinite(c)]
    lowest = min(finite) if finite else math.inf
    is_flat = bool(finite) and len(finite) == len(tried) and max(finite) - lowest <= flat * lowest
    return DampingProfile(beta, list(tried.items()), is_flat)
