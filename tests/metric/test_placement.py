"""Where the inputs live (issue 19): every public metric entry point refuses a meta tensor, a
sparse tensor, or an input on another device than img1's with a one-line error naming the
argument (torch's own errors said nothing about which input). Always checked: these checks
read no data, so ``validate=False`` keeps them."""

from __future__ import annotations

import pytest
import torch
from metric_helpers import ENTRY_POINTS
from one_line import one_line_error

from lensdist_torch import quality_map
from lensdist_torch.metric import error_images, local_criteria

SHAPE = (2, 1, 16, 24)


def inputs():
    g = torch.Generator().manual_seed(3)
    return torch.rand(SHAPE, generator=g), torch.rand(SHAPE, generator=g), torch.ones(SHAPE)




@pytest.mark.bad_input
@pytest.mark.parametrize("validate", [True, False])
@pytest.mark.parametrize("name", sorted(ENTRY_POINTS))
def test_meta_tensors_are_named(name, validate):
    call = ENTRY_POINTS[name]
    img1, img2, valid = inputs()
    meta = lambda t: t.to("meta")  # noqa: E731
    one_line_error(ValueError, lambda: call(img1, meta(img2), valid, validate=validate), "img2", "meta", "cpu")
    one_line_error(ValueError, lambda: call(meta(img1), img2, valid, validate=validate), "img1", "meta")
    one_line_error(ValueError, lambda: call(meta(img1), meta(img2), None, validate=validate), "img1", "meta")
    if name != "local_criteria":  # it takes no mask
        one_line_error(ValueError, lambda: call(img1, img2, meta(valid), validate=validate), "valid", "meta", "cpu")


@pytest.mark.bad_input
@pytest.mark.parametrize("name", sorted(ENTRY_POINTS))
def test_sparse_tensors_are_named(name):
    call = ENTRY_POINTS[name]
    img1, img2, valid = inputs()
    one_line_error(TypeError, lambda: call(img1, img2.to_sparse(), valid), "img2", "dense", "sparse")
    one_line_error(TypeError, lambda: call(img1.to_sparse(), img2, valid), "img1", "dense")
    if name != "local_criteria":
        one_line_error(TypeError, lambda: call(img1, img2, valid.to_sparse()), "valid", "dense")


@pytest.mark.bad_input
@pytest.mark.parametrize("name", sorted(ENTRY_POINTS))
def test_wrong_dtypes_are_named(name):
    call = ENTRY_POINTS[name]
    img1, img2, valid = inputs()
    for bad in (torch.complex64, torch.bool, torch.int16):
        worse1, worse2 = img1.to(bad), img2.to(bad)
        one_line_error(TypeError, lambda w=worse2: call(img1, w, valid), "img2", str(bad).replace("torch.", ""))
        one_line_error(TypeError, lambda w=worse1: call(w, img2, valid), "img1")
    if name != "local_criteria":
        one_line_error(TypeError, lambda: call(img1, img2, valid.to(torch.complex64)), "valid", "complex64")


@pytest.mark.bad_input
def test_error_images_mask_placement():
    img1, img2, valid = inputs()
    crit = local_criteria(img1, img2)
    one_line_error(ValueError, lambda: error_images(crit, valid.to("meta")), "valid", "meta")
    one_line_error(ValueError, lambda: error_images(crit, valid.to("meta"), validate=False), "valid", "meta")
    one_line_error(TypeError, lambda: error_images(crit, valid.to_sparse()), "valid", "dense")
    # a good mask still works
    assert float(error_images(crit, torch.zeros(SHAPE)).e_reg.sum()) == 0.0


def test_same_device_inputs_are_unchanged():
    img1, img2, valid = inputs()
    assert torch.equal(quality_map(img1, img2, valid), quality_map(img1, img2))
    assert torch.equal(quality_map(img1, img2, valid.bool()), quality_map(img1, img2))


@pytest.mark.bad_input
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("name", sorted(ENTRY_POINTS))
def test_inputs_on_two_devices_are_named(name):
    call = ENTRY_POINTS[name]
    img1, img2, valid = inputs()
    cuda = torch.device("cuda", torch.cuda.current_device())
    one_line_error(ValueError, lambda: call(img1.cuda(), img2, valid.cuda()), "img2 is on cpu", str(cuda))
    one_line_error(ValueError, lambda: call(img1, img2.cuda(), valid), "img2 is on cuda", "cpu")
    if name != "local_criteria":
        one_line_error(ValueError, lambda: call(img1.cuda(), img2.cuda(), valid), "valid is on cpu", str(cuda))
    call(img1.cuda(), img2.cuda(), valid.cuda())  # one device: no error
