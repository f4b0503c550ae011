//! Round trips, hostile input and limits of the codec, the framing and the handshake.

use std::io::{Cursor, Read};

use bytes::BytesMut;
use glam::Mat4;
use proptest::prelude::*;
use tokio_util::codec::{Decoder, Encoder};

use crate::auth::FarmSecret;
use crate::stream::FrameCodec;
use crate::*;

// ---------------------------------------------------------------------------------------
// Strategies

fn ids() -> impl Strategy<Value = BatchIds> {
    (any::<u64>(), any::<u64>(), any::<u64>(), any::<u64>(), 0u32..64).prop_map(
        |(batch_id, task_id, session_id, frame_id, view_index)| BatchIds {
            batch_id,
            task_id,
            session_id,
            frame_id,
            view_index,
        },
    )
}

fn token(max: usize) -> impl Strategy<Value = String> {
    proptest::string::string_regex(&format!("[A-Za-z0-9_-][A-Za-z0-9_-]{{0,{}}}", max - 1)).expect("regex")
}

fn text() -> impl Strategy<Value = String> {
    proptest::string::string_regex(".{0,40}").expect("regex")
}

fn finite() -> impl Strategy<Value = f32> {
    -1e6f32..1e6f32
}

fn camera() -> impl Strategy<Value = ViewProjection> {
    (1u32..300, 1u32..300, prop::array::uniform16(finite()), prop::array::uniform16(finite())).prop_map(
        |(width, height, view, projection)| ViewProjection {
            width,
            height,
            view: Mat4::from_cols_array(&view),
            projection: Mat4::from_cols_array(&projection),
        },
    )
}

/// A camera and 1..200 pixel indices inside its image.
fn camera_and_pixels() -> impl Strategy<Value = (ViewProjection, Vec<u32>)> {
    camera().prop_flat_map(|c| {
        let n = c.width * c.height;
        (Just(c), prop::collection::vec(0..n, 1..200))
    })
}

fn address() -> impl Strategy<Value = String> {
    (token(20), 1u16..).prop_map(|(host, port)| format!("{host}:{port}"))
}

fn stats() -> impl Strategy<Value = KernelStats> {
    (any::<u64>(), any::<u64>(), any::<u64>(), any::<u64>()).prop_map(|(rays, rays_hit, queries, hidden)| KernelStats {
        rays,
        rays_hit,
        queries,
        hidden,
    })
}

fn error_code() -> impl Strategy<Value = ErrorCode> {
    prop_oneof![
        Just(ErrorCode::Malformed),
        Just(ErrorCode::InvalidField),
        Just(ErrorCode::UnknownAsset),
        Just(ErrorCode::DeadlineExpired),
        Just(ErrorCode::ShuttingDown),
        Just(ErrorCode::Internal),
    ]
}

fn derived_view() -> impl Strategy<Value = DerivedView> {
    (ids(), camera_and_pixels()).prop_map(|(ids, (camera, pixels))| DerivedView { ids, camera, pixels })
}

fn reuse_limits() -> impl Strategy<Value = ReuseLimits> {
    (0.0f32..=90.0, prop_oneof![0.0f32..10.0, Just(f32::INFINITY)], 0..=ReuseLimits::MAX_PREVIOUS_FRAMES, any::<bool>())
        .prop_map(|(max_angle_deg, max_contrast, previous_frames, rows_complete)| ReuseLimits {
            max_angle_deg,
            max_contrast,
            previous_frames,
            rows_complete,
            // Valid batches hold derived views, which a render ahead may not.
            ahead: false,
        })
}

fn ray_batch() -> impl Strategy<Value = RayBatch> {
    (
        ids(),
        token(40),
        camera_and_pixels(),
        any::<Option<u64>>(),
        address(),
        proptest::collection::vec(derived_view(), 0..3),
        reuse_limits(),
        proptest::collection::vec(solid_grid(), 0..3),
    )
        .prop_map(|(ids, asset_id, (camera, pixels), deadline_in_us, composer, derived, reuse, occluders)| {
            RayBatch { ids, asset_id, camera, pixels, deadline_in_us, composer, derived, reuse, occluders }
        })
}

fn solid_grid() -> impl Strategy<Value = SolidGrid> {
    (prop::array::uniform3(-10.0f32..10.0), prop::array::uniform3(0.01f32..5.0), prop::array::uniform3(1u32..12))
        .prop_flat_map(|(min, size, dims)| {
            let words = (dims.iter().product::<u32>() as usize).div_ceil(64);
            prop::collection::vec(any::<u64>(), words).prop_map(move |bits| SolidGrid {
                min,
                max: [min[0] + size[0], min[1] + size[1], min[2] + size[2]],
                dims,
                bits,
            })
        })
}

fn batch_result() -> impl Strategy<Value = BatchResult> {
    (ids(), any::<u64>(), camera_and_pixels(), any::<u64>(), stats()).prop_flat_map(
        |(ids, worker_id, (camera, pixels), render_time_us, stats)| {
            let n = pixels.len();
            (
                prop::collection::vec(prop::array::uniform3(finite()), n),
                prop::collection::vec(0.0f32..=1.0, n),
                prop::collection::vec(0.0f32..1e4, n),
            )
                .prop_map(move |(color, opacity, depth)| BatchResult {
                    ids,
                    worker_id,
                    width: camera.width,
                    height: camera.height,
                    pixels: pixels.clone(),
                    color,
                    opacity,
                    depth,
                    render_time_us,
                    stats,
                    encoding: crate::ResultEncoding::F32,
                })
        },
    )
}

/// The messages between master and composer.
fn composer_message() -> impl Strategy<Value = Message> {
    let sdp = || proptest::string::string_regex("v=0\r\n.{0,60}").expect("regex");
    prop_oneof![
        (token(64), address())
            .prop_map(|(name, results_address)| Message::ComposerRegister(ComposerRegister { name, results_address })),
        (any::<u64>(), token(64), sdp(), 1u32..=64, 1u32..=256, 1u32..=256, 1.0f32..240.0).prop_map(
            |(session_id, session_name, offer_sdp, views, width, height, target_fps)| {
                Message::OpenStream(OpenStream {
                    session_id,
                    session_name,
                    offer_sdp,
                    views,
                    width,
                    height,
                    target_fps,
                })
            }
        ),
        (any::<u64>(), prop_oneof![sdp().prop_map(Ok), text().prop_map(Err)])
            .prop_map(|(session_id, answer)| Message::StreamOpened(StreamOpened { session_id, answer })),
        (any::<u64>(), any::<u32>(), -1e9f64..1e9, prop::collection::vec(camera(), 1..4)).prop_map(
            |(session_id, sequence, client_time_ms, views)| Message::ClientPose(ClientPose {
                session_id,
                sequence,
                client_time_ms,
                views
            })
        ),
        (any::<u64>(), any::<u64>(), any::<u32>(), 0.0f64..1e9, 1u32..300, 1u32..300, 1u32..=64, any::<Option<u64>>())
            .prop_flat_map(
                |(session_id, frame_id, pose_sequence, client_time_ms, width, height, views, deadline_in_us)| {
                    let part = (0..views, any::<u64>(), any::<u64>()).prop_map(|(view, task_id, object_id)| PlanPart {
                        view,
                        task_id,
                        object_id,
                    });
                    prop::collection::vec(part, 0..8).prop_map(move |parts| {
                        Message::FramePlan(FramePlan {
                            session_id,
                            frame_id,
                            pose_sequence,
                            client_time_ms,
                            width,
                            height,
                            views,
                            parts,
                            deadline_in_us,
                        })
                    })
                }
            ),
        any::<u64>().prop_map(|task_id| Message::ReleaseTask(ReleaseTask { task_id })),
        (any::<u64>(), text())
            .prop_map(|(session_id, reason)| Message::CloseStream(CloseStream { session_id, reason })),
    ]
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![3 => worker_message(), 1 => composer_message()]
}

/// The messages between master, workers and tools.
fn worker_message() -> impl Strategy<Value = Message> {
    let role = prop_oneof![Just(Role::Master), Just(Role::Worker), Just(Role::Composer), Just(Role::Tool)];
    prop_oneof![
        role.prop_map(|r| Message::Hello(Hello::new(r))),
        any::<[u8; 32]>().prop_map(|nonce| Message::Challenge(Challenge { nonce })),
        any::<Option<[u8; 32]>>().prop_map(|mac| Message::Proof(Proof { mac })),
        (token(64), 1u32..512, prop::collection::vec(token(32), 1..4), 0.0f64..1e12, "[ -~]{0,40}").prop_map(
            |(name, threads, kernels, rays_per_second, device)| Message::Register(Register {
                name,
                threads,
                kernels,
                rays_per_second,
                device
            })
        ),
        (any::<u64>(), 10u32..=60_000).prop_map(|(worker_id, load_report_interval_ms)| Message::Registered(
            Registered { worker_id, load_report_interval_ms }
        )),
        (any::<u32>(), any::<u32>(), any::<u64>(), 0.0f64..1e12, any::<u64>(), any::<u64>()).prop_map(
            |(a, b, c, d, e, f)| {
                Message::LoadReport(LoadReport {
                    in_flight_batches: a,
                    queued_batches: b,
                    queued_rays: c,
                    recent_rays_per_second: d,
                    batches_done: e,
                    rays_done: f,
                })
            }
        ),
        ray_batch().prop_map(Message::RayBatch),
        batch_result().prop_map(Message::BatchResult),
        (ids(), 0u32..1000, any::<u64>(), stats()).prop_map(|(ids, pixels, render_time_us, stats)| Message::BatchDone(
            BatchDone { ids, pixels, render_time_us, stats }
        )),
        (ids(), error_code(), text()).prop_map(|(ids, code, message)| Message::BatchFailed(BatchFailed {
            ids,
            code,
            message
        })),
        prop_oneof![
            any::<u64>().prop_map(CancelTarget::Batch),
            (any::<u64>(), any::<u64>())
                .prop_map(|(session_id, frame_id)| CancelTarget::Frame { session_id, frame_id }),
            any::<u64>().prop_map(CancelTarget::Session),
        ]
        .prop_map(|target| Message::Cancel(Cancel { target })),
        (text(), prop::collection::vec(any::<u64>(), 0..10))
            .prop_map(|(reason, returned_batches)| Message::Goodbye(Goodbye { reason, returned_batches })),
        (error_code(), text()).prop_map(|(code, message)| Message::Error(ErrorMessage { code, message })),
    ]
}

// ---------------------------------------------------------------------------------------
// Fixtures

fn cfg() -> FrameConfig {
    FrameConfig::default()
}

fn good_camera() -> ViewProjection {
    let mut view = [0.0; 16];
    view[0] = 1.0;
    view[5] = 1.0;
    view[10] = 1.0;
    view[14] = -4.0;
    view[15] = 1.0;
    let mut projection = [0.0; 16];
    projection[0] = 1.5;
    projection[5] = 2.0;
    projection[10] = -1.0;
    projection[11] = -1.0;
    projection[14] = -0.2;
    ViewProjection {
        width: 64,
        height: 48,
        view: Mat4::from_cols_array(&view),
        projection: Mat4::from_cols_array(&projection),
    }
}

fn good_batch() -> RayBatch {
    RayBatch {
        ids: BatchIds { batch_id: 7, task_id: 5, session_id: 3, frame_id: 11, view_index: 1 },
        asset_id: "diffuse".into(),
        camera: good_camera(),
        pixels: (0..64 * 48).step_by(7).collect(),
        deadline_in_us: Some(40_000),
        composer: "127.0.0.1:7000".into(),
        derived: Vec::new(),
        reuse: ReuseLimits::default(),
        occluders: Vec::new(),
    }
}

fn good_result(n: usize) -> BatchResult {
    let pixels: Vec<u32> = (0..n as u32).map(|i| (i * 13) % (640 * 480)).collect();
    BatchResult {
        ids: BatchIds { batch_id: 9, task_id: 8, session_id: 1, frame_id: 2, view_index: 0 },
        worker_id: 4,
        width: 640,
        height: 480,
        color: pixels.iter().map(|&p| [p as f32 * 1e-3, 0.5, 0.25]).collect(),
        opacity: pixels.iter().map(|&p| (p % 2) as f32).collect(),
        depth: pixels.iter().map(|&p| (p % 7) as f32).collect(),
        pixels,
        render_time_us: 1234,
        stats: KernelStats { rays: 10, rays_hit: 5, queries: 40, hidden: 0 },
        encoding: crate::ResultEncoding::F32,
    }
}

fn frame_of(message: &Message) -> Vec<u8> {
    let mut out = Vec::new();
    encode_frame(message, &mut out, &cfg()).expect("encodes");
    out
}

/// A frame around a raw payload (no validation): how a buggy or hostile peer sends.
fn raw_frame(tag: u8, body: &[u8]) -> Vec<u8> {
    let mut out = ((body.len() + 1) as u32).to_le_bytes().to_vec();
    out.push(tag);
    out.extend_from_slice(body);
    out
}

fn decode_one(bytes: &[u8]) -> Result<Incoming, ProtoError> {
    decode_frame(bytes, &cfg()).map(|(incoming, rest)| {
        assert!(rest.is_empty());
        incoming
    })
}

fn rejected(bytes: &[u8]) -> Rejected {
    match decode_one(bytes) {
        Ok(Err(rejected)) => rejected,
        other => panic!("expected a rejected message, got {other:?}"),
    }
}

/// Every decoder we have, fed the same bytes: none may panic. Returns what the in-memory
/// decoder said about the first frame.
fn feed_all_decoders(bytes: &[u8], config: FrameConfig) -> Option<bool> {
    let first = decode_frame(bytes, &config).ok().map(|(incoming, _)| incoming.is_ok());
    let mut reader = FrameReader::new(Cursor::new(bytes), config);
    while let Ok(_incoming) = reader.read_message() {}
    let mut codec = FrameCodec::new(config);
    let mut buf = BytesMut::from(bytes);
    while let Ok(Some(_)) = codec.decode(&mut buf) {}
    let _ = codec.decode_eof(&mut buf);
    first
}

// ---------------------------------------------------------------------------------------
// Round trips

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn every_message_round_trips_through_every_framing(message in message()) {
        let frame = frame_of(&message);
        // In memory.
        let (decoded, rest) = decode_frame(&frame, &cfg()).expect("decodes");
        prop_assert!(rest.is_empty());
        prop_assert_eq!(decoded, Ok(message.clone()));
        // Blocking reader, two frames back to back, then a clean end.
        let mut two = frame.clone();
        two.extend_from_slice(&frame);
        let mut reader = FrameReader::new(Cursor::new(two), cfg());
        prop_assert_eq!(reader.read_message().expect("first"), Ok(message.clone()));
        prop_assert_eq!(reader.read_message().expect("second"), Ok(message.clone()));
        prop_assert!(matches!(reader.read_message(), Err(ProtoError::Closed)));
        // tokio codec, fed one byte at a time.
        let mut codec = FrameCodec::new(cfg());
        let mut encoded = BytesMut::new();
        codec.encode(&message, &mut encoded).expect("codec encodes");
        prop_assert_eq!(&encoded[..], &frame[..]);
        let mut buf = BytesMut::new();
        let mut out = None;
        for (i, b) in frame.iter().enumerate() {
            buf.extend_from_slice(&[*b]);
            if let Some(item) = codec.decode(&mut buf).expect("no error") {
                prop_assert_eq!(i, frame.len() - 1);
                out = Some(item);
            }
        }
        prop_assert_eq!(out, Some(Ok(message)));
        prop_assert!(buf.is_empty());
    }

    #[test]
    fn every_strict_prefix_is_truncated(message in message()) {
        let frame = frame_of(&message);
        for cut in 0..frame.len() {
            let prefix = &frame[..cut];
            prop_assert!(matches!(decode_frame(prefix, &cfg()), Err(ProtoError::Truncated { .. })), "cut {}", cut);
            let mut reader = FrameReader::new(Cursor::new(prefix), cfg());
            match reader.read_message() {
                Err(ProtoError::Closed) => prop_assert_eq!(cut, 0),
                Err(ProtoError::Truncated { received, .. }) => prop_assert_eq!(received, cut as u64),
                other => prop_assert!(false, "cut {}: {:?}", cut, other),
            }
            let mut buf = BytesMut::from(prefix);
            let mut codec = FrameCodec::new(cfg());
            prop_assert!(matches!(codec.decode(&mut buf), Ok(None)));
            let eof = codec.decode_eof(&mut buf);
            let expected_eof = if cut == 0 { matches!(eof, Ok(None)) } else { matches!(eof, Err(ProtoError::Truncated { .. })) };
            prop_assert!(expected_eof, "cut {}: {:?}", cut, eof);
        }
    }

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
        feed_all_decoders(&bytes, cfg());
        feed_all_decoders(&bytes, FrameConfig { max_frame: 16 });
        let _ = decode_payload(&bytes);
    }

    #[test]
    fn random_payloads_behind_a_valid_header_never_panic(tag in prop_oneof![0u8..20, Just(compact::COMPACT_TAG)], body in prop::collection::vec(any::<u8>(), 0..400)) {
        feed_all_decoders(&raw_frame(tag, &body), cfg());
    }

    #[test]
    fn corrupted_frames_never_panic(message in message(), flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6)) {
        let mut frame = frame_of(&message);
        for (at, value) in flips {
            let i = at.index(frame.len());
            frame[i] = value;
        }
        feed_all_decoders(&frame, cfg());
    }
}

// ---------------------------------------------------------------------------------------
// Packed arrays

#[test]
fn pixel_arrays_travel_packed() {
    let n = 10_000;
    let frame = frame_of(&Message::BatchResult(good_result(n)));
    // 4 (index) + 12 (colour) + 4 (opacity) + 4 (depth) bytes per pixel plus a few dozen
    // bytes of ids, lengths and stats: no per-element tags or varints.
    assert!(frame.len() >= 24 * n && frame.len() <= 24 * n + 80, "{} bytes for {n} pixels", frame.len());
    // The first pixel's colour sits verbatim (LE f32) in the frame.
    let result = good_result(n);
    let needle: Vec<u8> = result.color[..4].iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    assert!(frame.windows(needle.len()).any(|w| w == needle));
    let batch = frame_of(&Message::RayBatch(good_batch()));
    assert!(batch.len() <= 4 * good_batch().pixels.len() + 200);
}

#[test]
fn packed_arrays_of_a_partial_element_are_malformed() {
    // Hand-written body: a postcard BatchResult whose pixel block is 5 bytes long.
    let mut body = postcard::to_allocvec(&BatchIds::default()).expect("ids");
    body.extend(postcard::to_allocvec(&(4u64, 640u32, 480u32)).expect("header"));
    body.push(5);
    body.extend([0u8; 5]);
    assert!(matches!(
        decode_one(&raw_frame(MessageKind::BatchResult.tag(), &body)),
        Err(ProtoError::Malformed { kind: MessageKind::BatchResult, .. })
    ));
}

// ---------------------------------------------------------------------------------------
// Hostile and broken input

#[test]
fn a_4_gib_length_prefix_is_refused_without_allocating() {
    let header = u32::MAX.to_le_bytes();
    assert!(matches!(
        decode_frame(&header, &cfg()),
        Err(ProtoError::FrameTooLarge { len, max }) if len == u64::from(u32::MAX) && max == DEFAULT_MAX_FRAME
    ));
    // A reader that would hand out endless bytes: only the header is read.
    let mut endless = FrameReader::new(Read::chain(&header[..], std::io::repeat(0)), cfg());
    assert!(matches!(endless.read_message(), Err(ProtoError::FrameTooLarge { .. })));
    assert_eq!(endless.buf_capacity(), 0);
    let mut codec = FrameCodec::new(cfg());
    let mut buf = BytesMut::from(&header[..]);
    assert!(matches!(codec.decode(&mut buf), Err(ProtoError::FrameTooLarge { .. })));
    assert!(buf.capacity() < 1024);
}

#[test]
fn a_large_claim_under_the_limit_allocates_only_what_arrives() {
    let claim = (DEFAULT_MAX_FRAME - 1) as u32;
    let mut bytes = claim.to_le_bytes().to_vec();
    bytes.extend([6u8; 100]);
    let mut reader = FrameReader::new(Cursor::new(&bytes), cfg());
    assert!(matches!(reader.read_message(), Err(ProtoError::Truncated { received: 104, .. })));
    assert!(reader.buf_capacity() <= 1 << 20, "{}", reader.buf_capacity());
    let mut codec = FrameCodec::new(cfg());
    let mut buf = BytesMut::from(&bytes[..]);
    assert!(matches!(codec.decode(&mut buf), Ok(None)));
    assert!(buf.capacity() <= 1 << 20, "{}", buf.capacity());
}

#[test]
fn the_frame_limit_is_configurable_both_ways() {
    let small = FrameConfig { max_frame: 1000 };
    let big = Message::BatchResult(good_result(100));
    let mut out = vec![1, 2, 3];
    assert!(matches!(encode_frame(&big, &mut out, &small), Err(ProtoError::FrameTooLarge { .. })));
    assert_eq!(out, [1, 2, 3], "a refused frame leaves the buffer as it was");
    let frame = frame_of(&big);
    assert!(matches!(decode_frame(&frame, &small), Err(ProtoError::FrameTooLarge { .. })));
    assert!(matches!(
        FrameReader::new(Cursor::new(&frame), small).read_message(),
        Err(ProtoError::FrameTooLarge { .. })
    ));
}

#[test]
fn unknown_message_types_and_empty_frames_are_fatal() {
    for tag in [0u8, 21, 99, 255] {
        let err = decode_one(&raw_frame(tag, &[1, 2, 3])).expect_err("unknown");
        assert!(matches!(err, ProtoError::UnknownMessageType(t) if t == tag));
        assert!(err.is_fatal());
        assert_eq!(err.code(), ErrorCode::UnknownMessageType);
    }
    assert!(matches!(decode_one(&0u32.to_le_bytes()), Err(ProtoError::EmptyFrame)));
}

#[test]
fn wrong_versions_magic_and_roles_are_refused() {
    let hello = |magic: &[u8; 4], version: u16, role: u8| {
        let mut body = magic.to_vec();
        body.extend(version.to_le_bytes());
        body.push(role);
        raw_frame(MessageKind::Hello.tag(), &body)
    };
    assert_eq!(
        decode_one(&hello(&MAGIC, PROTOCOL_VERSION, 2)).expect("ok"),
        Ok(Message::Hello(Hello::new(Role::Worker)))
    );
    let err = decode_one(&hello(&MAGIC, PROTOCOL_VERSION + 1, 2)).expect_err("version");
    assert!(
        matches!(err, ProtoError::VersionMismatch { ours: PROTOCOL_VERSION, theirs } if theirs == PROTOCOL_VERSION + 1)
    );
    assert_eq!(err.code(), ErrorCode::VersionMismatch);
    assert!(matches!(decode_one(&hello(&MAGIC, 0, 2)), Err(ProtoError::VersionMismatch { theirs: 0, .. })));
    assert!(matches!(decode_one(&hello(b"HTTP", 1, 2)), Err(ProtoError::BadMagic(m)) if &m == b"HTTP"));
    assert!(matches!(decode_one(&hello(&MAGIC, PROTOCOL_VERSION, 9)), Err(ProtoError::UnknownRole(9))));
    let mut long = hello(&MAGIC, PROTOCOL_VERSION, 2);
    long.push(0);
    long[0] += 1;
    assert!(matches!(decode_one(&long), Err(ProtoError::TrailingBytes { kind: MessageKind::Hello, count: 1 })));
    // An encoder can never produce another version's hello.
    let mut out = Vec::new();
    let other = PROTOCOL_VERSION + 7;
    encode_frame(&Message::Hello(Hello { version: other, role: Role::Tool }), &mut out, &cfg()).expect("encodes");
    assert!(matches!(decode_one(&out), Err(ProtoError::VersionMismatch { theirs, .. }) if theirs == other));
}

#[test]
fn trailing_bytes_after_a_body_are_fatal() {
    let mut body = postcard::to_allocvec(&Registered { worker_id: 1, load_report_interval_ms: 100 }).expect("body");
    body.push(0);
    assert!(matches!(
        decode_one(&raw_frame(MessageKind::Registered.tag(), &body)),
        Err(ProtoError::TrailingBytes { kind: MessageKind::Registered, count: 1 })
    ));
}

/// Encodes without validation, as a hostile peer could.
fn unchecked<T: serde::Serialize>(kind: MessageKind, value: &T) -> Vec<u8> {
    raw_frame(kind.tag(), &postcard::to_allocvec(value).expect("postcard"))
}

#[test]
fn nan_and_infinite_cameras_are_rejected_with_the_batch_ids() {
    for (slot, value) in [(3usize, f32::NAN), (14, f32::INFINITY), (20, f32::NEG_INFINITY), (31, f32::NAN)] {
        let mut batch = good_batch();
        if slot < 16 {
            batch.camera.view.as_mut()[slot] = value;
        } else {
            batch.camera.projection.as_mut()[slot - 16] = value;
        }
        let mut via_api = Vec::new();
        encode_frame_unchecked(&Message::RayBatch(batch.clone()), &mut via_api, &cfg()).expect("unchecked");
        assert_eq!(via_api, unchecked(MessageKind::RayBatch, &batch));
        let r = rejected(&unchecked(MessageKind::RayBatch, &batch));
        assert_eq!(r.kind, MessageKind::RayBatch);
        assert_eq!(r.ids, Some(batch.ids));
        assert!(matches!(r.error, ValidationError::NonFinite { .. }), "{r}");
        // And we refuse to send it.
        let err = encode_frame(&Message::RayBatch(batch), &mut Vec::new(), &cfg()).expect_err("invalid");
        assert!(!err.is_fatal());
    }
}

#[test]
fn derived_views_and_reuse_limits_are_checked() {
    let mut batch = good_batch();
    batch.derived.push(DerivedView { ids: batch.ids, camera: good_camera(), pixels: vec![0, 5, 64 * 48 - 1] });
    let mut bytes = Vec::new();
    encode_frame(&Message::RayBatch(batch.clone()), &mut bytes, &cfg()).expect("valid");
    assert_eq!(decode_one(&bytes).expect("frame").expect("valid"), Message::RayBatch(batch.clone()));
    let mut bad = batch.clone();
    bad.derived[0].pixels.push(64 * 48);
    assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::PixelOutOfImage { .. }));
    let mut bad = batch.clone();
    bad.derived[0].camera.view.as_mut()[0] = f32::NAN;
    assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::NonFinite { .. }));
    for (angle, contrast) in [(-1.0, 0.2), (91.0, 0.2), (f32::NAN, 0.2), (6.0, -0.1), (6.0, f32::NAN)] {
        let mut bad = batch.clone();
        bad.reuse = ReuseLimits { max_angle_deg: angle, max_contrast: contrast, ..ReuseLimits::default() };
        assert!(
            matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::OutOfRange { .. }),
            "{angle} {contrast}"
        );
    }
    let mut bad = batch.clone();
    bad.reuse.previous_frames = ReuseLimits::MAX_PREVIOUS_FRAMES + 1;
    assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::Count { .. }));
    // A render ahead: kept for later batches (previous_frames >= 1), no derived views.
    let mut ahead = batch.clone();
    ahead.derived.clear();
    ahead.reuse = ReuseLimits { previous_frames: 3, ahead: true, ..ReuseLimits::default() };
    let mut bytes = Vec::new();
    encode_frame(&Message::RayBatch(ahead.clone()), &mut bytes, &cfg()).expect("valid");
    assert_eq!(decode_one(&bytes).expect("frame").expect("valid"), Message::RayBatch(ahead.clone()));
    let mut bad = ahead.clone();
    bad.reuse.previous_frames = 0;
    assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::Count { .. }));
    let mut bad = ahead;
    bad.derived = batch.derived.clone();
    assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::Count { .. }));
    let mut bad = batch;
    bad.derived = vec![bad.derived[0].clone(); validate::MAX_VIEWS as usize + 1];
    assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &bad)).error, ValidationError::Count { .. }));
}

#[test]
fn occluders_are_checked() {
    let mut batch = good_batch();
    let grid = SolidGrid { min: [0.0; 3], max: [1.0; 3], dims: [4, 4, 4], bits: vec![u64::MAX] };
    batch.occluders = vec![grid.clone()];
    assert!(decode_one(&unchecked(MessageKind::RayBatch, &batch)).expect("decodes").is_ok());
    for bad in [
        SolidGrid { bits: vec![0; 2], ..grid.clone() },
        SolidGrid { dims: [0, 4, 4], ..grid.clone() },
        SolidGrid { dims: [64, 64, 65], bits: vec![0; 64 * 65], ..grid.clone() },
        SolidGrid { max: [1.0, 0.0, 1.0], ..grid.clone() },
        SolidGrid { min: [f32::NEG_INFINITY, 0.0, 0.0], ..grid.clone() },
    ] {
        batch.occluders = vec![bad];
        assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &batch)).error, ValidationError::Occluder(_)));
    }
    batch.occluders = vec![grid; RayBatch::MAX_OCCLUDERS + 1];
    assert!(matches!(
        rejected(&unchecked(MessageKind::RayBatch, &batch)).error,
        ValidationError::Count { field: "occluders", .. }
    ));
}

#[test]
fn pixel_sets_out_of_the_image_and_bad_sizes_are_rejected() {
    let mut batch = good_batch();
    batch.pixels.push(64 * 48);
    assert_eq!(
        rejected(&unchecked(MessageKind::RayBatch, &batch)).error,
        ValidationError::PixelOutOfImage { index: 64 * 48, width: 64, height: 48 }
    );
    batch.pixels = vec![u32::MAX];
    assert!(matches!(
        rejected(&unchecked(MessageKind::RayBatch, &batch)).error,
        ValidationError::PixelOutOfImage { .. }
    ));
    batch.pixels = vec![];
    assert!(matches!(
        rejected(&unchecked(MessageKind::RayBatch, &batch)).error,
        ValidationError::Count { field: "pixels", .. }
    ));
    for (w, h) in [(0, 48), (64, 0), (16385, 1)] {
        let mut batch = good_batch();
        batch.camera.width = w;
        batch.camera.height = h;
        batch.pixels = vec![0];
        assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &batch)).error, ValidationError::ImageSize { .. }));
    }
    // The 16384^2 image does not overflow u32 arithmetic.
    let mut batch = good_batch();
    batch.camera.width = 16384;
    batch.camera.height = 16384;
    batch.pixels = vec![u32::MAX];
    assert!(decode_one(&unchecked(MessageKind::RayBatch, &batch)).expect("decodes").is_err());
    batch.pixels = vec![16384 * 16384 - 1];
    assert!(decode_one(&unchecked(MessageKind::RayBatch, &batch)).expect("decodes").is_ok());
}

/// What the compact encoding promises (see `compact`): only the touched pixels, in order;
/// colour and depth to half-float precision, opacity to 16 bits.
fn check_compact(sent: &BatchResult, got: &BatchResult) -> Result<(), TestCaseError> {
    prop_assert_eq!(got.encoding, ResultEncoding::Compact);
    prop_assert_eq!(
        (got.ids, got.worker_id, got.width, got.height),
        (sent.ids, sent.worker_id, sent.width, sent.height)
    );
    prop_assert_eq!((got.render_time_us, got.stats), (sent.render_time_us, sent.stats));
    // Touched pixels, except those whose opacity and colour both round to 0 on the wire
    // (misses again after decoding).
    let rounds_to_zero = |i: usize| {
        (sent.opacity[i].clamp(0.0, 1.0) * 65535.0).round() == 0.0
            && sent.color[i].iter().all(|&c| half::f16::from_f32(c).to_f32() == 0.0)
    };
    let kept: Vec<usize> = (0..sent.pixels.len())
        .filter(|&i| (sent.opacity[i] > 0.0 || sent.color[i] != [0.0; 3]) && !rounds_to_zero(i))
        .collect();
    prop_assert_eq!(got.pixels.len(), kept.len());
    let half_max = 65504.0f32;
    let close = |want: f32, have: f32| {
        let want = want.clamp(-half_max, half_max);
        (want - have).abs() <= want.abs() * 2f32.powi(-11) + 2f32.powi(-24)
    };
    for (j, &i) in kept.iter().enumerate() {
        prop_assert_eq!(got.pixels[j], sent.pixels[i]);
        for k in 0..3 {
            prop_assert!(
                close(sent.color[i][k], got.color[j][k]),
                "colour {} vs {}",
                sent.color[i][k],
                got.color[j][k]
            );
        }
        prop_assert!((sent.opacity[i] - got.opacity[j]).abs() <= 1.0 / 131070.0 + 1e-7);
        prop_assert!(close(sent.depth[i], got.depth[j]), "depth {} vs {}", sent.depth[i], got.depth[j]);
    }
    Ok(())
}

proptest! {
    #[test]
    fn compact_results_keep_the_touched_pixels_within_the_stated_error(r in batch_result()) {
        let sent = BatchResult { encoding: ResultEncoding::Compact, ..r };
        let got = match decode_one(&frame_of(&Message::BatchResult(sent.clone()))) {
            Ok(Ok(Message::BatchResult(got))) => got,
            other => panic!("{other:?}"),
        };
        check_compact(&sent, &got)?;
        // Decoding again changes nothing: the encoding is idempotent on its own output.
        let again = match decode_one(&frame_of(&Message::BatchResult(got.clone()))) {
            Ok(Ok(Message::BatchResult(again))) => again,
            other => panic!("{other:?}"),
        };
        prop_assert_eq!(again, got);
    }
}

#[test]
fn compact_results_cost_about_eleven_bytes_per_touched_pixel() {
    // 4096 pixels in a row, a quarter of them touched (in one run): a quarter of the bytes
    // and less than half per pixel.
    let mut r = good_result(4096);
    r.pixels = (0..4096).collect();
    r.opacity = (0..4096).map(|i| if (1000..2024).contains(&i) { 0.5 } else { 0.0 }).collect();
    r.color = (0..4096).map(|i| if (1000..2024).contains(&i) { [0.1, 0.2, 0.3] } else { [0.0; 3] }).collect();
    let f32_bytes = frame_of(&Message::BatchResult(r.clone())).len();
    let compact = BatchResult { encoding: ResultEncoding::Compact, ..r };
    let compact_bytes = frame_of(&Message::BatchResult(compact)).len();
    assert!(f32_bytes >= 4096 * 24, "{f32_bytes}");
    assert!(compact_bytes <= 1024 * (compact::VALUE_BYTES + 1) + 4 + 64, "{compact_bytes}");
    // Nothing touched: a result without pixels, still valid (the composer learns the batch
    // is done and that the object covers none of it).
    let mut empty = good_result(16);
    empty.opacity = vec![0.0; 16];
    empty.color = vec![[0.0; 3]; 16];
    empty.encoding = ResultEncoding::Compact;
    match decode_one(&frame_of(&Message::BatchResult(empty))) {
        Ok(Ok(Message::BatchResult(got))) => assert!(got.pixels.is_empty() && got.color.is_empty()),
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_compact_pixel_that_rounds_to_nothing_decodes_as_a_miss() {
    // Pixel 0 has an opacity below 16-bit resolution and no colour: sent (it is touched), but
    // its values arrive as zeros. The decoder drops it, so that the decoded result encodes to
    // the same pixels again (the `decode` fuzz target found the mismatch).
    let mut r = good_result(4);
    r.opacity[0] = 1e-6;
    r.color[0] = [0.0; 3];
    r.encoding = ResultEncoding::Compact;
    let decoded = match decode_one(&frame_of(&Message::BatchResult(r.clone()))) {
        Ok(Ok(Message::BatchResult(got))) => got,
        other => panic!("{other:?}"),
    };
    assert_eq!(decoded.pixels, r.pixels[1..].to_vec());
    match decode_one(&frame_of(&Message::BatchResult(decoded.clone()))) {
        Ok(Ok(Message::BatchResult(again))) => assert_eq!(again, decoded),
        other => panic!("{other:?}"),
    }
}

#[test]
fn hostile_compact_results_are_rejected_or_refused() {
    let r = BatchResult { encoding: ResultEncoding::Compact, ..good_result(8) };
    let frame = frame_of(&Message::BatchResult(r));
    // The last 10 bytes before the render time and stats are the last pixel's values; set
    // them to all ones: NaN colour halves and depth -> a rejected (not fatal) message.
    let mut bad = frame.clone();
    let tail = bad.len();
    let body = &mut bad[..tail];
    let values_end = body.len() - (1 + 3 + 1 + 1 + 1); // render_time_us (1234: 2 bytes) + 3 stats varints
    for b in &mut body[values_end - 12..values_end - 2] {
        *b = 0xff;
    }
    assert!(matches!(decode_one(&bad), Ok(Err(_)) | Err(_)), "NaN values must not pass");
    // Index deltas past the image: rejected with the index.
    let mut far = good_result(2);
    far.opacity = vec![1.0, 1.0];
    far.pixels = vec![0, 640 * 480 - 1];
    far.encoding = ResultEncoding::Compact;
    let mut frame = frame_of(&Message::BatchResult(far));
    // The second delta (zigzag 2 * 307199) is a three-byte varint after the first one; make
    // it larger by setting its top byte.
    let pos = frame.iter().position(|&b| b == 0xfe).expect("delta bytes");
    frame[pos + 2] = 0x7f;
    assert!(matches!(rejected(&frame).error, ValidationError::PixelOutOfImage { .. }));
    // Truncated index varints and values that are not whole pixels are fatal.
    for body in [vec![0u8; 3], vec![0xff; 40]] {
        assert!(decode_one(&raw_frame(compact::COMPACT_TAG, &body)).is_err());
    }
}

#[test]
fn mismatched_and_out_of_range_result_arrays_are_rejected() {
    let mut r = good_result(10);
    r.depth.pop();
    assert_eq!(
        rejected(&unchecked(MessageKind::BatchResult, &r)).error,
        ValidationError::LengthMismatch { field: "depth", len: 9, expected: 10 }
    );
    let mut r = good_result(10);
    r.color.push([0.0; 3]);
    assert!(matches!(
        rejected(&unchecked(MessageKind::BatchResult, &r)).error,
        ValidationError::LengthMismatch { field: "color", .. }
    ));
    let mut r = good_result(10);
    r.opacity[3] = 1.5;
    assert!(matches!(
        rejected(&unchecked(MessageKind::BatchResult, &r)).error,
        ValidationError::OutOfRange { field: "opacity", .. }
    ));
    let mut r = good_result(10);
    r.color[2][1] = f32::NAN;
    assert!(matches!(
        rejected(&unchecked(MessageKind::BatchResult, &r)).error,
        ValidationError::NonFinite { field: "color" }
    ));
    let mut r = good_result(10);
    r.depth[0] = -1.0;
    assert!(matches!(
        rejected(&unchecked(MessageKind::BatchResult, &r)).error,
        ValidationError::OutOfRange { field: "depth", .. }
    ));
}

#[test]
fn names_asset_ids_and_addresses_are_checked() {
    for good in ["diffuse", "lego.v2", "room-day", "a_b-c.d", "x"] {
        assert!(validate::asset_id(good).is_ok(), "{good}");
    }
    let too_long = "a".repeat(129);
    for bad in ["", "..", "../etc/passwd", "a/b", "a\\b", ".hidden", "a..b", "lego/../x", "é", "a b", "a\0b", &too_long]
    {
        assert!(validate::asset_id(bad).is_err(), "{bad:?}");
        let mut batch = good_batch();
        batch.asset_id = bad.to_string();
        assert!(matches!(rejected(&unchecked(MessageKind::RayBatch, &batch)).error, ValidationError::BadString { .. }));
    }
    for good in ["127.0.0.1:7000", "composer-0.nephele:9000", "[::1]:80"] {
        assert!(validate::address(good).is_ok(), "{good}");
    }
    for bad in ["", "127.0.0.1", ":80", "host:0", "host:65536", "host:http", "a b:1"] {
        assert!(validate::address(bad).is_err(), "{bad:?}");
    }
    let register = |name: &str, threads, kernels: Vec<String>, rays_per_second| {
        Message::Register(Register { name: name.into(), threads, kernels, rays_per_second, device: "cpu".into() })
    };
    let ok = register("w1", 4, vec!["pathtrace".into()], 1e6);
    assert!(validate::message(&ok).is_ok());
    for bad in [
        register("", 4, vec!["pathtrace".into()], 1e6),
        register("w/1", 4, vec!["pathtrace".into()], 1e6),
        register("w1", 0, vec!["pathtrace".into()], 1e6),
        register("w1", 4, vec![], 1e6),
        register("w1", 4, vec!["".into()], 1e6),
        register("w1", 4, vec!["pathtrace".into()], f64::NAN),
        register("w1", 4, vec!["pathtrace".into()], -1.0),
    ] {
        assert!(validate::message(&bad).is_err(), "{bad:?}");
    }
}

fn good_open() -> OpenStream {
    OpenStream {
        session_id: 4,
        session_name: "s1-abc123".into(),
        offer_sdp: "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 96\r\n".into(),
        views: 2,
        width: 640,
        height: 480,
        target_fps: 30.0,
    }
}

fn good_plan() -> FramePlan {
    FramePlan {
        session_id: 4,
        frame_id: 12,
        pose_sequence: 99,
        client_time_ms: 1234.5,
        width: 64,
        height: 48,
        views: 2,
        parts: vec![PlanPart { view: 0, task_id: 3, object_id: 1 }, PlanPart { view: 1, task_id: 4, object_id: 1 }],
        deadline_in_us: Some(40_000),
    }
}

#[test]
fn composer_messages_round_trip_and_bad_fields_are_rejected() {
    let pose =
        ClientPose { session_id: 4, sequence: 7, client_time_ms: 16.5, views: vec![good_camera(), good_camera()] };
    let good = [
        Message::ComposerRegister(ComposerRegister {
            name: "composer-0".into(),
            results_address: "127.0.0.1:7100".into(),
        }),
        Message::OpenStream(good_open()),
        Message::StreamOpened(StreamOpened { session_id: 4, answer: Ok("v=0\r\n".into()) }),
        Message::StreamOpened(StreamOpened { session_id: 4, answer: Err("no H.264 in the offer".into()) }),
        Message::ClientPose(pose.clone()),
        Message::FramePlan(good_plan()),
        Message::FramePlan(FramePlan { parts: vec![], deadline_in_us: None, ..good_plan() }),
        Message::ReleaseTask(ReleaseTask { task_id: u64::MAX }),
        Message::CloseStream(CloseStream { session_id: 4, reason: "the client closed it".into() }),
    ];
    for message in &good {
        assert_eq!(decode_one(&frame_of(message)).expect("decodes"), Ok(message.clone()), "{message:?}");
    }

    let huge_sdp = format!("v=0{}", "a".repeat(validate::MAX_SDP_LEN));
    let bad: Vec<(Message, &str)> = vec![
        (
            Message::ComposerRegister(ComposerRegister { name: "a/b".into(), results_address: "127.0.0.1:1".into() }),
            "composer name",
        ),
        (
            Message::ComposerRegister(ComposerRegister { name: "c".into(), results_address: "nowhere".into() }),
            "address",
        ),
        (Message::OpenStream(OpenStream { offer_sdp: huge_sdp.clone(), ..good_open() }), "offer_sdp"),
        (Message::OpenStream(OpenStream { offer_sdp: String::new(), ..good_open() }), "offer_sdp"),
        (Message::OpenStream(OpenStream { session_name: "../x".into(), ..good_open() }), "session name"),
        (Message::OpenStream(OpenStream { views: 0, ..good_open() }), "views"),
        (Message::OpenStream(OpenStream { views: 65, ..good_open() }), "views"),
        (Message::OpenStream(OpenStream { views: 64, width: 4096, ..good_open() }), "image size"),
        (Message::OpenStream(OpenStream { width: 0, ..good_open() }), "image size"),
        (Message::OpenStream(OpenStream { target_fps: f32::NAN, ..good_open() }), "target_fps"),
        (Message::OpenStream(OpenStream { target_fps: 0.0, ..good_open() }), "target_fps"),
        (Message::StreamOpened(StreamOpened { session_id: 1, answer: Ok(huge_sdp) }), "answer sdp"),
        (Message::StreamOpened(StreamOpened { session_id: 1, answer: Err("x".repeat(5000)) }), "answer error"),
        (Message::ClientPose(ClientPose { views: vec![], ..pose.clone() }), "views"),
        (Message::ClientPose(ClientPose { views: vec![good_camera(); 65], ..pose.clone() }), "views"),
        (Message::ClientPose(ClientPose { client_time_ms: f64::NAN, ..pose.clone() }), "client_time_ms"),
        (
            Message::ClientPose(ClientPose {
                views: vec![
                    good_camera(),
                    ViewProjection { view: Mat4::from_cols_array(&[f32::INFINITY; 16]), ..good_camera() },
                ],
                ..pose.clone()
            }),
            "camera view matrix",
        ),
        (
            Message::ClientPose(ClientPose { views: vec![ViewProjection { width: 0, ..good_camera() }], ..pose }),
            "image size",
        ),
        (
            Message::FramePlan(FramePlan {
                parts: vec![PlanPart { view: 2, task_id: 1, object_id: 1 }],
                ..good_plan()
            }),
            "part view",
        ),
        (Message::FramePlan(FramePlan { views: 0, parts: vec![], ..good_plan() }), "views"),
        (Message::FramePlan(FramePlan { height: 16385, ..good_plan() }), "image size"),
        (Message::FramePlan(FramePlan { client_time_ms: f64::INFINITY, ..good_plan() }), "client_time_ms"),
        (Message::CloseStream(CloseStream { session_id: 1, reason: "r".repeat(5000) }), "reason"),
    ];
    for (message, field) in bad {
        // We refuse to send it...
        let err = encode_frame(&message, &mut Vec::new(), &cfg()).expect_err("invalid");
        assert!(!err.is_fatal(), "{message:?}");
        // ...and a peer that sends it anyway gets it rejected, the stream still in sync.
        let mut bytes = Vec::new();
        encode_frame_unchecked(&message, &mut bytes, &cfg()).expect("unchecked");
        let r = rejected(&bytes);
        assert_eq!(r.kind, message.kind());
        let text = r.error.to_string();
        assert!(text.contains(field), "{field:?} not in {text:?} for {message:?}");
    }
}

#[test]
fn batch_ids_carry_the_task() {
    let batch = good_batch();
    let Ok(Message::RayBatch(decoded)) = decode_one(&frame_of(&Message::RayBatch(batch.clone()))).expect("decodes")
    else {
        panic!("a ray batch")
    };
    assert_eq!(decoded.ids.task_id, 5);
    let result = good_result(3);
    let Ok(Message::BatchResult(decoded)) = decode_one(&frame_of(&Message::BatchResult(result))).expect("decodes")
    else {
        panic!("a batch result")
    };
    assert_eq!(decoded.ids.task_id, 8);
}

#[test]
fn rejected_messages_leave_the_stream_in_sync() {
    let mut bad = good_batch();
    bad.camera.view.as_mut()[0] = f32::NAN;
    let mut bytes = unchecked(MessageKind::RayBatch, &bad);
    bytes.extend(frame_of(&Message::RayBatch(good_batch())));
    let mut reader = FrameReader::new(Cursor::new(&bytes), cfg());
    let first = reader.read_message().expect("framing is fine");
    assert_eq!(first.expect_err("rejected").ids.map(|i| i.batch_id), Some(7));
    assert_eq!(reader.read_message().expect("second"), Ok(Message::RayBatch(good_batch())));
    let mut codec = FrameCodec::new(cfg());
    let mut buf = BytesMut::from(&bytes[..]);
    assert!(matches!(codec.decode(&mut buf), Ok(Some(Err(_)))));
    assert!(matches!(codec.decode(&mut buf), Ok(Some(Ok(Message::RayBatch(_))))));
}

#[test]
fn error_messages_fit_the_text_limit() {
    let long = ProtoError::Malformed { kind: MessageKind::Register, reason: "é".repeat(5000) };
    let Message::Error(e) = error_message(&long) else { panic!("error message") };
    assert!(e.message.len() <= validate::MAX_TEXT_LEN && e.code == ErrorCode::Malformed);
    assert!(validate::message(&Message::Error(e)).is_ok());
}

// ---------------------------------------------------------------------------------------
// Handshakes over real sockets

#[test]
fn blocking_handshake_over_tcp() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = listener.local_addr().expect("addr");
    let server = std::thread::spawn(move || {
        let (stream, _) = listener.accept().expect("accept");
        let mut reader = FrameReader::new(stream.try_clone().expect("clone"), cfg());
        let mut writer = FrameWriter::new(stream, cfg());
        let peer = frame::handshake(&mut reader, &mut writer, Role::Master, &[Role::Worker], None).expect("handshake");
        assert_eq!(peer.role, Role::Worker);
        let msg = reader.read_message().expect("frame").expect("valid");
        writer.write_message(&msg).expect("echo");
    });
    let stream = std::net::TcpStream::connect(addr).expect("connect");
    let mut reader = FrameReader::new(stream.try_clone().expect("clone"), cfg());
    let mut writer = FrameWriter::new(stream, cfg());
    let peer = frame::handshake(&mut reader, &mut writer, Role::Worker, &[Role::Master], None).expect("handshake");
    assert_eq!(peer, Hello::new(Role::Master));
    let batch = Message::BatchResult(good_result(1000));
    writer.write_message(&batch).expect("send");
    assert_eq!(reader.read_message().expect("echo"), Ok(batch));
    server.join().expect("server");
}

#[tokio::test]
async fn async_handshake_refuses_wrong_roles_and_versions() {
    use futures_util::StreamExt;
    use std::time::Duration;
    use tokio::io::AsyncWriteExt;

    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    let timeout = Duration::from_secs(5);

    // A worker where a composer is expected: refused, and told why.
    let server = tokio::spawn(async move {
        let (s, _) = listener.accept().await.expect("accept");
        let mut conn = stream::framed(s, cfg());
        let err =
            stream::handshake(&mut conn, Role::Master, &[Role::Composer], None, timeout).await.expect_err("wrong role");
        assert!(matches!(err, ProtoError::WrongRole(Role::Worker)));
        let (s, _) = listener.accept().await.expect("accept");
        let mut conn = stream::framed(s, cfg());
        let err =
            stream::handshake(&mut conn, Role::Master, &[Role::Worker], None, timeout).await.expect_err("version");
        assert!(matches!(err, ProtoError::VersionMismatch { theirs, .. } if theirs == PROTOCOL_VERSION + 1));
    });
    let mut conn = stream::framed(tokio::net::TcpStream::connect(addr).await.expect("connect"), cfg());
    // We accept the master's Hello; it refuses ours, and says why instead of a challenge.
    let err = stream::handshake(&mut conn, Role::Worker, &[Role::Master], None, timeout).await.expect_err("refused");
    assert!(matches!(err, ProtoError::Refused { code: ErrorCode::InvalidField, .. }), "{err}");

    // A peer from the future.
    let mut raw = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let mut body = MAGIC.to_vec();
    body.extend((PROTOCOL_VERSION + 1).to_le_bytes());
    body.push(Role::Worker.to_byte());
    raw.write_all(&raw_frame(MessageKind::Hello.tag(), &body)).await.expect("send");
    let mut conn = stream::framed(raw, cfg());
    // Our hello, then the error telling why.
    assert!(matches!(conn.next().await, Some(Ok(Ok(Message::Hello(_))))));
    match conn.next().await {
        Some(Ok(Ok(Message::Error(e)))) => assert_eq!(e.code, ErrorCode::VersionMismatch),
        other => panic!("expected an error message, got {other:?}"),
    }
    server.await.expect("server");
}

// ---------------------------------------------------------------------------------------
// The farm credential

fn secret(text: &str) -> FarmSecret {
    FarmSecret::from_text(text, "test").expect("secret")
}

/// Runs an async handshake between a `server` role and a `client` role with the given
/// secrets; returns both sides' results.
async fn handshake_pair(
    server: (Role, Option<FarmSecret>),
    client: (Role, Option<FarmSecret>),
) -> (Result<Hello, ProtoError>, Result<Hello, ProtoError>) {
    use std::time::Duration;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    let timeout = Duration::from_secs(5);
    let (server_role, server_secret) = server;
    let accepted = tokio::spawn(async move {
        let (s, _) = listener.accept().await.expect("accept");
        let mut conn = stream::framed(s, cfg());
        let all = [Role::Master, Role::Worker, Role::Composer, Role::Tool];
        stream::handshake(&mut conn, server_role, &all, server_secret.as_ref(), timeout).await
    });
    let mut conn = stream::framed(tokio::net::TcpStream::connect(addr).await.expect("connect"), cfg());
    let all = [Role::Master, Role::Worker, Role::Composer, Role::Tool];
    let ours = stream::handshake(&mut conn, client.0, &all, client.1.as_ref(), timeout).await;
    (accepted.await.expect("server task"), ours)
}

#[tokio::test]
async fn the_farm_credential_admits_holders_of_the_secret_and_refuses_the_rest() {
    let good = || Some(secret("a farm secret of some length"));
    // Same secret on both sides, every pair of roles that meets in a farm.
    for (server, client) in [
        (Role::Master, Role::Worker),
        (Role::Master, Role::Composer),
        (Role::Composer, Role::Worker),
        (Role::Composer, Role::Tool),
    ] {
        let (s, c) = handshake_pair((server, good()), (client, good())).await;
        assert_eq!(s.expect("server admits").role, client);
        assert_eq!(c.expect("client admits").role, server);
    }
    // An open farm: nobody holds a secret.
    let (s, c) = handshake_pair((Role::Master, None), (Role::Worker, None)).await;
    assert!(s.is_ok() && c.is_ok());

    // A worker without the secret: the master refuses it; the worker reads why.
    let (s, c) = handshake_pair((Role::Master, good()), (Role::Worker, None)).await;
    let s = s.expect_err("no secret");
    assert!(matches!(&s, ProtoError::Unauthenticated(why) if why.contains("no farm secret")), "{s}");
    let c = c.expect_err("refused");
    assert!(matches!(&c, ProtoError::Refused { code: ErrorCode::Unauthenticated, .. }), "{c}");

    // A worker with the wrong secret.
    let (s, c) =
        handshake_pair((Role::Master, good()), (Role::Worker, Some(secret("not the farm secret at all")))).await;
    let s = s.expect_err("wrong secret");
    assert!(matches!(&s, ProtoError::Unauthenticated(why) if why.contains("wrong")), "{s}");
    assert!(matches!(c, Err(ProtoError::Refused { code: ErrorCode::Unauthenticated, .. })));

    // Mutual: a worker holding the secret refuses a master (or composer) without it, so a
    // stranger cannot pose as the farm and collect its results.
    let (s, c) = handshake_pair((Role::Master, None), (Role::Worker, good())).await;
    let c = c.expect_err("the master has no secret");
    assert!(matches!(&c, ProtoError::Unauthenticated(why) if why.contains("master")), "{c}");
    // (The master, proving last, has finished its side by then; it reads the worker's
    // refusal where it expects the registration.)
    drop(s);
    // Different secrets: the composer (checking first) refuses, the worker reads why.
    let (s, c) =
        handshake_pair((Role::Composer, Some(secret("another secret, not ours"))), (Role::Worker, good())).await;
    assert!(matches!(s, Err(ProtoError::Unauthenticated(_))));
    assert!(matches!(c, Err(ProtoError::Refused { code: ErrorCode::Unauthenticated, .. })));
}

#[test]
fn blocking_handshake_proves_the_secret_too() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = listener.local_addr().expect("addr");
    let server = std::thread::spawn(move || {
        let mut results = Vec::new();
        for _ in 0..2 {
            let (stream, _) = listener.accept().expect("accept");
            let mut reader = FrameReader::new(stream.try_clone().expect("clone"), cfg());
            let mut writer = FrameWriter::new(stream, cfg());
            let s = secret("the blocking farm secret");
            results.push(frame::handshake(&mut reader, &mut writer, Role::Master, &[Role::Worker], Some(&s)).is_ok());
        }
        results
    });
    for (text, ok) in [("the blocking farm secret", true), ("a different farm secret", false)] {
        let stream = std::net::TcpStream::connect(addr).expect("connect");
        let mut reader = FrameReader::new(stream.try_clone().expect("clone"), cfg());
        let mut writer = FrameWriter::new(stream, cfg());
        let r = frame::handshake(&mut reader, &mut writer, Role::Worker, &[Role::Master], Some(&secret(text)));
        assert_eq!(r.is_ok(), ok, "{r:?}");
    }
    assert_eq!(server.join().expect("server"), vec![true, false]);
}

#[test]
fn proofs_are_bound_to_the_nonce_and_the_roles() {
    use crate::auth::{prove, verify};
    let s = secret("the farm secret for proofs");
    let (a, b, c) = ([1u8; 32], [2u8; 32], [3u8; 32]);
    let proof = prove(Some(&s), Role::Worker, Role::Master, &a, &b);
    assert!(verify(Some(&s), Role::Worker, Role::Master, &a, &b, &proof).is_ok());
    // Replayed against a fresh challenge.
    assert!(verify(Some(&s), Role::Worker, Role::Master, &c, &b, &proof).is_err());
    // Reflected: the master's own proof does not pass for a worker's.
    let reflected = prove(Some(&s), Role::Master, Role::Worker, &a, &b);
    assert!(verify(Some(&s), Role::Worker, Role::Master, &a, &b, &reflected).is_err());
    // Another secret, no secret, a flipped bit.
    let other = secret("some other farm secret");
    assert!(verify(Some(&other), Role::Worker, Role::Master, &a, &b, &proof).is_err());
    assert!(verify(Some(&s), Role::Worker, Role::Master, &a, &b, &Proof { mac: None }).is_err());
    let mut flipped = proof;
    if let Some(m) = flipped.mac.as_mut() {
        m[7] ^= 1;
    }
    assert!(verify(Some(&s), Role::Worker, Role::Master, &a, &b, &flipped).is_err());
    // An open side accepts anything and proves nothing.
    assert!(verify(None, Role::Worker, Role::Master, &a, &b, &Proof { mac: None }).is_ok());
    assert_eq!(prove(None, Role::Worker, Role::Master, &a, &b).mac, None);
}

#[test]
fn farm_secrets_are_trimmed_long_enough_fresh_and_never_printed() {
    let s = FarmSecret::from_text("  0123456789abcdef-secret\n", "env").expect("secret");
    assert_eq!(s.expose(), "0123456789abcdef-secret");
    let short = FarmSecret::from_text("short\n", "env").expect_err("too short");
    assert!(short.to_string().contains("at least 16"), "{short}");
    let (g1, g2) = (FarmSecret::generate().expect("random"), FarmSecret::generate().expect("random"));
    assert_eq!(g1.expose().len(), 64);
    assert!(g1.expose().bytes().all(|b| b.is_ascii_hexdigit()));
    assert_ne!(g1, g2);
    assert!(!format!("{g1:?}").contains(g1.expose()));
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("farm-secret");
    std::fs::write(&path, format!("{}\n", g1.expose())).expect("write");
    assert_eq!(FarmSecret::read_file(&path).expect("read"), g1);
    std::fs::write(&path, vec![b'x'; 10_000]).expect("write");
    assert!(FarmSecret::read_file(&path).is_err(), "a huge file is refused");
    assert!(FarmSecret::read_file(&dir.path().join("missing")).is_err());
}

/// Writes one valid frame of every message kind (and a few broken ones) as seeds for the
/// fuzz target: `cargo test -p nephele-proto write_fuzz_seeds -- --ignored`.
#[test]
#[ignore = "writes files: run by hand to refresh proto/fuzz/seeds"]
fn write_fuzz_seeds() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/decode");
    std::fs::create_dir_all(&dir).expect("seed dir");
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let mut seen = std::collections::HashSet::new();
    let mut count = 0;
    while seen.len() < MessageKind::ALL.len() {
        let message = proptest::strategy::ValueTree::current(&message().new_tree(&mut runner).expect("sample"));
        if seen.insert(message.kind()) {
            std::fs::write(dir.join(format!("{}.bin", message.kind())), frame_of(&message)).expect("write");
            count += 1;
        }
    }
    let mut bad = good_batch();
    bad.camera.view.as_mut()[0] = f32::NAN;
    std::fs::write(dir.join("RayBatch-nan.bin"), unchecked(MessageKind::RayBatch, &bad)).expect("write");
    std::fs::write(dir.join("BatchResult-10.bin"), frame_of(&Message::BatchResult(good_result(10)))).expect("write");
    let compact = BatchResult { encoding: ResultEncoding::Compact, ..good_result(10) };
    std::fs::write(dir.join("BatchResult-compact-10.bin"), frame_of(&Message::BatchResult(compact))).expect("write");
    std::fs::write(dir.join("huge-length.bin"), u32::MAX.to_le_bytes()).expect("write");
    assert_eq!(count, MessageKind::ALL.len());
}
