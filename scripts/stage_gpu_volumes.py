"""Copy ../shared/volumes into .vols/ (git-ignored) small enough to travel to the GPU machine.

The device run carries at most 64 MiB and the GPU kit takes 46 MiB of it, so the one large
file, the chest CT's uncompressed `.raw`, travels as gzipped NIfTI; `volumes.json` names it.
Names given stage those volumes only (beside the kit's part b, one volume fits: bonsai, 2.6 MB).
    python scripts/stage_gpu_volumes.py [NAME ...] && echo /.vols/ >> .git/info/exclude
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import nibabel as nib
import numpy as np

from isosr_render.catalog import shared_volumes_dir
from isosr_render.volume_io import load_volume

root = Path(__file__).resolve().parents[1]
source, target = shared_volumes_dir(), root / ".vols"
shutil.rmtree(target, ignore_errors=True)
target.mkdir()
manifest = [entry for entry in json.loads((source / "volumes.json").read_text())
            if len(sys.argv) < 2 or entry["name"] in sys.argv[1:]]
for entry in manifest:
    path = source / entry["file"]
    if path.suffix == ".dat":
        volume = load_volume(path)
        lo, hi = volume.value_range
        values = np.rint(volume.data * (hi - lo) + lo).astype(entry["dtype"])
        image = nib.Nifti1Image(values, np.diag([*volume.spacing, 1.0]))
        image.header.set_zooms(volume.spacing)
        entry["file"] = f"{entry['name']}.nii.gz"
        nib.save(image, target / entry["file"])
        assert np.array_equal(load_volume(target / entry["file"]).data, volume.data)
    elif path.parent != source:
        shutil.copytree(path.parent, target / path.parent.name)
    else:
        shutil.copy(path, target / path.name)
(target / "volumes.json").write_text(json.dumps(manifest, indent=1))
print(f"staged {len(manifest)} volumes in {target}")
