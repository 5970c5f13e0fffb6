"""The closed loop's control law, a pure function: a Measurement, the model's prediction at the
settings it was taken with, the black level and the limits -> a Correction.

G = b + c P_pixel t with P_pixel ~ 1 / kappa^2 (eq. 10, 17): the signal S = G - b scales with
t / kappa^2, and G is in [low, high] when S is in [low - b, high - b]. So one gain k = target /
sqrt(S_min S_max) centres the measured signal geometrically in that band (the target:
evaluate.target_gray). The shutter takes k first; where it hits its limits the f-number takes the
rest, never wider than the depth of field allows. What neither absorbs is re-planned with the
measured model error (of the signal) as an effective albedo scale: only the product c rho is
observable, so the scale also absorbs an error in c.

`correct` decides, the first that applies (README, closed loop):
  1. black pixels   more than BLACK_FRACTION of the region's pixels read the black level while
                    the others are lit: no light comes from there (off the part, a cast shadow),
                    which no exposure or albedo fixes: stop, check the fixture / hand-eye
  2. albedo         the albedo scale the capture implies (the loop's times the measured error) is
                    outside loop.albedo_scale_range: the model is wrong in more than its level:
                    stop, not acted on
  3. spread         the signal's range relatively wider than the band's: no exposure narrows it
                    and an albedo scale does not change the predicted shape: stop
  4. exposure       a shutter and f-number within range put the range in the band
  5. re-plan        with the albedo scale the capture implies

Several features in one capture share one exposure (`shared_correction`): each is judged alone,
then their measurements joined against the bands' intersection; what needs more than an
exposure stops there, a shot of several features being neither refitted nor re-planned. (A shot
lit by lights on the controller has its drives re-solved on basis captures first, each feature's
samples in its own band: cell.run.loop.rebalance, cell.run.channels.)
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.planning.evaluate import target_gray
from cell.planning.plan import gray_stats
from cell.run import measurement

if TYPE_CHECKING:
    from cell.run.measurement import BlackLevel, Measurement

DARK = 0.5                  # a pixel at the black level reads below the first gray level above it
SATURATED_STEP = 4.0        # every pixel saturated: step this far past the lower bound (2 stops)
RESOLVED = 0.5              # darkest pixel below this x the band's low end: noise and black level
                            # dominate its spread, so brighten and look again before judging it
BLACK_FRACTION = 0.001      # more of the region's pixels than this at the black level: no light
                            # (a 0.25 deg hand-eye tilt puts 0.35 % of the conrod's off its shank)
LIT_CONTRAST = 8.0          # the others lit: their median this many black-level ceilings above b


@dataclass(frozen=True)
class Limits:
    """What a correction must respect: the gray band, the shutter range, the f-number range (its
    low end the widest the depth of field allows) and the plausible albedo scales."""

    band: tuple[float, float]
    shutter_range: tuple[float, float]
    f_number_range: tuple[float, float]
    albedo_range: tuple[float, float] = (0.1, 10.0)


def model_error(sample_gray: np.ndarray, predicted: np.ndarray, saturation: float,
                black_level: float = 0.0) -> tuple[float, str]:
    """(measured / predicted signal G - b at the samples, relation): the median over samples the
    sensor resolves, "="; if every one saturates the tightest lower bound, ">="; if every one
    reads the black level the tightest upper bound (true signal < DARK), "<="."""
    ok = np.isfinite(sample_gray) & (predicted > black_level)
    g, p, top = sample_gray[ok] - black_level, predicted[ok] - black_level, saturation - black_level
    resolved = (g > 0) & (g < top)
    if resolved.any():
        return float(np.median(g[resolved] / p[resolved])), "="
    if (g >= top).any():
        return float(np.max(top / p[g >= top])), ">="
    return float(np.min(DARK / p)), "<="


def describe_error(error: float, relation: str) -> str:
    """`measured gray is at least 1.3x the model's`: the model error and its relation in words."""
    bound = {"=": "", ">=": "at least ", "<=": "at most "}[relation]
    return f"measured gray is {bound}{error:.3g}x the model's"


def true_range(m: Measurement, predicted: np.ndarray, error: float,
               black_level: float = 0.0) -> tuple[float, float]:
    """The feature's gray range (lo, hi) the capture implies: the measured extremes where the
    sensor resolves them; at saturation (true >= it) or at the black level b (true signal < DARK)
    b + the model's signal times the measured error, within what the reading allows."""
    def resolve(reading: float, estimate: float) -> float:
        estimate = black_level + error * (estimate - black_level)
        if reading >= m.saturation:
            return max(m.saturation, estimate)
        return min(black_level + DARK, estimate) if reading <= black_level else reading
    return resolve(m.min, predicted.min()), resolve(m.max, predicted.max())


def spread_exceeds_band(lo: float, hi: float, band: tuple[float, float], black_level: float = 0.0) -> bool:
    """Whether the feature's signal range (gray - b) is relatively wider than the band's
    (max/min > (high - b)/(low - b)), so that no exposure fits it, G - b ~ t / kappa^2 scaling all
    alike. A dim range (lo - b < RESOLVED (low - b)) is not judged: noise and the black level
    inflate it."""
    low, high = band[0] - black_level, band[1] - black_level
    lo, hi = lo - black_level, hi - black_level
    return lo >= RESOLVED * low and hi * low > lo * high


def correct_exposure(lo: float, hi: float, relation: str, shutter_s: float, f_number: float,
                     band: tuple[float, float], shutter_range: tuple[float, float],
                     f_number_range: tuple[float, float], black_level: float = 0.0,
                     ) -> tuple[float, float, str | None]:
    """(shutter, f-number, reason): the gain target / sqrt(S_lo S_hi) on the signal S = G - b,
    S ~ t / kappa^2, shutter first, the f-number within f_number_range for what the shutter's
    range leaves. With every pixel saturated (relation ">=", lo and hi lower bounds) it steps
    SATURATED_STEP further, so the next capture measures. A dim range (S_lo < RESOLVED (low - b),
    whose spread is not judged: spread_exceeds_band) is brightened. reason is None when the range
    can then be in band (or, dim, is brighter), else says why not."""
    b = black_level
    low, high = band[0] - b, band[1] - b
    s_lo, s_hi = lo - b, hi - b
    dim = s_lo < RESOLVED * low
    step = SATURATED_STEP if relation == ">=" else 1.0
    exposure = shutter_s / f_number**2 * target_gray((low, high)) / np.sqrt(s_lo * s_hi) / step
    shutter = float(np.clip(exposure * f_number**2, *shutter_range))
    kappa = float(np.clip(np.sqrt(shutter / exposure), *f_number_range))
    k = shutter / kappa**2 / (shutter_s / f_number**2)
    fits = {"=": low <= s_lo * k and s_hi * k <= high, ">=": s_lo * k <= high, "<=": s_hi * k >= low}[relation]
    if not fits and not (dim and k > 1.0 + 1e-9):
        bound = {"=": "at", ">=": "at least", "<=": "at most"}[relation]
        return shutter, kappa, (f"even at {1e3 * shutter:.3g} ms and f/{kappa:.1f} the feature would be "
                                f"{bound} {b + s_lo * k:.1f}-{b + s_hi * k:.1f}, band {band[0]:g}-{band[1]:g}")
    return shutter, kappa, None


def black_pixels(m: Measurement, black: BlackLevel) -> tuple[float, bool]:
    """(fraction of the region's pixels at the BlackLevel, whether the others are lit: their
    median at least LIT_CONTRAST x (ceiling - b) above b, so the capture tells light from none)."""
    fraction = m.black_fraction(black)
    others = m.gray[m.gray > black.ceiling]
    lit = others.size > 0 and np.median(others) >= black.value + LIT_CONTRAST * (black.ceiling - black.value)
    return fraction, bool(lit)


def implausible_albedo(albedo: float, relation: str, albedo_range: tuple[float, float]) -> bool:
    """Whether an implied albedo scale (a bound for relation ">=" / "<=") lies surely outside the
    plausible range."""
    low, high = albedo_range
    return {"=": not low <= albedo <= high, ">=": albedo > high, "<=": albedo < low}[relation]


@dataclass(frozen=True)
class Correction:
    """What the loop does next, as data: `exposure` (new shutter and f-number), `replan` (with
    the albedo multiplied by `model_error`), or `stop` (no correction can help; `cause` names the
    decision of the module docstring, `reason` says why). gray_range is the feature's gray the
    capture implies (true_range)."""

    action: str
    gray_range: tuple[float, float]
    model_error: float
    relation: str
    shutter_s: float = float("nan")
    f_number: float = float("nan")
    reason: str = ""
    cause: str = ""

    def document(self, albedo_scale: float) -> dict[str, Any]:
        """The correction in report.json and log.jsonl (albedo_scale: the re-plan's, in all)."""
        if self.action == "exposure":
            return {"action": "exposure", "shutter_s": self.shutter_s, "f_number": self.f_number,
                    "gray_range": list(self.gray_range)}
        return {"action": self.action, "albedo_scale": albedo_scale, "reason": self.reason} | (
            {"cause": self.cause} if self.cause else {})

    def message(self, shutter_s: float, f_number: float, albedo_scale: float) -> str:
        """The sentence of log.jsonl's `correct` step, from the settings it corrects."""
        lo, hi = self.gray_range
        if self.action == "exposure":
            return (f"exposure: shutter {1e3 * shutter_s:.3f} -> {1e3 * self.shutter_s:.3f} ms, "
                    f"f/{f_number:.2f} -> f/{self.f_number:.2f} (gray range taken as {lo:.1f}-{hi:.1f})")
        return f"re-plan with albedo x{albedo_scale:.3g}: {self.reason}"


def correct(m: Measurement, predicted: np.ndarray, shutter_s: float, f_number: float, limits: Limits,
            black: BlackLevel, albedo_scale: float = 1.0) -> Correction:
    """The Correction for Measurement m of a capture at (shutter_s, f_number) whose model
    prediction per sample at those settings is `predicted`, planned with `albedo_scale`; black is
    the BlackLevel. The decision of the module docstring, in its order."""
    b, band = black.value, limits.band
    error, relation = model_error(m.sample_gray, predicted, m.saturation, b)
    lo, hi = true_range(m, predicted, error, b)
    fraction, lit = black_pixels(m, black)
    if fraction > BLACK_FRACTION and lit:
        return Correction("stop", (lo, hi), error, relation, cause="black pixels", reason=(
            f"{100 * fraction:.2g} % of the feature's pixels read the black level {b:.1f} (off the part "
            f"or shadowed), where the model lights every sample: check the part's fixture / hand-eye"))
    implied = albedo_scale * error
    if implausible_albedo(implied, relation, limits.albedo_range):
        bound = {"=": "", ">=": "at least ", "<=": "at most "}[relation]
        dark = " (every pixel of the feature reads the black level)" if fraction == 1.0 else ""
        a_lo, a_hi = limits.albedo_range
        return Correction("stop", (lo, hi), error, relation, cause="albedo", reason=(
            f"{describe_error(error, relation)}{dark}: a correction would imply an albedo {bound}"
            f"x{implied:.3g} of the material table's, outside the plausible x{a_lo:g}-x{a_hi:g} "
            f"(loop.albedo_scale_range), so none is made: check that the lamp is on and lights the "
            f"feature, the camera constant (cell calibrate) and the material table"))
    if spread_exceeds_band(lo, hi, band, b):
        p = gray_stats(b + (predicted - b) * error)
        above = "" if b == 0 else f" (above the black level {b:.1f})"
        return Correction("stop", (lo, hi), error, relation, cause="spread", reason=(
            f"the feature's gray spans {lo:.1f}-{hi:.1f}, max/min{above} {(hi - b) / (lo - b):.2f} > the "
            f"band's {(band[1] - b) / (band[0] - b):.2f}, where the model (its albedo corrected) predicts "
            f"{p['min']:.1f}-{p['max']:.1f}: no exposure narrows it, and a re-plan with a corrected "
            f"albedo would not either; the light falls otherwise than modelled (check the lamp's "
            f"aim, shadows on the feature and the material table)"))
    shutter, kappa, why = correct_exposure(lo, hi, relation, shutter_s, f_number, band, limits.shutter_range,
                                           limits.f_number_range, b)
    if why is None:
        return Correction("exposure", (lo, hi), error, relation, shutter, kappa)
    return Correction("replan", (lo, hi), error, relation, reason=why)


def shared_correction(names: Sequence[str], measured: Sequence[tuple[object, Measurement, np.ndarray]],
                      limits: Sequence[Limits], shutter_s: float, f_number: float,
                      black: BlackLevel) -> Correction:
    """The one Correction of a capture of several features (names; measured: each one's
    (Iteration, Measurement, predicted gray per sample), cell.run.loop.measure_capture's; limits:
    each one's Limits). Each feature is judged alone first (correct): a stop names it. Then all
    together, their measurements joined (measurement.joined) against the band they all accept
    (the bands' intersection), for the exposure: a spread there that no feature has alone means the features
    disagree (cause `features`): no one exposure puts them all in band. What the exposure cannot
    absorb stops (cause `replan`): a shot of several features is not re-planned."""
    for name, (_, m, predicted), lim in zip(names, measured, limits):
        c = correct(m, predicted, shutter_s, f_number, lim, black)
        if c.action == "stop":
            note = " (a shot of several features is not refitted)" if c.cause == "spread" else ""
            return replace(c, reason=f"{name}: {c.reason}{note}")
    band = (max(lim.band[0] for lim in limits), min(lim.band[1] for lim in limits))
    joint = Limits(band, limits[0].shutter_range, (max(lim.f_number_range[0] for lim in limits),
                                                   min(lim.f_number_range[1] for lim in limits)),
                   limits[0].albedo_range)
    if band[0] > band[1]:
        return Correction("stop", (np.nan, np.nan), np.nan, "=", cause="bands", reason=(
            "the shot's features have gray bands with nothing in common ("
            + ", ".join(f"{n} {lim.band[0]:g}-{lim.band[1]:g}" for n, lim in zip(names, limits))
            + "): one exposure cannot be corrected toward all of them"))
    predicted = np.concatenate([p for _, _, p in measured])
    c = correct(measurement.joined(m for _, m, _ in measured), predicted, shutter_s, f_number, joint, black)
    if c.action == "stop" and c.cause == "spread":
        b = black.value
        ranges = ", ".join(f"{n} {m.min:.1f}-{m.max:.1f}" for n, (_, m, _) in zip(names, measured))
        lo, hi = c.gray_range
        return replace(c, cause="features", reason=(
            f"the shot's features disagree: {ranges}; together max/min {(hi - b) / (lo - b):.2f} > the "
            f"band's {(band[1] - b) / (band[0] - b):.2f} ({band[0]:g}-{band[1]:g}), so no one exposure puts "
            f"all of them in band (each alone would fit): plan them in shots of their own"))
    if c.action == "replan":
        return replace(c, action="stop", cause="replan", reason=(
            f"{c.reason}; a shot of several features is not re-planned (plan them in shots of their own, "
            f"or correct the model: {describe_error(c.model_error, c.relation)})"))
    return c
