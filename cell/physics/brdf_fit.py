"""The BRDF of eq. (6)-(7) fitted to goniometer data, one fit per phase angle (sec. 3.3): `cell fit-brdf`.

R = rho (cos ti + sigma1 c^m1 + sigma2 c^m2), c = 2 cos te cos ti - cos alpha. The diffuse term has
no coefficient of its own, so rho (the diffuse albedo) and the sigma_k (specular amplitudes relative
to it) are separately identifiable once the data sample the diffuse background as well as the
specular peak; no normalization is needed. (The paper fits only sigma_k, m_k with eq. 8-9 because its
gray values have an unknown scale and gets rho from eq. 18-19; our CSV holds R, so rho is fitted
too, with the Jacobian including rho as the physics notes require.) Two degeneracies remain:
- the two terms can swap: the lobe is the broader one (m1 < m2), and a lone specular term is a lobe;
- sigma_k = 0 leaves m_k free: a term is kept only if an F-test against the model without it
  says the data need it (p < SIGNIFICANCE); an absent term gets sigma_k = 0 and infinite standard
  errors, and its phase angle is listed under `unidentifiable`.
- a term narrower than the data's step about the mirror direction falls between the readings:
  an exponent above M = ln 2 / (2 s^2) (sampling_step s, resolvable_exponent), or a term the
  F-test drops, is unresolved (unresolved_terms: sigma 0, m = M, infinite standard errors).
  `cell fit-brdf` and `cell measure-brdf` both fit by fit_goniometer, so on one CSV they write
  one material and say what is unresolved in the same words (unresolved_notes).
Residuals are relative, (R - y) / y: readings span the spike's peak and the diffuse background
(often 1000:1) and their error grows with the reading; readings under DARK_FRACTION of the phase's
largest are weighted as if they were that large (dark level). R is linear in rho, so each phase is
fitted in units of its largest reading: the fit is the same at any scale of the readings.
"""

from __future__ import annotations

import csv
import dataclasses
import io
from collections.abc import Iterator, Sequence
from typing import Any
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np
from scipy import optimize, stats

from cell.core.errors import TaskError
from cell.core.inputs import read_text
from cell.physics.material import PARAMETERS, TERMS
from cell.physics.brdf import brdf_terms, reflectance, reflectance_jacobian

COLUMNS = ("theta_i_deg", "theta_e_deg", "phase_deg", "reflectance")
MIN_ROWS = len(PARAMETERS) + 1          # one more than the parameters, so the residual is defined
TRIANGLE_TOLERANCE_DEG = 1e-6
LN_M_MAX = np.log(1e5)                  # exponents in [1, 1e5], where stable_power is accurate
LN_M_GRID = np.linspace(0.0, LN_M_MAX, 21)   # multi-start grid: factor 1.78 between exponents
STARTS = 3                              # best grid points refined by nonlinear least squares
RHO_MIN = 1e-9                          # rho > 0 (loader), in units of the phase's largest reading;
                                        # binds only without a diffuse background
SIGMA_MAX = 1e12                        # a term 1e12 times the diffuse: the data never sampled its peak
SIGNIFICANCE = 1e-3                     # F-test level for keeping a specular term
DARK_FRACTION = 1e-3
RESIDUAL_FLOOR = 1e-6                   # relative error no goniometer beats (noise-free data)
ROWS_MAX = 100_000                      # data rows read at most: the fit takes ~1 s per 10,000 rows
PHASES_MAX = 1_000                      # phase angles fitted at most, ~0.04 s each
SHOWN_CHARS = 80                        # an error line quotes at most this much of a value
REFLECTANCE_MAX = 1e100                 # far above any reading (a mirror through a 0.01 deg aperture: ~1e7)
BRIGHTEST_MIN = 1e-100                  # each phase's largest reading at least this; with REFLECTANCE_MAX,
                                        # rho, its stderr and the residual scaled back stay finite and > 0


@dataclass(frozen=True)
class Measurements:
    """Goniometer rows sharing one phase angle: angles [deg] and measured reflectance."""

    phase_deg: float
    theta_i_deg: np.ndarray
    theta_e_deg: np.ndarray
    reflectance: np.ndarray


@dataclass(frozen=True)
class PhaseFit:
    """The fit at one phase angle and its verdict: uncertainties, residual, absent terms."""

    phase_deg: float
    rows: int
    params: np.ndarray        # rho, sigma1, m1, sigma2, m2
    stderr: np.ndarray        # same order; inf where the data do not determine the parameter
    rms_residual: float       # RMS of R_fit - R_measured [reflectance units]
    p_values: tuple[float, float]# F-test p of adding the lobe (to diffuse), the spike (to the lobe)
    absent: tuple[str, ...]   # terms the data do not support, from TERMS


# --- reading the CSV ---

def shown(text: str) -> str:
    """A value as an error line shows it: quoted, at most SHOWN_CHARS characters of it, '...' after."""
    text = text.strip()
    if not text:
        return "an empty field"
    return repr(text[:SHOWN_CHARS]) + ("..." if len(text) > SHOWN_CHARS else "")


def _lines(first, last):
    """Where a row is: a quoted field may hold line breaks (an unclosed quote runs on to the end)."""
    return f"line {first}" if first == last else f"lines {first}-{last}"


def _csv_rows(path, text):
    """(where, fields) of each non-blank row of CSV text, at most ROWS_MAX + 1 of them (the header)."""
    reader, rows, last = csv.reader(io.StringIO(text, newline="")), [], 0
    try:
        for row in reader:
            if any(x.strip() for x in row):
                if len(rows) > ROWS_MAX:
                    where = _lines(last + 1, reader.line_num)
                    raise TaskError(path, where, f"more than {ROWS_MAX:,} data rows",
                                    f"at most {ROWS_MAX:,} (cell.physics.brdf_fit.ROWS_MAX; fitting takes ~1 s per 10,000)")
                rows.append((_lines(last + 1, reader.line_num), row))
            last = reader.line_num
    except csv.Error as err:
        raise TaskError(path, f"line {last + 1}", f"broken CSV ({err})", "CSV text") from None
    return rows


def _cell(path, where, column, text, ok, expected):
    """One field as a finite float passing ok."""
    where, found = f"{where}, {column}", shown(text)
    try:
        value = float(text)
    except ValueError:
        raise TaskError(path, where, found, "a number") from None
    if not np.isfinite(value):
        raise TaskError(path, where, found, "a finite number")
    if not ok(value):
        raise TaskError(path, where, found, expected)
    return value


def read_goniometer(path: str | PathLike[str]) -> list[Measurements]:
    """The CSV's rows grouped by phase angle (ascending); any bad field, row or group is a TaskError."""
    path = Path(path)
    rows = _csv_rows(path, read_text(path, "csv"))
    if not rows:
        raise TaskError(path, "", "an empty file", "a header " + ",".join(COLUMNS) + " and data rows")
    header = [h.strip() for h in rows[0][1]]
    where = f"{rows[0][0]} (header)"
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise TaskError(path, where, "columns " + shown(",".join(header)),
                        f"the columns {','.join(COLUMNS)} (missing {', '.join(missing)})")
    twice = next((h for i, h in enumerate(header) if h and h in header[:i]), None)
    if twice is not None:
        fields = ", ".join(str(i + 1) for i, h in enumerate(header) if h == twice)
        raise TaskError(path, where, f"the column {shown(twice)} in fields {fields}",
                        "each column named once")
    angle = (lambda v: 0 <= v < 90, "an angle in [0, 90) deg (lamp and camera in front of the surface)")
    checks = {"theta_i_deg": angle, "theta_e_deg": angle,
              "phase_deg": (lambda v: 0 <= v <= 180, "an angle in [0, 180] deg"),
              "reflectance": (lambda v: 0 <= v <= REFLECTANCE_MAX,
                              f"a reflectance in [0, {REFLECTANCE_MAX:g}]")}
    groups: dict[float, list[tuple[float, float, float]]] = {}
    for where, row in rows[1:]:
        if len(row) != len(header):
            raise TaskError(path, where, f"{len(row)} fields", f"{len(header)}, as in the header")
        ti, te, phase, r = (_cell(path, where, c, row[header.index(c)], *checks[c]) for c in COLUMNS)
        if not abs(ti - te) - TRIANGLE_TOLERANCE_DEG <= phase <= ti + te + TRIANGLE_TOLERANCE_DEG:
            found = f"theta_i {ti:.10g}, theta_e {te:.10g}, phase {phase:.10g} deg"
            raise TaskError(path, where, found,
                            "|theta_i - theta_e| <= phase <= theta_i + theta_e (lamp, camera and normal "
                            "form a spherical triangle)")
        groups.setdefault(phase, []).append((ti, te, r))
    if not groups:
        raise TaskError(path, "", "a header but no data rows", "one row per measurement")
    if len(groups) > PHASES_MAX:
        raise TaskError(path, "phase_deg", f"{len(groups):,} phase angles",
                        f"at most {PHASES_MAX:,} (cell.physics.brdf_fit.PHASES_MAX; one fit each)")
    for phase, group in groups.items():
        if len(group) < MIN_ROWS:
            raise TaskError(path, f"phase_deg {phase:g}", f"{len(group)} rows",
                            f"at least {MIN_ROWS} rows per phase angle (5 parameters and a residual)")
        brightest = max(r for _, _, r in group)
        if brightest < BRIGHTEST_MIN:
            found = "all 0" if brightest == 0 else f"the largest {brightest:.3g}"
            raise TaskError(path, f"phase_deg {phase:g}", f"{len(group)} readings, {found}",
                            f"a reflectance of at least {BRIGHTEST_MIN:g} at each phase angle "
                            "(nothing to fit)")
    return [Measurements(phase, *np.array(groups[phase]).T) for phase in sorted(groups)]


# --- fitting one phase angle ---

def _physical(x):
    """Fit vector (rho, sigma1, ln m1, sigma2, ln m2), possibly cut short after rho or m1 ->
    (rho, sigma1, m1, sigma2, m2); a term cut off has sigma 0 (its m = 1 then has no effect)."""
    p = np.zeros(len(PARAMETERS))
    p[:len(x)] = x
    p[2::2] = np.exp(p[2::2])
    return p


def _grid_starts(terms, y, w, powers):
    """(weighted RSS, fit vector) per grid exponent pair; for fixed m_k, R is linear in
    (rho, rho sigma1, rho sigma2), solved by non-negative least squares, then held in the bounds."""
    n = len(LN_M_GRID)
    pairs = ([()] if terms == 0 else [(a,) for a in range(n)] if terms == 1 else
             [(a, b) for a in range(n) for b in range(a + 2, n)])   # m2 >= 3 m1
    for ks in pairs:
        a = np.column_stack([powers[-1]] + [powers[k] for k in ks]) / w[:, None]
        coef, _ = optimize.nnls(a, y / w)
        rho = max(coef[0], RHO_MIN)
        with np.errstate(over="ignore"):         # a column ~0 at every row: a huge coefficient, clipped
            sigmas = np.minimum(coef[1:] / rho, SIGMA_MAX)
        x0 = [rho] + [v for sigma, k in zip(sigmas, ks) for v in (sigma, LN_M_GRID[k])]
        yield np.sum((a @ np.concatenate([[rho], rho * sigmas]) - y / w) ** 2), np.array(x0)


def _fit_terms(geometry, y, w, terms, powers):
    """Best fit vector with `terms` specular terms (0, 1, 2) and its weighted RSS: the best STARTS
    grid points refined by bounded least squares (trf) with the analytic Jacobian of eq. (8)-(9)."""
    k = 1 + 2 * terms

    def residual(x):
        return (reflectance(*geometry, *_physical(x)) - y) / w

    def jacobian(x):
        p = _physical(x)
        j = reflectance_jacobian(*geometry, *p)
        j[:, 2::2] *= p[2::2]                          # d/d(ln m) = m d/dm
        return j[:, :k] / w[:, None]

    lower = np.array([RHO_MIN, 0.0, 0.0, 0.0, 0.0])[:k]
    upper = np.array([np.inf, SIGMA_MAX, LN_M_MAX, SIGMA_MAX, LN_M_MAX])[:k]
    starts = sorted(_grid_starts(terms, y, w, powers), key=lambda s: s[0])[:STARTS]
    best = min((optimize.least_squares(residual, x0, jac=jacobian, bounds=(lower, upper), method="trf",
                                       x_scale="jac") for _, x0 in starts), key=lambda r: r.cost)
    return best.x, 2.0 * best.cost


def _p_value(rss_without, rss_with, extra, dof):
    """F-test: chance that `extra` parameters lower the weighted RSS this much on pure noise."""
    noise = max(rss_with, dof * RESIDUAL_FLOOR**2) / dof
    return float(stats.f.sf(max(rss_without - rss_with, 0.0) / extra / noise, extra, dof))


def standard_errors(jac_w: np.ndarray, rss: float, dof: int) -> np.ndarray:
    """sqrt(diag(s^2 (J^T J)^-1)), s^2 = RSS / dof, J the weighted Jacobian; via the SVD of J with
    scaled columns, inf for a parameter in a direction J cannot see (zero column, singular J)."""
    norms = np.linalg.norm(jac_w, axis=0)
    stderr = np.full(jac_w.shape[1], np.inf)
    live = norms > 0
    _, s, vt = np.linalg.svd(jac_w[:, live] / norms[live], full_matrices=False)
    null = s <= 1e-10 * s[0]
    variance = np.sum((vt[~null] / s[~null, None]) ** 2, axis=0) * rss / dof
    blind = np.any(np.abs(vt[null]) > 1e-8, axis=0)
    stderr[live] = np.where(blind, np.inf, np.sqrt(variance) / norms[live])
    return stderr


def fit_phase(m: Measurements) -> PhaseFit:
    """Fit eq. (7) to the Measurements at one phase angle; the model (diffuse, + lobe, + spike)
    is the smallest the F-tests allow."""
    cos_i, cos_e, cos_alpha = (np.cos(np.radians(a)) for a in (m.theta_i_deg, m.theta_e_deg, m.phase_deg))
    geometry = (cos_i, cos_e, cos_alpha)
    scale = float(m.reflectance.max()) or 1.0
    y, n = m.reflectance / scale, len(m.reflectance)
    w = np.maximum(y, DARK_FRACTION * y.max()) if y.max() > 0 else np.ones(n)
    diffuse, _, _ = brdf_terms(*geometry, 0.0, 1.0, 0.0, 1.0)
    powers = [brdf_terms(*geometry, 1.0, np.exp(g), 0.0, 1.0)[1] for g in LN_M_GRID] + [diffuse]
    fits = [_fit_terms(geometry, y, w, terms, powers) for terms in (0, 1, 2)]
    p_values = (_p_value(fits[0][1], fits[1][1], 2, n - 3), _p_value(fits[1][1], fits[2][1], 2, n - 5))
    terms = 2 if p_values[1] < SIGNIFICANCE else 1 if p_values[0] < SIGNIFICANCE else 0
    x, rss = fits[terms]
    params = _physical(x)
    if params[2] > params[4] and terms == 2:          # the lobe is the broader term
        params = params[[0, 3, 4, 1, 2]]
    k = 1 + 2 * terms
    jac_w = reflectance_jacobian(*geometry, *params)[:, :k] / w[:, None]
    stderr = np.concatenate([standard_errors(jac_w, rss, n - k), np.full(len(PARAMETERS) - k, np.inf)])
    rms = float(np.sqrt(np.mean((reflectance(*geometry, *params) - y) ** 2)))
    unit = np.array([scale, 1.0, 1.0, 1.0, 1.0])                 # rho in the readings' units
    return PhaseFit(float(m.phase_deg), n, params * unit, stderr * unit, rms * scale, p_values, TERMS[terms:])


def fit_material(groups: Sequence[Measurements]) -> list[PhaseFit]:
    """PhaseFits for all phase angles. The exponent of an absent term does not change R, but the
    table is interpolated over the phase angle: take it from the nearest phases that have the term
    (so a fading spike keeps its width), and keep m2 > m1 as the loader requires."""
    fits = [fit_phase(m) for m in groups]
    phase = np.array([f.phase_deg for f in fits])
    table = np.array([f.params for f in fits])
    for term, col in zip(TERMS, (2, 4)):
        has = np.array([term not in f.absent for f in fits])
        if has.any() and not has.all():
            table[~has, col] = np.interp(phase[~has], phase[has], table[has, col])
    no_spike = np.array(["spike" in f.absent for f in fits])
    table[no_spike, 4] = np.maximum(table[no_spike, 4], 2.0 * table[no_spike, 2])
    return [dataclasses.replace(f, params=p) for f, p in zip(fits, table)]


# --- what the sampling resolves ---

STEP_DIGITS = 6                         # the step in degrees, as the material file writes it


def mirror_tilt(m: Measurements) -> np.ndarray:
    """beta [rad] of each reading, eq. (7)'s mirror cosine c = cos 2 beta: half the angle between
    the camera and the lamp's mirror direction. sin^2 beta = (1 - c) / 2, with 2 cos ti cos te =
    cos(ti - te) + cos(ti + te) written as sines, so a mirror pose (ti = te = alpha / 2 in the
    plane of incidence) is exactly 0, not the sqrt of a rounding error."""
    ti, te, alpha = m.theta_i_deg, m.theta_e_deg, m.phase_deg
    half = lambda deg: np.sin(np.radians(0.5 * deg))          # noqa: E731
    sin2 = half(ti - te) ** 2 + half(ti + te + alpha) * half(ti + te - alpha)
    return np.arcsin(np.sqrt(np.clip(sin2, 0.0, 1.0)))


def sampling_step(groups: Sequence[Measurements]) -> float:
    """The data's step s about the mirror direction [rad], the coarsest of the phase angles': per
    phase, the larger of twice the tilt beta of the reading nearest the mirror and the gap from it
    to the next distinct beta (a goniometer stepping beta by s from 0, or from s / 2, gives s;
    data that miss the mirror give at least twice their nearest tilt). Rounded as the file writes it."""
    steps = []
    for m in groups:
        beta = np.unique(np.round(mirror_tilt(m), 9))
        gap = beta[1] - beta[0] if len(beta) > 1 else np.pi / 2
        steps.append(max(2.0 * beta[0], gap))
    return float(np.radians(float(f"{np.degrees(max(steps)):.{STEP_DIGITS}g}")))


def resolvable_exponent(step_rad: float) -> float:
    """M = ln 2 / (2 step^2): the largest exponent whose peak (half width sqrt(ln 2 / (2 m)) in
    beta, c^m ~ exp(-2 m beta^2)) is at least one step wide."""
    return float(np.log(2.0) / (2.0 * step_rad**2))


def unresolved_terms(doc: dict[str, Any], step_rad: float) -> dict[str, list[float]]:
    """Mark in the material document (in place) each phase's lobe or spike the sampling cannot
    resolve: a spike absent from the data, or an exponent above resolvable_exponent(step); there
    sigma 0, m = M (a spike's at least twice m1), standard errors inf, and the `unresolved`
    section. Returns {term: [phase_deg]}."""
    m_max = resolvable_exponent(step_rad)
    out: dict[str, list[float]] = {}
    for term, s, m in (("lobe", "sigma1", "m1"), ("spike", "sigma2", "m2")):
        absent = doc.get("unidentifiable", {}).get(term, []) if term == "spike" else []
        for i, phase in enumerate(doc["phase_deg"]):
            if phase in absent or doc[m][i] > m_max:
                doc[s][i] = 0.0
                doc[m][i] = float(f"{m_max if term == 'lobe' else max(m_max, 2.0 * doc['m1'][i]):.6g}")
                doc[f"{s}_stderr"][i] = doc[f"{m}_stderr"][i] = float("inf")
                out.setdefault(term, []).append(phase)
    if out:
        doc["unresolved"] = {"terms": out, "step_deg": float(f"{np.degrees(step_rad):.{STEP_DIGITS}g}"),
                             "resolvable_m_max": float(f"{m_max:.6g}")}
    return out


def unresolved_notes(doc: dict[str, Any]) -> list[str]:
    """One line per unresolved term, as both commands say it."""
    section = doc.get("unresolved")
    if not section:
        return []
    return [f"{term} unresolved at phase {', '.join(f'{p:g}' for p in phases)} deg: the data's step of "
            f"{section['step_deg']:g} deg about the mirror direction sees exponents up to "
            f"{section['resolvable_m_max']:.4g}; a finer step measures it (cell measure-brdf: "
            "calibration.goniometer.step_deg)" for term, phases in section["terms"].items()]


def shown_estimate(doc: dict[str, Any], parameter: str, k: int) -> str:
    """A material document's `parameter` at its k-th phase as both commands print it: `value +-
    standard error`; the exponent of a term the data cannot resolve (unresolved) or do not hold
    (unidentifiable) there `- (not resolved)` / `- (no <term> in the data)`, its value meaningless;
    a value whose standard error is infinite (a term set to 0) `value (not resolved)`, not `+- inf`."""
    term = {"sigma1": "lobe", "m1": "lobe", "sigma2": "spike", "m2": "spike"}.get(parameter)
    phase = doc["phase_deg"][k]
    if parameter in ("m1", "m2"):
        if phase in (doc.get("unresolved") or {}).get("terms", {}).get(term, []):
            return "- (not resolved)"
        if phase in doc.get("unidentifiable", {}).get(term, []):
            return f"- (no {term} in the data)"
    value, stderr = doc[parameter][k], doc[f"{parameter}_stderr"][k]
    if not np.isfinite(stderr):
        return f"{value:.4g} (not resolved)"
    return f"{value:.4g} +- {stderr:.2g}"


@dataclass(frozen=True)
class GoniometerFit:
    """One fit of goniometer data (fit_goniometer): the per-phase fits, the material document
    (unresolved terms marked), the data's step [rad] and what is unresolved {term: [phase_deg]}."""

    fits: list[PhaseFit]
    material: dict[str, Any]
    step_rad: float
    unresolved: dict[str, list[float]]


def fit_goniometer(groups: Sequence[Measurements], name: str, source: str) -> GoniometerFit:
    """The material of goniometer data: per phase fits (fit_material), the document, and the
    terms the data's step cannot resolve marked (unresolved_terms) - the one fit of both commands."""
    fits = fit_material(groups)
    doc = material_document(fits, name, source)
    step = sampling_step(groups)
    return GoniometerFit(fits, doc, step, unresolved_terms(doc, step))


# --- output ---

def _round(value, digits):
    return float(f"{value:.{digits}g}")


def material_document(fits: Sequence[PhaseFit], name: str, source: str) -> dict[str, object]:
    """The material file's keys (docs/formats.md, "Material"), in file order."""
    doc: dict[str, object] = {"name": name, "source": source, "phase_deg": [f.phase_deg for f in fits]}
    for i, p in enumerate(PARAMETERS):
        doc[p] = [_round(f.params[i], 6) for f in fits]
    for i, p in enumerate(PARAMETERS):
        doc[f"{p}_stderr"] = [_round(f.stderr[i], 3) for f in fits]
    doc["rms_residual"] = [_round(f.rms_residual, 3) for f in fits]
    absent = {t: [f.phase_deg for f in fits if t in f.absent] for t in TERMS}
    if any(absent.values()):
        doc["unidentifiable"] = {t: phases for t, phases in absent.items() if phases}
    return doc


def absent_notes(fits: Sequence[PhaseFit]) -> Iterator[str]:
    """One line per phase angle with a term the data do not support."""
    for f in fits:
        for term in f.absent:
            k = TERMS.index(term) + 1
            yield (f"phase {f.phase_deg:g} deg: no {term} in the data (F-test p = {f.p_values[k - 1]:.2g} "
                   f"for adding it): sigma{k} = 0, m{k} unidentifiable")
