"""``[image]``, ``[distortion]``, ``[protocol]``: the analysis size, the coefficient ranges and the pair protocol.

docs/method.md, sections 1, 6, 7.
"""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import flag, integer, names, pair, real

__all__ = ["ImageConfig", "DistortionConfig", "ProtocolConfig"]


@dataclass(frozen=True)
class ImageConfig:
    """Analysis size (docs/method.md section 1): 320 x 424 gives 40 x 53 blocks, feature vectors of 2120.

    Example:
        >>> from dataclasses import replace
        >>> ImageConfig().size, replace(ImageConfig(), width=512).size
        ((320, 424), (320, 512))
    """

    height: int = 320
    width: int = 424

    def __post_init__(self) -> None:
        integer(self, "height")
        integer(self, "width")

    @property
    def size(self) -> tuple[int, int]:
        """(height, width)."""
        return self.height, self.width


@dataclass(frozen=True)
class DistortionConfig:
    """Ranges of the radial coefficients (docs/method.md section 6).

    k2 lies in ]0, k2_max], k4 in ]0, k4_max]. ``n_classes`` is 4: the labels are the classes
    1-4 and R.

    Example:
        >>> from dataclasses import replace
        >>> DistortionConfig().k2_max, replace(DistortionConfig(), k2_max=1e-6).k2_max
        (2.5e-06, 1e-06)
    """

    k2_max: float = 2.5e-6
    k4_max: float = 2.5e-11
    n_classes: int = 4

    def __post_init__(self) -> None:
        real(self, "k2_max", lo=0, lo_open=True)
        real(self, "k4_max", lo=0, lo_open=True)
        integer(self, "n_classes")
        if self.n_classes != 4:
            raise ValueError(
                f"distortion.n_classes must be 4 (the labels are the classes 1-4 and R), got {self.n_classes}"
            )


@dataclass(frozen=True)
class ProtocolConfig:
    """The pair protocol (docs/method.md section 7): motion ranges, set sizes, seed (``[protocol]``).

    The choices a user makes when generating data; the protocol's constants (the perspective
    terms' half-width, the class-R perturbation's, an occluding patch's area) are named in the
    modules that use them (:mod:`~lensdist_torch.data.synthesis`, ``realism``).

    ``seed`` is any int; ``scenes`` distinct embedded scene names; the ranges (low, high); the
    rotation half-width >= 0.
    ``unseen_scenes``: embedded scenes none of ``scenes``, on which ``lensdist reproduce`` also
    tests every method (a scene unlike the training ones; empty: no such test; not in the data
    fingerprint: the training and test pairs do not depend on it).

    ``realistic`` (off by default) adds the effects of a photograph (docs/method.md section 7,
    the realistic protocol), each drawn per view or per pair: ``gain_range`` (> 0),
    ``offset_range`` (in [-1, 1]), ``gamma_range`` (> 0, log-uniform), ``illumination`` (the
    largest share, in [0, 1[, that a ramp / vignetting darkens), ``noise_range`` (Gaussian
    sigma, in [0, 1]), ``jpeg_quality`` (ints in [1, 100]), ``relief`` (in [0, 0.5[: the
    largest height of the scene over its plane as a fraction of camera 1's height; each pair
    draws its own uniformly in [0, relief], and its parallax follows from its motion) and
    ``occluder_rate`` (share of pairs with a moving or occluding patch, in [0, 1]).

    Example:
        >>> from dataclasses import replace
        >>> ProtocolConfig().n_train, replace(ProtocolConfig(), n_train=100).n_train
        (12000, 100)
        >>> ProtocolConfig(ty_range=(40, 0))
        Traceback (most recent call last):
        ...
        ValueError: protocol.ty_range must be (low, high): two finite numbers with low <= high, got (40, 0) (tuple)
    """

    seed: int = 0
    scenes: tuple[str, ...] = ("gravel", "grass")
    unseen_scenes: tuple[str, ...] = ("brick",)
    n_train: int = 12000
    n_test_distorted: int = 400
    n_test_undistorted: int = 100
    ty_range: tuple[float, float] = (0.0, 40.0)
    tx_range: tuple[float, float] = (-4.0, 4.0)
    rotation_deg: float = 1.0
    scale_range: tuple[float, float] = (0.98, 1.02)
    shard_size: int = 500
    realistic: bool = False
    gain_range: tuple[float, float] = (0.7, 1.3)
    offset_range: tuple[float, float] = (-0.1, 0.1)
    gamma_range: tuple[float, float] = (0.8, 1.25)
    illumination: float = 0.25
    noise_range: tuple[float, float] = (0.0, 0.02)
    jpeg_quality: tuple[int, int] = (60, 95)
    relief: float = 0.0
    occluder_rate: float = 0.2

    def __post_init__(self) -> None:
        integer(self, "seed", lo=None)
        names(self, "scenes")
        names(self, "unseen_scenes", empty=True)
        if set(self.unseen_scenes) & set(self.scenes):
            raise ValueError(f"protocol.unseen_scenes must share no scene with protocol.scenes, both hold "
                             f"{sorted(set(self.unseen_scenes) & set(self.scenes))}")
        for name in ("n_train", "n_test_distorted", "n_test_undistorted"):
            integer(self, name, lo=0)
        pair(self, "ty_range")
        pair(self, "tx_range")
        pair(self, "scale_range", positive=True)
        real(self, "rotation_deg", lo=0)
        integer(self, "shard_size")
        flag(self, "realistic")
        pair(self, "gain_range", positive=True)
        pair(self, "offset_range", within=(-1, 1))
        pair(self, "gamma_range", positive=True)
        real(self, "illumination", lo=0, hi=1, hi_open=True)
        pair(self, "noise_range", within=(0, 1))
        pair(self, "jpeg_quality", within=(1, 100), integral=True)
        real(self, "relief", lo=0, hi=0.5, hi_open=True, why="a fraction of the camera's height")
        real(self, "occluder_rate", lo=0, hi=1)
