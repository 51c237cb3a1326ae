"""Camera sequences: the per-frame render requests of a path, each frame's previous camera set.

    for camera, request in sequence_requests(cameras, 96, 96, iso, ("mask", "normal", "depth", "flow")):
        frame = renderer.render(camera, request)

The first frame has no previous frame: its ``prev_camera`` is None and it drops ``flow``
(flow is defined only against a previous camera). Every later frame's ``prev_camera`` is
the camera before it.
"""

from __future__ import annotations

from collections.abc import Sequence

from isosr_render.camera import Camera
from isosr_render.renderer import RenderRequest


def sequence_cameras(cameras: Sequence[Camera]) -> list[tuple[Camera, Camera | None]]:
    """``(camera, previous camera)`` per frame of a path, the first without a previous one."""
    return list(zip(cameras, [None, *cameras[:-1]]))


def sequence_requests(cameras: Sequence[Camera], width: int, height: int, iso: float,
                      outputs: tuple[str, ...], **options) -> list[tuple[Camera, RenderRequest]]:
    """``(camera, request)`` per frame of ``cameras``, with the previous frame's camera for flow.

    Args:
        cameras: the path, in order.
        width, height, iso, outputs: as in :class:`RenderRequest`; the first frame omits ``flow``.
        options: further :class:`RenderRequest` fields (spp, ao_samples, seed, ...), the same
            for every frame; ``prev_camera`` is set here.

    Raises:
        ValueError: ``options`` names ``prev_camera``, or what :class:`RenderRequest` refuses.
    """
    if "prev_camera" in options:
        raise ValueError("sequence_requests sets prev_camera itself (the camera before each frame)")
    first_outputs = tuple(o for o in outputs if o != "flow")
    return [(camera, RenderRequest(width, height, iso, outputs if prev else first_outputs, prev_camera=prev,
                                   **options))
            for camera, prev in sequence_cameras(cameras)]
