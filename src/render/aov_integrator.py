"""A path tracer that also writes the KPCN auxiliary buffers and their second moments.

One Python ``mi.SamplingIntegrator`` (vectorised by Dr.Jit in the ``llvm_ad_rgb`` / ``cuda_ad_rgb``
variants) produces, per camera sample:

* ``color``: unidirectional path tracing with next-event estimation and MIS (as Mitsuba's ``path``);
* ``diffuse`` / ``specular``: the same radiance split at the *first* bounce by BSDF lobe: light reached
  by a direction sampled from a diffuse lobe (and the diffuse-lobe share of next-event estimation at
  the first vertex) goes to ``diffuse``, everything through glossy/delta lobes to ``specular``.
  Emission seen directly by the camera goes to ``diffuse``. ``color`` is computed as their sum, so
  color == diffuse + specular per sample and therefore per pixel mean;
* ``albedo`` (diffuse reflectance at the first hit; for BSDFs without a diffuse lobe the sampled
  BSDF weight, i.e. a one-sample estimate of the directional albedo; 1 where the camera ray escapes,
  so that diffuse / (albedo + eps) stays finite on background pixels), ``normal`` (world-space shading
  normal), ``depth`` (distance to the first hit, 0 on escape) and ``visibility`` (1 when the
  next-event light sample at the first hit is unoccluded, 0 otherwise and on escape).

Mitsuba's film with a box reconstruction filter averages samples within a pixel, so the film gives
the per-pixel *mean* of every channel. To get the variance of that mean we also output each buffer's
square; ``render.moments`` turns the two means into the variance of the pixel mean.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from src.data.kpcn_buffers import KPCN_BUFFERS

# Buffers written as AOVs after the film's RGB color, in ``aov_names`` order.
AOV_BUFFERS = ("diffuse", "specular", "albedo", "normal", "depth", "visibility")
# Buffers whose per-sample square is also written (second moments for the variance of the mean).
MOMENT_BUFFERS: tuple[str, ...] = ("color", "diffuse", "specular", "albedo", "normal", "depth", "visibility")
CHANNEL_COUNT = {buf: len(KPCN_BUFFERS[buf]) for buf in ("color", *AOV_BUFFERS)}


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


def _channels(x, n: int) -> list:
    return [x[i] for i in range(3)] if n == 3 else [x]


class KPCNAovIntegrator(mi.SamplingIntegrator):
    """Path tracer with a first-bounce diffuse/specular split and KPCN feature AOVs.

    Properties: ``max_depth`` (longest path, -1 for unbounded) and ``rr_depth`` (depth from which
    Russian roulette starts), both from the dataset config.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth = props.get("max_depth", 8)
        self.rr_depth = props.get("rr_depth", 5)
        if self.max_depth < -1 or self.max_depth == 0:
            raise ValueError(f"max_depth must be -1 or >= 1, got {self.max_depth}")
        self._max_depth = 0xFFFFFFFF if self.max_depth == -1 else self.max_depth

    def aov_names(self):
        return aov_channel_names()

    def to_string(self):
        return f"KPCNAovIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"

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
            albedo = dr.select(first, dr.select(hit_first, surface_albedo, 1.0), albedo)
            normal = dr.select(hit_first, mi.Vector3f(si.sh_frame.n), normal)
            hit_depth = dr.select(hit_first, si.t, hit_depth)

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
            # Purely glossy/specular surfaces have no diffuse reflectance; their albedo is the sampled
            # BSDF weight, a one-sample estimate of the directional albedo (Fresnel tint of a mirror).
            glossy_first = hit_first & ~has_diffuse_lobe
            albedo = dr.select(glossy_first, bsdf_weight, albedo)
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

        color = L_diff + L_spec
        values = {
            "color": color,
            "diffuse": L_diff,
            "specular": L_spec,
            "albedo": albedo,
            "normal": normal,
            "depth": hit_depth,
            "visibility": visibility,
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
