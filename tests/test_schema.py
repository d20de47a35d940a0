"""The config schemas' bounds by value (`src/schema/`): for every bounded field, the boundary itself is
accepted and the value just outside it rejected (an exclusive bound: the boundary rejected, the value just
inside accepted), with the one line the harness prints; then the cross-field checks at their edges.

Each field is checked alone, in a one-field model with the schema's own annotation (no whole config to
compose), through `src.schema.checks.check`, the function a job start calls. The table below is written
out by hand: a changed bound (`ge` -> `gt`, `0` -> `1`, a PositiveInt that became a NonNegativeInt) fails
its row, and a bounded field without a row fails `test_every_bounded_field_has_a_row`."""

from __future__ import annotations

import importlib
import math
import re
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import annotated_types
import pytest
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, create_model
from pydantic.fields import FieldInfo
from pydantic_core import PydanticCustomError

from src.errors import ConfigError
from src.schema.checks import check, error_line
from src.schema.dataset import _within
from src.schema.types import PositiveInt, Range, Schema, passes

MODULES = ("types", "run", "denoise", "nerf", "filter_search", "dataset")


@dataclass(frozen=True)
class Bound:
    """A field's bounds: `lo`/`hi` (None: unbounded), open or closed; `shape`: where the bounded number
    sits in the field's value: `scalar`, `item` (a list's items), `colour` (the 3 items of a colour),
    `colours` (a list of colours), `value` (a mapping's values) or `range` (a [lo, hi] pair)."""

    kind: type
    lo: float | None = None
    lo_open: bool = False
    hi: float | None = None
    hi_open: bool = False
    shape: str = "scalar"


POSITIVE_INT = Bound(int, lo=0, lo_open=True)
POSITIVE = Bound(float, lo=0, lo_open=True)
NON_NEGATIVE_INT = Bound(int, lo=0)
NON_NEGATIVE = Bound(float, lo=0)
PROBABILITY = Bound(float, lo=0, hi=1)
AT_LEAST_ONE = Bound(float, lo=1)
PERCENTILE = Bound(float, lo=0, lo_open=True, hi=100)
FRACTION = Bound(float, lo=0, lo_open=True, hi=1)
OPEN_UNIT = Bound(float, lo=0, lo_open=True, hi=1, hi_open=True)
POSITIVE_INT_ITEMS = Bound(int, lo=0, lo_open=True, shape="item")
NON_NEGATIVE_INT_ITEMS = Bound(int, lo=0, shape="item")
POSITIVE_ITEMS = Bound(float, lo=0, lo_open=True, shape="item")
NON_NEGATIVE_VALUES = Bound(float, lo=0, shape="value")
DEPTH = Bound(int, lo=-1)
GRID_RES = Bound(int, lo=4)
COLOUR = Bound(float, lo=0, shape="colour")
POSITIVE_SIZE3 = Bound(float, lo=0, lo_open=True, shape="colour")
COLOURS = Bound(float, lo=0, shape="colours")
ANGLE = Bound(float, lo=0, lo_open=True, hi=3.14159, hi_open=True)
ELEVATION = Bound(float, lo=-90, hi=90)
UNIT_RANGE = Bound(float, lo=0, hi=1, shape="range")
NON_NEGATIVE_RANGE = Bound(float, lo=0, shape="range")
POSITIVE_RANGE = Bound(float, lo=1e-9, shape="range")
SLATS_RANGE = Bound(float, lo=1, shape="range")
ELEVATION_RANGE = Bound(float, lo=-89, hi=89, shape="range")
ZENITH_RANGE = Bound(float, lo=0, hi=90, shape="range")
HG_RANGE = Bound(float, lo=-0.99, hi=0.99, shape="range")

#: Every bounded field of the schemas, `<module of src.schema>.<model>.<field>` (a field a subclass inherits
#: is listed under the model that declares it).
BOUNDED: dict[Bound, str] = {
    POSITIVE_INT: """
        run.Ssim.win_size run.Export.spp run.Export.frames dataset.PatchCounts.train dataset.PatchCounts.val
        denoise.Preprocess.patch_size run.Report.min_tile_px
        dataset.StillPreprocess.patches_per_image dataset.SequencePreprocess.sequence_frames
        dataset.SequencePreprocess.patches_per_sequence dataset.FeatureSelection.max_size
        dataset.FeatureSelection.val_batches denoise.Train.batch_size denoise.Train.epochs
        denoise.Train.max_steps denoise.Train.log_every denoise.Eval.crop_size denoise.Eval.crop_zoom
        nerf.Train.max_steps nerf.Train.batch_size nerf.Train.micro_batch_rays
        nerf.Train.cpu_micro_batch_rays nerf.Train.max_train_images nerf.Train.max_val_images
        nerf.Train.val_rays nerf.Train.chunk nerf.Train.cpu_chunk nerf.Train.log_every
        nerf.Train.val_every nerf.Train.checkpoint_every nerf.Eval.max_images nerf.Eval.chunk
        nerf.Eval.cpu_chunk filter_search.Search.max_images filter_search.Search.crop
        filter_search.Search.islands filter_search.Search.population
        filter_search.Search.migration_interval filter_search.Search.migrants
        filter_search.Search.tournament_size filter_search.Search.max_length
        filter_search.Search.tree_batch dataset.Integrator.albedo_samples dataset.Randomize.env_res
        dataset.Randomize.texture_res dataset.Randomize.noise_octaves dataset.Randomize.noise_base_cells
        dataset.ProceduralDataset.scenes_per_base dataset.ProceduralDataset.width
        dataset.ProceduralDataset.height dataset.ProceduralDataset.reference_spp
        dataset.ProceduralDataset.max_pass_samples dataset.Medium.octaves
        dataset.VolumetricDataset.scenes_per_base dataset.VolumetricDataset.frames
        dataset.VolumetricDataset.width dataset.VolumetricDataset.height
        dataset.VolumetricDataset.reference_spp dataset.VolumetricDataset.max_pass_samples
        dataset.DenoisingData.input_channels
        dataset.Views.train dataset.Views.val dataset.Views.test dataset.StudioEnv.res
        dataset.Busy.n_objects dataset.Busy.texture_res dataset.Busy.noise_octaves
        dataset.Busy.noise_base_cells dataset.NerfTabletop.texture_res dataset.NerfTabletop.noise_octaves
        dataset.NerfTabletop.noise_base_cells dataset.NerfProceduralDataset.width
        dataset.NerfProceduralDataset.height dataset.NerfProceduralDataset.spp
        dataset.NerfProceduralDataset.max_pass_samples dataset.BlenderDataset.downscale
        dataset.BlenderDataset.max_images dataset.NoisebaseDataset.frames
        dataset.NoisebaseDataset.reference_spp dataset.NoisebaseDataset.rendering_height
        dataset.NoisebaseDataset.rendering_width
    """,
    POSITIVE: """
        run.Ssim.sigma run.Ssim.k1 run.Ssim.k2 run.Metrics.gamma run.Metrics.relmse_eps run.Cvvdp.fps
        run.SppEquivalentOptions.margin
        run.Metrics.smape_eps denoise.Repair.firefly_clamp dataset.StillPreprocess.eps_albedo
        denoise.Preprocess.importance_window denoise.Preprocess.whiten_eps denoise.Train.lr
        nerf.Train.lr_init nerf.Train.grad_max_norm filter_search.SeedSigmas.spatial
        filter_search.SeedSigmas.color filter_search.SeedSigmas.normal filter_search.SeedSigmas.albedo
        filter_search.SeedSigmas.depth filter_search.Search.fitness_eps dataset.Randomize.sun_radius_deg
        dataset.Randomize.noise_persistence dataset.Objects.spread dataset.Objects.scale
        dataset.CornellCamera.distance dataset.OrbitCamera.distance dataset.Plane.size
        dataset.AreaLight.distance dataset.AreaLight.size dataset.Medium.feature_size
        dataset.Medium.persistence dataset.CloudMedium.softness dataset.CloudMedium.worley_cells
        dataset.PlumeMedium.radius dataset.Canopy.size dataset.Canopy.thickness dataset.NearFar.near
        dataset.NearFar.far dataset.Stripes.width_deg dataset.StudioSun.radius_deg
        dataset.Spheres.sphere_radius dataset.Spheres.spacing dataset.Spheres.dielectric_ior
        dataset.Busy.noise_persistence dataset.Ground.radius dataset.Ground.checks
        dataset.GlossySphere.roughness dataset.NerfTabletop.sphere_radius dataset.NerfTabletop.ring_radius
        dataset.NerfTabletop.cube_half_edge dataset.NerfTabletop.centre_radius
        dataset.NerfTabletop.dielectric_ior dataset.NerfTabletop.noise_persistence
        dataset.NerfProceduralDataset.radius dataset.NerfProceduralDataset.bound_radius
    """,
    NON_NEGATIVE_INT: """
        run.Lpips.seed run.Metrics.relmse_crop run.NoisebaseProtocol.warmup run.Report.images
        run.VolumetricCompare.selected_size
        run.RunSchema.seed run.RunSchema.data_seed denoise.Preprocess.split_seed
        denoise.Preprocess.sample_seed dataset.FeatureSelection.size dataset.FeatureSelection.random_seed
        denoise.Train.num_workers denoise.Eval.tile nerf.Train.precrop_iters filter_search.Search.radius
        filter_search.Search.generations filter_search.Search.seed filter_search.Search.max_constants
        filter_search.Search.hall_of_fame dataset.Integrator.rr_depth
        dataset.ProceduralDataset.seed dataset.VolumeIntegrator.rr_depth dataset.VolumetricDataset.seed
        dataset.Stripes.count dataset.NerfTabletop.n_textured dataset.NerfProceduralDataset.rr_depth
        dataset.NerfProceduralDataset.seed
    """,
    PROBABILITY: """
        denoise.Split.train denoise.Split.val denoise.Split.test denoise.Preprocess.min_keep_prob
        dataset.FeatureSelection.dropout filter_search.Search.replication filter_search.Search.crossover
        filter_search.Search.mutation filter_search.Search.crossover_mutation
        filter_search.Search.seed_copies dataset.Randomize.textured_probability
        dataset.Randomize.checker_probability dataset.Randomize.sphere_probability
        dataset.VolumetricRandomize.isotropic_probability dataset.PlumeMedium.detail
        dataset.Busy.textured_fraction dataset.Busy.checker_probability
        dataset.NerfTabletop.checker_probability
    """,
    AT_LEAST_ONE: """
        denoise.Preprocess.candidates_factor
    """,
    NON_NEGATIVE: """
        denoise.Preprocess.min_distance dataset.SequenceTrain.temporal_weight
        dataset.OrbitCamera.target_jitter dataset.AreaLight.radiance dataset.Tabletop.sky_scale
        dataset.PlumeMedium.source_jitter dataset.PlumeMedium.spread dataset.PlumeMedium.sway
        dataset.Cloud.sky_scale dataset.Godrays.sky_scale dataset.Stripes.intensity
        dataset.StudioSun.intensity dataset.StudioEnv.scale dataset.DirectionalSun.irradiance
        dataset.Busy.ambient filter_search.Search.bias_guard
    """,
    PERCENTILE: """
        denoise.Preprocess.importance_percentile
    """,
    FRACTION: """
        nerf.Train.precrop_frac
    """,
    OPEN_UNIT: """
        run.Ledger.alpha
    """,
    POSITIVE_INT_ITEMS: """
        filter_search.Search.spp dataset.ProceduralDataset.noisy_spp dataset.VolumetricDataset.noisy_spp
        dataset.NoisebaseDataset.noisy_spp dataset.ProceduralDataset.ladder_spp
        dataset.VolumetricDataset.ladder_spp dataset.NoisebaseDataset.ladder_spp
    """,
    NON_NEGATIVE_VALUES: """
        filter_search.Search.mutation_kinds
    """,
    DEPTH: """
        dataset.Integrator.max_depth dataset.VolumeIntegrator.max_depth
        dataset.NerfProceduralDataset.max_depth
    """,
    UNIT_RANGE: """
        dataset.VolumetricRandomize.albedo_tint dataset.Medium.albedo dataset.FogMedium.modulation
        dataset.HazeMedium.modulation
    """,
    NON_NEGATIVE_RANGE: """
        dataset.VolumetricRandomize.wind_speed dataset.VolumetricRandomize.evolve_speed
        dataset.Sun.irradiance dataset.Medium.density_scale
    """,
    ELEVATION_RANGE: """
        dataset.VolumeCamera.elevation
    """,
    ZENITH_RANGE: """
        dataset.Sun.zenith_angle
    """,
    POSITIVE_ITEMS: """
        dataset.Spheres.roughness
    """,
    POSITIVE_SIZE3: """
        dataset.MediumBox.size
    """,
    HG_RANGE: """
        dataset.Medium.g
    """,
    POSITIVE_RANGE: """
        dataset.FogMedium.scale_height dataset.Canopy.slat_width
    """,
    SLATS_RANGE: """
        dataset.Canopy.slats
    """,
    GRID_RES: """
        dataset.VolumetricDataset.grid_res
    """,
    NON_NEGATIVE_INT_ITEMS: """
        dataset.VolumetricDataset.render_frames
    """,
    COLOUR: """
        dataset.NearFar.background dataset.StudioEnv.zenith dataset.StudioEnv.horizon
        dataset.StudioEnv.ground dataset.Spheres.plastic_color dataset.Ground.color0 dataset.Ground.color1
        dataset.NerfTabletop.plastic_color
    """,
    COLOURS: """
        dataset.Stripes.colors
    """,
    ANGLE: """
        dataset.NerfProceduralDataset.camera_angle_x
    """,
    ELEVATION: """
        dataset.NerfProceduralDataset.test_elevation_deg
    """,
}
ROWS = [(name, bound) for bound, names in BOUNDED.items() for name in names.split()]


def _model(name: str) -> tuple[type[BaseModel], str]:
    module, model, field = name.split(".")
    return getattr(importlib.import_module(f"src.schema.{module}"), model), field


def _one_field(name: str) -> tuple[type[BaseModel], str]:
    """A closed, strict model holding only that field, with the schema's annotation and constraints."""
    model, field = _model(name)
    info = model.model_fields[field]
    return create_model(f"Only_{field}", __base__=Schema, **{field: (info.annotation, info)}), field


def _value(bound: Bound, x: float, other: float | None = None):
    """The field's value with the bounded number x where the bound applies (a range: [x, other])."""
    x = bound.kind(x)
    return {
        "scalar": x,
        "item": [x],
        "colour": [x, x, x],
        "colours": [[x, x, x]],
        "value": {"insert": x},
        "range": [x, x] if other is None else [x, other],
    }[bound.shape]


def _near(bound: Bound, b: float, direction: int) -> float:
    """The representable value next to bound b in `direction` (+1 up, -1 down) for the field's type."""
    if bound.kind is int:
        return b + direction
    return b + direction * 1e-9 * max(1.0, abs(b))


def _key(bound: Bound, field: str) -> str:
    """Where the one line puts the key of the first offending number."""
    index = {"item": "[0]", "colour": "[0]", "colours": "[0][0]", "value": ".insert"}
    return f"x.{field}{index.get(bound.shape, '')}"


def _expectation(bound: Bound, op: str, b: float) -> str:
    """The words `check` states (src.schema.checks._expectation), as a regex."""
    if bound.shape == "range":
        hi = bound.hi if bound.hi is not None else math.inf
        return re.escape(f"in [{bound.lo:g}, {hi:g}]") + "$"
    if b == 0 and op in (">", ">="):
        adjective = "positive" if op == ">" else "non-negative"
        noun = "integer" if bound.kind is int else "number"  # a list's or mapping's items by their type
        return f"expected a {adjective} {noun}$"
    number = re.escape(f"{b:g}") + (r"(\.0)?" if float(b).is_integer() else "")
    return f"expected a value {re.escape(op)} {number}$"


def _accepted(model, field, value):
    assert getattr(check(model, {field: value}, "x"), field) == value


def _rejected(model, field, value, bound, op, b):
    with pytest.raises(ConfigError) as err:
        check(model, {field: value}, "x")
    line = str(err.value)
    assert line.startswith(_key(bound, field) + "="), line
    assert re.search(_expectation(bound, op, b), line), line


@pytest.mark.parametrize(("name", "bound"), ROWS, ids=[name for name, _ in ROWS])
def test_a_bounded_field_accepts_its_boundary_and_rejects_just_outside(name, bound):
    model, field = _one_field(name)
    if bound.lo is not None:
        lo, below, above = bound.lo, _near(bound, bound.lo, -1), _near(bound, bound.lo, +1)
        other = None if bound.shape != "range" else (bound.hi if bound.hi is not None else lo + 1)
        if bound.lo_open:
            _rejected(model, field, _value(bound, lo), bound, ">", lo)
            _accepted(model, field, _value(bound, above))
        else:
            _accepted(model, field, _value(bound, lo, other))
            _rejected(model, field, _value(bound, below, other), bound, ">=", lo)
    if bound.hi is not None:
        hi, below, above = bound.hi, _near(bound, bound.hi, -1), _near(bound, bound.hi, +1)
        first = None if bound.shape != "range" else bound.lo
        if bound.hi_open:
            _rejected(model, field, _value(bound, hi), bound, "<", hi)
            _accepted(model, field, _value(bound, below))
        elif bound.shape == "range":  # [lo, hi] and [lo, hi + eps]
            _accepted(model, field, [bound.kind(first), bound.kind(hi)])
            _rejected(model, field, [bound.kind(first), bound.kind(above)], bound, "<=", hi)
        else:
            _accepted(model, field, _value(bound, hi))
            _rejected(model, field, _value(bound, above), bound, "<=", hi)


BOUNDS = (annotated_types.Gt, annotated_types.Ge, annotated_types.Lt, annotated_types.Le)


def _has_bound(annotation) -> bool:
    """Whether an annotation (unions, lists, Annotated metadata walked) holds a numeric bound or a
    `_within` range check."""
    if isinstance(annotation, BOUNDS):
        return True
    if isinstance(annotation, AfterValidator):
        return "_within" in annotation.func.__qualname__  # also under mutmut's x__within__mutmut_orig
    if isinstance(annotation, FieldInfo):
        return _has_bound(annotation.annotation) or any(_has_bound(m) for m in annotation.metadata)
    return any(_has_bound(a) for a in typing.get_args(annotation))


def test_every_bounded_field_has_a_row():
    found = set()
    for module_name in MODULES:
        module = importlib.import_module(f"src.schema.{module_name}")
        for model in vars(module).values():
            if not isinstance(model, type) or model.__module__ != module.__name__:
                continue
            assert issubclass(model, BaseModel), model
            declared = vars(model).get("__annotations__", {})
            for field, info in model.model_fields.items():
                if field in declared and _has_bound(info):
                    found.add(f"{module_name}.{model.__name__}.{field}")
    listed = [name for name, _ in ROWS]
    assert len(listed) == len(set(listed))
    assert found == set(listed)


SEARCH = {
    "split": "val",
    "spp": [4],
    "max_images": None,
    "crop": None,
    "radius": 10,
    "normalize": True,
    "seed_sigmas": {"spatial": 5.0, "color": 0.5, "normal": 0.3, "albedo": 0.1, "depth": 0.05},
    "islands": 4,
    "population": 100,
    "generations": 200,
    "migration_interval": 5,
    "migrants": 1,
    "tournament_size": 8,
    "replication": 0.1,
    "crossover": 0.45,
    "mutation": 0.45,
    "crossover_mutation": 0.85,
    "seed_copies": 0.1,
    "mutation_kinds": {"insert": 0.3, "replace": 0.3, "swap": 0.3, "delete": 0.1},
    "max_length": 75,
    "vector_pairs": "mixed",
    "crossover_points": "type_first",
    "shares_count": "draws",
    "max_constants": None,
    "color_variance": False,
    "hall_of_fame": 0,
    "fitness_cache": True,
    "fitness_eps": 0.01,
    "bias_guard": 0.0,
    "tree_batch": 16,
    "seed": 0,
    "resume": None,
    "out_dir": "search",
}


def _line(model, values, prefix):
    with pytest.raises(ConfigError) as err:
        check(model, values, prefix)
    return str(err.value)


def test_the_split_fractions_may_sit_at_0_and_1_and_must_sum_to_1_within_1e6():
    from src.schema.denoise import Split

    key = "task.preprocess.split"
    for fractions in ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.7, 0.2, 0.1), (0.7, 0.2, 0.1 + 9e-7)):
        check(Split, dict(zip(("train", "val", "test"), fractions, strict=True)), key)
    bad = _line(Split, {"train": 0.7, "val": 0.2, "test": 0.10001}, key)
    assert bad == "task.preprocess.split: fractions sum to 1.00001; expected 1"
    assert _line(Split, {"train": 0.7, "val": 0.2, "test": 0.1 - 2e-6}, key).startswith(key)


def test_the_search_probabilities_may_sit_at_their_bounds_and_migrants_stay_below_the_population():
    from src.schema.filter_search import Search

    for change in (
        {"replication": 0.0, "crossover": 0.0, "mutation": 1.0},
        {"replication": 1.0, "crossover": 0.0, "mutation": 0.0},
        {"crossover_mutation": 0.0, "seed_copies": 1.0},
        {"population": 2, "migrants": 1},
        {"population": 5, "migrants": 4},
        {"mutation_kinds": {"insert": 0.0, "delete": 1e-9}},
        {"generations": 0, "radius": 0, "seed": 0},
    ):
        check(Search, {**SEARCH, **change}, "task.search")
    line = _line(Search, {**SEARCH, "population": 5, "migrants": 5}, "task.search")
    assert line == "task.search.migrants=5: expected fewer than task.search.population=5"
    line = _line(Search, {**SEARCH, "mutation_kinds": {"insert": 0.0, "swap": 0.0}}, "task.search")
    assert line == "task.search.mutation_kinds: the weights sum to 0; expected a positive sum"
    line = _line(Search, {**SEARCH, "mutation": 0.45 + 2e-6}, "task.search")
    assert line.startswith("task.search: replication + crossover + mutation = 1")
    # the constant cap admits the seed: 2 constants per finite sigma (10 for five)
    check(Search, {**SEARCH, "max_constants": 10}, "task.search")
    line = _line(Search, {**SEARCH, "max_constants": 9}, "task.search")
    assert line.startswith("task.search.max_constants=9: the seed") and "has 10 constants" in line


def test_far_must_lie_beyond_near_and_a_range_may_be_a_single_value():
    from src.schema.dataset import NearFar

    scene = {
        "_target_": "kind",
        "near": 2.0,
        "far": 2.0 + 1e-9,
        "background": [0.0, 0.0, 0.0],
        "alpha": "auto",
    }
    check(NearFar, scene, "dataset")
    line = _line(NearFar, {**scene, "far": 2.0}, "dataset")
    assert line == "dataset.far=2: expected more than dataset.near=2"
    fov, _ = _one_field("dataset.Randomize.fov")
    check(fov, {"fov": [30.0, 30.0]}, "x")
    assert _line(fov, {"fov": [30.0, 30.0 - 1e-9]}, "x") == (
        "x.fov=[30.0, 29.999999999]: expected [lo, hi] with lo <= hi"
    )


def _no_sevens(value: int) -> None:
    if value == 7:
        raise ConfigError("lucky.number=7: a check's own line, kept whole")


class _Inner(Schema):
    depth: PositiveInt
    tags: list[str] = []


class _Opaque:
    """A type pydantic checks by isinstance only."""


class _Lax(BaseModel):
    """Not strict: a float for an int is its own kind of error (`int_from_float`)."""

    n: int


class _Sample(Schema):
    model_config = ConfigDict(strict=True, extra="forbid", arbitrary_types_allowed=True)

    flag: bool
    count: int | None
    ratio: float
    names: list[str] = Field(min_length=1)
    pair: list[float] = Field(min_length=2, max_length=2)
    mode: Literal["a", "b", "c"]
    inner: _Inner
    maybe: _Inner | None
    label: str = Field(min_length=1)
    table: dict[str, float]
    above_two: float = Field(gt=2)
    even: int = Field(multiple_of=2)
    aliased: str = Field(alias="_aliased_")
    lucky: Annotated[int, AfterValidator(lambda v: passes(_no_sevens, v))]
    # unions whose first member names itself in the error's loc: not a key
    range_or_number: Range | float
    auto_or_count: Literal["auto"] | PositiveInt
    path_or_count: Path | int
    opaque_or_count: _Opaque | int


SAMPLE = {
    "flag": True,
    "count": None,
    "ratio": 1.0,
    "names": ["a"],
    "pair": [1.0, 2.0],
    "mode": "a",
    "inner": {"depth": 1},
    "maybe": None,
    "label": "l",
    "table": {},
    "above_two": 2.5,
    "even": 2,
    "_aliased_": "s",
    "lucky": 8,
    "range_or_number": 1.0,
    "auto_or_count": "auto",
    "path_or_count": 3,
    "opaque_or_count": 3,
}
#: (key, value, the one line) for each kind of violation `checks._expectation` words
VIOLATIONS = [
    ("flag", 1, "x.flag=1: expected true or false"),
    ("flag", None, "x.flag=null: expected true or false"),
    ("count", "a", "x.count='a': expected an integer"),
    ("count", True, "x.count=true: expected an integer"),
    ("count", 2.5, "x.count=2.5: expected an integer"),
    ("ratio", "abc", "x.ratio='abc': expected a number"),
    ("names", "a", "x.names='a': expected a list"),
    ("names", [], "x.names=[]: expected a non-empty list"),
    ("names", [1], "x.names[0]=1: expected a string"),
    ("pair", [1.0], "x.pair=[1.0]: expected at least 2 items"),
    ("pair", [1.0, 2.0, 3.0], "x.pair=[1.0, 2.0, 3.0]: expected at most 2 items"),
    ("mode", "d", "x.mode='d': expected one of 'a', 'b' or 'c'"),
    ("inner", 3, "x.inner=3: expected a mapping"),
    ("inner", {"depth": 0}, "x.inner.depth=0: expected a positive integer"),
    ("inner", {"depth": 1, "extra": 2}, "x.inner.extra: unknown key; expected one of ['depth', 'tags']"),
    ("inner", {}, "x.inner.depth: missing; expected a value"),
    ("maybe", {"depth": 0}, "x.maybe.depth=0: expected a positive integer"),
    ("maybe", {"depth": 1, "deep": 1}, "x.maybe.deep: unknown key; expected one of ['depth', 'tags']"),
    ("label", "", "x.label='': expected a non-empty string"),
    ("table", [1], "x.table=[1]: expected a mapping"),
    ("table", {"k": "v"}, "x.table.k='v': expected a number"),
    ("above_two", 2.0, "x.above_two=2.0: expected a value > 2.0"),
    ("even", 3, "x.even=3: expected input should be a multiple of 2"),
    ("_aliased_", 3, "x._aliased_=3: expected a string"),
    ("lucky", 7, "lucky.number=7: a check's own line, kept whole"),
    ("inner", {"depth": 1, "tags": ["a", 1]}, "x.inner.tags[1]=1: expected a string"),
    ("range_or_number", [2.0, 1.0], "x.range_or_number=[2.0, 1.0]: expected [lo, hi] with lo <= hi"),
    ("auto_or_count", 0, "x.auto_or_count=0: expected one of 'auto' or a positive integer"),
    # a union with no validator of ours: every member's expectation, joined
    ("path_or_count", "p", "x.path_or_count='p': expected input should be an instance of Path or an integer"),
    (
        "opaque_or_count",
        "o",
        "x.opaque_or_count='o': expected input should be an instance of _Opaque or an integer",
    ),
]


@pytest.mark.parametrize(("key", "value", "line"), VIOLATIONS, ids=[line for _, _, line in VIOLATIONS])
def test_each_kind_of_violation_is_one_line_with_the_key_the_value_and_what_is_expected(key, value, line):
    assert check(_Sample, SAMPLE, "x").lucky == 8  # the base is valid, the checked value kept
    assert _line(_Sample, {**SAMPLE, key: value}, "x") == line


def test_a_missing_or_unknown_root_key_is_named_without_a_prefix():
    with pytest.raises(ConfigError, match=r"^flag: missing; expected a value$"):
        check(_Sample, {k: v for k, v in SAMPLE.items() if k != "flag"})  # no prefix by default
    assert _line(_Lax, {"n": 2.5}, "x") == "x.n=2.5: expected an integer"
    known = list(SAMPLE)  # SAMPLE lists every key in declaration order, the alias as written
    assert _line(_Sample, {**SAMPLE, "bogus": 1}, "") == f"bogus: unknown key; expected one of {known}"


def test_within_checks_every_value_against_both_ends():
    # The validator factory behind UnitRange, Medium.g and the rest, called here too: it runs at import,
    # where mutmut's mutants cannot be seen.
    within = _within(-1.0, 2.0, "things").func
    assert within([-1.0, 2.0]) == [-1.0, 2.0]
    for bad in ([-1.0 - 1e-9, 0.0], [0.0, 2.0 + 1e-9]):
        with pytest.raises(PydanticCustomError) as err:
            within(bad)
        assert str(err.value) == "expected things in [-1, 2]"


def test_a_union_field_is_named_by_its_key_alone():
    camera, _ = _one_field("dataset.CornellCamera.origin_x")  # Jitter: float | Range
    assert _line(camera, {"origin_x": [2.0, 1.0]}, "x").startswith("x.origin_x=[2.0, 1.0]: ")
    loss, _ = _one_field("dataset.SequenceTrain.loss")  # str | Target
    assert _line(loss, {"loss": 3}, "x").startswith("x.loss=3: ")
    kinds, _ = _one_field("filter_search.Search.mutation_kinds")  # dict[Literal[...], float]
    assert _line(kinds, {"mutation_kinds": {"grow": 1.0}}, "x").startswith("x.mutation_kinds.grow=")


def test_a_union_reports_its_matching_members_expectation_or_all_of_them():
    """Pydantic reports one error per union member, in member order: the member whose shape the value has
    (our own validator's line) wins, else every member's expectation is named."""
    camera, _ = _one_field("dataset.CornellCamera.origin_x")
    assert (
        _line(camera, {"origin_x": [2.0, 1.0]}, "x")
        == "x.origin_x=[2.0, 1.0]: expected [lo, hi] with lo <= hi"
    )
    loss, _ = _one_field("dataset.SequenceTrain.loss")
    assert _line(loss, {"loss": 3}, "x") == "x.loss=3: expected a string or a mapping"


class _Inner(BaseModel):
    model_config = ConfigDict(extra="forbid")
    depth: int = 1


class _Outer(BaseModel):
    model_config = ConfigDict(extra="forbid")
    inner: _Inner = _Inner()


class _Unions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    count: PositiveInt | Literal["auto"]
    ratio: float | Literal["auto"] = 0.5
    inner_or_count: _Inner | int = 1
    outers: list[_Outer] = []
    flag: bool | Literal["x"]
    maybe: None | Literal["x"] | int
    spp: list[PositiveInt]


@pytest.mark.parametrize(
    ("value", "line"),
    [
        ({"count": 0}, "x.count=0: expected a positive integer or one of 'auto'"),
        ({"flag": "q"}, "x.flag='q': expected true or false or one of 'x'"),
        ({"maybe": "q"}, "x.maybe='q': expected one of 'x' or an integer"),
        ({"spp": [1, 0]}, "x.spp[1]=0: expected a positive integer"),
        ({"ratio": "q"}, "x.ratio='q': expected a number or one of 'auto'"),
        # an unknown key inside a union's model member, and in a model inside a list of models
        ({"inner_or_count": {"bogus": 1}}, "x.inner_or_count.bogus: unknown key; expected one of ['depth']"),
        (
            {"outers": [{}, {"inner": {"bogus": 1}}]},
            "x.outers[1].inner.bogus: unknown key; expected one of ['depth']",
        ),
    ],
)
def test_union_members_are_labels_not_keys_and_an_items_noun_is_its_type(value, line):
    """pydantic's member labels (`constrained-int`, `bool`, `literal['x']`, `int`) stay out of the key, the
    bound's noun is read from the member type (integer), each member's expectation is named."""
    assert _line(_Unions, {"count": 1, "flag": True, "maybe": None, "spp": [1], **value}, "x") == line


@pytest.mark.parametrize(
    "label",
    ["float", "int", "str", "bool", "none", "[key]", "constrained-int", "function-after[f(), int]",
     "lax-or-strict[lax=int,strict=int]", "is-instance[Path]", "literal['a']", "nullable[int]",
     "list[float]", "dict[str,float]", "tuple[int, int]", "GlossySphere"],
)  # fmt: skip
def test_pydantics_labels_are_tags_and_keys_are_not(label):
    from src.schema.checks import _is_tag

    importlib.import_module("src.schema.dataset")  # GlossySphere: a schema model's class name
    assert _is_tag(label)
    assert not any(_is_tag(key) for key in ("spp", "lr", "my-scene", "float_type", "glossy", "_target_"))


def test_an_unknown_key_in_a_list_of_models_names_the_items_keys():
    scene = importlib.import_module("src.schema.dataset").NerfTabletop
    with pytest.raises(ValidationError) as err:
        scene.model_validate({"glossy": [{"material": "x", "roughness": 0.1, "bogus": 1}]})
    (extra,) = [e for e in err.value.errors() if e["type"] == "extra_forbidden"]
    assert (
        error_line(extra, scene, "x")
        == "x.glossy[0].bogus: unknown key; expected one of ['material', 'roughness']"
    )


# Surviving mutants of src/schema/checks.py, types.py and dataset.py (bash scripts/mutation.sh schema), all
# equivalent here. (mutmut mutates function bodies only: the bounds themselves, `Field(gt=0)` and the
# like, are class and module attributes; the table above checks them, and hand-made mutants (PositiveInt
# gt -> ge, Probability le -> lt, Percentile 100 -> 101, grid_res ge -> gt, a NonNegativeInt that became a
# PositiveInt, Colour ge -> gt, the decorated cross-field validators' tolerances and comparisons) each
# failed rows here.)
# - _expectation, literal_error `ctx.get("expected", "")` with the default None / 'XXXX' / dropped (3
#   mutants): pydantic always puts `expected` in a literal_error's ctx.
# - _field `if loc` -> `if loc or True`: _noun, its only caller, runs for a bound's error only, whose loc
#   names at least the field.
# - _noun, the fallback `0` of `end` -> 1 / None / dropped, and `if end` -> `if end or True` (4 mutants): the
#   fallback is taken only when no prefix of the loc is a schema field, and a model's errors always start
#   at one of its fields.
# - _first_violation `at_key[0]` -> `at_key[1]`: the errors at one key are one union's members, all
#   reporting the same input.
# - _models_in `found += ...` -> `found = ...`: differs only for a union of a model and a list of models,
#   which no schema has.
