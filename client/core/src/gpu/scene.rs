//! The GPU copy of a brick map.
//!
//! Five storage arrays, each the byte-for-byte image of one `BrickMap` array (the protocol crate
//! is the one home of the layout; nothing is re-encoded here):
//!
//! | array          | words per entry | source                   |
//! |----------------|-----------------|--------------------------|
//! | `regions`      | 1 per region    | `BrickMap::regions`      |
//! | `colour_bases` | 1 per slot      | `BrickMap::colour_bases` |
//! | `cells`        | 64 per block    | `BrickMap::cells`        |
//! | `masks`        | 16 per slot     | `BrickMap::masks`        |
//! | `colours`      | ½ per pool word | `BrickMap::colour_pool`  |
//!
//! Updates are incremental: the map's GPU change log names the entries that changed and only
//! those are written (coalesced into runs). A pool that runs out of room is reallocated with
//! headroom, and only the pages that changed size are re-filled. How much headroom depends on
//! why the pool grew: a full upload of a synced scene gets 1/8 (room for edits; a 2048³ scene
//! is 69 MB and should not cost 100), a pool outgrown by streaming bricks gets half again (so a
//! scene arriving in batches reallocates O(log n) times).
//!
//! The three pools that grow with the scene (cells, masks, colours) may be larger than one
//! storage binding (128 MiB on lavapipe and many GPUs), so each is split into up to
//! [`PAGES`] buffers of `2^page_shift` words; the shader picks the page from the index.

use std::ops::Range;

use brickcast_protocol::BrickMap;
use brickcast_protocol::map::GpuChanges;

use super::{GpuContext, GpuError};

/// Bindings per paged pool; the shader declares this many. Two regions arrays plus three pools
/// of two pages are the eight storage buffers WebGPU guarantees a stage.
pub const PAGES: usize = 2;

/// Smallest buffer ever created: bindings may not be empty.
const MIN_WORDS: u64 = 64;
/// Headroom of a pool sized by a full upload: 1/8 of the scene's own size.
const FULL_UPLOAD_HEADROOM: u64 = 8;
/// Headroom of a pool outgrown by an update: half again.
const GROWTH_HEADROOM: u64 = 2;

#[cfg(not(target_endian = "little"))]
compile_error!("the GPU upload reinterprets mask words in place and assumes a little-endian host");

/// Which of the map's arrays.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Array {
    Regions,
    ColourBases,
    Cells,
    Masks,
    Colours,
}

impl Array {
    const ALL: [Array; 5] = [
        Array::Regions,
        Array::ColourBases,
        Array::Cells,
        Array::Masks,
        Array::Colours,
    ];

    fn name(self) -> &'static str {
        match self {
            Array::Regions => "regions",
            Array::ColourBases => "colour bases",
            Array::Cells => "cells",
            Array::Masks => "masks",
            Array::Colours => "colours",
        }
    }

    fn max_pages(self) -> usize {
        match self {
            Array::Regions | Array::ColourBases => 1,
            Array::Cells | Array::Masks | Array::Colours => PAGES,
        }
    }

    fn len_words(self, map: &BrickMap) -> u64 {
        match self {
            Array::Regions => map.regions().len() as u64,
            Array::ColourBases => map.colour_bases().len() as u64,
            Array::Cells => map.cells().len() as u64,
            Array::Masks => map.masks().len() as u64 * 16,
            Array::Colours => (map.colour_pool().len() as u64).div_ceil(2),
        }
    }

    /// Words `range` of this array, as the GPU stores them.
    fn words(self, map: &BrickMap, range: Range<u64>) -> std::borrow::Cow<'_, [u32]> {
        let r = range.start as usize..range.end as usize;
        match self {
            Array::Regions => map.regions()[r].into(),
            Array::ColourBases => map.colour_bases()[r].into(),
            Array::Cells => map.cells()[r].into(),
            Array::Masks => bytemuck::cast_slice::<[u64; 8], u32>(map.masks())[r].into(),
            Array::Colours => {
                // Two 16-bit words of colour blocks per word, the even one in the low half.
                let pool = map.colour_pool();
                r.map(|w| {
                    let lo = pool.get(2 * w).copied().unwrap_or(0);
                    let hi = pool.get(2 * w + 1).copied().unwrap_or(0);
                    u32::from(lo) | (u32::from(hi) << 16)
                })
                .collect::<Vec<u32>>()
                .into()
            }
        }
    }
}

/// One array on the GPU: up to `max_pages` buffers of `page_words` words each (the last one
/// possibly shorter).
struct PagedArray {
    array: Array,
    page_words: u64,
    capacity_words: u64,
    pages: Vec<wgpu::Buffer>,
}

impl PagedArray {
    fn new(array: Array, page_words: u64) -> PagedArray {
        PagedArray {
            array,
            page_words,
            capacity_words: 0,
            pages: Vec::new(),
        }
    }

    fn max_words(&self) -> u64 {
        self.page_words * self.array.max_pages() as u64
    }

    /// Makes room for `needed` words, plus `needed / headroom_divisor` when it must reallocate,
    /// within `cap` words (unless it needs more). With `shrink`, an array over `cap` (it
    /// shrank, or a budget leaves it less room) is reallocated smaller. Returns the word range
    /// whose contents must be written again (buffers replaced, less what a grown page took
    /// over from the one it replaced), or `None` when everything already fitted.
    fn reserve(
        &mut self,
        ctx: &GpuContext,
        needed: u64,
        headroom_divisor: u64,
        cap: u64,
        shrink: bool,
    ) -> Result<Option<Range<u64>>, GpuError> {
        let over = shrink && self.capacity_words > cap.max(needed).max(MIN_WORDS);
        if needed <= self.capacity_words && !self.pages.is_empty() && !over {
            return Ok(None);
        }
        if over {
            // Smaller: every page goes (their contents are written again).
            self.pages.clear();
            self.capacity_words = 0;
        }
        if needed > self.max_words() {
            return Err(GpuError::TooBig {
                adapter: ctx.adapter_name.clone(),
                what: self.array.name(),
                bytes: needed * 4,
                max: self.max_words() * 4,
            });
        }
        let want = (needed + needed / headroom_divisor)
            .min(cap.max(needed))
            .max(MIN_WORDS)
            .min(self.max_words());
        // Only the last page can be short; full pages stay as they are, contents and all.
        let last_is_full = self
            .pages
            .last()
            .is_some_and(|p| p.size() / 4 >= self.page_words);
        let first_changed_page = if last_is_full {
            self.pages.len()
        } else {
            self.pages.len().saturating_sub(1)
        };
        // The short last page is replaced by a larger one; what it held is copied over on the
        // GPU, so only the words past it need writing (growing a pool used to write it whole
        // again from the CPU: in a browser every byte crosses to the GPU process).
        let kept = self.pages.drain(first_changed_page..).next();
        let mut start = first_changed_page as u64 * self.page_words;
        let first_new = self.pages.len();
        while start < want {
            let words = (want - start).min(self.page_words).max(MIN_WORDS);
            self.pages
                .push(ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(self.array.name()),
                    size: words * 4,
                    usage: wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_DST
                        | wgpu::BufferUsages::COPY_SRC,
                    mapped_at_creation: false,
                }));
            start += words;
        }
        self.capacity_words = start;
        let mut fresh_from = first_changed_page as u64 * self.page_words;
        if let (Some(old), Some(new)) = (kept, self.pages.get(first_new)) {
            let bytes = old.size().min(new.size());
            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("grow a pool"),
                });
            encoder.copy_buffer_to_buffer(&old, 0, new, 0, bytes);
            // Submitted now: writes queued after this land on top of the copy.
            ctx.queue.submit([encoder.finish()]);
            fresh_from += bytes / 4;
        }
        Ok(Some(fresh_from..self.capacity_words))
    }

    /// Writes `words` at word offset `first`, split at page boundaries.
    fn write(&self, queue: &wgpu::Queue, first: u64, words: &[u32]) -> u64 {
        let mut at = first;
        let mut rest = words;
        while !rest.is_empty() {
            let page = (at / self.page_words) as usize;
            let offset = at % self.page_words;
            let n = ((self.page_words - offset) as usize).min(rest.len());
            queue.write_buffer(
                &self.pages[page],
                offset * 4,
                bytemuck::cast_slice(&rest[..n]),
            );
            at += n as u64;
            rest = &rest[n..];
        }
        words.len() as u64 * 4
    }

    fn bytes(&self) -> u64 {
        self.pages.iter().map(|b| b.size()).sum()
    }
}

/// What an update did, for tests and the viewer's status line.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UploadStats {
    pub bytes: u64,
    pub writes: u64,
    /// Pools that had to be reallocated.
    pub reallocations: u32,
}

/// The GPU copy of one scene.
pub struct GpuScene {
    size: [u32; 3],
    region_dims: [u32; 3],
    /// The map's occupied region box at the last upload or update: the tracer's bounds.
    occupied: Option<([u32; 3], [u32; 3])>,
    cell_dims: [u32; 3],
    page_shift: u32,
    arrays: [PagedArray; 5],
    /// Bumped whenever a buffer is replaced, so bind groups know to follow.
    generation: u64,
    dummy: wgpu::Buffer,
    /// Totals since creation.
    pub uploaded: UploadStats,
    /// GPU bytes the scene's buffers may take (`--gpu-budget`): headroom is cut to fit it,
    /// and buffers larger than their share are reallocated smaller. `None`: no limit.
    budget: Option<u64>,
}

impl GpuScene {
    /// Uploads all of `map` and starts recording its changes. `page_bytes` overrides the page
    /// size (tests use small pages to exercise paging on small scenes); by default a page is the
    /// largest power of two that fits one binding.
    pub fn new(
        ctx: &GpuContext,
        map: &mut BrickMap,
        page_bytes: Option<u64>,
    ) -> Result<GpuScene, GpuError> {
        GpuScene::within(ctx, map, page_bytes, None)
    }

    /// [`GpuScene::new`] with buffers kept within `budget` bytes ([`GpuScene::set_budget`]).
    pub fn within(
        ctx: &GpuContext,
        map: &mut BrickMap,
        page_bytes: Option<u64>,
        budget: Option<u64>,
    ) -> Result<GpuScene, GpuError> {
        let limit = ctx.max_binding_bytes();
        let page_bytes = page_bytes.unwrap_or(limit).min(limit).max(MIN_WORDS * 4);
        // Largest power of two of words not above the limit.
        let page_shift = 63 - (page_bytes / 4).leading_zeros();
        let page_words = 1u64 << page_shift;
        let arrays = Array::ALL.map(|a| {
            let page = if a.max_pages() == 1 {
                // Single-binding arrays may use the whole binding, not just a power of two.
                limit / 4
            } else {
                page_words
            };
            PagedArray::new(a, page)
        });
        let dummy = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("unused page"),
            size: MIN_WORDS * 4,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let mut scene = GpuScene {
            size: map.size(),
            region_dims: map.region_dims(),
            occupied: map.occupied_regions(),
            cell_dims: map.cell_dims(),
            page_shift,
            arrays,
            generation: 0,
            dummy,
            uploaded: UploadStats::default(),
            budget,
        };
        map.record_gpu_changes(true);
        scene.upload_all(ctx, map)?;
        Ok(scene)
    }

    /// Writes every array in full (first upload, or after the map was replaced).
    pub fn upload_all(
        &mut self,
        ctx: &GpuContext,
        map: &mut BrickMap,
    ) -> Result<UploadStats, GpuError> {
        if map.size() != self.size {
            return Err(GpuError::SceneMismatch {
                expected: self.size,
                got: map.size(),
            });
        }
        map.take_gpu_changes();
        self.occupied = map.occupied_regions();
        let mut stats = UploadStats::default();
        let (caps, shrink) = (self.caps(map), self.over_budget(map));
        for (array, cap) in self.arrays.iter_mut().zip(caps) {
            let len = array.array.len_words(map);
            if array
                .reserve(ctx, len, FULL_UPLOAD_HEADROOM, cap, shrink)?
                .is_some()
            {
                stats.reallocations += 1;
            }
            if len > 0 {
                stats.bytes += array.write(&ctx.queue, 0, &array.array.words(map, 0..len));
                stats.writes += 1;
            }
        }
        if stats.reallocations > 0 {
            self.generation += 1;
        }
        self.add(stats);
        Ok(stats)
    }

    /// Writes what changed in `map` since the last update.
    pub fn update(
        &mut self,
        ctx: &GpuContext,
        map: &mut BrickMap,
    ) -> Result<UploadStats, GpuError> {
        let changes = map.take_gpu_changes();
        self.occupied = map.occupied_regions();
        let mut stats = UploadStats::default();
        if changes.is_empty() {
            return Ok(stats);
        }
        let (caps, shrink) = (self.caps(map), self.over_budget(map));
        for (array, cap) in self.arrays.iter_mut().zip(caps) {
            let len = array.array.len_words(map);
            let fresh = array.reserve(ctx, len, GROWTH_HEADROOM, cap, shrink)?;
            if let Some(range) = &fresh {
                stats.reallocations += 1;
                let end = range.end.min(len);
                if range.start < end {
                    stats.bytes += array.write(
                        &ctx.queue,
                        range.start,
                        &array.array.words(map, range.start..end),
                    );
                    stats.writes += 1;
                }
            }
            for run in changed_runs(array.array, &changes, RUN_GAP_WORDS) {
                let run = run.start..run.end.min(len);
                // Already written in full if it lies in a reallocated range.
                let run = match &fresh {
                    Some(f) if run.start >= f.start => continue,
                    Some(f) => run.start..run.end.min(f.start),
                    None => run,
                };
                if run.start < run.end {
                    stats.bytes += array.write(&ctx.queue, run.start, &array.array.words(map, run));
                    stats.writes += 1;
                }
            }
        }
        if stats.reallocations > 0 {
            self.generation += 1;
        }
        self.add(stats);
        Ok(stats)
    }

    /// Keeps the buffers within `budget` bytes from the next update on (`None`: no limit).
    /// A map larger than the budget still gets buffers that hold it, without headroom.
    pub fn set_budget(&mut self, budget: Option<u64>) {
        self.budget = budget;
    }

    /// The most words each array may take: without a budget, any; with one, what the array
    /// needs and an equal share of what the budget leaves over (at most half again its size).
    fn caps(&self, map: &BrickMap) -> [u64; 5] {
        let lens = self.arrays.each_ref().map(|a| a.array.len_words(map));
        let Some(budget) = self.budget else {
            return [u64::MAX; 5];
        };
        let spare = (budget / 4).saturating_sub(lens.iter().sum()) / lens.len() as u64;
        lens.map(|len| len + spare.min(len / GROWTH_HEADROOM))
    }

    /// Whether the buffers would take more than the budget once each holds its array: then
    /// those over their share shrink.
    fn over_budget(&self, map: &BrickMap) -> bool {
        self.budget.is_some_and(|b| {
            let words: u64 = self
                .arrays
                .iter()
                .map(|a| a.capacity_words.max(a.array.len_words(map)))
                .sum();
            words * 4 > b
        })
    }

    fn add(&mut self, s: UploadStats) {
        self.uploaded.bytes += s.bytes;
        self.uploaded.writes += s.writes;
        self.uploaded.reallocations += s.reallocations;
    }

    /// Bytes of GPU memory the scene occupies (every buffer, headroom included).
    pub fn gpu_bytes(&self) -> u64 {
        self.arrays.iter().map(PagedArray::bytes).sum()
    }

    pub fn size(&self) -> [u32; 3] {
        self.size
    }
    pub fn region_dims(&self) -> [u32; 3] {
        self.region_dims
    }
    /// Inclusive bounds of the occupied regions as last uploaded (`None`: nothing to trace).
    pub fn occupied_regions(&self) -> Option<([u32; 3], [u32; 3])> {
        self.occupied
    }
    pub fn cell_dims(&self) -> [u32; 3] {
        self.cell_dims
    }
    pub fn page_shift(&self) -> u32 {
        self.page_shift
    }
    /// Buffers (bindings) each array occupies now, by array name: paging made visible.
    pub fn page_counts(&self) -> Vec<(&'static str, usize)> {
        self.arrays
            .iter()
            .map(|a| (a.array.name(), a.pages.len()))
            .collect()
    }

    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// The buffers in the shader's binding order (1..=8).
    pub fn bindings(&self) -> Vec<&wgpu::Buffer> {
        let mut out = Vec::with_capacity(2 + 3 * PAGES);
        for array in &self.arrays {
            for page in 0..array.array.max_pages() {
                out.push(array.pages.get(page).unwrap_or(&self.dummy));
            }
        }
        out
    }
}

/// Runs of changed words at most this far apart are written as one, the words between them
/// too (they hold what the map holds, so writing them again is harmless). A write is a call
/// with a cost of its own, large in a browser (a call into JavaScript, a message to the GPU
/// process): a working set's first sync made about 560,000 of them, most a region word or a
/// brick's mask, where 4 KiB more per write costs little.
const RUN_GAP_WORDS: u64 = 1024;

/// Word ranges of `array` named by the change log, sorted and coalesced; ranges at most `gap`
/// words apart join.
fn changed_runs(array: Array, changes: &GpuChanges, gap: u64) -> Vec<Range<u64>> {
    let mut ranges: Vec<Range<u64>> = match array {
        Array::Regions => changes
            .regions
            .iter()
            .map(|&r| u64::from(r)..u64::from(r) + 1)
            .collect(),
        Array::ColourBases => changes
            .slots
            .iter()
            .map(|&s| u64::from(s)..u64::from(s) + 1)
            .collect(),
        Array::Cells => changes
            .cell_blocks
            .iter()
            .map(|&b| u64::from(b) * 64..u64::from(b) * 64 + 64)
            .collect(),
        Array::Masks => changes
            .slots
            .iter()
            .map(|&s| u64::from(s) * 16..u64::from(s) * 16 + 16)
            .collect(),
        Array::Colours => changes
            .colours
            .iter()
            .map(|&(first, count)| {
                let (first, count) = (u64::from(first), u64::from(count));
                first / 2..(first + count).div_ceil(2)
            })
            .collect(),
    };
    ranges.sort_unstable_by_key(|r| r.start);
    let mut runs: Vec<Range<u64>> = Vec::with_capacity(ranges.len());
    for r in ranges {
        match runs.last_mut() {
            Some(last) if r.start <= last.end + gap => last.end = last.end.max(r.end),
            _ => runs.push(r),
        }
    }
    runs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_coalesce_and_cover_odd_colour_ranges() {
        let changes = GpuChanges {
            regions: vec![5, 3, 4, 9],
            cell_blocks: vec![2, 0],
            slots: vec![1, 2],
            colours: vec![(3, 2), (10, 1)],
        };
        assert_eq!(changed_runs(Array::Regions, &changes, 0), vec![3..6, 9..10]);
        assert_eq!(
            changed_runs(Array::Cells, &changes, 0),
            vec![0..64, 128..192]
        );
        assert_eq!(changed_runs(Array::Masks, &changes, 0), vec![16..48]);
        assert_eq!(changed_runs(Array::ColourBases, &changes, 0), vec![1..3]);
        // Colours 3..5 live in words 1 and 2; colour 10 in word 5.
        assert_eq!(changed_runs(Array::Colours, &changes, 0), vec![1..3, 5..6]);
    }

    #[test]
    fn runs_close_together_are_written_as_one() {
        let changes = GpuChanges {
            regions: vec![5, 3, 4, 9, 40, 41, 100],
            ..GpuChanges::default()
        };
        // A gap of 3 words (6..9) joins, one of 30 (10..40) does not at a gap of 3.
        assert_eq!(
            changed_runs(Array::Regions, &changes, 3),
            vec![3..10, 40..42, 100..101]
        );
        assert_eq!(changed_runs(Array::Regions, &changes, 58), vec![3..101]);
        // Every changed word stays inside a run, whatever the gap.
        for gap in [0, 1, 7, RUN_GAP_WORDS] {
            let runs = changed_runs(Array::Regions, &changes, gap);
            for &r in &changes.regions {
                assert!(
                    runs.iter().any(|run| run.contains(&u64::from(r))),
                    "{r} at gap {gap}"
                );
            }
        }
    }
}
