"""Generated data sets shared by the tests of the data sets (tests/data) and of `lensdist train`
(tests/classify): the tiny config, and a config's data set generated once for a module.

Imported by name (``from generated_sets import TINY``): ``tests/`` is on the path the way pytest
loads its conftest.
"""

from __future__ import annotations

from pathlib import Path

from lensdist_torch.config import LensdistConfig, config_from_dict
from lensdist_torch.data.shards import generate

#: The tiny data set: 96 x 128 views, 8 training and 4 + 2 test pairs, shards of 4.
TINY = {
    "image": {"height": 96, "width": 128},
    "protocol": {"n_train": 8, "n_test_distorted": 4, "n_test_undistorted": 2, "shard_size": 4},
}
TINY_CFG = config_from_dict(TINY)


def generate_once(
    tmp_path_factory, name: str, config: LensdistConfig = TINY_CFG, folder: str = "ref"
) -> tuple[Path, dict]:
    """``generate`` of ``config`` into a new ``name``/``folder`` (a module-scoped fixture's data
    set): the folder and generate's summary."""
    out = tmp_path_factory.mktemp(name) / folder
    return out, generate(config, out, progress=False)
