import math

import pytest

from torchmanifold.pipeline.schedule import BandwidthSchedule, bandwidth_factor, bandwidth_factors


@pytest.mark.parametrize("alpha", [0.3, 2 / 3, 0.8, 1.0])
def test_ratio_rule(alpha):
    f = bandwidth_factors(50, alpha)
    for i in range(1, 50):  # sigma_{i+1}^2 / sigma_i^2 = (i + a) / (i + 1), 1-based
        assert f[i] ** 2 / f[i - 1] ** 2 == pytest.approx((i + alpha) / (i + 1), rel=1e-12)
        assert bandwidth_factor(i + 1, alpha) == pytest.approx(f[i], rel=1e-12)
    # sigma_i^2 ~ i^(a-1): the product tends to Gamma(1)/Gamma(1+a) * i^(a-1)
    assert f[-1] ** 2 * 50 ** (1 - alpha) == pytest.approx(1 / math.gamma(1 + alpha), rel=0.05)


def test_schedule_object_and_errors():
    s = BandwidthSchedule(8.0, 0.5, alpha=0.5, min_sigma_s=1.0)
    assert s.sigma_s(1) == 8.0 and s.sigma_r(1) == 0.5
    assert s.sigma_s(10**6) == 1.0  # floored
    assert s.sigma_r(100) < s.sigma_r(10) < s.sigma_r(1)
    with pytest.raises(ValueError, match="alpha"):
        BandwidthSchedule(8.0, alpha=1.5)
    with pytest.raises(ValueError, match="sigma_s"):
        BandwidthSchedule(-1.0)
    with pytest.raises(ValueError, match="iteration"):
        bandwidth_factor(0)
