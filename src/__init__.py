"""nrbench: a reproducible experiment and benchmark harness for neural rendering research."""

from omegaconf import OmegaConf

from src.data.features import feature_count as _feature_count
from src.data.volume_features import volume_feature_count as _volume_feature_count

# `${nrbench.join:${compare.denoise.learned},...}`: config lists joined into a Hydra sweep value
# ("kpcn,dpcn,resnet"), so that a sweep reads the compared models from conf/compare.yaml. Registered on
# import of the package, i.e. before any config that uses it is composed.
OmegaConf.register_new_resolver(
    "nrbench.join", lambda *lists: ",".join(str(item) for items in lists for item in items), replace=True
)


def _scale(value, *factors) -> str:
    """`${nrbench.scale:${task.search.population},0.5,1,2,4}` -> "2,4,8,16" at population 4: a sweep's
    values as multiples of the profile's value (integers, at least 1), so one study fits every profile."""
    return ",".join(str(max(1, round(float(value) * float(f)))) for f in factors)


# `${nrbench.scale:<value>,<factor>,...}`: see `_scale`.
OmegaConf.register_new_resolver("nrbench.scale", _scale, replace=True)

# `in_channels: ${nrbench.channels:${task.features}}`: a denoiser's input channel count, derived from the
# configured feature list (src/data/features.py) instead of typed by hand.
OmegaConf.register_new_resolver("nrbench.channels", _feature_count, replace=True)
# `${nrbench.volume_channels:${dataset.volume_features}}`: the same for the volumetric denoiser's inputs.
OmegaConf.register_new_resolver("nrbench.volume_channels", _volume_feature_count, replace=True)
