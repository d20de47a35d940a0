"""scripts/compare_metrics.py: the refactor check compares every number but the timings."""

import importlib.util

from tests.conftest import ROOT

spec = importlib.util.spec_from_file_location("compare_metrics", ROOT / "scripts" / "compare_metrics.py")
compare_metrics = importlib.util.module_from_spec(spec)
spec.loader.exec_module(compare_metrics)


def test_timings_are_ignored_and_any_other_number_counts():
    before = {
        "model": "kpcn",
        "images": 2,
        "mean": {"psnr": 30.0, "ms_per_image": 5.0},
        "per_spp": {"4": {"ssim": 0.9}},
    }
    after = {
        "model": "kpcn",
        "images": 2,
        "mean": {"psnr": 30.0, "ms_per_image": 9.0},
        "per_spp": {"4": {"ssim": 0.9}},
    }
    assert compare_metrics.numbers(before) == {"images": 2, "mean.psnr": 30.0, "per_spp.4.ssim": 0.9}
    assert compare_metrics.differences(before, after) == []
    after["per_spp"]["4"]["ssim"] = 0.9000001
    assert compare_metrics.differences(before, after) == [("per_spp.4.ssim", 0.9, 0.9000001)]
    del after["mean"]["psnr"]
    assert ("mean.psnr", 30.0, None) in compare_metrics.differences(before, after)
