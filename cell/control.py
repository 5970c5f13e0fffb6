"""The closed loop's control law, a pure function: a Measurement, the model's prediction at the
settings it was taken with and the limits -> a Correction (design.md step 3).

From G = c P_pixel t with P_pixel ~ 1 / kappa^2 (eq. 10, 17) the gray scales with t / kappa^2, so
one gain k = target / sqrt(G_min G_max) centres the measured range in the band geometrically
(the target: evaluate.target_gray, sqrt(low high) for a band not starting near 0). The shutter takes k first; where it hits its limits the f-number takes the rest,
never wider than the depth of field allows. What neither absorbs is re-planned with the measured
model error as an effective albedo scale: only the product c rho is observable, so the scale also
absorbs an error in c. A range relatively wider than the band is no exposure problem and an albedo
scale does not change the predicted shape: the loop stops at once and says so.
"""
from dataclasses import dataclass

import numpy as np

from cell.evaluate import target_gray
from cell.plan import gray_stats

DARK = 0.5                  # a pixel reading 0 is below the first gray level: true gray < 0.5
SATURATED_STEP = 4.0        # every pixel saturated: step this far past the lower bound (2 stops)
RESOLVED = 0.5              # darkest pixel below this x the band's low end: noise and black level
                            # dominate its spread, so brighten and look again before judging it


def model_error(sample_gray, predicted, saturation):
    """(measured / predicted gray at the samples, relation): the median over samples the sensor
    resolves, "="; if every one saturates the tightest lower bound, ">="; if every one reads 0
    the tightest upper bound (true gray < DARK), "<="."""
    ok = np.isfinite(sample_gray) & (predicted > 0)
    g, p = sample_gray[ok], predicted[ok]
    resolved = (g > 0) & (g < saturation)
    if resolved.any():
        return float(np.median(g[resolved] / p[resolved])), "="
    if (g >= saturation).any():
        return float(np.max(saturation / p[g >= saturation])), ">="
    return float(np.min(DARK / p)), "<="


def describe_error(error, relation):
    bound = {"=": "", ">=": "at least ", "<=": "at most "}[relation]
    return f"measured gray is {bound}{error:.3g}x the model's"


def true_range(m, predicted, error):
    """The feature's gray range (lo, hi) the capture implies: the measured extremes where the
    sensor resolves them; at saturation (true >= it) or at 0 (true < DARK) the model times the
    measured error, within what the reading allows."""
    def resolve(reading, estimate):
        if reading >= m.saturation:
            return max(m.saturation, estimate)
        return min(DARK, estimate) if reading <= 0 else reading
    return resolve(m.min, error * predicted.min()), resolve(m.max, error * predicted.max())


def spread_exceeds_band(lo, hi, band):
    """Whether the feature's gray range is relatively wider than the band (max/min > high/low), so
    that no exposure fits it, G ~ t / kappa^2 scaling all alike. A dim range (lo < RESOLVED low)
    is not judged: noise and black level inflate it."""
    low, high = band
    return lo >= RESOLVED * low and hi * low > lo * high


def correct_exposure(lo, hi, relation, shutter_s, f_number, band, shutter_range, f_number_range):
    """(shutter, f-number, reason): the gain target / sqrt(lo hi) on G ~ t / kappa^2,
    shutter first, the f-number within f_number_range (its low end the widest the depth of field
    allows) for what the shutter's range leaves. With every pixel saturated (relation ">=", lo and
    hi lower bounds) it steps SATURATED_STEP further, so the next capture measures. A dim range
    (lo < RESOLVED low, whose spread is not judged: spread_exceeds_band) is brightened. reason is
    None when the range can then be in band (or, dim, is brighter), else says why not."""
    low, high = band
    dim = lo < RESOLVED * low
    step = SATURATED_STEP if relation == ">=" else 1.0
    exposure = shutter_s / f_number**2 * target_gray(band) / np.sqrt(lo * hi) / step
    shutter = float(np.clip(exposure * f_number**2, *shutter_range))
    kappa = float(np.clip(np.sqrt(shutter / exposure), *f_number_range))
    k = shutter / kappa**2 / (shutter_s / f_number**2)
    fits = {"=": low <= lo * k and hi * k <= high, ">=": lo * k <= high, "<=": hi * k >= low}[relation]
    if not fits and not (dim and k > 1.0 + 1e-9):
        bound = {"=": "at", ">=": "at least", "<=": "at most"}[relation]
        return shutter, kappa, (f"even at {1e3 * shutter:.3g} ms and f/{kappa:.1f} the feature would be "
                                f"{bound} {lo * k:.1f}-{hi * k:.1f}, band {low:g}-{high:g}")
    return shutter, kappa, None


@dataclass(frozen=True)
class Correction:
    """What the loop does next, as data: `exposure` (new shutter and f-number), `replan` (with
    the albedo multiplied by `model_error`), or `stop` (no correction can help; `reason` says
    why). gray_range is the feature's gray the capture implies (true_range)."""

    action: str
    gray_range: tuple
    model_error: float
    relation: str
    shutter_s: float = float("nan")
    f_number: float = float("nan")
    reason: str = ""

    def document(self, albedo_scale):
        """The correction in report.json and log.jsonl (albedo_scale: the re-plan's, in all)."""
        if self.action == "exposure":
            return {"action": "exposure", "shutter_s": self.shutter_s, "f_number": self.f_number,
                    "gray_range": list(self.gray_range)}
        return {"action": self.action, "albedo_scale": albedo_scale, "reason": self.reason}

    def message(self, shutter_s, f_number, albedo_scale):
        """The sentence of log.jsonl's `correct` step, from the settings it corrects."""
        lo, hi = self.gray_range
        if self.action == "exposure":
            return (f"exposure: shutter {1e3 * shutter_s:.3f} -> {1e3 * self.shutter_s:.3f} ms, "
                    f"f/{f_number:.2f} -> f/{self.f_number:.2f} (gray range taken as {lo:.1f}-{hi:.1f})")
        return f"re-plan with albedo x{albedo_scale:.3g}: {self.reason}"


def correct(m, predicted, shutter_s, f_number, band, shutter_range, f_number_range):
    """The Correction for Measurement m of a capture at (shutter_s, f_number) whose model
    prediction per sample at those settings is `predicted`."""
    error, relation = model_error(m.sample_gray, predicted, m.saturation)
    lo, hi = true_range(m, predicted, error)
    if spread_exceeds_band(lo, hi, band):
        p = gray_stats(predicted * error)
        return Correction("stop", (lo, hi), error, relation, reason=(
            f"the feature's gray spans {lo:.1f}-{hi:.1f}, max/min {hi / lo:.2f} > the band's "
            f"{band[1] / band[0]:.2f}, where the model (its albedo corrected) predicts "
            f"{p['min']:.1f}-{p['max']:.1f}: no exposure narrows it, and a re-plan with a corrected "
            f"albedo would not either; the light falls otherwise than modelled (check the lamp's "
            f"aim, shadows on the feature and the material table)"))
    shutter, kappa, why = correct_exposure(lo, hi, relation, shutter_s, f_number, band, shutter_range,
                                           f_number_range)
    if why is None:
        return Correction("exposure", (lo, hi), error, relation, shutter, kappa)
    return Correction("replan", (lo, hi), error, relation, reason=why)
