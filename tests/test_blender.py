"""Blender-format loader, pixel-centre camera rays and reproducible ray batches, on tiny hand-made scenes."""

import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from src.data.blender import load_blender_split
from src.data.ray_batches import RayBatcher, step_seed
from src.data.rays import RADIUS_SCALE, generate_rays, pixel_footprint_radii, rays_for_pixels
from src.data.rgba import downscale_rgba
from src.errors import ConfigError, DataError
from tests.conftest import one_line_error

ANGLE = 0.6911112070083618
W, H = 6, 4  # non-square on purpose


def rotation(axis, degrees):
    """3x3 rotation about a unit axis (Rodrigues)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def c2w_matrix(axis, degrees, translation):
    m = np.eye(4)
    m[:3, :3] = rotation(axis, degrees)
    m[:3, 3] = translation
    return m


def fixture_images():
    """Two 6x4 RGBA uint8 images with known straight colour and alpha."""
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(2, H, W, 4), dtype=np.uint8)
    images[0, 0, 0] = [255, 0, 0, 255]  # opaque red
    images[0, 0, 1] = [0, 0, 0, 0]  # transparent: background only
    images[0, 1, 0] = [0, 255, 0, 51]  # 20 % green
    return images


def write_scene(root, frames=None, images=None, angle=ANGLE, split="train"):
    """A Blender-format scene at ``root``: PNGs under train/ and transforms_<split>.json."""
    images = fixture_images() if images is None else images
    (root / split).mkdir(parents=True, exist_ok=True)
    poses = [c2w_matrix([0, 0, 1], 30, [1, 2, 3]), c2w_matrix([1, 1, 0], -50, [-0.5, 0.25, 4])]
    if frames is None:
        frames = []
        for i, img in enumerate(images):
            Image.fromarray(img, mode="RGBA" if img.shape[-1] == 4 else "RGB").save(
                root / split / f"r_{i}.png"
            )
            # one path with the extension, one without (the nerf_synthetic way)
            path = f"./{split}/r_{i}" + (".png" if i == 1 else "")
            frames.append({"file_path": path, "transform_matrix": poses[i % 2].tolist()})
    meta = {"camera_angle_x": angle, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root / f"transforms_{split}.json", images, poses


def test_images_are_composited_on_the_background(tmp_path):
    _, images, poses = write_scene(tmp_path)
    bg = (0.2, 0.4, 0.6)
    split = load_blender_split(tmp_path, "train", background=bg)
    rgba = images.astype(np.float32) / 255
    expected = rgba[..., :3] * rgba[..., 3:] + np.array(bg, np.float32) * (1 - rgba[..., 3:])
    assert split.images.shape == (2, H, W, 3) and split.images.dtype == np.float32
    np.testing.assert_allclose(split.images, expected, atol=1e-6)
    np.testing.assert_allclose(split.alphas, rgba[..., 3], atol=1e-7)
    np.testing.assert_allclose(split.images[0, 0, 0], [1, 0, 0])
    np.testing.assert_allclose(split.images[0, 0, 1], bg, atol=1e-7)
    np.testing.assert_allclose(split.images[0, 1, 0], [0.8 * 0.2, 0.2 + 0.8 * 0.4, 0.8 * 0.6], atol=1e-6)
    np.testing.assert_allclose(split.c2w, np.stack(poses), atol=1e-6)
    assert (split.width, split.height, split.names) == (W, H, ["r_0", "r_1"])
    assert split.focal == pytest.approx(0.5 * W / math.tan(0.5 * ANGLE))
    white = load_blender_split(tmp_path, "train", max_images=1)
    assert white.images.shape == (1, H, W, 3)
    np.testing.assert_allclose(white.images[0, 0, 1], [1, 1, 1])


def test_rgb_images_without_alpha_are_opaque(tmp_path):
    images = fixture_images()[..., :3]
    write_scene(tmp_path, images=images)
    split = load_blender_split(tmp_path, "train")
    assert np.all(split.alphas == 1)
    np.testing.assert_allclose(split.images, images / 255.0, atol=1e-6)


def test_downscale_averages_premultiplied_colour_and_scales_focal(tmp_path):
    images = np.zeros((2, H, W, 4), np.uint8)
    images[:, 0, 0] = [255, 0, 0, 255]  # one opaque red pixel in a 2x2 block of transparent black
    images[:, 2:, 4:] = [0, 0, 255, 255]  # a fully opaque blue block
    write_scene(tmp_path, images=images)
    full = load_blender_split(tmp_path, "train")
    half = load_blender_split(tmp_path, "train", downscale=2)
    assert half.images.shape == (2, 2, 3, 3) and (half.width, half.height) == (3, 2)
    assert half.focal == pytest.approx(full.focal / 2)
    # 1/4 red over white: no dark halo from the transparent pixels' black colour
    np.testing.assert_allclose(half.images[0, 0, 0], [1.0, 0.75, 0.75], atol=1e-6)
    np.testing.assert_allclose(half.alphas[0, 0, 0], 0.25)
    np.testing.assert_allclose(half.images[0, 1, 2], [0, 0, 1], atol=1e-6)
    # compositing commutes with premultiplied box averaging
    np.testing.assert_allclose(half.images, full.images.reshape(2, 2, 2, 3, 2, 3).mean((2, 4)), atol=1e-6)
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "train", downscale=4)
    one_line_error(err, "r_0.png", "6x4", "downscale=4")
    # factor 1 leaves the pixels as they are, even the colour stored under zero alpha
    rgba = np.random.default_rng(0).random((H, W, 4), dtype=np.float32)
    rgba[0, 0, 3] = 0.0
    np.testing.assert_array_equal(downscale_rgba(rgba, 1), rgba)


def test_rays_go_through_pixel_centres_in_camera_row_column_order():
    poses = np.stack([c2w_matrix([0, 0, 1], 30, [1, 2, 3]), c2w_matrix([1, 1, 0], -50, [-0.5, 0.25, 4])])
    w, h, focal = 5, 3, 4.0  # odd sizes: a pixel centre lies on the optical axis
    rays = generate_rays(poses, focal, w, h, near=2.0, far=6.0)
    n = 2 * h * w
    assert {k: tuple(v.shape) for k, v in rays.items()} == {
        "origins": (n, 3),
        "directions": (n, 3),
        "viewdirs": (n, 3),
        "radii": (n, 1),
        "near": (n, 1),
        "far": (n, 1),
    }
    grid = {k: v.reshape(2, h, w, -1).numpy() for k, v in rays.items()}
    for cam in range(2):
        np.testing.assert_allclose(
            grid["origins"][cam], np.broadcast_to(poses[cam, :3, 3], (h, w, 3)), atol=1e-6
        )
        centre = grid["directions"][cam, h // 2, w // 2]
        np.testing.assert_allclose(centre, -poses[cam, :3, 2], atol=1e-6)  # camera looks down -z
        for row, col in [(0, 0), (2, 4), (1, 3)]:
            d_cam = np.array([(col + 0.5 - w / 2) / focal, -(row + 0.5 - h / 2) / focal, -1.0])
            np.testing.assert_allclose(
                grid["directions"][cam, row, col], poses[cam, :3, :3] @ d_cam, atol=1e-6
            )
            flat = rays["directions"][(cam * h + row) * w + col].numpy()
            np.testing.assert_allclose(flat, poses[cam, :3, :3] @ d_cam, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(grid["viewdirs"], axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(grid["radii"], 2 / math.sqrt(12) / focal, rtol=1e-6)
    footprint = pixel_footprint_radii(rays["directions"].reshape(2, h, w, 3))
    np.testing.assert_allclose(footprint.reshape(-1, 1), rays["radii"], rtol=1e-5)
    assert torch.all(rays["near"] == 2.0) and torch.all(rays["far"] == 6.0)
    # a single 4x4 pose works too; the even-width centre offsets are +-0.5 px
    single = generate_rays(poses[0], 2.0, 4, 2, 2.0, 6.0)["directions"].reshape(2, 4, 3)
    d = np.linalg.solve(poses[0, :3, :3], single[0, 1].numpy())
    np.testing.assert_allclose(d, [-0.25, 0.25, -1.0], atol=1e-6)


def test_rays_for_pixels_match_the_full_grid():
    poses = np.stack([c2w_matrix([0, 1, 0], 70, [0, 0, 4]), c2w_matrix([1, 0, 1], 20, [3, 1, 0])])
    full = generate_rays(poses, 7.5, W, H, 2.0, 6.0)
    cam, row, col = torch.tensor([0, 1, 1, 0]), torch.tensor([0, 3, 2, 1]), torch.tensor([5, 0, 4, 2])
    some = rays_for_pixels(torch.as_tensor(poses), cam, row, col, 7.5, W, H, 2.0, 6.0)
    index = (cam * H + row) * W + col
    for key in full:
        torch.testing.assert_close(some[key], full[key][index])


def _bad(tmp_path, mutate):
    """A fixture scene whose transforms JSON (as a dict) is modified by ``mutate``; returns its path."""
    path, _, _ = write_scene(tmp_path)
    meta = json.loads(path.read_text())
    mutate(meta)
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize(
    ("mutate", "needles"),
    [
        (lambda m: m.pop("camera_angle_x"), ["camera_angle_x"]),
        (lambda m: m.pop("frames"), ["'frames'"]),
        (lambda m: m["frames"][1].pop("file_path"), ["frames[1]", "file_path"]),
        (lambda m: m["frames"][0].pop("transform_matrix"), ["frames[0]", "transform_matrix"]),
        (lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0, 0]] * 3), ["(3, 4)", "(4, 4)"]),
        (lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")), ["NaN"]),
        (lambda m: m["frames"][0].update(transform_matrix=np.diag([2, 1, 1, 1.0]).tolist()), ["orthonormal"]),
        (lambda m: m["frames"][0].update(transform_matrix=(2 * np.eye(4)).tolist()), ["bottom row"]),
        (lambda m: m["frames"][0].update(transform_matrix=np.diag([1, 1, -1, 1.0]).tolist()), ["det"]),
        (lambda m: m["frames"][0].update(transform_matrix=[["a"] * 4] * 4), ["not an array of numbers"]),
        (lambda m: m["frames"][0].update(file_path="./train/missing"), ["frames[0]", "missing"]),
        (lambda m: m.update(camera_angle_x=-1), ["camera_angle_x", "(0, pi)"]),
        (lambda m: m.update(frames=[]), ["non-empty list"]),
    ],
)
def test_malformed_transforms_give_one_line_errors(tmp_path, mutate, needles):
    path = _bad(tmp_path, mutate)
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "train")
    one_line_error(err, str(path), *needles)


def test_malformed_files_give_one_line_errors(tmp_path):
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "val")
    one_line_error(err, "transforms_val.json", "not found")
    path, images, _ = write_scene(tmp_path)
    path.write_text('{"camera_angle_x": 0.7, "frames": [')
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "train")
    one_line_error(err, str(path), "malformed JSON", "line 1")

    # second image of another size
    write_scene(tmp_path)
    Image.fromarray(np.zeros((H, W + 2, 4), np.uint8)).save(tmp_path / "train" / "r_1.png")
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "train")
    one_line_error(err, "r_1.png", "8x4", "expected 6x4", "r_0.png")

    # grey + alpha: two channels
    write_scene(tmp_path)
    Image.fromarray(np.zeros((H, W, 2), np.uint8), mode="LA").save(tmp_path / "train" / "r_0.png")
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "train")
    one_line_error(err, "r_0.png", "2 channel", "expected 3 (RGB) or 4 (RGBA)")

    # not an image at all
    write_scene(tmp_path)
    (tmp_path / "train" / "r_0.png").write_bytes(b"not a png")
    with pytest.raises(DataError) as err:
        load_blender_split(tmp_path, "train")
    one_line_error(err, "r_0.png", "unreadable image")


def _batcher(seed=3, **kwargs):
    rng = np.random.default_rng(1)
    images = rng.random((3, 10, 16, 3), dtype=np.float32)
    poses = np.stack([c2w_matrix([0, 0, 1], 40 * i, [0, 0, 4]) for i in range(3)])
    defaults = {"near": 2.0, "far": 6.0, "batch_size": 512, "seed": seed}
    return RayBatcher(images, poses, 12.0, **{**defaults, **kwargs}), images, poses


def test_ray_batches_are_a_function_of_seed_and_step():
    batcher, images, poses = _batcher()
    a, b = batcher.batch(7), _batcher()[0].batch(7)  # a fresh batcher (a resumed run) gives the same batch
    for key in a:
        torch.testing.assert_close(a[key], b[key])
    later = batcher.batch(8)
    assert not (torch.equal(a["cam"], later["cam"]) and torch.equal(a["row"], later["row"]))
    other = _batcher(seed=4)[0].batch(7)
    assert not torch.equal(a["row"], other["row"])
    assert step_seed(3, 7) == step_seed(3, 7) != step_seed(3, 8)
    np.testing.assert_allclose(a["rgb"].numpy(), images[a["cam"], a["row"], a["col"]])
    expected = rays_for_pixels(torch.as_tensor(poses), a["cam"], a["row"], a["col"], 12.0, 16, 10, 2.0, 6.0)
    for key, value in expected.items():
        torch.testing.assert_close(a[key], value)
    assert set(a["cam"].tolist()) == {0, 1, 2}
    with pytest.raises(ValueError) as err:
        batcher.batch(-1)
    one_line_error(err, "step must be >= 0, got -1")


def test_precrop_samples_only_the_image_centre_during_warm_up():
    batcher, _, _ = _batcher(precrop_iters=5, precrop_frac=0.5)
    assert batcher.pixel_ranges(0) == ((3, 7), (4, 12))  # rows 5 +- 2, columns 8 +- 4 (NeRF's dH, dW)
    for step in range(5):
        b = batcher.batch(step)
        assert b["row"].min() >= 3 and b["row"].max() <= 6 and b["col"].min() >= 4 and b["col"].max() <= 11
    late = batcher.batch(5)
    assert (
        late["row"].min() == 0
        and late["row"].max() == 9
        and late["col"].min() == 0
        and late["col"].max() == 15
    )


def test_batcher_from_a_loaded_split(tmp_path):
    write_scene(tmp_path)
    split = load_blender_split(tmp_path, "train")
    batcher = RayBatcher.from_split(split, near=2.0, far=6.0, batch_size=64, seed=0)
    b = batcher.batch(0)
    np.testing.assert_allclose(b["rgb"].numpy(), split.images[b["cam"], b["row"], b["col"]])
    np.testing.assert_allclose(b["radii"].numpy(), RADIUS_SCALE / split.focal, rtol=1e-6)


def test_alpha_is_present_in_every_frame_or_explicitly_absent(tmp_path):
    rgba = fixture_images()
    write_scene(tmp_path / "mixed", images=[rgba[0], rgba[1][..., :3]])  # frame 1 lost its alpha
    with pytest.raises(DataError) as excinfo:
        load_blender_split(tmp_path / "mixed", "train")
    one_line_error(excinfo, "r_1.png", "has no alpha channel", "expected RGBA", "like", "r_0.png")

    write_scene(tmp_path / "rgb", images=[img[..., :3] for img in rgba])
    assert (load_blender_split(tmp_path / "rgb", "train", alpha="rgb").alphas == 1).all()
    with pytest.raises(DataError) as excinfo:
        load_blender_split(tmp_path / "rgb", "train", alpha="rgba")
    one_line_error(excinfo, "r_0.png", "has no alpha channel", "dataset.alpha=rgba")
    with pytest.raises(DataError) as excinfo:
        load_blender_split(tmp_path / "mixed", "train", alpha="rgb")
    one_line_error(excinfo, "r_0.png", "has an alpha channel", "expected RGB (dataset.alpha=rgb)")
    with pytest.raises(ConfigError) as excinfo:
        load_blender_split(tmp_path / "rgb", "train", alpha="maybe")
    one_line_error(excinfo, "dataset.alpha='maybe'", "'rgba'")
