//! The path tracer: unidirectional paths with next-event estimation towards area lights, the
//! sun and the environment, combined with BSDF sampling by multiple importance sampling
//! (Veach 1997, power heuristic), and Russian roulette after a few bounces.
//!
//! One [`Renderer`] prepares a scene once (BVH, light table) and renders any number of views.
//! Pixels are independent and each draws from its own random stream, so an image depends
//! only on the scene, the camera and the options, never on the thread count.

use glam::Vec3;
use rayon::prelude::*;
use thiserror::Error;

use nephele_geometry::SolidGrid;
use nephele_geometry::camera::{Camera, Ray};
use nephele_geometry::solid::SolidTraversal;

use super::bvh::{Bvh, Hit, TraversalStats};
use super::material::{DielectricEvent, Material, fresnel_dielectric, luminance, refract};
use super::sampling::{Distribution1D, Frame, Rng, cosine_hemisphere, power_heuristic, uniform_cone, uniform_triangle};
use super::scene::{Scene, SceneError};

/// Most samples per pixel accepted (a guard against typos, not a technical limit).
pub const MAX_SAMPLES_PER_PIXEL: u32 = 1 << 16;
/// Most bounces accepted.
pub const MAX_BOUNCES: u32 = 1024;
/// Bounces after which Russian roulette may end a path.
const ROULETTE_AFTER: u32 = 3;

#[derive(Debug, Error, PartialEq)]
pub enum RenderError {
    #[error("invalid scene: {0}")]
    Scene(#[from] SceneError),
    #[error("samples per pixel must be between 1 and {MAX_SAMPLES_PER_PIXEL}, got {0}")]
    SamplesPerPixel(u32),
    #[error("max bounces must be at most {MAX_BOUNCES}, got {0}")]
    MaxBounces(u32),
}

/// What rays that hit nothing show.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Background {
    /// Alpha 0 and no colour where camera rays miss (NeRF-synthetic style objects).
    #[default]
    Transparent,
    /// The environment is visible and every pixel is opaque (interiors, skies).
    Environment,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    pub samples_per_pixel: u32,
    /// Longest path, in surface interactions after the camera ray's hit.
    pub max_bounces: u32,
    pub seed: u64,
    pub background: Background,
    /// Trace only what [`RenderOutput::direct`] needs (the G-buffer a rasteriser would give and
    /// its direct light, as the environment kernel serves): the camera ray, next-event
    /// estimation at its hit, and the one bounce ray that finds emitters and the environment
    /// for MIS; no light is gathered at the bounce's hit (that would be indirect light) and
    /// the path ends there. `color` then equals `direct`. Of up to eight rays per sample at
    /// `max_bounces = 1` (camera, three shadow rays, bounce, three more shadow rays) the last
    /// three are never cast; `max_bounces` is ignored.
    pub direct_only: bool,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            samples_per_pixel: 16,
            max_bounces: 8,
            seed: 0,
            background: Background::Transparent,
            direct_only: false,
        }
    }
}

impl RenderOptions {
    pub fn validate(&self) -> Result<(), RenderError> {
        if self.samples_per_pixel == 0 || self.samples_per_pixel > MAX_SAMPLES_PER_PIXEL {
            return Err(RenderError::SamplesPerPixel(self.samples_per_pixel));
        }
        if self.max_bounces > MAX_BOUNCES {
            return Err(RenderError::MaxBounces(self.max_bounces));
        }
        Ok(())
    }
}

/// Work done while rendering, for benchmarks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RenderStats {
    /// Camera samples traced.
    pub samples: u64,
    /// Every ray cast: camera, bounce and shadow rays.
    pub traversal: TraversalStats,
    /// Samples whose estimate was not finite and was dropped (should stay 0).
    pub dropped_non_finite: u64,
    /// Camera samples whose first hit lies behind an occluder's solid cells
    /// ([`Renderer::render_behind`]): traced for the G-buffer, not lit.
    pub hidden_samples: u64,
    /// Shadow and bounce rays an occluder's solid cells stopped before they reached their
    /// light or surface ([`Renderer::render_behind`]: the objects' shadows on the scene).
    pub light_blocked: u64,
}

/// Per-pixel outputs of one render. Colours are linear; `color` and `direct` are
/// premultiplied by `alpha`. Geometric outputs are averages over the samples that hit a
/// surface, 0 where none did.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    pub width: u32,
    pub height: u32,
    /// Full global illumination.
    pub color: Vec<Vec3>,
    /// Emission seen directly plus light that reached the first surface straight from a light
    /// source, the sun or the environment.
    pub direct: Vec<Vec3>,
    /// Coverage: share of camera samples that hit geometry (1 everywhere with
    /// [`Background::Environment`]).
    pub alpha: Vec<f32>,
    /// View-space depth (see the crate conventions).
    pub depth: Vec<f32>,
    pub position: Vec<Vec3>,
    /// Shading normal of the first hit, turned towards the camera.
    pub normal: Vec<Vec3>,
    pub albedo: Vec<Vec3>,
    /// Pixels every camera sample of which [`Renderer::render_behind`]'s occluders hid (all
    /// `false` without occluders): the objects cover them fully.
    pub covered: Vec<bool>,
    pub stats: RenderStats,
}

/// One pixel of [`Renderer::render_pixel_list`]: colour premultiplied by alpha, alpha, view depth.
pub type ListedPixel = (Vec3, f32, f32);

/// A scene prepared for rendering.
#[derive(Debug)]
pub struct Renderer {
    scene: Scene,
    bvh: Bvh,
    lights: Option<LightTable>,
}

/// Emissive triangles, picked in proportion to their power.
#[derive(Debug)]
struct LightTable {
    triangles: Vec<u32>,
    distribution: Distribution1D,
    /// Index into `triangles` for each mesh triangle, `u32::MAX` if it does not emit.
    light_of_triangle: Vec<u32>,
}

/// One camera sample's result.
#[derive(Debug, Default)]
struct SampleResult {
    radiance: Vec3,
    direct: Vec3,
    first_hit: Option<FirstHit>,
    /// The first hit lies behind an occluder: not lit.
    hidden: bool,
}

#[derive(Debug)]
struct FirstHit {
    distance: f32,
    position: Vec3,
    normal: Vec3,
    albedo: Vec3,
}

/// A resolved ray-surface intersection.
struct SurfacePoint {
    position: Vec3,
    /// Geometric normal turned to the side the ray came from.
    geometric: Vec3,
    /// Shading normal on the same side as `geometric`.
    shading: Vec3,
    /// Whether the ray hit the triangle's front (counter-clockwise) face.
    front_face: bool,
    material: Material,
    triangle: u32,
}

impl Renderer {
    pub fn new(scene: Scene) -> Result<Renderer, RenderError> {
        scene.validate()?;
        let bvh = Bvh::build(&scene.mesh);
        let lights = build_light_table(&scene);
        Ok(Renderer { scene, bvh, lights })
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Renders every pixel of `camera`. `progress` is called with the number of rows just
    /// finished (from worker threads).
    pub fn render(
        &self,
        camera: &Camera,
        options: &RenderOptions,
        progress: &(dyn Fn(u32) + Sync),
    ) -> Result<RenderOutput, RenderError> {
        self.render_behind(camera, options, &[], progress)
    }

    /// [`Renderer::render`] for a scene that objects stand in, whose solid matter
    /// (`occluders`, in this scene's coordinates) hides whatever lies behind it: a camera
    /// sample whose first hit lies beyond the point where its ray enters a solid cell is
    /// traced for the G-buffer (position, normal, albedo, depth) but not lit (no shadow
    /// rays, no bounce; `color` and `direct` get nothing from it), and counted in
    /// [`RenderStats::hidden_samples`]. Issue 13: the pixels the objects cover fully are
    /// not shaded for the environment.
    ///
    /// The same solid matter **casts shadows**: a shadow ray (to an area light, the sun or
    /// the environment) or a bounce ray that enters a solid cell before its light or surface
    /// brings nothing, counted in [`RenderStats::light_blocked`]; the objects reflect no
    /// light onto the scene. Light only falls: a pixel's direct light is never more than
    /// [`Renderer::render`] gives it, and pixels none of whose rays an occluder meets
    /// render exactly as there (a hidden sample or a stopped bounce draws fewer random
    /// numbers, so the next sample of its pixel takes another path).
    pub fn render_behind(
        &self,
        camera: &Camera,
        options: &RenderOptions,
        occluders: &[SolidGrid],
        progress: &(dyn Fn(u32) + Sync),
    ) -> Result<RenderOutput, RenderError> {
        options.validate()?;
        let (width, height) = (camera.width(), camera.height());
        // Where a camera ray may meet a solid cell at all; the walk runs only there.
        let mut footprint = vec![false; if occluders.is_empty() { 0 } else { width as usize * height as usize }];
        for grid in occluders {
            grid.footprint(camera, &mut footprint);
        }
        let occluders: Vec<SolidTraversal> = occluders.iter().map(SolidGrid::traversal).collect();
        let occluders = occluders.as_slice();
        let pixels = width as usize * height as usize;
        let mut out = RenderOutput {
            width,
            height,
            color: vec![Vec3::ZERO; pixels],
            direct: vec![Vec3::ZERO; pixels],
            alpha: vec![0.0; pixels],
            depth: vec![0.0; pixels],
            position: vec![Vec3::ZERO; pixels],
            normal: vec![Vec3::ZERO; pixels],
            albedo: vec![Vec3::ZERO; pixels],
            covered: vec![false; pixels],
            stats: RenderStats::default(),
        };
        let row_stats: Vec<RenderStats> = out
            .color
            .par_chunks_mut(width as usize)
            .zip(out.direct.par_chunks_mut(width as usize))
            .zip(out.alpha.par_chunks_mut(width as usize))
            .zip(out.depth.par_chunks_mut(width as usize))
            .zip(out.position.par_chunks_mut(width as usize))
            .zip(out.normal.par_chunks_mut(width as usize))
            .zip(out.albedo.par_chunks_mut(width as usize))
            .zip(out.covered.par_chunks_mut(width as usize))
            .enumerate()
            .map(|(y, (((((((color, direct), alpha), depth), position), normal), albedo), covered))| {
                let mut stats = RenderStats::default();
                let row = footprint.get(y * width as usize..(y + 1) * width as usize).unwrap_or(&[]);
                let mut behind = Behind::new(occluders, row);
                for x in 0..width as usize {
                    let pixel_index = y as u64 * u64::from(width) + x as u64;
                    let px =
                        self.render_pixel(camera, options, &mut behind, x as u32, y as u32, pixel_index, &mut stats);
                    color[x] = px.color;
                    direct[x] = px.direct;
                    alpha[x] = px.alpha;
                    depth[x] = px.depth;
                    position[x] = px.position;
                    normal[x] = px.normal;
                    albedo[x] = px.albedo;
                    covered[x] = px.covered;
                }
                progress(1);
                stats
            })
            .collect();
        for s in row_stats {
            out.stats.samples += s.samples;
            out.stats.traversal += s.traversal;
            out.stats.dropped_non_finite += s.dropped_non_finite;
            out.stats.hidden_samples += s.hidden_samples;
            out.stats.light_blocked += s.light_blocked;
        }
        Ok(out)
    }

    /// Renders only the listed pixels (`y * width + x`, each `< width * height`): the unit
    /// of work the render farm ships. Returns `(colour premultiplied by alpha, alpha, view
    /// depth)` per listed pixel, in the order given, and the work done. A pixel renders to
    /// exactly the value the full-frame [`Renderer::render`] gives it.
    ///
    /// # Panics
    /// Never on pixel indices: out-of-range indices are the caller's contract to check
    /// ([`nephele_geometry::validate_pixels`]); they are clamped to the last pixel here.
    pub fn render_pixel_list(
        &self,
        camera: &Camera,
        options: &RenderOptions,
        pixels: &[u32],
    ) -> Result<(Vec<ListedPixel>, RenderStats), RenderError> {
        options.validate()?;
        let width = camera.width();
        let last = u64::from(width) * u64::from(camera.height()) - 1;
        let results: Vec<((Vec3, f32, f32), RenderStats)> = pixels
            .par_iter()
            .with_min_len(64)
            .map(|&index| {
                let index = u64::from(index).min(last);
                let (x, y) = ((index % u64::from(width)) as u32, (index / u64::from(width)) as u32);
                let mut stats = RenderStats::default();
                let px = self.render_pixel(camera, options, &mut Behind::new(&[], &[]), x, y, index, &mut stats);
                ((px.color, px.alpha, px.depth), stats)
            })
            .collect();
        let mut total = RenderStats::default();
        let values = results
            .into_iter()
            .map(|(value, s)| {
                total.samples += s.samples;
                total.traversal += s.traversal;
                total.dropped_non_finite += s.dropped_non_finite;
                value
            })
            .collect();
        Ok((values, total))
    }

    #[allow(clippy::too_many_arguments)]
    fn render_pixel(
        &self,
        camera: &Camera,
        options: &RenderOptions,
        behind: &mut Behind,
        x: u32,
        y: u32,
        pixel_index: u64,
        stats: &mut RenderStats,
    ) -> PixelValue {
        let mut rng = Rng::new(options.seed, pixel_index);
        let may_hide = behind.footprint.get(x as usize).copied().unwrap_or(false);
        let mut acc = PixelValue::default();
        let mut hits = 0u32;
        let mut hidden = 0u32;
        let spp = options.samples_per_pixel;
        for _ in 0..spp {
            let jitter = rng.next_vec2();
            let ray = camera.ray(x as f32 + jitter.x, y as f32 + jitter.y);
            let sample = self.trace(ray, options, behind, may_hide, &mut rng, stats);
            stats.samples += 1;
            stats.hidden_samples += u64::from(sample.hidden);
            hidden += u32::from(sample.hidden);
            if !(sample.radiance.is_finite() && sample.direct.is_finite()) {
                stats.dropped_non_finite += 1;
                continue;
            }
            acc.color += sample.radiance;
            acc.direct += sample.direct;
            if let Some(hit) = sample.first_hit {
                hits += 1;
                acc.depth += hit.distance * camera.depth_per_distance(&ray);
                acc.position += hit.position;
                acc.normal += hit.normal;
                acc.albedo += hit.albedo;
            }
        }
        acc.covered = hidden == spp;
        let inv_spp = 1.0 / spp as f32;
        acc.color *= inv_spp;
        acc.direct *= inv_spp;
        acc.alpha = match options.background {
            Background::Transparent => hits as f32 * inv_spp,
            Background::Environment => 1.0,
        };
        if hits > 0 {
            let inv_hits = 1.0 / hits as f32;
            acc.depth *= inv_hits;
            acc.position *= inv_hits;
            acc.normal = acc.normal.normalize_or_zero();
            acc.albedo *= inv_hits;
        }
        acc
    }

    /// Follows one camera ray; see the module documentation. `may_hide`: the camera ray may
    /// meet one of `behind`'s occluders (its pixel lies in their footprint).
    fn trace(
        &self,
        mut ray: Ray,
        options: &RenderOptions,
        behind: &mut Behind,
        may_hide: bool,
        rng: &mut Rng,
        stats: &mut RenderStats,
    ) -> SampleResult {
        let mut result = SampleResult::default();
        let mut throughput = Vec3::ONE;
        // Density with which the previous bounce chose this ray, and the normal there, for
        // MIS when the ray finds a light; `None` after the camera or a delta bounce.
        let mut previous: Option<(f32, Vec3, Vec3)> = None; // (bsdf pdf, position, shading normal)
        // Direct light ends with what the first bounce's ray finds (see `direct_only`).
        let last_bounce = if options.direct_only { 1 } else { options.max_bounces };
        for bounce in 0..=last_bounce {
            let is_direct = bounce <= 1;
            let hit = self.bvh.intersect(&ray, 0.0, f32::INFINITY, &mut stats.traversal);
            if bounce == 0 && may_hide {
                let reach = hit.as_ref().map_or(f32::INFINITY, |h| h.t);
                if behind.hides(&ray, reach) {
                    result.hidden = true;
                    result.first_hit = hit.map(|h| first_hit(&self.surface_point(&ray, &h), h.t));
                    break;
                }
            }
            // An object's solid matter stops a bounce ray before the surface or light it
            // would reach: the object absorbs it (it reflects nothing onto the scene).
            if bounce > 0 && behind.blocks_light(&ray, hit.as_ref().map_or(f32::INFINITY, |h| h.t), stats) {
                break;
            }
            let Some(hit) = hit else {
                if bounce == 0 && options.background == Background::Transparent {
                    break;
                }
                let env = self.scene.environment.radiance(ray.direction);
                let weight = match previous {
                    Some((bsdf_pdf, _, normal)) => power_heuristic(bsdf_pdf, environment_pdf(normal, ray.direction)),
                    None => 1.0,
                };
                add(&mut result, throughput * env * weight, is_direct);
                break;
            };
            let surface = self.surface_point(&ray, &hit);
            if bounce == 0 {
                result.first_hit = Some(first_hit(&surface, hit.t));
            }
            if options.direct_only && bounce >= 1 && !matches!(surface.material, Material::Emissive { .. }) {
                // Light gathered here, or further along, would be indirect.
                break;
            }
            match surface.material {
                Material::Emissive { radiance } => {
                    if surface.front_face {
                        let weight = match previous {
                            Some((bsdf_pdf, from, _)) => {
                                power_heuristic(bsdf_pdf, self.light_pdf(surface.triangle, from, &surface, hit.t))
                            }
                            None => 1.0,
                        };
                        add(&mut result, throughput * radiance * weight, is_direct);
                    }
                    break; // lights do not reflect
                }
                Material::Dielectric { ior, tint } => {
                    let (direction, event) = sample_dielectric(ray.direction, &surface, ior, rng.next_f32());
                    if let DielectricEvent::Refract { .. } = event {
                        throughput *= tint;
                    }
                    ray = Ray { origin: offset_origin(surface.position, surface.geometric, direction), direction };
                    previous = None;
                }
                material => {
                    let frame = Frame::from_normal(surface.shading);
                    let wo = frame.to_local(-ray.direction);
                    let direct_light = self.next_event(&surface, (&material, &frame, wo), behind, rng, stats);
                    add(&mut result, throughput * direct_light, bounce == 0);
                    let Some(sample) = material.sample(wo, rng.next_f32(), rng.next_vec2()) else { break };
                    let direction = frame.to_world(sample.wi);
                    // A shading normal must not send light through the geometric surface.
                    if direction.dot(surface.geometric) <= 0.0 {
                        break;
                    }
                    throughput *= sample.weight;
                    ray = Ray { origin: offset_origin(surface.position, surface.geometric, direction), direction };
                    previous = Some((sample.pdf, surface.position, surface.shading));
                }
            }
            if bounce >= ROULETTE_AFTER {
                let survive = throughput.max_element().min(0.95);
                if !(rng.next_f32() < survive) {
                    break;
                }
                throughput /= survive;
            }
        }
        result
    }

    fn surface_point(&self, ray: &Ray, hit: &Hit) -> SurfacePoint {
        let mesh = &self.scene.mesh;
        let tri = mesh.indices[hit.triangle as usize];
        let [a, b, c] = tri.map(|i| mesh.positions[i as usize]);
        let w = 1.0 - hit.u - hit.v;
        let position = a * w + b * hit.u + c * hit.v;
        let face = (b - a).cross(c - a).normalize_or_zero();
        let front_face = face.dot(ray.direction) < 0.0;
        let geometric = if front_face { face } else { -face };
        let shading = mesh
            .normals
            .as_ref()
            .map(|ns| {
                let [na, nb, nc] = tri.map(|i| ns[i as usize]);
                let n = (na * w + nb * hit.u + nc * hit.v).normalize_or_zero();
                if front_face { n } else { -n }
            })
            // An interpolated normal facing away from the viewer would make the BSDF black.
            .filter(|n| n.dot(-ray.direction) > 1e-4)
            .unwrap_or(geometric);
        let material = self.scene.materials[self.scene.material_of_triangle[hit.triangle as usize] as usize];
        SurfacePoint { position, geometric, shading, front_face, material, triangle: hit.triangle }
    }

    /// Direct light at a non-delta surface from every light kind, MIS-weighted against BSDF
    /// sampling where that could also find the light.
    /// Shadow rays meet `behind`'s occluders (the objects' solid matter) as well as the scene.
    fn next_event(
        &self,
        surface: &SurfacePoint,
        (material, frame, wo): (&Material, &Frame, Vec3),
        behind: &mut Behind,
        rng: &mut Rng,
        stats: &mut RenderStats,
    ) -> Vec3 {
        let mut total = Vec3::ZERO;
        let origin_for = |dir: Vec3| offset_origin(surface.position, surface.geometric, dir);
        // Area lights.
        if let Some(lights) = &self.lights {
            let (k, p_pick) = lights.distribution.sample(rng.next_f32());
            let tri = lights.triangles[k];
            let [a, b, c] = self.scene.mesh.indices[tri as usize].map(|i| self.scene.mesh.positions[i as usize]);
            let bary = uniform_triangle(rng.next_vec2());
            let q = a * (1.0 - bary.x - bary.y) + b * bary.x + c * bary.y;
            let cross = (b - a).cross(c - a);
            let area = 0.5 * cross.length();
            let light_normal = cross.normalize_or_zero();
            let to_light = q - surface.position;
            let dist2 = to_light.length_squared();
            let dist = dist2.sqrt();
            let wi = to_light / dist;
            let cos_light = light_normal.dot(-wi);
            if cos_light > 0.0 && area > 0.0 && wi.dot(surface.geometric) > 0.0 {
                let (f, bsdf_pdf) = material.eval(wo, frame.to_local(wi));
                let cos_surface = frame.to_local(wi).z;
                if f != Vec3::ZERO && cos_surface > 0.0 {
                    let light_pdf = p_pick / area * dist2 / cos_light;
                    let shadow = Ray { origin: origin_for(wi), direction: wi };
                    let reach = (q - shadow.origin).length() * (1.0 - 1e-4);
                    if !self.bvh.occluded(&shadow, 0.0, reach, &mut stats.traversal)
                        && !behind.blocks_light(&shadow, reach, stats)
                        && let Material::Emissive { radiance } = self.material_of(tri)
                    {
                        total += f * radiance * cos_surface / light_pdf * power_heuristic(light_pdf, bsdf_pdf);
                    }
                }
            }
        }
        // The sun: a (nearly) delta light, found only by this strategy.
        if let Some(sun) = self.scene.sun {
            let cone = uniform_cone(rng.next_vec2(), sun.angular_radius.cos());
            let wi = Frame::from_normal(sun.direction).to_world(cone).normalize();
            if wi.dot(surface.geometric) > 0.0 {
                let local = frame.to_local(wi);
                let (f, _) = material.eval(wo, local);
                if f != Vec3::ZERO && local.z > 0.0 {
                    let shadow = Ray { origin: origin_for(wi), direction: wi };
                    if !self.bvh.occluded(&shadow, 0.0, f32::INFINITY, &mut stats.traversal)
                        && !behind.blocks_light(&shadow, f32::INFINITY, stats)
                    {
                        total += f * sun.irradiance * local.z;
                    }
                }
            }
        }
        // The environment, sampled by cosine about the shading normal.
        if !self.scene.environment.is_black() {
            let wi = frame.to_world(cosine_hemisphere(rng.next_vec2()));
            let env_pdf = environment_pdf(surface.shading, wi);
            if wi.dot(surface.geometric) > 0.0 && env_pdf > 0.0 {
                let local = frame.to_local(wi);
                let (f, bsdf_pdf) = material.eval(wo, local);
                if f != Vec3::ZERO {
                    let shadow = Ray { origin: origin_for(wi), direction: wi };
                    if !self.bvh.occluded(&shadow, 0.0, f32::INFINITY, &mut stats.traversal)
                        && !behind.blocks_light(&shadow, f32::INFINITY, stats)
                    {
                        let env = self.scene.environment.radiance(wi);
                        total += f * env * local.z / env_pdf * power_heuristic(env_pdf, bsdf_pdf);
                    }
                }
            }
        }
        total
    }

    fn material_of(&self, triangle: u32) -> Material {
        self.scene.materials[self.scene.material_of_triangle[triangle as usize] as usize]
    }

    /// Solid-angle density with which next-event estimation from `from` picks the point on
    /// emissive `triangle` that a ray reached at distance `distance`.
    fn light_pdf(&self, triangle: u32, from: Vec3, surface: &SurfacePoint, distance: f32) -> f32 {
        let Some(lights) = &self.lights else { return 0.0 };
        let k = lights.light_of_triangle[triangle as usize];
        if k == u32::MAX {
            return 0.0;
        }
        let [a, b, c] = self.scene.mesh.indices[triangle as usize].map(|i| self.scene.mesh.positions[i as usize]);
        let area = 0.5 * (b - a).cross(c - a).length();
        let to_point = surface.position - from;
        let cos_light = surface.geometric.dot(-to_point.normalize_or_zero()).abs();
        if area <= 0.0 || cos_light <= 0.0 {
            return 0.0;
        }
        lights.distribution.probability(k as usize) / area * distance * distance / cos_light
    }
}

#[derive(Debug, Default, Clone, Copy)]
struct PixelValue {
    color: Vec3,
    direct: Vec3,
    alpha: f32,
    depth: f32,
    position: Vec3,
    normal: Vec3,
    albedo: Vec3,
    /// Every sample hidden behind the occluders.
    covered: bool,
}

/// The occluders of [`Renderer::render_behind`] as one thread walks a row of camera rays:
/// the row's pixels whose rays may meet a solid cell, and the solid cell that last blocked a
/// camera ray of each occluder (tried first for the next ray), the same for shadow and
/// bounce rays (neighbouring pixels' shadow rays to one light are coherent too).
struct Behind<'a> {
    occluders: &'a [SolidTraversal<'a>],
    footprint: &'a [bool],
    hints: Vec<Option<[u32; 3]>>,
    light_hints: Vec<Option<[u32; 3]>>,
}

impl<'a> Behind<'a> {
    fn new(occluders: &'a [SolidTraversal<'a>], footprint: &'a [bool]) -> Behind<'a> {
        let hints = vec![None; occluders.len()];
        Behind { occluders, footprint, light_hints: hints.clone(), hints }
    }

    /// Whether an occluder stops a shadow or bounce `ray` before distance `reach` (counted).
    fn blocks_light(&mut self, ray: &Ray, reach: f32, stats: &mut RenderStats) -> bool {
        let blocked = self
            .occluders
            .iter()
            .zip(&mut self.light_hints)
            .any(|(o, hint)| o.blocks_near(ray.origin, ray.direction, reach, hint));
        stats.light_blocked += u64::from(blocked);
        blocked
    }

    /// Whether an occluder hides what `ray` meets at distance `reach`.
    fn hides(&mut self, ray: &Ray, reach: f32) -> bool {
        self.occluders
            .iter()
            .zip(&mut self.hints)
            .any(|(o, hint)| o.blocks_near(ray.origin, ray.direction, reach, hint))
    }
}

/// What the G-buffer keeps of a camera ray's hit.
fn first_hit(surface: &SurfacePoint, distance: f32) -> FirstHit {
    FirstHit { distance, position: surface.position, normal: surface.shading, albedo: surface.material.albedo() }
}

fn add(result: &mut SampleResult, contribution: Vec3, is_direct: bool) {
    result.radiance += contribution;
    if is_direct {
        result.direct += contribution;
    }
}

/// Density of the environment strategy of next-event estimation: cosine about the normal.
fn environment_pdf(normal: Vec3, direction: Vec3) -> f32 {
    normal.dot(direction).max(0.0) * std::f32::consts::FRAC_1_PI
}

/// Moves a ray origin off the surface, to the side `direction` leaves through, by an amount
/// that grows with the coordinates' magnitude (float spacing), to avoid self-intersection.
fn offset_origin(position: Vec3, geometric_normal: Vec3, direction: Vec3) -> Vec3 {
    let epsilon = 1e-4 * (1.0 + position.abs().max_element());
    let side = if direction.dot(geometric_normal) >= 0.0 { 1.0 } else { -1.0 };
    position + geometric_normal * (side * epsilon)
}

/// Reflects or refracts through a smooth dielectric, choosing by the Fresnel reflectance.
fn sample_dielectric(incoming: Vec3, surface: &SurfacePoint, ior: f32, u: f32) -> (Vec3, DielectricEvent) {
    // Front face = entering the medium from outside.
    let eta = if surface.front_face { 1.0 / ior } else { ior };
    let n = surface.geometric;
    let cos_i = -incoming.dot(n);
    let reflectance = fresnel_dielectric(cos_i, eta);
    let reflected = (incoming + 2.0 * cos_i * n).normalize();
    if u < reflectance {
        return (reflected, DielectricEvent::Reflect);
    }
    match refract(incoming, n, eta) {
        Some(t) => (t, DielectricEvent::Refract { eta }),
        None => (reflected, DielectricEvent::Reflect),
    }
}

fn build_light_table(scene: &Scene) -> Option<LightTable> {
    let mut triangles = Vec::new();
    let mut powers = Vec::new();
    let mut light_of_triangle = vec![u32::MAX; scene.mesh.indices.len()];
    for (t, tri) in scene.mesh.indices.iter().enumerate() {
        let material = scene.materials[scene.material_of_triangle[t] as usize];
        if let Material::Emissive { radiance } = material {
            let [a, b, c] = tri.map(|i| scene.mesh.positions[i as usize]);
            let area = 0.5 * (b - a).cross(c - a).length();
            let power = area * luminance(radiance);
            if power > 0.0 && power.is_finite() {
                light_of_triangle[t] = triangles.len() as u32;
                triangles.push(t as u32);
                powers.push(power);
            }
        }
    }
    let distribution = Distribution1D::new(&powers)?;
    Some(LightTable { triangles, distribution, light_of_triangle })
}

/// A per-pixel output of [`RenderOutput`] that can be written to a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Aov {
    /// Full global illumination with alpha.
    Color,
    /// Direct light only, with alpha.
    Direct,
    Alpha,
    Depth,
    Position,
    Normal,
    Albedo,
}

impl Aov {
    pub const ALL: [Aov; 7] =
        [Aov::Color, Aov::Direct, Aov::Alpha, Aov::Depth, Aov::Position, Aov::Normal, Aov::Albedo];

    pub fn name(self) -> &'static str {
        match self {
            Aov::Color => "color",
            Aov::Direct => "direct",
            Aov::Alpha => "alpha",
            Aov::Depth => "depth",
            Aov::Position => "position",
            Aov::Normal => "normal",
            Aov::Albedo => "albedo",
        }
    }

    pub fn from_name(name: &str) -> Option<Aov> {
        Aov::ALL.into_iter().find(|a| a.name() == name)
    }
}

impl RenderOutput {
    /// An 8-bit-ready image of `Color` or `Direct` (other outputs: `Color`): sRGB-encoded,
    /// clamped to `[0, 1]`, straight alpha, as NeRF-synthetic stores its views.
    pub fn to_rgba(&self, aov: Aov) -> nephele_imaging::image::RgbaImage {
        let colours = if aov == Aov::Direct { &self.direct } else { &self.color };
        let pixels = colours
            .iter()
            .zip(&self.alpha)
            .map(|(&c, &a)| {
                let straight = if a > 0.0 { c / a } else { Vec3::ZERO };
                let s = straight.to_array().map(|v| nephele_imaging::image::linear_to_srgb(v.clamp(0.0, 1.0)));
                [s[0], s[1], s[2], a.clamp(0.0, 1.0)]
            })
            .collect();
        nephele_imaging::image::RgbaImage::from_pixels(self.width, self.height, pixels)
            .unwrap_or_else(|_| nephele_imaging::image::RgbaImage::new(self.width, self.height))
    }

    /// Linear floating-point data of one output: 4 channels (premultiplied) for colours,
    /// 1 for alpha and depth, 3 otherwise.
    pub fn to_float(&self, aov: Aov) -> nephele_imaging::image::FloatImage {
        let rgba = |c: &[Vec3]| c.iter().zip(&self.alpha).flat_map(|(c, &a)| [c.x, c.y, c.z, a]).collect::<Vec<f32>>();
        let rgb = |c: &[Vec3]| c.iter().flat_map(|c| c.to_array()).collect::<Vec<f32>>();
        let (channels, data) = match aov {
            Aov::Color => (4, rgba(&self.color)),
            Aov::Direct => (4, rgba(&self.direct)),
            Aov::Alpha => (1, self.alpha.clone()),
            Aov::Depth => (1, self.depth.clone()),
            Aov::Position => (3, rgb(&self.position)),
            Aov::Normal => (3, rgb(&self.normal)),
            Aov::Albedo => (3, rgb(&self.albedo)),
        };
        nephele_imaging::image::FloatImage::from_data(self.width, self.height, channels, data)
            .unwrap_or_else(|_| unreachable_image(self.width, self.height, channels))
    }
}

/// `from_data` only fails on a size mismatch, which the renderer's own buffers cannot have.
fn unreachable_image(width: u32, height: u32, channels: usize) -> nephele_imaging::image::FloatImage {
    nephele_imaging::image::FloatImage::new(width, height, channels).unwrap_or_else(|_| {
        nephele_imaging::image::FloatImage::new(1, 1, 1).unwrap_or_else(|e| panic!("1x1 image: {e}"))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Environment, Mesh, SceneBuilder, Sun};
    use glam::Affine3A;

    /// A closed cube of half-size `h` centred at the origin, outward winding.
    fn cube(h: f32) -> Mesh {
        let p = |x: f32, y: f32, z: f32| Vec3::new(x, y, z) * h;
        let positions = vec![
            p(-1., -1., -1.),
            p(1., -1., -1.),
            p(1., 1., -1.),
            p(-1., 1., -1.),
            p(-1., -1., 1.),
            p(1., -1., 1.),
            p(1., 1., 1.),
            p(-1., 1., 1.),
        ];
        let quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [1, 2, 6, 5], [0, 4, 7, 3]];
        let indices = quads.iter().flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        Mesh::new(positions, indices)
    }

    /// A square in the z = 0 plane facing +z, of half-size `h`.
    fn square(h: f32) -> Mesh {
        Mesh::new(
            vec![Vec3::new(-h, -h, 0.0), Vec3::new(h, -h, 0.0), Vec3::new(h, h, 0.0), Vec3::new(-h, h, 0.0)],
            vec![[0, 1, 2], [0, 2, 3]],
        )
    }

    fn camera(size: u32, eye: Vec3) -> Camera {
        Camera::look_at(size, size, 0.5, eye, Vec3::ZERO, Vec3::Z).expect("camera")
    }

    fn mean_over_covered(out: &RenderOutput) -> Vec3 {
        let covered: Vec<Vec3> =
            out.color.iter().zip(&out.alpha).filter(|(_, a)| **a == 1.0).map(|(c, _)| *c).collect();
        assert!(!covered.is_empty());
        covered.iter().sum::<Vec3>() / covered.len() as f32
    }

    #[test]
    fn furnace_white_convex_object_in_uniform_light_matches_the_light() {
        for (albedo, expected) in [(1.0, 0.5), (0.5, 0.25)] {
            let mut b = SceneBuilder::new();
            b.add(&cube(0.5), Affine3A::IDENTITY, Material::lambertian(Vec3::splat(albedo)));
            b.environment(Environment::Uniform(Vec3::splat(0.5)));
            let renderer = Renderer::new(b.build().expect("scene")).expect("renderer");
            let options = RenderOptions { samples_per_pixel: 64, ..Default::default() };
            let out = renderer.render(&camera(24, Vec3::new(3.0, -2.0, 1.5)), &options, &|_| {}).expect("render");
            let mean = mean_over_covered(&out);
            for c in mean.to_array() {
                assert!((c / expected - 1.0).abs() < 0.01, "albedo {albedo}: {mean} vs {expected}");
            }
            assert_eq!(out.stats.dropped_non_finite, 0);
        }
    }

    #[test]
    fn alpha_is_exactly_zero_where_rays_miss() {
        let mut b = SceneBuilder::new();
        b.add(&cube(0.3), Affine3A::IDENTITY, Material::lambertian(Vec3::splat(0.7)));
        b.environment(Environment::Uniform(Vec3::ONE));
        let renderer = Renderer::new(b.build().expect("scene")).expect("renderer");
        let cam = camera(32, Vec3::new(0.0, -4.0, 0.0));
        let out = renderer
            .render(&cam, &RenderOptions { samples_per_pixel: 4, ..Default::default() }, &|_| {})
            .expect("render");
        // The cube's silhouette seen face-on spans a known pixel range; every pixel whose
        // square lies outside it must be exactly empty, every one inside exactly covered.
        let (lo, hi) = (
            cam.project(Vec3::new(-0.3, -0.3, 0.3)).expect("in front"),
            cam.project(Vec3::new(0.3, -0.3, -0.3)).expect("in front"),
        );
        let mut seen_empty = 0;
        for y in 0..32u32 {
            for x in 0..32u32 {
                let i = (y * 32 + x) as usize;
                let (xf, yf) = (x as f32, y as f32);
                let outside = xf + 1.0 <= lo.x || xf >= hi.x || yf + 1.0 <= lo.y || yf >= hi.y;
                let inside = xf >= lo.x && xf + 1.0 <= hi.x && yf >= lo.y && yf + 1.0 <= hi.y;
                if outside {
                    seen_empty += 1;
                    assert_eq!(out.alpha[i], 0.0, "pixel {x},{y}");
                    assert_eq!(out.color[i], Vec3::ZERO);
                    assert_eq!(out.depth[i], 0.0);
                }
                if inside {
                    assert_eq!(out.alpha[i], 1.0, "pixel {x},{y}");
                    assert!((out.depth[i] - 3.7).abs() < 1e-3, "depth {}", out.depth[i]);
                }
            }
        }
        assert!(seen_empty > 100);
    }

    /// Irradiance at a point from a parallel rectangle `[0,a] x [0,b]` at height `h` whose
    /// corner is straight above it, for unit radiance (view factor times pi).
    fn corner_rectangle_irradiance(a: f32, b: f32, h: f32) -> f32 {
        let (x, y) = (a / h, b / h);
        let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
        0.5 * (x / sx * (y / sx).atan() + y / sy * (x / sy).atan())
    }

    #[test]
    fn area_light_sun_and_sky_give_the_analytic_radiance() {
        let albedo = 0.6;
        let floor = || Material::lambertian(Vec3::splat(albedo));
        let options = RenderOptions { samples_per_pixel: 4000, ..Default::default() };
        let view = |r: &Renderer| {
            let cam = Camera::look_at(1, 1, 0.01, Vec3::new(0.0, -2.0, 2.0), Vec3::ZERO, Vec3::Z).expect("camera");
            r.render(&cam, &options, &|_| {}).expect("render")
        };
        // A 1 x 1 emitter of radiance 3 facing down, 1 above the floor's centre.
        let mut b = SceneBuilder::new();
        b.add(&square(5.0), Affine3A::IDENTITY, floor());
        b.add(
            &square(0.5),
            Affine3A::from_rotation_translation(glam::Quat::from_rotation_x(std::f32::consts::PI), Vec3::Z),
            Material::emissive(Vec3::splat(3.0)),
        );
        let out = view(&Renderer::new(b.build().expect("scene")).expect("renderer"));
        let irradiance = 3.0 * 4.0 * corner_rectangle_irradiance(0.5, 0.5, 1.0);
        let expected = albedo * irradiance / std::f32::consts::PI;
        assert!((out.color[0].x / expected - 1.0).abs() < 0.02, "{} vs {expected}", out.color[0].x);
        assert!((out.direct[0] - out.color[0]).abs().max_element() < 1e-6, "one bounce only");
        // Sun at 60 degrees elevation with irradiance 2.
        let mut b = SceneBuilder::new();
        b.add(&square(5.0), Affine3A::IDENTITY, floor());
        let dir = Vec3::new(0.5, 0.0, 3f32.sqrt() / 2.0);
        b.sun(Sun { direction: dir, irradiance: Vec3::splat(2.0), angular_radius: 0.0 });
        let out = view(&Renderer::new(b.build().expect("scene")).expect("renderer"));
        let expected = albedo / std::f32::consts::PI * 2.0 * dir.z;
        assert!((out.color[0].x / expected - 1.0).abs() < 1e-3, "{} vs {expected}", out.color[0].x);
        // Uniform sky over an open floor: albedo times the sky.
        let mut b = SceneBuilder::new();
        b.add(&square(5.0), Affine3A::IDENTITY, floor());
        b.environment(Environment::Uniform(Vec3::splat(0.8)));
        let out = view(&Renderer::new(b.build().expect("scene")).expect("renderer"));
        assert!((out.color[0].x / (albedo * 0.8) - 1.0).abs() < 0.01, "{}", out.color[0].x);
    }

    #[test]
    fn rendering_is_deterministic_whatever_the_thread_count() {
        let mut b = SceneBuilder::new();
        b.add(&cube(0.4), Affine3A::IDENTITY, Material::glossy(Vec3::new(0.7, 0.3, 0.2), Vec3::splat(0.04), 0.3));
        b.add(&cube(0.2), Affine3A::from_translation(Vec3::new(0.5, 0.0, 0.5)), Material::glass(1.5, Vec3::ONE));
        b.environment(Environment::Sky {
            zenith: Vec3::new(0.3, 0.5, 1.0),
            horizon: Vec3::ONE,
            ground: Vec3::splat(0.2),
        });
        let renderer = Renderer::new(b.build().expect("scene")).expect("renderer");
        let options = RenderOptions { samples_per_pixel: 3, seed: 42, ..Default::default() };
        let cam = camera(20, Vec3::new(2.0, -3.0, 1.0));
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool")
                .install(|| renderer.render(&cam, &options, &|_| {}).expect("render"))
        };
        let (a, b) = (run(1), run(2));
        assert_eq!(a.color, b.color);
        assert_eq!(a.depth, b.depth);
        let other_seed = renderer.render(&cam, &RenderOptions { seed: 43, ..options }, &|_| {}).expect("render");
        assert_ne!(a.color, other_seed.color);
        assert!(a.color.iter().all(|c| c.is_finite()));
    }

    /// The direct-light-only mode casts fewer rays and, with one sample per pixel (the random
    /// stream is the same until the path ends), gives exactly the full tracer's direct light;
    /// its colour is its direct light. Both rooms: the sun and the sky through windows by day,
    /// area lamps by night.
    #[test]
    fn direct_only_traces_exactly_the_direct_light_with_fewer_rays() {
        for name in ["room-day", "room-night"] {
            let builtin = crate::scenes::builtin(name).expect("scene");
            let (eye, target, fov_y) = builtin.default_view();
            let cam = Camera::look_at(24, 18, fov_y, eye, target, Vec3::Z).expect("camera");
            let renderer = Renderer::new(builtin.scene).expect("renderer");
            let full = RenderOptions {
                samples_per_pixel: 1,
                max_bounces: 1,
                seed: 7,
                background: Background::Environment,
                direct_only: false,
            };
            let direct = RenderOptions { direct_only: true, ..full };
            let deep = RenderOptions { max_bounces: 6, ..full };
            let a = renderer.render(&cam, &full, &|_| {}).expect("render");
            let b = renderer.render(&cam, &direct, &|_| {}).expect("render");
            let c = renderer.render(&cam, &deep, &|_| {}).expect("render");
            assert_eq!(a.direct, b.direct, "{name}");
            assert_eq!(c.direct, b.direct, "{name}");
            assert_eq!(b.color, b.direct, "{name}");
            assert_eq!((&a.depth, &a.position, &a.normal, &a.albedo), (&b.depth, &b.position, &b.normal, &b.albedo));
            assert!(b.direct.iter().any(|d| d.max_element() > 0.0), "{name}: some light");
            let (rays_full, rays_direct) = (a.stats.traversal.rays, b.stats.traversal.rays);
            assert!(rays_direct < rays_full, "{name}: {rays_direct} rays against {rays_full}");
        }
    }

    #[test]
    fn samples_behind_an_occluder_keep_their_g_buffer_and_lose_their_light() {
        let builtin = crate::scenes::builtin("room-day").expect("scene");
        let (eye, target, fov_y) = builtin.default_view();
        let cam = Camera::look_at(32, 24, fov_y, eye, target, Vec3::Z).expect("camera");
        let renderer = Renderer::new(builtin.scene).expect("renderer");
        let options = RenderOptions {
            samples_per_pixel: 1,
            max_bounces: 1,
            seed: 3,
            background: Background::Environment,
            direct_only: true,
        };
        // A solid block 0.2 m across, 0.6 m in front of the eye: nothing of the room is
        // nearer, so every ray through it is hidden.
        let at = eye + (target - eye).normalize() * 0.6 + Vec3::new(0.05, 0.0, 0.03);
        let block = SolidGrid::new(at - Vec3::splat(0.1), at + Vec3::splat(0.1), [2, 2, 2], &[true; 8]).expect("grid");
        let plain = renderer.render(&cam, &options, &|_| {}).expect("render");
        let behind = renderer.render_behind(&cam, &options, std::slice::from_ref(&block), &|_| {}).expect("render");
        let none = renderer.render_behind(&cam, &options, &[], &|_| {}).expect("render");
        assert_eq!((&none.color, &none.depth), (&plain.color, &plain.depth));
        assert_eq!(plain.stats.hidden_samples, 0);
        let (mut sure, mut possible, mut light_lost) = (0u64, 0u64, 0.0f32);
        for y in 0..24u32 {
            for x in 0..32u32 {
                let i = (y * 32 + x) as usize;
                let corners = [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(dx, dy)| {
                    let ray = cam.ray((x + dx) as f32, (y + dy) as f32);
                    block.blocks(ray.origin, ray.direction, f32::INFINITY)
                });
                // The G-buffer is traced either way.
                assert_eq!(
                    (behind.depth[i], behind.position[i], behind.normal[i], behind.albedo[i]),
                    (plain.depth[i], plain.position[i], plain.normal[i], plain.albedo[i])
                );
                // One sample per pixel: covered is hidden.
                assert!(!plain.covered[i]);
                if corners.iter().all(|&b| b) {
                    sure += 1;
                    assert!(behind.covered[i], "pixel {x} {y}");
                    assert_eq!((behind.direct[i], behind.color[i]), (Vec3::ZERO, Vec3::ZERO), "pixel {x} {y}");
                    light_lost += plain.direct[i].max_element();
                } else if !corners.iter().any(|&b| b) {
                    // Seen, and lit but for what the block's shadow takes (one sample of
                    // direct light: the random stream is the same, light can only fall).
                    assert!(behind.direct[i].cmple(plain.direct[i]).all(), "pixel {x} {y}");
                    assert!(!behind.covered[i], "pixel {x} {y}");
                }
                possible += u64::from(corners.iter().any(|&b| b));
            }
        }
        assert!(sure >= 4 && light_lost > 0.0, "the block covers some lit pixels: {sure}");
        let hidden = behind.stats.hidden_samples;
        assert!((sure..=possible).contains(&hidden), "{hidden} hidden samples, {sure}..={possible} expected");
        assert_eq!(behind.covered.iter().filter(|&&c| c).count() as u64, hidden);
        assert!(behind.stats.traversal.rays < plain.stats.traversal.rays);
    }

    /// The objects' solid matter casts shadows: a floor under a small lamp with a solid block
    /// between them. Floor points from which the block hides the whole lamp get no direct
    /// light; points whose rays to the lamp's corners all pass beside the block keep exactly
    /// their light; nowhere is there more light than without the block.
    #[test]
    fn occluders_cast_shadows_on_the_scene() {
        let mut b = SceneBuilder::new();
        let floor = Affine3A::from_scale_rotation_translation(
            Vec3::new(4.0, 4.0, 0.01),
            glam::Quat::IDENTITY,
            Vec3::new(0.0, 0.0, -0.01),
        );
        b.add(&cube(1.0), floor, Material::lambertian(Vec3::splat(0.7)));
        let lamp_at = Vec3::new(0.0, 0.0, 2.0);
        b.add(&cube(0.1), Affine3A::from_translation(lamp_at), Material::emissive(Vec3::splat(20.0)));
        let renderer = Renderer::new(b.build().expect("scene")).expect("renderer");
        // A slab 0.6 m across halfway up: it hides the whole lamp from the floor within about
        // 0.4 m of the centre and none of it beyond 0.8 m.
        let block = SolidGrid::new(Vec3::new(-0.3, -0.3, 0.95), Vec3::new(0.3, 0.3, 1.05), [4, 4, 1], &[true; 16])
            .expect("grid");
        // Looking down at the floor from the side, below the slab (no camera ray rises).
        let cam = Camera::look_at(48, 48, 0.8, Vec3::new(0.0, -1.6, 0.7), Vec3::ZERO, Vec3::Z).expect("camera");
        let options = RenderOptions {
            samples_per_pixel: 1,
            max_bounces: 1,
            seed: 11,
            background: Background::Environment,
            direct_only: true,
        };
        let plain = renderer.render(&cam, &options, &|_| {}).expect("render");
        let shaded = renderer.render_behind(&cam, &options, std::slice::from_ref(&block), &|_| {}).expect("render");
        assert_eq!(shaded.stats.hidden_samples, 0, "the camera sees past the slab");
        assert!(shaded.stats.light_blocked > 0);
        assert_eq!(plain.stats.light_blocked, 0);
        let lamp_corners: Vec<Vec3> = (0..8)
            .map(|k| lamp_at + Vec3::new([-0.1, 0.1][k & 1], [-0.1, 0.1][(k >> 1) & 1], [-0.1, 0.1][k >> 2]))
            .collect();
        let (mut dark, mut lit) = (0, 0);
        for i in 0..plain.direct.len() {
            assert_eq!(shaded.position[i], plain.position[i], "the G-buffer does not change");
            assert!(shaded.direct[i].is_finite() && shaded.direct[i].cmple(plain.direct[i]).all(), "pixel {i}");
            let p = plain.position[i];
            if p.z.abs() > 1e-3 || plain.direct[i] == Vec3::ZERO {
                continue; // not the floor's top, or unlit anyway
            }
            // The lamp is convex, so its hull is hidden where its corners are.
            let blocked = lamp_corners.iter().map(|&c| block.blocks(p, c - p, 1.0)).collect::<Vec<_>>();
            if blocked.iter().all(|&b| b) {
                dark += 1;
                assert_eq!(shaded.direct[i], Vec3::ZERO, "pixel {i} at {p} lies in the umbra");
            } else if p.truncate().abs().max_element() > 0.85 {
                lit += 1;
                assert_eq!(shaded.direct[i], plain.direct[i], "pixel {i} at {p} lies outside the shadow");
            }
        }
        assert!(dark >= 20 && lit >= 20, "{dark} pixels in the umbra, {lit} outside the shadow");
    }

    #[test]
    fn bad_options_are_rejected() {
        let mut b = SceneBuilder::new();
        b.add(&cube(0.4), Affine3A::IDENTITY, Material::lambertian(Vec3::ONE));
        let renderer = Renderer::new(b.build().expect("scene")).expect("renderer");
        let cam = camera(4, Vec3::new(0.0, -3.0, 0.0));
        let zero = RenderOptions { samples_per_pixel: 0, ..Default::default() };
        assert_eq!(renderer.render(&cam, &zero, &|_| {}).err(), Some(RenderError::SamplesPerPixel(0)));
        let deep = RenderOptions { max_bounces: 5000, ..Default::default() };
        assert_eq!(renderer.render(&cam, &deep, &|_| {}).err(), Some(RenderError::MaxBounces(5000)));
    }
}
