"""src/report/paired.py (the paired comparison of two study arms) against a brute-force signed-rank test,
and scripts/gp_study.py (the filter-search studies' seed spread and paired comparisons) on a fake
multirun folder whose numbers are known."""

import importlib.util
import itertools
import json
import math

import numpy as np
import pandas as pd
import pytest
import yaml

from src.errors import DataError
from src.report.paired import Paired, paired_difference
from tests.conftest import ROOT, one_line_error

spec = importlib.util.spec_from_file_location("gp_study", ROOT / "scripts" / "gp_study.py")
gp_study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gp_study)


def _signed_rank_p(d):
    """Two-sided exact Wilcoxon signed-rank p by enumerating all 2^n sign patterns (distinct |d|, no 0)."""
    ranks = np.argsort(np.argsort(np.abs(d))) + 1
    observed = ranks[np.asarray(d) > 0].sum()
    totals = [
        sum(r for r, s in zip(ranks, signs, strict=True) if s)
        for signs in itertools.product((0, 1), repeat=len(d))
    ]
    low = sum(t <= observed for t in totals) / len(totals)
    high = sum(t >= observed for t in totals) / len(totals)
    return min(1.0, 2 * min(low, high))


@pytest.mark.parametrize(
    "d", [[1.0, 2.5, -0.5, 4.0, 3.2, 5.1], [0.3, -1.2, 0.8, -2.0, 1.5], [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]]
)
def test_paired_difference_is_the_exact_signed_rank_test(d):
    b = np.array([10.0, 20.0, 5.0, 7.0, 1.0, 3.0])[: len(d)]
    p = paired_difference(b + np.array(d), b)
    assert p.n == len(d) and p.mean_difference == pytest.approx(np.mean(d))
    assert (p.a_higher, p.b_higher) == (sum(x > 0 for x in d), sum(x < 0 for x in d))
    assert p.p_value == pytest.approx(_signed_rank_p(np.array(d)), rel=1e-9)
    assert p.shown() == (p.p_value < 0.05)


def test_six_pairs_all_one_way_is_the_smallest_p_and_shown():
    p = paired_difference([2, 3, 4, 5, 6, 7], [1, 1, 1, 1, 1, 1])
    assert p.p_value == pytest.approx(2 / 2**6) and p.shown()
    assert not paired_difference([2, 3, 4, 5, 6], [1, 1, 1, 1, 1]).shown(alpha=0.05)  # 2/32 = 0.0625


def test_log_differences_give_the_geometric_mean_ratio():
    p = paired_difference([2.0, 8.0], [1.0, 2.0], log=True)
    assert p.ratio == pytest.approx(math.sqrt(8.0)) and p.mean_difference == pytest.approx(math.log(8) / 2)
    with pytest.raises(ValueError):
        _ = paired_difference([2.0, 8.0], [1.0, 2.0]).ratio
    assert math.isnan(paired_difference([1.0, 2.0], [1.0, 2.0]).p_value)


@pytest.mark.parametrize(
    ("a", "b", "log", "needle"),
    [
        ([1, 2], [1], False, "one per item"),
        ([1, float("nan")], [1, 2], False, "NaN"),
        ([1, 0], [1, 2], True, "<= 0"),
    ],
)
def test_bad_paired_input_is_one_line(a, b, log, needle):
    with pytest.raises(DataError) as excinfo:
        paired_difference(a, b, log=log)
    one_line_error(excinfo, "paired comparison", needle)


# -- scripts/gp_study.py --------------------------------------------------------------------------------

SCENES = ("outdoor-0003", "tabletop-0003")


def _job(folder, arm, seed, ratios, energy=1.0, fitness=(0.05, 0.04)):
    """A finished job: `ratios[scene][spp]` held-out relMSE / noisy; psnr = 30 - 10 ratio."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / "search").mkdir()
    (folder / "eval").mkdir()
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([arm, f"seed={seed}", "+sweep=x"]))
    history = [{"islands": [{"best": f}]} for f in fitness]
    (folder / "search" / "history.json").write_text(json.dumps(history))
    best = [{"model": {"expression": f"expr-{arm}-{seed}"}}]
    (folder / "search" / "best_expressions.yaml").write_text(yaml.safe_dump(best))
    rows = [
        {"scene": s, "spp": spp, "relmse_ratio": r, "psnr": 30 - 10 * r, "energy": energy}
        for s in SCENES
        for spp, r in ratios[s].items()
    ]
    pd.DataFrame(rows).to_csv(folder / "eval" / "per_image.csv", index=False)


def _sweep(tmp_path):
    """Arm A (seeds 0, 1) and arm B, whose every held-out ratio is half of A's at 4 spp and equal at 16."""
    base = {0: {"outdoor-0003": 0.2, "tabletop-0003": 0.4}, 1: {"outdoor-0003": 0.3, "tabletop-0003": 0.1}}
    for k, (arm, seed) in enumerate(itertools.product(("a=1", "a=2"), (0, 1))):
        half = 0.5 if arm == "a=2" else 1.0
        ratios = {s: {4: base[seed][s] * half, 16: 0.9} for s in SCENES}
        _job(
            tmp_path / str(k),
            arm,
            seed,
            ratios,
            energy=0.9 if arm == "a=2" else 1.0,
            fitness=(0.05, 0.03 + seed / 100),
        )
    return tmp_path


def test_gp_study_arm_table_is_the_mean_and_spread_over_seeds(tmp_path):
    jobs, unfinished = gp_study.load_jobs(_sweep(tmp_path))
    assert unfinished == [] and [j["arm"] for j in jobs] == ["a=1", "a=1", "a=2", "a=2"]
    table = gp_study.arm_table(jobs, 4).set_index("arm")
    a = table.loc["a=1"]
    assert a["seeds"] == 2 and a["min fitness"] == f"0.0350 ± {np.std([0.03, 0.04], ddof=1):.4f}"
    assert a["relMSE/noisy outdoor"] == f"0.2500 ± {np.std([0.2, 0.3], ddof=1):.4f}"
    assert a["relMSE/noisy 4 spp"] == "0.2500 ± 0.0707"  # seed means 0.3 and 0.2
    assert a["relMSE/noisy all spp"] == f"{np.mean([0.6, 0.55]):.4f} ± {np.std([0.6, 0.55], ddof=1):.4f}"
    assert table.loc["a=2", "energy tabletop"] == "0.900 ± 0.000"


def test_gp_study_compares_each_arm_with_the_first_paired_by_seed_and_image(tmp_path):
    jobs, _ = gp_study.load_jobs(_sweep(tmp_path))
    rows = gp_study.comparisons(jobs, 4).set_index("spp")
    at4, every = rows.loc[4], rows.loc["all"]
    assert at4["pairs"] == 4 and at4["relMSE/noisy ratio"] == "0.500" and at4["lower/higher"] == "4/0"
    assert at4["relMSE"] == "not significant (n = 4)"  # 4 pairs: the smallest two-sided p is 2/16
    assert every["pairs"] == 8 and every["relMSE/noisy ratio"] == f"{0.5**0.5:.3f}"
    assert at4["|energy-1| diff"] == "+0.1000"
    text = gp_study.report(tmp_path, 4)
    assert "expr-a=2-1" in text and "Unfinished" not in text


def test_gp_study_leaves_out_unfinished_jobs_and_refuses_a_folder_without_jobs(tmp_path, capsys):
    sweep = _sweep(tmp_path / "s")
    (sweep / "4" / "search").mkdir(parents=True)  # a job still running
    assert "Unfinished jobs left out: 4." in gp_study.report(sweep, 4)
    assert gp_study.main([str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nowhere" in err and "not a folder" in err


# -- the report's paired table (src/report/tables.py::paired_table) --------------------------------------


def _images(rows):
    """Per-image rows as `collect.per_image_rows` gives them: model, seed, scene, spp, scores."""
    out = []
    for model, seed, scene, ratio, psnr in rows:
        out.append(
            {
                "params.model.name": model,
                "params.seed": str(seed),
                "run_id": f"{model}-{seed}",
                "scene": scene,
                "spp": 4,
                "metrics.relmse_ratio": ratio,
                "metrics.psnr": psnr,
            }
        )
    return pd.DataFrame(out)


def _study():
    """A (the best), B twice A's relMSE and 1 dB under on all 6 items (seed x scene), C within noise of A,
    D only seed 0."""
    base = {(s, sc): 0.1 * (1 + s) * (2 if sc == "s1" else 1) for s in range(3) for sc in ("s0", "s1")}
    wiggle = dict(zip(sorted(base), (0.95, 1.1, 1.12, 0.93, 1.15, 0.97), strict=True))
    rows = []
    for (seed, scene), r in base.items():
        psnr = 30 + seed + (scene == "s1")
        rows += [("A", seed, scene, r, psnr), ("B", seed, scene, 2 * r, psnr - 1)]
        rows.append(
            ("C", seed, scene, r * wiggle[seed, scene], psnr + (0.1 if wiggle[seed, scene] < 1 else -0.2))
        )
        if seed == 0:
            rows.append(("D", seed, scene, 3 * r, psnr - 2))
    return _images(rows)


def test_paired_table_compares_each_row_with_the_best_by_seed_and_image():
    from src.report.paired import paired_table
    from src.report.table_writers import to_markdown

    table = paired_table(_study(), ["model.name"])
    row = {m: table.loc[(m,)] for m in "ABCD"}
    assert row["A"]["relMSE / noisy"] == "best" and row["A"]["PSNR"] == "best"
    assert row["B"]["relMSE / noisy vs best (ratio)"] == pytest.approx(2.0)
    assert (
        row["B"]["relMSE / noisy p"] == pytest.approx(2 / 2**6)
        and row["B"]["relMSE / noisy"] == "significant (n = 6)"
    )
    assert (
        row["B"]["PSNR vs best (difference)"] == pytest.approx(-1.0)
        and row["B"]["PSNR"] == "significant (n = 6)"
    )
    assert row["B"]["pairs"] == 6 and row["B"]["runs"] == 3
    d = np.log([0.95, 1.1, 1.12, 0.93, 1.15, 0.97])  # C against A, in the items' sorted order
    assert row["C"]["relMSE / noisy vs best (ratio)"] == pytest.approx(math.exp(d.mean()))
    assert row["C"]["relMSE / noisy p"] == pytest.approx(_signed_rank_p(d))
    assert row["C"]["relMSE / noisy"] == "not significant (n = 6)"
    assert row["D"]["pairs"] == 2 and row["D"]["relMSE / noisy vs best (ratio)"] == pytest.approx(3.0)
    assert row["D"]["relMSE / noisy"] == "not significant (n = 2)"  # 2 pairs: the smallest p is 0.5
    text = to_markdown(table)
    assert "not significant (n = 6)" in text and "**" not in text  # verdicts, no best-value bolding


def test_paired_table_needs_two_rows_and_compares_differences_where_a_ratio_is_zero():
    from src.report.paired import paired_table

    study = _study()
    assert paired_table(study[study["params.model.name"] == "A"], ["model.name"]) is None
    assert paired_table(pd.DataFrame(), ["model.name"]) is None
    zero = study.copy()
    zero.loc[(zero["params.model.name"] == "A") & (zero["scene"] == "s0"), "metrics.relmse_ratio"] = 0.0
    table = paired_table(zero, ["model.name"])
    assert "relMSE / noisy vs best (difference)" in table and "relMSE / noisy vs best (ratio)" not in table


def test_paired_table_compares_sequences_on_their_flicker_and_temporal_psnr():
    """Sequence rows carry per-item `flicker_unbiased` and `tpsnr`: lower flicker and higher tPSNR are
    best; an infinite tPSNR (an output changing exactly as its reference) pairs nothing instead of
    failing; still-image rows, which lack both, get no such columns."""
    from src.report.paired import paired_table

    study = _study()
    assert "Flicker vs truth" not in paired_table(study, ["model.name"])
    a = study["params.model.name"] == "A"
    b = study["params.model.name"] == "B"
    study.loc[a, "metrics.flicker_unbiased"] = 0.02
    study.loc[b, "metrics.flicker_unbiased"] = 0.05
    study["metrics.tpsnr"] = 30.0
    study.loc[b, "metrics.tpsnr"] = 28.0
    first_a = study.index[a][0]
    study.loc[first_a, "metrics.tpsnr"] = np.inf
    table = paired_table(study, ["model.name"])
    assert table.loc[("A",), "Flicker vs truth"] == "best"
    assert table.loc[("B",), "Flicker vs truth vs best (difference)"] == pytest.approx(0.03)
    from src.report.table_writers import cells

    header, _, rows = cells(table)
    b_row = {h: text for h, (text, _, _) in zip(header, rows[1], strict=True)}
    assert b_row["Flicker vs truth vs best (difference)"] == "+0.03"  # a positive difference keeps its sign
    assert table.loc[("B",), "Flicker vs truth"] == "significant (n = 6)"  # 6 of 6 pairs one way
    assert pd.isna(table.loc[("C",), "Flicker vs truth vs best (difference)"])  # C has no flicker scores
    assert table.loc[("B",), "tPSNR vs best (difference)"] == pytest.approx(-2.0)
    assert table.loc[("B",), "tPSNR"] == "not significant (n = 5)"  # 5 pairs left: the smallest p is 0.0625


def test_the_paired_rules_at_their_boundaries():
    # two pairs are enough for a test (p = 0.5, the smallest two-sided p with n = 2), one is not
    assert paired_difference([2.0, 3.0], [1.0, 1.0]).p_value == pytest.approx(0.5)
    assert math.isnan(paired_difference([2.0], [1.0]).p_value)
    # a tie counts for neither arm
    tied = paired_difference([2.0, 1.0, 0.5], [1.0, 1.0, 1.0])
    assert (tied.a_higher, tied.b_higher) == (1, 1)
    # p exactly at the level is not significant: "below alpha"
    at_level = Paired(6, 1.0, 6, 0, 0.05, False)
    assert not at_level.shown(0.05) and at_level.shown(0.0500001)
    assert at_level.verdict(0.05) == "not significant (n = 6)"
    # a log comparison refuses a zero in either arm
    for a, b in (([1.0, 2.0], [0.0, 1.0]), ([0.0, 2.0], [1.0, 1.0])):
        with pytest.raises(DataError, match="<= 0"):
            paired_difference(a, b, log=True)


def test_the_paired_tables_cells_print_ratios_differences_and_p_at_their_own_digits():
    from src.report.paired import paired_table
    from src.report.table_writers import cells

    table = paired_table(_study(), ["model.name"])
    header, _, rows = cells(table)
    b_row = {h: text for h, (text, _, _) in zip(header, rows[1], strict=True)}
    assert b_row["model"] == "B" and b_row["relMSE / noisy vs best (ratio)"] == "2"
    assert b_row["PSNR vs best (difference)"] == "-1"  # signed: its direction is visible beside the verdict
    assert b_row["relMSE / noisy p"] == "0.0312" and b_row["pairs"] == "6"
    assert table.attrs["axes"] == ["model"]
    assert table.loc[("A",), "PSNR vs best (difference)"] == 0.0  # the best row against itself


# -- what the paired table's mutation run (scripts/mutation.sh report_paired) found untested ------------


def test_the_paired_tables_formats_are_its_metrics_spec():
    """Each compared metric's three columns and `pairs`, as the table writers read them: a ratio to 4
    significant digits, a difference signed to 3, p to 3, the verdict as text, pairs as a count."""
    from src.report.paired import paired_table

    assert paired_table(_study(), ["model.name"]).attrs["metrics"] == {
        "relMSE / noisy vs best (ratio)": ("", None, "{:.4g}"),
        "relMSE / noisy p": ("", None, "{:.3g}"),
        "relMSE / noisy": ("", None, "{}"),
        "pairs": ("", None, "{:,.0f}"),
        "PSNR vs best (difference)": ("", None, "{:+.3g}"),
        "PSNR p": ("", None, "{:.3g}"),
        "PSNR": ("", None, "{}"),
    }


def test_the_best_row_against_itself_and_a_row_with_too_few_common_items():
    """The best row: ratio 1 (or difference 0), no p, "best", its own item count as pairs; a row sharing one
    item with the best: no value, no p, "-", one pair."""
    from src.report.paired import paired_table

    study = _study()
    only_one = study[(study["params.model.name"] == "D") & (study["scene"] == "s0")]
    table = paired_table(pd.concat([study[study["params.model.name"] != "D"], only_one]), ["model.name"])
    best, lone = table.loc[("A",)], table.loc[("D",)]
    assert best["relMSE / noisy vs best (ratio)"] == 1.0 and best["PSNR vs best (difference)"] == 0.0
    assert math.isnan(best["relMSE / noisy p"]) and best["relMSE / noisy"] == "best" and best["pairs"] == 6
    assert math.isnan(lone["relMSE / noisy vs best (ratio)"]) and math.isnan(lone["relMSE / noisy p"])
    assert lone["relMSE / noisy"] == "-" and lone["pairs"] == 1


def test_a_ratio_metrics_best_row_is_the_lowest_geometric_mean():
    """relMSE / noisy compares ratios: row A's items 0.01 and 1 (arithmetic mean 0.505, geometric 0.1)
    beat B's 0.3 and 0.3 (both means 0.3). PSNR, compared by differences, picks the highest plain mean:
    A's 40 and 14 (mean 27, geometric 23.7) over B's 26 and 26."""
    from src.report.paired import paired_table

    rows = [("A", 0, "s0", 0.01, 40.0), ("A", 0, "s1", 1.0, 14.0), ("B", 0, "s0", 0.3, 26.0)]
    table = paired_table(_images([*rows, ("B", 0, "s1", 0.3, 26.0)]), ["model.name"])
    assert table.loc[("A",), "relMSE / noisy"] == "best" and table.loc[("A",), "PSNR"] == "best"
    assert table.loc[("B",), "relMSE / noisy vs best (ratio)"] == pytest.approx(0.3 / 0.1)
    assert table.loc[("B",), "PSNR vs best (difference)"] == pytest.approx(-1.0)


def test_two_rows_are_enough_and_the_axes_given_are_the_rows():
    from src.report.paired import paired_table

    study = _study()
    two = paired_table(study[study["params.model.name"].isin(["A", "B"])], ["model.name"])
    assert list(two.index) == [("A",), ("B",)] and two.loc[("B",), "relMSE / noisy"] == "significant (n = 6)"
    by_scene = paired_table(study.assign(**{"params.scene_group": study["scene"]}), ["scene_group"])
    assert by_scene.attrs["axes"] == ["scene_group"] and list(by_scene.index) == [("s0",), ("s1",)]
    assert list(by_scene.index.names) == ["scene_group"]


def test_an_axis_a_run_lacks_is_a_dash_in_its_row_key():
    """A column of the axes missing from the images, or empty for some of them, reads "-" there: rows
    are told apart by the axes they do have. The images' index need not be 0..n-1 (a filtered frame)."""
    from src.report.paired import paired_table

    study = _study()
    study.index = study.index * 10 + 7
    table = paired_table(study, ["model.name", "model.width"])
    assert list(table.index) == [("A", "-"), ("B", "-"), ("C", "-"), ("D", "-")]
    assert table.loc[("B", "-"), "relMSE / noisy vs best (ratio)"] == pytest.approx(2.0)
    study["params.model.width"] = np.where(study["params.model.name"] == "B", "64", None)
    table = paired_table(study, ["model.name", "model.width"])
    assert ("B", "64") in table.index and ("A", "-") in table.index
    assert table.loc[("B", "64"), "pairs"] == 6


def test_a_metric_that_is_absent_or_never_finite_is_skipped_and_the_next_one_compared():
    from src.report.paired import paired_table

    study = _study()
    no_ratio = paired_table(study.drop(columns="metrics.relmse_ratio"), ["model.name"])
    assert "relMSE / noisy" not in no_ratio and no_ratio.loc[("B",), "PSNR"] == "significant (n = 6)"
    infinite = paired_table(study.assign(**{"metrics.relmse_ratio": np.inf}), ["model.name"])
    assert "relMSE / noisy" not in infinite and infinite.loc[("B",), "PSNR vs best (difference)"] == -1.0


def test_pairs_counts_the_first_compared_metric_and_runs_the_images_without_run_ids():
    """`pairs` is the first metric's item count (PSNR here has fewer items than the ratio); without a
    run_id column each image row counts as a run."""
    from src.report.paired import paired_table

    study = _study()
    b_first = study.index[study["params.model.name"] == "B"][0]
    study.loc[b_first, "metrics.psnr"] = np.nan
    table = paired_table(study, ["model.name"])
    assert table.loc[("B",), "pairs"] == 6 and table.loc[("B",), "PSNR"] == "not significant (n = 5)"
    assert table.loc[("B",), "runs"] == 3
    assert paired_table(study.drop(columns="run_id"), ["model.name"]).loc[("B",), "runs"] == 6


def test_item_means_average_repeats_and_drop_either_infinity():
    from src.report.paired import item_means

    part = pd.DataFrame(
        {"params.seed": ["0", "0", "1", "2"], "scene": ["a", "a", "a", "a"], "m": [1.0, 3.0, -np.inf, np.inf]}
    )
    means = item_means(part, "m")
    assert means.to_dict() == {("0", "a", "-"): 2.0}  # spp missing: "-"; seeds 1 and 2 pair nothing


def test_scores_given_as_text_compare_as_numbers():
    """Per-image scores read back from a CSV may arrive as text."""
    result = paired_difference(["2.0", "3.0", "5.0"], ["1.0", "1.0", "1.0"])
    assert (result.n, result.mean_difference, result.a_higher) == (3, pytest.approx(7 / 3), 3)
    log = paired_difference(["2.0", "4.0"], ["1.0", "1.0"], log=True)
    assert log.ratio == pytest.approx(math.sqrt(8))


# Mutation testing (scripts/mutation.sh report_paired, src/report/paired.py): 212 of 255 killed by the
# tests before the block above; of the 43 survivors, 37 fail a test of that block (each applied by hand).
# The 6 left are equivalent here:
# - item_means: infinities replaced by None instead of NaN (pandas stores None in a float column as NaN);
# - paired_difference: float("NAN") for float("nan");
# - paired_table: zip(*parts) with strict=None / False / dropped (every part has one entry per image row,
#   by construction);
# - paired_table: the best row's p appended as None instead of NaN (a float column stores it as NaN).
