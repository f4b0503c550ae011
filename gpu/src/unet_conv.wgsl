// One convolution of the GI U-Net (`nephele_nn::conv::conv_forward`): k x k (1 or 3), zero
// padding, stride 1, optional ReLU; images channels-last, weights
// `[((ky * k + kx) * inputs + i) * outputs + o]` then the biases, at `weights` in the
// network's one parameter buffer. The input is `a` then `b` per pixel (the decoder's
// concatenation, read in place): `a` at half resolution with nearest upsampling when
// `a_half` is 1 (the level below), `b` (the skip) at full resolution; `cb` is 0 elsewhere.
// One invocation per output value. With `masked` 1 only the pixels whose bit is set in
// `mask` (bit `pixel % 32` of word `mask_offset + pixel / 32`) are computed, the others
// written 0 (the CPU's `conv_forward_masked` computes the same set).

struct ConvParams {
    width: u32,
    height: u32,
    ca: u32,
    cb: u32,
    co: u32,
    k: u32,
    relu: u32,
    a_half: u32,
    weights: u32,
    masked: u32,
    mask_offset: u32,
    pad0: u32,
};

@group(0) @binding(0) var<uniform> p: ConvParams;
@group(0) @binding(1) var<storage, read> net: array<f32>;
@group(0) @binding(2) var<storage, read> in_a: array<f32>;
@group(0) @binding(3) var<storage, read> in_b: array<f32>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;
@group(0) @binding(5) var<storage, read> mask: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = gid.x + gid.y * groups.x * WORKGROUP;
    if (index >= p.width * p.height * p.co) {
        return;
    }
    let o = index % p.co;
    let pixel = index / p.co;
    if (p.masked == 1u && ((mask[p.mask_offset + pixel / 32u] >> (pixel % 32u)) & 1u) == 0u) {
        out[index] = 0.0;
        return;
    }
    let x = i32(pixel % p.width);
    let y = i32(pixel / p.width);
    let ci = p.ca + p.cb;
    let k = i32(p.k);
    let pad = k / 2;
    var acc = net[p.weights + p.k * p.k * ci * p.co + o];
    for (var ky = 0; ky < k; ky++) {
        let sy = y + ky - pad;
        if (sy < 0 || sy >= i32(p.height)) {
            continue;
        }
        for (var kx = 0; kx < k; kx++) {
            let sx = x + kx - pad;
            if (sx < 0 || sx >= i32(p.width)) {
                continue;
            }
            let w = p.weights + u32(ky * k + kx) * ci * p.co + o;
            var a = (u32(sy) * p.width + u32(sx)) * p.ca;
            if (p.a_half == 1u) {
                a = (u32(sy / 2) * (p.width / 2u) + u32(sx / 2)) * p.ca;
            }
            for (var i = 0u; i < p.ca; i++) {
                acc += in_a[a + i] * net[w + i * p.co];
            }
            let b = (u32(sy) * p.width + u32(sx)) * p.cb;
            for (var i = 0u; i < p.cb; i++) {
                acc += in_b[b + i] * net[w + (p.ca + i) * p.co];
            }
        }
    }
    if (p.relu == 1u) {
        acc = max(acc, 0.0);
    }
    out[index] = acc;
}
