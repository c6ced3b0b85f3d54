"""The refinement network: two grey patches, 0.5-3 px apart, in; the residual offsets out.

The coarse network of learnreg correlates 1/8-resolution features, where a 1-3 px residual is a
fraction of a feature pixel. The fine network correlates at 1/4 resolution over +-``radius``
feature pixels (+-8 px at the default radius 2) and regresses the eight offsets from the cost
volume. Its building blocks (standardisation, zero-initialised head, bounded output) are
learnreg's.
"""

from __future__ import annotations

from learnreg.models import CorrelationHomographyNet, conv_block, offset_head
from torch import nn

__all__ = ["FineNet", "build_model"]


class FineNet(CorrelationHomographyNet):
    """(B, 1, P, P) x 2 -> (B, 4, 2) corner offsets in px, bounded to +-1.5 ``rho``.

    A siamese encoder to unit feature vectors at 1/4 resolution, their local correlation over
    (2 radius + 1)^2 displacements, three stride-2 blocks (1/32) and learnreg's offset head,
    which starts at zero: the untrained network predicts no correction. The forward pass is
    learnreg's correlation network's; only the layers differ.
    """

    def __init__(
        self, patch: int = 128, rho: float = 3.0, width: int = 16, hidden: int = 256, radius: int = 2, norm: bool = True
    ) -> None:
        nn.Module.__init__(self)  # other layers than the parent's, the same forward
        w = width
        self.encoder = nn.Sequential(
            *conv_block(1, w, 2, norm),
            *conv_block(w, 2 * w, 1, norm),
            *conv_block(2 * w, 2 * w, 2, norm),
            nn.Conv2d(2 * w, 2 * w, 3, padding=1),
        )
        self.radius = int(radius)
        k = 2 * self.radius + 1
        self.regressor = nn.Sequential(
            *conv_block(k * k, 4 * w, 2, norm), *conv_block(4 * w, 4 * w, 2, norm), *conv_block(4 * w, 8 * w, 2, norm)
        )
        self.head = offset_head(8 * w * (patch // 32) ** 2, hidden)
        self.rho = float(rho)


def build_model(cfg: dict) -> FineNet:
    """The fine network sized by ``data.patch``, bounded by ``data.r_max``."""
    d, m = cfg["data"], cfg["model"]
    return FineNet(
        int(d["patch"]), float(d["r_max"]), int(m["width"]), int(m["hidden"]), int(m["radius"]), bool(m["batch_norm"])
    )
