"""One reconstruction call for the frames of several streams (:meth:`Reconstructor.reconstruct_batch`,
issue 50): each stream's frames equal those it makes alone (within float rounding at another batch
size), streams that continue and streams that cut form their own calls, and a frame that fails its
checks is its own stream's error, its state kept as it was (read at once) or started over (read late)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import DEVICE

from isosr_net import reconstructor as reconstructor_module
from isosr_net.inference import InputChecks
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, GraphCache, Reconstructor, graph_chunks
from isosr_render import Renderer, RenderRequest, parse_procedural
from isosr_render.camera import orbit_path
from isosr_render.shading import ShadingParams

W, H, AO_RAYS = 48, 32, 2
STREAMS = 3


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer(parse_procedural("proc:cloud@32"), DEVICE)


def rendered(renderer: Renderer, stream: int, t: int, cut: bool = False):
    """Frame ``t`` of a stream's orbit, with flow against its previous camera unless ``cut``."""
    path = orbit_path(t + 1, yaw0=20.0 + 40.0 * stream, yaw_step=5.0, pitch=25.0, distance=1.3)
    prev = None if t == 0 or cut else path[t - 1]
    outputs = ("mask", "normal", "depth", "ao", "position") + (("flow",) if prev is not None else ())
    return renderer.render(path[t], RenderRequest(W, H, 0.5, outputs, prev_camera=prev, ao_samples=AO_RAYS,
                                                  seed=7 * stream + t))


def twins(n: int) -> list[Reconstructor]:
    template = Reconstructor.served(DEFAULT_RECON_MODEL, DEVICE, "fp32")
    return [template.own() for _ in range(n)]


def assert_close_frames(got, expected) -> None:
    for name in ("mask", "normal", "depth", "ao", "color"):
        torch.testing.assert_close(getattr(got, name), getattr(expected, name), rtol=1e-5, atol=1e-5, msg=name)


def test_a_batch_equals_each_stream_alone_and_a_cut_forms_its_own_call(renderer):
    alone, together = twins(STREAMS), twins(STREAMS)
    for t in range(3):
        frames = [rendered(renderer, k, t, cut=(k == 1 and t == 2)) for k in range(STREAMS)]
        expected = [net.reconstruct(f, AO_RAYS, 1, ShadingParams()) for net, f in zip(alone, frames)]
        got = Reconstructor.reconstruct_batch(together, frames, AO_RAYS, 1, ShadingParams())
        for g, e in zip(got, expected):
            assert not isinstance(g, Exception), g
            assert_close_frames(g, e)
        for a, b in zip(alone, together):  # the state each stream carries on
            torch.testing.assert_close(b.previous, a.previous, rtol=1e-5, atol=1e-5)


def test_the_streams_rays_accumulate_in_one_launch_a_call_and_each_keeps_its_own_state(renderer, monkeypatch):
    """The streams' ray histories join (issue 50): one accumulation over all their frames per network
    call, the first frames' (no history) and the next ones' alike; a stream that cuts has its own call.
    After it, each stream's output and history are of its own memory: one that stops making frames
    holds none of its batch mates'."""
    from isosr_net import ray_history

    sizes = []
    accumulate = ray_history.accumulate_rays
    monkeypatch.setattr(ray_history, "accumulate_rays",
                        lambda ao, *a, **k: (sizes.append(ao.shape[0]), accumulate(ao, *a, **k))[1])
    nets = twins(STREAMS)
    for t in range(3):
        frames = [rendered(renderer, k, t, cut=(k == 1 and t == 2)) for k in range(STREAMS)]
        Reconstructor.reconstruct_batch(nets, frames, AO_RAYS, 1, ShadingParams())
    assert sizes == [STREAMS, STREAMS, STREAMS - 1, 1]
    held = [{t.untyped_storage().data_ptr() for t in (net.previous, *net.history.tensors())} for net in nets]
    assert all(not (a & b) for i, a in enumerate(held) for b in held[i + 1:]), "a stream holds another's memory"


def test_a_frame_that_fails_its_checks_is_its_streams_error_only(renderer):
    nets, reference = twins(STREAMS), twins(1)[0]
    first = [rendered(renderer, k, 0) for k in range(STREAMS)]
    Reconstructor.reconstruct_batch(nets, first, AO_RAYS, 1, ShadingParams())
    reference.reconstruct(first[2], AO_RAYS, 1, ShadingParams())
    kept = nets[1].previous.clone()
    second = [rendered(renderer, k, 1) for k in range(STREAMS)]
    second[1].depth = second[1].depth.clone()
    second[1].depth[0, 0] = float("nan")
    got = Reconstructor.reconstruct_batch(nets, second, AO_RAYS, 1, ShadingParams())
    assert isinstance(got[1], ValueError) and "NaN" in str(got[1])
    assert torch.equal(nets[1].previous, kept), "the refused frame's stream keeps its state"
    assert_close_frames(got[2], reference.reconstruct(second[2], AO_RAYS, 1, ShadingParams()))
    assert not isinstance(got[0], Exception)


def test_checks_read_later_keep_the_state_and_a_failure_starts_the_stream_over(renderer):
    """The service's way (:meth:`Reconstructor.settle_checks_later`): no wait for the device; a frame whose
    checks fail gives its error to whoever reads them, and its stream's next frame starts over as after a
    cut (equal to a fresh stream's), where one that passed goes on carrying its state."""
    net, fresh = twins(1)[0], twins(1)[0]

    def later(frame):
        net.defer_checks()
        net.reconstruct(frame, AO_RAYS, 1, ShadingParams())
        return net.settle_checks_later()
    assert later(rendered(renderer, 0, 0)).error() is None and net.previous is not None
    poisoned = rendered(renderer, 0, 1)
    poisoned.depth = poisoned.depth.clone()
    poisoned.depth[0, 0] = float("nan")
    error = later(poisoned).error()
    assert isinstance(error, ValueError) and "NaN" in str(error)
    third = rendered(renderer, 0, 2)
    assert_close_frames(net.reconstruct(third, AO_RAYS, 1, ShadingParams()),
                        fresh.reconstruct(third, AO_RAYS, 1, ShadingParams()))
    assert net.settle_checks_later() is None, "nothing deferred: nothing to read"


def test_a_batch_s_checks_travel_in_one_copy_and_each_stream_reads_its_own(renderer):
    """:meth:`Reconstructor.settle_checks_later_each`: a batch's checks go to the host in one copy (one event),
    each stream's its own share of it: the poisoned stream's say NaN, its batch mates' pass; a stream that
    deferred none has none."""
    nets = twins(STREAMS + 1)
    frames = [rendered(renderer, k, 0) for k in range(STREAMS)]
    frames[1].depth = frames[1].depth.clone()
    frames[1].depth[0, 0] = float("nan")
    for net in nets:
        net.defer_checks()
    for net, frame in zip(nets, frames):
        net.reconstruct(frame, AO_RAYS, 1, ShadingParams())
    late = Reconstructor.settle_checks_later_each(nets)
    assert late[STREAMS] is None
    assert [checks.error() is None for checks in late[:STREAMS]] == [True, False, True]
    assert "NaN" in str(late[1].error())
    assert len({checks.values.untyped_storage().data_ptr() for checks in late[:STREAMS]}) == 1, "one copy"


class Unreached:
    """A device event not reached until ``reached`` is set; a wait for it is counted."""

    def __init__(self):
        self.reached, self.waits = False, 0

    def query(self) -> bool:
        return self.reached

    def synchronize(self) -> None:
        self.waits += 1
        self.reached = True


def test_a_frame_asked_for_before_the_device_reached_the_last_checks_does_not_wait(renderer, monkeypatch):
    """A stream's next frame while its failing frame's checks are still on their way (frames in flight) is
    made at once, on the state as kept, and its output checked too: here the kept state's NaN reaches it, a
    clear error; the first frame after the device reached the failing checks starts over."""
    net, fresh, event = twins(1)[0], twins(1)[0], Unreached()

    def later(frame):
        net.defer_checks()
        net.reconstruct(frame, AO_RAYS, 1, ShadingParams())
        return net.settle_checks_later()
    later(rendered(renderer, 0, 0))
    poisoned = rendered(renderer, 0, 1)
    poisoned.depth = poisoned.depth.clone()
    poisoned.depth[0, 0] = float("nan")
    read_later = InputChecks.read_later
    monkeypatch.setattr(InputChecks, "read_later", lambda checks: dataclasses.replace(read_later(checks), ready=event))
    late = later(poisoned)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="the output, over a state kept before"):
        net.reconstruct(rendered(renderer, 0, 2), AO_RAYS, 1, ShadingParams())
    assert event.waits == 0, "made at once, carrying the state as kept"
    event.reached = True
    fourth = rendered(renderer, 0, 3)
    assert_close_frames(net.reconstruct(fourth, AO_RAYS, 1, ShadingParams()),
                        fresh.reconstruct(fourth, AO_RAYS, 1, ShadingParams()))
    assert "NaN" in str(late.error())


def test_graph_chunks_are_powers_of_two_that_make_up_the_batch():
    assert (graph_chunks(1), graph_chunks(9), graph_chunks(16), graph_chunks(41)) == ([1], [8, 1], [16], [16, 16, 8, 1])
    for batch in range(1, 70):
        chunks = graph_chunks(batch)
        assert sum(chunks) == batch and chunks == sorted(chunks, reverse=True), chunks
        assert all(c <= 16 and c & (c - 1) == 0 for c in chunks), chunks
        assert len(chunks) - chunks.count(16) == len(set(chunks) - {16}), chunks  # each smaller size once
    with pytest.raises(ValueError, match="power of two"):
        graph_chunks(4, largest=6)
    with pytest.raises(ValueError, match="batch >= 1"):
        graph_chunks(0)


def test_a_batch_graph_is_captured_at_its_key_s_second_use():
    cache = GraphCache(max_graphs=2, capture_at=2)
    assert [cache.due("a"), cache.due("a")] == [False, True]
    cache.add("a", "graph", 1)
    assert cache.use("a") == "graph"
    assert [cache.due("b"), cache.due("c"), cache.due("d")] == [False] * 3
    assert not cache.due("b"), "uses are remembered of the most recent keys only"
    assert GraphCache().due("x"), "by default a key is captured at its first use"


def graphed_batches_equal_plain(renderer: Renderer, streams: int, steps: int) -> list[Reconstructor]:
    """``steps`` frames of ``streams`` streams made in batches through the batch graphs' path (its replay as the
    test patches it) and without: each frame, and the state each stream carries after it, equal. Returns the
    streams of the graphs' path."""
    plain, graphed = twins(streams), twins(streams)
    for net in graphed:
        net.batch_graphs = True
    for t in range(steps):
        frames = [rendered(renderer, k % STREAMS, t) for k in range(streams)]
        expected = Reconstructor.reconstruct_batch(plain, frames, AO_RAYS, 1, ShadingParams())
        got = Reconstructor.reconstruct_batch(graphed, frames, AO_RAYS, 1, ShadingParams())
        for g, e in zip(got, expected):
            assert_close_frames(g, e)
        for a, b in zip(plain, graphed):
            torch.testing.assert_close(b.previous, a.previous, rtol=1e-5, atol=1e-5)
    return graphed


def test_batch_graphs_run_a_batch_in_chunks_that_equal_one_call(renderer, monkeypatch):
    """batch_graphs' chunks (:func:`graph_chunks`; a chunk's replay needs CUDA: here each runs as it is): 7
    streams go in chunks of 4, 2 and 1, each given its slice of the batch; the frames and the state each
    stream carries equal those of one call."""
    streams, chunked = 7, []
    monkeypatch.setattr(Reconstructor, "_replay",
                        lambda self, work, args, cache, pool: (chunked.append(args[0].shape[0]), work(*args))[1])
    graphed = graphed_batches_equal_plain(renderer, streams, 2)
    assert chunked == [4, 2, 1] * 2
    # larger frames take smaller chunks, so that all of a size's graphs fit the bound; past it, none
    frames = [rendered(renderer, k % STREAMS, 2) for k in range(streams)]
    for bound, chunks in ((2 * 3 * W * H, [2, 2, 2, 1]), (W * H, [])):
        chunked.clear()
        monkeypatch.setattr(reconstructor_module, "MAX_BATCH_GRAPH_PIXELS", bound)
        Reconstructor.reconstruct_batch(graphed, frames, AO_RAYS, 1, ShadingParams())
        assert chunked == chunks


class ReplayOnCPU:
    """A CUDA graph's stand-in on CPUs: made by a capture of ``work``, its outputs the tensors that first call
    returned, which each replay overwrites in place with a new call's (as a graph writes its own)."""

    def __init__(self, work):
        self.work, self.outs = work, work()

    def replay(self) -> None:
        for mine, new in zip(self.outs, self.work()):
            if mine is not None:
                mine.copy_(new)


@pytest.mark.skipif(DEVICE != "cpu", reason="the replay's logic with a stand-in graph, on CPUs: on a GPU the chunks' "
                    "convolutions may take other algorithms than one call's (beyond 1e-5); "
                    "test_the_batch_graphs_replay_the_network_s_frames replays real graphs there")
def test_batch_graphs_replayed_as_captured_equal_one_call_chunk_after_chunk(renderer, monkeypatch):
    """The replay's logic on CPUs (the graph a stand-in, :class:`ReplayOnCPU`): 33 streams in chunks 16, 16
    and 1 (one graph replayed twice in a batch, each chunk's results copied out before the next), captured at
    a shape's second use, frame after frame equal to one call, each stream's state its own."""
    monkeypatch.setattr(Reconstructor, "_capture",
                        lambda self, work, pool, restore=None: (graph := ReplayOnCPU(work), graph.outs))
    graphed = graphed_batches_equal_plain(renderer, 33, 4)
    # the first frames' chunk of 16 (its second use: the same batch), the carried frames' 16 (t = 1) and 1 (t = 2)
    assert len(graphed[0]._batch_captured) == 3


@pytest.mark.skipif(DEVICE != "cuda", reason="CUDA graphs: ISOSR_TEST_DEVICE=cuda, on the GPU machine")
def test_the_batch_graphs_replay_the_network_s_frames(renderer):
    """The service's network on a GPU (fused kernels, batch graphs shared by its streams): a batch of five
    streams, eager at a key's first use, then captured and replayed, equals the same batches made
    without graphs, frame after frame."""
    served = Reconstructor.served(DEFAULT_RECON_MODEL, DEVICE, "fp16")
    if not served.batch_graphs:
        pytest.skip("the fused kernels do not run here (Triton)")
    plain = Reconstructor(DEFAULT_RECON_MODEL, DEVICE, "fp16", channels_last=True, fused=True)
    streams = 5
    graphed, alone = [served.own() for _ in range(streams)], [plain.own() for _ in range(streams)]
    for t in range(4):
        frames = [rendered(renderer, k % STREAMS, t) for k in range(streams)]
        expected = Reconstructor.reconstruct_batch(alone, frames, AO_RAYS, 1, ShadingParams())
        got = Reconstructor.reconstruct_batch(graphed, frames, AO_RAYS, 1, ShadingParams())
        for g, e in zip(got, expected):
            assert not isinstance(g, Exception), g
            for name in ("mask", "normal", "depth", "ao", "color"):
                torch.testing.assert_close(getattr(g, name), getattr(e, name), rtol=1e-3, atol=1e-3, msg=name)
    assert len(served._batch_captured) == 2, "chunks 4 and 1 of the carried frames, shared by the streams"
    assert all(net._batch_captured is served._batch_captured for net in graphed)


def test_only_ungraphed_twins_of_one_network_batch(renderer):
    one, other = twins(1)[0], twins(1)[0]
    frame = rendered(renderer, 0, 0)
    with pytest.raises(ValueError, match="twins of one network"):
        Reconstructor.reconstruct_batch([one, other], [frame, frame], AO_RAYS)


def test_the_runners_batch_renders_each_stream_then_runs_the_network_once(renderer, monkeypatch):
    """ReconstructRunner.make_batch where the network is batched (GPUs; here the CPU let in): each
    stream's frames equal its runner's alone, with a cut in one stream; one network call a batch."""
    from isosr_net.methods import FrameMethod, Networks, make_runner
    from isosr_net.methods import reconstruct as recon_module

    monkeypatch.setattr(recon_module, "BATCHED_NETWORK_DEVICES", (DEVICE,))
    calls = []
    batch = Reconstructor.reconstruct_batch
    monkeypatch.setattr(Reconstructor, "reconstruct_batch",
                        staticmethod(lambda nets, *a, **k: (calls.append(len(nets)), batch(nets, *a, **k))[1]))
    method = FrameMethod.of("reconstruct", ao_rays=AO_RAYS)
    networks = Networks(lambda cls, *args: cls.served(*args))  # the service's: ungraphed on CUDA too
    alone = [make_runner(method, renderer, 0.5, W, H, networks=networks.fork()) for _ in range(STREAMS)]
    together = [make_runner(method, renderer, 0.5, W, H, networks=networks.fork()) for _ in range(STREAMS)]
    paths = [orbit_path(3, yaw0=20.0 + 40.0 * k, yaw_step=5.0, pitch=25.0, distance=1.3) for k in range(STREAMS)]
    for t in range(3):
        prevs = [None if t == 0 or (k == 1 and t == 2) else paths[k][t - 1] for k in range(STREAMS)]
        expected = [r.frame(p[t], q) for r, p, q in zip(alone, paths, prevs)]
        got = type(together[0]).make_batch([(r, p[t], q) for r, p, q in zip(together, paths, prevs)])
        for g, e in zip(got, expected):
            assert not isinstance(g, Exception), g
            assert g.continued == e.continued
            assert_close_frames(g.buffers, e.buffers)
    assert calls == [STREAMS] * 3
