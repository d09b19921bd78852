//! What `--colours bounded` costs a picture (issue #29): Sibenik imported at 2048³ and traced
//! from its first camera on the CPU, exact against bounded; the frame's PSNR and the pixels
//! within 8/255. Needs the shared scenes; CI runs it (`BRICKCAST_SCENES`).

use brickcast_protocol::blocks::Quality;
use brickcast_protocol::palette::Mix;
use brickcast_protocol::render::{Lighting, render};
use brickcast_protocol::{BrickMap, viewpoint};

#[test]
#[ignore = "needs the shared scenes: set BRICKCAST_SCENES"]
fn sibenik_bounded_frame_stays_close_to_the_exact_one() {
    use brickcast_server::import::{ImportOptions, NoProgress, import_file};
    let scenes = std::env::var("BRICKCAST_SCENES").expect("BRICKCAST_SCENES");
    let options = ImportOptions {
        resolution: 2048,
        threads: 0,
        ..ImportOptions::default()
    };
    let obj = std::path::Path::new(&scenes).join("sibenik/sibenik.obj");
    let exact = import_file(&obj, &options, &NoProgress)
        .expect("import")
        .map;
    let bound = Quality::default().bound().expect("bounded by default");
    let mut bounded = BrickMap::new(exact.size()).expect("size");
    bounded.set_colour_bound(Some(bound));
    bounded
        .write_bricks(
            exact
                .bricks()
                .map(|(b, _)| (b.cell, Some((b.mask, b.colours)))),
        )
        .expect("bricks");
    bounded.rebuild_clearance();
    let mix = Mix::bounded(&exact, bound);
    let psnr_voxels = mix.psnr_db.expect("something is lossy");
    let found = viewpoint::find(&exact, 60.0);
    // A cathedral is an interior: its pillars and vaults are inside the enclosure.
    assert_eq!(found.placement, viewpoint::Placement::Inside, "{found:?}");
    let camera = found.camera;
    let projection = camera.project(640, 360).expect("camera");
    let lighting = Lighting::default();
    let want = render(&exact, &projection, &lighting, 0);
    let got = render(&bounded, &projection, &lighting, 0);
    assert_eq!(want.hits, got.hits, "lossy colours moved a hit");
    let mut squared = 0f64;
    let mut close = 0usize;
    for (a, b) in want.pixels.iter().zip(&got.pixels) {
        let d: Vec<f64> = (0..3).map(|k| f64::from(a[k]) - f64::from(b[k])).collect();
        squared += d.iter().map(|v| v * v).sum::<f64>();
        close += usize::from(d.iter().all(|v| v.abs() <= 8.0));
    }
    let mse = squared / (3.0 * want.pixels.len() as f64);
    let psnr = 10.0 * (255.0f64 * 255.0 / mse.max(1e-9)).log10();
    let within = close as f64 / want.pixels.len() as f64;
    let memory = (exact.memory().total_bytes, bounded.memory().total_bytes);
    println!(
        "sibenik 2048: layout {} -> {} bytes; voxels PSNR {psnr_voxels:.2} dB; frame PSNR \
         {psnr:.2} dB, {:.3}% of pixels within 8/255",
        memory.0,
        memory.1,
        100.0 * within
    );
    assert!(psnr_voxels >= 40.0, "voxel PSNR {psnr_voxels:.2} dB");
    assert!(psnr >= 38.0, "frame PSNR {psnr:.2} dB");
    assert!(within >= 0.99, "only {:.3}% within 8/255", 100.0 * within);
    assert!(memory.1 <= 40_000_000, "{} bytes", memory.1);
}
