"""The paper's metric as the verifier of a calibration: registration errors before and after undistortion.

A camera's distortion, estimated from a sequence, is checked against the one thing it must do:
frames of a planar (or distant) scene corrected with it are related by a homography, so their
registration leaves fewer error blocks (docs/method.md, section 3: intensity and orientation
criteria, the 8 x 8 block map). :func:`verify_undistortion` registers a few of the sequence's
pairs as they are and again after :func:`~lensdist_torch.geometry.undistort.undistort_image`
with the estimate, and counts the error blocks among the blocks that are valid in both views
(the undistorted frames lose their outer pixels: only fully valid blocks count, each time as a
share of the blocks counted). The undistorted frames are registered inside the largest centred
rectangle of the frame's shape where every corrected pixel is valid (:func:`valid_box`): a
pincushion correction leaves the corners empty, and empty corners that stay in place in both
views would hold the registration at the identity. ``lensdist calibrate`` withholds the class of an estimate whose
correction does not lower that share (``calibration.verify_margin``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from lensdist_torch.calibration.controllers.answer_lens import eq4_lens, lens_grid
from lensdist_torch.config import LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.geometry.distortion import sample_at_pixels
from lensdist_torch.metric.quality import counts_to_map, registration_error_counts
from lensdist_torch.registration.direct import warp_to_reference
from lensdist_torch.registration.wide_baseline import estimate_homography_robust

__all__ = ["COUNTS", "VERDICTS", "error_blocks", "valid_box", "verdict", "verify_undistortion"]

#: The counts of :func:`verify_undistortion`'s dict.
COUNTS = ("pairs", "registered_before", "registered_after", "error_blocks_before", "error_blocks_after",
          "blocks_before", "blocks_after")
#: What a verification says of an estimate: its correction lowered the registration errors, did
#: not (the class is withheld), or nothing could be compared (the class stands, unverified).
VERDICTS = ("lowered", "not lowered", "not measurable")
#: The undistorted frames are registered inside :func:`valid_box` where both its sides are this long (px).
MIN_BOX = 32


def verdict(check: dict, count_gained: bool = True) -> str:
    """The verdict of :func:`verify_undistortion`'s dict (one of ``VERDICTS``).

    A pair that does not register is all error, so a correction that registers more pairs than
    before lowered the errors ("lowered"), whatever the shares of the pairs that registered both
    times. Otherwise, pairs registered both times: the shares decide ("lowered" where the share
    falls); else "not lowered" where the correction broke registrations, "not measurable" where
    there was nothing to compare (far-apart views no homography relates).

    ``count_gained`` False: the rule of older calibration files, which did not count the
    pairs a correction registers in addition (a calibration file with that verdict still loads).

    Example:
        >>> counts = {"registered_before": 1, "registered_after": 3,
        ...           "error_share_before": 0.050, "error_share_after": 0.056}
        >>> verdict(counts)  # two more pairs register after the correction: the paper's metric says it helped
        'lowered'
        >>> verdict(counts, count_gained=False), verdict({**counts, "registered_after": 1})  # the shares decide
        ('not lowered', 'not lowered')
    """
    if count_gained and check["registered_after"] > check["registered_before"]:
        return VERDICTS[0]
    before, after = check["error_share_before"], check["error_share_after"]
    if before is not None and after is not None:
        return VERDICTS[0] if after < before else VERDICTS[1]
    return VERDICTS[1] if check["registered_before"] > check["registered_after"] else VERDICTS[2]


def error_blocks(img1: torch.Tensor, img2: torch.Tensor, mask1: torch.Tensor, mask2: torch.Tensor,
                 *,
                 settings: LensdistConfig) -> tuple[int, int, bool]:
    """(error blocks, blocks counted, registered) of one pair registered by a homography.

    img1, img2: (1, 1, H, W) in [0, 1]; mask1, mask2: (1, 1, H, W) of 0 / 1, where each view
    holds image content. A block counts where every pixel of img1 is valid and maps to a valid
    pixel of img2; it is an error block where the quality map (the paper's metric) marks it.
    """
    H, info = estimate_homography_robust(img1, img2, config=settings.registration)
    ok = bool(info.converged[0]) and bool(torch.isfinite(H).all())
    if not ok:
        return 0, 0, False
    warped, inside = warp_to_reference(img2, H)
    content, _ = warp_to_reference(mask2.to(img2.dtype), H)
    valid = (inside > 0) & (content > 0.999) & (mask1 > 0)
    qmap = counts_to_map(registration_error_counts(img1, warped, valid, config=settings.quality), settings.quality)
    b = settings.quality.block_size
    v = valid.float()
    v = F.pad(v, (0, qmap.shape[-1] * b - v.shape[-1], 0, qmap.shape[-2] * b - v.shape[-2]))  # the map's padded blocks
    full = -F.max_pool2d(-v, b) > 0.5  # every pixel of the block valid
    return int(((qmap > 0) & full).sum()), int(full.sum()), True


def valid_box(valid: torch.Tensor) -> tuple[int, int, int, int]:
    """(top, left, bottom, right): the largest centred rectangle of the frame's shape inside ``valid`` (1, 1, H, W).

    Shrunk in steps of 1 % of the frame's sides until every pixel in it is valid; the whole
    frame where it is valid, an empty box where not even the centre pixel is.

    Example:
        >>> valid = torch.ones(1, 1, 40, 60, dtype=torch.bool)
        >>> valid[..., :4, :6] = False  # an empty corner
        >>> valid_box(valid), valid_box(torch.ones(1, 1, 40, 60))
        ((4, 5, 36, 54), (0, 0, 40, 60))
    """
    h, w = valid.shape[-2:]
    v = valid.reshape(h, w) > 0
    for pct in range(100, 0, -1):
        bh, bw = max(1, round(h * pct / 100)), max(1, round(w * pct / 100))
        top, left = (h - bh) // 2, (w - bw) // 2
        if bool(v[top : top + bh, left : left + bw].all()):
            return top, left, top + bh, left + bw
    return h // 2, w // 2, h // 2, w // 2


def verify_undistortion(frames: torch.Tensor, pairs: torch.Tensor, k2: float, k4: float,
                        *,
                        settings: LensdistConfig | None = None, max_pairs: int = 6, lens: dict | None = None) -> dict:
    """Registration-error blocks of up to ``max_pairs`` pairs before and after undistorting with (k2, k4), or ``lens``.

    Args:
        frames: (N, 1, H, W) grey frames at the analysis size, in [0, 1].
        pairs: (P, 2) frame indices (e.g. the pairs a sequence calibration used); evenly spread
            ones are taken.
        k2: eq. 4's k2 at the frames' size (analysis px), about the frame centre.
        k4: eq. 4's k4, likewise.
        settings: registration and quality settings (the defaults when None).
        max_pairs: how many pairs to check.
        lens: the answer's own lens at the frames' size
            (:func:`~lensdist_torch.calibration.controllers.answer_lens.answer_lens`, scaled), applied instead
            of (k2, k4), which then only approximate it; None: eq. 4.

    Returns:
        {"pairs": checked, "registered_before", "registered_after", "error_share_before",
        "error_share_after" (error blocks / blocks counted over the pairs registered both
        times; None without one), "error_blocks_before", "error_blocks_after", "blocks_before",
        "blocks_after"}.

    Example:
        >>> from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
        >>> frames, _ = synthetic_sequence(6, 2e-6, 0.0, size=(160, 212), step_px=(20, 24))
        >>> out = verify_undistortion(frames, torch.tensor([[0, 3], [1, 4], [2, 5]]), 2e-6, 0.0)
        >>> out["error_share_after"] < out["error_share_before"]
        True
    """
    st = or_defaults(settings, LensdistConfig, "settings")
    pairs = torch.as_tensor(pairs).reshape(-1, 2)
    if len(pairs) > max_pairs:
        pairs = pairs[torch.linspace(0, len(pairs) - 1, max_pairs).round().long()]
    ones = torch.ones_like(frames[:1])
    used = sorted(set(pairs.flatten().tolist()))  # only the frames checked are corrected
    row = {f: r for r, f in enumerate(used)}
    grid, valid = lens_grid(lens or eq4_lens(k2, k4), *frames.shape[-2:], dtype=frames.dtype, device=frames.device)
    masks = valid.expand(len(used), -1, -1, -1)
    fixed = sample_at_pixels(frames[used], grid.expand(len(used), -1, -1, -1)) * masks
    top, left, bottom, right = valid_box(valid)
    if min(bottom - top, right - left) >= MIN_BOX:  # registered inside the valid box (module docstring)
        fixed, masks = fixed[..., top:bottom, left:right], masks[..., top:bottom, left:right]
    totals = dict.fromkeys(("error_blocks_before", "blocks_before", "error_blocks_after", "blocks_after",
                            "registered_before", "registered_after"), 0)
    for i, j in pairs.tolist():
        e0, n0, ok0 = error_blocks(frames[i : i + 1], frames[j : j + 1], ones, ones, settings=st)
        fi, fj = row[i], row[j]
        e1, n1, ok1 = error_blocks(
            fixed[fi : fi + 1], fixed[fj : fj + 1], masks[fi : fi + 1], masks[fj : fj + 1], settings=st
        )
        totals["registered_before"] += ok0
        totals["registered_after"] += ok1
        if ok0 and ok1:
            totals["error_blocks_before"] += e0
            totals["blocks_before"] += n0
            totals["error_blocks_after"] += e1
            totals["blocks_after"] += n1
    share = {w: (totals[f"error_blocks_{w}"] / totals[f"blocks_{w}"] if totals[f"blocks_{w}"] else None)
             for w in ("before", "after")}
    return {"pairs": len(pairs), **totals, "error_share_before": share["before"], "error_share_after": share["after"]}
