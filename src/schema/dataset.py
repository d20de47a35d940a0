"""Schemas of `dataset:`, one per shipped data kind (each kind's `schema`, `src/kinds/`; a user's own kind
may leave it None and check its config where it reads it), down to the scene families' layout, light and
material blocks."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, Field, field_validator, model_validator

from src.data.volume_features import volume_feature_channels
from src.schema.types import (
    Colour,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    Probability,
    Range,
    Schema,
    Target,
    expected,
    known_loss,
    own_error,
    passes,
)

SppList = Annotated[list[PositiveInt], Field(min_length=1)]
Names = Annotated[list[Annotated[str, Field(min_length=1)]], Field(min_length=1)]
Depth = Annotated[int, Field(ge=-1)]  # -1: unbounded


class Integrator(Schema):
    max_depth: Depth
    rr_depth: NonNegativeInt
    albedo_samples: PositiveInt


class Randomize(Schema):
    fov: Range
    camera_distance: Range
    elevation: Range
    roughness: Range
    ior: Range
    conductors: Names
    textured_probability: Probability
    checker_probability: Probability
    color: Range
    light_scale: Range
    env_rotation: Range
    env_res: PositiveInt
    sky_zenith: Range
    sky_horizon: Range
    sky_ground: Range
    sun_elevation: Range
    sun_radius_deg: PositiveFloat
    sun_intensity: Range
    texture_res: PositiveInt
    noise_octaves: PositiveInt
    noise_base_cells: PositiveInt
    noise_persistence: PositiveFloat
    checker_scale: Range
    n_objects: Range
    object_size: Range
    sphere_probability: Probability
    cube_rotation: Range
    azimuth: Range
    materials: list[Literal["diffuse", "conductor", "dielectric", "plastic"]] = Field(min_length=1)


Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Jitter = float | Range  # a fixed value, or a uniform [lo, hi] range


class Objects(Schema):
    centre: Vector3
    spread: PositiveFloat
    ground_y: float
    scale: PositiveFloat


class CornellCamera(Schema):
    distance: PositiveFloat
    origin_x: Jitter
    origin_y: Jitter
    target_x: Jitter
    target_y: Jitter
    target_z: Jitter


class OrbitCamera(Schema):
    distance: PositiveFloat
    target_height: float
    target_jitter: NonNegativeFloat


class Plane(Schema):
    size: PositiveFloat
    y: float


class AreaLight(Schema):
    elevation: Range
    distance: PositiveFloat
    target: Vector3
    size: PositiveFloat
    radiance: NonNegativeFloat


class Cornell(Schema):
    objects: Objects
    camera: CornellCamera


class Tabletop(Schema):
    table: Plane
    objects: Objects
    light: AreaLight
    sky_scale: NonNegativeFloat
    camera: OrbitCamera


class Outdoor(Schema):
    ground: Plane
    objects: Objects
    camera: OrbitCamera


class BaseScenes(Schema):
    """`dataset.base_scenes`: the layout, light and camera of each base scene."""

    cornell: Cornell
    tabletop: Tabletop
    outdoor: Outdoor


class DatasetSchema(Schema):
    """Every `dataset:` group names its data kind (`src/kinds/`)."""

    target: str = Field(alias="_target_", min_length=1)


class DenoisingData(DatasetSchema):
    """The batch contract of the denoising kinds (`src/models/denoise/base.py`): the colour's branches and
    each branch's input channels."""

    branches: Names
    input_channels: PositiveInt


class PatchCounts(Schema):
    train: PositiveInt
    val: PositiveInt


class StillPreprocess(Schema):
    """`dataset.preprocess` of the still images (src/data/shards.py; task.preprocess applies too)."""

    eps_albedo: PositiveFloat
    specular_variance: Literal["delta", "thesis"]
    patches_per_image: PositiveInt
    patches_per_split: PatchCounts | None


class ProceduralDataset(DenoisingData):
    name: Literal["procedural"]
    preprocess: StillPreprocess
    # Empty when the user's own scene files are the whole dataset (`dataset.bases=[]`); not both empty.
    bases: list[Literal["cornell", "tabletop", "outdoor"]]
    scenes_per_base: PositiveInt
    scene_files: list[str]
    width: PositiveInt
    height: PositiveInt
    noisy_spp: SppList
    reference_spp: PositiveInt
    # The held-out scenes' plain renders the spp-equivalent reads (src/data/ladder.py); [] or null: none.
    ladder_spp: list[PositiveInt] | None = None
    seed: NonNegativeInt
    integrator: Integrator
    max_pass_samples: PositiveInt
    randomize: Randomize
    base_scenes: BaseScenes

    @model_validator(mode="after")
    def _some_scenes(self) -> ProceduralDataset:
        """The scenes are the bases' permutations plus the scene files: at least one of the two lists."""
        if not self.bases and not self.scene_files:
            raise own_error(
                "dataset.bases=[]: expected a non-empty list of base scenes, or your own scenes in "
                "dataset.scene_files"
            )
        return self

    @model_validator(mode="after")
    def _reference_above_noisy(self) -> ProceduralDataset:
        """The renderer's own check of the sample counts (`spp_counts`)."""
        from src.render.render_dataset import spp_counts

        passes(spp_counts, {"noisy_spp": self.noisy_spp, "reference_spp": self.reference_spp})
        from src.data.ladder import ladder_counts  # the ladder's own check of its counts

        passes(ladder_counts, {"ladder_spp": self.ladder_spp, "reference_spp": self.reference_spp})
        return self


def _within(lo: float, hi: float, what: str):
    """An AfterValidator: every value of a list lies in [lo, hi]."""

    def check(values: list[float]) -> list[float]:
        if any(not lo <= v <= hi for v in values):
            raise expected(f"expected {what} in [{lo:g}, {hi:g}]")
        return values

    return AfterValidator(check)


UnitRange = Annotated[Range, _within(0.0, 1.0, "values")]
NonNegativeRange = Annotated[Range, _within(0.0, float("inf"), "values")]
PositiveRange = Annotated[Range, _within(1e-9, float("inf"), "positive values")]
Size3 = Annotated[list[PositiveFloat], Field(min_length=3, max_length=3)]


class VolumeIntegrator(Schema):
    max_depth: Depth
    rr_depth: NonNegativeInt


class VolumetricRandomize(Randomize):
    """The surface family's ranges (the table-top bases reuse its builders) plus the media and animation."""

    isotropic_probability: Probability
    albedo_tint: UnitRange
    wind_speed: NonNegativeRange
    wind_azimuth: Range
    evolve_speed: NonNegativeRange
    orbit_speed: Range
    dolly_speed: Range


class VolumeCamera(OrbitCamera):
    elevation: Annotated[Range, _within(-89.0, 89.0, "degrees")]


class Sun(Schema):
    zenith_angle: Annotated[Range, _within(0.0, 90.0, "degrees")]
    irradiance: NonNegativeRange


class MediumBox(Schema):
    centre: Vector3
    size: Size3


class Medium(Schema):
    box: MediumBox
    density_scale: NonNegativeRange
    albedo: UnitRange
    g: Annotated[Range, _within(-0.99, 0.99, "Henyey-Greenstein g")]
    feature_size: PositiveFloat
    octaves: PositiveInt
    persistence: PositiveFloat


class CloudMedium(Medium):
    coverage: Range
    softness: PositiveFloat
    worley_cells: PositiveFloat


class PlumeMedium(Medium):
    source_jitter: NonNegativeFloat
    radius: PositiveFloat
    spread: NonNegativeFloat
    sway: NonNegativeFloat
    detail: Probability
    rise_speed: float


class FogMedium(Medium):
    scale_height: PositiveRange
    modulation: UnitRange


class HazeMedium(Medium):
    modulation: UnitRange


class Canopy(Schema):
    height: float
    size: PositiveFloat
    slats: Annotated[Range, _within(1.0, float("inf"), "slat counts")]
    slat_width: PositiveRange
    thickness: PositiveFloat


class Cloud(Schema):
    ground: Plane
    sky_scale: NonNegativeFloat
    sun: Sun
    camera: VolumeCamera
    medium: CloudMedium


class SmokeTabletop(Tabletop):
    camera: VolumeCamera
    medium: PlumeMedium


class FogObjects(Tabletop):
    camera: VolumeCamera
    medium: FogMedium


class Godrays(Schema):
    ground: Plane
    objects: Objects
    sky_scale: NonNegativeFloat
    sun: Sun
    canopy: Canopy
    camera: VolumeCamera
    medium: HazeMedium


class VolumetricBaseScenes(Schema):
    """`dataset.base_scenes` of the volumetric family: each base's layout, lights, camera and medium."""

    cloud: Cloud
    smoke_tabletop: SmokeTabletop
    fog_objects: FogObjects
    godrays: Godrays


class SequencePreprocess(Schema):
    """`dataset.preprocess` of the sequence kinds (src/data/volume_shards.py; task.preprocess applies too)."""

    volume_transform: Literal["log_modulus", "none"]
    sequence_frames: PositiveInt
    patches_per_sequence: PositiveInt


class SequenceTrain(Schema):
    """`dataset.train` of the sequence kinds: what a model is fitted to (src/objectives/terms.py)."""

    loss: str | Target
    temporal_weight: NonNegativeFloat
    temporal_mode: Literal["signed", "abs"]
    temporal_warp: bool
    schedule: Target | None

    _known_loss = field_validator("loss")(classmethod(lambda cls, value: known_loss(value)))


class FeatureSelection(Schema):
    size: NonNegativeInt | None
    order: Literal["greedy", "random"]
    random_seed: NonNegativeInt
    start: list[str]
    candidates: list[str] | None
    subsets: Literal["uniform_size", "independent"]
    dropout: Probability
    neutral: dict[str, float]
    max_size: PositiveInt | None
    val_batches: PositiveInt | None
    dir: str

    @field_validator("start", "candidates")
    @classmethod
    def _known_features(cls, value: list[str] | None) -> list[str] | None:
        return value if value is None else passes(volume_feature_channels, value)


class SequenceOptions(DenoisingData):
    """The options every sequence kind has (conf/dataset/sequences/options.yaml): its input features, their
    automatic selection, its preprocessing and its objective."""

    volume_features: list[str] | None
    feature_selection: FeatureSelection
    preprocess: SequencePreprocess
    train: SequenceTrain

    @field_validator("volume_features")
    @classmethod
    def _known_volume_features(cls, value: list[str] | None) -> list[str] | None:
        return passes(volume_feature_channels, value)


class VolumetricDataset(SequenceOptions):
    name: Literal["volumetric"]
    experiment_suffix: str
    bases: list[Literal["cloud", "smoke_tabletop", "fog_objects", "godrays"]] = Field(min_length=1)
    scenes_per_base: PositiveInt
    frames: PositiveInt
    width: PositiveInt
    height: PositiveInt
    noisy_spp: SppList
    reference_spp: PositiveInt
    # The held-out scenes' plain renders the spp-equivalent reads (src/data/ladder.py); [] or null: none.
    ladder_spp: list[PositiveInt] | None = None
    seed: NonNegativeInt
    integrator: VolumeIntegrator
    max_pass_samples: PositiveInt
    grid_res: Annotated[int, Field(ge=4)]
    randomize: VolumetricRandomize
    base_scenes: VolumetricBaseScenes
    # Subsets the render stage renders (null: all), to fan it out over jobs; not part of any file's key.
    render_scenes: Annotated[list[Annotated[str, Field(min_length=1)]], Field(min_length=1)] | None = None
    render_frames: Annotated[list[NonNegativeInt], Field(min_length=1)] | None = None
    # A second, independently seeded reference of the held-out sequences (src/render/volume_dataset.py).
    second_reference: bool

    @model_validator(mode="after")
    def _reference_above_noisy(self) -> VolumetricDataset:
        from src.render.render_dataset import spp_counts

        passes(spp_counts, {"noisy_spp": self.noisy_spp, "reference_spp": self.reference_spp})
        from src.data.ladder import ladder_counts  # the ladder's own check of its counts

        passes(ladder_counts, {"ladder_spp": self.ladder_spp, "reference_spp": self.reference_spp})
        return self


class Views(Schema):
    train: PositiveInt
    val: PositiveInt
    test: PositiveInt


class NearFar(DatasetSchema):
    """Shared by the radiance-field datasets: the ray interval and the compositing colour."""

    near: PositiveFloat
    far: PositiveFloat
    background: Colour
    alpha: Literal["auto", "rgba", "rgb"]

    @model_validator(mode="after")
    def _far_beyond_near(self) -> NearFar:
        if self.far <= self.near:
            raise own_error(f"dataset.far={self.far:g}: expected more than dataset.near={self.near:g}")
        return self


class Stripes(Schema):
    count: NonNegativeInt
    width_deg: PositiveFloat
    elevation_deg: Range
    intensity: NonNegativeFloat
    colors: list[Colour] = Field(min_length=1)


class StudioSun(Schema):
    elevation_deg: float
    azimuth_deg: float
    radius_deg: PositiveFloat
    intensity: NonNegativeFloat


class StudioEnv(Schema):
    res: PositiveInt
    scale: NonNegativeFloat
    rotation_deg: float
    zenith: Colour
    horizon: Colour
    ground: Colour
    stripes: Stripes
    sun: StudioSun


class Spheres(Schema):
    rows: list[Literal["conductor", "plastic", "dielectric"]] = Field(min_length=1)
    roughness: list[PositiveFloat] = Field(min_length=1)
    sphere_radius: PositiveFloat
    spacing: PositiveFloat
    conductor: str = Field(min_length=1)
    plastic_color: Colour
    dielectric_ior: PositiveFloat
    env: StudioEnv


class DirectionalSun(Schema):
    direction: Vector3
    irradiance: NonNegativeFloat


class Busy(Schema):
    n_objects: PositiveInt
    shapes: list[Literal["sphere", "cube", "cylinder"]] = Field(min_length=1)
    size: Range
    textured_fraction: Probability
    checker_probability: Probability
    color: Range
    texture_res: PositiveInt
    noise_octaves: PositiveInt
    noise_base_cells: PositiveInt
    noise_persistence: PositiveFloat
    checker_scale: Range
    ambient: NonNegativeFloat
    sun: DirectionalSun


class Ground(Schema):
    height: float
    radius: PositiveFloat
    checks: PositiveFloat
    color0: Colour
    color1: Colour


class GlossySphere(Schema):
    material: Literal["conductor", "plastic", "dielectric"]
    roughness: PositiveFloat


class NerfTabletop(Schema):
    ground: Ground
    glossy: list[GlossySphere] = Field(min_length=1)
    sphere_radius: PositiveFloat
    ring_radius: PositiveFloat
    n_textured: NonNegativeInt
    cube_half_edge: PositiveFloat
    centre_radius: PositiveFloat
    conductor: str = Field(min_length=1)
    plastic_color: Colour
    dielectric_ior: PositiveFloat
    color: Range
    checker_probability: Probability
    checker_scale: Range
    texture_res: PositiveInt
    noise_octaves: PositiveInt
    noise_base_cells: PositiveInt
    noise_persistence: PositiveFloat
    env: StudioEnv


class SceneParams(Schema):
    """`dataset.scene_params`: each multi-view scene's materials, layout and lights."""

    spheres: Spheres
    busy: Busy
    tabletop: NerfTabletop


class NerfProceduralDataset(NearFar):
    name: Literal["nerf_procedural"]
    scenes: Names
    width: PositiveInt
    height: PositiveInt
    views: Views
    spp: PositiveInt
    max_pass_samples: PositiveInt
    max_depth: Depth
    rr_depth: NonNegativeInt
    rfilter: str
    camera_angle_x: float = Field(gt=0, lt=3.14159)
    radius: PositiveFloat
    elevation_range_deg: Range
    test_elevation_deg: float = Field(ge=-90, le=90)
    test_azimuth_start_deg: float
    bound_radius: PositiveFloat
    seed: NonNegativeInt
    scene_params: SceneParams


class BlenderDataset(NearFar):
    name: Literal["blender"]
    root: str
    scenes: Names
    downscale: PositiveInt
    max_images: PositiveInt | None

    @field_validator("root")
    @classmethod
    def _given(cls, root: str) -> str:
        if root in ("", "???"):
            raise expected("missing; expected the folder holding your Blender scenes (dataset.root=...)")
        return root


class NoisebaseDataset(SequenceOptions):
    """`dataset=noisebase` (docs/noisebase.md): which sequences, frames, window and sample counts of a
    downloaded Noisebase set nrbench reads."""

    name: Literal["noisebase"]
    experiment_suffix: str
    root: str
    format: Literal["training", "test"]
    files: Annotated[str, Field(min_length=1)]
    sequences: Annotated[list[int | str], Field(min_length=1)]  # checked below, with the format
    frames: PositiveInt
    crop: list[int] | None  # [top, left, height, width], checked below
    noisy_spp: SppList
    reference_spp: PositiveInt
    # The held-out sequences' ladder, averaged from their stored samples (src/data/noisebase.py
    # `ladder_color`); [] or null: none.
    ladder_spp: list[PositiveInt] | None = None
    rendering_height: PositiveInt
    rendering_width: PositiveInt
    second_reference: Literal[False]  # no second reference of a downloaded set

    @field_validator("root")
    @classmethod
    def _given(cls, root: str) -> str:
        if root in ("", "???"):
            raise expected("missing; expected the folder holding the Noisebase set (dataset.root=...)")
        return root

    @model_validator(mode="after")
    def _counts_and_files(self) -> NoisebaseDataset:
        from src.data.ladder import ladder_counts  # the ladder's own check of its counts
        from src.render.render_dataset import spp_counts

        passes(spp_counts, {"noisy_spp": self.noisy_spp, "reference_spp": self.reference_spp})
        passes(ladder_counts, {"ladder_spp": self.ladder_spp, "reference_spp": self.reference_spp})
        needs = ["{index"] if self.format == "training" else ["{sequence_name", "{index"]
        if not all(n in self.files for n in needs):
            raise own_error(
                f"dataset.files={self.files!r}: a {self.format}-format set's file names need "
                f"{' and '.join(n + '}' for n in needs)}"
            )
        if self.format == "training" and not all(isinstance(s, int) and s >= 0 for s in self.sequences):
            raise own_error(
                f"dataset.sequences={self.sequences}: a training-format set's sequences are indices >= 0 "
                "(scene{index:04d}.zip)"
            )
        if self.format == "test" and not all(isinstance(s, str) and s for s in self.sequences):
            raise own_error(f"dataset.sequences={self.sequences}: a test-format set's sequences are names")
        c = self.crop
        if c is not None and (len(c) != 4 or min(c[:2]) < 0 or min(c[2:]) < 1):
            raise own_error(
                f"dataset.crop={c}: expected [top, left, height, width] with top, left >= 0 and "
                "height, width >= 1, or null"
            )
        return self
