//! Scene import: meshes generated here (written as real OBJ/MTL/PNG files where the file path
//! matters), with exact expectations; `.vox` round trips; the shared Sibenik scene (ignored
//! unless `BRICKCAST_SCENES` points at the shared scenes).

use std::path::{Path, PathBuf};

use brickcast_protocol::brick::{BRICK_EDGE, bit_voxel, for_each_bit};
use brickcast_protocol::{BrickMap, BrushMode, Colour, Ray, trace};
use brickcast_server::import::mesh::{Material, Mesh};
use brickcast_server::import::voxelize::voxelize;
use brickcast_server::import::{ImportError, ImportOptions, NoProgress, import_file, vox};

fn options(resolution: u32) -> ImportOptions {
    ImportOptions {
        resolution,
        threads: 2,
        ..ImportOptions::default()
    }
}

/// Every solid voxel with its colour, sorted: two maps hold the same scene iff these are equal.
fn voxels(map: &BrickMap) -> Vec<([u32; 3], Colour)> {
    let mut out = Vec::new();
    for (brick, _) in map.bricks() {
        let mut rank = 0;
        for_each_bit(&brick.mask, |bit| {
            let l = bit_voxel(bit);
            out.push((
                [0, 1, 2].map(|i| brick.cell[i] * BRICK_EDGE + l[i]),
                brick.colours[rank],
            ));
            rank += 1;
        });
    }
    out.sort_by_key(|(p, _)| [p[2], p[1], p[0]]);
    out
}

/// The unit cube's 12 triangles, each face with UVs spanning 0..1 and its own material.
const CUBE_OBJ: &str = "\
mtllib cube.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
vt 0 0
vt 1 0
vt 1 1
vt 0 1
usemtl textured
# z = 0 (front): u along x, v along y
f 1/1 2/2 3/3
f 1/1 3/3 4/4
usemtl plain
# z = 1 (back)
f 5/1 7/3 6/2
f 5/1 8/4 7/3
# x = 0, x = 1, y = 0, y = 1
f 1/1 4/4 8/3
f 1/1 8/3 5/2
f 2/1 6/2 7/3
f 2/1 7/3 3/4
f 1/1 5/4 6/3
f 1/1 6/3 2/2
f 4/1 3/2 7/3
f 4/1 7/3 8/4
";

const RED: [u8; 3] = [255, 0, 0];
const GREEN: [u8; 3] = [0, 255, 0];
const BLUE: [u8; 3] = [0, 0, 255];
const WHITE: [u8; 3] = [255, 255, 255];

/// A 64×64 texture in quadrants: top-left red, top-right green, bottom-left blue, bottom-right
/// white (image rows run top to bottom; OBJ's v runs bottom to top).
fn write_quadrant_texture(path: &Path) {
    let image = image::RgbImage::from_fn(64, 64, |x, y| {
        image::Rgb(match (x < 32, y < 32) {
            (true, true) => RED,
            (false, true) => GREEN,
            (true, false) => BLUE,
            (false, false) => WHITE,
        })
    });
    image.save(path).unwrap();
}

fn write_cube(dir: &Path, mtl: Option<&str>, texture: bool) -> PathBuf {
    let obj = dir.join("cube.obj");
    std::fs::write(&obj, CUBE_OBJ).unwrap();
    if let Some(mtl) = mtl {
        std::fs::write(dir.join("cube.mtl"), mtl).unwrap();
    }
    if texture {
        write_quadrant_texture(&dir.join("quadrants.png"));
    }
    obj
}

const CUBE_MTL: &str = "\
newmtl textured
Kd 1 1 1
map_Kd quadrants.png
newmtl plain
Kd 0.2 0.4 0.6
";

fn colour(rgb: [u8; 3]) -> Colour {
    Colour::from_rgb8(rgb[0], rgb[1], rgb[2])
}

#[test]
fn textured_cube_is_a_one_voxel_shell_with_sampled_colours() {
    let dir = tempfile::tempdir().unwrap();
    let obj = write_cube(dir.path(), Some(CUBE_MTL), true);
    for resolution in [8, 16, 64] {
        let imported = import_file(&obj, &options(resolution), &NoProgress).unwrap();
        let map = &imported.map;
        let r = resolution;
        assert_eq!(map.size(), [r, r, r]);
        // Faces lie on voxel centres (0.5 and R − 0.5): the shell is exactly one voxel thick.
        assert_eq!(
            map.solid_voxels(),
            (r as u64).pow(3) - (r as u64 - 2).pow(3)
        );
        assert!(
            imported.report.warnings.is_empty(),
            "{:?}",
            imported.report.warnings
        );
        assert_eq!(
            (
                imported.report.triangles,
                imported.report.degenerate_triangles
            ),
            (12, 0)
        );
        map.check_invariants().unwrap();

        // Front face (z = 0): u = x, v = y, so the top-left quadrant of the image is at low x,
        // high y. Voxel centres never fall on a quadrant border (centres are at k/(R−1)).
        let q = r / 4;
        let front = |x: u32, y: u32| map.get([x, y, 0]);
        assert_eq!(front(q, r - 1 - q), Some(colour(RED)));
        assert_eq!(front(r - 1 - q, r - 1 - q), Some(colour(GREEN)));
        assert_eq!(front(q, q), Some(colour(BLUE)));
        assert_eq!(front(r - 1 - q, q), Some(colour(WHITE)));
        // Back face: the material's diffuse colour, no texture.
        let plain = Colour::from_rgb8(51, 102, 153);
        assert_eq!(map.get([r / 2, r / 2, r - 1]), Some(plain));
        // Inside is empty.
        assert_eq!(map.get([r / 2, r / 2, r / 2]), None);
        // A closed model is an object: its first view (and thumbnail) looks at it from
        // outside, not at the inside of its shell.
        let view = brickcast_protocol::viewpoint::find(map, 60.0);
        assert_eq!(
            view.placement,
            brickcast_protocol::viewpoint::Placement::Outside,
            "{view:?}"
        );
    }
}

#[test]
fn missing_texture_and_missing_mtl_are_warnings() {
    let dir = tempfile::tempdir().unwrap();
    // The MTL names a texture that is not there: warn, use Kd.
    let mtl = CUBE_MTL.replace("quadrants.png", "nothere.png");
    let obj = write_cube(dir.path(), Some(&mtl), false);
    let imported = import_file(&obj, &options(8), &NoProgress).unwrap();
    let warnings = imported.report.warnings.join("\n");
    assert!(warnings.contains("nothere.png"), "{warnings}");
    assert_eq!(imported.map.get([2, 2, 0]), Some(Colour::WHITE));
    assert_eq!(imported.map.solid_voxels(), 296);

    // No MTL at all: warn, every surface gets the default grey.
    let dir = tempfile::tempdir().unwrap();
    let obj = write_cube(dir.path(), None, false);
    let imported = import_file(&obj, &options(8), &NoProgress).unwrap();
    let warnings = imported.report.warnings.join("\n");
    assert!(warnings.contains("cube.mtl"), "{warnings}");
    let grey = Colour::from_rgb8(204, 204, 204);
    assert!(voxels(&imported.map).iter().all(|(_, c)| *c == grey));
    assert_eq!(imported.map.solid_voxels(), 296);
}

#[test]
fn malformed_obj_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    for (name, text) in [
        ("letters.obj", "v 0 0 0\nv 1 banana 0\nv 0 1 0\nf 1 2 3\n"),
        ("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n"),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let err = import_file(&path, &options(8), &NoProgress)
            .err()
            .expect("malformed OBJ must fail");
        assert!(matches!(err, ImportError::BadObj { .. }), "{name}: {err}");
        assert!(err.to_string().contains(name), "{err}");
    }
    let err = import_file(&dir.path().join("absent.obj"), &options(8), &NoProgress)
        .err()
        .unwrap();
    assert!(matches!(err, ImportError::Read { .. }), "{err}");
    let err = import_file(&dir.path().join("model.stl"), &options(8), &NoProgress)
        .err()
        .unwrap();
    assert!(matches!(err, ImportError::UnknownFormat { .. }), "{err}");
    for bad in [0, 6, 100, 16384] {
        let err = import_file(&dir.path().join("x.obj"), &options(bad), &NoProgress)
            .err()
            .unwrap();
        assert!(
            matches!(err, ImportError::BadResolution(r) if r == bad),
            "{err}"
        );
    }
}

fn single(corners: [[f32; 3]; 3]) -> Mesh {
    let mut mesh = Mesh::new();
    mesh.add_triangle(corners, None, 0);
    mesh
}

#[test]
fn thin_triangle_keeps_every_voxel_along_it() {
    // A sliver 0.1% as wide as it is long, along x: one unbroken row of voxels.
    let mesh = single([[0.0, 0.0, 0.0], [1.0, 0.0005, 0.0], [1.0, 0.0, 0.001]]);
    let (map, stats) = voxelize(&mesh, &options(64), &NoProgress).unwrap();
    assert_eq!(map.size(), [64, 1, 1]);
    assert_eq!(stats.degenerate, 0);
    let got: Vec<[u32; 3]> = voxels(&map).into_iter().map(|(p, _)| p).collect();
    let row: Vec<[u32; 3]> = (0..64).map(|x| [x, 0, 0]).collect();
    assert_eq!(got, row);
}

#[test]
fn degenerate_triangles_are_skipped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let obj = write_cube(dir.path(), Some(CUBE_MTL), true);
    let with_line = dir.path().join("cube_and_line.obj");
    // Three corners on one line (a zero-area face) and one repeated vertex.
    let text = format!("{CUBE_OBJ}v 0 0 0.5\nv 0.5 0.5 0.5\nv 1 1 0.5\nf 9 10 11\nf 1 1 2\n");
    std::fs::write(&with_line, text).unwrap();
    let plain = import_file(&obj, &options(16), &NoProgress).unwrap();
    let imported = import_file(&with_line, &options(16), &NoProgress).unwrap();
    assert_eq!(imported.report.triangles, 14);
    assert_eq!(imported.report.degenerate_triangles, 2);
    assert_eq!(voxels(&imported.map), voxels(&plain.map));

    let only_line = single([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]);
    assert!(matches!(
        voxelize(&only_line, &options(16), &NoProgress),
        Err(ImportError::EmptyMesh)
    ));
}

/// An icosahedron subdivided twice and turned off the axes: a closed mesh.
fn sphere_mesh() -> Mesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<[f32; 3]> = vec![
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    let mut f: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..2 {
        let mut next = Vec::new();
        let mut mid = std::collections::HashMap::new();
        let mut midpoint = |a: usize, b: usize, v: &mut Vec<[f32; 3]>| {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let m: [f32; 3] = std::array::from_fn(|i| (v[a][i] + v[b][i]) / 2.0);
                let len = m.iter().map(|x| x * x).sum::<f32>().sqrt();
                v.push(m.map(|x| x / len * (1.0 + t * t).sqrt()));
                v.len() - 1
            })
        };
        for [a, b, c] in f {
            let (ab, bc, ca) = (
                midpoint(a, b, &mut v),
                midpoint(b, c, &mut v),
                midpoint(c, a, &mut v),
            );
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = next;
    }
    // Rotate so no face is axis-aligned.
    let (s, c) = (0.4f32.sin(), 0.4f32.cos());
    let v: Vec<[f32; 3]> = v
        .iter()
        .map(|p| {
            let q = [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]];
            [q[0], c * q[1] - s * q[2], s * q[1] + c * q[2]]
        })
        .collect();
    let mut mesh = Mesh::new();
    for [a, b, c] in f {
        mesh.add_triangle([v[a], v[b], v[c]], None, 0);
    }
    mesh
}

#[test]
fn closed_mesh_has_no_holes_at_any_resolution() {
    let mesh = sphere_mesh();
    for resolution in [8, 16, 32, 128] {
        let (map, _) = voxelize(&mesh, &options(resolution), &NoProgress).unwrap();
        let size = map.size();
        let centre = size.map(|s| s as f32 / 2.0);
        // Every ray from the centre must hit the shell: a miss is a hole.
        let mut state = 12345u32;
        for _ in 0..3000 {
            let mut d = [0.0f32; 3];
            for x in &mut d {
                state = state.wrapping_mul(1664525).wrapping_add(1013904223);
                *x = (state >> 8) as f32 / (1 << 24) as f32 * 2.0 - 1.0;
            }
            if d.iter().all(|x| x.abs() < 1e-3) {
                continue;
            }
            let hit = trace(
                &map,
                &Ray {
                    origin: centre,
                    dir: d,
                },
            );
            assert!(
                hit.is_some(),
                "resolution {resolution}: ray {d:?} escapes the sphere"
            );
        }
    }
}

#[test]
fn vox_round_trip_is_exact_across_model_boundaries() {
    // 300 along x splits into two models; corners and a sphere across the seam.
    let mut map = BrickMap::new([300, 20, 40]).unwrap();
    let palette: Vec<Colour> = (0..40u32)
        .map(|i| Colour::from_rgb8((i * 6) as u8, 200 - i as u8, (i * 3) as u8))
        .collect();
    map.set([0, 0, 0], palette[0]);
    map.set([299, 19, 39], palette[1]);
    map.set([299, 0, 0], palette[2]);
    map.set([0, 19, 39], palette[3]);
    map.sphere([256.0, 10.0, 20.0], 9.0, BrushMode::Fill, palette[4]);
    for i in 0..36 {
        map.set([10 + i * 8, 5, (i * 7) % 40], palette[4 + i as usize]);
    }
    let (bytes, report) = vox::export_vox(&map);
    assert_eq!(report.models, 2);
    assert!(report.colours.exact);
    assert_eq!(report.voxels, map.solid_voxels());
    let back = vox::import_vox(&bytes, Path::new("round.vox")).unwrap();
    assert_eq!(back.size(), map.size());
    assert_eq!(voxels(&back), voxels(&map));
}

#[test]
fn vox_export_quantises_many_colours_and_reports_the_error() {
    let mut map = BrickMap::new([64, 64, 8]).unwrap();
    for x in 0..64 {
        for y in 0..64 {
            map.set(
                [x, y, 0],
                Colour::from_rgb8((x * 4) as u8, (y * 4) as u8, 90),
            );
        }
    }
    let (bytes, report) = vox::export_vox(&map);
    assert!(!report.colours.exact);
    assert_eq!(report.colours.palette, 255);
    assert!(report.colours.distinct > 1000);
    let back = vox::import_vox(&bytes, Path::new("q.vox")).unwrap();
    let (a, b) = (voxels(&map), voxels(&back));
    assert_eq!(a.len(), b.len());
    for ((p, c), (q, d)) in a.iter().zip(&b) {
        assert_eq!(p, q);
        let (c, d) = (c.to_rgb8(), d.to_rgb8());
        let err = ((0..3)
            .map(|i| (c[i] as f64 - d[i] as f64).powi(2))
            .sum::<f64>())
        .sqrt();
        // RGB565 rounding of the palette entry adds at most a few units.
        assert!(
            err <= report.colours.max_error + 8.0,
            "{p:?}: {c:?} became {d:?}"
        );
    }
}

#[test]
fn vox_axes_palette_and_scene_graph_placement() {
    use dot_vox::{DotVoxData, Frame, Model, SceneNode, ShapeModel, Size, Voxel};
    let model = |x, y, z, voxels| Model {
        size: Size { x, y, z },
        voxels,
    };
    let transform = |t: &str, child| SceneNode::Transform {
        attributes: Default::default(),
        frames: vec![Frame::new([("_t".to_string(), t.to_string())].into())],
        child,
        layer_id: 0,
    };
    let shape = |id| SceneNode::Shape {
        attributes: Default::default(),
        models: vec![ShapeModel {
            model_id: id,
            attributes: Default::default(),
        }],
    };
    let mut palette = dot_vox::DEFAULT_PALETTE.to_vec();
    palette[4] = dot_vox::Color {
        r: 10,
        g: 20,
        b: 30,
        a: 255,
    };
    palette[7] = dot_vox::Color {
        r: 200,
        g: 100,
        b: 0,
        a: 255,
    };
    // Model 0 (4×3×2) centred at (2, 1, 1): it spans x 0..4, y 0..3, z 0..2.
    // Model 1 (1×1×1) centred at (10, 0, 5).
    let data = DotVoxData {
        version: 150,
        index_map: dot_vox::DEFAULT_INDEX_MAP.to_vec(),
        models: vec![
            model(
                4,
                3,
                2,
                vec![Voxel {
                    x: 1,
                    y: 0,
                    z: 1,
                    i: 4,
                }],
            ),
            model(
                1,
                1,
                1,
                vec![Voxel {
                    x: 0,
                    y: 0,
                    z: 0,
                    i: 7,
                }],
            ),
        ],
        palette,
        materials: vec![],
        scenes: vec![
            transform("0 0 0", 1),
            SceneNode::Group {
                attributes: Default::default(),
                children: vec![2, 4],
            },
            transform("2 1 1", 3),
            shape(0),
            transform("10 0 5", 5),
            shape(1),
        ],
        layers: vec![],
    };
    let mut bytes = Vec::new();
    data.write_vox(&mut bytes).unwrap();
    let map = vox::import_vox(&bytes, Path::new("placed.vox")).unwrap();
    // File box: x 0..=10, y 0..=2, z 0..=5 → ours (x, z, mirrored y): 11 × 6 × 3.
    assert_eq!(map.size(), [11, 6, 3]);
    // File (1, 0, 1) → ours (1, 1, 2 − 0); file (10, 0, 5) → ours (10, 5, 2).
    assert_eq!(
        voxels(&map),
        vec![
            ([1, 1, 2], Colour::from_rgb8(10, 20, 30)),
            ([10, 5, 2], Colour::from_rgb8(200, 100, 0)),
        ]
    );
    // The scene's shared palette starts with the model's colours, in the file's order; the
    // default swatches fill the rest.
    let swatches = map.swatches();
    assert_eq!(swatches.get(0), Colour::from_rgb8(10, 20, 30));
    assert_eq!(swatches.get(1), Colour::from_rgb8(200, 100, 0));
    let default = brickcast_protocol::swatches::Swatches::default();
    assert_eq!(&swatches.0[2..], &default.0[2..]);

    assert!(matches!(
        vox::import_vox(b"VOX nonsense", Path::new("bad.vox")),
        Err(ImportError::BadVox { .. })
    ));
    // A group that lists itself: refused, not expanded forever.
    let cyclic = DotVoxData {
        models: vec![model(
            1,
            1,
            1,
            vec![Voxel {
                x: 0,
                y: 0,
                z: 0,
                i: 1,
            }],
        )],
        scenes: vec![SceneNode::Group {
            attributes: Default::default(),
            children: vec![0, 0],
        }],
        palette: data.palette.clone(),
        index_map: data.index_map.clone(),
        materials: vec![],
        layers: vec![],
        version: 150,
    };
    let mut bytes = Vec::new();
    cyclic.write_vox(&mut bytes).unwrap();
    let err = vox::import_vox(&bytes, Path::new("loop.vox"))
        .err()
        .unwrap();
    assert!(err.to_string().contains("refer back"), "{err}");
    let empty = DotVoxData {
        models: vec![model(4, 4, 4, vec![])],
        scenes: vec![],
        ..data
    };
    let mut bytes = Vec::new();
    empty.write_vox(&mut bytes).unwrap();
    assert!(matches!(
        vox::import_vox(&bytes, Path::new("empty.vox")),
        Err(ImportError::EmptyModel(_))
    ));
}

#[test]
fn materials_without_textures_use_their_diffuse_colour() {
    let mut mesh = Mesh::new();
    let red = mesh.add_material(Material {
        name: "red".into(),
        diffuse: [1.0, 0.0, 0.0],
        texture: None,
    });
    // UVs on an untextured material are ignored.
    mesh.add_triangle(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        Some([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
        red,
    );
    let (map, _) = voxelize(&mesh, &options(8), &NoProgress).unwrap();
    assert!(map.solid_voxels() > 20);
    assert!(
        voxels(&map)
            .iter()
            .all(|(_, c)| *c == Colour::from_rgb8(255, 0, 0))
    );
}

/// Sibenik at 2048³, the paper's Table 1 scene: imports with textures and the bump maps'
/// absence reported, within the memory goal.
#[test]
#[ignore = "needs the shared scenes: set BRICKCAST_SCENES"]
fn sibenik_imports_at_2048() {
    let scenes = std::env::var("BRICKCAST_SCENES").expect("BRICKCAST_SCENES");
    let obj = Path::new(&scenes).join("sibenik/sibenik.obj");
    let imported = import_file(&obj, &options(2048), &NoProgress).unwrap();
    let map = &imported.map;
    assert_eq!(map.size()[0], 2048);
    assert_eq!(imported.report.triangles, 73_564);
    let warnings = imported.report.warnings.join("\n");
    assert!(warnings.contains("kamen-bump.png"), "{warnings}");
    assert!(!warnings.contains("kamen.png "), "{warnings}");
    let memory = map.memory();
    assert!(
        (15_000_000..30_000_000).contains(&memory.solid_voxels),
        "{memory:?}"
    );
    assert!(memory.total_bytes <= 100_000_000, "{memory:?}");
    // Textured: stone has many shades, where 14 untextured materials would give 14 colours.
    let mut distinct = std::collections::HashSet::new();
    for (brick, _) in map.bricks() {
        distinct.extend(brick.colours.iter().map(|c| c.0));
    }
    assert!(distinct.len() > 100, "{} colours", distinct.len());
    map.check_invariants().unwrap();
}

/// A model names files by path: outside its folder they are refused (with a warning, the surface
/// keeps its plain colour) unless the operator allows it, and a device is never read.
#[test]
fn a_model_cannot_reach_files_outside_its_folder() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model");
    std::fs::create_dir(&model).unwrap();
    // The texture sits beside the model's folder, named with `../`.
    write_quadrant_texture(&dir.path().join("quadrants.png"));
    let mtl = CUBE_MTL.replace("quadrants.png", "../quadrants.png");
    let obj = write_cube(&model, Some(&mtl), false);
    let imported = import_file(&obj, &options(8), &NoProgress).unwrap();
    let warnings = imported.report.warnings.join("\n");
    assert!(
        warnings.contains("outside the model's folder"),
        "{warnings}"
    );
    assert_eq!(imported.map.get([2, 5, 0]), Some(Colour::WHITE), "Kd only");
    let allowed = ImportOptions {
        allow_outside_files: true,
        ..options(8)
    };
    let imported = import_file(&obj, &allowed, &NoProgress).unwrap();
    assert!(
        imported.report.warnings.is_empty(),
        "{:?}",
        imported.report.warnings
    );
    assert_eq!(
        imported.map.get([2, 5, 0]),
        Some(colour(RED)),
        "the texture was read"
    );

    // `mtllib /dev/zero`: not a regular file, refused at once (it used to allocate 8 GB).
    let obj = model.join("zero.obj");
    std::fs::write(
        &obj,
        CUBE_OBJ.replace("mtllib cube.mtl", "mtllib /dev/zero"),
    )
    .unwrap();
    for options in [options(8), allowed] {
        let imported = import_file(&obj, &options, &NoProgress).unwrap();
        let warnings = imported.report.warnings.join("\n");
        assert!(
            warnings.contains("/dev/zero")
                && (warnings.contains("not a regular file") || warnings.contains("outside")),
            "{warnings}"
        );
    }
}

/// A face with more corners than any model has is refused before parsing (a million-corner
/// face took 108 s).
#[test]
fn a_face_with_too_many_corners_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut obj = String::new();
    for i in 0..5000 {
        let a = i as f32 * 0.001;
        obj.push_str(&format!("v {} {} 0\n", a.cos(), a.sin()));
    }
    obj.push('f');
    for i in 1..=5000 {
        obj.push_str(&format!(" {i}"));
    }
    obj.push('\n');
    let path = dir.path().join("fan.obj");
    std::fs::write(&path, obj).unwrap();
    let err = import_file(&path, &options(8), &NoProgress).err().unwrap();
    assert!(
        err.to_string().contains("line 5001 has 5000 corners"),
        "{err}"
    );
}

/// A small file whose scene graph fans out (groups of groups) places a model too many times:
/// refused quickly, not expanded for minutes. A truncated file is reported as damaged.
#[test]
fn vox_fan_out_and_truncation_are_refused() {
    use dot_vox::{DotVoxData, Model, SceneNode, ShapeModel, Size, Voxel};
    let group = |children: Vec<u32>| SceneNode::Group {
        attributes: Default::default(),
        children,
    };
    // Node 0: 700 × node 1; node 1: 700 × node 2; node 2: the shape.
    let data = DotVoxData {
        version: 150,
        index_map: dot_vox::DEFAULT_INDEX_MAP.to_vec(),
        models: vec![Model {
            size: Size { x: 1, y: 1, z: 1 },
            voxels: vec![Voxel {
                x: 0,
                y: 0,
                z: 0,
                i: 1,
            }],
        }],
        palette: dot_vox::DEFAULT_PALETTE.to_vec(),
        materials: vec![],
        scenes: vec![
            group(vec![1; 700]),
            group(vec![2; 700]),
            SceneNode::Shape {
                attributes: Default::default(),
                models: vec![ShapeModel {
                    model_id: 0,
                    attributes: Default::default(),
                }],
            },
        ],
        layers: vec![],
    };
    let mut bytes = Vec::new();
    data.write_vox(&mut bytes).unwrap();
    assert!(bytes.len() < 30_000);
    let started = std::time::Instant::now();
    let err = vox::import_vox(&bytes, Path::new("fan.vox")).err().unwrap();
    assert!(err.to_string().contains("model instances"), "{err}");
    assert!(started.elapsed() < std::time::Duration::from_secs(5));

    let one = DotVoxData {
        scenes: vec![],
        ..data
    };
    let mut bytes = Vec::new();
    one.write_vox(&mut bytes).unwrap();
    bytes.truncate(bytes.len() - 10);
    let err = vox::import_vox(&bytes, Path::new("cut.vox")).err().unwrap();
    assert!(err.to_string().contains("truncated"), "{err}");
}
