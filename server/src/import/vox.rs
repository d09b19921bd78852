//! MagicaVoxel `.vox` in and out (through `dot_vox`).
//!
//! MagicaVoxel is z-up and right-handed; brickcast is y-up and right-handed. A `.vox` voxel
//! `(x, y, z)` becomes ours at `(x, z, Y − 1 − y)` (Y: the file's extent along its y), which
//! keeps handedness, so a model is not mirrored. Import places every model where the file's
//! scene graph puts it (translations and rotations of transform nodes, summed down the graph);
//! the scene is the box spanned by all placed models. Export splits the scene into models of at
//! most 256³ (the format's limit) on a regular grid, each placed by a transform node, and
//! quantises colours to the format's 255-entry palette ([`super::palette`]). A scene with at
//! most 255 colours round-trips exactly. An imported scene's shared palette
//! ([`brickcast_protocol::swatches`]) is the model's most used colours, in the file's order.

use std::path::Path;

use brickcast_protocol::brick::{BRICK_EDGE, bit_voxel, for_each_bit};
use brickcast_protocol::map::MAX_SCENE_EDGE;
use brickcast_protocol::swatches::{SWATCHES, Swatches};
use brickcast_protocol::{BrickMap, Colour};
use dot_vox::{DotVoxData, Frame, Model, Rotation, SceneNode, ShapeModel, Size, Voxel};

use super::ImportError;
use super::palette::{QuantizeReport, quantize};

/// The format's largest model edge.
pub const MODEL_EDGE: u32 = 256;

/// A model placed in the file's world: voxel `p` lands at `floor(R·(p + ½ − size/2) + t)`.
struct Instance {
    model: usize,
    rotation: [[i32; 3]; 3],
    translation: [i32; 3],
}

impl Instance {
    fn place(&self, size: Size, p: [u32; 3]) -> [i32; 3] {
        // In doubled units so the half-voxel centre stays integral.
        let s = [size.x, size.y, size.z];
        let centred: [i32; 3] = std::array::from_fn(|i| 2 * p[i] as i32 + 1 - s[i] as i32);
        std::array::from_fn(|row| {
            let r: i32 = (0..3)
                .map(|col| self.rotation[row][col] * centred[col])
                .sum();
            (r + 2 * self.translation[row]).div_euclid(2)
        })
    }
}

const IDENTITY: [[i32; 3]; 3] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];

fn matmul(a: [[i32; 3]; 3], b: [[i32; 3]; 3]) -> [[i32; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..3).map(|k| a[r][k] * b[k][c]).sum()))
}

fn rotation_matrix(r: Rotation) -> [[i32; 3]; 3] {
    // dot_vox gives columns; we apply rows.
    let cols = r.to_cols_array_2d();
    std::array::from_fn(|row| std::array::from_fn(|col| cols[col][row].round() as i32))
}

/// Scene-graph nodes visited at most: a file whose graph refers back to itself would otherwise
/// expand without end.
const MAX_GRAPH_VISITS: usize = 1 << 20;
/// Model instances the scene graph may place: a 22 KB file whose groups fan out (700 × 700)
/// placed a model half a million times. Real scenes place hundreds.
pub const MAX_INSTANCES: usize = 1 << 16;
/// Voxels written into the scene, over every placed instance (about half a minute of work).
pub const MAX_VOXELS: u64 = 1 << 27;

/// Every model instance the scene graph places (or each model at the origin without a graph).
fn instances(data: &DotVoxData) -> Result<Vec<Instance>, String> {
    if data.scenes.is_empty() {
        return Ok((0..data.models.len())
            .map(|model| Instance {
                model,
                rotation: IDENTITY,
                translation: [0; 3],
            })
            .collect());
    }
    let mut out = Vec::new();
    let mut stack = vec![(0u32, IDENTITY, [0i32; 3])];
    let mut visits = 0;
    while let Some((node, rotation, translation)) = stack.pop() {
        visits += 1;
        if visits > MAX_GRAPH_VISITS {
            return Err(format!(
                "its scene graph expands to over {MAX_GRAPH_VISITS} nodes (does it refer back to itself?)"
            ));
        }
        match data.scenes.get(node as usize) {
            Some(SceneNode::Transform { frames, child, .. }) => {
                let frame = frames.first();
                let local_r = frame
                    .and_then(Frame::orientation)
                    .map_or(IDENTITY, rotation_matrix);
                let local_t = frame
                    .and_then(Frame::position)
                    .map_or([0; 3], |p| [p.x, p.y, p.z]);
                let rotated: [i32; 3] = std::array::from_fn(|row| {
                    (0..3).map(|col| rotation[row][col] * local_t[col]).sum()
                });
                let t = std::array::from_fn(|i| translation[i] + rotated[i]);
                stack.push((*child, matmul(rotation, local_r), t));
            }
            Some(SceneNode::Group { children, .. }) => {
                for &c in children {
                    stack.push((c, rotation, translation));
                }
            }
            Some(SceneNode::Shape { models, .. }) => {
                for m in models {
                    if (m.model_id as usize) < data.models.len() {
                        if out.len() == MAX_INSTANCES {
                            return Err(format!(
                                "its scene graph places over {MAX_INSTANCES} model instances"
                            ));
                        }
                        out.push(Instance {
                            model: m.model_id as usize,
                            rotation,
                            translation,
                        });
                    }
                }
            }
            None => {}
        }
    }
    Ok(out)
}

/// Checks the file's chunk structure: the parser reads what it can of a truncated file and
/// would report "no voxels" for a damaged one.
fn check_chunks(bytes: &[u8]) -> Result<(), String> {
    let word = |at: usize| -> Option<u32> {
        Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
    };
    if bytes.get(..4) != Some(b"VOX ") {
        return Err("it does not start with \"VOX \"".into());
    }
    if bytes.get(8..12) != Some(b"MAIN") {
        return Err("the MAIN chunk is missing: the file is damaged or truncated".into());
    }
    let (content, children) = match (word(12), word(16)) {
        (Some(c), Some(ch)) => (c as usize, ch as usize),
        _ => return Err("the file is truncated in its MAIN chunk".into()),
    };
    let end = 20usize.saturating_add(content).saturating_add(children);
    if end > bytes.len() {
        return Err(format!(
            "the file is truncated: its chunks need {end} bytes, it holds {}",
            bytes.len()
        ));
    }
    let mut at = 20 + content;
    while at < end {
        let id = bytes.get(at..at + 4).map(String::from_utf8_lossy);
        let (Some(id), Some(c), Some(ch)) = (id, word(at + 4), word(at + 8)) else {
            return Err(format!(
                "the chunk header at byte {at} is cut off: the file is damaged"
            ));
        };
        let next = (at + 12)
            .saturating_add(c as usize)
            .saturating_add(ch as usize);
        if next > end {
            return Err(format!(
                "chunk {id} at byte {at} runs past the end of the file: the file is damaged"
            ));
        }
        at = next;
    }
    Ok(())
}

/// Reads a `.vox` file's bytes into a scene.
pub fn import_vox(bytes: &[u8], path: &Path) -> Result<BrickMap, ImportError> {
    let bad = |detail: String| ImportError::BadVox {
        path: path.into(),
        detail,
    };
    check_chunks(bytes).map_err(bad)?;
    let data = dot_vox::load_bytes(bytes).map_err(|e| ImportError::BadVox {
        path: path.into(),
        detail: e.to_string(),
    })?;
    let instances = instances(&data).map_err(|detail| ImportError::BadVox {
        path: path.into(),
        detail,
    })?;
    // The scene is the box spanned by every placed model (its corners, not just its voxels, so
    // empty margins survive a round trip).
    let mut lo = [i32::MAX; 3];
    let mut hi = [i32::MIN; 3];
    for inst in &instances {
        let size = data.models[inst.model].size;
        if size.x == 0 || size.y == 0 || size.z == 0 {
            continue;
        }
        for corner in 0..8u32 {
            let p = [
                if corner & 1 == 0 { 0 } else { size.x - 1 },
                if corner & 2 == 0 { 0 } else { size.y - 1 },
                if corner & 4 == 0 { 0 } else { size.z - 1 },
            ];
            let w = inst.place(size, p);
            for i in 0..3 {
                lo[i] = lo[i].min(w[i]);
                hi[i] = hi[i].max(w[i]);
            }
        }
    }
    let voxel_count: u64 = instances
        .iter()
        .map(|i| data.models[i.model].voxels.len() as u64)
        .sum();
    if voxel_count == 0 || lo[0] > hi[0] {
        return Err(ImportError::EmptyModel(path.into()));
    }
    if voxel_count > MAX_VOXELS {
        return Err(bad(format!(
            "its models place {voxel_count} voxels; at most {MAX_VOXELS} are imported"
        )));
    }
    let extent: [i64; 3] = std::array::from_fn(|i| hi[i] as i64 - lo[i] as i64 + 1);
    if extent.iter().any(|&e| e > MAX_SCENE_EDGE as i64) {
        return Err(ImportError::BadVox {
            path: path.into(),
            detail: format!(
                "the models span {extent:?} voxels; a scene holds at most {MAX_SCENE_EDGE} per axis"
            ),
        });
    }
    // Ours: x, y = file z, z = mirrored file y.
    let size = [extent[0] as u32, extent[2] as u32, extent[1] as u32];
    let mut map = BrickMap::new(size)?;
    let palette: Vec<Colour> = (0..256)
        .map(|i| {
            data.palette
                .get(i)
                .map_or(Colour::WHITE, |c| Colour::from_rgb8(c.r, c.g, c.b))
        })
        .collect();
    let mut uses = [0u64; 256];
    for inst in &instances {
        let model = &data.models[inst.model];
        for v in &model.voxels {
            uses[v.i as usize] += 1;
            let p = [v.x as u32, v.y as u32, v.z as u32];
            if p[0] >= model.size.x || p[1] >= model.size.y || p[2] >= model.size.z {
                return Err(ImportError::BadVox {
                    path: path.into(),
                    detail: format!("model {} has a voxel at {p:?} outside its size", inst.model),
                });
            }
            let w = inst.place(model.size, p);
            let ours = [
                (w[0] - lo[0]) as u32,
                (w[2] - lo[2]) as u32,
                (hi[1] - w[1]) as u32,
            ];
            map.set(ours, palette[v.i as usize]);
        }
    }
    map.set_swatches(swatches_of(&palette, &uses));
    map.rebuild_clearance();
    Ok(map)
}

/// The scene's palette from a model's: its most used colours (at most [`SWATCHES`], each once),
/// in the order the file's palette has them (the artist's order), then the default swatches
/// for the rest of the places.
fn swatches_of(palette: &[Colour], uses: &[u64; 256]) -> Swatches {
    let mut used: Vec<(u64, usize)> = (0..palette.len().min(256))
        .filter(|&i| uses[i] > 0)
        .map(|i| (uses[i], i))
        .collect();
    // Most used first; the same colour at two indices counts once, at its more used one.
    used.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut chosen: Vec<usize> = Vec::new();
    for (_, i) in used {
        if chosen.len() == SWATCHES {
            break;
        }
        if !chosen.iter().any(|&c| palette[c] == palette[i]) {
            chosen.push(i);
        }
    }
    chosen.sort_unstable();
    let mut swatches = Swatches::default();
    for (place, &i) in chosen.iter().enumerate() {
        swatches.set(place, palette[i]);
    }
    swatches
}

/// What an export wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExportReport {
    pub models: usize,
    pub voxels: u64,
    pub colours: QuantizeReport,
}

fn frame_at(t: [i32; 3]) -> Frame {
    Frame::new([("_t".to_string(), format!("{} {} {}", t[0], t[1], t[2]))].into())
}

/// Writes a scene as `.vox` bytes: a grid of ≤ 256³ models and a palette of ≤ 255 colours.
pub fn export_vox(map: &BrickMap) -> (Vec<u8>, ExportReport) {
    let size = map.size();
    // File axes: X = our x, Y = our z (mirrored), Z = our y.
    let file_size = [size[0], size[2], size[1]];
    let tiles = file_size.map(|s| s.div_ceil(MODEL_EDGE));
    let tile_index = |t: [u32; 3]| (t[0] + tiles[0] * (t[1] + tiles[1] * t[2])) as usize;

    let mut histogram = vec![0u64; 1 << 16];
    for (brick, _) in map.bricks() {
        for c in &brick.colours {
            histogram[c.0 as usize] += 1;
        }
    }
    let (palette, colours) = quantize(&histogram, 255);

    let mut models: Vec<Model> = Vec::with_capacity(tiles.iter().map(|&t| t as usize).product());
    for tz in 0..tiles[2] {
        for ty in 0..tiles[1] {
            for tx in 0..tiles[0] {
                let t = [tx, ty, tz];
                let s = [0, 1, 2].map(|i| (file_size[i] - t[i] * MODEL_EDGE).min(MODEL_EDGE));
                models.push(Model {
                    size: Size {
                        x: s[0],
                        y: s[1],
                        z: s[2],
                    },
                    voxels: Vec::new(),
                });
            }
        }
    }
    let mut voxels = 0u64;
    for (brick, _) in map.bricks() {
        let mut rank = 0;
        for_each_bit(&brick.mask, |bit| {
            let l = bit_voxel(bit);
            let ours = [0, 1, 2].map(|i| brick.cell[i] * BRICK_EDGE + l[i]);
            let file = [ours[0], size[2] - 1 - ours[2], ours[1]];
            let tile = file.map(|c| c / MODEL_EDGE);
            models[tile_index(tile)].voxels.push(Voxel {
                x: (file[0] % MODEL_EDGE) as u8,
                y: (file[1] % MODEL_EDGE) as u8,
                z: (file[2] % MODEL_EDGE) as u8,
                i: palette.index(brick.colours[rank]),
            });
            rank += 1;
            voxels += 1;
        });
    }

    // Scene graph: root transform → group → (transform → shape) per model. A model's transform
    // puts its centre (origin + ⌊size/2⌋) where the tile sits.
    let mut scenes = vec![
        SceneNode::Transform {
            attributes: Default::default(),
            frames: vec![Frame::new(Default::default())],
            child: 1,
            layer_id: u32::MAX,
        },
        SceneNode::Group {
            attributes: Default::default(),
            children: (0..models.len() as u32).map(|k| 2 + 2 * k).collect(),
        },
    ];
    for (k, model) in models.iter().enumerate() {
        let tile = [
            k as u32 % tiles[0],
            (k as u32 / tiles[0]) % tiles[1],
            k as u32 / (tiles[0] * tiles[1]),
        ];
        let s = [model.size.x, model.size.y, model.size.z];
        let t: [i32; 3] = std::array::from_fn(|i| (tile[i] * MODEL_EDGE + s[i] / 2) as i32);
        scenes.push(SceneNode::Transform {
            attributes: Default::default(),
            frames: vec![frame_at(t)],
            child: 3 + 2 * k as u32,
            layer_id: 0,
        });
        scenes.push(SceneNode::Shape {
            attributes: Default::default(),
            models: vec![ShapeModel {
                model_id: k as u32,
                attributes: Default::default(),
            }],
        });
    }
    let mut file_palette: Vec<dot_vox::Color> = palette
        .colours
        .iter()
        .map(|c| dot_vox::Color {
            r: c[0],
            g: c[1],
            b: c[2],
            a: 255,
        })
        .collect();
    file_palette.resize(
        256,
        dot_vox::Color {
            r: 0,
            g: 0,
            b: 0,
            a: 255,
        },
    );
    let data = DotVoxData {
        version: 150,
        index_map: dot_vox::DEFAULT_INDEX_MAP.to_vec(),
        models,
        palette: file_palette,
        materials: Vec::new(),
        scenes,
        layers: vec![dot_vox::Layer {
            attributes: Default::default(),
        }],
    };
    let mut bytes = Vec::new();
    // Writing to a Vec cannot fail.
    let _ = data.write_vox(&mut bytes);
    let report = ExportReport {
        models: data.models.len(),
        voxels,
        colours,
    };
    (bytes, report)
}

#[cfg(test)]
mod swatch_tests {
    use super::*;

    /// Of 40 colours, the 32 most used become swatches, in the file's order; a colour at two
    /// indices takes one swatch.
    #[test]
    fn the_most_used_colours_become_the_swatches_in_file_order() {
        let mut palette: Vec<Colour> = (0..256u16).map(|i| Colour(1000 + i)).collect();
        palette[41] = palette[40];
        let mut uses = [0u64; 256];
        for (i, n) in uses.iter_mut().take(40).enumerate() {
            *n = 100 + i as u64; // 9..=39 are the most used after 41
        }
        uses[41] = 1_000; // the same colour as 40: counted at 41
        uses[40] = 1;
        let s = swatches_of(&palette, &uses);
        let want: Vec<Colour> = (9..40).map(|i| palette[i]).chain([palette[41]]).collect();
        assert_eq!(s.0.to_vec(), want);
        // Fewer colours than swatches: the rest stay the defaults.
        let mut few = [0u64; 256];
        few[3] = 5;
        let s = swatches_of(&palette, &few);
        assert_eq!(s.get(0), palette[3]);
        assert_eq!(&s.0[1..], &Swatches::default().0[1..]);
    }
}
