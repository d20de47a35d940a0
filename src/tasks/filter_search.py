"""The filter-search task (`task=filter_search`): evolve filter weight expressions with genetic
programming (Davletaliyev 2016, Ch. 3; `src.gp.search`) on the denoising dataset, then evaluate the best
one as `model=gp_filter` with the denoise evaluation.

    render, preprocess  the denoise task's (same settings, so the prepared data are shared)
    search              the GP on the full images of `task.search.split`; per generation each island's best
                        and mean fitness (and count of undefined expressions) go to MLflow, the best
                        expression to the tag `search.best_expression`; writes under `task.search.out_dir`
                        state.json (the checkpoint, after every generation), history.json and
                        best_expressions.yaml (each island's best, as `model=gp_filter` settings)
    eval                the best expression of best_expressions.yaml as a GPFilter on `task.eval.split`,
                        through `src.eval.denoise_eval` (relMSE, PSNR, SSIM, time in the usual tables)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import torch
import yaml
from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError, DataError
from src.models.filters.gp_filter import GPFilter
from src.schema.filter_search import FilterSearchTaskSchema
from src.tasks.denoise import DenoiseTask

BEST_FILE = "best_expressions.yaml"
ISLANDS_FILE = "islands.csv"
#: Held-out means in islands.csv, beside each island's fitness and expression.
ISLAND_COLUMNS = ("psnr", "ssim", "relmse", "relmse_ratio", "undefined", "ms_per_mpixel")
STATE_FILE = "state.json"
HISTORY_FILE = "history.json"


def resumable_search_state(cfg: DictConfig) -> Path | None:
    """The search checkpoint a job of `cfg` continues: `task.search.resume` when set; else, with
    `auto_resume`, `state.json` in `task.search.out_dir` when the same configuration wrote it (a requeued
    job in its own run folder); else None (start over)."""
    from src.gp.search import saved_job
    from src.provenance import continued_in_place

    if cfg.task.search.resume is not None:
        return Path(cfg.task.search.resume)
    path = Path(cfg.task.search.out_dir) / STATE_FILE
    return path if continued_in_place(cfg, path, lambda p: saved_job(p).get("config_digest")) else None


def search_params(cfg: DictConfig):
    """`task.search` as `src.gp.search.SearchParams`."""
    from src.gp.search import SearchParams

    s = OmegaConf.to_container(cfg.task.search, resolve=True)
    keys = SearchParams.__dataclass_fields__
    return SearchParams(**{k: s[k] for k in keys})


def seed_expression(cfg: DictConfig) -> str:
    """The cross-bilateral seed (Sec. 3.2.5) with `task.search.seed_sigmas`."""
    from src.gp.published import bilateral_expression

    s = cfg.task.search.seed_sigmas
    return bilateral_expression(s.spatial, s.color, s.normal, s.albedo, s.depth)


def _feature_builder(cfg: DictConfig, expression: str):
    """A GPFilter whose `features` builds the terminals (its `needed` is set per use)."""
    from src.data.features import input_features
    from src.models.filters.gp_filter import GPFilter

    search = cfg.task.search
    return GPFilter(expression, int(search.radius), input_features(cfg), bool(search.normalize))


def search_image_indices(
    images: list[dict[str, Any]], spp: list[int] | None, max_images: int | None
) -> list[int]:
    """Indices of the split's images (index entries with `spp`) the search trains on: those at one of the
    sample counts `spp` (None: all), the first `max_images` of them (None: all)."""
    wanted = [i for i, meta in enumerate(images) if spp is None or int(meta["spp"]) in spp]
    return wanted if max_images is None else wanted[: int(max_images)]


def training_images(cfg: DictConfig) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
    """The search's images as one batch (N, C, H, W) per key, and each image's scene/spp."""
    from src.data.denoise_dataset import FullImageDataset
    from src.data.features import input_features

    search = cfg.task.search
    data = FullImageDataset(cfg.paths.prepared, str(search.split), features=input_features(cfg))
    wanted = search_image_indices(data.images, search.spp, search.max_images)
    if not wanted:
        spp = "" if search.spp is None else f" at task.search.spp={list(search.spp)}"
        raise DataError(f"{cfg.paths.prepared}/full/{search.split}: no images to search on{spp}")
    items = [data[i] for i in wanted]
    shapes = {tuple(item["color"].shape) for item in items}
    if len(shapes) > 1:
        raise DataError(f"task.search.split={search.split}: images of different sizes {sorted(shapes)}")
    keys = [k for k, v in items[0].items() if isinstance(v, torch.Tensor)]
    batch = {k: torch.stack([item[k] for item in items]).float() for k in keys}
    meta = [{"scene": item["scene"], "spp": int(item["spp"])} for item in items]
    return batch, meta


def _crop(x: torch.Tensor, size: int | None) -> torch.Tensor:
    if size is None:
        return x
    h, w = x.shape[-2:]
    ch, cw = min(size, h), min(size, w)
    top, left = (h - ch) // 2, (w - cw) // 2
    return x[..., top : top + ch, left : left + cw]


def available_terminals(builder, batch: dict[str, torch.Tensor]) -> list[str]:
    """The grammar's feature terminals the batch can give (`GPFilter.features` builds each or names what
    is missing): the search grammar draws only these."""
    from src.gp.grammar import ALL_VARIABLES, VECTORS

    out = []
    for name in (*VECTORS, *ALL_VARIABLES):
        if name == "pixel":
            continue
        builder.needed = {name}
        try:
            builder.features(batch)
        except ConfigError:
            continue
        out.append(name)
    return out


def build_fitness(cfg: DictConfig, device: torch.device):
    """(fitness, available terminals, image meta) of the search's images on `device`."""
    from src.gp.fitness import Fitness

    search = cfg.task.search
    batch, meta = training_images(cfg)
    builder = _feature_builder(cfg, seed_expression(cfg))
    available = available_terminals(builder, batch)
    builder.needed = set(available)
    features = {k: _crop(v, search.crop).to(device) for k, v in builder.features(batch).items()}
    color = _crop(batch["color"], search.crop).to(device)
    reference = _crop(batch["reference"], search.crop).to(device)
    fitness = Fitness(
        features,
        color,
        reference,
        int(search.radius),
        float(search.fitness_eps),
        int(search.tree_batch),
        bias_guard=float(search.bias_guard),
    )
    return fitness, available, meta


def make_search(cfg: DictConfig, fitness, available: list[str]):
    """The `GPSearch` of `task.search` over the available terminals."""
    from src.gp.grammar import GRAMMAR_VECTORS
    from src.gp.search import GPSearch, search_pset
    from src.gp.variation import codebook, kernel_expressions

    if cfg.task.search.color_variance and "colorVariance" not in available:
        raise ConfigError(
            "task.search.color_variance=true: the search images have no colour variance (batch key "
            "'color_var'; data prepared before it was stored: run stage=preprocess again); or set it false"
        )
    pset = search_pset(available, bool(cfg.task.search.color_variance))
    book = codebook(kernel_expressions([f for f in GRAMMAR_VECTORS if f in available]), pset)
    return GPSearch(fitness, seed_expression(cfg), search_params(cfg), pset, book), pset


def _with_expression(cfg: DictConfig, model: dict[str, Any]) -> DictConfig:
    """`cfg` with `model.expression`, `.radius` and `.normalize` of one best_expressions.yaml entry."""
    cfg = cfg.copy()
    for key in ("expression", "radius", "normalize"):
        OmegaConf.update(cfg, f"model.{key}", model[key], merge=False)
    return cfg


def best_expressions(state, cfg: DictConfig) -> list[dict[str, Any]]:
    """Each island's best, as `model=gp_filter` settings, best first, with the island's top expressions
    (its hall of fame, `top`: fitness and infix text, best first; the best alone without one)."""
    from src.gp.search import top_per_island
    from src.gp.text import to_infix

    search = cfg.task.search
    rows = [
        {
            "island": k,
            "fitness": float(top[0].fitness.values[0]),
            "model": {
                "name": "gp_filter",
                "expression": to_infix(top[0]),
                "radius": int(search.radius),
                "normalize": bool(search.normalize),
            },
            "top": [{"fitness": float(ind.fitness.values[0]), "expression": to_infix(ind)} for ind in top],
        }
        for k, top in enumerate(top_per_island(state))
    ]
    return sorted(rows, key=lambda r: r["fitness"])


class FilterSearchTask(DenoiseTask):
    schema = FilterSearchTaskSchema
    # Its evaluation runs each island's best expression as the model (`_with_expression`): a GP filter.
    methods = GPFilter

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        prepared, preprocessed = Path(cfg.paths.prepared), "stage=preprocess (or dvc repro)"
        if stage == "search":
            return {prepared / "full" / str(cfg.task.search.split) / "index.json": preprocessed}
        if stage == "eval":
            best = Path(cfg.task.search.out_dir) / BEST_FILE
            test = prepared / "full" / str(cfg.task.eval.split) / "index.json"
            return {test: preprocessed, best: "stage=search"}
        return super().inputs(stage, cfg)

    def check_stages(self, stages: list[str], cfg: DictConfig) -> None:
        """The denoise task's checks, and `task.search.spp` among the dataset's noisy sample counts."""
        super().check_stages(stages, cfg)
        spp, rendered = cfg.task.search.spp, cfg.dataset.get("noisy_spp")
        if "search" in stages and spp is not None and rendered is not None:
            missing = sorted(set(spp) - set(rendered))
            if missing:
                raise ConfigError(
                    f"task.search.spp={list(spp)}: {missing} not rendered; expected among dataset.noisy_spp="
                    f"{list(rendered)}"
                )

    def search(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Run (or resume) the search; log it; write the checkpoint, history and best expressions."""
        import time

        from tqdm import tqdm

        from src.gp.fitness import WORST
        from src.gp.run_metrics import best_through, search_run_metrics
        from src.gp.search import load_state, saved_job
        from src.io.atomic import atomic_write_json, atomic_write_text
        from src.provenance import config_digest
        from src.train.device import pick_device

        search_cfg = cfg.task.search
        out = Path(search_cfg.out_dir)
        device = pick_device(cfg.device)
        fitness, available, meta = build_fitness(cfg, device)
        gp_search, pset = make_search(cfg, fitness, available)
        params = gp_search.params
        state, searched_before = None, 0.0
        resume = resumable_search_state(cfg)
        if resume is not None:
            state = load_state(resume, params, pset)
            tracker.skip_logged_after(state.generation)
            # the search's clock continues where the checkpoint's job left it (0 in older checkpoints)
            searched_before = float(saved_job(resume).get("search_time_s", 0.0))
        h, w = fitness.color.shape[-2:]
        print(
            f"search: {params.islands} islands x {params.population}, {params.generations} generations on "
            f"{len(meta)} {search_cfg.split} images of {w}x{h} (radius {search_cfg.radius}, {device}); "
            f"features {', '.join(available)}"
        )
        done = state.generation if state else 0
        bar = tqdm(total=params.generations, desc="search", unit="gen", initial=done)
        start = time.perf_counter()

        def clock() -> float:
            """The search's seconds so far, over every job that ran it (the quality-against-time x axis)."""
            return searched_before + time.perf_counter() - start

        def on_generation(s) -> None:
            stats = s.history[-1]
            metrics: dict[str, float] = {"search_evaluations": stats["evaluations"], "search_time_s": clock()}
            for k, island in enumerate(stats["islands"]):
                metrics[f"search_best_island{k}"] = island["best"]
                if island["mean"] < WORST:
                    metrics[f"search_mean_island{k}"] = island["mean"]
                metrics[f"search_invalid_island{k}"] = island["invalid"]
            best = min(stats["islands"], key=lambda i: i["best"])
            metrics["search_best"] = best["best"]
            # The thesis's Figures 4.6-4.7 measure: the minimum over every expression so far (Sec. 4.2);
            # search_best can rise again when a generation loses its best (little replication).
            metrics["search_best_so_far"] = best_through(s.history, s.generation)
            tracker.log_metrics(metrics, step=s.generation)
            tracker.set_tags({"search.best_expression": best["best_expression"][:4000]})
            if s.generation > 0:
                bar.update(1)
            bar.set_postfix(best=f"{best['best']:.4f}")

        job = {"config_digest": config_digest(cfg), "mlflow_run_id": tracker.run_id}
        state = gp_search.run(
            state=state,
            checkpoint=out / STATE_FILE,
            on_generation=on_generation,
            job=lambda: {**job, "search_time_s": clock()},
        )
        bar.close()
        seconds = clock()  # a resumed search's total, not only this job's part
        rows = best_expressions(state, cfg)
        header = (
            "# Best expression of each island (Davletaliyev 2016, Sec. 3.2.6), best first; fitness = mean\n"
            "# relMSE(filtered) / relMSE(noisy) (Eq. 3.5) on the search images. Use one as\n"
            '#   python -m src.run task=denoise model=gp_filter model.expression="<expr>" model.radius=<r>\n'
        )
        atomic_write_text(out / BEST_FILE, header + yaml.safe_dump(rows, sort_keys=False, width=10_000))
        atomic_write_json(out / HISTORY_FILE, state.history)
        for name in (BEST_FILE, HISTORY_FILE):
            tracker.log_artifact(out / name, "search")
        summary = {
            "best_fitness": rows[0]["fitness"],
            "best_expression": rows[0]["model"]["expression"],
            "generations": state.generation,
            "evaluations": sum(h["evaluations"] for h in state.history),
            # expressions the fitness cache answered (counted in `evaluations`, not filtered again)
            "cache_hits": gp_search.cache_hits,
            "seconds": seconds,
            "images": meta,
            "features": available,
        }
        finished = {"search_seconds": seconds} | search_run_metrics(
            state.history, rows[0]["model"]["expression"]
        )
        tracker.log_metrics(finished, step=state.generation)
        seed_fitness = state.history[0]["islands"][0]["best"]
        print(
            f"search: best fitness {rows[0]['fitness']:.4f} (generation 0: {seed_fitness:.4f}"
            f") in {seconds:.1f} s ({gp_search.cache_hits} of {summary['evaluations']} evaluations from the "
            f"fitness cache) -> {out / BEST_FILE}\n  {rows[0]['model']['expression']}"
        )
        return summary

    def evaluate(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Each island's best expression (best_expressions.yaml) as `model=gp_filter`, by the denoise
        evaluation: the best one into `task.eval.out_dir` and the run's metrics, the other islands' into
        `<out_dir>/island<k>/` (not logged as the run's metrics); their means side by side in
        `<out_dir>/islands.csv` (logged as an artifact)."""
        from src.io.atomic import atomic_write_text
        from src.tracking.tracker import Tracker

        rows = yaml.safe_load((Path(cfg.task.search.out_dir) / BEST_FILE).read_text())
        tracker.set_tags({"search.evaluated_expression": rows[0]["model"]["expression"][:4000]})
        summaries, table = [], []
        for rank, row in enumerate(rows):
            island_cfg = _with_expression(cfg, row["model"])
            if rank > 0:  # numbers only: no images, no run metrics, the baseline scored once
                out_dir = f"{cfg.task.eval.out_dir}/island{row['island']}"
                numbers_only = {"out_dir": out_dir, "save_exr": False, "strips": False, "baseline": None}
                OmegaConf.update(island_cfg, "task.eval", numbers_only, merge=True)
            summaries.append(super().evaluate(island_cfg, tracker if rank == 0 else Tracker(None)))
            mean = summaries[-1]["mean"]
            table.append(
                {"island": row["island"], "fitness": row["fitness"]}
                | {k: mean[k] for k in ISLAND_COLUMNS}
                | {"expression": row["model"]["expression"]}
            )
        baseline = summaries[0]["mean"]
        if cfg.task.eval.get("baseline") is not None:  # its row: the same held-out images
            table.append(
                {"island": "baseline", "fitness": None}
                | {k: baseline.get(f"baseline_{k}") for k in ISLAND_COLUMNS}
                | {"expression": cfg.task.eval.baseline.name}
            )
        out = Path(cfg.task.eval.out_dir) / ISLANDS_FILE
        atomic_write_text(out, pd.DataFrame(table).to_csv(index=False))
        tracker.log_artifact(out, "eval")
        return summaries[0]
