//! Handing a new scene to a running server.
//!
//! redb lets one process at a time open the store, so while a server runs, `brickcast-server
//! import` cannot write into it. Instead the importer drops the scene into the store folder's
//! `incoming/` spool (written under a temporary name, then renamed, so the server never sees half
//! a file), and the server, which polls the spool, stores the scene, starts its owner and serves
//! it at once. A scene the server cannot take (its name is taken, the file is damaged) is left
//! beside a `NAME.error` file that says why, so nothing is lost and the importer can report it.
//!
//! A spool file is `MAGIC`, a format version, then bincode of [`Spooled`]: the scene's name,
//! size and bricks as zstd [`BrickBlob`]s (the wire format's, so the scene costs about 100 bytes
//! a brick), followed since version 2 by the scene's palette ([`Swatches`]); version-1 files
//! read with the default palette.

use std::path::{Path, PathBuf};

use brickcast_protocol::BrickMap;
use brickcast_protocol::brick::BrickData;
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::BrickBlob;
use serde::{Deserialize, Serialize};

use crate::envelope::Format;

/// A scene file's body after its header (name, size, bricks), at most 1 GiB.
const BODY: Format<{ 1 << 30 }> = Format::new("scene file", b"");
const MAGIC: &[u8; 16] = b"brickcast-scene\n";
const VERSION: u32 = 2;
/// Files written before the palette (no [`Swatches`] after the body).
const VERSION_1: u32 = 1;
/// Bricks per blob: keeps each blob's decompressed size modest.
const BLOB_BRICKS: usize = 4096;
/// Extension of a complete spool file.
pub const EXTENSION: &str = "scene";

#[derive(Debug, thiserror::Error)]
pub enum SpoolError {
    #[error("spool I/O on {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("spool file {path} is damaged: {detail}")]
    Damaged { path: PathBuf, detail: String },
}

#[derive(Serialize, Deserialize)]
struct Spooled {
    name: String,
    size: [u32; 3],
    blobs: Vec<BrickBlob>,
}

/// The spool folder of a store folder.
pub fn spool_dir(data: &Path) -> PathBuf {
    data.join("incoming")
}

/// Where the server leaves its reason for refusing `file`.
pub fn error_path(file: &Path) -> PathBuf {
    file.with_extension("error")
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SpoolError + '_ {
    move |source| SpoolError::Io {
        path: path.into(),
        source,
    }
}

/// Writes `map` as scene `name` into the spool of store folder `data`; returns the file's path.
pub fn write(data: &Path, name: &str, map: &BrickMap) -> Result<PathBuf, SpoolError> {
    let dir = spool_dir(data);
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let bytes = encode(name, map).map_err(|detail| SpoolError::Damaged {
        path: dir.clone(),
        detail,
    })?;
    let file = dir.join(format!("{name}.{EXTENSION}"));
    let temporary = dir.join(format!(".{name}.{}.partial", std::process::id()));
    std::fs::write(&temporary, &bytes).map_err(io(&temporary))?;
    let _ = std::fs::remove_file(error_path(&file));
    std::fs::rename(&temporary, &file).map_err(io(&file))?;
    Ok(file)
}

/// A scene file's bytes: what the spool holds and what an admin backup is
/// (`crate::admin`).
pub fn encode(name: &str, map: &BrickMap) -> Result<Vec<u8>, String> {
    let bricks: Vec<BrickData> = map.bricks().map(|(b, _)| b).collect();
    let blobs = bricks
        .chunks(BLOB_BRICKS)
        .map(|chunk| BrickBlob::encode(chunk, 3))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| e.to_string())?;
    drop(bricks);
    let spooled = Spooled {
        name: name.into(),
        size: map.size(),
        blobs,
    };
    let mut bytes = MAGIC.to_vec();
    bytes.extend_from_slice(&VERSION.to_le_bytes());
    BODY.append(&(&spooled, map.swatches()), &mut bytes)
        .map_err(|e| e.to_string())?;
    Ok(bytes)
}

/// Whether `bytes` begin like a scene file.
pub fn is_scene_file(bytes: &[u8]) -> bool {
    bytes.starts_with(MAGIC)
}

/// Largest scene file read (a 2048³ scene like Sibenik spools to about 35 MB).
pub const MAX_SPOOL_BYTES: u64 = 8 << 30;

/// Opens a spool entry the way nothing planted in the folder can misuse: never following a
/// link, never blocking (a FIFO), and only a regular file.
fn open_regular(file: &Path) -> Result<std::fs::File, SpoolError> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK);
    }
    let opened = options.open(file).map_err(io(file))?;
    let meta = opened.metadata().map_err(io(file))?;
    if !meta.is_file() {
        return Err(SpoolError::Damaged {
            path: file.into(),
            detail: "not a regular file".into(),
        });
    }
    Ok(opened)
}

/// Reads a spool file back into a scene name and map.
pub fn read(file: &Path) -> Result<(String, BrickMap), SpoolError> {
    use std::io::Read;
    let mut bytes = Vec::new();
    open_regular(file)?
        .take(MAX_SPOOL_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io(file))?;
    decode(&bytes).map_err(|detail| SpoolError::Damaged {
        path: file.into(),
        detail,
    })
}

/// A scene file's name and map (see [`encode`]); the error says what is wrong with it.
pub fn decode(bytes: &[u8]) -> Result<(String, BrickMap), String> {
    if bytes.len() as u64 > MAX_SPOOL_BYTES {
        return Err(format!("over {MAX_SPOOL_BYTES} bytes"));
    }
    if bytes.len() < MAGIC.len() + 4 || &bytes[..MAGIC.len()] != MAGIC {
        return Err("not a brickcast scene file".into());
    }
    let version = u32::from_le_bytes(
        bytes[MAGIC.len()..MAGIC.len() + 4]
            .try_into()
            .map_err(|_| "truncated header".to_string())?,
    );
    let body = &bytes[MAGIC.len() + 4..];
    let (spooled, swatches): (Spooled, Swatches) = match version {
        VERSION => BODY.decode_body(body).map_err(|e| e.to_string())?,
        VERSION_1 => (
            BODY.decode_body(body).map_err(|e| e.to_string())?,
            Swatches::default(),
        ),
        _ => {
            return Err(format!(
                "format version {version}, this server reads {VERSION_1} to {VERSION}"
            ));
        }
    };
    let mut map = BrickMap::new(spooled.size).map_err(|e| e.to_string())?;
    map.set_swatches(swatches);
    for blob in &spooled.blobs {
        for brick in blob.decode(BLOB_BRICKS as u32).map_err(|e| e.to_string())? {
            map.put_brick(&brick).map_err(|e| e.to_string())?;
        }
    }
    map.rebuild_clearance();
    Ok((spooled.name, map))
}

/// Writes the server's reason for refusing `file` beside it. Through a new temporary file and
/// a rename, so a planted `NAME.error` link is replaced, never written through.
pub fn write_error(file: &Path, text: &str) -> Result<(), SpoolError> {
    let target = error_path(file);
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let temporary = target.with_file_name(format!(".{name}.{}.partial", std::process::id()));
    let _ = std::fs::remove_file(&temporary);
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    let mut out = options.open(&temporary).map_err(io(&temporary))?;
    std::io::Write::write_all(&mut out, text.as_bytes()).map_err(io(&temporary))?;
    drop(out);
    std::fs::rename(&temporary, &target).map_err(io(&target))
}

/// Complete spool files waiting in `data`'s spool, oldest name first, skipping those the server
/// already refused (they have an `.error` beside them). Entries that are not regular files (a
/// link, a FIFO, a folder named `*.scene`) are listed too: reading refuses them, with a reason.
pub fn pending(data: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(spool_dir(data)) else {
        return Vec::new();
    };
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == EXTENSION))
        // Only a regular file marks a refusal: a planted link in its place is replaced.
        .filter(|p| !std::fs::symlink_metadata(error_path(p)).is_ok_and(|m| m.is_file()))
        .collect();
    files.sort();
    files
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::{BrushMode, Colour};

    #[test]
    fn spool_round_trip_and_damage() {
        let dir = tempfile::tempdir().unwrap();
        let mut map = BrickMap::new([100, 40, 70]).unwrap();
        map.sphere(
            [50.0, 20.0, 35.0],
            15.0,
            BrushMode::Fill,
            Colour::from_rgb8(9, 99, 199),
        );
        map.set_swatch(12, Colour(0x0f0f));
        let file = write(dir.path(), "ball", &map).unwrap();
        assert_eq!(pending(dir.path()), vec![file.clone()]);
        let (name, back) = read(&file).unwrap();
        assert_eq!(name, "ball");
        assert_eq!(back.size(), map.size());
        assert_eq!(back.content_hash(), map.content_hash());
        assert_eq!(
            back.swatches(),
            map.swatches(),
            "the palette travels with the scene"
        );

        // A file from before the palette (version 1: no palette after the body) still reads.
        let old = Spooled {
            name: "old".into(),
            size: map.size(),
            blobs: vec![
                BrickBlob::encode(&map.bricks().map(|(b, _)| b).collect::<Vec<_>>(), 3).unwrap(),
            ],
        };
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&VERSION_1.to_le_bytes());
        BODY.append(&old, &mut bytes).unwrap();
        let (_, back) = decode(&bytes).unwrap();
        assert_eq!(back.swatches(), &Swatches::default());
        bytes[MAGIC.len()] = 9;
        assert!(decode(&bytes).is_err_and(|e| e.contains("format version 9")));

        std::fs::write(error_path(&file), "refused").unwrap();
        assert!(pending(dir.path()).is_empty());

        let mut bytes = std::fs::read(&file).unwrap();
        let n = bytes.len();
        bytes.truncate(n / 2);
        std::fs::write(&file, &bytes).unwrap();
        assert!(matches!(read(&file), Err(SpoolError::Damaged { .. })));
        std::fs::write(&file, b"hello").unwrap();
        assert!(matches!(read(&file), Err(SpoolError::Damaged { .. })));
    }
}
