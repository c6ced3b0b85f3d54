"""Host syncs and torch.compile: the value checks are switchable (``validate``, kornia's
convention) and skipped while compiling, so the compiled loss has no graph break."""

from __future__ import annotations

import pytest
import torch
from metric_helpers import ENTRY_POINTS, textured

import lensdist_torch.metric._inputs as inputs
from lensdist_torch import RegistrationQualityLoss, quality_map, registration_quality, registration_quality_loss
from lensdist_torch.metric.stateful import RegistrationQualityMetric


def _compiled_vs_eager(backend: str) -> None:
    torch._dynamo.reset()
    loss_fn = RegistrationQualityLoss()  # validate=True: skipped while compiling
    compiled = torch.compile(loss_fn, fullgraph=True, backend=backend)  # raises on a graph break
    img1 = textured(1, 32, 32, seed=0, dtype=torch.float32)
    img2 = torch.roll(img1, 1, dims=-1)
    valid = torch.ones(1, 1, 32, 32)
    valid[..., :, :5] = 0
    x_eager = img1.clone().requires_grad_()
    x_comp = img1.clone().requires_grad_()
    eager = loss_fn(x_eager, img2, valid)
    eager.backward()
    comp = compiled(x_comp, img2, valid)
    comp.backward()
    assert float(eager.detach()) > 0.1
    torch.testing.assert_close(comp.detach(), eager.detach(), atol=1e-5, rtol=0)
    torch.testing.assert_close(x_comp.grad, x_eager.grad, atol=1e-5, rtol=0)


@pytest.mark.slow
def test_compiled_loss_inductor_equals_eager():
    """The default backend (inductor, C++ on the CPU): forward and backward, no graph break.

    About 25 s of CPU on a cold inductor cache (a few seconds warm); marked slow.
    """
    _compiled_vs_eager("inductor")


def test_compiled_loss_has_no_graph_break():
    """The same through dynamo and AOTAutograd without code generation (2 s): the graph-break
    check that stays in a ``-m "not slow"`` run."""
    _compiled_vs_eager("aot_eager")


def _counting(monkeypatch):
    calls = []
    original = inputs.check_values

    def counted(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(inputs, "check_values", counted)
    return calls


def test_validate_false_skips_the_value_checks(monkeypatch):
    calls = _counting(monkeypatch)
    img = torch.rand(2, 1, 16, 24)
    valid = torch.ones(2, 1, 16, 24)
    entry_points = [  # every entry point but the per-pixel variant
        lambda v, call=call: call(img, img, valid, validate=v)
        for name, call in ENTRY_POINTS.items()
        if name != "registration_quality pixels"
    ]
    for call in entry_points:
        call(False)
    assert calls == []
    for call in entry_points:
        call(True)
    assert len(calls) == len(entry_points)


def test_checks_are_skipped_while_compiling(monkeypatch):
    calls = _counting(monkeypatch)
    img = torch.rand(1, 1, 16, 16)
    monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
    registration_quality_loss(img, img)
    quality_map(img, img)
    assert calls == []


@pytest.mark.bad_input
def test_validate_false_trusts_the_values():
    """Without the checks a 0-255 float image goes through (the caller vouches for it)."""
    img = 255 * torch.rand(1, 1, 16, 16)
    with pytest.raises(ValueError, match="data_range=255"):
        RegistrationQualityLoss()(img, img)
    assert float(RegistrationQualityLoss(validate=False)(img, img)) >= 0
    # shapes and types are still checked
    with pytest.raises(ValueError, match="same shape"):
        quality_map(img, img[..., :8], validate=False)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_no_host_sync_on_cuda_without_validation():
    """With validate=False the maps, the loss (forward and backward) and the stateful update
    never wait for the GPU; with the checks on, there is exactly the one synchronisation."""
    img1 = textured(2, 37, 61, seed=1, dtype=torch.float32).cuda()
    img2 = torch.roll(img1, 1, dims=-1)
    valid = torch.ones(2, 1, 37, 61, device="cuda")
    x = img1.clone().requires_grad_()
    metric = RegistrationQualityMetric(validate=False).cuda()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        quality_map(img1, img2, valid, validate=False)
        registration_quality(img1, img2, valid, validate=False)
        registration_quality_loss(x, img2, valid, validate=False).backward()
        metric.update(img1, img2, valid)
        with pytest.raises(RuntimeError, match="synchroniz"):
            quality_map(img1, img2, valid)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert bool(torch.isfinite(x.grad).all())


@pytest.mark.bad_input
def test_one_switch_for_every_value_check(monkeypatch):
    """check_image's finite check (the estimators' validate=) goes through should_validate, as
    the metric's: asked for and not while compiling."""
    from lensdist_torch.core.images import check_image

    img = torch.rand(1, 1, 16, 16)
    img[0, 0, 3, 4] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        check_image(img)
    check_image(img, finite=False)  # the caller vouches for the values
    monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
    check_image(img)  # no host sync while tracing
