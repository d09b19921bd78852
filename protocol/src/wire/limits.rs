//! The per-server limits a client learns in `Welcome`.

use serde::{Deserialize, Serialize};

/// Highest presence rate a server may announce.
pub const MAX_PRESENCE_HZ: u32 = 100;

use super::{MAX_BRICKS_PER_FRAME, MAX_FRAME_BYTES, MAX_OPS_PER_BATCH, MIN_FRAME_BYTES, WireError};

/// The limits a server announces in `Welcome` and then enforces.
///
/// The hard caps in [`crate::wire`] bound what the protocol can ever carry; these are the
/// (usually tighter) values one server chose for its hardware and audience. Sending them lets a
/// client size its edit batches and reject oversized server frames with the same numbers the
/// server uses, instead of discovering them through errors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    /// Largest websocket frame either side may send, in bytes.
    pub max_frame_bytes: u32,
    /// Most ops in one `Edit` batch.
    pub max_ops_per_batch: u32,
    /// Most bricks in one `BrickBlob` (one `SyncBatch` or `Delta`).
    pub max_bricks_per_frame: u32,
    /// Largest sphere brush radius, in voxels.
    pub max_brush_radius: f32,
    /// Largest box edge, in voxels, per axis.
    pub max_box_extent: u32,
    /// Voxel edits one client may request per second before `RateLimited`.
    pub max_edits_per_second: u32,
    /// Most undo steps the server keeps per user (oldest dropped first).
    pub max_undo_steps: u32,
    /// Most bytes of history (compressed before/after images of the bricks each step changed)
    /// the server keeps per user (oldest dropped first; the newest step is always kept).
    pub max_undo_bytes: u64,
    /// Presence messages a client may send per second, and presence frames the server sends.
    pub presence_hz: u32,
    /// Most voxels one fill or extrude may change (its op's `limit` is at most this).
    pub max_tool_voxels: u32,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_frame_bytes: 4 << 20,
            max_ops_per_batch: 4096,
            max_bricks_per_frame: 4096,
            max_brush_radius: 64.0,
            max_box_extent: 256,
            max_edits_per_second: 200_000,
            max_undo_steps: 256,
            max_undo_bytes: 64 << 20,
            presence_hz: 20,
            // Charged `TOOL_VOXEL_WORK` each: half of a server's default work per edit.
            max_tool_voxels: 1 << 19,
        }
    }
}

impl Limits {
    /// The most permissive limits the protocol allows: for a client that has not seen `Welcome`
    /// yet and will accept anything a conforming server can send, and for checking what a
    /// sender produces against the hard caps.
    pub fn hard_caps() -> Self {
        Limits {
            max_frame_bytes: MAX_FRAME_BYTES as u32,
            max_ops_per_batch: MAX_OPS_PER_BATCH,
            max_bricks_per_frame: MAX_BRICKS_PER_FRAME,
            max_brush_radius: f32::MAX,
            max_box_extent: u32::MAX,
            max_edits_per_second: u32::MAX,
            max_undo_steps: u32::MAX,
            max_undo_bytes: u64::MAX,
            presence_hz: MAX_PRESENCE_HZ,
            max_tool_voxels: u32::MAX,
        }
    }

    /// Refuses limits the protocol cannot honour: values above the hard caps, zero counts that
    /// would make every edit or sync impossible, a frame too small for one brick, and a brush
    /// radius that is not a positive finite number.
    pub fn validate(&self) -> Result<(), WireError> {
        let invalid = |field, value: f64, reason| {
            Err(WireError::InvalidLimit {
                field,
                value,
                reason,
            })
        };
        let frame = self.max_frame_bytes;
        if frame < MIN_FRAME_BYTES || frame as usize > MAX_FRAME_BYTES {
            return invalid(
                "max_frame_bytes",
                frame.into(),
                "must be between 64 KiB and 16 MiB",
            );
        }
        if self.max_ops_per_batch == 0 || self.max_ops_per_batch > MAX_OPS_PER_BATCH {
            return invalid(
                "max_ops_per_batch",
                self.max_ops_per_batch.into(),
                "must be between 1 and MAX_OPS_PER_BATCH (8192)",
            );
        }
        if self.max_bricks_per_frame == 0 || self.max_bricks_per_frame > MAX_BRICKS_PER_FRAME {
            return invalid(
                "max_bricks_per_frame",
                self.max_bricks_per_frame.into(),
                "must be between 1 and MAX_BRICKS_PER_FRAME (8192)",
            );
        }
        let radius = self.max_brush_radius;
        if !radius.is_finite() || radius <= 0.0 {
            return invalid(
                "max_brush_radius",
                radius.into(),
                "must be a finite number above 0",
            );
        }
        if self.max_box_extent == 0 {
            return invalid("max_box_extent", 0.0, "must be at least 1");
        }
        if self.max_edits_per_second == 0 {
            return invalid("max_edits_per_second", 0.0, "must be at least 1");
        }
        if self.max_tool_voxels == 0 {
            return invalid("max_tool_voxels", 0.0, "must be at least 1");
        }
        if self.presence_hz == 0 || self.presence_hz > MAX_PRESENCE_HZ {
            return invalid(
                "presence_hz",
                self.presence_hz.into(),
                "must be between 1 and 100",
            );
        }
        Ok(())
    }

    /// The frame bound actually applied: never above the hard cap, even if a caller hands in
    /// limits it has not validated.
    pub(crate) fn frame_cap(&self) -> usize {
        (self.max_frame_bytes as usize).min(MAX_FRAME_BYTES)
    }

    /// Same idea for the brick count.
    pub(crate) fn brick_cap(&self) -> u32 {
        self.max_bricks_per_frame.min(MAX_BRICKS_PER_FRAME)
    }

    /// Same idea for the op count.
    pub(crate) fn ops_cap(&self) -> u32 {
        self.max_ops_per_batch.min(MAX_OPS_PER_BATCH)
    }
}
