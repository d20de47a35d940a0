"""A filter whose weights come from a genetic-programming expression (Davletaliyev 2016; `conf/model/
gp_filter.yaml`, the three published expressions in `conf/model/gp_expr{1,2,3}.yaml`).

    out_p = sum_q w(p, q) c_q / sum_q w(p, q) over the (2r+1)^2 window,  w = the expression (`src.gp`)

The expression's terminals are read from the batch (`FEATURE_KEYS`): a vector feature from its batch key, or
else (for the visibility) from the `diffuse_in` channel of that name when `model.input_features` lists the
run's `task.features`; a variance from the batch key `<buffer>_var` or that `diffuse_in` channel; a gradient
is computed here (Sobel, `src.gp.features`) from its feature. With `normalize` (the thesis, Sec. 3.3.2)
every vector feature but the colour and the pixel coordinates is normalised per image (1-D by its maximum,
3-D by its longest vector) and each variance is scaled with its feature (divided by the square of the same
factor). A feature the data lack is a one-line ConfigError naming it, its batch key and `model.expression`:
`check_batch_keys` raises it from the data's index before any image is filtered (at job start when
`stage=eval` finds the prepared data; otherwise when the eval stage opens them), and a call does too.
World position and secondary texture (batch keys `position`, `secondary_albedo`, `position_var`,
`secondary_albedo_var`) are rendered by the `kpcn_aov` integrator and stored by preprocessing
when the raw EXRs have them; real KPCN data and older renders lack them, so expressions 2 and 3 (world
position) then stop with that error. The guide variances and the visibility are batch keys of the denoise
datasets (`src.data.denoise_dataset.GUIDE_KEYS`), so they need not be in `task.features`.

"Scene maximum": the thesis normalises by "the maximum value in the scene" (Sec. 3.3.2); we normalise per
image, which is the same for our data (one view per scene and sample count, each noisy image evaluated on its
own), except that two sample counts of a scene get the maxima of their own (noisy) features.
"""

from __future__ import annotations

import logging
from collections.abc import Collection

import torch

from src.data.features import feature_channels
from src.errors import ConfigError
from src.gp.evaluate import filter_images, required_terminals
from src.gp.features import normalization_scale, sobel_gradient
from src.gp.grammar import GRADIENT_OF, PSET
from src.gp.text import ExpressionError, parse, to_infix
from src.models.denoise.base import Batch, Denoiser

log = logging.getLogger(__name__)

#: Vector terminal -> batch key of its buffer (`directIllumination` may also come from `diffuse_in`).
FEATURE_KEYS = {
    "color": "color",
    "normal": "normal",
    "texture": "albedo",
    "depth": "depth",
    "directIllumination": "visibility",
    "worldPosition": "position",
    "secondaryTexture": "secondary_albedo",
}
#: Variance terminal -> the vector terminal it is the per-pixel variance of (batch key `<buffer>_var`).
VARIANCE_OF = {
    "wpVariance": "worldPosition",
    "nVariance": "normal",
    "texVariance": "texture",
    "secTexVariance": "secondaryTexture",
    "dovVariance": "depth",
    "diVariance": "directIllumination",
    "colorVariance": "color",  # batch key color_var; the colour is not normalised, nor is its variance
}
#: Features that are not normalised: the filtered colour itself and the pixel coordinates.
UNNORMALIZED = ("color", "pixel")


class GPFilter(Denoiser):
    """Filter with an expression's weights (module docstring). Reads `batch["color"]` and what the
    expression needs; returns {"color": filtered linear HDR colour}. Nothing is trained."""

    learned = False

    def __init__(
        self,
        expression: str,
        radius: int,
        input_features: list[str] | None = None,
        normalize: bool = True,
    ) -> None:
        super().__init__()
        if int(radius) != radius or radius < 0:
            raise ConfigError(f"model.radius must be an integer >= 0, got {radius!r}")
        try:
            self.tree = parse(str(expression), PSET)
        except ExpressionError as err:
            raise ConfigError(f"model.expression: {err}") from None
        self.expression = to_infix(self.tree)
        self.radius = int(radius)
        self.normalize = bool(normalize)
        self.needed = required_terminals([self.tree])
        self.input_channels: tuple[str, ...] | None = None
        if input_features is not None:
            self.input_channels = feature_channels([str(f) for f in input_features])

    @property
    def halo(self) -> int | None:
        """The window radius (+1 for a Sobel gradient); None (whole frame) when features are normalised,
        since the normalisation divides by a maximum over the whole image."""
        if self.normalize:
            return None
        return self.radius + (1 if self.needed & set(GRADIENT_OF) else 0)

    def _missing(self, terminal: str, key: str) -> ConfigError:
        if key in _INPUT_CHANNELS:
            feature = key.replace("_var", ".var")
            where = (
                f"no batch key {key!r} and no {key!r} channel in the network inputs that "
                f"model.input_features lists (add {feature} to task.features)"
            )
        else:
            where = (
                f"no batch key {key!r} (not in this dataset: real KPCN data and renders older than the "
                "position/secondary_albedo buffers lack it; render with stage=render and preprocess again)"
            )
        return ConfigError(f"model.expression needs feature {terminal!r}: {where}")

    def _from_inputs(self, keys: Collection[str], key: str) -> bool:
        """Whether `key` is read from a `diffuse_in` channel (the batch has no key of that name)."""
        channels = self.input_channels or ()
        return key not in keys and key in _INPUT_CHANNELS and key in channels and "diffuse_in" in keys

    def _read(self, batch: Batch, terminal: str, key: str) -> torch.Tensor:
        if key in batch:
            return batch[key].float()
        if self._from_inputs(batch.keys(), key):
            i = self.input_channels.index(key)
            return batch["diffuse_in"][:, i : i + 1].float()
        raise self._missing(terminal, key)

    def _base_terminals(self) -> list[str]:
        """The vector terminals read from the batch: the needed ones, the features of needed gradients,
        and (normalising) the features of needed variances, whose scale divides them."""
        base = {GRADIENT_OF.get(t, t) for t in self.needed}
        if self.normalize:
            base |= {VARIANCE_OF[t] for t in self.needed if t in VARIANCE_OF}
        return sorted(t for t in base if t in FEATURE_KEYS)

    def _variance_key(self, terminal: str) -> str:
        return f"{FEATURE_KEYS[VARIANCE_OF[terminal]]}_var"

    def check_batch_keys(self, keys: Collection[str]) -> None:
        """The one-line ConfigError of the first terminal that batches with tensor `keys` cannot give."""
        wanted = [(t, FEATURE_KEYS[t]) for t in self._base_terminals()]
        wanted += [(t, self._variance_key(t)) for t in sorted(self.needed) if t in VARIANCE_OF]
        for terminal, key in wanted:
            if key not in keys and not self._from_inputs(keys, key):
                raise self._missing(terminal, key)

    def features(self, batch: Batch) -> dict[str, torch.Tensor]:
        """The terminals the expression reads, from `batch` (module docstring)."""
        raw = {t: self._read(batch, t, FEATURE_KEYS[t]) for t in self._base_terminals()}
        scale = {
            t: normalization_scale(x) for t, x in raw.items() if self.normalize and t not in UNNORMALIZED
        }
        out: dict[str, torch.Tensor] = {}
        for t in self.needed:
            if t in FEATURE_KEYS:
                out[t] = raw[t] / scale[t] if t in scale else raw[t]
            elif t in GRADIENT_OF:
                grad = sobel_gradient(raw[GRADIENT_OF[t]])
                out[t] = grad / normalization_scale(grad) if self.normalize else grad
            else:
                base = VARIANCE_OF[t]
                var = self._read(batch, t, self._variance_key(t))
                out[t] = var / scale[base].square() if base in scale else var
        return out

    @torch.no_grad()
    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        """The filtered colour; NaN for every image on which the expression is undefined (the thesis's
        "undefined operation", Sec. 3.2.3: a NaN/Inf weight or a zero weight sum at some pixel). The
        search gives such an expression the worst fitness; a searched expression valid on every search
        image can still be undefined on a held-out one, and the evaluation then scores that image as
        undefined (NaN metrics, counted in its `undefined` column) instead of ending the run."""
        color = batch["color"].float()
        result = filter_images([self.tree], self.features(batch), color, self.radius)
        valid, out = result.valid[0], result.color[0]
        if not bool(valid.all()):
            bad = [int(i) for i in torch.nonzero(~valid).flatten()]
            log.warning(
                "model.expression %r: undefined weights (NaN/Inf or a zero weight sum) on batch image(s) "
                "%s: their output is NaN",
                self.expression,
                bad,
            )
            out = torch.where(valid.view(-1, 1, 1, 1), out, torch.full_like(out, float("nan")))
        return {"color": out}


#: Batch keys that may instead be a channel of `diffuse_in` (named as in `src.data.features`).
_INPUT_CHANNELS = ("visibility", "normal_var", "albedo_var", "depth_var", "visibility_var")
