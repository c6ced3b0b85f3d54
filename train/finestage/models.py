"""The refinement network: two grey patches, 0.5-3 px apart, in; the residual offsets out.

The coarse network of learnreg correlates 1/8-resolution features, where a 1-3 px residual is a
fraction of a feature pixel. The fine network correlates at 1/4 resolution over +-``radius``
feature pixels (+-8 px at the default radius 2) and regresses the eight offsets from the cost
volume. Its building blocks (standardisation, zero-initialised head, bounded output) are
learnreg's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from learnreg.models import _bounded, _offset_head, _standardise
from torch import nn

__all__ = ["FineNet", "build_model"]


def _block(cin: int, cout: int, stride: int, norm: bool) -> list[nn.Module]:
    return (
        [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=not norm)]
        + ([nn.BatchNorm2d(cout)] if norm else [])
        + [nn.ReLU(inplace=True)]
    )


class FineNet(nn.Module):
    """(B, 1, P, P) x 2 -> (B, 4, 2) corner offsets in px, bounded to +-1.5 ``rho``.

    A siamese encoder to unit feature vectors at 1/4 resolution, their local correlation over
    (2 radius + 1)^2 displacements, three stride-2 blocks (1/32) and learnreg's offset head,
    which starts at zero: the untrained network predicts no correction.
    """

    def __init__(
        self, patch: int = 128, rho: float = 3.0, width: int = 16, hidden: int = 256, radius: int = 2, norm: bool = True
    ) -> None:
        super().__init__()
        w = width
        self.encoder = nn.Sequential(
            *_block(1, w, 2, norm),
            *_block(w, 2 * w, 1, norm),
            *_block(2 * w, 2 * w, 2, norm),
            nn.Conv2d(2 * w, 2 * w, 3, padding=1),
        )
        self.radius = int(radius)
        k = 2 * self.radius + 1
        self.regressor = nn.Sequential(
            *_block(k * k, 4 * w, 2, norm), *_block(4 * w, 4 * w, 2, norm), *_block(4 * w, 8 * w, 2, norm)
        )
        self.head = _offset_head(8 * w * (patch // 32) ** 2, hidden)
        self.rho = float(rho)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        f = F.normalize(self.encoder(_standardise(torch.cat([a, b], dim=0))), dim=1)
        fa, fb = f[: a.shape[0]], f[a.shape[0] :]
        n, c, h, w = fa.shape
        k = 2 * self.radius + 1
        windows = F.unfold(fb, k, padding=self.radius).view(n, c, k * k, h * w)
        cost = (fa.view(n, c, 1, h * w) * windows).sum(1).view(n, k * k, h, w)
        return _bounded(self.head(self.regressor(cost)), self.rho)


def build_model(cfg: dict) -> FineNet:
    """The fine network sized by ``data.patch``, bounded by ``data.r_max``."""
    d, m = cfg["data"], cfg["model"]
    return FineNet(
        int(d["patch"]), float(d["r_max"]), int(m["width"]), int(m["hidden"]), int(m["radius"]), bool(m["batch_norm"])
    )
