"""Every way to make a frame: one contract (:mod:`isosr_net.methods.base`), one module per way,
a registry by name (:data:`RUNNERS`):

    full         ray cast at full resolution with N AO rays (0: none) and M rays per pixel
    atrous       full resolution, few AO rays smoothed by the a-trous filter
    svgf         full resolution, few AO rays accumulated over frames along the flow and filtered
    oidn         full resolution, few AO rays shaded and denoised by Intel Open Image Denoise
                 (optional: where ``pyoidn`` is installed)
    reconstruct  full resolution, few (or no) AO rays reconstructed by a trained network
    upscale      a low-res ray cast upscaled by interpolation
    network      a low-res ray cast upscaled by a trained network (which infers AO)
    buffers      the low-res ray cast itself, unshaded (for a client that upscales)

Every runner computes only the buffers its method needs (plus those a caller asks to ``keep``)
and reports per-stage times:

    runner = make_runner(FrameMethod.of("reconstruct", ao_rays=1, precision="fp16"), renderer, iso, 1920, 1080)
    result = runner.frame(camera, prev_camera)  # FrameResult: buffers (color, mask, normal, ...), times
    result.buffers.color                         # (H, W, 3) in [0, 1]

``prev_camera=None`` starts a new sequence (a recurrent network forgets its previous output).
A new method is one module here (a registered `FrameRunner` with its label, and its knobs with
their defaults and bounds as a :class:`MethodOptions` subclass, found without a list to edit),
its filter under :mod:`isosr_net.filters`, and its test class in ``tests/test_method_contract.py`` (the shared contract runs every registered method); the CLI,
the service's modes, the viewer, the Pareto study and the budget policy read the registry. A kind that needs an optional package says why it cannot run
where it is missing (:func:`unavailable_kinds`); making its runner raises that reason.
"""

from importlib import import_module
from pkgutil import iter_modules

from isosr_net.methods.base import (DRAW_SEEDS, FIRST_TEMPORAL_SEED, MAX_FACTOR, RUNNERS, FrameMethod, FrameResult,
                                    FrameRunner, FrameStream, MethodOptions, Networks, finish_steps, make_runner,
                                    parse_method, register_runner, run_sequence, unavailable_kinds)

# The registry's order is the menus' order: these first, then any other module here by name (a
# new method is a module of this package, nothing else to edit).
METHOD_MODULES = ("full", "atrous", "svgf", "oidn", "reconstruct", "upscale", "network", "buffers")
_found = sorted(m.name for m in iter_modules(__path__) if m.name != "base")
for _name in [*METHOD_MODULES, *(n for n in _found if n not in METHOD_MODULES)]:
    import_module(f"{__name__}.{_name}")

from isosr_net.methods.upscale import upscale_classic  # noqa: E402 (after the registry is filled)

__all__ = ["DRAW_SEEDS", "FIRST_TEMPORAL_SEED", "MAX_FACTOR", "METHOD_MODULES", "RUNNERS", "FrameMethod", "FrameResult",
           "FrameRunner", "FrameStream", "MethodOptions", "Networks", "finish_steps", "make_runner", "register_runner",
           "parse_method", "run_sequence", "unavailable_kinds", "upscale_classic"]
