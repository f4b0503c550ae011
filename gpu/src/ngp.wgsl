// The i-NGP-style baseline (a radiance field volume-rendered through its occupancy grid),
// one invocation per pixel: the GPU twin of `nephele_kernels::ngp::NgpKernel` (CPU):
// `Marcher` (samples on a grid of t, empty blocks and cells skipped), `HashGrid::encode`,
// the density MLP, the colour MLP where the blending weight matters, early stop, and the
// conversion to linear premultiplied colour and view depth. Both networks' weights are read
// from a storage buffer (they are too large for workgroup memory).
//
// The host prepends `common.wgsl` and the sizes as constants: LEVELS, ENC (= 2 LEVELS),
// D_HIDDEN, D_OUT (1 + geometric features), C_IN (D_OUT + SH_COUNT), C_HIDDEN, C_LAYERS,
// SH_COUNT, C_OFFSET (first colour-network weight).

struct Params {
    camera: Camera,
    // Field box: min xyz, side w.
    box_min: vec4<f32>,
    dt: f32,
    occupancy_resolution: u32,
    fine_offset: u32,   // words in `occupancy`
    coarse_offset: u32,
    level_offset: u32,  // 5 words per level: scale bits, resolution, first entry, entries, dense
    early_stop: f32,
    min_color_weight: f32,
    pad: u32,
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> pixels: array<u32>;
@group(0) @binding(2) var<storage, read> occupancy: array<u32>;
@group(0) @binding(3) var<storage, read> grid: array<f32>;
@group(0) @binding(4) var<storage, read> mlp: array<f32>;
// Per pixel: r, g, b, opacity, depth, samples.
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

const BIG: f32 = 3.0e38;
const OCC_BLOCK: u32 = 8u;

fn bit(offset: u32, index: u32) -> bool {
    return ((occupancy[offset + (index >> 5u)] >> (index & 31u)) & 1u) == 1u;
}

// `Marcher::exit`: t at which the ray (unit-cube origin o, direction d) leaves the cell of
// side 1 / cells holding p.
fn cell_exit(o: vec3<f32>, d: vec3<f32>, p: vec3<f32>, cells: f32) -> f32 {
    var t_exit = BIG;
    for (var a = 0; a < 3; a++) {
        if d[a] == 0.0 {
            continue;
        }
        let c = floor(p[a] * cells);
        var boundary = c / cells;
        if d[a] > 0.0 {
            boundary = (c + 1.0) / cells;
        }
        t_exit = min(t_exit, (boundary - o[a]) / d[a]);
    }
    return t_exit;
}

// `HashGrid::encode` of a unit-cube point.
fn encode(p: vec3<f32>) -> array<f32, ENC> {
    var enc = array<f32, ENC>();
    let q = clamp(p, vec3<f32>(0.0), vec3<f32>(1.0));
    for (var l = 0u; l < LEVELS; l++) {
        let base_word = params.level_offset + 5u * l;
        let scale = bitcast<f32>(occupancy[base_word]);
        let resolution = occupancy[base_word + 1u];
        let first = occupancy[base_word + 2u];
        let size = occupancy[base_word + 3u];
        let dense = occupancy[base_word + 4u] != 0u;
        let x = q * scale + vec3<f32>(0.5);
        let f = floor(x);
        let b = vec3<u32>(f);
        let frac = x - f;
        var f0 = 0.0;
        var f1 = 0.0;
        for (var c = 0u; c < 8u; c++) {
            var w = 1.0;
            var v = b;
            for (var d = 0u; d < 3u; d++) {
                if (c & (1u << d)) != 0u {
                    w *= frac[d];
                    v[d] = b[d] + 1u;
                } else {
                    w *= 1.0 - frac[d];
                }
            }
            var index: u32;
            if dense {
                index = v.x + resolution * (v.y + resolution * v.z);
            } else {
                index = (v.x ^ (v.y * 2654435761u) ^ (v.z * 805459861u)) & (size - 1u);
            }
            let e = (first + index) * 2u;
            f0 += w * grid[e];
            f1 += w * grid[e + 1u];
        }
        enc[2u * l] = f0;
        enc[2u * l + 1u] = f1;
    }
    return enc;
}

// The density MLP: ENC -> D_HIDDEN (ReLU) -> D_OUT (raw).
fn density_mlp(x: ptr<function, array<f32, ENC>>) -> array<f32, D_OUT> {
    var h = array<f32, D_HIDDEN>();
    for (var o = 0u; o < D_HIDDEN; o++) {
        var acc = mlp[ENC * D_HIDDEN + o];
        for (var k = 0u; k < ENC; k++) {
            acc += (*x)[k] * mlp[k * D_HIDDEN + o];
        }
        h[o] = max(acc, 0.0);
    }
    let off = ENC * D_HIDDEN + D_HIDDEN;
    var y = array<f32, D_OUT>();
    for (var o = 0u; o < D_OUT; o++) {
        var acc = mlp[off + D_HIDDEN * D_OUT + o];
        for (var k = 0u; k < D_HIDDEN; k++) {
            acc += h[k] * mlp[off + k * D_OUT + o];
        }
        y[o] = acc;
    }
    return y;
}

// The colour MLP: C_IN -> C_HIDDEN (ReLU) x C_LAYERS -> 3 (sigmoid).
fn color_mlp(x: ptr<function, array<f32, C_IN>>) -> vec3<f32> {
    var out3 = vec3<f32>(0.0);
    if C_LAYERS == 0u {
        for (var o = 0u; o < 3u; o++) {
            var acc = mlp[C_OFFSET + C_IN * 3u + o];
            for (var k = 0u; k < C_IN; k++) {
                acc += (*x)[k] * mlp[C_OFFSET + k * 3u + o];
            }
            out3[o] = sigmoid(acc);
        }
        return out3;
    }
    var a = array<f32, C_HIDDEN>();
    var b = array<f32, C_HIDDEN>();
    var off = C_OFFSET;
    for (var o = 0u; o < C_HIDDEN; o++) {
        var acc = mlp[off + C_IN * C_HIDDEN + o];
        for (var k = 0u; k < C_IN; k++) {
            acc += (*x)[k] * mlp[off + k * C_HIDDEN + o];
        }
        a[o] = max(acc, 0.0);
    }
    off += C_IN * C_HIDDEN + C_HIDDEN;
    for (var layer = 1u; layer < C_LAYERS; layer++) {
        for (var o = 0u; o < C_HIDDEN; o++) {
            var acc = mlp[off + C_HIDDEN * C_HIDDEN + o];
            for (var k = 0u; k < C_HIDDEN; k++) {
                acc += a[k] * mlp[off + k * C_HIDDEN + o];
            }
            b[o] = max(acc, 0.0);
        }
        a = b;
        off += C_HIDDEN * C_HIDDEN + C_HIDDEN;
    }
    for (var o = 0u; o < 3u; o++) {
        var acc = mlp[off + C_HIDDEN * 3u + o];
        for (var k = 0u; k < C_HIDDEN; k++) {
            acc += a[k] * mlp[off + k * 3u + o];
        }
        out3[o] = sigmoid(acc);
    }
    return out3;
}

fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        return v / 12.92;
    }
    return pow((v + 0.055) / 1.055, 2.4);
}

fn write(i: u32, c: vec3<f32>, a: f32, depth: f32, samples: u32) {
    out[i * 6u + 0u] = c.x;
    out[i * 6u + 1u] = c.y;
    out[i * 6u + 2u] = c.z;
    out[i * 6u + 3u] = a;
    out[i * 6u + 4u] = depth;
    out[i * 6u + 5u] = f32(samples);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.y * groups.x * WORKGROUP + gid.x;
    if i >= params.camera.pixel_count {
        return;
    }
    let ray = camera_ray(params.camera, pixels[i]);
    let box_min = params.box_min.xyz;
    let size = params.box_min.w;
    let box_max = box_min + vec3<f32>(size);

    // `ray_box`: entry and exit; a miss unless t0 <= t1, t1 >= 0 and t1 finite.
    var t0 = -BIG;
    var t1 = BIG;
    for (var a = 0; a < 3; a++) {
        let o = ray.origin[a];
        let d = ray.dir[a];
        if d == 0.0 {
            if o < box_min[a] || o > box_max[a] {
                write(i, vec3<f32>(0.0), 0.0, 0.0, 0u);
                return;
            }
            continue;
        }
        let inv = 1.0 / d;
        let ta = (box_min[a] - o) * inv;
        let tb = (box_max[a] - o) * inv;
        t0 = max(t0, min(ta, tb));
        t1 = min(t1, max(ta, tb));
    }
    let dt = params.dt;
    let start = max(t0, 0.0);
    if !(t0 <= t1 && t1 >= 0.0 && t1 < BIG) || start >= t1 {
        write(i, vec3<f32>(0.0), 0.0, 0.0, 0u);
        return;
    }
    // Samples at t = (k + 1/2) dt (`Marcher::new` with offset 0.5).
    var t = (ceil(start / dt - 0.5) + 0.5) * dt;
    let o = (ray.origin - box_min) / size;
    let d = ray.dir / size;
    let r = f32(params.occupancy_resolution);
    let max_cell = params.occupancy_resolution - 1u;
    let blocks = params.occupancy_resolution / OCC_BLOCK;

    let sh = sh_values(ray.dir);
    var transmittance = 1.0;
    var color = vec3<f32>(0.0);
    var opacity = 0.0;
    var weighted_t = 0.0;
    var samples = 0u;
    loop {
        if !(t < t1) {
            break;
        }
        let p = o + t * d;
        let c = floor(p * r);
        let cell = min(vec3<u32>(max(c, vec3<f32>(0.0))), vec3<u32>(max_cell));
        let bc = cell / OCC_BLOCK;
        let block = bc.x + blocks * (bc.y + blocks * bc.z);
        var skip_cells = 0.0;
        if !bit(params.coarse_offset, block) {
            skip_cells = r / f32(OCC_BLOCK);
        } else if !bit(params.fine_offset, cell.x + params.occupancy_resolution * (cell.y + params.occupancy_resolution * cell.z)) {
            skip_cells = r;
        }
        if skip_cells > 0.0 {
            // `Marcher::skip_to`: at least one step, onto the sample grid.
            let t_exit = cell_exit(o, d, clamp(p, vec3<f32>(0.0), vec3<f32>(1.0)), skip_cells);
            t += max(ceil((t_exit - t) / dt), 1.0) * dt;
            continue;
        }
        let ts = t;
        t += dt;
        samples += 1u;
        var enc = encode(p);
        let geo = density_mlp(&enc);
        let sigma = exp(min(geo[0], 15.0));
        let alpha = 1.0 - exp(-sigma * dt);
        let w = transmittance * alpha;
        transmittance *= 1.0 - alpha;
        if w >= params.min_color_weight {
            var x = array<f32, C_IN>();
            for (var k = 0u; k < D_OUT; k++) {
                x[k] = geo[k];
            }
            for (var k = 0u; k < SH_COUNT; k++) {
                x[D_OUT + k] = sh[k];
            }
            color += w * color_mlp(&x);
        }
        opacity += w;
        weighted_t += w * ts;
        if transmittance < params.early_stop {
            break;
        }
    }
    opacity = clamp(opacity, 0.0, 1.0);
    var distance = 0.0;
    if opacity > 0.0 {
        distance = weighted_t / opacity;
    }
    if !(is_finite(color.x) && is_finite(color.y) && is_finite(color.z) && is_finite(distance)) || !(opacity > 0.0) {
        write(i, vec3<f32>(0.0), 0.0, 0.0, samples);
        return;
    }
    // The field composites sRGB-encoded colour; the farm wants linear, premultiplied.
    let straight = clamp(color / opacity, vec3<f32>(0.0), vec3<f32>(1.0));
    let linear = opacity * vec3<f32>(srgb_to_linear(straight.x), srgb_to_linear(straight.y), srgb_to_linear(straight.z));
    let depth = distance * depth_per_distance(params.camera, ray.dir);
    if !(is_finite(depth) && depth > 0.0) {
        write(i, vec3<f32>(0.0), 0.0, 0.0, samples);
        return;
    }
    write(i, linear, opacity, depth, samples);
}
