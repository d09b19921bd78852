//! The lighting options `brickcast render` and `brickcast view` share.

use anyhow::{Result, anyhow};
use brickcast_protocol::Lighting;

/// How a frame is lit (defaults: `Lighting::default()`, which shows shape indoors and out).
#[derive(Debug, Clone, clap::Args)]
pub struct LightArgs {
    /// Direction towards the sun, "x,y,z" (any length; y is up).
    #[arg(long, value_parser = crate::light::parse_vec3)]
    pub sun: Option<[f32; 3]>,
    /// Sun strength (0 turns it off).
    #[arg(long)]
    pub sun_strength: Option<f32>,
    /// Sky light strength.
    #[arg(long)]
    pub sky: Option<f32>,
    /// Strength of a light at the camera (0 turns it off; helps fully enclosed scenes).
    #[arg(long)]
    pub headlight: Option<f32>,
    /// Exposure before tone mapping (above 1 brightens).
    #[arg(long)]
    pub exposure: Option<f32>,
    /// No shadow rays: the sun lights every face turned to it.
    #[arg(long)]
    pub no_shadows: bool,
    /// No ambient occlusion.
    #[arg(long)]
    pub no_ao: bool,
}

impl LightArgs {
    /// The lighting these options ask for, checked.
    pub fn lighting(&self) -> Result<Lighting> {
        let d = Lighting::default();
        Lighting {
            sun: self.sun.unwrap_or(d.sun),
            sun_strength: self.sun_strength.unwrap_or(d.sun_strength),
            sky: self.sky.unwrap_or(d.sky),
            headlight: self.headlight.unwrap_or(d.headlight),
            exposure: self.exposure.unwrap_or(d.exposure),
            shadows: !self.no_shadows,
            ao: !self.no_ao,
        }
        .checked()
        .map_err(|e| anyhow!("lighting: {e}"))
    }
}

/// Parses "x,y,z" into three finite numbers.
pub fn parse_vec3(text: &str) -> Result<[f32; 3], String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(format!("expected x,y,z, got {text:?}"));
    };
    let parse = |s: &str| {
        s.parse::<f32>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("{s:?} is not a finite number"))
    };
    Ok([parse(x)?, parse(y)?, parse(z)?])
}
