"""Training, evaluation and feature selection on the volumetric sequences (issue 17), end to end on a
tiny synthetic prepared dataset (`tests/test_volume_shards.py`'s frames): the sequence trainer's losses,
the evaluation's flicker column, `stage=select_features` and `dataset.feature_selection.size`, and their
one-line errors from the command line."""

from __future__ import annotations

import json
import subprocess

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch

from src.data.volume_features import VOLUME_CANDIDATE_FEATURES
from src.errors import ConfigError
from src.eval.denoise_eval import DenoiseEvaluation
from src.stages import evaluate, select_features, task_of, train
from src.tasks.denoise import DenoiseTask
from src.tracking.mlflow_tracking import job_run
from src.tracking.tracker import Tracker
from src.train.checkpoint import load_checkpoint
from src.train.trainer import DenoiserTrainer
from tests.conftest import (
    ROOT,
    cli_job,
    compose_config,
    data_kind,
    one_line_cli_error,
    one_line_error,
    smoke_config,
)
from tests.test_temporal import _np_temporal_loss
from tests.test_volume_shards import SPPS, synthetic_frame

SMALL = ["task.train.epochs=2", "task.train.batch_size=4", "task.eval.save_exr=false"]
FAST_METRICS = ["metrics.lpips.enabled=false", "metrics.flip.enabled=false"]


def _cfg(data, run_dir, *overrides):
    base = ["dataset=volumetric", "model=unet_kpcn", *SMALL, *FAST_METRICS]
    return smoke_config(data, run_dir, [*base, *overrides])


def test_sequence_training_fits_smape_plus_weighted_temporal_loss_and_logs_each_term(vol_data, tmp_path):
    cfg = _cfg(vol_data, tmp_path, "dataset.train.temporal_weight=0.5")
    with job_run(cfg, run_name="unet-test", tags={}) as tracker:
        summary = train(cfg, tracker)
        evaluate(cfg, tracker)
        run_id = tracker.run_id
    client = mlflow.MlflowClient(cfg.tracking.uri)
    metrics = client.get_run(run_id).data.metrics
    for split in ("train", "val"):
        for term in ("color", "temporal", "total"):
            assert f"{split}_loss_{term}" in metrics, (split, term)
    curves = pd.read_csv(tmp_path / "curves.csv")
    expected = curves["val_loss_color"] + 0.5 * curves["val_loss_temporal"]
    pd.testing.assert_series_equal(curves["val_loss_total"], expected, check_names=False, rtol=1e-5)
    state = load_checkpoint(summary["checkpoint"])
    assert state["features"] is None  # every candidate
    rows = pd.read_csv(tmp_path / "eval" / "per_image.csv")
    assert len(rows) == 2 and set(rows["frames"]) == {4}  # the test scene at 2 and 8 spp, 4 frames each
    # The flicker of the output, not of the input (its value: the stub-denoiser test below); logged as the
    # rows' mean and per spp.
    assert (rows["temporal"] > 0).all() and (rows["noisy_temporal"] > 0).all()
    assert (rows["temporal"] != rows["noisy_temporal"]).all()
    assert metrics["eval_temporal"] == pytest.approx(rows["temporal"].mean(), rel=1e-6)
    assert metrics["eval_noisy_temporal"] == pytest.approx(rows["noisy_temporal"].mean(), rel=1e-6)
    spp2 = rows.loc[rows["spp"] == 2, "temporal"].item()
    assert metrics["eval_temporal_spp2"] == pytest.approx(spp2, rel=1e-6)
    assert len(list((tmp_path / "eval" / "strips").glob("*.png"))) == 2  # the middle frame of each


#: The known output of the stub denoiser below: each reference frame scaled by its own factor, so the
#: output moves, but not as the reference does, and unlike the noisy input.
_FRAME_SCALES = torch.tensor([1.0, 0.6, 1.5, 0.8])


def _reinhard(x, gamma=2.2):
    positive = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    return (positive / (1.0 + positive)) ** (1.0 / gamma)


def _flicker_by_hand(frames, reference):
    """mean over pairs (t, t+1) of mean |Δ tm(frames) - Δ tm(reference)|, Reinhard + gamma 2.2."""
    pairs = [
        (_reinhard(frames[t + 1]) - _reinhard(frames[t]))
        - (_reinhard(reference[t + 1]) - _reinhard(reference[t]))
        for t in range(len(frames) - 1)
    ]
    return float(np.mean([np.abs(d).mean() for d in pairs]))


def test_the_flicker_column_is_the_metric_of_the_denoised_frames(vol_data, tmp_path, monkeypatch):
    """Sequence evaluation with a stub denoiser of known output (the reference frames scaled per frame):
    `temporal` is the flicker of that output, `noisy_temporal` the noisy input's, both computed here from
    the synthetic raw frames; the means and the logged per-spp values are the rows'."""
    cfg = _cfg(
        vol_data, tmp_path, "model=cross_bilateral", "metrics.tonemap=reinhard_gamma", "metrics.gamma=2.2"
    )
    monkeypatch.setattr(
        DenoiseEvaluation,
        "infer",
        lambda self, item: item["item"]["reference"] * _FRAME_SCALES.view(4, 1, 1, 1),
    )
    evaluation = DenoiseEvaluation(cfg, Tracker(), data_kind(cfg))
    summary = evaluation.run(desc="stub")
    rows = pd.read_csv(tmp_path / "eval" / "per_image.csv")
    assert len(rows) == 2
    for row in rows.itertuples():
        frames = range(4)
        # The raw frames (H, W, 3): the highest sample count is the reference.
        reference = np.stack([synthetic_frame(row.scene, f, max(SPPS))["color"] for f in frames])
        noisy = np.stack([synthetic_frame(row.scene, f, row.spp)["color"] for f in frames])
        denoised = reference * _FRAME_SCALES.numpy().reshape(4, 1, 1, 1)
        expected, expected_noisy = _flicker_by_hand(denoised, reference), _flicker_by_hand(noisy, reference)
        assert row.temporal == pytest.approx(expected, rel=1e-5), row.spp
        assert row.noisy_temporal == pytest.approx(expected_noisy, rel=1e-5), row.spp
        assert abs(expected - expected_noisy) > 0.01  # the fixture tells output and input apart
    assert summary["mean"]["temporal"] == pytest.approx(rows["temporal"].mean(), rel=1e-12)
    logged = evaluation.logged_metrics(summary)
    for row in rows.itertuples():
        assert logged[f"eval_temporal_spp{row.spp}"] == pytest.approx(row.temporal, rel=1e-12)
        assert logged[f"eval_noisy_temporal_spp{row.spp}"] == pytest.approx(row.noisy_temporal, rel=1e-12)
    assert logged["eval_temporal"] == pytest.approx(rows["temporal"].mean(), rel=1e-12)


def test_the_temporal_weight_changes_the_objective_only_through_the_temporal_term(vol_data, tmp_path):
    batch = next(
        iter(torch.utils.data.DataLoader(_trainer(vol_data, tmp_path, 0.0).train_data, batch_size=3))
    )
    values = {w: _trainer(vol_data, tmp_path / str(w), w).losses(batch) for w in (0.0, 2.0)}
    torch.testing.assert_close(values[0.0]["color"], values[2.0]["color"])  # same seed: same weights
    torch.testing.assert_close(values[0.0]["total"], values[0.0]["color"])
    assert values[2.0]["temporal"] > 0
    torch.testing.assert_close(values[2.0]["total"], values[2.0]["color"] + 2.0 * values[2.0]["temporal"])


class _KnownOutput(torch.nn.Module):
    """A stand-in model whose linear colour output is given (signed, unlike any reference)."""

    def __init__(self, color):
        super().__init__()
        self.color = color

    def forward(self, frames):
        return {"color": self.color}


@pytest.mark.parametrize("mode", ["signed", "abs"])
def test_the_sequence_objective_is_smape_on_linear_plus_the_temporal_loss_of_the_transformed_output(
    vol_data, tmp_path, mode
):
    """By value, from a known output: SMAPE against the linear reference, the temporal loss of the
    log-modulus output against the stored (log-modulus) target, per pair in numpy, weighted 0.7."""
    trainer = _trainer(vol_data, tmp_path, 0.7, False, f"dataset.train.temporal_mode={mode}")
    batch = next(iter(torch.utils.data.DataLoader(trainer.train_data, batch_size=2)))
    n, k, _, h, w = batch["reference"].shape
    color = torch.randn((n * k, 3, h, w), generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 3
    trainer.model = _KnownOutput(color)
    values = trainer.losses(batch)
    output = color.view(n, k, 3, h, w).numpy()
    reference, target = batch["reference"].double().numpy(), batch["radiance_target"].double().numpy()
    smape = np.abs(output - reference) / (np.abs(output) + np.abs(reference) + 0.01)
    temporal = _np_temporal_loss(np.sign(output) * np.log1p(np.abs(output)), target, mode)
    assert values["color"].item() == pytest.approx(smape.mean(), rel=1e-5)
    assert values["temporal"].item() == pytest.approx(temporal, rel=1e-5)
    assert values["total"].item() == pytest.approx(smape.mean() + 0.7 * temporal, rel=1e-5)
    # The fixture tells the spaces apart: the temporal loss of the linear output, or against the linear
    # reference, is another number.
    assert _np_temporal_loss(output, target, mode) != pytest.approx(temporal, rel=1e-2)
    assert _np_temporal_loss(np.sign(output) * np.log1p(np.abs(output)), reference, mode) != pytest.approx(
        temporal, rel=1e-2
    )


def _trainer(data, run_dir, weight, probe=False, *overrides):
    cfg = _cfg(data, run_dir, f"dataset.train.temporal_weight={weight}", *overrides)
    return DenoiserTrainer(cfg, Tracker(), probe=probe, kind=data_kind(cfg))


def test_the_sequences_train_on_their_own_schedule_else_the_tasks(vol_data, tmp_path):
    """`dataset.train.schedule` (the talk's decay) replaces `task.train.schedule` on the sequences;
    null falls back to it (`RenderedSequences.schedule`)."""
    from src.train.schedules import log_linear_lr

    own = "{_target_: src.train.schedules.log_linear_lr, _partial_: true, lr_final: 1.0e-6}"
    task = "{_target_: src.train.schedules.log_linear_lr, _partial_: true, lr_final: 0.5}"
    schedules = {"dataset.train.schedule": own, "task.train.schedule": task}
    trainer = _trainer(vol_data, tmp_path / "own", 0.5, False, *(f"{k}={v}" for k, v in schedules.items()))
    assert trainer.schedule(5, lr_init=1.0, max_steps=10) == pytest.approx(log_linear_lr(5, 1.0, 1e-6, 10))
    fallback = _trainer(
        vol_data,
        tmp_path / "task",
        0.5,
        False,
        "dataset.train.schedule=null",
        f"task.train.schedule={task}",
    )
    assert fallback.schedule(5, lr_init=1.0, max_steps=10) == pytest.approx(log_linear_lr(5, 1.0, 0.5, 10))


def test_the_probe_drops_features_to_their_neutral_values_but_never_the_colour(vol_data, tmp_path):
    overrides = ("dataset.feature_selection.subsets=independent", "dataset.feature_selection.dropout=1.0")
    trainer = _trainer(vol_data, tmp_path, 0.5, True, *overrides)
    inputs = torch.rand((6, 62, 8, 8)) + 2.0  # no stored value is a neutral value
    dropped = trainer.dropout(inputs, 2, 3, step=0)
    names = [name for name, _ in trainer.dropout.slices]
    for name, channels in trainer.dropout.slices:
        expected = 1.0 if name == "transmittance" else 0.0
        if name in ("color", "color.var"):
            assert torch.equal(dropped[:, channels], inputs[:, channels]), name
        else:
            assert (dropped[:, channels] == expected).all(), name
    assert names == list(VOLUME_CANDIDATE_FEATURES)


def test_select_features_orders_the_candidates_and_size_picks_the_first_k(vol_data, tmp_path, caplog):
    overrides = [
        "dataset.feature_selection.candidates=[albedo,depth,transmittance,motion]",
        "task.train.epochs=1",
    ]
    cfg = _cfg(vol_data, tmp_path, *overrides)
    summary = select_features(cfg, Tracker())
    rows = summary["rows"]
    # Again (a requeued job): the probe continues its own checkpoint, trained to the end: the same rows.
    caplog.set_level("INFO")
    again = select_features(cfg, Tracker())["rows"]
    probe_last = vol_data / "volumetric" / "smoke" / "feature_selection" / "probe" / "checkpoints" / "last.pt"
    assert f"resumed from {probe_last}" in caplog.text and again == rows
    assert [r["round"] for r in rows] == [0, 1, 2, 3, 4] and rows[0]["features"] == ["color", "color.var"]
    assert sorted(r["added"] for r in rows[1:]) == ["albedo", "depth", "motion", "transmittance"]
    out = vol_data / "volumetric" / "smoke" / "feature_selection"
    table = pd.read_csv(out / "selection.csv")
    assert list(table["rank"]) == [0, 1, 2, 3, 4] and (out / "selection_curve.png").is_file()
    assert (out / "probe" / "checkpoints" / "final.pt").is_file()
    # A run with size=2 trains on the colour plus the first two, its model sized to match: settled when the
    # job starts (composing the config reads no stage's output).
    sized = _cfg(vol_data, tmp_path, "dataset.feature_selection.size=2")
    assert sized.dataset.volume_features is None
    task_of(sized).resolve_at_job_start(sized)
    assert list(sized.dataset.volume_features) == rows[2]["features"]
    assert sized.model.in_channels == 4 + sum(
        {"albedo": 3, "depth": 1, "transmittance": 1, "motion": 2}[f] for f in rows[2]["features"][2:]
    )
    random_arm = _cfg(
        vol_data, tmp_path, "dataset.feature_selection.size=2", "dataset.feature_selection.order=random"
    )
    task_of(random_arm).resolve_at_job_start(random_arm)
    assert len(random_arm.dataset.volume_features) == 4 and list(random_arm.dataset.volume_features)[:2] == [
        "color",
        "color.var",
    ]
    assert json.loads((out / "selection.json").read_text())["provenance"]["git_commit"]


def test_select_features_ranks_by_the_probes_loss_on_the_spread_validation_batches(tmp_path, monkeypatch):
    """The stage around a fixed probe with a known answer (the set cover of tests/test_feature_selection.py)
    instead of a trained one: its order, losses, channel counts, table, logged curve and `size` arms."""
    from omegaconf import OmegaConf

    from src.data.feature_choice import features_for_size
    from src.train import select_features as stage
    from src.train.trainer import _FeatureDropout
    from tests.test_feature_selection import COVER_NEUTRAL, _cover_inputs, _cover_probe_loss

    candidates = ["transmittance", "depth", "sigma_t", "albedo.var"]
    sel_dir = tmp_path / "selection"
    cfg = OmegaConf.create(
        {
            "seed": 3,
            "model": {"name": "fixed_probe"},
            "paths": {"raw": str(tmp_path / "raw")},
            "task": {"train": {"resume": None, "batch_size": 2, "checkpoint_dir": "x", "curves_file": "x"}},
            "dataset": {
                "volume_features": None,
                "feature_selection": {
                    "size": None,
                    "order": "greedy",
                    "random_seed": 0,
                    "start": ["color"],
                    "candidates": candidates,
                    "subsets": "uniform_size",
                    "dropout": 0.5,
                    "neutral": COVER_NEUTRAL,
                    "max_size": None,
                    "val_batches": 2,
                    "dir": str(sel_dir),
                },
            },
        }
    )
    # Four validation batches (8 samples / batch_size 2); val_batches=2 scores batches 0 and 2 only, per
    # sample. Batches 1 and 3 hold only component 4, which albedo.var alone explains: were they scored,
    # albedo.var would come first.
    amps = [
        (3, {1: 1.0, 2: 1.0, 3: 1.0, 4: 0.0}),
        (1, {1: 0.0, 2: 0.0, 3: 0.0, 4: 8.0}),
        (1, {1: 2.0, 2: 2.0, 3: 2.0, 4: 0.0}),  # 4x the energy, 1 sample of 4 scored
        (2, {1: 0.0, 2: 0.0, 3: 0.0, 4: 8.0}),
    ]
    batches = []
    for n, amp in amps:
        inputs, reference = _cover_inputs(n, [amp] * n)
        k = 2  # two identical frames per sample
        batches.append(
            {
                "radiance_in": inputs.unsqueeze(1).expand(n, k, *inputs.shape[1:]),
                "reference": reference.unsqueeze(1).expand(n, k, *reference.shape[1:]),
                "color": reference.unsqueeze(1).expand(n, k, *reference.shape[1:]),
            }
        )
    made = []

    class FixedProbe:
        device = torch.device("cpu")
        model = torch.nn.Identity()
        val_data = list(range(8))

        def __init__(self, probe_cfg, tracker, probe=False, kind=None):
            made.append((probe_cfg, probe))
            self.dropout = _FeatureDropout(probe_cfg, list(probe_cfg.dataset.volume_features), "radiance_in")

        def fit(self):
            return {"steps": 0, "train_time_s": 0.0, "param_count": 0}

        def _batches(self, data, epoch):
            return iter(batches)

        def losses_of_frames(self, frames, batch, n, k):
            names = [name for name, _ in self.dropout.slices]
            loss = _cover_probe_loss(frames["radiance_in"], frames["reference"], names, COVER_NEUTRAL)
            return {"total": torch.tensor(loss)}

    class Recorder:
        def __init__(self):
            self.metrics, self.artifacts = [], []

        def log_metrics(self, metrics, step):
            self.metrics.append((step, metrics))

        def log_artifact(self, path, artifact_path):
            self.artifacts.append((path, artifact_path))

    monkeypatch.setattr(stage, "DenoiserTrainer", FixedProbe)
    tracker = Recorder()
    rows = stage.select_features(cfg, tracker, kind=None)["rows"]
    probe_cfg, probe = made[0]
    assert probe and list(probe_cfg.dataset.volume_features) == ["color", *candidates]  # all, start first
    order = ["transmittance", "sigma_t", "depth", "albedo.var"]  # by marginal gain, ties to the earlier
    assert [r["added"] for r in rows] == [None, *order]
    losses = [(3 * 9 / 16 + 4 * 9 / 16) / 4, (3 * 3 / 16 + 4 * 3 / 16) / 4, 0.0, 0.0, 0.0]
    assert [r["loss"] for r in rows] == losses
    channels = [3, 6, 9, 10, 11]
    assert [r["channels"] for r in rows] == channels
    steps = enumerate(zip(losses, channels, strict=True))
    assert tracker.metrics == [(i, {"select_loss": loss, "select_channels": c}) for i, (loss, c) in steps]
    table = pd.read_csv(sel_dir / "selection.csv")
    assert table.to_dict("list") == {
        "rank": [0, 1, 2, 3, 4],
        "feature": ["color", *order],
        "channels": channels,
        "val_loss": losses,
    }
    record = json.loads((sel_dir / "selection.json").read_text())
    assert record["start"] == ["color"] and record["candidates"] == candidates and record["rows"] == rows
    assert {a for _, a in tracker.artifacts} == {"feature_selection"} and len(tracker.artifacts) == 3
    # `size` = k: the start set plus the first k of that order; the random arm k of the candidates
    sized = OmegaConf.merge(cfg.dataset.feature_selection, {"size": 2})
    assert features_for_size(sized) == ["color", "transmittance", "sigma_t"]
    arm = features_for_size(OmegaConf.merge(sized, {"order": "random", "random_seed": 4}))
    assert arm[0] == "color" and len(set(arm[1:])) == 2 and set(arm[1:]) <= set(candidates)
    with pytest.raises(ConfigError, match=r"dataset\.feature_selection\.start"):
        features_for_size(OmegaConf.merge(sized, {"start": ["color", "color.var"]}))


def test_a_selected_size_without_a_selection_is_one_line_from_the_command_line(tmp_path):
    """The resolver's error reaches the user as one line (exit 2), though OmegaConf wraps it."""
    args = ["dataset=volumetric", "stage=train", "dataset.feature_selection.size=3", "profile=smoke"]
    command, env = cli_job(args, tmp_path)
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    one_line_cli_error(result, "dataset.feature_selection.size=3", "stage=select_features")


def test_feature_selection_needs_the_volumetric_candidates(tmp_path):
    cfg = smoke_config(tmp_path, tmp_path / "run", ["stage=select_features"])
    with pytest.raises(ConfigError) as excinfo:
        DenoiseTask.for_run(cfg).check_stages(["select_features"], cfg)
    one_line_error(excinfo, "stage=select_features", "dataset=volumetric")


@pytest.mark.slow
def test_an_interrupted_probe_resumes_to_the_weights_of_an_uninterrupted_one(vol_data, tmp_path):
    """The probe's dropout masks depend on (seed, step) only, so resuming inside an epoch replays them."""
    from src.train.loop import run_training
    from tests.conftest import stop_at

    def probe_trainer(cfg, tracker, on_step=None):
        return DenoiserTrainer(cfg, tracker, on_step, probe=True, kind=data_kind(cfg))

    def cfg(name, *extra):
        return _cfg(vol_data, tmp_path / name, "task.train.epochs=2", "tracking.enabled=false", *extra)

    logged = ("steps",)
    straight = run_training(probe_trainer, cfg("a"), Tracker(), None, logged)
    with pytest.raises(KeyboardInterrupt):
        run_training(probe_trainer, cfg("b"), Tracker(), stop_at(straight["steps"] // 2 + 1), logged)
    resumed = run_training(
        probe_trainer, cfg("c", f"task.train.resume={tmp_path}/b/checkpoints"), Tracker(), None, logged
    )
    assert resumed["steps"] == straight["steps"]
    a, c = load_checkpoint(straight["checkpoint"])["model"], load_checkpoint(resumed["checkpoint"])["model"]
    for key, value in a.items():
        assert torch.equal(c[key], value), key


def test_a_selection_file_naming_an_unknown_feature_is_one_line_at_job_start(tmp_path):
    """The features a selection file names are checked when the job settles them, as the schema checks
    configured ones: a hand-edited `selection.json` is one line naming dataset.volume_features."""
    rows = [{"features": ["color", "color.var"]}, {"features": ["color", "color.var", "fog_density"]}]
    (tmp_path / "selection.json").write_text(json.dumps({"rows": rows}))
    cfg = compose_config(
        [
            "dataset=volumetric",
            f"dataset.feature_selection.dir={tmp_path}",
            "dataset.feature_selection.size=1",
        ]
    )
    with pytest.raises(ConfigError) as err:
        DenoiseTask.for_run(cfg).resolve_at_job_start(cfg)
    one_line_error(err, "dataset.volume_features[2]='fog_density'", "expected a buffer of")
    assert cfg.dataset.volume_features is None  # nothing settled
    rows[1]["features"][2] = "sigma_t"
    (tmp_path / "selection.json").write_text(json.dumps({"rows": rows}))
    DenoiseTask.for_run(cfg).resolve_at_job_start(cfg)
    assert list(cfg.dataset.volume_features) == ["color", "color.var", "sigma_t"]


@pytest.mark.parametrize("model", ["kpcn", "dpcn"])
def test_kernel_prediction_and_direct_regression_train_and_score_on_the_sequences(vol_data, tmp_path, model):
    """The `kernel_vs_direct` study's two arms on the sequences' one radiance branch: each trains and
    scores the held-out frames; DPCN regresses the colour directly, KPCN predicts kernels."""
    cfg = smoke_config(
        vol_data,
        tmp_path,
        ["dataset=volumetric", f"model={model}", *SMALL, *FAST_METRICS, "task.train.epochs=1"],
    )
    assert list(cfg.model.branches) == ["radiance"] and cfg.model.output == (
        "direct" if model == "dpcn" else "kernel"
    )
    train(cfg, Tracker(None))
    evaluate(cfg, Tracker(None))
    rows = pd.read_csv(tmp_path / "eval" / "per_image.csv")
    assert len(rows) == 2 and rows["psnr"].notna().all() and set(rows["frames"]) == {4}


def test_dpcn_trains_twice_kpcns_epochs_on_the_sequences_at_cpu():
    """The ratio the kpcn_beats_dpcn_volumetric rule declares ({task.train.epochs: 2}), read from the
    composed configs of the study's two arms."""
    epochs = {
        m: compose_config(["dataset=volumetric", f"model={m}", "profile=cpu"]).task.train.epochs
        for m in ("kpcn", "dpcn")
    }
    assert epochs == {"kpcn": 8, "dpcn": 16}
