"""guard tune's rule for flights unlike one another (guard.runtime.tune.unlike), on innovations
whose spread is set by hand: a log is flagged only where it passes both the tuned model and all the
logs together by more than the margin."""

import pytest

from guard.model.sensors import Sensor
from guard.runtime.tune import Innovations, unlike


def spread(**factors: float) -> Innovations:
    """Innovations whose per-sample factor is each given value (100 samples, no block means)."""
    one = Innovations()
    for name, f in factors.items():
        s = Sensor(name)
        one.n[s] = 100
        one.sum[s] = 100 * f * f
    return one


@pytest.mark.parametrize("log_f, pooled_f, flagged", [
    (1.33, 0.90, True),         # over the model, and 1.48 times the logs together
    (0.95, 0.92, False),        # alike flights within the model (a simulator's)
    (0.08, 0.06, False),        # far inside the model: differing there does not matter
    (1.05, 0.95, False),        # over the model, but not MARGIN over the others
    (1.2, 0.9, True),
])
def test_a_log_is_unlike_the_others_only_past_the_model_and_the_margin(log_f, pooled_f, flagged):
    each = [spread(gnss_vel=log_f, mag=0.8), spread(gnss_vel=0.8, mag=0.8)]
    over = unlike(["a.bin", "b.bin"], each, spread(gnss_vel=pooled_f, mag=0.8))
    assert over == ([(pytest.approx(log_f), "a.bin", Sensor.GNSS_VEL)] if flagged else [])


def test_a_sensor_missing_from_a_log_or_from_all_is_not_unlike():
    each = [spread(gnss_vel=2.0), spread(mag=0.8)]
    assert unlike(["a", "b"], each, spread(mag=0.8)) == []         # no pooled figure for it: nothing to be unlike
