"""``[image]``, ``[distortion]``, ``[protocol]``: the analysis size, the coefficient ranges and the pair protocol.

docs/method.md, sections 1, 6, 7.
"""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import flag, integer, names, real

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

    k2 lies in ]0, k2_max], k4 in ]0, k4_max]; the classes 1-4 are equal-width bins of the Delta
    they give (their number, 4, is ``geometry.distortion.N_CLASSES``).

    Example:
        >>> from dataclasses import replace
        >>> DistortionConfig().k2_max, replace(DistortionConfig(), k2_max=1e-6).k2_max
        (2.5e-06, 1e-06)
    """

    k2_max: float = 2.5e-6
    k4_max: float = 2.5e-11

    def __post_init__(self) -> None:
        real(self, "k2_max", lo=0, lo_open=True)
        real(self, "k4_max", lo=0, lo_open=True)


@dataclass(frozen=True)
class ProtocolConfig:
    """The pair protocol (docs/method.md section 7): seed, scenes, set sizes, switches (``[protocol]``).

    The choices a user makes when generating data; the protocol's constants (the motion ranges,
    the perspective terms' half-width, the class-R perturbation's, the realistic protocol's
    ranges, an occluding patch's rate and area) are named in the modules that use them
    (:mod:`~lensdist_torch.data.synthesis`, ``realism``).

    ``seed`` is any int; ``scenes`` distinct embedded scene names; ``shard_size`` pairs per
    shard file. ``unseen_scenes``: embedded scenes none of ``scenes``, on which ``lensdist
    reproduce`` also tests every method (a scene unlike the training ones; empty: no such test;
    not in the data fingerprint: the training and test pairs do not depend on it).

    ``realistic`` (off by default) adds the effects of a photograph (docs/method.md section 7,
    the realistic protocol), each drawn per view or per pair; ``relief`` (in [0, 0.5[: the
    largest height of the scene over its plane as a fraction of camera 1's height; each pair
    draws its own uniformly in [0, relief], and its parallax follows from its motion).

    Example:
        >>> from dataclasses import replace
        >>> ProtocolConfig().n_train, replace(ProtocolConfig(), n_train=100).n_train
        (12000, 100)
        >>> ProtocolConfig(relief=0.5)
        Traceback (most recent call last):
        ...
        ValueError: protocol.relief must be a number in [0, 0.5[ (a fraction of the camera's height), got 0.5
    """

    seed: int = 0
    scenes: tuple[str, ...] = ("gravel", "grass")
    unseen_scenes: tuple[str, ...] = ("brick",)
    n_train: int = 12000
    n_test_distorted: int = 400
    n_test_undistorted: int = 100
    shard_size: int = 500
    realistic: bool = False
    relief: float = 0.0

    def __post_init__(self) -> None:
        integer(self, "seed", lo=None)
        names(self, "scenes")
        names(self, "unseen_scenes", empty=True)
        if set(self.unseen_scenes) & set(self.scenes):
            raise ValueError(f"protocol.unseen_scenes must share no scene with protocol.scenes, both hold "
                             f"{sorted(set(self.unseen_scenes) & set(self.scenes))}")
        for name in ("n_train", "n_test_distorted", "n_test_undistorted"):
            integer(self, name, lo=0)
        integer(self, "shard_size")
        flag(self, "realistic")
        real(self, "relief", lo=0, hi=0.5, hi_open=True, why="a fraction of the camera's height")
