"""The routes alone, without uvicorn and without loading a model: `TestClient` on `create_app`
(no lifespan runs outside ``with TestClient(...)``), state replaced through `app.dependency_overrides`."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from isosr_server.api.deps import get_catalog, get_engine, is_ready
from isosr_server.app import create_app
from isosr_server.core.config import Settings
from isosr_server.volumes import VolumeInfo

TOKEN = "correct-horse-battery"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class FakeEngine:
    upscale_factor = 3

    def model_info(self) -> dict:
        return {"upscale_factor": self.upscale_factor, "model": "fake_model"}

    def recon_info(self) -> dict:
        return {"model": "fake_recon", "max_ao_rays": 5}


def test_routes_run_on_fake_state_without_a_model():
    app = create_app(Settings())
    catalog = SimpleNamespace(names=lambda: ["fake"], info=lambda n: VolumeInfo(n, (2, 3, 4), (0.0, 1.0), 0.5))
    app.dependency_overrides |= {get_engine: FakeEngine, get_catalog: lambda: catalog, is_ready: lambda: True}
    client = TestClient(app)
    model = client.get("/v2/models/isosr").json()
    assert model["name"] == "isosr" and model["parameters"]["upscale_factor"] == 3
    assert all(t["datatype"] == "FP32" for t in model["inputs"] + model["outputs"])
    assert {t["name"]: t["parameters"]["accepted_datatypes"] for t in model["inputs"]}["depth"] == ["FP32", "FP16"]
    assert client.get("/v2/models/isosr-recon").json()["parameters"] == {"model": "fake_recon", "max_ao_rays": 5}
    assert client.get("/v1/volumes").json()["volumes"] == [{"name": "fake", "shape": [2, 3, 4],
                                                            "value_range": [0.0, 1.0], "iso": 0.5, "histogram": None,
                                                            "histogram_bins": 64, "level": None, "levels": None,
                                                            "steps": 1}]


def test_probes_need_no_token_and_the_rest_does():
    client = TestClient(create_app(Settings(token=TOKEN)))  # not started: not ready
    assert client.get("/v2/health/live").json() == {"live": True}
    ready = client.get("/v2/health/ready")
    assert (ready.status_code, ready.json()) == (503, {"ready": False})
    for path in ("/v2", "/v2/models/isosr", "/v2/models/isosr/ready", "/v1/volumes", "/metrics"):
        got = client.get(path)
        assert got.status_code == 401 and "token" in got.json()["error"], path
    meta = client.get("/v2", headers=AUTH).json()
    assert meta["name"] == "isosr" and meta["version"] and "isosr-view" in meta["extensions"]
    loading = client.get("/v2/models/isosr", headers=AUTH)
    assert (loading.status_code, loading.json()["error"]) == (503, "the model is loading")
    assert client.get("/v2/models/isosr-recon/ready", headers=AUTH).json() == {"name": "isosr-recon", "ready": False}


def test_docs_pages_are_off_and_the_schema_is_served():
    client = TestClient(create_app(Settings()))
    assert client.get("/docs").status_code == 404 and client.get("/redoc").status_code == 404
    paths = client.get("/openapi.json").json()["paths"]
    assert "/v1/upscale" in paths and "/v2/models/isosr-recon" in paths


def test_listed_and_loaded_volumes_agree_on_the_suggested_iso(tmp_path):
    """The manifest's Otsu threshold (here unlike the voxels' own) is the one suggestion, loaded or not."""
    data = np.linspace(0.0, 200.0, 20 * 16 * 12, dtype=np.float32).reshape(20, 16, 12)
    np.save(tmp_path / "ramp.npy", data)
    entry = {"name": "ramp", "file": "ramp.npy", "shape_xyz": [20, 16, 12], "value_range": [0.0, 200.0],
             "otsu_iso_normalized": 0.3027}
    (tmp_path / "volumes.json").write_text(json.dumps([entry]))
    client = TestClient(create_app(Settings(volumes=tmp_path)))
    listed = {v["name"]: v for v in client.get("/v1/volumes").json()["volumes"]}["ramp"]
    loaded = client.get("/v1/volumes/ramp").json()
    assert listed["iso"] == loaded["iso"] == pytest.approx(0.3027 * 200.0)
    too_big = client.get("/v1/volumes/proc:sphere@129")
    assert too_big.status_code == 400 and "at most 128" in too_big.json()["error"]
