"""`stage=select_features` (dataset=volumetric): automatic auxiliary-feature selection after Zhang et al.
2022, as the 2023 production volumetric denoising talk (Zhu et al.) adapted it, and the choice of a run's
features from its result (`dataset.feature_selection.size`).

1. One probe denoiser (the run's `model`) is trained on the start set plus every candidate with random
   feature dropout (`DenoiserTrainer(probe=True)`): each sample drops each candidate with probability
   `dropout`, its channels set to their neutral values.
2. Greedy forward selection with that probe and no retraining (`feature_selection.greedy_forward_selection`):
   from the start set (the noisy colour), each round adds the candidate whose addition lowers the probe's
   validation loss most, every feature not selected held at its neutral value.

Writes, under `dataset.feature_selection.dir`: `probe/` (its checkpoints and curves), `selection.json` (the
ordered rows, what made them), `selection.csv` (the talk's "Table 1": rank, feature, channels, validation
loss) and `selection_curve.png` (loss against the number of features); all are also MLflow artifacts of
the run, with `select_loss` logged per round. A later run with `size=k` trains on the start set plus the
first k (`src.data.feature_choice.features_for_size`, read by the data kind when a job starts), so the
feature count follows a storage budget without a new selection.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from src.data.feature_choice import SELECTION_FILE, selection_candidates
from src.data.volume_features import volume_feature_channels
from src.io.atomic import atomic_path, atomic_write_csv, atomic_write_json
from src.provenance import provenance
from src.train import feature_selection as fs
from src.train.checkpoint import resumable_checkpoint
from src.train.loop import Means
from src.train.trainer import DenoiserTrainer, flatten_frames


def probe_config(cfg: DictConfig) -> DictConfig:
    """The run's config as the probe trains: every candidate as input, its own checkpoints and curves."""
    sel = cfg.dataset.feature_selection
    start = [str(f) for f in sel.start]
    probe = copy.deepcopy(cfg)
    probe.dataset.volume_features = start + selection_candidates(start, sel.candidates)
    probe.dataset.feature_selection.size = None
    probe_dir = Path(sel.dir) / "probe"
    probe.task.train.checkpoint_dir = str(probe_dir / "checkpoints")
    probe.task.train.curves_file = str(probe_dir / "curves.csv")
    return probe


@torch.no_grad()
def _validation_loss(trainer: DenoiserTrainer, batches: list[dict], keep: torch.Tensor) -> float:
    """The probe's mean validation objective with only the `keep` features (others neutral)."""
    means = Means()
    for batch in batches:
        n, k = batch["color"].shape[:2]
        frames = flatten_frames(batch)
        mask = keep.expand(n * k, -1)
        key = trainer.dropout.key
        frames[key] = fs.drop_features(
            frames[key], mask, trainer.dropout.slices, trainer.dropout.neutral, channel_axis=1
        )
        losses = trainer.losses_of_frames(frames, batch, n, k)
        means.add({"total": float(losses["total"])}, n)
    return means.result()["total"]


def _save_curve(path: Path, rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([r["round"] for r in rows], [r["loss"] for r in rows], marker="o")
    for r in rows[1:]:
        ax.annotate(r["added"], (r["round"], r["loss"]), fontsize=6, rotation=45, ha="left", va="bottom")
    ax.set_xlabel("features added to the noisy colour")
    ax.set_ylabel("probe validation loss")
    ax.set_title("Greedy forward feature selection (probe, no retraining)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def probe_kind(kind: Any, probe: DictConfig) -> Any:
    """The run's data kind with the probe's options (`probe_config`'s `dataset:`): every candidate read;
    None stays None (a stand-in probe of the tests reads no data)."""
    return None if kind is None else type(kind)(**OmegaConf.to_container(probe.dataset, resolve=True))


def select_features(cfg: DictConfig, tracker, kind: Any) -> dict[str, Any]:
    """Train the probe on the data kind `kind`'s samples, run the greedy selection, write and log the
    ordered table (module docstring)."""
    sel = cfg.dataset.feature_selection
    probe = probe_config(cfg)
    trainer = DenoiserTrainer(probe, tracker, probe=True, kind=probe_kind(kind, probe))
    checkpoint = resumable_checkpoint(probe)
    if checkpoint:
        trainer.restore(checkpoint)
    summary = trainer.fit()
    trainer.model.eval()
    total = math.ceil(len(trainer.val_data) / int(cfg.task.train.batch_size))
    keep = set(fs.spread_indices(total, sel.val_batches))
    batches = [b for i, b in enumerate(trainer._batches(trainer.val_data, epoch=0)) if i in keep]
    features = [name for name, _ in trainer.dropout.slices]

    def loss_of(subset) -> float:
        keep = fs.keep_only(subset, features).to(trainer.device)
        return _validation_loss(trainer, batches, keep)

    start = [str(f) for f in sel.start]
    candidates = [f for f in features if f not in start]
    rows = fs.greedy_forward_selection(loss_of, candidates, start, max_size=sel.max_size)
    for row in rows:
        row["channels"] = len(volume_feature_channels(row["features"]))
        tracker.log_metrics(
            {"select_loss": row["loss"], "select_channels": row["channels"]}, step=row["round"]
        )
    out = Path(sel.dir)
    table = [
        {
            "rank": r["round"],
            "feature": r["added"] or "+".join(start),
            "channels": r["channels"],
            "val_loss": r["loss"],
        }
        for r in rows
    ]
    atomic_write_csv(out / "selection.csv", table)
    _save_curve(out / "selection_curve.png", rows)
    record = {
        "model": cfg.model.name,
        "start": start,
        "candidates": candidates,
        "rows": rows,
        "probe": {k: summary[k] for k in ("steps", "train_time_s", "param_count")},
        "provenance": provenance(cfg, Path(cfg.paths.raw)),
        "settings": OmegaConf.to_container(sel, resolve=True),
    }
    atomic_write_json(out / SELECTION_FILE, record)  # last: its presence means the selection is complete
    for name in (SELECTION_FILE, "selection.csv", "selection_curve.png"):
        tracker.log_artifact(str(out / name), "feature_selection")
    order = ", ".join(r["added"] for r in rows[1:])
    print(f"select_features: {len(rows) - 1} rounds, order: {order} -> {out / SELECTION_FILE}")
    return {"rows": rows, "dir": str(out)}
