//! Mesh → voxels, the paper's section 3.4: split the mesh into an octree, and every leaf voxel
//! that holds part of a triangle becomes solid, coloured from the texture where the voxel's
//! centre projects onto the closest triangle.
//!
//! * **Overlap** is exact and conservative: a voxel is solid when the closed triangle meets the
//!   closed voxel box (Schwarz & Seidel's form of the separating-axis test: the triangle's plane
//!   crosses the box, and each of the three axis-aligned projections of the triangle meets the
//!   box's projection). Thin, axis-aligned and sliver triangles get every voxel they touch, so a
//!   closed mesh voxelizes to a closed surface at any resolution. Triangles with no area (all
//!   corners on a line) carry no surface and are counted and skipped.
//! * **Octree**: nodes are cubes of power-of-two voxels. The top nodes (≤ 256³) get the triangles
//!   that overlap them; workers take top nodes largest first and descend depth-first, handing
//!   each child only the triangles that overlap it, down to 32³ leaves (one map region).
//! * **Leaves**: each triangle of a leaf walks the voxel columns along its dominant axis, so the
//!   work is proportional to the voxels it covers, not to its bounding box. A per-worker 32³
//!   scratch keeps, per voxel, the distance to the closest triangle so far and its colour; only
//!   bricks a leaf touched are emitted and cleared. Nothing per-voxel outlives a leaf: memory is
//!   the final bricks plus 192 KiB per worker.
//! * **Coordinates**: the mesh's bounding box is scaled so its longest axis spans voxel centres
//!   0.5 … R − 0.5 (R = resolution): a surface lying on the box's face is one voxel thick rather
//!   than straddling two. Setup and tests run in f64 so triangles far from the origin of an
//!   8192³ grid keep sub-voxel precision.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;

use brickcast_protocol::brick::{BRICK_EDGE, BrickData, EMPTY_MASK, mask_set};
use brickcast_protocol::map::REGION_EDGE;
use brickcast_protocol::{BrickMap, Colour};

use super::mesh::Mesh;
use super::{ImportError, ImportOptions, Phase, Progress};

/// Leaf edge in voxels: one map region, 4³ bricks.
const LEAF: u32 = REGION_EDGE;
const LEAF_BRICKS: usize = ((LEAF / BRICK_EDGE) as usize).pow(3);
const LEAF_VOXELS: usize = (LEAF as usize).pow(3);
// A leaf's touched bricks are one u64 bit set.
const _: () = assert!(LEAF_BRICKS <= 64);
/// Largest top-level node: big enough that a top node's triangle list is cheap to build, small
/// enough that there are many more nodes than workers.
const TOP_MAX: u32 = 256;
/// Bricks sent from a worker to the map builder at a time.
const BATCH: usize = 2048;

/// Counts from a voxelization besides the map itself.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct VoxelizeStats {
    /// Triangles skipped because they have no area.
    pub degenerate: u64,
}

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The projection onto the plane normal to axis `c` uses the cyclic pair (a, b): (x, y) for z,
/// (y, z) for x, (z, x) for y, so that the projected triangle's signed area is `n[c]`.
const fn pair(c: usize) -> (usize, usize) {
    ((c + 1) % 3, (c + 2) % 3)
}

/// A triangle prepared for box overlap tests in voxel space.
struct Triangle {
    corners: [V3; 3],
    uvs: Option<[[f32; 2]; 3]>,
    material: u32,
    normal: V3,
    /// `n · v0`: the plane is `n · p = plane`.
    plane: f64,
    /// Per projection axis c, per edge: the edge's inward normal (na, nb) in the (a, b) plane and
    /// `-(na·v_a + nb·v_b)`. A box of edge Δ at (pa, pb) meets the projected triangle when, for
    /// every edge, `na·pa + nb·pb + offset + Δ·(max(na,0) + max(nb,0)) ≥ 0`.
    edges: [[[f64; 3]; 3]; 3],
    /// Axis along which |n| is largest: leaves walk columns along it.
    dominant: usize,
    /// Voxel range the closed triangle can touch, clamped to the scene (inclusive).
    lo: [u32; 3],
    hi: [u32; 3],
}

impl Triangle {
    fn new(corners: [V3; 3], size: [u32; 3]) -> Option<Triangle> {
        let normal = cross(sub(corners[1], corners[0]), sub(corners[2], corners[0]));
        if normal == [0.0; 3] || normal.iter().any(|c| !c.is_finite()) {
            return None;
        }
        let mut edges = [[[0.0; 3]; 3]; 3];
        for (c, per_edge) in edges.iter_mut().enumerate() {
            let (a, b) = pair(c);
            let sign = if normal[c] >= 0.0 { 1.0 } else { -1.0 };
            for (i, edge) in per_edge.iter_mut().enumerate() {
                let v = corners[i];
                let e = sub(corners[(i + 1) % 3], v);
                let (na, nb) = (-e[b] * sign, e[a] * sign);
                *edge = [na, nb, -(na * v[a] + nb * v[b])];
            }
        }
        let dominant = (0..3)
            .max_by(|&i, &j| normal[i].abs().total_cmp(&normal[j].abs()))
            .unwrap_or(0);
        let mut lo = [0; 3];
        let mut hi = [0; 3];
        for i in 0..3 {
            let min = corners.iter().map(|c| c[i]).fold(f64::INFINITY, f64::min);
            let max = corners
                .iter()
                .map(|c| c[i])
                .fold(f64::NEG_INFINITY, f64::max);
            // Voxel v = [v, v+1] touches [min, max] when v ≤ max and v + 1 ≥ min.
            let first = (min.ceil() - 1.0).max(0.0);
            let last = max.floor().min(size[i] as f64 - 1.0);
            if first > last {
                return None;
            }
            lo[i] = first as u32;
            hi[i] = last as u32;
        }
        Some(Triangle {
            corners,
            uvs: None,
            material: 0,
            normal,
            plane: dot(normal, corners[0]),
            edges,
            dominant,
            lo,
            hi,
        })
    }

    /// Whether the triangle's plane meets the box `[p, p + Δ]`.
    fn plane_meets(&self, p: V3, delta: f64) -> bool {
        let n = self.normal;
        let np = dot(n, p) - self.plane;
        let high: f64 = n.iter().map(|&c| c.max(0.0)).sum::<f64>() * delta;
        let low: f64 = n.iter().map(|&c| c.min(0.0)).sum::<f64>() * delta;
        (np + high) * (np + low) <= 0.0
    }

    /// Whether the projection along axis `c` meets the projected box `[p, p + Δ]`.
    fn projection_meets(&self, c: usize, p: V3, delta: f64) -> bool {
        let (a, b) = pair(c);
        self.edges[c].iter().all(|&[na, nb, offset]| {
            na * p[a] + nb * p[b] + offset + delta * (na.max(0.0) + nb.max(0.0)) >= 0.0
        })
    }

    /// The separating-axis test against the box `[p, p + Δ]` (given the boxes' ranges overlap).
    fn meets(&self, p: V3, delta: f64) -> bool {
        self.plane_meets(p, delta) && (0..3).all(|c| self.projection_meets(c, p, delta))
    }

    /// Whether the triangle overlaps the cube at voxel `lo` with edge `size`.
    fn overlaps_node(&self, lo: [u32; 3], size: u32) -> bool {
        (0..3).all(|i| self.hi[i] >= lo[i] && self.lo[i] < lo[i] + size)
            && self.meets(lo.map(f64::from), size as f64)
    }

    /// The point of the triangle closest to `p`, as barycentric weights, and its squared
    /// distance (Ericson, Real-Time Collision Detection, 5.1.5).
    fn closest(&self, p: V3) -> ([f64; 3], f64) {
        let [a, b, c] = self.corners;
        let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
        let (d1, d2) = (dot(ab, ap), dot(ac, ap));
        let weights = 'w: {
            if d1 <= 0.0 && d2 <= 0.0 {
                break 'w [1.0, 0.0, 0.0];
            }
            let bp = sub(p, b);
            let (d3, d4) = (dot(ab, bp), dot(ac, bp));
            if d3 >= 0.0 && d4 <= d3 {
                break 'w [0.0, 1.0, 0.0];
            }
            let vc = d1 * d4 - d3 * d2;
            if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
                let v = d1 / (d1 - d3);
                break 'w [1.0 - v, v, 0.0];
            }
            let cp = sub(p, c);
            let (d5, d6) = (dot(ab, cp), dot(ac, cp));
            if d6 >= 0.0 && d5 <= d6 {
                break 'w [0.0, 0.0, 1.0];
            }
            let vb = d5 * d2 - d1 * d6;
            if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
                let w = d2 / (d2 - d6);
                break 'w [1.0 - w, 0.0, w];
            }
            let va = d3 * d6 - d5 * d4;
            if va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
                let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
                break 'w [0.0, 1.0 - w, w];
            }
            let denom = 1.0 / (va + vb + vc);
            let (v, w) = (vb * denom, vc * denom);
            [1.0 - v - w, v, w]
        };
        let q: V3 =
            std::array::from_fn(|i| weights[0] * a[i] + weights[1] * b[i] + weights[2] * c[i]);
        let d = sub(p, q);
        (weights, dot(d, d))
    }
}

/// Maps mesh coordinates to voxel coordinates: the bounding box's longest axis spans voxel
/// centres 0.5 … R − 0.5.
struct Placement {
    origin: V3,
    scale: f64,
    size: [u32; 3],
}

impl Placement {
    fn new(mesh: &Mesh, resolution: u32) -> Result<Placement, ImportError> {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for t in &mesh.triangles {
            for &c in &t.corners {
                let p = mesh.positions[c as usize];
                for i in 0..3 {
                    lo[i] = lo[i].min(p[i] as f64);
                    hi[i] = hi[i].max(p[i] as f64);
                }
            }
        }
        let extent = sub(hi, lo);
        let longest = extent.iter().copied().fold(0.0, f64::max);
        if !longest.is_finite() || longest <= 0.0 {
            return Err(ImportError::EmptyMesh);
        }
        let scale = (resolution - 1) as f64 / longest;
        let size = extent.map(|e| ((e * scale + 0.5).floor() as u32 + 1).min(resolution));
        Ok(Placement {
            origin: lo,
            scale,
            size,
        })
    }

    fn voxel(&self, p: [f32; 3]) -> V3 {
        std::array::from_fn(|i| (p[i] as f64 - self.origin[i]) * self.scale + 0.5)
    }
}

/// Voxelizes a mesh at `options.resolution` voxels along its longest axis.
pub fn voxelize(
    mesh: &Mesh,
    options: &ImportOptions,
    progress: &dyn Progress,
) -> Result<(BrickMap, VoxelizeStats), ImportError> {
    options.check()?;
    let placement = Placement::new(mesh, options.resolution)?;
    let size = placement.size;
    let mut stats = VoxelizeStats::default();
    let mut triangles = Vec::with_capacity(mesh.triangles.len());
    for t in &mesh.triangles {
        let corners = t
            .corners
            .map(|c| placement.voxel(mesh.positions[c as usize]));
        match Triangle::new(corners, size) {
            Some(mut tri) => {
                tri.material = t.material.min(mesh.materials.len() as u32 - 1);
                tri.uvs = t.textured.then(|| {
                    t.corners
                        .map(|c| mesh.uvs.get(c as usize).copied().unwrap_or_default())
                });
                triangles.push(tri);
            }
            None => stats.degenerate += 1,
        }
    }
    if triangles.is_empty() {
        return Err(ImportError::EmptyMesh);
    }

    // Top nodes and the triangles overlapping each.
    let root = size
        .iter()
        .copied()
        .max()
        .unwrap_or(1)
        .next_power_of_two()
        .max(LEAF);
    let top = (root / 8).clamp(LEAF, TOP_MAX);
    let nodes_per_axis = size.map(|s| s.div_ceil(top));
    let node_index =
        |n: [u32; 3]| (n[0] + nodes_per_axis[0] * (n[1] + nodes_per_axis[1] * n[2])) as usize;
    let mut top_lists: Vec<Vec<u32>> =
        vec![Vec::new(); nodes_per_axis.iter().map(|&n| n as usize).product()];
    for (id, tri) in triangles.iter().enumerate() {
        let (lo, hi) = (tri.lo.map(|v| v / top), tri.hi.map(|v| v / top));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let n = [x, y, z];
                    if tri.overlaps_node(n.map(|v| v * top), top) {
                        top_lists[node_index(n)].push(id as u32);
                    }
                }
            }
        }
    }
    let mut jobs: Vec<([u32; 3], Vec<u32>)> = Vec::new();
    for z in 0..nodes_per_axis[2] {
        for y in 0..nodes_per_axis[1] {
            for x in 0..nodes_per_axis[0] {
                let list = std::mem::take(&mut top_lists[node_index([x, y, z])]);
                if !list.is_empty() {
                    jobs.push(([x * top, y * top, z * top], list));
                }
            }
        }
    }
    // Largest first, so the last jobs to finish are small ones.
    jobs.sort_by_key(|(_, list)| std::cmp::Reverse(list.len()));
    progress.start(
        Phase::Voxelizing,
        jobs.iter().map(|(_, l)| l.len() as u64).sum(),
    );

    let mut map = BrickMap::new(size)?;
    let next = AtomicUsize::new(0);
    let (tx, rx) = mpsc::sync_channel::<Vec<BrickData>>(8);
    let workers = options.worker_threads().min(jobs.len()).max(1);
    let mut put_error = None;
    std::thread::scope(|scope| {
        for _ in 0..workers {
            let tx = tx.clone();
            let (jobs, triangles, next) = (&jobs, &triangles, &next);
            scope.spawn(move || {
                let mut worker = Worker::new(mesh, triangles, size, tx);
                while let Some((lo, list)) = jobs.get(next.fetch_add(1, Ordering::Relaxed)) {
                    worker.descend(*lo, top, list);
                    progress.advance(list.len() as u64);
                }
                worker.flush();
            });
        }
        drop(tx);
        for batch in rx {
            for brick in &batch {
                if let Err(e) = map.put_brick(brick) {
                    put_error.get_or_insert(e);
                }
            }
        }
    });
    progress.finish();
    if let Some(e) = put_error {
        return Err(e.into());
    }
    map.rebuild_clearance();
    Ok((map, stats))
}

/// One voxelizing thread: its leaf scratch and its outgoing batch of bricks.
struct Worker<'a> {
    mesh: &'a Mesh,
    triangles: &'a [Triangle],
    size: [u32; 3],
    /// Per leaf voxel (brick-major: brick · 512 + bit): squared distance from its centre to the
    /// closest triangle so far (∞: empty) and that triangle's colour there.
    best: Vec<f64>,
    colour: Vec<Colour>,
    /// Bricks of the current leaf with at least one solid voxel.
    touched: u64,
    out: Vec<BrickData>,
    tx: mpsc::SyncSender<Vec<BrickData>>,
}

impl<'a> Worker<'a> {
    fn new(
        mesh: &'a Mesh,
        triangles: &'a [Triangle],
        size: [u32; 3],
        tx: mpsc::SyncSender<Vec<BrickData>>,
    ) -> Worker<'a> {
        Worker {
            mesh,
            triangles,
            size,
            best: vec![f64::INFINITY; LEAF_VOXELS],
            colour: vec![Colour::BLACK; LEAF_VOXELS],
            touched: 0,
            out: Vec::with_capacity(BATCH),
            tx,
        }
    }

    /// Depth-first through the octree below the node at `lo` of edge `size`, whose overlapping
    /// triangles are `list`.
    fn descend(&mut self, lo: [u32; 3], size: u32, list: &[u32]) {
        if size <= LEAF {
            self.leaf(lo, list);
            return;
        }
        let half = size / 2;
        let mut child_list = Vec::with_capacity(list.len());
        for octant in 0..8u32 {
            let child = [0, 1, 2].map(|i| lo[i] + half * ((octant >> i) & 1));
            if (0..3).any(|i| child[i] >= self.size[i]) {
                continue;
            }
            child_list.clear();
            child_list.extend(
                list.iter()
                    .copied()
                    .filter(|&t| self.triangles[t as usize].overlaps_node(child, half)),
            );
            if !child_list.is_empty() {
                let list = std::mem::take(&mut child_list);
                self.descend(child, half, &list);
                child_list = list;
            }
        }
    }

    /// Voxelizes the triangles of one 32³ leaf and emits its bricks.
    fn leaf(&mut self, leaf_lo: [u32; 3], list: &[u32]) {
        let leaf_hi = [0, 1, 2].map(|i| (leaf_lo[i] + LEAF).min(self.size[i]) - 1);
        for &t in list {
            let tri = &self.triangles[t as usize];
            let lo: [u32; 3] = std::array::from_fn(|i| tri.lo[i].max(leaf_lo[i]));
            let hi: [u32; 3] = std::array::from_fn(|i| tri.hi[i].min(leaf_hi[i]));
            if (0..3).any(|i| lo[i] > hi[i]) {
                continue;
            }
            self.rasterize(tri, lo, hi, leaf_lo);
        }
        self.emit(leaf_lo);
    }

    /// Walks the voxel columns along the triangle's dominant axis within `lo..=hi`.
    fn rasterize(&mut self, tri: &Triangle, lo: [u32; 3], hi: [u32; 3], leaf_lo: [u32; 3]) {
        let w = tri.dominant;
        let (u, v) = pair(w);
        let n = tri.normal;
        for pu in lo[u]..=hi[u] {
            for pv in lo[v]..=hi[v] {
                let mut p = [0.0; 3];
                p[u] = pu as f64;
                p[v] = pv as f64;
                if !tri.projection_meets(w, p, 1.0) {
                    continue;
                }
                // The plane over this column's square spans w in [w_min, w_max]; widen by one
                // voxel each way and let the exact test decide, so rounding never drops one.
                let (mut w_min, mut w_max) = (f64::INFINITY, f64::NEG_INFINITY);
                for (du, dv) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                    let at = (tri.plane - n[u] * (p[u] + du) - n[v] * (p[v] + dv)) / n[w];
                    w_min = w_min.min(at);
                    w_max = w_max.max(at);
                }
                let first = (w_min.floor() - 1.0).max(lo[w] as f64) as u32;
                let last = (w_max.floor() + 1.0).min(hi[w] as f64);
                if last < first as f64 {
                    continue;
                }
                for pw in first..=last as u32 {
                    p[w] = pw as f64;
                    if tri.plane_meets(p, 1.0)
                        && tri.projection_meets(u, p, 1.0)
                        && tri.projection_meets(v, p, 1.0)
                    {
                        let mut voxel = [0; 3];
                        voxel[u] = pu;
                        voxel[v] = pv;
                        voxel[w] = pw;
                        self.record(tri, voxel, leaf_lo);
                    }
                }
            }
        }
    }

    /// Marks a voxel solid and keeps the colour of the triangle closest to its centre.
    fn record(&mut self, tri: &Triangle, voxel: [u32; 3], leaf_lo: [u32; 3]) {
        let local = [0, 1, 2].map(|i| voxel[i] - leaf_lo[i]);
        let brick = (local[0] / 8 + 4 * (local[1] / 8) + 16 * (local[2] / 8)) as usize;
        let bit = (local[0] % 8 + 8 * (local[1] % 8) + 64 * (local[2] % 8)) as usize;
        let index = brick * 512 + bit;
        let centre = voxel.map(|c| c as f64 + 0.5);
        let (weights, distance) = tri.closest(centre);
        if distance >= self.best[index] {
            return;
        }
        self.best[index] = distance;
        self.touched |= 1 << brick;
        let uv = tri.uvs.map(|uvs| {
            let w = weights.map(|x| x as f32);
            [0, 1].map(|k| w[0] * uvs[0][k] + w[1] * uvs[1][k] + w[2] * uvs[2][k])
        });
        let rgb = self.mesh.materials[tri.material as usize].colour(uv);
        let [r, g, b] = rgb.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8);
        self.colour[index] = Colour::from_rgb8(r, g, b);
    }

    /// Turns the leaf's touched bricks into [`BrickData`] and clears their scratch.
    fn emit(&mut self, leaf_lo: [u32; 3]) {
        let mut touched = std::mem::take(&mut self.touched);
        while touched != 0 {
            let brick = touched.trailing_zeros() as usize;
            touched &= touched - 1;
            let range = brick * 512..(brick + 1) * 512;
            let mut mask = EMPTY_MASK;
            let mut colours = Vec::new();
            for (bit, (best, colour)) in self.best[range.clone()]
                .iter_mut()
                .zip(&self.colour[range])
                .enumerate()
            {
                if best.is_finite() {
                    mask_set(&mut mask, bit as u32, true);
                    colours.push(*colour);
                    *best = f64::INFINITY;
                }
            }
            let b = brick as u32;
            let cell = [b % 4, (b / 4) % 4, b / 16];
            self.out.push(BrickData {
                cell: [0, 1, 2].map(|i| leaf_lo[i] / BRICK_EDGE + cell[i]),
                mask,
                colours,
            });
        }
        if self.out.len() >= BATCH {
            self.flush();
        }
    }

    fn flush(&mut self) {
        if !self.out.is_empty() {
            // The receiver only goes away if the builder thread is gone, and then there is no
            // map to put bricks into anyway.
            let _ = self
                .tx
                .send(std::mem::replace(&mut self.out, Vec::with_capacity(BATCH)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference: Akenine-Möller's 13-axis separating-axis test of a triangle against a box.
    fn sat_reference(tri: [V3; 3], lo: V3, delta: f64) -> bool {
        let h = delta / 2.0;
        let centre = lo.map(|c| c + h);
        let v = tri.map(|p| sub(p, centre));
        let e = [sub(v[1], v[0]), sub(v[2], v[1]), sub(v[0], v[2])];
        let mut axes: Vec<V3> = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        axes.push(cross(e[0], e[1]));
        for edge in e {
            for unit in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
                axes.push(cross(unit, edge));
            }
        }
        axes.iter().all(|&a| {
            let p = v.map(|x| dot(x, a));
            let r = h * (a[0].abs() + a[1].abs() + a[2].abs());
            let (min, max) = (
                p.iter().copied().fold(f64::INFINITY, f64::min),
                p.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            );
            !(min > r || max < -r)
        })
    }

    /// Seeded ChaCha8 (`rand_chacha`: the same numbers on every platform and rand release).
    struct Rng(rand_chacha::ChaCha8Rng);
    impl Rng {
        fn new(seed: u64) -> Rng {
            Rng(rand::SeedableRng::seed_from_u64(seed))
        }
        /// Uniform in 0..1.
        fn next(&mut self) -> f64 {
            rand::Rng::random(&mut self.0)
        }
        /// Coordinates that are often exactly on voxel planes or centres.
        fn coord(&mut self, span: f64) -> f64 {
            let x = self.next() * span;
            match (self.next() * 4.0) as u32 {
                0 => x.floor(),
                1 => x.floor() + 0.5,
                _ => x,
            }
        }
    }

    #[test]
    fn box_test_matches_the_13_axis_reference() {
        let mut rng = Rng::new(0x9E37_79B9_7F4A_7C15);
        let (mut checked, mut touching_only) = (0, 0);
        for _ in 0..20_000 {
            let mut tri: [V3; 3] = std::array::from_fn(|_| std::array::from_fn(|_| rng.coord(6.0)));
            // Some slivers and axis-aligned triangles.
            match (rng.next() * 4.0) as u32 {
                0 => {
                    tri[2] = std::array::from_fn(|i| {
                        tri[0][i] + (tri[1][i] - tri[0][i]) * 0.5 + 1e-3 * rng.next()
                    })
                }
                1 => {
                    let z = tri[0][2];
                    tri[1][2] = z;
                    tri[2][2] = z;
                }
                _ => {}
            }
            let Some(t) = Triangle::new(tri, [8, 8, 8]) else {
                continue;
            };
            for _ in 0..8 {
                let lo: V3 = std::array::from_fn(|_| (rng.next() * 7.0).floor());
                let bbox_overlap = (0..3).all(|i| {
                    let min = tri.iter().map(|c| c[i]).fold(f64::INFINITY, f64::min);
                    let max = tri.iter().map(|c| c[i]).fold(f64::NEG_INFINITY, f64::max);
                    max >= lo[i] && min <= lo[i] + 1.0
                });
                let ours = bbox_overlap && t.meets(lo, 1.0);
                if ours != sat_reference(tri, lo, 1.0) {
                    // Both tests round; they may differ only where the triangle merely touches
                    // the box (a corner on a face, say): a hair larger box must overlap and a
                    // hair smaller one must not.
                    let eps = 1e-9;
                    let touching = sat_reference(tri, lo.map(|c| c - eps), 1.0 + 2.0 * eps)
                        && !sat_reference(tri, lo.map(|c| c + eps), 1.0 - 2.0 * eps);
                    assert!(touching, "triangle {tri:?}, box at {lo:?}: ours {ours}");
                    touching_only += 1;
                }
                checked += 1;
            }
        }
        assert!(checked > 100_000);
        assert!(
            touching_only * 100 < checked,
            "{touching_only} of {checked} differ"
        );
    }

    /// The voxelizer's output is exactly the set of voxels the reference test says a triangle
    /// overlaps (up to boxes a triangle merely touches), on random meshes of thin, axis-aligned
    /// and ordinary triangles at several resolutions.
    #[test]
    fn voxel_set_is_exactly_the_overlapping_voxels() {
        let mut rng = Rng::new(0x2545_F491_4F6C_DD1D);
        for case in 0..24 {
            let mut mesh = Mesh::new();
            // Fix the placement: corners at 0 and 1 on every axis.
            mesh.add_triangle([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 1.0]], None, 0);
            for _ in 0..5 {
                let mut t: [[f32; 3]; 3] =
                    std::array::from_fn(|_| std::array::from_fn(|_| rng.next() as f32));
                match case % 3 {
                    0 => {
                        t[2] = std::array::from_fn(|i| {
                            (t[0][i] + t[1][i]) * 0.5 + 0.002 * rng.next() as f32
                        })
                    }
                    1 => {
                        let y = t[0][1];
                        t[1][1] = y;
                        t[2][1] = y;
                    }
                    _ => {}
                }
                mesh.add_triangle(t, None, 0);
            }
            let resolution = [8, 16, 32, 64][case % 4];
            let options = ImportOptions {
                resolution,
                threads: 2,
                ..ImportOptions::default()
            };
            let (map, _) = voxelize(&mesh, &options, &super::super::NoProgress).unwrap();
            let placement = Placement::new(&mesh, resolution).unwrap();
            let size = map.size();
            let tris: Vec<[V3; 3]> = mesh
                .triangles
                .iter()
                .map(|t| {
                    t.corners
                        .map(|c| placement.voxel(mesh.positions[c as usize]))
                })
                .collect();
            let eps = 1e-6;
            for z in 0..size[2] {
                for y in 0..size[1] {
                    for x in 0..size[0] {
                        let lo = [x, y, z].map(f64::from);
                        let inside = tris
                            .iter()
                            .any(|t| sat_reference(*t, lo.map(|c| c + eps), 1.0 - 2.0 * eps));
                        let touching = tris
                            .iter()
                            .any(|t| sat_reference(*t, lo.map(|c| c - eps), 1.0 + 2.0 * eps));
                        let solid = map.is_solid([x, y, z]);
                        assert!(
                            !inside || solid,
                            "case {case}: voxel {:?} overlaps a triangle but is empty",
                            [x, y, z]
                        );
                        assert!(
                            !solid || touching,
                            "case {case}: voxel {:?} is solid but touches no triangle",
                            [x, y, z]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn closest_point_weights_are_barycentric() {
        let t = Triangle::new(
            [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]],
            [8, 8, 8],
        )
        .unwrap();
        let (w, d) = t.closest([1.0, 1.0, 2.0]);
        assert_eq!((w, d), ([0.5, 0.25, 0.25], 4.0));
        let (w, d) = t.closest([6.0, -1.0, 0.0]);
        assert_eq!((w, d), ([0.0, 1.0, 0.0], 5.0));
        let (w, _) = t.closest([3.0, 3.0, 0.0]);
        assert_eq!(w, [0.0, 0.5, 0.5]);
    }
}
