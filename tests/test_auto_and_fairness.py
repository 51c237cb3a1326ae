"""The service's ``auto`` mode (the budget policy per session share) and fair device time (a
maximal frame runs in slices that other sessions' frames interleave with), through a real server
on loopback, plus the auto policy's caching on its own."""

from __future__ import annotations

import json
import logging
import math
import threading
import time

import pytest

from isosr_net import budget
from isosr_net.budget import BudgetChoice, CostTable, default_candidates, method_key
from isosr_net.methods import FrameMethod, Networks, finish_steps, make_runner, run_sequence
from isosr_net.reconstructor import RECON_X2_MODEL
from isosr_render import orbit
from isosr_render.clip import Clip
from isosr_render.images import to_uint8
from isosr_server import protocol as P
from isosr_server.auto import PROBE, AutoPolicy, ProbeCache, prior_method
from isosr_server.views import expected
from server_fixtures import (DEVICE, VOLUME, H, W, assert_image, cam, frame, lib, running_server,  # noqa: F401
                             send, server_settings, session)


@pytest.fixture(scope="module")
def srv():
    with running_server(server_settings(limits=P.Limits(max_fps=1000.0, max_messages_per_s=5000.0))) as s:
        yield s


def candidates_names(srv) -> set[str]:
    policy = srv.app.state.engine.auto
    return {m.name for m in policy.candidates}


def test_auto_is_the_default_and_names_the_method_it_chose(srv):
    with session(srv) as (ws, ready):
        assert ready.settings.mode == "auto"
        f = frame(ws)
        assert f.mode == "auto" and f.method in candidates_names(srv), f.method
        assert f.times["total"] > 0 and "render" in f.times


def test_a_choices_expectation_travels_finite_or_not_at_all():
    """A frame's expectation is a valid wire message whatever the probe measured: a PSNR of a candidate equal to
    its reference (inf) or of nothing covered (NaN), a time never measured, travel as None."""
    method = FrameMethod.of("full", ao_rays=1, spp=1)
    for ms, psnr, source in ((1.5, math.inf, "table"), (math.nan, math.nan, "prior"), (2.0, 31.5, "table")):
        choice = expected(BudgetChoice(method, ms, psnr, True, 4.0, math.nan, False, (0, 0), 0.0, ()))
        wire = P.FrameMsg(seq=0, ack=-1, mode="auto", method=method.name, width=W, height=H, encoding="jpeg",
                          times={}, nbytes=1, image=b"x", choice=choice)
        back = P.parse(P.encode(wire), P.Limits(), P.SERVER_VIEW_MESSAGES).choice
        assert back == choice and back.source == source and back.budget_ms == 4.0
        assert (back.ms, back.psnr_db) == (None if math.isnan(ms) else ms, psnr if math.isfinite(psnr) else None)


def test_other_modes_name_their_method(srv):
    """Each mode's frames name their method and carry no auto choice; nor does a still camera's refined frame."""
    expected = {"network": "x4 network fp32", "upscale": "x4 bilinear", "full": "full, AO 2, spp 1",
                "atrous": "full, AO 2, a-trous", "reconstruct": "full, AO 2, spp 1, recon fp32"}
    for mode, name in expected.items():
        with session(srv, mode=mode, ao_rays=2) as (ws, _):
            f = frame(ws)
            assert (f.method, f.choice) == (name, None)
    with session(srv, refine=True) as (ws, _):
        first, refined = frame(ws), frame(ws)
        assert first.choice is not None and refined.refined and refined.choice is None


def test_auto_offers_the_x2_reconstruction_and_serves_its_frames_at_the_full_size(srv, lib, monkeypatch):
    """With the x2 reconstruction its only candidate, the auto mode's frames are the library's: the
    render at half the sides reconstructed to the window's size, recurrent state carried."""
    policy = srv.app.state.engine.auto
    x2 = [m for m in policy.candidates if m.kind == "reconstruct" and m.factor == 2]
    assert {(m.ao_rays, m.spp) for m in x2} >= {(1, 1), (16, 1), (4, 2)}
    assert all((m.options.model, m.options.model_name, m.options.precision) == (str(RECON_X2_MODEL), "recon_x2", "fp32")
               for m in x2)
    monkeypatch.setattr(policy, "candidates", (x2[0],))
    width = W + 16  # a size no other test's choice is cached for
    cameras = [orbit(30, 20, 1.8), orbit(33, 20, 1.8), orbit(36, 20, 1.8)]
    expected = run_sequence(make_runner(x2[0], lib.renderer, lib.iso, width, H, networks=Networks.eager()), cameras)
    with session(srv, width=width, height=H) as (ws, _):
        for i, yaw in enumerate((30, 33, 36)):
            if i:
                send(ws, cam(yaw, seq=i))
            f = frame(ws)
            assert (f.mode, f.method, f.width, f.height) == ("auto", "x2, AO 1, spp 1, recon_x2 fp32", width, H)
            assert_image(f.image, to_uint8(expected[i].color))


def test_auto_budget_is_the_sessions_share_of_the_servers_gpu_share():
    """A replica with a quarter of a GPU gives a frame a quarter of a whole GPU's budget; a share
    outside (0, 1] is refused by the policy and the settings alike."""
    from isosr_server.core.config import Settings

    quarter = AutoPolicy.for_server(DEVICE, "fp32", 4, {}, 30.0, Networks(), gpu_share=0.25)
    assert quarter.budget_ms(4) == pytest.approx(1000 * 0.25 / 120)
    for bad in (0.0, -0.5, 1.5, math.nan):
        with pytest.raises(ValueError, match="gpu_share must lie in"):
            AutoPolicy(quarter.candidates, 30.0, Networks(), gpu_share=bad)
        with pytest.raises(ValueError, match="gpu_share must lie in"):
            Settings(gpu_share=bad)


def test_auto_policy_chooses_at_once_and_probes_in_the_background(lib, tmp_path):
    """The first choice of a scene and size is the prior, with no device work; the probe waits as
    steps for the engine; its choice is cached, a new session count reuses its quality and times,
    and a policy started later on the same cache file chooses without probing."""
    renderer, iso = lib.renderer, lib.iso
    cache = tmp_path / "probes.json"
    policy = AutoPolicy.for_server(DEVICE, "fp32", 4, {}, 30.0, Networks(), cache=ProbeCache(cache, "this CPU"))
    assert policy.budget_ms(1) == pytest.approx(1000 / 30) and policy.budget_ms(4) == pytest.approx(1000 / 120)
    cam = orbit(30, 20, 1.8)
    first = policy.choose(renderer, VOLUME, iso, 64, 48, cam, 1, 0.05)
    assert first.method == prior_method(policy.candidates) and first.method.name == "full, AO 0, spp 1"
    assert len(policy.pending) == 1 and not cache.exists()
    assert policy.choose(renderer, VOLUME, iso, 64, 48, cam, 1, 0.05).method == first.method
    assert len(policy.pending) == 1, "one probe per scene, size and session count"
    one = finish_steps(policy.pending.pop())
    assert isinstance(one, BudgetChoice) and one.budget_ms == pytest.approx(1000 / 30) and one.table
    assert policy.choose(renderer, VOLUME, iso, 64, 48, cam, 1, 0.05) is one, "a choice is cached"
    scene = (VOLUME, round(iso, 6), 64, 48, 0.05)
    timed = dict(policy._timings[scene])
    many = policy.choose(renderer, VOLUME, iso, 64, 48, cam, 16, 0.05)
    if policy.pending:  # the times known did not decide it: the new budget times more methods
        many = finish_steps(policy.pending.pop())
    assert many.budget_ms == pytest.approx(1000 / 480) and many is not one
    assert len(policy._quality) == 1, "a new session count probes no quality again"
    assert all(policy._timings[scene][m] == t for m, t in timed.items()), "no method is timed twice"
    later = AutoPolicy.for_server(DEVICE, "fp32", 4, {}, 30.0, Networks(), cache=ProbeCache(cache, "this CPU"))
    again = later.choose(renderer, VOLUME, iso, 64, 48, cam, 1, 0.05)
    assert again.method == one.method and again.expected_psnr == pytest.approx(one.expected_psnr)
    assert not later.pending, "a restarted server's policy reads what the probe learned"
    other = AutoPolicy.for_server(DEVICE, "fp32", 4, {}, 30.0, Networks(), cache=ProbeCache(cache, "another CPU"))
    assert other.choose(renderer, VOLUME, iso, 64, 48, cam, 1, 0.05).method == first.method and other.pending


def test_a_choice_is_held_to_what_its_frames_cost_in_service(lib, caplog):
    """A replica's first choice budgets its share of the GPU; once SERVICE_FRAMES frames of it are served, their
    device time over the probe's (the load) rescales the whole budget: a light load frees the rest of the GPU, a
    heavier one cuts it, one within DRIFT keeps the choice. The scene's load is the latest measure; a method's own
    holds for it LOAD_HOLD_S where higher: a method that proved dear is not tried again at once, a spike that one
    method met does not hold the others back, and the choice is made again once the held load lapses. Frames of a
    prior, of another method or without a positive finite time measure nothing."""
    from isosr_server.auto import DRIFT, LOAD_HOLD_S, SERVICE_FRAMES

    plain, some_ao, more_ao = FrameMethod.of("full"), FrameMethod.of("full", ao_rays=2), FrameMethod.of("full",
                                                                                                        ao_rays=8)
    times = {plain: 1.0, some_ao: 3.0, more_ao: 6.0}
    policy = AutoPolicy(tuple(times), 30.0, Networks(), gpu_share=0.5)
    cam, scene, whole = orbit(30, 20, 1.8), (VOLUME, lib.iso, 64, 48), 1000 / (2 * 30)  # 16.7 ms, 12.5 usable
    scene_key = (VOLUME, round(lib.iso, 6), 64, 48, 0.05)
    policy._quality[scene_key] = budget.QualityProbe((64, 48), {plain: 20.0, some_ao: 26.0, more_ao: 30.0}, 12.0,
                                                     True, 0.0, {})
    policy._timings[scene_key] = dict(times)  # all timed: choices without device work
    now = [0.0]
    policy.clock = lambda: now[0]

    def choose() -> BudgetChoice:
        choice = policy.choose(lib.renderer, *scene, cam, 2, 0.05)
        assert not policy.pending
        return choice

    def serve(method: FrameMethod, load: float, frames: int = SERVICE_FRAMES) -> None:
        for _ in range(frames):
            policy.served(*scene, 2, 0.05, Clip(), method, load * times[method])

    first = choose()
    assert first.method == more_ao and first.budget_ms == pytest.approx(0.5 * whole), "the share until measured"
    serve(more_ao, math.nan), serve(more_ao, 0.0), serve(more_ao, -1.0), serve(plain, 100.0)
    serve(more_ao, 1.0, SERVICE_FRAMES - 1)
    assert choose() is first, "nothing measured yet"
    with caplog.at_level(logging.DEBUG, logger="isosr.server"):
        serve(more_ao, 1.0, 1)  # the window's last frame: a load of 1, the rest of the GPU is free
    assert "1.00 times its probe's time (load 1.00, chosen at 2.00): choosing again" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="isosr.server"):
        light = choose()
    assert light.method == more_ao and light.budget_ms == pytest.approx(whole)
    assert not caplog.text, "a re-choice that keeps the method is said only when debugging"
    serve(more_ao, 3.0)  # dear in service: 18 ms a frame
    with caplog.at_level(logging.INFO, logger="isosr.server"):
        cut = choose()
    assert cut.method == some_ao and cut.budget_ms == pytest.approx(whole / 3)
    assert f"budget {whole / 3:.3g} ms: {some_ao.name}" in caplog.text, "a change of method is said"
    serve(some_ao, 0.9 * DRIFT * 3)
    assert choose() is cut, "within DRIFT of the load it was chosen for"
    now[0] = 10.0
    serve(some_ao, 1.0)  # the scene eases: its load is 1, more_ao's own 3 still holds for it (18 of 12.5 usable)
    eased = choose()
    assert eased.method == some_ao and eased.budget_ms == pytest.approx(whole) and policy.load(scene_key) == 1.0
    now[0] = LOAD_HOLD_S
    lapsed = choose()  # more_ao's own load lapsed: tried again at the scene's
    assert lapsed.method == more_ao and lapsed.budget_ms == pytest.approx(whole)
    serve(more_ao, 16.0)  # a spike (every replica probing at once): nothing fits, the fastest
    spiked = choose()
    assert spiked.method == plain and not spiked.fits
    serve(plain, 1.2)  # gone: plain's own load, not the spike, sets the budget; more_ao is held at 16
    after = choose()
    assert after.method == some_ao and after.budget_ms == pytest.approx(whole / 1.2)


def test_while_a_probe_chooses_again_a_choice_that_no_longer_fits_gives_way_at_once(lib, monkeypatch, caplog):
    """A load that cuts the budget below the choice's time starts a probe with candidates still to time; until it
    decides, frames get the best timed candidate that fits, else the prior at the cut budget (here the cheapest
    frame), not the choice that proved dear; a load that frees budget keeps the choice meanwhile."""
    from isosr_server.auto import SERVICE_FRAMES

    plain, some_ao, more_ao, most_ao = (FrameMethod.of("full", ao_rays=n) for n in (0, 2, 8, 16))
    times = {plain: 1.0, some_ao: 3.0, more_ao: 6.0, most_ao: 20.0}

    def time_candidate(runner, cameras, config, budget_ms, slice_ms=None):  # a unit, then a set time
        yield
        return times[runner.method]

    monkeypatch.setattr(budget, "_time_candidate_steps", time_candidate)
    cam, scene, scene_key = orbit(30, 20, 1.8), (VOLUME, lib.iso, 64, 48), (VOLUME, round(lib.iso, 6), 64, 48, 0.05)

    def policy_timed(known: tuple) -> AutoPolicy:
        policy = AutoPolicy((plain, some_ao, more_ao, most_ao), 30.0, Networks(), gpu_share=0.5)
        psnr = {plain: 20.0, some_ao: 26.0, more_ao: 30.0, most_ao: 34.0}
        policy._quality[scene_key] = budget.QualityProbe((64, 48), psnr, 12.0, True, 0.0, {})
        policy._timings[scene_key] = {m: times[m] for m in known}
        return policy

    def serve(policy: AutoPolicy, method: FrameMethod, load: float) -> None:
        for _ in range(SERVICE_FRAMES):
            policy.served(*scene, 2, 0.05, Clip(), method, load * times[method])

    policy = policy_timed((more_ao, most_ao))  # a probe timed these: 6 ms fits 6.25 of 8.33
    assert policy.choose(lib.renderer, *scene, cam, 2, 0.05).method == more_ao and not policy.pending
    serve(policy, more_ao, 3.0)  # 4.17 of 5.56 ms left: more_ao no longer fits; some_ao and plain untimed
    with caplog.at_level(logging.INFO, logger="isosr.server"):
        meanwhile = policy.choose(lib.renderer, *scene, cam, 2, 0.05)
        policy.choose(lib.renderer, *scene, cam, 2, 0.05)
    assert policy.pending and meanwhile.method == plain == prior_method(policy.candidates)
    said = f"2 sessions: {more_ao.name} no longer fits 5.56 ms; {plain.name} until the probe chooses"
    assert caplog.text.count(said) == 1, "said once, as the probe starts"
    assert meanwhile.budget_ms == pytest.approx(1000 / (2 * 30 * 3.0)), "the whole budget over the load"
    decided = finish_steps(policy.pending.pop())
    assert decided.method == some_ao and policy.choose(lib.renderer, *scene, cam, 2, 0.05) is decided

    policy = policy_timed((some_ao, more_ao, most_ao))
    policy.choose(lib.renderer, *scene, cam, 2, 0.05)
    serve(policy, more_ao, 3.0)  # 4.17 of 5.56 ms: more_ao's 6 no longer fits, some_ao's 3 (timed) does
    policy._timings[scene_key].pop(most_ao)  # (a candidate still to time, so that the probe has device work)
    meanwhile = policy.choose(lib.renderer, *scene, cam, 2, 0.05)
    assert policy.pending and meanwhile.method == some_ao and meanwhile.fits and meanwhile.expected_psnr == 26.0
    policy.pending.clear(), policy._probing.clear()
    serve(policy, more_ao, 1.0)  # the load eases to 1: more_ao fits the freed budget (12.5 of 16.7), kept meanwhile
    assert policy.choose(lib.renderer, *scene, cam, 2, 0.05).method == more_ao and policy.pending


def test_under_load_auto_gives_up_rate_down_to_min_fps_to_keep_the_ao_a_scene_shows(lib, caplog):
    """Where the target rate's budget leaves only a frame without AO (or with rays that gain nothing over none) and
    AO matters, auto takes the cheapest candidate with AO rays that gains KEEP_AO_DB over it and keeps min_fps, of
    those timed already and the first KEEP_AO_TRIES untimed; otherwise (none keeps min_fps, no candidate gains
    enough, AO does not matter, min_fps is the target) the target's choice."""
    from isosr_server.auto import KEEP_AO_DB

    plain, noisy, cheap_ao, dear_ao, *more_ao = (FrameMethod.of("full", ao_rays=n) for n in (0, 1, 2, 8, 16, 32, 64))
    base = {plain: 1.0, noisy: 1.2, cheap_ao: 3.0, dear_ao: 6.0}  # the policy's candidates: cheapest first
    cam, scene_key = orbit(30, 20, 1.8), (VOLUME, round(lib.iso, 6), 64, 48, 0.05)
    target = 1000 / (16 * 30)  # 16 sessions at 30 frames/s: 2.08 ms, 1.56 within the headroom

    def choose(min_fps: float | None, ao_matters: bool = True, psnr_ao: float = 28.0,
               untimed_floor_ms: float | None = None, **times_of) -> BudgetChoice:
        times = base | {FrameMethod.of("full", ao_rays=int(k[2:])): v for k, v in times_of.items()}
        policy = AutoPolicy(tuple(times), 30.0, Networks(), min_fps=min_fps)
        psnr = {m: psnr_ao + 2 for m in times} | {cheap_ao: psnr_ao, plain: 20.0, noisy: 19.0}  # 1 ray: no gain
        probe_ms = {} if untimed_floor_ms is None else {cheap_ao: untimed_floor_ms / budget.FLOOR_SHARE}
        policy._quality[scene_key] = budget.QualityProbe((64, 48), psnr, 12.0, ao_matters, 0.0, probe_ms)
        policy._timings[scene_key] = dict(times)  # all timed: the choice is made without device work
        if untimed_floor_ms is not None:  # as on CPUs: its floor from the quality probe's frames, not timed
            del policy._timings[scene_key][cheap_ao]
        choice = policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 16, 0.05)
        assert not policy.pending
        return choice

    assert choose(None).method == plain and choose(30.0).method == plain, "min_fps at the target: no trade"
    with caplog.at_level(logging.INFO, logger="isosr.server"):
        kept = choose(15.0)  # twice the budget: 3.0 ms of 4.17 fits its headroom
    assert kept.method == cheap_ao and kept.fits and kept.budget_ms == pytest.approx(2 * target)
    assert f"{plain.name} (20.0 dB) drops the AO the scene shows; at 15 frames/s a session: {cheap_ao.name}" in \
        caplog.text
    assert choose(5.0).method == cheap_ao, "the cheapest frame that keeps AO, not the best the floor allows (6 ms)"
    assert choose(15.0, ao2=5.0, ao8=3.0).method == dear_ao, "the cheapest by rank is too dear: the next that fits"
    with caplog.at_level(logging.INFO, logger="isosr.server"):
        assert choose(20.0).method == plain, "3.0 ms does not keep 20 frames/s"
    assert f"none with AO keeps 20 frames/s a session within 2.34 ms ({cheap_ao.name} 28.0 dB 3.00 ms, " in caplog.text
    assert choose(15.0, ao_matters=False).method == plain
    assert choose(15.0, psnr_ao=20.0 + KEEP_AO_DB - 0.1).method == plain, "AO rays that gain too little"
    assert choose(15.0, psnr_ao=math.nan).method == plain
    assert choose(15.0, untimed_floor_ms=2.2 * target).method == plain, "its floor over the budget: not even timed"
    # the budget fits nothing: the fastest is 1 ray a pixel, noisier than none; it drops AO too
    assert choose(15.0, ao0=2.0, ao1=1.9).method == cheap_ao
    assert choose(15.0, ao0=2.0, ao1=1.9, ao2=5.0, ao8=3.0).method == dear_ao
    dear = {f"ao{m.ao_rays}": 5.0 for m in (cheap_ao, dear_ao, *more_ao)}
    assert choose(15.0, **dear | {"ao32": 3.0}).method == more_ao[1], "a 4th timed already is weighed too"
    assert choose(15.0, **dear).method == plain
    assert choose(15.0, **dear | {"ao16": 3.0}).method == more_ao[0]
    with pytest.raises(ValueError, match="min_fps must lie in"):
        AutoPolicy(tuple(base), 30.0, Networks(), min_fps=31.0)


def test_trading_rate_for_ao_times_at_most_keep_ao_tries_new_candidates(lib, monkeypatch):
    """The trade times the first KEEP_AO_TRIES candidates not timed yet, cheapest first, and no more: a 4th untimed
    one is not timed even where it would fit, while one timed already is weighed at no device cost. (Untimed
    candidates reach the trade where min_fps lies below half the target rate: floors over twice the target's
    budget, which the target's choice does not time, may fit the min_fps budget.)"""
    from isosr_server.auto import KEEP_AO_TRIES

    plain, *with_ao = (FrameMethod.of("full", ao_rays=n) for n in (0, 2, 8, 16, 32))
    cam, scene_key = orbit(30, 20, 1.8), (VOLUME, round(lib.iso, 6), 64, 48, 0.05)
    # 16 sessions at 30 frames/s: 2.08 ms; at min_fps 5, 12.5 (9.4 within the headroom); AO floors 5 ms
    dear, fits = 10.0, 3.0
    timed: list[FrameMethod] = []

    def time_candidate(runner, cameras, config, budget_ms, slice_ms=None):  # no device work: a set time
        timed.append(runner.method)
        return fits if runner.method == with_ao[-1] else dear
        yield

    monkeypatch.setattr(budget, "_time_candidate_steps", time_candidate)

    def choose(known: dict) -> BudgetChoice:
        timed.clear()
        policy = AutoPolicy((plain, *with_ao), 30.0, Networks(), min_fps=5.0)
        psnr = {plain: 20.0} | dict.fromkeys(with_ao, 28.0)
        probe_ms = dict.fromkeys(with_ao, 5.0 / budget.FLOOR_SHARE)
        policy._quality[scene_key] = budget.QualityProbe((64, 48), psnr, 12.0, True, 0.0, probe_ms)
        policy._timings[scene_key] = {plain: 1.0} | known
        return policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 16, 0.05)

    assert KEEP_AO_TRIES == 3 and choose({}).method == plain and timed == with_ao[:3], "the 4th untimed: not timed"
    kept = choose({with_ao[-1]: fits})
    assert kept.method == with_ao[-1] and kept.fits and timed == with_ao[:3], "timed already: weighed, not timed"


def test_the_servers_auto_keeps_ao_down_to_half_its_target_rate_unless_told(srv):
    from isosr_server.core.config import Settings

    assert srv.app.state.engine.auto.min_fps == 15.0 == Settings().resolved_min_fps
    assert Settings(target_fps=10.0).resolved_min_fps == 5.0 and Settings(min_fps=30.0).resolved_min_fps == 30.0
    for bad in (40.0, 0.0, math.inf, math.nan):
        with pytest.raises(ValueError, match=r"min_fps must lie in \(0, target_fps = 30\], got"):
            Settings(min_fps=bad)


def test_the_service_tells_auto_what_each_of_its_frames_cost(srv, monkeypatch):
    """What each auto frame cost the device thread (its stages and the host work between them: the wall clock the
    probe times by; here a coding step slowed by 30 ms) reaches the policy with the scene, size, session count and
    method it was chosen for (a first frame runs in slices, between which others' frames run: its stages' time);
    other modes' frames do not."""
    engine = srv.app.state.engine
    policy, told, codes_sync = engine.auto, [], engine.codes_sync
    monkeypatch.setattr(policy, "served", lambda *args: told.append(args))
    monkeypatch.setattr(engine, "codes_sync", lambda made, video=None: (time.sleep(0.03), codes_sync(made, video))[1])
    width = W + 32  # a size no other test's choice is cached for
    with session(srv, width=width, height=H) as (ws, _):
        frames = [frame(ws)] + [(send(ws, cam(30 + i, seq=i)), frame(ws))[1] for i in (1, 2)]
    with session(srv, mode="full") as (ws, _):
        frame(ws)
    assert len(told) == len(frames)
    for (scene, iso, w, h, sessions, ao_radius, clip, method, ms), f in zip(told, frames):
        assert (scene, w, h, sessions, clip.active, method.name) == (VOLUME, width, H, 1, False, f.method)
        device = sum(v for k, v in f.times.items() if k not in ("encode", "total"))
        assert device + (30 if f is not frames[0] else 0) <= ms <= f.times["total"]


def test_auto_probes_the_clipped_scene_the_view_shows(lib, monkeypatch):
    """A clip is part of the scene auto probes: a probe of its own, beside the unclipped scene's,
    whose reference and every candidate it scores or times render clipped (here a clip that keeps
    nothing: nothing to score, no AO to see, where the unclipped probe scores its candidates)."""
    made, here = [], threading.current_thread()

    def spy(method, *args, **options):  # this test's runners: the module's server may be probing meanwhile
        if threading.current_thread() is here:
            made.append(options.get("clip", Clip()))
        return make_runner(method, *args, **options)

    monkeypatch.setattr(budget, "make_runner", spy)
    policy = AutoPolicy((FrameMethod.of("full"), FrameMethod.of("full", ao_rays=2)), 30.0, Networks())
    nothing = Clip(planes=(((0.0, 0.0, 0.9), (0.0, 0.0, 1.0)),))  # keeps z >= 0.9: beyond the volume
    cam = orbit(30, 20, 1.8)
    for clip in (Clip(), nothing):
        policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 1, 0.05, clip)
    assert len(policy.pending) == 2, "a probe per clip"
    plain = finish_steps(policy.pending.pop(0))
    assert not math.isnan(plain.expected_psnr) and set(made) == {Clip()}
    made.clear()
    cut = finish_steps(policy.pending.pop(0))
    assert math.isnan(cut.expected_psnr) and math.isnan(cut.ao_effect_db) and not cut.ao_matters
    assert made and set(made) == {nothing}, "every runner of the clipped probe clips"
    assert policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 1, 0.05, nothing) is cut


def test_before_its_probe_auto_takes_the_cost_tables_best_fit_for_the_scenes_first_hit(lib):
    """Frames before the probe: the cheapest candidate until the probe's first units timed the
    scene's plain first-hit frame; then the committed table's best PSNR whose cost in first-hit
    frames fits the budget's headroom (a tabled method that does not fit is passed over)."""
    cheap, mid, dear = FrameMethod.of("full"), FrameMethod.of("full", ao_rays=2), FrameMethod.of("atrous", ao_rays=2)
    costs = CostTable("a GPU", "abc", {method_key(cheap): (1.0, 25.0), method_key(mid): (3.0, 30.0),
                                       method_key(dear): (50.0, 33.0)})
    policy = AutoPolicy((cheap, mid, dear), 30.0, Networks(), costs=costs)
    cam = orbit(30, 20, 1.8)
    assert policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 1, 0.05).method == cheap
    probe = policy.pending[0]
    next(probe), next(probe)  # the first-hit frame's warm-up and its timed frame
    (first_hit,) = policy._first_hit.values()
    assert first_hit > 0
    policy.target_fps = 1000 / (10 * first_hit / PROBE["headroom"])  # a budget of 10 first-hit frames
    choice = policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 1, 0.05)
    assert (choice.method, choice.expected_psnr) == (mid, 30.0) and choice.ms == pytest.approx(3 * first_hit)
    policy.target_fps = 1000 / (100 * first_hit / PROBE["headroom"])
    assert policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, cam, 1, 0.05).method == dear
    assert policy.costs.choose((cheap, mid), first_hit, 0.5 * first_hit, 1.0) is None  # nothing fits: the cheapest
    assert policy.costs.choose((cheap, mid), first_hit, first_hit, 1.0)[0] == cheap
    assert policy.costs.choose((cheap, mid), first_hit, first_hit, 0.9) is None  # within the headroom only
    finish_steps(probe)


def test_the_committed_cost_table_covers_the_gpu_candidates():
    """The CUDA table (made from the committed Pareto study) knows every default candidate that
    the study ran, a plain first-hit frame costs 1 of itself, and more rays cost more."""
    table = CostTable.for_device("cuda")
    assert table is not None and table.rows[("full", 0, 1, 1)][0] == 1.0
    tabled = [m for m in default_candidates("cuda") if method_key(m) in table.rows]
    assert len(tabled) >= 0.8 * len(default_candidates("cuda"))
    assert table.rows[("full", 64, 4, 1)][0] > table.rows[("full", 8, 1, 1)][0] > 1.0


def test_the_cost_table_takes_a_rows_scene_region_score_and_skips_unscored_rows():
    """Per method the medians over scenes of cost in first-hit frames and of the study's ranking PSNR (front_psnr:
    the scene's region where a row has it); a row that covers nothing (null) is left out, not a crash."""
    def row(volume, kind, rays, ms, psnr, scene=None):
        return {"volume": volume, "size": "1080p", "kind": kind, "ao_rays": rays, "spp": 1, "factor": 1, "ms": ms,
                "color_psnr": psnr} | ({} if scene is None else {"color_psnr_scene": scene})

    rows = [row("a", "full", 0, 1.0, 20.0, 19.0), row("a", "full", 8, 3.0, 30.0, 29.0), row("b", "full", 0, 2.0, 22.0),
            row("b", "full", 8, 8.0, 32.0), row("c", "full", 0, 1.0, None, None), row("c", "full", 8, 2.0, None, None)]
    table = {(r["kind"], r["ao_rays"]): r for r in CostTable.from_pareto(rows)}
    assert (table["full", 8]["cost"], table["full", 8]["color_psnr"], table["full", 8]["scenes"]) == (3.5, 30.5, 2)
    assert table["full", 0]["color_psnr"] == 20.5, "a: its scene score 19; b: written before it, its color_psnr 22"


def test_a_probe_cache_that_cannot_be_read_is_probed_anew(lib, tmp_path, caplog):
    cache = tmp_path / "probes.json"
    cache.write_text("{not json")
    policy = AutoPolicy.for_server(DEVICE, "fp32", 4, {}, 30.0, Networks(), cache=ProbeCache(cache, "this CPU"))
    assert "cannot be read" in caplog.text
    policy.choose(lib.renderer, VOLUME, lib.iso, 64, 48, orbit(30, 20, 1.8), 1, 0.05)
    finish_steps(policy.pending.pop())
    assert json.loads(cache.read_text()), "the probe's results replace the unreadable file"


def test_the_first_auto_frame_is_the_prior_and_later_frames_the_probes_choice(srv):
    """A new size's first auto frame does not wait for the probe, and says so (``choice``: nothing
    measured, the session's budget); once the probe has run in the background between frames, the
    frames name its choice and carry what it expects of it (time, PSNR, within the budget or not)."""
    policy = srv.app.state.engine.auto
    width = W + 24  # a size no other test probed
    with session(srv, width=width, height=H, refine=False) as (ws, _):
        f = frame(ws)
        assert f.method == prior_method(policy.candidates).name
        assert f.choice == P.AutoChoice(policy.budget_ms(1), None, None, False, "prior"), f.choice
        for i in range(1, 200):
            send(ws, cam(30 + i % 2, seq=i))
            f = frame(ws)
            chosen = [c for k, (c, *_) in policy._chosen.items() if k[2] == width]
            if chosen:
                break
        assert chosen, "the probe ran between frames"
        send(ws, cam(40, seq=i + 1))
        f, (choice,) = frame(ws), chosen
        assert f.method == choice.method.name and f.choice.source == "probe"
        assert (f.choice.budget_ms, f.choice.ms, f.choice.psnr_db, f.choice.fits) == pytest.approx(
            (policy.budget_ms(1), choice.ms, choice.expected_psnr, choice.fits))
        assert math.isfinite(f.choice.ms) and math.isfinite(f.choice.psnr_db)


@pytest.mark.slow
def test_an_honest_session_beside_the_heaviest_frame_gets_its_first_frame_first(srv):
    """The heaviest frame the default limits allow (3840x2160, 256 AO rays; about 45 s on this
    CPU) runs in slices: a small session opened beside it gets its frame before the heavy one is done."""
    limits = P.Limits()
    limits.check_size(3840, 2160)
    with srv.view() as heavy:
        heavy.send(P.encode(P.OpenMsg(VOLUME, P.SettingsUpdate(mode="full", width=3840, height=2160,
                                                               ao_rays=limits.max_ao_rays, refine=False))))
        assert isinstance(P.parse(heavy.recv(timeout=60), P.Limits(max_message_bytes=2**28),
                                  P.SERVER_VIEW_MESSAGES), P.ReadyMsg)
        time.sleep(1.0)  # the heavy frame is under way
        with session(srv, mode="full") as (ws, _):
            f = frame(ws)
        assert f.method == "full, AO 0, spp 1"
        with pytest.raises(TimeoutError):  # an order, not a time: the heavy frame is not done yet
            heavy.recv(timeout=0.1)


def test_upscale_sessions_bound_each_client_and_never_lock_others_out():
    from isosr_server.sessions import UpscaleSessions

    made = []
    sessions = UpscaleSessions(P.Limits(max_sessions=4, max_sessions_per_client=2),
                               lambda cls: made.append(object()) or made[-1])
    assert sessions.get("a", "10.0.0.1") is sessions.get("a", "10.0.0.1")
    sessions.get("b", "10.0.0.1")
    with pytest.raises(P.ProtocolError, match="this client holds 2 upscale sessions") as e:
        sessions.get("c", "10.0.0.1")
    assert e.value.http_status == 429
    for i in range(3):  # another client fills the server, then a third still gets a slot
        sessions.get(f"x{i}", f"10.0.0.{2 + i}")
    assert len(sessions) == 4 and "a" not in {k for _, k in sessions._by_id}, "the least recently used id made room"
    stream = sessions.open_stream()
    assert len(sessions) == 4 and stream is made[-1]


def test_warming_the_policy_makes_every_candidates_first_frames_at_each_size_and_its_probes(lib, monkeypatch):
    """At start (GPUs), each candidate makes a first frame and one carrying it at each window size and at
    that size's probe size (a factor that does not divide a size skipped), and the policy is left as
    it was: nothing probed, chosen or pending."""
    import isosr_server.auto as auto

    made = []

    def recording(method, renderer, iso, width, height, **options):
        runner = make_runner(method, renderer, iso, width, height, **options)
        frame = runner.frame
        runner.frame = lambda camera, prev=None: (made.append((method, width, height, prev is None)),
                                                  frame(camera, prev))[1]
        return runner

    monkeypatch.setattr(auto, "make_runner", recording)
    candidates = (FrameMethod.of("full"), FrameMethod.of("full", ao_rays=2), FrameMethod.of("svgf", ao_rays=1),
                  FrameMethod.of("upscale", factor=4))
    policy = AutoPolicy(candidates, 30.0, Networks())
    monkeypatch.setattr(auto, "default_probe_height", lambda device: 24)
    policy.warm(lib.renderer, ((48, 64), (30, 40)))
    sizes = {(64, 48), (40, 30), (32, 24)}  # each window and the probes' (24 rows, the aspect kept: both 32x24)
    assert {(w, h) for _, w, h, _ in made} == sizes
    assert {(w, h) for m, w, h, _ in made if m.factor == 4} == {(64, 48), (32, 24)}, "not 40x30: 4 does not divide 30"
    for m in candidates[:3]:
        for w, h in sizes:
            assert [first for n, *size, first in made if n == m and tuple(size) == (w, h)] == [True, False], (m, w, h)
    assert not (policy.pending or policy._chosen or policy._quality or policy._timings)


def test_a_probe_unit_that_held_the_device_thread_is_logged(caplog):
    """The engine times each unit of a probe on the device thread and says when one was long enough for
    viewers to see their frames wait."""
    from isosr_server import engine

    def units():
        yield
        time.sleep(0.02)
        return "done"

    steps = units()
    assert engine._advance(steps)[:2] == (False, None)
    done, result, seconds = engine._advance(steps)
    assert (done, result) == (True, "done") and seconds >= 0.02
    with caplog.at_level(logging.INFO, logger="isosr.server"):
        engine.Engine._log_slow_unit(engine.SLOW_PROBE_UNIT_S / 2)
        assert "held the device thread" not in caplog.text
        engine.Engine._log_slow_unit(2 * engine.SLOW_PROBE_UNIT_S)
    assert "one unit held the device thread for" in caplog.text
