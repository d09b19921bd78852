// The GPU tracer: a line-by-line twin of `protocol/src/trace.rs` (the DDA), `protocol/src/render.rs`
// (camera rays) and `protocol/src/shade.rs` (shading, sky). Read those first; the comments there
// say why each step is the way it is. Differences, all forced by WGSL:
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
// Not here, because they are CPU speed-ups that give the same hits: the beam pre-pass
// (`beam.rs`; one invocation marching per workgroup made lavapipe ~20% slower), settling by
// `floor` alone, and the scalar voxel loop. The traversal order, the occupied box and the cell
// and region clearance jumps are the same.
//
// Buffers mirror `BrickMap`'s arrays byte for byte (see `client/src/gpu/scene.rs`). The three pools
// that can outgrow one storage binding (cells, masks, colours) are split into two bindings of
// 2^page_shift words each; `*_word(i)` picks the page.

const BIG: f32 = 3.0e38;
const EMPTY_REGION: u32 = 0xFFFFFF00u;
const STAND_IN: u32 = 0x80000000u;
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
    // `LightUniform` (shade.rs): xyz: unit vector towards the sun; w: sun strength.
    sun: vec4<f32>,
    // x, z: the sun's compass direction times SUN_SIDE; y: sky scale; w: headlight.
    sky: vec4<f32>,
    // x: exposure; y: 1 for shadows; z: 1 for ambient occlusion.
    flags: vec4<f32>,
    // xyz: scene size in voxels.
    size: vec4<u32>,
    // xyz: regions per axis; w: iteration budget per ray.
    region_dims: vec4<u32>,
    // xyz: cells per axis; w: log2 of the words per page.
    cell_dims: vec4<u32>,
    // x, y: image size in pixels.
    image: vec4<u32>,
    // `BrickMap::occupied_regions`, inclusive region bounds; w: 1 when any region is occupied.
    occupied_lo: vec4<i32>,
    occupied_hi: vec4<i32>,
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

// 16-bit word `i` of the colour pool: two per word, the even one in the low half.
fn pool_word(i: u32) -> u32 {
    return (colour_word(i >> 1u) >> ((i & 1u) * 16u)) & 0xFFFFu;
}

// Weight `w` (0 to `top`) of the line from RGB565 `a` to `b`, channel by channel in integers
// (`protocol::blocks::mix`).
fn mix565(a: u32, b: u32, w: u32, top: u32) -> u32 {
    let half = top / 2u;
    let red = ((a >> 11u) * (top - w) + (b >> 11u) * w + half) / top;
    let green = (((a >> 5u) & 63u) * (top - w) + ((b >> 5u) & 63u) * w + half) / top;
    let blue = ((a & 31u) * (top - w) + (b & 31u) * w + half) / top;
    return (red << 11u) | (green << 5u) | blue;
}

// RGB565 colour of the voxel of rank `r` in the colour block at pool word `base`
// (`protocol::palette`, the same steps as `palette::colour_at_words`): a header word (bits 0-3
// the index width: 0 one colour, 15 raw, 14 and 13 bounded-error groups, else a palette of bits
// 4-11 + 1 entries), then the one colour, the raw colours, the groups of 16 (two end points and
// 2- or 3-bit weights: `protocol::blocks`), or the palette and the packed indices.
fn brick_colour(base: u32, r: u32) -> u32 {
    let header = pool_word(base);
    let bits = header & 15u;
    if bits == 0u {
        return pool_word(base + 1u);
    }
    if bits == 15u {
        return pool_word(base + 1u + r);
    }
    if bits == 14u || bits == 13u {
        // Weights of 2 bits (header 14) or 3 (header 13): groups of 2 + width words.
        let width = 16u - bits;
        let top = (1u << width) - 1u;
        let g = base + 1u + (r >> 4u) * (2u + width);
        let at = (r & 15u) * width;
        var weights = pool_word(g + 2u + (at >> 4u));
        if (at & 15u) + width > 16u {
            weights = weights | (pool_word(g + 3u + (at >> 4u)) << 16u);
        }
        let w = (weights >> (at & 15u)) & top;
        return mix565(pool_word(g), pool_word(g + 1u), w, top);
    }
    let entries = ((header >> 4u) & 255u) + 1u;
    let at = r * bits;
    let index = (pool_word(base + 1u + entries + (at >> 4u)) >> (at & 15u)) & ((1u << bits) - 1u);
    return pool_word(base + 1u + min(index, entries - 1u));
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
// Empty cells are coded like empty regions: `0xFFFFFF00 | clearance` (in cells).
// Stand-in region entries (`map/stand_in.rs`): `STAND_IN | level << 27 | slot`.
fn is_stand_in(entry: u32) -> bool {
    return (entry & STAND_IN) != 0u && !region_is_empty(entry);
}

fn stand_in_level(entry: u32) -> u32 {
    return (entry >> 27u) & 15u;
}

fn stand_in_slot(entry: u32) -> u32 {
    return entry & 0x7FFFFFFu;
}

// `map::coarse_bit`: the mask bit of the level-`level` voxel covering level-0 voxel `p`.
fn coarse_bit(p: vec3<i32>, level: u32) -> u32 {
    let g = (p >> vec3<u32>(level)) & vec3<i32>(7);
    return u32(g.x | (g.y << 3u) | (g.z << 6u));
}

fn cell_is_empty(entry: u32) -> bool {
    return entry >= EMPTY_REGION;
}
fn cell_clearance(entry: u32) -> i32 {
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

// `Dda::start_in` (with `t_min` 0): false when the ray misses the box `lo..hi` or is unusable.
fn start_in(origin: vec3<f32>, dir: vec3<f32>, lo: vec3<i32>, hi: vec3<i32>) -> bool {
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
    if all(first >= lo) && all(first < hi) {
        v = first;
    } else {
        var near = -BIG;
        var near_axis = 0;
        var far = BIG;
        var far_axis = 0;
        for (var i = 0; i < 3; i++) {
            if stp[i] == 0 {
                if origin[i] < f32(lo[i]) || origin[i] >= f32(hi[i]) {
                    return false;
                }
                continue;
            }
            var enter: f32;
            var leave: f32;
            if stp[i] > 0 {
                enter = plane_t(i, lo[i]);
                leave = plane_t(i, hi[i]);
            } else {
                enter = plane_t(i, hi[i]);
                leave = plane_t(i, lo[i]);
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
                v[i] = select(hi[k] - 1, lo[k], stp[k] > 0);
            } else {
                v[i] = settle(i, lo[i], hi[i] - 1, near, k);
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

// `trace_with_stats`, without the stats: only the occupied box is traced. (The CPU's beam
// pre-pass is not here: marched by one invocation per workgroup it cost lavapipe about 20%.)
fn trace(origin: vec3<f32>, dir: vec3<f32>) -> Hit {
    if frame.occupied_lo.w == 0 {
        return miss();
    }
    let rlo = frame.occupied_lo.xyz;
    let rhi = frame.occupied_hi.xyz;
    let box_hi = min((rhi + vec3<i32>(1)) * REGION_EDGE, vec3<i32>(frame.size.xyz));
    if !start_in(origin, dir, rlo * REGION_EDGE, box_hi) {
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
                let lo = max(r - vec3<i32>(clear), rlo);
                let hi = min(r + vec3<i32>(clear), rhi);
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
            if r[k] < rlo[k] || r[k] > rhi[k] {
                return miss();
            }
            rnext[k] = block_exit_t(k, r[k], REGION_EDGE);
        }
        if !v_valid {
            let lo = r * REGION_EDGE;
            enter_block(lo, min(lo + vec3<i32>(REGION_EDGE - 1), n - vec3<i32>(1)));
            v_valid = true;
        }
        if is_stand_in(block) {
            // A coarse brick stands in for this region: blocks of 2^level voxels (the whole
            // region from level 5 on), stepped like cells; a solid one is hit where entered.
            let level = stand_in_level(block);
            let slot = stand_in_slot(block);
            let scale = 1 << min(level, 5u);
            let lo = r * REGION_EDGE;
            let hi = min(lo + vec3<i32>(REGION_EDGE), n) - vec3<i32>(1);
            let blo = lo / scale;
            let bhi = hi / scale;
            var b = v / scale;
            var bnext = block_exit(b, scale);
            loop {
                if budget == 0u {
                    return miss();
                }
                budget -= 1u;
                let bit = coarse_bit(b * scale, level);
                if ((mask_word(slot * 16u + (bit >> 5u)) >> (bit & 31u)) & 1u) != 0u {
                    if !v_valid {
                        let at = b * scale;
                        enter_block(at, min(at + vec3<i32>(scale - 1), hi));
                    }
                    return make_hit(brick_colour(colour_bases[slot], rank(slot, bit)));
                }
                v_valid = false;
                let k = earliest(bnext);
                t = bnext[k];
                axis = k;
                b[k] += stp[k];
                if b[k] < blo[k] || b[k] > bhi[k] {
                    r[k] += stp[k];
                    if r[k] < rlo[k] || r[k] > rhi[k] {
                        return miss();
                    }
                    rnext[k] = block_exit_t(k, r[k], REGION_EDGE);
                    break;
                }
                bnext[k] = block_exit_t(k, b[k], scale);
            }
            continue;
        }
        // Cell level, inside this region: cells `clo..=chi`.
        let clo = r * 4;
        let chi = min(clo + vec3<i32>(3), cdims - vec3<i32>(1));
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
            if cell_is_empty(slot) {
                v_valid = false;
                let clear = cell_clearance(slot);
                if clear >= 1 {
                    let lo = max(c - vec3<i32>(clear), clo);
                    let hi = min(c + vec3<i32>(clear), chi);
                    let exit = block_exit(select(lo, hi, stp > vec3<i32>(0)), BRICK_EDGE);
                    k = earliest(exit);
                    t = exit[k];
                    axis = k;
                    for (var i = 0; i < 3; i++) {
                        if i != k {
                            c[i] = settle_scaled(i, lo[i], hi[i], t, k, BRICK_EDGE);
                            cnext[i] = block_exit_t(i, c[i], BRICK_EDGE);
                        }
                    }
                    c[k] = select(lo[k] - 1, hi[k] + 1, stp[k] > 0);
                    cnext[k] = block_exit_t(k, c[k], BRICK_EDGE);
                } else {
                    k = earliest(cnext);
                    t = cnext[k];
                    axis = k;
                    c[k] += stp[k];
                    cnext[k] = block_exit_t(k, c[k], BRICK_EDGE);
                }
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
                        return make_hit(brick_colour(colour_bases[slot], rank(slot, bit)));
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
            if c[k] < clo[k] || c[k] > chi[k] {
                r[k] += stp[k];
                if r[k] < rlo[k] || r[k] > rhi[k] {
                    return miss();
                }
                rnext[k] = block_exit_t(k, r[k], REGION_EDGE);
                break;
            }
        }
    }
    return miss();
}

// ---- shading (shade.rs) ----------------------------------------------------------------------

const SKY_ZENITH: vec3<f32> = vec3<f32>(0.80, 0.88, 1.0);
const SKY_GROUND: vec3<f32> = vec3<f32>(0.22, 0.20, 0.18);
const SUN_COLOUR: vec3<f32> = vec3<f32>(1.0, 0.94, 0.82);
const AO_FLOOR: f32 = 0.3;

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        return c / 12.92;
    }
    return pow((c + 0.055) / 1.055, 2.4);
}

fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.0031308 {
        return c * 12.92;
    }
    return 1.055 * pow(c, 1.0 / 2.4) - 0.055;
}

fn albedo(c: u32) -> vec3<f32> {
    let r5 = f32((c >> 11u) & 0x1Fu);
    let g6 = f32((c >> 5u) & 0x3Fu);
    let b5 = f32(c & 0x1Fu);
    return vec3<f32>(srgb_to_linear(r5 / 31.0), srgb_to_linear(g6 / 63.0), srgb_to_linear(b5 / 31.0));
}

fn sky(dir: vec3<f32>) -> vec3<f32> {
    let len = sqrt(dot(dir, dir));
    let up = select(0.0, dir.y / len, len > 0.0);
    let s = clamp(up * 0.5 + 0.5, 0.0, 1.0);
    return vec3<f32>(0.80 - 0.35 * s, 0.87 - 0.25 * s, 0.95 - 0.05 * s);
}

fn sky_light(nrm: vec3<f32>) -> vec3<f32> {
    let h = 0.5 + 0.5 * nrm.y;
    let side = 1.0 + nrm.x * frame.sky.x + nrm.z * frame.sky.z;
    let scale = side * frame.sky.y;
    return (SKY_GROUND + (SKY_ZENITH - SKY_GROUND) * h) * scale;
}

// `BrickMap::is_solid`: false outside the grid.
fn solid(p: vec3<i32>) -> bool {
    if any(p < vec3<i32>(0)) || any(p >= vec3<i32>(frame.size.xyz)) {
        return false;
    }
    let rdims = vec3<i32>(frame.region_dims.xyz);
    let r = p / REGION_EDGE;
    let entry = regions[u32(r.x + rdims.x * (r.y + rdims.y * r.z))];
    if region_is_empty(entry) {
        return false;
    }
    if is_stand_in(entry) {
        let bit = coarse_bit(p, stand_in_level(entry));
        let slot = stand_in_slot(entry);
        return ((mask_word(slot * 16u + (bit >> 5u)) >> (bit & 31u)) & 1u) != 0u;
    }
    let c = p / BRICK_EDGE;
    let local = u32((c.x & 3) | ((c.y & 3) << 2u) | ((c.z & 3) << 4u));
    let slot = cell_word(entry * 64u + local);
    if cell_is_empty(slot) {
        return false;
    }
    let bit = u32((p.x & 7) | ((p.y & 7) << 3u) | ((p.z & 7) << 6u));
    return ((mask_word(slot * 16u + (bit >> 5u)) >> (bit & 31u)) & 1u) != 0u;
}

fn occupied(p: vec3<i32>) -> f32 {
    return select(0.0, 1.0, solid(p));
}

fn corner_level(side_a: f32, side_b: f32, diagonal: f32) -> f32 {
    if side_a + side_b == 2.0 {
        return 0.0;
    }
    return 3.0 - (side_a + side_b + diagonal);
}

// `ambient_occlusion`.
fn ambient_occlusion(hit: Hit, origin: vec3<f32>, dir: vec3<f32>) -> f32 {
    var k = -1;
    for (var i = 0; i < 3; i++) {
        if k < 0 && hit.normal[i] != 0 {
            k = i;
        }
    }
    if k < 0 {
        return 1.0;
    }
    let a = (k + 1) % 3;
    let b = (k + 2) % 3;
    var ea = vec3<i32>(0);
    ea[a] = 1;
    var eb = vec3<i32>(0);
    eb[b] = 1;
    let front = hit.voxel + hit.normal;
    let am = occupied(front - ea);
    let ap = occupied(front + ea);
    let bm = occupied(front - eb);
    let bp = occupied(front + eb);
    let l00 = corner_level(am, bm, occupied(front - ea - eb));
    let l10 = corner_level(ap, bm, occupied(front + ea - eb));
    let l01 = corner_level(am, bp, occupied(front - ea + eb));
    let l11 = corner_level(ap, bp, occupied(front + ea + eb));
    let u = clamp(origin[a] + dir[a] * hit.t - f32(hit.voxel[a]), 0.0, 1.0);
    let w = clamp(origin[b] + dir[b] * hit.t - f32(hit.voxel[b]), 0.0, 1.0);
    let lo = l00 + (l10 - l00) * u;
    let hi = l01 + (l11 - l01) * u;
    let level = lo + (hi - lo) * w;
    return AO_FLOOR + (1.0 - AO_FLOOR) * (level / 3.0);
}

// `sun_reaches`.
fn sun_reaches(hit: Hit) -> bool {
    if frame.flags.y == 0.0 || all(hit.normal == vec3<i32>(0)) {
        return true;
    }
    let front = vec3<f32>(hit.voxel + hit.normal) + vec3<f32>(0.5);
    return !trace(front, frame.sun.xyz).found;
}

// `shade`.
fn shade(hit: Hit, dir: vec3<f32>, sun_visible: bool, ao: f32) -> vec3<f32> {
    let nrm = vec3<f32>(hit.normal);
    let sky_in = sky_light(nrm);
    let len = sqrt(dot(dir, dir));
    var facing = 0.0;
    if len > 0.0 {
        facing = max(-dot(nrm, dir) / len, 0.0);
    }
    let head = frame.sky.w * facing;
    let cos_sun = max(dot(nrm, frame.sun.xyz), 0.0);
    var sun = 0.0;
    if sun_visible {
        sun = frame.sun.w * cos_sun;
    }
    let light = (sky_in + vec3<f32>(head)) * ao + SUN_COLOUR * sun;
    let c = albedo(hit.colour) * light * frame.flags.x;
    let mapped = vec3<f32>(1.0) - exp(-c);
    return vec3<f32>(linear_to_srgb(mapped.x), linear_to_srgb(mapped.y), linear_to_srgb(mapped.z));
}

// `shade_hit`.
fn shade_hit(hit: Hit, origin: vec3<f32>, dir: vec3<f32>) -> vec3<f32> {
    let faces_sun = dot(vec3<f32>(hit.normal), frame.sun.xyz) > 0.0 && frame.sun.w > 0.0;
    var sun_visible = false;
    if faces_sun {
        sun_visible = sun_reaches(hit);
    }
    var ao = 1.0;
    if frame.flags.z != 0.0 {
        ao = ambient_occlusion(hit, origin, dir);
    }
    return shade(hit, dir, sun_visible, ao);
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
        rgb = shade_hit(hit, frame.eye.xyz, dir);
        let p = vec3<u32>(hit.voxel);
        record = vec2<u32>(p.x | (p.y << 16u), p.z);
    } else {
        rgb = sky(dir);
    }
    textureStore(out_image, vec2<i32>(id.xy), vec4<f32>(clamp(rgb, vec3<f32>(0.0), vec3<f32>(1.0)), 1.0));
    textureStore(out_hits, vec2<i32>(id.xy), vec4<u32>(record, 0u, 0u));
}
