"""Frame files and atomic writes: round trips, shape checks, nothing half-written."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest
import torch

from isosr_render.atomic import atomic_write
from isosr_render.buffers import FrameBuffers
from isosr_render.conventions import AO, DEPTH, HIGHRES_BUFFERS, HIGHRES_CHANNELS, MASK, NORMAL


def test_frame_file_round_trip(tmp_path):
    frame = FrameBuffers(mask=torch.ones(3, 4), normal=torch.rand(3, 4, 3), flow=torch.zeros(3, 4, 2))
    frame.save_npz(tmp_path / "f.npz")
    back = FrameBuffers.load_npz(tmp_path / "f.npz")
    assert back.present() == ["mask", "normal", "flow"]
    torch.testing.assert_close(back.normal, frame.normal)


@pytest.mark.parametrize("arrays, message", [({"normal": np.zeros((3, 4, 2), np.float32)}, "normal"),
                                             ({"mask": np.zeros((3, 4, 1), np.float32)}, "mask"),
                                             ({"colour": np.zeros((3, 4), np.float32)}, "unknown")])
def test_frame_file_with_wrong_buffers_is_refused(tmp_path, arrays, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=message):
        FrameBuffers.load_npz(tmp_path / "bad.npz")


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")

    def broken(f):
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, broken)
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["out.bin"]


def test_written_file_has_the_usual_permissions(tmp_path):
    atomic_write(tmp_path / "x.bin", lambda f: f.write(b"x"))
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "x.bin").stat().st_mode) == 0o666 & ~umask


def test_channels_first_stacks_in_the_network_order():
    h, w = 3, 4
    frame = FrameBuffers(mask=torch.rand(h, w), normal=torch.rand(h, w, 3), depth=torch.rand(h, w), ao=torch.rand(h, w))
    stacked = frame.channels_first(HIGHRES_BUFFERS)
    assert stacked.shape == (len(HIGHRES_CHANNELS), h, w)
    assert torch.equal(stacked[MASK][0], frame.mask) and torch.equal(stacked[DEPTH][0], frame.depth)
    assert torch.equal(stacked[NORMAL], frame.normal.permute(2, 0, 1)) and torch.equal(stacked[AO][0], frame.ao)
    with pytest.raises(ValueError, match="lacks its ao buffer"):
        FrameBuffers(mask=frame.mask, normal=frame.normal, depth=frame.depth).channels_first(HIGHRES_BUFFERS)
