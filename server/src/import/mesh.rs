//! A triangle mesh with materials and textures, read from OBJ + MTL (through `tobj` and `image`).
//!
//! The voxelizer needs little from a mesh: corner positions, texture coordinates where the mesh
//! has them, and per triangle a material that turns a UV into a colour. Everything else in OBJ
//! (normals, groups, smoothing) is dropped here. What is missing but not essential — an MTL file,
//! a texture, a material name — becomes a warning and a plain colour, so a mesh copied without
//! all its files still imports.

use std::cell::RefCell;
use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::ImportError;
use super::files::{MAX_MTL_BYTES, MAX_TEXTURE_BYTES, Reach, decode_image};

/// Most corners one OBJ face may have: real models use 3 or 4, and a face with a million
/// corners (a million triangles of one fan) is an attack, not a model.
pub const MAX_FACE_VERTICES: usize = 1024;

/// Diffuse colour of surfaces whose material is unknown (no MTL, or a name it does not define).
pub const DEFAULT_DIFFUSE: [f32; 3] = [0.8, 0.8, 0.8];

/// An RGBA8 image, rows top to bottom.
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<[u8; 4]>,
}

impl Texture {
    /// Bilinear sample at `uv`, wrapping (OBJ UVs repeat outside 0..1; `v` points up, rows down).
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 3] {
        let (w, h) = (self.width as i64, self.height as i64);
        let u = uv[0] - uv[0].floor();
        let v = uv[1] - uv[1].floor();
        let x = u * w as f32 - 0.5;
        let y = (1.0 - v) * h as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let texel = |xi: i64, yi: i64| {
            let t = self.texels[(yi.rem_euclid(h) * w + xi.rem_euclid(w)) as usize];
            [t[0] as f32, t[1] as f32, t[2] as f32]
        };
        let (x0, y0) = (x0 as i64, y0 as i64);
        let (a, b) = (texel(x0, y0), texel(x0 + 1, y0));
        let (c, d) = (texel(x0, y0 + 1), texel(x0 + 1, y0 + 1));
        std::array::from_fn(|i| {
            let top = a[i] + (b[i] - a[i]) * fx;
            let bottom = c[i] + (d[i] - c[i]) * fx;
            (top + (bottom - top) * fy) / 255.0
        })
    }
}

/// How a surface gets its colour: the diffuse colour, times the diffuse texture where there is
/// one (the MTL convention: `map_Kd` is multiplied by `Kd`).
pub struct Material {
    pub name: String,
    pub diffuse: [f32; 3],
    pub texture: Option<Arc<Texture>>,
}

impl Material {
    /// Colour in 0..1 at texture coordinate `uv` (`None`: the triangle has no UVs).
    pub fn colour(&self, uv: Option<[f32; 2]>) -> [f32; 3] {
        match (&self.texture, uv) {
            (Some(texture), Some(uv)) => {
                let t = texture.sample(uv);
                std::array::from_fn(|i| t[i] * self.diffuse[i])
            }
            _ => self.diffuse,
        }
    }
}

/// One triangle: three corners (indices into [`Mesh::positions`] and, where `textured`,
/// [`Mesh::uvs`]) and its material (an index into [`Mesh::materials`]).
#[derive(Debug, Clone, Copy)]
pub struct MeshTriangle {
    pub corners: [u32; 3],
    pub material: u32,
    pub textured: bool,
}

/// Triangles, their corners and materials. Material 0 is always the default grey used for
/// surfaces with no known material.
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    /// Texture coordinates, indexed like `positions` (zeros for corners without one).
    pub uvs: Vec<[f32; 2]>,
    pub triangles: Vec<MeshTriangle>,
    pub materials: Vec<Material>,
    pub warnings: Vec<String>,
}

impl Mesh {
    /// An empty mesh holding only the default material; meshes built in code start here.
    pub fn new() -> Mesh {
        Mesh {
            positions: Vec::new(),
            uvs: Vec::new(),
            triangles: Vec::new(),
            materials: vec![Material {
                name: "(default)".into(),
                diffuse: DEFAULT_DIFFUSE,
                texture: None,
            }],
            warnings: Vec::new(),
        }
    }

    /// Adds a material and returns its index.
    pub fn add_material(&mut self, material: Material) -> u32 {
        self.materials.push(material);
        (self.materials.len() - 1) as u32
    }

    /// Adds a triangle with its own corners; `uvs` makes it textured.
    pub fn add_triangle(
        &mut self,
        corners: [[f32; 3]; 3],
        uvs: Option<[[f32; 2]; 3]>,
        material: u32,
    ) {
        let first = self.positions.len() as u32;
        self.positions.extend_from_slice(&corners);
        self.uvs.extend_from_slice(&uvs.unwrap_or_default());
        self.triangles.push(MeshTriangle {
            corners: [first, first + 1, first + 2],
            material,
            textured: uvs.is_some(),
        });
    }
}

impl Default for Mesh {
    fn default() -> Self {
        Mesh::new()
    }
}

/// Decodes an image file into a texture, if `reach` allows reading it (see [`Reach`]).
pub fn load_texture(reach: &Reach, path: &Path) -> Result<Texture, String> {
    let bytes = reach.read(path, MAX_TEXTURE_BYTES)?;
    let image = decode_image(&bytes)?;
    let (width, height) = image.dimensions();
    if width == 0 || height == 0 {
        return Err("the image is empty".into());
    }
    let texels = image.pixels().map(|p| p.0).collect();
    Ok(Texture {
        width,
        height,
        texels,
    })
}

/// Where a texture named in an MTL file lives: relative to the MTL's folder, Windows separators
/// allowed, and map options (`-bm 0.5 file.png`) skipped by trying the last word.
fn texture_path(base: &Path, name: &str) -> PathBuf {
    let name = name.trim().replace('\\', "/");
    let whole = base.join(&name);
    if whole.exists() {
        return whole;
    }
    match name.rsplit(char::is_whitespace).next() {
        Some(last) if last != name => base.join(last),
        _ => whole,
    }
}

/// Refuses an OBJ with a face of more than [`MAX_FACE_VERTICES`] corners, before it is parsed.
fn check_faces(path: &Path) -> Result<(), ImportError> {
    let file = std::fs::File::open(path).map_err(|source| ImportError::Read {
        path: path.into(),
        source,
    })?;
    let mut reader = BufReader::new(file);
    let mut line = Vec::new();
    let mut number = 0u64;
    loop {
        line.clear();
        let read = reader
            .read_until(b'\n', &mut line)
            .map_err(|source| ImportError::Read {
                path: path.into(),
                source,
            })?;
        if read == 0 {
            return Ok(());
        }
        number += 1;
        if let Some(rest) = line.strip_prefix(b"f")
            && rest.first().is_some_and(u8::is_ascii_whitespace)
        {
            let corners = rest
                .split(u8::is_ascii_whitespace)
                .filter(|t| !t.is_empty())
                .count();
            if corners > MAX_FACE_VERTICES {
                return Err(ImportError::BadObj {
                    path: path.into(),
                    detail: format!(
                        "the face on line {number} has {corners} corners; at most {MAX_FACE_VERTICES} are read"
                    ),
                });
            }
        }
    }
}

/// Reads an OBJ file, its MTL files and their diffuse textures. The files it names are read
/// only from the OBJ's folder unless `allow_outside` (see [`Reach`]).
pub fn load_obj(path: &Path, allow_outside: bool) -> Result<Mesh, ImportError> {
    check_faces(path)?;
    let file = std::fs::File::open(path).map_err(|source| ImportError::Read {
        path: path.into(),
        source,
    })?;
    let base = path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let reach = Reach::new(&base, allow_outside);
    let missing_mtl = RefCell::new(Vec::new());
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, materials) =
        tobj::load_obj_buf(&mut BufReader::new(file), &options, |mtl: &Path| {
            let mtl_path = base.join(mtl);
            match reach.read(&mtl_path, MAX_MTL_BYTES) {
                Ok(bytes) => tobj::load_mtl_buf(&mut std::io::Cursor::new(bytes)),
                Err(e) => {
                    missing_mtl
                        .borrow_mut()
                        .push(format!("material library {}: {e}", mtl_path.display()));
                    Err(tobj::LoadError::OpenFileFailed)
                }
            }
        })
        .map_err(|e| ImportError::BadObj {
            path: path.into(),
            detail: e.to_string(),
        })?;

    let mut mesh = Mesh::new();
    mesh.warnings.extend(
        missing_mtl
            .into_inner()
            .into_iter()
            .map(|w| format!("{w}; surfaces use the default colour")),
    );
    let materials = match materials {
        Ok(m) => m,
        Err(e) => {
            if mesh.warnings.is_empty() {
                mesh.warnings.push(format!(
                    "materials could not be read ({e}); surfaces use the default colour"
                ));
            }
            Vec::new()
        }
    };
    let mut textures: HashMap<PathBuf, Option<Arc<Texture>>> = HashMap::new();
    // Maps the voxelizer does not use are still checked: a missing file usually means the
    // model was copied incompletely, which the user wants to know once per file.
    let mut reported = std::collections::HashSet::new();
    for m in &materials {
        let unused = [
            ("ambient", &m.ambient_texture),
            ("specular", &m.specular_texture),
            ("bump", &m.normal_texture),
            ("shininess", &m.shininess_texture),
            ("dissolve", &m.dissolve_texture),
        ];
        for (kind, name) in unused {
            let Some(name) = name else { continue };
            let map_path = texture_path(&base, name);
            if !map_path.exists() && reported.insert(map_path.clone()) {
                mesh.warnings.push(format!(
                    "{kind} map {} of material {} is missing (the voxelizer does not use it)",
                    map_path.display(),
                    m.name
                ));
            }
        }
    }
    for m in &materials {
        let texture = m.diffuse_texture.as_deref().and_then(|name| {
            let tex_path = texture_path(&base, name);
            textures
                .entry(tex_path.clone())
                .or_insert_with(|| match load_texture(&reach, &tex_path) {
                    Ok(t) => Some(Arc::new(t)),
                    Err(e) => {
                        mesh.warnings.push(format!(
                            "texture {} of material {}: {e}; using its diffuse colour",
                            tex_path.display(),
                            m.name
                        ));
                        None
                    }
                })
                .clone()
        });
        mesh.materials.push(Material {
            name: m.name.clone(),
            diffuse: m.diffuse.unwrap_or(DEFAULT_DIFFUSE),
            texture,
        });
    }

    for model in &models {
        let m = &model.mesh;
        let first = mesh.positions.len() as u32;
        let count = m.positions.len() / 3;
        let textured = m.texcoords.len() == count * 2 && count > 0;
        mesh.positions
            .extend(m.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]));
        if textured {
            mesh.uvs
                .extend(m.texcoords.chunks_exact(2).map(|t| [t[0], t[1]]));
        } else {
            mesh.uvs.extend(std::iter::repeat_n([0.0, 0.0], count));
        }
        // Material 0 is the default; the MTL's materials follow it.
        let material = m
            .material_id
            .filter(|&id| id < materials.len())
            .map_or(0, |id| id as u32 + 1);
        for tri in m.indices.chunks_exact(3) {
            if tri.iter().any(|&i| i as usize >= count) {
                return Err(ImportError::BadObj {
                    path: path.into(),
                    detail: format!(
                        "object {:?} has a face with a vertex index out of range",
                        model.name
                    ),
                });
            }
            mesh.triangles.push(MeshTriangle {
                corners: [first + tri[0], first + tri[1], first + tri[2]],
                material,
                textured,
            });
        }
    }
    if let Some(p) = mesh
        .positions
        .iter()
        .find(|p| p.iter().any(|c| !c.is_finite()))
    {
        return Err(ImportError::BadObj {
            path: path.into(),
            detail: format!("a vertex position is not a finite number: {p:?}"),
        });
    }
    Ok(mesh)
}
