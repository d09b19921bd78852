//! Shading: the colour of a hit, identical in `shaders/trace.wgsl`.
//!
//! Why this model: indoors the sun reaches almost nothing, so a constant ambient paints every
//! face of an untextured room the same grey and walls, tables and chairs vanish into each other.
//! Every term here depends on the face's normal or on its neighbours, so shape shows everywhere:
//!
//! * **Sky light** ([`sky_light`]): a hemisphere between a warm ground bounce and a blue zenith,
//!   brighter on the side the sun is on. The six face directions of a voxel all get different
//!   amounts (with the default sun), lit by the sun or not.
//! * **Ambient occlusion** ([`ambient_occlusion`]): the classic voxel AO ("smooth lighting"):
//!   each corner of the hit face darkens by how many of the three voxels around it (two sides,
//!   one diagonal) are solid, in the layer in front of the face, and the hit point interpolates
//!   the four corners bilinearly. Exact and deterministic: eight occupancy lookups, no rays.
//! * **Sun** with its shadow ray, traced only where the face turns towards it (by the CPU
//!   renderer from a per-frame table of the sun's voxel walk, [`crate::shadow::SunPaths`]).
//! * **Headlight**: a light carried by the camera, for scenes the sky and sun cannot reach.
//! * **Exposure and tone mapping**: albedo is decoded from sRGB, light is summed in linear
//!   units, `1 - exp(-exposure · c)` rolls bright values off instead of clipping them, and the
//!   result is encoded back to sRGB for an 8-bit, non-sRGB target (on the CPU both curves are
//!   tables: [`tone_map`], [`encode_srgb`]).
//!
//! AO and the headlight scale the sky term, not the sun: the sun has its own (sharp) shadow.
//! Everything a pixel needs that does not depend on the pixel (the sun's horizontal direction,
//! the flags) is computed once in [`Lighting::uniform`] and handed to the shader, so both twins
//! do the same float operations per pixel.

use std::sync::LazyLock;

use crate::brick::{BRICK_EDGE, mask_get};
use crate::colour::Colour;
use crate::map::BrickMap;
use crate::shadow::SunPaths;
use crate::trace::{Hit, Ray, blocked};

/// Zenith colour of the sky light (linear RGB, before [`Lighting::sky`]). Chosen with
/// [`SKY_GROUND`] and [`SUN_SIDE`] so that, under the default sun, the six face directions get
/// six clearly different amounts: up > towards the sun's side (two) > away (two) > down.
pub const SKY_ZENITH: [f32; 3] = [0.80, 0.88, 1.0];
/// Light bounced up from the ground, what faces pointing down receive.
pub const SKY_GROUND: [f32; 3] = [0.22, 0.20, 0.18];
/// How much brighter the sky is on the sun's side: faces turned towards the sun's compass
/// direction get `1 + SUN_SIDE`, faces turned away `1 - SUN_SIDE`.
pub const SUN_SIDE: f32 = 0.3;
/// Sun colour (linear RGB, before [`Lighting::sun_strength`]).
pub const SUN_COLOUR: [f32; 3] = [1.0, 0.94, 0.82];
/// What a fully occluded corner (AO level 0 of 3) keeps of the sky light.
pub const AO_FLOOR: f32 = 0.3;

/// How a frame is lit. Shared by the CPU renderer and the shader (see [`Lighting::uniform`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lighting {
    /// Unit vector towards the sun.
    pub sun: [f32; 3],
    /// Sun irradiance on a face square to it, in linear units (0 turns the sun off).
    pub sun_strength: f32,
    /// Scale of the sky light ([`SKY_ZENITH`], [`SKY_GROUND`]).
    pub sky: f32,
    /// Irradiance of the light at the camera on a face square to the view ray.
    pub headlight: f32,
    /// Multiplies the light before tone mapping: above 1 brightens dark scenes.
    pub exposure: f32,
    /// Trace a ray towards the sun from the empty voxel in front of each hit that faces it.
    pub shadows: bool,
    /// Darken corners and creases by their neighbours ([`ambient_occlusion`]).
    pub ao: bool,
}

impl Default for Lighting {
    fn default() -> Self {
        Lighting {
            sun: normalize([0.5, 0.8, 0.25]).unwrap_or([0.0, 1.0, 0.0]),
            sun_strength: 2.0,
            sky: 0.8,
            // Off by default: a light that follows the view makes the same face change brightness
            // as the camera turns, and evens out exactly the face differences the sky light
            // makes. `--headlight` (or H in the viewers) turns it on.
            headlight: 0.0,
            exposure: 1.0,
            shadows: true,
            ao: true,
        }
    }
}

/// Why a [`Lighting`] a user asked for cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LightingError {
    #[error("the sun direction {0:?} is not a usable direction (zero length or not finite)")]
    BadSun([f32; 3]),
    #[error("{0} must be a finite number from 0 to 100, got {1}")]
    OutOfRange(&'static str, f32),
}

/// The per-frame lighting constants exactly as the shader receives them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightUniform {
    /// xyz: unit vector towards the sun; w: sun strength.
    pub sun: [f32; 4],
    /// x, z: the sun's compass direction (unit, or zero when the sun is overhead) times
    /// [`SUN_SIDE`]; y: sky scale; w: headlight.
    pub sky: [f32; 4],
    /// x: exposure; y: 1 for shadows; z: 1 for AO.
    pub flags: [f32; 4],
}

impl Lighting {
    /// A lighting with the sun towards `sun` (any length) and the given strengths; checks
    /// everything a user can type.
    pub fn checked(self) -> Result<Lighting, LightingError> {
        let sun = normalize(self.sun).ok_or(LightingError::BadSun(self.sun))?;
        for (name, value) in [
            ("sun strength", self.sun_strength),
            ("sky", self.sky),
            ("headlight", self.headlight),
            ("exposure", self.exposure),
        ] {
            if !(value.is_finite() && (0.0..=100.0).contains(&value)) {
                return Err(LightingError::OutOfRange(name, value));
            }
        }
        Ok(Lighting { sun, ..self })
    }

    /// The constants the shader's `Frame` uniform carries for this lighting.
    pub fn uniform(&self) -> LightUniform {
        let [sx, _, sz] = self.sun;
        let len = (sx * sx + sz * sz).sqrt();
        let (hx, hz) = if len > 1e-6 {
            (sx / len * SUN_SIDE, sz / len * SUN_SIDE)
        } else {
            (0.0, 0.0)
        };
        LightUniform {
            sun: [self.sun[0], self.sun[1], self.sun[2], self.sun_strength],
            sky: [hx, self.sky, hz, self.headlight],
            flags: [
                self.exposure,
                f32::from(u8::from(self.shadows)),
                f32::from(u8::from(self.ao)),
                0.0,
            ],
        }
    }
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn normalize(a: [f32; 3]) -> Option<[f32; 3]> {
    let len = dot(a, a).sqrt();
    (len > 1e-12 && len.is_finite()).then(|| a.map(|c| c / len))
}

/// Sky colour for a missed ray: a vertical gradient on the ray direction, already in display
/// (sRGB) values.
pub fn sky(dir: [f32; 3]) -> [f32; 3] {
    let len = dot(dir, dir).sqrt();
    let up = if len > 0.0 { dir[1] / len } else { 0.0 };
    let t = (up * 0.5 + 0.5).clamp(0.0, 1.0);
    [0.80 - 0.35 * t, 0.87 - 0.25 * t, 0.95 - 0.05 * t]
}

/// sRGB-encoded channel → linear.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear channel in 0..1 → sRGB-encoded.
pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// [`linear_to_srgb`] at 4096 even steps of 0..=1, for [`encode_srgb`].
static SRGB_STEPS: LazyLock<[f32; 4097]> =
    LazyLock::new(|| std::array::from_fn(|i| linear_to_srgb(i as f32 / 4096.0)));

/// [`linear_to_srgb`] by linear interpolation in a table: three `powf` calls per pixel cost more
/// than tracing some rays. Within 2e-5 of the formula (0.005 of an 8-bit level) everywhere, so
/// the shader, which calls `pow`, stays within the twins' tolerance.
#[inline]
pub fn encode_srgb(c: f32) -> f32 {
    // NaN lands on 0, like `to_byte`.
    let x = if c > 0.0 { c.min(1.0) * 4096.0 } else { 0.0 };
    let i = (x as usize).min(4095);
    let f = x - i as f32;
    let (a, b) = (SRGB_STEPS[i], SRGB_STEPS[i + 1]);
    a + (b - a) * f
}

/// Where [`TONE_STEPS`] ends: past it `1 - exp(-c)` is 1 within 1.2e-7.
const TONE_END: f32 = 16.0;

/// `1 - exp(-c)` at 4096 even steps of `0..=TONE_END`, for [`tone_map`].
static TONE_STEPS: LazyLock<[f32; 4097]> =
    LazyLock::new(|| std::array::from_fn(|i| 1.0 - (-(i as f32) * TONE_END / 4096.0).exp()));

/// The tone curve `1 - exp(-c)` by linear interpolation in a table, for the same reason as
/// [`encode_srgb`]: three `exp` calls per pixel cost about as much as the rest of the shading.
/// Within 2e-6 of the formula everywhere (the curve bends at most by 1 per unit², so a step of
/// 1/256 leaves at most 1/8 of a step² of error).
#[inline]
pub fn tone_map(c: f32) -> f32 {
    // NaN and negative light land on 0.
    let x = if c > 0.0 {
        c.min(TONE_END) * (4096.0 / TONE_END)
    } else {
        0.0
    };
    let i = (x as usize).min(4095);
    let f = x - i as f32;
    let (a, b) = (TONE_STEPS[i], TONE_STEPS[i + 1]);
    a + (b - a) * f
}

/// Linear albedo of each 5-bit and 6-bit channel value: RGB565 has only 32 and 64 levels, so
/// the CPU looks them up instead of calling `powf` per pixel (same formula, same results).
static LINEAR5: LazyLock<[f32; 32]> =
    LazyLock::new(|| std::array::from_fn(|i| srgb_to_linear(i as f32 / 31.0)));
static LINEAR6: LazyLock<[f32; 64]> =
    LazyLock::new(|| std::array::from_fn(|i| srgb_to_linear(i as f32 / 63.0)));

/// A voxel colour as linear albedo.
pub fn albedo(colour: Colour) -> [f32; 3] {
    let c = colour.0;
    [
        LINEAR5[usize::from((c >> 11) & 0x1F)],
        LINEAR6[usize::from((c >> 5) & 0x3F)],
        LINEAR5[usize::from(c & 0x1F)],
    ]
}

/// Sky light reaching a face with normal `n` (linear RGB).
pub fn sky_light(n: [f32; 3], u: &LightUniform) -> [f32; 3] {
    let h = 0.5 + 0.5 * n[1];
    let side = 1.0 + n[0] * u.sky[0] + n[2] * u.sky[2];
    let scale = side * u.sky[1];
    std::array::from_fn(|i| (SKY_GROUND[i] + (SKY_ZENITH[i] - SKY_GROUND[i]) * h) * scale)
}

/// AO level (0..=3) of the face corner at `(ca, cb)` from its two side voxels and the diagonal.
#[inline]
fn corner_level(side_a: f32, side_b: f32, diagonal: f32) -> f32 {
    if side_a + side_b == 2.0 {
        0.0
    } else {
        3.0 - (side_a + side_b + diagonal)
    }
}

/// How much sky light reaches the hit point, `AO_FLOOR..=1`: the voxel AO of the face it hit.
/// 1 for a hit without a face (the ray started inside the voxel).
pub fn ambient_occlusion(map: &BrickMap, hit: &Hit, ray: &Ray) -> f32 {
    let n = hit.normal;
    let k = if n[0] != 0 {
        0
    } else if n[1] != 0 {
        1
    } else if n[2] != 0 {
        2
    } else {
        return 1.0;
    };
    let (a, b) = ((k + 1) % 3, (k + 2) % 3);
    let size = map.size().map(|s| s as i32);
    let front: [i32; 3] = std::array::from_fn(|i| hit.voxel[i] as i32 + n[i]);
    if front[k] < 0 || front[k] >= size[k] {
        return 1.0;
    }
    // The 3×3 neighbours of the front voxel in the face's plane, bit (da + 1) + 3·(db + 1).
    // They lie in at most two bricks along each of the two axes, usually in one brick: each
    // brick's mask is looked up once and answers for the neighbours inside it (and inside the
    // grid), found as ranges of `da` and `db` rather than tested one by one.
    const E: i32 = BRICK_EDGE as i32;
    const STRIDE: [i32; 3] = [1, E, E * E];
    let (fa, fb) = (front[a], front[b]);
    let (a0, a1) = ((fa - 1).div_euclid(E), (fa + 1).div_euclid(E));
    let (b0, b1) = ((fb - 1).div_euclid(E), (fb + 1).div_euclid(E));
    let base_bit = (front[k] & (E - 1)) * STRIDE[k];
    let mut bits = 0u32;
    if map.stand_in_count() > 0 {
        // Coarse bricks stand in for some regions: ask voxel by voxel what the map shows.
        for db in -1..=1 {
            for da in -1..=1 {
                let mut p = front;
                p[a] += da;
                p[b] += db;
                if map.looks_solid(p) {
                    bits |= 1 << ((da + 1) + 3 * (db + 1));
                }
            }
        }
    } else {
        for ca in a0..=a1 {
            // The `da` whose voxel is in brick column `ca` and in the grid.
            let da_lo = (ca * E - fa).max(-1).max(-fa);
            let da_hi = (ca * E + E - 1 - fa).min(1).min(size[a] - 1 - fa);
            for cb in b0..=b1 {
                let db_lo = (cb * E - fb).max(-1).max(-fb);
                let db_hi = (cb * E + E - 1 - fb).min(1).min(size[b] - 1 - fb);
                if da_lo > da_hi || db_lo > db_hi {
                    continue;
                }
                let mut cell = [0u32; 3];
                cell[k] = (front[k] / E) as u32;
                cell[a] = ca as u32;
                cell[b] = cb as u32;
                let Some(mask) = map
                    .slot_of_cell(cell)
                    .and_then(|slot| map.masks().get(slot as usize))
                else {
                    continue;
                };
                for db in db_lo..=db_hi {
                    let row = base_bit + ((fb + db) & (E - 1)) * STRIDE[b];
                    for da in da_lo..=da_hi {
                        let bit = row + ((fa + da) & (E - 1)) * STRIDE[a];
                        if mask_get(mask, bit as u32) {
                            bits |= 1 << ((da + 1) + 3 * (db + 1));
                        }
                    }
                }
            }
        }
    }
    let solid = |da: i32, db: i32| -> f32 { ((bits >> ((da + 1) + 3 * (db + 1))) & 1) as f32 };
    let (am, ap, bm, bp) = (solid(-1, 0), solid(1, 0), solid(0, -1), solid(0, 1));
    let l00 = corner_level(am, bm, solid(-1, -1));
    let l10 = corner_level(ap, bm, solid(1, -1));
    let l01 = corner_level(am, bp, solid(-1, 1));
    let l11 = corner_level(ap, bp, solid(1, 1));
    let u = (ray.origin[a] + ray.dir[a] * hit.t - hit.voxel[a] as f32).clamp(0.0, 1.0);
    let w = (ray.origin[b] + ray.dir[b] * hit.t - hit.voxel[b] as f32).clamp(0.0, 1.0);
    let lo = l00 + (l10 - l00) * u;
    let hi = l01 + (l11 - l01) * u;
    let level = lo + (hi - lo) * w;
    AO_FLOOR + (1.0 - AO_FLOOR) * (level / 3.0)
}

/// Whether the sun reaches a hit: false when shadows are on and a ray from the empty voxel in
/// front of the hit towards the sun meets a voxel. Starting from that voxel's centre keeps the
/// shadow ray off the hit surface without any epsilon. Only asked for faces turned to the sun.
/// `paths`, the frame's table of the sun's voxel walk, answers the same faster.
pub fn sun_reaches(
    map: &BrickMap,
    hit: &Hit,
    lighting: &Lighting,
    paths: Option<&SunPaths>,
) -> bool {
    if !lighting.shadows || hit.normal == [0; 3] {
        return true;
    }
    let from: [i32; 3] = std::array::from_fn(|i| hit.voxel[i] as i32 + hit.normal[i]);
    match paths {
        Some(paths) if paths.dir() == lighting.sun => !paths.blocked(map, from),
        _ => !blocked(
            map,
            &Ray {
                origin: from.map(|c| c as f32 + 0.5),
                dir: lighting.sun,
            },
        ),
    }
}

/// Display colour (sRGB, 0..1) of a hit, from its albedo, normal, the view ray, the AO factor
/// and whether the sun reaches it.
pub fn shade(hit: &Hit, dir: [f32; 3], u: &LightUniform, sun_visible: bool, ao: f32) -> [f32; 3] {
    let n = hit.normal.map(|c| c as f32);
    let sky = sky_light(n, u);
    let len = dot(dir, dir).sqrt();
    let facing = if len > 0.0 {
        (-dot(n, dir) / len).max(0.0)
    } else {
        0.0
    };
    let head = u.sky[3] * facing;
    let cos_sun = dot(n, [u.sun[0], u.sun[1], u.sun[2]]).max(0.0);
    let sun = if sun_visible { u.sun[3] * cos_sun } else { 0.0 };
    let albedo = albedo(hit.colour);
    std::array::from_fn(|i| {
        let light = (sky[i] + head) * ao + SUN_COLOUR[i] * sun;
        let c = albedo[i] * light * u.flags[0];
        encode_srgb(tone_map(c))
    })
}

/// Everything about one hit: AO, the sun's shadow ray where the face turns towards the sun, and
/// the shaded colour (display values, 0..1).
pub fn shade_hit(
    map: &BrickMap,
    hit: &Hit,
    ray: &Ray,
    lighting: &Lighting,
    u: &LightUniform,
    paths: Option<&SunPaths>,
) -> [f32; 3] {
    let faces_sun =
        dot(hit.normal.map(|c| c as f32), lighting.sun) > 0.0 && lighting.sun_strength > 0.0;
    let sun_visible = faces_sun && sun_reaches(map, hit, lighting, paths);
    let ao = if lighting.ao {
        ambient_occlusion(map, hit, ray)
    } else {
        1.0
    };
    shade(hit, ray.dir, u, sun_visible, ao)
}

/// Converts a 0..1 channel to a byte, rounding to nearest.
#[inline]
pub fn to_byte(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_tone_map_follows_the_formula() {
        let worst = (0..=200_000)
            .map(|i| i as f32 / 10_000.0)
            .map(|c| (tone_map(c) - (1.0 - (-c).exp())).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 2e-6, "worst error {worst}");
        assert_eq!(tone_map(-1.0), 0.0);
        assert_eq!(tone_map(f32::NAN), 0.0);
        assert!((tone_map(f32::INFINITY) - 1.0).abs() < 2e-7);
    }

    #[test]
    fn table_encoding_follows_the_formula() {
        let worst = (0..=100_000)
            .map(|i| i as f32 / 100_000.0)
            .map(|c| (encode_srgb(c) - linear_to_srgb(c)).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 2e-5, "worst error {worst}");
        assert_eq!(encode_srgb(-1.0), 0.0);
        assert!((encode_srgb(2.0) - 1.0).abs() < 1e-6);
        assert_eq!(encode_srgb(f32::NAN), 0.0);
    }

    #[test]
    fn every_face_direction_gets_a_different_sky_light() {
        let u = Lighting::default().uniform();
        let mut seen: Vec<f32> = [
            [1, 0, 0],
            [-1, 0, 0],
            [0, 1, 0],
            [0, -1, 0],
            [0, 0, 1],
            [0, 0, -1],
        ]
        .iter()
        .map(|n: &[i32; 3]| sky_light(n.map(|c| c as f32), &u)[1])
        .collect();
        seen.sort_by(f32::total_cmp);
        for pair in seen.windows(2) {
            assert!(pair[1] > pair[0] * 1.1, "too close: {seen:?}");
        }
    }
}
