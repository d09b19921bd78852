//! The edit log's record: what one sequence number did to a scene, in a durable format of its
//! own rather than the wire's `Vec<EditOp>`, so that the log can hold more than edit ops (an
//! undo writes whole bricks) and the wire can change without rewriting stores.
//!
//! Format: `[0, VERSION]` then the bincode of [`LogRecord`]. Version 3 added
//! [`LogRecord::Revert`]; in version 5 ops may be the editing tools (protocol 6: fills,
//! extrudes, spans; appended variants, so older records read as before); in version 7 they may
//! set a swatch of the scene's palette or copy (protocol 7, `EditOp::Swatch`, `EditOp::Copy`),
//! and a paste is its own record, [`LogRecord::Paste`]; version 9 adds [`LogRecord::Rewind`]
//! (a restore to an earlier sequence); version 2 records
//! (no `Revert`) read as before too. (4, 6 and 8 are not versions: they tag the turn rows below
//! as they were before versions 5, 7 and 9, now tagged 10, so a build from before refuses the
//! new rows by their version instead of failing inside one.) Stores written by brickcast 0.1
//! hold a bare bincode `Vec<EditOp>`; those are read as [`LogRecord::Ops`] with no user. They
//! never start with a 0 byte followed by more bytes (a 0 length prefix is an empty list, and
//! only batches that applied something were logged), so the two cannot be confused.
//!
//! **A turn in one row** (issue #31): a redb row costs about a microsecond to insert, so a turn
//! of a thousand one-voxel messages spent more on rows than on the edits. Since store format 3
//! a turn's records (consecutive sequences) are one row keyed by the *last* sequence:
//! `[0, BATCH]`, the count (u32 LE), then the bincode of the records in order. A row keyed by a
//! turn's last sequence keeps every rule of the log as it was: snapshots happen between turns,
//! so trimming `..=seq` never splits a row, and "the log holds an entry past the snapshot" is
//! still a look at the last key. Rows of one record are written as before ([`read_row`] reads
//! both).

use brickcast_protocol::BrickMap;
use brickcast_protocol::wire::{EditOp, Limits, UserId};
use serde::{Deserialize, Serialize};

use crate::envelope::Format;
use crate::scene::history::{Image, Step, apply_after, write_bricks};

/// Replay cost of one brick of a `Revert`, in single-voxel ops (the snapshot budget's unit):
/// read, merged and written a mask word at a time, a brick costs about as much as a dozen
/// single-voxel ops.
pub const REVERT_BRICK_OPS: u64 = 16;

/// The version of [`LogRecord`] written now.
const VERSION: u8 = 9;
/// The oldest version read (an older `[0, v]` prefix is not a record of this format).
const FIRST_VERSION: u8 = 2;
/// The prefix of a row holding a turn's records (records of version [`VERSION`]).
const BATCH: u8 = 10;
/// The prefix such rows had with records of version 7.
const BATCH_V7: u8 = 8;
/// The prefix such rows had with records of version 5.
const BATCH_V5: u8 = 6;
/// The prefix such rows had with records of version 3.
const OLD_BATCH: u8 = 4;
/// A record's (or a row's) bincode after its `[0, …]` header: at most 1 GiB.
const RECORD: Format<{ 1 << 30 }> = Format::new("log record", b"");

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
    /// A paste (`EditOp::Paste`) as the step it made: replayed like a `Revert`, by setting
    /// every voxel it changed to its after-value, so replay needs no clipboard. Version 7.
    Paste {
        user: UserId,
        bricks: u32,
        step: Vec<u8>,
    },
    /// A restore of a box to how it was at sequence `to` (`EditOp::Restore`), as the step it
    /// made: replayed like a `Paste`, so replay needs no past. Version 9.
    Rewind {
        user: UserId,
        to: u64,
        bricks: u32,
        step: Vec<u8>,
    },
}

impl LogRecord {
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), String> {
        out.clear();
        out.extend_from_slice(&[0, VERSION]);
        RECORD.append(self, out).map_err(|e| e.to_string())
    }

    pub fn decode(bytes: &[u8]) -> Result<LogRecord, String> {
        match bytes {
            [0, version, body @ ..]
                if (FIRST_VERSION..=VERSION).contains(version)
                    && *version != OLD_BATCH
                    && *version != BATCH_V5
                    && *version != BATCH_V7 =>
            {
                RECORD.decode_body(body).map_err(|e| e.to_string())
            }
            [0, version, _, ..] => Err(format!(
                "log record version {version}, this server reads up to {VERSION}"
            )),
            _ => {
                let (ops, _): (Vec<EditOp>, usize) =
                    RECORD.decode_prefix(bytes).map_err(|e| e.to_string())?;
                Ok(LogRecord::Ops { user: 0, ops })
            }
        }
    }

    /// One row of the log: `records` (consecutive sequences, at least one) as one batch, keyed
    /// by the last sequence. A single record is written as itself.
    pub fn encode_batch(records: &[(u64, LogRecord)], out: &mut Vec<u8>) -> Result<(), String> {
        if let [(_, only)] = records {
            return only.encode(out);
        }
        if records.windows(2).any(|w| w[1].0 != w[0].0.wrapping_add(1)) || records.is_empty() {
            return Err("a log row holds consecutive sequences".into());
        }
        let count = u32::try_from(records.len()).map_err(|_| "too many records for one row")?;
        out.clear();
        out.extend_from_slice(&[0, BATCH]);
        out.extend_from_slice(&count.to_le_bytes());
        for (_, record) in records {
            RECORD.append(record, out).map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    /// How many sequences the row holds (1 for a single record), without decoding it.
    pub fn row_len(bytes: &[u8]) -> u64 {
        match bytes {
            [0, BATCH | BATCH_V7 | BATCH_V5 | OLD_BATCH, a, b, c, d, ..] => {
                u64::from(u32::from_le_bytes([*a, *b, *c, *d]))
            }
            _ => 1,
        }
    }

    /// The records of the log row keyed `key`, with their sequences, in order.
    pub fn read_row(key: u64, bytes: &[u8]) -> Result<Vec<(u64, LogRecord)>, String> {
        let [
            0,
            BATCH | BATCH_V7 | BATCH_V5 | OLD_BATCH,
            a,
            b,
            c,
            d,
            body @ ..,
        ] = bytes
        else {
            return Ok(vec![(key, LogRecord::decode(bytes)?)]);
        };
        let mut body: &[u8] = body;
        let count = u64::from(u32::from_le_bytes([*a, *b, *c, *d]));
        if count == 0 || count > key {
            return Err(format!("a row of {count} records keyed {key}"));
        }
        let mut out = Vec::with_capacity(count.min(1 << 16) as usize);
        for seq in key + 1 - count..=key {
            let (record, read): (LogRecord, usize) = RECORD
                .decode_prefix(body)
                .map_err(|e| format!("record {seq} of the row: {e}"))?;
            body = &body[read..];
            out.push((seq, record));
        }
        if !body.is_empty() {
            return Err(format!("{} bytes after the row's records", body.len()));
        }
        Ok(out)
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
            LogRecord::Revert { step, .. }
            | LogRecord::Paste { step, .. }
            | LogRecord::Rewind { step, .. } => apply_after(map, &Step::decode(step)?),
        }
    }

    /// Ops in the record, or what replaying it costs in ops (for replay cost accounting).
    pub fn op_count(&self) -> usize {
        match self {
            LogRecord::Ops { ops, .. } => ops.len(),
            LogRecord::Restore { bricks, .. } => bricks.len(),
            LogRecord::Revert { bricks, .. }
            | LogRecord::Paste { bricks, .. }
            | LogRecord::Rewind { bricks, .. } => (u64::from(*bricks) * REVERT_BRICK_OPS) as usize,
        }
    }

    /// Who it was.
    pub fn user(&self) -> UserId {
        match self {
            LogRecord::Ops { user, .. }
            | LogRecord::Restore { user, .. }
            | LogRecord::Revert { user, .. }
            | LogRecord::Paste { user, .. }
            | LogRecord::Rewind { user, .. } => *user,
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
            LogRecord::Ops {
                user: 0,
                ops: ops.clone()
            }
        );
        assert!(
            LogRecord::decode(&[0, 11, 1])
                .unwrap_err()
                .contains("version 11")
        );
        // The tags of turn rows are not record versions.
        for tag in [OLD_BATCH, BATCH_V5, BATCH_V7, BATCH] {
            assert!(LogRecord::decode(&[0, tag, 1]).is_err(), "{tag}");
        }
        // A swatch (version 7) round-trips.
        let swatch = LogRecord::Ops {
            user: 4,
            ops: vec![EditOp::Swatch {
                index: 31,
                colour: Colour(0x1234),
            }],
        };
        swatch.encode(&mut buf).unwrap();
        assert_eq!(&buf[..2], &[0, VERSION]);
        assert_eq!(LogRecord::decode(&buf).unwrap(), swatch);
        // Written by version 7, it reads the same.
        buf[1] = 7;
        assert_eq!(LogRecord::decode(&buf).unwrap(), swatch);
        // A paste (version 7) is its step: it round-trips, and replays to the pasted scene.
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        let before = map.clone();
        map.begin_journal();
        map.set([3, 4, 5], Colour(77));
        map.set([20, 4, 5], Colour(78));
        let step = Step::from_journal(&mut map);
        let paste = LogRecord::Paste {
            user: 4,
            bricks: step.bricks.len() as u32,
            step: step.encode(),
        };
        paste.encode(&mut buf).unwrap();
        let back = LogRecord::decode(&buf).unwrap();
        assert_eq!(back, paste);
        let mut replayed = before.clone();
        back.replay(&mut replayed, &LogRecord::replay_limits())
            .unwrap();
        assert_eq!(replayed.content_hash(), map.content_hash());
        assert_eq!(back.op_count(), 2 * REVERT_BRICK_OPS as usize);
        // A restore (version 9) is its step too, and names the sequence it went back to.
        let rewind = LogRecord::Rewind {
            user: 5,
            to: 17,
            bricks: step.bricks.len() as u32,
            step: step.encode(),
        };
        rewind.encode(&mut buf).unwrap();
        let back = LogRecord::decode(&buf).unwrap();
        assert_eq!(back, rewind);
        assert_eq!(back.user(), 5);
        let mut replayed = before;
        back.replay(&mut replayed, &LogRecord::replay_limits())
            .unwrap();
        assert_eq!(replayed.content_hash(), map.content_hash());
        // A version-3 record of an op that version 5 also has reads the same.
        LogRecord::Ops {
            user: 9,
            ops: ops.clone(),
        }
        .encode(&mut buf)
        .unwrap();
        buf[1] = 3;
        assert_eq!(
            LogRecord::decode(&buf).unwrap(),
            LogRecord::Ops {
                user: 9,
                ops: ops.clone()
            }
        );
        assert!(LogRecord::decode(&[0, VERSION, 7, 7, 7]).is_err());
        assert!(LogRecord::decode(&[]).is_err());
    }

    #[test]
    fn a_turn_is_one_row_and_single_records_read_as_before() {
        let set = |x| LogRecord::Ops {
            user: 2,
            ops: vec![EditOp::Set {
                pos: [x, 0, 0],
                colour: Colour::WHITE,
            }],
        };
        let turn: Vec<(u64, LogRecord)> = (0..5).map(|i| (41 + i, set(i as u32))).collect();
        let mut row = Vec::new();
        LogRecord::encode_batch(&turn, &mut row).unwrap();
        assert_eq!(LogRecord::row_len(&row), 5);
        assert_eq!(LogRecord::read_row(45, &row).unwrap(), turn);
        // Rows written before record versions 5, 7 and 9 (tagged 4, 6 and 8) read the same; a
        // build from before reads the new tag as a record version it does not know.
        assert_eq!(&row[..2], &[0, BATCH]);
        for tag in [OLD_BATCH, BATCH_V5, BATCH_V7] {
            let mut old = row.clone();
            old[1] = tag;
            assert_eq!(LogRecord::read_row(45, &old).unwrap(), turn);
            assert_eq!(LogRecord::row_len(&old), 5);
        }
        // A single record is the record itself, as rows were before.
        LogRecord::encode_batch(&turn[..1], &mut row).unwrap();
        assert_eq!(LogRecord::decode(&row).unwrap(), turn[0].1);
        assert_eq!(LogRecord::read_row(41, &row).unwrap(), turn[..1].to_vec());
        assert_eq!(LogRecord::row_len(&row), 1);
        // Gaps, an empty turn, a truncated or padded row, a count past the key: errors.
        let gap = vec![turn[0].clone(), turn[2].clone()];
        assert!(LogRecord::encode_batch(&gap, &mut row).is_err());
        assert!(LogRecord::encode_batch(&[], &mut row).is_err());
        LogRecord::encode_batch(&turn, &mut row).unwrap();
        assert!(LogRecord::read_row(45, &row[..row.len() - 1]).is_err());
        let mut padded = row.clone();
        padded.push(0);
        assert!(LogRecord::read_row(45, &padded).is_err());
        assert!(LogRecord::read_row(3, &row).is_err());
        assert!(LogRecord::read_row(45, &[0, BATCH, 0, 0, 0, 0]).is_err());
    }
}
