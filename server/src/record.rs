//! The edit log's record: what one sequence number did to a scene, in a durable format of its
//! own rather than the wire's `Vec<EditOp>`, so that the log can hold more than edit ops (an
//! undo writes whole bricks) and the wire can change without rewriting stores.
//!
//! Format: `[0, VERSION]` then the bincode of [`LogRecord`]. Version 3 added
//! [`LogRecord::Revert`]; version 2 records (no such variant) read as before. Stores written by brickcast 0.1
//! hold a bare bincode `Vec<EditOp>`; those are read as [`LogRecord::Ops`] with no user. They
//! never start with a 0 byte followed by more bytes (a 0 length prefix is an empty list, and
//! only batches that applied something were logged), so the two cannot be confused.

use brickcast_protocol::BrickMap;
use brickcast_protocol::wire::{EditOp, Limits, UserId};
use serde::{Deserialize, Serialize};

use crate::scene::history::{Image, Step, apply_after, write_bricks};

/// Replay cost of one brick of a `Revert`, in single-voxel ops (the snapshot budget's unit):
/// read, merged and written a mask word at a time, a brick costs about as much as a dozen
/// single-voxel ops.
pub const REVERT_BRICK_OPS: u64 = 16;

/// The version of [`LogRecord`] written now.
const VERSION: u8 = 3;
/// The oldest version read (an older `[0, v]` prefix is not a record of this format).
const FIRST_VERSION: u8 = 2;

/// What one logged sequence did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum LogRecord {
    /// An edit message's ops that applied, replayed through the same `apply_op` as live edits.
    Ops { user: UserId, ops: Vec<EditOp> },
    /// An undo or redo: the bricks it wrote (linear cell → contents, `None`: emptied), replayed
    /// as written. The history that decided them is not needed to replay.
    Restore {
        user: UserId,
        redo: bool,
        bricks: Vec<(u32, Option<Image>)>,
    },
    /// An undo or redo as the step it recorded (the stored form the opposite stack holds,
    /// `scene::step`): replayed by setting every voxel it changed to its after-value. A
    /// box's undo is a few hundred KB here where its bricks were tens of MB. Written since
    /// version 3.
    Revert {
        user: UserId,
        redo: bool,
        /// Bricks the step changed (replay cost accounting without decoding it).
        bricks: u32,
        step: Vec<u8>,
    },
}

impl LogRecord {
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), String> {
        out.clear();
        out.extend_from_slice(&[0, VERSION]);
        bincode::serde::encode_into_std_write(self, out, bincode::config::standard())
            .map(|_| ())
            .map_err(|e| e.to_string())
    }

    pub fn decode(bytes: &[u8]) -> Result<LogRecord, String> {
        let config = bincode::config::standard();
        match bytes {
            [0, version, body @ ..] if (FIRST_VERSION..=VERSION).contains(version) => {
                let (record, read): (LogRecord, usize) =
                    bincode::serde::decode_from_slice(body, config).map_err(|e| e.to_string())?;
                if read != body.len() {
                    return Err(format!("{} bytes after the record", body.len() - read));
                }
                Ok(record)
            }
            [0, version, _, ..] => Err(format!(
                "log record version {version}, this server reads up to {VERSION}"
            )),
            _ => {
                let (ops, _): (Vec<EditOp>, usize) =
                    bincode::serde::decode_from_slice(bytes, config).map_err(|e| e.to_string())?;
                Ok(LogRecord::Ops { user: 0, ops })
            }
        }
    }

    /// The limits a replay runs with: no brush limits, since every logged op was validated
    /// against the server's limits when it was accepted and must apply again even if those
    /// limits were lowered since. Every store replays with these.
    pub fn replay_limits() -> Limits {
        Limits {
            max_brush_radius: f32::MAX,
            max_box_extent: u32::MAX,
            ..Limits::hard_caps()
        }
    }

    /// Replays the record onto `map` (stamped with the record's sequence by the caller).
    pub fn replay(&self, map: &mut BrickMap, limits: &Limits) -> Result<(), String> {
        match self {
            LogRecord::Ops { ops, .. } => ops.iter().try_for_each(|op| {
                brickcast_protocol::apply::apply_op(map, op, limits)
                    .map(|_| ())
                    .map_err(|e| e.to_string())
            }),
            LogRecord::Restore { bricks, .. } => write_bricks(map, bricks),
            LogRecord::Revert { step, .. } => apply_after(map, &Step::decode(step)?),
        }
    }

    /// Ops in the record, or what replaying it costs in ops (for replay cost accounting).
    pub fn op_count(&self) -> usize {
        match self {
            LogRecord::Ops { ops, .. } => ops.len(),
            LogRecord::Restore { bricks, .. } => bricks.len(),
            LogRecord::Revert { bricks, .. } => (u64::from(*bricks) * REVERT_BRICK_OPS) as usize,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::Colour;

    #[test]
    fn records_round_trip_and_old_logs_still_read() {
        let ops = vec![EditOp::Set {
            pos: [1, 2, 3],
            colour: Colour::WHITE,
        }];
        let mut buf = Vec::new();
        for record in [
            LogRecord::Ops {
                user: 9,
                ops: ops.clone(),
            },
            LogRecord::Restore {
                user: 9,
                redo: true,
                bricks: vec![(4, None)],
            },
            LogRecord::Revert {
                user: 9,
                redo: false,
                bricks: 0,
                step: Step::default().encode(),
            },
        ] {
            record.encode(&mut buf).unwrap();
            assert_eq!(LogRecord::decode(&buf).unwrap(), record);
        }
        // Version 2 wrote the same bincode for the variants it had.
        let restore = LogRecord::Restore {
            user: 3,
            redo: false,
            bricks: vec![(1, None)],
        };
        restore.encode(&mut buf).unwrap();
        buf[1] = 2;
        assert_eq!(LogRecord::decode(&buf).unwrap(), restore);
        let old = bincode::serde::encode_to_vec(&ops, bincode::config::standard()).unwrap();
        assert_eq!(
            LogRecord::decode(&old).unwrap(),
            LogRecord::Ops { user: 0, ops }
        );
        assert!(
            LogRecord::decode(&[0, 4, 1])
                .unwrap_err()
                .contains("version 4")
        );
        assert!(LogRecord::decode(&[0, VERSION, 7, 7, 7]).is_err());
        assert!(LogRecord::decode(&[]).is_err());
    }
}
