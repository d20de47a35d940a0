"""Mitsuba variant selection: CUDA with a GPU, LLVM >= 16 otherwise, else a clear error."""

import pytest

from src.errors import ConfigError, EnvironmentSetupError
from src.render import backend


@pytest.mark.parametrize(
    ("name", "major"),
    [("libLLVM-19.so", 19), ("libLLVM.so.19.1", 19), ("libLLVM-15.so.1", 15), ("libLLVM.so", None)],
)
def test_llvm_major_from_file_name(name, major):
    assert backend.llvm_major(f"/usr/lib/x86_64-linux-gnu/{name}") == major


def test_llvm_15_alone_is_not_enough(monkeypatch, tmp_path):
    (tmp_path / "libLLVM-15.so.1").touch()
    monkeypatch.setattr(backend, "LLVM_SEARCH_GLOBS", (str(tmp_path / "libLLVM*.so*"),))
    assert backend.find_llvm_library() is None
    (tmp_path / "libLLVM-19.so").touch()
    (tmp_path / "libLLVM-17.so").touch()
    assert backend.find_llvm_library().endswith("libLLVM-19.so")


def test_missing_backends_give_an_install_hint(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(backend, "has_cuda_device", lambda: False)
    monkeypatch.setattr(backend, "find_llvm_library", lambda: None)
    with pytest.raises(EnvironmentSetupError, match="apt-get install libllvm19") as err:
        backend.resolve_variant("auto")
    assert "\n" not in str(err.value)
    with pytest.raises(EnvironmentSetupError, match="no NVIDIA GPU"):
        backend.resolve_variant("cuda_ad_rgb")
    with pytest.raises(ConfigError, match="render.variant"):
        backend.resolve_variant("scalar_rgb")


def test_cuda_preferred_when_present(monkeypatch):
    monkeypatch.setattr(backend, "has_cuda_device", lambda: True)
    assert backend.resolve_variant("auto") == "cuda_ad_rgb"
    assert backend.resolve_variant("llvm_ad_rgb") == "llvm_ad_rgb"
