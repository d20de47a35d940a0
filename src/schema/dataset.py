"""Schemas of `dataset:`, one per shipped dataset (chosen by `dataset.name`; a user's own dataset config
is checked where it is read). The scene families' nested layout blocks (`base_scenes`, `scene_params`)
are checked by their builders."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from src.schema.types import (
    Colour,
    NonNegativeInt,
    Open,
    PositiveFloat,
    PositiveInt,
    Probability,
    Range,
    Schema,
    expected,
    own_error,
)

SppList = Annotated[list[PositiveInt], Field(min_length=1)]
Names = Annotated[list[Annotated[str, Field(min_length=1)]], Field(min_length=1)]
Depth = Annotated[int, Field(ge=-1)]  # -1: unbounded


class Integrator(Schema):
    max_depth: Depth
    rr_depth: NonNegativeInt


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


class ProceduralDataset(Schema):
    name: Literal["procedural"]
    bases: list[Literal["cornell", "tabletop", "outdoor"]] = Field(min_length=1)
    scenes_per_base: PositiveInt
    scene_files: list[str]
    width: PositiveInt
    height: PositiveInt
    noisy_spp: SppList
    reference_spp: PositiveInt
    seed: NonNegativeInt
    integrator: Integrator
    max_pass_samples: PositiveInt
    randomize: Randomize
    base_scenes: Open

    @model_validator(mode="after")
    def _reference_above_noisy(self) -> ProceduralDataset:
        if self.reference_spp <= max(self.noisy_spp):
            raise own_error(
                f"dataset.reference_spp={self.reference_spp}: expected more than the largest noisy_spp "
                f"({max(self.noisy_spp)}); the reference is the highest sample count of a scene"
            )
        return self


class Views(Schema):
    train: PositiveInt
    val: PositiveInt
    test: PositiveInt


class NearFar(Schema):
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
    scene_params: Open


class BlenderDataset(NearFar):
    name: Literal["blender"]
    root: str
    scenes: Names
    downscale: PositiveInt
    max_images: PositiveInt | None
    # Set by the nerf task's profiles for the procedural scenes (conf/task_profile/nerf_*.yaml), which
    # apply whatever the dataset; a user's scenes come at their own size, so these are not read.
    width: PositiveInt | None = None
    height: PositiveInt | None = None
    views: Views | None = None
    spp: PositiveInt | None = None
    scene_params: Open | None = None

    @field_validator("root")
    @classmethod
    def _given(cls, root: str) -> str:
        if root in ("", "???"):
            raise expected("missing; expected the folder holding your Blender scenes (dataset.root=...)")
        return root


#: The schema of each shipped dataset, by `dataset.name`.
DATASET_SCHEMAS = {
    "procedural": ProceduralDataset,
    "nerf_procedural": NerfProceduralDataset,
    "blender": BlenderDataset,
}
