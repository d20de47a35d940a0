"""ColorVideoVDP and FovVideoVDP in one process (src/metrics/own_modules.py): each package binds its own
top-level `interp`, in either import order. Run in fresh interpreters: the order is the point."""

from __future__ import annotations

import subprocess
import sys

import pytest

from src.metrics.own_modules import package_dir
from tests.conftest import ROOT

CHECK = """
import sys
from src.metrics.noisebase_protocol import import_pyfvvdp
from src.metrics.own_modules import import_own
first, second = {order}
loaded = {{}}
for name in (first, second):
    loaded[name] = import_pyfvvdp() if name == "fvvdp" else import_own("pycvvdp.cvvdp_metric", "pycvvdp")
fv, cv = sys.modules["pyfvvdp.fvvdp"], loaded["cvvdp"]
print(fv.interp1.__code__.co_filename)
print(cv.interp1dim2.__code__.co_filename)
print("interp" in sys.modules)
"""


@pytest.mark.skipif(package_dir("pycvvdp") is None or package_dir("pyfvvdp") is None, reason="packages")
@pytest.mark.parametrize("order", [("fvvdp", "cvvdp"), ("cvvdp", "fvvdp")])
def test_each_video_metric_binds_its_own_interp_in_either_order(order):
    out = subprocess.run(
        [sys.executable, "-c", CHECK.format(order=order)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    fv_file, cv_file, cached = out.stdout.strip().splitlines()[-3:]
    assert fv_file.startswith(str(package_dir("pyfvvdp"))) and cv_file.startswith(str(package_dir("pycvvdp")))
    assert cached == "False"  # the shared name is not left behind for the next importer
