"""Phase-shifting decoding on real captures (kamino410/phase-shifting), region by region.

    PYTHONPATH=toolbox .venv/bin/python benchmarks/phase_real.py [--data DIR] [--sets object1,object2,gamma]

Each set is imported with one ``import_phase`` call (presets ``kamino410-phase`` and
``kamino410-gamma``) and decoded with :func:`slscan.decode.phase.decode_phase`; beside it,
a *straightforward 3-step decoder* written here: per period the wrapped phase
``arctan2(sqrt(3) (I1 - I3), 2 I2 - I1 - I3)`` (the tool's own formula), unwrapped by the
Gray code per period (the fringe order nearest the centre of the pixel's Gray cell, each
Gray bit read as pattern > inverse), no neighbour check and no mask but white - black
above the same 3 % of full scale the slscan decoder calls lit.

Regions are hand-drawn polygons in camera pixels (:data:`REGIONS`, drawn on the white
captures, kept a few pixels inside the edges): the foam sponges (object1: subsurface
scattering), the mugs (object2: gloss, inter-reflections), the cardboard backdrop of
each, and the plane of the gamma set. Per region and decoder, for the projector columns:

- ``lit``: pixels with white - black above 3 % of full scale;
- ``decoded``: share of the lit pixels with a column (slscan: the final map; the
  baseline decodes every lit pixel);
- ``agree``: share of the lit pixels where the two fringe sets' own unwrapped columns
  (``axes["columns"].periods``; the baseline's two periods) are both there and within
  0.5 projector px of each other (gamma set: the same period pre-distorted for two
  responses);
- ``in cell``: share of the decoded pixels whose column lies inside the Gray-code cell
  read at that pixel (slscan: the final column; baseline: the mean of its two periods),
  and ``> P/4``: share more than a quarter of the longest period outside it;
- ``clipped``: share of the region's pixels at full scale in some image of the set.

A second table gives slscan's whole-image counts per axis (``AxisDecode.counts``: order
corrections and rejections by the neighbour check, periods that disagree, low
modulation) and the projector response (gamma) the phases were corrected for
(``PhaseResult.projector_gamma``). ``--gamma none`` decodes without that correction (as
before it existed), ``--gamma 2.2`` corrects for a given response. No timing assertions; the data folder is ``slscan.data.shared_data_dir()``
(``$SLSCAN_DATA`` or ``../shared/data``) unless ``--data`` is given.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from slscan.capture.phase_import import import_phase
from slscan.data import ENV_VAR, shared_data_dir
from slscan.decode.phase import (
    MIN_CONTRAST,
    AxisSet,
    PhaseResult,
    decode_phase,
    gray_order,
    phase_sets,
)

SETS = {  # name: (folder under phaseshift_kamino410/sample_data, preset)
    "object1": ("object1", "kamino410-phase"),
    "object2": ("object2", "kamino410-phase"),
    "gamma": ("gamma_correction", "kamino410-gamma"),
}
REGIONS: dict[str, dict[str, list[list[tuple[int, int]]]]] = {
    "object1": {
        "sponges": [[(676, 400), (1100, 400), (1100, 1020), (676, 1020)],
                    [(540, 1070), (1240, 1070), (1240, 1200), (540, 1200)]],
        "backdrop": [[(360, 60), (640, 60), (640, 960), (360, 960)],
                     [(1620, 60), (1880, 60), (1880, 880), (1620, 880)]],
    },
    "object2": {
        "mugs": [[(510, 560), (890, 560), (890, 1040), (510, 1040)],
                 [(990, 740), (1450, 740), (1420, 960), (1340, 1090), (1080, 1090), (1000, 960)]],
        "backdrop": [[(360, 60), (780, 60), (780, 480), (360, 480)],
                     [(1360, 60), (1880, 60), (1880, 480), (1360, 480)]],
    },
    "gamma": {
        "plane": [[(200, 120), (1780, 80), (1780, 1180), (200, 1180)]],
    },
}
"""Camera-pixel polygons (x, y) per set and region, drawn on the white captures
(1936 x 1216); a region is the union of its polygons."""
AGREE_PX = 0.5


def region_mask(shape: tuple[int, int], polygons: list[list[tuple[int, int]]]) -> np.ndarray:
    """(h, w) bool: inside any of ``polygons`` (camera px)."""
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.int32(p) for p in polygons], 1)
    return mask.astype(bool)


def gray_cells(images, s: AxisSet) -> np.ndarray:
    """(h, w) int32 Gray-code cell index at every pixel, each bit read as pattern > inverse."""
    bits = [images(pat) > images(inv) for pat, inv in s.gray.bits]
    return gray_order(bits)


def baseline(images, s: AxisSet, lit: np.ndarray, order: np.ndarray) -> list[np.ndarray]:
    """The straightforward decoder: per fringe set, the tool's 3-step arctan and the fringe
    order nearest the Gray cell's centre; (h, w) float64 column per set, NaN where not lit."""
    centre = s.gray.origin + s.gray.cell * (order + 0.5)
    out = []
    for f in s.fringes:
        if len(f.ids) != 3 or not np.allclose(f.shifts, (-2 * np.pi / 3, 0, 2 * np.pi / 3)):
            raise SystemExit(f"the baseline needs 3 steps shifted by -120, 0, 120 degrees, got {f.shifts}")
        i1, i2, i3 = (images(i) for i in f.ids)
        phase = np.arctan2(np.sqrt(3) * (i1 - i3), 2 * i2 - i1 - i3)
        frac = np.mod(phase / (2 * np.pi), 1.0)
        k = np.rint((centre - f.origin) / f.period - frac)
        out.append(np.where(lit, f.origin + f.period * (k + frac), np.nan))
    return out


def cell_agreement(column: np.ndarray, order: np.ndarray, s: AxisSet, where: np.ndarray) -> tuple[float, float]:
    """Share of ``where`` pixels whose ``column`` lies inside their Gray cell, and share
    more than a quarter of the longest period outside it."""
    lo = s.gray.origin + s.gray.cell * order - 0.5  # cell c covers pixel centres c*cell ... (c+1)*cell - 1
    hi = lo + s.gray.cell
    c = column[where]
    outside = np.maximum(lo[where] - c, c - hi[where])
    n = max(c.size, 1)
    return float((outside <= 0).sum() / n), float((outside > s.fringes[0].period / 4).sum() / n)


def measure(name: str, session, result: PhaseResult) -> list[dict]:
    """One row per region and decoder."""
    view = session.views[0]
    s = phase_sets(session.patterns)["columns"]
    cache: dict[str, np.ndarray] = {}

    def images(pid: str) -> np.ndarray:
        if pid not in cache:
            cache[pid] = session.read_image(view, view.image_for(pid)).astype(np.float32)
        return cache[pid]

    top = 255.0 if session.bit_depth == 8 else 65535.0
    lit = (images("white") - images("black")) > MIN_CONTRAST * top
    order = gray_cells(images, s)
    base = baseline(images, s, lit, order)
    base_column = np.mean(base, axis=0)
    ours = result.axes["columns"].periods
    rows = []
    for region, polygons in REGIONS[name].items():
        inside = region_mask(lit.shape, polygons)
        n_lit = int((inside & lit).sum())
        for decoder, column, per in (("slscan", result.column, ours), ("3-step", base_column, base)):
            decoded = inside & lit & np.isfinite(column)
            both = np.isfinite(per[0]) & np.isfinite(per[-1])
            agree = inside & lit & both & (np.abs(np.nan_to_num(per[0] - per[-1], nan=np.inf)) < AGREE_PX)
            in_cell, far = cell_agreement(column, order, s, decoded)
            rows.append({
                "set": name, "region": region, "decoder": decoder, "lit": n_lit,
                "decoded": decoded.sum() / max(n_lit, 1), "agree": agree.sum() / max(n_lit, 1),
                "in_cell": in_cell, "far": far,
                "clipped": float(result.saturated[inside].mean()),
            })
    return rows


def period_difference(diff: np.ndarray, size: int = 9) -> tuple[float, float, float]:
    """(median |difference|, robust SD of its pixel-to-pixel part, median |smooth part|) of
    two periods' column maps' difference (NaN where either is not decoded), px: noise
    differs from pixel to pixel, a bias (the fringes' residual distortion) does not."""
    from scipy import ndimage

    ok = np.isfinite(diff)
    filled = np.where(ok, diff, 0.0)
    weight = ndimage.uniform_filter(ok.astype(float), size)
    mean = ndimage.uniform_filter(filled, size) / np.maximum(weight, 1e-9)
    inner = ok & (weight > 0.9)
    high = (diff - mean)[inner]
    return (float(np.median(np.abs(diff[ok]))), float(1.4826 * np.median(np.abs(high - np.median(high)))),
            float(np.median(np.abs(mean[inner]))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, help=f"the shared data folder (default: ${ENV_VAR} or ../shared/data)")
    parser.add_argument("--sets", default=",".join(SETS), help=f"comma-separated, of {', '.join(SETS)}")
    parser.add_argument("--gamma", default="auto",
                        help="slscan's projector_gamma: auto (default, estimated per view), none (no "
                             "correction) or a number")
    args = parser.parse_args()
    data = args.data or shared_data_dir()
    root = None if data is None else data / "phaseshift_kamino410" / "sample_data"
    if root is None or not root.is_dir():
        raise SystemExit(f"phaseshift_kamino410 captures not found (set {ENV_VAR} or pass --data)")
    rows, counts, spreads = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sets.split(","):
            folder, preset = SETS[name]
            session = import_phase(root / folder, Path(tmp) / name, preset=preset)
            choice = args.gamma.lower()
            gamma = None if choice == "none" else choice if choice == "auto" else float(choice)
            result = decode_phase(session, session.views[0], projector_gamma=gamma)
            rows += measure(name, session, result)
            for axis, a in result.axes.items():
                counts.append((name, axis, a.counts, float(result.saturated.mean()),
                               float(np.isfinite(result.column).mean()), result.projector_gamma))
                if len(a.periods) > 1:
                    spreads.append((name, axis, *period_difference(a.periods[-1] - a.periods[0])))
    head = (f"{'set':<9}{'region':<10}{'decoder':<8}{'lit px':>10}{'decoded':>9}{'agree':>8}"
            f"{'in cell':>9}{'> P/4':>8}{'clipped':>9}")
    print(f"columns, per region (agree: both fringe sets' columns within {AGREE_PX} px, share of lit; "
          "in cell / > P/4: share of decoded)")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['set']:<9}{r['region']:<10}{r['decoder']:<8}{r['lit']:>10,}{r['decoded']:>9.1%}"
              f"{r['agree']:>8.1%}{r['in_cell']:>9.1%}{r['far']:>8.2%}{r['clipped']:>9.2%}")
    print()
    keys = ("lit", "low_modulation", "noisy", "order_from_periods", "periods_disagree", "order_corrected",
            "order_rejected",
            "out_of_range", "valid")
    head = (f"{'set':<9}{'axis':<8}" + "".join(f"{k:>19}" for k in keys)
            + f"{'clipped':>9}{'column':>8}{'gamma':>7}")
    print("slscan decoder, whole image (pixels; clipped: share of the image; column: share decoded; gamma: "
          "the projector response the phases were corrected for)")
    print(head)
    print("-" * len(head))
    for name, axis, c, clipped, share, gamma in counts:
        print(f"{name:<9}{axis:<8}" + "".join(f"{c.get(k, 0):>19,}" for k in keys)
              + f"{clipped:>9.2%}{share:>8.1%}{gamma:>7.2f}")
    if spreads:
        print("\nthe two periods' columns: their difference split into a pixel-to-pixel part (robust SD of the "
              "difference minus its 9x9 mean: noise) and a smooth part (median |9x9 mean|: bias), px")
        print(f"{'set':<9}{'axis':<8}{'|difference| median':>21}{'noise SD':>10}{'smooth |bias|':>15}")
        for name, axis, median, noise, bias in spreads:
            print(f"{name:<9}{axis:<8}{median:>21.3f}{noise:>10.3f}{bias:>15.3f}")


if __name__ == "__main__":
    main()
