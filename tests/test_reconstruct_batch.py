"""One reconstruction call for the frames of several streams (:meth:`Reconstructor.reconstruct_batch`,
issue 50): each stream's frames equal those it makes alone (within float rounding at another batch
size), streams that continue and streams that cut form their own calls, and a frame that fails its
checks is its own stream's error, its state kept as it was (read at once) or started over (read late)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import DEVICE

from isosr_net.inference import InputChecks
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, Reconstructor
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
