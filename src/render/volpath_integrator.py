"""A volumetric path tracer that writes candidate volumetric denoising features (issue 16).

``VolumetricAovIntegrator`` (registered as ``{"type": "nrbench_volpath"}``) is a Python
``mi.SamplingIntegrator``, vectorised by Dr.Jit symbolic loops like ``src.render.aov_integrator``. Its
light transport follows Mitsuba 3's C++ ``volpath``:

* free-flight sampling by delta tracking against the medium majorant (``Medium.sample_interaction``),
  a colour channel picked per camera sample for the distance distribution and the other channels
  re-weighted by transmittance / pdf when the extinction is spectral; a tentative collision is real
  with probability sigma_t / majorant (of that channel), null otherwise;
* next-event estimation at surfaces and at real medium collisions, its transmittance estimated by
  ratio tracking (product of sigma_n / majorant over tentative collisions) through media and
  ``eval_null_transmission`` through null-BSDF boundaries;
* MIS (power heuristic) between emitter sampling and BSDF / phase-function sampling;
* null-BSDF medium boundaries: the current medium is switched with ``si.target_medium`` when a path or
  a shadow ray crosses a medium transition; the sensor's medium is the initial medium;
* Russian roulette and ``max_depth`` counted as in ``volpath`` (a real medium collision and a non-null
  surface bounce each add one to the depth).

The one structural difference: at a real medium collision and at a surface vertex the emitter sample is
drawn by one shared shadow-ray loop (a lane is at one or the other in a loop iteration), so the random
numbers differ from ``volpath``'s; the estimator is the same, so the two agree in expectation
(tests/test_volpath.py checks it statistically).

Outputs. The film's RGB is ``color``; the AOVs follow in ``VOLUME_BUFFERS`` order and then the per-sample
square of every buffer in ``MOMENT_BUFFERS`` (``color`` first), so ``src.render.moments`` turns the
film's means into the variance of each pixel mean. That layout, and rendering a scene into buffers and
variances with this integrator (``render_volume_buffers``), are ``src.render.volume_film``'s.

Radiance split (per sample, exact: ``color = surface + volume`` and ``volume = volume_single +
volume_multi`` are computed as those sums). A *real scattering vertex* is a real medium collision or a
surface hit whose sampled/evaluated BSDF lobe is not null (null-BSDF boundaries and null collisions are
not vertices). Every radiance contribution (an emitter hit, or a next-event estimate at a vertex) is
classified by the vertices of the path that carries it:

* ``surface``: the path's first real scattering vertex is a surface, or it has none (emitters and the
  environment seen directly by the camera, attenuated by any media in between);
* ``volume_single``: the first vertex is a medium collision and it is the only vertex of the path,
  i.e. light scattered exactly once, in a medium, on its way to the camera (next-event estimation at
  the first collision plus emitters hit by the phase-sampled direction from it): the single-scatter
  (first-scatter) radiance;
* ``volume_multi``: the first vertex is a medium collision and the path has two or more vertices (more
  medium collisions and/or surface bounces after it): the multiple-scatter radiance.
* ``volume = volume_single + volume_multi``.

Surface features, at the first real scattering *surface* along the camera ray (the camera ray followed
through null-BSDF boundaries and media without scattering, so they do not depend on whether this sample
scattered in a medium first): ``albedo``, ``normal``, ``depth``, ``visibility`` with the definitions of
``src.render.aov_integrator`` (albedo 1 and the others 0 on escape; the albedo of a glossy/specular hit
is its ``albedo_samples``-sample directional albedo, computed by that module's estimator); ``visibility``
is geometric here: 1 when the shadow ray to the emitter sample reaches it crossing only null-BSDF
surfaces (media do not occlude).

Candidate volumetric features. Zhang et al. 2022 ("Automatic Feature Selection for Denoising
Volumetric Renderings", Computer Graphics Forum 41(4), EGSR) denoise the surface and the volume
contributions of the colour separately and select the volume denoiser's inputs from a pool of candidate
volumetric features; the Pixar/Disney 2023 talk "Denoising Production Volumetric Rendering" reports
that decomposition in production. The features below are our candidate pool in that spirit, each one
an AOV with its square; we do not claim each equals a feature of their pool:

* ``transmittance`` (RGB): transmittance of the camera ray from the camera to the first real scattering
  surface, or to infinity when it escapes: exp(-``optical_thickness``) times the null transmission of
  the boundaries crossed. Exact (closed form) in homogeneous media; see ``optical_thickness`` for
  heterogeneous ones.
* ``optical_thickness`` (RGB): tau = integral of sigma_t along that same camera segment (summed over
  every medium it crosses; capped at ``MAX_OPTICAL_THICKNESS`` = 1000, reached e.g. when the ray escapes
  in an unbounded homogeneous medium). Each medium segment runs between the boundary points, not
  from the offset origins of the spawned rays. Homogeneous
  media: sigma_t * length, exact. Heterogeneous media: stratified (jittered) ray-marched quadrature,
  ``volume_steps`` equal steps over the segment's part inside the medium's bounding box, one uniform
  random point in each step. Each point is uniform in its step, so the sum is an unbiased estimate of
  tau, and for a smooth density its standard deviation falls as steps^-1.5 (independent jitter per
  step; one offset shared by all steps would only give steps^-1 on a monotone density); its noise does
  not depend on the majorant, unlike the ratio- or track-length estimators, whose tau estimate is a
  Poisson collision count, noisy in dense media; the cost is a fixed ``volume_steps`` density lookups
  per crossed medium. We use exp(-tau_hat) as the transmittance: low-noise and consistent, but biased
  up by about T * Var(tau_hat) / 2 in heterogeneous media (Jensen; estimated ~0.3 % at 8 steps for a density
  ramp of optical thickness 2.4 in tests/test_volpath.py); ratio tracking would be unbiased but noisy.
* ``scatter_depth`` (1): distance from the camera to the path's first real scattering vertex when that
  vertex is a medium collision (a ``volume`` path), else 0. Since it lies on the camera ray, it is the
  collision's depth along the ray.
* ``scatter_position`` (3): world position of that collision, else 0.
* ``scatter_media_distance`` (1): length of the camera ray inside media (between null boundaries, where
  the current medium is not null) up to that collision, else 0; differs from ``scatter_depth`` by the
  empty space in front of the medium.
* ``sigma_t``, ``sigma_s`` (RGB): extinction and scattering coefficients at that collision (the
  medium's ``scale`` included), else 0; ``scatter_albedo`` (RGB): sigma_s / sigma_t there, else 0.
* ``scattered`` (1): 1 when the path had at least one real medium collision anywhere (its pixel mean is
  the fraction of such paths), else 0.
* ``volume_events`` (1): the number of real medium collisions on the path (its mean: the average count).
* ``volume_single`` / ``volume_multi``: the single- and multiple-scatter radiance above.
* ``position`` (3): world position of whichever comes first along the camera ray, the first real
  scattering surface or this sample's first medium collision; 0 when the ray escapes without either.
  For motion vectors (reprojecting this point with the previous frame's camera).

Parameters: ``max_depth`` (-1: unbounded; default -1 as ``volpath``), ``rr_depth`` (default 5),
``albedo_samples`` (as ``aov_integrator``), ``volume_steps`` (quadrature steps per heterogeneous medium
crossed by the camera ray, default 16) and ``features`` (default true; false: colour only, no AOVs and no
feature work, for timing the bare path tracer).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from src.render.aov_integrator import DEFAULT_ALBEDO_SAMPLES, KPCNAovIntegrator, hammersley_3d
from src.render.volume_film import film_aovs, volume_channel_names

#: Registered plugin name.
PLUGIN_NAME = "nrbench_volpath"
#: Default quadrature steps per heterogeneous medium on the camera segment.
DEFAULT_VOLUME_STEPS = 16
#: Cap of the optical-thickness feature (an unbounded medium gives inf; exp(-1000) is 0 in float32
#: anyway, and a finite value keeps its square and variance finite).
MAX_OPTICAL_THICKNESS = 1000.0
#: Most null-BSDF boundaries the feature pass follows along one camera ray / shadow ray.
MAX_CROSSINGS = 16
#: BSDF lobes that scatter (every lobe but Null).
_SCATTERING_LOBES = int(mi.BSDFFlags.All) & ~int(mi.BSDFFlags.Null)


def _scatters(bsdf):
    """Per lane: the BSDF has a lobe that scatters (not only a null one)."""
    return (bsdf.flags() & _SCATTERING_LOBES) != 0


def _split_contribution(contrib, first_is_volume, single, surface, volume_single, volume_multi):
    """Add one radiance contribution to the buffer its path belongs to (module docstring): surface
    unless the first vertex is a medium collision, then single- or multiple-scatter volume."""
    return (
        surface + dr.select(first_is_volume, 0.0, contrib),
        volume_single + dr.select(single, contrib, 0.0),
        volume_multi + dr.select(first_is_volume & ~single, contrib, 0.0),
    )


def _mis_weight(pdf_a, pdf_b):
    """Power heuristic, 0 where it is not finite (as Mitsuba's ``mis_weight``)."""
    a2 = dr.square(pdf_a)
    w = a2 / (a2 + dr.square(pdf_b))
    return dr.select(dr.isfinite(w), w, 0.0)


def _index_spectrum(spec, idx):
    """Channel ``idx`` of an RGB spectrum, per lane."""
    m = mi.Float(spec[0])
    m[idx == 1] = spec[1]
    m[idx == 2] = spec[2]
    return m


class VolumetricAovIntegrator(mi.SamplingIntegrator):
    """Volumetric path tracer (as Mitsuba's ``volpath``) with surface/volume radiance split and
    volumetric feature AOVs; see the module docstring."""

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.max_depth = props.get("max_depth", -1)
        self.rr_depth = props.get("rr_depth", 5)
        self.albedo_samples = props.get("albedo_samples", DEFAULT_ALBEDO_SAMPLES)
        self.volume_steps = props.get("volume_steps", DEFAULT_VOLUME_STEPS)
        self.features = props.get("features", True)
        if self.max_depth < -1 or self.max_depth == 0:
            raise ValueError(f"max_depth must be -1 or >= 1, got {self.max_depth}")
        if self.albedo_samples < 1 or self.volume_steps < 1:
            raise ValueError(
                f"albedo_samples and volume_steps must be >= 1, got {self.albedo_samples}, "
                f"{self.volume_steps}"
            )
        self._max_depth = 0xFFFFFFFF if self.max_depth == -1 else self.max_depth
        points = hammersley_3d(self.albedo_samples)
        # Read by KPCNAovIntegrator.directional_albedo, which we call with this object as ``self``.
        self._albedo_points = [mi.Float(points[:, d]) for d in range(3)]

    def aov_names(self):
        return volume_channel_names() if self.features else []

    def to_string(self):
        return (
            f"VolumetricAovIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
            f"albedo_samples={self.albedo_samples}, volume_steps={self.volume_steps}, "
            f"features={self.features}]"
        )

    # ------------------------------------------------------------------ camera-segment features

    @dr.syntax
    def optical_depth(self, medium, ray, t_end, sampler, active):
        """Integral of sigma_t along ``ray`` over [0, t_end] inside ``medium`` (see the module
        docstring: exact for homogeneous media, jittered quadrature for heterogeneous ones)."""
        active = mi.Bool(active)
        hit, mint, maxt = medium.intersect_aabb(ray)
        a = dr.maximum(mint, 0.0)
        b = dr.minimum(maxt, t_end)
        length = dr.maximum(b - a, 0.0)
        active &= hit & (b > a)
        homogeneous = active & medium.is_homogeneous()
        mei = dr.zeros(mi.MediumInteraction3f)
        mei.p = ray(a)
        _, _, sigma_t = medium.get_scattering_coefficients(mei, homogeneous)
        tau = dr.select(homogeneous & (sigma_t > 0.0), sigma_t * length, 0.0)

        run = active & ~homogeneous
        h = length / self.volume_steps
        total = mi.Spectrum(0.0)
        k = mi.UInt32(0)
        while dr.hint(run, label="nrbench_volpath optical depth"):
            mei.p = ray(a + (mi.Float(k) + sampler.next_1d(run)) * h)
            _, _, sigma_t_k = medium.get_scattering_coefficients(mei, run)
            total += sigma_t_k
            k += 1
            run &= k < self.volume_steps
        return dr.select(active & ~homogeneous, total * h, tau)

    @dr.syntax
    def camera_segment(self, scene, sampler, ray, medium, active):
        """Follow the camera ray through null-BSDF boundaries to its first scattering surface.

        Returns (that surface interaction, invalid on escape; optical thickness; null transmission)."""
        ray = mi.Ray3f(ray)
        medium = mi.MediumPtr(medium)
        tau = mi.Spectrum(0.0)
        null_tr = mi.Spectrum(1.0)
        first_si = dr.zeros(mi.SurfaceInteraction3f)
        # Where the current medium segment starts (the camera, then the last boundary crossed): the
        # segment is measured from there, not from the spawned ray's offset origin.
        origin = mi.Point3f(ray.o)
        crossings = mi.UInt32(0)
        run = mi.Bool(active)
        while dr.hint(run, label="nrbench_volpath camera segment"):
            si = scene.ray_intersect(ray, mi.RayFlags.All, crossings == 0, run)
            in_medium = run & (medium != None)  # noqa: E711 (a Dr.Jit pointer array comparison)
            t_end = dr.select(si.is_valid(), dr.dot(si.p - origin, ray.d), dr.inf)
            segment = mi.Ray3f(origin, ray.d)
            tau += self.optical_depth(medium, segment, t_end, sampler, in_medium)
            bsdf = si.bsdf(ray)
            passes = run & si.is_valid() & ~_scatters(bsdf)
            first_si[run & ~passes] = si
            null_tr[passes] *= bsdf.eval_null_transmission(si, passes)
            medium[passes & si.is_medium_transition()] = si.target_medium(ray.d)
            ray[passes] = si.spawn_ray(ray.d)
            origin[passes] = si.p
            crossings += 1
            run = passes & (crossings < MAX_CROSSINGS)
        tau = dr.minimum(tau, MAX_OPTICAL_THICKNESS)
        return first_si, tau, null_tr

    @dr.syntax
    def geometric_visibility(self, scene, si, sampler, active):
        """1 where a shadow ray from ``si`` to an emitter sample crosses only null-BSDF surfaces."""
        active = mi.Bool(active)
        ds, _ = scene.sample_emitter_direction(si, sampler.next_2d(active), False, active)
        active &= ds.pdf != 0.0
        ray = si.spawn_ray_to(ds.p)
        visible = mi.Bool(active)
        crossings = mi.UInt32(0)
        run = mi.Bool(active)
        while dr.hint(run, label="nrbench_volpath visibility"):
            hit = scene.ray_intersect(ray, mi.RayFlags.All, False, run)
            bsdf = hit.bsdf(ray)
            blocked = run & hit.is_valid() & _scatters(bsdf)
            visible &= ~blocked
            passes = run & hit.is_valid() & ~blocked
            remaining = ray.maxt - hit.t
            ray[passes] = hit.spawn_ray(ray.d)
            ray.maxt[passes] = remaining
            crossings += 1
            run = passes & (crossings < MAX_CROSSINGS)
        return dr.select(visible, 1.0, 0.0)

    # ------------------------------------------------------------------ next-event estimation

    @dr.syntax
    def sample_emitter(self, scene, sampler, ref, si, on_surface, medium, channel, active):
        """Emitter sample from ``ref`` (a medium collision or the surface ``si`` where ``on_surface``)
        with its ratio-tracking transmittance: (emitter weight * transmittance, direction sample)."""
        active = mi.Bool(active)
        ds, emitter_val = scene.sample_emitter_direction(ref, sampler.next_2d(active), False, active)
        emitter_val[ds.pdf == 0.0] = 0.0
        active &= ds.pdf != 0.0

        medium = dr.select(active, medium, dr.zeros(mi.MediumPtr))
        medium[on_surface & active & si.is_medium_transition()] = si.target_medium(ds.d)
        ray = ref.spawn_ray_to(ds.p)
        max_dist = mi.Float(ray.maxt)
        total_dist = mi.Float(0.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        transmittance = mi.Spectrum(1.0)
        while dr.hint(active, label="nrbench_volpath shadow ray"):
            remaining = max_dist - total_dist
            ray.maxt = remaining
            active &= remaining > 0.0
            active_medium = active & (medium != None)  # noqa: E711
            active_surface = active & ~active_medium

            mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel, active_medium)
            ray.maxt[active_medium & medium.is_homogeneous() & mei.is_valid()] = dr.minimum(mei.t, remaining)
            intersect = needs_intersection & active_medium
            si[intersect] = scene.ray_intersect(ray, intersect)
            mei.t[active_medium & (si.t < mei.t)] = dr.inf
            needs_intersection &= ~active_medium

            is_spectral = active_medium & medium.has_spectral_extinction()
            not_spectral = active_medium & ~is_spectral
            t = dr.minimum(remaining, dr.minimum(mei.t, si.t)) - mei.mint
            tr = dr.exp(-t * mei.combined_extinction)
            ff_pdf = dr.select((si.t < mei.t) | (mei.t > remaining), tr, tr * mei.combined_extinction)
            tr_pdf = _index_spectrum(ff_pdf, channel)
            transmittance[is_spectral] *= dr.select(tr_pdf > 0.0, tr / tr_pdf, 0.0)

            # A tentative collision beyond the emitter: the segment is done.
            total_dist[active_medium & (mei.t > remaining) & mei.is_valid()] = ds.dist
            mei.t[active_medium & (mei.t > remaining)] = dr.inf
            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            total_dist[active_medium] += mei.t
            ray.o[active_medium] = mei.p
            si.t[active_medium] = si.t - mei.t
            transmittance[is_spectral & active_medium] *= mei.sigma_n
            transmittance[not_spectral & active_medium] *= mei.sigma_n / mei.combined_extinction

            intersect = active_surface & needs_intersection
            si[intersect] = scene.ray_intersect(ray, intersect)
            needs_intersection &= ~intersect
            active_surface |= escaped_medium
            total_dist[active_surface] += si.t
            active_surface &= si.is_valid() & active & ~active_medium
            bsdf = si.bsdf(ray)
            transmittance[active_surface] *= bsdf.eval_null_transmission(si, active_surface)

            ray[active_surface] = si.spawn_ray(ray.d)
            ray.maxt = remaining
            needs_intersection |= active_surface
            active &= (active_medium | active_surface) & dr.any(transmittance != 0.0)
            medium[active_surface & si.is_medium_transition()] = si.target_medium(ray.d)
        return emitter_val * transmittance, ds

    # ------------------------------------------------------------------ the path

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        features = self.features
        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        medium = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        camera_o = mi.Point3f(ray.o)

        if dr.hint(features, mode="scalar"):
            first_si, tau, null_tr = self.camera_segment(scene, sampler, ray, medium, active)
            hit = active & first_si.is_valid()
            first_bsdf = first_si.bsdf(ray)
            has_diffuse = mi.has_flag(first_bsdf.flags(), mi.BSDFFlags.Diffuse)
            diffuse_albedo = first_bsdf.eval_diffuse_reflectance(first_si, hit & has_diffuse)
            glossy_albedo = KPCNAovIntegrator.directional_albedo(
                self, first_bsdf, first_si, sampler, hit & ~has_diffuse
            )
            albedo = dr.select(hit, dr.select(has_diffuse, diffuse_albedo, glossy_albedo), 1.0)
            normal = dr.select(hit, mi.Vector3f(first_si.sh_frame.n), 0.0)
            surface_depth = dr.select(hit, dr.norm(first_si.p - camera_o), 0.0)
            smooth = hit & mi.has_flag(first_bsdf.flags(), mi.BSDFFlags.Smooth)
            visibility = self.geometric_visibility(scene, first_si, sampler, smooth)
            transmittance = null_tr * dr.exp(-tau)

        # Path state, as in Mitsuba's volpath.
        valid_ray = mi.Bool(scene.environment() is not None)
        eta = mi.Float(1.0)
        throughput = mi.Spectrum(1.0)
        L_surface = mi.Spectrum(0.0)
        L_single = mi.Spectrum(0.0)
        L_multi = mi.Spectrum(0.0)
        specular_chain = mi.Bool(active)
        depth = mi.UInt32(0)
        n_channels = dr.size_v(mi.Spectrum)
        channel = mi.UInt32(dr.minimum(n_channels * sampler.next_1d(active), n_channels - 1))
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        last_scatter_event = dr.zeros(mi.Interaction3f)
        last_scatter_direction_pdf = mi.Float(1.0)

        # First-vertex bookkeeping and first-collision features.
        first_is_volume = mi.Bool(False)
        volume_events = mi.UInt32(0)
        media_dist = mi.Float(0.0)
        scatter_position = mi.Point3f(0.0)
        scatter_media_distance = mi.Float(0.0)
        scatter_sigma_t = mi.Spectrum(0.0)
        scatter_sigma_s = mi.Spectrum(0.0)

        while dr.hint(active, max_iterations=-1, label="nrbench_volpath path"):
            # Russian roulette and depth limit, as volpath.
            active &= dr.any(throughput != 0.0)
            q = dr.minimum(dr.max(throughput) * dr.square(eta), 0.95)
            perform_rr = depth > self.rr_depth
            active &= (sampler.next_1d(active) < q) | ~perform_rr
            throughput[perform_rr] *= dr.rcp(q)
            active &= depth < self._max_depth

            # ---------------- free-flight sampling (delta tracking) ----------------
            active_medium = active & (medium != None)  # noqa: E711
            active_surface = active & ~active_medium
            is_spectral = active_medium & medium.has_spectral_extinction()
            not_spectral = active_medium & ~is_spectral

            mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel, active_medium)
            ray.maxt[active_medium & medium.is_homogeneous() & mei.is_valid()] = mei.t
            intersect = needs_intersection & active_medium
            si[intersect] = scene.ray_intersect(ray, intersect)
            needs_intersection &= ~active_medium
            mei.t[active_medium & (si.t < mei.t)] = dr.inf
            tr, ff_pdf = medium.transmittance_eval_pdf(mei, si, is_spectral)
            tr_pdf = _index_spectrum(ff_pdf, channel)
            throughput[is_spectral] *= dr.select(tr_pdf > 0.0, tr / tr_pdf, 0.0)

            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            majorant_c = _index_spectrum(mei.combined_extinction, channel)
            null_scatter = (
                sampler.next_1d(active_medium) >= _index_spectrum(mei.sigma_t, channel) / majorant_c
            )
            act_null_scatter = active_medium & null_scatter
            act_medium_scatter = active_medium & ~null_scatter
            throughput[is_spectral & act_null_scatter] *= (
                mei.sigma_n * majorant_c / _index_spectrum(mei.sigma_n, channel)
            )

            if dr.hint(features, mode="scalar"):
                on_camera_ray = depth == 0
                media_dist[on_camera_ray & escaped_medium & si.is_valid()] += si.t
                media_dist[on_camera_ray & active_medium] += mei.t
                first_collision = on_camera_ray & act_medium_scatter
                first_is_volume |= first_collision
                scatter_position[first_collision] = mei.p
                scatter_media_distance[first_collision] = media_dist
                scatter_sigma_t[first_collision] = mei.sigma_t
                scatter_sigma_s[first_collision] = mei.sigma_s
                volume_events[act_medium_scatter] += 1

            depth[act_medium_scatter] += 1
            last_scatter_event[act_medium_scatter] = mei

            active &= depth < self._max_depth
            act_medium_scatter &= active
            ray.o[act_null_scatter] = mei.p
            si.t[act_null_scatter] = si.t - mei.t

            throughput[is_spectral & act_medium_scatter] *= (
                mei.sigma_s * majorant_c / _index_spectrum(mei.sigma_t, channel)
            )
            throughput[not_spectral & act_medium_scatter] *= mei.sigma_s / mei.sigma_t
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            phase[~act_medium_scatter] = dr.zeros(mi.PhaseFunctionPtr)
            sample_emitters = mei.medium.use_emitter_sampling()
            valid_ray |= act_medium_scatter
            specular_chain &= ~act_medium_scatter
            specular_chain |= act_medium_scatter & ~sample_emitters
            active_e_medium = act_medium_scatter & sample_emitters

            # ---------------- surfaces: emitter hit ----------------
            active_surface |= escaped_medium
            intersect = active_surface & needs_intersection
            si[intersect] = scene.ray_intersect(ray, intersect)

            count_direct = (active_surface & (depth == 0)) | specular_chain
            emitter = si.emitter(scene)
            active_e = active_surface & (emitter != None)  # noqa: E711
            ds = mi.DirectionSample3f(scene, si, last_scatter_event)
            emitter_pdf = scene.pdf_emitter_direction(last_scatter_event, ds, active_e & ~count_direct)
            emitted = emitter.eval(si, active_e)
            mis = dr.select(count_direct, 1.0, _mis_weight(last_scatter_direction_pdf, emitter_pdf))
            # Radiance is non-negative; round-off in the spectral delta-tracking weights leaves ~-1e-19
            # here and there, which the dataset loader would reject as negative radiance.
            contrib = dr.maximum(dr.select(active_e, throughput * mis * emitted, 0.0), 0.0)
            if dr.hint(features, mode="scalar"):
                single = first_is_volume & (depth == 1)
                L_surface, L_single, L_multi = _split_contribution(
                    contrib, first_is_volume, single, L_surface, L_single, L_multi
                )
            else:
                L_surface += contrib

            active_surface &= si.is_valid()
            bsdf_ctx = mi.BSDFContext()
            bsdf = si.bsdf(ray)

            # ---------------- next-event estimation (medium collisions and surfaces) ----------------
            active_e_surface = (
                active_surface
                & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                & (depth + 1 < self._max_depth)
            )
            active_nee = active_e_medium | active_e_surface
            ref = dr.zeros(mi.Interaction3f)
            ref[active_e_medium] = mei
            ref[active_e_surface] = si
            emitted, ds = self.sample_emitter(
                scene, sampler, ref, si, active_e_surface, medium, channel, active_nee
            )
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, si.to_local(ds.d), active_e_surface)
            phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, active_e_medium)
            nee_val = dr.select(active_e_surface, bsdf_val, phase_val)
            nee_pdf = dr.select(ds.delta, 0.0, dr.select(active_e_surface, bsdf_pdf, phase_pdf))
            contrib = dr.select(
                active_nee, throughput * nee_val * _mis_weight(ds.pdf, nee_pdf) * emitted, 0.0
            )
            contrib = dr.maximum(contrib, 0.0)  # round-off negatives, as above
            if dr.hint(features, mode="scalar"):
                # Vertices of this path: the collision is counted in depth, the surface not yet.
                vertices = dr.select(active_e_medium, depth, depth + 1)
                single = first_is_volume & (vertices == 1)
                L_surface, L_single, L_multi = _split_contribution(
                    contrib, first_is_volume, single, L_surface, L_single, L_multi
                )
            else:
                L_surface += contrib

            # ---------------- phase-function sampling ----------------
            wo, phase_weight, phase_sample_pdf = phase.sample(
                phase_ctx,
                mei,
                sampler.next_1d(act_medium_scatter),
                sampler.next_2d(act_medium_scatter),
                act_medium_scatter,
            )
            act_medium_scatter &= phase_sample_pdf > 0.0
            ray[act_medium_scatter] = mei.spawn_ray(wo)
            needs_intersection |= act_medium_scatter
            last_scatter_direction_pdf[act_medium_scatter] = phase_sample_pdf
            throughput[act_medium_scatter] *= phase_weight

            # ---------------- BSDF sampling ----------------
            bs, bsdf_weight = bsdf.sample(
                bsdf_ctx, si, sampler.next_1d(active_surface), sampler.next_2d(active_surface), active_surface
            )
            throughput[active_surface] *= bsdf_weight
            eta[active_surface] *= bs.eta
            ray[active_surface] = si.spawn_ray(si.to_world(bs.wo))
            needs_intersection |= active_surface
            non_null_bsdf = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth[non_null_bsdf] += 1
            last_scatter_event[non_null_bsdf] = si
            last_scatter_direction_pdf[non_null_bsdf] = bs.pdf
            valid_ray |= non_null_bsdf
            specular_chain |= non_null_bsdf & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(active_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            medium[active_surface & si.is_medium_transition()] = si.target_medium(ray.d)
            active &= active_surface | active_medium

        L_volume = L_single + L_multi
        color = L_surface + L_volume
        aovs = []
        if dr.hint(features, mode="scalar"):
            scatter_depth = dr.select(first_is_volume, dr.norm(scatter_position - camera_o), 0.0)
            values = {
                "color": color,
                "surface": L_surface,
                "volume": L_volume,
                "volume_single": L_single,
                "volume_multi": L_multi,
                "albedo": albedo,
                "normal": normal,
                "depth": surface_depth,
                "visibility": visibility,
                "position": dr.select(first_is_volume, scatter_position, dr.select(hit, first_si.p, 0.0)),
                "transmittance": transmittance,
                "optical_thickness": tau,
                "scatter_depth": scatter_depth,
                "scatter_position": scatter_position,
                "scatter_media_distance": scatter_media_distance,
                "sigma_t": scatter_sigma_t,
                "sigma_s": scatter_sigma_s,
                "scatter_albedo": dr.select(scatter_sigma_t > 0.0, scatter_sigma_s / scatter_sigma_t, 0.0),
                "scattered": dr.select(volume_events > 0, 1.0, 0.0),
                "volume_events": mi.Float(volume_events),
            }
            aovs = film_aovs(values)
        return color, valid_ray, aovs


def register() -> None:
    """Make the integrator available as ``{"type": "nrbench_volpath"}`` (idempotent)."""
    mi.register_integrator(PLUGIN_NAME, lambda props: VolumetricAovIntegrator(props))
