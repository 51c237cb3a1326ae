"""`isosr render` as a user runs it: frame files, images, and clear errors on bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from isosr_cli.main import main
from isosr_net.methods import FrameMethod, make_runner, run_sequence
from isosr_net.reconstructor import RECON_X2_MODEL
from isosr_net.upscaler import DEFAULT_MODEL
from isosr_render import Renderer, open_volume, resolve_iso
from isosr_render.buffers import FrameBuffers
from isosr_render.camera import orbit
from isosr_render.catalog import shared_volumes_dir


def test_render_npz_frame_file_holds_the_asked_buffers_in_the_documented_layout(tmp_path, capsys):
    out = tmp_path / "frame.npz"
    rc = main(["render", "proc:sphere", "--size", "40x30", "--orbit", "30,20,1.6", "--prev-orbit", "28,20,1.6",
               "--outputs", "mask,normal,depth,position,flow,ao,color", "--ao-samples", "8", "-o", str(out)])
    assert rc == 0
    assert "40x30" in capsys.readouterr().out
    with np.load(out) as z:
        arrays = {k: z[k] for k in z.files}
    assert sorted(arrays) == sorted(["mask", "normal", "depth", "position", "flow", "ao", "color"])
    shapes = {"mask": (30, 40), "normal": (30, 40, 3), "depth": (30, 40), "position": (30, 40, 3),
              "flow": (30, 40, 2), "ao": (30, 40), "color": (30, 40, 3)}
    for name, shape in shapes.items():
        assert arrays[name].shape == shape and arrays[name].dtype == np.float32, name
    hit = arrays["mask"] > 0
    assert set(np.unique(arrays["mask"])) <= {0.0, 1.0} and hit.sum() > 50
    np.testing.assert_allclose(np.linalg.norm(arrays["normal"][hit], axis=-1), 1.0, atol=1e-5)
    # The sphere of radius 0.3 (procedural default) seen from 1.6 away: depth near 1.3 at the center.
    assert 1.25 < arrays["depth"][hit].min() < 1.35
    np.testing.assert_allclose(np.linalg.norm(arrays["position"][hit], axis=-1), 0.3, atol=2e-3)
    # Orbiting by 2 degrees moves the visible surface: flow is nonzero on hits, zero elsewhere.
    assert np.abs(arrays["flow"][hit]).max() > 0.1 and (arrays["flow"][~hit] == 0).all()
    assert ((arrays["ao"] >= 0) & (arrays["ao"] <= 1)).all()
    assert FrameBuffers.load_npz(out).present() == ["mask", "normal", "depth", "position", "flow", "ao", "color"]


def test_render_png_is_the_shaded_image_or_one_buffer(tmp_path):
    color, normal = tmp_path / "c.png", tmp_path / "n.png"
    assert main(["render", "proc:torus", "--size", "48x32", "-o", str(color)]) == 0
    assert main(["render", "proc:torus", "--size", "48x32", "--png-of", "normal", "-o", str(normal)]) == 0
    c, n = cv2.imread(str(color)), cv2.imread(str(normal))
    assert c.shape == (32, 48, 3) and n.shape == (32, 48, 3)
    assert (c == 255).all(axis=-1).mean() > 0.3  # white background around the torus
    assert not np.array_equal(c, n)


def test_eye_camera_and_data_unit_iso_match_orbit_and_normalized_iso(tmp_path):
    eye = orbit(30.0, 20.0, 1.6).eye
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert main(["render", "proc:sphere", "--size", "24x24", "--orbit", "30,20,1.6", "--iso", "0",
                 "--outputs", "mask", "-o", str(a)]) == 0
    from isosr_render import open_volume
    iso = open_volume("proc:sphere").normalized_iso(0.0)
    assert main(["render", "proc:sphere", "--size", "24x24", "--eye", ",".join(map(str, eye)), "--iso", str(iso),
                 "--normalized-iso", "--outputs", "mask", "-o", str(b)]) == 0
    np.testing.assert_array_equal(np.load(a)["mask"], np.load(b)["mask"])


def test_render_reconstruct_writes_what_the_reconstruct_method_makes(tmp_path, capsys):
    volume = open_volume("proc:cloud:3@48")
    renderer, iso = Renderer(volume, "cpu"), resolve_iso("proc:cloud:3@48", volume)
    cameras = [orbit(28.0, 20.0, 1.6), orbit(30.0, 20.0, 1.6)]
    one, two = tmp_path / "one.npz", tmp_path / "two.npz"
    common = ["render", "proc:cloud:3@48", "--size", "48x32", "--orbit", "30,20,1.6"]
    assert main(common + ["--method", "reconstruct:ao_rays=2", "--outputs", "mask,normal,depth,ao,color",
                          "-o", str(one)]) == 0
    assert "made by full, AO 2, spp 1, recon fp32: mask,normal,depth,ao,color at 48x32" in capsys.readouterr().out
    frame = FrameBuffers.load_npz(one)
    assert frame.present() == ["mask", "normal", "depth", "ao", "color"]
    method = FrameMethod.of("reconstruct", ao_rays=2)
    expected = run_sequence(make_runner(method, renderer, iso, 48, 32), cameras[1:])[0]
    for name in frame.present():
        torch.testing.assert_close(getattr(frame, name), getattr(expected, name), rtol=0, atol=1e-5)
    assert 0 < frame.mask.mean() < 1 and ((frame.mask > 0) & (frame.mask < 1)).any()  # antialiased edges
    # A previous camera: its frame is reconstructed first and carried over by the flow.
    assert main(common + ["--method", "reconstruct:ao_rays=0,spp=2", "--outputs", "ao,color", "--prev-orbit",
                          "28,20,1.6", "-o", str(two)]) == 0
    assert "full, AO 0, spp 2, recon fp32 from the previous camera on:" in capsys.readouterr().out
    frame = FrameBuffers.load_npz(two)
    assert frame.present() == ["ao", "color"]
    method = FrameMethod.of("reconstruct", ao_rays=0, spp=2)
    carried = run_sequence(make_runner(method, renderer, iso, 48, 32), cameras)[-1]
    alone = run_sequence(make_runner(method, renderer, iso, 48, 32), cameras[1:])[0]
    torch.testing.assert_close(frame.color, carried.color, rtol=0, atol=1e-5)
    assert (frame.color - alone.color).abs().max() > 1e-3


def test_render_reconstruct_to_png_and_in_bf16(tmp_path):
    png, fp32, bf16 = tmp_path / "ao.png", tmp_path / "fp32.npz", tmp_path / "bf16.npz"
    common = ["render", "proc:torus", "--size", "48x32", "--method"]
    assert main(common + ["reconstruct:ao_rays=2", "--png-of", "ao", "-o", str(png)]) == 0
    assert cv2.imread(str(png)).shape == (32, 48, 3)
    assert main(common + ["reconstruct:ao_rays=2", "--outputs", "color", "-o", str(fp32)]) == 0
    assert main(common + ["reconstruct:ao_rays=2,precision=bf16", "--outputs", "color", "-o", str(bf16)]) == 0
    a, b = np.load(fp32)["color"], np.load(bf16)["color"]
    assert np.isfinite(b).all() and 0 < np.abs(a - b).max() < 0.1


@pytest.mark.parametrize("argv, message", [
    (["render", "/no/such/volume.nii.gz", "-o", "x.npz"], "no such file"),
    (["render", "proc:nonsense", "-o", "x.npz"], "valid"),
    (["render", "proc:sphere", "--outputs", "flow", "-o", "x.npz"], "previous camera"),
    (["render", "proc:sphere", "--outputs", "mask,bogus", "-o", "x.npz"], "unknown outputs"),
    (["render", "proc:sphere", "-o", "x.jpg"], ".npz or .png"),
    (["render", "proc:sphere", "--spp", "0", "-o", "x.npz"], "spp"),
    (["render", "proc:sphere", "--eye", "0,0,2", "--orbit", "0,0,2", "-o", "x.npz"], "either --eye or --orbit"),
    (["render", "proc:sphere", "--device", "cuda", "-o", "x.npz"], "CUDA"),
    (["render", "proc:sphere", "--method", "reconstruct", "--budget-ms", "5", "-o", "x.npz"], "exclude each other"),
    (["render", "proc:sphere", "--method", "reconstruct:ao_rays=4097", "-o", "x.npz"],
     "ao_rays must be an integer in [0, 4096]"),
    (["render", "proc:sphere", "--method", "reconstruct:ao_rays=-1", "-o", "x.npz"], "ao_rays must be an integer"),
    (["render", "proc:sphere", "--method", "reconstruct:spp=0", "-o", "x.npz"], "spp"),
    (["render", "proc:sphere", "--method", "reconstruct", "--spp", "2", "-o", "x.npz"], "without --spp"),
    (["render", "proc:sphere", "--method", "reconstruct", "--outputs", "mask,flow", "-o", "x.npz"], "not flow"),
    (["render", "proc:sphere", "--method", "reconstruct", "--seed", "3", "--refine", "bisection", "-o", "x.npz"],
     "without --refine, --seed"),
    (["render", "proc:sphere", "--method", "warp", "-o", "x.npz"], "unknown frame method 'warp'; registered: full"),
    (["render", "proc:sphere", "--method", "full:factor=2", "-o", "x.npz"], "takes no factor"),
    (["render", "proc:sphere", "--method", "upscale:interpolation=cubic", "-o", "x.npz"], "interpolation must be one of"),
    (["render", "proc:sphere", "--method", f"reconstruct:model={DEFAULT_MODEL}", "-o", "x.npz"],
     "not a reconstruction network"),
    (["render", "-o", "x.npz"], "give a volume and -o FILE"),
])
def test_bad_input_gives_one_line_error_and_exit_code_2(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    if "cuda" in argv:
        import warp as wp
        if wp.is_cuda_available():
            pytest.skip("this machine has CUDA")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("isosr render: error:") and message in err
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_shared_volume_renders_from_the_command_line(tmp_path):
    root = shared_volumes_dir()
    if not (root / "volumes.json").is_file():
        pytest.skip(f"../shared/volumes not found at {root}")
    entry = next(e for e in json.loads((root / "volumes.json").read_text()) if e["name"] == "chest_lidc")
    out = tmp_path / "chest.npz"
    assert main(["render", str(root / entry["file"]), "--iso", str(entry["otsu_iso_normalized"]), "--normalized-iso",
                 "--size", "48x48", "--outputs", "mask,depth", "-o", str(out)]) == 0
    assert np.load(out)["mask"].mean() > 0.1


def test_installed_console_script_runs():
    """The `isosr` entry point that `pip install` makes (what the README's quick start calls)."""
    exe = __import__("shutil").which("isosr") or str(__import__("pathlib").Path(sys.executable).parent / "isosr")
    result = subprocess.run([exe, "render", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "--outputs" in result.stdout


# `isosr` with the server extra's msgspec missing (a GPU machine with only the base install).
WITHOUT_SERVER_EXTRA = "import sys; sys.modules['msgspec'] = None; from isosr_cli.main import main; sys.exit(main())"


def test_without_the_server_extra_training_runs_and_serve_says_what_to_install():
    def isosr(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", WITHOUT_SERVER_EXTRA, *argv], capture_output=True, text=True,
                              timeout=120)

    train = isosr("train", "--help")
    assert train.returncode == 0 and "--time-limit-minutes" in train.stdout, train.stderr
    for command in ("serve", "client"):
        result = isosr(command, "--port", "8000")
        assert result.returncode == 2
        assert result.stderr.strip().endswith(f"isosr {command}: error: needs the server extra "
                                              "(pip install 'isosr[server]'): module 'msgspec' is not installed")


def test_render_reconstruct_with_the_x2_model_renders_half_the_sides_and_writes_the_full_size(tmp_path, capsys):
    out = tmp_path / "x2.npz"
    assert main(["render", "proc:cloud:3@48", "--size", "64x48", "--method", f"reconstruct:model={RECON_X2_MODEL},ao_rays=2",
                 "--outputs", "mask,ao,color", "-o", str(out)]) == 0
    assert "x2, AO 2, spp 1, recon fp32" in capsys.readouterr().out
    frame = np.load(out)
    assert frame["mask"].shape == (48, 64) and frame["color"].shape == (48, 64, 3)
    assert np.isfinite(frame["color"]).all() and 0 <= frame["ao"].min() and frame["ao"].max() <= 1


def test_render_lists_every_registered_method_and_makes_each(tmp_path, capsys):
    """``--list-methods`` names every kind of the registry with its knobs; ``--method`` makes any of
    them (a new method needs no CLI change)."""
    from isosr_net.methods import RUNNERS, unavailable_kinds

    assert main(["render", "--list-methods"]) == 0
    listing = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listing] == list(RUNNERS)
    assert any(line.startswith("atrous") and "ao_rays=1..4096" in line for line in listing)
    for kind in RUNNERS:
        if kind in unavailable_kinds():
            continue
        out = tmp_path / f"{kind}.npz"
        outputs = "mask" if not RUNNERS[kind].shaded else "mask,color"
        assert main(["render", "proc:torus@24", "--size", "32x24", "--method", kind, "--outputs", outputs,
                     "-o", str(out)]) == 0, kind
        frame = np.load(out)
        assert all(np.isfinite(frame[name]).all() for name in frame.files), kind


def test_render_prints_the_pick_under_a_pixel(tmp_path, capsys):
    """``--pick X,Y``: the library's pick of the rendered view, as one JSON line; a point outside
    the image is an error before anything is written."""
    from isosr_render.picking import pick

    out = tmp_path / "torus.png"
    assert main(["render", "proc:torus@32", "--size", "64x48", "--pick", "24.5,24.5", "-o", str(out)]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    picked = json.loads(line)
    volume = open_volume("proc:torus@32")
    expected = pick(Renderer(volume, "cpu"), orbit(30.0, 20.0, 1.8), resolve_iso("proc:torus@32", volume), 64, 48,
                    24.5, 24.5)
    assert picked["hit"] and tuple(picked["voxel"]) == expected.voxel
    assert picked["value"] == pytest.approx(expected.value)
    assert main(["render", "proc:torus@32", "--size", "64x48", "--pick", "70,1", "-o", str(tmp_path / "x.png")]) == 2
    assert "lies outside the 64x48 image" in capsys.readouterr().err and not (tmp_path / "x.png").exists()


def test_render_picks_which_of_several_surfaces(tmp_path, capsys):
    """With several --iso, --pick names the surface under the pixel: a sphere's distance field seen
    from +z, the centre pixel on the outer of two nested spheres (listed second), a corner on none."""
    for x, expected in ((16.5, 1), (0.5, None)):
        assert main(["render", "proc:sphere@32", "--eye", "0,0,2", "--size", "33x33", "--iso=-0.1", "--iso", "0.1",
                     "--pick", f"{x},{x}", "-o", str(tmp_path / "two.png")]) == 0
        picked = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert picked["surface"] == expected and picked["hit"] == (expected is not None)


def test_render_colored_by_a_field(tmp_path, capsys):
    """--color-by (a volume of the grid, or the gradient), --colormap and --color-range reach the render, a plain
    one and a method's; a field of another grid and a bad colour map are refused naming them."""
    out = tmp_path / "colored.npz"
    for method in ([], ["--method", "atrous:ao_rays=1"]):
        assert main(["render", "proc:sphere@32", "--eye", "0,0,2", "--size", "33x33", "--outputs", "mask,albedo,color",
                     "--color-by", "proc:torus@32", "--colormap", "gray", "--color-range", "0,1", *method,
                     "-o", str(out)]) == 0
        frame = FrameBuffers.load_npz(out)
        hit = frame.mask[16, 16] > 0
        assert hit and frame.albedo[16, 16].min() > 0 and float(frame.albedo[0, 0].max()) == 0.0
    assert main(["render", "proc:sphere@32", "--size", "33x33", "--outputs", "mask,albedo",
                 "--color-by", "gradient", "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["render", "proc:sphere@32", "--color-by", "proc:torus@16", "-o", str(out)]) == 2
    assert "(16, 16, 16) is not the volume's (32, 32, 32)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "proc:sphere@32", "--color-by", "gradient", "--colormap", "jet", "-o", str(out)])


def test_render_several_isos(tmp_path, capsys):
    """--iso (repeated) and --iso-color reach a plain render and a method's: the outer sphere of two (the SDF's
    values 0.1 and -0.1 around its surface) hides the inner; bad counts and colours are refused naming them."""
    out = tmp_path / "two.npz"
    for method in ([], ["--method", "atrous:ao_rays=1"]):
        assert main(["render", "proc:sphere@32", "--eye", "0,0,2", "--size", "33x33", "--outputs",
                     "mask,depth,albedo,color", "--iso=-0.1", "--iso", "0.1", "--iso-color", "0,0,1",
                     "--iso-color", "1,0,0", *method, "-o", str(out)]) == 0
        frame = FrameBuffers.load_npz(out)
        assert frame.albedo[16, 16].tolist() == [1.0, 0.0, 0.0] and float(frame.albedo[0, 0].max()) == 0.0
        assert abs(float(frame.depth[16, 16]) - 1.6) < 1e-2  # the radius-0.4 sphere from 2 away
    assert main(["render", "proc:sphere@32", "--eye", "0,0,2", "--size", "33x33", "--outputs", "mask,surface",
                 "--iso=-0.1", "--iso", "0.1", "-o", str(out)]) == 0
    assert float(FrameBuffers.load_npz(out).surface[16, 16]) == 1.0
    # The outer one at 0: the inner one's colour in the middle, by full and by a filter run on each layer; an
    # unshaded method refuses it.
    for method in ("full", "atrous:ao_rays=1"):
        assert main(["render", "proc:sphere@32", "--eye", "0,0,2", "--size", "33x33", "--outputs", "mask,depth,color",
                     "--iso=-0.1", "--iso", "0.1", "--iso-color", "0,0,1", "--iso-color", "1,0,0", "--iso-opacity",
                     "1", "--iso-opacity", "0", "--method", method, "-o", str(out)]) == 0
        frame = FrameBuffers.load_npz(out)
        assert frame.color[16, 16, 2] > 2 * frame.color[16, 16, 0] and abs(float(frame.depth[16, 16]) - 1.6) < 1e-2, \
            method
    capsys.readouterr()
    assert main(["render", "proc:sphere@32", "--iso=-0.1", "--iso", "0.1", "--iso-opacity", "1", "--iso-opacity",
                 "0.3", "--method", "buffers", "-o", str(out)]) == 2
    assert "surfaces: translucent ones" in capsys.readouterr().err
    for bad, message in ((["--iso", "0.1", "--iso-color", "1,0,0", "--iso-color", "0,1,0"], "one --iso-color per"),
                         (["--iso", "0.1", "--iso-color", "1,2,0"], "surfaces[0].color must be three numbers"),
                         (["--iso", "0.1", "--iso-opacity", "2"], "surfaces[0].opacity must be in [0, 1]"),
                         (["--iso", "0.1", "--iso", "0.2", "--iso-opacity", "1"], "one --iso-opacity per"),
                         ([f"--iso={v}" for v in (-0.2, -0.1, 0.0, 0.1, 0.2)], "at most 4 surfaces"),
                         (["--iso=-0.1", "--iso", "9"], "iso 9 is outside"),
                         (["--iso=-0.1", "--iso", "0.1", "--budget-ms", "50"], "takes one --iso")):
        assert main(["render", "proc:sphere@32", *bad, "-o", str(out)]) == 2
        assert message in capsys.readouterr().err, bad


def test_render_clipped_and_capped(tmp_path, capsys):
    """--clip-plane (repeatable), --crop-box and --cap reach the render; a bad plane is refused naming it."""
    out = tmp_path / "cut.npz"
    assert main(["render", "proc:sphere@32", "--eye", "0,0,2", "--size", "33x33", "--outputs", "mask,depth,cap",
                 "--clip-plane", "0,0,0.1,0,0,-1", "--clip-plane=0,0,-5,0,0,1", "--crop-box=-1,-1,-1,1,1,1",
                 "--cap", "below", "-o", str(out)]) == 0
    frame = FrameBuffers.load_npz(out)
    assert abs(float(frame.depth[16, 16]) - 1.9) < 1e-4 and float(frame.cap[16, 16, 0]) == 1.0
    capsys.readouterr()
    assert main(["render", "proc:sphere@32", "--clip-plane", "0,0,0,0,0,0", "-o", str(out)]) == 2
    assert "clip.planes[0].normal must be a nonzero vector" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "proc:sphere@32", "--clip-plane", "0,0,0,1", "-o", str(out)])


def test_serve_refuses_replicas_beyond_loopback_unless_a_reverse_proxy_fronts_them(monkeypatch):
    """Ray Serve's proxy bounds neither headers nor TLS handshakes: `isosr serve --replicas` beyond
    loopback says so and stops before Ray starts; --behind-proxy goes only with --replicas."""
    import isosr_cli.serve_cmd as serve_cmd

    monkeypatch.setenv("ISOSR_TOKEN", "correct-horse-battery")
    with pytest.raises(SystemExit, match="Ray Serve's proxy, which bounds neither header size and time, TLS"):
        main(["serve", "--replicas", "2", "--host", "0.0.0.0", "--insecure"])
    with pytest.raises(SystemExit, match="go with --replicas N"):
        main(["serve", "--behind-proxy"])
    started = []
    monkeypatch.setattr(serve_cmd, "check_replica_exposure", lambda host, accepted: started.append((host, accepted)))
    monkeypatch.setitem(sys.modules, "isosr_server.cluster", None)  # no Ray: stop right after the check
    with pytest.raises(SystemExit, match="needs Ray Serve"):
        main(["serve", "--replicas", "2", "--host", "0.0.0.0", "--insecure", "--behind-proxy"])
    assert started == [("0.0.0.0", True)]
