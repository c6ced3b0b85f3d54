"""``[quality]``: the registration-quality metric's thresholds, temperature and block size.

docs/method.md, sections 2-5.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from lensdist_torch.config.checks import integer, positive, real

__all__ = ["GAMMA", "K", "QualityConfig", "SIGMA", "TAU_B", "TAU_D", "TAU_E", "TAU_G", "TEMPERATURES"]

#: Xydeas and Petrovic's constants of the edge-preservation sigmoid E = GAMMA / (1 + exp(K (A - SIGMA)))
#: (docs/method.md, section 3): the paper's, fixed, not settings.
GAMMA = 0.9879
K = -22.0
SIGMA = 0.8
#: The smooth path's temperatures at ``temperature`` 1 (docs/method.md, section 5): the gradient-magnitude,
#: edge-preservation, intensity-difference and block-floor steps; ``QualityConfig.temperature`` scales all four.
TAU_G = 0.004
TAU_E = 0.05
TAU_D = 0.02
TAU_B = 0.02
#: The names ``QualityConfig`` reads the four temperatures by.
TEMPERATURES = ("tau_g", "tau_e", "tau_d", "tau_b")


def _scaled(base: float, name: str) -> property:
    return property(lambda self: base * self.temperature, doc=f":data:`{name}` times ``temperature``.")


@dataclass(frozen=True)
class QualityConfig:
    """Settings of the registration-quality metric (docs/method.md sections 2-5).

    Attributes:
        block_size: side of the square pooling blocks in pixels.
        theta_g: gradient-magnitude threshold of the risk map (normalised Sobel on [0, 1]).
        theta_e: edge-preservation threshold (in ]0, :data:`GAMMA`[) below which a structured pixel errs.
        theta_d: intensity-difference threshold of the visual error.
        min_block_ratio: block error ratios below this are set to 0; in [0, 1].
        temperature: the factor on the smooth path's four temperatures (:data:`TAU_G`, :data:`TAU_E`,
            :data:`TAU_D`, :data:`TAU_B`; read them as ``tau_g`` ... ``tau_b``): smaller is sharper,
            nearer the hard metric; positive.
        chunk_size: pairs processed at once inside a big batch, so that the intermediates of a
            chunk stay in the CPU cache. The result does not depend on it.

    ``gamma``, ``k`` and ``sigma`` read the Xydeas-Petrovic constants (:data:`GAMMA`, :data:`K`,
    :data:`SIGMA`).

    Example:
        >>> from dataclasses import replace
        >>> QualityConfig().theta_e, replace(QualityConfig(), theta_e=0.6).theta_e
        (0.5, 0.6)
        >>> QualityConfig(temperature=0.5).tau_e, QualityConfig().gamma
        (0.025, 0.9879)
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
    temperature: float = 1.0
    chunk_size: int = 2

    def __post_init__(self) -> None:
        integer(self, "block_size")
        integer(self, "chunk_size")
        for name in ("theta_g", "theta_d", "temperature"):
            real(self, name, lo=0, lo_open=True)
        real(self, "theta_e", lo=0, hi=GAMMA, lo_open=True, hi_open=True, hi_name=f"gamma={GAMMA}")
        real(self, "min_block_ratio", lo=0, hi=1)

    gamma = property(lambda self: GAMMA, doc=":data:`GAMMA`.")
    k = property(lambda self: K, doc=":data:`K`.")
    sigma = property(lambda self: SIGMA, doc=":data:`SIGMA`.")
    tau_g = _scaled(TAU_G, "TAU_G")
    tau_e = _scaled(TAU_E, "TAU_E")
    tau_d = _scaled(TAU_D, "TAU_D")
    tau_b = _scaled(TAU_B, "TAU_B")

    def with_temperature_scale(self, factor: float) -> "QualityConfig":
        """A copy with every temperature multiplied by ``factor`` (for annealing)."""
        positive("factor", factor)
        return dataclasses.replace(self, temperature=self.temperature * factor)
