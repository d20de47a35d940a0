"""The peak memory of one stage of a job: host (the process's resident set) and device (what PyTorch's CUDA
allocator held), for the cost card of every result (`<stage>_peak_host_mb`, `<stage>_peak_device_mb`).

The host peak is sampled: a daemon thread reads the resident set size (psutil) every `interval` seconds,
and once more when the stage ends, so a spike shorter than the interval can be missed (the process-wide
`ru_maxrss` would not miss it, but it never falls: it cannot tell a stage's peak from an earlier stage's).
The device peak is PyTorch's own counter (`torch.cuda.max_memory_allocated`), reset when the stage starts;
memory that other libraries (Mitsuba's Dr.Jit, OIDN) allocate on the GPU is not in it.
"""

from __future__ import annotations

import threading

import psutil

MB = 1024.0**2


class PeakMemory:
    """`with PeakMemory() as peak: ...`, then `peak.host_mb` and `peak.device_mb` (None without CUDA)."""

    def __init__(self, interval: float = 0.05) -> None:
        self.interval = interval
        self.host_mb = 0.0
        self.device_mb: float | None = None
        self._process = psutil.Process()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        self.host_mb = max(self.host_mb, self._process.memory_info().rss / MB)

    def _watch(self) -> None:
        while not self._stop.wait(self.interval):
            self._sample()

    def __enter__(self) -> PeakMemory:
        cuda = _cuda()
        if cuda is not None:
            cuda.reset_peak_memory_stats()
        self._sample()
        self._thread = threading.Thread(target=self._watch, name="peak-memory", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()
        cuda = _cuda()
        if cuda is not None:
            self.device_mb = cuda.max_memory_allocated() / MB

    def metrics(self, stage: str) -> dict[str, float]:
        """The MLflow metrics of `stage`'s peaks (the device's only where there was one)."""
        out = {f"{stage}_peak_host_mb": round(self.host_mb, 1)}
        if self.device_mb is not None:
            out[f"{stage}_peak_device_mb"] = round(self.device_mb, 1)
        return out


def _cuda():
    """torch.cuda when PyTorch is loaded and a GPU is there (never imports torch itself: a stage that did
    not load it used no GPU through it)."""
    import sys

    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available():
        return None
    return torch.cuda
