//! Round trips, hostile input and limits of the wire format.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use brickcast_protocol::brick::{BrickData, EMPTY_MASK, FULL_MASK, Mask, popcount};
use brickcast_protocol::colour::Colour;
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::*;
use proptest::collection::vec;
use proptest::prelude::*;

// ---------------------------------------------------------------------------------------------
// Allocation probe: the largest single allocation made by the current thread, so tests can
// check that hostile headers are refused before they size a buffer (tests run on many threads,
// so a global counter would see the neighbours).

struct PeakAlloc;

thread_local! {
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn note(size: usize) {
    let _ = PEAK.try_with(|p| p.set(p.get().max(size)));
}

unsafe impl GlobalAlloc for PeakAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOC: PeakAlloc = PeakAlloc;

/// Runs `f` and returns its result with the largest single allocation it made.
fn peak_alloc<T>(f: impl FnOnce() -> T) -> (T, usize) {
    PEAK.with(|p| p.set(0));
    let out = f();
    (out, PEAK.with(|p| p.get()))
}

// ---------------------------------------------------------------------------------------------
// Strategies.

fn colour() -> impl Strategy<Value = Colour> {
    any::<u16>().prop_map(Colour)
}

fn finite() -> impl Strategy<Value = f32> {
    use proptest::num::f32 as f;
    f::POSITIVE | f::NEGATIVE | f::NORMAL | f::SUBNORMAL | f::ZERO
}

fn vec3() -> impl Strategy<Value = [f32; 3]> {
    [finite(), finite(), finite()]
}

fn pos() -> impl Strategy<Value = [u32; 3]> {
    any::<[u32; 3]>()
}

fn brush_mode() -> impl Strategy<Value = BrushMode> {
    prop_oneof![
        Just(BrushMode::Fill),
        Just(BrushMode::Erase),
        Just(BrushMode::Paint)
    ]
}

fn ray_action() -> impl Strategy<Value = RayAction> {
    prop_oneof![
        Just(RayAction::Remove),
        colour().prop_map(|colour| RayAction::Place { colour }),
        colour().prop_map(|colour| RayAction::Paint { colour }),
        (brush_mode(), finite(), colour()).prop_map(|(mode, radius, colour)| RayAction::Sphere {
            mode,
            radius,
            colour
        }),
        (colour(), any::<u32>()).prop_map(|(colour, limit)| RayAction::Fill { colour, limit }),
        (any::<bool>(), any::<u32>()).prop_map(|(out, limit)| RayAction::Extrude { out, limit }),
    ]
}

fn edit_op() -> impl Strategy<Value = EditOp> {
    prop_oneof![
        (pos(), colour()).prop_map(|(pos, colour)| EditOp::Set { pos, colour }),
        pos().prop_map(|pos| EditOp::Clear { pos }),
        (pos(), colour()).prop_map(|(pos, colour)| EditOp::Paint { pos, colour }),
        (vec3(), finite(), brush_mode(), colour()).prop_map(|(centre, radius, mode, colour)| {
            EditOp::Sphere {
                centre,
                radius,
                mode,
                colour,
            }
        }),
        (pos(), pos(), brush_mode(), colour()).prop_map(|(min, max, mode, colour)| EditOp::Box {
            min,
            max,
            mode,
            colour
        }),
        (vec3(), vec3(), ray_action()).prop_map(|(origin, dir, action)| EditOp::Ray {
            origin,
            dir,
            action
        }),
        (
            (vec3(), vec3(), vec3(), vec3()),
            prop_oneof![Just(Shape::Box), Just(Shape::Line)],
            brush_mode(),
            colour(),
            any::<u32>()
        )
            .prop_map(
                |((from, from_dir, to, to_dir), shape, mode, colour, extent)| {
                    EditOp::Span {
                        from,
                        from_dir,
                        to,
                        to_dir,
                        shape,
                        mode,
                        colour,
                        extent,
                    }
                }
            ),
        (any::<u8>(), colour()).prop_map(|(index, colour)| EditOp::Swatch { index, colour }),
        (pos(), pos()).prop_map(|(min, max)| EditOp::Copy { min, max }),
        (pos(), pos(), any::<u8>(), any::<bool>()).prop_map(|(at, size, turns, mirror)| {
            EditOp::Paste {
                at,
                size,
                turns,
                mirror,
            }
        }),
    ]
}

fn client_msg() -> impl Strategy<Value = ClientMsg> {
    prop_oneof![
        (
            any::<u32>(),
            "\\PC{0,16}",
            proptest::option::of("\\PC{0,64}"),
            any::<Option<u64>>()
        )
            .prop_map(|(protocol, name, token, resume_from)| ClientMsg::Hello {
                protocol,
                name,
                token,
                resume_from,
                user: resume_from.unwrap_or(7),
                budget: resume_from.map(|r| Budget {
                    bytes: r.wrapping_mul(3),
                    eye: (r % 2 == 0).then_some([r as f32, 1.5, -2.0]),
                }),
            }),
        (any::<u64>(), vec(edit_op(), 0..48))
            .prop_map(|(client_seq, ops)| ClientMsg::Edit { client_seq, ops }),
        (vec3(), vec3()).prop_map(|(eye, forward)| ClientMsg::Camera { eye, forward }),
        any::<u64>().prop_map(|since| ClientMsg::Resume { since }),
        any::<u64>().prop_map(|nonce| ClientMsg::Ping { nonce }),
        any::<u64>().prop_map(|client_seq| ClientMsg::Undo { client_seq }),
        any::<u64>().prop_map(|client_seq| ClientMsg::Redo { client_seq }),
        (
            proptest::option::of(view()),
            proptest::option::of(cursor()),
            proptest::option::of(selection())
        )
            .prop_map(|(view, cursor, selection)| ClientMsg::Presence {
                view,
                cursor,
                selection
            }),
        "\\PC{0,80}".prop_map(|name| ClientMsg::Rename { name }),
    ]
}

fn view() -> impl Strategy<Value = View> {
    (vec3(), vec3()).prop_map(|(eye, forward)| View { eye, forward })
}

fn cursor() -> impl Strategy<Value = Cursor> {
    (pos(), finite()).prop_map(|(voxel, radius)| Cursor { voxel, radius })
}

fn peer() -> impl Strategy<Value = Peer> {
    (
        any::<u64>(),
        any::<u64>(),
        "\\PC{0,16}",
        colour(),
        prop_oneof![Just(Role::Editor), Just(Role::Viewer)],
    )
        .prop_map(|(id, user, name, colour, role)| Peer {
            id,
            user,
            name,
            colour,
            role,
        })
}

fn peer_state() -> impl Strategy<Value = PeerState> {
    (
        any::<u64>(),
        proptest::option::of(view()),
        proptest::option::of(cursor()),
        proptest::option::of(selection()),
    )
        .prop_map(|(id, view, cursor, selection)| PeerState {
            id,
            view,
            cursor,
            selection,
        })
}

fn selection() -> impl Strategy<Value = Selection> {
    (any::<[u32; 3]>(), any::<[u32; 3]>()).prop_map(|(min, max)| Selection { min, max })
}

fn refusal() -> impl Strategy<Value = Refusal> {
    prop_oneof![
        Just(Refusal::NothingToUndo),
        Just(Refusal::NothingToRedo),
        Just(Refusal::NotAllowed),
        Just(Refusal::RateLimited),
        Just(Refusal::NotFinite),
        any::<u32>().prop_map(|max| Refusal::BadName { max }),
        Just(Refusal::OutOfRange),
        Just(Refusal::NameTaken),
    ]
}

fn brick() -> impl Strategy<Value = BrickData> {
    (any::<[u16; 3]>(), any::<[u64; 8]>(), 0..512u32)
        .prop_flat_map(|(cell, mut mask, forced)| {
            // Never empty: force one bit on.
            mask[(forced / 64) as usize] |= 1 << (forced % 64);
            let n = popcount(&mask) as usize;
            (Just(cell.map(u32::from)), Just(mask), vec(colour(), n))
        })
        .prop_map(|(cell, mask, colours)| BrickData {
            cell,
            mask,
            colours,
        })
}

fn bricks() -> impl Strategy<Value = Vec<BrickData>> {
    vec(brick(), 0..4)
}

fn blob() -> impl Strategy<Value = BrickBlob> {
    bricks().prop_map(|b| BrickBlob::encode(&b, 1).expect("valid bricks encode"))
}

fn limits() -> impl Strategy<Value = Limits> {
    (
        MIN_FRAME_BYTES..=MAX_FRAME_BYTES as u32,
        1..=MAX_OPS_PER_BATCH,
        1..=MAX_BRICKS_PER_FRAME,
        finite().prop_filter("positive", |r| *r > 0.0),
        1..=u32::MAX,
        1..=u32::MAX,
        (
            any::<u32>(),
            any::<u64>(),
            1..=MAX_PRESENCE_HZ,
            1..=u32::MAX,
        ),
    )
        .prop_map(|(f, o, b, r, e, s, (steps, bytes, hz, tool))| Limits {
            max_frame_bytes: f,
            max_ops_per_batch: o,
            max_bricks_per_frame: b,
            max_brush_radius: r,
            max_box_extent: e,
            max_edits_per_second: s,
            max_undo_steps: steps,
            max_undo_bytes: bytes,
            presence_hz: hz,
            max_tool_voxels: tool,
        })
}

fn rejection() -> impl Strategy<Value = Rejection> {
    prop_oneof![
        Just(Rejection::OutOfBounds),
        Just(Rejection::InvalidNumber),
        Just(Rejection::TooLarge),
        Just(Rejection::RayMissed),
        Just(Rejection::NothingToPlace),
        Just(Rejection::NotAllowed),
        Just(Rejection::RateLimited),
        "\\PC{0,32}".prop_map(Rejection::Malformed),
    ]
}

fn error_code() -> impl Strategy<Value = ErrorCode> {
    use ErrorCode::*;
    prop_oneof![
        Just(VersionMismatch),
        Just(Unauthorized),
        Just(NotAllowed),
        Just(MalformedFrame),
        Just(FrameTooLarge),
        Just(RateLimited),
        Just(UnknownScene),
        Just(ShuttingDown),
        Just(Internal),
    ]
}

fn server_msg() -> impl Strategy<Value = ServerMsg> {
    let role = prop_oneof![Just(Role::Editor), Just(Role::Viewer)];
    prop_oneof![
        (
            any::<u32>(),
            "\\PC{0,16}",
            "\\PC{0,16}",
            pos(),
            any::<u64>(),
            role,
            limits(),
            any::<u32>(),
            (peer(), vec(peer(), 0..4)),
        )
            .prop_map(
                |(protocol, server, scene, size, seq, role, limits, total_bricks, (you, peers))| {
                    ServerMsg::Welcome {
                        protocol,
                        server,
                        scene,
                        size,
                        seq,
                        role,
                        limits,
                        total_bricks,
                        you,
                        peers,
                    }
                }
            ),
        (blob(), any::<u32>(), any::<u32>()).prop_map(|(bricks, sent, total)| {
            ServerMsg::SyncBatch {
                bricks,
                sent,
                total,
            }
        }),
        any::<u64>().prop_map(|seq| ServerMsg::SyncDone { seq }),
        (any::<u64>(), any::<u64>(), blob(), vec(pos(), 0..32)).prop_map(
            |(from_seq, to_seq, bricks, removed)| ServerMsg::Delta {
                from_seq,
                to_seq,
                bricks,
                removed
            }
        ),
        any::<u64>().prop_map(|since| ServerMsg::Resync { since }),
        (
            any::<u64>(),
            any::<Option<u64>>(),
            any::<u32>(),
            vec((any::<u32>(), rejection()), 0..16)
        )
            .prop_map(|(client_seq, seq, applied, rejected)| ServerMsg::Ack {
                client_seq,
                seq,
                applied,
                rejected: rejected
                    .into_iter()
                    .map(|(index, reason)| OpRejection { index, reason })
                    .collect(),
            }),
        (error_code(), "\\PC{0,256}")
            .prop_map(|(code, message)| ServerMsg::Error { code, message }),
        any::<u64>().prop_map(|nonce| ServerMsg::Pong { nonce }),
        (
            any::<bool>(),
            vec(peer(), 0..4),
            vec(any::<u64>(), 0..4),
            vec(peer_state(), 0..8)
        )
            .prop_map(|(full, joined, left, states)| ServerMsg::Presence {
                full,
                joined,
                left,
                states
            }),
        (
            any::<u64>(),
            any::<bool>(),
            any::<Option<u64>>(),
            any::<(u64, u64)>(),
            proptest::option::of(refusal())
        )
            .prop_map(|(client_seq, redo, seq, (restored, kept), refused)| {
                ServerMsg::Undone {
                    client_seq,
                    redo,
                    seq,
                    restored,
                    kept,
                    refused,
                }
            }),
        refusal().prop_map(|reason| ServerMsg::Refused { reason }),
        (any::<[u32; 3]>(), any::<u32>(), any::<u32>())
            .prop_map(|(eye, near, top)| ServerMsg::Follow { eye, near, top }),
        (vec(any::<[u32; 3]>(), 0..6), blob())
            .prop_map(|(regions, bricks)| ServerMsg::Regions { regions, bricks }),
        (any::<u32>(), blob(), vec(any::<[u32; 3]>(), 0..6)).prop_map(|(level, bricks, empty)| {
            ServerMsg::Coarse {
                level,
                bricks,
                empty,
            }
        }),
        any::<[u16; 32]>().prop_map(|words| ServerMsg::Palette {
            swatches: Swatches(words.map(Colour)),
        }),
    ]
}

/// A blob header and data that may or may not make sense.
fn hostile_blob() -> impl Strategy<Value = BrickBlob> {
    let count = prop_oneof![0..4u32, any::<u32>()];
    let raw_len = prop_oneof![0..5000u32, any::<u32>()];
    let arbitrary =
        (count, raw_len, vec(any::<u8>(), 0..512)).prop_map(|(count, raw_len, data)| BrickBlob {
            count,
            raw_len,
            data,
        });
    // Real zstd frames of random raw bytes with a plausible header, so decoding gets past
    // decompression into the layout checks.
    let compressed = vec(any::<u8>(), 72..3000).prop_flat_map(|raw| {
        let max_count = (raw.len() / 72) as u32;
        (1..=max_count, Just(raw)).prop_map(|(count, raw)| BrickBlob {
            count,
            raw_len: raw.len() as u32,
            data: zstd::bulk::compress(&raw, 1).expect("compress"),
        })
    });
    prop_oneof![arbitrary, compressed]
}

// ---------------------------------------------------------------------------------------------
// Properties.

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 512,
        failure_persistence: Some(Box::new(
            proptest::test_runner::FileFailurePersistence::WithSource("proptest-regressions"),
        )),
        ..ProptestConfig::default()
    })]

    #[test]
    fn client_messages_round_trip(msg in client_msg()) {
        let bytes = encode_client(&msg).expect("encode");
        prop_assert_eq!(decode_client(&bytes, &Limits::hard_caps()).expect("decode"), msg);
    }

    #[test]
    fn server_messages_round_trip(msg in server_msg()) {
        let bytes = encode_server(&msg).expect("encode");
        prop_assert_eq!(decode_server(&bytes, &Limits::hard_caps()).expect("decode"), msg);
    }

    #[test]
    fn blobs_round_trip(bricks in bricks(), level in -5..6i32) {
        let blob = BrickBlob::encode(&bricks, level).expect("encode");
        prop_assert_eq!(blob.count as usize, bricks.len());
        prop_assert_eq!(blob.decode(MAX_BRICKS_PER_FRAME).expect("decode"), bricks);
    }

    #[test]
    fn arbitrary_bytes_never_panic(bytes in vec(any::<u8>(), 0..4096)) {
        for limits in [Limits::default(), Limits::hard_caps()] {
            let _ = decode_client(&bytes, &limits);
            if let Ok(ServerMsg::SyncBatch { bricks, .. } | ServerMsg::Delta { bricks, .. }) =
                decode_server(&bytes, &limits)
            {
                let _ = bricks.decode(limits.max_bricks_per_frame);
            }
        }
    }

    #[test]
    fn hostile_blobs_never_panic(blob in hostile_blob(), max in prop_oneof![Just(MAX_BRICKS_PER_FRAME), any::<u32>()]) {
        let _ = blob.decode(max);
        let mut calls = 0u32;
        let res = BlobDecoder::new().expect("decoder").for_each(&blob, max, |_| calls += 1);
        match res {
            Ok(n) => prop_assert_eq!(n, calls),
            Err(_) => prop_assert_eq!(calls, 0, "callbacks before an error"),
        }
    }

    #[test]
    fn mangled_client_frames_never_panic(
        msg in client_msg(),
        flips in vec((any::<prop::sample::Index>(), 1..=255u8), 0..8),
        cut in proptest::option::of(any::<prop::sample::Index>()),
    ) {
        let mut bytes = encode_client(&msg).expect("encode");
        mangle(&mut bytes, &flips, cut);
        let _ = decode_client(&bytes, &Limits::hard_caps());
        let _ = decode_client(&bytes, &Limits::default());
    }

    #[test]
    fn mangled_server_frames_never_panic(
        msg in server_msg(),
        flips in vec((any::<prop::sample::Index>(), 1..=255u8), 0..8),
        cut in proptest::option::of(any::<prop::sample::Index>()),
    ) {
        let mut bytes = encode_server(&msg).expect("encode");
        mangle(&mut bytes, &flips, cut);
        for limits in [Limits::default(), Limits::hard_caps()] {
            if let Ok(ServerMsg::SyncBatch { bricks, .. } | ServerMsg::Delta { bricks, .. }) =
                decode_server(&bytes, &limits)
            {
                let _ = bricks.decode(limits.max_bricks_per_frame);
            }
        }
    }

    #[test]
    fn mangled_blob_data_never_panics(
        bricks in vec(brick(), 1..4),
        flips in vec((any::<prop::sample::Index>(), 1..=255u8), 1..8),
    ) {
        let mut blob = BrickBlob::encode(&bricks, 1).expect("encode");
        mangle(&mut blob.data, &flips, None);
        if let Ok(out) = blob.decode(MAX_BRICKS_PER_FRAME) {
            prop_assert_eq!(out.len(), bricks.len());
            prop_assert!(out.iter().all(BrickData::is_consistent));
        }
    }

    #[test]
    fn decoded_ops_re_encode_identically(msg in client_msg()) {
        // Decoding then encoding is the identity on well-formed frames: no field is lost.
        let bytes = encode_client(&msg).expect("encode");
        let back = decode_client(&bytes, &Limits::hard_caps()).expect("decode");
        prop_assert_eq!(encode_client(&back).expect("re-encode"), bytes);
    }
}

fn mangle(
    bytes: &mut Vec<u8>,
    flips: &[(prop::sample::Index, u8)],
    cut: Option<prop::sample::Index>,
) {
    if bytes.is_empty() {
        return;
    }
    for (at, x) in flips {
        let i = at.index(bytes.len());
        bytes[i] ^= x;
    }
    if let Some(cut) = cut {
        bytes.truncate(cut.index(bytes.len()));
    }
}

// ---------------------------------------------------------------------------------------------
// Unit tests.

fn hello() -> ClientMsg {
    ClientMsg::Hello {
        protocol: PROTOCOL_VERSION,
        name: "viewer".into(),
        token: Some("secret".into()),
        resume_from: Some(42),
        user: 1234,
        budget: None,
    }
}

fn solid_brick(cell: [u32; 3], mask: Mask) -> BrickData {
    let n = popcount(&mask) as usize;
    BrickData {
        cell,
        mask,
        colours: vec![Colour(0x1234); n],
    }
}

/// Encodes anything with the wire configuration, bypassing the sender-side checks, to build
/// frames that a buggy or hostile peer could send.
fn raw_frame<T: serde::Serialize>(value: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(value, bincode::config::standard()).expect("raw encode")
}

#[test]
fn hello_carries_the_protocol_version() {
    assert_eq!(PROTOCOL_VERSION, 8);
    let bytes = encode_client(&hello()).expect("encode");
    match decode_client(&bytes, &Limits::default()).expect("decode") {
        ClientMsg::Hello { protocol, .. } => assert_eq!(protocol, PROTOCOL_VERSION),
        other => panic!("decoded {other:?}"),
    }
}

/// A budget's eye orders what the server streams: a non-finite one is refused on decode.
#[test]
fn a_budget_eye_must_be_finite() {
    let mut msg = hello();
    if let ClientMsg::Hello { budget, .. } = &mut msg {
        *budget = Some(Budget {
            bytes: 1 << 28,
            eye: Some([1.0, f32::NAN, 2.0]),
        });
    }
    assert!(matches!(
        decode_client(&raw_frame(&msg), &Limits::default()),
        Err(WireError::NotFinite { .. })
    ));
}

#[test]
fn hello_layout_is_stable() {
    // Variant 0, then the version as a varint: what an old or new server reads first.
    let bytes = encode_client(&hello()).expect("encode");
    assert_eq!(&bytes[..2], &[0, PROTOCOL_VERSION as u8]);
}

#[test]
fn a_future_hello_still_shows_its_version() {
    // Version 3 of `Hello` with a field this version does not know about.
    let future = raw_frame(&(0u32, 3u32, "name", None::<String>, None::<u64>, 5u64, 99u8));
    assert!(decode_client(&future, &Limits::default()).is_err());
    assert_eq!(hello_version(&future), Some(3));
    // Version 1, whose `Hello` had no user id: its version still reads.
    let past = raw_frame(&(0u32, 1u32, "name", None::<String>, None::<u64>));
    assert!(decode_client(&past, &Limits::default()).is_err());
    assert_eq!(hello_version(&past), Some(1));
    assert_eq!(
        hello_version(&encode_client(&hello()).expect("encode")),
        Some(PROTOCOL_VERSION)
    );
    let ping = encode_client(&ClientMsg::Ping { nonce: 0 }).expect("encode");
    assert_eq!(hello_version(&ping), None);
    assert_eq!(hello_version(&[]), None);
    assert_eq!(hello_version(&[0]), None);
}

#[test]
fn frame_over_the_limit_is_refused_before_parsing() {
    let limits = Limits::default();
    let max = limits.max_frame_bytes as usize;
    let bytes = vec![0u8; max + 1];
    let (res, peak) = peak_alloc(|| decode_client(&bytes, &limits));
    assert!(
        matches!(res, Err(WireError::FrameTooLarge { len, max: m }) if len == max + 1 && m == max)
    );
    assert_eq!(peak, 0, "nothing allocated to refuse it");
    assert!(matches!(
        decode_server(&bytes, &limits),
        Err(WireError::FrameTooLarge { .. })
    ));
}

#[test]
fn trailing_bytes_are_refused() {
    let mut bytes = encode_client(&ClientMsg::Ping { nonce: 7 }).expect("encode");
    bytes.push(0);
    assert!(matches!(
        decode_client(&bytes, &Limits::default()),
        Err(WireError::TrailingBytes { extra: 1 })
    ));
}

#[test]
fn too_many_ops_for_the_limits_are_refused() {
    let limits = Limits::default();
    let ops = vec![EditOp::Clear { pos: [1, 2, 3] }; limits.max_ops_per_batch as usize + 1];
    let msg = ClientMsg::Edit { client_seq: 1, ops };
    // Under the hard cap, so it encodes; over this server's limit, so it does not decode.
    let bytes = encode_client(&msg).expect("encode");
    assert!(matches!(
        decode_client(&bytes, &limits),
        Err(WireError::TooMany {
            len: 4097,
            max: 4096,
            ..
        })
    ));
    assert!(decode_client(&bytes, &Limits::hard_caps()).is_ok());
}

#[test]
fn ops_over_the_hard_cap_are_refused_while_parsing() {
    let ops = vec![EditOp::Clear { pos: [0, 0, 0] }; MAX_OPS_PER_BATCH as usize + 1];
    let msg = ClientMsg::Edit { client_seq: 1, ops };
    assert!(matches!(
        encode_client(&msg),
        Err(WireError::TooMany { .. })
    ));
    let bytes = raw_frame(&msg);
    let err = decode_client(&bytes, &Limits::hard_caps()).expect_err("over the cap");
    assert!(matches!(err, WireError::Malformed(_)), "{err}");
    assert!(err.to_string().contains("8192"), "{err}");
}

#[test]
fn a_huge_claimed_list_allocates_nothing_big() {
    // Tag of `Edit`, client_seq 0, then an op count of u32::MAX with no ops behind it.
    let bytes = [1u8, 0, 0xFB, 0xFF, 0xFF, 0xFF, 0xFF];
    let (res, peak) = peak_alloc(|| decode_client(&bytes, &Limits::hard_caps()));
    assert!(res.is_err());
    assert!(peak < 4096, "peak allocation {peak}");
}

#[test]
fn a_huge_claimed_string_allocates_nothing_big() {
    // Tag of `Hello`, version 1, then a name of 16 MiB - 1 with 3 bytes behind it.
    let mut bytes = vec![0u8, 1, 0xFC];
    bytes.extend_from_slice(&((16u32 << 20) - 1).to_le_bytes());
    bytes.extend_from_slice(b"abc");
    let (res, peak) = peak_alloc(|| decode_client(&bytes, &Limits::hard_caps()));
    assert!(matches!(res, Err(WireError::Malformed(_))));
    assert!(peak < 4096, "peak allocation {peak}");
}

#[test]
fn long_texts_are_refused_both_ways() {
    let long = ClientMsg::Hello {
        protocol: 1,
        name: "x".repeat(MAX_NAME_BYTES + 1),
        token: None,
        resume_from: None,
        user: 0,
        budget: None,
    };
    assert!(matches!(
        encode_client(&long),
        Err(WireError::TooLong {
            len: 65,
            max: 64,
            ..
        })
    ));
    assert!(matches!(
        decode_client(&raw_frame(&long), &Limits::hard_caps()),
        Err(WireError::Malformed(_))
    ));
    let token = ClientMsg::Hello {
        protocol: 1,
        name: "n".into(),
        token: Some("t".repeat(MAX_TOKEN_BYTES + 1)),
        resume_from: None,
        user: 0,
        budget: None,
    };
    assert!(decode_client(&raw_frame(&token), &Limits::hard_caps()).is_err());
    let error = ServerMsg::Error {
        code: ErrorCode::Internal,
        message: "m".repeat(MAX_MESSAGE_BYTES + 1),
    };
    assert!(matches!(
        encode_server(&error),
        Err(WireError::TooLong { .. })
    ));
    assert!(decode_server(&raw_frame(&error), &Limits::hard_caps()).is_err());
    // The helper constructors cut instead, on a character boundary.
    match ServerMsg::error(ErrorCode::Internal, "é".repeat(MAX_MESSAGE_BYTES)) {
        ServerMsg::Error { message, .. } => assert_eq!(message.len(), MAX_MESSAGE_BYTES),
        other => panic!("{other:?}"),
    }
    match Rejection::malformed("ü".repeat(200)) {
        Rejection::Malformed(text) => assert!(text.len() <= MAX_REASON_BYTES),
        other => panic!("{other:?}"),
    }
}

#[test]
fn welcome_with_unusable_limits_is_refused() {
    let welcome = |limits| ServerMsg::Welcome {
        protocol: PROTOCOL_VERSION,
        server: "s".into(),
        scene: "sponza".into(),
        size: [256; 3],
        seq: 0,
        role: Role::Editor,
        limits,
        total_bricks: 0,
        you: Peer {
            id: 1,
            user: 2,
            name: "me".into(),
            colour: Colour::WHITE,
            role: Role::Editor,
        },
        peers: Vec::new(),
    };
    let ok = encode_server(&welcome(Limits::default())).expect("encode");
    assert!(decode_server(&ok, &Limits::hard_caps()).is_ok());
    for bad in [
        Limits {
            max_frame_bytes: 32 << 20,
            ..Limits::default()
        },
        Limits {
            max_ops_per_batch: MAX_OPS_PER_BATCH + 1,
            ..Limits::default()
        },
        Limits {
            max_bricks_per_frame: 0,
            ..Limits::default()
        },
        Limits {
            max_brush_radius: f32::NAN,
            ..Limits::default()
        },
        Limits {
            max_brush_radius: 0.0,
            ..Limits::default()
        },
        Limits {
            max_brush_radius: f32::INFINITY,
            ..Limits::default()
        },
    ] {
        assert!(
            matches!(bad.validate(), Err(WireError::InvalidLimit { .. })),
            "{bad:?}"
        );
        assert!(encode_server(&welcome(bad.clone())).is_err());
        let res = decode_server(&raw_frame(&welcome(bad)), &Limits::hard_caps());
        assert!(matches!(res, Err(WireError::InvalidLimit { .. })));
    }
    assert!(Limits::default().validate().is_ok());
    assert!(Limits::hard_caps().validate().is_ok());
}

#[test]
fn camera_must_be_finite() {
    let msg = ClientMsg::Camera {
        eye: [0.0, f32::NAN, 0.0],
        forward: [0.0, 0.0, 1.0],
    };
    assert!(matches!(
        encode_client(&msg),
        Err(WireError::NotFinite { .. })
    ));
    assert!(matches!(
        decode_client(&raw_frame(&msg), &Limits::default()),
        Err(WireError::NotFinite { .. })
    ));
}

#[test]
fn removed_cells_are_capped() {
    let msg = ServerMsg::Delta {
        from_seq: 1,
        to_seq: 2,
        bricks: BrickBlob::empty(),
        removed: vec![[0; 3]; MAX_REMOVED_PER_FRAME + 1],
    };
    assert!(matches!(
        encode_server(&msg),
        Err(WireError::TooMany { .. })
    ));
    assert!(decode_server(&raw_frame(&msg), &Limits::hard_caps()).is_err());
}

#[test]
fn blob_brick_count_is_checked_against_the_receivers_limits() {
    let bricks: Vec<_> = (0..3).map(|i| solid_brick([i, 0, 0], FULL_MASK)).collect();
    let blob = BrickBlob::encode(&bricks, 1).expect("encode");
    let msg = ServerMsg::SyncBatch {
        bricks: blob.clone(),
        sent: 3,
        total: 3,
    };
    let bytes = encode_server(&msg).expect("encode");
    let tight = Limits {
        max_bricks_per_frame: 2,
        ..Limits::default()
    };
    assert!(matches!(
        decode_server(&bytes, &tight),
        Err(WireError::TooMany { len: 3, max: 2, .. })
    ));
    assert!(matches!(blob.decode(2), Err(WireError::TooMany { .. })));
    assert_eq!(blob.decode(3).expect("decode"), bricks);
}

#[test]
fn encode_refuses_frames_over_the_hard_cap() {
    // A header that passes the plausibility check with far too much data behind it.
    let blob = BrickBlob {
        count: 1,
        raw_len: 100,
        data: vec![0; MAX_FRAME_BYTES],
    };
    let msg = ServerMsg::SyncBatch {
        bricks: blob,
        sent: 1,
        total: 1,
    };
    let (res, peak) = peak_alloc(|| encode_server(&msg));
    match res {
        Err(WireError::FrameTooLarge { len, max }) => {
            assert_eq!(max, MAX_FRAME_BYTES);
            assert!(len > MAX_FRAME_BYTES);
        }
        other => panic!("{other:?}"),
    }
    assert!(peak <= 2 * MAX_FRAME_BYTES, "peak allocation {peak}");
}

#[test]
fn blob_claiming_a_gigabyte_fails_fast() {
    for count in [1, MAX_BRICKS_PER_FRAME] {
        let blob = BrickBlob {
            count,
            raw_len: 1 << 30,
            data: vec![0x28, 0xB5, 0x2F, 0xFD],
        };
        let (res, peak) = peak_alloc(|| blob.decode(MAX_BRICKS_PER_FRAME));
        assert!(matches!(res, Err(WireError::BlobRawLen { .. })), "{res:?}");
        assert!(peak < 4096, "peak allocation {peak}");
        let (res, peak) =
            peak_alloc(|| BlobDecoder::new().and_then(|mut d| d.decode(&blob, count)));
        assert!(matches!(res, Err(WireError::BlobRawLen { .. })));
        assert!(peak < 1 << 20, "peak allocation {peak} (zstd context only)");
    }
    let too_many = BrickBlob {
        count: MAX_BRICKS_PER_FRAME + 1,
        raw_len: 0,
        data: vec![],
    };
    assert!(matches!(
        too_many.decode(u32::MAX),
        Err(WireError::TooMany { .. })
    ));
}

/// Builds a blob from raw layout bytes, bypassing the encoder's checks.
fn blob_from_raw(count: u32, raw: &[u8]) -> BrickBlob {
    BrickBlob {
        count,
        raw_len: raw.len() as u32,
        data: zstd::bulk::compress(raw, 1).expect("compress"),
    }
}

/// One brick's raw blob bytes with `block` as its colour block, whatever that holds.
fn raw_brick(cell: [u16; 3], mask: Mask, block: &[u16]) -> Vec<u8> {
    let mut raw = Vec::new();
    cell.iter()
        .for_each(|c| raw.extend_from_slice(&c.to_le_bytes()));
    mask.iter()
        .for_each(|w| raw.extend_from_slice(&w.to_le_bytes()));
    block
        .iter()
        .for_each(|w| raw.extend_from_slice(&w.to_le_bytes()));
    raw
}

/// A raw colour block (header 15) of `colours` voxels of one colour.
fn raw_block(colours: usize) -> Vec<u16> {
    let mut block = vec![15];
    block.extend(std::iter::repeat_n(0x1234, colours));
    block
}

#[test]
fn blob_layout_is_as_documented() {
    let mut mask = EMPTY_MASK;
    mask[0] = 0b101;
    mask[7] = 1 << 63;
    let brick = BrickData {
        cell: [1, 2, 513],
        mask,
        colours: vec![Colour(1), Colour(2), Colour(3)],
    };
    // Four voxels of two colours: a palette of 1-bit indices.
    let mut four = EMPTY_MASK;
    four[1] = 0b1111;
    let two_colours = BrickData {
        cell: [3, 0, 0],
        mask: four,
        colours: vec![Colour(9), Colour(5), Colour(9), Colour(9)],
    };
    let bricks = [brick, two_colours];
    let blob = BrickBlob::encode(&bricks, 0).expect("encode");
    let raw = zstd::bulk::decompress(&blob.data, 1 << 20).expect("zstd");
    let mut expected = vec![1, 0, 2, 0, 1, 2, 3, 0, 0, 0, 0, 0];
    for m in [mask, four] {
        m.iter()
            .for_each(|w| expected.extend_from_slice(&w.to_le_bytes()));
    }
    // Three distinct colours in three voxels: raw (header 15) is smaller than a palette.
    expected.extend_from_slice(&[15, 0, 1, 0, 2, 0, 3, 0]);
    // Palette header: 1-bit indices, 2 entries; entries 5, 9; indices 1,0,1,1 from bit 0.
    expected.extend_from_slice(&[0x11, 0, 5, 0, 9, 0, 0b1101, 0]);
    assert_eq!(raw, expected);
    assert_eq!(blob.raw_len as usize, raw.len());
    assert_eq!(
        blob_from_raw(2, &raw).decode(2).expect("decode"),
        bricks.to_vec()
    );
}

#[test]
fn blob_with_wrong_colour_count_is_refused() {
    let mut mask = EMPTY_MASK;
    mask[3] = 0b111;
    for colours in [2, 4] {
        let blob = blob_from_raw(1, &raw_brick([0, 0, 0], mask, &raw_block(colours)));
        let res = blob.decode(1);
        assert!(
            matches!(res, Err(WireError::ColourBytes { needed: 8, .. })),
            "{colours} colours: {res:?}"
        );
    }
    // Odd byte count: half a word.
    let mut raw = raw_brick([0, 0, 0], mask, &raw_block(3));
    raw.push(0);
    assert!(matches!(
        blob_from_raw(1, &raw).decode(1),
        Err(WireError::ColourBytes { .. })
    ));
}

#[test]
fn blob_with_a_bad_colour_block_is_refused() {
    let mut mask = EMPTY_MASK;
    mask[3] = 0b111;
    let refused = |block: &[u16]| blob_from_raw(1, &raw_brick([0, 0, 0], mask, block)).decode(1);
    // Sound: a 1-bit palette of 2 entries, indices 0,1,1.
    assert!(refused(&[0x11, 5, 9, 0b110]).is_ok());
    // A 2-bit palette of 3 entries whose third voxel points at a fourth entry.
    let res = refused(&[0x22, 5, 9, 11, 0b11_01_00]);
    assert!(
        matches!(res, Err(WireError::ColourBlock { index: 0, .. })),
        "{res:?}"
    );
    // Entries not ascending: two encodings of one brick would be possible.
    let res = refused(&[0x11, 9, 5, 0b110]);
    assert!(
        matches!(res, Err(WireError::ColourBlock { index: 0, .. })),
        "{res:?}"
    );
    // A header that names no coding.
    let res = refused(&[0x7, 1, 2, 3]);
    assert!(
        matches!(res, Err(WireError::ColourBlock { index: 0, .. })),
        "{res:?}"
    );
    // A lossy block (2-bit weights) never travels.
    let mut lossy = vec![14];
    lossy.resize(brickcast_protocol::blocks::words(2, 3), 0);
    let res = refused(&lossy);
    assert!(
        matches!(res, Err(WireError::LossyBlock { index: 0 })),
        "{res:?}"
    );
}

#[test]
fn blob_with_an_empty_mask_is_refused_and_nothing_is_delivered() {
    let mut first = EMPTY_MASK;
    first[0] = 1;
    // Two bricks, the second empty: cells, masks, then the single colour.
    let mut raw = Vec::new();
    raw.extend_from_slice(&[0; 12]);
    first
        .iter()
        .chain(&EMPTY_MASK)
        .for_each(|w| raw.extend_from_slice(&w.to_le_bytes()));
    raw.extend_from_slice(&[0, 0, 9, 9]); // one colour
    raw.extend_from_slice(&[0; 4]); // pad to the two-brick minimum size
    let blob = blob_from_raw(2, &raw);
    let mut calls = 0;
    let res = BlobDecoder::new()
        .expect("decoder")
        .for_each(&blob, 2, |_| calls += 1);
    assert!(
        matches!(res, Err(WireError::EmptyMask { index: 1 })),
        "{res:?}"
    );
    assert_eq!(calls, 0);
}

#[test]
fn blob_whose_data_is_longer_or_shorter_than_announced_is_refused() {
    let mut mask = EMPTY_MASK;
    mask[5] = 0xF0;
    let raw = raw_brick([0, 0, 0], mask, &raw_block(4));
    let mut blob = blob_from_raw(1, &raw);
    blob.raw_len -= 2;
    assert!(matches!(blob.decode(1), Err(WireError::Decompress(_))));
    blob.raw_len += 4;
    assert!(matches!(blob.decode(1), Err(WireError::BlobLength { .. })));
    let garbage = BrickBlob {
        count: 1,
        raw_len: 100,
        data: vec![1, 2, 3],
    };
    assert!(matches!(garbage.decode(1), Err(WireError::Decompress(_))));
    let empty_with_data = BrickBlob {
        count: 0,
        raw_len: 0,
        data: vec![1],
    };
    assert!(matches!(
        empty_with_data.decode(1),
        Err(WireError::EmptyBlobData { len: 1 })
    ));
}

#[test]
fn encoder_refuses_bad_bricks() {
    let empty = BrickData {
        cell: [0; 3],
        mask: EMPTY_MASK,
        colours: vec![],
    };
    assert!(matches!(
        BrickBlob::encode(&[empty], 1),
        Err(WireError::InconsistentBrick { index: 0, .. })
    ));
    let mut short = solid_brick([0; 3], FULL_MASK);
    short.colours.pop();
    let good = solid_brick([1, 0, 0], FULL_MASK);
    assert!(matches!(
        BrickBlob::encode(&[good.clone(), short], 1),
        Err(WireError::InconsistentBrick { index: 1, .. })
    ));
    let far = solid_brick([0, 65536, 0], FULL_MASK);
    assert!(matches!(
        BrickBlob::encode(&[far], 1),
        Err(WireError::CellOutOfRange { .. })
    ));
    let many = vec![good; MAX_BRICKS_PER_FRAME as usize + 1];
    assert!(matches!(
        BrickBlob::encode(&many, 1),
        Err(WireError::TooMany { .. })
    ));
}

#[test]
fn empty_blob() {
    let blob = BrickBlob::encode(&[], 3).expect("encode");
    assert_eq!(blob, BrickBlob::empty());
    assert!(blob.is_empty());
    assert_eq!(blob.decode(0).expect("decode"), vec![]);
}

#[test]
fn encoder_and_decoder_are_reusable() {
    let mut enc = BlobEncoder::new(3).expect("encoder");
    let mut dec = BlobDecoder::new().expect("decoder");
    for round in 0..3u32 {
        let bricks: Vec<_> = (0..=round)
            .map(|i| solid_brick([i, round, 7], FULL_MASK))
            .collect();
        for b in &bricks {
            enc.push_brick(b).expect("push");
        }
        assert_eq!(enc.len(), round + 1);
        // One colour each: a 4-byte block.
        assert_eq!(enc.raw_len(), bricks.len() * (6 + 64 + 4));
        let blob = enc.finish().expect("finish");
        assert!(enc.is_empty());
        assert_eq!(dec.decode(&blob, 64).expect("decode"), bricks);
        let mut seen = Vec::new();
        dec.for_each(&blob, 64, |b| {
            assert_eq!(b.colour_count(), 512);
            assert_eq!(b.block(), &[0, 0x1234]);
            assert_eq!(b.colours()[511], Colour(0x1234));
            seen.push(b.to_brick());
        })
        .expect("for_each");
        assert_eq!(seen, bricks);
    }
    // A refused push leaves the batch usable.
    let bad = BrickData {
        cell: [0; 3],
        mask: FULL_MASK,
        colours: vec![],
    };
    enc.push_brick(&solid_brick([5; 3], FULL_MASK))
        .expect("push");
    assert!(enc.push_brick(&bad).is_err());
    assert_eq!(
        enc.finish()
            .expect("finish")
            .decode(8)
            .expect("decode")
            .len(),
        1
    );
}

#[test]
fn validate_checks_bounds_numbers_and_sizes() {
    let size = [64, 32, 16];
    let limits = Limits::default();
    let c = Colour::WHITE;
    let check = |op: EditOp| op.validate(size, &limits);

    assert_eq!(
        check(EditOp::Set {
            pos: [63, 31, 15],
            colour: c
        }),
        Ok(())
    );
    assert_eq!(
        check(EditOp::Set {
            pos: [64, 0, 0],
            colour: c
        }),
        Err(Rejection::OutOfBounds)
    );
    assert_eq!(
        check(EditOp::Clear { pos: [0, 0, 16] }),
        Err(Rejection::OutOfBounds)
    );
    assert_eq!(
        check(EditOp::Paint {
            pos: [0, 32, 0],
            colour: c
        }),
        Err(Rejection::OutOfBounds)
    );

    let sphere = |centre, radius| EditOp::Sphere {
        centre,
        radius,
        mode: BrushMode::Fill,
        colour: c,
    };
    assert_eq!(check(sphere([64.0, 0.0, 16.0], 64.0)), Ok(()));
    assert_eq!(
        check(sphere([f32::NAN, 0.0, 0.0], 4.0)),
        Err(Rejection::InvalidNumber)
    );
    assert_eq!(
        check(sphere([0.0, f32::INFINITY, 0.0], 4.0)),
        Err(Rejection::InvalidNumber)
    );
    assert_eq!(
        check(sphere([-0.5, 0.0, 0.0], 4.0)),
        Err(Rejection::OutOfBounds)
    );
    assert_eq!(check(sphere([1.0; 3], 0.0)), Err(Rejection::InvalidNumber));
    assert_eq!(
        check(sphere([1.0; 3], f32::NAN)),
        Err(Rejection::InvalidNumber)
    );
    assert_eq!(check(sphere([1.0; 3], 64.5)), Err(Rejection::TooLarge));

    let boxed = |min, max| EditOp::Box {
        min,
        max,
        mode: BrushMode::Erase,
        colour: c,
    };
    assert_eq!(check(boxed([0; 3], [63, 31, 15])), Ok(()));
    assert_eq!(check(boxed([5; 3], [5; 3])), Ok(()));
    assert!(matches!(
        check(boxed([6, 0, 0], [5, 0, 0])),
        Err(Rejection::Malformed(_))
    ));
    assert_eq!(
        check(boxed([0; 3], [64, 0, 0])),
        Err(Rejection::OutOfBounds)
    );
    let big = [1 << 20; 3];
    let oversized = boxed([0; 3], [256, 1, 1]).validate(big, &limits);
    assert_eq!(oversized, Err(Rejection::TooLarge));
    assert_eq!(boxed([1, 0, 0], [256, 1, 1]).validate(big, &limits), Ok(()));

    let ray = |origin, dir, action| EditOp::Ray {
        origin,
        dir,
        action,
    };
    let down = [0.0, -1.0, 0.0];
    assert_eq!(
        check(ray([-100.0, 50.0, 3.0], down, RayAction::Remove)),
        Ok(())
    );
    assert_eq!(
        check(ray([0.0; 3], [0.0; 3], RayAction::Remove)),
        Err(Rejection::InvalidNumber)
    );
    assert_eq!(
        check(ray([0.0; 3], [1e-7; 3], RayAction::Remove)),
        Err(Rejection::InvalidNumber)
    );
    assert_eq!(
        check(ray(
            [0.0, f32::NAN, 0.0],
            down,
            RayAction::Place { colour: c }
        )),
        Err(Rejection::InvalidNumber)
    );
    let ray_sphere = |radius| RayAction::Sphere {
        mode: BrushMode::Paint,
        radius,
        colour: c,
    };
    assert_eq!(check(ray([0.0; 3], down, ray_sphere(8.0))), Ok(()));
    assert_eq!(
        check(ray([0.0; 3], down, ray_sphere(100.0))),
        Err(Rejection::TooLarge)
    );
    assert_eq!(
        check(ray([0.0; 3], down, ray_sphere(-1.0))),
        Err(Rejection::InvalidNumber)
    );

    // The tools: a fill's or extrude's limit within the server's, a span's extent within its
    // largest box and both its rays sound.
    let fill = |limit| RayAction::Fill { colour: c, limit };
    assert_eq!(check(ray([0.0; 3], down, fill(1))), Ok(()));
    assert_eq!(
        check(ray([0.0; 3], down, fill(limits.max_tool_voxels + 1))),
        Err(Rejection::TooLarge)
    );
    assert!(matches!(
        check(ray([0.0; 3], down, fill(0))),
        Err(Rejection::Malformed(_))
    ));
    let extrude = RayAction::Extrude {
        out: true,
        limit: limits.max_tool_voxels,
    };
    assert_eq!(check(ray([0.0; 3], down, extrude)), Ok(()));
    let span = |to_dir, extent| EditOp::Span {
        from: [1.0; 3],
        from_dir: down,
        to: [-50.0, 3.0, 9.0],
        to_dir,
        shape: Shape::Box,
        mode: BrushMode::Fill,
        colour: c,
        extent,
    };
    assert_eq!(check(span(down, 16)), Ok(()));
    assert_eq!(
        check(span(down, limits.max_box_extent + 1)),
        Err(Rejection::TooLarge)
    );
    assert!(matches!(check(span(down, 0)), Err(Rejection::Malformed(_))));
    assert_eq!(check(span([0.0; 3], 16)), Err(Rejection::InvalidNumber));
    assert_eq!(
        check(span([f32::NAN, 1.0, 0.0], 16)),
        Err(Rejection::InvalidNumber)
    );
    // Charged for what they may do: a fill 32 brush voxels a voxel of its limit, a box its
    // extent cubed.
    let size = [512, 512, 512];
    let walk = 1536;
    assert_eq!(ray([0.0; 3], down, fill(1000)).work(size), walk + 32_000);
    assert_eq!(span(down, 16).work(size), 2 * walk + 16 * 16 * 16);
}

#[test]
fn rejections_read_well() {
    assert_eq!(
        Rejection::OutOfBounds.to_string(),
        "the edit reaches outside the scene"
    );
    assert_eq!(
        Rejection::malformed("bad").to_string(),
        "malformed edit: bad"
    );
    let err = WireError::FrameTooLarge { len: 10, max: 5 };
    assert_eq!(err.to_string(), "frame is 10 bytes, over the 5-byte limit");
}

/// Tiny deterministic generator so the compression figure is the same every run.
struct XorShift(u64);

impl XorShift {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
}

#[test]
fn a_full_frame_of_half_full_bricks_compresses() {
    let mut rng = XorShift(0x9E37_79B9_7F4A_7C15);
    let palette: Vec<Colour> = (0..8).map(|_| Colour(rng.next() as u16)).collect();
    let mut random_colours = Vec::new();
    let mut palette_colours = Vec::new();
    for i in 0..4096u32 {
        let cell = [i % 16, (i / 16) % 16, i / 256];
        let mask: Mask = std::array::from_fn(|_| rng.next());
        let n = popcount(&mask) as usize;
        let random = (0..n).map(|_| Colour(rng.next() as u16)).collect();
        random_colours.push(BrickData {
            cell,
            mask,
            colours: random,
        });
        let base = (rng.next() % 8) as usize;
        let material = (0..n)
            .map(|_| palette[(base + rng.next().is_multiple_of(16) as usize) % palette.len()])
            .collect();
        palette_colours.push(BrickData {
            cell,
            mask,
            colours: material,
        });
    }
    for (what, bricks) in [
        ("random colours", &random_colours),
        ("palette colours", &palette_colours),
    ] {
        let blob = BrickBlob::encode(bricks, 3).expect("encode");
        assert_eq!(&blob.decode(MAX_BRICKS_PER_FRAME).expect("decode"), bricks);
        println!(
            "4096 half-full bricks, {what}: raw {} B, compressed {} B, {:.1} B/brick ({:.1} raw)",
            blob.raw_len,
            blob.data.len(),
            blob.data.len() as f64 / 4096.0,
            blob.raw_len as f64 / 4096.0,
        );
        let frame = encode_server(&ServerMsg::SyncBatch {
            bricks: blob,
            sent: 4096,
            total: 4096,
        })
        .expect("frame");
        assert!(frame.len() <= Limits::default().max_frame_bytes as usize);
    }
}
