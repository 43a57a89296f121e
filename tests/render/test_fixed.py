"""A fixed layer drawn once per camera (stgs.render.fixed): the same pixels as one `rasterize` of both layers,
with the tiles only the fixed layer reaches copied instead of composited."""

from __future__ import annotations

import pytest
import torch

from stgs.camera import Camera, intrinsics, look_at
from stgs.model.renderer import FrameRenderer, StaticDrawer
from stgs.model.static import merge
from stgs.native.library import available
from stgs.render import rasterize
from stgs.render.fixed import FixedLayerView
from stgs.render.native import NativeComposite, bin_native, f32, project_native
from stgs.render.project import project
from tests.conftest import pinhole, random_scene
from tests.model.test_gop import random_model
from tests.model.test_layers import random_static

pytestmark = pytest.mark.skipif(not available(), reason="the native library could not be built here")

WIDTH, HEIGHT = 97, 71  # partial tiles on both axes: 7 x 5 tiles


def layers(n_fixed: int, n_moving: int, spread: float, seed: int = 0):
    """A fixed layer over the whole view and a moving one within `spread` of the axis, float32."""
    fixed = [t.float() for t in random_scene(n_fixed, seed, log_scale=-3.0)]
    moving = [t.float() for t in random_scene(n_moving, seed + 1, spread=spread, log_scale=-3.5)]
    return fixed, moving


def both(fixed, moving, view, K, background=None) -> torch.Tensor:
    return rasterize(*(torch.cat([a, b]) for a, b in zip(fixed, moving, strict=True)), view, K, WIDTH, HEIGHT,
                     background)


@pytest.mark.parametrize("spread, reused", [
    (0.05, range(20, 35)),  # a small moving cluster: most of the 35 tiles copied
    (3.0, range(0, 3)),  # moving Gaussians everywhere: (nearly) every tile composited
])
def test_draw_equals_one_rasterize_of_both_layers(spread, reused):
    view, K = (t.float() for t in pinhole(WIDTH, HEIGHT, 60.0))
    fixed, moving = layers(3000, 300, spread)
    bg = torch.tensor([0.2, 0.4, 0.1])
    layer = FixedLayerView(*fixed, view, K, WIDTH, HEIGHT, bg)
    assert torch.equal(layer.image, rasterize(*fixed, view, K, WIDTH, HEIGHT, bg))
    for step in range(3):  # the moving layer moves; the kept layer serves every frame
        moved = [moving[0] + step * torch.tensor([0.02, -0.01, 0.0]), *moving[1:]]
        image = layer.draw(*moved)
        assert torch.equal(image, both(fixed, moved, view, K, bg))
        assert layer.last_reused_tiles in reused, layer.last_reused_tiles


@pytest.mark.parametrize("spread", [0.05, 3.0])
def test_draw_with_gradients_equals_one_composite_of_both_layers(spread):
    """Moving Gaussians that need gradients (training over a frozen layer): the image and every gradient are
    bit for bit those of one native composite of both layers (the kept layer projected natively, the moving
    one by torch, as `rasterize` projects what it differentiates), though only the reached tiles are visited."""
    view, K = (t.float() for t in pinhole(WIDTH, HEIGHT, 60.0))
    fixed, moving = layers(3000, 300, spread, seed=5)
    bg = torch.tensor([0.2, 0.4, 0.1])
    weights = torch.rand(HEIGHT, WIDTH, 3, generator=torch.Generator().manual_seed(1))
    layer = FixedLayerView(*fixed, view, K, WIDTH, HEIGHT, bg)

    def gradients(draw):
        params = [t.clone().requires_grad_() for t in moving]
        image = draw(params)
        (image * weights).sum().backward()
        return image.detach(), [t.grad for t in params]

    def one_composite(params):
        kept = project_native(*fixed[:4], view, K)
        moved = project(*(t.double() for t in params[:3]), params[3], view, K)
        cat = {f: torch.cat([getattr(kept, f), getattr(moved, f).float()])
               for f in ("means2d", "conics", "depths", "extents")}
        return NativeComposite.apply(cat["means2d"], cat["conics"], torch.cat([fixed[3], params[3]]),
                                     torch.cat([fixed[4], params[4]]), bg, cat["depths"], cat["extents"], WIDTH,
                                     HEIGHT)

    image, grads = gradients(lambda params: layer.draw(*params))
    expected, expected_grads = gradients(one_composite)
    # The tiles the moving layer reaches are composited as one composite of both does it; the others are the
    # kept image, drawn by the inference kernel (float32 rounding apart from the tracked one).
    moved = project(*(t.double() for t in moving[:3]), moving[3], view, K)
    bins = bin_native(*(f32(t) for t in (moved.means2d, moved.conics, moving[3], moved.depths, moved.extents)),
                      WIDTH, HEIGHT).bins()
    per_tile = (bins.tile_start[1:] > bins.tile_start[:-1]).reshape(bins.tiles_y, bins.tiles_x)
    reached = per_tile.repeat_interleave(16, 0).repeat_interleave(16, 1)[:HEIGHT, :WIDTH]
    assert int(reached.sum()) > 0 and (spread > 1 or not reached.all())
    assert torch.equal(image[reached], expected[reached])
    assert torch.equal(image[~reached], layer.image[~reached])
    torch.testing.assert_close(image, expected, atol=1e-6, rtol=0)
    for name, got, want in zip(("means", "quats", "scales", "opacities", "colors"), grads, expected_grads,
                               strict=True):
        assert torch.equal(got, want), name
        assert want.abs().sum() > 0, name  # the moving layer shows in the image
    # And the same as rasterize of both layers, which projects both by torch (float32 rounding apart).
    plain, plain_grads = gradients(lambda params: both(fixed, params, view, K, bg))
    torch.testing.assert_close(image, plain, atol=1e-5, rtol=0)
    for got, want in zip(grads, plain_grads, strict=True):
        torch.testing.assert_close(got, want, atol=1e-3, rtol=1e-3)


def test_no_moving_gaussians_is_the_kept_image():
    view, K = (t.float() for t in pinhole(WIDTH, HEIGHT, 60.0))
    fixed, _ = layers(500, 1, 0.1)
    layer = FixedLayerView(*fixed, view, K, WIDTH, HEIGHT)
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    assert torch.equal(layer.draw(*empty), layer.image)
    assert layer.last_reused_tiles == 7 * 5


def test_equal_depths_and_culled_gaussians_order_as_one_bin_of_both():
    """Moving Gaussians at exactly a kept one's depth come after it (as the stable sort of both orders them);
    culled ones, and an empty kept layer, change nothing."""
    view, K = (t.float() for t in pinhole(WIDTH, HEIGHT, 60.0))
    fixed, moving = layers(400, 200, 0.3, seed=3)
    moving[0][:100] = fixed[0][:100]  # the same means: the same depths, and overlapping footprints
    moving[3][:100] = 0.9
    fixed[3][:100] = 0.9
    moving[0][150:160, 2] = -1.0  # behind the camera
    fixed[0][300:310, 2] = -1.0
    layer = FixedLayerView(*fixed, view, K, WIDTH, HEIGHT)
    assert torch.equal(layer.draw(*moving), both(fixed, moving, view, K))
    none = [t[:0] for t in fixed]
    empty = FixedLayerView(*none, view, K, WIDTH, HEIGHT)
    assert torch.equal(empty.image, torch.zeros(HEIGHT, WIDTH, 3))
    assert torch.equal(empty.draw(*moving), both(none, moving, view, K))


def test_bad_inputs_are_clear_errors():
    view, K = (t.float() for t in pinhole(WIDTH, HEIGHT, 60.0))
    fixed, moving = layers(100, 10, 0.1)
    with pytest.raises(ValueError, match="float32"):
        FixedLayerView(*(t.double() for t in fixed), view.double(), K.double(), WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="gradients"):
        FixedLayerView(fixed[0].requires_grad_(), *fixed[1:], view, K, WIDTH, HEIGHT)
    fixed[0] = fixed[0].detach()
    layer = FixedLayerView(*fixed, view, K, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="quats has shape"):
        layer.draw(moving[0], moving[1][:5], *moving[2:])
    moving[0][3, 1] = float("nan")
    with pytest.raises(ValueError, match="means contains NaN"):
        layer.draw(*moving)


def test_frame_renderer_keeps_the_static_layer_per_camera_and_background():
    """A layered FrameRenderer draws what one splat of both layers draws, frame after frame, when the camera
    moves and back, and when the background changes."""
    model = random_model(n=36, gop_size=4, seed=2)
    static = random_static(400, seed=1, sh_degree=1)
    renderer = FrameRenderer(model, native=True, static=static)
    here = Camera("a", intrinsics(80, 60, 60.0), look_at((0.0, 0.3, -2.5), (0.0, 0.0, 0.0)), 80, 60)
    there = Camera("b", here.K, look_at((0.6, 0.2, -2.4), (0.0, 0.0, 0.0)), 80, 60)
    white = torch.tensor([1.0, 1.0, 1.0])
    kept = []
    for i, camera, bg in ((0, here, None), (1, here, None), (2, here, None), (2, there, None), (3, here, None),
                          (3, here, None), (3, here, white), (0, here, white)):
        expected = renderer.splat(merge(renderer.static_gaussians(camera), renderer.dynamic_gaussians(i, camera)),
                                  camera, bg, guarded=True)
        assert torch.equal(renderer.render(i, camera, bg), expected), (i, camera.name, bg)
        kept.append(renderer.static_drawer._kept[1])
    # The static layer is kept from the second frame of a camera and background on, and never for one frame.
    assert [view is not None for view in kept] == [False, True, True, False, False, True, False, True]
    assert kept[1] is kept[2] and kept[5] is not kept[2]
    assert kept[-1].last_reused_tiles > 0  # the static layer reaches tiles the GOP does not


def test_a_shared_drawer_keeps_the_static_layer_across_gops():
    static = random_static(400, seed=1)
    drawer = StaticDrawer(static)
    gops = [FrameRenderer(random_model(n=36, gop_size=4, seed=s), native=True, static=drawer) for s in (2, 3)]
    cam = Camera("a", intrinsics(80, 60, 60.0), look_at((0.0, 0.3, -2.5), (0.0, 0.0, 0.0)), 80, 60)
    kept = []
    for renderer in (gops[0], gops[0], gops[1], gops[1]):
        image = renderer.render(1, cam)
        assert torch.equal(image, renderer.splat(renderer.gaussians(1, cam), cam, guarded=True))
        kept.append(drawer._kept[1])
    assert kept[0] is None and kept[1] is not None and kept[1] is kept[2] is kept[3]
