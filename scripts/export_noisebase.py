"""Export nrbench's volumetric sequences as a Noisebase sample set (issue 35; docs/noisebase.md).

python scripts/export_noisebase.py OUT [--format training|test] [--spp N] [--scenes a,b]
    [--frames F --pan-deg D] [OVERRIDE ...]

composes the root config as `python -m src.run` would (dataset=volumetric unless an override names
another dataset; e.g. profile=smoke, dataset.frames=4), renders every frame of the chosen scenes once per
sample with distinct seeds (dataset=volumetric: its animations; dataset=procedural: each still scene as F
frames whose camera pans by D degrees per frame), and writes a training-format store per sequence
(OUT/scene{index:04d}.zip) or test-format stores per frame (OUT/<scene>/frame{index:04d}.zip), readable
by the `noisebase` package's loaders (src/render/noisebase_export.py). Bad input: one line, exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv: list[str]) -> int:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from src.errors import ConfigError, DataError
    from src.render.noisebase_export import export_still_sequences, export_volumetric_sequences

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--format", choices=["training", "test"], default="training")
    parser.add_argument("--spp", type=int, default=8, help="samples per pixel stored (default 8)")
    parser.add_argument("--scenes", default=None, help="comma-separated scene names (default: all)")
    parser.add_argument("--frames", type=int, default=8, help="dataset=procedural: frames per sequence")
    parser.add_argument("--pan-deg", type=float, default=1.0, help="dataset=procedural: pan per frame")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. profile=smoke")
    args = parser.parse_intermixed_args(argv)
    overrides = list(args.overrides)
    if not any(o.startswith("dataset=") for o in overrides):
        overrides.insert(0, "dataset=volumetric")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    ds = OmegaConf.to_container(cfg.dataset, resolve=True)
    target, scenes = str(ds.get("_target_", "")), (args.scenes.split(",") if args.scenes else None)
    try:
        if target == "src.kinds.sequences.RenderedSequences":
            written = export_volumetric_sequences(
                ds, args.out, args.format, args.spp, scenes, cfg.render.variant
            )
        elif target == "src.kinds.stills.RenderedStills":
            written = export_still_sequences(
                ds, args.out, args.format, args.spp, args.frames, args.pan_deg, scenes, cfg.render.variant
            )
        else:
            raise ConfigError(
                f"dataset={ds.get('name')}: the export renders dataset=volumetric's sequences or "
                "dataset=procedural's scenes"
            )
    except (ConfigError, DataError) as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return 2
    print(f"export: {len(written)} Noisebase {args.format}-format stores ({args.spp} spp) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
