// The GPU tracer: a line-by-line twin of `protocol/src/trace.rs` (the DDA) and
// `protocol/src/render.rs` (camera rays, shading, sky). Read those first; the comments there say
// why each step is the way it is. Differences, all forced by WGSL:
//
// * No infinity literal: `BIG` stands in for +inf. Plane times of moving axes are finite and far
//   below it, so every comparison comes out as it would with a real infinity.
// * No labelled loops or break-with-value: the cell loop's "which axis left the brick" is a var.
// * The DDA state lives in `var<private>` globals, one copy per invocation, shared by the primary
//   and the shadow ray which run one after the other.
// * Every loop iteration crosses at least one plane, so a ray takes at most about nx+ny+nz
//   iterations; `frame.region_dims.w` is a budget well above that which turns a driver hang on a
//   bug into a visible miss instead.
//
// Buffers mirror `BrickMap`'s arrays byte for byte (see `client/src/gpu/scene.rs`). The three pools
// that can outgrow one storage binding (cells, masks, colours) are split into two bindings of
// 2^page_shift words each; `*_word(i)` picks the page.

const BIG: f32 = 3.0e38;
const EMPTY: u32 = 0xFFFFFFFFu;
const EMPTY_REGION: u32 = 0xFFFFFF00u;
const REGION_EDGE: i32 = 32;
const BRICK_EDGE: i32 = 8;
const MIN_DIRECTION: f32 = 1e-30;
const NO_AXIS: i32 = -1;
const MISS: u32 = 0xFFFFFFFFu;

struct Frame {
    eye: vec4<f32>,
    forward: vec4<f32>,
    // Scaled to one pixel at unit distance, as `Projection` has them.
    right: vec4<f32>,
    up: vec4<f32>,
    // xyz: unit vector towards the sun; w: ambient.
    sun: vec4<f32>,
    // xyz: scene size in voxels; w: 1 to trace shadow rays.
    size: vec4<u32>,
    // xyz: regions per axis; w: iteration budget per ray.
    region_dims: vec4<u32>,
    // xyz: cells per axis; w: log2 of the words per page.
    cell_dims: vec4<u32>,
    // x, y: image size in pixels.
    image: vec4<u32>,
}

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> regions: array<u32>;
@group(0) @binding(2) var<storage, read> colour_bases: array<u32>;
@group(0) @binding(3) var<storage, read> cells0: array<u32>;
@group(0) @binding(4) var<storage, read> cells1: array<u32>;
@group(0) @binding(5) var<storage, read> masks0: array<u32>;
@group(0) @binding(6) var<storage, read> masks1: array<u32>;
@group(0) @binding(7) var<storage, read> colours0: array<u32>;
@group(0) @binding(8) var<storage, read> colours1: array<u32>;
@group(0) @binding(9) var out_image: texture_storage_2d<rgba8unorm, write>;
// Per pixel: (x | y << 16, z) of the primary hit, or (MISS, MISS). For tests and picking. A
// storage texture rather than a buffer: WebGPU guarantees only 8 storage buffers per stage, and
// the scene's eight take them all.
@group(0) @binding(10) var out_hits: texture_storage_2d<rg32uint, write>;

// ---- paged pools ---------------------------------------------------------------------------

fn page_of(i: u32) -> u32 {
    return i >> frame.cell_dims.w;
}
fn in_page(i: u32) -> u32 {
    return i & ((1u << frame.cell_dims.w) - 1u);
}

fn cell_word(i: u32) -> u32 {
    let o = in_page(i);
    switch page_of(i) {
        case 0u: { return cells0[o]; }
        default: { return cells1[o]; }
    }
}

fn mask_word(i: u32) -> u32 {
    let o = in_page(i);
    switch page_of(i) {
        case 0u: { return masks0[o]; }
        default: { return masks1[o]; }
    }
}

fn colour_word(i: u32) -> u32 {
    let o = in_page(i);
    switch page_of(i) {
        case 0u: { return colours0[o]; }
        default: { return colours1[o]; }
    }
}

// RGB565 colour number `i` of the pool: two per word, the even one in the low half.
fn colour_at(i: u32) -> u32 {
    return (colour_word(i >> 1u) >> ((i & 1u) * 16u)) & 0xFFFFu;
}

// Solid voxels of brick `slot` before bit `bit` (`brick::rank`).
fn rank(slot: u32, bit: u32) -> u32 {
    let word = bit >> 5u;
    var count = 0u;
    for (var w = 0u; w < word; w++) {
        count += countOneBits(mask_word(slot * 16u + w));
    }
    let partial = mask_word(slot * 16u + word) & ((1u << (bit & 31u)) - 1u);
    return count + countOneBits(partial);
}

fn region_is_empty(entry: u32) -> bool {
    return entry >= EMPTY_REGION;
}
fn region_clearance(entry: u32) -> i32 {
    return i32(entry & 0xFFu);
}

// ---- the DDA (trace.rs `Dda`) ----------------------------------------------------------------

var<private> o: vec3<f32>;
var<private> d: vec3<f32>;
var<private> inv: vec3<f32>;
var<private> stp: vec3<i32>;
var<private> n: vec3<i32>;
var<private> v: vec3<i32>;
var<private> next: vec3<f32>;
var<private> t: f32;
var<private> axis: i32;

fn floor_div(a: i32, s: i32) -> i32 {
    return select(a / s, (a - s + 1) / s, a < 0);
}

fn before(tt: f32, ax: i32, at: f32, at_axis: i32) -> bool {
    return tt < at || (tt == at && ax < at_axis);
}

fn plane_t(i: i32, plane: i32) -> f32 {
    return (f32(plane) - o[i]) * inv[i];
}

fn exit_t(i: i32, vi: i32) -> f32 {
    if stp[i] == 0 {
        return BIG;
    }
    return plane_t(i, vi + select(0, 1, stp[i] > 0));
}

fn settle_scaled(i: i32, lo: i32, hi: i32, at: f32, k: i32, scale: i32) -> i32 {
    if stp[i] == 0 {
        return clamp(i32(floor(o[i])) / scale, lo, hi);
    }
    let guess = i32(floor(o[i] + d[i] * at));
    var g = clamp(floor_div(guess, scale), lo, hi);
    if stp[i] > 0 {
        while g < hi && before(plane_t(i, (g + 1) * scale), i, at, k) {
            g += 1;
        }
        while g > lo && !before(plane_t(i, g * scale), i, at, k) {
            g -= 1;
        }
    } else {
        while g > lo && before(plane_t(i, g * scale), i, at, k) {
            g -= 1;
        }
        while g < hi && !before(plane_t(i, (g + 1) * scale), i, at, k) {
            g += 1;
        }
    }
    return g;
}

fn settle(i: i32, lo: i32, hi: i32, at: f32, k: i32) -> i32 {
    return settle_scaled(i, lo, hi, at, k, 1);
}

// `Dda::start`: false when the ray misses the grid or is unusable.
fn start(origin: vec3<f32>, dir: vec3<f32>) -> bool {
    o = origin;
    d = dir;
    n = vec3<i32>(frame.size.xyz);
    inv = vec3<f32>(0.0);
    stp = vec3<i32>(0);
    v = vec3<i32>(0);
    next = vec3<f32>(BIG);
    t = 0.0;
    axis = NO_AXIS;
    for (var i = 0; i < 3; i++) {
        if abs(dir[i]) >= MIN_DIRECTION {
            stp[i] = select(-1, 1, dir[i] > 0.0);
            inv[i] = 1.0 / dir[i];
        }
    }
    if all(stp == vec3<i32>(0)) {
        return false;
    }
    var first: vec3<i32>;
    for (var i = 0; i < 3; i++) {
        if stp[i] < 0 {
            first[i] = i32(ceil(origin[i])) - 1;
        } else {
            first[i] = i32(floor(origin[i]));
        }
    }
    if all(first >= vec3<i32>(0)) && all(first < n) {
        v = first;
    } else {
        var near = -BIG;
        var near_axis = 0;
        var far = BIG;
        var far_axis = 0;
        for (var i = 0; i < 3; i++) {
            if stp[i] == 0 {
                if origin[i] < 0.0 || origin[i] >= f32(n[i]) {
                    return false;
                }
                continue;
            }
            var enter: f32;
            var leave: f32;
            if stp[i] > 0 {
                enter = plane_t(i, 0);
                leave = plane_t(i, n[i]);
            } else {
                enter = plane_t(i, n[i]);
                leave = plane_t(i, 0);
            }
            if !before(enter, i, near, near_axis) {
                near = enter;
                near_axis = i;
            }
            if before(leave, i, far, far_axis) {
                far = leave;
                far_axis = i;
            }
        }
        if !before(near, near_axis, far, far_axis) || near < 0.0 {
            return false;
        }
        let k = near_axis;
        for (var i = 0; i < 3; i++) {
            if i == k {
                v[i] = select(n[k] - 1, 0, stp[k] > 0);
            } else {
                v[i] = settle(i, 0, n[i] - 1, near, k);
            }
        }
        t = near;
        axis = k;
    }
    for (var i = 0; i < 3; i++) {
        next[i] = exit_t(i, v[i]);
    }
    return true;
}

fn block_exit_t(i: i32, b: i32, scale: i32) -> f32 {
    if stp[i] > 0 {
        return plane_t(i, min((b + 1) * scale, n[i]));
    } else if stp[i] < 0 {
        return plane_t(i, b * scale);
    }
    return BIG;
}

fn block_exit(b: vec3<i32>, scale: i32) -> vec3<f32> {
    return vec3<f32>(block_exit_t(0, b.x, scale), block_exit_t(1, b.y, scale), block_exit_t(2, b.z, scale));
}

fn enter_block(lo: vec3<i32>, hi: vec3<i32>) {
    if axis == NO_AXIS {
        return;
    }
    let k = axis;
    for (var i = 0; i < 3; i++) {
        if i == k {
            v[i] = select(hi[k], lo[k], stp[k] > 0);
        } else {
            v[i] = settle(i, lo[i], hi[i], t, k);
        }
    }
}

fn earliest(x: vec3<f32>) -> i32 {
    let a = select(0, 1, x[1] < x[0]);
    let m = select(x[0], x[1], a == 1);
    return select(a, 2, x[2] < m);
}

struct Hit {
    found: bool,
    voxel: vec3<i32>,
    colour: u32,
    normal: vec3<i32>,
    t: f32,
}

fn miss() -> Hit {
    return Hit(false, vec3<i32>(0), 0u, vec3<i32>(0), 0.0);
}

fn make_hit(colour: u32) -> Hit {
    var normal = vec3<i32>(0);
    if axis != NO_AXIS {
        normal[axis] = -stp[axis];
    }
    return Hit(true, v, colour, normal, t);
}

// `trace_with_stats`, without the stats.
fn trace(origin: vec3<f32>, dir: vec3<f32>) -> Hit {
    if !start(origin, dir) {
        return miss();
    }
    let rdims = vec3<i32>(frame.region_dims.xyz);
    let cdims = vec3<i32>(frame.cell_dims.xyz);
    var budget = frame.region_dims.w;
    var v_valid = true;
    var r = v / REGION_EDGE;
    var rnext = block_exit(r, REGION_EDGE);
    loop {
        // Region level.
        var block: u32;
        loop {
            let entry = regions[u32(r.x + rdims.x * (r.y + rdims.y * r.z))];
            if !region_is_empty(entry) {
                block = entry;
                break;
            }
            if budget == 0u {
                return miss();
            }
            budget -= 1u;
            v_valid = false;
            let clear = region_clearance(entry);
            if clear >= 2 {
                let lo = max(r - vec3<i32>(clear), vec3<i32>(0));
                let hi = min(r + vec3<i32>(clear), rdims - vec3<i32>(1));
                let exit = block_exit(select(lo, hi, stp > vec3<i32>(0)), REGION_EDGE);
                let k = earliest(exit);
                t = exit[k];
                axis = k;
                for (var i = 0; i < 3; i++) {
                    if i != k {
                        r[i] = settle_scaled(i, lo[i], hi[i], t, k, REGION_EDGE);
                        rnext[i] = block_exit_t(i, r[i], REGION_EDGE);
                    }
                }
                r[k] = select(lo[k] - 1, hi[k] + 1, stp[k] > 0);
            } else {
                let k = earliest(rnext);
                t = rnext[k];
                axis = k;
                r[k] += stp[k];
            }
            let k = axis;
            if r[k] < 0 || r[k] >= rdims[k] {
                return miss();
            }
            rnext[k] = block_exit_t(k, r[k], REGION_EDGE);
        }
        if !v_valid {
            let lo = r * REGION_EDGE;
            enter_block(lo, min(lo + vec3<i32>(REGION_EDGE - 1), n - vec3<i32>(1)));
            v_valid = true;
        }
        // Cell level, inside this region.
        var c = v / BRICK_EDGE;
        var cnext = block_exit(c, BRICK_EDGE);
        loop {
            if budget == 0u {
                return miss();
            }
            budget -= 1u;
            let local = u32((c.x & 3) | ((c.y & 3) << 2u) | ((c.z & 3) << 4u));
            let slot = cell_word(block * 64u + local);
            var k: i32;
            if slot == EMPTY {
                k = earliest(cnext);
                t = cnext[k];
                axis = k;
                c[k] += stp[k];
                cnext[k] = block_exit_t(k, c[k], BRICK_EDGE);
                v_valid = false;
            } else {
                let lo = c * BRICK_EDGE;
                let hi = min(lo + vec3<i32>(BRICK_EDGE - 1), n - vec3<i32>(1));
                if !v_valid {
                    enter_block(lo, hi);
                    v_valid = true;
                }
                for (var i = 0; i < 3; i++) {
                    next[i] = exit_t(i, v[i]);
                }
                // Voxel level, inside this brick.
                loop {
                    let bit = u32((v.x & 7) | ((v.y & 7) << 3u) | ((v.z & 7) << 6u));
                    if ((mask_word(slot * 16u + (bit >> 5u)) >> (bit & 31u)) & 1u) != 0u {
                        return make_hit(colour_at(colour_bases[slot] + rank(slot, bit)));
                    }
                    if budget == 0u {
                        return miss();
                    }
                    budget -= 1u;
                    let kk = earliest(next);
                    t = next[kk];
                    axis = kk;
                    v[kk] += stp[kk];
                    next[kk] = exit_t(kk, v[kk]);
                    if v[kk] < lo[kk] || v[kk] > hi[kk] {
                        c[kk] += stp[kk];
                        cnext[kk] = block_exit_t(kk, c[kk], BRICK_EDGE);
                        k = kk;
                        break;
                    }
                }
            }
            if c[k] < 0 || c[k] >= cdims[k] {
                return miss();
            }
            if c[k] / 4 != r[k] {
                r[k] += stp[k];
                if r[k] < 0 || r[k] >= rdims[k] {
                    return miss();
                }
                rnext[k] = block_exit_t(k, r[k], REGION_EDGE);
                break;
            }
        }
    }
    return miss();
}

// ---- shading (render.rs) ---------------------------------------------------------------------

fn colour_f32(c: u32) -> vec3<f32> {
    let r5 = f32((c >> 11u) & 0x1Fu);
    let g6 = f32((c >> 5u) & 0x3Fu);
    let b5 = f32(c & 0x1Fu);
    return vec3<f32>(r5 / 31.0, g6 / 63.0, b5 / 31.0);
}

fn sky(dir: vec3<f32>) -> vec3<f32> {
    let len = sqrt(dot(dir, dir));
    let up = select(0.0, dir.y / len, len > 0.0);
    let s = clamp(up * 0.5 + 0.5, 0.0, 1.0);
    return vec3<f32>(0.80 - 0.35 * s, 0.87 - 0.25 * s, 0.95 - 0.05 * s);
}

fn shadowed(hit: Hit) -> bool {
    if frame.size.w == 0u || all(hit.normal == vec3<i32>(0)) {
        return false;
    }
    let front = vec3<f32>(hit.voxel + hit.normal) + vec3<f32>(0.5);
    return trace(front, frame.sun.xyz).found;
}

fn shade(hit: Hit, in_shadow: bool) -> vec3<f32> {
    let nrm = vec3<f32>(hit.normal);
    var diffuse = 0.0;
    if !in_shadow {
        diffuse = max(dot(nrm, frame.sun.xyz), 0.0);
    }
    let ambient = frame.sun.w;
    let light = ambient + (1.0 - ambient) * diffuse;
    return colour_f32(hit.colour) * light;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let width = frame.image.x;
    let height = frame.image.y;
    if id.x >= width || id.y >= height {
        return;
    }
    let u = f32(id.x) + 0.5 - f32(width) * 0.5;
    let vv = f32(height) * 0.5 - (f32(id.y) + 0.5);
    let dir = frame.forward.xyz + frame.right.xyz * u + frame.up.xyz * vv;
    let hit = trace(frame.eye.xyz, dir);
    var rgb: vec3<f32>;
    var record = vec2<u32>(MISS, MISS);
    if hit.found {
        rgb = shade(hit, shadowed(hit));
        let p = vec3<u32>(hit.voxel);
        record = vec2<u32>(p.x | (p.y << 16u), p.z);
    } else {
        rgb = sky(dir);
    }
    textureStore(out_image, vec2<i32>(id.xy), vec4<f32>(clamp(rgb, vec3<f32>(0.0), vec3<f32>(1.0)), 1.0));
    textureStore(out_hits, vec2<i32>(id.xy), vec4<u32>(record, 0u, 0u));
}
