//! `brickcast load`'s options: parsed and checked before any socket opens, then checked once more
//! against the scene size and limits the server announces in its Welcome.
//!
//! Mistakes are caught here with a sentence that names the option, rather than discovered as a
//! run full of rejected ops.

use std::str::FromStr;

use brickcast_protocol::wire::{Limits, MAX_OPS_PER_BATCH};

/// Most connections (editors plus viewers) one run opens: each holds a socket and a full copy of
/// the scene, so far more than this would exhaust memory or file descriptors before the server.
pub const MAX_CONNECTIONS: u32 = 10_000;
/// Longest run, in seconds.
pub const MAX_DURATION_S: f64 = 86_400.0;

/// The options of `brickcast load`, as typed.
#[derive(clap::Args, Debug, Clone, PartialEq)]
pub struct LoadArgs {
    /// Concurrent editing clients (one websocket and one tokio task each).
    #[arg(long, default_value_t = 16)]
    pub clients: u32,
    /// Seconds of editing (connecting and syncing before it, and draining after, not counted).
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
    /// Ops per client per second; 0 sends as fast as acks allow (at most about 2048 voxel ops'
    /// worth unacknowledged per client, in at least 2 batches).
    #[arg(long, default_value_t = 0.0)]
    pub rate: f64,
    /// Ops per edit message.
    #[arg(long, default_value_t = 16)]
    pub batch: u32,
    /// What each op does: set or clear one voxel, a sphere brush (fill or erase), paint a solid
    /// voxel, or a ray edit (place or remove where a downward ray hits).
    #[arg(long, value_enum, default_value_t = OpKind::Voxel)]
    pub op: OpKind,
    /// Sphere radius in voxels (--op sphere).
    #[arg(long, default_value_t = 4.0)]
    pub radius: f32,
    /// Where edits go: `all` (the whole scene, every client), `X0,Y0,Z0,X1,Y1,Z1` (an inclusive
    /// voxel box shared by every client: contended), or `disjoint` / `disjoint:X0,Y0,Z0,X1,Y1,Z1`
    /// (the scene or box cut into one slab per client, on brick boundaries when wide enough).
    #[arg(long, default_value = "all")]
    pub region: RegionSpec,
    /// The fraction of each editor's messages that are undos or redos of its own steps instead
    /// of edits (0 to 1): an undo after an edit, a redo after an undo. Undo messages count as
    /// messages in `--rate` and their acks in the latency figures; their voxels are reported
    /// apart.
    #[arg(long, default_value_t = 0.0)]
    pub undo_ratio: f64,
    /// Presence messages each client (editors and viewers) sends per second, as a viewer moving
    /// its camera and pointer would (0: none). The report adds how long presence takes to reach
    /// the other clients and what it costs the server.
    #[arg(long, default_value_t = 0.0)]
    pub presence_hz: f64,
    /// Extra clients that only watch (receive every delta, never edit).
    #[arg(long, default_value_t = 0)]
    pub viewers: u32,
    /// Access token (servers started with --auth); it must allow editing.
    #[arg(long)]
    pub token: Option<String>,
    /// Edit the scene itself even when it holds voxels (its edits stay in it). Without this,
    /// a run on a scene that holds voxels edits a scratch scene of the same size that it makes
    /// and deletes through the server's admin API (an admin --token, or the server's own
    /// machine when it has no auth file).
    #[arg(long, alias = "overwrite")]
    pub in_place: bool,
    /// Print one JSON object on stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
}

/// What each generated op does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum OpKind {
    /// `Set` (random colour) or `Clear` of one random voxel, half each, so a long run neither
    /// fills nor empties the region.
    Voxel,
    /// A sphere brush of `--radius`, fill or erase, half each.
    Sphere,
    /// `Paint` of a voxel that was solid when the client synced.
    Paint,
    /// A ray cast down into the region that places a voxel on, or removes, what it hits.
    Ray,
}

/// An inclusive box of voxels: where one client's edits go (`--region`, or its slab of it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VoxelBox {
    pub min: [u32; 3],
    pub max: [u32; 3],
}

impl VoxelBox {
    /// The whole scene.
    pub fn scene(size: [u32; 3]) -> VoxelBox {
        VoxelBox {
            min: [0; 3],
            max: size.map(|s| s.saturating_sub(1)),
        }
    }

    /// Voxels along `axis`.
    pub fn extent(&self, axis: usize) -> u32 {
        self.max[axis] - self.min[axis] + 1
    }

    pub fn contains(&self, p: [u32; 3]) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }
}

/// What `--region` asked for. The default is the whole scene, shared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct RegionSpec {
    /// `None`: the whole scene.
    pub area: Option<VoxelBox>,
    /// One slab of the area per client instead of the whole area for everyone.
    pub disjoint: bool,
}

/// Why the options cannot make a sensible run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptionError {
    #[error(
        "--region {0:?}: expected all, disjoint, X0,Y0,Z0,X1,Y1,Z1 or disjoint:X0,Y0,Z0,X1,Y1,Z1"
    )]
    RegionSyntax(String),
    #[error("--region: {axis} runs from {min} down to {max}; give the smaller corner first")]
    RegionInverted { axis: char, min: u32, max: u32 },
    #[error("--clients must be at least 1 (use --viewers for clients that only watch)")]
    NoClients,
    #[error(
        "--clients plus --viewers is {0}, more than the {MAX_CONNECTIONS} connections one run may open"
    )]
    TooManyConnections(u64),
    #[error("--duration {0} is not a number of seconds between 0 and {MAX_DURATION_S}")]
    Duration(f64),
    #[error("--rate {0} is not a number of ops per second ≥ 0")]
    Rate(f64),
    #[error("--undo-ratio {0} is out of range: 0 to 1")]
    UndoRatio(f64),
    #[error("--presence-hz {0} is out of range: 0 to 1000")]
    PresenceHz(f64),
    #[error("--batch {batch} is out of range: 1 to {max} ops per message")]
    Batch { batch: u32, max: u32 },
    #[error("--radius {radius} is out of range: above 0 and at most {max} (the server's limit)")]
    Radius { radius: f32, max: f32 },
    #[error("--region reaches {max:?}, outside the scene of {size:?} voxels")]
    RegionOutside { max: [u32; 3], size: [u32; 3] },
    #[error(
        "--region disjoint: {width} voxels along {axis} cannot be cut into {clients} slabs of at least {need} (fewer clients, a wider region or a smaller radius)"
    )]
    RegionTooNarrow {
        axis: char,
        width: u32,
        clients: u32,
        need: u32,
    },
}

const AXES: [char; 3] = ['x', 'y', 'z'];

impl FromStr for RegionSpec {
    type Err = OptionError;

    fn from_str(text: &str) -> Result<RegionSpec, OptionError> {
        let text = text.trim();
        let syntax = || OptionError::RegionSyntax(text.to_string());
        let (disjoint, rest) = match text {
            "all" => return Ok(RegionSpec::default()),
            "disjoint" => {
                return Ok(RegionSpec {
                    area: None,
                    disjoint: true,
                });
            }
            _ => match text.strip_prefix("disjoint:") {
                Some(rest) => (true, rest),
                None => (false, text),
            },
        };
        let numbers = rest
            .split(',')
            .map(|n| n.trim().parse::<u32>().map_err(|_| syntax()))
            .collect::<Result<Vec<u32>, OptionError>>()?;
        let [x0, y0, z0, x1, y1, z1] = numbers.as_slice() else {
            return Err(syntax());
        };
        let (min, max) = ([*x0, *y0, *z0], [*x1, *y1, *z1]);
        for axis in 0..3 {
            if min[axis] > max[axis] {
                return Err(OptionError::RegionInverted {
                    axis: AXES[axis],
                    min: min[axis],
                    max: max[axis],
                });
            }
        }
        Ok(RegionSpec {
            area: Some(VoxelBox { min, max }),
            disjoint,
        })
    }
}

/// The rate and pacing of one client, derived from the options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pace {
    /// Time between two edit messages; `None` sends whenever the unacked bound allows.
    pub interval: Option<std::time::Duration>,
}

impl LoadArgs {
    /// Checks what can be checked without a server.
    pub fn check(&self) -> Result<(), OptionError> {
        if self.clients == 0 {
            return Err(OptionError::NoClients);
        }
        let connections = u64::from(self.clients) + u64::from(self.viewers);
        if connections > u64::from(MAX_CONNECTIONS) {
            return Err(OptionError::TooManyConnections(connections));
        }
        if !(self.duration.is_finite() && self.duration > 0.0 && self.duration <= MAX_DURATION_S) {
            return Err(OptionError::Duration(self.duration));
        }
        if !(self.rate.is_finite() && self.rate >= 0.0) {
            return Err(OptionError::Rate(self.rate));
        }
        if !(0.0..=1.0).contains(&self.undo_ratio) {
            return Err(OptionError::UndoRatio(self.undo_ratio));
        }
        if !(self.presence_hz.is_finite() && (0.0..=1000.0).contains(&self.presence_hz)) {
            return Err(OptionError::PresenceHz(self.presence_hz));
        }
        if self.batch == 0 || self.batch > MAX_OPS_PER_BATCH {
            return Err(OptionError::Batch {
                batch: self.batch,
                max: MAX_OPS_PER_BATCH,
            });
        }
        if self.op == OpKind::Sphere && !(self.radius.is_finite() && self.radius > 0.0) {
            return Err(OptionError::Radius {
                radius: self.radius,
                max: f32::MAX,
            });
        }
        Ok(())
    }

    /// Checks the options against the scene and the server's limits, and returns each editing
    /// client's area (where its ops go; for spheres, where their centres go).
    pub fn plan(&self, size: [u32; 3], limits: &Limits) -> Result<Vec<VoxelBox>, OptionError> {
        self.check()?;
        if self.batch > limits.max_ops_per_batch {
            return Err(OptionError::Batch {
                batch: self.batch,
                max: limits.max_ops_per_batch,
            });
        }
        if self.op == OpKind::Sphere && self.radius > limits.max_brush_radius {
            return Err(OptionError::Radius {
                radius: self.radius,
                max: limits.max_brush_radius,
            });
        }
        let area = match self.region.area {
            Some(area) => {
                if (0..3).any(|i| area.max[i] >= size[i]) {
                    return Err(OptionError::RegionOutside {
                        max: area.max,
                        size,
                    });
                }
                area
            }
            None => VoxelBox::scene(size),
        };
        if !self.region.disjoint {
            return Ok(vec![area; self.clients as usize]);
        }
        // A sphere reaches `radius` past its centre: keep centres that far inside each slab so
        // neighbouring clients never touch the same voxel.
        let margin = if self.op == OpKind::Sphere {
            self.radius.ceil() as u32
        } else {
            0
        };
        split(area, self.clients, margin)
    }

    /// How one client paces its messages.
    pub fn pace(&self) -> Pace {
        Pace {
            interval: (self.rate > 0.0)
                .then(|| std::time::Duration::from_secs_f64(f64::from(self.batch) / self.rate)),
        }
    }
}

/// Cuts `area` into `n` slabs across its longer horizontal axis (x or z: the scene's height is
/// often mostly sky). Slab borders fall on brick boundaries (multiples of 8) when every slab can
/// be at least two bricks wide, so no two clients edit the same brick; narrower slabs share the
/// bricks at their borders. `margin` voxels are then taken off both sides of each slab.
pub fn split(area: VoxelBox, n: u32, margin: u32) -> Result<Vec<VoxelBox>, OptionError> {
    let axis = if area.extent(0) >= area.extent(2) {
        0
    } else {
        2
    };
    let width = area.extent(axis);
    let need = 1 + 2 * margin;
    if n == 0 || width / n < need {
        return Err(OptionError::RegionTooNarrow {
            axis: AXES[axis],
            width,
            clients: n,
            need,
        });
    }
    let lo = u64::from(area.min[axis]);
    let end = u64::from(area.max[axis]) + 1;
    let align = width / n >= 16;
    let border = |i: u32| -> u64 {
        let b = lo + u64::from(width) * u64::from(i) / u64::from(n);
        if i == 0 || i == n {
            return b.min(end);
        }
        if align { (b + 4) / 8 * 8 } else { b }.clamp(lo, end)
    };
    let mut slabs = Vec::with_capacity(n as usize);
    for i in 0..n {
        let (from, to) = (border(i), border(i + 1));
        // Unaligned borders are at least `need` apart; aligned ones (slabs of 16 or more) at
        // least 8, which the margin may still eat: hence the check below.
        let mut slab = area;
        slab.min[axis] = (from + u64::from(margin)) as u32;
        slab.max[axis] = (to - 1 - u64::from(margin)) as u32;
        if slab.min[axis] > slab.max[axis] {
            return Err(OptionError::RegionTooNarrow {
                axis: AXES[axis],
                width,
                clients: n,
                need,
            });
        }
        slabs.push(slab);
    }
    Ok(slabs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// Parses a `brickcast load` command line the way the binary does.
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: LoadArgs,
    }

    fn parse(line: &[&str]) -> Result<LoadArgs, String> {
        Cli::try_parse_from(std::iter::once("load").chain(line.iter().copied()))
            .map(|c| c.args)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn defaults_and_every_option_parse() {
        let a = parse(&[]).unwrap();
        assert_eq!(
            (
                a.clients, a.duration, a.rate, a.batch, a.op, a.viewers, a.json
            ),
            (16, 10.0, 0.0, 16, OpKind::Voxel, 0, false)
        );
        assert_eq!(a.region, RegionSpec::default());
        assert!(a.check().is_ok());
        let a = parse(&[
            "--clients",
            "3",
            "--duration",
            "2.5",
            "--rate",
            "1000",
            "--batch",
            "8",
            "--op",
            "sphere",
            "--radius",
            "6",
            "--region",
            "disjoint:0,0,0,255,63,255",
            "--viewers",
            "5",
            "--token",
            "t0k",
            "--json",
        ])
        .unwrap();
        assert_eq!(a.op, OpKind::Sphere);
        assert_eq!(a.radius, 6.0);
        assert_eq!(a.token.as_deref(), Some("t0k"));
        assert_eq!(
            a.region,
            RegionSpec {
                area: Some(VoxelBox {
                    min: [0, 0, 0],
                    max: [255, 63, 255]
                }),
                disjoint: true
            }
        );
        assert_eq!(a.pace().interval, Some(std::time::Duration::from_millis(8)));
        assert!(a.check().is_ok());
        for op in ["voxel", "paint", "ray"] {
            assert!(parse(&["--op", op]).is_ok(), "{op}");
        }
        assert!(parse(&["--op", "cube"]).is_err());
    }

    #[test]
    fn bad_options_are_refused_with_the_option_named() {
        let base = parse(&[]).unwrap();
        let cases: Vec<(LoadArgs, &str)> = vec![
            (
                LoadArgs {
                    clients: 0,
                    ..base.clone()
                },
                "--clients",
            ),
            (
                LoadArgs {
                    clients: 9_000,
                    viewers: 2_000,
                    ..base.clone()
                },
                "--viewers",
            ),
            (
                LoadArgs {
                    duration: 0.0,
                    ..base.clone()
                },
                "--duration",
            ),
            (
                LoadArgs {
                    duration: f64::NAN,
                    ..base.clone()
                },
                "--duration",
            ),
            (
                LoadArgs {
                    rate: -1.0,
                    ..base.clone()
                },
                "--rate",
            ),
            (
                LoadArgs {
                    batch: 0,
                    ..base.clone()
                },
                "--batch",
            ),
            (
                LoadArgs {
                    batch: MAX_OPS_PER_BATCH + 1,
                    ..base.clone()
                },
                "--batch",
            ),
            (
                LoadArgs {
                    op: OpKind::Sphere,
                    radius: 0.0,
                    ..base.clone()
                },
                "--radius",
            ),
        ];
        for (args, option) in cases {
            let err = args.check().expect_err(option).to_string();
            assert!(err.contains(option), "{option}: {err}");
        }
        // A zero radius only matters to spheres.
        let voxel = LoadArgs {
            radius: 0.0,
            ..base
        };
        assert!(voxel.check().is_ok());
    }

    #[test]
    fn region_syntax() {
        assert_eq!("all".parse::<RegionSpec>(), Ok(RegionSpec::default()));
        assert_eq!(
            "disjoint".parse::<RegionSpec>(),
            Ok(RegionSpec {
                area: None,
                disjoint: true
            })
        );
        assert_eq!(
            " 1, 2,3,4,5,6 ".parse::<RegionSpec>(),
            Ok(RegionSpec {
                area: Some(VoxelBox {
                    min: [1, 2, 3],
                    max: [4, 5, 6]
                }),
                disjoint: false
            })
        );
        for bad in [
            "",
            "some",
            "1,2,3",
            "1,2,3,4,5,6,7",
            "1,2,3,4,5,x",
            "-1,0,0,1,1,1",
            "disjoint:",
        ] {
            assert!(
                matches!(bad.parse::<RegionSpec>(), Err(OptionError::RegionSyntax(_))),
                "{bad:?}"
            );
        }
        assert_eq!(
            "0,9,0,5,3,5".parse::<RegionSpec>(),
            Err(OptionError::RegionInverted {
                axis: 'y',
                min: 9,
                max: 3
            })
        );
    }

    #[test]
    fn plan_checks_the_scene_and_the_server_limits() {
        let limits = Limits::default();
        let size = [128, 64, 128];
        let mut args = parse(&["--clients", "4"]).unwrap();
        let areas = args.plan(size, &limits).unwrap();
        assert_eq!(areas, vec![VoxelBox::scene(size); 4]);

        args.region = "0,0,0,127,64,127".parse().unwrap();
        assert!(matches!(
            args.plan(size, &limits),
            Err(OptionError::RegionOutside { .. })
        ));

        args.region = RegionSpec::default();
        args.batch = limits.max_ops_per_batch + 1;
        let err = args.plan(size, &limits).unwrap_err();
        assert_eq!(
            err,
            OptionError::Batch {
                batch: limits.max_ops_per_batch + 1,
                max: limits.max_ops_per_batch
            }
        );

        args.batch = 16;
        args.op = OpKind::Sphere;
        args.radius = limits.max_brush_radius + 1.0;
        assert!(matches!(
            args.plan(size, &limits),
            Err(OptionError::Radius { .. })
        ));

        // 128 voxels cannot hold 4 slabs each 2·30 + 1 wide.
        args.radius = 30.0;
        args.region = "disjoint".parse().unwrap();
        assert!(matches!(
            args.plan(size, &limits),
            Err(OptionError::RegionTooNarrow { need: 61, .. })
        ));
        args.radius = 4.0;
        let slabs = args.plan(size, &limits).unwrap();
        assert_eq!(slabs.len(), 4);
        // Sphere centres stay `radius` inside each 32-voxel slab.
        assert_eq!(slabs[0].min[0], 4);
        assert_eq!(slabs[0].max[0], 27);
        assert_eq!(slabs[3].max[0], 123);
    }

    #[test]
    fn disjoint_slabs_cover_the_area_once_and_follow_bricks_when_wide() {
        let area = VoxelBox {
            min: [3, 0, 10],
            max: [300, 20, 50],
        };
        for n in [1, 2, 3, 7, 16, 18, 100, 298] {
            let slabs = split(area, n, 0).unwrap();
            assert_eq!(slabs.len(), n as usize);
            let mut next = area.min[0];
            for s in &slabs {
                assert_eq!(
                    s.min[0], next,
                    "n={n}: slabs must tile x with no gap or overlap"
                );
                assert!(s.max[0] >= s.min[0]);
                assert_eq!((s.min[1], s.max[1], s.min[2], s.max[2]), (0, 20, 10, 50));
                next = s.max[0] + 1;
            }
            assert_eq!(next, area.max[0] + 1, "n={n}");
            if 298 / n >= 16 {
                for s in &slabs[1..] {
                    assert_eq!(s.min[0] % 8, 0, "n={n}: inner borders on brick boundaries");
                }
            }
        }
        assert!(matches!(
            split(area, 299, 0),
            Err(OptionError::RegionTooNarrow { axis: 'x', .. })
        ));
        // The longer horizontal axis is cut, never y.
        let tall = VoxelBox {
            min: [0, 0, 0],
            max: [15, 511, 63],
        };
        let slabs = split(tall, 4, 0).unwrap();
        assert_eq!(slabs[1].min[2], 16);
        assert_eq!(slabs[1].max[1], 511);
    }
}
