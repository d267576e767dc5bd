"""How many samples plain path tracing needs to reach an error: the equal-error spp of a result."""
from __future__ import annotations

import math
from typing import Sequence

__all__ = ["spp_to_match"]


def spp_to_match(raw_mse: Sequence[float], target_mse: float) -> float:
    """Samples per pixel plain path tracing needs to reach ``target_mse``, from its measured curve
    ``raw_mse[n-1]`` at n spp: interpolated where reached, else extrapolated with MSE ~ 1/spp from the
    last point."""
    for n, m in enumerate(raw_mse, start=1):
        if m <= target_mse:
            if n == 1:
                return 1.0
            m0 = raw_mse[n - 2]  # log-log interpolation between n-1 and n
            s = (math.log(m0) - math.log(target_mse)) / max(math.log(m0) - math.log(m), 1e-12)
            return float((n - 1) * (n / (n - 1)) ** s)
    n = len(raw_mse)
    return float(n * raw_mse[-1] / max(target_mse, 1e-30))
