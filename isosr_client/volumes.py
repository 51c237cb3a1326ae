"""A server's volumes over HTTP: their listing and orthogonal slices.

    from isosr_client.volumes import slice_remote
    rgb = slice_remote("http://127.0.0.1:8000", "bonsai", "z", 40, iso=80.0)   # (H, W, 3) uint8

The slices are the server's (:func:`isosr_render.slices.slice_image`): grey levels over the
volume's range at its physical aspect, with the iso contour drawn where ``iso`` (data units) is
given.
"""

from __future__ import annotations

import json
from pathlib import Path
from urllib.parse import quote, urlencode

import numpy as np

from isosr_client.view import http_call
from isosr_render.image_codec import decode_image


def volumes_remote(url: str, token: str | None = None, cafile: str | Path | None = None,
                   timeout: float = 60.0) -> list[dict]:
    """The server's volumes (``GET /v1/volumes``): name, shape, value range, suggested iso, or why
    one cannot be opened (``error``)."""
    return json.loads(http_call(url, "/v1/volumes", token, cafile, timeout)[1])["volumes"]


def slice_remote(url: str, volume: str, axis: str, index: int, iso: float | None = None, token: str | None = None,
                 cafile: str | Path | None = None, timeout: float = 60.0) -> np.ndarray:
    """The slice of ``volume`` across ``axis`` (``x``, ``y`` or ``z``) at voxel ``index``, with the
    contour of ``iso`` (data units; None: none), as (H, W, 3) uint8 RGB.

    Raises:
        ServerError: the server refused it (an unknown volume, an index outside it, an iso
            outside its value range), with its reason.
    """
    query = urlencode({"index": index} | ({} if iso is None else {"iso": iso}))
    _, png = http_call(url, f"/v1/volumes/{quote(volume, safe='')}/slices/{axis}?{query}", token, cafile, timeout)
    return decode_image(png)
