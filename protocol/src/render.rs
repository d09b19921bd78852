//! Camera and the multi-threaded CPU renderer (shading lives in [`crate::shade`]).
//!
//! This is the oracle for the GPU tracer and the fallback renderer for machines without one.
//! Everything a pixel depends on (the camera basis, per-pixel steps, the light) is computed once
//! here and handed to the shader as uniforms, so CPU and GPU do the same float operations per
//! pixel; only the few pixels exactly on a voxel edge can differ.

use std::sync::atomic::{AtomicU32, Ordering};

use crate::beam::{TILE, TileStarts};
use crate::map::BrickMap;
pub use crate::shade::{LightUniform, Lighting, LightingError, sky, to_byte};
use crate::shade::{normalize, shade_hit};
use crate::shadow::SunPaths;
use crate::trace::{Hit, PendingHit, Ray, TraceStats, trace, trace_pending};

/// Marks a pixel whose primary ray missed, in [`Frame::hits`].
pub const MISS: u32 = u32::MAX;

/// A pinhole camera in voxel units, y up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub eye: [f32; 3],
    pub target: [f32; 3],
    /// Vertical field of view in degrees.
    pub fov_y: f32,
}

/// The per-frame constants of a camera at a resolution: what the shader receives.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projection {
    pub eye: [f32; 3],
    pub forward: [f32; 3],
    /// Right vector scaled to the width of one pixel at unit distance.
    pub right: [f32; 3],
    /// Up vector scaled to the height of one pixel at unit distance.
    pub up: [f32; 3],
    pub width: u32,
    pub height: u32,
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn scale(a: [f32; 3], s: f32) -> [f32; 3] {
    a.map(|c| c * s)
}

impl Camera {
    /// A view of the whole scene from above one corner, looking across it: the default when a
    /// user names no camera.
    pub fn overview(size: [u32; 3]) -> Camera {
        let [sx, sy, sz] = size.map(|s| s as f32);
        Camera {
            eye: [-0.117 * sx, 0.45 * sy.max(0.25 * sx.max(sz)), -0.117 * sz],
            target: [0.586 * sx, 0.117 * sy, 0.586 * sz],
            fov_y: 55.0,
        }
    }

    /// Per-frame constants for a `width`×`height` image; `None` for a degenerate camera (eye on
    /// target, non-finite values, zero-sized image).
    pub fn project(&self, width: u32, height: u32) -> Option<Projection> {
        if width == 0 || height == 0 || !(self.fov_y > 0.0 && self.fov_y < 180.0) {
            return None;
        }
        let forward = normalize(sub(self.target, self.eye))?;
        // Looking straight up or down: pick another reference so the basis stays defined.
        let reference = if forward[1].abs() > 0.999 {
            [0.0, 0.0, 1.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let right = normalize(cross(forward, reference))?;
        let up = cross(right, forward);
        let half_h = (self.fov_y.to_radians() * 0.5).tan();
        let pixel = 2.0 * half_h / height as f32;
        Some(Projection {
            eye: self.eye,
            forward,
            right: scale(right, pixel),
            up: scale(up, pixel),
            width,
            height,
        })
    }
}

impl Projection {
    /// The primary ray through the centre of pixel `(x, y)` (y down).
    #[inline]
    pub fn ray(&self, x: u32, y: u32) -> Ray {
        let u = x as f32 + 0.5 - self.width as f32 * 0.5;
        let v = self.height as f32 * 0.5 - (y as f32 + 0.5);
        let dir = std::array::from_fn(|i| self.forward[i] + self.right[i] * u + self.up[i] * v);
        Ray {
            origin: self.eye,
            dir,
        }
    }
}

/// One rendered image plus what each pixel hit, for comparing renderers.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// RGBA8, row-major, top row first.
    pub pixels: Vec<[u8; 4]>,
    /// Linear voxel index (`x + sx·(y + sy·z)`) of each pixel's primary hit, or [`MISS`].
    pub hits: Vec<u32>,
}

/// Linear index of a voxel, as used in [`Frame::hits`]. Scenes of more than 2^32 voxels wrap it
/// (it only identifies a hit for comparing renderers), so no scene size can make it panic.
pub fn voxel_index(size: [u32; 3], v: [u32; 3]) -> u32 {
    v[0].wrapping_add(size[0].wrapping_mul(v[1].wrapping_add(size[1].wrapping_mul(v[2]))))
}

/// Shaded colour and voxel index of a primary ray's result.
fn pixel_of(
    map: &BrickMap,
    ray: &Ray,
    hit: Option<Hit>,
    lighting: &Lighting,
    uniform: &LightUniform,
    paths: Option<&SunPaths>,
) -> ([u8; 4], u32) {
    match hit {
        Some(hit) => {
            let rgb = shade_hit(map, &hit, ray, lighting, uniform, paths);
            (
                [to_byte(rgb[0]), to_byte(rgb[1]), to_byte(rgb[2]), 255],
                voxel_index(map.size(), hit.voxel),
            )
        }
        None => {
            let rgb = sky(ray.dir);
            (
                [to_byte(rgb[0]), to_byte(rgb[1]), to_byte(rgb[2]), 255],
                MISS,
            )
        }
    }
}

/// Renders one pixel: shaded colour and primary hit. `uniform` is `lighting.uniform()`, computed
/// once per frame. (The frame renderers trace the same hit faster, after a beam pre-pass.)
pub fn render_pixel(
    map: &BrickMap,
    projection: &Projection,
    lighting: &Lighting,
    uniform: &LightUniform,
    x: u32,
    y: u32,
) -> ([u8; 4], u32) {
    let ray = projection.ray(x, y);
    pixel_of(map, &ray, trace(map, &ray), lighting, uniform, None)
}

/// Calls `f(x, y, ray, hit)` for each pixel of the band of rows `y0..y0 + TILE` with its
/// primary hit, tile by tile: the tile's rays start where the beam pre-pass ([`TileStarts`])
/// puts them, and their colours are read after all of them are traced ([`PendingHit`]).
fn for_band(
    map: &BrickMap,
    projection: &Projection,
    y0: u32,
    mut f: impl FnMut(u32, u32, &Ray, Option<Hit>),
) {
    let y1 = (y0 + TILE).min(projection.height);
    let mut pending: Vec<(u32, u32, Option<PendingHit>)> =
        Vec::with_capacity((TILE * TILE) as usize);
    for x0 in (0..projection.width).step_by(TILE as usize) {
        let x1 = (x0 + TILE).min(projection.width);
        let starts = TileStarts::new(projection, map, x0, y0);
        let mut stats = TraceStats::default();
        for y in y0..y1 {
            for x in x0..x1 {
                let ray = projection.ray(x, y);
                pending.push((x, y, trace_pending(map, &ray, starts.at(x, y), &mut stats)));
            }
        }
        // Colours after the whole tile is traced: their loads (which usually miss) overlap.
        for (x, y, hit) in pending.drain(..) {
            f(x, y, &projection.ray(x, y), hit.map(|h| h.resolve(map)));
        }
    }
}

/// Renders a frame on `threads` threads (0 = all cores). Bands of [`TILE`] rows are handed out
/// one at a time from a shared counter, so a thread that draws sky does not sit idle while
/// another draws terrain.
pub fn render(
    map: &BrickMap,
    projection: &Projection,
    lighting: &Lighting,
    threads: usize,
) -> Frame {
    let w = projection.width;
    let uniform = lighting.uniform();
    // The sun's voxel walk, once per frame, for every shadow ray ([`SunPaths`]).
    let paths =
        (lighting.shadows && lighting.sun_strength > 0.0).then(|| SunPaths::shared(lighting.sun));
    let mut pixels = vec![[0u8; 4]; (w * projection.height) as usize];
    let mut hits = vec![MISS; (w * projection.height) as usize];
    let bands = by_bands(projection.height, threads, |y0| {
        let mut band = Vec::with_capacity((w * TILE) as usize);
        for_band(map, projection, y0, |x, y, ray, hit| {
            let (p, hit) = pixel_of(map, ray, hit, lighting, &uniform, paths.as_deref());
            band.push(((y * w + x) as usize, p, hit));
        });
        band
    });
    for (_, band) in bands {
        for (at, p, hit) in band {
            pixels[at] = p;
            hits[at] = hit;
        }
    }
    Frame {
        width: w,
        height: projection.height,
        pixels,
        hits,
    }
}

/// Traces just the primary rays of a frame on `threads` threads, without shading: the tracer's
/// throughput figure. Returns the number of rays that hit.
pub fn trace_frame(map: &BrickMap, projection: &Projection, threads: usize) -> u64 {
    by_bands(projection.height, threads.max(1), |y0| {
        let mut hits = 0u64;
        for_band(map, projection, y0, |_, _, _, hit| {
            // The colour is part of a primary ray's work: keep its read.
            hits += u64::from(std::hint::black_box(hit).is_some());
        });
        hits
    })
    .into_iter()
    .map(|(_, hits)| hits)
    .sum()
}

/// `band(y0)` for every band of [`TILE`] rows (y0 = 0, TILE, 2·TILE, …) below `height`.
fn by_bands<R: Send>(height: u32, threads: usize, band: impl Fn(u32) -> R + Sync) -> Vec<(u32, R)> {
    by_rows(height.div_ceil(TILE), threads, |b| band(b * TILE))
}

/// `row(y)` for every row below `height`, on `threads` threads (0 = all cores) that take rows
/// from a shared counter. One thread, and every wasm32 build (where `std::thread` cannot spawn),
/// runs them inline on the caller's thread.
fn by_rows<R: Send>(height: u32, threads: usize, row: impl Fn(u32) -> R + Sync) -> Vec<(u32, R)> {
    let threads = if cfg!(target_arch = "wasm32") {
        1
    } else if threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        threads
    }
    .min(height as usize)
    .max(1);
    if threads == 1 {
        return (0..height).map(|y| (y, row(y))).collect();
    }
    let next_row = AtomicU32::new(0);
    std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| {
                    let mut done = Vec::new();
                    loop {
                        let y = next_row.fetch_add(1, Ordering::Relaxed);
                        if y >= height {
                            break done;
                        }
                        done.push((y, row(y)));
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|w| w.join().unwrap_or_default())
            .collect()
    })
}

/// Mean absolute difference of two colours, used by renderer comparisons.
pub fn colour_distance(a: [u8; 4], b: [u8; 4]) -> u32 {
    (0..3)
        .map(|i| (a[i] as i32 - b[i] as i32).unsigned_abs())
        .max()
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::map::BrushMode;

    #[test]
    fn centre_pixel_looks_at_target() {
        let cam = Camera {
            eye: [0.0, 0.0, 0.0],
            target: [0.0, 0.0, 10.0],
            fov_y: 60.0,
        };
        let p = cam.project(3, 3).unwrap();
        let ray = p.ray(1, 1);
        assert_eq!(ray.dir, [0.0, 0.0, 1.0]);
        // Top row looks up, left column looks left (right-handed, y up, looking +z: right is -x).
        assert!(p.ray(1, 0).dir[1] > 0.0);
        assert!(p.ray(0, 1).dir[0] > 0.0);
        assert!(
            Camera {
                eye: [1.0; 3],
                target: [1.0; 3],
                fov_y: 60.0
            }
            .project(3, 3)
            .is_none()
        );
        assert!(cam.project(0, 3).is_none());
        let down = Camera {
            eye: [0.0, 10.0, 0.0],
            target: [0.0, 0.0, 0.0],
            fov_y: 60.0,
        };
        assert!(down.project(4, 4).is_some(), "looking straight down works");
    }

    /// The frame renderer's shortcuts (beam starts, colours read after the tile, the sun's walk
    /// table for shadow rays) change no pixel: every pixel equals the plain per-pixel render.
    #[test]
    fn frame_equals_plain_pixels() {
        let map = crate::demo::demo_scene([160, 96, 160]).unwrap();
        let lighting = Lighting::default();
        let uniform = lighting.uniform();
        for camera in [
            Camera::overview(map.size()),
            Camera {
                eye: [20.0, 40.0, 30.0],
                target: [120.0, 15.0, 140.0],
                fov_y: 70.0,
            },
        ] {
            let p = camera.project(96, 64).unwrap();
            let frame = render(&map, &p, &lighting, 2);
            let mut hits = 0;
            for y in 0..p.height {
                for x in 0..p.width {
                    let (pixel, hit) = render_pixel(&map, &p, &lighting, &uniform, x, y);
                    let at = (y * p.width + x) as usize;
                    assert_eq!(
                        (frame.pixels[at], frame.hits[at]),
                        (pixel, hit),
                        "({x}, {y})"
                    );
                    hits += usize::from(hit != MISS);
                }
            }
            assert!(hits > 1000, "{hits}");
        }
    }

    #[test]
    fn renders_lit_and_shadowed_faces() {
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 3, 63], BrushMode::Fill, Colour::WHITE);
        map.fill_box([28, 4, 28], [35, 30, 35], BrushMode::Fill, Colour::WHITE);
        let cam = Camera {
            eye: [32.0, 60.0, -20.0],
            target: [32.0, 0.0, 32.0],
            fov_y: 50.0,
        };
        let p = cam.project(64, 48).unwrap();
        let frame = render(&map, &p, &Lighting::default(), 2);
        assert_eq!(frame.pixels.len(), 64 * 48);
        assert!(
            frame.hits.contains(&MISS),
            "the top rows see sky past the scene"
        );
        assert!(
            frame.hits.iter().filter(|&&h| h != MISS).count() > 64 * 24,
            "most of the frame sees the floor"
        );
        let serial = render(&map, &p, &Lighting::default(), 1);
        assert_eq!(frame, serial, "thread count does not change the image");
        // Floor pixels in shadow are darker than lit floor pixels.
        let floor: Vec<u8> = frame
            .pixels
            .iter()
            .zip(&frame.hits)
            .filter(|(_, h)| **h != MISS && (**h / 64) % 64 == 3)
            .map(|(p, _)| p[0])
            .collect();
        let (lo, hi) = (floor.iter().min().copied(), floor.iter().max().copied());
        assert!(hi > lo, "some floor in shadow: {lo:?}..{hi:?}");
    }
}
