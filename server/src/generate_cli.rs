//! `brickcast-server generate terrain`: a procedural world made tile by tile on every core and
//! streamed into the store (`brickcast_server::generate`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use brickcast_protocol::world::{TILE_EDGE, World};
use brickcast_server::generate;
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
pub fn parse_size(text: &str) -> Result<[u32; 3], String> {
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
    let generated = generate::into_store(&store, &args.scene, &world, threads, |_, bricks| {
        bar.inc(1);
        bar.set_message(format!("{bricks} bricks"));
    })?;
    let (bricks, voxels) = (generated.bricks, generated.solid_voxels);
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
