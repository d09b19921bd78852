//! Times `BrickMap::rebuild_clearance` (regions and cells) on the demo scene.
//! `cargo run --release -p brickcast-protocol --example rebuild_time -- [edge]`
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let edge: u32 = std::env::args()
        .nth(1)
        .map(|a| a.parse())
        .transpose()?
        .unwrap_or(1024);
    let mut map = brickcast_protocol::demo::demo_scene([edge; 3])?;
    let mut best = f64::MAX;
    for _ in 0..5 {
        let started = std::time::Instant::now();
        map.rebuild_clearance();
        best = best.min(started.elapsed().as_secs_f64() * 1e3);
    }
    println!(
        "{edge}³ demo, {} bricks: rebuild_clearance {best:.2} ms (best of 5)",
        map.brick_count()
    );
    Ok(())
}
