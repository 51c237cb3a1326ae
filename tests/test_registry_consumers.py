"""Every consumer reads the registry (issue 46): a method registered in a test appears in the
Pareto study's grid, the report's plot colors and the budget policy's candidates."""

from __future__ import annotations

import pytest

from isosr_bench import bench_pareto
from isosr_bench.report import plot_colors
from isosr_net.budget import default_candidates
from isosr_net.methods import RUNNERS, FrameMethod, register_runner
from isosr_net.methods.atrous import ATrousRunner


@pytest.fixture
def throwaway():
    """The a-trous runner registered anew as ``throwaway``, with a color of its own; removed after."""
    @register_runner("throwaway")
    class ThrowawayRunner(ATrousRunner):
        plot_color = "C9"

    yield ThrowawayRunner
    del RUNNERS["throwaway"]


def test_a_registered_method_appears_in_the_pareto_grid_the_plots_and_the_candidates(throwaway):
    smoke, study = bench_pareto.methods(True, "cpu", {}), bench_pareto.methods(False, "cpu", {})
    assert [m for m in smoke if m.kind == "throwaway"] == [FrameMethod.of("throwaway", ao_rays=2)]
    assert [m.ao_rays for m in study if m.kind == "throwaway"] == [1, 2, 4]
    assert plot_colors()["throwaway"] == "C9"
    candidates = default_candidates("cpu")
    for n in (1, 2, 4):  # each right after the a-trous candidate of the same rank
        atrous = candidates.index(FrameMethod.of("atrous", ao_rays=n))
        assert candidates[atrous + 1] == FrameMethod.of("throwaway", ao_rays=n)


def test_kinds_without_a_color_are_not_plotted():
    assert "buffers" not in plot_colors() and set(plot_colors()) < set(RUNNERS)
