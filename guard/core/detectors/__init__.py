"""Change detectors on the filter's innovations, one statistic per channel.

Each detector has one method, `test(sensor, t_us, r, S)`, which takes the innovation r = y - ŷ of
one sensor (shape (m,)) and its covariance S (m, m), and returns the statistic and threshold of each
channel and the indices of the channels that rejected H0 at this sample (with the estimated shift).

`paper`: the two-sided CUSUM of the paper (eq. 11) exactly as written,
    S(k+1) = max(0, S(k) + |r(k+1)|)  while S(k) <= tau(k);  else S = 0 and k_alpha = k.
It has no drift term, so under H0 S grows like n E|r|: it only works against a growing threshold.
The paper builds its band "from the weighted sum of the first 10 samples"; we read that as
    tau(n) = n m + kappa s sqrt(n),
n the samples since the (re)start, m and s the mean and standard deviation of |r| over the first
10 of them: the centre is the first 10 samples' sum scaled by n/10, the half-width the spread of a
sum of n such samples. No decision is taken in those first 10 samples (the paper's blind start).

`gate` and `chi2` are the baselines a detector must beat: the autopilots' 5-sigma innovation gate
with a persistence rule, and a memoryless chi-square test of each sensor's innovation.

`cusum`: Page's two-sided CUSUM on the normalised innovation z = r / sqrt(S_ii),
    g+(k) = max(0, g+(k-1) + z(k) - k_ref),   g-(k) = max(0, g-(k-1) - z(k) - k_ref),
alarm when max(g+, g-) > h. k_ref = delta/2 for a design shift of delta sigmas, one CUSUM per
design shift in a bank (default 1 and 4 sigmas: unknown attack sizes); h is set from a
target mean time between false alarms (all channels together) with Siegmund's approximation of
the in-control average run length, ARL0(h) = (exp(2 k (h + 1.166)) - 2 k (h + 1.166) - 1) / (2 k^2).
Against the exact ARL0 (Page's integral equation, checked in the tests) the approximation is
within 1 % at k = 0.5 and overstates it by half at k = 2 (exact 0.66 of it): on white innovations
the default bank's real mean time between false alarms is about 0.8 of the target.
"""

from __future__ import annotations

from guard.core.detectors.base import Detector, DetectorConfig
from guard.core.detectors.baselines import ChiSquare, Gate, chi2_quantile
from guard.core.detectors.cusum import PageCusum, siegmund_arl, threshold_for_arl
from guard.core.detectors.paper import PaperCusum

__all__ = ["DETECTORS", "ChiSquare", "Detector", "DetectorConfig", "Gate", "PageCusum", "PaperCusum",
           "chi2_quantile", "make_detector", "siegmund_arl", "threshold_for_arl"]

# the registry: a new detector is one module and one line here
DETECTORS: dict[str, type[Detector]] = {"cusum": PageCusum, "paper": PaperCusum, "gate": Gate, "chi2": ChiSquare}


def make_detector(cfg: DetectorConfig, n_channels: int) -> Detector:
    return DETECTORS[cfg.name](cfg, n_channels)
