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
            Material::Lambertian { albedo } if !unit(albedo) => {
                Err(format!("albedo {albedo} must lie in [0, 1]"))
            }
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
            Material::Emissive { radiance }
                if !(radiance.is_finite() && radiance.min_element() >= 0.0) =>
            {
                Err(format!("emitted radiance {radiance} must be finite and >= 0"))
            }
            _ => Ok(()),
        }
    }
}
