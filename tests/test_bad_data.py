"""Bad folders and data (issue 45): what cannot be opened is listed with its reason and refused
with 422 / 1008, never 500 / 1011 or an ERROR log; symlinks out of the volumes folder are skipped;
degenerate data (constant, all zeros, an iso at or outside the value range, a Siemens mosaic)
says so in one line, in the CLI and in the server alike (one rule: `check_iso`)."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from isosr_cli.main import main
from isosr_render import Volume, resolve_iso
from isosr_render.catalog import IsoOutOfRange, check_iso, otsu_inside, shared_volumes_dir
from isosr_render.volume_io import open_source
from isosr_render.voxels import VolumeError
from isosr_server import protocol as P
from isosr_server.volumes import VolumeCatalog
from server_fixtures import CAM0, expect_close, recv, running_server, send, server_settings
from test_formats import VALUES, _dicom, _write_series

LIMITS = P.Limits(max_message_bytes=2**20, max_sessions=4, idle_timeout_s=30.0, max_fps=1000.0,
                  max_messages_per_s=5000.0)
# A 0..200 ramp: a good volume whose value range the messages name.
RAMP = np.linspace(0.0, 200.0, 20 * 16 * 12, dtype=np.float32).reshape(20, 16, 12)
VIEW = {"mode": "full", "ao_rays": 0}


def _bad_folder(root: Path) -> Path:
    """A volumes folder: a good ramp, a broken .npy, a constant and an all-zeros volume, a DICOM
    folder of two series, and a symlink to a volume outside the folder."""
    root.mkdir()
    np.save(root / "ramp.npy", RAMP)
    (root / "broken.npy").write_bytes(b"\x93NUMPY garbage, not an array")
    np.save(root / "flat.npy", np.full((8, 8, 8), 7, np.uint8))
    np.save(root / "zeros.npy", np.zeros((8, 8, 8), np.float32))
    _write_series(root / "mixed", series="1.2.3.4")
    _write_series(root / "mixed", values=VALUES[:, :, :4], series="1.2.3.99", names=[f"B{k}" for k in range(4)])
    np.save(root.parent / "secret.npy", RAMP)
    (root / "escape.npy").symlink_to(root.parent / "secret.npy")
    return root


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return _bad_folder(tmp_path_factory.mktemp("bad") / "volumes")


@pytest.fixture(scope="module")
def srv(folder):
    with running_server(server_settings(volumes=folder, limits=LIMITS)) as s:
        yield s


def _listing(srv) -> dict[str, dict]:
    status, body = srv.get_json("/v1/volumes")
    assert status == 200, body
    return {v["name"]: v for v in body["volumes"]}


# --- the one rule -----------------------------------------------------------------------------------

def test_an_iso_must_lie_strictly_inside_the_value_range():
    ramp = Volume.from_array(RAMP, name="ramp")
    assert check_iso(ramp, 0.25) == 0.25
    for iso, where in ((999.0, "iso 999 is outside ramp's value range [0, 200]"),
                       (-5.0, "iso -5 is outside"), (0.0, "iso 0 is at an end of"), (200.0, "iso 200 is at an end of")):
        with pytest.raises(IsoOutOfRange, match=re.escape(where)):
            check_iso(ramp, ramp.normalized_iso(iso))
    flat = Volume.from_array(np.full((4, 4, 4), 7.0, np.float32), name="flat")
    with pytest.raises(IsoOutOfRange, match=r"^flat is constant \(every voxel 7\): it has no isosurface at any iso$"):
        check_iso(flat, 0.5)  # even a normalized iso inside (0, 1)


def test_two_valued_data_get_a_suggested_iso_inside_the_range():
    """OpenCV's Otsu puts the threshold of two-valued data at the lower value, where no surface is."""
    binary = Volume.from_array(np.pad(np.ones((4, 4, 4), np.uint8), 2), name="binary")
    assert binary.otsu_iso() == 0.0
    assert otsu_inside(binary) == 0.5 == resolve_iso("binary.npy", binary)
    assert check_iso(binary, resolve_iso("binary.npy", binary)) == 0.5


# --- the CLI ----------------------------------------------------------------------------------------

def test_the_cli_refuses_an_iso_outside_the_range_and_writes_no_png(tmp_path, capsys):
    np.save(tmp_path / "ramp.npy", RAMP)
    out = tmp_path / "out.png"
    assert main(["render", str(tmp_path / "ramp.npy"), "--iso", "999", "--size", "16x12", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "iso 999 is outside" in err and "ramp.npy's value range [0, 200]" in err and err.count("\n") == 1
    assert main(["render", str(tmp_path / "ramp.npy"), "--iso", "1", "--normalized-iso", "-o", str(out)]) == 2
    assert "iso 200 is at an end of" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.skipif(not (shared_volumes_dir() / "volumes.json").is_file(), reason="no shared volumes")
def test_the_cli_names_a_shared_volumes_range(tmp_path, capsys):
    """The issue's own case: ``isosr render shared:bonsai --iso 999``."""
    out = tmp_path / "bonsai.png"
    assert main(["render", "shared:bonsai", "--iso", "999", "-o", str(out)]) == 2
    assert "iso 999 is outside bonsai's value range [0, 255]" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("values, says", [(np.zeros((8, 8, 8), np.float32), "is all zeros"),
                                          (np.full((8, 8, 8), 7, np.uint8), "is constant (every voxel 7)")])
def test_the_cli_refuses_a_constant_volume_in_one_line(tmp_path, capsys, values, says):
    np.save(tmp_path / "v.npy", values)
    out = tmp_path / "v.png"
    assert main(["render", str(tmp_path / "v.npy"), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"v.npy {says}: it has no isosurface at any iso" in err and err.count("\n") == 1
    assert not out.exists()


# --- DICOM --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("mark", ["tag", "image_type"])
def test_a_siemens_mosaic_is_refused_naming_it(tmp_path, mark):
    for k in range(2):  # two mosaics of an fMRI run: the same position, so otherwise "same position"
        ds = _dicom(np.zeros((24, 24), np.int16), (0.0, 0.0, 0.0), number=k + 1)
        if mark == "tag":
            ds.add_new((0x0019, 0x100A), "US", 36)
        else:
            ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "MOSAIC"]
        ds.save_as(tmp_path / f"MR{k}", enforce_file_format=True)
    with pytest.raises(VolumeError) as info:
        open_source(tmp_path)
    message = str(info.value)
    assert "Siemens mosaic" in message and "dcm2niix" in message and "\n" not in message
    assert ("36 slices" in message) == (mark == "tag")


# --- the catalog and the server -------------------------------------------------------------------

def test_a_symlink_out_of_the_folder_is_skipped_with_one_warning(folder, caplog):
    with caplog.at_level(logging.INFO, logger="isosr"):
        catalog = VolumeCatalog(folder)
        assert "escape" not in catalog.names() and "ramp" in catalog.names()
        for name in catalog.names():
            catalog.info(name)
    skipped = [r for r in caplog.records if "escape.npy" in r.getMessage()]
    assert len(skipped) == 1 and skipped[0].levelno == logging.WARNING and "outside" in skipped[0].getMessage()
    assert str(folder.parent / "secret.npy") not in caplog.text


def test_a_manifest_entry_outside_the_folder_is_skipped(tmp_path, caplog):
    (tmp_path / "volumes").mkdir()
    np.save(tmp_path / "volumes" / "ramp.npy", RAMP)
    np.save(tmp_path / "secret.npy", RAMP)
    entries = [{"name": n, "file": f, "shape_xyz": [20, 16, 12], "value_range": [0.0, 200.0]}
               for n, f in (("ramp", "ramp.npy"), ("secret", "../secret.npy"))]
    (tmp_path / "volumes" / "volumes.json").write_text(json.dumps(entries))
    with caplog.at_level(logging.INFO, logger="isosr"):
        catalog = VolumeCatalog(tmp_path / "volumes")
    assert "secret" not in catalog.names() and catalog.info("ramp").error is None
    assert [r.levelno for r in caplog.records if "'secret'" in r.getMessage()] == [logging.WARNING]


def test_a_broken_file_is_listed_with_its_reason_and_the_rest_is_unaffected(srv, caplog):
    with caplog.at_level(logging.INFO, logger="isosr"):
        listed = _listing(srv)
        status, broken = srv.get_json("/v1/volumes/broken")
        good_status, good = srv.get_json("/v1/volumes/ramp")
    assert "escape" not in listed and {"ramp", "broken", "mixed", "flat", "zeros", "proc:sphere"} <= set(listed)
    assert "broken.npy: cannot read" in listed["broken"]["error"] and str(srv.settings.volumes) not in str(listed)
    assert "error" not in listed["ramp"] and "error" not in listed["proc:sphere"]
    assert status == 422 and listed["broken"]["error"] in broken["error"]
    assert good_status == 200 and good["value_range"] == [0.0, 200.0] and "error" not in good
    assert any(r.levelno == logging.INFO and "422" in r.getMessage() for r in caplog.records)
    assert srv.errors.messages() == []


def test_a_mixed_dicom_folder_is_listed_and_refused_with_its_reason(srv, caplog):
    assert "2 DICOM series mixed" in _listing(srv)["mixed"]["error"]
    with caplog.at_level(logging.INFO, logger="isosr"):
        status, body = srv.get_json("/v1/volumes/mixed")
        assert status == 422 and "mixed: 2 DICOM series mixed" in body["error"]
        with srv.view() as ws:
            send(ws, P.OpenMsg("mixed", P.SettingsUpdate(width=32, height=24, **VIEW), CAM0))
            expect_close(ws, P.CLOSE_POLICY, "volume 'mixed' cannot be opened: mixed: 2 DICOM series mixed")
    assert any(r.levelno == logging.INFO and "1008" in r.getMessage() for r in caplog.records)
    assert srv.errors.messages() == []


def test_a_view_refuses_an_iso_outside_the_range_naming_it(srv):
    with srv.view() as ws:
        send(ws, P.OpenMsg("ramp", P.SettingsUpdate(width=32, height=24, **VIEW), CAM0, iso=999.0))
        expect_close(ws, P.CLOSE_POLICY, "open.iso: iso 999 is outside ramp's value range [0, 200]")
    with srv.view() as ws:
        send(ws, P.OpenMsg("ramp", P.SettingsUpdate(width=32, height=24, **VIEW), CAM0, iso=50.0))
        ready = recv(ws)
        assert isinstance(ready, P.ReadyMsg) and ready.volume.iso_normalized == pytest.approx(0.25)
        send(ws, P.IsoMsg(-5.0, seq=1))
        expect_close(ws, P.CLOSE_POLICY, "iso.value: iso -5 is outside ramp's value range [0, 200]")
    assert srv.errors.messages() == []


@pytest.mark.parametrize("name, says", [("flat", "flat is constant (every voxel 7)"), ("zeros", "zeros is all zeros")])
def test_a_view_of_a_constant_volume_is_refused_in_one_line(srv, name, says):
    with srv.view() as ws:
        send(ws, P.OpenMsg(name, P.SettingsUpdate(width=32, height=24, **VIEW), CAM0))
        expect_close(ws, P.CLOSE_POLICY, f"open.volume: {says}: it has no isosurface at any iso")
    status, info = srv.get_json(f"/v1/volumes/{name}")  # its info loads; it says why no view opens
    assert status == 200 and info["error"] == f"{says}: it has no isosurface at any iso"
    assert _listing(srv)[name]["error"] == info["error"]
    assert srv.errors.messages() == []
