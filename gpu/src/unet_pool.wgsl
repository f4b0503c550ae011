// 2x2 average pooling of the GI U-Net (`nephele_nn::conv::pool_forward`): the input is
// `width x height` with `channels` per pixel, channels-last. One invocation per output value.

struct PoolParams {
    width: u32,
    height: u32,
    channels: u32,
    pad0: u32,
};

@group(0) @binding(0) var<uniform> p: PoolParams;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = gid.x + gid.y * groups.x * WORKGROUP;
    let w2 = p.width / 2u;
    if (index >= w2 * (p.height / 2u) * p.channels) {
        return;
    }
    let c = index % p.channels;
    let pixel = index / p.channels;
    let x = 2u * (pixel % w2);
    let y = 2u * (pixel / w2);
    let at = (y * p.width + x) * p.channels + c;
    let below = at + p.width * p.channels;
    out[index] = 0.25 * (src[at] + src[at + p.channels] + src[below] + src[below + p.channels]);
}
