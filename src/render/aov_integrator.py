"""A path tracer that also writes the KPCN auxiliary buffers and their second moments.

One Python ``mi.SamplingIntegrator`` (vectorised by Dr.Jit in the ``llvm_ad_rgb`` / ``cuda_ad_rgb``
variants) produces, per camera sample:

* ``color``: unidirectional path tracing with next-event estimation and MIS (as Mitsuba's ``path``);
* ``diffuse`` / ``specular``: the same radiance split at the *first* bounce by BSDF lobe: light reached
  by a direction sampled from a diffuse lobe (and the diffuse-lobe share of next-event estimation at
  the first vertex) goes to ``diffuse``, everything through glossy/delta lobes to ``specular``.
  Emission seen directly by the camera goes to ``diffuse``. ``color`` is computed as their sum, so
  color == diffuse + specular per sample and therefore per pixel mean;
* ``albedo``: at a first hit whose BSDF has a diffuse lobe, its diffuse reflectance
  (``eval_diffuse_reflectance``); at a purely glossy/specular first hit (conductors, dielectrics) the
  directional albedo, see below; 1 where the camera ray escapes, so that diffuse / (albedo + eps) stays
  finite on background pixels. Also ``normal`` (world-space shading normal), ``depth`` (distance to the
  first hit, 0 on escape) and ``visibility`` (1 when the next-event light sample at the first hit is
  unoccluded, 0 otherwise and on escape);
* ``position`` and ``secondary_albedo``, the two features of the genetic-programming filters
  (Davletaliyev 2016, Sec. 3.2.1.2, "Vector Variables") that KPCN lacks: ``position`` is the world
  position of the first hit (0 where the camera ray escapes); ``secondary_albedo`` the albedo at the hit
  of the *reflected* ray, the perfect-mirror reflection of the camera ray about the first hit's shading
  normal (one extra ray per camera sample, traced after the path). The thesis defines it as "a value of
  the texture at the intersection point of the reflected ray" ("valuable information for the glossy
  surfaces ... because it is possible to see the reflection of other objects on it"); its OptiX renderer
  takes it "at the intersection of second bounce" (Sec. 3.3.2), and it does not say what an escaping ray
  gives. We use the mirror direction for every surface (deterministic given the first hit, so the feature
  is as smooth as the normal, not a random bounce) and 0 where either ray escapes (no texture seen: unlike
  ``albedo`` it is never a divisor, so it needs no 1). The albedo at the secondary hit is computed as the
  first hit's (diffuse reflectance, or the K-sample directional albedo of a glossy/specular surface).
  Depth's variance: the thesis drops it because depth is a function of the world position (Sec.
  3.2.1.2, "Scalar Variables"); we keep our ``depthVariance`` (KPCN's data have it).

Albedo of glossy and glass surfaces. The albedo is a denoising guide: KPCN (Bako et al. 2017) divides
diffuse by it and feeds it, its variance and its gradients to the network, and the cross-bilateral
filter and OIDN use it as a guide; noise in it is copied into all of these. Mitsuba's BSDF interface has
no albedo query for conductors and dielectrics (only ``eval_diffuse_reflectance``, for diffuse lobes),
so at such a first hit we estimate the directional albedo rho(wi) = integral of f(wi, wo) |cos theta_o|
dwo as the mean of ``albedo_samples`` (K, ``dataset.integrator.albedo_samples``) BSDF sample weights at
that hit, drawn separately from the path's own sample. The K sample points are a 3D Hammersley set (k/K,
phi_2(k), phi_3(k)) shifted by one uniform random offset per camera sample (Cranley-Patterson rotation):
each point is uniform, so the mean is unbiased, and the set is stratified over the lobe choice and the
microfacet normal, so its variance typically falls faster than 1/K (tests/test_render.py: a rough copper
sphere's albedo variance is ~90x lower at K = 16 than at K = 1). The weights are taken in importance
(adjoint) transport mode, i.e. without the eta^2 radiance scaling of refracted light: the albedo is the
scattered fraction of energy, reflectance + transmittance, in [0, 1]. A smooth conductor gets its
Fresnel reflectance at the viewing angle (deterministic, as before), a smooth dielectric gets R + T = 1
for every sample (radiance mode would give R + T / eta^2, e.g. ~0.47 for glass, a random 1 or 1 / eta^2
per sample, and values up to eta^2 > 1 seen from inside). This follows OIDN's documented convention
(RenderKit/oidn doc/api.md, RT filter, "Albedos": the albedo of a dielectric should be 1, or for a
perfect specular one the Fresnel blend of the reflected and transmitted albedos; a metal's the
reflectivity at normal incidence or the average reflectivity, or 1; always in [0, 1]). BSDFs with a
diffuse lobe (diffuse, plastic) keep their diffuse reflectance. The estimate costs K BSDF samples, no
rays, per glossy first hit; K = 1 is one independent sample, as noisy as the former reuse of the path's
BSDF sample but in importance mode.

Mitsuba's film with a box reconstruction filter averages samples within a pixel, so the film gives
the per-pixel *mean* of every channel. To get the variance of that mean we also output each buffer's
square; ``render.moments`` turns the two means into the variance of the pixel mean.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from src.data.kpcn_buffers import KPCN_BUFFERS

# Buffers written as AOVs after the film's RGB color, in ``aov_names`` order.
AOV_BUFFERS = (
    "diffuse",
    "specular",
    "albedo",
    "normal",
    "depth",
    "visibility",
    "position",
    "secondary_albedo",
)
# Buffers whose per-sample square is also written (second moments for the variance of the mean).
MOMENT_BUFFERS: tuple[str, ...] = ("color", *AOV_BUFFERS)
CHANNEL_COUNT = {buf: len(KPCN_BUFFERS[buf]) for buf in ("color", *AOV_BUFFERS)}
#: BSDF samples per glossy/specular first hit for the albedo when the config gives none.
DEFAULT_ALBEDO_SAMPLES = 16
#: The largest float32 below 1.
ONE_MINUS_EPSILON = float(np.nextafter(np.float32(1.0), np.float32(0.0)))


def aov_channel_names() -> list[str]:
    """AOV channel names in the order ``sample`` returns them: buffers first, then squares."""
    names = []
    for buf in AOV_BUFFERS:
        names += [f"{buf}.{i}" for i in range(CHANNEL_COUNT[buf])]
    for buf in MOMENT_BUFFERS:
        names += [f"{buf}_sq.{i}" for i in range(CHANNEL_COUNT[buf])]
    return names


def _mis_weight(pdf_a, pdf_b):
    """Power heuristic (beta = 2), as in Mitsuba's path integrator."""
    a2 = dr.square(pdf_a)
    return dr.detach(dr.select(pdf_a > 0, a2 / dr.fma(pdf_b, pdf_b, a2), 0))


def radical_inverse(k: int, base: int) -> float:
    """Van der Corput radical inverse phi_base(k): k's digits in ``base`` mirrored about the point."""
    inv, scale = 0.0, 1.0 / base
    while k:
        k, digit = divmod(k, base)
        inv += digit * scale
        scale /= base
    return inv


def hammersley_3d(n: int) -> np.ndarray:
    """(n, 3) Hammersley points (k/n, phi_2(k), phi_3(k)), k = 0..n-1, in [0, 1)^3."""
    return np.array([[k / n, radical_inverse(k, 2), radical_inverse(k, 3)] for k in range(n)], np.float32)


def _wrap(x):
    """x mod 1 for x in [0, 2), kept below 1 (a BSDF sample must lie in [0, 1))."""
    return dr.minimum(x - dr.floor(x), ONE_MINUS_EPSILON)


def _channels(x, n: int) -> list:
    return [x[i] for i in range(3)] if n == 3 else [x]


class KPCNAovIntegrator(mi.SamplingIntegrator):
    """Path tracer with a first-bounce diffuse/specular split and KPCN feature AOVs.

    Properties: ``max_depth`` (longest path, -1 for unbounded), ``rr_depth`` (depth from which
    Russian roulette starts) and ``albedo_samples`` (BSDF samples per camera sample for the albedo of a
    glossy/specular first hit), all from ``dataset.integrator``.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth = props.get("max_depth", 8)
        self.rr_depth = props.get("rr_depth", 5)
        self.albedo_samples = props.get("albedo_samples", DEFAULT_ALBEDO_SAMPLES)
        if self.max_depth < -1 or self.max_depth == 0:
            raise ValueError(f"max_depth must be -1 or >= 1, got {self.max_depth}")
        if self.albedo_samples < 1:
            raise ValueError(f"albedo_samples must be >= 1, got {self.albedo_samples}")
        self._max_depth = 0xFFFFFFFF if self.max_depth == -1 else self.max_depth
        points = hammersley_3d(self.albedo_samples)
        self._albedo_points = [mi.Float(points[:, d]) for d in range(3)]

    def aov_names(self):
        return aov_channel_names()

    def to_string(self):
        return (
            f"KPCNAovIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
            f"albedo_samples={self.albedo_samples}]"
        )

    @dr.syntax
    def directional_albedo(self, bsdf, si, sampler, active):
        """Mean importance-mode weight of ``albedo_samples`` BSDF samples at ``si``: an unbiased,
        stratified estimate of the directional albedo (reflectance + transmittance) for ``si.wi``."""
        ctx = mi.BSDFContext(mi.TransportMode.Importance)
        shift1 = sampler.next_1d(active)
        shift2 = sampler.next_2d(active)
        total = mi.Spectrum(0.0)
        k = mi.UInt32(0)
        run = mi.Bool(active)
        while dr.hint(run, label="KPCN albedo samples"):
            u1, u2x, u2y = (dr.gather(mi.Float, pts, k, run) for pts in self._albedo_points)
            sample1 = _wrap(shift1 + u1)
            sample2 = mi.Point2f(_wrap(shift2.x + u2x), _wrap(shift2.y + u2y))
            _, weight = bsdf.sample(ctx, si, sample1, sample2, run)
            total += weight
            k += 1
            run &= k < self.albedo_samples
        return total / self.albedo_samples

    def surface_albedo(self, si, ray, sampler, active):
        """The albedo guide at ``si`` (hit by ``ray``): diffuse reflectance where the BSDF has a diffuse lobe,
        else the `directional_albedo` estimate; 0 where ``active`` is false."""
        bsdf = si.bsdf(ray)
        has_diffuse_lobe = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse)
        diffuse = bsdf.eval_diffuse_reflectance(si, active & has_diffuse_lobe)
        glossy = self.directional_albedo(bsdf, si, sampler, active & ~has_diffuse_lobe)
        return dr.select(active, dr.select(has_diffuse_lobe, diffuse, glossy), 0.0)

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        bsdf_ctx = mi.BSDFContext()
        diffuse_ctx = mi.BSDFContext()
        diffuse_ctx.type_mask = mi.BSDFFlags.Diffuse

        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        L_diff = mi.Spectrum(0.0)
        L_spec = mi.Spectrum(0.0)
        beta = mi.Spectrum(1.0)
        depth = mi.UInt32(0)
        on_diffuse_path = mi.Bool(True)  # lobe sampled at the first vertex
        eta = mi.Float(1.0)
        prev_si = dr.zeros(mi.SurfaceInteraction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)

        # First-hit features.
        albedo = mi.Spectrum(1.0)
        normal = mi.Vector3f(0.0)
        hit_depth = mi.Float(0.0)
        visibility = mi.Float(0.0)
        position = mi.Point3f(0.0)
        mirror_o = mi.Point3f(0.0)  # the mirror-reflected ray at the first hit (secondary albedo)
        mirror_d = mi.Vector3f(0.0)
        mirror_valid = mi.Bool(False)

        while dr.hint(active, max_iterations=-1, label="KPCN path"):
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0))
            first = depth == 0

            # Emission hit by this ray (camera ray, or the BSDF-sampled continuation), MIS-weighted.
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = mi.Float(0.0)
            if ~prev_bsdf_delta:
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
            emitted = beta * _mis_weight(prev_bsdf_pdf, em_pdf) * ds.emitter.eval(si, prev_bsdf_pdf > 0)
            to_diffuse = first | on_diffuse_path
            L_diff += dr.select(to_diffuse, emitted, 0.0)
            L_spec += dr.select(to_diffuse, 0.0, emitted)

            bsdf = si.bsdf(ray)
            hit_first = first & si.is_valid()
            has_diffuse_lobe = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse)
            surface_albedo = bsdf.eval_diffuse_reflectance(si, hit_first & has_diffuse_lobe)
            # Purely glossy/specular surfaces have no diffuse reflectance: estimate their directional
            # albedo from several BSDF samples (see the module docstring).
            glossy_first = hit_first & ~has_diffuse_lobe
            glossy_albedo = self.directional_albedo(bsdf, si, sampler, glossy_first)
            surface_albedo = dr.select(has_diffuse_lobe, surface_albedo, glossy_albedo)
            albedo = dr.select(first, dr.select(hit_first, surface_albedo, 1.0), albedo)
            normal = dr.select(hit_first, mi.Vector3f(si.sh_frame.n), normal)
            hit_depth = dr.select(hit_first, si.t, hit_depth)
            position = dr.select(hit_first, si.p, position)
            mirror = si.spawn_ray(si.to_world(mi.reflect(si.wi)))
            mirror_o = dr.select(hit_first, mirror.o, mirror_o)
            mirror_d = dr.select(hit_first, mirror.d, mirror_d)
            mirror_valid |= hit_first

            active_next = (depth + 1 < self._max_depth) & si.is_valid()

            # Next-event estimation; visibility tested separately so the first vertex can record it.
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
            active_em &= ds.pdf != 0.0
            unoccluded = active_em & ~scene.ray_test(si.spawn_ray_to(ds.p), active_em)
            visibility = dr.select(first, dr.select(unoccluded, 1.0, 0.0), visibility)
            wo = si.to_local(ds.d)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, unoccluded)
            mis_em = dr.select(ds.delta, 1.0, _mis_weight(ds.pdf, bsdf_pdf))
            nee = dr.select(unoccluded, beta * mis_em * em_weight, 0.0)
            # At the first vertex split NEE by lobe: the diffuse lobes' share of the BSDF value.
            diffuse_val = dr.select(first, bsdf.eval(diffuse_ctx, si, wo, unoccluded), bsdf_val)
            diffuse_val = dr.select(first | on_diffuse_path, diffuse_val, 0.0)
            L_diff += nee * diffuse_val
            L_spec += nee * (bsdf_val - diffuse_val)

            # BSDF sampling continues the path.
            bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            sampled_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
            on_diffuse_path = dr.select(first, sampled_diffuse, on_diffuse_path)
            beta *= bsdf_weight
            eta *= bs.eta
            ray = si.spawn_ray(si.to_world(bs.wo))
            prev_si = dr.detach(si, True)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            depth[si.is_valid()] += 1

            # Russian roulette on the throughput, as in Mitsuba's path integrator.
            beta_max = dr.max(beta)
            rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
            rr_active = depth >= self.rr_depth
            beta[rr_active] *= dr.rcp(rr_prob)
            rr_continue = sampler.next_1d() < rr_prob
            active = active_next & (~rr_active | rr_continue) & (beta_max != 0.0) & (bs.pdf > 0)

        # Secondary albedo: the albedo where the mirror ray hits; 0 where it or the camera ray escapes.
        mirror_ray = mi.Ray3f(mirror_o, mirror_d)
        si2 = scene.ray_intersect(mirror_ray, ray_flags=mi.RayFlags.All, coherent=False, active=mirror_valid)
        secondary_albedo = self.surface_albedo(si2, mirror_ray, sampler, mirror_valid & si2.is_valid())

        color = L_diff + L_spec
        values = {
            "color": color,
            "diffuse": L_diff,
            "specular": L_spec,
            "albedo": albedo,
            "normal": normal,
            "depth": hit_depth,
            "visibility": visibility,
            "position": position,
            "secondary_albedo": secondary_albedo,
        }
        aovs = []
        for buf in AOV_BUFFERS:
            aovs += _channels(values[buf], CHANNEL_COUNT[buf])
        for buf in MOMENT_BUFFERS:
            aovs += [dr.square(c) for c in _channels(values[buf], CHANNEL_COUNT[buf])]
        return color, mi.Bool(True), aovs


def register() -> None:
    """Make the integrator available to scene dicts as ``{"type": "kpcn_aov"}`` (idempotent)."""
    mi.register_integrator("kpcn_aov", lambda props: KPCNAovIntegrator(props))
