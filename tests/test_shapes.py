"""The one shape check (isosr_render.shapes.check_shape)."""

import numpy as np
import pytest
import torch

from isosr_render.shapes import check_shape


def test_binds_names_and_returns_their_sizes():
    assert check_shape(torch.zeros(2, 5, 3, 4), "(B, 5, H, W)", "x", "f") == {"B": 2, "H": 3, "W": 4}
    assert check_shape(np.zeros((3, 4, 3)), "(H, W, 3)", "x", "f", {"H": 3}) == {"H": 3, "W": 4}


@pytest.mark.parametrize("shape, spec, dims, match", [
    ((2, 4, 3, 4), "(B, 5, H, W)", None, r"f: x must be \(B, 5, H, W\), got \(2, 4, 3, 4\)"),
    ((2, 5, 3), "(B, 5, H, W)", None, r"got \(2, 5, 3\)"),
    ((2, 5, 3, 4), "(B, 5, H, W)", {"B": 1, "H": 3}, r"\(B, 5, H, W\) with B=1, H=3, got \(2, 5, 3, 4\)"),
    ((3, 4), "(H, H)", None, r"\(H, H\), got \(3, 4\)"),
    ((1, 4, 8, 8), "(B, 5|6, H, W)", None, r"\(B, 5\|6, H, W\)"),
    ((2,), "(*, H, W)", None, r"\(\*, H, W\), got \(2,\)"),
])
def test_refuses_with_the_spec_and_the_shape(shape, spec, dims, match):
    with pytest.raises(ValueError, match=match):
        check_shape(torch.zeros(shape), spec, "x", "f", dims)


def test_alternatives_and_leading_star():
    check_shape(torch.zeros(1, 6, 2, 2), "(B, 5|6, H, W)", "x", "f")
    assert check_shape(torch.zeros(7, 2, 3, 4, 3), "(*, H, W, 3)", "x", "f") == {"H": 3, "W": 4}
    assert check_shape(torch.zeros(3, 4), "(*, H, W)", "x", "f") == {"H": 3, "W": 4}


def test_a_star_after_the_first_dim_is_a_bad_spec():
    with pytest.raises(ValueError, match="bad spec"):
        check_shape(torch.zeros(2, 3), "(H, *)", "x", "f")
