"""Helpers of the workflow tests (the fixtures are in conftest.py)."""

from __future__ import annotations

#: A protocol small enough for CI: 96 x 128 images, 200 training and 12 test pairs.
TINY = {
    "image": {"height": 96, "width": 128},
    "protocol": {"n_train": 200, "n_test_distorted": 8, "n_test_undistorted": 4, "shard_size": 100},
    "classifier": {"n_eigenvectors": 2},
}

#: The same protocol as a config file, for the CLI.
TINY_TOML = "\n".join(f"[{sec}]\n" + "".join(f"{k} = {v}\n" for k, v in fields.items()) for sec, fields in TINY.items())


def tiny_cli_folder(tiny_out, folder):
    """``folder`` holding a copy of the tiny run's data and its config file: (folder, config path)."""
    import shutil

    shutil.copytree(tiny_out / "data", folder / "data")
    (folder / "tiny.toml").write_text(TINY_TOML)
    return folder, folder / "tiny.toml"
