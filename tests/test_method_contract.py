"""Every registered frame method kept to the one contract (:class:`method_contract.MethodContract`):
a class per method that names it and its options. A new method needs its class here
(``test_every_registered_kind_has_a_contract_test`` fails without one).

On a GPU machine ``ISOSR_TEST_DEVICE=cuda pytest tests/test_method_contract.py`` runs them there.
"""

from __future__ import annotations


from method_contract import MethodContract

from isosr_net.methods import RUNNERS, FrameMethod, unavailable_kinds


class TestFull(MethodContract):
    method = FrameMethod.of("full", ao_rays=2)


class TestFullWithoutAO(MethodContract):
    method = FrameMethod.of("full")


class TestFullSupersampled(MethodContract):
    method = FrameMethod.of("full", ao_rays=1, spp=2)


class TestATrous(MethodContract):
    method = FrameMethod.of("atrous", ao_rays=2)


class TestSVGF(MethodContract):
    method = FrameMethod.of("svgf", ao_rays=1)


class TestOIDN(MethodContract):
    method = FrameMethod.of("oidn", ao_rays=1, quality="fast")


class TestReconstruct(MethodContract):
    method = FrameMethod.of("reconstruct", ao_rays=2)


class TestReconstructWithoutAO(MethodContract):
    method = FrameMethod.of("reconstruct", ao_rays=0)


class TestReconstructX2(MethodContract):
    method = FrameMethod.of("reconstruct", ao_rays=2, factor=2)


class TestUpscale(MethodContract):
    method = FrameMethod.of("upscale", factor=2, interpolation="bicubic")


class TestNetwork(MethodContract):
    method = FrameMethod.of("network", factor=2)


class TestBuffers(MethodContract):
    method = FrameMethod.of("buffers", factor=2)


# The shipped models (cheap at this size on the CPU), as the service and the study run them.
class TestReconstructShipped(MethodContract):
    method = FrameMethod.of("reconstruct", ao_rays=2)
    shipped_model = True


class TestNetworkShipped(MethodContract):
    method = FrameMethod.of("network", factor=4)
    shipped_model = True


def contract_classes(cls=MethodContract) -> list[type[MethodContract]]:
    """The contract's test classes (subclasses at any depth)."""
    return [c for sub in cls.__subclasses__() for c in (sub, *contract_classes(sub))]


def test_every_registered_kind_has_a_contract_test():
    covered = {c.method.kind for c in contract_classes() if c.__name__.startswith("Test")}
    runnable = set(RUNNERS) - set(unavailable_kinds())
    assert runnable <= covered, f"frame method kinds without a MethodContract test class: {sorted(runnable - covered)}"
    # kinds that cannot run here (an optional package missing) have theirs too, skipped with the reason
    assert set(RUNNERS) <= covered, f"without a MethodContract test class: {sorted(set(RUNNERS) - covered)}"
