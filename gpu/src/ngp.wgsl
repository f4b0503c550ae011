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
//
// Loop trip counts are kept low on purpose: Mesa's llvmpipe (the software Vulkan CI runs on)
// ends every loop of an invocation once 65535 iterations have run in all loops together
// (`LP_MAX_TGSI_LOOP_ITERATIONS`, shared by every loop of a shader). The MLP layers work on
// four outputs and eight inputs per iteration and the hash-grid corners are written out, so
// with the default sizes a coloured sample costs about 250 iterations and a ray can take some
// 250 coloured samples before the cap; real GPUs have no such cap.

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
// `march::advance`: `t + by` for `t >= 0`, but at least one float step past `t` (far from the
// box a step can be below half a float step of `t`).
fn advance(t: f32, by: f32) -> f32 {
    let next = t + by;
    return select(bitcast<f32>(bitcast<u32>(t) + 1u), next, next > t);
}

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

// One private array holds every activation: the hash encoding, the density network's
// hidden layer, the colour network's input (geometric features, then SH), its two hidden
// buffers and its output. Arrays live in `main` and go by pointer.
const A_ENC: u32 = 0u;
const A_H: u32 = A_ENC + ENC;
const A_CIN: u32 = A_H + D_HIDDEN;
const A_CA: u32 = A_CIN + C_IN;
const A_CB: u32 = A_CA + C_HIDDEN;
const A_COUT: u32 = A_CB + C_HIDDEN;
const ACT: u32 = A_COUT + 4u;

// `HashGrid::encode` of a unit-cube point into act[A_ENC..].
fn encode(p: vec3<f32>, act: ptr<function, array<f32, ACT>>) {
    let q = clamp(p, vec3<f32>(0.0), vec3<f32>(1.0));
    for (var l = 0u; l < LEVELS; l++) {
        let base_word = params.level_offset + 5u * l;
        let scale = bitcast<f32>(occupancy[base_word]);
        let resolution = occupancy[base_word + 1u];
        let first = occupancy[base_word + 2u];
        let size = occupancy[base_word + 3u];
        let dense = occupancy[base_word + 4u] != 0u;
        let x = q * scale + vec3<f32>(0.5);
        let fl = floor(x);
        let b = vec3<u32>(fl);
        let frac = x - fl;
        let level = Level(b, frac, resolution, first, size, dense);
        // The eight corners written out (no loop: see the trip-count note above).
        let f = corner(level, 0u) + corner(level, 1u) + corner(level, 2u) + corner(level, 3u)
            + corner(level, 4u) + corner(level, 5u) + corner(level, 6u) + corner(level, 7u);
        (*act)[A_ENC + 2u * l] = f.x;
        (*act)[A_ENC + 2u * l + 1u] = f.y;
    }
}

struct Level {
    base: vec3<u32>,
    frac: vec3<f32>,
    resolution: u32,
    first: u32,
    size: u32,
    dense: bool,
};

// Weighted features of corner c (bit d set: +1 along axis d) of a level's cell.
fn corner(l: Level, c: u32) -> vec2<f32> {
    let up = vec3<u32>(c & 1u, (c >> 1u) & 1u, (c >> 2u) & 1u);
    let v = l.base + up;
    let wv = select(vec3<f32>(1.0) - l.frac, l.frac, up == vec3<u32>(1u));
    let w = wv.x * wv.y * wv.z;
    var index: u32;
    if l.dense {
        index = v.x + l.resolution * (v.y + l.resolution * v.z);
    } else {
        index = (v.x ^ (v.y * 2654435761u) ^ (v.z * 805459861u)) & (l.size - 1u);
    }
    let e = (l.first + index) * 2u;
    return w * vec2<f32>(grid[e], grid[e + 1u]);
}

fn row4(i: u32) -> vec4<f32> {
    return vec4<f32>(mlp[i], mlp[i + 1u], mlp[i + 2u], mlp[i + 3u]);
}

// One layer of `nephele_nn::Mlp` (weights input-major, w[k * n_out + o], then the bias):
// act[y0..y0 + n_out] = act(W^T act[x0..x0 + n_in] + b), four outputs and eight inputs per
// iteration (four inputs for the last outputs when n_out is not a multiple of four).
fn layer(act: ptr<function, array<f32, ACT>>, x0: u32, n_in: u32, y0: u32, n_out: u32, w0: u32, relu: bool) {
    let bias = w0 + n_in * n_out;
    var o = 0u;
    loop {
        if o + 4u > n_out {
            break;
        }
        var acc = row4(bias + o);
        var k = 0u;
        loop {
            if k + 8u > n_in {
                break;
            }
            let r = w0 + k * n_out + o;
            let n = n_out;
            acc += (*act)[x0 + k] * row4(r) + (*act)[x0 + k + 1u] * row4(r + n)
                + (*act)[x0 + k + 2u] * row4(r + 2u * n) + (*act)[x0 + k + 3u] * row4(r + 3u * n)
                + (*act)[x0 + k + 4u] * row4(r + 4u * n) + (*act)[x0 + k + 5u] * row4(r + 5u * n)
                + (*act)[x0 + k + 6u] * row4(r + 6u * n) + (*act)[x0 + k + 7u] * row4(r + 7u * n);
            k += 8u;
        }
        loop {
            if k >= n_in {
                break;
            }
            acc += (*act)[x0 + k] * row4(w0 + k * n_out + o);
            k += 1u;
        }
        if relu {
            acc = max(acc, vec4<f32>(0.0));
        }
        (*act)[y0 + o] = acc.x;
        (*act)[y0 + o + 1u] = acc.y;
        (*act)[y0 + o + 2u] = acc.z;
        (*act)[y0 + o + 3u] = acc.w;
        o += 4u;
    }
    loop {
        if o >= n_out {
            break;
        }
        var acc = mlp[bias + o];
        var k = 0u;
        loop {
            if k + 4u > n_in {
                break;
            }
            let r = w0 + k * n_out + o;
            acc += (*act)[x0 + k] * mlp[r] + (*act)[x0 + k + 1u] * mlp[r + n_out]
                + (*act)[x0 + k + 2u] * mlp[r + 2u * n_out] + (*act)[x0 + k + 3u] * mlp[r + 3u * n_out];
            k += 4u;
        }
        loop {
            if k >= n_in {
                break;
            }
            acc += (*act)[x0 + k] * mlp[w0 + k * n_out + o];
            k += 1u;
        }
        if relu {
            acc = max(acc, 0.0);
        }
        (*act)[y0 + o] = acc;
        o += 1u;
    }
}

// The density MLP: ENC -> D_HIDDEN (ReLU) -> D_OUT (raw), its output written where the
// colour network reads it.
fn density_mlp(act: ptr<function, array<f32, ACT>>) {
    layer(act, A_ENC, ENC, A_H, D_HIDDEN, 0u, true);
    layer(act, A_H, D_HIDDEN, A_CIN, D_OUT, ENC * D_HIDDEN + D_HIDDEN, false);
}

// The colour MLP: C_IN -> C_HIDDEN (ReLU) x C_LAYERS -> 3 (sigmoid).
fn color_mlp(act: ptr<function, array<f32, ACT>>) -> vec3<f32> {
    var src = A_CIN;
    var n_in = C_IN;
    var w = C_OFFSET;
    var dst = A_CA;
    for (var l = 0u; l < C_LAYERS; l++) {
        layer(act, src, n_in, dst, C_HIDDEN, w, true);
        w += n_in * C_HIDDEN + C_HIDDEN;
        src = dst;
        n_in = C_HIDDEN;
        dst = select(A_CA, A_CB, dst == A_CA);
    }
    layer(act, src, n_in, A_COUT, 3u, w, false);
    return vec3<f32>(sigmoid((*act)[A_COUT]), sigmoid((*act)[A_COUT + 1u]), sigmoid((*act)[A_COUT + 2u]));
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
    // `marchable_direction`: components under 1e-20 count as 0 (camera rays are unit length).
    let dir = select(ray.dir, vec3<f32>(0.0), abs(ray.dir) < vec3<f32>(1e-20));

    // `ray_box`: entry and exit; a miss unless t0 <= t1, t1 >= 0 and t1 finite.
    var t0 = -BIG;
    var t1 = BIG;
    for (var a = 0; a < 3; a++) {
        let o = ray.origin[a];
        let d = dir[a];
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
    let d = dir / size;
    let r = f32(params.occupancy_resolution);
    let max_cell = params.occupancy_resolution - 1u;
    let blocks = params.occupancy_resolution / OCC_BLOCK;

    var act = array<f32, ACT>();
    // The direction's SH: the colour input's tail, the same for every sample.
    let sh = sh_values(ray.dir);
    for (var k = 0u; k < SH_COUNT; k++) {
        act[A_CIN + D_OUT + k] = sh[k];
    }
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
            t = advance(t, max(ceil((t_exit - t) / dt), 1.0) * dt);
            continue;
        }
        let ts = t;
        t = advance(t, dt);
        samples += 1u;
        encode(p, &act);
        density_mlp(&act);
        let sigma = exp(min(act[A_CIN], 15.0));
        let alpha = 1.0 - exp(-sigma * dt);
        let w = transmittance * alpha;
        transmittance *= 1.0 - alpha;
        if w >= params.min_color_weight {
            color += w * color_mlp(&act);
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
