// i-NOLF inference, one invocation per pixel: the GPU twin of
// `nephele_kernels::inolf::kernel::InolfKernel::render_chunk` (CPU) and of
// `DensityCubes::march` (NEPHELE section 4.1, eq. 4), `PshEncoding::encode` (section 4.2),
// `sh_encode`, `SparseCubes::sample` and `combine` (eq. 7). Every step mirrors the CPU code
// line by line so that the two agree to rounding; the tests in `src/tests.rs` hold them to it.
//
// The host prepends `common.wgsl` (camera, rays, SH) and the sizes of the asset's specular
// MLP as constants:
//   S_IN, S_HIDDEN, S_LAYERS (hidden layers), S_OUT_ACT (activation code), S_PARAMS,
//   PSH_DIM, SH_COUNT; and MAX_BLEND_SAMPLES (`cubes::MAX_BLEND_SAMPLES`).
//
// Tables arrive as arrays of u32 (bytes packed four to a word, floats as bit patterns),
// in four read-only buffers (density, diffuse, PSH, specular weights) so that each stays
// under the device's binding size.

struct Params {
    camera: Camera,
    ray_near: f32,
    hit_opacity: f32,
    d_stride: f32,       // voxels between the march's samples (`DensityCubes::set_march_stride`)
    layer_opacity: f32,  // `HitRule::LayerBehind`'s opacity; 2 (never reached): the largest weight

    // Density cubes.
    d_min: vec4<f32>,   // xyz min, w cell
    d_dims: vec4<u32>,  // xyz dims, w cube_res
    d_step: f32,         // sample step
    d_min_transmittance: f32,
    d_voxel_words: u32,  // voxel words (u32) per cube
    d_index_offset: u32, // word offsets inside the density buffer
    d_data_offset: u32,
    d_voxel_offset: u32,
    d_proximity_offset: u32, // one byte per cell, four to a word
    d_lut_offset: u32,

    // Diffuse cubes.
    c_min: vec4<f32>,
    c_dims: vec4<u32>,   // xyz dims, w cube_res
    c_channels: u32,
    c_index_offset: u32,
    c_data_offset: u32,
    c_blend: u32,        // the march's samples of largest weight that the diffuse colour blends (`DensityCubes::blend_samples`); 0: the hit point's

    // PSH: lattice origin and voxel, domain u, table side m, offset side r.
    p_origin: vec4<f32>, // xyz origin, w voxel
    p_u: u32,
    p_m: u32,
    p_r: u32,
    p_offsets_offset: u32,
    p_keys_offset: u32,
    p_features_offset: u32,
    layer_gap: f32,      // `HitRule::LayerBehind`'s gap, a distance (voxels x sample step)
    median_level: f32,   // `HitRule::median_transmittance`: 0.5 for the median depth, -1 (never) else
};

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> pixels: array<u32>;
@group(0) @binding(2) var<storage, read> density: array<u32>;
@group(0) @binding(3) var<storage, read> diffuse: array<u32>;
@group(0) @binding(4) var<storage, read> psh: array<u32>;
@group(0) @binding(5) var<storage, read> specular: array<f32>;
// Per pixel: r, g, b, opacity, depth, hit (1 if the coarse opacity reached HIT_OPACITY).
@group(0) @binding(6) var<storage, read_write> out: array<f32>;

const EMPTY_CELL: u32 = 0xffffffffu;
const BIG: f32 = 3.0e38;

// The specular MLP's weights, loaded once per workgroup.
var<workgroup> mlp_weights: array<f32, S_PARAMS>;

fn density_byte(index: u32) -> u32 {
    return (density[params.d_data_offset + (index >> 2u)] >> (8u * (index & 3u))) & 255u;
}

fn lut(code: u32) -> f32 {
    return bitcast<f32>(density[params.d_lut_offset + code]);
}

// `DensityCubes::density_at`: 0 when the voxel is clear, else the trilinear interpolation of
// the decoded corners. `cube` indexes the cube table, `g` is in cube-local sample units.
fn density_at(cube: u32, g: vec3<f32>) -> f32 {
    let res = params.d_dims.w;
    let v = res - 1u;
    let top = f32(v);
    let f = clamp(g, vec3<f32>(0.0), vec3<f32>(top));
    let last = i32(res) - 2;
    let ix = min(i32(f.x), last);
    let iy = min(i32(f.y), last);
    let iz = min(i32(f.z), last);
    let w = f - vec3<f32>(f32(ix), f32(iy), f32(iz));
    let voxel = u32(ix) + v * (u32(iy) + v * u32(iz));
    let word = density[params.d_voxel_offset + cube * params.d_voxel_words + (voxel >> 5u)];
    if (word & (1u << (voxel & 31u))) == 0u {
        return 0.0;
    }
    let base = cube * res * res * res + u32(ix) + res * (u32(iy) + res * u32(iz));
    let r = res;
    let rr = res * res;
    let x00 = mix(lut(density_byte(base)), lut(density_byte(base + 1u)), w.x);
    let x10 = mix(lut(density_byte(base + r)), lut(density_byte(base + r + 1u)), w.x);
    let x01 = mix(lut(density_byte(base + rr)), lut(density_byte(base + rr + 1u)), w.x);
    let x11 = mix(lut(density_byte(base + rr + r)), lut(density_byte(base + rr + r + 1u)), w.x);
    return mix(mix(x00, x10, w.y), mix(x01, x11, w.y), w.z);
}

fn cube_at(c: vec3<i32>) -> u32 {
    let d = params.d_dims;
    let i = u32(c.x) + d.x * (u32(c.y) + d.y * u32(c.z));
    return density[params.d_index_offset + i];
}

// Chebyshev distance in cells from cell `c` to the nearest cell with a cube (at most 255).
fn proximity(c: vec3<i32>) -> i32 {
    let d = params.d_dims;
    let i = u32(c.x) + d.x * (u32(c.y) + d.y * u32(c.z));
    let word = density[params.d_proximity_offset + (i >> 2u)];
    return i32((word >> ((i & 3u) * 8u)) & 0xffu);
}

fn floor_clamped(x: f32, hi: i32) -> i32 {
    // floor in the float domain, clamped before the cast (no overflow on huge values).
    return i32(clamp(floor(x), 0.0, f32(hi)));
}

struct March {
    opacity: f32,
    t: f32,
    front_t: f32, // `MarchHit::front_t`: the sample of largest weight, the depth reported
    blend_t: array<f32, MAX_BLEND_SAMPLES>, // `MarchHit::blend`: the `c_blend` samples of largest weight, distances
    blend_w: array<f32, MAX_BLEND_SAMPLES>, // and weights (0 past them)
};

// `MarchHit::keep_for_blend`: (t, w) replaces the first of the smallest of the `c_blend` kept weights.
fn keep_for_blend(hit: ptr<function, March>, t: f32, w: f32) {
    var smallest = 0u;
    for (var j = 1u; j < params.c_blend; j++) {
        if (*hit).blend_w[j] < (*hit).blend_w[smallest] {
            smallest = j;
        }
    }
    if w > (*hit).blend_w[smallest] {
        (*hit).blend_w[smallest] = w;
        (*hit).blend_t[smallest] = t;
    }
}

// `DensityCubes::march` over [t_near, infinity): DDA over coarse cells, the empty box around
// a cell far from every cube crossed in one step, samples at t0 + (k + 1/2) span (span: the
// sample step times the march stride); returns the coarse opacity and the distance
// of the sample of largest blending weight.
fn march(origin: vec3<f32>, dir_in: vec3<f32>, t_near: f32) -> March {
    var hit = March(0.0, 0.0, 0.0, array<f32, MAX_BLEND_SAMPLES>(), array<f32, MAX_BLEND_SAMPLES>());
    // `marchable_direction` (nephele-geometry): components under 1e-20 count as 0. Camera
    // rays are unit length, so its length check never refuses one here.
    let dir = select(dir_in, vec3<f32>(0.0), abs(dir_in) < vec3<f32>(1e-20));
    var max_weight = 0.0;
    var layer_t = BIG;
    var median_t = BIG;
    let lo = params.d_min.xyz;
    let cell_size = params.d_min.w;
    let d = vec3<i32>(params.d_dims.xyz);
    let hi = lo + cell_size * vec3<f32>(d);
    var t0 = max(t_near, 0.0);
    var t1 = BIG;
    for (var a = 0; a < 3; a++) {
        if dir[a] == 0.0 {
            if origin[a] < lo[a] || origin[a] > hi[a] {
                return hit;
            }
        } else {
            let inv = 1.0 / dir[a];
            let ta = (lo[a] - origin[a]) * inv;
            let tb = (hi[a] - origin[a]) * inv;
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    if !(t0 < t1) {
        return hit;
    }
    let step = params.d_step;
    let inv_step = 1.0 / step;
    let span = step * params.d_stride;
    let g_step = dir * params.d_stride;
    let entry = origin + dir * t0;
    let f = (entry - lo) / cell_size;
    var c = vec3<i32>(0);
    var t_next = vec3<f32>(BIG);
    var t_delta = vec3<f32>(BIG);
    var stepdir = vec3<i32>(0);
    var inv_dir = vec3<f32>(0.0);
    for (var a = 0; a < 3; a++) {
        c[a] = floor_clamped(f[a], d[a] - 1);
        if dir[a] > 0.0 {
            stepdir[a] = 1;
            t_next[a] = (lo[a] + f32(c[a] + 1) * cell_size - origin[a]) / dir[a];
            t_delta[a] = cell_size / dir[a];
            inv_dir[a] = 1.0 / dir[a];
        } else if dir[a] < 0.0 {
            stepdir[a] = -1;
            t_next[a] = (lo[a] + f32(c[a]) * cell_size - origin[a]) / dir[a];
            t_delta[a] = -cell_size / dir[a];
            inv_dir[a] = 1.0 / dir[a];
        }
    }
    var transmittance = 1.0;
    var t_cur = t0;
    var k = 0u;
    let max_cells = u32(d.x + d.y + d.z) + 3u;
    for (var iter = 0u; iter < max_cells; iter++) {
        // At Chebyshev distance n >= 2 from every cube, the box of 2n - 1 cells around c is
        // empty: leave it in one step (see the CPU march).
        let n = proximity(c);
        if n >= 2 {
            let reach = n - 1;
            var t_leave = BIG;
            var exit_axis = 0;
            for (var a = 0; a < 3; a++) {
                if stepdir[a] != 0 {
                    var face_cell = c[a] - reach;
                    if stepdir[a] > 0 {
                        face_cell = c[a] + reach + 1;
                    }
                    let t = (lo[a] + f32(face_cell) * cell_size - origin[a]) * inv_dir[a];
                    if t < t_leave {
                        t_leave = t;
                        exit_axis = a;
                    }
                }
            }
            if t_leave >= t1 {
                break;
            }
            t_cur = max(t_cur, t_leave);
            let p = origin + dir * t_cur;
            for (var a = 0; a < 3; a++) {
                if stepdir[a] == 0 {
                    continue;
                }
                if a == exit_axis {
                    c[a] = c[a] + stepdir[a] * (reach + 1);
                } else {
                    // Only along stepdir (see the CPU march: no ping-pong at box edges).
                    let at = floor_clamped((p[a] - lo[a]) / cell_size, d[a] - 1);
                    if stepdir[a] > 0 {
                        c[a] = max(c[a], at);
                    } else {
                        c[a] = min(c[a], at);
                    }
                }
                var up = 0;
                if stepdir[a] > 0 {
                    up = 1;
                }
                t_next[a] = (lo[a] + f32(c[a] + up) * cell_size - origin[a]) / dir[a];
            }
            if c[exit_axis] < 0 || c[exit_axis] >= d[exit_axis] {
                break;
            }
            continue;
        }
        var axis = 2;
        if t_next.x <= t_next.y && t_next.x <= t_next.z {
            axis = 0;
        } else if t_next.y <= t_next.z {
            axis = 1;
        }
        let t_exit = min(t_next[axis], t1);
        let cube = cube_at(c);
        if cube != EMPTY_CELL {
            let first = u32(ceil(max((t_cur - t0) / span - 0.5, 0.0)));
            k = max(k, first);
            let cell_min = lo + cell_size * vec3<f32>(c);
            var g = (origin + dir * (t0 + (f32(k) + 0.5) * span) - cell_min) * inv_step;
            loop {
                let t = t0 + (f32(k) + 0.5) * span;
                if t >= t_exit {
                    break;
                }
                k += 1u;
                let sigma = density_at(cube, g);
                g += g_step;
                if sigma <= 0.0 {
                    continue;
                }
                let alpha = 1.0 - exp(-sigma * span);
                let w = transmittance * alpha;
                // Kept only for heads that blend (`DensityCubes::set_blend_samples`).
                if params.c_blend > 0u {
                    keep_for_blend(&hit, t, w);
                }
                if w > max_weight {
                    max_weight = w;
                    hit.t = t;
                }
                let entering = transmittance;
                transmittance *= 1.0 - alpha;
                if layer_t == BIG && 1.0 - transmittance >= params.layer_opacity {
                    layer_t = t;
                }
                if transmittance <= params.median_level && entering > params.median_level {
                    median_t = crossing_depth(t, span, entering, params.median_level, sigma);
                }
                if transmittance < params.d_min_transmittance {
                    hit.opacity = clamp(1.0 - transmittance, 0.0, 1.0);
                    return take_hit_point(hit, layer_t, median_t);
                }
            }
        }
        if t_exit >= t1 {
            break;
        }
        t_cur = t_exit;
        c[axis] += stepdir[axis];
        if c[axis] < 0 || c[axis] >= d[axis] {
            break;
        }
        t_next[axis] += t_delta[axis];
    }
    hit.opacity = clamp(1.0 - transmittance, 0.0, 1.0);
    return take_hit_point(hit, layer_t, median_t);
}

// `crossing_depth`: where the sample centred at t brings the transmittance down to `level`.
fn crossing_depth(t: f32, span: f32, entering: f32, level: f32, sigma: f32) -> f32 {
    let start = t - 0.5 * span;
    return clamp(start + log(entering / level) / sigma, start, start + span);
}

// `MarchHit::take_hit_point`: the median depth where the ray crossed it; else the layer when
// it lies more than the gap behind the sample of largest weight.
fn take_hit_point(hit_in: March, layer_t: f32, median_t: f32) -> March {
    var hit = hit_in;
    hit.front_t = hit.t;
    if median_t < BIG {
        hit.t = median_t;
    } else if layer_t < BIG && layer_t - hit.t > params.layer_gap {
        hit.t = layer_t;
    }
    return hit;
}

// `SparseCubes::sample` of the diffuse cubes followed by `decode_diffuse` (v * v); zeros
// where no cube covers p.
fn diffuse_at(p: vec3<f32>) -> array<f32, 6> {
    var outv = array<f32, 6>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let lo = params.c_min.xyz;
    let cell_size = params.c_min.w;
    let d = params.c_dims.xyz;
    let f = (p - lo) / cell_size;
    if !(f.x >= 0.0 && f.y >= 0.0 && f.z >= 0.0) || f.x > f32(d.x) || f.y > f32(d.y) || f.z > f32(d.z) {
        return outv;
    }
    let c = vec3<u32>(min(u32(f.x), d.x - 1u), min(u32(f.y), d.y - 1u), min(u32(f.z), d.z - 1u));
    let cube = diffuse[params.c_index_offset + c.x + d.x * (c.y + d.y * c.z)];
    if cube == EMPTY_CELL {
        return outv;
    }
    let res = params.c_dims.w;
    let top = f32(res - 1u);
    let sample_step = cell_size / top;
    let cell_min = lo + cell_size * vec3<f32>(c);
    let g = clamp((p - cell_min) / sample_step, vec3<f32>(0.0), vec3<f32>(top));
    let last = res - 2u;
    let ix = min(u32(g.x), last);
    let iy = min(u32(g.y), last);
    let iz = min(u32(g.z), last);
    let w = g - vec3<f32>(f32(ix), f32(iy), f32(iz));
    let channels = params.c_channels;
    let base = cube * res * res * res;
    for (var corner = 0u; corner < 8u; corner++) {
        let dx = corner & 1u;
        let dy = (corner >> 1u) & 1u;
        let dz = corner >> 2u;
        var wc = 1.0;
        if dx == 1u { wc *= w.x; } else { wc *= 1.0 - w.x; }
        if dy == 1u { wc *= w.y; } else { wc *= 1.0 - w.y; }
        if dz == 1u { wc *= w.z; } else { wc *= 1.0 - w.z; }
        let off = (base + (ix + dx) + res * ((iy + dy) + res * (iz + dz))) * channels;
        for (var ch = 0u; ch < 6u; ch++) {
            if ch < channels {
                let i = off + ch;
                let byte = (diffuse[params.c_data_offset + (i >> 2u)] >> (8u * (i & 3u))) & 255u;
                outv[ch] += wc * f32(byte);
            }
        }
    }
    for (var ch = 0u; ch < 6u; ch++) {
        let v = outv[ch] * (1.0 / 255.0);
        outv[ch] = v * v;
    }
    return outv;
}

// `PshTable::slot_i`: the slot of lattice point v, or EMPTY_CELL.
fn psh_slot(v: vec3<i32>) -> u32 {
    if v.x < 0 || v.y < 0 || v.z < 0 {
        return EMPTY_CELL;
    }
    let p = vec3<u32>(v);
    let u = params.p_u;
    if p.x >= u || p.y >= u || p.z >= u {
        return EMPTY_CELL;
    }
    let m = params.p_m;
    let r = params.p_r;
    let q = (p.x % r) + r * ((p.y % r) + r * (p.z % r));
    let o = psh[params.p_offsets_offset + q];
    let x = (p.x % m + (o & 1023u)) % m;
    let y = (p.y % m + ((o >> 10u) & 1023u)) % m;
    let z = (p.z % m + ((o >> 20u) & 1023u)) % m;
    let slot = x + m * (y + m * z);
    let key = p.x | (p.y << 10u) | (p.z << 20u);
    if psh[params.p_keys_offset + slot] == key {
        return slot;
    }
    return EMPTY_CELL;
}

fn activate(x: f32, code: u32) -> f32 {
    switch code {
        case 1u: { return max(x, 0.0); }
        case 2u: { return 1.0 / (1.0 + exp(-x)); }
        case 3u: { return exp(min(x, 15.0)); }
        case 4u: {
            if x > 15.0 { return x; }
            return log(1.0 + exp(x));
        }
        default: { return x; }
    }
}

// The SH part of the specular input row.
fn sh_encode(dir: vec3<f32>, row: ptr<function, array<f32, S_IN>>) {
    let sh = sh_values(dir);
    for (var i = 0u; i < SH_COUNT; i++) {
        (*row)[PSH_DIM + i] = sh[i];
    }
}

// The specular MLP (ReLU hidden layers, S_OUT_ACT on the output) from workgroup memory.
// Layout as `nephele_nn::Mlp`: per layer the weights (input-major: w[k * out + o]) then the
// bias.
fn specular_mlp(input: ptr<function, array<f32, S_IN>>) -> vec4<f32> {
    var a = array<f32, S_HIDDEN>();
    var b = array<f32, S_HIDDEN>();
    var offset = 0u;
    var out4 = vec4<f32>(0.0);
    if S_LAYERS == 0u {
        for (var o = 0u; o < 4u; o++) {
            var acc = mlp_weights[S_IN * 4u + o];
            for (var k = 0u; k < S_IN; k++) {
                acc += (*input)[k] * mlp_weights[k * 4u + o];
            }
            out4[o] = activate(acc, S_OUT_ACT);
        }
        return out4;
    }
    for (var o = 0u; o < S_HIDDEN; o++) {
        var acc = mlp_weights[S_IN * S_HIDDEN + o];
        for (var k = 0u; k < S_IN; k++) {
            acc += (*input)[k] * mlp_weights[k * S_HIDDEN + o];
        }
        a[o] = max(acc, 0.0);
    }
    offset = S_IN * S_HIDDEN + S_HIDDEN;
    for (var layer = 1u; layer < S_LAYERS; layer++) {
        for (var o = 0u; o < S_HIDDEN; o++) {
            var acc = mlp_weights[offset + S_HIDDEN * S_HIDDEN + o];
            for (var k = 0u; k < S_HIDDEN; k++) {
                acc += a[k] * mlp_weights[offset + k * S_HIDDEN + o];
            }
            b[o] = max(acc, 0.0);
        }
        a = b;
        offset += S_HIDDEN * S_HIDDEN + S_HIDDEN;
    }
    for (var o = 0u; o < 4u; o++) {
        var acc = mlp_weights[offset + S_HIDDEN * 4u + o];
        for (var k = 0u; k < S_HIDDEN; k++) {
            acc += a[k] * mlp_weights[offset + k * 4u + o];
        }
        out4[o] = activate(acc, S_OUT_ACT);
    }
    return out4;
}

fn write_miss(i: u32, hit: f32) {
    for (var j = 0u; j < 5u; j++) {
        out[i * 6u + j] = 0.0;
    }
    out[i * 6u + 5u] = hit;
}

@compute @workgroup_size(64)
fn main(
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    // Weights into workgroup memory before any invocation leaves (the barrier needs them all).
    for (var w = lid; w < S_PARAMS; w += WORKGROUP) {
        mlp_weights[w] = specular[w];
    }
    workgroupBarrier();

    let i = (wid.y * groups.x + wid.x) * WORKGROUP + lid;
    if i >= params.camera.pixel_count {
        return;
    }
    let ray = camera_ray(params.camera, pixels[i]);
    let dir = ray.dir;
    let origin = ray.origin;

    // A var: its blend arrays are indexed at run time.
    var m = march(origin, dir, params.ray_near);
    if !(m.opacity >= params.hit_opacity) {
        write_miss(i, 0.0);
        return;
    }
    let p = origin + dir * m.t;

    // Diffuse colour and tint: at the hit point, or blended over the samples of largest
    // weight (`MarchHit::normalised_blend`).
    var dif = array<f32, 6>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    var blend_total = 0.0;
    for (var j = 0u; j < params.c_blend; j++) {
        blend_total += m.blend_w[j];
    }
    if params.c_blend > 0u && blend_total > 0.0 {
        for (var j = 0u; j < params.c_blend; j++) {
            let w = m.blend_w[j] * (1.0 / blend_total);
            if w > 0.0 {
                let read = diffuse_at(origin + dir * m.blend_t[j]);
                for (var c = 0u; c < 6u; c++) {
                    dif[c] += w * read[c];
                }
            }
        }
    } else {
        dif = diffuse_at(p);
    }

    // Specular input row: PSH features, SH of the direction, coarse opacity.
    var row = array<f32, S_IN>();
    let fp = (p - params.p_origin.xyz) / params.p_origin.w;
    if is_finite(fp.x) && is_finite(fp.y) && is_finite(fp.z) {
        let bf = floor(fp);
        let w = fp - bf;
        let u = i32(params.p_u);
        // Range check in the float domain before any cast.
        if all(bf >= vec3<f32>(-1.0)) && all(bf < vec3<f32>(f32(u))) {
            let bi = vec3<i32>(bf);
            var slots = array<u32, 8>();
            var weights = array<f32, 8>();
            var count = 0u;
            var total = 0.0;
            for (var corner = 0u; corner < 8u; corner++) {
                let dx = i32(corner & 1u);
                let dy = i32((corner >> 1u) & 1u);
                let dz = i32(corner >> 2u);
                let slot = psh_slot(bi + vec3<i32>(dx, dy, dz));
                if slot != EMPTY_CELL {
                    var wc = 1.0;
                    if dx == 1 { wc *= w.x; } else { wc *= 1.0 - w.x; }
                    if dy == 1 { wc *= w.y; } else { wc *= 1.0 - w.y; }
                    if dz == 1 { wc *= w.z; } else { wc *= 1.0 - w.z; }
                    slots[count] = slot;
                    weights[count] = wc;
                    count += 1u;
                    total += wc;
                }
            }
            if total > 1e-12 {
                for (var c = 0u; c < count; c++) {
                    let wc = weights[c] / total;
                    let base = params.p_features_offset + slots[c] * PSH_DIM;
                    for (var j = 0u; j < PSH_DIM; j++) {
                        row[j] += wc * bitcast<f32>(psh[base + j]);
                    }
                }
            }
        }
    }
    sh_encode(dir, &row);
    row[PSH_DIM + SH_COUNT] = m.opacity;

    // Specular head and its activation (`specular_activation`).
    let raw = specular_mlp(&row);
    let a_coarse = clamp(m.opacity, 1e-4, 1.0 - 1e-4);
    let logit = log(a_coarse / (1.0 - a_coarse));
    let spec = vec3<f32>(
        1.0 / (1.0 + exp(-raw.x)),
        1.0 / (1.0 + exp(-raw.y)),
        1.0 / (1.0 + exp(-raw.z)),
    );
    let a = 1.0 / (1.0 + exp(-(raw.w + logit)));

    // Eq. 7.
    let c = a * (vec3<f32>(dif[0], dif[1], dif[2]) + vec3<f32>(dif[3], dif[4], dif[5]) * spec);
    let depth = view_depth(params.camera, origin + dir * m.front_t);
    if a > 0.0 && is_finite(a) && is_finite(depth) && depth > 0.0 && is_finite(c.x) && is_finite(c.y) && is_finite(c.z) {
        out[i * 6u + 0u] = max(c.x, 0.0);
        out[i * 6u + 1u] = max(c.y, 0.0);
        out[i * 6u + 2u] = max(c.z, 0.0);
        out[i * 6u + 3u] = clamp(a, 0.0, 1.0);
        out[i * 6u + 4u] = depth;
        out[i * 6u + 5u] = 1.0;
    } else {
        write_miss(i, 1.0);
    }
}
