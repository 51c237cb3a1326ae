"""Tests for isosr_render.voxels: ArraySource, source checks, chunk-aligned boxes."""

from __future__ import annotations

import numpy as np
import pytest

from isosr_render.voxels import ArraySource, VolumeError, VoxelSource, box_extent, boxes


def test_array_source_reads_boxes_as_stored():
    values = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    source = ArraySource(values, (1, 2, 3), "v", rescale=(2.0, -1024.0))
    assert isinstance(source, VoxelSource)
    assert source.shape == (4, 5, 6) and source.dtype == np.int16 and source.spacing == (1.0, 2.0, 3.0)
    np.testing.assert_array_equal(source.read(slice(1, 3), slice(0, 5), slice(2, 4)), values[1:3, :, 2:4])
    with pytest.raises(ValueError):
        source.read(slice(0, 1), slice(0, 1), slice(0, 1))[0, 0, 0] = 1  # read-only


@pytest.mark.parametrize("kwargs, message", [
    (dict(values=np.zeros((3, 3))), "expected a 3D volume"),
    (dict(values=np.zeros((3, 1, 3))), "at least 2 voxels"),
    (dict(values=np.zeros((3, 3, 3), np.complex64)), "unsupported voxel dtype complex64"),
    (dict(values=np.zeros((3, 3, 3)), spacing=(1, 0, 1)), "spacing"),
    (dict(values=np.zeros((3, 3, 3)), rescale=(0.0, 1.0)), "nonzero slope"),
])
def test_bad_sources_get_one_line_errors(kwargs, message):
    with pytest.raises(VolumeError, match=f"^bad: .*{message}"):
        ArraySource(name="bad", **kwargs)


@pytest.mark.parametrize("shape, chunks, brick, budget", [
    ((50, 37, 20), (16, 16, 1), 8, 40_000), ((9, 9, 9), (9, 9, 9), 8, 1 << 20), ((64, 64, 64), (64, 64, 64), 8, 1000),
])
def test_boxes_tile_the_volume_once_aligned_to_chunks_and_bricks(shape, chunks, brick, budget):
    source = ArraySource(np.zeros(shape, np.uint16), chunks=chunks)
    extent = box_extent(source, brick, budget)
    count = np.zeros(shape, np.int32)
    for box in boxes(source, brick, budget):
        count[box] += 1
        for s, e, c, n in zip(box, extent, chunks, shape):
            assert s.start % e == 0 and (e % brick == 0 or e == n) and (e % c == 0 or e == n)
    assert (count == 1).all()
