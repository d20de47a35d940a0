"""A small writer of Noisebase sample sets, independent of nrbench's reader and exporter and of the
`noisebase` package's encoder: it writes the arrays of the documented formats (`docs/noisebase.md`;
`sample_training_v1.md`, `sample_test_v1.md` in the package's repository) from known numpy values, so
that tests compare what is read against numbers they know.

Colour is written as RGBE bytes drawn at random with their exposure range; the radiance each sample
stands for is the documented decoding, computed here in float64: `byte / 255 * exp((e + 1) / 256 *
(max - min) + min)`. Cameras look at the origin from a position that moves per frame; the view-projection
matrix is built as the package builds it (row vectors: `[p, 1] @ view_proj`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr

#: A perspective matrix of the package's docstring (`noisebase.projective.FlipRotate.apply_camera`).
PROJ = np.array(
    [[0.984375, 0.0, 0.0, 0.0], [0.0, 1.75, 0.0, 0.0], [0.0, 0.0, 1.0001, -0.10001], [0.0, 0.0, 1.0, 0.0]],
    np.float32,
)


def decoded_rgbe(rgbe: np.ndarray, exposure: np.ndarray) -> np.ndarray:
    """The documented RGBE decoding, in float64: (4, ...) bytes -> (3, ...) radiance."""
    lo, hi = float(exposure[0]), float(exposure[1])
    scale = np.exp((rgbe[3].astype(np.float64) + 1) / 256 * (hi - lo) + lo)
    return rgbe[:3].astype(np.float64) / 255 * scale


def view_proj(position, target, up, proj=PROJ) -> np.ndarray:
    """World -> clip, row vectors: the basis rows (right, up, forward) times the translation, transposed."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, up)
    right = right / np.linalg.norm(right)
    upv = np.cross(right, forward)
    upv = upv / np.linalg.norm(upv)
    view = np.eye(4)
    view[:3, :3] = np.stack([right, upv, forward])
    view[:3, 3] = -view[:3, :3] @ position
    return (view.T @ proj.T).astype(np.float32)


def cameras(frames: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per-frame cameras circling the origin at distance 5, looking at it, +Y up."""
    angle = 0.05 * np.arange(frames) + rng.uniform(0, 2 * np.pi)
    pos = np.stack([5 * np.sin(angle), 0.5 + 0.1 * np.arange(frames), 5 * np.cos(angle)], 1).astype(
        np.float32
    )
    target = np.zeros((frames, 3), np.float32)
    up = np.tile(np.float32([0, 1, 0]), (frames, 1))
    vp = np.stack([view_proj(pos[f], target[f], up[f]) for f in range(frames)])
    return {
        "camera_position": pos,
        "camera_target": target,
        "camera_up": up,
        "proj_mat": np.tile(PROJ, (frames, 1, 1)),
        "view_proj_mat": vp,
    }


def frame_arrays(frames: int, height: int, width: int, spp: int, rng: np.random.Generator) -> dict:
    """Every per-sample array of `frames` frames (leading F axis) and the radiance they encode."""
    shape = (frames, 3, height, width, spp)
    rgbe = rng.integers(0, 256, (frames, 4, height, width, spp)).astype(np.uint8)
    exposure = np.stack([rng.uniform(-4, -1, frames), rng.uniform(1, 3, frames)], 1).astype(np.float32)
    normal = rng.normal(size=shape)
    normal = (normal / np.linalg.norm(normal, axis=1, keepdims=True)).astype(np.float16)
    return {
        "color": rgbe,
        "exposure": exposure,
        "reference": rng.uniform(0, 2, (frames, 3, height, width)).astype(np.float32),
        "position": rng.uniform(-1, 1, shape).astype(np.float32),
        "motion": rng.uniform(-0.01, 0.01, shape).astype(np.float32),
        "normal": normal,
        "diffuse": rng.uniform(0, 1, shape).astype(np.float16),
        "radiance": np.stack([decoded_rgbe(rgbe[f], exposure[f]) for f in range(frames)]),
    }


def _write(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    store = zarr.ZipStore(str(path), mode="w")
    group = zarr.group(store=store)
    for name, value in arrays.items():
        group.create_dataset(name, data=value, chunks=value.shape)
    store.close()


def write_training_sequence(
    path, frames=2, size=16, spp=4, seed=0, rendering=(64, 96), skip=(), replace=None
) -> dict[str, np.ndarray]:
    """One training-format store (`scene{index:04d}.zip`): `frames` crops of `size` x `size` at moving
    offsets inside a `rendering` (height, width) camera frame. `skip` leaves arrays out and `replace`
    swaps some for others (bad files for the error tests). Returns every array written, plus `radiance`
    (F, 3, H, W, S), the colour the RGBE bytes encode."""
    rng = np.random.default_rng(seed)
    data = frame_arrays(frames, size, size, spp, rng) | cameras(frames, rng)
    data["crop_offset"] = np.stack([[4 + f, 8 + 2 * f] for f in range(frames)]).astype(
        np.int32
    )  # (row, column), moving
    stored = {k: v for k, v in data.items() if k != "radiance" and k not in skip} | (replace or {})
    _write(Path(path), stored)
    return data


def write_test_sequence(folder, name, frames=2, height=72, width=16, spp=4, seed=0) -> dict[str, np.ndarray]:
    """A test-format sequence: `frames` stores `<folder>/<name>/frame{index:04d}.zip`, each a whole camera
    frame (no F axis). Returns the arrays stacked over frames, plus `radiance`."""
    rng = np.random.default_rng(seed)
    data = frame_arrays(frames, height, width, spp, rng) | cameras(frames, rng)
    data["crop_offset"] = np.zeros((frames, 2), np.int32)
    for f in range(frames):
        _write(
            Path(folder) / name / f"frame{f:04d}.zip",
            {k: v[f] for k, v in data.items() if k != "radiance"},
        )
    return data


def package_training_loader(root, frames: int, crop: int, rendering: tuple[int, int], samples: int, buffers):
    """The `noisebase` package's own training loader (1.1.1) over `<root>/train/scene0000.zip`, one
    sequence, no flips: what the tests compare our reader and our exporter against; index it with
    `{"idx": frame, "epoch": 0}`."""
    from noisebase.loaders.torch.training_sample_v1 import TrainingSampleDataset
    from noisebase.torch import Shuffler

    src = {
        "files": "train/scene{index:04d}.zip",
        "frames_per_sequence": frames,
        "crop": crop,
        "rendering_height": rendering[0],
        "rendering_width": rendering[1],
        "sequences": 1,
    }
    return TrainingSampleDataset(
        src=src,
        sequence_idxs=[0],
        rng=Shuffler(0),
        flip_rotate=False,
        buffers=list(buffers),
        samples=samples,
        data_path=str(root),
        batch_size=1,
    )


def package_test_loader(root, name: str, frames: int, rendering: tuple[int, int], samples: int, buffers):
    """The `noisebase` package's own test loader (1.1.1) over `<root>/test8/<name>/frame*.zip`; index it
    with a frame number (it keeps rows 28:-28 of each frame)."""
    from noisebase.loaders.torch.test_sample_v1 import TestSampleDataset

    return TestSampleDataset(
        sequence={"name": name, "frames": frames},
        src={
            "files": "test8/{sequence_name}/frame{index:04d}.zip",
            "rendering_height": rendering[0],
            "rendering_width": rendering[1],
        },
        buffers=list(buffers),
        data_path=str(root),
        samples=samples,
    )
