// Shared by every kernel shader (the host prepends it): the camera as the kernels receive
// it, the pixel-centre ray (`nephele_geometry::camera::Camera::pixel_center_ray`), view
// depth, a finiteness test and real spherical harmonics (`nephele_nn::sh_encode`).

const WORKGROUP: u32 = 64u;

struct Camera {
    // Columns of camera-to-world (x, y, z axes, then the eye) and the third row of
    // world-to-camera (view depth = -(row . p)).
    c2w_x: vec4<f32>,
    c2w_y: vec4<f32>,
    c2w_z: vec4<f32>,
    eye: vec4<f32>,
    w2c_row_z: vec4<f32>,
    // fx, fy, cx, cy
    intrinsics: vec4<f32>,
    width: u32,
    pixel_count: u32,
    pad0: u32,
    pad1: u32,
};

struct Ray {
    origin: vec3<f32>,
    dir: vec3<f32>,
};

fn is_finite(x: f32) -> bool {
    // A bit test: compilers may assume no NaN or infinity in float comparisons.
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// The ray through the centre of pixel `y * width + x`, unit direction.
fn camera_ray(camera: Camera, pixel: u32) -> Ray {
    let px = f32(pixel % camera.width) + 0.5;
    let py = f32(pixel / camera.width) + 0.5;
    let k = camera.intrinsics;
    let d = vec3<f32>((px - k.z) / k.x, -(py - k.w) / k.y, -1.0);
    let world = camera.c2w_x.xyz * d.x + camera.c2w_y.xyz * d.y + camera.c2w_z.xyz * d.z;
    return Ray(camera.eye.xyz, normalize(world));
}

// View-space depth of a world point (positive in front of the camera).
fn view_depth(camera: Camera, p: vec3<f32>) -> f32 {
    return -(dot(camera.w2c_row_z.xyz, p) + camera.w2c_row_z.w);
}

// Depth per unit of distance along a world direction.
fn depth_per_distance(camera: Camera, dir: vec3<f32>) -> f32 {
    return -dot(camera.w2c_row_z.xyz, dir);
}

// Real spherical harmonics up to degree 5 (25 values) of a direction, normalised first
// (a zero or non-finite direction counts as +z).
fn sh_values(dir: vec3<f32>) -> array<f32, 25> {
    let len = length(dir);
    var x = 0.0;
    var y = 0.0;
    var z = 1.0;
    if is_finite(len) && len > 1e-20 {
        x = dir.x / len;
        y = dir.y / len;
        z = dir.z / len;
    }
    let x2 = x * x;
    let y2 = y * y;
    let z2 = z * z;
    var sh = array<f32, 25>();
    sh[0] = 0.2820948;
    sh[1] = -0.48860252 * y;
    sh[2] = 0.48860252 * z;
    sh[3] = -0.48860252 * x;
    sh[4] = 1.0925484 * x * y;
    sh[5] = -1.0925484 * y * z;
    sh[6] = 0.9461747 * z2 - 0.31539157;
    sh[7] = -1.0925484 * x * z;
    sh[8] = 0.5462742 * (x2 - y2);
    sh[9] = 0.5900436 * y * (-3.0 * x2 + y2);
    sh[10] = 2.8906114 * x * y * z;
    sh[11] = 0.4570458 * y * (1.0 - 5.0 * z2);
    sh[12] = 0.37317633 * z * (5.0 * z2 - 3.0);
    sh[13] = 0.4570458 * x * (1.0 - 5.0 * z2);
    sh[14] = 1.4453057 * z * (x2 - y2);
    sh[15] = 0.5900436 * x * (-x2 + 3.0 * y2);
    sh[16] = 2.503343 * x * y * (x2 - y2);
    sh[17] = 1.7701308 * y * z * (-3.0 * x2 + y2);
    sh[18] = 0.9461747 * x * y * (7.0 * z2 - 1.0);
    sh[19] = 0.6690465 * y * z * (7.0 * z2 - 3.0);
    sh[20] = -3.1735664 * z2 + 3.702494 * z2 * z2 + 0.31735664;
    sh[21] = 0.6690465 * x * z * (7.0 * z2 - 3.0);
    sh[22] = 0.47308734 * (x2 - y2) * (7.0 * z2 - 1.0);
    sh[23] = 1.7701308 * x * z * (-x2 + 3.0 * y2);
    sh[24] = -3.7550144 * x2 * y2 + 0.6258357 * x2 * x2 + 0.6258357 * y2 * y2;
    return sh;
}

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}
