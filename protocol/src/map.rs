//! The brick map: the scene as both sides hold it.
//!
//! Three levels, each a flat array so the GPU can hold byte-for-byte the same layout:
//!
//! * `regions`: one `u32` per region of 4×4×4 coarse cells (32³ voxels), pointing to a cell block
//!   or, when empty, `0xFFFFFF00 | clearance` (see [`region_clearance`]). This is the paper's "grid
//!   above the top level": a ray leaves an empty region, and the empty regions around it, in one
//!   step, and empty regions cost 4 bytes instead of 256, which keeps the coarse level sparse (a
//!   dense 512³ coarse grid for a 4096³ scene would alone be 512 MiB).
//! * `cells`: cell blocks of 64 `u32`s, each a brick slot or, when empty, `0xFFFFFF00 |
//!   clearance` in cells (see [`cell_clearance`]); the paper's brick grid. Cells of empty regions
//!   are not stored.
//! * per brick slot: a 512-bit `mask` and a `colour_base` into the shared `colours` pool, which holds
//!   only the colours of solid voxels (see [`crate::brick`]).
//!
//! Colour chunks are allocated in size classes (at most 1/8 slack) with a free list per class, so
//! bricks can grow and shrink under edits without leaking: a brick that becomes empty frees its
//! slot and chunk, a cell block whose last brick goes frees the block, and later allocations reuse
//! them first.
//!
//! Every brick carries the sequence number of the last edit that touched it, and removed bricks
//! leave a tombstone, so "what changed since sequence S" is answerable for a reconnecting client.

use crate::brick::{
    BRICK_EDGE, BRICK_VOXELS, BrickData, EMPTY, EMPTY_MASK, Mask, for_each_bit, mask_get,
    mask_is_empty, mask_set, popcount, rank, rank_and_count, voxel_bit,
};
use crate::colour::Colour;

mod compact;
mod stand_in;
pub use compact::Compacted;
use stand_in::COARSE;
pub use stand_in::{
    MAX_STAND_IN_LEVEL, MAX_STAND_IN_SLOTS, MIN_STAND_IN_LEVEL, STAND_IN, coarse_bit, coarse_cell,
    region_block, region_stand_in, stand_in_entry,
};

/// Coarse cells along one edge of a region.
pub const REGION_CELLS: u32 = 4;
/// Voxels along one edge of a region.
pub const REGION_EDGE: u32 = REGION_CELLS * BRICK_EDGE;
/// Cells in one cell block.
pub const CELLS_PER_BLOCK: u32 = REGION_CELLS * REGION_CELLS * REGION_CELLS;
/// Largest scene edge in voxels: BrickMap's 16384×512×16384 world fits. Keeps every coordinate
/// exact in `f32` (< 2^24), coarse cells in `u16` on the wire, and the tracers' settle shortcut
/// sound (`trace::clearly_inside_voxel` allows planes up to this).
pub const MAX_SCENE_EDGE: u32 = 16384;
/// Most regions a scene may have: the region array is at most 64 MiB however the scene is shaped
/// (a 16384×512×16384 world has 4 Mi regions; a 16384³ cube, 128 Mi, is refused).
pub const MAX_REGIONS: u64 = 1 << 24;

/// Largest clearance stored for an empty region. Allocating a region lowers the clearance of the
/// (2·cap+1)³ regions around it, so the cap bounds that cost; 6 lets a ray leave up to 13 regions
/// (416 voxels) in one step.
pub const CLEARANCE_CAP: u32 = 6;

/// The largest colour block: a header and 512 raw colours ([`crate::palette`]).
pub const MAX_BLOCK_WORDS: u32 = 1 + BRICK_VOXELS;

/// Voxels of a brick, as a length.
const VOXELS: usize = BRICK_VOXELS as usize;
/// Region entries at or above this are empty; the low byte is the clearance.
pub const EMPTY_REGION: u32 = 0xFFFF_FF00;

/// Whether a region entry is empty.
#[inline(always)]
pub const fn region_is_empty(entry: u32) -> bool {
    entry >= EMPTY_REGION
}

/// Largest clearance stored for an empty cell (in cells). Creating a brick lowers the clearance
/// of the (2·cap+1)³ cells around it, so the cap bounds that cost.
pub const CELL_CLEARANCE_CAP: u32 = 2;
/// An empty cell with no clearance: what a new block and a removed brick leave.
pub const EMPTY_CELL: u32 = EMPTY_REGION;

/// Whether a cell entry is empty.
#[inline(always)]
pub const fn cell_is_empty(entry: u32) -> bool {
    entry >= EMPTY_CELL
}

/// Clearance of an empty cell entry: every cell within this Chebyshev distance (in cells) is
/// empty, in this region or in the ones around it (cells of empty regions count as empty), so a
/// ray may leave that cube of cells in one step. Conservative like [`region_clearance`].
#[inline(always)]
pub const fn cell_clearance(entry: u32) -> u32 {
    entry & 0xFF
}

/// Clearance of an empty region entry: every region within this Chebyshev distance (in regions)
/// is empty or outside the grid, so a ray may leave that whole cube in one step. Conservative:
/// edits only ever lower it; [`BrickMap::rebuild_clearance`] raises it back.
#[inline(always)]
pub const fn region_clearance(entry: u32) -> u32 {
    entry & 0xFF
}

/// Every point of the box `lo..hi` (exclusive), x fastest then y then z: the order of every
/// linear index in this crate, so walking regions or cells this way walks memory in order.
pub fn box_points(lo: [u32; 3], hi: [u32; 3]) -> BoxPoints {
    let empty = (0..3).any(|i| lo[i] >= hi[i]);
    BoxPoints {
        lo,
        hi,
        next: (!empty).then_some(lo),
    }
}

/// The points [`box_points`] lists: three counters, not chained `flat_map`s, whose per-point
/// cost was 15% of a client taking a working set in (about a million coarse cells' boxes, most
/// of them one region).
#[derive(Debug, Clone)]
pub struct BoxPoints {
    lo: [u32; 3],
    hi: [u32; 3],
    next: Option<[u32; 3]>,
}

impl Iterator for BoxPoints {
    type Item = [u32; 3];

    #[inline]
    fn next(&mut self) -> Option<[u32; 3]> {
        let p = self.next?;
        let mut q = p;
        q[0] += 1;
        if q[0] == self.hi[0] {
            q[0] = self.lo[0];
            q[1] += 1;
            if q[1] == self.hi[1] {
                q[1] = self.lo[1];
                q[2] += 1;
            }
        }
        self.next = (q[2] < self.hi[2]).then_some(q);
        Some(p)
    }
}

/// Why a map could not be built or a brick not stored.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MapError {
    #[error("scene size {0:?} is invalid: every axis must be 1..={MAX_SCENE_EDGE} voxels")]
    BadSize([u32; 3]),
    #[error(
        "scene size {size:?} is too large: it needs {regions} regions of {REGION_EDGE}³ voxels, at most {MAX_REGIONS} are allowed (e.g. 16384×512×16384 or 8192³)"
    )]
    TooManyRegions { size: [u32; 3], regions: u64 },
    #[error("brick cell {cell:?} lies outside the scene's coarse grid {cells:?}")]
    CellOutOfBounds { cell: [u32; 3], cells: [u32; 3] },
    #[error("brick at cell {0:?} has solid voxels outside the scene bounds")]
    VoxelsOutOfBounds([u32; 3]),
    #[error(
        "brick at cell {0:?} is inconsistent: empty mask or colour count differs from its solid voxels"
    )]
    InconsistentBrick([u32; 3]),
    #[error("brick at cell {cell:?} lies outside region {region:?}, whose bricks were expected")]
    OutsideRegion { cell: [u32; 3], region: [u32; 3] },
    #[error("coarse brick refused: {0}")]
    BadCoarseBrick(&'static str),
    #[error("region {0:?} holds level-0 bricks: a coarse brick cannot stand in for it")]
    RegionHoldsBricks([u32; 3]),
}

/// What a brush does to the voxels it covers.
///
/// One enum for the single-voxel edits, the sphere and box brushes and the ray-placed sphere, so
/// a client UI has one mode switch and the map one code path per shape. It travels on the wire
/// inside edit ops.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum BrushMode {
    /// Make every covered voxel solid with the brush colour.
    Fill,
    /// Make every covered voxel empty.
    Erase,
    /// Recolour the covered voxels that are already solid; empty ones stay empty.
    Paint,
}

/// GPU-side changes since the last [`BrickMap::take_gpu_changes`]: indices into each array whose
/// contents must be re-uploaded. Lists may repeat an index; `grew` says an array got longer.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct GpuChanges {
    pub regions: Vec<u32>,
    pub cell_blocks: Vec<u32>,
    pub slots: Vec<u32>,
    /// `(first colour, count)` ranges of the colour pool.
    pub colours: Vec<(u32, u32)>,
}

impl GpuChanges {
    pub fn is_empty(&self) -> bool {
        self.regions.is_empty()
            && self.cell_blocks.is_empty()
            && self.slots.is_empty()
            && self.colours.is_empty()
    }
}

/// What a client that saw everything up to some sequence is missing (see
/// [`BrickMap::changes_since`]).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Changes {
    /// Cells whose brick changed after that sequence (send the brick).
    pub changed: Vec<[u32; 3]>,
    /// Cells whose brick was removed after it, sorted (send a removal).
    pub removed: Vec<[u32; 3]>,
}

/// Bytes used by each component of the map, as laid out on the GPU, and the paper's figure.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MemoryStats {
    pub size: [u32; 3],
    pub bricks: u64,
    pub solid_voxels: u64,
    pub cell_blocks: u64,
    pub region_bytes: u64,
    pub cell_bytes: u64,
    pub mask_bytes: u64,
    pub colour_base_bytes: u64,
    /// Colour pool including free chunks and per-chunk slack.
    pub colour_bytes: u64,
    /// Colour bytes that hold a live voxel's colour.
    pub colour_used_bytes: u64,
    pub total_bytes: u64,
    /// The paper's M = 4·(grid cells) + 20·bricks + 2048·textures for the same scene, with a dense
    /// coarse grid and one RGBA texture per brick.
    pub paper_formula_bytes: u64,
    pub bytes_per_solid_voxel: f64,
    /// Bits per solid voxel of the masks alone.
    pub mask_bits_per_voxel: f64,
    /// Bits per solid voxel of the colour pool (free chunks and slack included).
    pub colour_bits_per_voxel: f64,
}

/// How a brick's exact colours are coded when the map stores them.
#[derive(Clone, Copy)]
enum Exact<'a> {
    /// The smallest coding ([`crate::palette::choose`]).
    Smallest,
    /// Raw: a brick whose single-voxel edits keep bringing new colours (see `edit_voxel`).
    Raw,
    /// This block, already coded (checked by the caller to code the colours, its own length).
    Given(&'a [u16]),
}

/// A scene as a sparse three-level brick map. See the module docs for the layout.
#[derive(Clone)]
pub struct BrickMap {
    size: [u32; 3],
    cell_dims: [u32; 3],
    region_dims: [u32; 3],

    // GPU-mirrored arrays.
    pub(crate) regions: Vec<u32>,
    pub(crate) cells: Vec<u32>,
    pub(crate) masks: Vec<Mask>,
    pub(crate) colour_base: Vec<u32>,
    /// Per brick a [`crate::palette`] block of 16-bit words at its `colour_base`.
    pub(crate) colours: Vec<u16>,

    // CPU bookkeeping, per slot.
    slot_cell: Vec<u32>,
    slot_version: Vec<u64>,
    slot_capacity: Vec<u16>,
    free_slots: Vec<u32>,
    /// Per cell block: which of its 64 cells hold a brick (bit = index in the block). The beam
    /// pre-pass tests a box of cells against it in one `and`.
    block_cells: Vec<u64>,
    free_blocks: Vec<u32>,
    /// Free colour chunks, indexed by capacity.
    free_chunks: Vec<Vec<u32>>,

    /// Linear cell index → sequence at which its brick was removed.
    tombstones: rustc_hash::FxHashMap<u32, u64>,
    /// Tombstones at or below this sequence have been dropped: a resume from before it needs a
    /// full resync.
    tombstone_horizon: u64,

    /// Inclusive region bounds of every allocated region (grown when one is allocated, made
    /// tight again by [`BrickMap::rebuild_clearance`]); `None` while no region is. Rays start
    /// where they enter this box and end where they leave it.
    occupied: Option<([u32; 3], [u32; 3])>,
    sequence: u64,
    solid_voxels: u64,
    /// Words of the colour pool that live bricks' blocks take.
    coded_words: u64,
    /// Bricks written from now on may be coded in lossy blocks within this error per channel
    /// (0–255 scale) where that is smaller; `None`: every brick exact.
    colour_bound: Option<u32>,
    bricks: u64,
    /// Regions shown by a coarse brick ([`stand_in`]).
    stand_ins: u64,
    touched: Vec<u32>,
    track_touched: bool,
    gpu: Option<GpuChanges>,
    /// While journaling: each changed cell's brick before its first change (`crate::journal`).
    journal: crate::journal::Journal,
    /// The scene's shared palette ([`crate::swatches`]): scene state like the voxels, set by
    /// [`crate::wire::EditOp::Swatch`], kept by snapshots and replayed from the log.
    swatches: crate::swatches::Swatches,
    /// During [`BrickMap::write_bricks`]: regions of the bricks inserted, whose cells' clearance
    /// is recomputed once at the end instead of after every brick.
    deferred_clearance: Option<Vec<u32>>,
    /// While [`BrickMap::defer_region_clearance`] holds: the box of regions stand-ins occupied,
    /// whose surroundings' clearance is lowered once at the end (`None` inside: none yet).
    deferred_regions: Option<Option<([u32; 3], [u32; 3])>>,
    /// Between [`BrickMap::begin_bulk_load`] and [`BrickMap::end_bulk_load`]: writes leave the
    /// clearance alone, rebuilt whole at the end.
    bulk: bool,
}

/// An 8×8×8 cube of cells as bits (cell (x, y, z) is bit `x + 8y` of word `z`, like a brick's
/// mask) grown by one cell in every direction, diagonals included: the cells within Chebyshev
/// distance 1 of a set one.
fn dilate_cells(m: [u64; 8]) -> [u64; 8] {
    let along_x =
        |w: u64| w | ((w << 1) & 0xFEFE_FEFE_FEFE_FEFE) | ((w >> 1) & 0x7F7F_7F7F_7F7F_7F7F);
    let plane = m.map(|w| {
        let x = along_x(w);
        x | (x << 8) | (x >> 8)
    });
    std::array::from_fn(|z| {
        let below = if z > 0 { plane[z - 1] } else { 0 };
        let above = if z < 7 { plane[z + 1] } else { 0 };
        plane[z] | below | above
    })
}

/// Colour-pool capacity given to a brick whose colour block is `n` words: rounded up to a
/// multiple of 2 (one `u32` on the GPU), then to 1/8 of its power of two, which bounds slack at
/// 12.5% and keeps the number of classes (and so free lists) small.
pub const fn colour_capacity(n: u32) -> u32 {
    if n <= 16 {
        let even = n.div_ceil(2) * 2;
        if even == 0 { 2 } else { even }
    } else {
        let granule = 1 << (31 - n.leading_zeros() - 3);
        n.div_ceil(granule) * granule
    }
}

impl BrickMap {
    /// An empty scene of `size` voxels.
    pub fn new(size: [u32; 3]) -> Result<BrickMap, MapError> {
        Self::check_size(size)?;
        let cell_dims = size.map(|s| s.div_ceil(BRICK_EDGE));
        let region_dims = cell_dims.map(|c| c.div_ceil(REGION_CELLS));
        let region_count = region_dims.iter().map(|&d| d as usize).product();
        Ok(BrickMap {
            size,
            cell_dims,
            region_dims,
            regions: vec![EMPTY_REGION | CLEARANCE_CAP; region_count],
            cells: Vec::new(),
            masks: Vec::new(),
            colour_base: Vec::new(),
            colours: Vec::new(),
            slot_cell: Vec::new(),
            slot_version: Vec::new(),
            slot_capacity: Vec::new(),
            free_slots: Vec::new(),
            block_cells: Vec::new(),
            free_blocks: Vec::new(),
            free_chunks: vec![Vec::new(); colour_capacity(MAX_BLOCK_WORDS) as usize + 1],
            tombstones: Default::default(),
            tombstone_horizon: 0,
            occupied: None,
            sequence: 0,
            solid_voxels: 0,
            coded_words: 0,
            colour_bound: None,
            bricks: 0,
            stand_ins: 0,
            touched: Vec::new(),
            track_touched: false,
            gpu: None,
            journal: crate::journal::Journal::default(),
            swatches: Default::default(),
            deferred_clearance: None,
            deferred_regions: None,
            bulk: false,
        })
    }

    /// Whether a scene of `size` voxels may exist: every axis 1..=[`MAX_SCENE_EDGE`] and at most
    /// [`MAX_REGIONS`] regions. Allocates nothing, so a caller can check a world too large to build
    /// whole.
    pub fn check_size(size: [u32; 3]) -> Result<(), MapError> {
        if size.iter().any(|&s| s == 0 || s > MAX_SCENE_EDGE) {
            return Err(MapError::BadSize(size));
        }
        let regions = size
            .iter()
            .map(|&s| u64::from(s.div_ceil(REGION_EDGE)))
            .product::<u64>();
        if regions > MAX_REGIONS {
            return Err(MapError::TooManyRegions { size, regions });
        }
        Ok(())
    }

    pub fn size(&self) -> [u32; 3] {
        self.size
    }
    pub fn cell_dims(&self) -> [u32; 3] {
        self.cell_dims
    }
    pub fn region_dims(&self) -> [u32; 3] {
        self.region_dims
    }
    pub fn brick_count(&self) -> u64 {
        self.bricks
    }
    pub fn solid_voxels(&self) -> u64 {
        self.solid_voxels
    }

    /// The sequence number stamped on bricks by the following edits.
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    /// Sets the sequence number that edits stamp on the bricks they change. The scene owner calls
    /// this once per edit batch; it never goes backwards.
    pub fn set_sequence(&mut self, sequence: u64) {
        debug_assert!(sequence >= self.sequence, "sequence went backwards");
        self.sequence = sequence;
    }

    /// The scene's shared palette.
    pub fn swatches(&self) -> &crate::swatches::Swatches {
        &self.swatches
    }

    /// Replaces the palette (a snapshot restored, a `Palette` frame received).
    pub fn set_swatches(&mut self, swatches: crate::swatches::Swatches) {
        self.swatches = swatches;
    }

    /// Sets one swatch; `false` when there is no such swatch (nothing changes).
    pub fn set_swatch(&mut self, index: usize, colour: Colour) -> bool {
        self.swatches.set(index, colour)
    }

    /// Starts recording the brick every following edit changes, as it was before its first
    /// change: the before-image of a step, for undo. [`BrickMap::end_journal`] hands it over.
    pub fn begin_journal(&mut self) {
        self.journal.begin();
    }

    /// Stops journaling and calls `f(cell, bit, before, after)` for each voxel changed since
    /// [`BrickMap::begin_journal`] (`None`: empty), cells in the order first changed (linear
    /// index) and voxels in bit order within a cell. A voxel changed and changed back is not
    /// named.
    pub fn end_journal(&mut self, mut f: impl FnMut(u32, u16, Option<Colour>, Option<Colour>)) {
        let mut journal = std::mem::take(&mut self.journal);
        let mut scratch = [Colour::BLACK; VOXELS];
        // Single voxels by cell, then bit: each cell's run in the order cells were first changed.
        journal.voxels.retain(|v| v.0 != u32::MAX);
        journal.voxels.sort_unstable_by_key(|v| (v.0, v.1));
        let mut voxels = journal.voxels.iter().peekable();
        for (i, e) in journal.entries.iter().enumerate() {
            let coords = self.cell_coords(e.cell);
            let slot = self.slot_of_cell(coords);
            if e.whole {
                let before = (
                    &e.mask,
                    &journal.colours[e.start as usize..(e.start + e.len) as usize],
                );
                let after = match slot {
                    Some(slot) => (
                        &self.masks[slot as usize],
                        self.slot_colours(slot, &mut scratch),
                    ),
                    None => (&EMPTY_MASK, &[][..]),
                };
                crate::journal::diff_bricks(before, after, |bit, b, a| f(e.cell, bit, b, a));
                continue;
            }
            while let Some(&(_, bit, before)) = voxels.next_if(|v| v.0 == i as u32) {
                let after = slot.and_then(|slot| {
                    let mask = &self.masks[slot as usize];
                    let bit = u32::from(bit);
                    mask_get(mask, bit)
                        .then(|| {
                            crate::palette::colour_at_words(
                                self.block(slot),
                                rank(mask, bit) as usize,
                            )
                        })
                        .flatten()
                });
                if before != after {
                    f(e.cell, bit, before, after);
                }
            }
        }
        self.journal = journal;
        self.journal.on = false;
    }

    /// Journals the cell's whole brick before a change, once per journal (a cell journaled
    /// voxel by voxel so far gets its whole before-image now).
    fn note_before(&mut self, cell: [u32; 3]) {
        if !self.journal.on {
            return;
        }
        let index = self.cell_index(cell);
        let entry = self.journal.entry(index);
        if entry.is_some_and(|e| self.journal.entries[e].whole) {
            return;
        }
        let mut scratch = [Colour::BLACK; VOXELS];
        let (mask, colours) = match self.slot_of_cell(cell) {
            Some(slot) => (
                self.masks[slot as usize],
                self.slot_colours(slot, &mut scratch),
            ),
            None => (EMPTY_MASK, &[][..]),
        };
        match entry {
            Some(e) => self.journal.make_whole(e, &mask, colours),
            None => self.journal.record(index, mask, colours),
        }
    }

    /// Journals one voxel's value before a single-voxel edit changes it. In a map that codes
    /// colours within a bound a re-coded block may move other voxels' colours: the whole brick
    /// is journaled there.
    fn note_voxel(&mut self, cell: [u32; 3], bit: u32) {
        if self.colour_bound.is_some() {
            return self.note_before(cell);
        }
        let index = self.cell_index(cell);
        let before = self.slot_of_cell(cell).and_then(|slot| {
            let mask = &self.masks[slot as usize];
            mask_get(mask, bit)
                .then(|| {
                    crate::palette::colour_at_words(self.block(slot), rank(mask, bit) as usize)
                })
                .flatten()
        });
        self.journal.record_voxel(index, bit as u16, before);
    }

    /// Starts (or stops) recording which cells edits touch, for delta streaming.
    pub fn record_touched(&mut self, on: bool) {
        self.track_touched = on;
        self.touched.clear();
    }

    /// Linear cell indices touched since the last call, each once, in ascending order.
    pub fn take_touched(&mut self) -> Vec<u32> {
        let mut touched = std::mem::take(&mut self.touched);
        touched.sort_unstable();
        touched.dedup();
        touched
    }

    /// Starts recording which parts of the GPU arrays change; the client's uploader drains them.
    pub fn record_gpu_changes(&mut self, on: bool) {
        self.gpu = on.then(GpuChanges::default);
    }

    /// The GPU changes since the last call (empty when not recording).
    pub fn take_gpu_changes(&mut self) -> GpuChanges {
        match &mut self.gpu {
            Some(changes) => std::mem::take(changes),
            None => GpuChanges::default(),
        }
    }

    // ---- the raw arrays, for GPU upload -------------------------------------------------------

    pub fn regions(&self) -> &[u32] {
        &self.regions
    }
    pub fn cells(&self) -> &[u32] {
        &self.cells
    }
    /// Per cell block (the values of non-empty region entries): a bit per cell that holds a
    /// brick, indexed like the block's cells (`x + 4·y + 16·z` inside the region).
    pub fn block_cells(&self) -> &[u64] {
        &self.block_cells
    }
    pub fn masks(&self) -> &[Mask] {
        &self.masks
    }
    pub fn colour_bases(&self) -> &[u32] {
        &self.colour_base
    }
    /// Every brick's colour block ([`crate::palette`]) at its base, and free chunks.
    pub fn colour_pool(&self) -> &[u16] {
        &self.colours
    }

    // ---- addressing ---------------------------------------------------------------------------

    /// Whether a voxel coordinate lies inside the scene.
    #[inline]
    pub fn in_bounds(&self, pos: [u32; 3]) -> bool {
        pos[0] < self.size[0] && pos[1] < self.size[1] && pos[2] < self.size[2]
    }

    /// Linear index of a coarse cell.
    #[inline]
    pub fn cell_index(&self, cell: [u32; 3]) -> u32 {
        cell[0] + self.cell_dims[0] * (cell[1] + self.cell_dims[1] * cell[2])
    }

    /// Coarse cell of a linear index.
    #[inline]
    pub fn cell_coords(&self, index: u32) -> [u32; 3] {
        let x = index % self.cell_dims[0];
        let rest = index / self.cell_dims[0];
        [x, rest % self.cell_dims[1], rest / self.cell_dims[1]]
    }

    #[inline]
    pub(crate) fn region_index(&self, region: [u32; 3]) -> usize {
        (region[0] + self.region_dims[0] * (region[1] + self.region_dims[1] * region[2])) as usize
    }

    fn region_coords(&self, index: usize) -> [u32; 3] {
        let i = index as u32;
        let [dx, dy, _] = self.region_dims;
        [i % dx, (i / dx) % dy, i / (dx * dy)]
    }

    /// Inclusive region bounds that contain every allocated region, `None` when none is. Never
    /// smaller than the occupied regions; after [`BrickMap::rebuild_clearance`] exactly their
    /// bounding box (edits that free regions leave it larger until then, which is still safe).
    pub fn occupied_regions(&self) -> Option<([u32; 3], [u32; 3])> {
        self.occupied
    }

    /// The coarse cells of region `r` that lie inside the grid, x fastest.
    pub fn region_cells(&self, r: [u32; 3]) -> impl Iterator<Item = [u32; 3]> + use<> {
        let lo = r.map(|c| c.saturating_mul(REGION_CELLS));
        let hi: [u32; 3] =
            std::array::from_fn(|i| lo[i].saturating_add(REGION_CELLS).min(self.cell_dims[i]));
        box_points(lo, hi)
    }

    /// Index of a cell inside its block.
    #[inline]
    pub(crate) const fn cell_in_block(cell: [u32; 3]) -> u32 {
        (cell[0] & 3) | ((cell[1] & 3) << 2) | ((cell[2] & 3) << 4)
    }

    /// Brick slot of a coarse cell, or `None` if the cell is empty or outside the grid.
    #[inline]
    pub fn slot_of_cell(&self, cell: [u32; 3]) -> Option<u32> {
        if cell[0] >= self.cell_dims[0]
            || cell[1] >= self.cell_dims[1]
            || cell[2] >= self.cell_dims[2]
        {
            return None;
        }
        let block = region_block(self.regions[self.region_index(cell.map(|c| c / REGION_CELLS))])?;
        let slot = self.cells[(block * CELLS_PER_BLOCK + Self::cell_in_block(cell)) as usize];
        (!cell_is_empty(slot)).then_some(slot)
    }

    /// Colour of a voxel, `None` where it is empty or outside the scene.
    pub fn get(&self, pos: [u32; 3]) -> Option<Colour> {
        if !self.in_bounds(pos) {
            return None;
        }
        let slot = self.slot_of_cell(pos.map(|p| p / BRICK_EDGE))? as usize;
        let bit = voxel_bit(pos[0], pos[1], pos[2]);
        let mask = &self.masks[slot];
        if !mask_get(mask, bit) {
            return None;
        }
        crate::palette::colour_at_words(self.block(slot as u32), rank(mask, bit) as usize)
    }

    /// Whether a voxel is solid (the mask alone: no colour lookup). False outside the scene.
    pub fn is_solid(&self, pos: [u32; 3]) -> bool {
        if !self.in_bounds(pos) {
            return false;
        }
        self.slot_of_cell(pos.map(|p| p / BRICK_EDGE))
            .is_some_and(|slot| {
                mask_get(
                    &self.masks[slot as usize],
                    voxel_bit(pos[0], pos[1], pos[2]),
                )
            })
    }

    // ---- single-voxel edits -------------------------------------------------------------------

    /// Makes a voxel solid with `colour`. Returns whether anything changed. Out of bounds: no-op
    /// returning false (callers validate ops before applying them).
    pub fn set(&mut self, pos: [u32; 3], colour: Colour) -> bool {
        self.edit_voxel(pos, BrushMode::Fill, colour)
    }

    /// Makes a voxel empty. Returns whether anything changed.
    pub fn clear(&mut self, pos: [u32; 3]) -> bool {
        self.edit_voxel(pos, BrushMode::Erase, Colour::BLACK)
    }

    /// Recolours a voxel if it is solid. Returns whether anything changed.
    pub fn paint(&mut self, pos: [u32; 3], colour: Colour) -> bool {
        self.edit_voxel(pos, BrushMode::Paint, colour)
    }

    fn edit_voxel(&mut self, pos: [u32; 3], mode: BrushMode, colour: Colour) -> bool {
        if !self.in_bounds(pos) {
            return false;
        }
        let cell = pos.map(|p| p / BRICK_EDGE);
        let bit = voxel_bit(pos[0], pos[1], pos[2]);
        if self.journal.on {
            self.note_voxel(cell, bit);
        }
        let Some(slot) = self.slot_of_cell(cell) else {
            if mode != BrushMode::Fill {
                return false;
            }
            let mut mask = EMPTY_MASK;
            mask_set(&mut mask, bit, true);
            self.insert_brick(cell, mask, &[colour]);
            return true;
        };
        let s = slot as usize;
        let solid = mask_get(&self.masks[s], bit);
        // A random edit's time is its cache misses (the cell, the mask, the block): each is
        // read once here and handed on, not looked up again.
        let (r, n) = rank_and_count(&self.masks[s], bit);
        let (r, n) = (r as usize, n as usize);
        let block = self.block(slot);
        let coding = crate::palette::coding_of_words(block).ok();
        let one = match coding {
            Some(crate::palette::Coding::One) => block.get(1).copied().map(Colour),
            _ => None,
        };
        match (mode, solid) {
            (BrushMode::Paint | BrushMode::Erase, false) => return false,
            (BrushMode::Fill | BrushMode::Paint, true)
                if coding.and_then(|c| c.colour_at(block, r)) == Some(colour) =>
            {
                return false;
            }
            (BrushMode::Erase, true) if n == 1 => {
                self.remove_slot(slot);
                return true;
            }
            // A one-colour block holds any number of voxels of its colour: only the mask moves.
            (BrushMode::Fill, false) | (BrushMode::Erase, true)
                if one.is_some_and(|c| mode == BrushMode::Erase || c == colour) =>
            {
                mask_set(&mut self.masks[s], bit, mode == BrushMode::Fill);
                if mode == BrushMode::Fill {
                    self.solid_voxels += 1;
                } else {
                    self.solid_voxels -= 1;
                }
                self.mark_slot(slot);
            }
            _ if coding.is_some_and(|coding| {
                self.edit_block_in_place(slot, bit, (r, n), coding, mode, colour)
            }) => {}
            _ => {
                let mut scratch = [Colour::BLACK; VOXELS + 1];
                let len = n;
                self.slot_colours(slot, (&mut scratch[..VOXELS]).try_into().expect("512"));
                let mut mask = self.masks[s];
                let n = match (mode, solid) {
                    (BrushMode::Erase, _) => {
                        scratch.copy_within(r + 1..len, r);
                        len - 1
                    }
                    (_, true) => {
                        scratch[r] = colour;
                        len
                    }
                    (_, false) => {
                        scratch.copy_within(r..len, r + 1);
                        scratch[r] = colour;
                        len + 1
                    }
                };
                mask_set(
                    &mut mask,
                    bit,
                    mode == BrushMode::Fill || (mode == BrushMode::Paint),
                );
                // Single voxels in many colours (a 16-colour palette full, or raw already): raw,
                // which the next such edits change in place, rather than sorting the brick's
                // colours each time. Brushes and loads re-code it at its smallest.
                let raw = self.colour_bound.is_none()
                    && match coding {
                        Some(crate::palette::Coding::Raw) => true,
                        Some(crate::palette::Coding::Palette { bits, entries }) => {
                            bits >= 4 && entries == 1 << bits && mode != BrushMode::Erase
                        }
                        _ => false,
                    };
                let how = if raw { Exact::Raw } else { Exact::Smallest };
                self.replace_brick_as(slot, mask, &scratch[..n], how);
                return true;
            }
        }
        self.stamp(slot);
        true
    }

    /// A single voxel's edit (voxel `bit`, the `r`th solid one of its brick) made in its
    /// brick's block where it lies (`crate::block_edit`): whether it was. Not in a copy with a
    /// colour bound (its blocks are re-coded whole). `n`: the brick's solid voxels; `coding`:
    /// its block's.
    fn edit_block_in_place(
        &mut self,
        slot: u32,
        bit: u32,
        (r, n): (usize, usize),
        coding: crate::palette::Coding,
        mode: BrushMode,
        colour: Colour,
    ) -> bool {
        use crate::block_edit::{Edit, edit_in_place};
        if self.colour_bound.is_some() {
            return false;
        }
        let s = slot as usize;
        let edit = match (mode, mask_get(&self.masks[s], bit)) {
            (BrushMode::Erase, true) => Edit::Remove,
            (BrushMode::Fill | BrushMode::Paint, true) => Edit::Recolour(colour),
            (BrushMode::Fill, false) => Edit::Insert(colour),
            (BrushMode::Erase | BrushMode::Paint, false) => return false,
        };
        let base = self.colour_base[s] as usize;
        let cap = usize::from(self.slot_capacity[s]);
        let Some(changed) = edit_in_place(&mut self.colours[base..base + cap], coding, n, r, edit)
        else {
            return false;
        };
        match edit {
            Edit::Insert(_) => {
                mask_set(&mut self.masks[s], bit, true);
                self.solid_voxels += 1;
                self.mark_slot(slot);
            }
            Edit::Remove => {
                mask_set(&mut self.masks[s], bit, false);
                self.solid_voxels -= 1;
                self.mark_slot(slot);
            }
            Edit::Recolour(_) => {}
        }
        self.coded_words = self.coded_words + changed.words as u64 - changed.before as u64;
        let end = changed.words.max(changed.before);
        if end > changed.first {
            self.mark_colours((base + changed.first) as u32, (end - changed.first) as u32);
        }
        true
    }

    // ---- brushes ------------------------------------------------------------------------------

    /// Applies `mode` to every voxel whose centre lies within `radius` of `centre`, clipped to the
    /// scene. Returns the number of voxels whose solidity or colour changed.
    pub fn sphere(
        &mut self,
        centre: [f32; 3],
        radius: f32,
        mode: BrushMode,
        colour: Colour,
    ) -> u64 {
        let mut changed = 0;
        let within = self.whole();
        sphere_brushes(centre, radius, within, |cell, brush| {
            changed += self.apply_brush(cell, brush, mode, colour);
        });
        changed
    }

    /// Applies `mode` to every voxel in the inclusive box `min..=max`, clipped to the scene.
    /// Returns the number of voxels whose solidity or colour changed.
    pub fn fill_box(
        &mut self,
        min: [u32; 3],
        max: [u32; 3],
        mode: BrushMode,
        colour: Colour,
    ) -> u64 {
        let mut changed = 0;
        let within = self.whole();
        box_brushes(min, max, within, |cell, brush| {
            changed += self.apply_brush(cell, brush, mode, colour);
        });
        changed
    }

    /// The scene as an inclusive voxel box.
    pub fn whole(&self) -> VoxelBox {
        VoxelBox {
            lo: [0; 3],
            hi: self.size.map(|s| s - 1),
        }
    }

    /// Applies a brush mask to one brick. The brush must not cover voxels outside the scene.
    /// Returns the number of voxels whose solidity or colour changed.
    pub fn apply_brush(
        &mut self,
        cell: [u32; 3],
        brush: &Mask,
        mode: BrushMode,
        colour: Colour,
    ) -> u64 {
        let slot = self.slot_of_cell(cell);
        let mut old = [Colour::BLACK; VOXELS];
        let (old_mask, old_colours): (Mask, &[Colour]) = match slot {
            Some(s) => (self.masks[s as usize], self.slot_colours(s, &mut old)),
            None => (EMPTY_MASK, &[]),
        };
        let mut scratch = [Colour::BLACK; 512];
        let (new_mask, n, changed) =
            brush_brick((&old_mask, old_colours), brush, mode, colour, &mut scratch);
        if changed == 0 {
            return 0;
        }
        self.note_before(cell);
        match slot {
            None => self.insert_brick(cell, new_mask, &scratch[..n]),
            Some(s) if n == 0 => self.remove_slot(s),
            Some(s) => self.replace_brick(s, new_mask, &scratch[..n]),
        }
        changed
    }

    // ---- whole bricks -------------------------------------------------------------------------

    /// Stores a whole brick (as received from the server or loaded from a snapshot), replacing
    /// whatever the cell held. Validates it against the scene first; on error nothing changes.
    pub fn put_brick(&mut self, brick: &BrickData) -> Result<(), MapError> {
        self.check_brick(brick)?;
        self.write_checked(brick.cell, brick.mask, &brick.colours, Exact::Smallest);
        Ok(())
    }

    /// Stores a checked brick at `cell` (inserted or replacing), its colours coded as `how`.
    fn write_checked(&mut self, cell: [u32; 3], mask: Mask, colours: &[Colour], how: Exact) {
        self.note_before(cell);
        match self.slot_of_cell(cell) {
            Some(slot) => self.replace_brick_as(slot, mask, colours, how),
            None => self.insert_brick_as(cell, mask, colours, how),
        }
    }

    /// [`BrickMap::put_brick`] for a brick whose colour block is at hand, as a received blob
    /// hands it out ([`crate::wire::BrickRef`]): the block is stored as it is, without coding
    /// the colours again. `block` must decode to `colours`: an exact block (the blob decoder
    /// decoded it to get them), or, in a map with a colour bound, the lossy block
    /// [`crate::palette::lossy`] made from them within that bound. A map with a colour bound
    /// does not try lossy blocks itself here: its caller did (a viewer codes a blob's bricks on
    /// several threads at once, [`crate::palette::lossy_many`]) and hands over the exact block
    /// where they did not pay. A block that names no coding or another length, or a lossy
    /// block in an exact map, is refused as an inconsistent brick. On error nothing changes.
    pub fn put_coded(
        &mut self,
        cell: [u32; 3],
        mask: Mask,
        colours: &[Colour],
        block: &[u16],
    ) -> Result<(), MapError> {
        self.check_cell(cell)?;
        let Some(block) = self.given_block(&mask, colours.len(), block) else {
            return Err(MapError::InconsistentBrick(cell));
        };
        self.check_voxels(cell, &mask)?;
        self.write_checked(cell, mask, colours, Exact::Given(block));
        Ok(())
    }

    /// The words of `block` that code `n` colours of a brick with `mask`, if this map may
    /// store it as it is (see [`BrickMap::put_coded`]); `None`: it may not.
    pub(crate) fn given_block<'b>(
        &self,
        mask: &Mask,
        n: usize,
        block: &'b [u16],
    ) -> Option<&'b [u16]> {
        let fitting = match crate::palette::coding_of_words(block) {
            Ok(crate::palette::Coding::Blocks { .. }) if self.colour_bound.is_none() => None,
            Err(_) => None,
            Ok(coding) => block.get(..coding.words(n)),
        };
        fitting.filter(|_| n > 0 && popcount(mask) as usize == n)
    }

    /// Writes many whole bricks (`None`: the cell empties), as [`BrickMap::put_brick`] and
    /// [`BrickMap::remove_brick`] would one by one, but recomputes the clearance of the empty
    /// cells around the inserted bricks once, block by block, instead of lowering it around
    /// each brick (125 cells visited per brick: most of the cost of writing the 65,536 bricks
    /// of a large undo). Stops at the first brick that does not fit this scene; those before
    /// it stay written, with their clearance right.
    pub fn write_bricks(
        &mut self,
        bricks: impl IntoIterator<Item = ([u32; 3], Option<(Mask, Vec<Colour>)>)>,
    ) -> Result<(), MapError> {
        self.deferred_clearance = Some(Vec::new());
        let mut result = Ok(());
        for (cell, brick) in bricks {
            match brick {
                Some((mask, colours)) => {
                    let brick = BrickData {
                        cell,
                        mask,
                        colours,
                    };
                    if let Err(e) = self.put_brick(&brick) {
                        result = Err(e);
                        break;
                    }
                }
                None => {
                    self.remove_brick(cell);
                }
            }
        }
        let mut regions = self.deferred_clearance.take().unwrap_or_default();
        regions.sort_unstable();
        regions.dedup();
        // The cells within two of an inserted brick lie in its region or the 26 around it.
        let dims = self.region_dims.map(i64::from);
        let mut around = Vec::with_capacity(regions.len() * 2);
        for &r in &regions {
            let c = self.region_coords(r as usize).map(i64::from);
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let n = [c[0] + dx, c[1] + dy, c[2] + dz];
                        if (0..3).all(|i| n[i] >= 0 && n[i] < dims[i]) {
                            around.push(self.region_index(n.map(|v| v as u32)));
                        }
                    }
                }
            }
        }
        around.sort_unstable();
        around.dedup();
        self.rebuild_cell_clearance_in(around);
        result
    }

    /// Checks that a brick fits this scene: inside the coarse grid, consistent, and with no solid
    /// voxel beyond the scene's edge (the last brick on an axis may be partial).
    /// [`BrickMap::check_brick`] for a brick given by its parts (a wire blob's `BrickRef`).
    pub fn check_parts(
        &self,
        cell: [u32; 3],
        mask: &Mask,
        colours: &[Colour],
    ) -> Result<(), MapError> {
        self.check_cell(cell)?;
        if crate::brick::mask_is_empty(mask) || colours.len() != popcount(mask) as usize {
            return Err(MapError::InconsistentBrick(cell));
        }
        self.check_voxels(cell, mask)
    }

    pub fn check_brick(&self, brick: &BrickData) -> Result<(), MapError> {
        self.check_cell(brick.cell)?;
        if !brick.is_consistent() {
            return Err(MapError::InconsistentBrick(brick.cell));
        }
        self.check_voxels(brick.cell, &brick.mask)
    }

    fn check_cell(&self, cell: [u32; 3]) -> Result<(), MapError> {
        if (0..3).any(|i| cell[i] >= self.cell_dims[i]) {
            return Err(MapError::CellOutOfBounds {
                cell,
                cells: self.cell_dims,
            });
        }
        Ok(())
    }

    /// No voxel of `mask` at `cell` lies past the scene's far edge.
    fn check_voxels(&self, cell: [u32; 3], mask: &Mask) -> Result<(), MapError> {
        // Only a brick at the scene's far edge on some axis can hold a voxel beyond it: the
        // rest are not walked bit by bit (a full brick was 512 steps of every sync and write).
        let partial = (0..3).any(|i| cell[i] * BRICK_EDGE + BRICK_EDGE > self.size[i]);
        let mut outside = false;
        if partial {
            for_each_bit(mask, |b| {
                let l = crate::brick::bit_voxel(b);
                outside |= (0..3).any(|i| cell[i] * BRICK_EDGE + l[i] >= self.size[i]);
            });
        }
        if outside {
            return Err(MapError::VoxelsOutOfBounds(cell));
        }
        Ok(())
    }

    /// Removes the brick at a cell, if any. Returns whether there was one.
    pub fn remove_brick(&mut self, cell: [u32; 3]) -> bool {
        match self.slot_of_cell(cell) {
            Some(slot) => {
                self.note_before(cell);
                self.remove_slot(slot);
                true
            }
            None => false,
        }
    }

    /// The brick at a cell in compact form.
    pub fn brick(&self, cell: [u32; 3]) -> Option<BrickData> {
        self.slot_of_cell(cell).map(|slot| self.slot_brick(slot))
    }

    /// Version (sequence of the last edit) of the brick at a cell.
    pub fn brick_version(&self, cell: [u32; 3]) -> Option<u64> {
        self.slot_of_cell(cell)
            .map(|slot| self.slot_version[slot as usize])
    }

    fn slot_brick(&self, slot: u32) -> BrickData {
        BrickData {
            cell: self.cell_coords(self.slot_cell[slot as usize]),
            mask: self.masks[slot as usize],
            colours: {
                let mut scratch = [Colour::BLACK; VOXELS];
                self.slot_colours(slot, &mut scratch).to_vec()
            },
        }
    }

    /// The colour block of the brick in `slot` ([`crate::palette`]): from its base to the end
    /// of its chunk (a block knows its own length).
    pub fn block(&self, slot: u32) -> &[u16] {
        let s = slot as usize;
        let base = self.colour_base[s] as usize;
        &self.colours[base..base + usize::from(self.slot_capacity[s])]
    }

    /// The colours of the brick in `slot`, one per solid voxel in bit order, decoded into `out`.
    pub fn slot_colours<'a>(&self, slot: u32, out: &'a mut [Colour; VOXELS]) -> &'a [Colour] {
        let n = popcount(&self.masks[slot as usize]) as usize;
        let out = &mut out[..n];
        // The map wrote every block itself; `check_invariants` decodes them all.
        if crate::palette::decode_words(self.block(slot), out).is_err() {
            debug_assert!(
                false,
                "slot {slot} holds a colour block that does not decode"
            );
        }
        out
    }

    /// Every brick, in slot order, with its version.
    pub fn bricks(&self) -> impl Iterator<Item = (BrickData, u64)> + '_ {
        (0..self.slot_cell.len() as u32)
            .filter(|&s| self.slot_cell[s as usize] < COARSE)
            .map(|s| (self.slot_brick(s), self.slot_version[s as usize]))
    }

    /// Cells of every brick, with version, without copying brick contents.
    pub fn brick_cells(&self) -> impl Iterator<Item = ([u32; 3], u64)> + '_ {
        self.slot_cell
            .iter()
            .zip(&self.slot_version)
            .filter(|(c, _)| **c < COARSE)
            .map(|(&c, &v)| (self.cell_coords(c), v))
    }

    /// Brick slots so far (some may be free): the end of the range [`BrickMap::slot_cells`] takes.
    pub fn slot_count(&self) -> u32 {
        self.slot_cell.len() as u32
    }

    /// Linear cell indices of the bricks in slots `slots` (free slots skipped), for walking a
    /// large map a part at a time.
    pub fn slot_cells(&self, slots: std::ops::Range<u32>) -> impl Iterator<Item = u32> + '_ {
        let end = (slots.end as usize).min(self.slot_cell.len());
        let start = (slots.start as usize).min(end);
        self.slot_cell[start..end]
            .iter()
            .copied()
            .filter(|&c| c < COARSE)
    }

    /// What a client that has seen everything up to `since` is missing: the cells of bricks
    /// changed after it and the cells whose bricks were removed after it. `None` when tombstones
    /// that old were already dropped: such a client needs a full resync.
    pub fn changes_since(&self, since: u64) -> Option<Changes> {
        if since < self.tombstone_horizon {
            return None;
        }
        let changed = self
            .brick_cells()
            .filter(|&(_, v)| v > since)
            .map(|(c, _)| c)
            .collect();
        let mut removed: Vec<[u32; 3]> = self
            .tombstones
            .iter()
            .filter(|&(_, &v)| v > since)
            .map(|(&c, _)| self.cell_coords(c))
            .collect();
        removed.sort_unstable();
        Some(Changes { changed, removed })
    }

    /// Drops tombstones at or below `sequence`; resumes from before it will need a full resync.
    pub fn prune_tombstones(&mut self, sequence: u64) {
        self.tombstones.retain(|_, v| *v > sequence);
        self.tombstone_horizon = self.tombstone_horizon.max(sequence);
    }

    pub fn tombstone_count(&self) -> usize {
        self.tombstones.len()
    }

    /// An order-independent 64-bit hash of the whole scene (cells, masks, colours, and the
    /// shared palette): two maps with equal hashes hold the same voxels and palette, whatever
    /// their slot layout.
    pub fn content_hash(&self) -> u64 {
        let mut total = mix(u64::from(self.size[0])
            | u64::from(self.size[1]) << 21
            | u64::from(self.size[2]) << 42);
        for (i, four) in self.swatches.0.chunks(4).enumerate() {
            let word = four.iter().fold(0, |acc, c| acc << 16 | u64::from(c.0));
            // Each group of four salted by its place, so a reordered palette hashes otherwise.
            total = total.wrapping_add(mix(word ^ mix(0x5a5a_0000 ^ i as u64)));
        }
        for slot in 0..self.slot_cell.len() as u32 {
            let cell = self.slot_cell[slot as usize];
            if cell < COARSE {
                let mut scratch = [Colour::BLACK; VOXELS];
                total = total.wrapping_add(brick_hash(
                    cell,
                    &self.masks[slot as usize],
                    self.slot_colours(slot, &mut scratch),
                ));
            }
        }
        total
    }

    /// Bytes per component as laid out on the GPU.
    pub fn memory(&self) -> MemoryStats {
        let region_bytes = self.regions.len() as u64 * 4;
        let cell_bytes = self.cells.len() as u64 * 4;
        let mask_bytes = self.masks.len() as u64 * 64;
        let colour_base_bytes = self.colour_base.len() as u64 * 4;
        let colour_bytes = self.colours.len() as u64 * 2;
        let total_bytes = region_bytes + cell_bytes + mask_bytes + colour_base_bytes + colour_bytes;
        let dense_cells: u64 = self.cell_dims.iter().map(|&d| u64::from(d)).product();
        let per_voxel = |bytes: u64| {
            if self.solid_voxels == 0 {
                0.0
            } else {
                bytes as f64 / self.solid_voxels as f64
            }
        };
        MemoryStats {
            size: self.size,
            bricks: self.bricks,
            solid_voxels: self.solid_voxels,
            cell_blocks: (self.block_cells.len() - self.free_blocks.len()) as u64,
            region_bytes,
            cell_bytes,
            mask_bytes,
            colour_base_bytes,
            colour_bytes,
            colour_used_bytes: self.coded_words * 2,
            total_bytes,
            paper_formula_bytes: 4 * dense_cells + 20 * self.bricks + 2048 * self.bricks,
            bytes_per_solid_voxel: per_voxel(total_bytes),
            mask_bits_per_voxel: 8.0 * per_voxel(mask_bytes),
            colour_bits_per_voxel: 8.0 * per_voxel(colour_bytes),
        }
    }

    // ---- allocation ---------------------------------------------------------------------------

    fn insert_brick(&mut self, cell: [u32; 3], mask: Mask, colours: &[Colour]) {
        self.insert_brick_as(cell, mask, colours, Exact::Smallest);
    }

    /// [`BrickMap::insert_brick`], the colours coded as `how` says.
    fn insert_brick_as(&mut self, cell: [u32; 3], mask: Mask, colours: &[Colour], how: Exact) {
        debug_assert_eq!(popcount(&mask) as usize, colours.len());
        let region = self.region_index(cell.map(|c| c / REGION_CELLS));
        let entry = self.regions[region];
        let block = match region_block(entry) {
            Some(block) => block,
            None => {
                // An empty region, or a stand-in: level 0 takes its place.
                if region_stand_in(entry).is_some() {
                    self.stand_ins -= 1;
                }
                let block = self.alloc_block();
                self.regions[region] = block;
                if let Some(g) = &mut self.gpu {
                    g.regions.push(region as u32);
                }
                let r = cell.map(|c| c / REGION_CELLS);
                self.occupy_region(r);
                self.lower_clearance_for(r);
                block
            }
        };
        let slot = self.alloc_slot();
        let s = slot as usize;
        self.masks[s] = mask;
        self.slot_capacity[s] = 0;
        self.store_colours_as(slot, colours, how);
        let cell_index = self.cell_index(cell);
        self.slot_cell[s] = cell_index;
        let local = Self::cell_in_block(cell);
        self.cells[(block * CELLS_PER_BLOCK + local) as usize] = slot;
        self.block_cells[block as usize] |= 1 << local;
        match &mut self.deferred_clearance {
            Some(regions) => regions.push(region as u32),
            None if self.bulk => {}
            None => self.lower_cell_clearance_around(cell),
        }
        self.tombstones.remove(&cell_index);
        self.bricks += 1;
        self.solid_voxels += colours.len() as u64;
        if let Some(g) = &mut self.gpu {
            g.cell_blocks.push(block);
        }
        self.mark_slot(slot);
        self.stamp(slot);
    }

    /// Rewrites an existing brick, moving its colours to a chunk of the right class if needed.
    fn replace_brick(&mut self, slot: u32, mask: Mask, colours: &[Colour]) {
        self.replace_brick_as(slot, mask, colours, Exact::Smallest);
    }

    /// [`BrickMap::replace_brick`], the colours coded as `how` says.
    fn replace_brick_as(&mut self, slot: u32, mask: Mask, colours: &[Colour], how: Exact) {
        debug_assert_eq!(popcount(&mask) as usize, colours.len());
        let s = slot as usize;
        let old_n = popcount(&self.masks[s]);
        self.coded_words -= self.block_words(slot) as u64;
        self.masks[s] = mask;
        self.store_colours_as(slot, colours, how);
        self.solid_voxels = self.solid_voxels + colours.len() as u64 - u64::from(old_n);
        self.mark_slot(slot);
        self.stamp(slot);
    }

    /// Lets bricks written from now on be coded in lossy blocks ([`crate::blocks`]) where every
    /// voxel stays within `bound` per channel (0–255 scale) and the blocks are smaller than the
    /// exact coding; `None` (the default) keeps every brick exact. A viewer's GPU copy is the
    /// place for it: the server's scene, its store and the wire stay exact, and each brick
    /// arrives exact and is coded once, so errors never compound.
    pub fn set_colour_bound(&mut self, bound: Option<u32>) {
        self.colour_bound = bound;
    }

    pub fn colour_bound(&self) -> Option<u32> {
        self.colour_bound
    }

    /// Each brick's coding in the colour pool and its number of voxels, in slot order.
    pub fn codings(&self) -> impl Iterator<Item = (crate::palette::Coding, usize)> + '_ {
        (0..self.slot_cell.len() as u32)
            .filter(|&s| self.slot_cell[s as usize] < COARSE)
            .filter_map(|s| {
                let n = popcount(&self.masks[s as usize]) as usize;
                crate::palette::coding_of_words(self.block(s))
                    .ok()
                    .map(|c| (c, n))
            })
    }

    /// Words of the colour chunk the brick in `slot` takes once written into a fresh map as it
    /// is coded here ([`BrickMap::put_coded`] with [`BrickMap::block`]): its block's length
    /// rounded to the size class.
    pub fn fresh_chunk_words(&self, slot: u32) -> u32 {
        colour_capacity(self.block_words(slot) as u32)
    }

    /// Words the block of the brick in `slot` takes (its header says how it is coded).
    fn block_words(&self, slot: u32) -> usize {
        let n = popcount(&self.masks[slot as usize]) as usize;
        crate::palette::coding_of_words(self.block(slot)).map_or(0, |c| c.words(n))
    }

    /// Codes `colours` into the slot's chunk, moving it to a chunk of the right class if the
    /// block outgrew it or takes less than half of it (so a brick edited back and forth does
    /// not thrash). A slot with capacity 0 gets its first chunk. The exact coding is as `how`
    /// says; a map with a colour bound codes lossy blocks where they are smaller.
    fn store_colours_as(&mut self, slot: u32, colours: &[Colour], how: Exact) {
        let s = slot as usize;
        let (coding, palette) = match how {
            Exact::Smallest => crate::palette::choose(colours),
            Exact::Raw => (crate::palette::Coding::Raw, Vec::new()),
            Exact::Given(block) => (
                crate::palette::coding_of_words(block).unwrap_or(crate::palette::Coding::Raw),
                Vec::new(),
            ),
        };
        let n = colours.len();
        let mut lossy = Vec::new();
        if let Some(bound) = self.colour_bound
            && !matches!(how, Exact::Given(_))
        {
            // `None`: exact is smaller, or some voxel would stray past the bound; `lossy`
            // stays empty.
            crate::palette::lossy(colours, coding, bound, &mut lossy);
        }
        let words = if lossy.is_empty() {
            coding.words(n) as u32
        } else {
            lossy.len() as u32
        };
        let cap = u32::from(self.slot_capacity[s]);
        if words > cap || colour_capacity(words) * 2 <= cap {
            self.free_chunk(self.colour_base[s], cap);
            let new_cap = colour_capacity(words);
            self.colour_base[s] = self.alloc_chunk(new_cap);
            self.slot_capacity[s] = new_cap as u16;
        }
        let base = self.colour_base[s];
        let out = &mut self.colours[base as usize..(base + words) as usize];
        if lossy.is_empty() {
            match how {
                // `put_coded` handed exactly the block's own words.
                Exact::Given(block) => out.copy_from_slice(block),
                Exact::Raw | Exact::Smallest => {
                    crate::palette::encode_words(colours, coding, &palette, out)
                }
            }
        } else {
            out.copy_from_slice(&lossy);
        }
        self.coded_words += u64::from(words);
        self.mark_colours(base, words);
    }

    fn remove_slot(&mut self, slot: u32) {
        let s = slot as usize;
        let cell_index = self.slot_cell[s];
        let cell = self.cell_coords(cell_index);
        let region = self.region_index(cell.map(|c| c / REGION_CELLS));
        let block = self.regions[region];
        let local = Self::cell_in_block(cell);
        self.cells[(block * CELLS_PER_BLOCK + local) as usize] = EMPTY_CELL;
        self.block_cells[block as usize] &= !(1 << local);
        if let Some(g) = &mut self.gpu {
            g.cell_blocks.push(block);
        }
        if self.block_cells[block as usize] == 0 {
            // Clearance 0 is always safe; neighbours keep theirs (still conservative).
            self.regions[region] = EMPTY_REGION;
            self.free_blocks.push(block);
            if let Some(g) = &mut self.gpu {
                g.regions.push(region as u32);
            }
        }
        self.solid_voxels -= u64::from(popcount(&self.masks[s]));
        self.coded_words -= self.block_words(slot) as u64;
        self.free_chunk(self.colour_base[s], u32::from(self.slot_capacity[s]));
        self.masks[s] = EMPTY_MASK;
        self.slot_cell[s] = EMPTY;
        self.slot_capacity[s] = 0;
        self.free_slots.push(slot);
        self.bricks -= 1;
        self.tombstones.insert(cell_index, self.sequence);
        if self.track_touched {
            self.touched.push(cell_index);
        }
        self.mark_slot(slot);
    }

    /// A region just became occupied: no empty region within distance D of it may claim a
    /// clearance of D or more.
    /// Region `r` was just occupied: the clearance around it is lowered now, or, while
    /// [`BrickMap::defer_region_clearance`] holds, once around the box of all such regions.
    fn lower_clearance_for(&mut self, r: [u32; 3]) {
        if self.bulk {
            return;
        }
        match &mut self.deferred_regions {
            Some(b) => {
                *b = Some(match *b {
                    None => (r, r),
                    Some((lo, hi)) => (
                        std::array::from_fn(|a| lo[a].min(r[a])),
                        std::array::from_fn(|a| hi[a].max(r[a])),
                    ),
                });
            }
            None => self.lower_clearance_around_box(r, r),
        }
    }

    /// Regions `lo..=hi` were occupied (some or all of them): empty regions within
    /// [`CLEARANCE_CAP`] of the box may claim less clearance than they do, and an empty region
    /// inside the box claims none (lowering around each occupied region would leave it at most
    /// that; zero is always safe, and [`BrickMap::rebuild_clearance`] makes it exact again).
    ///
    /// Outside the box it goes shell by shell (the regions at distance 1, then 2, ...) and
    /// stops at the first shell where no region had to be lowered: clearance is 1-Lipschitz
    /// (it is a capped distance, and every change keeps it so: lowering takes the minimum with
    /// another such distance, a freed region gets 0 beside an occupied neighbour), so if every
    /// region at distance `d` claims less than `d`, every region at `d + 1` claims less than
    /// `d + 1`. Where the box lies among occupied regions this visits the 26 around it, not
    /// (2·cap+1)³.
    fn lower_clearance_around_box(&mut self, lo: [u32; 3], hi: [u32; 3]) {
        let dims = self.region_dims.map(i64::from);
        let (lo, hi) = (lo.map(i64::from), hi.map(i64::from));
        let lower = |map: &mut BrickMap, x: i64, y: i64, z: i64, d: i64| -> bool {
            let i = (x + dims[0] * (y + dims[1] * z)) as usize;
            let entry = map.regions[i];
            if !region_is_empty(entry) || i64::from(region_clearance(entry)) < d.max(1) {
                return false;
            }
            map.regions[i] = EMPTY_REGION | (d - 1).max(0) as u32;
            if let Some(g) = &mut map.gpu {
                g.regions.push(i as u32);
            }
            true
        };
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    lower(self, x, y, z, 0);
                }
            }
        }
        for d in 1..=i64::from(CLEARANCE_CAP) {
            let from: [i64; 3] = std::array::from_fn(|a| lo[a] - d);
            let to: [i64; 3] = std::array::from_fn(|a| hi[a] + d);
            let inside = |v: i64, a: usize| v > from[a] && v < to[a];
            let mut any = false;
            for z in from[2].max(0)..=to[2].min(dims[2] - 1) {
                for y in from[1].max(0)..=to[1].min(dims[1] - 1) {
                    if inside(z, 2) && inside(y, 1) {
                        // Only the two ends of this row lie on the shell.
                        for x in [from[0], to[0]] {
                            if x >= 0 && x < dims[0] {
                                any |= lower(self, x, y, z, d);
                            }
                        }
                    } else {
                        for x in from[0].max(0)..=to[0].min(dims[0] - 1) {
                            any |= lower(self, x, y, z, d);
                        }
                    }
                }
            }
            if !any {
                break;
            }
        }
    }

    /// Every empty region claims no clearance (always safe): regions occupied from now on
    /// lower nothing around them, until [`BrickMap::rebuild_clearance`]. For a copy about to
    /// take many regions in empty space at once.
    pub fn zero_region_clearance(&mut self) {
        for i in 0..self.regions.len() {
            if region_is_empty(self.regions[i]) && region_clearance(self.regions[i]) != 0 {
                self.regions[i] = EMPTY_REGION;
                if let Some(g) = &mut self.gpu {
                    g.regions.push(i as u32);
                }
            }
        }
    }

    /// From now until [`BrickMap::end_bulk_load`], writing a brick does not keep the empty
    /// space's clearance (what lets rays skip it) current: a scene loaded whole from a store
    /// writes millions of bricks, and lowering the clearance around each (up to 125 cells and a
    /// shell of regions) cost a third of loading. Until then tracing may skip solid voxels.
    pub fn begin_bulk_load(&mut self) {
        self.bulk = true;
    }

    /// Ends [`BrickMap::begin_bulk_load`]: the clearance is rebuilt whole, exactly.
    pub fn end_bulk_load(&mut self) {
        self.bulk = false;
        self.rebuild_clearance();
    }

    /// From now until [`BrickMap::lower_deferred_region_clearance`], regions newly occupied
    /// (by a stand-in or a first brick) do not lower the clearance around them one by one: it
    /// is lowered once around the box of them all. For many regions close together (those a
    /// coarse brick covers, a batch of level-0 regions), where lowering around each visits
    /// (2·cap+1)³ regions.
    pub fn defer_region_clearance(&mut self) {
        self.deferred_regions = Some(None);
    }

    /// Ends [`BrickMap::defer_region_clearance`]: lowers the clearance around the box of the
    /// stand-ins set meanwhile.
    pub fn lower_deferred_region_clearance(&mut self) {
        if let Some(Some((lo, hi))) = self.deferred_regions.take() {
            self.lower_clearance_around_box(lo, hi);
        }
    }

    /// The cell entry of `cell` (any coordinates, outside the grid included): `None` where the
    /// cell's region is empty or the cell lies outside the grid, else `(index into cells,
    /// entry)`.
    fn cell_entry(&self, cell: [i64; 3]) -> Option<(usize, u32)> {
        let dims = self.cell_dims;
        if (0..3).any(|i| cell[i] < 0 || cell[i] >= i64::from(dims[i])) {
            return None;
        }
        let cell = cell.map(|c| c as u32);
        let block = region_block(self.regions[self.region_index(cell.map(|c| c / REGION_CELLS))])?;
        let at = (block * CELLS_PER_BLOCK + Self::cell_in_block(cell)) as usize;
        Some((at, self.cells[at]))
    }

    /// A brick appeared at `cell`: empty cells within [`CELL_CLEARANCE_CAP`] of it may claim
    /// less clearance than they do.
    fn lower_cell_clearance_around(&mut self, cell: [u32; 3]) {
        let cap = i64::from(CELL_CLEARANCE_CAP);
        let c = cell.map(i64::from);
        for z in c[2] - cap..=c[2] + cap {
            for y in c[1] - cap..=c[1] + cap {
                for x in c[0] - cap..=c[0] + cap {
                    let d = (x - c[0]).abs().max((y - c[1]).abs()).max((z - c[2]).abs());
                    let Some((at, entry)) = self.cell_entry([x, y, z]) else {
                        continue;
                    };
                    if d > 0 && cell_is_empty(entry) && i64::from(cell_clearance(entry)) >= d {
                        self.cells[at] = EMPTY_CELL | (d - 1) as u32;
                        if let Some(g) = &mut self.gpu {
                            g.cell_blocks.push(at as u32 / CELLS_PER_BLOCK);
                        }
                    }
                }
            }
        }
    }

    /// Recomputes every empty cell's clearance exactly, one allocated block at a time: the
    /// occupied cells of the block and its 26 neighbours go into an 8×8×8 bit window (the block's
    /// 4³ cells with 2 around them; cells of empty regions and past the grid are empty), which is
    /// dilated by one cell twice with shifts. An empty cell outside the first dilation has
    /// clearance ≥ 1, outside the second 2 (the cap). `rebuild_clearance` as a whole takes
    /// 4.9 ms on the 1024³ demo scene, 28 ms on the 2048³ one (`examples/rebuild_time.rs`).
    fn rebuild_cell_clearance(&mut self) {
        self.rebuild_cell_clearance_in(0..self.regions.len());
    }

    /// [`BrickMap::rebuild_cell_clearance`] of the blocks of some regions (by index).
    fn rebuild_cell_clearance_in(&mut self, regions: impl IntoIterator<Item = usize>) {
        const _: () = assert!(CELL_CLEARANCE_CAP == 2 && REGION_CELLS == 4);
        let rd = self.region_dims.map(i64::from);
        for index in regions {
            let Some(block) = region_block(self.regions[index]) else {
                continue;
            };
            let r = self.region_coords(index).map(i64::from);
            // Window cell (x, y, z) is cell r·4 − 2 + (x, y, z): bit x + 8y of word z.
            let mut window = [0u64; 8];
            for dz in -1..=1i64 {
                for dy in -1..=1i64 {
                    for dx in -1..=1i64 {
                        let n = [r[0] + dx, r[1] + dy, r[2] + dz];
                        if (0..3).any(|i| n[i] < 0 || n[i] >= rd[i]) {
                            continue;
                        }
                        let neighbour = self.regions[self.region_index(n.map(|c| c as u32))];
                        let mut bits = match region_block(neighbour) {
                            Some(b) => self.block_cells[b as usize],
                            // A stand-in's cells all count as occupied.
                            None if !region_is_empty(neighbour) => u64::MAX,
                            None => continue,
                        };
                        while bits != 0 {
                            let l = i64::from(bits.trailing_zeros());
                            bits &= bits - 1;
                            let w = [
                                dx * 4 + (l & 3) + 2,
                                dy * 4 + ((l >> 2) & 3) + 2,
                                dz * 4 + ((l >> 4) & 3) + 2,
                            ];
                            if w.iter().all(|&c| (0..8).contains(&c)) {
                                window[w[2] as usize] |= 1 << (w[0] + 8 * w[1]);
                            }
                        }
                    }
                }
            }
            let near1 = dilate_cells(window);
            let near2 = dilate_cells(near1);
            let mut changed = false;
            for l in 0..CELLS_PER_BLOCK {
                let at = (block * CELLS_PER_BLOCK + l) as usize;
                if !cell_is_empty(self.cells[at]) {
                    continue;
                }
                let w = [(l & 3) + 2, ((l >> 2) & 3) + 2, ((l >> 4) & 3) + 2];
                let bit = |m: &[u64; 8]| (m[w[2] as usize] >> (w[0] + 8 * w[1])) & 1 == 1;
                let clearance = if bit(&near1) {
                    0
                } else if bit(&near2) {
                    1
                } else {
                    2
                };
                if self.cells[at] != EMPTY_CELL | clearance {
                    self.cells[at] = EMPTY_CELL | clearance;
                    changed = true;
                }
            }
            if changed && let Some(g) = &mut self.gpu {
                g.cell_blocks.push(block);
            }
        }
    }

    /// Recomputes every empty region's clearance exactly (edits only lower it). Cheap: three
    /// separable passes of a capped Chebyshev distance transform over the region grid. The client
    /// runs it after a full sync, the server after loading a scene.
    pub fn rebuild_clearance(&mut self) {
        self.rebuild_cell_clearance();
        let dims = self.region_dims.map(|d| d as usize);
        let far = CLEARANCE_CAP + 1;
        // Distance to the nearest occupied region, capped at `far`; out-of-grid counts as empty.
        let mut dist: Vec<u32> = self
            .regions
            .iter()
            .map(|&e| if region_is_empty(e) { far } else { 0 })
            .collect();
        let strides = [1, dims[0], dims[0] * dims[1]];
        for axis in 0..3 {
            let len = dims[axis];
            let mut line = vec![0u32; len];
            for start in 0..dist.len() {
                // Visit each line along `axis` once, from its first element.
                if (start / strides[axis]) % len != 0 {
                    continue;
                }
                for (j, value) in line.iter_mut().enumerate() {
                    *value = dist[start + j * strides[axis]];
                }
                for j in 0..len {
                    // Chebyshev: the distance through neighbour j' is max(|j - j'|, its distance).
                    let lo = j.saturating_sub(far as usize);
                    let hi = (j + far as usize).min(len - 1);
                    let best = (lo..=hi)
                        .map(|jj| (j.abs_diff(jj) as u32).max(line[jj]))
                        .min()
                        .unwrap_or(far);
                    dist[start + j * strides[axis]] = best.min(far);
                }
            }
        }
        self.occupied = None;
        for (i, &entry) in self.regions.iter().enumerate() {
            if !region_is_empty(entry) {
                let r = self.region_coords(i);
                self.occupied = Some(match self.occupied {
                    None => (r, r),
                    Some((lo, hi)) => (
                        std::array::from_fn(|a| lo[a].min(r[a])),
                        std::array::from_fn(|a| hi[a].max(r[a])),
                    ),
                });
            }
        }
        for (i, &d) in dist.iter().enumerate() {
            if region_is_empty(self.regions[i]) {
                let entry = EMPTY_REGION | (d.max(1) - 1).min(CLEARANCE_CAP);
                if self.regions[i] != entry {
                    self.regions[i] = entry;
                    if let Some(g) = &mut self.gpu {
                        g.regions.push(i as u32);
                    }
                }
            }
        }
    }

    /// A free brick slot: a freed one first, else a new one at the end of the arrays.
    fn alloc_slot(&mut self) -> u32 {
        match self.free_slots.pop() {
            Some(s) => s,
            None => {
                self.masks.push(EMPTY_MASK);
                self.colour_base.push(0);
                self.slot_cell.push(EMPTY);
                self.slot_version.push(0);
                self.slot_capacity.push(0);
                self.masks.len() as u32 - 1
            }
        }
    }

    fn alloc_block(&mut self) -> u32 {
        match self.free_blocks.pop() {
            Some(b) => {
                // Its cells still carry clearances from the region it served before.
                let at = (b * CELLS_PER_BLOCK) as usize;
                self.cells[at..at + CELLS_PER_BLOCK as usize].fill(EMPTY_CELL);
                if let Some(g) = &mut self.gpu {
                    g.cell_blocks.push(b);
                }
                b
            }
            None => {
                self.cells
                    .extend(std::iter::repeat_n(EMPTY_CELL, CELLS_PER_BLOCK as usize));
                self.block_cells.push(0);
                self.block_cells.len() as u32 - 1
            }
        }
    }

    fn alloc_chunk(&mut self, cap: u32) -> u32 {
        match self.free_chunks[cap as usize].pop() {
            Some(base) => base,
            None => {
                let base = self.colours.len() as u32;
                self.colours.resize(self.colours.len() + cap as usize, 0);
                base
            }
        }
    }

    fn free_chunk(&mut self, base: u32, cap: u32) {
        if cap > 0 {
            self.free_chunks[cap as usize].push(base);
        }
    }

    fn stamp(&mut self, slot: u32) {
        self.slot_version[slot as usize] = self.sequence;
        if self.track_touched {
            self.touched.push(self.slot_cell[slot as usize]);
        }
    }

    fn mark_slot(&mut self, slot: u32) {
        if let Some(g) = &mut self.gpu {
            g.slots.push(slot);
        }
    }

    fn mark_colours(&mut self, first: u32, count: u32) {
        if count > 0
            && let Some(g) = &mut self.gpu
        {
            g.colours.push((first, count));
        }
    }

    /// Internal consistency check used by tests: every counter and free list agrees with the
    /// arrays. Returns a description of the first problem found.
    pub fn check_invariants(&self) -> Result<(), String> {
        let mut bricks = 0u64;
        let mut voxels = 0u64;
        let mut coded = 0u64;
        for (s, &cell) in self.slot_cell.iter().enumerate() {
            if cell == EMPTY {
                if !self.free_slots.contains(&(s as u32)) {
                    return Err(format!("slot {s} is neither used nor free"));
                }
                continue;
            }
            if cell == COARSE {
                let n = popcount(&self.masks[s]) as usize;
                let mut scratch = [Colour::BLACK; VOXELS];
                if n == 0
                    || crate::palette::decode_words(self.block(s as u32), &mut scratch[..n])
                        .is_err()
                {
                    return Err(format!("coarse slot {s} holds no brick or a bad block"));
                }
                let words = self.block_words(s as u32);
                if words > usize::from(self.slot_capacity[s]) {
                    return Err(format!("coarse slot {s} overflows its colour chunk"));
                }
                coded += words as u64;
                continue;
            }
            let coords = self.cell_coords(cell);
            if self.slot_of_cell(coords) != Some(s as u32) {
                return Err(format!("slot {s} not reachable from its cell {coords:?}"));
            }
            let n = popcount(&self.masks[s]);
            if n == 0 {
                return Err(format!("slot {s} holds an empty brick"));
            }
            let mut scratch = [Colour::BLACK; VOXELS];
            if let Err(e) =
                crate::palette::decode_words(self.block(s as u32), &mut scratch[..n as usize])
            {
                return Err(format!("slot {s}'s colour block: {e}"));
            }
            let words = self.block_words(s as u32);
            if words > usize::from(self.slot_capacity[s]) {
                return Err(format!("slot {s} overflows its colour chunk"));
            }
            coded += words as u64;
            bricks += 1;
            voxels += u64::from(n);
        }
        if coded != self.coded_words {
            return Err(format!(
                "counter {} coded words, blocks {coded}",
                self.coded_words
            ));
        }
        if bricks != self.bricks || voxels != self.solid_voxels {
            return Err(format!(
                "counters {} bricks / {} voxels, arrays {bricks} / {voxels}",
                self.bricks, self.solid_voxels
            ));
        }
        for (b, &bits) in self.block_cells.iter().enumerate() {
            let used = self.cells[b * 64..b * 64 + 64]
                .iter()
                .enumerate()
                .filter(|(_, c)| !cell_is_empty(**c))
                .fold(0u64, |used, (l, _)| used | 1 << l);
            if used != bits {
                return Err(format!(
                    "block {b} marks cells {bits:#x} but {used:#x} are used"
                ));
            }
        }
        // Stand-ins point at coarse bricks and are counted.
        let mut stand_ins = 0u64;
        for (i, &entry) in self.regions.iter().enumerate() {
            if let Some((level, slot)) = region_stand_in(entry) {
                stand_ins += 1;
                if !(MIN_STAND_IN_LEVEL..=MAX_STAND_IN_LEVEL).contains(&level)
                    || self.slot_cell.get(slot as usize) != Some(&COARSE)
                {
                    return Err(format!(
                        "region {i} stands in with level {level}, slot {slot}"
                    ));
                }
            }
        }
        if stand_ins != self.stand_ins {
            return Err(format!(
                "counter {} stand-ins, regions {stand_ins}",
                self.stand_ins
            ));
        }
        // The occupied box holds every allocated region.
        for (i, &entry) in self.regions.iter().enumerate() {
            if region_is_empty(entry) {
                continue;
            }
            let r = self.region_coords(i);
            let inside = self
                .occupied
                .is_some_and(|(lo, hi)| (0..3).all(|a| lo[a] <= r[a] && r[a] <= hi[a]));
            if !inside {
                return Err(format!(
                    "region {r:?} is allocated but outside the occupied box {:?}",
                    self.occupied
                ));
            }
        }
        // Cell clearance never claims an occupied cell.
        let mut region_of_block = vec![None; self.block_cells.len()];
        for (i, &entry) in self.regions.iter().enumerate() {
            if let Some(slot) = region_of_block.get_mut(entry as usize) {
                *slot = Some(i);
            }
        }
        for (at, &entry) in self.cells.iter().enumerate() {
            if !cell_is_empty(entry) || self.block_cells[at / 64] == 0 {
                continue;
            }
            let Some(region) = region_of_block[at / 64] else {
                continue;
            };
            let r = self.region_coords(region);
            let local = at as u32 % 64;
            let l = [local & 3, (local >> 2) & 3, (local >> 4) & 3];
            let c: [i64; 3] = std::array::from_fn(|i| i64::from(r[i] * REGION_CELLS + l[i]));
            if (0..3).any(|i| c[i] >= i64::from(self.cell_dims[i])) {
                continue; // past the grid's edge: no ray visits it
            }
            let k = i64::from(cell_clearance(entry));
            for z in c[2] - k..=c[2] + k {
                for y in c[1] - k..=c[1] + k {
                    for x in c[0] - k..=c[0] + k {
                        let stand_in = (x >= 0 && y >= 0 && z >= 0)
                            && self
                                .stand_in([x, y, z].map(|c| c as u32 / REGION_CELLS))
                                .is_some();
                        if stand_in
                            || self
                                .cell_entry([x, y, z])
                                .is_some_and(|(_, e)| !cell_is_empty(e))
                        {
                            return Err(format!(
                                "cell {c:?} claims clearance {k} past occupied cell {:?}",
                                [x, y, z]
                            ));
                        }
                    }
                }
            }
        }
        // Clearance never claims an occupied region.
        let rd = self.region_dims;
        for (i, &entry) in self.regions.iter().enumerate() {
            if !region_is_empty(entry) {
                continue;
            }
            let c = region_clearance(entry) as i64;
            let (x, y, z) = (
                (i as u32 % rd[0]) as i64,
                (i as u32 / rd[0] % rd[1]) as i64,
                (i as u32 / rd[0] / rd[1]) as i64,
            );
            for zz in (z - c).max(0)..=(z + c).min(rd[2] as i64 - 1) {
                for yy in (y - c).max(0)..=(y + c).min(rd[1] as i64 - 1) {
                    for xx in (x - c).max(0)..=(x + c).min(rd[0] as i64 - 1) {
                        let j = (xx + rd[0] as i64 * (yy + rd[1] as i64 * zz)) as usize;
                        if !region_is_empty(self.regions[j]) {
                            return Err(format!(
                                "region {i} claims clearance {c} past occupied region {j}"
                            ));
                        }
                    }
                }
            }
        }
        // Chunks must not overlap: live ones plus free ones tile at most the pool.
        let mut spans: Vec<(u32, u32)> = Vec::new();
        for (s, &cell) in self.slot_cell.iter().enumerate() {
            if cell != EMPTY {
                spans.push((self.colour_base[s], u32::from(self.slot_capacity[s])));
            }
        }
        for (cap, list) in self.free_chunks.iter().enumerate() {
            spans.extend(list.iter().map(|&b| (b, cap as u32)));
        }
        spans.sort_unstable();
        for pair in spans.windows(2) {
            if pair[0].0 + pair[0].1 > pair[1].0 {
                return Err(format!(
                    "colour chunks overlap: {:?} and {:?}",
                    pair[0], pair[1]
                ));
            }
        }
        Ok(())
    }
}

/// An inclusive box of voxels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VoxelBox {
    pub lo: [u32; 3],
    pub hi: [u32; 3],
}

impl VoxelBox {
    /// The part of this box inside `other`, if any.
    pub fn clip(&self, other: &VoxelBox) -> Option<VoxelBox> {
        let lo = std::array::from_fn(|i| self.lo[i].max(other.lo[i]));
        let hi = std::array::from_fn(|i| self.hi[i].min(other.hi[i]));
        (0..3)
            .all(|i| lo[i] <= hi[i])
            .then_some(VoxelBox { lo, hi })
    }
}

/// The voxels a sphere brush covers (centres within `radius` of `centre`), bounded: `None` for a
/// sphere that covers nothing or has a non-finite part. Not clipped to any scene.
pub fn sphere_bounds(centre: [f32; 3], radius: f32) -> Option<VoxelBox> {
    if !radius.is_finite() || radius <= 0.0 || centre.iter().any(|c| !c.is_finite()) {
        return None;
    }
    let lo = centre.map(|c| (c - radius - 0.5).floor().max(0.0));
    let hi: [f32; 3] = std::array::from_fn(|i| (centre[i] + radius - 0.5).ceil());
    if (0..3).any(|i| lo[i] > hi[i] || hi[i] < 0.0) {
        return None;
    }
    Some(VoxelBox {
        lo: lo.map(|v| v as u32),
        hi: hi.map(|v| v.min(u32::MAX as f32) as u32),
    })
}

/// Calls `each(cell, brush)` for every brick where a sphere brush covers a voxel inside
/// `within` (the scene, or a brick-aligned part of it), with the brush's mask in that brick.
/// Changes nothing: [`BrickMap::sphere`] applies what this describes.
pub fn sphere_brushes(
    centre: [f32; 3],
    radius: f32,
    within: VoxelBox,
    each: impl FnMut([u32; 3], &Mask),
) {
    let Some(bounds) = sphere_bounds(centre, radius).and_then(|b| b.clip(&within)) else {
        return;
    };
    let r2 = radius * radius;
    brick_brushes(bounds, each, |base, mask| {
        for z in 0..8u32 {
            let dz = (base[2] + z) as f32 + 0.5 - centre[2];
            for y in 0..8u32 {
                let dy = (base[1] + y) as f32 + 0.5 - centre[1];
                let rest = r2 - dy * dy - dz * dz;
                if rest < 0.0 {
                    continue;
                }
                let half = rest.sqrt();
                // Voxel x is inside when |x + 0.5 - cx| <= half.
                let x0 = (centre[0] - half - 0.5).ceil() - base[0] as f32;
                let x1 = (centre[0] + half - 0.5).floor() - base[0] as f32;
                let x0 = x0.max(0.0);
                let x1 = x1.min(7.0);
                if x0 > x1 {
                    continue;
                }
                let (x0, x1) = (x0 as u32, x1 as u32);
                let row = ((0xFFu32 >> (7 - (x1 - x0))) << x0) as u64;
                mask[z as usize] |= row << (y * 8);
            }
        }
    });
}

/// [`sphere_brushes`] for the inclusive box `min..=max`.
pub fn box_brushes(
    min: [u32; 3],
    max: [u32; 3],
    within: VoxelBox,
    each: impl FnMut([u32; 3], &Mask),
) {
    let Some(bounds) = (VoxelBox { lo: min, hi: max }).clip(&within) else {
        return;
    };
    brick_brushes(bounds, each, |base, mask| *mask = box_mask(base, min, max));
}

/// Runs a brush shape over every brick overlapping `bounds`: `shape` fills the brush mask of
/// one brick given the brick's first voxel; what it covers outside `bounds` is clipped, and
/// bricks it does not cover are skipped.
fn brick_brushes(
    bounds: VoxelBox,
    mut each: impl FnMut([u32; 3], &Mask),
    mut shape: impl FnMut([u32; 3], &mut Mask),
) {
    let VoxelBox { lo, hi } = bounds;
    let clo = lo.map(|v| v / BRICK_EDGE);
    let chi = hi.map(|v| v / BRICK_EDGE);
    for cz in clo[2]..=chi[2] {
        for cy in clo[1]..=chi[1] {
            for cx in clo[0]..=chi[0] {
                let cell = [cx, cy, cz];
                let base = cell.map(|c| c * BRICK_EDGE);
                let mut brush = EMPTY_MASK;
                shape(base, &mut brush);
                // Shapes may spill past the bounds (and so past the scene edge): clip them.
                let clip = box_mask(base, lo, hi);
                for w in 0..8 {
                    brush[w] &= clip[w];
                }
                if !mask_is_empty(&brush) {
                    each(cell, &brush);
                }
            }
        }
    }
}

/// What a brush does to one brick (`old`: its mask and colours in bit order): the new mask,
/// with the new colours written to `out[..n]`, and the number of voxels whose solidity or
/// colour changed. The one definition of a brush, for the map and for plans made beside it.
pub fn brush_brick(
    old: (&Mask, &[Colour]),
    brush: &Mask,
    mode: BrushMode,
    colour: Colour,
    out: &mut [Colour; 512],
) -> (Mask, usize, u64) {
    let (old_mask, old_colours) = old;
    let new_mask: Mask = std::array::from_fn(|w| match mode {
        BrushMode::Fill => old_mask[w] | brush[w],
        BrushMode::Erase => old_mask[w] & !brush[w],
        BrushMode::Paint => old_mask[w],
    });
    let mut n = 0usize;
    let mut changed = 0u64;
    let mut old_i = 0usize;
    // Walk the union of old and new solid voxels in bit order, carrying the old colour index.
    for w in 0..8 {
        let mut bits = old_mask[w] | new_mask[w];
        while bits != 0 {
            let b = bits.trailing_zeros();
            bits &= bits - 1;
            let was = (old_mask[w] >> b) & 1 == 1;
            let is = (new_mask[w] >> b) & 1 == 1;
            let old_colour = if was {
                old_i += 1;
                old_colours.get(old_i - 1).copied()
            } else {
                None
            };
            if is {
                let covered = (brush[w] >> b) & 1 == 1;
                let c = match old_colour {
                    Some(c) if !covered || mode == BrushMode::Erase => c,
                    _ => colour,
                };
                if old_colour != Some(c) {
                    changed += 1;
                }
                out[n] = c;
                n += 1;
            } else {
                changed += 1;
            }
        }
    }
    (new_mask, n, changed)
}

/// Mask of the voxels of the brick starting at `base` that lie in the inclusive box `lo..=hi`.
fn box_mask(base: [u32; 3], lo: [u32; 3], hi: [u32; 3]) -> Mask {
    let mut mask = EMPTY_MASK;
    if (0..3).any(|i| hi[i] < base[i] || lo[i] > base[i] + 7) {
        return mask;
    }
    let lo_l: [u32; 3] = std::array::from_fn(|i| lo[i].max(base[i]) - base[i]);
    let hi_l: [u32; 3] = std::array::from_fn(|i| hi[i].min(base[i] + 7) - base[i]);
    let row = u64::from((0xFFu32 >> (7 - (hi_l[0] - lo_l[0]))) << lo_l[0]);
    for z in lo_l[2]..=hi_l[2] {
        for y in lo_l[1]..=hi_l[1] {
            mask[z as usize] |= row << (y * 8);
        }
    }
    mask
}

/// splitmix64 finaliser: cheap, well-mixed, stable across platforms.
#[inline]
fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// Hash of one brick, combined by addition in [`BrickMap::content_hash`].
pub fn brick_hash(cell_index: u32, mask: &Mask, colours: &[Colour]) -> u64 {
    let mut h = mix(u64::from(cell_index));
    for &w in mask {
        h = mix(h ^ w);
    }
    for chunk in colours.chunks(4) {
        let mut word = 0u64;
        for (i, c) in chunk.iter().enumerate() {
            word |= u64::from(c.0) << (16 * i);
        }
        h = mix(h ^ word);
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    fn red() -> Colour {
        Colour::from_rgb8(255, 0, 0)
    }

    /// `box_points` lists exactly the nested loops' points in their order, empty and
    /// one-point boxes included.
    #[test]
    fn box_points_are_the_nested_loops() {
        let boxes = [
            ([0, 0, 0], [3, 2, 4]),
            ([2, 1, 1], [3, 2, 2]),
            ([1, 1, 1], [1, 5, 5]),
            ([0, 0, 0], [4, 0, 4]),
            ([0, 0, 5], [4, 4, 2]),
            ([5, 7, 9], [8, 9, 10]),
        ];
        for (lo, hi) in boxes {
            let mut want = Vec::new();
            for z in lo[2]..hi[2] {
                for y in lo[1]..hi[1] {
                    for x in lo[0]..hi[0] {
                        want.push([x, y, z]);
                    }
                }
            }
            assert_eq!(
                box_points(lo, hi).collect::<Vec<_>>(),
                want,
                "{lo:?}..{hi:?}"
            );
        }
    }

    #[test]
    fn capacity_classes_bound_slack() {
        for n in 1..=512 {
            let c = colour_capacity(n);
            assert!(c >= n && c <= 512 && c.is_multiple_of(2), "{n} -> {c}");
            assert!((c - n) as f64 <= (n as f64 / 8.0).max(1.0), "{n} -> {c}");
            assert_eq!(colour_capacity(c), c, "classes are fixed points");
        }
    }

    /// A scene written in bulk ends with the clearance a brick-by-brick write followed by a
    /// rebuild gives, which traces exactly; during the bulk write nothing lowers it.
    #[test]
    fn a_bulk_load_ends_with_the_exact_clearance() {
        let mut bricks = Vec::new();
        let mut x = 7u64;
        for _ in 0..300 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let cell = [
                (x >> 20) as u32 % 40,
                (x >> 30) as u32 % 6,
                (x >> 40) as u32 % 40,
            ];
            let mut mask = EMPTY_MASK;
            mask[(x >> 50) as usize % 8] = x | 1;
            let colours = vec![Colour((x >> 8) as u16); popcount(&mask) as usize];
            bricks.push(BrickData {
                cell,
                mask,
                colours,
            });
        }
        let mut plain = BrickMap::new([320, 48, 320]).unwrap();
        let mut bulk = BrickMap::new([320, 48, 320]).unwrap();
        bulk.begin_bulk_load();
        for b in &bricks {
            plain.put_brick(b).unwrap();
            bulk.put_brick(b).unwrap();
        }
        assert_eq!(
            bulk.regions()
                .iter()
                .filter(|&&e| region_is_empty(e))
                .count(),
            bulk.regions()
                .iter()
                .filter(|&&e| e == EMPTY_REGION | CLEARANCE_CAP)
                .count(),
            "nothing lowered the clearance during the bulk write"
        );
        bulk.end_bulk_load();
        plain.rebuild_clearance();
        assert_eq!(bulk.regions(), plain.regions());
        assert_eq!(bulk.cells(), plain.cells());
        bulk.check_invariants().unwrap();
        // Writes after the bulk load keep it current again.
        bulk.set([300, 40, 300], Colour::WHITE);
        bulk.check_invariants().unwrap();
    }

    #[test]
    fn set_get_clear_paint() {
        let mut map = BrickMap::new([100, 50, 30]).unwrap();
        assert!(map.set([1, 2, 3], red()));
        assert!(!map.set([1, 2, 3], red()), "same colour is no change");
        assert_eq!(map.get([1, 2, 3]), Some(red()));
        assert_eq!(map.get([1, 2, 4]), None);
        assert!(map.paint([1, 2, 3], Colour::WHITE));
        assert!(
            !map.paint([9, 9, 9], Colour::WHITE),
            "painting air does nothing"
        );
        assert_eq!(map.get([1, 2, 3]), Some(Colour::WHITE));
        assert!(!map.set([100, 0, 0], red()), "out of bounds");
        assert!(map.clear([1, 2, 3]));
        assert_eq!(map.brick_count(), 0);
        assert_eq!(
            map.regions.iter().filter(|&&r| !region_is_empty(r)).count(),
            0,
            "block freed"
        );
        map.check_invariants().unwrap();
    }

    #[test]
    fn filling_a_brick_voxel_by_voxel_keeps_colours_in_order() {
        let mut map = BrickMap::new([16, 16, 16]).unwrap();
        // Insert in a scrambled order so every insert shifts colours.
        for i in 0..512u32 {
            let b = (i * 37) % 512;
            let [x, y, z] = crate::brick::bit_voxel(b);
            map.set([x, y, z], Colour(b as u16));
            map.check_invariants().unwrap();
        }
        for b in 0..512u32 {
            let [x, y, z] = crate::brick::bit_voxel(b);
            assert_eq!(map.get([x, y, z]), Some(Colour(b as u16)));
        }
        for i in 0..512u32 {
            let b = (i * 91) % 512;
            let [x, y, z] = crate::brick::bit_voxel(b);
            assert!(map.clear([x, y, z]));
            map.check_invariants().unwrap();
        }
        assert_eq!(map.solid_voxels(), 0);
    }

    #[test]
    fn freed_slots_and_chunks_are_reused() {
        let mut map = BrickMap::new([256, 256, 256]).unwrap();
        for round in 0..20u32 {
            map.sphere(
                [128.0, 128.0, 128.0],
                40.0,
                BrushMode::Fill,
                Colour(round as u16),
            );
            map.sphere([128.0, 128.0, 128.0], 40.0, BrushMode::Erase, Colour::BLACK);
            map.check_invariants().unwrap();
        }
        assert_eq!(map.solid_voxels(), 0);
        let after_churn = map.memory();
        map.sphere([128.0, 128.0, 128.0], 40.0, BrushMode::Fill, Colour::WHITE);
        let m = map.memory();
        assert_eq!(
            m.mask_bytes, after_churn.mask_bytes,
            "slots reused, arrays did not grow"
        );
        assert_eq!(m.colour_bytes, after_churn.colour_bytes, "chunks reused");
    }

    #[test]
    fn sphere_matches_per_voxel_definition() {
        let mut map = BrickMap::new([64, 64, 40]).unwrap();
        let (c, r) = ([20.3, 30.7, 19.5], 11.2f32);
        let changed = map.sphere(c, r, BrushMode::Fill, red());
        let mut expect = 0;
        for z in 0..40u32 {
            for y in 0..64u32 {
                for x in 0..64u32 {
                    let d = [
                        x as f32 + 0.5 - c[0],
                        y as f32 + 0.5 - c[1],
                        z as f32 + 0.5 - c[2],
                    ];
                    let inside = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r * r;
                    // Row-wise sqrt can differ from the squared test by one ulp right at the edge.
                    if inside != map.is_solid([x, y, z]) {
                        let err = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - r * r).abs();
                        assert!(
                            err < 1e-3,
                            "voxel {x},{y},{z} mismatch far from the surface"
                        );
                    }
                    expect += inside as u64;
                }
            }
        }
        assert!((changed as i64 - expect as i64).abs() <= 4);
        assert_eq!(changed, map.solid_voxels());
        map.check_invariants().unwrap();
    }

    #[test]
    fn sphere_clips_at_scene_edge() {
        let mut map = BrickMap::new([20, 20, 20]).unwrap();
        map.sphere([19.0, 19.0, 19.0], 6.0, BrushMode::Fill, red());
        for (b, _) in map.bricks() {
            map.check_brick(&b).unwrap();
        }
        map.check_invariants().unwrap();
    }

    #[test]
    fn box_fill_erase_paint() {
        let mut map = BrickMap::new([40, 40, 40]).unwrap();
        assert_eq!(
            map.fill_box([3, 4, 5], [20, 9, 30], BrushMode::Fill, red()),
            18 * 6 * 26
        );
        assert_eq!(
            map.fill_box([0, 0, 0], [39, 39, 10], BrushMode::Paint, Colour::WHITE),
            18 * 6 * 6
        );
        assert_eq!(map.get([3, 4, 5]), Some(Colour::WHITE));
        assert_eq!(map.get([3, 4, 11]), Some(red()));
        assert_eq!(
            map.fill_box([0, 0, 0], [39, 39, 39], BrushMode::Erase, red()),
            18 * 6 * 26
        );
        assert_eq!(map.brick_count(), 0);
        map.check_invariants().unwrap();
    }

    #[test]
    fn versions_and_tombstones_answer_changes_since() {
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.set_sequence(1);
        map.set([1, 1, 1], red());
        map.set([20, 1, 1], red());
        map.set_sequence(2);
        map.set([40, 1, 1], red());
        map.clear([1, 1, 1]);
        let changes = map.changes_since(1).unwrap();
        assert_eq!(changes.changed, vec![[5, 0, 0]]);
        assert_eq!(changes.removed, vec![[0, 0, 0]]);
        assert_eq!(map.changes_since(0).unwrap().changed.len(), 2);
        map.prune_tombstones(2);
        assert!(map.changes_since(1).is_none(), "too old: full resync");
        map.set_sequence(3);
        map.set([1, 1, 1], red());
        assert_eq!(map.brick_version([0, 0, 0]), Some(3));
    }

    #[test]
    fn content_hash_ignores_layout() {
        let mut a = BrickMap::new([64, 64, 64]).unwrap();
        let mut b = BrickMap::new([64, 64, 64]).unwrap();
        a.set([1, 1, 1], red());
        a.set([50, 1, 1], Colour::WHITE);
        b.set([50, 1, 1], Colour::WHITE);
        b.set([9, 9, 9], red());
        b.clear([9, 9, 9]);
        b.set([1, 1, 1], red());
        assert_eq!(a.content_hash(), b.content_hash());
        b.paint([1, 1, 1], Colour::WHITE);
        assert_ne!(a.content_hash(), b.content_hash());
    }

    #[test]
    fn put_brick_rejects_bad_bricks_and_changes_nothing() {
        let mut map = BrickMap::new([12, 12, 12]).unwrap();
        let mut mask = EMPTY_MASK;
        mask_set(&mut mask, voxel_bit(7, 0, 0), true);
        let outside = BrickData {
            cell: [1, 0, 0],
            mask,
            colours: vec![red()],
        };
        assert_eq!(
            map.put_brick(&outside),
            Err(MapError::VoxelsOutOfBounds([1, 0, 0]))
        );
        let far = BrickData {
            cell: [2, 0, 0],
            mask,
            colours: vec![red()],
        };
        assert!(matches!(
            map.put_brick(&far),
            Err(MapError::CellOutOfBounds { .. })
        ));
        let wrong = BrickData {
            cell: [0, 0, 0],
            mask,
            colours: vec![],
        };
        assert_eq!(
            map.put_brick(&wrong),
            Err(MapError::InconsistentBrick([0, 0, 0]))
        );
        assert_eq!(map.brick_count(), 0);
        let good = BrickData {
            cell: [0, 0, 0],
            mask,
            colours: vec![red()],
        };
        map.put_brick(&good).unwrap();
        assert_eq!(map.get([7, 0, 0]), Some(red()));
        assert_eq!(map.brick([0, 0, 0]), Some(good));
    }

    /// Bricks of one colour, a few, many and noise, each with its exact block.
    fn coded_bricks() -> Vec<(BrickData, Vec<u16>)> {
        let mut seed = 7u32;
        let mut next = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            seed >> 8
        };
        [1u32, 3, 40, 400]
            .into_iter()
            .enumerate()
            .map(|(i, distinct)| {
                let mut mask = EMPTY_MASK;
                for bit in 0..BRICK_VOXELS {
                    mask_set(&mut mask, bit, next() % 3 != 0);
                }
                let n = popcount(&mask) as usize;
                // Neighbouring shades, as a texture has: lossy blocks pay off on the last two.
                let colours: Vec<Colour> = (0..n)
                    .map(|_| {
                        let k = (next() % distinct) as u8;
                        Colour::from_rgb8(100 + k / 4, 80 + k / 8, 60 + k / 16)
                    })
                    .collect();
                let mut bytes = Vec::new();
                crate::palette::encode(&colours, &mut bytes);
                let block = crate::palette::words_of(&bytes);
                let brick = BrickData {
                    cell: [i as u32, 1, 0],
                    mask,
                    colours,
                };
                (brick, block)
            })
            .collect()
    }

    #[test]
    fn put_coded_stores_what_put_brick_would() {
        for bound in [None, Some(crate::blocks::DEFAULT_BOUND)] {
            let mut by_colours = BrickMap::new([64, 64, 64]).unwrap();
            let mut by_block = BrickMap::new([64, 64, 64]).unwrap();
            by_colours.set_colour_bound(bound);
            by_block.set_colour_bound(bound);
            // Twice: inserted into empty cells, then replacing what is there.
            for _ in 0..2 {
                for (brick, exact) in coded_bricks() {
                    by_colours.put_brick(&brick).unwrap();
                    // What a viewer hands over: the lossy block where it pays.
                    let mut block = Vec::new();
                    if let Some(bound) = bound {
                        let coding = crate::palette::coding_of_words(&exact).unwrap();
                        crate::palette::lossy(&brick.colours, coding, bound, &mut block);
                    }
                    if block.is_empty() {
                        block = exact;
                    }
                    by_block
                        .put_coded(brick.cell, brick.mask, &brick.colours, &block)
                        .unwrap();
                    let (a, b) = (
                        by_colours.slot_of_cell(brick.cell).unwrap(),
                        by_block.slot_of_cell(brick.cell).unwrap(),
                    );
                    let words = crate::palette::coding_of_words(by_block.block(b))
                        .unwrap()
                        .words(brick.colours.len());
                    assert_eq!(by_colours.block(a)[..words], by_block.block(b)[..words]);
                    if bound.is_none() {
                        assert_eq!(by_block.brick(brick.cell), Some(brick));
                    }
                }
            }
            assert_eq!(by_colours.memory(), by_block.memory());
            let lossy = by_block
                .codings()
                .filter(|(c, _)| matches!(c, crate::palette::Coding::Blocks { .. }))
                .count();
            assert_eq!(lossy > 0, bound.is_some(), "{lossy} lossy blocks");
            by_block.check_invariants().unwrap();
        }
    }

    #[test]
    fn put_coded_refuses_a_block_that_does_not_fit_and_changes_nothing() {
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        let (brick, block) = coded_bricks().swap_remove(2);
        let n = brick.colours.len();
        let refused = |map: &mut BrickMap, mask: Mask, colours: &[Colour], block: &[u16]| {
            map.put_coded(brick.cell, mask, colours, block)
        };
        let inconsistent = Err(MapError::InconsistentBrick(brick.cell));
        // Cut short, a colour short, a lossy header, a header naming nothing, an empty mask.
        assert_eq!(
            refused(
                &mut map,
                brick.mask,
                &brick.colours,
                &block[..block.len() - 1]
            ),
            inconsistent
        );
        assert_eq!(
            refused(&mut map, brick.mask, &brick.colours[..n - 1], &block),
            inconsistent
        );
        let mut lossy = block.clone();
        lossy[0] = crate::blocks::header(2);
        assert_eq!(
            refused(&mut map, brick.mask, &brick.colours, &lossy),
            inconsistent
        );
        assert_eq!(
            refused(&mut map, brick.mask, &brick.colours, &[0x7, 1, 2]),
            inconsistent
        );
        assert_eq!(refused(&mut map, EMPTY_MASK, &[], &[0, 5]), inconsistent);
        let far = map.put_coded([8, 0, 0], brick.mask, &brick.colours, &block);
        assert!(
            matches!(far, Err(MapError::CellOutOfBounds { .. })),
            "{far:?}"
        );
        assert_eq!(map.brick_count(), 0);
        map.check_invariants().unwrap();
    }

    #[test]
    fn gpu_changes_are_recorded() {
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.record_gpu_changes(true);
        map.set([1, 1, 1], red());
        let g = map.take_gpu_changes();
        assert!(g.regions.contains(&0));
        assert!(g.slots.contains(&0) && g.cell_blocks.contains(&0));
        // The brick's colour block: a header and its one colour.
        assert_eq!(g.colours, vec![(0, 2)]);
        assert!(map.take_gpu_changes().is_empty());
    }

    #[test]
    fn clearance_is_exact_after_rebuild_and_safe_after_edits() {
        let mut map = BrickMap::new([640, 64, 320]).unwrap(); // 20 × 2 × 10 regions
        let exact = |map: &BrickMap, occupied: &[[i64; 3]]| {
            let rd = map.region_dims();
            for (i, &e) in map.regions().iter().enumerate() {
                if !region_is_empty(e) {
                    continue;
                }
                let p = [
                    (i as u32 % rd[0]) as i64,
                    (i as u32 / rd[0] % rd[1]) as i64,
                    (i as u32 / rd[0] / rd[1]) as i64,
                ];
                assert_eq!(
                    i64::from(region_clearance(e)),
                    exact_clearance(p, occupied, CLEARANCE_CAP),
                    "region {p:?}"
                );
            }
        };
        map.set([5 * 32 + 3, 40, 4 * 32], red());
        exact(&map, &[[5, 1, 4]]);
        map.set([15 * 32, 0, 9 * 32 + 31], red());
        exact(&map, &[[5, 1, 4], [15, 0, 9]]);
        map.clear([5 * 32 + 3, 40, 4 * 32]);
        map.check_invariants().unwrap();
        map.rebuild_clearance();
        exact(&map, &[[15, 0, 9]]);
        map.check_invariants().unwrap();
    }

    /// The clearance brute force gives `p`: Chebyshev distance to the nearest occupied block,
    /// less one, capped.
    fn exact_clearance(p: [i64; 3], occupied: &[[i64; 3]], cap: u32) -> i64 {
        let d = occupied
            .iter()
            .map(|o| (0..3).map(|k| (p[k] - o[k]).abs()).max().unwrap_or(0))
            .min()
            .unwrap_or(i64::MAX);
        (d - 1).min(i64::from(cap))
    }

    /// Rebuilt cell clearances are the largest true ones: min(cap, distance to the nearest
    /// occupied cell − 1), checked by brute force over a scene with bricks across region borders.
    /// Bricks written in bulk hold what they would written one by one, and every empty cell
    /// of an occupied region gets its exact clearance (a scene that already had bricks, and
    /// writes that remove some).
    #[test]
    fn bricks_written_in_bulk_have_exact_clearance() {
        let mut one = BrickMap::new([200, 72, 136]).unwrap();
        one.fill_box([0, 0, 0], [199, 7, 135], BrushMode::Fill, red());
        let mut bulk = one.clone();
        let mut rng = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = |n: u32| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % u64::from(n)) as u32
        };
        let mut writes = Vec::new();
        for i in 0..300 {
            let cell = [next(25), next(9), next(17)];
            let brick = (i % 7 != 0).then(|| {
                let mut mask = EMPTY_MASK;
                mask[next(8) as usize] = u64::from(next(u32::MAX)) | 1;
                let colours = vec![red(); popcount(&mask) as usize];
                (mask, colours)
            });
            writes.push((cell, brick));
        }
        for (cell, brick) in writes.clone() {
            match brick {
                Some((mask, colours)) => one
                    .put_brick(&BrickData {
                        cell,
                        mask,
                        colours,
                    })
                    .unwrap(),
                None => {
                    one.remove_brick(cell);
                }
            }
        }
        bulk.write_bricks(writes).unwrap();
        bulk.check_invariants().unwrap();
        assert_eq!(bulk.content_hash(), one.content_hash());
        let occupied: Vec<[i64; 3]> = bulk.brick_cells().map(|(c, _)| c.map(i64::from)).collect();
        let cd = bulk.cell_dims();
        let mut checked = 0;
        for z in 0..cd[2] {
            for y in 0..cd[1] {
                for x in 0..cd[0] {
                    let p = [x, y, z].map(i64::from);
                    let Some((_, entry)) = bulk.cell_entry(p) else {
                        continue;
                    };
                    if !cell_is_empty(entry) {
                        continue;
                    }
                    // Exact near what was written; never above exact anywhere (safe).
                    let exact = exact_clearance(p, &occupied, CELL_CLEARANCE_CAP);
                    assert!(i64::from(cell_clearance(entry)) <= exact, "cell {p:?}");
                    if y < 9 {
                        assert_eq!(i64::from(cell_clearance(entry)), exact, "cell {p:?}");
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 1000, "only {checked} empty cells checked");
    }

    #[test]
    fn cell_clearance_is_exact_after_rebuild() {
        let mut map = BrickMap::new([200, 72, 136]).unwrap();
        let mut rng = 0x2545_F491_4F6C_DD1Du64;
        let mut next = |n: u32| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % u64::from(n)) as u32
        };
        for _ in 0..120 {
            map.set([next(200), next(72), next(136)], red());
        }
        map.rebuild_clearance();
        map.check_invariants().unwrap();
        let occupied: Vec<[i64; 3]> = map.brick_cells().map(|(c, _)| c.map(i64::from)).collect();
        let cd = map.cell_dims();
        let mut checked = 0;
        for z in 0..cd[2] {
            for y in 0..cd[1] {
                for x in 0..cd[0] {
                    let Some((_, entry)) = map.cell_entry([x, y, z].map(i64::from)) else {
                        continue;
                    };
                    if !cell_is_empty(entry) {
                        continue;
                    }
                    let p = [x, y, z].map(i64::from);
                    assert_eq!(
                        i64::from(cell_clearance(entry)),
                        exact_clearance(p, &occupied, CELL_CLEARANCE_CAP),
                        "cell {p:?}"
                    );
                    checked += 1;
                }
            }
        }
        assert!(
            checked > 1000,
            "only {checked} empty cells in occupied regions"
        );
    }

    #[test]
    fn bad_sizes_are_errors() {
        assert!(BrickMap::new([0, 1, 1]).is_err());
        assert!(BrickMap::new([MAX_SCENE_EDGE + 1, 1, 1]).is_err());
        let big = BrickMap::new([4096, 4096, 4096]).unwrap();
        assert_eq!(big.memory().region_bytes, 128 * 128 * 128 * 4);
        // BrickMap's world is allowed; a cube of the same edge would need 512 MiB of regions.
        let world = BrickMap::new([MAX_SCENE_EDGE, 512, MAX_SCENE_EDGE]).unwrap();
        assert_eq!(world.memory().region_bytes, 512 * 16 * 512 * 4);
        let cube = [MAX_SCENE_EDGE; 3];
        let err = BrickMap::check_size(cube).unwrap_err();
        assert_eq!(
            err,
            MapError::TooManyRegions {
                size: cube,
                regions: 512 * 512 * 512
            }
        );
        assert!(err.to_string().contains("16384×512×16384"), "{err}");
        assert!(BrickMap::check_size([8192; 3]).is_ok());
    }
}
