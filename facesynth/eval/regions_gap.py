"""What a whole-region PSNR target needs from each region: the arithmetic over
``psnr_frame_common_regions`` and ``psnr_frame_common_shares`` of ``metrics.json``.

The common region's parts (``eyes``, ``mouth_interior``, ``lips``, ``brows``, ``rest``;
runs measured before lips and brows were split off hold the first, second and last only,
and a run whose evaluated frames never open the mouth has no ``mouth_interior``)
partition it (:mod:`facesynth.eval.common_region`), so its mean squared error is the pixel-share weighted
mean of theirs. With s_r the shares and p_r the parts' PSNR (dB, peak 255)::

    whole = -10 log10( sum_r s_r 10^(-p_r / 10) )                       (:func:`combine`)

From it: the whole figure if some parts were predicted as well as another row of the table
(e.g. the ``oracle``: the frame's own texture projected on the appearance PCA) --
:func:`substitute` -- and the PSNR one part would need, the others fixed, for the whole to
reach a target (:func:`needed`; ``inf`` when the others alone already miss it).

:func:`scheme_gap` applies them to a pair of runs of one clip on two landmark schemes
(does the dense scheme beat ``ibug68`` by ``margin`` dB over the common region?).
``bench/studies/scheme_gap.py`` prints it for run folders.
"""

from __future__ import annotations

import math

from facesynth.errors import FacesynthError
from facesynth.landmarks import FACE_REGIONS

# the parts every run has; lips and brows when measured, the mouth interior when an evaluated
# frame opens the mouth (a closed mouth has none, facesynth.landmarks.face_region_masks)
PARTS = ("eyes", "rest")


def _parts(table: dict) -> list[str]:
    """The parts of :data:`FACE_REGIONS` present in ``table`` (a run's regions or shares)."""
    return [p for p in FACE_REGIONS if p in table]


def _mse(db: float) -> float:
    return 10.0 ** (-db / 10.0)


def _db(mse: float) -> float:
    return -10.0 * math.log10(mse) if mse > 0 else math.inf


def _tables(metrics: dict, where: str) -> tuple[dict, dict]:
    regions, shares = metrics.get("psnr_frame_common_regions"), metrics.get("psnr_frame_common_shares")
    if not regions or not shares:
        raise FacesynthError(f"{where}: no psnr_frame_common_regions / psnr_frame_common_shares "
                             "(train with eval.common_region=true and eval.frame_level=true)")
    missing = [p for p in PARTS if p not in regions or p not in shares]
    if missing:
        raise FacesynthError(f"{where}: psnr_frame_common_regions / psnr_frame_common_shares lack {', '.join(missing)}")
    return regions, shares


def combine(shares: dict, parts_db: dict) -> float:
    """Whole-region PSNR (dB) of parts ``parts_db`` {part: dB} with pixel ``shares`` {part: fraction}."""
    parts = _parts(shares)
    return _db(sum(shares[p] * _mse(parts_db[p]) for p in parts) / sum(shares[p] for p in parts))


def substitute(metrics: dict, rows: dict, noise: str = "0", where: str = "metrics") -> float:
    """Whole-region PSNR with the parts of ``rows`` {part: row} (e.g. ``{"eyes": "oracle"}``)
    taken from that row of the table and the others from ``sadm``, at landmark noise ``noise``."""
    regions, shares = _tables(metrics, where)
    return combine(shares, {p: regions[p][rows.get(p, "sadm")][noise] for p in _parts(shares)})


def needed(metrics: dict, part: str, target_db: float, rows: dict | None = None, noise: str = "0",
           where: str = "metrics") -> float:
    """The PSNR (dB) that ``part`` would need for the whole region to reach ``target_db``, the other
    parts as in ``rows`` (default ``sadm``); ``inf`` if they alone already exceed the error budget."""
    regions, shares = _tables(metrics, where)
    parts = _parts(shares)
    total = sum(shares[p] for p in parts)
    others = sum(shares[p] * _mse(regions[p][(rows or {}).get(p, "sadm")][noise]) for p in parts if p != part)
    budget = _mse(target_db) * total - others
    return _db(budget / shares[part]) if budget > 0 else math.inf


def scheme_gap(dense: dict, base: dict, margin: float = 1.0, noise: str = "0",
               where: tuple[str, str] = ("dense", "base")) -> dict:
    """Figures (dB) for "``dense`` beats ``base`` by ``margin`` dB over the common region", for one clip.

    ``whole_*``: measured; ``target``: base + margin; ``whole_eyes_mouth_at_oracle``: the dense
    run with its eyes and mouth interior at its oracle (what gaze and the inner lips could give at
    most on this appearance model); ``rest_needed``: the dense run's ``rest`` figure the target needs
    with its other parts as predicted, and ``rest_needed_eyes_mouth_at_oracle`` with them at the
    oracle; against ``rest_dense``, ``rest_base`` and the dense run's ``rest_oracle``.
    """
    reg_d, shares = _tables(dense, where[0])
    reg_b, _ = _tables(base, where[1])
    target = reg_b["whole"]["sadm"][noise] + margin
    at_oracle = {"eyes": "oracle", "mouth_interior": "oracle"}
    return {
        "whole_dense": reg_d["whole"]["sadm"][noise], "whole_base": reg_b["whole"]["sadm"][noise],
        "difference": reg_d["whole"]["sadm"][noise] - reg_b["whole"]["sadm"][noise], "target": target,
        "whole_eyes_mouth_at_oracle": substitute(dense, at_oracle, noise, where[0]),
        "rest_needed": needed(dense, "rest", target, None, noise, where[0]),
        "rest_needed_eyes_mouth_at_oracle": needed(dense, "rest", target, at_oracle, noise, where[0]),
        "rest_dense": reg_d["rest"]["sadm"][noise], "rest_base": reg_b["rest"]["sadm"][noise],
        "rest_oracle": reg_d["rest"]["oracle"][noise],
        "shares": {p: shares[p] for p in _parts(shares)},
    }
