//! Reading the files a model names (MTL libraries, textures) within limits.
//!
//! Why: a model file is input from whoever made it. An OBJ may name `mtllib /dev/zero` (read
//! forever) or `../../home/you/.ssh/id_rsa.png`; an MTL may name any texture on disk, which the
//! import would bake into a scene served to everyone. So the files a model names are opened only
//! inside the model's own folder (unless the operator allows more), only if they are regular
//! files, and only up to a size; images are decoded with dimension and allocation limits.

use std::io::Read;
use std::path::{Path, PathBuf};

/// Largest MTL library read.
pub const MAX_MTL_BYTES: u64 = 16 << 20;
/// Largest texture file read.
pub const MAX_TEXTURE_BYTES: u64 = 256 << 20;
/// Largest texture edge, in pixels.
pub const MAX_TEXTURE_EDGE: u32 = 16_384;
/// Most memory one decoded texture may take.
pub const MAX_TEXTURE_ALLOC: u64 = 1 << 30;

/// Where a model may reach for the files it names.
#[derive(Debug, Clone)]
pub struct Reach {
    /// The model's folder, canonical.
    base: PathBuf,
    /// Whether files outside `base` may be read (`import --allow-outside-files`).
    outside: bool,
}

impl Reach {
    /// The reach of a model in folder `base`.
    pub fn new(base: &Path, outside: bool) -> Reach {
        Reach {
            base: base.canonicalize().unwrap_or_else(|_| base.to_path_buf()),
            outside,
        }
    }

    /// Reads `path` whole if it is a regular file inside the reach and at most `max` bytes.
    pub fn read(&self, path: &Path, max: u64) -> Result<Vec<u8>, String> {
        let real = path
            .canonicalize()
            .map_err(|e| format!("cannot open it: {e}"))?;
        if !self.outside && !real.starts_with(&self.base) {
            return Err(format!(
                "it is outside the model's folder {} (import --allow-outside-files reads it)",
                self.base.display()
            ));
        }
        let file = std::fs::File::open(&real).map_err(|e| format!("cannot open it: {e}"))?;
        let meta = file
            .metadata()
            .map_err(|e| format!("cannot read it: {e}"))?;
        if !meta.is_file() {
            return Err("it is not a regular file".into());
        }
        if meta.len() > max {
            return Err(format!(
                "it is {} bytes, over the limit of {max}",
                meta.len()
            ));
        }
        let mut bytes = Vec::with_capacity(meta.len() as usize);
        // The file may grow while being read: never take more than the limit.
        file.take(max + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| format!("cannot read it: {e}"))?;
        if bytes.len() as u64 > max {
            return Err(format!("it grew past the limit of {max} bytes while read"));
        }
        Ok(bytes)
    }
}

/// Decodes an image from memory with dimension and allocation limits.
pub fn decode_image(bytes: &[u8]) -> Result<image::RgbaImage, String> {
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| e.to_string())?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_TEXTURE_EDGE);
    limits.max_image_height = Some(MAX_TEXTURE_EDGE);
    limits.max_alloc = Some(MAX_TEXTURE_ALLOC);
    reader.limits(limits);
    Ok(reader.decode().map_err(|e| e.to_string())?.into_rgba8())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reach_stays_in_the_model_folder() {
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("model");
        std::fs::create_dir(&model).unwrap();
        std::fs::write(model.join("a.mtl"), "newmtl a\n").unwrap();
        std::fs::write(dir.path().join("secret.txt"), "secret").unwrap();
        let reach = Reach::new(&model, false);
        assert_eq!(
            reach.read(&model.join("a.mtl"), 100).unwrap(),
            b"newmtl a\n"
        );
        let outside = reach.read(&model.join("../secret.txt"), 100).unwrap_err();
        assert!(outside.contains("outside the model's folder"), "{outside}");
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(dir.path().join("secret.txt"), model.join("link.mtl"))
                .unwrap();
            assert!(
                reach.read(&model.join("link.mtl"), 100).is_err(),
                "links out are refused"
            );
            let zero = Reach::new(&model, true).read(Path::new("/dev/zero"), 100);
            assert!(zero.unwrap_err().contains("not a regular file"));
        }
        assert!(
            reach
                .read(&model.join("a.mtl"), 3)
                .unwrap_err()
                .contains("over the limit")
        );
        let allowed = Reach::new(&model, true);
        assert_eq!(
            allowed.read(&model.join("../secret.txt"), 100).unwrap(),
            b"secret"
        );
    }
}
