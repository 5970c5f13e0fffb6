"""Drive levels of several light channels, shutter and f-number by linear programming.

Below saturation a pixel's gray is linear in each channel's drive level w_k (eq. 10, 17, summed
over the channels): G_p = b + x sum_k w_k v_kp, x = t / kappa^2 [s], v_kp >= 0 channel k's gray
per exposure at sample p at full drive (kernels.gray's `value`), b the black level [gray]. In the
products x and u_k = x w_k the band is linear; the margin m [gray] is maximised:

    max m  s.t.  b + (1 - delta) sum_k u_k v_kp >= low_p + m,   b + (1 + delta) sum_k u_k v_kp <= high_p - m,
                 x w_min_k <= u_k <= x w_max_k,   t_lo / kappa_hi^2 <= x <= t_hi / kappa_open^2,

for every sample p (its band [low_p, high_p]: one for all, or each sample its feature's when one
shot lights several, cell.planning.joint), robust to a relative drive error delta (each channel's
true drive in w (1 +- delta)); then, with m within MARGIN_SLACK of the best, the shortest exposure (min x). A
switched channel (off or at w_max_k) is a binary z_k by big-M (scipy.optimize.milp), its pattern
then fixed and the LP (scipy.optimize.linprog, HiGHS) solved again; both with the samples' rows
generated as they bind (thousands of samples, an optimum binding a few). Shutter and f-number follow
from x as in the one-lamp planner (evaluate.exposure_for_gain). Unlike centring_exposure, which
aims at the band's geometric centre, the LP puts the extremes equally far inside the band's ends.

A channel whose drive adds at most SLACK_GRAY at every sample (the program's slack: its level
moves no margin, or solver noise of 1e-12) is written as exactly 0, where the margin stays as
good: a light at drive 0 is off for every other requirement (it casts
no light a shadow, a dominant term or a picture would count), one at 1e-12 would be on.

A declared defect joins as rows of its own (ContrastRows): at a sample, orientation and part r its
contrast s_r sum_k u_k d_kr (d_kr channel k's defect gray less the good one's per exposure, the
sign s_r the spot alone's) must reach min_cnr times the noise sqrt(a + K sum_k u_k t_kr) (EMVA 1288
of both pixels: t_kr their signals' sum per exposure, a = 2 (K^2 sigma_d^2 + 1/12)). The square
root is concave, so its tangent at z0 lies above it: s_r d_r u >= c (q0 + K (t_r u - z0) / (2 q0)),
q0 = sqrt(a + K z0), is linear and sufficient. The tangents are taken at the band's optimum and
again at each solution (CUT_ROUNDS), the rows held generated as they bind (the CONTRAST_ROWS of
least CNR at the band's optimum, then those short at a solution join); a program the rows make
infeasible keeps the band's drives, the CNR judged after them as before (not robust to the drive
error: the band's rows are).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import Bounds, LinearConstraint, OptimizeResult, linprog, milp

from cell.planning.evaluate import exposure_for_gain
from kernels.runtime import native_output_silenced

# band widths of margin given up for a shorter exposure: the solver's noise, not a trade; a
# switched pattern is chosen to milp's feasibility tolerance (a floor closer to its optimum than
# that, HiGHS's presolve may call infeasible): a pattern may give up twice PATTERN_SLACK
MARGIN_SLACK = 1e-9
PATTERN_SLACK = 1e-6
# a sample binds when its side's slack is within this many band widths of the margin: above
# HiGHS's feasibility tolerance (1e-7), far below a gray level
BINDING_SLACK = 1e-6
# band widths by which a sample's row left out of the program may be violated before it joins
VIOLATION = 1e-9
# gray levels: a channel adding at most this at every sample is off (drive exactly 0); a hundredth
# of a level, which no 8-bit capture resolves
SLACK_GRAY = 0.01

CUT_ROUNDS = 4         # tangent cuts of the contrast rows' noise: at the band's optimum, then at each solution
CONTRAST_ROWS = 32     # the rows first held: the least CNR at the band's optimum; then every row short at a solution

Cause = Literal["in band", "unlit", "too dark", "too bright", "too uneven"]


@dataclass(frozen=True)
class ContrastRows:
    """A declared defect's contrast rows (the module's docstring), R of them: per channel (K, R)
    the defect's gray less the good surface's (`difference`) and their sum less 2 b (`total`)
    per exposure at full drive, the sign each contrast keeps (R,), min_cnr (R,), the system gain K
    [gray/e-] and the dark noise [e-]."""

    difference: np.ndarray
    total: np.ndarray
    sign: np.ndarray
    min_cnr: np.ndarray
    gain: float
    dark_e: float

    @property
    def noise_floor(self) -> float:
        """a = 2 (K^2 sigma_d^2 + 1/12) [gray^2]: both pixels' dark and quantization noise."""
        return 2.0 * (self.gain**2 * self.dark_e**2 + 1.0 / 12.0)

    def cnr(self, u: np.ndarray) -> np.ndarray:
        """(R,) each row's CNR at exposures u_k = x w_k (K,) [s / kappa^2] (its contrast's sign kept:
        negative where it turned)."""
        noise = np.sqrt(self.noise_floor + self.gain * np.maximum(u @ self.total, 0.0))
        return self.sign * (u @ self.difference) / noise

    def cuts(self, u0: np.ndarray, active: np.ndarray, per_column: float) -> tuple[np.ndarray, np.ndarray]:
        """(A (R, K'), b (R,)): the rows A u' <= b in the program's columns of the active channels
        (u' = u per_column), tangent to the noise at u0 (K,)."""
        z0 = np.maximum(u0 @ self.total, 0.0)
        q0 = np.sqrt(self.noise_floor + self.gain * z0)
        slope = self.min_cnr * self.gain / (2.0 * q0)
        a = -(self.sign * self.difference[active] - slope * self.total[active]).T / per_column
        return a, -self.min_cnr * (q0 - self.gain * z0 / (2.0 * q0))


@dataclass(frozen=True)
class Drives:
    """Drive levels (K,) in [0, 1], shutter [s] and f-number, and the verdict: the margin
    [gray] by which every sample's gray stays inside the band with the drive error included
    (negative: by how much the best drive levels miss it), the cause when infeasible, the
    predicted gray (P,) at the nominal drives, the samples binding at the band's low and high
    end (`darkest`, `brightest`: the tightest of each), the channels that light no sample (left
    at their lowest drive), the samples no channel lights, and what the extremes reach:
    `dark_fraction`, the darkest sample's gray over the band's low end with every channel at full
    drive (less the drive error) and the longest shutter at kappa_open (inf for a band from 0);
    `bright_fraction`, the brightest sample's over the high end with every channel at its lowest
    drive (plus the drive error), the shortest shutter and the smallest aperture. HiGHS's own
    verdict: the number of solves and the last one's message."""

    drive: np.ndarray
    shutter_s: float
    f_number: float
    margin_gray: float
    feasible: bool
    cause: Cause
    gray: np.ndarray
    darkest: int
    brightest: int
    low_binding: tuple[int, ...]
    high_binding: tuple[int, ...]
    dark_channels: tuple[int, ...]
    unlit_samples: tuple[int, ...]
    dark_fraction: float
    bright_fraction: float
    band: tuple[float, float]
    drive_error: float
    solves: int
    solver_message: str

    @property
    def message(self) -> str:
        """The verdict in one sentence, with the channels and samples that no light reaches."""
        low, high = self.band
        error = f" less the drive error of {self.drive_error:.0%}" if self.drive_error else ""
        if self.cause == "in band":
            text = (f"every sample in band {low:g}-{high:g} by {self.margin_gray:.1f} gray"
                    f"{' with the drive error included' if self.drive_error else ''}: gray "
                    f"{self.gray.min():.1f}-{self.gray.max():.1f} at {1e3 * self.shutter_s:.3g} ms, "
                    f"f/{self.f_number:.1f}")
        elif self.cause == "unlit":
            text = "no channel lights any sample"
        elif self.cause == "too dark":
            text = (f"the darkest sample reaches {self.dark_fraction:.0%} of the band's low end {low:g} with "
                    f"every channel at full drive{error} and the longest shutter at the depth of field's widest "
                    f"aperture")
        elif self.cause == "too bright":
            text = (f"the brightest sample reaches {self.bright_fraction:.0%} of the band's high end {high:g} "
                    f"with every channel at its lowest drive{error.replace('less', 'plus')}, the shortest "
                    f"shutter and the smallest aperture")
        else:
            text = (f"no drive levels put every sample in band {low:g}-{high:g}: the lights cannot make the patch "
                    f"even enough, the best misses the band by {-self.margin_gray:.1f} gray "
                    f"({_count(self.low_binding)} at the low end, {_count(self.high_binding)} at the high end)")
        if self.unlit_samples and self.cause != "unlit":
            text += f"; {_count(self.unlit_samples)} lit by no channel"
        if self.dark_channels and self.cause != "unlit":
            text += (f"; {len(self.dark_channels)} channel{'s' if len(self.dark_channels) > 1 else ''} "
                     f"light{'' if len(self.dark_channels) > 1 else 's'} no sample (left at the lowest drive)")
        return text


def _count(samples: tuple[int, ...]) -> str:
    """'1 sample', '3 samples': a count for a sentence (which ones are the Drives' fields)."""
    return f"{len(samples)} sample{'' if len(samples) == 1 else 's'}"


def _per_sample(band: tuple[ArrayLike, ArrayLike], n_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The band's low and high ends (each a number or one per sample) as one per sample (P,)."""
    low, high = (np.broadcast_to(np.asarray(end, float), (n_samples,)) for end in band)
    return low, high


def solve_drives(unit_gray: ArrayLike, band: tuple[ArrayLike, ArrayLike], black_level: float, kappa_open: float,
                 shutter_range_s: tuple[float, float], f_number_range: tuple[float, float],
                 drive_range: ArrayLike | None = None, switched: ArrayLike | None = None,
                 drive_error: float = 0.0, contrast: ContrastRows | None = None) -> Drives:
    """Drives of channels with gray per exposure `unit_gray` (K, P) [gray / (s / kappa^2)] at full
    drive, within `drive_range` ((K, 2) or (2,) of [w_min, w_max] in [0, 1]; default [0, 1]),
    `switched` (K,) bool channels off or at w_max only, for the gray band [gray] (low, high: each
    a number or one per sample (P,)) and black level b, the widest f-number kappa_open the depth of
    field allows, the shutter and the lens's f-number range, robust to a relative drive error
    (0 <= delta < 1), and a declared defect's `contrast` rows where given. The module docstring
    gives the LP."""
    v = np.asarray(unit_gray, float)
    if v.ndim != 2 or v.shape[1] == 0 or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ValueError(f"unit_gray must be (K, P >= 1) finite and >= 0, found shape {v.shape}")
    n_channels, n_samples = v.shape
    low, high = _per_sample(band, n_samples)
    t_lo, t_hi = map(float, shutter_range_s)
    k_hi = float(f_number_range[1])
    if not (np.all(low < high) and np.all(0 < high) and 0 < t_lo <= t_hi < np.inf and 0 < kappa_open <= k_hi < np.inf
            and 0 <= drive_error < 1):
        raise ValueError(f"need low < high, high > 0, 0 < t_lo <= t_hi, 0 < kappa_open <= kappa_max, 0 <= drive_error < 1: "
                         f"band {low.min():g}-{high.max():g}, shutter {shutter_range_s}, kappa_open {kappa_open}, "
                         f"f-numbers {f_number_range}, drive_error {drive_error}")
    w_range = np.broadcast_to(np.asarray([0.0, 1.0] if drive_range is None else drive_range, float),
                              (n_channels, 2))
    on_off = np.broadcast_to(np.asarray(False if switched is None else switched, bool), (n_channels,))
    w_min, w_max = np.where(on_off, 0.0, w_range[:, 0]), w_range[:, 1]    # a switched channel's lowest: off
    if np.any(w_min < 0) or np.any(w_min > w_max) or np.any(w_max > 1):
        raise ValueError(f"drive ranges must lie in [0, 1] with w_min <= w_max, found {w_range.tolist()}")
    x_lo, x_hi = t_lo / k_hi**2, t_hi / kappa_open**2

    lit = v > 0
    active = lit.any(axis=1)
    # HiGHS works in scaled units: v over its max, gray in (the narrowest) band widths, so x by v_max / width
    width = float((high - low).min())
    v_max = float(v.max()) if active.any() else 1.0
    scale = v_max / width
    bounds = ((low - black_level) / width, (high - black_level) / width)
    gain, w_active, solves, message = _optimum(v[active] / v_max, bounds, drive_error, w_min[active],
                                               w_max[active], on_off[active], (x_lo * scale, x_hi * scale))
    if contrast is not None:
        gain, w_active, more, message = _with_contrast(v[active] / v_max, bounds, drive_error, w_min, w_max, on_off,
                                                       (x_lo * scale, x_hi * scale), contrast, active, scale,
                                                       (gain, w_active, message))
        solves += more
    drive = w_min.copy()
    drive[active] = w_active
    shutter, kappa = (float(a) for a in exposure_for_gain(gain / scale, kappa_open, (t_lo, t_hi), f_number_range))
    drive = _slack_off(drive, v, shutter / kappa**2, w_min, black_level, low, high, drive_error)
    return _judged(v, drive, shutter, kappa, black_level, low, high, w_min, w_max, (x_lo, x_hi), drive_error,
                   solves, message)


def raised(d: Drives, unit_gray: ArrayLike, black_level: float, kappa_open: float,
           shutter_range_s: tuple[float, float], f_number_range: tuple[float, float], drive_range: ArrayLike,
           top_signal: float) -> Drives:
    """The Drives `d` with every exposure u_k = x w_k raised by one common factor lambda >= 1, the
    largest that keeps the brightest sample's signal (its gray less b, at the nominal drives) at
    most `top_signal` [gray], the exposure gain x at most t_hi / kappa_open^2 and each drive at most
    its w_max (x first, then the drives): `gray_band: any`'s exposure. A defect's CNR grows with
    lambda (contrast lambda D, noise sqrt(a + lambda K T): CNR(lambda) = lambda D / sqrt(a +
    lambda K T), increasing), so every CNR of the drives' mix is the largest the ceiling allows:
    with one channel, the largest any exposure gives."""
    v = np.asarray(unit_gray, float)
    n_channels, n_samples = v.shape
    w_range = np.broadcast_to(np.asarray(drive_range, float), (n_channels, 2))
    t_lo, t_hi = map(float, shutter_range_s)
    x_lo, x_hi = t_lo / float(f_number_range[1])**2, t_hi / kappa_open**2
    x = d.shutter_s / d.f_number**2
    u = x * d.drive
    brightest = float(np.max(u @ v))
    if brightest <= 0 or top_signal <= 0:
        return d
    on = d.drive > 0
    room = np.min(w_range[on, 1] / d.drive[on], initial=np.inf) * x_hi / x
    factor = max(1.0, min(top_signal / brightest, room))
    x_new = min(x * factor, x_hi)
    drive = np.minimum(u * factor / x_new, w_range[:, 1])
    shutter, kappa = (float(a) for a in exposure_for_gain(x_new, kappa_open, (t_lo, t_hi), f_number_range))
    low, high = _per_sample(d.band, n_samples)
    return _judged(v, drive, shutter, kappa, black_level, low, high, w_range[:, 0], w_range[:, 1], (x_lo, x_hi),
                   d.drive_error, d.solves, d.solver_message + f"; raised x{factor:.3g} to the top (gray_band any)")


def _judged(v, drive, shutter, kappa, black_level, low, high, w_min, w_max, gain_range, drive_error, solves,
            message) -> Drives:
    """The Drives of these drive levels and exposure: the predicted gray, the margin, the cause and
    what the extremes reach (Drives' fields)."""
    x_lo, x_hi = gain_range
    lit = v > 0
    active = lit.any(axis=1)
    width = float((high - low).min())
    signal = shutter / kappa**2 * (drive @ v)
    gray = black_level + signal
    low_slack = black_level + (1 - drive_error) * signal - low
    high_slack = high - black_level - (1 + drive_error) * signal
    margin = float(min(low_slack.min(), high_slack.min()))
    darkest_full = black_level + x_hi * (1 - drive_error) * (w_max @ v)
    brightest_least = black_level + x_lo * (1 + drive_error) * (w_min @ v)
    with np.errstate(over="ignore", divide="ignore"):   # a low end a hair above 0 reads as inf: nothing to reach
        dark_fraction = float(np.min(np.where(low > 0, darkest_full / np.where(low > 0, low, 1.0), np.inf)))
    bright_fraction = float(np.max(brightest_least / high))
    dark, bright = dark_fraction < 1, bright_fraction > 1
    cause: Cause = ("unlit" if not lit.any() else "in band" if margin >= 0 else "too dark" if dark and not bright
                    else "too bright" if bright and not dark else "too uneven")
    near = margin + BINDING_SLACK * width
    return Drives(drive, shutter, kappa, margin, cause == "in band", cause, gray,
                  int(np.argmin(low_slack)), int(np.argmin(high_slack)),
                  tuple(int(p) for p in np.flatnonzero(low_slack <= near)),
                  tuple(int(p) for p in np.flatnonzero(high_slack <= near)),
                  tuple(int(k) for k in np.flatnonzero(~active)),
                  tuple(int(p) for p in np.flatnonzero(~lit.any(axis=0))),
                  dark_fraction, bright_fraction, (float(low.min()), float(high.max())), float(drive_error),
                  solves, message)


def _slack_off(drive: np.ndarray, v: np.ndarray, gain: float, w_min: np.ndarray, black_level: float,
               low: np.ndarray, high: np.ndarray, delta: float) -> np.ndarray:
    """`drive` with every channel that may be off (w_min 0) and adds at most SLACK_GRAY at every
    sample at exposure gain x (x w_k max_p v_kp) set to exactly 0, where the band's margin stays
    as good (within BINDING_SLACK band widths, HiGHS's own tolerance's scale): the program's
    slack, written as off."""
    def margin(w):
        signal = gain * (w @ v)
        return min(float((black_level + (1 - delta) * signal - low).min()),
                   float((high - black_level - (1 + delta) * signal).min()))

    faint = (w_min == 0) & (drive > 0) & (gain * drive * v.max(axis=1) <= SLACK_GRAY)
    if not faint.any():
        return drive
    off = np.where(faint, 0.0, drive)
    before, after = margin(drive), margin(off)
    return off if after >= before - BINDING_SLACK * float((high - low).min()) else drive


def _with_contrast(v, bounds, delta, w_min, w_max, switched, gain_range, contrast, active, scale, band_only):
    """(x, w, solves, message) in scaled units with the contrast rows, tangent at the band's
    optimum `band_only` (x, w, message) and then at each solution (CUT_ROUNDS); the band's own
    where the rows make the program infeasible."""
    x, w, message = band_only
    solves = 0
    held = set()
    for _ in range(CUT_ROUNDS):
        u = np.zeros(len(active))
        u[active] = x * w / scale
        short = contrast.cnr(u) - contrast.min_cnr
        held |= set(np.argsort(short)[:CONTRAST_ROWS].tolist()) if not held else set(np.flatnonzero(short < 0).tolist())
        if not held:
            break
        chosen = np.array(sorted(held))
        a, b = contrast.cuts(u, active, scale)
        try:
            x, w, more, message = _optimum(v, bounds, delta, w_min[active], w_max[active], switched[active],
                                           gain_range, (a[chosen], b[chosen]))
        except RuntimeError:                      # infeasible with the rows: the band's drives stand
            return band_only[0], band_only[1], solves, band_only[2] + "; the defects' contrast rows infeasible"
        solves += more
    return x, w, solves, message


def _optimum(v, bounds, delta, w_min, w_max, switched, gain_range, extra=None):
    """(x, w (K,), solves, HiGHS's last message) in scaled units: with switched channels the
    mixed-integer program picks which are on, and the LP is solved again with that pattern fixed,
    since milp's integrality tolerance lets z_k sit a hair off 0 or 1 and big-M leaks M times it."""
    solves = 0
    if switched.any():
        _, w, solves, _ = _two_stages(v, bounds, delta, w_min, w_max, switched, gain_range, extra)
        on = w > 0.5 * w_max
        w_min = np.where(switched & on, w_max, w_min)
        w_max = np.where(switched & ~on, 0.0, w_max)
    x, w, more, message = _two_stages(v, bounds, delta, w_min, w_max, np.zeros_like(switched), gain_range, extra)
    return x, w, solves + more, message


def _two_stages(v, bounds, delta, w_min, w_max, switched, gain_range, extra=None):
    """(x, w, solves, message): the best margin m*, then the shortest exposure with m >= m* -
    MARGIN_SLACK (PATTERN_SLACK with switched channels). Columns [x, u_0 .. u_K-1, m, z_j for the switched], all in scaled units."""
    low, high = bounds
    k = len(v)
    s = int(switched.sum())
    x_lo, x_hi = gain_range
    n = k + 2 + s
    # every feasible point's margin is at least m0, that of the least light (x_lo, lowest drives); so
    # (1 + delta) u_k v_kp <= high_p - m0 holds at the optimum: a tight bound on u_k and big-M
    signal0 = x_lo * (w_min @ v)
    m0 = min(((1 - delta) * signal0 - low).min(), (high - (1 + delta) * signal0).min())
    with np.errstate(divide="ignore"):
        u_cap = np.min(np.where(v > 0, (high - m0) / ((1 + delta) * np.where(v > 0, v, 1.0)), np.inf), axis=1)
    # and x need not exceed what puts some u_k at x w_max_k: a longer exposure with the same u (the
    # same gray) has a switched channel off, or dimmable ones lower, and min x picks the shorter one
    some = w_max > 0
    x_hi = min(x_hi, max(x_lo, float(np.max(u_cap[some] / w_max[some], initial=0.0))))
    rows = [np.hstack([-w_max[:, None], np.eye(k), np.zeros((k, 1 + s))]),         # u_k <= x w_max
            np.hstack([w_min[:, None], -np.eye(k), np.zeros((k, 1 + s))])]         # u_k >= x w_min
    rhs = [np.zeros(k), np.zeros(k)]
    if s:
        idx = np.flatnonzero(switched)
        pick = np.eye(k)[idx]                                   # (s, k): channel of each z_j
        big = np.minimum(x_hi * w_max[idx], u_cap[idx])
        rows += [np.hstack([np.zeros((s, 1)), pick, np.zeros((s, 1)), -np.diag(big)]),    # u_k <= M z_k
                 np.hstack([w_max[idx, None], -pick, np.zeros((s, 1)),                   # u_k >= x w_max
                            np.diag(x_hi * w_max[idx])])]                                #   - M (1 - z_k)
        rhs += [np.zeros(s), x_hi * w_max[idx]]
    if extra is not None:                                       # rows on the u columns alone (ContrastRows.cuts)
        a_u, b_u = extra
        rows.append(np.hstack([np.zeros((len(b_u), 1)), a_u, np.zeros((len(b_u), 1 + s))]))
        rhs.append(b_u)
    lb = np.concatenate([[x_lo], np.zeros(k), [-np.inf], np.zeros(s)])
    ub = np.concatenate([[x_hi], np.minimum(u_cap, x_hi * w_max), [np.inf], np.ones(s)])
    program = _BandRows(v, bounds, delta, np.vstack(rows).reshape(-1, n), np.concatenate(rhs), lb, ub, s)
    best = program.solve(-np.eye(n)[k + 1])
    if not best.success:                      # always feasible (m is free): the solver failed
        raise RuntimeError(f"drive levels: HiGHS failed: {best.message}")
    m_best = best.x[k + 1]
    # never trade a margin >= 0 for one below: a band from b keeps an unlit sample in at m = 0
    res = program.solve(np.eye(n)[0], max(m_best - (PATTERN_SLACK if s else MARGIN_SLACK), min(m_best, 0.0)))
    message = res.message
    if not res.success:       # HiGHS's tolerances, a floor this close to its own optimum: that optimum stands
        res, message = best, f"{best.message}; the shortest exposure's: {res.message} (the best margin's kept)"
    x = max(res.x[0], x_lo)   # HiGHS may return a hair below the bound (its feasibility tolerance), even 0
    return x, np.clip(res.x[1:k + 1] / x, w_min, w_max), program.solves, message


class _BandRows:
    """The program's band rows by constraint generation: HiGHS solves with the samples' rows
    that bind or were violated so far (at first each channel's darkest and brightest sample and the
    extremes of their sum), every sample is checked at the solution and the worst violated rows
    join, until none is. At the end the solution holds for every sample: it is the full program's
    optimum, at a fraction of its size (an optimum binds at most as many rows as it has columns)."""

    def __init__(self, v: np.ndarray, bounds: tuple[np.ndarray, np.ndarray], delta: float, fixed_a: np.ndarray,
                 fixed_b: np.ndarray, lb: np.ndarray, ub: np.ndarray, n_integer: int) -> None:
        self.v, self.bounds, self.delta = v, bounds, delta
        self.fixed_a, self.fixed_b, self.lb, self.ub, self.n_integer = fixed_a, fixed_b, lb, ub, n_integer
        total = v.sum(axis=0)
        self.low_rows = set(v.argmin(axis=1).tolist()) | {int(total.argmin())}
        self.high_rows = set(v.argmax(axis=1).tolist()) | {int(total.argmax())}
        self.solves = 0

    def solve(self, c: np.ndarray, margin_at_least: float = -np.inf) -> OptimizeResult:
        """HiGHS's result on min c z, m >= margin_at_least, every sample's rows held (or its
        failure, unsuccessful)."""
        v, (low, high), delta = self.v, self.bounds, self.delta
        k, n = len(v), len(c)
        lb = self.lb.copy()
        lb[k + 1] = margin_at_least
        while True:
            lows, highs = sorted(self.low_rows), sorted(self.high_rows)
            band_a = np.zeros((len(lows) + len(highs), n))
            band_a[:len(lows), 1:k + 1] = -(1 - delta) * v[:, lows].T
            band_a[len(lows):, 1:k + 1] = (1 + delta) * v[:, highs].T
            band_a[:, k + 1] = 1.0
            band_b = np.concatenate([-low[lows], high[highs]])
            res = _highs(c, np.vstack([band_a, self.fixed_a]), np.concatenate([band_b, self.fixed_b]),
                         lb, self.ub, self.n_integer)
            self.solves += 1
            if not res.success:
                return res
            signal, m = res.x[1:k + 1] @ v, res.x[k + 1]
            added = 0
            for rows, short in ((self.low_rows, (1 - delta) * signal - low - m),
                                (self.high_rows, high - (1 + delta) * signal - m)):
                short[list(rows)] = 0.0
                worst = np.argsort(short)[:n]
                new = worst[short[worst] < -VIOLATION]
                rows.update(new.tolist())
                added += len(new)
            if not added:
                return res


def _highs(c, a, b, lb, ub, n_integer):
    """HiGHS on min c z, a z <= b, lb <= z <= ub, the last n_integer columns integer: milp when
    there are any, linprog otherwise."""
    if n_integer:
        integrality = np.concatenate([np.zeros(len(c) - n_integer), np.ones(n_integer)])
        with native_output_silenced(1):  # HiGHS's MIP prints a debug line from C++ at times, whatever disp says
            return milp(c, integrality=integrality, bounds=Bounds(lb, ub),
                        constraints=LinearConstraint(a, -np.inf, b), options={"mip_rel_gap": 0.0})
    return linprog(c, A_ub=a, b_ub=b, bounds=np.column_stack([lb, ub]), method="highs")
