//! `brickcast-server generate terrain`: a procedural world (`protocol::world`) made tile by
//! tile on every core and streamed into the store as the tiles come, so a world is never held
//! whole (`Store::begin_scene`).

use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Instant;

use anyhow::Context;
use brickcast_protocol::brick::BrickData;
use brickcast_protocol::map::MapError;
use brickcast_protocol::world::{TILE_EDGE, World};
use brickcast_server::store::{Store, valid_scene_name};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

#[derive(clap::Subcommand)]
pub enum Kind {
    /// Terrain with water, forests and houses, in the spirit of the demo scene but with
    /// features of fixed size, so a larger world has more of them.
    Terrain(Args),
}

#[derive(clap::Args)]
pub struct Args {
    /// Name of the new scene.
    #[arg(long)]
    scene: String,
    /// Voxels along x, y (up) and z, e.g. `4096,256,4096`.
    #[arg(long, value_parser = parse_size)]
    size: [u32; 3],
    /// Another seed, another world; the same seed and size give the same voxels.
    #[arg(long, default_value_t = 1)]
    seed: u32,
    #[arg(long, default_value = "./brickcast-data")]
    data: PathBuf,
    /// Replace an existing scene of that name.
    #[arg(long)]
    replace: bool,
    /// Generating threads (default: one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Print the summary as one JSON object.
    #[arg(long)]
    json: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// `X,Y,Z` voxels, each at least 1.
fn parse_size(text: &str) -> Result<[u32; 3], String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(format!(
            "{text:?} is not X,Y,Z (three numbers of voxels, e.g. 4096,256,4096)"
        ));
    };
    let axis = |s: &str| match s.parse::<u32>() {
        Ok(v) if v > 0 => Ok(v),
        _ => Err(format!(
            "{s:?} in {text:?} is not a number of voxels (1 or more)"
        )),
    };
    Ok([axis(x)?, axis(y)?, axis(z)?])
}

pub fn run(kind: Kind) -> anyhow::Result<()> {
    let Kind::Terrain(args) = kind;
    if !valid_scene_name(&args.scene) {
        anyhow::bail!(
            "scene name {:?} is invalid: use 1-64 letters, digits, '-', '_' or '.'",
            args.scene
        );
    }
    let world = World::new(args.size, args.seed).with_context(|| "cannot make that world")?;
    let store = match Store::open(&args.data) {
        Ok(store) => store,
        Err(e) if e.is_locked() => anyhow::bail!(
            "a running server holds {}: stop it to generate into this store (a world is written straight into the store, tile by tile)",
            args.data.display()
        ),
        Err(e) => return Err(e.into()),
    };
    if store.scenes()?.iter().any(|(n, _)| *n == args.scene) {
        if !args.replace {
            anyhow::bail!(
                "scene {} already exists in {}; pass --replace to overwrite it",
                args.scene,
                args.data.display()
            );
        }
        store.delete_scene(&args.scene)?;
        eprintln!("replaced the earlier scene {}", args.scene);
    }
    let started = Instant::now();
    let [nx, nz] = world.tiles();
    let tiles = nx * nz;
    let bar = if args.quiet || args.json {
        ProgressBar::hidden()
    } else {
        let bar =
            ProgressBar::with_draw_target(Some(u64::from(tiles)), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template(
                "generating {bar:40} {pos}/{len} tiles, {msg} ({eta} left)",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    };
    let threads = match args.threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    };
    let mut writer = store.begin_scene(&args.scene, args.size)?;
    let voxels = generate(&world, threads, |bricks| {
        writer.put(&bricks)?;
        bar.inc(1);
        bar.set_message(format!("{} bricks", writer.written()));
        Ok(())
    })?;
    let bricks = writer.finish()?;
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "scene": args.scene,
                "size": args.size,
                "seed": args.seed,
                "tiles": tiles,
                "bricks": bricks,
                "solid_voxels": voxels,
                "seconds": seconds,
            })
        );
    } else {
        println!(
            "generated scene {}: {}x{}x{} voxels (seed {}), {tiles} tiles of {TILE_EDGE}², {bricks} bricks, {voxels} solid voxels in {seconds:.1} s",
            args.scene, args.size[0], args.size[1], args.size[2], args.seed
        );
    }
    Ok(())
}

/// Makes every tile of `world` on `threads` threads and hands each tile's bricks to `write`
/// on this thread, in the order they are done. At most two tiles per thread wait to be
/// written, so memory stays a few tiles whatever the world's size. Returns the solid voxels.
fn generate(
    world: &World,
    threads: usize,
    mut write: impl FnMut(Vec<BrickData>) -> anyhow::Result<()>,
) -> anyhow::Result<u64> {
    let [nx, nz] = world.tiles();
    let next = AtomicU32::new(0);
    let (tx, rx) = std::sync::mpsc::sync_channel::<Result<Vec<BrickData>, MapError>>(2 * threads);
    std::thread::scope(|scope| {
        for _ in 0..threads {
            let (tx, next) = (tx.clone(), &next);
            scope.spawn(move || {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= nx * nz {
                        return;
                    }
                    // A send fails only once the writer stopped (an error): stop too.
                    if tx.send(world.tile([i % nx, i / nx])).is_err() {
                        return;
                    }
                }
            });
        }
        drop(tx);
        let mut voxels = 0u64;
        for tile in rx {
            let bricks = tile.context("generating a tile")?;
            voxels += bricks.iter().map(|b| b.colours.len() as u64).sum::<u64>();
            write(bricks)?;
        }
        Ok(voxels)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_or_say_why_not() {
        assert_eq!(parse_size("4096,256,4096"), Ok([4096, 256, 4096]));
        assert_eq!(parse_size(" 8, 16 ,24"), Ok([8, 16, 24]));
        for bad in ["", "1,2", "1,2,3,4", "0,8,8", "8,-1,8", "a,b,c"] {
            assert!(parse_size(bad).is_err(), "{bad}");
        }
    }
}
