"""The cost card (issue 46): the device's measured peak from the bench's reference convolution, a run's
fraction of it, and the peak memory of a stage."""

from __future__ import annotations

import math
import time

import numpy as np
import pandas as pd
import pytest

from src.report.cost_card import DEVICE_TAG, PRECISION_TAG, measured_peaks, with_peak_fraction
from src.tracking.peak_memory import PeakMemory


def test_the_peak_is_the_best_reference_convolution_of_each_device():
    bench = pd.DataFrame(
        {
            "metrics.seconds_conv2d": [2.0, 1.0, 0.5, np.nan],
            "params.width": ["1280", "1280", "64", "1280"],
            "params.height": ["720", "720", "64", "720"],
            DEVICE_TAG: ["EPYC", "EPYC", "H200", "EPYC"],
            PRECISION_TAG: ["fp32", "fp32", "fp32 (TF32 convolutions)", "fp32"],
        }
    )
    per_pixel = 2.0 * 100 * 100 * 25
    peaks = measured_peaks(bench)
    assert peaks[("EPYC", "fp32")] == pytest.approx(per_pixel * 1280 * 720 / 1.0 / 1e9)  # the faster of two
    assert peaks[("H200", "fp32 (TF32 convolutions)")] == pytest.approx(per_pixel * 64 * 64 / 0.5 / 1e9)
    assert measured_peaks(bench.drop(columns="params.width")) == {}
    assert measured_peaks(bench.drop(columns=PRECISION_TAG)) == {}  # untagged bench runs: no peak


def test_a_runs_fraction_of_peak_needs_its_devices_peak():
    runs = pd.DataFrame(
        {
            "metrics.eval_gflops": [50.0, 50.0, 50.0],
            DEVICE_TAG: ["EPYC", "other", "EPYC"],
            PRECISION_TAG: ["fp32", "fp32", "bf16-autocast"],
        }
    )
    out = with_peak_fraction(runs, {("EPYC", "fp32"): 200.0})["metrics.eval_peak_fraction"]
    assert out[0] == 0.25 and math.isnan(out[1]) and math.isnan(out[2])  # another device, another precision
    assert "metrics.eval_peak_fraction" not in with_peak_fraction(runs.drop(columns=DEVICE_TAG), {})


def test_a_stage_that_holds_more_memory_has_a_higher_peak():
    with PeakMemory(interval=0.01) as idle:
        pass
    with PeakMemory(interval=0.01) as busy:
        block = np.ones(300 * 2**20 // 8)  # 300 MB, touched
        time.sleep(0.05)
        del block
    assert busy.host_mb - idle.host_mb > 250  # the sample at the block's end missed, the thread did not
    assert set(busy.metrics("train")) == {"train_peak_host_mb"}  # no GPU here: no device peak
