"""A plain numpy/scipy implementation of the same method, for ``bench``'s speed ratio and as
the tests' references (tests/core/naive.py re-exports these functions).

Slow and obvious on purpose: Python loops, scipy's least squares for the MEMG fits and the
ellipsoid intersection, exhaustive association with the product's cost. It leaves out the
echo-quality weights (every matched echo weighs 1). Needs scipy (``pip install scipy``);
``available()`` says whether it is installed.
"""

from __future__ import annotations

import itertools

import numpy as np

from spiel_edge.profile.schema import Profile


def available() -> bool:
    try:
        import scipy.optimize  # noqa: F401
    except ImportError:
        return False
    return True


def preprocess(frames, background, blind_zone):
    y = frames - background if background is not None else frames.copy()
    y = np.clip(y, 0.0, None)
    y[:, :blind_zone] = 0.0
    return y


def detect(y, threshold, hysteresis, min_amplitude, max_echoes, first_sample):
    peaks = np.full((y.shape[0], max_echoes), -1)
    counts = np.zeros(y.shape[0], dtype=int)
    for c, row in enumerate(y):
        starts, rising = [], False
        for t in range(max(1, first_sample + 1), len(row)):
            g = row[t] - row[t - 1]
            if not rising and g > threshold:
                rising = True
                starts.append(t - 1)
            elif rising and g < threshold * hysteresis:
                rising = False
        cands = []
        for i, s in enumerate(starts):
            end = starts[i + 1] if i + 1 < len(starts) else len(row)
            best = s + int(np.argmax(row[s:end]))
            if row[best] >= min_amplitude:
                cands.append((row[best], best))
        strongest = sorted(cands, key=lambda a: (-a[0], a[1]))[:max_echoes]
        chosen = sorted(b for _, b in strongest)
        peaks[c, : len(chosen)] = chosen
        counts[c] = len(chosen)
    return peaks, counts


def emg(t, alpha, mu, sigma, eta):
    from scipy.special import erf

    u = (t - mu) / sigma
    return alpha * np.exp(-0.5 * u * u) * (1 + erf(eta * u / np.sqrt(2)))


def emg_gradient(t, alpha, mu, sigma, eta):
    """Partial derivatives (len(t), 4) of :func:`emg` by alpha, mu, sigma, eta."""
    from scipy.special import erf

    u = (t - mu) / sigma
    g = np.exp(-0.5 * u * u)
    e = 1 + erf(eta * u / np.sqrt(2))
    s = np.sqrt(2 / np.pi) * np.exp(-0.5 * eta * eta * u * u)
    dm_du = alpha * g * (-u * e + eta * s)
    return np.c_[g * e, -dm_du / sigma, -dm_du * u / sigma, alpha * g * s * u]


def paths(position, channels, emitter):
    return np.linalg.norm(position - emitter) + np.linalg.norm(position - channels, axis=1)


def locate(d, channels, emitter, use, start, weights=None):
    from scipy.optimize import least_squares

    w = np.ones(len(d)) if weights is None else np.asarray(weights)

    def resid(p):
        return w[use] * (paths(p, channels[use], emitter) - d[use])

    sol = least_squares(resid, start, method="lm", xtol=1e-12, ftol=1e-12)
    plain = paths(sol.x, channels[use], emitter) - d[use]
    return sol.x, float(np.sqrt(np.mean(plain**2)))


def fit_memg(y, peaks, counts, mu_window=3.0, max_iter=12, gap=7, before=5, after=6):
    """Each cluster of echoes closer than ``gap`` samples fitted jointly (scipy, bounded)."""
    from scipy.optimize import least_squares

    params = np.full(peaks.shape + (4,), np.nan)
    t_all = np.arange(y.shape[1], dtype=float)
    for c in range(y.shape[0]):
        k = 0
        while k < counts[c]:
            last = k
            while last + 1 < counts[c] and peaks[c, last + 1] - peaks[c, last] < gap:
                last += 1
            idx = range(k, last + 1)
            lo, hi = max(0, peaks[c, k] - before), min(y.shape[1], peaks[c, last] + after + 1)
            t, data = t_all[lo:hi], y[c, lo:hi]
            start = [
                v
                for i in idx
                for v in (max(y[c, peaks[c, i]], 1e-3) * 0.6, peaks[c, i] - 0.5, 1.5, 1.0)
            ]
            low = [v for i in idx for v in (1e-6, peaks[c, i] - mu_window, 0.4, -4.0)]
            high = [v for i in idx for v in (4 * data.max() + 1, peaks[c, i] + mu_window, 6.0, 8.0)]
            start = np.clip(start, np.array(low) + 1e-9, np.array(high) - 1e-9)

            def resid(p, t=t, data=data):
                return data - sum(emg(t, *p[4 * j : 4 * j + 4]) for j in range(len(p) // 4))

            def jac(p, t=t):
                return -np.hstack(
                    [emg_gradient(t, *p[4 * j : 4 * j + 4]) for j in range(len(p) // 4)]
                )

            # the kernel's iteration cap, in function evaluations
            sol = least_squares(resid, start, jac=jac, bounds=(low, high), max_nfev=3 * max_iter)
            params[c, k : last + 1] = sol.x.reshape(-1, 4)
            k = last + 1
    return params


def mode(alpha, mu, sigma, eta):
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(
        lambda t: -emg(t, alpha, mu, sigma, eta),
        bounds=(mu - 2 * sigma, mu + 3 * sigma),
        method="bounded",
    )
    return float(res.x)


def associate_and_locate(profile: Profile, toa, alpha, counts):
    """Every combination of one echo (or none) per channel, pruned by feasible path
    differences, located with scipy and scored with the geometric associator's cost."""
    g, s = profile.geometry, profile.associate
    ch, em, facing = np.asarray(g.channels_mm), np.asarray(g.emitter_mm), np.asarray(g.facing)
    d_all = (toa - g.delays()[:, None]) * profile.mm_per_sample
    strength = s.strength_weight_mm * np.log(np.where(alpha > 1.0, alpha, 1.0))
    max_diff = np.linalg.norm(ch[:, None] - ch[None], axis=-1) + s.tolerance_mm
    n_ch = len(counts)
    best, best_cost = None, np.inf
    for choice in itertools.product(*[range(-1, int(k)) for k in counts]):
        used = [c for c in range(n_ch) if choice[c] >= 0]
        if len(used) < s.min_channels:
            continue
        if any(
            abs(d_all[i, choice[i]] - d_all[j, choice[j]]) > max_diff[i, j]
            for i in used
            for j in used
            if i < j
        ):
            continue
        d = np.array([d_all[c, choice[c]] if choice[c] >= 0 else 0.0 for c in range(n_ch)])
        use = np.array([k >= 0 for k in choice])
        start = em + facing * max(d[use].mean() / 2, 1.0)
        pos, rms = locate(d, ch, em, use, start)
        if float(np.dot(pos - em, facing)) <= 0 or rms > s.max_residual_mm:
            continue
        cost = (
            rms
            + s.missing_penalty_mm * (n_ch - len(used))
            - np.mean([strength[c, choice[c]] for c in used])
            + s.range_weight * np.linalg.norm(pos - em)
        )
        if cost < best_cost:
            best, best_cost = (choice, pos), cost
    return best


def process(profile: Profile, frames: np.ndarray, background: np.ndarray | None):
    """Position (mm) of one acquisition, or None."""
    p = profile
    bg = background if p.preprocess.background_subtraction else None
    y = preprocess(np.asarray(frames, float), bg, p.preprocess.blind_zone_samples)
    d = p.detect
    peaks, counts = detect(
        y, d.threshold, d.hysteresis, d.min_amplitude, d.max_echoes, p.preprocess.blind_zone_samples
    )
    params = fit_memg(y, peaks, counts, p.memg.mu_window, p.memg.max_iterations)
    toa = np.full(peaks.shape, np.nan)
    for c in range(peaks.shape[0]):
        for k in range(counts[c]):
            toa[c, k] = mode(*params[c, k])
    best = associate_and_locate(p, toa, params[:, :, 0], counts)
    return None if best is None else best[1]
