"""Training ops (stgs.train.ops): whatever moves, copies or resets Gaussians does the same to Adam's moments."""

from __future__ import annotations

import torch

from stgs.model.gop import GOPModel, GOPShape
from stgs.train.config import budget
from stgs.train.ops import (
    GAUSSIAN_AXIS,
    Optimizer,
    copies_allowed,
    opacity_level,
    prune,
    relocate,
    sort,
    track_opacities,
)

SIDE = 8


def stepped_model(seed: int = 0) -> tuple[GOPModel, Optimizer]:
    """A model whose every per-Gaussian parameter and Adam moment differs from row to row."""
    torch.manual_seed(seed)
    model = GOPModel(GOPShape(SIDE * SIDE, gop_size=4, window=2))
    with torch.no_grad():
        for name in GAUSSIAN_AXIS:
            getattr(model, name).copy_(torch.randn_like(getattr(model, name)))
    opt = Optimizer(model, budget("quick", grid_side=SIDE, gop_size=4, window=2), 1.0, None)
    for _ in range(2):
        opt.opt.zero_grad()
        loss = sum((getattr(model, name) ** 3 * torch.randn_like(getattr(model, name))).sum() for name in GAUSSIAN_AXIS)
        loss.backward()
        opt.opt.step()
    return model, opt


def rows(model: GOPModel, opt: Optimizer, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(parameter, exp_avg, exp_avg_sq) with the Gaussians on axis 0."""
    param = getattr(model, name)
    state = opt.opt.state[param]
    axis = GAUSSIAN_AXIS[name]
    return tuple(t.detach().movedim(axis, 0).clone() for t in (param, state["exp_avg"], state["exp_avg_sq"]))


def test_sort_permutes_parameters_moments_and_accumulator_together():
    model, opt = stepped_model()
    before = {name: rows(model, opt, name) for name in GAUSSIAN_AXIS}
    accum = torch.stack([torch.arange(SIDE * SIDE, dtype=torch.float32), torch.ones(SIDE * SIDE)])
    sort(model, opt, accum, seed=0)
    order = accum[0].long()  # where each slot's Gaussian came from
    assert not torch.equal(order, torch.arange(SIDE * SIDE))  # the sort did move rows
    assert sorted(order.tolist()) == list(range(SIDE * SIDE))
    for name in GAUSSIAN_AXIS:
        for was, now in zip(before[name], rows(model, opt, name), strict=True):
            assert torch.equal(now, was[order]), name


def test_relocation_copies_live_rows_onto_dead_ones_and_restarts_both_moments():
    model, opt = stepped_model(1)
    opacity_before = torch.sigmoid(model.opacity_logit.detach()).clone()
    before = {name: rows(model, opt, name) for name in GAUSSIAN_AXIS}
    avg = torch.full((SIDE * SIDE,), 0.5)
    dead = torch.tensor([3, 10, 40])
    avg[dead] = 0.001
    moved = relocate(model, opt, avg, dead_opacity=0.005, gen=torch.Generator().manual_seed(0))
    assert moved == 3
    after = {name: rows(model, opt, name) for name in GAUSSIAN_AXIS}
    # each dead slot now holds a copy of one live Gaussian (colour is never touched after the copy)
    sources = [int((before["color"][0] == after["color"][0][d]).all(dim=1).nonzero()[0]) for d in dead]
    assert all(avg[s] == 0.5 for s in sources)
    touched = set(dead.tolist()) | set(sources)
    for name in GAUSSIAN_AXIS:
        _, m1, m2 = after[name]
        for i in range(SIDE * SIDE):
            if i in touched:
                assert not m1[i].any() and not m2[i].any(), (name, i)
            else:
                assert torch.equal(m1[i], before[name][1][i]) and torch.equal(m2[i], before[name][2][i]), (name, i)
    # the source's opacity is split so that n + 1 copies composite as the one did
    opacity = torch.sigmoid(model.opacity_logit.detach())
    for s in set(sources):
        copies = sources.count(s) + 1
        assert torch.allclose(1 - (1 - opacity[s]) ** copies, opacity_before[s].clamp(max=1 - 1e-6), atol=1e-4)


def test_relocation_without_live_gaussians_moves_nothing():
    model, opt = stepped_model(2)
    before = {name: rows(model, opt, name) for name in GAUSSIAN_AXIS}
    assert relocate(model, opt, torch.zeros(SIDE * SIDE), 0.005, torch.Generator()) == 0
    for name in GAUSSIAN_AXIS:
        assert all(torch.equal(a, b) for a, b in zip(before[name], rows(model, opt, name), strict=True))


def test_relocation_onto_a_faint_live_set_never_splits_below_twice_the_dead_opacity():
    # 4 live Gaussians at opacity 0.1 and 60 dead ones: uncapped, each live one would be split into ~16 copies
    # of opacity ~0.006, all dead at the next relocation (the collapse the cap prevents)
    model, opt = stepped_model(3)
    live = torch.tensor([5, 20, 33, 61])
    with torch.no_grad():
        model.opacity_logit.fill_(-6.0)
        model.opacity_logit[live] = torch.logit(torch.tensor(0.1))
    avg = torch.sigmoid(model.opacity_logit.detach())
    dead_opacity = 0.02
    moved = relocate(model, opt, avg, dead_opacity, torch.Generator().manual_seed(0))
    opacity = torch.sigmoid(model.opacity_logit.detach())
    assert 1 <= moved <= len(live)  # opacity 0.1 allows one copy each: 1 − 0.9^(1/2) = 0.051 ≥ 0.04, a third is not
    assert int((opacity >= 2 * dead_opacity).sum()) == len(live) + moved
    assert copies_allowed(torch.tensor([0.1, 0.5]), dead_opacity).tolist() == [1, 15]
    for _ in range(5):  # relocating again and again keeps live Gaussians
        avg = torch.sigmoid(model.opacity_logit.detach())
        relocate(model, opt, avg, dead_opacity, torch.Generator().manual_seed(1))
        assert int((torch.sigmoid(model.opacity_logit.detach()) >= dead_opacity).sum()) >= len(live)


def test_a_gaussian_drawn_in_a_few_frames_is_dead_by_its_mean_but_alive_by_its_peak():
    """A dynamic-layer Gaussian that fades in for 2 of 20 drawn frames (opacity 0.15) averages 0.015, under the
    dead threshold; judged by its peak it stays, and one faint in every frame is dead either way."""
    n, dead_opacity = 4, 0.02
    drawn = torch.zeros(20, n)
    drawn[:, 0] = 0.5                  # on in every frame
    drawn[[3, 11], 1] = 0.15           # on in two frames only
    drawn[:, 2] = 0.01                 # faint throughout
    drawn[5, 3] = 0.019                # faint at its peak
    levels = {}
    for peak in (False, True):
        accum = torch.zeros(2, n)
        for opacities in drawn:
            track_opacities(accum, opacities, peak)
        assert accum[1].tolist() == [20.0] * n
        levels[peak] = opacity_level(accum, peak)
        model = GOPModel(GOPShape(n, gop_size=4, window=2))
        with torch.no_grad():
            model.opacity_logit.fill_(0.0)
        pruned = prune(model, accum, dead_opacity, peak)
        assert pruned == (2 if peak else 3)
        assert (model.opacity_logit[1] < 0).item() is not peak
    assert torch.allclose(levels[False], torch.tensor([0.5, 0.015, 0.01, 0.00095]))
    assert torch.allclose(levels[True], torch.tensor([0.5, 0.15, 0.01, 0.019]))
