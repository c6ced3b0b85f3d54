"""Phase correlation: the translation between two images, batched, to a fraction of a pixel.

The initial translation of registration (docs/method.md, section 7) and of self-calibration.
"""

from __future__ import annotations

import torch

__all__ = ["phase_correlation"]


def phase_correlation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Translation t = (tx, ty) with a(p) ~ b(p + t), per pair: (B, h, w), (B, h, w) -> (B, 2).

    Both images minus their means, times a 2-D Hann window; the normalised cross-power spectrum
    (regularised by 1e-6 of its largest magnitude) peaks at +t, cyclically. Sub-pixel: per axis,
    a parabola through the peak and its two cyclic neighbours, where it is concave, its vertex
    clamped to +-0.5 px. Shifts beyond half the size wrap to negative. a's dtype and device.

    Example:
        >>> x = torch.rand(1, 32, 48)
        >>> phase_correlation(x, torch.roll(x, (2, -5), dims=(1, 2))).round().tolist()
        [[-5.0, 2.0]]
    """
    n, h, w = a.shape
    win = torch.outer(*(torch.hann_window(k, periodic=False, device=a.device) for k in (h, w)))
    a, b = ((x - x.mean(dim=(1, 2), keepdim=True)) * win for x in (a, b))
    x = torch.fft.rfft2(b) * torch.fft.rfft2(a).conj()
    mag = x.abs()
    r = torch.fft.irfft2(x / (mag + 1e-6 * mag.amax(dim=(1, 2), keepdim=True) + 1e-30), s=(h, w))  # peak at +t
    i = r.flatten(1).argmax(dim=1)
    iy, ix, ar = i // w, i % w, torch.arange(n, device=a.device)
    r0, shift = r[ar, iy, ix], []
    for c, m, lo, hi in ((ix, w, r[ar, iy, (ix - 1) % w], r[ar, iy, (ix + 1) % w]),
                         (iy, h, r[ar, (iy - 1) % h, ix], r[ar, (iy + 1) % h, ix])):
        den = lo - 2 * r0 + hi  # parabola through the peak and its cyclic neighbours
        d = torch.where(den < 0, 0.5 * (lo - hi) / torch.where(den < 0, den, -1.0), 0.0)
        c = c.to(r.dtype) + d.clamp(-0.5, 0.5)
        shift.append(torch.where(c > m / 2, c - m, c))
    return torch.stack(shift, dim=1)
