"""The networks: two grey patches in, four corner offsets (B, 4, 2) in px out.

``correlation`` (the default): a siamese encoder and a 1/8-resolution cost volume.
``stacked``: the plain HomographyNet on the two stacked patches, which learned too slowly for a
CPU budget (``train/README.md``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["HomographyNet", "CorrelationHomographyNet", "MODELS", "build_model"]


def offset_head(in_features: int, hidden: int) -> nn.Sequential:
    """Flatten -> hidden -> 8 corner offsets; the last layer starts at zero (identity)."""
    head = nn.Sequential(nn.Flatten(), nn.Linear(in_features, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 8))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


def _standardise(x: torch.Tensor) -> torch.Tensor:
    """Each (patch, channel) to zero mean and unit variance (variance floored)."""
    mu = x.mean(dim=(2, 3), keepdim=True)
    return (x - mu) / x.std(dim=(2, 3), keepdim=True).clamp_min(1e-3)


def _bounded(raw: torch.Tensor, rho: float) -> torch.Tensor:
    """(B, 8) -> (B, 4, 2) offsets squashed into +-1.5 rho: a runaway prediction cannot push A
    out of the frame (where the masked losses would be trivially small)."""
    return 1.5 * rho * torch.tanh(raw.view(-1, 4, 2) / 1.5)


def conv_block(cin: int, cout: int, stride: int, norm: bool) -> list[nn.Module]:
    """3 x 3 convolution (no bias under batch norm), [batch norm], ReLU."""
    return (
        [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=not norm)]
        + ([nn.BatchNorm2d(cout)] if norm else [])
        + [nn.ReLU(inplace=True)]
    )


class HomographyNet(nn.Module):
    """Two stacked grey patches (B, 2, P, P) -> four corner offsets (B, 4, 2) in px.

    A small VGG-like regressor in the style of HomographyNet (DeTone et al. 2016). Each patch is
    normalised to zero mean and unit variance first; the last layer starts at zero, so the
    untrained network predicts the identity. The offsets are squashed into [-1.5 rho, 1.5 rho].
    """

    def __init__(
        self, patch: int = 128, rho: float = 16.0, width: int = 16, hidden: int = 256, norm: bool = True
    ) -> None:
        super().__init__()
        w = width
        chans = [w, 2 * w, 4 * w, 4 * w, 8 * w]  # five stride-2 convolutions: P -> P / 32
        layers: list[nn.Module] = []
        for cin, cout in zip([2, *chans[:-1]], chans):
            layers += conv_block(cin, cout, 2, norm)
        self.features = nn.Sequential(*layers)
        self.head = offset_head(8 * w * (patch // 32) ** 2, hidden)
        self.rho = rho

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        x = _standardise(torch.cat([a, b], dim=1))
        return _bounded(self.head(self.features(x)), self.rho)


class CorrelationHomographyNet(nn.Module):
    """Same input and output as :class:`HomographyNet`, with a correlation front end.

    A shared (siamese) encoder maps each normalised patch to unit feature vectors at 1/8
    resolution; their local correlation over displacements of up to ``ceil(1.5 rho / 8)``
    feature pixels is a cost volume that a small CNN regresses onto the four corner offsets. Reading
    the displacement from a cost volume is far easier to learn than from stacked patches, which
    is what makes a CPU budget of a thousand steps enough.
    """

    def __init__(
        self, patch: int = 128, rho: float = 16.0, width: int = 16, hidden: int = 256, norm: bool = True
    ) -> None:
        super().__init__()
        w = width
        self.encoder = nn.Sequential(
            *conv_block(1, w, 2, norm), *conv_block(w, 2 * w, 2, norm), *conv_block(2 * w, 2 * w, 2, norm),
            nn.Conv2d(2 * w, 2 * w, 3, padding=1),
        )
        self.radius = math.ceil(1.5 * rho / 8)  # feature pixels are 8 px
        n_disp = (2 * self.radius + 1) ** 2
        self.regressor = nn.Sequential(
            *conv_block(n_disp, 4 * w, 1, norm), *conv_block(4 * w, 4 * w, 2, norm), *conv_block(4 * w, 8 * w, 2, norm)
        )
        self.head = offset_head(8 * w * (patch // 32) ** 2, hidden)
        self.rho = rho

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Encode both patches, correlate over +-``radius`` feature px, regress the offsets."""
        f = F.normalize(self.encoder(_standardise(torch.cat([a, b], dim=0))), dim=1)
        fa, fb = f[: a.shape[0]], f[a.shape[0] :]
        n, c, h, w = fa.shape
        k = 2 * self.radius + 1
        windows = F.unfold(fb, k, padding=self.radius).view(n, c, k * k, h * w)
        cost = (fa.view(n, c, 1, h * w) * windows).sum(1).view(n, k * k, h, w)
        return _bounded(self.head(self.regressor(cost)), self.rho)


MODELS = {"correlation": CorrelationHomographyNet, "stacked": HomographyNet}


def build_model(cfg: dict) -> nn.Module:
    """The network of ``model.kind``, sized by ``data.patch`` and bounded by ``data.rho``."""
    d, m = cfg["data"], cfg["model"]
    if m["kind"] not in MODELS:
        raise ValueError(f"model.kind must be one of {sorted(MODELS)}, got {m['kind']!r}")
    return MODELS[m["kind"]](int(d["patch"]), float(d["rho"]), int(m["width"]), int(m["hidden"]), bool(m["batch_norm"]))
