"""``lensdist demo``: the quality map of a known misregistration of the embedded scene."""

from __future__ import annotations

import torch
from kornia.geometry.transform import warp_perspective

from lensdist_torch.config import LensdistConfig
from lensdist_torch.core.images import load_scene
from lensdist_torch.geometry.distortion import distortion_center
from lensdist_torch.metric.quality import registration_quality

__all__ = ["MAX_SCALE_ERROR", "scale_error_demo"]

#: The largest relative scale error the demo shows. Its point is that errors grow from the
#: centre outwards: that holds while the offset at the edge of the centre third (s R / 3, R the
#: half diagonal, 88 px at 424 x 320) stays below about one 8 px block of the map, s <~ 0.09.
#: The quality index is lowest near 0.1 (0.372) and rises again as the error grows (0.395 at
#: 0.5, 0.967 at 1e6, where the second view is a flat patch): beyond 0.1 a larger error would read
#: as a better registration. A negative error (a shrink) leaves the outer third without valid
#: pixels (its mean error ratio 0), and an offset "up to" a negative number means nothing.
MAX_SCALE_ERROR = 0.1


def scale_error_demo(config: LensdistConfig, scene: str = "gravel", scale_error: float = 0.01) -> tuple[dict, tuple]:
    """Two views of ``scene``, the second scaled by ``1 + scale_error`` about the image centre.

    A relative scale error s moves a pixel at radius r by s r px, so the registration errors
    should grow from the centre outwards.

    Args:
        config: image size and quality thresholds.
        scene: an embedded scene.
        scale_error: the relative scale error of the second view, in [0, MAX_SCALE_ERROR].

    Raises:
        ValueError: ``scale_error`` outside [0, MAX_SCALE_ERROR] or not a number.

    Returns:
        A summary dict (offsets, blocks with errors, mean error ratio in the centre and outer
        thirds, quality index) and the tensors (img1, img2, quality map, pixel validity).
    """
    if (
        isinstance(scale_error, bool)
        or not isinstance(scale_error, (int, float))
        or not 0 <= scale_error <= MAX_SCALE_ERROR
    ):
        raise ValueError(
            f"scale_error must be a number from 0 to {MAX_SCALE_ERROR} (the range the demo shows), got {scale_error!r}"
        )
    h, w = config.image.height, config.image.width
    full = load_scene(scene)
    y0, x0 = (full.shape[-2] - h) // 2, (full.shape[-1] - w) // 2
    img1 = full[..., y0 : y0 + h, x0 : x0 + w].contiguous()
    cx, cy = distortion_center(h, w)
    s = 1.0 + scale_error
    err = torch.tensor([[[s, 0.0, (1 - s) * cx], [0.0, s, (1 - s) * cy], [0.0, 0.0, 1.0]]])
    img2 = warp_perspective(img1, err, (h, w), align_corners=True)
    valid = warp_perspective(torch.ones_like(img1), err, (h, w), align_corners=True) > 0.999
    res = registration_quality(img1, img2, valid.float(), config=config.quality)
    qmap = res.registration_map
    hb, wb = qmap.shape[-2:]
    yy, xx = torch.meshgrid(torch.arange(hb), torch.arange(wb), indexing="ij")
    r = torch.sqrt((yy - (hb - 1) / 2) ** 2 + (xx - (wb - 1) / 2) ** 2)
    inner, outer = qmap[0, 0][r < r.max() / 3], qmap[0, 0][r > 2 * r.max() / 3]
    summary = {
        "scene": scene,
        "size": [h, w],
        "scale_error": scale_error,
        "max_offset_px": scale_error * float(torch.hypot(torch.tensor(cx), torch.tensor(cy))),
        "blocks": hb * wb,
        "blocks_with_errors": int((qmap > 0).sum()),
        "mean_error_ratio": float(qmap.mean()),
        "quality_index": float(res.quality_index[0]),
        "mean_error_ratio_centre_third": float(inner.mean()),
        "mean_error_ratio_outer_third": float(outer.mean()),
        "visual_error_blocks": int((res.visual_map > 0).sum()),
    }
    return summary, (img1, img2, qmap, valid)
