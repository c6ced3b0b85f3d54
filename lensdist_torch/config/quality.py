"""``[quality]``: the registration-quality metric's thresholds, temperatures and block size.

docs/method.md, sections 2-5.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from lensdist_torch.config.checks import integer, positive, real

__all__ = ["QualityConfig"]


@dataclass(frozen=True)
class QualityConfig:
    """Settings of the registration-quality metric (docs/method.md sections 2-5).

    Attributes:
        block_size: side of the square pooling blocks in pixels.
        theta_g: gradient-magnitude threshold of the risk map (normalised Sobel on [0, 1]).
        theta_e: edge-preservation threshold (in ]0, gamma[) below which a structured pixel errs.
        theta_d: intensity-difference threshold of the visual error.
        min_block_ratio: block error ratios below this are set to 0; in [0, 1].
        gamma, k, sigma: Xydeas-Petrovic constants of the edge-preservation sigmoid
            E = gamma / (1 + exp(k (A - sigma))): gamma in ]0, 1], k < 0, sigma in ]0, 1[.
        tau_g, tau_e, tau_d, tau_b: temperatures of the smooth path (gradient-magnitude,
            edge-preservation, intensity-difference and block-floor steps). Smaller is sharper.
        chunk_size: pairs processed at once inside a big batch, so that the intermediates of a
            chunk stay in the CPU cache. The result does not depend on it.

    Example:
        >>> from dataclasses import replace
        >>> QualityConfig().theta_e, replace(QualityConfig(), theta_e=0.6).theta_e
        (0.5, 0.6)
        >>> QualityConfig(theta_e=0.99)
        Traceback (most recent call last):
        ...
        ValueError: quality.theta_e must be a number in ]0, gamma=0.9879[, got 0.99
    """

    block_size: int = 8
    theta_g: float = 0.02
    theta_e: float = 0.5
    theta_d: float = 0.1
    min_block_ratio: float = 0.1
    gamma: float = 0.9879
    k: float = -22.0
    sigma: float = 0.8
    tau_g: float = 0.004
    tau_e: float = 0.05
    tau_d: float = 0.02
    tau_b: float = 0.02
    chunk_size: int = 2

    def __post_init__(self) -> None:
        integer(self, "block_size")
        integer(self, "chunk_size")
        for name in ("theta_g", "theta_d", "tau_g", "tau_e", "tau_d", "tau_b"):
            real(self, name, lo=0, lo_open=True)
        real(self, "gamma", lo=0, hi=1, lo_open=True)
        real(self, "theta_e", lo=0, hi=self.gamma, lo_open=True, hi_open=True, hi_name=f"gamma={self.gamma}")
        real(self, "min_block_ratio", lo=0, hi=1)
        real(self, "k", hi=0, hi_open=True, why="E grows with A")
        real(self, "sigma", lo=0, hi=1, lo_open=True, hi_open=True)

    def with_temperature_scale(self, factor: float) -> "QualityConfig":
        """A copy with every temperature multiplied by ``factor`` (for annealing)."""
        positive("factor", factor)
        t = {name: getattr(self, name) * factor for name in ("tau_g", "tau_e", "tau_d", "tau_b")}
        return dataclasses.replace(self, **t)
