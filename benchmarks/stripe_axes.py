"""Accuracy, coverage and speed of the hybrid decoder's line estimators on the virtual rig.

    .venv/bin/python benchmarks/stripe_axes.py [--scale 1.0] [--scenes figurine tile] [--repeat 3]
                                               [--no-smooth-rows] [--trim-line-ends N]

Captures one view per scene (default sensor: shot and read noise, 8 bit) and decodes it
with every estimator of :mod:`slscan.decode.hybrid`. Per estimator and scene the table
gives:

- samples: line samples kept by the decoder
- indexed %: samples whose line index is the line nearest the ground-truth projector
  column at the sample (a sample more than one line spacing off counts as wrong)
- RMS, p95: camera-x error of the medial axis in px against the truth's crossing of the
  line's column (``projector_uv[r, :, 0] = c``, interpolated), over correctly indexed
  samples
- coverage %: correctly indexed samples / line crossings the truth has over lit pixels
  (adjacent lit pixels of a row between which ``u`` passes a line column)
- decode s: median wall time of ``decode_hybrid`` for the view, PNG reading included

then, for the default estimator, the error split by the true surface colour under each
sample (neutral, saturated red / green / blue paint, dark) and by line continuity (the
sample's line goes on in both neighbouring rows, in one — a line end — or in neither; see
``StripeSamples.continuity``), with each class's share of the mean squared error.
``--trim-line-ends N`` drops N samples at either end of every line first (as
``slscan decode --trim-line-ends``).

Scenes: "figurine" (painted, noisy), "tile" (flat, noisy), "tile-clean" (flat, noise-free),
"figurine-clean" (noise-free: what is left is the image formation on the relief, not noise).
Absolute times drift on shared machines.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from slscan.capture.session import LIT, Session
from slscan.decode.hybrid import DEFAULT_ESTIMATOR, ESTIMATORS, HybridResult, decode_hybrid
from slscan.patterns import hybrid
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor

SCENES = {
    "figurine": {"scene": "object"},
    "tile": {"scene": "tile"},
    "tile-clean": {"scene": "tile", "sensor": Sensor(noise=False)},
    "figurine-clean": {"scene": "object", "sensor": Sensor(noise=False)},
}


def line_columns(session: Session) -> np.ndarray:
    levels = max(p.params["levels"] for p in session.patterns if p.family == "hybrid")
    return hybrid.line_columns(session.projector_size[0], levels)


def possible_crossings(u: np.ndarray, lit: np.ndarray, columns: np.ndarray) -> int:
    """Line columns passed between horizontally adjacent lit pixels, all rows together."""
    a, b = u[:, :-1], u[:, 1:]
    both = lit[:, :-1] & lit[:, 1:] & np.isfinite(a) & np.isfinite(b)
    lo, hi = np.minimum(a[both], b[both]), np.maximum(a[both], b[both])
    return int(
        (
            np.searchsorted(columns, hi, side="left") - np.searchsorted(columns, lo, side="left")
        ).sum()
    )


def axis_errors(session: Session, result: HybridResult, truth=None) -> dict[str, np.ndarray]:
    """Per sample of ``result`` (first view): ``known`` (the truth has a projector column
    there), ``correct`` (known and indexed as the nearest line), ``measured`` (correct and
    the truth crosses the line's column in the row) and ``error`` (camera-x px, sample
    minus truth; NaN where not measured)."""
    truth = truth if truth is not None else session.load_ground_truth(session.views[0])
    u = truth.projector_uv[..., 0].astype(np.float64)
    columns = line_columns(session)
    s = result.samples
    w = u.shape[1]
    x0 = np.clip(np.floor(s.x).astype(int), 0, w - 2)
    t = s.x - x0
    u_at = u[s.row, x0] * (1 - t) + u[s.row, x0 + 1] * t
    known = np.isfinite(u_at)
    nearest = np.abs(columns[None, :] - np.where(known, u_at, -1e9)[:, None]).argmin(axis=1)
    correct = known & (nearest == s.stripe)
    true_x = truth.column_crossings(s.row, s.x, s.projector_column)
    measured = correct & np.isfinite(true_x)
    return {"known": known, "correct": correct, "measured": measured,
            "error": np.where(measured, s.x - np.nan_to_num(true_x), np.nan)}


def evaluate(session: Session, result: HybridResult) -> dict[str, float]:
    truth = session.load_ground_truth(session.views[0])
    u = truth.projector_uv[..., 0].astype(np.float64)
    columns = line_columns(session)
    s = result.samples
    a = axis_errors(session, result, truth)
    known, correct, measured = a["known"], a["correct"], a["measured"]
    err = np.abs(a["error"][measured])
    lit = truth.visibility == LIT
    return {
        "samples": len(s),
        "indexed": 100.0 * correct.sum() / max(known.sum(), 1),
        "rms": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        "p95": float(np.percentile(err, 95)) if len(err) else float("nan"),
        "coverage": 100.0 * correct.sum() / max(possible_crossings(u, lit, columns), 1),
        "by_surface": by_surface(truth.albedo, s.row[measured], s.x[measured], err),
        "by_continuity": {
            label: (int((n == k).sum()), float(np.sqrt(np.mean(err[n == k] ** 2))),
                    float(np.percentile(err[n == k], 95)))
            for n in [s.continuity()[measured]]
            for k, label in ((2, "inside a line"), (1, "line end"), (0, "lone sample"))
            if (n == k).any()
        },
    }


def surface_class(albedo: np.ndarray) -> np.ndarray:
    """(k,) names for true albedos (k, 3): "neutral", "dark", or "<channel> paint" where one
    channel reflects at least four times the weakest (saturated paint)."""
    top = albedo.max(axis=1)
    names = np.array(["red paint", "green paint", "blue paint"])[albedo.argmax(axis=1)].astype(object)
    names[albedo.min(axis=1) >= 0.25 * top] = "neutral"
    names[top < 0.1] = "dark"
    return names


def by_surface(albedo: np.ndarray, rows: np.ndarray, x: np.ndarray, err: np.ndarray) -> dict:
    """Axis error by the surface under the sample: name -> (samples, RMS px, p95 px)."""
    cols = np.clip(np.round(x).astype(int), 0, albedo.shape[1] - 1)
    names = surface_class(albedo[rows, cols].astype(np.float64))
    return {
        name: (int((names == name).sum()), float(np.sqrt(np.mean(err[names == name] ** 2))),
               float(np.percentile(err[names == name], 95)))
        for name in ("neutral", "red paint", "blue paint", "green paint", "dark")
        if (names == name).any()
    }


def print_by_surface(m: dict, indent: str = "", key: str = "by_surface") -> None:
    """The by-surface (or ``key="by_continuity"``) rows of :func:`evaluate`'s result, with
    each class's share of the squared error."""
    total = sum(n * rms**2 for n, rms, _ in m[key].values())
    for name, (n, rms, p95) in m[key].items():
        print(f"{indent}{name:<15}{n:>8d}{rms:>9.4f}{p95:>9.4f}{100 * n * rms**2 / total:>10.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="resolution factor (1: 1440x960 camera, 1024x768 projector)",
    )
    parser.add_argument("--scenes", nargs="+", default=["figurine", "tile"], choices=sorted(SCENES))
    parser.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), choices=ESTIMATORS)
    parser.add_argument(
        "--repeat", type=int, default=3, help="decode repetitions; the median time is shown"
    )
    parser.add_argument(
        "--smooth-rows",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="filter the line signal across rows before finding maxima (the decoder's default)",
    )
    parser.add_argument("--trim-line-ends", type=int, default=0, metavar="N",
                        help="drop N samples at either end of every line before measuring")
    args = parser.parse_args()

    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    print(
        f"hybrid pattern, {levels} levels ({2**levels - 1} lines), scale {args.scale}; "
        f"default estimator: {DEFAULT_ESTIMATOR}; "
        f"row smoothing {'on' if args.smooth_rows else 'off'}; line ends trimmed: {args.trim_line_ends}"
    )
    header = (
        f"{'scene':<16}{'estimator':<13}{'samples':>9}{'indexed %':>11}{'RMS px':>9}"
        f"{'p95 px':>9}{'coverage %':>12}{'decode s':>10}"
    )
    print(header)
    print("-" * len(header))
    surfaces = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes:
            config = VirtualCaptureConfig(
                camera_scale=args.scale,
                projector_scale=args.scale,
                levels=levels,
                lit_images=False,
                **SCENES[name],
            )
            session = capture_session(config, Path(tmp) / name)
            view = session.views[0]
            for estimator in args.estimators:
                times = []
                for _ in range(args.repeat):
                    t = time.perf_counter()
                    result = decode_hybrid(
                        session, view, estimator=estimator, smooth_rows=args.smooth_rows
                    )
                    times.append(time.perf_counter() - t)
                if args.trim_line_ends:
                    result = replace(result, samples=result.samples.trim_line_ends(args.trim_line_ends))
                m = evaluate(session, result)
                print(
                    f"{name:<16}{estimator:<13}{m['samples']:>9d}{m['indexed']:>11.2f}"
                    f"{m['rms']:>9.3f}"
                    f"{m['p95']:>9.3f}{m['coverage']:>12.1f}{statistics.median(times):>10.2f}"
                )
                if estimator == DEFAULT_ESTIMATOR:
                    surfaces[name] = m
        for name, m in surfaces.items():
            print(f"\n{name}, {DEFAULT_ESTIMATOR} estimator, by the true surface colour under the sample")
            print(f"{'surface':<15}{'samples':>8}{'RMS px':>9}{'p95 px':>9}{'% of MS':>10}")
            print_by_surface(m)
            print(f"{'continuity':<15}{'samples':>8}{'RMS px':>9}{'p95 px':>9}{'% of MS':>10}")
            print_by_surface(m, key="by_continuity")


if __name__ == "__main__":
    main()
