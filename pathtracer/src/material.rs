//! Materials of the reference renderer.
use glam::Vec3;

/// A surface material. All colours are linear RGB.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Material {
    /// Ideal diffuse reflector.
    Lambertian { albedo: Vec3 },
    /// A GGX microfacet specular layer (Fresnel `specular` at normal incidence, `roughness`
    /// = perceptual roughness, alpha = roughness^2) over a Lambertian base `albedo`. With a
    /// black base and a coloured `specular` it is a rough metal.
    Glossy { albedo: Vec3, specular: Vec3, roughness: f32 },
    /// Smooth dielectric (glass, water): Fresnel-weighted reflection and refraction;
    /// `tint` multiplies transmitted light.
    Dielectric { ior: f32, tint: Vec3 },
    /// A light-emitting surface (front face only), black otherwise.
    Emissive { radiance: Vec3 },
}

impl Material {
    pub fn lambertian(albedo: Vec3) -> Self {
        Material::Lambertian { albedo }
    }
    pub fn glossy(albedo: Vec3, specular: Vec3, roughness: f32) -> Self {
        Material::Glossy { albedo, specular, roughness }
    }
    pub fn metal(color: Vec3, roughness: f32) -> Self {
        Material::Glossy { albedo: Vec3::ZERO, specular: color, roughness }
    }
    pub fn glass(ior: f32, tint: Vec3) -> Self {
        Material::Dielectric { ior, tint }
    }
    pub fn emissive(radiance: Vec3) -> Self {
        Material::Emissive { radiance }
    }
    /// Checks the parameters are physically plausible (energy conserving, finite).
    pub fn validate(&self) -> Result<(), String> {
        let unit = |v: Vec3| v.is_finite() && v.min_element() >= 0.0 && v.max_element() <= 1.0;
        match *self {
            Material::Lambertian { albedo } if !unit(albedo) => Err(format!("albedo {albedo} must lie in [0, 1]")),
            Material::Glossy { albedo, specular, roughness } => {
                if !unit(albedo) || !unit(specular) {
                    Err(format!("albedo {albedo} and specular {specular} must lie in [0, 1]"))
                } else if !(roughness.is_finite() && (0.0..=1.0).contains(&roughness)) {
                    Err(format!("roughness {roughness} must lie in [0, 1]"))
                } else {
                    Ok(())
                }
            }
            Material::Dielectric { ior, tint } => {
                if !(ior.is_finite() && ior >= 1.0) {
                    Err(format!("index of refraction {ior} must be >= 1"))
                } else if !unit(tint) {
                    Err(format!("tint {tint} must lie in [0, 1]"))
                } else {
                    Ok(())
                }
            }
            Material::Emissive { radiance } if !(radiance.is_finite() && radiance.min_element() >= 0.0) => {
                Err(format!("emitted radiance {radiance} must be finite and >= 0"))
            }
            _ => Ok(()),
        }
    }
}

/// Result of sampling a non-delta BSDF, in the local shading frame (+z = normal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BsdfSample {
    /// Incident direction (pointing away from the surface).
    pub wi: Vec3,
    /// `f * cos(theta_i) / pdf`: what the path throughput is multiplied by.
    pub weight: Vec3,
    /// Solid-angle density of `wi` under the full (all lobes) sampling strategy.
    pub pdf: f32,
}

/// What a dielectric interface did to a ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DielectricEvent {
    Reflect,
    Refract { eta: f32 },
}

const MIN_ALPHA: f32 = 1e-3;

impl Material {
    /// True for materials whose BSDF is not a delta distribution (next-event estimation works).
    pub fn is_smooth_delta(&self) -> bool {
        matches!(self, Material::Dielectric { .. })
    }

    /// The colour written to the albedo output.
    pub fn albedo(&self) -> Vec3 {
        match *self {
            Material::Lambertian { albedo } => albedo,
            Material::Glossy { albedo, specular, .. } => (albedo + specular).min(Vec3::ONE),
            Material::Dielectric { tint, .. } => tint,
            Material::Emissive { .. } => Vec3::ZERO,
        }
    }

    /// BSDF value and sampling density for local directions `wo`, `wi` (both pointing away).
    /// Delta and emissive materials return zero.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return (Vec3::ZERO, 0.0);
        }
        match *self {
            Material::Lambertian { albedo } => (albedo * FRAC_1_PI, wi.z * FRAC_1_PI),
            Material::Glossy { albedo, specular, roughness } => {
                let lobe = GlossyLobes::new(albedo, specular, roughness, wo);
                let h = (wo + wi).normalize();
                let d = ggx_d(h, lobe.alpha);
                let f_spec = schlick(specular, wi.dot(h)) * d * ggx_g2(wo, wi, lobe.alpha) / (4.0 * wo.z * wi.z);
                let f = lobe.diffuse * FRAC_1_PI + f_spec;
                let pdf_spec = ggx_g1(wo, lobe.alpha) * d / (4.0 * wo.z);
                let pdf = lobe.p_specular * pdf_spec + (1.0 - lobe.p_specular) * wi.z * FRAC_1_PI;
                (f, pdf)
            }
            Material::Dielectric { .. } | Material::Emissive { .. } => (Vec3::ZERO, 0.0),
        }
    }

    /// Samples an incident direction for outgoing `wo` (local frame). `None` for delta and
    /// emissive materials, and when the sample falls below the surface.
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: glam::Vec2) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let wi = match *self {
            Material::Lambertian { .. } => super::sampling::cosine_hemisphere(u),
            Material::Glossy { albedo, specular, roughness } => {
                let lobe = GlossyLobes::new(albedo, specular, roughness, wo);
                if u_lobe < lobe.p_specular {
                    let h = ggx_sample_visible_normal(wo, lobe.alpha, u);
                    reflect(wo, h)
                } else {
                    super::sampling::cosine_hemisphere(u)
                }
            }
            Material::Dielectric { .. } | Material::Emissive { .. } => return None,
        };
        if wi.z <= 0.0 {
            return None;
        }
        let (f, pdf) = self.eval(wo, wi);
        if !(pdf > 0.0) || !pdf.is_finite() {
            return None;
        }
        let weight = f * wi.z / pdf;
        weight.is_finite().then_some(BsdfSample { wi, weight, pdf })
    }
}

/// The Lambertian base and specular-lobe choice of a glossy material seen from `wo`.
struct GlossyLobes {
    alpha: f32,
    diffuse: Vec3,
    p_specular: f32,
}

impl GlossyLobes {
    fn new(albedo: Vec3, specular: Vec3, roughness: f32, wo: Vec3) -> Self {
        let alpha = (roughness * roughness).max(MIN_ALPHA);
        let fresnel_out = schlick(specular, wo.z);
        // Light reflected by the coat never reaches the base.
        let diffuse = albedo * (1.0 - fresnel_out.max_element());
        let spec_weight = luminance(fresnel_out);
        let diff_weight = luminance(diffuse);
        let p_specular =
            if diff_weight <= 0.0 { 1.0 } else { (spec_weight / (spec_weight + diff_weight)).clamp(0.1, 0.9) };
        GlossyLobes { alpha, diffuse, p_specular }
    }
}

pub fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.2126, 0.7152, 0.0722))
}

fn reflect(wo: Vec3, h: Vec3) -> Vec3 {
    2.0 * wo.dot(h) * h - wo
}

fn schlick(f0: Vec3, cos_theta: f32) -> Vec3 {
    let m = (1.0 - cos_theta.clamp(0.0, 1.0)).powi(5);
    f0 + (Vec3::ONE - f0) * m
}

/// GGX normal distribution (Walter et al. 2007).
fn ggx_d(h: Vec3, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    let c2 = h.z * h.z;
    let denom = c2 * (a2 - 1.0) + 1.0;
    a2 / (PI * denom * denom)
}

/// Smith's Lambda for GGX.
fn ggx_lambda(w: Vec3, alpha: f32) -> f32 {
    let c2 = w.z * w.z;
    if c2 <= 0.0 {
        return f32::INFINITY;
    }
    let tan2 = (1.0 - c2).max(0.0) / c2;
    (-1.0 + (1.0 + alpha * alpha * tan2).sqrt()) * 0.5
}

fn ggx_g1(w: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(w, alpha))
}

/// Height-correlated Smith masking-shadowing.
fn ggx_g2(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))
}

/// Samples a microfacet normal from the distribution of normals visible from `wo`
/// (Heitz 2018, "Sampling the GGX Distribution of Visible Normals").
fn ggx_sample_visible_normal(wo: Vec3, alpha: f32, u: glam::Vec2) -> Vec3 {
    let vh = Vec3::new(alpha * wo.x, alpha * wo.y, wo.z).normalize();
    let len2 = vh.x * vh.x + vh.y * vh.y;
    let t1 = if len2 > 0.0 { Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt() } else { Vec3::X };
    let t2 = vh.cross(t1);
    let r = u.x.sqrt();
    let phi = 2.0 * PI * u.y;
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
    let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(1e-6)).normalize()
}

/// Unpolarised Fresnel reflectance of a dielectric interface; `eta` = n_incident / n_transmitted,
/// `cos_i` the cosine on the incident side. Returns 1 under total internal reflection.
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_t = eta * eta * (1.0 - cos_i * cos_i);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (rs * rs + rp * rp)
}

/// Direction refracted through a surface with unit normal `n` on the incident side
/// (`dot(d, n) < 0`), for `eta` = n_incident / n_transmitted; `None` under total internal
/// reflection.
pub fn refract(d: Vec3, n: Vec3, eta: f32) -> Option<Vec3> {
    let cos_i = -d.dot(n);
    let sin2_t = eta * eta * (1.0 - cos_i * cos_i).max(0.0);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some((eta * d + (eta * cos_i - cos_t) * n).normalize())
}

use std::f32::consts::{FRAC_1_PI, PI};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{Rng, UNIFORM_SPHERE_PDF, uniform_sphere};

    fn materials() -> Vec<Material> {
        vec![
            Material::lambertian(Vec3::new(0.8, 0.5, 0.2)),
            Material::glossy(Vec3::new(0.6, 0.2, 0.2), Vec3::splat(0.04), 0.2),
            Material::glossy(Vec3::splat(0.5), Vec3::splat(0.04), 0.9),
            Material::metal(Vec3::new(0.95, 0.8, 0.5), 0.05),
            Material::metal(Vec3::splat(1.0), 0.5),
        ]
    }

    #[test]
    fn pdfs_integrate_to_at_most_one_and_sampling_agrees_with_eval() {
        let mut rng = Rng::new(3, 5);
        for m in materials() {
            for wo in [Vec3::Z, Vec3::new(0.6, 0.0, 0.8), Vec3::new(-0.1, 0.97, 0.2).normalize()] {
                // Integral of the pdf over the sphere (uniform sampling): 1 up to the part of
                // specular mass that would fall below the horizon.
                let n = 200_000;
                let integral: f32 =
                    (0..n).map(|_| m.eval(wo, uniform_sphere(rng.next_vec2())).1 / UNIFORM_SPHERE_PDF).sum::<f32>()
                        / n as f32;
                // Uniform sampling cannot resolve a very sharp lobe; check the broad ones.
                let broad = !matches!(m, Material::Glossy { roughness, .. } if roughness < 0.15);
                if broad {
                    assert!(integral <= 1.03 && integral > 0.7, "{m:?} {wo}: {integral}");
                }
                // Directional albedo by importance sampling: energy conservation.
                let albedo: Vec3 = (0..n)
                    .filter_map(|_| m.sample(wo, rng.next_f32(), rng.next_vec2()))
                    .map(|s| {
                        let (f, pdf) = m.eval(wo, s.wi);
                        assert!((pdf - s.pdf).abs() <= 1e-3 * pdf.max(1.0), "{pdf} {}", s.pdf);
                        assert!(
                            ((f * s.wi.z / pdf) - s.weight).abs().max_element()
                                < 1e-3 * s.weight.max_element().max(1.0)
                        );
                        s.weight
                    })
                    .sum::<Vec3>()
                    / n as f32;
                assert!(albedo.max_element() <= 1.01, "{m:?} {wo}: albedo {albedo}");
            }
        }
    }

    #[test]
    fn lambertian_white_reflects_everything() {
        let m = Material::lambertian(Vec3::ONE);
        let mut rng = Rng::new(1, 2);
        let wo = Vec3::new(0.3, 0.4, 0.866).normalize();
        let n = 10_000;
        let albedo: Vec3 =
            (0..n).filter_map(|_| m.sample(wo, 0.5, rng.next_vec2())).map(|s| s.weight).sum::<Vec3>() / n as f32;
        assert!((albedo - Vec3::ONE).abs().max_element() < 1e-4, "{albedo}");
    }

    #[test]
    fn fresnel_and_refraction_obey_snell() {
        assert!((fresnel_dielectric(1.0, 1.0 / 1.5) - 0.04).abs() < 1e-4);
        assert_eq!(fresnel_dielectric(0.1, 1.5), 1.0, "total internal reflection");
        let d = Vec3::new(0.5, 0.0, -0.866_025_4);
        let t = refract(d, Vec3::Z, 1.0 / 1.5).expect("refracts");
        let sin_i = 0.5;
        let sin_t = (t.x * t.x + t.y * t.y).sqrt();
        assert!((sin_i - 1.5 * sin_t).abs() < 1e-5);
        assert!(refract(Vec3::new(0.9, 0.0, -0.436).normalize(), Vec3::Z, 1.5).is_none());
    }

    #[test]
    fn validation_rejects_bad_parameters() {
        assert!(Material::lambertian(Vec3::splat(1.2)).validate().is_err());
        assert!(Material::glossy(Vec3::ONE, Vec3::ONE, f32::NAN).validate().is_err());
        assert!(Material::glass(0.5, Vec3::ONE).validate().is_err());
        assert!(Material::emissive(Vec3::splat(-1.0)).validate().is_err());
        assert!(Material::emissive(Vec3::splat(10.0)).validate().is_ok());
    }
}
