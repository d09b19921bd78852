//! Arbitrary bytes into every decoder that reads from the network.
//!
//! Besides "never panics", checks that whatever decodes re-encodes, and that the re-encoded
//! frame decodes to the same frame again (compared as bytes, since decoded edit ops may hold NaN).
//!
//! Run with `cargo +nightly fuzz run decode` from `protocol/`.

#![no_main]

use brickcast_protocol::wire::{
    BrickBlob, Limits, MAX_BRICKS_PER_FRAME, ServerMsg, decode_client, decode_server,
    encode_client, encode_server,
};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for limits in [Limits::default(), Limits::hard_caps()] {
        if let Ok(msg) = decode_client(data, &limits) {
            let bytes = encode_client(&msg).expect("a decoded client message re-encodes");
            let again = decode_client(&bytes, &limits).expect("a re-encoded message decodes");
            assert_eq!(encode_client(&again).ok(), Some(bytes));
        }
        if let Ok(msg) = decode_server(data, &limits) {
            let bytes = encode_server(&msg).expect("a decoded server message re-encodes");
            let again = decode_server(&bytes, &limits).expect("a re-encoded message decodes");
            assert_eq!(encode_server(&again).ok(), Some(bytes));
            if let ServerMsg::SyncBatch { bricks, .. } | ServerMsg::Delta { bricks, .. } = &msg {
                check_blob(bricks, limits.max_bricks_per_frame);
            }
        }
    }

    // The same bytes as a blob: an 8-byte header (count, raw_len), then the compressed data.
    let Some((count, rest)) = data.split_first_chunk::<4>() else {
        return;
    };
    let Some((raw_len, payload)) = rest.split_first_chunk::<4>() else {
        return;
    };
    let count = u32::from_le_bytes(*count);
    let blob = BrickBlob {
        count,
        raw_len: u32::from_le_bytes(*raw_len),
        data: payload.to_vec(),
    };
    check_blob(&blob, MAX_BRICKS_PER_FRAME);

    // Random bytes are almost never a zstd frame; to reach the layout checks, also treat the
    // payload as the raw layout and compress it honestly, with a small brick count.
    if let Ok(data) = zstd::bulk::compress(payload, 1) {
        let count = count % 16;
        let blob = BrickBlob {
            count,
            raw_len: payload.len() as u32,
            data,
        };
        check_blob(&blob, MAX_BRICKS_PER_FRAME);
    }
});

fn check_blob(blob: &BrickBlob, max_bricks: u32) {
    if let Ok(bricks) = blob.decode(max_bricks) {
        assert_eq!(bricks.len(), blob.count as usize);
        assert!(bricks.iter().all(|b| b.is_consistent()));
        let again = BrickBlob::encode(&bricks, 1).expect("decoded bricks re-encode");
        assert_eq!(
            again.decode(max_bricks).expect("re-encoded blob decodes"),
            bricks
        );
    }
}
