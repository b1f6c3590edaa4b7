"""The projector's response in phase shifting: its gamma, measured, and the phase error it leaves.

A projector shown pattern value ``v`` (in [0, 1]) emits about ``v ** gamma`` (uncalibrated
projectors: gamma 1.5 to 2.5). Fringes pre-distorted for ``gamma_p`` (``v = I ** (1 /
gamma_p)``, the descriptions' ``gamma``) reach the scene as ``I ** (gamma / gamma_p)``:
not a sinusoid, but one with harmonics, which an N-step fit turns into a phase error
periodic in N times the phase (N = 3: the 2nd and 4th harmonics; N = 4: the 3rd and 5th,
much weaker). Two remedies, both here:

- **correct the phase** afterwards: for a known effective exponent the error is a fixed
  function of the phase, so a lookup table maps each measured phase back to the true one
  (:func:`phase_correction`; ``slscan decode --projector-gamma G``);
- **measure gamma** from a response capture: fringes of a long period pre-distorted with
  two or more exponents, and a fine Gray code that gives every pixel's projector
  coordinate to a pixel; for each set the exponent whose distorted cosines best explain
  the N captures at every pixel (offset and gain free per pixel) is the effective one,
  ``gamma = effective * gamma_p`` (:func:`estimate_gamma`; ``slscan response``). This is
  the idea of Hoang et al. (2010): two pre-distortions make the estimate independent of
  how the camera sees the fringes' amplitude.
- **estimate gamma from any capture** (:func:`gamma_from_phases`; the decoder's
  ``projector_gamma="auto"``): the error piles the fitted phases up at N values per
  period, while on a surface that sees many fringes the true phases are evenly spread; the
  gamma whose correction levels the phases' N-th harmonic is the rig's (projector and
  camera together, as the fringes reach the camera: blur and subsurface scattering soften
  them, so a scene's estimate can be below the projector's own).

References
----------
.. [1] Hoang, Pan, Nguyen, Wang, "Generic gamma correction for accuracy enhancement in
   fringe-projection profilometry", Optics Letters 35(12), 2010.
.. [2] Zhang, Yau, "Generic nonsinusoidal phase error correction for three-dimensional
   shape measurement using a digital video projector", Applied Optics 46(1), 2007
   (the phase error as a lookup table of the phase).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slscan.capture.session import Session, ViewRecord
from slscan.errors import SlscanError

GAMMA_RANGE = (0.2, 5.0)
"""Effective exponents searched by :func:`fit_effective_gamma`."""
LUT_SIZE = 4096


def emitted(theta: np.ndarray, gamma: float) -> np.ndarray:
    """Fringe light at phase ``theta`` through a response of exponent ``gamma``: ``((1 + cos theta) / 2) ** gamma``."""
    return (0.5 + 0.5 * np.cos(theta)) ** gamma


def _fit_matrix(shifts: Sequence[float]) -> np.ndarray:
    s = np.asarray(shifts, np.float64)
    m = np.stack([np.ones_like(s), np.cos(s), -np.sin(s)], axis=1)
    return np.linalg.solve(m.T @ m, m.T)  # (3, N)


def measured_phase(theta: np.ndarray, shifts: Sequence[float], gamma: float) -> np.ndarray:
    """The wrapped phase an N-step least-squares fit returns for fringes of true phase
    ``theta`` emitted through a response of exponent ``gamma`` (radians, [0, 2 pi))."""
    theta = np.asarray(theta, np.float64)
    pinv = _fit_matrix(shifts)
    images = np.stack([emitted(theta + d, gamma) for d in shifts])  # (N, m)
    c, s = pinv[1] @ images, pinv[2] @ images
    return np.mod(np.arctan2(s, c), 2 * np.pi)


@functools.lru_cache(maxsize=16)
def _table(shifts: tuple[float, ...], gamma: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(0, 2 * np.pi, size, endpoint=False)
    meas = measured_phase(theta, shifts, gamma)
    # unwrap the measured phase along the true one so that it increases monotonically
    meas = theta + np.angle(np.exp(1j * (meas - theta)))
    order = np.argsort(meas)
    return meas[order], theta[order]


def phase_error(theta: np.ndarray, shifts: Sequence[float], gamma: float) -> np.ndarray:
    """Measured minus true phase (radians, wrapped to (-pi, pi]) for fringes through ``gamma``."""
    return np.angle(np.exp(1j * (measured_phase(theta, shifts, gamma) - np.asarray(theta))))


def phase_correction(phase: np.ndarray, shifts: Sequence[float], gamma: float) -> np.ndarray:
    """The true phase (float32, [0, 2 pi)) of measured wrapped ``phase`` values of fringes
    emitted through a response of (effective) exponent ``gamma``: the inverse of
    :func:`measured_phase` by a lookup table. ``gamma`` 1 returns ``phase`` itself."""
    if abs(gamma - 1.0) < 1e-9:
        return phase
    meas, true = _table(tuple(float(s) for s in shifts), float(gamma), LUT_SIZE)
    period = 2 * np.pi
    xp = np.concatenate([meas - period, meas, meas + period])
    fp = np.concatenate([true - period, true, true + period])
    out = np.interp(np.asarray(phase, np.float64), xp, fp)
    return np.mod(out, period).astype(np.float32)


def fit_effective_gamma(images: np.ndarray, theta: np.ndarray, shifts: Sequence[float]) -> tuple[float, float]:
    """The exponent ``g`` for which ``I_k = a + b * emitted(theta + shift_k, g)`` best explains
    the captures, with ``a``, ``b`` free at every pixel.

    images : (N, n) linear captures of n pixels; theta : (n,) their true phases (radians)
    Returns ``g`` and the RMS residual (same unit as ``images``).
    """
    from scipy.optimize import minimize_scalar

    images = np.asarray(images, np.float64)
    n_img, n = images.shape
    if n_img < 3 or n < 100:
        raise SlscanError(f"gamma fit: {n_img} images of {n} pixels; expected at least 3 images of 100 pixels")
    centred = images - images.mean(axis=0)
    total = (centred**2).sum(axis=0)

    def residual(g: float) -> float:
        f = np.stack([emitted(theta + d, g) for d in shifts])
        f -= f.mean(axis=0)
        ff = (f * f).sum(axis=0)
        fi = (f * centred).sum(axis=0)
        return float(np.sum(total - fi * fi / np.maximum(ff, 1e-12)))

    best = minimize_scalar(residual, bounds=GAMMA_RANGE, method="bounded", options={"xatol": 1e-4})
    return float(best.x), math.sqrt(max(best.fun, 0.0) / (n * max(n_img - 2, 1)))


def _refined(x: np.ndarray, stacks: Sequence[np.ndarray], fringes, gamma: float) -> np.ndarray:
    """Coordinates ``x`` (px) moved to the fringes' phase, corrected for ``gamma``, within
    half a period of where they were (the mean over the sets, weighted alike)."""
    moves = []
    for st, f in zip(stacks, fringes):
        pinv = _fit_matrix(f.shifts)
        c, s = pinv[1] @ st, pinv[2] @ st
        phase = phase_correction(np.mod(np.arctan2(s, c), 2 * np.pi), f.shifts, gamma / f.gamma)
        at = 2 * np.pi * (x - f.origin) / f.period
        moves.append(np.angle(np.exp(1j * (phase - at))) * f.period / (2 * np.pi))
    return x + np.mean(moves, axis=0)


def unevenness(phases: Sequence[np.ndarray], fringes, gamma: float) -> float:
    """Mean over fringe sets of the N-th harmonic (0: even, 1: all alike) of the wrapped
    ``phases`` (one (n,) sample per set) corrected for a projector of exponent ``gamma``."""
    return float(np.mean([
        abs(np.mean(np.exp(1j * len(f.shifts) * phase_correction(ph, f.shifts, gamma / f.gamma))))
        for ph, f in zip(phases, fringes)
    ]))


def gamma_from_phases(phases: Sequence[np.ndarray], fringes) -> tuple[float, float, float]:
    """The projector exponent that spreads the fitted ``phases`` (one (n,) sample of
    well-modulated pixels per fringe set, :class:`~slscan.decode.phase.Fringes`) most
    evenly: a grid over :data:`GAMMA_RANGE` (log-spaced), refined by golden section.

    Returns (gamma, the harmonic there, the harmonic as the fringes are described: the
    level before correcting; infinite when the sets' pre-distortions differ).
    """
    lo, hi = np.log(GAMMA_RANGE[0]), np.log(GAMMA_RANGE[1])
    grid = np.exp(np.linspace(lo, hi, 41))
    costs = [unevenness(phases, fringes, g) for g in grid]
    i = int(np.argmin(costs))
    a, b = np.log(grid[max(i - 1, 0)]), np.log(grid[min(i + 1, len(grid) - 1)])
    for _ in range(20):
        m1, m2 = b - 0.618 * (b - a), a + 0.618 * (b - a)
        if unevenness(phases, fringes, np.exp(m1)) <= unevenness(phases, fringes, np.exp(m2)):
            b = m2
        else:
            a = m1
    gamma = float(np.exp(0.5 * (a + b)))
    own = {f.gamma for f in fringes}
    before = unevenness(phases, fringes, own.pop()) if len(own) == 1 else math.inf
    return gamma, unevenness(phases, fringes, gamma), before


@dataclass(frozen=True)
class GammaEstimate:
    """The projector's gamma from a response capture.

    gamma : the estimate (the mean over the sets)
    per_set : ``(gamma_p, effective, gamma = effective * gamma_p, rms)`` per pre-distortion
        and axis set, rms a fraction of full scale
    pixels : pixels used
    """

    gamma: float
    per_set: tuple[tuple[float, float, float, float], ...]
    pixels: int

    @property
    def spread(self) -> float:
        """Largest minus smallest per-set gamma: how far the sets agree."""
        values = [g for _, _, g, _ in self.per_set]
        return max(values) - min(values)

    def describe(self) -> str:
        sets = "; ".join(f"fringes for {gp:g}: effective {e:.3f} -> {g:.3f} (rms {r:.4f})"
                         for gp, e, g, r in self.per_set)
        return f"projector gamma {self.gamma:.3f} from {self.pixels:,} pixels ({sets})"


def estimate_gamma(session: Session, view: ViewRecord | str | None = None, *, max_pixels: int = 200_000,
                   min_modulation: float = 0.2) -> GammaEstimate:
    """The projector's gamma from a response capture (:func:`slscan.patterns.phase.response_set`,
    or an imported one such as kamino410's gamma set): its fringes, pre-distorted for two or
    more exponents, fitted at every lit pixel whose projector coordinate the set's Gray code
    gives (cells at most half a period), subsampled to ``max_pixels``.

    Raises
    ------
    SlscanError
        The session has no fringes with a Gray code to give the true phase, or too few lit
        pixels.
    """
    from slscan.decode.phase import _Grey, gray_order, phase_sets

    view = session.views[0] if view is None else session.view(view) if isinstance(view, str) else view
    sets = phase_sets(session.patterns, where=str(session.root))
    white_id, black_id = session.flat_frame_ids("measuring the projector's response")

    def read(pid: str) -> np.ndarray:
        return session.read_image(view, view.image_for(pid), linear=True)

    grey = _Grey(luma=session.lossy)
    white, black = grey(read(white_id), "white"), grey(read(black_id), "black")
    lit = (white - black) > 0.1
    per_set = []
    used = 0
    for s in sets.values():
        if s.gray is None or s.gray.cell > min(f.period for f in s.fringes) / 4:
            continue
        bits = [grey(read(pat), pat) > (grey(read(inv), inv) if inv is not None else 0.5 * (white + black))
                for pat, inv in s.gray.bits]
        x = s.gray.origin + s.gray.cell * (gray_order(bits) + 0.5)
        idx = np.flatnonzero(lit.ravel())
        if len(idx) > max_pixels:
            idx = idx[:: math.ceil(len(idx) / max_pixels)]
        stacks = [np.stack([grey(read(i), i).ravel()[idx] for i in f.ids]) for f in s.fringes]
        swing = np.min([st.max(axis=0) - st.min(axis=0) for st in stacks], axis=0)
        keep = swing > min_modulation * (white - black).ravel()[idx]
        stacks = [st[:, keep] for st in stacks]
        xs = x.ravel()[idx][keep]
        # the Gray code gives each pixel's coordinate to a cell; the fringes, once corrected
        # for the gamma found, to a fraction of that: refine the true phase and fit again
        results = None
        for _ in range(3):
            results = [fit_effective_gamma(st, 2 * np.pi * (xs - f.origin) / f.period, f.shifts)
                       for st, f in zip(stacks, s.fringes)]
            gamma = float(np.mean([eff * f.gamma for (eff, _), f in zip(results, s.fringes)]))
            xs = _refined(xs, stacks, s.fringes, gamma)
        per_set += [(f.gamma, eff, eff * f.gamma, rms) for (eff, rms), f in zip(results, s.fringes)]
        used = max(used, int(keep.sum()))
    if not per_set:
        raise SlscanError(
            f"{session.root}: no fringes with a Gray code fine enough (cells of at most a quarter period) to give "
            "every pixel's true phase: capture the response set (slscan patterns --family phase-response)"
        )
    return GammaEstimate(float(np.mean([g for _, _, g, _ in per_set])), tuple(per_set), used)
