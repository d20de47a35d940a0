"""Intel Open Image Denoise (`pyoidn`) as a non-learned baseline behind the Denoiser interface
(`conf/model/oidn.yaml`).

OIDN's RT filter is a pretrained U-Net that we call, not train (`learned = False`). Its inputs follow
the OIDN conventions (checked against `help(pyoidn.denoise)`, pyoidn 2.5): (H, W, 3) float32 arrays,
colour linear and non-negative in HDR mode, albedo in [0, 1], normals in [-1, 1]. Our buffers are Monte
Carlo averages, so we clamp them into those ranges (colour >= 0, albedo to [0, 1], normal to [-1, 1])
before the call.

Tiling: OIDN's receptive field is large and it handles image borders itself, so we never tile it. `halo`
is `None`, meaning "do not tile": tiled inference must call this model on the full frame.
"""

from __future__ import annotations

import numpy as np
import torch

from src.errors import ConfigError, EnvironmentSetupError, one_line
from src.models.denoise.base import Batch, Denoiser

#: Accepted values of `quality` (pyoidn also accepts "default" and the OIDN_QUALITY_* integers).
QUALITIES = ("high", "balanced", "fast", "default")


def _import_pyoidn():
    """The pyoidn module, or a one-line EnvironmentSetupError (its native library may fail to load)."""
    try:
        import pyoidn
    except Exception as err:  # ImportError, or OSError from the bundled shared library
        raise EnvironmentSetupError(
            f"pyoidn (Intel Open Image Denoise) cannot be imported: {one_line(err)}; "
            "install the pinned `pyoidn` package (uv sync)"
        ) from err
    return pyoidn


def _hwc(x: torch.Tensor, lo: float | None, hi: float | None) -> np.ndarray:
    """(3, H, W) tensor -> clamped, contiguous float32 (H, W, 3) numpy array on the CPU."""
    x = x.detach().float().clamp(min=lo, max=hi).permute(1, 2, 0)
    return np.ascontiguousarray(x.cpu().numpy(), dtype=np.float32)


class OIDNDenoiser(Denoiser):
    """OIDN RT filter on batch["color"] (N, 3, H, W), optionally guided by batch["albedo"] and
    batch["normal"]; returns {"color": denoised linear colour} on the input's device."""

    learned = False

    def __init__(
        self,
        hdr: bool = True,
        quality: str = "high",
        use_albedo: bool = True,
        use_normal: bool = True,
        clean_aux: bool = False,
    ) -> None:
        super().__init__()
        if quality not in QUALITIES:
            raise ConfigError(f"model.quality={quality!r}; expected one of {', '.join(QUALITIES)}")
        if use_normal and not use_albedo:
            # OIDN's RT filter accepts a normal image only together with an albedo image.
            raise ConfigError("model.use_normal=true needs model.use_albedo=true (an OIDN requirement)")
        self.hdr = bool(hdr)
        self.quality = str(quality)
        self.use_albedo = bool(use_albedo)
        self.use_normal = bool(use_normal)
        self.clean_aux = bool(clean_aux)
        self._pyoidn = _import_pyoidn()

    @property
    def halo(self) -> None:
        """None: OIDN is not tiled by us; call it on the full frame."""
        return None

    def _denoise_one(self, color: torch.Tensor, albedo: torch.Tensor | None, normal: torch.Tensor | None):
        """One (3, H, W) image through pyoidn.denoise -> (H, W, 3) float32 numpy array."""
        # HDR colour must be non-negative; LDR colour must also be <= 1.
        rgb = _hwc(color, 0.0, None if self.hdr else 1.0)
        alb = _hwc(albedo, 0.0, 1.0) if albedo is not None else None
        nrm = _hwc(normal, -1.0, 1.0) if normal is not None else None
        try:
            return self._pyoidn.denoise(
                rgb, alb, nrm, hdr=self.hdr, quality=self.quality, clean_aux=self.clean_aux
            )
        except Exception as err:  # TypeError/ValueError/RuntimeError from pyoidn or the OIDN library
            raise EnvironmentSetupError(f"pyoidn.denoise failed: {one_line(err)}") from err

    @torch.no_grad()
    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        color = batch["color"]
        albedo = batch["albedo"] if self.use_albedo else None
        normal = batch["normal"] if self.use_normal else None
        out = [
            self._denoise_one(
                color[i],
                albedo[i] if albedo is not None else None,
                normal[i] if normal is not None else None,
            )
            for i in range(color.shape[0])
        ]
        stacked = torch.from_numpy(np.stack(out)).permute(0, 3, 1, 2).contiguous()
        return {"color": stacked.to(device=color.device, dtype=torch.float32)}
