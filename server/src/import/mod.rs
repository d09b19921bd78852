//! Scene import and export: meshes (OBJ + MTL + textures) voxelized through an octree, and
//! MagicaVoxel `.vox` in and out.
//!
//! * [`mesh`]: reads an OBJ with its materials and textures into a [`Mesh`]; a missing MTL or
//!   texture is a warning, a malformed OBJ an error.
//! * [`voxelize`]: the paper's section 3.4 — an octree over the mesh down to 32³-voxel leaves,
//!   every voxel a triangle overlaps becomes solid, coloured from the closest triangle's texture.
//! * [`vox`]: `.vox` models placed by their scene graph, and export split into ≤ 256³ models
//!   with a palette quantised to 255 colours ([`palette`]).
//!
//! Everything here produces or reads a [`BrickMap`]; storing it is the caller's business (the
//! CLI writes it to the store, or hands it to a running server through [`crate::incoming`]).

pub mod files;
pub mod mesh;
pub mod palette;
pub mod vox;
pub mod voxelize;

use std::path::{Path, PathBuf};
use std::time::Instant;

use brickcast_protocol::BrickMap;
use brickcast_protocol::map::MapError;

pub use mesh::Mesh;

/// Why an import or export failed. Warnings (a missing texture, say) are not errors: they are
/// collected in [`ImportReport::warnings`] and the import carries on.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} is not a valid OBJ file: {detail}")]
    BadObj { path: PathBuf, detail: String },
    #[error("{path} is not a valid MagicaVoxel file: {detail}")]
    BadVox { path: PathBuf, detail: String },
    #[error("{path}: unknown model format (expected .obj or .vox)")]
    UnknownFormat { path: PathBuf },
    #[error(
        "resolution {0} is invalid: use a power of two from 8 to {MAX_RESOLUTION} (voxels along the longest axis)"
    )]
    BadResolution(u32),
    #[error("the mesh has no triangles with area to voxelize")]
    EmptyMesh,
    #[error("{0}: the model holds no voxels")]
    EmptyModel(PathBuf),
    #[error("the model does not fit a scene: {0}")]
    Map(#[from] MapError),
}

/// Largest mesh resolution: the voxelizer's precision is argued for an 8192³ grid (see
/// `voxelize`), and a 16384³ cube would exceed the scene's region limit anyway.
pub const MAX_RESOLUTION: u32 = 8192;

/// What the import should do; `resolution` applies to meshes only (a `.vox` is already voxels).
#[derive(Debug, Clone, Copy)]
pub struct ImportOptions {
    /// Voxels along the mesh's longest axis: a power of two, the depth of the octree.
    pub resolution: u32,
    /// Worker threads for voxelizing; 0 means one per core.
    pub threads: usize,
    /// Whether the files a model names (MTL libraries, textures) may be read from outside
    /// the model's own folder.
    pub allow_outside_files: bool,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            resolution: 2048,
            threads: 0,
            allow_outside_files: false,
        }
    }
}

impl ImportOptions {
    pub fn check(&self) -> Result<(), ImportError> {
        let r = self.resolution;
        if !(8..=MAX_RESOLUTION).contains(&r) || !r.is_power_of_two() {
            return Err(ImportError::BadResolution(r));
        }
        Ok(())
    }

    pub fn worker_threads(&self) -> usize {
        if self.threads > 0 {
            self.threads
        } else {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        }
    }
}

/// The stages an import goes through, for progress display.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    Parsing,
    Voxelizing,
    Storing,
}

impl Phase {
    pub fn label(self) -> &'static str {
        match self {
            Phase::Parsing => "parsing",
            Phase::Voxelizing => "voxelizing",
            Phase::Storing => "storing",
        }
    }
}

/// Progress sink: the CLI draws bars, tests and libraries pass [`NoProgress`]. `advance` is
/// called from worker threads.
pub trait Progress: Sync {
    /// A phase starts; `total` units of work are expected (0 when unknown).
    fn start(&self, phase: Phase, total: u64);
    fn advance(&self, units: u64);
    /// The current phase is over.
    fn finish(&self);
}

/// Progress that goes nowhere.
pub struct NoProgress;

impl Progress for NoProgress {
    fn start(&self, _: Phase, _: u64) {}
    fn advance(&self, _: u64) {}
    fn finish(&self) {}
}

/// What an import did, for the summary line and `--json`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ImportReport {
    pub source: String,
    pub size: [u32; 3],
    /// Triangles in the mesh (0 for `.vox`).
    pub triangles: u64,
    /// Triangles skipped because they have no area (all corners on one line).
    pub degenerate_triangles: u64,
    pub voxels: u64,
    pub bricks: u64,
    pub parse_seconds: f64,
    pub voxelize_seconds: f64,
    /// Things that were wrong but did not stop the import (missing MTL or texture, …).
    pub warnings: Vec<String>,
}

/// A scene read from a model file, with what happened on the way.
pub struct Imported {
    pub map: BrickMap,
    pub report: ImportReport,
}

/// Model formats by extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Obj,
    Vox,
}

impl Format {
    pub fn of(path: &Path) -> Result<Format, ImportError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("obj") => Ok(Format::Obj),
            Some("vox") => Ok(Format::Vox),
            _ => Err(ImportError::UnknownFormat { path: path.into() }),
        }
    }
}

/// Reads a model file (format chosen by extension) into a brick map.
pub fn import_file(
    path: &Path,
    options: &ImportOptions,
    progress: &dyn Progress,
) -> Result<Imported, ImportError> {
    let format = Format::of(path)?;
    let started = Instant::now();
    progress.start(Phase::Parsing, 0);
    match format {
        Format::Obj => {
            options.check()?;
            let mesh = mesh::load_obj(path, options.allow_outside_files)?;
            progress.finish();
            let parse_seconds = started.elapsed().as_secs_f64();
            let started = Instant::now();
            let (map, stats) = voxelize::voxelize(&mesh, options, progress)?;
            Ok(Imported {
                report: ImportReport {
                    source: path.display().to_string(),
                    size: map.size(),
                    triangles: mesh.triangles.len() as u64,
                    degenerate_triangles: stats.degenerate,
                    voxels: map.solid_voxels(),
                    bricks: map.brick_count(),
                    parse_seconds,
                    voxelize_seconds: started.elapsed().as_secs_f64(),
                    warnings: mesh.warnings,
                },
                map,
            })
        }
        Format::Vox => {
            let bytes = std::fs::read(path).map_err(|source| ImportError::Read {
                path: path.into(),
                source,
            })?;
            let map = vox::import_vox(&bytes, path)?;
            progress.finish();
            Ok(Imported {
                report: ImportReport {
                    source: path.display().to_string(),
                    size: map.size(),
                    voxels: map.solid_voxels(),
                    bricks: map.brick_count(),
                    parse_seconds: started.elapsed().as_secs_f64(),
                    ..ImportReport::default()
                },
                map,
            })
        }
    }
}
