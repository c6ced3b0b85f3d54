"""Shared fixtures of the workflow tests: one tiny protocol run (small images, few pairs), a stand-in for PyAV."""

from __future__ import annotations

import sys
import types

import pytest
import torch
from workflow_helpers import TINY

from lensdist_torch.config import config_from_dict


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """``reproduce`` of the tiny protocol, once per session: (out folder, its return value)."""
    from lensdist_torch.workflows.reproduce import reproduce

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out = tmp_path_factory.mktemp("reproduce")
        res = reproduce(config_from_dict(TINY), out, workers=1, progress=False, figures=True)
    finally:
        torch.set_num_threads(n)
    return out, res


@pytest.fixture
def fake_pyav(monkeypatch):
    """``fake_pyav(frames)`` makes ``import av`` a stand-in for PyAV's open / decode whose one video
    stream yields a frame for each of ``frames``: functions ``format -> array``, the frame's
    ``to_ndarray(format=...)``, or an exception the decoder raises there; its header announces
    ``announced`` frames (default: as many)."""

    def install(frames, announced: int | None = None) -> None:
        class Container:
            streams = types.SimpleNamespace(video=[types.SimpleNamespace(frames=len(frames) if announced is None
                                                                         else announced)])

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return False

            def decode(self, video):
                assert video == 0
                for f in frames:  # an exception among them: the decoder raises it there
                    if isinstance(f, Exception):
                        raise f
                    yield types.SimpleNamespace(to_ndarray=f)

        monkeypatch.setitem(sys.modules, "av", types.SimpleNamespace(open=lambda path: Container()))

    return install
