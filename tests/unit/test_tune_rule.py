"""guard tune's rule for a flight that one noise level does not fit (guard.runtime.tune.unfitted), on
innovations whose spread is set by hand: a log is flagged only where its innovations pass the tuned
model and its test comes near its threshold."""

import pytest

from guard.model.sensors import Sensor
from guard.runtime.tune import NEAR, Innovations, unfitted


def spread(**factors: float) -> Innovations:
    """Innovations whose per-sample factor is each given value (100 samples, no block means)."""
    one = Innovations()
    for name, f in factors.items():
        s = Sensor(name)
        one.n[s] = 100
        one.sum[s] = 100 * f * f
    return one


@pytest.mark.parametrize("factor, peak, flagged", [
    (1.33, 2.02, True),         # over the model and alarmed with it (a real copter's tuning flight)
    (1.33, 0.11, False),        # over the model by chance on a short log, its test far from alarming
    (0.95, 0.90, False),        # inside the model: near the threshold by chance, not by the model
    (1.05, NEAR, True),
])
def test_a_log_is_flagged_only_past_the_model_and_near_its_threshold(factor, peak, flagged):
    each = [spread(gnss_vel=factor, mag=0.8), spread(gnss_vel=0.8, mag=0.8)]
    reports = [{"peak_ratio": {"gnss_vel": peak, "mag": 0.9}}, {"peak_ratio": {"gnss_vel": 0.3}}]
    over = unfitted(["a.bin", "b.bin"], each, reports)
    assert over == ([(pytest.approx(factor), "a.bin", Sensor.GNSS_VEL, peak)] if flagged else [])


def test_a_sensor_a_log_lacks_is_not_flagged():
    each = [spread(mag=0.8), spread(gnss_vel=2.0)]
    reports = [{"peak_ratio": {"mag": 0.5}}, {"peak_ratio": {}}]        # never tested: no peak
    assert unfitted(["a", "b"], each, reports) == []
